"""Batch jobs: render datasets and bake IBL libraries from a JSON Lines job file, in this process or
on a Ray cluster, resumable, each job done once (docs/batch.md).

    jobs = jaxpbr.batch.load_jobs("examples/batch/jobs.jsonl")   # every row validated first
    summary = jaxpbr.batch.run_batch(jobs, "out/")               # engine="ray" for Ray
"""

from .engine import ENGINES, order_jobs, run_batch
from .jobs import BakeJob, JobFileError, RenderJob, load_jobs, parse_jobs
from .store import SUMMARY, OutputFolder, RunLocked
from .work import Worker

__all__ = [
    "ENGINES",
    "SUMMARY",
    "BakeJob",
    "JobFileError",
    "OutputFolder",
    "RenderJob",
    "RunLocked",
    "Worker",
    "load_jobs",
    "order_jobs",
    "parse_jobs",
    "run_batch",
]
