"""jaxpbr: physically based shading and image-based lighting in JAX.

Pure, jit-compiled, vmappable kernels (GGX / Smith / Fresnel-Schlick / Lambert / Burley, the glTF
metallic-roughness and LearnOpenGL/UE4 models), punctual direct lighting, image-based lighting
(cube maps, exact and SH9 irradiance, GGX-prefiltered mips, the converged split-sum LUT, split-sum
shading), colour and image I/O (EXR, HDR, PNG, KTX2).
Conventions (axes, units, alpha = r^2, ...) are listed in `jaxpbr.CONVENTIONS` and docs/conventions.md.
"""

from . import _entry  # first, before NumPy and JAX load: the command line's signal handlers

_entry.early()
_entry.phase("start")

from . import atomic, brdf_terms, color, demo, envs, image, ktx2, renderer, scene
from ._version import __version__
from .brdf_terms import MIN_ROUGHNESS, MODELS
from .layered import brdf
from .conventions import CONVENTIONS
from .cubemap import Cubemap
from .diffuse import irradiance, sh9_irradiance, sh9_project
from .ibl import shade_ibl
from .lights import (
    DirectionalLight,
    LightSet,
    PointLight,
    SpotLight,
    pack_lights,
    shade_direct,
)
from .lut import compute_brdf_lut, lut_lookup, lut_reference
from .material import Material
from .renderer import RenderOptions, bake, render, render_batch
from .scene import Camera, Environment, GBuffer, Plane, Scene, Sphere, TexturedMaterial
from .shipped_luts import brdf_lut
from .specular import prefilter, prefilter_reference, roughness_to_lod

__all__ = [
    "__version__",
    "atomic",
    "bake",
    "CONVENTIONS",
    "Camera",
    "Cubemap",
    "Environment",
    "GBuffer",
    "Plane",
    "RenderOptions",
    "Scene",
    "Sphere",
    "TexturedMaterial",
    "demo",
    "render",
    "render_batch",
    "renderer",
    "brdf_lut",
    "compute_brdf_lut",
    "envs",
    "irradiance",
    "ktx2",
    "lut_lookup",
    "lut_reference",
    "prefilter",
    "prefilter_reference",
    "roughness_to_lod",
    "sh9_irradiance",
    "sh9_project",
    "shade_ibl",
    "DirectionalLight",
    "LightSet",
    "MIN_ROUGHNESS",
    "MODELS",
    "Material",
    "PointLight",
    "SpotLight",
    "brdf",
    "brdf_terms",
    "color",
    "image",
    "scene",
    "pack_lights",
    "shade_direct",
]
