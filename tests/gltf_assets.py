"""Named glTF 2.0 test assets, generated in code (tests/gltf_writer.py's Builder), each small enough for
the default test suite: a function per asset writes it into a folder and returns its path.

    textured_cube           every sampler mode: wrap REPEAT / CLAMP_TO_EDGE / MIRRORED_REPEAT, mag and
                            min filters with the four mipmap modes (one face per sampler)
    node_hierarchy          TRS and matrix nodes three levels deep, two meshes instanced by several
                            nodes, a mirrored (negative-determinant) node and a child under it
    normal_mapped_plane     a plane with a normal texture and no TANGENT (MikkTSpace is needed)
    alpha_mask_leaf         a leaf cut-out: a quad whose base-colour alpha is a leaf silhouette
                            (alphaMode MASK, alphaCutoff, doubleSided)
    sphere_grid             7 x 7 UV-sphere meshes, metallic 0 -> 1 down the rows, roughness 0 -> 1
                            along the columns
    khr_extension_spheres   a row of spheres: a plain one, then one per KHR material extension
                            (clearcoat, sheen, specular, ior, transmission, volume, anisotropy,
                            emissive_strength), most with a texture too
    lights_and_cameras      a floor under KHR_lights_punctual point, spot and directional lights,
                            a perspective camera in a node hierarchy and an orthographic camera

Regenerate and validate them all with the Khronos glTF Validator:

    python tests/gltf_assets.py --out DIR

The values written are module constants (`SAMPLERS`, `KHR_SPHERES`, `LIGHTS`, ...) that the tests
(tests/test_gltf_assets.py) compare with what jaxpbr reads.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gltf_writer import (
    ARRAY_BUFFER,
    CUBE_FACES,
    ELEMENT_ARRAY_BUFFER,
    FLOAT,
    UINT,
    USHORT,
    Builder,
    png_bytes,
    print_validation,
    uv_sphere,
)

# glTF sampler enums
NEAREST, LINEAR = 9728, 9729
NEAREST_MIPMAP_NEAREST, LINEAR_MIPMAP_NEAREST, NEAREST_MIPMAP_LINEAR, LINEAR_MIPMAP_LINEAR = 9984, 9985, 9986, 9987
REPEAT, CLAMP_TO_EDGE, MIRRORED_REPEAT = 10497, 33071, 33648


# ---------------------------------------------------------------------------------------------
# Small helpers (matrices and quaternions written here, independent of the loader)
# ---------------------------------------------------------------------------------------------
def quat_axis_angle(axis, angle) -> list[float]:
    """Unit quaternion (x, y, z, w) of a rotation by `angle` radians about `axis`."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    s = math.sin(angle / 2)
    return [float(a[0] * s), float(a[1] * s), float(a[2] * s), math.cos(angle / 2)]


def quat_matrix(q) -> np.ndarray:
    """3x3 rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quat_from_matrix(m) -> list[float]:
    """Unit quaternion (x, y, z, w) of a 3x3 rotation matrix (Shepperd's method)."""
    m = np.asarray(m, np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2 * math.sqrt(1 + tr)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * math.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = s / 4
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q)
    return [float(v) for v in q / np.linalg.norm(q)]


def look_rotation(position, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """The rotation of a glTF camera or light node at `position` facing `target` (its -Z axis
    along target - position, its +Y as close to `up` as possible)."""
    f = np.asarray(target, np.float64) - np.asarray(position, np.float64)
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    return np.stack([r, u, -f], axis=1)  # columns: the node's X, Y, Z axes in world space


def trs_matrix(t=(0, 0, 0), q=(0, 0, 0, 1), s=(1, 1, 1)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_matrix(q) @ np.diag(s)
    m[:3, 3] = t
    return m


def colmajor(m) -> list[float]:
    return [float(x) for x in np.asarray(m).T.ravel()]


def srgb_to_linear(c):
    """The sRGB EOTF (IEC 61966-2-1), for 8-bit texture values given in [0, 1]."""
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _attributes(b: Builder, positions, normals=None, uv=None, tangents=None) -> dict:
    attrs = {"POSITION": b.accessor(np.asarray(positions, np.float32), FLOAT, "VEC3", minmax=True, target=ARRAY_BUFFER)}
    if normals is not None:
        attrs["NORMAL"] = b.accessor(np.asarray(normals, np.float32), FLOAT, "VEC3", target=ARRAY_BUFFER)
    if uv is not None:
        attrs["TEXCOORD_0"] = b.accessor(np.asarray(uv, np.float32), FLOAT, "VEC2", target=ARRAY_BUFFER)
    if tangents is not None:
        attrs["TANGENT"] = b.accessor(np.asarray(tangents, np.float32), FLOAT, "VEC4", target=ARRAY_BUFFER)
    return attrs


def _indices(b: Builder, triangles) -> int:
    t = np.asarray(triangles).ravel()
    if t.max() < 65536:
        return b.accessor(t.astype(np.uint16), USHORT, "SCALAR", target=ELEMENT_ARRAY_BUFFER)
    return b.accessor(t.astype(np.uint32), UINT, "SCALAR", target=ELEMENT_ARRAY_BUFFER)


def _png_texture(b: Builder, pixels_u8: np.ndarray, sampler: int | None = None, name: str | None = None) -> int:
    image = {"bufferView": b.view(png_bytes(pixels_u8)), "mimeType": "image/png"}
    if name:
        image["name"] = name
    tex = {"source": b.add("images", image)}
    if sampler is not None:
        tex["sampler"] = sampler
    return b.add("textures", tex)


def _scene(b: Builder, roots):
    b.add("scenes", {"nodes": list(roots)})
    b.doc["scene"] = 0


# ---------------------------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------------------------


def cube_face(f: int, uv_range=(0.0, 1.0)):
    """(positions, normals, uv, triangles) of face f of the unit cube centred at the origin."""
    n, u, v = (np.array(a, np.float64) for a in CUBE_FACES[f])
    lo, hi = uv_range
    pos, uv = [], []
    for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        pos.append(0.5 * n + 0.5 * su * u + 0.5 * sv * v)
        uv.append((lo + (hi - lo) * (su + 1) / 2, lo + (hi - lo) * (1 - sv) / 2))
    return np.array(pos), np.tile(n, (4, 1)), np.array(uv), np.array([[0, 1, 2], [0, 2, 3]])


def cube():
    """(positions, normals, triangles) of the unit cube, 24 vertices."""
    faces = [cube_face(f) for f in range(6)]
    pos = np.concatenate([f[0] for f in faces])
    nrm = np.concatenate([f[1] for f in faces])
    tri = np.concatenate([f[3] + 4 * k for k, f in enumerate(faces)])
    return pos, nrm, tri


TETRA = np.array([[0.5, 0.0, 0.0], [-0.25, 0.0, 0.43], [-0.25, 0.0, -0.43], [0.0, 0.6, 0.0]])
TETRA_TRIANGLES = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]])  # counter-clockwise from outside


def sphere_tangents(normals: np.ndarray) -> np.ndarray:
    """TANGENT of `uv_sphere`: the unit dP/du (u = longitude / 2 pi) and w = +1, so that
    cross(N, T) w points up the texture (towards decreasing v, the north pole); at the poles
    (where dP/du vanishes) the limit along the seam's meridian."""
    phi = np.arctan2(normals[:, 0], normals[:, 2])
    pole = np.hypot(normals[:, 0], normals[:, 2]) < 1e-6
    phi = np.where(pole, 0.0, phi)
    t = np.stack([np.cos(phi), np.zeros_like(phi), -np.sin(phi), np.ones_like(phi)], -1)
    return t


# ---------------------------------------------------------------------------------------------
# (1) The textured cube: one face per sampler
# ---------------------------------------------------------------------------------------------
#: (wrapS, wrapT, magFilter, minFilter) of faces 0..5; every wrap mode along S and T, both
#: magnification filters and all six minification filters.
SAMPLERS = [
    (REPEAT, REPEAT, NEAREST, NEAREST),
    (CLAMP_TO_EDGE, CLAMP_TO_EDGE, LINEAR, LINEAR),
    (MIRRORED_REPEAT, MIRRORED_REPEAT, NEAREST, NEAREST_MIPMAP_NEAREST),
    (REPEAT, CLAMP_TO_EDGE, LINEAR, LINEAR_MIPMAP_NEAREST),
    (CLAMP_TO_EDGE, MIRRORED_REPEAT, NEAREST, NEAREST_MIPMAP_LINEAR),
    (MIRRORED_REPEAT, REPEAT, LINEAR, LINEAR_MIPMAP_LINEAR),
]
CUBE_UV_RANGE = (-0.5, 1.5)  # outside [0, 1]: the wrap modes decide what the corners show


def cube_texture() -> np.ndarray:
    """8 x 8 RGB, uint8: a checker whose four quadrants have different colours (so that every
    wrap mode shows a different pattern)."""
    y, x = np.indices((8, 8))
    quad = np.array([[[220, 60, 40], [40, 180, 60]], [[50, 80, 220], [230, 200, 40]]], np.uint8)
    px = quad[y // 4, x // 4].astype(np.int32)
    px[(x + y) % 2 == 1] //= 2
    return px.astype(np.uint8)


def textured_cube(out: Path) -> Path:
    b = Builder("jaxpbr test assets")
    tex_image = b.add("images", {"name": "quadrant-checker", "bufferView": b.view(png_bytes(cube_texture())),
                                 "mimeType": "image/png"})
    prims = []
    for f, (ws, wt, mag, mn) in enumerate(SAMPLERS):
        s = b.add("samplers", {"wrapS": ws, "wrapT": wt, "magFilter": mag, "minFilter": mn})
        t = b.add("textures", {"source": tex_image, "sampler": s})
        m = b.add("materials", {"name": f"face{f}", "pbrMetallicRoughness": {
            "baseColorTexture": {"index": t}, "metallicFactor": 0.0, "roughnessFactor": 0.7}})
        pos, nrm, uv, tri = cube_face(f, CUBE_UV_RANGE)
        prims.append({"attributes": _attributes(b, pos, nrm, uv), "indices": _indices(b, tri), "material": m})
    mesh = b.add("meshes", {"name": "cube", "primitives": prims})
    _scene(b, [b.add("nodes", {"name": "cube", "mesh": mesh, "rotation": quat_axis_angle((1, 1, 0), 0.4)})])
    return b.write(Path(out) / "textured_cube.glb", mode="glb")


# ---------------------------------------------------------------------------------------------
# (2) The node hierarchy
# ---------------------------------------------------------------------------------------------
_Q_ROOT = quat_axis_angle((0, 1, 0), math.radians(30))
_M_ARM = trs_matrix((0, 2, 0), quat_axis_angle((1, 0, 0), math.radians(45)), (0.5, 0.5, 0.5))
#: name -> (parent, mesh, local matrix); meshes: 'cube' (3 instances), 'tetra' (2 instances).
HIERARCHY = {
    "root": (None, None, trs_matrix((1, 0, 0), _Q_ROOT, (1, 1, 1))),
    "arm (matrix)": ("root", "cube", _M_ARM),
    "mirror": ("root", "cube", trs_matrix((-3, 0, 0), s=(-1, 1, 1))),
    "stretched": ("root", "cube", trs_matrix((3, 0, 0), quat_axis_angle((0, 0, 1), 0.3), (1, 2, 0.5))),
    "tip": ("arm (matrix)", "tetra", trs_matrix((0, 1.5, 0))),
    "under the mirror": ("mirror", "tetra", trs_matrix((0, 1.5, 0), quat_axis_angle((0, 0, 1), math.radians(90)))),
}


def hierarchy_world_matrices() -> dict[str, np.ndarray]:
    """World matrix of each node of HIERARCHY (products of the local matrices, root first)."""
    out = {}
    for name, (parent, _, m) in HIERARCHY.items():
        out[name] = (out[parent] if parent else np.eye(4)) @ m
    return out


def node_hierarchy(out: Path) -> Path:
    b = Builder("jaxpbr test assets")
    mat = b.add("materials", {"name": "grey", "pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.6, 0.6, 1.0],
                                                                       "metallicFactor": 0.0}})
    pos, nrm, tri = cube()
    meshes = {"cube": b.add("meshes", {"name": "cube", "primitives": [
        {"attributes": _attributes(b, pos, nrm), "indices": _indices(b, tri), "material": mat}]})}
    # The tetrahedron without NORMAL: flat normals, and an index buffer of UNSIGNED_SHORT.
    meshes["tetra"] = b.add("meshes", {"name": "tetra", "primitives": [
        {"attributes": _attributes(b, TETRA), "indices": _indices(b, TETRA_TRIANGLES), "material": mat}]})
    index = {name: k for k, name in enumerate(HIERARCHY)}
    for name, (parent, mesh, m) in HIERARCHY.items():
        node = {"name": name}
        if name == "arm (matrix)":
            node["matrix"] = colmajor(m)
        else:  # TRS: recover (t, q, s) from the matrices built above
            t = m[:3, 3]
            s = np.linalg.norm(m[:3, :3], axis=0) * np.sign(np.linalg.det(m[:3, :3]))
            s = np.where(np.arange(3) == 0, s, np.abs(s))  # a mirror flips X
            node["translation"] = [float(v) for v in t]
            node["rotation"] = quat_from_matrix(m[:3, :3] / s)
            node["scale"] = [float(v) for v in s]
        if mesh is not None:
            node["mesh"] = meshes[mesh]
        children = [index[c] for c, (p, _, _) in HIERARCHY.items() if p == name]
        if children:
            node["children"] = children
        b.add("nodes", node)
    _scene(b, [index["root"]])
    return b.write(Path(out) / "node_hierarchy.gltf", mode="bin")


# ---------------------------------------------------------------------------------------------
# (3) The normal-mapped plane without tangents
# ---------------------------------------------------------------------------------------------
def normal_map_texture(size: int = 16) -> np.ndarray:
    """size x size RGB uint8 tangent-space normals: a bump per quadrant (a sine dome)."""
    s = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(s, s)
    hx = 0.6 * np.cos(4 * np.pi * u) * np.sin(2 * np.pi * v)
    hy = 0.6 * np.sin(2 * np.pi * u) * np.cos(4 * np.pi * v)
    n = np.stack([hx, hy, np.ones_like(hx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.round((n + 1) / 2 * 255).astype(np.uint8)


PLANE_SIZE, PLANE_CELLS = 4.0, 3


def plane_grid():
    """(positions, normals, uv, triangles): a PLANE_CELLS^2 grid in the XZ plane facing +Y; u grows
    along +X, v along +Z."""
    k = PLANE_CELLS + 1
    s = np.linspace(0.0, 1.0, k)
    u, v = np.meshgrid(s, s)
    pos = np.stack([(u - 0.5) * PLANE_SIZE, np.zeros_like(u), (v - 0.5) * PLANE_SIZE], -1).reshape(-1, 3)
    uv = np.stack([u, v], -1).reshape(-1, 2)
    tri = []
    for i in range(PLANE_CELLS):
        for j in range(PLANE_CELLS):
            a, b_, c, d = i * k + j, i * k + j + 1, (i + 1) * k + j + 1, (i + 1) * k + j
            tri += [(a, d, c), (a, c, b_)]  # counter-clockwise seen from +Y
    return pos, np.tile([0.0, 1.0, 0.0], (len(pos), 1)), uv, np.array(tri)


def normal_mapped_plane(out: Path) -> Path:
    b = Builder("jaxpbr test assets")
    t = _png_texture(b, normal_map_texture(), name="bumps")
    m = b.add("materials", {"name": "bumpy", "normalTexture": {"index": t, "scale": 0.8},
                            "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1.0], "metallicFactor": 0.0,
                                                     "roughnessFactor": 0.4}})
    pos, nrm, uv, tri = plane_grid()
    mesh = b.add("meshes", {"name": "plane", "primitives": [
        {"attributes": _attributes(b, pos, nrm, uv), "indices": _indices(b, tri), "material": m}]})
    _scene(b, [b.add("nodes", {"name": "plane", "mesh": mesh})])
    return b.write(Path(out) / "normal_mapped_plane.glb", mode="glb")


# ---------------------------------------------------------------------------------------------
# (4) The alpha-mask leaf
# ---------------------------------------------------------------------------------------------
LEAF_TEXELS, LEAF_CUTOFF = 32, 0.4
LEAF_HALF_SIZE = 1.0  # the quad spans x, y in [-1, 1] at z = 0, facing +Z


def leaf_inside(s, t) -> np.ndarray:
    """The leaf silhouette in texture space (s right, t down, both in [0, 1]): a blade along the
    diagonal, pointed at both ends, wider towards its base, and a stem."""
    x, y = 2 * np.asarray(s) - 1, 1 - 2 * np.asarray(t)  # y up
    c, sn = math.cos(math.radians(35)), math.sin(math.radians(35))
    a, w = c * x + sn * y, -sn * x + c * y  # along and across the blade
    a = a / 0.8
    half = 0.42 * np.clip(1 - a * a, 0, None) * (1 - 0.35 * a)
    blade = (np.abs(a) < 1) & (np.abs(w) < half)
    stem = (a < -0.95) & (a > -1.2) & (np.abs(w) < 0.025)
    return blade | stem


def leaf_texture() -> np.ndarray:
    """LEAF_TEXELS^2 RGBA uint8: a green leaf with a lighter mid-rib; alpha = the silhouette's
    coverage of each texel (8 x 8 samples), 0 around it."""
    n, k = LEAF_TEXELS, 8
    sub = (np.arange(n * k) + 0.5) / (n * k)
    ss, tt = np.meshgrid(sub, sub)
    cover = leaf_inside(ss, tt).reshape(n, k, n, k).mean(axis=(1, 3))
    s = (np.arange(n) + 0.5) / n
    S_, T_ = np.meshgrid(s, s)
    rib = np.abs((S_ - 0.5) * math.sin(math.radians(35)) + (T_ - 0.5) * math.cos(math.radians(35))) < 0.02
    rgb = np.where(rib[..., None], [150, 200, 90], [60, 140, 40]).astype(np.float64)
    rgba = np.concatenate([rgb, 255 * cover[..., None]], -1)
    return np.round(rgba).astype(np.uint8)


def leaf_quad():
    """(positions, normals, uv, triangles) of the leaf's quad: uv (0, 0) at the top-left corner."""
    h = LEAF_HALF_SIZE
    pos = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], np.float64)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    return pos, np.tile([0.0, 0.0, 1.0], (4, 1)), uv, np.array([[0, 2, 1], [0, 3, 2]])


def alpha_mask_leaf(out: Path, mag_filter: int = LINEAR) -> Path:
    """The leaf; mag_filter NEAREST writes the variant alpha_mask_leaf_nearest.glb (the same
    texture and quad, magnified texel by texel)."""
    b = Builder("jaxpbr test assets")
    s = b.add("samplers", {"wrapS": CLAMP_TO_EDGE, "wrapT": CLAMP_TO_EDGE, "magFilter": mag_filter,
                           "minFilter": LINEAR_MIPMAP_LINEAR})
    t = _png_texture(b, leaf_texture(), sampler=s, name="leaf")
    m = b.add("materials", {"name": "leaf", "alphaMode": "MASK", "alphaCutoff": LEAF_CUTOFF, "doubleSided": True,
                            "pbrMetallicRoughness": {"baseColorTexture": {"index": t}, "metallicFactor": 0.0,
                                                     "roughnessFactor": 0.6}})
    pos, nrm, uv, tri = leaf_quad()
    mesh = b.add("meshes", {"name": "leaf", "primitives": [
        {"attributes": _attributes(b, pos, nrm, uv), "indices": _indices(b, tri), "material": m}]})
    _scene(b, [b.add("nodes", {"name": "leaf", "mesh": mesh})])
    name = "alpha_mask_leaf.glb" if mag_filter == LINEAR else "alpha_mask_leaf_nearest.glb"
    return b.write(Path(out) / name, mode="glb")


# ---------------------------------------------------------------------------------------------
# (5) The 7 x 7 metal/roughness sphere grid
# ---------------------------------------------------------------------------------------------
GRID_N, GRID_SPACING, GRID_RADIUS, GRID_TESSELLATION = 7, 1.0, 0.4, (8, 16)
GRID_BASE_COLOR = (0.9, 0.55, 0.3, 1.0)


def grid_params(i: int, j: int):
    """(metallic, roughness, centre) of the sphere in row i (top), column j (left)."""
    c = (GRID_N - 1) / 2
    return i / (GRID_N - 1), j / (GRID_N - 1), ((j - c) * GRID_SPACING, (c - i) * GRID_SPACING, 0.0)


def sphere_grid(out: Path) -> Path:
    """One set of sphere accessors shared by 49 meshes (one material each), one node each."""
    b = Builder("jaxpbr test assets")
    P, N, _, T = uv_sphere(*GRID_TESSELLATION, radius=GRID_RADIUS)
    attrs, idx = _attributes(b, P, N), _indices(b, T)
    roots = []
    for i in range(GRID_N):
        for j in range(GRID_N):
            metallic, roughness, centre = grid_params(i, j)
            m = b.add("materials", {"name": f"m{metallic:.3f} r{roughness:.3f}", "pbrMetallicRoughness": {
                "baseColorFactor": list(GRID_BASE_COLOR), "metallicFactor": metallic, "roughnessFactor": roughness}})
            mesh = b.add("meshes", {"primitives": [{"attributes": dict(attrs), "indices": idx, "material": m}]})
            roots.append(b.add("nodes", {"name": f"sphere {i},{j}", "mesh": mesh, "translation": list(centre)}))
    _scene(b, roots)
    return b.write(Path(out) / "sphere_grid.glb", mode="glb")


# ---------------------------------------------------------------------------------------------
# (6) The row of KHR-extension spheres
# ---------------------------------------------------------------------------------------------
KHR_CORE = {"baseColorFactor": [0.8, 0.8, 0.8, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.5}
KHR_EMISSIVE = [0.5, 0.25, 0.1]  # the emissive sphere's emissiveFactor
KHR_SPACING, KHR_RADIUS, KHR_TESSELLATION = 1.0, 0.42, (16, 32)
#: The uniform textures of the texture variants (8-bit values, 4 x 4 texels): data (linear) and
#: colour (sRGB-encoded).
KHR_DATA_TEXEL = (255, 255, 128, 255)  # clearcoat/transmission R = 1, thickness G = 1, anisotropy B = 0.5
KHR_COLOUR_TEXEL = (200, 150, 100)
#: (name, extension, its JSON with "#data" / "#colour" standing for the textures, extra core JSON),
#: in the order of the row (x = (k - 4) KHR_SPACING); sphere 0 is the plain material.
KHR_SPHERES = [
    ("plain", None, None, {}),
    ("clearcoat", "KHR_materials_clearcoat",
     {"clearcoatFactor": 1.0, "clearcoatRoughnessFactor": 0.3, "clearcoatTexture": "#data"}, {}),
    ("sheen", "KHR_materials_sheen",
     {"sheenColorFactor": [1.0, 0.6, 0.8], "sheenRoughnessFactor": 0.5, "sheenColorTexture": "#white"}, {}),
    ("specular", "KHR_materials_specular",
     {"specularFactor": 0.0, "specularColorFactor": [1.0, 0.9, 0.8], "specularColorTexture": "#colour"}, {}),
    ("ior", "KHR_materials_ior", {"ior": 2.5}, {}),
    ("transmission", "KHR_materials_transmission",
     {"transmissionFactor": 1.0, "transmissionTexture": "#data"}, {}),
    ("volume", "KHR_materials_volume",
     {"thicknessFactor": 0.5, "attenuationDistance": 1.0, "attenuationColor": [1.0, 0.5, 0.25],
      "thicknessTexture": "#data"}, {}),
    ("anisotropy", "KHR_materials_anisotropy",
     {"anisotropyStrength": 0.8, "anisotropyRotation": 0.0, "anisotropyTexture": "#data"}, {}),
    ("emissive_strength", "KHR_materials_emissive_strength", {"emissiveStrength": 4.0},
     {"emissiveFactor": KHR_EMISSIVE, "emissiveTexture": "#colour"}),
]


def khr_sphere_centre(k: int):
    return ((k - (len(KHR_SPHERES) - 1) / 2) * KHR_SPACING, 0.0, 0.0)


def khr_extension_spheres(out: Path) -> Path:
    """The spheres share one set of accessors (with TANGENT, for anisotropy); the volume sphere
    is also transmissive (KHR_materials_volume needs KHR_materials_transmission)."""
    b = Builder("jaxpbr test assets")
    b.used(*(ext for _, ext, _, _ in KHR_SPHERES if ext))
    tex = {
        "#data": _png_texture(b, np.broadcast_to(np.uint8(KHR_DATA_TEXEL), (4, 4, 4)).copy(), name="data"),
        "#colour": _png_texture(b, np.broadcast_to(np.uint8(KHR_COLOUR_TEXEL), (4, 4, 3)).copy(), name="colour"),
        "#white": _png_texture(b, np.full((4, 4, 3), 255, np.uint8), name="white"),
    }

    def resolve(d):
        return {k: ({"index": tex[v]} if isinstance(v, str) and v.startswith("#") else v) for k, v in d.items()}

    P, N, UV, _ = uv_sphere(*KHR_TESSELLATION, radius=KHR_RADIUS)
    T = uv_sphere(*KHR_TESSELLATION)[3]
    attrs, idx = _attributes(b, P, N, UV, sphere_tangents(N)), _indices(b, T)
    roots = []
    for k, (name, ext, body, core) in enumerate(KHR_SPHERES):
        mat = {"name": name, "pbrMetallicRoughness": dict(KHR_CORE), **resolve(core)}
        if ext:
            mat["extensions"] = {ext: resolve(body)}
            if ext == "KHR_materials_volume":
                mat["extensions"]["KHR_materials_transmission"] = {"transmissionFactor": 1.0}
        m = b.add("materials", mat)
        mesh = b.add("meshes", {"name": name, "primitives": [{"attributes": dict(attrs), "indices": idx, "material": m}]})
        roots.append(b.add("nodes", {"name": name, "mesh": mesh, "translation": list(khr_sphere_centre(k))}))
    _scene(b, roots)
    return b.write(Path(out) / "khr_extension_spheres.glb", mode="glb")


# ---------------------------------------------------------------------------------------------
# (7) Lights and cameras
# ---------------------------------------------------------------------------------------------
FLOOR_HALF, FLOOR_BASE_COLOR = 3.0, (0.8, 0.7, 0.6)
RIG_TRANSLATION = (0.0, 1.0, 0.0)  # the cameras' parent node
CAMERA_POSITION, CAMERA_TARGET = (0.5, 5.0, 5.0), (0.0, 0.0, 0.0)  # world space
CAMERA_YFOV, CAMERA_ASPECT, CAMERA_ZNEAR, CAMERA_ZFAR = 0.75, 1.5, 0.05, 100.0
ORTHO = {"xmag": 4.0, "ymag": 3.0, "znear": 0.01, "zfar": 50.0}
ORTHO_POSITION = (0.0, 8.0, 0.0)  # looking straight down
#: name -> (type, world position, world direction (None for a point light), properties written)
LIGHTS = {
    "point": ("point", (1.0, 2.0, 0.5), None, {"color": [1.0, 0.9, 0.8], "intensity": 5.0}),
    "spot": ("spot", (-1.5, 2.5, -1.0), (0.0, -1.0, 0.0),
             {"color": [0.6, 0.8, 1.0], "intensity": 20.0, "spot": {"innerConeAngle": 0.3, "outerConeAngle": 0.5}}),
    "sun": ("directional", None, tuple(np.array([0.3, -1.0, -0.4]) / np.linalg.norm([0.3, -1.0, -0.4])),
            {"color": [1.0, 1.0, 0.9], "intensity": 0.5}),
}


def lights_and_cameras(out: Path) -> Path:
    """A floor (Lambertian: KHR_materials_specular factor 0), the three KHR_lights_punctual
    lights, a perspective camera under a translated parent node and an orthographic camera; the
    buffer as a data URI."""
    b = Builder("jaxpbr test assets")
    b.used("KHR_lights_punctual", "KHR_materials_specular")
    b.doc["extensions"] = {"KHR_lights_punctual": {"lights": [dict(name=n, type=t, **props)
                                                              for n, (t, _, _, props) in LIGHTS.items()]}}
    m = b.add("materials", {"name": "floor", "pbrMetallicRoughness": {
        "baseColorFactor": [*FLOOR_BASE_COLOR, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0},
        "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}})
    h = FLOOR_HALF
    pos = np.array([[-h, 0, h], [h, 0, h], [h, 0, -h], [-h, 0, -h]])
    mesh = b.add("meshes", {"name": "floor", "primitives": [{"attributes": _attributes(
        b, pos, np.tile([0.0, 1.0, 0.0], (4, 1))), "indices": _indices(b, [[0, 1, 2], [0, 2, 3]]), "material": m}]})
    nodes = [b.add("nodes", {"name": "floor", "mesh": mesh})]
    for k, (name, (kind, p, d, _)) in enumerate(LIGHTS.items()):
        node = {"name": f"{name} light", "extensions": {"KHR_lights_punctual": {"light": k}}}
        if p is not None:
            node["translation"] = list(p)
        if d is not None:  # the light shines along the node's -Z
            node["rotation"] = quat_from_matrix(look_rotation((0, 0, 0), d, up=(0, 0, -1) if abs(d[1]) > 0.99 else (0, 1, 0)))
        nodes.append(b.add("nodes", node))
    persp = b.add("cameras", {"name": "perspective", "type": "perspective", "perspective": {
        "yfov": CAMERA_YFOV, "aspectRatio": CAMERA_ASPECT, "znear": CAMERA_ZNEAR, "zfar": CAMERA_ZFAR}})
    ortho = b.add("cameras", {"name": "orthographic", "type": "orthographic", "orthographic": dict(ORTHO)})
    local = np.asarray(CAMERA_POSITION) - np.asarray(RIG_TRANSLATION)
    cam_node = b.add("nodes", {"name": "perspective camera", "camera": persp, "translation": [float(v) for v in local],
                               "rotation": quat_from_matrix(look_rotation(CAMERA_POSITION, CAMERA_TARGET))})
    nodes.append(b.add("nodes", {"name": "rig", "translation": list(RIG_TRANSLATION), "children": [cam_node]}))
    nodes.append(b.add("nodes", {"name": "orthographic camera", "camera": ortho, "translation": list(ORTHO_POSITION),
                                 "rotation": quat_axis_angle((1, 0, 0), -math.pi / 2)}))
    _scene(b, nodes)
    return b.write(Path(out) / "lights_and_cameras.gltf", mode="data")


ASSETS = {
    "textured_cube": textured_cube,
    "node_hierarchy": node_hierarchy,
    "normal_mapped_plane": normal_mapped_plane,
    "alpha_mask_leaf": alpha_mask_leaf,
    "sphere_grid": sphere_grid,
    "khr_extension_spheres": khr_extension_spheres,
    "lights_and_cameras": lights_and_cameras,
}


def write_all(out: Path) -> dict[str, Path]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return {name: f(out) for name, f in ASSETS.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Write jaxpbr's named glTF test assets and validate them.")
    ap.add_argument("--out", required=True, help="folder to write the assets into")
    args = ap.parse_args(argv)
    return print_validation(list(write_all(Path(args.out)).values()))


if __name__ == "__main__":
    sys.exit(main())
