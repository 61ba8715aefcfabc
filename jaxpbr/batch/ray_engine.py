"""The Ray engine: the jobs of a batch run on actors of a Ray cluster (`pip install 'jaxpbr[ray]'`).

One actor per node (or `workers` actors sharing the cluster's CPUs), each holding a `Worker` (its compiled programs, loaded
scenes and baked environments stay with it across chunks). The driver sends chunks of up to
`chunk` jobs of one group (to an actor that ran the group before, where one is idle) and
receives only their records: workers write the output files and
the completion records themselves, atomically, into the output folder, which every worker must
see at the same path (one machine, or a shared file system on a cluster).

A worker that dies (killed, out of memory, its node lost) fails its chunk: the driver reads the
records of the chunk's jobs from the folder, counts those finished before the death as done, and
sends the rest to a fresh actor, up to `retries` more attempts per job; then the job is marked
failed with the cause. A job with a record is never sent again, so each job is done once.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import warnings

from ..errors import InputError
from .store import OutputFolder
from .work import Worker, failure

__all__ = ["run_ray"]


class BatchActor:
    """What runs inside a Ray actor: a `Worker` on the output folder."""

    def __init__(self, out: str, setup=None):
        if setup is not None:
            setup()
        self.worker = Worker(OutputFolder(out))

    def pid(self) -> int:
        return os.getpid()

    def run_chunk(self, jobs, attempts: dict) -> list:
        out = []
        for job in jobs:
            try:
                rec = self.worker.run(job, attempt=attempts[job.name])
                out.append((job.name, {"status": "done", "record": rec, "attempts": attempts[job.name]}))
            except Exception as e:  # noqa: BLE001 - reported per job, the chunk goes on
                out.append((job.name, failure(e, attempts[job.name])))
        return out


def _chunks(jobs, size: int) -> collections.deque:
    out: collections.deque = collections.deque()
    for j in jobs:
        if out and len(out[-1]) < size and out[-1][-1].group == j.group:
            out[-1].append(j)
        else:
            out.append([j])
    return out


def _take(pending: collections.deque, group) -> list:
    """The next chunk for an actor: the first pending chunk of the group it ran last, else the next."""
    for k, js in enumerate(pending):
        if js[0].group == group:
            del pending[k]
            return js
    return pending.popleft()


def run_ray(jobs, folder: OutputFolder, report, *, address=None, workers=None, retries: int = 2, chunk: int = 4,
            worker_setup=None) -> dict:
    """Run ordered jobs on Ray actors; `report(name, result)` for each. -> {"workers", "pids",
    "replaced"} (how many actors ran and how many were started in place of dead ones)."""
    try:
        import ray
    except ImportError:
        raise InputError("--engine ray needs Ray: pip install 'jaxpbr[ray]' (or pip install ray)") from None
    if not jobs:
        return {"workers": 0, "pids": [], "replaced": 0}
    started_here = not ray.is_initialized()
    if started_here:
        kw = {"include_dashboard": False, "logging_level": logging.WARNING, "log_to_driver": False}
        with warnings.catch_warnings():
            # Ray starts its processes with fork + exec (no Python runs in the forked child).
            warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
            if address is None:
                ray.init(num_cpus=os.cpu_count() or 1, **kw)
            else:
                ray.init(address=address, **kw)
    actors: list = []
    try:
        # XLA spreads one render over every core of its machine: by default one actor per node,
        # holding the node's CPUs (two actors on a 2-core machine ran at half the rate of one).
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        nodes = max(1, sum(1 for nd in ray.nodes() if nd.get("Alive")))
        n = workers or nodes
        remote = ray.remote(num_cpus=max(1, cpus // n), max_restarts=0)(BatchActor)
        pending = _chunks(jobs, max(1, chunk))
        attempts = collections.Counter()
        actors = [remote.remote(str(folder.root), worker_setup) for _ in range(min(n, len(pending)))]
        pids = set()
        idle = list(actors)
        inflight: dict = {}
        last: dict = {}  # actor -> the group of its last chunk (its scene and environment are loaded)
        replaced = 0
        while pending or inflight:
            while idle and pending:
                actor = idle.pop()
                js = _take(pending, last.get(actor))
                last[actor] = js[0].group
                for j in js:
                    attempts[j.name] += 1
                fut = actor.run_chunk.remote(js, {j.name: attempts[j.name] for j in js})
                inflight[fut] = (actor, js)
            ready, _ = ray.wait(list(inflight), num_returns=1)
            fut = ready[0]
            actor, js = inflight.pop(fut)
            try:
                results = ray.get(fut)
            except ray.exceptions.RayError as e:
                cause = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                retry = []
                for j in js:
                    rec = folder.completed(j)
                    if rec is not None:  # finished (files and record) before the worker died
                        report(j.name, {"status": "done", "record": rec, "attempts": attempts[j.name]})
                    elif attempts[j.name] > retries:
                        report(j.name, {"status": "failed", "attempts": attempts[j.name],
                                        "error": f"its worker died on each of {attempts[j.name]} attempts; last: {type(e).__name__}: {cause}"})
                    else:
                        retry.append(j)
                if retry:
                    pending.appendleft(retry)
                _kill(ray, actor)
                actors.remove(actor)
                if pending:
                    fresh = remote.remote(str(folder.root), worker_setup)
                    actors.append(fresh)
                    idle.append(fresh)
                    replaced += 1
                continue
            for name, result in results:
                if result["status"] == "done":
                    pids.add(result["record"]["worker"])
                report(name, result)
            idle.append(actor)
        return {"workers": len(pids), "pids": sorted(pids), "replaced": replaced}
    finally:
        for a in actors:
            _kill(ray, a)
        if started_here:
            ray.shutdown()


def _kill(ray, actor) -> None:
    """Stop an actor; one that is already gone raises, which is what was wanted."""
    with contextlib.suppress(Exception):
        ray.kill(actor)
