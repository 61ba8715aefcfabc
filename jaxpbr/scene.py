"""Scene layer (minimal for now): perspective camera, analytic spheres, a G-buffer, the demo scene.

The demo is the LearnOpenGL "PBR / Lighting" chapter: a 7x7 grid of spheres (metallic by row,
roughness by column), albedo (0.5, 0, 0), four point lights of 300 at (+-10, +-10, 10), a constant
ambient of 0.03 * albedo * ao. The scene is ray-cast analytically in JAX and shaded with
`shade_direct`; everything is one jitted program.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._numerics import dot, safe_normalize, safe_sqrt
from .lights import PointLight, shade_direct
from .material import Material

__all__ = [
    "Camera",
    "GBuffer",
    "Spheres",
    "demo_scene",
    "primary_rays",
    "raycast_spheres",
    "render_demo",
]


@dataclasses.dataclass(frozen=True)
class Camera:
    """Pinhole camera (static configuration). Right-handed, +Y up; looks from `position` at `target`.

    fov_y_deg: vertical field of view in degrees. Pixel (i, j) (row i from the top) looks through
    the centre of its pixel footprint.
    """

    position: tuple[float, float, float] = (0.0, 0.0, 24.0)
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_y_deg: float = 45.0
    width: int = 1280
    height: int = 720

    def __post_init__(self):
        if not (isinstance(self.width, int) and isinstance(self.height, int)) or self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive integers, got {self.width}x{self.height}.")
        if not 0.0 < self.fov_y_deg < 180.0:
            raise ValueError(f"fov_y_deg must be in (0, 180), got {self.fov_y_deg}.")
        f = np.subtract(self.target, self.position)
        if np.linalg.norm(f) == 0 or np.linalg.norm(np.cross(f, self.up)) == 0:
            raise ValueError("camera target must differ from position and not be parallel to up.")


def primary_rays(cam: Camera, dtype=jnp.float32) -> tuple[jax.Array, jax.Array]:
    """Ray origins and unit directions, each (H, W, 3)."""
    pos = jnp.asarray(cam.position, dtype)
    fwd = safe_normalize(jnp.asarray(cam.target, dtype) - pos)
    right = safe_normalize(jnp.cross(fwd, jnp.asarray(cam.up, dtype)))
    up = jnp.cross(right, fwd)
    t = math.tan(math.radians(cam.fov_y_deg) / 2)
    aspect = cam.width / cam.height
    x = (2.0 * (jnp.arange(cam.width, dtype=dtype) + 0.5) / cam.width - 1.0) * t * aspect
    y = (1.0 - 2.0 * (jnp.arange(cam.height, dtype=dtype) + 0.5) / cam.height) * t
    d = fwd + x[None, :, None] * right + y[:, None, None] * up
    d = safe_normalize(d)
    return jnp.broadcast_to(pos, d.shape), d


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True)
class Spheres:
    """K spheres: center (K, 3), radius (K,), material with leaves (K, ...)."""

    center: jax.Array
    radius: jax.Array
    material: Material

    def tree_flatten(self):
        return (self.center, self.radius, self.material), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(*children)


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True)
class GBuffer:
    """Per-pixel surface data: hit (H, W) bool, position, normal, view direction (H, W, 3), material."""

    hit: jax.Array
    position: jax.Array
    normal: jax.Array
    view: jax.Array
    material: Material

    def tree_flatten(self):
        return (self.hit, self.position, self.normal, self.view, self.material), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(*children)


def raycast_spheres(origins: jax.Array, dirs: jax.Array, spheres: Spheres) -> GBuffer:
    """Nearest hit of each ray with K spheres (camera outside all spheres), memory O(pixels).

    A `fori_loop` over spheres keeps the closest `t` and its index (no (pixels x K) array).
    Ray-sphere: t = -b - sqrt(b^2 - c), b = (o - c).d, c = |o - c|^2 - R^2, |d| = 1.
    """
    dtype = dirs.dtype
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)

    def body(k, carry):
        t_best, idx = carry
        oc = origins - spheres.center[k]
        b = dot(oc, dirs)
        c = dot(oc, oc) - spheres.radius[k] ** 2
        disc = b * b - c
        t = -b - safe_sqrt(disc)
        ok = (disc > 0) & (t > 0) & (t < t_best)
        return jnp.where(ok, t, t_best), jnp.where(ok, k, idx)

    shape = dirs.shape[:-1]
    t, idx = jax.lax.fori_loop(
        0, spheres.radius.shape[0], body, (jnp.full(shape, big), jnp.zeros(shape, jnp.int32))
    )
    hit = t < big
    t = jnp.where(hit, t, 0.0)
    p = origins + t[..., None] * dirs
    normal = safe_normalize(p - spheres.center[idx])
    mat = jax.tree_util.tree_map(lambda x: x[idx], spheres.material)
    return GBuffer(hit=hit, position=p, normal=normal, view=-dirs, material=mat)


def demo_scene(dtype=jnp.float32) -> tuple[Spheres, list[PointLight]]:
    """The LearnOpenGL lighting-chapter scene: 7x7 spheres, spacing 2.5, radius 1, in the z = 0 plane.

    Row (y, from the bottom) sets metallic = row/7; column (x) sets roughness = clamp(col/7, 0.05, 1).
    """
    rows = cols = 7
    spacing = 2.5
    r_idx, c_idx = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    r_idx, c_idx = r_idx.ravel(), c_idx.ravel()
    center = np.stack(
        [(c_idx - cols // 2) * spacing, (r_idx - rows // 2) * spacing, np.zeros(rows * cols)], axis=-1
    )
    k = rows * cols
    material = Material(
        base_color=jnp.broadcast_to(jnp.asarray([0.5, 0.0, 0.0], dtype), (k, 3)),
        metallic=jnp.asarray(r_idx / rows, dtype),
        roughness=jnp.asarray(np.clip(c_idx / cols, 0.05, 1.0), dtype),
        occlusion=jnp.ones(k, dtype),
        emissive=jnp.zeros((k, 3), dtype),
    )
    spheres = Spheres(center=jnp.asarray(center, dtype), radius=jnp.ones(k, dtype), material=material)
    lights = [
        PointLight(position=jnp.asarray(pos, dtype), color=jnp.ones(3, dtype), intensity=jnp.asarray(300.0, dtype))
        for pos in [(-10.0, 10.0, 10.0), (10.0, 10.0, 10.0), (-10.0, -10.0, 10.0), (10.0, -10.0, 10.0)]
    ]
    return spheres, lights


@functools.partial(jax.jit, static_argnames=("camera", "model", "ambient"))
def _render(spheres: Spheres, lights, *, camera: Camera, model: str, ambient: float) -> jax.Array:
    o, d = primary_rays(camera, dtype=spheres.center.dtype)
    g = raycast_spheres(o, d, spheres)
    lo = shade_direct(g.position, g.normal, g.view, g.material, lights, model=model, ambient=ambient)
    return jnp.where(g.hit[..., None], lo, 0.0)


def render_demo(
    width: int = 1280,
    height: int = 720,
    *,
    model: str = "gltf",
    ambient: float = 0.03,
    dtype=jnp.float32,
) -> jax.Array:
    """Render the demo scene to linear HDR radiance, (height, width, 3), black background."""
    spheres, lights = demo_scene(dtype)
    camera = Camera(width=width, height=height)
    return _render(spheres, lights, camera=camera, model=model, ambient=float(ambient))
