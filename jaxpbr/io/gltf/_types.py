"""The loaded asset: plain dataclasses of NumPy arrays (host side, world space)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
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
]

#: Which channels of each texture role carry what (glTF 2.0 and the KHR_materials_* READMEs); the
#: shader multiplies the factor of the same name in `GltfMaterial.factors` by the sampled value.
TEXTURE_CHANNELS: dict[str, str] = {
    "base_color": "RGB x base_color, A x base_color_alpha (sRGB-encoded RGB)",
    "metallic_roughness": "B x metallic, G x roughness",
    "normal": "RGB tangent-space normal, XY scaled by `scale`",
    "occlusion": "R; occlusion = 1 + strength * (R - 1)",
    "emissive": "RGB x emissive (sRGB-encoded)",
    "clearcoat": "R x clearcoat",
    "clearcoat_roughness": "G x clearcoat_roughness",
    "clearcoat_normal": "RGB tangent-space normal of the coat, XY scaled by `scale`",
    "sheen_color": "RGB x sheen_color (sRGB-encoded)",
    "sheen_roughness": "A x sheen_roughness",
    "specular": "A x specular",
    "specular_color": "RGB x specular_color (sRGB-encoded)",
    "anisotropy": "RG direction in [-1, 1] (tangent space), B x anisotropy_strength",
    "transmission": "R x transmission",
    "thickness": "G x thickness",
}


@dataclass(frozen=True)
class GltfSampler:
    """How a texture is sampled (glTF `sampler`).

    Fields:
        wrap_s, wrap_t: 'repeat' | 'clamp' (CLAMP_TO_EDGE) | 'mirror' (MIRRORED_REPEAT).
        mag_filter: 'nearest' | 'linear'.
        min_filter: 'nearest' | 'linear' | 'nearest_mipmap_nearest' | 'linear_mipmap_nearest' |
            'nearest_mipmap_linear' | 'linear_mipmap_linear'.
    The spec leaves unset filters to the implementation ("auto filtering"); they read here as
    'linear' / 'linear_mipmap_linear', and a texture without a sampler gets repeat wrapping with
    those filters (the spec's rule). `specified`: the texture names a sampler of the file.
    """

    wrap_s: str = "repeat"
    wrap_t: str = "repeat"
    mag_filter: str = "linear"
    min_filter: str = "linear_mipmap_linear"
    specified: bool = False


@dataclass(frozen=True, eq=False)
class GltfTextureRef:
    """One material texture slot (a glTF `textureInfo`), resolved.

    Fields:
        role: the slot (a key of `TEXTURE_CHANNELS`).
        texture: index into the file's `textures`; image: index into `GltfAsset.images`.
        texcoord: the TEXCOORD_n set to sample with (KHR_texture_transform's texCoord override
            already applied).
        sampler: `GltfSampler`.
        transform: (3, 3) float64 matrix M applied to (u, v, 1): uv' = (M @ [u, v, 1])[:2]
            (KHR_texture_transform; identity when absent). M = T(offset) R(rotation) S(scale) with
            R = [[cos r, sin r], [-sin r, cos r]]: counter-clockwise in glTF's v-down UV space, the
            direction of the README's worked example and of three.js, Babylon.js and Blender
            (KhronosGroup/glTF#1563: the README's GLSL listing has the opposite sign).
        has_transform: the file gave a KHR_texture_transform for this slot.
        colorspace: 'srgb' (base_color, emissive, sheen_color, specular_color) or 'linear'.
            Images are stored as encoded; the renderer decodes 'srgb' ones.
        scale: normalTextureInfo.scale (normal, clearcoat_normal); 1.0 for other roles.
        strength: occlusionTextureInfo.strength (occlusion); 1.0 for other roles.
    """

    role: str
    texture: int
    image: int
    texcoord: int
    sampler: GltfSampler
    transform: np.ndarray
    has_transform: bool
    colorspace: str
    scale: float = 1.0
    strength: float = 1.0


@dataclass(eq=False)
class GltfMaterial:
    """A glTF material in jaxpbr's terms.

    Fields:
        index: index in the file's `materials`; None for the spec's default material (used by
            primitives without a material; then `is_default` is True).
        name: the material's name ('' when unnamed).
        factors: keyword arguments for `jaxpbr.Material` (linear values, glTF defaults filled in):
            always base_color (3), metallic, roughness, occlusion (1.0: occlusionTexture.strength
            stays on the texture ref), emissive (3); plus the fields of each KHR_materials_*
            extension group the material uses, with the extension's defaults for unset values:
            clearcoat, clearcoat_roughness | sheen_color (3), sheen_roughness | specular,
            specular_color (3) | ior | anisotropy_strength, anisotropy_rotation |
            emissive_strength | transmission | thickness, attenuation_distance (inf when absent),
            attenuation_color (3). Colours are tuples of floats.
        base_color_alpha: baseColorFactor[3].
        alpha_mode: 'OPAQUE' | 'MASK' | 'BLEND'; alpha_cutoff: 0.5 unless given (MASK only).
        double_sided: bool.
        textures: role -> `GltfTextureRef` for the slots the material fills.
        extensions: the KHR_materials_* extension names the material uses (supported ones).
        unlit: KHR_materials_unlit: the base colour is also the emission (factor and texture), and
            the pixels of the material's mesh show that emission alone (`Mesh.unlit`).
    """

    index: int | None
    name: str
    factors: dict[str, Any]
    base_color_alpha: float = 1.0
    alpha_mode: str = "OPAQUE"
    alpha_cutoff: float = 0.5
    double_sided: bool = False
    textures: dict[str, GltfTextureRef] = field(default_factory=dict)
    extensions: tuple[str, ...] = ()
    unlit: bool = False

    @property
    def is_default(self) -> bool:
        return self.index is None

    @property
    def needs_tangents(self) -> bool:
        """Whether shading needs a tangent frame: a normal or clearcoat-normal texture, or anisotropy."""
        return bool({"normal", "clearcoat_normal", "anisotropy"} & set(self.textures)) or (
            "anisotropy_strength" in self.factors
        )


class GltfImage:
    """An image of the file, decoded on first access of `pixels` (and only once).

    `read_gltf` decodes the images that materials use before it returns (so a bad image fails the
    load), unless it was called with `lazy_images=True`.

    Attributes:
        index: index in the file's `images`; name: its name ('' when unnamed).
        mime_type: 'image/png' or 'image/jpeg' (declared, or sniffed from the bytes).
        source: where the bytes come from ('bufferView 3', 'data URI', or the file path).
        pixels: (H, W, C) float32 in [0, 1], C in {1, 2, 3, 4}, the *encoded* values (no colour
            conversion; alpha not premultiplied); row 0 is the top of the image, i.e. v = 0.
    """

    def __init__(self, index: int, name: str, mime_type: str, source: str, loader):
        self.index = index
        self.name = name
        self.mime_type = mime_type
        self.source = source
        self._loader = loader
        self._pixels: np.ndarray | None = None

    @property
    def decoded(self) -> bool:
        return self._pixels is not None

    @property
    def pixels(self) -> np.ndarray:
        if self._pixels is None:
            self._pixels = self._loader()
            self._loader = None
        return self._pixels

    def __repr__(self) -> str:
        shape = tuple(self._pixels.shape) if self._pixels is not None else "not decoded"
        return f"GltfImage({self.index}, {self.name!r}, {self.mime_type}, {self.source}, {shape})"


@dataclass(frozen=True, eq=False)
class GltfChannel:
    """One animated property of a node: `path` ('translation', 'rotation', 'scale' or 'weights'),
    its sampler's `interpolation` ('LINEAR', 'STEP', 'CUBICSPLINE'), key `times` (K,) float64
    strictly increasing (seconds) and `values`: (K, C) float64, or (K, 3, C) for CUBICSPLINE
    (in-tangent, value, out-tangent); C is 3, 4 (quaternion x y z w) or the mesh's morph targets."""

    node: int
    path: str
    interpolation: str
    times: np.ndarray
    values: np.ndarray


@dataclass(frozen=True, eq=False)
class GltfAnimation:
    """An animation of the file: its index, name ('' when absent) and channels. Its time runs from
    0 to `duration` (the last key time of its channels)."""

    index: int
    name: str
    channels: tuple[GltfChannel, ...]

    @property
    def duration(self) -> float:
        return max((float(c.times[-1]) for c in self.channels), default=0.0)

    @property
    def nodes(self) -> frozenset:
        """The nodes whose transform or morph weights it animates."""
        return frozenset(c.node for c in self.channels)


@dataclass(frozen=True, eq=False)
class GltfSkin:
    """A skin: its `joints` (J,) node indices and `inverse_bind` (J, 4, 4) float64 matrices
    (identities when the file gives none)."""

    index: int
    name: str
    joints: np.ndarray
    inverse_bind: np.ndarray


@dataclass(frozen=True, eq=False)
class GltfNodes:
    """Every node of the file (not only the loaded scene's): `parents` (N,) (-1 for a root), the rest
    transform as `translation` (N, 3), `rotation` (N, 4) x y z w, `scale` (N, 3) and as `matrix`
    (N, 4, 4) (a node given by its matrix: that matrix, `has_matrix`), and `levels`: the nodes
    grouped by depth (`jaxpbr.geometry.pose.hierarchy_levels`)."""

    parents: np.ndarray
    translation: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    matrix: np.ndarray
    has_matrix: np.ndarray
    levels: tuple


@dataclass(frozen=True, eq=False)
class GltfDeform:
    """What poses a primitive whose placement changes with its nodes (animated, skinned or morphed),
    in object space with the primitive's vertex order (`GltfPrimitive.positions` is this posed at
    the time loaded):

    positions, normals: (V, 3) float64; tangents: (V, 4) float64 or None.
    targets: morph-target deltas {'POSITION'|'NORMAL'|'TANGENT': (K, V, 3) float64} ({} without).
    skin: the node's skin index or None; joints, weights: (V, n) int64 indices into the skin's
        joints and float64 weights (rows summing to 1), n = 4 x the JOINTS_n/WEIGHTS_n sets.
    instance: (4, 4) float64, the EXT_mesh_gpu_instancing transform inside the node (identity
        without instancing).
    tris: (T, 3) int64 counter-clockwise triangles in object space (flat normals are made again
        from the morphed triangles).
    morph_weights: (K,) float64 the weights when no animation sets them (the node's, else the
        mesh's, else zeros), or None without morph targets."""

    positions: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray | None
    targets: dict
    skin: int | None
    joints: np.ndarray | None
    weights: np.ndarray | None
    instance: np.ndarray
    tris: np.ndarray
    morph_weights: np.ndarray | None


@dataclass(eq=False, slots=True)
class GltfPrimitive:
    """One mesh primitive instanced by one node, in world space, as a triangle list.

    Fields:
        positions: (V, 3) float32, world space.
        normals: (V, 3) float32 unit vectors, world space (M^-T of the node's world matrix M).
            Flat normals (one per triangle, vertices unwelded) when the file has none.
        indices: (T, 3) int32 triangles, counter-clockwise front faces in world space (a mirroring
            world matrix, det < 0, swaps two indices of each triangle).
        tangents: (V, 4) float32 or None: xyz = M @ tangent, normalized; w = file's w * sign(det M),
            so that bitangent = cross(normal, tangent.xyz) * w is M @ (object bitangent) also
            under a mirroring M. Generated with MikkTSpace (object space, before the transform)
            when the material needs them and the file has none (`generated_tangents`).
        texcoord_0, texcoord_1: (V, 2) float32 or None (glTF convention: v = 0 is the image's top).
        color_0: (V, 4) float32 or None (RGB data gets alpha 1); linear.
        material: index into `GltfAsset.materials`.
        node, mesh, primitive: where it comes from (node index, mesh index, index in the mesh).
        instance: the EXT_mesh_gpu_instancing instance (world_matrix includes its transform), or
            None for a node without instancing.
        name: 'mesh name/primitive index' (+ '#instance').
        world_matrix: (4, 4) float64 node-to-world matrix.
        flat_normals: the normals were generated (flat); generated_tangents: the tangents were.
        deform: `GltfDeform` for a primitive that animations, skins or morph targets move (what
            `jaxpbr.rendering.animated` poses it from), else None.
    """

    positions: np.ndarray
    normals: np.ndarray
    indices: np.ndarray
    material: int
    node: int
    mesh: int
    primitive: int
    name: str
    world_matrix: np.ndarray
    tangents: np.ndarray | None = None
    texcoord_0: np.ndarray | None = None
    texcoord_1: np.ndarray | None = None
    color_0: np.ndarray | None = None
    flat_normals: bool = False
    generated_tangents: bool = False
    instance: int | None = None
    deform: GltfDeform | None = None

    @property
    def num_vertices(self) -> int:
        return int(self.positions.shape[0])

    @property
    def num_triangles(self) -> int:
        return int(self.indices.shape[0])

    def texcoord(self, n: int) -> np.ndarray | None:
        """TEXCOORD_n (n = 0 or 1), or None."""
        return {0: self.texcoord_0, 1: self.texcoord_1}.get(n)


@dataclass(eq=False)
class GltfLight:
    """A KHR_lights_punctual light instanced by a node, in world space.

    Fields:
        type: 'directional' | 'point' | 'spot'.
        color: (3,) float64 linear RGB; intensity: candela (point, spot) or lux (directional).
        range: distance cut-off, inf when absent (directional lights ignore it).
        inner_cone_angle, outer_cone_angle: radians (spot; defaults 0 and pi/4), None otherwise.
        position: (3,) world position of the node; direction: (3,) unit vector, the node's -Z axis
            in world space (where the light points).
        light: index in the extension's `lights`; node: the instancing node; name.
    """

    type: str
    color: np.ndarray
    intensity: float
    range: float
    position: np.ndarray
    direction: np.ndarray
    light: int
    node: int
    name: str = ""
    inner_cone_angle: float | None = None
    outer_cone_angle: float | None = None


@dataclass(eq=False)
class GltfCamera:
    """A camera instanced by a node.

    Fields:
        type: 'perspective' | 'orthographic'.
        yfov (radians), aspect_ratio (None: use the viewport's), znear, zfar (inf when absent:
            infinite projection) for perspective; xmag, ymag, znear, zfar for orthographic
            (None for the fields of the other type).
        world_matrix: (4, 4) float64 camera-to-world matrix; the camera looks down its -Z axis
            with +Y up (`position`, `forward`, `up` read it).
        camera: index in the file's `cameras`; node: the instancing node; name.
    """

    type: str
    world_matrix: np.ndarray
    camera: int
    node: int
    name: str = ""
    znear: float | None = None
    zfar: float | None = None
    yfov: float | None = None
    aspect_ratio: float | None = None
    xmag: float | None = None
    ymag: float | None = None

    @property
    def position(self) -> np.ndarray:
        return self.world_matrix[:3, 3].copy()

    @property
    def forward(self) -> np.ndarray:
        v = -self.world_matrix[:3, 2]
        return v / max(float(np.linalg.norm(v)), 1e-300)

    @property
    def up(self) -> np.ndarray:
        v = self.world_matrix[:3, 1]
        return v / max(float(np.linalg.norm(v)), 1e-300)


@dataclass(eq=False)
class GltfAsset:
    """A loaded glTF 2.0 scene, flattened to world space (see `read_gltf`).

    Fields:
        path: the file read.
        generator: asset.generator ('' when absent); version: asset.version.
        scene: index of the scene loaded (None when the file has no scenes: then all root nodes).
        primitives: list of `GltfPrimitive`, one per (node, mesh primitive), scene traversal order.
        materials: list of `GltfMaterial`, the file's materials in order, then the default
            material when a primitive has none.
        images: list of `GltfImage`, all of the file's images, in order.
        lights: list of `GltfLight`; cameras: list of `GltfCamera` (scene traversal order).
        bounds: (2, 3) float64 world AABB [min, max] of all positions, None without geometry.
        extensions_used: the file's extensionsUsed.
        warnings: the messages `read_gltf` warned (ignored extensions and features).
        animations: every `GltfAnimation` of the file; skins: the `GltfSkin`s the scene's meshes
            use (by index); nodes: `GltfNodes`, every node's parent and rest transform.
        time, animation: the time (seconds) and the index of the animation the primitives are
            posed at (None, None: the rest pose, skins and default morph weights applied).
    """

    path: Path
    generator: str
    version: str
    scene: int | None
    primitives: list[GltfPrimitive]
    materials: list[GltfMaterial]
    images: list[GltfImage]
    lights: list[GltfLight]
    cameras: list[GltfCamera]
    bounds: np.ndarray | None
    extensions_used: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    animations: tuple = ()
    skins: dict = field(default_factory=dict)
    nodes: GltfNodes | None = None
    time: float | None = None
    animation: int | None = None

    def summary(self) -> dict[str, Any]:
        """Counts: primitives, triangles, vertices, materials, images, textured slots, lights, cameras."""
        return {
            "primitives": len(self.primitives),
            "triangles": int(sum(p.num_triangles for p in self.primitives)),
            "vertices": int(sum(p.num_vertices for p in self.primitives)),
            "materials": len(self.materials),
            "images": len(self.images),
            "texture_slots": int(sum(len(m.textures) for m in self.materials)),
            "lights": len(self.lights),
            "cameras": len(self.cameras),
            "bounds": None if self.bounds is None else self.bounds.tolist(),
            "generator": self.generator,
        }

    def __repr__(self) -> str:
        s = self.summary()
        return (
            f"GltfAsset({str(self.path)!r}: {s['primitives']} primitives, {s['triangles']} triangles, "
            f"{s['materials']} materials, {s['images']} images, {s['lights']} lights, {s['cameras']} cameras)"
        )
