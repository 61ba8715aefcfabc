"""`jaxpbr report precompute` and `jaxpbr bench ibl`: the pieces on tiny inputs (fast), the commands
end to end (slow)."""

import numpy as np
import pytest

from jaxpbr.cli import main
from jaxpbr.cli import report_precompute as report
from jaxpbr.cli._common import have_matplotlib
from jaxpbr.ibl import envs


def test_report_rows_table_and_plot(tmp_path):
    env = envs.sky_with_sun_cubemap(16, supersample=2)
    rows = report.lut_rows(sizes=(8,), smiths=("correlated",), log=lambda m: None)
    rows += report.irradiance_rows(env, "sky", size=4, source_sizes=(8,), log=lambda m: None)
    rows += report.prefilter_rows(env, "sky", samples=(16,), exact_texels=(0, 64), texels_per_level=16, log=lambda m: None)
    assert [r["what"] for r in rows] == ["lut", "irradiance", "irradiance", "prefilter", "prefilter"]
    for r in rows:
        assert r["seconds"] > 0 and r["compile_s"] >= 0 and 0 <= r["mean"] <= r["max"] and np.isfinite(r["max"])
    assert rows[0]["max"] < 1e-4  # the converged LUT, every texel
    # the sun: exact texels must beat plain sampling on the worst texel at equal samples
    assert rows[4]["max"] < rows[3]["max"]
    md = report.markdown(rows)
    assert md.count("\n") == len(rows) + 2 and "| prefilter | sky | FIS + exact sun | 16 |" in md
    if not have_matplotlib():  # optional [report] extra: the table is written, the plot is not
        assert report.plot(rows, tmp_path / "p.png") is False and not (tmp_path / "p.png").exists()
        return
    assert report.plot(rows, tmp_path / "p.png")
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_report_and_bench_commands(tmp_path, capsys):
    assert main(["report", "precompute", "--quick", "--face-size", "16", "--out", str(tmp_path / "rep")]) == 0
    assert (tmp_path / "rep.md").exists()
    assert main(["bench", "ibl", "--face-size", "32", "--baseline-samples", "512"]) == 0
    out = capsys.readouterr().out
    assert "prefilter 32^2" in out and "BRDF LUT 256^2" in out and "irradiance 32^2" in out
