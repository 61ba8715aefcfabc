"""Every matmul / einsum / dot jaxpbr traces asks for HIGHEST precision (issue 10, item 4).

XLA on NVIDIA GPUs runs default-precision float32 matmuls in TF32 (a 10-bit mantissa): measured
3.8e-4 relative errors in the irradiance on an H100. The CPU computes them exactly either way, so
the only check that holds here is structural: walk the jaxprs of the precomputes and the renderer
(into every nested jit, scan, remat, cond) and fail on any `dot_general` whose precision is not
HIGHEST on both operands.
"""

from __future__ import annotations

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.ibl import diffuse, reference_render, specular
from jaxpbr.shading.lut import compute_brdf_lut

HIGHEST = jax.lax.Precision.HIGHEST


def _sub_jaxprs(value):
    if isinstance(value, jax.extend.core.ClosedJaxpr):
        yield value.jaxpr
    elif isinstance(value, jax.extend.core.Jaxpr):
        yield value
    elif isinstance(value, (tuple, list)):
        for v in value:
            yield from _sub_jaxprs(v)


def dot_generals(jaxpr):
    """Every dot_general equation in jaxpr and in the jaxprs nested in its equations' parameters."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            yield eqn
        for value in eqn.params.values():
            for sub in _sub_jaxprs(value):
                yield from dot_generals(sub)


def _is_highest(eqn) -> bool:
    p = eqn.params.get("precision")
    if p is None:
        return False
    if isinstance(p, tuple):
        return all(x == HIGHEST for x in p)
    return p == HIGHEST


def not_highest(fn, *args):
    """(number of dot_generals, the ones without HIGHEST precision) traced by fn(*args)."""
    jaxpr = jax.make_jaxpr(fn)(*args).jaxpr
    dots = list(dot_generals(jaxpr))
    return len(dots), [str(e) for e in dots if not _is_highest(e)]


def test_the_walk_finds_a_default_precision_matmul_inside_nested_programs():
    """The check can fail: a default-precision matmul inside a jit inside a scan is found."""
    inner = jax.jit(lambda a, b: a @ b)

    def fn(a, b):
        return jax.lax.scan(lambda c, x: (c + inner(x, b), None), jnp.zeros((2, 2)), a)[0]

    n, bad = not_highest(fn, jnp.ones((3, 2, 2)), jnp.ones((2, 2)))
    assert n == 1 and len(bad) == 1
    good = jax.jit(lambda a, b: jnp.matmul(a, b, precision=HIGHEST))
    n, bad = not_highest(good, jnp.ones((2, 2)), jnp.ones((2, 2)))
    assert n == 1 and not bad


@pytest.fixture(scope="module")
def env():
    return jp.envs.sky_with_sun_cubemap(16)


@pytest.mark.parametrize("method", ["exact", "sh9"])
def test_irradiance(env, method):
    n, bad = not_highest(lambda lv: diffuse.irradiance(jp.Cubemap([lv]), size=8, method=method).levels[0], env.levels[0])
    assert n > 0 and not bad, bad[:3]


def test_prefilter(env):
    """Traced in the texels (the bright-texel split is then the fixed-size candidate set)."""
    n, bad = not_highest(lambda lv: specular.prefilter(jp.Cubemap([lv])).levels, env.levels[0])
    assert n > 0 and not bad, bad[:3]


def test_prefilter_reference(env):
    dirs = np.asarray([[0.0, 1.0, 0.0], [0.6, 0.0, 0.8]])
    # The reference converts to NumPy at the end; walk its summation program.
    with jax.enable_x64(True):
        from jaxpbr.ibl.cubemap import _subtexel_coords, texel_solid_angles

        L = jnp.ones((6, 4, 4, 3))
        c = jax.device_put(_subtexel_coords(4, 2))
        om = jax.device_put(texel_solid_angles(4)[0])
        n, bad = not_highest(lambda R: specular._reference_sum(R, L, c, c, om, 0.3, q=2, rows=2, chunk=2), jnp.asarray(dirs))
    assert n > 0 and not bad, bad[:3]


def test_lut():
    n, bad = not_highest(lambda: compute_brdf_lut(size=8))
    assert not bad, bad[:3]


def test_render_and_bake(env):
    scene = jp.Scene(
        camera=jp.Camera(position=(0.0, 0.0, 3.2), width=8, height=8),
        objects=[jp.Sphere(material=jp.Material(base_color=(0.8, 0.5, 0.3), metallic=0.5, roughness=0.4))],
        lights=[jp.PointLight(position=(3.0, 3.0, 3.0), intensity=20.0)],
        environment=jp.Environment(radiance=env),
    )

    def fn(lv, r):
        e = scene.environment.replace(radiance=jp.Cubemap([lv]))
        m = scene.objects[0].material.replace(roughness=r)
        s = scene.replace(environment=e, objects=[scene.objects[0].replace(material=m)])
        return jp.render(s), jp.bake(e).prefiltered.levels

    n, bad = not_highest(fn, env.levels[0], 0.4)
    assert n > 0 and not bad, bad[:3]
    # The differentiated program (what fit_material compiles) as well.
    n, bad = not_highest(jax.grad(lambda lv, r: jnp.sum(fn(lv, r)[0]), argnums=(0, 1)), env.levels[0], 0.4)
    assert n > 0 and not bad, bad[:3]


def test_reference_render(env, monkeypatch):
    """The float64 brute-force reference: its per-chunk program, with the arguments of a real call."""
    real = reference_render._terms_chunk
    seen = []

    def spy(*args, **kw):
        seen.append(not_highest(lambda *a: real(*a, **kw), *args))
        return real(*args, **kw)

    monkeypatch.setattr(reference_render, "_terms_chunk", spy)
    with jax.enable_x64(True):
        reference_render.reference_ibl_terms([[0.0, 0.0, 1.0]], [[0.0, 0.6, 0.8]], 0.4, env)
    assert seen and all(n > 0 and not bad for n, bad in seen), seen[0][1][:3]
