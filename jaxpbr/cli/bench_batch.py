"""`jaxpbr bench batch`: the throughput of `jaxpbr.batch` against the Python loop a user writes
without it, side by side in one process (docs/batch.md).

The same N render jobs (the demo scene at S x S, cameras on an orbit, two environments: the
procedural sky and a panorama written by `write_panorama`) are run by

(a) **loop**: per job, what a script does: build the scene (`demo_scene`, `load_environment`),
    `jp.render`, tone map, write the PNG;
(b) **loop, reused**: the same loop with each scene and environment built once (a stronger
    baseline: only the render, the tone map and the write are left per job);
(c) **engine local**: `run_batch(jobs, fresh folder, engine="local")` (one `Worker`, the host
    writes of one job overlapped with the render of the next, a completion record per job);
(d) **engine ray** (`--ray`; skipped when Ray is not importable): `run_batch(engine="ray")` with 1
    and 2 workers on a local cluster started once by the benchmark; each run starts its actors
    (their compiled programs come from the persistent cache on disk), so its figure includes them.
    The cost of starting and stopping a local cluster (`ray.init` + `ray.shutdown`) is timed apart.

Every variant runs once to compile and warm the caches, then `rounds` timed passes, each into a
fresh folder; the best pass is reported as jobs per second. The outputs of the loop and the engine
are the same images (the engine's PNGs also carry metadata and a completion record each).
`profile_engine` splits one engine job into its steps (render, host copy, PNG encode and write with
its read-back check, record checksum) to show where the time goes.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from .. import color
from ..batch import load_jobs, run_batch
from ..batch.work import Worker
from ..ibl.cubeio import load_environment
from ..io import image
from ..rendering.demo import demo_scene
from ..rendering.renderer import render
from ..rendering.scene import Environment
from ._common import positive_int_arg
from .timing import time_interleaved

__all__ = ["BatchBenchResult", "add_command", "bench_batch", "cmd_bench_batch", "job_rows", "profile_engine",
           "write_panorama"]


def write_panorama(path, width: int = 256) -> Path:
    """A small procedural equirect panorama (width x width/2, Radiance .hdr): a warm low sun over a
    blue-to-orange sky and a dark ground, different enough from `procedural:sky` to light the
    scene differently. Deterministic (the same bytes every time)."""
    if width < 4 or width % 2:
        raise ValueError(f"width must be an even number >= 4, got {width}")
    h = width // 2
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(h) + 0.5) / h
    phi = (u - 0.5) * 2.0 * math.pi  # azimuth
    theta = v * math.pi  # polar angle from +Y
    P, T = np.meshgrid(phi, theta)
    d = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1)
    up = d[..., 1:2]
    zenith, horizon, ground = np.array([0.15, 0.3, 0.8]), np.array([1.6, 0.9, 0.45]), np.array([0.12, 0.1, 0.08])
    t = np.clip(up, 0.0, 1.0) ** 0.5
    sky = horizon * (1.0 - t) + zenith * t
    img = np.where(up >= 0.0, sky, ground * (1.0 + up))
    sun = np.array([math.cos(0.2) * math.cos(0.8), math.sin(0.2), math.cos(0.2) * math.sin(0.8)])
    c = np.clip(d @ sun, -1.0, 1.0)
    img = img + np.array([60.0, 40.0, 22.0]) * np.exp((c - 1.0) / 0.002)[..., None]
    path = Path(path)
    image.write(path, img.astype(np.float32))
    return path


def job_rows(n: int, size: int, environments) -> list[dict]:
    """n render jobs of the demo scene at size^2: cameras on an orbit (24 units away, heights
    alternating), environments taken in turn."""
    rows = []
    for k in range(n):
        a = math.radians(-40.0 + 80.0 * k / max(1, n - 1))
        y = (-4.0, 0.0, 4.0)[k % 3]
        pos = [round(24.0 * math.sin(a), 4), y, round(24.0 * math.cos(a), 4)]
        rows.append({"name": f"job{k:03d}", "scene": "demo", "width": size, "height": size,
                     "camera": {"position": pos, "target": [0.0, 0.0, 0.0]},
                     "environment": environments[k % len(environments)]})
    return rows


def _loop(jobs, out: Path, *, reuse: bool) -> None:
    """The user's loop: per job build (or reuse) the scene, render, tone map, write the PNG."""
    scenes: dict = {}
    envs: dict = {}
    for job in jobs:
        if reuse and (job.width, job.height) in scenes:
            scene = scenes[(job.width, job.height)]
        else:
            scene = scenes[(job.width, job.height)] = demo_scene(job.width, job.height)
        if reuse and job.environment in envs:
            cube = envs[job.environment]
        else:
            cube = envs[job.environment] = load_environment(job.environment)
        cam = scene.camera.replace(position=job.camera["position"], target=job.camera["target"])
        s = scene.replace(camera=cam, environment=Environment(radiance=cube))
        hdr = render(s)
        image.write(out / f"{job.name}.png", np.asarray(color.tonemap(hdr, "aces")), encoding="srgb")


@dataclasses.dataclass(frozen=True)
class BatchBenchResult:
    jobs: int
    size: int
    device: str
    #: variant -> best seconds of a timed pass over every job
    seconds: dict
    #: variant -> seconds of the first (compiling) pass
    first: dict
    #: seconds of ray.init(num_cpus=2) + ray.shutdown(), when measured
    ray_cluster: float | None = None
    ray_note: str | None = None
    png_bytes: float = 0.0
    profile: dict | None = None

    def rate(self, variant: str) -> float:
        return self.jobs / self.seconds[variant]

    def report(self) -> str:
        lines = [(f"jaxpbr bench batch: {self.jobs} render jobs of the demo scene at {self.size}^2, 2 environments, "
                  f"PNG out ({self.png_bytes / 1024:.0f} KiB each); {os.cpu_count()} CPU cores, device {self.device}"),
                 f"{'variant':<34}{'first pass s':>13}{'warm s':>9}{'jobs/s':>9}{'vs (a)':>8}{'vs (b)':>8}"]
        a, b = self.seconds["(a) loop"], self.seconds["(b) loop, reused"]
        for k, s in self.seconds.items():
            lines.append(f"{k:<34}{self.first[k]:>13.2f}{s:>9.2f}{self.jobs / s:>9.2f}{a / s:>8.2f}{b / s:>8.2f}")
        if self.ray_cluster is not None:
            lines.append(f"local Ray cluster start + stop (ray.init(num_cpus=2) + ray.shutdown()): {self.ray_cluster:.2f} s")
        if self.ray_note:
            lines.append(self.ray_note)
        if self.profile:
            p = self.profile
            tot = sum(p.values())
            lines.append("one engine job, step by step (seconds, mean over the jobs; steps run one after another here):")
            for k, v in p.items():
                lines.append(f"  {k:<44}{v:>8.4f}  {100 * v / tot:5.1f} %")
        return "\n".join(lines)

    def to_json(self) -> dict:
        return {**dataclasses.asdict(self), "jobs_per_second": {k: self.rate(k) for k in self.seconds}}


def _interleaved(variants: dict, rounds: int):
    """`timing.time_interleaved` -> ({name: best seconds}, {name: first-pass seconds})."""
    t = time_interleaved(variants, rounds=rounds)
    return {k: v.best for k, v in t.items()}, {k: v.first for k, v in t.items()}


def profile_engine(jobs, out) -> dict:
    """Mean seconds per step of an engine render job, each step synchronised on its own: building
    the group's scene and environment (its first job only), the render's device work, the host copy, PNG encode + atomic write (with its read-back check), the
    record's checksum and write. Run warm (after a pass of the same jobs)."""
    from ..batch.store import OutputFolder

    folder = OutputFolder(out)
    folder.records.mkdir(parents=True, exist_ok=True)
    worker = Worker(folder)
    steps = {"scene + environment (built once per group)": 0.0, "render (device work, incl. tone map)": 0.0, "copy to host": 0.0, "PNG encode + write + read-back": 0.0,
             "record (sha256 + JSON write)": 0.0}
    for job in jobs:
        tl = time.perf_counter()
        worker.scene(job)  # loads and keeps the group's scene and environment (the first job of a group)
        t0 = time.perf_counter()
        pending = worker.compute(job)
        jax.block_until_ready((pending["hdr"], pending["ldr"]))
        t1 = time.perf_counter()
        hdr, ldr = np.asarray(pending["hdr"]), np.asarray(pending["ldr"])
        assert np.all(np.isfinite(hdr))
        t2 = time.perf_counter()
        d = pending["display"]
        image.write(folder.root / f"{job.name}.png", ldr, bits=d["bits"], encoding=d["encoding"], encoded=True,
                    metadata={"software": "jaxpbr", "jaxpbr:job": job.name, "jaxpbr:plan": pending["plan"]})
        t3 = time.perf_counter()
        folder.commit(job, [f"{job.name}.png"], seconds=t3 - t0, worker="profile")
        t4 = time.perf_counter()
        for k, v in zip(steps, (t0 - tl, t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            steps[k] += v / len(jobs)
    return steps


def bench_batch(n: int = 16, size: int = 256, *, rounds: int = 2, ray: bool = False, ray_workers=(1, 2),
                panorama_width: int = 256, profile: bool = True, workdir=None) -> BatchBenchResult:
    """Run the variants of the module docstring on n jobs of size^2 -> BatchBenchResult."""
    own = workdir is None
    work = Path(tempfile.mkdtemp(prefix="jaxpbr-bench-batch-") if own else workdir)
    work.mkdir(parents=True, exist_ok=True)
    try:
        write_panorama(work / "panorama.hdr", panorama_width)
        rows = job_rows(n, size, ["procedural:sky", "panorama.hdr"])
        (work / "jobs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
        jobs = load_jobs(work / "jobs.jsonl")
        counter = [0]

        def fresh() -> Path:
            counter[0] += 1
            d = work / f"out{counter[0]:03d}"
            d.mkdir()
            return d

        def loop(reuse):
            return lambda: _loop(jobs, fresh(), reuse=reuse)

        def engine(**kw):
            def go():
                out = fresh()
                s = run_batch(jobs, out, **kw)
                if s["counts"]["done"] != len(jobs):
                    raise RuntimeError(f"the engine did {s['counts']} of {len(jobs)} jobs")
            return go

        variants = {"(a) loop": loop(False), "(b) loop, reused": loop(True), "(c) engine local": engine(engine="local")}
        seconds, first = _interleaved(variants, rounds)
        png = [p.stat().st_size for p in sorted(work.glob("out*/*.png"))]
        ray_cluster = note = None
        if ray:
            ray_cluster, note = _bench_ray(engine, seconds, first, ray_workers, rounds, variants)
        prof = profile_engine(jobs, fresh()) if profile else None
        return BatchBenchResult(jobs=n, size=size, device=jax.devices()[0].device_kind, seconds=seconds, first=first,
                                ray_cluster=ray_cluster, ray_note=note, png_bytes=float(np.mean(png)), profile=prof)
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)


def _bench_ray(engine, seconds, first, ray_workers, rounds, baselines):
    try:
        import ray
    except ImportError:
        return None, "(d) engine ray: skipped (Ray is not installed: pip install 'jaxpbr[ray]')"
    import logging
    import warnings

    from .batch import setup_worker

    if ray.is_initialized():
        return None, "(d) engine ray: skipped (Ray is already initialised in this process)"
    kw = {"include_dashboard": False, "logging_level": logging.WARNING, "log_to_driver": False}
    ncpu = max(2, max(ray_workers))
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        t0 = time.perf_counter()
        ray.init(num_cpus=ncpu, **kw)
        ray.shutdown()
        cluster = time.perf_counter() - t0
        ray.init(num_cpus=ncpu, **kw)
    try:
        # The baselines again, interleaved with the Ray runs (the same load for each).
        variants = dict(baselines)
        for w in ray_workers:
            variants[f"(d) engine ray, {w} worker{'s' if w > 1 else ''}"] = engine(
                engine="ray", workers=w, worker_setup=setup_worker)
        best, firsts = _interleaved(variants, rounds)
    finally:
        ray.shutdown()
    for k, v in best.items():
        seconds[k] = min(seconds.get(k, math.inf), v)
        first.setdefault(k, firsts[k])
    return cluster, None


def add_command(bsub) -> None:
    """Register `jaxpbr bench batch`."""
    p = bsub.add_parser(
        "batch",
        help="jaxpbr batch (in-process engine, optionally Ray) vs a Python loop of render + write, side by side",
        description="Warm throughput of N render jobs: (a) a Python loop building the scene per job, (b) the "
        "same loop with scenes and environments built once, (c) jaxpbr.batch in this process, (d) with --ray, "
        "jaxpbr.batch on a local Ray cluster with 1 and 2 workers, plus the cluster's start/stop cost.",
    )
    p.add_argument("--jobs", type=positive_int_arg, default=16, metavar="N", help="render jobs (default: %(default)s)")
    p.add_argument("--size", type=positive_int_arg, default=256, metavar="S", help="image side in pixels (default: %(default)s)")
    p.add_argument("--rounds", type=positive_int_arg, default=2, help="timed passes per variant, best reported (default: %(default)s)")
    p.add_argument("--ray", action="store_true", help="also time the Ray engine (skipped if Ray is not installed)")
    p.add_argument("--no-profile", dest="profile", action="store_false", help="leave out the per-step profile of an engine job")
    p.add_argument("--json", default=None, metavar="FILE", help="also write the figures as JSON")
    p.set_defaults(func=cmd_bench_batch)


def cmd_bench_batch(args) -> int:
    res = bench_batch(args.jobs, args.size, rounds=args.rounds, ray=args.ray, profile=args.profile)
    print(res.report())
    if args.json:
        from ..io.atomic import write_json

        write_json(args.json, res.to_json())
    return 0
