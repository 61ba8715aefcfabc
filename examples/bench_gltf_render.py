"""A glTF asset of about a million triangles rendered at 1080p with 4 point lights and split-sum IBL,
against the same scene with analytic spheres, side by side in one process.

The asset is the demo's 7x7 sphere grid written as UV-sphere meshes (`tests/gltf_writer.py`), with
the tessellation chosen for the requested triangle count. Reported: loading, the acceleration
structure's build, one visibility query of the primary rays, the first render (compiles included), the
warm render (median of back-to-back runs) with and without shadows, the analytic render's warm time and
the ratio of the two, and the process's peak memory.

    python examples/bench_gltf_render.py [--triangles 1000000] [--width 1920 --height 1080] [--repeats 3]
"""

from __future__ import annotations

import argparse
import math
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import jaxpbr as jp
from jaxpbr.rendering.demo import demo_scene
from jaxpbr.rendering.scene import primary_rays
from jaxpbr.rendering.visibility import TriangleAccel

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gltf_sphere_grid import write_grid  # noqa: E402


def median_time(f, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        f().block_until_ready()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    n = max(4, round(math.sqrt(args.triangles / (49 * 4))))
    ref_scene = demo_scene(args.width, args.height)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        path = write_grid(Path(d) / "grid.glb", n)
        rows.append(("write the .glb", time.perf_counter() - t))
        t = time.perf_counter()
        scene = jp.load_gltf(path, camera=ref_scene.camera, environment=ref_scene.environment, lights=ref_scene.lights)
        rows.append(("load_gltf", time.perf_counter() - t))
    tris = sum(m.num_triangles for m in scene.objects)
    V = np.concatenate([np.asarray(m.positions) for m in scene.objects])
    offs = np.cumsum([0] + [m.num_vertices for m in scene.objects])
    T = np.concatenate([np.asarray(m.triangles) + offs[k] for k, m in enumerate(scene.objects)])
    t = time.perf_counter()
    accel = TriangleAccel.build(V, T)
    rows.append((f"acceleration structure ({accel.backend})", time.perf_counter() - t))
    o, dirs = (np.asarray(x).reshape(-1, 3) for x in primary_rays(scene.camera))
    accel.intersect(o, dirs)
    ts = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        accel.intersect(o, dirs)
        ts.append(time.perf_counter() - t)
    rows.append((f"visibility of {len(o):,} primary rays (median)", float(np.median(ts))))
    t = time.perf_counter()
    jp.render(scene).block_until_ready()
    rows.append(("first render (compiles, IBL precompute, structure)", time.perf_counter() - t))
    mesh_sh = median_time(lambda: jp.render(scene), args.repeats)
    jp.render(scene, shadows=False).block_until_ready()
    mesh = median_time(lambda: jp.render(scene, shadows=False), args.repeats)
    jp.render(ref_scene).block_until_ready()
    ana = median_time(lambda: jp.render(ref_scene), args.repeats)
    rows += [
        ("warm render, meshes with shadows", mesh_sh),
        ("warm render, meshes without shadows", mesh),
        ("warm render, analytic spheres (no shadows)", ana),
    ]
    print(f"{tris:,} triangles ({n} x {2 * n} per sphere), {args.width}x{args.height}, 4 point lights + IBL")
    print("| step | seconds |\n|---|---|")
    for name, s in rows:
        print(f"| {name} | {s:.3f} |")
    print(f"meshes / analytic spheres, warm, no shadows: {mesh / ana:.2f}x; with shadows: {mesh_sh / ana:.2f}x")
    print(f"peak resident memory of the process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GB")


if __name__ == "__main__":
    main()
