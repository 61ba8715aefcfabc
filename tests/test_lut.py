"""The split-sum BRDF LUT: the float64 reference against docs/math.md §7.2/§7.3 and an independent scipy
integral, the fast table against the reference at every texel, lookup, gradients, bad arguments.

Oracles: docs/math.md tables (quoted to 4 decimals, stated error <~1e-4), closed forms (r = 0 mirror,
1 - ln 2 at NoV = 1, r = 1; the grazing limit 20/21, 1/21 at r = 1), scipy adaptive quadrature in
l-space written here from the textbook terms of tests/reference.py. `lut_reference` is itself only
an oracle for `compute_brdf_lut` after it has passed those checks.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as ref
from scipy import integrate

from jaxpbr.shading.lut import (
    SMITH_VARIANTS,
    compute_brdf_lut,
    lut_lookup,
    lut_reference,
)

lookup = jax.jit(lut_lookup)  # one compilation per shape instead of one per primitive (eager)
lookup_clamped = jax.jit(functools.partial(lut_lookup, edges="clamp"))

NOV_TABLE = np.array([0.02, 0.1, 0.25, 0.5, 0.75, 1.0])
# docs/math.md §7.2, rows r, columns NoV_TABLE, entries (A, B).
TABLE = {
    "correlated": {
        0.0: [(0.0961, 0.9039), (0.4095, 0.5905), (0.7627, 0.2373), (0.9688, 0.0312), (0.9990, 0.0010), (1, 0)],
        0.25: [(0.4580, 0.4812), (0.5052, 0.3916), (0.7580, 0.2035), (0.9557, 0.0326), (0.9923, 0.0015), (0.9957, 0.0)],
        0.5: [(0.7870, 0.1807), (0.7519, 0.1397), (0.7593, 0.0808), (0.8349, 0.0223), (0.8888, 0.0027), (0.9158, 0.0)],
        0.75: [(0.8770, 0.0747), (0.7958, 0.0526), (0.7165, 0.0279), (0.6547, 0.0085), (0.6312, 0.0016), (0.6268, 0.0)],
        1.0: [(0.8819, 0.0394), (0.7363, 0.0239), (0.5868, 0.0109), (0.4477, 0.0030), (0.3639, 0.0006), (0.3068, 0.0)],
    },
    "schlick_ggx": {
        0.25: [(0.3553, 0.3367), (0.3913, 0.2911), (0.6573, 0.1733), (0.9023, 0.0305), (0.9717, 0.0014), (0.9943, 0.0)],
        0.5: [(0.6601, 0.1278), (0.5902, 0.0984), (0.6094, 0.0609), (0.7285, 0.0185), (0.8275, 0.0024), (0.8950, 0.0)],
        0.75: [(0.6904, 0.0460), (0.6409, 0.0353), (0.5935, 0.0206), (0.5730, 0.0070), (0.5821, 0.0015), (0.6036, 0.0)],
        1.0: [(0.5833, 0.0183), (0.5444, 0.0136), (0.4835, 0.0075), (0.4067, 0.0025), (0.3501, 0.0006), (0.3068, 0.0)],
    },
}


def _centres(n):
    return (np.arange(n) + 0.5) / n


def _closed_form_r0(mu):
    w = (1.0 - np.asarray(mu, np.float64)) ** 5
    return np.stack([1.0 - w, w], axis=-1)


# --------------------------------------------------------------------------------------------
# The reference
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("smith", [s for s in SMITH_VARIANTS if s in TABLE])  # docs/math.md tables two of them
def test_reference_matches_math_tables(smith):
    """docs/math.md §7.2 to its precision: 4 decimals (rounding 5e-5) with error <~1e-4 -> 1e-4."""
    rows = TABLE[smith]
    r = np.repeat(list(rows), len(NOV_TABLE))
    mu = np.tile(NOV_TABLE, len(rows))
    got = lut_reference(mu, r, smith=smith)
    expect = np.concatenate([np.array(v, float) for v in rows.values()])
    np.testing.assert_allclose(got, expect, atol=1e-4)


@pytest.mark.parametrize("smith", SMITH_VARIANTS)
def test_reference_closed_forms(smith):
    mu = np.array([1e-9, 1e-3, 0.02, 0.3, 0.77, 1.0])
    # r = 0: the mirror, exactly (docs/math.md §7.2 "Limits")
    np.testing.assert_allclose(lut_reference(mu, 0.0, smith=smith), _closed_form_r0(mu), rtol=0, atol=1e-12)
    # NoV = 1, r = 1: D = 1/pi, G1(v) = 1 and both variants have G2 = 2c/(1+c), c = n.l, so
    # f (n.l) dl = c/(1+c) dc: E = A + B = 1 - ln 2 exactly (docs/math.md §7.3), and with
    # v.h = sqrt((1+c)/2), B = int_0^1 c/(1+c) (1 - sqrt((1+c)/2))^5 dc = 3.36e-5 (so A alone is
    # not 1 - ln 2, as docs/math.md §7.2 words it; the difference is below its 1e-4 precision).
    b_exact = integrate.quad(lambda c: c / (1 + c) * (1 - np.sqrt((1 + c) / 2)) ** 5, 0, 1, epsabs=1e-15)[0]
    a, b = lut_reference(1.0, 1.0, smith=smith)
    assert abs(a + b - (1.0 - np.log(2.0))) < 1e-10 and abs(b - b_exact) < 1e-10
    # B(NoV = 1) < 1e-4 for every r (docs/math.md §7.2)
    assert np.all(lut_reference(1.0, np.array([0.1, 0.25, 0.5, 0.75]), smith=smith)[:, 1] < 1e-4)


def test_reference_normal_incidence_albedo_math_7_3():
    """E(mu = 1) = A + B for the height-correlated lobe, quoted to 6 decimals (docs/math.md §7.3)."""
    r = np.array([0.1, 0.25, 0.5, 0.75, 1.0])
    e = lut_reference(np.ones_like(r), r, smith="correlated").sum(-1)
    np.testing.assert_allclose(e, [0.999899, 0.995688, 0.915812, 0.626886, 0.306853], atol=1e-6)
    # and E(mu) at 0.5, 0.1 to the table's 4 decimals
    e5 = lut_reference(0.5, r[1:], smith="correlated").sum(-1)
    e1 = lut_reference(0.1, r[1:], smith="correlated").sum(-1)
    np.testing.assert_allclose(e5, [0.9883, 0.8572, 0.6632, 0.4507], atol=1e-4)
    np.testing.assert_allclose(e1, [0.8968, 0.8916, 0.8484, 0.7602], atol=1e-4)


def test_separable_smith_is_below_the_correlated_one():
    """G1(v) G1(l) <= 1 / (1 + Lambda(v) + Lambda(l)) (the uncorrelated form ignores the height
    correlation and shadows more): the separable table's A + B is below the correlated one's
    everywhere, equal at NoV = 1 (G1(v) = 1 there: both are G1(l)), and the gap grows at grazing
    NoV and high roughness."""
    mu = np.array([0.05, 0.3, 0.7, 1.0])
    r = np.array([0.3, 0.6, 1.0])
    M, R = np.meshgrid(mu, r, indexing="ij")
    sep = lut_reference(M, R, smith="separable").sum(-1)
    cor = lut_reference(M, R, smith="correlated").sum(-1)
    assert np.all(sep[:-1] < cor[:-1])
    np.testing.assert_allclose(sep[-1], cor[-1], atol=1e-12)
    assert (cor - sep)[0, -1] > 0.2 and (cor - sep)[0, -1] > 100 * (cor - sep)[2, 0]


def test_reference_grazing_limit():
    """NoV -> 0 (docs/math.md §7.2): height-correlated A + B -> 1; at r = 1 the limit is exact:
    the visible normals of a grazing v have density prop. to max(0, h.x) with D = 1/pi, so
    B -> E[(1 - c)^5] with c ~ 2c dc, = 1/21, A -> 20/21. Schlick-GGX stays below 1 (MATH's values).
    (docs/math.md quotes correlated A = 0.4895 / 0.8067 / 0.9520 at NoV = 1e-6; those sum to 0.9997 and
    are ~3.5e-4 low: the limit is 0.489829 / 0.807064 / 0.952381 by a direct 2-D quadrature.)"""
    r = np.array([0.25, 0.5, 1.0])
    corr = lut_reference(1e-6, r, smith="correlated")
    np.testing.assert_allclose(corr.sum(-1), 1.0, atol=1e-4)
    np.testing.assert_allclose(corr[:, 1], [0.5102, 0.1929, 0.0476], atol=1e-4)  # MATH's B values
    np.testing.assert_allclose(lut_reference(1e-9, 1.0, smith="correlated"), [20 / 21, 1 / 21], atol=1e-6)
    sch = lut_reference(1e-6, r, smith="schlick_ggx")
    np.testing.assert_allclose(sch, [(0.4492, 0.4029), (0.7010, 0.1384), (0.5940, 0.0197)], atol=1e-4)


def _scipy_l_space(mu, r, smith):
    """(A, B) by scipy adaptive quadrature over l = (theta_l, phi_l) about n, from the textbook
    terms of tests/reference.py: f_spec (n.l) = D G2 / (4 NoV NoL) NoL, no half-vector change of
    variables and no horizon geometry (the domain is the plain hemisphere)."""
    alpha = r * r
    v = np.array([np.sqrt(1 - mu * mu), 0.0, mu])
    theta_v = np.arccos(mu)

    def f(tl, pl, channel):
        l = np.array([np.sin(tl) * np.cos(pl), np.sin(tl) * np.sin(pl), np.cos(tl)])
        h = (v + l) / np.linalg.norm(v + l)
        if smith == "correlated":
            vis = ref.v_smith_correlated(mu, l[2], alpha)
        elif smith == "separable":
            vis = ref.v_smith_separable(mu, l[2], alpha)
        else:
            vis = ref.v_schlick_ggx(mu, l[2], ref.k_ibl(r))
        fc = (1 - v @ h) ** 5
        return ref.d_ggx(h[2], alpha) * vis * l[2] * np.sin(tl) * (fc if channel else 1 - fc)

    out = []
    for ch in (0, 1):
        inner = lambda p, ch=ch: integrate.quad(
            lambda t: f(t, np.pi - p, ch), 0, np.pi / 2, points=[theta_v], epsabs=1e-11
        )[0]
        out.append(2 * integrate.quad(inner, 0, np.pi, points=[0.1, 1.0], epsabs=1e-11)[0])
    return np.array(out)


@pytest.mark.parametrize("smith", SMITH_VARIANTS)
def test_reference_matches_independent_scipy_integral(smith):
    for mu, r in [(0.35, 0.8), (0.9, 0.6)]:
        np.testing.assert_allclose(lut_reference(mu, r, smith=smith), _scipy_l_space(mu, r, smith), atol=1e-8)


@pytest.mark.slow
def test_reference_converged_under_refinement():
    """Default rule (order 10, 7 levels) vs order 14 / 8 levels at the hardest texels of a 256^2
    table (first column, low roughness) and a few easy ones: agreement to 1e-8 (measured 8e-10
    at worst over a 17 000-texel subset, where the refined rule also matches a third, differently
    built integration to ~1e-11)."""
    mu = np.array([0.5 / 256] * 5 + [0.3, 0.999])
    r = np.array([0.5 / 256, 0.01, 0.0215, 0.2, 1.0, 0.5, 0.05])
    for smith in SMITH_VARIANTS:
        base = lut_reference(mu, r, smith=smith)
        fine = lut_reference(mu, r, smith=smith, order=14, levels=8)
        np.testing.assert_allclose(base, fine, rtol=0, atol=1e-8)


def test_reference_validates_its_arguments():
    with pytest.raises(ValueError, match="n_dot_v must lie in"):
        lut_reference(0.0, 0.5)
    with pytest.raises(ValueError, match="n_dot_v must lie in"):
        lut_reference(1.5, 0.5)
    with pytest.raises(ValueError, match="roughness must lie in"):
        lut_reference(0.5, -0.1)
    with pytest.raises(ValueError, match="smith must be one of"):
        lut_reference(0.5, 0.5, smith="height-correlated")
    with pytest.raises(ValueError, match="order must be a positive int"):
        lut_reference(0.5, 0.5, order=0)


# --------------------------------------------------------------------------------------------
# compute_brdf_lut
# --------------------------------------------------------------------------------------------


# Small tables for the every-texel check: non-square in both orientations (a transposed or
# shifted layout is off by far more than the tolerance), one float32 and one float64.
SMALL = {"correlated": ((32, 24), jnp.float32), "schlick_ggx": ((24, 32), jnp.float64), "separable": ((20, 16), jnp.float32)}


@pytest.fixture(scope="module")
def small_luts():
    return {s: compute_brdf_lut(size=size, smith=s, dtype=dt) for s, (size, dt) in SMALL.items()}


@pytest.mark.parametrize("smith", SMITH_VARIANTS)
def test_lut_every_texel_matches_reference(small_luts, smith):
    """Every texel vs the reference at r = (j + 0.5)/n_r, NoV = (i + 0.5)/n_nov. The requirement
    is 1e-4; the default rule is measured at ~1.4e-6 (256^2), so 1e-5 is asserted to catch a loss
    of convergence."""
    (n_r, n_nov), dtype = SMALL[smith]
    lut = small_luts[smith]
    assert lut.shape == (n_r, n_nov, 2) and lut.dtype == dtype
    R, M = np.meshgrid(_centres(n_r), _centres(n_nov), indexing="ij")
    err = np.abs(np.asarray(lut, np.float64) - lut_reference(M, R, smith=smith))
    assert err.max() < 1e-5, (err.max(), np.unravel_index(err.argmax(), err.shape))


def test_lut_first_row_approaches_the_mirror():
    """The r = 0.5/n row vs the exact r = 0 row (docs/math.md §7.2). Height-correlated Smith deviates by
    O((alpha/NoV)^2): < 1e-4 from 128 rows on (measured 9.9e-6 at 128, 2.2e-6 at 256). Schlick-GGX
    deviates to first order, G1_schlick(NoV) = NoV / (NoV (1-k) + k) ~ 1 - k/NoV with k = alpha/2,
    and the mirror of a grazing v is grazing too, so the row is ~G1_schlick(NoV)^2 times the
    mirror values: 3.8e-3 (128) / 1.9e-3 (256) from the r = 0 closed form in the first column,
    but within 1e-5 of that product."""
    for n in (128,):  # 256 in the slow test
        c = _centres(n)
        row = lut_reference(c, c[0], smith="correlated")
        assert np.abs(row - _closed_form_r0(c)).max() < 1e-4
        k = c[0] ** 2 / 2
        g1 = c / (c * (1 - k) + k)
        row = lut_reference(c, c[0], smith="schlick_ggx")
        assert np.abs(row - g1[:, None] ** 2 * _closed_form_r0(c)).max() < 1e-5
        assert np.abs(row - _closed_form_r0(c)).max() > 1e-3  # the first-order effect is real


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(size=0), "size must be a positive int"),
        (dict(size=-4), "size must be a positive int"),
        (dict(size=2.5), "size must be a positive int"),
        (dict(size="128"), "size must be a positive int"),
        (dict(size=True), "size must be a positive int"),
        (dict(size=(32,)), "size must be an int or a pair"),
        (dict(size=(0, 32)), "size must be a positive int"),
        (dict(samples=0), "samples must be a positive int"),
        (dict(samples=10.0), "samples must be a positive int"),
        (dict(smith="uncorrelated"), "smith must be one of"),
        (dict(smith="Schlick"), "smith must be one of"),
        (dict(dtype=jnp.int32), "dtype must be float32 or float64"),
    ],
)
def test_compute_brdf_lut_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        compute_brdf_lut(**kwargs)


def test_schlick_is_a_deprecated_alias_of_schlick_ggx():
    """The LUT's Schlick-GGX (k = alpha/2) is "schlick_ggx" (distinct from brdf's Smith-GGX
    "separable"); the old name "schlick" still works, with a DeprecationWarning."""
    with pytest.warns(DeprecationWarning, match="schlick_ggx"):
        old = compute_brdf_lut(size=8, smith="schlick")
    np.testing.assert_array_equal(np.asarray(old), np.asarray(compute_brdf_lut(size=8, smith="schlick_ggx")))
    with pytest.warns(DeprecationWarning, match="schlick_ggx"):
        ref_old = lut_reference(0.5, 0.5, smith="schlick")
    np.testing.assert_array_equal(ref_old, lut_reference(0.5, 0.5, smith="schlick_ggx"))


def test_positional_smith_still_works_with_a_deprecation_warning():
    with pytest.warns(DeprecationWarning, match="smith=... by keyword"):
        old = compute_brdf_lut(8, "schlick_ggx")
    np.testing.assert_array_equal(np.asarray(old), np.asarray(compute_brdf_lut(size=8, smith="schlick_ggx")))
    with pytest.warns(DeprecationWarning, match="positionally"):
        np.testing.assert_array_equal(lut_reference(0.5, 0.5, "correlated"), lut_reference(0.5, 0.5))
    with pytest.raises(TypeError, match="positional"):
        compute_brdf_lut(8, "correlated", 864)


# --------------------------------------------------------------------------------------------
# lut_lookup
# --------------------------------------------------------------------------------------------


def _bilinear_table(n_r, n_nov, channels=2):
    """LUT holding f(r, mu) = (1 + 2r + 3mu + 5 r mu, -r mu + 0.5) at the texel centres: a
    bilinear function, which bilinear interpolation must reproduce exactly between centres."""
    r, mu = np.meshgrid(_centres(n_r), _centres(n_nov), indexing="ij")
    f = np.stack([1 + 2 * r + 3 * mu + 5 * r * mu, -r * mu + 0.5], -1)
    return f[..., :channels]


def test_lookup_exact_at_texel_centres_and_bilinear_between():
    rng = np.random.default_rng(0)
    lut = rng.uniform(size=(5, 7, 2))
    j, i = np.meshgrid(np.arange(5), np.arange(7), indexing="ij")
    got = lookup(lut, (i + 0.5) / 7, (j + 0.5) / 5)
    np.testing.assert_allclose(got, lut, rtol=0, atol=1e-15)
    # halfway between four centres: their mean
    mid = lookup(lut, 2.0 / 7, 3.0 / 5)  # between i = 1, 2 and j = 2, 3
    np.testing.assert_allclose(mid, lut[2:4, 1:3].mean(axis=(0, 1)), atol=1e-15)
    # a bilinear function is reproduced exactly anywhere between the centres
    table = _bilinear_table(5, 7)
    mu = rng.uniform(0.5 / 7, 6.5 / 7, 50)
    r = rng.uniform(0.5 / 5, 4.5 / 5, 50)
    expect = np.stack([1 + 2 * r + 3 * mu + 5 * r * mu, -r * mu + 0.5], -1)
    np.testing.assert_allclose(lookup(table, mu, r), expect, atol=1e-13)


def test_lookup_clamps_to_edge():
    """edges="clamp": beyond the outermost texel centres the value is that at the clamped
    coordinates: the bilinear table function evaluated there (its exact interpolant inside)."""
    table = _bilinear_table(4, 6)
    lo_mu, hi_mu, lo_r, hi_r = 0.5 / 6, 5.5 / 6, 0.5 / 4, 3.5 / 4
    f = lambda m, r: np.array([1 + 2 * r + 3 * m + 5 * r * m, -r * m + 0.5])
    for mu, r, mu_c, r_c in [
        (0.0, 0.0, lo_mu, lo_r),
        (-3.0, 0.3, lo_mu, 0.3),
        (1.0, 1.0, hi_mu, hi_r),
        (7.0, -2.0, hi_mu, lo_r),
        (0.4, 1.5, 0.4, hi_r),
    ]:
        np.testing.assert_allclose(lookup_clamped(table, mu, r), f(mu_c, r_c), atol=1e-14)
    # a 1 x 1 table is a constant
    np.testing.assert_allclose(lookup_clamped(np.full((1, 1, 2), 0.25), np.array([0.0, 0.7, 3.0]), 0.5), 0.25)


def test_lookup_split_sum_edges():
    """Default edges: up to r = 1 and NoV = 1 the table is extrapolated linearly over the last half
    texel, so a bilinear table function is reproduced exactly to the corner (it clamped at the last
    centres: 1.28 % high at r = 1 in a 128^2 LUT, issue 13); below the first row's centre the value
    blends linearly into the r = 0 closed form (1 - (1 - mu)^5, (1 - mu)^5); beyond [0, 1] it clamps."""
    n_r, n_nov = 4, 6
    table = _bilinear_table(n_r, n_nov)
    f = lambda m, r: np.stack([1 + 2 * r + 3 * m + 5 * r * m, -r * m + 0.5], -1)  # noqa: E731
    rng = np.random.default_rng(3)
    mu = np.concatenate([rng.uniform(0.5 / n_nov, 1.0, 200), [1.0, 1.0, 5.5 / 6]])
    r = np.concatenate([rng.uniform(0.5 / n_r, 1.0, 200), [1.0, 3.5 / 4, 1.0]])
    np.testing.assert_allclose(lookup(table, mu, r), f(mu, r), atol=1e-13)
    np.testing.assert_allclose(lookup(table, 7.0, 2.0), f(1.0, 1.0), atol=1e-13)  # clamped beyond
    # r = 0: the closed form, exactly, at every NoV in [0, 1]
    m = np.linspace(0.0, 1.0, 101)
    np.testing.assert_allclose(lookup(table, m, 0.0), _closed_form_r0(m), rtol=0, atol=1e-15)
    # between r = 0 and the first centre: linear in r between the two
    rr = 0.3 * 0.5 / n_r
    mm = np.linspace(0.5 / n_nov, 1.0, 21)
    expect = _closed_form_r0(mm) + (f(mm, 0.5 / n_r) - _closed_form_r0(mm)) * 0.3
    np.testing.assert_allclose(lookup(table, mm, rr), expect, atol=1e-13)
    with pytest.raises(ValueError, match="edges"):
        lut_lookup(table, 0.5, 0.5, edges="mirror")
    with pytest.raises(ValueError, match="2 channels"):
        lut_lookup(np.zeros((4, 4, 3)), 0.5, 0.5)


def test_lookup_edges_against_the_float64_reference(small_luts):
    """The measured gain at the edges of a 24 x 24 table (old: clamp to the edge texels)."""
    lut = small_luts["correlated"]
    pts = [(0.5, 1.0), (0.9, 1.0), (1.0, 0.5), (1.0, 1.0), (0.5, 0.999)]
    for mu, r in pts:
        ref = lut_reference(mu, r)
        new = np.abs(np.asarray(lookup(lut, mu, r)) - ref).max()
        old = np.abs(np.asarray(lookup_clamped(lut, mu, r)) - ref).max()
        assert new < 2.5e-3 and new < old / 3, (mu, r, new, old)


def test_lookup_shapes_dtype_jit_vmap():
    table = jnp.asarray(_bilinear_table(8, 8), jnp.float32)
    mu = jnp.linspace(0, 1, 12, dtype=jnp.float32).reshape(3, 1, 4)
    r = jnp.linspace(0, 1, 2, dtype=jnp.float32).reshape(1, 2, 1)
    out = lookup(table, mu, r)
    assert out.shape == (3, 2, 4, 2) and out.dtype == jnp.float32
    m_, r_ = np.broadcast_arrays(np.asarray(mu, np.float64), np.asarray(r, np.float64))
    expect = np.stack([1 + 2 * r_ + 3 * m_ + 5 * r_ * m_, -r_ * m_ + 0.5], -1)
    inside = ((m_ > 1 / 16) & (m_ < 15 / 16) & (r_ > 1 / 16) & (r_ < 15 / 16))[..., None]
    np.testing.assert_allclose(np.where(inside, out, expect), expect, rtol=1e-6)
    vm = jax.jit(jax.vmap(lut_lookup, in_axes=(None, 0, None)))(table, mu.reshape(12), 0.3)
    np.testing.assert_allclose(vm, lookup(table, mu.reshape(12), jnp.float32(0.3)), rtol=1e-6)
    with pytest.raises(ValueError, match="lut must have shape"):
        lut_lookup(np.zeros((4, 4)), 0.5, 0.5)


def test_lookup_gradients_finite_everywhere():
    """d/dNoV, d/dr and d/dlut at the edges (0, 1), texel centres, and far outside [0, 1]
    (float32, the dtype LUTs are stored in)."""
    dtype = jnp.float32
    table = jnp.asarray(_bilinear_table(8, 8), dtype)
    pts = jnp.asarray([-1.0, 0.0, 1 / 16, 0.3, 0.5, 15 / 16, 1.0, 2.0], dtype)
    mu, r = jnp.meshgrid(pts, pts, indexing="ij")
    f = lambda t, m, rr: jnp.sum(lut_lookup(t, m, rr) * jnp.asarray([1.0, -2.0], dtype))
    g_t, g_mu, g_r = jax.jit(jax.grad(f, argnums=(0, 1, 2)))(table, mu, r)
    for g in (g_t, g_mu, g_r):
        assert np.isfinite(np.asarray(g)).all()
    # inside and in the extrapolated bands up to NoV = 1, r = 1: the slope of the bilinear
    # function; where the coordinates clamp (NoV below the first centre, beyond [0, 1]): 0
    m_, r_ = np.asarray(mu), np.asarray(r)
    inside = (m_ > 1 / 16) & (m_ < 1.0) & (r_ > 1 / 16) & (r_ < 1.0)
    np.testing.assert_allclose(np.asarray(g_mu)[inside], ((3 + 5 * r_) + 2 * r_)[inside], rtol=1e-5)
    assert np.all(np.asarray(g_mu)[((m_ < 1 / 16) | (m_ > 1.0)) & (r_ >= 1 / 16)] == 0.0)


def test_lookup_r0_against_closed_form(small_luts):
    """At r = 0 the lookup is the mirror's closed form at every NoV in [0, 1] (it clamped to the
    first row, r = 1/48, and interpolated in NoV: up to 5.4e-4 off on 24 columns; issue 13)."""
    mu = np.linspace(0.0, 1.0, 201)
    for smith in SMITH_VARIANTS:
        got = np.asarray(lookup(small_luts[smith], mu, 0.0), np.float64)
        np.testing.assert_allclose(got, _closed_form_r0(mu), rtol=0, atol=1e-6)
    # Inside the first half texel the table takes part: against the float64 reference at
    # r = 0.25 / n_r (between the closed form and the first row), for NoV inside the centre range.
    lut = small_luts["correlated"]
    n_r, n_nov = lut.shape[:2]
    m = np.linspace(0.5 / n_nov, 1.0 - 0.5 / n_nov, 9)
    got = np.asarray(lookup(lut, m, 0.25 / n_r), np.float64)
    # measured 6.8e-4 (the NoV interpolation over 24 columns); the old clamp to the first row: 1.35e-3
    np.testing.assert_allclose(got, lut_reference(m, 0.25 / n_r), rtol=0, atol=1e-3)


# --------------------------------------------------------------------------------------------
# Slow: the full-size requirement
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("n", [128, 256])
@pytest.mark.parametrize("smith", SMITH_VARIANTS)
def test_full_size_lut_every_texel_within_1e4_of_reference(n, smith):
    """The requirement: every texel of a 128^2 and a 256^2 table within 1e-4 of the float64
    reference, both Smith variants (measured max 1.4e-6; the reference takes ~1-2 min at 256^2)."""
    c = _centres(n)
    R, M = np.meshgrid(c, c, indexing="ij")
    lut = np.asarray(compute_brdf_lut(size=n, smith=smith), np.float64)
    err = np.abs(lut - lut_reference(M, R, smith=smith))
    assert err.max() < 1e-4
    assert err.max() < 1e-5  # the documented margin of the default rule
    # the first row against the mirror (see test_lut_first_row_approaches_the_mirror)
    k = c[0] ** 2 / 2
    factor = 1.0 if smith != "schlick_ggx" else (c / (c * (1 - k) + k))[:, None] ** 2  # Smith G: second order
    assert np.abs(lut[0] - factor * _closed_form_r0(c)).max() < 1e-4
