"""A BLEND surface's coverage is the alpha of the whole material (glTF 2.0, "Alpha Coverage"):
baseColorFactor's A x the base colour texture's A, over every lobe (the base's specular
reflection and the clear coat alike). Issue 43, item 2: Khronos ClearCoatTest's "Partial_Coating"
(BLEND, single-sided, black base colour and its alpha from an RGBA texture, roughness 0.03) was
drawn opaque where the texture's A is 0 -- the layers were composited with the geometry's alpha
(factor x COLOR_0's A), so the texture's A never reached the composite and the surface's Fresnel
reflection of the environment (0.04) showed instead of what lies behind it.

The asset is written here (validator-clean): three quads facing the camera, each textured with the
same 3 x 1 RGBA texture (RGB 0; A = 0, 128/255, 1 left to right; NEAREST, magnified: a pixel reads
one texel, except within a pixel of a texel border, where the lookup's footprint taps reach across
it and which is not checked), in front of a uniform environment of radiance 1, seen by an
orthographic camera:

* "partial coating": as the sample's material (single-sided, no clear coat);
* "coated, double-sided": the same with KHR_materials_clearcoat (factor 1, roughness 0.03);
* "half factor": baseColorFactor's A 0.5 (coverage 0.5 x the texture's A).

Oracle (closed forms): the background is the environment's radiance, 1. An opaque black dielectric
(ior 1.5) of roughness 0.03 seen head-on under radiance 1 reflects its specular albedo, F0 =
((1.5 - 1) / (1.5 + 1))^2 = 0.04 at normal incidence for a near-mirror; under a clear coat
(F0 0.04, its lobe's albedo 1 without the Fresnel) KHR_materials_clearcoat's layering gives
0.04 (1 - 0.04) + 0.04 x 1 = 0.0784. A layer of coverage a over the background shows
a C + (1 - a) x 1 (docs/gltf.md, "Alpha"), the texture's A read linearly (128/255, not sRGB-decoded).
Tolerances: 2e-4 on the lit values: seen head-on the split sum gives F0 A + B with A = E(mu = 1) >=
0.999899 and B < 1e-4 at r <= 0.1 (docs/math.md §7.2), the coat's lobe likewise, read from the
interpolated LUT (measured: 4e-8); 1e-6 where the coverage is 0 (float32 of a sum that is the
background's value exactly; it was 0.96 off before the fix).
"""

from __future__ import annotations

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.rendering.gltf_scene import load_gltf

from gltf_writer import ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, FLOAT, USHORT, Builder, assert_valid, png_bytes

pytest.importorskip("embreex")

NEAREST, CLAMP_TO_EDGE = 9728, 33071
TEXEL_ALPHA = (0, 128, 255)  # the texture's A, left to right (8-bit)
CENTRES = (-2.5, 0.0, 2.5)  # the quads' x centres; each is 2 x 2, facing +Z
F0 = 0.04  # ((1.5 - 1) / (1.5 + 1))^2
LIT = {"partial coating": F0, "coated, double-sided": F0 * (1 - F0) + F0, "half factor": F0}
FACTOR_A = {"partial coating": 1.0, "coated, double-sided": 1.0, "half factor": 0.5}
W, H, YMAG = 60, 20, 1.25  # pixels 0.125 wide; the view spans x in [-3.75, 3.75]


def _write_asset(path):
    b = Builder()
    b.used("KHR_materials_clearcoat")
    rgba = np.zeros((1, 3, 4), np.uint8)
    rgba[0, :, 3] = TEXEL_ALPHA
    s = b.add("samplers", {"magFilter": NEAREST, "minFilter": NEAREST, "wrapS": CLAMP_TO_EDGE, "wrapT": CLAMP_TO_EDGE})
    img = b.add("images", {"bufferView": b.view(png_bytes(rgba)), "mimeType": "image/png"})
    tex = b.add("textures", {"source": img, "sampler": s})
    pos = np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]], np.float32)
    attrs = {
        "POSITION": b.accessor(pos, FLOAT, "VEC3", minmax=True, target=ARRAY_BUFFER),
        "NORMAL": b.accessor(np.tile(np.float32([0, 0, 1]), (4, 1)), FLOAT, "VEC3", target=ARRAY_BUFFER),
        "TEXCOORD_0": b.accessor(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32), FLOAT, "VEC2", target=ARRAY_BUFFER),
    }
    idx = b.accessor(np.array([0, 2, 1, 0, 3, 2], np.uint16), USHORT, "SCALAR", target=ELEMENT_ARRAY_BUFFER)
    nodes = []
    for name, x in zip(LIT, CENTRES, strict=True):
        pbr = {"baseColorTexture": {"index": tex}, "metallicFactor": 0.0, "roughnessFactor": 0.03}
        if FACTOR_A[name] != 1.0:
            pbr["baseColorFactor"] = [1.0, 1.0, 1.0, FACTOR_A[name]]
        mat = {"name": name, "alphaMode": "BLEND", "pbrMetallicRoughness": pbr}
        if name.startswith("coated"):
            mat["doubleSided"] = True
            mat["extensions"] = {"KHR_materials_clearcoat": {"clearcoatFactor": 1.0, "clearcoatRoughnessFactor": 0.03}}
        m = b.add("materials", mat)
        mesh = b.add("meshes", {"name": name, "primitives": [{"attributes": attrs, "indices": idx, "material": m}]})
        nodes.append(b.add("nodes", {"name": name, "mesh": mesh, "translation": [x, 0.0, 0.0]}))
    b.add("scenes", {"nodes": nodes})
    b.doc["scene"] = 0
    return b.write(path, mode="glb")


def _expected():
    """Per pixel (H, W): the expected radiance (NaN where not checked: the quads' texel borders and
    edges, within a pixel of them) from the pixel centres' x."""
    x = -YMAG * W / H + (np.arange(W) + 0.5) * (2 * YMAG / H)
    want = np.full(W, np.nan)
    for name, cx in zip(LIT, CENTRES, strict=True):
        u = (x - cx + 1.0) / 2.0
        band = np.floor(3 * u)
        inside = (band >= 0) & (band <= 2) & (np.abs(3 * u - np.round(3 * u)) > 3 * 0.125 / 2)
        a = FACTOR_A[name] * np.asarray(TEXEL_ALPHA, np.float64)[np.clip(band, 0, 2).astype(int)] / 255.0
        want = np.where(inside, a * LIT[name] + (1 - a) * 1.0, want)
    gaps = np.all([np.abs(x - cx) > 1.0 + 0.125 for cx in CENTRES], axis=0)
    want = np.where(gaps, 1.0, want)
    y = YMAG - (np.arange(H) + 0.5) * (2 * YMAG / H)
    rows = np.abs(y) < 1.0 - 0.125  # within the quads' height
    return np.where(rows[:, None], want[None, :], np.where(np.abs(y)[:, None] > 1.0 + 0.125, 1.0, np.nan))


def test_blend_coverage_from_the_texture_covers_every_lobe(tmp_path):
    path = _write_asset(tmp_path / "partial_coating.glb")
    assert_valid(path)
    white = jp.Cubemap(np.ones((6, 8, 8, 3), np.float32))
    cam = jp.Camera(position=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), projection="orthographic", ymag=YMAG, width=W, height=H)
    scene = load_gltf(path, camera=cam, environment=jp.Environment(radiance=white))
    img = np.asarray(jp.render(scene, extract_lights=False, shadows=False), np.float64)
    want = _expected()
    checked = np.isfinite(want)
    # Each quad's three bands (A = 0 shows the background, 1) and the gaps: seven values in all.
    assert checked.sum() > 0.5 * H * W and len(np.unique(want[checked])) == 7
    see_through = checked & (want == 1.0)
    for tol, sel in ((1e-6, see_through), (2e-4, checked & ~see_through)):
        got, exp = img[sel], np.repeat(want[sel][:, None], 3, -1)
        err = np.abs(got - exp).max()
        assert err <= tol, (tol, err)
    # The alpha-0 texels of each quad show the background: nothing of the base's nor the coat's reflection.
    x = -YMAG * W / H + (np.arange(W) + 0.5) * (2 * YMAG / H)
    for cx in CENTRES:
        cols = (x > cx - 1.0 + 0.125) & (x < cx - 1.0 / 3 - 0.125)
        np.testing.assert_allclose(img[H // 2, cols], 1.0, rtol=0, atol=1e-6)
