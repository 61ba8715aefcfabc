"""Texture filtering for glTF materials: mip pyramids, footprint-driven LOD, trilinear and
anisotropic filtering, per-sampler wrap and filter modes, sRGB decoding, ray differentials.

Conventions
-----------
* **glTF uv**: origin at the image's top-left corner, u to the right, v *down*. Texel (i, j) (row i,
  column j) of an (H, W, C) level has its centre at uv = ((j + 0.5) / W, (i + 0.5) / H), as in
  `jaxpbr._interp` (continuous texel coordinates x = u W - 0.5, y = v H - 0.5).
* **Linear-space filtering.** Every level holds *linear* values. A colour texture (`srgb=True`:
  glTF's baseColorTexture, emissiveTexture, sheenColorTexture, specularColorTexture) is decoded with
  the exact piecewise sRGB EOTF (`jaxpbr.color.srgb_decode`) *before* the pyramid is built and
  before any filtering, as a GPU does with an `*_SRGB` format; an alpha channel (the last of 2 or 4
  channels) is linear in glTF/PNG and is not decoded. Data textures (normal, metallic-roughness,
  occlusion, ...) are filtered as stored.
* **Pyramid** (`build_mips`): level m has shape (max(1, H >> m), max(1, W >> m)) (OpenGL's floor
  convention), down to 1 x 1: `mip_count(H, W) = 1 + floor(log2(max(H, W)))` levels. Each level is
  made from the previous one, separably per axis, in JAX (so gradients reach the texels):
    - an even axis n -> n/2: the 2-tap box (a + b) / 2;
    - an odd axis n = 2m + 1 -> m: the *polyphase 3-tap box*. Output texel i covers the input
      interval [i n/m, (i+1) n/m) (n/m = 2 + 1/m texels wide); its exact box average weights the
      three input texels 2i, 2i+1, 2i+2 by ((m - i), m, (i + 1)) / (2m + 1) (Guthe and Heckbert,
      "Non-Power-of-Two Mipmap Creation", NVIDIA technical report TR-01838-001, 2003). Weights sum to 1 and every input texel's weights over the outputs
      sum to m/n, so the mean is preserved exactly (up to rounding), unlike the common
      "drop the last row" 2x2 box, which shifts the image and loses a texel row per level. For
      n = 3 it is the plain 3-tap box (1/3, 1/3, 1/3).
    - an axis of size 1 stays 1 (non-square textures keep halving the other axis).
  Written as b + w0 (a - b) + w2 (c - b) (odd) and (a + b) / 2 (even), a constant texture stays
  exactly constant at every level.
* **Sampler** (static, part of the compiled program): wrap_s / wrap_t in `WRAP_MODES` ('repeat',
  'clamp' = CLAMP_TO_EDGE, 'mirror' = MIRRORED_REPEAT; glTF 10497 / 33071 / 33648), mag_filter in
  `MAG_FILTERS`, min_filter in `MIN_FILTERS` (glTF 9728, 9729, 9984..9987), max_anisotropy (the
  most taps along the footprint's major axis; 1 = isotropic trilinear). A glTF sampler without
  minFilter / magFilter gets 'linear_mipmap_linear' / 'linear' (the spec leaves the choice to the
  implementation; it is a common engine default, and the only min filter that neither aliases
  under minification nor shows mip-level seams).

Sampling (`sample`)
-------------------
OpenGL 4.6 §8.14 with EXT_texture_filter_anisotropic's footprint rule:

1. The footprint's two axes in level-0 texel units: a = (du/dx W, dv/dx H), b = (du/dy W, dv/dy H).
2. Isotropic (max_anisotropy = 1): rho = max(|a|, |b|), lambda = log2 rho (§8.14.1).
   Anisotropic (K = max_anisotropy > 1): P_max = max(|a|, |b|), P_min = min(|a|, |b|);
   lambda = log2 max(P_min, P_max / K) -- the LOD of the *minor* axis, raised only when the tap
   budget cannot cover the major one -- and N = ceil(P_max / 2^lambda) in [1, K] taps, centred on
   the N equal segments of the major axis: offsets ((k + 1/2) / N - 1/2) * major, k = 0..N-1, each
   weighted 1/N (N boxes of width P_max / N tile the footprint; the extension's i / (N+1) spacing
   leaves the ends under-covered). A tap is a complete trilinear (or whatever min_filter says)
   lookup at lambda. N is static-bounded: all K taps are evaluated (a `lax.scan` over K), the
   ones past N with weight 0 (no data-dependent shapes under jit), so a lookup costs K trilinear
   lookups whatever the footprint (a GPU pays for N). Measured on a 256^2 grazing-plane frame
   (XLA:CPU, rays and differentials included): trilinear 3.0 ms, K = 4 / 8 / 16 7.7 / 9.5 /
   13.1 ms (examples/texture_aliasing.py).
3. lambda <= 0: magnification, mag_filter on level 0. lambda > 0: min_filter; for the mip-mapped
   ones lambda is clamped to [0, q] (q = last level); *_mipmap_nearest takes level
   ceil(lambda + 1/2) - 1 (0 for lambda <= 1/2), *_mipmap_linear blends floor(lambda) and the next
   level by frac(lambda).
4. Wrapping is applied to the integer texel indices of every level (§8.14.2, Table 8.20), per axis.
   Before that, the coordinate is reduced by whole periods (repeat: u - floor u; mirror: u - 2
   floor(u / 2); clamp: clipped to [-1, 2]), which keeps texel positions exact for large repeating
   uv and int32 indices in range for huge ones.

NaN or infinite uv give NaN (no out-of-range reads: every index is wrapped or clamped).

Derivatives: the result is differentiable in the texels (through the pyramid: `Texture.from_image`
is traceable, so differentiate a function that builds the texture) and in uv (through the bilinear
fractions; nearest filters have zero uv-gradient, as the function is piecewise constant) and in
duv_dx, duv_dy (through the trilinear blend factor and the tap offsets). Gradients are finite for
zero derivatives (lambda = -inf is replaced by `LOD_MIN`), for huge ones (components clamped to
2^40 texels, far past the last level), and for degenerate triangles / grazing rays in the ray
differential helper.

Ray differentials (`uv_derivatives_on_triangle`, `pinhole_ray_differentials`) follow Igehy 1999,
"Tracing ray differentials", transfer to the triangle's plane and barycentric derivatives.
KHR_texture_transform (`texture_transform_matrix`, `apply_texture_transform`) maps uv and, with its
linear part, the uv derivatives.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import color
from .._interp import lerp, lerp2, split_coordinate
from .._numerics import (
    as_float,
    eps,
    pack3,
    safe_div,
    safe_sqrt,
    unpack3,
    vcross,
    vdot,
    vnormalize,
)
from .._pytree import Pytree, leaf, static
from ..errors import InputError
from ..io.gltf import GLTF_MAG_FILTERS, GLTF_MIN_FILTERS, GLTF_WRAP_MODES  # glTF sampler enums -> names

__all__ = [
    "DEFAULT_MAX_ANISOTROPY",
    "GLTF_MAG_FILTERS",
    "GLTF_MIN_FILTERS",
    "GLTF_WRAP_MODES",
    "LOD_MIN",
    "MAG_FILTERS",
    "MIN_FILTERS",
    "WRAP_MODES",
    "Footprint",
    "Texture",
    "apply_texture_transform",
    "build_mips",
    "footprint",
    "mip_count",
    "pinhole_ray_differentials",
    "sample",
    "sample_lod",
    "sampler_from_gltf",
    "texture_transform_matrix",
    "uv_derivatives_on_triangle",
]

WRAP_MODES = ("repeat", "clamp", "mirror")
MAG_FILTERS = ("nearest", "linear")
MIN_FILTERS = (
    "nearest",
    "linear",
    "nearest_mipmap_nearest",
    "linear_mipmap_nearest",
    "nearest_mipmap_linear",
    "linear_mipmap_linear",
)
DEFAULT_MAX_ANISOTROPY = 16
#: The LOD given to a zero footprint (log2 0 = -inf): any value <= 0 means magnification.
LOD_MIN = -50.0
_LOD_FLOOR_SQ = 2.0**-100  # squared footprints at or below this get LOD_MIN
_MAX_TEXELS = 2.0**40  # footprint components are clamped to this many level-0 texels
_TAP_TOLERANCE = 1e-4  # a ratio within this (relative) of an integer n takes n taps, not n + 1


# ------------------------------------------------------------------------------------------
# The pyramid
# ------------------------------------------------------------------------------------------


def mip_count(height: int, width: int) -> int:
    """Levels of a full pyramid down to 1 x 1: 1 + floor(log2(max(H, W)))."""
    return int(max(int(height), int(width))).bit_length()


def _level_shape(height: int, width: int, m: int) -> tuple[int, int]:
    return max(1, height >> m), max(1, width >> m)


def _halve_axis(x, axis: int):
    """One level down along `axis` (negative, counted from the end): 2-tap box for an even size,
    the polyphase 3-tap box for an odd one, unchanged for size 1 (see the module docstring)."""
    n = x.shape[axis]
    if n == 1:
        return x

    def take(start, stop):
        return jax.lax.slice_in_dim(x, start, stop, stride=2, axis=x.ndim + axis)

    if n % 2 == 0:
        return (take(0, n) + take(1, n)) * 0.5
    m = n // 2
    a, b, c = take(0, 2 * m), take(1, 2 * m + 1), take(2, 2 * m + 1)
    i = np.arange(m, dtype=np.float64)
    shape = [1] * x.ndim
    shape[x.ndim + axis] = m
    w0 = jnp.asarray(((m - i) / (2 * m + 1)).reshape(shape), x.dtype)
    w2 = jnp.asarray(((i + 1) / (2 * m + 1)).reshape(shape), x.dtype)
    return b + w0 * (a - b) + w2 * (c - b)


def build_mips(level0, num_levels: int | None = None) -> tuple:
    """The pyramid of an (..., H, W, C) float array: (level0, level1, ...), `num_levels` of them
    (default: the full chain to 1 x 1, `mip_count(H, W)`). Traceable and differentiable; leading
    axes are batch axes."""
    level0 = jnp.asarray(level0)
    H, W = level0.shape[-3], level0.shape[-2]
    full = mip_count(H, W)
    n = full if num_levels is None else int(num_levels)
    if not 1 <= n <= full:
        raise ValueError(f"num_levels must be in [1, {full}] for a {H}x{W} texture, got {num_levels}")
    return _build_mips(level0, n, False)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _build_mips(level0, n: int, srgb: bool) -> tuple:
    # One compiled program per (shape, dtype, n, srgb): called eagerly, the ~10 ops per level
    # would otherwise each be dispatched (and compiled once) on their own; inlined under jit.
    if srgb:
        level0 = _decode_srgb(level0)
    levels = [level0]
    for _ in range(1, n):
        levels.append(_halve_axis(_halve_axis(levels[-1], -3), -2))
    return tuple(levels)


def _as_texels(img, dtype=None):
    """An image (H, W), (H, W, C) of floats or 8/16-bit integers -> float (H, W, C) in [0, 1] scale
    for integers (code value / 255 or / 65535)."""
    if isinstance(img, (np.ndarray, jax.Array)) and jnp.issubdtype(img.dtype, jnp.integer):
        scale = float(jnp.iinfo(img.dtype).max)
        x = jnp.asarray(img).astype(dtype or jnp.float32) / scale
    else:
        x = as_float(img)
        if dtype is not None:
            x = x.astype(dtype)
    if x.ndim == 2:
        x = x[..., None]
    return x


def _decode_srgb(x):
    """sRGB-decode the colour channels of an (..., C) image; the alpha channel of a 2- or 4-channel
    image (luminance-alpha, RGBA) is linear in glTF / PNG and stays as stored."""
    C = x.shape[-1]
    if C in (2, 4):
        return jnp.concatenate([color.srgb_decode(x[..., : C - 1]), x[..., C - 1 :]], axis=-1)
    return color.srgb_decode(x)


# ------------------------------------------------------------------------------------------
# Texture
# ------------------------------------------------------------------------------------------


def _choice(name: str, value, options) -> str:
    if not isinstance(value, str) or value not in options:
        raise ValueError(f"Texture.{name} must be one of {', '.join(map(repr, options))}; got {value!r}")
    return value


class Texture(Pytree):
    """A mip-mapped texture and its sampler.

    levels: tuple of (H_m, W_m, C) float arrays, level 0 first, each the next level of the
        previous one's shape (`build_mips`); *linear* values (a colour texture is decoded from sRGB
        before the levels are made: see `from_image`). A tuple of fewer levels than the full chain
        is allowed (the LOD is clamped to the last one). Leading axes are batch axes.
    wrap_s, wrap_t: 'repeat' | 'clamp' | 'mirror' along u (columns) / v (rows).
    mag_filter: 'nearest' | 'linear'.
    min_filter: 'nearest' | 'linear' | '{nearest,linear}_mipmap_{nearest,linear}' (GL naming:
        within-level filter first, between-level filter second).
    max_anisotropy: the most taps along the footprint's major axis (1 = isotropic). All of them
        are evaluated for every lookup (static shapes): cost grows linearly with it.
    srgb: the source texels were sRGB-encoded (and have been decoded into `levels`); metadata.

    Build it with `Texture.from_image` (decodes, makes the pyramid) or `Texture.from_gltf`; the
    constructor takes ready-made levels (e.g. a KTX2 file's own mip chain).
    """

    levels: Any = leaf(rank=3)
    wrap_s: str = static("repeat")
    wrap_t: str = static("repeat")
    mag_filter: str = static("linear")
    min_filter: str = static("linear_mipmap_linear")
    max_anisotropy: int = static(DEFAULT_MAX_ANISOTROPY)
    srgb: bool = static(False)

    def _validate(self) -> None:
        levels = self.levels
        if isinstance(levels, (jax.Array, np.ndarray)) or not isinstance(levels, (tuple, list)):
            levels = (levels,)
        levels = tuple(as_float(lv) for lv in levels)
        if not levels:
            raise ValueError("a Texture needs at least one level")
        s0 = levels[0].shape
        if len(s0) < 3 or s0[-3] < 1 or s0[-2] < 1 or s0[-1] < 1:
            raise ValueError(f"texture level 0 must be an (H, W, C) array, got shape {s0}")
        H, W, C = s0[-3:]
        if len(levels) > mip_count(H, W):
            raise ValueError(f"a {H}x{W} texture has at most {mip_count(H, W)} levels, got {len(levels)}")
        for m, lv in enumerate(levels[1:], 1):
            want = _level_shape(H, W, m) + (C,)
            if lv.shape[-3:] != want or lv.shape[:-3] != s0[:-3]:
                raise ValueError(
                    f"texture level {m} has shape {lv.shape}; expected {s0[:-3] + want} "
                    f"(level m is (max(1, H >> m), max(1, W >> m), C))"
                )
        wrap_s = _choice("wrap_s", self.wrap_s, WRAP_MODES)
        wrap_t = _choice("wrap_t", self.wrap_t, WRAP_MODES)
        mag = _choice("mag_filter", self.mag_filter, MAG_FILTERS)
        mn = _choice("min_filter", self.min_filter, MIN_FILTERS)
        K = self.max_anisotropy
        if isinstance(K, bool) or not isinstance(K, (int, np.integer)):
            raise TypeError(f"Texture.max_anisotropy must be an integer in [1, 64], got {K!r}")
        if not 1 <= K <= 64:
            raise ValueError(f"Texture.max_anisotropy must be an integer in [1, 64], got {K!r}")
        if not isinstance(self.srgb, (bool, np.bool_)):
            raise TypeError(f"Texture.srgb must be a bool, got {self.srgb!r}")
        self._set(
            levels=levels, wrap_s=wrap_s, wrap_t=wrap_t, mag_filter=mag, min_filter=mn,
            max_anisotropy=int(K), srgb=bool(self.srgb),
        )

    # construction ---------------------------------------------------------------------------
    @classmethod
    def from_image(
        cls,
        img,
        *,
        srgb: bool,
        wrap_s: str = "repeat",
        wrap_t: str = "repeat",
        mag_filter: str = "linear",
        min_filter: str = "linear_mipmap_linear",
        max_anisotropy: int = DEFAULT_MAX_ANISOTROPY,
        num_levels: int | None = None,
        dtype=None,
    ) -> Texture:
        """A texture from an (H, W) or (H, W, C) image: floats as given, uint8 / uint16 as code
        value / max. srgb=True (colour textures): decoded to linear (`jaxpbr.color.srgb_decode`,
        alpha excepted) before the pyramid is built; srgb=False (data textures): as stored. The
        full pyramid (or `num_levels` levels) is built in JAX: traceable, differentiable in `img`.
        dtype: the levels' float dtype (default: img's, float32 for integer images)."""
        if not isinstance(srgb, (bool, np.bool_)):
            raise TypeError("Texture.from_image: pass srgb=True (colour texture) or srgb=False (data texture)")
        x = _as_texels(img, dtype)
        if x.ndim != 3:
            raise ValueError(f"Texture.from_image expects an (H, W) or (H, W, C) image, got shape {jnp.shape(img)}")
        full = mip_count(x.shape[0], x.shape[1])
        n = full if num_levels is None else int(num_levels)
        if not 1 <= n <= full:
            raise ValueError(f"num_levels must be in [1, {full}] for a {x.shape[0]}x{x.shape[1]} texture, got {num_levels}")
        return cls(
            levels=_build_mips(x, n, bool(srgb)),
            wrap_s=wrap_s,
            wrap_t=wrap_t,
            mag_filter=mag_filter,
            min_filter=min_filter,
            max_anisotropy=max_anisotropy,
            srgb=bool(srgb),
        )

    @classmethod
    def from_gltf(
        cls, img, sampler: dict | None = None, *, srgb: bool, max_anisotropy: int = DEFAULT_MAX_ANISOTROPY, **kwargs
    ) -> Texture:
        """A texture from an image and a glTF `sampler` object (the JSON dict, or None for the
        default sampler): see `sampler_from_gltf`. Other keywords go to `from_image`."""
        return cls.from_image(img, srgb=srgb, max_anisotropy=max_anisotropy, **sampler_from_gltf(sampler), **kwargs)

    # properties -----------------------------------------------------------------------------
    @property
    def height(self) -> int:
        return int(self.levels[0].shape[-3])

    @property
    def width(self) -> int:
        return int(self.levels[0].shape[-2])

    @property
    def channels(self) -> int:
        return int(self.levels[0].shape[-1])

    @property
    def num_levels(self) -> int:
        return len(self.levels)

    @property
    def dtype(self):
        return self.levels[0].dtype


def sampler_from_gltf(sampler: dict | None) -> dict:
    """glTF sampler JSON ({'magFilter', 'minFilter', 'wrapS', 'wrapT'}, all optional) -> the
    keyword arguments wrap_s, wrap_t, mag_filter, min_filter of `Texture`. Missing wrap modes are
    REPEAT (the glTF default); a missing magFilter is 'linear' and a missing minFilter
    'linear_mipmap_linear' (glTF leaves both to the implementation). Unknown enums: InputError."""
    sampler = {} if sampler is None else dict(sampler)

    def look(key, table, default):
        value = sampler.get(key)
        if value is None:
            return default
        try:
            return table[int(value)]
        except (KeyError, TypeError, ValueError):
            raise InputError(
                f"glTF sampler {key}={value!r} is not a valid enum; expected one of {sorted(table)}"
            ) from None

    return {
        "wrap_s": look("wrapS", GLTF_WRAP_MODES, "repeat"),
        "wrap_t": look("wrapT", GLTF_WRAP_MODES, "repeat"),
        "mag_filter": look("magFilter", GLTF_MAG_FILTERS, "linear"),
        "min_filter": look("minFilter", GLTF_MIN_FILTERS, "linear_mipmap_linear"),
    }


# ------------------------------------------------------------------------------------------
# Lookups
# ------------------------------------------------------------------------------------------


def _reduce(u, mode: str):
    """Remove whole periods from a normalised coordinate (exact: floor of the value, gradient 1)."""
    if mode == "repeat":
        return u - jnp.floor(jax.lax.stop_gradient(u))
    if mode == "mirror":
        return u - 2.0 * jnp.floor(jax.lax.stop_gradient(u) * 0.5)
    return jnp.clip(u, -1.0, 2.0)


def _wrap(i, n, mode: str):
    """GL wrap of integer texel indices (OpenGL 4.6 Table 8.20)."""
    if mode == "repeat":
        return jnp.mod(i, n)
    if mode == "clamp":
        return jnp.clip(i, 0, n - 1)
    p = jnp.mod(i, 2 * n)
    return jnp.where(p < n, p, 2 * n - 1 - p)


def _wrap_pair(i0, n, mode: str):
    """(wrap(i0), wrap(i0 + 1)) for the texel index i0 of a coordinate reduced by `_reduce`
    (u in [0, 1] for repeat, [0, 2] for mirror, so i0 in [-1, period]): compares and selects
    instead of integer division. Equal to `_wrap` on that range (tests/test_texture.py checks
    both against the spec's wrap functions)."""
    if mode == "clamp":
        return jnp.clip(i0, 0, n - 1), jnp.clip(i0 + 1, 0, n - 1)
    period = n if mode == "repeat" else 2 * n
    a = jnp.where(i0 < 0, i0 + period, jnp.where(i0 >= period, i0 - period, i0))  # i0 mod period
    b = jnp.where(a + 1 >= period, a + 1 - period, a + 1)
    if mode == "mirror":
        a = jnp.where(a < n, a, 2 * n - 1 - a)
        b = jnp.where(b < n, b, 2 * n - 1 - b)
    return a, b


class _Packed(NamedTuple):
    flat: Any  # (sum of H_m W_m, C): every level, row-major, one after the other
    heights: tuple
    widths: tuple
    offsets: tuple


def _pack(tex: Texture) -> _Packed:
    """All levels in one (T, C) array, so one gather reads from a per-lookup (traced) level."""
    C = tex.levels[0].shape[-1]
    flat = jnp.concatenate([lv.reshape(-1, C) for lv in tex.levels], axis=0)
    hs = tuple(int(lv.shape[-3]) for lv in tex.levels)
    ws = tuple(int(lv.shape[-2]) for lv in tex.levels)
    offs = tuple(int(o) for o in np.cumsum((0,) + tuple(h * w for h, w in zip(hs, ws)))[:-1])
    return _Packed(flat, hs, ws, offs)


def _fetch(p: _Packed, level, u, v, nearest, wrap_s: str, wrap_t: str):
    """Bilinear (or, where `nearest`, nearest) lookup of level `level` (a Python int or an int32
    array broadcasting with u, v) at reduced coordinates u, v -> (..., C)."""
    if isinstance(level, int):
        Hl, Wl, off = p.heights[level], p.widths[level], p.offsets[level]
        Hf, Wf = float(Hl), float(Wl)
    else:
        Hl = jnp.asarray(p.heights, jnp.int32)[level]
        Wl = jnp.asarray(p.widths, jnp.int32)[level]
        off = jnp.asarray(p.offsets, jnp.int32)[level]
        Hf, Wf = Hl.astype(u.dtype), Wl.astype(u.dtype)
    j0, fx = split_coordinate(u * Wf - 0.5)
    i0, fy = split_coordinate(v * Hf - 0.5)
    if nearest is not False:
        # nearest texel floor(u W) = j0 + [fx >= 1/2]; fraction 0 (exact: lerp(a, b, 0) = a).
        jn = j0 + (jax.lax.stop_gradient(fx) >= 0.5).astype(j0.dtype)
        in_ = i0 + (jax.lax.stop_gradient(fy) >= 0.5).astype(i0.dtype)
        j0, i0 = jnp.where(nearest, jn, j0), jnp.where(nearest, in_, i0)
        fx, fy = jnp.where(nearest, 0.0, fx), jnp.where(nearest, 0.0, fy)
    ja, jb = _wrap_pair(j0, Wl, wrap_s)
    ia, ib = _wrap_pair(i0, Hl, wrap_t)
    ra, rb = off + ia * Wl, off + ib * Wl

    def g(idx):
        return p.flat.at[idx].get(mode="promise_in_bounds")

    return lerp2(g(ra + ja), g(ra + jb), g(rb + ja), g(rb + jb), fx, fy)


def _filtered(tex: Texture, p: _Packed, u, v, lam):
    """One GL lookup (mag or min filter by lambda, mip selection, wrap) at u, v with LOD lam."""
    u, v = _reduce(u, tex.wrap_s), _reduce(v, tex.wrap_t)
    q = tex.num_levels - 1
    mn = tex.min_filter
    mag_nearest = tex.mag_filter == "nearest"
    min_nearest = mn.startswith("nearest")
    if mag_nearest == min_nearest:
        nearest = mag_nearest
    else:
        nearest = jnp.where(lam <= 0.0, mag_nearest, min_nearest)  # GL's c = 0
    if mn in ("nearest", "linear") or q == 0:
        return _fetch(p, 0, u, v, nearest, tex.wrap_s, tex.wrap_t)
    lam_s = jax.lax.stop_gradient(lam)
    if mn.endswith("mipmap_nearest"):
        d = jnp.clip(jnp.ceil(lam_s + 0.5) - 1.0, 0.0, q)
        d = jnp.where(lam_s <= 0.5, 0.0, d).astype(jnp.int32)
        return _fetch(p, d, u, v, nearest, tex.wrap_s, tex.wrap_t)
    lc = jnp.clip(lam, 0.0, float(q))
    d1 = jnp.floor(jax.lax.stop_gradient(lc))
    f = lc - d1
    d1 = d1.astype(jnp.int32)
    d2 = jnp.minimum(d1 + 1, q)
    a = _fetch(p, d1, u, v, nearest, tex.wrap_s, tex.wrap_t)
    b = _fetch(p, d2, u, v, nearest, tex.wrap_s, tex.wrap_t)
    return lerp(a, b, f[..., None])


def _half_log2(x2):
    """log2 sqrt(x2) for a squared length, LOD_MIN at (near) 0, finite gradient (double where)."""
    ok = x2 > _LOD_FLOOR_SQ
    return jnp.where(ok, 0.5 * jnp.log2(jnp.where(ok, x2, 1.0)), LOD_MIN)


class Footprint(NamedTuple):
    """A lookup's footprint: lod (unclamped lambda; LOD_MIN for a zero footprint), taps (the
    number N of anisotropic taps, float, 1 when isotropic), major (the major axis in uv, (..., 2);
    zeros when isotropic)."""

    lod: Any
    taps: Any
    major: Any


def _broadcast_inputs(uv, duv_dx, duv_dy):
    uv = as_float(uv)
    dx = jnp.zeros_like(uv) if duv_dx is None else as_float(duv_dx)
    dy = jnp.zeros_like(uv) if duv_dy is None else as_float(duv_dy)
    for name, a in (("uv", uv), ("duv_dx", dx), ("duv_dy", dy)):
        if a.ndim < 1 or a.shape[-1] != 2:
            raise ValueError(f"{name} must be a (..., 2) array, got shape {a.shape}")
    shape = jnp.broadcast_shapes(uv.shape, dx.shape, dy.shape)
    dt = jnp.result_type(uv, dx, dy)
    return tuple(jnp.broadcast_to(a, shape).astype(dt) for a in (uv, dx, dy))


def footprint(tex: Texture, duv_dx, duv_dy) -> Footprint:
    """The LOD, anisotropic tap count and major axis of the footprint spanned by duv_dx, duv_dy
    (..., 2) (uv per pixel), by `tex`'s level-0 size and max_anisotropy (module docstring, step 2)."""
    _, dx, dy = _broadcast_inputs(jnp.zeros((2,)), duv_dx, duv_dy)
    return jax.jit(_footprint)(tex, dx, dy)


def _footprint(tex: Texture, dx, dy) -> Footprint:
    H, W = tex.height, tex.width
    ax, ay = jnp.clip(dx[..., 0] * W, -_MAX_TEXELS, _MAX_TEXELS), jnp.clip(dx[..., 1] * H, -_MAX_TEXELS, _MAX_TEXELS)
    bx, by = jnp.clip(dy[..., 0] * W, -_MAX_TEXELS, _MAX_TEXELS), jnp.clip(dy[..., 1] * H, -_MAX_TEXELS, _MAX_TEXELS)
    la2, lb2 = ax * ax + ay * ay, bx * bx + by * by
    K = tex.max_anisotropy
    one = jnp.ones_like(la2)
    if K == 1:
        return Footprint(_half_log2(jnp.maximum(la2, lb2)), one, jnp.zeros(la2.shape + (2,), la2.dtype))
    a_major = la2 >= lb2
    pmax2 = jnp.where(a_major, la2, lb2)
    pmin2 = jnp.where(a_major, lb2, la2)
    minor2 = jnp.maximum(pmin2, pmax2 * (1.0 / (K * K)))  # (2^lambda)^2
    lam = _half_log2(minor2)
    ratio = jnp.sqrt(jax.lax.stop_gradient(safe_div(pmax2, minor2, minor2 > 0, fill=1.0)))
    taps = jnp.clip(jnp.ceil(ratio * (1.0 - _TAP_TOLERANCE)), 1.0, float(K))
    major = jnp.stack([jnp.where(a_major, ax, bx) / W, jnp.where(a_major, ay, by) / H], axis=-1)
    return Footprint(lam, taps, major)


def sample(tex: Texture, uv, duv_dx=None, duv_dy=None, *, lod_bias=0.0):
    """Filtered lookup of `tex` at glTF uv (..., 2) with the screen-space derivatives duv_dx,
    duv_dy (..., 2) (uv per pixel; None = 0: magnification, level 0) -> (..., C) linear values.

    The LOD and anisotropic taps come from the footprint (`footprint`); lod_bias is added to the
    LOD (GL's texture LOD bias). Shapes broadcast; jit / vmap / grad friendly (no Python loops
    over pixels, static shapes). See the module docstring for the exact rules."""
    uv, dx, dy = _broadcast_inputs(uv, duv_dx, duv_dy)
    return _sample(tex, uv, dx, dy, jnp.asarray(lod_bias, uv.dtype))


@jax.jit
def _sample(tex: Texture, uv, dx, dy, lod_bias):
    # jitted for eager callers (one program per sampler, shapes and dtypes; inlined under jit)
    fp = _footprint(tex, dx, dy)
    lam = fp.lod + lod_bias
    p = _pack(tex)
    u, v = uv[..., 0], uv[..., 1]
    K = tex.max_anisotropy
    if K == 1:
        return _filtered(tex, p, u, v, lam)
    # One tap per step of a scan (a loop of K steps, each one lookup per pixel): the same
    # lookups on a (K, ...) axis compiled, on XLA:CPU, to fusions that each recomputed the tap
    # coordinates and a slow reduction over K (measured 10-20x slower than K trilinear lookups).
    n = fp.taps
    inv_n = 1.0 / n
    mu, mv = fp.major[..., 0], fp.major[..., 1]

    def tap(acc, k):
        t = (k + 0.5) * inv_n - 0.5
        active = k < n
        t = jnp.where(active, t, 0.0)
        w = jnp.where(active, inv_n, 0.0)[..., None]
        return acc + w * _filtered(tex, p, u + t * mu, v + t * mv, lam), None

    acc0 = jnp.zeros(u.shape + (tex.channels,), jnp.result_type(u, tex.dtype))
    return jax.lax.scan(tap, acc0, jnp.arange(K, dtype=u.dtype))[0]


def sample_lod(tex: Texture, uv, lod):
    """Lookup at an explicit LOD (GLSL textureLod): uv (..., 2), lod (...) broadcasting; no
    anisotropy; lod <= 0 uses the mag filter, otherwise the min filter as in `sample`."""
    uv = as_float(uv)
    lod = jnp.asarray(lod, uv.dtype)
    shape = jnp.broadcast_shapes(uv.shape[:-1], lod.shape)
    uv = jnp.broadcast_to(uv, shape + (2,))
    return _sample_lod(tex, uv, jnp.broadcast_to(lod, shape))


@jax.jit
def _sample_lod(tex: Texture, uv, lod):
    return _filtered(tex, _pack(tex), uv[..., 0], uv[..., 1], lod)


# ------------------------------------------------------------------------------------------
# Ray differentials (Igehy 1999) and KHR_texture_transform
# ------------------------------------------------------------------------------------------


def pinhole_ray_differentials(
    position, target, up, fov_y_deg, width: int, height: int, *, dtype=jnp.float32, offset=(0.5, 0.5)
):
    """Per-pixel ray origin, unit direction and its pixel derivatives of a pinhole camera, each
    (height, width, 3).

    The camera of `jaxpbr.scene.Camera` / `primary_rays`: forward = normalize(target - position),
    right = normalize(forward x up), up' = right x forward; pixel (i, j) looks along
    d = forward + x right + y up' with x = (2 (j + ox) / W - 1) tan(fov/2) W/H and
    y = (1 - 2 (i + oy) / H) tan(fov/2), (ox, oy) = offset. D = d / |d|, and (Igehy 1999, eq. 8)
    dD/dx = (dd/dx - D (D . dd/dx)) / |d| with dd/dx = (2 tan(fov/2) (W/H) / W) right (x = column
    j), dd/dy = -(2 tan(fov/2) / H) up' (y = row i, downwards). The origin does not move
    (dO/dx = dO/dy = 0)."""
    # Vec3 planes, not (..., 3) arrays: reductions over a size-3 minor axis compile to slow
    # separate passes on XLA:CPU (see jaxpbr._numerics): measured 9x faster on a 256^2 frame.
    pos = jnp.asarray(position, dtype)
    f = vnormalize(unpack3(jnp.asarray(target, dtype) - pos))
    r = vnormalize(vcross(f, unpack3(jnp.asarray(up, dtype))))
    u = vcross(r, f)
    t = jnp.tan(jnp.deg2rad(jnp.asarray(fov_y_deg, dtype)) / 2)
    W, H = int(width), int(height)
    x = ((2.0 * (jnp.arange(W, dtype=dtype) + offset[0]) / W - 1.0) * t * (W / H))[None, :]
    y = ((1.0 - 2.0 * (jnp.arange(H, dtype=dtype) + offset[1]) / H) * t)[:, None]
    d = tuple(f[i] + x * r[i] + y * u[i] for i in range(3))
    inv = jax.lax.rsqrt(vdot(d, d))
    D = tuple(c * inv for c in d)
    s = 2.0 * t / H  # dx/dj = 2 t (W/H) / W; dy/di = -2 t / H

    def transfer(dd):
        dD = vdot(D, dd)
        return pack3(tuple((dd[i] - D[i] * dD) * inv for i in range(3)))

    Dp = pack3(D)
    return (
        jnp.broadcast_to(pos, Dp.shape),
        Dp,
        transfer(tuple(s * c for c in r)),
        transfer(tuple(-s * c for c in u)),
    )


def uv_derivatives_on_triangle(
    p0, p1, p2, uv0, uv1, uv2, origin, direction, ddir_dx, ddir_dy, *, dorigin_dx=None, dorigin_dy=None, min_cos=1e-6
):
    """uv at the ray's hit on the triangle's plane and its screen derivatives (Igehy 1999).

    p0, p1, p2: (..., 3) vertices; uv0, uv1, uv2: (..., 2) their texture coordinates; origin,
    direction: (..., 3) the ray (any direction length); ddir_dx, ddir_dy: (..., 3) the direction's
    derivatives per pixel (`pinhole_ray_differentials`); dorigin_dx, dorigin_dy: the origin's
    (None = 0, a pinhole camera). Everything broadcasts. Returns (uv, duv_dx, duv_dy), each (..., 2).

    The offset rays are transferred to the *plane* of the triangle (Igehy eq. 10-12): with
    n = (p1 - p0) x (p2 - p0), t = (p0 - o) . n / (D . n), P = o + t D,
    dP = (dO + t dD) + dt D, dt = -(dO + t dD) . n / (D . n); the barycentrics
    b1 = (P - p0) . (e2 x n) / |n|^2, b2 = (P - p0) . (n x e1) / |n|^2 (e1 = p1 - p0, e2 = p2 - p0)
    are linear in P, so db = dP . (same vectors) / |n|^2, and uv = uv0 + b1 (uv1 - uv0) +
    b2 (uv2 - uv0), duv = db1 (uv1 - uv0) + db2 (uv2 - uv0). Whether the hit lies inside the
    triangle, or in front of the ray (t > 0), is the caller's business.

    Clamps (finite values and gradients everywhere):
      * grazing rays: |D . n| is raised to min_cos |D| |n| (sign kept; 0 counts as +), i.e. the
        ray is treated as at least asin(min_cos) off the plane. The footprint is then at most
        ~1/min_cos times the pixel's distance and the LOD saturates at the last level anyway.
      * degenerate triangles (|n|^2 <= eps^2 |e1|^2 |e2|^2, collinear or coincident vertices):
        uv = uv0 and zero derivatives (level-0 lookup of the first vertex's texel).
    """
    V = unpack3
    p0_ = V(jnp.asarray(p0))
    P1, P2, O, D = V(jnp.asarray(p1)), V(jnp.asarray(p2)), V(jnp.asarray(origin)), V(jnp.asarray(direction))
    dDx, dDy = V(jnp.asarray(ddir_dx)), V(jnp.asarray(ddir_dy))
    zero = (0.0, 0.0, 0.0)
    dOx = zero if dorigin_dx is None else V(jnp.asarray(dorigin_dx))
    dOy = zero if dorigin_dy is None else V(jnp.asarray(dorigin_dy))
    e1 = tuple(a - b for a, b in zip(P1, p0_))
    e2 = tuple(a - b for a, b in zip(P2, p0_))
    n = vcross(e1, e2)
    nn = vdot(n, n)
    dt_ = jnp.result_type(nn, *O, *D)
    tol = eps(dt_)
    ok_tri = (nn > tol * tol * vdot(e1, e1) * vdot(e2, e2)) & (nn > 0)
    nn_s = jnp.where(ok_tri, nn, 1.0)
    # grazing clamp of D . n (double where: no division by ~0 anywhere)
    dn = vdot(D, n)
    lim = min_cos * safe_sqrt(vdot(D, D) * nn)  # safe: sqrt'(0) = inf would give 0 * inf = NaN
    sgn = jnp.where(dn < 0, -1.0, 1.0)
    dn = jnp.where(jnp.abs(dn) >= lim, dn, sgn * lim)
    dn = jnp.where(dn == 0, 1.0, dn)  # D = 0 or n = 0 (the latter masked below)
    op = tuple(a - b for a, b in zip(O, p0_))  # o - p0
    t = -vdot(op, n) / dn
    rel = tuple(a + t * d for a, d in zip(op, D))  # P - p0
    g1 = vcross(e2, n)
    g2 = vcross(n, e1)
    b1 = vdot(rel, g1) / nn_s
    b2 = vdot(rel, g2) / nn_s

    def dP(dO, dD):
        q = tuple(a + t * b for a, b in zip(dO, dD))
        dtt = -vdot(q, n) / dn
        return tuple(a + dtt * d for a, d in zip(q, D))

    uv0, uv1, uv2 = jnp.asarray(uv0), jnp.asarray(uv1), jnp.asarray(uv2)
    du1, du2 = uv1 - uv0, uv2 - uv0

    def to_uv(c1, c2):
        c1 = jnp.where(ok_tri, c1, 0.0)[..., None]
        c2 = jnp.where(ok_tri, c2, 0.0)[..., None]
        return c1 * du1 + c2 * du2

    outs = []
    for dO, dD in ((dOx, dDx), (dOy, dDy)):
        q = dP(dO, dD)
        outs.append(to_uv(vdot(q, g1) / nn_s, vdot(q, g2) / nn_s))
    return uv0 + to_uv(b1, b2), outs[0], outs[1]


def texture_transform_matrix(offset=(0.0, 0.0), rotation=0.0, scale=(1.0, 1.0)):
    """KHR_texture_transform's 3x3 matrix T(offset) R(rotation) S(scale), acting on (u, v, 1).

    R = [[cos r, sin r, 0], [-sin r, cos r, 0], [0, 0, 1]] (rows): "rotate the UVs counter-
    clockwise" in glTF's v-down uv space, which is what the extension's example requires (offset
    (0, 1), rotation pi/2, scale 1/2 shows the lower-left quadrant rotated 90 degrees clockwise),
    and what the glTF Sample Viewer and three.js compute. (The GLSL in the extension's text, read
    with GLSL's column-major constructor, is the transpose; its example is the normative check.)"""
    ox, oy = jnp.asarray(offset[0]), jnp.asarray(offset[1])
    sx, sy = jnp.asarray(scale[0]), jnp.asarray(scale[1])
    c, s = jnp.cos(rotation), jnp.sin(rotation)
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack(
        [
            jnp.stack([sx * c, sy * s, ox * one]),
            jnp.stack([-sx * s, sy * c, oy * one]),
            jnp.stack([zero, zero, one]),
        ]
    )


def apply_texture_transform(matrix, uv, duv_dx=None, duv_dy=None):
    """uv' = A uv + b and duv' = A duv for the affine (3, 3) `matrix` [[A, b], [0, 0, 1]] (its last
    row is ignored: KHR_texture_transform is affine). uv, duv_dx, duv_dy: (..., 2); derivatives may
    be None (returned as None). Returns (uv', duv_dx', duv_dy'). Written out per component (no
    matmul: exact in float32 on GPUs, where default-precision matmuls run in TF32)."""
    M = jnp.asarray(matrix)

    def lin(d):
        return jnp.stack([M[0, 0] * d[..., 0] + M[0, 1] * d[..., 1], M[1, 0] * d[..., 0] + M[1, 1] * d[..., 1]], -1)

    uv = jnp.asarray(uv)
    out = lin(uv) + jnp.stack([M[0, 2], M[1, 2]])
    return out, (None if duv_dx is None else lin(jnp.asarray(duv_dx))), (None if duv_dy is None else lin(jnp.asarray(duv_dy)))
