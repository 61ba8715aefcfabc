"""Scene description: camera, analytic spheres and planes, textured materials, environment, G-buffer.

Everything here is a JAX pytree whose array fields are leaves (so a scene can be differentiated,
vmapped over a batch axis or passed through `jax.jit`) and whose structure -- which objects, which
textures, image size -- is static. The types are declared with `jaxpbr._pytree` (each field once,
as `leaf(rank=...)`, `subtree()` or `static()`; validation in each class's `_validate`).
`jaxpbr.rendering.renderer.render` turns a `Scene` into linear HDR radiance; this module holds the data types
and the geometry (primary rays, ray casting, surface attributes).

Conventions (docs/conventions.md): right-handed, +Y up, the camera looks from `position` to `target`; pixel
(i, j) has row i from the top. Texture coordinates follow glTF: uv = (0, 0) is the top-left corner
of the image (row 0), u to the right, v down; texel (i, j) sits at ((j + 0.5)/W, (i + 0.5)/H);
lookups are bilinear with repeat wrapping. Tangent frames: T = dP/du (normalised), B = N x T, so a
tangent-space normal map's +Y points towards decreasing v ("up" in the image), the glTF / OpenGL
convention.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._api import keyword_only
from .._numerics import (
    as_float,
    is_concrete,
    safe_div,
    safe_sqrt,
    small_sq,
    vcross,
    vdot,
    vnormalize,
)
from .._pytree import Pytree, leaf, static, subtree
from .._validate import check_radiance, check_values, positive_int, vector
from ..ibl.cubemap import Cubemap
from ..shading.lights import DirectionalLight, LightSet, PointLight, SpotLight
from ..shading.material import Material
from .textured import (  # noqa: F401  (re-exported: the scene's material types)
    EXTENSION_TEXTURES,
    TexturedMaterial,
    TextureSlot,
    apply_extension_textures,
    sample_texture,
    texels,
)

__all__ = [
    "Camera",
    "Environment",
    "GBuffer",
    "Plane",
    "Scene",
    "Sphere",
    "TexturedMaterial",
    "apply_extension_textures",
    "primary_rays",
    "sample_texture",
    "TextureSlot",
]


def _vec(name: str, x, n: int = 3) -> jax.Array:
    return check_values(name, vector(name, x, n))


def _scalar(name: str, x, *, lo=None, hi=None, open_lo=False) -> jax.Array:
    return check_values(name, as_float(x), lo=lo, hi=hi, open_lo=open_lo)


# ------------------------------------------------------------------------------------------
# Camera
# ------------------------------------------------------------------------------------------


#: Largest `Camera.supersample`: s^2 passes of the whole image, run one after another; at 64
#: (4096 per pixel) a pixel's edge coverage already comes in steps finer than any 8- or 12-bit
#: output resolves, and 100000 started 1e10 passes without a word.
MAX_SUPERSAMPLE = 64


#: `Camera.projection` values.
PROJECTIONS = ("perspective", "orthographic")


class Camera(Pytree):
    """Pinhole perspective or orthographic camera.

    position, target, up: (3,) world-space points / vector (leaves: may be batched or traced).
    fov_y_deg: vertical field of view in degrees (leaf; perspective).
    projection: "perspective" (rays from `position` through the image plane) or "orthographic"
        (static): parallel rays along target - position, from the plane through `position`
        perpendicular to it, over a view 2 ymag high and 2 ymag width/height wide (glTF's
        orthographic camera; its xmag follows from the image's aspect ratio).
    ymag: half the orthographic view's height in world units (leaf; orthographic).
    width, height: image size in pixels (static).
    supersample: s -> s x s stratified samples per pixel, averaged in linear HDR (static).
    jitter: (2,) sub-pixel offset in pixels added to every sample (leaf), e.g. for progressive or
        temporal accumulation; (0, 0) samples the pixel (or sub-cell) centres.
    """

    position: Any = leaf((0.0, 0.0, 24.0), rank=1)
    target: Any = leaf((0.0, 0.0, 0.0), rank=1)
    up: Any = leaf((0.0, 1.0, 0.0), rank=1)
    fov_y_deg: Any = leaf(45.0)
    projection: str = static("perspective")
    ymag: Any = leaf(1.0)
    width: int = static(1280)
    height: int = static(720)
    supersample: int = static(1)
    jitter: Any = leaf((0.0, 0.0), rank=1)

    def _validate(self) -> None:
        positive_int("Camera.width", self.width)
        positive_int("Camera.height", self.height)
        positive_int("Camera.supersample", self.supersample)
        if self.supersample > MAX_SUPERSAMPLE:
            raise ValueError(
                f"Camera.supersample must be <= {MAX_SUPERSAMPLE} ({MAX_SUPERSAMPLE}^2 samples per pixel, one pass of the "
                f"whole image each), got {self.supersample}; 4 to 16 is plenty for anti-aliasing"
            )
        pos = _vec("Camera.position", self.position)
        tgt = _vec("Camera.target", self.target)
        up = _vec("Camera.up", self.up)
        fov = _scalar("Camera.fov_y_deg", self.fov_y_deg, lo=0.0, open_lo=True, hi=179.0)
        if self.projection not in PROJECTIONS:
            raise ValueError(f"Camera.projection must be one of {', '.join(PROJECTIONS)}, got {self.projection!r}")
        ymag = _scalar("Camera.ymag", self.ymag, lo=0.0, open_lo=True)
        jit = _vec("Camera.jitter", self.jitter, 2)
        if all(is_concrete(x) for x in (pos, tgt, up)):
            f = np.asarray(tgt, np.float64) - np.asarray(pos, np.float64)
            if np.any(np.linalg.norm(f, axis=-1) == 0):
                raise ValueError("Camera.target must differ from Camera.position")
            if np.any(np.linalg.norm(np.cross(f, np.asarray(up, np.float64)), axis=-1) < 1e-12):
                raise ValueError("Camera.up must not be parallel to the viewing direction; pick another up")
        self._set(position=pos, target=tgt, up=up, fov_y_deg=fov, ymag=ymag, jitter=jit)


def camera_basis(cam: Camera, dtype):
    """(position, forward, right, up) unit Vec3s of the camera frame."""
    pos = tuple(jnp.asarray(cam.position, dtype)[..., i] for i in range(3))
    tgt = tuple(jnp.asarray(cam.target, dtype)[..., i] for i in range(3))
    upv = tuple(jnp.asarray(cam.up, dtype)[..., i] for i in range(3))
    fwd = vnormalize(tuple(t - p for t, p in zip(tgt, pos)))
    right = vnormalize(vcross(fwd, upv))
    up = vcross(right, fwd)
    return pos, fwd, right, up


@keyword_only("dtype", "offset")
def primary_rays(cam: Camera, *, dtype=jnp.float32, offset=(0.5, 0.5), rows: int = 0):
    """Ray origins and unit directions of every pixel, each (H, W, 3).

    offset: sample position inside the pixel in pixel units ((0.5, 0.5) = centre), to which
    `cam.jitter` is added. Perspective: pixel (i, j) looks from the camera's position through
    x = (2 (j + ox)/W - 1) tan(fov/2) aspect, y = (1 - 2 (i + oy)/H) tan(fov/2) on the image plane
    at distance 1. Orthographic: the ray of pixel (i, j) starts at position + x right + y up with
    x = (2 (j + ox)/W - 1) ymag aspect, y = (1 - 2 (i + oy)/H) ymag, along the viewing direction.
    rows: 0 for the whole image; otherwise only the band of `rows` image rows starting at row
    offset[2] (possibly traced; rows past the image bottom continue the projection), (rows, W, 3).
    """
    pos, fwd, right, up = camera_basis(cam, dtype)
    W, H = cam.width, cam.height
    ortho = cam.projection == "orthographic"
    t = jnp.asarray(cam.ymag, dtype) if ortho else jnp.tan(jnp.deg2rad(jnp.asarray(cam.fov_y_deg, dtype)) / 2)
    jit = jnp.asarray(cam.jitter, dtype)
    x = (2.0 * (jnp.arange(W, dtype=dtype) + offset[0] + jit[0]) / W - 1.0) * t * (W / H)
    i = jnp.arange(H, dtype=dtype) if not rows else jnp.arange(rows, dtype=dtype) + offset[2]
    y = (1.0 - 2.0 * (i + offset[1] + jit[1]) / H) * t
    x = x[None, :]
    y = y[:, None]
    shape = (y.shape[0], W)
    if ortho:
        o = jnp.stack([jnp.broadcast_to(pos[i] + x * right[i] + y * up[i], shape) for i in range(3)], -1)
        d = jnp.broadcast_to(jnp.stack(fwd), o.shape)
        return o, d
    d = vnormalize(tuple(fwd[i] + x * right[i] + y * up[i] for i in range(3)))
    d = jnp.stack([jnp.broadcast_to(c, shape) for c in d], -1)
    o = jnp.broadcast_to(jnp.stack(pos), d.shape)
    return o, d


# ------------------------------------------------------------------------------------------
# Geometry
# ------------------------------------------------------------------------------------------


def _check_material(owner: str, m):
    if not isinstance(m, (Material, TexturedMaterial)):
        raise TypeError(f"{owner}.material must be a Material or TexturedMaterial, got {type(m).__name__}")


class Sphere(Pytree):
    """Analytic sphere. uv: u = 0.5 + atan2(n.x, n.z)/(2 pi) (u = 0.5 faces +Z, growing towards +X),
    v = 0.5 - asin(n.y)/pi (v = 0 at the north pole, +Y); T = dP/du."""

    center: Any = leaf((0.0, 0.0, 0.0), rank=1)
    radius: Any = leaf(1.0)
    material: Any = subtree(default_factory=Material)

    def _validate(self) -> None:
        _check_material("Sphere", self.material)
        self._set(center=_vec("Sphere.center", self.center), radius=_scalar("Sphere.radius", self.radius, lo=0.0, open_lo=True))


class Plane(Pytree):
    """Infinite plane through `point` with normal `normal`, shaded on the side facing the camera.

    tangent: direction of +u in the plane (projected onto it and normalised); default: the world
    axis least aligned with the normal, orthogonalised. uv = (dot(p - point, T), -dot(p - point, B))
    * uv_scale, B = N x T (so an upright image is not mirrored when seen from the normal's side).
    """

    point: Any = leaf((0.0, 0.0, 0.0), rank=1)
    normal: Any = leaf((0.0, 1.0, 0.0), rank=1)
    material: Any = subtree(default_factory=Material)
    tangent: Any = leaf(None, rank=1)
    uv_scale: Any = leaf(1.0)

    def _validate(self) -> None:
        _check_material("Plane", self.material)
        n = _vec("Plane.normal", self.normal)
        if is_concrete(n) and np.any(np.linalg.norm(np.asarray(n), axis=-1) == 0):
            raise ValueError("Plane.normal must be non-zero")
        t = self.tangent
        if t is None:  # the world axis least aligned with n, made orthogonal to it (jnp: works traced)
            nn = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
            axis = jnp.eye(3, dtype=nn.dtype)[jnp.argmin(jnp.abs(nn), axis=-1)]
            t = axis - nn * jnp.sum(nn * axis, -1, keepdims=True)
            t = t / jnp.linalg.norm(t, axis=-1, keepdims=True)
        t = _vec("Plane.tangent", t)
        self._set(point=_vec("Plane.point", self.point), normal=n, tangent=t, uv_scale=_scalar("Plane.uv_scale", self.uv_scale))


# ------------------------------------------------------------------------------------------
# Environment, G-buffer, Scene
# ------------------------------------------------------------------------------------------


class Environment(Pytree):
    """Distant lighting from a cube map, also drawn as the background.

    radiance: Cubemap of linear radiance (level 0 is used; mips are rebuilt).
    intensity: scalar multiplier (leaf).
    rotation: rotation of the environment about +Y in radians (leaf): the radiance seen in world
        direction d is radiance(R_y(-rotation) d). Rotations need no new precompute.
    show_background: draw the environment where rays miss (static); else Scene.background.
    irradiance, prefiltered: optional precomputed maps (E/pi and LD mips) to use instead of
        computing them from `radiance` (e.g. loaded from disk, or to differentiate through them).
    lut, lut_smith: optional split-sum LUT (n_r, n_nov, 2) and the Smith variant it was computed
        for (static; `brdf_terms.MODEL_REGISTRY[model].lut_smith`); a render with a model whose
        variant differs raises. `jaxpbr.bake(environment)` fills irradiance, prefiltered and lut.
    lights: optional tuple of disc `DirectionalLight`s split out of the environment (`jaxpbr.ibl.extract`),
        in the environment's frame and units (rotation and intensity apply to them too). Set by
        `bake` (or a user who split the lights: `radiance` and the maps are then the residual);
        when None and no map is given, `render` extracts them itself (`RenderOptions.extract_lights`).
    charlie, sheen_lut: optional Charlie-prefiltered Cubemap (`jaxpbr.ibl.sheen_prefilter`) and sheen
        albedo table (n_r, n_nov) (`jaxpbr.shading.sheen_lut`), read by materials with KHR_materials_sheen;
        `bake` fills them, `render` computes them only for a scene that has sheen.
    """

    radiance: Any = subtree(None)
    intensity: Any = leaf(1.0)
    rotation: Any = leaf(0.0)
    show_background: bool = static(True)
    irradiance: Any = subtree(None)
    prefiltered: Any = subtree(None)
    lut: Any = leaf(None, rank=3)
    lut_smith: str | None = static(None)
    lights: Any = subtree(None)
    charlie: Any = subtree(None)
    sheen_lut: Any = leaf(None, rank=2)

    @property
    def baked(self) -> bool:
        """True when the precomputed assets are all present (`jaxpbr.bake`): a render needs no
        precompute of this environment."""
        return self.irradiance is not None and self.prefiltered is not None and self.lut is not None

    def _validate(self) -> None:
        if not isinstance(self.radiance, Cubemap):
            raise TypeError(
                "Environment.radiance must be a jaxpbr.Cubemap (e.g. Cubemap.from_equirect(img, face_size=128))"
            )
        for name in ("irradiance", "prefiltered", "charlie"):
            x = getattr(self, name)
            if x is not None and not isinstance(x, Cubemap):
                raise TypeError(f"Environment.{name} must be a Cubemap or None")
        if self.sheen_lut is not None:
            t = jnp.asarray(self.sheen_lut)
            if t.ndim != 2:
                raise ValueError(f"Environment.sheen_lut must be an (n_r, n_nov) sheen albedo table, got shape {t.shape}")
            self._set(sheen_lut=t)
        for name in ("radiance", "irradiance", "prefiltered", "charlie"):
            cube = getattr(self, name)
            if cube is not None:
                for m, lv in enumerate(cube.levels):
                    check_radiance(f"Environment.{name}.levels[{m}]", lv)
        if self.lut is not None:
            lut = jnp.asarray(self.lut)
            if lut.ndim != 3 or lut.shape[-1] != 2:
                raise ValueError(f"Environment.lut must be an (n_r, n_nov, 2) split-sum LUT, got shape {lut.shape}")
            if self.lut_smith is None:
                raise ValueError(
                    "Environment.lut needs lut_smith, the Smith variant it was computed for "
                    "('correlated' for gltf, 'schlick_ggx' for learnopengl); jaxpbr.bake sets both"
                )
            self._set(lut=lut)
        self._set(
            intensity=_scalar("Environment.intensity", self.intensity, lo=0.0),
            rotation=_scalar("Environment.rotation", self.rotation),
        )


class GBuffer(Pytree):
    """Per-pixel surface data from the user's own rasteriser (or the ray caster).

    hit: (H, W) bool, False where no surface (background); position, normal (shading normal),
    view (unit direction to the viewer): (H, W, 3); material: `Material` with (H, W) leaves.
    """

    hit: Any = leaf(rank=2)
    position: Any = leaf(rank=3)
    normal: Any = leaf(rank=3)
    view: Any = leaf(rank=3)
    material: Any = subtree()

    def _validate(self) -> None:
        if not isinstance(self.material, Material):
            raise TypeError("GBuffer.material must be a Material with per-pixel (H, W[, 3]) leaves")
        hit = jnp.asarray(self.hit)
        if hit.dtype != jnp.bool_ or hit.ndim != 2:
            raise ValueError(f"GBuffer.hit must be an (H, W) bool array, got {hit.dtype} {hit.shape}")
        vals = {}
        for name in ("position", "normal", "view"):
            x = _vec(f"GBuffer.{name}", getattr(self, name))
            if x.shape != hit.shape + (3,):
                raise ValueError(f"GBuffer.{name} has shape {x.shape}; expected {hit.shape + (3,)}")
            vals[name] = x
        self._set(hit=hit, **vals)

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.hit.shape)


_LIGHT_TYPES = (PointLight, DirectionalLight, SpotLight, LightSet)


class Scene(Pytree):
    """Camera + geometry (analytic `objects` or a user `gbuffer`) + lights + optional environment.

    objects: sequence of Sphere / Plane / Mesh; gbuffer: a GBuffer instead (then `camera` is optional).
    lights: sequence of PointLight / DirectionalLight / SpotLight (or a LightSet).
    environment: Environment or None (no image-based lighting).
    background: (3,) linear radiance where nothing is hit and no environment is shown.
    ambient: LearnOpenGL's constant `ambient * albedo * ao` term (static; 0 = off, the default).
    """

    camera: Any = subtree(None)
    objects: Any = subtree(())
    lights: Any = subtree(())
    environment: Any = subtree(None)
    gbuffer: Any = subtree(None)
    background: Any = leaf((0.0, 0.0, 0.0), rank=1)
    ambient: float = static(0.0)

    def _validate(self) -> None:
        objects = tuple(self.objects) if isinstance(self.objects, (list, tuple)) else (self.objects,)
        lights = self.lights
        if isinstance(lights, _LIGHT_TYPES):
            lights = (lights,)
        lights = tuple(lights)
        from .mesh import Mesh

        for x in objects:
            if not isinstance(x, (Sphere, Plane, Mesh)):
                raise TypeError(f"Scene.objects must hold Sphere, Plane or Mesh, got {type(x).__name__}")
        for x in lights:
            if not isinstance(x, _LIGHT_TYPES):
                raise TypeError(
                    f"Scene.lights must hold PointLight, DirectionalLight or SpotLight, got {type(x).__name__}"
                )
        if self.gbuffer is None and not objects:
            raise ValueError("a Scene needs objects (spheres/planes) or a gbuffer")
        if self.gbuffer is not None and objects:
            raise ValueError("give a Scene either objects or a gbuffer, not both")
        if self.gbuffer is not None and not isinstance(self.gbuffer, GBuffer):
            raise TypeError("Scene.gbuffer must be a GBuffer")
        if objects and not isinstance(self.camera, Camera):
            raise ValueError("a Scene with objects needs a Camera")
        if self.environment is not None and not isinstance(self.environment, Environment):
            raise TypeError("Scene.environment must be an Environment or None")
        if not isinstance(self.ambient, (int, float)) or not math.isfinite(self.ambient) or self.ambient < 0:
            raise ValueError(f"Scene.ambient must be a finite number >= 0, got {self.ambient!r}")
        self._set(objects=objects, lights=lights, background=_vec("Scene.background", self.background), ambient=float(self.ambient))

    @property
    def image_shape(self) -> tuple[int, int]:
        if self.gbuffer is not None:
            return self.gbuffer.shape
        return (self.camera.height, self.camera.width)


# ------------------------------------------------------------------------------------------
# Ray casting
# ------------------------------------------------------------------------------------------


def intersect_sphere(o, d, center, radius):
    """Nearest positive hit distance t (...) and a validity mask of rays o + t d (Vec3s, |d| = 1).

    b = (o - c).d, c' = |o - c|^2 - R^2, disc = b^2 - c'. The far root t1 = -b + sqrt(disc) has no
    cancellation for a sphere in front (b < 0); the near root is t0 = c'/t1 (t0 t1 = c'). Inside the
    sphere (c' < 0) the far root is the hit.
    """
    oc = tuple(o[i] - center[i] for i in range(3))
    b = vdot(oc, d)
    c = vdot(oc, oc) - radius * radius
    disc = b * b - c
    t1 = -b + safe_sqrt(disc)
    pos = t1 > 0
    t0 = safe_div(c, t1, pos)
    t = jnp.where(c > 0, t0, t1)
    ok = (disc > 0) & pos & (t > 0)
    return t, ok


def intersect_plane(o, d, point, normal):
    """Hit distance of rays with the plane through `point` with normal `normal` (any length)."""
    denom = vdot(d, normal)
    num = vdot(tuple(point[i] - o[i] for i in range(3)), normal)
    ok = denom * denom > small_sq(denom.dtype)  # a ray (almost) parallel to the plane misses it
    t = safe_div(num, denom, ok)
    return t, ok & (t > 0)
