"""Bad values through the public API (issue 23, item 4): every public function that takes an
environment Cubemap, and `render_batch`'s environment parameters, refuse a concrete NaN, +Inf or
negative value with the message `Environment` gives (instead of NaN texels, a silently dropped
texel or negative radiance); traced values (jit / vmap / grad) are not checked and keep working.

Inputs are tiny (8^2 faces, few samples) so that the file runs in seconds.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.ibl.extract import extract_lights
from jaxpbr.ibl.sheen_prefilter import charlie_reference, prefilter_charlie

S = 8
BAD = {"nan": np.nan, "inf": np.inf, "negative": -1000.0}
DIRS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])


def level(bad=None, *, value=0.5):
    a = np.full((6, S, S, 3), value, np.float32)
    a[0, 2, 5] = (1.0, 2.0, 3.0)  # not flat (a gradient of a constant map would test little)
    if bad is not None:
        a[2, 3, 4, 1] = bad
    return jnp.asarray(a)


def cube(bad=None):
    return jp.Cubemap((level(bad),))


#: name -> (concrete call on a Cubemap, the level the message names)
CUBE_FUNCTIONS = {
    "prefilter": lambda c: jp.prefilter(c, num_levels=2, samples=16),
    "prefilter(method='reference')": lambda c: jp.prefilter(c, num_levels=2, method="reference"),
    "prefilter_reference": lambda c: jp.prefilter_reference(c, DIRS, 0.5, supersample=1),
    "irradiance": lambda c: jp.irradiance(c, size=4),
    "irradiance(method='sh9')": lambda c: jp.irradiance(c, size=4, method="sh9"),
    "diffuse.irradiance_at": lambda c: jp.ibl.diffuse.irradiance_at(c, DIRS),
    "sh9_project": lambda c: jp.sh9_project(c),
    "prefilter_charlie": lambda c: prefilter_charlie(c, size=S, num_levels=2),
    "charlie_reference": lambda c: charlie_reference(c, DIRS, 0.5, supersample=1),
    "extract_lights": lambda c: extract_lights(c),
}


def environment_message(kind: str) -> str:
    """What `Environment` says about the same texel, without the name it puts first."""
    with pytest.raises(ValueError) as e:
        jp.Environment(radiance=cube(BAD[kind]))
    msg = str(e.value)
    assert msg.startswith("Environment.radiance.levels[0] has 1 ")
    return msg[len("Environment.radiance.levels[0]"):]


@pytest.mark.parametrize("kind", list(BAD))
@pytest.mark.parametrize("name", list(CUBE_FUNCTIONS))
def test_cube_functions_refuse_bad_texels_like_environment(name, kind):
    expected = environment_message(kind)
    with pytest.raises(ValueError) as e:
        CUBE_FUNCTIONS[name](cube(BAD[kind]))
    msg = str(e.value)
    assert msg.endswith(expected), msg
    assert "levels[0]" in msg  # names the level, as Environment does
    if kind == "negative":
        assert "radiance cannot be negative" in msg and "min -1000" in msg
    else:
        assert "radiance must be finite" in msg


@pytest.mark.parametrize("name", list(CUBE_FUNCTIONS))
def test_cube_functions_accept_good_texels(name):
    out = CUBE_FUNCTIONS[name](cube())
    leaves = out.levels if isinstance(out, jp.Cubemap) else jax.tree_util.tree_leaves(out)
    assert all(np.isfinite(np.asarray(x)).all() for x in leaves if hasattr(x, "dtype"))


def test_bad_texel_in_a_mip_level_is_refused():
    """Every level of the Cubemap is radiance (as Environment checks): a bad mip is named."""
    good = cube().with_mips(2)
    lv1 = np.asarray(good.levels[1]).copy()
    lv1[1, 0, 0, 0] = np.nan
    bad = jp.Cubemap((good.levels[0], jnp.asarray(lv1)))
    with pytest.raises(ValueError, match=re.escape("levels[1] has 1 NaN/Inf values")):
        jp.sh9_project(bad)


def test_zero_texels_are_accepted():
    """Zero radiance is valid (the check is >= 0, not > 0)."""
    c = jp.Cubemap((jnp.zeros((6, S, S, 3), jnp.float32),))
    assert float(jnp.abs(jp.sh9_project(c)).max()) == 0.0


# ---- traced values are not checked, and the functions still trace ----------------------------


TRACEABLE = {
    "prefilter": lambda lv: jp.prefilter(jp.Cubemap((lv,)), num_levels=2, samples=16).levels[1],
    "irradiance": lambda lv: jp.irradiance(jp.Cubemap((lv,)), size=4).levels[0],
    "irradiance(method='sh9')": lambda lv: jp.irradiance(jp.Cubemap((lv,)), size=4, method="sh9").levels[0],
    "sh9_project": lambda lv: jp.sh9_project(jp.Cubemap((lv,))),
    "prefilter_charlie": lambda lv: prefilter_charlie(jp.Cubemap((lv,)), size=S, num_levels=2).levels[1],
}


@pytest.mark.parametrize("name", list(TRACEABLE))
def test_traced_jit_and_grad(name):
    f = TRACEABLE[name]
    lv = level()
    eager = float(jnp.sum(f(lv)))
    value, g = jax.jit(jax.value_and_grad(lambda x: jnp.sum(f(x))))(lv)  # traced by jit and grad at once
    np.testing.assert_allclose(float(value), eager, rtol=1e-5)
    assert g.shape == lv.shape and np.isfinite(np.asarray(g)).all() and float(jnp.abs(g).sum()) > 0


@pytest.mark.parametrize("name", ["irradiance", "sh9_project"])
def test_traced_bad_values_are_not_checked(name):
    """Under jit the texels are tracers: no check (and no error) inside the trace."""
    out = np.asarray(jax.jit(TRACEABLE[name])(level(-1000.0)))
    assert out.shape and np.isfinite(out).all()


def test_vmap_over_levels():
    lvs = jnp.stack([level(), level(value=0.25)])
    out = jax.vmap(TRACEABLE["sh9_project"])(lvs)
    np.testing.assert_allclose(np.asarray(out[1]), np.asarray(TRACEABLE["sh9_project"](lvs[1])), rtol=1e-5, atol=1e-6)


# ---- render_batch's environment parameters --------------------------------------------------


@pytest.fixture(scope="module")
def scene():
    env = jp.Environment(radiance=cube())
    return jp.Scene(camera=jp.Camera(width=4, height=4), objects=(jp.Sphere(),), environment=env)


RENDER = dict(prefilter_size=S, extract_lights=False, irradiance_size=4)


@pytest.mark.parametrize(
    "key, values, env_kw",
    [
        ("env_rotation", [0.0, np.nan], dict(rotation=np.nan)),
        ("env_rotation", [0.0, np.inf], dict(rotation=np.inf)),
        ("env_intensity", [1.0, np.nan], dict(intensity=np.nan)),
        ("env_intensity", [1.0, np.inf], dict(intensity=np.inf)),
        ("env_intensity", [1.0, -1.0], dict(intensity=-1.0)),
    ],
)
def test_render_batch_refuses_bad_environment_parameters_like_environment(scene, key, values, env_kw):
    field = next(iter(env_kw))
    with pytest.raises(ValueError) as e:
        jp.Environment(radiance=cube(), **env_kw)
    expected = str(e.value)
    assert expected.startswith(f"Environment.{field} ")
    with pytest.raises(ValueError) as e:
        jp.render_batch(scene, **{key: jnp.asarray(values, jnp.float32)}, **RENDER)
    msg = str(e.value)
    assert key in msg and msg.endswith(expected[len(f"Environment.{field}"):]), msg


def test_render_batch_environment_parameters_traced(scene):
    """jit and grad wrt env_rotation and env_intensity still work (tracers are not checked)."""
    rot = jnp.asarray([0.0, 0.5], jnp.float32)
    k = jnp.asarray([1.0, 2.0], jnp.float32)
    eager = np.asarray(jp.render_batch(scene, env_rotation=rot, env_intensity=k, **RENDER))
    assert np.isfinite(eager).all() and eager.min() >= 0
    loss = lambda r, k: jnp.sum(jp.render_batch(scene, env_rotation=r, env_intensity=k, **RENDER))  # noqa: E731
    value, (g_rot, g_k) = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(rot, k)
    np.testing.assert_allclose(float(value), eager.sum(), rtol=1e-5)
    assert np.isfinite(np.asarray(g_rot)).all() and np.isfinite(np.asarray(g_k)).all() and (np.asarray(g_k) > 0).all()


def test_precomputes_of_a_constant_environment_inside_jit():
    """A concrete environment captured by a jitted function: the radiance check and the prefilter's
    bright-texel selection run while tracing, on the host path and on the accelerator path (forced
    here: two device reductions, which must not be staged into the caller's trace)."""
    from jaxpbr import _validate

    env = jp.envs.sky_with_sun_cubemap(8)
    out = jax.jit(lambda: jp.prefilter(env, size=8, samples=16).levels[1])()
    np.testing.assert_allclose(np.asarray(out), np.asarray(jp.prefilter(env, size=8, samples=16).levels[1]), rtol=1e-5)
    for on_host in (True, False):
        fresh = jp.Cubemap(env.levels[0] + 0.0)  # not yet checked
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(_validate, "_on_host", lambda x, v=on_host: v)
            e = jax.jit(lambda n: jp.ibl.diffuse.irradiance_at(fresh, n))(jnp.asarray([[0.0, 1.0, 0.0]]))
        assert np.isfinite(np.asarray(e)).all()
        bad = np.asarray(env.levels[0]).copy()
        bad[0, 0, 0, 0] = np.nan
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(_validate, "_on_host", lambda x, v=on_host: v)
            with pytest.raises(ValueError, match="NaN/Inf"):
                jax.jit(lambda n, b=jp.Cubemap(jnp.asarray(bad)): jp.ibl.diffuse.irradiance_at(b, n))(jnp.asarray([[0.0, 1.0, 0.0]]))
