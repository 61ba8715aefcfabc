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
    (["--time", "nan", "-o", "{tmp}/x.png"], "not a finite number"),
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
