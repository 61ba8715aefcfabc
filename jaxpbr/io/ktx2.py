"""KTX 2.0 container files for uncompressed float textures: cubemaps with mips, 2D textures (e.g. a BRDF LUT).

Written from the Khronos *KTX File Format Specification*, version 2.0 (``ktxspec.adoc``; section names below are
that document's) and the *Khronos Data Format Specification* 1.4 (KDF, for the Data Format Descriptor).

Layout of a file written here (all integers little endian, "Endianness")::

    Byte[12] identifier                 « K T X ␠ 2 0 » \\r \\n \\x1A \\n
    UInt32   vkFormat ... supercompressionScheme   (9 fields, "File Structure")
    Index:   dfdByteOffset, dfdByteLength, kvdByteOffset, kvdByteLength (UInt32), sgdByteOffset, sgdByteLength (UInt64)
    Level Index: levelCount x {byteOffset, byteLength, uncompressedByteLength} (UInt64), level 0 (largest) first
    Data Format Descriptor: dfdTotalSize + one Khronos Basic Descriptor Block
    Key/Value Data: {keyAndValueByteLength, "key\\0value\\0", padding to 4} sorted by key
    mipPadding (zeros) to lcm(texel block size, 4), then the levels' images from the SMALLEST level to level 0,
    each level starting on an lcm(texel block size, 4) boundary ("Mip Level Array", "mipPadding")

No supercompression (scheme 0) and no supercompression global data (sgdByteOffset = sgdByteLength = 0).

Cubemap face and texel layout (spec "faceCount", "KTXorientation", appendix "Cubemap Orientation")
----------------------------------------------------------------------------------------------------
KTX stores cube faces in the order +X, -X, +Y, -Y, +Z, -Z, all with orientation ``rd``, laid out so that they are
"directly compatible with the Vulkan and OpenGL cube samplers" (the major-axis face-selection table and its (s, t)
equations). Within a face, texel data are rows of texels, row after row, tightly packed ("Packing"), and "the first
pixel in the data stream for each face ... is closest to the origin of the texture coordinate system": the texel at
row ``y``, column ``x`` of the stream is the one at ``s = (x + 0.5)/S``, ``t = (y + 0.5)/S``, as a GL/Vulkan
upload of the same bytes places it. jaxpbr's convention (docs/conventions.md) is exactly that table's (s, t):
``levels[m][f, i, j]`` is the texel of face f at ``s = (j + 0.5)/S``, ``t = (i + 0.5)/S``. So

    file face f = array face f (the same order), file row i = ``levels[m][f, i, :]``, file column j = index j,

with no flip or face swap. ``KTXorientation = "rd"`` (S increases to the right, T downwards: row 0 is the top row
when a face is viewed as an image) is written explicitly; it is also what the spec requires of cubemaps and
assumes when the key is absent. A sampler given the same direction vector d that jaxpbr's cube code uses returns
the same texel. (The spec's appendix notes that a skybox drawn in a right-handed object space must negate one
axis of its lookup vector to avoid a mirror image; that concerns the viewer's coordinates, not the file.)

2D textures: ``levels[m][i, j]`` is row i, column j; row 0 is written first and is the image's top row
(``KTXorientation = "rd"``), as for jaxpbr's images. For the BRDF LUT ``[j_roughness, i_nov]`` this means
roughness runs down the rows (t) and NoV along them (s).
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import Float16RangeError
from .atomic import atomic_write

__all__ = ["FORMATS", "read_ktx2", "write_ktx2"]

#: "identifier": the 12-byte file identifier of KTX version 2.
IDENTIFIER = bytes([0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A])

_HEADER_SIZE = 12 + 9 * 4  # identifier + 9 UInt32 header fields
_INDEX_SIZE = 4 * 4 + 2 * 8  # dfd/kvd offsets+lengths (UInt32) + sgd offset+length (UInt64)
_LEVEL_ENTRY_SIZE = 3 * 8  # byteOffset, byteLength, uncompressedByteLength (UInt64)

# Khronos Data Format Specification constants (KDF 1.4, "Khronos Basic Data Format Descriptor Block").
_KHR_DF_VENDORID_KHRONOS = 0
_KHR_DF_KHR_DESCRIPTORTYPE_BASICFORMAT = 0
_KHR_DF_VERSIONNUMBER = 2
_KHR_DF_MODEL_RGBSDA = 1
_KHR_DF_PRIMARIES_UNSPECIFIED = 0
_KHR_DF_PRIMARIES_BT709 = 1
_KHR_DF_TRANSFER_LINEAR = 1
_KHR_DF_FLAG_ALPHA_STRAIGHT = 0
_KHR_DF_SAMPLE_DATATYPE_FLOAT = 0x80
_KHR_DF_SAMPLE_DATATYPE_SIGNED = 0x40
_CHANNEL_IDS = {2: (0, 1), 4: (0, 1, 2, 15)}  # RGBSDA: R=0, G=1, B=2, A=15
_FLOAT_MINUS_ONE_BITS = 0xBF800000  # IEEE 754 binary32 -1.0: sampleLower of a float sample (KDF example)
_FLOAT_ONE_BITS = 0x3F800000  # IEEE 754 binary32 +1.0: sampleUpper of a float sample

_HALF_MAX = 65504.0  # largest finite IEEE 754 binary16 value
_FLOAT_MAX = float(np.finfo(np.float32).max)


@dataclass(frozen=True)
class _Format:
    name: str
    vk_format: int  # VkFormat enum value
    channels: int
    type_size: int  # bytes per component ("typeSize")
    primaries: int  # DFD colorPrimaries

    @property
    def dtype(self) -> np.dtype:
        return np.dtype("<f2" if self.type_size == 2 else "<f4")

    @property
    def texel_block_size(self) -> int:  # bytes per texel (Vulkan "texel block size" of an uncompressed format)
        return self.channels * self.type_size

    @property
    def alignment(self) -> int:  # "mipPadding": lcm(texel block size, 4)
        return math.lcm(self.texel_block_size, 4)

    @property
    def wide(self) -> str:  # the 32-bit format with the same channels
        return "rgba32f" if self.channels == 4 else "rg32f"


#: Supported formats: name -> (VkFormat, channels, bytes per channel). RGBA formats describe linear Rec.709
#: radiance (DFD primaries BT709); RG formats hold non-colour data such as the BRDF LUT's (A, B)
#: (DFD primaries UNSPECIFIED). All are linear (KHR_DF_TRANSFER_LINEAR).
_FORMATS: dict[str, _Format] = {
    "rgba16f": _Format("rgba16f", 97, 4, 2, _KHR_DF_PRIMARIES_BT709),  # VK_FORMAT_R16G16B16A16_SFLOAT
    "rgba32f": _Format("rgba32f", 109, 4, 4, _KHR_DF_PRIMARIES_BT709),  # VK_FORMAT_R32G32B32A32_SFLOAT
    "rg16f": _Format("rg16f", 83, 2, 2, _KHR_DF_PRIMARIES_UNSPECIFIED),  # VK_FORMAT_R16G16_SFLOAT
    "rg32f": _Format("rg32f", 103, 2, 4, _KHR_DF_PRIMARIES_UNSPECIFIED),  # VK_FORMAT_R32G32_SFLOAT
}
_BY_VK = {f.vk_format: f for f in _FORMATS.values()}
FORMATS = {name: (f.vk_format, f.channels, f.type_size) for name, f in _FORMATS.items()}


# ------------------------------------------------------------------------------------------------------ writing


def write_ktx2(path, levels: Sequence, *, fmt: str = "rgba16f", metadata: Mapping[str, str] | None = None) -> None:
    """Write a mip chain as an uncompressed KTX 2.0 file (a cubemap or a 2D texture).

    Args:
      path: output file (conventionally ``.ktx2``). Written atomically: a temporary file in the same directory is
        renamed over ``path`` only once complete, so a failure leaves neither a partial file nor the temporary.
      levels: sequence of arrays, level 0 (largest) first, all with the same channel count C:
        a cubemap is ``(6, S_m, S_m, C)`` per level, faces +X, -X, +Y, -Y, +Z, -Z, ``[f, i, j]`` at
        ``s = (j + 0.5)/S_m``, ``t = (i + 0.5)/S_m`` (module docstring); a 2D texture is ``(H_m, W_m, C)``, row 0
        the top. Each level must be half the previous one in every dimension, rounded down, at least 1
        (``S_m = max(1, S_{m-1} // 2)``), and there may be at most ``floor(log2(max size)) + 1`` levels (spec
        "levelCount"). A partial chain (e.g. only level 0) is allowed. Values are in the caller's units (jaxpbr:
        linear radiance, or the LUT's dimensionless (A, B)); NaN and Inf are refused.
      fmt: ``"rgba16f"`` (VK_FORMAT_R16G16B16A16_SFLOAT), ``"rgba32f"`` (R32G32B32A32_SFLOAT), ``"rg16f"``
        (R16G16_SFLOAT) or ``"rg32f"`` (R32G32_SFLOAT). RGBA formats take C = 4, or C = 3 padded with alpha 1;
        RG formats take C = 2. Values are rounded to nearest (even) float16/float32; 16-bit formats refuse values
        with magnitude above 65504 (the largest finite half) rather than store Inf: pre-expose (scale) the data
        or use a 32-bit format.
      metadata: extra key/value pairs, ``str -> str``, stored as NUL-terminated UTF-8 strings ("Key/Value Data").
        Keys starting with ``KTX``/``ktx`` are reserved by the spec; jaxpbr itself writes ``KTXwriter`` =
        ``"jaxpbr <version>"`` and ``KTXorientation`` = ``"rd"``. All pairs are written sorted by key.

    Raises:
      ValueError: bad shapes, sizes, channel count, format, values or metadata (nothing is written).
      FileNotFoundError / NotADirectoryError / IsADirectoryError / PermissionError / OSError: the file cannot be
        written (nothing is left behind).
    """
    path = Path(os.fspath(path))
    if fmt not in _FORMATS:
        raise ValueError(f"unknown KTX2 format {fmt!r}; choose one of {', '.join(map(repr, _FORMATS))}")
    form = _FORMATS[fmt]
    arrays, is_cube = _validated_levels(levels, form)
    kv = _metadata_pairs(metadata)
    payload = _encode(arrays, is_cube, form, kv)

    def writer(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            fh.write(payload)

    atomic_write(path, writer)


def _validated_levels(levels, form: _Format) -> tuple[list[np.ndarray], bool]:
    """Check shapes, sizes, channels and values; return the levels as C-contiguous arrays of ``form.dtype``."""
    if hasattr(levels, "ndim") or isinstance(levels, (str, bytes)) or not hasattr(levels, "__iter__"):
        raise ValueError(
            "levels must be a sequence of arrays (level 0 first), e.g. [level0] for a single level; "
            f"got {type(levels).__name__}"
        )
    arrays = [np.asarray(a) for a in levels]
    if not arrays:
        raise ValueError("levels is empty: give at least level 0")

    first = arrays[0]
    if first.ndim == 4:
        is_cube = True
        if first.shape[0] != 6 or first.shape[1] != first.shape[2]:
            raise ValueError(
                f"a cubemap level must have shape (6, S, S, C) (6 square faces +X, -X, +Y, -Y, +Z, -Z); "
                f"level 0 has shape {first.shape}"
            )
    elif first.ndim == 3:
        is_cube = False
    else:
        raise ValueError(
            f"each level must be (6, S, S, C) for a cubemap or (H, W, C) for a 2D texture; "
            f"level 0 has shape {first.shape}"
        )
    channels = first.shape[-1]
    accepted = (3, 4) if form.channels == 4 else (2,)
    if channels not in accepted:
        want = "4 (RGBA) or 3 (RGB, padded with alpha = 1)" if form.channels == 4 else "2 (RG)"
        other = {1: "", 2: " (use fmt='rg16f' or 'rg32f')", 3: " (use fmt='rgba16f' or 'rgba32f')",
                 4: " (use fmt='rgba16f' or 'rgba32f')"}.get(channels, "")
        raise ValueError(
            f"format {form.name!r} stores {form.channels} channels and takes input with {want} channels; "
            f"the levels have {channels} channel(s){other}"
        )

    spatial = first.shape[1:3] if is_cube else first.shape[0:2]
    if min(spatial) < 1:
        raise ValueError(f"level 0 is empty: shape {first.shape}")
    max_levels = max(spatial).bit_length()  # floor(log2(max size)) + 1
    if len(arrays) > max_levels:
        raise ValueError(
            f"{len(arrays)} levels given, but a {spatial[1]}x{spatial[0]} base level has at most {max_levels} "
            "(down to 1x1; KTX 2.0 'levelCount')"
        )

    expected = tuple(spatial)
    for m, a in enumerate(arrays):
        if a.dtype.kind not in "fiu":
            raise ValueError(f"level {m} must hold real numbers; got dtype {a.dtype}")
        if a.ndim != first.ndim or a.shape[-1] != channels or (is_cube and a.shape[0] != 6):
            kind = f"(6, S, S, {channels})" if is_cube else f"(H, W, {channels})"
            raise ValueError(f"level {m} has shape {a.shape}; every level must be {kind} like level 0")
        got = tuple(a.shape[1:3] if is_cube else a.shape[0:2])
        if got != expected:
            prev = arrays[m - 1].shape
            raise ValueError(
                f"level {m} has shape {a.shape}, but level {m - 1} has shape {prev}: each level must be half "
                f"the previous one (rounded down, at least 1), i.e. {expected[0]}x{expected[1]} texels per "
                f"{'face' if is_cube else 'image'} (rows x columns)"
            )
        expected = (max(1, got[0] // 2), max(1, got[1] // 2))

    # Non-finite values: count texels (not channels) so the message speaks in the units the user sees.
    bad = []
    for m, a in enumerate(arrays):
        if a.dtype.kind == "f":
            n = int(np.count_nonzero(~np.isfinite(a).all(axis=-1)))
            if n:
                bad.append((m, n))
    if bad:
        total = sum(n for _, n in bad)
        per = ", ".join(f"level {m}: {n}" for m, n in bad)
        raise ValueError(
            f"{total} texel(s) hold NaN or Inf ({per}); refusing to write them into the KTX2 file. Find where "
            "they come from, or replace them explicitly (e.g. np.nan_to_num) if that is what you want."
        )

    limit = _HALF_MAX if form.type_size == 2 else _FLOAT_MAX
    over = [(m, int(np.count_nonzero(np.abs(a) > limit)), float(np.max(np.abs(a)))) for m, a in enumerate(arrays)]
    over = [o for o in over if o[1]]
    if over:
        total = sum(n for _, n, _ in over)
        peak = max(p for _, _, p in over)
        if form.type_size == 2:
            raise Float16RangeError(
                f"{total} value(s) exceed the float16 range of format {form.name!r} (|x| <= 65504; largest "
                f"|x| = {peak:.6g}, levels {[m for m, _, _ in over]}); they would become Inf. Pre-expose the data "
                f"(scale it down, and record the scale in metadata) or use fmt={form.wide!r}.",
                fmt=form.name, wide=form.wide, count=total, peak=peak,
            )
        raise ValueError(
            f"{total} value(s) exceed the float32 range (largest |x| = {peak:.6g}); they would become Inf"
        )

    out = []
    for a in arrays:
        if a.shape[-1] == 3:
            a = np.concatenate([a, np.ones(a.shape[:-1] + (1,), dtype=a.dtype)], axis=-1)
        out.append(np.ascontiguousarray(a.astype(form.dtype)))
    return out, is_cube


def _metadata_pairs(metadata) -> list[tuple[bytes, bytes]]:
    """The key/value pairs to write, as (key, value) UTF-8 bytes without terminators, sorted by key."""
    pairs = {"KTXwriter": f"jaxpbr {__version__}", "KTXorientation": "rd"}
    for key, value in (metadata or {}).items():
        if not isinstance(key, str) or not key:
            raise ValueError(f"metadata keys must be non-empty str; got {key!r}")
        if key[:3] in ("KTX", "ktx"):
            raise ValueError(
                f"metadata key {key!r}: keys starting with 'KTX'/'ktx' are reserved by the KTX 2.0 spec "
                "(jaxpbr writes KTXwriter and KTXorientation itself); use another key, e.g. 'jaxpbr:...'"
            )
        if not isinstance(value, str):
            raise ValueError(  # noqa: TRY004 - ValueError for all bad metadata, as in jaxpbr.io.image
                f"metadata value for {key!r} must be str (KTX2 values are stored as UTF-8 strings); got "
                f"{type(value).__name__}. Serialise it first, e.g. json.dumps(value)."
            )
        for what, text in (("key", key), ("value", value)):
            if "\x00" in text:
                raise ValueError(f"metadata {what} for {key!r} contains a NUL character, which KTX2 uses as terminator")
        pairs[key] = value
    # "Key/value data must be written to the file sorted by the Unicode code points of the keys": Python's str
    # ordering is code-point ordering.
    return [(k.encode("utf-8"), pairs[k].encode("utf-8")) for k in sorted(pairs)]


def _dfd(form: _Format) -> bytes:
    """Data Format Descriptor: dfdTotalSize + one Khronos Basic Descriptor Block (KDF 1.4), for a linear,
    straight-alpha RGBSDA float format with one 16- or 32-bit sample per channel at bit offsets 0, bits, 2*bits..."""
    bits = 8 * form.type_size
    channel_ids = _CHANNEL_IDS[form.channels]
    block_size = 24 + 16 * len(channel_ids)
    words = [
        _KHR_DF_VENDORID_KHRONOS | (_KHR_DF_KHR_DESCRIPTORTYPE_BASICFORMAT << 17),
        _KHR_DF_VERSIONNUMBER | (block_size << 16),
        _KHR_DF_MODEL_RGBSDA | (form.primaries << 8) | (_KHR_DF_TRANSFER_LINEAR << 16)
        | (_KHR_DF_FLAG_ALPHA_STRAIGHT << 24),
        0,  # texelBlockDimension0..3 = 0: a 1x1x1x1 texel block (stored as size - 1)
        form.texel_block_size,  # bytesPlane0 (bytesPlane1..3 = 0)
        0,  # bytesPlane4..7
    ]
    qualifiers = _KHR_DF_SAMPLE_DATATYPE_FLOAT | _KHR_DF_SAMPLE_DATATYPE_SIGNED
    for k, channel in enumerate(channel_ids):
        words += [
            (k * bits) | ((bits - 1) << 16) | ((qualifiers | channel) << 24),  # bitOffset, bitLength-1, channelType
            0,  # samplePosition0..3
            _FLOAT_MINUS_ONE_BITS,  # sampleLower (-1.0f)
            _FLOAT_ONE_BITS,  # sampleUpper (1.0f)
        ]
    total = 4 + 4 * len(words)
    return struct.pack(f"<I{len(words)}I", total, *words)


def _kvd(pairs: list[tuple[bytes, bytes]]) -> bytes:
    out = bytearray()
    for key, value in pairs:
        entry = key + b"\x00" + value + b"\x00"
        out += struct.pack("<I", len(entry)) + entry
        out += b"\x00" * (-len(entry) % 4)  # valuePadding
    return bytes(out)


def _align(n: int, a: int) -> int:
    return n + (-n % a)


def _encode(arrays: list[np.ndarray], is_cube: bool, form: _Format, pairs) -> bytes:
    n_levels = len(arrays)
    faces = 6 if is_cube else 1
    height, width = arrays[0].shape[1:3] if is_cube else arrays[0].shape[0:2]

    dfd = _dfd(form)
    kvd = _kvd(pairs)
    dfd_offset = _HEADER_SIZE + _INDEX_SIZE + _LEVEL_ENTRY_SIZE * n_levels
    kvd_offset = dfd_offset + len(dfd)
    end = kvd_offset + len(kvd)

    # Mip Level Array: smallest level first; each level's data begins on an lcm(texel block size, 4) boundary.
    datas = [a.tobytes() for a in arrays]
    offsets = [0] * n_levels
    for p in reversed(range(n_levels)):
        offsets[p] = _align(end, form.alignment)
        end = offsets[p] + len(datas[p])

    buf = bytearray(end)
    struct.pack_into(
        "<12s9I", buf, 0, IDENTIFIER,
        form.vk_format, form.type_size, width, height,
        0,  # pixelDepth: not a 3D texture
        0,  # layerCount: not an array texture
        faces, n_levels,
        0,  # supercompressionScheme: none
    )
    struct.pack_into("<4I2Q", buf, _HEADER_SIZE, dfd_offset, len(dfd), kvd_offset, len(kvd), 0, 0)
    for p in range(n_levels):
        struct.pack_into("<3Q", buf, _HEADER_SIZE + _INDEX_SIZE + _LEVEL_ENTRY_SIZE * p,
                         offsets[p], len(datas[p]), len(datas[p]))
    buf[dfd_offset:kvd_offset] = dfd
    buf[kvd_offset:kvd_offset + len(kvd)] = kvd
    for p in range(n_levels):
        buf[offsets[p]:offsets[p] + len(datas[p])] = datas[p]
    return bytes(buf)


# ------------------------------------------------------------------------------------------------------ reading


def read_ktx2(path) -> tuple[list[np.ndarray], dict[str, str], dict]:
    """Read an uncompressed float KTX 2.0 file of one of :data:`FORMATS` (as :func:`write_ktx2` writes them).

    Returns:
      levels: list of float32 arrays, level 0 first: ``(6, S_m, S_m, C)`` for a cubemap (faces +X, -X, +Y, -Y,
        +Z, -Z; ``[f, i, j]`` = row i, column j of face f in the file), ``(H_m, W_m, C)`` for a 2D texture (row 0
        = first row in the file); C = 4 for RGBA formats, 2 for RG formats.
      metadata: the key/value pairs whose values are UTF-8 text, ``str -> str`` (one trailing NUL removed),
        including ``KTXwriter`` / ``KTXorientation`` when present.
      info: ``vk_format``, ``format`` (name in :data:`FORMATS`), ``type_size``, ``pixel_width``, ``pixel_height``,
        ``pixel_depth``, ``layer_count``, ``face_count``, ``level_count`` (the header field; 0 means only the base
        level is stored), ``supercompression_scheme``, ``dfd`` (the Data Format Descriptor's bytes, dfdTotalSize
        included), ``color_model``, ``color_primaries``, ``transfer_function``, ``level_index`` (list of
        ``(byteOffset, byteLength, uncompressedByteLength)``, level 0 first) and ``binary_metadata`` (values that
        are not UTF-8 text, as bytes).

    Raises:
      ValueError: not a KTX 2.0 file, a structurally invalid one, or one using features this reader does not
        handle (supercompression, other formats, 1D/3D/array textures); the message says which.
    """
    path = Path(os.fspath(path))
    buf = path.read_bytes()
    where = f"{str(path)!r}"

    def fail(msg: str) -> ValueError:
        return ValueError(f"cannot read KTX2 file {where}: {msg}")

    if len(buf) < 12 or buf[:12] != IDENTIFIER:
        raise fail("it does not start with the KTX 2.0 file identifier «KTX 20»")
    if len(buf) < _HEADER_SIZE + _INDEX_SIZE:
        raise fail(f"file is truncated ({len(buf)} bytes; the header and index alone take 80)")
    (vk_format, type_size, width, height, depth, layers, faces, level_count, scheme) = struct.unpack_from(
        "<9I", buf, 12
    )
    dfd_off, dfd_len, kvd_off, kvd_len, sgd_off, sgd_len = struct.unpack_from("<4I2Q", buf, _HEADER_SIZE)

    if scheme != 0:
        raise fail(f"supercompressionScheme {scheme} is not supported (only 0, no supercompression)")
    if vk_format not in _BY_VK:
        known = ", ".join(f"{f.vk_format} ({f.name})" for f in _FORMATS.values())
        raise fail(f"vkFormat {vk_format} is not supported; this reader handles {known}")
    form = _BY_VK[vk_format]
    if type_size != form.type_size:
        raise fail(f"typeSize is {type_size}, but vkFormat {vk_format} ({form.name}) requires {form.type_size}")
    if width == 0:
        raise fail("pixelWidth is 0 (not allowed)")
    if height == 0:
        raise fail("pixelHeight is 0: 1D textures are not supported")
    if depth != 0:
        raise fail(f"pixelDepth is {depth}: 3D textures are not supported")
    if layers != 0:
        raise fail(f"layerCount is {layers}: array textures are not supported")
    if faces not in (1, 6):
        raise fail(f"faceCount is {faces}; it must be 1 or 6")
    if faces == 6 and width != height:
        raise fail(f"cubemap with pixelWidth {width} != pixelHeight {height}")
    num_levels = max(1, level_count)
    if num_levels > max(width, height).bit_length():  # levelCount <= floor(log2(max size)) + 1
        raise fail(f"levelCount {level_count} exceeds the number of levels of a {width}x{height} texture")

    index_end = _HEADER_SIZE + _INDEX_SIZE + _LEVEL_ENTRY_SIZE * num_levels
    if len(buf) < index_end:
        raise fail("file is truncated inside the level index")

    # Data Format Descriptor.
    if dfd_len < 4 or dfd_off < index_end or dfd_off + dfd_len > len(buf):
        raise fail(f"DFD at {dfd_off} (+{dfd_len} bytes) lies outside the file or overlaps the index")
    dfd = bytes(buf[dfd_off:dfd_off + dfd_len])
    (dfd_total,) = struct.unpack_from("<I", dfd, 0)
    if dfd_total != dfd_len:
        raise fail(f"dfdTotalSize {dfd_total} != dfdByteLength {dfd_len}")
    if kvd_len and dfd_total != kvd_off - dfd_off:
        raise fail(f"dfdTotalSize {dfd_total} != kvdByteOffset - dfdByteOffset = {kvd_off - dfd_off}")
    dfd_info = _check_dfd(dfd, form, fail)

    # Key/Value Data.
    if kvd_len == 0 and kvd_off != 0:
        raise fail(f"kvdByteOffset is {kvd_off} although kvdByteLength is 0 (must then be 0)")
    if kvd_len and (kvd_off < index_end or kvd_off + kvd_len > len(buf)):
        raise fail(f"key/value data at {kvd_off} (+{kvd_len} bytes) lies outside the file or overlaps the index")
    metadata, binary = _parse_kvd(bytes(buf[kvd_off:kvd_off + kvd_len]), fail)

    if sgd_len != 0 or sgd_off != 0:
        raise fail(f"supercompression global data present (offset {sgd_off}, {sgd_len} bytes) without supercompression")

    # Level Index and Mip Level Array.
    header_end = max(index_end, dfd_off + dfd_len, kvd_off + kvd_len)
    level_index = []
    levels = []
    shape_hw = (height, width)
    for p in range(num_levels):
        off, length, ulength = struct.unpack_from("<3Q", buf, _HEADER_SIZE + _INDEX_SIZE + _LEVEL_ENTRY_SIZE * p)
        level_index.append((off, length, ulength))
        h, w = shape_hw
        expected = faces * h * w * form.texel_block_size
        if length != ulength:
            raise fail(f"level {p}: byteLength {length} != uncompressedByteLength {ulength} without supercompression")
        if length != expected:
            raise fail(f"level {p}: byteLength {length}, expected {expected} for {faces} x {h}x{w} {form.name} texels")
        if off % form.alignment:
            raise fail(f"level {p}: byteOffset {off} is not a multiple of lcm(texel block size, 4) = {form.alignment}")
        if off < header_end or off + length > len(buf):
            raise fail(f"level {p}: data at {off} (+{length} bytes) lies outside the image data area of the file")
        data = np.frombuffer(buf, dtype=form.dtype, count=length // form.type_size, offset=off)
        data = data.reshape(faces, h, w, form.channels).astype(np.float32)
        levels.append(data if faces == 6 else data[0])
        shape_hw = (max(1, h // 2), max(1, w // 2))

    info = {
        "vk_format": vk_format,
        "format": form.name,
        "type_size": type_size,
        "pixel_width": width,
        "pixel_height": height,
        "pixel_depth": depth,
        "layer_count": layers,
        "face_count": faces,
        "level_count": level_count,
        "supercompression_scheme": scheme,
        "dfd": dfd,
        **dfd_info,
        "level_index": level_index,
        "binary_metadata": binary,
    }
    return levels, metadata, info


def _check_dfd(dfd: bytes, form: _Format, fail) -> dict:
    """Check that the DFD's first (basic) descriptor block describes ``form`` as KTX 2.0 "Restrictions" require."""
    if len(dfd) < 4 + 24:
        raise fail(f"DFD is {len(dfd)} bytes, too short for a basic descriptor block")
    w = struct.unpack_from("<6I", dfd, 4)
    vendor, dtype_ = w[0] & 0x1FFFF, w[0] >> 17
    version, block_size = w[1] & 0xFFFF, w[1] >> 16
    if vendor != _KHR_DF_VENDORID_KHRONOS or dtype_ != _KHR_DF_KHR_DESCRIPTORTYPE_BASICFORMAT:
        raise fail(f"first DFD block is not a Khronos basic descriptor block (vendorId {vendor}, type {dtype_})")
    if version != _KHR_DF_VERSIONNUMBER:
        raise fail(f"basic descriptor block versionNumber {version} (expected 2)")
    n_samples = (block_size - 24) // 16
    if block_size < 24 or (block_size - 24) % 16 or 4 + block_size > len(dfd):
        raise fail(f"basic descriptor block size {block_size} is inconsistent with the DFD's {len(dfd)} bytes")
    model, primaries, transfer, flags = w[2] & 0xFF, (w[2] >> 8) & 0xFF, (w[2] >> 16) & 0xFF, w[2] >> 24
    if model != _KHR_DF_MODEL_RGBSDA:
        raise fail(f"DFD colorModel {model} (expected 1, KHR_DF_MODEL_RGBSDA, for {form.name})")
    if w[3] != 0 or (w[4] & 0xFF) != form.texel_block_size:
        raise fail(f"DFD texel block / bytesPlane0 do not match {form.name} ({form.texel_block_size} bytes, 1x1)")
    bits = 8 * form.type_size
    channel_ids = _CHANNEL_IDS[form.channels]
    if n_samples != len(channel_ids):
        raise fail(f"DFD has {n_samples} samples; {form.name} has {len(channel_ids)} channels")
    for k, channel in enumerate(channel_ids):
        s0 = struct.unpack_from("<I", dfd, 4 + 24 + 16 * k)[0]
        offset, length, ctype = s0 & 0xFFFF, ((s0 >> 16) & 0xFF) + 1, s0 >> 24
        is_float = bool(ctype & _KHR_DF_SAMPLE_DATATYPE_FLOAT)
        if offset != k * bits or length != bits or (ctype & 0x0F) != channel or not is_float:
            raise fail(
                f"DFD sample {k} (bitOffset {offset}, {length} bits, channelType {ctype:#x}) does not describe "
                f"channel {channel} of {form.name}"
            )
    return {"color_model": model, "color_primaries": primaries, "transfer_function": transfer, "dfd_flags": flags}


def _parse_kvd(kvd: bytes, fail) -> tuple[dict[str, str], dict[str, bytes]]:
    text: dict[str, str] = {}
    binary: dict[str, bytes] = {}
    pos = 0
    while pos < len(kvd):
        if pos + 4 > len(kvd):
            raise fail("key/value data ends inside a keyAndValueByteLength field")
        (n,) = struct.unpack_from("<I", kvd, pos)
        start = pos + 4
        if n < 2 or start + n > len(kvd):
            raise fail(f"key/value pair at kvd offset {pos} has invalid keyAndValueByteLength {n}")
        entry = kvd[start:start + n]
        nul = entry.find(b"\x00")
        if nul <= 0:
            raise fail(f"key/value pair at kvd offset {pos} has no NUL-terminated key")
        try:
            key = entry[:nul].decode("utf-8")
        except UnicodeDecodeError as e:
            raise fail(f"key at kvd offset {pos} is not UTF-8: {e}") from e
        if key in text or key in binary:
            raise fail(f"key {key!r} appears more than once")
        raw = entry[nul + 1:]
        value = raw[:-1] if raw.endswith(b"\x00") else raw
        try:
            text[key] = value.decode("utf-8")
            if "\x00" in text[key]:
                raise UnicodeDecodeError("utf-8", value, 0, len(value), "embedded NUL")
        except UnicodeDecodeError:
            text.pop(key, None)
            binary[key] = bytes(raw)
        pos = start + n + (-n % 4)
    if pos != len(kvd):
        raise fail(f"key/value pairs with their padding take {pos} bytes, but kvdByteLength is {len(kvd)}")
    return text, binary
