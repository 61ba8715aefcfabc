"""The command line's first second: signal handlers in place before the heavy imports.

`jaxpbr/__init__.py` imports this module first, before NumPy and JAX. When the process is the
command line (the `jaxpbr` console script or `python -m jaxpbr`),
`early()` replaces Python's default SIGINT handler and the default SIGTERM action: nothing has been
written yet while the modules load, so a signal then prints the command line's one line
(`jaxpbr: interrupted` / `jaxpbr: terminated`) and exits at once with 130 / 143. Python's own
SIGINT handler would raise KeyboardInterrupt wherever the import happens to be: a traceback, or,
inside a garbage-collection callback, an exception that Python drops and a run that goes on. An
application importing jaxpbr as a library keeps its handlers: `early()` does nothing there.
`cli.main` installs the command's own handlers (rollback of its outputs) before any work.

Only a few small standard-library modules are imported here, so that the handlers are in place
a few milliseconds after the interpreter starts.

`phase(name)` marks the moments of start-up ("start": here; "main": the start of `cli.main`) for
the tests: with `JAXPBR_TEST_PHASES` set to a file, each name is appended to it as it is reached,
and `JAXPBR_TEST_PAUSE=<name>` makes the process wait at that moment (for a signal).
"""

import gc
import os
import signal
import sys
import time

__all__ = ["early", "phase"]

#: What a console script generated for `jaxpbr = "jaxpbr.cli:main"` runs.
_SCRIPT_LINE = b"from jaxpbr.cli import main"


def _is_command_line() -> bool:
    if sys.argv[:1] == ["-m"]:  # `python -m X` while X is being found and imported
        argv = list(getattr(sys, "orig_argv", ()))
        try:
            i = argv.index("-m")
        except ValueError:
            return False
        return argv[i + 1 : i + 2] == ["jaxpbr"]
    path = getattr(sys.modules.get("__main__"), "__file__", None)
    if not path or os.path.basename(path).split(".")[0].removesuffix("-script") != "jaxpbr":
        return False
    try:
        with open(path, "rb") as f:
            return _SCRIPT_LINE in f.read(4096)
    except OSError:
        return False


def _exit_on_signal(signum, frame):
    term = signum == signal.SIGTERM
    try:
        os.write(2, b"jaxpbr: terminated\n" if term else b"jaxpbr: interrupted\n")
    finally:
        os._exit(128 + signal.SIGTERM if term else 130)


def early() -> None:
    """Install the start-up handlers if this process is the command line (see the module's doc)."""
    if not _is_command_line():
        return
    # No cyclic garbage collection while the modules load (about 0.04 s of collections over objects
    # that live as long as the process); `cli.main` freezes them and turns it back on.
    gc.disable()
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            # Python's default, the system's default, or ignored (a background job of a script):
            # taken over, as `cli.main` takes them over later.
            if signal.getsignal(sig) in (signal.default_int_handler, signal.SIG_DFL, signal.SIG_IGN):
                signal.signal(sig, _exit_on_signal)
        except (ValueError, OSError):  # not the main thread
            pass


def phase(name: str) -> None:
    """Test hook: report reaching `name` (JAXPBR_TEST_PHASES), wait there if JAXPBR_TEST_PAUSE names it."""
    path = os.environ.get("JAXPBR_TEST_PHASES")
    if not path:
        return
    with open(path, "a") as f:
        f.write(name + "\n")
    if os.environ.get("JAXPBR_TEST_PAUSE") == name:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            time.sleep(0.05)
