"""The metallic-roughness material (glTF 2.0 `pbrMetallicRoughness`) as a JAX pytree."""

from __future__ import annotations

import reprlib
from typing import Any

import jax
import numpy as np

from .._numerics import as_float, is_concrete
from .._pytree import Pytree, fields_of, leaf

__all__ = ["EXTENSIONS", "EXTENSION_FIELDS", "Material", "F0_DIELECTRIC"]

#: Normal-incidence reflectance of the dielectric layer: ((ior - 1)/(ior + 1))^2 with ior = 1.5
#: (glTF 2.0 Appendix B, LearnOpenGL `vec3(0.04)`).
F0_DIELECTRIC = 0.04

#: Material fields that must lie in [0, 1] (the scene file checks them with the same list).
UNIT_FIELDS = (
    "metallic",
    "roughness",
    "occlusion",
    "clearcoat",
    "clearcoat_roughness",
    "sheen_roughness",
    "specular",
    "anisotropy_strength",
    "transmission",
)

#: The glTF material extensions jaxpbr shades: group -> {field: neutral value}. The neutral value
#: is the extension's default (its schema), at which the extension changes nothing. A group is
#: *present* in a `Material` when any of its fields is not None (`Material.extensions`); its other
#: fields then take these values (`Material.complete`). Absent groups compile no code.
EXTENSION_FIELDS: dict[str, dict[str, Any]] = {
    "clearcoat": {"clearcoat": 0.0, "clearcoat_roughness": 0.0},
    "sheen": {"sheen_color": (0.0, 0.0, 0.0), "sheen_roughness": 0.0},
    "specular": {"specular": 1.0, "specular_color": (1.0, 1.0, 1.0)},
    "ior": {"ior": 1.5},
    "anisotropy": {"anisotropy_strength": 0.0, "anisotropy_rotation": 0.0},
    "emissive_strength": {"emissive_strength": 1.0},
    "transmission": {"transmission": 0.0},
    "volume": {"thickness": 0.0, "attenuation_distance": float("inf"), "attenuation_color": (1.0, 1.0, 1.0)},
}
#: The extension groups, in layering order (KHR_materials_<name>).
EXTENSIONS = tuple(EXTENSION_FIELDS)
_EXT_OF = {f: g for g, fs in EXTENSION_FIELDS.items() for f in fs}


class Material(Pytree):
    """Metallic-roughness material; every leaf may carry batch axes that broadcast with the geometry.

    Fields (defaults are glTF's):
        base_color: (..., 3) linear RGB albedo / F0 of metals, in [0, 1]. Default (1, 1, 1).
        metallic:   (...)    in [0, 1]. Default 1.
        roughness:  (...)    *perceptual* roughness r in [0, 1]; the GGX width is alpha = r^2.
                             Default 1.
        occlusion:  (...)    ambient occlusion in [0, 1], applied to ambient/indirect light only.
                             Default 1.
        emissive:   (..., 3) emitted linear radiance, >= 0. Default (0, 0, 0).

    glTF material extensions (KHR_materials_<group>; every field None = the extension is absent,
    which compiles none of its code; `EXTENSION_FIELDS` lists the neutral values a present
    group's unset fields take):
        clearcoat, clearcoat_roughness:  (...) in [0, 1] (KHR_materials_clearcoat; the coat
                             normal is an argument of the shading functions / a texture).
        sheen_color: (..., 3) in [0, 1]; sheen_roughness: (...) in [0, 1] (KHR_materials_sheen).
        specular: (...) in [0, 1]; specular_color: (..., 3) >= 0 (KHR_materials_specular).
        ior: (...) >= 1, or 0 (specular-glossiness mode: F = 1) (KHR_materials_ior).
        anisotropy_strength: (...) in [0, 1]; anisotropy_rotation: (...) radians from the tangent
                             (KHR_materials_anisotropy; needs a tangent).
        emissive_strength: (...) >= 0, multiplies emissive (KHR_materials_emissive_strength).
        transmission: (...) in [0, 1] (KHR_materials_transmission, thin-walled unless volume).
        thickness: (...) >= 0; attenuation_distance: (...) > 0, inf allowed; attenuation_color:
                             (..., 3) in [0, 1] (KHR_materials_volume).

    Concrete values are validated (range, shape, finiteness) when the Material is built or
    `replace`d (`_validate`); traced values (inside jit/vmap/grad) cannot be checked and are taken
    as given (the trailing RGB axis, a shape, is checked even then).
    """

    base_color: Any = leaf((1.0, 1.0, 1.0), rank=1)
    metallic: Any = leaf(1.0)
    roughness: Any = leaf(1.0)
    occlusion: Any = leaf(1.0)
    emissive: Any = leaf((0.0, 0.0, 0.0), rank=1)
    clearcoat: Any = leaf(None)
    clearcoat_roughness: Any = leaf(None)
    sheen_color: Any = leaf(None, rank=1)
    sheen_roughness: Any = leaf(None)
    specular: Any = leaf(None)
    specular_color: Any = leaf(None, rank=1)
    ior: Any = leaf(None)
    anisotropy_strength: Any = leaf(None)
    anisotropy_rotation: Any = leaf(None)
    emissive_strength: Any = leaf(None)
    transmission: Any = leaf(None)
    thickness: Any = leaf(None)
    attenuation_distance: Any = leaf(None)
    attenuation_color: Any = leaf(None, rank=1)

    @property
    def extensions(self) -> tuple[str, ...]:
        """The extension groups present (any field not None), in `EXTENSIONS` order. Static: it
        is part of the pytree structure, so it is known inside jit."""
        return tuple(g for g, fs in EXTENSION_FIELDS.items() if any(getattr(self, f) is not None for f in fs))

    @property
    def layered(self) -> bool:
        """Whether shading needs the layered BSDF (`jaxpbr.shading.layered`): some extension other than
        emissive_strength, which only scales the emission, is present."""
        return any(g != "emissive_strength" for g in self.extensions)

    def complete(self, groups=None) -> "Material":
        """A copy whose groups `groups` (default: the present ones) have every field set, unset
        ones to their neutral values (unchecked: safe inside transformations)."""
        from .._pytree import evolve

        groups = self.extensions if groups is None else tuple(groups)
        fill = {}
        for g in groups:
            for f, neutral in EXTENSION_FIELDS[g].items():
                if getattr(self, f) is None:
                    fill[f] = as_float(neutral)
        return evolve(self, **fill) if fill else self

    def emission(self) -> jax.Array:
        """emissive * emissive_strength (KHR_materials_emissive_strength), (..., 3)."""
        if self.emissive_strength is None:
            return self.emissive
        return self.emissive * self.emissive_strength[..., None]

    def _validate(self) -> None:
        for field in fields_of(self):
            name = field.name
            if getattr(self, name) is None and name in _EXT_OF:
                continue
            value = _as_number(name, getattr(self, name), field.rank)
            if field.rank == 1 and (value.ndim == 0 or value.shape[-1] != 3):
                raise ValueError(
                    f"Material.{name} must have a trailing axis of 3 (linear RGB), got shape "
                    f"{value.shape}; pass e.g. {name}=(r, g, b)."
                )
            if is_concrete(value):
                _check_values(name, value)
            self._set(**{name: value})

    # Derived quantities (glTF Appendix B).
    def f0(self, f0_dielectric: float = F0_DIELECTRIC) -> jax.Array:
        """Normal-incidence reflectance, (..., 3): lerp(0.04, base_color, metallic)."""
        m = self.metallic[..., None]
        return f0_dielectric * (1.0 - m) + self.base_color * m

    def diffuse_color(self) -> jax.Array:
        """c_diff = base_color * (1 - metallic), (..., 3): metals have no diffuse lobe."""
        return self.base_color * (1.0 - self.metallic[..., None])


def _as_number(name: str, x, rank: int) -> jax.Array:
    """`as_float(x)`, or a TypeError naming `Material.<name>` (JAX's own names neither the field
    nor the fix: a string such as roughness='0.5' gave "... is not a valid JAX type")."""
    example = f"{name}=(0.8, 0.5, 0.3)" if rank == 1 else f"{name}=0.5"
    if isinstance(x, (str, bytes)):
        raise TypeError(f"Material.{name} must be a number or an array of numbers, got the string {x!r}; pass e.g. {example}")
    try:
        return as_float(x)
    except TypeError as e:
        if "real values" in str(e):  # complex: as_float's own message, with the field named
            raise TypeError(f"Material.{name}: {e}") from None
        raise TypeError(
            f"Material.{name} must be a number or an array of numbers, got {type(x).__name__} {reprlib.repr(x)}; pass e.g. {example}"
        ) from None


def _check_values(name: str, value: jax.Array) -> None:
    a = np.asarray(value)
    if name == "attenuation_distance":
        if np.any(np.isnan(a)) or a.min(initial=1.0) <= 0.0:
            raise ValueError(
                f"Material.attenuation_distance must be > 0 (inf = no absorption, the default), "
                f"got minimum {a.min():g}; pass a positive distance in scene units."
            )
        return
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Material.{name} contains NaN or Inf; pass finite values.")
    if name in UNIT_FIELDS and (a.min(initial=0.0) < 0.0 or a.max(initial=0.0) > 1.0):
        raise ValueError(
            f"Material.{name} must lie in [0, 1], got values in [{a.min():g}, {a.max():g}]; "
            f"clip it (roughness is perceptual r, not alpha = r^2)."
        )
    if name == "ior" and np.any((a != 0.0) & (a < 1.0)):
        raise ValueError(
            f"Material.ior must be >= 1 (or exactly 0, glTF's specular-glossiness mode), got minimum "
            f"{a.min():g}; an ior below 1 is a medium less dense than air."
        )
    if name in ("sheen_color", "attenuation_color") and (a.min(initial=0.0) < 0.0 or a.max(initial=0.0) > 1.0):
        raise ValueError(f"Material.{name} must lie in [0, 1] (linear RGB), got [{a.min():g}, {a.max():g}].")
    if name in ("specular_color", "emissive_strength", "thickness") and a.min(initial=0.0) < 0.0:
        raise ValueError(f"Material.{name} must be >= 0, got minimum {a.min():g}.")
    if name in ("base_color", "emissive") and a.min(initial=0.0) < 0.0:
        raise ValueError(f"Material.{name} must be >= 0 (linear RGB), got minimum {a.min():g}.")
    if name == "base_color" and a.max(initial=0.0) > 1.0:
        raise ValueError(
            f"Material.base_color must lie in [0, 1] (an albedo), got maximum {a.max():g}; "
            "use emissive for light-emitting surfaces."
        )
