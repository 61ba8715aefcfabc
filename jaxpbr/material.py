"""The metallic-roughness material (glTF 2.0 `pbrMetallicRoughness`) as a JAX pytree."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from ._numerics import as_float, is_concrete

__all__ = ["Material", "F0_DIELECTRIC"]

#: Normal-incidence reflectance of the dielectric layer: ((ior - 1)/(ior + 1))^2 with ior = 1.5
#: (glTF 2.0 Appendix B, LearnOpenGL `vec3(0.04)`).
F0_DIELECTRIC = 0.04

_FIELDS = ("base_color", "metallic", "roughness", "occlusion", "emissive")
_VECTOR_FIELDS = ("base_color", "emissive")
_UNIT_FIELDS = ("metallic", "roughness", "occlusion")


@jax.tree_util.register_pytree_node_class
class Material:
    """Metallic-roughness material; every leaf may carry batch axes that broadcast with the geometry.

    Fields (defaults are glTF's):
        base_color: (..., 3) linear RGB albedo / F0 of metals, in [0, 1]. Default (1, 1, 1).
        metallic:   (...)    in [0, 1]. Default 1.
        roughness:  (...)    *perceptual* roughness r in [0, 1]; the GGX width is alpha = r^2.
                             Default 1.
        occlusion:  (...)    ambient occlusion in [0, 1], applied to ambient/indirect light only.
                             Default 1.
        emissive:   (..., 3) emitted linear radiance, >= 0. Default (0, 0, 0).

    Concrete values are validated (range, shape, finiteness) when the Material is built; traced
    values (inside jit/vmap/grad) cannot be checked and are taken as given.
    """

    __slots__ = _FIELDS

    def __init__(
        self,
        base_color: Any = (1.0, 1.0, 1.0),
        metallic: Any = 1.0,
        roughness: Any = 1.0,
        occlusion: Any = 1.0,
        emissive: Any = (0.0, 0.0, 0.0),
    ):
        values = dict(
            base_color=base_color,
            metallic=metallic,
            roughness=roughness,
            occlusion=occlusion,
            emissive=emissive,
        )
        for name, value in values.items():
            value = as_float(value)
            if name in _VECTOR_FIELDS and (value.ndim == 0 or value.shape[-1] != 3):
                raise ValueError(
                    f"Material.{name} must have a trailing axis of 3 (linear RGB), got shape "
                    f"{value.shape}; pass e.g. {name}=(r, g, b)."
                )
            if is_concrete(value):
                _validate(name, value)
            object.__setattr__(self, name, value)

    # Pytree protocol: unflatten bypasses __init__ so that tracers, None or sentinel leaves that
    # JAX transformations put in the tree are never converted or validated.
    def tree_flatten(self):
        return tuple(getattr(self, f) for f in _FIELDS), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        for f, c in zip(_FIELDS, children):
            object.__setattr__(obj, f, c)
        return obj

    def __setattr__(self, name, value):
        raise AttributeError("Material is immutable; use material.replace(field=value).")

    def replace(self, **changes) -> "Material":
        """A copy with some fields replaced (validated like the constructor)."""
        unknown = set(changes) - set(_FIELDS)
        if unknown:
            raise TypeError(f"Material has no field(s) {sorted(unknown)}; fields are {list(_FIELDS)}.")
        values = {f: getattr(self, f) for f in _FIELDS}
        values.update(changes)
        return Material(**values)

    def __repr__(self) -> str:
        parts = []
        for f in _FIELDS:
            x = getattr(self, f)
            if is_concrete(x) and getattr(x, "size", 2) <= 3:
                parts.append(f"{f}={np.asarray(x).tolist()}")
            else:
                parts.append(f"{f}={getattr(x, 'dtype', '?')}{list(getattr(x, 'shape', ()))}")
        return "Material(" + ", ".join(parts) + ")"

    # Derived quantities (glTF Appendix B).
    def f0(self, f0_dielectric: float = F0_DIELECTRIC) -> jax.Array:
        """Normal-incidence reflectance, (..., 3): lerp(0.04, base_color, metallic)."""
        m = self.metallic[..., None]
        return f0_dielectric * (1.0 - m) + self.base_color * m

    def diffuse_color(self) -> jax.Array:
        """c_diff = base_color * (1 - metallic), (..., 3): metals have no diffuse lobe."""
        return self.base_color * (1.0 - self.metallic[..., None])


def _validate(name: str, value: jax.Array) -> None:
    a = np.asarray(value)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Material.{name} contains NaN or Inf; pass finite values.")
    if name in _UNIT_FIELDS and (a.min(initial=0.0) < 0.0 or a.max(initial=0.0) > 1.0):
        raise ValueError(
            f"Material.{name} must lie in [0, 1], got values in [{a.min():g}, {a.max():g}]; "
            f"clip it (roughness is perceptual r, not alpha = r^2)."
        )
    if name in _VECTOR_FIELDS and a.min(initial=0.0) < 0.0:
        raise ValueError(f"Material.{name} must be >= 0 (linear RGB), got minimum {a.min():g}.")
    if name == "base_color" and a.max(initial=0.0) > 1.0:
        raise ValueError(
            f"Material.base_color must lie in [0, 1] (an albedo), got maximum {a.max():g}; "
            "use emissive for light-emitting surfaces."
        )
