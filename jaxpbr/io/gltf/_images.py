"""glTF images (PNG, JPEG) decoded with OpenImageIO to float32 arrays of the encoded values."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from ._binary import fail, get, read_uri, resolve_uri
from ._types import GltfImage

__all__ = ["SUPPORTED_MIME_TYPES", "make_images"]

SUPPORTED_MIME_TYPES = ("image/png", "image/jpeg")
_SUFFIX = {"image/png": ".png", "image/jpeg": ".jpg"}
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


def _decode(file, where: str, data: bytes, mime: str, path: Path | None) -> np.ndarray:
    import OpenImageIO as oiio

    found = sniff(data)
    if mime not in SUPPORTED_MIME_TYPES or (found is not None and found not in SUPPORTED_MIME_TYPES):
        shown = found if found not in SUPPORTED_MIME_TYPES and found is not None else mime
        fail(file, where, f"mime type {shown!r} is not supported (jaxpbr decodes {', '.join(SUPPORTED_MIME_TYPES)})",
             "convert the image to PNG or JPEG (e.g. with gltf-transform or Blender) and re-export")
    if found is None:
        fail(file, where, f"declared as {mime} but its bytes are not a PNG or JPEG image",
             "the image is corrupt or mislabelled: re-export the asset")
    mime = found
    tmp = None
    try:
        if path is None or path.suffix.lower() not in (".png", ".jpg", ".jpeg") or _BY_EXTENSION[path.suffix.lower()] != mime:
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
        where = f"image {i}" + (f" ({name!r})" if name else "")
        mime = get(im, "mimeType")
        uri, view = get(im, "uri"), get(im, "bufferView")
        if view is not None:
            buffers.view(view, where)  # range check now

            def load(view=view, where=where, mime=mime):
                data = buffers.view_bytes(view, where)
                return _decode(file, where, data, mime or sniff(data) or "unknown", None)

            source = f"bufferView {view}"
            if mime is None:
                mime = sniff(buffers.view_bytes(view, where)) or "unknown"
        elif uri is not None:
            try:
                kind, uri_mime, value = resolve_uri(uri, buffers.base)
            except ValueError:
                kind, uri_mime, value = "bad", None, None
            if kind == "data":
                mime = mime or uri_mime or sniff(value) or "unknown"
                source = "data URI"

                def load(data=value, where=where, mime=mime):
                    return _decode(file, where, data, mime, None)
            else:
                if kind == "bad":
                    read_uri(file, where, uri, buffers.base)  # raises with the reason
                if not value.is_file():
                    fail(file, where, f"file {str(value)!r} (uri {uri!r}) not found",
                         "put the image next to the .gltf as its uri says, or re-export as a self-contained .glb")
                mime = mime or _BY_EXTENSION.get(value.suffix.lower()) or "unknown"
                source = str(value)

                def load(path=value, where=where, mime=mime):
                    try:
                        data = path.read_bytes()
                    except OSError as e:
                        fail(file, where, f"cannot read {str(path)!r}: {e}", "check the image file's path and permissions")
                    return _decode(file, where, data, mime, path)
        else:
            fail(file, where, "has neither uri nor bufferView", "repair or re-export the asset")
        out.append(GltfImage(i, name, mime, source, load))
    return out
