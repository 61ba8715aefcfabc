"""Diffuse irradiance maps: exact cosine convolution and order-2 spherical harmonics (SH9).

Stored quantity (docs/conventions.md, docs/math.md 6.1): Ebar(n) = E(n)/pi = (1/pi) * integral of L(w) max(0, n.w) dw,
the cosine-weighted mean radiance, so a Lambert surface reflects c_diff * Ebar(n). A constant
environment L gives Ebar = L.

* `method="exact"`: the environment is the piecewise-constant texel function of its level 0. The
  clamped cosine is *linear* in w on each side of the horizon, so for a texel entirely above the
  horizon  sum_j L_j max(0, n.w_j) Omega_j = n . (sum_j L_j m_j)  with the texel's exact first moment
  m_j = integral over the texel of w dw. Summing moments up the pyramid therefore convolves a
  coarse level *exactly* except for the few coarse texels the horizon of n cuts through, which is
  why a 64^2 source level is enough for a 32^2 map (error measured in `jaxpbr report precompute`).
  The convolution is a chunked matrix product (memory O(chunk x source texels)).
* `method="sh9"`: Ramamoorthi & Hanrahan 2001: project L on the 9 real SH (R&H basis, no
  Condon-Shortley sign; docs/math.md 6.2) with exact solid angles, scale by A_l = (pi, 2pi/3, pi/4),
  evaluate, clamp at 0 (the ringing of a sun goes negative), divide by pi.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._api import keyword_only
from .._memory import irradiance_bytes, require
from .._numerics import HIGHEST, map_row_chunks, progress_token, row_chunk_count
from .._program_cache import cpu_jit
from .._validate import check_radiance, positive_int
from .cubemap import (
    _FACE_TABLE,
    Cubemap,
    texel_directions,
    texel_solid_angles,
)

__all__ = [
    "IRRADIANCE_METHODS",
    "SH9_BASIS_CONSTANTS",
    "irradiance",
    "irradiance_at",
    "sh9_basis",
    "sh9_irradiance",
    "sh9_project",
]

IRRADIANCE_METHODS = ("exact", "sh9")

#: Real SH basis constants, index order (0,0),(1,-1),(1,0),(1,1),(2,-2),(2,-1),(2,0),(2,1),(2,2).
SH9_BASIS_CONSTANTS = (
    0.5 / math.sqrt(math.pi),
    math.sqrt(3.0 / (4.0 * math.pi)),
    math.sqrt(3.0 / (4.0 * math.pi)),
    math.sqrt(3.0 / (4.0 * math.pi)),
    0.5 * math.sqrt(15.0 / math.pi),
    0.5 * math.sqrt(15.0 / math.pi),
    0.25 * math.sqrt(5.0 / math.pi),
    0.5 * math.sqrt(15.0 / math.pi),
    0.25 * math.sqrt(15.0 / math.pi),
)
#: Clamped-cosine convolution factors A_l for the 9 coefficients (R&H 2001: pi, 2pi/3, pi/4).
_SH9_A = (math.pi,) + (2.0 * math.pi / 3.0,) * 3 + (math.pi / 4.0,) * 5

#: Default face size of the source level the exact convolution runs on (see module docstring).
EXACT_SOURCE_SIZE = 64


def sh9_basis(d) -> jax.Array:
    """The 9 real SH basis functions of unit directions d (..., 3) -> (..., 9), R&H convention:
    c0, c1 y, c1 z, c1 x, c4 xy, c4 yz, c6 (3z^2 - 1), c4 xz, c8 (x^2 - y^2)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    c = SH9_BASIS_CONSTANTS
    return jnp.stack(
        [
            jnp.full_like(x, c[0]),
            c[1] * y,
            c[2] * z,
            c[3] * x,
            c[4] * x * y,
            c[5] * y * z,
            c[6] * (3.0 * z * z - 1.0),
            c[7] * x * z,
            c[8] * (x * x - y * y),
        ],
        axis=-1,
    )


def sh9_project(env: Cubemap, *, level: int = 0) -> jax.Array:
    """Radiance SH coefficients L_lm = sum_i L_i Y_lm(w_i) Omega_i over `level` -> (9, C).

    Texel centres and exact solid angles (uniform weights would bias by +3.1 %, docs/math.md 7.4).
    Computed in float64 when x64 is enabled, otherwise in the map's dtype.
    """
    check_radiance("sh9_project: env", env)
    lv = env.levels[level]
    return _sh9_sum(lv, *_sh9_tables(lv.shape[1], lv.dtype))


def _sh9_tables(S: int, dtype):
    """Texel directions (6,S,S,3) and solid angles (6,S,S) on the device, as arguments for the
    projection (closed over, they were program constants growing with S^2)."""
    return (jax.device_put(np.asarray(texel_directions(S), dtype)), jax.device_put(np.asarray(texel_solid_angles(S), dtype)))


def _sh9_sum(lv, dirs, omega):
    Y = sh9_basis(dirs).reshape(-1, 9)
    return jnp.matmul(Y.T, lv.reshape(-1, lv.shape[-1]) * omega.reshape(-1, 1), precision=HIGHEST)


def sh9_irradiance(coeffs, n) -> jax.Array:
    """Ebar(n) = max(0, sum_lm A_l L_lm Y_lm(n)) / pi from radiance coefficients (9, C); n (..., 3).

    -> (..., C). The clamp matters: SH9 of a single directional light dips to -0.0396 of its
    irradiance at cos = -8/15 (docs/math.md 7.4).
    """
    coeffs = jnp.asarray(coeffs)
    a = jnp.asarray(_SH9_A, coeffs.dtype)[:, None] / math.pi
    e = jnp.matmul(sh9_basis(jnp.asarray(n, coeffs.dtype)), coeffs * a, precision=HIGHEST)
    return jnp.maximum(e, 0.0)


def _texel_moments(S: int) -> np.ndarray:
    """First moments m_i = integral over texel i of w dw, float64 (6, S, S, 3), exact: the face
    moments of `_face_moments` rotated onto the six faces with the face table."""
    return np.einsum("fab,ijb->fija", _FACE_TABLE, _face_moments(S))


@functools.lru_cache(maxsize=4)
def _face_moments(S: int) -> np.ndarray:
    """First moments of the texels of one face in its plane coordinates (sc, tc, 1), float64
    (S, S, 3), read-only.

    A texel is a spherical quadrilateral; its moment is (1/2) sum over its edges of
    theta_e * normalize(u_e x u_e+1), with u the unit corner directions in counter-clockwise order
    seen from outside and theta_e the edge's arc length (Arvo 1995, the "vector irradiance" of a
    polygon).
    """
    e = np.linspace(-1.0, 1.0, S + 1)
    x0, x1 = e[None, :-1], e[None, 1:]  # sc varies along j (columns)
    y0, y1 = e[:-1, None], e[1:, None]  # tc varies along i (rows)

    def unit(x, y):
        x, y = np.broadcast_arrays(x, y)
        v = np.stack([x, y, np.ones_like(x)], -1)
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    corners = [unit(x0, y0), unit(x1, y0), unit(x1, y1), unit(x0, y1)]  # CCW seen from +z (outside)
    m = np.zeros((S, S, 3))
    for k in range(4):
        u, v = corners[k], corners[(k + 1) % 4]
        c = np.cross(u, v)
        sn = np.linalg.norm(c, axis=-1, keepdims=True)
        theta = np.arctan2(sn, np.sum(u * v, -1, keepdims=True))
        m += 0.5 * theta * c / sn
    m.setflags(write=False)
    return m


def _moment_pyramid(lv, mloc, source_size: int):
    """Radiance-weighted moments per channel (6,s,s,C,3) at face size s: sums of L_i m_i over the
    level-0 texels (6,S,S,C) that each coarse texel covers (exact power). mloc: the face moments
    (S,S,3) (`_face_moments`), an argument of the program (as a (6,S,S,3) constant it cost
    300 MB of program and gigabytes of compile memory at 2048^2; issue 13); the sums run in face
    coordinates and are rotated onto the faces at the coarse size."""
    S, C = lv.shape[1], lv.shape[-1]
    f = S // source_size
    lm = (lv[..., :, None] * mloc[None, :, :, None, :]).reshape(6, source_size, f, source_size, f, C, 3).sum((2, 4))
    return jnp.einsum("fab,fijcb->fijca", jnp.asarray(_FACE_TABLE, lv.dtype), lm, precision=HIGHEST)


def irradiance_at(
    env: Cubemap, n, *, method: str = "exact", source_size: int | None = None, chunk: int = 16, progress=None
):
    """Ebar = E/pi at arbitrary unit normals n (..., 3) -> (..., C). See `irradiance`."""
    if method not in IRRADIANCE_METHODS:
        raise ValueError(f"unknown irradiance method {method!r}; choose one of {IRRADIANCE_METHODS}")
    check_radiance("irradiance_at: env", env)
    n = jnp.asarray(n, env.dtype)
    s = _source_size(env.face_size, source_size) if method == "exact" else 0
    # Bound the (chunk, Ns, C) intermediate of the exact convolution to ~2^24 elements. The
    # default 16 keeps it in cache (64^2 source: 16 -> 0.27 s, 227 -> 2.8 s for a 64^2 map).
    chunk = max(1, min(positive_int("chunk", chunk), (1 << 24) // max(1, 6 * s * s * env.channels)))
    total = row_chunk_count(math.prod(n.shape[:-1]), chunk) if method == "exact" else 1
    if method == "exact":
        tables = jax.device_put(_face_moments(env.face_size).astype(env.dtype))
    else:
        tables = _sh9_tables(env.face_size, env.dtype)
    with progress_token(progress if method == "exact" else None, total) as token:
        out = _irradiance_at(env.levels[0], n, token, tables, method=method, source_size=s, chunk=chunk)
        if token is not None:
            out = jax.block_until_ready(out)
    if progress is not None and method != "exact":
        progress(1, 1)
    return out


@functools.partial(cpu_jit, static_argnames=("method", "source_size", "chunk"))
def _irradiance_at(level0, n, token, tables, *, method: str, source_size: int, chunk: int):
    """`irradiance_at` as one compiled program (moments, pyramid sums and the chunked convolution);
    token: a `progress_token` or None; tables: `_face_moments` of level0's face size (exact) or
    the `_sh9_tables` (sh9), arguments rather than constants."""
    env = Cubemap((level0,))
    if method == "sh9":
        return sh9_irradiance(_sh9_sum(level0, *tables), n)
    lm = _moment_pyramid(level0, tables, source_size).reshape(-1, env.channels, 3)  # (Ns, C, 3)
    out = _exact_conv(n.reshape(-1, 3), lm, chunk=chunk, token=token)
    return out.reshape(n.shape[:-1] + (env.channels,))


def _exact_conv(n, lm, *, chunk, token=None):
    C = lm.shape[1]
    lmT = jnp.transpose(lm, (2, 1, 0)).reshape(3, -1)  # (3, C*Ns): each channel's sources contiguous

    def one(nc):
        # n . (L m) per channel and source texel (a (chunk,3)@(3,C*Ns) product), clamped at the
        # horizon, summed over the source texels (the contiguous last axis).
        dots = jnp.matmul(nc, lmT, precision=HIGHEST).reshape(nc.shape[0], C, -1)
        return jnp.sum(jnp.maximum(dots, 0.0), axis=-1) / math.pi

    return map_row_chunks(one, chunk, n, token=token)


def _source_size(S: int, source_size: int | None) -> int:
    if source_size is None:
        source_size = min(S, EXACT_SOURCE_SIZE)
    source_size = positive_int("source_size", source_size)
    if source_size > S or S % source_size or (S // source_size) & (S // source_size - 1):
        raise ValueError(
            f"source_size {source_size} must divide the environment face size {S} by a power of two"
        )
    return source_size


@keyword_only("size")
def irradiance(
    env: Cubemap,
    *,
    size: int = 32,
    method: str = "exact",
    source_size: int | None = None,
    chunk: int = 16,
    progress=None,
) -> Cubemap:
    """Irradiance cube map storing Ebar(n) = E(n)/pi at the texel centres of a `size`^2 cube.

    env: environment Cubemap (level 0 is the radiance; its face size a power-of-two multiple of
        `source_size`).
    method: "exact" (cosine convolution through texel moments, see module docstring) or "sh9".
    source_size: face size of the level the exact convolution sums over (default min(S, 64));
        `source_size = env.face_size` is the full-resolution convolution.
    progress: optional callable(done, total), in chunks of output texels (see `prefilter`: called
        from XLA's callback thread while the program runs, and at the end).
    Returns a one-level Cubemap (6, size, size, C) with `info` recording quantity and method.
    """
    size = positive_int("size", size)
    require(f"a {size}^2 irradiance map", irradiance_bytes(size), where="irradiance")
    if method not in IRRADIANCE_METHODS:
        raise ValueError(f"unknown irradiance method {method!r}; choose one of {IRRADIANCE_METHODS}")
    check_radiance("irradiance: env", env)
    dirs = jax.device_put(np.asarray(texel_directions(size), env.dtype))  # a copy, no XLA program
    vals = irradiance_at(env, dirs, method=method, source_size=source_size, chunk=chunk, progress=progress)
    info = {
        "quantity": "Ebar = E/pi (cosine-weighted mean radiance), value at texel centres",
        "irradiance_method": method,
    }
    if method == "exact":
        info["irradiance_source_size"] = str(_source_size(env.face_size, source_size))
    return Cubemap((vals,), info)
