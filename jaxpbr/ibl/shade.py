"""Split-sum image-based lighting: diffuse irradiance + prefiltered specular + BRDF LUT.

    L_o = ao * ( c_diff * k_d(n.v) * Ebar(n)  +  LD(R, r) * (F0 * A + F90 * B) ),    R = reflect(-v, n)

with k_d = 0.96 (1 - W(n.v)) the dielectric Fresnel layer's (1 - F) averaged over the Lambertian
lobe (`diffuse_fresnel_weight`; the float64 reference integrates the glTF BRDF's (1 - F) diffuse
weight, and leaving it out makes dielectrics ~4 % too bright).

(Karis 2013; docs/math.md 4, 6). `Ebar = E/pi` comes from `jaxpbr.ibl.diffuse`, `LD` from
`jaxpbr.ibl.specular` (its roughness -> mip mapping is read from the map's metadata), `(A, B)` from
`jaxpbr.shading.lut`. With `multiscatter=True` the Fdez-Aguera 2019 energy compensation (docs/math.md 5.3, with
the *minus* sign: k_D = c_diff (1 - FssEss - FmsEms)) is applied per lobe -- the dielectric lobe
(F0 = 0.04, c_diff = base_color) and the metal lobe (F0 = base_color, no diffuse) -- and the two
are mixed by metallic, so a white furnace returns exactly 1 for either (docs/math.md 7.5).

The `learnopengl` model reproduces the LearnOpenGL IBL chapter's ambient term for fidelity:
F = fresnelSchlickRoughness(NoV, F0, r) used in place of F0 (`F A + B`) and kD = (1 - F)(1 - metallic)
on the diffuse term; it expects a LUT built with `smith="schlick_ggx"`. It over-brightens grazing
angles (docs/math.md 1.4); the default `gltf` model uses the correct F0 A + B.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._numerics import as_float, pack3, unpack3, vdot, vnormalize
from .._validate import batch_shape
from ..shading.brdf_terms import MODELS, check_options, fresnel_schlick_roughness
from ..shading.lut import lut_lookup
from ..shading.material import F0_DIELECTRIC, Material
from ..shading.split_sum import (  # noqa: F401  (re-exported: the split sum's pieces are part of this module's API)
    MIN_N_DOT_V,
    diffuse_fresnel_weight,
    disc_multiscatter,
    multiscatter_weight,
    schlick_lambert_average,
    specular_dominant_direction,
    split_sum_weights,
)
from .cubemap import Cubemap
from .specular import lookup_of, roughness_to_lod

__all__ = ["IBL_MODELS", "MIN_N_DOT_V", "diffuse_fresnel_weight", "schlick_lambert_average", "shade_ibl", "disc_multiscatter", "multiscatter_weight", "specular_dominant_direction", "split_sum_weights"]

#: The models `shade_ibl` accepts: `brdf_terms.MODELS` (kept under this name for users).
IBL_MODELS = MODELS



def shade_ibl(
    n,
    v,
    m: Material,
    irr: Cubemap,
    pre: Cubemap,
    lut,
    *,
    model: str = "gltf",
    multiscatter: bool = False,
    tangent=None,
    coat_normal=None,
    sheen_lut=None,
    charlie=None,
    volume_distance=None,
    transmit_direction=None,
    transmit_weight: bool = False,
) -> jax.Array:
    """Image-based lighting radiance (..., 3) by the split sum.

    n: (..., 3) unit shading normal; v: (..., 3) unit direction to the viewer.
    m: Material (leaves broadcast with n); occlusion multiplies the result; emissive is *not*
        added (shade_direct adds it once).
    irr: irradiance Cubemap storing Ebar = E/pi (`jaxpbr.ibl.diffuse`), or None to leave the diffuse
        term out (exact for metals, metallic = 1, without multiscatter; the scene layer does this).
    pre: prefiltered Cubemap (`jaxpbr.ibl.specular`); lod from its metadata (`specular.lookup_of`:
        "roughness_mapping", "lod_blend", absent in maps written before it: lod = r (M-1)). A map
        holding only the first mips of an M-level chain (metadata "mapping_levels" = M) is looked
        up with the M-level mapping, clamped to its last level.
    lut: (n_r, n_nov, 2) split-sum LUT (`jaxpbr.brdf_lut`; smith="correlated" for gltf,
        "schlick_ggx" for learnopengl: `brdf_terms.MODEL_REGISTRY[model].lut_smith`).
    model: "gltf" (F0 A + B) or "learnopengl" (fresnelSchlickRoughness, see module docstring).
    multiscatter: Fdez-Aguera energy compensation (gltf model only: True with learnopengl raises
        ValueError, False is allowed).
    tangent, coat_normal, sheen_lut, charlie, volume_distance, transmit_direction: inputs of the
        glTF material extensions (`jaxpbr.ibl.layered_ibl`): (..., 3) tangent (anisotropy), (..., 3)
        coat normal (default n), the sheen albedo table and the Charlie-prefiltered environment
        (sheen), (...) path length in the medium and (..., 3) direction the transmitted light
        comes from (volume; defaults: thickness and the refracted -v). A Material without
        extension fields takes the core split sum above, unchanged.
    transmit_weight: return (radiance, w) with w (..., 3) the factor of the transmission lobe's
        incoming radiance in the result, occlusion included (0 without transmission): a renderer
        adds w x (what the scene behind changes in that radiance) (`layered_ibl.shade_ibl_layered`).
    """
    check_options(model, what="IBL model", multiscatter=multiscatter)
    if irr is None and multiscatter:
        raise ValueError("multiscatter compensation needs the irradiance map (irr) even for metals")
    batch_shape("shade_ibl", ("n", n, 1), ("v", v, 1), material=m)
    n3 = vnormalize(unpack3(as_float(n)))
    v3 = vnormalize(unpack3(as_float(v)))
    nov_raw = vdot(n3, v3)
    # R = 2 (n.v) n - v, the mirror direction; always unit for unit n and v.
    R = pack3(tuple(2.0 * nov_raw * n3[i] - v3[i] for i in range(3)))
    nov = jnp.clip(nov_raw, MIN_N_DOT_V, 1.0)
    r = jnp.clip(m.roughness, 0.0, 1.0)
    nov, r = jnp.broadcast_arrays(nov, r)
    # Traced values are not validated: clamp metallic once, for f0(), diffuse_color() and the
    # mixes below alike (as `brdf_soa` does).
    m = m.replace(metallic=jnp.clip(m.metallic, 0.0, 1.0))

    if m.layered:
        if model != "gltf":
            raise ValueError(
                f"the glTF material extensions {m.extensions} are shaded with model='gltf' only; "
                "use model='gltf' (or drop the extension fields)."
            )
        from .layered_ibl import shade_ibl_layered

        out = shade_ibl_layered(
            n3, v3, R, nov, r, m, irr, pre, lut, multiscatter=multiscatter, tangent=tangent, coat_normal=coat_normal, sheen_lut=sheen_lut,
            charlie=charlie, volume_distance=volume_distance, transmit_direction=transmit_direction,
            transmit_weight=transmit_weight,
        )
        if transmit_weight:
            occ = m.occlusion[..., None]
            return out[0] * occ, out[1] * occ
        return out * m.occlusion[..., None]
    ab = lut_lookup(lut, nov, r)
    a, b = ab[..., 0], ab[..., 1]
    M, mapping, blend = lookup_of(pre)
    # LearnOpenGL looks up at R; the glTF model at the dominant direction.
    d = R if model == "learnopengl" else specular_dominant_direction(pack3(n3), R, r)
    ld = pre.sample(d, roughness_to_lod(r, M, mapping=mapping, lod_blend=blend))
    ebar = irr.sample(pack3(n3)) if irr is not None else None
    base = m.base_color
    metallic = m.metallic[..., None]

    if model == "learnopengl":
        f0 = m.f0()
        F = fresnel_schlick_roughness(nov, f0, r)
        out = ld * (F * a[..., None] + b[..., None])
        if ebar is not None:
            out = out + (1.0 - F) * (1.0 - metallic) * base * ebar
    elif not multiscatter:
        fss_ess, _ = split_sum_weights(m.f0(), a, b)
        out = ld * fss_ess
        if ebar is not None:
            # The diffuse lobe under the dielectric Fresnel layer, (1 - F) averaged over it.
            out = out + m.diffuse_color() * diffuse_fresnel_weight(F0_DIELECTRIC, 1.0, nov) * ebar
    else:
        # Per lobe, then mixed by metallic (the compensation is not linear in F0).
        f0_d = jnp.full_like(base, F0_DIELECTRIC)
        fss_d, fms_d = split_sum_weights(f0_d, a, b, multiscatter=True)
        kd = base * (1.0 - fss_d - fms_d)
        diel = fss_d * ld + (fms_d + kd) * ebar
        fss_m, fms_m = split_sum_weights(base, a, b, multiscatter=True)
        metal = fss_m * ld + fms_m * ebar
        out = diel + (metal - diel) * metallic
    out = out * m.occlusion[..., None]
    return (out, jnp.zeros_like(out)) if transmit_weight else out
