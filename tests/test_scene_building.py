"""One way to build a scene from a glTF asset: `jp.load_gltf`, `jaxpbr render ASSET` and a batch
job give the same scene (camera, meshes, lights, environment) for the same asset and flags: the
camera rules (the asset's first camera, else a framing of its bounds; overrides of position,
target and field of view) and the environment ("procedural:sky" is the demo's baked sky, a file is
read by `jp.load_environment`) are written once (`gltf_scene.scene_from_asset`)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.batch.jobs import parse_jobs
from jaxpbr.errors import InputError
from jaxpbr.batch.work import Worker
from jaxpbr.cli import build_parser
from jaxpbr.cli.render import _gltf_scene
from jaxpbr.rendering.demo import demo_environment, write_demo_glb

W, H = 64, 36


@pytest.fixture(scope="module", params=[True, False], ids=["asset-camera", "no-camera"])
def asset(request, tmp_path_factory):
    path = tmp_path_factory.mktemp("grid") / "grid.glb"
    write_demo_glb(path, triangles=2000, camera=request.param)
    return path


FLAGS = {
    "none": {},
    "fov": {"fov_y_deg": 30.0},
    "position": {"camera_position": (3.0, 2.0, 30.0)},
    "both": {"camera_position": (3.0, 2.0, 30.0), "camera_target": (1.0, 0.0, 0.0), "fov_y_deg": 50.0},
}


def _cli(path, flags, env, intensity):
    argv = ["render", str(path), "--width", str(W), "--height", str(H), "--environment", env,
            "--environment-intensity", str(intensity)]
    if "camera_position" in flags:
        argv += ["--camera-position", ",".join(map(str, flags["camera_position"]))]
    if "camera_target" in flags:
        argv += ["--camera-target", ",".join(map(str, flags["camera_target"]))]
    if "fov_y_deg" in flags:
        argv += ["--fov-y", str(flags["fov_y_deg"])]
    return _gltf_scene(build_parser().parse_args(argv))[0]


def _batch(path, flags, env, intensity, tmp_path):
    cam = {}
    if "camera_position" in flags:
        cam["position"] = list(flags["camera_position"])
    if "camera_target" in flags:
        cam["target"] = list(flags["camera_target"])
    if "fov_y_deg" in flags:
        cam["fov_y"] = flags["fov_y_deg"]
    row = {"name": "a", "scene": str(path), "width": W, "height": H, "environment": env, "environment_intensity": intensity}
    if cam:
        row["camera"] = cam
    (job,) = parse_jobs(json.dumps(row), base_dir=tmp_path)
    return Worker(tmp_path / "out").scene(job)[0]


def _same(a, b):
    for f in ("position", "target", "up", "fov_y_deg", "width", "height", "supersample", "projection"):
        x, y = getattr(a.camera, f), getattr(b.camera, f)
        if isinstance(x, str):
            assert x == y, f
        else:
            np.testing.assert_allclose(np.asarray(x, np.float64), np.asarray(y, np.float64), rtol=1e-6, atol=1e-9, err_msg=f)
    assert len(a.objects) == len(b.objects) and len(a.lights) == len(b.lights)
    for p, q in zip(a.objects, b.objects, strict=True):
        np.testing.assert_array_equal(np.asarray(p.positions), np.asarray(q.positions))
    ea, eb = a.environment, b.environment
    assert float(ea.intensity) == float(eb.intensity) and float(ea.rotation) == float(eb.rotation)
    np.testing.assert_array_equal(np.asarray(ea.radiance.levels[0]), np.asarray(eb.radiance.levels[0]))
    assert (ea.prefiltered is None) == (eb.prefiltered is None)


@pytest.mark.parametrize("name", list(FLAGS))
def test_library_command_line_and_batch_build_the_same_scene(asset, name, tmp_path):
    flags = FLAGS[name]
    lib = jp.load_gltf(asset, width=W, height=H, environment="procedural:sky", environment_intensity=0.5, **flags)
    _same(lib, _cli(asset, flags, "procedural:sky", 0.5))
    _same(lib, _batch(asset, flags, "procedural:sky", 0.5, tmp_path))
    # "procedural:sky" is the demo's sky, baked: the shipped set (nothing to precompute)
    sky = demo_environment()
    np.testing.assert_array_equal(np.asarray(lib.environment.radiance.levels[0]), np.asarray(sky.radiance.levels[0]))
    assert lib.environment.prefiltered is not None
    # the rules themselves: an override is kept; the field of view is the override's, else the
    # asset's first camera's, else 45 degrees
    if "camera_position" in flags:
        np.testing.assert_allclose(lib.camera.position, flags["camera_position"])
    cams = _cameras(asset)
    fov = flags.get("fov_y_deg", math.degrees(cams[0].yfov) if cams else 45.0)
    assert math.isclose(float(lib.camera.fov_y_deg), fov, rel_tol=1e-6)


def _cameras(path):
    from jaxpbr.io.gltf import read_gltf

    return read_gltf(path).cameras


def test_an_environment_file_is_read_the_same_way(asset, tmp_path):
    hdr = tmp_path / "sky.hdr"
    jp.image.write(hdr, np.broadcast_to(np.linspace(0.2, 2.0, 32, dtype=np.float32)[:, None, None], (32, 64, 3)).copy())
    lib = jp.load_gltf(asset, width=W, height=H, environment=str(hdr))
    _same(lib, _cli(asset, {}, str(hdr), 1.0))
    _same(lib, _batch(asset, {}, str(hdr), 1.0, tmp_path))
    np.testing.assert_array_equal(np.asarray(lib.environment.radiance.levels[0]),
                                  np.asarray(jp.load_environment(str(hdr)).levels[0]))


def test_an_environment_keeps_the_rotation_and_intensity_not_given(asset):
    from jaxpbr.rendering.gltf_scene import environment_from

    env = demo_environment().replace(rotation=1.0, intensity=3.0)
    e = environment_from(env, intensity=2.0)
    assert float(e.rotation) == 1.0 and float(e.intensity) == 2.0
    e = environment_from(env, rotation=0.5)
    assert float(e.rotation) == 0.5 and float(e.intensity) == 3.0
    assert environment_from(env) is env
    lib = jp.load_gltf(asset, width=W, height=H, environment=env, environment_rotation=0.25)
    assert float(lib.environment.rotation) == 0.25 and float(lib.environment.intensity) == 3.0


def test_a_loaded_cubemap_or_a_path_is_an_environment_and_anything_else_is_refused(asset, tmp_path):
    """`jp.load_environment` returns a Cubemap; passed on to `jp.load_gltf` it is the scene's
    radiance, as the same file's path (or a pathlib.Path) is. Another type is an InputError naming
    what is accepted."""
    hdr = tmp_path / "sky.hdr"
    jp.image.write(hdr, np.broadcast_to(np.linspace(0.2, 2.0, 32, dtype=np.float32)[:, None, None], (32, 64, 3)).copy())
    by_path = jp.load_gltf(asset, width=W, height=H, environment=str(hdr))
    for env in (jp.load_environment(str(hdr)), hdr):
        got = jp.load_gltf(asset, width=W, height=H, environment=env)
        np.testing.assert_array_equal(np.asarray(got.environment.radiance.levels[0]),
                                      np.asarray(by_path.environment.radiance.levels[0]))
    with pytest.raises(InputError, match="environment must be None, an Environment, a Cubemap"):
        jp.load_gltf(asset, width=W, height=H, environment=3.0)
