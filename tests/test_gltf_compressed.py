"""Compressed glTF content: KHR_draco_mesh_compression (geometry) and EXT_texture_webp (images).

The fixtures are written here: a UV sphere encoded with DracoPy (Google's Draco encoder) and WebP
textures encoded with OpenImageIO (libwebp), each checked with the Khronos glTF-Validator when it
is installed. The oracle is the data that was encoded: the sphere's positions, normals, texture
coordinates and colours (to within the quantization the encoder was asked for) and the texels of
lossless WebP images (exactly). Where the npm package @gltf-transform/cli is installed (CI installs
it), assets compressed by that independent writer are read against their uncompressed originals."""

from __future__ import annotations

from pathlib import Path

import DracoPy
import numpy as np
import pytest
from gltf_assets import sphere_grid, textured_cube
from gltf_writer import (
    FLOAT,
    UBYTE,
    USHORT,
    Builder,
    assert_valid,
    gltf_transform,
    gltf_transform_missing,
    png_bytes,
    uv_sphere,
)

from jaxpbr.errors import InputError
from jaxpbr.io.gltf import read_gltf
from jaxpbr.io.gltf._draco import declared_size
from jaxpbr.io.gltf._images import header_shape

DRACO = "KHR_draco_mesh_compression"
#: Quantization bits of the encoded sphere, and the tolerances they give (a unit sphere: positions
#: span 2, texture coordinates 1; normals are octahedral, about pi / 2^bits per axis).
BITS = 14
TOL_POS = 1.5 * 2.0 / (2**BITS - 1)
TOL_UV = 1.5 * 1.0 / (2**BITS - 1)
TOL_N = 4.0 * np.pi / 2**BITS


def _sphere():
    pos, nrm, uv, tri = uv_sphere(12, 24)
    rng = np.random.default_rng(7)
    col = rng.integers(0, 256, (len(pos), 4), dtype=np.uint8)
    return pos.astype(np.float32), nrm.astype(np.float64), uv.astype(np.float64), tri.astype(np.uint32), col


def draco_sphere(out: Path, *, preserve_order=False, uv1=False, colors=True, mode="glb", edit=None):
    """A Draco-compressed sphere (POSITION, NORMAL, TEXCOORD_0, COLOR_0 as normalized UNSIGNED_BYTE)
    and the arrays that were encoded. uv1: a TEXCOORD_1 stored uncompressed beside it (the original
    order: pass preserve_order). colors=False: no COLOR_0. edit(doc, ids): a change to the
    document before it is written."""
    pos, nrm, uv, tri, col = _sphere()
    data = DracoPy.encode(pos, tri, normals=nrm, tex_coord=uv, colors=col if colors else None, quantization_bits=BITS,
                          normal_quantization_bits=BITS, tex_coord_quantization_bits=BITS, preserve_order=preserve_order)
    decoded = DracoPy.decode(data)
    ids = {a["attribute_type"]: a["unique_id"] for a in decoded.attributes}
    n = len(decoded.points)
    b = Builder()
    view = b.view(data)
    attrs = {
        "POSITION": b.add("accessors", {"componentType": FLOAT, "type": "VEC3", "count": n,
                                        "min": decoded.points.min(0).tolist(), "max": decoded.points.max(0).tolist()}),
        "NORMAL": b.add("accessors", {"componentType": FLOAT, "type": "VEC3", "count": n}),
        "TEXCOORD_0": b.add("accessors", {"componentType": FLOAT, "type": "VEC2", "count": n}),
    }
    if colors:
        attrs["COLOR_0"] = b.add("accessors", {"componentType": UBYTE, "type": "VEC4", "count": n, "normalized": True})
    uv1_values = None
    if uv1:
        uv1_values = np.stack([pos[:, 0] * 0.5 + 0.5, pos[:, 2] * 0.25], 1).astype(np.float32)
        attrs["TEXCOORD_1"] = b.accessor(uv1_values, FLOAT, "VEC2")
    ind = b.add("accessors", {"componentType": USHORT, "type": "SCALAR", "count": int(decoded.faces.size)})
    names = {"POSITION": ids[0], "NORMAL": ids[1], "TEXCOORD_0": ids[3], **({"COLOR_0": ids[2]} if colors else {})}
    prim = {"attributes": attrs, "indices": ind, "mode": 4, "extensions": {DRACO: {"bufferView": view, "attributes": names}}}
    mesh = b.add("meshes", {"name": "sphere", "primitives": [prim]})
    b.add("scenes", {"nodes": [b.add("nodes", {"mesh": mesh})]})
    b.doc["scene"] = 0
    b.used(DRACO, required=(DRACO,))
    if edit is not None:
        edit(b.doc, names)
    path = b.write(Path(out) / f"sphere_draco.{'glb' if mode == 'glb' else 'gltf'}", mode=mode)
    return path, {"pos": pos, "nrm": nrm, "uv": uv, "tri": tri, "col": col, "uv1": uv1_values, "decoded_points": n}


def _nearest(a, b):
    """For each row of a, the index of the nearest row of b, and the distance."""
    from scipy.spatial import cKDTree

    dist, k = cKDTree(b).query(a)
    return k, dist


def _cyclic_error(t, r):
    """Per triangle, the smallest max-abs difference between the corners of t (T, 3, C) and of r
    over the three cyclic rotations (the same triangle and winding, whichever corner comes first)."""
    return np.min([np.abs(np.roll(t, s, axis=1) - r).reshape(len(t), -1).max(1) for s in range(3)], axis=0)


@pytest.mark.parametrize("mode", ["glb", "bin"])
def test_draco_sphere_is_the_encoded_mesh(tmp_path, mode):
    path, ref = draco_sphere(tmp_path, mode=mode)
    assert_valid(path)
    asset = read_gltf(path)
    (p,) = asset.primitives
    assert len(p.positions) == ref["decoded_points"]
    # Every decoded triangle is one of the encoded ones, corners in the same cyclic order (the
    # winding), and every encoded triangle is found once.
    tri_d = p.positions[p.indices]  # (T, 3, 3)
    tri_r = ref["pos"][ref["tri"]].astype(np.float64)
    assert tri_d.shape == tri_r.shape
    k, dist = _nearest(tri_d.mean(1), tri_r.mean(1))
    assert dist.max() <= TOL_POS and len(set(k.tolist())) == len(k)
    match = tri_r[k]
    assert _cyclic_error(tri_d, match).max() <= TOL_POS
    # Each decoded vertex against the encoded vertex nearest in position and texture coordinate
    # (the seam's vertices share positions): normals, coordinates and colours.
    key_d = np.concatenate([p.positions, p.texcoord_0], 1)
    key_r = np.concatenate([ref["pos"], ref["uv"]], 1)
    j, dist = _nearest(key_d, key_r)
    assert dist.max() <= 2 * TOL_POS
    assert np.abs(p.texcoord_0 - ref["uv"][j]).max() <= TOL_UV
    assert np.abs(p.normals - ref["nrm"][j]).max() <= TOL_N
    np.testing.assert_array_equal(p.color_0, (ref["col"][j] / 255.0).astype(np.float32))


def test_draco_keeps_uncompressed_attributes_beside_it(tmp_path):
    path, ref = draco_sphere(tmp_path, preserve_order=True, uv1=True)
    assert_valid(path)
    (p,) = read_gltf(path).primitives
    # preserve_order: Draco kept the vertices in their order, so the uncompressed TEXCOORD_1 (read
    # from its accessor, as the spec says for attributes the extension does not name) lines up.
    assert np.abs(p.positions - ref["pos"]).max() <= TOL_POS
    np.testing.assert_array_equal(p.texcoord_1, ref["uv1"])
    np.testing.assert_array_equal(np.sort(p.indices, axis=1), np.sort(ref["tri"].astype(np.int64), axis=1))


@pytest.mark.slow  # (the geometry is checked exactly above; this adds a render's compile)
def test_draco_renders_as_the_uncompressed_sphere(tmp_path):
    from gltf_writer import Writer

    import jaxpbr as jp

    path, ref = draco_sphere(tmp_path, colors=False)
    w = Writer()
    w.node(mesh=w.mesh(ref["pos"], ref["tri"], normals=ref["nrm"].astype(np.float32), uv=ref["uv"].astype(np.float32)))
    plain = w.save(tmp_path / "sphere_plain.glb")
    cam = jp.Camera(position=(0.0, 0.0, 4.0), target=(0.0, 0.0, 0.0), fov_y_deg=40.0, width=40, height=40)
    light = jp.PointLight(position=(2.0, 3.0, 4.0), color=(1.0, 1.0, 1.0), intensity=30.0)
    imgs = []
    for f in (path, plain):
        scene = jp.load_gltf(f, camera=cam, width=40, height=40, lights=(light,))
        imgs.append(np.asarray(jp.render(scene)))
    a, b = imgs
    assert np.isfinite(a).all() and b.max() > 0.05
    # The difference is the quantization (positions 1.2e-4, normals ~2e-4 rad): 0.08 % of the
    # brightest pixel measured.
    assert np.abs(a - b).max() <= 0.005 * b.max()


def _expect_error(path, *fragments):
    with pytest.raises(InputError) as e:
        read_gltf(path)
    msg = str(e.value)
    assert "\n" not in msg
    for f in fragments:
        assert f in msg, msg
    return msg


def test_draco_bad_input_names_the_pointer(tmp_path):
    ext = "/meshes/0/primitives/0/extensions/KHR_draco_mesh_compression"
    # damaged data: the bufferView holds half of the Draco bytes
    def cut(doc, ids):
        doc["bufferViews"][0]["byteLength"] //= 2
    (tmp_path / "cut").mkdir()
    path, _ = draco_sphere(tmp_path / "cut", edit=cut)
    _expect_error(path, ext + "/bufferView", "do not decode as Draco geometry")
    # an attribute id the data does not hold
    def bad_id(doc, ids):
        doc["meshes"][0]["primitives"][0]["extensions"][DRACO]["attributes"]["NORMAL"] = 77
    (tmp_path / "id").mkdir()
    path, _ = draco_sphere(tmp_path / "id", edit=bad_id)
    _expect_error(path, ext + "/attributes/NORMAL", "Draco attribute 77", "does not hold")
    # an accessor whose count is not the decoded data's
    def bad_count(doc, ids):
        doc["accessors"][1]["count"] += 3
    (tmp_path / "count").mkdir()
    path, _ = draco_sphere(tmp_path / "count", edit=bad_count)
    _expect_error(path, "/meshes/0/primitives/0/attributes/NORMAL", "/accessors/1", "decompressed data")
    # an accessor type too narrow for the decoded values (colours stored as 8-bit: indices as
    # UNSIGNED_BYTE cannot hold the 325 vertices' ids)
    def narrow(doc, ids):
        doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]["componentType"] = UBYTE
    (tmp_path / "narrow").mkdir()
    path, _ = draco_sphere(tmp_path / "narrow", edit=narrow)
    _expect_error(path, "/meshes/0/primitives/0/indices", "UNSIGNED_BYTE", "decompressed data holds values outside its range (the first in element")
    # strips are not decoded
    def strip(doc, ids):
        doc["meshes"][0]["primitives"][0]["mode"] = 5
    (tmp_path / "strip").mkdir()
    path, _ = draco_sphere(tmp_path / "strip", edit=strip)
    _expect_error(path, "/meshes/0/primitives/0/mode", "TRIANGLES")


# ---------------------------------------------------------------------------------------------
# EXT_texture_webp
# ---------------------------------------------------------------------------------------------
def webp_bytes(pixels: np.ndarray, *, lossless=True, quality=90) -> bytes:
    """uint8 (H, W, C) pixels encoded as WebP by OpenImageIO (libwebp); straight alpha."""
    import tempfile

    import OpenImageIO as oiio

    H, W, C = pixels.shape
    with tempfile.TemporaryDirectory() as d:
        f = str(Path(d) / "t.webp")
        out = oiio.ImageOutput.create(f)
        spec = oiio.ImageSpec(W, H, C, oiio.UINT8)
        spec.attribute("compression", "lossless" if lossless else f"webp:{quality}")
        spec.attribute("oiio:UnassociatedAlpha", 1)
        assert out.open(f, spec), oiio.geterror()
        out.write_image(np.ascontiguousarray(pixels))
        out.close()
        return Path(f).read_bytes()


def _textured_quad(b: Builder, texture: int):
    pos = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    attrs = {"POSITION": b.accessor(pos, FLOAT, "VEC3", minmax=True), "NORMAL": b.accessor(np.tile([0, 0, 1], (4, 1)), FLOAT, "VEC3"),
             "TEXCOORD_0": b.accessor(uv, FLOAT, "VEC2")}
    ind = b.accessor(np.array([0, 1, 2, 0, 2, 3], np.uint16), USHORT, "SCALAR")
    mat = b.add("materials", {"pbrMetallicRoughness": {"baseColorTexture": {"index": texture}}})
    mesh = b.add("meshes", {"primitives": [{"attributes": attrs, "indices": ind, "material": mat}]})
    b.add("scenes", {"nodes": [b.add("nodes", {"mesh": mesh})]})
    b.doc["scene"] = 0


@pytest.mark.parametrize("channels", [3, 4])
def test_webp_texture_preferred_to_its_fallback(tmp_path, channels):
    rng = np.random.default_rng(channels)
    px = rng.integers(0, 256, (6, 10, channels), dtype=np.uint8)
    if channels == 4:
        px[..., 3] = rng.integers(1, 256, (6, 10))  # (straight alpha; no texel fully transparent)
    b = Builder()
    fallback = b.add("images", {"bufferView": b.view(png_bytes(np.zeros((2, 2, 3), np.uint8))), "mimeType": "image/png"})
    webp = b.add("images", {"bufferView": b.view(webp_bytes(px)), "mimeType": "image/webp"})
    tex = b.add("textures", {"source": fallback, "extensions": {"EXT_texture_webp": {"source": webp}}})
    _textured_quad(b, tex)
    b.used("EXT_texture_webp")
    path = b.write(tmp_path / "webp.glb", mode="glb")
    assert_valid(path)
    asset = read_gltf(path)
    ref = asset.materials[0].textures["base_color"]
    assert ref.image == webp
    assert asset.images[webp].mime_type == "image/webp"
    np.testing.assert_array_equal(np.round(asset.images[webp].pixels * 255).astype(np.uint8), px)


def test_webp_only_texture_when_required(tmp_path):
    px = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3) * 3
    b = Builder()
    webp = b.add("images", {"bufferView": b.view(webp_bytes(px)), "mimeType": "image/webp"})
    tex = b.add("textures", {"extensions": {"EXT_texture_webp": {"source": webp}}})
    _textured_quad(b, tex)
    b.used("EXT_texture_webp", required=("EXT_texture_webp",))
    path = b.write(tmp_path / "webp_only.gltf", mode="data")
    assert_valid(path)
    asset = read_gltf(path)
    assert asset.materials[0].textures["base_color"].image == webp
    # a source that does not exist is named by its pointer
    b.doc["textures"][0]["extensions"]["EXT_texture_webp"]["source"] = 9
    bad = b.write(tmp_path / "webp_bad.gltf", mode="data")
    _expect_error(bad, "/textures/0/extensions/EXT_texture_webp/source", "names image 9, which does not exist")


@pytest.mark.parametrize("channels,lossless", [(3, True), (4, True), (3, False), (4, False)])
def test_webp_header_shape(channels, lossless):
    """The (H, W, C) read from a WebP's first chunk (VP8L lossless, VP8 lossy, VP8X lossy with
    alpha) is the decoded image's, before any pixel is decoded (the memory guard's estimate)."""
    import tempfile

    import OpenImageIO as oiio

    px = np.full((37, 53, channels), 200, np.uint8)
    data = webp_bytes(px, lossless=lossless)
    assert header_shape(lambda o, n: data[o : o + n]) == (37, 53, channels)
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "t.webp"
        f.write_bytes(data)
        inp = oiio.ImageInput.open(str(f))
        spec = inp.spec()
        inp.close()
    assert (spec.height, spec.width, spec.nchannels) == (37, 53, channels)


# ---------------------------------------------------------------------------------------------
# Files compressed by an independent writer (gltf-transform)
# ---------------------------------------------------------------------------------------------
def _triangles(asset):
    """Per primitive, the world-space triangles (T, 3, 3) float64."""
    return [p.positions[p.indices].astype(np.float64) for p in asset.primitives]


def _draco_views(path):
    """The Draco bitstreams of a .glb's primitives (read with pygltflib, independently of jaxpbr)."""
    import pygltflib

    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()
    out = []
    for mesh in g.meshes:
        for prim in mesh.primitives:
            ext = (prim.extensions or {}).get(DRACO)
            if ext is not None:
                v = g.bufferViews[ext["bufferView"]]
                out.append(blob[(v.byteOffset or 0) : (v.byteOffset or 0) + v.byteLength])
    assert out
    return out


def test_gltf_transform_draco_reads_as_the_original(tmp_path):
    why = gltf_transform_missing()
    if why:
        pytest.skip(why)
    for make in (sphere_grid, textured_cube):
        src = make(tmp_path)
        out = tmp_path / f"{src.stem}_draco.glb"
        gltf_transform("draco", src, out, "--quantize-position", BITS)
        assert_valid(out)
        a, c = read_gltf(src), read_gltf(out)
        assert "KHR_draco_mesh_compression" in c.extensions_used
        assert len(a.primitives) == len(c.primitives)
        # the header parser on this encoder's (draco3dgltf's) bitstreams: the counts DracoPy decodes
        for data in _draco_views(out):
            decoded = DracoPy.decode(data)
            assert declared_size(data) == (len(decoded.faces), len(decoded.points))
        span = max(float(np.ptp(np.concatenate([p.positions for p in a.primitives]), axis=0).max()), 1e-9)
        for pa, pc, ta, tc in zip(a.primitives, c.primitives, _triangles(a), _triangles(c), strict=True):
            assert ta.shape == tc.shape
            # each compressed triangle is an original one (the encoder may reorder them), within
            # the quantization of the primitive's bounding box (1.5 steps of the mesh's span)
            k, dist = _nearest(tc.mean(1), ta.mean(1))
            tol = 1.5 * span / (2**BITS - 1)
            assert dist.max() <= tol and len(set(k.tolist())) == len(k)
            assert _cyclic_error(tc, ta[k]).max() <= tol
            assert (pc.texcoord_0 is None) == (pa.texcoord_0 is None)


def test_gltf_transform_webp_lossless_reads_as_the_original(tmp_path):
    why = gltf_transform_missing()
    if why:
        pytest.skip(why)
    src = textured_cube(tmp_path)
    out = tmp_path / "cube_webp.glb"
    gltf_transform("webp", src, out, "--lossless", "true")
    assert_valid(out)
    a, c = read_gltf(src), read_gltf(out)
    assert "EXT_texture_webp" in c.extensions_used and [im.mime_type for im in c.images] == ["image/webp"]
    for ia, ic in zip(a.images, c.images, strict=True):
        np.testing.assert_array_equal(ic.pixels, ia.pixels)


#: gltf-transform pipelines whose output jaxpbr reads: KHR_mesh_quantization in an interleaved
#: vertex buffer; its `optimize` (deduplication, flattening, joining the 49 spheres into one
#: primitive, welding, a palette texture for their 49 materials, pruning) with Draco compression.
PIPELINES = {
    "quantize-interleaved": ("quantize", "--vertex-layout", "interleaved"),
    "optimize-draco": ("optimize", "--compress", "draco", "--simplify", "false", "--texture-compress", "false"),
}


def _transformed(tmp_path, name):
    why = gltf_transform_missing()
    if why:
        pytest.skip(why)
    src = sphere_grid(tmp_path)
    out = tmp_path / f"grid_{name}.glb"
    cmd, *opts = PIPELINES[name]
    gltf_transform(cmd, src, out, *opts)
    assert_valid(out)
    return src, out


@pytest.mark.parametrize("name", list(PIPELINES))
def test_gltf_transform_pipeline_keeps_the_surfaces(tmp_path, name):
    src, out = _transformed(tmp_path, name)
    a, c = read_gltf(src), read_gltf(out)
    ta, tc = np.concatenate(_triangles(a)), np.concatenate(_triangles(c))
    assert ta.shape == tc.shape
    # Every triangle, in world space, is an original one with its winding, within the positions'
    # quantization (14 bits over the largest mesh's span, 2.0, or the joined mesh's, 6.8).
    tol = 1.5 * 6.8 / (2**14 - 1)
    k, dist = _nearest(tc.mean(1), ta.mean(1))
    assert dist.max() <= tol and len(set(k.tolist())) == len(k)
    assert _cyclic_error(tc, ta[k]).max() <= tol
    # and the shading normals at its corners are the original's (10-bit quantization: 2e-3 rad),
    # corner for corner (positions and normals side by side)
    na = np.concatenate([p.normals[p.indices] for p in a.primitives])[k]
    nc = np.concatenate([p.normals[p.indices] for p in c.primitives])
    err = _cyclic_error(np.concatenate([tc / tol, nc / 4e-3], -1), np.concatenate([ta[k] / tol, na / 4e-3], -1))
    assert err.max() <= 1.0


@pytest.mark.slow
@pytest.mark.parametrize("name", list(PIPELINES))
def test_gltf_transform_pipeline_renders_as_the_original(tmp_path, name):
    """The same image: for optimize, the 49 materials come from the palette texture it made."""
    import jaxpbr as jp

    src, out = _transformed(tmp_path, name)
    cam = jp.Camera(position=(0.0, 0.0, 15.0), target=(0.0, 0.0, 0.0), fov_y_deg=30.0, width=64, height=64)
    light = jp.PointLight(position=(5.0, 8.0, 20.0), color=(1.0, 1.0, 1.0), intensity=3000.0)
    a, c = (np.asarray(jp.render(jp.load_gltf(f, camera=cam, width=64, height=64, lights=(light,)))) for f in (src, out))
    hit_a, hit_c = a.max(-1) > 0, c.max(-1) > 0
    # Silhouette pixels whose centres lie within the positions' quantization of an edge may change
    # sides: a few of the 4096.
    assert (hit_a != hit_c).mean() <= 0.01
    both = hit_a & hit_c
    rel = np.abs(c - a).max(-1)[both] / a.max(-1)[both]
    # Elsewhere the normals' 10-bit quantization, and for optimize the palette's 8-bit texels for the
    # materials' factors (base colour in sRGB, metallic, roughness). Measured: median 0.05 % and
    # 0.19 %, 90th percentile 0.19 % and 1.0 %.
    assert np.median(rel) <= 0.005 and np.percentile(rel, 90) <= 0.02


# ---------------------------------------------------------------------------------------------
# The Draco header's counts, read before decoding (the memory check)
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("preserve_order", [False, True])  # edgebreaker, sequential connectivity
@pytest.mark.parametrize("metadata", [False, True])
def test_draco_header_declares_the_decoded_size(preserve_order, metadata):
    pos, nrm, _, tri, _ = _sphere()
    data = DracoPy.encode(pos, tri, normals=nrm, preserve_order=preserve_order, create_metadata=metadata)
    decoded = DracoPy.decode(data)
    assert declared_size(data) == (len(decoded.faces), len(decoded.points))
    assert declared_size(data[:12]) is None and declared_size(b"PNG" + data[3:]) is None


def _varuint(n: int) -> bytes:
    out = bytearray()
    while True:
        b, n = n & 0x7F, n >> 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


@pytest.mark.parametrize("method", [0, 1])
def test_draco_declaring_billions_is_refused_before_decoding(tmp_path, monkeypatch, method):
    """A few bytes whose header declares 2 billion triangles: refused by the memory check, naming
    the primitive's extension, before DracoPy allocates anything."""
    from jaxpbr._memory import MemoryLimitError

    head = b"DRACO" + bytes([2, 2, 1, method, 0, 0])
    if method == 0:  # sequential: num_faces, num_points
        head += _varuint(2_000_000_000) + _varuint(1_000_000_000) + b"\x01"
    else:  # edgebreaker: traversal type, num_encoded_vertices, num_faces
        head += b"\x00" + _varuint(1_000_000_000) + _varuint(2_000_000_000)
    assert declared_size(head) == (2_000_000_000, 1_000_000_000)
    b = Builder()
    attrs = {"POSITION": b.add("accessors", {"componentType": FLOAT, "type": "VEC3", "count": 3,
                                             "min": [0, 0, 0], "max": [1, 1, 0]})}
    ind = b.add("accessors", {"componentType": USHORT, "type": "SCALAR", "count": 3})
    ext = {DRACO: {"bufferView": b.view(head + bytes(16)), "attributes": {"POSITION": 0}}}
    mesh = b.add("meshes", {"primitives": [{"attributes": attrs, "indices": ind, "extensions": ext}]})
    b.add("scenes", {"nodes": [b.add("nodes", {"mesh": mesh})]})
    b.doc["scene"] = 0
    b.used(DRACO, required=(DRACO,))
    path = b.write(tmp_path / "bomb.glb", mode="glb")
    monkeypatch.setattr(DracoPy, "decode", lambda data: pytest.fail("decoded before the memory check"))
    with pytest.raises(MemoryLimitError) as e:
        read_gltf(path)
    msg = str(e.value)
    assert "/meshes/0/primitives/0/extensions/KHR_draco_mesh_compression" in msg and "2000000000 triangles" in msg
