"""The KHR_materials_sheen lobe: the "Charlie" fibre distribution and its visibility term.

Conty Estevez & Kulla 2017 ("Production Friendly Microfacet Sheen BRDF"), as KHR_materials_sheen
writes it (Implementation Notes), with `alpha = sheen_roughness^2`:

    D_c(h)   = (2 + 1/alpha) sin(theta_h)^(1/alpha) / (2 pi),        sin^2 = 1 - (n.h)^2
    V_c(v,l) = 1 / ((1 + Lambda(n.v) + Lambda(n.l)) 4 (n.v)(n.l))
    Lambda(mu) = exp(L(mu))                        mu < 0.5
               = exp(2 L(0.5) - L(1 - mu))         mu >= 0.5
    L(x) = a / (1 + b x^c) + d x + e,   (a..e) = lerp(P0, P1, (1 - alpha)^2)

    f_sheen = sheen_color * D_c V_c,
    base    *= sheen_albedo_scaling = min(1 - max3(sheen_color) E(n.v), 1 - max3(sheen_color) E(n.l))

where E(mu) = int D_c V_c (n.l) dl is the sheen lobe's directional albedo (`jaxpbr.shading.sheen_lut`).

Stiff cases. alpha -> 0 makes D a delta at theta_h = 90 deg (`pow(sin^2, 1/(2 alpha))` is 0^inf or
1^inf); sheen roughness is floored like the base roughness (`floored_sheen_roughness`, the same
`min_roughness`, Filament's MIN_PERCEPTUAL_ROUGHNESS), and D is evaluated in the log domain,
`exp(log(sin^2) / (2 alpha))`, with sin^2 floored at the smallest normal so that its gradient is
finite where sin = 0 (n.h = 1: D = 0 to float precision for every alpha < 1, and d/d alpha = 0).
`x^c` in L has an infinite derivative at x = 0 (mu = 0 or mu = 1, c ~ 0.17-0.2): it is evaluated
as exp(c log x) on x > 0 and set to its value 0 at x = 0 by a double where, so the value is exact
and the gradient there is 0 instead of inf * 0 = NaN. (Flooring x would not do: x^c is 0.08 at
x = 1e-6, so L would move by ~6.)
E (the sheen albedo) exceeds 1 at grazing views for small sheen roughness (up to 4.4 at r = 0.045,
n.v = 1/512: the fitted visibility is not energy conserving there, `jaxpbr.shading.sheen_lut`), so
`sheen_albedo_scaling` is clamped at 0: the base layer is never subtracted.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

__all__ = [
    "SHEEN_FIT",
    "d_charlie",
    "floored_sheen_roughness",
    "lambda_sheen",
    "max3",
    "sheen_albedo_scaling",
    "v_ashikhmin",
    "v_charlie",
]

#: Conty Estevez & Kulla's fit of the Charlie Lambda: L(x) = a/(1 + b x^c) + d x + e, each
#: coefficient lerp(alpha=1 value, alpha=0 value, (1 - alpha)^2) (KHR_materials_sheen).
SHEEN_FIT = {
    "a": (21.5473, 25.3245),
    "b": (3.82987, 3.32435),
    "c": (0.19823, 0.16801),
    "d": (-1.97760, -1.27393),
    "e": (-4.32054, -4.85967),
}

_INV_2PI = 1.0 / (2.0 * math.pi)


def floored_sheen_roughness(r, min_roughness: float):
    """clip(sheen_roughness, min_roughness, 1): alpha = r^2 > 0, so D_c is a function, not a delta."""
    return jnp.clip(r, min_roughness, 1.0)


def d_charlie(n_dot_h, alpha, sin2_h=None):
    """Charlie NDF `(2 + 1/alpha) sin(theta_h)^(1/alpha) / (2 pi)`, normalised so that
    int D (n.h) dh = 1 over the hemisphere. `sin2_h = 1 - (n.h)^2` may be passed exactly
    (|n x h|^2). alpha > 0 (floor it, `floored_sheen_roughness`). Zero for n.h <= 0."""
    if sin2_h is None:
        sin2_h = 1.0 - n_dot_h * n_dot_h
    tiny = jnp.finfo(jnp.result_type(sin2_h, float)).tiny
    inv_a = 1.0 / alpha
    s2 = jnp.maximum(sin2_h, tiny)
    d = (2.0 + inv_a) * jnp.exp(0.5 * inv_a * jnp.log(s2)) * _INV_2PI
    return jnp.where((n_dot_h > 0) & (sin2_h > 0), d, 0.0)


def _l_fit(x, alpha):
    t = (1.0 - alpha) ** 2
    a, b, c, d, e = (p0 + (p1 - p0) * t for p0, p1 in SHEEN_FIT.values())
    pos = x > 0
    xc = jnp.where(pos, jnp.exp(c * jnp.log(jnp.where(pos, x, 1.0))), 0.0)
    return a / (1.0 + b * xc) + d * x + e


def lambda_sheen(mu, alpha):
    """Charlie Lambda(mu) (the spec's `lambda_sheen`, mu = |cos theta| in [0, 1])."""
    mu = jnp.abs(mu)
    low = jnp.exp(_l_fit(mu, alpha))
    high = jnp.exp(2.0 * _l_fit(0.5, alpha) - _l_fit(1.0 - mu, alpha))
    return jnp.where(mu < 0.5, low, high)


def v_charlie(n_dot_v, n_dot_l, alpha):
    """Charlie visibility `1 / ((1 + Lambda(n.v) + Lambda(n.l)) 4 (n.v)(n.l))`, for n.v, n.l > 0."""
    return 1.0 / ((1.0 + lambda_sheen(n_dot_v, alpha) + lambda_sheen(n_dot_l, alpha)) * (4.0 * n_dot_v * n_dot_l))


def v_ashikhmin(n_dot_v, n_dot_l):
    """Ashikhmin & Premoze visibility `1 / (4 (n.l + n.v - n.l n.v))` (the spec's cheap option;
    not energy conserving with albedo scaling). Provided for comparison only."""
    return 0.25 / (n_dot_l + n_dot_v - n_dot_l * n_dot_v)


def max3(c: jax.Array) -> jax.Array:
    """max over the trailing RGB axis."""
    return jnp.max(c, axis=-1)


def sheen_albedo_scaling(sheen_color, e_v, e_l=None):
    """`min(1 - max3(sheen_color) E(n.v), 1 - max3(sheen_color) E(n.l))` (KHR_materials_sheen);
    with `e_l` None, the view-only form `1 - max3(sheen_color) E(n.v)` used for the IBL term.
    Clamped at 0 (E > 1 at grazing views for small roughness, see the module docstring)."""
    m = max3(sheen_color)
    s = 1.0 - m * e_v
    if e_l is not None:
        s = jnp.minimum(s, 1.0 - m * e_l)
    return jnp.maximum(s, 0.0)
