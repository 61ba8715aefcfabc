"""Cube maps: direction <-> texel, exact texel solid angles, seam-aware lookup, pyramids, equirect.

Conventions (docs/conventions.md; written into every output's metadata):

* Faces in the order +X, -X, +Y, -Y, +Z, -Z with the OpenGL / KTX orientation (the major-axis table
  of the OpenGL spec, "Cube Map Texture Selection"): for a direction r with major axis ma,

      face | sc   tc   ma          face | sc   tc   ma
      +X   | -rz  -ry  rx          -Y   | +rx  -rz  ry
      -X   | +rz  -ry  rx          +Z   | +rx  -ry  rz
      +Y   | +rx  +rz  ry          -Z   | -rx  -ry  rz

  s = (sc/|ma| + 1)/2, t = (tc/|ma| + 1)/2, and `levels[m][f, i, j]` is the texel of face f whose
  centre is s = (j + 0.5)/S, t = (i + 0.5)/S.
* Equirect (lat-long) images (H, 2H, C): row 0 is the top (+Y); for a direction d,
  u = 0.5 + atan2(d.z, d.x)/(2 pi), v_up = 0.5 + asin(d.y)/pi, column = u W, row = (1 - v_up) H.
* A texel's value is the mean radiance over its footprint (area filter); pyramids average the four
  children weighted by their exact solid angles, so every level carries the same total power.

Lookups are seam-aware: every level is padded by one texel taken from the neighbouring faces (the
three texels meeting at a cube corner are averaged into the corner pad), so bilinear filtering is
continuous across edges and corners, like GL's TEXTURE_CUBE_MAP_SEAMLESS.
"""

from __future__ import annotations

import functools
import math
import weakref
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .._api import keyword_only
from .._interp import bilinear, lerp2
from .._memory import cube_bytes, require
from .._numerics import HIGHEST, computed_once, is_concrete, trace_state_clean
from .._program_cache import LOOP_EMITTERS, cached_jit, cpu_jit
from .._pytree import Pytree, leaf, static, unchecked
from .._validate import positive_int

__all__ = [
    "FACE_NAMES",
    "Cubemap",
    "dir_to_equirect",
    "dir_to_face",
    "equirect_directions",
    "equirect_to_dir",
    "face_to_dir",
    "texel_directions",
    "texel_solid_angles",
]

FACE_NAMES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


# ------------------------------------------------------------------------------------------
# Direction <-> (face, s, t)
# ------------------------------------------------------------------------------------------


@keyword_only("xp")
def face_to_dir(face, s, t, *, xp=jnp):
    """(face, s, t) -> un-normalised direction on the unit cube, (..., 3).

    `face` int array (0..5), `s, t` in [0, 1] (values outside extend the face's plane, which the
    seam padding uses). The inverse of the major-axis table in the module docstring.
    """
    sc = 2.0 * s - 1.0
    tc = 2.0 * t - 1.0
    coef = _FACE_TABLE if xp is np else jnp.asarray(_FACE_TABLE)
    T = coef[xp.asarray(face).astype(np.int32)]  # (..., 3 out, 3 in: sc, tc, 1)
    return T[..., 0] * sc[..., None] + T[..., 1] * tc[..., None] + T[..., 2]


# direction = T[face] @ (sc, tc, 1): the inverse of the major-axis table.
_FACE_TABLE = np.array(
    [
        [[0, 0, 1], [0, -1, 0], [-1, 0, 0]],  # +X: ( 1, -tc, -sc)
        [[0, 0, -1], [0, -1, 0], [1, 0, 0]],  # -X: (-1, -tc,  sc)
        [[1, 0, 0], [0, 0, 1], [0, 1, 0]],  # +Y: (sc,   1,  tc)
        [[1, 0, 0], [0, 0, -1], [0, -1, 0]],  # -Y: (sc,  -1, -tc)
        [[1, 0, 0], [0, -1, 0], [0, 0, 1]],  # +Z: (sc, -tc,   1)
        [[-1, 0, 0], [0, -1, 0], [0, 0, -1]],  # -Z: (-sc, -tc, -1)
    ],
    dtype=np.float64,
)


@keyword_only("xp")
def dir_to_face(d, *, xp=jnp):
    """Direction (..., 3) (any length > 0) -> (face int32 (...), s (...), t (...)), s, t in [0, 1].

    Ties between axes (exact diagonals) go to x before y before z. A zero vector maps to the centre
    of +X (finite value and gradient; the direction is undefined there).
    """
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    ax, ay, az = xp.abs(x), xp.abs(y), xp.abs(z)
    is_x = (ax >= ay) & (ax >= az)
    is_y = ~is_x & (ay >= az)
    ma = xp.where(is_x, ax, xp.where(is_y, ay, az))
    face = xp.where(is_x, xp.where(x >= 0, 0, 1), xp.where(is_y, xp.where(y >= 0, 2, 3), xp.where(z >= 0, 4, 5)))
    sc = xp.where(is_x, xp.where(x >= 0, -z, z), xp.where(is_y, x, xp.where(z >= 0, x, -x)))
    tc = xp.where(is_x, -y, xp.where(is_y, xp.where(y >= 0, z, -z), -y))
    # Double where: 0/0 at the zero vector would poison the gradient.
    ok = ma > 0
    inv = xp.where(ok, 1.0 / xp.where(ok, ma, 1.0), 0.0)
    s = xp.clip(0.5 * (sc * inv + 1.0), 0.0, 1.0)
    t = xp.clip(0.5 * (tc * inv + 1.0), 0.0, 1.0)
    return face.astype(np.int32), s, t


@functools.lru_cache(maxsize=32)
def _texel_directions_np(size: int) -> np.ndarray:
    c = (np.arange(size, dtype=np.float64) + 0.5) / size
    s = np.broadcast_to(c[None, None, :], (6, size, size))
    t = np.broadcast_to(c[None, :, None], (6, size, size))
    face = np.broadcast_to(np.arange(6)[:, None, None], (6, size, size))
    d = face_to_dir(face, s, t, xp=np)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    d.setflags(write=False)
    return d


def texel_directions(size: int) -> np.ndarray:
    """Unit directions of every texel centre of a `size`^2 cube face set, float64 (6, S, S, 3)."""
    return _texel_directions_np(positive_int("size", size))


@functools.lru_cache(maxsize=32)
def _solid_angles_np(size: int) -> np.ndarray:
    # Exact: the solid angle of the region [0,x]x[0,y] of the plane z = 1 seen from the origin is
    # A(x, y) = atan2(x y, sqrt(x^2 + y^2 + 1)); a texel is the signed sum over its four corners
    # (docs/math.md 3.4; Filament CubemapUtils::solidAngle). The six faces are identical.
    e = np.linspace(-1.0, 1.0, size + 1, dtype=np.float64)
    x0, x1 = e[None, :-1], e[None, 1:]
    y0, y1 = e[:-1, None], e[1:, None]
    area = lambda x, y: np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))
    om = area(x0, y0) - area(x0, y1) - area(x1, y0) + area(x1, y1)
    om = np.broadcast_to(om, (6, size, size)).copy()
    om.setflags(write=False)
    return om


def texel_solid_angles(size: int) -> np.ndarray:
    """Exact solid angle (sr) of every texel, float64 (6, S, S); they sum to 4 pi."""
    return _solid_angles_np(positive_int("size", size))


# ------------------------------------------------------------------------------------------
# Equirect <-> direction
# ------------------------------------------------------------------------------------------


@keyword_only("xp")
def equirect_to_dir(u, v_up, *, xp=jnp):
    """(u, v_up) in [0, 1] -> unit direction (..., 3), the inverse of `dir_to_equirect`."""
    phi = (u - 0.5) * (2.0 * math.pi)
    lat = (v_up - 0.5) * math.pi
    phi, lat = xp.broadcast_arrays(phi, lat)
    c = xp.cos(lat)
    return xp.stack([c * xp.cos(phi), xp.sin(lat), c * xp.sin(phi)], axis=-1)


def dir_to_equirect(d):
    """Unit direction (..., 3) -> (u, v_up): u = 0.5 + atan2(z, x)/(2 pi), v_up = 0.5 + asin(y)/pi."""
    u = 0.5 + jnp.arctan2(d[..., 2], d[..., 0]) / (2.0 * math.pi)
    v_up = 0.5 + jnp.arcsin(jnp.clip(d[..., 1], -1.0, 1.0)) / math.pi
    return u, v_up


@keyword_only("width")
def equirect_directions(height: int, *, width: int | None = None) -> np.ndarray:
    """Unit directions of the pixel centres of an equirect image, float64 (H, W, 3)."""
    height = positive_int("height", height)
    width = 2 * height if width is None else positive_int("width", width)
    u = (np.arange(width) + 0.5) / width
    v_up = 1.0 - (np.arange(height) + 0.5) / height
    return equirect_to_dir(u[None, :], v_up[:, None], xp=np)


def _equirect_row_solid_angles(height: int, width: int) -> np.ndarray:
    # Exact per-pixel solid angle of row k: (2 pi / W)(cos(pi k/H) - cos(pi (k+1)/H)) (docs/math.md 3.4).
    k = np.arange(height + 1)
    return (2.0 * math.pi / width) * -np.diff(np.cos(np.pi * k / height))


# ------------------------------------------------------------------------------------------
# Seam padding and lookup
# ------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=64)
def pad_index(size: int) -> np.ndarray:
    """Flat source indices (6, S+2, S+2, 3) into a (6*S*S) face array for the one-texel seam pad.

    Interior pads repeat their own index 3 times; an edge pad is the nearest texel of the
    neighbouring face (found by extending the face plane one half texel past the edge and
    re-projecting); a corner pad averages the three texels that meet at the cube corner.
    """
    S = size
    ii, jj = np.meshgrid(np.arange(-1, S + 1), np.arange(-1, S + 1), indexing="ij")
    idx = np.stack([_pad_sources(S, f, ii.ravel(), jj.ravel()).reshape(S + 2, S + 2, 3) for f in range(6)])
    idx.setflags(write=False)
    return idx


def _pad_level(level, xp=jnp):
    """(6, S, S, C) -> (6, S+2, S+2, C) with the seam pad of `pad_index`: the interior copied,
    the border (`_pad_border`: O(S) indices, not a (6, S+2, S+2, 3) table, which XLA embedded as
    a constant: 75 MB at 1024^2 and ~1 GB of compile memory; issue 13) gathered and scattered.
    xp: jnp (traceable) or np (on the host, `padded`: the same values)."""
    S, C = level.shape[1], level.shape[3]
    pos, src, corner = _pad_border(S)
    g = level.reshape(6 * S * S, C)[xp.asarray(src)]  # (E, 3, C)
    # Only the corner pads average (three distinct texels); elsewhere the three indices are equal
    # and the texel is copied exactly ((3v)/3 is not always v in floating point).
    third = np.dtype(level.dtype).type(1.0 / 3.0)
    val = xp.where(xp.asarray(corner)[:, None], (g[:, 0] + g[:, 1] + g[:, 2]) * third, g[:, 0])
    out = xp.pad(level, ((0, 0), (1, 1), (1, 1), (0, 0))).reshape(-1, C)
    if xp is np:
        out[pos] = val
    else:
        out = out.at[jnp.asarray(pos)].set(val)
    return out.reshape(6, S + 2, S + 2, C)


@functools.lru_cache(maxsize=64)
def _pad_border(S: int):
    """The border cells of the seam pad: flat positions (E,) into (6, S+2, S+2), their three
    source indices (E, 3) into (6*S*S) (as in `pad_index`) and whether each is a corner (E,);
    E = 6 (4S + 4). int32 / bool NumPy arrays."""
    k = np.arange(-1, S + 1)
    ii = np.concatenate([np.full(S + 2, -1), np.full(S + 2, S), np.arange(S), np.arange(S)])
    jj = np.concatenate([k, k, np.full(S, -1), np.full(S, S)])
    pos, src, corner = [], [], []
    for f in range(6):
        pos.append((f * (S + 2) + ii + 1) * (S + 2) + jj + 1)
        src.append(_pad_sources(S, f, ii, jj))
        corner.append(((ii < 0) | (ii >= S)) & ((jj < 0) | (jj >= S)))
    out = np.concatenate(pos).astype(np.int32), np.concatenate(src).astype(np.int32), np.concatenate(corner)
    for a in out:
        a.setflags(write=False)
    return out


def _pad_sources(S: int, f: int, ii, jj):
    """The three source indices (n, 3) of the pad cells (ii, jj) in [-1, S] of face f (see
    `pad_index`): interior cells repeat their own index; an edge pad is the nearest texel of the
    neighbouring face (the face plane extended one half texel past the edge and re-projected); a
    corner pad lists its own clamped texel and the two across its edges."""

    def nearest(i, j):
        d = face_to_dir(np.full(np.shape(i), f), (j + 0.5) / S, (i + 0.5) / S, xp=np)
        f2, s2, t2 = dir_to_face(d, xp=np)
        j2 = np.clip(np.floor(s2 * S).astype(np.int64), 0, S - 1)
        i2 = np.clip(np.floor(t2 * S).astype(np.int64), 0, S - 1)
        return (f2 * S + i2) * S + j2

    ci, cj = np.clip(ii, 0, S - 1), np.clip(jj, 0, S - 1)
    own = (f * S + ci) * S + cj
    inside_i, inside_j = (ii >= 0) & (ii < S), (jj >= 0) & (jj < S)
    edge_a = nearest(ii, cj)  # out in i only (or corner: the texel across the i edge)
    edge_b = nearest(ci, jj)  # out in j only (or corner: the texel across the j edge)
    one = np.where(inside_i & inside_j, own, np.where(~inside_i & inside_j, edge_a, edge_b))
    corner = ~inside_i & ~inside_j
    return np.stack([np.where(corner, own, one), np.where(corner, edge_a, one), np.where(corner, edge_b, one)], -1)


@functools.lru_cache(maxsize=64)
def corner_mask(S: int) -> np.ndarray:
    m = np.zeros((6, S + 2, S + 2), bool)
    m[:, [0, 0, -1, -1], [0, -1, 0, -1]] = True
    return m


class _Pyramid:
    """All levels padded and concatenated into one flat (N, C) buffer, for gathers at dynamic LOD."""

    def __init__(self, levels: Sequence[jax.Array] | None, *, flat=None, sizes=None):
        if levels is not None:
            sizes = [lv.shape[1] for lv in levels]
            pads = [_pad_level(lv) for lv in levels]
            flat = jnp.concatenate([p.reshape(-1, p.shape[-1]) for p in pads], axis=0)
        self.flat = flat
        offs = np.cumsum([0] + [6 * (s + 2) ** 2 for s in sizes])[:-1]
        self.offsets = np.asarray(offs, np.int32)
        self.sizes = np.asarray(sizes, np.int32)
        self.num_levels = len(sizes)

    def bilinear(self, face, s, t, level):
        """Bilinear lookup at integer `level` (array, same shape as s), -> (..., C)."""
        if self.num_levels == 1:
            S = float(self.sizes[0])
            off = 0
            Si = int(self.sizes[0])
        else:
            Si = jnp.asarray(self.sizes)[level]
            S = Si.astype(s.dtype)
            off = jnp.asarray(self.offsets)[level]
        W = Si + 2
        # Padded texel coordinates: centre of texel j sits at j + 1.
        x = s * S + 0.5
        y = t * S + 0.5
        x0f = jnp.clip(jnp.floor(x), 0, S)
        y0f = jnp.clip(jnp.floor(y), 0, S)
        x0 = x0f.astype(jnp.int32)
        y0 = y0f.astype(jnp.int32)
        base = off + (face * W + y0) * W + x0
        f = self.flat
        return lerp2(f[base], f[base + 1], f[base + W], f[base + W + 1], x - x0f, y - y0f)

    def sample(self, dirs, lod):
        face, s, t = dir_to_face(dirs)
        if self.num_levels == 1:
            return self.bilinear(face, s, t, 0)
        lod = jnp.clip(jnp.asarray(lod, s.dtype), 0.0, self.num_levels - 1)
        lod = jnp.broadcast_to(lod, s.shape)
        m0f = jnp.floor(jax.lax.stop_gradient(lod))
        m0 = m0f.astype(jnp.int32)
        m1 = jnp.minimum(m0 + 1, self.num_levels - 1)
        w = (lod - m0f)[..., None]
        a = self.bilinear(face, s, t, m0)
        b = self.bilinear(face, s, t, m1)
        return a + (b - a) * w


# ------------------------------------------------------------------------------------------
# Pyramid
# ------------------------------------------------------------------------------------------


def downsample(level: jax.Array) -> jax.Array:
    """One area-correct pyramid step: (6, S, S, C) -> (6, S/2, S/2, C), S even.

    parent = sum(Omega_c L_c) / sum(Omega_c) over its four children with exact solid angles, so the
    power sum(L Omega) is preserved exactly (texel edges of the two levels coincide).
    """
    S = level.shape[1]
    if S % 2:
        raise ValueError(f"cannot halve a cube face of odd size {S}; use a power-of-two face size")
    # One face's solid angles (the six are identical): a smaller constant in the program.
    om = jnp.asarray(texel_solid_angles(S)[0], level.dtype)[None, ..., None]
    w = (level * om).reshape(6, S // 2, 2, S // 2, 2, -1).sum((2, 4))
    ow = om.reshape(1, S // 2, 2, S // 2, 2, 1).sum((2, 4))
    return w / ow


def _mip_chain_impl(level0, num_levels: int):
    """Level 0 and num_levels - 1 `downsample` steps (traceable; `_mip_chain` is its jit)."""
    levels = [level0]
    for _ in range(num_levels - 1):
        levels.append(downsample(levels[-1]))
    return tuple(levels)


#: The pyramid compiled as one program (op-by-op dispatch of the chain cost over a second of
#: compilation at 256^2).
_mip_chain = cpu_jit(_mip_chain_impl, static_argnums=1)


def mip_count(size: int) -> int:
    n = 1
    while size % 2 == 0 and size > 1:
        size //= 2
        n += 1
    return n


# ------------------------------------------------------------------------------------------
# The pytree
# ------------------------------------------------------------------------------------------


#: The metadata keys that change how a map is read (`specular.lookup_of`,
#: `sheen_prefilter.charlie_lookup`): only these are part of a Cubemap's identity in compiled
#: programs. Every other key (the environment's name, sample counts, checksums) is provenance.
LOOKUP_KEYS = frozenset({"distribution", "mapping_levels", "roughness_mapping", "lod_blend", "min_roughness"})


def _lookup_part(pairs) -> tuple:
    """The lookup pairs, sorted by key: the order metadata arrives in (a KTX2 file stores its keys
    sorted) does not change a compiled program's identity."""
    return tuple(sorted((kv for kv in pairs if kv[0] in LOOKUP_KEYS), key=lambda kv: kv[0]))


class CubeInfo(tuple):
    """A Cubemap's metadata, (key, value) pairs, as its static pytree data. Equality and hash see
    the lookup keys (`LOOKUP_KEYS`) only, so two environments of one size whose metadata differs in
    provenance alone share every compiled program. (A Cubemap *returned* by a cached jitted
    function carries the provenance of the call that compiled it.)"""

    __slots__ = ()

    def __eq__(self, other):
        return isinstance(other, tuple) and _lookup_part(self) == _lookup_part(other)

    def __ne__(self, other):
        return not self == other

    def __hash__(self):
        return hash(_lookup_part(self))

    def _program_key(self) -> tuple:
        """What the stored programs' keys name (`jaxpbr._program_cache`): the lookup pairs."""
        return _lookup_part(self)



def _filtered(fn, d, wt):
    """The solid-angle-weighted mean of fn over each texel's sub-texel points (d, wt)."""
    vals = jnp.asarray(fn(d), jnp.float64)
    if vals.ndim == d.ndim - 1:
        vals = vals[..., None]
    if vals.shape[:-1] != d.shape[:-1]:
        raise ValueError(
            f"fn returned shape {vals.shape} for directions of shape {d.shape}; "
            "expected (..., C) radiance for (..., 3) directions"
        )
    return jnp.sum(vals * wt[None, ..., None], axis=-2)


def _filtered_level(coords, fn, S, q, kw):
    return _filtered(functools.partial(fn, **dict(kw)), *_subtexel_grid(S, q, jnp, coords))


#: `Cubemap.from_function` of a named function with plain keyword values (the procedural sky).
_FILTERED_LEVEL = cached_jit(_filtered_level, static_argnums=(1, 2, 3, 4), cpu_options=LOOP_EMITTERS)

class Cubemap(Pytree):
    """Six square faces with an optional mip chain: `levels[m]` is (6, S >> m, S >> m, C).

    `levels` accepts one (6, S, S, C) array or a sequence of them; it is stored as a tuple (its
    length, the number of levels, is part of the tree structure). `info` is static metadata (a
    tuple of (key, value) string pairs, or a dict), e.g. what a prefiltered map's levels mean; it
    travels with the pytree as auxiliary data, and only its lookup keys (`LOOKUP_KEYS`) are part
    of the compiled programs' identity (`CubeInfo`).
    """

    levels: Any = leaf(rank=4)
    info: Any = static(())

    def _validate(self) -> None:
        levels = self.levels
        if isinstance(levels, (jax.Array, np.ndarray)):
            levels = (levels,)
        # (a NumPy level is copied as it is: jnp.asarray would run an XLA program per shape)
        levels = tuple(jax.device_put(lv) if isinstance(lv, np.ndarray) and lv.dtype != object else jnp.asarray(lv)
                       for lv in levels)
        if not levels:
            raise ValueError("a Cubemap needs at least one level")
        S = None
        for m, lv in enumerate(levels):
            if lv.ndim != 4 or lv.shape[0] != 6 or lv.shape[1] != lv.shape[2]:
                raise ValueError(
                    f"cube level {m} has shape {lv.shape}; expected (6, S, S, C): six square faces "
                    "+X,-X,+Y,-Y,+Z,-Z"
                )
            if not jnp.issubdtype(lv.dtype, jnp.floating):
                raise ValueError(f"cube level {m} has dtype {lv.dtype}; expected a float array of radiance")
            if m == 0:
                S = lv.shape[1]
            elif lv.shape[1] != max(1, S >> m) or lv.shape[3] != levels[0].shape[3]:
                raise ValueError(
                    f"cube level {m} has shape {lv.shape}; level m must be (6, S>>m, S>>m, C) with "
                    f"S = {S}, C = {levels[0].shape[3]}"
                )
        info = self.info
        self._set(levels=levels, info=CubeInfo(info.items() if isinstance(info, dict) else info))

    # properties -----------------------------------------------------------------------------
    @property
    def face_size(self) -> int:
        return int(self.levels[0].shape[1])

    @property
    def num_levels(self) -> int:
        return len(self.levels)

    @property
    def channels(self) -> int:
        return int(self.levels[0].shape[3])

    @property
    def dtype(self):
        return self.levels[0].dtype

    @property
    def metadata(self) -> dict:
        return dict(self.info)

    def __repr__(self) -> str:
        return (
            f"Cubemap(face_size={self.face_size}, num_levels={self.num_levels}, channels={self.channels}, "
            f"dtype={self.dtype}, info={dict(self.info)})"
        )

    def replace(self, levels=None, info=None) -> "Cubemap":
        return Cubemap(self.levels if levels is None else levels, self.info if info is None else info)

    # lookup -----------------------------------------------------------------------------------
    def sample(self, dirs, lod=0.0) -> jax.Array:
        """Radiance in directions `dirs` (..., 3) (any length > 0), seam-aware; -> (..., C).

        `lod` (scalar or (...)) selects the level: bilinear within a level, linear between the two
        nearest levels (trilinear), clamped to [0, num_levels - 1]. Differentiable in the texel
        values, in `dirs` (within a face) and in `lod`.
        """
        dirs = jnp.asarray(dirs, self.dtype)
        # A static lod at or below 0 reads level 0 alone (the same values: trilinear weight 0 on
        # level 1), without padding and gathering the other levels (a background lookup).
        levels = self.levels[:1] if isinstance(lod, (int, float)) and lod <= 0 else self.levels
        # As arrays of their own (`computed_once`): the texel gathers fused into the shading
        # that reads the samples kept XLA:CPU from vectorising that shading (the demo's IBL stage
        # at 1280x720: 232 against 291 ms).
        return computed_once(lambda o: _Pyramid(levels).sample(*o), (dirs, lod), levels[0][0, 0, 0, 0])

    def solid_angles(self, level: int = 0) -> np.ndarray:
        """Exact texel solid angles of `level`, float64 (6, S_m, S_m)."""
        return texel_solid_angles(self.levels[level].shape[1])

    def directions(self, level: int = 0) -> np.ndarray:
        """Unit texel-centre directions of `level`, float64 (6, S_m, S_m, 3)."""
        return texel_directions(self.levels[level].shape[1])

    # pyramids ---------------------------------------------------------------------------------
    def with_mips(self, num_levels: int | None = None) -> "Cubemap":
        """This map's level 0 with an area-correct pyramid (default: down to 1x1, or the last
        even size)."""
        S = self.face_size
        most = mip_count(S)
        if num_levels is None:
            num_levels = most
        num_levels = positive_int("num_levels", num_levels)
        if num_levels > most:
            raise ValueError(
                f"a {S}^2 cube supports at most {most} levels (each halves the face size); asked for {num_levels}"
            )
        return Cubemap(_mip_chain(self.levels[0], num_levels), self.info)

    def level_cube(self, level: int) -> "Cubemap":
        """A single-level Cubemap holding `levels[level]`."""
        return Cubemap((self.levels[level],), self.info)

    def power(self) -> jax.Array:
        """sum(L Omega) over level 0 per channel: the integral of radiance over the sphere."""
        om = jnp.asarray(self.solid_angles(0), self.dtype)[..., None]
        return jnp.sum(self.levels[0] * om, axis=(0, 1, 2))

    # constructors -----------------------------------------------------------------------------
    @classmethod
    def from_function(
        cls, fn: Callable, face_size: int, *, supersample: int = 4, dtype=jnp.float32, info: Any = (),
        fn_kwargs: dict | None = None,
    ) -> "Cubemap":
        """Area-filtered cube map of a radiance function.

        fn: (..., 3) unit directions (float64 NumPy-compatible jax array) -> (..., C) radiance,
        called as fn(d, **fn_kwargs) when fn_kwargs is given: then fn must be a module-level
        function and the values hashable (numbers, strings, tuples), and the filtering program
        is shared by every call with the same function and values.
        Each texel is the solid-angle-weighted mean of fn over `supersample`^2 points of its
        footprint (supersample=1: point samples at texel centres).
        """
        S = positive_int("face_size", face_size)
        q = positive_int("supersample", supersample)
        require(f"a {S}^2 cube at supersample {q}", cube_bytes(S, supersample=q), where="Cubemap.from_function")

        call = fn if fn_kwargs is None else functools.partial(fn, **fn_kwargs)

        def filtered(d, wt):
            return _filtered(call, d, wt)

        with jax.enable_x64(True):
            try:  # one compiled program: the sub-texel grid, fn and the filter
                coords = jax.device_put(_subtexel_coords(S, q))
                if fn_kwargs is not None:  # a named function and plain values: one program kept on disk
                    level = _FILTERED_LEVEL(coords, fn, S, q, tuple(sorted(fn_kwargs.items())))
                else:
                    level = jax.jit(lambda c: filtered(*_subtexel_grid(S, q, jnp, c)))(coords)
            except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
                    jax.errors.TracerIntegerConversionError):
                # fn needs concrete values (e.g. NumPy inside): eagerly, on the host grid
                # (6, S, S, q*q, 3) with weights (S, S, q*q), the same on every face.
                level = filtered(*(jnp.asarray(a) for a in _subtexel_points(S, q)))
            level = np.asarray(level)
        _check_finite(level, "fn")
        return cls((jax.device_put(level.astype(dtype)),), info)

    @classmethod
    def from_equirect(cls, img, face_size: int, *, dtype=jnp.float32, info: Any = ()) -> "Cubemap":
        """Area-filtered cube map from an equirect panorama `img` (H, 2H, C) of linear radiance.

        Filtering (so a 4k panorama into a 64^2 cube does not alias): the panorama is first halved
        with exact-solid-angle box filtering while it still has >= 4 pixels per cube texel across,
        then each cube texel averages q x q bilinear samples (q chosen so that samples are no
        farther apart than a panorama pixel), weighted by their solid angles.
        """
        S = positive_int("face_size", face_size)
        require(f"a {S}^2 cube", cube_bytes(S), where="Cubemap.from_equirect")
        img = np.asarray(img)
        if img.ndim == 2:
            img = img[..., None]
        if img.ndim != 3 or img.shape[1] != 2 * img.shape[0] or img.shape[0] < 1:
            raise ValueError(
                f"equirect image has shape {img.shape}; expected (H, 2H, C) lat-long panorama "
                "(width exactly twice the height)"
            )
        _check_finite(img, "equirect image")
        img = img.astype(np.float64 if np.dtype(dtype) == np.float64 else np.float32)
        H = img.shape[0]
        # Cube texel angular size at the face centre: 2 atan(1/S) ~ pi/(2S).
        cube_texel = 2.0 * math.atan(1.0 / S)
        while H % 2 == 0 and (math.pi / H) * 2 * 4 <= cube_texel:
            img = _halve_equirect(img)
            H = img.shape[0]
        q = int(min(16, max(1, math.ceil(cube_texel / (math.pi / H)))))
        # Rows of texels in blocks of ~2^20 sub-texel points, generated on the device: the grid
        # of a 1024^2 cube was 600 MB of float64 on the host (kept in a cache) and the load's
        # peak 2.1 GB (issue 13).
        B = max(1, min(S, _EQUIRECT_POINTS // (S * q * q)))
        coords = _subtexel_coords(S, q).astype(img.dtype)
        rows = np.concatenate([coords, np.repeat(coords[-1:], (-S) % B, 0)]).reshape(-1, B, q)
        level = _equirect_faces(jax.device_put(img), jax.device_put(rows), jax.device_put(coords), q=q)
        return cls((level.astype(dtype),), info)

    def to_equirect(self, height: int | None = None, *, lod=0.0, supersample: int = 1) -> jax.Array:
        """Equirect panorama (H, 2H, C) of this map (seam-aware bilinear / trilinear lookups at
        `lod`), each pixel the mean of `supersample`^2 lookups weighted by solid angle."""
        H = 2 * self.face_size if height is None else positive_int("height", height)
        q = positive_int("supersample", supersample)
        W = 2 * H
        o = (np.arange(q) + 0.5) / q
        u = (np.arange(W)[:, None] + o[None, :]).reshape(-1) / W
        vd = (np.arange(H)[:, None] + o[None, :]).reshape(-1) / H
        d = equirect_to_dir(u[None, :], 1.0 - vd[:, None], xp=np)  # (H q, W q, 3)
        rad = self.sample(jnp.asarray(d, self.dtype), lod)
        C = rad.shape[-1]
        rad = rad.reshape(H, q, W, q, C)
        wy = np.cos((0.5 - (1.0 - vd)) * np.pi).reshape(H, q)  # cos(latitude) ~ solid angle per sample
        wy = wy / wy.sum(1, keepdims=True)
        return jnp.einsum("hawbc,ha->hwc", rad, jnp.asarray(wy, rad.dtype), precision=HIGHEST) / q



class PaddedCubemap(Cubemap):
    """A `Cubemap` that also carries its levels padded for lookups: `_Pyramid`'s flat buffer (each
    level with its one-texel seam pad, concatenated), made once on the host by `padded`. Its
    lookups read that buffer instead of padding the levels inside every program that samples
    the map (the demo's IBL stage: about 0.1 s less XLA compile time); the values are the same."""

    flat: Any = leaf(None, rank=2)

    def sample(self, dirs, lod=0.0) -> jax.Array:
        dirs = jnp.asarray(dirs, self.dtype)
        sizes = [lv.shape[1] for lv in self.levels]
        if isinstance(lod, (int, float)) and lod <= 0:
            sizes = sizes[:1]  # (level 0 is first in the buffer; see `Cubemap.sample`)
        flat = jnp.asarray(self.flat)  # (a host array inside a trace: `padded`)
        return computed_once(lambda o: _Pyramid(None, flat=flat, sizes=sizes).sample(*o), (dirs, lod), flat[0, 0])


_PADDED: dict = {}


def padded(cube: Cubemap) -> Cubemap:
    """`cube` as a `PaddedCubemap` whose flat buffer is padded once, on the host, per set of level
    arrays (kept while they live); `cube` itself where a level is traced (the lookups then pad
    inside the trace, differentiably). Levels given as `jax.ShapeDtypeStruct`s give the buffer's
    shape (`_program_cache.ahead`)."""
    if isinstance(cube, PaddedCubemap) or not isinstance(cube, Cubemap):
        return cube
    levels = tuple(cube.levels)
    C = levels[0].shape[3]
    if all(isinstance(lv, jax.ShapeDtypeStruct) for lv in levels):
        n = sum(6 * (lv.shape[1] + 2) ** 2 for lv in levels)
        flat = jax.ShapeDtypeStruct((n, C), levels[0].dtype)
    elif all(isinstance(lv, jax.Array) and is_concrete(lv) for lv in levels):
        key = (id(levels[0]), len(levels))
        hit = _PADDED.get(key)
        if hit is None or not all(r() is lv for r, lv in zip(hit[0], levels, strict=True)):
            host = np.concatenate([_pad_level(np.asarray(lv), np).reshape(-1, C) for lv in levels])
            host.setflags(write=False)
            hit = [tuple(weakref.ref(lv, lambda _, k=key: _PADDED.pop(k, None)) for lv in levels), host]
            _PADDED[key] = hit
        # On the device once, outside any trace (the host copy then dropped); inside one (a render
        # under jit / grad of a concrete environment) a host array, a constant of that trace: a
        # `device_put` there would be a traced value, which must not be kept.
        flat = hit[1]
        if trace_state_clean() and isinstance(flat, np.ndarray):
            flat = hit[1] = jax.device_put(flat)
        elif not trace_state_clean() and not isinstance(flat, np.ndarray):
            flat = np.asarray(flat)
    else:
        return cube
    return unchecked(PaddedCubemap, levels=levels, info=cube.info, flat=flat)


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------


def _check_finite(a: np.ndarray, what: str) -> None:
    if not is_concrete(a):
        return
    a = np.asarray(a)
    bad = ~np.isfinite(a)
    if bad.any():
        raise ValueError(f"{what} contains {int(bad.sum())} NaN/Inf values; fix or clamp the input first")


def _subtexel_points(S: int, q: int, *, xp=np):
    """Directions (6, S, S, q*q, 3) of a q x q grid inside every texel and their normalised
    solid-angle weights (S, S, q*q): dOmega = ds dt / (1 + sc^2 + tc^2)^(3/2) on the face plane.
    NumPy float64 (read-only arrays, cached) or, with xp=jnp, traceable (inside a jitted program
    the grid is generated on the device instead of copied there; never cached: tracers)."""
    return _subtexel_points_np(S, q) if xp is np else _subtexel_grid(S, q, jnp)


@functools.lru_cache(maxsize=16)
def _subtexel_points_np(S: int, q: int):
    return _subtexel_grid(S, q, np)


def _subtexel_coords(S: int, q: int, xp=np):
    """Face coordinates (S, q) of the q sub-texel centres of each of the S texels along an axis."""
    o = (xp.arange(q) + 0.5) / q
    return (xp.arange(S)[:, None] + o[None, :]) / S


def _subtexel_grid(S: int, q: int, xp, c=None):
    """`_subtexel_points` from the coordinates c (S, q) (default `_subtexel_coords`). Inside a jit,
    pass c as an argument: a grid computed from constants alone is constant-folded by XLA at
    compile time (seconds for a 256^2 cube)."""
    c = _subtexel_coords(S, q, xp) if c is None else c
    t = xp.broadcast_to(c[:, None, :, None], (S, S, q, q)).reshape(S, S, q * q)
    s = xp.broadcast_to(c[None, :, None, :], (S, S, q, q)).reshape(S, S, q * q)
    # A Python int face: its table row is a constant (a (S, S, q*q) face array would make XLA
    # constant-fold a gather of that size at compile time: 5 s at 256^2).
    dirs = xp.stack([face_to_dir(f, s, t, xp=xp) for f in range(6)])
    r2 = xp.sum(dirs[0] ** 2, axis=-1)
    w = r2**-1.5
    w = w / w.sum(-1, keepdims=True)
    dirs = dirs / xp.linalg.norm(dirs, axis=-1, keepdims=True)
    if xp is np:
        dirs.setflags(write=False)
        w.setflags(write=False)
    return dirs, w


def _halve_equirect(img: np.ndarray) -> np.ndarray:
    """(H, W, C) -> (H/2, W/2, C), each output pixel the exact-solid-angle mean of its 2x2 block."""
    H, W, C = img.shape
    om = _equirect_row_solid_angles(H, W)[:, None, None]
    num = (img * om).reshape(H // 2, 2, W // 2, 2, C).sum((1, 3))
    den = np.broadcast_to(om, (H, W, 1)).reshape(H // 2, 2, W // 2, 2, 1).sum((1, 3))
    return (num / den).astype(img.dtype)


#: Sub-texel points per block of `_equirect_faces` (bounds its memory: ~50 MB of float32 per block).
_EQUIRECT_POINTS = 1 << 20


@functools.partial(jax.jit, static_argnames=("q",))
def _equirect_faces(img, rows, cols, *, q: int):
    """The six faces (6, S, S, C) of a cube from an equirect panorama img (H, W, C): each texel the
    solid-angle-weighted mean of bilinear lookups at its q x q sub-texel points. rows (nb, B, q):
    the t coordinates of the sub-texel centres, in blocks of B texel rows (the last block padded);
    cols (S, q): the s coordinates. One block of rows at a time (`lax.map`)."""
    H, W, C = img.shape
    S = cols.shape[0]
    s = jnp.broadcast_to(cols[None, :, None, :], (rows.shape[1], S, q, q)).reshape(rows.shape[1], S, q * q)

    def block(face, ct):
        t = jnp.broadcast_to(ct[:, None, :, None], s.shape[:2] + (q, q)).reshape(s.shape)
        d = face_to_dir(face, s, t, xp=jnp)  # a Python int face: no constant-folded face table
        r2 = jnp.sum(d * d, -1)
        w = r2**-1.5
        w = w / jnp.sum(w, -1, keepdims=True)
        u, v_up = dir_to_equirect(d / jnp.sqrt(r2)[..., None])
        val = bilinear(img, u * W - 0.5, (1.0 - v_up) * H - 0.5, wrap_x=True)  # longitude wraps, latitude clamps
        return jnp.sum(val * w[..., None], axis=-2)  # (B, S, C)

    faces = [jax.lax.map(functools.partial(block, f), rows).reshape(-1, S, C)[:S] for f in range(6)]
    return jnp.stack(faces)
