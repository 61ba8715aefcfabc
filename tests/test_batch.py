"""Batch jobs (jaxpbr.batch, `jaxpbr batch`): job-file validation, records and resume, the run lock,
signals, and the Ray engine (bit-identical outputs, a worker killed in the middle)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.batch import (
    JobFileError,
    OutputFolder,
    RunLocked,
    load_jobs,
    parse_jobs,
    run_batch,
)
from jaxpbr.batch.store import sha256_file
from jaxpbr.cli import main

# A scene factory module written next to each job file: a small scene that compiles fast, and a
# factory that kills its worker process the first time it runs (a marker file remembers it).
FACTORY = '''
import os
from pathlib import Path
import jaxpbr as jp

def ball(roughness=0.5, metallic=0.0):
    return jp.Scene(
        camera=jp.Camera(position=(0.0, 0.0, 3.0), width=24, height=16),
        objects=[jp.Sphere(material=jp.Material((0.8, 0.3, 0.2), metallic, roughness))],
        lights=[jp.PointLight(position=(2.0, 2.0, 3.0), intensity=10.0)],
    )

def crash_once(marker, roughness=0.5):
    m = Path(marker)
    if not m.exists():
        m.write_text(str(os.getpid()))
        os._exit(1)  # the worker process dies in the middle of its chunk
    return ball(roughness)

def always_die():
    os._exit(1)
'''


def _rows(n=4, **extra):
    return [{"name": f"img/{k}", "scene": {"factory": "scenes_mod:ball", "args": {"roughness": round(0.05 + 0.9 * k / max(n - 1, 1), 4)}},
             "camera": {"position": [0.3 * k, 0.0, 3.0]}, **extra} for k in range(n)]


def _job_file(folder: Path, rows) -> Path:
    mod = folder / "scenes_mod.py"
    if not mod.exists() or mod.read_text() != FACTORY:  # rewriting it would change the jobs' keys
        mod.write_text(FACTORY)
    p = folder / "jobs.jsonl"
    p.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    return p


def _checksums(out: Path) -> dict:
    return {str(p.relative_to(out)): sha256_file(p) for p in sorted(out.rglob("*"))
            if p.is_file() and ".jaxpbr-batch" not in p.parts and p.name != "batch-summary.json"
            and not p.name.endswith(".json")}


# -- validation ------------------------------------------------------------------------------

BAD_ROWS = [
    ("not json", "not JSON"),
    ("[1, 2]", "expected a JSON object"),
    ('{"width": 8}', "name: missing"),
    ('{"name": "../up"}', "name: expected a relative output name"),
    ('{"name": "a", "kind": "paint"}', "kind: 'paint' is not a job kind"),
    ('{"name": "a", "widht": 8}', "did you mean 'width'"),
    ('{"name": "a", "width": 0}', "width: expected an integer"),
    ('{"name": "a", "supersample": 99}', "supersample: expected an integer"),
    ('{"name": "a", "scene": "missing.toml"}', "scene: file 'missing.toml' does not exist"),
    ('{"name": "a", "scene": "x.obj"}', "scene: 'x.obj' is not one of"),
    ('{"name": "a", "scene": {"factory": "no colon"}}', "scene.factory: expected 'module:function'"),
    ('{"name": "a", "camera": {"position": [0, 0]}}', "camera.position: expected three numbers"),
    ('{"name": "a", "camera": {"fov_y": 200}}', "camera.fov_y: expected degrees in (0, 180)"),
    ('{"name": "a", "camera": {"ymag": 0}}', "camera.ymag: expected a positive number"),
    ('{"name": "a", "camera": {"position": [0, 0, 1], "target": [0, 0, 1]}}', "position and target are the same point"),
    ('{"name": "a", "environment": "procedural:moon"}', "unknown procedural environment"),
    ('{"name": "a", "environment": "sky.png"}', "environment: 'sky.png' is not one of"),
    ('{"name": "a", "environment_intensity": -1}', "environment_intensity: expected a finite number >= 0"),
    ('{"name": "a", "material": {"roughnes": 0.2}}', "material.roughnes: not a Material field"),
    ('{"name": "a", "material": {"metallic": 2}}', "material: Material.metallic"),
    ('{"name": "a", "options": {"model": "phong"}}', "options:"),
    ('{"name": "a", "options": {"modle": "gltf"}}', "options.modle: not a RenderOptions keyword"),
    ('{"name": "a", "output": {"formats": ["jpg"]}}', "output.formats"),
    ('{"name": "a", "output": {"aovs": ["depth"]}}', "add 'exr' to output.formats"),
    ('{"name": "a", "output": {"formats": ["exr"], "aovs": ["colour"]}}', "output.aovs: expected a list from"),
    ('{"name": "a", "output": {"tonemap": "filmic"}}', "output.tonemap: 'filmic' is not one of"),
    ('{"name": "a", "output": {"formats": ["exr"], "aovs": ["motion"]}}', "'motion' needs the next frame's scene"),
    ('{"name": "a", "time": 1.0}', "time/animation: apply to glTF assets"),
    ('{"name": "a", "time": "soon"}', "time: expected a finite number"),
    ('{"name": "a", "output": {"bits": 12}}', "output.bits: expected 8 or 16"),
    ('{"kind": "bake", "name": "b"}', "environment: missing"),
    ('{"kind": "bake", "name": "b", "environment": "procedural:sky", "container": "zip"}', "container: 'zip' is not one of"),
    ('{"kind": "bake", "name": "b", "environment": "procedural:sky", "face_size": "big"}', "face_size: expected a non-negative integer"),
    ('{"kind": "bake", "name": "b", "environment": "procedural:sky", "colour": 1}', "colour: unknown field of a bake job"),
]


@pytest.mark.parametrize("line, expected", BAD_ROWS, ids=[b[1][:40] for b in BAD_ROWS])
def test_every_bad_row_kind_is_named(tmp_path, line, expected):
    with pytest.raises(JobFileError) as e:
        parse_jobs('{"name": "ok"}\n' + line + "\n", base_dir=tmp_path, source="jobs.jsonl")
    assert len(e.value.problems) == 1, e.value.problems
    assert e.value.problems[0].startswith("jobs.jsonl:2: ") and expected in e.value.problems[0], e.value.problems


def test_duplicate_and_nested_names(tmp_path):
    text = '{"name": "a"}\n{"name": "a"}\n{"kind": "bake", "name": "ibl", "environment": "procedural:sky"}\n{"name": "ibl/x"}\n'
    with pytest.raises(JobFileError) as e:
        parse_jobs(text, base_dir=tmp_path, source="j")
    assert [p.split(": ")[0] for p in e.value.problems] == ["j:2", "j:4"]
    assert "already the name of row 1" in e.value.problems[0] and "inside 'ibl'" in e.value.problems[1]


def test_cli_lists_every_bad_row_and_writes_nothing(tmp_path, capsys):
    jobs = tmp_path / "jobs.jsonl"
    jobs.write_text('{"name": "a", "width": -3}\n\n{"name": "b", "options": {"dtype": "float16"}}\n{"name": "c"}\n')
    out = tmp_path / "out"
    assert main(["batch", str(jobs), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("jaxpbr: error: jobs.jsonl:1: width") and err[1].startswith("jaxpbr: error: jobs.jsonl:3: options")
    assert "2 problem(s)" in err[-1] and not out.exists()


def test_empty_file_and_missing_file(tmp_path):
    with pytest.raises(JobFileError, match="no jobs"):
        parse_jobs("\n\n", base_dir=tmp_path)
    with pytest.raises(jp.errors.InputError, match="does not exist"):
        load_jobs(tmp_path / "none.jsonl")


# -- the in-process engine -------------------------------------------------------------------


def test_local_run_outputs_records_and_resume(tmp_path):
    rows = _rows(3) + [{"name": "lit", "scene": {"factory": "scenes_mod:ball"}, "width": 20, "height": 12,
                        "environment": "procedural:sky", "environment_rotation": 30,
                        "output": {"formats": ["png", "exr"], "aovs": ["depth", "mask"]}}]
    jobs = load_jobs(_job_file(tmp_path, rows))
    out = tmp_path / "out"
    s = run_batch(jobs, out)
    assert s["counts"] == {"done": 4, "skipped": 0, "failed": 0, "not run": 0}
    # The images are the library's render of the same scene (tone-mapped as the command line does).
    img = jp.image.read(out / "lit.exr")
    import importlib
    import sys as _sys

    _sys.path.insert(0, str(tmp_path))
    try:
        mod = importlib.import_module("scenes_mod")
    finally:
        _sys.path.remove(str(tmp_path))
    scene = mod.ball()
    scene = scene.replace(camera=scene.camera.replace(width=20, height=12),
                          environment=jp.rendering.demo.demo_environment(rotation=np.radians(30)))  # procedural:sky: the demo's baked sky
    np.testing.assert_array_equal(img[..., :3], np.asarray(jp.render(scene)))
    rec = OutputFolder(out).completed(jobs[3])
    assert set(rec["outputs"]) == {"lit.png", "lit.exr"}
    assert rec["outputs"]["lit.exr"] == sha256_file(out / "lit.exr")
    summary = json.loads((out / "batch-summary.json").read_text())
    assert [r["status"] for r in summary["jobs"]] == ["done"] * 4
    before = _checksums(out)

    # Rerun: everything complete is skipped, nothing rewritten.
    mtimes = {p: p.stat().st_mtime_ns for p in out.rglob("*.png")}
    s = run_batch(jobs, out)
    assert s["counts"]["skipped"] == 4 and s["counts"]["done"] == 0
    assert mtimes == {p: p.stat().st_mtime_ns for p in out.rglob("*.png")}

    # A damaged output and a changed row are redone; the others are not.
    (out / "img/0.png").write_bytes(b"damaged")
    rows[1]["camera"]["position"] = [0.1, 0.1, 3.0]
    jobs2 = load_jobs(_job_file(tmp_path, rows))
    s = run_batch(jobs2, out)
    status = {r["name"]: r["status"] for r in s["jobs"]}
    assert status == {"img/0": "done", "img/1": "done", "img/2": "skipped", "lit": "skipped"}
    after = _checksums(out)
    assert after["img/0.png"] == before["img/0.png"]  # redone to the same bytes
    assert after["img/1.png"] != before["img/1.png"]  # a different camera

    # Editing the factory module (its file is part of the key) redoes the jobs built by it.
    mod = tmp_path / "scenes_mod.py"
    st = mod.stat()
    os.utime(mod, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    s = run_batch(load_jobs(tmp_path / "jobs.jsonl"), out)
    assert s["counts"]["done"] == 4 and s["counts"]["skipped"] == 0


def test_failed_job_is_reported_and_the_run_goes_on(tmp_path, capsys):
    rows = _rows(2)
    rows.insert(1, {"name": "broken", "scene": {"factory": "scenes_mod:nothing_here"}})
    out = tmp_path / "out"
    code = main(["batch", str(_job_file(tmp_path, rows)), "--out", str(out), "--quiet"])
    assert code == 1
    s = json.loads((out / "batch-summary.json").read_text())
    assert [r["status"] for r in s["jobs"]] == ["done", "failed", "done"]
    assert "nothing_here" in s["jobs"][1]["error"] and "broken" in capsys.readouterr().err
    assert not list(out.glob("broken*"))


def test_second_run_on_the_same_folder_is_refused(tmp_path, capsys):
    jobs = load_jobs(_job_file(tmp_path, _rows(1)))
    out = tmp_path / "out"
    with OutputFolder(out):  # another run holds the folder
        with pytest.raises(RunLocked, match="another jaxpbr batch run is writing"):
            run_batch(jobs, out)
        assert main(["batch", str(tmp_path / "jobs.jsonl"), "--out", str(out)]) == 2
        assert "another jaxpbr batch run" in capsys.readouterr().err
    assert not list(out.glob("img/*"))
    assert run_batch(jobs, out)["counts"]["done"] == 1  # free again


def test_leftovers_of_a_killed_writer_are_removed(tmp_path):
    out = tmp_path / "out"
    (out / "img").mkdir(parents=True)
    junk = [out / "img" / ".0.tmp-0123abcd.png", out / ".x.png.jaxpbr-old-89abcdef"]
    for j in junk:
        j.write_bytes(b"half")
    keep = out / ".hidden_user_file"
    keep.write_text("mine")
    run_batch(load_jobs(_job_file(tmp_path, _rows(1))), out)
    assert not any(j.exists() for j in junk) and keep.exists()


def test_bake_job_writes_a_set_read_baked_reads(tmp_path):
    rows = [{"kind": "bake", "name": "ibl/sky", "environment": "procedural:sky", "face_size": 16,
             "irradiance_size": 8, "lut_size": 32, "sheen": False, "measure_error": False}]
    out = tmp_path / "out"
    s = run_batch(load_jobs(_job_file(tmp_path, rows)), out)
    assert s["counts"]["done"] == 1
    files = s["jobs"][0]["outputs"]
    assert "ibl/sky/ibl.json" in files and "ibl/sky/prefiltered.ktx2" in files
    env = jp.read_baked(out / "ibl" / "sky")
    assert env.prefiltered.face_size == 16


@pytest.mark.slow
def test_sigterm_stops_cleanly_and_the_rerun_completes(tmp_path):
    """SIGTERM in the middle: exit 143, no partial file, every record true; the rerun does the rest
    and the result equals an uninterrupted run."""
    rows = _rows(24)
    jobs_path = _job_file(tmp_path, rows)
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "jaxpbr", "batch", str(jobs_path), "--out", str(out), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    records = out / ".jaxpbr-batch" / "records"
    deadline = time.time() + 240
    while time.time() < deadline and (not records.is_dir() or len(list(records.iterdir())) < 3):
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    folder = OutputFolder(out)
    jobs = load_jobs(jobs_path)
    done = [j for j in jobs if folder.completed(j)]
    assert 3 <= len(done) < len(jobs)
    assert not [p for p in out.rglob(".*") if p.is_file() and ".jaxpbr-batch" not in p.parts]
    summary = json.loads((out / "batch-summary.json").read_text())
    assert summary["counts"]["not run"] + summary["counts"]["done"] == len(jobs)
    s = run_batch(jobs, out)
    assert s["counts"]["skipped"] == len(done) and s["counts"]["done"] == len(jobs) - len(done)
    clean = tmp_path / "clean"
    run_batch(jobs, clean)
    assert _checksums(out) == _checksums(clean)


# -- the Ray engine --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def ray_cluster():
    # Skips only the Ray tests when ray is missing (a module-level importorskip here would skip the whole file).
    ray = pytest.importorskip("ray", reason="the Ray engine needs ray (pip install 'jaxpbr[ray]')")
    with warnings.catch_warnings():  # Ray starts its processes with fork + exec
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_ray_outputs_equal_the_in_process_engine_bit_for_bit(tmp_path, ray_cluster):
    rows = _rows(4) + [{"name": "exr", "scene": {"factory": "scenes_mod:ball"}, "output": {"formats": ["exr"], "aovs": ["normal"]}}]
    jobs = load_jobs(_job_file(tmp_path, rows))
    s_local = run_batch(jobs, tmp_path / "local")
    s_ray = run_batch(jobs, tmp_path / "ray", engine="ray", workers=2, chunk=2)
    assert s_ray["counts"]["done"] == len(jobs) == s_local["counts"]["done"]
    assert _checksums(tmp_path / "ray") == _checksums(tmp_path / "local")
    assert len(_checksums(tmp_path / "ray")) == 5
    assert {r["worker"] for r in s_ray["jobs"]} != {r["worker"] for r in s_local["jobs"]}  # ran elsewhere


@pytest.mark.slow
def test_ray_worker_killed_in_the_middle_every_job_once(tmp_path, ray_cluster):
    marker = tmp_path / "died"
    rows = _rows(6)
    rows.insert(3, {"name": "img/crash", "scene": {"factory": "scenes_mod:crash_once", "args": {"marker": str(marker)}}})
    jobs = load_jobs(_job_file(tmp_path, rows))
    s = run_batch(jobs, tmp_path / "ray", engine="ray", workers=2, chunk=4)
    assert marker.exists()  # a worker did die
    assert s["counts"] == {"done": 7, "skipped": 0, "failed": 0, "not run": 0}
    attempts = {r["name"]: r["attempts"] for r in s["jobs"]}
    assert attempts["img/crash"] == 2
    # Done exactly once: one record per job, and each job's record was written by one worker.
    folder = OutputFolder(tmp_path / "ray")
    assert all(folder.completed(j) for j in jobs)
    assert len(list(folder.records.iterdir())) == len(jobs)
    # The outputs equal an in-process run of the jobs (the crash factory renders the ball).
    marker.write_text("already")
    run_batch(jobs, tmp_path / "local")
    assert _checksums(tmp_path / "ray") == _checksums(tmp_path / "local")


@pytest.mark.slow
def test_ray_job_whose_worker_always_dies_is_failed_with_the_cause(tmp_path, ray_cluster):
    rows = _rows(2) + [{"name": "doomed", "scene": {"factory": "scenes_mod:always_die"}}]
    jobs = load_jobs(_job_file(tmp_path, rows))
    s = run_batch(jobs, tmp_path / "ray", engine="ray", workers=2, retries=1, chunk=1)
    status = {r["name"]: (r["status"], r.get("attempts")) for r in s["jobs"]}
    assert status == {"img/0": ("done", 1), "img/1": ("done", 1), "doomed": ("failed", 2)}
    assert "worker died on each of 2 attempts" in s["jobs"][2]["error"]


def test_glTF_rows_at_times(tmp_path):
    """Rows with `time` (and `animation`) render the asset posed there: each output is the render of
    `jaxpbr.load_gltf(path, time=t)` (same camera rules), and the times give different images."""
    from gltf_animated import trs_animation

    path, _ = trs_animation(tmp_path)
    cam = {"position": [3, 2, 6], "target": [0, 0.5, 1]}
    rows = [{"name": f"t{k}", "scene": path.name, "width": 24, "height": 16, "camera": cam, "time": t,
             "animation": "trs", "environment": "procedural:sky", "output": {"formats": ["exr"]}}
            for k, t in enumerate((0.5, 1.25))]
    out = tmp_path / "out"
    s = run_batch(load_jobs(_job_file(tmp_path, rows)), out)
    assert s["counts"]["done"] == 2
    imgs = []
    for k, t in enumerate((0.5, 1.25)):
        img = jp.image.read(out / f"t{k}.exr")[..., :3]
        scene = jp.load_gltf(path, time=t, animation="trs", width=24, height=16, camera_position=(3, 2, 6),
                             camera_target=(0, 0.5, 1), environment="procedural:sky")
        np.testing.assert_allclose(img, np.asarray(jp.render(scene)), rtol=1e-5, atol=1e-6)
        imgs.append(img)
    assert np.abs(imgs[0] - imgs[1]).max() > 0.05
