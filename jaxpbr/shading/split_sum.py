"""The pieces of the split sum shared by the core and the layered IBL (`jaxpbr.ibl.shade`,
`jaxpbr.ibl.layered_ibl`) and the scene layer: the LUT weights with Fdez-Aguera's multiple-scattering
term, the diffuse lobe's Fresnel factor, the prefiltered map's lookup direction, and the
compensation of the suns split out of an environment. Re-exported by `jaxpbr.ibl.shade`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._numerics import pack3, safe_normalize, safe_sqrt, unpack3, vdot
from .lights import cap_factor, light_incidence_soa, pack_lights
from .lut import lut_lookup
from .material import F0_DIELECTRIC, Material

__all__ = ["MIN_N_DOT_V", "SCHLICK_LAMBERT_FIT", "diffuse_fresnel_weight", "disc_multiscatter", "multiscatter_weight", "schlick_lambert_average", "specular_dominant_direction", "split_sum_weights"]

#: NoV is clamped to at least this (Filament MIN_N_DOT_V) before the LUT lookup: back-facing or
#: grazing shading normals (normal maps, interpolation) still get the grazing-angle response.
MIN_N_DOT_V = 1e-4


#: Coefficients (in powers of 1 - n.v) of `schlick_lambert_average`: a least-squares fit to the float64
#: Gauss-Legendre integral (400 x 400 nodes) at 401 values of n.v; max error 1.0e-6 (tests check it
#: against an independent quadrature).
SCHLICK_LAMBERT_FIT = (
    8.2385909068e-05, 2.0384538051e-03, 9.2429978670e-03, 6.4808141113e-03,
    1.7973936343e-02, -2.0884349791e-02, 2.0543165137e-02, -7.3208785935e-03,
)


def schlick_lambert_average(nov):
    """W(n.v) = (1/pi) integral over the hemisphere of (1 - v.h)^5 (n.l) dl, h = normalize(v + l):
    the Schlick weight averaged over a Lambertian lobe (MATH: the diffuse lobe's Fresnel factor).
    8.2e-5 at n.v = 1, 0.0282 at n.v = 0. nov (...) in [0, 1]."""
    x = 1.0 - nov
    out = jnp.full_like(x, SCHLICK_LAMBERT_FIT[-1])
    for c in SCHLICK_LAMBERT_FIT[-2::-1]:
        out = out * x + c
    return out


def diffuse_fresnel_weight(f0, f90, nov):
    """What the glTF BRDF's diffuse lobe keeps under its Fresnel layer, averaged over the lobe:
    integral (1 - F(v.h)) (n.l)/pi dl = 1 - f0 - (f90 - f0) W(n.v), F = f0 + (f90 - f0)(1 - v.h)^5
    (Schlick is linear in f0, f90). 0.96 (1 - W) for the core dielectric (f0 0.04, f90 1): the
    split sum's diffuse term is c_diff Ebar(n) times this, exact for a uniform environment.
    f0, f90 broadcasting with nov[..., None] -> (..., C)."""
    w = schlick_lambert_average(nov)[..., None]
    return 1.0 - f0 - (f90 - f0) * w


def specular_dominant_direction(n, R, r):
    """The prefiltered map's lookup direction: the mirror direction R bent towards the normal n
    with roughness (Lagarde & de Rousiers 2014, "Moving Frostbite to PBR", 4.9.3): the lobe of a
    rough surface seen off the normal leans towards n, the more the rougher; the prefilter assumes
    n = v = R. With alpha = r^2 and s = 1 - alpha, d = normalize(n + (R - n) s (sqrt(s) + alpha)):
    R at r = 0, n at r = 1. n, R (..., 3) packed unit vectors; r (...) clamped roughness."""
    a = r * r
    s = 1.0 - a
    t = (s * (safe_sqrt(s) + a))[..., None]  # sqrt'(0) = inf at r = 1: the safe root's gradient is 0
    d = safe_normalize(n + (R - n) * t)
    # d = 0 only for R = -n (a back-facing normal, v = -n) at t = 1/2: look up n there.
    return jnp.where(jnp.sum(d * d, -1, keepdims=True) > 0, d, n)


def split_sum_weights(f0, a, b, *, multiscatter: bool = False, f90=1.0):
    """Specular weight FssEss = F0 A + F90 B and multiple-scattering term FmsEms (0 unless asked).

    f0 (..., C), f90 (broadcasting; 1 for the core model); a, b (...) LUT channels. Fdez-Aguera:
    Ess = A + B, Ems = 1 - Ess, F_avg = F0 + (F90 - F0)/21, FmsEms = FssEss F_avg Ems / (1 - F_avg Ems).
    """
    a = a[..., None]
    b = b[..., None]
    fss_ess = f0 * a + f90 * b
    if not multiscatter:
        return fss_ess, jnp.zeros_like(fss_ess)
    ems = 1.0 - (a + b)
    f_avg = f0 + (f90 - f0) / 21.0
    # 1 - F_avg Ems >= 1 - Ems = Ess > 0 for F_avg <= 1: no division by zero.
    fms_ems = fss_ess * f_avg * ems / (1.0 - f_avg * ems)
    return fss_ess, fms_ems


def multiscatter_weight(nov, m: Material, lut) -> jax.Array:
    """FmsEms of the base material (the dielectric and metal lobes mixed by metallic), (..., 3):
    what the Fdez-Aguera compensation adds per unit Ebar(n). `shade_ibl(multiscatter=True)` adds it
    times the environment's irradiance; the scene layer adds it times the irradiance of the suns
    split out of the environment (`jaxpbr.ibl.extract`). The dielectric lobe takes the material's F0 and
    F90 (KHR_materials_ior / _specular); the sheen and clear-coat layers' scaling of the base and an
    anisotropic lobe's albedo are not applied here, so with those extensions splitting a sun out
    changes the compensation slightly. nov (...) clamped n.v; the roughness is m.roughness clamped
    to [0, 1]."""
    r = jnp.clip(m.roughness, 0.0, 1.0)
    ab = lut_lookup(lut, *jnp.broadcast_arrays(nov, r))
    a, b = ab[..., 0], ab[..., 1]
    base = m.base_color
    if m.layered:
        from .layered import dielectric_fresnel

        f0, f90 = (jnp.stack(jnp.broadcast_arrays(*x), -1) for x in dielectric_fresnel(m.complete()))
        _, fms_d = split_sum_weights(f0, a, b, multiscatter=True, f90=f90)
    else:
        _, fms_d = split_sum_weights(jnp.full_like(base, F0_DIELECTRIC), a, b, multiscatter=True)
    _, fms_m = split_sum_weights(base, a, b, multiscatter=True)
    metallic = jnp.clip(m.metallic, 0.0, 1.0)[..., None]
    return fms_d + (fms_m - fms_d) * metallic


def disc_multiscatter(n, v, m: Material, lut, suns, *, visibility=None) -> jax.Array:
    """The multiple-scattering compensation of disc lights split out of an environment: FmsEms
    (`multiscatter_weight`) times their irradiance / pi at n, as `shade_ibl(multiscatter=True)`
    gives the residual environment's, so splitting a sun out leaves the compensation unchanged (up
    to the extensions `multiscatter_weight` leaves out). n, v (..., 3) unit; suns: a list of DirectionalLights or a LightSet;
    visibility: optional (..., L) fraction of each sun that reaches the point (shadows), or
    (..., L, 3) per colour channel with every batch axis of n present. Occlusion applied."""
    n3 = unpack3(n)
    ls = pack_lights(suns if not isinstance(suns, tuple) else list(suns))
    ebar = None
    zero = tuple(jnp.zeros_like(c) for c in n3)
    for i in range(ls.num_lights):
        light = jax.tree_util.tree_map(lambda x, i=i: x[i], ls)
        l3, e = light_incidence_soa(light, zero)
        k = cap_factor(vdot(n3, l3), light.sin_radius) / jnp.pi
        if visibility is not None and jnp.ndim(visibility) == jnp.ndim(n) + 1:  # (..., L, 3)
            term = pack3(tuple(e[c] * k * visibility[..., i, c] for c in range(3)))
        else:
            if visibility is not None:
                k = k * visibility[..., i]
            term = pack3(tuple(e[c] * k for c in range(3)))
        ebar = term if ebar is None else ebar + term
    nov = jnp.clip(jnp.sum(n * v, -1), MIN_N_DOT_V, 1.0)
    return multiscatter_weight(nov, m, lut) * ebar * m.occlusion[..., None]
