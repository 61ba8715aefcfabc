"""`jaxpbr render ASSET --time T [--animation NAME]` and `--frames START:END:STEP -o frame_%04d.png`:
each frame is the render of `jaxpbr.load_gltf(path, time=t)` with the same camera, the files are
written whole or not at all, and misuse is one clear line."""

from __future__ import annotations

import numpy as np
import pytest

import jaxpbr as jp
from gltf_animated import trs_animation
from jaxpbr.cli import main

CAM = ["--camera-position", "3,2,6", "--camera-target", "0,0.5,1", "--width", "40", "--height", "30", "--environment", "procedural:sky"]


@pytest.fixture(scope="module")
def asset(tmp_path_factory):
    return trs_animation(tmp_path_factory.mktemp("anim"))[0]


def test_frames_match_load_gltf_at_each_time(asset, tmp_path, capsys):
    out = tmp_path / "f_%02d.png"
    assert main(["render", str(asset), "--frames", "0.5:2:0.75", "--animation", "trs", "--hdr", "-o", str(out), *CAM]) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["f_00.exr", "f_00.png", "f_01.exr", "f_01.png", "f_02.exr", "f_02.png"]
    frames = []
    for k, t in enumerate((0.5, 1.25, 2.0)):
        img, meta = jp.image.read_with_metadata(tmp_path / f"f_{k:02d}.exr")
        assert f"animation 0 (trs) at {t:g} s" in str(meta.get("jaxpbr:scene"))
        scene = jp.load_gltf(asset, time=t, animation="trs", camera_position=(3, 2, 6), camera_target=(0, 0.5, 1),
                             width=40, height=30, environment="procedural:sky")
        np.testing.assert_allclose(img, np.asarray(jp.render(scene)), rtol=1e-5, atol=1e-6)
        frames.append(img)
    assert all(np.abs(frames[k] - frames[k + 1]).max() > 0.05 for k in range(2))  # the animation moves
    assert capsys.readouterr().out.count("wrote") == 6  # (a PNG and an EXR a frame)


def test_time_poses_one_image(asset, tmp_path):
    out = tmp_path / "t.png"
    assert main(["render", str(asset), "--time", "1.25", "--hdr", "-o", str(out), *CAM]) == 0
    rest = tmp_path / "rest.png"
    assert main(["render", str(asset), "--hdr", "-o", str(rest), *CAM]) == 0
    a, b = jp.image.read(tmp_path / "t.exr"), jp.image.read(tmp_path / "rest.exr")
    assert np.abs(a - b).max() > 0.05


@pytest.mark.parametrize("argv,message", [
    (["--frames", "0:1:0.5", "-o", "{tmp}/x.png"], "needs one frame-number pattern"),
    (["--frames", "0:1:0", "-o", "{tmp}/x_%d.png"], "STEP must be > 0"),
    (["--time", "1", "--frames", "0:1:0.5", "-o", "{tmp}/x_%d.png"], "exclude each other"),
    (["--time", "1", "--animation", "nope", "-o", "{tmp}/x.png"], "names no animation of the file"),
    (["--time", "nan", "-o", "{tmp}/x.png"], "expected a finite number"),
])
def test_misuse_is_one_line_and_writes_nothing(asset, tmp_path, capsys, argv, message):
    argv = ["render", str(asset), *[a.format(tmp=tmp_path) for a in argv], *CAM]
    try:
        code = main(argv)
    except SystemExit as e:  # (argparse's own errors)
        code = e.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) <= 2
    assert list(tmp_path.iterdir()) == []


def test_time_applies_to_gltf_only(tmp_path, capsys):
    assert main(["render", "--time", "1", "-o", str(tmp_path / "d.png"), "--width", "8", "--height", "8"]) == 2
    assert "apply to glTF assets" in capsys.readouterr().err


def test_motion_vectors_of_a_rigid_motion(asset):
    """The motion AOV against an independent oracle: the fixture's tetrahedron moves rigidly with its
    node, so a surface point P at t is W(t + dt) W(t)^-1 P at t + dt (W the node's closed-form world
    matrix, `tests/gltf_animated.py`); both points projected by the camera, whose projection is
    first checked to put each pixel's surface point at that pixel's centre."""
    from jaxpbr.rendering.aovs import _project, aovs

    path = asset
    (path.parent / "again").mkdir(exist_ok=True)
    _, closed = trs_animation(path.parent / "again")  # (the closed forms)
    t, dt = 1.1, 0.02
    kw = dict(camera_position=(3, 2, 6), camera_target=(0, 0.5, 1), width=40, height=30)
    now, later = jp.load_gltf(path, time=t, **kw), jp.load_gltf(path, time=t + dt, **kw)
    v = aovs(now, ["motion", "position", "mask"], next_scene=later)
    hit = v["mask"] > 0
    assert hit.sum() > 20
    P = v["position"][hit].astype(np.float64)
    ij = np.argwhere(hit)
    np.testing.assert_allclose(_project(now.camera, P), ij[:, ::-1] + 0.5, atol=2e-3)  # (the projection)
    W0, W1 = closed.world_matrices(t, 0)[1], closed.world_matrices(t + dt, 0)[1]
    M = W1 @ np.linalg.inv(W0)
    P1 = P @ M[:3, :3].T + M[:3, 3]
    want = _project(later.camera, P1) - _project(now.camera, P)
    assert np.abs(want).max() > 0.2  # (it moves by a fraction of a pixel or more)
    np.testing.assert_allclose(v["motion"][hit], want, atol=2e-3)
    assert (v["motion"][~hit] == 0).all()
    # a static scene under a static camera: exactly 0
    assert (aovs(now, ["motion"], next_scene=now)["motion"] == 0).all()


def test_motion_aov_in_the_exr(asset, tmp_path):
    out = tmp_path / "m.png"
    assert main(["render", str(asset), "--time", "1.0", "--motion-dt", "0.05", "--aov", "motion", "-o", str(out), *CAM]) == 0
    img, meta = jp.image.read_with_metadata(tmp_path / "m.exr", channels=("motion.X", "motion.Y"))
    assert img.shape == (30, 40, 2) and np.abs(img).max() > 0.1
    assert "motion vectors to t + 0.05 s" in str(meta.get("jaxpbr:scene"))
