"""Throughput of the IBL visibility rays (`RenderOptions(ibl_visibility="ao" | "ratio")`) through the
ray engine, beside the primary rays and raw embreex on the same rays.

The demo sphere grid as a glTF asset (`write_demo_glb`, --triangles) at --width x --height: the
G-buffer of the camera's pixels, K rays per pixel drawn as the renderer draws them (cosine and GGX
visible normals in turn), their segments as the renderer makes them (`shadows.shadow_segments`,
offset origins), then, each back to back in one process (median of --repeats):

* the renderer's query: `shadows.host_mesh_hits` over the K parts in one call;
* the same parts one call each;
* raw embreex: embreex's own `occluded` query on the same rays (one thread, no exact refinement);
* the primary rays: `TriangleAccel.intersect` of the camera's rays.

    python examples/ibl_visibility_rays.py [--triangles 1000000] [--width 1920 --height 1080] [--samples 4]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import jaxpbr as jp
from jaxpbr.rendering import stages
from jaxpbr.rendering.demo import demo_environment, write_demo_glb
from jaxpbr.rendering.plan import plan
from jaxpbr.rendering.scene import primary_rays
from jaxpbr.rendering.shadows import host_mesh_hits, shadow_segments
from jaxpbr.rendering.visibility import TriangleAccel


def timed(fn, repeats):
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "grid.glb"
        write_demo_glb(path, triangles=args.triangles)
        scene = jp.load_gltf(path, width=args.width, height=args.height, environment=demo_environment())
    opts = jp.RenderOptions(ibl_visibility="ratio", ibl_samples=args.samples)
    p = plan(scene, options=opts).for_stages()
    off = jnp.asarray((0.5, 0.5), jnp.float32)
    g = stages.staged_geometry(scene, p, opts, off, light_shadows=False)
    dirs = stages._ibl_directions(scene, p, opts, g, off)
    parts = shadow_segments(scene.objects, g["pos"], g["ng"], [tuple(dirs[k][..., i] for i in range(3)) for k in range(args.samples)],
                            jnp.float32, directions_only=True)
    parts = [{k: (np.asarray(v) if v is not None else None) for k, v in part.items()} for part in parts]
    arrays = stages.scene_host_arrays(scene, jnp.float32)
    mask = np.asarray(g["hit"])
    n_rays = int(mask.sum()) * args.samples
    host_mesh_hits(arrays, parts, mask)  # (builds the ray engine)
    t_batched = timed(lambda: host_mesh_hits(arrays, parts, mask), args.repeats)
    t_split = timed(lambda: [host_mesh_hits(arrays, [pt], mask) for pt in parts], args.repeats)
    sel = mask.reshape(-1)
    o = np.concatenate([pt["o32"].reshape(-1, 3)[sel] for pt in parts]).astype(np.float32)
    d = np.concatenate([pt["l"].reshape(-1, 3)[sel] for pt in parts]).astype(np.float32)
    from embreex.mesh_construction import TriangleMesh
    from embreex.rtcore_scene import EmbreeScene

    es = EmbreeScene()
    TriangleMesh(es, np.asarray(arrays["positions"], np.float32), np.asarray(arrays["triangles"], np.int32))
    es.run(o[:1], d[:1])
    t_raw = timed(lambda: es.run(o, d, query="OCCLUDED"), args.repeats)
    o_px, d_px = primary_rays(scene.camera)
    po, pd = np.asarray(o_px, np.float32).reshape(-1, 3), np.asarray(d_px, np.float32).reshape(-1, 3)
    acc = TriangleAccel.build(np.asarray(arrays["positions"], np.float32), np.asarray(arrays["triangles"], np.int32))
    acc.intersect(po[:8], pd[:8])
    t_primary = timed(lambda: acc.intersect(po, pd), args.repeats)
    tri = int(np.asarray(arrays["triangles"]).shape[0])
    print(f"{tri} triangles, {args.width}x{args.height}, K = {args.samples}: {n_rays} visibility rays from {int(mask.sum())} surface pixels")
    print(f"{'query':44} {'s':>7} {'Mrays/s':>8}")
    for name, t, n in (("renderer: host_mesh_hits, the K parts at once", t_batched, n_rays),
                       ("host_mesh_hits, one call per part", t_split, n_rays),
                       ("raw embreex occluded (1 thread)", t_raw, n_rays),
                       ("primary rays: TriangleAccel.intersect", t_primary, len(po))):
        print(f"{name:44} {t:7.3f} {n / t / 1e6:8.2f}")


if __name__ == "__main__":
    main()
