"""The named glTF test assets (tests/gltf_assets.py): each passes the Khronos glTF Validator, its
world-space triangles read by jaxpbr equal trimesh's, and what jaxpbr reads, builds and renders from
it matches the values written and closed forms (camera projections, texture lookups, Lambert
irradiance of punctual lights, the linearity of emission)."""

from __future__ import annotations

import importlib.util
import math
import warnings

import gltf_assets as A
import numpy as np
import pytest
from gltf_writer import validate, validator_missing

import jaxpbr as jp
from jaxpbr.io.gltf import read_gltf

# The renders use Embree, as tests/test_gltf_render.py's do; reading and validating do not.
renders = pytest.mark.skipif(importlib.util.find_spec("embreex") is None, reason="embreex is not installed")


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    return A.write_all(tmp_path_factory.mktemp("assets"))


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rays(position, target, fov_y_deg, width, height, up=(0.0, 1.0, 0.0)):
    """Pinhole rays through pixel centres (closed form): origin (3,), unit directions (H, W, 3)."""
    f = unit(np.asarray(target, np.float64) - position)
    r = unit(np.cross(f, up))
    u = np.cross(r, f)
    t = math.tan(math.radians(fov_y_deg) / 2)
    x = (2 * (np.arange(width) + 0.5) / width - 1) * t * width / height
    y = (1 - 2 * (np.arange(height) + 0.5) / height) * t
    d = f + x[None, :, None] * r + y[:, None, None] * u
    return np.asarray(position, np.float64), unit(d)


def _quiet_read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_gltf(path)


# ---------------------------------------------------------------------------------------------
# Independent readers: the Khronos validator and trimesh
# ---------------------------------------------------------------------------------------------
def test_every_asset_passes_the_khronos_validator(assets):
    why = validator_missing()
    if why:
        pytest.skip(why)
    report = validate(*assets.values())
    for name, path in assets.items():
        r = report[str(path)]
        assert r["numErrors"] == 0, (name, r["errors"])
        # The one warning: the plane is written without TANGENT on purpose.
        expected = ["MESH_PRIMITIVE_GENERATED_TANGENT_SPACE"] if name == "normal_mapped_plane" else []
        assert [w.split()[0] for w in r["warnings"]] == expected, (name, r["warnings"])


def _triangles_key(tris: np.ndarray) -> np.ndarray:
    """World-space triangles (n, 3, 3) as rows independent of vertex order and triangle order."""
    t = np.round(np.asarray(tris, np.float64), 4) + 0.0  # +0.0: no negative zeros
    t = np.array([sorted(map(tuple, tri)) for tri in t]).reshape(len(t), 9)
    return t[np.lexsort(t.T[::-1])]


@pytest.mark.parametrize("name", list(A.ASSETS))
def test_world_triangles_equal_trimesh(assets, name):
    trimesh = pytest.importorskip("trimesh")
    scene = trimesh.load(assets[name], force="scene", process=False)
    theirs = []
    for node in scene.graph.nodes_geometry:
        transform, geom = scene.graph[node]
        mesh = scene.geometry[geom]
        v = np.asarray(mesh.vertices, np.float64) @ transform[:3, :3].T + transform[:3, 3]
        theirs.append(v[np.asarray(mesh.faces)])
    ours = [p.positions.astype(np.float64)[p.indices] for p in _quiet_read(assets[name]).primitives]
    theirs, ours = np.concatenate(theirs), np.concatenate(ours)
    assert len(ours) == len(theirs) and len(ours) > 0
    np.testing.assert_allclose(_triangles_key(ours), _triangles_key(theirs), atol=2e-4)


# ---------------------------------------------------------------------------------------------
# (1) textured cube, (2) node hierarchy, (3) normal-mapped plane, (5) sphere grid: what is read
# ---------------------------------------------------------------------------------------------
_WRAP = {A.REPEAT: "repeat", A.CLAMP_TO_EDGE: "clamp", A.MIRRORED_REPEAT: "mirror"}
_FILTER = {A.NEAREST: "nearest", A.LINEAR: "linear", A.NEAREST_MIPMAP_NEAREST: "nearest_mipmap_nearest",
           A.LINEAR_MIPMAP_NEAREST: "linear_mipmap_nearest", A.NEAREST_MIPMAP_LINEAR: "nearest_mipmap_linear",
           A.LINEAR_MIPMAP_LINEAR: "linear_mipmap_linear"}


def test_textured_cube_every_sampler_reaches_its_texture(assets):
    """Each face's sampler (every wrap mode, both mag filters, all six min filters) is read and
    carried by the face's texture in the scene; the image decodes to the PNG's values."""
    assert {s[2] for s in A.SAMPLERS} == {A.NEAREST, A.LINEAR}
    assert {s[3] for s in A.SAMPLERS} == set(_FILTER)
    assert {s[0] for s in A.SAMPLERS} == {s[1] for s in A.SAMPLERS} == set(_WRAP)
    asset = read_gltf(assets["textured_cube"])
    np.testing.assert_allclose(asset.images[0].pixels, A.cube_texture() / 255.0, rtol=1e-6)
    scene = jp.load_gltf(assets["textured_cube"], width=8, height=8)
    assert len(scene.objects) == 6
    for f, (ws, wt, mag, mn) in enumerate(A.SAMPLERS):
        mat = asset.materials[f]
        s = mat.textures["base_color"].sampler
        assert (s.wrap_s, s.wrap_t, s.mag_filter, s.min_filter) == (_WRAP[ws], _WRAP[wt], _FILTER[mag], _FILTER[mn])
        tex = scene.objects[f].material.base_color_texture.texture
        assert (tex.wrap_s, tex.wrap_t, tex.mag_filter, tex.min_filter) == (_WRAP[ws], _WRAP[wt], _FILTER[mag], _FILTER[mn])
        prim = asset.primitives[f]
        assert prim.texcoord_0.min() == A.CUBE_UV_RANGE[0] and prim.texcoord_0.max() == A.CUBE_UV_RANGE[1]


def test_node_hierarchy_world_matrices_instancing_and_the_mirror(assets):
    """World matrices are the products of the local ones; the cube is drawn by three nodes and the
    tetrahedron by two; under the mirrored nodes (negative determinant) front faces stay
    counter-clockwise seen from outside, and the tetrahedron (no NORMAL) gets outward flat normals."""
    asset = read_gltf(assets["node_hierarchy"])
    world = A.hierarchy_world_matrices()
    names = list(A.HIERARCHY)
    drawn = [n for n, (_, mesh, _) in A.HIERARCHY.items() if mesh]
    assert sorted(names[p.node] for p in asset.primitives) == sorted(drawn)  # depth-first order
    assert sorted(p.mesh for p in asset.primitives) == [0, 0, 0, 1, 1]
    dets = []
    for p in asset.primitives:
        m = world[names[p.node]]
        np.testing.assert_allclose(p.world_matrix, m, atol=1e-12)
        local, ltri = (A.cube()[::2]) if A.HIERARCHY[names[p.node]][1] == "cube" else (A.TETRA, A.TETRA_TRIANGLES)
        want = (local @ m[:3, :3].T + m[:3, 3])[ltri]
        np.testing.assert_allclose(_triangles_key(p.positions[p.indices]), _triangles_key(want), atol=2e-4)
        tri = p.positions.astype(np.float64)[p.indices]
        face = unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
        centre = local.mean(0) @ m[:3, :3].T + m[:3, 3]
        assert np.all(np.einsum("ij,ij->i", face, tri.mean(1) - centre) > 0), names[p.node]
        np.testing.assert_allclose(p.normals[p.indices[:, 0]], face, atol=1e-5)
        dets.append(np.linalg.det(m[:3, :3]))
    assert sum(d < 0 for d in dets) == 2  # the mirror and its child


def test_normal_mapped_plane_gets_tangents_along_u_and_up_the_image(assets):
    """No TANGENT in the file: the generated frame has T = dP/du (+X) and bitangent
    cross(N, T) w = -dP/dv (-Z: a normal map's +Y points up the image, towards smaller v)."""
    asset = _quiet_read(assets["normal_mapped_plane"])
    (prim,) = asset.primitives
    assert asset.materials[0].needs_tangents and prim.tangents is not None
    np.testing.assert_allclose(prim.tangents[:, :3], np.tile([1.0, 0.0, 0.0], (prim.num_vertices, 1)), atol=1e-6)
    bit = np.cross(prim.normals, prim.tangents[:, :3]) * prim.tangents[:, 3:]
    np.testing.assert_allclose(bit, np.tile([0.0, 0.0, -1.0], (prim.num_vertices, 1)), atol=1e-6)
    t = asset.materials[0].textures["normal"]
    assert t.scale == 0.8 and t.colorspace == "linear"
    np.testing.assert_allclose(asset.images[t.image].pixels, A.normal_map_texture() / 255.0, rtol=1e-6)


def test_sphere_grid_materials_and_placement(assets):
    asset = read_gltf(assets["sphere_grid"])
    assert len(asset.primitives) == A.GRID_N ** 2 and len(asset.materials) == A.GRID_N ** 2
    for p in asset.primitives:
        i, j = divmod(p.material, A.GRID_N)
        metallic, roughness, centre = A.grid_params(i, j)
        f = asset.materials[p.material].factors
        assert (f["metallic"], f["roughness"]) == pytest.approx((metallic, roughness), abs=1e-12)
        np.testing.assert_allclose(f["base_color"], A.GRID_BASE_COLOR[:3])
        np.testing.assert_allclose(np.linalg.norm(p.positions - np.asarray(centre), axis=1), A.GRID_RADIUS, rtol=1e-6)
    h = (A.GRID_N - 1) / 2 * A.GRID_SPACING + A.GRID_RADIUS
    np.testing.assert_allclose(asset.bounds, [[-h, -h, -A.GRID_RADIUS], [h, h, A.GRID_RADIUS]], atol=1e-6)


# ---------------------------------------------------------------------------------------------
# (4) The alpha-mask leaf, rendered from both sides
# ---------------------------------------------------------------------------------------------
_BG = (0.05, 0.05, 0.1)


def _bilinear_alpha(u, v):
    """The texture's alpha at (u, v): GL LINEAR on level 0, CLAMP_TO_EDGE (texel centres at
    (i + 0.5) / n), from the uint8 texture written."""
    a = A.leaf_texture()[..., 3] / 255.0
    n = a.shape[0]
    x, y = u * n - 0.5, v * n - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    c = lambda i: np.clip(i, 0, n - 1)
    return ((1 - fx) * (1 - fy) * a[c(y0), c(x0)] + fx * (1 - fy) * a[c(y0), c(x0 + 1)]
            + (1 - fx) * fy * a[c(y0 + 1), c(x0)] + fx * fy * a[c(y0 + 1), c(x0 + 1)])


@renders
@pytest.mark.parametrize("side", [1.0, -1.0], ids=["front", "back"])
def test_alpha_mask_leaf_cut_out_follows_the_silhouette(assets, side):
    """Seen from the front and (doubleSided) from the back, lit from the viewer's side: a pixel
    whose ray meets the quad where the texture's alpha is below alphaCutoff shows the background,
    one where it is above shows the leaf (green, lit); the silhouette is computed here from the
    texture written and the camera's projection. The quad is magnified (texels larger than
    pixels), so the lookup is LINEAR on level 0."""
    W = H = 48
    cam_pos, fov = np.array([0.0, 0.0, 3.0 * side]), 45.0
    cam = jp.Camera(position=tuple(cam_pos), target=(0.0, 0.0, 0.0), fov_y_deg=fov, width=W, height=H)
    light = jp.DirectionalLight(direction=(0.0, -0.2, -side), intensity=3.0)
    scene = jp.load_gltf(assets["alpha_mask_leaf"], camera=cam, lights=[light], background=_BG)
    (mesh,) = scene.objects
    assert (mesh.alpha_mode, mesh.alpha_cutoff, mesh.double_sided) == ("MASK", A.LEAF_CUTOFF, True)
    img = np.asarray(jp.render(scene))
    o, d = rays(cam_pos, (0, 0, 0), fov, W, H)
    t = -o[2] / d[..., 2]
    x, y = o[0] + t * d[..., 0], o[1] + t * d[..., 1]
    h = A.LEAF_HALF_SIZE
    u, v = (x + h) / (2 * h), (h - y) / (2 * h)
    on_quad = (np.abs(x) < h - 1e-3) & (np.abs(y) < h - 1e-3)
    alpha = np.where(on_quad, _bilinear_alpha(np.clip(u, 0, 1), np.clip(v, 0, 1)), 0.0)
    clear = (alpha < A.LEAF_CUTOFF - 0.03)
    leaf = on_quad & (alpha > A.LEAF_CUTOFF + 0.03)
    assert leaf.sum() > 150 and (clear & on_quad).sum() > 300  # both in the picture, also inside the quad
    np.testing.assert_array_equal(img[clear], np.broadcast_to(np.float32(_BG), img[clear].shape))
    assert np.all(img[leaf] != np.float32(_BG))
    g = img[leaf]
    assert np.all(g[:, 1] > g[:, 0]) and np.all(g[:, 1] > g[:, 2])  # green, unlike the background


def _nearest_alpha(u, v):
    """The texture's alpha at (u, v) under GL NEAREST on level 0, CLAMP_TO_EDGE: the texel
    (floor(v n), floor(u n)) of the uint8 texture written."""
    a = A.leaf_texture()[..., 3] / 255.0
    n = a.shape[0]
    return a[np.clip(np.floor(v * n).astype(int), 0, n - 1), np.clip(np.floor(u * n).astype(int), 0, n - 1)]


@renders
def test_alpha_mask_leaf_nearest_cut_out_follows_the_texels(tmp_path):
    """The leaf with its sampler's magFilter NEAREST: the cut-out follows the texels, as the colour
    does -- a pixel shows the background exactly where the alpha of the texel its ray lands in is
    below alphaCutoff, and the leaf where it is above (rays within 1e-3 texel of a texel edge, and
    texels within 0.01 of the cutoff, are left out). Pixels where the bilinear and the nearest
    silhouettes disagree are in the picture, both ways."""
    W = H = 48
    cam_pos, fov = np.array([0.0, 0.0, 3.0]), 45.0
    cam = jp.Camera(position=tuple(cam_pos), target=(0.0, 0.0, 0.0), fov_y_deg=fov, width=W, height=H)
    light = jp.DirectionalLight(direction=(0.0, -0.2, -1.0), intensity=3.0)
    path = A.alpha_mask_leaf(tmp_path, mag_filter=A.NEAREST)
    scene = jp.load_gltf(path, camera=cam, lights=[light], background=_BG)
    (mesh,) = scene.objects
    assert mesh.material.base_color_texture.texture.mag_filter == "nearest"
    img = np.asarray(jp.render(scene))
    o, d = rays(cam_pos, (0, 0, 0), fov, W, H)
    t = -o[2] / d[..., 2]
    x, y = o[0] + t * d[..., 0], o[1] + t * d[..., 1]
    h, n = A.LEAF_HALF_SIZE, A.LEAF_TEXELS
    u, v = (x + h) / (2 * h), (h - y) / (2 * h)
    on_quad = (np.abs(x) < h - 1e-3) & (np.abs(y) < h - 1e-3)
    un, vn = np.clip(u, 0, 1) * n, np.clip(v, 0, 1) * n
    inside_texel = (np.abs(un - np.round(un)) > 1e-3) & (np.abs(vn - np.round(vn)) > 1e-3)
    alpha = np.where(on_quad, _nearest_alpha(np.clip(u, 0, 1), np.clip(v, 0, 1)), 0.0)
    sure = inside_texel & (np.abs(alpha - A.LEAF_CUTOFF) > 0.01)
    clear = sure & (alpha < A.LEAF_CUTOFF)
    leaf = sure & on_quad & (alpha > A.LEAF_CUTOFF)
    lin = np.where(on_quad, _bilinear_alpha(np.clip(u, 0, 1), np.clip(v, 0, 1)), 0.0)
    assert (clear & on_quad & (lin > A.LEAF_CUTOFF)).sum() > 5 and (leaf & (lin < A.LEAF_CUTOFF)).sum() > 5
    assert leaf.sum() > 150 and (clear & on_quad).sum() > 300
    np.testing.assert_array_equal(img[clear], np.broadcast_to(np.float32(_BG), img[clear].shape))
    assert np.all(img[leaf] != np.float32(_BG))
    g = img[leaf]
    assert np.all(g[:, 1] > g[:, 0]) and np.all(g[:, 1] > g[:, 2])


# ---------------------------------------------------------------------------------------------
# (6) The KHR extension row
# ---------------------------------------------------------------------------------------------
_FIELDS = {  # glTF property -> Material field
    "clearcoatFactor": "clearcoat", "clearcoatRoughnessFactor": "clearcoat_roughness",
    "sheenColorFactor": "sheen_color", "sheenRoughnessFactor": "sheen_roughness",
    "specularFactor": "specular", "specularColorFactor": "specular_color", "ior": "ior",
    "transmissionFactor": "transmission", "thicknessFactor": "thickness",
    "attenuationDistance": "attenuation_distance", "attenuationColor": "attenuation_color",
    "anisotropyStrength": "anisotropy_strength", "anisotropyRotation": "anisotropy_rotation",
    "emissiveStrength": "emissive_strength",
}
_TEXTURES = {"clearcoatTexture": "clearcoat_texture", "sheenColorTexture": "sheen_color_texture",
             "specularColorTexture": "specular_color_texture", "transmissionTexture": "transmission_texture",
             "thicknessTexture": "thickness_texture", "anisotropyTexture": "anisotropy_texture",
             "emissiveTexture": "emissive_texture"}


def _factors(m):
    return m.factors if isinstance(m, jp.TexturedMaterial) else m


def test_khr_row_loads_the_values_written(assets):
    """Every extension's factors land on the Material fields, its textures on the TexturedMaterial
    slots (with the 8-bit texel values, sRGB-decoded for colour slots), the plain sphere has no
    extension at all."""
    scene = jp.load_gltf(assets["khr_extension_spheres"], width=16, height=8)
    assert len(scene.objects) == len(A.KHR_SPHERES)
    for mesh, (name, ext, body, core) in zip(scene.objects, A.KHR_SPHERES):
        m = mesh.material
        f = _factors(m)
        np.testing.assert_allclose(f.base_color, A.KHR_CORE["baseColorFactor"][:3])
        assert (float(f.metallic), float(f.roughness)) == (0.0, 0.5)
        if ext is None:
            assert isinstance(m, jp.Material) and not f.extensions, name
            continue
        written = dict(body)
        if ext == "KHR_materials_volume":
            written["transmissionFactor"] = 1.0
        for key, value in written.items():
            if key in _FIELDS:
                np.testing.assert_allclose(np.asarray(getattr(f, _FIELDS[key]), np.float64), value, rtol=1e-7, err_msg=f"{name} {key}")
        slots = {k: v for k, v in {**body, **core}.items() if k in _TEXTURES}
        assert isinstance(m, jp.TexturedMaterial) == bool(slots), name
        for key, ref in slots.items():
            slot = getattr(m, _TEXTURES[key])
            assert slot is not None, f"{name} {key}"
            level0 = np.asarray(slot.texture.levels[0])
            texel = {"#data": np.array(A.KHR_DATA_TEXEL) / 255.0, "#white": np.ones(3),
                     "#colour": srgb(np.array(A.KHR_COLOUR_TEXEL) / 255.0)}[ref]
            np.testing.assert_allclose(level0[0, 0, : len(texel)], texel, rtol=1e-5, err_msg=f"{name} {key}")
        if name == "emissive_strength":
            np.testing.assert_allclose(f.emissive, A.KHR_EMISSIVE)


def srgb(c):
    return A.srgb_to_linear(c)


# The row seen from afar (nearly parallel views) at 160 x 40 pixels, so that with a light along the
# view each sphere's brightest pixel is where its normal is close to the half vector.
_ROW_W, _ROW_H, _ROW_DIST = 160, 40, 30.0
_ROW_FOV = math.degrees(2 * math.atan((4 * A.KHR_SPACING + A.KHR_RADIUS + 0.15) / (_ROW_W / _ROW_H) / _ROW_DIST))
_ROW_CAM = jp.Camera(position=(0.0, 0.0, _ROW_DIST), target=(0.0, 0.0, 0.0), fov_y_deg=_ROW_FOV, width=_ROW_W, height=_ROW_H)


def _row_masks(shrink=0.8):
    """Per sphere, the pixels whose ray meets the sphere of radius shrink x KHR_RADIUS (closed form:
    inside the tessellated sphere, away from its silhouette)."""
    o, d = rays(np.asarray(_ROW_CAM.position), _ROW_CAM.target, _ROW_FOV, _ROW_W, _ROW_H)
    out = []
    for k in range(len(A.KHR_SPHERES)):
        oc = o - np.asarray(A.khr_sphere_centre(k))
        b = d @ oc
        out.append(b * b - (oc @ oc - (shrink * A.KHR_RADIUS) ** 2) > 0)
    return out


def _plain(m):
    """The material without its extension: the same core factors (and emissive texture)."""
    f = _factors(m)
    core = jp.Material(base_color=f.base_color, metallic=f.metallic, roughness=f.roughness, occlusion=f.occlusion,
                       emissive=f.emissive)
    if isinstance(m, jp.TexturedMaterial) and m.emissive_texture is not None:
        return jp.TexturedMaterial(factors=core, emissive_texture=m.emissive_texture)
    return core


def _row_renders(path, light, names, **kw):
    """(with the extensions, with the plain materials, masks) of the spheres `names` of the row."""
    scene = jp.load_gltf(path, camera=_ROW_CAM, lights=[light])
    keep = [k for k, s in enumerate(A.KHR_SPHERES) if s[0] in names]
    scene = scene.replace(objects=tuple(scene.objects[k] for k in keep))
    ext = np.asarray(jp.render(scene, **kw))
    plain = np.asarray(jp.render(scene.replace(objects=tuple(o.replace(material=_plain(o.material)) for o in scene.objects)), **kw))
    assert np.all(np.isfinite(ext)) and np.all(np.isfinite(plain))
    masks = _row_masks()
    return ext, plain, {A.KHR_SPHERES[k][0]: masks[k] for k in keep}


@renders
@pytest.mark.slow
def test_khr_row_rendered_in_light_along_the_view(assets):
    """A directional light along the view: at each sphere's brightest plain pixel q (normal near
    the half vector, where the GGX lobe exceeds the Lambert term) -- clearcoat adds a coat lobe
    (brighter); ior 2.5 raises F0 from 0.04 to 0.18 (brighter); specularFactor 0 removes the
    Fresnel-weighted lobe (darker); anisotropy stretches the lobe and lowers its peak (darker);
    sheen's Charlie lobe vanishes where h = n while its albedo scaling dims the base (darker);
    transmission and volume replace the diffuse lobe by one that needs light from behind (darker).
    Every sphere's pixels are finite and differ from the plain material's."""
    light = jp.DirectionalLight(direction=(0.0, 0.0, -1.0), intensity=3.0)
    ext, plain, m = _row_renders(assets["khr_extension_spheres"], light, [s[0] for s in A.KHR_SPHERES])
    brighter, darker = {"clearcoat", "ior"}, {"specular", "anisotropy", "sheen", "transmission", "volume"}
    for name, mask in m.items():
        if name == "plain":  # the layered path at its defaults: the core path to float32 rounding
            np.testing.assert_allclose(ext[mask], plain[mask], rtol=1e-6, atol=1e-7)
            continue
        assert np.abs(ext[mask] - plain[mask]).max() > 1e-3, name
        if name in brighter | darker:
            q = np.unravel_index(np.argmax(np.where(mask, plain.sum(-1), -1.0)), mask.shape)
            assert (ext[q].sum() > plain[q].sum()) == (name in brighter), (name, ext[q], plain[q])


@renders
def test_khr_row_back_light_transmission_and_emissive_strength(assets):
    """A directional light from behind the row, shadows on: the plain sphere's visible pixels face
    away from it (black), the transmissive spheres let it through; the volume's attenuationColor
    (1, 0.5, 0.25) tints what comes through red > green > blue. On its way in, the light crosses
    the sphere's back wall, a thin-walled transmissive surface: it keeps transmission x base colour
    = 1 x 0.8 of itself, so each transmissive sphere's pixels are 0.8 x the same render without
    shadows. emissive_strength s multiplies the emission: that sphere's pixels exceed the same
    material without the extension by (s - 1) emissiveFactor x the emissive texel (sRGB-decoded)."""
    light = jp.DirectionalLight(direction=(0.0, 0.0, 1.0), intensity=3.0)
    names = ("plain", "transmission", "volume", "emissive_strength")
    ext, plain, m = _row_renders(assets["khr_extension_spheres"], light, names)
    unshadowed, _, _ = _row_renders(assets["khr_extension_spheres"], light, names, shadows=False)
    for name in ("plain", "transmission", "volume"):
        assert m[name].sum() > 80 and np.all(plain[m[name]] == 0.0), name
    assert np.all(ext[m["plain"]] == 0.0)
    t = ext[m["transmission"]]
    assert np.all(t > 0) and t.mean() > 0.5
    v = ext[m["volume"]]
    assert np.all(v[:, 0] > v[:, 1]) and np.all(v[:, 1] > v[:, 2]) and np.all(v[:, 2] > 0)
    through = A.KHR_CORE["baseColorFactor"][0] * A.KHR_DATA_TEXEL[0] / 255  # transmission 1 x its texture's R 1
    for name in ("transmission", "volume"):
        np.testing.assert_allclose(ext[m[name]], through * unshadowed[m[name]], rtol=1e-5, err_msg=name)
    e = np.asarray(A.KHR_EMISSIVE) * srgb(np.asarray(A.KHR_COLOUR_TEXEL) / 255.0)
    s = {k: b for k, _, b, _ in A.KHR_SPHERES[1:]}["emissive_strength"]["emissiveStrength"]
    em = m["emissive_strength"]
    np.testing.assert_allclose(plain[em], np.broadcast_to(e, plain[em].shape), rtol=1e-5)  # lit from behind: emission only
    np.testing.assert_allclose(ext[em], np.broadcast_to(s * e, ext[em].shape), rtol=1e-5)



# ---------------------------------------------------------------------------------------------
# (7) Lights and cameras
# ---------------------------------------------------------------------------------------------
def test_lights_and_cameras_reach_the_scene_in_the_specs_units(assets):
    """jp.load_gltf: the perspective camera's world pose (under a translated parent) and yfov; the
    point and spot lights in candela at their node positions, the spot's cone angles and direction
    (the node's -Z), the directional light in lux along its node's -Z; the orthographic camera is read."""
    scene = jp.load_gltf(assets["lights_and_cameras"], width=48, height=32)  # the camera's aspectRatio
    cam = scene.camera
    np.testing.assert_allclose(cam.position, A.CAMERA_POSITION, atol=1e-6)
    fwd = unit(np.asarray(cam.target, np.float64) - np.asarray(cam.position))
    np.testing.assert_allclose(fwd, unit(np.subtract(A.CAMERA_TARGET, A.CAMERA_POSITION)), atol=1e-6)
    assert abs(np.dot(unit(cam.up), fwd)) < 1e-6 and np.asarray(cam.up)[1] > 0
    assert float(cam.fov_y_deg) == pytest.approx(math.degrees(A.CAMERA_YFOV), abs=1e-9)
    point, spot, sun = scene.lights
    assert isinstance(point, jp.PointLight) and isinstance(spot, jp.SpotLight) and isinstance(sun, jp.DirectionalLight)
    for light, name in ((point, "point"), (spot, "spot"), (sun, "sun")):
        _, pos, direction, props = A.LIGHTS[name]
        assert float(light.intensity) == props["intensity"], name
        np.testing.assert_allclose(light.color, props["color"], err_msg=name)
        if pos is not None:
            np.testing.assert_allclose(light.position, pos, atol=1e-6, err_msg=name)
        if direction is not None:
            np.testing.assert_allclose(unit(light.direction), direction, atol=1e-6, err_msg=name)
    assert (float(spot.inner_cone_angle), float(spot.outer_cone_angle)) == (0.3, 0.5)
    assert float(point.inv_range) == 0.0 and float(spot.inv_range) == 0.0  # no range: unlimited
    ortho = [c for c in _quiet_read(assets["lights_and_cameras"]).cameras if c.type == "orthographic"]
    assert len(ortho) == 1 and (ortho[0].xmag, ortho[0].ymag, ortho[0].znear, ortho[0].zfar) == (
        A.ORTHO["xmag"], A.ORTHO["ymag"], A.ORTHO["znear"], A.ORTHO["zfar"])
    np.testing.assert_allclose(ortho[0].position, A.ORTHO_POSITION, atol=1e-9)
    np.testing.assert_allclose(ortho[0].forward, [0, -1, 0], atol=1e-9)


@renders
def test_lights_and_cameras_render_the_lambert_irradiance(assets):
    """Through the asset's own camera, the Lambertian floor (specularFactor 0) shows
    L = base_color / pi x sum of colour x E: a point or spot light of I candela at distance d gives
    E = I cos(theta) / d^2 (the spot inside its inner cone; pixels between the cones are left out),
    the directional light of E lux gives E cos(theta); the rays are the written camera's, computed
    here."""
    W, H = 48, 32
    scene = jp.load_gltf(assets["lights_and_cameras"], width=W, height=H)
    img = np.asarray(jp.render(scene, antialias=False))  # (the oracle is the pixel centres' radiance)
    o, d = rays(np.asarray(A.CAMERA_POSITION, np.float64), A.CAMERA_TARGET, math.degrees(A.CAMERA_YFOV), W, H)
    t = -o[1] / d[..., 1]
    x = o + t[..., None] * d
    floor = (t > 0) & (np.abs(x[..., [0, 2]]).max(-1) < A.FLOOR_HALF - 0.05)
    want, usable = _floor_radiance(x)
    usable &= floor
    assert usable.sum() > 500 and (floor & ~usable).sum() > 10
    np.testing.assert_allclose(img[usable], want[usable], rtol=1e-4)
    assert np.all(img[~floor & (t < 0)] == 0.0)


def _floor_radiance(x):
    """(radiance (..., 3), usable (...)) of the Lambertian floor of `lights_and_cameras` at the points
    x (..., 3) on it, lit by the asset's three lights; usable is False between the spot's cones."""
    n = np.array([0.0, 1.0, 0.0])
    E = np.zeros(x.shape)
    usable = np.ones(x.shape[:-1], bool)
    for name in ("point", "spot"):
        _, pos, direction, props = A.LIGHTS[name]
        to = np.asarray(pos) - x
        dist = np.linalg.norm(to, axis=-1)
        cos = np.clip(to @ n / dist, 0, None)
        e = props["intensity"] * cos / dist ** 2
        if name == "spot":
            cd = -(to / dist[..., None]) @ np.asarray(direction)
            inner, outer = math.cos(props["spot"]["innerConeAngle"]), math.cos(props["spot"]["outerConeAngle"])
            usable &= (cd > inner + 1e-3) | (cd < outer - 1e-3)
            e = np.where(cd > inner, e, 0.0)
        E += e[..., None] * np.asarray(props["color"])
    _, _, direction, props = A.LIGHTS["sun"]
    E += props["intensity"] * max(-np.dot(direction, n), 0.0) * np.asarray(props["color"])
    return np.asarray(A.FLOOR_BASE_COLOR) / math.pi * E, usable


@renders
def test_an_orthographic_camera_renders_parallel_rays_over_its_xmag_ymag_view(assets, tmp_path):
    """The asset's first camera orthographic (the perspective one's node left out of the scene):
    jp.load_gltf gives Camera(projection="orthographic", ymag=3) looking down from the node, and
    the image is the floor seen along parallel rays: pixel (i, j) sees the point
    position + x right + y up with x = (2 (j + 1/2)/W - 1) ymag W/H, y = (1 - 2 (i + 1/2)/H) ymag
    (xmag 4 = ymag W/H: the whole floor of half-size 3 fits the 8 x 6 view), lit as the closed
    form says; outside the floor nothing is hit."""
    import json

    doc = json.loads(assets["lights_and_cameras"].read_text())
    doc["scenes"][0]["nodes"] = [k for k in doc["scenes"][0]["nodes"] if doc["nodes"][k].get("name") != "rig"]
    path = tmp_path / "ortho.gltf"
    path.write_text(json.dumps(doc))
    W, H = 40, 30
    scene = jp.load_gltf(path, width=W, height=H)
    cam = scene.camera
    assert cam.projection == "orthographic" and float(cam.ymag) == A.ORTHO["ymag"]
    pos = np.asarray(cam.position, np.float64)
    fwd = unit(np.asarray(cam.target, np.float64) - pos)
    np.testing.assert_allclose(pos, A.ORTHO_POSITION, atol=1e-6)
    np.testing.assert_allclose(fwd, [0.0, -1.0, 0.0], atol=1e-6)
    right = unit(np.cross(fwd, np.asarray(cam.up, np.float64)))
    up = np.cross(right, fwd)
    xs = (2 * (np.arange(W) + 0.5) / W - 1) * A.ORTHO["ymag"] * W / H
    ys = (1 - 2 * (np.arange(H) + 0.5) / H) * A.ORTHO["ymag"]
    x = pos + xs[None, :, None] * right + ys[:, None, None] * up
    x[..., 1] = 0.0  # straight down onto the floor
    img = np.asarray(jp.render(scene))
    inside = np.abs(x[..., [0, 2]]).max(-1)
    floor = inside < A.FLOOR_HALF - 0.05
    want, usable = _floor_radiance(x)
    usable &= floor
    assert usable.sum() > 500
    np.testing.assert_allclose(img[usable], want[usable], rtol=1e-4)
    assert np.all(img[inside > A.FLOOR_HALF + 0.05] == 0.0)
