"""The demo render, the CLI (render, bench, errors) and `python -m jaxpbr`."""

import subprocess
import sys

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.cli import main
from jaxpbr.rendering.demo import demo_scene, learnopengl_scene


def test_learnopengl_model_differs_from_gltf_but_is_close():
    scene = learnopengl_scene(33, 19)
    g = np.asarray(jp.render(scene))
    lo = np.asarray(jp.render(scene, model="learnopengl"))
    assert np.isfinite(lo).all()
    assert not np.allclose(lo, g)
    hit = g.sum(-1) > 0
    # Same scene and lights, different G and diffuse/specular split: within a factor of 2 on average.
    ratio = lo[hit].sum() / g[hit].sum()
    assert 0.5 < ratio < 2.0


def test_default_demo_renders_finite_with_sky_background():
    """The README's main job at a small size: 49 spheres (r = 0 mirror column included), the sky
    with its 3000-radiance sun, four lights; finite, non-negative, sky where nothing is hit."""
    scene = demo_scene(48, 27, face_size=32)
    img = np.asarray(jp.render(scene))
    assert img.shape == (27, 48, 3) and np.isfinite(img).all() and (img >= 0).all()
    plan = jp.rendering.renderer.plan(scene)
    assert plan.direct and plan.ibl and plan.ibl_diffuse and plan.prefilter_levels == plan.mapping_levels
    # Top-left corner: sky above the horizon, bluish (zenith blue > red).
    assert img[0, 0, 2] > img[0, 0, 0] > 0


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
