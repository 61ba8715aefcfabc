"""KHR_texture_transform on every texture slot the glTF loader maps (core and KHR_materials_*):
a quad rendered with a texture T under a transform equals the quad rendered with the
untransformed texture T' whose texels were moved by hand in NumPy (np.roll, np.flip, np.rot90).

Oracle: the moved image. The quad fills a 16 x 16 orthographic view and its uv = ((x + 1)/2,
(1 - y)/2) (glTF: v down), so pixel (r, c) reads uv ((c + .5)/16, (r + .5)/16): texel (r // 2,
c // 2) of the 8 x 8 texture, a quarter texel from its edges. The sampler is NEAREST (magnified,
so no mips), and each transform maps texel centres onto texel centres (offsets of whole texels,
a flip, a quarter turn), so both renders read the same 8-bit texel at every pixel and shade it
with the same program inputs; they agree to float32 rounding of the transformed uv, which moves a
lookup by ~1e-7 of a texel, far from a texel edge. Tolerance: 1e-5 relative (the shading of equal
inputs; the quarter-turn's cos(pi/2) = -4.4e-8 in float32 changes no texel).

Each case also renders the *unmoved* texture without a transform and requires it to differ, so a
slot the setup cannot see (or a transform that is dropped) fails rather than passes vacuously.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.rendering.gltf_scene import load_gltf

from gltf_writer import FLOAT, UINT, Builder, assert_valid, png_bytes

pytest.importorskip("embreex")

N = 8  # texels per side
PX = 16  # pixels per side

# slot -> (glTF extension or None, textureInfo property, material JSON around it (without the
# textureInfo), channels of the image)
_BASE = {"pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.5, 0.4, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.5}}


def _ext(name, **factors):
    return {**_BASE, "extensions": {name: factors}}


SLOTS = {
    "base_color": (None, ("pbrMetallicRoughness", "baseColorTexture"), _BASE, 3),
    "metallic_roughness": (None, ("pbrMetallicRoughness", "metallicRoughnessTexture"),
                           {"pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.5, 0.4, 1.0]}}, 3),
    "normal": (None, ("normalTexture",), _BASE, 3),
    "occlusion": (None, ("occlusionTexture",), _BASE, 3),
    "emissive": (None, ("emissiveTexture",), {**_BASE, "emissiveFactor": [1.0, 1.0, 1.0]}, 3),
    "clearcoat": ("KHR_materials_clearcoat", ("clearcoatTexture",),
                  _ext("KHR_materials_clearcoat", clearcoatFactor=1.0, clearcoatRoughnessFactor=0.3), 3),
    "clearcoat_roughness": ("KHR_materials_clearcoat", ("clearcoatRoughnessTexture",),
                            _ext("KHR_materials_clearcoat", clearcoatFactor=1.0, clearcoatRoughnessFactor=1.0), 3),
    "clearcoat_normal": ("KHR_materials_clearcoat", ("clearcoatNormalTexture",),
                         _ext("KHR_materials_clearcoat", clearcoatFactor=1.0, clearcoatRoughnessFactor=0.2), 3),
    "sheen_color": ("KHR_materials_sheen", ("sheenColorTexture",),
                    _ext("KHR_materials_sheen", sheenColorFactor=[1.0, 1.0, 1.0], sheenRoughnessFactor=0.5), 3),
    "sheen_roughness": ("KHR_materials_sheen", ("sheenRoughnessTexture",),
                        _ext("KHR_materials_sheen", sheenColorFactor=[1.0, 1.0, 1.0], sheenRoughnessFactor=1.0), 4),
    "specular": ("KHR_materials_specular", ("specularTexture",), _ext("KHR_materials_specular", specularFactor=1.0), 4),
    "specular_color": ("KHR_materials_specular", ("specularColorTexture",),
                       _ext("KHR_materials_specular", specularColorFactor=[1.0, 1.0, 1.0]), 3),
    "anisotropy": ("KHR_materials_anisotropy", ("anisotropyTexture",),
                   _ext("KHR_materials_anisotropy", anisotropyStrength=1.0), 3),
    "transmission": ("KHR_materials_transmission", ("transmissionTexture",),
                     _ext("KHR_materials_transmission", transmissionFactor=1.0), 3),
    "thickness": ("KHR_materials_volume", ("thicknessTexture",),
                  {**_BASE, "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0},
                                           "KHR_materials_volume": {"thicknessFactor": 2.0, "attenuationDistance": 0.5,
                                                                    "attenuationColor": [0.9, 0.4, 0.2]}}}, 3),
}

# transform name -> (KHR_texture_transform JSON, the texels moved by hand: T'[i, j] = T at the
# transformed uv of texel (i, j)'s centre, with repeat wrapping)
#   offset (3/8, -2/8): uv' = uv + offset -> T'[i, j] = T[i - 2, j + 3]
#   scale (-1, 1):      u' = -u = 1 - u    -> T'[i, j] = T[i, N - 1 - j]
#   rotation pi/2:      (u', v') = (v, -u) (R = [[c, s], [-s, c]] in v-down uv: the UVs turn
#                       counter-clockwise, the image clockwise) -> T'[i, j] = T[N - 1 - j, i]
#   texCoord 1:         the transform's texCoord overrides the textureInfo's (0); TEXCOORD_1 =
#                       (u, 1 - v) -> T'[i, j] = T[N - 1 - i, j]
TRANSFORMS = {
    "offset": ({"offset": [3 / 8, -2 / 8]}, lambda t: np.roll(t, (2, -3), axis=(0, 1))),
    "flip": ({"scale": [-1.0, 1.0]}, lambda t: np.flip(t, 1)),
    "rot90": ({"rotation": math.pi / 2}, lambda t: np.rot90(t, -1)),
    "texcoord": ({"texCoord": 1}, lambda t: np.flip(t, 0)),
}


def _texels(slot, channels):
    """8-bit texels with every channel varying; normal maps keep +Z (B >= 160)."""
    rng = np.random.default_rng(list(SLOTS).index(slot))  # (str hashes vary between processes)
    t = rng.integers(0, 256, (N, N, channels), dtype=np.uint8)
    if slot in ("normal", "clearcoat_normal"):
        t[..., 2] = rng.integers(160, 256, (N, N), dtype=np.uint8)
    return t


def _asset(tmp_path, name, slot, texels, transform):
    ext, where, material, _ = SLOTS[slot]
    b = Builder()
    pos = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    uv0 = np.stack([(pos[:, 0] + 1) / 2, (1 - pos[:, 1]) / 2], -1)
    uv1 = np.stack([uv0[:, 0], 1 - uv0[:, 1]], -1)
    attrs = {
        "POSITION": b.accessor(pos, FLOAT, "VEC3", minmax=True),
        "NORMAL": b.accessor(np.tile(np.float32([0, 0, 1]), (4, 1)), FLOAT, "VEC3"),
        "TANGENT": b.accessor(np.tile(np.float32([1, 0, 0, 1]), (4, 1)), FLOAT, "VEC4"),
        "TEXCOORD_0": b.accessor(uv0, FLOAT, "VEC2"),
        "TEXCOORD_1": b.accessor(uv1, FLOAT, "VEC2"),
    }
    idx = b.accessor(np.array([0, 1, 2, 0, 2, 3], np.uint32), UINT, "SCALAR")
    img = b.add("images", {"bufferView": b.view(png_bytes(texels)), "mimeType": "image/png"})
    smp = b.add("samplers", {"magFilter": 9728, "minFilter": 9728, "wrapS": 10497, "wrapT": 10497})
    tex = b.add("textures", {"source": img, "sampler": smp})
    info = {"index": tex}
    used = [ext] if ext else []
    if slot == "thickness":
        used = ["KHR_materials_transmission", "KHR_materials_volume"]
    if transform is not None:
        info["extensions"] = {"KHR_texture_transform": transform}
        used.append("KHR_texture_transform")
    mat = json_copy(material)
    node = mat if ext is None else mat["extensions"][ext]
    for key in where[:-1]:
        node = node.setdefault(key, {})
    node[where[-1]] = info
    m = b.add("materials", mat)
    mesh = b.add("meshes", {"primitives": [{"attributes": attrs, "indices": idx, "material": m}]})
    b.add("nodes", {"mesh": mesh})
    b.doc["scenes"] = [{"nodes": [0]}]
    b.doc["scene"] = 0
    if used:
        b.used(*used)
    path = b.write(tmp_path / f"{name}.gltf", mode="data")
    assert_valid(path)
    return path


def json_copy(x):
    import json

    return json.loads(json.dumps(x))


CAMERA = jp.Camera(position=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), projection="orthographic", ymag=1.0,
                   width=PX, height=PX)
SUN = jp.DirectionalLight(direction=(-0.3, -0.2, -1.0), color=(1.0, 1.0, 1.0), intensity=3.0)


def _render(path):
    env = jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(16))
    scene = load_gltf(path, camera=CAMERA, lights=[SUN], environment=env)
    return np.asarray(jp.render(scene), np.float64)


def _check(tmp_path, slot, transform):
    tt, move = TRANSFORMS[transform]
    texels = _texels(slot, SLOTS[slot][3])
    moved = np.ascontiguousarray(move(texels))
    assert not np.array_equal(moved, texels)
    a = _render(_asset(tmp_path, "transformed", slot, texels, tt))
    b = _render(_asset(tmp_path, "moved", slot, moved, None))
    c = _render(_asset(tmp_path, "unmoved", slot, texels, None))
    assert np.all(np.isfinite(a)) and a.max() > 1e-3
    # the slot is visible in this setup: the unmoved texture gives another image
    assert np.abs(c - b).max() > 1e-3 * max(np.abs(b).max(), 1e-6), f"{slot}: the texture does not show"
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * np.abs(b).max(), err_msg=f"{slot} under {transform}")


DEFAULT = [("clearcoat_roughness", "rot90"), ("base_color", "offset")]


@pytest.mark.parametrize("slot,transform", DEFAULT)
def test_transformed_slot_equals_texels_moved_by_hand(tmp_path, slot, transform):
    _check(tmp_path, slot, transform)


@pytest.mark.slow
@pytest.mark.parametrize("transform", list(TRANSFORMS))
@pytest.mark.parametrize("slot", list(SLOTS))
def test_every_slot_under_every_transform_slow(tmp_path, slot, transform):
    if (slot, transform) in DEFAULT:
        pytest.skip("in the default suite")
    _check(tmp_path, slot, transform)


# ------------------------------------------------------------------------------------------
# The coat lobe of the IBL term under multiple scattering (`RenderOptions.multiscatter`, on by
# default): compensated as the base's lobes are, so that a rough coat reflects its whole weight.
# ------------------------------------------------------------------------------------------

L_ENV = 0.5


def _coat_energy(rc, tilt_deg, multiscatter):
    """(coated - (1 - Fc) uncoated) / (Fc L) in a uniform environment of radiance L: the energy the
    coat lobe reflects per unit of its layer weight Fc (KHR_materials_clearcoat: coated =
    mix(base, coat_brdf, clearcoat Fc), Fc = 0.04 + 0.96 (1 - n.v)^5, here in float64)."""
    env = jp.Environment(radiance=jp.Cubemap([np.full((6, 16, 16, 3), L_ENV, np.float32)]))
    t = math.radians(tilt_deg)
    cam = jp.Camera(position=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), projection="orthographic", ymag=0.5,
                    width=4, height=4)
    base = dict(base_color=(0.004, 0.03, 0.17), metallic=1.0, roughness=1.0)  # the sample's coated tiles

    def draw(mat):
        plane = jp.Plane(point=(0.0, 0.0, 0.0), normal=(0.0, math.sin(t), math.cos(t)), material=mat)
        scene = jp.Scene(camera=cam, objects=[plane], environment=env)
        return np.asarray(jp.render(scene, multiscatter=multiscatter), np.float64)

    u = draw(jp.Material(**base))
    c = draw(jp.Material(**base, clearcoat=1.0, clearcoat_roughness=rc))
    fc = 0.04 + 0.96 * (1.0 - math.cos(t)) ** 5
    return (c - (1.0 - fc) * u) / (fc * L_ENV)


@pytest.mark.parametrize("rc,tilt", [(1.0, 0.0), (1.0, 60.0), (0.03, 60.0)])
def test_compensated_coat_lobe_reflects_its_whole_weight(rc, tilt):
    """With multiscatter (the default) the coat lobe, like the base's, is Fdez-Aguera compensated:
    its F0 = F90 = 1 (its Fresnel is the layer weight) give F_avg = 1 and Ess + FmsEms = 1, so in a
    uniform environment the coat adds clearcoat Fc L (glTF-Sample-Viewer's coat term). It gave
    0.31 at r = 1, n.v = 1 (1 - ln 2: the lobe's single scattering alone) and 0.45 at n.v = 0.5.
    Tolerance 2e-3: the irradiance of the uniform 16^2 map is 0.999 L (its convolution's
    quadrature), and the multiply-scattered part (0.69 of the lobe at r = 1) is lit by it."""
    np.testing.assert_allclose(_coat_energy(rc, tilt, True), 1.0, atol=2e-3)


def test_single_scattering_coat_lobe_is_the_spec_brdf():
    """multiscatter=False keeps the spec's single-scattering coat: at r = 1 (alpha = 1: D = 1/pi)
    and n.v = 1 the lobe's albedo is the closed form integral of (1/pi) V(l) (n.l) dl with the
    height-correlated V = 1/(2 (1 + n.l)): 2 pi (1/pi) (1/2) int_0^1 x/(1 + x) dx = 1 - ln 2.
    Tolerance 2e-3: the LUT's extrapolated corner (r = 1, n.v = 1) and float32."""
    np.testing.assert_allclose(_coat_energy(1.0, 0.0, False), 1.0 - math.log(2.0), atol=2e-3)
