"""The demo render, the CLI (render, bench, errors) and `python -m jaxpbr`."""

import subprocess
import sys

import numpy as np
import pytest

import jaxpbr as jp
import reference as ref
from jaxpbr.cli import main
from jaxpbr.scene import Camera, demo_scene, primary_rays, render_demo

W, H = 65, 37  # odd: the centre pixel's ray is exactly the camera axis


@pytest.fixture(scope="module")
def demo():
    return np.asarray(render_demo(W, H))


def test_demo_render_is_finite_nonnegative_and_shows_49_spheres(demo):
    assert demo.shape == (H, W, 3) and demo.dtype == np.float32
    assert np.isfinite(demo).all() and (demo >= 0).all()
    # Each sphere centre projects inside the frame and is lit (non-black) there.
    cam = Camera(width=W, height=H)
    spheres, _ = demo_scene()
    t = np.tan(np.radians(cam.fov_y_deg) / 2)
    for c in np.asarray(spheres.center):
        z = cam.position[2] - c[2]
        j = int((c[0] / (z * t * W / H) + 1) / 2 * W)
        i = int((1 - c[1] / (z * t)) / 2 * H)
        assert demo[i, j].sum() > 0


def test_demo_centre_pixel_matches_independent_shading(demo):
    """Centre pixel: ray -Z hits the middle sphere (row 3, col 3) at p = (0, 0, 1), n = v = +Z.
    Shade it independently: glTF BRDF of tests/reference.py, 4 lights of 300 at (+-10, +-10, 10)
    with 1/d^2, plus the 0.03 * albedo * ao ambient; float32 image vs float64 reference."""
    p = np.array([0.0, 0.0, 1.0])
    n = v = np.array([0.0, 0.0, 1.0])
    albedo, metallic, rough = np.array([0.5, 0.0, 0.0]), 3 / 7, 3 / 7
    expected = 0.03 * albedo
    for x in (-10.0, 10.0):
        for y in (-10.0, 10.0):
            d = np.array([x, y, 10.0]) - p
            l = d / np.linalg.norm(d)
            expected = expected + ref.gltf_material(n, v, l, albedo, metallic, rough) * 300.0 / d.dot(d) * n.dot(l)
    o, dirs = primary_rays(Camera(width=W, height=H), dtype=np.float64)
    np.testing.assert_allclose(np.asarray(dirs)[H // 2, W // 2], [0, 0, -1], atol=1e-12)
    # float32 pipeline (ray-sphere hit, normals, shading): relative error a few ulps x condition.
    np.testing.assert_allclose(demo[H // 2, W // 2], expected, rtol=2e-5, atol=1e-7)


def test_learnopengl_demo_differs_from_gltf_but_is_close(demo):
    lo = np.asarray(render_demo(W, H, model="learnopengl"))
    assert np.isfinite(lo).all()
    assert not np.allclose(lo, demo)
    hit = demo.sum(-1) > 0
    # Same scene and lights, different G and diffuse/specular split: within a factor of 2 on average.
    ratio = lo[hit].sum() / demo[hit].sum()
    assert 0.5 < ratio < 2.0


def test_cli_render_writes_png_and_exr_with_metadata(tmp_path, capsys):
    out = tmp_path / "demo.png"
    assert main(["render", "-o", str(out), "--width", "48", "--height", "32", "--hdr", "--bits", "16"]) == 0
    png, meta = jp.image.read_with_metadata(out)
    assert png.shape[:2] == (32, 48) and png.max() > 0.1
    exr, exr_meta = jp.image.read_with_metadata(tmp_path / "demo.exr")
    assert exr.shape == (32, 48, 3) and np.isfinite(exr).all()
    assert "gltf" in str(exr_meta.get("jaxpbr:model"))
    assert "alpha = r^2" in str(exr_meta.get("jaxpbr:conventions"))
    assert "wrote" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv,message",
    [
        (["render", "-o", "{tmp}/missing_dir/x.png"], "does not exist"),
        (["render", "-o", "{tmp}/x.jpg"], "must end in .png"),
    ],
)
def test_cli_bad_output_one_line_error_no_file(tmp_path, capsys, argv, message):
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxpbr: error:") and message in err and len(err.splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_cli_rejects_nonpositive_size(capsys):
    with pytest.raises(SystemExit) as e:
        main(["render", "--width", "0"])
    assert e.value.code == 2
    assert "positive integer" in capsys.readouterr().err


def test_cli_bench_shade_small_runs_and_agrees(capsys):
    # Runs the benchmark machinery at a tiny size: it checks JAX and NumPy agree, not speed.
    assert main(["bench", "shade", "--width", "40", "--height", "24", "--repeats", "1", "--numpy-repeats", "1"]) == 0
    out = capsys.readouterr().out
    assert "speed-up jax/numpy" in out
    rel = float(out.split("max relative difference jax vs numpy:")[1].split()[0])
    assert rel < 1e-4  # float32 both sides, same formulas


def test_python_dash_m_help():
    r = subprocess.run([sys.executable, "-m", "jaxpbr", "--help"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "render" in r.stdout and "bench" in r.stdout
