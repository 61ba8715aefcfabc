"""GGX-prefiltered specular environment mips (the "LD" term of the split sum).

Level m of the result stores (docs/conventions.md, docs/math.md 3.3)

    LD(R, r_m) = integral L(l) D(h) (R.l)+ dl / integral D(h) (R.l)+ dl,     n = v = R, h = (R+l)/|R+l|,

at the texel centres of a (S >> m)^2 cube, with r_m given by the roughness -> mip mapping:
"linear" (default, glTF viewer / Khronos sampler / LearnOpenGL): r_m = m/(M-1);
"quadratic" (Filament): r_m = 1 - sqrt(1 - m/(M-1)). Level 0 (r = 0) is the source itself (D is a
delta). The chain stops at DEFAULT_CHAIN_FLOOR^2 faces by default, with at least MIN_CHAIN_LEVELS
levels (`default_num_levels`).

The lookup between two levels (`roughness_to_lod`, option lod_blend) is either the mapping's own
formula ("roughness": lod = r (M-1), or (M-1) r (2 - r) for "quadratic"; what engines do) or,
by default, "mean_cosine": between the bracketing levels m, m+1 the weight is linear in the lobe's
mean cosine c(r) = int K (R.l) (R.l) dl / int K (R.l) dl, K = D(h) (R.l)+, alpha = r^2
(`lobe_mean_cosine`):

    lod = m + (c(r_m) - c(r)) / (c(r_m) - c(r_{m+1})),

which is exact for an environment linear in direction (LD = a + b c(alpha) R.d). Both choices, the
chain floor and the measured error behind them are in docs/ibl.md.

Two methods:

* `"fis"` (default): filtered importance sampling (Krivanek & Colbert 2008; Filament cmgen). The same
  GGX-distributed half vectors (Hammersley, NDF sampling with v = n) serve every texel; each sample
  reads the environment's area-correct pyramid trilinearly at
  lod = 1/2 log2(Omega_s/Omega_p) + bias, Omega_s = 1/(N p_l), p_l = D/4, Omega_p = 4 pi/(6 S0^2), so a
  sample averages the solid angle it stands for (bias 1 = K 4, GPU Gems 3 ch. 20). The estimate is
  sum L(l_k) NoL_k / sum NoL_k: a constant environment comes out constant to rounding.
* `"reference"`: float64 brute-force convolution over *every* texel of the environment's level 0
  (the environment being the piecewise-constant texel function), with each source texel split into
  q x q sub-texels when the lobe is narrower than 4 source texels. Memory is bounded by chunking
  over output texels. `prefilter_reference` evaluates it at arbitrary directions, which is how the
  error of `"fis"` is measured on large maps.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._api import keyword_only
from .._memory import check_samples, prefilter_bytes, require
from .._numerics import (
    HIGHEST,
    is_concrete,
    map_row_chunks,
    outside_traces,
    progress_token,
    row_chunk_count,
    safe_div,
)
from .._validate import check_radiance, positive_int
from ..conventions import luminance
from ..shading.sampling import hammersley, pdf_ggx_h, sample_ggx_h, tangent_frame
from .cubemap import (
    Cubemap,
    _mip_chain_impl,
    mip_count,
    _Pyramid,
    face_to_dir,
    texel_directions,
    texel_solid_angles,
)
from .lobe_reference import LOD_TABLE_STEPS, chain_lookup_metadata, check_lod_blend, lobe_reference, lobe_reference_sum

__all__ = [
    "DEFAULT_CHAIN_FLOOR",
    "DEFAULT_LOD_BLEND",
    "LOD_BLENDS",
    "MAPPINGS",
    "MIN_CHAIN_LEVELS",
    "PREFILTER_METHODS",
    "default_num_levels",
    "level_roughness",
    "levels_for_roughness",
    "lobe_mean_cosine",
    "lookup_metadata",
    "lookup_of",
    "prefilter",
    "prefilter_reference",
    "roughness_to_lod",
]

MAPPINGS = ("linear", "quadratic")
#: How `roughness_to_lod` blends two levels: "roughness" (the mapping's formula, lod = r (M-1) for
#: "linear") or "mean_cosine" (linear in the lobe's mean cosine between the bracketing levels).
LOD_BLENDS = ("roughness", "mean_cosine")
#: Default lookup blend (chosen from `jaxpbr report precompute`'s chain sweep; see docs/ibl.md): on an
#: environment linear in direction, lookups at random directions and roughnesses of a 128^2 chain
#: to 16^2 are off by mean 0.03 % / max 0.38 % with "mean_cosine" and 0.38 % / 7.1 % with "roughness".
DEFAULT_LOD_BLEND = "mean_cosine"
#: Default smallest face size of a prefiltered chain (see `default_num_levels`): smaller faces
#: cannot hold even a linear environment's convolution between texel centres (1^2: max 38 % at r = 1,
#: 4^2: 3.1 %, 8^2: 0.9-1.0 %, 16^2: 0.26 %).
DEFAULT_CHAIN_FLOOR = 16
#: ... but at least this many levels where the size allows (sources below 256^2 go below the floor):
#: fewer levels are coarser roughness steps, and on sharp real environments (an indoor loft, an
#: overcast sky) 3 levels of a 64^2 map were 1.5-2x worse than the old full chain (docs/ibl.md).
MIN_CHAIN_LEVELS = 5
#: The lookup a map is read with when its metadata predates "lod_blend" (jaxpbr before issue 11).
LEGACY_LOD_BLEND = "roughness"
PREFILTER_METHODS = ("fis", "reference")

#: Default FIS sample count per level (chosen from the error-vs-time sweep of `jaxpbr report
#: precompute`; see docs/ibl.md).
DEFAULT_SAMPLES = 256
#: Most FIS samples `default_sample_counts` gives a level.
MAX_SAMPLES = 4096
#: Default number of brightest source texels convolved exactly instead of sampled (see `split_bright`),
#: per 256^2 of face area: the budget is a solid angle (2.1 % of the sphere), so that a sun covers
#: the same share of it at every resolution (`default_exact_texels`). A fixed 256 let a 1-degree
#: 5e4 sun (~700 texels at 1024^2) stay in the sampled part: worst texel 130 % (issue 13); 256 per
#: 256^2 left most of a wide sun (a 4-degree Gaussian of peak 400: 5795 texels above 4x the mean at
#: 256^2) in the sampled part, whose clamp at the 257th texel (332, 220x the mean) the FIS could not
#: sample: worst texel 18 % at r = 0.25, 7 % at r = 0.5 and 1 (issue 23). The far field's grids and
#: second moments (`_bright_all`) keep the cost of thousands of texels near that of the sampling.
DEFAULT_EXACT_TEXELS = 8192
#: ... and at least this many (small faces).
MIN_EXACT_TEXELS = 256


def default_exact_texels(face_size: int) -> int:
    """max(MIN_EXACT_TEXELS, DEFAULT_EXACT_TEXELS x (face_size / 256)^2): 256 up to 45^2, 2048 at
    128^2, 8192 at 256^2, 32768 at 512^2, 131072 at 1024^2, 524288 at 2048^2. Only the texels
    actually above threshold are convolved (rounded up to a power of two), and far from them cell
    sums stand in for them (`_bright_all`)."""
    return max(MIN_EXACT_TEXELS, (DEFAULT_EXACT_TEXELS * face_size * face_size) // (256 * 256))
#: Default FIS LOD bias (+1 = Filament's K = 4).
DEFAULT_LOD_BIAS = 1.0


# ------------------------------------------------------------------------------------------
# roughness <-> mip
# ------------------------------------------------------------------------------------------


def default_num_levels(size: int, *, floor: int = DEFAULT_CHAIN_FLOOR, min_levels: int = MIN_CHAIN_LEVELS) -> int:
    """M of the default chain of a size^2 prefiltered cube: halving while the face stays >= floor
    (and even), but at least min_levels where the size allows (`cubemap` halving down to 1 x 1):
    1024 -> 7 (1024..16), 512 -> 6, 256 -> 5 (256..16), 128 -> 5 (128..8), 64 -> 5 (64..4),
    16 -> 5 (16..1), 4 -> 3, 1 -> 1."""
    S = positive_int("size", size)
    floor = positive_int("floor", floor)
    most = mip_count(S)
    M = 1
    while S % 2 == 0 and S // 2 >= floor:
        S //= 2
        M += 1
    return max(M, min(positive_int("min_levels", min_levels), most))


@keyword_only("mapping")
def level_roughness(num_levels: int, *, mapping: str = "linear") -> np.ndarray:
    """Perceptual roughness r_m of each level m = 0..M-1 (float64)."""
    _check_mapping(mapping)
    M = positive_int("num_levels", num_levels)
    x = np.arange(M) / max(M - 1, 1)
    if mapping == "linear":
        return x
    return 1.0 - np.sqrt(1.0 - x)


#: Gauss-Legendre nodes of `lobe_mean_cosine` (in s on [0, 1], see there): 1e-13 relative at every alpha.
_LOBE_NODES = 160
#: Points of the 1 - c(r) table `roughness_to_lod` interpolates (r = k/(n-1)); linear interpolation
#: in r is within 2e-7 of 1 - c.
_TABLE_POINTS = 1025


def lobe_mean_cosine(alpha) -> np.ndarray:
    """c(alpha) = int K (R.l)^2 dl / int K (R.l) dl with K = D(h) (R.l)+, n = v = R: the mean cosine of
    the prefiltering lobe about R, float64 NumPy (vectorised; no JAX). c(0) = 1, decreasing to
    2/3 at alpha = 1. For an environment linear in direction, L = a + b (l.d), LD(R, alpha) =
    a + b c(alpha) (R.d) exactly (the lobe is symmetric about R).

    As in `lobe_normalizer`, int D(h) (R.l)+^p dl = 4 E[(NoL)+^p] under GGX NDF sampling; with
    xi = sin^2(phi), tan(theta_h) = alpha tan(phi) and NoL = cos(2 theta_h) = (1 - t)/(1 + t),
    t = alpha^2 tan^2(phi), that is int_0^atan(1/alpha) NoL^p sin(2 phi) dphi. In psi = pi/2 - phi,
    psi = psi_0 (pi / (2 psi_0))^s, psi_0 = atan(alpha), the integrand is smooth in s at every alpha
    (the lobe's scale alpha becomes O(1) wide), and `_LOBE_NODES` Gauss-Legendre nodes converge.
    """
    a = np.atleast_1d(np.asarray(alpha, np.float64))
    out = np.ones_like(a)
    pos = a > 0
    if np.any(pos):
        x, w = np.polynomial.legendre.leggauss(_LOBE_NODES)
        s, w = 0.5 * (x + 1.0), 0.5 * w
        ap = a[pos][:, None]
        psi0 = np.arctan(ap)
        L = np.log(0.5 * np.pi / psi0)
        psi = psi0 * np.exp(s * L)
        jac = psi * L  # d psi / d s
        t = (ap / np.tan(psi)) ** 2  # alpha^2 tan^2(phi), tan(phi) = cot(psi)
        nol = (1.0 - t) / (1.0 + t)
        g = np.sin(2.0 * psi) * jac * w
        out[pos] = np.sum(g * nol * nol, -1) / np.sum(g * nol, -1)
    return out.reshape(np.shape(alpha))


@functools.lru_cache(maxsize=1)
def _one_minus_c_table() -> tuple[np.ndarray, np.ndarray]:
    """(r grid, 1 - c(r^2)) float64, computed once (about 10 ms)."""
    r = np.linspace(0.0, 1.0, _TABLE_POINTS)
    return r, 1.0 - lobe_mean_cosine(r * r)


def _one_minus_c(r, xp):
    """1 - c(r^2) by linear interpolation of the table (r in [0, 1]); xp = np or jnp. 1 - c rather
    than c: near r = 0, c - 1 would cancel in float32."""
    grid, tab = _one_minus_c_table()
    if xp is np:
        return np.interp(r, grid, tab)
    dt = jnp.result_type(r, float)
    return jnp.interp(r, jnp.asarray(grid, dt), jnp.asarray(tab, dt))


def _check_blend(lod_blend):
    check_lod_blend(lod_blend, LOD_BLENDS)


@keyword_only("mapping")
def roughness_to_lod(r, num_levels: int, *, mapping: str = "linear", lod_blend: str = DEFAULT_LOD_BLEND, xp=jnp):
    """Fractional mip level for perceptual roughness r (clamped to [0, 1]), for `Cubemap.sample`.

    num_levels: M of the map's chain (its metadata "mapping_levels"; `lookup_of` reads all three).
    mapping: where the levels are ("linear": r_m = m/(M-1); "quadratic": Filament's).
    lod_blend: "mean_cosine" (default): between the bracketing levels, linear in the lobe's mean
        cosine c (`lobe_mean_cosine`; exact for an environment linear in direction);
        "roughness": the mapping's formula, lod = r (M-1) ("linear") or (M-1) r (2 - r)
        ("quadratic"), as engines do. Both give lod = m at r = r_m, and 0 at r = 0, M-1 at r = 1.
    xp: jnp (traceable: jit, vmap, grad; finite gradients on [0, 1], ends included) or np.
    """
    _check_mapping(mapping)
    _check_blend(lod_blend)
    M = positive_int("num_levels", num_levels)
    r = xp.clip(r, 0.0, 1.0)
    if lod_blend == "roughness":
        L = M - 1
        return r * L if mapping == "linear" else r * (2.0 - r) * L
    if M == 1:
        return r * 0.0
    # The levels' 1 - c through the same table interpolation as r's: lod(r_m) = m exactly.
    g_levels = _one_minus_c(level_roughness(M, mapping=mapping), np)
    g = _one_minus_c(r, xp)
    if xp is np:
        return np.interp(g, g_levels, np.arange(M, dtype=np.float64))
    dt = g.dtype
    return jnp.interp(g, jnp.asarray(g_levels, dt), jnp.arange(M, dtype=dt))


def levels_for_roughness(r_max: float, num_levels: int, *, mapping: str = "linear", lod_blend: str = DEFAULT_LOD_BLEND) -> int:
    """How many levels (from level 0) of an M-level chain the lookups of roughness <= r_max read:
    ceil(lod(r_max)) + 1, at most M. Plain Python (it runs at trace time, inside jit)."""
    M = positive_int("num_levels", num_levels)
    r = min(max(float(r_max), 0.0), 1.0)
    lod = float(roughness_to_lod(r, M, mapping=mapping, lod_blend=lod_blend, xp=np))
    return min(M, int(math.ceil(lod - 1e-9)) + 1)


def lookup_of(pre: Cubemap) -> tuple[int, str, str]:
    """(M, mapping, lod_blend) the prefiltered map `pre` is looked up with, from its metadata:
    "mapping_levels" (default: its own level count), "roughness_mapping" (default "linear") and
    "lod_blend" (default "roughness": maps written before the key existed keep the lookup they were
    made for)."""
    meta = pre.metadata
    dist = meta.get("distribution", "ggx")
    if dist != "ggx":
        raise ValueError(
            f"this map is {dist}-prefiltered (metadata 'distribution'), not a GGX-prefiltered map; pass "
            "the GGX map (jaxpbr.prefilter) as `pre` (a Charlie map is read by sheen_prefilter.charlie_lookup)."
        )
    M = int(meta.get("mapping_levels", pre.num_levels))
    return M, meta.get("roughness_mapping", "linear"), meta.get("lod_blend", LEGACY_LOD_BLEND)


def lookup_metadata(num_levels: int, *, mapping: str, lod_blend: str, face_size: int) -> dict:
    """The metadata keys that reproduce a chain's lookup beyond "roughness_mapping" and
    "mapping_levels" (written by `prefilter`, hence into the KTX2 key/values of `jaxpbr ibl` and
    `jaxpbr prefilter`): the blend and its formula, the chain's smallest face, each level's mean
    cosine c_m, and for engines "lod_table": lod at u = k/K, k = 0..K, K = LOD_TABLE_STEPS (M-1),
    u = r ("linear") or r (2 - r) ("quadratic"); linear interpolation of it in u is within 0.015
    lod of `roughness_to_lod` (the table's nodes fall on the levels)."""
    M = positive_int("num_levels", num_levels)
    _check_mapping(mapping)
    _check_blend(lod_blend)
    rough = level_roughness(M, mapping=mapping)
    K = LOD_TABLE_STEPS * (M - 1)
    u = np.linspace(0.0, 1.0, K + 1)
    r_nodes = u if mapping == "linear" else 1.0 - np.sqrt(np.clip(1.0 - u, 0.0, 1.0))
    table = roughness_to_lod(r_nodes, M, mapping=mapping, lod_blend=lod_blend, xp=np)
    plain = "lod = r*(M-1)" if mapping == "linear" else "lod = (M-1)*r*(2-r)"
    return chain_lookup_metadata(
        M,
        lod_blend=lod_blend,
        formula=plain if lod_blend == "roughness" else (
            "lod = m + (c_m - c(r)) / (c_m - c_{m+1}) between the levels m, m+1 whose roughness brackets r; "
            "c(r) = int K (R.l)^2 dl / int K (R.l) dl, K = D_GGX(h; alpha = r^2) (R.l)+, n = v = R; "
            "c_m = level_mean_cosine"
        ),
        face_size=face_size,
        level_mean_cosine=lobe_mean_cosine(rough * rough),
        table=table,
        abscissa=f"u = k/{K}, k = 0..{K}, u = {'r' if mapping == 'linear' else 'r*(2-r)'}; linear interpolation in u",
    )


def default_sample_counts(base: int, size: int, num_levels: int, max_samples: int = MAX_SAMPLES) -> list[int]:
    """FIS samples per level: `base` for the large levels, and as many more on the small (rough)
    levels as keeps the work per level at most that of a 64^2 level at `base` samples, capped at
    `max_samples` (a rough lobe reads coarse, blurry pyramid levels, so its error falls with more
    samples, and small levels make them cheap)."""
    budget = base * 6 * 64 * 64
    out = [base]
    for m in range(1, num_levels):
        texels = 6 * max(1, size >> m) ** 2
        out.append(int(min(max(base, max_samples), max(base, budget // texels))))
    return out


def _check_mapping(mapping):
    if mapping not in MAPPINGS:
        raise ValueError(f"unknown roughness->mip mapping {mapping!r}; choose one of {MAPPINGS}")


# ------------------------------------------------------------------------------------------
# filtered importance sampling
# ------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("n",))
def _ggx_lobe_samples(alpha, *, n: int):
    """n GGX half vectors (Hammersley points through `sample_ggx_h`) and the density of their
    reflected directions p_l = p_h / (4 n.h) for n = v = +z, as one program per n (the sample
    counts are few: one compile each, not one per level and per operation)."""
    dt = jnp.result_type(float)
    h = sample_ggx_h(hammersley(n, dt), alpha)
    cos_h = h[:, 2]
    return h, pdf_ggx_h(cos_h, alpha) / (4.0 * cos_h)


@functools.lru_cache(maxsize=64)
def _fis_samples(alpha: float, n: int, src_size: int, num_src_levels: int, lod_bias: float):
    """Local-frame light directions (n, 3), weights NoL (n,), source LODs (n,) for v = n = +z.

    `sampling.hammersley` points through `sampling.sample_ggx_h` (GGX NDF sampling in the sin^2
    form, docs/math.md 3.2, 8.3), l = 2 (n.h) h - n; pdf p_l = p_h / (4 v.h) = D/4 (`sampling.pdf_ggx_h`).
    Evaluated once per (alpha, n, source) in float64, eagerly even when `prefilter` is being traced
    (jit / grad): these are constants of the computation.
    """
    def run():
        with jax.enable_x64(True):
            h, pdf = _ggx_lobe_samples(np.float64(alpha), n=n)
            return np.asarray(h, np.float64), np.asarray(pdf, np.float64)

    h, pdf = outside_traces(run)
    cos_h = h[:, 2]
    local = 2.0 * cos_h[:, None] * h
    local[:, 2] -= 1.0
    nol = local[:, 2]
    keep = nol > 0
    # Samples below the horizon keep their slot with weight 0 (fixed shapes).
    local[~keep] = (0.0, 0.0, 1.0)
    omega_s = 1.0 / (n * pdf)
    omega_p = 4.0 * math.pi / (6.0 * src_size * src_size)
    lod = np.clip(0.5 * np.log2(omega_s / omega_p) + lod_bias, 0.0, num_src_levels - 1)
    return local, np.where(keep, nol, 0.0), np.where(keep, lod, 0.0)


#: FIS samples per row of work: a level's n samples are n / FIS_BATCH rows per output direction
#: (the last padded with weight 0), so every level runs through the same compiled loop body.
FIS_BATCH = 256


def _fis_rows_body(flat, R, table, local, w, lod, *, sizes):
    """Unnormalised sum_k w_k L(l_k) for a chunk of rows: directions R (chunk, 3), each with its
    own batch of FIS_BATCH local-frame samples (index `table` (chunk,) into local (T, k, 3), weights
    w (T, k), source LODs lod (T, k))."""
    pyr = _Pyramid(None, flat=flat, sizes=list(sizes))
    t, b = tangent_frame(R)
    lc, wc, dc = local[table], w[table], lod[table]  # (chunk, k, 3), (chunk, k), (chunk, k)
    l = t[:, None, :] * lc[..., 0:1] + b[:, None, :] * lc[..., 1:2] + R[:, None, :] * lc[..., 2:3]
    rad = pyr.sample(l, dc)  # (chunk, k, C)
    return jnp.einsum("ckz,ck->cz", rad, wc, precision=HIGHEST)


def _fis_rows(flat, sizes, R, table, local, w, lod, chunk: int, token=None):
    """`_fis_rows_body` over all rows, in chunks. Rematerialised under differentiation
    (`jax.checkpoint`): the backward pass recomputes the (chunk, k) lookups instead of storing
    them for every chunk, so differentiating a prefilter wrt the environment keeps the memory of
    one chunk."""
    body = jax.checkpoint(functools.partial(_fis_rows_body, sizes=sizes))
    return map_row_chunks(lambda Rc, tc: body(flat, Rc, tc, local, w, lod), chunk, R, table, token=token)


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



@functools.partial(jax.jit, static_argnames=("max_texels", "min_ratio"))
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


@functools.partial(jax.jit, static_argnames=("min_ratio",))
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
    seg = lambda x: jax.ops.segment_sum(x, slot, num_segments=n_slots)  # noqa: E731
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
    div = lambda x: safe_div(seg(w[:, None] * x), cw[:, None], has[:, None])  # noqa: E731
    outer = lambda a, b: jnp.stack([a[:, 0] * b[:, 0], a[:, 1] * b[:, 1], a[:, 2] * b[:, 2], a[:, 0] * b[:, 1], a[:, 0] * b[:, 2], a[:, 1] * b[:, 2]], -1)  # noqa: E731
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
    pad = lambda x: jnp.pad(x, ((0, n - x.shape[0]), (0, 0)))  # noqa: E731  (weight 0: adds nothing)
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
            far_sum = lambda: _bright_far_chunk(Rc, mu - fq[j] * dmu, cov + fq[j] * dcov, cBw[j], a2[j])  # noqa: E731
            return jax.lax.cond(near(grids[t]), lambda: from_tier(t + 1), far_sum)

        return from_tier(0)

    return map_row_chunks(jax.checkpoint(chunk_fn), chunk, R, level_of, token=token)


def _tile_order(x, S: int, inverse: bool = False):
    """Rows (6 S^2, ...) of a level's texels from face-major row order into b x b tiles (b = gcd(S,
    8)), or back (inverse): a chunk of 64 bright-pass directions is then an 8 x 8 patch, not a strip
    of a row (a compact chunk is far from more cells). Reshapes only (no index constants)."""
    b = math.gcd(S, 8)
    n = S // b
    tail = x.shape[1:]
    if inverse:
        y = x.reshape((6, n, n, b, b) + tail)
    else:
        y = x.reshape((6, n, b, n, b) + tail)
    return jnp.swapaxes(y, 2, 3).reshape(x.shape)


@functools.partial(jax.jit, static_argnames=("sizes", "plan", "chunk", "S0", "n_bright", "tiers", "n_slots", "far", "kink", "bright_chunk"))
def _prefilter_fis(level0, idx, bright, slots, omega, R, table, local, w, lod, token, *, sizes, plan, chunk, S0, n_bright, tiers, n_slots, far, kink, bright_chunk):
    """Every FIS level of a prefilter as one compiled program.

    level0: the (residual) source; its area-correct pyramid (`sizes`) is built here. R (rows, 3)
    and table (rows,) are the rows of work of all levels: level m contributes N_m directions x
    nb_m sample batches, direction-major. plan: per level (N_m, nb_m, alpha_m). Returns the levels'
    LD (6, S_m, S_m, C) as a tuple: the rows' sums reduced over batches and divided by the sample weights'
    sum, plus the exact convolution of the first n_bright bright-texel candidates (idx, bright:
    None for none). slots: per far-field grid g of `tiers` (`bright_tiers`), each candidate's cell
    slot (n_bright,) (None: numbered in the program), n_slots[t] of them; omega: one face's texel solid angles (S0, S0), an argument
    rather than a constant; token: a `progress_token` (None: no progress reports)."""
    flat = _Pyramid(_mip_chain_impl(level0, len(sizes))).flat
    sums = _fis_rows(flat, sizes, R, table, local, w, lod, chunk, token)
    out, row, tab = [], 0, 0
    for N, nb, _ in plan:
        part = sums[row : row + N * nb].reshape(N, nb, -1).sum(1)
        out.append(part / jnp.sum(w[tab : tab + nb]))
        row += N * nb
        tab += nb
    faces = lambda x: x.reshape(6, math.isqrt(x.shape[0] // 6), -1, x.shape[-1])  # noqa: E731  (N, C) -> (6, S, S, C)
    if idx is None:
        return tuple(faces(o) for o in out)
    # Bright pass: each level's directions in 8 x 8 tiles, padded to whole chunks (one source set
    # per chunk).
    Rb, lv_of, spans, pos, start = [], [], [], 0, 0
    for m, (N, nb, _) in enumerate(plan):
        Rm = R[start : start + N * nb : nb]  # the level's directions (rows are direction-major)
        Rm = _tile_order(Rm, math.isqrt(N // 6))
        start += N * nb
        padn = (-N) % bright_chunk
        Rb.append(jnp.concatenate([Rm, jnp.broadcast_to(Rm[:1], (padn, 3))]) if padn else Rm)
        lv_of.append(jnp.full((N + padn,), m, jnp.int32))
        spans.append((pos, N))
        pos += N + padn
    ex = _bright_all(
        jnp.concatenate(Rb), jnp.concatenate(lv_of), idx[:n_bright], bright[:n_bright], slots, omega, S0,
        tuple(a for _, _, a in plan), tiers, n_slots, far, kink, bright_chunk, token,
    )
    return tuple(faces(o + _tile_order(ex[p : p + N], math.isqrt(N // 6), inverse=True)) for o, (p, N) in zip(out, spans))


# ------------------------------------------------------------------------------------------
# float64 reference
# ------------------------------------------------------------------------------------------


def _reference_supersample(alpha: float, S0: int, max_q: int = 4) -> int:
    """Sub-texels per source-texel side so that sub-texels are <= alpha/4 across (lobe half-width
    in l is ~1.3 alpha), capped at `max_q`."""
    if alpha <= 0:
        return 1
    texel = 2.0 * math.atan(1.0 / S0)
    return int(min(max_q, max(1, math.ceil(texel / (alpha / 4.0)))))


def prefilter_reference(env: Cubemap, dirs, roughness: float, *, supersample: int | None = None, chunk: int = 64):
    """float64 LD(R, r) at unit directions `dirs` (..., 3) by brute force over every texel of
    env level 0 -> (..., C) float64 NumPy array.

    Kernel K(R.l) = D(h) (R.l)+ with h = (R + l)/|R + l|, n = v = R: with c = R.l,
    NoH^2 = (1+c)/2 and 1 - NoH^2 = (1-c)/2, so D is proportional to 1/((1-c)/2 + (1+c)/2 alpha^2)^2
    (constants cancel in the ratio). Each source texel is split into q x q sub-texels with their
    exact share of its solid angle (q from `_reference_supersample` unless given). r = 0 returns the
    bilinear lookup of the source (D is a delta).
    """
    check_radiance("prefilter_reference: env", env)
    r = float(roughness)
    if not 0.0 <= r <= 1.0:
        raise ValueError(f"roughness must be in [0, 1], got {r}")
    dirs = np.asarray(dirs, np.float64)
    if r == 0.0:
        with jax.enable_x64(True):
            return np.asarray(Cubemap(env.levels[0].astype(jnp.float64)).sample(jnp.asarray(dirs)))
    alpha = r * r
    q = _reference_supersample(alpha, env.face_size) if supersample is None else positive_int("supersample", supersample)
    chunk = positive_int("chunk", chunk)
    # Source rows per block: the (chunk, block points) kernel stays ~2^22 float64 whatever the face size.
    return lobe_reference(env, dirs, _ggx_kernel, alpha, q=q, chunk=chunk, budget=1 << 22)


def _ggx_kernel(c, alpha):
    """K(c) = D(h) (R.l)+ up to a constant, c = R.l, n = v = R: NoH^2 = (1+c)/2, 1 - NoH^2 = (1-c)/2."""
    a2 = alpha * alpha
    return jnp.maximum(c, 0.0) / (0.5 * (1.0 - c) + 0.5 * (1.0 + c) * a2) ** 2


#: The float64 sum of `prefilter_reference` (the GGX lobe in `lobe_reference.lobe_reference_sum`).
_reference_sum = functools.partial(lobe_reference_sum, lobe=_ggx_kernel)


# ------------------------------------------------------------------------------------------
# driver
# ------------------------------------------------------------------------------------------


def prefilter(
    env: Cubemap,
    size: int | None = None,
    *,
    num_levels: int | None = None,
    max_level: int | None = None,
    mapping: str = "linear",
    lod_blend: str = DEFAULT_LOD_BLEND,
    method: str = "fis",
    samples=None,
    lod_bias: float = DEFAULT_LOD_BIAS,
    exact_texels: int | None = None,
    chunk: int = 512,
    progress=None,
) -> Cubemap:
    """GGX-prefiltered specular cube map with mips: level m holds LD(R, r_m) at (S >> m)^2 texels.

    env: environment Cubemap; level 0 is the radiance (its pyramid is rebuilt area-correctly).
    size: face size S of level 0 of the result (default env.face_size); env.face_size / S must be
        a power of two (level 0 is then the env's area-correct pyramid level at that size).
    num_levels: M (default `default_num_levels(S)`: down to DEFAULT_CHAIN_FLOOR^2 faces, at least
        MIN_CHAIN_LEVELS levels; 256 -> 5 levels, 256^2 .. 16^2; 1024 -> 7; 128 -> 5, 128^2 .. 8^2).
    max_level: compute only levels 0..max_level of the M-level chain (default M - 1: all). The
        mapping still refers to M levels (metadata "mapping_levels"), so a scene whose roughness
        never exceeds r needs only levels up to ceil(lod(r)); lookups clamp to the last level.
    mapping: "linear" (r_m = m/(M-1)) or "quadratic" (Filament); recorded in the result's info.
    lod_blend: the lookup the map is made for ("mean_cosine" default, or "roughness"; see
        `roughness_to_lod`); it does not change the levels, only the metadata `shade_ibl` reads
        ("lod_blend", and what an engine needs to reproduce it: `lookup_metadata`).
    method: "fis" or "reference" (see module docstring).
    samples: FIS samples: an int n gives n on the large levels and more on the small, rough ones
        (`default_sample_counts`); a sequence of M ints sets every level (level 0 ignores it).
    exact_texels: at most this many brightest texels (default `default_exact_texels` of the
        environment's face size; those above max(4 x mean luminance, the
        (k+1)-th largest)) are clamped in the sampled map and their excess convolved exactly.
    progress: optional callable(done, total) for progress reporting, in chunks of work (method
        "fis": called from XLA's callback thread while the one program runs, at most once per
        percent, and once more from the caller's thread at the end; an exception it raises is
        re-raised here once the program returns); "reference": per level.

    Method "fis" is traceable in env's texel values (jax.jit, jax.grad / jax.vjp wrt env.levels[0]):
    the bright texels are a fixed-size top-k set with zero weights for the unselected ones (see
    `_split_bright_fixed`); traced, the metadata "exact_texels" reads "<=k" instead of the count.
    Options (size, num_levels, samples, ...) are static Python values.
    """
    if method not in PREFILTER_METHODS:
        raise ValueError(f"unknown prefilter method {method!r}; choose one of {PREFILTER_METHODS}")
    _check_mapping(mapping)
    _check_blend(lod_blend)
    check_radiance("prefilter: env", env)
    S0 = env.face_size
    S = S0 if size is None else positive_int("size", size)
    ratio = S0 // S if S <= S0 else 0
    if ratio == 0 or S0 % S or ratio & (ratio - 1):
        raise ValueError(
            f"prefilter size {S} must be the environment's face size {S0} divided by a power of two "
            f"(1, 2, 4, ...); resample the environment with Cubemap.from_equirect/from_function first"
        )
    most = mip_count(S)
    M = default_num_levels(S) if num_levels is None else positive_int("num_levels", num_levels)
    last = M - 1 if max_level is None else int(max_level)
    if not 0 <= last <= M - 1:
        raise ValueError(f"max_level must be in [0, {M - 1}] for a {M}-level chain, got {max_level}")
    if M > most:
        raise ValueError(f"a {S}^2 prefiltered cube supports at most {most} levels; asked for {M}")
    if samples is None:
        samples = DEFAULT_SAMPLES
    if isinstance(samples, (int, np.integer)) and not isinstance(samples, bool):
        per_level = default_sample_counts(positive_int("samples", samples), S, M)
    else:
        per_level = list(samples)
    if len(per_level) != M:
        raise ValueError(f"samples has {len(per_level)} entries; expected one per level ({M})")
    per_level = [check_samples("samples", positive_int("samples", n), where="prefilter") for n in per_level]
    if method == "fis":  # before any work: a huge size or sample count aborted inside XLA
        require(f"a prefilter of a {S0}^2 environment to {S}^2 with up to {max(per_level[1:], default=0)} samples per texel",
                prefilter_bytes(S0, S, per_level[: last + 1]), where="prefilter",
                names={"face_size": "the environment's face size"})

    full = env.level_cube(0).with_mips(int(round(math.log2(ratio))) + 1)  # down to the output size
    rough = level_roughness(M, mapping=mapping)
    levels = [full.levels[-1]]  # r = 0: the source at the output size
    idx = bright = None  # candidate bright texels (None: none) and their excess radiance
    n_bright = 0  # how many of the candidates are convolved exactly
    tiers = bright_tiers(S0)  # the far field's cell grids
    slots, n_slots = (None,) * len(tiers), ()  # the candidates' cell slots per grid (None: computed in the program)
    n_exact = "0"
    if method == "fis":
        exact_texels = default_exact_texels(S0) if exact_texels is None else int(exact_texels)
        if exact_texels < 0:
            raise ValueError(f"exact_texels must be >= 0, got {exact_texels}")
        src_level0 = env.levels[0]
        # One face's texel solid angles in the widest float available, an argument of the
        # programs (closed over, an S0^2 table was a constant once per level).
        omega = jax.device_put(np.asarray(texel_solid_angles(S0)[0], jnp.result_type(float)))
        if 0 < exact_texels < 6 * S0 * S0:
            # Concrete values: top_k over a power of two above the count of texels over the
            # threshold, not the whole budget (the same selection; 524288 of 2048^2 faces took 4 s).
            k = _selection_size(src_level0, omega, exact_texels) if is_concrete(src_level0) else exact_texels
            resid, idx, bright, sel = _split_bright_fixed(src_level0, omega, k)
            if is_concrete(sel):
                # Concrete values: convolve only the selected texels (a prefix of the candidates,
                # which come in decreasing luminance), rounded up to a power of two (the extra
                # candidates have zero excess) so that few distinct programs are compiled; the
                # far-field cells of each grid numbered over the occupied ones only (also a power
                # of two).
                n = int(np.count_nonzero(np.asarray(sel)))
                n_exact = str(n)
                n_bright = min(exact_texels, 1 << max(0, n - 1).bit_length()) if n else 0
                slots = []
                for g in tiers:
                    cells = bright_cells(np.asarray(idx[:n]).astype(np.int64), S0, g)[0]
                    occupied, inverse = np.unique(cells, return_inverse=True)
                    slot = np.zeros(n_bright, np.int32)
                    slot[:n] = inverse.reshape(-1)
                    slots.append(slot)
                    n_slots += (1 << max(0, len(occupied) - 1).bit_length(),)
            else:
                n_exact = f"<={exact_texels}"  # traced: the count is not known here
                n_bright = exact_texels
                n_slots = tuple(min(6 * g * g, n_bright) for g in tiers)
            if n_bright:
                src_level0 = resid
            else:
                idx = bright = None
        sizes = tuple(S0 >> i for i in range(mip_count(S0)))
        dt = np.dtype(env.dtype)
        # Rows of work of all levels (direction-major: N_m directions x nb_m sample batches) and
        # their sample tables stacked: one program computes the whole chain.
        plan, R_rows, tables, tabs, t0 = [], [], [], [], 0
        for m in range(1, last + 1):
            dirs = texel_directions(max(1, S >> m)).reshape(-1, 3)
            alpha = float(rough[m]) ** 2
            local, w, lod = _fis_samples(alpha, per_level[m], S0, len(sizes), float(lod_bias))
            kpad = (-len(w)) % FIS_BATCH
            if kpad:
                local = np.concatenate([local, np.tile([[0.0, 0.0, 1.0]], (kpad, 1))])
                w, lod = np.concatenate([w, np.zeros(kpad)]), np.concatenate([lod, np.zeros(kpad)])
            nb = len(w) // FIS_BATCH
            tables.append((local.reshape(nb, FIS_BATCH, 3), w.reshape(nb, FIS_BATCH), lod.reshape(nb, FIS_BATCH)))
            R_rows.append(np.repeat(dirs, nb, axis=0))
            tabs.append(np.tile(np.arange(t0, t0 + nb, dtype=np.int32), len(dirs)))
            plan.append((len(dirs), nb, alpha))
            t0 += nb
        if plan:
            dev = lambda x, t=dt: jax.device_put(np.asarray(x, t))  # noqa: E731  (a copy, no XLA program)
            chunk = positive_int("chunk", chunk)
            R_all = np.concatenate(R_rows)
            # Progress: the FIS chunks, then the bright pass's (each level padded to whole chunks).
            total = row_chunk_count(len(R_all), chunk)
            if n_bright:
                total += row_chunk_count(sum(N + (-N) % BRIGHT_CHUNK for N, _, _ in plan), BRIGHT_CHUNK)
            with progress_token(progress, total) as token:
                lvs = _prefilter_fis(
                    src_level0, idx, bright, tuple(None if sl is None else dev(sl, np.int32) for sl in slots), omega,
                    dev(R_all), dev(np.concatenate(tabs), np.int32),
                    *(dev(np.concatenate([tb[i] for tb in tables])) for i in range(3)), token,
                    sizes=sizes, plan=tuple(plan), chunk=chunk, S0=S0, n_bright=n_bright, tiers=tiers, n_slots=n_slots,
                    far=float(BRIGHT_FAR), kink=float(BRIGHT_KINK), bright_chunk=BRIGHT_CHUNK,
                )
                if token is not None:
                    lvs = jax.block_until_ready(lvs)
            levels.extend(lvs)
    else:
        for m in range(1, last + 1):
            Sm = max(1, S >> m)
            ld = prefilter_reference(env, texel_directions(Sm).reshape(-1, 3), float(rough[m]))
            levels.append(jnp.asarray(ld.reshape(6, Sm, Sm, -1), env.dtype))
            if progress is not None:
                progress(m, last)
    info = {
        "quantity": "LD(R, r_m) = int L D (R.l)+ dl / int D (R.l)+ dl, n = v = R (Karis split sum)",
        "roughness_mapping": mapping,
        "mapping_levels": str(M),
        "level_roughness": ",".join(f"{x:.9g}" for x in rough),
        **lookup_metadata(M, mapping=mapping, lod_blend=lod_blend, face_size=S),
        "prefilter_method": method,
    }
    if method == "fis":
        info["fis_samples"] = ",".join(str(n) for n in per_level)
        info["fis_lod_bias"] = f"{float(lod_bias):g}"
        info["exact_texels"] = n_exact
    return Cubemap(levels, info)
