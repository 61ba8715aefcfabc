"""Hammersley points, GGX (NDF and VNDF) and cosine sampling, densities and tangent frames.

Oracles are independent of jaxpbr: a bit-by-bit Python radical inverse, scipy quadrature and
Gauss-Legendre grids over the textbook D / G1 of tests/reference.py (docs/math.md §1, §3, §7.1).
Functions under test are called jitted with shared shapes, so the file compiles little.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as ref
from scipy import integrate

from jaxpbr.shading import sampling as S

DTYPES = [jnp.float32, jnp.float64]
N_QMC = 2**16

hammersley = jax.jit(S.hammersley, static_argnums=(0, 1))  # one compilation per (n, dtype)
sample_ggx_h = jax.jit(S.sample_ggx_h)
sample_ggx_vndf = jax.jit(S.sample_ggx_vndf)
sample_cosine = jax.jit(S.sample_cosine)
pdf_ggx_h = jax.jit(S.pdf_ggx_h)
pdf_ggx_vndf = jax.jit(S.pdf_ggx_vndf)


def _radical_inverse_py(i: int) -> float:
    """Phi_2(i) bit by bit: binary digits of i mirrored about the binary point (exact in float64)."""
    out, scale = 0.0, 0.5
    for _ in range(32):
        out += (i & 1) * scale
        i >>= 1
        scale *= 0.5
    return out


def _gl01(n):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1), 0.5 * w


def _visible_grid(alpha, mu, n_theta=40, n_phi=48):
    """Nodes and weights for int of g(h) over {n.h > 0, v.h > 0} (v = (sqrt(1-mu^2), 0, mu)), for
    g even in phi. theta panels [0, a/4, a, 4a, 16a, t0, pi/2] (clipped; graded at the GGX peak;
    t0 = pi/2 - theta_v is where the v.h > 0 cut starts, the phi integral has a (theta - t0)^(3/2)
    term there), and per theta phi in [0, phi_max(theta)] where v.h reaches 0, so the
    max(0, v.h) kink is an endpoint; Gauss-Legendre throughout, times 2 for the phi symmetry.
    Fixed shape (6 n_theta, n_phi) whatever alpha and mu (empty panels have zero weight)."""
    x, w = _gl01(n_theta)
    t0 = np.pi / 2 - np.arccos(mu)
    br = np.sort(np.clip([0, alpha / 4, alpha, 4 * alpha, 16 * alpha, t0, np.pi / 2], 0, np.pi / 2))
    th = np.concatenate([a + (b - a) * x for a, b in itertools.pairwise(br)])
    wt = np.concatenate([(b - a) * w for a, b in itertools.pairwise(br)])
    s_v = np.sqrt(1 - mu * mu)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = -mu * np.cos(th) / (s_v * np.sin(th))  # v.h = 0 at cos(phi) = c
    phi_max = np.arccos(np.clip(np.nan_to_num(c, nan=-1.0), -1.0, 1.0))
    xp, wp = _gl01(n_phi)
    P = phi_max[:, None] * xp
    W = 2 * (wt * np.sin(th) * phi_max)[:, None] * wp
    return np.broadcast_to(th[:, None], P.shape), P, W


def _dirs(T, P):
    return np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)


# --------------------------------------------------------------------------------------------
# Hammersley
# --------------------------------------------------------------------------------------------


def test_radical_inverse_matches_bit_by_bit_definition():
    idx = list(range(1025)) + [2**16 + 3, 123456789, 2**31 + 5, 2**32 - 1]
    expect = np.array([_radical_inverse_py(i) for i in idx])
    got64 = np.asarray(S.radical_inverse(np.array(idx, np.uint32), jnp.float64))
    np.testing.assert_array_equal(got64, expect)
    # float32 keeps the top 24 reversed bits: floor(Phi * 2^24) / 2^24, exact, and never 1.0
    got32 = np.asarray(S.radical_inverse(np.array(idx, np.uint32), jnp.float32))
    np.testing.assert_array_equal(got32.astype(np.float64), np.floor(expect * 2**24) / 2**24)
    assert got32.max() < 1.0 and expect[-1] > 1 - 2**-31
    assert got32[:5].tolist() == [0.0, 0.5, 0.25, 0.75, 0.125]


@pytest.mark.parametrize("dtype", DTYPES)
def test_hammersley_points(dtype):
    n = 1000
    x = np.asarray(hammersley(n, dtype))
    assert x.shape == (n, 2) and x.dtype == dtype
    np.testing.assert_allclose(x[:, 0], np.arange(n) / n, rtol=float(jnp.finfo(dtype).eps))
    phi2 = np.array([_radical_inverse_py(i) for i in range(n)])  # exact in float32 for i < 2^24
    np.testing.assert_array_equal(x[:, 1], phi2.astype(dtype))
    assert x.min() >= 0.0 and x.max() < 1.0
    # a base-2 point set is stratified: every dyadic interval of length 1/8 holds n/8 points (+-1)
    counts = np.bincount((x[:, 1] * 8).astype(int), minlength=8)
    assert np.all(np.abs(counts - n / 8) <= 1)
    eager = np.asarray(S.hammersley(3, dtype))  # not jitted, n = 3
    np.testing.assert_allclose(eager, [[0, 0], [1 / 3, 0.5], [2 / 3, 0.25]], rtol=float(jnp.finfo(dtype).eps))


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, None, 2**32])
def test_hammersley_rejects_bad_n(bad):
    with pytest.raises(ValueError, match="n must be"):
        S.hammersley(bad)


# --------------------------------------------------------------------------------------------
# GGX NDF sampling
# --------------------------------------------------------------------------------------------

ALPHAS = (0.05, 0.3, 1.0)


def _mean_cos_quad(alpha):
    """E[cos theta_h] under D(h) (n.h): 2 pi int cos^2 sin D dtheta (scipy, textbook D)."""
    f = lambda t: 2 * np.pi * np.cos(t) ** 2 * np.sin(t) * ref.d_ggx(np.cos(t), alpha)
    pts = [p for p in (alpha, 4 * alpha) if p < np.pi / 2]
    return integrate.quad(f, 0, np.pi / 2, points=pts, epsabs=1e-13, epsrel=1e-12, limit=200)[0]


def test_mean_cos_quadrature_reproduces_math_value():
    # docs/math.md §7.1: alpha = 0.3, quadrature 0.90463 (checks the oracle used below)
    assert abs(_mean_cos_quad(0.3) - 0.90463) < 5e-6


@pytest.mark.parametrize("dtype", DTYPES)
def test_sample_ggx_h_mean_cos_matches_quadrature(dtype):
    """docs/math.md §7.1 sampling check, for alpha = 0.05, 0.3, 1 at once (alpha (3, 1) broadcasts)."""
    h = sample_ggx_h(hammersley(N_QMC, dtype), jnp.asarray(ALPHAS, dtype)[:, None])
    assert h.shape == (3, N_QMC, 3) and h.dtype == dtype
    got = np.mean(np.asarray(h[..., 2], np.float64), axis=-1)
    np.testing.assert_allclose(got, [_mean_cos_quad(a) for a in ALPHAS], atol=2e-5)


def test_sample_ggx_h_azimuth_and_polar_angle_are_the_documented_maps():
    xi = np.array([[0.0, 0.0], [0.25, 0.5], [0.5, 0.9], [0.8, 0.999]])
    alpha = 0.4
    h = np.asarray(sample_ggx_h(jnp.asarray(xi, jnp.float64), alpha))
    tan2 = alpha**2 * xi[:, 1] / (1 - xi[:, 1])  # pbrt-v4 form of the same inverse CDF
    np.testing.assert_allclose(h[:, 2], 1 / np.sqrt(1 + tan2), rtol=1e-12)
    phi = np.arctan2(h[1:, 1], h[1:, 0]) % (2 * np.pi)
    np.testing.assert_allclose(phi, 2 * np.pi * xi[1:, 0], rtol=1e-12)


def test_sample_ggx_h_small_alpha_float32_keeps_sin_theta():
    """docs/math.md §8.3: at r = 0.02, sqrt(1 - cos^2) is exactly 0 in float32 for xi <= 0.01."""
    alpha = 0.02**2
    xi1 = np.array([1e-4, 1e-3, 1e-2, 0.5])
    exact = alpha * np.sqrt(xi1 / (1 - xi1 + alpha**2 * xi1))  # sin theta, float64
    xi = np.stack([np.zeros_like(xi1), xi1], -1)
    h32 = np.asarray(sample_ggx_h(jnp.asarray(xi, jnp.float32), jnp.float32(alpha)))
    np.testing.assert_allclose(np.hypot(h32[:, 0], h32[:, 1]), exact, rtol=1e-5)


def test_pdf_ggx_h_is_d_times_cos_and_integrates_to_one():
    nh = np.linspace(-0.2, 1.0, 25)
    for alpha in ALPHAS:
        np.testing.assert_allclose(pdf_ggx_h(nh, alpha), ref.d_ggx(nh, alpha) * np.maximum(nh, 0), rtol=1e-10)
        f = lambda t, a=alpha: float(pdf_ggx_h(np.cos(t), a)) * np.sin(t) * 2 * np.pi
        pts = [p for p in (alpha, 4 * alpha) if p < np.pi / 2]
        total = integrate.quad(f, 0, np.pi / 2, points=pts, epsabs=1e-12, epsrel=1e-10, limit=200)[0]
        assert abs(total - 1.0) < 1e-8, alpha


def test_ggx_sampler_and_its_pdf_agree():
    """Importance-sampling identity E[g(h) / p(h)] = int g dw_h ties the sampler to its pdf.
    g = (n.h)^2 has int = 2 pi / 3 over the hemisphere."""
    alpha = 0.6
    h = sample_ggx_h(hammersley(N_QMC, jnp.float64), alpha)
    est = float(jnp.mean(h[:, 2] ** 2 / pdf_ggx_h(h[:, 2], alpha)))
    assert abs(est / (2 * np.pi / 3) - 1) < 1e-3


# --------------------------------------------------------------------------------------------
# VNDF sampling
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mu", [1.0, 0.7, 0.3, 0.1])
def test_pdf_ggx_vndf_matches_textbook_and_integrates_to_one(mu):
    """docs/math.md §7.1: int G1(v) max(0, v.h) D(h) dh = cos theta_v, i.e. the pdf integrates to 1,
    for alpha in {1, 0.5, 0.3}."""
    v = np.array([np.sqrt(1 - mu * mu), 0.0, mu])
    for alpha in (1.0, 0.5, 0.3):
        T, P, W = _visible_grid(alpha, mu)
        h = _dirs(T, P)
        vh, nh = h @ v, h[..., 2]
        p = np.asarray(pdf_ggx_vndf(np.full_like(nh, mu), nh, vh, alpha))
        expect = ref.smith_g1(mu, alpha) * np.maximum(vh, 0) * ref.d_ggx(nh, alpha) / mu
        np.testing.assert_allclose(p, expect, rtol=1e-10, atol=1e-300)
        assert abs(np.sum(p * W) - 1.0) < 1e-8, alpha
        # the density of l = reflect(v, h) is p / (4 v.h) (pdf_reflect), 0 where v.h <= 0
        np.testing.assert_allclose(S.pdf_reflect(p, vh), p / (4 * vh), rtol=1e-12)
    assert float(S.pdf_reflect(1.0, -0.2)) == 0.0


@pytest.mark.parametrize("dtype", DTYPES)
def test_vndf_sample_mean_matches_quadrature(dtype):
    """Mean of g(h) = h.x + 2 h.z^2 over VNDF samples vs quadrature of g G1 max(0,v.h) D / NoV
    (textbook terms). The NDF-sampled mean misses the oracle by far more than the tolerance, so
    the test tells the two distributions apart."""
    g = lambda h: h[..., 0] + 2 * h[..., 2] ** 2
    xi = hammersley(N_QMC, dtype)
    tol = 2e-3
    for mu, alpha in [(0.4, 0.2), (0.9, 0.6), (0.15, 0.5)]:
        v = np.array([np.sqrt(1 - mu * mu), 0.0, mu])
        T, P, W = _visible_grid(alpha, mu)
        h = _dirs(T, P)
        dens = ref.smith_g1(mu, alpha) * np.maximum(h @ v, 0) * ref.d_ggx(h[..., 2], alpha) / mu
        oracle = np.sum(g(h) * dens * W)
        hs = np.asarray(sample_ggx_vndf(jnp.asarray(v, dtype), xi, jnp.asarray(alpha, dtype)), np.float64)
        assert abs(g(hs).mean() - oracle) < tol, (mu, alpha)
        ndf = np.asarray(sample_ggx_h(xi, jnp.asarray(alpha, dtype)), np.float64)
        assert abs(g(ndf).mean() - oracle) > 10 * tol, (mu, alpha)
        assert np.all(hs @ v > -1e-6)  # visible normals only (v.h >= 0 up to rounding)


def test_vndf_at_normal_incidence_is_the_ndf():
    """For v = n the visible-normal density G1 (v.h) D / NoV reduces to D (n.h)."""
    h = sample_ggx_vndf(jnp.array([0.0, 0.0, 1.0]), hammersley(N_QMC, jnp.float64), 0.3)
    assert abs(float(jnp.mean(h[:, 2])) - _mean_cos_quad(0.3)) < 1e-4


# --------------------------------------------------------------------------------------------
# Cosine sampling
# --------------------------------------------------------------------------------------------


def test_cosine_sampling_mean_and_pdf():
    for dtype in DTYPES:
        d = sample_cosine(hammersley(N_QMC, dtype))
        assert d.dtype == dtype
        # E[cos theta] under cos/pi = (1/pi) int cos^2 dw = 2/3
        assert abs(float(jnp.mean(d[:, 2].astype(jnp.float64))) - 2 / 3) < 1e-4
    total = integrate.quad(lambda t: float(S.pdf_cosine(np.cos(t))) * np.sin(t) * 2 * np.pi, 0, np.pi / 2)[0]
    assert abs(total - 1) < 1e-12
    assert float(S.pdf_cosine(-0.5)) == 0.0


# --------------------------------------------------------------------------------------------
# Shared properties: unit length, finiteness at the stiff inputs, jit/vmap
# --------------------------------------------------------------------------------------------

_EDGE_XI = np.array([[a, b] for a in (0.0, 0.3, 1.0) for b in (0.0, 1e-7, 0.5, 1 - 1e-7, 1.0)])
_V_CASES = {  # v in the tangent frame: normal, oblique, grazing, on the horizon (v.z = 0)
    "normal": [0.0, 0.0, 1.0],
    "oblique": [0.6, 0.0, 0.8],
    "grazing": [np.sqrt(1 - 1e-12), 0.0, 1e-6],
    "horizon": [1.0, 0.0, 0.0],
}


def _all_samplers(xi, alpha):
    """Every sampler on the same samples: (6, A, K, 3) for alpha (A, 1) and xi (K, 2); the four
    views of VNDF in one broadcast call (v (4, 1, 1, 3))."""
    ggx = S.sample_ggx_h(xi, alpha)
    v = jnp.asarray(list(_V_CASES.values()), xi.dtype)[:, None, None, :]
    vndf = S.sample_ggx_vndf(v, xi, alpha)
    cos = jnp.broadcast_to(S.sample_cosine(xi), ggx.shape)
    return jnp.concatenate([ggx[None], vndf, cos[None]])


@pytest.mark.parametrize("dtype", DTYPES)
def test_samples_unit_length_upper_hemisphere_finite_gradients(dtype):
    """Every sampler at alpha in {0, 1e-4, 0.3, 1} x xi on the edges of the unit square (0, 1,
    1 -+ 1e-7) and inside: finite, unit length, n.h >= 0; h = n at alpha = 0; finite derivatives
    with respect to xi and alpha."""
    xi = jnp.asarray(np.concatenate([_EDGE_XI, np.asarray(hammersley(64, jnp.float64))]), dtype)
    alpha = jnp.asarray([[0.0], [1e-4], [0.3], [1.0]], dtype)
    # Values and derivatives from one forward-mode pass with a dense random tangent: a NaN/inf
    # partial derivative anywhere shows up in the output tangent (NaN * t = NaN for t != 0), and
    # it compiles much faster than the reverse-mode gradient of all six samplers.
    rng = np.random.default_rng(0)
    tx, ta = (jnp.asarray(rng.uniform(0.5, 1.0, x.shape), dtype) for x in (xi, alpha))
    h, tangent = jax.jit(lambda x, a: jax.jvp(_all_samplers, (x, a), (tx, ta)))(xi, alpha)
    assert np.isfinite(np.asarray(tangent)).all()
    h = np.asarray(h)
    assert h.shape == (6, 4, len(xi), 3) and h.dtype == dtype and np.isfinite(h).all()
    tol = 10 * float(jnp.finfo(dtype).eps)
    np.testing.assert_allclose(np.linalg.norm(h.astype(np.float64), axis=-1), 1.0, atol=tol)
    assert np.all(h[..., 2] >= 0.0)
    np.testing.assert_array_equal(h[:5, 0, :, :2], 0.0)  # alpha = 0 is a mirror: h = n


@pytest.mark.parametrize("dtype", DTYPES)
def test_pdfs_at_alpha_zero_are_the_delta_with_finite_gradients(dtype):
    nh = jnp.asarray([1.0, 0.999, 0.5, 0.0, -0.3], dtype)
    zero = jnp.asarray(0.0, dtype)
    p = np.asarray(pdf_ggx_h(nh, zero))
    assert p[0] == np.inf and np.all(p[1:] == 0.0)
    pv = np.asarray(pdf_ggx_vndf(jnp.full_like(nh, 0.5), nh, nh, zero))
    assert pv[0] == np.inf and np.all(pv[1:] == 0.0)

    def finite_part(a, c):
        return (
            jnp.sum(S.pdf_ggx_h(c, a)[1:])
            + jnp.sum(S.pdf_ggx_vndf(c, c, c, a)[1:])
            + jnp.sum(S.pdf_reflect(S.pdf_ggx_h(c, a + 0.5), c))
        )

    g = jax.jit(jax.grad(finite_part, argnums=(0, 1)))(zero, nh)
    assert all(np.isfinite(np.asarray(x)).all() for x in g)
    # NoV <= 0 (the viewer below the surface): density 0, not NaN
    assert float(pdf_ggx_vndf(0.0, 1.0, 0.5, 0.3)) == 0.0


def test_samplers_vmap_and_broadcasting_agree():
    """vmap over alpha == broadcasting alpha (A, 1) against the samples."""
    xi = hammersley(N_QMC, jnp.float64)
    alphas = jnp.asarray(ALPHAS, jnp.float64)
    batched = jax.jit(jax.vmap(S.sample_ggx_h, in_axes=(None, 0)))(xi, alphas)
    np.testing.assert_allclose(sample_ggx_h(xi, alphas[:, None]), batched, rtol=1e-12, atol=1e-15)
    assert float(jnp.abs(batched[0, :, 2] - batched[2, :, 2]).max()) > 0.1  # the rows differ


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------


def _frame_normals():
    """+-X, +-Y, +-Z, both sides of the |n.z| = 0.999 switch, 20 random unit normals, and the
    zero vector last (its frame must be finite: zero vectors)."""
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    c = 0.999  # the switch between the two `up` vectors, on both sides
    near = [[np.sqrt(1 - z * z), 0, z] for z in (c - 1e-6, c, c + 1e-6, -c + 1e-6, -c, -c - 1e-6)]
    rnd = np.random.default_rng(0).normal(size=(20, 3))
    return np.concatenate([axes, near, rnd / np.linalg.norm(rnd, axis=-1, keepdims=True), np.zeros((1, 3))])


@pytest.mark.parametrize("dtype", DTYPES)
def test_tangent_frame_orthonormal_right_handed_everywhere(dtype):
    n = jnp.asarray(_frame_normals(), dtype)
    # values and (forward-mode, dense random tangent) derivatives in one compiled call
    tn = jnp.asarray(np.random.default_rng(3).normal(size=n.shape), dtype)
    (t, b), (dt, db) = jax.jit(lambda x: jax.jvp(S.tangent_frame, (x,), (tn,)))(n)
    assert np.isfinite(np.asarray(dt)).all() and np.isfinite(np.asarray(db)).all()
    t, b, nn = (np.asarray(x, np.float64) for x in (t, b, n))
    np.testing.assert_array_equal(np.concatenate([t[-1], b[-1]]), 0.0)  # zero normal: zero frame
    t, b, nn = t[:-1], b[:-1], nn[:-1]
    tol = 10 * float(jnp.finfo(dtype).eps)
    for a, c, expect in [(t, t, 1), (b, b, 1), (t, b, 0), (t, nn, 0), (b, nn, 0)]:
        np.testing.assert_allclose(np.sum(a * c, -1), expect, atol=tol)
    np.testing.assert_allclose(np.cross(t, b), nn, atol=tol)


@pytest.mark.parametrize("dtype", DTYPES)
def test_to_world_maps_the_tangent_frame_onto_n(dtype):
    n = jnp.asarray(_frame_normals()[:-1], dtype)
    tol = 10 * float(jnp.finfo(dtype).eps)
    to_world = jax.jit(S.to_world)
    z = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], dtype), n.shape)
    np.testing.assert_allclose(to_world(z, n), n, atol=tol)
    a = jnp.asarray(np.random.default_rng(1).normal(size=(len(n), 3)), dtype)
    b = jnp.asarray(np.random.default_rng(2).normal(size=(len(n), 3)), dtype)
    np.testing.assert_allclose(jnp.sum(to_world(a, n) * to_world(b, n), -1), jnp.sum(a * b, -1), atol=100 * tol)
    # a GGX sample around n keeps n.h = local z (the tangent-frame convention)
    h_local = sample_ggx_h(hammersley(len(n), dtype), jnp.asarray(0.5, dtype))
    np.testing.assert_allclose(jnp.sum(to_world(h_local, n) * n, -1), h_local[:, 2], atol=tol)


def test_reflect_mirrors_about_h():
    v = np.array([0.6, 0.0, 0.8])
    np.testing.assert_allclose(S.reflect(v, np.array([0.0, 0.0, 1.0])), [-0.6, 0.0, 0.8], atol=1e-15)
    h = np.array([0.0, 0.6, 0.8])
    l = np.asarray(S.reflect(v, h))
    np.testing.assert_allclose(np.linalg.norm(l), 1.0)
    np.testing.assert_allclose((v + l) / np.linalg.norm(v + l), h, atol=1e-15)
