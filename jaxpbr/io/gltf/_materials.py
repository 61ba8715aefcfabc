"""glTF materials -> `GltfMaterial` (core metallic-roughness, KHR_materials_*, KHR_materials_unlit,
KHR_texture_transform)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from ._binary import fail, get, loc, pointer
from ._types import GltfMaterial, GltfSampler, GltfTextureRef

__all__ = ["MATERIAL_EXTENSIONS", "MaterialReader", "texture_transform_matrix"]

WRAP = {10497: "repeat", 33071: "clamp", 33648: "mirror"}
MAG_FILTER = {9728: "nearest", 9729: "linear"}
MIN_FILTER = {
    9728: "nearest",
    9729: "linear",
    9984: "nearest_mipmap_nearest",
    9985: "linear_mipmap_nearest",
    9986: "nearest_mipmap_linear",
    9987: "linear_mipmap_linear",
}
SRGB_ROLES = frozenset({"base_color", "emissive", "sheen_color", "specular_color"})

#: KHR extension -> (its factors: glTF property -> (jaxpbr field, default)), (its textures: glTF
#: property -> role). Defaults are the extensions' schema defaults.
MATERIAL_EXTENSIONS = {
    "KHR_materials_clearcoat": (
        {"clearcoatFactor": ("clearcoat", 0.0), "clearcoatRoughnessFactor": ("clearcoat_roughness", 0.0)},
        {"clearcoatTexture": "clearcoat", "clearcoatRoughnessTexture": "clearcoat_roughness",
         "clearcoatNormalTexture": "clearcoat_normal"},
    ),
    "KHR_materials_sheen": (
        {"sheenColorFactor": ("sheen_color", (0.0, 0.0, 0.0)), "sheenRoughnessFactor": ("sheen_roughness", 0.0)},
        {"sheenColorTexture": "sheen_color", "sheenRoughnessTexture": "sheen_roughness"},
    ),
    "KHR_materials_specular": (
        {"specularFactor": ("specular", 1.0), "specularColorFactor": ("specular_color", (1.0, 1.0, 1.0))},
        {"specularTexture": "specular", "specularColorTexture": "specular_color"},
    ),
    "KHR_materials_ior": ({"ior": ("ior", 1.5)}, {}),
    "KHR_materials_anisotropy": (
        {"anisotropyStrength": ("anisotropy_strength", 0.0), "anisotropyRotation": ("anisotropy_rotation", 0.0)},
        {"anisotropyTexture": "anisotropy"},
    ),
    "KHR_materials_emissive_strength": ({"emissiveStrength": ("emissive_strength", 1.0)}, {}),
    "KHR_materials_transmission": (
        {"transmissionFactor": ("transmission", 0.0)},
        {"transmissionTexture": "transmission"},
    ),
    "KHR_materials_volume": (
        {"thicknessFactor": ("thickness", 0.0), "attenuationDistance": ("attenuation_distance", math.inf),
         "attenuationColor": ("attenuation_color", (1.0, 1.0, 1.0))},
        {"thicknessTexture": "thickness"},
    ),
}


def texture_transform_matrix(offset=(0.0, 0.0), rotation=0.0, scale=(1.0, 1.0)) -> np.ndarray:
    """KHR_texture_transform as a (3, 3) matrix on (u, v, 1): T(offset) @ R(rotation) @ S(scale).

    R = [[cos, sin], [-sin, cos]]: the UVs turn counter-clockwise in glTF's v-down UV space (the
    image turns clockwise on the surface), as the README's example and its implementations do."""
    c, s = math.cos(rotation), math.sin(rotation)
    t = np.array([[1.0, 0.0, offset[0]], [0.0, 1.0, offset[1]], [0.0, 0.0, 1.0]])
    r = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    k = np.diag([float(scale[0]), float(scale[1]), 1.0])
    return t @ r @ k


def _floats(value, n, file, where):
    try:
        out = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        out = ()
    if len(out) != n or not all(math.isfinite(x) for x in out):
        fail(file, where, f"expected {n} finite numbers, got {value!r}", "repair or re-export the asset")
    return out


def _float(value, file, where, *, allow_inf=False):
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = math.nan
    if math.isnan(out) or (math.isinf(out) and not allow_inf):
        fail(file, where, f"expected a number, got {value!r}", "repair or re-export the asset")
    return out


class MaterialReader:
    """Reads the file's materials, textures and samplers; `notes` collects what is dropped."""

    def __init__(self, gltf, file: Path, notes: list[str]):
        self.gltf = gltf
        self.file = file
        self.notes = notes
        self._samplers: dict[int, GltfSampler] = {}

    def sampler(self, i: int | None, where: str) -> GltfSampler:
        """Sampler i; `where`: the texture naming it, with the pointer of its `sampler` property."""
        if i is None:
            return GltfSampler()
        if i in self._samplers:
            return self._samplers[i]
        samplers = self.gltf.samplers or []
        if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < len(samplers):
            fail(self.file, where, f"sampler {i!r} does not exist (the file has {len(samplers)})",
                 "repair or re-export the asset")
        s = samplers[i]
        values = {}
        for key, table, default in (("wrapS", WRAP, 10497), ("wrapT", WRAP, 10497),
                                    ("magFilter", MAG_FILTER, 9729), ("minFilter", MIN_FILTER, 9987)):
            v = get(s, key, default)
            if v not in table:
                fail(self.file, loc(f"sampler {i}", pointer("samplers", i, key)),
                     f"{key} = {v} is not a valid glTF value ({sorted(table)})", "repair or re-export the asset")
            values[key] = table[v]
        out = GltfSampler(values["wrapS"], values["wrapT"], values["magFilter"], values["minFilter"], True)
        self._samplers[i] = out
        return out

    def texref(self, role: str, info, where: str, at: str) -> GltfTextureRef | None:
        """The slot `role` of a material; `at`: the JSON pointer of its textureInfo."""
        where = f"{where} {role} texture"
        index = get(info, "index")
        textures = self.gltf.textures or []
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(textures):
            fail(self.file, loc(where, at + "/index"), f"texture {index!r} does not exist (the file has {len(textures)})",
                 "repair or re-export the asset")
        tex = textures[index]
        # EXT_texture_webp names a WebP image, preferred to `source` (its PNG/JPEG fallback, if any).
        webp = (get(tex, "extensions", {}) or {}).get("EXT_texture_webp")
        source, source_at = get(tex, "source"), pointer("textures", index, "source")
        if webp is not None:
            source, source_at = get(webp, "source"), pointer("textures", index, "extensions", "EXT_texture_webp", "source")
        if source is None:
            exts = sorted(get(tex, "extensions", {}) or {})
            self.notes.append(f"{loc(where, at)}: texture {index} has no PNG/JPEG/WebP source"
                              + (f" (only {', '.join(exts)})" if exts else "") + "; the slot is dropped")
            return None
        images = self.gltf.images or []
        if not isinstance(source, int) or isinstance(source, bool) or not 0 <= source < len(images):
            fail(self.file, f"{loc(where, at)}: {loc(f'texture {index}', source_at)}",
                 f"image {source!r} does not exist (the file has {len(images)})", "repair or re-export the asset")
        texcoord = get(info, "texCoord", 0)
        tc_at = at + "/texCoord"
        transform = np.eye(3)
        tt = (get(info, "extensions", {}) or {}).get("KHR_texture_transform")
        if tt is not None:
            tt_at = at + "/extensions/KHR_texture_transform"
            offset = _floats(get(tt, "offset", (0.0, 0.0)), 2, self.file, loc(where, tt_at + "/offset"))
            scale = _floats(get(tt, "scale", (1.0, 1.0)), 2, self.file, loc(where, tt_at + "/scale"))
            rotation = _float(get(tt, "rotation", 0.0), self.file, loc(where, tt_at + "/rotation"))
            transform = texture_transform_matrix(offset, rotation, scale)
            if get(tt, "texCoord") is not None:
                texcoord, tc_at = get(tt, "texCoord"), tt_at + "/texCoord"
        if not isinstance(texcoord, int) or isinstance(texcoord, bool) or texcoord < 0:
            fail(self.file, loc(where, tc_at), f"texCoord {texcoord!r} is not a valid set index",
                 "repair or re-export the asset")
        transform.flags.writeable = False
        return GltfTextureRef(
            role=role,
            texture=index,
            image=source,
            texcoord=texcoord,
            sampler=self.sampler(get(tex, "sampler"), f"{loc(where, at)}: {loc(f'texture {index}', pointer('textures', index, 'sampler'))}"),
            transform=transform,
            has_transform=tt is not None,
            colorspace="srgb" if role in SRGB_ROLES else "linear",
            scale=_float(get(info, "scale", 1.0), self.file, loc(where, at + "/scale")) if role in ("normal", "clearcoat_normal") else 1.0,
            strength=_float(get(info, "strength", 1.0), self.file, loc(where, at + "/strength")) if role == "occlusion" else 1.0,
        )

    def material(self, i: int | None) -> GltfMaterial:
        if i is None:
            return GltfMaterial(index=None, name="default", factors=_core_factors(None, None, self.file, "", ""))
        m = self.gltf.materials[i]
        name = get(m, "name", "")
        where = f"material {i}" + (f" ({name!r})" if name else "")
        at = pointer("materials", i)
        pbr = get(m, "pbrMetallicRoughness")
        factors = _core_factors(m, pbr, self.file, where, at)
        bcf = _floats(get(pbr, "baseColorFactor", (1.0, 1.0, 1.0, 1.0)), 4, self.file,
                      loc(where, at + "/pbrMetallicRoughness/baseColorFactor"))
        textures = {}

        def add(role, info, info_at):
            if info is not None:
                ref = self.texref(role, info, where, info_at)
                if ref is not None:
                    textures[role] = ref

        add("base_color", get(pbr, "baseColorTexture"), at + "/pbrMetallicRoughness/baseColorTexture")
        add("metallic_roughness", get(pbr, "metallicRoughnessTexture"), at + "/pbrMetallicRoughness/metallicRoughnessTexture")
        add("normal", get(m, "normalTexture"), at + "/normalTexture")
        add("occlusion", get(m, "occlusionTexture"), at + "/occlusionTexture")
        add("emissive", get(m, "emissiveTexture"), at + "/emissiveTexture")
        used = []
        exts = get(m, "extensions", {}) or {}
        for ext, (fields, roles) in MATERIAL_EXTENSIONS.items():
            if ext not in exts:
                continue
            used.append(ext)
            data = exts[ext] or {}
            ext_at = pointer("materials", i, "extensions", ext)
            for key, (fname, default) in fields.items():
                value = get(data, key, default)
                if isinstance(default, tuple):
                    factors[fname] = _floats(value, len(default), self.file, loc(where, f"{ext_at}/{key}"))
                else:
                    factors[fname] = _float(value, self.file, loc(where, f"{ext_at}/{key}"),
                                            allow_inf=fname == "attenuation_distance")
            for key, role in roles.items():
                add(role, get(data, key), f"{ext_at}/{key}")
        alpha_mode = get(m, "alphaMode", "OPAQUE")
        if alpha_mode not in ("OPAQUE", "MASK", "BLEND"):
            fail(self.file, loc(where, at + "/alphaMode"), f"alphaMode {alpha_mode!r} is not OPAQUE, MASK or BLEND",
                 "repair or re-export the asset")
        unlit = UNLIT in exts
        if unlit:
            factors, textures = _unlit(factors, textures, alpha_mode)
            if used:
                self.notes.append(f"{loc(where, at)} is unlit (KHR_materials_unlit): its {', '.join(used)} "
                                  "are not shaded")
            used = [UNLIT]
        return GltfMaterial(
            index=i,
            name=name,
            factors=factors,
            base_color_alpha=bcf[3],
            alpha_mode=alpha_mode,
            alpha_cutoff=_float(get(m, "alphaCutoff", 0.5), self.file, loc(where, at + "/alphaCutoff")),
            double_sided=bool(get(m, "doubleSided", False)),
            textures=textures,
            extensions=tuple(used),
            unlit=unlit,
        )


#: KHR_materials_unlit: the material is drawn in its base colour, without lighting.
UNLIT = "KHR_materials_unlit"


def _unlit(factors: dict, textures: dict, alpha_mode: str) -> tuple[dict, dict]:
    """The factors and textures of an unlit material: its colour (base colour factor x texture;
    COLOR_0 is added by the renderer) as the emission, which the pixels of an unlit mesh show alone
    (`Mesh.unlit`: no light, environment or sun is added there); the base colour keeps the same
    values (its texture's A for MASK and BLEND, the base-colour AOV), and the core model's other
    factors and slots are dropped (the extension shades none of them)."""
    out = {
        "base_color": tuple(float(c) for c in factors["base_color"]), "metallic": 0.0, "roughness": 1.0,
        "occlusion": 1.0, "emissive": tuple(float(c) for c in factors["base_color"]),
    }
    tex = {}
    if "base_color" in textures:
        tex["base_color"] = textures["base_color"]
        tex["emissive"] = dataclasses.replace(textures["base_color"], role="emissive")
    return out, tex


def _core_factors(m, pbr, file, where, at) -> dict:
    pbr_at = at + "/pbrMetallicRoughness"
    bcf = _floats(get(pbr, "baseColorFactor", (1.0, 1.0, 1.0, 1.0)), 4, file, loc(where, pbr_at + "/baseColorFactor"))
    return {
        "base_color": bcf[:3],
        "metallic": _float(get(pbr, "metallicFactor", 1.0), file, loc(where, pbr_at + "/metallicFactor")),
        "roughness": _float(get(pbr, "roughnessFactor", 1.0), file, loc(where, pbr_at + "/roughnessFactor")),
        "occlusion": 1.0,
        "emissive": _floats(get(m, "emissiveFactor", (0.0, 0.0, 0.0)), 3, file, loc(where, at + "/emissiveFactor")),
    }
