"""Material pytree and the numerically safe helpers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr._numerics import as_float, cross, dot, safe_normalize, safe_sqrt


def test_material_defaults_are_gltf_and_derived_quantities():
    m = jp.Material()
    np.testing.assert_array_equal(m.base_color, [1, 1, 1])
    assert float(m.metallic) == 1.0 and float(m.roughness) == 1.0 and float(m.occlusion) == 1.0
    np.testing.assert_array_equal(m.emissive, [0, 0, 0])
    m = jp.Material(base_color=(0.5, 0.25, 1.0), metallic=0.5)
    np.testing.assert_allclose(m.f0(), 0.04 * 0.5 + np.array([0.5, 0.25, 1.0]) * 0.5)
    np.testing.assert_allclose(m.diffuse_color(), np.array([0.5, 0.25, 1.0]) * 0.5)


def test_material_is_a_pytree_through_jit_vmap_grad():
    m = jp.Material(base_color=np.full((4, 3), 0.5), metallic=np.linspace(0, 1, 4), roughness=np.full(4, 0.5))
    leaves, tree = jax.tree_util.tree_flatten(m)
    assert len(leaves) == 5
    in_axes = jax.tree_util.tree_unflatten(tree, [0, 0, 0, None, None])  # unflatten skips validation
    out = jax.jit(jax.vmap(lambda mm: mm.f0(), in_axes=(in_axes,)))(m)
    np.testing.assert_allclose(out, m.f0())
    g = jax.grad(lambda mm: jnp.sum(mm.f0()))(m)
    assert isinstance(g, jp.Material)
    np.testing.assert_allclose(g.metallic, 3 * 0.5 - 3 * 0.04)


def test_python_number_inputs_do_not_promote_float32():
    m = jp.Material(base_color=(0.9, 0.6, 0.2), metallic=1, roughness=0.5)
    assert m.base_color.weak_type and m.emissive.weak_type
    assert (m.base_color * jnp.float32(1)).dtype == jnp.float32
    assert as_float([1, 2, 3]).dtype == jnp.result_type(float)  # ints become floats


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(roughness=1.5), "roughness must lie in"),
        (dict(metallic=-0.1), "metallic must lie in"),
        (dict(occlusion=2.0), "occlusion must lie in"),
        (dict(base_color=(1.2, 0.5, 0.5)), "base_color must lie in"),
        (dict(base_color=(0.5, 0.5)), "trailing axis of 3"),
        (dict(emissive=(-1.0, 0.0, 0.0)), "emissive must be >= 0"),
        (dict(roughness=float("nan")), "NaN"),
    ],
)
def test_material_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jp.Material(**kwargs)


def test_material_immutable_and_replace():
    m = jp.Material(roughness=0.3)
    with pytest.raises(AttributeError):
        m.roughness = 0.5
    assert float(m.replace(roughness=0.7).roughness) == 0.7
    with pytest.raises(TypeError, match="no field"):
        m.replace(shininess=2)
    with pytest.raises(ValueError):
        m.replace(roughness=2.0)


def test_traced_material_is_not_validated():
    # Inside jit the values are tracers: construction must not try to read them.
    f = jax.jit(lambda r: jp.Material(roughness=r).roughness * 2)
    assert float(f(0.25)) == 0.5


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_safe_normalize_zero_vector_value_and_gradient(dtype):
    x = jnp.asarray([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [1e-30, 0.0, 0.0]], dtype)
    y = safe_normalize(x)
    np.testing.assert_allclose(y[0], [0.6, 0.8, 0.0], rtol=1e-6)
    np.testing.assert_array_equal(y[1:], 0.0)  # |x| below eps -> zero vector, not NaN
    g = jax.jacfwd(lambda x: safe_normalize(x).sum())(x)
    assert np.isfinite(np.asarray(g)).all()
    g = jax.grad(lambda x: safe_normalize(x).sum())(x)
    assert np.isfinite(np.asarray(g)).all()
    np.testing.assert_array_equal(g[1], 0.0)


def test_safe_sqrt_gradient_at_and_below_zero():
    g = jax.vmap(jax.grad(safe_sqrt))(jnp.asarray([-1.0, 0.0, 4.0]))
    np.testing.assert_allclose(g, [0.0, 0.0, 0.25])
    # The naive masked version is NaN: this is the bug safe_sqrt exists for.
    naive = jax.grad(lambda t: jnp.where(t > 0, jnp.sqrt(t), 0.0))(0.0)
    assert np.isnan(naive)


def test_dot_and_cross_match_numpy():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 5, 4, 3))
    np.testing.assert_allclose(dot(a, b), np.sum(a * b, -1), rtol=1e-12)
    np.testing.assert_allclose(cross(a, b), np.cross(a, b), rtol=1e-12)
