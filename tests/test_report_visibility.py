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
