"""Ctrl-C (and SIGTERM) in the first second of a command: before and during the heavy imports.

Each case re-bakes over a complete set in a subprocess and signals it at a named moment of its
start-up. The command reports the moments it reaches in the file named by `JAXPBR_TEST_PHASES`
and waits at the one named by `JAXPBR_TEST_PAUSE` (`jaxpbr/_entry.py`), so the signal lands where
the test says, not where a timer guesses: "start" is the first statement of the package, before
NumPy and JAX are imported; "main" is the start of `cli.main`, every module imported. The outcome
wanted at every moment: one line on stderr, exit status 130 (143 for SIGTERM), nothing on stdout,
and the previous set exactly as it was.
"""

from __future__ import annotations

import argparse
import gc
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import jaxpbr.cli
from jaxpbr.cli import main
from jaxpbr.cli._common import PENDING, raise_pending
from jaxpbr.ibl.cubemap import equirect_directions
from jaxpbr.io import atomic, image

_SCRIPT = Path(sys.executable).parent / "jaxpbr"  # the console script next to this interpreter


def _ibl_args(pano, out_dir):
    return ["ibl", str(pano), "--face-size", "16", "--samples", "16", "--lut-size", "8", "--charlie-size", "8",
            "--charlie-levels", "3", "--no-error", "--quiet", "--out-dir", str(out_dir)]


def _state(d):
    """Every file (hidden temporaries and backups included) with its bytes, mtime and inode."""
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns, p.stat().st_ino) for p in sorted(d.iterdir())}


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    """A small panorama (written in code) and a complete set baked from it."""
    root = tmp_path_factory.mktemp("sigint")
    pano = root / "sky.exr"
    d = equirect_directions(16)
    image.write(pano, ((1.0 + 0.5 * d[..., 1:2]) * np.array([1.0, 0.9, 0.8])).astype(np.float32))
    out_dir = root / "set"
    out_dir.mkdir()
    assert main(_ibl_args(pano, out_dir)) == 0
    assert {"irradiance.ktx2", "prefiltered.ktx2", "brdf_lut.exr", "ibl.json"} <= {p.name for p in out_dir.iterdir()}
    return pano, out_dir


def _signal_at(cmd, phase, sig, *, pause, tmp_path):
    """Run `cmd`; when it reports `phase` (waiting there if `pause`), send `sig`.
    -> (exit status, stdout, stderr, phases reached)."""
    phases = tmp_path / "phases.txt"
    env = dict(os.environ, JAXPBR_TEST_PHASES=str(phases), JAXPBR_COMPILATION_CACHE="off")
    env.pop("JAXPBR_TEST_PAUSE", None)
    if pause:
        env["JAXPBR_TEST_PAUSE"] = phase
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        t0 = time.monotonic()
        while not (phases.exists() and phase in phases.read_text().split()):
            assert p.poll() is None, f"exited ({p.returncode}) before reaching {phase!r}: {p.stderr.read()}"
            assert time.monotonic() - t0 < 120, f"{phase!r} not reached in 120 s"
            time.sleep(0.002)
        p.send_signal(sig)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    return p.returncode, out, err, phases.read_text().split()


def _entry(kind):
    if kind == "script":
        if not _SCRIPT.exists():
            pytest.skip("no jaxpbr console script next to this interpreter")
        return [str(_SCRIPT)]
    return [sys.executable, "-m", "jaxpbr"]


@pytest.mark.parametrize("kind", ["script", "module"])
def test_sigint_before_the_heavy_imports(baked, tmp_path, kind):
    """Signalled while waiting at the package's first statement (the issue: a traceback from inside
    the imports)."""
    pano, out_dir = baked
    before = _state(out_dir)
    code, out, err, _ = _signal_at(_entry(kind) + _ibl_args(pano, out_dir), "start", signal.SIGINT, pause=True, tmp_path=tmp_path)
    assert (code, out, err) == (130, "", "jaxpbr: interrupted\n"), err
    assert _state(out_dir) == before


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_during_the_imports(baked, tmp_path, sig):
    """Signalled as soon as the package starts importing, without waiting: it lands inside the
    imports of NumPy / JAX (the issue: a traceback, or an interrupt lost in a garbage-collection
    callback and the set replaced with exit 0)."""
    pano, out_dir = baked
    before = _state(out_dir)
    code, out, err, reached = _signal_at(_entry("script") + _ibl_args(pano, out_dir), "start", sig, pause=False, tmp_path=tmp_path)
    assert "main" not in reached, "the signal arrived after the imports; this case wants it during them"
    want = (130, "jaxpbr: interrupted\n") if sig == signal.SIGINT else (128 + signal.SIGTERM, "jaxpbr: terminated\n")
    assert (code, out, err) == (want[0], "", want[1]), err
    assert _state(out_dir) == before


def test_sigint_after_the_imports_before_the_command_starts(baked, tmp_path):
    """Signalled at the start of `cli.main`: every module imported, the command's own handlers not
    installed yet."""
    pano, out_dir = baked
    before = _state(out_dir)
    code, out, err, _ = _signal_at(_entry("script") + _ibl_args(pano, out_dir), "main", signal.SIGINT, pause=True, tmp_path=tmp_path)
    assert (code, out, err) == (130, "", "jaxpbr: interrupted\n"), err
    assert _state(out_dir) == before


# ----------------------------------------------- a signal whose exception Python drops


def test_a_signal_dropped_in_a_gc_callback_rolls_back_with_one_line(tmp_path, monkeypatch, capsys):
    """SIGINT handled while a garbage-collection callback runs (JAX's `_xla_gc_callback`): Python
    prints "Exception ignored in ..." and drops the KeyboardInterrupt. The command still ends as
    interrupted, with one line, and the outputs it wrote are rolled back, not committed."""
    keep, new = tmp_path / "kept.txt", tmp_path / "new.txt"
    keep.write_text("old")

    def command(args):
        with atomic.OutputSet() as outs:
            for p in (keep, new):
                outs.add(p)
                atomic.atomic_write(p, lambda tmp: Path(tmp).write_text("new"))

            def callback(phase, info):
                gc.callbacks.remove(callback)
                os.kill(os.getpid(), signal.SIGINT)
                for _ in range(100_000):  # the handler runs here, inside the callback
                    pass

            gc.callbacks.append(callback)
            gc.collect()
        return 0

    parser = argparse.ArgumentParser(prog="jaxpbr")
    parser.add_argument("--debug", action="store_true")
    parser.set_defaults(func=command)
    monkeypatch.setattr(jaxpbr.cli, "build_parser", lambda: parser)
    dropped = []  # what reaches Python's hook that prints "Exception ignored in ..."
    monkeypatch.setattr(sys, "unraisablehook", lambda u: dropped.append(u.exc_type))
    assert main([]) == 130
    assert capsys.readouterr().err == "jaxpbr: interrupted\n" and dropped == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept.txt"] and keep.read_text() == "old"


def test_outputs_are_not_committed_while_a_signal_is_pending(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic, "CRITICAL_EXIT_HOOKS", [raise_pending])
    keep = tmp_path / "kept.txt"
    keep.write_text("old")
    try:
        with pytest.raises(KeyboardInterrupt):
            with atomic.OutputSet() as outs:
                for p in (keep, tmp_path / "new.txt"):
                    outs.add(p)
                    atomic.atomic_write(p, lambda tmp: Path(tmp).write_text("new"))
                PENDING[0] = KeyboardInterrupt  # received, its exception dropped
        assert PENDING[0] is None
    finally:
        PENDING[0] = None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept.txt"] and keep.read_text() == "old"


def test_critical_sections_are_per_thread(monkeypatch):
    # Signal handlers run in the main thread: a worker's critical section (an atomic write from a
    # writer thread) must not defer them, and its end must not run the hooks (which would raise the
    # main thread's pending interrupt in the worker).
    import threading

    calls = []
    monkeypatch.setattr(atomic, "CRITICAL_EXIT_HOOKS", [lambda: calls.append(threading.current_thread().name)])
    inside, release, seen = threading.Event(), threading.Event(), {}

    def worker():
        with atomic.critical():
            seen["worker"] = atomic.in_critical()
            inside.set()
            release.wait(10)

    t = threading.Thread(target=worker, name="writer")
    t.start()
    assert inside.wait(10)
    seen["main while the worker is inside"] = atomic.in_critical()
    release.set()
    t.join(10)
    assert seen == {"worker": True, "main while the worker is inside": False}
    assert calls == []
    with atomic.critical():
        with atomic.critical():
            assert atomic.in_critical()
        assert calls == []  # only the outermost section's end
    assert not atomic.in_critical() and calls == [threading.main_thread().name]


def test_critical_depth_survives_concurrent_writers(tmp_path):
    # Many threads entering and leaving sections at once leave no stale depth behind (a shared
    # counter's read-modify-write can lose updates and keep every later signal deferred).
    from concurrent.futures import ThreadPoolExecutor

    def writes(k):
        for i in range(50):
            atomic.atomic_write(tmp_path / f"{k}-{i}.txt", lambda tmp: Path(tmp).write_text("x"))

    with ThreadPoolExecutor(8) as pool:
        list(pool.map(writes, range(8)))
    assert not atomic.in_critical() and len(list(tmp_path.iterdir())) == 400


def test_the_command_line_collects_no_garbage_while_loading_and_less_after(monkeypatch):
    """The command line's process (`_entry.early`) loads its modules without cyclic garbage
    collection; `cli.main` then freezes what they made and collects the young generation every
    10,000 allocations. A library import and an in-process `cli.main` leave the collector alone."""
    from jaxpbr import _entry

    threshold = gc.get_threshold()
    monkeypatch.setattr(_entry.signal, "signal", lambda *a: None)  # (pytest keeps its own handlers)
    try:
        monkeypatch.setattr(_entry, "_is_command_line", lambda: False)
        _entry.early()
        assert gc.isenabled()
        monkeypatch.setattr(_entry, "_is_command_line", lambda: True)
        _entry.early()
        assert not gc.isenabled()
        jaxpbr.cli._collect_less()
        assert gc.isenabled() and gc.get_threshold() == (10_000, 10, 10) and gc.get_freeze_count() > 100_000
    finally:
        gc.unfreeze()
        gc.set_threshold(*threshold)
        gc.enable()
    monkeypatch.setattr(jaxpbr.cli, "_collect_less", lambda: pytest.fail("collector changed in process"))
    parser = argparse.ArgumentParser(prog="jaxpbr")
    parser.add_argument("--debug", action="store_true")
    parser.set_defaults(func=lambda args: 0)
    monkeypatch.setattr(jaxpbr.cli, "build_parser", lambda: parser)
    assert main([]) == 0 and gc.isenabled() and gc.get_threshold() == threshold
