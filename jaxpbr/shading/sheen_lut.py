"""The Charlie sheen directional albedo E (KHR_materials_sheen): converged tables, a float64
reference, lookup.

Definition. For a unit normal n, a view direction v with `mu = n.v` and the sheen lobe of
`jaxpbr.shading.sheen` (Charlie NDF D_c, Charlie visibility V_c with the Conty-Kulla Lambda fit),

    E(mu, r) = int_{H^2} D_c(h) V_c(v, l) (n.l) dl,    alpha = max(r, 0.045)^2,

r the perceptual sheen roughness, floored at `brdf_terms.MIN_ROUGHNESS` like everywhere else.
E is two things at once: the directional albedo of the sheen lobe in the albedo scaling of the
layer below, `1 - max3(sheen_color) E` (KHR_materials_sheen), and the split-sum weight of the
sheen IBL term, `LD_charlie(n, r) * sheen_color * E(mu, r)`: the sheen lobe has no Fresnel
factor, so the split-sum "DG" integral `int D_c V_c (n.l) dl` is the same integral as E (the GGX
LUT needs two channels A, B for F0 and F90; the sheen table needs one).

E is NOT bounded by 1. The Charlie visibility (a fitted Lambda, not a microfacet-consistent one)
is not energy conserving at grazing view for narrow lobes: E reaches 4.37 at NoV = 1/512,
r = 0.045 (texel [0, 0] of a 256^2 table; 4.14 at [0, 0] of 128^2), and exceeds 1 in the corner
r < 0.256, NoV < 0.053 (NoV < 0.049 at the floor, < 0.053 at r ~ 0.065, only the first column at
r = 0.25); for r >= 0.26 and everywhere at NoV >= 0.055 it is < 1 (measured with
`sheen_lut_reference` at every texel centre of 128^2 and 256^2 tables, and confirmed by an
independent Monte Carlo estimate, `tests/test_sheen_lut.py`). The albedo scaling
`1 - max3(sheen_color) E` is then negative in that corner. As mu -> 0 the
integrand's 1/mu is not cancelled (Lambda(mu) stays finite), so E has no limit there; the
lookup clamps NoV to the first texel centre.

Layout (as the GGX LUT, `jaxpbr.shading.lut`): shape `(n_roughness, n_nov)`, element `[j, i]` at
`r = (j + 0.5) / n_roughness`, `NoV = (i + 0.5) / n_nov`; rows whose r is below the floor hold
E at the floor. `sheen_lut_lookup` is bilinear between texel centres and clamps to the edge.
In EXR files (`jaxpbr/_luts/sheen_lut_*.exr`): R = E, G = B = 0, image row j (row 0 at the top).

`compute_sheen_lut` is a deterministic product Gauss-Legendre rule in half-vector space (see the
notes above `_sheen_row`): 4 m^2 nodes per texel; with the default 784 (m = 14) every texel of a
128^2 and of a 256^2 table is within 1.3e-6 of `sheen_lut_reference` (float32).
`sheen_lut_reference` is an independent float64 NumPy construction (light-direction variables,
other integration order, composite graded rule, its own D and Lambda), converged to ~1e-9
(checked by refinement, against scipy and against Monte Carlo in the tests).
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .._interp import bilinear
from .._numerics import map_row_chunks, progress_token, row_chunk_count
from .._validate import positive_int
from .brdf_terms import MIN_ROUGHNESS
from .lut import _gauss_legendre_01, _phi_lines
from .sheen import SHEEN_FIT, floored_sheen_roughness, lambda_sheen

__all__ = [
    "DEFAULT_SAMPLES",
    "LOOKUP_MIN_NOV",
    "compute_sheen_lut",
    "sheen_lut_error",
    "sheen_lut_lookup",
    "sheen_lut_reference",
]

#: Default quadrature nodes per texel of `compute_sheen_lut`: 4 m^2 with order m = 14. Chosen from
#: the measured error against `sheen_lut_reference` at every texel of a 128^2 / 256^2 table
#: (float32 tables, max abs error / mean abs error):
#:   m =  8 (256 nodes): 8.6e-5 / 8.6e-7   and 1.1e-4 / 8.8e-7
#:   m = 10 (400 nodes): 5.9e-6 / 3.0e-7   and 9.4e-6 / 3.1e-7
#:   m = 12 (576 nodes): 2.2e-6 / 1.6e-7   and 2.2e-6 / 1.6e-7
#:   m = 14 (784 nodes): 1.3e-6 / 9.7e-8   and 1.2e-6 / 9.8e-8
#:   m = 16 (1024 nodes): 9.6e-7 / 6.7e-8  and 8.2e-7 / 6.7e-8
#:   m = 20 (1600 nodes, float64 nodes): 2.8e-7 / 2.5e-8 and 2.9e-7 / 2.6e-8
#: 784 has an 80x margin under the 1e-4 target (the GGX LUT's default has 70x); the error decays
#: algebraically beyond (the Lambda fit's kink at n.l = 1/2 and cusp at n.l = 1 lie inside the
#: theta pieces). A 256^2 table takes ~1.5-3 s on one CPU core.
DEFAULT_SAMPLES = 4 * 14**2

#: `sheen_lut_lookup` clamps NoV to [LOOKUP_MIN_NOV, 1] (E has no limit at NoV = 0).
LOOKUP_MIN_NOV = 1e-4

_PI = math.pi


def _sheen_shape(size) -> tuple[int, int]:
    fix = "pass an int such as 128, or a pair (n_roughness, n_nov) such as (64, 128)"
    if isinstance(size, (tuple, list)):
        if len(size) != 2:
            raise ValueError(f"compute_sheen_lut: size must be an int or a pair, got {size!r}; {fix}")
        return tuple(positive_int("size", s, where="compute_sheen_lut", fix=fix) for s in size)
    n = positive_int("size", size, where="compute_sheen_lut", fix=fix)
    return n, n


def _order_from_samples(samples: int) -> int:
    """Gauss-Legendre order m of the sheen rule: 4 m^2 nodes, the most that fit in `samples`."""
    return max(1, math.isqrt(samples // 4))


# ============================================================================================
# compute_sheen_lut: the fast, converged rule
# ============================================================================================
#
# Geometry (as `jaxpbr.shading.lut`). n = +z, v = (s_v, 0, mu), h = (sin t cos p, sin t sin p, cos t),
# dl = 4 (v.h) dw_h, so with V_c (n.l) = 1 / ((1 + Lambda(mu) + Lambda(n.l)) 4 mu):
#
#     E = 2 int_0^pi dp int D_c(t) (v.h) sin t / (mu (1 + Lambda(mu) + Lambda(n.l))) dt.
#
# l is above the horizon for t < t_max(p) (`lut._phi_lines`: 2m phi lines per column, graded
# towards p = pi/2 at the grazing scale 2 mu / s_v; they give R and t_max per line), and
# n.l = R sin(2 (t_max - t)). The Charlie lobe lives at t ~ pi/2 (h near the horizon): with
# delta = pi/2 - t it is (2 + 1/alpha)/(2 pi) cos(delta)^(1/alpha) ~ exp(-delta^2 / (2 alpha)), a
# Gaussian of width sqrt(alpha) centred *outside* the visible range delta >= delta_min =
# pi/2 - t_max. So each line is integrated in u = delta - delta_min from the horizon inwards:
#
# * u in [0, u_A] ("horizon piece"): u = w (e^y - 1), y uniform (Gauss-Legendre), w =
#   min(mu, 0.02) / (2R). 1/(1 + Lambda(mu) + Lambda(n.l)) switches on over n.l ~ mu (Lambda(x)
#   grows like ~1/x towards the horizon, smooth in log x), so the nodes are log-spaced from that
#   scale. u_A = min(u at n.l = 1/2, u_cut, 2 alpha / (delta_min + sqrt(alpha))): the Lambda fit
#   switches branches at n.l = 1/2 (a jump of the second derivative; splitting there took the
#   error of a 24-node line from 1.8e-6 to 3e-8), and the head of the Gaussian (the decay length
#   alpha / (delta_min + sqrt(alpha))) belongs to the graded piece.
# * u in [u_A, u_cut] ("body"): plain Gauss-Legendre. u_cut is where D has fallen to 1e-13 of
#   its value at delta_min (closed form: cos(delta_min + u) = cos(delta_min) 1e-13^alpha), or
#   t = 0.
# Both pieces use m nodes and the phi lines 2m: 4 m^2 nodes per texel.
#
# D in the log domain: log sin^2(theta_h) = log1p(-sin^2 delta) (accurate near the lobe's peak,
# where 1 - sin^2 would lose the digits that 1/(2 alpha) ~ 250 amplifies) or 2 log cos delta
# (delta >= pi/4). Lambda is `jaxpbr.shading.sheen.lambda_sheen`, the one the shading code uses.
#
# Precision: per-line quantities are float64; the integrand at the nodes is evaluated in
# `node_dtype` (float32 for a float32 table; measured effect ~1e-7) and summed in float64.

_CUT = 1e-13  # D relative to its line maximum where the body piece ends
_HORIZON_NL = 0.02  # the horizon scale in n.l: min(mu, this)
_HEAD = 2.0  # the graded piece covers this many decay lengths of the Gaussian


def _sheen_row(r, mu, lines, m: int, node_dtype):
    """E for one (floored) roughness r (scalar) at all columns mu (n_nov,) -> (n_nov,) float64."""
    cos_p, w_phi, radius, t_max = lines  # (n_nov, 2m) each, float64
    f64 = jnp.float64
    alpha = r * r
    mu_l = mu[:, None]
    s_v = jnp.sqrt(1.0 - mu_l * mu_l)
    d_min = 0.5 * _PI - t_max
    lam_v = lambda_sheen(mu_l, alpha)
    sqrt_a = jnp.sqrt(alpha)

    u_cut = jnp.minimum(t_max, jnp.arccos(jnp.cos(d_min) * _CUT**alpha) - d_min)
    u_half = 0.5 * jnp.arcsin(jnp.minimum(0.5 / radius, 1.0))  # n.l = 1/2 (or the top of the line)
    u_a = jnp.minimum(jnp.minimum(u_half, u_cut), _HEAD * alpha / (d_min + sqrt_a))
    w = jnp.minimum(jnp.minimum(mu_l, _HORIZON_NL) / (2.0 * radius), u_a)
    y_a = jnp.log1p(u_a / w)

    x, wx = (jnp.asarray(a, node_dtype) for a in _gauss_legendre_01(m))
    zero = jnp.zeros_like(cos_p)
    c = lambda a: (a + zero).astype(node_dtype)[..., None]  # line quantity -> (n_nov, 2m, 1)
    alpha_n = jnp.asarray(alpha, node_dtype)
    mu_n, s_v_n, cos_p_n, rad_n, d_min_n, lam_v_n = c(mu_l), c(s_v), c(cos_p), c(radius), c(d_min), c(lam_v)
    norm = (2.0 + 1.0 / alpha_n) / (2.0 * _PI)

    def line_sum(u, du):
        d = d_min_n + u
        sin_d, cos_d = jnp.sin(d), jnp.maximum(jnp.cos(d), 0.0)
        log_s2 = jnp.where(d < 0.25 * _PI, jnp.log1p(-sin_d * sin_d), 2.0 * jnp.log(cos_d))
        dd = norm * jnp.exp(log_s2 * (0.5 / alpha_n))
        v_dot_h = s_v_n * cos_d * cos_p_n + mu_n * sin_d
        n_dot_l = rad_n * jnp.sin(2.0 * u)
        g = 1.0 / (1.0 + lam_v_n + lambda_sheen(n_dot_l, alpha_n))
        return jnp.sum((dd * v_dot_h * cos_d * g * du).astype(f64), axis=-1)

    ey = jnp.exp(c(y_a) * x)
    s = line_sum(c(w) * (ey - 1.0), c(w * y_a) * ey * wx)
    s = s + line_sum(c(u_a) + c(u_cut - u_a) * x, c(u_cut - u_a) * wx)
    return jnp.sum(s * (2.0 * w_phi), axis=-1) / mu  # 2: phi symmetry


@partial(jax.jit, static_argnames=("n_r", "n_nov", "m", "node_dtype", "rows_per_chunk"))
def _sheen_fast(token, *, n_r, n_nov, m, node_dtype, rows_per_chunk):
    mu = (jnp.arange(n_nov, dtype=jnp.float64) + 0.5) / n_nov
    r = jnp.maximum((jnp.arange(n_r, dtype=jnp.float64) + 0.5) / n_r, MIN_ROUGHNESS)
    lines = _phi_lines(mu, m)
    row = partial(_sheen_row, mu=mu, lines=lines, m=m, node_dtype=node_dtype)
    return map_row_chunks(jax.vmap(row), rows_per_chunk, r, token=token)


def compute_sheen_lut(size=128, *, samples: int = DEFAULT_SAMPLES, dtype=jnp.float32, progress=None) -> jax.Array:
    """The sheen albedo table E, converged to the float64 reference (see the module docstring).

    Args:
      size: int n for an n x n table, or a pair `(n_roughness, n_nov)`.
      samples: integrand evaluations per texel; the deterministic Gauss-Legendre rule uses
        4 m^2 of them with m = max(1, floor(sqrt(samples / 4))). Default `DEFAULT_SAMPLES` = 784
        (max abs error 1.3e-6 at every texel of 128^2 and 256^2).
      dtype: output dtype (float32 or float64). The rule sums in float64 either way; float32
        evaluates the integrand at the nodes in float32 (~1e-7 effect), float64 in float64.
      progress: optional callable(done, total) in groups of rows (as `compute_brdf_lut`).

    Returns:
      (n_roughness, n_nov) array; `[j, i]` holds E at `r = max((j + 0.5)/n_roughness, 0.045)`,
      `NoV = (i + 0.5)/n_nov`.

    Compiles once per (size, samples, dtype) (~2 s); a 128^2 table then takes ~0.5 s, 256^2
    ~1.5-3 s on one CPU core.
    """
    n_r, n_nov = _sheen_shape(size)
    samples = positive_int("samples", samples, where="compute_sheen_lut", fix=f"the default is {DEFAULT_SAMPLES}")
    dtype = jnp.dtype(dtype)
    if dtype not in (jnp.dtype(jnp.float32), jnp.dtype(jnp.float64)):
        raise ValueError(f"compute_sheen_lut: dtype must be float32 or float64, got {dtype}")
    node_dtype = jnp.float32 if dtype == jnp.dtype(jnp.float32) else jnp.float64
    rows = max(1, min(n_r, 4096 // n_nov))
    with jax.enable_x64(True), progress_token(progress, row_chunk_count(n_r, rows)) as token:
        out = _sheen_fast(
            token, n_r=n_r, n_nov=n_nov, m=_order_from_samples(samples), node_dtype=node_dtype, rows_per_chunk=rows
        ).astype(dtype)
        return out if token is None else jax.block_until_ready(out)


# ============================================================================================
# sheen_lut_reference: independent float64 construction
# ============================================================================================
#
# Same integral, other variables and order: the light direction in spherical coordinates,
# l = (s_l cos phi, s_l sin phi, x), x = n.l, dl = dx dphi, so n.l cancels against V_c and
#
#     E = 1/(2 mu) int_0^1 dx / (1 + Lambda(mu) + Lambda(x)) int_0^pi dphi D_c(h)     (2: phi symmetry)
#
# with n.h = (mu + x)/|v + l| and, free of cancellation,
#     sin^2(theta_h) = T / (T + (mu + x)^2),   T = |v + l|_tangential^2 = (s_v - s_l)^2 + 4 s_v s_l cos^2(phi/2),
# so log D = log((2 + 1/alpha)/(2 pi)) - log1p((mu + x)^2 / T) / (2 alpha). D and Lambda are written
# here again in NumPy from the extension text (only the fit's coefficient table is shared with
# `jaxpbr.shading.sheen`; a test compares the two implementations).
# Composite Gauss-Legendre on panels, all geometric with ratio 4: in x towards 0 (the horizon,
# where Lambda(x) grows through many decades: 4^-levels), towards 1 (sqrt(1 - x^2) and the
# (1 - x)^c of the fit's upper branch are singular there: 4^-(levels - 6)), at x = 1/2 (the fit's
# branch switch), at sqrt(alpha) 2^k (the lobe's width) and mu 4^k (where Lambda(x) crosses
# Lambda(mu)); in phi towards both ends (4^-(levels - 10)): towards pi the lobe vanishes where
# h -> n (a dip of width ~ (mu + x)/sqrt(alpha)), towards 0 it narrows for large (mu + x)^2/alpha.
# The default (order 10, levels 16) agrees with order 14 / levels 20 to 1.3e-9 over a 64^2 grid.

_REF_CHUNK = 16  # points per vectorised block (keeps the (chunk, x, phi) arrays ~ 4 MB)


def _ref_lambda(x, alpha):
    """Conty-Kulla Lambda(x) in NumPy: exp(L(x)) below 1/2, exp(2 L(1/2) - L(1 - x)) above."""
    t = (1.0 - alpha) ** 2
    a, b, c, d, e = (p0 + (p1 - p0) * t for p0, p1 in SHEEN_FIT.values())

    def fit(y):
        return a / (1.0 + b * y**c) + d * y + e

    lo = fit(np.minimum(x, 0.5))
    hi = 2.0 * fit(0.5) - fit(1.0 - np.maximum(x, 0.5))
    return np.exp(np.where(x < 0.5, lo, hi))


def _ref_panels(breaks, xg, wg):
    lo, hi = breaks[..., :-1, None], breaks[..., 1:, None]
    shape = breaks.shape[:-1] + (-1,)
    return (lo + (hi - lo) * xg).reshape(shape), ((hi - lo) * wg).reshape(shape)


def _ref_block(mu, alpha, xg, wg, phi, w_phi, levels):
    """E at the points mu, alpha (k,) (float64 NumPy)."""
    k = mu.shape[0]
    m2, a2 = mu[:, None], alpha[:, None]
    fixed = np.concatenate([[0.0, 0.5, 1.0], 4.0 ** -np.arange(1, levels + 1), 1.0 - 4.0 ** -np.arange(1, levels - 5)])
    breaks = np.concatenate(
        [np.broadcast_to(fixed, (k, fixed.size)), np.sqrt(a2) * 2.0 ** np.arange(-3, 4), m2 * 4.0 ** np.arange(-2, 3)], axis=-1
    )
    x, wx = _ref_panels(np.sort(np.clip(breaks, 0.0, 1.0), axis=-1), xg, wg)  # (k, Nx)
    outer = wx / (1.0 + _ref_lambda(m2, a2) + _ref_lambda(x, a2))
    s_v, s_l = np.sqrt(1.0 - m2 * m2), np.sqrt(1.0 - x * x)
    t0 = ((s_v - s_l) ** 2)[..., None]
    t1 = (4.0 * s_v * s_l)[..., None]
    q = ((m2 + x) ** 2)[..., None]
    tt = t0 + t1 * np.cos(0.5 * phi) ** 2
    with np.errstate(divide="ignore"):  # T = 0 only at h = n: D = exp(-inf) = 0
        dd = np.exp(np.log1p(q / tt) * (-0.5 / a2[..., None]))
    inner = dd @ w_phi  # (k, Nx)
    return (2.0 + 1.0 / alpha) / (2.0 * _PI) * np.sum(inner * outer, axis=-1) / (2.0 * mu)


def sheen_lut_reference(n_dot_v, roughness, *, order: int = 10, levels: int = 16) -> np.ndarray:
    """Float64 reference E at arbitrary points, shape broadcast(n_dot_v, roughness).

    Args:
      n_dot_v: NoV in (0, 1] (E has no limit at NoV -> 0). roughness: perceptual sheen roughness
        in [0, 1], floored at 0.045 as in the tables. Both broadcast.
      order, levels: Gauss-Legendre points per panel, and the depth of the geometric grading
        (panels down to 4^-levels towards the horizon; see the notes above). The defaults agree
        with order 14 / levels 20 to ~1e-9.

    Independent of `compute_sheen_lut` (light-direction variables, NumPy, its own D and Lambda).
    ~4.5e4 integrand evaluations per point: every texel of a 128^2 table takes ~8 s, 256^2 ~35 s.
    """
    mu, r = np.broadcast_arrays(np.asarray(n_dot_v, np.float64), np.asarray(roughness, np.float64))
    if not (np.all(mu > 0.0) and np.all(mu <= 1.0)):
        raise ValueError("sheen_lut_reference: n_dot_v must lie in (0, 1] (E has no limit at NoV = 0)")
    if not (np.all(r >= 0.0) and np.all(r <= 1.0)):
        raise ValueError("sheen_lut_reference: roughness must lie in [0, 1]")
    order = positive_int("order", order, where="sheen_lut_reference", fix="the default is 10")
    levels = positive_int("levels", levels, minimum=11, where="sheen_lut_reference", fix="the default is 16")
    shape = mu.shape
    mu, alpha = mu.ravel(), np.maximum(r.ravel(), MIN_ROUGHNESS) ** 2
    x, w = np.polynomial.legendre.leggauss(order)
    xg, wg = 0.5 * (x + 1.0), 0.5 * w
    g = 4.0 ** -np.arange(1, levels - 9)
    phi, w_phi = _ref_panels(np.unique(np.concatenate([[0.0, _PI], _PI * g, _PI * (1.0 - g)])), xg, wg)
    out = np.empty(mu.shape)
    for s in range(0, mu.size, _REF_CHUNK):
        out[s : s + _REF_CHUNK] = _ref_block(mu[s : s + _REF_CHUNK], alpha[s : s + _REF_CHUNK], xg, wg, phi, w_phi, levels)
    return out.reshape(shape)


# ============================================================================================
# Lookup
# ============================================================================================


def sheen_lut_lookup(lut: jax.Array, n_dot_v: jax.Array, sheen_roughness: jax.Array) -> jax.Array:
    """E(NoV, r) from a table in the layout of `compute_sheen_lut` (bilinear, clamp to edge).

    Args:
      lut: (n_roughness, n_nov) table, texel [j, i] at r = (j + 0.5)/n_roughness,
        NoV = (i + 0.5)/n_nov.
      n_dot_v, sheen_roughness: broadcasting arrays. NoV is clamped to [1e-4, 1]
        (`LOOKUP_MIN_NOV`), the roughness to [0.045, 1] (`floored_sheen_roughness` with
        `brdf_terms.MIN_ROUGHNESS`: the table's rows below the floor hold E at the floor).

    Returns:
      broadcast(n_dot_v, sheen_roughness).shape, in the table's dtype promoted with the inputs'.

    Bilinear between texel centres; outside the centres' range (NoV < 0.5/n_nov or
    > 1 - 0.5/n_nov, r > 1 - 0.5/n_roughness) it clamps to the edge texels (GL_CLAMP_TO_EDGE).
    Clamping, not extrapolating: E is steep and unbounded towards NoV = 0 (4.37 at the first
    centre of a 256^2 table at the floor), where no extrapolation is trustworthy, and varies
    slowly at NoV -> 1 and r -> 1. Exact at texel centres. Differentiable: the gradient with
    respect to NoV and r is the bilinear slope, 0 where they are clamped, finite everywhere
    (NoV = 0 or 1, r = 0 or 1 included); NaN inputs give NaN.
    """
    lut = jnp.asarray(lut)
    if lut.ndim != 2:
        raise ValueError(f"sheen_lut_lookup: lut must have shape (n_roughness, n_nov), got {lut.shape}")
    n_r, n_nov = lut.shape
    dtype = jnp.result_type(lut.dtype, jnp.asarray(n_dot_v).dtype, jnp.asarray(sheen_roughness).dtype, float)
    mu, r = jnp.broadcast_arrays(jnp.asarray(n_dot_v, dtype), jnp.asarray(sheen_roughness, dtype))
    mu = jnp.clip(mu, LOOKUP_MIN_NOV, 1.0)
    r = floored_sheen_roughness(r, MIN_ROUGHNESS)
    return bilinear(lut.astype(dtype)[..., None], mu * n_nov - 0.5, r * n_r - 0.5)[..., 0]


def sheen_lut_error(lut, *, texels: int | None = 1024, seed: int = 0) -> dict:
    """Max / mean absolute error of a table (n_r, n_nov) against `sheen_lut_reference` at its
    texel centres: every texel if `texels` is None, else the four edges plus a seeded random
    subset (as `jaxpbr.ibl.measure.lut_error`)."""
    lut = np.asarray(lut, np.float64)
    nr, nn = lut.shape
    jj, ii = np.meshgrid(np.arange(nr), np.arange(nn), indexing="ij")
    j, i = jj.reshape(-1), ii.reshape(-1)
    if texels is not None and nr * nn > texels:
        edge = (j == 0) | (j == nr - 1) | (i == 0) | (i == nn - 1)
        pick = np.union1d(np.nonzero(edge)[0], np.random.default_rng(seed).choice(nr * nn, texels, replace=False))
        j, i = j[pick], i[pick]
    err = np.abs(lut[j, i] - sheen_lut_reference((i + 0.5) / nn, (j + 0.5) / nr))
    return dict(texels=len(j), max=float(err.max()), mean=float(err.mean()), all_texels=texels is None or nr * nn <= texels)
