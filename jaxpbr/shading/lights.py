"""Punctual lights (KHR_lights_punctual) and the direct-lighting sum.

Units follow KHR_lights_punctual: point and spot `intensity` in candela (lm/sr), directional in lux
(lm/m^2); `color` is a linear RGB filter. A light at distance d delivers irradiance
`E_perp = color * intensity * window(d) / d^2` on a plane facing it (directional: `color *
intensity`), and the reflected radiance is `f_r(v, l) * E_perp * max(n.l, 0)`.

Any mix of lights is packed into one `LightSet`: a struct of arrays with a leading light axis, in
which a point light is a spot light with no cone and a directional light a flag. `shade_direct`
then evaluates all lights in one traced program: a static, unrolled sum for a few lights (XLA fuses
it into a single pass over the pixels) and a `lax.scan` over lights beyond `UNROLL_MAX_LIGHTS`, so
the program size does not grow with the number of lights.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._numerics import (
    Vec3,
    as_float,
    computed_once,
    cpu_cond,
    is_concrete,
    orthonormal_frame,
    pack3,
    safe_div,
    safe_sqrt,
    saturate,
    unpack3,
    vdot,
    vnormalize,
)
from .._pytree import Pytree, fields_of, leaf
from .._validate import batch_shape, check_values, vector
from .brdf_terms import (
    MIN_ROUGHNESS,
    brdf_soa,
    check_options,
    floored_roughness,
    geometry_soa,
)
from .layered import (
    anisotropic_alphas,
    anisotropy_frame,
    emission_soa,
    layer_setup,
    layered_soa,
)
from .material import Material

__all__ = [
    "DirectionalLight",
    "LightSet",
    "PointLight",
    "SpotLight",
    "UNROLL_MAX_LIGHTS",
    "MIN_LIGHT_DISTANCE",
    "MAX_ANGULAR_RADIUS",
    "cap_factor",
    "cap_irradiance",
    "pack_lights",
    "shade_direct",
]

#: Up to this many lights the sum over lights is unrolled at trace time (fused by XLA);
#: beyond it a `lax.scan` keeps the traced program constant-size.
UNROLL_MAX_LIGHTS = 8

#: Largest angular radius of a disc light (rad): just under a hemisphere (89 degrees).
MAX_ANGULAR_RADIUS = math.radians(89.0)

#: Distances to point/spot lights below this (scene units) are clamped in the inverse square law,
#: so a light sitting on the surface gives a huge but finite irradiance.
MIN_LIGHT_DISTANCE = 1e-4

# KHR_lights_punctual: lightAngleScale = 1 / max(0.001, cos(inner) - cos(outer)).
_MIN_CONE_COS_DELTA = 1e-3


def _range_arg(range_) -> jax.Array:
    """KHR `range` (> 0): None or inf mean unlimited; stored as 1/range (0 = unlimited)."""
    if range_ is None:
        return as_float(0.0)
    rng = as_float(range_)
    if is_concrete(rng):
        a = np.asarray(rng)
        if np.any(np.isnan(a)) or np.any(a <= 0):
            raise ValueError(
                f"light range must be > 0 (KHR_lights_punctual), or None/inf for unlimited; got {a.min():g}."
            )
    return 1.0 / rng  # 1/inf = 0: unlimited


class PointLight(Pytree):
    """Point light. position (..., 3) [scene units]; color (..., 3) linear RGB; intensity (...) [cd];
    range (...) or None: KHR smooth window `clamp(1 - (d/range)^4, 0, 1)^2` (None = unlimited),
    stored as `inv_range` = 1/range (0 = unlimited)."""

    position: Any = leaf(rank=1)
    color: Any = leaf((1.0, 1.0, 1.0), rank=1)
    intensity: Any = leaf(1.0)
    inv_range: Any = leaf(0.0)

    def __init__(self, position, color=(1.0, 1.0, 1.0), intensity=1.0, range=None):
        self._set(position=position, color=color, intensity=intensity, inv_range=_range_arg(range))
        self._validate()

    def _validate(self) -> None:
        self._set(
            position=vector("PointLight.position", self.position),
            color=vector("PointLight.color", self.color),
            intensity=as_float(self.intensity),
            inv_range=as_float(self.inv_range),
        )
        check_values("PointLight.position", self.position)
        check_values("PointLight.color", self.color, lo=0.0)
        check_values("PointLight.intensity", self.intensity, lo=0.0)
        check_values("PointLight.inv_range", self.inv_range, lo=0.0, finite=False)


class DirectionalLight(Pytree):
    """Directional light (sun). direction (..., 3): the direction the light *travels* (KHR: the
    node's -Z), so the unit vector towards the light is `-direction`; color (..., 3);
    intensity (...) [lux]: the irradiance on a plane facing the light.

    angular_radius (...) [rad], in [0, pi/2): 0 (default, KHR_lights_punctual) is a punctual
    light; > 0 makes it a uniform disc of that angular radius around -direction (the sun is
    ~0.0047 rad), of radiance `color * intensity / (pi sin^2(angular_radius))`, so the same
    intensity gives the same irradiance on a facing plane. `shade_direct` shades a disc with its
    exact diffuse irradiance (`cap_irradiance`, also where the disc is partly below the horizon)
    and its specular by a representative point with energy normalisation (see `shade_direct`).
    """

    direction: Any = leaf(rank=1)
    color: Any = leaf((1.0, 1.0, 1.0), rank=1)
    intensity: Any = leaf(1.0)
    angular_radius: Any = leaf(0.0)

    def _validate(self) -> None:
        self._set(
            direction=vector("DirectionalLight.direction", self.direction),
            color=vector("DirectionalLight.color", self.color),
            intensity=as_float(self.intensity),
            angular_radius=as_float(self.angular_radius),
        )
        check_values("DirectionalLight.angular_radius", self.angular_radius, lo=0.0, hi=MAX_ANGULAR_RADIUS)
        check_values("DirectionalLight.direction", self.direction)
        if is_concrete(self.direction) and np.any(np.linalg.norm(np.asarray(self.direction), axis=-1) == 0):
            raise ValueError("DirectionalLight.direction must be a non-zero vector.")
        check_values("DirectionalLight.color", self.color, lo=0.0)
        check_values("DirectionalLight.intensity", self.intensity, lo=0.0)


class SpotLight(Pytree):
    """Spot light (KHR_lights_punctual). position, direction (the cone axis, pointing away from the
    light), color (..., 3); intensity (...) [cd]; inner/outer cone angles in radians with
    0 <= inner < outer <= pi/2 (KHR defaults 0 and pi/4); optional range as for `PointLight`
    (stored as `inv_range`).

    Angular falloff (KHR): `t = saturate(cos(angle) * s + o)`, `s = 1/max(1e-3, cos(inner) -
    cos(outer))`, `o = -cos(outer) * s`, attenuation `t^2`.
    """

    position: Any = leaf(rank=1)
    direction: Any = leaf(rank=1)
    color: Any = leaf((1.0, 1.0, 1.0), rank=1)
    intensity: Any = leaf(1.0)
    inner_cone_angle: Any = leaf(0.0)
    outer_cone_angle: Any = leaf(math.pi / 4)
    inv_range: Any = leaf(0.0)

    def __init__(
        self,
        position,
        direction,
        color=(1.0, 1.0, 1.0),
        intensity=1.0,
        inner_cone_angle=0.0,
        outer_cone_angle=math.pi / 4,
        range=None,
    ):
        self._set(
            position=position,
            direction=direction,
            color=color,
            intensity=intensity,
            inner_cone_angle=inner_cone_angle,
            outer_cone_angle=outer_cone_angle,
            inv_range=_range_arg(range),
        )
        self._validate()

    def _validate(self) -> None:
        self._set(
            position=vector("SpotLight.position", self.position),
            direction=vector("SpotLight.direction", self.direction),
            color=vector("SpotLight.color", self.color),
            intensity=as_float(self.intensity),
            inner_cone_angle=as_float(self.inner_cone_angle),
            outer_cone_angle=as_float(self.outer_cone_angle),
            inv_range=as_float(self.inv_range),
        )
        check_values("SpotLight.position", self.position)
        check_values("SpotLight.color", self.color, lo=0.0)
        check_values("SpotLight.intensity", self.intensity, lo=0.0)
        check_values("SpotLight.inner_cone_angle", self.inner_cone_angle, lo=0.0)
        check_values("SpotLight.outer_cone_angle", self.outer_cone_angle, lo=0.0, hi=math.pi / 2 + 1e-12)
        check_values("SpotLight.inv_range", self.inv_range, lo=0.0, finite=False)
        if is_concrete(self.inner_cone_angle) and is_concrete(self.outer_cone_angle):
            if np.any(np.asarray(self.inner_cone_angle) >= np.asarray(self.outer_cone_angle)):
                raise ValueError(
                    "SpotLight.inner_cone_angle must be smaller than outer_cone_angle "
                    "(KHR_lights_punctual); both are in radians."
                )


class LightSet(Pytree):
    """Any mix of punctual lights as a struct of arrays with one leading light axis (N, ...).

    position (N, 3); direction (N, 3) (travel direction; used by directional and spot lights);
    radiant (N, 3) = color * intensity; inv_range (N,); cone_scale, cone_offset (N,) (a point
    light has scale 0, offset 1); directional (N,) bool; sin_radius (N,): sin of a directional
    light's angular radius (0: punctual; always 0 for point and spot lights). Built by
    `pack_lights`, taken as given (no validation). The light axis N is a batch axis: the declared
    ranks count the core axes.
    """

    position: Any = leaf(rank=1)
    direction: Any = leaf(rank=1)
    radiant: Any = leaf(rank=1)
    inv_range: Any = leaf()
    cone_scale: Any = leaf()
    cone_offset: Any = leaf()
    directional: Any = leaf()
    sin_radius: Any = leaf(0.0)

    @property
    def num_lights(self) -> int:
        return self.radiant.shape[0]


def _pack_one(light) -> LightSet:
    """One light object (leaves possibly batched) -> LightSet with a flat leading light axis."""
    if isinstance(light, LightSet):
        return light
    if not isinstance(light, (PointLight, DirectionalLight, SpotLight)):
        raise TypeError(
            f"expected PointLight, DirectionalLight, SpotLight or LightSet, got {type(light).__name__}."
        )
    radiant = light.color * light.intensity[..., None]
    # The light's batch axes: those of all its leaves broadcast (a batch of directions with one
    # shared colour is a batch of lights).
    batch = jnp.broadcast_shapes(*(jnp.shape(x)[: jnp.ndim(x) - f.rank] for f in fields_of(light) for x in [getattr(light, f.name)]))
    radiant = jnp.broadcast_to(radiant, batch + (3,))
    dtype = radiant.dtype
    zero3, zero, one = jnp.zeros(3, dtype), jnp.zeros((), dtype), jnp.ones((), dtype)
    fields = dict(radiant=radiant, cone_scale=zero, cone_offset=one, sin_radius=zero)  # no cone: point/directional
    if isinstance(light, DirectionalLight):
        fields.update(position=zero3, direction=light.direction, inv_range=zero, directional=True)
        fields["sin_radius"] = jnp.sin(light.angular_radius).astype(dtype)
    else:
        fields.update(position=light.position, inv_range=light.inv_range, directional=False)
        fields["direction"] = light.direction if isinstance(light, SpotLight) else zero3
    if isinstance(light, SpotLight):
        cos_outer = jnp.cos(light.outer_cone_angle)
        scale = 1.0 / jnp.maximum(_MIN_CONE_COS_DELTA, jnp.cos(light.inner_cone_angle) - cos_outer)
        fields.update(cone_scale=scale, cone_offset=-cos_outer * scale)
    out = {}
    for f in fields_of(LightSet):
        x = jnp.asarray(fields[f.name])
        tail = (3,) * f.rank  # xyz / RGB
        out[f.name] = jnp.broadcast_to(x, batch + tail).reshape((-1,) + tail)
    return LightSet(**out)


def pack_lights(lights: Any) -> LightSet:
    """Pack one light, a (possibly batched) light object, a LightSet, or a list of them into a
    single `LightSet` with a flat leading light axis. Works inside jit (shapes are static)."""
    if isinstance(lights, (PointLight, DirectionalLight, SpotLight, LightSet)):
        return _pack_one(lights)
    if not isinstance(lights, (list, tuple)):
        raise TypeError(
            f"lights must be a light, a LightSet or a list of lights, got {type(lights).__name__}."
        )
    if len(lights) == 0:
        raise ValueError("lights is empty; pass at least one light (or skip direct lighting).")
    sets = [_pack_one(x) for x in lights]
    dtype = jnp.result_type(*[s.radiant for s in sets])
    return LightSet(
        **{
            f.name: jnp.concatenate(
                [getattr(s, f.name).astype(bool if f.name == "directional" else dtype) for s in sets], axis=0
            )
            for f in fields_of(LightSet)
        }
    )


def light_incidence_soa(light: LightSet, p: Vec3) -> tuple[Vec3, Vec3]:
    """For ONE light (fields without the leading axis) and points `p` (Vec3): the unit direction
    towards the light `l` and the per-channel perpendicular irradiance `E_perp` (both Vec3)."""
    to_light = tuple(light.position[i] - p[i] for i in range(3))
    d2 = vdot(to_light, to_light)
    l_local = vnormalize(to_light)
    d2_safe = jnp.maximum(d2, MIN_LIGHT_DISTANCE**2)
    # KHR range window clamp(1 - (d/range)^4, 0, 1)^2; inv_range = 0 means unlimited.
    x = d2 * light.inv_range**2
    window = saturate(1.0 - x * x) ** 2
    # Spot cone: cos of the angle between the cone axis and the direction light -> point.
    axis = vnormalize(unpack3(light.direction))
    cd = -vdot(axis, l_local)
    cone = saturate(cd * light.cone_scale + light.cone_offset) ** 2
    atten = jnp.where(light.directional, 1.0, window * cone / d2_safe)
    l = tuple(jnp.where(light.directional, -axis[i], l_local[i]) for i in range(3))
    e = tuple(light.radiant[i] * atten for i in range(3))
    return l, e


def light_incidence(light: LightSet, p: jax.Array) -> tuple[jax.Array, jax.Array]:
    """For ONE light (fields without the leading axis) and points p (..., 3): the unit direction
    towards the light `l` (..., 3) and the perpendicular irradiance `E_perp` (..., 3)."""
    l, e = light_incidence_soa(light, unpack3(p))
    return pack3(l), pack3(e)


def shade_direct(
    p: jax.Array,
    n: jax.Array,
    v: jax.Array,
    m: Material,
    lights: Any,
    *,
    model: str = "gltf",
    ambient: Any = 0.0,
    min_roughness: float = MIN_ROUGHNESS,
    disc_lights: bool | None = None,
    tangent=None,
    coat_normal=None,
    volume_distance=None,
    sheen_lut=None,
    visibility=None,
    **brdf_options,
) -> jax.Array:
    """Outgoing radiance from punctual and disc lights: `sum_i f_r(v, l_i) E_i max(n.l_i, 0)
    + ambient * base_color * occlusion + emissive`, shape (..., 3).

    A directional light with an angular radius sigma > 0 is a uniform disc (a sun). Both lobes
    are evaluated at the disc centre (lifted just above the horizon where the disc straddles it)
    and multiplied by the exact cosine-weighted solid angle of the cap, `E_perp
    cap_irradiance(n.l, sin sigma) / (pi sin^2 sigma)`: the diffuse lobe is then exact for a
    Lambertian. In the specular lobe, D is replaced by its mean over the disc (`disc_lobe_ratio`:
    the GGX slope distribution's mass over the disc's elliptical image in slope space). That gives
    D itself at sigma = 0 and the mirror image of the disc, F E_perp / (pi sin^2 sigma), as
    r -> 0; V and F are taken at the centre. Its error against quadrature over the disc, per
    roughness and radius, is in docs/ibl.md (`examples/disc_light_error.py`).
    sigma = 0 reduces to the punctual light.

    Args:
      p: (..., 3) surface positions; n: (..., 3) normals; v: (..., 3) directions to the viewer.
      m: `Material` broadcasting with the pixel axes.
      lights: a light, a list of mixed lights, or a `LightSet` (see `pack_lights`).
      model: "gltf" | "learnopengl" (see `brdf`).
      ambient: constant ambient radiance (scalar or (3,)), applied as LearnOpenGL's
        `ambient * albedo * ao` (not physically based; use IBL for that). Default 0.
      disc_lights: which lights take the disc-light code (static): None (default) the
        DirectionalLights (and a packed LightSet) whose angular radius is traced or > 0; True
        every DirectionalLight / LightSet; False none (all punctual). Point and spot lights are
        always punctual.
      min_roughness, **brdf_options: passed to `brdf` (smith, diffuse, shader_epsilon). An option
        the model does not use (`brdf_terms.MODEL_REGISTRY`) raises ValueError unless it has its
        default value.
      tangent, coat_normal, volume_distance, sheen_lut: what the glTF material extensions need
        (`jaxpbr.shading.layered`): (..., 3) surface tangent (anisotropy), (..., 3) clear-coat normal
        (default n), (...) path length in the medium (volume; default the thickness), the sheen
        albedo table (default the shipped 128^2 one, `jaxpbr.shading.sheen_lut()`). A Material with
        extensions is shaded by the layered BSDF (model "gltf" only); one without by the core
        model, bit for bit as before.
      visibility: optional (..., L) factors in [0, 1], one per light in the order of `lights`
        (a LightSet's lights in its order): the fraction of each light that reaches the point
        (shadows; `jaxpbr.render` computes it with shadow rays), or (..., L, 3) per colour channel
        (light tinted by transmissive occluders) with every batch axis of p, n, v present. Default:
        every light visible.
    """
    unknown = set(brdf_options) - {"smith", "diffuse", "shader_epsilon"}
    if unknown:
        raise TypeError(f"shade_direct got unknown option(s) {sorted(unknown)}.")
    check_options(model, min_roughness=min_roughness, **brdf_options)
    # Lights shaded as discs (static): DirectionalLights whose angular radius may be > 0 (traced,
    # or concrete and > 0); every other light takes the punctual path, so a scene of punctual
    # lights compiles no disc code even when its lights are traced. A packed LightSet is one group.
    if isinstance(lights, LightSet) or isinstance(lights, (PointLight, SpotLight, DirectionalLight)):
        items = [lights]
    elif isinstance(lights, (list, tuple)):
        items = list(lights)
    else:
        items = [lights]
    if not items:
        raise ValueError("lights is empty; pass at least one light (or skip direct lighting).")

    def may_be_disc(x):
        r = x.sin_radius if isinstance(x, LightSet) else getattr(x, "angular_radius", None)
        if r is None:
            return False
        return not is_concrete(r) or bool(np.any(np.asarray(r) > 0))

    if disc_lights is None:
        disc_items = [x for x in items if may_be_disc(x)]
    elif disc_lights:
        disc_items = [x for x in items if isinstance(x, (DirectionalLight, LightSet))]
    else:
        disc_items = []
    point_items = [x for x in items if not any(x is y for y in disc_items)]
    groups = [(pack_lights(g), disc) for g, disc in ((point_items, False), (disc_items, True)) if g]
    group_vis = [None] * len(groups)
    if visibility is not None:
        # Each group's columns of `visibility` (input order -> the group's packed order).
        sizes = [_pack_one(x).num_lights for x in items]
        offs = np.cumsum([0] + sizes)
        cols = {id(x): np.arange(offs[k], offs[k + 1]) for k, x in enumerate(items)}
        vis = jnp.asarray(visibility)
        batch_ndim = max(jnp.ndim(x) for x in (p, n, v)) - 1
        rgb = vis.ndim == batch_ndim + 2 and vis.shape[-1] == 3  # (..., L, 3): per channel
        lights_axis = -2 if rgb else -1
        if vis.shape[lights_axis] != offs[-1]:
            raise ValueError(f"visibility has {vis.shape[lights_axis]} columns for {offs[-1]} lights")
        # Static slices, not a gather: a gather fused into the shading loop kept XLA:CPU from
        # vectorising it (1280x720, 4 lights: 104 ms against 15 ms without visibility).
        axis = vis.ndim + lights_axis
        group_vis = [
            jnp.stack([jax.lax.index_in_dim(vis, int(j), axis, keepdims=False) for x in g for j in cols[id(x)]], axis)
            for g in (point_items, disc_items) if g
        ]
    batch_shape("shade_direct", ("p", p, 1), ("n", n, 1), ("v", v, 1), material=m)
    p3 = unpack3(p)
    n3 = vnormalize(unpack3(n))
    v3 = vnormalize(unpack3(v))
    base = unpack3(m.base_color)

    if disc_items:
        alpha2 = floored_roughness(m.roughness, min_roughness) ** 4
    lobe = lambda g, **w: brdf_soa(g, base, m.metallic, m.roughness, model=model, min_roughness=min_roughness, **brdf_options, **w)  # noqa: E731
    layers = layer_setup(m, model, tangent, coat_normal, volume_distance, sheen_lut)
    if layers is not None:
        extra, sheen_lut = layers
        opts = {k: brdf_options[k] for k in ("smith", "diffuse") if k in brdf_options}
        layered = lambda l3, **w: layered_soa(n3, v3, l3, m, min_roughness=min_roughness, sheen_lut=sheen_lut, extra=extra, **opts, **w)  # noqa: E731
        transmits = "transmission" in m.extensions
        # With these groups each point light's layered BSDF is computed once, as arrays of its own:
        # inlined, every light's is fused into the one loop that stacks the colour channels and
        # evaluated there per channel (`jaxpbr bench render --extensions`, 1280x720, the core
        # material's frame = 1: KHR_materials_specular 3.6x inlined, 1.3x computed once; sheen 4.5x
        # against 2.7x). The lighter groups (clearcoat, transmission, volume, ior) run faster inlined
        # (clearcoat 1.53x against 1.69x, transmission 1.28x against 1.55x computed once).
        once = bool({"sheen", "specular", "anisotropy"} & set(m.extensions))
        aniso = None
        if disc_items and "anisotropy" in m.extensions and extra.tangent is not None:
            # The disc's lobe ratio over the stretched slope distribution (`disc_lobe_ratio`).
            mc = m.complete(("anisotropy",))
            T, B = anisotropy_frame(n3, vnormalize(extra.tangent), mc.anisotropy_rotation)
            at, ab = anisotropic_alphas(floored_roughness(m.roughness, min_roughness) ** 2,
                                        jnp.clip(mc.anisotropy_strength, 0.0, 1.0))
            aniso = (T, B, at, ab)

    def one(light: LightSet, disc_lights: bool) -> Vec3:
        l3, e = light_incidence_soa(light, p3)
        if layers is not None:
            if not disc_lights:
                if once:
                    fc = computed_once(lambda o: layered(o), l3, jnp.ravel(light.radiant)[0])
                else:
                    fc = layered(l3)
                return tuple(fc[i] * e[i] for i in range(3))
            s = light.sin_radius
            c = vdot(n3, l3)
            # The part of the disc above the horizon: reflection at the centre lifted just above
            # it (as the core path), times the cap's cosine-weighted solid angle above.
            lift = jnp.maximum(s - c, 0.0)
            lc = vnormalize(tuple(l3[i] + lift * n3[i] for i in range(3)))
            ratio = disc_lobe_ratio(n3, v3, lc, s, alpha2, aniso=aniso)
            w = {}
            if "clearcoat" in m.extensions:  # the coat's own lobe ratio, about its normal
                nc3 = n3 if extra.coat_normal is None else vnormalize(extra.coat_normal)
                ac2 = floored_roughness(m.complete(("clearcoat",)).clearcoat_roughness, min_roughness) ** 4
                w["coat_weight"] = disc_lobe_ratio(nc3, v3, lc, s, ac2)
            fc = layered(lc, specular_weight=ratio, **w)
            # f cos at the lifted centre -> f times the cap's cosine-weighted solid angle.
            cl = vdot(n3, lc)
            k = jnp.where(cl > 0, cap_factor(c, s) / jnp.where(cl > 0, cl, 1.0), 0.0)
            out = tuple(fc[i] * e[i] * k for i in range(3))
            if transmits:
                # The part below the horizon: transmission at the centre lowered just below it,
                # times the cap's |cos|-weighted solid angle below (the mirror image of the part
                # above). A disc straddling the horizon gets both; transmission 0 adds exactly 0.
                drop = jnp.maximum(s + c, 0.0)
                ld = vnormalize(tuple(l3[i] - drop * n3[i] for i in range(3)))
                cd = -vdot(n3, ld)
                kd = jnp.where(cd > 0, cap_factor(-c, s) / jnp.where(cd > 0, cd, 1.0), 0.0)
                ft = layered(ld, **({"coat_weight": 0.0} if "clearcoat" in m.extensions else {}))  # the coat: above only
                out = tuple(out[i] + ft[i] * e[i] * kd for i in range(3))
            return out
        if not disc_lights:
            g = geometry_soa(n3, v3, l3)
            f = lobe(g)
            # g.n_dot_l is the clamped cosine on front lanes; f is 0 elsewhere.
            return tuple(f[i] * e[i] * g.n_dot_l for i in range(3))
        s = light.sin_radius
        # Both lobes at the disc centre, lifted just above the horizon where the disc straddles
        # it, times the exact cosine-weighted solid angle of the cap (cap_factor = n.l off the
        # horizon) ...
        c = vdot(n3, l3)
        lift = jnp.maximum(s - c, 0.0)
        lc = vnormalize(tuple(l3[i] + lift * n3[i] for i in range(3)))
        g = geometry_soa(n3, v3, lc)
        # ... with D replaced by its mean over the disc (`disc_lobe_ratio`).
        ratio = disc_lobe_ratio(n3, v3, lc, s, alpha2)
        f = lobe(g, specular_weight=ratio)
        cap = cap_factor(c, s)
        return tuple(f[i] * e[i] * cap for i in range(3))

    def add(a: Vec3, b: Vec3) -> Vec3:
        return tuple(x + y for x, y in zip(a, b))

    def seen(c: Vec3, w) -> Vec3:
        if w is None:
            return c
        if rgb:  # w (..., 3): one factor per channel
            return tuple(c[k] * w[..., k] for k in range(3))
        return tuple(x * w for x in c)

    rgb = visibility is not None and lights_axis == -2
    out = None
    for (ls, disc), gv in zip(groups, group_vis):
        take = lambda i, ls=ls: jax.tree_util.tree_map(lambda x: x[i], ls)  # noqa: E731
        col = lambda i, gv=gv: None if gv is None else (gv[..., i, :] if rgb else gv[..., i])  # noqa: E731
        num = ls.num_lights
        acc = seen(one(take(0), disc), col(0))
        if num <= UNROLL_MAX_LIGHTS:
            for i in range(1, num):
                acc = add(acc, seen(one(take(i), disc), col(i)))
        else:
            shape = jnp.broadcast_shapes(*(jnp.shape(c) for c in acc))
            acc = tuple(jnp.broadcast_to(c, shape) for c in acc)
            rest = jax.tree_util.tree_map(lambda x: x[1:], ls)
            if gv is None:
                acc, _ = jax.lax.scan(lambda a, light, disc=disc: (add(a, one(light, disc)), None), acc, rest)
            else:
                vrest = jnp.moveaxis(gv[..., 1:, :], -2, 0) if rgb else jnp.moveaxis(gv[..., 1:], -1, 0)
                acc, _ = jax.lax.scan(
                    lambda a, xs, disc=disc: (add(a, seen(one(xs[0], disc), xs[1])), None), acc, (rest, vrest)
                )
        out = acc if out is None else add(out, acc)

    if not (isinstance(ambient, (int, float)) and ambient == 0):  # static zero: no ambient code
        amb = as_float(ambient)
        amb3 = unpack3(jnp.broadcast_to(amb, amb.shape[:-1] + (3,)) if amb.ndim else jnp.broadcast_to(amb, (3,)))
        out = tuple(out[i] + amb3[i] * base[i] * m.occlusion for i in range(3))
    if layers is None:
        emissive = unpack3(m.emission())
    else:
        emissive = unpack3(emission_soa(m, n3, v3, layers[0].coat_normal))
    return pack3(tuple(out[i] + emissive[i] for i in range(3)))



#: Quadrature points of `disc_lobe_ratio` (directions from the slope-space origin).
DISC_LOBE_POINTS = 16


def disc_lobe_ratio(n: Vec3, v: Vec3, l: Vec3, sin_sigma, alpha2, aniso=None) -> jax.Array:
    """`_disc_lobe_ratio` (below) of the `Geometry` of (n, v, l) where the disc has a radius, else 1
    (its value at sigma = 0).

    On the CPU the quadrature runs as a branch of a conditional on sigma > 0 (`cpu_cond`): XLA:CPU
    then keeps its result as an array of its own, where inlined it was fused into every consumer and recomputed there (once
    per colour channel): a sun's `shade_direct` at 1280x720 measured 155 ms against 216 ms."""
    s = jnp.asarray(sin_sigma)
    shape = jnp.broadcast_shapes(*(jnp.shape(x) for x in jax.tree_util.tree_leaves((n, v, l, s, alpha2))))
    dtype = jnp.result_type(*jax.tree_util.tree_leaves((n, v, l, alpha2)))
    # The geometry is made inside the branch from (n, v, l): a conditional's operands are arrays of
    # their own, and the geometry's six would be six more (the sun stage: 0.97 against 1.03-1.15 s
    # to compile, 118 against 130 ms to run at 1280x720).
    return cpu_cond(
        jnp.any(s > 0),
        lambda o: jnp.broadcast_to(_disc_lobe_ratio(*o[:5], geometry_soa(*o[:3]), aniso=o[5]), shape).astype(dtype),
        lambda o: jnp.ones(shape, dtype),
        (n, v, l, s, alpha2, aniso),
    )


def _disc_lobe_ratio(n: Vec3, v: Vec3, l: Vec3, sin_sigma, alpha2, g, aniso=None) -> jax.Array:
    """Mean of the GGX D over a disc of directions (centre l, angular radius sigma), divided by D
    at the centre's half vector: the factor `shade_direct` puts on the specular lobe of a disc
    light. g: `Geometry` of (n, v, l); alpha2 = alpha^2 (floored, > 0).

    Method. Over the disc, integral D dl = 4 (v.h) / (n.h) * P, with P the probability mass of
    GGX's slope distribution over the disc's image in slope space. To first order in sigma that
    image is an ellipse: the disc's tangent circle mapped by the Jacobian of
    l -> h = normalize(v + l) -> slope (h_t / h_n), which stretches it by 1/(2 v.h) across the
    plane of v and l and by 1/cos^2 theta_h (radially) and 1/cos theta_h (tangentially) around n.
    In slope units of alpha, the density is 1/(pi (1 + |u|^2)^2), whose mass inside radius R from
    the origin along a ray is R^2 / (2 pi (1 + R^2)) per radian; P is that integrated over the
    rays from the origin that cross the ellipse, in closed form along each ray (entry and exit
    radii from a quadratic) and by a DISC_LOBE_POINTS-point rule over the rays' angle (uniform
    when the origin is inside the ellipse; when outside, over the ellipse's angular extent with a
    sine substitution that absorbs the square-root ends). sigma -> 0 gives 1 (D itself);
    alpha -> 0 gives the disc's mirror image. Finite values and gradients (double where).

    aniso: (T, B, alpha_t, alpha_b) for an anisotropic lobe (KHR_materials_anisotropy): the slope
    axes are T and B, scaled by alpha_t and alpha_b (the anisotropic slope distribution is the
    isotropic one stretched along them), and D at the centre is the anisotropic D.
    """
    # Double where: lanes the BRDF masks (viewer or light below the surface, v = -l) get the
    # benign v = l = n, whose huge or 0/0 Jacobian would otherwise reach the value and gradient.
    front = g.front
    v = tuple(jnp.where(front, v[i], n[i]) for i in range(3))
    l = tuple(jnp.where(front, l[i], n[i]) for i in range(3))
    s = sin_sigma
    h = vnormalize(tuple(v[i] + l[i] for i in range(3)))
    t1, t2 = orthonormal_frame(n) if aniso is None else aniso[:2]
    e1, e2 = orthonormal_frame(l)
    hn = jnp.maximum(vdot(n, h), 1e-6)
    vh = jnp.maximum(vdot(v, h), 1e-6)
    alpha = jnp.sqrt(alpha2)
    ht1, ht2 = vdot(t1, h), vdot(t2, h)

    def slope_step(e):  # d(slope)/dl along e, in units of alpha, times sin sigma
        he = vdot(h, e)
        dh = tuple((e[i] - h[i] * he) / (2.0 * vh) for i in range(3))
        dn = vdot(n, dh)
        if aniso is None:
            k = s / (alpha * hn * hn)
            return ((vdot(t1, dh) * hn - ht1 * dn) * k, (vdot(t2, dh) * hn - ht2 * dn) * k)
        k = s / (hn * hn)
        return ((vdot(t1, dh) * hn - ht1 * dn) * k / aniso[2], (vdot(t2, dh) * hn - ht2 * dn) * k / aniso[3])

    (a11, a21), (a12, a22) = slope_step(e1), slope_step(e2)
    if aniso is None:
        c1, c2 = ht1 / (hn * alpha), ht2 / (hn * alpha)
    else:
        c1, c2 = ht1 / (hn * aniso[2]), ht2 / (hn * aniso[3])
    det = a11 * a22 - a12 * a21
    ok = (jnp.abs(det) > 1e-30) & (s > 0) & front
    det_s = jnp.where(ok, det, 1.0)
    # centre in the ellipse's unit-circle coordinates: c_B = A^-1 c
    b1 = (a22 * c1 - a12 * c2) / det_s
    b2 = (-a21 * c1 + a11 * c2) / det_s
    d2 = b1 * b1 + b2 * b2
    d = safe_sqrt(d2)
    inside = d2 < 1.0
    dn_ = jnp.where(d > 0, d, 1.0)
    u1, u2 = jnp.where(d > 0, b1 / dn_, 1.0), jnp.where(d > 0, b2 / dn_, 0.0)
    half = jnp.arcsin(jnp.clip(1.0 / jnp.where(inside, 2.0, dn_), 0.0, 1.0 - 1e-7))
    # The rule's points one after another in a loop (one compiled body, not K unrolled copies),
    # summed in a fixed order whatever the image's shape (a render in bands equals the whole image).
    # Measured against the points along a trailing axis summed in order: a sun's shading at
    # 1280x720 0.73x the run time (111 against 152 ms), the IBL stage holding it 0.87x; the same
    # compile time.
    K = DISC_LOBE_POINTS
    dt = jnp.result_type(d)

    def point(j, total):
        x = (j.astype(dt) + 0.5) / K
        theta = (x - 0.5) * jnp.pi
        phi = jnp.where(inside, 2.0 * jnp.pi * x, half * jnp.sin(theta))
        w_phi = jnp.where(inside, 2.0 * jnp.pi / K, half * jnp.cos(theta) * (jnp.pi / K))
        cp, sp = jnp.cos(phi), jnp.sin(phi)
        y1, y2 = cp * u1 - sp * u2, sp * u1 + cp * u2  # the ray's direction: c_B's rotated by phi
        p = d * cp
        sq = safe_sqrt(1.0 - d * d * sp * sp)
        t_out = p + sq
        t_in = jnp.where(inside, 0.0, jnp.maximum(p - sq, 0.0))
        w2 = (a11 * y1 + a12 * y2) ** 2 + (a21 * y1 + a22 * y2) ** 2  # |A y|^2
        dt2 = jnp.where(inside, t_out * t_out, 4.0 * p * sq)  # t_out^2 - t_in^2
        return total + w_phi * dt2 / ((1.0 + t_out * t_out * w2) * (1.0 + t_in * t_in * w2))

    shape = jnp.broadcast_shapes(*(jnp.shape(a) for a in (d, half, u1, u2, a11, a12, a21, a22)))
    total = jax.lax.fori_loop(0, K, point, jnp.zeros(shape, dt))
    mass = jnp.abs(det_s) * total / (2.0 * jnp.pi)
    s2 = jnp.where(ok, s * s, 1.0)
    if aniso is None:
        d0 = g.sin2_h + g.n_dot_h * g.n_dot_h * alpha2
        ratio = 4.0 * vh * mass * d0 * d0 / (hn * s2 * alpha2)
    else:
        from .layered import d_ggx_anisotropic

        dc = d_ggx_anisotropic(hn, ht1, ht2, aniso[2], aniso[3])
        ratio = 4.0 * vh * mass / (hn * s2 * jnp.pi * jnp.where(ok, dc, 1.0))
    return jnp.where(ok, ratio, 1.0)


def cap_factor(cos_theta, sin_sigma) -> jax.Array:
    """`cap_irradiance(cos_theta, sin_sigma) / (pi sin^2 sigma)`: a disc light's irradiance per
    unit perpendicular irradiance; exactly max(cos_theta, 0) wherever the disc is wholly above or
    below the horizon, and so for sigma -> 0 (a punctual light)."""
    c, s, straddle, part = _cap_parts(cos_theta, sin_sigma)
    s2 = jnp.where(straddle, s * s, 1.0)
    return jnp.where(straddle, jnp.maximum(part, 0.0) / (jnp.pi * s2), jnp.maximum(c, 0.0))


def cap_irradiance(cos_theta, sin_sigma) -> jax.Array:
    """Irradiance E = integral over a spherical cap of max(n.w, 0) dw, per unit radiance: the
    cosine-weighted solid angle of a uniform disc light (a sun) of angular radius sigma whose centre
    makes the angle theta with the normal n, including a cap partly below the horizon.

    cos_theta: n . (cap centre direction); sin_sigma: sin of the angular radius, in [0, 1]
    (broadcasting arrays). E/pi is the share of a white Lambertian's reflectance.

    Closed form (the sphere/disc "form factor" with horizon clipping; Snyder 1996, Lagarde & de
    Rousiers 2014 sec. 4.7.2): fully above the horizon (theta <= pi/2 - sigma) E = pi sin^2 sigma
    cos theta (the cap's vector irradiance dotted with n); fully below, 0; in between, with
    x = cot sigma and y = -x cot theta,
    E = (cos theta acos y - x sin theta sqrt(1 - y^2)) sin^2 sigma + atan2(sin theta sqrt(1 - y^2), x).
    The three pieces join continuously at cos^2 theta = sin^2 sigma (y = -+1 there). Values and
    gradients are finite everywhere (double where: the straddling formula is evaluated only where
    it applies, away from |y| = 1, where its terms have infinite slopes that cancel).
    """
    c, s, straddle, part = _cap_parts(cos_theta, sin_sigma)
    return jnp.where(straddle, jnp.maximum(part, 0.0), jnp.pi * s * s * jnp.maximum(c, 0.0))


def _cap_parts(cos_theta, sin_sigma):
    """(c, s, straddle mask, the straddling formula's value) of `cap_irradiance`."""
    c = jnp.clip(as_float(cos_theta), -1.0, 1.0)
    s = jnp.clip(as_float(sin_sigma), 0.0, 1.0)
    c, s = jnp.broadcast_arrays(c, s)
    s2 = s * s
    sin_t = safe_sqrt(1.0 - c * c)
    cos_sigma = safe_sqrt(1.0 - s2)
    x = safe_div(cos_sigma, s, s > 0)  # cot sigma (unused where s = 0: no straddling there)
    y = -x * safe_div(c, sin_t, sin_t > 0)
    # Straddling the horizon: |theta - pi/2| < sigma, i.e. c^2 < s^2 (and y strictly inside (-1, 1)).
    straddle = (c * c < s2) & (jnp.abs(y) < 1.0 - 1e-7)
    # Benign inputs off the straddling lanes (double where): arctan2(0, 0) at sigma = pi/2,
    # theta = 0 has a NaN slope that a mask alone would let into the gradient.
    ys = jnp.where(straddle, y, 0.0)
    xs = jnp.where(straddle, x, 1.0)
    st = jnp.where(straddle, sin_t, 1.0)

    def formula(o):
        c, s2, ys, xs, st = o
        root = jnp.sqrt(1.0 - ys * ys)
        return (c * jnp.arccos(ys) - xs * st * root) * s2 + jnp.arctan2(st * root, xs)

    # On the CPU only where some lane straddles (the callers use `part` on those lanes only, so 0
    # elsewhere is exact; `cpu_cond`). As a conditional's branch XLA:CPU computes it once per point; fused, every consumer
    # (each colour channel of a shaded pixel) evaluated its arccos and arctan2 again.
    operands = (c, s2, ys, xs, st)
    part = cpu_cond(jnp.any(straddle), formula, lambda o: jnp.zeros_like(o[0]), operands)
    return c, s, straddle, part
