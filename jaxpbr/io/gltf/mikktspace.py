"""MikkTSpace tangents in NumPy, for glTF primitives that are normal-mapped but have no TANGENT.

glTF 2.0 asks (SHOULD) for MikkTSpace tangents (Morten S. Mikkelsen, "Simulation of wrinkled
surfaces revisited", 2008; the reference implementation is mikktspace.c) when a primitive has a
normal texture and no TANGENT attribute, so that normal maps baked against MikkTSpace decode as
baked. `mikktspace_tangents` follows the reference implementation's rules, quirks included, with
whole-array operations:

1. Corners (a triangle's three vertices) with bit-identical float32 position, normal and texcoord
   (-0 equal to +0) are welded into one vertex. A triangle with two corners at the same position
   is "degenerate" and set aside (step 7).
2. Per triangle, in float32 as the reference computes it: the texture-space orientation (sign of
   the signed UV area), dP/ds and dP/dt (the reference's vOs, vOt) normalised and multiplied by that
   sign. A triangle whose UV area, |dP/ds| or |dP/dt| is zero (|x| <= FLT_MIN) may "group with
   anything": it contributes nothing, but joins its neighbours' groups and takes the orientation of
   the first group that reaches it.
3. Neighbours: triangles sharing an edge with opposite winding; an edge of more than two triangles
   pairs them greedily in triangle order. The reference finds pairs by sorting edges, and its
   sub-sorts skip the last run of equal smaller-vertex indices (a quirk of mikktspace.c's
   BuildNeighborsFast), so an edge there finds its twin only if they end up adjacent. That depends
   on its vertex indices (the representative each weld picks in its spatial partition) and on its
   seeded quicksort; both are replayed, so the same edge goes unpaired here and its two end
   vertices keep split frames (on the mirrored-UV sheet of the tests: 3 corners, 0.85 degrees off
   the smooth frame).
4. Groups: around each welded vertex, triangles connected through paired edges and of the same
   orientation form a group (so a UV mirror seam splits a vertex into two frames). Where "group
   with anything" triangles are involved, the reference's seed order is replayed (seeds in triangle
   order; the first group to reach such a triangle fixes its orientation).
5. A corner's tangent: the sum over its group's triangles, in triangle order and in float32, of the
   triangle's dP/ds projected onto the vertex normal's tangent plane and normalised, weighted by the
   corner angle between the projected edges; then normalised. The reference's 180-degree rule is
   kept: a triangle whose projected dP/ds or dP/dt is opposite to the corner's own (float32
   cos <= -1, the default threshold) is left out of that corner's sum.
6. w is the orientation sign: in the reference's convention +1 where the UV orientation is positive.
7. A degenerate triangle's corner copies the frame of the first good corner at the same welded
   vertex, if there is one.

Conventions and deliberate differences from the reference:

* `convention="gltf"` (the default) returns w = -(reference w), what glTF-Transform stores (see
  KhronosGroup/glTF-Sample-Models issue 174): glTF texcoords have v pointing down the image while
  MikkTSpace's t axis points up, so bitangent = cross(normal, tangent.xyz) * w is along -dP/dv
  (the normal map's +Y, up the image). This equals running the reference on (u, 1 - v).
  `convention="mikktspace"` returns the reference's own w.
* Where the reference leaves a corner without a frame (a "group with anything" triangle that no
  group reached; a degenerate triangle with no good corner at its vertex) it writes (1, 0, 0), which
  need not be orthogonal to the normal; where a group's sum vanishes it writes (0, 0, 0). Here the
  tangent is always a finite unit vector orthogonal to the (normalised) normal: (1, 0, 0) projected
  onto the tangent plane, or the coordinate axis least aligned with the normal when (1, 0, 0) is
  (nearly) parallel to it. Every tangent is re-orthogonalised against the normalised normal in
  float64 (a no-op for the unit normals glTF requires; non-unit normals are normalised first).
* arccos comes from another libm and the final normalisation is float64, so directions agree with
  the reference to float32 resolution (~5e-6 degrees measured), not bit for bit. In a pathological
  group (more than 4M member pairs touched by the 180-degree rule) the left-out members are
  subtracted in float64 instead of re-summed.

Cost: about 0.5 s per 100k triangles (about the WebAssembly build's speed), O(T log T) apart from
the 180-degree rule's pair checks in large, nearly cancelling vertex fans.
"""

from __future__ import annotations

import numpy as np

from jaxpbr.errors import InputError

__all__ = ["mikktspace_tangents"]

_FLT_MIN = np.float32(1.17549435e-38)  # the reference's "not zero" test is |x| > FLT_MIN
_PREV = np.array([2, 0, 1])  # corner i -> corner i-1 (mod 3)
_NEXT = np.array([1, 2, 0])  # corner i -> corner i+1 (mod 3)
_SMALL_GROUP = 32  # groups up to this size check the 180-degree rule pair by pair
_PAIR_CHUNK = 1 << 22
_SORT_SEED = 39871946  # the reference's INTERNAL_RND_SORT_SEED
_GRID_CELLS = 2048  # the reference's g_iCells


def mikktspace_tangents(positions, normals, texcoords, *, convention: str = "gltf") -> np.ndarray:
    """MikkTSpace tangents of an unwelded triangle soup.

    positions (3T, 3), normals (3T, 3), texcoords (3T, 2): corner k of triangle t at row 3t + k
    (un-index a glTF primitive with `attribute[indices]` first; triangles only). Computed in float32
    like the reference (the inputs are cast).

    Returns (3T, 4) float32: xyz a unit tangent orthogonal to the normal, w = +1 or -1 with
    bitangent = cross(normal, xyz) * w. With the default convention="gltf" the bitangent points
    along -dP/dv for glTF texcoords (v down the image: the normal map's +Y), which is the reference
    implementation's w negated; convention="mikktspace" gives the reference's own w. See the module
    docstring for the rules and for what differs from the reference (always a unit tangent, even for
    degenerate triangles)."""
    if convention not in ("gltf", "mikktspace"):
        raise InputError(f"convention must be 'gltf' or 'mikktspace', not {convention!r}")
    P, N, UV = _validated(positions, normals, texcoords)
    n_corners = P.shape[0]
    out = np.zeros((n_corners, 4), np.float32)
    if n_corners == 0:
        return out
    T = n_corners // 3
    Nq = _unit_normals32(N)

    vid = _weld(P, N, UV)
    rid = _reference_vertex_ids(P, vid)[vid]
    P3, UV3, N3 = P.reshape(T, 3, 3), UV.reshape(T, 3, 2), Nq.reshape(T, 3, 3)
    p0, p1, p2 = P3[:, 0], P3[:, 1], P3[:, 2]
    degen = (p0 == p1).all(1) | (p0 == p2).all(1) | (p1 == p2).all(1)
    good = np.flatnonzero(~degen)  # the reference keeps the good triangles' order

    vec = np.zeros((n_corners, 3), np.float64)
    orient = np.zeros(n_corners, bool)
    have = np.zeros(n_corners, bool)  # False: no frame from the reference (default or zero sum)
    if good.size:
        gv, go, gh = _good_frames(P3[good], UV3[good], N3[good], vid.reshape(T, 3)[good],
                                  rid.reshape(T, 3)[good])
        rows = (3 * good[:, None] + np.arange(3)).ravel()
        vec[rows], orient[rows], have[rows] = gv, go, gh
        bad = np.flatnonzero(degen)
        if bad.size:  # a degenerate corner copies the first good corner at its welded vertex
            bad_rows = (3 * bad[:, None] + np.arange(3)).ravel()
            keys, first = np.unique(vid[rows], return_index=True)
            at = np.minimum(np.searchsorted(keys, vid[bad_rows]), keys.size - 1)
            hit = keys[at] == vid[bad_rows]
            src = rows[first[at[hit]]]
            dst = bad_rows[hit]
            vec[dst], orient[dst], have[dst] = vec[src], orient[src], have[src]

    n64 = Nq.astype(np.float64)
    n64 /= np.maximum(np.sqrt((n64 * n64).sum(1)), 1e-300)[:, None]
    length = np.sqrt((vec * vec).sum(1))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = np.where(have[:, None], vec / length[:, None], np.array([1.0, 0.0, 0.0]))
    t = _tangent_plane_unit(t, n64)
    out[:, :3] = t
    sign = np.where(orient, 1.0, -1.0)
    out[:, 3] = -sign if convention == "gltf" else sign
    return out


# ---------------------------------------------------------------------------------------------
# input


def _validated(positions, normals, texcoords):
    arrays = []
    for name, value, width in (("positions", positions, 3), ("normals", normals, 3),
                               ("texcoords", texcoords, 2)):
        try:
            a = np.asarray(value)
        except (TypeError, ValueError) as exc:  # ragged lists and the like
            raise InputError(f"{name}: not an array ({exc})") from None
        if a.ndim != 2 or a.shape[1] != width:
            raise InputError(f"{name}: expected shape (3T, {width}), got {a.shape}")
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise InputError(f"{name}: expected numbers, got dtype {a.dtype}")
        with np.errstate(over="ignore", invalid="ignore"):
            a = np.ascontiguousarray(a, dtype=np.float32)
        if not np.isfinite(a).all():
            raise InputError(f"{name}: non-finite values (or values beyond float32 range)")
        arrays.append(a)
    P, N, UV = arrays
    if not (P.shape[0] == N.shape[0] == UV.shape[0]):
        raise InputError("positions, normals and texcoords must have the same number of rows "
                         f"(got {P.shape[0]}, {N.shape[0]}, {UV.shape[0]})")
    if P.shape[0] % 3:
        raise InputError(f"an unwelded triangle list has 3T rows, got {P.shape[0]}: un-index the "
                         "primitive (attribute[indices]) and pass triangles only")
    return P, N, UV


def _unit_normals32(N):
    """Normals that are unit to float32 precision are kept bit for bit (as the reference uses them);
    others are normalised; zero normals stay zero (no projection)."""
    n64 = N.astype(np.float64)
    length = np.sqrt((n64 * n64).sum(1))
    fix = (np.abs(length - 1.0) > 1e-6) & (length > 0)
    if fix.any():
        N = N.copy()
        N[fix] = (n64[fix] / length[fix, None]).astype(np.float32)
    return N


def _weld(P, N, UV):
    """Welded vertex id per corner: equal iff position, normal and texcoord are equal as floats."""
    key = np.concatenate([P, N, UV], axis=1) + np.float32(0.0)  # -0.0 + 0.0 = +0.0
    bits = key.view(np.uint32).astype(np.uint64)
    h = np.zeros(len(bits), np.uint64)
    for k in range(8):  # a 64-bit mix of the 8 words; collisions are detected below
        h = (h ^ bits[:, k]) * np.uint64(0x100000001B3) + np.uint64(k + 1)
        h ^= h >> np.uint64(29)
    order = np.argsort(h, kind="stable")
    s = bits[order]
    hs = h[order]
    new = np.empty(len(s), bool)
    new[0] = True
    new[1:] = (s[1:] != s[:-1]).any(1)
    if (new[1:] & (hs[1:] == hs[:-1])).any():  # a collision: sort by the words themselves
        order = np.lexsort(bits.T[::-1])
        s = bits[order]
        new[1:] = (s[1:] != s[:-1]).any(1)
    vid = np.empty(len(s), np.int64)
    vid[order] = np.cumsum(new) - 1
    return vid


# ---------------------------------------------------------------------------------------------
# float32 helpers, in the reference's operation order


def _unique(x):
    """Sorted distinct values (np.unique without its hash-table path, slow on large int arrays)."""
    x = np.sort(x)
    return x[np.append(True, x[1:] != x[:-1])] if x.size else x


def _dot32(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _normalize_if_nonzero32(v):
    nonzero = (np.abs(v) > _FLT_MIN).any(-1)
    length = np.sqrt(_dot32(v, v))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        unit = (np.float32(1.0) / length)[..., None] * v
    return np.where(nonzero[..., None], unit, v)


def _project_normalize32(v, n):
    return _normalize_if_nonzero32(v - _dot32(n, v)[..., None] * n)


# ---------------------------------------------------------------------------------------------
# the good (non-degenerate) triangles


def _good_frames(P, UV, N, V, R):
    """Frames of the good triangles' corners: (vec (3G,3) float64 unnormalised, orient (3G,) bool,
    have (3G,) bool)."""
    G = P.shape[0]
    vOs, vOt, orient, gwa = _triangle_derivatives(P, UV)
    nbr = _neighbors(R)
    cL = _corner_links(V, nbr)  # across edge (i, i+1)
    cR = _corner_links(V, nbr[:, _PREV])  # across edge (i-1, i)
    label = _groups(V, orient, gwa, cL, cR)  # group id (a corner index) per corner, -1: none

    # per corner: projected, normalised dP/ds and dP/dt, corner angle (float32 like the reference)
    uS = _project_normalize32(np.broadcast_to(vOs[:, None, :], (G, 3, 3)), N).reshape(-1, 3)
    uT = _project_normalize32(np.broadcast_to(vOt[:, None, :], (G, 3, 3)), N).reshape(-1, 3)
    e1 = _project_normalize32(P[:, _PREV] - P, N)
    e2 = _project_normalize32(P[:, _NEXT] - P, N)
    cos = np.clip(_dot32(e1, e2), np.float32(-1), np.float32(1))
    angle = np.arccos(cos.astype(np.float64)).astype(np.float32).reshape(-1)
    contrib = angle[:, None] * uS  # float32, as the reference adds fAngle * vOs

    # the sums run over each group's triangles in triangle order, in float32, as EvalTspace does;
    # "group with anything" triangles add nothing
    member = np.flatnonzero((label >= 0) & ~np.repeat(gwa, 3))
    member = member[np.argsort(label[member], kind="stable")]  # by group, then corner order
    row_of_group = np.full(3 * G, -1, np.int64)
    first = np.ones(member.size, bool)
    first[1:] = label[member[1:]] != label[member[:-1]]
    starts = np.flatnonzero(first)
    sizes = np.diff(np.append(starts, member.size))
    row_of_group[label[member[starts]]] = np.arange(starts.size)
    slot = np.empty(3 * G, np.int64)  # a member's position in its group's row
    slot[member] = np.arange(member.size) - np.repeat(starts, sizes)

    # the 180-degree rule: a corner whose group has members opposite to it gets a row of its own,
    # the group's row with those members left out
    i, j = _opposite_pairs(member, starts, sizes, uS, uT)
    rows_members = [member]
    row_starts, row_sizes = [starts], [sizes]
    row_of_corner = np.full(3 * G, -1, np.int64)
    assigned = label >= 0
    row_of_corner[assigned] = row_of_group[label[assigned]]
    excluded = None
    if i.size and sizes[row_of_group[label[_unique(i)]]].sum() > _PAIR_CHUNK:
        # pathological (say a fan of 10^4 triangles around one vertex with a z^2-like UV map):
        # subtract the left-out members from the group's sum instead (float64; not bit-exact)
        excluded = np.zeros((3 * G, 3))
        np.add.at(excluded, i, contrib[j].astype(np.float64))
    elif i.size:
        own, inv = np.unique(i, return_inverse=True)
        g_rows = row_of_group[label[own]]
        o_sizes = sizes[g_rows]
        o_starts = member.size + np.cumsum(o_sizes) - o_sizes
        take = np.repeat(starts[g_rows], o_sizes) + (np.arange(o_sizes.sum())
                                                     - np.repeat(o_starts - member.size, o_sizes))
        copy = member[take]
        copy[o_starts[inv] - member.size + slot[j]] = -1
        rows_members.append(copy)
        row_starts.append(o_starts)
        row_sizes.append(o_sizes)
        row_of_corner[own] = starts.size + np.arange(own.size)
    sums = _sequential_sums(np.concatenate(rows_members), np.concatenate(row_starts),
                            np.concatenate(row_sizes), contrib)

    has_row = row_of_corner >= 0
    vec = np.zeros((3 * G, 3))
    vec[has_row] = sums[row_of_corner[has_row]]
    if excluded is not None:
        vec -= excluded
    have = has_row & (np.abs(vec) > _FLT_MIN).any(1)  # the reference's VNotZero
    group_orient = orient[np.maximum(label, 0) // 3]
    return vec, np.where(assigned, group_orient, False), have


def _sequential_sums(members, starts, sizes, contrib):
    """Per row, the float32 sum of contrib[members[start:start+size]] taken left to right (-1
    members add nothing), like the reference's loop."""
    vals = np.where((members >= 0)[:, None], contrib[np.maximum(members, 0)], np.float32(0))
    acc = np.zeros((starts.size, 3), np.float32)
    short = sizes <= 64
    for k in range(int(sizes[short].max()) if short.any() else 0):
        sel = np.flatnonzero(short & (sizes > k))
        acc[sel] += vals[starts[sel] + k]
    for r in np.flatnonzero(~short).tolist():
        acc[r] = np.cumsum(vals[starts[r]:starts[r] + sizes[r]], axis=0, dtype=np.float32)[-1]
    return acc


def _triangle_derivatives(P, UV):
    """The reference's per-triangle vOs, vOt (unit, times the orientation sign, or zero), the
    orientation (UV area > 0) and the group-with-anything flag, in float32."""
    v1, v2, v3 = P[:, 0], P[:, 1], P[:, 2]
    t21x, t21y = UV[:, 1, 0] - UV[:, 0, 0], UV[:, 1, 1] - UV[:, 0, 1]
    t31x, t31y = UV[:, 2, 0] - UV[:, 0, 0], UV[:, 2, 1] - UV[:, 0, 1]
    d1, d2 = v2 - v1, v3 - v1
    area = t21x * t31y - t21y * t31x
    vOs = t31y[:, None] * d1 - t21y[:, None] * d2
    vOt = (-t31x)[:, None] * d1 + t21x[:, None] * d2
    orient = area > 0
    area_ok = np.abs(area) > _FLT_MIN
    len_s, len_t = np.sqrt(_dot32(vOs, vOs)), np.sqrt(_dot32(vOt, vOt))
    sign = np.where(orient, np.float32(1), np.float32(-1))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        s_unit = (sign / len_s)[:, None] * vOs
        t_unit = (sign / len_t)[:, None] * vOt
        mag_s = len_s / np.abs(area)
        mag_t = len_t / np.abs(area)
    vOs = np.where((area_ok & (len_s > _FLT_MIN))[:, None], s_unit, np.float32(0))
    vOt = np.where((area_ok & (len_t > _FLT_MIN))[:, None], t_unit, np.float32(0))
    gwa = ~(area_ok & (mag_s > _FLT_MIN) & (mag_t > _FLT_MIN))
    return vOs, vOt, orient, gwa


def _neighbors(R):
    """nbr[g, e]: the triangle across edge (R[g,e], R[g,e+1]) with the opposite winding, or -1, as
    the reference's BuildNeighborsFast pairs them. R holds the reference's vertex indices (see
    `_reference_vertex_ids`). Edges are sorted by (smaller index, larger index, triangle) and each
    unpaired edge pairs with the first later unpaired one of opposite winding in its run (an edge of
    more than two triangles pairs them greedily). As in mikktspace.c, the run of edges whose smaller
    index is the largest one is left in the order its quicksort gives (the sub-sorts skip the last
    run), so an edge there pairs only with an equal edge adjacent to it: `_quicksort_tail` replays
    that order."""
    G = R.shape[0]
    a = R.ravel()
    b = R[:, _NEXT].ravel()
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    nbr = np.full(3 * G, -1, np.int64)
    top = lo.max()
    rest = np.flatnonzero(lo != top)
    order = rest[np.lexsort((hi[rest], lo[rest]))]  # stable: equal edges stay in triangle order
    lo_s, hi_s = lo[order], hi[order]
    start = np.ones(order.size, bool)
    start[1:] = (lo_s[1:] != lo_s[:-1]) | (hi_s[1:] != hi_s[:-1])
    starts = np.flatnonzero(start)
    counts = np.diff(np.append(starts, order.size))
    two = starts[counts == 2]
    x, y = order[two], order[two + 1]
    ok = a[x] == b[y]
    nbr[x[ok]] = y[ok] // 3
    nbr[y[ok]] = x[ok] // 3
    runs = [order[s:s + c].tolist() for s, c in zip(starts[counts > 2].tolist(),
                                                   counts[counts > 2].tolist())]

    tail = _quicksort_tail(lo).tolist()  # the entries with lo == top, in the reference's order
    blocks = []
    for e in tail:
        if blocks and hi[blocks[-1][-1]] == hi[e]:
            blocks[-1].append(e)
        else:
            blocks.append([e])
    runs += [sorted(block) for block in blocks[:-1]] + blocks[-1:]

    for entries in runs:
        for ii, ei in enumerate(entries):
            if nbr[ei] != -1:
                continue
            for ej in entries[ii + 1:]:
                if nbr[ej] == -1 and a[ei] == b[ej]:
                    nbr[ei], nbr[ej] = ej // 3, ei // 3
                    break
    return nbr.reshape(G, 3)


def _next_seed(seed):
    t = seed & 31
    rot = ((seed << t) | (seed >> (32 - t))) & 0xFFFFFFFF if t else seed
    return (seed + rot + 3) & 0xFFFFFFFF


def _quicksort_tail(keys):
    """Indices of the entries holding the largest key, in the order the reference's QuickSortEdges
    (Hoare partitions around a pseudo-random pivot, fixed seed) leaves them. Only the partitions of
    segments that hold such entries are replayed, each with whole-array operations: the k-th entry
    >= pivot from the left swaps with the k-th entry <= pivot from the right while they have not
    crossed."""
    E = keys.size
    top = keys.max()
    buf = keys.copy()
    ids = np.arange(E)
    stack = [(0, E - 1, _SORT_SEED)]
    while stack:
        left, right, seed = stack.pop()
        n = right - left + 1
        if n < 2:
            continue
        seg, sid = buf[left:right + 1], ids[left:right + 1]  # views
        if not (seg == top).any():
            continue
        if n == 2:
            if seg[0] > seg[1]:
                seg[:] = seg[::-1].copy()
                sid[:] = sid[::-1].copy()
            continue
        seed = _next_seed(seed)
        pivot = seg[seed % n]
        ge = np.flatnonzero(seg >= pivot)
        le = np.flatnonzero(seg <= pivot)[::-1]
        m = min(ge.size, le.size)
        crossed = ge[:m] > le[:m]
        k = int(np.argmax(crossed)) if crossed.any() else m
        g, lw = ge[:k], le[:k]
        seg[g], seg[lw] = seg[lw].copy(), seg[g].copy()
        sid[g], sid[lw] = sid[lw].copy(), sid[g].copy()
        i_l, i_r = ge[k - 1] + 1, le[k - 1] - 1
        if i_l <= i_r:  # one more scan that stops without a swap
            i_l = min(ge[k] if k < ge.size else n, le[k - 1])
            i_r = max(le[k] if k < le.size else -1, ge[k - 1])
        if i_r > 0:
            stack.append((left, left + int(i_r), seed))
        if i_l < n - 1:
            stack.append((left + int(i_l), right, seed))
    return ids[buf == top]


def _reference_vertex_ids(P, vid):
    """The reference's index for each welded vertex (GenerateSharedVerticesIndexList): the encoded
    corner 4 * triangle + corner of the member that comes first after its MergeVertsFast, a
    spatial split (2048 cells along the widest axis, then recursive halving of each cell's widest
    extent with Hoare partitions) that ends in runs compared pairwise. Only the edge order of
    `_neighbors` depends on these values; the replay is level by level over all segments at once."""
    n = P.shape[0]
    vmin, vmax = P.min(0), P.max(0)
    d = vmax - vmin
    ch = 1 if (d[1] > d[0] and d[1] > d[2]) else (2 if d[2] > d[0] else 0)
    with np.errstate(all="ignore"):
        f = np.float32(_GRID_CELLS) * ((P[:, ch] - vmin[ch]) / (vmax[ch] - vmin[ch]))
    f = np.where(np.isnan(f), np.float32(0), f)
    cell = np.clip(np.trunc(np.clip(f, -1e9, 1e9)), 0, _GRID_CELLS - 1).astype(np.int64)
    perm = np.argsort(cell, kind="stable")  # per cell, in corner order
    cell_start = np.flatnonzero(np.r_[True, cell[perm][1:] != cell[perm][:-1]])
    cell_end = np.append(cell_start[1:], n)
    keep = cell_end - cell_start >= 2
    starts, ends = cell_start[keep], cell_end[keep]
    half = np.float32(0.5)
    Pp = P[perm]  # positions in perm order, swapped along with perm
    while starts.size:
        lens = ends - starts
        S = starts.size
        seg_of = np.repeat(np.arange(S), lens)
        first = np.cumsum(lens) - lens
        at = np.repeat(starts, lens) + (np.arange(lens.sum()) - np.repeat(first, lens))
        pos = Pp[at]
        mn = np.minimum.reduceat(pos, first, axis=0)
        mx = np.maximum.reduceat(pos, first, axis=0)
        d = mx - mn
        ch = np.where((d[:, 1] > d[:, 0]) & (d[:, 1] > d[:, 2]), 1,
                      np.where(d[:, 2] > d[:, 0], 2, 0))
        r = np.arange(S)
        lo, hi = mn[r, ch], mx[r, ch]
        sep = half * (hi + lo)
        split = ~((sep >= hi) | (sep <= lo))  # else: a run compared pairwise, order kept
        if not split.any():
            break
        el = split[seg_of]
        at, seg_of = at[el], seg_of[el]
        lt = pos[el, ch[seg_of]] < sep[seg_of]
        n_lt = np.bincount(seg_of[lt], minlength=S)
        n_ge = np.bincount(seg_of[~lt], minlength=S)
        ge_at, lt_at = at[~lt], at[lt]  # by segment, ascending
        pairs = np.minimum(n_ge, n_lt)
        k = np.arange(pairs.sum()) - np.repeat(np.cumsum(pairs) - pairs, pairs)
        gi = ge_at[np.repeat(np.cumsum(n_ge) - n_ge, pairs) + k]  # k-th >= sep from the left
        li = lt_at[np.repeat(np.cumsum(n_lt) - 1, pairs) - k]  # k-th < sep from the right
        swap = gi < li
        gi, li = gi[swap], li[swap]
        perm[gi], perm[li] = perm[li], perm[gi].copy()
        Pp[gi], Pp[li] = Pp[li], Pp[gi].copy()
        s_idx = np.flatnonzero(split)
        mid = starts[s_idx] + n_lt[s_idx]
        new_starts = np.concatenate([starts[s_idx], mid])
        new_ends = np.concatenate([mid, ends[s_idx]])
        keep = new_ends - new_starts >= 2
        starts, ends = new_starts[keep], new_ends[keep]
    _, first_at = np.unique(vid[perm], return_index=True)
    rep_corner = perm[first_at]  # per welded vertex id (0..nV-1)
    return 4 * (rep_corner // 3) + rep_corner % 3


def _corner_links(V, nbr):
    """For corner (g, i) and neighbour h = nbr[g, i]: the corner of h at the same welded vertex
    (as a flat corner index 3h + j), or -1."""
    valid = nbr >= 0
    h = np.where(valid, nbr, 0)
    j = (V[h] == V[:, :, None]).argmax(2)
    return np.where(valid, 3 * h + j, -1).reshape(-1)


def _groups(V, orient, gwa, cL, cR):
    """Group id per corner (the index of a corner in the group; -1 where the reference assigns
    none). Vertices that touch no group-with-anything triangle: connected components of
    same-orientation neighbours, computed with whole-array union-find. The others: the reference's
    seed order replayed in Python (their grouping depends on it)."""
    G = V.shape[0]
    nc = 3 * G
    dirty_v = np.zeros(int(V.max()) + 1, bool)
    dirty_v[V[gwa].ravel()] = True
    dirty = dirty_v[V.ravel()]
    corner_orient = np.repeat(orient, 3)
    label = np.full(nc, -1, np.int64)

    clean = ~dirty
    src, dst = [], []
    for link in (cL, cR):
        m = clean & (link >= 0)
        c = np.flatnonzero(m)
        d = link[m]
        keep = corner_orient[c] == corner_orient[d]
        src.append(c[keep])
        dst.append(d[keep])
    parent = _components(nc, np.concatenate(src), np.concatenate(dst))
    label[clean] = parent[clean]

    if dirty.any():
        _replay_groups(label, dirty, orient, gwa, cL, cR)
    return label


def _components(n, a, b):
    """Union-find by hooking to the smaller root and pointer jumping; returns each node's root (the
    smallest index in its component)."""
    parent = np.arange(n, dtype=np.int64)
    while a.size:
        pa, pb = parent[a], parent[b]
        differ = pa != pb
        if not differ.any():
            break
        a, b, pa, pb = a[differ], b[differ], pa[differ], pb[differ]
        np.minimum.at(parent, np.maximum(pa, pb), np.minimum(pa, pb))
        while True:
            jumped = parent[parent]
            if np.array_equal(jumped, parent):
                break
            parent = jumped
    return parent


def _replay_groups(label, dirty, orient, gwa, cL, cR):
    """Build4RuleGroups/AssignRecur of the reference on the corners at "dirty" vertices: seeds in
    corner order from triangles that are not group-with-anything; a group spreads to neighbours of
    its orientation, and a group-with-anything triangle that no group has reached yet takes the
    orientation of the first one that does."""
    tri_orient = orient.tolist()
    tri_gwa = gwa.tolist()
    n_assigned = [0] * len(tri_orient)
    links_l, links_r = cL.tolist(), cR.tolist()
    lab = label.tolist()
    seeds = np.flatnonzero(dirty & ~np.repeat(gwa, 3)).tolist()
    for seed in seeds:
        if lab[seed] >= 0:
            continue
        o = tri_orient[seed // 3]
        lab[seed] = seed
        n_assigned[seed // 3] += 1
        stack = [links_r[seed], links_l[seed]]
        while stack:
            c = stack.pop()
            if c < 0 or lab[c] >= 0:
                continue
            t = c // 3
            if tri_gwa[t] and n_assigned[t] == 0:
                tri_orient[t] = o
            if tri_orient[t] != o:
                continue
            lab[c] = seed
            n_assigned[t] += 1
            stack.append(links_r[c])
            stack.append(links_l[c])
    label[dirty] = np.asarray(lab, np.int64)[dirty]


# ---------------------------------------------------------------------------------------------
# the 180-degree rule


def _opposite_pairs(member, starts, sizes, uS, uT):
    """Pairs (i, j) of corners in the same group (members only: "group with anything" triangles are
    exempt) whose projected dP/ds or dP/dt are opposite: float32 cos <= -1, the reference's test
    against cos(180 degrees). Groups up to _SMALL_GROUP members are checked pair by pair; larger
    ones merge identical rows and compare only nearly opposite vectors (`_near_opposite`)."""
    out_i, out_j = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    if member.size < 2:
        return out_i[0], out_j[0]
    # Only a group whose members do not all lie strictly on one side of their mean can hold an
    # opposite pair: cos <= -1 in float32 needs |u + u'| < 2e-3, so min(u.m, u'.m) < 1e-3 |m|.
    possible = np.zeros(sizes.size, bool)
    for u in (uS, uT):
        um = u[member].astype(np.float64)
        mean = np.stack([np.add.reduceat(um[:, k], starts) for k in range(3)], 1)
        mean /= np.maximum(np.sqrt((mean * mean).sum(1)), 1e-30)[:, None]
        side = (um * np.repeat(mean, sizes, axis=0)).sum(1)
        side[(um * um).sum(1) < 0.25] = np.inf  # short vectors: no cos <= -1
        possible |= np.minimum.reduceat(side, starts) < 1e-2
    small = np.flatnonzero((sizes >= 2) & (sizes <= _SMALL_GROUP) & possible)
    if small.size:
        k = sizes[small]
        k2 = k * k
        chunk = (np.cumsum(k2) - 1) // _PAIR_CHUNK
        cuts = (np.flatnonzero(np.diff(chunk)) + 1).tolist()
        for lo, hi in zip([0, *cuts], [*cuts, k.size]):
            gk, gs = k[lo:hi], starts[small[lo:hi]]
            gk2 = gk * gk
            rep = np.repeat(np.arange(gk.size), gk2)
            o = np.arange(gk2.sum()) - np.repeat(np.cumsum(gk2) - gk2, gk2)
            i = member[gs[rep] + o // gk[rep]]
            j = member[gs[rep] + o % gk[rep]]
            fail = (_dot32(uS[i], uS[j]) <= -1) | (_dot32(uT[i], uT[j]) <= -1)
            out_i.append(i[fail])
            out_j.append(j[fail])
    for g in np.flatnonzero((sizes > _SMALL_GROUP) & possible).tolist():
        corners = member[starts[g]:starts[g] + sizes[g]]
        i, j = _opposite_pairs_large(corners, uS, uT)
        out_i.append(i)
        out_j.append(j)
    return np.concatenate(out_i), np.concatenate(out_j)


def _opposite_pairs_large(corners, uS, uT):
    rows = np.concatenate([uS[corners], uT[corners]], axis=1)
    classes, inverse = np.unique(rows.view(np.uint32), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    cs = classes.view(np.float32)
    ci, cj = zip(*(_near_opposite(u) for u in (cs[:, :3], cs[:, 3:])))
    ci, cj = np.concatenate(ci), np.concatenate(cj)
    fail = (_dot32(cs[ci, :3], cs[cj, :3]) <= -1) | (_dot32(cs[ci, 3:], cs[cj, 3:]) <= -1)
    code = _unique(ci[fail] * cs.shape[0] + cj[fail])
    if not code.size:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs = np.stack([code // cs.shape[0], code % cs.shape[0]], 1)
    # expand class pairs to corner pairs
    order = np.argsort(inverse, kind="stable")
    count = np.bincount(inverse, minlength=cs.shape[0])
    off = np.cumsum(count) - count
    a, b = pairs[:, 0], pairs[:, 1]
    n = count[a] * count[b]
    q = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    cb = np.repeat(count[b], n)
    i = corners[order[np.repeat(off[a], n) + q // cb]]
    j = corners[order[np.repeat(off[b], n) + q % cb]]
    return i, j


def _near_opposite(u, h=2.0 ** -8, tol=1.5e-3):
    """Pairs (i, j) with u[j] within tol of -u[i] (among near-unit vectors), via a grid of cell
    h >= 2 tol (so the box around -u[i] touches at most 2 cells per axis)."""
    u64 = u.astype(np.float64)
    ok = np.flatnonzero((u64 * u64).sum(1) > 0.25)
    if ok.size < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cells = np.floor(u64[ok] / h).astype(np.int64) + 1024

    def code(c):
        return (c[..., 0] * 4096 + c[..., 1]) * 4096 + c[..., 2]

    keys = code(cells)
    order = np.argsort(keys, kind="stable")
    skeys = keys[order]
    w = -u64[ok]
    lo = np.floor((w - tol) / h).astype(np.int64) + 1024
    hi = np.floor((w + tol) / h).astype(np.int64) + 1024
    out_i, out_j = [], []
    for bits in range(8):
        pick = [(bits >> axis) & 1 for axis in range(3)]
        q = np.stack([hi[:, a] if pick[a] else lo[:, a] for a in range(3)], 1)
        dup = np.zeros(ok.size, bool)
        for a in range(3):
            if pick[a]:
                dup |= hi[:, a] == lo[:, a]
        qk = code(q)
        left = np.searchsorted(skeys, qk, "left")
        right = np.searchsorted(skeys, qk, "right")
        n = np.where(dup, 0, right - left)
        if not n.any():
            continue
        qi = np.repeat(np.arange(ok.size), n)
        off = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        out_i.append(ok[qi])
        out_j.append(ok[order[np.repeat(left, n) + off]])
    if not out_i:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_i), np.concatenate(out_j)


# ---------------------------------------------------------------------------------------------
# output


def _tangent_plane_unit(t, n):
    """Unit vectors orthogonal to the unit normals n (float64): t projected onto the tangent plane;
    where that vanishes, the coordinate axis least aligned with n, projected."""
    t = t - (t * n).sum(1, keepdims=True) * n
    length = np.sqrt((t * t).sum(1))
    weak = length < 1e-6
    if weak.any():
        nw = n[weak]
        axis = np.eye(3)[np.argmin(np.abs(nw), 1)]
        alt = axis - (axis * nw).sum(1, keepdims=True) * nw
        t[weak] = alt
        length[weak] = np.sqrt((alt * alt).sum(1))
    return t / length[:, None]
