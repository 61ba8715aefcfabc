"""Textured materials: procedural UV textures (checker base colour, packed ORM with a roughness
ramp, a bumpy normal map, emissive stripes) on spheres and a ground plane, lit by the procedural
sky + a point light. Textures are made in code; see docs/scene_format.md for loading them from
files in a scene.toml.

    python examples/textured_spheres.py [--output textured_spheres.png]
"""

import argparse
import math

import numpy as np

import jaxpbr as jp

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--width", type=int, default=960)
ap.add_argument("--height", type=int, default=540)
ap.add_argument("--output", default="textured_spheres.png")
args = ap.parse_args()

N = 128
j, i = np.meshgrid(np.arange(N), np.arange(N))
u, v = (j + 0.5) / N, (i + 0.5) / N
checker = ((np.floor(u * 8) + np.floor(v * 4)) % 2)[..., None]
albedo = checker * np.array([0.9, 0.85, 0.8]) + (1 - checker) * np.array([0.1, 0.25, 0.6])
orm = np.stack([np.ones_like(u), 0.1 + 0.8 * u, checker[..., 0]], -1)  # R occlusion, G roughness, B metallic
# Bumps: height h = 0.5 sin sin; tangent-space normal (-dh/du, -dh/dv, 1) normalised, encoded (n+1)/2.
# glTF: +Y of the map points towards decreasing v, so the v-derivative enters with a + sign.
k = 2 * math.pi * 6
h_u = 0.05 * k * np.cos(k * u) * np.sin(k * v)
h_v = 0.05 * k * np.sin(k * u) * np.cos(k * v)
nrm = np.stack([-h_u, h_v, np.ones_like(u)], -1)
nrm = nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)
normal_map = (nrm + 1) / 2
stripes = ((np.floor(u * 16) % 2) * np.array([4.0, 1.5, 0.3]))[..., None, :].reshape(N, N, 3) * (v < 0.5)[..., None]

mats = [
    jp.TexturedMaterial(factors=jp.Material(metallic=1.0, roughness=1.0), base_color_texture=albedo, metallic_roughness_texture=orm, occlusion_texture=orm),
    jp.TexturedMaterial(factors=jp.Material(base_color=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.35), normal_texture=normal_map),
    jp.TexturedMaterial(factors=jp.Material(base_color=(0.05, 0.05, 0.05), metallic=0.0, roughness=0.5, emissive=(1.0, 1.0, 1.0)), emissive_texture=stripes),
]
objects = [jp.Sphere(center=((k - 1) * 2.4, 0.0, 0.0), radius=1.0, material=m) for k, m in enumerate(mats)]
objects.append(
    jp.Plane(point=(0.0, -1.0, 0.0), normal=(0.0, 1.0, 0.0), uv_scale=0.25,
             material=jp.TexturedMaterial(factors=jp.Material(metallic=0.0, roughness=0.8), base_color_texture=albedo))
)
scene = jp.Scene(
    camera=jp.Camera(position=(0.0, 1.5, 8.0), target=(0.0, -0.2, 0.0), width=args.width, height=args.height, supersample=2),
    objects=objects,
    lights=[jp.PointLight(position=(3.0, 4.0, 4.0), intensity=60.0)],
    environment=jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(128), rotation=math.radians(-75)),
)
print("plan:", jp.rendering.renderer.plan(scene).describe())
hdr = jp.render(scene)
jp.image.write(args.output, np.asarray(jp.color.tonemap(hdr, "aces")), encoding="srgb")
print(f"wrote {args.output}")
