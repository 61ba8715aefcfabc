"""Procedural environments generated in code (no files needed): a sky with a bright sun, and
simple closed-form test environments. Radiance is linear Rec.709 RGB; +Y is up."""

from __future__ import annotations

import math

import jax.numpy as jnp

from .cubemap import Cubemap

__all__ = ["SUN_DIRECTION", "sky_with_sun", "sky_with_sun_cubemap"]

#: Default sun direction (towards the sun): 20 degrees above the horizon.
SUN_DIRECTION = (
    math.cos(math.radians(20.0)) * math.cos(math.radians(35.0)),
    math.sin(math.radians(20.0)),
    -math.cos(math.radians(20.0)) * math.sin(math.radians(35.0)),
)


def sky_with_sun(
    d,
    *,
    sun_direction=SUN_DIRECTION,
    sun_radiance: float = 3000.0,
    sun_radius_deg: float = 2.0,
    zenith=(0.25, 0.45, 0.95),
    horizon=(0.9, 0.95, 1.0),
    ground=(0.25, 0.22, 0.2),
):
    """Radiance (..., 3) of a clear sky in unit directions d (..., 3).

    Sky: horizon colour blending to the zenith colour with sqrt(elevation); ground: constant below the
    horizon; sun: a uniform disc of `sun_radiance` and angular radius `sun_radius_deg` (the defaults
    put ~55-60 % of the sphere's power in the sun, a stiff case for the precomputes). The disc edge is
    anti-aliased over 0.05 degrees so that area-filtered cube maps converge with resolution.
    """
    d = jnp.asarray(d)
    y = d[..., 1:2]
    t = jnp.sqrt(jnp.clip(y, 0.0, 1.0))
    sky = jnp.asarray(horizon, d.dtype) * (1.0 - t) + jnp.asarray(zenith, d.dtype) * t
    col = jnp.where(y > 0.0, sky, jnp.asarray(ground, d.dtype))
    s = jnp.asarray(sun_direction, d.dtype)
    s = s / jnp.linalg.norm(s)
    ang = jnp.arccos(jnp.clip(jnp.sum(d * s, -1, keepdims=True), -1.0, 1.0))
    edge = jnp.clip((math.radians(sun_radius_deg) - ang) / math.radians(0.05) + 0.5, 0.0, 1.0)
    return col + edge * sun_radiance * jnp.asarray((1.0, 0.95, 0.88), d.dtype)


def sky_with_sun_cubemap(face_size: int = 256, *, supersample: int = 4, dtype=jnp.float32, **kwargs) -> Cubemap:
    """`sky_with_sun` as an area-filtered Cubemap (see `Cubemap.from_function`)."""
    try:
        hash(tuple(kwargs.items()))
        named = {"fn": sky_with_sun, "fn_kwargs": kwargs}
    except TypeError:  # (arrays among the values: a program of its own)
        named = {"fn": lambda d: sky_with_sun(d, **kwargs)}
    return Cubemap.from_function(
        face_size=face_size,
        supersample=supersample,
        dtype=dtype,
        info={"environment": "procedural sky_with_sun", **{k: str(v) for k, v in kwargs.items()}},
        **named,
    )
