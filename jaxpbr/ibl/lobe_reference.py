"""What the GGX and Charlie prefiltered chains share: their float64 brute-force reference, and the
metadata that lets an engine reproduce their lookup.

The reference
-------------
LD(R) = sum K(R.l) L(l) Omega(l) / sum K(R.l) Omega(l) over every texel of an environment's level 0,
each split into q x q sub-texels with their exact share of its solid angle, for a lobe K given as a
function of c = R.l (n = v = R). `jaxpbr.ibl.specular.prefilter_reference` passes the GGX lobe and
`jaxpbr.ibl.sheen_prefilter.charlie_reference` the Charlie one; everything else (sub-texel
geometry, blocking, float64 accumulation) is this one code.

The lookup metadata
-------------------
`chain_lookup_metadata` writes the keys both chains carry (blend and formula, smallest face, each
level's mean cosine, and "lod_table": the lod at ``LOD_TABLE_STEPS`` nodes per level interval).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._numerics import HIGHEST, map_row_chunks
from .._validate import choice, positive_int
from .cubemap import Cubemap, _subtexel_coords, face_to_dir, texel_solid_angles

__all__ = ["LOD_TABLE_STEPS", "chain_lookup_metadata", "check_lod_blend", "lobe_reference", "lobe_reference_sum"]

#: Entries per level interval of the metadata's "lod_table" (for engines; see `chain_lookup_metadata`).
LOD_TABLE_STEPS = 8


def check_lod_blend(lod_blend, options) -> str:
    """`lod_blend` if it is one of `options` (the blends a chain supports), else a ValueError."""
    return choice("lod_blend", lod_blend, options)


def chain_lookup_metadata(
    num_levels: int, *, lod_blend: str, formula: str, face_size: int, level_mean_cosine, table, abscissa: str,
    level_alpha=None,
) -> dict:
    """The lookup keys of a prefiltered chain, in the order they are written: "lod_blend",
    "lod_formula", "chain_floor" (the face of the chain's last level), "level_alpha" (when given),
    "level_mean_cosine", "lod_table" (the lod at the table's nodes) and "lod_table_abscissa" (what
    the nodes are). Numbers are written with 9 (per level) and 6 (table) significant digits."""
    M = positive_int("num_levels", num_levels)
    meta = {
        "lod_blend": lod_blend,
        "lod_formula": formula,
        "chain_floor": str(max(1, positive_int("face_size", face_size) >> (M - 1))),
    }
    if level_alpha is not None:
        meta["level_alpha"] = ",".join(f"{x:.9g}" for x in level_alpha)
    meta["level_mean_cosine"] = ",".join(f"{x:.9g}" for x in level_mean_cosine)
    meta["lod_table"] = ",".join(f"{x:.6g}" for x in np.asarray(table))
    meta["lod_table_abscissa"] = abscissa
    return meta


# ------------------------------------------------------------------------------------------
# float64 reference
# ------------------------------------------------------------------------------------------


def lobe_reference(env: Cubemap, dirs, lobe, alpha: float, *, q: int, chunk: int, budget: int) -> np.ndarray:
    """float64 LD(R) at unit directions `dirs` (..., 3) under `lobe` -> (..., C) float64 NumPy.

    lobe(c, alpha) -> K: the lobe's weight at c = R.l (any positive scale: it cancels in the
    ratio), traceable in float64; a module-level function (it is a static argument of the
    compiled sum). q: sub-texels per texel side. chunk: output directions per pass. budget:
    about how many float64 kernel entries a (chunk, source block) pass may hold; the source rows
    per block follow from it."""
    dirs = np.asarray(dirs, np.float64)
    shape = dirs.shape[:-1]
    S0 = env.face_size
    with jax.enable_x64(True):
        B = max(1, min(S0, budget // (chunk * S0 * q * q)))  # source rows per block
        nb = -(-S0 // B)
        coords = _subtexel_coords(S0, q)  # (S0, q): the sub-texel centres' face coordinates
        pad = nb * B - S0
        om = np.concatenate([texel_solid_angles(S0)[0], np.zeros((pad, S0))])  # padded rows weigh 0
        t = np.concatenate([coords, np.repeat(coords[-1:], pad, 0)])
        L = env.levels[0]
        L = jnp.concatenate([L, jnp.zeros((6, pad) + L.shape[2:], L.dtype)], 1) if pad else L
        out = np.asarray(lobe_reference_sum(
            jnp.asarray(dirs.reshape(-1, 3)), L, jax.device_put(t), jax.device_put(coords), jax.device_put(om),
            jnp.float64(alpha), lobe=lobe, q=q, rows=B, chunk=chunk,
        ))
    C = env.channels
    return (out[:, :C] / out[:, C:]).reshape(shape + (C,))


@functools.partial(jax.jit, static_argnames=("lobe", "q", "rows", "chunk"))
def lobe_reference_sum(R, L, t, s, om, alpha, *, lobe, q, rows, chunk):
    """sum over every source sub-texel of lobe(R.l, alpha) (L Omega, Omega) -> (N, C + 1), float64.

    L (6, S', S, C) the level (rows padded to whole blocks), t (S', q) / s (S, q) the sub-texel
    face coordinates along rows / columns, om (S', S) one face's texel solid angles (padded rows 0).
    The sources are generated on the device block by block (`rows` texel rows of a face at a
    time) inside each chunk of output directions: no (6 S^2 q^2, 3) source array is ever held
    (at 2048^2 faces it would be 0.6 GB on the host plus its device copy and the weights)."""
    S, C = s.shape[0], L.shape[-1]
    f64 = jnp.float64
    ss = jnp.broadcast_to(s[None, :, None, :], (rows, S, q, q)).reshape(rows, S, q * q)

    def block(face, Rc, acc, start):
        ct = jax.lax.dynamic_slice_in_dim(t, start, rows)  # (rows, q)
        tt = jnp.broadcast_to(ct[:, None, :, None], (rows, S, q, q)).reshape(rows, S, q * q)
        d = face_to_dir(face, ss, tt, xp=jnp)  # a Python int face: no constant-folded face table
        r2 = jnp.sum(d * d, -1)
        w = r2**-1.5
        w = w / jnp.sum(w, -1, keepdims=True)
        d = (d / jnp.sqrt(r2)[..., None]).reshape(-1, 3)
        omq = jax.lax.dynamic_slice_in_dim(om, start, rows)[..., None] * w  # (rows, S, q*q) sub-texel solid angles
        Lb = jax.lax.dynamic_slice_in_dim(L[face], start, rows).astype(f64)  # (rows, S, C)
        Lw = jnp.concatenate([Lb[:, :, None, :] * omq[..., None], omq[..., None]], -1).reshape(-1, C + 1)
        k = lobe(jnp.matmul(Rc, d.T, precision=HIGHEST), alpha)  # (chunk, P)
        return acc + jnp.matmul(k, Lw, precision=HIGHEST)

    def one(Rc):
        acc = jnp.zeros((Rc.shape[0], C + 1), f64)
        starts = jnp.arange(0, L.shape[1], rows)
        for face in range(6):
            acc, _ = jax.lax.scan(lambda a, st, f=face: (block(f, Rc, a, st), None), acc, starts)
        return acc

    return map_row_chunks(one, chunk, R.astype(f64))
