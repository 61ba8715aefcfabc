"""`examples/first_image_vs_mitsuba.py`'s inputs, checked without running the processes it times:
the panorama it writes reads back (an equirect HDR with a sun), and the Mitsuba scene it describes
holds the asset's triangles (its PLY read by trimesh, an independent reader) and the demo's 49
spheres, materials and camera."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from jaxpbr.io import image
from jaxpbr.rendering.demo import demo_scene, uv_sphere, write_demo_glb


@pytest.fixture(scope="module")
def example():
    path = Path(__file__).resolve().parent.parent / "examples" / "first_image_vs_mitsuba.py"
    spec = importlib.util.spec_from_file_location("first_image_vs_mitsuba", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_panorama_is_a_readable_hdr_with_a_sun(example, tmp_path):
    a = image.read(example.write_panorama(tmp_path / "a.hdr", width=256, seed=1))
    b = image.read(example.write_panorama(tmp_path / "b.hdr", width=256, seed=2))
    assert a.shape == (128, 256, 3) and np.isfinite(a).all() and (a >= 0).all()
    assert a.max() > 1e4 and 0.05 < np.median(a) < 2.0  # a sun far above a sky and ground of order 1
    assert not np.array_equal(a, b)  # fresh content per seed: never found in a cache


def test_mitsuba_scene_has_the_assets_triangles_spheres_and_camera(example, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    asset = write_demo_glb(tmp_path / "grid.glb", triangles=5000)
    spec = json.loads(example.mitsuba_spec(asset, tmp_path, tmp_path / "p.hdr", "scalar_rgb", 16, size=(64, 48)).read_text())
    P, _, T = uv_sphere(asset.lat)
    ply = trimesh.load(spec["ply"], process=False)
    np.testing.assert_array_equal(np.asarray(ply.faces), T)
    np.testing.assert_allclose(np.asarray(ply.vertices), P, rtol=0, atol=1e-7)
    assert 49 * len(T) == asset.triangles
    ref = demo_scene(64, 48)
    assert len(spec["spheres"]) == len(ref.objects) == 49
    for s, o in zip(spec["spheres"], ref.objects):
        np.testing.assert_allclose(s["center"], np.asarray(o.center))
        assert s["radius"] == pytest.approx(float(o.radius))
        assert s["roughness"] == pytest.approx(float(o.material.roughness))
        assert s["metallic"] == pytest.approx(float(o.material.metallic))
    cam = spec["camera"]
    assert (cam["width"], cam["height"]) == (64, 48) and cam["fov_y"] == pytest.approx(float(ref.camera.fov_y_deg))


@pytest.mark.slow
def test_gradient_step_memory_example_runs_every_phase():
    """`examples/gradient_step_memory.py` on a small asset: every phase reported with its memory,
    and the step's gradient points back towards the target (the base colours were scaled by 0.9 of
    the target's: raising the scale lowers the loss)."""
    path = Path(__file__).resolve().parent.parent / "examples" / "gradient_step_memory.py"
    spec = importlib.util.spec_from_file_location("gradient_step_memory", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = mod.main(["--size", "32", "--triangles", "2000", "--steps", "1"])
    assert [r["phase"].split()[0] for r in out["rows"]] == ["imported,", "asset", "forward", "gradient", "1"]
    assert all(np.isfinite(r["peak_gb"]) and r["peak_gb"] > 0 for r in out["rows"])
    assert out["loss"] > 0 and np.isfinite(out["grad"]) and out["grad"] < 0
    assert out["xla_temp_bytes"] > 0
