"""Gradients of rendered images: finite everywhere, equal to central finite differences.

All checks in float64 (the render's dtype option): the loss is sum(w * image) with fixed random
weights w; central differences with step h have truncation error O(h^2 f''') ~ 1e-8 relative at
h = 1e-5, and rounding error eps/h ~ 1e-11 relative, so agreement to 1e-6 relative is expected of
a correct gradient and fails on any missing or wrong term."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gradcheck import check_partials

import jaxpbr as jp

W, H = 10, 8
F64 = dict(dtype="float64")


def make_scene(base_color=(0.8, 0.4, 0.2), metallic=0.3, roughness=0.4, light_pos=(2.0, 3.0, 4.0), intensity=40.0,
               texture=None, env_level=None, sun_dir=(0.0, -1.0, -1.0)):
    mat = jp.Material(base_color=base_color, metallic=metallic, roughness=roughness)
    if texture is not None:
        mat = jp.TexturedMaterial(factors=mat, base_color_texture=texture)
    env = None
    if env_level is not None:
        env = jp.Environment(radiance=jp.Cubemap((env_level,)))
    return jp.Scene(
        camera=jp.Camera(position=(0.3, 0.4, 3.5), width=W, height=H, fov_y_deg=50.0),
        objects=[
            jp.Sphere(center=(0.0, 0.0, 0.0), radius=1.0, material=mat),
            jp.Plane(point=(0.0, -1.0, 0.0), normal=(0.0, 1.0, 0.0), material=jp.Material((0.5, 0.5, 0.5), 0.0, 0.7)),
        ],
        lights=[jp.PointLight(position=light_pos, intensity=intensity), jp.DirectionalLight(direction=sun_dir, intensity=2.0)],
        environment=env,
    )


def weights(shape=(H, W, 3)):
    return np.random.default_rng(7).uniform(size=shape)


def check(fn, x, idx_list, h=1e-5, rtol=1e-6):
    """jax.grad(fn)(x) is finite and not identically zero, and its partials at the given flat indices
    equal central differences with step h to rtol * max|grad| + 1e-9 (check_grads, reverse mode).
    Eager: `render` compiles its stages once and every evaluation here reuses them (a jitted loss is
    one large program, compiled again for its gradient and its VJP)."""
    x = np.asarray(x, np.float64)
    g = np.asarray(jax.grad(fn)(jnp.asarray(x))).ravel()
    assert np.isfinite(g).all()
    scale = np.abs(g).max()
    assert scale > 0, "gradient is identically zero: the check would be vacuous"
    check_partials(fn, x, idx_list, step=h, atol=rtol * scale + 1e-9, rtol=0.0)
    return g


@pytest.fixture(scope="module")
def env_level():
    with jax.enable_x64(True):
        return jnp.asarray(jp.envs.sky_with_sun_cubemap(8, dtype=jnp.float64).levels[0])


def test_grad_wrt_material_parameters(env_level):
    w = weights()

    def loss(p):
        img = jp.render(make_scene(base_color=p[:3], metallic=p[3], roughness=p[4], env_level=env_level), **F64)
        return jnp.sum(img * w)

    check(loss, np.array([0.8, 0.4, 0.2, 0.3, 0.4]), range(5))


def test_grad_wrt_light_parameters():
    w = weights()

    def loss(p):
        img = jp.render(make_scene(light_pos=p[:3], intensity=p[3]), **F64)
        return jnp.sum(img * w)

    # Under jax.jit (as in an optimisation loop): the stages inline into one program, differentiated
    # as a whole; the other checks differentiate render's own compiled stages.
    check(jax.jit(loss), np.array([2.0, 3.0, 4.0, 40.0]), range(4))


def test_grad_wrt_texture_texels():
    tex = np.random.default_rng(1).uniform(0.2, 0.8, size=(4, 6, 3))
    w = weights()

    def loss(t):
        return jnp.sum(jp.render(make_scene(texture=t), **F64) * w)

    g = check(loss, tex, [0, 5, 17, 30, 44, 71])
    assert (g != 0).sum() > 10  # many texels are seen


@pytest.mark.slow  # ~20 s (traced prefilter + its gradient); tests/test_precompute_grad.py checks the precomputes fast
def test_grad_wrt_environment_texels(env_level):
    """Through the irradiance and prefilter precomputes and the background lookup. Without the
    sun's extraction: it runs on concrete environments only (a host-side step, not differentiable),
    so with it the finite differences (concrete) and the gradient (traced) would be of two
    different functions (their values differ by 2.6 % on this scene)."""
    w = weights()
    base = np.asarray(env_level)

    def loss(lv):
        return jnp.sum(jp.render(make_scene(env_level=lv), extract_lights=False, **F64) * w)

    g = np.asarray(jax.grad(loss)(jnp.asarray(base))).ravel()
    assert np.isfinite(g).all()
    # The texels with the largest gradients (seen directly, or through the lobes) and a few others.
    top = list(np.argsort(-np.abs(g))[:6])
    rng = np.random.default_rng(3)
    check(loss, base, top + list(rng.choice(base.size, 4, replace=False)), h=1e-4)


@pytest.mark.parametrize(
    "dtype,roughness",
    [("float32", 0.0)]
    + [
        pytest.param(d, r, marks=pytest.mark.slow)
        for d, r in (("float32", 1e-4), ("float32", 0.045), ("float64", 0.0), ("float64", 1e-4), ("float64", 0.045))
    ],
)
def test_gradients_finite_at_roughness_floor_and_silhouettes(env_level, roughness, dtype):
    """r -> 0 (mirror IBL lookup, delta-like direct lobe) and grazing silhouette pixels: the image
    and every gradient stay finite. (Below the punctual floor 0.045 d/dr of the direct term is 0
    by design; the IBL term keeps a gradient.)"""
    w = weights()
    lv = env_level.astype(dtype)

    def loss(p, lv):
        img = jp.render(make_scene(base_color=p[:3], metallic=p[3], roughness=p[4], light_pos=p[5:8], env_level=lv), dtype=dtype)
        return jnp.sum(img * w)

    p = jnp.asarray([0.8, 0.4, 0.2, 1.0, roughness, 2.0, 3.0, 4.0], dtype)
    # Eager: render runs its own compiled stages (one jitted program of the whole loss, traced
    # precomputes included, takes ~4x longer to compile).
    val, (gp, glv) = jax.value_and_grad(loss, argnums=(0, 1))(p, lv)
    assert np.isfinite(float(val))
    assert np.isfinite(np.asarray(gp)).all() and np.isfinite(np.asarray(glv)).all()
    assert np.abs(np.asarray(gp)[:3]).max() > 0
