"""Slow, deliberate checks (`python3 -m pytest -q -m slow`): dense sweeps of the stiff domain and
the full-size benchmark agreement."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.cli.numpy_baselines import bench_lights, make_gbuffer, shade_numpy

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("model", ["gltf", "learnopengl"])
def test_dense_stiff_sweep_values_and_gradients_finite(model, dtype):
    """A dense sweep: NoV, NoL over 41 values each in [-1, 1] with extra points near 0 (+-1e-7 ..
    +-1e-2), 3 azimuths, roughness over 9 values in [0, 1] including 0 and 1e-6; radiance 1e6."""
    near0 = np.array([1e-7, 1e-6, 1e-4, 1e-2])
    cos = np.unique(np.concatenate([np.linspace(-1, 1, 33), near0, -near0, [0.0]]))
    rough = np.array([0.0, 1e-6, 1e-3, 0.02, 0.045, 0.1, 0.3, 0.7, 1.0])
    nv, nl, phi, r = np.meshgrid(cos, cos, np.array([0.0, 1.0, np.pi]), rough, indexing="ij")
    nv, nl, phi, r = (x.ravel() for x in (nv, nl, phi, r))
    sv, sl = np.sqrt(1 - nv**2), np.sqrt(1 - nl**2)
    v = np.stack([sv, np.zeros_like(sv), nv], -1)
    l = np.stack([sl * np.cos(phi), sl * np.sin(phi), nl], -1)
    n = np.broadcast_to([0.0, 0.0, 1.0], v.shape)
    k = len(r)
    args = [jnp.asarray(x, dtype) for x in (n, v, l, np.full((k, 3), 0.6), np.full(k, 0.5), r)]

    def f(n, v, l, base, metallic, rough):
        m = jp.Material(base_color=base, metallic=metallic, roughness=rough)
        return jp.brdf(n, v, l, m, model=model) * (1e6 * jnp.maximum(jnp.sum(n * l, -1), 0.0))[..., None]

    assert np.isfinite(np.asarray(jax.jit(f)(*args))).all()
    grads = jax.jit(jax.grad(lambda *a: jnp.sum(f(*a)), argnums=tuple(range(6))))(*args)
    for g in grads:
        assert np.isfinite(np.asarray(g)).all()


def test_full_hd_jax_matches_numpy_benchmark_implementation():
    """The 1920x1080 benchmark G-buffer: jitted shade_direct vs the NumPy implementation, float32."""
    g = make_gbuffer(1920, 1080)
    lights = bench_lights()
    m = jp.Material(base_color=g["base_color"], metallic=g["metallic"], roughness=g["roughness"])
    jl = [jp.PointLight(position=x["position"], intensity=np.float32(300.0)) for x in lights]
    out = np.asarray(jax.jit(jp.shade_direct)(g["position"], g["normal"], g["view"], m, jl))
    ref = shade_numpy(g, lights)
    assert out.dtype == np.float32
    # Both float32, same formulas, different operation order: relative error ~ 1e2 ulps at the
    # sharpest highlights (D at r = 0.05 amplifies angle rounding by ~2/alpha).
    np.testing.assert_allclose(out, ref, rtol=1e-4, atol=1e-6)


def _compact_sun_1024():
    from jaxpbr.ibl.envs import sky_with_sun

    return jp.Cubemap.from_function(lambda d: sky_with_sun(d, sun_radiance=5e4, sun_radius_deg=1.0), 1024, supersample=2)


def test_prefilter_quality_at_1024_faces_with_a_compact_sun():
    """Issue 13, item 7: a 1-degree, 5e4-radiance sun at 1024^2 faces (~700 texels) stayed in the
    sampled part with a fixed budget of 256 exact texels: worst level mean 19.8 %, worst texel 130 %
    (512^2: 0.30 % / 0.83 %). With the budget scaled by face area, measured (LOD bias 0): worst
    level mean 0.11 %; within 60 degrees of the sun, every texel of the 64^2 level (r = 0.67, the
    level with the largest errors) within 0.07 %. (The worst texels are elsewhere: see the next
    test.)"""
    from jaxpbr.ibl.cubemap import texel_directions
    from jaxpbr.ibl.measure import brightest_direction, prefilter_error, summarize
    from jaxpbr.ibl.specular import level_roughness, prefilter_reference

    env = _compact_sun_1024()
    pre = jp.prefilter(env)
    assert int(pre.metadata["exact_texels"]) > 256
    worst = summarize(prefilter_error(env, pre))
    assert worst["mean"] < 5e-3, worst
    d = texel_directions(64).reshape(-1, 3)
    near = d[d @ np.asarray(brightest_direction(env)) > np.cos(np.radians(60))]
    ref = prefilter_reference(env, near, float(level_roughness(pre.num_levels)[4]))
    got = np.asarray(pre.levels[4], np.float64).reshape(-1, 3)[d @ np.asarray(brightest_direction(env)) > np.cos(np.radians(60))]
    assert (np.abs(got - ref).max(1) / np.abs(ref).max(1)).max() < 1.5e-2


@pytest.mark.xfail(strict=True, reason="a known defect: at 1024^2 faces under the compact sun, texels of the dark ground "
                   "(elevation -20 to -63 degrees) at r = 0.67 are 4.6 % off the float64 reference, with LOD bias 0 or 1 alike "
                   "(2500 random texels of the 64^2 level; 99th percentile 0.62 % with bias 0, 1.77 % with 1)")
def test_prefilter_worst_texel_at_1024_faces_with_a_compact_sun():
    """The worst texel over 2500 random texels of the 64^2 level (r = 0.67) within 1.5 %."""
    from jaxpbr.ibl.cubemap import texel_directions
    from jaxpbr.ibl.specular import level_roughness, prefilter_reference

    env = _compact_sun_1024()
    pre = jp.prefilter(env)
    d = texel_directions(64).reshape(-1, 3)
    sel = np.random.default_rng(0).choice(len(d), 2500, replace=False)
    ref = prefilter_reference(env, d[sel], float(level_roughness(pre.num_levels)[4]))
    got = np.asarray(pre.levels[4], np.float64).reshape(-1, 3)[sel]
    assert (np.abs(got - ref).max(1) / np.abs(ref).max(1)).max() < 1.5e-2