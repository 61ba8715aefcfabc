"""glTF 2.0 loader (jaxpbr.io.gltf): fixtures are written here byte by byte (JSON + struct/NumPy),
checked with the Khronos glTF-Validator when it is installed, and the loader's output is compared
with closed forms (matrices built here), geometric invariants (outward normals, counter-clockwise
fronts) and trimesh as an independent reader."""

from __future__ import annotations

import base64
import json
import math
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
from gltf_writer import (  # the writer and validator runner these tests share
    _NP,
    ARRAY_BUFFER,
    BYTE,
    CUBE_FACES,
    ELEMENT_ARRAY_BUFFER,
    FLOAT,
    SHORT,
    UBYTE,
    UINT,
    USHORT,
    Builder,
    assert_valid,
    png_bytes,
)

from jaxpbr.errors import InputError
from jaxpbr.io.gltf import GltfAsset, read_gltf


# ---------------------------------------------------------------------------------------------
# Matrices of the tests (independent of the loader's)
# ---------------------------------------------------------------------------------------------
def T(x, y, z):
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def S(x, y, z):
    return np.diag([x, y, z, 1.0])


def Rz(a):
    c, s = math.cos(a), math.sin(a)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


def Rx(a):
    c, s = math.cos(a), math.sin(a)
    m = np.eye(4)
    m[1:3, 1:3] = [[c, -s], [s, c]]
    return m


def Ry(a):
    c, s = math.cos(a), math.sin(a)
    m = np.eye(4)
    m[0, 0], m[0, 2], m[2, 0], m[2, 2] = c, s, -s, c
    return m


def apply(m, p):
    return np.asarray(p, np.float64) @ m[:3, :3].T + m[:3, 3]


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# The cube: 24 vertices interleaved (POSITION, NORMAL, TEXCOORD_0, TANGENT; byteStride 48)
# ---------------------------------------------------------------------------------------------


def cube_arrays():
    pos, nrm, uv, tan, bit, idx = [], [], [], [], [], []
    for f, (n, u, v) in enumerate(CUBE_FACES):
        n, u, v = (np.array(a, np.float64) for a in (n, u, v))
        for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            pos.append(0.5 * n + 0.5 * su * u + 0.5 * sv * v)
            nrm.append(n)
            uv.append(((su + 1) / 2, (1 - sv) / 2))
            tan.append((*u, 1.0))
            bit.append(v)
        b = 4 * f
        idx += [b, b + 1, b + 2, b, b + 2, b + 3]
    return (np.array(pos), np.array(nrm), np.array(uv), np.array(tan), np.array(bit),
            np.array(idx, np.uint16).reshape(-1, 3))


def add_cube(b: Builder, name="cube", material=None) -> int:
    pos, nrm, uv, tan, _, idx = cube_arrays()
    rec = np.zeros(len(pos), dtype=[("p", "<f4", 3), ("n", "<f4", 3), ("uv", "<f4", 2), ("t", "<f4", 4)])
    rec["p"], rec["n"], rec["uv"], rec["t"] = pos, nrm, uv, tan
    b.view(b"\xAA" * 20)  # something before, so that the bufferView has a byteOffset
    view = b.view(rec.tobytes(), stride=rec.dtype.itemsize, target=ARRAY_BUFFER)
    attrs = {
        "POSITION": b.accessor(pos, FLOAT, "VEC3", view=view, offset=0, minmax=True),
        "NORMAL": b.accessor(nrm, FLOAT, "VEC3", view=view, offset=12),
        "TEXCOORD_0": b.accessor(uv, FLOAT, "VEC2", view=view, offset=24),
        "TANGENT": b.accessor(tan, FLOAT, "VEC4", view=view, offset=32),
    }
    prim = {"attributes": attrs, "indices": b.accessor(idx.ravel(), USHORT, "SCALAR", target=ELEMENT_ARRAY_BUFFER)}
    if material is not None:
        prim["material"] = material
    return b.add("meshes", {"name": name, "primitives": [prim]})


def colmajor(m):
    return [float(x) for x in m.T.ravel()]


# Node transforms of the hierarchy fixture, and the world matrices they make.
_Q30 = (0.0, 0.0, math.sin(math.radians(15)), math.cos(math.radians(15)))  # Rz(30 deg), xyzw
M_ROOT = T(1, 2, 3) @ Rz(math.radians(30)) @ S(2, 1, 1)
M_MATRIX = M_ROOT @ (T(0, 5, 0) @ Rx(math.radians(90)))
M_MIRROR = M_ROOT @ (T(-4, 0, 0) @ S(-1, 1, 1))


@pytest.fixture(scope="module")
def hierarchy(tmp_path_factory):
    """The cube instanced by three nodes: TRS root, a matrix child, a mirrored child; a fourth node
    outside the scene; a second scene."""
    b = Builder()
    mesh = add_cube(b)
    b.add("nodes", {"name": "root", "mesh": mesh, "translation": [1, 2, 3], "rotation": list(_Q30),
                    "scale": [2, 1, 1], "children": [1, 2]})
    b.add("nodes", {"name": "by-matrix", "mesh": mesh, "matrix": colmajor(T(0, 5, 0) @ Rx(math.radians(90)))})
    b.add("nodes", {"name": "mirror", "mesh": mesh, "translation": [-4, 0, 0], "scale": [-1, 1, 1]})
    b.add("nodes", {"name": "elsewhere", "mesh": mesh, "translation": [100, 0, 0]})
    b.add("scenes", {"nodes": [0]})
    b.add("scenes", {"nodes": [3]})
    b.doc["scene"] = 0
    path = b.write(tmp_path_factory.mktemp("hierarchy") / "cube.gltf")
    assert_valid(path)
    return path


def test_hierarchy_world_positions_closed_form(hierarchy):
    asset = read_gltf(hierarchy)
    assert isinstance(asset, GltfAsset) and asset.scene == 0
    assert [p.node for p in asset.primitives] == [0, 1, 2]
    pos = cube_arrays()[0]
    for prim, m in zip(asset.primitives, (M_ROOT, M_MATRIX, M_MIRROR)):
        assert prim.positions.dtype == np.float32 and prim.positions.shape == (24, 3)
        np.testing.assert_allclose(prim.positions, apply(m, pos), atol=2e-6)
        np.testing.assert_allclose(prim.world_matrix, m, atol=1e-12)
        assert prim.indices.dtype == np.int32 and prim.indices.shape == (12, 3)
    allpos = np.concatenate([apply(m, pos) for m in (M_ROOT, M_MATRIX, M_MIRROR)])
    np.testing.assert_allclose(asset.bounds, [allpos.min(0), allpos.max(0)], atol=2e-6)
    assert asset.summary()["triangles"] == 36 and asset.summary()["primitives"] == 3
    assert asset.generator == "jaxpbr tests"


def test_hierarchy_normals_winding_and_tangents(hierarchy):
    """Outward normals, counter-clockwise fronts (also under the mirror), bitangent = A @ v."""
    asset = read_gltf(hierarchy)
    bit = cube_arrays()[4]
    for prim, m in zip(asset.primitives, (M_ROOT, M_MATRIX, M_MIRROR)):
        p = prim.positions.astype(np.float64)
        tri = p[prim.indices]
        face = unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
        centre = apply(m, np.zeros(3))
        assert np.all(np.einsum("ij,ij->i", face, tri.mean(axis=1) - centre) > 0)  # outward, CCW
        for k in range(3):  # vertex normals agree with the face they belong to
            np.testing.assert_allclose(prim.normals[prim.indices[:, k]], face, atol=1e-5)
        np.testing.assert_allclose(np.linalg.norm(prim.normals, axis=1), 1, atol=1e-6)
        det = np.linalg.det(m[:3, :3])
        np.testing.assert_array_equal(prim.tangents[:, 3], np.sign(det))
        bitangent = np.cross(prim.normals, prim.tangents[:, :3]) * prim.tangents[:, 3:]
        np.testing.assert_allclose(bitangent, unit(bit @ m[:3, :3].T), atol=1e-5)
        np.testing.assert_allclose(prim.tangents[:, :3], unit(cube_arrays()[3][:, :3] @ m[:3, :3].T), atol=1e-6)
    mirror = asset.primitives[2]
    np.testing.assert_array_equal(mirror.indices, cube_arrays()[5][:, [0, 2, 1]])


def test_hierarchy_other_scene_and_bad_scene(hierarchy):
    asset = read_gltf(hierarchy, scene=1)
    assert [p.node for p in asset.primitives] == [3]
    np.testing.assert_allclose(asset.primitives[0].positions, cube_arrays()[0] + (100, 0, 0), atol=1e-6)
    with pytest.raises(InputError, match="scene 5 does not exist"):
        read_gltf(hierarchy, scene=5)


def test_hierarchy_against_trimesh(hierarchy):
    trimesh = pytest.importorskip("trimesh")
    scene = trimesh.load(hierarchy, force="scene")
    theirs = []
    for node in scene.graph.nodes_geometry:
        transform, geom = scene.graph[node]
        mesh = scene.geometry[geom]
        theirs.append((apply(transform, mesh.vertices), len(mesh.faces)))
    ours = read_gltf(hierarchy).primitives
    assert sorted(n for _, n in theirs) == sorted(p.num_triangles for p in ours)

    def key(v):
        return sorted(map(tuple, np.round(v, 4)))

    assert sorted(key(np.unique(v, axis=0)) for v, _ in theirs) == sorted(
        key(np.unique(p.positions.astype(np.float64), axis=0)) for p in ours)


# ---------------------------------------------------------------------------------------------
# Topologies: strip, fan; points/lines refused
# ---------------------------------------------------------------------------------------------
def _planar(b, positions, mode, indices=None, name="m"):
    prim = {"attributes": {"POSITION": b.accessor(np.asarray(positions, np.float32), FLOAT, "VEC3", minmax=True),
                           "NORMAL": b.accessor(np.tile(np.float32([0, 0, 1]), (len(positions), 1)), FLOAT, "VEC3")},
            "mode": mode}
    if indices is not None:
        prim["indices"] = b.accessor(np.asarray(indices, np.uint8), UBYTE, "SCALAR")
    return b.add("meshes", {"name": name, "primitives": [prim]})


def test_strip_and_fan(tmp_path):
    b = Builder()
    # Strip zig-zag along x: 0 (0,0) 1 (0,1) 2 (1,0) 3 (1,1) 4 (2,0) 5 (2,1) -> spec order (i, i+1+i%2, i+2-i%2).
    strip = [(0, 0, 0), (0, 1, 0), (1, 0, 0), (1, 1, 0), (2, 0, 0), (2, 1, 0)]
    # The strip's vertex order makes clockwise triangles in +z view... so order it the CCW way:
    strip = [(0, 1, 0), (0, 0, 0), (1, 1, 0), (1, 0, 0), (2, 1, 0), (2, 0, 0)]
    fan = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (-1, 1, 0)]
    m_strip = _planar(b, strip, 5, name="strip")
    m_fan = _planar(b, fan, 6, indices=[0, 1, 2, 3, 4], name="fan")
    b.add("nodes", {"mesh": m_strip})
    b.add("nodes", {"mesh": m_fan})
    b.add("scenes", {"nodes": [0, 1]})
    path = b.write(tmp_path / "topo.gltf")
    assert_valid(path)
    s, f = read_gltf(path).primitives
    np.testing.assert_array_equal(s.indices, [[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4]])
    np.testing.assert_array_equal(f.indices, [[1, 2, 0], [2, 3, 0], [3, 4, 0]])
    for prim in (s, f):  # every triangle is counter-clockwise seen from +z
        tri = prim.positions[prim.indices].astype(np.float64)
        z = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2]
        assert np.all(z > 0)


@pytest.mark.parametrize("mode,name", [(0, "POINTS"), (1, "LINES"), (2, "LINE_LOOP"), (3, "LINE_STRIP")])
def test_points_and_lines_refused(tmp_path, mode, name):
    b = Builder()
    m = _planar(b, [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], mode, name="wire")
    b.add("nodes", {"mesh": m})
    b.add("scenes", {"nodes": [0]})
    path = b.write(tmp_path / f"mode{mode}.gltf")
    if mode == 1:
        assert_valid(path)
    with pytest.raises(InputError) as e:
        read_gltf(path)
    assert "'wire'" in str(e.value) and "primitive 0" in str(e.value) and name in str(e.value)
    assert "mode5.gltf" not in str(e.value) and f"mode{mode}.gltf" in str(e.value)


# ---------------------------------------------------------------------------------------------
# Accessors: sparse, no bufferView, normalized integers, every component type; data URIs; GLB
# ---------------------------------------------------------------------------------------------
def test_sparse_accessors_and_normalized_attributes(tmp_path):
    b = Builder()
    base = np.float32([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    subst = np.float32([[5, 0, 0], [0, 7, 0]])
    sparse = {"count": 2, "indices": {"bufferView": b.view(np.uint16([1, 3]).tobytes()), "componentType": USHORT},
              "values": {"bufferView": b.view(subst.tobytes())}}
    final = base.copy()
    final[[1, 3]] = subst
    pos = b.accessor(base, FLOAT, "VEC3", sparse=sparse)
    b.doc["accessors"][pos]["min"] = final.min(0).tolist()
    b.doc["accessors"][pos]["max"] = final.max(0).tolist()
    # TEXCOORD_1 without a bufferView: zeros, with one sparse value.
    sp_uv = {"count": 1, "indices": {"bufferView": b.view(np.uint8([2, 0, 0, 0]).tobytes()), "componentType": UBYTE},
             "values": {"bufferView": b.view(np.float32([0.25, 0.5]).tobytes())}}
    uv1 = b.accessor(np.zeros((4, 2)), FLOAT, "VEC2", count=4, sparse=sp_uv)
    b.doc["accessors"][uv1].pop("bufferView", None)
    uv_raw = np.uint16([[0, 65535], [32768, 16384], [1, 2], [65535, 0]])
    colour_raw = np.uint8([[255, 0, 128], [1, 2, 3], [0, 0, 0], [255, 255, 255]])
    attrs = {
        "POSITION": pos,
        "NORMAL": b.accessor(np.float32([[0, 0, 1]] * 4), FLOAT, "VEC3"),
        "TEXCOORD_0": b.accessor(uv_raw, USHORT, "VEC2", normalized=True),
        "TEXCOORD_1": uv1,
        "COLOR_0": b.accessor(colour_raw, UBYTE, "VEC3", normalized=True),
    }
    idx = b.accessor(np.uint32([0, 1, 2, 0, 2, 3]), UINT, "SCALAR")
    b.add("meshes", {"primitives": [{"attributes": attrs, "indices": idx}]})
    b.add("nodes", {"mesh": 0})
    b.add("scenes", {"nodes": [0]})
    path = b.write(tmp_path / "sparse.gltf", mode="data")
    assert_valid(path)
    assert "data:application/octet-stream;base64," in path.read_text()
    (prim,) = read_gltf(path).primitives
    np.testing.assert_array_equal(prim.positions, final)
    np.testing.assert_allclose(prim.texcoord_0, uv_raw / 65535.0, rtol=1e-6)
    np.testing.assert_array_equal(prim.texcoord_1, [[0, 0], [0, 0], [0.25, 0.5], [0, 0]])
    np.testing.assert_allclose(prim.color_0[:, :3], colour_raw / 255.0, rtol=1e-6)
    np.testing.assert_array_equal(prim.color_0[:, 3], 1.0)
    np.testing.assert_array_equal(prim.indices, [[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize("ctype,normalized", [(FLOAT, False), (BYTE, False), (BYTE, True), (UBYTE, False),
                                              (UBYTE, True), (SHORT, False), (SHORT, True), (USHORT, False),
                                              (USHORT, True)])
def test_position_component_types(tmp_path, ctype, normalized):
    """KHR_mesh_quantization positions; indices in all three unsigned types; normalized BYTE normals."""
    info = np.iinfo(_NP[ctype]) if ctype != FLOAT else None
    raw = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]] if info is None or info.min == 0 else
                   [[info.min, 0, 0], [info.max, 0, 0], [0, info.max, 0]], dtype=_NP[ctype])
    if info is not None and info.min == 0:
        raw = np.array([[0, 0, 0], [info.max, 0, 0], [0, info.max, 0]], dtype=_NP[ctype])
    if normalized:
        scale = float(info.max)
        expect = np.maximum(raw.astype(np.float64) / scale, -1.0)  # spec: max(c / (2^(n-1) - 1), -1)
    else:
        expect = raw.astype(np.float64)
    b = Builder()
    b.used("KHR_mesh_quantization", required=["KHR_mesh_quantization"])
    pos = b.accessor(raw, ctype, "VEC3", normalized=normalized, minmax=True)
    nrm = b.accessor(np.int8([[0, 0, 127]] * 3), BYTE, "VEC3", normalized=True)
    itype = {FLOAT: UINT, BYTE: UBYTE, UBYTE: UBYTE}.get(ctype, USHORT)
    idx = b.accessor(np.array([0, 1, 2], _NP[itype]), itype, "SCALAR")
    b.add("meshes", {"primitives": [{"attributes": {"POSITION": pos, "NORMAL": nrm}, "indices": idx}]})
    b.add("nodes", {"mesh": 0, "scale": [0.5, 0.5, 0.5]})
    b.add("scenes", {"nodes": [0]})
    path = b.write(tmp_path / "q.glb", mode="glb")
    assert_valid(path)
    (prim,) = read_gltf(path).primitives
    np.testing.assert_allclose(prim.positions, 0.5 * expect, rtol=1e-6)
    np.testing.assert_array_equal(prim.normals, [[0, 0, 1]] * 3)
    if ctype == BYTE and normalized:
        assert prim.positions[0, 0] == -0.5  # -128 clamps to -1


def test_normalized_byte_clamp_in_normals(tmp_path):
    b = Builder()
    b.used("KHR_mesh_quantization", required=["KHR_mesh_quantization"])
    pos = b.accessor(np.float32([[0, 0, 0], [0, 1, 0], [1, 0, 0]]), FLOAT, "VEC3", minmax=True)
    nrm = b.accessor(np.int8([[0, 0, -128], [0, 0, -127], [0, 0, -128]]), BYTE, "VEC3", normalized=True)
    b.add("meshes", {"primitives": [{"attributes": {"POSITION": pos, "NORMAL": nrm}}]})
    b.add("nodes", {"mesh": 0})
    b.add("scenes", {"nodes": [0]})
    path = b.write(tmp_path / "n.gltf")
    assert_valid(path)
    (prim,) = read_gltf(path).primitives
    np.testing.assert_array_equal(prim.normals, [[0, 0, -1]] * 3)
    np.testing.assert_array_equal(prim.indices, [[0, 1, 2]])  # non-indexed: 0..V-1


def test_flat_normals_when_missing(tmp_path):
    """Tetrahedron with shared vertices and no NORMAL: unwelded, one face normal per triangle; the
    file's tangents are ignored (spec)."""
    b = Builder()
    p = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    tris = np.uint16([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    attrs = {"POSITION": b.accessor(p, FLOAT, "VEC3", minmax=True),
             "TANGENT": b.accessor(np.float32([[1, 0, 0, 1]] * 4), FLOAT, "VEC4")}
    b.add("meshes", {"primitives": [{"attributes": attrs, "indices": b.accessor(tris.ravel(), USHORT, "SCALAR")}]})
    b.add("nodes", {"mesh": 0, "translation": [0, 0, 2]})
    b.add("scenes", {"nodes": [0]})
    path = b.write(tmp_path / "tet.gltf")
    assert_valid(path)
    (prim,) = read_gltf(path).primitives
    assert prim.flat_normals and prim.tangents is None
    assert prim.positions.shape == (12, 3)
    np.testing.assert_array_equal(prim.indices, np.arange(12).reshape(4, 3))
    expect = np.repeat([[0, 0, -1], [0, -1, 0], [-1, 0, 0], [1 / math.sqrt(3)] * 3], 3, axis=0)
    np.testing.assert_allclose(prim.normals, expect, atol=1e-6)
    np.testing.assert_allclose(prim.positions, p[tris.ravel()] + (0, 0, 2), atol=0)


# ---------------------------------------------------------------------------------------------
# Materials, textures, images
# ---------------------------------------------------------------------------------------------
_IMG = np.array([[[255, 0, 0, 255], [0, 255, 0, 128]], [[0, 0, 255, 0], [10, 20, 30, 40]]], np.uint8)
_ALL_EXT = ["KHR_materials_clearcoat", "KHR_materials_sheen", "KHR_materials_specular", "KHR_materials_ior",
            "KHR_materials_anisotropy", "KHR_materials_emissive_strength", "KHR_materials_transmission",
            "KHR_materials_volume"]


def _quad(b, material=None, uv1=True, tangents=True):
    pos = np.float32([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    attrs = {"POSITION": b.accessor(pos, FLOAT, "VEC3", minmax=True),
             "NORMAL": b.accessor(np.float32([[0, 0, 1]] * 4), FLOAT, "VEC3"),
             "TEXCOORD_0": b.accessor(np.float32([[0, 1], [1, 1], [1, 0], [0, 0]]), FLOAT, "VEC2")}
    if uv1:
        attrs["TEXCOORD_1"] = b.accessor(np.float32([[0, 0], [1, 0], [1, 1], [0, 1]]), FLOAT, "VEC2")
    if tangents:
        attrs["TANGENT"] = b.accessor(np.float32([[1, 0, 0, 1]] * 4), FLOAT, "VEC4")
    prim = {"attributes": attrs, "indices": b.accessor(np.uint8([0, 1, 2, 0, 2, 3]), UBYTE, "SCALAR")}
    if material is not None:
        prim["material"] = material
    return prim


@pytest.fixture(scope="module")
def materials_file(tmp_path_factory):
    b = Builder()
    b.used(*_ALL_EXT, "KHR_texture_transform", "KHR_materials_iridescence")
    png = png_bytes(_IMG)
    b.add("images", {"name": "checker", "bufferView": b.view(png), "mimeType": "image/png"})
    b.add("images", {"name": "inline", "uri": "data:image/png;base64," + base64.b64encode(png_bytes(_IMG[:1, :1, :3])).decode()})
    b.add("samplers", {"wrapS": 33071, "wrapT": 33648, "magFilter": 9728, "minFilter": 9985})
    b.add("textures", {"source": 0, "sampler": 0})
    b.add("textures", {"source": 0})
    b.add("textures", {"source": 1})
    tt = {"KHR_texture_transform": {"offset": [0.1, 0.2], "rotation": 0.3, "scale": [2, 3]}}
    everything = {
        "name": "everything",
        "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.25, 0.125, 0.75], "metallicFactor": 0.3,
                                 "roughnessFactor": 0.6,
                                 "baseColorTexture": {"index": 0, "texCoord": 1, "extensions": tt},
                                 "metallicRoughnessTexture": {"index": 1}},
        "normalTexture": {"index": 1, "scale": 0.8},
        "occlusionTexture": {"index": 1, "strength": 0.4},
        "emissiveTexture": {"index": 2, "extensions": {"KHR_texture_transform": {"texCoord": 1}}},
        "emissiveFactor": [1, 0.5, 0.25],
        "alphaMode": "MASK", "alphaCutoff": 0.3, "doubleSided": True,
        "extensions": {
            "KHR_materials_clearcoat": {"clearcoatFactor": 0.9, "clearcoatRoughnessFactor": 0.2,
                                        "clearcoatTexture": {"index": 1}, "clearcoatRoughnessTexture": {"index": 1},
                                        "clearcoatNormalTexture": {"index": 1, "scale": 0.5}},
            "KHR_materials_sheen": {"sheenColorFactor": [0.1, 0.2, 0.3], "sheenColorTexture": {"index": 0},
                                    "sheenRoughnessTexture": {"index": 1}},
            "KHR_materials_specular": {"specularFactor": 0.7, "specularTexture": {"index": 1},
                                       "specularColorTexture": {"index": 0}},
            "KHR_materials_ior": {"ior": 1.33},
            "KHR_materials_anisotropy": {"anisotropyStrength": 0.5, "anisotropyRotation": 0.25,
                                         "anisotropyTexture": {"index": 1}},
            "KHR_materials_emissive_strength": {"emissiveStrength": 5},
            "KHR_materials_transmission": {"transmissionFactor": 0.6, "transmissionTexture": {"index": 1}},
            "KHR_materials_volume": {"thicknessFactor": 0.1, "attenuationColor": [0.9, 0.8, 0.7],
                                     "thicknessTexture": {"index": 1}},
        },
    }
    b.add("materials", everything)
    b.add("materials", {"name": "volume-defaults", "extensions": {"KHR_materials_volume": {},
                                                                  "KHR_materials_iridescence": {}}})
    b.add("meshes", {"name": "quads", "primitives": [_quad(b, 0), _quad(b, 1), _quad(b, None)]})
    b.add("nodes", {"mesh": 0})
    b.add("scenes", {"nodes": [0]})
    path = b.write(tmp_path_factory.mktemp("materials") / "materials.glb", mode="glb")
    assert_valid(path)
    return path


def _load_quiet(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_gltf(path, **kw)


def test_material_factors(materials_file):
    asset = _load_quiet(materials_file)
    m0, m1, default = asset.materials
    assert [p.material for p in asset.primitives] == [0, 1, 2]
    assert m0.name == "everything" and set(m0.extensions) == set(_ALL_EXT)
    expect = {
        "base_color": (0.5, 0.25, 0.125), "metallic": 0.3, "roughness": 0.6, "occlusion": 1.0,
        "emissive": (1.0, 0.5, 0.25),
        "clearcoat": 0.9, "clearcoat_roughness": 0.2,
        "sheen_color": (0.1, 0.2, 0.3), "sheen_roughness": 0.0,
        "specular": 0.7, "specular_color": (1.0, 1.0, 1.0),
        "ior": 1.33,
        "anisotropy_strength": 0.5, "anisotropy_rotation": 0.25,
        "emissive_strength": 5.0,
        "transmission": 0.6,
        "thickness": 0.1, "attenuation_distance": math.inf, "attenuation_color": (0.9, 0.8, 0.7),
    }
    assert set(m0.factors) == set(expect)
    for k, v in expect.items():
        np.testing.assert_allclose(m0.factors[k], v, rtol=1e-12, err_msg=k)
    assert (m0.base_color_alpha, m0.alpha_mode, m0.alpha_cutoff, m0.double_sided) == (0.75, "MASK", 0.3, True)
    assert m1.extensions == ("KHR_materials_volume",)
    assert m1.factors == {"base_color": (1.0, 1.0, 1.0), "metallic": 1.0, "roughness": 1.0, "occlusion": 1.0,
                          "emissive": (0.0, 0.0, 0.0), "thickness": 0.0, "attenuation_distance": math.inf,
                          "attenuation_color": (1.0, 1.0, 1.0)}
    assert (m1.alpha_mode, m1.alpha_cutoff, m1.double_sided, m1.textures) == ("OPAQUE", 0.5, False, {})
    assert default.is_default and default.factors == {"base_color": (1.0, 1.0, 1.0), "metallic": 1.0,
                                                      "roughness": 1.0, "occlusion": 1.0, "emissive": (0.0, 0.0, 0.0)}
    assert not m1.is_default and m0.needs_tangents and not m1.needs_tangents


def test_material_textures(materials_file):
    asset = _load_quiet(materials_file)
    t = asset.materials[0].textures
    assert set(t) == {"base_color", "metallic_roughness", "normal", "occlusion", "emissive", "clearcoat",
                      "clearcoat_roughness", "clearcoat_normal", "sheen_color", "sheen_roughness", "specular",
                      "specular_color", "anisotropy", "transmission", "thickness"}
    srgb = {r for r, ref in t.items() if ref.colorspace == "srgb"}
    assert srgb == {"base_color", "emissive", "sheen_color", "specular_color"}
    assert all(ref.colorspace == "linear" for r, ref in t.items() if r not in srgb)
    assert (t["normal"].scale, t["clearcoat_normal"].scale, t["occlusion"].strength) == (0.8, 0.5, 0.4)
    assert t["base_color"].scale == 1.0 and t["base_color"].strength == 1.0
    assert (t["base_color"].texture, t["base_color"].image, t["emissive"].image) == (0, 0, 1)
    s = t["base_color"].sampler
    assert (s.wrap_s, s.wrap_t, s.mag_filter, s.min_filter, s.specified) == ("clamp", "mirror", "nearest",
                                                                             "linear_mipmap_nearest", True)
    d = t["normal"].sampler  # texture without sampler: repeat wrapping, auto (linear) filtering
    assert (d.wrap_s, d.wrap_t, d.mag_filter, d.specified) == ("repeat", "repeat", "linear", False)
    # texCoord: given (1), overridden by KHR_texture_transform (emissive: 0 -> 1), default 0.
    assert (t["base_color"].texcoord, t["emissive"].texcoord, t["normal"].texcoord) == (1, 1, 0)
    assert t["emissive"].has_transform and not t["normal"].has_transform
    np.testing.assert_array_equal(t["emissive"].transform, np.eye(3))
    c, s_ = math.cos(0.3), math.sin(0.3)
    expect = (np.array([[1, 0, 0.1], [0, 1, 0.2], [0, 0, 1]]) @ np.array([[c, s_, 0], [-s_, c, 0], [0, 0, 1]])
              @ np.diag([2.0, 3.0, 1.0]))
    np.testing.assert_allclose(t["base_color"].transform, expect, atol=1e-12)


def test_texture_transform_readme_example():
    """KHR_texture_transform README: offset (0, 1), rotation pi/2, scale 0.5 'utilizes only the lower
    left quadrant of the source image' (v points down: lower = v in [0.5, 1])."""
    from jaxpbr.io.gltf import texture_transform_matrix

    m = texture_transform_matrix((0.0, 1.0), 1.57079632679, (0.5, 0.5))
    corners = np.array([[u, v, 1.0] for u in (0, 1) for v in (0, 1)]) @ m.T
    assert np.all(corners[:, 0] > -1e-9) and np.all(corners[:, 0] < 0.5 + 1e-9)
    assert np.all(corners[:, 1] > 0.5 - 1e-9) and np.all(corners[:, 1] < 1 + 1e-9)


def test_images_decoded_once_as_encoded_values(materials_file):
    asset = _load_quiet(materials_file)
    assert len(asset.images) == 2 and all(im.decoded for im in asset.images)
    img = asset.images[0]
    assert img.mime_type == "image/png" and img.name == "checker" and img.source == "bufferView 0"
    assert img.pixels.dtype == np.float32 and img.pixels.shape == (2, 2, 4)
    np.testing.assert_allclose(img.pixels, _IMG / 255.0, rtol=1e-6)  # raw values, straight alpha
    assert img.pixels is img.pixels
    np.testing.assert_allclose(asset.images[1].pixels, _IMG[:1, :1, :3] / 255.0, rtol=1e-6)
    lazy = _load_quiet(materials_file, lazy_images=True)
    assert not any(im.decoded for im in lazy.images)
    np.testing.assert_array_equal(lazy.images[0].pixels, img.pixels)


def test_ignored_extension_warned_once(materials_file):
    with pytest.warns(UserWarning) as record:
        asset = read_gltf(materials_file)
    msgs = [str(w.message) for w in record if "KHR_materials_iridescence" in str(w.message)]
    assert len(msgs) == 1 and "extensionsUsed" in msgs[0]
    assert any("KHR_materials_iridescence" in w for w in asset.warnings)


def test_external_png_and_jpeg(tmp_path):
    oiio = pytest.importorskip("OpenImageIO")
    (tmp_path / "tex dir").mkdir()
    (tmp_path / "tex dir" / "a b.png").write_bytes(png_bytes(_IMG[:, :, :3]))
    jpg = tmp_path / "flat.jpg"
    out = oiio.ImageOutput.create(str(jpg))
    out.open(str(jpg), oiio.ImageSpec(8, 8, 3, "uint8"))
    out.write_image(np.full((8, 8, 3), (200, 100, 50), np.uint8))
    out.close()
    b = Builder()
    b.add("images", {"uri": "tex%20dir/a%20b.png"})
    b.add("images", {"uri": "flat.jpg"})
    b.add("textures", {"source": 0})
    b.add("textures", {"source": 1})
    b.add("materials", {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}, "emissiveTexture": {"index": 1}})
    b.add("meshes", {"primitives": [_quad(b, 0, uv1=False, tangents=False)]})
    b.add("nodes", {"mesh": 0})
    b.add("scenes", {"nodes": [0]})
    path = b.write(tmp_path / "ext.gltf")
    assert_valid(path)
    asset = read_gltf(path)
    png, jpeg = asset.images
    assert png.mime_type == "image/png" and jpeg.mime_type == "image/jpeg"
    np.testing.assert_allclose(png.pixels, _IMG[:, :, :3] / 255.0, rtol=1e-6)
    assert jpeg.pixels.shape == (8, 8, 3)
    np.testing.assert_allclose(jpeg.pixels, np.broadcast_to(np.float32([200, 100, 50]) / 255, (8, 8, 3)), atol=3 / 255)


# ---------------------------------------------------------------------------------------------
# Lights and cameras
# ---------------------------------------------------------------------------------------------
def test_lights_and_cameras(tmp_path):
    b = Builder()
    h = math.sqrt(0.5)
    b.used("KHR_lights_punctual")
    b.doc["extensions"] = {"KHR_lights_punctual": {"lights": [
        {"name": "spot", "type": "spot", "color": [1, 0.5, 0.25], "intensity": 10, "range": 20,
         "spot": {"innerConeAngle": 0.1, "outerConeAngle": 0.5}},
        {"type": "point"},
        {"type": "directional", "intensity": 3},
    ]}}
    b.add("cameras", {"name": "persp", "type": "perspective",
                      "perspective": {"yfov": 0.8, "aspectRatio": 1.5, "znear": 0.1}})
    b.add("cameras", {"type": "orthographic", "orthographic": {"xmag": 2, "ymag": 1, "znear": 0.01, "zfar": 100}})
    b.add("nodes", {"translation": [1, 2, 3], "rotation": [h, 0, 0, h],
                    "extensions": {"KHR_lights_punctual": {"light": 0}}})
    b.add("nodes", {"translation": [0, 0, 10], "children": [2]})
    b.add("nodes", {"translation": [0, 1, 0], "camera": 0, "extensions": {"KHR_lights_punctual": {"light": 1}}})
    b.add("nodes", {"rotation": [0, 1, 0, 0], "camera": 1})
    b.add("nodes", {"rotation": [0, h, 0, h], "extensions": {"KHR_lights_punctual": {"light": 2}}})
    b.add("scenes", {"nodes": [0, 1, 3, 4]})
    path = b.write(tmp_path / "lights.gltf")
    assert_valid(path)
    asset = read_gltf(path)
    assert asset.primitives == [] and asset.bounds is None
    spot, point, sun = asset.lights
    assert (spot.type, spot.name, spot.intensity, spot.range) == ("spot", "spot", 10.0, 20.0)
    assert (spot.inner_cone_angle, spot.outer_cone_angle) == (0.1, 0.5)
    np.testing.assert_allclose(spot.color, [1, 0.5, 0.25])
    np.testing.assert_allclose(spot.position, [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(spot.direction, apply(Rx(math.pi / 2), [0, 0, -1]), atol=1e-12)  # (0, 1, 0)
    np.testing.assert_allclose(spot.direction, [0, 1, 0], atol=1e-12)
    assert (point.type, point.intensity, point.range, point.inner_cone_angle) == ("point", 1.0, math.inf, None)
    np.testing.assert_allclose(point.color, [1, 1, 1])
    np.testing.assert_allclose(point.position, [0, 1, 10])
    np.testing.assert_allclose(sun.direction, [-1, 0, 0], atol=1e-12)  # Ry(90) of -Z
    persp, ortho = asset.cameras
    assert (persp.type, persp.name, persp.yfov, persp.aspect_ratio, persp.znear, persp.zfar) == (
        "perspective", "persp", 0.8, 1.5, 0.1, math.inf)
    np.testing.assert_allclose(persp.world_matrix, T(0, 0, 10) @ T(0, 1, 0))
    np.testing.assert_allclose(persp.forward, [0, 0, -1]) and np.testing.assert_allclose(persp.up, [0, 1, 0])
    assert (ortho.type, ortho.xmag, ortho.ymag, ortho.znear, ortho.zfar, ortho.yfov) == (
        "orthographic", 2.0, 1.0, 0.01, 100.0, None)
    np.testing.assert_allclose(ortho.forward, [0, 0, 1], atol=1e-12)  # Ry(180) turns -Z to +Z
    np.testing.assert_allclose(ortho.world_matrix, Ry(math.pi), atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Extensions policy and bad files
# ---------------------------------------------------------------------------------------------
def _minimal(b=None):
    b = b or Builder()
    b.add("meshes", {"name": "tri", "primitives": [{"attributes": {
        "POSITION": b.accessor(np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), FLOAT, "VEC3", minmax=True)}}]})
    b.add("nodes", {"mesh": 0})
    b.add("scenes", {"nodes": [0]})
    return b


def test_required_extensions_refused_in_one_error(tmp_path):
    b = _minimal()
    b.used("KHR_materials_ior", "EXT_jaxpbr_alpha", "EXT_jaxpbr_beta",
           required=["KHR_materials_ior", "EXT_jaxpbr_alpha", "EXT_jaxpbr_beta"])
    path = b.write(tmp_path / "req.gltf")
    assert_valid(path)
    with pytest.raises(InputError) as e:
        read_gltf(path)
    msg = str(e.value)
    assert "EXT_jaxpbr_alpha" in msg and "EXT_jaxpbr_beta" in msg and "extensionsRequired" in msg
    assert "KHR_materials_ior, KHR" not in msg.split("supported")[0]  # the supported one is not named as missing
    assert "supported: " in msg and "KHR_texture_transform" in msg


def test_used_extensions_ignored_with_one_warning(tmp_path):
    b = _minimal()
    b.used("EXT_jaxpbr_alpha", "KHR_materials_variants")
    path = b.write(tmp_path / "used.gltf")
    with pytest.warns(UserWarning, match="EXT_jaxpbr_alpha, KHR_materials_variants") as record:
        asset = read_gltf(path)
    assert len([w for w in record if "extensionsUsed" in str(w.message)]) == 1
    assert asset.primitives[0].flat_normals


def test_skin_morph_and_animation_posed(tmp_path):
    """A mesh with a morph target, an identity skin and a weights animation: the rest pose is the
    mesh's default weights, a time poses it (keys clamped at both ends), nothing is warned."""
    b = _minimal()
    b.doc["meshes"][0]["primitives"][0]["targets"] = [{"POSITION": b.accessor(np.float32([[0, 0, 1]] * 3), FLOAT, "VEC3", minmax=True)}]
    b.doc["meshes"][0]["weights"] = [0.0]
    prim = b.doc["meshes"][0]["primitives"][0]
    prim["attributes"]["JOINTS_0"] = b.accessor(np.uint8([[0, 0, 0, 0]] * 3), UBYTE, "VEC4")
    prim["attributes"]["WEIGHTS_0"] = b.accessor(np.float32([[1, 0, 0, 0]] * 3), FLOAT, "VEC4")
    b.doc["nodes"][0]["skin"] = b.add("skins", {"joints": [1]})
    b.add("nodes", {"name": "joint"})
    b.doc["scenes"][0]["nodes"].append(1)
    times = b.accessor(np.float32([0, 1]), FLOAT, "SCALAR", minmax=True)
    b.add("animations", {"channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
                         "samplers": [{"input": times, "output": b.accessor(np.float32([0, 1]), FLOAT, "SCALAR")}]})
    path = b.write(tmp_path / "anim.gltf")
    assert_valid(path)
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rest = read_gltf(path)
        assert rest.time is None and len(rest.animations) == 1 and rest.animations[0].duration == 1.0
        np.testing.assert_array_equal(rest.primitives[0].positions, tri)
        assert rest.primitives[0].deform is not None and rest.primitives[0].deform.skin == 0
        for t, w in ((-1.0, 0.0), (0.25, 0.25), (1.0, 1.0), (7.0, 1.0)):
            posed = read_gltf(path, time=t)
            assert posed.time == t and posed.animation == 0
            np.testing.assert_allclose(posed.primitives[0].positions, tri + [0, 0, w], atol=1e-7)


def _bad(tmp_path, name="bad.gltf"):
    return _minimal().write(tmp_path / name)


def test_missing_buffer_file(tmp_path):
    path = _bad(tmp_path)
    (tmp_path / "bad.bin").unlink()
    with pytest.raises(InputError, match=r"bad\.gltf.*buffer 0.*bad\.bin.*not found.*Fix"):
        read_gltf(path)


def test_accessor_outside_its_buffer(tmp_path):
    path = _bad(tmp_path)
    doc = json.loads(path.read_text())
    doc["accessors"][0]["count"] = 4
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"mesh 0 \('tri'\) primitive 0 POSITION \(/meshes/0/primitives/0/attributes/POSITION\): "
                                         r"accessor 0 \(/accessors/0\).*bufferView 0 \(/bufferViews/0\)"):
        read_gltf(path)
    doc["accessors"][0]["count"] = 3
    doc["bufferViews"][0]["byteLength"] = 400
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"bufferView 0 \(/bufferViews/0\).*\[0, 400\) of buffer 0 \(/buffers/0\).*36 bytes"):
        read_gltf(path)


def test_index_out_of_range(tmp_path):
    b = _minimal()
    b.doc["meshes"][0]["primitives"][0]["indices"] = b.accessor(np.uint8([0, 1, 9]), UBYTE, "SCALAR")
    path = b.write(tmp_path / "idx.gltf")
    with pytest.raises(InputError, match=r"'tri'.*\(/meshes/0/primitives/0/indices\).*the first at position 2\): the vertex attributes have 3 elements"):
        read_gltf(path)


def test_bad_json_truncated_glb_and_missing_file(tmp_path):
    (tmp_path / "broken.gltf").write_text('{"asset": {"version": "2.0"}, "nodes": [')
    with pytest.raises(InputError, match=r"broken\.gltf.*JSON"):
        read_gltf(tmp_path / "broken.gltf")
    glb = _minimal().write(tmp_path / "t.glb", mode="glb")
    data = glb.read_bytes()
    (tmp_path / "cut.glb").write_bytes(data[: len(data) - 8])
    with pytest.raises(InputError, match=r"cut\.glb.*truncated"):
        read_gltf(tmp_path / "cut.glb")
    with pytest.raises(InputError, match="not found"):
        read_gltf(tmp_path / "nothing.gltf")
    doc = json.loads((_bad(tmp_path, "v1.gltf")).read_text())
    doc["asset"]["version"] = "1.0"
    (tmp_path / "v1.gltf").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="only glTF 2"):
        read_gltf(tmp_path / "v1.gltf")


@pytest.mark.parametrize("mode", ["gltf", "glb"])
def test_a_gltf_1_document_is_refused_by_its_version(tmp_path, mode):
    """A glTF 1.x document as its exporters wrote it (objects in dictionaries keyed by id, a
    top-level `scene` id) is refused by its version, before pygltflib reads it (which fails on
    such a document with an error of its own)."""
    doc = {
        "asset": {"version": "1.1", "generator": "an exporter of glTF 1"},
        "scene": "defaultScene",
        "scenes": {"defaultScene": {"nodes": ["node_1"]}},
        "nodes": {"node_1": {"meshes": ["mesh_1"], "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}},
        "meshes": {"mesh_1": {"primitives": [{"attributes": {"POSITION": "accessor_1"}, "mode": 4}]}},
        "accessors": {"accessor_1": {"bufferView": "bufferView_1", "byteOffset": 0, "componentType": 5126,
                                     "count": 3, "type": "VEC3"}},
        "bufferViews": {"bufferView_1": {"buffer": "buffer_1", "byteOffset": 0, "byteLength": 36}},
        "buffers": {"buffer_1": {"byteLength": 36, "uri": "data:application/octet-stream;base64," + "A" * 48}},
    }
    text = json.dumps(doc)
    if mode == "gltf":
        path = tmp_path / "v1.gltf"
        path.write_text(text)
    else:
        body = text.encode() + b" " * (-len(text) % 4)
        path = tmp_path / "v1.glb"
        path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(body)) + struct.pack("<II", len(body), 0x4E4F534A) + body)
    with pytest.raises(InputError, match=r"asset\.version \(/asset/version\): is '1\.1'; only glTF 2\.x is read.*gltf-pipeline") as err:
        read_gltf(path)
    assert "pygltflib" not in str(err.value)


def test_node_cycle_refused(tmp_path):
    b = _minimal()
    b.doc["nodes"][0]["children"] = [1]
    b.add("nodes", {"children": [0]})
    path = b.write(tmp_path / "cycle.gltf")
    with pytest.raises(InputError, match="cycle"):
        read_gltf(path)


def test_unsupported_image_type(tmp_path):
    b = _minimal()
    ktx2 = b"\xabKTX 20\xbb\r\n\x1a\n" + bytes(68)  # a KTX2 identifier (KHR_texture_basisu's images)
    b.add("images", {"name": "pic", "bufferView": b.view(ktx2), "mimeType": "image/ktx2"})
    b.add("textures", {"source": 0})
    b.add("materials", {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}})
    b.doc["meshes"][0]["primitives"][0]["material"] = 0
    path = b.write(tmp_path / "ktx2.gltf")
    with pytest.raises(InputError, match=r"image 0 \('pic'\).*image/ktx2.*not supported.*PNG, JPEG or WebP"):
        read_gltf(path)
    assert len(read_gltf(path, lazy_images=True).images) == 1  # refused only when decoded


# ---------------------------------------------------------------------------------------------
# Generated tangents (MikkTSpace; the generator lives in jaxpbr.io.gltf.mikktspace)
# ---------------------------------------------------------------------------------------------
def test_generated_tangents(tmp_path):
    pytest.importorskip("jaxpbr.io.gltf.mikktspace")
    b = Builder()
    b.add("images", {"uri": "data:image/png;base64," + base64.b64encode(png_bytes(_IMG[:1, :1, :3])).decode()})
    b.add("textures", {"source": 0})
    b.add("materials", {"normalTexture": {"index": 0}})
    b.add("meshes", {"primitives": [_quad(b, 0, uv1=False, tangents=False)]})
    b.add("nodes", {"mesh": 0, "scale": [-2, 1, 1]})
    b.add("scenes", {"nodes": [0]})
    path = b.write(tmp_path / "mikk.gltf")
    assert_valid(path)
    (prim,) = read_gltf(path).primitives
    assert prim.generated_tangents and prim.tangents.shape == (prim.num_vertices, 4)
    # u grows along object +x, i.e. world -x under the mirror.
    np.testing.assert_allclose(prim.tangents[:, :3], np.tile([-1.0, 0, 0], (prim.num_vertices, 1)), atol=1e-5)
    np.testing.assert_allclose(np.abs(prim.tangents[:, 3]), 1)


# ---------------------------------------------------------------------------------------------
# A real exporter: trimesh writes a GLB, the loader reads it back
# ---------------------------------------------------------------------------------------------
def test_trimesh_exported_glb(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    box = trimesh.creation.box(extents=(1, 2, 3))
    ball = trimesh.creation.icosphere(subdivisions=1)
    transforms = [Rz(0.3) @ T(1, 0, 0), T(0, 0, 5) @ S(2, 1, 1), T(-3, 0, 0) @ S(-1, 1, 1)]
    scene = trimesh.Scene()
    scene.add_geometry(box, geom_name="box", transform=transforms[0])
    scene.add_geometry(ball, geom_name="ball", transform=transforms[1])
    scene.add_geometry(box, geom_name="box", node_name="mirrored box", transform=transforms[2])
    path = tmp_path / "trimesh.glb"
    scene.export(path)
    assert_valid(path)
    asset = read_gltf(path)
    assert "trimesh" in asset.generator
    assert len(asset.primitives) == 3
    expected = {}
    for node in scene.graph.nodes_geometry:
        transform, geom = scene.graph[node]
        mesh = scene.geometry[geom]
        v = apply(transform, mesh.vertices)
        expected[round(float(np.linalg.det(transform[:3, :3])), 6), len(mesh.faces)] = (v[mesh.faces], v.mean(0))
    for prim in asset.primitives:
        det = round(float(np.linalg.det(prim.world_matrix[:3, :3])), 6)
        tris, centre = expected[det, prim.num_triangles]
        ours = prim.positions[prim.indices].astype(np.float64)
        # Same triangles (as vertex sets; a mirrored node reverses their order) ...
        np.testing.assert_allclose(np.sort(ours, axis=1), np.sort(tris, axis=1), atol=1e-5)
        # ... facing outward in world space (the convex shapes' fronts).
        face = np.cross(ours[:, 1] - ours[:, 0], ours[:, 2] - ours[:, 0])
        assert np.all(np.einsum("ij,ij->i", face, ours.mean(axis=1) - centre) > 0)
        np.testing.assert_allclose(prim.normals[prim.indices[:, 0]], unit(face), atol=1e-5)


def test_ext_mesh_gpu_instancing(tmp_path):
    """Each instance is node world @ T @ R @ S (ROTATION as normalized SHORT quaternions)."""
    b = _minimal()
    b.used("EXT_mesh_gpu_instancing", required=["EXT_mesh_gpu_instancing"])
    q = 23170  # round(32767 * sqrt(1/2)): a 90-degree turn about z once normalized
    attrs = {"TRANSLATION": b.accessor(np.float32([[0, 0, 0], [10, 0, 0], [0, 10, 0]]), FLOAT, "VEC3"),
             "ROTATION": b.accessor(np.int16([[0, 0, 0, 32767], [0, 0, q, q], [0, 0, 0, 32767]]), SHORT, "VEC4",
                                    normalized=True),
             "SCALE": b.accessor(np.float32([[1, 1, 1], [1, 1, 1], [2, 2, 2]]), FLOAT, "VEC3")}
    b.doc["nodes"][0].update({"translation": [0, 0, 5], "extensions": {"EXT_mesh_gpu_instancing": {"attributes": attrs}}})
    path = b.write(tmp_path / "inst.gltf")
    assert_valid(path)
    prims = read_gltf(path).primitives
    assert [p.instance for p in prims] == [0, 1, 2]
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    for p, m in zip(prims, (T(0, 0, 5), T(0, 0, 5) @ T(10, 0, 0) @ Rz(math.pi / 2), T(0, 0, 5) @ T(0, 10, 0) @ S(2, 2, 2))):
        np.testing.assert_allclose(p.positions, apply(m, tri), atol=1e-6)
        np.testing.assert_allclose(p.world_matrix, m, atol=1e-9)


def test_no_scenes_loads_root_nodes(tmp_path):
    b = _minimal()
    del b.doc["scenes"]
    b.doc["nodes"][0]["children"] = [1]
    b.add("nodes", {"mesh": 0, "translation": [0, 0, 1]})
    path = b.write(tmp_path / "noscene.gltf")
    assert_valid(path)
    asset = read_gltf(path)
    assert asset.scene is None and [p.node for p in asset.primitives] == [0, 1]


def test_integer_colour_must_be_normalized(tmp_path):
    b = _minimal()
    b.doc["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"] = b.accessor(np.uint8([[255, 0, 0, 255]] * 3),
                                                                              UBYTE, "VEC4")
    path = b.write(tmp_path / "colour.gltf")
    with pytest.raises(InputError, match=r"'tri'.*COLOR_0 \(/meshes/0/primitives/0/attributes/COLOR_0\): accessor 1 \(/accessors/1\).*normalized"):
        read_gltf(path)


# ---------------------------------------------------------------------------------------------
# Bad input: one line naming the JSON pointer (RFC 6901) of the offending object; the memory
# guard before any buffer is read; the command line's one-line error, exit status 2, no output
# ---------------------------------------------------------------------------------------------
def _error(path, error=InputError, **kw) -> str:
    """The message read_gltf raises for `path`, checked to be one line."""
    with pytest.raises(error) as e:
        read_gltf(path, **kw)
    msg = str(e.value)
    assert "\n" not in msg and "\r" not in msg, msg
    return msg


def _edit(path: Path, edit) -> Path:
    """Apply edit(doc) to the JSON of a .gltf, or of a .glb's JSON chunk (the BIN chunk kept)."""
    data = path.read_bytes()
    if data[:4] != b"glTF":
        doc = json.loads(data)
        edit(doc)
        path.write_text(json.dumps(doc))
        return path
    jlen = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + jlen])
    edit(doc)
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<I4s", len(js), b"JSON") + js + data[20 + jlen :]
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)
    return path


def _with_texture(b: Builder, image: dict) -> Builder:
    """The image as the base colour texture of the triangle's material."""
    b.add("images", image)
    b.add("textures", {"source": len(b.doc["images"]) - 1})
    b.add("materials", {"pbrMetallicRoughness": {"baseColorTexture": {"index": len(b.doc["textures"]) - 1}}})
    b.doc["meshes"][0]["primitives"][0]["material"] = len(b.doc["materials"]) - 1
    return b


def _png_bomb(w=12_000, h=12_000) -> bytes:
    """A valid PNG header declaring w x h RGBA pixels (2.3 GB as float32) and a token IDAT."""
    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


@pytest.mark.parametrize("attr,n", [("POSITION", 3), ("NORMAL", 3), ("TANGENT", 4), ("TEXCOORD_0", 2)])
def test_non_finite_attribute_refused(tmp_path, attr, n):
    b = _minimal()
    values = np.float32([[0, 0, 0, 1], [1, 0, 0, 1], [0, 1, 0, 1]])[:, :n].copy()
    values[1, 0], values[2, 0], values[2, 1] = np.nan, np.nan, -np.inf
    acc = b.accessor(values, FLOAT, f"VEC{n}")
    b.doc["meshes"][0]["primitives"][0]["attributes"][attr] = acc
    msg = _error(b.write(tmp_path / "nan.gltf"))
    assert (f"mesh 0 ('tri') primitive 0 {attr} (/meshes/0/primitives/0/attributes/{attr}): "
            f"accessor {acc} (/accessors/{acc}): holds 3 non-finite values (2 NaN, 1 infinite) "
            f"among its {3 * n} values, the first in element 1") in msg


def test_non_finite_instance_translation_refused(tmp_path):
    b = _minimal()
    b.used("EXT_mesh_gpu_instancing")
    acc = b.accessor(np.float32([[0, 0, 0], [np.inf, 0, 0]]), FLOAT, "VEC3")
    b.doc["nodes"][0]["extensions"] = {"EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": acc}}}
    msg = _error(b.write(tmp_path / "inst.gltf"))
    assert f"(/nodes/0/extensions/EXT_mesh_gpu_instancing/attributes/TRANSLATION): accessor {acc} (/accessors/{acc})" in msg
    assert "1 non-finite values (0 NaN, 1 infinite)" in msg


def test_indices_out_of_range_counted(tmp_path):
    b = _minimal()
    b.doc["meshes"][0]["primitives"][0]["indices"] = b.accessor(np.uint16([0, 1, 2, 2, 7, 3]), USHORT, "SCALAR")
    msg = _error(b.write(tmp_path / "idx.gltf"))
    assert ("mesh 0 ('tri') primitive 0 indices (/meshes/0/primitives/0/indices): accessor 1 (/accessors/1): "
            "2 of its 6 indices are out of range (the first at position 4): the vertex attributes have 3 elements") in msg
    assert "7" not in msg.split("/accessors/1): ")[1]  # the index value read from the buffer is not echoed


def test_short_buffer_external_and_glb(tmp_path):
    path = _bad(tmp_path)
    (tmp_path / "bad.bin").write_bytes((tmp_path / "bad.bin").read_bytes()[:20])
    msg = _error(path)
    assert "buffer 0 (/buffers/0/byteLength): byteLength is 36 but file" in msg and "holds only 20 bytes" in msg
    glb = _edit(_minimal().write(tmp_path / "short.glb", mode="glb"), lambda d: d["buffers"][0].update(byteLength=4096))
    assert "buffer 0 (/buffers/0/byteLength): byteLength is 4096 but the GLB's BIN chunk holds only 36 bytes" in _error(glb)


def test_views_and_accessors_outside_their_data(tmp_path):
    path = _minimal().write(tmp_path / "v.glb", mode="glb")
    _edit(path, lambda d: d["bufferViews"][0].update(byteOffset=8))
    assert ("accessor 0 (/accessors/0): bufferView 0 (/bufferViews/0): covers bytes [8, 44) of buffer 0 (/buffers/0), "
            "which has 36 bytes") in _error(path)
    _edit(path, lambda d: (d["bufferViews"][0].update(byteOffset=0), d["accessors"][0].update(byteOffset=4)))
    assert ("accessor 0 (/accessors/0): count 3 x 12 bytes from byteOffset 4 reads bytes [4, 40) of bufferView 0 "
            "(/bufferViews/0), which has 36 bytes") in _error(path)
    _edit(path, lambda d: d["accessors"][0].update(byteOffset=0, bufferView=5))
    assert "accessor 0 (/accessors/0/bufferView): names bufferView 5, which does not exist" in _error(path)


def test_missing_truncated_and_outside_images(tmp_path):
    b = _with_texture(_minimal(), {"uri": "gone.png"})
    msg = _error(b.write(tmp_path / "gone.gltf"))
    assert "image 0 (/images/0/uri): file" in msg and "gone.png' (uri 'gone.png') not found" in msg
    (tmp_path / "cut.png").write_bytes(png_bytes(_IMG)[:60])
    msg = _error(_with_texture(_minimal(), {"uri": "cut.png"}).write(tmp_path / "cut.gltf"))
    assert "image 0 (/images/0): the PNG data (60 bytes) is truncated: chunk 'IDAT' at byte 33" in msg
    b = _with_texture(_minimal(), {"bufferView": 1, "mimeType": "image/png"})
    b.view(png_bytes(_IMG))
    path = _edit(b.write(tmp_path / "out.glb", mode="glb"), lambda d: d["bufferViews"][1].update(byteLength=10**6))
    assert "image 0 (/images/0): bufferView 1 (/bufferViews/1): covers bytes [36, 1000036) of buffer 0 (/buffers/0)" in _error(path)


def _set(path: str, value):
    """An edit setting doc[a][b]... = value for path 'a/b/...' (integers index lists)."""
    keys = [int(k) if k.isdigit() else k for k in path.split("/")]

    def edit(doc):
        for k in keys[:-1]:
            doc = doc.setdefault(k, {}) if isinstance(doc, dict) else doc[k]
        doc[keys[-1]] = value

    return edit


@pytest.mark.parametrize("edit,expected", [
    (_set("scenes/0/nodes", [0, 4]), "scene 0 (/scenes/0/nodes/1): names node 4, which does not exist (the file has 1)"),
    (_set("nodes/0/children", [0]), "node 0 (/nodes/0/children/0): is its own child"),
    (_set("nodes/0/mesh", 3), "node 0 (/nodes/0/mesh): names mesh 3, which does not exist (the file has 1)"),
    (_set("nodes/0/translation", [0, float("nan"), 0]), "node 0 (/nodes/0/translation/1): translation[1] NaN is not a finite number"),
    (_set("meshes/0/primitives/0/mode", 1), "mesh 0 ('tri') primitive 0 (/meshes/0/primitives/0/mode): has mode LINES"),
    (_set("meshes/0/primitives/0/material", 2), "mesh 0 ('tri') primitive 0 (/meshes/0/primitives/0/material): names material 2, which does not exist"),
    (_set("meshes/0/primitives/0/attributes/NORMAL", 9),
     "mesh 0 ('tri') primitive 0 (/meshes/0/primitives/0/attributes/NORMAL): names accessor 9, which does not exist"),
    (_set("accessors/0/type", "VEC2"), "accessor 0 (/accessors/0): has type VEC2, expected VEC3"),
    (_set("extensionsRequired", ["KHR_materials_ior", "EXT_nope"]),
     "extensionsRequired (/extensionsRequired): needs EXT_nope (/extensionsRequired/1)"),
    (_set("asset/version", "1.0"), "asset.version (/asset/version): is '1.0'"),
    (_set("bufferViews/0/buffer", 2), "bufferView 0 (/bufferViews/0/buffer): names buffer 2, which does not exist"),
    (_set("materials", [{"normalTexture": {"index": 3}}]),
     "material 0 (/materials/0/normalTexture/index): names texture 3, which does not exist"),
    (_set("materials", [{"pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1]}}]),
     "material 0 (/materials/0/pbrMetallicRoughness/baseColorFactor): baseColorFactor [1, 1, 1] has 3 items; expected an array of 4 numbers"),
    (lambda d: (_set("cameras", [{"type": "fisheye"}])(d), _set("nodes/0/camera", 0)(d)),
     'camera 0 (/cameras/0/type): type "fisheye" is not a valid value; expected one of "perspective", "orthographic"'),
    (lambda d: (_set("cameras", [{"type": "orthographic", "orthographic": {"xmag": 2, "ymag": 0, "znear": 0, "zfar": 9}}])(d),
                _set("nodes/0/camera", 0)(d)),
     "camera 0 (/cameras/0/orthographic/ymag): ymag 0 is out of range; expected a finite non-zero number"),
    (_set("nodes/0/extensions", {"KHR_lights_punctual": {"light": 1}}),
     "node 0 (/nodes/0/extensions/KHR_lights_punctual/light): names KHR_lights_punctual light 1, which does not exist"),
], ids=lambda x: x.split(":")[0] if isinstance(x, str) else None)
def test_structure_errors_name_the_pointer(tmp_path, edit, expected):
    assert expected in _error(_edit(_bad(tmp_path), edit))


def test_sampler_and_texture_source_pointers(tmp_path):
    b = _with_texture(_minimal(), {"uri": "data:image/png;base64," + base64.b64encode(png_bytes(_IMG[:1, :1, :3])).decode()})
    path = b.write(tmp_path / "s.gltf")
    _edit(path, lambda d: (d.setdefault("samplers", []).append({"wrapS": 1}), d["textures"][0].update(sampler=0)))
    assert "sampler 0 (/samplers/0/wrapS): wrapS 1 is not a valid value; expected one of 33071 (CLAMP_TO_EDGE)" in _error(path)
    _edit(path, lambda d: (d["textures"][0].pop("sampler"), d["textures"][0].update(source=7)))
    assert "texture 0 (/textures/0/source): names image 7, which does not exist (the file has 1)" in _error(path)


def test_huge_count_refused_before_any_buffer_is_read(tmp_path, monkeypatch):
    """A declared count of 4e9 (an accessor without a bufferView decodes to zeros of that count) is
    refused by the memory check from the JSON alone: neither the buffer nor an accessor is read."""
    from jaxpbr._memory import MemoryLimitError
    from jaxpbr.io.gltf._binary import Buffers

    def never(*args, **kw):
        raise AssertionError("read before the memory check")

    path = _edit(_bad(tmp_path), lambda d: (d["accessors"][0].pop("bufferView"), d["accessors"][0].update(count=4_000_000_000)))
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "64")
    monkeypatch.setattr(Buffers, "buffer", never)
    monkeypatch.setattr(Buffers, "_decode", never)
    msg = _error(path, MemoryLimitError)
    assert "(largest: mesh 0 ('tri') primitive 0 (/meshes/0/primitives/0)" in msg
    assert "more than the 64 GB available; lower the vertex and index counts of /meshes/0/primitives/0 " \
           "(POSITION /accessors/0 count 4000000000)" in msg and "JAXPBR_MEMORY_LIMIT" in msg
    # The same check under a limit below a small asset's needs names the parts it would read (the
    # JSON's own check, which comes first, left out).
    monkeypatch.setattr("jaxpbr.io.gltf._loader._require_json", lambda *a, **k: None)
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "1e-9")
    msg = _error(_bad(tmp_path, "small.gltf"), MemoryLimitError)
    assert "/meshes/0/primitives/0" in msg and "buffer 0 (/buffers/0)" in msg


def test_image_resolution_from_its_header_refused_before_decoding(tmp_path, monkeypatch):
    """A PNG whose header declares 12000^2 RGBA pixels: refused from the header (no pixels decoded)
    at load, and by the decode's own check when read lazily."""
    from jaxpbr._memory import MemoryLimitError
    from jaxpbr.io.gltf import _images

    b = _with_texture(_minimal(), {"bufferView": 1, "mimeType": "image/png", "name": "bomb"})
    b.view(_png_bomb())
    path = b.write(tmp_path / "bomb.glb", mode="glb")
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "2")
    real = _images._decode
    monkeypatch.setattr(_images, "_decode", lambda *a, **k: pytest.fail("decoded before the memory check"))
    msg = _error(path, MemoryLimitError)
    assert "(largest: image 0 ('bomb') (/images/0) 6.91 GB; mesh 0 ('tri') primitive 0 (/meshes/0/primitives/0) " in msg
    assert "lower the resolution of /images/0 (12000x12000, 4 channels)" in msg
    monkeypatch.setattr(_images, "_decode", real)
    asset = read_gltf(path, lazy_images=True)
    with pytest.raises(MemoryLimitError, match=r"decoding image 0 \('bomb'\) \(/images/0\) \(12000x12000, 4 channels\) needs about 6.91 GB"):
        asset.images[0].pixels  # noqa: B018


def test_image_headers_read_for_the_estimate(tmp_path):
    """The estimate's (H, W, C) of PNG and JPEG headers, read without decoding, equal the decoded shapes."""
    from jaxpbr.io.gltf._images import header_shape

    oiio = pytest.importorskip("OpenImageIO")
    for shape in ((5, 7, 3), (4, 9, 4), (6, 2, 1)):
        data = png_bytes(np.zeros(shape, np.uint8))
        assert header_shape(lambda o, n, d=data: d[o : o + n]) == shape
    buf = oiio.ImageBuf(oiio.ImageSpec(11, 6, 3, "uint8"))
    jpg = tmp_path / "a.jpg"
    assert buf.write(str(jpg))
    data = jpg.read_bytes()
    assert header_shape(lambda o, n: data[o : o + n]) == (6, 11, 3)
    assert header_shape(lambda o, n: data[o : o + n][:2]) is None  # cut short: unknown, not a guess
    # In a GLB, behind 90 kB of APPn segments: read at the offsets, the BIN chunk is not loaded.
    from jaxpbr.io.gltf._binary import Buffers
    from jaxpbr.io.gltf._images import image_source
    from jaxpbr.io.gltf._loader import _read_document

    def app(n):
        return b"\xff\xe9" + (n + 2).to_bytes(2, "big") + b"x" * n

    b = _with_texture(_minimal(), {"bufferView": 1, "mimeType": "image/jpeg"})
    b.view(data[:2] + app(60000) + app(30000) + data[2:])
    path = b.write(tmp_path / "jpeg.glb", mode="glb")
    gltf, _, glb_bin = _read_document(path)
    buffers = Buffers(gltf, path, glb_bin)
    assert image_source(gltf, buffers, 0) == ((6, 11, 3), len(data) + 90008) and not buffers._buffers
    assert read_gltf(path).images[0].pixels.shape == (6, 11, 3)


@pytest.mark.parametrize("kind,expected", [
    ("nan", "(/meshes/0/primitives/0/attributes/POSITION): accessor 1 (/accessors/1): holds 1 non-finite values"),
    ("huge", "lower the vertex and index counts of /meshes/0/primitives/0"),
    ("image", "image 0 (/images/0): the PNG data (60 bytes) is truncated"),
])
def test_cli_render_of_a_bad_asset(tmp_path, capsys, monkeypatch, kind, expected):
    """`jaxpbr render bad.glb -o out.png`: one line `jaxpbr: error: ...` naming the pointer, exit 2, nothing written."""
    from jaxpbr.cli import main

    b = _minimal()
    if kind == "nan":
        b.doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = b.accessor(
            np.float32([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]]), FLOAT, "VEC3")
    elif kind == "image":
        _with_texture(b, {"bufferView": 1, "mimeType": "image/png"})
        b.view(png_bytes(_IMG)[:60])
    path = b.write(tmp_path / "bad.glb", mode="glb")
    if kind == "huge":
        _edit(path, lambda d: (d["accessors"][0].pop("bufferView"), d["accessors"][0].update(count=4_000_000_000)))
        monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "64")
    before = sorted(tmp_path.rglob("*"))
    code = main(["render", str(path), "-o", str(tmp_path / "out.png"), "--width", "32", "--height", "18"])
    err = capsys.readouterr().err
    assert code == 2
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"jaxpbr: error: glTF file {str(path)!r}: "), err
    assert expected in lines[0]
    assert sorted(tmp_path.rglob("*")) == before
