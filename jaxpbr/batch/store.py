"""The output folder of a batch run: one run at a time, a completion record per job, the summary.

Layout of `OUT/`:
    <job outputs>                 written atomically by whoever runs the job (driver or worker)
    .jaxpbr-batch/lock            held by the run (an OS file lock: a second run is refused)
    .jaxpbr-batch/records/*.json  one per completed job, written atomically *after* its outputs:
                                  {"name", "key", "outputs": {file: "sha256:..."}, "seconds", ...}
    batch-summary.json            per job: status, seconds, outputs with checksums (end of a run)

A job is complete when its record exists, names the job's current key (the row and its inputs'
stamps, `jobs.RenderJob.key`) and every output it lists still has the recorded checksum; anything
else is redone. A record is never written for outputs that are not all in place, so a run
stopped at any moment (a signal, a dead worker, a power cut) leaves records that are true.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import socket
import time
from pathlib import Path

import filelock

from .._version import __version__
from ..errors import InputError
from ..io.atomic import atomic_write, write_json

__all__ = ["STATE_DIR", "SUMMARY", "OutputFolder", "RunLocked", "sha256_file"]

STATE_DIR = ".jaxpbr-batch"
SUMMARY = "batch-summary.json"
#: Leftovers of an atomic write or an output set interrupted by a killed process.
_LEFTOVER = re.compile(r"^\..+\.(tmp-[0-9a-f]{8}.*|jaxpbr-old-[0-9a-f]{8})$")


class RunLocked(InputError):
    """Another run holds the output folder."""


def sha256_file(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return "sha256:" + h.hexdigest()


class OutputFolder:
    """The output folder: its lock, the completion records and the summary."""

    def __init__(self, root):
        self.root = Path(root).resolve()
        self.state = self.root / STATE_DIR
        self.records = self.state / "records"
        self._lock: filelock.BaseFileLock | None = None

    # -- one run at a time -------------------------------------------------------------------

    def acquire(self) -> None:
        """Create the folder and take its lock; RunLocked if another run holds it."""
        if self.root.exists() and not self.root.is_dir():
            raise InputError(f"--out {str(self.root)!r} is a file; give a folder")
        self.records.mkdir(parents=True, exist_ok=True)
        lock = filelock.FileLock(str(self.state / "lock"), timeout=0)
        try:
            lock.acquire()
        except filelock.Timeout:
            owner = ""
            try:
                owner = f" ({(self.state / 'owner').read_text().strip()})"
            except OSError:
                pass
            raise RunLocked(f"another jaxpbr batch run is writing {str(self.root)!r}{owner}; "
                            f"wait for it to finish or give another --out") from None
        self._lock = lock
        owner = f"pid {os.getpid()} on {socket.gethostname()}\n"
        atomic_write(self.state / "owner", lambda tmp: Path(tmp).write_text(owner))
        self._remove_leftovers()

    def release(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __enter__(self):
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def _remove_leftovers(self) -> None:
        """Temporary files and kept-back copies left by a process killed in the middle of a write
        (only ever there while a run holds the lock, and this run does)."""
        for dirpath, dirnames, filenames in os.walk(self.root):
            dirnames[:] = [d for d in dirnames if d != STATE_DIR]
            for f in filenames:
                if _LEFTOVER.match(f):
                    try:
                        os.unlink(os.path.join(dirpath, f))
                    except OSError:
                        pass

    # -- completion records ------------------------------------------------------------------

    def record_path(self, name: str) -> Path:
        return self.records / (hashlib.sha1(name.encode()).hexdigest()[:20] + ".json")

    def read_record(self, name: str) -> dict | None:
        try:
            return json.loads(self.record_path(name).read_text())
        except (OSError, ValueError):
            return None

    def completed(self, job) -> dict | None:
        """The job's record if the job is complete (same key, every output as recorded), else None."""
        rec = self.read_record(job.name)
        if rec is None or rec.get("name") != job.name or rec.get("key") != job.key:
            return None
        for rel, digest in rec.get("outputs", {}).items():
            p = self.root / rel
            if not p.is_file() or sha256_file(p) != digest:
                return None
        return rec if rec.get("outputs") else None

    def commit(self, job, files, *, seconds: float, worker: str, attempt: int = 1) -> dict:
        """Checksum the job's output files (paths relative to the folder) and write its record."""
        rec = {
            "name": job.name,
            "kind": job.kind,
            "key": job.key,
            "outputs": {rel: sha256_file(self.root / rel) for rel in sorted(files)},
            "seconds": round(float(seconds), 4),
            "worker": worker,
            "attempt": int(attempt),
            "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "jaxpbr": __version__,
        }
        write_json(self.record_path(job.name), rec)
        return rec

    def write_summary(self, summary: dict) -> Path:
        return write_json(self.root / SUMMARY, summary)
