"""The first image with a user's own HDR, as whole processes: jaxpbr against its demo and against
Mitsuba 3's first 16-spp image of the same triangles under the same panorama.

Each run is a fresh Python process started from scratch, timed from start to exit, with its peak
resident memory (its own VmHWM as it exits):

* ``demo``: `jaxpbr render` (the demo: analytic spheres, the shipped procedural sky), empty caches;
* ``asset + HDR``: `jaxpbr render grid.glb --environment PANORAMA.hdr`, empty caches: the panorama
  is new to the package, so the process loads it, bakes its irradiance, prefiltered chain and
  sun extraction, compiles the render and renders (the image size is `jaxpbr render`'s default,
  1280x720);
* ``asset + HDR, warm``: the same command again on the caches the cold run filled;
* ``mitsuba``: a Python process that imports Mitsuba 3 (variant `llvm_ad_rgb` by default), loads the
  same 49 spheres (the sphere's triangles as a PLY file, 49 shapes placed and coloured as the
  asset's nodes and materials: `principled` BSDFs of the same base colour, metallic and roughness),
  the same panorama as an `envmap`, the same camera, renders 16 samples per pixel with the `direct`
  integrator and writes an EXR.

The runs alternate (demo, asset, mitsuba, then the reverse order, ...) so that a drift of the
machine's speed touches all of them alike; medians over `--runs`. The asset is the demo grid
written with `--triangles` triangles (`jaxpbr.rendering.demo.write_demo_glb`). The panorama is a
procedural sky with a sun and a textured ground, written as Radiance HDR with fresh random detail
in every invocation (`--hdr` uses a file instead).

    pip install mitsuba            # optional: without it the Mitsuba runs are skipped
    python examples/first_image_vs_mitsuba.py [--runs 3] [--triangles 100000] [--hdr FILE]
        [--variant llvm_ad_rgb] [--spp 16]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from jaxpbr.cli.bench_gltf import ProcessRun, run_process
from jaxpbr.io import image
from jaxpbr.rendering.demo import demo_scene, uv_sphere, write_demo_glb

#: The Mitsuba child: argv[1] the scene description (JSON), argv[2] the peak-memory file.
_MITSUBA_CHILD = r"""
import atexit, json, sys
spec, peak_out = json.load(open(sys.argv[1])), sys.argv[2]

def peak():
    with open("/proc/self/status") as f:
        hwm = next((line.split()[1] for line in f if line.startswith("VmHWM:")), "nan")
    open(peak_out, "w").write(hwm)

atexit.register(peak)
import mitsuba as mi
mi.set_variant(spec["variant"])
T = mi.ScalarTransform4f
cam = spec["camera"]
d = {"type": "scene", "integrator": {"type": "direct"},
     "sensor": {"type": "perspective", "fov": cam["fov_y"], "fov_axis": "y",
                "to_world": T().look_at(origin=cam["position"], target=cam["target"], up=cam["up"]),
                "sampler": {"type": "independent", "sample_count": spec["spp"]},
                "film": {"type": "hdrfilm", "width": cam["width"], "height": cam["height"], "pixel_format": "rgb"}},
     "sky": {"type": "envmap", "filename": spec["hdr"]}}
for k, s in enumerate(spec["spheres"]):
    d[f"sphere{k}"] = {"type": "ply", "filename": spec["ply"],
                       "to_world": T().translate(s["center"]) @ T().scale(s["radius"]),
                       "bsdf": {"type": spec.get("bsdf", "principled"), "base_color": {"type": "rgb", "value": s["base_color"]},
                                "metallic": s["metallic"], "roughness": s["roughness"]}}
img = mi.render(mi.load_dict(d))
mi.util.write_bitmap(spec["out"], img)
"""


def write_panorama(path: Path, width: int = 1024, seed: int | None = None) -> Path:
    """A sky-and-ground equirect panorama (width x width/2) with a sun and random detail."""
    rng = np.random.default_rng(seed)
    h = width // 2
    theta = (np.arange(h) + 0.5) / h * math.pi  # from +Y (up)
    phi = (np.arange(width) + 0.5) / width * 2 * math.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(th) * np.sin(ph), np.cos(th), -np.sin(th) * np.cos(ph)], -1)
    up = d[..., 1]
    sky = np.where(up[..., None] > 0, np.array([0.35, 0.55, 1.0]) * (0.4 + 0.6 * up[..., None]), 0.0)
    ground = np.where(up[..., None] <= 0, np.array([0.3, 0.25, 0.2]) * (0.5 + rng.random((h, width, 1))), 0.0)
    sun_dir = np.array([0.4, 0.6, -0.5]) + rng.normal(scale=0.05, size=3)
    sun_dir /= np.linalg.norm(sun_dir)
    sun = 4.0e4 * (d @ sun_dir > math.cos(math.radians(0.6)))[..., None]
    clouds = 1.0 + 0.3 * rng.random((h // 8, width // 8, 1)).repeat(8, 0).repeat(8, 1)
    img = ((sky * clouds + ground + sun) * np.array([1.0, 0.97, 0.92])).astype(np.float32)
    image.write(path, img)
    return path


def mitsuba_spec(asset, tmp: Path, hdr: Path, variant: str, spp: int, size=(1280, 720)) -> Path:
    """The Mitsuba child's scene description: the asset's sphere as PLY, its 49 placements and
    materials (those of `demo_scene`, which the asset is written from) and its camera."""
    P, N, T = uv_sphere(asset.lat)
    ply = tmp / "sphere.ply"
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(P)}\nproperty float x\nproperty float y\n"
              f"property float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face {len(T)}\n"
              "property list uchar int vertex_indices\nend_header\n")
    faces = np.empty(len(T), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, T
    ply.write_bytes(header.encode() + np.concatenate([P, N], 1).astype("<f4").tobytes() + faces.tobytes())
    ref = demo_scene(*size)
    cam = ref.camera
    spheres = [{"center": [float(x) for x in np.asarray(s.center)], "radius": float(s.radius),
                "base_color": [float(x) for x in np.asarray(s.material.base_color)],
                "metallic": float(s.material.metallic), "roughness": float(s.material.roughness)} for s in ref.objects]
    spec = {"variant": variant, "spp": spp, "hdr": str(hdr), "ply": str(ply), "out": str(tmp / "mitsuba.exr"), "spheres": spheres,
            "camera": {"position": [float(x) for x in np.asarray(cam.position)], "target": [float(x) for x in np.asarray(cam.target)],
                       "up": [float(x) for x in np.asarray(cam.up)], "fov_y": float(cam.fov_y_deg), "width": size[0], "height": size[1]}}
    path = tmp / "mitsuba.json"
    path.write_text(json.dumps(spec))
    return path


def run_mitsuba(spec: Path, log_dir: Path) -> ProcessRun:
    peak_file = Path(tempfile.mkstemp(dir=log_dir, suffix=".peak")[1])
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", _MITSUBA_CHILD, str(spec), str(peak_file)], capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    try:
        peak = float(peak_file.read_text()) * 1024.0
    except (OSError, ValueError):
        peak = math.nan
    return ProcessRun(wall_s=wall, peak_rss=peak, returncode=p.returncode, message=(p.stderr.strip().splitlines() or [""])[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--triangles", type=int, default=100_000)
    ap.add_argument("--hdr", type=Path, default=None, help="an equirect panorama (default: a fresh procedural one)")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--spp", type=int, default=16)
    args = ap.parse_args(argv)
    try:
        import mitsuba  # noqa: F401
        have_mitsuba = True
    except ImportError:
        have_mitsuba = False
        print("mitsuba is not installed (pip install mitsuba): its runs are skipped")
    runs: dict[str, list[ProcessRun]] = {"demo": [], "asset + HDR": [], "asset + HDR, warm": [], "mitsuba": []}
    variant = args.variant
    with tempfile.TemporaryDirectory(prefix="jaxpbr-first-image-") as tmp:
        d = Path(tmp)
        asset = write_demo_glb(d / "grid.glb", triangles=args.triangles)
        print(f"asset: {asset.triangles:,} triangles; {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
        for i in range(args.runs):
            hdr = args.hdr or write_panorama(d / f"panorama{i}.hdr")  # new content every run: never cached
            spec = mitsuba_spec(asset, d, hdr, variant, args.spp) if have_mitsuba else None
            order = ["demo", "asset", "mitsuba"]
            for which in order if i % 2 == 0 else order[::-1]:
                if which == "mitsuba":
                    if spec is not None:
                        r = run_mitsuba(spec, d)
                        if r.returncode and variant != "scalar_rgb" and not runs["mitsuba"]:
                            # (Dr.Jit's LLVM backend crashes in LLVM 15's AVX-512 code generator on
                            # some machines: the scalar variant, which compiles nothing, instead)
                            print(f"the Mitsuba variant {variant} failed ({r.message}); using scalar_rgb")
                            variant = "scalar_rgb"
                            r = run_mitsuba(spec := mitsuba_spec(asset, d, hdr, variant, args.spp), d)
                        if r.returncode:
                            raise RuntimeError(f"the Mitsuba run failed: {r.message}")
                        runs["mitsuba"].append(r)
                    continue
                cache = Path(tempfile.mkdtemp(dir=d, prefix="cache-"))
                argv = ["render", "-o", str(d / f"{which}.png")]
                if which == "asset":
                    argv[1:1] = [str(asset.path), "--environment", str(hdr)]
                names = ["demo"] if which == "demo" else ["asset + HDR", "asset + HDR, warm"]
                for name in names:
                    r = run_process(argv, cache_dir=cache, log_dir=d)
                    if r.returncode:
                        raise RuntimeError(f"jaxpbr {' '.join(argv)} failed: {r.message}")
                    runs[name].append(r)
            print(f"run {i + 1}: " + ", ".join(f"{k} {v[-1].wall_s:.2f} s" for k, v in runs.items() if v), flush=True)
    med = {k: statistics.median(r.wall_s for r in v) for k, v in runs.items() if v}
    mem = {k: statistics.median(r.peak_rss for r in v) for k, v in runs.items() if v}
    print(f"\n| process | wall s (median of {args.runs}) | min–max | peak RSS GB | × demo | × Mitsuba |")
    print("|---|---|---|---|---|---|")
    for k, v in runs.items():
        if not v:
            continue
        ws = [r.wall_s for r in v]
        rel_m = f"{med[k] / med['mitsuba']:.2f}" if "mitsuba" in med else "–"
        print(f"| {k} | {med[k]:.2f} | {min(ws):.2f}–{max(ws):.2f} | {mem[k] / 1e9:.2f} | {med[k] / med['demo']:.2f} | {rel_m} |")
    if "mitsuba" in mem:
        print(f"Mitsuba variant {variant}, {args.spp} spp, direct integrator")
        print(f"peak memory, asset + HDR against Mitsuba: {mem['asset + HDR'] / mem['mitsuba']:.2f}x")
    print(f"(load average at the end {os.getloadavg()[0]:.1f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
