"""The stiff grid (docs/math.md §8): values AND gradients stay finite at every degenerate input.

Every combination of r in {0, 1e-4, 0.045, 1}, NoV in {-0.5, 0, 1e-6, 1}, NoL in {-0.5, 0, 1e-6, 1}
(each with the light on the mirror side and on the same side as the viewer), plus v = -l, a
zero-length normal and radiance 1e6, in float32 and float64, for both models. All configurations
are evaluated in one vectorised call per (model, dtype), so the grid is a single compilation.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp

ROUGHNESS = (0.0, 1e-4, 0.045, 1.0)
COSINES = (-0.5, 0.0, 1e-6, 1.0)
RADIANCE = 1e6


def _dir(mu, phi):
    s = np.sqrt(max(0.0, 1.0 - mu * mu))
    return np.array([s * np.cos(phi), s * np.sin(phi), mu])


def stiff_grid():
    """Rows of (n, v, l, r, label)."""
    rows = []
    n = np.array([0.0, 0.0, 1.0])
    for r, nv, nl in itertools.product(ROUGHNESS, COSINES, COSINES):
        v = _dir(nv, 0.0)
        for phi in (np.pi, 0.0, 0.5):  # mirror side, same side, oblique
            rows.append((n, v, _dir(nl, phi), r, f"r={r} NoV={nv} NoL={nl} phi={phi:.2f}"))
    for r, mu in itertools.product(ROUGHNESS, COSINES):  # v = -l exactly
        v = _dir(mu, 0.3)
        rows.append((n, v, -v, r, f"r={r} v=-l NoV={mu}"))
    for r in ROUGHNESS:  # zero-length normal
        rows.append((np.zeros(3), _dir(0.5, 0.0), _dir(0.5, np.pi), r, f"r={r} n=0"))
        rows.append((n, np.zeros(3), _dir(0.5, np.pi), r, f"r={r} v=0"))
    n_, v_, l_, r_, labels = zip(*rows)
    return np.array(n_), np.array(v_), np.array(l_), np.array(r_), labels


MODEL_OPTIONS = [
    ("gltf", {}),
    ("gltf", {"smith": "separable", "diffuse": "burley"}),
    ("learnopengl", {}),
    ("learnopengl", {"shader_epsilon": 0.0}),
]


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("model,opts", MODEL_OPTIONS)
def test_stiff_grid_values_and_gradients_finite(model, opts, dtype):
    n, v, l, r, labels = stiff_grid()
    k = len(labels)
    args = tuple(jnp.asarray(x, dtype) for x in (n, v, l, np.full((k, 3), 0.7), np.full(k, 0.5), r))

    def radiance(n, v, l, base, metallic, rough):
        m = jp.Material(base_color=base, metallic=metallic, roughness=rough)
        f = jp.brdf(n, v, l, m, model=model, **opts)
        cos = jnp.maximum(jnp.sum(n * l, axis=-1), 0.0)
        return f * (RADIANCE * cos)[..., None]

    value = jax.jit(radiance)(*args)
    assert value.dtype == dtype
    bad = ~np.isfinite(np.asarray(value)).all(-1)
    assert not bad.any(), [labels[i] for i in np.flatnonzero(bad)]
    assert (np.asarray(value) >= 0).all()

    grads = jax.jit(jax.grad(lambda *a: jnp.sum(radiance(*a)), argnums=tuple(range(6))))(*args)
    names = ("n", "v", "l", "base_color", "metallic", "roughness")
    for name, g in zip(names, grads):
        g = np.asarray(g).reshape(k, -1)
        bad = ~np.isfinite(g).all(-1)
        assert not bad.any(), (name, [labels[i] for i in np.flatnonzero(bad)])


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_stiff_values_are_the_right_limits(dtype):
    """Not just finite: below-horizon lanes are exactly 0, v = -l is 0, r < floor equals the floor."""
    n, v, l, r, labels = stiff_grid()
    m = jp.Material(base_color=jnp.full((len(r), 3), 0.7, dtype), metallic=jnp.full(len(r), 0.5, dtype),
                    roughness=jnp.asarray(r, dtype))
    f = np.asarray(jp.brdf(jnp.asarray(n, dtype), jnp.asarray(v, dtype), jnp.asarray(l, dtype), m))
    nv, nl = np.sum(n * v, -1), np.sum(n * l, -1)
    below = (nv <= 0) | (nl <= 0)
    assert np.all(f[below] == 0)
    assert np.all(f[~below] > 0)
    # r = 0 and r = 1e-4 are evaluated at the floor 0.045: identical to r = 0.045 lanes.
    key = [lab.split(" ", 1)[1] for lab in labels]
    at = {(rr, kk): i for i, (rr, kk) in enumerate(zip(r, key))}
    for (rr, kk), i in at.items():
        if rr < jp.MIN_ROUGHNESS:
            np.testing.assert_array_equal(f[i], f[at[(0.045, kk)]])


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_shade_direct_stiff_lights_finite(dtype):
    """shade_direct with a 1e6 lux sun, a 1e6 cd point light sitting ON the surface point and a
    spot light at grazing incidence: values and gradients w.r.t. material, geometry and light
    parameters finite, for surfaces from r = 0 to 1 and grazing/back-facing views."""
    n, v, l, r, labels = stiff_grid()
    k = len(labels)
    p = jnp.zeros((k, 3), dtype)

    def lo(n, v, base, metallic, rough, sun_dir, point_pos, intensity):
        m = jp.Material(base_color=base, metallic=metallic, roughness=rough)
        lights = [
            jp.DirectionalLight(direction=sun_dir, intensity=intensity),
            jp.PointLight(position=point_pos, intensity=intensity),
            jp.SpotLight(position=jnp.asarray([1.0, 0.0, 0.0], dtype), direction=jnp.asarray([-1.0, 0.0, 0.0], dtype),
                         intensity=intensity, inner_cone_angle=0.0, outer_cone_angle=0.5),
        ]
        return jp.shade_direct(p, n, v, m, lights, ambient=0.03)

    args = (
        jnp.asarray(n, dtype), jnp.asarray(v, dtype), jnp.full((k, 3), 0.7, dtype), jnp.full(k, 0.5, dtype),
        jnp.asarray(r, dtype), jnp.asarray([0.0, 0.0, -1.0], dtype), jnp.zeros(3, dtype), jnp.asarray(RADIANCE, dtype),
    )
    value = np.asarray(jax.jit(lo)(*args))
    assert np.isfinite(value).all()
    grads = jax.jit(jax.grad(lambda *a: jnp.sum(lo(*a)), argnums=tuple(range(8))))(*args)
    for i, g in enumerate(grads):
        assert np.isfinite(np.asarray(g)).all(), i
