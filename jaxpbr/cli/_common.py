"""What every command shares: the user-facing error type, argument types, progress output."""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time

from .._validate import positive_int as _positive_int_value

__all__ = ["CLIError", "Progress", "have_matplotlib", "nonnegative_int_arg", "positive_int_arg"]


class CLIError(Exception):
    """An expected, user-facing error: printed as one line, exit status 2."""


def positive_int_arg(text: str) -> int:
    """argparse type: an integer > 0 (the library's validator, as an argparse error)."""
    try:
        return _positive_int_value("value", int(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None


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
    """A one-line progress indicator on stderr (silent when `quiet`); the library's precomputes take
    it as their `progress(done, total)` callback and know nothing of the terminal."""

    def __init__(self, label: str, quiet: bool = False):
        self.label, self.quiet, self.t0 = label, quiet, time.perf_counter()

    def __call__(self, done: int, total: int) -> None:
        if threading.current_thread() is threading.main_thread():
            raise_pending()  # on XLA's callback thread a raise would only abort the program
        if self.quiet:
            return
        width = 24
        fill = int(width * done / max(total, 1))
        end = "\n" if done >= total else ""
        _OPEN_LINE[0] = not end
        print(
            f"\r{self.label}: [{'#' * fill}{'.' * (width - fill)}] {done}/{total}  {time.perf_counter() - self.t0:.1f} s",
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
MEMORY_ENV = "JAXPBR_MEMORY_LIMIT"


def available_memory() -> float:
    """Bytes the command may use: $JAXPBR_MEMORY_LIMIT (GB) if set, else MemAvailable from
    /proc/meminfo (else the physical memory)."""
    own = os.environ.get(MEMORY_ENV)
    if own:
        try:
            return float(own) * 1e9
        except ValueError:
            raise CLIError(f"{MEMORY_ENV} must be a number of gigabytes, got {own!r}") from None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return float("inf")


def require_memory(what: str, nbytes: float, fix: str) -> None:
    """Refuse before any work when `what` would need more memory than is available (issue 13:
    huge sizes aborted inside XLA with a C++ stack, or ran the machine out of memory). The
    estimates are per-texel / per-pixel costs measured on the CPU backend, rounded up."""
    limit = available_memory()
    if nbytes > limit:
        raise CLIError(
            f"{what} needs about {nbytes / 1e9:.3g} GB of memory, more than the {limit / 1e9:.3g} GB available; "
            f"{fix}, or set {MEMORY_ENV}=<GB> to allow more"
        )
