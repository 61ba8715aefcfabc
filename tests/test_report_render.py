"""`jaxpbr report render` (jaxpbr.cli.report_render): the split-sum error report against the reference."""

import argparse
import json

import numpy as np
import pytest

from jaxpbr.cli._common import have_matplotlib
from jaxpbr.cli.report_render import (
    add_command,
    markdown,
    render_report,
    sphere_gbuffer,
)


def _parser():
    parser = argparse.ArgumentParser(prog="jaxpbr")
    sub = parser.add_subparsers(dest="command")
    rp = sub.add_parser("report")
    rsub = rp.add_subparsers(dest="report")
    add_command(rsub)
    return parser


def test_sphere_gbuffer():
    mask, n, v, p = sphere_gbuffer(16)
    assert mask.shape == (16, 16) and n.shape == (mask.sum(), 3)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0)
    assert np.all(n[:, 2] > 0) and np.all(v == [0, 0, 1]) and np.all(p == n)
    assert mask[0].sum() < mask[8].sum()  # a disc


def test_cli_render_report_tiny(tmp_path, capsys):
    args = _parser().parse_args(
        ["report", "render", "--env", "procedural:sky", "--output-dir", str(tmp_path), "--face-size", "16", "--pixels", "16", "--roughness", "0.5", "--metallic", "0,1", "--quiet"]
    )
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "| 0.5 | 0 |" in out and "| 0.5 | 1 |" in out
    md = (tmp_path / "render_report.md").read_text()
    assert "split-sum error" in md and md.count("\n| 0.5 |") == 4  # the error table and the by-part table
    data = json.loads((tmp_path / "render_report.json").read_text())
    assert len(data["materials"]) == 2
    for row in data["materials"]:
        for k in ("mean_rel_error", "max_pixel_rel_error", "ibl_mean_rel_error", "split_sum_s", "reference_s"):
            assert np.isfinite(row[k]) and row[k] >= 0
        assert row["max_pixel_rel_error"] >= row["mean_rel_error"]
    assert data["precompute_s"] > 0 and data["config"]["pixels"] == 16
    assert (tmp_path / "render_report.png").exists() == have_matplotlib()


def test_extension_row_quick(tmp_path, capsys):
    """One extension row (clear coat at coat roughness 0.5) at low resolution through the CLI: a
    finite error below a generous bound (measured 1.5 % mean, 9.8 % max pixel at 8^2 px on a 16^2
    map), the table's extension section and the JSON rows; unknown names are refused."""
    args = _parser().parse_args(
        ["report", "render", "--output-dir", str(tmp_path), "--face-size", "16", "--pixels", "8", "--roughness", "0.5", "--metallic", "1",
         "--extensions", "clearcoat", "--extension-roughness", "0.5", "--quiet"]
    )
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "## glTF material extensions" in out and "| clearcoat | clearcoat_roughness 0.5 | 0 |" in out
    data = json.loads((tmp_path / "render_report.json").read_text())
    (row,) = data["extensions"]
    assert row["extension"] == "clearcoat" and row["roughness"] == 0.5
    for k in ("mean_rel_error", "max_pixel_rel_error", "ibl_mean_rel_error", "ibl_max_pixel_rel_error"):
        assert np.isfinite(row[k]) and 0 <= row[k]
    assert row["mean_rel_error"] < 0.05 and row["ibl_mean_rel_error"] < 0.08 and row["max_pixel_rel_error"] < 0.3
    assert data["config"]["extension_rows"]["clearcoat"]["roughness_field"] == "clearcoat_roughness"
    # default: no extension rows; --no-extensions after --extensions turns them off
    p = _parser()
    assert p.parse_args(["report", "render"]).extensions is None
    assert p.parse_args(["report", "render", "--extensions"]).extensions == "all"
    assert p.parse_args(["report", "render", "--extensions", "thin_transmission,ior"]).extensions == ["thin transmission", "ior"]
    assert p.parse_args(["report", "render", "--extensions", "--no-extensions"]).extensions is None
    with pytest.raises(SystemExit):
        p.parse_args(["report", "render", "--extensions", "glitter"])
    with pytest.raises(ValueError, match="unknown extension"):
        render_report(pixels=4, face_size=16, roughness=(0.5,), metallic=(1.0,), extensions=("glitter",), log=lambda m: None)
    with pytest.raises(ValueError, match="extension roughness"):
        render_report(pixels=4, face_size=16, roughness=(0.5,), metallic=(1.0,), extensions=("ior",), extension_roughness=(0.05,), log=lambda m: None)


def test_sheen_row_unavailable_without_its_modules(monkeypatch):
    """Without the sheen modules the sheen row says so instead of failing (the markdown too)."""
    import builtins

    real = builtins.__import__

    def fake(name, *a, **k):
        if name.endswith("sheen_prefilter"):
            raise ImportError("no module named sheen_prefilter")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake)
    res = render_report(pixels=4, face_size=16, roughness=(0.5,), metallic=(1.0,), extensions=("sheen",), log=lambda m: None)
    (row,) = res["extensions"]
    assert row["extension"] == "sheen" and "unavailable" in row["unavailable"]
    assert "| sheen | - | - | sheen assets unavailable" in markdown(res)


def test_bad_inputs(tmp_path):
    p = _parser()
    with pytest.raises(SystemExit):
        p.parse_args(["report", "render", "--roughness", "1.5"])
    args = p.parse_args(["report", "render", "--output-dir", str(tmp_path / "missing")])
    with pytest.raises(ValueError, match="does not exist"):
        args.func(args)
    with pytest.raises(ValueError, match="resolves roughness"):
        render_report(roughness=(0.05,), metallic=(1.0,), pixels=4, face_size=16, log=lambda m: None)


def test_markdown_from_numbers():
    res = dict(
        config=dict(environment="e", environment_face_size=16, pixels=4, pixels_on_sphere=12, base_color=[1, 1, 1], lights="l", split_sum="s", reference="r", timing="t", device="cpu", roughness=[0.5], metallic=[1.0]),
        precompute_s=1.0,
        materials=[dict(roughness=0.5, metallic=1.0, mean_rel_error=0.01, max_pixel_rel_error=0.1, ibl_mean_rel_error=0.02, ibl_max_pixel_rel_error=0.2, ibl_share_of_radiance=0.5, split_sum_s=1e-3, reference_s=2.0)],
    )
    md = markdown(res)
    assert "| 0.5 | 1 | 1.00 % | 10.0 % | 2.00 % | 20.0 % | 50 % | 1.00 | 2.00 |" in md


@pytest.mark.slow
def test_default_report_runs(tmp_path):
    """The full default report (12 materials, 48^2 px, face 64): about 1.5 minutes on 2 CPU cores."""
    res = render_report(log=lambda m: None)
    assert len(res["materials"]) == 12
    rough_dielectric = [r for r in res["materials"] if r["metallic"] == 0.0 and r["roughness"] >= 0.5]
    assert all(r["mean_rel_error"] < 0.15 for r in rough_dielectric)


@pytest.mark.slow
def test_report_with_the_sun_extracted_meets_the_issue_targets():
    """The sun-extraction targets, reproduced from `report render` (sky + 3000-radiance sun, face 64,
    48^2 px): with the sun split out, metals <= 10 % and dielectrics <= 3 % mean relative error
    for r >= 0.3; the split sum alone is far off on the r = 0.3 and 0.5 metals (29 % and 28 %
    measured: the check can fail). At r = 1 the split sum alone meets the metal target too since
    the prefiltered map is read at the lobe's dominant direction and bright texels are convolved
    exactly (7.8 % measured); there the check is that the extraction still lowers the
    error severalfold (0.7 % measured).
    (r <= 0.15 is left out: there the sun's mirror image is sub-pixel and one sample per pixel
    decides the number for the reference and the render alike; see docs/ibl.md.)"""
    kw = dict(roughness=(0.3, 0.5, 1.0), log=lambda m: None)
    on = render_report(**kw)
    off = render_report(extract_lights=False, **kw)
    for a, b in zip(on["materials"], off["materials"]):
        target = 0.10 if a["metallic"] == 1.0 else 0.03
        assert a["mean_rel_error"] <= target, a
        if a["metallic"] == 1.0 and a["roughness"] < 1.0:
            assert b["mean_rel_error"] > 2 * target, b
        elif a["metallic"] == 1.0:
            assert b["mean_rel_error"] > 4 * a["mean_rel_error"], (a, b)
    assert len(on["config"]["extracted_lights"]) == 1


def test_split_sum_dielectrics_and_rough_metals_against_the_reference():
    """The IBL term of white-ish spheres under the procedural sky (sun split out, face 32, 16^2 px)
    against the float64 reference: dielectrics within 1 % (mean and bias; the diffuse lobe without
    the (1 - F) factor was +2.7 %), the diffuse part's bias within 0.5 %, the rough metal's IBL
    within 3 % (looked up at R it was 4.1 % at r = 1 on the 64^2 sky). The energy-model columns
    are present and finite for every material."""
    res = render_report(pixels=16, face_size=32, roughness=(0.5, 1.0), metallic=(0.0, 1.0), log=lambda m: None)
    for row in res["materials"]:
        assert np.isfinite(row["ibl_single_scatter_furnace_normalised_error"]) and np.isfinite(row["ibl_multi_scatter_furnace_normalised_error"])
        if row["metallic"] == 0.0:
            assert row["ibl_mean_rel_error"] <= 0.01 and abs(row["ibl_bias"]) <= 0.01, row
            assert abs(row["ibl_diffuse_bias"]) <= 0.005, row
        elif row["roughness"] == 1.0:
            assert row["ibl_mean_rel_error"] <= 0.03, row
    assert "furnace-normalised" in markdown(res)
