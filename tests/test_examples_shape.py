"""Smoke test of examples/fit_shape.py at tiny settings: a sphere's vertices moved by the gradient of
images of a hidden lumpy shape. Checks that can fail: the shape gets closer to the hidden one
(Chamfer distance and silhouette IoU), and the control without the outlines' gradients gets less
far (the silhouettes are what moves a sphere into a lump)."""

import importlib.util
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "fit_shape.py"

pytest.importorskip("optax")


def _example():
    spec = importlib.util.spec_from_file_location("fit_shape", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


ARGS = ["--views", "3", "--size", "32", "--steps", "30", "--print-every", "29"]


@pytest.mark.slow  # ~1 min on a 2-core CPU, most of it compiling the step
def test_fit_shape_moves_the_sphere_towards_the_hidden_shape(tmp_path):
    res = _example().main(ARGS + ["--out", str(tmp_path)])
    first, last = res["history"][0], res["history"][-1]
    assert last["chamfer"] < 0.6 * first["chamfer"], res["history"]
    assert last["iou"] > first["iou"] + 0.05, res["history"]
    assert (tmp_path / "fit_shape.png").is_file()


@pytest.mark.slow
def test_fit_shape_needs_the_outlines(tmp_path):
    """The control: the same fit without the outlines' gradients (antialias="none") gets less far."""
    ex = _example()
    last = ex.main(ARGS + ["--out", str(tmp_path / "edges")])["history"][-1]
    control = ex.main(ARGS + ["--out", str(tmp_path / "interior"), "--interior-only"])["history"][-1]
    assert last["chamfer"] < 0.8 * control["chamfer"] and last["iou"] > control["iou"], (last, control)
