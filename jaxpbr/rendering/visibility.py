"""Ray/triangle-mesh visibility: closest hits, occlusion, ray continuation, shadow-ray offsets.

`TriangleAccel.build(vertices, triangles, backend=...)` builds an acceleration structure once on the
host; `intersect` gives per ray the triangle id, barycentrics and distance of the first hit,
`occluded` answers shadow rays, `first_k_hits` lists the k first hits (for blended layers), and
`offset_ray_origin` moves a surface point off its surface for secondary rays.

Backends
--------
* ``"embree"`` (embreex, CPU): NumPy in, NumPy out. embree proposes the nearest triangle in float32;
  the reported hit is then decided on the host by the same float32 watertight test as the JAX
  backend (`bvh.watertight_test`), so both backends share one definition of a hit and of t. The
  refinement also resolves near-ties exactly (see "Hit order"): when the proposal's hit lies within
  `tol` of its edges, when its triangle has non-adjacent triangles within `tol` (coplanar copies,
  interpenetrating parts; found at build time by a grid broad phase), or when the watertight test
  rejects the proposal, the neighbouring triangles are tested as well. tol = 2^-19 (|o| + S) in
  world units (S: the mesh's largest coordinate; embree's t was measured within 2e-7 of that scale).
  embreex traces one ray at a time with the GIL released; rays are split over `os.cpu_count()`
  threads. embreex has no tnear, so tnear > 0 moves the origin to o + tnear d (float32).
* ``"jax"``: the NumPy-built BVH of `jaxpbr.rendering.bvh`, traversed in JAX (jit-compiled, any JAX
  device): jnp in, jnp out. `intersect_bvh` & co. are the tracer-friendly functions underneath.
* ``"auto"``: embree when embreex imports and JAX's default backend is the CPU, else jax.

Both backends report the same triangle ids (rows of `triangles`); zero-area triangles are never hit.

Precision
---------
Rays are traced in float32 (origins and directions are rounded to float32). t is the float32 value
of the watertight test (relative error a few 1e-7 for origins not much farther than the mesh's
size), the canonical key of the hit order. Barycentrics (b1, b2 of vertices 1 and 2, clamped into
the triangle) are recomputed for the winning triangle by Moller-Trumbore from the caller's rays:
in float64 on the embree path; on the JAX path in the dtype of the origins (float64 when they are
float64 and jax_enable_x64 is on, else float32, where their error is about
1e-7 |o - v0| / (edge length * |cos incidence|), i.e. 1e-5 and more for distant, grazing rays).

Hit order and ray continuation (alpha MASK, BLEND)
--------------------------------------------------
The hits along a ray are ordered by (t, triangle id). `intersect(o, d, tnear=t_prev,
after_prim=prim_prev)` returns the first hit after the previous one in that order, and never the
previous triangle again. Chained, it visits every triangle on the ray exactly once, nearest first:
two coplanar overlapping triangles (equal t) are both reported, the smaller id first; a ray passing
exactly through a shared edge reports every triangle whose watertight test it passes there (one or
both; renderers blending layers may want to merge consecutive hits with equal t on adjacent
triangles). The origin and direction must stay bit-identical between the calls (do not move the
origin to the previous hit). `first_k_hits` is this loop. With after_prim = -1 (the default) the
result is the plain closest hit in [tnear, tfar]. An alpha-MASK loop:

    hits = acc.intersect(o, d)
    for _ in range(max_layers):
        cut = alpha_of(hits) < cutoff                # the caller's texture lookup; misses: False
        if not cut.any():
            break
        nxt = acc.intersect(o, d, tnear=hits.t, after_prim=hits.prim)
        hits = Hits(*(np.where(cut, b, a) for a, b in zip(hits, nxt)))

(The usual `tnear = t * (1 + eps)` instead skips every layer closer than the epsilon, coplanar
copies included, and can hit the same triangle again; the tests show both.)

Shadow rays
-----------
`occluded(o, d, tnear, tfar)` is True when some triangle is hit with tnear <= t <= tfar. For shadow
rays leaving a surface, start from `offset_ray_origin(p, n_geom)` (Waechter & Binder, Ray Tracing
Gems ch. 6) with the geometric normal flipped to the side the ray leaves on, tnear = 0, and tfar a
little short of the light (e.g. (1 - 1e-4) * distance).
"""

from __future__ import annotations

import atexit
import collections
import itertools
import operator
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from jaxpbr.errors import InputError

from .._numerics import cross_rows
from .._program_cache import cached_jit
from . import bvh as _bvh
from .bvh import (
    BVH,
    Hits,
    build_bvh,
    first_k_hits_bvh,
    intersect_bvh,
    occluded_bvh,
    pad_rays,
)

__all__ = [
    "BVH",
    "Hits",
    "GroupedAccel",
    "TriangleAccel",
    "build_bvh",
    "embree_available",
    "first_k_hits_bvh",
    "first_k_hits_jax",
    "intersect_bvh",
    "intersect_jax",
    "occluded_bvh",
    "occluded_jax",
    "offset_ray_origin",
]

F32 = np.float32
#: Near-tie tolerance of the embree refinement, relative to |origin| + the mesh's largest coordinate.
TIE_TOL = 2.0**-19
_NONE = np.iinfo(np.int32).max

intersect_jax = jax.jit(intersect_bvh, static_argnames=("lanes",))
occluded_jax = jax.jit(occluded_bvh, static_argnames=("lanes",))
first_k_hits_jax = jax.jit(first_k_hits_bvh, static_argnames=("k", "lanes"))
intersect_jax.__doc__ = "jax.jit(intersect_bvh): " + (intersect_bvh.__doc__ or "")
occluded_jax.__doc__ = "jax.jit(occluded_bvh): " + (occluded_bvh.__doc__ or "")
first_k_hits_jax.__doc__ = "jax.jit(first_k_hits_bvh): " + (first_k_hits_bvh.__doc__ or "")


def embree_available() -> bool:
    """Whether embreex imports."""
    try:
        import embreex.mesh_construction
        import embreex.rtcore_scene  # noqa: F401
    except Exception:  # noqa: BLE001 (ImportError, or a broken binary wheel)
        return False
    return True


# --------------------------------------------------------------------------------------------------
# offset_ray_origin


def offset_ray_origin(p, n):
    """Move surface points p (..., 3) off their surface along the geometric normal n (..., 3), as
    Waechter & Binder, "A Fast and Robust Method for Avoiding Self-Intersection" (Ray Tracing Gems,
    ch. 6): each coordinate is nudged by int(256 n_i) float32 ulps (an offset that scales with the
    coordinate's magnitude, so it covers the rounding error of a computed hit point anywhere in the
    scene), and coordinates with |p_i| < 1/32 (where ulps get too small) by n_i / 65536 instead.
    n must point to the side the new ray leaves on (flip it for transmission) and be unit length.
    Float32 in and out; NumPy in -> NumPy out, jax in -> jax out (jit-friendly)."""
    if isinstance(p, jax.Array) or isinstance(n, jax.Array):
        xp, p, n = jnp, jnp.asarray(p, jnp.float32), jnp.asarray(n, jnp.float32)

        def as_int(x):
            return jax.lax.bitcast_convert_type(x, jnp.int32)

        def as_float(i):
            return jax.lax.bitcast_convert_type(i, jnp.float32)

    else:
        xp, p, n = np, np.asarray(p, F32), np.asarray(n, F32)

        def as_int(x):
            return np.ascontiguousarray(x).view(np.int32)

        def as_float(i):
            return np.ascontiguousarray(i).view(F32)

    origin, float_scale, int_scale = 1.0 / 32.0, 1.0 / 65536.0, 256.0
    of_i = (n * F32(int_scale)).astype(np.int32)  # truncates towards zero, like the C cast
    p_i = as_float(as_int(p) + xp.where(p < 0, -of_i, of_i))
    return xp.where(xp.abs(p) < F32(origin), p + F32(float_scale) * n, p_i).astype(F32)


# --------------------------------------------------------------------------------------------------
# the embree backend


def _weld(v: np.ndarray) -> np.ndarray:
    """Vertex ids merged by float32 position (so that seams split by index still count as
    adjacent): (V,) int64. Positions are hashed to 64 bits; a collision merges two positions,
    which only adds candidates to the tie tests."""
    bits = np.ascontiguousarray(v.astype(F32)).view(np.uint32).reshape(-1, 3).astype(np.uint64)
    key = (bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)) ^ (bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)) ^ (bits[:, 2] << np.uint64(21))
    _, inv = np.unique(key, return_inverse=True)
    return inv.reshape(-1)


def _csr(keys: np.ndarray, values: np.ndarray, n: int):
    """(offsets (n+1,), values sorted by key)."""
    order = _stable_argsort(keys, n)
    offs = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(keys, minlength=n), out=offs[1:])
    return offs, values[order]


def _row_norms(x: np.ndarray) -> np.ndarray:
    """Euclidean norms of the rows of (N, 3) float64 x: what np.linalg.norm(x, axis=1) computes
    (the same values), without its checks and copies."""
    return np.sqrt((x * x).sum(1))


def _stable_argsort(keys: np.ndarray, n: int) -> np.ndarray:
    """np.argsort(keys, kind="stable") for integer keys in [0, n): below 2^32 as two stable passes
    over 16-bit digits, which NumPy sorts by radix (3 M keys: 0.09 against 0.33 s)."""
    if n > 1 << 32:
        return np.argsort(keys, kind="stable")
    low = np.argsort((keys & 0xFFFF).astype(np.uint16), kind="stable")
    if n <= 1 << 16:
        return low
    return low[np.argsort((keys[low] >> 16).astype(np.uint16), kind="stable")]


def _gather_lists(offs, vals, which):
    """Concatenated CSR lists of `which` (m,): (owner index into which (k,), values (k,))."""
    starts, counts = offs[which], offs[which + 1] - offs[which]
    owner = np.repeat(np.arange(which.size), counts)
    first = np.cumsum(counts) - counts
    pos = starts[owner] + (np.arange(owner.size) - first[owner])
    return owner, vals[pos]


def _near_pairs(tri: np.ndarray, welded: np.ndarray, tol: float, chunk: int = 1 << 21) -> np.ndarray:
    """Pairs (i, j), i < j, of triangles that come within about `tol` of each other away from the
    vertices they share: interpenetrating or touching parts, coplanar overlapping copies. A superset
    for pairs without a shared (welded) vertex: boxes grown by tol overlap, each triangle reaches
    the other's plane within tol, and in the plane no edge axis separates them by more than 2 tol.
    Pairs sharing a vertex must be coplanar within tol and overlap by more than tol in the plane
    (a duplicate, a fold); edge neighbours are handled by the near-edge test instead. (Triangles
    that share a vertex and cross elsewhere at an angle are not found.)

    Candidates come from a hierarchical uniform grid: a triangle lives on the level whose cells
    (h0 2^level) are at least its size, and is paired with the triangles of its own level or finer
    that share a cell with it; a pair sharing several cells is kept in the cell of the low corner
    of the intersection of their cell ranges only, before any of its data is read: there, on every
    axis, one of the two is in its own lowest cell (their `_cell_entries` bits are disjoint). The
    per-pair tests run as one jitted JAX kernel on chunks of candidates (in NumPy they were the
    bulk of the build)."""
    n = len(tri)
    if n < 2:
        return np.zeros((0, 2), np.int64)
    # Triangles in Morton order of their centroids: the two triangles of a candidate pair (near
    # in space) are then near in memory too, and gathering their rows hits the caches (in the
    # caller's order, neighbours can lie a quarter of the mesh apart: 100 against 20 ns a pair).
    perm = _morton_order(tri.mean(1))
    tri, welded = tri[perm], welded[perm]
    center = 0.5 * (tri.reshape(-1, 3).min(0) + tri.reshape(-1, 3).max(0))
    tri -= center  # (a copy: tri[perm]) float32 below: centred coordinates keep its rounding well under tol
    lo = tri.min(1) - tol
    hi = tri.max(1) + tol
    ext = (hi - lo).max(1)
    h0 = max(float(np.percentile(ext, 90)), 1e-30)  # most triangles on level 0
    level = np.maximum(0, np.ceil(np.log2(np.maximum(ext / h0, 1.0)))).astype(np.int64)
    nrm = cross_rows(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(nrm, axis=1)
    nrm /= area2[:, None]
    # per triangle, one float32 row (one gather per side of a pair): the box grown by tol (lo, hi),
    # the unit normal, the plane offset, the vertices and the welded vertex ids (their bits)
    data = {"rows": np.concatenate([lo.astype(F32), hi.astype(F32), nrm.astype(F32), np.einsum("nk,nk->n", nrm, tri[:, 0]).astype(F32)[:, None],
                                    tri.reshape(-1, 9).astype(F32), np.ascontiguousarray(welded, np.int32).view(F32)], 1)}
    dev, found = [], []

    def candidates():  # (i, j) per chunk of about `chunk` cell pairs, each pair once
        for lev in range(int(level.max()) + 1):
            members = np.nonzero(level <= lev)[0]
            own = level[members] == lev
            if not own.any():
                continue
            h = h0 * 2.0**lev
            ilo = np.floor(lo[members] / h).astype(np.int64)
            ihi = np.floor(hi[members] / h).astype(np.int64)
            key, tri_of, is_own, above = _cell_entries(ilo, ihi, own)
            run_end = np.r_[np.nonzero(np.diff(key))[0] + 1, key.size]
            end_of = np.repeat(run_end, np.diff(np.r_[0, run_end]))
            first = np.nonzero(is_own)[0]  # pair each own entry with the later entries of its cell
            cnt = end_of[first] - first - 1
            cum = np.cumsum(cnt)
            start = 0
            while start < first.size:
                stop = int(np.searchsorted(cum, (cum[start - 1] if start else 0) + chunk, "right"))
                stop = max(stop, start + 1)
                src, off = _expand(cnt[start:stop])
                a = first[start:stop][src]
                b = a + 1 + off
                low = (above[a] & above[b]) == 0  # this cell is the pair's low corner (once per pair)
                a, b = a[low], b[low]
                i, j = members[tri_of[a]], members[tri_of[b]]
                # (the in-plane test projects onto i's plane: i is the smaller of the caller's ids)
                swap = perm[i] > perm[j]
                yield np.where(swap, j, i), np.where(swap, i, j)
                start = stop

    def test(i, j):  # the pair tests, then the in-plane test of the pairs they keep
        m = i.size
        if m < _KERNEL_MIN_PAIRS:
            keep, shared = _pair_tests(i, j, data, F32(tol))
        else:
            if not dev:
                dev.append({k: jnp.asarray(v) for k, v in data.items()})
            size = 1 << (m - 1).bit_length()  # padded: few compiled sizes (pairs of row 0 with itself, cut off)
            ii = np.pad(i.astype(np.int32), (0, size - m))
            jj = np.pad(j.astype(np.int32), (0, size - m))
            keep, shared = (np.asarray(x)[:m] for x in _pair_kernel(ii, jj, dev[0], jnp.float32(tol)))
        if keep.any():
            i, j, shared = i[keep], j[keep], shared[keep]
            sep = _not_separated(tri[i], tri[j], np.where(shared, -tol, 2 * tol))
            if sep.any():
                found.append(np.sort(perm[np.stack([i[sep], j[sep]], 1)], 1))

    # The candidates go to the tests in blocks of exactly `chunk` pairs (the last one padded to a
    # power of two): the cell filter leaves chunks of any size, which padded one by one cost ~40 %.
    pending, count = [], 0
    for i, j in candidates():
        pending.append((i, j))
        count += i.size
        if count >= chunk:
            i, j = (np.concatenate(x) for x in zip(*pending))
            full = count - count % chunk
            for s0 in range(0, full, chunk):
                test(i[s0:s0 + chunk], j[s0:s0 + chunk])
            pending, count = [(i[full:], j[full:])], count - full
    if count:
        test(*(np.concatenate(x) for x in zip(*pending)))
    if not found:
        return np.zeros((0, 2), np.int64)
    return np.unique(np.concatenate(found), axis=0)


def _morton_order(points: np.ndarray) -> np.ndarray:
    """The permutation that sorts points (n, 3) by their Morton (Z-order) code on a 2^21 grid over
    their bounding box (ties by index)."""
    lo, hi = points.min(0), points.max(0)
    q = ((points - lo) / np.where(hi > lo, hi - lo, 1.0) * ((1 << 21) - 1)).astype(np.uint64)

    def spread(x):  # the 21 bits of x to every third bit
        x &= np.uint64(0x1FFFFF)
        for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F), (4, 0x10C30C30C30C30C3),
                            (2, 0x1249249249249249)):
            x = (x | (x << np.uint64(shift))) & np.uint64(mask)
        return x

    code = spread(q[:, 0]) | (spread(q[:, 1]) << np.uint64(1)) | (spread(q[:, 2]) << np.uint64(2))
    return np.argsort(code, kind="stable")


def _cell_entries(ilo, ihi, own):
    """The (cell, triangle) entries of one grid level, sorted by cell and, within a cell, this
    level's own triangles first: (key (N,) int64, tri_of (N,) int64, is_own (N,) bool, above (N,)
    uint8) for triangles whose box spans cells ilo..ihi (m, 3) (at most 2 per axis: a triangle's
    level is one whose cells are at least its size). key numbers the cells of the level's bounding
    grid (x-major; where that numbering would overflow, as for small triangles far apart, the
    cells' ranks in the same order); above has bit k set where the entry's cell is past the
    triangle's lowest cell on axis k. Where the key, the own flag, the bits and the triangle index
    fit in 63 bits, the entries are sorted as packed integers (no argsort and gathers of the
    columns), else by argsort."""
    cmin = ilo.min(0)
    base = ilo - cmin
    dims = ihi.max(0) - cmin + 1
    cells = float(dims[0]) * float(dims[1]) * float(dims[2])
    ranked = cells >= 2.0**62
    two = ihi > ilo
    tris, keys, bits = [], [], []
    for dx, dy, dz in itertools.product((0, 1), repeat=3):
        sel = np.ones(len(ilo), bool)
        for axis, dd in enumerate((dx, dy, dz)):
            if dd:
                sel &= two[:, axis]
        t = np.flatnonzero(sel)
        c = base[t] + (dx, dy, dz)
        keys.append(c if ranked else (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2])
        tris.append(t)
        bits.append(np.full(t.size, dx | dy << 1 | dz << 2, np.int64))
    tri_of, above = np.concatenate(tris), np.concatenate(bits)
    if ranked:
        _, key = np.unique(np.concatenate(keys), axis=0, return_inverse=True)
        key = key.reshape(-1).astype(np.int64)
        cells = float(key.max() + 1)
    else:
        key = np.concatenate(keys)
    not_own = ~own[tri_of]
    tbits = max(1, int(len(ilo) - 1).bit_length())
    if cells * 2.0 ** (tbits + 4) < 2.0**63:
        packed = np.sort((((((key << 1) | not_own) << 3) | above) << tbits) | tri_of)
        tri_of = packed & ((1 << tbits) - 1)
        above = ((packed >> tbits) & 7).astype(np.uint8)
        is_own = (packed >> (tbits + 3)) & 1 == 0
        key = packed >> (tbits + 4)
    else:
        order = np.lexsort((not_own, key))
        key, tri_of, is_own, above = key[order], tri_of[order], ~not_own[order], above[order].astype(np.uint8)
    return key, tri_of, is_own, above


def _pair_tests(i, j, data, tol, xp=np):
    """The per-pair tests of `_near_pairs` in float32, for NumPy or (jitted, `_pair_kernel`)
    jax.numpy: (keep, shared)."""
    tol = tol * 1.5  # a superset: generous against float32 rounding
    ri, rj = data["rows"][i], data["rows"][j]  # the rows of `_near_pairs`'s table

    def welded(r):
        bits = r[:, 19:22]
        return jax.lax.bitcast_convert_type(bits, jnp.int32) if xp is jnp else np.ascontiguousarray(bits).view(np.int32)

    lo_i, lo_j, hi_i, hi_j = ri[:, 0:3], rj[:, 0:3], ri[:, 3:6], rj[:, 3:6]
    box = xp.all((lo_i <= hi_j) & (lo_j <= hi_i), axis=1)
    wi, wj = welded(ri), welded(rj)
    shared = xp.any(wi[:, :, None] == wj[:, None, :], axis=(1, 2))
    ni, nj = ri[:, 6:9], rj[:, 6:9]

    def dist(n, d, verts):  # (m, 3) signed distances of the vertices from the plane (n, d)
        v = verts.reshape(-1, 3, 3)
        return (v[..., 0] * n[:, None, 0] + v[..., 1] * n[:, None, 1]) + v[..., 2] * n[:, None, 2] - d[:, None]

    dij = dist(ni, ri[:, 9], rj[:, 10:19])
    dji = dist(nj, rj[:, 9], ri[:, 10:19])
    coplanar = xp.all(xp.abs(dij) <= tol, axis=1) & xp.all(xp.abs(dji) <= tol, axis=1)

    def reaches(dd):
        return ~(xp.all(dd > tol, axis=1) | xp.all(dd < -tol, axis=1))

    # triangles sharing a vertex meet there anyway: they count only when they also overlap in a
    # common plane (a duplicate, a fold): coplanar within tol (the in-plane overlap is tested after)
    keep = box & xp.where(shared, coplanar, reaches(dij) & reaches(dji))
    return keep, shared


_pair_kernel = jax.jit(lambda i, j, data, tol: _pair_tests(i, j, data, tol, jnp))
#: Candidate chunks at least this large go through the jitted kernel (compiling it costs ~0.5 s).
_KERNEL_MIN_PAIRS = 1 << 18


def _expand(counts):
    """For counts (m,): (owner (sum,), index within the owner's run (sum,))."""
    counts = np.asarray(counts, np.int64)
    owner = np.repeat(np.arange(counts.size), counts)
    first = np.cumsum(counts) - counts
    return owner, np.arange(owner.size) - first[owner]


def _not_separated_in_plane(a, b, margin, xp=np, mul=operator.mul):
    """Separating-axis test in a's plane with the six edge normals of the two projected
    triangles (only decisive for coplanar pairs): True unless some axis separates them by more
    than `margin` (per pair; a negative margin asks for an overlap of at least -margin). NumPy, or
    jax.numpy with `bvh.opaque_mul` (`_separated_jit`: the same decisions, compiled)."""
    e1, e2 = a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]
    nrm = xp.stack([mul(e1[:, 1], e2[:, 2]) - mul(e1[:, 2], e2[:, 1]), mul(e1[:, 2], e2[:, 0]) - mul(e1[:, 0], e2[:, 2]),
                    mul(e1[:, 0], e2[:, 1]) - mul(e1[:, 1], e2[:, 0])], 1)
    drop = xp.argmax(xp.abs(nrm), 1)[:, None]  # keep axes (1, 2), (0, 2) or (0, 1)

    def project(t):  # (n, 3) arrays of the vertices' u and v
        return xp.where(drop == 0, t[..., 1], t[..., 0]), xp.where(drop == 2, t[..., 1], t[..., 2])

    (au, av), (bu, bv) = project(a), project(b)
    sep = xp.zeros(a.shape[0], bool)
    for pu, pv in ((au, av), (bu, bv)):
        for e in range(3):
            du, dv = pu[:, (e + 1) % 3] - pu[:, e], pv[:, (e + 1) % 3] - pv[:, e]
            ln = xp.sqrt(mul(du, du) + mul(dv, dv))
            ln = xp.where(ln > 0, ln, 1.0)
            xu, xv = (-dv / ln)[:, None], (du / ln)[:, None]  # the edge's normal in the plane
            qa = mul(xu, au) + mul(xv, av)
            qb = mul(xu, bu) + mul(xv, bv)
            # (projecting along the dominant axis of a's normal shrinks distances by at most
            # 1/sqrt 3 in a direction; the margins are generous enough for a superset)
            sep |= (qa.min(1) > qb.max(1) + margin) | (qb.min(1) > qa.max(1) + margin)
    return ~sep


_separated_jit = jax.jit(lambda a, b, margin, zero: _not_separated_in_plane(a, b, margin, jnp, _bvh.opaque_mul(zero)))
#: Pairs at least this many take `_separated_jit` (compiling it costs about 0.3 s).
_SEPARATION_MIN_PAIRS = 1 << 15
#: Pairs per call of `_separated_jit` (`_not_separated`).
_SEPARATION_BLOCK = 1 << 18


def _not_separated(a, b, margin):
    """`_not_separated_in_plane`, compiled for many pairs, in blocks of exactly _SEPARATION_BLOCK
    (the last one padded): one program whatever the count (a count padded to its power of two
    compiled one program per octave, about 0.37 s each in a fresh process)."""
    m = len(a)
    if m < _SEPARATION_MIN_PAIRS:
        return _not_separated_in_plane(a, b, margin)
    margin = np.broadcast_to(margin, (m,)).astype(np.float64)
    out = np.empty(m, bool)
    B = _SEPARATION_BLOCK
    with jax.default_device(jax.devices("cpu")[0]), jax.enable_x64(True):
        for s0 in range(0, m, B):
            s1 = min(m, s0 + B)
            pad = ((0, B - (s1 - s0)), (0, 0), (0, 0))
            res = _separated_jit(np.pad(a[s0:s1], pad), np.pad(b[s0:s1], pad), np.pad(margin[s0:s1], pad[0]), np.int64(0))
            out[s0:s1] = np.asarray(res)[: s1 - s0]
    return out


class _RayData:
    """Per-ray constants of the host-side exact test, computed on first need for a subset of
    the rays (most primary rays miss, and only hits are tested): float32 rays, the watertight
    test's setup, and the tie tolerance (world units, and in t)."""

    def __init__(self, o64, d64, scale):
        n = len(o64)
        self.o32, self.d32 = o64.astype(F32), d64.astype(F32)
        self.scale = scale
        self.have = np.zeros(n, bool)
        self.setup = [np.zeros(n, np.int32) for _ in range(3)] + [np.zeros(n, F32) for _ in range(3)] + [np.zeros(n, bool)]
        self.tol_abs = np.zeros(n)
        self.tol_t = np.zeros(n)

    def ensure(self, rays):
        need = rays[~self.have[rays]]
        if need.size == 0:
            return
        if need.size > 1 and (np.diff(need) <= 0).any():  # not strictly increasing: dedupe
            mark = np.zeros(len(self.have), bool)
            mark[need] = True
            need = np.nonzero(mark)[0]
        for dst, src in zip(self.setup, _bvh.ray_setup(self.d32[need], np)):
            dst[need] = src
        o, d = self.o32[need].astype(np.float64), self.d32[need].astype(np.float64)
        self.tol_abs[need] = TIE_TOL * (self.scale + np.sqrt(np.einsum("nk,nk->n", o, o)))
        dn = np.sqrt(np.einsum("nk,nk->n", d, d))
        self.tol_t[need] = self.tol_abs[need] / np.where(dn > 0, dn, 1.0)
        self.have[need] = True


#: Triangles per block of `_triangle_tables`: a block's float64 temporaries (2.4 MB) stay in the
#: processor's caches and reuse their memory, where whole-array temporaries (about 350 MB at 1 M
#: triangles) each fault fresh pages in.
TABLE_BLOCK = 1 << 15


def _triangle_tables(tri: np.ndarray):
    """(valid (T,) bool: `bvh.valid_triangles`, altitudes (T, 3) float64: each vertex's distance
    from the opposite edge, 0 across a zero-length edge) of float32 triangles (T, 3, 3), block by
    block: the values of the same expressions over the whole array, row by row."""
    n = len(tri)
    valid = np.empty(n, bool)
    alt = np.empty((n, 3), np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # (non-finite triangles are not valid)
        for a in range(0, n, TABLE_BLOCK):
            b = min(n, a + TABLE_BLOCK)
            t64 = tri[a:b].astype(np.float64)
            valid[a:b], nrm64 = _bvh._valid_and_normal(t64)
            area2 = _row_norms(nrm64)
            edge = np.stack([_row_norms(t64[:, (i + 2) % 3] - t64[:, (i + 1) % 3]) for i in range(3)], 1)
            alt[a:b] = np.where(edge > 0, area2[:, None] / edge, 0.0)
    return valid, alt


#: Rays per call of the compiled first round (`_first_round`): one size, so that its program is
#: compiled once per triangle-table size (`_table_rows`).
REFINE_BLOCK = 1 << 16
#: Queries of fewer primary rays are refined in NumPy only (`_EmbreeBackend.closest`).
KERNEL_MIN_RAYS = 1 << 14
#: The compiled first round's near-edge tolerance is this much wider than the NumPy test's, and it
#: calls a ray done only when the hit is within this share of the tie zone: margins far above the
#: float32 rounding of its tests (float64 in NumPy), so that every ray the NumPy round would refine
#: or continue is also sent on by the compiled one (the bound on the done test: the hit lies within
#: sqrt 3 (S + |o|) of the origin, so float32 rounding of t costs at most 0.06 of the zone).
NEAR_WIDEN = 1.0 + 2.0**-10
DONE_SHARE = 0.5


#: The compiled first round serves an acceleration structure from its this-many-th query of primary
#: rays on: a process that asks once (`jaxpbr render`'s single frame) does not pay its compile (about
#: 0.5 s on 2 cores) to save a fraction of that.
COMPILED_FROM_QUERY = 2
#: The program is compiled on a background thread; until it is ready, queries take the NumPy rounds
#: (the same hits, bit for bit). False: compiled by the query that first needs it.
COMPILE_IN_BACKGROUND = True
_COMPILED: dict = {}  # (table rows, bary) -> threading.Event, set once the program is compiled
_COMPILED_LOCK = threading.Lock()


def _compiled_ready(key, compile_it) -> bool:
    """Whether the first round's program for `key` is compiled in this process; the first ask
    starts `compile_it()` (on a daemon thread with COMPILE_IN_BACKGROUND)."""
    with _COMPILED_LOCK:
        event = _COMPILED.get(key)
        start = event is None
        if start:
            event = _COMPILED[key] = threading.Event()
    if start:
        def run():
            try:
                compile_it()
            finally:  # (a failure shows again where the program is called)
                event.set()

        if COMPILE_IN_BACKGROUND:
            thread = threading.Thread(target=run, name="jaxpbr-first-round-compile", daemon=True)
            thread.start()
            _COMPILING.append(thread)
        else:
            run()
    return event.is_set()


_COMPILING: list = []


@atexit.register
def _join_compiles() -> None:
    """A process that ends while a background compile runs waits for it (a daemon thread stopped
    inside XLA during the interpreter's finalization can crash it)."""
    for thread in _COMPILING:
        thread.join(timeout=120)


def _table_rows(n: int) -> int:
    """Rows of the compiled first round's triangle tables for n triangles: at least 4096, rounded up
    to an eighth of the largest power of two <= n (at most 12.5 % padding; eight compiled sizes
    per octave)."""
    n = max(int(n), 4096)
    step = 1 << (n.bit_length() - 4)
    return -(-n // step) * step


def _first_round(tables, scale, zero32, zero64, o, d, pid, te, *, bary: bool):
    """The first round of `_EmbreeBackend.closest` for primary rays (tnear = 0, tfar = inf, no
    previous hit), compiled: for rays (o, d) (B, 3) float32 and embree's proposals (pid (B,) int32
    primID, -1 for a miss; te (B,) float32), the watertight test of the proposal with NumPy's
    rounding (`bvh.opaque_mul`), and whether the ray needs the NumPy rounds (the test rejects the
    proposal, the hit is near an edge or on a triangle with near pairs, or it is not done). Returns
    (t, prim, hard) and with bary the float64 barycentrics (b1, b2) of the proposal: for the rays
    that are not hard, the values `closest` and `barycentrics` give (the same expressions)."""
    tri9, alt, flagged, ids = tables
    mul = _bvh.opaque_mul(zero32)
    hitm = pid >= 0
    prop = ids[jnp.maximum(pid, 0)]
    kx, ky, kz, sx, sy, sz, okd = _bvh.ray_setup(d, jnp)
    v = tri9[prop]

    def rel(j):
        q0, q1, q2 = v[:, 3 * j] - o[:, 0], v[:, 3 * j + 1] - o[:, 1], v[:, 3 * j + 2] - o[:, 2]
        return tuple(_bvh._pick(q0, q1, q2, k, jnp) for k in (kx, ky, kz))

    hit, t, u, w1, w2, det = _bvh._woop_core(rel(0), rel(1), rel(2), sx, sy, sz, jnp, mul)
    ok = hit & okd & (t >= 0)
    tol_abs = F32(TIE_TOL) * (scale + jnp.sqrt(jnp.sum(o * o, 1)))
    dn = jnp.sqrt(jnp.sum(d * d, 1))
    tol_t = tol_abs / jnp.where(dn > 0, dn, F32(1))
    a = alt[prop]
    wide = tol_abs * F32(NEAR_WIDEN)
    near = ((u / det) * a[:, 0] <= wide) | ((w1 / det) * a[:, 1] <= wide) | ((w2 / det) * a[:, 2] <= wide)
    easy = ok & ~flagged[prop] & ~near & (t <= te + F32(DONE_SHARE) * tol_t)
    out = (jnp.where(hitm, t, jnp.inf), jnp.where(hitm, prop, -1), hitm & ~easy)
    if bary:
        f64 = [x.astype(jnp.float64) for x in (o, d, v[:, 0:3], v[:, 3:6], v[:, 6:9])]
        out += tuple(jnp.where(hitm, x, 0.0) for x in _bvh.barycentrics(*f64, jnp, _bvh.opaque_mul(zero64)))
    return out


_first_round_jit = cached_jit(_first_round, static_argnames=("bary",))


class _EmbreeBackend:
    """embree scene + the host-side data of the exact refinement: the float32 triangles in the
    caller's order, altitudes (near-edge test), welded-vertex adjacency, near pairs."""

    def __init__(self, vertices, triangles, threads=None, exact_ties=True):
        from embreex.mesh_construction import TriangleMesh
        from embreex.rtcore_scene import EmbreeScene

        v, f = _bvh._as_mesh(vertices, triangles)
        self.n_tri = len(f)
        self.tri = v[f]  # (T, 3, 3) float32, caller's order
        # = bvh.valid_triangles; altitudes (distance of each vertex from the opposite edge) for the near-edge test
        valid, self.alt = _triangle_tables(self.tri)
        self.ids = np.nonzero(valid)[0].astype(np.int32)  # embree primID -> triangle id
        self.scene = EmbreeScene()
        if self.ids.size:
            TriangleMesh(self.scene, v, f[self.ids].astype(np.int32))
        # commit now (embreex commits on the first query; queries then run concurrently)
        self.scene.run(np.zeros((1, 3), F32), np.ones((1, 3), F32), dists=np.ones(1, F32))
        # The largest |coordinate| of a valid triangle's vertices (per vertex, then per corner).
        self.scale = float(np.abs(v).max(axis=1)[f[self.ids]].max()) if self.ids.size else 1.0
        self.threads = int(threads or os.cpu_count() or 1)
        self._pool = None
        self._lock = threading.Lock()
        self._local = threading.local()  # set on worker threads that run whole chunks
        # adjacency by welded vertex, and the near pairs that share no vertex
        # welded per vertex, then per corner: the same partition as welding the 3 T corners, on V rows
        welded = _weld(v)[f] if len(v) else np.zeros((0, 3), np.int64)
        nv = int(welded.max()) + 1 if welded.size else 0
        corner_tri = np.repeat(np.arange(self.n_tri), 3)
        corner_ok = np.repeat(valid, 3)
        self.welded = welded
        self.v2t = _csr(welded.reshape(-1)[corner_ok], corner_tri[corner_ok], nv)
        tol_build = TIE_TOL * 4.0 * self.scale
        pairs = (self.ids[_near_pairs(self.tri[self.ids].astype(np.float64), welded[self.ids], tol_build)] if exact_ties
                 else np.zeros((0, 2), np.int64))
        both = np.concatenate([pairs, pairs[:, ::-1]]) if pairs.size else np.zeros((0, 2), np.int64)
        self.near = _csr(both[:, 0], both[:, 1], self.n_tri)
        self.flagged = np.diff(self.near[0]) > 0
        self.n_near_pairs = len(pairs)
        # (rays hit, rays refined, rays going on) of the latest embree rounds, for tuning
        self.rounds_log = collections.deque(maxlen=64)
        self._compiled_tables = None  # the compiled first round's tables, made on first use
        self._primary_queries = 0  # calls of intersect_from_origin (top level)

    # -- embree calls ------------------------------------------------------------------------------
    def _pool_get(self):
        with self._lock:
            if self._pool is None and self.threads > 1:
                self._pool = ThreadPoolExecutor(self.threads)
            return self._pool

    def _run(self, o32, d32, tfar32, query):
        n = len(o32)
        if n == 0:
            return np.zeros(0, np.int32), np.zeros(0, F32)
        o32, d32 = np.ascontiguousarray(o32, F32), np.ascontiguousarray(d32, F32)
        tf = np.ascontiguousarray(tfar32, F32).copy()  # embreex writes the hit distance into it

        def one(a, b):
            if query == "OCCLUDED":
                return self.scene.run(o32[a:b], d32[a:b], dists=tf[a:b], query="OCCLUDED"), None
            r = self.scene.run(o32[a:b], d32[a:b], dists=tf[a:b], output=True)
            return r["primID"], r["tfar"]

        pool = self._pool_get()
        if pool is None or n < 4096 or getattr(self._local, "inside", False):
            parts = [one(0, n)]
        else:
            m = self.threads * 4
            cuts = np.linspace(0, n, m + 1).astype(int)
            parts = list(pool.map(lambda ab: one(*ab), itertools.pairwise(cuts)))
        prim = np.concatenate([p[0] for p in parts])
        if query == "OCCLUDED":
            return prim == 0, None
        return prim, np.concatenate([p[1] for p in parts])

    # -- the exact refinement ------------------------------------------------------------------------
    def _test(self, rd, ray, cand):
        """Watertight test of the pairs (ray[i], cand[i]): (hit, t, b0, b1, b2), float32 (the
        barycentrics only for the near-edge test)."""
        kx, ky, kz, sx, sy, sz, ok = (x[ray] for x in rd.setup)
        tri = self.tri[cand]
        o = rd.o32[ray]

        def rel(p):
            q0, q1, q2 = p[:, 0] - o[:, 0], p[:, 1] - o[:, 1], p[:, 2] - o[:, 2]
            return tuple(_bvh._pick(q0, q1, q2, k, np) for k in (kx, ky, kz))

        with np.errstate(all="ignore"):
            hit, t, u, v, w, det = _bvh._woop_core(rel(tri[:, 0]), rel(tri[:, 1]), rel(tri[:, 2]), sx, sy, sz, np)
            return hit & ok, t, u / det, v / det, w / det

    def _near_edge(self, cand, b0, b1, b2, tol_abs):
        dist = np.stack([b0, b1, b2], 1) * self.alt[cand]
        return (dist <= tol_abs[:, None]).any(1)

    def _adjacent(self, tris):
        """Triangles sharing a welded vertex with each of `tris` (m,): (owner, candidate)."""
        offs, vals = self.v2t
        corners = self.welded[tris].reshape(-1)
        owner3 = np.repeat(np.arange(tris.size), 3)
        own, cand = _gather_lists(offs, vals, corners)
        return owner3[own], cand

    def _flagged_near(self, tris):
        offs, vals = self.near
        return _gather_lists(offs, vals, tris)

    @staticmethod
    def _update(best_t, best_p, ray, t, p, ok, unique=False):
        """Lexicographic (t, id) minimum of the valid candidates into best (in place); unique:
        each ray appears at most once in `ray`."""
        ray, t, p = ray[ok], t[ok], p[ok]
        if ray.size == 0:
            return
        if not unique:
            order = np.lexsort((p, t, ray))
            ray, t, p = ray[order], t[order], p[order]
            first = np.r_[True, ray[1:] != ray[:-1]]
            ray, t, p = ray[first], t[first], p[first]
        better = (t < best_t[ray]) | ((t == best_t[ray]) & (p < best_p[ray]))
        best_t[ray[better]] = t[better]
        best_p[ray[better]] = p[better]

    def closest(self, o64, d64, tnear, tfar, after, max_rounds=64, first=None):
        """Canonical closest hit (see the module docstring): (t float32, prim int64 or _NONE).

        embree proposes the nearest triangle beyond s (s = tnear, or just past the previous hit's
        tie zone when continuing); the proposal, and when it may be tied its neighbours, are
        tested exactly; a ray is done when the best valid hit so far is no farther than the
        proposal's tie zone (everything untested lies beyond it), else s moves past the zone.
        first: embree's first proposals (primID, t), already asked for these rays from tnear = 0
        with tfar = inf and no previous hit (`closest_from_origin`), used instead of asking again."""
        n = len(o64)
        rd = _RayData(o64, d64, self.scale)
        tn32, tf32 = tnear.astype(F32), tfar.astype(F32)
        best_t = np.full(n, np.inf, F32)
        best_p = np.full(n, _NONE, np.int64)

        def valid(ray, cand, hit, t):
            ok = hit & (t >= tn32[ray]) & (t <= tf32[ray]) & (cand != after[ray])
            return ok & ((t > tn32[ray]) | (cand > after[ray]))

        def consider(ray, cand):
            if ray.size:
                hit, t, *_ = self._test(rd, ray, cand)
                self._update(best_t, best_p, ray, t, cand, valid(ray, cand, hit, t))

        s = tnear.astype(np.float64)
        cont = np.nonzero(after >= 0)[0]
        if cont.size:  # the hits tied with the previous one are its neighbours: test them directly
            s = s.copy()
            rd.ensure(cont)
            prev = after[cont]
            own, cand = self._flagged_near(prev)
            consider(cont[own], cand)
            hit, t, b0, b1, b2 = self._test(rd, cont, prev)
            e = cont[self._near_edge(prev, b0, b1, b2, rd.tol_abs[cont]) | ~hit]
            if e.size:
                own, cand = self._adjacent(after[e])
                consider(e[own], cand)
            s[cont] += rd.tol_t[cont]
        # A hit at exactly tnear counts (with no previous hit); from an origin moved to tnear,
        # embree can put it a rounding behind: start its search the tie zone earlier (the hits
        # before tnear it then proposes fail `valid` and are refined past).
        back = np.nonzero((after < 0) & (tnear > 0) & np.isfinite(tnear))[0]
        if back.size:
            s = s.copy() if s is tnear else s
            rd.ensure(back)
            s[back] = np.maximum(s[back] - rd.tol_t[back], 0.0)
        active = None  # all rays
        for _ in range(max_rounds):
            sa = s if active is None else s[active]
            d32 = rd.d32 if active is None else rd.d32[active]
            if not sa.any():
                org = rd.o32 if active is None else rd.o32[active]
            else:
                o_, d_ = (o64, d64) if active is None else (o64[active], d64[active])
                shift = np.where(np.isfinite(sa), sa, 0.0)  # (an infinite tnear gets span < 0 below)
                org = (o_ + shift[:, None] * d_).astype(F32)
            with np.errstate(invalid="ignore"):
                span = ((tfar if active is None else tfar[active]) - sa).astype(F32)
            span = np.where(np.isnan(span), F32(-1), span)
            if first is not None:
                pid, te = first
                first = None
            else:
                pid, te = self._run(org, d32, np.maximum(span, F32(0)), "INTERSECT")
            hitm = (pid >= 0) & (span >= 0)
            sub = np.nonzero(hitm)[0]
            ray = sub if active is None else active[sub]
            if ray.size == 0:
                break
            rd.ensure(ray)
            prop = self.ids[pid[sub]]
            t_ref = sa[sub] + te[sub].astype(np.float64)
            hit, t, b0, b1, b2 = self._test(rd, ray, prop)
            ok = valid(ray, prop, hit, t)
            self._update(best_t, best_p, ray, t, prop, ok, unique=True)
            refine = ~ok | self.flagged[prop] | self._near_edge(prop, b0, b1, b2, rd.tol_abs[ray])
            r = np.nonzero(refine)[0]
            if r.size:
                own, cand = self._flagged_near(prop[r])
                consider(ray[r[own]], cand)
                own, cand = self._adjacent(prop[r])
                consider(ray[r[own]], cand)
            done = best_t[ray].astype(np.float64) <= t_ref + rd.tol_t[ray]
            active = ray[~done]
            self.rounds_log.append((ray.size, int(r.size), int(active.size)))
            if active.size == 0:
                break
            s = s.copy() if s is tnear else s
            s[active] = t_ref[~done] + rd.tol_t[active]
        return best_t, best_p

    def closest_from_origin(self, o32, d32):
        """`closest` of float32 rays from tnear = 0 with tfar = inf and no previous hit (primary
        rays), (t, prim) the same: embree's first round runs on the float32 rays themselves, and
        only the rays it hits (a quarter of a typical frame's) are made float64 and refined. The
        refinement is per ray, so refining that subset gives every ray the result the whole set
        would (a ray embree misses in the first round is a miss there too)."""
        n = len(o32)
        best_t = np.full(n, np.inf, F32)
        best_p = np.full(n, _NONE, np.int64)
        pid, te = self._run(o32, d32, np.full(n, np.inf, F32), "INTERSECT")
        sub = np.flatnonzero(pid >= 0)
        if sub.size:
            m = sub.size
            t, p = self.closest(o32[sub].astype(np.float64), d32[sub].astype(np.float64), np.zeros(m), np.full(m, np.inf),
                                np.full(m, -1, np.int64), first=(pid[sub], te[sub]))
            best_t[sub], best_p[sub] = t, p
        return best_t, best_p

    def _tables(self):
        """The compiled first round's tables on JAX's CPU device, padded to `_table_rows`: the
        float32 vertices (rows of 9), the altitudes in float32, the near-pair flags, and the embree
        primID -> triangle id map (made on first use: queries of few rays never need them)."""
        with self._lock:
            if self._compiled_tables is None:
                rows = _table_rows(self.n_tri)
                pad = rows - self.n_tri
                host = (np.pad(self.tri.reshape(-1, 9), ((0, pad), (0, 0))), np.pad(self.alt.astype(F32), ((0, pad), (0, 0))),
                        np.pad(self.flagged, (0, pad)), np.pad(self.ids, (0, rows - self.ids.size)))
                cpu = jax.devices("cpu")[0]
                self._compiled_tables = (cpu, tuple(jax.device_put(x, cpu) for x in host))
            return self._compiled_tables

    def _use_compiled(self, n: int, bary: bool) -> bool:
        """Whether a query of n primary rays takes the compiled first round: enough rays, from the
        COMPILED_FROM_QUERY-th query on, once the program is compiled (`_compiled_ready`)."""
        if n < KERNEL_MIN_RAYS:
            return False
        with self._lock:
            self._primary_queries += 1
            if self._primary_queries < COMPILED_FROM_QUERY:
                return False
        cpu, tables = self._tables()

        def compile_it():  # one call on a block of misses: traces, compiles (or loads) the program
            with jax.default_device(cpu), jax.enable_x64(True):
                o = np.zeros((REFINE_BLOCK, 3), F32)
                rays = (o, o, np.full(REFINE_BLOCK, -1, np.int32), np.zeros(REFINE_BLOCK, F32))
                jax.block_until_ready(_first_round_jit(tables, F32(self.scale), np.int32(0), np.int64(0), *rays, bary=bary))

        return _compiled_ready((int(tables[0].shape[0]), REFINE_BLOCK, bool(bary)), compile_it)

    def compiled_from_origin(self, o32, d32, bary: bool) -> Hits:
        """`intersect_from_origin`'s Hits by the compiled first round (`_first_round`, blocks of
        REFINE_BLOCK rays on JAX's CPU device): embree's proposals tested with NumPy's rounding,
        float64 barycentrics; the rays it cannot settle (near edges, near pairs, rejected
        proposals: a few in 10^4 on a typical frame) go through `closest` and `barycentrics`."""
        n = len(o32)
        pid, te = self._run(o32, d32, np.full(n, np.inf, F32), "INTERSECT")
        cpu, tables = self._tables()
        t, prim, hard = np.empty(n, F32), np.empty(n, np.int32), np.empty(n, bool)
        b1, b2 = (np.zeros(n), np.zeros(n)) if bary else (None, None)
        outs = (t, prim, hard, b1, b2)
        with jax.default_device(cpu), jax.enable_x64(True):
            consts = (np.float32(self.scale), np.int32(0), np.int64(0))
            for a in range(0, n, REFINE_BLOCK):
                b = min(n, a + REFINE_BLOCK)
                pad = REFINE_BLOCK - (b - a)
                rays = (o32[a:b], d32[a:b], pid[a:b], te[a:b])
                if pad:  # (the last block; full ones go as they are, uncopied)
                    rays = (np.pad(rays[0], ((0, pad), (0, 0))), np.pad(rays[1], ((0, pad), (0, 0))),
                            np.pad(rays[2], (0, pad), constant_values=-1), np.pad(rays[3], (0, pad)))
                res = _first_round_jit(tables, *consts, *rays, bary=bary)
                for dst, x in zip(outs, res):
                    dst[a:b] = np.asarray(x)[: b - a]
        idx = np.flatnonzero(hard)
        if idx.size:
            m = idx.size
            o64, d64 = o32[idx].astype(np.float64), d32[idx].astype(np.float64)
            th, ph = self.closest(o64, d64, np.zeros(m), np.full(m, np.inf), np.full(m, -1, np.int64), first=(pid[idx], te[idx]))
            h = _hits(th, ph, *(self.barycentrics(o64, d64, ph) if bary else (None, None)))
            t[idx], prim[idx] = h.t, h.prim
            if bary:
                b1[idx], b2[idx] = h.b1, h.b2
        return Hits(t, prim, b1, b2)

    def barycentrics(self, o64, d64, prim):
        hit = prim != _NONE
        b1 = np.zeros(len(prim))
        b2 = np.zeros(len(prim))
        if hit.any():
            tri = self.tri[prim[hit]].astype(np.float64)
            b1[hit], b2[hit] = _bvh.barycentrics(o64[hit], d64[hit], tri[:, 0], tri[:, 1], tri[:, 2], np)
        return b1, b2

    def intersect(self, o64, d64, tnear, tfar, after, bary: bool = True):
        n = len(o64)
        chunked = self._on_workers(n, lambda a, b: self.intersect(o64[a:b], d64[a:b], tnear[a:b], tfar[a:b], after[a:b], bary))
        if chunked is not None:
            return chunked
        t, p = self.closest(o64, d64, tnear, tfar, after)
        b1, b2 = self.barycentrics(o64, d64, p) if bary else (None, None)
        return _hits(t, p, b1, b2)

    def intersect_from_origin(self, o32, d32, bary: bool = True, compiled: bool | None = None):
        """`intersect` of float32 rays from tnear = 0 with tfar = inf and no previous hit (the same
        Hits), by `compiled_from_origin` where `_use_compiled` says so (compiled: decided by the
        caller, a chunk of a larger query), else by `closest_from_origin`."""
        n = len(o32)
        if compiled is None:
            compiled = self._use_compiled(n, bary)
        chunked = self._on_workers(n, lambda a, b: self.intersect_from_origin(o32[a:b], d32[a:b], bary, compiled))
        if chunked is not None:
            return chunked
        if compiled:
            return self.compiled_from_origin(o32, d32, bary)
        t, p = self.closest_from_origin(o32, d32)
        b1 = b2 = None
        if bary:
            hit = np.flatnonzero(p != _NONE)
            b1, b2 = np.zeros(n), np.zeros(n)
            if hit.size:
                b1[hit], b2[hit] = self.barycentrics(o32[hit].astype(np.float64), d32[hit].astype(np.float64), p[hit])
        return _hits(t, p, b1, b2)

    def _on_workers(self, n: int, call):
        """The Hits of `call(a, b)` over chunks [a, b) of the n rays, each chunk whole on a worker
        thread (embree and the NumPy refinement, which releases the GIL in its array operations);
        None where the rays are few, there is one thread, or this already is a worker thread."""
        pool = self._pool_get()
        if pool is None or n < 1 << 16 or getattr(self._local, "inside", False):
            return None

        def part(ab):
            self._local.inside = True
            try:
                return call(*ab)
            finally:
                self._local.inside = False

        cuts = np.linspace(0, n, 2 * self.threads + 1).astype(int)
        parts = list(pool.map(part, itertools.pairwise(cuts)))
        return Hits(*(None if x[0] is None else np.concatenate(x) for x in zip(*parts)))

    def occluded_from_origin(self, o32, d32, span32):
        """`occluded` of float32 rays from tnear = 0 (span32: tfar as float32)."""
        ok = span32 >= 0  # (False for NaN)
        occ, _ = self._run(o32, d32, np.where(ok, span32, F32(0)), "OCCLUDED")
        return occ & ok

    def occluded(self, o64, d64, tnear, tfar):
        shift = np.where(np.isfinite(tnear), tnear, 0.0)
        org = (o64 + shift[:, None] * d64).astype(F32)
        with np.errstate(invalid="ignore"):
            span = (tfar - tnear).astype(F32)
        ok = span >= 0  # (NaN for inf - inf: False)
        occ, _ = self._run(org, d64.astype(F32), np.where(ok, span, F32(0)), "OCCLUDED")
        return occ & ok


# --------------------------------------------------------------------------------------------------
# the public class


def _float32_rays(origins, directions, tnear):
    """(shape, o (n, 3), d (n, 3)) float32 of NumPy float32 rays with finite directions and
    tnear = 0, for which `_EmbreeBackend.occluded`'s float64 origin o + 0 d rounds back to o
    itself; None otherwise."""
    if not (isinstance(tnear, (int, float)) and tnear == 0):
        return None
    if not all(isinstance(x, np.ndarray) and x.dtype == F32 and x.shape[-1:] == (3,) for x in (origins, directions)):
        return None
    if not np.isfinite(directions).all():
        return None
    shape = np.broadcast_shapes(origins.shape, directions.shape)[:-1]
    n = int(np.prod(shape, dtype=np.int64))
    o = np.ascontiguousarray(np.broadcast_to(origins, shape + (3,)).reshape(n, 3))
    d = np.ascontiguousarray(np.broadcast_to(directions, shape + (3,)).reshape(n, 3))
    return shape, o, d


def _hits(t, p, b1, b2) -> Hits:
    """Hits of `closest`'s (t, prim): t = inf and prim = -1 where nothing was hit."""
    miss = p == _NONE
    return Hits(np.where(miss, np.inf, t).astype(F32), np.where(miss, -1, p).astype(np.int32), b1, b2)


def _is_scalar(x, value) -> bool:
    """x is the Python or NumPy scalar `value` (not an array of rays' values)."""
    return isinstance(x, (int, float, np.integer, np.floating)) and x == value


def _host_rays(origins, directions, tnear, tfar, after):
    o = np.asarray(origins, np.float64)
    d = np.asarray(directions, np.float64)
    if o.shape[-1:] != (3,) or d.shape[-1:] != (3,):
        raise InputError(f"origins and directions must be (..., 3), got {o.shape} and {d.shape}")
    shape = np.broadcast_shapes(o.shape, d.shape)[:-1]
    n = int(np.prod(shape, dtype=np.int64))
    o = np.broadcast_to(o, shape + (3,)).reshape(n, 3)
    d = np.broadcast_to(d, shape + (3,)).reshape(n, 3)
    tn = np.broadcast_to(np.asarray(tnear, np.float64), shape).reshape(n)
    tf = np.broadcast_to(np.asarray(tfar, np.float64), shape).reshape(n)
    af = np.broadcast_to(np.asarray(after, np.int64), shape).reshape(n)
    return shape, o, d, tn, tf, af


def _check_after(after, n_tri):
    a = np.asarray(after)
    if a.size and (a.min() < -1 or a.max() >= max(n_tri, 1)):
        raise InputError(f"after_prim must be -1 or a triangle id in [0, {n_tri}), got [{a.min()}, {a.max()}]")


class TriangleAccel:
    """Visibility queries against one triangle mesh (see the module docstring).

    Build with `TriangleAccel.build(vertices, triangles, backend="auto" | "embree" | "jax")`.
    Attributes: `backend` ("embree" or "jax"), `num_triangles`, and for the jax backend `bvh` (the
    device-resident `BVH` to pass to the jitted `intersect_jax` / `occluded_jax` / `first_k_hits_jax`
    inside a renderer's own jit)."""

    def __init__(self, backend: str, impl, num_triangles: int, lanes: int | None = None):
        self.backend = backend
        self._impl = impl
        self.num_triangles = num_triangles
        # rays in flight in the JAX traversal: enough to amortise a step's fixed cost; a GPU
        # needs many more than a CPU to fill it (a guess there: no GPU measurement behind it)
        self._on_cpu = jax.default_backend() == "cpu"
        self.lanes = int(lanes or (_bvh.DEFAULT_LANES if self._on_cpu else 1 << 17))
        self.threads = os.cpu_count() or 1

    @classmethod
    def build(
        cls,
        vertices,
        triangles,
        *,
        backend: str = "auto",
        leaf_size: int = 2,
        lanes: int | None = None,
        min_triangles: int = 0,
        threads: int | None = None,
        exact_ties: bool = True,
    ) -> TriangleAccel:
        """Build on the host. vertices (V, 3) float, triangles (T, 3) int. backend: "auto" (embree
        if importable and JAX runs on the CPU, else jax), "embree" or "jax". leaf_size, lanes and
        min_triangles tune the jax backend (triangles per BVH leaf; rays in flight, default 8192
        on a CPU and 131072 elsewhere; pad the BVH arrays as for this many triangles so that
        several meshes share one compiled traversal),
        threads and exact_ties the embree one (threads: default os.cpu_count(); exact_ties=False
        skips the build-time search for non-adjacent triangles within the tie tolerance, about
        half of the build time: then coplanar copies and crossing triangles may come out of
        continuation in embree's order, or one of them be skipped)."""
        if backend not in ("auto", "embree", "jax"):
            raise InputError(f"backend must be 'auto', 'embree' or 'jax', got {backend!r}")
        if backend == "auto":
            backend = "embree" if (jax.default_backend() == "cpu" and embree_available()) else "jax"
        n_tri = int(np.shape(triangles)[0]) if np.ndim(triangles) == 2 else 0
        if backend == "embree":
            if not embree_available():
                raise InputError("backend='embree' needs the embreex package (pip install embreex)")
            return cls("embree", _EmbreeBackend(vertices, triangles, threads, exact_ties), n_tri, lanes)
        bvh = build_bvh(vertices, triangles, leaf_size=leaf_size, min_triangles=min_triangles).to_device()
        return cls("jax", bvh, n_tri, lanes)

    @property
    def bvh(self) -> BVH:
        if self.backend != "jax":
            raise AttributeError("only the jax backend has a BVH")
        return self._impl

    # The jax backend pads the ray count to a power-of-two bucket (at least 1024) so that the
    # traversal compiles once per bucket; the padding rays have a zero direction and end at once.
    def _jax_call(self, fn, shape, arrays, **kw):
        """arrays: name -> (value, trailing shape, dtype). Everything is cast to a definite
        (strong) dtype, so Python scalars and arrays hit the same compiled program. Ray counts are
        padded to power-of-two buckets. On a CPU, large batches are cut into one part per core,
        traced concurrently from Python threads: XLA runs this loop on about one core per call
        (measured on 2 cores: 2 concurrent calls 2-3x faster than one call on twice the rays)."""
        n = int(np.prod(shape, dtype=np.int64))
        # Host rays (NumPy arrays, numbers) are cast, cut and padded in NumPy and the results come
        # back as NumPy: an eager jnp slice, pad or cast compiles a small program per ray count
        # (a walk through layers asks with a different count each round: 0.1-0.2 s each).
        host = not any(isinstance(a, jax.Array) for a, _, _ in arrays.values())
        xp = np if host else jnp
        flat = {}
        for name, (a, tail, dt) in arrays.items():
            flat[name] = (xp.broadcast_to(xp.asarray(a).astype(dt), shape + tail).reshape((n,) + tail), tail)
        parts = self.threads if (self._on_cpu and n >= 2 * _bvh.DEFAULT_LANES) else 1

        def cut(x, k):
            return np.asarray(x)[:k] if host else x[:k]

        def run(lo, hi):
            m = pad_rays(hi - lo)
            args = {k: xp.pad(a[lo:hi], [(0, m - (hi - lo))] + [(0, 0)] * len(t)) for k, (a, t) in flat.items()}
            out = fn(self._impl, **args, lanes=min(self.lanes, m), **kw)
            out = jax.tree.map(lambda x: cut(x, hi - lo), out)
            return jax.block_until_ready(out) if parts > 1 and not host else out

        if parts == 1:
            out = run(0, n)
        else:
            cuts = np.linspace(0, n, parts + 1).astype(int)
            with ThreadPoolExecutor(parts) as pool:
                outs = list(pool.map(lambda ab: run(*ab), itertools.pairwise(cuts)))
            out = jax.tree.map(lambda *xs: xp.concatenate(xs), *outs)
        return jax.tree.map(lambda x: x.reshape(shape + x.shape[1:]), out)

    @staticmethod
    def _ray_dtype(origins, directions):
        """float64 when either is float64 (and x64 is on), else float32: the barycentrics' dtype."""
        dts = [np.result_type(x) if not isinstance(x, jax.Array) else x.dtype for x in (origins, directions)]
        wide = any(np.dtype(dt) == np.float64 for dt in dts)
        return jnp.float64 if wide and jax.config.jax_enable_x64 else jnp.float32

    @staticmethod
    def _shape(origins, directions):
        so, sd = np.shape(origins), np.shape(directions)
        if so[-1:] != (3,) or sd[-1:] != (3,):
            raise InputError(f"origins and directions must be (..., 3), got {so} and {sd}")
        return tuple(np.broadcast_shapes(so, sd)[:-1])

    def intersect(self, origins, directions, tnear=0.0, tfar=np.inf, after_prim=-1, *, barycentrics: bool = True) -> Hits:
        """Closest hits: Hits(t, prim, b1, b2) of shape (...) for rays (..., 3). A triangle hit
        (t, id) counts when tnear <= t <= tfar, id != after_prim and (t, id) > (tnear, after_prim);
        the least (t, id) wins. after_prim = -1: the plain closest hit in [tnear, tfar]; the
        previous hit's (t, prim): the next hit along the same ray (continuation).
        barycentrics=False: the embree backend leaves b1 and b2 out (None) for a caller that reads
        only t and prim (2 M rays: about 0.04 s less)."""
        if not isinstance(after_prim, jax.core.Tracer):
            _check_after(after_prim, self.num_triangles)
        if self.backend == "embree":
            plain = _float32_rays(origins, directions, tnear)
            if plain is not None and _is_scalar(tfar, np.inf) and _is_scalar(after_prim, -1):
                # Float32 primary rays: no float64 copies of the whole set (the same hits).
                shape, o, d = plain
                h = self._impl.intersect_from_origin(o, d, barycentrics)
                return Hits(*(None if x is None else x.reshape(shape) for x in h))
            shape, o, d, tn, tf, af = _host_rays(origins, directions, tnear, tfar, after_prim)
            h = self._impl.intersect(o, d, tn, tf, af, barycentrics)
            return Hits(*(None if x is None else x.reshape(shape) for x in h))
        shape = self._shape(origins, directions)
        dt = self._ray_dtype(origins, directions)
        args = {"origins": (origins, (3,), dt), "directions": (directions, (3,), dt)}
        args.update(tnear=(tnear, (), jnp.float32), tfar=(tfar, (), jnp.float32), after_prim=(after_prim, (), jnp.int32))
        return self._jax_call(intersect_jax, shape, args)

    def occluded(self, origins, directions, tnear=0.0, tfar=np.inf):
        """Shadow rays: bool (...), True when a triangle is hit with tnear <= t <= tfar.
        (embree: embree's own float32 any-hit test, which can differ from `intersect` for hits
        within float32 rounding of tnear/tfar or exactly on an edge.)"""
        if self.backend == "embree":
            plain = _float32_rays(origins, directions, tnear)
            if plain is not None:  # float32 rays from tnear = 0: no float64 copies (the same test)
                shape, o, d = plain
                tf = np.broadcast_to(np.asarray(tfar, np.float64).astype(F32), shape).reshape(-1)
                return self._impl.occluded_from_origin(o, d, tf).reshape(shape)
            shape, o, d, tn, tf, _ = _host_rays(origins, directions, tnear, tfar, -1)
            return self._impl.occluded(o, d, tn, tf).reshape(shape)
        shape = self._shape(origins, directions)
        args = {"origins": (origins, (3,), jnp.float32), "directions": (directions, (3,), jnp.float32)}
        args.update(tnear=(tnear, (), jnp.float32), tfar=(tfar, (), jnp.float32))
        return self._jax_call(occluded_jax, shape, args)

    def first_k_hits(self, origins, directions, k: int, tnear=0.0, tfar=np.inf) -> Hits:
        """The k first hits per ray in (t, id) order: Hits of shape (..., k); missing layers have
        t = inf, prim = -1, b1 = b2 = 0. Every triangle on the ray is reported once."""
        k = int(k)
        if self.backend == "embree":
            shape, o, d, tn, tf, af = _host_rays(origins, directions, tnear, tfar, -1)
            n = len(o)
            out = [np.full((n, k), np.inf, F32), np.full((n, k), -1, np.int32), np.zeros((n, k)), np.zeros((n, k))]
            live = np.arange(n)
            t_prev, p_prev = tn.copy(), af.copy()
            for i in range(k):
                if live.size == 0:
                    break
                h = self._impl.intersect(o[live], d[live], t_prev[live], tf[live], p_prev[live])
                for j, x in enumerate(h):
                    out[j][live, i] = x
                t_prev[live] = h.t
                p_prev[live] = h.prim
                live = live[h.prim >= 0]
            return Hits(*(x.reshape(shape + (k,)) for x in out))
        shape = self._shape(origins, directions)
        dt = self._ray_dtype(origins, directions)
        args = {"origins": (origins, (3,), dt), "directions": (directions, (3,), dt)}
        args.update(tnear=(tnear, (), jnp.float32), tfar=(tfar, (), jnp.float32))
        return self._jax_call(first_k_hits_jax, shape, args, k=k)


class GroupedAccel:
    """Visibility queries against a mesh split into groups of triangles, each with its own
    `TriangleAccel` (a two-level structure whose top level is the list of groups): the same answers
    as one `TriangleAccel` over the whole mesh, in the same (t, id) order with the whole mesh's
    triangle ids, continuation included. What a scene of static and moving meshes needs: the static
    group keeps its structure while the moving one is rebuilt (`mesh.ACCELS.get(parts=...)`).

    groups: [(accel, ids)], ids (n_g,) increasing: the whole mesh's id of each of the group's
    triangles (the group's rows). A ray queries every group; a group it misses costs a box test."""

    def __init__(self, groups, num_triangles: int):
        self.groups = [(a, np.asarray(ids, np.int64)) for a, ids in groups]
        for a, ids in self.groups:
            if ids.shape != (a.num_triangles,) or np.any(np.diff(ids) <= 0):
                raise InputError("GroupedAccel: a group's ids must be increasing, one per triangle of its structure")
        self.backend = self.groups[0][0].backend
        self.num_triangles = int(num_triangles)

    def device_groups(self):
        """((BVH, ids (n,) int32), ...) on JAX's default device for `intersect_groups` (jax
        backend; made once per structure)."""
        if self.backend != "jax":
            raise AttributeError("only the jax backend has BVHs")
        if getattr(self, "_device", None) is None:
            self._device = tuple((a.bvh, _device_ids(a, ids)) for a, ids in self.groups)
        return self._device

    def _group_hits(self, accel, ids, o, d, tn, tf, after, barycentrics):
        """The group's first hit after (tn, after) in the whole mesh's order: (t, global id or -1, b1, b2)."""
        local = np.searchsorted(ids, after, side="right") - 1  # the group's last triangle at or before `after`
        own = (local >= 0) & (ids[np.maximum(local, 0)] == after)
        h = accel.intersect(o, d, tn, tf, np.where(own, local, -1), barycentrics=barycentrics)
        t, p = np.array(h.t, F32), np.array(h.prim, np.int64)  # (copies: rows are redone below)
        b1 = None if h.b1 is None else np.array(h.b1)
        b2 = None if h.b2 is None else np.array(h.b2)
        # A group without `after` answered from tnear on: hits exactly at tnear ordered before
        # `after` (coplanar copies across groups) come before it, so go on past them.
        redo = np.nonzero(~own & (p >= 0) & (t == tn) & (ids[np.maximum(p, 0)] < after))[0]
        while redo.size:
            h = accel.intersect(o[redo], d[redo], tn[redo], tf[redo], p[redo], barycentrics=barycentrics)
            t[redo], p[redo] = np.asarray(h.t, F32), np.asarray(h.prim, np.int64)
            if b1 is not None:
                b1[redo], b2[redo] = np.asarray(h.b1), np.asarray(h.b2)
            q = p[redo]
            redo = redo[(q >= 0) & (t[redo] == tn[redo]) & (ids[np.maximum(q, 0)] < after[redo])]
        return t, np.where(p >= 0, ids[np.maximum(p, 0)], -1), b1, b2

    def intersect(self, origins, directions, tnear=0.0, tfar=np.inf, after_prim=-1, *, barycentrics: bool = True) -> Hits:
        """`TriangleAccel.intersect` over the groups: the least (t, id) of the groups' answers."""
        _check_after(after_prim, self.num_triangles)
        plain = _is_scalar(after_prim, -1)
        if plain:  # each group's own first hit (its fast path for float32 rays from tnear = 0)
            shape = TriangleAccel._shape(origins, directions)
        else:
            shape, o, d, tn, tf, af = _host_rays(origins, directions, tnear, tfar, after_prim)
            tn, tf = tn.astype(F32), tf.astype(F32)
        n = int(np.prod(shape, dtype=np.int64))
        best_t = np.full(n, np.inf, F32)
        best_p = np.full(n, -1, np.int64)
        best_b = [None, None]
        for accel, ids in self.groups:
            if plain:
                h = accel.intersect(origins, directions, tnear, tfar, -1, barycentrics=barycentrics)
                t = np.asarray(h.t, F32).reshape(n)
                p = np.asarray(h.prim, np.int64).reshape(n)
                p = np.where(p >= 0, ids[np.maximum(p, 0)], -1)
                b = [None if x is None else np.asarray(x).reshape(n) for x in (h.b1, h.b2)]
            else:
                t, p, *b = self._group_hits(accel, ids, o, d, tn, tf, af, barycentrics)
            first = best_b[0] is None and b[0] is not None
            if first:
                best_b = [np.zeros(n, b[0].dtype), np.zeros(n, b[1].dtype)]
            better = (p >= 0) & ((best_p < 0) | (t < best_t) | ((t == best_t) & (p < best_p)))
            best_t = np.where(better, t, best_t)
            best_p = np.where(better, p, best_p)
            if b[0] is not None:
                for k in range(2):
                    best_b[k] = np.where(better, b[k], best_b[k])
        out = [best_t, best_p.astype(np.int32)] + best_b
        return Hits(*(None if x is None else x.reshape(shape) for x in out))

    def occluded(self, origins, directions, tnear=0.0, tfar=np.inf):
        """`TriangleAccel.occluded` over the groups: some group is hit in [tnear, tfar]."""
        out = None
        for accel, _ in self.groups:
            occ = np.asarray(accel.occluded(origins, directions, tnear, tfar), bool)
            out = occ if out is None else out | occ
        return out

    def first_k_hits(self, origins, directions, k: int, tnear=0.0, tfar=np.inf) -> Hits:
        """`TriangleAccel.first_k_hits`: k continuations of `intersect`."""
        k = int(k)
        shape, o, d, tn, tf, _ = _host_rays(origins, directions, tnear, tfar, -1)
        n = len(o)
        out = [np.full((n, k), np.inf, F32), np.full((n, k), -1, np.int32), np.zeros((n, k)), np.zeros((n, k))]
        live = np.arange(n)
        t_prev, p_prev = tn.astype(F32), np.full(n, -1, np.int64)
        for i in range(k):
            if live.size == 0:
                break
            h = self.intersect(o[live], d[live], t_prev[live], tf[live], p_prev[live])
            for j, x in enumerate(h):
                out[j][live, i] = x
            t_prev[live], p_prev[live] = h.t, h.prim
            live = live[np.asarray(h.prim) >= 0]
        return Hits(*(x.reshape(shape + (k,)) for x in out))


def _device_ids(accel, ids: np.ndarray):
    """`ids` on the device, kept with the group's structure: a static group is in a new
    `GroupedAccel` every frame, its ids are not sent to the device again (4 MB per million
    triangles)."""
    kept = getattr(accel, "_device_ids", None)
    if kept is not None and kept[0].shape == ids.shape and np.array_equal(kept[0], ids):
        return kept[1]
    dev = jnp.asarray(ids, jnp.int32)
    accel._device_ids = (ids, dev)
    return dev


def intersect_groups(groups, origins, directions, tnear=0.0, tfar=np.inf, after_prim=-1, *, lanes: int = _bvh.DEFAULT_LANES) -> Hits:
    """`intersect_bvh` over groups of one mesh ((BVH, ids), ... as `GroupedAccel.device_groups`),
    traceable: the least (t, id) of the groups' hits with the whole mesh's ids, continuation after
    (tnear, after_prim) included (`GroupedAccel.intersect`). Rays (N, 3), per-ray arrays (N,)."""
    n = origins.shape[0]
    tnear = jnp.broadcast_to(jnp.asarray(tnear, jnp.float32), (n,))
    tfar = jnp.broadcast_to(jnp.asarray(tfar, jnp.float32), (n,))
    after = jnp.broadcast_to(jnp.asarray(after_prim, jnp.int32), (n,))
    best = None
    for bvh, ids in groups:
        local = jnp.searchsorted(ids, after, side="right").astype(jnp.int32) - 1
        own = (local >= 0) & (ids[jnp.maximum(local, 0)] == after)
        h = intersect_bvh(bvh, origins, directions, tnear, tfar, jnp.where(own, local, -1), lanes=lanes)

        def early(h):  # a hit exactly at tnear ordered before `after`, in a group without it
            return ~own & (h.prim >= 0) & (h.t == tnear) & (ids[jnp.maximum(h.prim, 0)] < after)

        def again(h, bvh=bvh, early=early):
            redo = early(h)
            h2 = intersect_bvh(bvh, origins, directions, tnear, jnp.where(redo, tfar, -jnp.inf), jnp.where(redo, h.prim, -1), lanes=lanes)
            return Hits(*(jnp.where(redo, b, a) for a, b in zip(h, h2, strict=True)))

        h = jax.lax.while_loop(lambda h, early=early: jnp.any(early(h)), again, h)
        h = h._replace(prim=jnp.where(h.prim >= 0, ids[jnp.maximum(h.prim, 0)], -1))
        if best is None:
            best = h
            continue
        better = (h.prim >= 0) & ((best.prim < 0) | (h.t < best.t) | ((h.t == best.t) & (h.prim < best.prim)))
        best = Hits(*(jnp.where(better, b, a) for a, b in zip(best, h, strict=True)))
    return best
