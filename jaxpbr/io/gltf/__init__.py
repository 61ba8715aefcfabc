"""glTF 2.0 loader: `read_gltf(path)` -> `GltfAsset`, a scene flattened to world space in NumPy.

Reads .gltf (external .bin/images, data: URIs) and .glb (the container parsed here, the JSON with
Python's json module, every value type-checked against the glTF 2.0 schema before use); accessors (all component types, normalized integers, byteStride, sparse, no
bufferView) are decoded in NumPy. Materials map onto `jaxpbr.Material` keyword arguments
(`GltfMaterial.factors`) plus texture slots (`GltfTextureRef`); images are decoded with
OpenImageIO to float32 arrays of the encoded values. KHR_lights_punctual lights and cameras come
with world transforms. Animations (`GltfAnimation`), skins and morph targets pose the asset at a
time (`read_gltf(path, time=, animation=)`, `posed_asset`), in NumPy or traced by JAX
(`pose_primitives`). See `read_gltf` for what is supported, refused and ignored.
"""

from ._animation import pose_primitives, posed_asset
from ._loader import SUPPORTED_EXTENSIONS, read_gltf
from ._materials import MAG_FILTER as GLTF_MAG_FILTERS
from ._materials import MIN_FILTER as GLTF_MIN_FILTERS
from ._materials import WRAP as GLTF_WRAP_MODES
from ._materials import texture_transform_matrix
from ._types import (
    TEXTURE_CHANNELS,
    GltfAnimation,
    GltfAsset,
    GltfChannel,
    GltfDeform,
    GltfNodes,
    GltfSkin,
    GltfCamera,
    GltfImage,
    GltfLight,
    GltfMaterial,
    GltfPrimitive,
    GltfSampler,
    GltfTextureRef,
)


__all__ = [
    "GLTF_MAG_FILTERS",
    "GLTF_MIN_FILTERS",
    "GLTF_WRAP_MODES",
    "SUPPORTED_EXTENSIONS",
    "TEXTURE_CHANNELS",
    "GltfAnimation",
    "GltfAsset",
    "GltfChannel",
    "GltfDeform",
    "GltfNodes",
    "GltfSkin",
    "GltfCamera",
    "GltfImage",
    "GltfLight",
    "GltfMaterial",
    "GltfPrimitive",
    "GltfSampler",
    "GltfTextureRef",
    "pose_primitives",
    "posed_asset",
    "read_gltf",
    "texture_transform_matrix",
]
