"""The brightest source texels of a GGX prefilter, convolved exactly instead of sampled: the split
of a level-0 face set into its bright texels and the rest (`split_bright`), their exact near-field
sums and the cell sums with second moments that stand in for them far from a texel (`_bright_all`).
A sun of a few texels is where importance sampling fails; see `specular` for how the two parts
combine and docs/ibl.md for the measured error.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._numerics import (
    HIGHEST,
    is_concrete,
    map_row_chunks,
    safe_div,
)
from .._program_cache import cpu_jit
from ..conventions import luminance
from .cubemap import (
    face_to_dir,
    texel_solid_angles,
)

# ------------------------------------------------------------------------------------------
# the brightest texels, convolved exactly
# ------------------------------------------------------------------------------------------


def lobe_normalizer(alpha: float) -> float:
    """W(alpha) = integral of D(h) (R.l)+ dl with n = v = R (D normalised as in docs/math.md 1.1).

    dl = 4 (v.h) dw_h turns it into 4 E[(NoL)+] under the sampling density D cos(theta_h); with
    xi uniform, cos^2 = (1-xi)/(1+(a^2-1)xi) and NoL = 2cos^2 - 1 > 0 for xi < 1/(1+a^2), giving
    W = 4 [2a^2 ln(2a^2/(1+a^2)) + 1 - a^2] / (1-a^2)^2   (a = alpha),
    with the series 4 (1/4 + e/6 + 11 e^2/96) in e = 1 - a^2 near a = 1 (the closed form cancels there).
    W -> 1 at alpha = 1 and -> 4 as alpha -> 0.
    """
    a2 = float(alpha) ** 2
    e = 1.0 - a2
    if abs(e) < 1e-3:
        return 4.0 * (0.25 + e / 6.0 + 11.0 * e * e / 96.0)
    return 4.0 * (2.0 * a2 * math.log(2.0 * a2 / (1.0 + a2)) + e) / (e * e)


def split_bright(level0: np.ndarray, max_texels: int, min_ratio: float = 4.0):
    """Split radiance (6,S,S,C) into (residual, bright indices (k,), bright radiance (k, C)).

    The brightest texels (at most `max_texels`, and only those whose luminance exceeds `min_ratio`
    times the environment's mean radiance) are clamped to the luminance threshold tau (colour kept);
    the excess over tau is the sparse "bright" part, convolved exactly. The residual's dynamic
    range is then bounded by tau, which is what importance sampling handles well.

    NumPy (concrete values only); `prefilter` uses the traceable fixed-size `_split_bright_fixed`,
    which selects the same texels.
    """
    L = np.asarray(level0, np.float64)
    S, C = L.shape[1], L.shape[-1]
    lum = luminance(L)
    om = texel_solid_angles(S)
    mean = float(np.sum(lum * om) / (4.0 * math.pi))
    flat = lum.reshape(-1)
    if max_texels <= 0 or mean <= 0 or flat.size <= max_texels:
        return L, np.zeros(0, np.int64), np.zeros((0, C))
    tau = max(min_ratio * mean, float(np.partition(flat, -max_texels - 1)[-max_texels - 1]))
    idx = np.nonzero(flat > tau)[0]
    scale = np.ones_like(flat)
    scale[idx] = tau / flat[idx]
    resid = (L.reshape(-1, C) * scale[:, None]).reshape(L.shape)
    bright = L.reshape(-1, C)[idx] - resid.reshape(-1, C)[idx]
    return resid, idx, bright



@functools.partial(cpu_jit, static_argnames=("max_texels", "min_ratio"))
def _split_bright_fixed(level0, omega, max_texels: int, min_ratio: float = 4.0):
    """`split_bright` with a fixed-size selection, traceable (jit, grad) in the texel values.

    level0 (6, S, S, C), 0 < max_texels < 6 S^2. Returns (residual (6,S,S,C) in level0's dtype,
    candidate flat indices (k,) int32, excess radiance (k, C), selected (k,) bool), k = max_texels:
    `lax.top_k` of the luminance with k + 1 entries gives the (k+1)-th largest value (the threshold
    candidate) and the k brightest texels, in decreasing luminance; the selected ones (luminance >
    tau = max(min_ratio x mean, (k+1)-th largest), and mean > 0) are a prefix of them. Unselected
    candidates keep scale 1 and zero excess, so the set has a fixed size with zero weights.

    Computed in the widest float available (float64 when x64 is enabled, as `split_bright` does),
    the residual cast back to level0's dtype.

    Derivatives: only the selection (which texels, the top_k indices) is piecewise constant; tau
    (through the mean and through the (k+1)-th value of top_k) and the clamp scale tau/lum carry
    their gradients (no stop_gradient), because the computed prefilter, FIS(residual) +
    exact(excess), depends on tau through both terms and FIS != exact: dropping those terms would
    not be the derivative of the function computed. That function is continuous across selection
    changes (a texel entering the set at lum = tau has zero excess), so the gradient is that of the
    smooth piece the input lies on.
    """
    hp = jnp.promote_types(level0.dtype, jnp.result_type(float))
    S, C = level0.shape[1], level0.shape[-1]
    L = level0.astype(hp).reshape(-1, C)
    lum = luminance(L)
    om = omega.astype(hp)  # one face's solid angles (the six are identical), an argument
    mean = jnp.sum(lum.reshape(6, S, S) * om) / (4.0 * math.pi)
    vals, idx = jax.lax.top_k(lum, max_texels + 1)
    tau = jnp.maximum(min_ratio * mean, vals[max_texels])
    vals, idx = vals[:max_texels], idx[:max_texels]
    sel = (vals > tau) & (mean > 0)
    # Double where: tau / lum only on the selected lanes (lum > tau >= 0 there).
    scale = safe_div(tau, vals, sel, fill=1.0)
    Lc = L[idx]
    rc = Lc * scale[:, None]
    excess = jnp.where(sel[:, None], Lc - rc, 0.0)
    resid = L.at[idx].set(rc)  # unselected candidates: rc = Lc * 1 exactly
    return resid.reshape(level0.shape).astype(level0.dtype), idx, excess, sel


@functools.partial(cpu_jit, static_argnames=("min_ratio",))
def _count_bright(level0, omega, min_ratio: float = 4.0):
    """How many texels of level0 (6, S, S, C) have a luminance above min_ratio x the mean (as
    `_split_bright_fixed` computes it)."""
    hp = jnp.promote_types(level0.dtype, jnp.result_type(float))
    lum = luminance(level0.astype(hp))
    mean = jnp.sum(lum * omega.astype(hp)) / (4.0 * math.pi)
    return jnp.sum((lum > min_ratio * mean) & (mean > 0))


def _selection_size(level0, omega, max_texels: int) -> int:
    """The k to give `_split_bright_fixed` for concrete texels: a power of two above the count of
    texels over the threshold (>= 1), at most max_texels. Selects what max_texels would (the
    (k+1)-th largest is then not above the threshold), with a smaller top_k and fewer programs."""
    above = _count_bright(level0, omega)
    if not is_concrete(above):  # concrete texels inside an outer trace: the count is traced
        return max_texels
    above = int(above)
    return max(1, min(max_texels, 1 << above.bit_length()))


def _subtexel_points_at(idx, S: int, q: int, omega):
    """Directions (k, q*q, 3) and solid angles (k, q*q) of the q x q sub-texels of the texels with
    (possibly traced) flat indices idx (k,) into (6, S, S): the points and weights of
    `cubemap._subtexel_points` (texel solid angle x normalised sub-texel weight), computed in jnp in
    the widest float available."""
    hp = jnp.result_type(float)
    o = (np.arange(q) + 0.5) / q
    o_t = jnp.asarray(np.repeat(o, q), hp)  # sub-texel a*q + b: t offset o[a], s offset o[b]
    o_s = jnp.asarray(np.tile(o, q), hp)
    idx = jnp.asarray(idx, jnp.int32)
    face = idx // (S * S)
    rem = idx % (S * S)
    i, j = rem // S, rem % S
    s = (j[:, None].astype(hp) + o_s[None, :]) / S
    t = (i[:, None].astype(hp) + o_t[None, :]) / S
    d = face_to_dir(jnp.broadcast_to(face[:, None], s.shape), s, t, xp=jnp).astype(hp)
    r2 = jnp.sum(d * d, -1)
    w = r2**-1.5
    w = w / jnp.sum(w, -1, keepdims=True)
    d = d / jnp.sqrt(r2)[..., None]
    om = omega.astype(hp).reshape(-1)[rem]  # one face's solid angles (the six are identical)
    return d, om[:, None] * w


def _bright_sources(idx, bright, norm, omega, *, S, q, dtype):
    """Sub-texel directions (k q^2, 3) and weights B Omega / W(alpha) (k q^2, C) of the bright texels
    idx (k,) with excess radiance bright (k, C), both possibly traced; norm = W(alpha)."""
    sub, om = _subtexel_points_at(idx, S, q, omega)  # (k, q*q, 3), (k, q*q)
    Bw = (bright[:, None, :].astype(om.dtype) * om[..., None]).reshape(-1, bright.shape[-1]) / norm
    return sub.reshape(-1, 3).astype(dtype), Bw.astype(dtype)


def _bright_chunk(R, sub, Bw, a2):
    """sum_j B_j K(R.w_j) Omega_j for R (chunk, 3), sub-texel directions (n, 3), B Omega (n, C).

    D(h) with NoH^2 = (1+c)/2, 1 - NoH^2 = (1-c)/2 = |R-w|^2/4 (no cancellation near the peak)."""
    q = jnp.sum((R[:, None, :] - sub[None, :, :]) ** 2, -1)  # |R - w|^2 = 2(1 - c)
    c = 1.0 - 0.5 * q
    d = 0.25 * q + (1.0 - 0.25 * q) * a2
    k = a2 / (math.pi * d * d) * jnp.maximum(c, 0.0)
    return jnp.matmul(k, Bw, precision=HIGHEST)


def _bright_far_chunk(R, mu, cov, Bw, a2):
    """sum_g P_g E_g[K(R.w)] over cells g for R (chunk, 3): each cell's texels as their power-weighted
    mean mu (G, 3) (inside the sphere, |mu| < 1) and covariance cov (G, 6) (xx, yy, zz, xy, xz, yz),
    Bw (G, C) the cells' B Omega / W. With c = R.w and f(c) = K, the cell's mean kernel is
    E f(c) = f(c_bar) + f''(c_bar) Var(c) / 2 + O(E|c - c_bar|^3) exactly (c_bar = R.mu,
    Var(c) = R^T cov R): no first-order term, and the second-order one computed, so a cell may be
    several times wider against the lobe than a point at its centroid allows.

    f = a2 c / (pi d^2), d = (1-c)/2 + (1+c)/2 a2, f'' = 2 a2 B (2d + 3Bc) / (pi d^4), B = (1-a2)/2;
    1 - c_bar = (|R - mu|^2 + 1 - |mu|^2)/2 (1 - |mu|^2 = tr cov) without cancellation. Cells
    across the lobe's horizon (a kink of f) are left to the caller's criterion."""
    q = jnp.sum((R[:, None, :] - mu[None, :, :]) ** 2, -1)
    u = 0.5 * (q + jnp.sum(cov[:, :3], -1)[None, :])  # 1 - c_bar
    c = 1.0 - u
    d = 0.5 * u + (1.0 - 0.5 * u) * a2
    B = 0.5 * (1.0 - a2)
    x, y, z = R[:, 0], R[:, 1], R[:, 2]
    RR = jnp.stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z], -1)
    var = jnp.matmul(RR, cov.T, precision=HIGHEST)  # (chunk, G)
    k = a2 / (math.pi * d * d) * (c + B * (2.0 * d + 3.0 * B * c) * var / (d * d))
    return jnp.matmul(jnp.where(c > 0, k, 0.0), Bw, precision=HIGHEST)


#: Output directions per chunk of the exact bright-texel convolution.
BRIGHT_CHUNK = 64

#: The bright texels are grouped into the cells of a BRIGHT_CELLS^2-per-face grid; a chunk of output
#: directions far from every cell (relative to the cell's spread and the lobe width) sums the cells'
#: power at their centroids instead of every sub-texel (see `_bright_all`).
BRIGHT_CELLS = 8

#: Far-field criterion: a cell of rms angular spread rho seen from output directions at angle theta
#: (beyond the chunk's radius) with GGX width alpha is summed from its moments when
#: BRIGHT_FAR^2 rho^2 <= alpha^2 + theta^2 / 4, and when the lobe's horizon (R.l = 0, a kink of the
#: kernel) cannot cross it (BRIGHT_KINK). The moments (power, mean direction, covariance:
#: `_bright_far_chunk`) leave no first- or second-order error; the third-order one is
#: ~ (rho^2 / (alpha^2 + theta^2/4))^(3/2) of the cell's share. The centroid alone (no covariance)
#: needed 40 for 1.6e-4 on the 1-degree 5e4 sun at 1024^2 faces (issue 13: 7.3e-3 at 10). With the
#: covariance, max relative difference from the full sum over all levels of a 4-degree, 400-peak
#: Gaussian sun (8192 exact texels of a 256^2 cube, prefiltered to 128^2): 2.6e-5 at 40, 2.7e-5 at
#: 20, 9.6e-5 at 10 (with BRIGHT_KINK 40), 3.6e-4 at 10 / 10.
BRIGHT_FAR = 10.0

#: The horizon's criterion (see `_bright_all`): a cell whose error across the horizon could exceed
#: 1/BRIGHT_KINK^2 of its power spread evenly over the hemisphere is summed finer (finer grids, or
#: the texels). Off (0 difference) on the narrow levels, where the kernel at the horizon is ~4 alpha^4
#: of its peak; on the rough ones, 10 instead of 40 halved the bright pass of the sun above at 512^2.
BRIGHT_KINK = 10.0


def bright_cells(idx, S0: int, g: int | None = None):
    """The far-field cell of each flat texel index idx (k,) into (6, S0, S0): face-major cells of a
    g x g grid per face, g = min(S0, BRIGHT_CELLS) unless given. Works on NumPy and JAX integers.
    -> (cells, 6 g^2)."""
    g = min(S0, BRIGHT_CELLS) if g is None else g
    face, rem = idx // (S0 * S0), idx % (S0 * S0)
    i, j = rem // S0, rem % S0
    return face * g * g + (i * g // S0) * g + (j * g // S0), 6 * g * g


def bright_tiers(S0: int) -> tuple[int, ...]:
    """The far field's cell grids, coarsest first: g x g cells per face for g = BRIGHT_CELLS,
    2 BRIGHT_CELLS, ..., up to S0/2 (just min(S0, BRIGHT_CELLS) for faces up to 2 BRIGHT_CELLS).
    A chunk of output directions sums the bright texels at the coarsest grid whose every cell is
    far enough (`_bright_all`), the texels themselves only where none is."""
    g = min(S0, BRIGHT_CELLS)
    out = [g]
    while 4 * g <= S0:
        g *= 2
        out.append(g)
    return tuple(out)


def _tier_slots(idx, S0: int, g: int, n_slots: int):
    """Cell slots (k,) of the candidates idx (k,) at grid g, in the program (traced candidates):
    the cell numbers themselves when n_slots = 6 g^2, else the cells renumbered 0..n_slots-1
    (`jnp.unique` with a fixed size, n_slots >= k)."""
    cells, total = bright_cells(idx, S0, g)
    if n_slots == total:
        return cells
    return jnp.unique(cells, size=n_slots, fill_value=0, return_inverse=True)[1].reshape(-1).astype(jnp.int32)


def _bright_clusters(idx, bright, slot, n_slots: int, S0: int, omega):
    """Per cell slot: power-weighted centroid direction (G, 3), power B Omega (G, C), squared rms
    angular spread rho^2 (G,) and angular extent (G,) (the largest angle from the centroid to a
    texel centre, plus the texel's half-diagonal), and the moments (mu, cov, dmu, dcov) of the
    directions: the centres' mean (G, 3) and covariance (G, 6) (xx, yy, zz, xy, xz, yz;
    `_bright_far_chunk`), and what the texels' extent takes from the mean and adds to the
    covariance, all power-weighted; empty slots have zero power. Differentiable in bright (double-where on the empty slots)."""
    d, om = _subtexel_points_at(idx, S0, 1, omega)
    d, om = d[:, 0], om[:, 0]
    P = bright.astype(om.dtype) * om[:, None]  # (k, C)
    w = jnp.sum(P, -1)  # >= 0: excess radiance is non-negative
    seg = lambda x: jax.ops.segment_sum(x, slot, num_segments=n_slots)
    cw, cm, cP = seg(w), seg(w[:, None] * d), seg(P)
    has = cw > 0
    norm = jnp.sqrt(jnp.where(has, jnp.sum(cm * cm, -1), 1.0))
    centre = jnp.where(has[:, None], cm / norm[:, None], jnp.asarray([0.0, 0.0, 1.0], cm.dtype))
    half = math.sqrt(2.0) / S0  # a texel's half-diagonal (angle at the face centre; smaller elsewhere)
    spread = jnp.where(has, 2.0 * jnp.maximum(1.0 - safe_div(norm, cw, has), 0.0), 0.0) + half * half
    # Extent over the candidates that carry power (zero-excess padding excluded).
    ang = jnp.where(w > 0, _angle(d, jax.lax.stop_gradient(centre)[slot]), 0.0)
    extent = jax.ops.segment_max(ang, slot, num_segments=n_slots)
    extent = jnp.where(has, extent, 0.0) + half
    # Mean and covariance of the texel centres (centred: no cancellation in float32), and what a
    # texel's own extent adds: as a uniform patch of solid angle Omega its directions have mean
    # (1 - Omega/12) d and covariance Omega/12 (I - d d^T); q x q sub-texels have (1 - 1/q^2) of
    # that (the caller scales it per level, as its sub-texel sum does), and tr cov = 1 - |mu|^2 to
    # second order either way.
    div = lambda x: safe_div(seg(w[:, None] * x), cw[:, None], has[:, None])
    outer = lambda a, b: jnp.stack([a[:, 0] * b[:, 0], a[:, 1] * b[:, 1], a[:, 2] * b[:, 2], a[:, 0] * b[:, 1], a[:, 0] * b[:, 2], a[:, 1] * b[:, 2]], -1)
    mu = div(d)
    e = d - mu[slot]
    v = (om / 12.0)[:, None]
    eye = jnp.asarray([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], d.dtype)
    moments = (mu, div(outer(e, e)), div(v * d), div(v * (eye - outer(d, d))))
    return centre, cP, spread, jax.lax.stop_gradient(extent), has, moments


def _angle(a, b):
    """Angle between unit vectors (..., 3), accurate at small angles: 2 asin(|a - b| / 2)."""
    return 2.0 * jnp.arcsin(jnp.minimum(0.5 * jnp.linalg.norm(a - b, axis=-1), 1.0))


def _bright_all(R, level_of, idx, bright, slots, omega, S0: int, alphas: tuple, tiers: tuple, n_slots: tuple, far: float, kink: float, chunk: int = BRIGHT_CHUNK, token=None):
    """Exact (sub-texel) convolution of the sparse bright part at output directions R (N, 3), each
    of level `level_of` (N,) with GGX width alphas[level]; every chunk of R lies in one level.

    idx (k,) flat texel indices and bright (k, C) excess radiance may be traced (zero rows are
    unselected candidates). Each level's sub-texel sources (q x q per texel, q from its alpha) are
    padded with zero weights to a common count so that one compiled loop body serves every level.

    Far field, a hierarchy of cell grids (`bright_tiers`: g x g cells per face, g = tiers[t],
    coarsest first; slots[t] (k,) numbers the candidates' cells 0..n_slots[t]-1, None: numbered
    here). A chunk of directions takes the coarsest grid whose every non-empty cell is far from it
    (`far`: BRIGHT_FAR; infinity turns the far field off): small against the lobe at that distance,
    and not crossed by the lobe's horizon (R.l = 0, a kink of the kernel; `kink`: BRIGHT_KINK). It
    then sums that grid's cells from their moments (`_bright_far_chunk`; n_slots[t] terms per
    direction) instead of all k q^2 sub-texels, which it does only where no grid is far enough:
    near a compact sun, the full sum; near a wide one (thousands of texels), cells a few texels across on the narrow levels and
    tens of texels across on the rough ones (nested lax.cond: only the branch taken runs, and a
    finer grid is tested only where the coarser one failed). Rematerialised under
    differentiation, like `_fis_rows`."""
    srcs, fq = [], []
    for alpha in alphas:
        q = _reference_supersample(alpha, S0)
        fq.append(1.0 - 1.0 / (q * q))  # the share of a texel's own extent the q x q sum sees
        srcs.append(_bright_sources(idx, bright, lobe_normalizer(alpha), omega, S=S0, q=q, dtype=R.dtype))
    n = max(sub.shape[0] for sub, _ in srcs)
    pad = lambda x: jnp.pad(x, ((0, n - x.shape[0]), (0, 0)))
    sub = jnp.stack([pad(a) for a, _ in srcs])  # (M, n, 3)
    Bw = jnp.stack([pad(b) for _, b in srcs])  # (M, n, C)
    a2 = jnp.asarray([a * a for a in alphas], R.dtype)
    # The kink's weight per level: a cell of angular extent e across the horizon errs by about
    # s e B Omega, s = 4 a^2 / (pi (1 + a^2)^2) the kernel's slope in R.l there; it counts when
    # that is more than 1/BRIGHT_KINK^2 of the cell's power spread evenly over the hemisphere,
    # B Omega W(alpha) / (2 pi), i.e. when e > kink_at[level]. On the narrow levels (alpha = 0.04:
    # 1.6e-4 of it at e = 0.05) the horizon never matters: the kernel there is ~4 alpha^4 of its peak.
    kink_at = jnp.asarray(
        [lobe_normalizer(a) * (1 + a * a) ** 2 / (8.0 * a * a * kink * kink) if far < math.inf else 0.0 for a in alphas], R.dtype
    )
    grids = []
    for g, slot, ns in zip(tiers, slots, n_slots):
        if slot is None:
            slot = _tier_slots(idx, S0, g, ns)
        centre, cP, spread, extent, has, moments = _bright_clusters(idx, bright, slot, ns, S0, omega)
        cBw = jnp.stack([cP / lobe_normalizer(a) for a in alphas]).astype(R.dtype)  # (M, G, C)
        grids.append(tuple(x.astype(R.dtype) for x in (centre, cBw, spread, extent)) + (has, tuple(x.astype(R.dtype) for x in moments)))
    fq = jnp.asarray(fq, R.dtype)
    half_pi = 0.5 * math.pi

    def chunk_fn(Rc, lc):
        j = lc[0]  # levels are padded to whole chunks: one source set per chunk
        # The chunk's centre u and angular radius; each cell's nearest and farthest angle from
        # the chunk's directions.
        u = jnp.sum(Rc, 0)
        u = u / jnp.maximum(jnp.linalg.norm(u), 1e-6)
        radius = jnp.max(_angle(Rc, u))

        def near(grid):
            centre, _, spread, extent, has, _ = grid
            to = _angle(centre, u)
            theta = jnp.maximum(to - radius, 0.0)
            # Near: the cell is not small against the lobe at that distance (third-order error
            # of the moments), or the lobe's horizon R.l = 0 (a kink of the kernel: first-order
            # error) may cross the cell where that matters (extent > kink_at).
            smooth = far * far * spread > a2[j] + 0.25 * theta * theta
            crosses = (jnp.abs(to - half_pi) < radius + extent) & (extent > kink_at[j])
            return jax.lax.stop_gradient(jnp.any(has & (smooth | crosses)))

        def from_tier(t):
            if t == len(grids):
                return _bright_chunk(Rc, sub[j], Bw[j], a2[j])
            _, cBw, _, _, _, (mu, cov, dmu, dcov) = grids[t]
            far_sum = lambda: _bright_far_chunk(Rc, mu - fq[j] * dmu, cov + fq[j] * dcov, cBw[j], a2[j])
            return jax.lax.cond(near(grids[t]), lambda: from_tier(t + 1), far_sum)

        return from_tier(0)

    return map_row_chunks(jax.checkpoint(chunk_fn), chunk, R, level_of, token=token)


def _reference_supersample(alpha: float, S0: int, max_q: int = 4) -> int:
    """Sub-texels per source-texel side so that sub-texels are <= alpha/4 across (lobe half-width
    in l is ~1.3 alpha), capped at `max_q`."""
    if alpha <= 0:
        return 1
    texel = 2.0 * math.atan(1.0 / S0)
    return int(min(max_q, max(1, math.ceil(texel / (alpha / 4.0)))))
