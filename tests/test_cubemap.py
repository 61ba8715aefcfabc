"""Tests for jaxpbr.ibl.cubemap: the GL/KTX face table, exact texel solid angles, the seam-aware
bilinear/trilinear lookup, the area-correct pyramid, from_function / from_equirect / to_equirect.

Every oracle is independent of the module: the OpenGL major-axis table is written out below from the
GL spec ("Cube Map Texture Selection"), solid angles come from our own corner formula and from scipy
quadrature, texel first moments from Lambert's / Arvo's closed form for a spherical polygon.
"""

import functools
import math

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import reference as ref  # noqa: E402
from gradcheck import check_partials  # noqa: E402
from scipy import integrate  # noqa: E402

from jaxpbr.ibl.cubemap import (  # noqa: E402
    Cubemap,
    dir_to_equirect,
    dir_to_face,
    downsample,
    equirect_directions,
    equirect_to_dir,
    face_to_dir,
    texel_directions,
    texel_solid_angles,
)

EPS64 = np.finfo(np.float64).eps
EPS32 = np.finfo(np.float32).eps

# ----------------------------------------------------------------------------------------------
# Independent geometry (float64 NumPy), written from the GL spec table
#
#   face | sc   tc   ma          face | sc   tc   ma
#   +X   | -rz  -ry  rx          -Y   | +rx  -rz  ry
#   -X   | +rz  -ry  rx          +Z   | +rx  -ry  rz
#   +Y   | +rx  +rz  ry          -Z   | -rx  -ry  rz
#   s = (sc/|ma| + 1)/2, t = (tc/|ma| + 1)/2
# ----------------------------------------------------------------------------------------------

GL_TABLE = {  # face -> (sc, tc, ma) as functions of r
    0: lambda r: (-r[..., 2], -r[..., 1], r[..., 0]),
    1: lambda r: (r[..., 2], -r[..., 1], r[..., 0]),
    2: lambda r: (r[..., 0], r[..., 2], r[..., 1]),
    3: lambda r: (r[..., 0], -r[..., 2], r[..., 1]),
    4: lambda r: (r[..., 0], -r[..., 1], r[..., 2]),
    5: lambda r: (-r[..., 0], -r[..., 1], r[..., 2]),
}


def gl_select(r):
    """Reference (face, s, t) of directions r (N, 3) by the spec table (major axis, ties x<y<z)."""
    r = np.asarray(r, np.float64)
    out_f, out_s, out_t = [], [], []
    for v in r:
        a = np.abs(v)
        axis = 0 if a[0] >= a[1] and a[0] >= a[2] else (1 if a[1] >= a[2] else 2)
        face = 2 * axis + (0 if v[axis] >= 0 else 1)
        sc, tc, ma = GL_TABLE[face](v)
        out_f.append(face)
        out_s.append((sc / abs(ma) + 1) / 2)
        out_t.append((tc / abs(ma) + 1) / 2)
    return np.array(out_f), np.array(out_s), np.array(out_t)


gl_inverse = ref.gl_inverse


ref_geometry = ref.cube_geometry


ref_solid_angles = ref.solid_angles  # our own corner formula


polygon_moment = ref.polygon_moment  # Lambert / Arvo closed form


@jax.jit
def _jsample(cube, d, lod):
    return cube.sample(d, lod)


def sample(cube, d, lod=0.0):
    """Jitted lookup (`test_jit_matches_eager` checks it against the eager one). To keep the number of
    compilations down, the directions are flattened and padded to a few bucket sizes (the lookup is
    per-direction, so padding cannot change the other results); `test_batch_shapes` calls it unpadded."""
    d = np.asarray(d)
    shape = d.shape[:-1]
    lod = np.broadcast_to(np.asarray(lod, np.float64), shape).reshape(-1)
    d = d.reshape(-1, 3)
    n = len(d)
    N = next(b for b in (512, 4096, 32768, 1 << 30) if n <= b)
    # the module converts directions to the map's dtype first; doing it here shares compilations.
    d = np.concatenate([d, np.tile([[1.0, 0.0, 0.0]], (N - n, 1))]).astype(cube.dtype)
    lod = np.concatenate([lod, np.zeros(N - n)])
    out = _jsample(cube, jnp.asarray(d), jnp.asarray(lod, cube.dtype))[:n]
    return out.reshape(shape + out.shape[-1:])


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rand_dirs(n, seed):
    return unit(np.random.default_rng(seed).normal(size=(n, 3)))


def smooth_f(d):
    """A smooth 3-channel radiance on the sphere (works for NumPy and jax arrays)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    xp = jnp if isinstance(d, jax.Array) else np
    return xp.stack([1.0 + 0.5 * x + 0.3 * y * z + 0.2 * z * z, 0.7 + 0.4 * y - 0.2 * x * y, 0.5 + 0.3 * x * z], -1)


# Bounds for smooth_f used below (tangential derivatives on the unit sphere):
#   |grad f| <= 0.5 + 0.3 + 0.4 = 1.2 per channel, |second derivatives| <= 0.5 + 0.6 + 0.4 + ... <= 2.
SMOOTH_GRAD = 1.2
SMOOTH_HESS = 2.0


# ----------------------------------------------------------------------------------------------
# Face table
# ----------------------------------------------------------------------------------------------


jit_dir_to_face = jax.jit(dir_to_face)


@pytest.mark.parametrize("xp", [np, jnp], ids=["numpy", "jax"])
def test_texel_centres_map_back_to_their_texel(xp):
    sizes = (1, 2, 5, 8)
    d = [texel_directions(S) for S in sizes]
    for S, x in zip(sizes, d):
        assert x.shape == (6, S, S, 3) and x.dtype == np.float64
    flat = np.concatenate([x.reshape(-1, 3) for x in d])
    face, s, t = dir_to_face(flat, xp=np) if xp is np else jit_dir_to_face(jnp.asarray(flat))
    f_ref = np.concatenate([np.broadcast_to(np.arange(6)[:, None, None], (6, S, S)).ravel() for S in sizes])
    c = [(np.arange(S) + 0.5) / S for S in sizes]
    s_ref = np.concatenate([np.broadcast_to(c_[None, None, :], (6, S, S)).ravel() for S, c_ in zip(sizes, c)])
    t_ref = np.concatenate([np.broadcast_to(c_[None, :, None], (6, S, S)).ravel() for S, c_ in zip(sizes, c)])
    np.testing.assert_array_equal(np.asarray(face), f_ref)
    # s, t come from a normalised direction: a few roundings of size eps (|sc/ma| <= 1).
    np.testing.assert_allclose(np.asarray(s), s_ref, rtol=0, atol=8 * EPS64)
    np.testing.assert_allclose(np.asarray(t), t_ref, rtol=0, atol=8 * EPS64)


@pytest.mark.parametrize("S", [1, 2, 7, 16])
def test_texel_directions_follow_gl_table(S):
    cen, _ = ref_geometry(S)
    np.testing.assert_allclose(texel_directions(S), cen, rtol=0, atol=4 * EPS64)


def test_dir_to_face_matches_gl_table_on_random_directions():
    d = np.concatenate([rand_dirs(3000, 1), 7.5 * rand_dirs(50, 2)])  # any length > 0
    f, s, t = dir_to_face(d, xp=np)
    fr, sr, tr = gl_select(d)
    np.testing.assert_array_equal(f, fr)
    np.testing.assert_allclose(s, sr, rtol=0, atol=4 * EPS64)
    np.testing.assert_allclose(t, tr, rtol=0, atol=4 * EPS64)
    fj, sj, tj = jit_dir_to_face(jnp.asarray(d))
    np.testing.assert_array_equal(np.asarray(fj), fr)
    np.testing.assert_allclose(np.asarray(sj), sr, rtol=0, atol=4 * EPS64)


# (s, t) = (0, 0) corner of each face, derived by hand from the table: e.g. +X: s = 0 -> sc = -1 = -rz
# -> rz = +1; t = 0 -> tc = -1 = -ry -> ry = +1; so +X (0,0) points to (+1, +1, +1).
CORNER_00 = {0: (1, 1, 1), 1: (-1, 1, -1), 2: (-1, 1, -1), 3: (-1, -1, 1), 4: (-1, 1, 1), 5: (1, 1, -1)}
# Texel [f, 0, 0] of a 2x2 face has its centre at sc = tc = -1/2.
TEXEL00_S2 = {
    0: (1, 0.5, 0.5),
    1: (-1, 0.5, -0.5),
    2: (-0.5, 1, -0.5),
    3: (-0.5, -1, 0.5),
    4: (-0.5, 0.5, 1),
    5: (0.5, 0.5, -1),
}


@pytest.mark.parametrize("face", range(6))
def test_face_corners_by_hand(face):
    d = face_to_dir(np.array(face), np.array(0.0), np.array(0.0), xp=np)
    np.testing.assert_array_equal(d, CORNER_00[face])
    np.testing.assert_allclose(texel_directions(2)[face, 0, 0], unit(TEXEL00_S2[face]), rtol=0, atol=4 * EPS64)
    # ... and the (1, 1) corner is the mirror image through the face centre.
    centre = face_to_dir(np.array(face), np.array(0.5), np.array(0.5), xp=np)
    d11 = face_to_dir(np.array(face), np.array(1.0), np.array(1.0), xp=np)
    np.testing.assert_array_equal(d11, 2 * centre - np.array(CORNER_00[face]))


def test_face_to_dir_inverts_dir_to_face():
    rng = np.random.default_rng(3)
    face = rng.integers(0, 6, 500)
    s, t = rng.uniform(0, 1, (2, 500))
    f2, s2, t2 = dir_to_face(face_to_dir(face, s, t, xp=np), xp=np)
    np.testing.assert_array_equal(f2, face)
    np.testing.assert_allclose(s2, s, atol=4 * EPS64)
    np.testing.assert_allclose(t2, t, atol=4 * EPS64)


def test_ties_and_zero_vector():
    # Documented: exact diagonals go to x before y before z; the zero vector maps to the centre of +X.
    f, s, t = dir_to_face(np.array([[1.0, 1.0, 1.0], [0.0, -2.0, 2.0], [-1.0, 1.0, 0.5], [0.0, 0.0, 0.0]]), xp=np)
    np.testing.assert_array_equal(f, [0, 3, 1, 0])
    assert s[3] == 0.5 and t[3] == 0.5


# ----------------------------------------------------------------------------------------------
# Solid angles
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("S", [1, 2, 3, 8, 64, 256])
def test_solid_angles_sum_to_4pi(S):
    om = texel_solid_angles(S)
    assert om.shape == (6, S, S) and (om > 0).all()
    # float64 sum of 6 S^2 positive terms, each with a relative error of a few eps: |err| <= 6S^2 * 8 eps * 4pi/(6S^2).
    assert abs(om.sum() - 4 * math.pi) <= 8 * EPS64 * 4 * math.pi * max(1, math.log2(6 * S * S))
    # The corner formula is a signed sum of four atan2 values |A| <= pi/6 (cancelling to ~4/S^2): both
    # evaluations carry an absolute error of a few ulps of pi/6 each, whatever the texel size.
    np.testing.assert_allclose(om, ref_solid_angles(S), rtol=0, atol=16 * EPS64 * math.pi / 6)


@pytest.mark.parametrize("S, i, j", [(1, 0, 0), (5, 2, 2), (5, 0, 3), (8, 0, 0), (8, 3, 4), (16, 15, 2)])
def test_solid_angle_matches_quadrature(S, i, j):
    # Solid angle of a region of the plane z = 1: integral of dA / (1 + x^2 + y^2)^(3/2).
    x0, x1 = -1 + 2 * j / S, -1 + 2 * (j + 1) / S
    y0, y1 = -1 + 2 * i / S, -1 + 2 * (i + 1) / S
    val, err = integrate.dblquad(lambda y, x: (1 + x * x + y * y) ** -1.5, x0, x1, y0, y1, epsabs=0, epsrel=1e-13)
    assert err < 1e-13
    for f in range(6):  # the six faces are congruent
        np.testing.assert_allclose(texel_solid_angles(S)[f, i, j], val, rtol=1e-12)


def test_centre_corner_ratio_tends_to_3_sqrt3():
    # MATH 3.4: Omega(centre)/Omega(corner) -> 3^(3/2). For even S the centre texel sits at x = y = 1/S and the
    # corner texel at 1 - 1/S; log ratio = -3/2 [ln(1 + 2/S^2) - ln(1 + 2(1 - 1/S)^2)] + O(1/S^3), i.e.
    # ratio / 3^(3/2) = 1 - 2/S + O(1/S^2): the relative deficit times S must tend to 2.
    prev = None
    for S in (16, 64, 256, 1024):
        om = texel_solid_angles(S)[0]
        ratio = om[S // 2, S // 2] / om[0, 0]
        deficit = 1 - ratio / 3**1.5
        assert 0 < deficit * S < 2.0 + 8.0 / S, (S, deficit * S)
        assert deficit * S > 2.0 - 8.0 / S, (S, deficit * S)
        if prev is not None:
            assert deficit < prev
        prev = deficit


def test_cubemap_solid_angles_and_directions_per_level():
    c = Cubemap(jnp.ones((6, 8, 8, 1))).with_mips()
    for m in range(c.num_levels):
        Sm = 8 >> m
        np.testing.assert_allclose(c.solid_angles(m), ref_solid_angles(Sm), rtol=0, atol=16 * EPS64 * math.pi / 6)
        np.testing.assert_allclose(c.directions(m), ref_geometry(Sm)[0], atol=4 * EPS64)


# ----------------------------------------------------------------------------------------------
# Lookup
# ----------------------------------------------------------------------------------------------


def cube_plane_centres(S):
    """Texel centres as un-normalised points on the unit cube: s, t are dyadic, so exactly representable."""
    c = (np.arange(S) + 0.5) / S
    tc, sc = np.meshgrid(2 * c - 1, 2 * c - 1, indexing="ij")
    return np.stack([gl_inverse(f, sc, tc) for f in range(6)])


def random_cube(S, C=3, seed=0, dtype=np.float64, lo=0.1, hi=3.0):
    return Cubemap(jnp.asarray(np.random.default_rng(seed).uniform(lo, hi, (6, S, S, C)), dtype))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sample_at_texel_centres_is_exact(dtype):
    # Directions on the cube with dyadic (s, t): s = (sc/|ma| + 1)/2 is exact, x = sS + 1/2 is an integer,
    # the bilinear fraction is exactly 0, so the lookup must reproduce the texel bit for bit.
    S = 8
    cube = random_cube(S, dtype=dtype)
    out = np.asarray(sample(cube, cube_plane_centres(S)))
    np.testing.assert_array_equal(out, np.asarray(cube.levels[0]))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sample_at_texel_centres(dtype):
    S = 8
    cube = random_cube(S, dtype=dtype)
    lv = np.asarray(cube.levels[0], np.float64)
    eps = np.finfo(dtype).eps
    # Unit texel-centre directions in `dtype`: s is off by a few eps (rounding of the direction, |sc/ma|,
    # the division), so x = sS + 1/2 is off by <= 4 S eps and the bilinear weights leak <= 4 S eps of a
    # neighbour (values differ by <= 2.9). Plus <= 2 ulps of the value itself (pad average + lerp).
    out = np.asarray(sample(cube, jnp.asarray(texel_directions(S), dtype)), np.float64)
    tol = 4 * S * eps * 2.9 * 2 + 2 * eps * 3.0
    np.testing.assert_allclose(out, lv, rtol=0, atol=tol)
    # From points on the cube (exact s, t) only the value rounding remains: <= 1 ulp.
    out = np.asarray(sample(cube, cube_plane_centres(S)), np.float64)
    np.testing.assert_allclose(out, lv, rtol=eps, atol=0)


def bilinear_ref(level, face, s, t):
    """Independent in-face bilinear lookup (no seams) for points at least half a texel inside the face."""
    S = level.shape[1]
    x, y = s * S - 0.5, t * S - 0.5
    j0, i0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - j0)[..., None], (y - i0)[..., None]
    g = lambda i, j: level[face, i, j]  # noqa: E731
    return (g(i0, j0) * (1 - fx) + g(i0, j0 + 1) * fx) * (1 - fy) + (
        g(i0 + 1, j0) * (1 - fx) + g(i0 + 1, j0 + 1) * fx
    ) * fy


def test_sample_inside_faces_is_bilinear():
    S = 8
    cube = random_cube(S, C=3, seed=5)
    rng = np.random.default_rng(6)
    face = rng.integers(0, 6, 400)
    s, t = rng.uniform(0.5 / S, 1 - 0.5 / S, (2, 400))
    d = face_to_dir(face, s, t, xp=np) * rng.uniform(0.3, 3.0, (400, 1))  # any length
    out = np.asarray(sample(cube, d))
    # Both sides are a few float64 operations on values <= 3.
    np.testing.assert_allclose(out, bilinear_ref(np.asarray(cube.levels[0]), face, s, t), rtol=0, atol=64 * EPS64)


# The 12 cube edges as (axis a, sign a, axis b, sign b), and the 8 corners.
EDGES = [(a, sa, b, sb) for a in range(3) for b in range(a + 1, 3) for sa in (1, -1) for sb in (1, -1)]
CORNERS = [np.array([sx, sy, sz], float) for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)]


def edge_pairs(eps, k=39):
    """Points just either side of every cube edge: p +/- eps (sa e_a - sb e_b), p on the edge."""
    u = np.concatenate([np.linspace(-0.98, 0.98, k), [-0.9999, 0.9999]])
    plus, minus = [], []
    for a, sa, b, sb in EDGES:
        c = 3 - a - b
        p = np.zeros((len(u), 3))
        p[:, a], p[:, b], p[:, c] = sa, sb, u
        step = np.zeros(3)
        step[a], step[b] = sa * eps, -sb * eps
        plus.append(p + step)
        minus.append(p - step)
    return np.concatenate(plus), np.concatenate(minus)


def corner_triples(eps):
    """Three points next to every cube corner, each pushed onto a different face."""
    return [np.stack([c + eps * c * np.eye(3)[k] for k in range(3)]) for c in CORNERS]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("kind", ["random", "smooth"])
def test_lookup_is_continuous_across_edges_and_corners(kind, dtype):
    S = 8
    if kind == "random":
        cube = random_cube(S, C=3, seed=11, dtype=dtype, lo=0.0, hi=1.0)
    else:
        cube = Cubemap.from_function(smooth_f, S, dtype=dtype)
    lv = np.asarray(cube.levels[0], np.float64)
    rng_ = lv.max() - lv.min()
    eps = 1e-9 if dtype == np.float64 else 1e-4
    ulp = np.finfo(dtype).eps
    # Moving a direction by eps changes |sc/ma| by <= 2 eps, i.e. the padded texel coordinate by <= S eps on
    # each side; a bilinear patch changes by at most (value range) per texel: |jump| <= 2 S eps range, plus the
    # rounding of the directions/values in `dtype` (the cube converts the directions to its dtype).
    tol = 2 * S * eps * rng_ * 2 + 16 * S * ulp * rng_
    p, m = edge_pairs(eps)
    fp, _, _ = dir_to_face(p, xp=np)
    fm, _, _ = dir_to_face(m, xp=np)
    assert (fp != fm).all()  # each pair really straddles a seam
    jump = np.abs(np.asarray(sample(cube, p), np.float64) - np.asarray(sample(cube, m), np.float64))
    assert jump.max() <= tol, (jump.max(), tol)
    for tri in corner_triples(eps):
        f3, _, _ = dir_to_face(tri, xp=np)
        assert len(set(f3.tolist())) == 3
        v = np.asarray(sample(cube, tri), np.float64)
        assert np.abs(v - v[0]).max() <= 2 * tol
    # The check has teeth: for random data the texels on the two sides of these edges differ by O(range),
    # so a lookup without the seam pad (nearest texel, or clamp to the face) would jump by that much.
    if kind == "random":
        fa, sa_, ta = dir_to_face(p, xp=np)
        fb, sb_, tb = dir_to_face(m, xp=np)
        ja = np.clip((sa_ * S).astype(int), 0, S - 1)
        ia = np.clip((ta * S).astype(int), 0, S - 1)
        jb = np.clip((sb_ * S).astype(int), 0, S - 1)
        ib = np.clip((tb * S).astype(int), 0, S - 1)
        nearest_jump = np.abs(lv[fa, ia, ja] - lv[fb, ib, jb])
        assert nearest_jump.max() > 0.5  # a nearest-texel lookup would jump here


def test_smooth_function_lookup_accuracy_inside_faces():
    # Away from the seams the lookup of an area-filtered smooth function is second order: bilinear
    # interpolation error <= h^2 M2/8 plus area-mean vs point value <= h^2 M2/24 per axis, h <= pi/(2S) the
    # texel's angular size. (Within one texel of a face edge the GL-style seam pad -- the nearest texel of the
    # neighbouring face treated as if it lay on this face's extended plane -- is first order, see the round trip.)
    for S in (16, 32):
        cube = Cubemap.from_function(smooth_f, S, dtype=jnp.float64)
        rng = np.random.default_rng(S)
        face = rng.integers(0, 6, 500)
        s, t = rng.uniform(1.0 / S, 1 - 1.0 / S, (2, 500))
        d = unit(face_to_dir(face, s, t, xp=np))
        err = np.abs(np.asarray(sample(cube, d)) - smooth_f(d)).max()
        h = math.pi / (2 * S)
        assert err <= 2 * (h * h * SMOOTH_HESS / 8 + h * h * SMOOTH_HESS / 24), (S, err)


def test_trilinear_at_integer_lod_is_bilinear_on_that_level():
    cube = random_cube(8, C=3, seed=2).with_mips()
    d = np.concatenate([rand_dirs(300, 4), texel_directions(2).reshape(-1, 3)])
    for m in range(cube.num_levels):
        a = np.asarray(sample(cube, d, lod=float(m)))
        b = np.asarray(sample(cube.level_cube(m), d))
        # The weight of level m+1 is exactly 0; the two compiled programs may still contract the bilinear
        # lerps into FMAs differently: <= 4 roundings of values <= 3.
        np.testing.assert_allclose(a, b, rtol=0, atol=4 * 3 * EPS64)
    # Fractional lod: linear between the two levels.
    for lod in (0.25, 2.75):
        m = int(lod)
        a = np.asarray(sample(cube.level_cube(m), d))
        b = np.asarray(sample(cube.level_cube(m + 1), d))
        np.testing.assert_allclose(
            np.asarray(sample(cube, d, lod=lod)), a + (lod - m) * (b - a), rtol=0, atol=16 * EPS64
        )
    # Per-direction lod of the same batch shape.
    lods = np.random.default_rng(1).uniform(0, 3, len(d))
    each = np.stack([np.asarray(sample(cube, d[k], lod=lods[k])) for k in range(0, len(d), 37)])
    np.testing.assert_allclose(np.asarray(sample(cube, d, lod=lods))[::37], each, rtol=0, atol=16 * EPS64)


def test_lod_is_clamped():
    cube = random_cube(8, C=3, seed=3).with_mips()
    d = rand_dirs(50, 5)
    last = cube.num_levels - 1
    # Same program (only the lod value differs): clamped values must agree bit for bit.
    np.testing.assert_array_equal(np.asarray(sample(cube, d, lod=-2.5)), np.asarray(sample(cube, d, lod=0.0)))
    np.testing.assert_array_equal(np.asarray(sample(cube, d, lod=99.0)), np.asarray(sample(cube, d, lod=float(last))))
    np.testing.assert_array_equal(np.asarray(sample(cube, d, lod=np.inf)), np.asarray(sample(cube, d, lod=float(last))))
    # ... and the last level is that level's own bilinear lookup (separate program: FMA contraction may differ).
    np.testing.assert_allclose(
        np.asarray(sample(cube, d, lod=99.0)), np.asarray(sample(cube.level_cube(last), d)), rtol=0, atol=4 * 3 * EPS64
    )
    # A single-level map ignores lod.
    single = cube.level_cube(0)
    np.testing.assert_array_equal(np.asarray(sample(single, d, lod=3.0)), np.asarray(sample(single, d)))


def test_gradients_finite_and_correct():
    cube = random_cube(8, C=3, seed=7).with_mips()
    special = [[1.0, 1.0, 1.0], [1.0, 0.0, 1.0], [0.0, 0.0, 0.0]]  # cube corner, edge, zero vector
    d = np.concatenate([rand_dirs(64, 8), texel_directions(2).reshape(-1, 3), special])
    n = len(d)
    weights = jnp.array([1.0, -0.5, 0.25])

    def f(levels, x, lod):
        return jnp.sum(Cubemap(levels).sample(x, lod) * weights)

    # One compiled gradient w.r.t. texels, directions and lod, evaluated at several (per-direction) lods,
    # including integer lods, both clamps and beyond them.
    grad = jax.jit(jax.grad(f, argnums=(0, 1, 2)))
    for lod in (1.3, 0.0, 1.0, 3.0, -1.0, 7.0):
        g_lv, g_d, g_lod = grad(cube.levels, jnp.asarray(d), jnp.full(n, lod))
        assert all(np.isfinite(np.asarray(g)).all() for g in g_lv)
        assert np.isfinite(np.asarray(g_d)).all() and np.isfinite(np.asarray(g_lod)).all()
        # the lookup is linear in the texels with interpolation weights summing to 1 per output
        tot = [sum(float(jnp.sum(g[..., c])) for g in g_lv) for c in range(3)]
        np.testing.assert_allclose(tot, n * np.asarray(weights), rtol=1e-12)
        if lod == 1.3:
            # d/dlod of a + (b - a)(lod - m) is b - a, the difference of the two levels' lookups.
            diff = np.asarray(sample(cube.level_cube(2), d)) - np.asarray(sample(cube.level_cube(1), d))
            np.testing.assert_allclose(np.asarray(g_lod), diff @ np.asarray(weights), rtol=1e-10, atol=1e-12)
        if lod in (-1.0, 7.0):
            np.testing.assert_array_equal(np.asarray(g_lod), 0.0)  # clamped: no gradient

    # Directions against central differences at generic points inside faces (piecewise bilinear: a step of
    # 1e-7 stays inside one bilinear patch except with probability ~1e-6; truncation error O(step^2), rounding
    # ~eps * |f| / step = 2e-9): each partial derivative (reverse mode) at each point.
    rng = np.random.default_rng(9)
    face = rng.integers(0, 6, 20)
    s, t = rng.uniform(0.1, 0.9, (2, 20))
    x0 = unit(face_to_dir(face, s, t, xp=np))
    f1 = jax.jit(lambda x: f(cube.levels, x, 0.7))  # one direction -> one weighted lookup
    for x in x0:
        check_partials(f1, x, range(3), step=1e-7, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2)])
def test_batch_shapes(shape, dtype=np.float64):
    cube = random_cube(8, C=3, seed=4, dtype=dtype).with_mips()
    n = int(np.prod(shape, dtype=int))
    d_all, lod_all = rand_dirs(6, 12), np.random.default_rng(2).uniform(0, 3, 6)
    d, lod = d_all[:n].reshape(shape + (3,)), lod_all[:n].reshape(shape)
    out = _jsample(cube, jnp.asarray(d), jnp.asarray(lod))
    assert out.shape == shape + (3,) and out.dtype == dtype
    flat = np.asarray(sample(cube, d_all, lod=lod_all))[:n].reshape(shape + (3,))
    # different programs (batch shapes): FMA contraction may differ, a few roundings of values <= 3.
    np.testing.assert_allclose(np.asarray(out), flat, rtol=0, atol=4 * 3 * np.finfo(dtype).eps)
    # scalar lod broadcast over any batch
    assert _jsample(cube, jnp.asarray(d), jnp.asarray(1.0)).shape == shape + (3,)


def test_jit_matches_eager(dtype=np.float32):
    # One dtype: the eager path compiles every primitive separately (seconds); float32 is the stricter case
    # for FMA / fusion differences.
    cube = random_cube(4, C=3, seed=13, dtype=dtype).with_mips()
    d = jnp.asarray(rand_dirs(200, 14), dtype)
    lod = jnp.asarray(np.random.default_rng(3).uniform(-1, 4, 200), dtype)
    eager = np.asarray(cube.sample(d, lod))
    jitted = np.asarray(jax.jit(lambda c, x, l: c.sample(x, l))(cube, d, lod))
    # XLA may fuse/contract the lerps into FMAs: a few roundings of values <= 3.
    np.testing.assert_allclose(jitted, eager, rtol=0, atol=8 * np.finfo(dtype).eps * 3)


def test_float32_matches_float64():
    c64 = random_cube(8, C=3, seed=15).with_mips()
    c32 = Cubemap([lv.astype(jnp.float32) for lv in c64.levels])
    d = rand_dirs(300, 16)
    a = np.asarray(sample(c64, d, lod=1.4))
    b = np.asarray(sample(c32, jnp.asarray(d, jnp.float32), lod=1.4), np.float64)
    # float32 rounding of values (<= 3) and of the direction (s off by ~4 eps32 -> weights off by 4 S eps32).
    np.testing.assert_allclose(b, a, rtol=0, atol=3 * (16 + 4 * 8 * 2) * EPS32)


# ----------------------------------------------------------------------------------------------
# Pyramid
# ----------------------------------------------------------------------------------------------


def test_downsample_preserves_power_exactly():
    cube = random_cube(16, C=3, seed=21, lo=0.0, hi=50.0)
    mips = cube.with_mips()
    assert [lv.shape[1] for lv in mips.levels] == [16, 8, 4, 2, 1]
    p0 = np.sum(np.asarray(cube.levels[0]) * ref_solid_angles(16)[..., None], axis=(0, 1, 2))
    for m, lv in enumerate(mips.levels):
        Sm = lv.shape[1]
        p = np.sum(np.asarray(lv) * ref_solid_angles(Sm)[..., None], axis=(0, 1, 2))
        # float64 sums of <= 1536 positive terms per level, each level built from the previous by sums of
        # four: relative error <= (1536 + 8 m) eps.
        np.testing.assert_allclose(p, p0, rtol=(1536 + 8 * m) * EPS64)
    np.testing.assert_allclose(np.asarray(mips.power()), p0, rtol=1536 * EPS64)


def test_downsample_is_solid_angle_weighted_mean():
    lv = np.random.default_rng(22).uniform(0, 1, (6, 8, 8, 2))
    om = ref_solid_angles(8)[..., None]
    ref = (lv * om).reshape(6, 4, 2, 4, 2, 2).sum((2, 4)) / om.reshape(6, 4, 2, 4, 2, 1).sum((2, 4))
    np.testing.assert_allclose(np.asarray(downsample(jnp.asarray(lv))), ref, rtol=8 * EPS64)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_downsample_keeps_constants(dtype):
    c = np.asarray(0.7, dtype)
    mips = Cubemap(jnp.full((6, 16, 16, 1), c, dtype)).with_mips()
    eps = np.finfo(dtype).eps
    for m, lv in enumerate(mips.levels):
        assert lv.dtype == dtype
        # each level: ratio of two 4-term sums (<= 3 eps each) and one product / division: <= 9 eps per level.
        np.testing.assert_allclose(np.asarray(lv, np.float64), float(c), rtol=9 * m * eps + eps)


def test_pyramid_errors_and_odd_sizes():
    with pytest.raises(ValueError, match="odd size 3"):
        downsample(jnp.ones((6, 3, 3, 1)))
    with pytest.raises(ValueError, match="at most 4 levels"):
        Cubemap(jnp.ones((6, 8, 8, 1))).with_mips(5)
    with pytest.raises(ValueError, match="positive integer"):
        Cubemap(jnp.ones((6, 8, 8, 1))).with_mips(0)
    # 12 -> 6 -> 3 stops at the first odd size
    assert [lv.shape[1] for lv in Cubemap(jnp.ones((6, 12, 12, 1))).with_mips().levels] == [12, 6, 3]
    with pytest.raises(ValueError, match=r"\(6, S, S, C\)"):
        Cubemap(jnp.ones((6, 4, 5, 1)))
    with pytest.raises(ValueError, match="S>>m"):
        Cubemap([jnp.ones((6, 8, 8, 1)), jnp.ones((6, 3, 3, 1))])
    with pytest.raises(ValueError, match="float"):
        Cubemap(jnp.ones((6, 4, 4, 1), jnp.int32))


def test_cubemap_is_a_pytree():
    cube = random_cube(4, C=2).with_mips()
    cube = Cubemap(cube.levels, {"quantity": "test"})
    leaves, tree = jax.tree_util.tree_flatten(cube)
    assert len(leaves) == 3
    back = jax.tree_util.tree_unflatten(tree, [2 * x for x in leaves])
    assert back.metadata == {"quantity": "test"} and back.face_size == 4 and back.num_levels == 3
    np.testing.assert_array_equal(np.asarray(back.levels[1]), 2 * np.asarray(cube.levels[1]))


# ----------------------------------------------------------------------------------------------
# from_function
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_from_function_constant(dtype):
    cube = Cubemap.from_function(lambda d: jnp.full(d.shape[:-1] + (3,), 2.3), 8, dtype=dtype)
    assert cube.levels[0].shape == (6, 8, 8, 3) and cube.dtype == dtype
    # sum of q^2 = 16 normalised weights times a constant: <= 16 eps64 before the cast to `dtype`.
    np.testing.assert_allclose(np.asarray(cube.levels[0], np.float64), 2.3, rtol=16 * EPS64 + np.finfo(dtype).eps)
    # a scalar-valued fn gives one channel
    assert Cubemap.from_function(lambda d: d[..., 0] * 0 + 1.0, 4).channels == 1


def test_from_function_point_samples():
    # supersample=1: the value at the texel centre.
    cube = Cubemap.from_function(smooth_f, 8, supersample=1, dtype=jnp.float64)
    np.testing.assert_allclose(np.asarray(cube.levels[0]), smooth_f(ref_geometry(8)[0]), rtol=0, atol=16 * EPS64)


def test_from_function_linear_is_texel_mean():
    # For L = a + b.w the exact area-filtered texel is a + b.Phi_j/Omega_j with Phi_j the texel's first
    # moment (closed form). from_function uses a q x q midpoint rule: its error is second order in the
    # sub-cell size, so halving the sub-cells must divide the error by ~4 (we require > 3), and q = 8 must
    # be within 1e-4 (midpoint rule, sub-cell h = 2/(8 S) = 1/32: h^2/24 * |Laplacian/f| <= 8 -> 3e-4 relative
    # on the moment of a texel, times |b| = 1.2 => 4e-4 bound; measured ~1.5e-5).
    S = 8
    a, b = 0.4, np.array([0.8, -0.5, 0.7])
    _, cor = ref_geometry(S)
    exact = a + polygon_moment(cor) @ b / ref_solid_angles(S)
    errs = []
    for q in (2, 4, 8):
        cube = Cubemap.from_function(lambda d: a + d @ jnp.asarray(b), S, supersample=q, dtype=jnp.float64)
        errs.append(np.abs(np.asarray(cube.levels[0])[..., 0] - exact).max())
    assert errs[0] / errs[1] > 3 and errs[1] / errs[2] > 3, errs
    assert errs[2] < 4e-4 * np.linalg.norm(b)


def test_from_function_bad_output():
    with pytest.raises(ValueError, match="expected"):
        Cubemap.from_function(lambda d: jnp.ones(5), 4)
    with pytest.raises(ValueError, match="NaN"):
        Cubemap.from_function(lambda d: jnp.where(d[..., 0] > 0.9, jnp.nan, 1.0), 4)
    for bad in (0, -2, 2.5, True):
        with pytest.raises(ValueError, match="positive integer"):
            Cubemap.from_function(lambda d: d[..., 0], bad)


# ----------------------------------------------------------------------------------------------
# Equirect
# ----------------------------------------------------------------------------------------------


def test_equirect_convention():
    # docs/conventions.md: u = 0.5 + atan2(z, x)/(2 pi), v_up = 0.5 + asin(y)/pi, row 0 on top (+Y).
    d = rand_dirs(500, 30)
    u, v = jax.jit(dir_to_equirect)(jnp.asarray(d))
    np.testing.assert_allclose(np.asarray(u), 0.5 + np.arctan2(d[:, 2], d[:, 0]) / (2 * np.pi), atol=4 * EPS64)
    np.testing.assert_allclose(np.asarray(v), 0.5 + np.arcsin(d[:, 1]) / np.pi, atol=4 * EPS64)
    np.testing.assert_allclose(np.asarray(jax.jit(equirect_to_dir)(u, v)), d, atol=16 * EPS64)
    e = equirect_directions(4)
    assert e.shape == (4, 8, 3)
    assert e[0, 0, 1] > 0.9 * math.sin(3 * math.pi / 8) and e[-1, 0, 1] < 0  # row 0 is the top
    np.testing.assert_allclose(
        e[2, 4],
        [
            math.cos(math.pi / 8) * math.cos(math.pi / 8),
            -math.sin(math.pi / 8),
            math.cos(math.pi / 8) * math.sin(math.pi / 8),
        ],
        atol=1e-15,
    )


def test_from_equirect_smooth_matches_from_function():
    # Point samples of smooth_f on a 256 x 512 panorama. from_equirect halves it once (solid-angle 2x2 box)
    # and averages bilinear lookups; each step is second order in the pixel size h = pi/128 (after halving):
    # box-then-interpolate <= h^2 M2/4, bilinear <= h^2 M2/8, sub-sample quadrature <= h^2 M2/24
    # -> <= 0.4 h^2 M2 = 4.8e-4 with M2 = 2. (Measured: 3e-4.)
    img = smooth_f(equirect_directions(256))
    for dtype in (jnp.float64,):  # float32 panoramas: see the high-frequency test
        cube = Cubemap.from_equirect(img, 16, dtype=dtype)
        ref = Cubemap.from_function(smooth_f, 16, supersample=16, dtype=jnp.float64)
        assert cube.dtype == dtype and cube.levels[0].shape == (6, 16, 16, 3)
        err = np.abs(np.asarray(cube.levels[0], np.float64) - np.asarray(ref.levels[0])).max()
        h = math.pi / 128
        assert err <= 0.4 * h * h * SMOOTH_HESS + 4 * np.finfo(dtype).eps, err


@pytest.mark.parametrize("pattern", ["checkerboard", "columns"])
def test_from_equirect_high_frequency_does_not_alias(pattern):
    H = 1024
    i, j = np.meshgrid(np.arange(H), np.arange(2 * H), indexing="ij", sparse=True)
    img = ((i + j) % 2 if pattern == "checkerboard" else (j % 2) + 0 * i).astype(np.float32)
    cube = Cubemap.from_equirect(img, 16)
    vals = np.asarray(cube.levels[0])[..., 0]
    # A 16^2 cube texel spans >= 2 atan(1/16)/(pi/1024) = 40 pixels across, so any area filter sees >= 1600
    # pixels of which at most one boundary row/column (~4*40) is unbalanced: |mean - 1/2| <= 160/(2*1600) = 0.05.
    assert np.abs(vals - 0.5).max() <= 0.05, np.abs(vals - 0.5).max()
    # Point sampling (nearest pixel at the texel centre, written here) aliases to 0/1 everywhere.
    u, v = dir_to_equirect(jnp.asarray(texel_directions(16)))
    col = np.clip((np.asarray(u) * 2 * H).astype(int), 0, 2 * H - 1)
    row = np.clip(((1 - np.asarray(v)) * H).astype(int), 0, H - 1)
    point = img[row, col]
    assert np.abs(point - 0.5).min() == 0.5


@functools.partial(jax.jit, static_argnums=(1, 2))
def to_equirect(cube, height, supersample=1):
    return cube.to_equirect(height, supersample=supersample)


def test_equirect_cube_equirect_round_trip():
    # Smooth function -> 64 x 128 panorama -> cube -> panorama. Second-order interior errors
    # (<= h^2 M2 with h = pi/(2S)) plus a first-order seam term: within one texel of a face edge the pad is
    # the neighbouring face's nearest texel placed on this face's extended plane, misplaced along the edge by
    # <= 1/S on the plane (<= 0.58/S rad), i.e. a value error <= |grad f| 0.58/S, seen with weight <= 1/2.
    img = smooth_f(equirect_directions(64))
    errs = {}
    for S in (32, 64):
        cube = Cubemap.from_equirect(img, S, dtype=jnp.float64)
        back = np.asarray(to_equirect(cube, 64))
        assert back.shape == img.shape
        errs[S] = np.abs(back - img).max()
        h = math.pi / (2 * S)
        assert (
            errs[S] <= 0.5 * SMOOTH_GRAD * 0.58 / S + h * h * SMOOTH_HESS + 0.4 * (math.pi / 64) ** 2 * SMOOTH_HESS
        ), (S, errs[S])
    assert errs[64] < 0.6 * errs[32]  # converges (first order at the seams)
    # to_equirect with supersampling: pixel means instead of point values, still close.
    back2 = np.asarray(to_equirect(Cubemap.from_equirect(img, 64, dtype=jnp.float64), 32, 2))
    assert back2.shape == (32, 64, 3)


def test_from_equirect_bad_input():
    good = np.ones((8, 16, 3), np.float32)
    with pytest.raises(ValueError, match="twice the height"):
        Cubemap.from_equirect(np.ones((8, 15, 3)), 4)
    with pytest.raises(ValueError, match="twice the height"):
        Cubemap.from_equirect(np.ones((16, 8, 3)), 4)
    with pytest.raises(ValueError, match="twice the height"):
        Cubemap.from_equirect(np.ones((2, 8, 16, 3)), 4)
    with pytest.raises(ValueError, match="twice the height"):
        Cubemap.from_equirect(np.ones((0, 0, 3)), 4)
    for bad in (np.nan, np.inf, -np.inf):
        img = good.copy()
        img[3, 5, 1] = bad
        with pytest.raises(ValueError, match="1 NaN/Inf"):
            Cubemap.from_equirect(img, 4)
    for size in (0, -4, 4.0, None):
        with pytest.raises(ValueError, match="face_size must be a positive integer"):
            Cubemap.from_equirect(good, size)
    # 2-D (grey) panoramas are accepted as one channel
    assert Cubemap.from_equirect(np.ones((8, 16)), 4).channels == 1


def test_static_lods_and_a_cube_padded_on_the_host_sample_as_the_plain_cube():
    """`sample(d, 0.0)` (a static lod: the background's lookup) reads level 0 alone and gives what
    the trilinear lookup at a traced lod of 0 gives, bit for bit, as does a static negative lod.
    `padded`: the flat buffer made in NumPy is `_Pyramid`'s bit for bit (float32 and float64);
    lookups through it (traced and static lods) give the same values; it is made once per set of
    levels; a traced cube is left as it is; shapes give the buffer's shape."""
    from jaxpbr.ibl.cubemap import PaddedCubemap, _Pyramid, padded

    rng = np.random.default_rng(12)
    levels = [rng.uniform(0.0, 4.0, (6, 16 >> m, 16 >> m, 3)) for m in range(4)]
    with jax.enable_x64(True):
        cube64 = Cubemap([jnp.asarray(lv, jnp.float64) for lv in levels])
        np.testing.assert_array_equal(np.asarray(padded(cube64).flat), np.asarray(jax.jit(lambda c: _Pyramid(c.levels).flat)(cube64)))
    cube = Cubemap([jnp.asarray(lv, jnp.float32) for lv in levels])
    p = padded(cube)
    assert isinstance(p, PaddedCubemap) and padded(cube).flat is p.flat and padded(p) is p
    d = jnp.asarray(rng.standard_normal((800, 3)), jnp.float32)
    lod = jnp.asarray(rng.uniform(-0.5, 3.5, 800), jnp.float32)

    @jax.jit
    def looks(cube, p, d, lod):
        flat = _Pyramid(cube.levels).flat
        zero = jnp.zeros_like(lod)
        return (flat, p.flat, cube.sample(d, lod), p.sample(d, lod), cube.sample(d, zero),
                cube.sample(d, 0.0), cube.sample(d, 0), cube.sample(d, -2.5), p.sample(d, 0.0),
                Cubemap([cube.levels[0]]).sample(d, 0.0), jnp.float32(isinstance(padded(cube), PaddedCubemap)))

    out = [np.asarray(x) for x in looks(cube, p, d, lod)]
    np.testing.assert_array_equal(out[0], out[1])  # the host pads are the in-trace ones
    np.testing.assert_array_equal(out[2], out[3])  # trilinear at traced lods
    for k in range(5, 10):  # static lods <= 0, plain and padded, and the one-level cube
        np.testing.assert_array_equal(out[k], out[4])
    assert out[10] == 0  # traced levels are not padded on the host
    # A concrete cube first padded inside a trace (a render under jit of a concrete environment):
    # the trace gets the host array as a constant, and no traced value is kept for later calls.
    fresh = Cubemap([jnp.asarray(lv, jnp.float32) for lv in levels])
    inside = jax.jit(lambda d: padded(fresh).sample(d, 0.0))(d)
    assert not isinstance(padded(fresh).flat, jax.core.Tracer)
    np.testing.assert_array_equal(np.asarray(inside), out[4])
    shapes = Cubemap.__new__(Cubemap)
    shapes.__dict__.update(levels=tuple(jax.ShapeDtypeStruct((6, 8 >> m, 8 >> m, 3), jnp.float32) for m in range(2)), info=cube.info)
    assert padded(shapes).flat.shape == (6 * (10 * 10 + 6 * 6), 3)
