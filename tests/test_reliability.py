"""Probe cases of issue 13 (nothing lost, nothing silent), each reproduced first and kept fixed here.

Covered: a full disk (a real tiny tmpfs when the machine allows mounting one, and an injected
silent short write otherwise), files whose content is not the format their extension names, a
truncated image (one line on stderr, nothing on stdout), SIGINT and SIGTERM rolling back (also an
interrupted re-bake over a complete set, and a signal during a long native call), a scene asking
for float64, checks before the work (outputs, --exposure, --size that is not a mip of the cube,
float16 overflow naming --ktx-format), huge sizes refused with the flag named, API misuse (vectors
that are not 3-vectors, NaN directions and radiance, complex values, an empty batch, batch axes
that do not broadcast named per input) and exit status 2 for user-facing errors. Elsewhere: the
tracer in the asset cache, one program per supersampling offset and per render band
(tests/test_bake.py), the prefilter's exact-texel budget and far field (tests/test_specular.py; the
1024^2 sun in tests/test_slow.py), progress from inside the precompute programs
(tests/test_specular.py, tests/test_diffuse.py), the LUT's exact edges (tests/test_lut.py).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.io import image


def _cli(capfd, args, *, in_process=True, timeout=300):
    """`jaxpbr ARGS`: in this process through `jaxpbr.cli.main` (output captured at the file
    descriptors, so what a native library prints is seen too), or as a child process (the console
    entry as a user starts it; a few checks keep that path). -> (status, stdout, stderr)."""
    args = [str(a) for a in args]
    if not in_process:
        r = subprocess.run([sys.executable, "-m", "jaxpbr", *args], capture_output=True, text=True, timeout=timeout)
        return r.returncode, r.stdout, r.stderr
    from jaxpbr.cli import main

    capfd.readouterr()
    try:
        code = main(args)
    except SystemExit as exc:  # argparse's refusals
        code = exc.code
    out, err = capfd.readouterr()
    return code, out, err


# ---------------------------------------------------------------------------------- full disk


@pytest.fixture
def tiny_disk(tmp_path):
    """A 64 KiB tmpfs (needs mount privileges; skipped where there are none)."""
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    if shutil.which("mount") is None:
        pytest.skip("no mount command")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


@pytest.mark.parametrize("ext", [".png", ".exr", ".hdr"])
def test_image_write_to_a_full_disk_raises_and_leaves_nothing(tiny_disk, ext):
    img = np.random.default_rng(0).random((300, 300, 3)).astype(np.float32)  # far more than 64 KiB
    with pytest.raises(OSError):
        image.write(tiny_disk / f"x{ext}", img)
    assert list(tiny_disk.iterdir()) == []


def test_render_to_a_full_disk_fails_with_one_line_and_status_2(tiny_disk):
    out = subprocess.run(
        [sys.executable, "-m", "jaxpbr", "render", "--width", "640", "--height", "360", "-o", str(tiny_disk / "r.png")],
        capture_output=True, text=True, timeout=600,
    )
    assert out.returncode == 2, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("jaxpbr: error:") and "disk" in lines[0], out.stderr
    assert list(tiny_disk.iterdir()) == []


@pytest.mark.parametrize("ext", [".png", ".hdr", ".exr"])
@pytest.mark.parametrize("how", ["empty", "truncated"])
def test_a_silently_short_write_is_caught(tmp_path, monkeypatch, ext, how):
    """The image libraries returned normally on ENOSPC and left a 0-byte or truncated file: the
    write is read back before it replaces the destination, whose old content survives."""
    dest = tmp_path / f"x{ext}"
    old = np.full((8, 8, 3), 0.25, np.float32)
    image.write(dest, old)
    before = dest.read_bytes()
    real = {"png": image._write_oiio, "hdr": image._write_oiio, "exr": image._write_exr}[ext[1:]]

    def short(tmp, *a, **k):
        real(tmp, *a, **k)
        data = Path(tmp).read_bytes()
        Path(tmp).write_bytes(b"" if how == "empty" else data[: len(data) // 2])

    monkeypatch.setattr(image, "_write_exr" if ext == ".exr" else "_write_oiio", short)
    with pytest.raises(OSError, match="not written completely"):
        image.write(dest, np.random.default_rng(1).random((64, 64, 3)).astype(np.float32))
    assert dest.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == [dest.name]  # no temporary file left


# ------------------------------------------------------------------------- content, not the name


@pytest.mark.parametrize("real, named", [(".png", ".hdr"), (".png", ".exr"), (".exr", ".hdr"), (".hdr", ".png")])
def test_a_renamed_image_is_refused_naming_its_real_format(tmp_path, real, named):
    src = tmp_path / f"img{real}"
    image.write(src, np.full((4, 8, 3), 0.5, np.float32))
    renamed = tmp_path / f"img{named}"
    src.rename(renamed)
    want = {".png": "PNG", ".exr": "OpenEXR", ".hdr": "Radiance HDR"}[real]
    with pytest.raises(ValueError, match=f"content is {want}"):
        image.read(renamed)


def test_garbage_with_an_image_extension_is_refused(tmp_path):
    bad = tmp_path / "sky.hdr"
    bad.write_bytes(b"hello, not an image")
    with pytest.raises(ValueError, match="not an image format"):
        image.read(bad)


@pytest.mark.parametrize("ext", [".exr", ".hdr", ".png"])
def test_a_truncated_image_gives_one_line_and_nothing_on_stdout(tmp_path, capfd, ext):
    """OpenEXR's binding printed a warning on stdout and libOpenEXR a line on stderr, beside ours
    (the EXR case as a child process, the others in this process)."""
    rng = np.random.default_rng(0)
    whole = tmp_path / f"whole{ext}"
    image.write(whole, rng.random((64, 128, 3)).astype(np.float32))
    cut = tmp_path / f"cut{ext}"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size * 2 // 3])
    code, out, err = _cli(capfd, ["prefilter", cut, "--quiet", "-o", tmp_path / "p.ktx2"], in_process=ext != ".exr")
    assert code == 2, err
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxpbr: error:") and "cut" in lines[0], err


def test_cli_refuses_a_png_renamed_hdr_before_any_work(tmp_path):
    png = tmp_path / "pano.png"
    image.write(png, np.full((16, 32, 3), 0.5, np.float32))
    fake = tmp_path / "pano.hdr"
    png.rename(fake)
    out = subprocess.run(
        [sys.executable, "-m", "jaxpbr", "irradiance", str(fake), "-o", str(tmp_path / "irr.ktx2")],
        capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 2 and "content is PNG" in out.stderr, out.stderr
    assert len([ln for ln in out.stderr.splitlines() if ln.strip()]) == 1
    assert not (tmp_path / "irr.ktx2").exists()


# --------------------------------------------------------------------------------- signals


def _wait_for(pred, timeout):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if pred():
            return True
        time.sleep(0.02)
    return False


def _signal_when(cmd, ready, sig, env):
    """Start `cmd`, send `sig` as soon as ready() holds (skipping the probe if the command ends
    first), wait for it to exit -> (exit status, stderr)."""
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        seen = _wait_for(lambda: ready() or p.poll() is not None, 300)
        assert seen and p.poll() is None, "the command finished before the moment to probe"
        p.send_signal(sig)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    return p.returncode, err


def _status(sig):
    return 130 if sig == signal.SIGINT else 128 + signal.SIGTERM


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_during_a_bake_rolls_back(tmp_path, sig):
    """`jaxpbr ibl` killed after its first output appeared: nothing of the new set is left (the
    issue: only SIGINT rolled back; SIGTERM left irradiance.ktx2 + its sidecar)."""
    out_dir = tmp_path / "set"
    out_dir.mkdir()
    env = dict(os.environ, JAXPBR_COMPILATION_CACHE="off")
    cmd = [sys.executable, "-m", "jaxpbr", "ibl", "procedural:sky", "--face-size", "64", "--out-dir", str(out_dir), "--quiet"]
    code, err = _signal_when(cmd, lambda: any(out_dir.iterdir()), sig, env)
    assert code == _status(sig), err
    assert sorted(q.name for q in out_dir.iterdir()) == [], err


# ------------------------------------------------------------------------------ scene dtype


def test_scene_file_float64_renders_in_float64(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(
        '[render]\ndtype = "float64"\n[camera]\nwidth = 8\nheight = 6\n'
        '[[objects]]\ntype = "sphere"\ncenter = [0.0, 0.0, -3.0]\nradius = 1.0\n'
        '[[lights]]\ntype = "point"\nposition = [2.0, 2.0, 0.0]\nintensity = 10.0\n'
    )
    out = subprocess.run(
        [sys.executable, "-m", "jaxpbr", "render", str(scene), "-o", str(tmp_path / "s.png"), "--hdr"],
        capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert "warn" not in out.stderr.lower(), out.stderr
    meta = image.read_with_metadata(tmp_path / "s.exr")[1]
    assert "float64" in meta["jaxpbr:render_options"]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupted_rebake_keeps_the_previous_set(tmp_path, sig):
    """A complete set in the folder, then a re-bake interrupted after its first new file appeared:
    the previous set is there, byte for byte (the issue: the rollback deleted the new irradiance,
    which had replaced the old one, leaving an ibl.json naming a missing file)."""
    out_dir = tmp_path / "set"
    out_dir.mkdir()
    env = dict(os.environ, JAXPBR_COMPILATION_CACHE="off")
    cmd = [sys.executable, "-m", "jaxpbr", "ibl", "procedural:sky", "--face-size", "32", "--out-dir", str(out_dir), "--quiet"]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert first.returncode == 0, first.stderr
    before = {p.name: p.read_bytes() for p in out_dir.iterdir()}
    assert {"irradiance.ktx2", "prefiltered.ktx2", "brdf_lut.exr", "ibl.json"} <= set(before)
    stamp = {p.name: p.stat().st_mtime_ns for p in out_dir.iterdir()}
    cmd[cmd.index("--face-size") + 1] = "64"  # a different set, so every file changes

    def replaced():
        return any(q.name in stamp and q.stat().st_mtime_ns != stamp[q.name] for q in out_dir.iterdir() if not q.name.startswith("."))

    code, err = _signal_when(cmd, replaced, sig, env)
    assert code == _status(sig), err
    after = {q.name: q.read_bytes() for q in out_dir.iterdir()}
    assert after == before


def test_output_set_protect_restores_replaced_files_and_cleans_up(tmp_path):
    from jaxpbr.io.atomic import OutputSet, atomic_write

    a, b, c = tmp_path / "a.txt", tmp_path / "b.txt", tmp_path / "c.txt"
    a.write_text("old a")
    b.write_text("old b")
    with pytest.raises(RuntimeError):
        with OutputSet() as outs:
            outs.protect([a, b, c])  # c does not exist yet
            for p in (a, c):
                outs.add(p)  # registered before the write (the protocol)
                atomic_write(p, lambda tmp: Path(tmp).write_text("new"))
            outs.add(b)  # registered, failure before it is written: its old content stays
            raise RuntimeError("fails midway")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]
    assert a.read_text() == "old a" and b.read_text() == "old b"
    with OutputSet() as outs:
        outs.protect([a, b])
        outs.add(a)
        atomic_write(a, lambda tmp: Path(tmp).write_text("new a"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]  # no backups left
    assert a.read_text() == "new a" and b.read_text() == "old b"


# ----------------------------------------------------------------------- checks before the work


@pytest.mark.parametrize("case", ["output_is_a_dir", "exr_is_a_dir", "missing_dir", "nan_exposure", "inf_exposure"])
def test_render_refuses_bad_outputs_and_values_before_rendering(tmp_path, capfd, case):
    """(missing_dir as a child process, the others in this process)"""
    out = tmp_path / "r.png"
    args = ["--width", "16", "--height", "9", "-o", out]
    if case == "output_is_a_dir":
        out.mkdir()
    elif case == "exr_is_a_dir":
        (tmp_path / "r.exr").mkdir()
        args.append("--hdr")
    elif case == "missing_dir":
        args[-1] = tmp_path / "nope" / "r.png"
    else:
        args += ["--exposure", "nan" if case == "nan_exposure" else "inf"]
    t0 = time.monotonic()
    code, out, err = _cli(capfd, ["render", *args], in_process=case != "missing_dir")
    assert code == 2, err
    assert "render " not in out  # nothing was rendered
    assert len([ln for ln in err.splitlines() if ln.strip()]) == 1, err  # one line (argparse's too)
    assert not (tmp_path / "r.png").is_file()
    assert time.monotonic() - t0 < 60


def test_render_hdr_failure_leaves_no_png(tmp_path, monkeypatch):
    """--hdr writes the PNG then the EXR; if the EXR cannot be written, the PNG goes too (in process)."""
    from jaxpbr.cli import main

    def fail_exr(*a, **k):
        raise OSError("injected: no space left on device")

    monkeypatch.setattr(image, "_write_exr", fail_exr)
    out = tmp_path / "r.png"
    assert main(["render", "--width", "16", "--height", "9", "-o", str(out), "--hdr"]) == 2
    assert list(tmp_path.iterdir()) == []


def test_render_to_a_read_only_folder_is_refused_before_rendering(tmp_path, capfd):
    mnt = tmp_path / "ro"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k,ro", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip("cannot mount a read-only tmpfs here")
    try:
        code, out, err = _cli(capfd, ["render", "--width", "16", "--height", "9", "-o", mnt / "r.png"])
        assert code == 2 and "not writable" in err, err
        assert "render " not in out
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


# ------------------------------------------------------------------------------ API misuse


@pytest.mark.parametrize("shape", [(1,), (2,), (4,), (5,), ()])
def test_brdf_refuses_vectors_that_are_not_3_vectors(shape):
    good = np.array([0.0, 0.0, 1.0])
    bad = np.ones(shape)
    m = jp.Material()
    for args in ((bad, good, good), (good, bad, good), (good, good, bad)):
        with pytest.raises(ValueError, match=r"trailing axis of 3|3-vector"):
            jp.brdf(*args, m)


def test_brdf_refuses_a_nan_direction_and_names_it():
    good = np.array([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="^n contains NaN"):
        jp.brdf(np.array([np.nan, 0.0, 1.0]), good, good, jp.Material())


def test_traced_metallic_out_of_range_is_clamped_not_negative():
    n = jnp.array([0.0, 0.0, 1.0])
    v = jnp.array([0.0, 0.6, 0.8])
    l = jnp.array([0.6, 0.0, 0.8])

    def f(met):  # a traced metallic is not validated (its value does not exist yet)
        return jp.brdf(n, v, l, jp.Material(base_color=(0.9, 0.5, 0.2), metallic=met, roughness=0.5))

    low, high = jax.jit(f)(-1.0), jax.jit(f)(2.0)
    np.testing.assert_array_equal(np.asarray(low), np.asarray(jax.jit(f)(0.0)))
    np.testing.assert_array_equal(np.asarray(high), np.asarray(jax.jit(f)(1.0)))
    assert np.all(np.asarray(low) >= 0)


def _batch_case(kernel):
    """(fn, args, names): a kernel whose inputs' batch axes disagree (n, v of 10; l of 7, a
    roughness of 4 or a v of 3), and the names the message must contain."""
    n = np.tile([0.0, 0.0, 1.0], (10, 1))
    v = np.tile([0.0, 0.6, 0.8], (10, 1))
    r4 = np.full(4, 0.5)
    if kernel == "brdf":
        return (lambda n, v, l: jp.brdf(n, v, l, jp.Material())), (n, v, v[:7]), ("brdf", "n (10,)", "l (7,)")
    if kernel == "brdf_material":
        return (lambda n, v, r: jp.brdf(n, v, v, jp.Material(roughness=r))), (n, v, r4), ("brdf", "m.roughness (4,)")
    if kernel == "shade_direct":
        light = jp.DirectionalLight(direction=(0.0, -1.0, 0.0))
        fn = lambda n, v, r: jp.shade_direct(jnp.zeros_like(n), n, v, jp.Material(roughness=r), [light])  # noqa: E731
        return fn, (n, v, r4), ("shade_direct", "m.roughness (4,)")
    env = jp.Cubemap([np.ones((6, 2, 2, 3), np.float32)])
    lut = np.ones((4, 4, 2), np.float32)
    return (lambda n, v: jp.shade_ibl(n, v, jp.Material(), env, env, lut)), (n, v[:3]), ("shade_ibl", "v (3,)")


@pytest.mark.parametrize("kernel", ["brdf", "brdf_material", "shade_direct", "shade_ibl"])
@pytest.mark.parametrize("traced", [False, True])
def test_mismatched_batch_axes_name_the_function_and_the_inputs(kernel, traced):
    fn, args, names = _batch_case(kernel)
    with pytest.raises(ValueError, match="batch axes do not broadcast") as err:
        (jax.jit(fn) if traced else fn)(*args)
    for name in names:
        assert name in str(err.value)


@pytest.mark.parametrize("model, multiscatter", [("gltf", False), ("gltf", True), ("learnopengl", False)])
def test_traced_metallic_out_of_range_is_clamped_in_ibl(model, multiscatter):
    """The IBL term clamped metallic only in its multiscatter mix: f0() and diffuse_color() read
    the raw value, so a traced metallic -1 shaded brighter than metallic 0."""
    env = jp.Cubemap([np.ones((6, 2, 2, 3), np.float32)])
    lut = np.asarray(jp.compute_brdf_lut(size=8, smith="schlick_ggx" if model == "learnopengl" else "correlated"))
    n, v = jnp.array([0.0, 0.0, 1.0]), jnp.array([0.0, 0.6, 0.8])

    def f(met):
        m = jp.Material(base_color=(0.8, 0.5, 0.3), metallic=met, roughness=0.5)
        return jp.shade_ibl(n, v, m, env, env, lut, model=model, multiscatter=multiscatter)

    g = jax.jit(f)
    np.testing.assert_array_equal(np.asarray(g(-1.0)), np.asarray(g(0.0)))
    np.testing.assert_array_equal(np.asarray(g(2.0)), np.asarray(g(1.0)))


def test_complex_values_are_refused():
    with pytest.raises(TypeError, match="real values"):
        jp.Material(roughness=0.5 + 0.1j)


def test_render_batch_refuses_an_empty_batch():
    scene = jp.Scene(camera=jp.Camera(width=4, height=4), objects=[jp.Sphere(center=(0, 0, -3))])
    mats = jp.Material(base_color=np.zeros((0, 3)), metallic=np.zeros(0), roughness=np.zeros(0))
    with pytest.raises(ValueError, match="empty batch"):
        jp.render_batch(scene, materials=mats)


@pytest.mark.parametrize("bad, what", [(np.nan, "NaN"), (-1.0, "negative")])
def test_environment_refuses_nan_and_negative_radiance(bad, what):
    lv = np.ones((6, 4, 4, 3), np.float32)
    lv[2, 1, 1, 0] = bad
    with pytest.raises(ValueError, match=what):
        jp.Environment(radiance=jp.Cubemap([lv]))


def test_a_grey_panorama_becomes_rgb_radiance(tmp_path):
    from jaxpbr.ibl.cubeio import load_environment

    grey = tmp_path / "grey.exr"
    image.write(grey, np.full((16, 32), 2.0, np.float32))
    cube = load_environment(str(grey), face_size=8)
    assert cube.channels == 3
    np.testing.assert_allclose(np.asarray(cube.levels[0]), 2.0, rtol=1e-6)


def test_ibl_checks_every_output_before_any_work(tmp_path):
    (tmp_path / "brdf_lut.exr").mkdir()  # the last output cannot be written
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "jaxpbr", "ibl", "procedural:sky", "--face-size", "16", "--out-dir", str(tmp_path)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "brdf_lut.exr" in r.stderr, r.stderr
    assert "wrote" not in r.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["brdf_lut.exr"]
    assert time.monotonic() - t0 < 60


def _no_work(monkeypatch):
    """Make every precompute of the IBL commands fail loudly: a refusal must come before them."""
    import jaxpbr.cli.ibl as cli_ibl

    def started(*a, **k):
        raise AssertionError("the work started before the input was refused")

    for name in ("prefilter", "irradiance", "brdf_lut"):
        monkeypatch.setattr(cli_ibl, name, started)


@pytest.fixture
def hot_panorama(tmp_path):
    """A 64 x 128 panorama with a 1e6-radiance spot: beyond float16 (65504) at every size."""
    img = np.ones((64, 128, 3), np.float32)
    img[20:28, 40:48] = 1e6
    path = tmp_path / "hot.exr"
    image.write(path, img)
    return path


@pytest.mark.parametrize("command", ["prefilter", "ibl"])
def test_float16_overflow_is_refused_before_the_work_naming_the_flag(tmp_path, monkeypatch, capsys, hot_panorama, command):
    from jaxpbr.cli import main

    _no_work(monkeypatch)
    out = ["-o", str(tmp_path / "p.ktx2")] if command == "prefilter" else ["--out-dir", str(tmp_path)]
    assert main([command, str(hot_panorama), "--quiet", *out]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--ktx-format rgba32f" in err[0] and "fmt=" not in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hot.exr"]


def test_float16_overflow_found_at_the_write_names_the_flag(tmp_path, capsys):
    """Irradiance cannot be bounded before it is computed: its write refuses, naming the flag."""
    from jaxpbr.cli import main

    uniform = tmp_path / "uniform.exr"
    image.write(uniform, np.full((16, 32, 3), 1e5, np.float32))
    assert main(["irradiance", str(uniform), "--size", "4", "--quiet", "--no-error", "-o", str(tmp_path / "irr.ktx2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--ktx-format rgba32f" in err[0] and "fmt=" not in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["uniform.exr"]


@pytest.mark.parametrize("command", ["prefilter", "ibl"])
@pytest.mark.parametrize("face", [None, "64"])
def test_a_prefilter_size_that_is_not_a_mip_is_refused_before_the_work(tmp_path, monkeypatch, capsys, command, face):
    from jaxpbr.cli import main

    _no_work(monkeypatch)
    out = ["-o", str(tmp_path / "p.ktx2")] if command == "prefilter" else ["--out-dir", str(tmp_path)]
    sizes = ["--face-size", face] if face else []
    assert main([command, "procedural:sky", *sizes, "--size", "48", "--quiet", *out]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--size 48" in err[0] and "from_equirect" not in err[0], err
    assert list(tmp_path.iterdir()) == []


def test_report_precompute_checks_its_output_before_the_sweep(tmp_path, capfd):
    """The sweep logs its progress on stderr: a refusal before it is the only line there."""
    t0 = time.monotonic()
    code, _, err = _cli(capfd, ["report", "precompute", "--quick", "--out", tmp_path / "nope" / "rep"])
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "does not exist" in lines[0], err
    assert time.monotonic() - t0 < 30


def test_the_command_line_ends_after_the_work_in_flight_and_the_exit_handlers(tmp_path):
    """The command line's process ends with os._exit (no interpreter finalization), after a
    program still being compiled and stored and a map still going to the asset cache are done,
    after the atexit handlers, with its output flushed."""
    script = f"""
import atexit, sys, time
from pathlib import Path
from jaxpbr import _program_cache
from jaxpbr.cli import _end_process
from jaxpbr.rendering import execute
d = Path({str(tmp_path)!r})
def slow(name):
    time.sleep(0.5)
    (d / name).write_text("done")
_program_cache._compiler(1).submit(slow, "stored")
execute.worker_pool().submit(slow, "cached")
atexit.register(lambda: (d / "atexit").write_text("ran"))
print("buffered line", end="")
import ctypes
libc = ctypes.CDLL(None)
libc.printf(b" and C's")  # (C's stdout to a pipe is block-buffered)
_end_process(3)
"""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # (which unbuffers C's stdio too)
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False, env=env)
    assert r.returncode == 3, r.stderr
    assert r.stdout == "buffered line and C's"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["atexit", "cached", "stored"]


# ------------------------------------------------------------------------------- huge sizes


@pytest.mark.parametrize(
    "args, flag",
    [
        (["lut", "--size", "100000", "-o", "{d}/x.exr"], "--size"),
        (["render", "--width", "100000", "--height", "100000", "-o", "{d}/x.png"], "--width/--height"),
        (["prefilter", "procedural:sky", "--face-size", "100000", "-o", "{d}/x.ktx2"], "--face-size"),
        (["irradiance", "procedural:sky", "--size", "100000", "-o", "{d}/x.ktx2"], "--size"),
        (["ibl", "procedural:sky", "--face-size", "100000", "--out-dir", "{d}"], "--face-size"),
    ],
)
def test_huge_sizes_are_refused_before_any_work_naming_the_flag(tmp_path, capfd, args, flag):
    """They aborted inside XLA (exit 134 with a C++ stack) or printed NumPy's allocation error
    (render's case as a child process, the others in this process)."""
    t0 = time.monotonic()
    code, _, err = _cli(capfd, [a.format(d=tmp_path) for a in args], in_process=args[0] != "render", timeout=120)
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "GB of memory" in lines[0] and flag in lines[0] and "JAXPBR_MEMORY_LIMIT" in lines[0], err
    assert list(tmp_path.iterdir()) == []
    assert time.monotonic() - t0 < 60


def test_the_memory_limit_can_be_set(monkeypatch):
    from jaxpbr.cli._common import CLIError, require_memory

    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "1")
    require_memory("a small thing", 0.5e9, "lower it")
    with pytest.raises(CLIError, match=r"needs about 2 GB of memory, more than the 1 GB available; lower it"):
        require_memory("a big thing", 2e9, "lower it")
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "lots")
    with pytest.raises(CLIError, match="number of gigabytes"):
        require_memory("anything", 1.0, "x")


def test_sigterm_during_a_long_native_call_acts_within_seconds(tmp_path):
    """While the main thread sits in one long XLA computation, Python cannot run a signal handler;
    the watchdog thread rolls back and exits with the signal's status after a short grace period
    (a `timeout` SIGTERM was otherwise ignored until the computation ended: minutes)."""
    env = dict(os.environ, JAXPBR_COMPILATION_CACHE="off")
    p = subprocess.Popen([sys.executable, "-m", "jaxpbr", "lut", "--size", "6000", "-o", str(tmp_path / "big.exr"), "--no-error"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        time.sleep(4.0)  # past start-up, inside the LUT computation
        assert p.poll() is None, "finished too early to probe"
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=30)
        waited = time.monotonic() - t0
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines()[-1] == "jaxpbr: terminated"
    assert waited < 10, waited
    assert list(tmp_path.iterdir()) == []
