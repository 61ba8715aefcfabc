"""`jaxpbr bench render --gltf`: a glTF asset of triangle meshes against the analytic spheres.

The asset is the demo's 7x7 sphere grid written as UV-sphere meshes (`jaxpbr.rendering.demo.
write_demo_glb`, tessellated for the requested triangle count) into a temporary folder. In this
process, side by side: writing and loading it, the acceleration structure's build, one visibility
query of the primary rays (median of back-to-back calls after a first one), the first renders, and
the warm frame times (medians) of the mesh grid and of the analytic grid (`demo_scene`: same camera,
four point lights, procedural sky with sun), with and without shadow rays; the ratios of the two.
As whole processes: the cold start (fresh caches) of `jaxpbr render ASSET.glb --environment
procedural:sky` against the demo's `jaxpbr render`, several runs alternating, then a warm rerun of
each on the caches the cold run filled; the peak resident memory of each process (its VmHWM,
read by the process itself as it exits: `wait4`'s ru_maxrss would count the parent's memory that
the child had before its exec); and optionally processes rendering larger assets (`--memory-triangles`), whose peak
memory is reported, or the memory guard's refusal with its estimate.
"""

from __future__ import annotations

import gc
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np

from .. import _memory
from .._validate import positive_int
from ..rendering.demo import demo_grid_lat, demo_scene, write_demo_glb
from ..rendering.gltf_scene import load_gltf
from ..rendering.renderer import render
from ..rendering.scene import primary_rays
from ..rendering.visibility import TriangleAccel
from .timing import time_interleaved

__all__ = ["GltfBenchResult", "ProcessRun", "bench_gltf", "grid_counts", "run_process"]

#: Targets printed next to the measurements (2-core CPU, 1080p, ~1 M triangles).
VISIBILITY_TARGET_S = 0.5
FRAME_RATIO_TARGET = 1.5
COLD_START_TARGET_S = 2.0
#: The image size of `jaxpbr render` when none is given (the whole-process runs use it by default).
RENDER_DEFAULT_SIZE = (1280, 720)
#: Variables that would point the child processes at caches other than their fresh folder.
_CACHE_VARIABLES = ("JAX_COMPILATION_CACHE_DIR", "JAXPBR_COMPILATION_CACHE", "JAXPBR_ASSET_CACHE")


def grid_counts(lat: int) -> tuple[int, int]:
    """(triangles, vertices) of the demo grid written with `lat` latitude bands per sphere."""
    return 49 * 4 * lat * (lat - 1), 49 * (lat + 1) * (2 * lat + 1)


@dataclass(frozen=True)
class ProcessRun:
    """One child process: its wall time (start to reaped), peak resident memory and outcome."""

    wall_s: float
    peak_rss: float  # bytes
    returncode: int
    message: str = ""  # the last line of stderr when it failed


#: `python -c` program: run `jaxpbr ARGS...` (argv[2:]) as `python -m jaxpbr` does and, on the way
#: out, write the process's peak resident memory (VmHWM of /proc/self/status, kB) to argv[1]: an
#: atexit handler, which the command line runs before it ends its process (`cli._end_process`).
_PEAK_WRAPPER = """
import atexit, runpy, sys
out = sys.argv[1]

def peak():
    with open("/proc/self/status") as f:
        hwm = next((line.split()[1] for line in f if line.startswith("VmHWM:")), "nan")
    with open(out, "w") as f:
        f.write(hwm)

atexit.register(peak)
sys.argv = ["jaxpbr", *sys.argv[2:]]
runpy.run_module("jaxpbr", run_name="__main__", alter_sys=True)
"""


def run_process(args: list[str], *, cache_dir: Path, log_dir: Path) -> ProcessRun:
    """Run `jaxpbr ARGS` as a fresh Python process with its caches in `cache_dir` (XDG_CACHE_HOME;
    the variables that would redirect them are removed) and its output in a file of `log_dir`;
    time it from start to exit; its peak RSS is its own VmHWM at exit (NaN where /proc is not)."""
    env = {k: v for k, v in os.environ.items() if k not in _CACHE_VARIABLES}
    env["XDG_CACHE_HOME"] = str(cache_dir)
    fd, log_name = tempfile.mkstemp(dir=log_dir, suffix=".log")
    peak_file = Path(log_name).with_suffix(".peak")
    with os.fdopen(fd, "w+") as log:
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-c", _PEAK_WRAPPER, str(peak_file), *args], stdout=log,
                           stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env, check=False)
        wall = time.perf_counter() - t0
        log.seek(0)
        lines = [x for x in log.read().splitlines() if x.strip()]
    try:
        peak = float(peak_file.read_text()) * 1024.0
    except (OSError, ValueError):
        peak = math.nan
    message = lines[-1] if p.returncode != 0 and lines else ""
    return ProcessRun(wall_s=wall, peak_rss=peak, returncode=p.returncode, message=message)


@dataclass(frozen=True)
class MemoryRun:
    """A process loading and rendering a larger asset: its peak RSS, or the guard's refusal."""

    triangles: int
    vertices: int
    width: int
    height: int
    estimate: float  # bytes: the guard's estimate of the meshes and the image
    run: ProcessRun


@dataclass
class GltfBenchResult:
    triangles: int
    vertices: int
    lat: int
    width: int
    height: int
    repeats: int
    device: str
    cores: int
    accel_backend: str
    rays: int
    steps: dict  # seconds: "write", "load", "build", "first_mesh", "first_analytic"
    visibility_s: float
    mesh_s: float
    mesh_shadows_s: float
    analytic_s: float
    analytic_shadows_s: float
    peak_rss: float  # bytes, this process
    process_size: tuple[int, int] = RENDER_DEFAULT_SIZE
    cold: dict = field(default_factory=dict)  # {"demo" | "asset": [ProcessRun]}
    warm: dict = field(default_factory=dict)
    memory: list = field(default_factory=list)  # [MemoryRun]

    @property
    def ratio(self) -> float:
        """Warm frame time, meshes / analytic spheres, without shadows."""
        return self.mesh_s / self.analytic_s

    @property
    def ratio_shadows(self) -> float:
        """Warm frame time, meshes / analytic spheres, both with shadows."""
        return self.mesh_shadows_s / self.analytic_shadows_s

    def cold_stats(self, which: str, warm: bool = False) -> tuple[float, float]:
        """(min, median) wall seconds of the demo's or the asset's processes."""
        runs = [r.wall_s for r in (self.warm if warm else self.cold).get(which, [])]
        return (min(runs), statistics.median(runs)) if runs else (math.nan, math.nan)

    def report(self) -> str:
        gb = lambda b: f"{b / 1e9:.2f} GB"
        ok = lambda good: "met" if good else "NOT met"
        w, h = self.process_size
        lines = [
            (
                f"jaxpbr bench render --gltf: the demo grid as {self.triangles:,} triangles ({self.vertices:,} vertices; "
                f"49 UV spheres of {self.lat} x {2 * self.lat}) vs the 49 analytic spheres, {self.width}x{self.height}, "
                f"4 point lights + IBL (procedural sky with sun, 128^2), JAX device {self.device}, {self.cores} CPU cores"
            ),
            f"  {'step':<58}{'seconds':>9}",
            f"  {'write the .glb':<58}{self.steps['write']:>9.2f}",
            f"  {'load_gltf':<58}{self.steps['load']:>9.2f}",
            f"  {f'acceleration structure ({self.accel_backend})':<58}{self.steps['build']:>9.2f}",
            (
                f"  {f'visibility of {self.rays:,} primary rays (median of {self.repeats})':<58}{self.visibility_s:>9.3f}"
                f"   target <= {VISIBILITY_TARGET_S} s: {ok(self.visibility_s <= VISIBILITY_TARGET_S)}"
            ),
            f"  {'first render, meshes (compiles, IBL precompute, structure)':<58}{self.steps['first_mesh']:>9.2f}",
            f"  {'first render, analytic spheres':<58}{self.steps['first_analytic']:>9.2f}",
            f"  {f'warm frame, median of {self.repeats}':<26}{'meshes s':>10}{'analytic s':>12}{'ratio':>8}   target",
        ]
        for label, m, a in (("without shadows", self.mesh_s, self.analytic_s),
                            ("with shadows", self.mesh_shadows_s, self.analytic_shadows_s)):
            r = m / a
            lines.append(f"    {label:<24}{m:>10.3f}{a:>12.3f}{r:>7.2f}x   <= {FRAME_RATIO_TARGET}x: {ok(r <= FRAME_RATIO_TARGET)}")
        lines.append(
            f"    meshes with shadows / analytic without: {self.mesh_shadows_s / self.analytic_s:.2f}x "
            "(the analytic scene renders without shadows by default, a mesh scene with them)"
        )
        lines.append(f"  peak resident memory of this process: {gb(self.peak_rss)}")
        if self.cold:
            n = len(self.cold.get("demo", []))
            size = "" if (w, h) == RENDER_DEFAULT_SIZE else f" --width {w} --height {h}"
            lines.append(f"  whole process, {w}x{h}, {n} run(s) each, alternating; seconds min / median; peak RSS (max)")
            rows = (("demo", f"jaxpbr render{size}"), ("asset", f"jaxpbr render ASSET.glb --environment procedural:sky{size}"))
            for which, cmd in rows:
                c, m = self.cold_stats(which), self.cold_stats(which, warm=True)
                rss = max(r.peak_rss for r in self.cold[which] + self.warm.get(which, []))
                lines.append(f"    {cmd:<62} cold {c[0]:6.2f} / {c[1]:6.2f}   warm {m[0]:6.2f} / {m[1]:6.2f}   {gb(rss)}")
            d = self.cold_stats("asset")[1] - self.cold_stats("demo")[1]
            dw = self.cold_stats("asset", True)[1] - self.cold_stats("demo", True)[1]
            lines.append(
                f"    asset - demo, medians: cold {d:+.2f} s   target <= {COLD_START_TARGET_S} s: {ok(d <= COLD_START_TARGET_S)};"
                f" warm {dw:+.2f} s"
            )
        for mr in self.memory:
            what = f"  memory, {mr.triangles:,} triangles ({mr.vertices:,} vertices) at {mr.width}x{mr.height}:"
            if mr.run.returncode == 0:
                lines.append(f"{what} peak RSS {gb(mr.run.peak_rss)} in {mr.run.wall_s:.1f} s (the guard's estimate of meshes + image: {gb(mr.estimate)})")
            else:
                lines.append(f"{what} exit status {mr.run.returncode} after {mr.run.wall_s:.1f} s (the guard's estimate of meshes + image: {gb(mr.estimate)}): {mr.run.message}")
        return "\n".join(lines)


def _render_argv(asset: Path | None, out: Path, size: tuple[int, int]) -> list[str]:
    argv = ["render"]
    if asset is not None:
        argv += [str(asset), "--environment", "procedural:sky"]
    argv += ["-o", str(out)]
    if tuple(size) != RENDER_DEFAULT_SIZE:
        argv += ["--width", str(size[0]), "--height", str(size[1])]
    return argv


def estimate_bytes(triangles: int, vertices: int, width: int, height: int) -> float:
    """The memory guard's estimate of a render's meshes and image (the IBL precomputes apart)."""
    from ..rendering.plan import mesh_engine

    return float(sum(_memory.mesh_bytes(vertices, triangles, mesh_engine()).values())
                 + sum(_memory.render_bytes(width, height).values()))


def bench_gltf(
    triangles: int = 1_000_000,
    width: int = 1920,
    height: int = 1080,
    *,
    repeats: int = 3,
    cold_runs: int = 3,
    process_size: tuple[int, int] = RENDER_DEFAULT_SIZE,
    memory_triangles: tuple[int, ...] = (),
    log=None,
) -> GltfBenchResult:
    """Run the measurements of the module docstring; `cold_runs` = 0 skips the whole-process runs.
    `log(text)` (default: nothing) hears of each phase."""
    for name, x in (("triangles", triangles), ("width", width), ("height", height), ("repeats", repeats),
                    ("process width", process_size[0]), ("process height", process_size[1])):
        positive_int(name, x)
    if cold_runs < 0:
        raise ValueError(f"cold_runs must be >= 0, got {cold_runs}")
    for t in memory_triangles:
        positive_int("memory_triangles", t)
    say = log or (lambda text: None)
    ref = demo_scene(width, height)
    steps: dict = {}
    with tempfile.TemporaryDirectory(prefix="jaxpbr-bench-gltf-") as tmp:
        d = Path(tmp)
        t0 = time.perf_counter()
        asset = write_demo_glb(d / "grid.glb", triangles=triangles)
        steps["write"] = time.perf_counter() - t0
        say(f"wrote {asset.triangles:,} triangles ({asset.path.stat().st_size / 1e6:.0f} MB)")
        t0 = time.perf_counter()
        scene = load_gltf(asset.path, camera=ref.camera, environment=ref.environment, lights=ref.lights, asset_lights=False)
        steps["load"] = time.perf_counter() - t0

        # Visibility of the primary rays against the whole grid as one mesh (the ray engine render uses).
        meshes = scene.objects
        offs = np.cumsum([0] + [m.num_vertices for m in meshes])
        V = np.concatenate([np.asarray(m.positions) for m in meshes])
        T = np.concatenate([np.asarray(m.triangles) + offs[k] for k, m in enumerate(meshes)])
        t0 = time.perf_counter()
        # As render builds it for opaque meshes (`mesh.ACCELS`): without the exact-ties search,
        # which only alpha-blended and cut-out layers walked by continuation need.
        accel = TriangleAccel.build(V, T, exact_ties=False)
        steps["build"] = time.perf_counter() - t0
        o, dirs = (np.asarray(x).reshape(-1, 3) for x in primary_rays(scene.camera))
        accel.intersect(o, dirs)
        vis = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            accel.intersect(o, dirs)
            vis.append(time.perf_counter() - t0)
        backend, rays = accel.backend, len(o)
        del accel, V, T, o, dirs
        say(f"visibility {statistics.median(vis):.3f} s; rendering")

        scenes = {"mesh": scene}
        del scene
        # Interleaved: each round renders the four frames in turn, so a drift of the machine's
        # speed during the benchmark leaves the ratios alone.
        t = time_interleaved({
            "mesh shadows": lambda: render(scenes["mesh"], shadows=True),
            "mesh": lambda: render(scenes["mesh"], shadows=False),
            "analytic": lambda: render(ref, shadows=False),
            "analytic shadows": lambda: render(ref, shadows=True),
        }, rounds=repeats)
        t_sh, t_mesh, t_ana, t_ana_sh = t["mesh shadows"], t["mesh"], t["analytic"], t["analytic shadows"]
        steps["first_mesh"], steps["first_analytic"] = t_sh.first, t_ana.first
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0
        # The child processes below get the memory back: the meshes, their ray engine and programs.
        scenes.clear()
        jax.clear_caches()
        gc.collect()
        result = GltfBenchResult(
            triangles=asset.triangles, vertices=asset.vertices, lat=asset.lat, width=width, height=height,
            repeats=repeats, device=_device_kind(), cores=len(os.sched_getaffinity(0)), accel_backend=backend,
            rays=rays, steps=steps, visibility_s=statistics.median(vis), mesh_s=t_mesh.median,
            mesh_shadows_s=t_sh.median, analytic_s=t_ana.median, analytic_shadows_s=t_ana_sh.median,
            peak_rss=peak, process_size=tuple(process_size),
        )

        # Whole processes: a fresh cache folder for each cold run, the same one for its warm rerun.
        if cold_runs:
            result.cold, result.warm = {"demo": [], "asset": []}, {"demo": [], "asset": []}
            for i in range(cold_runs):
                order = ("demo", "asset") if i % 2 == 0 else ("asset", "demo")
                for which in order:
                    cache = Path(tempfile.mkdtemp(dir=d, prefix=f"cache-{which}-"))
                    argv = _render_argv(asset.path if which == "asset" else None, d / f"{which}.png", process_size)
                    for store in (result.cold, result.warm):
                        run = run_process(argv, cache_dir=cache, log_dir=d)
                        if run.returncode != 0:
                            raise RuntimeError(f"jaxpbr {' '.join(argv)} failed (exit status {run.returncode}): {run.message}")
                        store[which].append(run)
                    say(f"{which}: cold {result.cold[which][-1].wall_s:.2f} s, warm {result.warm[which][-1].wall_s:.2f} s")
        asset.path.unlink()

        for n in memory_triangles:
            lat = demo_grid_lat(n)
            tri, vert = grid_counts(lat)
            big = write_demo_glb(d / f"grid{tri}.glb", lat=lat)
            cache = Path(tempfile.mkdtemp(dir=d, prefix="cache-memory-"))
            run = run_process(_render_argv(big.path, d / "memory.png", process_size), cache_dir=cache, log_dir=d)
            big.path.unlink()
            result.memory.append(MemoryRun(tri, vert, *process_size, estimate_bytes(tri, vert, *process_size), run))
            say(f"memory at {tri:,} triangles: exit status {run.returncode}, peak RSS {run.peak_rss / 1e9:.2f} GB")
    return result


def _device_kind() -> str:
    d = jax.devices()[0]
    return getattr(d, "device_kind", str(d))
