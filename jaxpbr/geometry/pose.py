"""Posing meshes: node transforms, the hierarchy's world matrices, morph targets and skinning
(glTF 2.0 §3.5.3 transformations, §3.7.2.2 morph targets, §3.7.3 skins), for NumPy and JAX alike.

* A node's local matrix is T · R · S (translation, rotation quaternion x y z w, scale), or the
  node's `matrix`; its world matrix is its parent's world matrix times its local matrix.
* Morph targets add weighted deltas to the base attributes: p = p0 + Σ_k w_k Δp_k (likewise the
  normals and the tangents' xyz, renormalised after).
* Skinning: each vertex blends its joints' matrices J_i = world(joint_i) · inverseBind_i with its
  weights, M = Σ_i w_i J_i, and p' = M p. The skinned mesh's node transform is not applied (the
  joints place the mesh). Normals go through the cofactor matrix of M's 3 × 3 part (det · M⁻ᵀ,
  defined also where M is singular) with the sign of det, tangents through M (their w times the
  sign of det); both renormalised. Morphing comes first, then skinning.

Every function takes `xp` (numpy or jax.numpy); with jax.numpy the products run at the highest
precision (`jaxpbr._numerics.HIGHEST`, as every jaxpbr product), so gradients reach the node
transforms, the key values, the morph weights and the vertices through the same code that poses an
asset at load time.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "deform",
    "face_normals",
    "hierarchy_levels",
    "place",
    "morph",
    "normal_matrices",
    "quaternion_matrices",
    "skin",
    "skin_matrices",
    "trs_matrices",
    "unit_rows",
    "world_matrices",
]


def _einsum(xp, spec, *ops):
    if xp is np:
        return np.einsum(spec, *ops)
    from .._numerics import HIGHEST

    return xp.einsum(spec, *ops, precision=HIGHEST)


def quaternion_matrices(q, xp=np):
    """(..., 3, 3) rotations of quaternions (..., 4) = (x, y, z, w), normalised first (a zero
    quaternion gives the identity's scale 0: the zero matrix plus nothing; callers pass unit ones)."""
    q = unit_rows(q, xp)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def trs_matrices(t, r, s, xp=np):
    """(..., 4, 4) local matrices T · R · S of translations (..., 3), rotations (..., 4) and scales (..., 3)."""
    rs = quaternion_matrices(r, xp) * s[..., None, :]
    top = xp.concatenate([rs, t[..., :, None]], axis=-1)
    bottom = xp.broadcast_to(xp.asarray([0.0, 0.0, 0.0, 1.0], dtype=top.dtype), top.shape[:-2] + (1, 4))
    return xp.concatenate([top, bottom], axis=-2)


def hierarchy_levels(parents) -> tuple[np.ndarray, ...]:
    """The nodes grouped by depth (roots first), from parents (N,) (-1 for a root): each group's
    parents lie in the groups before it, so `world_matrices` fills a level with one product."""
    parents = np.asarray(parents, np.int64)
    depth = np.full(parents.shape, -1, np.int64)
    depth[parents < 0] = 0
    for _ in range(parents.shape[0]):
        todo = depth < 0
        if not todo.any():
            break
        ready = todo & (depth[np.maximum(parents, 0)] >= 0)
        if not ready.any():
            raise ValueError("the parent links hold a cycle")
        depth[ready] = depth[parents[ready]] + 1
    return tuple(np.flatnonzero(depth == d) for d in range(int(depth.max()) + 1)) if parents.size else ()


def world_matrices(local, parents, levels, xp=np):
    """(N, 4, 4) world matrices of local matrices (N, 4, 4), given parents (N,) and
    `hierarchy_levels(parents)` (static: one product per level)."""
    parents = np.asarray(parents)
    world = local
    for lvl in levels[1:]:
        w = _einsum(xp, "nij,njk->nik", world[parents[lvl]], local[lvl])
        world = world.at[lvl].set(w) if xp is not np else _set(world, lvl, w)
    return world


def _set(a, idx, v):
    a = a.copy()
    a[idx] = v
    return a


def morph(base, deltas, weights, xp=np):
    """base (V, C) + Σ_k weights[k] deltas[k] (deltas (K, V, C), weights (K,))."""
    if deltas is None or deltas.shape[0] == 0:
        return base
    return base + _einsum(xp, "k,kvc->vc", weights, deltas)


def skin_matrices(world, joints, inverse_bind, xp=np):
    """(J, 4, 4) joint matrices world[joints] · inverseBind."""
    return _einsum(xp, "jab,jbc->jac", world[np.asarray(joints)], inverse_bind)


def normal_matrices(m, xp=np):
    """(..., 3, 3) matrices taking normals through the linear maps m (..., 3, 3): the cofactor
    matrix (det · m⁻ᵀ, whose columns are cross products of m's columns) times the sign of det. Exact
    for any invertible m, finite for a singular one; callers renormalise."""
    c0, c1, c2 = m[..., :, 0], m[..., :, 1], m[..., :, 2]
    cof = xp.stack([xp.cross(c1, c2), xp.cross(c2, c0), xp.cross(c0, c1)], axis=-1)
    det = xp.sum(c0 * cof[..., :, 0], axis=-1)
    return cof * xp.where(det < 0, -1.0, 1.0)[..., None, None], det


def unit_rows(v, xp=np):
    """v / |v| along the last axis; zero rows stay zero, with a finite gradient (double where)."""
    n2 = xp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > 0
    return xp.where(ok, v / xp.sqrt(xp.where(ok, n2, 1.0)), 0.0)


def skin(positions, joint_mats, joints, weights, normals=None, tangents=None, xp=np):
    """Linear blend skinning: (positions (V, 3), normals (V, 3) or None, tangents (V, 4) or None).

    joint_mats: (J, 4, 4) from `skin_matrices`; joints: (V, n) indices into them; weights: (V, n)."""
    m = _einsum(xp, "vi,viab->vab", weights, joint_mats[:, :3, :][joints])  # (V, 3, 4): the affine rows only
    a = m[:, :, :3]
    pos = _einsum(xp, "vab,vb->va", a, positions) + m[:, :3, 3]
    nrm = tan = None
    if normals is not None or tangents is not None:
        nm, det = normal_matrices(a, xp)
        if normals is not None:
            nrm = unit_rows(_einsum(xp, "vab,vb->va", nm, normals), xp)
        if tangents is not None:
            xyz = unit_rows(_einsum(xp, "vab,vb->va", a, tangents[:, :3]), xp)
            tan = xp.concatenate([xyz, tangents[:, 3:] * xp.where(det < 0, -1.0, 1.0)[:, None]], axis=-1)
    return pos, nrm, tan


def face_normals(positions, tris, xp=np):
    """(T, 3) unit normals of counter-clockwise triangles (zero for degenerate ones)."""
    a, b, c = positions[tris[:, 0]], positions[tris[:, 1]], positions[tris[:, 2]]
    return unit_rows(xp.cross(b - a, c - a), xp)


def deform(positions, normals, tangents, *, tris=None, flat_normals=False, targets=None, weights=None,
           joint_mats=None, joints=None, joint_weights=None, xp=np):
    """A mesh primitive's vertices morphed (targets {'POSITION'|'NORMAL'|'TANGENT': (K, V, 3)} by
    weights (K,)) then skinned (joint_mats (J, 4, 4), joints and joint_weights (V, n)):
    (positions, normals, tangents or None). Flat normals (the file had none) are made again from
    the morphed triangles (tris (T, 3), counter-clockwise); the others take the NORMAL deltas."""
    pos, nrm, tan = positions, normals, tangents
    if targets and weights is not None:
        pos = morph(pos, targets.get("POSITION"), weights, xp)
        if flat_normals:
            fn = xp.repeat(face_normals(pos, tris, xp), 3, axis=0)
            nrm = nrm.at[tris.ravel()].set(fn) if xp is not np else _set(nrm, tris.ravel(), fn)
        elif "NORMAL" in targets:
            nrm = unit_rows(morph(nrm, targets["NORMAL"], weights, xp), xp)
        if tan is not None and "TANGENT" in targets:
            tan = xp.concatenate([unit_rows(morph(tan[:, :3], targets["TANGENT"], weights, xp), xp), tan[:, 3:]], axis=-1)
    if joint_mats is not None:
        pos, nrm, tan = skin(pos, joint_mats, joints, joint_weights, nrm, tan, xp)
    return pos, nrm, tan


def place(matrix, positions, normals, tangents, xp=np):
    """Vertices through one affine matrix (4, 4): positions, normals (cofactor, renormalised),
    tangents (xyz through the matrix, w times the sign of its determinant)."""
    a = matrix[:3, :3]
    pos = _einsum(xp, "ab,vb->va", a, positions) + matrix[:3, 3]
    nm, det = normal_matrices(a, xp)
    nrm = unit_rows(_einsum(xp, "ab,vb->va", nm, normals), xp)
    tan = None
    if tangents is not None:
        xyz = unit_rows(_einsum(xp, "ab,vb->va", a, tangents[:, :3]), xp)
        tan = xp.concatenate([xyz, tangents[:, 3:] * xp.where(det < 0, -1.0, 1.0)], axis=-1)
    return pos, nrm, tan
