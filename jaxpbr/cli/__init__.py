"""The `jaxpbr` command line (also `python -m jaxpbr`): commands, benchmarks, reports, scene files.

This subpackage sits on top of the library and the library never imports it. Each command lives
in its own module and registers itself with `add_command`; errors are reported as one line on
stderr with a non-zero exit status (`--debug` shows the traceback instead).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import warnings

from .. import _entry, _program_cache
from .._version import __version__
from ..io import atomic
from . import (
    _cache,
    batch,
    bench_batch,
    bench_grad,
    bench_ibl,
    bench_render,
    bench_shade,
    ibl,
    render,
    report_precompute,
    report_render,
)
from ._common import PENDING, CLIError, Terminated, close_progress_line, raise_pending

__all__ = ["CLIError", "build_parser", "main"]


class _Parser(argparse.ArgumentParser):
    """argparse with the command line's one-line errors: `jaxpbr render: error: ... (see --help)`
    on stderr and exit status 2, instead of the usage block first."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="jaxpbr",
        description="Physically based shading and image-based lighting in JAX.",
    )
    parser.add_argument("--version", action="version", version=f"jaxpbr {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    render.add_command(sub)
    ibl.add_commands(sub)
    batch.add_command(sub)

    b = sub.add_parser("bench", help="benchmarks (JAX vs NumPy or the peers' recipes, side by side in one process)")
    bsub = b.add_subparsers(dest="bench", metavar="BENCH")
    b.set_defaults(func=lambda args: b.print_help() or 0)
    bench_shade.add_command(bsub)
    bench_grad.add_command(bsub)
    bench_ibl.add_command(bsub)
    bench_render.add_command(bsub)
    bench_batch.add_command(bsub)

    rp = sub.add_parser("report", help="error-vs-run-time reports")
    rsub = rp.add_subparsers(dest="report", metavar="REPORT")
    rp.set_defaults(func=lambda args: rp.print_help() or 0)
    report_precompute.add_command(rsub)
    report_render.add_command(rsub)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None):
    print(f"jaxpbr: warning: {message}", file=sys.stderr)


#: The exception type of the current command's first signal (kept once raised, unlike PENDING).
_SIGNALLED: list = [None]


def _catch_signals():
    """SIGINT and SIGTERM raise in the main thread (KeyboardInterrupt / Terminated) and are also
    remembered (`_common.raise_pending`): Python drops an exception raised while a garbage
    collection callback runs ("Exception ignored in: _xla_gc_callback"), which once let an
    interrupted bake run on and exit 0. Such a dropped exception is pending again (and not
    printed: `sys.unraisablehook`), so the next safe point raises it; the outputs' commit is one
    (`atomic.OutputSet`). A repeated signal does not cut the first one's rollback short.
    Returns the previous handlers and unraisable hook (the before-the-imports handlers of
    `jaxpbr._entry` when this process is the command line)."""

    def handler(signum, frame):
        if _SIGNALLED[0] is not None:  # a repeat: the first signal's exit is under way (or pending)
            return
        exc = Terminated if signum == signal.SIGTERM else KeyboardInterrupt
        _SIGNALLED[0] = PENDING[0] = exc
        if atomic.in_critical():  # raised when the section ends (atomic.CRITICAL_EXIT_HOOKS)
            return
        raise exc()

    previous_hook = sys.unraisablehook

    def unraisable(u):
        if isinstance(u.exc_value, KeyboardInterrupt):  # raised at the next safe point instead
            PENDING[0] = PENDING[0] or type(u.exc_value)
            return
        previous_hook(u)

    if raise_pending not in atomic.CRITICAL_EXIT_HOOKS:
        atomic.CRITICAL_EXIT_HOOKS.append(raise_pending)

    _SIGNALLED[0] = PENDING[0] = None
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            previous[sig] = signal.signal(sig, handler)
        except ValueError:  # not the main thread: leave the defaults
            pass
    sys.unraisablehook = unraisable
    return previous, previous_hook


#: Seconds the main thread gets to act on SIGINT / SIGTERM before the watchdog does it.
SIGNAL_GRACE_S = 2.0
_HANDLED = threading.Event()


def _start_watchdog() -> None:
    """Python runs signal handlers in the main thread between bytecodes, so while that thread is
    inside a long XLA compilation or computation an interrupt waits (a `timeout` SIGTERM was
    ignored for minutes; the issue measured up to 13 s for SIGINT). The C-level handler also
    writes the signal number to a wakeup pipe; this thread reads it and, if the main thread has
    not acted within SIGNAL_GRACE_S, rolls back every open output set, removes temporary files,
    prints the one line and exits with the signal's status itself."""
    try:
        r, w = os.pipe()
        os.set_blocking(w, False)
        signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    except (ValueError, OSError):  # not the main thread, or no pipes: no watchdog
        return

    def watch():
        while True:
            data = os.read(r, 1)
            if not data or data[0] not in (signal.SIGINT, signal.SIGTERM):
                continue
            if _HANDLED.wait(SIGNAL_GRACE_S):
                return
            atomic.emergency_rollback()
            term = data[0] == signal.SIGTERM
            try:
                os.write(2, close_progress_line().encode() + (b"jaxpbr: terminated\n" if term else b"jaxpbr: interrupted\n"))
            finally:
                os._exit(128 + signal.SIGTERM if term else 130)

    threading.Thread(target=watch, name="jaxpbr-signal-watchdog", daemon=True).start()


def main(argv: list[str] | None = None, *, entry: bool | None = None) -> int:
    """The command line: `argv` (default sys.argv[1:]) -> exit status. entry: whether this is the
    process's command line (default: argv is None, as the console script and `python -m jaxpbr`
    call it), which then ends here (`_end_process`); in-process callers get the status back."""
    if entry is None:
        entry = argv is None
    if entry:
        _collect_less()
    code = _main(argv, entry)
    if entry:
        _end_process(code)
    return code


def _collect_less() -> None:
    """The command line's process: the objects made while the modules loaded (JAX's, NumPy's,
    jaxpbr's; about a million) are moved out of the garbage collector's generations
    (`gc.freeze`), which it then no longer walks, and collections of the young generation come
    every 10,000 allocations instead of 700. The demo's cold start spent 0.26-0.28 s in 408
    collections, mostly while tracing its stages; 0.013 s in 9 after this."""
    import gc

    gc.freeze()
    gc.set_threshold(10_000, 10, 10)
    gc.enable()


def _end_process(code: int) -> None:
    """End the command line's process with `code` once its work is done: the library's threads
    that may still write finish (a program being stored, a map going to the asset cache), the
    atexit handlers run (JAX's included), the streams are flushed, and `os._exit` skips the
    interpreter's finalization, which tears down every module and the XLA client's compiled
    programs one by one: 0.15-0.2 s of the demo's 1.2 s warm start (and of its cold one)."""
    import atexit

    from ..rendering import execute

    _program_cache.finish_work()
    execute.finish_work()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more can reach it
            pass
    try:  # what native libraries wrote through C's buffered stdio (exit() would flush it)
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):
        pass
    os._exit(code)


def _main(argv: list[str] | None, entry: bool) -> int:
    _entry.phase("main")
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 0
    if entry:
        _start_watchdog()
    _cache.enable()
    _cache.enable_assets()
    # The stored programs the last run of this very command used start loading now.
    signature = json.dumps(sys.argv[1:] if argv is None else list(argv))
    _program_cache.recall(signature)
    previous, previous_hook = {}, sys.unraisablehook
    try:
        previous, previous_hook = _catch_signals()
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning  # the library's warnings as one line, like errors
            code = int(args.func(args) or 0)
            raise_pending()  # a signal after the outputs' commit (`atomic.OutputSet`): report it
            if code == 0:
                _program_cache.remember(signature)
            return code
    except KeyboardInterrupt as exc:  # SIGINT, or SIGTERM (Terminated): files already rolled back
        return _interrupted(isinstance(exc, Terminated), entry)
    except Exception as exc:  # one line on stderr unless --debug
        if _SIGNALLED[0] is not None and not args.debug:
            # The signal's exception came back as another one: raised inside a callback that XLA
            # runs ("CpuCallback error"), or an import or extension cut short. Outputs rolled back.
            return _interrupted(_SIGNALLED[0] is Terminated, entry)
        if args.debug:
            raise
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"{close_progress_line()}jaxpbr: error: {msg}", file=sys.stderr)
        # 2: the user can fix it (bad input, a file or disk problem, too little memory); 1: a bug.
        return 2 if isinstance(exc, (CLIError, ValueError, OSError, MemoryError)) else 1
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)
        sys.unraisablehook = previous_hook
        # In-process callers (a notebook, tests) go on: nothing of this command's signals stays
        # pending for the library's later atomic writes.
        _SIGNALLED[0] = PENDING[0] = None
        if raise_pending in atomic.CRITICAL_EXIT_HOOKS:
            atomic.CRITICAL_EXIT_HOOKS.remove(raise_pending)


def _interrupted(terminated: bool, entry: bool) -> int:
    """The one line of an interrupted command and its exit status (exits at once as the command line)."""
    _HANDLED.set()
    print(close_progress_line() + ("jaxpbr: terminated" if terminated else "jaxpbr: interrupted"), file=sys.stderr)
    code = 128 + signal.SIGTERM if terminated else 130
    if entry:
        # Worker threads (a precompute still running) would keep the process alive until
        # they finish; everything that must be undone has been undone by now.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
