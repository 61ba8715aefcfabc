"""`jaxpbr batch JOBS --out DIR [--engine local|ray] [--address ADDR]`: run a job file (docs/batch.md)."""

from __future__ import annotations

import sys
import time

from ..batch import ENGINES, SUMMARY, JobFileError, load_jobs, run_batch
from . import _cache
from ._common import CLIError, Progress, nonnegative_int_arg, positive_int_arg

__all__ = ["add_command", "cmd_batch"]


def add_command(sub) -> None:
    """Register `jaxpbr batch` on the top-level sub-parsers."""
    p = sub.add_parser(
        "batch",
        help="run a job file of renders and IBL bakes (in this process or on Ray)",
        description="Run the render and bake jobs of a JSON Lines file into an output folder. Every row is "
        "checked first (one line per problem, exit 2, nothing written). Completed jobs are recorded; running the "
        "same file again skips the jobs whose outputs are still as recorded and redoes the rest. "
        "Exit status 0 when every job is done, 1 when some failed (see DIR/" + SUMMARY + ").",
    )
    p.add_argument("jobs", metavar="JOBS", help="job file (.jsonl; docs/batch.md)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if missing)")
    p.add_argument("--engine", choices=ENGINES, default="local", help="local: in this process (default); ray: Ray actors (pip install 'jaxpbr[ray]')")
    p.add_argument("--address", default=None, metavar="ADDR", help="ray: the cluster to join (default: start a local one)")
    p.add_argument("--workers", type=positive_int_arg, default=None, metavar="N", help="ray: actors (default: one per node, each holding the node's CPUs)")
    p.add_argument("--retries", type=nonnegative_int_arg, default=2, metavar="N", help="ray: further attempts of a job whose worker died (default: %(default)s)")
    p.add_argument("--chunk", type=positive_int_arg, default=4, metavar="N", help="ray: jobs of one group sent to a worker together (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=cmd_batch)


def setup_worker() -> None:
    """Run in each Ray worker before its first job: the command line's caches (compiled programs,
    baked maps) on disk, shared with the driver and the other workers."""
    _cache.enable()
    _cache.enable_assets()


def cmd_batch(args) -> int:
    if args.engine == "local" and (args.address or args.workers):
        raise CLIError("--address/--workers apply to --engine ray")
    try:
        jobs = load_jobs(args.jobs)
    except JobFileError as e:
        for line in e.problems:
            print(f"jaxpbr: error: {line}", file=sys.stderr)
        print(f"jaxpbr: {len(e.problems)} problem(s) in {args.jobs}; nothing was run", file=sys.stderr)
        return 2
    n_render = sum(j.kind == "render" for j in jobs)
    print(f"{args.jobs}: {len(jobs)} jobs ({n_render} render, {len(jobs) - n_render} bake), engine {args.engine}")
    t0 = time.perf_counter()
    summary = run_batch(
        jobs, args.out, engine=args.engine, address=args.address, workers=args.workers, retries=args.retries,
        chunk=args.chunk, progress=Progress("batch", quiet=args.quiet, rate_unit="jobs"), worker_setup=setup_worker, jobs_file=args.jobs,
    )
    dt = time.perf_counter() - t0
    c = summary["counts"]
    rate = f", {c['done'] / dt:.2f} jobs/s" if c["done"] else ""
    print(f"{c['done']} done, {c['skipped']} skipped (complete), {c['failed']} failed in {dt:.1f} s{rate}; "
          f"summary: {args.out}/{SUMMARY}")
    for row in summary["jobs"]:
        if row["status"] == "failed":
            print(f"  failed: {row['name']} (row {row['row']}): {row['error']}", file=sys.stderr)
    return 1 if c["failed"] else 0
