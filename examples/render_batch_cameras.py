"""`jp.render_batch` over cameras against a Python loop of `jp.render`, side by side in one process.

The demo sphere grid as a glTF asset (`write_demo_glb`, --triangles) under the demo's sky with its
sun, shadows on (the asset's four point lights and the sun), B cameras on an arc around it at
--size x --size. Each round times the loop and the batch back to back (warm: both run once
first); the images are checked equal. Printed: the median of --rounds for each, and their ratio.

    python examples/render_batch_cameras.py [--triangles 100000] [--cameras 16] [--size 256]
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
from jaxpbr.rendering.demo import write_demo_glb


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=100_000)
    ap.add_argument("--cameras", type=int, default=16)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "grid.glb"
        write_demo_glb(path, triangles=args.triangles)
        scene = jp.load_gltf(path, width=args.size, height=args.size, environment="procedural:sky")
    opts = jp.RenderOptions(shadows=True)
    cam = scene.camera
    p0 = np.asarray(cam.position, np.float64)
    ang = np.linspace(-0.4, 0.4, args.cameras)
    P = np.stack([[p0[0] * np.cos(a) + p0[2] * np.sin(a), p0[1], -p0[0] * np.sin(a) + p0[2] * np.cos(a)] for a in ang]).astype(np.float32)
    cams = cam.replace(position=jnp.asarray(P))

    def loop():
        return np.stack([np.asarray(jp.render(scene.replace(camera=cam.replace(position=tuple(P[i]))), options=opts))
                         for i in range(args.cameras)])

    def batch():
        return np.asarray(jp.render_batch(scene, cameras=cams, options=opts))

    a, b = loop(), batch()
    err = float(np.abs(a - b).max() / max(float(np.abs(a).max()), 1e-30))
    tl, tb = [], []
    for _ in range(args.rounds):
        t = time.perf_counter()
        loop()
        tl.append(time.perf_counter() - t)
        t = time.perf_counter()
        batch()
        tb.append(time.perf_counter() - t)
    ml, mb = statistics.median(tl), statistics.median(tb)
    print(f"{args.cameras} cameras at {args.size}^2, {args.triangles} triangles, shadows (4 lights + the sun): "
          f"loop of render {ml:.3f} s ({args.cameras / ml:.1f} frames/s), render_batch {mb:.3f} s "
          f"({args.cameras / mb:.1f} frames/s): {mb / ml:.2f}x the loop's time; images equal to {err:.1e} of the peak")


if __name__ == "__main__":
    main()
