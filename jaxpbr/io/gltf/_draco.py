"""KHR_draco_mesh_compression: a primitive's geometry compressed with Google's Draco, decoded by
DracoPy (the Python binding of Draco's own decoder).

The spec's loader process: the extension's bufferView is decoded first; the primitive's `indices`
and the attributes the extension names are then read from the decoded geometry, through the
primitive's accessors (which describe the decompressed data and have no bufferView of their own:
`Buffers.accessor_of_decoded`); attributes the extension does not name are read as usual. Draco may
reorder and deduplicate vertices, so the decoded indices and attributes go together. Only TRIANGLES
primitives (Draco decodes a triangle list; the spec also allows TRIANGLE_STRIP, which no exporter
jaxpbr knows of writes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ... import _memory
from ._binary import fail, get, loc

__all__ = ["EXTENSION", "DracoGeometry", "declared_size", "decode_primitive", "draco_extension"]

EXTENSION = "KHR_draco_mesh_compression"
#: Peak bytes of DracoPy's decode per triangle and per decoded attribute value (vertex x
#: component), for the memory check before decoding: measured (peak RSS) 69-75 B per triangle in
#: all at 1.96 M triangles, 0.98 M vertices, POSITION, NORMAL and TEXCOORD_0 (edgebreaker and
#: sequential); 40 + 16 x 8 x 0.5 = 104 B per triangle with these constants.
PER_FACE = 40.0
PER_VALUE = 16.0
_METADATA_FLAG = 0x8000
_FIX = "the compressed geometry is damaged or does not match the file: re-export the asset (or export it without Draco)"


@dataclass(frozen=True)
class DracoGeometry:
    """A primitive's decoded Draco geometry: the triangle list's vertex indices (3 T,) and, per
    glTF attribute name the extension maps, the decoded values (count, components) in the
    decoder's dtype (floats dequantized)."""

    indices: np.ndarray
    attributes: dict


class _Short(Exception):
    """The header ends (or is malformed) before the counts."""


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    """A Draco varUI32 (LEB128, at most 5 bytes) at pos: (value, the position after it)."""
    value = 0
    for k in range(5):
        if pos >= len(buf):
            raise _Short
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << (7 * k)
        if not b & 0x80:
            return value, pos
    raise _Short


def _skip_string(buf: bytes, pos: int) -> int:
    if pos >= len(buf):
        raise _Short
    return pos + 1 + buf[pos]


def _skip_metadata_element(buf: bytes, pos: int, depth: int = 0) -> int:
    """The position after a metadata element (entries, then named sub-elements)."""
    if depth > 32:
        raise _Short
    n, pos = _varint(buf, pos)
    for _ in range(n):
        pos = _skip_string(buf, _skip_string(buf, pos))  # name, value
    subs, pos = _varint(buf, pos)
    for _ in range(subs):
        pos = _skip_metadata_element(buf, _skip_string(buf, pos), depth + 1)
    return pos


def declared_size(data: bytes) -> tuple[int, int] | None:
    """(triangles, vertices) that a Draco mesh's header declares (Draco bitstream specification
    2.2: the header, the optional metadata, then the sequential connectivity's num_faces and
    num_points or the edgebreaker's num_encoded_vertices and num_faces), or None where the header
    does not say: not Draco, a point cloud, a version before 2.2, or data that ends first."""
    if len(data) < 11 or bytes(data[:5]) != b"DRACO":
        return None
    major, minor, encoder_type, method = data[5], data[6], data[7], data[8]
    if (major, minor) < (2, 2) or encoder_type != 1:
        return None
    flags = int.from_bytes(bytes(data[9:11]), "little")
    pos = 11
    try:
        if flags & _METADATA_FLAG:
            n, pos = _varint(data, pos)
            for _ in range(n):
                _, pos = _varint(data, pos)  # the attribute's id
                pos = _skip_metadata_element(data, pos)
            pos = _skip_metadata_element(data, pos)  # the file's
        if method == 0:  # sequential
            faces, pos = _varint(data, pos)
            points, pos = _varint(data, pos)
            return faces, points
        if pos >= len(data):
            raise _Short
        vertices, pos = _varint(data, pos + 1)  # after the traversal type
        faces, pos = _varint(data, pos)
        return faces, vertices
    except _Short:
        return None


def draco_extension(prim) -> dict | None:
    """The primitive's KHR_draco_mesh_compression object, or None."""
    return (get(prim, "extensions", {}) or {}).get(EXTENSION)


def decode_primitive(buffers, ext, file, where: str, at: str, mode: int) -> DracoGeometry:
    """Decode the Draco data of a primitive (`at`: its JSON pointer; `ext`: its extension object)."""
    ext_at = at + "/extensions/" + EXTENSION
    if mode != 4:
        fail(file, loc(where, at + "/mode"), f"is Draco-compressed with mode {mode}; jaxpbr decodes Draco triangle "
             "lists (mode 4, TRIANGLES) only", "re-export the mesh as TRIANGLES (or without Draco compression)")
    view, names = get(ext, "bufferView"), get(ext, "attributes")
    if not isinstance(names, dict) or not all(isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool)
                                              for k, v in names.items()):
        fail(file, loc(where, ext_at + "/attributes"), f"must map attribute names to Draco attribute ids, got {names!r}",
             "repair or re-export the asset")
    data = buffers.view_bytes(view, where, ext_at + "/bufferView")
    declared = declared_size(data)
    if declared is not None:
        # Before the decoder allocates what the header declares (a few bytes can declare billions);
        # each named attribute counted as 4 components (VEC4, the widest glTF vertex attribute).
        faces, vertices = declared
        _memory.require(f"decoding the Draco geometry of {loc(where, ext_at)} ({faces} triangles, {vertices} vertices)",
                        {"draco": PER_FACE * faces + PER_VALUE * 4 * len(names) * vertices},
                        where=f"glTF file {str(file)!r}", names={"draco": "the Draco geometry's size"})
    try:
        import DracoPy
    except ImportError:  # (a dependency of jaxpbr: only a broken installation lacks it)
        fail(file, loc(where, ext_at), "is Draco-compressed and the DracoPy package is not importable",
             "install it (pip install DracoPy) or re-export the asset without Draco compression")
    try:
        mesh = DracoPy.decode(bytes(data))
    except Exception as e:  # noqa: BLE001 (DracoPy raises its own and ValueError/RuntimeError types)
        fail(file, loc(where, ext_at + "/bufferView"), f"its {len(data)} bytes do not decode as Draco geometry "
             f"({type(e).__name__}: {e})", _FIX)
    faces = getattr(mesh, "faces", None)
    faces = np.zeros((0, 3), np.int64) if faces is None else np.asarray(faces)
    if faces.size == 0 or faces.ndim != 2 or faces.shape[1] != 3:
        fail(file, loc(where, ext_at + "/bufferView"), "decodes to a Draco point cloud (no triangles)", _FIX)
    points = np.asarray(mesh.points)
    n = points.shape[0]
    indices = faces.astype(np.int64).reshape(-1)
    if indices.min() < 0 or indices.max() >= n:
        fail(file, loc(where, ext_at + "/bufferView"), f"decodes to triangles whose vertex indices leave [0, {n})", _FIX)
    held = sorted(a["unique_id"] for a in mesh.attributes)
    out = {}
    for name, uid in names.items():
        a = mesh.get_attribute_by_unique_id(uid)
        if a is None:
            fail(file, loc(f"{where} {name}", f"{ext_at}/attributes/{name}"),
                 f"names Draco attribute {uid}, which the compressed data does not hold (it holds {held})", _FIX)
        values = np.asarray(a["data"])
        k = int(a["num_components"])
        if values.size != n * k:
            fail(file, loc(f"{where} {name}", f"{ext_at}/attributes/{name}"),
                 f"Draco attribute {uid} holds {values.size} values, not {n} vertices x {k} components", _FIX)
        out[name] = values.reshape(n, k)
    return DracoGeometry(indices=indices, attributes=out)
