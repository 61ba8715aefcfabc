"""`jaxpbr report render builtin:concave --visibility`: the rungs of the IBL's visibility against the
ground truth on the concave scene (small sizes; the table in docs/visibility.md is the command at
full size). Checks that can fail: the unshadowed rungs are biased bright on the occluded pixels, the
traced rungs remove most of that bias, the error falls with K, the outputs are written."""

from __future__ import annotations

import json

import pytest

from jaxpbr.cli import main


@pytest.mark.slow  # ~40 s: six rungs compiled and the ground truth
def test_visibility_report_on_the_concave_scene(tmp_path, capsys):
    code = main(["report", "render", "builtin:concave", "--visibility", "--samples", "1,16", "--spp", "48",
                 "--width", "48", "--height", "36", "--output-dir", str(tmp_path), "--quiet"])
    assert code == 0
    out = capsys.readouterr().out
    assert "| ratio K=16 |" in out
    res = json.loads((tmp_path / "visibility_report.json").read_text())
    rows = {r["label"]: r for r in res["rungs"]}
    assert res["truth"]["open_pixels"] > 100 and res["truth"]["occluded_pixels"] > 100
    none, ratio = rows["none"]["occluded"], rows["ratio K=16"]["occluded"]
    assert none["bias"] > 0.15  # the sky the walls hide is counted
    assert abs(ratio["bias"]) < 0.5 * none["bias"]
    assert rows["ratio K=16"]["all"]["mean"] < rows["ratio K=1"]["all"]["mean"]
    assert rows["ao K=16"]["occluded"]["mean"] < none["mean"]
    assert (tmp_path / "visibility_report.png").stat().st_size > 0 and (tmp_path / "visibility_report.md").is_file()
    # the image's L1 error (luminance-weighted) falls too; nothing is left out on flat-shaded walls
    assert rows["ratio K=16"]["occluded"]["l1"] < 0.6 * none["l1"]
    assert res["truth"]["back_facing_pixels"] == 0


def test_pixels_whose_shading_normal_faces_away_are_left_out_and_counted(monkeypatch):
    """Where a normal map bends the shading normal away from the viewer the truth's BRDF is 0 and the
    split sum's is not: those pixels are counted apart, not measured."""
    import numpy as np

    from jaxpbr.cli import report_visibility as rv
    from jaxpbr.rendering.demo import concave_scene

    scene = concave_scene(16, 12)
    real = rv.gbuffer

    def bent(sc):  # the G-buffer with the left half's normals turned to face away from the viewer
        g = real(sc)
        n = np.asarray(g.normal).copy()
        n[:, :8] = np.asarray(g.view)[:, :8] * -1.0
        return g.replace(normal=n)

    monkeypatch.setattr(rv, "gbuffer", bent)
    res = rv.visibility_report(scene, samples=(1,), spp=4, repeats=1, log=lambda *_: None)
    hit = rv.reference_render(scene, spp=2).hit
    assert res["truth"]["back_facing_pixels"] == int(hit[:, :8].sum()) > 0
    assert res["truth"]["surface_pixels"] == int(hit[:, 8:].sum())
    assert "left out" in rv.visibility_markdown(res)
