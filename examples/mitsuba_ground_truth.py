"""The ground truth against an independent renderer: Mitsuba 3's `direct` integrator on the same
triangles.

The concave scene (`jaxpbr.rendering.demo.concave_scene`: an open box of Lambertian walls on a ground,
a sphere in a corner, a slot between two fins) under a uniform sky of radiance 1 and a punctual sun is
rendered by `jp.reference_render` (float64 Monte Carlo of the direct light with visibility) and by
Mitsuba 3 (`direct` integrator, `twosided` `diffuse` BSDFs, `constant` and `directional` emitters; the
meshes written as OBJ with their vertex normals). Mitsuba integrates over each pixel's area with a box
filter, jaxpbr at the pixel centre: the comparison is on the pixels whose 3 x 3 neighbourhood of the
G-buffer is one surface (no silhouette or crease inside). Also shown: `jp.render` with the unshadowed
split sum and with the ratio estimator at K = 16 against Mitsuba.

    pip install mitsuba
    python examples/mitsuba_ground_truth.py [--size 128 96] [--spp 1024]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import jaxpbr as jp
from jaxpbr.ibl.cubemap import Cubemap
from jaxpbr.rendering.demo import concave_scene
from jaxpbr.rendering.mesh import Mesh
from jaxpbr.rendering.renderer import gbuffer

SUN_DIRECTION = (-0.45, -0.75, -0.5)  # the direction the light travels
SUN_IRRADIANCE = 3.0


def write_obj(path: Path, mesh: Mesh) -> None:
    P = np.asarray(mesh.positions, np.float64)
    T = np.asarray(mesh.triangles, np.int64) + 1
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in P]
    if mesh.normals is not None:
        N = np.asarray(mesh.normals, np.float64)
        lines += [f"vn {x:.9g} {y:.9g} {z:.9g}" for x, y, z in N]
        lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in T]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in T]
    path.write_text("\n".join(lines) + "\n")


def mitsuba_image(scene, spp: int, tmp: Path, bounces: int = 0) -> np.ndarray:
    """Mitsuba 3's image of the scene: `direct` (bounces 0) or `path` with max_depth = bounces + 2."""
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    cam = scene.camera
    integrator = ({"type": "direct", "emitter_samples": 1, "bsdf_samples": 1} if bounces == 0 else
                  {"type": "path", "max_depth": bounces + 2, "rr_depth": bounces + 3})
    d = {"type": "scene", "integrator": integrator,
         "sensor": {"type": "perspective", "fov": float(cam.fov_y_deg), "fov_axis": "y",
                    "to_world": mi.ScalarTransform4f().look_at(origin=list(map(float, cam.position)), target=list(map(float, cam.target)),
                                                               up=list(map(float, cam.up))),
                    "sampler": {"type": "independent", "sample_count": spp},
                    "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height, "rfilter": {"type": "box"},
                             "pixel_format": "rgb"}},
         "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
         "sun": {"type": "directional", "direction": list(SUN_DIRECTION), "irradiance": {"type": "rgb", "value": [SUN_IRRADIANCE] * 3}}}
    for k, ob in enumerate(scene.objects):
        path = tmp / f"mesh{k}.obj"
        write_obj(path, ob)
        rgb = [float(x) for x in np.asarray(ob.material.base_color)]
        d[f"mesh{k}"] = {"type": "obj", "filename": str(path), "face_normals": ob.normals is None,
                         "bsdf": {"type": "twosided", "material": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}}}
    img = mi.render(mi.load_dict(d))
    return np.asarray(img, np.float64)[..., :3]


def interior(scene) -> np.ndarray:
    """Pixels whose 3 x 3 neighbourhood shows one smooth surface (no silhouette, crease or object edge)."""
    g = gbuffer(scene)
    hit = np.asarray(g.hit)
    n = np.asarray(g.normal, np.float64)
    ok = hit.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            hs = np.roll(np.roll(hit, dy, 0), dx, 1)
            ns = np.roll(np.roll(n, dy, 0), dx, 1)
            ok &= hs & (np.sum(n * ns, -1) > 0.98)
    ok[0, :] = ok[-1, :] = ok[:, 0] = ok[:, -1] = False
    return ok


def luma(x):
    return np.asarray(x)[..., :3] @ np.array([0.2126, 0.7152, 0.0722])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, nargs=2, default=(128, 96), metavar=("W", "H"))
    ap.add_argument("--spp", type=int, default=1024, help="samples per pixel of both ground truths")
    ap.add_argument("--bounces", type=int, default=2, help="also compare reference_render(bounces=B) with Mitsuba's path tracer (0: not)")
    args = ap.parse_args(argv)
    W, H = args.size
    sky = jp.Environment(radiance=Cubemap.from_function(lambda d: 0.0 * d + 1.0, 32))
    sun = jp.DirectionalLight(direction=SUN_DIRECTION, intensity=SUN_IRRADIANCE)
    scene = jp.Scene(**{**{k: getattr(concave_scene(W, H, environment=sky), k) for k in ("camera", "objects", "environment")}},
                     lights=(sun,))
    t0 = time.perf_counter()
    truth = jp.reference_render(scene, spp=args.spp)
    t_j = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        mi_img = mitsuba_image(scene, args.spp, Path(tmp))
        t_m = time.perf_counter() - t0
        mi_path = mitsuba_image(scene, args.spp, Path(tmp), args.bounces) if args.bounces else None
    mask = interior(scene)
    ref = luma(mi_img)
    rows = [("jp.reference_render", truth.image, t_j)]
    for vis, k in (("none", 1), ("ratio", 16)):
        t0 = time.perf_counter()
        img = np.asarray(jp.render(scene, extract_lights=False, multiscatter=False, ibl_visibility=vis, ibl_samples=k), np.float64)
        rows.append((f"jp.render ibl_visibility={vis}" + (f" K={k}" if vis == "ratio" else ""), img, time.perf_counter() - t0))
    print(f"concave scene, {W}x{H}, uniform sky + punctual sun, {mask.sum()} interior surface pixels; Mitsuba 3 direct "
          f"{args.spp} spp in {t_m:.1f} s (scalar_rgb); relative luminance difference from Mitsuba")
    print(f"{'':34} {'median':>8} {'mean':>8} {'p90':>8} {'bias':>8} {'seconds':>8}")
    out = {}
    for name, img, t in rows:
        rel = np.abs(luma(img) - ref)[mask] / np.maximum(ref[mask], 1e-3)
        bias = (luma(img) - ref)[mask].mean() / ref[mask].mean()
        out[name] = (np.median(rel), rel.mean(), np.percentile(rel, 90), bias)
        print(f"{name:34} {np.median(rel):8.2%} {rel.mean():8.2%} {np.percentile(rel, 90):8.2%} {bias:+8.2%} {t:8.1f}")
    se = luma(truth.stderr)[mask] / np.maximum(luma(truth.image)[mask], 1e-3)
    print(f"jp.reference_render's own standard error: {np.median(se):.2%} median")
    if mi_path is not None:
        t0 = time.perf_counter()
        multi = jp.reference_render(scene, spp=args.spp, bounces=args.bounces)
        t = time.perf_counter() - t0
        refp = luma(mi_path)
        rel = np.abs(luma(multi.image) - refp)[mask] / np.maximum(refp[mask], 1e-3)
        bias = (luma(multi.image) - refp)[mask].mean() / refp[mask].mean()
        gain = refp[mask].mean() / ref[mask].mean() - 1
        name = f"reference_render bounces={args.bounces}"
        out[name] = (np.median(rel), rel.mean(), np.percentile(rel, 90), bias)
        print(f"{name} against Mitsuba's path tracer (max_depth {args.bounces + 2}; the bounces add {gain:.1%}): "
              f"median {np.median(rel):.2%}, mean {rel.mean():.2%}, bias {bias:+.2%}, {t:.1f} s")
    return out


if __name__ == "__main__":
    main()
