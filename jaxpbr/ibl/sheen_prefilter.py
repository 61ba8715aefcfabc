"""Charlie-prefiltered environment mips for the KHR_materials_sheen IBL term.

Level m of `prefilter_charlie`'s result stores (the Khronos glTF-IBL-Sampler's Charlie filter, with
its n = v = R assumption)

    LD_c(R, r_m) = int L(l) w(l) dl / int w(l) dl,   w(l) = D_c(h) (R.l)+,   h = (R + l)/|R + l|,

at the texel centres of a (S >> m)^2 cube, r_m = m/(M-1) (sheen roughness, "linear" mapping),
alpha_m = max(r_m, min_roughness)^2 (level 0 is r = 0 evaluated at the floor, 0.045 =
`brdf_terms.MIN_ROUGHNESS`). With c = R.l, sin^2(theta_h) = (1 - c)/2, so (constants dropped)

    w(c) = c ((1 - c)/2)^K,   K = 1/(2 alpha),   0 < c <= 1.

For small alpha the weight is a thin ring near the horizon R.l -> 0 (its peak is at c = 1/(K+1),
about 2 alpha rad above it, and about as wide): at the floor the ring is 0.23 deg wide, far
narrower than a texel of any source that can be summed in full, and w/w_peak ~ exp(-0.35/alpha)
away from it underflows float32.

Mean cosine: the measure on the sphere is dc dphi, so int w c^p dl are Beta functions and the
weight's mean cosine is closed form, k(alpha) = int w c dl / int w dl = 2/(K + 3) =
4 alpha/(1 + 6 alpha) (`charlie_mean_cosine`; 0.0080 at the floor, 4/7 at alpha = 1). An
environment linear in direction, L = a + g.l, gives LD_c = a + k(alpha) g.R.

Box path (method "box", and the default for levels >= 1): brute force over every texel of one area-correct pyramid level of
the environment (`source_size`^2 faces), output texels in chunks (`map_row_chunks`), one compiled
program for the whole chain. Because the ring is thinner than a source texel at low roughness, the
kernel is not point-sampled at the texel centre (that aliases: a texel counts or not depending on
where the ring crosses it) but *box-filtered in c*: texel j with centre cosine c_j, solid angle
Omega_j and angular size s_j = sqrt(Omega_j) gets

    W_j = Omega_j (F(c_j + h_j) - F(c_j - h_j)) / (2 h_j),   h_j = s_j sqrt(1 - c_j^2) / 2,

F the antiderivative of w (clamped to c in [0, 1]), i.e. the mean of w over a box in c with the same
variance as the distribution of c over the texel's footprint (a square of side s crossed by the
gradient of c, of norm sin(theta), at any angle: variance s^2 sin^2 / 12). F is closed form,
F(c) = -2^-K G(c), G(c) = (1 - c)^(K+1) (1 + (K+1) c) / ((K+1)(K+2)); the box keeps the kernel's
mass and its mean cosine (dc is the sphere's measure), so constants and linear environments come
out right at every roughness. Everything is in the log domain,
log(G(lo) - G(hi)) = log G(lo) + log(-expm1(log G(hi) - log G(lo))), and each output's largest log
weight is subtracted before exponentiating: every output's weights have max 1 and sum >= 1 (never
0/0, finite in float32 at every roughness, any radiance that is itself finite).

Reference (`charlie_reference`): float64 brute force over every texel of the environment's level 0,
each split into q x q sub-texels with their exact solid-angle shares (q so that a sub-texel is at
most a quarter of the ring's width 2 alpha, capped at `REFERENCE_MAX_Q`), the kernel
`sheen.d_charlie(sqrt((1+c)/2), alpha, (1-c)/2) (R.l)+` point-sampled: independent of the fast
path's source level and of its box filter.

Lookup (`charlie_lookup`, `charlie_roughness_to_lod`): trilinear in the chain at
lod_blend "mean_cosine" (default): lod linear in k(alpha) between the bracketing levels (exact for
a linear environment, lod = 0 below the floor), or "roughness": lod = r (M - 1) (the glTF sample
viewer's lookup of its Charlie map).

Zonal path (default for level 0, `zonal_levels` levels from the bottom; method="zonal"): the
weight depends on c = R.l only and the measure is dc dphi, so c is Beta(2, K+1). It is cut into n
equal-mass bands (n ~ the kernel's angular width / the finest texel read, at most `rings`); band i
is a ring at its conditional mean cosine (mass and mean cosine exact: constant and linear
environments reproduced), of width sqrt(12 var_i)/sin(theta_i); the ring is read along its
azimuth by bilinear lookups in the environment's area-correct pyramid at the level whose texel
matches that width (+ lod_bias, no finer than `zonal_source_size`), one sample per texel
(`phi_density`), weights 1/(n n_phi) (constants, normalised in float64: finite in float32 for any
finite radiance). At the floor this reads the great circle at the source's own resolution
(4 rings x ~1000 azimuths from a 256^2 environment's 128^2 level) instead of box-filtering a 64^2
source. One program (jit, chunked, `jax.checkpoint` per chunk).

Measured (`examples/charlie_prefilter_error.py`, 2-core shared CPU: times rough; relative error
|fast - ref|/ref per channel in %, mean / max over 48 random directions at each of 10 random sheen
roughnesses ("random r") and at the levels' r = 0 .. 1; reference at the full 256^2; 64^2 chain,
5 levels, box levels from the 64^2 source). Sky with its 2-degree 3000 sun, GGX prefilter
0.7-1.7 s:

    config                     | random r      | r=0          | r=.25      | r=.5        | r=.75       | r=1         | x GGX | x box
    box (before)               | 5.71/356.5    | 8.38/255.0   | 0.27/2.48  | 0.79/13.24  | 4.74/62.98  | 6.82/48.31  | 15.8  | 1
    zonal L0, src 256          | 5.24/262.3    | 0.77/ 27.5   | same as box for levels >= 1                          | 11.5* | 0.73*
    zonal L0, src 128 (default)| 5.33/277.1    | 2.16/ 63.0   | same as box for levels >= 1                          | 5.2   | 0.33
    zonal L0-1 (16 rings)      | 5.24/262.3    | 0.77/ 27.5   | 5.03/83.73 | (box)                                   | 16.6  | 1.05

(* measured while another job shared the CPU.) The zonal method is far better at level 0 and
worse at the rough levels (with the sun: coarse pyramid lookups of a 3000-radiance 2-degree disc;
up to 30k samples per direction did not reach the box method's 0.27 % at r = .25), so the default
keeps the better one per level: zonal for level 0, box for levels >= 1 (which now dominate the
cost). With all levels zonal (zonal_levels=M, rings=16) a linear environment is within 4.2e-4 of
the closed form at every level. The residual/soft-sky rows: run the example.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._interp import interp_nodes
from .._numerics import HIGHEST, map_row_chunks
from .._validate import check_radiance, positive_int
from ..shading.brdf_terms import MIN_ROUGHNESS
from ..shading.sampling import tangent_frame
from ..shading.sheen import d_charlie
from .cubemap import (
    Cubemap,
    _mip_chain,
    mip_count,
    _Pyramid,
    face_to_dir,
    texel_directions,
    texel_solid_angles,
)
from .lobe_reference import LOD_TABLE_STEPS, chain_lookup_metadata, check_lod_blend, lobe_reference, lobe_reference_sum

__all__ = [
    "CHARLIE_LOD_BLENDS",
    "DEFAULT_CHARLIE_LEVELS",
    "DEFAULT_CHARLIE_LOD_BLEND",
    "DEFAULT_CHARLIE_SIZE",
    "DEFAULT_CHARLIE_SOURCE_SIZE",
    "charlie_level_roughness",
    "charlie_lookup",
    "charlie_lookup_metadata",
    "charlie_mean_cosine",
    "charlie_reference",
    "charlie_roughness_to_lod",
    "prefilter_charlie",
]

#: Default face size of level 0 (measured: see the module docstring's table).
DEFAULT_CHARLIE_SIZE = 64
#: Default number of levels M (r_m = m/(M-1)).
DEFAULT_CHARLIE_LEVELS = 5
#: Default face size of the environment's pyramid level that is summed in full (method "box").
DEFAULT_CHARLIE_SOURCE_SIZE = 64
#: Default finest pyramid level the zonal method reads (face size; the env's level 0 when smaller).
DEFAULT_CHARLIE_ZONAL_SOURCE_SIZE = 128
#: Lookups between levels: "mean_cosine" (lod linear in k(alpha) between bracketing levels) or
#: "roughness" (lod = r (M-1), the glTF sample viewer's).
CHARLIE_LOD_BLENDS = ("mean_cosine", "roughness")
DEFAULT_CHARLIE_LOD_BLEND = "mean_cosine"
#: Output directions per chunk of the fast path (a (chunk, 6 source^2) weight block).
CHUNK = 64
#: Largest sub-texel split of the reference.
REFERENCE_MAX_Q = 8
#: Prefilter methods: "zonal" (rings in c, pyramid lookups matched to each sample's footprint)
#: and "box" (every texel of one source level, the kernel box-filtered over each texel).
CHARLIE_METHODS = ("zonal", "box")
DEFAULT_CHARLIE_METHOD = "zonal"
#: Most rings (equal-mass bands of the weight in c) per level.
DEFAULT_CHARLIE_RINGS = 4
#: Samples per texel width along a ring (1: spacing = the texel of the level read).
DEFAULT_CHARLIE_PHI_DENSITY = 1.0
#: Added to each ring's source level (log2 of footprint / texel).
DEFAULT_CHARLIE_LOD_BIAS = -2.0
#: Levels (from level 0) computed by the zonal method with method "zonal"; the others by "box".
DEFAULT_CHARLIE_ZONAL_LEVELS = 1
#: Most samples along one ring.
MAX_PHI = 2048
#: Output directions per chunk of the zonal path.
ZONAL_CHUNK = 32


# ------------------------------------------------------------------------------------------
# roughness <-> lod
# ------------------------------------------------------------------------------------------


def charlie_mean_cosine(alpha, xp=np):
    """k(alpha) = int w (R.l) dl / int w dl = 4 alpha / (1 + 6 alpha) for the Charlie weight
    w = D_c(h) (R.l)+ (n = v = R); xp = np or jnp (traceable, smooth in alpha >= 0)."""
    alpha = xp.asarray(alpha)
    return 4.0 * alpha / (1.0 + 6.0 * alpha)


def charlie_level_roughness(num_levels: int) -> np.ndarray:
    """Sheen roughness r_m = m/(M-1) of each level (float64; level 0 is evaluated at the floor)."""
    M = positive_int("num_levels", num_levels)
    return np.arange(M) / max(M - 1, 1)


def _alpha(r, min_roughness, xp):
    r = xp.clip(r, min_roughness, 1.0)
    return r * r


def _check_blend(lod_blend):
    check_lod_blend(lod_blend, CHARLIE_LOD_BLENDS)


def charlie_roughness_to_lod(r, num_levels: int, *, lod_blend: str = DEFAULT_CHARLIE_LOD_BLEND,
                             min_roughness: float = MIN_ROUGHNESS, xp=jnp):
    """Fractional level of a Charlie chain for sheen roughness r (clamped to [0, 1]).

    "mean_cosine": between the bracketing levels, linear in k(alpha) (`charlie_mean_cosine`,
    alpha = max(r, min_roughness)^2): lod = m exactly at r = r_m, 0 for r <= min_roughness
    (d lod / dr = 0 there), M - 1 at r = 1. "roughness": lod = r (M - 1).
    xp: jnp (jit / vmap / grad: finite gradients on [0, 1]) or np."""
    _check_blend(lod_blend)
    M = positive_int("num_levels", num_levels)
    r = xp.clip(r, 0.0, 1.0)
    if lod_blend == "roughness" or M == 1:
        return r * (M - 1)
    k_levels = charlie_mean_cosine(_alpha(charlie_level_roughness(M), min_roughness, np))
    k = charlie_mean_cosine(_alpha(r, min_roughness, xp), xp)
    if xp is np:
        return np.interp(k, k_levels, np.arange(M, dtype=np.float64))
    return interp_nodes(k, k_levels, np.arange(M, dtype=np.float64))


def charlie_lookup_metadata(num_levels: int, *, lod_blend: str, face_size: int,
                            min_roughness: float = MIN_ROUGHNESS) -> dict:
    """The metadata keys that reproduce a Charlie chain's lookup (mirroring
    `specular.lookup_metadata`): blend and formula, smallest face, each level's alpha and mean
    cosine k_m, and "lod_table": lod at r = k/K, K = LOD_TABLE_STEPS (M - 1) (its nodes fall on
    the levels; linear interpolation of it in r is what an engine can do)."""
    M = positive_int("num_levels", num_levels)
    _check_blend(lod_blend)
    alphas = _alpha(charlie_level_roughness(M), min_roughness, np)
    K = LOD_TABLE_STEPS * max(M - 1, 1)
    u = np.linspace(0.0, 1.0, K + 1)
    table = charlie_roughness_to_lod(u, M, lod_blend=lod_blend, min_roughness=min_roughness, xp=np)
    return chain_lookup_metadata(
        M,
        lod_blend=lod_blend,
        formula="lod = r*(M-1)" if lod_blend == "roughness" else (
            "lod = m + (k(r) - k_m) / (k_{m+1} - k_m) between the levels m, m+1 whose mean cosines bracket k(r); "
            "k(r) = 4 alpha / (1 + 6 alpha), alpha = max(r, min_roughness)^2 (the Charlie weight's mean cosine); "
            "k_m = level_mean_cosine; lod = 0 below min_roughness"
        ),
        face_size=face_size,
        level_alpha=alphas,
        level_mean_cosine=charlie_mean_cosine(alphas),
        table=table,
        abscissa=f"u = k/{K}, k = 0..{K}, u = r; linear interpolation in u",
    )


def _lookup_of(pre: Cubemap):
    meta = pre.metadata
    if meta.get("distribution", "charlie") != "charlie":
        raise ValueError(f"expected a Charlie-prefiltered map (metadata distribution 'charlie'), got {meta.get('distribution')!r}")
    return (int(meta.get("mapping_levels", pre.num_levels)), meta.get("lod_blend", DEFAULT_CHARLIE_LOD_BLEND),
            float(meta.get("min_roughness", MIN_ROUGHNESS)))


def charlie_lookup(pre: Cubemap, dirs, sheen_roughness, *, lod_blend: str | None = None):
    """LD_c at directions dirs (..., 3) and sheen roughness (scalar or (...)) from a
    `prefilter_charlie` chain -> (..., C): trilinear `Cubemap.sample` at
    `charlie_roughness_to_lod` (blend from the map's metadata unless given). Traceable (jit,
    vmap, grad): finite gradients in roughness (0 below the floor) and in dirs."""
    M, blend, floor = _lookup_of(pre)
    blend = blend if lod_blend is None else lod_blend
    dirs = jnp.asarray(dirs, pre.dtype)
    r = jnp.asarray(sheen_roughness, pre.dtype)
    lod = charlie_roughness_to_lod(r, M, lod_blend=blend, min_roughness=floor)
    return pre.sample(dirs, jnp.broadcast_to(lod, dirs.shape[:-1]))


# ------------------------------------------------------------------------------------------
# fast path
# ------------------------------------------------------------------------------------------


#: A (output, source texel) pair whose footprint is at least this many ring widths across in both
#: directions (K min(a, b) > TRAPEZOID_MIN) is weighted with the exact mean of w over the texel's
#: parallelogram (the distribution of c is a trapezoid); below it, with the mean over a box in c of
#: the same variance (the two differ at 4th order in the footprint / kernel scale, and the
#: trapezoid's second difference would cancel in float32 where the kernel is smooth).
TRAPEZOID_MIN = 0.25


def _charlie_chunk(Rc, Kc, D, EA, EB, logom, Lw, *, trapezoid: bool):
    """sum_j W_j (L_j, 1) / max_j W_j for output directions Rc (chunk, 3) with exponents K (chunk,)
    over source texels: centres D (P, 3), edge vectors EA, EB (P, 3) (the texel's sides, tangent,
    of angular length), log Omega_j (P,), [L, 1] (P, C+1). W_j = Omega_j x the mean of
    w(c) = c ((1-c)/2)^K over the texel, c linear across it (gradient R on the tangent plane):
    c = c_j + a u + b v, u, v uniform in [-1/2, 1/2], a = |R.A_j|, b = |R.B_j|. Per-row constant
    factors (2^-K / ((K+1)(K+2))) are dropped: they cancel in the ratio. trapezoid (static): whether
    any pair of the chunk's level can need the parallelogram mean (`TRAPEZOID_MIN`)."""
    dt = Rc.dtype
    one = 1.0 - jnp.finfo(dt).eps
    hp = functools.partial(jnp.matmul, precision=HIGHEST)
    c = jnp.clip(hp(Rc, D.T), -1.0, 1.0)  # (chunk, P)
    a0 = jnp.abs(hp(Rc, EA.T))
    b0 = jnp.abs(hp(Rc, EB.T))
    a = jnp.maximum(a0, b0)
    b = jnp.minimum(a0, b0)
    K = Kc[:, None]
    k1 = K + 1.0

    # Box in c of the footprint's variance: mean = (G(lo) - G(hi)) / width (/ (K+1)(K+2)),
    # G(x) = (1 - x)^(K+1) (1 + (K+1) x), decreasing on [0, 1].
    half = 0.5 * jnp.sqrt(a * a + b * b)
    lo = jnp.clip(c - half, 0.0, one)
    hi = jnp.clip(c + half, 0.0, one)
    ok = hi > lo
    lo_s = jnp.where(ok, lo, 0.0)
    hi_s = jnp.where(ok, hi, 0.5)
    gl = k1 * jnp.log1p(-lo_s) + jnp.log1p(k1 * lo_s)
    gh = k1 * jnp.log1p(-hi_s) + jnp.log1p(k1 * hi_s)
    base = gl
    ratio = -jnp.expm1(jnp.minimum(gh - gl, 0.0)) / jnp.where(ok, 2.0 * half, 1.0)
    live = ok
    if trapezoid:
        # Parallelogram: mean = (h(x1) - h(x2) - h(x3) + h(x4)) / (a b (K+3)) (/ (K+1)(K+2)) at
        # x = c +- (a+b)/2, c +- (a-b)/2, h the second antiderivative (up to constants):
        # h(x) = (1 - x)^(K+2) (2 + (K+1) x) on [0, 1], 2 - (K+3) x below 0 (w = 0 there), 0 at 1.
        def logh(x):
            xs = jnp.clip(x, 0.0, one)
            return (K + 2.0) * jnp.log1p(-xs) + jnp.log(jnp.where(x < 0, 2.0 - (K + 3.0) * x, 2.0 + k1 * xs))

        p, m = 0.5 * (a + b), 0.5 * (a - b)
        l1, l2, l3, l4 = logh(c + p), logh(c + m), logh(c - m), logh(c - p)  # l4 the largest
        sec = jnp.exp(l1 - l4) - jnp.exp(l2 - l4) - jnp.exp(l3 - l4) + 1.0
        need = K * b > TRAPEZOID_MIN
        use = need & (c + p > 0) & (sec > 0)
        base = jnp.where(need, l4, base)
        ratio = jnp.where(need, sec / jnp.where(use, a * b * (K + 3.0), 1.0), ratio)
        live = jnp.where(need, use, live)
    live = live & (ratio > 0)
    logw = jnp.where(live, base + jnp.log(jnp.where(live, ratio, 1.0)) + logom[None, :], -jnp.inf)
    mx = jax.lax.stop_gradient(jnp.max(logw, axis=1, keepdims=True))
    w = jnp.exp(logw - mx)
    return hp(w, Lw)


@functools.partial(jax.jit, static_argnames=("plan", "chunk"))
def _charlie_rows(R, K, D, EA, EB, logom, L, *, plan, chunk):
    """LD_c (N, C) at directions R (N, 3) with per-row exponents K = 1/(2 alpha) (N,); plan: per
    level (rows, trapezoid) (static), the levels' rows consecutive."""
    Lw = jnp.concatenate([L, jnp.ones(L.shape[:1] + (1,), L.dtype)], -1)
    out, row = [], 0
    for n, trap in plan:
        fn = functools.partial(_charlie_chunk, D=D, EA=EA, EB=EB, logom=logom, Lw=Lw, trapezoid=trap)
        out.append(map_row_chunks(fn, chunk, R[row : row + n], K[row : row + n]))
        row += n
    acc = jnp.concatenate(out)
    C = L.shape[-1]
    return acc[:, :C] / acc[:, C:]


@functools.lru_cache(maxsize=8)
def _texel_edges(S: int):
    """Edge vectors (6 S^2, 3) of every texel along s and along t: the chord between the
    directions of the midpoints of its two opposite sides (float64, tangent to second order)."""
    c = (np.arange(S) + 0.5) / S
    s = np.broadcast_to(c[None, None, :], (6, S, S))
    t = np.broadcast_to(c[None, :, None], (6, S, S))
    f = np.broadcast_to(np.arange(6)[:, None, None], (6, S, S))
    unit = lambda d: d / np.linalg.norm(d, axis=-1, keepdims=True)
    h = 0.5 / S
    EA = unit(face_to_dir(f, s + h, t, xp=np)) - unit(face_to_dir(f, s - h, t, xp=np))
    EB = unit(face_to_dir(f, s, t + h, xp=np)) - unit(face_to_dir(f, s, t - h, xp=np))
    return EA.reshape(-1, 3), EB.reshape(-1, 3)


def _source_level(env: Cubemap, source_size: int):
    """The area-correct pyramid level of env with the largest face <= source_size (level 0 when
    env is no larger, or when its size cannot be halved further)."""
    S0 = env.face_size
    steps, S = 0, S0
    while S > source_size and S % 2 == 0:
        S //= 2
        steps += 1
    if steps == 0:
        return env.levels[0]
    if env.num_levels > steps and env.levels[steps].shape[1] == S:
        return env.levels[steps]  # assume the stored chain is the area-correct pyramid
    return env.level_cube(0).with_mips(steps + 1).levels[-1]


def prefilter_charlie(
    env: Cubemap,
    *,
    size: int | None = None,
    num_levels: int | None = None,
    dtype=None,
    source_size: int | None = None,
    lod_blend: str = DEFAULT_CHARLIE_LOD_BLEND,
    min_roughness: float = MIN_ROUGHNESS,
    chunk: int | None = None,
    method: str = DEFAULT_CHARLIE_METHOD,
    rings: int = DEFAULT_CHARLIE_RINGS,
    phi_density: float = DEFAULT_CHARLIE_PHI_DENSITY,
    lod_bias: float = DEFAULT_CHARLIE_LOD_BIAS,
    zonal_levels: int = DEFAULT_CHARLIE_ZONAL_LEVELS,
    zonal_source_size: int | None = None,
) -> Cubemap:
    """Charlie-prefiltered chain: level m holds LD_c(R, r_m) at (S >> m)^2 texel centres,
    r_m = m/(M-1), alpha_m = max(r_m, min_roughness)^2 (module docstring).

    size: S (default DEFAULT_CHARLIE_SIZE); num_levels: M (default min(DEFAULT_CHARLIE_LEVELS,
    levels S allows)); dtype: of the computation and the result (default env.dtype; float32 is
    finite at every roughness); source_size: face size of the environment's pyramid level summed
    in full (default DEFAULT_CHARLIE_SOURCE_SIZE; the env's own level 0 when it is smaller);
    lod_blend: the lookup recorded in the metadata (`charlie_roughness_to_lod`).
    method: "zonal" (levels < zonal_levels by the zonal path, the rest by the box path) or "box"
    (every level by the box path); rings, phi_density, lod_bias, zonal_source_size: the zonal
    path's ring count cap, samples per texel along a ring, source-level bias, finest pyramid
    level read (default DEFAULT_CHARLIE_ZONAL_SOURCE_SIZE). source_size is the box path's.
    Linear (differentiable) in env's texel values.
    """
    _check_blend(lod_blend)
    check_radiance("prefilter_charlie: env", env)
    S = DEFAULT_CHARLIE_SIZE if size is None else positive_int("size", size)
    most = mip_count(S)
    M = min(DEFAULT_CHARLIE_LEVELS, most) if num_levels is None else positive_int("num_levels", num_levels)
    if M > most:
        raise ValueError(f"a {S}^2 Charlie chain supports at most {most} levels (each halves the face); asked for {M}")
    floor = float(min_roughness)
    if not 0.0 < floor <= 1.0:
        raise ValueError(f"min_roughness must be in (0, 1], got {min_roughness}")
    if method not in CHARLIE_METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {CHARLIE_METHODS}")
    dt = np.dtype(env.dtype if dtype is None else dtype)
    rough = charlie_level_roughness(M)
    alphas = _alpha(rough, floor, np)
    R_all, sizes = [], []
    for m in range(M):
        Sm = max(1, S >> m)
        R_all.append(texel_directions(Sm).reshape(-1, 3))
        sizes.append(Sm)
    dev = lambda x: jax.device_put(np.asarray(x, dt))  # noqa: E731
    C = env.channels
    Z = 0 if method == "box" else min(M, positive_int("zonal_levels", zonal_levels) if zonal_levels else 0)
    outs, method_info = [], {"prefilter_method": "charlie_box" if Z == 0 else ("charlie_zonal" if Z == M else "charlie_zonal+box")}
    if Z < M:  # the box method for levels Z..M-1
        src_target = DEFAULT_CHARLIE_SOURCE_SIZE if source_size is None else positive_int("source_size", source_size)
        src = _source_level(env, src_target)
        Ss = src.shape[1]
        D = texel_directions(Ss).reshape(-1, 3)
        om = texel_solid_angles(Ss).reshape(-1)
        K_all = [np.full(len(Rm), 0.5 / am) for Rm, am in zip(R_all[Z:], alphas[Z:])]
        EA, EB = _texel_edges(Ss)
        longest = float(np.max(np.minimum(np.linalg.norm(EA, axis=1), np.linalg.norm(EB, axis=1))))
        plan = tuple((len(Rm), bool(0.5 / am * longest > TRAPEZOID_MIN)) for Rm, am in zip(R_all[Z:], alphas[Z:]))
        outs.append(_charlie_rows(
            dev(np.concatenate(R_all[Z:])), dev(np.concatenate(K_all)), dev(D), dev(EA), dev(EB), dev(np.log(om)),
            jnp.asarray(src, dt).reshape(-1, C), plan=plan, chunk=positive_int("chunk", CHUNK if chunk is None else chunk),
        ))
        method_info.update({
            "source_face_size": str(Ss),
            "source_filter": "every texel of the environment's area-correct pyramid level source_face_size^2; "
                             "kernel box-filtered in c = R.l over each texel (mean of w over c +- sqrt(Omega) sin(theta)/2)",
        })
    if Z > 0:  # the zonal method for levels 0..Z-1
        S0 = env.face_size
        src_z = DEFAULT_CHARLIE_ZONAL_SOURCE_SIZE if zonal_source_size is None else positive_int("zonal_source_size", zonal_source_size)
        pyr_sizes = tuple(S0 >> i for i in range(mip_count(S0)))
        finest = _finest_level(S0, src_z)
        rings = positive_int("rings", rings)
        if not phi_density > 0:
            raise ValueError(f"phi_density must be > 0, got {phi_density}")
        tables, plan, counts = [], [], []
        for Rm, am in zip(R_all[:Z], alphas[:Z]):
            local, w, lod = _zonal_samples(float(am), pyr_sizes, finest, rings, float(phi_density), float(lod_bias))
            tables.append((dev(local), dev(w), jax.device_put(lod)))
            plan.append(len(Rm))
            counts.append(len(w))
        outs.insert(0, _zonal_rows(
            jnp.asarray(env.levels[0], dt), dev(np.concatenate(R_all[:Z])), tuple(tables), plan=tuple(plan),
            sizes=pyr_sizes, chunk=positive_int("chunk", ZONAL_CHUNK if chunk is None else chunk),
        ))
        method_info.update({
            "zonal_levels": str(Z),
            "zonal_source_face_size": str(pyr_sizes[finest]),
            "zonal_filter": "levels < zonal_levels: rings of equal weight in c = R.l at their conditional mean cosine, "
                            "each sampled along its azimuth with bilinear lookups in the environment's area-correct "
                            "pyramid at the level whose texel matches the ring's width (no finer than "
                            "zonal_source_face_size^2)",
            "charlie_samples": ",".join(str(n) for n in counts),
        })
        if Z == M:
            method_info["source_face_size"] = str(pyr_sizes[finest])
    out = jnp.concatenate(outs) if len(outs) > 1 else outs[0]
    levels, row = [], 0
    for Sm in sizes:
        n = 6 * Sm * Sm
        levels.append(out[row : row + n].reshape(6, Sm, Sm, C))
        row += n
    info = {
        "quantity": "LD_c(R, r_m) = int L D_charlie(h) (R.l)+ dl / int D_charlie(h) (R.l)+ dl, n = v = R "
                    "(KHR_materials_sheen IBL, Khronos glTF-IBL-Sampler's Charlie filter)",
        "distribution": "charlie",
        "roughness_mapping": "linear",
        "mapping_levels": str(M),
        "level_roughness": ",".join(f"{x:.9g}" for x in rough),
        "min_roughness": f"{floor:g}",
        "alpha": "max(sheen_roughness, min_roughness)^2",
        **charlie_lookup_metadata(M, lod_blend=lod_blend, face_size=S, min_roughness=floor),
        **method_info,
    }
    return Cubemap(levels, info)


# ------------------------------------------------------------------------------------------
# zonal path: rings in c = R.l, filtered samples along each ring
# ------------------------------------------------------------------------------------------

def _mean_texel(S: int) -> float:
    """Mean angular size of a texel of an S^2 cube face (sqrt of the mean solid angle)."""
    return math.sqrt(4.0 * math.pi / 6.0) / S


@functools.lru_cache(maxsize=128)
def _zonal_samples(alpha: float, sizes: tuple, finest: int, rings: int, density: float, lod_bias: float):
    """Local-frame samples (k, 3) (R = +z), weights (k,) (sum 1, float64), integer source levels
    (k,) for the Charlie weight w(c) = c (1 - c)^K (K = 1/(2 alpha), dc dphi measure: c is
    Beta(2, K+1)).

    The weight is cut into n equal-mass bands in c (n: the bands' typical angular width about the
    finest level's texel, at most `rings`); band i is a ring at its conditional mean cosine c_i
    (so the mass and the mean cosine are exact: constant and linear environments are reproduced
    up to the pyramid's filtering), of angular width dtheta_i = (b - a) / sin(theta_i). The ring
    reads the pyramid level whose texel matches dtheta_i (+ lod_bias, at least `finest`), at
    n_phi = 2 pi sin(theta_i) / texel * density equally spaced azimuths (offsets staggered
    between rings), each of weight 1/(n n_phi)."""
    from scipy.special import betainc, betaincinv

    K = 0.5 / alpha
    a, b = 2.0, K + 1.0
    L = len(sizes)
    t0 = _mean_texel(sizes[0])
    mean = a / (a + b)
    sd = math.sqrt(a * b / ((a + b) ** 2 * (a + b + 1)))
    width = math.sqrt(12.0) * sd / math.sqrt(max(1.0 - mean * mean, 1e-12))
    n = int(min(rings, max(1, math.ceil(width / _mean_texel(sizes[finest])))))
    q = np.concatenate([[0.0], betaincinv(a, b, np.arange(1, n) / n), [1.0]])
    # Conditional mean: E[c; band] = mean (I_3(hi) - I_3(lo)) with I_3 the Beta(3, K+1) cdf.
    m3 = betainc(a + 1, b, q)
    c = n * mean * np.diff(m3)
    c2 = n * mean * (a + 1.0) / (a + b + 1.0) * np.diff(betainc(a + 2.0, b, q))
    sin = np.sqrt(np.maximum(1.0 - c * c, 0.0))
    # The band's width: that of a box in c with its conditional variance, in angle about theta_i.
    dth = np.sqrt(12.0 * np.maximum(c2 - c * c, 0.0)) / np.maximum(sin, 1e-6)
    local, wts, lods = [], [], []
    golden = 0.5 * (math.sqrt(5.0) - 1.0)
    for i in range(n):
        lod = math.log2(max(dth[i], 1e-12) / t0) + lod_bias
        lv = int(min(L - 1, max(finest, math.ceil(lod - 1e-9))))
        nphi = int(min(MAX_PHI, max(3, math.ceil(2.0 * math.pi * sin[i] / _mean_texel(sizes[lv]) * density))))
        while nphi == MAX_PHI and lv < L - 1 and 2.0 * math.pi * sin[i] / _mean_texel(sizes[lv]) * density > MAX_PHI:
            lv += 1
            nphi = int(min(MAX_PHI, max(3, math.ceil(2.0 * math.pi * sin[i] / _mean_texel(sizes[lv]) * density))))
        phi = 2.0 * math.pi * (np.arange(nphi) + (i * golden) % 1.0) / nphi
        local.append(np.stack([sin[i] * np.cos(phi), sin[i] * np.sin(phi), np.full(nphi, c[i])], -1))
        wts.append(np.full(nphi, 1.0 / (n * nphi)))
        lods.append(np.full(nphi, lv, np.int32))
    return np.concatenate(local), np.concatenate(wts), np.concatenate(lods)


def _zonal_chunk(Rc, flat, local, w, lod, *, sizes):
    """sum_k w_k L(l_k) for output directions Rc (chunk, 3): l_k = local_k in the frame of R,
    bilinear in the pyramid level lod_k."""
    pyr = _Pyramid(None, flat=flat, sizes=list(sizes))
    t, b = tangent_frame(Rc)
    l = t[:, None, :] * local[None, :, 0:1] + b[:, None, :] * local[None, :, 1:2] + Rc[:, None, :] * local[None, :, 2:3]
    from .cubemap import dir_to_face

    face, s, tt = dir_to_face(l)
    rad = pyr.bilinear(face, s, tt, jnp.broadcast_to(lod, s.shape))
    return jnp.einsum("ckz,k->cz", rad, w, precision=HIGHEST) / jnp.sum(w)


@functools.partial(jax.jit, static_argnames=("plan", "sizes", "chunk"))
def _zonal_rows(level0, R, tables, *, plan, sizes, chunk):
    """LD_c rows of every level: R (N, 3) the levels' directions consecutive, plan the rows per
    level (static), tables per level (local, w, lod)."""
    levels = _mip_chain(level0, len(sizes)) if len(sizes) > 1 else (level0,)
    from .cubemap import _pad_level

    flat = jnp.concatenate([_pad_level(lv).reshape(-1, lv.shape[-1]) for lv in levels], 0)
    out, row = [], 0
    for n, (local, w, lod) in zip(plan, tables):
        fn = jax.checkpoint(functools.partial(_zonal_chunk, flat=flat, local=local, w=w, lod=lod, sizes=sizes))
        out.append(map_row_chunks(fn, chunk, R[row : row + n]))
        row += n
    return jnp.concatenate(out)


def _finest_level(S0: int, source_size: int) -> int:
    steps, S = 0, S0
    while S > source_size and S % 2 == 0:
        S //= 2
        steps += 1
    return steps


# ------------------------------------------------------------------------------------------
# float64 reference
# ------------------------------------------------------------------------------------------


def _reference_supersample(alpha: float, S0: int, max_q: int = REFERENCE_MAX_Q) -> int:
    """Sub-texels per source-texel side so that a sub-texel is <= a quarter of the ring's width
    2 alpha (capped at max_q)."""
    texel = 2.0 * math.atan(1.0 / S0)
    return int(min(max_q, max(1, math.ceil(texel / (0.5 * alpha)))))


def charlie_reference(env: Cubemap, dirs, roughness: float, *, supersample: int | None = None,
                      min_roughness: float = MIN_ROUGHNESS, chunk: int = 32) -> np.ndarray:
    """float64 LD_c(R, r) at unit directions dirs (..., 3) by brute force over every texel of env
    level 0 (q x q sub-texels each, q from `_reference_supersample` unless given), kernel
    `sheen.d_charlie(n.h, alpha, (1 - c)/2) (R.l)+`, alpha = max(r, min_roughness)^2
    -> (..., C) float64 NumPy."""
    check_radiance("charlie_reference: env", env)
    r = float(roughness)
    if not 0.0 <= r <= 1.0:
        raise ValueError(f"roughness must be in [0, 1], got {r}")
    alpha = max(r, float(min_roughness)) ** 2
    q = _reference_supersample(alpha, env.face_size) if supersample is None else positive_int("supersample", supersample)
    chunk = positive_int("chunk", chunk)
    return lobe_reference(env, dirs, _charlie_kernel, alpha, q=q, chunk=chunk, budget=1 << 21)


def _charlie_kernel(c, alpha):
    """D_c(h) (R.l)+ at c = R.l, n = v = R: n.h = sqrt((1 + c)/2), sin^2 = (1 - c)/2."""
    c = jnp.clip(c, -1.0, 1.0)
    return d_charlie(jnp.sqrt(0.5 * (1.0 + c)), alpha, 0.5 * (1.0 - c)) * jnp.maximum(c, 0.0)


#: The float64 sum of `charlie_reference` (the Charlie lobe in `lobe_reference.lobe_reference_sum`).
_reference_sum = functools.partial(lobe_reference_sum, lobe=_charlie_kernel)
