"""Transmission through the scene: error against run time.

A glass sphere (KHR_materials_transmission, thin-walled, single-sided) before an unlit checkered
quad under a uniform sky, rendered by jaxpbr with the environment-only split sum
(transmission_depth=0) and with transmitted rays traced into the scene at K = 1, 4, 16, 64 rays per
pixel, against the float64 reference of the same camera rays (`tests/test_transmission_scene.py`:
the sphere's triangles, the glTF BRDF and thin-walled BTDF integrated by importance sampling, every
transmitted sample traced to the quad). Errors on the sphere's pixels, relative to the reference's
mean there: mean |error|, 90th percentile, bias; time per frame (warm, best of 3) beside the
environment-only frame in the same process.

    python examples/transmission_error.py [--size 160 120] [--roughness 0 0.15 0.4]
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import jaxpbr as jp

TESTS = Path(__file__).resolve().parent.parent / "tests"


def _reference_module():
    sys.path.insert(0, str(TESTS))  # (its asset writer: tests/gltf_writer.py)
    spec = importlib.util.spec_from_file_location("transmission_scene", TESTS / "test_transmission_scene.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, nargs=2, default=(160, 120), metavar=("W", "H"))
    ap.add_argument("--roughness", type=float, nargs="+", default=(0.0, 0.15, 0.4))
    ap.add_argument("--samples", type=int, nargs="+", default=(1, 4, 16, 64))
    ap.add_argument("--reference-samples", type=int, default=4096)
    args = ap.parse_args(argv)
    T = _reference_module()
    T.W, T.H = args.size
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in args.roughness:
            path = T.sphere_before_quad(Path(tmp), r)
            ref, on, _ = T.reference(r, samples=args.reference_samples)
            cam = jp.Camera(**T.CAM, width=T.W, height=T.H)
            scene = jp.load_gltf(path, camera=cam, width=T.W, height=T.H, environment=T.uniform_sky())
            mean = ref[on].mean()
            base_t = None
            for depth, k in [(0, 1)] + [(1, k) for k in args.samples]:
                opts = dict(extract_lights=False, shadows=False, multiscatter=False, transmission_depth=depth, transmission_samples=k)
                img = np.asarray(jp.render(scene, **opts), np.float64)[..., 0]  # (compiles)
                times = []
                for _ in range(3):
                    t0 = time.perf_counter()
                    np.asarray(jp.render(scene, **opts))
                    times.append(time.perf_counter() - t0)
                t = min(times)
                base_t = t if depth == 0 else base_t
                e = (img - ref)[on]
                rows.append((r, depth, k, np.abs(e).mean() / mean, np.percentile(np.abs(e), 90) / mean, e.mean() / mean, t, t / base_t))
    print(f"sphere before a checkered quad, {T.W}x{T.H}, errors on the sphere's pixels relative to the reference's mean there")
    print(f"{'roughness':>9} {'depth':>5} {'K':>3} {'mean|e|':>8} {'p90|e|':>8} {'bias':>8} {'s/frame':>8} {'x depth 0':>9}")
    for r, depth, k, m, p90, b, t, ratio in rows:
        print(f"{r:9.2f} {depth:5d} {k if depth else '-':>3} {m:8.2%} {p90:8.2%} {b:+8.2%} {t:8.3f} {ratio:9.2f}")
    return rows


if __name__ == "__main__":
    main()
