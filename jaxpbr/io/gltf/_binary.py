"""Buffers, buffer views and accessors decoded in NumPy (glTF 2.0 §3.6)."""

from __future__ import annotations

import base64
import binascii
import os
import re
import stat
import urllib.parse
from pathlib import Path

import numpy as np

from ... import _memory
from ...errors import InputError

__all__ = [
    "CONTAIN_FIX", "Buffers", "JsonDocument", "UriRefused", "asset_roots", "fail", "get", "loc", "open_regular", "pointer",
    "primitive_attributes", "read_regular", "read_uri", "regular_size", "resolve_uri",
]

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


def pointer(*parts) -> str:
    """The RFC 6901 JSON pointer of a location in the glTF JSON: pointer('meshes', 3, 'primitives', 0)
    -> '/meshes/3/primitives/0' ('~' and '/' in a key escaped as '~0' and '~1')."""
    return "".join("/" + str(p).replace("~", "~0").replace("/", "~1") for p in parts)


def loc(where: str, at: str) -> str:
    """'<where> (<JSON pointer>)': a readable name and the JSON location it stands for."""
    return f"{where} ({at})" if where else at


_NEWLINES = re.compile(r"\s*[\r\n]+\s*")


def fail(file, where: str, problem: str, fix: str):
    """Raise the loader's InputError, one line: '<file>: <where>: <problem>. Fix: <fix>'; `where`
    names the JSON location (see `loc`, `pointer`)."""
    where = f"{where}: " if where else ""
    raise InputError(_NEWLINES.sub(" ", f"glTF file {str(file)!r}: {where}{problem}. Fix: {fix}"))


class JsonDocument:
    """The glTF JSON's top-level properties as attributes (`doc.nodes`, `doc.extensionsUsed`; None
    when absent); everything below them stays the JSON's own dicts and lists, read with `get`.
    (Reading the JSON into typed objects cost about 1 ms per node: 17 minutes for a scene of a
    million nodes, against microseconds here.)"""

    __slots__ = ("_doc",)

    def __init__(self, doc: dict):
        self._doc = doc

    def __getattr__(self, key):
        if key.startswith("_"):
            raise AttributeError(key)
        return self._doc.get(key)


def primitive_attributes(prim) -> dict:
    """A primitive's attributes {name: accessor index} (the JSON object; unset ones left out)."""
    raw = get(prim, "attributes")
    if not raw:
        return {}
    return {k: v for k, v in (vars(raw) if not isinstance(raw, dict) else raw).items() if v is not None}


def get(obj, key, default=None):
    """`obj[key]` for the JSON's dicts (`obj.key` for other objects); `default` when absent or None
    (or when `obj` is not an object at all: the schema check reports that)."""
    if obj is None:
        return default
    value = obj.get(key) if isinstance(obj, dict) else getattr(obj, key, None)
    return default if value is None else value


_DATA_URI = re.compile(r"^data:(?P<mime>[^;,]*)(?P<params>(;[^;,]*)*?),(?P<data>.*)$", re.DOTALL)

#: The fix every containment refusal gives.
CONTAIN_FIX = ("copy the file into the asset's folder and give its path relative to the .gltf, or, if you trust the "
               "asset, allow the folder that holds it (read_gltf(path, roots=[DIR]), jp.load_gltf(path, roots=[DIR]), "
               "jaxpbr render --asset-root DIR)")


_EMBED_FIX = "embed the data (GLB or a base64 data: URI) or put the file next to the .gltf and give its relative path"


class UriRefused(ValueError):
    """A URI that names something an asset may not read (outside its folders, a scheme, not a
    regular file); the message says which rule it breaks, as a predicate of "uri '...'", and
    `fix` what to do."""

    def __init__(self, reason: str, fix: str = CONTAIN_FIX):
        super().__init__(reason)
        self.fix = fix


def asset_roots(file, roots=()) -> tuple[str, ...]:
    """The folders (real paths, symbolic links resolved) whose files an asset may read: the folder
    of `file` and each of `roots`. A root that is not an existing folder is an InputError."""
    out = [os.path.realpath(Path(file).parent)]
    for r in roots or ():
        if isinstance(r, (bytes, bytearray)) or not isinstance(r, (str, os.PathLike)):
            raise InputError(f"roots: {r!r} is not a folder path. Fix: pass folder paths, e.g. roots=['textures/']")
        real = os.path.realpath(r)
        if not os.path.isdir(real):
            raise InputError(f"roots: {str(r)!r} is not an existing folder. Fix: name the folder that holds the "
                             "asset's buffers or images")
        out.append(real)
    return tuple(dict.fromkeys(out))


def _inside(real: str, roots) -> bool:
    return any(real == r or real.startswith(r.rstrip(os.sep) + os.sep) for r in roots)


def resolve_uri(uri, base: Path, roots=None):
    """('data', mime, bytes) for a data: URI, else ('file', None, real path) of a relative
    reference to a file inside `roots` (default: `base` itself; see `asset_roots`).

    Raises `UriRefused` (a ValueError) with the rule a URI breaks: a scheme other than data:
    (file:, http:, ...), an absolute path, a network path ('//host/...'), a NUL byte, or a path that
    resolves (through '..', percent-encoded or not, or a symbolic link) outside the roots."""
    if not isinstance(uri, str):
        raise UriRefused("is not a string", _EMBED_FIX)
    if uri.startswith("data:"):
        m = _DATA_URI.match(uri)
        if m is None:
            raise UriRefused("is a malformed data: URI (no ',' separating the header from the data)", _EMBED_FIX)
        params = m.group("params").split(";")
        data = m.group("data")
        if "base64" in params:
            try:
                payload = base64.b64decode(data, validate=False)
            except (binascii.Error, ValueError) as e:
                raise UriRefused(f"is a data: URI with invalid base64 ({e})", _EMBED_FIX) from None
        else:
            payload = urllib.parse.unquote_to_bytes(data)
        return "data", m.group("mime") or None, payload
    parts = urllib.parse.urlsplit(uri)
    if parts.scheme:
        if len(parts.scheme) == 1:  # a Windows drive letter: an absolute path
            raise UriRefused("is an absolute path (a drive letter); an asset reads only files inside its own folder")
        if parts.scheme.lower() == "file":
            raise UriRefused("is a file: URI; an asset reads only data: URIs and files named by paths relative to it")
        raise UriRefused(f"has the URI scheme {parts.scheme + ':'!r}; an asset reads only data: URIs and files named by "
                         "paths relative to it (nothing is downloaded)",
                         "download the file next to the .gltf and give its relative path, or embed it (GLB or a data: URI)")
    if parts.netloc or uri.startswith("//"):
        raise UriRefused("is a network path ('//host/...'); an asset reads only files inside its own folder")
    path = urllib.parse.unquote(uri)
    if "\0" in path:
        raise UriRefused("holds a NUL byte", _EMBED_FIX)
    if path.startswith(("/", "\\")) or os.path.isabs(path):
        raise UriRefused("is an absolute path; an asset reads only files inside its own folder")
    roots = roots if roots is not None else (os.path.realpath(base),)
    real = os.path.realpath(Path(base) / path)
    if not _inside(real, roots):
        shown = "its own folder" if len(roots) == 1 else f"its own folder and the {len(roots) - 1} allowed by roots"
        raise UriRefused(f"resolves (through '..' or a symbolic link) to a file outside {shown}")
    return "file", None, Path(real)


def open_regular(path) -> int:
    """A read-only descriptor of `path` if it is a regular file, else `UriRefused` (a device such
    as /dev/zero, a FIFO, a socket or a folder: reading those could block or never end). The open
    does not block on a FIFO and does not follow a symbolic link in the last component (the path
    is a real path: one there now was put there after the check)."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    fd = os.open(path, flags)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = ("a folder" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                    else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
                    else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
            raise UriRefused(f"names {kind}, not a regular file", "give the path of a regular file inside the asset's folder")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return fd
    except BaseException:
        os.close(fd)
        raise


def read_regular(path, n: int | None = None, offset: int = 0) -> bytearray:
    """Bytes [offset, offset + n) of a regular file (`open_regular`), read into one buffer (no
    copy of it is made); n None: to the end of the file as it is when opened (never more than its
    size then). Fewer bytes come back when the file is shorter."""
    fd = open_regular(path)
    try:
        size = os.fstat(fd).st_size
        n = max(0, size - offset) if n is None else max(0, min(n, size - offset))
        out = bytearray(n)
        view, got = memoryview(out), 0
        while got < n:
            k = os.preadv(fd, [view[got:]], offset + got)
            if k == 0:
                break
            got += k
        view.release()
        if got < n:
            del out[got:]
        return out
    finally:
        os.close(fd)


def regular_size(path) -> int:
    """The size of a regular file (`open_regular`'s checks), without reading it."""
    fd = open_regular(path)
    try:
        return os.fstat(fd).st_size
    finally:
        os.close(fd)


def read_uri(file, where: str, uri: str, base: Path, roots=None, length: int | None = None) -> tuple[str | None, bytes, str]:
    """(mime from a data URI or None, bytes, description) of a buffer/image URI contained by
    `roots` (`resolve_uri`), or InputError naming `where`. length: read at most that many bytes
    of a file (a buffer's byteLength; the caller checks that enough came)."""
    try:
        kind, mime, value = resolve_uri(uri, base, roots)
    except UriRefused as e:
        fail(file, where, f"uri {str(uri)[:80]!r} {e}", e.fix)
    if kind == "data":
        return mime, value, "data URI"
    try:
        return None, read_regular(value, length), str(value)
    except FileNotFoundError:
        fail(file, where, f"file {str(value)!r} (uri {uri!r}) not found",
             "put the file next to the .gltf as its uri says (relative paths are relative to the .gltf), "
             "or re-export the asset as a self-contained .glb")
    except UriRefused as e:
        fail(file, where, f"uri {uri[:80]!r} {e}", e.fix)
    except OSError as e:
        fail(file, where, f"cannot read {str(value)!r}: {e.strerror or e}", "check the file's permissions and path")


def _peek_data_uri(uri: str, off: int, n: int) -> bytes | None:
    """Bytes [off, off + n) of a base64 data: URI's payload, decoding only the characters that hold
    them (4 characters per 3 bytes); None for other data URIs."""
    comma = uri.find(",")
    if comma < 0 or ";base64" not in uri[:comma]:
        return None
    first = off // 3
    text = uri[comma + 1 + 4 * first : comma + 1 + 4 * -(-(off + n) // 3)]
    try:
        data = base64.b64decode(text + "=" * (-len(text) % 4), validate=False)
    except (binascii.Error, ValueError):
        return None
    return data[off - 3 * first : off - 3 * first + n]


def _normalize(a: np.ndarray) -> np.ndarray:
    """glTF's normalized-integer decoding (§3.11): unsigned c / (2^n - 1), signed max(c / (2^(n-1) - 1), -1)."""
    kind, bits = a.dtype.kind, a.dtype.itemsize * 8
    if kind == "u":
        return (a.astype(np.float64) / float(2**bits - 1)).astype(np.float32)
    if kind == "i":
        return np.maximum(a.astype(np.float64) / float(2 ** (bits - 1) - 1), -1.0).astype(np.float32)
    return a


class Buffers:
    """The file's buffers (read on first use) and its accessors decoded to NumPy.

    Every method takes the readable name and the JSON pointer of the place that uses the object
    (`where`, `at`), so that an error names both the use and the object's own JSON location."""

    def __init__(self, gltf, file: Path, glb_bin: tuple[int, int] | None, roots: tuple[str, ...] | None = None):
        """glb_bin: (offset, length) of a GLB's BIN chunk in `file` (read on first use), or None;
        roots: the folders whose files the asset may read (`asset_roots`; default its own)."""
        self.gltf = gltf
        self.file = file
        self.base = file.parent
        self.roots = roots if roots is not None else asset_roots(file)
        self.glb_bin = glb_bin
        self._buffers: dict[int, bytes] = {}
        self._accessors: dict[int, np.ndarray] = {}

    # -- buffers and views -------------------------------------------------------------------
    def _buffer_entry(self, i, where: str, at: str):
        """(the buffer's JSON object, its name, its pointer), or InputError for a bad index."""
        buffers = self.gltf.buffers or []
        if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < len(buffers):
            fail(self.file, f"{where}: {at}" if where else at,
                 f"names buffer {i!r}, which does not exist (the file has {len(buffers)})", "repair or re-export the asset")
        b = buffers[i]
        return b, f"buffer {i}" + (f" ({get(b, 'name')!r:.60})" if get(b, "name") else ""), pointer("buffers", i)

    def buffer(self, i, where: str, at: str) -> bytes:
        """The bytes of buffer i. where: the user, named with its pointer ("bufferView 2
        (/bufferViews/2)"); at: the pointer of the property naming the buffer (/bufferViews/2/buffer)."""
        if isinstance(i, int) and i in self._buffers:
            return self._buffers[i]
        b, what, own = self._buffer_entry(i, where, at)
        uri = get(b, "uri")
        length = get(b, "byteLength", 0)
        if not isinstance(length, int) or isinstance(length, bool) or length < 0:
            fail(self.file, loc(what, own + "/byteLength"), f"byteLength {length!r:.40} is not a byte count",
                 "repair or re-export the asset")
        # Exactly byteLength bytes are read, once the memory guard has accepted them.
        _memory.require(f"reading {what}", {"byteLength": float(length)}, where=f"glTF file {str(self.file)!r}",
                        names={"byteLength": f"{own}/byteLength"})
        if uri is None:
            if i != 0 or self.glb_bin is None:
                fail(self.file, loc(what, own), "has no uri and is not the GLB binary chunk",
                     "give the buffer a uri, or store the asset as .glb with this as buffer 0")
            offset, size = self.glb_bin
            if length > size:
                fail(self.file, loc(what, own + "/byteLength"),
                     f"byteLength is {length} but the GLB's BIN chunk holds only {size} bytes",
                     "the buffer is truncated or stale: download or re-export the asset")
            try:
                data = read_regular(self.file, length, offset)
            except (OSError, UriRefused) as e:
                fail(self.file, loc(what, own), f"the GLB's BIN chunk cannot be read: {e}", "check the file and its permissions")
            source = "the GLB's BIN chunk"
        else:
            _, data, source = read_uri(self.file, loc(what, own + "/uri"), uri, self.base, self.roots, length)
            source = "its data URI" if source == "data URI" else f"file {source!r}"
        if len(data) < length:
            fail(self.file, loc(what, own + "/byteLength"),
                 f"byteLength is {length} but {source} holds only {len(data)} bytes",
                 "the buffer is truncated or stale: download or re-export the asset")
        if len(data) > length:  # a longer data URI: the bytes past byteLength are not the buffer's
            data = data[:length]
        self._buffers[i] = data
        return data

    def buffer_size(self, i) -> int | None:
        """The bytes buffer i will hold once read (its byteLength, or less when its file, GLB chunk
        or data URI is shorter: reading it then fails), without reading it; None when unknown."""
        if isinstance(i, int) and i in self._buffers:
            return len(self._buffers[i])
        buffers = self.gltf.buffers or []
        if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < len(buffers):
            return None
        length = get(buffers[i], "byteLength")
        if not isinstance(length, int) or isinstance(length, bool) or length < 0:
            return None
        uri = get(buffers[i], "uri")
        if uri is None:
            return min(length, self.glb_bin[1]) if i == 0 and self.glb_bin is not None else None
        if not isinstance(uri, str):
            return None
        if uri.startswith("data:"):
            return min(length, len(uri) * 3 // 4)
        try:
            kind, _, value = resolve_uri(uri, self.base, self.roots)
            return min(length, regular_size(value)) if kind == "file" else None
        except (ValueError, OSError):
            return None

    def _view_entry(self, i, where: str, at: str):
        """(bufferView i's JSON object, its pointer), or InputError for a bad index."""
        views = self.gltf.bufferViews or []
        if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < len(views):
            fail(self.file, f"{where}: {at}" if where else at,
                 f"names bufferView {i!r}, which does not exist (the file has {len(views)})", "repair or re-export the asset")
        return views[i], pointer("bufferViews", i)

    def view(self, i, where: str, at: str) -> tuple[bytes, int, int, int | None]:
        """(buffer bytes, start offset, byteLength, byteStride) of bufferView i, range-checked.
        where: the user, named with its pointer ("... accessor 7 (/accessors/7)", "image 1
        (/images/1)"); at: the pointer of the property naming the view (/accessors/7/bufferView)."""
        v, own = self._view_entry(i, where, at)
        bi = get(v, "buffer", 0)
        buf = self.buffer(bi, loc(f"bufferView {i}", own), own + "/buffer")
        off, length = get(v, "byteOffset", 0), get(v, "byteLength", 0)
        prefix = f"{where}: " if where else ""
        here = prefix + loc(f"bufferView {i}", own)
        for key, value in (("byteOffset", off), ("byteLength", length)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                fail(self.file, prefix + loc(f"bufferView {i}", f"{own}/{key}"),
                     f"{key} {value!r} is not a byte count", "repair or re-export the asset")
        if off + length > len(buf):
            fail(self.file, here,
                 f"covers bytes [{off}, {off + length}) of buffer {bi} ({pointer('buffers', bi)}), which has {len(buf)} bytes",
                 "the buffer is truncated or the bufferView is wrong: re-export the asset")
        stride = get(v, "byteStride")
        if stride is not None and (not isinstance(stride, int) or isinstance(stride, bool) or stride <= 0):
            fail(self.file, prefix + loc(f"bufferView {i}", f"{own}/byteStride"),
                 f"byteStride {stride!r} is not a positive byte count", "repair or re-export the asset")
        return buf, off, length, stride

    def view_bytes(self, i, where: str, at: str) -> bytes:
        buf, off, length, _ = self.view(i, where, at)
        return bytes(buf[off : off + length])

    def peek_view(self, i, n: int, start: int = 0) -> bytes | None:
        """Up to n bytes of bufferView i from byte `start` of the view, read without loading its
        buffer (a GLB chunk or an external file is read at the offset, a base64 data URI decoded
        there, a loaded buffer sliced); None when that cannot be done cheaply or the view is
        invalid (its use reports that)."""
        views = self.gltf.bufferViews or []
        if not isinstance(i, int) or not 0 <= i < len(views):
            return None
        v = views[i]
        bi, off, length = get(v, "buffer", 0), get(v, "byteOffset", 0), get(v, "byteLength", 0)
        if not all(isinstance(x, int) for x in (bi, off, length)):
            return None
        if not 0 <= start <= length:
            return b""
        off, n = off + start, max(0, min(n, length - start))
        if bi in self._buffers:
            return bytes(self._buffers[bi][off : off + n])
        buffers = self.gltf.buffers or []
        if not 0 <= bi < len(buffers):
            return None
        uri = get(buffers[bi], "uri")
        try:
            if uri is None:
                if bi != 0 or self.glb_bin is None:
                    return None
                path, pos = self.file, self.glb_bin[0] + off
            elif uri.startswith("data:"):
                return _peek_data_uri(uri, off, n)
            else:
                kind, _, value = resolve_uri(uri, self.base, self.roots)
                if kind != "file":
                    return None
                path, pos = value, off
            return read_regular(path, n, pos)
        except (ValueError, OSError):
            return None

    # -- accessors ---------------------------------------------------------------------------
    def _read(self, view_index, byte_offset, count, dtype, cols, rows, where, at, stride=None, packed=False):
        """(count, cols*rows) raw array from a bufferView (`at`: the pointer naming the view);
        matrix columns are 4-byte aligned. Elements are copied out through a strided view of the
        buffer (no index arrays: the copy is the only allocation)."""
        col_bytes = rows * dtype.itemsize
        col_stride = -(-col_bytes // 4) * 4 if cols > 1 else col_bytes
        elem = col_stride * (cols - 1) + col_bytes  # bytes an element spans
        buf, off, length, view_stride = self.view(view_index, where, at)
        if stride is None:  # tightly packed: an element's size, matrix columns padded
            stride = col_stride * cols if (packed or view_stride is None) else view_stride
        if stride < elem:
            fail(self.file, f"{where}: {loc(f'bufferView {view_index}', pointer('bufferViews', view_index, 'byteStride'))}",
                 f"byteStride {stride} is smaller than one element ({elem} bytes)", "repair or re-export the asset")
        if not isinstance(byte_offset, int) or isinstance(byte_offset, bool) or byte_offset < 0:
            fail(self.file, where, f"byteOffset {byte_offset!r} is not a byte count", "repair or re-export the asset")
        end = byte_offset + (stride * (count - 1) + elem if count else 0)
        if end > length:
            fail(self.file, where,
                 f"count {count} x {stride} bytes from byteOffset {byte_offset} reads bytes [{byte_offset}, {end}) "
                 f"of bufferView {view_index} ({pointer('bufferViews', view_index)}), which has {length} bytes",
                 "the accessor's count/byteOffset or the bufferView's byteLength is wrong: re-export the asset")
        if count == 0:
            return np.zeros((0, cols * rows), dtype)
        raw = np.ndarray((count, cols, col_bytes), np.uint8, buffer=buf, offset=off + byte_offset,
                         strides=(stride, col_stride, 1))
        return np.ascontiguousarray(raw).view(dtype).reshape(count, cols * rows)

    def _accessor_entry(self, i, where: str, at: str, allowed_types, allowed_components):
        """(accessor i's JSON object, the error location naming the use and the accessor, its pointer),
        its index, type and componentType checked (InputError otherwise)."""
        accessors = self.gltf.accessors or []
        if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < len(accessors):
            fail(self.file, loc(where, at), f"accessor {i!r} does not exist (the file has {len(accessors)})",
                 "repair or re-export the asset")
        own = pointer("accessors", i)
        where = f"{loc(where, at)}: {loc(f'accessor {i}', own)}"
        a = accessors[i]
        if allowed_types is not None and get(a, "type") not in allowed_types:
            fail(self.file, where, f"has type {get(a, 'type')}, expected {' or '.join(allowed_types)}",
                 "repair or re-export the asset")
        if allowed_components is not None and get(a, "componentType") not in allowed_components:
            names = ", ".join(COMPONENT_NAMES[c] for c in allowed_components)
            fail(self.file, where,
                 f"has componentType {COMPONENT_NAMES.get(get(a, 'componentType'), get(a, 'componentType'))}, "
                 f"expected one of {names}", "repair or re-export the asset")
        return a, where, own

    def accessor(self, i, where: str, at: str, *, allowed_types=None, allowed_components=None,
                 finite: bool = False) -> np.ndarray:
        """Accessor i decoded: (count,) for SCALAR, (count, n) for VECn, (count, n, n) for MATn.

        where, at: the use's readable name and JSON pointer (e.g. "mesh 3 ('Body') primitive 0
        NORMAL", "/meshes/3/primitives/0/attributes/NORMAL"); errors name both and the accessor's
        own pointer. finite: refuse NaN and infinite values (counted in the error).

        Normalized integer accessors come back as float32 (spec formulas); FLOAT as float32; other
        integer accessors keep their integer dtype. Sparse substitution and accessors without a
        bufferView (zeros) are handled; min/max are not used."""
        a, where, own = self._accessor_entry(i, where, at, allowed_types, allowed_components)
        if i in self._accessors:
            out = self._accessors[i]
        else:
            out = self._decode(a, where, own)
            out.flags.writeable = False  # shared by every primitive that reads it
            self._accessors[i] = out
        if finite and out.dtype.kind == "f":
            bad = ~np.isfinite(out)
            if bad.any():
                nan = int(np.isnan(out).sum())
                inf = int(bad.sum()) - nan
                first = int(np.argmax(bad.reshape(out.shape[0], -1).any(axis=1)))
                fail(self.file, where, f"holds {nan + inf} non-finite values ({nan} NaN, {inf} infinite) among its "
                     f"{out.size} values, the first in element {first}",
                     "fix the exporter's data (a NaN or infinite vertex attribute cannot be rendered) and re-export")
        return out

    def accessor_of_decoded(self, i, values: np.ndarray, where: str, at: str, *, allowed_types=None,
                            allowed_components=None, finite: bool = False) -> np.ndarray:
        """Accessor i filled with `values`, data decompressed elsewhere (KHR_draco_mesh_compression:
        the accessor describes the data and has no bufferView of its own): the accessor's type and
        componentType are checked as `accessor` checks them, its count against the values'; integer
        values are read as the accessor's componentType (normalized ones as float32, as `accessor`
        returns them), float values as float32."""
        a, where, _ = self._accessor_entry(i, where, at, allowed_types, allowed_components or tuple(COMPONENT_TYPES))
        ctype, atype = get(a, "componentType"), get(a, "type")
        if atype not in TYPE_SHAPES:
            fail(self.file, where, f"unknown type {atype!r}", "repair or re-export the asset")
        cols, rows = TYPE_SHAPES[atype]
        values = np.asarray(values)
        count = len(values)
        if get(a, "count") != count or (values.size and values.reshape(count, -1).shape[1] != cols * rows):
            fail(self.file, where, f"describes {get(a, 'count')!r} elements of {atype}, but the decompressed data holds "
                 f"{count} of {values.reshape(count, -1).shape[1] if count else '?'} components",
                 "the accessor and the compressed data do not match: re-export the asset")
        dtype = COMPONENT_TYPES[ctype]
        if values.dtype.kind == "f":
            if dtype.kind != "f" and not get(a, "normalized", False):
                fail(self.file, where, f"is {COMPONENT_NAMES[ctype]} without normalized: true, but the decompressed "
                     "data holds floating-point values", "the accessor and the compressed data do not match: re-export the asset")
            out = values.astype(np.float32)
        else:
            info = np.iinfo(dtype) if dtype.kind in "iu" else None
            if info is not None and values.size and (int(values.min()) < info.min or int(values.max()) > info.max):
                flat = values.reshape(count, -1)
                first = int(np.argmax(((flat < info.min) | (flat > info.max)).any(axis=1)))
                fail(self.file, where, f"is {COMPONENT_NAMES[ctype]}, but the decompressed data holds values outside its "
                     f"range (the first in element {first})", "the accessor and the compressed data do not match: re-export the asset")
            out = values.astype(dtype)
            if get(a, "normalized", False) and dtype.kind in "iu":
                out = _normalize(out)
        out = out.reshape(count) if atype == "SCALAR" else out.reshape(count, cols * rows)
        if finite and out.dtype.kind == "f" and not np.isfinite(out).all():
            bad = ~np.isfinite(out)
            first = int(np.argmax(bad.reshape(count, -1).any(axis=1)))
            fail(self.file, where, f"holds {int(bad.sum())} non-finite values among its {out.size} decompressed values, "
                 f"the first in element {first}", "fix the exporter's data and re-export")
        out.flags.writeable = False
        return out

    def _decode(self, a, where: str, own: str) -> np.ndarray:
        ctype, atype = get(a, "componentType"), get(a, "type")
        if ctype not in COMPONENT_TYPES:
            fail(self.file, where, f"unknown componentType {ctype}", "repair or re-export the asset")
        if atype not in TYPE_SHAPES:
            fail(self.file, where, f"unknown type {atype!r}", "repair or re-export the asset")
        dtype = COMPONENT_TYPES[ctype]
        cols, rows = TYPE_SHAPES[atype]
        count = get(a, "count", 0)
        if not isinstance(count, int) or isinstance(count, bool) or count < 0:
            fail(self.file, where, f"invalid count {count!r}", "repair or re-export the asset")
        view = get(a, "bufferView")
        if view is None:
            data = np.zeros((count, cols * rows), dtype)
        else:
            data = self._read(view, get(a, "byteOffset", 0), count, dtype, cols, rows, where, own + "/bufferView")
        sparse = get(a, "sparse")
        if sparse is not None:
            data = data.copy()
            n = get(sparse, "count", 0)
            si, sv = get(sparse, "indices"), get(sparse, "values")
            if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n <= count or si is None or sv is None:
                fail(self.file, f"{where}: {own}/sparse", f"sparse count {n!r} (at most the accessor's {count}) "
                     "or its indices/values are missing", "repair or re-export the asset")
            ictype = get(si, "componentType")
            if ictype not in (5121, 5123, 5125):
                fail(self.file, f"{where}: {own}/sparse/indices", f"componentType {ictype} is not an unsigned integer type",
                     "repair or re-export the asset")
            idx = self._read(get(si, "bufferView"), get(si, "byteOffset", 0), n, COMPONENT_TYPES[ictype], 1, 1,
                             f"{where}: sparse indices ({own}/sparse/indices)", f"{own}/sparse/indices/bufferView",
                             packed=True).ravel().astype(np.int64)
            vals = self._read(get(sv, "bufferView"), get(sv, "byteOffset", 0), n, dtype, cols, rows,
                              f"{where}: sparse values ({own}/sparse/values)", f"{own}/sparse/values/bufferView",
                              packed=True)
            if n and (idx.min() < 0 or idx.max() >= count):
                # (the position, never the value: buffer bytes are not echoed in messages)
                first = int(np.argmax((idx < 0) | (idx >= count)))
                fail(self.file, f"{where}: sparse indices ({own}/sparse/indices)",
                     f"the index at position {first} is outside [0, {count})", "repair or re-export the asset")
            data[idx] = vals
        if get(a, "normalized", False) and dtype.kind in "iu":
            data = _normalize(data)
        if atype == "SCALAR":
            return data.reshape(count)
        if cols == 1:
            return data
        # Column-major storage: element[c * rows + r] is row r of column c.
        return data.reshape(count, cols, rows).transpose(0, 2, 1).copy()
