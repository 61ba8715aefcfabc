"""Spheres lit only by an HDR environment (image-based lighting), with the environment as the
background: a row of metals and a row of dielectrics at increasing roughness.

    python examples/ibl_spheres.py ENV.hdr [--face-size 256] [--exposure 0] [--output ibl_spheres.png]

ENV is an equirectangular .hdr/.exr (2:1), e.g. ../shared/data/spruit_sunrise_1k.hdr; without one,
the procedural sky + sun is used.
"""

import argparse
import math
import time

import numpy as np

import jaxpbr as jp

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("env", nargs="?", default=None)
ap.add_argument("--face-size", type=int, default=256)
ap.add_argument("--exposure", type=float, default=0.0)
ap.add_argument("--width", type=int, default=960)
ap.add_argument("--height", type=int, default=400)
ap.add_argument("--output", default="ibl_spheres.png")
args = ap.parse_args()

if args.env:
    cube = jp.Cubemap.from_equirect(jp.image.read(args.env), face_size=args.face_size)
else:
    cube = jp.envs.sky_with_sun_cubemap(args.face_size)
rough = np.linspace(0.0, 1.0, 6)
objects = []
for row, metallic in enumerate((1.0, 0.0)):
    for c, r in enumerate(rough):
        m = jp.Material(base_color=(0.95, 0.93, 0.88) if metallic else (0.8, 0.1, 0.1), metallic=metallic, roughness=float(r))
        objects.append(jp.Sphere(center=((c - 2.5) * 2.2, (0.5 - row) * 2.2, 0.0), radius=1.0, material=m))
scene = jp.Scene(
    camera=jp.Camera(position=(0.0, 0.0, 13.0), fov_y_deg=2 * math.degrees(math.atan(0.4)), width=args.width, height=args.height),
    objects=objects,
    environment=jp.Environment(radiance=cube),
)
print("plan:", jp.rendering.renderer.plan(scene).describe())
t0 = time.perf_counter()
hdr = jp.render(scene, multiscatter=True)
img = np.asarray(jp.color.tonemap(jp.color.exposure(hdr, args.exposure), "aces"))
print(f"rendered in {time.perf_counter() - t0:.2f} s (incl. precompute and compile)")
jp.image.write(args.output, img, encoding="srgb")
print(f"wrote {args.output}")
