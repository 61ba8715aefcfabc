"""glTF assets rendered: meshes against the analytic objects they approximate, back faces, textures,
COLOR_0, gradients, compiled programs, the command line.

Oracles: the analytic Sphere / Plane render of the same material, light and camera (their own
tests check them against closed forms), closed-form uv mappings, finite differences."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.rendering import mesh as mesh_mod
from jaxpbr.rendering import renderer as R
from jaxpbr.rendering import stages
from jaxpbr.rendering.gltf_scene import load_gltf, scene_from_asset
from jaxpbr.rendering.mesh import Mesh

from gltf_writer import Writer, uv_sphere

pytest.importorskip("embreex")

SUN = jp.DirectionalLight(direction=(-0.4, -0.6, -0.7), color=(1.0, 0.95, 0.9), intensity=3.0)


def _quad(size=2.0, y=0.0):
    s = size / 2
    pos = np.array([[-s, y, s], [s, y, s], [s, y, -s], [-s, y, -s]], np.float32)  # facing +Y
    tri = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    nrm = np.tile(np.float32([0, 1, 0]), (4, 1))
    return pos, tri, uv, nrm


def _camera(w=48, h=40, pos=(0.3, 2.2, 2.6), target=(0.0, 0.0, 0.0)):
    return jp.Camera(position=pos, target=target, fov_y_deg=40.0, width=w, height=h)


def test_quad_mesh_matches_the_analytic_plane():
    """Flat geometry: the mesh and the analytic plane see the same points with the same normal."""
    pos, tri, uv, nrm = _quad(size=40.0)
    mat = jp.Material(base_color=(0.7, 0.5, 0.3), metallic=0.0, roughness=0.4)
    cam = _camera()
    a = jp.render(jp.Scene(camera=cam, objects=[Mesh(positions=pos, triangles=tri, normals=nrm, material=mat)], lights=[SUN]))
    b = jp.render(jp.Scene(camera=cam, objects=[jp.Plane(point=(0, 0, 0), normal=(0, 1, 0), material=mat)], lights=[SUN]))
    a, b = np.asarray(a), np.asarray(b)
    assert np.all(np.isfinite(a)) and a.max() > 0.05
    np.testing.assert_allclose(a, b, rtol=2e-5, atol=2e-6)


def test_sphere_mesh_matches_the_analytic_sphere():
    """A finely tessellated sphere with smooth normals against the exact sphere: interior pixels
    agree to the tessellation's error (normals within ~0.5 degree at 96 x 192), silhouettes apart."""
    P, N, UV, T = uv_sphere(96, 192)
    mat = jp.Material(base_color=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.5)
    cam = _camera(64, 64, pos=(0.0, 0.5, 4.0))
    # Point samples (antialias=False): the coverage test compares which pixel centres each one hits.
    a = np.asarray(jp.render(jp.Scene(camera=cam, objects=[Mesh(positions=P, triangles=T, normals=N, material=mat)], lights=[SUN]),
                             antialias=False))
    b = np.asarray(jp.render(jp.Scene(camera=cam, objects=[jp.Sphere(center=(0, 0, 0), radius=1.0, material=mat)], lights=[SUN]),
                             antialias=False))
    hit_a, hit_b = a.sum(-1) > 0, b.sum(-1) > 0
    # Coverage differs only along the silhouette (the polygon lies inside the sphere).
    assert (hit_a & ~hit_b).sum() == 0
    assert (hit_b & ~hit_a).sum() <= 0.03 * hit_b.sum()
    # Interior: away from the silhouette (erode the mask by 2 pixels).
    inner = hit_b.copy()
    for _ in range(2):
        inner = inner & np.roll(inner, 1, 0) & np.roll(inner, -1, 0) & np.roll(inner, 1, 1) & np.roll(inner, -1, 1)
    err = np.abs(a - b)[inner].max() / b[inner].max()
    assert err < 0.01, err


def test_single_sided_back_faces_are_culled_double_sided_are_shaded():
    pos, tri, uv, nrm = _quad(size=4.0)
    mat = jp.Material(base_color=(0.5, 0.5, 0.5), metallic=0.0, roughness=0.5)
    below = _camera(pos=(0.2, -2.0, 1.5))  # looks at the quad's back
    light = jp.DirectionalLight(direction=(0.0, 1.0, 0.2), intensity=2.0)  # lights the back
    one = jp.render(jp.Scene(camera=below, objects=[Mesh(positions=pos, triangles=tri, normals=nrm, material=mat)], lights=[light], background=(0.1, 0.2, 0.3)))
    two = jp.render(jp.Scene(camera=below, objects=[Mesh(positions=pos, triangles=tri, normals=nrm, material=mat, double_sided=True)], lights=[light], background=(0.1, 0.2, 0.3)))
    one, two = np.asarray(one), np.asarray(two)
    assert np.allclose(one, (0.1, 0.2, 0.3))  # culled: the background everywhere
    centre = two[20, 24]
    # Double-sided: the back face is shaded with the reversed normal (lit from below).
    ref = np.asarray(jp.render(jp.Scene(camera=below, objects=[jp.Plane(point=(0, 0, 0), normal=(0, -1, 0), material=mat)], lights=[light])))[20, 24]
    np.testing.assert_allclose(centre, ref, rtol=1e-4)


def test_textured_glb_quad_matches_the_textured_plane(tmp_path):
    """A .glb quad with an sRGB base-colour PNG: the loader decodes sRGB, the mesh's TEXCOORD_0
    maps the texture as the analytic plane's uv does (u along +X, v along +Z on this quad)."""
    rng = np.random.default_rng(3)
    tex8 = rng.integers(0, 256, (8, 8, 3)) / 255.0
    w = Writer()
    t = w.image_png(tex8)
    m = w.material(pbrMetallicRoughness={"baseColorTexture": {"index": t}, "metallicFactor": 0.0, "roughnessFactor": 0.6})
    pos, tri, uv, nrm = _quad(size=2.0)
    mesh = w.mesh(pos, tri, normals=nrm, uv=uv, material=m)
    w.node(mesh=mesh)
    path = w.save(tmp_path / "quad.glb")
    cam = jp.Camera(position=(0.0, 3.0, 0.001), target=(0.0, 0.0, 0.0), up=(0, 0, -1), fov_y_deg=30.0, width=32, height=32)
    scene = load_gltf(path, camera=cam, lights=[jp.DirectionalLight(direction=(0, -1, 0), intensity=3.0)])
    img = np.asarray(jp.render(scene))
    # The same texture decoded independently (exact sRGB EOTF) on an analytic plane whose uv frame
    # matches the quad: u = (x + 1)/2, v = (z + 1)/2 -> tangent +X, uv_scale 1/2, origin at (-1, 0, -1).
    lin = np.where(tex8 <= 0.04045, tex8 / 12.92, ((tex8 + 0.055) / 1.055) ** 2.4)
    tm = jp.TexturedMaterial(factors=jp.Material(metallic=0.0, roughness=0.6), base_color_texture=lin)
    plane = jp.Plane(point=(-1.0, 0.0, -1.0), normal=(0, 1, 0), tangent=(1, 0, 0), uv_scale=0.5, material=tm)
    ref = np.asarray(jp.render(jp.Scene(camera=cam, objects=[plane], lights=[jp.DirectionalLight(direction=(0, -1, 0), intensity=3.0)])))
    covered = img.sum(-1) > 0
    assert covered.sum() > 100
    np.testing.assert_allclose(img[covered], ref[covered], rtol=2e-4, atol=2e-5)


def test_vertex_colours_multiply_the_base_colour():
    pos, tri, uv, nrm = _quad(size=40.0)
    cols = np.tile(np.float32([0.5, 0.25, 1.0, 1.0]), (4, 1))
    cam = _camera()
    base = jp.Material(base_color=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.5)
    a = np.asarray(jp.render(jp.Scene(camera=cam, objects=[Mesh(positions=pos, triangles=tri, normals=nrm, colors=cols, material=base)], lights=[SUN])))
    b = np.asarray(jp.render(jp.Scene(camera=cam, objects=[Mesh(positions=pos, triangles=tri, normals=nrm, material=base.replace(base_color=(0.4, 0.2, 0.8)))], lights=[SUN])))
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_asset_camera_and_lights_are_used(tmp_path):
    """The asset's perspective camera frames the image and its KHR light lights it (a spot at the
    camera pointing at the quad lights the centre, not the corners beyond its cone)."""
    w = Writer()
    m = w.material(pbrMetallicRoughness={"baseColorFactor": [0.8, 0.8, 0.8, 1.0], "metallicFactor": 0.0})
    pos, tri, uv, nrm = _quad(size=6.0)
    w.node(mesh=w.mesh(pos, tri, normals=nrm, material=m))
    cam = w.camera(type="perspective", perspective={"yfov": math.radians(50), "znear": 0.01})
    # Node looking straight down -Y: rotate -90 degrees about X (quaternion xyzw).
    q = [-math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4)]
    w.node(camera=cam, translation=[0.0, 3.0, 0.0], rotation=q)
    lt = w.light(type="spot", intensity=40.0, spot={"innerConeAngle": 0.1, "outerConeAngle": 0.3})
    w.node(translation=[0.0, 3.0, 0.0], rotation=q, extensions={"KHR_lights_punctual": {"light": lt}})
    path = w.save(tmp_path / "lit.gltf")
    scene = load_gltf(path, width=33, height=33)
    assert abs(float(scene.camera.fov_y_deg) - 50.0) < 1e-4
    assert len(scene.lights) == 1 and isinstance(scene.lights[0], jp.SpotLight)
    img = np.asarray(jp.render(scene))
    assert img[16, 16].sum() > 0.05 and img[0, 0].sum() == 0.0


def test_gradients_reach_material_vertices_and_lights():
    """d image / d (roughness, a vertex's height, light intensity): finite, and the material's
    derivative matches a central difference (float64)."""
    P, N, UV, T = uv_sphere(16, 32)
    cam = _camera(24, 24, pos=(0.0, 0.5, 4.0))
    # float64 (the suite runs with jax_enable_x64, tests/conftest.py)
    P64 = jnp.asarray(P, jnp.float64)

    def loss(r, dy, k):
        m = jp.Material(base_color=(0.8, 0.6, 0.4), metallic=0.0, roughness=r)
        mesh = Mesh(positions=P64.at[:, 1].add(dy), triangles=T, normals=N, material=m)
        light = jp.DirectionalLight(direction=(-0.4, -0.6, -0.7), intensity=k)
        img = jp.render(jp.Scene(camera=cam, objects=[mesh], lights=[light]), dtype="float64")
        return jnp.sum(img)

    g = jax.grad(loss, argnums=(0, 1, 2))(0.5, 0.0, 3.0)
    assert all(np.isfinite(float(x)) for x in g)
    assert abs(float(g[1])) > 0  # the surface moves with its vertices
    h = 1e-5
    fd = (loss(0.5 + h, 0.0, 3.0) - loss(0.5 - h, 0.0, 3.0)) / (2 * h)
    np.testing.assert_allclose(float(g[0]), float(fd), rtol=1e-5)
    np.testing.assert_allclose(float(g[2]), float(loss(0.5, 0.0, 3.0)) / 3.0, rtol=1e-9)  # linear in k


def test_meshes_of_other_sizes_reuse_the_shading_programs():
    """Only the geometry stage depends on the mesh's size: a second mesh with other vertex and
    triangle counts compiles no new direct-lighting or IBL program, and its acceleration structure
    is built once however often it is rendered."""
    mat = jp.Material(base_color=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.5)
    cam = _camera(20, 16, pos=(0.0, 0.5, 4.0))
    env = jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(16))

    def draw(n):
        P, N, UV, T = uv_sphere(n, 2 * n)
        return jp.render(jp.Scene(camera=cam, objects=[Mesh(positions=P, triangles=T, normals=N, material=mat)], lights=[SUN], environment=env))

    draw(8)
    direct, suns, rest = stages._shade_direct_jit._cache_size(), stages._shade_suns_jit._cache_size(), stages._shade_rest_jit._cache_size()
    builds = mesh_mod.ACCELS.builds
    draw(11)
    draw(11)
    assert stages._shade_direct_jit._cache_size() == direct and stages._shade_rest_jit._cache_size() == rest
    assert stages._shade_suns_jit._cache_size() == suns > 0
    assert mesh_mod.ACCELS.builds == builds + 1


def test_mesh_and_spheres_in_one_scene_occlude_each_other():
    """A sphere in front of a quad hides it and the quad hides a sphere behind it."""
    pos, tri, uv, nrm = _quad(size=3.0)
    pos = pos[:, [0, 2, 1]] * np.float32([1, -1, 1])  # rotated +90 degrees about X: facing +Z
    nrm = np.tile(np.float32([0, 0, 1]), (4, 1))
    red = jp.Material(base_color=(0.9, 0.1, 0.1), metallic=0.0, roughness=0.5)
    blue = jp.Material(base_color=(0.1, 0.1, 0.9), metallic=0.0, roughness=0.5)
    cam = jp.Camera(position=(0, 0, 5), target=(0, 0, 0), fov_y_deg=40.0, width=33, height=33)
    light = jp.DirectionalLight(direction=(0, 0, -1), intensity=3.0)
    front = jp.Sphere(center=(0, 0, 1.0), radius=0.4, material=blue)
    back = jp.Sphere(center=(0.0, 0.0, -2.0), radius=1.0, material=blue)
    quad = Mesh(positions=pos, triangles=tri, normals=nrm, material=red)
    img = np.asarray(jp.render(jp.Scene(camera=cam, objects=[quad, front, back], lights=[light])))
    c = img[16, 16]
    assert c[2] > c[0]  # the front sphere at the centre
    edge = img[16, 7]
    assert edge[0] > edge[2]  # the quad hides the sphere behind it


def test_asset_alpha_modes_reach_the_meshes(tmp_path):
    """alphaMode, alphaCutoff and baseColorFactor's alpha of the file end up on the Mesh."""
    w = Writer()
    pos, tri, uv, nrm = _quad()
    m1 = w.material(alphaMode="BLEND", pbrMetallicRoughness={"baseColorFactor": [1, 1, 1, 0.5]})
    m2 = w.material(alphaMode="MASK", alphaCutoff=0.25, pbrMetallicRoughness={"baseColorFactor": [1, 1, 1, 0.8]})
    w.node(mesh=w.mesh(pos, tri, normals=nrm, material=m1))
    w.node(mesh=w.mesh(pos + np.float32([0, 1, 0]), tri, normals=nrm, material=m2))
    path = w.save(tmp_path / "alpha.glb")
    from jaxpbr.io.gltf import read_gltf

    gs = scene_from_asset(read_gltf(path), width=8, height=8)
    got = sorted((m.alpha_mode, m.alpha_cutoff, float(m.alpha)) for m in gs.scene.objects)
    assert got == [("BLEND", 0.5, 0.5), ("MASK", 0.25, pytest.approx(0.8))]
    assert R.plan(gs.scene).blend_layers > 1


# ------------------------------------------------------------------------------------------
# Shadows
# ------------------------------------------------------------------------------------------


def _shadow_scene(analytic: bool, light, shadows=None):
    """A sphere (radius 0.5 at height 1) above a ground quad, seen from above at an angle."""
    red = jp.Material(base_color=(0.8, 0.3, 0.3), metallic=0.0, roughness=0.6)
    grey = jp.Material(base_color=(0.7, 0.7, 0.7), metallic=0.0, roughness=0.8)
    if analytic:
        objs = [jp.Plane(point=(0, 0, 0), normal=(0, 1, 0), material=grey), jp.Sphere(center=(0, 1, 0), radius=0.5, material=red)]
    else:
        pos, tri, uv, nrm = _quad(size=40.0)
        P, N, UV, T = uv_sphere(48, 96, radius=0.5)
        objs = [Mesh(positions=pos, triangles=tri, normals=nrm, material=grey),
                Mesh(positions=P + np.float32([0, 1, 0]), triangles=T, normals=N, material=red)]
    cam = jp.Camera(position=(0.0, 6.0, 4.0), target=(0.0, 0.0, 0.0), fov_y_deg=40.0, width=64, height=48)
    return jp.Scene(camera=cam, objects=objs, lights=[light]), cam


def _ground_shadow_oracle(cam, light_dir, centre=(0, 1, 0), radius=0.5):
    """Per pixel: (on the ground and not on the sphere, shadowed by the sphere) in closed form."""
    o, d = (np.asarray(x, np.float64) for x in jp.rendering.scene.primary_rays(cam, dtype=jnp.float64))
    c = np.asarray(centre, np.float64)
    # The sphere hides the ground where the primary ray meets it.
    oc = o - c
    b = np.sum(oc * d, -1)
    on_sphere = (b * b - (np.sum(oc * oc, -1) - radius**2)) > 0
    t = -o[..., 1] / d[..., 1]
    p = o + t[..., None] * d
    l = -np.asarray(light_dir, np.float64) / np.linalg.norm(light_dir)
    cp = c - p
    along = cp @ l
    dist2 = np.sum(cp * cp, -1) - along**2
    shadowed = (along > 0) & (dist2 < radius**2)
    # Distance to the shadow's edge in the ground plane, to leave out pixels the edge crosses.
    return (t > 0) & ~on_sphere, shadowed, np.abs(np.sqrt(dist2) - radius)


@pytest.mark.parametrize("analytic", [False, True], ids=["meshes", "sphere+plane"])
def test_directional_shadow_matches_the_closed_form(analytic):
    light_dir = (-0.5, -1.0, -0.3)
    light = jp.DirectionalLight(direction=light_dir, intensity=3.0)
    scene, cam = _shadow_scene(analytic, light)
    # (antialias=False: the oracle is the closed form at the pixel centres)
    lit = np.asarray(jp.render(scene, shadows=False, antialias=False))
    img = np.asarray(jp.render(scene, shadows=True, antialias=False))
    ground, shadowed, edge = _ground_shadow_oracle(cam, light_dir)
    clear = ground & (edge > 0.04)  # a few pixels' footprint away from the shadow's edge
    assert (clear & shadowed).sum() > 20 and (clear & ~shadowed).sum() > 500
    np.testing.assert_array_equal(img[clear & shadowed], 0.0)  # no ambient, no environment
    np.testing.assert_allclose(img[clear & ~shadowed], lit[clear & ~shadowed], rtol=1e-6)


def test_point_light_shadow_and_no_self_shadowing():
    """A point light above the sphere: the ground under it is dark, and the sphere's lit side
    (geometric normal facing the light) is never shadowed by itself (no acne)."""
    light = jp.PointLight((0.3, 3.0, 0.2), intensity=20.0)
    scene, cam = _shadow_scene(False, light)
    lit = np.asarray(jp.render(scene, shadows=False))
    img = np.asarray(jp.render(scene, shadows=True))
    # Directly below the sphere along the light ray: the ground point under the light through the
    # sphere's centre is shadowed.
    o, d = (np.asarray(x) for x in jp.rendering.scene.primary_rays(cam, dtype=jnp.float64))
    lp, c = np.array([0.3, 3.0, 0.2]), np.array([0.0, 1.0, 0.0])
    g = lp + (c - lp) * (lp[1] / (lp[1] - c[1]))  # where the ray light -> centre meets y = 0
    t = -o[..., 1] / d[..., 1]
    p = o + t[..., None] * d
    k = np.unravel_index(np.argmin(np.sum((p - g) ** 2, -1)), t.shape)
    assert lit[k].sum() > 0 and img[k].sum() == 0.0
    # On the sphere: pixels whose (smooth) normal faces the light by more than the tessellation's
    # deviation are unchanged.
    oc = o - c
    b = np.sum(oc * d, -1)
    disc = b * b - (np.sum(oc * oc, -1) - 0.25)
    hit = disc > 0
    ts = -b - np.sqrt(np.maximum(disc, 0))
    q = o + ts[..., None] * d
    nrm = (q - c) / 0.5
    to_l = lp - q
    facing = np.sum(nrm * to_l, -1) / np.linalg.norm(to_l, axis=-1) > 0.1
    sel = hit & facing
    assert sel.sum() > 50
    np.testing.assert_allclose(img[sel], lit[sel], rtol=1e-6)


def test_extracted_sun_casts_shadows():
    """Under the procedural sky, the sun split out of the environment casts the sphere's shadow on
    the ground; the rest of the ground is lit as without shadows."""
    env = jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(32))
    scene, cam = _shadow_scene(False, jp.PointLight((0, 50, 0), intensity=0.0))
    scene = scene.replace(environment=env, lights=())
    plan = R.plan(scene)
    assert plan.env_lights >= 1 and plan.shadows
    lit = np.asarray(jp.render(scene, shadows=False))
    img = np.asarray(jp.render(scene))
    darker = (img.sum(-1) < 0.8 * lit.sum(-1))
    assert darker.sum() > 10  # the sun's shadow
    assert (img.sum(-1) <= lit.sum(-1) * (1 + 1e-5) + 1e-7).all()  # shadows only remove light


def test_sun_shadows_of_analytic_objects_render_under_jit():
    """Analytic objects only (no ray engine) with the sun split out of the sky casting shadows:
    the render under jax.jit equals the one outside it, and the shadow is there (the staged shadow
    path read the traced hit mask as a NumPy array, which raised under jit; the shadow itself is
    `test_extracted_sun_casts_shadows`'s)."""
    from jaxpbr.rendering.demo import demo_environment

    scene, _ = _shadow_scene(True, jp.PointLight((0, 50, 0), intensity=0.0))
    scene = scene.replace(environment=demo_environment(), lights=(), camera=scene.camera.replace(width=24, height=16))
    assert R.plan(scene, shadows=True).env_lights >= 1
    eager = np.asarray(jp.render(scene, shadows=True))
    traced = np.asarray(jax.jit(lambda s: jp.render(s, shadows=True))(scene))
    np.testing.assert_allclose(traced, eager, rtol=1e-5, atol=1e-7)


def test_extracted_sun_shines_through_a_transmissive_sphere():
    """Under the procedural sky, the sun split out of the environment is the only shadowed light
    (image-based lighting is not shadowed), so with the sphere transmissive (t, base colour c) the
    ground is B + (t c)^2 (A - B) per channel: A the render without shadows, B with the sphere
    shadowing fully (transmission 0), the sun's light crossing the sphere's two walls. All three
    renders use materials with the transmission extension (one shading path)."""
    env = jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(32))
    scene, cam = _shadow_scene(False, jp.PointLight((0, 50, 0), intensity=0.0))
    scene = scene.replace(environment=env, lights=())
    floor, ball = scene.objects
    t, c = 0.6, np.asarray(ball.material.base_color, np.float64)

    def with_transmission(x):
        return scene.replace(objects=(floor, ball.replace(material=ball.material.replace(transmission=x))))

    lit = np.asarray(jp.render(with_transmission(t), shadows=False))
    opaque = np.asarray(jp.render(with_transmission(0.0)))
    img = np.asarray(jp.render(with_transmission(t)))
    ground, _, _ = _ground_shadow_oracle(cam, (0.0, -1.0, 0.0))  # (its shadow mask is for another light)
    assert (ground & (opaque.sum(-1) < 0.8 * lit.sum(-1))).sum() > 10  # the sun's shadow
    want = opaque + (t * c) ** 2 * (lit - opaque)
    np.testing.assert_allclose(img[ground], want[ground], rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------------------
# Alpha: MASK cut-outs and BLEND layers
# ------------------------------------------------------------------------------------------


def _wall(z, size=3.0, **kw):
    """A quad standing at depth z, facing +Z (towards the camera), uv (0,0) at its top-left."""
    s = size / 2
    pos = np.array([[-s, s, z], [s, s, z], [s, -s, z], [-s, -s, z]], np.float32)
    tri = np.array([[0, 2, 1], [0, 3, 2]], np.int32)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (4, 1))
    return Mesh(positions=pos, triangles=tri, normals=nrm, texcoords=uv, **kw)


_FRONT = jp.Camera(position=(0, 0, 5), target=(0, 0, 0), fov_y_deg=30.0, width=32, height=32)
_LIGHT = jp.DirectionalLight(direction=(0.2, -0.3, -1.0), intensity=3.0)
_BACK = jp.Sphere(center=(0, 0, -1.5), radius=1.2, material=jp.Material(base_color=(0.2, 0.3, 0.9), metallic=0.0, roughness=0.5))
_GREEN = jp.Material(base_color=(0.2, 0.8, 0.2), metallic=0.0, roughness=0.5)


def _draw(*objs, **kw):
    return np.asarray(jp.render(jp.Scene(camera=_FRONT, objects=list(objs), lights=[_LIGHT], background=(0.05, 0.05, 0.1)), **kw))


def test_mask_cuts_out_by_the_alpha_cutoff():
    """MASK: alpha below the cutoff is not there (the sphere behind shows and nothing is shadowed),
    at or above it the surface is opaque; a texture's A cuts out the texels it covers."""
    behind = _draw(_BACK)
    opaque = _draw(_wall(0.5, material=_GREEN), _BACK)
    np.testing.assert_allclose(_draw(_wall(0.5, material=_GREEN, alpha_mode="MASK", alpha=0.3), _BACK), behind, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(_draw(_wall(0.5, material=_GREEN, alpha_mode="MASK", alpha=0.7), _BACK), opaque, rtol=1e-6, atol=1e-7)
    # Left half of the texture transparent, right half opaque (A = 0 / 1), sampled at level 0.
    rgba = np.ones((8, 8, 4), np.float32)
    rgba[:, :4, 3] = 0.0
    tm = jp.TexturedMaterial(factors=_GREEN, base_color_texture=rgba)
    img = _draw(_wall(0.5, material=tm, alpha_mode="MASK"), _BACK)
    x = np.arange(32)
    cols_left, cols_right = x < 12, x > 19  # the wall spans the image; its middle column is 16
    np.testing.assert_allclose(img[:, cols_left], behind[:, cols_left], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(img[:, cols_right], opaque[:, cols_right], rtol=1e-6, atol=1e-7)


def _gl_wrap(i, n, mode):
    """GL wrap of integer texel indices (OpenGL 4.6, Table 8.20)."""
    if mode == "repeat":
        return np.mod(i, n)
    if mode == "clamp":
        return np.clip(i, 0, n - 1)
    m = np.mod(i, 2 * n) - n  # MIRRORED_REPEAT: (n - 1) - mirror((i mod 2n) - n)
    return (n - 1) - np.where(m >= 0, m, -(1 + m))


@pytest.mark.parametrize("mag", ["nearest", "linear"])
def test_cut_out_alpha_is_looked_up_with_the_samplers_filter_and_wraps(mag):
    """The alpha a MASK mesh is cut by, at hits with uv far outside [0, 1] under every pair of wrap
    modes and a texture transform: with a NEAREST magFilter the A of the texel (floor(v H),
    floor(u W)) after GL wrapping; with LINEAR the bilinear mix of the four texels around
    (u W - 1/2, v H - 1/2), each wrapped (both computed here from the GL rules); and equal to
    what the colour path's sampler returns there (`texture.sample`, magnified)."""
    from jaxpbr.rendering import texture as T

    rng = np.random.default_rng(3)
    Hh, Ww = 5, 7
    rgba = rng.uniform(0.0, 1.0, (Hh, Ww, 4)).astype(np.float32)
    b = rng.uniform(0.0, 1.0, (400, 2))
    b = np.where(b.sum(-1, keepdims=True) > 1, 1 - b, b)  # inside the triangle
    xform = np.array([[1.5, 0.2, 0.3], [-0.1, 1.2, -0.4], [0, 0, 1]])
    # One triangle whose uv spans [-1.5, 2.5]^2: uv = (-1.5 + 4 b1, -1.5 + 4 b2).
    uv = np.array([[-1.5, -1.5], [2.5, -1.5], [-1.5, 2.5]], np.float32)
    st = np.stack([-1.5 + 4 * b[:, 0], -1.5 + 4 * b[:, 1], np.ones(len(b))], -1) @ xform.T
    u, v = st[:, 0], st[:, 1]
    for ws in ("repeat", "clamp", "mirror"):
        for wt in ("repeat", "clamp", "mirror"):
            tex = jp.Texture.from_image(rgba, srgb=False, wrap_s=ws, wrap_t=wt, mag_filter=mag)
            mat = jp.TexturedMaterial(factors=_GREEN, base_color_texture=jp.TextureSlot(texture=tex, transform=xform))
            mesh = Mesh(positions=np.eye(3, dtype=np.float32), triangles=np.array([[0, 1, 2]], np.int32), texcoords=uv,
                        material=mat, alpha_mode="MASK")
            arrays = mesh_mod.concat_meshes([mesh], jnp.float64)
            _, got = mesh_mod.host_alpha(arrays["alpha"], np.array([[0, 1, 2]]), np.zeros(len(b), np.int32), b[:, 0], b[:, 1])
            a = rgba[..., 3].astype(np.float64)
            if mag == "nearest":
                want = a[_gl_wrap(np.floor(v * Hh).astype(int), Hh, wt), _gl_wrap(np.floor(u * Ww).astype(int), Ww, ws)]
            else:
                x, y = u * Ww - 0.5, v * Hh - 0.5
                x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
                fx, fy = x - x0, y - y0
                xa, xb = _gl_wrap(x0, Ww, ws), _gl_wrap(x0 + 1, Ww, ws)
                ya, yb = _gl_wrap(y0, Hh, wt), _gl_wrap(y0 + 1, Hh, wt)
                want = ((1 - fx) * (1 - fy) * a[ya, xa] + fx * (1 - fy) * a[ya, xb]
                        + (1 - fx) * fy * a[yb, xa] + fx * fy * a[yb, xb])
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7, err_msg=f"{ws} {wt}")
            colour = np.asarray(T.sample(tex, jnp.asarray(st[:, :2], jnp.float32)))[:, 3]
            np.testing.assert_allclose(got, colour, rtol=1e-5, atol=1e-5, err_msg=f"{ws} {wt}")


def test_blend_composites_layers_front_to_back():
    """BLEND: C = a1 C1 + (1 - a1) a2 C2 + (1 - a1)(1 - a2) C_behind, each C the surface drawn
    opaque on its own (shadows off: blended surfaces cast none, opaque stand-ins would)."""
    a1, a2 = 0.4, 0.7
    red = jp.Material(base_color=(0.9, 0.2, 0.1), metallic=0.0, roughness=0.5)
    w1 = lambda **k: _wall(0.8, size=2.0, material=red, **k)  # noqa: E731
    w2 = lambda **k: _wall(0.2, size=3.0, material=_GREEN, **k)  # noqa: E731
    # (antialias=False: the composite is checked per pixel centre, its layers' outlines not blended)
    c1 = _draw(w1(), _BACK, shadows=False, antialias=False)
    c2 = _draw(w2(), _BACK, shadows=False, antialias=False)
    cb = _draw(_BACK, shadows=False, antialias=False)
    got = _draw(w1(alpha_mode="BLEND", alpha=a1), w2(alpha_mode="BLEND", alpha=a2), _BACK, shadows=False, antialias=False)
    # Pixels covered by both walls (the inner one spans the centre), by the outer one only, by none.
    both = (c1 != cb).any(-1) & (c2 != cb).any(-1)
    only2 = ~(c1 != cb).any(-1) & (c2 != cb).any(-1)
    assert both.sum() > 100 and only2.sum() > 50
    want = a1 * c1 + (1 - a1) * a2 * c2 + (1 - a1) * (1 - a2) * cb
    np.testing.assert_allclose(got[both], want[both], rtol=1e-5, atol=1e-6)
    want2 = a2 * c2 + (1 - a2) * cb
    np.testing.assert_allclose(got[only2], want2[only2], rtol=1e-5, atol=1e-6)


def test_cut_out_and_blended_surfaces_cast_no_shadows():
    """A MASK wall below its cutoff and a BLEND wall between the light and the sphere leave the
    sphere lit as without them; an opaque wall shadows it."""
    light = jp.DirectionalLight(direction=(0.0, 0.0, -1.0), intensity=3.0)
    scene = lambda *o: np.asarray(jp.render(jp.Scene(camera=jp.Camera(position=(3, 0, 4), target=(0, 0, -1.5), fov_y_deg=40.0, width=32, height=32), objects=list(o), lights=[light])))  # noqa: E731
    alone = scene(_BACK, _wall(0.5, size=0.001, material=_GREEN))  # a speck: keeps the scene a mesh scene
    for w in (_wall(3.0, material=_GREEN, alpha_mode="MASK", alpha=0.2), _wall(3.0, material=_GREEN, alpha_mode="BLEND", alpha=0.5)):
        img = scene(_BACK, w)
        sphere_px = (alone != 0.0).any(-1) & (img != 0.0).any(-1)
        assert sphere_px.sum() > 50
    opaque = scene(_BACK, _wall(3.0, material=_GREEN))
    masked = scene(_BACK, _wall(3.0, material=_GREEN, alpha_mode="MASK", alpha=0.2))
    assert opaque.sum() < 0.5 * masked.sum()
    np.testing.assert_allclose(masked, alone, rtol=1e-6, atol=1e-7)


# A point light over a Lambertian floor (specularFactor 0), seen from below the occluders' height.
_FLOOR_MAT = jp.Material(base_color=(0.6, 0.6, 0.6), metallic=0.0, roughness=1.0, specular=0.0)
_LAMP = np.array([0.1, 3.0, 0.05])
_LAMP_CD = 10.0
_GLASS_T, _GLASS_BASE = 0.6, np.array([0.9, 0.5, 0.2])
_GLASS = jp.Material(base_color=tuple(_GLASS_BASE), metallic=0.0, roughness=0.3, transmission=_GLASS_T)


def _floor_render(*occluders, analytic=False, **kw):
    """The floor (a mesh quad, or an analytic plane) lit by the point light, 48 x 40 pixels, and
    per pixel: its floor point (closed form, NaN off the floor) and the Lambert radiance
    base / pi x I cos(theta) / d^2 there."""
    W, H = 48, 40
    cam_pos, target, fov = np.array([0.0, 0.8, 3.2]), (0.0, 0.0, 0.0), 50.0
    cam = jp.Camera(position=tuple(cam_pos), target=target, fov_y_deg=fov, width=W, height=H)
    half = 3.0
    floor = (jp.Plane(point=(0, 0, 0), normal=(0, 1, 0), material=_FLOOR_MAT) if analytic
             else Mesh(positions=np.array([[-half, 0, half], [half, 0, half], [half, 0, -half], [-half, 0, -half]], np.float32),
                       triangles=np.array([[0, 1, 2], [0, 2, 3]], np.int32), normals=np.tile(np.float32([0, 1, 0]), (4, 1)),
                       material=_FLOOR_MAT))
    scene = jp.Scene(camera=cam, objects=[floor, *occluders], lights=[jp.PointLight(tuple(_LAMP), intensity=_LAMP_CD)])
    img = np.asarray(jp.render(scene, antialias=False, **kw))  # (the oracles are the pixel centres')
    f = target - cam_pos
    f /= np.linalg.norm(f)
    r = np.cross(f, [0, 1, 0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    tn = math.tan(math.radians(fov) / 2)
    x = (2 * (np.arange(W) + 0.5) / W - 1) * tn * W / H
    y = (1 - 2 * (np.arange(H) + 0.5) / H) * tn
    d = f + x[None, :, None] * r + y[:, None, None] * u
    t = -cam_pos[1] / d[..., 1]
    p = cam_pos + t[..., None] * d
    on = (t > 0) & (np.abs(p[..., [0, 2]]).max(-1) < half - 0.05)
    p[~on] = np.nan
    to = _LAMP - p
    dist = np.linalg.norm(to, axis=-1)
    lambert = np.asarray(_FLOOR_MAT.base_color) / math.pi * (_LAMP_CD * to[..., 1] / dist ** 3)[..., None]
    return img, p, lambert


def _glass_quad(material, y=1.0, half=0.5):
    """A horizontal quad at height y, facing up (double-sided: a thin sheet)."""
    pos = np.array([[-half, y, half], [half, y, half], [half, y, -half], [-half, y, -half]], np.float32)
    return Mesh(positions=pos, triangles=np.array([[0, 1, 2], [0, 2, 3]], np.int32), normals=np.tile(np.float32([0, 1, 0]), (4, 1)),
                material=material, double_sided=True)


def test_transmissive_quad_tints_its_shadow_by_transmission_times_base_colour():
    """A thin transmissive quad (KHR_materials_transmission t, base colour c) between a point light
    and a Lambertian floor: under it the floor shows the Lambert radiance times t c (the light
    kept by one thin-walled crossing), elsewhere the Lambert radiance itself. The same quad opaque,
    or with transmission 0, shadows fully. The floor points under the quad: those whose segment to
    the light crosses y = 1 inside it (closed form; a 0.03 band around its edge left out)."""
    img, p, lambert = _floor_render(_glass_quad(_GLASS))
    s = (1.0 - p[..., 1]) / (_LAMP[1] - p[..., 1])
    cross = p + s[..., None] * (_LAMP - p)
    reach = np.abs(cross[..., [0, 2]]).max(-1)
    under, clear = reach < 0.5 - 0.03, reach > 0.5 + 0.03
    assert under.sum() > 40 and clear.sum() > 500
    tr = _GLASS_T * _GLASS_BASE
    np.testing.assert_allclose(img[under], lambert[under] * tr, rtol=1e-4)
    np.testing.assert_allclose(img[clear], lambert[clear], rtol=1e-4)
    opaque = jp.Material(base_color=tuple(_GLASS_BASE), metallic=0.0, roughness=0.3)
    zero = jp.Material(base_color=tuple(_GLASS_BASE), metallic=0.0, roughness=0.3, transmission=0.0)
    for m in (opaque, zero):
        img, _, _ = _floor_render(_glass_quad(m))
        np.testing.assert_array_equal(img[under], 0.0)
        np.testing.assert_allclose(img[clear], lambert[clear], rtol=1e-4)


@pytest.mark.parametrize("analytic", [False, True], ids=["mesh", "sphere+plane"])
def test_transmissive_sphere_tints_its_shadow_once_per_wall(analytic):
    """A transmissive sphere between the light and the floor (a UV-sphere mesh over a mesh floor,
    or an analytic sphere over a plane): a shadow ray through it crosses two thin walls, so the
    floor under it shows the Lambert radiance times (t c)^2; elsewhere the Lambert radiance.
    Under it: floor points whose segment to the light passes within r - 0.03 of the centre."""
    centre, r = np.array([0.0, 1.3, 0.0]), 0.5
    if analytic:
        ball = jp.Sphere(center=tuple(centre), radius=r, material=_GLASS)
    else:
        pos, nrm, _, tri = uv_sphere(24, 48, radius=r)
        ball = Mesh(positions=(pos + centre).astype(np.float32), triangles=tri.astype(np.int32), normals=nrm.astype(np.float32),
                    material=_GLASS)
    img, p, lambert = _floor_render(ball, analytic=analytic, shadows=True)
    seg = _LAMP - p
    k = np.clip(np.einsum("...i,...i->...", centre - p, seg) / np.einsum("...i,...i->...", seg, seg), 0, 1)
    miss = np.linalg.norm(p + k[..., None] * seg - centre, axis=-1)
    under, clear = miss < r - 0.03, miss > r + 0.03
    assert under.sum() > 40 and clear.sum() > 500
    tr = _GLASS_T * _GLASS_BASE
    np.testing.assert_allclose(img[under], lambert[under] * tr ** 2, rtol=1e-4)
    np.testing.assert_allclose(img[clear], lambert[clear], rtol=1e-4)


def test_mipmapped_texture_aliases_less_than_plain_bilinear():
    """A checkerboard floor seen at grazing angles: one sample per pixel of the mip-mapped,
    anisotropically filtered TextureSlot (footprint from ray differentials) is far closer to the
    8x8-supersampled image than one sample of plain bilinear lookups."""
    checks = (np.indices((64, 64)).sum(0) // 8 % 2).astype(np.float32)
    img = np.repeat(0.1 + 0.8 * checks[..., None], 3, -1)
    size, reps = 40.0, 20.0
    pos, tri, _, nrm = _quad(size=size)
    uv = np.array([[0, reps], [reps, reps], [reps, 0], [0, 0]], np.float32)
    light = jp.DirectionalLight(direction=(0.0, -1.0, 0.0), intensity=3.0)
    cam = jp.Camera(position=(0.0, 1.0, 6.0), target=(0.0, 0.0, -20.0), fov_y_deg=50.0, width=48, height=32)

    def draw(texture, s=1):
        tm = jp.TexturedMaterial(factors=jp.Material(metallic=0.0, roughness=1.0), base_color_texture=texture)
        mesh = Mesh(positions=pos, triangles=tri, normals=nrm, texcoords=uv, material=tm)
        return np.asarray(jp.render(jp.Scene(camera=cam.replace(supersample=s), objects=[mesh], lights=[light]), shadows=False))

    ref = draw(img, s=8)
    plain = draw(img)
    mip = draw(jp.TextureSlot(texture=jp.Texture.from_image(img, srgb=False)))
    floor = ref.sum(-1) > 0
    assert floor.sum() > 500
    err = lambda x: float(np.sqrt(np.mean((x[floor] - ref[floor]) ** 2)))  # noqa: E731
    assert err(mip) < 0.5 * err(plain), (err(mip), err(plain))
    print(f"RMSE against 8x8 supersampling: mip-mapped {err(mip):.4f}, plain bilinear {err(plain):.4f}")


def test_render_batch_over_cameras_and_materials_with_meshes():
    """render_batch vmaps the mesh path (visibility per image through the callback): each image
    equals the single render of its camera / material."""
    P, N, UV, T = uv_sphere(16, 32)
    mat = jp.Material(base_color=(0.8, 0.6, 0.4), metallic=0.0, roughness=0.5)
    cam = jp.Camera(position=(0, 0.5, 4), target=(0, 0, 0), width=24, height=16)
    scene = jp.Scene(camera=cam, objects=[Mesh(positions=P, triangles=T, normals=N, material=mat)], lights=[SUN])
    positions = np.array([[0, 0.5, 4.0], [3, 0.5, 3.0], [0, 3, 2.0]], np.float32)
    imgs = np.asarray(jp.render_batch(scene, cameras=cam.replace(position=jnp.asarray(positions))))
    for k in range(3):
        one = np.asarray(jp.render(scene.replace(camera=cam.replace(position=tuple(positions[k])))))
        np.testing.assert_allclose(imgs[k], one, rtol=1e-5, atol=1e-6)
    colours = np.array([[0.8, 0.2, 0.2], [0.2, 0.8, 0.2]], np.float32)
    imgs = np.asarray(jp.render_batch(scene, materials=jp.Material(base_color=jnp.asarray(colours), metallic=0.0, roughness=0.5)))
    for k in range(2):
        one = np.asarray(jp.render(scene.replace(objects=[scene.objects[0].replace(material=mat.replace(base_color=tuple(colours[k])))])))
        np.testing.assert_allclose(imgs[k], one, rtol=1e-5, atol=1e-6)


def test_aovs_against_closed_forms(tmp_path):
    """Depth, normal, position, mask, ids of a quad mesh and a sphere, against the closed-form ray
    casts; the command line writes them as EXR layers that read back equal."""
    from jaxpbr.io import image
    from jaxpbr.rendering.aovs import aovs

    pos, tri, uv, nrm = _quad(size=40.0)
    grey = jp.Material(base_color=(0.25, 0.5, 0.75), metallic=0.0, roughness=0.5)
    cam = _camera(40, 30, pos=(0.0, 3.0, 5.0))
    ball = jp.Sphere(center=(0.0, 0.5, 0.0), radius=0.5, material=grey)
    scene = jp.Scene(camera=cam, objects=[ball, Mesh(positions=pos, triangles=tri, normals=nrm, material=grey)], lights=[SUN])
    a = aovs(scene)
    o, d = (np.asarray(x, np.float64) for x in jp.rendering.scene.primary_rays(cam, dtype=jnp.float64))
    fwd = -np.asarray(cam.position, np.float64) / np.linalg.norm(cam.position)
    t_plane = -o[..., 1] / d[..., 1]
    oc = o - np.array([0.0, 0.5, 0.0])
    b = np.sum(oc * d, -1)
    disc = b * b - (np.sum(oc * oc, -1) - 0.25)
    on_ball = disc > 1e-3
    t_ball = -b - np.sqrt(np.maximum(disc, 0))
    on_plane = ~on_ball & (t_plane > 0) & (np.abs(o + t_plane[..., None] * d)[..., [0, 2]].max(-1) < 20)
    np.testing.assert_array_equal(a["mask"][on_ball | on_plane], 1.0)
    np.testing.assert_array_equal(a["object_id"][on_ball], 0.0)
    np.testing.assert_array_equal(a["object_id"][on_plane], 1.0)
    assert set(np.unique(a["primitive_id"][on_plane])) <= {0.0, 1.0}
    np.testing.assert_array_equal(a["primitive_id"][on_ball], -1.0)
    np.testing.assert_allclose(a["distance"][on_plane], t_plane[on_plane], rtol=1e-5)
    np.testing.assert_allclose(a["depth"][on_plane], (t_plane[..., None] * d @ fwd)[on_plane], rtol=1e-5)
    np.testing.assert_allclose(a["normal"][on_plane], np.broadcast_to([0, 1, 0], a["normal"][on_plane].shape), atol=1e-6)
    q = o + t_ball[..., None] * d
    np.testing.assert_allclose(a["position"][on_ball], q[on_ball], atol=2e-5)
    np.testing.assert_allclose(a["base_color"][on_plane], np.broadcast_to([0.25, 0.5, 0.75], a["base_color"][on_plane].shape), rtol=1e-6)
    # The command line: the same values as EXR layers.
    w = Writer()
    m = w.material(pbrMetallicRoughness={"baseColorFactor": [0.25, 0.5, 0.75, 1.0], "metallicFactor": 0.0})
    w.node(mesh=w.mesh(pos, tri, normals=nrm, material=m))
    path = w.save(tmp_path / "floor.glb")
    from jaxpbr.cli import main

    out = tmp_path / "floor.png"
    assert main(["render", str(path), "-o", str(out), "--width", "40", "--height", "30", "--camera-position", "0,3,5",
                 "--camera-target", "0,0,0", "--fov-y", "45", "--aov", "depth,normal,primitive_id"]) == 0
    z = image.read(out.with_suffix(".exr"), channels=["Z"])[..., 0]
    ny = image.read(out.with_suffix(".exr"), channels=["N.Y"])[..., 0]
    ref = aovs(load_gltf(path, camera=jp.Camera(position=(0, 3, 5), target=(0, 0, 0), fov_y_deg=45.0, width=40, height=30)))
    np.testing.assert_array_equal(z, ref["depth"])
    np.testing.assert_array_equal(ny, ref["normal"][..., 1])


def test_render_with_aovs_shares_the_render_s_geometry(monkeypatch):
    """render_with_aovs: the image and the AOVs equal separate `render` and `aovs` calls, with the
    meshes' primary rays cast once instead of twice (and twice again where the passes differ:
    supersampling). The shared pass is the staged one (XLA:CPU's default), so the test stages on
    any backend."""
    from jaxpbr.rendering import mesh as mesh_mod
    from jaxpbr.rendering.aovs import aovs, render_with_aovs
    from jaxpbr.rendering.execution import EXECUTION

    monkeypatch.setattr(EXECUTION, "staged", True)

    pos, tri, uv, nrm = _quad(size=40.0)
    grey = jp.Material(base_color=(0.25, 0.5, 0.75), metallic=0.0, roughness=0.5)
    ball = jp.Sphere(center=(0.0, 0.5, 0.0), radius=0.5, material=grey)
    scene = jp.Scene(camera=_camera(40, 30, pos=(0.0, 3.0, 5.0)),
                     objects=[ball, Mesh(positions=pos, triangles=tri, normals=nrm, material=grey)], lights=[SUN])
    names = ("depth", "normal", "base_color", "mask", "object_id", "primitive_id")
    casts = []
    accels = mesh_mod.ACCELS

    class Counted:  # the host cast asks the structure cache once per call (a compiled program keeps
        def get(self, *a, **k):  # the callback it was traced with, so that is not patched)
            casts.append(1)
            return accels.get(*a, **k)

    monkeypatch.setattr(mesh_mod, "ACCELS", Counted())
    hdr, a = render_with_aovs(scene, names)
    assert len(casts) == 1
    np.testing.assert_array_equal(np.asarray(hdr), np.asarray(jp.render(scene)))
    ref = aovs(scene, names)
    assert set(a) == set(ref)
    for k in names:
        np.testing.assert_array_equal(a[k], ref[k], err_msg=k)
    assert a["mask"].sum() > 100 and {0.0, 1.0} <= set(np.unique(a["object_id"]).tolist())
    casts.clear()
    ss = scene.replace(camera=scene.camera.replace(supersample=2))
    hdr2, a2 = render_with_aovs(ss, ("depth",))
    assert len(casts) == 4 + 1  # the 2 x 2 sub-pixel passes, then the AOVs' own pass
    np.testing.assert_array_equal(a2["depth"], aovs(ss, ("depth",))["depth"])


def test_toml_scene_includes_a_gltf_asset(tmp_path):
    """[[objects]] type = "gltf": the asset's meshes and lights join the scene file's objects; the
    render equals the same scene built in Python; a missing file is one error naming the key."""
    from jaxpbr.rendering.scene_file import load_scene
    from jaxpbr.errors import InputError

    w = Writer()
    m = w.material(pbrMetallicRoughness={"baseColorFactor": [0.7, 0.7, 0.7, 1.0], "metallicFactor": 0.0})
    pos, tri, uv, nrm = _quad(size=6.0)
    w.node(mesh=w.mesh(pos, tri, normals=nrm, material=m))
    lt = w.light(type="point", intensity=30.0)
    w.node(translation=[1.0, 2.0, 0.5], extensions={"KHR_lights_punctual": {"light": lt}})
    w.save(tmp_path / "floor.glb")
    toml = tmp_path / "s.toml"
    toml.write_text(
        '[camera]\nposition = [0.0, 3.0, 4.0]\ntarget = [0.0, 0.0, 0.0]\nwidth = 24\nheight = 16\n'
        '[[objects]]\ntype = "gltf"\npath = "floor.glb"\n'
        '[[objects]]\ntype = "sphere"\ncenter = [0.0, 0.5, 0.0]\nradius = 0.5\n'
    )
    sf = load_scene(toml)
    assert len(sf.scene.objects) == 2 and len(sf.scene.lights) == 1
    built = load_gltf(tmp_path / "floor.glb", camera=sf.scene.camera)
    ref = jp.Scene(camera=sf.scene.camera, objects=[*built.objects, jp.Sphere(center=(0, 0.5, 0), radius=0.5)], lights=built.lights)
    np.testing.assert_allclose(np.asarray(jp.render(sf.scene)), np.asarray(jp.render(ref)), rtol=1e-6, atol=1e-7)
    toml.write_text('[camera]\nposition = [0.0, 3.0, 4.0]\n[[objects]]\ntype = "gltf"\npath = "nope.glb"\n')
    with pytest.raises(InputError, match=r"objects\[0\]\.path"):
        load_scene(toml)


@pytest.mark.parametrize("tilt", [(0.5, 0.0), (0.0, 0.5)], ids=["x", "y"])
def test_normal_map_without_tangents_uses_mikktspace_frame(tmp_path, tilt):
    """A floor quad with a constant normal map and no TANGENT: the loader generates MikkTSpace
    tangents and the shading normal is T x + B y + N z with T = dP/du = +X and, since v grows
    along +Z here and a normal map's +Y points up the image (decreasing v), B = -Z. The oracle is
    the same floor without a map, its vertex normals set to that normal."""
    x, y = tilt
    z = math.sqrt(1 - x * x - y * y)
    code = np.round((np.array([x, y, z]) + 1) / 2 * 255) / 255  # what the 8-bit PNG stores
    nt = 2 * code - 1
    w = Writer()
    tex = w.image_png(np.broadcast_to(code, (4, 4, 3)).copy())
    m = w.material(normalTexture={"index": tex}, pbrMetallicRoughness={"baseColorFactor": [0.8, 0.8, 0.8, 1], "metallicFactor": 0.0, "roughnessFactor": 0.4})
    pos, tri, _, nrm = _quad(size=4.0)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)  # u along +X, v along +Z
    w.node(mesh=w.mesh(pos, tri, normals=nrm, uv=uv, material=m))
    path = w.save(tmp_path / "bumpy.glb")
    light = jp.PointLight((1.0, 2.0, 1.5), intensity=10.0)
    cam = _camera(32, 24, pos=(0.2, 3.0, 2.5))
    img = np.asarray(jp.render(load_gltf(path, camera=cam, lights=[light])))
    n_world = np.array([nt[0], nt[2], -nt[1]])  # T = +X, N = +Y, B = -Z
    n_world = (n_world / np.linalg.norm(n_world)).astype(np.float32)
    mat = jp.Material(base_color=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.4)
    ref_mesh = Mesh(positions=pos, triangles=tri, normals=np.tile(n_world, (4, 1)), material=mat)
    ref = np.asarray(jp.render(jp.Scene(camera=cam, objects=[ref_mesh], lights=[light])))
    covered = ref.sum(-1) > 0
    assert covered.sum() > 300
    np.testing.assert_allclose(img[covered], ref[covered], rtol=2e-4, atol=1e-6)


@pytest.mark.slow
def test_gradients_reach_texels_and_environment_texels():
    """d image / d (a base-colour texel of a mip-mapped slot, an environment texel): finite and equal
    to central differences (float64)."""
    P, N, UV, T = uv_sphere(12, 24)
    cam = _camera(16, 16, pos=(0.0, 0.3, 3.5))
    tex0 = np.full((8, 8, 3), 0.5)
    env0 = np.asarray(jp.envs.sky_with_sun_cubemap(8).levels[0], np.float64)

    def loss(tex, env_level):
        slot = jp.TextureSlot(texture=jp.Texture.from_image(tex, srgb=False))
        tm = jp.TexturedMaterial(factors=jp.Material(metallic=0.0, roughness=0.6), base_color_texture=slot)
        mesh = Mesh(positions=P, triangles=T, normals=N, texcoords=UV, material=tm)
        env = jp.Environment(radiance=jp.Cubemap(env_level), show_background=False)
        scene = jp.Scene(camera=cam, objects=[mesh], environment=env)
        return jnp.sum(jp.render(scene, dtype="float64", extract_lights=False, prefilter_samples=64))

    g_tex, g_env = jax.grad(loss, argnums=(0, 1))(jnp.asarray(tex0), jnp.asarray(env0))
    assert np.all(np.isfinite(np.asarray(g_tex))) and np.all(np.isfinite(np.asarray(g_env)))
    h = 1e-4
    for idx in [(3, 2, 0), (6, 5, 1)]:  # texels on the visible side
        e = np.zeros_like(tex0)
        e[idx] = h
        fd = (loss(jnp.asarray(tex0 + e), jnp.asarray(env0)) - loss(jnp.asarray(tex0 - e), jnp.asarray(env0))) / (2 * h)
        np.testing.assert_allclose(float(g_tex[idx]), float(fd), rtol=1e-5, atol=1e-9)
    k = np.unravel_index(np.argmax(np.abs(np.asarray(g_env))), env0.shape)
    e = np.zeros_like(env0)
    e[k] = h
    fd = (loss(jnp.asarray(tex0), jnp.asarray(env0 + e)) - loss(jnp.asarray(tex0), jnp.asarray(env0 - e))) / (2 * h)
    np.testing.assert_allclose(float(g_env[k]), float(fd), rtol=1e-5)
    assert abs(float(g_env[k])) > 0


def test_gradient_of_a_texel_under_a_light_matches_central_differences():
    """The fast companion of the slow test above: a base-colour texel of a mip-mapped slot on a
    mesh under a directional light (float64)."""
    P, N, UV, T = uv_sphere(12, 24)
    cam = _camera(16, 16, pos=(0.0, 0.3, 3.5))
    tex0 = np.full((8, 8, 3), 0.5)

    def loss(tex):
        slot = jp.TextureSlot(texture=jp.Texture.from_image(tex, srgb=True))
        tm = jp.TexturedMaterial(factors=jp.Material(metallic=0.0, roughness=0.6), base_color_texture=slot)
        mesh = Mesh(positions=P, triangles=T, normals=N, texcoords=UV, material=tm)
        return jnp.sum(jp.render(jp.Scene(camera=cam, objects=[mesh], lights=[SUN]), dtype="float64"))

    g = np.asarray(jax.grad(loss)(jnp.asarray(tex0)))
    assert np.all(np.isfinite(g))
    idx = np.unravel_index(np.argmax(np.abs(g)), g.shape)
    h = 1e-5
    e = np.zeros_like(tex0)
    e[idx] = h
    fd = (loss(jnp.asarray(tex0 + e)) - loss(jnp.asarray(tex0 - e))) / (2 * h)
    np.testing.assert_allclose(g[idx], float(fd), rtol=1e-5)


def test_memory_guard_counts_the_meshes(monkeypatch):
    """check_memory (what render runs first) refuses a mesh scene too large for the limit, naming the
    triangle count, before any work."""
    from jaxpbr.rendering.renderer import check_memory

    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "1")
    P = np.zeros((3_000_000, 3), np.float32)
    P[:, 0] = np.arange(3_000_000)
    P[1::3, 1] = 1.0
    T = np.arange(3_000_000, dtype=np.int32).reshape(-1, 3)
    scene = jp.Scene(camera=jp.Camera(width=64, height=36), objects=[Mesh(positions=P, triangles=T)])
    with pytest.raises(ValueError, match="the meshes' triangle count"):
        check_memory(scene)
    small = jp.Scene(camera=jp.Camera(width=64, height=36), objects=[Mesh(positions=P[:3], triangles=T[:1])])
    check_memory(small)


def test_concurrent_requests_for_one_content_build_it_once(monkeypatch):
    """Primary and shadow casts (and batch workers) may ask for a structure at the same time: the
    later callers wait for the first one's build instead of building it again."""
    import threading
    import time

    from jaxpbr.rendering import visibility
    from jaxpbr.rendering.mesh import _Accels

    real = visibility.TriangleAccel.build.__func__

    def slow_build(cls, *a, **k):  # a build long enough for every caller to arrive meanwhile
        time.sleep(0.3)
        return real(cls, *a, **k)

    monkeypatch.setattr(visibility.TriangleAccel, "build", classmethod(slow_build))

    P, _, _, T = uv_sphere(24, 48)
    verts, tris = np.ascontiguousarray(P, np.float32), np.ascontiguousarray(T, np.int32)
    accels = _Accels()
    start = threading.Barrier(4)
    got = []

    def ask():
        start.wait()
        got.append(accels.get(verts, tris, "jax"))

    threads = [threading.Thread(target=ask) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert accels.builds == 1 and len(got) == 4 and all(a is got[0] for a in got)
    assert not accels.building


def test_a_staged_mesh_render_calls_the_ray_engine_without_callback_programs(monkeypatch):
    """Outside transformations the primary and shadow rays go to the host ray engine between stored
    stages: no `jax.pure_callback` is traced (its program could not be kept across processes)."""
    light = jp.DirectionalLight(direction=(-0.5, -1.0, -0.3), intensity=3.0)
    scene, _ = _shadow_scene(False, light)
    callbacks = []
    real = jax.pure_callback
    monkeypatch.setattr(jax, "pure_callback", lambda *a, **k: callbacks.append(1) or real(*a, **k))
    img = np.asarray(jp.render(scene, shadows=True))
    assert not callbacks and np.isfinite(img).all() and (img == 0.0).any()  # the shadow is black


def test_a_staged_mesh_render_makes_the_ray_engine_s_arrays_once_per_scene(monkeypatch):
    """The meshes' arrays the host ray engine reads (concatenated positions, triangles, culling) are
    made by a program once per mesh content and kept on the host: a second frame and each light's
    shadow rays reuse them, and their content is hashed once. New positions make them again, and
    the frame follows the new geometry."""
    from jaxpbr.rendering.execution import EXECUTION

    monkeypatch.setattr(EXECUTION, "staged", True)  # (XLA:CPU's default; a GPU renders as one program)
    light = jp.DirectionalLight(direction=(-0.5, -1.0, -0.3), intensity=3.0)
    scene, _ = _shadow_scene(False, light)
    made, hashed = [], []
    real_make, real_opaque, real_digest = stages._host_arrays_jit, stages._host_arrays_opaque, mesh_mod._content_digest
    monkeypatch.setattr(stages, "_host_arrays_jit", lambda *a: made.append(1) or real_make(*a))
    monkeypatch.setattr(stages, "_host_arrays_opaque", lambda *a: made.append(1) or real_opaque(*a))
    monkeypatch.setattr(mesh_mod, "_content_digest", lambda x: hashed.append(id(x)) or real_digest(x))
    real_range = mesh_mod._range_digest  # (each mesh's range of them: `mesh.part_keys`)
    monkeypatch.setattr(mesh_mod, "_range_digest", lambda x, a, b: hashed.append(id(x)) or real_range(x, a, b))
    stages._HOST_ARRAYS.clear()
    first = np.asarray(jp.render(scene, shadows=True))
    assert len(made) == 1
    digests = len(hashed)
    again = np.asarray(jp.render(scene, shadows=True))
    # The engine is asked with the same two array objects (positions, triangles) for every cast of
    # both frames, so their digests (and their meshes' ranges') are remembered (`_numerics.remember_per_array`).
    assert len(made) == 1 and len(hashed) == 2 * digests and len(set(hashed)) == 2
    np.testing.assert_array_equal(first, again)
    meshes = [ob for ob in scene.objects if isinstance(ob, Mesh)]
    k = scene.objects.index(meshes[-1])
    moved = meshes[-1].replace(positions=np.asarray(meshes[-1].positions) + np.float32([0.0, 0.0, 0.25]))
    objs = list(scene.objects)
    objs[k] = moved
    shifted = np.asarray(jp.render(scene.replace(objects=objs), shadows=True))
    assert len(made) == 2 and not np.array_equal(shifted, first)


def test_the_opaque_meshes_host_arrays_in_numpy_equal_the_program_s():
    """Opaque meshes without transmission: the ray engine's arrays are concatenated in NumPy (no
    program); they equal `_host_arrays`' (positions, offset triangles, back-face culling)."""
    light = jp.DirectionalLight(direction=(-0.5, -1.0, -0.3), intensity=3.0)
    scene, _ = _shadow_scene(False, light)
    meshes = [ob for ob in scene.objects if isinstance(ob, Mesh)]
    meshes = tuple(meshes + [meshes[0].replace(double_sided=not meshes[0].double_sided)])
    assert len(meshes) >= 2 and len({m.double_sided for m in meshes}) == 2
    for dtype in ("float32", "float64"):
        with jax.enable_x64(dtype == "float64"):
            ref = stages._host_arrays(meshes, dtype)
        got = stages._host_arrays_opaque(meshes)
        assert got["alpha"] is None and ref["alpha"] is None and got["transmit"] is None and ref["transmit"] is None
        for k in ("positions", "triangles", "cull_back"):
            # read-only: the ray engine's caches remember their content digests per array object
            assert got[k].dtype == np.asarray(ref[k]).dtype and not got[k].flags.writeable, k
            np.testing.assert_array_equal(got[k], np.asarray(ref[k]))


def test_shadow_rays_are_cast_under_grad_of_the_vertices():
    """Under a JVP (grad) with respect to a mesh's vertices the shadow segments are free of
    gradients (and so concrete) while the vertices are traced: the shadow rays still reach the
    meshes (through the callback) and give the eager visibility. Ground points under a ball lit
    from above, some in its shadow."""
    light = jp.DirectionalLight(direction=(0.0, -1.0, 0.0), intensity=3.0)
    scene, _ = _shadow_scene(False, light)
    ground, ball = scene.objects
    x, z = np.meshgrid(np.linspace(-1.0, 1.0, 9), np.linspace(-1.0, 1.0, 9))
    pos = (jnp.asarray(x, jnp.float32), jnp.zeros(x.shape, jnp.float32), jnp.asarray(z, jnp.float32))
    ng = tuple(jnp.full(x.shape, c, jnp.float32) for c in (0.0, 1.0, 0.0))
    opts = R.RenderOptions(dtype="float32")

    def visibility(dy):
        moved = ball.replace(positions=jnp.asarray(ball.positions) + dy * jnp.asarray([0.0, 1.0, 0.0], jnp.float32))
        return stages._staged_shadows(stages._light_segments_jit, scene.replace(objects=[ground, moved]), opts, pos, ng)

    eager = np.asarray(visibility(0.0))
    under_jvp, _ = jax.jvp(visibility, (0.0,), (1.0,))
    shadowed = (np.hypot(x, z) < 0.45)[..., None]  # (the ball's radius is 0.5 over the origin)
    assert eager.shape == x.shape + (1,) and (eager[shadowed] == 0).all() and (eager[np.hypot(x, z) > 0.55] == 1).all()
    np.testing.assert_array_equal(np.asarray(under_jvp), eager)


@pytest.mark.slow  # compiles the whole render as one traced program: ~30 s
def test_staged_render_calls_the_ray_engine_directly_and_matches_the_callback_path(monkeypatch):
    """A render outside transformations casts its primary and shadow rays by calling the host ray
    engine between stored stages (no program holding a callback); under jit the same rays go
    through `jax.pure_callback` in the trace. Both give the same image: opaque, cut-out, blended
    and transmissive meshes, a point light and the sun split out of the sky."""
    env = jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(16))
    occluders = [_glass_quad(_GLASS, y=1.0), _wall(-0.5, size=1.0, material=_GREEN, alpha_mode="MASK", alpha=0.2),
                 _wall(-1.0, size=1.0, material=_GREEN, alpha_mode="BLEND", alpha=0.5),
                 Mesh(*(lambda P, N, UV, T: (P + np.float32([0.6, 0.5, 0.3]), T))(*uv_sphere(12, 24, radius=0.3)),
                      material=jp.Material(base_color=(0.8, 0.3, 0.3), roughness=0.5))]
    floor = Mesh(positions=np.array([[-3, 0, 3], [3, 0, 3], [3, 0, -3], [-3, 0, -3]], np.float32),
                 triangles=np.array([[0, 1, 2], [0, 2, 3]], np.int32), material=_FLOOR_MAT)
    cam = jp.Camera(position=(0.0, 2.5, 3.2), target=(0.0, 0.3, 0.0), fov_y_deg=50.0, width=32, height=24)
    scene = jp.Scene(camera=cam, objects=[floor, *occluders], lights=[jp.PointLight(tuple(_LAMP), intensity=_LAMP_CD)],
                     environment=env)
    assert R.plan(scene).shadows and R.plan(scene).env_lights >= 1 and R.plan(scene).blend_layers > 1
    callbacks = []
    real = jax.pure_callback
    monkeypatch.setattr(jax, "pure_callback", lambda *a, **k: callbacks.append(1) or real(*a, **k))
    direct = np.asarray(jp.render(scene))
    assert not callbacks  # the host engine was called directly
    # Under jit with the floor's vertices traced (the environment stays concrete: its sun is split
    # out as in the direct render), the casts go through the callback.
    traced = np.asarray(jax.jit(lambda p: jp.render(scene.replace(objects=[floor.replace(positions=p), *occluders])))(floor.positions))
    assert callbacks
    assert np.isfinite(direct).all() and direct.max() > 0
    np.testing.assert_allclose(direct, traced, rtol=2e-5, atol=1e-6)


def test_host_shadow_hits_trace_only_the_masked_points():
    """`shadows.host_mesh_hits` with a mask (the pixels that hit a surface) gives the unmasked
    answer there and "not blocked" elsewhere, for a direction shared by every ray and per ray."""
    from jaxpbr.rendering.shadows import host_mesh_hits

    quad = {"positions": np.array([[-1, 1, -1], [1, 1, -1], [1, 1, 1], [-1, 1, 1]], np.float32),
            "triangles": np.array([[0, 1, 2], [0, 2, 3]], np.int32), "alpha": None, "transmit": None}
    o = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.2], [3.0, 0.0, 0.0], [-0.3, 0.0, 0.4]], np.float32).reshape(2, 2, 3)
    tfar = np.full((2, 2), 1e30, np.float32)
    mask = np.array([[True, False], [True, True]])
    for d in (np.float32([0, 1, 0]), np.broadcast_to(np.float32([0, 1, 0]), (2, 2, 3))):
        part = [{"o32": o, "l": d, "tfar": tfar}]
        (full,) = host_mesh_hits(quad, part)
        (masked,) = host_mesh_hits(quad, part, mask)
        assert full.tolist() == [[True, True], [False, True]]
        np.testing.assert_array_equal(masked, np.where(mask, full, False))


def test_shadow_rays_of_points_facing_away_from_a_light_are_not_traced(monkeypatch):
    """Where the shading normal faces away from a light (beyond a disc's radius) a material without
    transmission or clear coat gets exactly 0 from it, so the meshes' shadow rays from there are
    left out: fewer rays go to the ray engine, for the point light and the sun split out of the sky,
    and the image is equal bit for bit to the one with every ray traced."""
    from jaxpbr.rendering import shadows

    P, N, _, T = uv_sphere(12, 24, radius=0.6)
    ball = Mesh(positions=P + np.float32([0.0, 0.6, 0.0]), normals=N, triangles=T,
                material=jp.Material(base_color=(0.8, 0.3, 0.3), roughness=0.5))
    floor = Mesh(positions=np.array([[-3, 0, 3], [3, 0, 3], [3, 0, -3], [-3, 0, -3]], np.float32),
                 triangles=np.array([[0, 1, 2], [0, 2, 3]], np.int32), material=_FLOOR_MAT)
    scene = jp.Scene(camera=jp.Camera(position=(0.0, 1.5, 3.0), target=(0.0, 0.4, 0.0), fov_y_deg=45.0, width=32, height=24),
                     objects=[floor, ball], lights=[jp.PointLight((2.5, 1.0, 0.5), intensity=30.0)],
                     environment=jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(16)))
    assert R.plan(scene).shadows and R.plan(scene).env_lights == 1 and R.plan(scene).extensions == ("specular",)
    traced = []
    real_occluded = shadows._host_occluded
    monkeypatch.setattr(shadows, "_host_occluded", lambda v, t, o, *a, **k: traced.append(len(o)) or real_occluded(v, t, o, *a, **k))
    culled = np.asarray(jp.render(scene))
    few = traced[:]
    real_hits = stages.host_mesh_hits
    monkeypatch.setattr(stages, "host_mesh_hits", lambda arrays, parts, mask=None: real_hits(
        arrays, [{k: x for k, x in p.items() if k != "trace"} for p in parts], mask))
    traced.clear()
    every = np.asarray(jp.render(scene))
    assert len(few) == len(traced) == 2  # the point light's rays, then the sun's
    assert all(a < 0.9 * b for a, b in zip(few, traced, strict=True)), (few, traced)
    assert np.isfinite(culled).all() and culled.max() > 0
    np.testing.assert_array_equal(culled, every)
    # A transmissive or clear-coated material lets light in from below its horizon: no ray is left out.
    assert stages._culls_facing(R.plan(scene))
    for ext in ({"transmission": 0.5}, {"clearcoat": 1.0}):
        other = scene.replace(objects=[floor, ball.replace(material=jp.Material(base_color=(0.8, 0.3, 0.3), roughness=0.5, **ext))])
        assert not stages._culls_facing(R.plan(other))
