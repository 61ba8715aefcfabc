"""`run_batch`: the driver of a batch run and the in-process engine.

The driver takes the output folder's lock (one run at a time), skips the jobs whose records show
them complete, orders the rest by group (jobs sharing a scene, an image size, options and an
environment run one after another, so each program compiles once and each environment is baked
once), runs them on an engine and writes the summary. The in-process engine (the default) runs
jobs in this process with a `Worker`, overlapping the host work of one render job (the copy to
the host, encoding and writing the files, the record) with the device work of the next. The Ray
engine (`ray_engine`) runs the same `Worker` in actors.

A job that fails (a broken asset, a memory refusal) is marked failed with its cause and the run
goes on; an interrupt (SIGINT / SIGTERM, raised as an exception by the command line) stops it
after the job being written is complete or rolled back, with the summary written.
"""

from __future__ import annotations

import concurrent.futures as cf
import time
from pathlib import Path

from .._version import __version__
from ..errors import InputError
from .store import OutputFolder
from .work import Worker, failure

__all__ = ["ENGINES", "order_jobs", "run_batch"]

ENGINES = ("local", "ray")


def order_jobs(jobs) -> list:
    """Jobs grouped by `job.group` (groups in order of first appearance, file order within)."""
    groups: dict = {}
    for j in jobs:
        groups.setdefault(j.group, []).append(j)
    return [j for g in groups.values() for j in g]


def run_batch(jobs, out, *, engine: str = "local", address: str | None = None, workers: int | None = None,
              retries: int = 2, chunk: int = 4, progress=None, worker_setup=None, jobs_file: str | None = None) -> dict:
    """Run validated jobs (`load_jobs`) into the folder `out` -> the summary (also written to
    `out/batch-summary.json`).

    engine: "local" (in this process) or "ray" (`ray_engine.run_ray`: actors on a local cluster,
        or the cluster at `address`; `workers` actors, default one per node, holding its CPUs;
        `retries`: how often a job whose worker died is tried again; `chunk`: jobs sent together).
    progress: optional callable(done, total): once before any job (done = the jobs found
        complete), then after each job.
    worker_setup: optional picklable callable run once in each Ray worker before its first job
        (the command line passes the one that turns on its compilation and asset caches).
    Summary: {"engine", "jobs": [{"name", "row", "kind", "status": done | skipped | failed |
    not run, "seconds", "outputs": {file: checksum}, "attempts", "error"}], "counts", ...}.
    """
    if engine not in ENGINES:
        raise InputError(f"engine {engine!r} is not one of {', '.join(ENGINES)}")
    if engine == "ray":  # before the output folder is made: a refused run writes nothing
        from .ray_engine import import_ray

        import_ray()
    jobs = list(jobs)
    folder = OutputFolder(out)
    t_start = time.perf_counter()
    with folder:
        results: dict[str, dict] = {}
        todo = []
        for j in jobs:
            rec = folder.completed(j)
            if rec is not None:
                results[j.name] = {"status": "skipped", "record": rec}
            else:
                todo.append(j)
        done_count = [len(jobs) - len(todo)]
        total = len(jobs)

        def report(name, result):
            results[name] = result
            done_count[0] += 1
            if progress is not None:
                progress(done_count[0], total)

        if progress is not None:
            progress(done_count[0], total)  # the starting point: jobs already complete
        try:
            if engine == "local":
                _run_local(order_jobs(todo), folder, report)
            else:
                from .ray_engine import run_ray

                run_ray(order_jobs(todo), folder, report, address=address, workers=workers, retries=retries,
                        chunk=chunk, worker_setup=worker_setup)
        finally:
            summary = _summary(jobs, results, engine=engine, seconds=time.perf_counter() - t_start, jobs_file=jobs_file)
            folder.write_summary(summary)
    return summary


def _run_local(jobs, folder: OutputFolder, report) -> None:
    worker = Worker(folder)
    # One writer thread: the host side of job k runs while the device works on job k + 1.
    with cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="jaxpbr-batch-write") as pool:
        pending: tuple | None = None  # (job, future)

        def settle(p):
            job, fut = p
            try:
                report(job.name, {"status": "done", "record": fut.result(), "attempts": 1})
            except Exception as e:  # noqa: BLE001 - a failed job is reported, the run goes on
                report(job.name, failure(e, 1))

        try:
            for job in jobs:
                t0 = time.perf_counter()
                try:
                    if job.kind == "bake":
                        if pending is not None:
                            settle(pending)
                            pending = None
                        report(job.name, {"status": "done", "record": worker.run(job), "attempts": 1})
                        continue
                    computed = worker.compute(job)
                except Exception as e:  # noqa: BLE001
                    report(job.name, failure(e, 1))
                    continue
                if pending is not None:
                    settle(pending)
                pending = (job, pool.submit(worker.write, job, computed, t0=t0))
        finally:
            # Interrupted or not, the job being written finishes (its files and record whole).
            if pending is not None:
                job, fut = pending
                try:
                    settle(pending)
                except BaseException:
                    fut.cancel()
                    raise


def _summary(jobs, results: dict, *, engine: str, seconds: float, jobs_file) -> dict:
    rows = []
    counts = {"done": 0, "skipped": 0, "failed": 0, "not run": 0}
    for j in jobs:
        r = results.get(j.name, {"status": "not run"})
        rec = r.get("record") or {}
        row = {"name": j.name, "row": j.row, "kind": j.kind, "status": r["status"]}
        if rec:
            row |= {"seconds": rec.get("seconds"), "outputs": rec.get("outputs", {}), "worker": rec.get("worker")}
        if "attempts" in r:
            row["attempts"] = r["attempts"]
        if "error" in r:
            row["error"] = r["error"]
        if "traceback" in r:
            row["traceback"] = r["traceback"]
        counts[r["status"]] += 1
        rows.append(row)
    return {
        "jaxpbr": __version__,
        "engine": engine,
        "jobs_file": None if jobs_file is None else str(Path(jobs_file).resolve()),
        "wall_seconds": round(seconds, 3),
        "counts": counts,
        "jobs": rows,
    }
