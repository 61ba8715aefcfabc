"""Error of every precompute against its float64 reference (used by the CLI sidecars and by
`jaxpbr report precompute`).

Relative error of a texel: sum_c |x_c - ref_c| / sum_c |ref_c| (an L1 ratio over the colour channels,
so a near-black channel does not dominate). Texel subsets are deterministic (seeded) and always
include the texels closest to the brightest source direction, where sampling errs most.
"""

from __future__ import annotations

import jax
import numpy as np

from .._api import keyword_only
from ..shading.lut import lut_reference, resolve_smith
from .cubemap import Cubemap, face_to_dir, texel_directions
from .diffuse import irradiance_at
from .specular import level_roughness, lookup_of, prefilter_reference

__all__ = ["irradiance_error", "lut_error", "prefilter_error", "texel_subset"]


def relative_error(x, ref) -> np.ndarray:
    x = np.asarray(x, np.float64)
    ref = np.asarray(ref, np.float64)
    return np.abs(x - ref).sum(-1) / np.maximum(np.abs(ref).sum(-1), 1e-300)


def brightest_direction(env: Cubemap) -> np.ndarray:
    """The centre direction of the texel with the largest channel sum (only that texel's
    direction is computed: the full direction grid of a 2048^2 cube was 0.6 GB)."""
    S = env.face_size
    k = int(np.argmax(np.asarray(env.levels[0]).sum(-1)))
    f, rem = divmod(k, S * S)
    i, j = divmod(rem, S)
    d = face_to_dir(np.asarray(f), np.asarray((j + 0.5) / S), np.asarray((i + 0.5) / S), xp=np)
    return d / np.linalg.norm(d)


@keyword_only("count")
def texel_subset(size: int, *, count: int, toward=None, seed: int = 0) -> np.ndarray:
    """Flat texel indices of a (6, size, size) cube: all if there are <= count, otherwise count
    seeded random ones plus the count/8 texels nearest `toward` (if given)."""
    n = 6 * size * size
    if n <= count:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    sel = rng.choice(n, count, replace=False)
    if toward is not None:
        d = texel_directions(size).reshape(-1, 3)
        m = max(1, count // 8)
        near = np.argpartition(-(d @ np.asarray(toward)), m - 1)[:m]
        sel = np.union1d(sel, near)
    return np.sort(sel)


def prefilter_error(env: Cubemap, pre: Cubemap, *, texels_per_level: int = 256, seed: int = 0, progress=None) -> list[dict]:
    """Per level m >= 1: mean and max relative error of `pre` against `prefilter_reference` at a
    texel subset. Level 0 is the (down-sampled) source itself and has no error by construction.
    progress: optional callable(done_levels, total_levels)."""
    M, mapping, _ = lookup_of(pre)  # a partial chain: the M-level roughness
    rough = level_roughness(M, mapping=mapping)
    sun = brightest_direction(env)
    rows = []
    for m in range(1, pre.num_levels):
        Sm = pre.levels[m].shape[1]
        sel = texel_subset(Sm, count=texels_per_level, toward=sun, seed=seed + m)
        d = texel_directions(Sm).reshape(-1, 3)[sel]
        ref = prefilter_reference(env, d, float(rough[m]))
        got = np.asarray(pre.levels[m], np.float64).reshape(-1, pre.channels)[sel]
        e = relative_error(got, ref)
        rows.append(
            dict(level=m, roughness=float(rough[m]), face_size=Sm, texels=len(sel), mean=float(e.mean()), max=float(e.max()))
        )
        if progress is not None:
            progress(m, pre.num_levels - 1)
    return rows


def irradiance_error(env: Cubemap, irr: Cubemap, *, texels: int = 512, seed: int = 0, progress=None) -> dict:
    """Mean / max relative error of an irradiance map against the full-resolution exact
    convolution (source_size = env face size) in float64, at a texel subset (`progress` as in
    `irradiance`)."""
    S = irr.face_size
    sel = texel_subset(S, count=texels, toward=brightest_direction(env), seed=seed)
    d = texel_directions(S).reshape(-1, 3)[sel]
    with jax.enable_x64(True):
        env64 = Cubemap(tuple(np.asarray(lv, np.float64) for lv in env.levels[:1]))
        ref = np.asarray(irradiance_at(env64, d, method="exact", source_size=env.face_size, chunk=16, progress=progress))
    got = np.asarray(irr.levels[0], np.float64).reshape(-1, irr.channels)[sel]
    e = relative_error(got, ref)
    return dict(texels=len(sel), mean=float(e.mean()), max=float(e.max()))


@keyword_only("smith")
def lut_error(lut, *, smith: str, texels: int | None = 1024, seed: int = 0) -> dict:
    """Max / mean absolute error of a LUT (n_r, n_nov, 2) against `lut_reference` at its texel
    centres: every texel if `texels` is None, else the four edges plus a seeded random subset.
    `smith`: the LUT's Smith term, "correlated" | "schlick_ggx" (as in `compute_brdf_lut`)."""
    smith = resolve_smith(smith, "lut_error")
    lut = np.asarray(lut, np.float64)
    nr, nn = lut.shape[:2]
    jj, ii = np.meshgrid(np.arange(nr), np.arange(nn), indexing="ij")
    j, i = jj.reshape(-1), ii.reshape(-1)
    if texels is not None and nr * nn > texels:
        edge = (j == 0) | (j == nr - 1) | (i == 0) | (i == nn - 1)
        rng = np.random.default_rng(seed)
        pick = np.union1d(np.nonzero(edge)[0], rng.choice(nr * nn, texels, replace=False))
        j, i = j[pick], i[pick]
    ref = lut_reference((i + 0.5) / nn, (j + 0.5) / nr, smith=smith)
    err = np.abs(lut[j, i] - ref)
    return dict(texels=int(len(j)), max=float(err.max()), mean=float(err.mean()), all_texels=texels is None or nr * nn <= texels)


def summarize(rows: list[dict]) -> dict:
    """Worst mean and worst max over prefilter levels."""
    if not rows:
        return dict(mean=0.0, max=0.0)
    return dict(mean=max(r["mean"] for r in rows), max=max(r["max"] for r in rows))
