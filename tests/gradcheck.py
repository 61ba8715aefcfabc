"""Finite-difference gradient checks, one partial derivative at a time, through `jax.test_util.check_grads`.

`check_grads(f, args, order=1)` compares the VJP ("rev") and/or JVP ("fwd") of `f` with a central
difference along one random direction. To check each partial derivative on its own (not one random
combination of them), `check_partials` applies it to the scalar restriction `t -> f(x + t e_k)`
(optionally one flat output `j` of it) at `t = 0`.

check_grads draws its direction T and cotangent C from `np.random.RandomState(0)`: for a scalar input
and output it compares T C g with C fd ("rev") and T g with fd ("fwd"), g the partial derivative and
fd = (f(x + eps T e_k) - f(x - eps T e_k)) / (2 eps), each to `atol + rtol |expected|`. With
eps = step / |T| that difference is the plain central difference with `step`, and an atol scaled by
min(|T|, |T C|) makes both comparisons at least as strict as |g - fd/T| <= atol + rtol |fd/T|: the
bound of a hand-written per-coordinate check.
"""

import jax.numpy as jnp
import numpy as np
from jax.test_util import check_grads

_T, _C = np.random.RandomState(0).randn(2)  # check_grads' tangent and cotangent (scalar input and output)
_ATOL_SCALE = min(abs(_T), abs(_T * _C))
_TINY = np.finfo(np.float64).tiny  # check_grads drops a zero rtol, and NumPy's default (1e-7) would apply


def check_partials(f, x, coords, *, step, atol, rtol, outputs=None, modes=("rev",)):
    """For every flat index k in `coords` (and flat output index j in `outputs`, if given): the
    derivative of t -> f(x + t e_k)[j] at 0 equals the central difference with `step` to
    |g - fd| <= atol + rtol |fd|. Default mode "rev" (the VJP, what jax.grad uses); add "fwd" for the JVP.

    f is called with concrete NumPy arrays for the primal value and the differences, and under
    jax.vjp / jax.jvp for the derivatives. Pass a jitted f (one compiled function, VJP and JVP for all
    coordinates) unless f already runs compiled stages."""
    x = np.asarray(x)
    t0 = np.zeros((), x.dtype)
    for k in coords:
        e = np.zeros(x.size, x.dtype)
        e[k] = 1.0
        e = e.reshape(x.shape)
        for j in [None] if outputs is None else outputs:

            def restricted(t, e=e, j=j):
                y = f(x + t * e)
                return y if j is None else jnp.reshape(y, -1)[j]

            check_grads(
                restricted,
                (t0,),
                order=1,
                modes=modes,
                eps=step / abs(_T),
                atol=atol * _ATOL_SCALE,
                rtol=rtol or _TINY,
            )
