"""jaxpbr._numerics helpers outside the kernels: the host-side row cross product."""

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest


def test_cross_rows_is_np_cross_bit_for_bit():
    from jaxpbr._numerics import cross_rows

    rng = np.random.default_rng(3)
    for dtype in (np.float32, np.float64):
        a, b = rng.standard_normal((1000, 3)).astype(dtype), rng.standard_normal((1000, 3)).astype(dtype)
        out = cross_rows(a, b)
        assert out.dtype == dtype
        np.testing.assert_array_equal(out, np.cross(a, b))
    np.testing.assert_array_equal(cross_rows(a, b[0]), np.cross(a, b[0]))  # broadcast against one row


def test_computed_once_compiles_its_function_once_and_returns_its_value():
    """`computed_once` is a conditional whose other branch is a constant: fn's code appears once in
    the program (both branches were fn before: the IBL stage compiled every cube lookup twice)."""
    import jax
    import jax.numpy as jnp

    from jaxpbr._numerics import computed_once

    def fn(o):
        return jnp.sinh(o[0]) * o[1]

    x = jnp.linspace(-2.0, 2.0, 64, dtype=jnp.float32)
    for guard in (jnp.float32(0.0), jnp.float32(-0.0), jnp.float32(np.nan), jnp.float32(np.inf), jnp.float32(-3.5)):
        f = jax.jit(lambda x, g: computed_once(fn, (x, 2.0 * x), g))
        np.testing.assert_array_equal(f(x, guard), fn((x, 2.0 * x)))  # fn's value whatever the guard
    if jax.default_backend() == "cpu":
        text = jax.jit(lambda x, g: computed_once(fn, (x, 2.0 * x), g)).lower(x, jnp.float32(1.0)).as_text()
        assert text.count("sinh") == 1, text
    # gradients flow through fn
    g = jax.grad(lambda x: computed_once(fn, (x, x), jnp.float32(1.0)).sum())(x)
    np.testing.assert_allclose(g, np.cosh(np.asarray(x)) * np.asarray(x) + np.sinh(np.asarray(x)), rtol=1e-5)


def test_eager_cpu_cond_and_computed_once_call_the_branch_and_lower_no_conditional(monkeypatch):
    """Outside any trace `cpu_cond` calls the branch its (concrete) predicate picks and
    `computed_once` calls fn: no conditional program is lowered (each eager call would otherwise
    lower and compile one, its branches being new closures). Inside a trace they still lower one."""
    import jax
    import jax.numpy as jnp

    from jaxpbr import _numerics
    from jaxpbr._numerics import computed_once, cpu_cond

    conds = []
    real_cond = jax.lax.cond
    monkeypatch.setattr(jax.lax, "cond", lambda *a, **k: conds.append(1) or real_cond(*a, **k))
    x = jnp.linspace(-2.0, 2.0, 16, dtype=jnp.float32)
    np.testing.assert_array_equal(cpu_cond(jnp.any(x > 5), lambda o: o * 2, lambda o: o - 1, x), x - 1)
    np.testing.assert_array_equal(cpu_cond(jnp.any(x > 0), lambda o: o * 2, lambda o: o - 1, x), x * 2)
    np.testing.assert_array_equal(computed_once(lambda o: jnp.sinh(o), x, jnp.float32(0.0)), jnp.sinh(x))
    assert conds == []
    assert _numerics._eager((x,))
    if jax.default_backend() == "cpu":  # traced: the conditional is there (platform_dependent's CPU branch)
        jax.jit(lambda x: cpu_cond(jnp.any(x > 5), lambda o: o * 2, lambda o: o - 1, x)).lower(x)
        jax.grad(lambda x: computed_once(lambda o: jnp.sinh(o), x, jnp.float32(0.0)).sum())(x)
        assert len(conds) == 2


def test_interp_uniform_and_interp_nodes_equal_jnp_interp_in_value_and_gradient():
    import jax
    import jax.numpy as jnp

    from jaxpbr._interp import interp_nodes, interp_uniform

    rng = np.random.default_rng(5)
    grid = np.linspace(-1.0, 3.0, 33)
    table = np.cumsum(rng.uniform(0.1, 1.0, 33))
    nodes = np.array([0.0, 0.05, 0.3, 0.31, 0.9, 1.0])
    values = np.arange(6.0)
    # inside, on every node, outside on both sides
    xs = np.concatenate([rng.uniform(-2.0, 4.0, 500), grid, nodes, [-1.0, 3.0, -5.0, 7.0]])
    for dtype in (jnp.float32, jnp.float64):
        with jax.enable_x64(dtype == jnp.float64):
            fns = (lambda x, dt=dtype: interp_uniform(x, -1.0, 3.0, jnp.asarray(table, dt)),
                   lambda x, dt=dtype: jnp.interp(x, jnp.asarray(grid, dt), jnp.asarray(table, dt)),
                   lambda x: interp_nodes(x, nodes, values),
                   lambda x, dt=dtype: jnp.interp(x, jnp.asarray(nodes, dt), jnp.asarray(values, dt)))
            both = jax.jit(lambda x, fns=fns: tuple((f(x), jax.vmap(jax.grad(f))(x)) for f in fns))
            (u, du), (ru, dru), (n, dn), (rn, drn) = both(jnp.asarray(xs, dtype))
            tol = 1e-6 if dtype == jnp.float32 else 1e-13
            for ours, ref, d_ours, d_ref in ((u, ru, du, dru), (n, rn, dn, drn)):
                assert ours.dtype == dtype
                np.testing.assert_allclose(ours, ref, rtol=tol, atol=tol * 10)
                np.testing.assert_allclose(d_ours, d_ref, rtol=1e-4, atol=1e-4)


def test_interp_nodes_with_a_repeated_node_is_finite_and_equals_jnp_interp():
    import jax
    import jax.numpy as jnp

    from jaxpbr._interp import interp_nodes

    nodes, values = np.array([0.0, 0.0, 0.5, 1.0]), np.arange(4.0)
    x = jnp.linspace(-0.2, 1.2, 15, dtype=jnp.float32)
    f = jax.jit(lambda x: (interp_nodes(x, nodes, values), jax.vmap(jax.grad(lambda t: interp_nodes(t, nodes, values)))(x)))
    v, g = f(x)
    np.testing.assert_allclose(v, jnp.interp(x, jnp.asarray(nodes, jnp.float32), jnp.asarray(values, jnp.float32)), rtol=1e-6)
    assert np.isfinite(np.asarray(g)).all()



@pytest.mark.parametrize("x64", [False, True], ids=["x32", "x64"])
def test_as_float_of_python_numbers_builds_the_weak_array_without_a_program(x64):
    """The weakly typed array of Python numbers is made without compiling anything and is what
    stacking their weakly typed scalars gives: values, dtype, weak type, shape."""
    from jaxpbr import _numerics

    compiled = []

    class _Compiles(logging.Handler):
        def emit(self, record):
            if "Finished XLA compilation" in record.getMessage():
                compiled.append(record.getMessage())

    values = (0.1, 0.25, 1e-30)
    handler = _Compiles()
    logging.getLogger("jax").addHandler(handler)
    try:
        with jax.enable_x64(x64), jax.log_compiles(True):
            got = _numerics._weak_array(values, (3,))
            grid = _numerics._weak_array((1.0, 2.0, 3.0, 4.0), (2, 2))
    finally:
        logging.getLogger("jax").removeHandler(handler)
    assert compiled == []
    with jax.enable_x64(x64):
        want = _numerics._weak_stack(*(jax.device_put(v) for v in values))
        assert got.weak_type and want.weak_type and got.dtype == want.dtype and got.shape == want.shape
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        assert grid.shape == (2, 2) and grid.weak_type
        np.testing.assert_array_equal(np.asarray(grid), [[1.0, 2.0], [3.0, 4.0]])
        # weakly typed: it takes the dtype of the array it meets, as a Python number does
        assert (got * jnp.ones(3, jnp.float16)).dtype == jnp.float16
    # Inside a trace the numbers are bound there (as the compiled stack is), and the direct
    # construction stays on for later calls outside.
    traced = jax.jit(lambda x: x * _numerics._weak_array((2.0, 3.0), (2,)))(jnp.ones(2, jnp.float16))
    assert traced.dtype == jnp.float16
    np.testing.assert_array_equal(np.asarray(traced), [2.0, 3.0])
    assert _numerics._WEAK_DIRECT[0]
