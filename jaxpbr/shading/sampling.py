"""Point sets and importance sampling for the GGX lobe, the cosine lobe and their densities.

Conventions (docs/math.md §0, §3): directions are sampled in the *tangent frame* of the normal, where
`n = (0, 0, 1)`; `to_world(local, n)` rotates them into world space with `tangent_frame(n)`. A
sample set is `xi`, shape (..., 2), with values in [0, 1]; as in Karis / LearnOpenGL / Filament
`phi = 2 pi xi[..., 0]` and the polar angle comes from `xi[..., 1]`. Roughness enters as the GGX
width `alpha = r^2` (never the perceptual r). Every function is pure, broadcasts over leading axes
and works under `jit`, `vmap` and `grad`; values and gradients stay finite for `alpha = 0` and for
`xi` exactly 0 or 1 (docs/math.md §8.1, §8.3, §8.12).

Densities are with respect to solid angle (1/sr): `pdf_ggx_h` and `pdf_ggx_vndf` in half-vector
space, `pdf_reflect` converts a half-vector density into the density of `l = reflect(v, h)`
(Jacobian `|dh/dl| = 1/(4 v.h)`), `pdf_cosine` is already in direction space.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .._numerics import (
    Vec3,
    as_float,
    eps,
    pack3,
    safe_div,
    safe_sqrt,
    unpack3,
    vcross,
    vdot,
    vnormalize,
)
from .brdf_terms import d_ggx, smith_g1

__all__ = [
    "hammersley",
    "pdf_cosine",
    "pdf_ggx_h",
    "pdf_ggx_vndf",
    "pdf_reflect",
    "radical_inverse",
    "reflect",
    "sample_cosine",
    "sample_ggx_h",
    "sample_ggx_vndf",
    "tangent_frame",
    "to_world",
]

_TWO_PI = 2.0 * math.pi
_INV_PI = 1.0 / math.pi


# --------------------------------------------------------------------------------------------
# Hammersley point set (docs/math.md §3.1, §8.12)
# --------------------------------------------------------------------------------------------


def _bitreverse32(bits: jax.Array) -> jax.Array:
    """Reverse the 32 bits of a uint32 array: swap the 16-bit halves, then bytes, nibbles, pairs,
    single bits (the masks of the Filament doc / LearnOpenGL `RadicalInverse_VdC`)."""
    u = jnp.uint32
    bits = (bits << u(16)) | (bits >> u(16))
    bits = ((bits & u(0x00FF00FF)) << u(8)) | ((bits & u(0xFF00FF00)) >> u(8))
    bits = ((bits & u(0x0F0F0F0F)) << u(4)) | ((bits & u(0xF0F0F0F0)) >> u(4))
    bits = ((bits & u(0x33333333)) << u(2)) | ((bits & u(0xCCCCCCCC)) >> u(2))
    bits = ((bits & u(0x55555555)) << u(1)) | ((bits & u(0xAAAAAAAA)) >> u(1))
    return bits


def radical_inverse(i: jax.Array, dtype=jnp.float32) -> jax.Array:
    """Van der Corput radical inverse in base 2, `Phi_2(i) = bitreverse32(i) * 2^-32`, in [0, 1).

    `i`: integer array (taken modulo 2^32). Returns `dtype`, same shape.

    float32 keeps only the top 24 reversed bits, `(bits >> 8) * 2^-24`: `float32(0xFFFFFFFF *
    2^-32)` rounds to exactly 1.0 (docs/math.md §8.12), and a sample at 1 is 0/0 in the GGX inversion
    at alpha = 0. The dropped bits are bits 24..31 of `i`, so the value is exact for i < 2^24.
    float64 represents all 32 bits exactly.
    """
    bits = _bitreverse32(jnp.asarray(i).astype(jnp.uint32))
    if jnp.dtype(dtype) == jnp.float64:
        return bits.astype(dtype) * (2.0**-32)
    return (bits >> jnp.uint32(8)).astype(dtype) * (2.0**-24)


def hammersley(n: int, dtype=jnp.float32, *, total=None) -> jax.Array:
    """The n-point Hammersley set `x_i = (i / n, Phi_2(i))`, i = 0 .. n-1, shape (n, 2), in [0, 1).

    docs/math.md §3.1 (Filament doc, LearnOpenGL). `n` is static (it is a shape): a positive Python int.
    Column 0 is used as `phi / (2 pi)`, column 1 for the polar angle. With `total` (a number or a
    traced scalar), the first n points of the `total`-point set, `x_i = (i / total, Phi_2(i))`: one
    compiled program serves several point counts (rows i >= total are not points of the set).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n <= 0:
        raise ValueError(f"hammersley: n must be a positive int (the number of points), got {n!r}")
    n = int(n)
    if n >= 2**32:
        raise ValueError(f"hammersley: n must be < 2**32 (the radical inverse uses 32 bits), got {n}")
    i = jnp.arange(n, dtype=jnp.uint32)
    # In float32, i / n rounds up to 1.0 once n > 2^24: clamp to the largest value below 1 so the
    # [0, 1) contract holds for every n.
    below_one = 1.0 - float(jnp.finfo(dtype).epsneg)
    x0 = jnp.minimum(jnp.arange(n, dtype=dtype) / jnp.asarray(n if total is None else total, dtype), below_one)
    return jnp.stack([x0, radical_inverse(i, dtype)], axis=-1)


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------


def _frame_soa(n: Vec3) -> tuple[Vec3, Vec3, Vec3]:
    """(t, b, n_unit) for a Vec3 normal; see `tangent_frame`."""
    n = vnormalize(n)
    # docs/math.md §8.13 (Karis / LearnOpenGL / Filament): cross with the +Z axis unless n is within
    # ~2.6 degrees of it, else with +X. |cross(up, n)| >= sqrt(1 - 0.999^2) = 0.045 on the branch
    # that is kept, so the normalisation is well conditioned; vnormalize guards the branch that is
    # evaluated but discarded (e.g. cross(Z, Z) = 0), so its gradient cannot leak NaN.
    use_z = jnp.abs(n[2]) < 0.999
    zero = jnp.zeros_like(n[0])
    t_z = vnormalize((-n[1], n[0], zero))  # cross((0, 0, 1), n)
    t_x = vnormalize((zero, -n[2], n[1]))  # cross((1, 0, 0), n)
    t = tuple(jnp.where(use_z, a, b) for a, b in zip(t_z, t_x))
    b = vcross(n, t)
    return t, b, n


def tangent_frame(n: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Right-handed orthonormal tangent frame `(t, b)` of a normal: `t x b = n`.

    Args:
      n: (..., 3) normal (normalised here; a zero vector gives zero vectors).
    Returns:
      `t, b`, each (..., 3), unit and orthogonal to each other and to n.

    `t = normalize(cross(up, n))`, `b = cross(n, t)` with `up = (0,0,1)` if `|n.z| < 0.999` else
    `(1,0,0)` (docs/math.md §8.13): a fixed `up` is NaN when n is parallel to it (LearnOpenGL's
    `up = (0,1,0)` fails at n = +-Y). Finite, with finite gradients, at n = +-X, +-Y, +-Z.
    """
    t, b, _ = _frame_soa(unpack3(as_float(n)))
    return pack3(t), pack3(b)


def to_world(local: jax.Array, n: jax.Array) -> jax.Array:
    """Rotate tangent-frame vectors into world space: `local.x t + local.y b + local.z n`.

    `local`: (..., 3) in the frame of `tangent_frame(n)` (where n is +Z); `n`: (..., 3) normal.
    Returns (..., 3); lengths are preserved.
    """
    t, b, nn = _frame_soa(unpack3(as_float(n)))
    x, y, z = unpack3(as_float(local))
    return pack3(tuple(x * ti + y * bi + z * ni for ti, bi, ni in zip(t, b, nn)))


def reflect(v: jax.Array, h: jax.Array) -> jax.Array:
    """Mirror direction `l = 2 (v.h) h - v`, (..., 3); v points away from the surface."""
    vv, hh = unpack3(as_float(v)), unpack3(as_float(h))
    d = 2.0 * vdot(vv, hh)
    return pack3(tuple(d * hi - vi for vi, hi in zip(vv, hh)))


# --------------------------------------------------------------------------------------------
# GGX NDF sampling (docs/math.md §3.2)
# --------------------------------------------------------------------------------------------


def _unit_xi(xi):
    """Split (..., 2) samples into two planes, clamped to [0, 1]: a value a rounding step outside
    the unit square would make `cos^2` or `sin^2` negative."""
    xi = as_float(xi)
    return jnp.clip(xi[..., 0], 0.0, 1.0), jnp.clip(xi[..., 1], 0.0, 1.0)


def sample_ggx_h(xi: jax.Array, alpha: jax.Array) -> jax.Array:
    """Half vector h distributed as `D(h) (n.h)` (GGX NDF sampling), in the tangent frame, (..., 3).

    Args:
      xi: (..., 2) uniform samples in [0, 1] (e.g. `hammersley`); sets the dtype.
      alpha: GGX width `r^2`, broadcasting with `xi[..., 0]`; alpha = 0 gives h = (0, 0, 1).

    Walter 2007 / Karis 2013 (docs/math.md §3.2):
      `phi = 2 pi xi0`, `cos^2 = (1 - xi1) / d`, `sin^2 = alpha^2 xi1 / d`, `d = (1 - xi1) + alpha^2 xi1`.
    `sin` comes from its own formula, not `sqrt(1 - cos^2)`: in float32 at r = 0.02 the latter is
    exactly 0 for xi1 <= 0.01 (true 4e-6 .. 4e-5, docs/math.md §8.3). `d` is written without the
    `1 + (alpha^2 - 1) xi1` cancellation. Density: `pdf_ggx_h`.
    """
    x0, x1 = _unit_xi(xi)
    a2 = jnp.asarray(alpha, x0.dtype) ** 2
    d = (1.0 - x1) + a2 * x1
    # d = 0 only at alpha = 0 and xi1 = 1 (0/0): the lobe is a delta there, so h = n. Double
    # where: the division sees a benign 1, so its gradient is finite on that lane too.
    ok = d > 0
    inv = safe_div(1.0, d, ok)
    cos_t = jnp.where(ok, safe_sqrt((1.0 - x1) * inv), 1.0)
    sin_t = safe_sqrt(a2 * x1 * inv)
    phi = _TWO_PI * x0
    return pack3((sin_t * jnp.cos(phi), sin_t * jnp.sin(phi), cos_t))


def pdf_ggx_h(n_dot_h: jax.Array, alpha: jax.Array) -> jax.Array:
    """Density of `sample_ggx_h` over half-vector solid angle: `p_h = D(h) (n.h)`, in 1/sr, (...).

    docs/math.md §3.2. Zero for n.h <= 0. At alpha = 0 the distribution is a delta at h = n: the
    density is +inf at n.h = 1 and 0 elsewhere (the value `1 / (N p)` of a PDF-based LOD then
    clamps to the finest level), with zero gradient.
    """
    nh = as_float(n_dot_h)
    alpha = jnp.asarray(alpha, nh.dtype)
    delta = alpha <= 0
    # Double where: D's 0/0 at alpha = 0 must not be evaluated on the delta lanes.
    a_safe = jnp.where(delta, 1.0, alpha)
    p = d_ggx(nh, a_safe) * jnp.maximum(nh, 0.0)
    return jnp.where(delta, jnp.where(nh >= 1.0, jnp.inf, 0.0), p)


def pdf_reflect(pdf_h: jax.Array, v_dot_h: jax.Array) -> jax.Array:
    """Density of `l = reflect(v, h)` from the density of h: `p_l = p_h / (4 v.h)`, (...).

    docs/math.md §3.2 (Jacobian `|dh/dl| = 1 / (4 v.h)`). Zero where v.h <= 0 (that h reflects v
    into the surface, the sample is discarded). Where `p_h` is inf (alpha = 0) so is `p_l`.
    """
    vh = as_float(v_dot_h)
    ok = vh > 0
    return safe_div(pdf_h, 4.0 * vh, ok)


# --------------------------------------------------------------------------------------------
# VNDF sampling (Heitz 2018)
# --------------------------------------------------------------------------------------------


def sample_ggx_vndf(v_local: jax.Array, xi: jax.Array, alpha: jax.Array) -> jax.Array:
    """Half vector h distributed as the GGX *visible* normals of v: `G1(v) max(0, v.h) D(h) / n.v`.

    Heitz 2018, "Sampling the GGX Distribution of Visible Normals" (JCGT 7(4)), isotropic alpha:
    stretch `v_h = normalize(alpha v.x, alpha v.y, v.z)`, sample the projected hemisphere
    (`r = sqrt(xi0)`, `phi = 2 pi xi1`, `s = (1 + v_h.z)/2`, `t2 = (1 - s) sqrt(1 - t1^2) + s t2`),
    unstretch `h = normalize(alpha n_h.x, alpha n_h.y, max(1e-6, n_h.z))` (docs/math.md §3.2; note this
    sampler takes the radius from xi0, following the paper).

    Args:
      v_local: (..., 3) unit view direction in the tangent frame, `v.z > 0` (for v.z <= 0 the
        result is finite but not meaningful).
      xi: (..., 2) uniform samples in [0, 1]; alpha: GGX width, broadcasting. alpha = 0 gives h = n.
    Returns (..., 3) unit h with h.z > 0. Density: `pdf_ggx_vndf`; the estimator weight of
    `f (n.l) / p_l` is `F G2 / G1(v)` (bounded by 1 times F).
    """
    x0, x1 = _unit_xi(xi)
    v = unpack3(as_float(v_local))
    alpha = jnp.asarray(alpha, x0.dtype)
    vh = vnormalize((alpha * v[0], alpha * v[1], v[2]))
    # Basis around v_h. At normal incidence (or alpha = 0) v_h = +Z and the azimuth is arbitrary:
    # T1 = +X there (Heitz). Below |(v_h.x, v_h.y)| = eps that azimuth is rounding noise and the
    # derivative of x / |x| ~ 1/|x| would overflow, so the same fallback is used; the double
    # where keeps rsqrt away from 0 (value and gradient).
    lensq = vh[0] * vh[0] + vh[1] * vh[1]
    ok = lensq > eps(lensq.dtype) ** 2
    inv = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, lensq, 1.0)), 0.0)
    zero = jnp.zeros_like(lensq)
    t1v = (jnp.where(ok, -vh[1] * inv, 1.0), jnp.where(ok, vh[0] * inv, 0.0), zero)
    t2v = vcross(vh, t1v)
    rad = safe_sqrt(x0)
    phi = _TWO_PI * x1
    t1 = rad * jnp.cos(phi)
    t2 = rad * jnp.sin(phi)
    s = 0.5 * (1.0 + vh[2])
    t2 = (1.0 - s) * safe_sqrt(1.0 - t1 * t1) + s * t2
    # safe_sqrt: 1 - t1^2 - t2^2 is 0 on the rim of the disc (and a rounding step below it).
    tz = safe_sqrt(1.0 - t1 * t1 - t2 * t2)
    nh = tuple(t1 * a + t2 * b + tz * c for a, b, c in zip(t1v, t2v, vh))
    # max(1e-6, .): on the rim n_h.z = 0 and h would be horizontal (or the zero vector at
    # alpha = 0); Heitz's clamp keeps h strictly in the upper hemisphere.
    h = vnormalize((alpha * nh[0], alpha * nh[1], jnp.maximum(nh[2], 1e-6)))
    return pack3(h)


def pdf_ggx_vndf(n_dot_v: jax.Array, n_dot_h: jax.Array, v_dot_h: jax.Array, alpha: jax.Array) -> jax.Array:
    """Density of `sample_ggx_vndf` over half-vector solid angle, (...), in 1/sr:

    `p_h = G1(v) max(0, v.h) D(h) / (n.v)` (Heitz 2018; docs/math.md §3.2), with the Smith G1 of GGX.
    It integrates to 1 over h for every v with n.v > 0 (docs/math.md §7.1). Zero for n.v <= 0 or
    n.h <= 0; alpha = 0 gives the delta (inf at n.h = 1, else 0) as in `pdf_ggx_h`. For the
    density of `l = reflect(v, h)` use `pdf_reflect` (giving `G1(v) D / (4 n.v)`).
    """
    nv = as_float(n_dot_v)
    nh = jnp.asarray(n_dot_h, nv.dtype)
    vh = jnp.asarray(v_dot_h, nv.dtype)
    alpha = jnp.asarray(alpha, nv.dtype)
    delta = alpha <= 0
    a_safe = jnp.where(delta, 1.0, alpha)
    ok = nv > 0
    nv_safe = jnp.where(ok, nv, 1.0)  # double where: no 0/0 on the lanes that are masked
    p = smith_g1(nv_safe, a_safe) * jnp.maximum(vh, 0.0) * d_ggx(nh, a_safe) / nv_safe
    p = jnp.where(delta, jnp.where(nh >= 1.0, jnp.inf, 0.0), p)
    return jnp.where(ok, p, 0.0)


# --------------------------------------------------------------------------------------------
# Cosine-weighted hemisphere
# --------------------------------------------------------------------------------------------


def sample_cosine(xi: jax.Array) -> jax.Array:
    """Direction distributed as `cos(theta) / pi` on the upper hemisphere (tangent frame), (..., 3).

    Malley's method: `phi = 2 pi xi0`, `sin^2 = xi1`, `cos = sqrt(1 - xi1)`; unit length exactly
    up to rounding, finite at xi = 0 and 1 (safe_sqrt: zero gradient at the endpoints).
    """
    x0, x1 = _unit_xi(xi)
    sin_t = safe_sqrt(x1)
    cos_t = safe_sqrt(1.0 - x1)
    phi = _TWO_PI * x0
    return pack3((sin_t * jnp.cos(phi), sin_t * jnp.sin(phi), cos_t))


def pdf_cosine(n_dot_l: jax.Array) -> jax.Array:
    """Density of `sample_cosine`: `max(0, n.l) / pi`, in 1/sr, (...)."""
    return jnp.maximum(as_float(n_dot_l), 0.0) * _INV_PI
