"""Bilinear interpolation: the one sampler behind textures, equirect panoramas, the BRDF LUT and
the cube-map pyramid.

Coordinates are *continuous texel coordinates*: texel (i, j) of an (H, W, C) image has its centre
at (x, y) = (j, i), so a normalised coordinate u maps to x = u * W - 0.5. Each axis either wraps
(repeat: texture u/v, equirect longitude) or clamps to the edge (LUT axes, equirect latitude);
clamping is done on the *indices*, so outside the centre range the edge texel is returned and the
derivative with respect to the coordinate is 0 (not NaN).

Why one core: the four samplers differed only in index handling and in how they wrote the lerp;
`a + (b - a) * t` is the form used everywhere because it reproduces a constant image exactly
(b - a = 0), which the white-furnace and constant-environment tests rely on, and is exact at t = 0.
The floor is taken of `stop_gradient(x)`: the integer part has no derivative, the fraction carries
all of it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["bilinear", "interp_nodes", "interp_uniform", "lerp", "lerp2", "split_coordinate"]


def lerp(a, b, t):
    """a + (b - a) t: exact at t = 0 and for a == b (constant-preserving)."""
    return a + (b - a) * t


def lerp2(v00, v01, v10, v11, fx, fy):
    """Bilinear blend of four corner values (..., C) with fractions fx (along the row, v00 -> v01)
    and fy (across rows, v00 -> v10), each (...)."""
    fx = fx[..., None]
    fy = fy[..., None]
    return lerp(lerp(v00, v01, fx), lerp(v10, v11, fx), fy)


def split_coordinate(x):
    """Continuous coordinate -> (integer part as int32, fraction in [0, 1)); the gradient flows
    through the fraction only."""
    x0 = jnp.floor(jax.lax.stop_gradient(x))
    return x0.astype(jnp.int32), x - x0


def _index(i, n: int, wrap: bool):
    return jnp.mod(i, n) if wrap else jnp.clip(i, 0, n - 1)


def bilinear(img, x, y, *, wrap_x: bool = False, wrap_y: bool = False):
    """Bilinear lookup of an (H, W, C) image at continuous texel coordinates x (column), y (row),
    broadcasting arrays -> broadcast shape + (C,). Each axis repeats (`wrap_*=True`) or clamps to
    the edge. Differentiable in the texels and in x, y."""
    H, W = img.shape[0], img.shape[1]
    x, y = jnp.broadcast_arrays(x, y)
    j0, fx = split_coordinate(x)
    i0, fy = split_coordinate(y)
    ja, jb = _index(j0, W, wrap_x), _index(j0 + 1, W, wrap_x)
    ia, ib = _index(i0, H, wrap_y), _index(i0 + 1, H, wrap_y)
    return lerp2(img[ia, ja], img[ia, jb], img[ib, ja], img[ib, jb], fx, fy)


def interp_uniform(x, x_first: float, x_last: float, table):
    """`jnp.interp(x, linspace(x_first, x_last, n), table)` for a table of n >= 2 values on a
    uniform grid, clamped to the end values outside it: the segment comes from x's position on
    the grid, not from a search (`jnp.interp`'s `searchsorted` is a loop and a gather per call,
    about 0.1 s of XLA:CPU compile time at 1280x720). Differentiable in x (slope of the segment)
    and in the table."""
    table = jnp.asarray(table)
    n = table.shape[0]
    dt = jnp.result_type(x, table.dtype, float)
    u = (x - x_first) * ((n - 1) / (x_last - x_first))
    i0 = jnp.clip(jnp.floor(jax.lax.stop_gradient(u)), 0, n - 2)
    i = i0.astype(jnp.int32)
    tab = table.astype(dt)
    # (the ends as jnp.interp takes them: the segment's slope at a node, no clamp's half slope)
    return jnp.where(u < 0, tab[0], jnp.where(u > n - 1, tab[n - 1], lerp(tab[i], tab[i + 1], u - i0)))


def interp_nodes(x, nodes, values):
    """`jnp.interp(x, nodes, values)` for a short, increasing, static list of nodes (NumPy, n >= 2):
    the segment is counted from comparisons and its ends picked by selects (no search, no gather:
    XLA:CPU keeps the loop vectorised). Clamped to the end values outside the nodes; exact at the
    nodes. Differentiable in x."""
    nodes = np.asarray(nodes, np.float64)
    values = np.asarray(values, np.float64)
    dt = jnp.result_type(x, float)
    k = sum((x >= nodes[j]).astype(jnp.int32) for j in range(1, len(nodes) - 1))  # segment 0..n-2
    x0, x1, f0, f1 = (jnp.zeros_like(x, dt) for _ in range(4))
    for j in range(len(nodes) - 1):
        at = k == j
        x0, x1 = jnp.where(at, nodes[j], x0), jnp.where(at, nodes[j + 1], x1)
        f0, f1 = jnp.where(at, values[j], f0), jnp.where(at, values[j + 1], f1)
    span = x1 - x0  # (> 0 but between repeated nodes, where x never selects the segment: no 0/0 in a gradient)
    inside = lerp(f0, f1, (x - x0) / jnp.where(span > 0, span, 1.0))
    return jnp.where(x < nodes[0], values[0], jnp.where(x > nodes[-1], values[-1], inside)).astype(dt)
