"""Job files (`jaxpbr batch`) and TOML scene files as untrusted input (issue 42): only regular files
are read (a FIFO or a device refused without waiting on it), never more than a cap, rows and tables
nested at most 64 deep (checked without recursion), no key given twice, job names kept inside the
output folder and out of the run's own state; `--engine ray` refused before anything is written
when Ray is missing, and a run whose Ray node dies ends with one line instead of waiting forever.

No test here renders except the slow Ray one: the command line is run in process (`jaxpbr.cli.main`,
output captured at the file descriptors) and every refusal comes before any work."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from jaxpbr.batch import (
    JobFileError,
    OutputFolder,
    load_jobs,
    parse_jobs,
    ray_engine,
    run_batch,
)
from jaxpbr.batch import jobs as jobs_module
from jaxpbr.cli import main
from jaxpbr.errors import InputError
from jaxpbr.rendering import scene_file
from jaxpbr.rendering.scene_file import load_scene, loads_scene

#: The caps the brief and the docs name (written out here, not read from the code under test).
JOB_FILE_CAP = 64 << 20
SCENE_FILE_CAP = 8 << 20
DEPTH_CAP = 64
NAME_CAP = 200

SPHERE = '[[objects]]\ntype = "sphere"\n'


def _run(capfd, args) -> tuple[int, list[str]]:
    """`jaxpbr ARGS` in this process -> (status, the non-empty lines of stderr)."""
    capfd.readouterr()
    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:  # argparse's refusals
        code = exc.code
    err = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
    return code, err


def _one_line(err: list[str]) -> str:
    assert len(err) == 1 and err[0].startswith("jaxpbr: error: "), err
    assert "Traceback" not in err[0]
    return err[0]


def _jobs(tmp_path: Path, lines, name="jobs.jsonl") -> Path:
    p = tmp_path / name
    p.write_text("".join((ln if isinstance(ln, str) else json.dumps(ln)) + "\n" for ln in lines))
    return p


@pytest.fixture
def fifo(tmp_path):
    """A FIFO with no writer. Should the code under test open it blocking, a helper opens it for
    writing after 20 s and closes it (the reader then sees end of file), so that the test fails
    instead of hanging."""
    made = []
    stop = threading.Event()

    def make(name):
        p = tmp_path / name
        os.mkfifo(p)
        made.append(p)
        return p

    def unblock():
        if stop.wait(20):
            return
        for p in made:
            try:
                os.close(os.open(p, os.O_WRONLY | os.O_NONBLOCK))  # ENXIO unless a reader waits
            except OSError:
                pass

    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this system")
    t = threading.Thread(target=unblock, daemon=True)
    t.start()
    yield make
    stop.set()
    t.join()


# -- 1. only regular files, never more than a cap -------------------------------------------------


def test_a_fifo_as_the_job_file_is_refused_at_once(tmp_path, fifo, capfd):
    path = fifo("jobs.jsonl")
    out = tmp_path / "out"
    t0 = time.monotonic()
    code, err = _run(capfd, ["batch", path, "--out", out])
    assert time.monotonic() - t0 < 10
    line = _one_line(err)
    assert code == 2 and str(path) in line and "not a regular file" in line and "FIFO" in line, line
    assert not out.exists()


def test_a_device_as_the_job_file_is_refused(tmp_path, capfd):
    if not os.path.exists("/dev/null"):
        pytest.skip("no /dev/null")
    out = tmp_path / "out"
    code, err = _run(capfd, ["batch", "/dev/null", "--out", out])  # reads as empty: "no jobs" before
    line = _one_line(err)
    assert code == 2 and "'/dev/null'" in line and "character device, not a regular file" in line, line
    assert not out.exists()


def test_a_folder_as_the_job_file_is_refused(tmp_path, capfd):
    code, err = _run(capfd, ["batch", tmp_path, "--out", tmp_path / "out"])
    line = _one_line(err)
    assert code == 2 and "is a folder, not a regular file" in line, line


def test_a_job_file_over_the_cap_is_refused_unread(tmp_path, capfd):
    path = tmp_path / "jobs.jsonl"
    with open(path, "wb") as f:  # sparse: nothing to read, only its declared size
        f.truncate(JOB_FILE_CAP + 1)
    code, err = _run(capfd, ["batch", path, "--out", tmp_path / "out"])
    line = _one_line(err)
    assert code == 2 and str(path) in line and "larger than 64 MiB" in line and "split it" in line, line
    assert not (tmp_path / "out").exists()


def test_the_cap_holds_for_a_file_that_declares_no_size(tmp_path):
    """The read is bounded, whatever the file's size says: a /proc file declares 0 bytes."""
    proc = Path("/proc/self/maps")
    if not proc.exists() or proc.stat().st_size != 0:
        pytest.skip("no /proc file that declares no size")
    assert len(proc.read_bytes()) > 100
    with pytest.raises(InputError, match=r"job file '/proc/self/maps' is larger than 0 MiB \(100 bytes\)"):
        scene_file.read_regular_file(proc, limit=100, what="job file", missing="", other="", smaller="split it")


def test_a_job_file_at_the_cap_is_read(tmp_path, monkeypatch):
    row = json.dumps({"name": "a"}) + "\n"
    path = tmp_path / "jobs.jsonl"
    path.write_text(row + " " * 50)
    monkeypatch.setattr(jobs_module, "MAX_JOB_FILE_BYTES", len(row) + 50)
    assert [j.name for j in load_jobs(path)] == ["a"]
    path.write_text(row + " " * 51)
    with pytest.raises(InputError, match="larger than"):
        load_jobs(path)


def test_a_fifo_or_device_as_the_scene_file_is_refused(tmp_path, fifo, capfd):
    path = fifo("scene.toml")
    t0 = time.monotonic()
    with pytest.raises(InputError) as e:
        load_scene(path)
    assert time.monotonic() - t0 < 10
    assert str(e.value) == f"scene file {str(path)!r} is a named pipe (FIFO), not a regular file; pass a .toml scene file"
    code, err = _run(capfd, ["render", path, "-o", tmp_path / "x.png"])
    assert code == 2 and "named pipe (FIFO), not a regular file" in _one_line(err)
    assert not (tmp_path / "x.png").exists()
    if os.path.exists("/dev/null"):
        with pytest.raises(InputError, match="character device, not a regular file"):
            load_scene("/dev/null")


def test_a_scene_file_over_the_cap_is_refused(tmp_path, capfd):
    path = tmp_path / "s.toml"
    path.write_text(SPHERE + "#" * (SCENE_FILE_CAP - len(SPHERE)))  # a valid scene of exactly the cap
    assert len(load_scene(path).scene.objects) == 1
    with open(path, "a") as f:
        f.write("#")
    with pytest.raises(InputError, match=r"^scene file '.*s\.toml' is larger than 8 MiB \(8388608 bytes\)"):
        load_scene(path)
    code, err = _run(capfd, ["render", path, "-o", tmp_path / "x.png"])
    assert code == 2 and "larger than 8 MiB" in _one_line(err)


def test_a_job_whose_scene_is_a_fifo_is_refused_at_validation(tmp_path, fifo):
    fifo("scene.toml")
    with pytest.raises(JobFileError) as e:
        parse_jobs('{"name": "a", "scene": "scene.toml"}\n', base_dir=tmp_path, source="jobs.jsonl")
    assert e.value.problems == [
        "jobs.jsonl:1: scene: file 'scene.toml' is not a regular file (paths are relative to the job file's folder)"
    ]


# -- nesting: refused with FILE:ROW before json.loads / tomllib recurse ------------------------------


def _factory_row(args_value, name="a") -> str:
    """A render row whose factory arguments may be any JSON: the row nests 3 levels around them."""
    return json.dumps({"name": name, "scene": {"factory": "mod:make", "args": {"x": args_value}}})


def _nested(levels: int):
    v: list = []
    for _ in range(levels - 1):
        v = [v]
    return v


def test_a_row_nested_deeper_than_the_cap_is_refused_naming_its_row(tmp_path, capfd):
    deep = "[" * 100_000 + "]" * 100_000
    path = _jobs(tmp_path, ['{"name": "ok"}', '{"name": "a", "scene": {"factory": "m:f", "args": {"x": ' + deep + "}}}"])
    out = tmp_path / "out"
    code, err = _run(capfd, ["batch", path, "--out", out])
    assert code == 2 and len(err) == 2, err
    assert err[0].startswith("jaxpbr: error: jobs.jsonl:2: ") and "nested more than 64 levels deep" in err[0], err
    assert "1 problem(s) in" in err[1] and not out.exists()


def test_the_nesting_cap_counts_brackets_outside_strings_only(tmp_path):
    (tmp_path / "mod.py").write_text("def f(**kw):\n    pass\n")  # the factory module the rows name
    # 3 levels of the row around the argument: 61 levels of lists make 64, 62 make 65.
    assert len(parse_jobs(_factory_row(_nested(DEPTH_CAP - 3)) + "\n", base_dir=tmp_path)) == 1
    with pytest.raises(JobFileError) as e:
        parse_jobs(_factory_row(_nested(DEPTH_CAP - 2)) + "\n", base_dir=tmp_path, source="j")
    assert e.value.problems[0].startswith("j:1: arrays and objects nested more than 64 levels deep")
    # Brackets inside strings (escaped quotes included) nest nothing.
    text = _factory_row('\\"[{' * 500 + '"' + "[" * 500) + "\n"
    assert len(parse_jobs(text, base_dir=tmp_path)) == 1


def test_an_unterminated_string_stops_the_scan_where_json_stops(tmp_path):
    with pytest.raises(JobFileError) as e:
        parse_jobs('{"name": "a", "x": "open' + "[" * 200 + "\n", base_dir=tmp_path, source="j")
    assert len(e.value.problems) == 1 and e.value.problems[0].startswith("j:1: not JSON"), e.value.problems


def test_a_huge_integer_is_a_row_problem_not_a_crash(tmp_path):
    with pytest.raises(JobFileError) as e:
        parse_jobs('{"name": "a", "width": 1' + "0" * 5000 + "}\n", base_dir=tmp_path, source="j")
    assert len(e.value.problems) == 1 and e.value.problems[0].startswith("j:1: not JSON that can be read")
    assert len(e.value.problems[0]) < 300


@pytest.mark.parametrize("text", [
    "a = " + "[" * 100_000 + "]" * 100_000,
    "a = " + "{b = " * 100_000 + "1" + "}" * 100_000,
    "a = " + "[" * 100_000,  # cut short: tomllib would recurse before it found the end
], ids=["arrays", "inline-tables", "unclosed"])
def test_a_scene_nested_deeper_than_the_cap_is_refused(tmp_path, capfd, text):
    path = tmp_path / "s.toml"
    path.write_text(SPHERE + text + "\n")
    with pytest.raises(InputError) as e:
        load_scene(path)
    assert str(e.value).startswith(f"{path}: tables and arrays nested more than 64 levels deep"), str(e.value)
    code, err = _run(capfd, ["render", path, "-o", tmp_path / "x.png"])
    assert code == 2 and "nested more than 64 levels deep" in _one_line(err)


def test_scene_nesting_by_headers_and_dotted_keys_is_capped():
    ok = "[" + ".".join(["t"] * (DEPTH_CAP - 1)) + "]\nx = 1\n"
    with pytest.raises(InputError, match="unknown table"):  # read (and refused for its table's name only)
        loads_scene(ok + SPHERE, name="s.toml")
    deep_header = "[" + ".".join(["t"] * (DEPTH_CAP + 1)) + "]\nx = 1\n"
    with pytest.raises(InputError, match=r"^s\.toml: a dotted key or table name of more than 64 parts"):
        loads_scene(deep_header + SPHERE, name="s.toml")
    # 3000 parts: tomllib checks every prefix of a dotted key (quadratic; 100,000 parts took all memory)
    dotted = ".".join(['"k"'] * 3000) + " = 1\n"
    t0 = time.monotonic()
    with pytest.raises(InputError, match=r"^s\.toml: a dotted key or table name of more than 64 parts"):
        loads_scene(dotted + SPHERE, name="s.toml")
    assert time.monotonic() - t0 < 2
    # Headers under the cap, a value nested under the cap: deeper than 64 together.
    both = "[" + ".".join(["t"] * 40) + "]\nx = " + "[" * 30 + "]" * 30 + "\n"
    with pytest.raises(InputError, match=r"^s\.toml: tables and arrays nested more than 64 levels deep"):
        loads_scene(SPHERE + both, name="s.toml")


def test_brackets_in_toml_strings_and_comments_nest_nothing():
    text = (
        SPHERE
        + 'radius = 1.0  # [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[ "\n'
        + "[materials.m]\nroughness = 0.5\n"
        + "# " + "{" * 100 + "\n"
        + "[[lights]]\ntype = 'point'  # '''[[[[[\nposition = [0, 1, 0]\n"
    )
    names = '"""' + "[" * 70 + '""""' + "\n"  # a multi-line string ending in a quote
    sf = loads_scene(text + "[scene]\nbackground = [0, 0, 0] # " + names, name="s.toml")
    assert len(sf.scene.objects) == 1 and len(sf.scene.lights) == 1 and "m" in sf.materials


def test_a_deep_scene_named_by_a_job_does_not_crash_validation(tmp_path):
    """A job's TOML scene is read at validation for its [render] table: a hostile one is left to
    the run, where loading it refuses it in one line (it ended validation with a RecursionError)."""
    (tmp_path / "deep.toml").write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    jobs = parse_jobs('{"name": "a", "scene": "deep.toml"}\n', base_dir=tmp_path)
    assert [j.name for j in jobs] == ["a"]
    with pytest.raises(InputError, match="nested more than 64 levels deep"):
        load_scene(jobs[0].scene)


# -- 2. a key given twice ---------------------------------------------------------------------------


@pytest.mark.parametrize("row, key", [
    ('{"name": "a", "width": 8, "width": 16}', "'width'"),
    ('{"name": "a", "name": "b"}', "'name'"),
    ('{"name": "a", "camera": {"fov_y": 30, "fov_y": 60}}', "'fov_y'"),
], ids=["top", "name", "nested"])
def test_a_key_given_twice_in_a_row_is_refused(tmp_path, capfd, row, key):
    path = _jobs(tmp_path, ['{"name": "ok"}', row])
    out = tmp_path / "out"
    code, err = _run(capfd, ["batch", path, "--out", out])
    assert code == 2 and len(err) == 2, err
    assert err[0].startswith(f"jaxpbr: error: jobs.jsonl:2: {key}: the key is given twice"), err
    assert not out.exists()


@pytest.mark.parametrize("text", [
    "[camera]\nwidth = 10\nwidth = 20\n",
    "[camera]\nwidth = 10\n[camera]\nheight = 10\n",
    "[[objects]]\ntype = 'sphere'\nmaterial = { roughness = 0.2, roughness = 0.3 }\n",
    "camera.width = 10\n[camera]\nheight = 10\n",
], ids=["key", "table", "inline", "dotted-then-table"])
def test_tomllib_refuses_a_key_or_table_given_twice(text):
    """tomllib already refuses duplicates (TOML 1.0 forbids them): this test keeps it so."""
    with pytest.raises(InputError, match=r"^s\.toml: invalid TOML: .*(twice|overwrite|Duplicate)"):
        loads_scene(text + SPHERE, name="s.toml")


# -- 3. job names stay inside the output folder and out of the run's state --------------------------


@pytest.mark.parametrize("name, expected", [
    (".jaxpbr-batch/records/x", "lies in '.jaxpbr-batch', the folder where the run keeps its lock and records"),
    (".jaxpbr-batch", "lies in '.jaxpbr-batch'"),
    (".JAXPBR-Batch/lock", "lies in '.jaxpbr-batch'"),  # the same folder on a case-insensitive system
    (".jaxpbr-batch-x/y", "lies in '.jaxpbr-batch'"),
    ("/etc/passwd", "expected a relative output name"),
    ("../outside", "expected a relative output name"),
    ("a/../../outside", "expected a relative output name"),
    ("a//b", "expected a relative output name"),
    (".a.tmp-0123abcd", "the form of the temporary files a run removes"),
    ("x" * 10_000, "10000 characters, more than the 200 a job name may have"),
    ("x" * (NAME_CAP + 1), "201 characters, more than the 200"),
], ids=["state", "state-itself", "state-case", "state-prefix", "absolute", "dotdot", "dotdot-inner", "empty-part",
        "leftover", "10000-chars", "201-chars"])
def test_bad_job_names_are_refused_at_validation(tmp_path, capfd, name, expected):
    path = _jobs(tmp_path, [{"name": "ok"}, {"name": name}])
    out = tmp_path / "out"
    code, err = _run(capfd, ["batch", path, "--out", out])
    assert code == 2 and len(err) == 2, err
    assert err[0].startswith("jaxpbr: error: jobs.jsonl:2: name: ") and expected in err[0], err
    assert len(err[0]) < 400  # a 10,000-character name is not printed whole
    assert not out.exists()


def test_the_summary_file_is_not_a_job_name(tmp_path):
    with pytest.raises(JobFileError) as e:
        parse_jobs('{"kind": "bake", "name": "batch-summary.json", "environment": "procedural:sky"}\n',
                   base_dir=tmp_path, source="j")
    assert e.value.problems == ["j:1: name: 'batch-summary.json' is the run's summary file; give another name"]


def test_names_up_to_the_cap_are_accepted(tmp_path):
    names = ["x" * NAME_CAP, "/".join(["d" * 60] * 3), "a.b/c-d_e", ".hidden", "sky.jaxpbr-batch"]
    jobs = parse_jobs("".join(json.dumps({"name": n}) + "\n" for n in names), base_dir=tmp_path)
    assert [j.name for j in jobs] == names


def test_a_name_part_over_the_file_name_limit_is_refused(tmp_path, monkeypatch):
    """Each part of a name, with what the engine adds to it (".png" and the name of the copy it keeps
    while it replaces a file), must stay within the 255 bytes of a file name."""
    monkeypatch.setattr(jobs_module, "MAX_NAME", 1000)
    ok, bad = "p" * 225, "p" * 226
    assert len(parse_jobs(json.dumps({"name": f"a/{ok}"}) + "\n", base_dir=tmp_path)) == 1
    with pytest.raises(JobFileError) as e:
        parse_jobs(json.dumps({"name": f"a/{bad}"}) + "\n", base_dir=tmp_path, source="j")
    assert e.value.problems[0].startswith("j:1: name: the part 'ppp") and "226 bytes, more than the 225" in e.value.problems[0]
    assert len(f".{ok}.png.jaxpbr-old-0123abcd") <= 255  # the longest name the engine makes of it (io.atomic)


# -- 4. --engine ray without Ray: refused before anything is written ------------------------------


def test_ray_engine_without_ray_writes_nothing(tmp_path, capfd, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    path = _jobs(tmp_path, [{"name": "a"}])
    out = tmp_path / "out"
    code, err = _run(capfd, ["batch", path, "--out", out, "--engine", "ray", "--quiet"])
    line = _one_line(err)
    assert code == 2 and "--engine ray needs Ray" in line and "pip install" in line, line
    assert not out.exists()
    with pytest.raises(InputError, match="needs Ray"):
        run_batch(load_jobs(path), out, engine="ray")
    assert not out.exists()


# -- 5. the Ray node dies: the run ends with one line (simulated Ray) --------------------------------


class _RayError(Exception):
    pass


class _ActorDiedError(_RayError):
    pass


class _WouldWaitForever(Exception):
    """The fake's `ray.wait` without a timeout and nothing that will ever finish: where real Ray
    blocks the driver for good."""


class _Ref:
    def __init__(self, result=None, error=None, ready=True):
        self.result, self.error, self.ready = result, error, ready


class FakeRay:
    """The slice of the `ray` module `ray_engine.run_ray` uses, with a cluster whose one node
    (`node`) dies on cue: `chunks` is the fate of each chunk sent, in order ("ok": its jobs done;
    "die": the actor dies with the node; "hang": no result, ever), `dies_after_polls`: the node is
    dead once `ray.nodes()` has been asked that many times (None: when a chunk dies),
    `nodes_block`: an Event `ray.nodes()` waits on after its first call (a cluster that stops answering),
    `node_dies_with_actor`: False for a worker that dies alone."""

    def __init__(self, chunks, *, dies_after_polls=None, nodes_block=None, node_dies_with_actor=True):
        self.chunks = list(chunks)
        self.node_dies_with_actor = node_dies_with_actor
        self.alive = True
        self.polls = 0
        self.dies_after_polls = dies_after_polls
        self.nodes_block = nodes_block
        self.exceptions = type("exceptions", (), {"RayError": _RayError, "ActorDiedError": _ActorDiedError})
        self.sent: list = []

    # cluster
    def is_initialized(self):
        return True

    def cluster_resources(self):
        return {"CPU": 2.0}

    def nodes(self):
        self.polls += 1
        if self.nodes_block is not None and self.polls > 1:  # the first call counts the nodes at the start
            self.nodes_block.wait()
        if self.dies_after_polls is not None and self.polls > self.dies_after_polls:
            self.alive = False
        return [{"NodeID": "node-1", "Alive": self.alive, "Resources": {"CPU": 2.0}}]

    def get_runtime_context(self):
        return type("ctx", (), {"get_node_id": staticmethod(lambda: "node-1")})()

    # actors and results
    def remote(self, **_):
        fake = self

        class Actor:
            def __init__(self):
                self.run_chunk = self

            def remote(self, jobs, attempts):
                fate = fake.chunks.pop(0) if fake.chunks else "hang"
                fake.sent.append([j.name for j in jobs])
                if fate == "ok":
                    rec = {"worker": "fake:1", "outputs": {}, "seconds": 0.0}
                    return _Ref(result=[(j.name, {"status": "done", "record": rec, "attempts": attempts[j.name]}) for j in jobs])
                if fate == "die":
                    fake.alive = not fake.node_dies_with_actor
                    return _Ref(error=_ActorDiedError("The actor died unexpectedly before finishing this task."))
                return _Ref(ready=False)

        return lambda cls: type("RemoteClass", (), {"remote": staticmethod(lambda *a: Actor())})

    def wait(self, refs, *, num_returns=1, timeout=None):
        ready = [r for r in refs if r.ready][:num_returns]
        if not ready and timeout is None:
            raise _WouldWaitForever("ray.wait without a timeout, and nothing will finish")
        if not ready:
            time.sleep(min(timeout, 0.01))
        return ready, [r for r in refs if r not in ready]

    def get(self, ref):
        if ref.error is not None:
            raise ref.error
        return ref.result

    def kill(self, actor):
        pass

    def shutdown(self):
        pass


@pytest.fixture
def fast_polls(monkeypatch):
    monkeypatch.setattr(ray_engine, "POLL_S", 0.01, raising=False)
    monkeypatch.setattr(ray_engine, "ASK_S", 0.5, raising=False)


def test_a_worker_lost_with_its_node_ends_the_run_in_one_line(tmp_path, capfd, monkeypatch, fast_polls):
    """The chunk's actor dies with the node (its raylet killed): before, the driver sent the
    chunk to a fresh actor that no node could start, and waited for it forever."""
    fake = FakeRay(["ok", "die"])
    monkeypatch.setitem(sys.modules, "ray", fake)
    path = _jobs(tmp_path, [{"name": f"img/{k}"} for k in range(4)])
    out = tmp_path / "out"
    t0 = time.monotonic()
    code, err = _run(capfd, ["batch", path, "--out", out, "--engine", "ray", "--chunk", "1", "--quiet"])
    assert time.monotonic() - t0 < 30
    line = _one_line([ln for ln in err if ln.startswith("jaxpbr: error")])
    assert code == 2 and "the Ray cluster can no longer run the jobs" in line and "is dead" in line, err
    assert "run the same job file again" in line
    assert fake.sent == [["img/0"], ["img/1"]]  # nothing sent after the node died
    summary = json.loads((out / "batch-summary.json").read_text())
    assert [r["status"] for r in summary["jobs"]] == ["done", "not run", "not run", "not run"]
    OutputFolder(out).acquire()  # the lock was released


def test_a_node_that_dies_while_the_driver_waits_is_noticed(tmp_path, monkeypatch, fast_polls):
    fake = FakeRay(["hang"], dies_after_polls=3)
    monkeypatch.setitem(sys.modules, "ray", fake)
    jobs = load_jobs(_jobs(tmp_path, [{"name": "a"}, {"name": "b"}]))
    with pytest.raises(ray_engine.ClusterLost, match=r"the node this run is attached to \(node-1\) is dead"):
        run_batch(jobs, tmp_path / "out", engine="ray")
    assert fake.polls == 4  # the count of nodes at the start, two polls while it lived, the one that found it dead


def test_a_cluster_that_does_not_answer_ends_the_run(tmp_path, monkeypatch, fast_polls):
    block = threading.Event()
    fake = FakeRay(["hang"], nodes_block=block)
    monkeypatch.setitem(sys.modules, "ray", fake)
    jobs = load_jobs(_jobs(tmp_path, [{"name": "a"}]))
    try:
        t0 = time.monotonic()
        with pytest.raises(ray_engine.ClusterLost, match=r"it did not answer within 0\.5 s"):
            run_batch(jobs, tmp_path / "out", engine="ray")
        assert time.monotonic() - t0 < 10
    finally:
        block.set()


def test_a_worker_that_dies_alone_is_still_replaced(tmp_path, monkeypatch, fast_polls):
    """The check does not take a lone dead worker for a lost cluster: its chunk goes to a fresh actor."""
    fake = FakeRay(["die", "ok"], node_dies_with_actor=False)
    monkeypatch.setitem(sys.modules, "ray", fake)
    jobs = load_jobs(_jobs(tmp_path, [{"name": "a"}]))
    summary = run_batch(jobs, tmp_path / "out", engine="ray")
    assert fake.sent == [["a"], ["a"]]
    assert summary["jobs"][0]["status"] == "done" and summary["jobs"][0]["attempts"] == 2


# -- 5. the real thing: the raylet of a local Ray run killed ------------------------------------------

NAP = '''
import time
from pathlib import Path
import jaxpbr as jp

def ball(marker, nap, roughness=0.5):
    if nap and Path(marker).exists():
        time.sleep(60)  # in flight while the node dies
    return jp.Scene(
        camera=jp.Camera(position=(0.0, 0.0, 3.0), width=16, height=12),
        objects=[jp.Sphere(material=jp.Material((0.8, 0.3, 0.2), 0.0, roughness))],
        lights=[jp.PointLight(position=(2.0, 2.0, 3.0), intensity=10.0)],
    )
'''


def _descendants(pid: int) -> list[tuple[int, str]]:
    """(pid, name) of the processes below `pid`, from /proc."""
    parent = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                st = Path(f"/proc/{d}/stat").read_text()
            except OSError:
                continue
            parent[int(d)] = (int(st[st.rindex(")") + 2 :].split()[1]), st[st.index("(") + 1 : st.rindex(")")])
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        for c, (pp, name) in parent.items():
            if pp == p:
                out.append((c, name))
                todo.append(c)
    return out


@pytest.mark.slow
def test_killing_the_raylet_ends_the_run_within_a_minute(tmp_path):
    pytest.importorskip("ray", reason="the Ray engine needs ray (pip install 'jaxpbr[ray]')")
    if not Path("/proc/self/stat").exists():
        pytest.skip("finds the raylet through /proc")
    (tmp_path / "nap.py").write_text(NAP)
    marker = tmp_path / "slow"
    marker.write_text("")  # the jobs after the first two nap while it is there
    rows = [{"name": f"img/{k}", "scene": {"factory": "nap:ball", "args": {"marker": str(marker), "nap": k >= 2,
                                                                          "roughness": 0.1 * (k + 1)}}}
            for k in range(6)]
    path = _jobs(tmp_path, rows)
    out = tmp_path / "out"
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    proc = subprocess.Popen([sys.executable, "-m", "jaxpbr", "batch", str(path), "--out", str(out), "--engine", "ray",
                             "--chunk", "1", "--workers", "1", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
    try:
        records = out / ".jaxpbr-batch" / "records"
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and (not records.is_dir() or len(list(records.iterdir())) < 2):
            time.sleep(0.05)
            assert proc.poll() is None, proc.communicate()
        time.sleep(1.0)  # the third job is in flight, napping
        raylets = [p for p, name in _descendants(proc.pid) if name == "raylet"]
        assert len(raylets) == 1, _descendants(proc.pid)
        os.kill(raylets[0], signal.SIGKILL)
        t_kill = time.monotonic()
        _, err = proc.communicate(timeout=90)
        took = time.monotonic() - t_kill
    finally:
        if proc.poll() is None:  # the run and the Ray processes it started
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 2 and took < 60, (proc.returncode, took, err[-3000:])
    lines = [ln for ln in err.splitlines() if ln.startswith("jaxpbr:")]
    assert len(lines) == 1 and lines[0].startswith("jaxpbr: error: the Ray cluster can no longer run the jobs"), err[-3000:]
    assert "Traceback" not in err
    # The jobs finished before the node died stay done; a rerun does only the rest.
    jobs = load_jobs(path)
    folder = OutputFolder(out)
    done = [j.name for j in jobs if folder.completed(j)]
    assert 2 <= len(done) < len(jobs), done
    marker.unlink()
    summary = run_batch(jobs, out)
    assert summary["counts"]["skipped"] == len(done) and summary["counts"]["done"] == len(jobs) - len(done)


def test_a_factory_is_imported_from_the_job_files_folder_only(tmp_path, capfd):
    """A factory naming an installed module (subprocess:run) would let a job file run any command:
    refused at validation, before anything runs or is written."""
    import jaxpbr.cli as cli

    marker = tmp_path / "pwned"
    jobs = tmp_path / "jobs.jsonl"
    for target in ("subprocess:run", "os:system", "jaxpbr.cli:main"):
        jobs.write_text(json.dumps({"name": "x", "scene": {"factory": target, "args": {"args": ["touch", str(marker)]}}}) + "\n")
        out = tmp_path / "out"
        code = cli.main(["batch", str(jobs), "--out", str(out), "--quiet"])
        err = capfd.readouterr().err
        assert code == 2 and "is not a Python file in the job file's folder" in err, err
        assert not marker.exists() and not out.exists()
    # the control: a module beside the job file is a factory like before
    (tmp_path / "myscenes.py").write_text(
        "import jaxpbr as jp\n"
        "def one(size=8):\n"
        "    cam = jp.Camera(position=(0, 0, 3), target=(0, 0, 0), width=size, height=size)\n"
        "    return jp.Scene(camera=cam, objects=[jp.Sphere(center=(0, 0, 0), radius=1.0, material=jp.Material())])\n")
    jobs.write_text(json.dumps({"name": "ok", "scene": {"factory": "myscenes:one", "args": {}}}) + "\n")
    from jaxpbr.batch.jobs import load_jobs

    assert len(load_jobs(jobs)) == 1
