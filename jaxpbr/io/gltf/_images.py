"""glTF images (PNG, JPEG, and WebP through EXT_texture_webp) decoded with OpenImageIO to float32 arrays of
the encoded values."""

from __future__ import annotations

import os
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np

from ... import _memory
from ._binary import UriRefused, fail, get, loc, open_regular, pointer, read_regular, read_uri, resolve_uri
from ._types import GltfImage

__all__ = ["PER_DECODED_VALUE", "SUPPORTED_MIME_TYPES", "header_shape", "image_source", "make_images"]

#: Peak bytes per decoded value (texel x channel) while OpenImageIO decodes a PNG or JPEG into the
#: float32 array that is kept (4 B of it): measured (peak RSS) 8.5 B for a 4096^2 RGBA PNG, 10.4 B
#: for a 4096 x 2048 RGB one; rounded up.
PER_DECODED_VALUE = 12.0

SUPPORTED_MIME_TYPES = ("image/png", "image/jpeg", "image/webp")
_SUFFIX = {"image/png": ".png", "image/jpeg": ".jpg", "image/webp": ".webp"}
_BY_EXTENSION = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".webp": "image/webp",
                 ".ktx2": "image/ktx2", ".dds": "image/vnd-ms.dds"}


def sniff(data: bytes) -> str | None:
    """The mime type the bytes' signature says, or None."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "image/png"
    if data[:3] == b"\xff\xd8\xff":
        return "image/jpeg"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "image/webp"
    if data[:12] == b"\xabKTX 20\xbb\r\n\x1a\n":
        return "image/ktx2"
    if data[:4] == b"DDS ":
        return "image/vnd-ms.dds"
    return None


_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})


def _webp_shape(head: bytes) -> tuple[int, int, int] | None:
    """(H, W, C) of a WebP from its first chunk (RIFF container, WebP container specification):
    VP8 (lossy: the key frame's 14-bit sizes, RGB), VP8L (lossless: 14-bit sizes minus one and the
    alpha hint) or VP8X (extended: 24-bit canvas sizes minus one, the alpha flag)."""
    if len(head) < 30:
        return None
    kind = head[12:16]
    if kind == b"VP8 ":
        if head[23:26] != b"\x9d\x01\x2a":
            return None
        w, h = struct.unpack_from("<HH", head, 26)
        w, h = w & 0x3FFF, h & 0x3FFF
        return (h, w, 3) if w and h else None
    if kind == b"VP8L":
        if head[20] != 0x2F:
            return None
        bits = int.from_bytes(head[21:25], "little")
        w, h, alpha = (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1, (bits >> 28) & 1
        return (h, w, 4 if alpha else 3)
    if kind == b"VP8X":
        alpha = head[20] & 0x10
        w = int.from_bytes(head[24:27], "little") + 1
        h = int.from_bytes(head[27:30], "little") + 1
        return (h, w, 4 if alpha else 3)
    return None


def header_shape(read) -> tuple[int, int, int] | None:
    """(H, W, C) of the array a PNG, JPEG or WebP decodes to, from its header alone; `read(offset,
    n)` returns bytes of the image. None when the header is not a PNG's IHDR, a JPEG's frame header
    or a WebP's first chunk (the decoder then refuses the image before it allocates its pixels). A
    palette PNG counts four channels (RGBA when it has transparency)."""
    head = read(0, 33)
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return _webp_shape(head)
    if head[:8] == b"\x89PNG\r\n\x1a\n":
        if len(head) < 26 or head[12:16] != b"IHDR":
            return None
        w, h, _, colour = struct.unpack(">IIBB", head[16:26])
        c = {0: 1, 2: 3, 3: 4, 4: 2, 6: 4}.get(colour)
        return (h, w, c) if c and w and h else None
    if head[:3] != b"\xff\xd8\xff":
        return None
    pos = 2
    for _ in range(4096):  # the frame header precedes the scan; segments are skipped by their length
        seg = read(pos, 10)
        if len(seg) < 2 or seg[0] != 0xFF:
            return None
        marker = seg[1]
        if marker == 0xFF:  # a fill byte
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # no length
            pos += 2
            continue
        if marker in (0xD9, 0xDA) or len(seg) < 4:
            return None
        if marker in _SOF:
            if len(seg) < 10:
                return None
            h, w, c = struct.unpack(">HHB", seg[5:10])
            return (h, w, c) if h and w and c else None
        pos += 2 + int.from_bytes(seg[2:4], "big")
    return None


def image_source(gltf, buffers, i):
    """(H, W, C) from image i's header or None, and the bytes of its encoded data (None when
    unknown), read without loading a buffer or decoding pixels."""
    images = gltf.images or []
    if not 0 <= i < len(images):
        return None, None
    im = images[i]
    uri, view = get(im, "uri"), get(im, "bufferView")
    if view is not None:
        views = gltf.bufferViews or []
        size = get(views[view], "byteLength") if isinstance(view, int) and 0 <= view < len(views) else None
        cache: dict = {}

        def read(offset, n):
            # one read of the first 64 KiB covers nearly every header; beyond, a read at the offset
            if offset + n <= 65536:
                if "head" not in cache:
                    cache["head"] = buffers.peek_view(view, 65536) or b""
                return cache["head"][offset : offset + n]
            return buffers.peek_view(view, n, offset) or b""

        return header_shape(read), size
    if uri is None:
        return None, None
    try:
        kind, _, value = resolve_uri(uri, buffers.base, buffers.roots)
    except ValueError:
        return None, None
    if kind == "data":
        return header_shape(lambda offset, n: value[offset : offset + n]), len(value)
    try:
        fd = open_regular(value)
    except (OSError, ValueError):
        return None, None
    try:
        return header_shape(lambda offset, n: os.pread(fd, n, offset)), os.fstat(fd).st_size
    except OSError:
        return None, None
    finally:
        os.close(fd)


def _png_problem(data: bytes, *, header_only: bool = False) -> str | None:
    """Why a PNG is broken, or None: its chunk structure (a chunk past the end of the data, a bad
    CRC, no IEND), then what else makes libpng fail (`jaxpbr.io.image.png_problem`: the IHDR's
    values, the chunks' order, the palette and, unless `header_only`, the image data's zlib stream,
    inflated a bounded step at a time to its end). Checked before libpng sees the data: libpng
    prints such errors to stderr besides failing."""
    from ..image import png_problem

    pos = 8
    while pos + 12 <= len(data):
        length, kind = struct.unpack_from(">I4s", data, pos)
        name = kind.decode("latin-1")
        if pos + 12 + length > len(data):
            return (f"is truncated: chunk {name!r} at byte {pos} needs {12 + length} bytes, "
                    f"{len(data) - pos} are left of the {len(data)}")
        if zlib.crc32(data[pos + 4 : pos + 8 + length]) & 0xFFFFFFFF != struct.unpack_from(">I", data, pos + 8 + length)[0]:
            return f"is corrupt: chunk {name!r} at byte {pos} fails its CRC check"
        if kind == b"IEND":
            problem = png_problem(data, header_only=header_only)
            return None if problem is None else f"is corrupt: {problem}"
        pos += 12 + length
    return f"is truncated: it ends after {len(data)} bytes without the IEND chunk"


def _decode(file, where: str, data: bytes, mime: str, path: Path | None) -> np.ndarray:
    import OpenImageIO as oiio

    from ..image import png_problem

    found = sniff(data)
    if mime not in SUPPORTED_MIME_TYPES or (found is not None and found not in SUPPORTED_MIME_TYPES):
        shown = found if found not in SUPPORTED_MIME_TYPES and found is not None else mime
        fail(file, where, f"mime type {shown!r} is not supported (jaxpbr decodes {', '.join(SUPPORTED_MIME_TYPES)})",
             "convert the image to PNG, JPEG or WebP (e.g. with gltf-transform or Blender) and re-export")
    if found is None:
        fail(file, where, f"declared as {mime} but its bytes are not a PNG, JPEG or WebP image",
             "the image is corrupt or mislabelled: re-export the asset")
    mime = found
    if mime == "image/png":  # the header here, the image data once the memory check has passed
        problem = _png_problem(data, header_only=True)
        if problem is not None:
            fail(file, where, f"the PNG data ({len(data)} bytes) {problem}",
                 "the image file is damaged or was cut short: export or download it again")
    tmp = None
    try:
        if path is None or path.suffix.lower() not in (".png", ".jpg", ".jpeg", ".webp") or _BY_EXTENSION[path.suffix.lower()] != mime:
            fd, tmp = tempfile.mkstemp(suffix=_SUFFIX[mime], prefix="jaxpbr-gltf-")
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            path = Path(tmp)
        config = oiio.ImageSpec()
        config.attribute("oiio:UnassociatedAlpha", 1)  # glTF alpha is straight; keep it so
        inp = oiio.ImageInput.open(str(path), config)
        if inp is None:
            fail(file, where, f"OpenImageIO cannot open the {mime} data: {oiio.geterror()}",
                 "the image is corrupt: re-export the asset")
        try:
            spec = inp.spec()
            _memory.require(f"decoding {where} ({spec.width}x{spec.height}, {spec.nchannels} channels)",
                            {"image": float(spec.width) * spec.height * spec.nchannels * PER_DECODED_VALUE},
                            where=f"glTF file {str(file)!r}", names={"image": "the image's resolution"})
            # (the chunks and the header were checked above: the image data's zlib stream now)
            if mime == "image/png" and (problem := png_problem(data)) is not None:
                fail(file, where, f"the PNG data ({len(data)} bytes) is corrupt: {problem}",
                     "the image file is damaged: export or download it again")
            pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
            err = inp.geterror() if pixels is None or inp.has_error else ""
        finally:
            inp.close()
        if pixels is None or err:
            fail(file, where, f"OpenImageIO cannot decode the {mime} data: {err or oiio.geterror()}",
                 "the image is corrupt: re-export the asset")
        pixels = np.asarray(pixels, np.float32).reshape(spec.height, spec.width, spec.nchannels)
        return np.ascontiguousarray(pixels)
    finally:
        if tmp is not None:
            os.unlink(tmp)


def make_images(gltf, buffers, file: Path) -> list[GltfImage]:
    """One `GltfImage` per entry of the file's `images`; sources are checked now, pixels decoded later."""
    out = []
    for i, im in enumerate(gltf.images or []):
        name = get(im, "name", "")
        at = pointer("images", i)
        label = f"image {i}" + (f" ({name!r})" if name else "")
        where = loc(label, at)
        mime = get(im, "mimeType")
        uri, view = get(im, "uri"), get(im, "bufferView")
        if view is not None:
            ref = at + "/bufferView"
            buffers.view(view, where, ref)  # range check now

            def load(view=view, where=where, ref=ref, mime=mime):
                data = buffers.view_bytes(view, where, ref)
                return _decode(file, where, data, mime or sniff(data) or "unknown", None)

            source = f"bufferView {view}"
            if mime is None:
                mime = sniff(buffers.peek_view(view, 16) or b"") or "unknown"
        elif uri is not None:
            try:
                kind, uri_mime, value = resolve_uri(uri, buffers.base, buffers.roots)
            except ValueError:
                kind, uri_mime, value = "bad", None, None
            if kind == "data":
                mime = mime or uri_mime or sniff(value) or "unknown"
                source = "data URI"

                def load(data=value, where=where, mime=mime):
                    return _decode(file, where, data, mime, None)
            else:
                if kind == "bad":
                    read_uri(file, loc(label, at + "/uri"), uri, buffers.base, buffers.roots)  # raises with the reason
                if not value.exists():
                    fail(file, loc(label, at + "/uri"), f"file {str(value)!r} (uri {uri!r}) not found",
                         "put the image next to the .gltf as its uri says, or re-export as a self-contained .glb")
                mime = mime or _BY_EXTENSION.get(value.suffix.lower()) or "unknown"
                source = str(value)

                def load(path=value, where=where, label=label, at=at, mime=mime, uri=uri):
                    try:
                        data = read_regular(path)  # a regular file only, no more than its size
                    except UriRefused as e:
                        fail(file, loc(label, at + "/uri"), f"uri {uri[:80]!r} {e}", e.fix)
                    except OSError as e:
                        fail(file, loc(label, at + "/uri"), f"cannot read {str(path)!r}: {e.strerror or e}",
                             "check the image file's path and permissions")
                    return _decode(file, where, data, mime, path)
        else:
            fail(file, where, "has neither uri nor bufferView", "repair or re-export the asset")
        out.append(GltfImage(i, name, mime, source, load))
    return out
