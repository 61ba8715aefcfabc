"""Float64 brute-force reference of image-based lighting: the full reflectance integral.

    Lo(v) = ao * integral over the sphere of L(l) f_r(v, l) (n.l)+ dl

with L the environment's level 0 as a piecewise-constant function of its texels (the definition
`jaxpbr.ibl.specular.prefilter_reference` and the exact irradiance use) and f_r the complete glTF
BRDF of `jaxpbr.brdf` (Lambert diffuse under the dielectric Fresnel layer + GGX / Smith specular),
with *no* roughness floor. This is what the split sum `jaxpbr.shade_ibl` approximates; the
difference of the two is the split-sum error that `jaxpbr.report_render` shows.

Decomposition (exact, no approximation). With w = (1 - v.h)^5, the glTF BRDF is

    f_r = (1 - metallic) 0.96 (1 - w) base/pi + (F0 (1 - w) + w) D V,    F0 = lerp(0.04, base, metallic)

(Schlick is linear in F0; 1 - F_dielectric = 0.96 (1 - w)), so per pixel three sums over the
environment suffice, whatever the material's colour and metallic:

    Ld = sum_j L_j  integral_j 0.96 (1 - w) (n.l)+ / pi   dl
    LA = sum_j L_j  integral_j D V (1 - w) (n.l)+          dl      (the split sum's LD * A)
    LB = sum_j L_j  integral_j D V w (n.l)+                dl      (the split sum's LD * B)
    Lo = ao * ((1 - metallic) base * Ld + F0 * LA + LB).

Quadrature. Each texel integral is a midpoint sum over q x q sub-texels with their solid-angle
weights (`cubemap._subtexel_points`; the fine tiers use the exact sub-texel solid angles). q is
chosen from the lobe width against the texel size: a sub-texel must be at most a quarter of the
local scale of the integrand, which is alpha near the specular peak and the distance to the peak
farther away. Hence tiers per pixel, selected around the mirror direction R:

* the `NEAR_TEXELS` texels closest to R (the 3 x 3 window around R's texel, continued across
  face edges): q_near = ceil(texel / (alpha min(NoV, 1/4))), at most `MAX_NEAR_Q` (a grazing view
  squeezes the lobe to ~2 alpha NoV across the plane of incidence, so pixels are grouped in NoV
  bands and the band's smallest NoV sets q);
* the next `RING_TEXELS` texels (the rest of the 7 x 7 window): q = min(q_near, 4);
* the (at most `BRIGHT_TEXELS`) texels brighter than `BRIGHT_RATIO` x the mean radiance (a sun):
  q = `BRIGHT_Q`, for every pixel (their horizon crossing and the kernel's curvature over them
  would otherwise dominate the error);
* every other texel: q = min(q_near, 2) (the integrand varies on >= 2 texels there), and at
  least enough for sub-texels of ~1/16 rad (2 on a 16^2 map: the horizon kink of (n.l)+).
Each texel is counted by exactly one tier (duplicates at cube edges and corners are dropped).

`refine=k` multiplies every q by k; `test_reference_render` checks that k = 2 changes the result
by less than the stated tolerance. Because q_near is capped, roughness below
`min_reference_roughness(face_size)` = sqrt(4 * texel / MAX_NEAR_Q) (0.044 at face 64, 0.088 at
16, 0.022 at 256) cannot be resolved even at NoV >= 1/4 and is rejected with a ValueError. Below
NoV = 1/4 the cap can bind for lobes near that floor (r = 0.05 at face 64 for NoV < 0.1): the
result there is still a float64 texel sum but less resolved (measured in docs/ibl.md). Memory is
bounded by evaluating chunks of pixels (a power of two that keeps the largest pixels x sub-texels
block near 4M float64 elements) with one compiled program per tier configuration, so any image
size runs; compilation (~2-5 s per configuration) dominates small calls.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._api import keyword_only
from .._numerics import HIGHEST
from .._pytree import evolve, fields_of
from .._validate import positive_int
from ..conventions import luminance
from ..shading.material import EXTENSION_FIELDS, F0_DIELECTRIC, Material
from .cubemap import (
    _FACE_TABLE,
    Cubemap,
    _subtexel_points,
    dir_to_face,
    face_to_dir,
    texel_solid_angles,
)

__all__ = [
    "MAX_NEAR_Q",
    "NEAR_TEXELS",
    "RING_TEXELS",
    "min_reference_roughness",
    "bright_texels",
    "reference_ibl",
    "reference_ibl_from_terms",
    "reference_ibl_terms",
    "reference_layered",
]

#: Most sub-texels per side in the texels around the mirror direction (sets the roughness floor).
MAX_NEAR_Q = 64
#: Texels around the mirror direction integrated with the lobe-resolving q_near.
NEAR_TEXELS = 9
#: The next texels around it, integrated with q = min(q_near, 4).
RING_TEXELS = 40
#: Texels brighter than BRIGHT_RATIO x the mean radiance (at most BRIGHT_TEXELS of them, e.g. the
#: sun) are integrated with BRIGHT_Q sub-texels per side for every pixel: their horizon crossing and
#: the kernel's curvature over them would otherwise dominate the error.
BRIGHT_TEXELS = 64
BRIGHT_RATIO = 8.0
BRIGHT_Q = 8
#: Elements of the largest (pixels x sub-texels) float64 block per chunk (~32 MB each).
_BLOCK = 1 << 22


def _texel_angle(face_size: int) -> float:
    """Angular size (rad) of the largest (face-centre) texel."""
    return 2.0 * math.atan(1.0 / face_size)


def min_reference_roughness(face_size: int, *, refine: int = 1) -> float:
    """Smallest perceptual roughness the reference resolves on a `face_size`^2 environment:
    alpha = r^2 must be >= 4 * texel / (MAX_NEAR_Q * refine)."""
    return math.sqrt(4.0 * _texel_angle(face_size) / (MAX_NEAR_Q * refine))


#: Lower NoV bound of each grazing band (band k: NoV in [_NOV_BANDS[k], 0.25 / 2^(k-1))); band 0
#: is NoV >= 0.25, the last one everything below 1/32 (evaluated as 1/64).
_NOV_BANDS = (0.25, 0.125, 0.0625, 0.03125, 0.015625)


def _supersampling(alpha_min: float, face_size: int, refine: int, grazing: float = 0.25) -> tuple[int, int, int, int]:
    """(q_far, q_ring, q_near, q_bright) sub-texels per side for the tiers (module docstring):
    near-tier sub-texels at most alpha * min(NoV, 1/4) across (the lobe is ~2 alpha NoV wide
    across the plane of incidence), capped at MAX_NEAR_Q."""
    q_near = max(1, math.ceil(_texel_angle(face_size) / (alpha_min * min(grazing, 0.25)) - 1e-9))
    q_near = min(q_near, MAX_NEAR_Q)
    # far tier: 2 where a lobe needs the near tiers, and sub-texels of at most ~1/16 rad anyway (the
    # horizon kink of (n.l)+ on coarse maps)
    q_far = max(min(q_near, 2), math.ceil(16.0 * _texel_angle(face_size) - 1e-9))
    if q_near <= q_far:  # no near tiers: one canonical configuration (one compiled program)
        return q_far * refine, q_far * refine, q_far * refine, BRIGHT_Q * refine
    return q_far * refine, min(q_near, 4) * refine, q_near * refine, BRIGHT_Q * refine


@keyword_only("max_texels", "ratio")
def bright_texels(level0, *, max_texels: int = BRIGHT_TEXELS, ratio: float = BRIGHT_RATIO) -> np.ndarray:
    """Flat indices of the (at most `max_texels`) brightest texels whose luminance exceeds `ratio`
    times the environment's mean radiance (e.g. the sun), brightest first."""
    L = np.asarray(level0, np.float64)
    S = L.shape[1]
    lum = luminance(L).reshape(-1)
    mean = float(np.sum(lum * texel_solid_angles(S).reshape(-1)) / (4.0 * math.pi))
    if max_texels <= 0 or mean <= 0:
        return np.zeros(0, np.int32)
    order = np.argsort(-lum, kind="stable")[:max_texels]
    return order[lum[order] > ratio * mean].astype(np.int32)


# ------------------------------------------------------------------------------------------
# the three kernels
# ------------------------------------------------------------------------------------------


def _kernels(nol, vol, nov, a2, smith: str):
    """(diffuse, spec_A, spec_B) integrands without L and dl, for dot products broadcasting
    together: nol = n.l, vol = v.l, nov = n.v, a2 = alpha^2. Zero where n.l <= 0 or n.v <= 0.

    h = (v + l)/|v + l|: v.h = sqrt((1 + v.l)/2), n.h = (n.v + n.l)/|v + l| (float64: the
    1 - NoH^2 cancellation costs ~1e-11 relative at alpha 0.002, docs/math.md 8.2 is a float32 issue).
    """
    front = (nol > 0.0) & (nov > 0.0)
    nl = jnp.where(front, nol, 1.0)
    nv = jnp.where(front, nov, 1.0)
    s2 = jnp.maximum(2.0 * (1.0 + vol), 1e-300)  # |v + l|^2; 0 only for v = -l, which is not front
    voh = jnp.sqrt(0.25 * s2)
    noh = (nv + nl) / jnp.sqrt(s2)
    noh2 = jnp.minimum(noh * noh, 1.0)
    d = (1.0 - noh2) + noh2 * a2
    D = a2 / (math.pi * d * d)
    if smith == "correlated":
        V = 0.5 / (nl * jnp.sqrt(nv * nv * (1.0 - a2) + a2) + nv * jnp.sqrt(nl * nl * (1.0 - a2) + a2))
    else:
        V = 1.0 / ((nv + jnp.sqrt(a2 + (1.0 - a2) * nv * nv)) * (nl + jnp.sqrt(a2 + (1.0 - a2) * nl * nl)))
    x = jnp.clip(1.0 - voh, 0.0, 1.0)
    w = x * x * x * x * x
    spec = jnp.where(front, D * V * nl, 0.0)
    diff = jnp.where(front, (1.0 - F0_DIELECTRIC) * (1.0 - w) * nl / math.pi, 0.0)
    return diff, spec * (1.0 - w), spec * w


def _apply(k3, om, L):
    """sum over the sub-texel axis (-1) with weights om, then over texels with radiance L.

    k3: three arrays (P, T, q2); om broadcasting to (P, T, q2); L (T, C) or (P, T, C) -> (P, 3, C)."""
    spec = "pt,tc->pc" if L.ndim == 2 else "pt,ptc->pc"
    return jnp.stack([jnp.einsum(spec, jnp.sum(k * om, -1), L, precision=HIGHEST) for k in k3], 1)


def _window_texels(R, S: int, half: int):
    """Flat texel indices (P, (2 half + 1)^2) of the window of texels around the texel that
    contains the direction R (P, 3), inner 3 x 3 first, then the rest; cells past a face edge
    continue on the neighbouring face (extended face plane, re-projected). A texel that appears
    twice (at edges and corners) gets weight 0 after its first occurrence: -> (idx, first)."""
    f, s, t = dir_to_face(R)
    j = jnp.clip(jnp.floor(s * S), 0, S - 1)
    i = jnp.clip(jnp.floor(t * S), 0, S - 1)
    offs = [(a, b) for a in range(-half, half + 1) for b in range(-half, half + 1)]
    offs.sort(key=lambda o: (max(abs(o[0]), abs(o[1])) > 1,))  # inner 3 x 3 first (stable)
    di = jnp.asarray([o[0] for o in offs], R.dtype)
    dj = jnp.asarray([o[1] for o in offs], R.dtype)
    ss = (j[:, None] + dj[None] + 0.5) / S
    tt = (i[:, None] + di[None] + 0.5) / S
    d = face_to_dir(jnp.broadcast_to(f[:, None], ss.shape), ss, tt)
    f2, s2, t2 = dir_to_face(d)
    j2 = jnp.clip(jnp.floor(s2 * S), 0, S - 1).astype(jnp.int32)
    i2 = jnp.clip(jnp.floor(t2 * S), 0, S - 1).astype(jnp.int32)
    idx = (f2 * S + i2) * S + j2
    K = idx.shape[1]
    same = idx[:, :, None] == idx[:, None, :]
    earlier = jnp.tril(jnp.ones((K, K), bool), -1)
    first = ~jnp.any(same & earlier[None], -1)
    return idx, first


class _Samples(NamedTuple):
    """The sub-texel samples of one tier group, handed to a kernel callback (`_tiered_sum`).

    X are the sample axes: (M,) for the concatenated fine tiers, (T, q2) for the far tier.
    nol, vol: n.l and v.l (P, *X); l: the directions as three planes broadcasting to (P, *X); om:
    quadrature weights (solid angle x tier weight) broadcasting to (P, *X); L: radiance (P, M, C)
    (fine) or (T, C) (far); n, v (P, 3) and nov (P,) the pixels."""

    nol: jax.Array
    vol: jax.Array
    l: tuple
    om: jax.Array
    L: jax.Array
    n: jax.Array
    v: jax.Array
    nov: jax.Array


def _tiered_sum(nc, vc, L, far_dirs, far_om, texel_om, bright, centres, kernel, *, q_far, q_tiers, q_bright, S):
    """sum over every environment texel of kernel(samples) for one chunk of pixels n, v (P, 3):
    the tiers of the module docstring around each lobe centre of `centres` (groups of directions
    (P, 3) or (P, k, 3), with (q_near, q_ring) per group in `q_tiers`), the bright texels, and the
    far tier.

    Every texel is counted exactly once, by the finest tier that contains it (ties: centres in
    order, near before ring, the windows before the bright tier); the far tier counts the rest.
    kernel(samples: _Samples, expand) -> (P, ...): the weighted sum over the samples' axes;
    expand(x) reshapes a per-pixel (P, ...) array to broadcast with the sample axes. It is called
    once for the fine tiers (if any) and once for the far tier, and the two results are added."""
    T = L.shape[0]
    nb = bright.shape[0]
    P = nc.shape[0]
    nov = jnp.sum(nc * vc, -1)
    keep = jnp.ones((P, T), nc.dtype)
    if nb:
        keep = keep.at[:, bright].set(0.0)
    tiers = []  # (idx (P, k) or (k,), q) in construction order
    for c, (q_near, q_ring) in zip(centres, q_tiers):
        if c.ndim == 2:
            c = c[:, None]
        kc = c.shape[1]
        win, _ = _window_texels(c.reshape(P * kc, 3), S, 3)  # 9 near + 40 ring texels around each centre
        win = win.reshape(P, kc, -1)
        keep = keep.at[jnp.arange(P)[:, None], win.reshape(P, -1)].set(0.0)
        tiers += [(win[:, :, :NEAR_TEXELS].reshape(P, -1), q_near), (win[:, :, NEAR_TEXELS:].reshape(P, -1), q_ring)]
    if nb:
        tiers.append((bright, q_bright))
    # weights: 1 at a texel's first occurrence in priority order (finer q first, stable), else 0
    weights = [None] * len(tiers)
    if centres:
        order = sorted(range(len(tiers)), key=lambda k: -tiers[k][1])
        cat = jnp.concatenate([jnp.broadcast_to(tiers[k][0], (P, tiers[k][0].shape[-1])) for k in order], 1)
        # first occurrence along the row: a stable sort keeps equal indices in priority order
        perm = jnp.argsort(cat, axis=1, stable=True)
        srt = jnp.take_along_axis(cat, perm, 1)
        is_first = jnp.concatenate([jnp.ones((P, 1), bool), srt[:, 1:] != srt[:, :-1]], 1)
        first = jnp.zeros(cat.shape, nc.dtype).at[jnp.arange(P)[:, None], perm].set(is_first.astype(nc.dtype))
        o = 0
        for k in order:
            kk = tiers[k][0].shape[-1]
            weights[k] = first[:, o : o + kk]
            o += kk
    elif nb:  # the bright tier alone
        weights = [jnp.ones((P, nb), nc.dtype)]

    def expand_to(nd):
        return lambda x: x.reshape(x.shape[:1] + (1,) * nd + x.shape[1:])

    out = 0.0
    if tiers:
        parts = []
        for (sel, q), wt in zip(tiers, weights):
            nol, vol, om, ld = _subtexel_dots(sel, nc, vc, S, q, texel_om, dirs=True)  # (P, k, q2) each
            Ls = jnp.broadcast_to(L[sel][..., None, :], om.shape[:-1] + (q * q, L.shape[1]))
            om = om * wt[..., None]
            ld = tuple(jnp.broadcast_to(x, nol.shape) for x in ld)
            parts.append(tuple(x.reshape(P, -1, *x.shape[3:]) for x in (nol, vol, om, jnp.broadcast_to(Ls, (P,) + Ls.shape[-3:])) + ld))
        nol, vol, om, Ls, l0, l1, l2 = (jnp.concatenate(x, 1) for x in zip(*parts))
        out = kernel(_Samples(nol, vol, (l0, l1, l2), om, Ls, nc, vc, nov), expand_to(1))
    nol = jnp.einsum("pk,tsk->pts", nc, far_dirs, precision=HIGHEST)
    vol = jnp.einsum("pk,tsk->pts", vc, far_dirs, precision=HIGHEST)
    ld = tuple(far_dirs[None, ..., i] for i in range(3))
    return out + kernel(_Samples(nol, vol, ld, far_om[None] * keep[..., None], L, nc, vc, nov), expand_to(2))


def _core_kernel(ac, smith: str):
    """The three glTF terms (module docstring) -> (P, 3 terms, C)."""

    def kernel(s: _Samples, expand):
        k3 = _kernels(s.nol, s.vol, expand(s.nov), expand(ac), smith)
        if s.L.ndim == 3:  # fine tiers
            return jnp.stack([jnp.einsum("pm,pmc->pc", k * s.om, s.L, precision=HIGHEST) for k in k3], 1)
        return _apply(k3, s.om, s.L)

    return kernel


@functools.partial(jax.jit, static_argnames=("q_far", "q_ring", "q_near", "q_bright", "S", "smith"))
def _terms_chunk(nc, vc, ac, L, far_dirs, far_om, texel_om, bright, *, q_far, q_ring, q_near, q_bright, S, smith):
    """(P, 3 terms, C) sums for one chunk of pixels n, v (P, 3), alpha^2 (P,); module docstring.
    One compiled program per tier configuration and chunk size (the caller pads the last chunk)."""
    nov = jnp.sum(nc * vc, -1)
    centres, q_tiers = (), ()
    if q_near > q_far:
        centres, q_tiers = (2.0 * nov[:, None] * nc - vc,), ((q_near, q_ring),)
    return _tiered_sum(
        nc, vc, L, far_dirs, far_om, texel_om, bright, centres, _core_kernel(ac, smith),
        q_far=q_far, q_tiers=q_tiers, q_bright=q_bright, S=S,
    )


def _subtexel_dots(idx, nc, vc, S: int, q: int, texel_om, *, dirs: bool = False):
    """n.l, v.l (P, k, q*q) and solid angles (P or 1, k, q*q) of the q x q sub-texel centres l of
    the texels with flat indices idx ((k,) shared by all pixels, or (P, k)) into (6, S, S).

    A sub-texel's weight is its midpoint solid angle ds dt / (1 + sc^2 + tc^2)^(3/2), rescaled so
    that the q*q weights of a texel add up to its exact solid angle (as `_subtexel_points`). The
    dot products are formed from the face table without materialising the directions:
    n.l = (n.T0 sc + n.T1 tc + n.T2) / |(sc, tc, 1)|.
    """
    f = idx // (S * S)
    i = (idx // S) % S
    j = idx % S
    o = (jnp.arange(q, dtype=nc.dtype) + 0.5) / q
    tc = 2.0 * (i[..., None] + o) / S - 1.0  # (..., q) rows along t
    sc = 2.0 * (j[..., None] + o) / S - 1.0  # (..., q) columns along s
    tc = jnp.repeat(tc, q, axis=-1)  # (..., q*q): sub-texel (a, b) at position a*q + b
    sc = jnp.tile(sc, (1,) * (sc.ndim - 1) + (q,))
    inv = jax.lax.rsqrt(1.0 + sc * sc + tc * tc)
    w = inv * inv * inv
    om = w * (texel_om[idx] / jnp.sum(w, -1))[..., None]
    Tm = jnp.asarray(_FACE_TABLE, nc.dtype)[f]  # (..., 3 out, 3 in)
    if idx.ndim == 1:
        an = jnp.einsum("pc,kci->pki", nc, Tm, precision=HIGHEST)
        av = jnp.einsum("pc,kci->pki", vc, Tm, precision=HIGHEST)
        sc, tc, inv, om = sc[None], tc[None], inv[None], om[None]
    else:
        an = jnp.einsum("pc,pkci->pki", nc, Tm, precision=HIGHEST)
        av = jnp.einsum("pc,pkci->pki", vc, Tm, precision=HIGHEST)
    nol = (an[..., 0:1] * sc + an[..., 1:2] * tc + an[..., 2:3]) * inv
    vol = (av[..., 0:1] * sc + av[..., 1:2] * tc + av[..., 2:3]) * inv
    if not dirs:
        return nol, vol, om
    if idx.ndim == 1:
        Tm = Tm[None]
    # l = T (sc, tc, 1) / |(sc, tc, 1)| as three planes (the face table maps face to world axes)
    ld = tuple((Tm[..., c, 0:1] * sc + Tm[..., c, 1:2] * tc + Tm[..., c, 2:3]) * inv for c in range(3))
    return nol, vol, om, ld


#: min_roughness handed to `layered.layered_soa`: far below every roughness the reference accepts
#: (`min_reference_roughness`), so it changes no accepted lobe; it only keeps the lobes whose
#: weight is 0 (clear coat of clearcoat = 0, sheen of sheen_color = 0: their roughness is free,
#: default 0) finite, so that 0 x lobe = 0.
LAYERED_MIN_ROUGHNESS = 1e-4
#: Elements of the largest (pixels x sub-texels) block per chunk of `reference_layered` (the
#: layered kernel keeps more temporaries alive than the three core terms).
_BLOCK_LAYERED = 1 << 20


def _layered_kernel(m, tangent, coat_normal, volume_distance, sheen_lut, smith: str):
    """sum of L(l) f(v, l) |cos| om over the samples with the layered BSDF -> (P, C)."""
    from ..shading.layered import LayerInputs, layered_soa

    def kernel(s: _Samples, expand):
        nd = s.nol.ndim - 1
        mx = evolve(m, **{f.name: expand(getattr(m, f.name)) for f in fields_of(m) if getattr(m, f.name) is not None})
        vec = lambda a: None if a is None else tuple(expand(a[:, i]) for i in range(3))  # noqa: E731
        extra = LayerInputs(
            tangent=vec(tangent),
            coat_normal=vec(coat_normal),
            volume_distance=None if volume_distance is None else expand(volume_distance),
        )
        fc = layered_soa(
            vec(s.n), vec(s.v), s.l, mx, min_roughness=LAYERED_MIN_ROUGHNESS, smith=smith, sheen_lut=sheen_lut, extra=extra
        )
        fc = [jnp.broadcast_to(x, s.nol.shape) * s.om for x in fc]
        if nd == 1:  # fine tiers: L (P, M, C)
            return jnp.stack([jnp.einsum("pm,pm->p", fc[c], s.L[..., c], precision=HIGHEST) for c in range(3)], -1)
        return jnp.stack([jnp.einsum("pt,t->p", jnp.sum(fc[c], -1), s.L[:, c], precision=HIGHEST) for c in range(3)], -1)

    return kernel


#: The spine of an anisotropic lobe is followed out to slopes ANISO_SPINE_SLOPES x alpha_t along the
#: anisotropy direction (the lobe's marginal beyond holds < 1/(2 x 10^2) = 0.5 % of its mass, where
#: the ring and far tiers resolve it).
ANISO_SPINE_SLOPES = 10.0


def _spine_angle(alpha_t):
    """Largest half-vector tilt (rad) along the anisotropy direction followed by spine centres."""
    return np.arctan(ANISO_SPINE_SLOPES * np.asarray(alpha_t))


def _spine_centres(count, nc, vc, m, tangent):
    """(P, count, 3): `count` (odd) centres along the anisotropic lobe's spine: the mirror directions of v about
    h = cos(theta) n + sin(theta) T, theta evenly spaced in [-theta_max, theta_max]
    (`_spine_angle`) with T the anisotropy direction; theta = 0 gives R."""
    from ..shading.layered import anisotropic_alphas, anisotropy_frame

    n3 = tuple(nc[:, i] for i in range(3))
    t3 = tangent / jnp.linalg.norm(tangent, axis=-1, keepdims=True)
    T, _ = anisotropy_frame(n3, tuple(t3[:, i] for i in range(3)), m.anisotropy_rotation)
    T = jnp.stack(T, -1)
    r = jnp.clip(m.roughness, LAYERED_MIN_ROUGHNESS, 1.0)
    at, _ = anisotropic_alphas(r * r, jnp.clip(m.anisotropy_strength, 0.0, 1.0))
    tmax = jnp.arctan(ANISO_SPINE_SLOPES * at)
    u = jnp.linspace(-1.0, 1.0, count, dtype=nc.dtype) if count > 1 else jnp.zeros(1, nc.dtype)
    th = tmax[:, None] * u[None]  # (P, count)
    h = jnp.cos(th)[..., None] * nc[:, None] + jnp.sin(th)[..., None] * T[:, None]
    return 2.0 * jnp.sum(h * vc[:, None], -1)[..., None] * h - vc[:, None]


def _layered_centres(kinds, nc, vc, m, coat_normal, tangent):
    """The lobe centres (P, 3) named by `kinds`: "R" the mirror direction of the base lobe, "Rc"
    the coat normal's mirror direction, "T" the transmission lobe's centre (-v thin-walled, the
    refracted -v where the volume has thickness > 0)."""
    from .layered_ibl import refract

    nov = jnp.sum(nc * vc, -1)
    mc = m.complete()
    out = []
    for k in kinds:
        if k == "R":
            out.append(2.0 * nov[:, None] * nc - vc)
        elif isinstance(k, tuple):  # ("A", count): the anisotropic lobe's spine
            out.append(_spine_centres(k[1], nc, vc, mc, tangent))
        elif k == "Rc":
            cn = nc if coat_normal is None else coat_normal / jnp.linalg.norm(coat_normal, axis=-1, keepdims=True)
            out.append(2.0 * jnp.sum(cn * vc, -1)[:, None] * cn - vc)
        else:
            t = -vc
            if m.thickness is not None:
                eta = jnp.maximum(m.ior, 1.0) if m.ior is not None else jnp.full_like(nov, 1.5)
                d = refract(-vc, nc, 1.0 / eta)
                ok = (m.thickness > 0)[:, None] & (jnp.sum(d * d, -1, keepdims=True) > 0)
                t = jnp.where(ok, d, t)
            out.append(t)
    return tuple(out)


@functools.partial(jax.jit, static_argnames=("kinds", "q_far", "q_tiers", "q_bright", "S", "smith"))
def _layered_chunk(nc, vc, m, tangent, coat_normal, volume_distance, sheen_lut, L, far_dirs, far_om, texel_om, bright, *, kinds, q_far, q_tiers, q_bright, S, smith):
    """(P, C) layered sums for one chunk of pixels (`reference_layered`)."""
    centres = _layered_centres(kinds, nc, vc, m, coat_normal, tangent)
    kernel = _layered_kernel(m, tangent, coat_normal, volume_distance, sheen_lut, smith)
    return _tiered_sum(nc, vc, L, far_dirs, far_om, texel_om, bright, centres, kernel, q_far=q_far, q_tiers=q_tiers, q_bright=q_bright, S=S)


# ------------------------------------------------------------------------------------------
# public API
# ------------------------------------------------------------------------------------------


def reference_ibl_terms(n, v, roughness, env: Cubemap, *, smith: str = "correlated", refine: int = 1, chunk: int | None = None) -> np.ndarray:
    """The three per-pixel environment sums (Ld, LA, LB) of the module docstring, float64
    (..., 3, C): [..., 0] diffuse (times (1 - metallic) base), [..., 1] specular (times F0),
    [..., 2] specular (times 1). n, v (..., 3) unit vectors; roughness (...) perceptual r."""
    if smith not in ("correlated", "separable"):
        raise ValueError(f"unknown smith {smith!r}; choose 'correlated' (glTF) or 'separable'")
    refine = positive_int("refine", refine)
    n = np.asarray(n, np.float64)
    v = np.asarray(v, np.float64)
    r = np.asarray(roughness, np.float64)
    shape = np.broadcast_shapes(n.shape[:-1], v.shape[:-1], r.shape)
    n = np.broadcast_to(n, shape + (3,)).reshape(-1, 3)
    v = np.broadcast_to(v, shape + (3,)).reshape(-1, 3)
    r = np.broadcast_to(r, shape).reshape(-1)
    if not np.all(np.isfinite(n)) or not np.all(np.isfinite(v)):
        raise ValueError("n and v must be finite")
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    v = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)
    S = env.face_size
    C = env.channels
    if r.size == 0:
        return np.zeros(shape + (3, C))
    if chunk is not None:
        positive_int("chunk", chunk)
    if np.any(r > 1.0) or not np.all(np.isfinite(r)):
        raise ValueError("roughness must lie in [0, 1]")
    r_min = min_reference_roughness(S)
    if r.min() < r_min:
        raise ValueError(
            f"reference_ibl resolves roughness >= {r_min:.4f} on a {S}^2-per-face environment "
            f"(alpha = r^2 >= 4 texels / {MAX_NEAR_Q} sub-texels), got r = {r.min():g}; use a larger face size "
            "(the floor halves in alpha with every doubling) or a larger roughness"
        )
    a2 = (r * r) ** 2
    bright = bright_texels(env.levels[0])
    nov = np.sum(n * v, -1)
    out = np.zeros((n.shape[0], 3, C))
    with jax.enable_x64(True):
        L = jnp.asarray(np.asarray(env.levels[0], np.float64).reshape(-1, C))
        T = L.shape[0]
        texel_om = jnp.asarray(texel_solid_angles(S).reshape(-1))
        # Grazing views compress the lobe across the plane of incidence to ~2 alpha NoV: pixels
        # are grouped by NoV and the near tier's q grows as 1/NoV below NoV = 1/4 (capped).
        band = np.clip(np.ceil(np.log2(0.25 / np.maximum(nov, 1e-300)) - 1e-12), 0, len(_NOV_BANDS) - 1).astype(int)
        band[(nov >= 0.25) | (nov <= 0.0)] = 0  # n.v <= 0: the BRDF is 0, nothing to resolve
        for k in np.unique(band):
            sel = np.nonzero(band == k)[0]
            q_far, q_ring, q_near, q_bright = _supersampling(float(r[sel].min()) ** 2, S, refine, grazing=_NOV_BANDS[k])
            far_dirs, w = _subtexel_points(S, q_far)  # (6,S,S,q2,3), (S,S,q2)
            far_om = texel_solid_angles(S)[..., None] * w[None]
            # chunk so that the largest (pixels x sub-texels) block stays ~_BLOCK elements
            per_pixel = max(T * q_far**2, NEAR_TEXELS * q_near**2, RING_TEXELS * q_ring**2, len(bright) * q_bright**2)
            # a power of two that depends only on the tier configuration, so that calls with any
            # number of pixels reuse one compiled program (the last chunk is padded)
            ck = max(1, min(64, _BLOCK // per_pixel)) if chunk is None else int(chunk)
            ck = 1 << (ck.bit_length() - 1)
            args = (jnp.asarray(far_dirs.reshape(T, -1, 3)), jnp.asarray(far_om.reshape(T, -1)), texel_om, jnp.asarray(bright))
            for i in range(0, len(sel), ck):
                idx = sel[i : i + ck]
                pad = ck - len(idx)
                nn = np.concatenate([n[idx], np.tile([[0.0, 0.0, 1.0]], (pad, 1))])
                vv = np.concatenate([v[idx], np.tile([[0.0, 0.0, 1.0]], (pad, 1))])
                aa = np.concatenate([a2[idx], np.ones(pad)])
                res = _terms_chunk(
                    jnp.asarray(nn), jnp.asarray(vv), jnp.asarray(aa), L, *args,
                    q_far=q_far, q_ring=q_ring, q_near=q_near, q_bright=q_bright, S=S, smith=smith,
                )
                out[idx] = np.asarray(res)[: len(idx)]
    return out.reshape(shape + (3, C))


def reference_ibl(
    n,
    v,
    material: Material,
    env: Cubemap,
    *,
    model: str = "gltf",
    smith: str = "correlated",
    refine: int = 1,
    chunk: int | None = None,
) -> np.ndarray:
    """Float64 reference of the image-based lighting radiance, (..., 3) NumPy array.

    Lo = occlusion * integral L(l) f_r(v, l) (n.l)+ dl over the whole sphere, L the piecewise-
    constant texels of env level 0, f_r = `jaxpbr.brdf(..., model="gltf", smith=smith)` without a
    roughness floor (Lambert diffuse). Emissive is not added (as in `shade_ibl`).

    n, v: (..., 3) normal and direction to the viewer (normalised here); material leaves
        broadcast with the pixel axes. Pixels with n.v <= 0 get 0 (the BRDF is 0 there; no
        MIN_N_DOT_V clamp, unlike the split sum).
    model: only "gltf" (the default model of `shade_ibl`; its split-sum terms map one to one onto Ld, LA, LB).
    refine: multiplies every sub-texel count (convergence checks: refine=2 vs 1).
    Raises ValueError for roughness below `min_reference_roughness(env.face_size)`.
    Cost: ~6 S^2 q_far^2 kernel evaluations per pixel plus the near tiers (module docstring).
    """
    if model != "gltf":
        raise ValueError(f"reference_ibl supports model 'gltf' only, got {model!r}")
    if not isinstance(material, Material):
        raise TypeError(f"material must be a jaxpbr.Material, got {type(material).__name__}")
    n = np.asarray(n, np.float64)
    v = np.asarray(v, np.float64)
    rough = np.asarray(material.roughness, np.float64)
    shape = np.broadcast_shapes(n.shape[:-1], v.shape[:-1], rough.shape)
    t = reference_ibl_terms(
        np.broadcast_to(n, shape + (3,)), np.broadcast_to(v, shape + (3,)), np.broadcast_to(rough, shape), env,
        smith=smith, refine=refine, chunk=chunk,
    )
    return reference_ibl_from_terms(t, material)


def reference_ibl_from_terms(terms, material: Material) -> np.ndarray:
    """Lo = occlusion ((1 - metallic) base Ld + F0 LA + LB) from `reference_ibl_terms` output
    (..., 3, 3) and a Material (leaves broadcasting with the pixel axes; its roughness must be the
    one the terms were computed for) -> (..., 3) float64."""
    t = np.asarray(terms, np.float64)
    if t.shape[-2:] != (3, 3):
        raise ValueError(f"expected terms of shape (..., 3, 3) from an RGB environment, got {t.shape}")
    base = np.asarray(material.base_color, np.float64)
    m = np.asarray(material.metallic, np.float64)[..., None]
    ao = np.asarray(material.occlusion, np.float64)[..., None]
    f0 = F0_DIELECTRIC * (1.0 - m) + base * m
    out = ((1.0 - m) * base * t[..., 0, :] + f0 * t[..., 1, :] + t[..., 2, :]) * ao
    shape = np.broadcast_shapes(out.shape[:-1], t.shape[:-2])
    return np.broadcast_to(out, shape + (3,)).copy()


def _flat(x, shape, core=()):
    """x broadcast to shape + core and flattened to (N,) + core (float64 NumPy)."""
    return np.broadcast_to(np.asarray(x, np.float64), tuple(shape) + tuple(core)).reshape((-1,) + tuple(core))


def reference_layered(
    n,
    v,
    material: Material,
    env: Cubemap,
    *,
    tangent=None,
    coat_normal=None,
    volume_distance=None,
    sheen_lut=None,
    smith: str = "correlated",
    refine: int = 1,
    chunk: int | None = None,
) -> np.ndarray:
    """Float64 reference of image-based lighting with the glTF material extensions, (..., 3).

    Lo = occlusion * integral over the whole sphere of L(l) f(v, l) |cos| dl, with f |cos| the
    layered BSDF of `jaxpbr.shading.layered.layered_soa` (clear coat, sheen, specular, ior, anisotropy,
    thin and volumetric transmission: reflection above the surface, transmission below it) and L
    the piecewise-constant texels of env level 0; the same quadrature as `reference_ibl` (module
    docstring), with near tiers around every lobe the material has:

    * "R": the base lobe around the mirror direction R (anisotropic lobes are stretched along the
      tangent; q_near is set by the narrower alpha_b = alpha);
    * "Rc": the coat lobe around the coat normal's mirror direction, at alpha_c (where any pixel has
      clearcoat > 0);
    * "T": the transmission lobe (where any pixel has transmission > 0 and metallic < 1): the base
      lobe mirrored through the tangent plane, centred on -v, at alpha (thin-walled); around the
      refracted direction refract(-v, n, 1/ior) at alpha (1 - 1/ior) / 2 (volume, thickness > 0: a
      microfacet tilt theta turns the refracted ray by ~theta (1 - 1/ior) against 2 theta for
      the reflected one, so the lobe is that much narrower).
    The sheen lobe (a band around theta_h = 90 deg, ~sheen_roughness wide) has no near tier: the
    far tier resolves it (its convergence is tested). Each texel is counted once, by the finest
    tier containing it.

    The BSDF is evaluated with min_roughness = `LAYERED_MIN_ROUGHNESS` (1e-4), below every roughness
    the quadrature accepts, i.e. effectively unfloored as in `reference_ibl`: roughness below
    `min_reference_roughness(env.face_size)` raises ValueError, and so does a clear-coat roughness
    (where clearcoat > 0), a sheen roughness (where sheen_color > 0) or a volume lobe width
    alpha (1 - 1/ior) / 2 (where thickness > 0) below that floor's alpha. The sheen albedo scaling
    reads the sheen albedo table E (`sheen_lut`, required with KHR_materials_sheen): E is part of
    the BSDF's definition (KHR_materials_sheen), not an approximation of the integral; a table
    lookup is as exact as the table. Emission is not added; occlusion multiplies.

    n, v: (..., 3) (normalised here); material leaves, tangent (..., 3) (required with
    anisotropy), coat_normal (..., 3) (default n) and volume_distance (...) (default thickness)
    broadcast with the pixel axes. Pixels with n.v <= 0 get 0.
    refine: multiplies every sub-texel count (convergence checks). chunk: pixels per compiled call.
    At neutral extension values the result equals `reference_ibl` to rounding (tested).
    """
    if not isinstance(material, Material):
        raise TypeError(f"material must be a jaxpbr.Material, got {type(material).__name__}")
    if smith not in ("correlated", "separable"):
        raise ValueError(f"unknown smith {smith!r}; choose 'correlated' (glTF) or 'separable'")
    refine = positive_int("refine", refine)
    if chunk is not None:
        positive_int("chunk", chunk)
    ext = material.extensions
    if "anisotropy" in ext and tangent is None:
        raise ValueError("the material has KHR_materials_anisotropy, which needs a surface tangent: pass tangent=.")
    if "sheen" in ext and sheen_lut is None:
        raise ValueError("the material has KHR_materials_sheen: pass sheen_lut= (the sheen albedo table, jaxpbr.shading.sheen_lut()).")
    n = np.asarray(n, np.float64)
    v = np.asarray(v, np.float64)
    fields = [(f.name, f.rank, np.asarray(getattr(material, f.name), np.float64)) for f in fields_of(material) if getattr(material, f.name) is not None]
    shapes = [n.shape[:-1], v.shape[:-1]] + [a.shape[: a.ndim - rank] for _, rank, a in fields]
    opt = {}
    for name, x, core in (("tangent", tangent, 1), ("coat_normal", coat_normal, 1), ("volume_distance", volume_distance, 0)):
        if x is not None:
            x = np.asarray(x, np.float64)
            opt[name] = x
            shapes.append(x.shape[: x.ndim - core])
    shape = np.broadcast_shapes(*shapes)
    n = _flat(n, shape, (3,))
    v = _flat(v, shape, (3,))
    if not np.all(np.isfinite(n)) or not np.all(np.isfinite(v)):
        raise ValueError("n and v must be finite")
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    v = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)
    leaves = {name: _flat(a, shape, (3,) * rank) for name, rank, a in fields}
    opt = {k: _flat(x, shape, (3,) if k != "volume_distance" else ()) for k, x in opt.items()}
    N = n.shape[0]
    S = env.face_size
    C = env.channels
    if C != 3:
        raise ValueError(f"reference_layered needs an RGB environment, got {C} channels")
    if N == 0:
        return np.zeros(shape + (3,))
    full = dict(leaves)  # with the present groups' unset fields at their neutral values
    for g in ext:
        for f, neutral in EXTENSION_FIELDS[g].items():
            if f not in full:
                full[f] = np.broadcast_to(np.asarray(neutral, np.float64), (N,) + np.shape(neutral))

    # the lobes and their widths (alpha), per pixel
    r_floor = min_reference_roughness(S)
    a_floor = r_floor**2
    r = full["roughness"]
    if r.min() < r_floor:
        raise ValueError(
            f"reference_layered resolves roughness >= {r_floor:.4f} on a {S}^2-per-face environment "
            f"(alpha = r^2 >= 4 texels / {MAX_NEAR_Q} sub-texels), got r = {r.min():g}; use a larger face size or a larger roughness"
        )
    nov = np.sum(n * v, -1)
    nov_band = nov.copy()
    lobes = {"R": r * r}
    spine = None  # the largest half-vector tilt followed along an anisotropic lobe, per pixel
    if "anisotropy" in ext:
        s_a = np.clip(full["anisotropy_strength"], 0.0, 1.0)
        a = r * r
        spine = np.where(s_a > 0, _spine_angle(a + (1.0 - a) * s_a * s_a), 0.0)
    if "clearcoat" in ext:
        has = full["clearcoat"] > 0
        if np.any(has):
            rc = full["clearcoat_roughness"]
            if rc[has].min() < r_floor:
                raise ValueError(f"reference_layered resolves clearcoat_roughness >= {r_floor:.4f} on a {S}^2-per-face environment, got {rc[has].min():g}")
            lobes["Rc"] = np.where(has, rc * rc, np.inf)
            cn = n if "coat_normal" not in opt else opt["coat_normal"] / np.linalg.norm(opt["coat_normal"], axis=-1, keepdims=True)
            ncv = np.sum(cn * v, -1)
            nov_band = np.where(has & (ncv > 0), np.minimum(nov_band, ncv), nov_band)
    if "sheen" in ext:
        has = full["sheen_color"].max(-1) > 0
        if np.any(has) and full["sheen_roughness"][has].min() < r_floor:
            raise ValueError(f"reference_layered resolves sheen_roughness >= {r_floor:.4f} on a {S}^2-per-face environment, got {full['sheen_roughness'][has].min():g}")
    if "transmission" in ext:
        has = (full["transmission"] > 0) & (full["metallic"] < 1)
        if np.any(has):
            at = r * r
            if "volume" in ext:
                eta = np.maximum(full["ior"], 1.0) if "ior" in full else np.full(N, 1.5)
                thick = full["thickness"] > 0
                at = np.where(thick, at * (1.0 - 1.0 / eta) / 2.0, at)
                if np.any(has & thick) and at[has & thick].min() < a_floor:
                    raise ValueError(
                        f"reference_layered resolves a volume transmission lobe of width alpha (1 - 1/ior) / 2 >= {a_floor:.4g} "
                        f"on a {S}^2-per-face environment, got {at[has & thick].min():g} (larger roughness or ior, or face size)"
                    )
            lobes["T"] = np.where(has, at, np.inf)

    bright = bright_texels(env.levels[0])
    out = np.zeros((N, C))
    with jax.enable_x64(True):
        L = jnp.asarray(np.asarray(env.levels[0], np.float64).reshape(-1, C))
        T = L.shape[0]
        texel_om = jnp.asarray(texel_solid_angles(S).reshape(-1))
        lut = None if sheen_lut is None else jax.tree_util.tree_map(jnp.asarray, sheen_lut)
        band = np.clip(np.ceil(np.log2(0.25 / np.maximum(nov_band, 1e-300)) - 1e-12), 0, len(_NOV_BANDS) - 1).astype(int)
        band[(nov_band >= 0.25) | (nov <= 0.0)] = 0
        for k in np.unique(band):
            sel = np.nonzero(band == k)[0]
            kinds, q_tiers, counts, q_far = [], [], [], 1
            for name, a in lobes.items():
                a_min = float(a[sel].min())
                if not np.isfinite(a_min):
                    continue
                qf, qr, qn, q_bright = _supersampling(a_min, S, refine, grazing=_NOV_BANDS[k])
                q_far = max(q_far, qf)
                if qn > qf and name == "R" and spine is not None and float(spine[sel].max()) > 0:
                    # centres every half texel of tilt: consecutive mirror directions (which move
                    # by at most twice the tilt) at most a texel apart, so the near windows cover
                    # the spine without gaps
                    count = 2 * math.ceil(float(spine[sel].max()) / (0.5 * _texel_angle(S) / refine) - 1e-9) + 1
                    kinds.append(("A", count))
                    q_tiers.append((qn, qr))
                    counts.append(count)
                elif qn > qf:
                    kinds.append(name)
                    q_tiers.append((qn, qr))
                    counts.append(1)
            q_bright = BRIGHT_Q * refine
            far_dirs, w = _subtexel_points(S, q_far)
            far_om = texel_solid_angles(S)[..., None] * w[None]
            per_pixel = max(T * q_far**2, sum(c * (NEAR_TEXELS * a**2 + RING_TEXELS * b**2) for c, (a, b) in zip(counts, q_tiers)) + len(bright) * q_bright**2)
            ck = max(1, min(64, _BLOCK_LAYERED // per_pixel)) if chunk is None else int(chunk)
            ck = 1 << (ck.bit_length() - 1)
            args = (jnp.asarray(far_dirs.reshape(T, -1, 3)), jnp.asarray(far_om.reshape(T, -1)), texel_om, jnp.asarray(bright))
            for i in range(0, len(sel), ck):
                idx = sel[i : i + ck]
                pad = np.concatenate([idx, np.full(ck - len(idx), idx[-1])])  # pad with the last pixel
                m = evolve(material, **{name: jnp.asarray(x[pad]) for name, x in leaves.items()})
                o = {name: jnp.asarray(x[pad]) for name, x in opt.items()}
                res = _layered_chunk(
                    jnp.asarray(n[pad]), jnp.asarray(v[pad]), m, o.get("tangent"), o.get("coat_normal"), o.get("volume_distance"), lut,
                    L, *args, kinds=tuple(kinds), q_far=q_far, q_tiers=tuple(q_tiers), q_bright=q_bright, S=S, smith=smith,
                )
                out[idx] = np.asarray(res)[: len(idx)]
    out = out * full["occlusion"][:, None]
    return out.reshape(shape + (3,))
