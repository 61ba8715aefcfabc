"""The installed package holds every room: each subpackage of the source tree imports from the
installation (not from this checkout), and the shipped tables come with it.

`pip install .` (what CI and users run) builds a wheel and installs it into site-packages; the test
runs a separate interpreter in isolated mode (`-I`: no current directory, no PYTHONPATH) from a
temporary directory, so a subpackage missing from the wheel fails here even though the tests
themselves import from the source tree. An editable install maps back to this checkout, so there
the test builds a wheel itself (`pip wheel`, needs the package index) and is marked slow."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

SOURCE = Path(__file__).resolve().parent.parent / "jaxpbr"


def _source_packages() -> set[str]:
    return {
        ".".join(p.parent.relative_to(SOURCE.parent).parts) for p in SOURCE.rglob("__init__.py")
    }


def _installed_root(cwd: Path) -> Path | None:
    """Where a separate interpreter in isolated mode (no current directory on sys.path, no
    PYTHONPATH) imports jaxpbr from, or None when it is not installed. (importlib.metadata from this
    process would find the `jaxpbr.egg-info` that building the wheel leaves in the checkout.)"""
    r = subprocess.run(
        [sys.executable, "-I", "-c", "import jaxpbr, pathlib; print(pathlib.Path(jaxpbr.__file__).resolve().parent)"],
        capture_output=True, text=True, cwd=cwd, timeout=300,
    )
    return Path(r.stdout.strip().splitlines()[-1]) if r.returncode == 0 and r.stdout.strip() else None


_PROBE = """
import importlib, json, sys
from pathlib import Path
names = json.loads(sys.argv[1])
out = {}
for n in names:
    m = importlib.import_module(n)
    out[n] = str(Path(m.__file__).resolve())
import jaxpbr
from jaxpbr.shading.shipped_luts import shipped_manifest
out["__luts__"] = len(shipped_manifest().get("luts", []))
from jaxpbr.rendering.demo import shipped_demo_sky
sky = shipped_demo_sky()
out["__demo_sky__"] = None if sky is None else [len(sky.prefiltered.levels), sky.radiance.face_size]
print(json.dumps(out))
"""


def _import_all(python: str, cwd: Path, env_path: str | None = None) -> dict:
    names = sorted(_source_packages())
    env = None if env_path is None else {"PYTHONPATH": env_path, "PATH": "/usr/bin:/bin"}
    # -I: no current directory, no PYTHONPATH, no user site; with env_path the unpacked wheel must
    # come first on PYTHONPATH, which -I would ignore.
    flags = ["-I"] if env_path is None else []
    r = subprocess.run(
        [python, *flags, "-c", _PROBE, json.dumps(names)], capture_output=True, text=True, cwd=cwd, env=env, timeout=300
    )
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def _check(found: dict, root: Path) -> None:
    assert found.pop("__luts__") >= 1, "the shipped LUTs are missing from the installation"
    assert found.pop("__demo_sky__") == [5, 128], "the demo's baked sky (jaxpbr/_demo_sky) is missing from the installation"
    for name, path in found.items():
        assert Path(path).is_relative_to(root), f"{name} imported from {path}, not from the installation {root}"
    assert set(found) == _source_packages()


def test_every_subpackage_imports_from_the_installation(tmp_path):
    root = _installed_root(tmp_path)
    if root is None:
        pytest.skip("jaxpbr is not installed (tests run from a bare checkout)")
    if root == SOURCE:
        pytest.skip("editable install (it maps back to this checkout): test_every_subpackage_in_a_built_wheel (slow) builds a wheel instead")
    _check(_import_all(sys.executable, tmp_path), root)


@pytest.mark.slow
def test_every_subpackage_in_a_built_wheel(tmp_path):
    wheels = tmp_path / "wheels"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(SOURCE.parent)],
        capture_output=True, text=True, timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    (wheel,) = wheels.glob("jaxpbr-*.whl")
    unpacked = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(unpacked)
    site = [p for p in sys.path if p.endswith("site-packages")]
    _check(_import_all(sys.executable, tmp_path, ":".join([str(unpacked), *site])), unpacked.resolve())
