"""The glTF material extensions, term for term: the layered BSDF for direct lighting.

The Khronos extension texts (KHR_materials_clearcoat, _sheen, _specular, _ior, _anisotropy,
_emissive_strength, _transmission, _volume; normative sections and their "Implementation" notes)
define the material as a stack, bottom to top:

    dielectric_f0  = min(((ior - 1)/(ior + 1))^2 specular_color, 1) specular     (RGB; _ior, _specular)
    dielectric_f90 = specular
    F_d            = dielectric_f0 + (dielectric_f90 - dielectric_f0) (1 - v.h)^5
    base_bsdf      = mix(diffuse_brdf(base_color), specular_btdf(alpha) base_color, transmission)
    dielectric     = F_d specular_brdf + (1 - max3(F_d)) base_bsdf                  (fresnel_mix)
    metal          = specular_brdf (base_color + (1 - base_color)(1 - v.h)^5)       (core)
    material       = mix(dielectric, metal, metallic)
    sheen_material = sheen_color D_c V_c + material sheen_albedo_scaling            (_sheen)
    coated         = mix(sheen_material, coat_brdf, clearcoat Fc),  Fc = 0.04 + 0.96 (1 - |v.n_c|)^5
    emission       = emissive emissive_strength (1 - clearcoat Fc)                  (_clearcoat)

with specular_brdf = D V (GGX, height-correlated Smith; anisotropic D and V with _anisotropy:
alpha_t = mix(alpha, 1, strength^2) along the rotated tangent, alpha_b = alpha), coat_brdf = D V at
alpha_c = clearcoat_roughness^2 about the coat normal n_c, D_c V_c the Charlie sheen lobe
(`jaxpbr.shading.sheen`), sheen_albedo_scaling = min(1 - max3(sheen_color) E(n.v), 1 - max3(sheen_color)
E(|n.l|)) with E the sheen albedo table (`jaxpbr.shading.sheen_lut`).

Transmission (light below the surface, n.l < 0, viewer above):
* thin-walled (thickness = 0; _transmission): specular_btdf = D(h_T) V_T with the transmission half
  vector h_T = normalize(v + l - 2 (n.l) n) (l mirrored to the viewer's side) and the separable
  Smith V_T of |n.l|, n.v; F_d at v.h_T;
* volumetric (thickness > 0; _volume): Walter et al.'s refractive BTDF as the extension writes it,
  h = -normalize(v + ior l) (oriented to n), |h.l||h.v| / (|n.l||n.v|) ior^2 G_T D / (h.v + ior h.l)^2,
  Fresnel at |v.h| (light leaves towards the viewer's lighter side: the spec's case 1), times Beer's
  law `attenuation_color^(x / attenuation_distance)` over the path length x in the medium
  (`volume_distance`, e.g. the chord of an analytic sphere; else `thickness`).
  With the ior^2 numerator, the integral of f |n.l| over the inner hemisphere is 1 - F for a
  smooth surface: the exit interface's radiance compression (1/ior^2) and the entry's (ior^2), which
  a one-interface model does not trace, cancel.
  A directional or point light shining from below is taken as arriving at the shading point along
  its own direction inside the medium (the entry refraction is not traced: the spec's rasterizer
  approximation, which shifts only a point light's position by the thickness).

Choices where the texts leave one (each documented where it is made): the anisotropic V is not
clamped to [0, 1] (the sample code's clamp breaks the reduction to the isotropic V, which is not
clamped, at grazing angles for small alpha); the transmission lobe is isotropic at the base alpha
(the anisotropy extension defines the reflection lobe only); roughness and sheen roughness are
floored at `min_roughness` like the core model.

Every extension at its neutral value gives the core glTF BRDF to float rounding (tested); a
Material without extensions never reaches this module (`brdf_terms.brdf_soa`).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._numerics import (
    Vec3,
    as_float,
    orthonormal_frame,
    pack3,
    unpack3,
    vcross,
    vdot,
    vnormalize,
)
from .._validate import batch_shape, check_values, vector
from . import brdf_terms
from .brdf_terms import (
    F0_DIELECTRIC,
    MIN_ROUGHNESS,
    alpha_from_roughness,
    d_ggx,
    f0_from_ior,
    floored_roughness,
    geometry_soa,
    schlick_weight,
    v_smith_correlated,
    v_smith_separable,
)
from .sheen import d_charlie, floored_sheen_roughness, sheen_albedo_scaling, v_charlie

__all__ = [
    "COAT_F0",
    "brdf",
    "layer_setup",
    "LayerInputs",
    "anisotropic_alphas",
    "anisotropy_frame",
    "coat_fresnel",
    "d_ggx_anisotropic",
    "dielectric_fresnel",
    "layered_soa",
    "needs_sheen_lut",
    "transmittance",
    "v_smith_correlated_anisotropic",
]

#: F0 of the clear coat (KHR_materials_clearcoat fixes its ior at 1.5).
COAT_F0 = F0_DIELECTRIC
_INV_PI = 1.0 / math.pi


class LayerInputs(NamedTuple):
    """Per-sample geometry the extensions need besides n, v, l (Vec3 or None)."""

    tangent: Vec3 | None = None  # surface tangent (anisotropy); orthonormalised against n here
    coat_normal: Vec3 | None = None  # clear-coat normal (None: the shading normal)
    volume_distance: jax.Array | None = None  # path length in the medium (None: thickness)


def needs_sheen_lut(m) -> bool:
    """Whether shading `m` reads the sheen albedo table."""
    return "sheen" in m.extensions


# ------------------------------------------------------------------------------------------------
# Terms
# ------------------------------------------------------------------------------------------------


def dielectric_fresnel(m):
    """(f0, f90), each 3 planes (or scalars), of the dielectric layer (KHR_materials_ior +
    _specular): f0 = min(((ior - 1)/(ior + 1))^2 specular_color, 1) specular, f90 = specular.
    Absent extensions give 0.04 and 1 exactly. ior = 0 is glTF's specular-glossiness mode: the
    Fresnel term is 1 at every angle, scaled by the specular factors, so f90 = f0 =
    min(specular_color, 1) specular there (a Schlick mix of equal ends is that constant).
    Traced specular and specular_color are clamped to [0, 1] and >= 0."""
    f0 = F0_DIELECTRIC if m.ior is None else f0_from_ior(m.ior)
    if m.specular is None and m.specular_color is None:
        f0s = (f0, f0, f0)
        f90 = 1.0
    else:
        sc = jnp.maximum(m.specular_color, 0.0) if m.specular_color is not None else jnp.ones(3)
        s = jnp.clip(m.specular, 0.0, 1.0) if m.specular is not None else 1.0
        f0s = tuple(jnp.minimum(f0 * sc[..., i], 1.0) * s for i in range(3))
        f90 = s
    if m.ior is None:
        return f0s, (f90, f90, f90)
    glossy = m.ior == 0
    return f0s, tuple(jnp.where(glossy, f0s[i], f90) for i in range(3))


def _max3(c):
    return jnp.maximum(jnp.maximum(c[0], c[1]), c[2])


#: The index of refraction standing for glTF's ior = 0 ("+infinity", specular-glossiness mode) in
#: refraction: the refracted ray then runs along -n.
IOR_INFINITY = 1e4


def refractive_index(m):
    """The ior refraction uses: max(ior, 1) (1.5 when absent), IOR_INFINITY for ior = 0."""
    if m.ior is None:
        return 1.5
    return jnp.where(m.ior == 0, IOR_INFINITY, jnp.maximum(m.ior, 1.0))


def coat_fresnel(n_c_dot_v):
    """Fc = 0.04 + 0.96 (1 - |n_c.v|)^5 (KHR_materials_clearcoat's layering weight, at n_c.v)."""
    return COAT_F0 + (1.0 - COAT_F0) * schlick_weight(jnp.abs(n_c_dot_v))


def anisotropic_alphas(alpha, strength):
    """(alpha_t, alpha_b) = (mix(alpha, 1, strength^2), alpha) (KHR_materials_anisotropy)."""
    return alpha + (1.0 - alpha) * strength * strength, alpha


def anisotropy_frame(n: Vec3, tangent: Vec3, rotation) -> tuple[Vec3, Vec3]:
    """(T, B): the anisotropy direction (the tangent, orthonormalised against n, rotated by
    `rotation` radians counter-clockwise towards the bitangent n x t) and B = n x T. A tangent
    that is zero or parallel to n has no direction in the surface: there the frame is
    `orthonormal_frame(n)`'s first tangent (a zero T would leave D and V unnormalised)."""
    tn = vdot(tangent, n)
    tp = tuple(tangent[i] - tn * n[i] for i in range(3))
    ok = vdot(tp, tp) > 1e-12 * jnp.maximum(vdot(tangent, tangent), 1e-30)
    fb = orthonormal_frame(n)[0]
    t = vnormalize(tuple(jnp.where(ok, tp[i], fb[i]) for i in range(3)))
    b = vcross(n, t)
    c, s = jnp.cos(rotation), jnp.sin(rotation)
    T = tuple(c * t[i] + s * b[i] for i in range(3))
    return T, vcross(n, T)


def d_ggx_anisotropic(n_dot_h, t_dot_h, b_dot_h, alpha_t, alpha_b):
    """Burley's anisotropic GGX `1 / (pi at ab ((t.h/at)^2 + (b.h/ab)^2 + (n.h)^2)^2)`, written as
    the extension's sample code does (no division by a small alpha^2). 0 for n.h <= 0."""
    a2 = alpha_t * alpha_b
    f = (alpha_b * t_dot_h) ** 2 + (alpha_t * b_dot_h) ** 2 + (a2 * n_dot_h) ** 2
    w2 = a2 / f
    return jnp.where(n_dot_h > 0, a2 * w2 * w2 * _INV_PI, 0.0)


def v_smith_correlated_anisotropic(n_dot_v, n_dot_l, t_dot_v, b_dot_v, t_dot_l, b_dot_l, alpha_t, alpha_b):
    """Height-correlated anisotropic Smith visibility (Heitz 2014), the extension's
    `V_GGX_anisotropic` without its clamp to [0, 1] (see the module docstring)."""
    gv = n_dot_l * jnp.sqrt((alpha_t * t_dot_v) ** 2 + (alpha_b * b_dot_v) ** 2 + n_dot_v * n_dot_v)
    gl = n_dot_v * jnp.sqrt((alpha_t * t_dot_l) ** 2 + (alpha_b * b_dot_l) ** 2 + n_dot_l * n_dot_l)
    return 0.5 / (gv + gl)


def transmittance(m, distance):
    """Beer's law `attenuation_color^(distance / attenuation_distance)` (KHR_materials_volume),
    (..., 3); exactly 1 where attenuation_distance = inf or attenuation_color = 1. Written as
    exp(log(c) x / d) with log(c) floored (c = 0 absorbs everything: finite, gradient finite)."""
    c = m.attenuation_color if m.attenuation_color is not None else jnp.ones(3)
    d = m.attenuation_distance if m.attenuation_distance is not None else jnp.inf
    tiny = jnp.finfo(jnp.result_type(c, float)).tiny
    logc = jnp.log(jnp.maximum(c, tiny))
    x = jnp.asarray(distance)
    ratio = jnp.where(jnp.isfinite(d), x / jnp.where(jnp.isfinite(d), d, 1.0), 0.0)
    return jnp.exp(logc * ratio[..., None])


# ------------------------------------------------------------------------------------------------
# The layered BSDF
# ------------------------------------------------------------------------------------------------


def layered_soa(
    n: Vec3,
    v: Vec3,
    l: Vec3,
    m,
    *,
    min_roughness: float,
    smith: str = "correlated",
    diffuse: str = "lambert",
    sheen_lut=None,
    extra: LayerInputs = LayerInputs(),
    specular_weight=1.0,
    coat_weight=1.0,
) -> Vec3:
    """f |cos|: the layered BSDF times the cosine of each lobe (|n.l| for the base, sheen and
    transmission, n_c.l for the coat), three per-channel planes; 0 where the light does not reach
    the viewer. `m` is a Material with extensions (completed here); n, v, l unit Vec3.

    Reflection where n.v > 0 and n.l > 0; transmission where n.v > 0 > n.l and the material
    has the transmission extension. specular_weight and coat_weight scale the base and the coat
    GGX lobes (a disc light's lobe ratios, `lights.disc_lobe_ratio`).
    """
    ext = m.extensions
    m = m.complete()
    base = tuple(m.base_color[..., i] for i in range(3))
    metallic = jnp.clip(m.metallic, 0.0, 1.0)
    r = floored_roughness(m.roughness, min_roughness)
    alpha = alpha_from_roughness(r)
    nv_raw = vdot(n, v)
    nl_raw = vdot(n, l)
    g = geometry_soa(n, v, l)

    # --- the base specular lobe (isotropic or anisotropic GGX) ---------------------------------
    if "anisotropy" in ext:
        if extra.tangent is None:
            raise ValueError(
                "the material has KHR_materials_anisotropy, which needs a surface tangent: pass "
                "tangent= (the glTF TANGENT direction) to the shading function."
            )
        T, B = anisotropy_frame(n, vnormalize(extra.tangent), m.anisotropy_rotation)
        at, ab = anisotropic_alphas(alpha, jnp.clip(m.anisotropy_strength, 0.0, 1.0))
        h = vnormalize(tuple(v[i] + l[i] for i in range(3)))
        # stand-ins on non-front lanes (h = n, v = l = n) before anything divides
        sel = lambda x, ok: jnp.where(g.front, x, ok)  # noqa: E731
        d = d_ggx_anisotropic(g.n_dot_h, sel(vdot(T, h), 0.0), sel(vdot(B, h), 0.0), at, ab)
        vis = v_smith_correlated_anisotropic(
            g.n_dot_v, g.n_dot_l, sel(vdot(T, v), 0.0), sel(vdot(B, v), 0.0), sel(vdot(T, l), 0.0), sel(vdot(B, l), 0.0), at, ab
        )
    else:
        d = d_ggx(g.n_dot_h, alpha, g.sin2_h)
        vis = (v_smith_correlated if smith == "correlated" else v_smith_separable)(g.n_dot_v, g.n_dot_l, alpha)
    spec = d * vis * specular_weight
    w = schlick_weight(g.v_dot_h)
    f0, f90 = dielectric_fresnel(m)
    F = tuple(f0[i] + (f90[i] - f0[i]) * w for i in range(3))
    fmax = jnp.maximum(jnp.maximum(F[0], F[1]), F[2])
    if diffuse == "lambert":
        diffuse_scale = _INV_PI
    else:  # Burley, as brdf_terms
        fd90 = 0.5 + 2.0 * r * g.v_dot_h * g.v_dot_h
        diffuse_scale = (1.0 + (fd90 - 1.0) * schlick_weight(g.n_dot_l)) * (1.0 + (fd90 - 1.0) * schlick_weight(g.n_dot_v)) * _INV_PI
    tr = jnp.clip(m.transmission, 0.0, 1.0) if "transmission" in ext else None
    if tr is not None:
        diffuse_scale = diffuse_scale * (1.0 - tr)
    refl = []
    for i in range(3):
        diel = F[i] * spec + (1.0 - fmax) * base[i] * diffuse_scale
        metal = spec * (base[i] + (1.0 - base[i]) * w)
        refl.append(jnp.where(g.front, diel * (1.0 - metallic) + metal * metallic, 0.0))
    cos = jnp.where(g.front, g.n_dot_l, 0.0)

    # --- transmission (light below the surface) ------------------------------------------------
    if tr is not None:
        back = (nv_raw > 0) & (nl_raw < 0)
        lm = tuple(l[i] - 2.0 * nl_raw * n[i] for i in range(3))  # mirrored to the viewer's side
        gt = geometry_soa(n, v, lm)  # front on exactly the `back` lanes
        btdf_thin = d_ggx(gt.n_dot_h, alpha, gt.sin2_h) * v_smith_separable(gt.n_dot_v, gt.n_dot_l, alpha)
        wt = schlick_weight(gt.v_dot_h)
        fmax_t = _max3(tuple(f0[i] + (f90[i] - f0[i]) * wt for i in range(3)))
        trans = [(1.0 - fmax_t) * btdf_thin for _ in range(3)]
        if "volume" in ext:
            thick = m.thickness > 0
            eta = refractive_index(m)
            # Walter et al. 2007 / KHR_materials_volume: h = -normalize(v + eta l), on n's side.
            hr = vnormalize(tuple(v[i] + eta * l[i] for i in range(3)))
            flip = jnp.where(vdot(hr, n) < 0, -1.0, 1.0)
            hr = tuple(flip * x for x in hr)
            hv = vdot(hr, v)
            hl = vdot(hr, l)
            noh = vdot(hr, n)
            ok = back & (hv > 0) & (hl < 0) & (noh > 0)
            hv_s = jnp.where(ok, hv, 1.0)
            hl_s = jnp.where(ok, hl, -0.5)
            noh_s = jnp.where(ok, noh, 1.0)
            nl_s = jnp.where(ok, -nl_raw, 1.0)
            nv_s = jnp.where(ok, nv_raw, 1.0)
            denom = hv_s + eta * hl_s
            denom2 = jnp.where(ok, denom * denom, 1.0)
            g2 = (2.0 * nl_s / (nl_s + jnp.sqrt(alpha * alpha + (1.0 - alpha * alpha) * nl_s * nl_s))) * (
                2.0 * nv_s / (nv_s + jnp.sqrt(alpha * alpha + (1.0 - alpha * alpha) * nv_s * nv_s))
            )
            btdf_vol = (
                jnp.abs(hl_s) * hv_s / (nl_s * nv_s) * eta * eta * g2 * d_ggx(noh_s, alpha) / denom2
            )
            btdf_vol = jnp.where(ok, btdf_vol, 0.0)
            wv = schlick_weight(jnp.abs(hv_s))
            fmax_v = _max3(tuple(f0[i] + (f90[i] - f0[i]) * wv for i in range(3)))
            dist = extra.volume_distance if extra.volume_distance is not None else m.thickness
            att = transmittance(m, dist)
            trans = [jnp.where(thick, (1.0 - fmax_v) * btdf_vol * att[..., i], trans[i]) for i in range(3)]
        k = tr * (1.0 - metallic)
        trans = [jnp.where(back, trans[i] * base[i] * k, 0.0) for i in range(3)]
        refl = [refl[i] + trans[i] for i in range(3)]
        cos = jnp.where(back, -nl_raw, cos)
    else:
        back = None
    lit = g.front if back is None else (g.front | back)
    fcos = [refl[i] * cos for i in range(3)]

    # --- sheen (on top of the base, under the coat) ---------------------------------------------
    if "sheen" in ext:
        from .sheen_lut import sheen_lut_lookup  # the table module imports the kernels

        if sheen_lut is None:
            raise ValueError("the material has KHR_materials_sheen: pass sheen_lut= (jaxpbr.shading.sheen_lut()).")
        rs = floored_sheen_roughness(m.sheen_roughness, min_roughness)
        a_s = rs * rs
        lobe = jnp.where(g.front, d_charlie(g.n_dot_h, a_s, g.sin2_h) * v_charlie(g.n_dot_v, g.n_dot_l, a_s) * g.n_dot_l, 0.0)
        # E(n.v) depends on the view only (the same expression for every light: one lookup).
        nv_c = jnp.where(nv_raw > 0, nv_raw, 1.0)
        nl_c = jnp.where(lit, jnp.abs(nl_raw), 1.0)
        sc = jnp.clip(m.sheen_color, 0.0, 1.0)  # traced values are not validated
        scale = sheen_albedo_scaling(sc, sheen_lut_lookup(sheen_lut, nv_c, rs), sheen_lut_lookup(sheen_lut, nl_c, rs))
        fcos = [sc[..., i] * lobe + fcos[i] * scale for i in range(3)]

    # --- clear coat (on top of everything, emission included) -----------------------------------
    if "clearcoat" in ext:
        nc = n if extra.coat_normal is None else vnormalize(extra.coat_normal)
        gc = geometry_soa(nc, v, l)
        rc = floored_roughness(m.clearcoat_roughness, min_roughness)
        ac = alpha_from_roughness(rc)
        vis_c = (v_smith_correlated if smith == "correlated" else v_smith_separable)(gc.n_dot_v, gc.n_dot_l, ac)
        coat = jnp.where(gc.front, d_ggx(gc.n_dot_h, ac, gc.sin2_h) * vis_c * coat_weight, 0.0)
        cc = jnp.clip(m.clearcoat, 0.0, 1.0) * coat_fresnel(vdot(nc, v))
        fcos = [fcos[i] * (1.0 - cc) + cc * coat * gc.n_dot_l for i in range(3)]
    return tuple(fcos)


def _check_layered_model(m, model) -> None:
    if model != "gltf":
        raise ValueError(
            f"the glTF material extensions {m.extensions} are defined on the glTF model only, not "
            f"model={model!r}; use model='gltf' or a Material without extension fields."
        )


def layer_setup(m, model, tangent, coat_normal, volume_distance, sheen_lut):
    """None for a Material without extensions (the core path, unchanged); else the layered
    inputs (LayerInputs, sheen table) after checking the model and the needed arguments."""
    if not m.layered:
        return None
    _check_layered_model(m, model)
    t3 = None if tangent is None else unpack3(as_float(tangent))
    nc3 = None if coat_normal is None else unpack3(as_float(coat_normal))
    dist = None if volume_distance is None else as_float(volume_distance)
    return LayerInputs(tangent=t3, coat_normal=nc3, volume_distance=dist), _sheen_table(m, sheen_lut)


def _sheen_table(m, sheen_lut):
    """The sheen albedo table `m` is shaded with: `sheen_lut`, else the shipped 128^2 one where `m`
    has sheen (None where it has none)."""
    if needs_sheen_lut(m) and sheen_lut is None:
        from .shipped_luts import sheen_lut as _sheen_lut

        return _sheen_lut()
    return sheen_lut


def brdf(
    n,
    v,
    l,
    m,
    *,
    model: str = "gltf",
    min_roughness: float = MIN_ROUGHNESS,
    smith: str = "correlated",
    diffuse: str = "lambert",
    shader_epsilon: float = 1e-4,
    tangent=None,
    coat_normal=None,
    volume_distance=None,
    sheen_lut=None,
) -> jax.Array:
    """`jaxpbr.brdf`: the BRDF f_r(v, l) in 1/sr (no cosine), (..., 3), of a Material with or without
    the glTF extensions. Without them: `brdf_terms.brdf` (every model and option, unchanged).
    With them (model "gltf" only): the layered BSDF of this module, which also transmits light
    from below the surface (n.l < 0) when the material has `transmission`; its value is the sum of
    the lobes times their own cosines divided by |n.l| (the coat's cosine is about coat_normal).
    tangent (..., 3): the surface tangent (anisotropy); coat_normal (..., 3): the clear coat's
    normal (default n); volume_distance (...): path length in the medium (default thickness);
    sheen_lut: the sheen albedo table (default the shipped 128^2 one).
    """
    if not m.layered:
        return brdf_terms.brdf(
            n, v, l, m, model=model, min_roughness=min_roughness, smith=smith, diffuse=diffuse, shader_epsilon=shader_epsilon
        )
    brdf_terms.check_options(model, min_roughness=min_roughness, smith=smith, diffuse=diffuse, shader_epsilon=shader_epsilon)
    n, v, l = (check_values(name, vector(name, x)) for name, x in (("n", n), ("v", v), ("l", l)))
    batch_shape("brdf", ("n", n, 1), ("v", v, 1), ("l", l, 1), material=m)
    _check_layered_model(m, model)
    # (the table as an argument of the program, not a constant folded into it)
    return _layered_brdf_program(n, v, l, m, tangent, coat_normal, volume_distance, _sheen_table(m, sheen_lut),
                                 min_roughness=min_roughness, smith=smith, diffuse=diffuse)


@functools.partial(jax.jit, static_argnames=("min_roughness", "smith", "diffuse"))
def _layered_brdf_program(n, v, l, m, tangent, coat_normal, volume_distance, sheen_lut, *, min_roughness, smith, diffuse):
    """`brdf` of a material with extensions after its checks, as one compiled program (see
    `brdf_terms._brdf_program`)."""
    n3, v3, l3 = (vnormalize(unpack3(x)) for x in (n, v, l))
    extra, table = layer_setup(m, "gltf", tangent, coat_normal, volume_distance, sheen_lut)
    fc = layered_soa(n3, v3, l3, m, min_roughness=min_roughness, smith=smith, diffuse=diffuse, sheen_lut=table, extra=extra)
    c = jnp.abs(vdot(n3, l3))
    return pack3(tuple(jnp.where(c > 0, x / jnp.where(c > 0, c, 1.0), 0.0) for x in fc))


def emission_soa(m, n: Vec3, v: Vec3, coat_normal: Vec3 | None = None) -> jax.Array:
    """emissive * emissive_strength, darkened by the coat (1 - clearcoat Fc), (..., 3)."""
    e = m.emission()
    if "clearcoat" not in m.extensions:
        return e
    mc = m.complete(("clearcoat",))
    nc = n if coat_normal is None else vnormalize(coat_normal)
    k = 1.0 - jnp.clip(mc.clearcoat, 0.0, 1.0) * coat_fresnel(vdot(nc, v))  # |n_c.v| inside
    return e * k[..., None]
