"""Built-in scenes: the default demo (sphere grid under a procedural sky + sun, plus lights) and
the LearnOpenGL lighting-chapter scene. Everything is generated in code (no files needed)."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..ibl.envs import sky_with_sun_cubemap
from ..shading.lights import PointLight
from ..shading.material import Material
from .scene import Camera, Environment, Scene, Sphere

__all__ = ["DEMO_BASE_COLOR", "DEMO_ENV_ROTATION", "demo_scene", "learnopengl_scene", "sphere_grid"]

#: Base colour of the demo spheres (linear RGB; a warm gold-like albedo).
DEMO_BASE_COLOR = (0.95, 0.64, 0.37)
#: Rotation of the procedural sky about +Y that puts its sun behind the camera, to the right
#: (world azimuth atan2(z, x) = +40 degrees, 20 degrees up), so the spheres are front-lit.
DEMO_ENV_ROTATION = math.radians(-75.0)


def sphere_grid(rows: int = 7, cols: int = 7, *, spacing: float = 2.5, base_color=DEMO_BASE_COLOR,
                metallic=None, roughness=None) -> tuple[Sphere, ...]:
    """rows x cols unit spheres in the z = 0 plane; metallic rises with the row (bottom to top),
    roughness with the column (left to right): metallic = row/(rows-1), roughness = col/(cols-1)
    unless given as arrays of length rows / cols."""
    met = np.linspace(0.0, 1.0, rows) if metallic is None else np.asarray(metallic, float)
    rough = np.linspace(0.0, 1.0, cols) if roughness is None else np.asarray(roughness, float)
    out = []
    for r in range(rows):
        for c in range(cols):
            center = ((c - (cols - 1) / 2) * spacing, (r - (rows - 1) / 2) * spacing, 0.0)
            m = Material(base_color=base_color, metallic=float(met[r]), roughness=float(rough[c]))
            out.append(Sphere(center=center, radius=1.0, material=m))
    return tuple(out)


def _four_lights(intensity: float = 300.0):
    return tuple(
        PointLight(position=pos, color=(1.0, 1.0, 1.0), intensity=intensity)
        for pos in [(-10.0, 10.0, 10.0), (10.0, 10.0, 10.0), (-10.0, -10.0, 10.0), (10.0, -10.0, 10.0)]
    )


def demo_scene(width: int = 1280, height: int = 720, *, face_size: int = 128, supersample: int = 1,
               lights: bool = True, environment: bool = True) -> Scene:
    """The default demo: a 7x7 sphere grid (metallic by row, roughness 0..1 by column) under the
    procedural sky with a 3000-radiance sun (`jaxpbr.ibl.envs`), rotated to light the spheres from
    behind the camera, plus four point lights of 300 cd at (+-10, +-10, 10)."""
    env = None
    if environment:
        env = Environment(radiance=sky_with_sun_cubemap(face_size), rotation=DEMO_ENV_ROTATION)
    return Scene(
        camera=Camera(position=(0.0, 0.0, 24.0), fov_y_deg=45.0, width=width, height=height, supersample=supersample),
        objects=sphere_grid(),
        lights=_four_lights() if lights else (),
        environment=env,
    )


def learnopengl_scene(width: int = 1280, height: int = 720) -> Scene:
    """The LearnOpenGL "PBR / Lighting" chapter: 7x7 spheres, albedo (0.5, 0, 0), metallic =
    row/7, roughness = clamp(col/7, 0.05, 1), four point lights of 300, constant ambient 0.03,
    black background."""
    rows = cols = 7
    spheres = sphere_grid(
        rows, cols, base_color=(0.5, 0.0, 0.0),
        metallic=np.arange(rows) / rows, roughness=np.clip(np.arange(cols) / cols, 0.05, 1.0),
    )
    return Scene(
        camera=Camera(width=width, height=height),
        objects=spheres,
        lights=_four_lights(),
        ambient=0.03,
        background=jnp.zeros(3),
    )
