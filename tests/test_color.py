"""Tests for jaxpbr.color: transfer functions against colour-science, tone maps against float64 NumPy
transcriptions of the published formulas, gradients at the singular points, dtypes, batching, jit."""

import jax

jax.config.update("jax_enable_x64", True)

import warnings  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from gradcheck import check_partials  # noqa: E402

from jaxpbr import color  # noqa: E402


def colour():
    """colour-science, imported on first use (it takes about a second to import, which every test
    worker would pay while collecting)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # colour-science warns that optional matplotlib is missing
        import colour as module
    return module


EPS32 = 2.0**-23  # float32 machine epsilon (1 ulp at 1.0)
KNEE_LIN = 0.0031308
KNEE_ENC = 0.04045
# colour-science switches its decode at 12.92 * 0.0031308 instead of the IEC 61966-2-1 threshold 0.04045.
COLOUR_DECODE_KNEE = 12.92 * 0.0031308


# ------------------------------------------------------------------------------------ float64 references


def ref_srgb_encode(x):
    """IEC 61966-2-1 inverse EOTF, float64 NumPy."""
    x = np.asarray(x, np.float64)
    return np.where(x <= KNEE_LIN, 12.92 * x, 1.055 * np.abs(x) ** (1 / 2.4) - 0.055)


def ref_srgb_decode(v):
    """IEC 61966-2-1 EOTF with the published threshold 0.04045, float64 NumPy."""
    v = np.asarray(v, np.float64)
    return np.where(v <= KNEE_ENC, v / 12.92, ((np.abs(v) + 0.055) / 1.055) ** 2.4)


def ref_reinhard(c):
    return c / (c + 1.0)


# Stephen Hill, BakingLab ACES.hlsl (ACESInputMat / ACESOutputMat / RRTAndODTFit / ACESFitted).
ACES_IN = np.array(
    [[0.59719, 0.35458, 0.04823], [0.07600, 0.90834, 0.01566], [0.02840, 0.13383, 0.83777]], np.float64
)
ACES_OUT = np.array(
    [[1.60475, -0.53108, -0.07367], [-0.10208, 1.10813, -0.00605], [-0.00327, -0.07276, 1.07602]], np.float64
)


def ref_aces_fitted(c):
    c = np.asarray(c, np.float64)
    v = c @ ACES_IN.T
    a = v * (v + 0.0245786) - 0.000090537
    b = v * (0.983729 * v + 0.4329510) + 0.238081
    return np.clip((a / b) @ ACES_OUT.T, 0.0, 1.0)


def ref_aces_narkowicz(x):
    x = np.asarray(x, np.float64)
    return np.clip(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)


def knee_points(knee, n=200):
    """Points straddling ``knee``: relative offsets down to 1e-12 and the float64 neighbours of the knee."""
    offsets = np.concatenate([-np.logspace(-12, -1, n), [0.0], np.logspace(-12, -1, n)])
    exact = [np.nextafter(knee, -1.0), knee, np.nextafter(knee, 2.0)]
    return np.concatenate([knee * (1.0 + offsets), exact])


# ------------------------------------------------------------------------------------ sRGB vs colour-science


def test_srgb_encode_matches_colour_science_float64():
    x = np.concatenate([np.linspace(-0.2, 1.5, 5001), np.logspace(-12, 1, 2001), [0.0], knee_points(KNEE_LIN)])
    ours = np.asarray(color.srgb_encode(jnp.asarray(x)))
    theirs = colour().cctf_encoding(x, function="sRGB")
    assert ours.dtype == np.float64
    assert np.max(np.abs(ours - theirs)) <= 1e-12
    # the branch is chosen exactly at the knee: 12.92 * knee on the line, the power just above it
    at = np.asarray(color.srgb_encode(jnp.asarray([KNEE_LIN, np.nextafter(KNEE_LIN, 1.0)])))
    assert at[0] == 12.92 * KNEE_LIN
    assert at[1] == pytest.approx(1.055 * np.nextafter(KNEE_LIN, 1.0) ** (1 / 2.4) - 0.055, rel=1e-15)


def test_srgb_decode_matches_colour_science_float64():
    v = np.concatenate([np.linspace(-0.2, 1.5, 5001), np.logspace(-12, 1, 2001), [0.0], knee_points(KNEE_ENC)])
    ours = np.asarray(color.srgb_decode(jnp.asarray(v)))
    theirs = colour().cctf_decoding(v, function="sRGB")
    sliver = (v > COLOUR_DECODE_KNEE) & (v <= KNEE_ENC)
    assert sliver.sum() > 10  # knee_points() does land in it
    assert np.max(np.abs(ours - theirs)[~sliver]) <= 1e-12
    # Inside the 6.4e-8-wide sliver we follow IEC 61966-2-1 (linear segment up to 0.04045 inclusive) ...
    # (rtol 1e-15 is ~4 ulps, six orders of magnitude below the 2.3e-9 gap that tells the segments apart)
    np.testing.assert_allclose(ours[sliver], v[sliver] / 12.92, rtol=1e-15, atol=0)
    assert np.max(np.abs(ours - ref_srgb_decode(v))) <= 1e-12
    # ... and differ from colour-science only by the tiny gap between the two segments there.
    assert np.max(np.abs(ours - theirs)[sliver]) <= 2.4e-9


def test_srgb_float32_matches_colour_science():
    # Reference: colour-science in float64 on the *float32* inputs, so only the function's own error counts.
    # Bounds come from how much the formulas amplify the ~1-ulp error of XLA's float32 `pow` (and of one
    # rounding before it): the encode's `1.055 p - 0.055` cancels by up to 1.055 p / V = 2.37 just above
    # the knee; the decode raises the rounded base (V + 0.055) / 1.055 to the power 2.4, which multiplies its
    # relative error by 2.4, on top of pow's own error.
    x = np.concatenate([np.linspace(-0.1, 1.0, 200001), np.logspace(-8, 0, 20001), knee_points(KNEE_LIN)])
    x = x.astype(np.float32)
    enc = np.asarray(color.srgb_encode(jnp.asarray(x)))
    assert enc.dtype == np.float32
    ref = colour().cctf_encoding(x.astype(np.float64), function="sRGB")
    assert np.all(np.abs(enc - ref) <= 2.4 * EPS32 * np.abs(ref))

    v = np.concatenate([np.linspace(-0.1, 1.0, 200001), knee_points(KNEE_ENC)]).astype(np.float32)
    v = v[~((v > COLOUR_DECODE_KNEE) & (v <= KNEE_ENC))]
    dec = np.asarray(color.srgb_decode(jnp.asarray(v)))
    assert dec.dtype == np.float32
    ref = colour().cctf_decoding(v.astype(np.float64), function="sRGB")
    assert np.all(np.abs(dec - ref) <= 2 * 2.4 * EPS32 * np.abs(ref))
    # The linear segments are a single multiplication/division: within 1 ulp.
    lin = v <= KNEE_ENC
    assert np.all(np.abs(dec - ref)[lin] <= EPS32 * np.abs(ref[lin]))


def test_srgb_round_trips():
    # IEC 61966-2-1's published constants are not exactly consistent: the power segment starts at
    # encode(0.0031308+) = 0.0404499075, below the decode threshold 0.04045. Linear values in
    # (0.0031308, 0.0031308073] therefore encode onto the decode's *linear* segment and come back off by up to
    # the 2.3e-9 gap between the segments; everywhere else the pair inverts to rounding error.
    x = np.concatenate([np.linspace(0.0, 2.0, 4001), knee_points(KNEE_LIN)])
    back = np.asarray(color.srgb_decode(color.srgb_encode(jnp.asarray(x))))
    gap = (x > KNEE_LIN) & (x <= ((KNEE_ENC + 0.055) / 1.055) ** 2.4)
    assert gap.sum() > 10
    np.testing.assert_allclose(back[~gap], x[~gap], rtol=1e-14, atol=1e-17)
    assert np.max(np.abs(back - x)[gap]) <= 2.4e-9
    v = np.concatenate([np.linspace(0.0, 1.0, 4001), knee_points(KNEE_ENC)])
    sliver = (v > 12.92 * KNEE_LIN) & (v <= KNEE_ENC)  # encoded values the encode never produces
    fwd = np.asarray(color.srgb_encode(color.srgb_decode(jnp.asarray(v))))
    np.testing.assert_allclose(fwd[~sliver], v[~sliver], rtol=1e-14, atol=1e-17)
    assert np.max(np.abs(fwd - v)[sliver]) <= 1e-7
    # host-side (colour-science) pair, float32 dtype kept
    x32 = np.linspace(0.0, 1.0, 101, dtype=np.float32)
    enc = color.srgb_encode_np(x32)
    assert enc.dtype == np.float32
    np.testing.assert_allclose(color.srgb_decode_np(enc), x32, rtol=3 * EPS32, atol=1e-9)
    np.testing.assert_allclose(color.srgb_encode_np(x32.astype(np.float64)), ref_srgb_encode(x32), rtol=1e-15)


def test_gamma_matches_formula_and_round_trips():
    x = np.concatenate([np.linspace(-0.5, 4.0, 901), [0.0, 1e-300]])
    np.testing.assert_allclose(color.gamma_encode(x), np.maximum(x, 0.0) ** (1 / 2.2), rtol=1e-15, atol=0)
    np.testing.assert_allclose(color.gamma_decode(x, 2.4), np.maximum(x, 0.0) ** 2.4, rtol=1e-15, atol=0)
    pos = x[x > 1e-10]  # (near 1e-300 pow's error grows with |log x|; the formula check above covers it)
    np.testing.assert_allclose(color.gamma_decode(color.gamma_encode(pos)), pos, rtol=1e-14)
    with pytest.raises(ValueError, match="gamma must be > 0"):
        color.gamma_encode(x, 0.0)
    with pytest.raises(ValueError, match="gamma must be > 0"):
        color.gamma_decode(x, -2.2)


# ----------------------------------------------------------------------------------------------- gradients
# Everything is evaluated through one jax.jit per test (and dtype): op-by-op execution compiles every primitive
# separately and would make this file slow.

SCALAR_FNS = {
    "srgb_encode": color.srgb_encode,
    "srgb_decode": color.srgb_decode,
    "gamma_encode": color.gamma_encode,
    "gamma_decode": color.gamma_decode,
    "reinhard": color.reinhard,
    "aces_narkowicz": color.aces_narkowicz,
    "tonemap_clamp": lambda c: color.tonemap(c, "clamp"),
    "exposure": lambda c: color.exposure(c, 1.5),
}
SINGULAR = np.array([0.0, -0.0, KNEE_LIN, KNEE_ENC, -1e-3, -1.0, -1e6, 1e-30, 1.0, 1e6])


@jax.jit
def _all_scalar_grads(x):
    return {name: jax.vmap(jax.grad(fn))(x) for name, fn in SCALAR_FNS.items()}


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_grad_finite_at_singular_points(dtype):
    x = jnp.asarray(SINGULAR, dtype)
    for name, g in _all_scalar_grads(x).items():
        assert g.dtype == dtype, name
        assert np.all(np.isfinite(np.asarray(g))), (name, SINGULAR, np.asarray(g))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_grad_finite_aces_fitted(dtype):
    pts = np.concatenate([SINGULAR, [np.inf]])
    c = np.stack(np.meshgrid(pts, pts[:4], pts[:4], indexing="ij"), -1).reshape(-1, 3)
    jac = jax.jit(jax.vmap(jax.jacfwd(color.aces_fitted)))(jnp.asarray(c, dtype))
    assert jac.shape == (c.shape[0], 3, 3) and jac.dtype == dtype
    assert np.all(np.isfinite(np.asarray(jac)))


def test_grad_values_at_the_kinks():
    x = jnp.array([0.0, -0.0, KNEE_LIN, -1.0, 1e-5, KNEE_ENC])
    g = {k: np.asarray(v) for k, v in _all_scalar_grads(x).items()}
    np.testing.assert_array_equal(g["srgb_encode"][:5], 12.92)  # the linear segment, knee included
    np.testing.assert_allclose(g["srgb_decode"][[0, 1, 3, 4, 5]], 1 / 12.92, rtol=1e-15)
    assert float(g["reinhard"][0]) == 1.0  # one-sided derivative into the domain at 0
    assert float(g["reinhard"][3]) == 0.0  # negative inputs are clamped
    assert float(g["gamma_encode"][0]) == 0.0  # documented: the infinite slope at 0 is cut to 0


def test_grad_wrt_exposure_and_gamma():
    @jax.jit
    def grads(ev, gam):
        return (
            jax.grad(lambda e: color.exposure(3.0, e))(ev),
            jax.grad(lambda g: color.gamma_encode(0.0, g))(gam),
            jax.grad(lambda g: color.gamma_encode(0.25, g))(gam),
        )

    g_ev, g_gam0, g_gam = grads(2.0, 2.0)
    assert float(g_ev) == pytest.approx(3.0 * 4.0 * np.log(2.0), rel=1e-15)
    assert float(g_gam0) == 0.0  # log(0) never reaches the gradient
    assert float(g_gam) == pytest.approx(0.25**0.5 * np.log(0.25) * (-1 / 4.0), rel=1e-14)


def test_grads_match_central_differences_away_from_kinks():
    # float64, step h = 1e-6: truncation error h**2 |f'''| / 6 < 1e-9 relative at these points, plus round-off
    # ~eps |f| / h ~ 2e-10 absolute (hence the atol). Every derivative (each point; each entry of the ACES
    # Jacobian per colour) on its own, in reverse mode.
    x = np.array([0.01, 0.1, 0.3, 0.7, 3.0, 40.0])
    h = 1e-6
    names = ["srgb_encode", "srgb_decode", "gamma_encode", "gamma_decode", "reinhard", "aces_narkowicz"]
    for n in names:
        f = jax.jit(SCALAR_FNS[n])  # one compiled function (and JVP, VJP) for the six points
        for xi in x:
            check_partials(f, np.asarray(xi), [0], step=h, atol=1e-9, rtol=1e-7)
    c = np.array([[0.05, 0.2, 0.6], [1.5, 0.3, 0.1], [8.0, 2.0, 30.0]])
    f = jax.jit(color.aces_fitted)
    for ci in c:
        check_partials(f, ci, range(3), outputs=range(3), step=h, atol=1e-9, rtol=1e-7)


# --------------------------------------------------------------------------------------------------- tone maps


def test_reinhard_matches_formula():
    rng = np.random.default_rng(0)
    c = np.concatenate([rng.random(1000) * 10.0, np.logspace(-10, 6, 500), [0.0, 1.0]])
    # 2 ulps: for c > 1 the function evaluates the exact rewrite 1 / (1 + 1/c) (finite at c = inf), which
    # rounds differently from c / (c + 1).
    c = np.concatenate([c, [np.inf, -2.0]])
    out = np.asarray(jax.jit(color.reinhard)(c))
    np.testing.assert_allclose(out[:-2], ref_reinhard(c[:-2]), rtol=2 * 2.0**-52, atol=0)
    assert out[-3] == 0.5  # c = 1
    assert out[-2] == 1.0  # c = inf
    assert out[-1] == 0.0  # outside the domain: clamped, not divided by -1


def test_aces_fitted_matches_published_formula():
    rng = np.random.default_rng(1)
    c = np.concatenate([rng.random((2000, 3)) * 4.0, np.exp(rng.normal(0.0, 3.0, (2000, 3)))])
    ours = np.asarray(jax.jit(color.aces_fitted)(c))
    # 1e-14: same algebra, different evaluation order (matrix sums, and v > 1 divided through by v**2).
    np.testing.assert_allclose(ours, ref_aces_fitted(c), rtol=0, atol=1e-14)


def test_aces_narkowicz_matches_published_formula():
    rng = np.random.default_rng(2)
    x = np.concatenate([rng.random(2000) * 4.0, np.exp(rng.normal(0.0, 3.0, 2000)), [0.0, 1.0]])
    out = np.asarray(jax.jit(color.aces_narkowicz)(x))
    np.testing.assert_allclose(out, ref_aces_narkowicz(x), rtol=0, atol=1e-15)
    assert out[-1] == pytest.approx(2.54 / 3.16, rel=1e-15)  # x = 1


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_tonemaps_monotone_and_in_range(dtype):
    ramp = np.concatenate([[0.0], np.logspace(-6, 8, 3000)]).astype(dtype)
    grey = np.repeat(ramp[:, None], 3, axis=1)
    outs = jax.jit(lambda g, r: {"aces": color.aces_fitted(g), "aces_narkowicz": color.aces_narkowicz(r),
                                  "reinhard": color.reinhard(r)})(grey, ramp)
    for name, out in outs.items():
        out = np.asarray(out)
        assert out.dtype == dtype, name
        assert np.all((out >= 0) & (out <= 1)), name
        assert np.all(np.diff(out, axis=0) >= 0), name
    # saturating colours, huge and infinite radiance, negative (out-of-domain) values: finite and in range
    rng = np.random.default_rng(3)
    big = np.finfo(dtype).max
    stiff = np.concatenate(
        [rng.random((500, 3)) * 10.0 ** rng.integers(-8, 30, (500, 1)), [[big, 0, 0], [np.inf, 1, 0], [-5, 2, 1e9]]]
    ).astype(dtype)
    outs = jax.jit(lambda c: {op: color.tonemap(c, op) for op in color.TONEMAP_OPERATORS})(stiff)
    for op, out in outs.items():
        out = np.asarray(out)
        assert out.dtype == dtype
        assert np.all(np.isfinite(out) & (out >= 0) & (out <= 1)), op


def test_tonemap_dispatch():
    c = jnp.array([[0.05, 0.5, 3.0], [-1.0, 1.0, 20.0]])

    @jax.jit
    def both(c):
        by_name = {op: color.tonemap(c, op) for op in color.TONEMAP_OPERATORS}
        by_name.update({t: color.encode(c, t) for t in color.TRANSFERS})
        direct = {
            "none": jnp.clip(c, 0, 1),
            "clamp": jnp.clip(c, 0, 1),
            "reinhard": color.reinhard(c),
            "aces": color.aces_fitted(c),
            "aces_narkowicz": color.aces_narkowicz(c),
            "srgb": color.srgb_encode(c),
            "gamma2.2": color.gamma_encode(c, 2.2),
            "linear": c,
        }
        return by_name, direct

    by_name, direct = both(c)
    assert sorted(by_name) == sorted(direct)
    for k in direct:
        np.testing.assert_array_equal(by_name[k], direct[k], err_msg=k)


@pytest.mark.parametrize("bad", ["filmic", "ACES", "", None, 3])
def test_bad_names_raise(bad):
    c = jnp.ones(3)
    with pytest.raises(ValueError, match="reinhard.*aces"):
        color.tonemap(c, bad)
    with pytest.raises(ValueError, match="'srgb', 'gamma2.2', 'linear'"):
        color.encode(c, bad)


def test_aces_fitted_needs_rgb():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        color.aces_fitted(jnp.ones((4, 2)))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        color.aces_fitted(1.0)


def test_nan_propagates():
    x = jnp.array([np.nan, 0.5])
    out = jax.jit(lambda x: {n: f(x) for n, f in SCALAR_FNS.items()})(x)
    for name, o in out.items():
        o = np.asarray(o)
        assert np.isnan(o[0]) and np.isfinite(o[1]), name
    aces = jax.jit(color.aces_fitted)(jnp.array([[np.nan, 0.1, 0.1], [0.1, 0.1, 0.1]]))
    assert np.all(np.isnan(np.asarray(aces[0]))) and np.all(np.isfinite(np.asarray(aces[1])))


# ---------------------------------------------------------------------------------------------- exposure


def test_exposure_exact_powers_of_two_and_broadcasting():
    c = np.linspace(0.0, 5.0, 11)
    ev = np.arange(-20.0, 21.0)[:, None]
    for dtype in (np.float32, np.float64):
        out = color.exposure(c.astype(dtype), ev)  # (41, 11): ev broadcasts against c
        assert out.dtype == dtype and out.shape == (41, 11)
        np.testing.assert_array_equal(out, c.astype(dtype) * 2.0**ev)  # integer stops are exact
    np.testing.assert_allclose(color.exposure(c, 0.5), c * np.sqrt(2.0), rtol=1e-15)
    batch = jnp.ones((4, 2, 3, 3))
    out = color.exposure(batch, jnp.arange(4.0)[:, None, None, None])  # one exposure per image
    np.testing.assert_array_equal(out[:, 0, 0, 0], 2.0 ** np.arange(4.0))
    # a float64 ev does not promote float32 images
    assert color.exposure(jnp.ones(3, jnp.float32), jnp.float64(1.0)).dtype == jnp.float32


# ------------------------------------------------------------------------------- dtype, batching, jit


# The per-element functions of the gradient tests, plus the `encode` dispatcher.
ELEMENTWISE = {**SCALAR_FNS, "encode_srgb": lambda c: color.encode(c, "srgb")}
RGB = {
    "aces_fitted": color.aces_fitted,
    "tonemap_aces": lambda c: color.tonemap(c, "aces"),
}


def _shapes_and_inputs(dtype, rgb):
    shapes = [(3,), (1, 3), (3, 1, 2, 3)] if rgb else [(), (1,), (3, 1, 2)]
    big = np.random.default_rng(4).uniform(-0.2, 3.0, shapes[-1]).astype(dtype)
    big.flat[:3] = [0.0, KNEE_LIN, KNEE_ENC]
    return shapes, big


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("rgb", [False, True], ids=["elementwise", "rgb"])
def test_dtype_batch_shapes_and_jit(rgb, dtype):
    fns = RGB if rgb else ELEMENTWISE
    shapes, big = _shapes_and_inputs(dtype, rgb)
    jitted = jax.jit(lambda x: {n: f(x) for n, f in fns.items()})  # one compilation per shape for all fns
    full = jitted(jnp.asarray(big))
    for shape in shapes:
        x = big.reshape(-1)[: int(np.prod(shape))].reshape(shape)
        for name, out in jitted(jnp.asarray(x)).items():
            assert out.shape == shape and out.dtype == dtype, (name, shape, out.shape, out.dtype)
            # batching does not change values: each element equals its value in the big batch
            np.testing.assert_array_equal(np.asarray(out).reshape(-1), np.asarray(full[name]).reshape(-1)[: out.size])
    # vmap over the leading axis equals the broadcast call
    vmapped = jax.jit(lambda x: {n: jax.vmap(f)(x) for n, f in fns.items()})(jnp.asarray(big))
    for name in fns:
        np.testing.assert_array_equal(vmapped[name], full[name], err_msg=name)
    # jit vs no-jit: XLA may fuse differently (e.g. into a fused multiply-add), so allow a couple of ulps; the
    # ACES output matrix has negative entries whose cancellation (sum |M_ij| / sum M_ij = 2.2) amplifies the
    # ulp-level differences of the rational fit, so there allow 8 ulps of the [0, 1] output range.
    eps = np.finfo(dtype).eps
    for name, fn in fns.items():
        eager = fn(jnp.asarray(big))
        assert eager.dtype == dtype and eager.shape == big.shape, name
        if rgb:
            np.testing.assert_allclose(full[name], eager, rtol=0, atol=8 * eps, err_msg=name)
        else:
            np.testing.assert_allclose(full[name], eager, rtol=2 * eps, atol=2 * np.finfo(dtype).tiny, err_msg=name)


def test_integer_and_python_inputs_promote_to_default_float():
    for name, fn in {**ELEMENTWISE, **RGB}.items():
        for arg in (jnp.arange(3), [1, 2, 3], 2) if name in ELEMENTWISE else (jnp.arange(3), [1, 2, 3]):
            assert jax.eval_shape(fn, arg).dtype == jnp.float64, (name, arg)  # x64 is enabled in this module


def test_an_eager_call_is_one_compiled_program_with_the_traced_values():
    """Called outside any transformation, a tone map and an encoding compile one program each (op
    by op they were 23 compilations), give the values of the same functions traced inside jit, and
    promote Python and integer inputs as traced."""
    import logging

    messages = []

    class Seen(logging.Handler):
        def emit(self, record):
            messages.append(record.getMessage())

    img = jnp.asarray(np.random.default_rng(7).random((3, 11, 3)) * 4.0, jnp.float32)  # a shape of this test only
    handler, logger = Seen(), logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            out = color.encode(color.tonemap(img, "aces"), "srgb")
    finally:
        logger.removeHandler(handler)
    lowered = [m.split()[-4] for m in messages if m.startswith("Finished jaxpr to MLIR module conversion")]
    assert lowered == ["jit(tonemap)", "jit(encode)"], messages
    traced = jax.jit(lambda c: color.encode(color.tonemap(c, "aces"), "srgb"))(img)
    np.testing.assert_array_equal(out, traced)
    for name, fn in {**ELEMENTWISE, **RGB}.items():
        for arg in (jnp.arange(3), [1, 2, 3]):
            assert fn(arg).dtype == jax.eval_shape(fn, arg).dtype == jnp.float64, (name, arg)


def test_exposure_of_infinite_stops():
    """ev = +-inf: inf and 0, as 2**ev (the exact ldexp split took ev - floor(ev) = NaN there)."""
    out = np.asarray(color.exposure(jnp.ones(3), jnp.asarray([jnp.inf, -jnp.inf, 2.0])))
    np.testing.assert_array_equal(out, [np.inf, 0.0, 4.0])



def _loaded_colour(tmp_path, steps: str) -> str:
    """Run `steps` in a fresh interpreter; its last line says whether colour-science was loaded after each."""
    import subprocess
    import sys

    code = "import sys, jaxpbr\nseen = ['colour' in sys.modules]\n" + steps + "print('loaded:', seen)\n"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=600, check=False)
    assert run.returncode == 0, run.stderr
    return run.stdout.splitlines()[-1]


def test_import_jaxpbr_does_not_load_colour_science(tmp_path):
    """colour-science takes about 1.5 s to import: `import jaxpbr` does not load it; the host-side
    sRGB (`srgb_encode_np`) does."""
    steps = "jaxpbr.color.srgb_encode_np([0.5])\nseen.append('colour' in sys.modules)\n"
    assert _loaded_colour(tmp_path, steps) == "loaded: [False, True]"


def test_demo_render_does_not_load_colour_science(tmp_path):
    """The demo render encodes sRGB on the device: the command does not load colour-science."""
    out = tmp_path / "demo.png"
    steps = (
        "from jaxpbr.cli import main\n"
        f"assert main(['render', '-o', {str(out)!r}, '--width', '16', '--height', '8']) == 0\n"
        "seen.append('colour' in sys.modules)\n"
    )
    assert _loaded_colour(tmp_path, steps) == "loaded: [False, False]" and out.is_file()
