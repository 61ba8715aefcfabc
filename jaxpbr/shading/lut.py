"""The split-sum BRDF LUT (Karis 2013): converged tables of (A, B), a float64 reference, lookup.

Definition (docs/math.md §4.1). For a unit normal n, view direction v with `mu = n.v`, and the GGX
specular lobe `f_spec = D(h) V(v, l) F(v.h)` with Schlick's `F = F0 + (F90 - F0)(1 - v.h)^5`,

    int_{H^2} f_spec(v, l) (n.l) dl = F0 A(mu, r) + F90 B(mu, r)
    A = int (1 - Fc) D V (n.l) dl,   B = int Fc D V (n.l) dl,   Fc = (1 - v.h)^5,

with `alpha = r^2` (r perceptual roughness). `smith` picks V: ``"correlated"`` — height-correlated
Smith (Heitz 2014; glTF 2.0 App. B, Filament; the default) —, ``"schlick_ggx"`` — separable
Schlick-GGX with `k = alpha / 2` (Karis 2013 for IBL; LearnOpenGL `brdf.fs`), *not* the
`(r + 1)^2 / 8` of analytic lights (docs/math.md §1.3) — or ``"separable"`` — the uncorrelated Smith-GGX
`G2 = G1(v) G1(l)` of `brdf(smith="separable")`, so that a render with that option shades its IBL
term with the same G; ``"schlick"`` is a deprecated alias of ``"schlick_ggx"``.
At r = 0 the lobe is a mirror and `A = 1 - (1 - mu)^5`, `B = (1 - mu)^5` exactly.

Layout (docs/conventions.md): shape `(n_roughness, n_nov, 2)`, element `[j, i]` at
`r = (j + 0.5) / n_roughness`, `NoV = (i + 0.5) / n_nov`, channels (A, B); `lut_lookup` is bilinear
between texel centres, uses the closed form at r = 0 and extrapolates linearly over the last half
texel to r = 1 and NoV = 1 (`lut_padded`).

Why not Monte Carlo: the usual 1024-sample Hammersley estimate (GGX NDF sampling) is off by up
to 1.3e-2 at the texels of a 256^2 table, mean 7.7e-4 (measured against `lut_reference`; docs/math.md
§7.2 quotes ~2e-3). `compute_brdf_lut` uses a deterministic product Gauss-Legendre rule in
half-vector space that splits off the below-horizon region exactly and grades its nodes into the
thin layers of the integrand; with the default 864 nodes per texel it is within 1.4e-6 of
`lut_reference` at every texel of a 128^2 and a 256^2 table (both Smith variants).
`lut_reference` is an independent float64 construction (other variables, other integration
order, composite graded rule, textbook Smith Lambda) whose convergence is checked by refinement
and against scipy in the tests.
"""

from __future__ import annotations

import math
import warnings
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .._api import keyword_only
from .._interp import bilinear, lerp
from .._memory import check_samples, lut_bytes, require
from .._numerics import computed_once, map_row_chunks, progress_token, row_chunk_count
from .._validate import positive_int
from .brdf_terms import (
    d_ggx,
    k_ibl,
    schlick_weight,
    v_schlick_ggx,
    v_smith_correlated,
    v_smith_separable,
)

__all__ = [
    "DEFAULT_SAMPLES",
    "LOOKUP_EDGES",
    "SMITH_ALIASES",
    "SMITH_VARIANTS",
    "compute_brdf_lut",
    "lut_lookup",
    "lut_reference",
]

#: The two Smith terms a LUT can be built with (see the module docstring).
SMITH_VARIANTS = ("correlated", "schlick_ggx", "separable")

#: Deprecated LUT Smith names -> current ones (accepted with a DeprecationWarning).
SMITH_ALIASES = {"schlick": "schlick_ggx"}

#: Default quadrature nodes per texel of `compute_brdf_lut`: 6 m^2 with order m = 12. Chosen from
#: the measured error against `lut_reference` at every texel of a 256^2 table (max abs error over
#: both channels, correlated / schlick_ggx): 384 nodes (m = 8) 1.3e-4 / 7.3e-5, 600 (m = 10)
#: 1.4e-5 / 3.5e-6, 864 (m = 12) 1.4e-6 / 4.2e-7, 1176 (m = 14) 1.3e-7 / 1.4e-7 (there the float32
#: node evaluation is the limit). 864 is the cheapest order with a 70x margin under the 1e-4
#: target; a 256^2 table then runs in 0.3-0.8 s on one CPU core (+ ~1.4 s compilation).
DEFAULT_SAMPLES = 6 * 12**2

_PI = math.pi


# ============================================================================================
# Validation
# ============================================================================================


def resolve_smith(smith, fn: str = "compute_brdf_lut") -> str:
    """The current name of a LUT Smith term: a `SMITH_VARIANTS` name as is, a deprecated alias
    ("schlick") mapped with a DeprecationWarning; anything else raises ValueError."""
    if isinstance(smith, str) and smith in SMITH_ALIASES:
        new = SMITH_ALIASES[smith]
        warnings.warn(
            f"{fn}: smith={smith!r} is deprecated; use smith={new!r} (Schlick-GGX with k = alpha/2, "
            "a different G from brdf's smith='separable')",
            DeprecationWarning,
            stacklevel=4,  # the caller of the public (keyword_only-wrapped) function
        )
        return new
    if smith not in SMITH_VARIANTS:
        raise ValueError(f"{fn}: smith must be one of {SMITH_VARIANTS}, got {smith!r}")
    return smith


def lut_shape(size) -> tuple[int, int]:
    fix = "pass an int such as 128, or a pair (n_roughness, n_nov) such as (64, 128)"
    if isinstance(size, (tuple, list)):
        if len(size) != 2:
            raise ValueError(f"compute_brdf_lut: size must be an int or a pair, got {size!r}; {fix}")
        return tuple(positive_int("size", s, where="compute_brdf_lut", fix=fix) for s in size)
    n = positive_int("size", size, where="compute_brdf_lut", fix=fix)
    return n, n


def _order_from_samples(samples: int) -> int:
    """Gauss-Legendre order m of the LUT rule: 6 m^2 nodes, the most that fit in `samples`."""
    return max(1, math.isqrt(samples // 6))


# ============================================================================================
# compute_brdf_lut: the fast, converged rule
# ============================================================================================
#
# Geometry. In the tangent frame n = +z, v = (s_v, 0, mu) with s_v = sqrt(1 - mu^2), and
# h = (sin t cos p, sin t sin p, cos t) (t = theta_h, p = phi_h). With dl = 4 (v.h) dw_h:
#
#     {A, B} = int D(h) V (n.l) {1 - Fc, Fc} 4 (v.h) dw_h,
#     v.h = s_v sin t cos p + mu cos t,   n.l = 2 (v.h) cos t - mu = R cos(2t - psi),
#     R = sqrt(mu^2 + s_v^2 cos^2 p),     psi = atan2(s_v cos p, mu).
#
# So l is above the horizon exactly for t < t_max(p) = pi/4 + psi/2 (which also implies v.h > 0),
# and n.l = R sin(2 (t_max - t)) there, a form without cancellation at the horizon. The region
# below the horizon is split off exactly instead of being integrated as zeros (a kink that costs
# Gauss-Legendre its exponential convergence). By symmetry p in [0, pi], times 2.
#
# The integrand still has three thin layers, and each gets its own variable:
# * phi near pi/2 at grazing view: t_max(p) falls from ~pi/2 to ~0 where cos p ~ mu / s_v. Each
#   half [0, pi/2], [pi/2, pi] is mapped by p = pi/2 -+ w (e^y - 1), y uniform (Gauss-Legendre),
#   w = 2 mu / s_v, which puts nodes densely at that scale and reduces to ~uniform when mu ~ 1.
# * theta near 0: the GGX peak of width alpha (alpha = 3.8e-6 in the first row of a 256^2 LUT).
#   Piece 1, t in [0, t1], uses the NDF inverse-CDF variable: tan t = alpha tan b, s = tan(b/2),
#   where D cos t dw_h = dxi dp / (2 pi), xi = sin^2 b = 4 s^2 / (1 + s^2)^2 (rational in s, no
#   trig per node). It ends at tan b = 4 (t1 = atan(4 alpha)), because the map is singular at
#   s = 1 (t = pi/2) and nodes crowd there for small alpha.
# * the GGX tail: D ~ alpha^2 / t^4 times the weight ~ t / alpha contributes equal shares per
#   octave of t, so piece 2, t in [t1, t2 = 0.65 t_max], is log-uniform: t = t1 e^y.
# * the horizon: V (n.l) rises from 0 over n.l ~ w_n: for correlated Smith V (n.l) is
#   ~ n.l / (n.l + mu) when alpha >> mu and ~ n.l / (n.l + sqrt(n.l^2 + alpha^2)) when alpha << mu;
#   for Schlick ~ n.l / (n.l + k), k = alpha/2.
#   Piece 3, t in [t2, t_max], uses t = t_max - w (e^y - 1), w = min(mu, alpha/2) / (2R) (n.l ~ 2R
#   (t_max - t) near the horizon).
# Pieces 1-3 and both phi halves use the same order m: 2m x 3m = 6 m^2 nodes per texel.
#
# Precision: everything per (texel, phi) line is float64; the integrand at the nodes is evaluated
# in `node_dtype` (float32 for a float32 LUT: 2.5x faster; its rounding, ~1e-7 relative per node,
# moves the table by ~1e-6 at most, measured) and every sum is accumulated in float64.

_P1_TAN_BETA = 4.0  # piece 1 ends at tan(beta) = 4: s <= tan(atan(4)/2) = 0.78, clear of s = 1
_P1_MAX_FRAC = 0.25  # ... or at t_max / 4 when the whole visible range lies inside the peak
_P2_FRAC = 0.65  # piece 2 / piece 3 split, as a fraction of t_max (0.5 .. 0.8 measured alike)
_PHI_SCALE = 2.0  # w_phi = 2 mu / s_v


def _gauss_legendre_01(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on [0, 1] (float64 NumPy)."""
    x, w = np.polynomial.legendre.leggauss(m)
    return 0.5 * (x + 1.0), 0.5 * w


def _phi_lines(mu: jax.Array, m: int):
    """Per column: the 2m phi nodes in [0, pi] and their weights, graded towards pi/2 (float64).

    Returns cos(phi), weight (both (n_nov, 2m)), and per line R and t_max (n_nov, 2m)."""
    x, w = (jnp.asarray(a, jnp.float64) for a in _gauss_legendre_01(m))
    s_v = jnp.sqrt(1.0 - mu * mu)
    # w_phi ~ mu / s_v: the phi-width of the grazing layer. The floor only matters at mu = 1
    # (s_v = 0), where the map becomes uniform anyway; it keeps w finite there.
    w_phi = _PHI_SCALE * mu / jnp.maximum(s_v, 1e-3 * mu)
    y_max = jnp.log1p((0.5 * _PI) / w_phi)
    y = y_max[:, None] * x
    d = w_phi[:, None] * jnp.expm1(y)
    jac = w_phi[:, None] * jnp.exp(y) * y_max[:, None] * w
    phi = jnp.concatenate([0.5 * _PI - d, 0.5 * _PI + d], axis=1)
    weight = jnp.concatenate([jac, jac], axis=1)
    cos_p = jnp.cos(phi)
    mu_, s_v_ = mu[:, None], s_v[:, None]
    radius = jnp.sqrt(mu_ * mu_ + (s_v_ * cos_p) ** 2)
    t_max = 0.25 * _PI + 0.5 * jnp.arctan2(s_v_ * cos_p, mu_)
    return cos_p, weight, radius, t_max


def _lut_row(r, mu, lines, m: int, smith: str, node_dtype):
    """(A, B) for one roughness r (scalar) at all columns mu (n_nov,) -> (n_nov, 2) float64."""
    cos_p, w_phi, radius, t_max = lines
    f64 = jnp.float64
    alpha = r * r
    mu_l = mu[:, None]  # (n_nov, 1): broadcast against the phi lines
    s_v_l = jnp.sqrt(1.0 - mu_l * mu_l)

    # Piece boundaries per line, in float64.
    t1 = jnp.minimum(jnp.arctan(_P1_TAN_BETA * alpha), _P1_MAX_FRAC * t_max)
    t2 = _P2_FRAC * t_max
    tan_t1 = jnp.tan(t1)
    s1 = tan_t1 / (alpha + jnp.sqrt(alpha * alpha + tan_t1 * tan_t1))  # tan(beta1 / 2)
    y2 = jnp.log(t2 / t1)
    # w_n = min(mu, alpha/2): the n.l scale of the horizon layer (see the notes above); / (2R)
    # converts it to theta. R >= mu > 0 at texel centres.
    w3 = jnp.minimum(mu_l, 0.5 * alpha) / (2.0 * radius)
    y3 = jnp.log1p((t_max - t2) / w3)

    x, w = (jnp.asarray(a, node_dtype) for a in _gauss_legendre_01(m))
    c = lambda a: a.astype(node_dtype)[..., None]  # line quantity -> (n_nov, 2m, 1) in node dtype
    alpha_n = jnp.asarray(alpha, node_dtype)
    mu_n, s_v_n, cos_p_n, rad_n = c(mu_l), c(s_v_l), c(cos_p), c(radius)

    if smith == "correlated":
        vis = lambda n_dot_l: v_smith_correlated(mu_n, n_dot_l, alpha_n)
    elif smith == "separable":
        vis = lambda n_dot_l: v_smith_separable(mu_n, n_dot_l, alpha_n)
    else:
        k_n = jnp.asarray(k_ibl(r), node_dtype)
        vis = lambda n_dot_l: v_schlick_ggx(mu_n, n_dot_l, k_n)

    def reduce(weight, v_dot_h):
        fc = schlick_weight(v_dot_h)
        a = jnp.sum((weight * (1.0 - fc)).astype(f64), axis=(-2, -1))
        b = jnp.sum((weight * fc).astype(f64), axis=(-2, -1))
        return a, b

    # Piece 1: measure D cos t dw_h = dxi dp / (2 pi); weight 4 V (n.l)(v.h) / cos t.
    # Line weight w_phi * 2 (symmetry) / (2 pi) = w_phi / pi.
    s = c(s1) * x
    one_m = 1.0 - s * s
    q = jax.lax.rsqrt(one_m * one_m + 4.0 * alpha_n * alpha_n * s * s)
    sin_t, cos_t = 2.0 * alpha_n * s * q, one_m * q
    v_dot_h = s_v_n * sin_t * cos_p_n + mu_n * cos_t
    # Far from the horizon here (t <= t_max / 4), so the direct form of n.l has no cancellation;
    # the max() only removes a rounding-level negative value.
    n_dot_l = jnp.maximum(2.0 * v_dot_h * cos_t - mu_n, 0.0)
    dxi_ds = 8.0 * s * one_m / (1.0 + s * s) ** 3
    wt = 4.0 * vis(n_dot_l) * n_dot_l * v_dot_h / cos_t * dxi_ds * (c(s1 * w_phi / _PI) * w)
    a1, b1 = reduce(wt, v_dot_h)

    # Pieces 2 and 3: plain theta measure sin t dt dp, integrand D V (n.l) 4 (v.h),
    # line weight 2 w_phi (symmetry).
    def theta_piece(theta, to_horizon, dtheta):
        sin_t, cos_t = jnp.sin(theta), jnp.cos(theta)
        v_dot_h = s_v_n * sin_t * cos_p_n + mu_n * cos_t
        n_dot_l = rad_n * jnp.sin(2.0 * to_horizon)  # = n.l, exact near the horizon
        dd = d_ggx(cos_t, alpha_n, sin2_h=sin_t * sin_t)
        return reduce(4.0 * dd * vis(n_dot_l) * n_dot_l * v_dot_h * sin_t * dtheta, v_dot_h)

    theta = c(t1) * jnp.exp(c(y2) * x)
    a2, b2 = theta_piece(theta, c(t_max) - theta, theta * (c(2.0 * y2 * w_phi) * w))
    em1 = jnp.expm1(c(y3) * x)  # expm1: the nodes nearest the horizon keep full relative precision
    to_h = c(w3) * em1
    a3, b3 = theta_piece(c(t_max) - to_h, to_h, c(w3) * (em1 + 1.0) * (c(2.0 * y3 * w_phi) * w))
    return jnp.stack([a1 + a2 + a3, b1 + b2 + b3], axis=-1)


@partial(jax.jit, static_argnames=("n_r", "n_nov", "m", "smith", "node_dtype", "rows_per_chunk"))
def _lut_fast(token, *, n_r, n_nov, m, smith, node_dtype, rows_per_chunk):
    mu = (jnp.arange(n_nov, dtype=jnp.float64) + 0.5) / n_nov
    r = (jnp.arange(n_r, dtype=jnp.float64) + 0.5) / n_r
    lines = _phi_lines(mu, m)
    row = partial(_lut_row, mu=mu, lines=lines, m=m, smith=smith, node_dtype=node_dtype)
    # Rows in chunks: the node arrays of one chunk are rows_per_chunk * n_nov * 6m^2, bounded
    # whatever the LUT size; token: a `progress_token` (reports per group of chunks) or None.
    return map_row_chunks(jax.vmap(row), rows_per_chunk, r, token=token)


@keyword_only("size", "smith")
def compute_brdf_lut(
    *,
    size=128,
    smith: str = "correlated",
    samples: int = DEFAULT_SAMPLES,
    dtype=jnp.float32,
    progress=None,
) -> jax.Array:
    """The split-sum BRDF LUT, converged to the float64 reference (see the module docstring).

    Args:
      size: int n for an n x n table, or a pair `(n_roughness, n_nov)`.
      smith: ``"correlated"`` (height-correlated Smith, glTF/Filament; default),
        ``"schlick_ggx"`` (Schlick-GGX with k = alpha/2, Karis/LearnOpenGL; ``"schlick"`` is its
        deprecated alias) or ``"separable"`` (uncorrelated Smith-GGX, `brdf(smith="separable")`).
      samples: integrand evaluations per texel; the deterministic Gauss-Legendre rule uses
        6 m^2 of them with m = max(1, floor(sqrt(samples / 6))). Default `DEFAULT_SAMPLES` = 864
        (max abs error 1.4e-6 at every texel of 128^2 and 256^2, both variants).
      dtype: output dtype (float32 or float64). The rule sums in float64 either way; float32
        evaluates the integrand at the nodes in float32 (~1e-6 effect), float64 in float64
        (2-2.5x slower).
      progress: optional callable(done, total) in groups of rows, called from XLA's callback
        thread while the program runs and once at the end (see `jaxpbr.prefilter`).

    Returns:
      (n_roughness, n_nov, 2) array; `[j, i]` holds (A, B) at `r = (j + 0.5)/n_roughness`,
      `NoV = (i + 0.5)/n_nov`, with `int f_spec (n.l) dl = F0 A + F90 B`.

    Cost ~ n_roughness * n_nov * samples evaluations, in chunks of whole rows of at most 4096
    texels (bounded memory). Compiles once per (size, smith, samples, dtype) (~1.4 s); a 256^2
    table then takes 0.3-0.8 s on one CPU core (XLA:CPU runs it single-threaded).
    """
    n_r, n_nov = lut_shape(size)
    smith = resolve_smith(smith, "compute_brdf_lut")
    samples = positive_int("samples", samples, where="compute_brdf_lut", fix=f"the default is {DEFAULT_SAMPLES}")
    check_samples("samples", samples, where="compute_brdf_lut")
    require(f"a LUT of {n_r}x{n_nov} texels with {samples} samples per texel", lut_bytes(n_r, n_nov, samples), where="compute_brdf_lut")
    dtype = jnp.dtype(dtype)
    if dtype not in (jnp.dtype(jnp.float32), jnp.dtype(jnp.float64)):
        raise ValueError(f"compute_brdf_lut: dtype must be float32 or float64, got {dtype}")
    node_dtype = jnp.float32 if dtype == jnp.dtype(jnp.float32) else jnp.float64
    rows = max(1, min(n_r, 4096 // n_nov))
    with jax.enable_x64(True), progress_token(progress, row_chunk_count(n_r, rows)) as token:
        out = _lut_fast(
            token,
            n_r=n_r,
            n_nov=n_nov,
            m=_order_from_samples(samples),
            smith=smith,
            node_dtype=node_dtype,
            rows_per_chunk=rows,
        ).astype(dtype)
        return out if token is None else jax.block_until_ready(out)


# ============================================================================================
# lut_reference: independent float64 construction
# ============================================================================================
#
# Same integral, built differently from the fast rule: theta_h is the *outer* variable and phi_h
# the inner one (the fast rule integrates phi outside), the integration is in plain (theta, phi)
# with a composite Gauss-Legendre rule on geometrically graded panels (no variable maps), the
# horizon enters as the inner limit phi_max(theta), n.l comes from the double-angle form
# mu cos 2t + s_v sin 2t cos p, and V from the textbook Smith Lambda / Schlick G1 (docs/math.md §1.2,
# §1.3), not from jaxpbr.shading.brdf_terms. With f_spec (n.l) dl = D G2 F / (4 mu) * 4 (v.h) dw_h:
#
#     {A, B} = 2 int_0^{t_top} dt sin t D(t) int_0^{phi_max(t)} dp G2 (v.h) {1-Fc, Fc} / mu
#
# t < t_c = pi/4 - theta_v/2: every phi is visible (phi_max = pi);
# t_c < t < t_top = pi/4 + theta_v/2: phi_max = acos(-mu cot(2t) / s_v).
# Panels in t, all geometric with ratio 4: towards 0 at the GGX scale (alpha 4^k, k >= -1), towards
# t_c from both sides (the inner integral behaves like (t - t_c)^{3/2} there) and towards t_top;
# in phi: towards phi_max (the horizon layer, where V (n.l) switches on). Convergence is shown by
# refinement: the default (order 10, 7 levels) agrees with order 14 / 8 levels to ~1e-9 and with
# a third construction (a high-order run of the fast rule's geometry) to ~1e-9.

_REF_CHUNK = 64  # points per compiled call
_REF_RATIO = 4.0  # geometric grading ratio of the reference panels


def _graded(a, b, toward_b: bool, levels: int):
    """Breakpoints of [a, b] graded by 1/4 towards one end: (..., levels) (a, b not included)."""
    k = _REF_RATIO ** -jnp.arange(1, levels + 1, dtype=jnp.float64)
    return (b - (b - a) * k) if toward_b else (a + (b - a) * k)


def _panels_nodes(breaks, xg, wg):
    """Sorted breakpoints (..., K) -> Gauss-Legendre nodes and weights (..., (K-1) p)."""
    lo, hi = breaks[..., :-1, None], breaks[..., 1:, None]
    nodes = lo + (hi - lo) * xg
    weights = (hi - lo) * wg
    shape = breaks.shape[:-1] + (-1,)
    return nodes.reshape(shape), weights.reshape(shape)


@partial(jax.jit, static_argnames=("smith", "order", "levels", "alpha_levels"))
def _reference_chunk(mu, alpha, *, smith, order, levels, alpha_levels):
    xg, wg = (jnp.asarray(a, jnp.float64) for a in _gauss_legendre_01(order))
    s_v = jnp.sqrt(1.0 - mu * mu)
    theta_v = jnp.arctan2(s_v, mu)
    t_c = 0.25 * _PI - 0.5 * theta_v
    t_top = 0.25 * _PI + 0.5 * theta_v
    col = lambda a: a[:, None]
    breaks = jnp.concatenate(
        [
            jnp.stack([jnp.zeros_like(mu), t_c, t_top], axis=-1),
            col(alpha) * _REF_RATIO ** jnp.arange(-1, alpha_levels + 1, dtype=jnp.float64),
            _graded(jnp.zeros_like(col(mu)), col(t_c), True, levels),
            _graded(col(t_c), col(t_top), False, levels),
            _graded(col(t_c), col(t_top), True, levels),
        ],
        axis=-1,
    )
    breaks = jnp.sort(jnp.clip(breaks, 0.0, col(t_top)), axis=-1)
    t, wt = _panels_nodes(breaks, xg, wg)  # (P, Nt)

    mu2, s_v2, alpha2 = col(mu), col(s_v), col(alpha)
    # phi_max: pi below t_c; beyond, where n.l = mu cos 2t + s_v sin 2t cos p reaches 0. The
    # denominator is floored only for the empty panels of mu = 1 (s_v = 0, t_c = t_top), whose
    # weights are 0; acos' argument is clipped against rounding.
    cos_lim = -mu2 * jnp.cos(2.0 * t) / jnp.maximum(s_v2 * jnp.sin(2.0 * t), 1e-300)
    phi_max = jnp.where(t < col(t_c), _PI, jnp.arccos(jnp.clip(cos_lim, -1.0, 1.0)))
    zero = jnp.zeros_like(phi_max)[..., None]
    inner_levels = max(levels - 2, 1)  # the phi layer needs less depth (4^-5 at levels 7, measured)
    pb = jnp.concatenate([zero, _graded(zero, phi_max[..., None], True, inner_levels), phi_max[..., None]], axis=-1)
    p, wp = _panels_nodes(pb, xg, wg)  # (P, Nt, Np)

    # Per outer node (theta): the trigonometry and D, materialised once (the barrier stops XLA
    # from fusing them into, and so recomputing them in, the loop over the inner nodes).
    sin_t, cos_t = jnp.sin(t), jnp.cos(t)
    # D = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2), with the bracket written as
    # sin^2 + alpha^2 cos^2 (identical; the textbook form cancels at small alpha even in float64).
    dd = alpha2 * alpha2 / (_PI * (sin_t * sin_t + (alpha2 * cos_t) ** 2) ** 2)
    outer = 2.0 * sin_t * dd * wt / mu2  # 2: phi symmetry
    sin_t, cos_t, cos_2t, sin_2t, outer = jax.lax.optimization_barrier(
        (sin_t, cos_t, cos_t * cos_t - sin_t * sin_t, 2.0 * sin_t * cos_t, outer)
    )
    sin_t, cos_t, cos_2t, sin_2t, outer = (a[..., None] for a in (sin_t, cos_t, cos_2t, sin_2t, outer))
    mu3, s_v3, a3 = mu2[..., None], s_v2[..., None], alpha2[..., None]
    cos_p = jnp.cos(p)
    v_dot_h = jnp.clip(s_v3 * sin_t * cos_p + mu3 * cos_t, 0.0, 1.0)
    n_dot_l = jnp.maximum(mu3 * cos_2t + s_v3 * sin_2t * cos_p, 0.0)
    if smith == "correlated":

        def lam(c):  # Smith Lambda = (sqrt(1 + alpha^2 tan^2) - 1) / 2; c = 0 gives inf, G2 = 0
            tan2 = (1.0 - c * c) / (c * c)
            return 0.5 * (jnp.sqrt(1.0 + a3 * a3 * tan2) - 1.0)

        g2 = 1.0 / (1.0 + lam(mu3) + lam(n_dot_l))
    elif smith == "separable":

        def lam(c):  # the same Lambda; G2 = G1(v) G1(l) (uncorrelated)
            tan2 = (1.0 - c * c) / (c * c)
            return 0.5 * (jnp.sqrt(1.0 + a3 * a3 * tan2) - 1.0)

        g2 = 1.0 / ((1.0 + lam(mu3)) * (1.0 + lam(n_dot_l)))
    else:
        k = 0.5 * a3
        g2 = mu3 / (mu3 * (1.0 - k) + k) * n_dot_l / (n_dot_l * (1.0 - k) + k)
    fc = (1.0 - v_dot_h) ** 5
    f = outer * g2 * v_dot_h * wp
    return jnp.stack([jnp.sum(f * (1.0 - fc), axis=(-2, -1)), jnp.sum(f * fc, axis=(-2, -1))], axis=-1)


@keyword_only("smith")
def lut_reference(n_dot_v, roughness, *, smith: str = "correlated", order: int = 10, levels: int = 7) -> np.ndarray:
    """Float64 reference (A, B) at arbitrary points, shape broadcast(n_dot_v, roughness) + (2,).

    Args:
      n_dot_v: NoV in (0, 1] (the integrand divides by NoV; NoV -> 0 is a limit, evaluate e.g.
        1e-6). roughness: perceptual r in [0, 1]. Both broadcast.
      smith: ``"correlated"``, ``"schlick_ggx"`` or ``"separable"`` as in `compute_brdf_lut`.
      order, levels: Gauss-Legendre points per panel, and the number of panels graded by 1/4
        towards each singular point of theta (levels - 2 towards the horizon in phi). The
        defaults agree with order 14 / levels 8 to ~1e-9 (tests, slow).

    r = 0 returns the exact mirror values `A = 1 - (1 - NoV)^5`, `B = (1 - NoV)^5`. For r > 0
    the integral is evaluated with the composite graded rule described above this function
    (independent of `compute_brdf_lut`'s rule), ~2.2e4 integrand evaluations per point, in
    compiled chunks of 64 points: every texel of a 128^2 table takes ~15 s of one CPU core,
    256^2 ~60 s.
    """
    smith = resolve_smith(smith, "lut_reference")
    mu, r = np.broadcast_arrays(np.asarray(n_dot_v, np.float64), np.asarray(roughness, np.float64))
    if not (np.all(mu > 0.0) and np.all(mu <= 1.0)):
        raise ValueError("lut_reference: n_dot_v must lie in (0, 1] (NoV -> 0 is a limit; evaluate at e.g. 1e-6)")
    if not (np.all(r >= 0.0) and np.all(r <= 1.0)):
        raise ValueError("lut_reference: roughness must lie in [0, 1]")
    order = positive_int("order", order, where="lut_reference", fix="the default is 10")
    levels = positive_int("levels", levels, where="lut_reference", fix="the default is 7")
    shape = mu.shape
    mu, r = mu.ravel(), r.ravel()
    alpha = r * r
    one_m = (1.0 - mu) ** 5
    out = np.stack([1.0 - one_m, one_m], axis=-1)  # exact at r = 0
    todo = np.nonzero(alpha > 0.0)[0]
    if todo.size:
        # alpha 4^k panels up to pi/2 from the smallest alpha. At least 12 (enough for r >= 6e-4)
        # and a multiple of 4, so that few distinct programs are compiled; a panel beyond t_top
        # has zero width and costs ~3 % per level.
        alpha_levels = int(np.ceil(np.log(0.5 * _PI / alpha[todo].min()) / np.log(_REF_RATIO))) + 1
        alpha_levels = max(12, 4 * -(-alpha_levels // 4))
        with jax.enable_x64(True):
            for start in range(0, todo.size, _REF_CHUNK):
                idx = todo[start : start + _REF_CHUNK]
                pad = _REF_CHUNK - idx.size
                m_c = np.pad(mu[idx], (0, pad), constant_values=0.5)
                a_c = np.pad(alpha[idx], (0, pad), constant_values=0.25)
                res = _reference_chunk(
                    jnp.asarray(m_c),
                    jnp.asarray(a_c),
                    smith=smith,
                    order=order,
                    levels=levels,
                    alpha_levels=alpha_levels,
                )
                out[idx] = np.asarray(res)[: idx.size]
    return out.reshape(shape + (2,))


# ============================================================================================
# Lookup
# ============================================================================================


#: Edge rules of `lut_lookup` (see there).
LOOKUP_EDGES = ("split_sum", "clamp")


def lut_padded(lut, *, xp=jnp):
    """The (n_r, n_nov, C) table extended half a texel to r = 1 and NoV = 1: (n_r + 1, n_nov + 1, C).

    Row n_r is r = 1 and column n_nov is NoV = 1, each extrapolated linearly from the last two
    rows / columns (a table of one row or column repeats it). Works on NumPy (xp=np) and JAX arrays."""
    n_r, n_nov, _ = lut.shape
    ext = lambda a, b: a + 0.5 * (a - b)  # noqa: E731  (linear, half a texel past a)
    rows = xp.concatenate([lut, (ext(lut[-1], lut[-2]) if n_r > 1 else lut[-1])[None]], 0)
    return xp.concatenate([rows, (ext(rows[:, -1], rows[:, -2]) if n_nov > 1 else rows[:, -1])[:, None]], 1)


def lut_coordinates(n_dot_v, roughness, n_r: int, n_nov: int, *, xp=jnp):
    """(x, y, t): continuous (column, row) coordinates into `lut_padded`'s table, and the weight t
    of the table against the r = 0 closed form (t < 1 only for r < 0.5/n_r).

    Texel centres stay where the file has them (x = i, y = j); r in [1 - 0.5/n_r, 1] maps onto
    [n_r - 1, n_r] and NoV in [1 - 0.5/n_nov, 1] onto [n_nov - 1, n_nov] (the extrapolated edges);
    r in [0, 0.5/n_r] reads the first row, blended with the closed form by t = 2 n_r r. Beyond
    [0, 1] the coordinates clamp (in `bilinear`); NoV below the first centre clamps to it."""
    r, mu = roughness, n_dot_v
    # >= : at a band's boundary the bilinear segment is the band's, so the derivative must be too.
    y = xp.where(r >= 1.0 - 0.5 / n_r, 2.0 * n_r * r - n_r, n_r * r - 0.5)
    x = xp.where(mu >= 1.0 - 0.5 / n_nov, 2.0 * n_nov * mu - n_nov, n_nov * mu - 0.5)
    return x, y, xp.where(r < 0.5 / n_r, xp.maximum(2.0 * n_r * r, 0.0), 1.0)


def lut_r0(n_dot_v, *, xp=jnp):
    """The split-sum (A, B) at r = 0 (a mirror: G = 1 for both Smith variants, F at v.h = NoV):
    (1 - (1 - mu)^5, (1 - mu)^5) with mu = NoV clamped to [0, 1]. -> (..., 2)."""
    mu = xp.clip(n_dot_v, 0.0, 1.0)
    # A = 1 - (1 - mu)^5 expanded (Horner): no cancellation against 1 at small mu.
    a = mu * (5.0 + mu * (-10.0 + mu * (10.0 + mu * (-5.0 + mu))))
    return xp.stack([a, (1.0 - mu) ** 5], -1)


def lut_lookup(lut: jax.Array, n_dot_v: jax.Array, roughness: jax.Array, *, edges: str = "split_sum") -> jax.Array:
    """Bilinear lookup of a LUT in the layout of `compute_brdf_lut`.

    Args:
      lut: (n_roughness, n_nov, C) table, texel [j, i] at r = (j + 0.5)/n_roughness,
        NoV = (i + 0.5)/n_nov.
      n_dot_v, roughness: broadcasting arrays (any values; beyond [0, 1] the edges clamp).
      edges: "split_sum" (default; C = 2, the (A, B) table): exact edges: the closed form at r = 0
        (`lut_r0`, blended linearly with the first row over the first half texel), linear
        extrapolation over the last half texel to r = 1 and to NoV = 1 (`lut_padded`); the
        NoV -> 0 side clamps to the first column (A and B are discontinuous at the corner
        r = 0, NoV = 0). "clamp": GL_CLAMP_TO_EDGE with linear filtering on both axes (any C).
        Why: the last texel centre is at r = 1 - 0.5/n_r, and clamping there read 1.28 % high at
        r = 1 in a 128^2 table (a white furnace at r = 1 came out 0.89 % bright; issue 13);
        extrapolating to r = 0 from a coarse table was worse than clamping (6.9e-3 on 24 rows),
        while the closed form is exact.
    Returns:
      broadcast(n_dot_v, roughness).shape + (C,), in the LUT's dtype (promoted with the inputs).

    Exact at texel centres, linear in each coordinate between them (and piecewise linear across
    the half-texel edge bands). Differentiable: the gradient with respect to NoV and r is the
    bilinear slope, 0 where the coordinates clamp, finite everywhere; the gradient with respect to
    `lut` is the bilinear weights. NaN inputs give NaN.
    """
    if edges not in LOOKUP_EDGES:
        raise ValueError(f"unknown LUT edges {edges!r}; choose one of {', '.join(map(repr, LOOKUP_EDGES))}")
    lut = jnp.asarray(lut)
    if lut.ndim != 3:
        raise ValueError(f"lut_lookup: lut must have shape (n_roughness, n_nov, channels), got {lut.shape}")
    n_r, n_nov, C = lut.shape
    dtype = jnp.result_type(lut.dtype, jnp.asarray(n_dot_v).dtype, jnp.asarray(roughness).dtype, float)
    mu, r = jnp.broadcast_arrays(jnp.asarray(n_dot_v, dtype), jnp.asarray(roughness, dtype))
    lut = lut.astype(dtype)
    if edges == "clamp":
        return bilinear(lut, mu * n_nov - 0.5, r * n_r - 0.5)
    if C != 2:
        raise ValueError(f"edges='split_sum' reads an (A, B) table (2 channels), got {C}; use edges='clamp'")
    def look(o):
        mu, r, lut = o
        x, y, t = lut_coordinates(mu, r, n_r, n_nov)
        return lerp(lut_r0(mu), bilinear(lut_padded(lut), x, y), t[..., None])

    # Once per point: fused, the (A, B) pair was looked up again for each colour channel that
    # reads it (the demo's IBL stage 0.90x the run time with this).
    return computed_once(look, (mu, r, lut), lut[0, 0, 0])
