"""Punctual lights: inverse-square, directional, KHR spot cone and range window, mixed sums,
the unrolled and scanned light loops, ambient/emissive, validation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as ref

import jaxpbr as jp
from jaxpbr.shading.lights import UNROLL_MAX_LIGHTS, light_incidence

N = np.array([0.0, 0.0, 1.0])
V = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
MAT = jp.Material(base_color=(0.8, 0.5, 0.3), metallic=0.3, roughness=0.4)


def _single(light):
    """The one light of a packed LightSet, without the leading light axis."""
    return jax.tree_util.tree_map(lambda x: x[0], jp.pack_lights(light))


def ref_radiance(p, n, v, l, e_perp):
    """Independent: glTF BRDF (tests/reference.py) * E_perp * cos."""
    f = ref.gltf_material(n, v, l, np.array([0.8, 0.5, 0.3]), 0.3, 0.4)
    return f * e_perp * max(np.dot(n, l), 0.0)


def test_point_light_inverse_square():
    pos = np.array([1.0, 2.0, 3.0])
    p = np.array([0.2, -0.1, 0.0])
    out = jp.shade_direct(p, N, V, MAT, jp.PointLight(position=pos, color=(1.0, 0.5, 0.25), intensity=40.0))
    d = pos - p
    e = np.array([1.0, 0.5, 0.25]) * 40.0 / np.dot(d, d)
    np.testing.assert_allclose(out, ref_radiance(p, N, V, d / np.linalg.norm(d), e), rtol=1e-12)


def test_directional_light_uses_minus_direction():
    direction = np.array([-0.3, 0.1, -1.0])
    out = jp.shade_direct(np.zeros(3), N, V, MAT, jp.DirectionalLight(direction=direction, intensity=3.0))
    l = -direction / np.linalg.norm(direction)
    np.testing.assert_allclose(out, ref_radiance(0, N, V, l, 3.0 * np.ones(3)), rtol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 0.2, 0.35, 0.45, 0.6])
def test_spot_cone_khr_falloff(angle):
    inner, outer = 0.3, 0.5
    pos = np.array([0.0, 0.0, 2.0])
    axis = np.array([np.sin(angle), 0.0, -np.cos(angle)])  # aim the cone `angle` away from p = 0
    light = jp.SpotLight(position=pos, direction=axis, intensity=8.0, inner_cone_angle=inner, outer_cone_angle=outer)
    _, e = light_incidence(_single(light), jnp.zeros(3))
    scale = 1.0 / max(1e-3, math.cos(inner) - math.cos(outer))
    t = min(max(math.cos(angle) * scale - math.cos(outer) * scale, 0.0), 1.0)
    np.testing.assert_allclose(e, 8.0 / 4.0 * t * t * np.ones(3), rtol=1e-12)
    if angle <= inner:
        np.testing.assert_allclose(e, 2.0, rtol=1e-12)
    if angle >= outer:
        assert np.all(np.asarray(e) == 0)


@pytest.mark.parametrize("dist", [0.5, 1.5, 2.9, 3.0, 4.0])
def test_range_window(dist):
    light = jp.PointLight(position=(0.0, 0.0, dist), intensity=1.0, range=3.0)
    _, e = light_incidence(_single(light), jnp.zeros(3))
    window = min(max(1 - (dist / 3.0) ** 4, 0.0), 1.0) ** 2
    np.testing.assert_allclose(e, window / dist**2 * np.ones(3), rtol=1e-12, atol=1e-300)


def _mixed_lights(k):
    rng = np.random.default_rng(k)
    out = []
    for i in range(k):
        kind = i % 3
        pos = rng.uniform(-3, 3, 3) + np.array([0, 0, 4.0])
        if kind == 0:
            out.append(jp.PointLight(position=pos, color=rng.uniform(0, 1, 3), intensity=rng.uniform(1, 50)))
        elif kind == 1:
            out.append(jp.DirectionalLight(direction=-pos, color=rng.uniform(0, 1, 3), intensity=rng.uniform(1, 5)))
        else:
            out.append(jp.SpotLight(position=pos, direction=-pos, color=rng.uniform(0, 1, 3), intensity=20.0,
                                    inner_cone_angle=0.1, outer_cone_angle=0.7, range=20.0))
    return out


@pytest.mark.parametrize("k", [3, UNROLL_MAX_LIGHTS + 5])  # unrolled and lax.scan paths
def test_mixed_lights_equal_sum_of_single_lights(k):
    lights = _mixed_lights(k)
    rng = np.random.default_rng(1)
    p = rng.uniform(-1, 1, (4, 5, 3)) * np.array([1, 1, 0])
    n = np.broadcast_to(N, p.shape)
    v = np.broadcast_to(V, p.shape)
    together = jax.jit(lambda ls: jp.shade_direct(p, n, v, MAT, ls))(lights)
    separately = sum(np.asarray(jp.shade_direct(p, n, v, MAT, light)) for light in lights)
    np.testing.assert_allclose(together, separately, rtol=1e-12, atol=1e-14)
    assert together.shape == (4, 5, 3)


def test_stacked_light_batch_and_vmap():
    """A PointLight with stacked leaves is many lights; vmap over a batch of light positions."""
    pos = np.array([[1.0, 0, 2], [-1, 0.5, 3], [0, -1, 1.5]])
    stacked = jp.PointLight(position=pos, intensity=np.array([1.0, 2.0, 3.0]))
    singles = [jp.PointLight(position=pos[i], intensity=float(i + 1)) for i in range(3)]
    p = np.zeros(3)
    np.testing.assert_allclose(jp.shade_direct(p, N, V, MAT, stacked), jp.shade_direct(p, N, V, MAT, singles), rtol=1e-12)
    per_light = jax.vmap(lambda q: jp.shade_direct(p, N, V, MAT, jp.PointLight(position=q, intensity=1.0)))(pos)
    for i in range(3):
        np.testing.assert_allclose(per_light[i], jp.shade_direct(p, N, V, MAT, jp.PointLight(position=pos[i])), rtol=1e-12)


def test_ambient_occlusion_emissive_and_light_below_horizon():
    m = jp.Material(base_color=(0.5, 0.4, 0.3), metallic=0.0, roughness=0.5, occlusion=0.25, emissive=(1.0, 2.0, 3.0))
    below = jp.DirectionalLight(direction=(0.0, 0.0, 1.0), intensity=100.0)  # travels up: light is below
    out = jp.shade_direct(np.zeros(3), N, V, m, below, ambient=0.03)
    np.testing.assert_allclose(out, 0.03 * np.array([0.5, 0.4, 0.3]) * 0.25 + np.array([1.0, 2.0, 3.0]), rtol=1e-12)


def test_learnopengl_model_through_shade_direct():
    pos = np.array([10.0, 10.0, 10.0])
    p = np.array([0.0, 0.0, 1.0])
    out = jp.shade_direct(p, N, V, MAT, jp.PointLight(position=pos, intensity=300.0), model="learnopengl")
    d = pos - p
    l = d / np.linalg.norm(d)
    f = ref.learnopengl_pbr_fs(N, V, l, np.array([0.8, 0.5, 0.3]), 0.3, 0.4)
    np.testing.assert_allclose(out, f * 300.0 / np.dot(d, d) * np.dot(N, l), rtol=1e-12)


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: jp.SpotLight(position=(0, 0, 1.0), direction=(0, 0, -1.0), inner_cone_angle=0.5, outer_cone_angle=0.4), "inner_cone_angle"),
        (lambda: jp.SpotLight(position=(0, 0, 1.0), direction=(0, 0, -1.0), outer_cone_angle=2.0), "outer_cone_angle"),
        (lambda: jp.PointLight(position=(0, 0, 1.0), intensity=-1.0), "intensity"),
        (lambda: jp.PointLight(position=(0, 1.0)), "trailing axis of 3"),
        (lambda: jp.PointLight(position=(0, 0, np.nan)), "NaN"),
        (lambda: jp.PointLight(position=(0, 0, 1.0), range=-2.0), "range"),
        (lambda: jp.PointLight(position=(0, 0, 1.0), range=0.0), "range must be > 0"),
        (lambda: jp.DirectionalLight(direction=(0, 0, 0.0)), "non-zero"),
        (lambda: jp.pack_lights([]), "empty"),
    ],
)
def test_bad_lights_raise(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_bad_light_type_and_option():
    with pytest.raises(TypeError, match="PointLight"):
        jp.pack_lights([object()])
    with pytest.raises(TypeError, match="unknown option"):
        jp.shade_direct(np.zeros(3), N, V, MAT, jp.PointLight(position=(0, 0, 1.0)), shininess=3)
    with pytest.raises(ValueError, match="model"):
        jp.shade_direct(np.zeros(3), N, V, MAT, jp.PointLight(position=(0, 0, 1.0)), model="phong")


def test_float32_preserved_and_jit_equals_nojit():
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    m = jp.Material(base_color=f32([0.8, 0.5, 0.3]), metallic=f32(0.3), roughness=f32(0.4))
    lights = [jp.PointLight(position=f32([1, 2, 3]), color=f32([1, 1, 1]), intensity=f32(30))]
    args = (f32(np.zeros(3)), f32(N), f32(V))
    eager = jp.shade_direct(*args, m, lights)
    jitted = jax.jit(lambda *a: jp.shade_direct(*a, m, lights))(*args)
    assert eager.dtype == jitted.dtype == jnp.float32
    np.testing.assert_allclose(eager, jitted, rtol=1e-6)


def test_infinite_range_equals_no_range():
    p = np.array([0.1, 0.2, 0.0])
    a = jp.shade_direct(p, N, V, MAT, jp.PointLight(position=(0.0, 1.0, 5.0), intensity=10.0, range=np.inf))
    b = jp.shade_direct(p, N, V, MAT, jp.PointLight(position=(0.0, 1.0, 5.0), intensity=10.0))
    np.testing.assert_array_equal(a, b)
    assert np.all(np.asarray(a) > 0)


# ------------------------------------------------------------------------------------------
# cap_irradiance: the cosine-weighted solid angle of a disc light (issue 11, groundwork)
# ------------------------------------------------------------------------------------------


def _cap_brute(theta, sigma):
    """integral over the cap of max(n.w, 0) dw by scipy quadrature in the cap's own polar
    coordinates (n = z, cap centre at polar angle theta): no horizon geometry is used."""
    from scipy import integrate

    c = np.array([math.sin(theta), 0.0, math.cos(theta)])
    u = np.array([math.cos(theta), 0.0, -math.sin(theta)])
    v = np.array([0.0, 1.0, 0.0])

    def f(b, a):
        w = math.cos(a) * c + math.sin(a) * (math.cos(b) * u + math.sin(b) * v)
        return max(w[2], 0.0) * math.sin(a)

    return integrate.dblquad(f, 0.0, sigma, 0.0, 2.0 * math.pi, epsabs=1e-12 * sigma * sigma, epsrel=1e-9)[0]


@pytest.mark.parametrize("sigma", [2e-3, 0.3, 1.4])
def test_cap_irradiance_against_quadrature(sigma):
    """Above, straddling and below the horizon, against 2-D quadrature over the cap; measured
    within 5e-8 of pi sin^2 sigma (the quadrature's own accuracy at the horizon kink) over 7
    radii x 37 angles; here 3 radii x 8 angles (the quadrature is slow)."""
    with jax.enable_x64(True):
        h = math.pi / 2
        thetas = np.array([0.0, 0.7, h - sigma / 2, h - sigma / 5, h, h + sigma / 3, h + 0.9 * sigma, 2.5])
        got = np.asarray(jp.shading.lights.cap_irradiance(np.cos(thetas), math.sin(sigma)))
        expect = np.array([_cap_brute(t, sigma) for t in thetas])
        np.testing.assert_allclose(got, expect, rtol=0, atol=1e-6 * math.pi * math.sin(sigma) ** 2)


def test_cap_irradiance_closed_form_limits():
    with jax.enable_x64(True):
        c = np.linspace(-1.0, 1.0, 41)
        # a hemisphere of directions (sigma = pi/2) centred at angle theta: pi (1 + cos theta) / 2
        np.testing.assert_allclose(jp.shading.lights.cap_irradiance(c, 1.0), math.pi * (1 + c) / 2, atol=1e-12)
        # fully above the horizon: pi sin^2 sigma cos theta; fully below: 0
        s = math.sin(0.2)
        above, below = c[c > math.sin(0.2) + 1e-9], c[c < -math.sin(0.2) - 1e-9]
        np.testing.assert_allclose(jp.shading.lights.cap_irradiance(above, s), math.pi * s * s * above, rtol=1e-14)
        assert np.all(np.asarray(jp.shading.lights.cap_irradiance(below, s)) == 0.0)
        # continuous where the cap touches the horizon (cos theta = +-sin sigma)
        for edge in (s, -s):
            lo, hi = jp.shading.lights.cap_irradiance(np.array([edge - 1e-9, edge + 1e-9]), s)
            assert abs(float(hi) - float(lo)) < 1e-8 * math.pi * s * s


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_cap_irradiance_values_and_gradients_finite_on_stiff_inputs(dtype):
    """Theta at the straddling boundaries (cos theta = +-sin sigma exactly), at 0, pi/2, pi, and
    sigma = 0, tiny, pi/2: finite values and gradients with respect to both arguments."""
    with jax.enable_x64(dtype == jnp.float64):
        s = np.array([0.0, 1e-6, 1e-3, math.sin(0.3), 0.9999, 1.0])
        c = np.unique(np.concatenate([[-1.0, -0.5, 0.0, 0.5, 1.0], s, -s]))
        C, S = (jnp.asarray(a, dtype) for a in np.meshgrid(c, s, indexing="ij"))
        val = jp.shading.lights.cap_irradiance(C, S)
        gc, gs = jax.vmap(jax.vmap(jax.grad(jp.shading.lights.cap_irradiance, argnums=(0, 1))))(C, S)
        for a in (val, gc, gs):
            assert np.all(np.isfinite(np.asarray(a)))
        assert np.all(np.asarray(val) >= 0)


def test_cap_irradiance_gradient_matches_finite_differences():
    """Inside each piece (above, straddling), d/dcos and d/dsin against central differences."""
    from gradcheck import check_partials

    with jax.enable_x64(True):
        for c0, s0 in [(0.8, 0.3), (0.1, 0.3), (-0.2, 0.5), (0.0, 0.05)]:
            x = np.array([c0, s0])
            check_partials(lambda v: jp.shading.lights.cap_irradiance(v[0], v[1]), x, [0, 1], step=1e-6, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("count", [3, UNROLL_MAX_LIGHTS + 3], ids=["unrolled", "scanned"])
def test_visibility_per_light_and_per_channel_weights_each_lights_term(count):
    """shade_direct is linear in the lights: with visibility (..., L) it is sum_i w_i x (light i
    alone), with (..., L, 3) sum_i w_ic x (light i alone) per channel c -- point and disc lights
    mixed (two groups in packed order), unrolled and scanned."""
    rng = np.random.default_rng(7)
    P = 5
    n = rng.normal(size=(P, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    v = n + 0.4 * rng.normal(size=(P, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    p = rng.normal(size=(P, 3)) * 0.2
    lights = []
    for i in range(count):
        if i % 3 == 2:
            lights.append(jp.DirectionalLight(direction=tuple(-rng.uniform(0.2, 1.0, 3)), intensity=2.0, angular_radius=0.05))
        else:
            lights.append(jp.PointLight(tuple(rng.normal(size=3) * 3 + np.array([0, 0, 4.0])), intensity=5.0))
    m = jp.Material(base_color=(0.7, 0.4, 0.2), metallic=0.3, roughness=0.5)
    alone = np.stack([np.asarray(jp.shade_direct(p, n, v, m, [lt])) for lt in lights], 1)  # (P, L, 3)
    w1 = rng.uniform(0, 1, (P, count))
    w3 = rng.uniform(0, 1, (P, count, 3))
    got1 = np.asarray(jp.shade_direct(p, n, v, m, lights, visibility=w1))
    got3 = np.asarray(jp.shade_direct(p, n, v, m, lights, visibility=w3))
    np.testing.assert_allclose(got1, np.sum(w1[..., None] * alone, 1), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(got3, np.sum(w3 * alone, 1), rtol=1e-5, atol=1e-7)
