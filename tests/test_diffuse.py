"""Tests for jaxpbr.ibl.diffuse: the stored quantity Ebar = E/pi for both methods ("exact" texel-moment
convolution and "sh9"), against closed forms (docs/math.md 7.4) and independent float64 computations.

Independent machinery written here (float64 NumPy):
* cube texel geometry from the GL face table, exact solid angles from the corner formula,
* exact texel first moments Phi_j = int_texel w dw by Lambert's / Arvo's closed form for a spherical polygon
  (1/2 sum_edges theta_e unit(v_e x v_e+1)); a texel is the central projection of a planar square, so its
  part above the horizon of n is the projection of the square clipped by the plane n.x = 0, and
  int_texel (n.w)+ dw = n . Phi(clipped square) *exactly*. That gives the exact convolution of the
  piecewise-constant environment, E_pc(n) = sum_j L_j n.Phi(clip_j), and the documented "exact" method
  with exact moments, E_method(n) = sum_J max(0, n . sum_{j in J} L_j Phi_j) (J: source-size texels);
  E_method <= E_pc, the difference being the loss at horizon-straddling source texels.
* the R&H 2001 SH9 basis, analytic coefficients and the closed-form evaluation with c1..c5 (docs/math.md 6.2).

Tolerances used throughout (derived, see the helpers): the module computes texel moments with a 4x4
midpoint rule, whose error is bounded by `quad_bound`; the piecewise-constant representation of a
continuous environment differs from it by at most `rep_bound_*`; horizon straddling is computed exactly.
"""

import functools
import math

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import reference as ref  # noqa: E402
from scipy import integrate  # noqa: E402

from jaxpbr.ibl.cubemap import Cubemap, texel_directions  # noqa: E402
from jaxpbr.ibl.diffuse import (  # noqa: E402
    irradiance,
    irradiance_at,
    sh9_basis,
    sh9_irradiance,
    sh9_project,
)

EPS64 = np.finfo(np.float64).eps
EPS32 = np.finfo(np.float32).eps

# ----------------------------------------------------------------------------------------------
# Independent cube geometry (GL major-axis table, see test_cubemap.py)
# ----------------------------------------------------------------------------------------------


gl_inverse = ref.gl_inverse


FACE_NORMALS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


polygon_moment = ref.polygon_moment  # int w dw over the central projection of a planar convex polygon


class Geo:
    """Texel centres c (6,S,S,3), corners (6,S,S,4,3) on the cube, solid angles (6,S,S), exact moments
    Phi (6,S,S,3), angular radius rho (max angle centre -> corner) (6,S,S)."""

    _cache = {}

    def __new__(cls, S):
        if S not in cls._cache:
            g = object.__new__(cls)
            e = np.linspace(-1.0, 1.0, S + 1)
            g.S = S
            g.c, g.cor = ref.cube_geometry(S)
            A = lambda x, y: np.arctan2(x * y, np.sqrt(1.0 + x * x + y * y))  # noqa: E731
            x0, x1, y0, y1 = e[None, :-1], e[None, 1:], e[:-1, None], e[1:, None]
            g.om = np.broadcast_to(A(x1, y1) - A(x0, y1) - A(x1, y0) + A(x0, y0), (6, S, S)).copy()
            g.phi = polygon_moment(g.cor)
            ucor = g.cor / np.linalg.norm(g.cor, axis=-1, keepdims=True)
            g.rho = np.arccos(np.clip(np.einsum("fijk,fijck->fijc", g.c, ucor), -1, 1)).max(-1)
            g.fz = np.einsum("fijk,fk->fij", g.phi, FACE_NORMALS)  # int_texel (face normal . w) dw
            cls._cache[S] = g
        return cls._cache[S]


def clip_moment(cor, n):
    """Exact moment of the part of each texel with n.w >= 0: cor (K,4,3) cube-plane corners, n (3,)."""
    d = cor @ n
    nxt, dn = np.roll(cor, -1, axis=1), np.roll(d, -1, axis=1)
    inside, inside_n = d >= 0, dn >= 0
    cross = inside != inside_n
    tpar = d / np.where(cross, d - dn, 1.0)
    hit = cor + (nxt - cor) * tpar[..., None]
    pts = np.stack([cor, hit], 2).reshape(len(cor), 8, 3)
    ok = np.stack([inside, cross], 2).reshape(len(cor), 8)
    # Compact: replace invalid slots by the previous valid vertex (duplicates add nothing to the moment).
    idx = np.where(ok, np.arange(8), -1)
    idx = np.maximum.accumulate(idx, axis=1)
    first = np.argmax(ok, axis=1)
    idx = np.where(idx < 0, first[:, None], idx)
    poly = np.take_along_axis(pts, idx[..., None], axis=1)
    m = polygon_moment(poly)
    return np.where(ok.any(1)[:, None], m, 0.0)


def oracles(L, normals, source_size=None):
    """(E_pc, E_method) as Ebar (N, C) for a (6,S,S,C) piecewise-constant environment L."""
    S = L.shape[1]
    g = Geo(S)
    src = S if source_size is None else source_size
    f = S // src
    LPhi = (L[..., :, None] * g.phi[..., None, :]).reshape(6, src, f, src, f, L.shape[-1], 3).sum((2, 4))
    e_pc, e_m = [], []
    for n in np.asarray(normals, float):
        e_m.append(np.maximum(LPhi @ n, 0.0).sum((0, 1, 2)) / np.pi)
        dc = g.cor @ n
        full, mixed = (dc >= 0).all(-1), (dc > 0).any(-1) & (dc < 0).any(-1)
        P = np.where(full, g.phi @ n, 0.0)
        P[mixed] = clip_moment(g.cor[mixed], n) @ n
        e_pc.append(np.einsum("fijc,fij->c", L, P) / np.pi)
    return np.array(e_pc), np.array(e_m)


def quad_bound(L):
    """Bound on |module - E_method| from the module's 4x4 midpoint-rule texel moments (irradiance.py
    `_texel_moments`), for an environment L (6,S,S,C).

    On a face plane the moment integrand is g = (x, y, 1)(1+x^2+y^2)^-2 dA; the midpoint rule on sub-cells
    of side h = 2/(4S) errs by (h^2/24) int Laplacian(g) + O(h^4), and |Laplacian g| <= 8 g_z on the face
    (the maximum, at the centre, of |(16 r^2 - 8)/(1+r^2)^2| for the z part; 4.5 for x, y). With a factor 1.25
    for the O(h^4) remainder: |m_j - Phi_j| <= (h^2/24) 10 int_j g_z = (h^2/24) 10 fz_j. The clamp
    max(0, .) is 1-Lipschitz, so |dEbar| <= sum_j |L_j| |m_j - Phi_j| / pi.
    """
    S = L.shape[1]
    g = Geo(S)
    h = 2.0 / (4 * S)
    return (h * h / 24.0) * 10.0 * np.einsum("fijc,fij->c", np.abs(L), g.fz) / np.pi


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def sample_normals(k=24, seed=0):
    """Axes, cube diagonals, random directions."""
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    return np.concatenate(
        [axes, unit([[1, 1, 1], [-1, 2, 0.5], [0.3, -0.2, -1]]), unit(np.random.default_rng(seed).normal(size=(k, 3)))]
    )


# ----------------------------------------------------------------------------------------------
# SH9 (R&H 2001, docs/math.md 6.2), written independently
# ----------------------------------------------------------------------------------------------

C0, C1, C4, C6, C8 = (
    0.5 / math.sqrt(math.pi),
    math.sqrt(3 / (4 * math.pi)),
    0.5 * math.sqrt(15 / math.pi),
    0.25 * math.sqrt(5 / math.pi),
    0.25 * math.sqrt(15 / math.pi),
)
RH_C1, RH_C2, RH_C3, RH_C4, RH_C5 = (
    math.sqrt(15 * math.pi) / 16,
    math.sqrt(3 * math.pi) / 6,
    3 * math.sqrt(5 * math.pi) / 16,
    math.sqrt(math.pi) / 2,
    math.sqrt(5 * math.pi) / 16,
)
A_HAT = np.array([math.pi] + [2 * math.pi / 3] * 3 + [math.pi / 4] * 5)
# Lipschitz constants (w.r.t. angle on the sphere) of the 9 basis functions: tangential gradient norms.
LIP = np.array([0, C1, C1, C1, C4, C4, 3 * C6, C4, 2 * C8])


def ref_basis(d):
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack(
        [
            np.full_like(x, C0),
            C1 * y,
            C1 * z,
            C1 * x,
            C4 * x * y,
            C4 * y * z,
            C6 * (3 * z * z - 1),
            C4 * x * z,
            C8 * (x * x - y * y),
        ],
        -1,
    )


def ref_project(L):
    """Discrete projection sum_j L_j Y(c_j) Omega_j, (9, C)."""
    g = Geo(L.shape[1])
    return np.einsum("fijk,fij,fijc->kc", ref_basis(g.c), g.om, L)


def rh_eval(coef, n, clamp=True):
    """R&H eq. 13 with c1..c5: E(n) from radiance coefficients (9, C); returns Ebar = E/pi (N, C)."""
    x, y, z = (np.asarray(n)[..., k, None] for k in range(3))
    L00, L1m1, L10, L11, L2m2, L2m1, L20, L21, L22 = coef
    E = (
        RH_C1 * L22 * (x * x - y * y)
        + RH_C3 * L20 * z * z
        + RH_C4 * L00
        - RH_C5 * L20
        + 2 * RH_C1 * (L2m2 * x * y + L21 * x * z + L2m1 * y * z)
        + 2 * RH_C2 * (L11 * x + L1m1 * y + L10 * z)
    )
    return (np.maximum(E, 0.0) if clamp else E) / np.pi


def sh_prop_bound(dcoef, n):
    """|dEbar(n)| <= sum_lm A_l |dL_lm| |Y_lm(n)| / pi for coefficient errors dcoef (9, C)."""
    return np.einsum("k,kc,nk->nc", A_HAT, np.abs(dcoef), np.abs(ref_basis(np.asarray(n)))) / np.pi


# ----------------------------------------------------------------------------------------------
# Environments (piecewise-constant texel values, computed here)
# ----------------------------------------------------------------------------------------------


def env_linear(S, a, b, d):
    """Exact texel means of L = a + b (w.d): a + b d.Phi_j/Omega_j; a, b (C,)."""
    g = Geo(S)
    return np.asarray(a) + np.asarray(b) * ((g.phi @ d) / g.om)[..., None]


def rep_bound_linear(S, b, normals):
    """|E_pc(n) - E(n)| for a linear env, (N, C). Per texel the error is int_j (L_j - L(w)) g(w) dw with
    g = (n.w)+ and L_j - L(w) = b d.(m_j - w), m_j = Phi_j/Omega_j, which has zero mean over the texel:
    * texel entirely below the horizon: g = 0, no error;
    * entirely above: g = n.w is linear, the error is -b int_j (d.(w - m_j))(n.(w - m_j)) <= |b| int_j |w - m_j|^2
      <= |b| int_j |w - c_j|^2 <= |b| Omega_j rho_j^2 (m_j minimises the mean square; chord <= angle);
    * straddled: g is 1-Lipschitz, |L_j - L| <= 2|b| rho_j, so <= 2|b| Omega_j rho_j^2."""
    g = Geo(S)
    out = []
    for n in np.asarray(normals, float):
        dc = g.cor @ n
        w = np.where((dc >= 0).all(-1), 1.0, np.where((dc <= 0).all(-1), 0.0, 2.0))
        out.append(np.sum(w * g.om * g.rho**2))
    return np.array(out)[:, None] * np.abs(np.asarray(b))[None, :] / np.pi


def env_sky(S, up_axis, Ls, Lg):
    """Sky Ls above the plane w[up_axis] = 0, ground Lg below; for even S that plane runs along texel edges."""
    g = Geo(S)
    return np.where(g.c[..., up_axis] > 0, Ls, Lg)[..., None] * np.ones(1)


def disk_solid_angle_in_rect(R, x0, x1, y0, y1):
    """Solid angle of {x^2 + y^2 <= R^2} n [x0,x1]x[y0,y1] on the plane z = 1 (inner integral closed form:
    int dy/(a^2+y^2)^(3/2) = y/(a^2 sqrt(a^2+y^2)), a^2 = 1 + x^2)."""
    G = lambda x, y: y / ((1 + x * x) * math.sqrt(1 + x * x + y * y))  # noqa: E731

    def inner(x):
        Y = math.sqrt(max(R * R - x * x, 0.0))
        lo, hi = max(y0, -Y), min(y1, Y)
        return G(x, hi) - G(x, lo) if hi > lo else 0.0

    xa, xb = max(x0, -R), min(x1, R)
    if xb <= xa:
        return 0.0
    pts = [s * math.sqrt(R * R - y * y) for y in (y0, y1) if R * R > y * y for s in (-1, 1)]
    pts = [p for p in pts if xa < p < xb]
    return integrate.quad(inner, xa, xb, points=pts or None, epsabs=1e-15, epsrel=1e-13, limit=200)[0]


def env_cone_z(S, gamma, Lc):
    """Cone (spherical cap) of half-angle gamma < pi/4 around +Z with radiance Lc: on the +Z face plane it is
    the disk of radius tan(gamma). Texel values are the exact covered fraction times Lc (1-D quadrature of
    the closed-form inner integral on boundary texels)."""
    g = Geo(S)
    R = math.tan(gamma)
    e = np.linspace(-1, 1, S + 1)
    cov = np.zeros((S, S))
    for i in range(S):  # tc in [e_i, e_i+1]; the disk is symmetric, so tc or -tc does not matter
        for j in range(S):
            x0, x1, y0, y1 = e[j], e[j + 1], e[i], e[i + 1]
            corners_in = sum(x * x + y * y <= R * R for x in (x0, x1) for y in (y0, y1))
            nx, ny = min(max(0.0, x0), x1), min(max(0.0, y0), y1)
            if corners_in == 4:
                cov[i, j] = 1.0
            elif nx * nx + ny * ny < R * R:
                cov[i, j] = disk_solid_angle_in_rect(R, x0, x1, y0, y1) / g.om[4, i, j]
    L = np.zeros((6, S, S, 1))
    L[4, :, :, 0] = Lc * cov
    return L, cov


def cone_irradiance(gamma, Lc, beta):
    """Ebar of the analytic cone at a normal at angle beta from its axis: (Lc/pi) int_0^gamma sin(t) dt
    int_0^2pi (A + B cos phi)+ dphi, A = cos t cos beta, B = sin t sin beta (the phi integral in closed form)."""

    def ring(t):
        A, B = math.cos(t) * math.cos(beta), math.sin(t) * math.sin(beta)
        if A >= abs(B):
            v = 2 * math.pi * A
        elif A <= -abs(B):
            v = 0.0
        else:  # positive for |phi| < p0
            p0 = math.acos(-A / abs(B))
            v = 2 * (A * p0 + abs(B) * math.sin(p0))
        return v * math.sin(t)

    # the ring integrand has kinks where A = +-|B|, i.e. t = pi/2 - beta and t = beta - pi/2
    kinks = [k for k in (math.pi / 2 - beta, beta - math.pi / 2) if 0 < k < gamma]
    return Lc / math.pi * integrate.quad(ring, 0, gamma, points=kinks or None, epsabs=1e-14, epsrel=1e-13)[0]


def rep_bound_cone(S, cov, Lc):
    """|E_pc - E_cone|: with exact coverage int_j (L_j - L_cone) = 0 and g = (n.w)+ is 1-Lipschitz, so a
    boundary texel contributes <= rho_j int_j |L_j - L_cone| = rho_j 2 Lc cov (1 - cov) Omega_j; / pi."""
    g = Geo(S)
    return np.sum(2 * Lc * cov * (1 - cov) * g.om[4] * g.rho[4]) / np.pi


@functools.partial(jax.jit, static_argnames=("method", "source_size"))
def _irradiance_at_jit(env, n, method, source_size):
    return irradiance_at(env, n, method=method, source_size=source_size)


def module(env_np, normals, method, dtype=np.float64, source_size=None):
    """The module's Ebar at `normals` (N, 3), jitted (`test_jit_matches_eager` compares with eager) with the
    normals padded to a bucket size so that tests share compilations (per-normal results are independent)."""
    env = Cubemap(jnp.asarray(env_np, dtype))
    normals = np.asarray(normals, np.float64).reshape(-1, 3)
    k = len(normals)
    N = next(b for b in (64, 512, 4096, 1 << 30) if k <= b)
    n = np.concatenate([normals, np.tile([[0.0, 0.0, 1.0]], (N - k, 1))])
    return np.asarray(_irradiance_at_jit(env, jnp.asarray(n, dtype), method, source_size), np.float64)[:k]


# ----------------------------------------------------------------------------------------------
# Self-checks of the independent machinery (so the oracles below can be trusted)
# ----------------------------------------------------------------------------------------------


def test_oracle_geometry_self_check():
    g = Geo(8)
    np.testing.assert_allclose(g.om.sum(), 4 * np.pi, rtol=1e-14)
    # Phi_j against scipy quadrature of (x, y, 1)(1+x^2+y^2)^-2 over one +Z texel (face plane = (sc, -tc, 1)).
    e = np.linspace(-1, 1, 9)
    i, j = 1, 5
    q = [
        integrate.dblquad(
            lambda t, s, k=k: np.array([s, -t, 1.0])[k] * (1 + s * s + t * t) ** -2,
            e[j],
            e[j + 1],
            e[i],
            e[i + 1],
            epsabs=1e-15,
            epsrel=1e-13,
        )[0]
        for k in range(3)
    ]
    np.testing.assert_allclose(g.phi[4, i, j], q, rtol=1e-11, atol=1e-16)
    np.testing.assert_allclose(g.phi.sum((0, 1, 2)), 0, atol=1e-14)
    # The clipped convolution of a constant env is exactly pi for every n: E_pc = 1.
    e_pc, e_m = oracles(np.ones((6, 8, 8, 1)), sample_normals(8))
    np.testing.assert_allclose(e_pc, 1.0, rtol=1e-13)
    assert (e_m <= e_pc + 1e-14).all()
    # R&H closed form with analytic coefficients of a linear env reproduces a + (2/3) b n.d (MATH 7.4).
    d = unit([0.2, 0.5, -0.7])
    coef = np.zeros((9, 1))
    coef[0], coef[[3, 1, 2], 0] = 2 * math.sqrt(math.pi) * 1.0, C1 * 4 * math.pi / 3 * 0.5 * d
    n = sample_normals(8)
    np.testing.assert_allclose(rh_eval(coef, n)[:, 0], 1.0 + (2 / 3) * 0.5 * (n @ d), rtol=1e-13)
    # Coverage of the cone: covered solid angle sums to the cap's 2 pi (1 - cos gamma).
    L, cov = env_cone_z(16, 0.5, 1.0)
    np.testing.assert_allclose(np.sum(cov * Geo(16).om[4]), 2 * math.pi * (1 - math.cos(0.5)), rtol=1e-11)
    np.testing.assert_allclose(cone_irradiance(0.5, 1.0, 0.0), math.sin(0.5) ** 2, rtol=1e-12)
    for beta in (1.3, 1.8):  # the cap straddles the horizon of n: plain 2-D quadrature of the clamped cosine
        n_ = np.array([math.sin(beta), 0.0, math.cos(beta)])

        def f2(phi, t):
            w = np.array([math.sin(t) * math.cos(phi), math.sin(t) * math.sin(phi), math.cos(t)])
            return max(0.0, float(n_ @ w)) * math.sin(t)

        q = integrate.dblquad(f2, 0, 0.5, 0, 2 * math.pi, epsabs=1e-10, epsrel=1e-10)[0] / math.pi
        np.testing.assert_allclose(cone_irradiance(0.5, 1.0, beta), q, rtol=1e-7)


# ----------------------------------------------------------------------------------------------
# Constant environment: Ebar = L
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_constant_environment(dtype):
    S, L = 16, 1.3
    env = np.full((6, S, S, 1), L)
    n = sample_normals(20)
    e_pc, e_m = oracles(env, n)
    assert np.allclose(e_pc, L, rtol=1e-13)
    eps = np.finfo(dtype).eps
    Ns = 6 * S * S
    # exact: |module - E_method| <= quad_bound (+ float rounding: sum of Ns positive terms, <= Ns eps relative);
    # E_method = L - (straddling loss), computed exactly here.
    got = module(env, n, "exact", dtype)
    assert np.all(np.abs(got - e_m) <= quad_bound(env) + (Ns + 8) * eps * L), np.abs(got - e_m).max()
    assert np.all(np.abs(got - L) <= quad_bound(env) + (e_pc - e_m) + (Ns + 8) * eps * L)
    # sh9: the projection of a constant is L00 = L sum_j c0 Omega_j = 2 sqrt(pi) L and (by the symmetry of the
    # texel set) zero elsewhere: Ebar = L up to the rounding of the 9 Ns-term sums.
    got = module(env, n, "sh9", dtype)
    np.testing.assert_allclose(got, L, rtol=(Ns + 16) * eps)


def test_exact_method_is_exact_when_no_texel_straddles():
    # For n = +-x, +-y, +-z and even S the horizon runs along texel edges, so the documented method has no
    # straddling texel and must return Ebar = L to rounding (the texel moments are exact, closed form).
    S = 16
    env = np.full((6, S, S, 1), 1.0)
    n = np.concatenate([np.eye(3), -np.eye(3)])
    e_pc, e_m = oracles(env, n)
    np.testing.assert_allclose(e_m, 1.0, rtol=1e-13)  # the oracle: no straddling loss at all
    np.testing.assert_allclose(module(env, n, "exact"), 1.0, rtol=1e-12)


def test_texel_moments_match_independent_closed_form():
    from jaxpbr.ibl.diffuse import _texel_moments

    g = Geo(16)
    np.testing.assert_allclose(_texel_moments(16), g.phi, rtol=1e-12, atol=1e-13 * np.abs(g.phi).max())


def test_texel_moments_within_midpoint_bound():
    # The bound quad_bound rests on: |m_j - Phi_j| <= (h^2/24) 10 fz_j, h = 2/(4S).
    from jaxpbr.ibl.diffuse import _texel_moments

    for S in (8, 16, 32):
        g = Geo(S)
        h = 2.0 / (4 * S)
        err = np.linalg.norm(_texel_moments(S) - g.phi, axis=-1)
        assert (err <= (h * h / 24) * 10 * g.fz).all()


# ----------------------------------------------------------------------------------------------
# Linear environment: Ebar = a + (2/3) b (n.d)  (exact in SH9 too)
# ----------------------------------------------------------------------------------------------

LIN_D = unit([0.3, 0.5, -0.8])
LIN_A, LIN_B = np.array([1.0, 0.5]), np.array([0.6, -0.4])


def linear_closed(n):
    return LIN_A + (2 / 3) * LIN_B * (np.asarray(n) @ LIN_D)[:, None]


def test_linear_environment_exact():
    S = 16
    env = env_linear(S, LIN_A, LIN_B, LIN_D)
    n = sample_normals(24, seed=1)
    e_pc, e_m = oracles(env, n)
    got = module(env, n, "exact")
    qb = quad_bound(env)
    assert np.all(np.abs(got - e_m) <= qb + 1e-13), (np.abs(got - e_m).max(0), qb)
    # closed form: + the straddling loss (computed exactly) + the piecewise-constant representation error.
    rb = rep_bound_linear(S, LIN_B, n)
    tol = qb + (e_pc - e_m) + rb + 1e-13
    assert np.all(np.abs(got - linear_closed(n)) <= tol), (np.abs(got - linear_closed(n)) / tol).max()
    # The representation bound is the main slack; it is a small fraction of the b term being tested.
    assert (rb < 0.015 * np.abs(LIN_B)).all(), rb.max(0)


def analytic_linear_coef():
    coef = np.zeros((9, 2))
    coef[0] = 2 * math.sqrt(math.pi) * LIN_A
    coef[[3, 1, 2]] = C1 * 4 * math.pi / 3 * LIN_D[:, None] * LIN_B[None, :]  # (x, y, z) -> indices 3, 1, 2
    return coef


def test_linear_environment_sh9():
    S = 16
    env = env_linear(S, LIN_A, LIN_B, LIN_D)
    n = sample_normals(24, seed=2)
    got = module(env, n, "sh9")
    disc = ref_project(env)
    np.testing.assert_allclose(np.asarray(sh9_project(Cubemap(jnp.asarray(env)))), disc, rtol=0, atol=1e-13)
    np.testing.assert_allclose(got, rh_eval(disc, n), rtol=0, atol=1e-13)
    # SH9 is exact for a linear env: the only error is the discrete projection (texel-centre rule),
    # dL = disc - analytic, propagated through A_l Y_lm(n).
    dL = disc - analytic_linear_coef()
    tol = sh_prop_bound(dL, n) + 1e-13
    assert np.all(np.abs(got - linear_closed(n)) <= tol)
    assert (np.abs(dL).max(0) < 0.01 * np.abs(LIN_B)).all()  # and that error is small


# ----------------------------------------------------------------------------------------------
# Sky over ground
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("up_axis", [1, 2], ids=["up=+Y", "up=+Z"])
def test_sky_over_ground(up_axis):
    S, Ls, Lg = 16, 2.0, 0.5
    env = env_sky(S, up_axis, Ls, Lg)
    n = sample_normals(24, seed=3)
    cos = n[:, up_axis]
    closed = (Ls * (1 + cos) + Lg * (1 - cos))[:, None] / 2
    e_pc, e_m = oracles(env, n)
    np.testing.assert_allclose(e_pc, closed, rtol=1e-13)  # the texels represent the step exactly
    got = module(env, n, "exact")
    assert np.all(np.abs(got - e_m) <= quad_bound(env) + 1e-13)
    assert np.all(np.abs(got - closed) <= quad_bound(env) + (e_pc - e_m) + 1e-13)
    # sh9: analytic coefficients L00 = sqrt(pi)(Ls+Lg), L_up = c1 pi (Ls-Lg), all others 0 (MATH 7.4).
    coef = np.zeros((9, 1))
    coef[0] = math.sqrt(math.pi) * (Ls + Lg)
    coef[{1: 1, 2: 2}[up_axis]] = C1 * math.pi * (Ls - Lg)
    np.testing.assert_allclose(rh_eval(coef, n), closed, rtol=1e-13)  # SH9 is exact here
    disc = ref_project(env)
    got = module(env, n, "sh9")
    np.testing.assert_allclose(got, rh_eval(disc, n), rtol=0, atol=1e-13)
    assert np.all(np.abs(got - closed) <= sh_prop_bound(disc - coef, n) + 1e-13)


@pytest.mark.parametrize("S, e_plus_z", [(16, 3.145627), (64, 3.141844)])
def test_sh9_project_hemisphere_matches_math_table(S, e_plus_z):
    # Uniform L = 1 on the upper hemisphere along +Z. MATH 7.4: L00 = sqrt(pi), L10 = pi 0.488603 in the limit;
    # with texel centres and exact solid angles L10 = c1 sum_{z_j > 0} z_j Omega_j = c1 E(+z), and MATH 7.4
    # tabulates E(+z) = 3.145627 (W=16), 3.141844 (W=64) for exactly that sum. Table values are rounded to
    # 1e-6 (so |dL10| <= 0.4886 5e-7 + 3.15 5e-7 < 2e-6).
    env = env_sky(S, 2, 1.0, 0.0)
    coef = np.asarray(sh9_project(Cubemap(jnp.asarray(env))))[:, 0]
    np.testing.assert_allclose(coef[0], math.sqrt(math.pi), rtol=1e-13)
    assert abs(coef[2] - 0.488603 * e_plus_z) < 2e-6
    # x, y, xy, yz, xz, x^2-y^2 vanish by the symmetry of the texel set; 3z^2-1 only in the limit.
    np.testing.assert_allclose(coef[[1, 3, 4, 5, 7, 8]], 0, atol=1e-14)
    np.testing.assert_allclose(coef, ref_project(env)[:, 0], atol=1e-13)


def test_sh9_project_hemisphere_converges_to_analytic():
    # L10 -> pi c1 at second order in 1/S: from S = 16 to 64 the error drops by ~16 (> 10). Every other
    # coefficient is already exact (L20 too: the cube's texel set is symmetric under axis permutations).
    errs = []
    for S in (16, 64):
        coef = np.asarray(sh9_project(Cubemap(jnp.asarray(env_sky(S, 2, 1.0, 0.0)))))[:, 0]
        errs.append(np.abs(coef - np.array([math.sqrt(math.pi), 0, math.pi * C1, 0, 0, 0, 0, 0, 0])))
        assert (np.delete(errs[-1], 2) < 1e-14).all()
    assert errs[1][2] < errs[0][2] / 10, errs


# ----------------------------------------------------------------------------------------------
# Cone (spherical cap) of half-angle gamma
# ----------------------------------------------------------------------------------------------

GAMMA, LC = 0.5, 3.0


@pytest.fixture(scope="module")
def cone():
    S = 32
    env, cov = env_cone_z(S, GAMMA, LC)
    return S, env, cov


def test_cone_exact(cone):
    S, env, cov = cone
    betas = np.array([0.0, 0.4, 0.9, 1.2, math.pi / 2, 1.8, 2.0])  # the last ones straddle n's horizon
    n = np.stack([np.sin(betas) * np.cos(0.3), np.sin(betas) * np.sin(0.3), np.cos(betas)], -1)
    closed = np.array([cone_irradiance(GAMMA, LC, b) for b in betas])[:, None]
    assert closed[0, 0] == pytest.approx(LC * math.sin(GAMMA) ** 2, rel=1e-12)  # MATH 7.4: E = pi L sin^2 gamma
    np.testing.assert_allclose(
        closed[1:3, 0], LC * math.sin(GAMMA) ** 2 * np.cos(betas[1:3]), rtol=1e-12
    )  # whole cap above
    e_pc, e_m = oracles(env, n)
    got = module(env, n, "exact")
    assert np.all(np.abs(got - e_m) <= quad_bound(env) + 1e-13)
    tol = quad_bound(env) + (e_pc - e_m) + rep_bound_cone(S, cov, LC) + 1e-13
    assert np.all(np.abs(got - closed) <= tol), (got[:, 0], closed[:, 0], tol)
    assert (tol[:3] < 0.01 * closed[:3]).all()  # the check is sharp where the cone is fully visible


def test_cone_sh9_matches_rh_prediction(cone):
    S, env, cov = cone
    g = Geo(S)
    betas = np.array([0.0, 0.6, 1.2, 1.8, 2.6, math.pi])
    n = np.stack([np.sin(betas), np.zeros_like(betas), np.cos(betas)], -1)
    got = module(env, n, "sh9")
    disc = ref_project(env)
    np.testing.assert_allclose(got, rh_eval(disc, n), rtol=0, atol=1e-13)
    # Analytic zonal coefficients of the cap around +Z: L00 = 2 pi c0 (1 - cos g), L10 = pi c1 sin^2 g,
    # L20 = 2 pi c6 cos g sin^2 g (times Lc). Projection error with exact coverage:
    # |dL_lm| <= sum_j L_j Omega_j Lip(Y_lm) rho_j.
    cg, sg2 = math.cos(GAMMA), math.sin(GAMMA) ** 2
    coef = np.zeros((9, 1))
    coef[0], coef[2], coef[6] = (
        LC * 2 * math.pi * C0 * (1 - cg),
        LC * math.pi * C1 * sg2,
        LC * 2 * math.pi * C6 * cg * sg2,
    )
    dL = (LIP * np.sum(env[..., 0] * g.om * g.rho))[:, None]
    pred = rh_eval(coef, n)
    assert np.all(np.abs(got - pred) <= sh_prop_bound(dL, n) + 1e-13)
    # (Why the R&H prediction and not the closed form: SH9 is not exact for a cone, on the axis the R&H value
    # is 4 % above Lc sin^2(gamma).)
    assert abs(pred[0, 0] / (LC * sg2) - 1) > 0.03


# ----------------------------------------------------------------------------------------------
# SH9 of a single directional light (MATH 7.4)
# ----------------------------------------------------------------------------------------------


def test_sh9_directional_light():
    # Radiance coefficients of a unit-irradiance directional light from d are Y_lm(d); then
    # pi Ebar(gamma) = 1/4 + cos/2 + (5/16) P2(cos), clamped at 0: 1.0625 at gamma = 0 (exact: 1),
    # 0.0625 at 180 deg, minimum -0.0396 at cos = -8/15 before clamping.
    d = unit([0.2, -0.4, 0.9])
    coef = ref_basis(d)[:, None]
    np.testing.assert_allclose(np.asarray(sh9_basis(jnp.asarray(d))), coef[:, 0], rtol=1e-15)
    t = np.linspace(-1, 1, 401)
    t = np.concatenate([t, [-8 / 15]])
    # normals at cos(angle to d) = t
    perp = unit(np.cross(d, [1.0, 0, 0]))
    n = t[:, None] * d + np.sqrt(1 - t * t)[:, None] * perp
    poly = 0.25 + t / 2 + (5 / 16) * (3 * t * t - 1) / 2
    assert poly.min() == pytest.approx(-0.0395833333, abs=1e-9) and poly[-1] == poly.min()
    got = np.asarray(sh9_irradiance(jnp.asarray(coef), jnp.asarray(n)))[:, 0] * math.pi
    np.testing.assert_allclose(got, np.maximum(poly, 0.0), rtol=0, atol=1e-14)
    assert got[-1] == 0.0 and (got >= 0).all()
    assert got[-2] == pytest.approx(1.0625, abs=1e-14) and got[0] == pytest.approx(0.0625, abs=1e-14)


def test_sh9_single_bright_texel_is_a_directional_light():
    # A one-texel environment with L_j Omega_j = 1 projects (texel-centre rule) to exactly Y_lm(c_j).
    S = 8
    g = Geo(S)
    env = np.zeros((6, S, S, 1))
    env[2, 3, 5, 0] = 1.0 / g.om[2, 3, 5]
    d = g.c[2, 3, 5]
    n = sample_normals(30, seed=4)
    t = n @ d
    expect = np.maximum(0.25 + t / 2 + (5 / 16) * (3 * t * t - 1) / 2, 0.0) / math.pi
    np.testing.assert_allclose(module(env, n, "sh9")[:, 0], expect, rtol=0, atol=1e-14)
    # The irradiance map stores the clamped values at its texel centres.
    out = np.asarray(irradiance(Cubemap(jnp.asarray(env)), size=4, method="sh9").levels[0])[..., 0]
    t = texel_directions(4) @ d
    np.testing.assert_allclose(
        out, np.maximum(0.25 + t / 2 + (5 / 16) * (3 * t * t - 1) / 2, 0.0) / math.pi, atol=1e-14
    )


def test_sh9_project_matches_brute_force():
    env = np.random.default_rng(5).uniform(0, 2, (6, 8, 8, 3))
    np.testing.assert_allclose(np.asarray(sh9_project(Cubemap(jnp.asarray(env)))), ref_project(env), rtol=0, atol=1e-13)
    # level argument
    cube = Cubemap(jnp.asarray(env)).with_mips()
    np.testing.assert_allclose(
        np.asarray(sh9_project(cube, level=1)), ref_project(np.asarray(cube.levels[1])), atol=1e-13
    )


# ----------------------------------------------------------------------------------------------
# Exact method on a random smooth environment
# ----------------------------------------------------------------------------------------------


def smooth_env(d):
    rng = np.random.default_rng(7)
    mu = unit(rng.normal(size=(4, 3)))
    kappa = np.array([2.0, 5.0, 9.0, 1.0])
    w = rng.uniform(0.2, 2.0, (4, 3))
    lobes = jnp.exp(kappa * (d @ jnp.asarray(mu.T) - 1.0))
    return 0.3 + lobes @ jnp.asarray(w)


@pytest.fixture(scope="module")
def random_env():
    return np.asarray(Cubemap.from_function(smooth_env, 32, supersample=2, dtype=jnp.float64).levels[0])


def test_exact_vs_point_brute_force(random_env):
    env = random_env
    g = Geo(32)
    n = sample_normals(24, seed=8)
    got = module(env, n, "exact")
    # Independent brute force over all texels (MATH 6.1): sum_j L_j max(0, n.c_j) Omega_j / pi.
    bf = np.einsum("fijc,nfij->nc", env, np.maximum(np.einsum("nk,fijk->nfij", n, g.c), 0) * g.om) / np.pi
    # |E_method - bf| <= sum_j L_j |n.(Phi_j - c_j Omega_j)| / pi (max is 1-Lipschitz; exact moments here).
    dev = np.einsum("fijc,nfij->nc", env, np.abs(np.einsum("nk,fijk->nfij", n, g.phi - g.c * g.om[..., None]))) / np.pi
    assert np.all(np.abs(got - bf) <= quad_bound(env) + dev + 1e-12)
    assert (dev < 2e-3 * bf).all()  # ... and that slack is small against Ebar
    _, e_m = oracles(env, n)
    assert np.all(np.abs(got - e_m) <= quad_bound(env) + 1e-12)


@pytest.mark.parametrize("source_size", [32, 16, 8])
def test_source_size(random_env, source_size):
    env = random_env
    n = sample_normals(12, seed=9)
    e_pc, e_m = oracles(env, n, source_size)
    got = module(env, n, "exact", source_size=source_size)
    assert np.all(np.abs(got - e_m) <= quad_bound(env) + 1e-12)
    # coarser source levels only lose at more coarse straddling texels: E_method <= E_pc
    assert np.all(e_m <= e_pc + 1e-12)


def test_irradiance_map_structure_and_default_source(random_env):
    env = Cubemap(jnp.asarray(random_env))
    out = irradiance(env, size=8)
    assert out.levels[0].shape == (6, 8, 8, 3) and out.num_levels == 1 and out.dtype == env.dtype
    md = out.metadata
    assert md["irradiance_method"] == "exact" and md["irradiance_source_size"] == "32" and "E/pi" in md["quantity"]
    # texel-centre values = irradiance_at at texel_directions (same computation)
    np.testing.assert_allclose(
        np.asarray(out.levels[0]), module(random_env, texel_directions(8), "exact").reshape(6, 8, 8, 3), rtol=1e-13
    )
    out = irradiance(env, size=4, method="sh9")
    assert out.metadata["irradiance_method"] == "sh9" and "irradiance_source_size" not in out.metadata
    # default source size is min(S, 64)
    big = Cubemap(jnp.ones((6, 128, 128, 1)))
    out = irradiance(big, size=2)
    assert out.metadata["irradiance_source_size"] == "64"
    np.testing.assert_allclose(np.asarray(out.levels[0]), 1.0, rtol=1e-4)  # moments at S=128: ~1e-6


@pytest.mark.parametrize("method", ["exact", "sh9"])
def test_progress_is_reported_and_changes_nothing(random_env, method):
    """`jaxpbr irradiance --size 2048` ran for minutes without a sign of life (issue 13): the exact
    convolution reports its chunks from inside the one program; sh9 reports once."""
    env = Cubemap(jnp.asarray(random_env))
    calls = []
    out = irradiance(env, size=8, method=method, chunk=4, progress=lambda d, t: calls.append((d, t)))
    total = 6 * 8 * 8 // 4 if method == "exact" else 1  # 96 chunks of 4 texels: one report each
    assert calls[-1] == (total, total) and [d for d, _ in calls] == sorted({d for d, _ in calls}), calls
    assert len(calls) == (96 if method == "exact" else 1)
    np.testing.assert_array_equal(np.asarray(out.levels[0]), np.asarray(irradiance(env, size=8, method=method, chunk=4).levels[0]))


@pytest.mark.parametrize("method", ["exact", "sh9"])
def test_float32_matches_float64(random_env, method):
    env = random_env[:, ::2, ::2]  # 16^2, Ns = 1536 texels
    n = sample_normals(12, seed=10)
    a = module(env, n, method, np.float64)
    b = module(env, n, method, np.float32)
    Ns = 6 * 16 * 16
    if method == "exact":
        # sum of Ns non-negative terms, each a few roundings: relative error <= (Ns + 8) eps32.
        np.testing.assert_allclose(b, a, rtol=(Ns + 8) * EPS32)
    else:
        # projection: Ns-term sums of mixed sign -> |dL_lm| <= (Ns + 8) eps32 sum_j |L_j Y_lm| Omega_j.
        g = Geo(16)
        absum = np.einsum("fijk,fij,fijc->kc", np.abs(ref_basis(g.c)), g.om, np.abs(env))
        tol = sh_prop_bound((Ns + 8) * EPS32 * absum, n) + 8 * EPS32 * np.abs(a)
        assert np.all(np.abs(b - a) <= tol)


@pytest.mark.parametrize("method", ["exact", "sh9"])
def test_jit_matches_eager(random_env, method):
    env = Cubemap(jnp.asarray(random_env[:, ::2, ::2]))
    n = jnp.asarray(sample_normals(12, seed=11))
    eager = np.asarray(irradiance_at(env, n, method=method))
    jitted = np.asarray(jax.jit(lambda e, x: irradiance_at(e, x, method=method))(env, n))
    np.testing.assert_allclose(jitted, eager, rtol=1e-13)


def test_batch_shapes(random_env):
    env = Cubemap(jnp.asarray(random_env[:, ::4, ::4]))
    n = sample_normals(0)[:6]
    flat = np.asarray(irradiance_at(env, jnp.asarray(n)))
    for shape in [(), (1,), (3, 1, 2)]:
        k = int(np.prod(shape, dtype=int))
        out = irradiance_at(env, jnp.asarray(n[:k].reshape(shape + (3,))))
        assert out.shape == shape + (3,)
        np.testing.assert_allclose(np.asarray(out).reshape(-1, 3), flat[:k], rtol=1e-13)


def test_bad_arguments():
    env = Cubemap(jnp.ones((6, 32, 32, 1)))
    with pytest.raises(ValueError, match="unknown irradiance method 'fast'"):
        irradiance(env, size=8, method="fast")
    with pytest.raises(ValueError, match="unknown irradiance method"):
        irradiance_at(env, jnp.ones(3), method="SH9")
    for size in (0, -8, 8.0):
        with pytest.raises(ValueError, match="size must be a positive integer"):
            irradiance(env, size=size)
    for src in (12, 64, 3):
        with pytest.raises(ValueError, match="must divide the environment face size 32 by a power of two"):
            irradiance(env, size=8, source_size=src)
    with pytest.raises(ValueError, match="source_size must be a positive integer"):
        irradiance(env, size=8, source_size=0)
    with pytest.raises(ValueError, match="chunk must be a positive integer"):
        irradiance(env, size=8, chunk=0)


def test_no_normals_give_an_empty_result():
    """map_row_chunks divided by zero rows (the old lax.map returned an empty result)."""
    env = Cubemap(jnp.ones((6, 4, 4, 3)))
    assert irradiance_at(env, np.zeros((0, 3))).shape == (0, 3)
