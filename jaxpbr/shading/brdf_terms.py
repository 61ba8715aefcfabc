"""BRDF terms (GGX, Smith, Schlick, Lambert, Burley) and the two complete models.

Notation follows docs/math.md: `n, v, l` unit vectors pointing away from the surface, `h = normalize(v+l)`,
`r` perceptual roughness, `alpha = r^2`, `NoV = n.v` etc. Every term is a pure function that
broadcasts over leading axes; scalars per sample are shaped `(...)`, colours `(..., 3)`.

Models (`brdf(..., model=...)`):

* ``"gltf"`` (default) — glTF 2.0 Appendix B metallic-roughness: GGX D, height-correlated Smith V,
  `fresnel_mix` for the dielectric layer over a Lambert base and `conductor_fresnel` for the metal.
* ``"learnopengl"`` — the UE4/Karis model as the LearnOpenGL PBR lighting shader (`pbr.fs`) writes
  it: Schlick-GGX with `k = (r+1)^2/8`, `F0 = mix(0.04, albedo, metallic)`,
  `kD = (1 - F)(1 - metallic)`, `f = kD*albedo/pi + D*G*F / (4*NoV*NoL + shader_epsilon)`.

`MODEL_REGISTRY` is the one list of models and of the options each uses; an option given a
non-default value with a model that does not use it is an error (`check_options`).

Stiff inputs (docs/math.md §8) are handled once, in `geometry_soa`: directions are normalised safely, the
half vector of v = -l is the zero vector, and lanes where the surface does not see both the viewer
and the light (NoV <= 0 or NoL <= 0) get benign stand-in values before anything divides, then a
BRDF of exactly 0. Roughness is floored at `min_roughness` (default 0.045, Filament's desktop
`MIN_PERCEPTUAL_ROUGHNESS`), because a punctual light on an r = 0 mirror is a delta: D = 0/0.
Below the floor the value is that of r = min_roughness and d f/d r = 0.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from .._numerics import Vec3, pack3, saturate, unpack3, vcross, vdot, vnormalize
from .._validate import batch_shape, check_values, vector
from .material import F0_DIELECTRIC, Material

__all__ = [
    "MIN_ROUGHNESS",
    "MODELS",
    "MODEL_REGISTRY",
    "OPTION_CHOICES",
    "OPTION_DEFAULTS",
    "alpha_from_roughness",
    "blinn_phong",
    "brdf",
    "burley",
    "conductor_fresnel",
    "d_ggx",
    "f0_from_ior",
    "fresnel_mix",
    "fresnel_schlick",
    "fresnel_schlick_roughness",
    "g1_schlick_ggx",
    "k_direct",
    "k_ibl",
    "lambert",
    "schlick_weight",
    "smith_g1",
    "smith_g2_separable",
    "smith_lambda",
    "v_schlick_ggx",
    "v_smith_correlated",
    "v_smith_separable",
]

#: Perceptual-roughness floor for punctual lights (Filament desktop MIN_PERCEPTUAL_ROUGHNESS;
#: alpha >= 0.002025). A delta lobe cannot be evaluated pointwise, and below this float32 D and its
#: gradient lose all precision.
MIN_ROUGHNESS = 0.045

#: Defaults of every option a model may use: the `brdf` / `shade_direct` options, then the
#: `shade_ibl` / `RenderOptions` one. Which model uses which is `MODEL_REGISTRY`.
OPTION_DEFAULTS: Mapping[str, Any] = MappingProxyType(
    {
        "min_roughness": MIN_ROUGHNESS,
        "smith": "correlated",
        "diffuse": "lambert",
        "shader_epsilon": 1e-4,
        "multiscatter": False,
    }
)

#: The valid values of the options that are names.
OPTION_CHOICES: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {"smith": ("correlated", "separable"), "diffuse": ("lambert", "burley")}
)


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """One BRDF model: the options it uses and the split-sum LUT its IBL term expects.

    options: the `brdf` / `shade_direct` options the model reads (defaults in `OPTION_DEFAULTS`).
    ibl_options: the `shade_ibl` / `RenderOptions` options it reads.
    lut_smith: the Smith term (`jaxpbr.shading.lut` vocabulary) of the LUT that `shade_ibl` expects with it.
    """

    options: frozenset[str]
    ibl_options: frozenset[str]
    lut_smith: str


#: The one registry of BRDF models: name -> ModelSpec. `brdf`, `shade_direct`, `shade_ibl`,
#: `RenderOptions`, the CLI's --model and scene files' [render] model all read it.
#:   gltf: GGX + Smith V (smith "correlated" | "separable") + diffuse ("lambert" | "burley"),
#:     roughness floor; Fdez-Aguera multiscatter in IBL; LUT with height-correlated Smith.
#:   learnopengl: GGX + Schlick-GGX k=(r+1)^2/8 (no smith/diffuse choice), the shader's epsilon,
#:     roughness floor; no multiscatter; LUT with Schlick-GGX k = alpha/2 ("schlick_ggx").
MODEL_REGISTRY: Mapping[str, ModelSpec] = MappingProxyType(
    {
        "gltf": ModelSpec(
            options=frozenset({"min_roughness", "smith", "diffuse"}),
            ibl_options=frozenset({"multiscatter"}),
            lut_smith="correlated",
        ),
        "learnopengl": ModelSpec(
            options=frozenset({"min_roughness", "shader_epsilon"}),
            ibl_options=frozenset(),
            lut_smith="schlick_ggx",
        ),
    }
)

#: The model names, from `MODEL_REGISTRY` (default first).
MODELS = tuple(MODEL_REGISTRY)

_INV_PI = 1.0 / math.pi


# --------------------------------------------------------------------------------------------
# Individual terms
# --------------------------------------------------------------------------------------------


def alpha_from_roughness(r: jax.Array) -> jax.Array:
    """GGX width alpha = r^2 from perceptual roughness r (glTF, Disney, Filament)."""
    return r * r


def d_ggx(n_dot_h: jax.Array, alpha: jax.Array, sin2_h: jax.Array | None = None) -> jax.Array:
    """GGX / Trowbridge-Reitz normal distribution D(h), in 1/sr, shape (...).

    `D = alpha^2 / (pi d^2)` with `d = (1 - NoH^2) + (NoH alpha)^2` — the cancellation-free form
    (docs/math.md §1.1, Filament `D_GGX`); the textbook `NoH^2 (alpha^2 - 1) + 1` loses ~20 % in float32
    at r = 0.02. Pass `sin2_h = |n x h|^2` (Lagrange identity) to avoid `1 - NoH^2` entirely.
    Domain: alpha > 0 (alpha = 0 is a delta). Zero for NoH <= 0 (chi+).
    """
    if sin2_h is None:
        sin2_h = 1.0 - n_dot_h * n_dot_h
    d = sin2_h + (n_dot_h * alpha) ** 2
    dd = alpha / d
    return jnp.where(n_dot_h > 0, dd * dd * _INV_PI, 0.0)


def smith_lambda(mu: jax.Array, alpha: jax.Array) -> jax.Array:
    """Smith Lambda for GGX, `(sqrt(alpha^2 + (1-alpha^2) mu^2)/mu - 1)/2`, for mu = cos theta > 0."""
    a2 = alpha * alpha
    return 0.5 * (jnp.sqrt(a2 + (1.0 - a2) * mu * mu) / mu - 1.0)


def smith_g1(mu: jax.Array, alpha: jax.Array) -> jax.Array:
    """Smith masking G1 = 1/(1+Lambda) = 2 mu / (mu + sqrt(alpha^2 + (1-alpha^2) mu^2)), mu >= 0."""
    a2 = alpha * alpha
    return 2.0 * mu / (mu + jnp.sqrt(a2 + (1.0 - a2) * mu * mu))


def smith_g2_separable(n_dot_v, n_dot_l, alpha):
    """Uncorrelated (separable) Smith G2 = G1(NoV) G1(NoL)."""
    return smith_g1(n_dot_v, alpha) * smith_g1(n_dot_l, alpha)


def v_smith_correlated(n_dot_v, n_dot_l, alpha):
    """Height-correlated Smith visibility V = G2 / (4 NoV NoL) (Heitz 2014; glTF App. B; Filament).

    `V = 0.5 / (NoL sqrt(NoV^2 (1-a^2) + a^2) + NoV sqrt(NoL^2 (1-a^2) + a^2))` — no NoV*NoL
    division, finite for NoV, NoL >= 0 unless alpha = 0 and both are 0.
    """
    a2 = alpha * alpha
    gv = n_dot_l * jnp.sqrt(n_dot_v * n_dot_v * (1.0 - a2) + a2)
    gl = n_dot_v * jnp.sqrt(n_dot_l * n_dot_l * (1.0 - a2) + a2)
    return 0.5 / (gv + gl)


def v_smith_separable(n_dot_v, n_dot_l, alpha):
    """Separable Smith visibility G1(NoV) G1(NoL) / (4 NoV NoL), division-free:

    `1 / ((NoV + sqrt(a^2 + (1-a^2) NoV^2)) (NoL + sqrt(a^2 + (1-a^2) NoL^2)))`.
    """
    a2 = alpha * alpha
    sv = n_dot_v + jnp.sqrt(a2 + (1.0 - a2) * n_dot_v * n_dot_v)
    sl = n_dot_l + jnp.sqrt(a2 + (1.0 - a2) * n_dot_l * n_dot_l)
    return 1.0 / (sv * sl)


def k_direct(r: jax.Array) -> jax.Array:
    """Schlick-GGX k for analytic lights, `(r + 1)^2 / 8` (Karis 2013, Disney's 'hotness' remap)."""
    return (r + 1.0) ** 2 / 8.0


def k_ibl(r: jax.Array) -> jax.Array:
    """Schlick-GGX k for image-based lighting, `alpha / 2 = r^2 / 2` (Karis 2013; exact Smith at r=1)."""
    return r * r / 2.0


def g1_schlick_ggx(mu: jax.Array, k: jax.Array) -> jax.Array:
    """Schlick-GGX masking `mu / (mu (1 - k) + k)`, for mu >= 0 and k > 0."""
    return mu / (mu * (1.0 - k) + k)


def v_schlick_ggx(n_dot_v, n_dot_l, k):
    """Schlick-GGX visibility `G1(NoV) G1(NoL) / (4 NoV NoL) = 1 / (4 (NoV(1-k)+k)(NoL(1-k)+k))`.

    Division-free (docs/math.md §1.3): finite for any k > 0 (k_direct >= 1/8 always).
    """
    return 0.25 / ((n_dot_v * (1.0 - k) + k) * (n_dot_l * (1.0 - k) + k))


def schlick_weight(cos_theta: jax.Array) -> jax.Array:
    """`(1 - cos)^5` with `1 - cos` clamped to [0, 1] (a dot product can exceed 1 by rounding)."""
    x = saturate(1.0 - cos_theta)
    x2 = x * x
    return x2 * x2 * x


def fresnel_schlick(cos_theta, f0, f90=1.0):
    """Schlick Fresnel `F0 + (F90 - F0)(1 - cos)^5`; `cos_theta` (...), `f0` (...) or (..., 3).

    For a colour `f0` pass `cos_theta[..., None]`.
    """
    return f0 + (f90 - f0) * schlick_weight(cos_theta)


def fresnel_schlick_roughness(n_dot_v, f0, r):
    """Lagarde's roughness-aware Schlick, `F0 + (max(1 - r, F0) - F0)(1 - NoV)^5` (docs/math.md §1.4).

    A heuristic for the ambient term of LearnOpenGL; note mu = NoV, not VoH. `n_dot_v` and `r`
    (...), `f0` (..., 3) -> (..., 3).
    """
    w = schlick_weight(n_dot_v)[..., None]
    return f0 + (jnp.maximum(1.0 - r[..., None], f0) - f0) * w


def f0_from_ior(ior):
    """Normal-incidence reflectance `((ior - 1)/(ior + 1))^2` (ior 1.5 -> 0.04)."""
    return ((ior - 1.0) / (ior + 1.0)) ** 2


def lambert(c_diff: jax.Array) -> jax.Array:
    """Lambert diffuse BRDF `c_diff / pi` (albedo = c_diff exactly)."""
    return c_diff * _INV_PI


def burley(c_diff, r, n_dot_v, n_dot_l, l_dot_h):
    """Burley / Disney 2012 diffuse, with *perceptual* r as in Disney's `disney.brdf`:

    `F_D90 = 0.5 + 2 r LoH^2`, `f = c_diff/pi (1 + (F_D90-1)(1-NoL)^5)(1 + (F_D90-1)(1-NoV)^5)`.
    Not energy conserving (albedo 87/84 at r = 1, NoV = 1). `c_diff` (..., 3), the rest (...).
    """
    fd90 = 0.5 + 2.0 * r * l_dot_h * l_dot_h
    scale = (1.0 + (fd90 - 1.0) * schlick_weight(n_dot_l)) * (1.0 + (fd90 - 1.0) * schlick_weight(n_dot_v))
    return c_diff * (scale * _INV_PI)[..., None]


def blinn_phong(n_dot_h, shininess, *, normalized: bool = False):
    """Blinn-Phong specular lobe `max(NoH, 0)^s` — the non-physical baseline, not an energy model.

    With `normalized=True` the lobe is scaled by `(s + 8) / (8 pi)` (the usual approximate
    normalisation). Used only for comparisons with the Blinn-Phong seeds.
    """
    lobe = jnp.power(jnp.maximum(n_dot_h, 0.0), shininess)
    if normalized:
        lobe = lobe * (shininess + 8.0) / (8.0 * math.pi)
    return lobe


def fresnel_mix(v_dot_h, base, layer, f0=F0_DIELECTRIC):
    """glTF `fresnel_mix(ior=1.5, base, layer)` = mix(base, layer, f0 + (1 - f0)(1 - VoH)^5).

    `v_dot_h` (...); `base` (..., 3) the diffuse BRDF (colour); `layer` (...) the specular BRDF,
    a per-sample scalar (glTF's specular_brdf is achromatic). Returns (..., 3).
    """
    fr = (f0 + (1.0 - f0) * schlick_weight(v_dot_h))[..., None]
    return base * (1.0 - fr) + jnp.asarray(layer)[..., None] * fr


def conductor_fresnel(v_dot_h, f0, bsdf):
    """glTF `conductor_fresnel(f0, bsdf)` = bsdf * (f0 + (1 - f0)(1 - VoH)^5).

    `v_dot_h` (...); `f0` (..., 3) colour; `bsdf` (...) per-sample scalar. Returns (..., 3).
    """
    return jnp.asarray(bsdf)[..., None] * fresnel_schlick(jnp.asarray(v_dot_h)[..., None], f0)


# --------------------------------------------------------------------------------------------
# Geometry shared by the models (structure-of-arrays internally, see _numerics.Vec3)
# --------------------------------------------------------------------------------------------


class Geometry(NamedTuple):
    """Dot products for one (n, v, l) configuration, already made safe. Fields are (...) planes.

    On lanes where `front` is False every field holds a benign stand-in (1 or 0) so that no term
    divides by zero and no NaN reaches the gradient; models must mask their result with `front`
    via `jnp.where`.
    """

    n_dot_v: jax.Array
    n_dot_l: jax.Array
    n_dot_h: jax.Array
    v_dot_h: jax.Array
    sin2_h: jax.Array  # |n x h|^2 = 1 - NoH^2 without cancellation
    front: jax.Array  # NoV > 0 and NoL > 0


def geometry_soa(n: Vec3, v: Vec3, l: Vec3) -> Geometry:
    """Safe dot products of unit Vec3 directions (`n, v, l` already normalised)."""
    h = vnormalize((v[0] + l[0], v[1] + l[1], v[2] + l[2]))  # v = -l -> h = 0, no NaN
    nv = vdot(n, v)
    nl = vdot(n, l)
    front = (nv > 0) & (nl > 0)
    c = vcross(n, h)
    # Double where: stand-ins on the masked lanes (see module docstring).
    return Geometry(
        n_dot_v=jnp.where(front, jnp.minimum(nv, 1.0), 1.0),
        n_dot_l=jnp.where(front, jnp.minimum(nl, 1.0), 1.0),
        n_dot_h=jnp.where(front, jnp.minimum(vdot(n, h), 1.0), 1.0),
        v_dot_h=jnp.where(front, saturate(vdot(v, h)), 1.0),
        sin2_h=jnp.where(front, vdot(c, c), 0.0),
        front=front,
    )


def geometry(n: jax.Array, v: jax.Array, l: jax.Array) -> Geometry:
    """Safe dot products of (..., 3) directions (normalised here; zero vectors give front = False)."""
    return geometry_soa(*(vnormalize(unpack3(x)) for x in (n, v, l)))


def floored_roughness(r: jax.Array, min_roughness: float) -> jax.Array:
    """clip(r, min_roughness, 1): the punctual-light floor (d/dr = 0 below it)."""
    return jnp.clip(r, min_roughness, 1.0)


# --------------------------------------------------------------------------------------------
# Models. Each maps (Geometry, per-channel base colour planes, metallic, floored r) to the three
# per-channel BRDF planes, unmasked. Written per channel so the kernel fuses (see Vec3).
# --------------------------------------------------------------------------------------------


def _is_default(name: str, value) -> bool:
    try:
        return bool(value == OPTION_DEFAULTS[name])
    except Exception:  # e.g. an array: not the (scalar) default
        return False


def check_options(model: str, *, what: str = "model", **options) -> ModelSpec:
    """Validate `model` and the static options passed with it against `MODEL_REGISTRY`; return
    the model's `ModelSpec`.

    Raises ValueError for an unknown model or choice, and for an option the model does not use
    given a value other than its default (naming the option, the model and the fix): such an
    option used to be ignored silently. Passing an unused option *with its default value* is
    allowed, so code that spells out every option, or loops over models with the same keywords,
    keeps working. An option name no model has raises TypeError. `what` names the model argument
    in the unknown-model message (e.g. "IBL model").
    """
    spec = MODEL_REGISTRY.get(model) if isinstance(model, str) else None
    if spec is None:
        raise ValueError(f"unknown {what} {model!r}; choose one of {MODELS}.")
    unknown = sorted(set(options) - set(OPTION_DEFAULTS))
    if unknown:
        raise TypeError(f"unknown option(s) {unknown}; the model options are {sorted(OPTION_DEFAULTS)}.")
    for name, value in options.items():
        choices = OPTION_CHOICES.get(name)
        if choices is not None and value not in choices:
            raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(map(repr, choices))}.")
        if name not in spec.options | spec.ibl_options and not _is_default(name, value):
            users = [m for m, s in MODEL_REGISTRY.items() if name in s.options | s.ibl_options]
            raise ValueError(
                f"{name} is defined for the {' and '.join(users)} model only, not model={model!r} "
                f"(got {name}={value!r}, which that model would ignore); leave {name} out "
                f"(or pass its default {OPTION_DEFAULTS[name]!r}), or use model={users[0]!r}."
            )
    if "min_roughness" in options:
        mr = options["min_roughness"]
        if isinstance(mr, bool) or not (isinstance(mr, (int, float)) and 0.0 < mr <= 1.0):
            raise ValueError(
                f"min_roughness must be a Python float in (0, 1], got {mr!r}; "
                f"the default {MIN_ROUGHNESS} is Filament's desktop floor."
            )
    return spec


def _gltf(g: Geometry, base: Vec3, metallic, r, *, smith: str, diffuse: str, specular_weight=1.0) -> Vec3:
    """glTF 2.0 App. B: mix(fresnel_mix(diffuse, specular), conductor_fresnel(base, specular), metallic).
    specular_weight scales the D V lobe (see `brdf_soa`)."""
    alpha = alpha_from_roughness(r)
    d = d_ggx(g.n_dot_h, alpha, g.sin2_h)
    if smith == "correlated":
        vis = v_smith_correlated(g.n_dot_v, g.n_dot_l, alpha)
    else:
        vis = v_smith_separable(g.n_dot_v, g.n_dot_l, alpha)
    specular = d * vis if isinstance(specular_weight, (int, float)) and specular_weight == 1 else d * vis * specular_weight
    w = schlick_weight(g.v_dot_h)
    f_diel = F0_DIELECTRIC + (1.0 - F0_DIELECTRIC) * w  # fresnel_mix weight, ior 1.5
    if diffuse == "lambert":
        diffuse_scale = _INV_PI
    else:  # Burley, with perceptual r (Disney)
        fd90 = 0.5 + 2.0 * r * g.v_dot_h * g.v_dot_h
        diffuse_scale = (
            (1.0 + (fd90 - 1.0) * schlick_weight(g.n_dot_l))
            * (1.0 + (fd90 - 1.0) * schlick_weight(g.n_dot_v))
            * _INV_PI
        )
    out = []
    for c in base:
        dielectric = c * diffuse_scale * (1.0 - f_diel) + specular * f_diel
        metal = specular * (c + (1.0 - c) * w)
        out.append(dielectric * (1.0 - metallic) + metal * metallic)
    return tuple(out)


def _learnopengl(g: Geometry, base: Vec3, metallic, r, *, shader_epsilon: float, specular_weight=1.0) -> Vec3:
    """LearnOpenGL pbr.fs: kD * albedo / pi + D G F / (4 NoV NoL + eps), kD = (1 - F)(1 - metallic).
    specular_weight scales the D V lobe (see `brdf_soa`)."""
    alpha = alpha_from_roughness(r)
    d = d_ggx(g.n_dot_h, alpha, g.sin2_h)
    vis = v_schlick_ggx(g.n_dot_v, g.n_dot_l, k_direct(r))  # = G / (4 NoV NoL), division-free
    if shader_epsilon:
        # The shader divides by 4 NoV NoL + eps: G/(4 NoV NoL + eps) = V * q/(q + eps), q = 4 NoV NoL.
        # Written this way the value is finite without relying on eps (q + eps >= eps > 0).
        q = 4.0 * g.n_dot_v * g.n_dot_l
        vis = vis * (q / (q + shader_epsilon))
    specular = d * vis if isinstance(specular_weight, (int, float)) and specular_weight == 1 else d * vis * specular_weight
    w = schlick_weight(g.v_dot_h)
    out = []
    for c in base:
        f0 = F0_DIELECTRIC * (1.0 - metallic) + c * metallic
        f = f0 + (1.0 - f0) * w
        k_d = (1.0 - f) * (1.0 - metallic)
        out.append(k_d * c * _INV_PI + f * specular)
    return tuple(out)


def brdf_soa(
    g: Geometry,
    base: Vec3,
    metallic: jax.Array,
    roughness: jax.Array,
    *,
    model: str,
    min_roughness: float,
    smith: str = "correlated",
    diffuse: str = "lambert",
    shader_epsilon: float = 1e-4,
    specular_weight=1.0,
) -> Vec3:
    """Per-channel BRDF planes, masked by `g.front` (options already validated).

    metallic is clamped to [0, 1] like roughness to its range: a concrete Material is validated,
    but a traced value is not, and metallic -1 made the BRDF negative (issue 13).
    specular_weight: a factor on the specular (D V) lobe, broadcasting with the planes: a disc light
    replaces D by its mean over the disc (`lights.disc_lobe_ratio`); the Python 1 adds no code."""
    r = floored_roughness(roughness, min_roughness)
    metallic = jnp.clip(metallic, 0.0, 1.0)
    if model == "gltf":
        f = _gltf(g, base, metallic, r, smith=smith, diffuse=diffuse, specular_weight=specular_weight)
    else:
        f = _learnopengl(g, base, metallic, r, shader_epsilon=float(shader_epsilon), specular_weight=specular_weight)
    return tuple(jnp.where(g.front, c, 0.0) for c in f)


def brdf(
    n: jax.Array,
    v: jax.Array,
    l: jax.Array,
    m: Material,
    *,
    model: str = "gltf",
    min_roughness: float = MIN_ROUGHNESS,
    smith: str = "correlated",
    diffuse: str = "lambert",
    shader_epsilon: float = 1e-4,
) -> jax.Array:
    """The full BRDF f_r(v, l) in 1/sr (no cosine factor), shape broadcast(...) + (3,).

    Args:
      n, v, l: (..., 3) normal, direction to the viewer, direction to the light (normalised here;
        zero vectors give 0). All point away from the surface.
      m: `Material`, leaves broadcasting with the directions' batch axes.
      model: "gltf" (glTF 2.0 App. B) or "learnopengl" (LearnOpenGL `pbr.fs`); `MODEL_REGISTRY`
        lists the options each one uses.
      min_roughness: perceptual-roughness floor (static). See module docstring.
      smith: gltf only — "correlated" (glTF spec, default) or "separable" visibility (both the
        Smith-GGX G2; not the LUT's "schlick_ggx").
      diffuse: gltf only — "lambert" (glTF spec, default) or "burley".
      shader_epsilon: learnopengl only — the shader's `+ 0.0001` in `4 NoV NoL + 0.0001`, kept so the
        model reproduces the tutorial's images; 0.0 gives the un-fudged UE4 model. Either way the
        value is computed division-free and stays finite at NoV, NoL -> 0.

    An option the chosen model does not use (e.g. `smith="separable"` with `model="learnopengl"`)
    raises ValueError; passing it with its default value is allowed (see `check_options`).

    Returns 0 where NoV <= 0 or NoL <= 0 (the light or the viewer is below the surface).

    The core model only: a Material with glTF extension fields raises ValueError; `jaxpbr.brdf`
    (`jaxpbr.shading.layered.brdf`) shades both.
    """
    check_options(model, min_roughness=min_roughness, smith=smith, diffuse=diffuse, shader_epsilon=shader_epsilon)
    # Named shape checks (always) and finiteness (concrete values): a NaN direction gave 0.
    n, v, l = (check_values(name, vector(name, x)) for name, x in (("n", n), ("v", v), ("l", l)))
    batch_shape("brdf", ("n", n, 1), ("v", v, 1), ("l", l, 1), material=m)
    if m.layered:
        raise ValueError(
            f"brdf_terms.brdf shades the core model; this material has the glTF extensions {m.extensions}: "
            "call jaxpbr.brdf (jaxpbr.shading.layered.brdf), which shades both."
        )
    return _brdf_program(n, v, l, m, model=model, min_roughness=min_roughness, smith=smith, diffuse=diffuse,
                         shader_epsilon=shader_epsilon)


@functools.partial(jax.jit, static_argnames=("model", "min_roughness", "smith", "diffuse", "shader_epsilon"))
def _brdf_program(n, v, l, m: Material, *, model, min_roughness, smith, diffuse, shader_epsilon) -> jax.Array:
    """`brdf` after its checks, as one compiled program: called outside a trace it is one dispatch
    (the operations one by one were each a program of their own, compiled at a first call); inside
    one it is inlined."""
    g = geometry(n, v, l)
    f = brdf_soa(
        g,
        unpack3(m.base_color),
        m.metallic,
        m.roughness,
        model=model,
        min_roughness=min_roughness,
        smith=smith,
        diffuse=diffuse,
        shader_epsilon=shader_epsilon,
    )
    return pack3(f)
