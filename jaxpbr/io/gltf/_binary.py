"""Buffers, buffer views and accessors decoded in NumPy (glTF 2.0 §3.6)."""

from __future__ import annotations

import base64
import binascii
import re
import urllib.parse
from pathlib import Path

import numpy as np

from ...errors import InputError

__all__ = ["Buffers", "fail", "read_uri", "resolve_uri"]

#: componentType -> little-endian NumPy dtype.
COMPONENT_TYPES = {
    5120: np.dtype("<i1"),
    5121: np.dtype("<u1"),
    5122: np.dtype("<i2"),
    5123: np.dtype("<u2"),
    5125: np.dtype("<u4"),
    5126: np.dtype("<f4"),
}
COMPONENT_NAMES = {
    5120: "BYTE",
    5121: "UNSIGNED_BYTE",
    5122: "SHORT",
    5123: "UNSIGNED_SHORT",
    5125: "UNSIGNED_INT",
    5126: "FLOAT",
}
#: type -> (columns, rows): a VECn is one column of n rows; MATn has n columns of n rows.
TYPE_SHAPES = {
    "SCALAR": (1, 1),
    "VEC2": (1, 2),
    "VEC3": (1, 3),
    "VEC4": (1, 4),
    "MAT2": (2, 2),
    "MAT3": (3, 3),
    "MAT4": (4, 4),
}


def fail(file, where: str, problem: str, fix: str):
    """Raise the loader's InputError: '<file>: <where>: <problem>. Fix: <fix>'."""
    where = f"{where}: " if where else ""
    raise InputError(f"glTF file {str(file)!r}: {where}{problem}. Fix: {fix}")


def get(obj, key, default=None):
    """`obj.key` for pygltflib objects or `obj[key]` for dicts; `default` when absent or None."""
    if obj is None:
        return default
    value = obj.get(key) if isinstance(obj, dict) else getattr(obj, key, None)
    return default if value is None else value


_DATA_URI = re.compile(r"^data:(?P<mime>[^;,]*)(?P<params>(;[^;,]*)*?),(?P<data>.*)$", re.DOTALL)


def resolve_uri(uri: str, base: Path):
    """('data', mime, bytes) for a data: URI, else ('file', None, Path) relative to `base`.

    Raises ValueError with a reason for URIs that are neither (remote, malformed)."""
    if uri.startswith("data:"):
        m = _DATA_URI.match(uri)
        if m is None:
            raise ValueError("malformed data: URI (no ',' separating the header from the data)")
        params = m.group("params").split(";")
        data = m.group("data")
        if "base64" in params:
            try:
                payload = base64.b64decode(data, validate=False)
            except (binascii.Error, ValueError) as e:
                raise ValueError(f"data: URI with invalid base64 ({e})") from None
        else:
            payload = urllib.parse.unquote_to_bytes(data)
        return "data", m.group("mime") or None, payload
    scheme = urllib.parse.urlsplit(uri).scheme
    if scheme and len(scheme) > 1:  # one letter: a Windows drive
        if scheme == "file":
            return "file", None, Path(urllib.parse.unquote(urllib.parse.urlsplit(uri).path))
        raise ValueError(f"remote or unsupported URI scheme {scheme!r}")
    return "file", None, base / urllib.parse.unquote(uri)


def read_uri(file, where: str, uri: str, base: Path) -> tuple[str | None, bytes, str]:
    """(mime from a data URI or None, bytes, description) of a buffer/image URI, or InputError."""
    try:
        kind, mime, value = resolve_uri(uri, base)
    except ValueError as e:
        fail(file, where, f"cannot read uri {uri[:80]!r}: {e}", "embed the data (GLB or a base64 data: URI) or "
             "put the file next to the .gltf and give its relative path")
    if kind == "data":
        return mime, value, "data URI"
    try:
        return None, value.read_bytes(), str(value)
    except FileNotFoundError:
        fail(file, where, f"file {str(value)!r} (uri {uri!r}) not found",
             "put the file next to the .gltf as its uri says (relative paths are relative to the .gltf), "
             "or re-export the asset as a self-contained .glb")
    except OSError as e:
        fail(file, where, f"cannot read {str(value)!r}: {e}", "check the file's permissions and path")


def _normalize(a: np.ndarray) -> np.ndarray:
    """glTF's normalized-integer decoding (§3.11): unsigned c / (2^n - 1), signed max(c / (2^(n-1) - 1), -1)."""
    kind, bits = a.dtype.kind, a.dtype.itemsize * 8
    if kind == "u":
        return (a.astype(np.float64) / float(2**bits - 1)).astype(np.float32)
    if kind == "i":
        return np.maximum(a.astype(np.float64) / float(2 ** (bits - 1) - 1), -1.0).astype(np.float32)
    return a


class Buffers:
    """The file's buffers (read on first use) and its accessors decoded to NumPy."""

    def __init__(self, gltf, file: Path, glb_blob: bytes | None):
        self.gltf = gltf
        self.file = file
        self.base = file.parent
        self.glb_blob = glb_blob
        self._buffers: dict[int, bytes] = {}
        self._accessors: dict[int, np.ndarray] = {}

    # -- buffers and views -------------------------------------------------------------------
    def buffer(self, i: int, where: str) -> bytes:
        if i in self._buffers:
            return self._buffers[i]
        buffers = self.gltf.buffers or []
        if not 0 <= i < len(buffers):
            fail(self.file, where, f"buffer {i} does not exist (the file has {len(buffers)})",
                 "repair or re-export the asset")
        b = buffers[i]
        what = f"buffer {i}" + (f" ({b.name!r})" if get(b, "name") else "")
        uri = get(b, "uri")
        if uri is None:
            if i != 0 or self.glb_blob is None:
                fail(self.file, what, "has no uri and is not the GLB binary chunk",
                     "give the buffer a uri, or store the asset as .glb with this as buffer 0")
            data = self.glb_blob
        else:
            _, data, _ = read_uri(self.file, what, uri, self.base)
        length = get(b, "byteLength", 0)
        if len(data) < length:
            fail(self.file, what, f"holds {len(data)} bytes but byteLength says {length}",
                 "the .bin file is truncated or stale: re-export the asset")
        self._buffers[i] = data
        return data

    def view(self, i: int, where: str) -> tuple[bytes, int, int, int | None]:
        """(buffer bytes, start offset, byteLength, byteStride) of bufferView i, range-checked."""
        views = self.gltf.bufferViews or []
        if not 0 <= i < len(views):
            fail(self.file, where, f"bufferView {i} does not exist (the file has {len(views)})",
                 "repair or re-export the asset")
        v = views[i]
        buf = self.buffer(get(v, "buffer", 0), f"{where} (bufferView {i})")
        off, length = get(v, "byteOffset", 0), get(v, "byteLength", 0)
        if off < 0 or length < 0 or off + length > len(buf):
            fail(self.file, f"{where}: bufferView {i}",
                 f"covers bytes [{off}, {off + length}) of buffer {get(v, 'buffer', 0)}, which has {len(buf)} bytes",
                 "the buffer is truncated or the bufferView is wrong: re-export the asset")
        return buf, off, length, get(v, "byteStride")

    def view_bytes(self, i: int, where: str) -> bytes:
        buf, off, length, _ = self.view(i, where)
        return bytes(buf[off : off + length])

    # -- accessors ---------------------------------------------------------------------------
    def _read(self, view_index, byte_offset, count, dtype, cols, rows, where, stride=None, packed=False):
        """(count, cols*rows) raw array from a bufferView; matrix columns are 4-byte aligned."""
        col_bytes = rows * dtype.itemsize
        col_stride = -(-col_bytes // 4) * 4 if cols > 1 else col_bytes
        elem = col_stride * (cols - 1) + col_bytes  # bytes an element spans
        buf, off, length, view_stride = self.view(view_index, where)
        if stride is None:  # tightly packed: an element's size, matrix columns padded
            stride = col_stride * cols if (packed or view_stride is None) else view_stride
        if stride < elem:
            fail(self.file, where, f"byteStride {stride} is smaller than one element ({elem} bytes)",
                 "repair or re-export the asset")
        end = byte_offset + (stride * (count - 1) + elem if count else 0)
        if byte_offset < 0 or end > length:
            fail(self.file, where,
                 f"reads bytes [{byte_offset}, {end}) of bufferView {view_index}, which has {length} bytes",
                 "the accessor's count/byteOffset or the bufferView's byteLength is wrong: re-export the asset")
        if count == 0:
            return np.zeros((0, cols * rows), dtype)
        raw = np.frombuffer(buf, np.uint8, count=end - byte_offset, offset=off + byte_offset)
        col_idx = (np.arange(cols)[:, None] * col_stride + np.arange(col_bytes)[None, :]).ravel()
        idx = np.arange(count)[:, None] * stride + col_idx[None, :]
        return np.ascontiguousarray(raw[idx]).view(dtype).reshape(count, cols * rows)

    def accessor(self, i: int, where: str, *, allowed_types=None, allowed_components=None) -> np.ndarray:
        """Accessor i decoded: (count,) for SCALAR, (count, n) for VECn, (count, n, n) for MATn.

        Normalized integer accessors come back as float32 (spec formulas); FLOAT as float32; other
        integer accessors keep their integer dtype. Sparse substitution and accessors without a
        bufferView (zeros) are handled; min/max are not used."""
        accessors = self.gltf.accessors or []
        if not isinstance(i, int) or not 0 <= i < len(accessors):
            fail(self.file, where, f"accessor {i} does not exist (the file has {len(accessors)})",
                 "repair or re-export the asset")
        where = f"{where} (accessor {i})"
        key = i
        if key in self._accessors:
            out = self._accessors[key]
        else:
            out = self._decode(accessors[i], where)
            out.flags.writeable = False  # shared by every primitive that reads it
            self._accessors[key] = out
        a = accessors[i]
        if allowed_types is not None and get(a, "type") not in allowed_types:
            fail(self.file, where, f"has type {get(a, 'type')}, expected {' or '.join(allowed_types)}",
                 "repair or re-export the asset")
        if allowed_components is not None and get(a, "componentType") not in allowed_components:
            names = ", ".join(COMPONENT_NAMES[c] for c in allowed_components)
            fail(self.file, where,
                 f"has componentType {COMPONENT_NAMES.get(get(a, 'componentType'), get(a, 'componentType'))}, "
                 f"expected one of {names}", "repair or re-export the asset")
        return out

    def _decode(self, a, where: str) -> np.ndarray:
        ctype, atype = get(a, "componentType"), get(a, "type")
        if ctype not in COMPONENT_TYPES:
            fail(self.file, where, f"unknown componentType {ctype}", "repair or re-export the asset")
        if atype not in TYPE_SHAPES:
            fail(self.file, where, f"unknown type {atype!r}", "repair or re-export the asset")
        dtype = COMPONENT_TYPES[ctype]
        cols, rows = TYPE_SHAPES[atype]
        count = get(a, "count", 0)
        if not isinstance(count, int) or count < 0:
            fail(self.file, where, f"invalid count {count!r}", "repair or re-export the asset")
        view = get(a, "bufferView")
        if view is None:
            data = np.zeros((count, cols * rows), dtype)
        else:
            data = self._read(view, get(a, "byteOffset", 0), count, dtype, cols, rows, where)
        sparse = get(a, "sparse")
        if sparse is not None:
            data = data.copy()
            n = get(sparse, "count", 0)
            si, sv = get(sparse, "indices"), get(sparse, "values")
            ictype = get(si, "componentType")
            if ictype not in (5121, 5123, 5125):
                fail(self.file, f"{where}: sparse.indices", f"componentType {ictype} is not an unsigned integer type",
                     "repair or re-export the asset")
            idx = self._read(get(si, "bufferView"), get(si, "byteOffset", 0), n, COMPONENT_TYPES[ictype], 1, 1,
                             f"{where}: sparse.indices", packed=True).ravel().astype(np.int64)
            vals = self._read(get(sv, "bufferView"), get(sv, "byteOffset", 0), n, dtype, cols, rows,
                              f"{where}: sparse.values", packed=True)
            if n and (idx.min() < 0 or idx.max() >= count):
                fail(self.file, f"{where}: sparse.indices", f"index {int(idx.max())} is outside [0, {count})",
                     "repair or re-export the asset")
            data[idx] = vals
        if get(a, "normalized", False) and dtype.kind in "iu":
            data = _normalize(data)
        if atype == "SCALAR":
            return data.reshape(count)
        if cols == 1:
            return data
        # Column-major storage: element[c * rows + r] is row r of column c.
        return data.reshape(count, cols, rows).transpose(0, 2, 1).copy()
