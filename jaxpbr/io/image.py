"""Image files: OpenEXR, Radiance ``.hdr`` and PNG reading and writing (host side, NumPy).

Formats
-------
``.exr``
    Linear float data: float32 or half, 1/3/4 channels stored as ``Y`` / ``RGB`` / ``RGBA``, ZIP compression,
    metadata as header attributes. Written through the OpenEXR package (``OpenEXR.File``); pixels are read
    through OpenImageIO and the header attributes through the OpenEXR package.
``.hdr``
    Radiance RGBE through OpenImageIO: linear, 3 channels, non-negative; each pixel shares one 8-bit exponent, so
    every channel is stored to within about 1/256 of the pixel's *largest* channel. No metadata.
``.png``
    Display-encoded 8- or 16-bit code values through OpenImageIO. :func:`write` encodes linear input
    (``encoding="srgb"`` through colour-science, or ``"gamma2.2"``) and :func:`read` returns the code values
    scaled to ``[0, 1]`` *without* decoding them (call :func:`jaxpbr.color.srgb_decode` for sRGB files).
    Alpha is stored straight (unassociated) and is never encoded. Metadata as text chunks (values come back as
    strings).

Reading prints nothing, also for a corrupt or truncated file: the decoders used report errors to the
caller (OpenImageIO keeps them for ``geterror``), and a PNG is checked chunk by chunk (:func:`png_problem`)
before libpng, which prints its fatal errors on stderr, is given it. The process's standard streams are never
touched.

Images are ``(H, W, C)`` arrays, row 0 at the top. Reads always return float32 ``(H, W, C)`` (``C = 1`` for
single-channel files). Writes accept NumPy or JAX arrays ``(H, W)`` or ``(H, W, C)`` with ``C`` in {1, 3, 4},
refuse NaN/Inf (and values the format cannot hold) with a message saying how many pixels are bad, and are atomic:
the file is written under a temporary name in the destination directory and renamed into place, so a failed
write leaves no file behind and never a half-written one.
"""

from __future__ import annotations

import json
import os
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np

from .. import color
from .atomic import atomic_write

__all__ = ["SUPPORTED_EXTENSIONS", "read", "read_with_metadata", "write"]

#: File extensions (lower case) that :func:`read` and :func:`write` understand.
SUPPORTED_EXTENSIONS = (".exr", ".hdr", ".png")

_HALF_MAX = 65504.0  # largest finite IEEE binary16 value
_FLOAT32_MAX = float(np.finfo(np.float32).max)
_INT32_RANGE = (-(2**31), 2**31 - 1)

# Structural EXR header attributes: written by the library itself, never returned or accepted as metadata.
_EXR_RESERVED = frozenset(
    {
        "channels",
        "compression",
        "dataWindow",
        "displayWindow",
        "lineOrder",
        "pixelAspectRatio",
        "screenWindowCenter",
        "screenWindowWidth",
        "tiles",
        "type",
        "name",
        "version",
        "chunkCount",
        "view",
        "maxSamplesPerPixel",
    }
)
_EXR_CHANNELS = {1: "Y", 3: "RGB", 4: "RGBA"}
_PNG_COLORSPACE = {"srgb": "sRGB", "gamma2.2": "Gamma2.2"}  # tags OIIO turns into the sRGB / gAMA chunks


# -------------------------------------------------------------------------------------------------- helpers


def _oiio():
    import OpenImageIO

    return OpenImageIO


def _exr():
    import OpenEXR

    return OpenEXR


def _extension(path: Path) -> str:
    ext = path.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        raise ValueError(
            f"unsupported image file extension {path.suffix or '(none)'!r} in {str(path)!r}; "
            f"supported: {', '.join(SUPPORTED_EXTENSIONS)}"
        )
    return ext


def _check_readable(path: Path) -> None:
    if not path.exists():
        raise FileNotFoundError(f"image file {str(path)!r} does not exist")
    if not path.is_file():
        raise ValueError(f"{str(path)!r} is not a regular file")
    if not os.access(path, os.R_OK):
        raise PermissionError(f"image file {str(path)!r} is not readable (check its permissions)")


#: The first bytes of each format (OpenEXR magic 20000630 little-endian; PNG signature; Radiance
#: "#?RADIANCE" or "#?RGBE" program type line).
_SIGNATURES = {
    ".exr": (b"\x76\x2f\x31\x01",),
    ".png": (b"\x89PNG\r\n\x1a\n",),
    ".hdr": (b"#?RADIANCE", b"#?RGBE"),
}
_FORMAT_NAMES = {".exr": "OpenEXR", ".png": "PNG", ".hdr": "Radiance HDR"}


def _check_format(path: Path, ext: str) -> None:
    """Refuse a file whose content is not the format its extension names (a PNG renamed .hdr would
    otherwise be read by content and its 8-bit code values taken as linear radiance)."""
    with open(path, "rb") as f:
        head = f.read(16)
    if any(head.startswith(sig) for sig in _SIGNATURES[ext]):
        return
    actual = next((_FORMAT_NAMES[e] for e, sigs in _SIGNATURES.items() if any(head.startswith(s) for s in sigs)), None)
    what = f"its content is {actual}" if actual else "its content is not an image format jaxpbr reads (corrupt, empty or truncated?)"
    raise ValueError(
        f"{str(path)!r} has the extension {ext} but {what}; give the file the extension of its real format"
        + (" (and note that PNG holds display-encoded values, not linear radiance)" if actual == "PNG" else "")
    )


# ------------------------------------------------------------------------------------------------------ read


def read(path, *, channels=None) -> np.ndarray:
    """Read an image file into a float32 ``(H, W, C)`` array.

    Args:
      path: ``.exr``, ``.hdr`` or ``.png`` file (``str`` or path-like; the extension picks the format).
      channels: ``.exr`` only: the channel names to read, in order (e.g. ``["Z"]`` or
        ``["diffuse.R", "diffuse.G", "diffuse.B"]``). By default ``R, G, B`` (plus ``A`` if present) are read;
        otherwise ``Y`` (plus ``A``); otherwise the only channel; otherwise the ``R, G, B(, A)`` of the one
        layer that has them.

    Returns:
      ``.exr``: the (first part's) data window, half/uint promoted to float32. ``.hdr``: linear radiance
      ``(H, W, 3)``. ``.png``: code values divided by 255 or 65535 — still display-encoded (apply
      :func:`jaxpbr.color.srgb_decode` to an sRGB image to get linear values); grey files give ``C = 1``,
      grey+alpha ``C = 2``; alpha is straight (not premultiplied).

    Raises:
      FileNotFoundError: the file does not exist.
      ValueError: unsupported extension, or the file is corrupt / not in the format its extension says.
    """
    return _read(path, channels, want_metadata=False)[0]


def dimensions(path) -> tuple[int, int, int] | None:
    """``(H, W, C)`` of an image file from its header, without reading the pixels (None if the
    header cannot be read: `read` then reports why)."""
    try:
        p = Path(os.fspath(path))
        if p.suffix.lower() == ".png" and _png_problem(p, header_only=True):
            return None  # libpng would print its error
        oiio = _oiio()
        inp = oiio.ImageInput.open(str(p))
        if inp is None:
            oiio.geterror()  # retrieved, or OIIO prints it at exit
            return None
        try:
            spec = inp.spec()
            return int(spec.height), int(spec.width), int(spec.nchannels)
        finally:
            inp.close()
    except Exception:  # noqa: BLE001 -- a missing or corrupt file: `read` gives the message
        return None


def read_with_metadata(path, *, channels=None) -> tuple[np.ndarray, dict]:
    """Like :func:`read`, and also return the file's metadata.

    Returns:
      ``(image, metadata)``. For ``.exr`` the header's string, int, float and double attributes other than the
      structural ones (channels, compression, windows, ...); values written by :func:`write` as JSON
      (dicts/lists/bools) come back as their JSON strings (``json.loads`` them). For ``.png`` the text
      attributes (all values are strings). For ``.hdr`` an empty dict.
    """
    return _read(path, channels, want_metadata=True)


def _read(path, channels, want_metadata):
    path = Path(os.fspath(path))
    ext = _extension(path)
    _check_readable(path)
    _check_format(path, ext)
    if channels is not None and ext != ".exr":
        raise ValueError(f"channels= selects EXR channels by name; {str(path)!r} is a {ext} file")
    if ext == ".exr":
        img, meta = _read_exr(path, channels, want_metadata)
    else:
        img, meta = _read_oiio(path, ext)
    if img.ndim != 3 or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"{str(path)!r} holds an empty or malformed image of shape {img.shape}")
    return img, (meta if want_metadata else {})


def _read_exr(path: Path, channels, want_metadata):
    # Pixels through OpenImageIO, which reports a corrupt file through geterror(); the OpenEXR
    # binding prints a warning on stdout and libOpenEXR a line on stderr for one. The header
    # attributes come from the binding (their EXR names and types), once OpenImageIO has decoded
    # the file, so it never meets a broken file.
    oiio = _oiio()
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"could not read {str(path)!r} as an OpenEXR image (corrupt or truncated?): {oiio.geterror()}")
    try:
        spec = inp.spec()
        if spec.deep:
            raise ValueError(f"{str(path)!r} is a deep OpenEXR image; deep images are not supported")
        all_names = list(spec.channelnames)
        names = _select_exr_channels(path, all_names, channels)
        index = [all_names.index(n) for n in names]
        formats = [spec.channelformat(i) for i in index]
        if all(f in (oiio.HALF, oiio.FLOAT) for f in formats):  # exact in float32: decode once
            pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
            planes = None if not isinstance(pixels, np.ndarray) else [pixels.reshape(pixels.shape[:2] + (-1,))[..., i] for i in index]
        else:  # integer (uint) channels: their own values, not OpenImageIO's [0, 1] normalisation
            planes = []
            for i, f in zip(index, formats):
                pixels = inp.read_image(0, 0, i, i + 1, f)
                if not isinstance(pixels, np.ndarray):
                    planes = None
                    break
                planes.append(pixels.reshape(pixels.shape[:2]))
        error = inp.geterror()
    finally:
        inp.close()
    if planes is None:
        raise ValueError(f"could not read {str(path)!r} as an OpenEXR image (corrupt or truncated?): {error}")
    img = np.stack([p.astype(np.float32, copy=False) for p in planes], axis=-1)

    meta = {}
    if not want_metadata:
        return img, meta
    OpenEXR = _exr()
    try:
        with OpenEXR.File(str(path), header_only=True) as f:
            header = dict(f.header())
    except Exception as e:  # decoded above, so not expected; reported like a corrupt file
        raise ValueError(f"could not read the header of {str(path)!r} (corrupt?): {e}") from e
    for key, value in header.items():
        if key in _EXR_RESERVED:
            continue
        if isinstance(value, str):
            meta[key] = value
        elif isinstance(value, (bool, np.bool_)):
            continue
        elif isinstance(value, (int, float)):
            meta[key] = value
        elif isinstance(value, np.ndarray) and value.dtype == np.float64 and value.size == 1:
            meta[key] = float(value.reshape(()))  # a `double` attribute (how write() stores Python floats)
    return img, meta


def _select_exr_channels(path: Path, names: list[str], requested):
    if requested is not None:
        requested = [requested] if isinstance(requested, str) else list(requested)
        missing = [n for n in requested if n not in names]
        if missing or not requested:
            raise ValueError(
                f"{str(path)!r} has no channel(s) {missing or requested}; its channels are {sorted(names)}"
            )
        return requested
    have = set(names)

    def rgba(prefix):
        rgb = [prefix + c for c in "RGB"]
        if not set(rgb) <= have:
            return None
        return rgb + ([prefix + "A"] if prefix + "A" in have else [])

    if (sel := rgba("")) is not None:
        return sel
    if "Y" in have and not ({"RY", "BY"} & have):
        return ["Y"] + (["A"] if "A" in have else [])
    if len(names) == 1:
        return names
    layers = {n.rsplit(".", 1)[0] + "." for n in names if n.endswith(".R")}
    found = [sel for p in sorted(layers) if (sel := rgba(p)) is not None]
    if len(found) == 1:
        return found[0]
    raise ValueError(
        f"{str(path)!r} has no unambiguous RGB/RGBA/Y channel set; its channels are {sorted(names)}. "
        "Pass channels=[...] to choose."
    )


def _read_oiio(path: Path, ext: str):
    if ext == ".png" and (problem := _png_problem(path)):
        raise ValueError(f"could not read {str(path)!r} as a PNG image (corrupt or truncated?): {problem}")
    oiio = _oiio()
    config = oiio.ImageSpec()
    # PNG stores straight alpha; without this hint OIIO premultiplies RGB by alpha on read.
    config.attribute("oiio:UnassociatedAlpha", 1)
    kind = "a Radiance .hdr" if ext == ".hdr" else "a PNG"
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise ValueError(f"could not read {str(path)!r} as {kind} image (corrupt or truncated?): {oiio.geterror()}")
    try:
        spec = inp.spec()
        if ext == ".hdr":
            orientation = spec.getattribute("Orientation")
            if orientation not in (None, 1):
                raise ValueError(
                    f"{str(path)!r} uses Radiance orientation code {orientation} (not '-Y H +X W'); "
                    "re-save it in the standard orientation (e.g. `oiiotool in.hdr --reorient -o out.hdr`)"
                )
            fmt = oiio.FLOAT
        else:
            fmt = spec.format
        pixels = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        error = inp.geterror()
    finally:
        inp.close()
    if pixels is None or not isinstance(pixels, np.ndarray) or pixels.size == 0:
        raise ValueError(f"could not read the pixels of {str(path)!r} (corrupt or truncated?): {error}")
    if pixels.ndim == 2:
        pixels = pixels[..., None]

    if ext == ".hdr":
        img = pixels.astype(np.float32, copy=False)
    else:
        if pixels.dtype == np.uint8:
            scale = 255.0
        elif pixels.dtype == np.uint16:
            scale = 65535.0
        else:  # pragma: no cover - PNG is 1/2/4/8/16-bit and OIIO delivers those as uint8/uint16
            raise ValueError(f"{str(path)!r}: unexpected PNG sample type {pixels.dtype}")
        img = (pixels.astype(np.float64) / scale).astype(np.float32)

    meta = {}
    if ext == ".png":
        for attr in spec.extra_attribs:
            if str(attr.type) == "string" and not attr.name.lower().startswith("oiio:"):
                meta[attr.name] = attr.value
    return img, meta


#: Samples per pixel of each PNG colour type, and the bit depths it allows (PNG specification, 11.2.2).
_PNG_COLOR_TYPES = {0: (1, (1, 2, 4, 8, 16)), 2: (3, (8, 16)), 3: (1, (1, 2, 4, 8)), 4: (2, (8, 16)), 6: (4, (8, 16))}
_PNG_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
_PNG_MAX_SIDE = 1_000_000  # libpng's default user limit on width and height
_PNG_FILTER_SUB = 0x10  # libpng's PNG_FILTER_SUB flag (OpenImageIO's "png:filter" attribute)
_PNG_CRITICAL = frozenset({b"IHDR", b"PLTE", b"IDAT", b"IEND"})
#: Bytes of a PNG's zlib stream given to the decompressor at a time, and the most it inflates at a
#: time, while checking a PNG (`png_problem`): the memory it needs whatever the header declares.
_PNG_FEED, _PNG_INFLATE_STEP = 1 << 16, 1 << 20


def _png_problem(path: Path, *, header_only: bool = False) -> str | None:
    """`png_problem` of a file's bytes."""
    return png_problem(path.read_bytes(), header_only=header_only)


def png_problem(data: bytes, *, header_only: bool = False) -> str | None:
    """What is wrong with the bytes of a PNG file, or None: the checks that make libpng fail, made
    first. Shared by the image files read here and the images of glTF assets (`jaxpbr.io.gltf`).

    On a fatal error libpng hands the message to OpenImageIO's handler and then prints it on
    stderr itself (``libpng error: ...``), so data libpng would refuse is refused here instead:
    the chunk layout up to the end of the image data (types of four ASCII letters with the reserved
    bit clear, lengths inside the data, one 13-byte IHDR first, no unknown critical chunk, no IEND
    before the data, one consecutive run of IDAT chunks), the CRC of every critical chunk, the IHDR
    values (size 1..1,000,000, libpng's limit, a bit depth the colour type allows, methods 0 and
    interlace 0/1), the palette a palette image needs (one PLTE of 1..256 entries) and (unless
    `header_only`) the zlib stream of the image data: it inflates without error to its end (its
    Adler-32 checked) and holds at least the bytes the image needs, with a valid filter type on
    every row. The stream is inflated a step at a time (`_PNG_INFLATE_STEP`) and never kept: memory
    stays bounded whatever size the header declares or the stream expands to. OpenImageIO reads
    nothing after the image data, and libpng drops an ancillary chunk with a bad CRC with a warning
    it does not print; neither is checked."""
    data = memoryview(data)
    if bytes(data[:8]) != b"\x89PNG\r\n\x1a\n":
        return "the data does not start with the PNG signature"
    pos, chunks = 8, []
    while True:
        if chunks and chunks[-1][0] == b"IDAT" and bytes(data[pos + 4 : pos + 8]) != b"IDAT":
            break  # OpenImageIO stops reading after the image data
        if pos + 8 > len(data):
            return "the file ends inside a chunk header (truncated?)"
        length, kind = struct.unpack_from(">I4s", data, pos)
        if not kind.isalpha():  # bytes.isalpha: ASCII letters only
            return f"a chunk has the invalid type {kind!r} (corrupt?)"
        if not kind[2:3].isupper():  # the reserved bit (the third letter's case) must be 0
            return f"chunk {kind.decode('latin-1')!r} has a reserved type (corrupt?)"
        if header_only and kind == b"IDAT":  # the header is read; the data is not
            chunks.append((kind, b""))
            break
        end = pos + 12 + length
        if length > 2**31 - 1 or end > len(data):
            return f"chunk {kind!r} runs past the end of the file (truncated?)"
        body = data[pos + 8 : end - 4]
        critical = kind[:1].isupper()
        if critical and zlib.crc32(body, zlib.crc32(kind)) != struct.unpack_from(">I", data, end - 4)[0]:
            return f"chunk {kind.decode('latin-1')!r} has a bad CRC (corrupt?)"
        if critical and kind not in _PNG_CRITICAL:
            return f"chunk {kind.decode('latin-1')!r} is an unknown critical chunk"
        if chunks and kind in (b"IHDR", b"IEND"):
            return f"chunk {kind.decode('latin-1')!r} is out of place"
        if kind == b"PLTE" and any(k == b"PLTE" for k, _ in chunks):
            return "the image has two PLTE chunks"
        chunks.append((kind, body))
        pos = end
    if chunks[0][0] != b"IHDR" or len(chunks[0][1]) != 13:
        return "the first chunk is not a 13-byte IHDR"
    width, height, depth, ctype, compression, filtering, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    if not (0 < width <= _PNG_MAX_SIDE and 0 < height <= _PNG_MAX_SIDE):
        return f"image size {width} x {height} is outside 1..{_PNG_MAX_SIDE}"
    if ctype not in _PNG_COLOR_TYPES or depth not in _PNG_COLOR_TYPES[ctype][1]:
        return f"invalid colour type {ctype} with bit depth {depth}"
    if compression or filtering or interlace not in (0, 1):
        return f"unknown compression, filter or interlace method ({compression}, {filtering}, {interlace})"
    kinds = [k for k, _ in chunks]
    if b"IDAT" not in kinds:
        return "no IDAT (image data) chunk"
    if ctype == 3:
        palette = [body for k, body in chunks[: kinds.index(b"IDAT")] if k == b"PLTE"]
        if not palette:
            return "a palette image without a PLTE chunk before its data"
        if not (0 < len(palette[0]) <= 3 * 256 and len(palette[0]) % 3 == 0):
            return f"the PLTE chunk has {len(palette[0])} bytes, not 1 to 256 RGB entries"
    if header_only:
        return None
    return _png_data_problem((body for kind, body in chunks if kind == b"IDAT"), width, height, depth, ctype, interlace)


def _png_data_problem(idat, width: int, height: int, depth: int, ctype: int, interlace: int) -> str | None:
    """What is wrong with the zlib stream of a PNG's image data (the bodies of its IDAT chunks,
    in order), or None; see `png_problem`."""
    passes = []  # (offset in the stream, row count, bytes per row with the filter byte) of each pass
    expected = 0
    samples = _PNG_COLOR_TYPES[ctype][0]
    for x0, y0, dx, dy in _PNG_ADAM7 if interlace else ((0, 0, 1, 1),):
        w, h = -(-(width - x0) // dx), -(-(height - y0) // dy)
        if w > 0 and h > 0:  # libpng skips an empty pass
            passes.append((expected, h, 1 + -(-(w * samples * depth) // 8)))
            expected += h * passes[-1][2]
    inflate = zlib.decompressobj()
    done = 0  # bytes of the stream inflated so far
    try:
        for body in idat:
            for at in range(0, len(body), _PNG_FEED):
                pending = body[at : at + _PNG_FEED]
                while True:
                    out = inflate.decompress(pending, _PNG_INFLATE_STEP)
                    pending = inflate.unconsumed_tail
                    if out and done < expected:  # the filter types of the rows that start in `out`
                        codes = np.frombuffer(out, np.uint8)
                        for start, h, n in passes:
                            first = start + max(0, -(-(done - start) // n)) * n
                            stop = min(done + len(out), start + h * n)
                            if first < stop and (codes[first - done : stop - done : n] > 4).any():
                                return "a row has an invalid filter type (corrupt?)"
                    done += len(out)
                    # input used up and the output not full: zlib holds no more output for now
                    if inflate.eof or (not pending and len(out) < _PNG_INFLATE_STEP):
                        break
                if inflate.eof:
                    break
            if inflate.eof:
                break
    except zlib.error as e:
        return f"the image data does not decompress ({e})"
    if done < expected:
        return f"the image data holds {done} of the {expected} bytes the image needs (truncated?)"
    if not inflate.eof:
        return "the image data's zlib stream does not end (truncated?)"
    return None


# ----------------------------------------------------------------------------------------------------- write


def write(path, img, *, metadata=None, half=False, bits=8, encoding="srgb", encoded=False, layers=None) -> None:
    """Write an image atomically; the extension picks the format.

    Args:
      path: destination ``.exr``, ``.hdr`` or ``.png`` (its directory must exist and be writable).
      img: ``(H, W)`` or ``(H, W, C)`` NumPy/JAX array, ``C`` in {1, 3, 4} (grey / RGB / RGBA), no NaN or Inf.
        ``.exr`` and ``.hdr`` take linear values (``.hdr``: RGB only, no negative values). ``.png`` takes linear
        values in ``[0, 1]`` scale that are encoded per ``encoding`` (alpha excepted), clipped to ``[0, 1]`` and
        rounded to the nearest code value (ties to even).
      metadata: optional dict of ``str -> value``. ``.exr``: written as header attributes — ``str`` as string,
        ``int`` as int (must fit 32 bits), ``float`` as double; ``dict``/``list``/``tuple``/``bool``/``None`` as
        JSON strings. ``.png``: text chunks (numbers written as their ``repr``, the rest as above). ``.hdr``
        cannot store it (a warning says so).
      half: ``.exr`` only: store IEEE half floats (values must satisfy ``|x| <= 65504``).
      bits: ``.png`` only: 8 or 16 bits per channel.
      encoding: ``.png`` only: ``"srgb"`` (IEC 61966-2-1 through colour-science, :func:`jaxpbr.color.srgb_encode_np`),
        ``"gamma2.2"`` (``max(c, 0) ** (1/2.2)``) or ``"linear"`` (values written as given — pass data that is
        already display-encoded, or non-colour data). The file is tagged sRGB (sRGB chunk) or gamma 2.2 (gAMA
        chunk) accordingly; ``"linear"`` keeps OpenImageIO's default sRGB tag.
      encoded: ``.png`` only: the values already carry the transfer function ``encoding`` (e.g. applied on the
        device with :func:`jaxpbr.color.encode`, in the same program as the tone map): they are written as given
        and the file is tagged for ``encoding``.
      layers: ``.exr`` only: more channels, ``{name: (H, W) array}`` with EXR channel names (``"Z"``,
        ``"N.X"``, ``"albedo.R"``, ...), written as float32 beside the image's own channels (e.g. the AOVs of
        :mod:`jaxpbr.rendering.aovs`); finite values, the image's height and width.

    Raises:
      ValueError: bad shape, channel count, dtype, NaN/Inf or out-of-range values, bad options or metadata.
      FileNotFoundError / NotADirectoryError / PermissionError: the destination directory is missing, is not a
        directory, or is not writable.
      OSError: the library failed to write the file (nothing is left behind).
    """
    path = Path(os.fspath(path))
    ext = _extension(path)
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16 (PNG bit depth); got {bits!r}")
    if encoding not in color.TRANSFERS:
        raise ValueError(
            f"unknown PNG encoding {encoding!r}; choose one of {', '.join(map(repr, color.TRANSFERS))}"
        )
    if half and ext != ".exr":
        raise ValueError(f"half=True only applies to .exr files; {str(path)!r} is a {ext} file")

    arr = _validated_image(img)
    if layers and ext != ".exr":
        raise ValueError(f"layers= only applies to .exr files; {str(path)!r} is a {ext} file")
    if ext == ".exr":
        payload = _exr_payload(arr, half)
        for name, layer in (layers or {}).items():
            a = np.asarray(layer)
            if a.shape != arr.shape[:2] or not np.all(np.isfinite(a)):
                raise ValueError(f"layer {name!r} must be a finite (H, W) = {arr.shape[:2]} array, got shape {a.shape}")
            if name in payload or name in ("R", "G", "B", "A", "Y"):
                raise ValueError(f"layer {name!r} would replace one of the image's own channels; name it differently")
            payload[name] = np.ascontiguousarray(a, np.float32)
        header = _exr_metadata(metadata)
        writer = lambda tmp: _write_exr(tmp, payload, header)  # noqa: E731
    elif ext == ".hdr":
        payload = _hdr_payload(arr)
        if metadata:
            warnings.warn(
                f"Radiance .hdr files cannot store metadata; {len(metadata)} key(s) were not written to "
                f"{str(path)!r} (use .exr to keep them)",
                UserWarning,
                stacklevel=2,
            )
        writer = lambda tmp: _write_oiio(tmp, "hdr", payload, {})  # noqa: E731
    else:
        payload = _png_payload(arr, bits, "linear" if encoded else encoding)
        attrs = _png_metadata(metadata)
        attrs["oiio:UnassociatedAlpha"] = 1  # store alpha as given (OIIO would otherwise un-premultiply)
        # libpng's "Sub" row filter for every row instead of trying all five per row: the 1280x720
        # demo writes in 45 against 67 ms, in a file 1 % larger.
        attrs["png:filter"] = _PNG_FILTER_SUB
        if encoding in _PNG_COLORSPACE:
            attrs["oiio:ColorSpace"] = _PNG_COLORSPACE[encoding]
        writer = lambda tmp: _write_oiio(tmp, "png", payload, attrs)  # noqa: E731
    atomic_write(path, _read_back(writer, arr.shape, ext[1:]))


def _read_back(writer, shape, fmt=None):
    """`writer` followed by a check that the temporary file decodes to an image of `shape` (H, W).

    The image libraries do not always report a failed write: on a full disk OpenImageIO's PNG and
    HDR writers and OpenEXR returned normally and left 0-byte or truncated files (issue 13). Reading
    the file back before it replaces the destination turns that into an error, and the
    destination is left as it was. A PNG is checked without decoding its pixels a second time:
    every critical chunk's CRC, a complete zlib stream of the image data with a valid filter byte
    on every row (`_png_problem`) and the size in its IHDR (writing the 1280x720 demo: 85 against
    101 ms)."""

    def run(tmp):
        writer(tmp)
        try:
            if fmt == "png":
                problem = _png_problem(Path(tmp))
                if problem is not None:
                    raise ValueError(problem)
                with open(tmp, "rb") as f:
                    width, height = struct.unpack(">II", f.read(24)[16:24])
                got = (height, width)
            else:
                img, _ = _read(tmp, None, want_metadata=False)
                got = img.shape[:2]
        except (ValueError, OSError) as e:
            raise OSError(f"the image was not written completely (is the disk full?): {e}") from e
        if got != tuple(shape[:2]):
            raise OSError(
                f"the image was not written completely (is the disk full?): it reads back as {got}, "
                f"expected {tuple(shape[:2])}"
            )

    return run


def _validated_image(img) -> np.ndarray:
    arr = np.asarray(img)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"image must be a real float or integer array; got dtype {arr.dtype}")
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3:
        raise ValueError(f"image must have shape (H, W) or (H, W, C); got shape {arr.shape}")
    if arr.shape[-1] not in (1, 3, 4):
        raise ValueError(
            f"image must have 1 (grey), 3 (RGB) or 4 (RGBA) channels in its last axis; got shape {arr.shape}"
        )
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"image is empty: shape {arr.shape}")
    if arr.dtype.kind == "f":
        finite = np.isfinite(arr)
        if not finite.all():
            bad_pixels = int(np.count_nonzero(~finite.all(axis=-1)))
            n_nan = int(np.count_nonzero(np.isnan(arr)))
            n_inf = int(arr.size - np.count_nonzero(finite) - n_nan)
            raise ValueError(
                f"image has {bad_pixels} of {arr.shape[0] * arr.shape[1]} pixels with non-finite values "
                f"({n_nan} NaN and {n_inf} Inf values); refusing to write. Find where they come from, or replace them "
                "explicitly (e.g. np.nan_to_num) if that is what you want."
            )
    return arr


def _count_pixels(mask: np.ndarray) -> int:
    return int(np.count_nonzero(mask.any(axis=-1)))


def _exr_payload(arr: np.ndarray, half: bool) -> dict:
    limit, name = (_HALF_MAX, "float16 (half)") if half else (_FLOAT32_MAX, "float32")
    too_big = np.abs(arr) > limit
    if too_big.any():
        fix = "Write float32 (half=False) or scale the image down" if half else "Scale the image down"
        raise ValueError(
            f"{_count_pixels(too_big)} pixels have values beyond the {name} maximum {limit:g} "
            f"(largest |value| {float(np.abs(arr).max()):g}); they would become Inf. {fix}."
        )
    dtype = np.float16 if half else np.float32
    name = _EXR_CHANNELS[arr.shape[-1]]
    # C-contiguous copies: the OpenEXR binding ignores NumPy strides and would scramble a strided view.
    data = np.ascontiguousarray(arr[..., 0] if name == "Y" else arr, dtype=dtype)
    return {name: data}


def _hdr_payload(arr: np.ndarray) -> np.ndarray:
    if arr.shape[-1] != 3:
        raise ValueError(
            f"Radiance .hdr stores RGB only; got {arr.shape[-1]} channels (write .exr for grey or RGBA images)"
        )
    negative = arr < 0
    if negative.any():
        raise ValueError(
            f"{_count_pixels(negative)} pixels have negative values, which Radiance RGBE cannot store "
            "(write .exr, or clip them explicitly if that is what you want)"
        )
    too_big = arr > _FLOAT32_MAX
    if too_big.any():
        raise ValueError(f"{_count_pixels(too_big)} pixels have values beyond the float32 maximum; scale them down")
    return np.ascontiguousarray(arr, dtype=np.float32)


def _png_payload(arr: np.ndarray, bits: int, encoding: str) -> np.ndarray:
    if arr.dtype.kind != "f":
        raise ValueError(
            f"PNG writing takes float values in [0, 1] scale; got integer dtype {arr.dtype} "
            "(divide 8-bit code values by 255 and pass encoding='linear')"
        )
    x = arr.astype(np.float64)
    n_color = 3 if x.shape[-1] == 4 else x.shape[-1]  # alpha is coverage, never transfer-encoded
    if encoding == "srgb":
        x[..., :n_color] = color.srgb_encode_np(x[..., :n_color])
    elif encoding == "gamma2.2":
        x[..., :n_color] = np.maximum(x[..., :n_color], 0.0) ** (1.0 / 2.2)
    top = 2**bits - 1
    codes = np.rint(np.clip(x, 0.0, 1.0) * top)
    return np.ascontiguousarray(codes, dtype=np.uint8 if bits == 8 else np.uint16)


def _metadata_items(metadata):
    if metadata is None:
        return []
    if not isinstance(metadata, dict):
        raise ValueError(f"metadata must be a dict of str -> value; got {type(metadata).__name__}")
    for key in metadata:
        if not isinstance(key, str) or not key:
            raise ValueError(f"metadata keys must be non-empty strings; got {key!r}")
        if key.lower().startswith("oiio:"):
            raise ValueError(f"metadata key {key!r} is reserved for OpenImageIO's own settings; rename it")
    return list(metadata.items())


def _json(key, value) -> str:
    if isinstance(value, np.ndarray):
        value = value.tolist()
    try:
        return json.dumps(value, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(
            f"metadata value for {key!r} ({type(value).__name__}) cannot be stored: {e}. "
            "Use str, int, float, or JSON-serialisable dict/list values."
        ) from e


def _exr_metadata(metadata) -> dict:
    OpenEXR = _exr()
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in _metadata_items(metadata):
        if key in _EXR_RESERVED:
            raise ValueError(
                f"metadata key {key!r} is a structural OpenEXR header attribute set by the writer; rename it"
            )
        if isinstance(value, str):
            header[key] = value
        elif isinstance(value, (bool, np.bool_)) or value is None:
            header[key] = _json(key, bool(value) if value is not None else None)
        elif isinstance(value, (int, np.integer)):
            v = int(value)
            if not _INT32_RANGE[0] <= v <= _INT32_RANGE[1]:
                raise ValueError(
                    f"metadata value {key!r} = {v} does not fit a 32-bit EXR int attribute; pass it as a str"
                )
            header[key] = v
        elif isinstance(value, (float, np.floating)):
            # A 0-d float64 array becomes an EXR `double` attribute; a Python float would be cut to 32 bits.
            header[key] = np.array(float(value), dtype=np.float64)
        else:
            header[key] = _json(key, value)
    return header


def _png_metadata(metadata) -> dict:
    attrs = {}
    for key, value in _metadata_items(metadata):
        if isinstance(value, str):
            attrs[key] = value
        elif isinstance(value, (bool, np.bool_)) or value is None:
            attrs[key] = _json(key, bool(value) if value is not None else None)
        elif isinstance(value, (int, np.integer)):
            attrs[key] = str(int(value))
        elif isinstance(value, (float, np.floating)):
            attrs[key] = repr(float(value))
        else:
            attrs[key] = _json(key, value)
    return attrs


def _write_exr(tmp: str, channels: dict, header: dict) -> None:
    OpenEXR = _exr()
    try:
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)
    except Exception as e:
        raise OSError(f"OpenEXR failed to write the image: {e}") from e


def _write_oiio(tmp: str, fmt: str, pixels: np.ndarray, attrs: dict) -> None:
    oiio = _oiio()
    h, w, c = pixels.shape
    typedesc = {np.dtype(np.float32): oiio.FLOAT, np.dtype(np.uint8): oiio.UINT8, np.dtype(np.uint16): oiio.UINT16}
    spec = oiio.ImageSpec(w, h, c, typedesc[pixels.dtype])
    for key, value in attrs.items():
        spec.attribute(key, value)
    out = oiio.ImageOutput.create(fmt)
    if out is None:
        raise OSError(f"OpenImageIO has no {fmt} writer: {oiio.geterror()}")
    if not out.open(tmp, spec):
        raise OSError(f"OpenImageIO could not open the file for writing: {out.geterror()}")
    ok = out.write_image(pixels)
    error = out.geterror()
    closed = out.close()
    if not ok or not closed:
        raise OSError(f"OpenImageIO failed to write the {fmt} image: {error or out.geterror()}")
