"""`jaxpbr bench batch` on a tiny configuration: the structure of its result, finite positive
figures, the engine's outputs; the panorama and job rows it builds (no timings are asserted)."""

import json
import math

import numpy as np

from jaxpbr.batch import load_jobs
from jaxpbr.cli import bench_batch as bb
from jaxpbr.cli import build_parser
from jaxpbr.io import image


def test_write_panorama_is_a_valid_environment(tmp_path):
    p = bb.write_panorama(tmp_path / "pano.hdr", 64)
    img = image.read(p)
    assert img.shape[:2] == (32, 64)
    assert np.all(np.isfinite(img)) and img.min() >= 0.0 and img.max() > 10.0  # the sun
    assert bb.write_panorama(tmp_path / "again.hdr", 64).read_bytes() == p.read_bytes()


def test_job_rows_load_as_render_jobs(tmp_path):
    bb.write_panorama(tmp_path / "pano.hdr", 16)
    rows = bb.job_rows(5, 8, ["procedural:sky", "pano.hdr"])
    (tmp_path / "jobs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    jobs = load_jobs(tmp_path / "jobs.jsonl")
    assert [j.name for j in jobs] == [f"job{k:03d}" for k in range(5)]
    assert {j.environment for j in jobs} == {"procedural:sky", str((tmp_path / "pano.hdr").resolve())}
    assert len({j.camera["position"] for j in jobs}) == 5


def test_bench_batch_tiny(tmp_path):
    res = bb.bench_batch(2, 8, rounds=1, panorama_width=16, workdir=tmp_path)
    assert list(res.seconds) == ["(a) loop", "(b) loop, reused", "(c) engine local"]
    for table in (res.seconds, res.first):
        assert all(math.isfinite(v) and v > 0 for v in table.values())
    assert all(math.isfinite(res.rate(k)) and res.rate(k) > 0 for k in res.seconds)
    assert res.png_bytes > 0
    assert set(res.profile) >= {"render (device work, incl. tone map)", "copy to host", "PNG encode + write + read-back",
                                "record (sha256 + JSON write)"}
    assert all(math.isfinite(v) and v >= 0 for v in res.profile.values())
    text = res.report()
    assert "(c) engine local" in text and "vs (b)" in text
    json.dumps(res.to_json())
    # Each engine pass wrote every job into its own folder, with a summary.
    summaries = sorted(tmp_path.glob("out*/batch-summary.json"))
    assert len(summaries) == 2  # the warm pass and one timed pass
    for s in summaries:
        assert json.loads(s.read_text())["counts"]["done"] == 2


def test_registered_on_the_command_line():
    args = build_parser().parse_args(["bench", "batch", "--jobs", "3", "--size", "8", "--ray"])
    assert (args.jobs, args.size, args.ray, args.func) == (3, 8, True, bb.cmd_bench_batch)
