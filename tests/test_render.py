"""Scene layer: geometry, textures, golden pixels, composition (plan + cache), batches, errors."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as ref

import jaxpbr as jp
from jaxpbr.rendering import renderer as R
from jaxpbr.rendering import stages as stages_
from jaxpbr.rendering.assets import ibl_assets
from jaxpbr.rendering.plan import split_environment
from jaxpbr.rendering.demo import learnopengl_scene, sphere_grid
from jaxpbr.rendering.scene import (
    intersect_plane,
    intersect_sphere,
    primary_rays,
    sample_texture,
)

W, H = 65, 37  # odd: the centre pixel's ray is exactly the camera axis

LIGHTS4 = [(-10.0, 10.0, 10.0), (10.0, 10.0, 10.0), (-10.0, -10.0, 10.0), (10.0, -10.0, 10.0)]


def small_env(S=16):
    return jp.envs.sky_with_sun_cubemap(S)


# ------------------------------------------------------------------------------------------
# Geometry
# ------------------------------------------------------------------------------------------


def test_primary_rays_centre_and_corners():
    cam = jp.Camera(width=W, height=H, fov_y_deg=60.0)
    o, d = primary_rays(cam, dtype=jnp.float64)
    d = np.asarray(d)
    np.testing.assert_allclose(d[H // 2, W // 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    # Top edge of the image plane: pixel centre row 0 sits at y = (1 - 1/H) tan(30 deg).
    t = math.tan(math.radians(30))
    top = d[0, W // 2]
    np.testing.assert_allclose(top[1] / -top[2], (1 - 1 / H) * t, rtol=1e-12)
    right = d[H // 2, -1]
    np.testing.assert_allclose(right[0] / -right[2], (1 - 1 / W) * t * W / H, rtol=1e-12)


def test_orthographic_primary_rays_are_parallel_over_the_ymag_view():
    """Orthographic: every ray has the viewing direction; pixel (i, j) starts at position +
    x right + y up, x = (2 (j + 1/2)/W - 1) ymag W/H, y = (1 - 2 (i + 1/2)/H) ymag, so the pixel
    centres span the view's 2 ymag (W/H) x 2 ymag less half a pixel at each edge; the jitter and
    a band of rows move the origins as they move a perspective camera's image-plane points."""
    pos = np.array([1.0, 2.0, 3.0])
    cam = jp.Camera(position=tuple(pos), target=(1.0, 2.0, -7.0), projection="orthographic", ymag=1.5, width=W, height=H)
    rays = jax.jit(lambda c: primary_rays(c, dtype=jnp.float64))
    o, d = (np.asarray(x) for x in rays(cam))
    np.testing.assert_allclose(d, np.broadcast_to([0.0, 0.0, -1.0], d.shape), atol=0)
    x = (2 * (np.arange(W) + 0.5) / W - 1) * 1.5 * W / H
    y = (1 - 2 * (np.arange(H) + 0.5) / H) * 1.5
    want = np.stack(np.broadcast_arrays(pos[0] + x[None, :], pos[1] + y[:, None], pos[2] + 0 * x[None, :]), -1)
    np.testing.assert_allclose(o, want, rtol=0, atol=1e-12)
    jit = cam.replace(jitter=(0.25, -0.5))
    oj, _ = rays(jit)
    np.testing.assert_allclose(np.asarray(oj) - o, np.broadcast_to([0.25 * 3.0 / H, 0.5 * 3.0 / H, 0.0], o.shape), atol=1e-12)
    ob, _ = jax.jit(lambda c: primary_rays(c, dtype=jnp.float64, offset=(0.5, 0.5, 3), rows=4))(cam)
    np.testing.assert_allclose(np.asarray(ob), o[3:7], atol=1e-12)


def test_orthographic_camera_validation():
    with pytest.raises(ValueError, match="projection must be one of perspective, orthographic"):
        jp.Camera(projection="fisheye")
    with pytest.raises(ValueError, match="Camera.ymag"):
        jp.Camera(projection="orthographic", ymag=0.0)


def test_an_orthographic_sphere_is_a_disc_of_its_radius_with_the_closed_form_depth():
    """A unit sphere seen orthographically: exactly the pixels whose centre lies within 1 of its
    axis are hit (centres within 1e-4 of the rim left out), at depth D - sqrt(1 - rho^2)."""
    from jaxpbr.rendering.aovs import aovs

    D, ymag, n = 5.0, 1.25, 40
    cam = jp.Camera(position=(0.0, 0.0, D), target=(0.0, 0.0, 0.0), projection="orthographic", ymag=ymag, width=n, height=n)
    scene = jp.Scene(camera=cam, objects=[jp.Sphere(center=(0.0, 0.0, 0.0), radius=1.0, material=jp.Material())])
    got = aovs(scene, ("mask", "depth"))
    c = (2 * (np.arange(n) + 0.5) / n - 1) * ymag
    rho = np.hypot(c[None, :], c[:, None])
    sure = np.abs(rho - 1.0) > 1e-4
    np.testing.assert_array_equal(got["mask"][sure] > 0, (rho < 1.0)[sure])
    inside = rho < 1.0 - 1e-4
    np.testing.assert_allclose(got["depth"][inside], D - np.sqrt(1.0 - rho[inside] ** 2), rtol=1e-5)


def test_sphere_and_plane_intersection_against_float64_numpy():
    rng = np.random.default_rng(0)
    o = rng.normal(size=(500, 3)) * 3
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    c, rad = np.array([0.3, -0.2, 0.5]), 1.7
    t, ok = intersect_sphere(tuple(o.T), tuple(d.T), tuple(c), rad)
    # Independent: solve |o + t d - c|^2 = R^2 with numpy roots, smallest positive root.
    for k in range(500):
        b = 2 * d[k].dot(o[k] - c)
        cc = (o[k] - c).dot(o[k] - c) - rad * rad
        disc = b * b - 4 * cc
        if disc <= 0:
            assert not ok[k]
            continue
        roots = sorted([(-b - math.sqrt(disc)) / 2, (-b + math.sqrt(disc)) / 2])
        pos = [r for r in roots if r > 0]
        assert bool(ok[k]) == bool(pos)
        if pos:
            assert abs(float(t[k]) - pos[0]) <= 1e-12 * max(1.0, pos[0])
    n = np.array([0.2, 1.0, -0.3])
    p0 = np.array([0.0, -1.0, 0.0])
    t, ok = intersect_plane(tuple(o.T), tuple(d.T), tuple(p0), tuple(n))
    tt = (p0 - o).dot(n) / d.dot(n)
    np.testing.assert_array_equal(np.asarray(ok), tt > 0)
    np.testing.assert_allclose(np.asarray(t)[tt > 0], tt[tt > 0], rtol=1e-12)


def test_sample_texture_bilinear_repeat_against_numpy():
    rng = np.random.default_rng(1)
    tex = rng.uniform(size=(5, 7, 3))
    u = rng.uniform(-1.5, 2.5, 200)
    v = rng.uniform(-1.5, 2.5, 200)
    got = np.asarray(sample_texture(jnp.asarray(tex), jnp.asarray(u), jnp.asarray(v)))
    Ht, Wt = tex.shape[:2]
    for k in range(200):
        x, y = u[k] * Wt - 0.5, v[k] * Ht - 0.5
        x0, y0 = math.floor(x), math.floor(y)
        fx, fy = x - x0, y - y0
        acc = 0
        for dy, wy in ((0, 1 - fy), (1, fy)):
            for dx, wx in ((0, 1 - fx), (1, fx)):
                acc = acc + wx * wy * tex[(y0 + dy) % Ht, (x0 + dx) % Wt]
        np.testing.assert_allclose(got[k], acc, atol=1e-12)
    # Texel centres return the texel exactly.
    np.testing.assert_allclose(
        np.asarray(sample_texture(jnp.asarray(tex), jnp.asarray(4.5 / 7), jnp.asarray(2.5 / 5))), tex[2, 4], atol=1e-14
    )


# ------------------------------------------------------------------------------------------
# Golden pixels (independent float64 shading)
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def lo_scene_img():
    return np.asarray(jp.render(learnopengl_scene(W, H)))


def test_learnopengl_scene_centre_pixel_matches_independent_shading(lo_scene_img):
    """Centre ray -Z hits the middle sphere (row 3, col 3) at p = (0, 0, 1), n = v = +Z. Shaded
    independently (tests/reference.py glTF BRDF, 4 lights of 300 with 1/d^2, 0.03 ambient).

    Tolerance: float32 pipeline (ray-sphere hit, normal, BRDF, 4 lights): a few ulps (6e-8) times
    the BRDF's condition number (< 100 here) -> rtol 2e-5."""
    img = lo_scene_img
    assert img.shape == (H, W, 3) and img.dtype == np.float32 and np.isfinite(img).all()
    p = np.array([0.0, 0.0, 1.0])
    n = v = np.array([0.0, 0.0, 1.0])
    albedo, metallic, rough = np.array([0.5, 0.0, 0.0]), 3 / 7, 3 / 7
    expected = 0.03 * albedo
    for pos in LIGHTS4:
        d = np.array(pos) - p
        l = d / np.linalg.norm(d)
        expected = expected + ref.gltf_material(n, v, l, albedo, metallic, rough) * 300.0 / d.dot(d) * n.dot(l)
    np.testing.assert_allclose(img[H // 2, W // 2], expected, rtol=2e-5, atol=1e-7)


def test_learnopengl_scene_every_sphere_visible_and_background_black(lo_scene_img):
    img = lo_scene_img
    t = math.tan(math.radians(45.0) / 2)
    for sph in learnopengl_scene(W, H).objects:
        c = np.asarray(sph.center)
        z = 24.0 - c[2]
        j = int((c[0] / (z * t * W / H) + 1) / 2 * W)
        i = int((1 - c[1] / (z * t)) / 2 * H)
        assert img[i, j].sum() > 0
    assert (img[0, 0] == 0).all() and (img[-1, -1] == 0).all()


def test_off_centre_pixel_matches_float64_reference_raycast():
    """Any hit pixel: the float32 render equals an independent float64 ray cast + shading."""
    scene = jp.Scene(
        camera=jp.Camera(position=(0.5, 1.0, 6.0), target=(0.0, 0.0, 0.0), width=31, height=23, fov_y_deg=40.0),
        objects=[jp.Sphere(center=(0.2, -0.1, 0.0), radius=1.3, material=jp.Material((0.8, 0.3, 0.2), 0.3, 0.4))],
        lights=[jp.PointLight(position=(3.0, 4.0, 5.0), intensity=80.0), jp.DirectionalLight(direction=(0.0, -1.0, -1.0), intensity=2.0)],
    )
    img = np.asarray(jp.render(scene, antialias=False))  # (the reference casts the pixel centre)
    with jax.enable_x64(True):
        o, d = primary_rays(scene.camera, dtype=jnp.float64)
    o, d = np.asarray(o), np.asarray(d)
    c, rad = np.array([0.2, -0.1, 0.0]), 1.3
    checked = 0
    for i in range(0, 23, 3):
        for j in range(0, 31, 3):
            oc = o[i, j] - c
            b = oc.dot(d[i, j])
            disc = b * b - (oc.dot(oc) - rad * rad)
            if disc <= 1e-3:  # skip silhouettes (hit/miss flips at float32 rounding)
                if disc < -1e-3:
                    assert (img[i, j] == 0).all()
                continue
            tt = -b - math.sqrt(disc)
            p = o[i, j] + tt * d[i, j]
            n = (p - c) / rad
            v = -d[i, j]
            expected = np.zeros(3)
            lp = np.array([3.0, 4.0, 5.0]) - p
            l = lp / np.linalg.norm(lp)
            if n.dot(l) > 0 and n.dot(v) > 0:
                expected += ref.gltf_material(n, v, l, np.array([0.8, 0.3, 0.2]), 0.3, 0.4) * 80.0 / lp.dot(lp) * n.dot(l)
            l2 = -np.array([0.0, -1.0, -1.0]) / math.sqrt(2)
            if n.dot(l2) > 0 and n.dot(v) > 0:
                expected += ref.gltf_material(n, v, l2, np.array([0.8, 0.3, 0.2]), 0.3, 0.4) * 2.0 * n.dot(l2)
            # float32 ray cast: the hit point carries ~|p| eps = 4e-7 relative error, amplified by
            # d(shading)/dp (lights within a few units): rtol 1e-4.
            np.testing.assert_allclose(img[i, j], expected, rtol=1e-4, atol=1e-6)
            checked += 1
    assert checked > 10


# ------------------------------------------------------------------------------------------
# Textures and planes
# ------------------------------------------------------------------------------------------


def test_textured_plane_seen_head_on_reproduces_the_texture():
    """An emissive-only textured plane facing the camera, viewed orthogonally-ish: the pixel at
    a texel centre's world position returns factor x texel (no lights, no environment)."""
    rng = np.random.default_rng(2)
    tex = rng.uniform(size=(4, 4, 3))
    mat = jp.TexturedMaterial(
        factors=jp.Material(base_color=(0, 0, 0), metallic=0.0, roughness=1.0, emissive=(2.0, 2.0, 2.0)),
        emissive_texture=tex,
    )
    plane = jp.Plane(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), tangent=(1.0, 0.0, 0.0), uv_scale=0.25, material=mat)
    # Camera at z = 10 looking at the origin; pixel centre rays hit the plane at x = 10 tan * ...
    cam = jp.Camera(position=(0.0, 0.0, 10.0), width=40, height=40, fov_y_deg=2 * math.degrees(math.atan(0.8)))
    img = np.asarray(jp.render(jp.Scene(camera=cam, objects=[plane])))
    # Half-width of the view at the plane: 10 * 0.8 = 8 units -> 40 px: 0.4 units per pixel.
    # uv = (x, -y) * 0.25; texel (i, j) centre at u = (j + 0.5)/4 -> x = j + 0.5, y = -(i + 0.5).
    for i in range(4):
        for j in range(4):
            x, y = j + 0.5, -(i + 0.5)
            px = int(round(x / 0.4 + 20 - 0.5))
            py = int(round(-y / 0.4 + 20 - 0.5))
            # pixel centre sits 0.2 units off the texel centre at most -> compare at the exact spot
            xc, yc = (px + 0.5 - 20) * 0.4, -(py + 0.5 - 20) * 0.4
            u, v = xc * 0.25, -yc * 0.25
            expect = 2.0 * np.asarray(sample_texture(jnp.asarray(tex), jnp.asarray(u), jnp.asarray(v)))
            np.testing.assert_allclose(img[py, px], expect, rtol=1e-5)


def test_flat_normal_map_equals_untextured_and_tilted_map_changes_shading():
    base = jp.Material(base_color=(0.7, 0.7, 0.7), metallic=0.0, roughness=0.5)
    flat = np.broadcast_to(np.array([0.5, 0.5, 1.0]), (4, 4, 3)).copy()
    lights = [jp.DirectionalLight(direction=(-0.3, -0.2, -1.0), intensity=3.0)]
    cam = jp.Camera(position=(0.0, 0.0, 5.0), width=24, height=24)

    def img(mat):
        return np.asarray(jp.render(jp.Scene(camera=cam, objects=[jp.Sphere(material=mat)], lights=lights)))

    a = img(base)
    b = img(jp.TexturedMaterial(factors=base, normal_texture=flat))
    np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-7)
    tilted = np.broadcast_to(np.array([0.8, 0.5, 0.9]), (4, 4, 3)).copy()
    c = img(jp.TexturedMaterial(factors=base, normal_texture=tilted))
    assert np.abs(c - a).max() > 1e-2 and np.isfinite(c).all()


def test_orm_texture_multiplies_factors():
    """A constant ORM texture (R occlusion, G roughness, B metallic) equals the constant material
    with the products of factor and texel."""
    orm = np.broadcast_to(np.array([0.5, 0.6, 0.25]), (3, 3, 3)).copy()
    fac = jp.Material(base_color=(0.9, 0.5, 0.3), metallic=0.8, roughness=0.5, occlusion=1.0)
    const = jp.Material(base_color=(0.9, 0.5, 0.3), metallic=0.2, roughness=0.3, occlusion=0.5)
    env = jp.Environment(radiance=small_env())
    cam = jp.Camera(position=(0.0, 0.0, 5.0), width=20, height=20)
    lights = [jp.PointLight(position=(2.0, 3.0, 4.0), intensity=30.0)]
    tm = jp.TexturedMaterial(factors=fac, metallic_roughness_texture=orm, occlusion_texture=orm)
    a = np.asarray(jp.render(jp.Scene(camera=cam, objects=[jp.Sphere(material=tm)], lights=lights, environment=env)))
    b = np.asarray(jp.render(jp.Scene(camera=cam, objects=[jp.Sphere(material=const)], lights=lights, environment=env)))
    np.testing.assert_allclose(a, b, rtol=2e-6, atol=1e-7)


# ------------------------------------------------------------------------------------------
# G-buffer path, supersampling
# ------------------------------------------------------------------------------------------


def test_gbuffer_scene_equals_direct_kernels():
    rng = np.random.default_rng(3)
    Hh, Ww = 6, 5
    n = rng.normal(size=(Hh, Ww, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    v = rng.normal(size=(Hh, Ww, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    p = rng.normal(size=(Hh, Ww, 3))
    m = jp.Material(
        base_color=rng.uniform(size=(Hh, Ww, 3)), metallic=rng.uniform(size=(Hh, Ww)), roughness=rng.uniform(size=(Hh, Ww))
    )
    hit = rng.uniform(size=(Hh, Ww)) > 0.2
    g = jp.GBuffer(hit=hit, position=p, normal=n, view=v, material=m)
    env = small_env()
    lights = [jp.PointLight(position=(2.0, 3.0, 4.0), intensity=30.0)]
    img = np.asarray(jp.render(jp.Scene(gbuffer=g, lights=lights, environment=jp.Environment(radiance=env)), extract_lights=False))
    irr = jp.irradiance(env, size=32)
    pre = jp.prefilter(env)
    lut = jp.brdf_lut(size=128)
    # Jitted (one program each instead of ~200 eager primitive compilations).
    # render's default for glTF: the multiple-scattering compensation of the IBL term.
    kernels = jax.jit(lambda p, n, v, m: jp.shade_direct(p, n, v, m, lights) + jp.shade_ibl(n, v, m, irr, pre, lut, multiscatter=True))
    want = np.asarray(kernels(p, n, v, m))
    bg = np.asarray(jax.jit(lambda c, d: c.sample(d))(env, -v.astype(np.float32)))
    want = np.where(hit[..., None], want, bg)
    np.testing.assert_allclose(img, want, rtol=1e-5, atol=1e-6)


def test_supersampling_is_the_mean_of_jittered_renders():
    scene = learnopengl_scene(20, 12)
    cam = scene.camera
    # (point samples: the outlines' blend works on cells 1/s of a pixel wide, a jittered pass's on whole pixels)
    ss = np.asarray(jp.render(scene.replace(camera=cam.replace(supersample=2)), antialias=False))
    acc = 0
    for oy in (-0.25, 0.25):
        for ox in (-0.25, 0.25):
            acc = acc + np.asarray(jp.render(scene.replace(camera=cam.replace(jitter=(ox, oy))), antialias=False))
    np.testing.assert_allclose(ss, acc / 4, rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------------------
# Compose only what is needed
# ------------------------------------------------------------------------------------------


def _primitives(scene, **options):
    opts = R.RenderOptions(**options)
    p = R.plan(scene, options=opts)
    assets = ibl_assets(split_environment(scene.environment, opts), p, opts) if p.ibl else None
    jaxpr = jax.make_jaxpr(lambda s, a: stages_._render_traced(s, a, p, opts))(scene, assets)
    text = str(jaxpr)
    return p, text


def test_plan_no_lights_no_environment_traces_neither(monkeypatch):
    calls = []
    monkeypatch.setattr(jp.ibl.diffuse, "irradiance", lambda *a, **k: calls.append("irr"))
    monkeypatch.setattr(jp.ibl.specular, "prefilter", lambda *a, **k: calls.append("pre"))
    scene = jp.Scene(camera=jp.Camera(width=8, height=6), objects=sphere_grid(2, 2))
    p, text = _primitives(scene)
    assert not p.direct and not p.ibl and p.prefilter_levels == 0
    img = np.asarray(jp.render(scene))
    assert calls == [] and (img == 0).all()
    # With lights the program grows by the BRDF (sqrt of the height-correlated V, rsqrt of
    # normalisations, ...); without, none of that is traced.
    lit = scene.replace(lights=[jp.PointLight(position=(0.0, 0.0, 5.0))])
    p2, text2 = _primitives(lit)
    assert p2.direct and text2.count("sqrt") > text.count("sqrt") + 2


def test_plan_metals_only_skips_irradiance_and_rough_range_limits_mips(monkeypatch):
    env = jp.Environment(radiance=small_env(64))
    mats = [jp.Material(metallic=1.0, roughness=r) for r in (0.0, 0.1, 0.3)]
    scene = jp.Scene(camera=jp.Camera(width=8, height=6), objects=[jp.Sphere(center=(x, 0, 0), material=m) for x, m in zip((-2, 0, 2), mats)], environment=env)
    assert R.plan(scene).ibl_diffuse  # the default multiple-scattering compensation reads Ebar
    ss = R.RenderOptions(multiscatter=False)
    p = R.plan(scene, options=ss)
    assert p.ibl and not p.ibl_diffuse
    # 64^2 prefilter: M = 5 levels (64 .. 4 at r = m/4), the default (mean-cosine) lod(0.3) = 1.15
    # -> levels 0..2 are enough.
    assert (p.mapping_levels, p.prefilter_levels) == (5, 3)
    seen = {}
    real_pre = jp.ibl.specular.prefilter

    def spy_pre(*a, **k):
        out = real_pre(*a, **k)
        seen["levels"] = out.num_levels
        return out

    monkeypatch.setattr(jp.ibl.specular, "prefilter", spy_pre)
    monkeypatch.setattr(jp.ibl.diffuse, "irradiance", lambda *a, **k: pytest.fail("irradiance computed for metals"))
    R.ASSETS.clear()
    img = np.asarray(jp.render(scene, options=ss))
    assert seen["levels"] == 3 and np.isfinite(img).all()
    # The truncated chain gives the same image as the full chain (lod <= 1.15 never reads beyond).
    full = ibl_assets(split_environment(env, ss), dataclasses.replace(p, prefilter_levels=5), ss)
    want = np.asarray(stages_._render_jit(scene, full, dataclasses.replace(p, prefilter_levels=5), ss))
    np.testing.assert_allclose(img, want, rtol=1e-6, atol=1e-7)
    # A dielectric brings the irradiance map back.
    p2 = R.plan(scene.replace(objects=scene.objects + (jp.Sphere(center=(0, 2, 0), material=jp.Material(metallic=0.5, roughness=0.3)),)))
    assert p2.ibl_diffuse


def test_precompute_is_cached_by_content_and_parameters():
    R.ASSETS.clear()
    env_map = small_env(16)
    scene = jp.Scene(
        camera=jp.Camera(width=8, height=6),
        objects=[jp.Sphere(material=jp.Material(metallic=0.0, roughness=0.5))],
        environment=jp.Environment(radiance=env_map),
    )
    jp.render(scene)
    assert R.ASSETS.stats["prefilter"] == {"hits": 0, "misses": 1}
    assert R.ASSETS.stats["irradiance"] == {"hits": 0, "misses": 1}
    # Same content in a new object, a new rotation and intensity: all hits.
    copy = jp.Cubemap([jnp.array(np.asarray(lv)) for lv in env_map.levels])
    jp.render(scene.replace(environment=jp.Environment(radiance=copy, rotation=1.0, intensity=2.0)))
    assert R.ASSETS.stats["prefilter"] == {"hits": 1, "misses": 1}
    assert R.ASSETS.stats["irradiance"] == {"hits": 1, "misses": 1}
    # Different parameters or content: misses.
    jp.render(scene, irradiance_size=16)
    assert R.ASSETS.stats["irradiance"]["misses"] == 2
    changed = jp.Cubemap([env_map.levels[0] * 1.5])
    jp.render(scene.replace(environment=jp.Environment(radiance=changed)))
    assert R.ASSETS.stats["prefilter"]["misses"] == 2


@pytest.mark.parametrize("staged", [True, False])
def test_a_cache_passed_in_is_the_only_one_read_and_filled(monkeypatch, staged):
    """`render(cache=)`, `bake(cache=)` and `render_batch(cache=)`: the environment's maps (and the
    suns split out of it) come from and go into the given AssetCache, on the staged path and the
    one-program path alike; the process's default `ASSETS` is neither read nor filled."""
    monkeypatch.setattr(R.EXECUTION, "staged", staged)
    R.ASSETS.clear()
    scene = jp.Scene(
        camera=jp.Camera(width=8, height=6),
        objects=[jp.Sphere(material=jp.Material(metallic=0.0, roughness=0.5))],
        environment=jp.Environment(radiance=small_env(16)),
    )
    mine = R.AssetCache()
    first = np.asarray(jp.render(scene, cache=mine))
    assert mine.stats["prefilter"] == {"hits": 0, "misses": 1} and mine.stats["irradiance"] == {"hits": 0, "misses": 1}
    assert mine.stats["extract"]["misses"] == 1
    assert not R.ASSETS.stats and not R.ASSETS._store
    again = np.asarray(jp.render(scene, cache=mine))
    assert mine.stats["prefilter"] == {"hits": 1, "misses": 1} and mine.stats["irradiance"] == {"hits": 1, "misses": 1}
    np.testing.assert_array_equal(again, first)
    # The default cache computes the same maps once for itself: the same image.
    np.testing.assert_array_equal(np.asarray(jp.render(scene)), first)
    assert R.ASSETS.stats["prefilter"] == {"hits": 0, "misses": 1}
    other = R.AssetCache()
    jp.bake(scene.environment, cache=other)
    assert other.stats["irradiance"] == {"hits": 0, "misses": 1} and R.ASSETS.stats["irradiance"]["misses"] == 1
    batch = R.AssetCache()
    jp.render_batch(scene, env_intensity=jnp.asarray([1.0, 2.0]), cache=batch)
    assert batch.stats["prefilter"] == {"hits": 0, "misses": 1} and R.ASSETS.stats["prefilter"]["misses"] == 1
    with pytest.raises(TypeError, match="AssetCache"):
        jp.render(scene, cache={})


def test_environment_rotation_rotates_the_lighting():
    """Rotating the environment by theta and the scene by theta about +Y gives the same image
    for a sphere at the origin seen from a rotated camera (rotation invariance of the split sum)."""
    env = small_env(32)
    mat = jp.Material(base_color=(0.8, 0.8, 0.8), metallic=0.5, roughness=0.4)
    th = 0.7
    cam0 = jp.Camera(position=(0.0, 0.0, 4.0), width=16, height=16)
    cam1 = jp.Camera(position=(4.0 * math.sin(th), 0.0, 4.0 * math.cos(th)), width=16, height=16)
    a = np.asarray(jp.render(jp.Scene(camera=cam0, objects=[jp.Sphere(material=mat)], environment=jp.Environment(radiance=env))))
    b = np.asarray(jp.render(jp.Scene(camera=cam1, objects=[jp.Sphere(material=mat)], environment=jp.Environment(radiance=env, rotation=th))))
    hit = a.sum(-1) > 0
    np.testing.assert_allclose(b, a, rtol=2e-4, atol=2e-5)
    assert hit.any()


# ------------------------------------------------------------------------------------------
# Errors
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "build,message",
    [
        (lambda: jp.Scene(objects=[jp.Sphere()]), "needs a Camera"),
        (lambda: jp.Scene(camera=jp.Camera()), "needs objects"),
        (lambda: jp.Scene(camera=jp.Camera(), objects=["ball"]), "Sphere, Plane or Mesh"),
        (lambda: jp.Scene(camera=jp.Camera(), objects=[jp.Sphere()], lights=[1.0]), "PointLight"),
        (lambda: jp.Sphere(radius=-1.0), "radius must be > 0"),
        (lambda: jp.Sphere(material="gold"), "Material or TexturedMaterial"),
        (lambda: jp.Camera(width=0), "width"),
        (lambda: jp.Camera(fov_y_deg=180.0), "fov_y_deg"),
        (lambda: jp.Camera(target=(0.0, 0.0, 24.0)), "differ"),
        (lambda: jp.Camera(position=(0.0, 5.0, 0.0)), "parallel"),
        (lambda: jp.Plane(normal=(0.0, 0.0, 0.0)), "non-zero"),
        (lambda: jp.TexturedMaterial(base_color_texture=np.full((2, 2, 3), 2.0)), "[0, 1]"),
        (lambda: jp.TexturedMaterial(normal_texture=np.zeros((2, 2))), "(H, W, C)"),
        (lambda: jp.Environment(radiance=np.zeros((6, 4, 4, 3))), "Cubemap"),
        (lambda: jp.render(learnopengl_scene(4, 4), model="phong"), "unknown model"),
        (lambda: jp.render(learnopengl_scene(4, 4), dtype="float16"), "dtype"),
    ],
)
def test_scene_errors_are_clear(build, message):
    with pytest.raises((ValueError, TypeError)) as e:
        build()
    assert message in str(e.value)


def test_gbuffer_scene_with_extracted_sun_equals_kernels():
    """By default the sun is split out: the render equals shade_direct over the scene's and the
    extracted disc lights plus the split sum of the residual environment (both compensated for
    multiple scattering, render's default)."""
    from jaxpbr.ibl.extract import extract_lights

    rng = np.random.default_rng(4)
    Hh, Ww = 5, 4
    n = rng.normal(size=(Hh, Ww, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    v = n + 0.5 * rng.normal(size=(Hh, Ww, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    m = jp.Material(base_color=rng.uniform(size=(Hh, Ww, 3)), metallic=rng.uniform(size=(Hh, Ww)), roughness=rng.uniform(0.05, 1, size=(Hh, Ww)))
    hit = np.ones((Hh, Ww), bool)
    g = jp.GBuffer(hit=hit, position=np.zeros((Hh, Ww, 3)), normal=n, view=v, material=m)
    env = jp.envs.sky_with_sun_cubemap(32)
    scene = jp.Scene(gbuffer=g, environment=jp.Environment(radiance=env))
    assert jp.rendering.renderer.plan(scene).env_lights == 1
    assert "1 sun(s) split out" in jp.rendering.renderer.plan(scene).describe()
    assert jp.rendering.renderer.plan(scene, extract_lights=False).env_lights == 0
    img = np.asarray(jp.render(scene))
    ex = extract_lights(env)
    (sun,) = ex.lights
    irr, pre, lut = jp.irradiance(ex.residual, size=32), jp.prefilter(ex.residual), jp.brdf_lut(size=128)
    # with the default compensation: of the residual's IBL term and of the sun (its FmsEms times its irradiance)
    want = jax.jit(lambda n, v, m: jp.shade_direct(np.zeros(3), n, v, m, sun) + jp.shade_ibl(n, v, m, irr, pre, lut, multiscatter=True)
                   + jp.ibl.shade.disc_multiscatter(n, v, m, lut, [sun]))(n, v, m)
    np.testing.assert_allclose(img, np.asarray(want), rtol=2e-5, atol=1e-6)
    off = np.asarray(jp.render(scene, extract_lights=False))
    assert np.abs(off - img).max() > 1e-3  # the split changes the image (the split sum's error)


def test_default_energy_model_compensates_multiple_scattering():
    """render's default for the glTF model is the Fdez-Aguera compensation (what glTF viewers
    show): a white rough metal in a white furnace reflects 1; multiscatter=False gives the
    single-scattering albedo A + B < 1 (1 - ln 2 at normal incidence, r = 1). learnopengl
    defaults to no compensation."""
    import dataclasses

    assert jp.RenderOptions().compensates and not jp.RenderOptions(model="learnopengl").compensates
    # None means "the model's default" also after replacing only the model
    assert not dataclasses.replace(jp.RenderOptions(), model="learnopengl").compensates
    with pytest.raises(ValueError, match="multiscatter is defined for the gltf model only"):
        jp.RenderOptions(model="learnopengl", multiscatter=True)
    white = jp.Cubemap.from_function(lambda d: jnp.ones(d.shape[:-1] + (3,)), 8)
    cam = jp.Camera(position=(0.0, 0.0, 4.0), target=(0.0, 0.0, 0.0), width=9, height=9, fov_y_deg=10.0)
    scene = jp.Scene(camera=cam, objects=[jp.Sphere(center=(0.0, 0.0, 0.0), radius=1.0,
                     material=jp.Material(base_color=(1.0, 1.0, 1.0), metallic=1.0, roughness=1.0))],
                     lights=[], environment=jp.Environment(radiance=white))
    ms = np.asarray(jp.render(scene))
    ss = np.asarray(jp.render(scene, multiscatter=False))
    np.testing.assert_allclose(ms[4, 4], 1.0, atol=2e-3)
    assert abs(ss[4, 4, 0] - (1 - np.log(2))) < 5e-3


def test_multiscatter_of_split_out_suns_matches_the_environment_s():
    """The compensation a rough white metal gets under a sky with a sun is the same whether the sun
    is split out as a disc light or left in the environment (FmsEms times the irradiance either
    way): the multiscatter - single-scatter difference agrees to 1 % over the sphere."""
    env = jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(32))
    cam = jp.Camera(position=(0.0, 0.0, 4.0), target=(0.0, 0.0, 0.0), width=16, height=16, fov_y_deg=40.0)
    scene = jp.Scene(camera=cam, objects=[jp.Sphere(center=(0.0, 0.0, 0.0), radius=1.0,
                     material=jp.Material(base_color=(1.0, 1.0, 1.0), metallic=1.0, roughness=0.8))],
                     lights=[], environment=env)
    assert jp.rendering.renderer.plan(scene).env_lights == 1
    delta = {ex: np.asarray(jp.render(scene, extract_lights=ex)) - np.asarray(jp.render(scene, extract_lights=ex, multiscatter=False))
             for ex in (True, False)}
    assert delta[False].sum() > 0.05 * np.asarray(jp.render(scene, extract_lights=False)).sum()
    assert abs(delta[True].sum() - delta[False].sum()) <= 0.01 * delta[False].sum()
