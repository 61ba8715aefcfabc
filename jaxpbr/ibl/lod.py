"""Roughness <-> mip of prefiltered chains: the chain's levels, the level roughnesses of the two
mappings ("linear", "quadratic"), the lookup between levels (`roughness_to_lod`, lod_blend
"roughness" | "mean_cosine") and the lookup metadata a map carries (docs/conventions.md, docs/ibl.md).
The prefilters (`specular`, `sheen_prefilter`) build their chains with it; shading reads through it.
"""

from __future__ import annotations

import functools
import math

import jax.numpy as jnp
import numpy as np

from .._api import keyword_only
from .._interp import interp_nodes, interp_uniform
from .._validate import positive_int
from .cubemap import (
    Cubemap,
    mip_count,
)
from .lobe_reference import (
    LOD_TABLE_STEPS,
    chain_lookup_metadata,
    check_lod_blend,
)

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
    return interp_uniform(r, 0.0, 1.0, jnp.asarray(tab, dt))


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
    return interp_nodes(g, g_levels, np.arange(M, dtype=np.float64))


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


def _check_mapping(mapping):
    if mapping not in MAPPINGS:
        raise ValueError(f"unknown roughness->mip mapping {mapping!r}; choose one of {MAPPINGS}")


