"""Silhouettes and occlusion edges: analytic antialiasing of a pass, and with it the image's
derivative with respect to where the edges are.

A pass samples each pixel once (at the pass's sub-pixel offset), so a visibility edge is a step
between two neighbouring samples and moving it changes nothing until it crosses a sample: the
sampled image has no derivative with respect to the edge. Here every pair of neighbouring samples
(horizontal and vertical) that sees two different surfaces is examined: if an edge of the nearer
surface's outline -- a mesh triangle's edge whose neighbour across it faces the other way or does
not exist, a sphere's contour, a plane's horizon -- crosses the segment between the two samples at
a fraction `a` of it, the sample whose cell the edge enters takes the other one's colour in
proportion to the part of its cell beyond the edge (Laine et al., "Modular Primitives for
High-Performance Differentiable Rendering", SIGGRAPH Asia 2020, section 4: analytic antialiasing).
`a` is computed from the edge's vertices (or the sphere's centre and radius, the plane's normal)
and the camera in the trace, so gradients reach them through the blend.

With s x s sub-pixel samples (`Camera.supersample`) each sample stands for a cell 1/s of a pixel
wide, centred on it; an edge at distance `a` (pixels) from a sample inside that sample's cell
(a < 1/(2s)) moves (1/(2s) - a) s of the cell to the other side. Averaged over the s^2 passes
this is the coverage of the pixel's area by each side to first order (exact for a straight edge
crossing a cell from side to side), and its derivative is the edge's motion times the colour
step, integrated over the edge's length in the pixel: the gradient of the box-filtered image.

Each edge is taken by the pairs across its major direction only -- horizontal pairs for edges
steeper than 45 degrees, vertical ones for the others (as the paper does): a slanted edge crosses
both kinds of pairs, and counted twice it would blend twice.

The test whether a pair crosses a triangle's edge is the triangle's edge functions along the
segment between the two samples' rays: with the camera's rays interpolated linearly on the image
plane (the unnormalised perspective directions, or the orthographic origins), each edge function
E_i = ((V_j - o) x (V_k - V_j)) . d is linear in the fraction, exact also for vertices behind the
camera (Olano and Greer 1997), and the first edge whose function changes sign is where the
segment leaves the triangle. A triangle's neighbours across its edges come from the mesh's
topology with vertices welded by position (`edge_neighbours`), so UV and normal seams are not
outlines.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
import itertools
import threading

import jax
import jax.numpy as jnp
import numpy as np

from .._numerics import safe_div, safe_sqrt, vcross, vdot
from ..errors import InputError
from .mesh import Mesh, concat_geometry, mesh_parts
from .scene import Plane, Sphere, camera_basis

__all__ = ["antialias_pass", "camera_plane_rays", "edge_neighbours", "neighbours"]


# ------------------------------------------------------------------------------------------
# Topology
# ------------------------------------------------------------------------------------------


def edge_neighbours(positions: np.ndarray, triangles: np.ndarray, *, open_edges: bool = False):
    """(T, 3) int32: for triangle t and edge i (the edge opposite vertex i, from vertex i+1 to i+2),
    the other triangle that shares the edge, or -1 where the edge is on a boundary, is shared by
    three or more triangles, or is degenerate (an outline in every case). Vertices are welded by
    position first (to `WELD_TOLERANCE` of the extent), so the duplicated vertices of texture, normal and
    material seams join their triangles; a corner shared by two coincident vertices on either side
    of a grid line stays split (an outline there: blended where the colours agree anyway).
    open_edges=True: also (T, 3) bool, the edges no other triangle shares (not degenerate), which
    another mesh's may join (`parts_neighbours`)."""
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    tri = np.asarray(triangles, np.int64).reshape(-1, 3)
    T = tri.shape[0]
    if T == 0:
        return (np.zeros((0, 3), np.int32), np.zeros((0, 3), bool)) if open_edges else np.zeros((0, 3), np.int32)
    # Welded on a grid of WELD_TOLERANCE times the mesh's extent: the two copies of a seam vertex
    # are often computed apart (sin(2 pi) is not 0) and differ in their last bits.
    lo_, hi_ = pos.min(0), pos.max(0)
    cell = max(float(np.max(hi_ - lo_)), 1e-30) * WELD_TOLERANCE
    bits = np.rint((pos - lo_) / cell).astype(np.int64)
    order = np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0]))
    srt = bits[order]
    new = np.ones(len(order), bool)
    new[1:] = np.any(srt[1:] != srt[:-1], axis=1)
    weld = np.empty(len(order), np.int64)
    weld[order] = np.cumsum(new) - 1
    w = weld[tri]
    a = w[:, [1, 2, 0]].reshape(-1)
    b = w[:, [2, 0, 1]].reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    n = int(weld.max()) + 1
    key = lo * n + hi
    # A triangle with two welded corners (a UV sphere's poles) has no area: no ray meets it, and
    # its edges would make the real edges beside them look shared three times. Left out.
    flat = np.repeat((w[:, 0] == w[:, 1]) | (w[:, 1] == w[:, 2]) | (w[:, 2] == w[:, 0]), 3)
    key[flat] = -1 - np.arange(int(np.count_nonzero(flat)))  # unique keys: no neighbours
    idx = np.argsort(key, kind="stable")
    ks = key[idx]
    start = np.ones(len(ks), bool)
    start[1:] = ks[1:] != ks[:-1]
    run = np.cumsum(start) - 1
    counts = np.bincount(run)
    pair = counts[run] == 2
    first = start & pair  # the first of each run of exactly two
    out = np.full(3 * T, -1, np.int64)
    i0 = idx[first]
    i1 = idx[np.flatnonzero(first) + 1]
    out[i0] = i1 // 3
    out[i1] = i0 // 3
    if not open_edges:
        return out.reshape(T, 3).astype(np.int32)
    single = np.zeros(3 * T, bool)
    single[idx] = (counts[run] == 1) & (ks >= 0)
    return out.reshape(T, 3).astype(np.int32), single.reshape(T, 3)


def parts_neighbours(positions: np.ndarray, parts, tables) -> np.ndarray:
    """The (T, 3) neighbour table of meshes concatenated (`mesh.mesh_parts` offsets `parts`) from
    each mesh's own (`tables`: (table, open edges) of `edge_neighbours(open_edges=True)` in the
    mesh's ids): the meshes' tables, and an open edge of one mesh joined to an open edge of
    another where their ends weld (on the grid of the whole extent) and no third open edge does."""
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    T = int(parts[-1][1])
    out = np.full((T, 3), -1, np.int32)
    ends, where = [], []
    for (v0, t0), (_, t1), (table, single), tri in tables:
        out[t0:t1] = np.where(table >= 0, table + np.int32(t0), -1)
        r, i = np.nonzero(single)
        if r.size:
            ends.append(np.stack([tri[r, (i + 1) % 3], tri[r, (i + 2) % 3]], 1) + v0)
            where.append(np.stack([r + t0, i, np.full(r.size, t0)], 1))
    if len(ends) < 2:
        return out
    ends, where = np.concatenate(ends), np.concatenate(where)
    lo_, hi_ = pos.min(0), pos.max(0)
    cell = max(float(np.max(hi_ - lo_)), 1e-30) * WELD_TOLERANCE
    bits = np.rint((pos[ends.reshape(-1)] - lo_) / cell).astype(np.int64)
    _, weld = np.unique(bits, axis=0, return_inverse=True)
    weld = weld.reshape(-1, 2)
    _, key, counts = np.unique(np.sort(weld, 1), axis=0, return_inverse=True, return_counts=True)
    key = key.reshape(-1)
    two = np.flatnonzero(counts[key] == 2)
    two = two[np.argsort(key[two], kind="stable")]
    a, b = two[0::2], two[1::2]
    across = where[a, 2] != where[b, 2]  # (two open edges of one mesh stay open)
    a, b = a[across], b[across]
    out[where[a, 0], where[a, 1]] = where[b, 0]
    out[where[b, 0], where[b, 1]] = where[a, 0]
    return out


#: Vertices closer than this fraction of the mesh's extent (on a grid) are one vertex for the
#: topology (`edge_neighbours`); 2^-20: about a micrometre on a one-metre asset.
WELD_TOLERANCE = 2.0 ** -20


class _Neighbours:
    """`edge_neighbours` by content digest: whole scenes' tables in a small LRU (`capacity`), and
    with parts each mesh's own table in another, bounded by its triangles (`mesh_triangles`; a
    million triangles take ~0.4 s)."""

    def __init__(self, capacity: int = 4, mesh_triangles: int = 1 << 23):
        self.capacity = capacity
        self.mesh_triangles = mesh_triangles
        self.entries: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self.meshes: OrderedDict[bytes, tuple] = OrderedDict()
        self.lock = threading.Lock()
        self.computed = 0  # counted by tests: tables computed (whole scenes or single meshes)

    def get(self, positions: np.ndarray, triangles: np.ndarray, parts=None) -> np.ndarray:
        """The table of the arrays; with `parts` (`mesh.mesh_parts`: several meshes) made from
        each mesh's own table, kept per mesh (`parts_neighbours`): a moving mesh beside a static
        set recomputes its own only."""
        positions = np.asarray(positions, np.float32)
        triangles = np.asarray(triangles, np.int32)
        if parts is None or len(parts) < 3:
            key = self._key(b"whole", positions, triangles)
            return self._kept(self.entries, key, lambda: edge_neighbours(positions, triangles), 0)
        from .mesh import part_keys

        keys = part_keys(positions, triangles, parts)
        tables = [((v0, t0), (v1, t1), k, positions[v0:v1], triangles[t0:t1])
                  for ((v0, t0), (v1, t1)), k in zip(itertools.pairwise(parts), keys, strict=True)]
        key = hashlib.blake2b(b"".join([b"parts"] + keys), digest_size=20).digest()

        def assemble():
            own = [(a, b, self._kept(self.meshes, k, lambda p=p, t=t, v0=a[0]: edge_neighbours(p, t - np.int32(v0), open_edges=True),
                                     b[1] - a[1]), t - np.int32(a[0])) for a, b, k, p, t in tables]
            return parts_neighbours(positions, parts, own)

        return self._kept(self.entries, key, assemble, 0)

    @staticmethod
    def _key(tag: bytes, positions, triangles) -> bytes:
        from .mesh import _content_digest

        h = hashlib.blake2b(tag, digest_size=20)
        h.update(np.int64(positions.shape + triangles.shape).tobytes())
        h.update(_content_digest(positions))
        h.update(_content_digest(triangles))
        return h.digest()

    def _kept(self, store: OrderedDict, key: bytes, compute, size: int):
        """store[key], computed by `compute()` when not kept; the mesh store drops its oldest
        tables beyond `mesh_triangles` (size: this one's triangles), the whole one beyond `capacity`."""
        with self.lock:
            if key in store:
                store.move_to_end(key)
                return store[key][0]
        out = compute()
        for a in out if isinstance(out, tuple) else (out,):
            a.setflags(write=False)
        with self.lock:
            self.computed += 1
            store[key] = (out, size)
            if store is self.meshes:
                total = sum(n for _, n in store.values())
                while total > self.mesh_triangles and len(store) > 1:
                    total -= store.popitem(last=False)[1][1]
            else:
                while len(store) > self.capacity:
                    store.popitem(last=False)
        return out


NEIGHBOURS = _Neighbours()


def neighbours(positions, triangles, parts=None):
    """`edge_neighbours` of the meshes' concatenated arrays: computed on the host (and kept per
    content) when they are concrete, through a callback from inside a trace (the positions'
    gradients stopped: the topology has none)."""
    if not isinstance(positions, jax.core.Tracer) and not isinstance(triangles, jax.core.Tracer):
        return jnp.asarray(NEIGHBOURS.get(np.asarray(positions, np.float32), np.asarray(triangles, np.int32), parts))
    pos = jax.lax.stop_gradient(positions).astype(jnp.float32)
    out = jax.ShapeDtypeStruct(triangles.shape, jnp.int32)
    return jax.pure_callback(lambda p, t: NEIGHBOURS.get(np.asarray(p), np.asarray(t), parts), out, pos, triangles,
                             vmap_method="sequential")


def check_topology(nbr, triangles: int) -> None:
    """Refuse a topology (or a structure made with it, `execute.deformable`) made for meshes of
    another triangle count than the scene's `triangles`."""
    made = int(np.shape(nbr)[0])
    if made != triangles:
        raise InputError(f"the scene's meshes have {triangles} triangles; their structure (jaxpbr.deformable) was made for "
                         f"{made}: only the vertices' positions may change. Call jaxpbr.deformable on the new meshes.")


# ------------------------------------------------------------------------------------------
# The camera's rays on the image plane
# ------------------------------------------------------------------------------------------


def camera_plane_rays(cam, dtype, offset):
    """(rays, step_x, step_y): `rays(col, row)` -> (o, d), the rays of the samples of a pass at
    sub-pixel `offset` (+ the camera's jitter) at pixel columns and rows (arrays, broadcast
    together; Vec3s of their shape), with the directions *not* normalised (perspective: the point
    on the image plane at distance 1, so that the rays between two samples are the linear blend of
    theirs), and the change of (o, d) from one pixel to the next along x and along y, each a pair
    of Vec3s (the origin's is zero in perspective, the direction's in orthographic). The same rays
    as `scene.primary_rays` up to the directions' length."""
    pos, fwd, right, up = camera_basis(cam, dtype)
    W, H = cam.width, cam.height
    ortho = cam.projection == "orthographic"
    t = jnp.asarray(cam.ymag, dtype) if ortho else jnp.tan(jnp.deg2rad(jnp.asarray(cam.fov_y_deg, dtype)) / 2)
    jit = jnp.asarray(cam.jitter, dtype)
    sx = 2.0 * t / H  # one pixel on the image plane (square pixels: W/H of the width's tan per W pixels)
    zero = (jnp.zeros((), dtype),) * 3
    step_x = tuple(sx * right[i] for i in range(3))
    step_y = tuple(-sx * up[i] for i in range(3))

    def rays(col, row):
        x = (2.0 * (col.astype(dtype) + offset[0] + jit[0]) / W - 1.0) * t * (W / H)
        y = (1.0 - 2.0 * (row.astype(dtype) + offset[1] + jit[1]) / H) * t
        shape = jnp.broadcast_shapes(x.shape, y.shape)
        if ortho:
            return (tuple(pos[i] + x * right[i] + y * up[i] for i in range(3)), tuple(jnp.broadcast_to(fwd[i], shape) for i in range(3)))
        return tuple(jnp.broadcast_to(pos[i], shape) for i in range(3)), tuple(fwd[i] + x * right[i] + y * up[i] for i in range(3))

    if ortho:
        return rays, (step_x, zero), (step_y, zero)
    return rays, (zero, step_x), (zero, step_y)


# ------------------------------------------------------------------------------------------
# Where a surface's outline crosses the segment between two samples
# ------------------------------------------------------------------------------------------


def _lerp3(a, b, s):
    return tuple(a[i] + s * (b[i] - a[i]) for i in range(3))


def _sub(a, b):
    return tuple(a[i] - b[i] for i in range(3))


def _slope_ok(f, o, d, along, across):
    """Whether the outline given by f(o, d) = 0 at the ray (o, d) runs closer to perpendicular to
    the pairs' direction than to parallel: |df along| >= |df across| (one pixel step each; the
    steps are (d origin, d direction) pairs). Evaluated without gradients (a choice)."""
    o, d = jax.lax.stop_gradient((o, d))

    def change(step):  # central difference: f's derivative along the step exactly (f is at most quadratic)
        (do_, dd_) = step
        fwd = f(tuple(o[i] + 0.5 * do_[i] for i in range(3)), tuple(d[i] + 0.5 * dd_[i] for i in range(3)))
        bwd = f(tuple(o[i] - 0.5 * do_[i] for i in range(3)), tuple(d[i] - 0.5 * dd_[i] for i in range(3)))
        return fwd - bwd

    return jnp.abs(change(along)) >= jnp.abs(change(across))


#: Most triangles the walk along a pair's segment crosses before it gives up (near a silhouette
#: a fine mesh's triangles project to slivers, several between two samples).
MAX_WALK = 8


def _edge_values(P, tris, tri_id, oi, di, oo, do, d_face):
    """Per edge i of the triangles `tri_id` (the edge opposite vertex i), its edge function
    E_i = ((V_j - o) x (V_k - V_j)) . d at the segment's two ends, oriented so that it is positive
    inside the triangle as the ray `d_face` sees it: ([e at inside ray] * 3, [e at outside ray] * 3,
    the triangles' normals). Linear in the fraction along the segment (the rays' origins or
    directions are, not both)."""
    v = [tuple(P[:, c][tris[:, k][tri_id]] for c in range(3)) for k in range(3)]
    n = vcross(_sub(v[1], v[0]), _sub(v[2], v[0]))
    sigma = jnp.where(vdot(n, d_face) >= 0, 1.0, -1.0).astype(di[0].dtype)
    e_in, e_out = [], []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        ejk = _sub(v[k], v[j])
        e_in.append(sigma * vdot(vcross(_sub(v[j], oi), ejk), di))
        e_out.append(sigma * vdot(vcross(_sub(v[j], oo), ejk), do))
    return e_in, e_out, n


def _exit(e_in, e_out, big):
    """(edge, fraction) where the segment leaves the triangle: the first of its edges whose function
    falls through zero along it (an edge whose function does not fall is never left)."""
    taus = [jnp.where(e_out[i] < e_in[i], e_in[i] / jnp.where(e_out[i] < e_in[i], e_in[i] - e_out[i], 1.0), big) for i in range(3)]
    t = jnp.stack(taus, -1)
    return jnp.argmin(t, -1), jnp.min(t, -1)


def _pick(values, i):
    return jnp.where(i == 0, values[0], jnp.where(i == 1, values[1], values[2]))


def _walk(P, rays, tris, nbr, prim):
    """The walk of `_mesh_outline` (no gradients), for lanes (1-D) with prim >= 0: (triangle whose
    edge is the outline, the fraction where the segment entered it, found, edge index); at most
    MAX_WALK steps (a while loop that ends when no lane walks on)."""
    oi, di, oo, do = rays
    dtype = di[0].dtype
    big = jnp.asarray(2.0, dtype)

    def cond(state):
        k, _, _, active, _, _ = state
        return (k < MAX_WALK) & jnp.any(active)

    def body(state):
        k, cur, t_in, active, found, edge = state
        d_face = _lerp3(di, do, t_in)
        e_in, e_out, n_cur = _edge_values(P, tris, cur, oi, di, oo, do, d_face)
        i, t_out = _exit(e_in, e_out, big)
        leaves = active & (t_out <= 1.0)
        other = _pick([nbr[cur, 0], nbr[cur, 1], nbr[cur, 2]], i)
        m = jnp.maximum(other, 0)
        w = [tuple(P[:, c][tris[:, kk][m]] for c in range(3)) for kk in range(3)]
        n_other = vcross(_sub(w[1], w[0]), _sub(w[2], w[0]))
        d_x = _lerp3(di, do, t_out)
        same_side = (vdot(n_other, d_x) * vdot(n_cur, d_face)) > 0
        outline = leaves & ((other < 0) | ~same_side)
        found = found | outline
        edge = jnp.where(outline, i.astype(jnp.int32), edge)
        walk = leaves & ~outline
        return (k + 1, jnp.where(walk, other, cur), jnp.where(walk, t_out, t_in), walk, found, edge)

    m = prim.shape
    state = (jnp.int32(0), jnp.maximum(prim, 0), jnp.zeros(m, dtype), prim >= 0, jnp.zeros(m, bool), jnp.zeros(m, jnp.int32))
    _, cur, t_in, _, found, edge = jax.lax.while_loop(cond, body, state)
    return cur, t_in, found, edge


def _joined(P, tris, nbr, pp, pq, dp, dq, two_sided: bool):
    """Pairs whose two samples see triangles of one sheet: neighbours across an edge (welded
    topology) or sharing a vertex, facing the same way (always, without double-sided meshes: only
    front faces are seen). No outline runs between them (bar a fold exactly at the shared vertex),
    so they are not walked -- on a fine mesh most neighbouring samples see different triangles."""
    both = (pp >= 0) & (pq >= 0)
    a, b = jnp.maximum(pp, 0), jnp.maximum(pq, 0)
    ta, tb = tris[a], tris[b]
    share = jnp.zeros(pp.shape, bool)
    for i in range(3):
        for j in range(3):
            share = share | (ta[..., i] == tb[..., j])
    nb = nbr[a]
    share = share | (nb[..., 0] == pq) | (nb[..., 1] == pq) | (nb[..., 2] == pq)
    joined = both & share
    if two_sided:
        P = jax.lax.stop_gradient(P)
        dp, dq = jax.lax.stop_gradient((dp, dq))

        def facing(t, d):
            v = [tuple(P[:, c][tris[:, k][t]] for c in range(3)) for k in range(3)]
            return vdot(vcross(_sub(v[1], v[0]), _sub(v[2], v[0])), d) >= 0

        joined = joined & (facing(a, dp) == facing(b, dq))
    return joined


def _edge_fraction(vj, vk, sigma, oi, di, oo, do, ok):
    """The oriented edge function E = sigma ((V_j - o) x (V_k - V_j)) . d of the edge from V_j to
    V_k at the segment's two ends, and its zero along the segment a / (a - b) where `ok` (fill 2):
    (fraction, E as a function of a ray)."""
    ejk = _sub(vk, vj)

    def f(o, d):
        return sigma * vdot(vcross(_sub(vj, o), ejk), d)

    a, b = f(oi, di), f(oo, do)
    return safe_div(a, a - b, ok & (jax.lax.stop_gradient(b) < jax.lax.stop_gradient(a)), fill=2.0), f


def _mesh_outline(P, tris, nbr, prim, oi, di, oo, do, along, across):
    """(valid, j, k, sigma) of the segment from the inside ray (oi, di), which hits triangle `prim`,
    to the outside one (oo, do), where it leaves the surface through an outline (no gradients: a
    discrete search). The walk goes from triangle to neighbour across the edge the segment leaves
    by, until that edge is an outline -- no neighbour, or a neighbour facing the other way along
    the ray there -- (found), the segment ends inside a triangle (none: the other sample's surface
    is in front), or MAX_WALK triangles (none). The outline edge runs from vertex j to vertex k,
    its function oriented by sigma (`_edge_fraction`); valid also needs the edge to be the pairs'
    to take (`_slope_ok`). Only the picked edge's function is evaluated here."""
    tri_id, t_in, found, edge = _walk(P, (oi, di, oo, do), tris, nbr, prim)
    corners = tris[tri_id]
    v = [tuple(P[:, c][corners[:, kk]] for c in range(3)) for kk in range(3)]
    n = vcross(_sub(v[1], v[0]), _sub(v[2], v[0]))
    sigma = jnp.where(vdot(n, _lerp3(di, do, t_in)) >= 0, 1.0, -1.0).astype(di[0].dtype)
    j = _pick([corners[:, 1], corners[:, 2], corners[:, 0]], edge)
    k = _pick([corners[:, 2], corners[:, 0], corners[:, 1]], edge)
    vj, vk = (tuple(P[:, c][j] for c in range(3)), tuple(P[:, c][k] for c in range(3)))
    tau, f = _edge_fraction(vj, vk, sigma, oi, di, oo, do, found)
    ok = found & (tau <= 1.0)
    steep = _slope_ok(f, _lerp3(oi, oo, tau), _lerp3(di, do, tau), along, across)
    return ok & steep, j, k, sigma


def _sphere_fraction(c, r, oi, di, oo, do):
    """(fraction, valid): where the segment of rays leaves the sphere's contour, and the contour
    as a function of a ray. With the rays linear in the fraction s, g(s) = |(c - o) x d|^2 -
    r^2 |d|^2 (the squared distance of the line from the centre, times |d|^2, minus r^2 |d|^2) is
    a quadratic, negative where the line meets the sphere; its root in (0, 1] with
    g(0) <= 0 < g(1) is 2 g0 / (-b - sqrt(b^2 - 4 a g0)) (no cancellation for either sign of a)."""
    A = vcross(_sub(c, oi), di)
    B = _sub(vcross(_sub(c, oo), do), A)
    dd = _sub(do, di)
    r2 = r * r
    a = vdot(B, B) - r2 * vdot(dd, dd)
    b = 2.0 * (vdot(A, B) - r2 * vdot(di, dd))
    g0 = vdot(A, A) - r2 * vdot(di, di)
    g1 = a + b + g0
    valid = (jax.lax.stop_gradient(g0) <= 0) & (jax.lax.stop_gradient(g1) > 0)
    den = -b - safe_sqrt(b * b - 4.0 * a * g0)
    tau = safe_div(2.0 * g0, den, valid & (jax.lax.stop_gradient(den) < 0), fill=2.0)

    def f(o, d):
        return vdot(vcross(_sub(c, o), d), vcross(_sub(c, o), d)) - r2 * vdot(d, d)

    return tau, valid & (jax.lax.stop_gradient(tau) <= 1.0), f


def _plane_fraction(pt, nrm, oi, di, oo, do):
    """(fraction, valid, f): where the segment of rays stops meeting the plane in front of the
    camera (its horizon, or in orthographic projection the line where the plane passes the rays'
    origins). f = ((pt - o).n)(d.n) > 0 where the ray meets it at t > 0; linear in the fraction (o
    or d varies, not both)."""

    def f(o, d):
        return vdot(_sub(pt, o), nrm) * vdot(d, nrm)

    fi, fo = f(oi, di), f(oo, do)
    valid = (jax.lax.stop_gradient(fi) >= 0) & (jax.lax.stop_gradient(fo) < 0)
    fin = jnp.maximum(fi, 0.0)
    return safe_div(fin, fin - fo, valid, fill=2.0), valid, f


def _steep(fraction, f, oi, di, oo, do, along, across):
    return _slope_ok(f, _lerp3(oi, oo, fraction), _lerp3(di, do, fraction), along, across)


# ------------------------------------------------------------------------------------------
# The pass
# ------------------------------------------------------------------------------------------


def _search(fn, order, count, fills: tuple):
    """fn(ids) -> a tuple of arrays (C,) for the lanes `ids` (C,) of each chunk of SEARCH_CHUNK
    entries of the candidate list `order` whose first `count` entries are live, as arrays laid out
    like `order`, `fills` past `count`. A while loop over the live chunks only: not differentiable
    (fn is the discrete search), its work in proportion to the candidates."""
    m = order.shape[0]
    C = min(m, SEARCH_CHUNK)
    n = -(-m // C) * C
    order = jnp.pad(order, (0, n - m))
    outs = tuple(jnp.full(n, jnp.asarray(f)) for f in fills)

    def body(state):
        k, outs = state
        ids = jax.lax.dynamic_slice(order, (k * C,), (C,))
        live = (k * C + jnp.arange(C)) < count
        new = fn(ids)
        new = tuple(jnp.where(live, y.astype(o.dtype), jnp.asarray(f, o.dtype)) for y, o, f in zip(new, outs, fills, strict=True))
        return k + 1, tuple(jax.lax.dynamic_update_slice(o, y, (k * C,)) for o, y in zip(outs, new, strict=True))

    _, outs = jax.lax.while_loop(lambda st: st[0] * C < count, body, (jnp.int32(0), outs))
    return tuple(o[:m] for o in outs)


def _chunked(fn, order, count, xs, fills: tuple):
    """fn(ids, x) -> a tuple of arrays (C,) for the lanes `ids` (C,) of each chunk of CHUNK entries of
    the candidate list `order` (its first `count` entries live) and that chunk of `xs` (arrays laid
    out like `order`), as arrays laid out like `order`; `fills` at the entries past `count`. A scan
    over the chunks with a fixed count (differentiable), whose chunks past the candidates skip fn
    (a conditional): one copy of fn in the program and its work in proportion to the candidates.
    fn is computed again in the backward pass rather than its intermediates kept (a scan keeps
    them for every chunk, the candidates' or not)."""
    C = min(order.shape[0], CHUNK)
    n = -(-order.shape[0] // C) * C
    pad = lambda a: jnp.pad(a, [(0, n - a.shape[0])] + [(0, 0)] * (a.ndim - 1))  # noqa: E731
    fills = tuple(jnp.asarray(x) for x in fills)

    def run(args):
        k, ids, x = args
        live = (k * C + jnp.arange(C)) < count

        def compute(_):
            out = fn(ids, x)
            return tuple(jnp.where(live, y.astype(f.dtype), f) for y, f in zip(out, fills, strict=True))

        def skip(_):
            return tuple(jnp.full(C, f) for f in fills)

        return jax.lax.cond(k * C < count, compute, skip, None)

    split = lambda a: pad(a).reshape((n // C, C) + a.shape[1:])  # noqa: E731
    outs = jax.lax.map(jax.checkpoint(run), (jnp.arange(n // C), split(order), jax.tree_util.tree_map(split, xs)))
    return tuple(y.reshape(-1)[:order.shape[0]] for y in outs)


#: Lanes of `_search`'s chunks (the walk: small, so that little is done past the candidates).
SEARCH_CHUNK = 1 << 12
#: Lanes of `_chunked`'s chunks (the differentiated fractions: large, so that the backward pass's
#: scan over them, which adds up the vertices' cotangents once per chunk, has few steps).
CHUNK = 1 << 16


def _cut(x, axis: int, first: bool):
    """The first (or last) n - 1 entries of x along the image axis `axis` (0 rows, 1 columns)."""
    n = x.shape[axis]
    return jax.lax.slice_in_dim(x, 0 if first else 1, n - 1 if first else n, axis=axis)


def _pad(x, axis: int, first: bool):
    """x (n - 1 along `axis`) placed at the first (or last) n - 1 entries, zero elsewhere."""
    pad = [(0, 0)] * x.ndim
    pad[axis] = (0, 1) if first else (1, 0)
    return jnp.pad(x, pad)


def antialias_pass(scene, dtype, offset, c, surf, samples: int, nbr=None, *, blend: bool = True):
    """The pass's image `c` (H, W, C) with its outlines blended (module docstring).

    scene: the scene of the pass (camera, objects; its meshes' positions are differentiated);
    offset: the pass's sub-pixel offset (2,); surf: the pass's G-buffer ids: hit (H, W) bool, idx
    (H, W) object index, t (H, W) distance along the unit ray, prim (H, W) triangle index into the
    meshes' concatenation (-1 elsewhere; absent without meshes); samples: the camera's
    `supersample` s (each sample's cell is 1/s of a pixel wide); nbr: `neighbours` of the meshes
    (None: the scene's own, else computed here); blend=False: the image `c` itself, with the
    blend's derivative (`RenderOptions.antialias`).

    The pairs: every two neighbouring samples, horizontal (H, W - 1) then vertical (H - 1, W), each
    twice -- with its first sample inside (p) and with its second (q) -- as one list of lanes (one
    copy of the edge maths in the program). A lane is its index in that list: its pixels, rays
    and surfaces are computed from the index where it is examined, so nothing per lane but the
    candidates' list is laid out in memory. Two passes over the candidates: the search (no
    gradients, nothing of it kept for the backward pass), then where the outlines found cross
    (differentiated, computed again in the backward pass)."""
    dtype = jnp.dtype(dtype)
    objects = scene.objects
    H, W = c.shape[:2]
    if H * W < 2:
        return c
    rays_at, step_x, step_y = camera_plane_rays(scene.camera, dtype, offset)
    hit, idx, t = surf["hit"], surf["idx"], surf["t"]
    K = len(objects)
    kind = jnp.asarray([0 if isinstance(ob, Mesh) else 1 if isinstance(ob, Sphere) else 2 for ob in objects], jnp.int32)
    has_sphere = any(isinstance(ob, Sphere) for ob in objects)
    has_plane = any(isinstance(ob, Plane) for ob in objects)
    has_mesh = any(isinstance(ob, Mesh) for ob in objects)
    zeros3 = jnp.zeros((K, 3), dtype)
    centers = jnp.stack([jnp.asarray(ob.center, dtype) if isinstance(ob, Sphere) else zeros3[0] for ob in objects])
    radii = jnp.stack([jnp.asarray(ob.radius, dtype) if isinstance(ob, Sphere) else jnp.zeros((), dtype) for ob in objects])
    points = jnp.stack([jnp.asarray(ob.point, dtype) if isinstance(ob, Plane) else zeros3[0] for ob in objects])
    normals = jnp.stack([jnp.asarray(ob.normal, dtype) if isinstance(ob, Plane) else zeros3[0] for ob in objects])
    prim = surf.get("prim") if has_mesh else None
    if has_mesh:
        P, tris = concat_geometry([ob for ob in objects if isinstance(ob, Mesh)], dtype)
        two_sided = any(ob.double_sided for ob in objects if isinstance(ob, Mesh))
        if nbr is None:
            nbr = getattr(scene, "neighbours", None)  # (`stages.AccelScene`: made with its BVH, or by `deformable`)
            if nbr is not None:
                check_topology(nbr, tris.shape[0])
        if nbr is None:
            nbr = neighbours(P, tris, mesh_parts([ob for ob in objects if isinstance(ob, Mesh)]))
    h = 0.5 / samples

    # The lanes: per part (horizontal pairs with p inside, with q inside, vertical ones likewise)
    # the pairs' grid (rows, columns) and where the part starts in the list.
    grids = [(H, W - 1)] * 2 + [(H - 1, W)] * 2
    bounds = np.cumsum([0] + [r * w for r, w in grids])
    flat = {"hit": hit.reshape(-1), "idx": idx.reshape(-1)}
    if has_mesh:
        flat["prim"] = prim.reshape(-1)

    def lane(ids):
        """What lane `ids` (C,) examines: (inside ray, outside ray, horizontal, the inside sample's
        flat pixel index)."""
        part = sum((ids >= int(b)).astype(jnp.int32) for b in bounds[1:4])
        horizontal = part < 2
        r = ids - jnp.asarray(bounds[:4], jnp.int32)[part]
        cols = jnp.where(horizontal, W - 1, W)
        y, x = r // cols, r % cols
        qy, qx = jnp.where(horizontal, y, y + 1), jnp.where(horizontal, x + 1, x)
        first = (part % 2) == 0
        iy, ix = jnp.where(first, y, qy), jnp.where(first, x, qx)
        oy, ox = jnp.where(first, qy, y), jnp.where(first, qx, x)
        return rays_at(ix, iy), rays_at(ox, oy), horizontal, iy * W + ix

    def steps(horizontal):
        """The steps of the slope test along and across the lanes' pairs."""
        pick = lambda a, b: tuple(tuple(jnp.where(horizontal, a[k][i], b[k][i]) for i in range(3)) for k in range(2))  # noqa: E731
        return pick(step_x, step_y), pick(step_y, step_x)

    def surface(at):
        """(object index, kind (-1: nothing), triangle or -1) the inside sample sees."""
        i_in = flat["idx"][at]
        kd = jnp.where(flat["hit"][at], kind[i_in], -1)
        return i_in, kd, (jnp.where(kd == 0, flat["prim"][at], -1) if has_mesh else None)

    def find(ids, _):
        """Which lanes an outline of the inside surface crosses, by its kind, and for a mesh the
        outline edge (its vertices j, k and orientation, `_mesh_outline`): a discrete search, no
        gradients."""
        (oi, di), (oo, do), horizontal, at = jax.lax.stop_gradient(lane(ids))
        rays = oi, di, oo, do
        along, across = jax.lax.stop_gradient(steps(horizontal))
        i_in, kd, pr = surface(at)
        valid = jnp.zeros(ids.shape, bool)
        j = k = jnp.zeros(ids.shape, jnp.int32)
        sigma = jnp.ones(ids.shape, dtype)
        if has_sphere:
            cc = tuple(jax.lax.stop_gradient(centers)[:, i][i_in] for i in range(3))
            ts, vs, f = _sphere_fraction(cc, jax.lax.stop_gradient(radii)[i_in], *rays)
            valid = jnp.where(kd == 1, vs & _steep(ts, f, *rays, along, across), valid)
        if has_plane:
            pt = tuple(jax.lax.stop_gradient(points)[:, i][i_in] for i in range(3))
            nn = tuple(jax.lax.stop_gradient(normals)[:, i][i_in] for i in range(3))
            tp, vp, f = _plane_fraction(pt, nn, *rays)
            valid = jnp.where(kd == 2, vp & _steep(tp, f, *rays, along, across), valid)
        if has_mesh:
            vm, j, k, sigma = _mesh_outline(jax.lax.stop_gradient(P), tris, nbr, pr, *rays, along, across)
            valid = jnp.where(pr >= 0, vm, valid)
        return valid, j, k, sigma

    def fraction(ids, found):
        """Where the outlines `find` found cross the lanes' segments, differentiable in the outline
        (a mesh edge's vertices, a sphere's centre and radius, a plane) and the camera."""
        valid, j, k, sigma = found
        (oi, di), (oo, do), _, at = lane(ids)
        rays = oi, di, oo, do
        i_in, kd, _ = surface(at)
        tau = jnp.full(ids.shape, 2.0, dtype)
        if has_sphere:
            cc = tuple(centers[:, i][i_in] for i in range(3))
            ts, vs, _ = _sphere_fraction(cc, radii[i_in], *rays)
            tau = jnp.where((kd == 1) & vs, ts, tau)
        if has_plane:
            pt = tuple(points[:, i][i_in] for i in range(3))
            nn = tuple(normals[:, i][i_in] for i in range(3))
            tp, vp, _ = _plane_fraction(pt, nn, *rays)
            tau = jnp.where((kd == 2) & vp, tp, tau)
        if has_mesh:
            vj, vk = (tuple(P[:, ci][e] for ci in range(3)) for e in (j, k))
            tm, _ = _edge_fraction(vj, vk, sigma, *rays, valid & (kd == 0))
            tau = jnp.where(kd == 0, tm, tau)
        return (jnp.where(valid, tau, 2.0),)

    # The candidates: pairs whose samples see different surfaces (a few per cent of an image's),
    # not joined across a mesh edge, with the lane's inside sample on a surface.
    cand, pairs = [], {}
    for axis in (1, 0):
        cut = lambda x, first, axis=axis: _cut(x, axis, first)  # noqa: E731
        hp, hq = cut(hit, True), cut(hit, False)
        differs = (hp != hq) | (hp & (cut(idx, True) != cut(idx, False)))
        if prim is not None:
            pp, pq = cut(prim, True), cut(prim, False)
            if two_sided:
                cols, rows = jnp.arange(W)[None, :], jnp.arange(H)[:, None]
                d_at = lambda first, cut=cut: tuple(cut(jnp.broadcast_to(x, (H, W)), first) for x in rays_at(cols, rows)[1])  # noqa: E731
                dp, dq = d_at(True), d_at(False)
            else:
                dp = dq = None
            differs = (differs | (hp & (pp != pq))) & ~_joined(P, tris, nbr, pp, pq, dp, dq, two_sided)
        pairs[axis] = (hp, hq, differs)
        cand += [(differs & hp).reshape(-1), (differs & hq).reshape(-1)]
    cand = jnp.concatenate(cand)
    n = cand.shape[0]
    count = jnp.sum(cand)
    (order,) = jnp.nonzero(cand, size=n, fill_value=0)
    found = _search(lambda ids: find(ids, None), order, count, (False, jnp.int32(0), jnp.int32(0), jnp.ones((), dtype)))
    (tau_c,) = _chunked(fraction, order, count, found, (jnp.full((), 2.0, dtype),))
    dest = jnp.where(jnp.arange(order.shape[0]) < count, order, n)  # (dropped: past the end)
    valid_all = jnp.zeros(n, bool).at[dest].set(found[0], mode="drop")
    tau_all = jnp.full(n, 2.0, dtype).at[dest].set(tau_c, mode="drop")
    delta = jnp.zeros_like(c)
    for n_axis, axis in enumerate((1, 0)):
        hp, hq, differs = pairs[axis]
        k0, k1 = 2 * n_axis, 2 * n_axis + 1
        ta = tau_all[bounds[k0]:bounds[k0 + 1]].reshape(hp.shape)
        va = valid_all[bounds[k0]:bounds[k0 + 1]].reshape(hp.shape) & hp & differs
        tb = tau_all[bounds[k1]:bounds[k1 + 1]].reshape(hp.shape)
        vb = valid_all[bounds[k1]:bounds[k1 + 1]].reshape(hp.shape) & hq & differs
        near_p = _cut(t, axis, True) <= _cut(t, axis, False)
        use_a = va & (~vb | near_p)
        use_b = vb & ~use_a
        a = jnp.where(use_a, ta, 1.0 - tb)  # the edge's distance from p, in pixels
        use = use_a | use_b
        w_p = jnp.where(use & (a < h), (h - a) / (2 * h), 0.0)[..., None]
        w_q = jnp.where(use & (a > 1.0 - h), (a - (1.0 - h)) / (2 * h), 0.0)[..., None]
        cp, cq = _cut(c, axis, True), _cut(c, axis, False)
        delta = delta + _pad(w_p * (cq - cp), axis, True) + _pad(w_q * (cp - cq), axis, False)
    return c + (delta if blend else delta - jax.lax.stop_gradient(delta))
