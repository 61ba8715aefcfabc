"""The scene layer with the glTF material extensions: the plan traces and bakes only what the
materials use; neutral values render the core image; sphere volumes; gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.ibl import sheen_prefilter
from jaxpbr.rendering import renderer, stages
from jaxpbr.shading.material import EXTENSION_FIELDS


def _env():
    return jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(16))


def _scene(mats, *, env=True, lights=True, w=24, h=12, floor=0.8):
    objs = [jp.Sphere(center=(2.2 * (i - (len(mats) - 1) / 2), 1.0, 0.0), radius=1.0, material=m) for i, m in enumerate(mats)]
    objs.append(jp.Plane(point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0), material=jp.Material((0.5, 0.5, 0.5), metallic=0.0, roughness=floor)))
    cam = jp.Camera(position=(0.0, 2.0, 9.0), target=(0.0, 1.0, 0.0), width=w, height=h, fov_y_deg=45.0)
    return jp.Scene(
        camera=cam, objects=objs, lights=[jp.PointLight(position=(0.0, 5.0, 5.0), intensity=30.0)] if lights else [],
        environment=_env() if env else None,
    )


BASE = dict(base_color=(0.8, 0.4, 0.2), metallic=0.0, roughness=0.5)


def test_plan_lists_the_extensions_the_materials_use():
    p = renderer.plan(_scene([jp.Material(**BASE)]))
    assert p.extensions == () and p.charlie_size == 0
    p = renderer.plan(_scene([jp.Material(**BASE, clearcoat=1.0), jp.Material(**BASE, transmission=0.5, thickness=0.1)]))
    assert p.extensions == ("clearcoat", "transmission", "volume") and p.charlie_size == 0
    assert "material extensions: clearcoat, transmission, volume" in p.describe()
    p = renderer.plan(_scene([jp.Material(**BASE, sheen_color=(1.0, 1.0, 1.0))]))
    assert p.extensions == ("sheen",) and p.charlie_size > 0
    p = renderer.plan(_scene([jp.Material(**BASE, sheen_color=(1.0, 1.0, 1.0))], env=False))
    assert p.extensions == ("sheen",) and p.charlie_size == 0  # no IBL: no Charlie cube


def test_plan_reads_the_prefiltered_chain_up_to_the_coat_roughness():
    p0 = renderer.plan(_scene([jp.Material(base_color=(1.0, 1.0, 1.0), metallic=1.0, roughness=0.1)], floor=0.1))
    p1 = renderer.plan(_scene([jp.Material(base_color=(1.0, 1.0, 1.0), metallic=1.0, roughness=0.1, clearcoat=1.0,
                                           clearcoat_roughness=0.9)], floor=0.1))
    assert p1.prefilter_levels > p0.prefilter_levels


def test_the_charlie_cube_is_baked_only_for_sheen(monkeypatch):
    calls = []
    real = sheen_prefilter.prefilter_charlie

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(sheen_prefilter, "prefilter_charlie", counting)
    renderer.ASSETS.clear()
    jp.render(_scene([jp.Material(**BASE, clearcoat=1.0)]))
    assert calls == []
    img = jp.render(_scene([jp.Material(**BASE, sheen_color=(0.9, 0.9, 0.9), sheen_roughness=0.5)]))
    assert len(calls) == 1 and np.isfinite(np.asarray(img)).all()
    jp.render(_scene([jp.Material(**BASE, sheen_color=(0.5, 0.9, 0.9), sheen_roughness=0.3)]))
    assert len(calls) == 1  # cached per environment content


@pytest.mark.parametrize("group", list(EXTENSION_FIELDS))
def test_neutral_extensions_render_the_core_image(group):
    core = jp.render(_scene([jp.Material(**BASE), jp.Material(base_color=(0.9, 0.9, 0.9), metallic=1.0, roughness=0.3)]))
    ext = jp.render(_scene([jp.Material(**BASE, **EXTENSION_FIELDS[group]),
                            jp.Material(base_color=(0.9, 0.9, 0.9), metallic=1.0, roughness=0.3)]))
    np.testing.assert_allclose(np.asarray(ext), np.asarray(core), rtol=2e-5, atol=2e-6)


@pytest.mark.parametrize("lights,env,suns", [(True, True, True)] + [
    pytest.param(*c, marks=pytest.mark.slow) for c in ((True, False, False), (False, True, False), (False, True, True))])
def test_all_neutral_extensions_render_the_core_image_in_every_lighting(lights, env, suns):
    """Every extension group at its neutral values on a dielectric, a metal and a half metal
    gives the core image to float32 rounding under point lights, IBL, and IBL with the sun split
    out as a disc light (the straddling disc of a transmission material lost its reflected part:
    5.6e-3 of the image maximum)."""
    neutral = {k: v for f in EXTENSION_FIELDS.values() for k, v in f.items()}
    mats = [dict(base_color=(0.8, 0.5, 0.3), metallic=0.0, roughness=0.5), dict(base_color=(0.9, 0.9, 0.9), metallic=1.0, roughness=0.3),
            dict(base_color=(0.3, 0.6, 0.9), metallic=0.5, roughness=0.7)]
    f32 = dict(dtype="float32", extract_lights=suns)
    env_obj = jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(32)) if env else None

    def scene(ext):
        s = _scene([jp.Material(**m, **(neutral if ext else {})) for m in mats], lights=lights, env=False, w=32, h=16)
        return s if env_obj is None else s.replace(environment=env_obj)

    if suns:
        assert renderer.plan(scene(False), extract_lights=True).env_lights >= 1
    core = np.asarray(jp.render(scene(False), **f32))
    ext = np.asarray(jp.render(scene(True), **f32))
    assert np.abs(ext - core).max() <= 2e-6 * core.max(), np.abs(ext - core).max() / core.max()


def test_every_extension_renders_finite_and_changes_its_sphere():
    """One scene, a sphere per extension (one compilation): finite, and each sphere's pixels differ
    from the same scene with core materials."""
    exts = (dict(clearcoat=1.0, clearcoat_roughness=0.1), dict(sheen_color=(1.0, 1.0, 1.0), sheen_roughness=0.4),
            dict(specular=0.2), dict(ior=2.5), dict(anisotropy_strength=0.9, anisotropy_rotation=0.5),
            dict(emissive=(1.0, 1.0, 1.0), emissive_strength=5.0), dict(transmission=1.0),
            dict(transmission=1.0, thickness=0.5, attenuation_distance=0.5, attenuation_color=(0.9, 0.3, 0.1)))

    def scene(with_ext):
        objs = [jp.Sphere(center=(2.5 * (i - 3.5), 1.0, 0.0), radius=1.0,
                          material=jp.Material(**BASE, **(e if with_ext else {}))) for i, e in enumerate(exts)]
        cam = jp.Camera(position=(0.0, 1.0, 24.0), target=(0.0, 1.0, 0.0), width=96, height=8, fov_y_deg=12.0)
        return jp.Scene(camera=cam, objects=objs, lights=[jp.PointLight(position=(0.0, 5.0, 5.0), intensity=30.0)],
                        environment=_env())

    core = np.asarray(jp.render(scene(False)))
    img = np.asarray(jp.render(scene(True)))
    assert np.isfinite(img).all()
    diff = np.abs(img - core).max(axis=(0, 2))  # per column
    # the camera sees x in [-tan(fov/2) * 24 * aspect, +...]: the sphere centres' columns
    half = np.tan(np.radians(6.0)) * 24.0 * 12.0
    for i, e in enumerate(exts):
        col = int((2.5 * (i - 3.5) / half * 0.5 + 0.5) * 96)
        assert diff[col - 1 : col + 2].max() > 1e-3, e


def test_sphere_volume_path_and_exit_direction():
    """ior 1: no refraction, the exit direction is -v and the chord 2 R n.v; normal incidence at
    any ior: straight through, chord 2 R; otherwise the exit direction is -v rotated away from
    the normal's side by the deviation 2 (theta_i - theta_t)."""
    n = np.array([[0.0, 0.0, 1.0]] * 3)
    mu = np.array([1.0, 0.6, 0.2])
    v = np.stack([np.sqrt(1 - mu * mu), np.zeros(3), mu], -1)
    g = dict(n=jp._numerics.unpack3(jnp.asarray(n)), view=jp._numerics.unpack3(jnp.asarray(v)), radius=jnp.full(3, 2.0))
    m = jp.Material(thickness=jnp.full(3, 0.1), ior=jnp.full(3, 1.0))
    dist, d = stages._volume_inputs(g, m, jnp.float64)
    np.testing.assert_allclose(np.asarray(dist), 4.0 * mu, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(d), -v, atol=1e-12)
    m = m.replace(ior=jnp.full(3, 1.5))
    dist, d = stages._volume_inputs(g, m, jnp.float64)
    ti = np.arccos(mu)
    tt = np.arcsin(np.sin(ti) / 1.5)
    np.testing.assert_allclose(np.asarray(dist), 4.0 * np.cos(tt), rtol=1e-12)
    dev = 2 * (ti - tt)  # total deviation of a ray through a sphere (no internal reflection)
    cos_dev = np.sum(np.asarray(d) * -v, -1)
    np.testing.assert_allclose(cos_dev, np.cos(dev), atol=1e-12)


def test_render_is_differentiable_in_the_extension_parameters():
    def loss(cc, sheen, tr):
        m = jp.Material(**BASE, clearcoat=cc, clearcoat_roughness=0.2, sheen_color=jnp.stack([sheen] * 3), sheen_roughness=0.5,
                        transmission=tr)
        return jnp.mean(jp.render(_scene([m], w=12, h=6)))

    args = (jnp.float32(0.5), jnp.float32(0.3), jnp.float32(0.4))
    grads = jax.grad(loss, argnums=(0, 1, 2))(*args)
    for i, gr in enumerate(grads):
        assert np.isfinite(float(gr))
        h = 1e-2
        hi = list(args)
        lo = list(args)
        hi[i] = hi[i] + h
        lo[i] = lo[i] - h
        fd = (float(loss(*hi)) - float(loss(*lo))) / (2 * h)
        assert abs(float(gr) - fd) <= 2e-2 * abs(fd) + 1e-4, (i, float(gr), fd)


def test_render_batch_over_an_extension_parameter_equals_single_renders():
    base = dict(BASE, sheen_color=(0.5, 0.5, 0.5))
    sc = _scene([jp.Material(**base, clearcoat=0.0)], w=12, h=6)
    out = np.asarray(jp.render_batch(sc, materials=jp.Material(**base, clearcoat=jnp.array([0.0, 0.5, 1.0])), objects=[0]))
    assert out.shape == (3, 6, 12, 3)
    for i, c in enumerate((0.0, 0.5, 1.0)):
        one = np.asarray(jp.render(_scene([jp.Material(**base, clearcoat=c)], w=12, h=6)))
        np.testing.assert_allclose(out[i], one, rtol=1e-5, atol=1e-6)


def test_a_gbuffer_with_extension_materials_renders():
    H, W = 4, 5
    gb = jp.GBuffer(
        hit=jnp.ones((H, W), bool), position=jnp.zeros((H, W, 3)), normal=jnp.tile(jnp.array([0.0, 0.0, 1.0]), (H, W, 1)),
        view=jnp.tile(jnp.array([0.0, 0.6, 0.8]), (H, W, 1)),
        material=jp.Material(base_color=jnp.full((H, W, 3), 0.5), metallic=jnp.zeros((H, W)), roughness=jnp.full((H, W), 0.5),
                             clearcoat=jnp.linspace(0.0, 1.0, H * W).reshape(H, W)),
    )
    img = np.asarray(jp.render(jp.Scene(gbuffer=gb, lights=[jp.DirectionalLight((0.0, 0.0, -1.0))], environment=_env())))
    assert np.isfinite(img).all()
    assert img[0, 0].sum() != img[-1, -1].sum()  # the coat weight changes the shading


def test_the_anisotropy_texture_does_not_turn_the_normal_map():
    """The normal map is in the surface's tangent frame; the anisotropy texture's direction only
    steers the anisotropic lobe (it used to become the normal map's tangent)."""
    from jaxpbr._numerics import unpack3

    H, W = 2, 2
    tilted = np.full((2, 2, 3), [0.8, 0.5, 0.9])  # tilted along +T
    f = jp.Material(base_color=(0.5, 0.5, 0.5), metallic=1.0, roughness=0.3, anisotropy_strength=1.0)
    normals = []
    for direction in (None, [0.5, 1.0, 1.0]):  # no anisotropy texture; a texture pointing along +B
        kw = {} if direction is None else {"anisotropy_texture": np.full((2, 2, 3), direction)}
        tm = jp.TexturedMaterial(factors=f, normal_texture=tilted, **kw)
        objects = (jp.Sphere(material=tm),)
        m = stages._gather_material(stages._stack_materials(objects, jnp.float32, ("anisotropy",)), jnp.zeros((H, W), jnp.int32))
        n = unpack3(jnp.tile(jnp.array([0.0, 0.0, 1.0]), (H, W, 1)))
        t = unpack3(jnp.tile(jnp.array([1.0, 0.0, 0.0]), (H, W, 1)))
        uv = (jnp.full((H, W), 0.25), jnp.full((H, W), 0.25))
        _, n_out, _, aniso, _ = stages._apply_texture(objects, 0, jnp.zeros((H, W), jnp.int32), uv, t, n, m, jnp.float32)
        normals.append(np.stack([np.asarray(c) for c in n_out], -1))
        if direction is not None:
            np.testing.assert_allclose(np.stack([np.asarray(c) for c in aniso], -1)[0, 0], [0.0, 1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(normals[1], normals[0], atol=1e-6)
    assert normals[0][0, 0, 0] > 0.3  # tilted along +T (x)


def test_bake_includes_the_sheen_assets_only_when_asked():
    env = _env()
    plain = jp.bake(env)
    assert plain.charlie is None and plain.sheen_lut is None
    full = jp.bake(env, sheen=True)
    assert full.charlie is not None and full.charlie.metadata["distribution"] == "charlie"
    assert full.sheen_lut.shape == (128, 128)
    # a sheen render on the fully baked environment computes no Charlie cube
    sc = _scene([jp.Material(**BASE, sheen_color=(1.0, 1.0, 1.0))]).replace(environment=full)
    assert renderer.plan(sc).charlie_size == full.charlie.face_size
    assert np.isfinite(np.asarray(jp.render(sc))).all()
