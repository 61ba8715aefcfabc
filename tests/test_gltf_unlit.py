"""KHR_materials_unlit: the material's colour (baseColorFactor x base colour texture x COLOR_0) is
drawn as it is, whatever lights the scene (the pixels of an unlit mesh show its emission alone).

The asset is written here (three quads seen through an orthographic camera, so that every camera
ray has the same direction and the background is one colour) and checked with the Khronos
glTF-Validator when it is installed. The oracle is closed-form: the factor, the factor times the
vertex colour, the factor times the sRGB-decoded texel (glTF's EOTF), and the background where a
MASK texel is cut out."""

from __future__ import annotations

import numpy as np
import pytest
from gltf_writer import FLOAT, USHORT, Builder, assert_valid, png_bytes

import jaxpbr as jp
from jaxpbr.io.gltf import read_gltf
from jaxpbr.rendering.demo import demo_environment

UNLIT = {"KHR_materials_unlit": {}}
FACTOR = (0.8, 0.3, 0.1, 1.0)
VERTEX_RGB = (0.5, 1.0, 0.25)
#: 2 x 2 RGBA texels (row 0 at the top of the image, v = 0); the bottom-right one is cut out.
TEXELS = np.array([[[255, 0, 0, 255], [0, 255, 0, 255]], [[0, 0, 255, 255], [255, 255, 255, 0]]], np.uint8)
#: quads' x ranges (y in [-1, 1]); the camera sees x in [-3, 3], y in [-1.5, 1.5]
QUADS = ((-2.8, -1.2), (-0.8, 0.8), (1.2, 2.8))
W, H = 96, 48


def srgb_to_linear(c):
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _quad(b: Builder, x0, x1, material, rgb=None):
    pos = np.array([[x0, -1, 0], [x1, -1, 0], [x1, 1, 0], [x0, 1, 0]], np.float32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    attrs = {"POSITION": b.accessor(pos, FLOAT, "VEC3", minmax=True),
             "NORMAL": b.accessor(np.tile(np.float32([0, 0, 1]), (4, 1)), FLOAT, "VEC3"),
             "TEXCOORD_0": b.accessor(uv, FLOAT, "VEC2")}
    if rgb is not None:
        attrs["COLOR_0"] = b.accessor(np.tile(np.float32(rgb), (4, 1)), FLOAT, "VEC3")
    ind = b.accessor(np.array([0, 1, 2, 0, 2, 3], np.uint16), USHORT, "SCALAR")
    return {"attributes": attrs, "indices": ind, "material": material}


def unlit_quads(out):
    b = Builder()
    b.add("images", {"bufferView": b.view(png_bytes(TEXELS)), "mimeType": "image/png"})
    b.add("samplers", {"magFilter": 9728, "minFilter": 9728})  # NEAREST: each texel a block of pixels
    b.add("textures", {"source": 0, "sampler": 0})
    plain = b.add("materials", {"name": "plain", "pbrMetallicRoughness": {"baseColorFactor": list(FACTOR)},
                                "extensions": UNLIT})
    # an unlit material with lit properties besides: all of them are to be ignored
    textured = b.add("materials", {
        "name": "textured", "alphaMode": "MASK",
        "pbrMetallicRoughness": {"baseColorFactor": list(FACTOR), "baseColorTexture": {"index": 0},
                                 "metallicFactor": 1.0, "roughnessFactor": 0.1},
        "emissiveFactor": [1.0, 1.0, 1.0], "occlusionTexture": {"index": 0},
        "extensions": {**UNLIT, "KHR_materials_clearcoat": {"clearcoatFactor": 1.0}}})
    prims = [_quad(b, *QUADS[0], plain), _quad(b, *QUADS[1], plain, VERTEX_RGB), _quad(b, *QUADS[2], textured)]
    b.add("meshes", {"primitives": prims})
    b.add("scenes", {"nodes": [b.add("nodes", {"mesh": 0})]})
    b.doc["scene"] = 0
    b.used("KHR_materials_unlit", "KHR_materials_clearcoat")
    path = b.write(out / "unlit_quads.glb", mode="glb")
    assert_valid(path)
    return path


@pytest.fixture(scope="module")
def asset_path(tmp_path_factory):
    return unlit_quads(tmp_path_factory.mktemp("unlit"))


def test_unlit_materials_load_as_emission_of_a_surface_reflecting_nothing(asset_path):
    with pytest.warns(UserWarning, match="unlit.*KHR_materials_clearcoat"):
        asset = read_gltf(asset_path)
    plain, textured = asset.materials
    assert plain.unlit and textured.unlit and textured.extensions == ("KHR_materials_unlit",)
    for m in (plain, textured):
        f = m.factors
        assert f["emissive"] == FACTOR[:3] and f["base_color"] == FACTOR[:3]
        # the core model only: an unlit material turns on no extension group (no layered BSDF for
        # the scene's other materials either)
        assert set(f) == {"base_color", "metallic", "roughness", "occlusion", "emissive"}
    assert plain.textures == {}
    # the base colour texture is the emission's too (and the base colour's: MASK's alpha, the AOV)
    assert set(textured.textures) == {"emissive", "base_color"}
    assert textured.textures["emissive"].image == 0 and textured.textures["emissive"].colorspace == "srgb"


def _pixel(x, y):
    """(row, column) of the pixel at world (x, y) on the plane z = 0."""
    return int((1.5 - y) / 3.0 * H), int((x + 3.0) / 6.0 * W)


def test_unlit_quads_render_their_colour_under_every_light(asset_path):
    cam = jp.Camera(position=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), projection="orthographic", ymag=1.5,
                    width=W, height=H)
    env = demo_environment()  # a sky with a sun (split out as a disc light) and IBL
    lights = (jp.PointLight(position=(0.0, 2.0, 3.0), color=(1.0, 1.0, 1.0), intensity=500.0),)
    with pytest.warns(UserWarning):
        scene = jp.load_gltf(asset_path, camera=cam, width=W, height=H, environment=env, lights=lights)
    img = np.asarray(jp.render(scene), np.float64)
    background = img[0, 0]
    assert background.max() > 0.01  # the sky is seen behind the quads
    # the plain quad: the factor; with COLOR_0: the factor times the vertex colour
    for (x0, x1), rgb in zip(QUADS[:2], ((1.0, 1.0, 1.0), VERTEX_RGB), strict=True):
        for fx in (0.25, 0.5, 0.75):
            for y in (-0.5, 0.0, 0.5):
                r, c = _pixel(x0 + fx * (x1 - x0), y)
                np.testing.assert_allclose(img[r, c], np.asarray(FACTOR[:3]) * rgb, rtol=1e-6)
    # the textured quad: the factor times each texel (sRGB-decoded); the cut-out texel shows the sky
    x0, x1 = QUADS[2]
    for i, y in enumerate((0.5, -0.5)):
        for j, x in enumerate((x0 + 0.25 * (x1 - x0), x0 + 0.75 * (x1 - x0))):
            r, c = _pixel(x, y)
            if TEXELS[i, j, 3] == 0:
                np.testing.assert_allclose(img[r, c], background, rtol=1e-6)
            else:
                expect = np.asarray(FACTOR[:3]) * srgb_to_linear(TEXELS[i, j, :3] / 255.0)
                np.testing.assert_allclose(img[r, c], expect, rtol=1e-5, atol=1e-7)
