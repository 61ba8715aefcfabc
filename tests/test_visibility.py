"""Triangle-mesh visibility (jaxpbr.rendering.visibility): both backends against a float64
brute-force Moller-Trumbore loop over all triangles, closed-form cases, occlusion, ray continuation
through stacked and coplanar layers, shadow-ray offsets, and what the JAX traversal compiles.

Every JAX BVH here is padded to the same shapes (min_triangles=_CAP) and every ray batch to one
bucket, so the traversal compiles once per query kind (intersect, occluded, first_k_hits)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpbr.errors import InputError
from jaxpbr.rendering import bvh as bvh_mod
from jaxpbr.rendering.visibility import (
    TriangleAccel,
    build_bvh,
    embree_available,
    intersect_jax,
    offset_ray_origin,
)

_CAP = 1024  # BVH arrays padded as for this many triangles: one compiled traversal for all meshes
BACKENDS = ["jax"] + (["embree"] if embree_available() else [])
backends = pytest.mark.parametrize("backend", BACKENDS)


def _accel(v, f, backend):
    return TriangleAccel.build(v, f, backend=backend, min_triangles=_CAP)


# --------------------------------------------------------------------------------------------------
# meshes and the oracle


def icosphere(sub=2, radius=1.0, center=(0.0, 0.0, 0.0)):
    t = (1 + 5**0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(sub):
        cache = {}
        verts = list(v)

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        nf = []
        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        v, f = np.array(verts), np.array(nf)
    return v * radius + np.asarray(center), f


def cube():
    v = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def soup(n=200, seed=3):
    rng = np.random.default_rng(seed)
    c = rng.uniform(-1, 1, (n, 1, 3))
    v = (c + rng.normal(scale=0.25, size=(n, 3, 3))).reshape(-1, 3)
    return v, np.arange(3 * n).reshape(n, 3)


def unit_grid(k):
    """A k x k grid of unit squares in the plane z = 0, two triangles each: (vertices, triangles)."""
    g = np.stack(np.meshgrid(np.arange(k + 1.0), np.arange(k + 1.0), indexing="ij"), -1).reshape(-1, 2)
    v = np.concatenate([g, np.zeros((len(g), 1))], 1)
    idx = np.arange((k + 1) ** 2).reshape(k + 1, k + 1)
    f = np.concatenate([np.stack([idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:]], -1).reshape(-1, 3),
                        np.stack([idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 3)])
    return v, f


MESHES = {"icosphere": icosphere(2), "soup": soup(), "cube": cube()}


def brute_all(v, f, o, d):
    """t (N, T) of every triangle hit (inf where missed), float64 Moller-Trumbore with closed
    barycentric intervals, on the float32-rounded mesh and rays; and b1, b2 (N, T)."""
    tri = np.asarray(v, np.float32).astype(np.float64)[f]
    o = np.asarray(o, np.float32).astype(np.float64)[:, None]
    d = np.asarray(d, np.float32).astype(np.float64)[:, None]
    v0, e1, e2 = tri[None, :, 0], (tri[:, 1] - tri[:, 0])[None], (tri[:, 2] - tri[:, 0])[None]
    p = np.cross(d, e2)
    det = (e1 * p).sum(-1)
    with np.errstate(all="ignore"):
        s = o - v0
        b1 = (s * p).sum(-1) / det
        q = np.cross(s, e1)
        b2 = (d * q).sum(-1) / det
        t = (e2 * q).sum(-1) / det
    ok = (det != 0) & (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1) & (t >= 0)
    return np.where(ok, t, np.inf), b1, b2


def rays_at(v, n, seed, spread=3.0):
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o = spread * o / np.linalg.norm(o, axis=1, keepdims=True)
    target = v[rng.integers(0, len(v), n)] * rng.uniform(0.0, 0.9, (n, 1)) + rng.normal(scale=0.05, size=(n, 3))
    return o, target - o


def check_against_brute(h, v, f, o, d, rtol_t=1e-5, tol_b=1e-5):
    """prim exact unless the brute force sees another triangle within a tie of the best t (edges,
    crossings); t relative, barycentrics absolute."""
    t_all, b1_all, b2_all = brute_all(v, f, o, d)
    best = t_all.min(1)
    t, prim, b1, b2 = (np.asarray(x) for x in h)
    hit = np.isfinite(best)
    assert np.array_equal(prim >= 0, hit)
    rows = np.nonzero(hit)[0]
    p = prim[rows]
    tie = np.abs(t_all[rows, p] - best[rows]) <= 1e-6 * best[rows]
    assert tie.all(), "a reported triangle that is not (one of) the nearest"
    np.testing.assert_allclose(t[rows], best[rows], rtol=rtol_t)
    np.testing.assert_allclose(b1[rows], b1_all[rows, p], atol=tol_b)
    np.testing.assert_allclose(b2[rows], b2_all[rows, p], atol=tol_b)
    exact = (t_all[rows] <= best[rows, None] * (1 + 1e-6)).sum(1) == 1
    assert np.array_equal(p[exact], np.argmin(t_all[rows], 1)[exact])
    return hit.mean()


# --------------------------------------------------------------------------------------------------
# against brute force


@backends
@pytest.mark.parametrize("mesh", list(MESHES))
def test_against_brute_force(mesh, backend):
    v, f = MESHES[mesh]
    o, d = rays_at(v, 300, seed=len(mesh))
    acc = _accel(v, f, backend)
    frac = check_against_brute(acc.intersect(o, d), v, f, o, d)
    assert frac > 0.5


def test_backends_agree():
    if "embree" not in BACKENDS:
        pytest.skip("embreex not installed")
    v, f = MESHES["soup"]
    o, d = rays_at(v, 1000, seed=7, spread=2.0)
    he = _accel(v, f, "embree").intersect(o, d)
    hj = _accel(v, f, "jax").intersect(o, d)
    assert np.array_equal(he.prim, np.asarray(hj.prim))
    np.testing.assert_allclose(he.t, np.asarray(hj.t), rtol=1e-6)
    np.testing.assert_allclose(he.b1, np.asarray(hj.b1), atol=1e-9)


# --------------------------------------------------------------------------------------------------
# closed forms


def unit_quad(z=0.0):
    v = np.array([[0, 0, z], [1, 0, z], [1, 1, z], [0, 1, z]], float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


@backends
def test_unit_quad_closed_form(backend):
    v, f = unit_quad()
    acc = _accel(v, f, backend)
    g = (np.arange(16) + 0.3) / 16.0
    x, y = [a.ravel() for a in np.meshgrid(g, g + 0.01)]
    keep = np.abs(x - y) > 1e-3  # off the diagonal (there both triangles are at the same t)
    x, y = x[keep], y[keep]
    for d in ([0.0, 0.0, -1.0], [0.3, -0.2, -1.0]):
        d = np.broadcast_to(np.array(d), (x.size, 3))
        s = 2.5
        o = np.stack([x, y, np.zeros_like(x)], 1) - s * d
        h = acc.intersect(o, d)
        lower = y < x  # triangle 0: p = b1 v1 + b2 v2 -> (b1 + b2, b2); triangle 1: (b1, b1 + b2)
        np.testing.assert_array_equal(np.asarray(h.prim), np.where(lower, 0, 1))
        np.testing.assert_allclose(np.asarray(h.t), s, rtol=1e-6)
        np.testing.assert_allclose(np.asarray(h.b1), np.where(lower, x - y, x), atol=1e-6)
        np.testing.assert_allclose(np.asarray(h.b2), np.where(lower, y, y - x), atol=1e-6)


@backends
@pytest.mark.parametrize("mesh", ["icosphere", "cube"])
def test_inside_a_closed_mesh_every_ray_hits(mesh, backend):
    """Including rays aimed exactly at vertices and edge midpoints (watertightness)."""
    v, f = MESHES[mesh]
    rng = np.random.default_rng(1)
    n = 300
    o = rng.normal(size=(n, 3))
    o *= rng.uniform(0, 0.5, (n, 1)) / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.normal(size=(n, 3))
    tri = v[f]
    aims = np.concatenate([v, 0.5 * (tri[:, 0] + tri[:, 1])])  # vertices, edge midpoints
    o = np.concatenate([o, np.zeros((len(aims), 3))])
    d = np.concatenate([d, aims])
    h = _accel(v, f, backend).intersect(o, d)
    assert (np.asarray(h.prim) >= 0).all()
    assert (np.asarray(h.t) > 0).all() and np.isfinite(np.asarray(h.t)).all()


@backends
def test_rays_parallel_to_a_triangle_miss(backend):
    v, f = unit_quad()
    acc = _accel(v, f, backend)
    o = np.array([[-1.0, 0.5, 0.0], [-1.0, 0.5, 1e-3], [0.5, -1.0, -1e-3], [-1, -1, 0.0]])
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    h = acc.intersect(o, d)
    assert (np.asarray(h.prim) == -1).all() and np.isinf(np.asarray(h.t)).all()
    assert not np.asarray(acc.occluded(o, d)).any()


@backends
def test_degenerate_triangles_are_never_hit(backend):
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [0, 0, 1], [np.nan, 0, 0], [0, 0, 5], [1, 0, 5], [0, 1, 5]], float)
    f = np.array([[0, 1, 2], [0, 0, 3], [3, 3, 3], [0, 5, 4], [6, 7, 8], [0, 2, 1]])  # only 4 is proper
    acc = _accel(v, f, backend)
    aims = np.array([[0.5, 0, 0], [1.5, 0, 0], [0, 0.5, 0], [0, 1, 0], [0, 0, 0.5], [0.2, 0.2, 5]])
    o = np.concatenate([aims + [0, 0, 1], aims + [0, 1, 0], aims + [1, 0, 0]])
    d = np.concatenate([np.tile([0, 0, -1.0], (6, 1)), np.tile([0, -1.0, 0], (6, 1)), np.tile([-1.0, 0, 0], (6, 1))])
    h = acc.intersect(o, d)
    prim = np.asarray(h.prim)
    assert set(prim.tolist()) <= {-1, 4}
    assert prim[5] == 4
    for x in h:
        assert not np.isnan(np.asarray(x, float)).any()
    # meshes with nothing to hit
    for v, f in ((np.zeros((3, 3)), np.array([[0, 1, 2]])), (np.zeros((0, 3)), np.zeros((0, 3), int))):
        acc = _accel(v, f, backend)
        assert (np.asarray(acc.intersect(o, d).prim) == -1).all() and not np.asarray(acc.occluded(o, d)).any()


# --------------------------------------------------------------------------------------------------
# occlusion and ranges


@backends
def test_occluded_matches_intersect(backend):
    """`occluded` answers what `intersect` finds in [tnear, tfar], also for rays that can hit nothing."""
    v, f = MESHES["soup"]
    o, d = rays_at(v, 600, seed=11, spread=2.0)
    rng = np.random.default_rng(2)
    acc = _accel(v, f, backend)
    first = np.asarray(acc.intersect(o, d).t)
    tfar = np.where(np.isfinite(first), first, 5.0) * rng.uniform(0.5, 1.5, len(o))
    tnear = rng.uniform(0, 0.3, len(o)) * tfar
    h = acc.intersect(o, d, tnear=tnear, tfar=tfar)
    occ = np.asarray(acc.occluded(o, d, tnear=tnear, tfar=tfar))
    expect = np.asarray(h.prim) >= 0
    t_all = brute_all(v, f, o, d)[0]
    near_edge = np.any(np.abs(t_all - tfar[:, None]) <= 1e-5 * tfar[:, None], 1)
    near_edge |= np.any(np.abs(t_all - tnear[:, None]) <= 1e-5 * tfar[:, None], 1)
    assert np.array_equal(occ[~near_edge], expect[~near_edge])
    if backend == "jax":
        assert np.array_equal(occ, expect)
    # the range: what intersect found lies in [tnear, tfar] and nothing nearer in it
    t = np.asarray(h.t)
    assert (t[expect] >= tnear[expect]).all() and (t[expect] <= tfar[expect]).all()
    inside = np.where((t_all >= tnear[:, None]) & (t_all <= tfar[:, None]), t_all, np.inf).min(1)
    np.testing.assert_allclose(t[expect], inside[expect], rtol=1e-5)
    # Rays that hit nothing, among rays that do (the same shapes: no other program): a zero or
    # non-finite direction, tfar = -inf, tfar < tnear. `occluded` says False, as `intersect`
    # reports a miss (the JAX BVH's any-hit marks a hit by t = -inf, where such a ray starts).
    hits = np.flatnonzero(expect & ~near_edge)[:5]
    assert hits.size == 5
    d2, tn2, tf2 = d.copy(), tnear.copy(), tfar.copy()
    d2[hits[0]] = 0.0
    d2[hits[1], 0] = np.nan
    tf2[hits[2]] = -np.inf
    tf2[hits[3]] = -1.0
    tn2[hits[4]], tf2[hits[4]] = tf2[hits[4]], tn2[hits[4]] * 0.5
    occ2 = np.asarray(acc.occluded(o, d2, tnear=tn2, tfar=tf2))
    prim2 = np.asarray(acc.intersect(o, d2, tnear=tn2, tfar=tf2).prim)
    assert not occ2[hits].any() and (prim2[hits] < 0).all()


@pytest.mark.skipif(not embree_available(), reason="embreex not installed")
def test_embree_float32_shadow_rays_equal_the_float64_path():
    """Float32 rays from tnear = 0 go to embree without float64 copies (`_float32_rays`); the
    answers equal the general path's (float64 rays, tnear an array of zeros), NaN and negative
    tfar included."""
    v, f = MESHES["soup"]
    o, d = rays_at(v, 4000, seed=5, spread=2.0)
    o, d = o.astype(np.float32), d.astype(np.float32)
    acc = _accel(v, f, "embree")
    tfar = np.random.default_rng(3).uniform(0.0, 4.0, len(o)).astype(np.float32)
    tfar[::37], tfar[::41] = np.nan, -1.0
    fast = np.asarray(acc.occluded(o, d, tnear=0.0, tfar=tfar))
    general = np.asarray(acc.occluded(o.astype(np.float64), d.astype(np.float64), tnear=np.zeros(len(o)), tfar=tfar))
    assert fast.any() and not fast.all()
    np.testing.assert_array_equal(fast, general)


def test_embree_triangle_tables_block_by_block(monkeypatch):
    """The Embree backend's per-triangle tables, made block by block (`_triangle_tables`): valid as
    `bvh.valid_triangles` (finite, non-zero area), each vertex's altitude over the opposite edge
    against an independent float64 formula, and the same values whatever the block size."""
    from jaxpbr.rendering import visibility

    rng = np.random.default_rng(5)
    tri = rng.normal(size=(53, 3, 3)).astype(np.float32)
    tri[3, 2] = tri[3, 0]  # a repeated vertex: zero area and a zero-length edge
    tri[7] = [[0, 0, 0], [1, 1, 1], [2, 2, 2]]  # collinear
    tri[11, 1, 2] = np.nan
    tri[19, 0, 0] = np.inf
    tri[23] *= np.float32(1e-20)  # tiny, still of non-zero area in float64
    valid, alt = visibility._triangle_tables(tri)
    t = tri.astype(np.float64)
    with np.errstate(invalid="ignore"):
        cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        in_bvh = bvh_mod.valid_triangles(tri)
    expect = np.isfinite(t).all(axis=(1, 2)) & (np.nan_to_num(np.abs(cross)).max(axis=1) > 0)
    assert np.array_equal(valid, expect) and np.array_equal(valid, in_bvh)
    assert not valid[[3, 7, 11, 19]].any() and valid[23] and valid.sum() == 49
    area2 = np.linalg.norm(cross[valid], axis=1)
    for i in range(3):
        edge = np.linalg.norm(t[valid, (i + 2) % 3] - t[valid, (i + 1) % 3], axis=1)
        np.testing.assert_allclose(alt[valid, i], area2 / edge, rtol=1e-13, atol=0)
    assert alt[3, 1] == 0.0  # across the zero-length edge (vertices 0 and 2): 0, not 0 / 0
    for block in (1, 7, 52, 53, 54):
        monkeypatch.setattr(visibility, "TABLE_BLOCK", block)
        v2, a2 = visibility._triangle_tables(tri)
        assert np.array_equal(v2, valid) and np.array_equal(a2, alt, equal_nan=True), block


@pytest.mark.skipif(not embree_available(), reason="embreex not installed")
def test_embree_intersect_without_barycentrics_gives_the_same_hits():
    v, f = MESHES["soup"]
    o, d = rays_at(v, 70000, seed=6, spread=2.0)  # above the size split over worker threads
    acc = _accel(v, f, "embree")
    full = acc.intersect(o, d)
    lean = acc.intersect(o, d, barycentrics=False)
    assert lean.b1 is None and lean.b2 is None
    np.testing.assert_array_equal(np.asarray(lean.prim), np.asarray(full.prim))
    np.testing.assert_array_equal(np.asarray(lean.t), np.asarray(full.t))


@pytest.mark.skipif(not embree_available(), reason="embreex not installed")
@pytest.mark.parametrize("n", [5000, 70000])  # one chunk; chunks on the worker threads
def test_embree_float32_primary_rays_equal_the_general_path(n, monkeypatch):
    """Float32 rays from tnear = 0 with tfar = inf and no previous hit (primary rays) are refined
    on the subset embree's first round hits, without float64 copies of the whole set
    (`closest_from_origin`); the hits equal the general path's (float64 rays, per-ray tnear,
    tfar and after_prim arrays), barycentrics included, on a grid of unit squares whose rays pass
    through shared edges and vertices (ties) and through the gaps beside it (misses)."""
    k = 24
    v, f = unit_grid(k)
    rng = np.random.default_rng(11)
    xy = rng.integers(-2, k + 2, (n, 2)) + rng.choice([0.0, 0.5, 1.0, 0.25], (n, 2))  # vertices, edges, centres
    o = np.concatenate([xy, rng.uniform(1.0, 3.0, (n, 1))], 1).astype(np.float32)
    tilt = rng.normal(0.0, 0.02, (n, 2)) * rng.choice([0.0, 1.0], (n, 1))  # half straight down: exact ties
    d = np.concatenate([tilt, -np.ones((n, 1))], 1).astype(np.float32)
    acc = _accel(v, f, "embree")
    general = acc.intersect(o.astype(np.float64), d.astype(np.float64), tnear=np.zeros(n), tfar=np.full(n, np.inf),
                            after_prim=np.full(n, -1))
    from jaxpbr.rendering import visibility

    def no_copies(*a, **k):
        raise AssertionError("float64 copies of the primary rays")

    monkeypatch.setattr(visibility, "_host_rays", no_copies)
    fast = acc.intersect(o, d)
    hit = np.asarray(fast.prim) >= 0
    assert 0.5 < hit.mean() < 1.0
    for a, b in zip(fast, general):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    lean = acc.intersect(o, d, barycentrics=False)
    np.testing.assert_array_equal(np.asarray(lean.prim), np.asarray(general.prim))
    np.testing.assert_array_equal(np.asarray(lean.t), np.asarray(general.t))


# --------------------------------------------------------------------------------------------------
# continuation


def layers():
    """Five parallel unit quads at z = 0..4 (triangles 0-9), a copy of the z = 2 quad with its own
    vertices (10, 11) and a larger quad in the same plane (12, 13)."""
    parts = [unit_quad(z) for z in range(5)] + [unit_quad(2.0)]
    big = np.array([[-0.5, -0.5, 2], [1.5, -0.5, 2], [1.5, 1.5, 2], [-0.5, 1.5, 2]], float)
    parts.append((big, np.array([[0, 1, 2], [0, 2, 3]])))
    vs, fs, off = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + off)
        off += len(v)
    return np.concatenate(vs), np.concatenate(fs)


@backends
def test_first_k_hits_through_stacked_and_coplanar_layers(backend):
    """Documented behaviour: every triangle on the ray once, in (t, id) order; coplanar overlapping
    triangles (equal t) are all reported, the smaller id first."""
    v, f = layers()
    acc = _accel(v, f, backend)
    rng = np.random.default_rng(5)
    n = 200
    xy = rng.uniform(0.05, 0.95, (n, 2))
    xy = xy[np.abs(xy[:, 0] - xy[:, 1]) > 0.05]  # off the quads' diagonals
    n = len(xy)
    slope = np.where(np.arange(n)[:, None] % 2 == 0, 0.0, rng.uniform(-0.01, 0.01, (n, 2)))
    o = np.c_[xy + 6.0 * slope, np.full(n, 6.0)]
    d = np.c_[-slope, -np.ones(n)]
    h = acc.first_k_hits(o, d, 8)
    prim, t = np.asarray(h.prim), np.asarray(h.t)
    t_all = brute_all(v, f, o, d)[0]
    for i in range(n):
        got = prim[i][prim[i] >= 0]
        assert len(got) == len(set(got.tolist())), "a layer reported twice"
        assert set(got.tolist()) == set(np.nonzero(np.isfinite(t_all[i]))[0].tolist()), "a layer lost"
        assert len(got) == 7  # z = 4, 3, three at z = 2, 1, 0
        key = list(zip(t[i][: len(got)].tolist(), got.tolist()))
        assert key == sorted(key)
    # the coplanar ones: exactly equal t for the vertical rays, then by id
    vert = np.arange(n) % 2 == 0
    assert (t[vert, 2] == t[vert, 3]).all() and (t[vert, 3] == t[vert, 4]).all()
    assert (np.diff(prim[vert, 2:5], axis=1) > 0).all()
    # the same by hand: intersect(tnear = previous t, after_prim = previous id)
    tn, after = np.zeros(n), np.full(n, -1)
    for i in range(8):
        hh = acc.intersect(o, d, tnear=tn, after_prim=after)
        assert np.array_equal(np.asarray(hh.prim), prim[:, i])
        tn = np.where(np.asarray(hh.prim) >= 0, np.asarray(hh.t), np.inf)
        after = np.asarray(hh.prim)
    # the epsilon pattern (tnear just past the previous t) loses the coplanar layers
    tn, seen = np.zeros(n), []
    for i in range(8):
        hh = acc.intersect(o, d, tnear=tn)
        seen.append(np.asarray(hh.prim))
        tn = np.asarray(hh.t, np.float64) * (1 + 1e-6) + 1e-6
    assert ((np.stack(seen, 1) >= 0).sum(1) == 5).all()


@backends
def test_continuation_on_a_closed_mesh_gives_entry_and_exit(backend):
    v, f = MESHES["icosphere"]
    o, d = rays_at(v, 300, seed=4)
    acc = _accel(v, f, backend)
    h = acc.first_k_hits(o, d, 8)
    prim = np.asarray(h.prim)
    t_all = brute_all(v, f, o, d)[0]
    n_hits = np.isfinite(t_all).sum(1)
    got = (prim >= 0).sum(1)
    # a ray through a shared edge may report both triangles there: allow it, but never lose one
    assert (got >= n_hits).all()
    assert (prim[:, 2][n_hits == 2] == -1).mean() > 0.95


# --------------------------------------------------------------------------------------------------
# shadow rays


@backends
@pytest.mark.parametrize("center", [(0.0, 0.0, 0.0), (100.0, -50.0, 20.0)])
def test_offset_shadow_rays_never_self_shadow_on_the_lit_side(center, backend):
    v, f = icosphere(3, radius=1.0, center=center)
    v = v.astype(np.float32)
    acc = _accel(v, f, backend)
    rng = np.random.default_rng(9)
    n = 1000
    tri = v[f]
    ti = rng.integers(0, len(f), n)
    b = rng.dirichlet([1, 1, 1], n).astype(np.float32)
    p = (b[:, :1] * tri[ti, 0] + b[:, 1:2] * tri[ti, 1] + b[:, 2:] * tri[ti, 2]).astype(np.float32)
    ng = np.cross(tri[ti, 1] - tri[ti, 0], tri[ti, 2] - tri[ti, 0]).astype(np.float64)
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    ng *= np.sign(np.einsum("nk,nk->n", ng, p - np.asarray(center)))[:, None]  # outward
    light = rng.normal(size=(n, 3))
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    c = np.einsum("nk,nk->n", light, ng)
    light -= 2 * np.minimum(c, 0)[:, None] * ng  # the lit side, down to grazing
    grazing = np.argsort(np.abs(c))[: n // 10]
    light[grazing] = light[grazing] - (np.einsum("nk,nk->n", light[grazing], ng[grazing]) - 1e-3)[:, None] * ng[grazing]
    origin = offset_ray_origin(p, ng.astype(np.float32))
    assert origin.dtype == np.float32 and np.abs(origin - p).max() > 0
    assert not np.asarray(acc.occluded(origin, light)).any()
    # without the offset the test has teeth: about half the rays start below their surface
    assert np.asarray(acc.occluded(p, light)).mean() > 0.2


def test_offset_ray_origin_numpy_and_jax_agree():
    rng = np.random.default_rng(0)
    p = (rng.normal(size=(1000, 3)) * 10.0 ** rng.uniform(-3, 3, (1000, 1))).astype(np.float32)
    n = rng.normal(size=(1000, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    a = offset_ray_origin(p, n)
    b = jax.jit(offset_ray_origin)(jnp.asarray(p), jnp.asarray(n))
    assert isinstance(a, np.ndarray) and isinstance(b, jax.Array)
    np.testing.assert_array_equal(a, np.asarray(b))
    # each coordinate moves along the normal's sign (or not at all where int(256 n) = 0)
    step = np.sign(a.astype(np.float64) - p)
    assert (step[step != 0] == np.sign(n)[step != 0]).all()


# --------------------------------------------------------------------------------------------------
# the JAX traversal: compilation, tracing, precision


def test_same_shapes_do_not_recompile():
    """The traversal is compiled per (ray count, BVH array shapes): meshes built with the same
    min_triangles share it, and TriangleAccel pads ray counts to power-of-two buckets."""
    v1, f1 = MESHES["icosphere"]
    v2, f2 = MESHES["soup"]
    a1, a2 = _accel(v1, f1, "jax"), _accel(v2, f2, "jax")
    assert jax.tree.map(np.shape, tuple(a1.bvh)) == jax.tree.map(np.shape, tuple(a2.bvh))
    o, d = rays_at(v1, 300, seed=1)
    a1.intersect(o, d)
    size = intersect_jax._cache_size()
    a2.intersect(o[:200], d[:200])
    a1.intersect(o[:17], d[:17])
    assert intersect_jax._cache_size() == size


def test_intersect_bvh_traces_inside_jit_and_vmap():
    """The functions under TriangleAccel are tracer-friendly: inside a caller's jit (float32 rays
    give float32 results) and under vmap."""
    v, f = MESHES["cube"]
    bvh = build_bvh(v, f).to_device()
    o, d = rays_at(v, 64, seed=2)
    o, d = o.astype(np.float32), d.astype(np.float32)
    t_all = brute_all(v, f, o, d)[0]

    @jax.jit
    def render(bvh, o, d):
        h = bvh_mod.intersect_bvh(bvh, o, d, lanes=16)
        batched = jax.vmap(lambda oo, dd: bvh_mod.intersect_bvh(bvh, oo, dd, lanes=16).prim)
        return h, jnp.where(h.prim >= 0, h.t, 0.0), batched(o.reshape(4, 16, 3), d.reshape(4, 16, 3))

    h, depth, batched = render(bvh, o, d)
    assert h.b1.dtype == jnp.float32 and h.t.dtype == jnp.float32 and h.prim.dtype == jnp.int32
    np.testing.assert_allclose(np.asarray(depth), np.where(np.isfinite(t_all.min(1)), t_all.min(1), 0), rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(batched).ravel(), np.asarray(h.prim))


def test_watertight_test_is_antisymmetric_under_xla():
    """The edge functions negate exactly when an edge is walked backwards, in NumPy and compiled
    (XLA contracts a*b - c*d into an FMA; the formulation must survive it): hits and distances with
    XLA:CPU's default fusion emitters, which the library's ray programs use (compile options given
    here: the suite runs on the loop emitters, tests/conftest.py). The loop emitters contract other
    products, so the distances of a triangle and its reverse differ by rounding there (up to 19
    float32 ulps measured), but the hit decisions, which make the test watertight, still agree."""
    rng = np.random.default_rng(0)
    n = 20000
    o = rng.normal(size=(n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    a, b, c = (rng.normal(size=(n, 3)).astype(np.float32) for _ in range(3))

    def both(o, d, a, b, c, xp):
        s = bvh_mod.ray_setup(d, xp)
        h1, t1, *_ = bvh_mod.watertight_test(o, s, a, b, c, xp)
        h2, t2, *_ = bvh_mod.watertight_test(o, s, b, a, c, xp)  # same triangle, reversed winding
        return h1, h2, t1, t2

    low = jax.jit(lambda *x: both(*x, jnp)).lower(o, d, a, b, c)
    fusion, loop = (low.compile(compiler_options={"xla_cpu_use_fusion_emitters": e})(o, d, a, b, c) for e in (True, False))
    for res in (both(o, d, a, b, c, np), fusion):
        h1, h2, t1, t2 = (np.asarray(x) for x in res)
        assert np.array_equal(h1, h2) and h1.sum() > 100
        np.testing.assert_array_equal(t1[h1], t2[h1])
    h1, h2, _, _ = (np.asarray(x) for x in loop)
    assert np.array_equal(h1, h2) and np.array_equal(h1, np.asarray(fusion[0]))


# --------------------------------------------------------------------------------------------------
# API


def test_auto_backend_and_errors():
    v, f = MESHES["cube"]
    acc = TriangleAccel.build(v, f)
    expect = "embree" if (embree_available() and jax.default_backend() == "cpu") else "jax"
    assert acc.backend == expect
    with pytest.raises(InputError):
        TriangleAccel.build(v, f, backend="optix")
    with pytest.raises(InputError):
        TriangleAccel.build(v[:, :2], f)
    with pytest.raises(InputError):
        TriangleAccel.build(v, f + 100)
    with pytest.raises(InputError):
        acc.intersect(np.zeros((3, 2)), np.ones((3, 2)))
    with pytest.raises(InputError):
        acc.intersect(np.zeros((3, 3)), np.ones((3, 3)), after_prim=len(f))


@backends
def test_batch_shapes_and_empty_queries(backend):
    v, f = MESHES["cube"]
    acc = _accel(v, f, backend)
    o = np.zeros((4, 5, 3))
    d = np.broadcast_to([1.0, 0.2, 0.1], (4, 5, 3))
    h = acc.intersect(o, d)
    assert np.shape(h.t) == (4, 5) and (np.asarray(h.prim) >= 0).all()
    assert np.shape(acc.occluded(o, d)) == (4, 5)
    assert np.shape(acc.first_k_hits(o, d, 8).prim) == (4, 5, 8)
    assert np.shape(acc.intersect(np.zeros((0, 3)), np.zeros((0, 3))).t) == (0,)


# --------------------------------------------------------------------------------------------------
# larger


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
def test_large_mesh_against_brute_force(backend):
    v, f = icosphere(5)  # 20480 triangles
    o, d = rays_at(v, 400, seed=21)
    acc = TriangleAccel.build(v, f, backend=backend)
    check_against_brute(acc.intersect(o, d), v, f, o, d)
    h = acc.first_k_hits(o, d, 2)
    t_all = brute_all(v, f, o, d)[0]
    srt = np.sort(t_all, 1)[:, :2]
    got = np.asarray(h.t)
    np.testing.assert_allclose(np.where(np.isfinite(srt), srt, 0), np.where(np.isfinite(got), got, 0), rtol=1e-5)


# --------------------------------------------------------------------------------------------------
# the compiled first round of the embree backend


def test_opaque_products_round_as_numpy():
    """`bvh.opaque_mul`: a compiled sum of products rounds operation by operation as NumPy's
    (XLA:CPU fuses a plain x * y + z into an FMA, rounded once: the plain program differs)."""
    rng = np.random.default_rng(2)
    x, y, z, w = (rng.normal(size=4096).astype(np.float32) for _ in range(4))
    expect = x * y - z * w
    zero = np.int32(0)
    plain = np.asarray(jax.jit(lambda x, y, z, w: x * y - z * w)(x, y, z, w))
    mul = jax.jit(lambda x, y, z, w, zero: bvh_mod.opaque_mul(zero)(x, y) - bvh_mod.opaque_mul(zero)(z, w))
    np.testing.assert_array_equal(np.asarray(mul(x, y, z, w, zero)), expect)
    if jax.default_backend() == "cpu":  # (the reason for it: not a requirement on other compilers)
        assert (plain != expect).any()


def test_table_rows_buckets():
    from jaxpbr.rendering.visibility import _table_rows

    assert _table_rows(1) == 4096 and _table_rows(4096) == 4096 and _table_rows(4097) == 4608 and _table_rows(8191) == 8192
    for n in (5000, 81920, 1310720, 3_000_001):
        r = _table_rows(n)
        assert n <= r <= 1.125 * n + 1
    assert len({_table_rows(n) for n in range((1 << 20) + 1, (1 << 21) + 1, 997)}) == 8  # eight sizes per octave


def _ties_mesh():
    """A unit-square grid (rays through shared edges and vertices), a coplanar copy of part of it
    (equal t, near pairs), a sheet crossing it at an angle, and a far, small icosphere (large |o|
    against small triangles): every reason the first round sends a ray on."""
    v, f = unit_grid(16)
    copy = f[: len(f) // 4]
    sheet_v = np.array([[2.0, 2.0, -1.0], [9.0, 2.0, 1.0], [2.0, 9.0, -1.0]])
    sv, sf = icosphere(3, radius=0.05, center=(40.0, 40.0, -30.0))
    verts = np.concatenate([v, sheet_v, sv])
    faces = np.concatenate([f, copy[:, ::-1], [[len(v), len(v) + 1, len(v) + 2]], sf + len(v) + 3])
    return verts, faces


@pytest.mark.skipif(not embree_available(), reason="embreex not installed")
@pytest.mark.parametrize("exact_ties", [True, False])
def test_embree_compiled_first_round_equals_the_numpy_rounds(exact_ties, monkeypatch):
    """Primary rays through the compiled first round (`_first_round`: embree's proposals tested in
    one compiled program, the rays it cannot settle sent through the NumPy rounds) give the hits of
    the NumPy rounds alone, t, prim and float64 barycentrics bit for bit: on exact ties (rays
    straight down through grid edges and vertices), coplanar copies, a crossing sheet, grazing
    rays and distant rays onto small triangles; blocks padded (the last block partly empty)."""
    from jaxpbr.rendering import visibility

    v, f = _ties_mesh()
    rng = np.random.default_rng(12)
    n = 9000
    xy = rng.integers(-1, 18, (n, 2)) + rng.choice([0.0, 0.5, 1.0, 0.25, 1 / 3], (n, 2))
    o = np.concatenate([xy, rng.uniform(0.5, 3.0, (n, 1))], 1)
    d = np.concatenate([rng.normal(0.0, 0.02, (n, 2)) * rng.choice([0.0, 1.0], (n, 1)), -np.ones((n, 1))], 1)
    graze = rng.random(n) < 0.1  # nearly in the grid's plane
    d[graze] = np.concatenate([rng.normal(size=(graze.sum(), 2)), -rng.uniform(1e-4, 1e-2, (graze.sum(), 1))], 1)
    far = rng.random(n) < 0.15  # from far away onto the small icosphere
    o[far] = [40.0, 40.0, 200.0]
    d[far] = np.array([40.0, 40.0, -30.0]) + rng.normal(scale=0.03, size=(far.sum(), 3)) - o[far]
    o, d = o.astype(np.float32), d.astype(np.float32)
    acc = TriangleAccel.build(v, f, backend="embree", exact_ties=exact_ties)
    monkeypatch.setattr(visibility, "KERNEL_MIN_RAYS", 1 << 40)
    reference = acc.intersect(o, d)
    monkeypatch.setattr(visibility, "KERNEL_MIN_RAYS", 1)
    monkeypatch.setattr(visibility, "REFINE_BLOCK", 4096)
    monkeypatch.setattr(visibility, "COMPILED_FROM_QUERY", 1)
    monkeypatch.setattr(visibility, "COMPILE_IN_BACKGROUND", False)
    monkeypatch.setattr(visibility, "_COMPILED", {})
    calls = []
    closest = acc._impl.closest
    monkeypatch.setattr(acc._impl, "closest", lambda *a, **k: calls.append(len(a[0])) or closest(*a, **k))
    compiled = acc.intersect(o, d)
    hit = np.asarray(reference.prim) >= 0
    assert 0.4 < hit.mean() < 0.95 and hit[far].mean() > 0.5
    assert calls and 0 < sum(calls) < hit.sum()  # some rays, not all, went on to the NumPy rounds
    for a, b in zip(compiled, reference):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    lean = acc.intersect(o, d, barycentrics=False)
    assert lean.b1 is None
    np.testing.assert_array_equal(lean.prim, reference.prim)
    np.testing.assert_array_equal(lean.t, reference.t)


@pytest.mark.skipif(not embree_available(), reason="embreex not installed")
def test_embree_compiled_first_round_from_the_second_query_compiled_in_the_background(monkeypatch):
    """The first query of an acceleration structure takes the NumPy rounds and compiles nothing;
    the second starts the compile on a background thread and, until it is ready, takes the NumPy
    rounds too; once it is, queries take the compiled round. Every answer is the same."""
    import threading

    from jaxpbr.rendering import visibility

    monkeypatch.setattr(visibility, "_COMPILED", {})
    monkeypatch.setattr(visibility, "REFINE_BLOCK", 1 << 14)
    v, f = icosphere(3)
    o, d = rays_at(v, 40000, seed=9, spread=1.5)
    o, d = o.astype(np.float32), d.astype(np.float32)
    acc = TriangleAccel.build(v, f, backend="embree")
    used = []
    compiled = acc._impl.compiled_from_origin
    monkeypatch.setattr(acc._impl, "compiled_from_origin", lambda *a, **k: used.append(1) or compiled(*a, **k))
    gate = threading.Event()
    ready = visibility._compiled_ready

    def held(key, compile_it):  # the background compile waits for the gate
        return ready(key, lambda: (gate.wait(60), compile_it()))

    monkeypatch.setattr(visibility, "_compiled_ready", held)
    first = acc.intersect(o, d)
    assert not used and not visibility._COMPILED  # first query: nothing compiled
    second = acc.intersect(o, d)
    assert not used and len(visibility._COMPILED) == 1  # compiling on the side
    gate.set()
    next(iter(visibility._COMPILED.values())).wait(120)
    third = acc.intersect(o, d)
    assert used
    for a, b, c in zip(first, second, third):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(a), np.asarray(c))


def _segments_cross_triangles(p, q, tri):
    """Float64 Moller-Trumbore: does segment p -> q (n, 3) cross triangle tri (n, 3, 3)?"""
    d = q - p
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(d, e2)
    det = (e1 * h).sum(1)
    with np.errstate(all="ignore"):
        s = p - tri[:, 0]
        u = (s * h).sum(1) / det
        qq = np.cross(s, e1)
        v = (d * qq).sum(1) / det
        t = (e2 * qq).sum(1) / det
        return (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def test_near_pairs_find_every_crossing_pair():
    """The build-time search for non-adjacent triangles within the tie tolerance (`_near_pairs`):
    none on a closed sphere; with a second sphere pushed through it, every pair of crossing
    triangles (an edge of one crosses the other: float64 brute force over all pairs) is found, and
    nothing else than pairs of the two spheres whose boxes overlap."""
    from jaxpbr.rendering import visibility

    def pairs(v, f):
        vv, ff = bvh_mod._as_mesh(v, f)
        tri = vv[ff]
        welded = visibility._weld(vv)[ff]
        scale = float(np.abs(vv).max())
        return visibility._near_pairs(tri.astype(np.float64), welded, visibility.TIE_TOL * 4.0 * scale)

    v, f = icosphere(3)
    assert len(pairs(v, f)) == 0
    w, g = icosphere(2, radius=0.6, center=(0.7, 0.1, 0.05))
    vv, ff = np.concatenate([v, w]), np.concatenate([f, g + len(v)])
    got = {(int(a), int(b)) for a, b in pairs(vv, ff)}
    tri = np.asarray(vv, np.float32).astype(np.float64)[ff]
    ia, ib = np.meshgrid(np.arange(len(f)), np.arange(len(f), len(ff)), indexing="ij")
    ia, ib = ia.ravel(), ib.ravel()
    lo, hi = tri.min(1), tri.max(1)
    boxes = ((lo[ia] <= hi[ib]) & (lo[ib] <= hi[ia])).all(1)
    ia, ib = ia[boxes], ib[boxes]
    crossing = np.zeros(len(ia), bool)
    for k in range(3):
        crossing |= _segments_cross_triangles(tri[ia, k], tri[ia, (k + 1) % 3], tri[ib])
        crossing |= _segments_cross_triangles(tri[ib, k], tri[ib, (k + 1) % 3], tri[ia])
    expect = {(int(a), int(b)) for a, b in zip(ia[crossing], ib[crossing])}
    assert len(expect) > 20
    assert expect <= got, sorted(expect - got)[:5]
    assert got <= {(int(a), int(b)) for a, b in zip(ia, ib)}  # (two spheres' pairs, boxes overlapping)


def _tie_pairs(v, f, **kw):
    """`_near_pairs` of a mesh as `TriangleAccel.build` calls it (welded vertices, its tolerance)."""
    from jaxpbr.rendering import visibility

    vv, ff = bvh_mod._as_mesh(v, f)
    scale = float(np.abs(vv).max())
    return visibility._near_pairs(vv[ff].astype(np.float64), visibility._weld(vv)[ff], visibility.TIE_TOL * 4.0 * scale, **kw)


def test_near_pairs_are_the_same_in_blocks_of_any_size_and_compiled(monkeypatch):
    """`_near_pairs` hands its candidates to the pair tests in blocks of exactly `chunk` pairs
    (carried over between grid cells and levels), in NumPy below `_KERNEL_MIN_PAIRS` and through the
    compiled program above it, and the in-plane test likewise (`_not_separated`: NumPy, or compiled
    blocks of `_SEPARATION_BLOCK` with the last one padded). Every split gives the same pairs, on a
    mesh with all three kinds: two interpenetrating spheres, a shifted coplanar copy of a grid (in-plane
    overlaps of vertex-sharing neighbours and of the copies) and a duplicated triangle."""
    from jaxpbr.rendering import visibility

    v1, f1 = icosphere(3)
    v2, f2 = icosphere(2, radius=0.6, center=(0.7, 0.1, 0.05))
    g, gf = unit_grid(10)
    g = g * 0.2 + [-1.0, -1.0, 1.5]
    parts = [(v1, f1), (v2, f2), (g, gf), (g + [0.05, 0.025, 0.0], gf), (g, gf[:1])]
    v, f, off = [], [], 0
    for pv, pf in parts:
        v.append(pv)
        f.append(pf + off)
        off += len(pv)
    v, f = np.concatenate(v), np.concatenate(f)
    want = _tie_pairs(v, f)
    assert len(want) > 300  # (crossing spheres, overlapping copies, the duplicate)
    for chunk in (97, 5000):
        np.testing.assert_array_equal(_tie_pairs(v, f, chunk=chunk), want)
    monkeypatch.setattr(visibility, "_KERNEL_MIN_PAIRS", 256)
    monkeypatch.setattr(visibility, "_SEPARATION_MIN_PAIRS", 16)
    monkeypatch.setattr(visibility, "_SEPARATION_BLOCK", 128)
    np.testing.assert_array_equal(_tie_pairs(v, f, chunk=3000), want)


@pytest.mark.parametrize("far", [False, True], ids=["near", "far-apart"])
def test_cell_entries_are_sorted_by_cell_with_own_triangles_first(far):
    """`_cell_entries`: one entry per cell a box spans (up to 2 per axis), grouped by cell in the
    cells' x-major order, the level's own triangles first within a cell, `above` naming the axes on
    which the entry's cell is past the box's lowest cell. Also with one box 2^22 cells away on every
    axis, where numbering the level's whole bounding grid overflows int64 (2^66 cells): the cells
    are then numbered by rank (numbered densely, entries of different cells shared keys)."""
    from jaxpbr.rendering import visibility

    rng = np.random.default_rng(4)
    n = 300
    ilo = rng.integers(0, 64, (n, 3))
    ihi = ilo + rng.integers(0, 2, (n, 3))
    if far:  # (2^66 cells: a dense numbering wraps the box's cells in among the others)
        ilo[0] = 1 << 22
        ihi[0] = ilo[0] + 1
    own = rng.random(n) < 0.5
    key, tri_of, is_own, above = visibility._cell_entries(ilo, ihi, own)
    assert len(key) == int(np.prod(ihi - ilo + 1, axis=1).sum())
    cell = ilo[tri_of] + np.stack([above & 1, (above >> 1) & 1, (above >> 2) & 1], 1)
    assert ((cell >= ilo[tri_of]) & (cell <= ihi[tri_of])).all()
    assert len({(tuple(c), int(t)) for c, t in zip(cell.tolist(), tri_of)}) == len(key)  # each (cell, triangle) once
    assert (np.diff(key) >= 0).all()
    same = np.diff(key) == 0
    assert np.array_equal(same, (np.diff(cell, axis=0) == 0).all(1))  # one key per cell, one cell per key
    order = np.lexsort(cell.T[::-1])
    assert np.array_equal(key[order], key)  # the keys follow the cells' x-major order
    assert not (same & ~is_own[:-1] & is_own[1:]).any()  # (never a foreign entry before an own one)
    assert np.array_equal(is_own, own[tri_of])
