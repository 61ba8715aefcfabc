"""The Charlie-prefiltered sheen chain (`jaxpbr.ibl.sheen_prefilter`): normalisation, an independent
oracle for a linear environment, agreement with the float64 reference, stiff inputs, metadata,
gradients of the lookup, HIGHEST-precision matmuls."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

from jaxpbr.ibl import envs
from jaxpbr.ibl.cubemap import Cubemap, texel_directions
from jaxpbr.ibl.sheen_prefilter import (
    _charlie_rows,
    _reference_sum,
    charlie_level_roughness,
    charlie_lookup,
    charlie_mean_cosine,
    charlie_reference,
    charlie_roughness_to_lod,
    prefilter_charlie,
)
from jaxpbr.shading.brdf_terms import MIN_ROUGHNESS
from tests.test_precision import not_highest

G = np.array([0.3, -0.5, 0.4])


def quad_mean_cosine(alpha: float) -> float:
    """k(alpha) = int w c dl / int w dl with w = D_charlie(h) (R.l)+ by 1-D float64 quadrature over
    c = R.l (dl = dc dphi), D written from its definition: sin^2(theta_h) = (1 - c)/2."""
    d = lambda c: (2.0 + 1.0 / alpha) * ((1.0 - c) / 2.0) ** (0.5 / alpha) / (2.0 * math.pi)
    pts = [p for p in (alpha, 2 * alpha, 4 * alpha, 8 * alpha, 16 * alpha) if p < 1.0]
    m = lambda p: integrate.quad(lambda c: d(c) * c**p, 0.0, 1.0, points=pts, epsabs=0, epsrel=1e-12, limit=500)[0]
    return m(2) / m(1)


def linear_env(S, dtype=jnp.float64):
    return Cubemap(jnp.asarray((1.0 + texel_directions(S) @ G)[..., None], dtype))


@pytest.fixture(scope="module")
def lin_pre():
    return prefilter_charlie(linear_env(32), size=16, source_size=32, num_levels=5)


@pytest.mark.parametrize("alpha", [MIN_ROUGHNESS**2, 0.01, 0.0625, 0.25, 0.5625, 1.0])
def test_mean_cosine_closed_form_matches_quadrature(alpha):
    assert charlie_mean_cosine(alpha) == pytest.approx(quad_mean_cosine(alpha), rel=1e-9)


@pytest.mark.parametrize("method,zl", [("zonal", 1), ("zonal", 4), ("box", 1)])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_constant_environment_is_reproduced_at_every_level(dtype, method, zl):
    env = Cubemap(jnp.full((6, 16, 16, 3), 2.5, dtype))
    pre = prefilter_charlie(env, size=8, num_levels=4, method=method, zonal_levels=zl)
    assert pre.dtype == dtype and pre.num_levels == 4
    tol = 32 * float(jnp.finfo(dtype).eps)  # a ratio of two sums over 1536 texels
    for lv in pre.levels:
        np.testing.assert_allclose(np.asarray(lv), 2.5, rtol=tol)


def test_linear_environment_gives_the_mean_cosine_oracle(lin_pre):
    """L = 1 + g.l -> LD_c = 1 + k(alpha) g.R, k by 1-D quadrature (not the module's closed form).
    Measured max |error|: 1.6e-3 at level 0 (r at the floor, the ring 0.23 deg wide on 2.8 deg
    source texels), 4.2e-4 at level 1, <= 2.7e-4 above."""
    bounds = [3e-3, 8e-4, 5e-4, 5e-4, 5e-4]
    for m, (lv, r) in enumerate(zip(lin_pre.levels, charlie_level_roughness(5))):
        R = texel_directions(lv.shape[1])
        want = 1.0 + quad_mean_cosine(max(r, MIN_ROUGHNESS) ** 2) * (R @ G)
        assert np.abs(np.asarray(lv[..., 0]) - want).max() < bounds[m], m


def test_linear_environment_all_levels_zonal():
    """Every level by the zonal method (rings, pyramid lookups): mass and mean cosine exact per
    ring, what is left is the pyramid's averaging of a linear function at coarse levels. Measured
    max |error| 1.5e-4, 4.2e-4, 2.7e-4, 1.8e-4, 1.4e-4 (float64, 32^2 source, 16 rings)."""
    pre = prefilter_charlie(linear_env(32), size=16, num_levels=5, zonal_levels=5, rings=16)
    assert pre.metadata["prefilter_method"] == "charlie_zonal"
    for m, (lv, r) in enumerate(zip(pre.levels, charlie_level_roughness(5))):
        R = texel_directions(lv.shape[1])
        want = 1.0 + charlie_mean_cosine(max(r, MIN_ROUGHNESS) ** 2) * (R @ G)
        assert np.abs(np.asarray(lv[..., 0]) - want).max() < 1e-3, m


def test_linear_environment_lookup_between_levels():
    """The "mean_cosine" blend is exact between levels for a linear environment; what is left is
    the bilinear lookup in the coarse faces (32, 16, 8). Measured max |error| 4.1e-3."""
    lin_pre = prefilter_charlie(linear_env(32), size=32, source_size=32, num_levels=3)
    rng = np.random.default_rng(1)
    R = rng.normal(size=(64, 3))
    R /= np.linalg.norm(R, axis=1, keepdims=True)
    r = rng.uniform(0.0, 1.0, 64)
    got = np.asarray(charlie_lookup(lin_pre, R, r))[:, 0]
    want = 1.0 + np.array([quad_mean_cosine(max(x, MIN_ROUGHNESS) ** 2) for x in r]) * (R @ G)
    assert np.abs(got - want).max() < 6e-3


def test_reference_on_linear_environment():
    rng = np.random.default_rng(2)
    R = rng.normal(size=(6, 3))
    R /= np.linalg.norm(R, axis=1, keepdims=True)
    env = linear_env(16)
    for r in (0.0, 0.3, 1.0):
        got = charlie_reference(env, R, r)[:, 0]
        want = 1.0 + quad_mean_cosine(max(r, MIN_ROUGHNESS) ** 2) * (R @ G)
        assert np.abs(got - want).max() < 1e-3


def test_fast_matches_reference_on_a_soft_sky():
    """A sky with a soft sun (15 deg, 20 radiance) at 32^2, the default chain (16^2, 3 levels: level 0
    zonal from the 32^2 level, the others box over all of it), at the levels' roughnesses 0 and 0.5
    vs the float64 reference. Measured max / mean relative error: 5.2 % / 0.73 % at r = 0 (16^2
    face; the box method: 6.3 % / 0.66 %), 22.7 % / 2.5 % at r = 0.5 (8^2 face).
    (A hard 2-degree 3000 sun is not representable at these sizes at low sheen roughness: see
    the module docstring.)"""
    sky = envs.sky_with_sun_cubemap(32, dtype=jnp.float64, sun_radius_deg=15.0, sun_radiance=20.0)
    pre = prefilter_charlie(sky, size=16, source_size=32, num_levels=3)
    rng = np.random.default_rng(1)
    rng.normal(size=(64, 3)), rng.uniform(0.0, 1.0, 64)
    R = rng.normal(size=(24, 3))
    R /= np.linalg.norm(R, axis=1, keepdims=True)
    for r, (emax, emean) in ((0.0, (0.08, 0.011)), (0.5, (0.3, 0.035))):
        ref = charlie_reference(sky, R, r)
        e = np.abs(np.asarray(charlie_lookup(pre, R, r)) - ref) / ref
        assert e.max() < emax and e.mean() < emean, (r, e.max(), e.mean())


@pytest.mark.parametrize("zl", [1, 4])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_finite_with_a_huge_sun_at_the_floor(dtype, zl):
    lv = np.full((6, 16, 16, 3), 0.5)
    lv[4, 7:9, 7:9] = 1e5
    pre = prefilter_charlie(Cubemap(jnp.asarray(lv, dtype)), size=8, num_levels=4, min_roughness=MIN_ROUGHNESS, zonal_levels=zl)
    for x in pre.levels:
        x = np.asarray(x)
        assert x.dtype == dtype and np.isfinite(x).all() and (x > 0.49).all() and (x < 1e5).all()
    # The floor itself and below it: the same level 0.
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    a = charlie_lookup(pre, R, 0.0)
    b = charlie_lookup(pre, R, MIN_ROUGHNESS)
    assert np.isfinite(np.asarray(a)).all()
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_metadata(lin_pre):
    meta = lin_pre.metadata
    for key in ("distribution", "roughness_mapping", "mapping_levels", "level_roughness", "min_roughness", "lod_blend",
                "lod_formula", "level_mean_cosine", "level_alpha", "lod_table", "source_face_size", "chain_floor"):
        assert key in meta, key
    assert meta["distribution"] == "charlie" and meta["mapping_levels"] == "5" and meta["source_face_size"] == "32"
    assert meta["chain_floor"] == "1"
    k = np.array([float(x) for x in meta["level_mean_cosine"].split(",")])
    np.testing.assert_allclose(k, charlie_mean_cosine(np.maximum(charlie_level_roughness(5), MIN_ROUGHNESS) ** 2))


def test_lod_mapping():
    r = np.linspace(0.0, 1.0, 101)
    lod = charlie_roughness_to_lod(r, 5, xp=np)
    assert lod[0] == 0.0 and lod[-1] == 4.0 and np.all(np.diff(lod) >= 0)
    np.testing.assert_allclose(charlie_roughness_to_lod(charlie_level_roughness(5), 5, xp=np), np.arange(5), atol=1e-12)
    assert np.all(lod[r <= MIN_ROUGHNESS] == 0.0)
    np.testing.assert_allclose(charlie_roughness_to_lod(r, 5, lod_blend="roughness", xp=np), 4 * r)


def test_lookup_gradients_are_finite(lin_pre):
    pre = Cubemap([lv.astype(jnp.float32) for lv in lin_pre.levels], lin_pre.info)

    def f(d, r):
        return jnp.sum(charlie_lookup(pre, d, r))

    g = jax.jit(jax.grad(f, argnums=(0, 1)))
    for r in (0.0, MIN_ROUGHNESS, 0.25, 0.6, 1.0):
        for d in ([0.3, 0.8, -0.5], [1.0, 0.0, 0.0], [0.577, 0.577, 0.577]):
            gd, gr = g(jnp.asarray(d, jnp.float32), jnp.float32(r))
            assert np.isfinite(np.asarray(gd)).all() and np.isfinite(float(gr))
    # vmap over roughness, and the derivative in r is non-zero between levels
    rs = jnp.linspace(0.1, 0.9, 5, dtype=jnp.float32)
    grs = jax.vmap(lambda r: jax.grad(f, 1)(jnp.asarray([0.3, 0.8, -0.5], jnp.float32), r))(rs)
    assert np.isfinite(np.asarray(grs)).all() and np.all(np.abs(np.asarray(grs)) > 0)


def test_matmuls_are_highest():
    env = envs.sky_with_sun_cubemap(8)
    for zl in (1, 3):
        n, bad = not_highest(lambda lv: prefilter_charlie(Cubemap([lv]), size=4, num_levels=3, zonal_levels=zl).levels, env.levels[0])
        assert n > 0 and not bad, bad[:3]
    with jax.enable_x64(True):
        from jaxpbr.ibl.cubemap import _subtexel_coords, texel_solid_angles

        L = jnp.ones((6, 4, 4, 3))
        c = jax.device_put(_subtexel_coords(4, 2))
        om = jax.device_put(texel_solid_angles(4)[0])
        n, bad = not_highest(lambda R: _reference_sum(R, L, c, c, om, 0.3, q=2, rows=2, chunk=2), jnp.ones((2, 3)) / 3**0.5)
    assert n > 0 and not bad, bad[:3]
    assert _charlie_rows is not None
