"""glTF 2.0 assets as scenes: `load_gltf(path, ...)` -> a `Scene` that `jaxpbr.render` draws.

The file is read by `jaxpbr.io.gltf.read_gltf` (NumPy, world space); here its primitives become
`Mesh` objects (one per material: every primitive of a material shares one mesh), its materials
`Material` / `TexturedMaterial` objects (the same classes and validation as scenes built by hand
or from TOML), its KHR_lights_punctual lights jaxpbr lights (same units: candela, lux), and a
camera is chosen: the one given, else the asset's first camera, else a framing of its bounds.

Textures become `TextureSlot`s: a mip-mapped `Texture` with the file's sampler (wrap and filter
modes), the texture-coordinate set and the KHR_texture_transform of the slot; colour textures
(base colour, emissive, sheen colour, specular colour) are decoded from sRGB before filtering,
data textures are filtered as stored, and the occlusion texture carries its strength
(1 + strength (R - 1)). What the scene does not reproduce is listed in `GltfScene.notes` and warned
once. alphaMode, alphaCutoff and baseColorFactor's alpha
go to the `Mesh` (MASK cut-outs in visibility and shadows, BLEND layers composited).
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.gltf import GltfAsset, GltfMaterial, read_gltf
from ..shading.lights import DirectionalLight, PointLight, SpotLight
from ..shading.material import Material
from .mesh import Mesh
from .scene import Camera, Scene, TexturedMaterial, TextureSlot
from .texture import Texture

__all__ = ["GltfScene", "load_gltf", "frame_bounds", "material_groups", "scene_from_asset"]

#: glTF texture role -> TexturedMaterial field (and the channels it reads are the glTF ones).
_TEXTURE_FIELDS = {
    "base_color": "base_color_texture",
    "metallic_roughness": "metallic_roughness_texture",
    "occlusion": "occlusion_texture",
    "normal": "normal_texture",
    "emissive": "emissive_texture",
    "clearcoat": "clearcoat_texture",
    "clearcoat_roughness": "clearcoat_roughness_texture",
    "clearcoat_normal": "clearcoat_normal_texture",
    "sheen_color": "sheen_color_texture",
    "sheen_roughness": "sheen_roughness_texture",
    "specular": "specular_texture",
    "specular_color": "specular_color_texture",
    "anisotropy": "anisotropy_texture",
    "transmission": "transmission_texture",
    "thickness": "thickness_texture",
}


@dataclass(eq=False)
class GltfScene:
    """A glTF asset ready to render: `scene` (a `jaxpbr.Scene`), the `asset` it came from
    (`jaxpbr.io.gltf.GltfAsset`), and `notes`: what of the asset the scene does not reproduce."""

    scene: Scene
    asset: GltfAsset
    notes: tuple[str, ...] = field(default=())
    #: for each of scene.objects made from the asset's primitives, their indices in
    #: `asset.primitives` in the order the mesh concatenates them (what `posed_scene` re-poses)
    layout: tuple[tuple[int, ...], ...] = field(default=())


def frame_bounds(lo, hi, *, fov_y_deg: float = 45.0, aspect: float = 16 / 9, direction=(0.45, 0.35, 1.0)) -> Camera:
    """A camera looking at the centre of the box [lo, hi] from `direction` (towards the camera),
    far enough that the box's bounding sphere fills the smaller field of view with a 5 % margin."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c = 0.5 * (lo + hi)
    r = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    half = math.radians(fov_y_deg) / 2
    half = min(half, math.atan(math.tan(half) * aspect))
    dist = 1.05 * r / math.sin(half)
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    return c + dist * d, c


def _texture_slot(asset: GltfAsset, mat: GltfMaterial, role: str) -> TextureSlot:
    """The material slot of a glTF texture: its image as a mip-mapped `Texture` (sRGB-decoded for
    colour roles, before filtering), its sampler, texture-coordinate set and transform."""
    ref = mat.textures[role]
    px = np.asarray(asset.images[ref.image].pixels, np.float32)
    if px.shape[-1] == 1:
        px = np.repeat(px, 3, -1)
    elif px.shape[-1] == 2:  # luminance + alpha
        px = np.concatenate([np.repeat(px[..., :1], 3, -1), px[..., 1:]], -1)
    if role in ("sheen_roughness", "specular") and px.shape[-1] == 3:
        px = np.concatenate([px, np.ones_like(px[..., :1])], -1)  # read from A: an opaque image's A is 1
    if role == "occlusion" and ref.strength != 1.0:
        # occlusion = 1 + strength (R - 1): linear in R, so it commutes with the filtering.
        px = 1.0 + np.float32(ref.strength) * (px - 1.0)
    s = ref.sampler
    tex = Texture.from_image(
        px, srgb=ref.colorspace == "srgb", wrap_s=s.wrap_s, wrap_t=s.wrap_t, mag_filter=s.mag_filter,
        min_filter=s.min_filter,
    )
    transform = np.asarray(ref.transform, np.float32) if ref.has_transform else None
    return TextureSlot(texture=tex, texcoord=int(ref.texcoord), transform=transform)


def material_from_gltf(asset: GltfAsset, mat: GltfMaterial, notes: set):
    """The jaxpbr material of a glTF material: `Material(**factors)`, or a `TexturedMaterial`
    holding it and the textures (linear, decoded)."""
    factors = Material(**mat.factors)
    if not mat.textures:
        return factors
    tex = {}
    for role in mat.textures:
        name = _TEXTURE_FIELDS.get(role)
        if name is None:
            continue
        tex[name] = _texture_slot(asset, mat, role)
    if "normal" in mat.textures:
        tex["normal_scale"] = float(mat.textures["normal"].scale)
    if "clearcoat_normal" in mat.textures:
        tex["clearcoat_normal_scale"] = float(mat.textures["clearcoat_normal"].scale)
    return TexturedMaterial(factors=factors, **tex)


def _concat(prims, name, width, fill):
    arrs = [getattr(p, name) for p in prims]
    if all(a is None for a in arrs):
        return None
    return _read_only(np.concatenate([
        np.asarray(a, np.float32) if a is not None else np.broadcast_to(np.float32(fill), (p.num_vertices, width))
        for a, p in zip(arrs, prims)
    ]))


def _read_only(a: np.ndarray) -> np.ndarray:
    """A new array handed to a Mesh as it is: read-only, so the Mesh keeps it without a copy."""
    a.setflags(write=False)
    return a


def material_groups(asset: GltfAsset) -> dict[int, list[int]]:
    """{material: the indices of its primitives}, materials in order of first use: one Mesh each."""
    by_mat: dict[int, list[int]] = {}
    for k, p in enumerate(asset.primitives):
        by_mat.setdefault(p.material, []).append(k)
    return by_mat


def meshes_from_asset(asset: GltfAsset, notes: set, material_cache: dict | None = None) -> list[Mesh]:
    """One Mesh per material of the asset's primitives (world space), in `material_groups` order.
    material_cache: {material index: jaxpbr material} kept by the caller across poses of one asset
    (its textures' mip pyramids are made once)."""
    meshes = []
    for mi, idx in material_groups(asset).items():
        prims = [asset.primitives[k] for k in idx]
        gm = asset.materials[mi]
        offs = np.cumsum([0] + [p.num_vertices for p in prims])
        tris = _read_only(np.concatenate([np.asarray(p.indices, np.int32) + int(offs[k]) for k, p in enumerate(prims)]))
        meshes.append(Mesh(
            positions=_read_only(np.concatenate([np.asarray(p.positions, np.float32) for p in prims])),
            triangles=tris,
            normals=_concat(prims, "normals", 3, (0.0, 0.0, 1.0)),
            texcoords=_concat(prims, "texcoord_0", 2, (0.0, 0.0)),
            texcoords1=_concat(prims, "texcoord_1", 2, (0.0, 0.0)),
            tangents=_concat(prims, "tangents", 4, (1.0, 0.0, 0.0, 1.0)),
            colors=_concat(prims, "color_0", 4, (1.0, 1.0, 1.0, 1.0)),
            material=_material(asset, mi, gm, notes, material_cache),
            double_sided=gm.double_sided,
            alpha_mode=gm.alpha_mode,
            alpha_cutoff=gm.alpha_cutoff,
            alpha=float(gm.base_color_alpha),
            unlit=gm.unlit,
        ))
    return meshes


def _material(asset, mi, gm, notes, cache):
    if cache is None:
        return material_from_gltf(asset, gm, notes)
    if mi not in cache:
        cache[mi] = material_from_gltf(asset, gm, notes)
    return cache[mi]


def lights_from_asset(asset: GltfAsset) -> list:
    out = []
    for lt in asset.lights:
        rng = None if not math.isfinite(lt.range) else float(lt.range)
        color = tuple(float(c) for c in lt.color)
        if lt.type == "directional":
            out.append(DirectionalLight(direction=tuple(lt.direction), color=color, intensity=float(lt.intensity)))
        elif lt.type == "point":
            out.append(PointLight(tuple(lt.position), color=color, intensity=float(lt.intensity), range=rng))
        else:
            out.append(SpotLight(
                tuple(lt.position), tuple(lt.direction), color=color, intensity=float(lt.intensity),
                inner_cone_angle=float(lt.inner_cone_angle), outer_cone_angle=float(lt.outer_cone_angle), range=rng,
            ))
    return out


def environment_from(spec, *, intensity: float | None = None, rotation: float | None = None):
    """The `Environment` a user names, as every entry point reads it (`load_gltf`, `jaxpbr render
    --environment`, batch jobs): None (none), an `Environment` (as it is), a `Cubemap` of radiance
    (what `jaxpbr.load_environment` returns: its environment), "procedural:sky" (the
    demo's sky at `cubeio.PROCEDURAL_FACE_SIZE`, the baked set the package ships: a render
    precomputes nothing), or an environment file (`jaxpbr.load_environment`: a 2:1 .hdr/.exr
    panorama, or six face images), then turned by `rotation` (radians about +Y) and scaled by
    `intensity` where given (None keeps the environment's own, 0 and 1 for a new one)."""
    from ..ibl.cubeio import load_environment
    from ..ibl.cubemap import Cubemap
    from .demo import demo_environment
    from .scene import Environment

    if spec is None:
        return None
    if isinstance(spec, Environment):
        env = spec
    elif isinstance(spec, Cubemap):
        env = Environment(radiance=spec)
    elif isinstance(spec, str) and spec == "procedural:sky":
        env = demo_environment()
    elif isinstance(spec, (str, os.PathLike)) or (isinstance(spec, (list, tuple)) and all(isinstance(p, (str, os.PathLike)) for p in spec)):
        env = Environment(radiance=load_environment(spec))
    else:
        raise InputError(f"environment must be None, an Environment, a Cubemap (jaxpbr.load_environment), \"procedural:sky\" "
                         f"or an environment file (a path, or six face paths), got {type(spec).__name__}")
    changes = {k: v for k, v in (("intensity", intensity), ("rotation", rotation)) if v is not None}
    return env.replace(**changes) if changes else env


def _asset_camera(asset: GltfAsset, width: int, height: int, notes: set, *, position=None, target=None, fov_y_deg=None,
                  supersample: int = 1) -> Camera:
    """The camera rules of every entry point (`load_gltf`, `jaxpbr render ASSET`, batch jobs):
    without overrides, the asset's first camera (perspective or orthographic) at width x height,
    else a perspective camera framing the asset's bounds from the front-right, above, with a
    45-degree vertical field of view. Overrides (`position`, `target`, `fov_y_deg`) make a
    perspective camera: what is not given comes from the asset's first perspective camera (its
    pose when neither position nor target is given, its field of view), else from the framing."""
    aspect = width / height
    size = {"width": width, "height": height, "supersample": supersample}
    overridden = position is not None or target is not None or fov_y_deg is not None
    cam = asset.cameras[0] if asset.cameras else None
    if cam is not None and not overridden:
        pose = {"position": tuple(cam.position), "target": tuple(cam.position + cam.forward), "up": tuple(cam.up), **size}
        if cam.type == "orthographic":
            # glTF's xmag and ymag are the view's half width and height; the image's aspect
            # ratio sets the width (as for a perspective camera's aspectRatio).
            if abs(abs(cam.xmag) / abs(cam.ymag) - aspect) > 1e-3:
                notes.add(f"the orthographic camera's xmag/ymag {abs(cam.xmag) / abs(cam.ymag):.4g} differs from the image's "
                          f"aspect ratio {aspect:.4g}: ymag (the view's height) is kept")
            return Camera(projection="orthographic", ymag=abs(cam.ymag), **pose)
        if cam.aspect_ratio is not None and abs(cam.aspect_ratio - aspect) > 1e-3:
            notes.add(f"the camera's aspectRatio {cam.aspect_ratio:.4g} differs from the image's {aspect:.4g}: the vertical field of view is kept")
        return Camera(fov_y_deg=math.degrees(cam.yfov), **pose)
    first = next((c for c in asset.cameras if c.type == "perspective"), None)
    fov = fov_y_deg if fov_y_deg is not None else (math.degrees(first.yfov) if first is not None else 45.0)
    up = (0.0, 1.0, 0.0)
    if first is not None and position is None and target is None:
        pos, tgt, up = first.position, first.position + first.forward, tuple(first.up)
    else:
        pos, tgt = frame_bounds(asset.bounds[0], asset.bounds[1], fov_y_deg=fov, aspect=aspect)
    return Camera(position=tuple(pos if position is None else position), target=tuple(tgt if target is None else target),
                  up=up, fov_y_deg=fov, **size)


def scene_from_asset(
    asset: GltfAsset,
    *,
    camera: Camera | None = None,
    width: int = 1280,
    height: int = 720,
    camera_position=None,
    camera_target=None,
    fov_y_deg: float | None = None,
    supersample: int = 1,
    environment=None,
    environment_intensity: float | None = None,
    environment_rotation: float | None = None,
    lights=(),
    asset_lights: bool = True,
    background=(0.0, 0.0, 0.0),
    material_cache: dict | None = None,
) -> GltfScene:
    """The `GltfScene` of a loaded asset; see `load_gltf`. material_cache: a dict kept across calls
    for poses of one asset (`jaxpbr.io.gltf.posed_asset`): its materials and textures are made once."""
    if not asset.primitives:
        raise InputError(f"glTF file {str(asset.path)!r} has no triangle geometry in the scene loaded; pick another scene (scene=N)")
    notes: set[str] = set()
    meshes = meshes_from_asset(asset, notes, material_cache)
    if camera is None:
        camera = _asset_camera(asset, width, height, notes, position=camera_position, target=camera_target,
                               fov_y_deg=fov_y_deg, supersample=supersample)
    environment = environment_from(environment, intensity=environment_intensity, rotation=environment_rotation)
    all_lights = (lights_from_asset(asset) if asset_lights else []) + list(lights)
    scene = Scene(camera=camera, objects=tuple(meshes), lights=tuple(all_lights), environment=environment, background=background)
    notes = tuple(sorted(notes))
    if notes:
        warnings.warn(f"{Path(asset.path).name}: " + "; ".join(notes), UserWarning, stacklevel=3)
    return GltfScene(scene=scene, asset=asset, notes=notes, layout=tuple(tuple(v) for v in material_groups(asset).values()))


def load_gltf(
    path,
    *,
    scene: int | None = None,
    camera: Camera | None = None,
    width: int = 1280,
    height: int = 720,
    camera_position=None,
    camera_target=None,
    fov_y_deg: float | None = None,
    supersample: int = 1,
    environment=None,
    environment_intensity: float | None = None,
    environment_rotation: float | None = None,
    lights=(),
    asset_lights: bool = True,
    background=(0.0, 0.0, 0.0),
    roots=(),
    time: float | None = None,
    animation=None,
) -> Scene:
    """A glTF 2.0 asset (.gltf or .glb) as a `Scene` that `jaxpbr.render` draws. The command line
    (`jaxpbr render ASSET`) and batch jobs build their scenes with the same rules (`scene_from_asset`).

    scene: which scene of the file (default: the file's default scene).
    camera: a `Camera`; default the asset's first camera (with width x height), else a camera
        framing the asset's bounds from the front-right, above (45-degree field of view).
        camera_position, camera_target, fov_y_deg: a perspective camera with these; what is not
        given comes from the asset's first perspective camera, else from the framing.
        supersample: the camera's samples per pixel side.
    environment: image-based lighting and background: an `Environment`, "procedural:sky" (the
        demo's sky, the baked set the package ships), an environment file (a 2:1 .hdr/.exr
        panorama, or six face images), or None; environment_rotation (radians about +Y) and
        environment_intensity replace its rotation and intensity where given.
    lights: extra lights added to the asset's own KHR_lights_punctual lights (`asset_lights=False`
        leaves those out).
    roots: folders besides the asset's own that its buffer and image URIs may name (by default
        an asset reads only regular files inside its own folder; docs/gltf.md, "Untrusted assets").
    time, animation: the asset posed at `time` seconds of `animation` (an index or a name; default
        the first): node transforms, skins and morph weights, its cameras and lights with them
        (glTF 2.0 §3.11). Without them, the rest pose (skins and default morph weights applied).
        `posed_scene` poses a loaded scene again inside JAX (differentiable, vmappable).
    The asset itself (materials, images, counts) is `jaxpbr.io.gltf.read_gltf(path)`;
    `scene_from_asset` builds the scene from one already read and also returns what the scene
    does not reproduce (`GltfScene.notes`, also warned).
    """
    from .plan import mesh_engine

    asset = read_gltf(path, scene=scene, roots=roots, ray_engine=mesh_engine(), time=time, animation=animation)
    return scene_from_asset(
        asset, camera=camera, width=width, height=height, camera_position=camera_position, camera_target=camera_target,
        fov_y_deg=fov_y_deg, supersample=supersample, environment=environment, environment_intensity=environment_intensity,
        environment_rotation=environment_rotation, lights=lights, asset_lights=asset_lights, background=background,
    ).scene
