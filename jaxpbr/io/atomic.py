"""Files written whole or not at all.

`atomic_write` writes through a temporary file in the target's directory and renames it over the
target, so a crash, a signal or a full disk never leaves a half-written file under the final name.
`OutputSet` groups the files one command writes: if the command fails, every file it already
wrote is removed again (no partial results). `write_json` is the atomic JSON sidecar writer.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import threading
from pathlib import Path

from .._api import keyword_only
from ..errors import InputError

__all__ = ["OutputSet", "atomic_write", "write_json"]


def atomic_write(path, writer) -> None:
    """Write through ``writer(tmp_path)`` to a temp file next to ``path``, then rename it over ``path``."""
    path = Path(path)
    parent = path.parent
    if not parent.exists():
        raise FileNotFoundError(
            f"cannot write {str(path)!r}: directory {str(parent)!r} does not exist (create it first)"
        )
    if not parent.is_dir():
        raise NotADirectoryError(f"cannot write {str(path)!r}: {str(parent)!r} is not a directory")
    if path.is_dir():
        raise IsADirectoryError(f"cannot write {str(path)!r}: it is an existing directory")

    # Hidden name in the same directory (so os.replace is an atomic rename on one file system), keeping the
    # extension last. Created with O_EXCL and mode 0o666 so the umask applies as for any new file. The
    # creation is a critical section: a signal arriving between the creation and the cleanup's reach
    # would leave the empty temporary file behind.
    tmp = fd = None
    try:
        with critical():
            tmp, fd = _create_temp(path)
            _TEMPS.add(tmp)
        os.close(fd)
        fd = None
        writer(str(tmp))
        with critical():
            os.replace(tmp, path)
            _TEMPS.discard(tmp)
            tmp = None  # in place: nothing left to clean up
    except BaseException as e:
        if fd is not None:
            os.close(fd)
        if tmp is not None:
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            _TEMPS.discard(tmp)
        if isinstance(e, OSError) and not isinstance(e, (FileNotFoundError, PermissionError)):
            raise OSError(f"failed to write {str(path)!r}: {e}") from e
        raise


#: Output sets open now and temporary files that exist now, for `emergency_rollback`.
_ACTIVE_SETS: list = []
_TEMPS: set = set()


def emergency_rollback() -> None:
    """Undo every open `OutputSet` and remove every temporary file, from any thread: for a
    process about to exit while its main thread is stuck in a long native call (the command
    line's signal watchdog)."""
    for tmp in list(_TEMPS):
        try:
            os.unlink(tmp)
        except OSError:
            pass
    for outs in list(_ACTIVE_SETS):
        try:
            outs.rollback()
        except OSError:
            pass


#: Critical-section depth, per thread. Python runs signal handlers in the main thread only, so
#: the section a signal must not cut is the main thread's: a worker thread's section (an atomic
#: write from a writer or cache thread) does not defer a signal aimed at the main thread, and its
#: end does not raise one in the worker (which would take the main thread's interrupt from it).
#: Each thread changes only its own depth, so no lock is needed and no update is lost.
_DEPTH = threading.local()
#: Called (no arguments) when the main thread's outermost critical section ends (and before an
#: `OutputSet` made in the main thread commits); the command line registers the re-raise of a
#: signal it deferred during the section.
CRITICAL_EXIT_HOOKS: list = []


def _depth() -> int:
    return getattr(_DEPTH, "n", 0)


def _run_exit_hooks() -> None:
    if threading.current_thread() is threading.main_thread():
        for hook in CRITICAL_EXIT_HOOKS:
            hook()


@contextlib.contextmanager
def critical():
    """A few statements that must not be cut in two by a signal (creating a temporary file and
    taking it in charge; renaming it into place). The command line's signal handlers consult
    `in_critical()` and defer the interrupt to the end of the section."""
    _DEPTH.n = _depth() + 1
    try:
        yield
    finally:
        _DEPTH.n -= 1
        if _DEPTH.n == 0:
            _run_exit_hooks()


def in_critical() -> bool:
    """Whether the calling thread is inside a `critical` section (a signal handler, which runs in
    the main thread, asks about the main thread)."""
    return _depth() > 0


def _create_temp(path: Path):
    parent = path.parent
    for _ in range(100):
        tmp = parent / f".{path.stem}.tmp-{secrets.token_hex(4)}{path.suffix}"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            break
        except FileExistsError:
            continue
        except OSError as e:
            raise type(e)(
                e.errno, f"cannot write {str(path)!r}: directory {str(parent)!r} is not writable ({e.strerror})"
            ) from e
    else:  # pragma: no cover - 100 random collisions
        raise OSError(f"cannot create a temporary file in {str(parent)!r}")
    return tmp, fd


@keyword_only("outputs")
def write_json(path, data, *, outputs: "OutputSet | None" = None) -> Path:
    """Write `data` as indented JSON atomically; register the file with `outputs` if given."""
    path = Path(path)
    text = json.dumps(data, indent=2, sort_keys=False) + "\n"

    def writer(tmp):
        with open(tmp, "w") as f:
            f.write(text)

    if outputs is not None:
        outputs.add(path)  # before the write: a signal right after the rename still rolls it back
    atomic_write(path, writer)
    return path


class OutputSet:
    """The files one command writes: validate targets before any work, remove them all on failure.

    Use as a context manager (`with OutputSet() as outs: ...`): if the block raises (an error,
    KeyboardInterrupt, or the CLI's SIGTERM), every file registered with `add` is deleted again,
    every file registered with `protect` gets its old content back, and the exception propagates.
    """

    def __init__(self):
        self.written: list[Path] = []
        self._backups: dict[Path, Path] = {}  # existing file -> hard link keeping its old content

    def check(self, path, suffixes: tuple[str, ...]) -> Path:
        """Validate an output path before any work: suffix, existing writable directory, not a directory."""
        path = Path(path)
        if path.suffix.lower() not in suffixes:
            raise InputError(f"output {str(path)!r} must end in one of {', '.join(suffixes)}")
        parent = path.resolve().parent
        if not parent.is_dir():
            raise InputError(f"output directory {str(parent)!r} does not exist; create it first")
        if path.is_dir():
            raise InputError(f"output {str(path)!r} is a directory")
        if not os.access(parent, os.W_OK):
            raise InputError(f"output directory {str(parent)!r} is not writable")
        return path

    def add(self, path) -> None:
        """Register a file this command writes -- *before* writing it, so that a failure or a
        signal at any moment removes it. A file already there is protected (`protect`): a rollback
        puts its old content back instead of deleting it."""
        path = Path(path)
        if path not in self.written:
            self.protect([path])
            self.written.append(path)

    def protect(self, paths) -> None:
        """Keep the current content of these existing files (before any work): a rollback puts it
        back, so an interrupted re-bake leaves the previous complete set as it was instead of a mix
        of new and old files. The old content is kept as a hidden hard link (a copy where the
        file system has no links) next to each file and removed once the set is complete."""
        for p in map(Path, paths):
            if p in self._backups or not p.is_file():
                continue
            keep = p.with_name(f".{p.name}.jaxpbr-old-{secrets.token_hex(4)}")
            try:
                os.link(p, keep)
            except OSError:
                shutil.copy2(p, keep)
            self._backups[p] = keep

    def rollback(self) -> None:
        for p in self.written:
            try:
                p.unlink()
            except FileNotFoundError:
                pass
        for p, keep in self._backups.items():
            try:
                untouched = os.path.samefile(keep, p)
            except FileNotFoundError:
                untouched = False
            if untouched:  # still the old file (rename() between two links of one file is a no-op)
                keep.unlink()
            else:
                os.replace(keep, p)
        self._backups.clear()

    def _discard_backups(self) -> None:
        for keep in self._backups.values():
            try:
                keep.unlink()
            except FileNotFoundError:
                pass
        self._backups.clear()

    def __enter__(self) -> "OutputSet":
        _ACTIVE_SETS.append(self)
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            if exc_type is None:  # a signal not raised yet (Python dropped its exception) raises here
                _run_exit_hooks()
        except BaseException:
            exc_type = BaseException
            raise
        finally:
            if self in _ACTIVE_SETS:
                _ACTIVE_SETS.remove(self)
            with critical():  # the commit or the rollback whole; a signal meanwhile raises after it
                if exc_type is not None:
                    self.rollback()
                else:
                    self._discard_backups()
        return False
