"""What every command shares: the user-facing error type, argument types, progress output."""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

from .. import _memory
from .._validate import positive_int as _positive_int_value

__all__ = ["FLOAT32_MAX", "CLIError", "Progress", "float32_arg", "have_matplotlib", "nonnegative_int_arg", "positive_int_arg"]


class CLIError(Exception):
    """An expected, user-facing error: printed as one line, exit status 2."""


def positive_int_arg(text: str) -> int:
    """argparse type: an integer > 0 (the library's validator, as an argparse error)."""
    try:
        return _positive_int_value("value", int(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None


#: The largest finite float32. The renderer computes in float32, so a flag's number beyond it
#: (`--environment-intensity 1e39`) became inf on its way in, with NumPy's overflow warning
#: printed before the error that followed (issue 42).
FLOAT32_MAX = float(np.finfo(np.float32).max)


def float32_arg(lo: float | None = None, hi: float | None = None, *, unit: str = "", why: str = "") -> Callable[[str], float]:
    """An argparse type: a finite number that float32 holds (|x| <= FLOAT32_MAX), and within
    [lo, hi] where given; anything else is the parser's one-line error, before any work. `unit`
    follows the bounds in the message ("degrees"), `why` explains them."""
    if lo is not None and hi is not None:
        shown = f"a number in [{lo:g}, {hi:g}]"
    else:
        shown = "a number" + ("" if lo is None else f" >= {lo:g}") + ("" if hi is None else f" <= {hi:g}")
    suffix = (f" {unit}" if unit else "") + (f" ({why})" if why else "")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if abs(value) > FLOAT32_MAX:
            raise argparse.ArgumentTypeError(f"{text.strip()} is outside float32's range (|x| <= {FLOAT32_MAX:.4g}), which the renderer computes in")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"expected {shown}{suffix}, got {text.strip()}")
        return value

    parse.__name__ = "number"  # argparse names the type in some messages
    return parse


def nonnegative_int_arg(text: str) -> int:
    """argparse type: an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


class Terminated(KeyboardInterrupt):
    """Raised in the main thread by SIGTERM, so that a terminated command rolls back exactly like an
    interrupted one (every cleanup path handles KeyboardInterrupt)."""


#: The exception type of a signal received during the current command (see `cli._catch_signals`).
PENDING: list = [None]


def raise_pending() -> None:
    """Raise the exception of a signal received earlier whose first raise was swallowed; commands
    call it before committing their outputs (and the progress bar calls it)."""
    if PENDING[0] is not None:
        exc, PENDING[0] = PENDING[0], None
        raise exc()


#: Whether a progress bar's line is still open on stderr (printed with "\r", no newline yet).
_OPEN_LINE = [False]


def close_progress_line() -> str:
    """A newline if a progress bar's line is open (so that a message does not land on it), else ""."""
    if _OPEN_LINE[0]:
        _OPEN_LINE[0] = False
        return "\n"
    return ""


class Progress:
    """A progress indicator on stderr (silent when `quiet`); the library's precomputes take it as
    their `progress(done, total)` callback and know nothing of the terminal. On a terminal: one line
    redrawn in place with the elapsed time and an estimate of the time left. Elsewhere (a log file, a
    pipe, CI): no carriage returns, one plain line per quarter of the work. With `rate_unit` (e.g.
    "jobs") the rate is shown too, and rate and estimate count from the first call's `done` (work
    found already done, such as the completed jobs of a resumed batch, is not counted as speed)."""

    def __init__(self, label: str, quiet: bool = False, *, tty: bool | None = None, rate_unit: str | None = None):
        self.label, self.quiet, self.t0 = label, quiet, time.perf_counter()
        self.tty = sys.stderr.isatty() if tty is None else tty
        self._quarter = -1
        self.rate_unit = rate_unit
        self._base: int | None = None

    def __call__(self, done: int, total: int) -> None:
        if threading.current_thread() is threading.main_thread():
            raise_pending()  # on XLA's callback thread a raise would only abort the program
        if self.quiet:
            return
        elapsed = time.perf_counter() - self.t0
        frac = done / max(total, 1)
        eta = f", about {elapsed * (1 - frac) / frac:.0f} s left" if 0 < frac < 1 else ""
        if self.rate_unit is not None:
            if self._base is None:
                self._base = done
            rate = (done - self._base) / elapsed if elapsed > 0 else 0.0
            eta = "" if rate <= 0 else f", {rate:.2f} {self.rate_unit}/s" + (f", about {(total - done) / rate:.0f} s left" if done < total else "")
        if not self.tty:
            quarter = int(4 * frac)
            if quarter > self._quarter:
                self._quarter = quarter
                print(f"{self.label}: {done}/{total} after {elapsed:.1f} s{eta}", file=sys.stderr, flush=True)
            return
        width = 24
        fill = int(width * frac)
        end = "\n" if done >= total else ""
        _OPEN_LINE[0] = not end
        print(
            f"\r{self.label}: [{'#' * fill}{'.' * (width - fill)}] {done}/{total}  {elapsed:.1f} s{eta}   ",
            end=end,
            file=sys.stderr,
            flush=True,
        )


def have_matplotlib() -> bool:
    """True if the real matplotlib is importable. (colour-science puts a `MagicMock` in
    sys.modules["matplotlib"] when matplotlib is missing, so a bare import is not enough.)"""
    try:
        import matplotlib
    except ImportError:
        return False
    return isinstance(getattr(matplotlib, "__file__", None), str)


#: Memory limit override (GB): `JAXPBR_MEMORY_LIMIT=64 jaxpbr ...` (default: the memory available now).
MEMORY_ENV = _memory.MEMORY_ENV


def available_memory() -> float:
    """Bytes the command may use (`jaxpbr._memory.available_memory`: $JAXPBR_MEMORY_LIMIT in GB
    if set, else MemAvailable), a malformed limit as a CLIError."""
    try:
        return _memory.available_memory()
    except ValueError as e:
        raise CLIError(str(e)) from None


def require_environment(face_size: int, *, procedural: bool = True, flag: str = "--face-size", samples=None, samples_flag: str = "--samples") -> None:
    """Refuse before any work an environment cube of `face_size` (built from the procedural sky or
    a panorama) and its default prefilter (or one with `samples` FIS samples on every level) that
    would not fit: the library's estimates with `flag` named."""
    from ..ibl.specular import (
        DEFAULT_SAMPLES,
        default_num_levels,
        default_sample_counts,
    )

    available_memory()  # a malformed limit: a CLIError
    M = default_num_levels(face_size)
    counts = [samples] * M if samples else default_sample_counts(DEFAULT_SAMPLES, face_size, M)
    pre = _memory.prefilter_bytes(face_size, face_size, counts)
    cube = _memory.cube_bytes(face_size, supersample=4 if procedural else None)["face_size"]
    try:  # the cube's construction peak is over before the prefilter starts
        _memory.require(f"a {face_size}^2 environment with its prefilter", {flag: max(cube, pre["face_size"]), samples_flag: pre["samples"]})
    except _memory.MemoryLimitError as e:
        raise CLIError(str(e)) from None


def require_memory(what: str, nbytes: float, fix: str) -> None:
    """Refuse before any work when `what` would need more memory than is available: the
    library's guard (`jaxpbr._memory.require`) with the command's fix, "lower <flag>". The
    estimates are per-texel / per-pixel costs measured on the CPU backend, rounded up."""
    available_memory()  # a malformed limit: a CLIError
    try:
        _memory.require(what, {fix.removeprefix("lower "): nbytes})
    except _memory.MemoryLimitError as e:
        raise CLIError(str(e)) from None
