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

A cluster that can no longer run jobs (the node of this driver lost, its raylet killed; no node
alive; the cluster not answering) ends the run with `ClusterLost`: the driver waits for results
`POLL_S` seconds at a time and between waits, and after each dead worker, asks the cluster for its
nodes (Ray marks a node whose raylet died dead after about 15 s of missed health checks). The
jobs recorded so far stay done: running the same job file again resumes.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import threading
import warnings

from ..errors import InputError
from .store import OutputFolder
from .work import Worker, failure

__all__ = ["ClusterLost", "import_ray", "run_ray"]

#: Seconds the driver waits for a result before it asks the cluster whether its nodes are alive
#: (a question to the cluster's control store, cheap; results that arrive end the wait at once).
POLL_S = 5.0
#: Seconds the cluster may take to answer that question before it is taken for gone.
ASK_S = 20.0


class ClusterLost(ConnectionError):
    """The Ray cluster can no longer run the jobs (this driver's node lost, no node alive, or the
    cluster not answering): the run ends, its finished jobs recorded."""


def import_ray():
    """The `ray` module, or InputError saying how to install it (checked before a run makes its
    output folder)."""
    try:
        import ray
    except ImportError:
        raise InputError("--engine ray needs Ray: pip install 'jaxpbr[ray]' (or pip install ray)") from None
    return ray


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
    ray = import_ray()
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
        node_id = _node_id(ray)
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
            try:
                ready, _ = ray.wait(list(inflight), num_returns=1, timeout=POLL_S)
            except ray.exceptions.RayError as e:  # the driver's connection to the cluster failed
                raise ClusterLost(_lost(f"waiting for results failed ({_first_line(e)})")) from None
            if not ready:  # nothing finished yet: is the cluster still there to finish it?
                problem = _cluster_problem(ray, node_id)
                if problem:
                    raise ClusterLost(_lost(problem))
                continue
            fut = ready[0]
            actor, js = inflight.pop(fut)
            try:
                results = ray.get(fut)
            except ray.exceptions.RayError as e:
                cause = _first_line(e)
                lost = _cluster_problem(ray, node_id)  # a worker lost with its node, or alone?
                if lost:
                    for j in js:
                        rec = folder.completed(j)
                        if rec is not None:  # finished (files and record) before the node went
                            report(j.name, {"status": "done", "record": rec, "attempts": attempts[j.name]})
                    raise ClusterLost(_lost(lost)) from None
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


def _first_line(e: BaseException) -> str:
    return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__


def _lost(problem: str) -> str:
    return (f"the Ray cluster can no longer run the jobs: {problem}; the jobs finished so far are recorded: "
            f"restart Ray (or its node) and run the same job file again to do the rest")


def _node_id(ray) -> str | None:
    """The id of the Ray node this driver is attached to (None where Ray does not say)."""
    try:
        return ray.get_runtime_context().get_node_id()
    except Exception:  # noqa: BLE001 - a client connection, an older Ray: checked by "any node alive"
        return None


def _cluster_problem(ray, node_id) -> str | None:
    """Why the cluster cannot run jobs any more, or None: this driver's node dead (its raylet
    killed), no node alive, or no answer within ASK_S seconds. The question is asked from a
    thread, so that a cluster that does not answer cannot hold the driver."""
    answer: dict = {}

    def ask():
        try:
            answer["nodes"] = ray.nodes()
        except Exception as e:  # noqa: BLE001 - reported as the cluster's answer
            answer["error"] = e

    t = threading.Thread(target=ask, name="jaxpbr-ray-nodes", daemon=True)
    t.start()
    t.join(ASK_S)
    if t.is_alive():
        return f"it did not answer within {ASK_S:g} s"
    if "error" in answer:
        return f"asking it for its nodes failed ({type(answer['error']).__name__}: {_first_line(answer['error'])})"
    nodes = answer["nodes"]
    if node_id is not None and not any(n.get("NodeID") == node_id and n.get("Alive") for n in nodes):
        return f"the node this run is attached to ({node_id[:12]}) is dead (its raylet stopped)"
    if not any(n.get("Alive") for n in nodes):
        return "none of its nodes is alive"
    return None


def _kill(ray, actor) -> None:
    """Stop an actor; one that is already gone raises, which is what was wanted."""
    with contextlib.suppress(Exception):
        ray.kill(actor)
