"""Materials with textures: `TexturedMaterial` (a glTF metallic-roughness material whose factors are
multiplied by textures, the KHR extensions' textures included), `TextureSlot` (a mip-mapped texture
with its sampler, texture-coordinate set and transform) and their evaluation on the pixels of an
object (`apply_extension_textures`, `sample_texture`).

Texture coordinates follow glTF: uv = (0, 0) is the top-left corner of the image (row 0), u to the
right, v down; texel (i, j) sits at ((j + 0.5)/W, (i + 0.5)/H). A plain (H, W, C) array is looked
up bilinearly with repeat wrapping; a `TextureSlot` is filtered by its footprint. Tangent frames:
T = dP/du (normalised), B = w (N x T) with w = +1 off meshes (a mesh's TANGENT.w), so a
tangent-space normal map's +Y points towards decreasing v ("up" in the image), the glTF / OpenGL
convention.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._interp import bilinear
from .._numerics import as_float, is_concrete, vcross, vdot, vnormalize
from .._pytree import Pytree, evolve, leaf, static, subtree
from .._validate import check_values
from ..shading.material import EXTENSION_FIELDS, Material

__all__ = [
    "EXTENSION_TEXTURES",
    "TextureSlot",
    "TexturedMaterial",
    "apply_extension_textures",
    "sample_texture",
    "texels",
]


def _scalar(name: str, x) -> jax.Array:
    return check_values(name, as_float(x))




class TextureSlot(Pytree):
    """A mip-mapped texture in a material slot (what a glTF textureInfo is).

    texture: a `jaxpbr.rendering.texture.Texture` (linear levels and the sampler: wrap and filter
        modes, anisotropy).
    texcoord: the texture-coordinate set it reads: 0 (TEXCOORD_0, `Mesh.texcoords`) or 1
        (TEXCOORD_1, `Mesh.texcoords1`; objects without it read set 0) (static).
    transform: (3, 3) KHR_texture_transform matrix applied to (u, v, 1) and to the derivatives,
        or None.

    A material slot holding a plain (H, W, C) array is sampled bilinearly with repeat wrapping and
    no mips; a TextureSlot is filtered by its footprint (`jaxpbr.rendering.texture.sample`).
    """

    texture: Any = subtree()
    texcoord: int = static(0)
    transform: Any = leaf(None, rank=2)

    def _validate(self) -> None:
        from .texture import Texture

        if not isinstance(self.texture, Texture):
            raise TypeError(f"TextureSlot.texture must be a jaxpbr.rendering.texture.Texture, got {type(self.texture).__name__}")
        if self.texcoord not in (0, 1):
            raise ValueError(f"TextureSlot.texcoord must be 0 or 1 (TEXCOORD_0 / TEXCOORD_1), got {self.texcoord!r}")
        if self.transform is not None:
            m = as_float(self.transform)
            if m.shape != (3, 3):
                raise ValueError(f"TextureSlot.transform must be a (3, 3) matrix, got shape {m.shape}")
            self._set(transform=m)

    @property
    def texels(self):
        """Level 0 (H, W, C): what range checks and memory estimates read."""
        return self.texture.levels[0]


def texels(x):
    """The (H, W, C) texels of a material texture (an array, or a TextureSlot's level 0)."""
    return x.texels if isinstance(x, TextureSlot) else x


def _texture(name: str, x, min_channels: int, *, lo=0.0, hi=1.0, holds: str = ""):
    if x is None:
        return None
    if isinstance(x, TextureSlot):
        _texture(name, x.texels, min_channels, lo=lo, hi=hi, holds=holds)
        return x
    x = as_float(x)
    if x.ndim != 3 or x.shape[-1] < min_channels or x.shape[0] < 1 or x.shape[1] < 1:
        what = f" ({holds})" if holds else ""
        raise ValueError(
            f"{name} must be an (H, W, C) image with C >= {min_channels}{what}, got shape {x.shape}"
        )
    if is_concrete(x):
        a = np.asarray(x)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or Inf")
        if (lo is not None and a.min() < lo) or (hi is not None and a.max() > hi):
            raise ValueError(
                f"{name} must hold linear values in [{lo}, {hi}], got [{a.min():g}, {a.max():g}]; "
                "decode 8-bit sRGB colour with jaxpbr.color and scale to [0, 1]"
            )
    return x


#: The extension textures of `TexturedMaterial`: name -> (extension group, minimum channels,
#: ((Material field it multiplies, channel: an index, or "rgb"), ...), what it holds). The channels
#: are the KHR extensions' (glTF textureInfo, linear data).
EXTENSION_TEXTURES: dict[str, tuple[str, int, tuple, str]] = {
    "clearcoat_texture": ("clearcoat", 1, (("clearcoat", 0),), "R = clear coat"),
    "clearcoat_roughness_texture": ("clearcoat", 2, (("clearcoat_roughness", 1),), "G = clear coat roughness"),
    "clearcoat_normal_texture": ("clearcoat", 3, (), "a tangent-space normal map (n + 1)/2"),
    "sheen_color_texture": ("sheen", 3, (("sheen_color", "rgb"),), "RGB = sheen colour"),
    "sheen_roughness_texture": ("sheen", 4, (("sheen_roughness", 3),), "A = sheen roughness: an RGBA image"),
    "specular_texture": ("specular", 4, (("specular", 3),), "A = specular: an RGBA image"),
    "specular_color_texture": ("specular", 3, (("specular_color", "rgb"),), "RGB = specular colour"),
    "anisotropy_texture": (
        "anisotropy", 3, (("anisotropy_strength", 2),), "RG = direction (d + 1)/2, B = anisotropy strength"
    ),
    "transmission_texture": ("transmission", 1, (("transmission", 0),), "R = transmission"),
    "thickness_texture": ("volume", 2, (("thickness", 1),), "G = thickness"),
}
_RGB_FACTORS = ("sheen_color", "specular_color", "attenuation_color")


class TexturedMaterial(Pytree):
    """A glTF metallic-roughness material with textures; each texture multiplies its factor.

    factors: `Material` holding the glTF factors (base_color, metallic, roughness, occlusion
        strength-as-multiplier, emissive).
    base_color_texture: (H, W, 3 or 4) *linear* RGB in [0, 1] (alpha ignored).
    metallic_roughness_texture: (H, W, >=3) glTF packing: G = roughness, B = metallic.
    occlusion_texture: (H, W, >=1) R = ambient occlusion (pass the same array as
        metallic_roughness_texture for a packed ORM texture).
    normal_texture: (H, W, 3) tangent-space normal map, stored as (n + 1)/2 in [0, 1]; X right,
        Y up (towards decreasing v), Z out of the surface.
    normal_scale: scales the map's X and Y (glTF normalTexture.scale).
    emissive_texture: (H, W, 3) linear RGB >= 0, multiplied by factors.emissive.

    Textures of the glTF material extensions (KHR_materials_<group>), all linear data in [0, 1],
    sampled with the same uv. Each multiplies its factor in `factors`; the factor's group must be
    present there (e.g. `Material(clearcoat=1.0)` for clearcoat_texture: an absent extension has
    no textures), and a present group's unset factor takes its neutral value, as in glTF (so a
    texture whose factor is unset and neutral 0, e.g. clearcoat_roughness, has no effect).
    `apply_extension_textures` evaluates them.
    clearcoat_texture: (H, W, >=1) R x clearcoat (KHR_materials_clearcoat).
    clearcoat_roughness_texture: (H, W, >=2) G x clearcoat_roughness.
    clearcoat_normal_texture: (H, W, 3) the clear coat's tangent-space normal map (as
        normal_texture); without it the coat takes the surface normal *without* normal_texture.
    clearcoat_normal_scale: scales its X and Y (glTF normalTexture.scale).
    sheen_color_texture: (H, W, >=3) RGB x sheen_color (linear; glTF stores it sRGB-encoded).
    sheen_roughness_texture: (H, W, 4) A x sheen_roughness (KHR_materials_sheen).
    specular_texture: (H, W, 4) A x specular.
    specular_color_texture: (H, W, >=3) RGB x specular_color (linear; KHR_materials_specular).
    anisotropy_texture: (H, W, >=3) RG = direction in tangent/bitangent space, stored as
        (d + 1)/2, rotated by anisotropy_rotation; B x anisotropy_strength (KHR_materials_anisotropy).
    transmission_texture: (H, W, >=1) R x transmission (KHR_materials_transmission).
    thickness_texture: (H, W, >=2) G x thickness (KHR_materials_volume).
    """

    factors: Material = subtree(default_factory=Material)
    base_color_texture: Any = leaf(None, rank=3)
    metallic_roughness_texture: Any = leaf(None, rank=3)
    occlusion_texture: Any = leaf(None, rank=3)
    normal_texture: Any = leaf(None, rank=3)
    emissive_texture: Any = leaf(None, rank=3)
    normal_scale: Any = leaf(1.0)
    clearcoat_texture: Any = leaf(None, rank=3)
    clearcoat_roughness_texture: Any = leaf(None, rank=3)
    clearcoat_normal_texture: Any = leaf(None, rank=3)
    clearcoat_normal_scale: Any = leaf(1.0)
    sheen_color_texture: Any = leaf(None, rank=3)
    sheen_roughness_texture: Any = leaf(None, rank=3)
    specular_texture: Any = leaf(None, rank=3)
    specular_color_texture: Any = leaf(None, rank=3)
    anisotropy_texture: Any = leaf(None, rank=3)
    transmission_texture: Any = leaf(None, rank=3)
    thickness_texture: Any = leaf(None, rank=3)

    def _validate(self) -> None:
        if not isinstance(self.factors, Material):
            raise TypeError(f"TexturedMaterial.factors must be a Material, got {type(self.factors).__name__}")
        self._set(
            base_color_texture=_texture("base_color_texture", self.base_color_texture, 3),
            metallic_roughness_texture=_texture("metallic_roughness_texture", self.metallic_roughness_texture, 3),
            occlusion_texture=_texture("occlusion_texture", self.occlusion_texture, 1),
            normal_texture=_texture("normal_texture", self.normal_texture, 3),
            emissive_texture=_texture("emissive_texture", self.emissive_texture, 3, hi=None),
            normal_scale=_scalar("normal_scale", self.normal_scale),
            clearcoat_normal_scale=_scalar("clearcoat_normal_scale", self.clearcoat_normal_scale),
        )
        present = self.factors.extensions
        for name, (group, channels, _factors, holds) in EXTENSION_TEXTURES.items():
            x = getattr(self, name)
            if x is None:
                continue
            if group not in present:
                fields = EXTENSION_FIELDS[group]
                first = next(iter(fields))
                value = "1.0" if first not in _RGB_FACTORS else "(1.0, 1.0, 1.0)"
                raise ValueError(
                    f"{name} needs the KHR_materials_{group} factors, which TexturedMaterial.factors lacks "
                    f"(an absent extension has no textures); set them, e.g. factors=Material(..., {first}={value})"
                )
            self._set(**{name: _texture(name, x, channels, holds=holds)})

    @property
    def extension_textures(self) -> tuple[str, ...]:
        """The names of the extension textures given (static: known inside jit)."""
        return tuple(n for n in EXTENSION_TEXTURES if getattr(self, n) is not None)

    @property
    def has_normal_map(self) -> bool:
        return self.normal_texture is not None


def sample_texture(tex: jax.Array, u, v) -> jax.Array:
    """Bilinear lookup with repeat wrapping of an (H, W, C) texture at glTF uv (...) -> (..., C).

    Texel (i, j) sits at ((j + 0.5)/W, (i + 0.5)/H); differentiable in the texels and in (u, v).
    """
    H, W = tex.shape[0], tex.shape[1]
    return bilinear(tex, u * W - 0.5, v * H - 0.5, wrap_x=True, wrap_y=True)


def _tangent_frame(tangent, n):
    """(T, B): the tangent Gram-Schmidt-orthogonalised against the unit normal n, B = n x T (glTF
    handedness +1). A tangent parallel to n gives T = B = 0 (no perturbation)."""
    tn = vdot(tangent, n)
    T = vnormalize(tuple(tangent[i] - tn * n[i] for i in range(3)))
    return T, vcross(n, T)


def _normal_from_map(tex, scale, T, B, n):
    """The unit normal of a tangent-space normal map's texels tex (..., 3) in [0, 1]: glTF's
    normalize(T x s + B y s + N z) with (x, y, z) = 2 tex - 1."""
    tx, ty, tz = (2.0 * tex[..., 0] - 1.0) * scale, (2.0 * tex[..., 1] - 1.0) * scale, 2.0 * tex[..., 2] - 1.0
    return vnormalize(tuple(T[i] * tx + B[i] * ty + n[i] * tz for i in range(3)))


def apply_extension_textures(tm: TexturedMaterial, m: Material, u, v, sel, n, tangent, *, dtype, lookup=None):
    """The extension textures of `tm` (KHR_materials_*) evaluated on the pixels `sel`.

    tm: the object's TexturedMaterial. m: the gathered per-pixel Material ((H, W[, 3]) leaves,
    already holding the object's factors on `sel`; its groups include tm.factors' groups -- a
    missing one is filled with its neutral values off `sel`). u, v: (H, W) texture coordinates.
    sel: (H, W) bool, the object's pixels. n: unit Vec3 normal *before* any normal_texture (the
    interpolated / geometric normal: glTF builds the tangent frame from it, and the clear coat
    takes it when it has no normal map of its own). tangent: Vec3 surface tangent dP/du (any
    length; Gram-Schmidt against n, B = n x T). dtype: the shading dtype. lookup: texture ->
    (H, W, C) samples (the renderer's, which filters `TextureSlot`s by their footprint); default
    a bilinear lookup of a plain array at (u, v).

    Returns (material, coat_normal, tangent):
      material: m with every textured field replaced on `sel` by factor x texture channel
        (`EXTENSION_TEXTURES`; the factors of tm.factors with a present group's unset fields at
        their neutral values, `Material.complete`), unchanged elsewhere.
      coat_normal: Vec3, or None when it is the shading normal. With clearcoat_normal_texture:
        the normal mapped by it on `sel`; otherwise, when the clear coat is present and the base
        has a normal_texture, n itself on `sel` (glTF: no normal mapping applies to the coat
        unless it has its own map). Off `sel` it equals n: merge with jnp.where(sel, ...).
      tangent: Vec3, or None when there is no anisotropy_texture: the anisotropy direction
        T' = normalize(dx T + dy B), (dx, dy) = 2 RG - 1, on `sel` (the input tangent elsewhere);
        the shading's anisotropy_rotation applied in the (T', n x T') frame then rotates the
        texture's direction, as in the extension's sample code. A texel direction of length ~0
        falls back to T.
    Differentiable in the factors, the textures, uv, n and tangent; traceable (jit, vmap).
    """
    f = tm.factors.complete()
    fields = {}
    if lookup is None:
        lookup = lambda x: sample_texture(jnp.asarray(x, dtype), u, v)  # noqa: E731

    def current(name, rank):
        x = getattr(m, name)
        if x is None:  # the gather left the group out: neutral values off `sel`
            group = next(g for g, fs in EXTENSION_FIELDS.items() if name in fs)
            x = jnp.broadcast_to(jnp.asarray(EXTENSION_FIELDS[group][name], dtype), u.shape + (3,) * rank)
        return x

    for name, (_group, _c, targets, _h) in EXTENSION_TEXTURES.items():
        x = getattr(tm, name)
        if x is None or not targets:
            continue
        tex = lookup(x)
        for field, ch in targets:
            factor = jnp.asarray(getattr(f, field), dtype)
            rgb = ch == "rgb"
            t = tex[..., :3] if rgb else tex[..., ch : ch + 1]
            value = factor * (t if rgb else t[..., 0])
            mask = sel[..., None] if rgb else sel
            fields[field] = jnp.where(mask, value, fields.get(field, current(field, int(rgb))))

    coat = None
    out_t = None
    need_frame = tm.clearcoat_normal_texture is not None or tm.anisotropy_texture is not None
    if need_frame:
        T, B = _tangent_frame(tangent, n)
    if tm.clearcoat_normal_texture is not None:
        tex = lookup(tm.clearcoat_normal_texture)[..., :3]
        pert = _normal_from_map(tex, jnp.asarray(tm.clearcoat_normal_scale, dtype), T, B, n)
        coat = tuple(jnp.where(sel, pert[i], n[i]) for i in range(3))
    elif tm.normal_texture is not None and "clearcoat" in f.extensions:
        coat = tuple(n)
    if tm.anisotropy_texture is not None:
        tex = lookup(tm.anisotropy_texture)[..., :2]
        dx, dy = 2.0 * tex[..., 0] - 1.0, 2.0 * tex[..., 1] - 1.0
        d = vnormalize(tuple(dx * T[i] + dy * B[i] for i in range(3)))
        ok = vdot(d, d) > 0.5  # vnormalize gives 0 for a direction of length ~0
        out_t = tuple(jnp.where(sel & ok, d[i], jnp.where(sel, T[i], tangent[i])) for i in range(3))
    return (evolve(m, **fields) if fields else m), coat, out_t


