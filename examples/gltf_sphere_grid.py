"""The demo's 7x7 sphere grid as a glTF asset of triangle meshes, rendered by jaxpbr and compared with
the analytic-sphere render of the same materials, camera, lights and environment: the difference is the
tessellation. Prints the error per tessellation and the render times; writes the image of the mesh
grid (with shadows) to docs/gltf_sphere_grid.png (or --out).

    python examples/gltf_sphere_grid.py [--width 640 --height 360] [--out docs/gltf_sphere_grid.png]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import jaxpbr as jp
from jaxpbr.rendering.demo import demo_scene, write_demo_glb


def write_grid(path: Path, n_lat: int) -> Path:
    """The demo grid as a .glb: one UV sphere (n_lat x 2 n_lat) shared by 49 meshes, 49 materials;
    no lights or camera (this script passes the demo's)."""
    return write_demo_glb(path, lat=n_lat, lights=False, camera=False).path


def timed(f):
    f().block_until_ready()
    t = time.perf_counter()
    out = f()
    out.block_until_ready()
    return np.asarray(out), time.perf_counter() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--lat", default="12,24,48", help="tessellations (latitude bands; longitude = 2x)")
    ap.add_argument("--out", default=None, help="PNG of the mesh grid with shadows (default: docs/gltf_sphere_grid.png)")
    args = ap.parse_args(argv)
    ref_scene = demo_scene(args.width, args.height)
    ref, t_ref = timed(lambda: jp.render(ref_scene))
    hit = ref.sum(-1) > 0
    inner = hit.copy()
    for _ in range(2):  # two pixels away from the silhouettes
        inner &= np.roll(inner, 1, 0) & np.roll(inner, -1, 0) & np.roll(inner, 1, 1) & np.roll(inner, -1, 1)
    print(f"analytic spheres: {t_ref:.3f} s per frame ({args.width}x{args.height}, warm)")
    print("| tessellation | triangles | mean rel. error | 99th pct | coverage differs | frame (warm) | vs analytic |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as d:
        for n in (int(x) for x in args.lat.split(",")):
            path = write_grid(Path(d) / f"grid{n}.glb", n)
            scene = jp.load_gltf(path, camera=ref_scene.camera, environment=ref_scene.environment, lights=ref_scene.lights)
            img, t = timed(lambda scene=scene: jp.render(scene, shadows=False))
            lum = lambda x: x @ np.array([0.2126, 0.7152, 0.0722])
            rel = np.abs(lum(img) - lum(ref))[inner] / np.maximum(lum(ref)[inner], 1e-3)
            tris = sum(m.num_triangles for m in scene.objects)
            cov = int(((img.sum(-1) > 0) != hit).sum())
            print(f"| {n} x {2 * n} | {tris} | {rel.mean() * 100:.2f} % | {np.percentile(rel, 99) * 100:.2f} % | "
                  f"{cov} px | {t:.3f} s | {t / t_ref:.1f}x |")
        # The picture: the finest grid standing on a floor, with shadows.
        s = 40.0
        floor = jp.Mesh(
            positions=np.array([[-s, -8.6, s], [s, -8.6, s], [s, -8.6, -s], [-s, -8.6, -s]], np.float32),
            triangles=np.array([[0, 1, 2], [0, 2, 3]], np.int32),
            normals=np.tile(np.float32([0, 1, 0]), (4, 1)),
            material=jp.Material(base_color=(0.5, 0.5, 0.5), metallic=0.0, roughness=0.7),
        )
        cam = ref_scene.camera.replace(position=(0.0, 3.0, 26.0), target=(0.0, -2.0, 0.0))
        shadowed = np.asarray(jp.render(scene.replace(objects=(*scene.objects, floor), camera=cam)))
    out = Path(args.out) if args.out else Path(__file__).resolve().parent.parent / "docs" / "gltf_sphere_grid.png"
    jp.image.write(out, jp.color.tonemap(shadowed, "aces"), encoding="srgb")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
