"""A bounding volume hierarchy over triangles: built on the host in NumPy, traversed in JAX.

`build_bvh` makes a binary BVH with a binned surface-area heuristic (16 bins along each node's
widest centroid extent, fewer for small nodes; top-down, one vectorised pass per tree level; at
most `leaf_size` triangles per leaf; below depth 40 splits turn into object medians so the depth
stays bounded) and flattens it into arrays:
for every inner node the boxes of its two children, and per child either an inner-node index or a
leaf's range in the leaf-ordered triangle array.

`intersect_bvh` / `occluded_bvh` / `first_k_hits_bvh` trace rays through it. Each ray's traversal is
a stack machine (a fixed-size stack; per step: test the current node's two child boxes, intersect
the triangles of the leaf children hit, go to the nearer inner child and push the farther, or pop).
`lanes` rays are in flight at once in one `lax.while_loop`; a lane whose ray is finished writes its
result and takes the next ray from the queue, so a slow ray holds up nobody (a vmapped per-ray loop
runs every ray for as many steps as the slowest one in its batch: measured 10x slower on CPU). The
functions are tracer-friendly (jit them, call them inside a jitted renderer, vmap them) and run on
any JAX backend.

The ray/triangle test, `watertight_test`, is the watertight test of Woop, Benthin & Wald ("Watertight
Ray/Triangle Intersection", JCGT 2013), written for both NumPy and jax.numpy so that the host (the
embree backend's refinement in `visibility.py`) and the traversal compute the same thing:

* the ray is sheared so that its direction becomes +z along its dominant axis; the three 2-D edge
  functions U, V, W of the sheared triangle at the ray decide the hit: all >= 0 or all <= 0 (front
  and back faces both hit; culling is the caller's choice, from the sign of the geometric normal).
  An edge function that is exactly 0 counts as inside, so a ray through a shared edge or vertex
  hits at least one of the triangles there (no cracks), sometimes several.
* XLA on CPU contracts `a*b - c*d` into a fused multiply-add, which breaks the exact antisymmetry
  U(edge a->b) = -U(edge b->a) that watertightness rests on (measured: XLA's `a*b - c*d` equals
  NumPy's in 75% of random cases and `fma(a, b, -(c*d))` in 100%). So each edge function is
  computed as `(a*b - c*d) - (c*d - a*b)` (twice its value): whichever product a compiler fuses,
  swapping the edge's vertices negates the result exactly. (Checked on CPU in the tests; GPU
  compilers contract too, the formulation is meant to survive that, not measured here.)
* no epsilon: a triangle whose edge functions sum to 0 (det = 0: the ray lies in its plane) is
  missed; t = T/det, barycentrics b1 = V/det (weight of vertex 1), b2 = W/det. Float32 throughout.
  t is accurate to a few float32 ulps of the hit's distance from the origin, measured along the
  dominant axis; it degrades (absolutely, not relatively) for a t much smaller than the triangle.

Zero-area triangles (vertices collinear or repeated in float32, or non-finite) are dropped at build
time and never hit. Triangle ids are the row indices into the caller's `triangles` array.

Hit order and continuation: the hits of a ray are ordered lexicographically by (t, triangle id), so
several triangles at exactly the same t (coplanar overlapping copies, a ray through a shared edge)
have a definite order. `intersect_bvh(..., tnear, after_prim)` returns the first hit strictly after
(tnear, after_prim) in that order (and never `after_prim` itself): passing the previous hit's t and
id walks through every triangle on the ray exactly once, nearest first (`first_k_hits_bvh`).

What recompiles: the traversal is compiled per (ray count, lanes, node-array length, triangle-array
length, stack size, leaf size, origin dtype (the barycentrics' dtype), k for first_k_hits). With
`build_bvh(..., bucket=True)` (the default) the node and triangle arrays are padded to powers of two
(at least `min_triangles`) and the stack to a multiple of 16 (at least 32), so meshes of similar
size share one compiled traversal; `pad_rays` gives the power-of-two bucket that
`visibility.TriangleAccel` pads ray counts to. Nothing here depends on the mesh's values, so a
renderer's shading stages never recompile because of the geometry.
"""

from __future__ import annotations

import operator
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxpbr.errors import InputError

from .._numerics import cross_rows

__all__ = [
    "BVH",
    "Hits",
    "build_bvh",
    "first_k_hits_bvh",
    "intersect_bvh",
    "occluded_bvh",
    "pad_rays",
    "refit_bvh",
    "valid_triangles",
    "watertight_test",
]

F32 = np.float32
#: Slab test: the far distance of a box is scaled by 1 + 4 ulp (Ize, "Robust BVH Ray Traversal",
#: JCGT 2013, asks for 1 + 2 gamma_3 ~ 1 + 3 ulp) so that float32 rounding never culls a box that
#: holds a hit; the boxes themselves are rounded outwards by one ulp at build time.
_BOX_GROW = 1.0 + 4.0 * 2.0**-23
#: A zero direction component is replaced by this (sign kept) before 1/d: no inf*0 = NaN in the slabs.
_TINY_DIR = 1e-30
#: Default number of rays in flight in the traversal loop (more: less per-step overhead, more memory).
DEFAULT_LANES = 8192
_MEDIAN_DEPTH = 40


class Hits(NamedTuple):
    """Closest hits: `t` (inf on a miss), `prim` (int32 triangle id, -1 on a miss) and the
    barycentric weights `b1`, `b2` of vertices 1 and 2 (0 on a miss): the hit point is
    `(1 - b1 - b2) v0 + b1 v1 + b2 v2` ~ `origin + t direction`. A NamedTuple, hence a pytree."""

    t: object
    prim: object
    b1: object
    b2: object


class BVH(NamedTuple):
    """The flattened BVH, a pytree of arrays whose shapes carry the static sizes.

    nodes  (M, 12) float32  per inner node (node 0 is the root) the boxes of its two children:
                            lo0 xyz, hi0 xyz, lo1 xyz, hi1 xyz (rounded outwards; empty: lo > hi)
    links  (M, 4) int32     child0, child1, count0, count1: an inner child is its node index with
                            count 0; a leaf child its first row in `tri` with its triangle count;
                            an empty child -1 with count 0
    tri    (T, 9) float32   triangle vertices v0 xyz, v1 xyz, v2 xyz in leaf order (padded)
    prim   (T,) int32       the caller's triangle id of each row (-1 in the padding)
    stack  (S,) int32       zeros; its length is the traversal stack size (> tree depth)
    lanes  (L,) int32       arange(leaf_size): the leaf size as a shape
    """

    nodes: object
    links: object
    tri: object
    prim: object
    stack: object
    lanes: object

    @property
    def leaf_size(self) -> int:
        return int(self.lanes.shape[0])

    @property
    def stack_size(self) -> int:
        return int(self.stack.shape[0])

    def to_device(self, device=None) -> BVH:
        """The arrays as jax arrays (on `device`, default: JAX's default device)."""
        return BVH(*(jax.device_put(np.asarray(a), device) for a in self))


# --------------------------------------------------------------------------------------------------
# the ray/triangle test, shared by NumPy (host) and jax.numpy (traversal)


def opaque_mul(zero):
    """A product XLA cannot fuse into a neighbouring sum (x * y + z as one FMA, rounded once, which
    XLA:CPU does whatever its flags say): the float bits go through an integer XOR with `zero`, a
    0 of the product's width passed to the program at run time (a traced value, so it is not folded
    away). Expressions written with it round as NumPy's, operation by operation."""

    def mul(a, b):
        p = a * b
        ints = jnp.int64 if p.dtype == jnp.float64 else jnp.int32
        return jax.lax.bitcast_convert_type(jax.lax.bitcast_convert_type(p, ints) ^ zero.astype(ints), p.dtype)

    return mul


def _pick(x0, x1, x2, k, xp):
    """Component k (0, 1 or 2, per ray) of a vector given as its three components: exact selects."""
    return xp.where(k == 0, x0, xp.where(k == 1, x1, x2))


def ray_setup(d, xp=np):
    """Per-ray constants of the watertight test for directions d (..., 3) float32:
    (kx, ky, kz, sx, sy, sz, ok). kz is the dominant axis (the first on ties), kx/ky are swapped
    when d[kz] < 0 to keep the winding; ok is False for a zero or non-finite direction."""
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    ax, ay, az = xp.abs(dx), xp.abs(dy), xp.abs(dz)
    kz = xp.where((ax >= ay) & (ax >= az), 0, xp.where(ay >= az, 1, 2)).astype(np.int32)
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    dkz = _pick(dx, dy, dz, kz, xp)
    neg = dkz < 0
    kx, ky = xp.where(neg, ky, kx), xp.where(neg, kx, ky)
    ok = (dkz != 0) & xp.isfinite(dx) & xp.isfinite(dy) & xp.isfinite(dz)
    dkz = xp.where(ok, dkz, xp.ones_like(dkz))
    sx = _pick(dx, dy, dz, kx, xp) / dkz
    sy = _pick(dx, dy, dz, ky, xp) / dkz
    sz = xp.ones_like(dkz) / dkz
    return kx, ky, kz, sx, sy, sz, ok


def _woop_core(a, b, c, sx, sy, sz, xp, mul=operator.mul):
    """The test on vertex coordinates relative to the ray origin, already permuted to
    (kx, ky, kz): a, b, c are 3-tuples. Returns (hit-before-range-check, t, u, v, w, det).
    mul: the product (`opaque_mul` for a compiled program that must round as NumPy does)."""

    def sheared(p):
        return p[0] - mul(sx, p[2]), p[1] - mul(sy, p[2])

    ax, ay = sheared(a)
    bx, by = sheared(b)
    cx, cy = sheared(c)

    def edge(px, py, qx, qy):  # 2 (px qy - py qx), exactly antisymmetric in (p, q)
        return (mul(px, qy) - mul(py, qx)) - (mul(py, qx) - mul(px, qy))

    u = edge(cx, cy, bx, by)  # weight of v0 (edge v1-v2)
    v = edge(ax, ay, cx, cy)  # weight of v1 (edge v2-v0)
    w = edge(bx, by, ax, ay)  # weight of v2 (edge v0-v1)
    neg = (u < 0) | (v < 0) | (w < 0)
    pos = (u > 0) | (v > 0) | (w > 0)
    det = (u + v) + w
    hit = ~(neg & pos) & (det != 0)
    det = xp.where(hit, det, xp.ones_like(det))
    t = ((mul(u, mul(sz, a[2])) + mul(v, mul(sz, b[2]))) + mul(w, mul(sz, c[2]))) / det
    hit = hit & (xp.abs(t) < np.inf)
    return hit, t, u, v, w, det


def watertight_test(o, setup, v0, v1, v2, xp=np):
    """Woop-Benthin-Wald watertight test of rays against triangles (broadcasting, float32).

    o (..., 3) ray origins, `setup` from `ray_setup` (shapes (...)), v0, v1, v2 (..., 3) vertices;
    returns (hit, t, b1, b2) with shapes (...). hit is True for front and back faces; t is not
    range-checked (the caller compares it with its tnear/tfar). The same expressions (in the same
    order) as the JAX traversal; see the module docstring for the edge functions."""
    kx, ky, kz, sx, sy, sz, ok = setup

    def rel(p):
        q0, q1, q2 = p[..., 0] - o[..., 0], p[..., 1] - o[..., 1], p[..., 2] - o[..., 2]
        return _pick(q0, q1, q2, kx, xp), _pick(q0, q1, q2, ky, xp), _pick(q0, q1, q2, kz, xp)

    hit, t, _u, v, w, det = _woop_core(rel(v0), rel(v1), rel(v2), sx, sy, sz, xp)
    return hit & ok, t, v / det, w / det


def barycentrics(o, d, v0, v1, v2, xp=np, mul=operator.mul):
    """Barycentric weights (b1, b2) of the point where the ray (o, d) meets the plane of (v0, v1,
    v2), by Moller-Trumbore (edges from v0: its error grows with |o - v0| / edge length rather than
    with |o|^2 / area as the watertight test's ratios do), clamped into the triangle. mul: as in
    `_woop_core`."""
    e1 = [v1[..., i] - v0[..., i] for i in range(3)]
    e2 = [v2[..., i] - v0[..., i] for i in range(3)]
    s = [o[..., i] - v0[..., i] for i in range(3)]
    dd = [d[..., i] for i in range(3)]

    def cross(a, b):
        return (mul(a[1], b[2]) - mul(a[2], b[1]), mul(a[2], b[0]) - mul(a[0], b[2]), mul(a[0], b[1]) - mul(a[1], b[0]))

    def dot(a, b):
        return (mul(a[0], b[0]) + mul(a[1], b[1])) + mul(a[2], b[2])

    p = cross(dd, e2)
    det = dot(e1, p)
    q = cross(s, e1)
    ok = det != 0
    det = xp.where(ok, det, xp.ones_like(det))
    b1 = xp.clip(xp.where(ok, dot(s, p) / det, 0), 0, 1)
    b2 = xp.clip(xp.where(ok, dot(dd, q) / det, 0), 0, 1)
    over = b1 + b2
    scale = xp.where(over > 1, 1 / xp.where(over > 1, over, 1), 1)
    return b1 * scale, b2 * scale


def valid_triangles(tri: np.ndarray) -> np.ndarray:
    """(T, 3, 3) float32 vertices -> bool (T,): finite and of nonzero area (cross product of the
    float32 edges, evaluated in float64, not exactly zero)."""
    return _valid_and_normal(np.asarray(tri).astype(np.float64))[0]


def _valid_and_normal(t64: np.ndarray):
    """(`valid_triangles`, the unnormalised face normals (T, 3)) of the triangles (T, 3, 3) as
    float64."""
    n = cross_rows(t64[:, 1] - t64[:, 0], t64[:, 2] - t64[:, 0])
    return np.isfinite(t64).all(axis=(1, 2)) & (np.abs(n).max(axis=1) > 0), n


# --------------------------------------------------------------------------------------------------
# build (NumPy)


def _as_mesh(vertices, triangles):
    v = np.asarray(vertices)
    f = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3 or not np.issubdtype(v.dtype, np.number):
        raise InputError(f"vertices must be a (V, 3) float array, got shape {v.shape} dtype {v.dtype}")
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise InputError(f"triangles must be a (T, 3) integer array, got shape {f.shape} dtype {f.dtype}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise InputError(f"triangle indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
    return v.astype(F32), f.astype(np.int64)


def _area(lo, hi):
    e = np.maximum(hi - lo, 0.0)
    return 2.0 * (e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0])


def _segments(starts, counts):
    """For nodes with element ranges [start, start+count): (segment id, position) per element."""
    seg = np.repeat(np.arange(len(counts)), counts)
    offs = np.cumsum(counts) - counts
    pos = starts[seg] + (np.arange(seg.size) - offs[seg])
    return seg, pos


def _seg_min_max(seg, k, x):
    """Per-segment min and max of x (E, 3) -> (k, 3), (k, 3) (1-D ufunc.at per column: fast)."""
    mn = np.full((3, k), np.inf)
    mx = np.full((3, k), -np.inf)
    for a in range(3):
        np.minimum.at(mn[a], seg, x[:, a])
        np.maximum.at(mx[a], seg, x[:, a])
    return mn.T, mx.T


def _seg_min_max_t(seg, k, x, op):
    """Per-segment op (np.minimum or np.maximum) of x (E, 3) -> (3, k), component-major."""
    out = np.full((3, k), np.inf if op is np.minimum else -np.inf)
    for a in range(3):
        op.at(out[a], seg, x[:, a])
    return out


def _area_t(lo, hi):
    """Surface area of boxes given component-major: lo, hi (3, ...)."""
    e = np.maximum(hi - lo, 0.0)
    return 2.0 * (e[0] * e[1] + e[1] * e[2] + e[2] * e[0])


def _build_tree(lo, hi, leaf_size, bins, c_trav=1.0, c_isect=1.0):
    """Binned SAH, level by level. lo, hi (n, 3) float64 triangle boxes. Returns
    (order, node_lo, node_hi, node_start, node_count, node_left, depth): node_left[i] = index of
    the left child (right = left + 1) or -1 for a leaf, whose triangles are order[start:start+count]."""
    n = len(lo)
    cen = 0.5 * (lo + hi)
    order = np.arange(n)
    n_lo, n_hi = [lo.min(0, initial=np.inf)[None]], [hi.max(0, initial=-np.inf)[None]]
    n_start, n_count = [np.zeros(1, np.int64)], [np.array([n], np.int64)]
    open_ids = np.array([0])
    starts, counts, boxes_lo, boxes_hi = n_start[0], n_count[0], n_lo[0], n_hi[0]
    total = 1
    depth = 0
    level_left = []
    while open_ids.size:
        k = open_ids.size
        seg, pos = _segments(starts, counts)
        idx = order[pos]
        c, tlo, thi = cen[idx], lo[idx], hi[idx]
        cmin, cmax = _seg_min_max(seg, k, c)
        ext = cmax - cmin
        best_cost = np.full(k, np.inf)
        best_axis = np.zeros(k, np.int64)
        best_bin = np.zeros(k, np.int64)
        elem_bins = np.empty((1, seg.size), np.int64)
        big = int(counts.max())  # small nodes: fewer bins (16 -> 8 -> 4)
        nb = bins if big > 4 * bins else max(2, bins // 2) if big > bins else max(2, bins // 4)
        # bins along each node's widest centroid extent only (3x cheaper than all three axes;
        # measured on icospheres: as good, 12.5 traversal steps per primary ray against 13.0)
        widest = np.argmax(ext, 1)
        for a in [0]:
            e = ext[np.arange(k), widest]
            inv = np.where(e > 0, nb / np.where(e > 0, e, 1.0), 0.0)
            ax_e = widest[seg]
            b = np.minimum(((c[np.arange(seg.size), ax_e] - cmin[seg, ax_e]) * inv[seg]).astype(np.int64), nb - 1)
            elem_bins[a] = b
            key = b * k + seg  # bin-major: the per-bin slices below are contiguous
            cnt = np.bincount(key, minlength=k * nb).reshape(nb, k)
            blo = _seg_min_max_t(key, k * nb, tlo, np.minimum).reshape(3, nb, k)
            bhi = _seg_min_max_t(key, k * nb, thi, np.maximum).reshape(3, nb, k)
            plo, phi, slo, shi = blo.copy(), bhi.copy(), blo.copy(), bhi.copy()
            for j in range(1, nb):  # prefix and suffix bounds, one bin at a time
                np.minimum(plo[:, j - 1], plo[:, j], out=plo[:, j])
                np.maximum(phi[:, j - 1], phi[:, j], out=phi[:, j])
                np.minimum(slo[:, nb - j], slo[:, nb - j - 1], out=slo[:, nb - j - 1])
                np.maximum(shi[:, nb - j], shi[:, nb - j - 1], out=shi[:, nb - j - 1])
            pc = np.cumsum(cnt, 0)
            nl, nr = pc[:-1], pc[-1:] - pc[:-1]
            with np.errstate(invalid="ignore"):
                cost = _area_t(plo[:, :-1], phi[:, :-1]) * nl + _area_t(slo[:, 1:], shi[:, 1:]) * nr
            cost = np.where((nl > 0) & (nr > 0), cost, np.inf).T  # (k, nb - 1)
            i = np.argmin(cost, 1)
            cbest = cost[np.arange(k), i]
            better = cbest < best_cost
            best_cost = np.where(better, cbest, best_cost)
            best_axis = np.where(better, a, best_axis)
            best_bin = np.where(better, i, best_bin)
        area = _area(boxes_lo, boxes_hi)
        split_cost = c_trav * area + c_isect * best_cost
        leaf_cost = c_isect * counts * area
        small = counts <= leaf_size
        make_leaf = small & ((counts <= 1) | ~(split_cost < leaf_cost))
        split = ~make_leaf
        median = split & (~np.isfinite(best_cost) | (depth >= _MEDIAN_DEPTH))
        left_ids = np.full(k, -1, np.int64)
        if split.any():
            ssplit = split[seg]
            go_right = elem_bins[best_axis[seg], np.arange(seg.size)] > best_bin[seg]
            # object median along the widest centroid extent (identical centroids: any half)
            med = median[seg]
            if med.any():
                ax = np.argmax(ext, 1)
                mseg = np.nonzero(med)[0]
                sub = np.lexsort((c[mseg, ax[seg[mseg]]], seg[mseg]))
                rank = np.empty(mseg.size, np.int64)
                rank[sub] = np.arange(mseg.size)
                cnt_seg = np.bincount(seg[mseg], minlength=k)
                first_of_seg = np.cumsum(cnt_seg) - cnt_seg
                mrank = rank - first_of_seg[seg[mseg]]
                go_right[mseg] = mrank >= (counts[seg[mseg]] // 2)
            left = ssplit & ~go_right
            right = ssplit & go_right
            nl = np.bincount(seg, weights=left, minlength=k).astype(np.int64)
            lc = np.cumsum(left) - left
            rc = np.cumsum(right) - right
            seg_first = np.cumsum(counts) - counts
            lc = lc - lc[seg_first][seg] if seg.size else lc
            rc = rc - rc[seg_first][seg] if seg.size else rc
            newpos = starts[seg] + np.where(left, lc, nl[seg] + rc)
            sel = ssplit
            order[newpos[sel]] = idx[sel]
            sids = np.nonzero(split)[0]
            m = sids.size
            left_ids[sids] = total + 2 * np.arange(m)
            ch_start = np.empty(2 * m, np.int64)
            ch_count = np.empty(2 * m, np.int64)
            ch_start[0::2] = starts[sids]
            ch_count[0::2] = nl[sids]
            ch_start[1::2] = starts[sids] + nl[sids]
            ch_count[1::2] = counts[sids] - nl[sids]
            cseg, cpos = _segments(ch_start, ch_count)
            cidx = order[cpos]
            clo = _seg_min_max(cseg, 2 * m, lo[cidx])[0]
            chi = _seg_min_max(cseg, 2 * m, hi[cidx])[1]
            n_lo.append(clo)
            n_hi.append(chi)
            n_start.append(ch_start)
            n_count.append(ch_count)
            new_open = np.arange(total, total + 2 * m)
            starts, counts, boxes_lo, boxes_hi = ch_start, ch_count, clo, chi
            total += 2 * m
        else:
            new_open = np.zeros(0, np.int64)
        level_left.append((open_ids, left_ids))
        open_ids = new_open
        depth += 1
    node_left = np.full(total, -1, np.int64)
    for ids, lefts in level_left:
        node_left[ids] = lefts
    return (
        order,
        np.concatenate(n_lo),
        np.concatenate(n_hi),
        np.concatenate(n_start),
        np.concatenate(n_count),
        node_left,
        depth,
    )


def _next_pow2(x: int) -> int:
    return 1 << max(0, int(x) - 1).bit_length()


def build_bvh(vertices, triangles, *, leaf_size: int = 2, bins: int = 16, bucket: bool = True, min_triangles: int = 0,
              keep_degenerate: bool = False) -> BVH:
    """Build the BVH of a triangle mesh on the host (NumPy arrays in the result; `BVH.to_device`
    moves them). vertices (V, 3) float, triangles (T, 3) int (rows are the triangle ids reported
    by the traversal). Zero-area and non-finite triangles are left out; with keep_degenerate=True
    only non-finite ones (a tree to be refitted to other positions, `refit_bvh`, where a triangle
    without area now may have some then; the ray test misses it while it has none).

    bucket: pad the node and triangle arrays to powers of two (at least `min_triangles`) and the
    stack to a multiple of 16 (at least 32), so that meshes of similar size share one compiled
    traversal; pass the largest mesh's size as min_triangles to give all meshes the same shapes."""
    if not 1 <= leaf_size <= 64:
        raise InputError(f"leaf_size must be in [1, 64], got {leaf_size}")
    v, f = _as_mesh(vertices, triangles)
    tri_all = v[f]  # (T, 3, 3) float32
    ids = np.nonzero(np.isfinite(tri_all).all(axis=(1, 2)) if keep_degenerate else valid_triangles(tri_all))[0]
    tri = tri_all[ids]
    t64 = tri.astype(np.float64)
    lo, hi = t64.min(1), t64.max(1)
    order, n_lo, n_hi, n_start, n_count, n_left, depth = _build_tree(lo, hi, leaf_size, bins)
    # flatten: inner nodes only, renumbered in creation order (root first)
    inner = np.nonzero(n_left >= 0)[0]
    if inner.size == 0:  # the root is a leaf (or the mesh is empty): one inner node, child 1 empty
        m = 1
        lo_c = np.empty((1, 2, 3))
        hi_c = np.empty((1, 2, 3))
        lo_c[0, 0], hi_c[0, 0] = n_lo[0], n_hi[0]
        lo_c[0, 1], hi_c[0, 1] = np.inf, -np.inf
        child = np.array([[0 if len(ids) else -1, -1]], np.int64)
        count = np.array([[len(ids), 0]], np.int64)
    else:
        m = inner.size
        new_index = np.full(len(n_left), -1, np.int64)
        new_index[inner] = np.arange(m)
        kids = np.stack([n_left[inner], n_left[inner] + 1], 1)  # (m, 2) old ids
        lo_c, hi_c = n_lo[kids], n_hi[kids]
        is_inner = n_left[kids] >= 0
        child = np.where(is_inner, new_index[kids], n_start[kids])
        count = np.where(is_inner, 0, n_count[kids])
        empty = ~is_inner & (n_count[kids] == 0)
        child = np.where(empty, -1, child)
        lo_c = np.where(empty[..., None], np.inf, lo_c)
        hi_c = np.where(empty[..., None], -np.inf, hi_c)
    with np.errstate(invalid="ignore", over="ignore"):
        lo32 = np.nextafter(lo_c.astype(F32), F32(-np.inf))
        hi32 = np.nextafter(hi_c.astype(F32), F32(np.inf))
    n_tri = len(ids)
    m_pad = _next_pow2(max(m, min_triangles)) if bucket else m
    t_pad = _next_pow2(max(n_tri, min_triangles) + leaf_size) if bucket else n_tri + leaf_size
    stack = depth + 2
    stack = max(32, -(-stack // 16) * 16) if bucket else stack

    def pad(a, rows, fill):
        out = np.full((rows,) + a.shape[1:], fill, a.dtype)
        out[: len(a)] = a
        return out

    nodes = np.concatenate([lo32[:, 0], hi32[:, 0], lo32[:, 1], hi32[:, 1]], axis=1).astype(F32)
    empty_node = np.array([np.inf] * 3 + [-np.inf] * 3 + [np.inf] * 3 + [-np.inf] * 3, F32)
    links = np.concatenate([child, count], axis=1).astype(np.int32)
    tri_sorted = tri[order].reshape(-1, 9) if n_tri else np.zeros((0, 9), F32)
    nodes_p = np.tile(empty_node, (m_pad, 1))
    nodes_p[:m] = nodes
    links_p = np.tile(np.array([-1, -1, 0, 0], np.int32), (m_pad, 1))
    links_p[:m] = links
    return BVH(
        nodes=nodes_p,
        links=links_p,
        tri=pad(tri_sorted.astype(F32), t_pad, 0.0),
        prim=pad(ids[order].astype(np.int32), t_pad, -1),
        stack=np.zeros(stack, np.int32),
        lanes=np.arange(leaf_size, dtype=np.int32),
    )
def refit_bvh(bvh: BVH, vertices, triangles) -> BVH:
    """The BVH's tree with its triangles moved to `vertices` (V, 3) (the same `triangles` (T, 3) it
    was built from, ids unchanged): the rows' vertices gathered again and every box recomputed
    bottom-up, rounded outwards as `build_bvh` rounds them. In JAX (jit-able, on any backend, no
    host round trip): for meshes that deform (a fit's vertices, a skinned pose) the tree built once
    on the host is kept and refitted in the program. Traversal of the result answers exactly as a
    tree built at `vertices` would (the boxes bound their triangles); only its speed degrades as
    the shape departs from the one the tree was built for. Build it with keep_degenerate=True: a
    triangle left out at build time is never hit. No gradients (visibility has none)."""
    bvh = _as_bvh(bvh)
    vertices = jax.lax.stop_gradient(jnp.asarray(vertices, jnp.float32))
    prim = bvh.prim
    live = prim >= 0
    v = vertices[jnp.asarray(triangles, jnp.int32)[jnp.maximum(prim, 0)]]  # (R, 3, 3)
    tri = jnp.where(live[:, None], v.reshape(-1, 9), jnp.asarray(bvh.tri, jnp.float32))
    inf = jnp.float32(jnp.inf)
    row_lo = jnp.where(live[:, None], v.min(1), inf)
    row_hi = jnp.where(live[:, None], v.max(1), -inf)
    child, count = bvh.links[:, :2], bvh.links[:, 2:]
    inner = (count == 0) & (child >= 0)
    # A leaf child's box: the union of its rows (at most leaf_size); an empty child's is empty.
    rows = jnp.clip(child[..., None] + jnp.arange(bvh.leaf_size), 0, prim.shape[0] - 1)  # (M, 2, L)
    in_leaf = (~inner[..., None] & (jnp.arange(bvh.leaf_size) < count[..., None]))[..., None]
    leaf_lo = jnp.min(jnp.where(in_leaf, row_lo[rows], inf), axis=2)  # (M, 2, 3)
    leaf_hi = jnp.max(jnp.where(in_leaf, row_hi[rows], -inf), axis=2)
    kid = jnp.maximum(child, 0)

    def children(node_lo, node_hi):
        return (jnp.where(inner[..., None], node_lo[kid], leaf_lo), jnp.where(inner[..., None], node_hi[kid], leaf_hi))

    def body(state):
        k, lo, hi, _ = state
        c_lo, c_hi = children(lo, hi)
        new_lo, new_hi = c_lo.min(1), c_hi.max(1)
        return k + 1, new_lo, new_hi, jnp.any(new_lo != lo) | jnp.any(new_hi != hi)

    # Every node's box from its children's, over and over: exact after as many rounds as the tree
    # is deep (the stack is deeper than the tree), and stopped when a round changes nothing.
    M = child.shape[0]
    state = (jnp.int32(0), jnp.full((M, 3), inf), jnp.full((M, 3), -inf), jnp.bool_(True))
    _, lo, hi, _ = jax.lax.while_loop(lambda s: s[3] & (s[0] <= bvh.stack_size), body, state)
    c_lo, c_hi = children(lo, hi)
    c_lo, c_hi = jnp.nextafter(c_lo, -inf), jnp.nextafter(c_hi, inf)
    nodes = jnp.concatenate([c_lo[:, 0], c_hi[:, 0], c_lo[:, 1], c_hi[:, 1]], axis=1)
    return BVH(nodes=nodes, links=bvh.links, tri=tri, prim=prim, stack=bvh.stack, lanes=bvh.lanes)


# --------------------------------------------------------------------------------------------------
# traversal (JAX)


def _ray_consts(o, d, tnear, tfar, after):
    """Per-ray constants packed for one gather each: (N, 16) float32 [o xyz, o along kx ky kz,
    1/d xyz (zero components -> +-1e30), sx sy sz, tnear, tfar, 0] and (N, 4) int32 [kx ky kz
    after]. A ray with an unusable direction gets tfar = -inf: it ends at the root, hitting nothing."""
    kx, ky, kz, sx, sy, sz, ok = ray_setup(d, jnp)
    oc = [o[..., i] for i in range(3)]
    inv = []
    for i in range(3):
        di = d[..., i]
        tiny = jnp.where(jnp.signbit(di), -jnp.float32(_TINY_DIR), jnp.float32(_TINY_DIR))
        inv.append(jnp.float32(1.0) / jnp.where(di == 0, tiny, di))
    tfar = jnp.where(ok, tfar, -jnp.inf)
    okk = [_pick(*oc, k, jnp) for k in (kx, ky, kz)]
    rf = jnp.stack(oc + okk + inv + [sx, sy, sz, tnear, tfar, jnp.zeros_like(tnear)], -1)
    ri = jnp.stack([kx, ky, kz, after], -1).astype(jnp.int32)
    return rf.astype(jnp.float32), ri


_NONE = np.iinfo(np.int32).max  # "no hit yet" in the (t, id) comparison


def _step(bvh: BVH, rf, ri, st, any_hit: bool):
    """One traversal step of one ray: test the two children of the current inner node, intersect
    the triangles of the leaf children that are hit, then go to the nearer inner child (pushing the
    farther) or pop. st = (node, sp, stack, best_t, best_id, best_row); node < 0: finished."""
    o, ok, inv, s = (rf[0], rf[1], rf[2]), (rf[3], rf[4], rf[5]), (rf[6], rf[7], rf[8]), (rf[9], rf[10], rf[11])
    tnear, tfar = rf[12], rf[13]
    k, after = (ri[0], ri[1], ri[2]), ri[3]
    node, sp, stack, bt, bp, brow = st
    nd = bvh.nodes[node]
    ln = bvh.links[node]
    grow = jnp.float32(_BOX_GROW)
    tmin, tmax = [], []
    for j in range(2):
        t0 = [(nd[6 * j + i] - o[i]) * inv[i] for i in range(3)]
        t1 = [(nd[6 * j + 3 + i] - o[i]) * inv[i] for i in range(3)]
        near = jnp.maximum(jnp.maximum(jnp.minimum(t0[0], t1[0]), jnp.minimum(t0[1], t1[1])), jnp.minimum(t0[2], t1[2]))
        far = jnp.minimum(jnp.minimum(jnp.maximum(t0[0], t1[0]), jnp.maximum(t0[1], t1[1])), jnp.maximum(t0[2], t1[2]))
        tmin.append(jnp.maximum(near, tnear))
        tmax.append(far * grow)
    child = (ln[0], ln[1])
    count = (ln[2], ln[3])
    # the triangles of both leaf children at once, as a (2L,) axis (masked)
    hit_leaf = [(count[j] > 0) & (tmin[j] <= jnp.minimum(tmax[j], bt)) for j in range(2)]
    rows = jnp.concatenate([jnp.maximum(child[0], 0) + bvh.lanes, jnp.maximum(child[1], 0) + bvh.lanes])
    live = jnp.concatenate([hit_leaf[0] & (bvh.lanes < count[0]), hit_leaf[1] & (bvh.lanes < count[1])])
    flat = bvh.tri.reshape(-1)
    base = rows * 9
    verts = [tuple(flat[base + (3 * v) + k[i]] - ok[i] for i in range(3)) for v in range(3)]
    hit, t, *_ = _woop_core(*verts, *s, jnp)
    pid = bvh.prim[rows]
    good = live & hit & (t >= tnear) & (t <= tfar) & (pid != after) & ((t > tnear) | (pid > after))
    if any_hit:
        found = jnp.any(good)
    else:
        found = jnp.bool_(False)
        tt = jnp.where(good, t, jnp.inf)
        tm = jnp.min(tt)
        pm = jnp.min(jnp.where(good & (tt == tm), pid, _NONE))
        rm = jnp.min(jnp.where(good & (tt == tm) & (pid == pm), rows, _NONE))
        better = jnp.any(good) & ((tm < bt) | ((tm == bt) & (pm < bp)))
        bt = jnp.where(better, tm, bt)
        bp = jnp.where(better, pm, bp)
        brow = jnp.where(better, rm, brow)
    if any_hit:
        bt = jnp.where(found, -jnp.inf, bt)
    inner = [(count[j] == 0) & (child[j] >= 0) & (tmin[j] <= jnp.minimum(tmax[j], bt)) for j in range(2)]
    near0 = tmin[0] <= tmin[1]
    both = inner[0] & inner[1]
    near_c = jnp.where(near0, child[0], child[1])
    far_c = jnp.where(near0, child[1], child[0])
    nxt = jnp.where(both, near_c, jnp.where(inner[0], child[0], jnp.where(inner[1], child[1], -1)))
    stack = stack.at[jnp.where(both, sp, stack.shape[0])].set(far_c, mode="drop")
    sp = sp + both.astype(sp.dtype)
    can_pop = (nxt < 0) & (sp > 0)
    nxt = jnp.where(can_pop, stack[jnp.maximum(sp - 1, 0)], nxt)
    sp = sp - can_pop.astype(sp.dtype)
    nxt = jnp.where(found, -1, nxt)
    return nxt, sp, stack, bt, bp, brow


def _trace(bvh: BVH, rf, ri, lanes: int, any_hit: bool):
    """Trace the rays (rf, ri from `_ray_consts`) with `lanes` traversals in flight: one while loop
    steps all lanes; a lane whose ray is finished writes its result and takes the next ray from the
    queue, so a slow ray does not hold the others up (as it would in a vmapped per-ray loop).
    Returns (t, id, row), each (N,)."""
    n = rf.shape[0]
    c = max(1, min(int(lanes), n))
    step = jax.vmap(lambda f, i, st: _step(bvh, f, i, st, any_hit))

    def fresh(f):
        m = f.shape[0]
        z = jnp.zeros(m, jnp.int32)
        return (z, z, f[:, 13], jnp.full(m, _NONE, jnp.int32), z)

    lane_ray = jnp.arange(c, dtype=jnp.int32)
    f0, i0 = rf[:c], ri[:c]
    out = jnp.zeros((n, 3), jnp.int32)
    stack = jnp.zeros((c, bvh.stack_size), jnp.int32)  # not reset between rays: sp = 0 suffices
    state = (lane_ray, jnp.int32(c), f0, i0, fresh(f0), stack, out)

    def cond(s):
        return jnp.any(s[0] >= 0)

    def body(s):
        lane_ray, nxt, f, i, st, stack, out = s
        node, sp, stack, bt, bp, brow = step(f, i, st[:2] + (stack,) + st[2:])
        st = (node, sp, bt, bp, brow)
        done = (lane_ray >= 0) & (st[0] < 0)
        res = jnp.stack([jax.lax.bitcast_convert_type(bt, jnp.int32), bp, brow], -1)
        out = out.at[jnp.where(done, lane_ray, n)].set(res, mode="drop")
        rank = jnp.cumsum(done, dtype=jnp.int32) - 1
        new = nxt + rank
        load = done & (new < n)
        lane_ray = jnp.where(load, new, jnp.where(done, -1, lane_ray))
        nxt = nxt + jnp.sum(done, dtype=jnp.int32)
        src = jnp.where(load, new, 0)
        f_new, i_new = rf[src], ri[src]
        f = jnp.where(load[:, None], f_new, f)
        i = jnp.where(load[:, None], i_new, i)
        st = tuple(jnp.where(load.reshape((-1,) + (1,) * (a.ndim - 1)), b, a) for a, b in zip(st, fresh(f_new)))
        return lane_ray, nxt, f, i, st, stack, out

    out = jax.lax.while_loop(cond, body, state)[-1]
    return jax.lax.bitcast_convert_type(out[:, 0], jnp.float32), out[:, 1], out[:, 2]


def _prep(origins, directions, tnear, tfar, after):
    """Flatten the rays: (shape, o, d (N, 3) float32, tnear, tfar (N,) float32, after (N,) int32,
    ob, db (N, 3) in the origins' float dtype, for the barycentrics)."""
    o_in, d_in = jnp.asarray(origins), jnp.asarray(directions)
    if o_in.shape[-1:] != (3,) or d_in.shape[-1:] != (3,):
        raise InputError(f"origins and directions must be (..., 3), got {o_in.shape} and {d_in.shape}")
    dt = o_in.dtype if jnp.issubdtype(o_in.dtype, jnp.floating) else jnp.float32
    dt = jnp.promote_types(dt, jnp.float32)
    shape = jnp.broadcast_shapes(o_in.shape, d_in.shape)[:-1]
    ob = jnp.broadcast_to(o_in.astype(dt), shape + (3,)).reshape(-1, 3)
    db = jnp.broadcast_to(d_in.astype(dt), shape + (3,)).reshape(-1, 3)
    n = ob.shape[0]
    tn = jnp.broadcast_to(jnp.asarray(tnear, jnp.float32), shape).reshape(n)
    tf = jnp.broadcast_to(jnp.asarray(tfar, jnp.float32), shape).reshape(n)
    af = jnp.broadcast_to(jnp.asarray(after, jnp.int32), shape).reshape(n)
    return shape, ob.astype(jnp.float32), db.astype(jnp.float32), tn, tf, af, ob, db


def _as_bvh(bvh) -> BVH:
    return BVH(*(jnp.asarray(a) for a in bvh))


def _hits(bvh: BVH, o, d, t, p, row) -> Hits:
    """Hits from the traversal's (t, id, row); barycentrics by Moller-Trumbore in o's dtype."""
    miss = p == _NONE
    tri = bvh.tri[row].astype(o.dtype)
    b1, b2 = barycentrics(o, d, tri[:, 0:3], tri[:, 3:6], tri[:, 6:9], jnp)
    zero = jnp.zeros((), o.dtype)
    return Hits(
        t=jnp.where(miss, jnp.inf, t),
        prim=jnp.where(miss, -1, p),
        b1=jnp.where(miss, zero, b1),
        b2=jnp.where(miss, zero, b2),
    )


def intersect_bvh(bvh: BVH, origins, directions, tnear=0.0, tfar=np.inf, after_prim=-1, *, lanes: int = DEFAULT_LANES) -> Hits:
    """Closest hits of rays against a BVH (tracer-friendly; jit it or call it inside a jit).

    origins, directions (..., 3) (any float dtype, used in float32; directions need not be unit
    length, t is in units of |direction|); tnear, tfar, after_prim scalars or (...). A triangle hit
    (t, id) counts when tnear <= t <= tfar, id != after_prim and (t, id) > (tnear, after_prim)
    lexicographically; the least such (t, id) is returned. after_prim = -1 gives the plain closest
    hit in [tnear, tfar]; the previous hit's (t, prim) gives the next hit along the ray.
    `lanes`: rays in flight at once (memory ~ lanes * stack size)."""
    bvh = _as_bvh(bvh)
    shape, o, d, tn, tf, af, ob, db = _prep(origins, directions, tnear, tfar, after_prim)
    n = o.shape[0]
    if n == 0:
        z = jnp.zeros(shape, jnp.float32)
        return Hits(z + jnp.inf, jnp.zeros(shape, jnp.int32) - 1, z, z)
    t, p, row = _trace(bvh, *_ray_consts(o, d, tn, tf, af), lanes, False)
    h = _hits(bvh, ob, db, t, p, row)
    return Hits(*(x.reshape(shape) for x in h))


def occluded_bvh(bvh: BVH, origins, directions, tnear=0.0, tfar=np.inf, *, lanes: int = DEFAULT_LANES):
    """Whether each ray hits any triangle with tnear <= t <= tfar: bool (...). Stops at the first
    hit found (any-hit). Tracer-friendly."""
    bvh = _as_bvh(bvh)
    shape, o, d, tn, tf, af, _ob, _db = _prep(origins, directions, tnear, tfar, -1)
    n = o.shape[0]
    if n == 0:
        return jnp.zeros(shape, bool)
    rf, ri = _ray_consts(o, d, tn, tf, af)
    t, _, _ = _trace(bvh, rf, ri, lanes, True)
    # A hit sets t to -inf; a ray that starts there (an unusable direction, or tfar = -inf: an empty
    # range) hits nothing.
    return ((t == -jnp.inf) & (rf[:, 13] > -jnp.inf)).reshape(shape)


def first_k_hits_bvh(bvh: BVH, origins, directions, k: int, tnear=0.0, tfar=np.inf, *, lanes: int = DEFAULT_LANES) -> Hits:
    """The k first hits of each ray in (t, id) order, as Hits of shape (..., k) (missing layers:
    t = inf, prim = -1, b = 0): k traces, each continuing from the previous hit's (t, id), so each
    triangle on the ray is reported once (coplanar overlapping triangles too, in id order)."""
    bvh = _as_bvh(bvh)
    shape, o, d, tn, tf, af, ob, db = _prep(origins, directions, tnear, tfar, -1)
    n = o.shape[0]
    if n == 0 or k == 0:
        z = jnp.zeros(shape + (k,), jnp.float32)
        return Hits(z + jnp.inf, jnp.zeros(shape + (k,), jnp.int32) - 1, z, z)
    rays_f, rays_i = _ray_consts(o, d, tn, tf, af)

    def layer(carry, _):
        # one trace per layer, continuing from the previous hit's (t, id); a ray that has run out
        # of hits gets an empty range (tfar = -inf): it ends at the root
        t_prev, p_prev = carry
        done = p_prev == _NONE
        f = rays_f.at[:, 12].set(t_prev).at[:, 13].set(jnp.where(done, -jnp.inf, rays_f[:, 13]))
        i = rays_i.at[:, 3].set(jnp.where(done, -1, p_prev))
        t, p, row = _trace(bvh, f, i, lanes, False)
        return (t, p), (t, p, row)

    _, (t, p, row) = jax.lax.scan(layer, (tn, af), None, length=int(k))  # (k, N) each
    h = _hits(bvh, jnp.tile(ob, (int(k), 1)), jnp.tile(db, (int(k), 1)), t.reshape(-1), p.reshape(-1), row.reshape(-1))
    return Hits(*(jnp.moveaxis(x.reshape((int(k), n)), 0, -1).reshape(shape + (int(k),)) for x in h))


def pad_rays(n: int, minimum: int = 1024) -> int:
    """The power-of-two bucket (>= minimum) a ray count is padded to, so that the traversal is
    compiled once per bucket rather than once per count."""
    return max(int(minimum), _next_pow2(int(n)))
