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

from . import color, ibl, io, rendering, shading
from .ibl import envs
from .io import image, ktx2
from .rendering import demo
from ._version import __version__
from .shading.brdf_terms import MIN_ROUGHNESS, MODELS
from .shading.layered import brdf
from .conventions import CONVENTIONS
from .ibl.baked import write_baked
from .ibl.cubemap import Cubemap
from .ibl.cubeio import load_environment
from .ibl.diffuse import irradiance, sh9_irradiance, sh9_project
from .ibl.shade import shade_ibl
from .shading.lights import (
    DirectionalLight,
    LightSet,
    PointLight,
    SpotLight,
    pack_lights,
    shade_direct,
)
from .shading.lut import compute_brdf_lut, lut_lookup, lut_reference
from .shading.material import Material
from .rendering.baked import read_baked
from .rendering.animated import posed_geometry, posed_scene
from .rendering.gltf_scene import load_gltf
from .rendering.scene_file import load_scene, loads_scene
from .rendering.mesh import Mesh
from .rendering.renderer import RenderOptions, bake, clear_caches, deformable, render, render_batch
from .rendering.texture import Texture
from .rendering.textured import TextureSlot
from .rendering.scene import Camera, Environment, GBuffer, Plane, Scene, Sphere, TexturedMaterial
from .shading.shipped_luts import brdf_lut
from .ibl.specular import prefilter, prefilter_reference, roughness_to_lod
from .reference import reference_render

__all__ = [
    "__version__",
    "shading",
    "ibl",
    "io",
    "rendering",
    "bake",
    "clear_caches",
    "read_baked",
    "write_baked",
    "CONVENTIONS",
    "Camera",
    "Cubemap",
    "Environment",
    "GBuffer",
    "Mesh",
    "Texture",
    "TextureSlot",
    "load_environment",
    "load_gltf",
    "posed_geometry",
    "posed_scene",
    "load_scene",
    "loads_scene",
    "Plane",
    "RenderOptions",
    "Scene",
    "Sphere",
    "TexturedMaterial",
    "demo",
    "deformable",
    "render",
    "render_batch",
    "reference_render",
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
    "color",
    "image",
    "pack_lights",
    "shade_direct",
]
