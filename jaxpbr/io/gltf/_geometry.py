"""Topology, transforms and generated normals: the NumPy geometry of the loader."""

from __future__ import annotations

import numpy as np

from ...geometry.pose import face_normals as pose_face_normals

__all__ = [
    "MODE_NAMES",
    "face_normals",
    "node_matrix",
    "normalize_rows",
    "quaternion_matrix",
    "triangle_list",
    "weld",
]

MODE_NAMES = {
    0: "POINTS",
    1: "LINES",
    2: "LINE_LOOP",
    3: "LINE_STRIP",
    4: "TRIANGLES",
    5: "TRIANGLE_STRIP",
    6: "TRIANGLE_FAN",
}


def triangle_list(idx: np.ndarray, mode: int) -> np.ndarray:
    """(T, 3) triangles from the primitive's vertex index sequence (glTF 2.0 §3.7.2.1).

    TRIANGLES: p_i = (v_3i, v_3i+1, v_3i+2); TRIANGLE_STRIP: p_i = (v_i, v_i+(1+i%2), v_i+(2-i%2));
    TRIANGLE_FAN: p_i = (v_i+1, v_i+2, v_0). The caller checks the count (3k; >= 3)."""
    idx = np.asarray(idx, np.int64)
    n = idx.shape[0]
    if mode == 4:
        return idx.reshape(n // 3, 3)
    i = np.arange(max(n - 2, 0))
    if mode == 5:
        odd = i % 2
        return np.stack([idx[i], idx[i + 1 + odd], idx[i + 2 - odd]], axis=1)
    if mode == 6:
        return np.stack([idx[i + 1], idx[i + 2], np.full_like(i, idx[0])], axis=1)
    raise ValueError(f"mode {mode} is not a triangle mode")


def quaternion_matrix(q) -> np.ndarray:
    """(3, 3) rotation of the unit quaternion q = (x, y, z, w) (normalized here)."""
    x, y, z, w = np.asarray(q, np.float64) / max(float(np.linalg.norm(q)), 1e-300)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def node_matrix(matrix=None, translation=None, rotation=None, scale=None) -> np.ndarray:
    """(4, 4) local transform: `matrix` (16 numbers, column-major) when given, else T @ R @ S."""
    if matrix is not None:
        return np.asarray(matrix, np.float64).reshape(4, 4).T.copy()
    m = np.eye(4)
    if rotation is None and scale is None:
        if translation is not None:
            m[:3, 3] = translation
        return m
    r = quaternion_matrix(rotation) if rotation is not None else np.eye(3)
    s = np.asarray(scale, np.float64) if scale is not None else np.ones(3)
    m[:3, :3] = r * s[None, :]
    if translation is not None:
        m[:3, 3] = translation
    return m


def normalize_rows(v: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length; zero rows stay zero."""
    v = np.asarray(v, np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), 0.0)


def face_normals(positions: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(T, 3) unit normals of counter-clockwise triangles (zero for degenerate ones), float64."""
    return pose_face_normals(np.asarray(positions, np.float64), tris)


def weld(arrays: list[np.ndarray], tris: np.ndarray):
    """Merge vertices whose attributes (the rows of all `arrays`) are bitwise equal.

    Returns (the welded arrays, the remapped triangles); vertex order follows first use."""
    n = arrays[0].shape[0]
    if n == 0:
        return arrays, tris
    row = np.concatenate([np.ascontiguousarray(a, np.float32).reshape(n, -1) for a in arrays], axis=1)
    row = np.ascontiguousarray(row)
    key = row.view(np.dtype((np.void, row.dtype.itemsize * row.shape[1]))).ravel()
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    order = np.argsort(first)  # keep first-use order
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    keep = first[order]
    return [a[keep] for a in arrays], rank[inverse.ravel()][tris]
