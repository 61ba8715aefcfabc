"""Image-based light that knows what occludes it: the rungs of `RenderOptions.ibl_visibility`
("none", "occlusion", "ao", "ratio") against closed forms and the ground truth.

* A Lambertian floor and wall, both infinite, under a uniform sky: half of every point's
  cosine-weighted hemisphere is blocked (exactly), so the truth is albedo x L / 2 where the
  unshadowed split sum gives albedo x L. The traced rungs converge to it as the rays grow; the
  ratio estimator is unbiased over the image.
* A convex object: nothing occludes its light, so every traced rung equals the unshadowed split sum.
* Determinism per pixel, finite gradients under every rung, and the plan: no rays for "none" and
  "occlusion"."""

from __future__ import annotations

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.ibl.cubemap import Cubemap
from jaxpbr.rendering.plan import plan

ALBEDO = 0.5
LAMBERT = dict(base_color=(ALBEDO, ALBEDO, ALBEDO), metallic=0.0, roughness=1.0, specular=0.0)


def uniform_sky(value=1.0):
    return jp.Environment(radiance=Cubemap.from_function(lambda d: 0.0 * d + value, 16))


def wall_scene(w=32, h=24):
    m = jp.Material(**LAMBERT)
    cam = jp.Camera(position=(0.7, 3.0, 4.0), target=(0.0, 0.6, 0.0), width=w, height=h)
    return jp.Scene(camera=cam, objects=(jp.Plane(point=(0, 0, 0), normal=(0, 1, 0), material=m),
                                         jp.Plane(point=(0, 0, 0), normal=(0, 0, 1), material=m)), environment=uniform_sky())


def shade(scene, vis, k=4, **kw):
    opts = dict(extract_lights=False, multiscatter=False, ibl_visibility=vis, ibl_samples=k)
    opts.update(kw)
    return np.asarray(jp.render(scene, **opts), np.float64)


def test_a_floor_beside_a_wall_converges_to_half_the_sky():
    scene = wall_scene()
    truth = ALBEDO * 0.5
    for vis in ("none", "occlusion"):
        np.testing.assert_allclose(shade(scene, vis)[..., 0], ALBEDO, rtol=2e-3)
    err = {}
    for vis in ("ao", "ratio"):
        for k in (2, 8, 32):
            img = shade(scene, vis, k)[..., 0]
            err[vis, k] = (np.abs(img - truth).mean() / truth, img.mean() / truth - 1)
    for vis in ("ao", "ratio"):
        means = [err[vis, k][0] for k in (2, 8, 32)]
        assert means[-1] <= means[0] and means[-1] < 0.2, (vis, means)
        assert abs(err[vis, 32][1]) < 0.02, (vis, err[vis, 32])  # unbiased over the image
    assert abs(err["ratio", 8][1]) < 0.03


def test_nothing_to_occlude_changes_nothing():
    metal = jp.Material(base_color=(0.9, 0.6, 0.3), metallic=1.0, roughness=0.35)
    glossy = jp.Material(base_color=(0.2, 0.4, 0.8), metallic=0.0, roughness=0.5)
    from jaxpbr.ibl.envs import sky_with_sun_cubemap

    cam = jp.Camera(position=(0, 0, 6.0), target=(0, 0, 0), width=24, height=16)
    scene = jp.Scene(camera=cam, objects=(jp.Sphere(center=(-1.2, 0, 0), radius=1.0, material=metal),
                                          jp.Sphere(center=(1.2, 0, 0), radius=1.0, material=glossy)),
                     environment=jp.Environment(radiance=sky_with_sun_cubemap(32)))
    # spheres 0.4 apart: rays from each see the other; with one sphere, nothing
    single = jp.Scene(camera=cam, objects=scene.objects[:1], environment=scene.environment)
    base = shade(single, "none")
    for vis in ("ao", "ratio"):
        np.testing.assert_allclose(shade(single, vis, 4), base, rtol=1e-5, atol=1e-6)
    # and the neighbour does darken the facing sides
    assert shade(scene, "ratio", 8).sum() < shade(scene, "none").sum()


def test_rungs_are_deterministic_and_planned():
    scene = wall_scene(12, 8)
    img = shade(scene, "ratio", 4)
    np.testing.assert_array_equal(img, shade(scene, "ratio", 4))
    assert abs(img[..., 0].mean() / (ALBEDO * 0.5) - 1) < 0.1  # the wall takes half the sky
    for vis in ("none", "occlusion"):
        p = plan(scene, ibl_visibility=vis, ibl_samples=16)
        assert p.ibl_samples == 0  # no rays, no programs for them
    p = plan(scene, ibl_visibility="ratio", ibl_samples=16)
    assert p.ibl_samples == 16 and "ratio" in p.describe()
    with pytest.raises(ValueError, match="ibl_visibility"):
        jp.RenderOptions(ibl_visibility="ssao")
    with pytest.raises(ValueError, match="ibl_samples"):
        jp.RenderOptions(ibl_samples=0)


def test_render_batch_traces_the_rungs_as_render_does():
    """render_batch (staged on the CPU: the rays of each chunk in one program) gives each image what
    render gives it, ray for ray: the wall's shadow is in every image of the batch."""
    scene = wall_scene(12, 8)
    ints = np.asarray([1.0, 0.5], np.float32)
    opts = dict(extract_lights=False, multiscatter=False, ibl_visibility="ratio", ibl_samples=4)
    imgs = np.asarray(jp.render_batch(scene, env_intensity=ints, **opts), np.float64)
    for i, s in enumerate(ints):
        one = shade(scene.replace(environment=scene.environment.replace(intensity=float(s))), "ratio", 4)
        np.testing.assert_allclose(imgs[i], one, rtol=1e-6, atol=1e-7)
    assert abs(imgs[0, ..., 0].mean() / (ALBEDO * 0.5) - 1) < 0.1  # shadowed, not the unshadowed ALBEDO


@pytest.mark.slow  # ~20 s: four compiled gradients and their finite differences
@pytest.mark.parametrize("vis", ["none", "occlusion", "ao", "ratio"])
def test_gradients_are_finite_under_every_rung(vis):
    import jax
    import jax.numpy as jnp

    from jaxpbr._pytree import evolve

    scene = wall_scene(10, 8)
    floor, wall = scene.objects

    def loss(base, intensity):
        f = evolve(floor, material=evolve(floor.material, base_color=base))
        env = evolve(scene.environment, intensity=intensity)
        img = jp.render(evolve(scene, objects=(f, wall), environment=env), extract_lights=False, ibl_visibility=vis, ibl_samples=2)
        return jnp.sum(img)

    base, inten = jnp.asarray([0.5, 0.5, 0.5]), jnp.asarray(1.0)
    g_b, g_i = jax.grad(loss, argnums=(0, 1))(base, inten)
    assert np.all(np.isfinite(np.asarray(g_b))) and np.isfinite(float(g_i)) and float(g_i) > 0
    # against central differences (the visibility does not move with these: the same rays)
    h = 1e-2
    fd_i = (float(loss(base, inten + h)) - float(loss(base, inten - h))) / (2 * h)
    np.testing.assert_allclose(float(g_i), fd_i, rtol=2e-3)
    e = jnp.asarray([0.0, 1.0, 0.0])
    fd_b = (float(loss(base + h * e, inten)) - float(loss(base - h * e, inten))) / (2 * h)
    np.testing.assert_allclose(float(g_b[1]), fd_b, rtol=2e-3)


@pytest.mark.slow  # ~15 s: three compiled gradients
@pytest.mark.parametrize("vis", ["occlusion", "ao", "ratio"])
def test_stiff_inputs_stay_finite_with_traced_light(vis):
    """Roughness 0 everywhere, a volume sphere of ior 1 (the refracted lobe's width has sqrt'(0)
    there), a mirror floor seen at a grazing angle, the sky with its sun: values and gradients with
    respect to both roughnesses and the ior are finite under every rung, transmission traced."""
    import jax
    import jax.numpy as jnp

    from jaxpbr._pytree import evolve
    from jaxpbr.ibl.envs import sky_with_sun_cubemap

    env = jp.Environment(radiance=sky_with_sun_cubemap(16))
    cam = jp.Camera(position=(0, 0.05, 4.0), target=(0, 0, 0), width=12, height=8)
    floor = jp.Plane(point=(0, -1, 0), normal=(0, 1, 0), material=jp.Material(base_color=(0.9, 0.9, 0.9), metallic=1.0, roughness=0.0))

    def loss(r, ior, gr):
        g = jp.Material(base_color=(1, 1, 1), metallic=0.0, roughness=gr, transmission=1.0, thickness=1.0, ior=ior)
        scene = jp.Scene(camera=cam, objects=(jp.Sphere(center=(0, 0, 0), radius=1.0, material=g),
                                              evolve(floor, material=evolve(floor.material, roughness=r))), environment=env)
        return jnp.sum(jp.render(scene, ibl_visibility=vis, ibl_samples=2))

    args = (jnp.asarray(0.0), jnp.asarray(1.0), jnp.asarray(0.0))
    assert np.isfinite(float(loss(*args)))
    assert all(np.isfinite(float(x)) for x in jax.grad(loss, argnums=(0, 1, 2))(*args))
