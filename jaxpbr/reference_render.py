"""Float64 brute-force reference of image-based lighting: the full reflectance integral.

    Lo(v) = ao * integral over the sphere of L(l) f_r(v, l) (n.l)+ dl

with L the environment's level 0 as a piecewise-constant function of its texels (the definition
`jaxpbr.specular.prefilter_reference` and the exact irradiance use) and f_r the complete glTF
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
result there is still a float64 texel sum but less resolved (measured in the README). Memory is
bounded by evaluating chunks of pixels (a power of two that keeps the largest pixels x sub-texels
block near 4M float64 elements) with one compiled program per tier configuration, so any image
size runs; compilation (~2-5 s per configuration) dominates small calls.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._api import keyword_only
from ._numerics import HIGHEST
from ._validate import positive_int
from .conventions import luminance
from .cubemap import (
    _FACE_TABLE,
    Cubemap,
    _subtexel_points,
    dir_to_face,
    face_to_dir,
    texel_solid_angles,
)
from .material import F0_DIELECTRIC, Material

__all__ = [
    "MAX_NEAR_Q",
    "NEAR_TEXELS",
    "RING_TEXELS",
    "min_reference_roughness",
    "bright_texels",
    "reference_ibl",
    "reference_ibl_from_terms",
    "reference_ibl_terms",
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
    1 - NoH^2 cancellation costs ~1e-11 relative at alpha 0.002, MATH.md 8.2 is a float32 issue).
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


@functools.partial(jax.jit, static_argnames=("q_far", "q_ring", "q_near", "q_bright", "S", "smith"))
def _terms_chunk(nc, vc, ac, L, far_dirs, far_om, texel_om, bright, *, q_far, q_ring, q_near, q_bright, S, smith):
    """(P, 3 terms, C) sums for one chunk of pixels n, v (P, 3), alpha^2 (P,); module docstring.
    One compiled program per tier configuration and chunk size (the caller pads the last chunk)."""
    T = L.shape[0]
    tiers = q_near > q_far
    nb = bright.shape[0]
    n = nc
    P = nc.shape[0]
    nov = jnp.sum(nc * vc, -1)
    a2c = ac[:, None, None]

    parts = []  # the fine tiers, flattened to (P, samples) and evaluated by one kernel call

    def tier(sel, q, weight):
        nol, vol, om = _subtexel_dots(sel, nc, vc, S, q, texel_om)  # (P, k, q2) each
        Ls = jnp.broadcast_to(L[sel][..., None, :], om.shape[:-1] + (q * q, L.shape[1]))
        om = om * weight[..., None]
        parts.append(tuple(x.reshape(P, -1, *x.shape[3:]) for x in (nol, vol, om, jnp.broadcast_to(Ls, (P,) + Ls.shape[-3:]))))

    keep = jnp.ones((P, T), n.dtype)
    wb = jnp.ones((P, nb), n.dtype)
    if nb:
        keep = keep.at[:, bright].set(0.0)
    if tiers:
        R = 2.0 * nov[:, None] * nc - vc
        win, first = _window_texels(R, S, 3)  # 9 near + 40 ring texels around R
        keep = keep.at[jnp.arange(P)[:, None], win].set(0.0)
        w = first.astype(n.dtype)
        if nb:
            # Each bright texel is counted once: by the near tier if it lies there and that
            # tier is at least as fine as the bright tier, otherwise by the bright tier.
            is_b = jnp.any(win[:, :, None] == bright[None, None, :], -1).astype(n.dtype)
            if q_near >= q_bright:
                w = w * jnp.concatenate([jnp.ones_like(is_b[:, :NEAR_TEXELS]), 1.0 - is_b[:, NEAR_TEXELS:]], 1)
                in_near = jnp.any(bright[None, :, None] == win[:, None, :NEAR_TEXELS], -1)
                wb = 1.0 - in_near.astype(n.dtype)
            else:
                w = w * (1.0 - is_b)
        tier(win[:, :NEAR_TEXELS], q_near, w[:, :NEAR_TEXELS])
        tier(win[:, NEAR_TEXELS:], q_ring, w[:, NEAR_TEXELS:])
    if nb:
        tier(bright, q_bright, wb)
    out = 0.0
    if parts:
        nol, vol, om, Ls = (jnp.concatenate(x, 1) for x in zip(*parts))
        k3 = _kernels(nol, vol, nov[:, None], ac[:, None], smith)
        out = jnp.stack([jnp.einsum("pm,pmc->pc", k * om, Ls, precision=HIGHEST) for k in k3], 1)
    nol = jnp.einsum("pk,tsk->pts", nc, far_dirs, precision=HIGHEST)
    vol = jnp.einsum("pk,tsk->pts", vc, far_dirs, precision=HIGHEST)
    k3 = _kernels(nol, vol, nov[:, None, None], a2c, smith)
    return out + _apply(k3, far_om[None] * keep[..., None], L)


def _subtexel_dots(idx, nc, vc, S: int, q: int, texel_om):
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
    return nol, vol, om


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
