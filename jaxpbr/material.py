"""The metallic-roughness material (glTF 2.0 `pbrMetallicRoughness`) as a JAX pytree."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from ._numerics import as_float, is_concrete
from ._pytree import Pytree, fields_of, leaf

__all__ = ["Material", "F0_DIELECTRIC"]

#: Normal-incidence reflectance of the dielectric layer: ((ior - 1)/(ior + 1))^2 with ior = 1.5
#: (glTF 2.0 Appendix B, LearnOpenGL `vec3(0.04)`).
F0_DIELECTRIC = 0.04

_UNIT_FIELDS = ("metallic", "roughness", "occlusion")


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

    Concrete values are validated (range, shape, finiteness) when the Material is built or
    `replace`d (`_validate`); traced values (inside jit/vmap/grad) cannot be checked and are taken
    as given (the trailing RGB axis, a shape, is checked even then).
    """

    base_color: Any = leaf((1.0, 1.0, 1.0), rank=1)
    metallic: Any = leaf(1.0)
    roughness: Any = leaf(1.0)
    occlusion: Any = leaf(1.0)
    emissive: Any = leaf((0.0, 0.0, 0.0), rank=1)

    def _validate(self) -> None:
        for field in fields_of(self):
            name = field.name
            value = as_float(getattr(self, name))
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


def _check_values(name: str, value: jax.Array) -> None:
    a = np.asarray(value)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Material.{name} contains NaN or Inf; pass finite values.")
    if name in _UNIT_FIELDS and (a.min(initial=0.0) < 0.0 or a.max(initial=0.0) > 1.0):
        raise ValueError(
            f"Material.{name} must lie in [0, 1], got values in [{a.min():g}, {a.max():g}]; "
            f"clip it (roughness is perceptual r, not alpha = r^2)."
        )
    if name in ("base_color", "emissive") and a.min(initial=0.0) < 0.0:
        raise ValueError(f"Material.{name} must be >= 0 (linear RGB), got minimum {a.min():g}.")
    if name == "base_color" and a.max(initial=0.0) > 1.0:
        raise ValueError(
            f"Material.base_color must lie in [0, 1] (an albedo), got maximum {a.max():g}; "
            "use emissive for light-emitting surfaces."
        )
