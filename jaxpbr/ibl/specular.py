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
  sample averages the solid angle it stands for (default bias 0; GPU Gems 3 ch. 20 and Filament use 1,
  K = 4, which blurs every sample over four times its solid angle: see DEFAULT_LOD_BIAS). The estimate is
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
)
from .._program_cache import cpu_jit
from .._validate import check_radiance, positive_int
from ..shading.sampling import hammersley, pdf_ggx_h, sample_ggx_h, tangent_frame
from .bright import (  # noqa: F401  (re-exported: jaxpbr.ibl.specular is the prefilter's public module)
    BRIGHT_CELLS,
    BRIGHT_CHUNK,
    BRIGHT_FAR,
    BRIGHT_KINK,
    _angle,
    _bright_all,
    _bright_chunk,
    _bright_clusters,
    _bright_far_chunk,
    _bright_sources,
    _count_bright,
    _reference_supersample,
    _selection_size,
    _split_bright_fixed,
    _subtexel_points_at,
    _tier_slots,
    bright_cells,
    bright_tiers,
    lobe_normalizer,
    split_bright,
)
from .cubemap import (
    Cubemap,
    _mip_chain_impl,
    _Pyramid,
    mip_count,
    texel_directions,
    texel_solid_angles,
)
from .lobe_reference import (
    lobe_reference,
    lobe_reference_sum,
)
from .lod import (  # noqa: F401  (re-exported: jaxpbr.ibl.specular is the prefilter's public module)
    _LOBE_NODES,
    _TABLE_POINTS,
    DEFAULT_CHAIN_FLOOR,
    DEFAULT_LOD_BLEND,
    LEGACY_LOD_BLEND,
    LOD_BLENDS,
    MAPPINGS,
    MIN_CHAIN_LEVELS,
    _check_blend,
    _check_mapping,
    _one_minus_c,
    _one_minus_c_table,
    default_num_levels,
    level_roughness,
    levels_for_roughness,
    lobe_mean_cosine,
    lookup_metadata,
    lookup_of,
    roughness_to_lod,
)

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
#: Default FIS LOD bias: 0, each sample reads the pyramid level of its own solid angle. Filament's
#: and GPU Gems 3's +1 (K = 4) makes every sample read a level twice as coarse, which blurs the
#: result beyond the lobe (an environment linear in direction, 64^2 chain, coarsest level at its
#: texel centres: 4.7e-3 relative error with bias 1, 9.4e-4 with bias 0); the bright texels
#: the sampling cannot handle are convolved exactly (`exact_texels`), so the blur buys no noise
#: reduction worth its bias. Measured at 256^2 faces against the float64 reference (`jaxpbr report
#: precompute`, docs/ibl.md): mean error per level 2-4x lower with bias 0 than 1 on the panoramas and
#: the procedural sky, worst texel lower or within 0.1 % of it, at the same run time.
DEFAULT_LOD_BIAS = 0.0




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


# ------------------------------------------------------------------------------------------
# filtered importance sampling
# ------------------------------------------------------------------------------------------


@functools.partial(cpu_jit, static_argnames=("capacity",))
def _ggx_lobe_samples(alpha, n, *, capacity: int):
    """GGX half vectors of the n-point Hammersley set (through `sample_ggx_h`) and the density of
    their reflected directions p_l = p_h / (4 n.h) for n = v = +z, in `capacity` >= n rows (the
    caller keeps the first n): one program for every count up to the capacity (the default chains'
    256, 1024 and 4096 samples compiled three before)."""
    dt = jnp.result_type(float)
    h = sample_ggx_h(hammersley(capacity, dt, total=n), alpha)
    cos_h = h[:, 2]
    return h, pdf_ggx_h(cos_h, alpha) / (4.0 * cos_h)


#: Rows of the sample program for counts up to it (counts above it: the next power of two).
LOBE_SAMPLE_CAPACITY = 4096


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
            capacity = max(LOBE_SAMPLE_CAPACITY, 1 << (int(n) - 1).bit_length())
            h, pdf = _ggx_lobe_samples(np.float64(alpha), np.float64(n), capacity=capacity)
            return np.asarray(h, np.float64)[:n], np.asarray(pdf, np.float64)[:n]

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


@functools.partial(cpu_jit, static_argnames=("sizes", "plan", "chunk", "S0", "n_bright", "tiers", "n_slots", "far", "kink", "bright_chunk"))
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


def prefilter_lookup(num_levels: int, *, mapping: str, lod_blend: str = DEFAULT_LOD_BLEND, face_size: int) -> dict:
    """The metadata of an M-level prefiltered chain that says how it is looked up (and the levels'
    roughness): what `prefilter` writes into its result's info, known before the levels are
    computed (the renderer compiles its IBL stage for it while the chain is computed)."""
    rough = level_roughness(num_levels, mapping=mapping)
    return {
        "roughness_mapping": mapping,
        "mapping_levels": str(num_levels),
        "level_roughness": ",".join(f"{x:.9g}" for x in rough),
        **lookup_metadata(num_levels, mapping=mapping, lod_blend=lod_blend, face_size=face_size),
    }


@keyword_only("size")
def prefilter(
    env: Cubemap,
    *,
    size: int | None = None,
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
    lod_bias: added to each FIS sample's source LOD (default 0, see DEFAULT_LOD_BIAS; Filament's
        K = 4 is 1); recorded as "fis_lod_bias".
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
        **prefilter_lookup(M, mapping=mapping, lod_blend=lod_blend, face_size=S),
        "prefilter_method": method,
    }
    if method == "fis":
        info["fis_samples"] = ",".join(str(n) for n in per_level)
        info["fis_lod_bias"] = f"{float(lod_bias):g}"
        info["exact_texels"] = n_exact
    return Cubemap(levels, info)
