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

from ._binary import fail, get, loc

__all__ = ["EXTENSION", "DracoGeometry", "decode_primitive", "draco_extension"]

EXTENSION = "KHR_draco_mesh_compression"
_FIX = "the compressed geometry is damaged or does not match the file: re-export the asset (or export it without Draco)"


@dataclass(frozen=True)
class DracoGeometry:
    """A primitive's decoded Draco geometry: the triangle list's vertex indices (3 T,) and, per
    glTF attribute name the extension maps, the decoded values (count, components) in the
    decoder's dtype (floats dequantized)."""

    indices: np.ndarray
    attributes: dict


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
