"""jaxpbr: physically based shading and image-based lighting in JAX.

Pure, jit-compiled, vmappable kernels (GGX / Smith / Fresnel-Schlick / Lambert / Burley, the glTF
metallic-roughness and LearnOpenGL/UE4 models), punctual direct lighting, colour and image I/O.
Conventions (axes, units, alpha = r^2, ...) are listed in `jaxpbr.CONVENTIONS` and the README.
"""

from . import brdf_terms
from . import color, image, scene
from .brdf_terms import MIN_ROUGHNESS, MODELS, brdf
from .conventions import CONVENTIONS
from .lights import DirectionalLight, LightSet, PointLight, SpotLight, pack_lights, shade_direct
from .material import Material

__version__ = "0.1.0"

__all__ = [
    "CONVENTIONS",
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
