"""Benchmark of triangle-mesh visibility (jaxpbr.rendering.visibility): the primary rays of a
pinhole camera (1920x1080 by default) onto icospheres, embree against the JAX BVH on this machine.

For each mesh and backend: the build time (host), then `intersect` run back to back `--repeats`
times in the same process (min and median reported; the JAX backend's first call, which compiles,
is reported apart). "embreex raw" is embreex's own `run` on the same rays, without the exact
refinement that `TriangleAccel` adds (the watertight test, ties, barycentrics), on one thread and
on every core (bands of rays on a thread pool, as `TriangleAccel` splits them).

    python examples/bench_visibility.py [--subdiv 6 8] [--repeats 3] [--width 1920 --height 1080]
        [--backends embree jax raw] [--shadow] [--refit]

--refit (with the jax backend): a deforming mesh's tree (`jaxpbr.deformable`). The sphere is pushed
in and out by a third of its radius; its tree built at the sphere and refitted in JAX to the new
shape (`bvh.refit_bvh`, jitted, back to back) against one built on the host at the new shape
(`build_bvh`), and the primary rays through each (same hits; the refitted tree's boxes are looser).

Subdivision 6 is 81,920 triangles, 7 is 327,680, 8 is 1,310,720.
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import time
from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np

from jaxpbr.rendering.visibility import TriangleAccel, embree_available


def icosphere(subdiv: int):
    """A unit icosphere: (vertices (V, 3) float64, triangles (T, 3) int64), 20 * 4^subdiv faces."""
    t = (1 + 5**0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdiv):
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(e, axis=0, return_inverse=True)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1) + len(v)  # midpoints of edges 01, 12, 20 per face
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        f = np.concatenate([np.stack(x, 1) for x in ([a, m[0], m[2]], [b, m[1], m[0]], [c, m[2], m[1]], [m[0], m[1], m[2]])])
        v = np.concatenate([v, mid])
    return v, f


def camera_rays(width: int, height: int, fov_y_deg: float = 45.0, eye=(0.3, 0.4, 2.1)):
    """Pinhole rays (origins, unit directions), (H*W, 3) float32, looking at the origin (from
    distance ~2.16 the unit sphere fills the frame's height: ~60% of the rays hit)."""
    eye = np.asarray(eye, float)
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    h = np.tan(np.radians(fov_y_deg) / 2)
    ys, xs = np.mgrid[0:height, 0:width]
    sx = ((xs + 0.5) / width * 2 - 1) * h * width / height
    sy = (1 - (ys + 0.5) / height * 2) * h
    d = fwd + sx[..., None] * right + sy[..., None] * up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d = d.reshape(-1, 3).astype(np.float32)
    return np.broadcast_to(eye.astype(np.float32), d.shape).copy(), d


def timed(fn, repeats):
    out, times = None, []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return out, times


def refit_rows(v, f, o, d, repeats):
    """The --refit rows: host build at the deformed shape, the refit in JAX, and rays through each."""
    from jaxpbr.rendering.bvh import build_bvh, intersect_bvh, refit_bvh

    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    v1 = (v * (1 + 0.35 * np.sin(3 * u[:, :1]) * np.cos(2 * u[:, 1:2]))).astype(np.float32)
    v0, f32 = v.astype(np.float32), f.astype(np.int32)
    start = build_bvh(v0, f32, keep_degenerate=True).to_device()
    (fresh,), build_s = timed(lambda: (build_bvh(v1, f32, keep_degenerate=True).to_device(),), repeats)
    refit = jax.jit(refit_bvh)
    t = time.perf_counter()
    jax.block_until_ready(refit(start, v1, f32))
    first = time.perf_counter() - t
    v1d, fd = jax.device_put(v1), jax.device_put(f32)
    refitted, refit_s = timed(lambda: jax.block_until_ready(refit(start, v1d, fd)), repeats)
    trace = jax.jit(lambda b, o, d: intersect_bvh(b, o, d, lanes=1 << 17).prim)
    jax.block_until_ready(trace(fresh, o, d))
    want, fresh_s = timed(lambda: jax.block_until_ready(trace(fresh, o, d)), repeats)
    got, refit_rays_s = timed(lambda: jax.block_until_ready(trace(refitted, o, d)), repeats)
    print(f"  {len(f)} triangles, deformed: the refitted tree agrees with the one built there on "
          f"{100 * np.mean(np.asarray(got) == np.asarray(want)):.4f}% of the pixels")
    return [(len(f), "deformed: build_bvh (host)", min(build_s), None, None, len(o)),
            (len(f), "deformed: refit_bvh (JAX)", min(refit_s), first, None, len(o)),
            (len(f), "  rays, tree built there", None, None, fresh_s, len(o)),
            (len(f), "  rays, refitted tree", None, None, refit_rays_s, len(o))]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subdiv", type=int, nargs="+", default=[6, 8])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--backends", nargs="+", default=["raw", "embree", "jax"], choices=["raw", "embree", "jax"])
    ap.add_argument("--shadow", action="store_true", help="also time occluded() for shadow rays from the hits")
    ap.add_argument("--refit", action="store_true", help="also time refitting a deformed mesh's JAX BVH against building it")
    args = ap.parse_args()
    if not embree_available():
        args.backends = [b for b in args.backends if b == "jax"]
    o, d = camera_rays(args.width, args.height)
    n = len(o)
    print(f"{args.width}x{args.height} = {n} primary rays; JAX {jax.__version__} on {jax.default_backend()}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
    rows = []
    for sub in args.subdiv:
        v, f = icosphere(sub)
        ref = None
        for backend in args.backends:
            if backend == "raw":
                from embreex.mesh_construction import TriangleMesh
                from embreex.rtcore_scene import EmbreeScene

                t = time.perf_counter()
                scene = EmbreeScene()
                TriangleMesh(scene, v.astype(np.float32), f.astype(np.int32))
                scene.run(o[:1], d[:1])  # commit
                build = time.perf_counter() - t
                _, times = timed(lambda: scene.run(o, d, output=True), args.repeats)
                rows.append((len(f), "embreex raw run (1 thread)", build, None, times, n))
                # every core: one band of rays per thread at a time (embreex releases the GIL per call)
                cuts = np.linspace(0, n, 4 * (os.cpu_count() or 1) + 1).astype(int)
                with ThreadPoolExecutor(os.cpu_count() or 1) as pool:
                    _, times = timed(lambda: list(pool.map(lambda ab: scene.run(o[ab[0]:ab[1]], d[ab[0]:ab[1]], output=True),
                                                           itertools.pairwise(cuts))), args.repeats)
                rows.append((len(f), f"embreex raw run ({os.cpu_count()} threads)", None, None, times, n))
                continue
            t = time.perf_counter()
            acc = TriangleAccel.build(v, f, backend=backend)
            build = time.perf_counter() - t
            first = None
            if backend == "jax":
                t = time.perf_counter()
                jax.block_until_ready(acc.intersect(o, d))
                first = time.perf_counter() - t
            h, times = timed(lambda: jax.block_until_ready(acc.intersect(o, d)), args.repeats)
            prim = np.asarray(h.prim)
            label = f"{backend} (TriangleAccel)" + (f", {acc._impl.threads} threads" if backend == "embree" else "")
            rows.append((len(f), label, build, first, times, n))
            if backend == "embree":  # what render's primary cast asks for: t and prim only
                _, times = timed(lambda: acc.intersect(o, d, barycentrics=False), args.repeats)
                rows.append((len(f), "  the same, barycentrics=False", None, None, times, n))
            if backend == "embree":
                t = time.perf_counter()
                TriangleAccel.build(v, f, backend=backend, exact_ties=False)
                rows.append((len(f), "  (build with exact_ties=False)", time.perf_counter() - t, None, None, n))
            if ref is None:
                ref = prim
            else:
                same = np.mean(prim == ref)
                print(f"  {len(f)} triangles: {backend} agrees with the first backend on {100 * same:.4f}% of the pixels")
            if args.shadow:
                hit = prim >= 0
                p = o[hit] + np.asarray(h.t)[hit, None] * d[hit]
                light = np.broadcast_to(np.array([0.4, 0.8, 0.45], np.float32), p.shape)
                nrm = p / np.linalg.norm(p, axis=1, keepdims=True)
                from jaxpbr.rendering.visibility import offset_ray_origin

                so = offset_ray_origin(p.astype(np.float32), nrm.astype(np.float32))
                jax.block_until_ready(acc.occluded(so, light))
                _, st = timed(lambda: jax.block_until_ready(acc.occluded(so, light)), args.repeats)
                rows.append((len(f), f"{backend} occluded, shadow rays", None, None, st, int(hit.sum())))
            if args.refit and backend == "jax":
                rows += refit_rows(v, f, o, d, args.repeats)
    print()
    print(f"{'triangles':>10}  {'backend':<34} {'rays':>8} {'build s':>8} {'1st call s':>10} {'min s':>8} {'median s':>9} {'Mrays/s':>8}")
    for tri, label, build, first, times, rays in rows:
        b = f"{build:8.2f}" if build is not None else f"{'':>8}"
        fc = f"{first:10.2f}" if first is not None else f"{'':>10}"
        if times is None:
            print(f"{tri:>10}  {label:<34} {'':>8} {b}")
            continue
        print(f"{tri:>10}  {label:<34} {rays:>8} {b} {fc} {min(times):8.3f} {statistics.median(times):9.3f} {rays / min(times) / 1e6:8.3f}")
    print(f"(Mrays/s from the best run; load average at the end {os.getloadavg()[0]:.1f})")


if __name__ == "__main__":
    main()
