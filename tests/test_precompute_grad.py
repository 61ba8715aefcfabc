"""The precomputation traced in the environment's texels: `prefilter` (method "fis", with its exactly convolved
brightest texels) and `irradiance` (method "exact") under jax.jit and jax.grad wrt level 0, so a renderer can
differentiate an image wrt environment texels.

Oracles: the eager result (for jit); the previous NumPy selection of the bright texels (copied below, so a change
of the selection fails here) plus an independent float64 NumPy convolution of their excess (for the eager
result); central finite differences of the same function at a step that leaves the selection unchanged (for the
gradients; the selection is piecewise constant, everything else is smooth on each piece).
"""

import math

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import reference as ref  # noqa: E402
from gradcheck import check_partials  # noqa: E402

from jaxpbr.ibl.cubemap import Cubemap  # noqa: E402
from jaxpbr.ibl.diffuse import irradiance  # noqa: E402
from jaxpbr.ibl.envs import sky_with_sun_cubemap  # noqa: E402
from jaxpbr.ibl.specular import level_roughness, lobe_normalizer, prefilter, split_bright  # noqa: E402

S = 16
M = 5
SAMPLES = [16] * M  # one FIS batch per level (padded to 256 slots); the default gives small levels up to 4096
LUMA = np.array([0.2126, 0.7152, 0.0722])


ref_solid_angles = ref.solid_angles


def exact_bright_np(idx, bright, S0, alpha, dirs):
    """float64 sum_j B_j K(R.w_j) Omega_j / W(alpha) over q x q sub-texels of the texels idx (flat into (6,S0,S0)),
    K = D(h) (R.l)+, h = (R+l)/|R+l|; sub-texel weights ~ dA/(1+sc^2+tc^2)^(3/2) normalised per texel."""
    q = int(min(4, max(1, math.ceil(2.0 * math.atan(1.0 / S0) / (alpha / 4.0)))))
    o = (np.arange(q) + 0.5) / q
    om = ref_solid_angles(S0)
    pts, wts = [], []
    for n in idx:
        f, i, j = n // (S0 * S0), (n // S0) % S0, n % S0
        tc, sc = np.meshgrid(-1.0 + 2.0 * (i + o) / S0, -1.0 + 2.0 * (j + o) / S0, indexing="ij")
        d = ref.gl_inverse(int(f), sc.ravel(), tc.ravel())
        w = (1.0 + sc.ravel() ** 2 + tc.ravel() ** 2) ** -1.5
        pts.append(d / np.linalg.norm(d, axis=-1, keepdims=True))
        wts.append(om[f, i, j] * w / w.sum())
    pts, wts = np.concatenate(pts), np.concatenate(wts)
    Bw = np.repeat(np.asarray(bright, np.float64), q * q, axis=0) * wts[:, None]
    c = dirs.reshape(-1, 3) @ pts.T
    a2 = alpha * alpha
    D = a2 / (math.pi * (0.5 * (1.0 + c) * (a2 - 1.0) + 1.0) ** 2)
    return ((D * np.maximum(c, 0.0)) @ Bw / lobe_normalizer(alpha)).reshape(dirs.shape[:-1] + (-1,))


def make_env(dtype, seed=0):
    """The sky with a wide sun, plus a few hot texels, times a little noise (no luminance ties)."""
    rng = np.random.default_rng(seed)
    lv = np.asarray(sky_with_sun_cubemap(S, supersample=2, sun_radius_deg=6.0, dtype=jnp.float64).levels[0])
    lv = lv * rng.uniform(0.95, 1.05, lv.shape)
    hot = rng.choice(6 * S * S, 5, replace=False)
    lv.reshape(-1, 3)[hot] *= rng.uniform(20.0, 200.0, (5, 1))
    return jnp.asarray(lv, dtype)


def pf(lv, exact_texels=256):
    return prefilter(Cubemap((lv,)), num_levels=M, samples=SAMPLES, exact_texels=exact_texels).levels  # the whole chain


# ----------------------------------------------------------------------------------------------
# eager == the previous algorithm; jit == eager
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype, rtol", [(np.float32, 3e-6), (np.float64, 1e-13)])
@pytest.mark.parametrize("exact_texels", [3, 256])
def test_eager_matches_previous_selection(dtype, rtol, exact_texels):
    lv = make_env(dtype)
    resid, idx, bright = split_bright(np.asarray(lv), exact_texels)
    n = len(idx)
    assert (n == 3) if exact_texels == 3 else (5 < n < 20), n  # the 5 hot texels and the sun's brightest
    out = prefilter(Cubemap((lv,)), num_levels=M, samples=SAMPLES, exact_texels=exact_texels)
    assert out.metadata["exact_texels"] == str(n)
    plain = pf(jnp.asarray(resid, dtype), exact_texels=0)  # FIS of the clamped map, same samples
    np.testing.assert_array_equal(np.asarray(out.levels[0]), np.asarray(lv))
    rough = level_roughness(M)
    for m in range(1, M):
        dirs = ref.cube_geometry(S >> m)[0]
        want = np.asarray(plain[m], np.float64) + exact_bright_np(idx, bright, S, rough[m] ** 2, dirs)
        np.testing.assert_allclose(np.asarray(out.levels[m], np.float64), want, rtol=rtol, err_msg=f"level {m}")


@pytest.mark.parametrize("dtype, rtol", [(np.float32, 1e-6), (np.float64, 1e-13)])
def test_jit_equals_eager(dtype, rtol):
    lv = make_env(dtype, seed=1)
    eager = pf(lv)
    jitted = jax.jit(pf)(lv)
    for m in range(M):
        assert jitted[m].dtype == dtype
        np.testing.assert_allclose(np.asarray(jitted[m]), np.asarray(eager[m]), rtol=rtol, err_msg=f"level {m}")
    e = irradiance(Cubemap((lv,)), size=8).levels[0]
    j = jax.jit(lambda x: irradiance(Cubemap((x,)), size=8).levels[0])(lv)
    assert j.dtype == dtype
    np.testing.assert_allclose(np.asarray(j), np.asarray(e), rtol=rtol)


# ----------------------------------------------------------------------------------------------
# gradients wrt level-0 texels vs central finite differences (float64)
# ----------------------------------------------------------------------------------------------


def probe_texels(lv, exact_texels, rng):
    """(texel, channel) pairs: the 3 brightest (selected) texels, the (k+1)-th brightest (the threshold for
    exact_texels = k when it exceeds 4x the mean), 6 ordinary texels."""
    lum = (np.asarray(lv, np.float64) @ LUMA).ravel()
    order = np.argsort(lum)[::-1]
    picks = list(order[:3]) + [order[exact_texels]] + list(rng.choice(order[20:], 6, replace=False))
    return [(int(t), int(rng.integers(3))) for t in picks]


def check_fd(loss, lv, probes, selection=None, rtol=1e-6):
    """The partial derivatives of loss at the probes vs central differences, relative error <= rtol
    (check_grads, reverse mode). Steps: 1e-4 x the value for selected texels (the clamp tau/lum is
    nonlinear in them: truncation error ~1e-9 here), 1e-2 x for the others (the function is linear in them on a
    piece of fixed selection; a small step would only add rounding noise). Every point the differences evaluate
    keeps the selection of lv (the derivative is that of one piece)."""
    f = jax.jit(loss)
    base = np.asarray(lv)
    sel = None if selection is None else selection(base)
    chosen = set() if sel is None else set(sel.tolist())

    def f_same_selection(x):
        if sel is not None and not isinstance(x, jax.core.Tracer):  # a concrete point of the differences
            assert np.array_equal(selection(np.asarray(x)), sel)
        return f(x)

    for t, c in probes:
        h = (1e-4 if t in chosen else 1e-2) * abs(base.reshape(-1, 3)[t, c])
        check_partials(f_same_selection, base, [3 * t + c], step=h, atol=0.0, rtol=rtol)


@pytest.mark.parametrize("exact_texels", [3, 256])
def test_prefilter_grad_matches_finite_differences(exact_texels):
    rng = np.random.default_rng(7)
    lv = make_env(jnp.float64, seed=2)
    w = [jnp.asarray(rng.normal(size=(6, S >> m, S >> m, 3))) for m in range(M)]

    def loss(x):
        levels = pf(x, exact_texels)
        return sum(jnp.sum(wm * lm) for wm, lm in zip(w[1:], levels[1:]))

    def selection(x):
        return split_bright(x, exact_texels)[1]

    probes = probe_texels(lv, exact_texels, rng)
    assert len({p[0] for p in probes} & set(selection(np.asarray(lv)).tolist())) == 3  # 3 selected texels
    check_fd(loss, lv, probes, selection)


def test_irradiance_grad_matches_finite_differences():
    rng = np.random.default_rng(8)
    lv = make_env(jnp.float64, seed=3)
    w = jnp.asarray(rng.normal(size=(6, 8, 8, 3)))

    def loss(x):
        return jnp.sum(w * irradiance(Cubemap((x,)), size=8).levels[0])

    check_fd(loss, lv, probe_texels(lv, 3, rng))


# Toggling x64 off inside this x64 process makes JAX warn about the float64 NumPy constants it truncates (a
# JAX dtype-cache quirk: a process that never enables x64 does not warn).
@pytest.mark.filterwarnings("ignore:Explicitly requested dtype float64")
def test_float32_gradients_are_finite():
    lv = np.asarray(make_env(jnp.float32, seed=4))
    rng = np.random.default_rng(9)
    w = [rng.normal(size=(6, S >> m, S >> m, 3)).astype(np.float32) for m in range(M)]

    def loss(x):
        return sum(jnp.sum(wm * lm) for wm, lm in zip(w, pf(x))) + jnp.sum(irradiance(Cubemap((x,)), size=8).levels[0])

    with jax.enable_x64(False):  # every intermediate float32 (x64 on, the split would run in float64)
        g = jax.jit(jax.grad(loss))(jnp.asarray(lv))
        assert g.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(g)))
        assert float(jnp.max(jnp.abs(g))) > 0
