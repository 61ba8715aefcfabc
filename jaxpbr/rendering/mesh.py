"""Triangle meshes in a `Scene`: the `Mesh` object, visibility by a ray engine on the host, and the
surface of mesh pixels computed in JAX.

Visibility (which triangle a ray sees first) is a discrete choice with no derivative. It runs in a
ray engine (`jaxpbr.rendering.visibility`: Embree on the CPU, a JAX BVH elsewhere) reached from
inside the compiled geometry stage through `jax.pure_callback`, on rays whose gradient is stopped.
Everything after it is JAX: the hit triangle's vertices are gathered, the ray is intersected with
that triangle again (Moller-Trumbore) for the distance and barycentrics, and the vertex attributes
are interpolated. Image gradients therefore flow to vertex positions, normals, texture
coordinates, materials, lights and the camera (the interior of each triangle; not the motion of
silhouette edges, which needs edge sampling).

The ray engine's acceleration structure is built on the host once per mesh content (positions
and triangles, hashed) and kept in a small cache; the callback receives the vertices as
arguments, so a second mesh of the same sizes reuses the compiled programs, and meshes of other
sizes recompile the geometry stage only (the shading stages see per-pixel arrays).
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import threading
import weakref
from collections import OrderedDict
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._numerics import as_float, cross_rows, is_concrete, remember_per_array, safe_div, small_sq, vcross, vdot, vnormalize
from .._pytree import Pytree, leaf, static, subtree
from ..shading.material import Material
from .textured import TexturedMaterial

__all__ = ["ALPHA_MODES", "MAX_BLEND_LAYERS", "Mesh", "mesh_bounds"]

#: glTF alphaMode values.
ALPHA_MODES = ("OPAQUE", "MASK", "BLEND")
#: Most surfaces composited per pixel in a scene with BLEND meshes (the nearest first; the rest of
#: the ray behind the last one is not seen). Each layer costs one more shading of the image.
MAX_BLEND_LAYERS = 4


def _int_array(name: str, x, shape_tail: tuple[int, ...]) -> Any:
    if not is_concrete(x):
        return x
    a = np.asarray(x)
    if a.dtype.kind not in "iu":
        raise TypeError(f"{name} must hold integer vertex indices, got dtype {a.dtype}")
    if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail:
        raise ValueError(f"{name} must have shape (T, {', '.join(map(str, shape_tail))}), got {a.shape}")
    return _frozen(a, np.int32)


def _frozen(a: np.ndarray, dtype) -> np.ndarray:
    """`a` as a read-only C-contiguous array of `dtype` that owns its memory (copied unless it is
    one already): a Mesh's NumPy arrays cannot change under it, so the caches keyed by their
    identity (content digests, the host ray engine's arrays) stay valid."""
    if a.dtype == dtype and a.flags.c_contiguous and a.flags.owndata and not a.flags.writeable:
        return a
    b = np.array(a, dtype, order="C", copy=True)
    b.setflags(write=False)
    return b


def _float_rows(name: str, x, width: int, rows: int | None) -> Any:
    if x is None:
        return None
    if not is_concrete(x):
        return x
    a = np.asarray(x)
    if a.ndim != 2 or a.shape[1] != width or (rows is not None and a.shape[0] != rows):
        want = f"({rows if rows is not None else 'V'}, {width})"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or Inf")
    return jnp.asarray(a) if isinstance(x, jax.Array) else _frozen(a, np.float32 if a.dtype != np.float64 else np.float64)


class Mesh(Pytree):
    """A triangle mesh in world space with one material.

    positions: (V, 3) vertex positions (world space).
    triangles: (T, 3) integer vertex indices, counter-clockwise seen from the front.
    normals: (V, 3) vertex normals, or None for flat shading (each triangle's own normal).
    texcoords: (V, 2) TEXCOORD_0 in glTF's convention (origin at the image's top-left, v down).
    texcoords1: (V, 2) TEXCOORD_1 (read by textures whose `texcoord` is 1).
    tangents: (V, 4) xyz tangent and w = +-1, the bitangent's sign: B = w (N x T) (glTF).
    colors: (V, 4) COLOR_0, linear RGBA; RGB multiplies the base colour.
    material: Material or TexturedMaterial.
    double_sided: back faces are seen (with reversed normals, as glTF specifies); otherwise a
        ray passes through the back of a triangle (static).
    alpha_mode: glTF alphaMode (static): "OPAQUE"; "MASK": rays pass through the points whose
        alpha is below `alpha_cutoff` (they are neither seen nor cast shadows); "BLEND": the
        surface is composited over what lies behind it with its alpha (up to `MAX_BLEND_LAYERS`
        layers per pixel, nearest first; blended surfaces cast no shadows).
    alpha_cutoff: the MASK threshold (static, glTF default 0.5).
    alpha: baseColorFactor's alpha; the alpha of a point is alpha x the base colour texture's A
        (when it has 4 channels) x COLOR_0's A.
    unlit: the mesh's pixels show the material's emission alone, without lighting (a glTF
        KHR_materials_unlit material, whose colour `jaxpbr.load_gltf` makes the emission) (static);
        COLOR_0's RGB multiplies the emission too.

    A glTF asset becomes one Mesh per material (`jaxpbr.load_gltf`); a scene may mix meshes with
    spheres and planes. NumPy arrays are kept as read-only copies (a read-only array that owns its
    memory is kept as it is): changing the array passed in does not change the Mesh, and the
    renderer's caches keyed by the arrays' identity (the ray engine's structure, its inputs) stay
    valid. Make a new Mesh (or `replace`) to move vertices.
    """

    positions: Any = leaf(rank=2)
    triangles: Any = leaf(rank=2)
    normals: Any = leaf(None, rank=2)
    texcoords: Any = leaf(None, rank=2)
    texcoords1: Any = leaf(None, rank=2)
    tangents: Any = leaf(None, rank=2)
    colors: Any = leaf(None, rank=2)
    material: Any = subtree(default_factory=Material)
    double_sided: bool = static(False)
    alpha_mode: str = static("OPAQUE")
    alpha_cutoff: float = static(0.5)
    alpha: Any = leaf(1.0)
    unlit: bool = static(False)

    def _validate(self) -> None:
        if not isinstance(self.material, (Material, TexturedMaterial)):
            raise TypeError(f"Mesh.material must be a Material or TexturedMaterial, got {type(self.material).__name__}")
        pos = _float_rows("Mesh.positions", self.positions, 3, None)
        V = int(np.shape(pos)[0])
        tri = _int_array("Mesh.triangles", self.triangles, (3,))
        if np.shape(tri)[0] == 0 or V == 0:
            raise ValueError("a Mesh needs at least one triangle and three vertices")
        if is_concrete(tri):
            lo, hi = int(tri.min()), int(tri.max())
            if lo < 0 or hi >= V:
                raise ValueError(
                    f"Mesh.triangles index vertex {lo if lo < 0 else hi}, outside the {V} vertices of Mesh.positions"
                )
        self._set(
            positions=pos,
            triangles=tri,
            normals=_float_rows("Mesh.normals", self.normals, 3, V),
            texcoords=_float_rows("Mesh.texcoords", self.texcoords, 2, V),
            texcoords1=_float_rows("Mesh.texcoords1", self.texcoords1, 2, V),
            tangents=_float_rows("Mesh.tangents", self.tangents, 4, V),
            colors=_float_rows("Mesh.colors", self.colors, 4, V),
            double_sided=bool(self.double_sided),
            unlit=bool(self.unlit),
        )
        if self.alpha_mode not in ALPHA_MODES:
            raise ValueError(f"Mesh.alpha_mode must be one of {ALPHA_MODES} (glTF alphaMode), got {self.alpha_mode!r}")
        cutoff = float(self.alpha_cutoff)
        if not 0.0 <= cutoff <= 1.0:
            raise ValueError(f"Mesh.alpha_cutoff must be in [0, 1], got {cutoff}")
        alpha = as_float(self.alpha)
        if is_concrete(alpha) and not (np.ndim(alpha) == 0 and 0.0 <= float(alpha) <= 1.0):
            raise ValueError(f"Mesh.alpha must be a number in [0, 1] (baseColorFactor's alpha), got {alpha}")
        self._set(alpha_cutoff=cutoff, alpha=alpha)

    @property
    def num_triangles(self) -> int:
        return int(np.shape(self.triangles)[0])

    @property
    def num_vertices(self) -> int:
        return int(np.shape(self.positions)[0])


def mesh_parts(meshes) -> tuple:
    """The (vertex, triangle) offsets of each mesh in the concatenation (`concat_meshes`) and the
    totals, ((0, 0), ..., (V, T)): static (from the shapes), for the ray engine's `ACCELS.get`."""
    v = np.cumsum([0] + [m.num_vertices for m in meshes])
    t = np.cumsum([0] + [m.num_triangles for m in meshes])
    return tuple((int(a), int(b)) for a, b in zip(v, t, strict=True))


def mesh_bounds(meshes) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) corners of the world-space box around the meshes' vertices (host)."""
    pts = np.concatenate([np.asarray(m.positions, np.float64).reshape(-1, 3) for m in meshes])
    return pts.min(0), pts.max(0)


# ------------------------------------------------------------------------------------------
# Visibility on the host: one acceleration structure per content
# ------------------------------------------------------------------------------------------


class _Accels:
    """Acceleration structures by content digest (a small LRU: building one costs far more than
    hashing the arrays, ~30 ms for a million triangles)."""

    def __init__(self, capacity: int = 4):
        self.capacity = capacity
        self.entries: OrderedDict[bytes, Any] = OrderedDict()
        self.lock = threading.Lock()
        self.building: dict[bytes, threading.Event] = {}  # content being built by another thread
        self.builds = 0  # counted by tests: one build per mesh content
        self.built_triangles = 0  # triangles of those builds
        self.seen: set = set()  # the part digests of the latest call with parts (`get`)
        self.split = True  # False: one structure per content, parts or not (a benchmark's baseline)
        self.directory: Path | None = None  # `use_directory`

    def use_directory(self, directory) -> None:
        """Keep the JAX backend's BVHs in `directory` too (None: memory only), as `bvh-<digest>.npz`
        (about 100 bytes per triangle): a later process loads one instead of building it (the NumPy
        build takes about 7 s per million triangles; Embree's structures cannot be stored and are
        built each time). The command line turns it on beside its IBL maps."""
        self.directory = None if directory is None else Path(directory)

    def _file(self, digest: bytes) -> Path | None:
        if self.directory is None:
            return None
        from .._version import __version__

        return self.directory / f"bvh-{__version__}-{digest.hex()}.npz"

    def _load(self, digest: bytes, n_tri: int):
        path = self._file(digest)
        if path is None or not path.is_file():
            return None
        from .bvh import BVH
        from .visibility import TriangleAccel

        try:
            with np.load(path) as z:
                bvh = BVH(*(np.asarray(z[f]) for f in BVH._fields))
        except Exception:  # noqa: BLE001 -- damaged, truncated or foreign (zipfile, pickle, format errors): build it again
            return None
        from .cache import _touch

        _touch(path)
        return TriangleAccel("jax", bvh.to_device(), n_tri)

    def _store(self, digest: bytes, accel) -> None:
        path = self._file(digest)
        if path is None:
            return
        from ..io.atomic import atomic_write

        arrays = {f: np.asarray(a) for f, a in zip(accel.bvh._fields, accel.bvh, strict=True)}

        def write(tmp):
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)

        try:
            atomic_write(path, write)
        except OSError:  # a full or read-only cache only costs the next process a build
            pass

    def get(self, vertices: np.ndarray, triangles: np.ndarray, backend: str, *, exact_ties: bool = False, parts=None):
        """The structure of this content; `exact_ties` (the embree engine's build-time search for
        nearly coincident triangles, 5x its build time at 1.3 M triangles) only where the order of
        coincident surfaces matters: alpha-blended and cut-out layers walked by continuation.

        parts: the meshes the arrays concatenate (`mesh_parts`: K + 1 (vertex, triangle) offsets),
        or None. With parts, a mesh whose content is the same as in the previous call is static:
        the static meshes share one structure, kept from call to call, and the meshes that moved
        are built on their own (a `GroupedAccel` of the two). An animated character beside a static
        set rebuilds the character only."""
        tag = f"{backend}/{exact_ties}".encode()
        if parts is None or len(parts) < 3 or not self.split:
            return self._get(self._digest(tag, vertices, triangles), lambda: (vertices, triangles), backend, exact_ties)
        keys = part_keys(vertices, triangles, parts)  # (content only: `seen` is any engine's)
        parts = np.asarray(parts, np.int64)
        whole = hashlib.blake2b(b"".join([tag, np.int64(vertices.shape + triangles.shape).tobytes()] + keys), digest_size=20).digest()
        with self.lock:
            known = whole in self.entries or whole in self.building
            seen, self.seen = self.seen, set(keys)
        moved = [k for k, key in enumerate(keys) if key not in seen]
        n_moved = sum(int(parts[k + 1, 1] - parts[k, 1]) for k in moved)
        if known or not 0 < n_moved < len(triangles):  # nothing to split: one structure
            return self._get(whole, lambda: (vertices, triangles), backend, exact_ties)
        from .visibility import GroupedAccel

        def group(which):
            v = np.concatenate([vertices[parts[k, 0]:parts[k + 1, 0]] for k in which])
            shift = np.cumsum([0] + [parts[k + 1, 0] - parts[k, 0] for k in which])[:-1] - parts[which, 0]
            t = np.concatenate([triangles[parts[k, 1]:parts[k + 1, 1]] + np.int32(s) for k, s in zip(which, shift, strict=True)])
            ids = np.concatenate([np.arange(parts[k, 1], parts[k + 1, 1]) for k in which])
            return v, t, ids

        still = [k for k in range(len(keys)) if k not in set(moved)]
        static_key = hashlib.blake2b(b"".join([tag, b"/static"] + [keys[k] for k in still]), digest_size=20).digest()
        s_ids = np.concatenate([np.arange(parts[k, 1], parts[k + 1, 1]) for k in still])
        static = self._get(static_key, lambda: group(still)[:2], backend, exact_ties)

        def build():
            v, t, m_ids = group(moved)
            return GroupedAccel([(static, s_ids), (self._build(v, t, backend, exact_ties), m_ids)], len(triangles))

        return self._get(whole, None, backend, exact_ties, build=build)

    @staticmethod
    def _digest(tag: bytes, vertices: np.ndarray, triangles: np.ndarray) -> bytes:
        h = hashlib.blake2b(digest_size=20)
        h.update(tag)
        h.update(np.int64(vertices.shape + triangles.shape).tobytes())
        # Each array's content digest is remembered per array object: the shadow rays of several
        # lights query one mesh with the same arrays (1 M triangles: 18 MB hashed once, not per light).
        h.update(_content_digest(vertices))
        h.update(_content_digest(triangles))
        return h.digest()

    def _build(self, vertices, triangles, backend, exact_ties):
        from .visibility import TriangleAccel

        with self.lock:
            self.builds += 1
            self.built_triangles += int(triangles.shape[0])
        return TriangleAccel.build(vertices, triangles, backend=backend, **({"exact_ties": exact_ties} if backend == "embree" else {}))

    def _get(self, digest: bytes, arrays, backend: str, exact_ties: bool, build=None):
        """The entry `digest`, built from `arrays()` (or by `build()`) when it is not kept."""
        while True:  # one build per content: a second caller waits for the first one's build
            with self.lock:
                if digest in self.entries:
                    self.entries.move_to_end(digest)
                    return self.entries[digest]
                pending = self.building.get(digest)
                if pending is None:
                    self.building[digest] = threading.Event()
                    break
            pending.wait()  # then found in the entries (or built here if that build failed)
        try:
            if build is not None:
                accel = build()
            else:
                vertices, triangles = arrays()
                accel = self._load(digest, int(triangles.shape[0])) if backend == "jax" else None
                if accel is None:
                    accel = self._build(vertices, triangles, backend, exact_ties)
                    if backend == "jax":
                        self._store(digest, accel)
            with self.lock:
                self.entries[digest] = accel
                while len(self.entries) > self.capacity:
                    self.entries.popitem(last=False)
        finally:
            with self.lock:
                self.building.pop(digest).set()
        return accel


ACCELS = _Accels()

_DIGESTS: dict = {}  # (id(array), tag) -> (weakref, blake2b digest of its dtype, shape and bytes)


def part_keys(vertices: np.ndarray, triangles: np.ndarray, parts) -> list:
    """A content digest of each mesh of the concatenated arrays (`mesh_parts` offsets), remembered
    per array object and range (`remember_per_array`): the same arrays asked again (each light's
    shadow rays, a second frame of the same scene) are not hashed again."""
    out = []
    for (v0, t0), (v1, t1) in itertools.pairwise(parts):
        h = hashlib.blake2b(b"part", digest_size=20)
        h.update(np.int64((v1 - v0, t1 - t0)).tobytes())
        h.update(_range_digest(vertices, v0, v1))
        h.update(_range_digest(triangles, t0, t1))
        out.append(h.digest())
    return out


def _range_digest(x: np.ndarray, start: int, stop: int) -> bytes:
    def digest():
        h = hashlib.blake2b(digest_size=20)
        h.update(f"{x.dtype.str}{x.shape[1:]}".encode())
        h.update(np.ascontiguousarray(x[start:stop]).tobytes())
        return h.digest()

    return remember_per_array(_DIGESTS, x, f"blake2b[{start}:{stop}]", digest)


def _content_digest(x: np.ndarray) -> bytes:
    def digest():
        h = hashlib.blake2b(digest_size=20)
        h.update(f"{x.dtype.str}{x.shape}".encode())
        h.update(np.ascontiguousarray(x).tobytes())
        return h.digest()

    return remember_per_array(_DIGESTS, x, "blake2b", digest)


#: Most continuations of a ray through culled back faces before it is declared a miss.
MAX_CULLED_HITS = 16


def _host_cast(vertices, triangles, cull_back, o, d, alpha=None, layers: int = 1, parts=None):
    """The primitives (int32, -1 = miss) each ray o + t d sees on the host, nearest first, (..., layers)
    (or (...) for one layer): front faces, and back faces of double-sided meshes; a ray continues
    through the back of a single-sided triangle and through MASK cut-outs (alpha < cutoff), and past
    BLEND surfaces to the next layer (`TriangleAccel.intersect` continuation: the next hit after
    (t, prim) in the engine's order). parts: the meshes' offsets (`mesh_parts`), so that static
    meshes keep their structure while moved ones are rebuilt (`ACCELS.get`)."""
    vertices = np.ascontiguousarray(vertices, np.float32)
    triangles = np.ascontiguousarray(triangles, np.int32)
    accel = ACCELS.get(vertices, triangles, "embree" if _embree() else "jax", exact_ties=alpha is not None, parts=parts)
    cull_back = np.asarray(cull_back, bool)
    shape = np.shape(o)[:-1]
    o = np.asarray(o, np.float32).reshape(-1, 3)
    d = np.asarray(d, np.float32).reshape(-1, 3)
    n = o.shape[0]
    prim = np.full((n, layers), -1, np.int32)
    count = np.zeros(n, np.int64)
    todo = np.arange(n)
    tnear = np.zeros(n, np.float32)
    after = np.full(n, -1, np.int32)
    for first in [True] + [False] * (MAX_CULLED_HITS + layers - 1):
        if todo.size == 0:
            break
        bary = alpha is not None  # (only the alpha test reads the barycentrics here)
        if first:  # every ray: the arrays themselves, not copies gathered by index
            hits = accel.intersect(o, d, tnear=0.0, after_prim=-1, barycentrics=bary)
        else:
            hits = accel.intersect(o[todo], d[todo], tnear=tnear[todo], after_prim=after[todo], barycentrics=bary)
        p = np.asarray(hits.prim, np.int32)
        t = np.asarray(hits.t, np.float32)
        hit = p >= 0
        skip = np.zeros_like(hit)
        if hit.any() and cull_back.any():
            face_normal = _face_normals(accel, vertices, triangles)
            ph = p[hit]
            skip[hit] = cull_back[ph] & (np.einsum("ij,ij->i", face_normal[ph], d[todo[hit]]) > 0)
        blend = np.zeros_like(hit)
        if alpha is not None and hit.any():
            tri_mesh = np.asarray(alpha["tri_mesh"])
            mesh = tri_mesh[np.maximum(p, 0)]
            mode, a = host_alpha(alpha, triangles, p, np.asarray(hits.b1), np.asarray(hits.b2))
            skip |= hit & (mode == 1) & (a < np.asarray(alpha["cutoff"])[mesh])
            # A ray through the edge shared by two triangles of one blended surface meets both at
            # the same distance: one layer, not two.
            prev = after[todo]
            same = (prev >= 0) & (tri_mesh[np.maximum(prev, 0)] == mesh) & (np.abs(t - tnear[todo]) <= 1e-6 * np.maximum(1.0, np.abs(t)))
            skip |= hit & (mode == 2) & same & (count[todo] > 0)
            blend = hit & (mode == 2) & ~skip
        keep = ~skip
        rows = todo[keep]
        prim[rows, count[rows]] = np.where(hit[keep], p[keep], -1)
        count[rows] += 1
        # Go on past skipped surfaces, and past blended ones while layers are left.
        again = skip | (blend & (count[todo] < layers))
        nxt = todo[again]
        tnear[nxt] = t[again]
        after[nxt] = p[again]
        todo = nxt
    return prim.reshape(shape + ((layers,) if layers > 1 else ()))


_FACE_NORMALS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _face_normals(accel, vertices, triangles) -> np.ndarray:
    """(v1 - v0) x (v2 - v0) of every triangle, float32 (T, 3): computed once per ray engine
    (`ACCELS` builds one per content) rather than at each cast (1 M triangles: about 0.05 s); a
    grouped one's from its groups', so that a static group's are kept (triangles: the array, or a
    function giving it when needed)."""
    normals = _FACE_NORMALS.get(accel)
    if normals is None and hasattr(accel, "groups"):  # (`GroupedAccel`: each group's own, kept with it)
        normals = np.empty((len(triangles), 3), np.float32)
        for sub, ids in accel.groups:
            normals[ids] = _face_normals(sub, vertices, lambda ids=ids: triangles[ids])
        _FACE_NORMALS[accel] = normals
    if normals is None:
        triangles = triangles() if callable(triangles) else triangles
        e1 = vertices[triangles[:, 1]] - vertices[triangles[:, 0]]
        e2 = vertices[triangles[:, 2]] - vertices[triangles[:, 0]]
        normals = _FACE_NORMALS[accel] = cross_rows(e1, e2)
    return normals


def _embree() -> bool:
    try:
        import embreex  # noqa: F401
    except ImportError:
        return False
    return True


def cast(arrays, o, d, *, layers: int = 1):
    """The primitive ids (int32, -1 = miss) each ray (..., 3) sees, from inside a trace:
    `jax.pure_callback` to the host ray engine, (...) or with layers > 1 the nearest `layers`
    surfaces (..., layers) (BLEND). Rays and vertices are passed with their gradients stopped
    (visibility has none). With `arrays["bvh"]` (`device_accel`: opaque meshes rendered as one
    program off the CPU) the rays are traced in the program instead (`_device_cast`)."""
    o = jax.lax.stop_gradient(o).astype(jnp.float32)
    d = jax.lax.stop_gradient(d).astype(jnp.float32)
    if arrays.get("bvh") is not None and layers == 1 and arrays["alpha"] is None:
        return _device_cast(arrays, o, d)
    verts = jax.lax.stop_gradient(arrays["positions"]).astype(jnp.float32)
    alpha = jax.lax.stop_gradient(arrays["alpha"]) if arrays["alpha"] is not None else None
    out = jax.ShapeDtypeStruct(o.shape[:-1] + ((layers,) if layers > 1 else ()), jnp.int32)
    return jax.pure_callback(
        functools.partial(_host_cast, layers=layers, parts=arrays.get("parts")), out, verts, arrays["triangles"], arrays["cull_back"], o, d, alpha,
        vmap_method="sequential",
    )


#: Rays in flight in the in-program traversal (`bvh._trace`'s lanes): `TriangleAccel`'s choice
#: off the CPU.
DEVICE_LANES = 1 << 17


def _device_cast(arrays, o, d):
    """`_host_cast` for opaque meshes (one layer, no alpha) in the program: the JAX BVH
    (`arrays["bvh"]`, built on the host from the same float32 triangles) traced on the device, with
    the same continuation through the back faces of single-sided meshes (the next hit after
    (t, prim), at most MAX_CULLED_HITS times): no host round trip."""
    from .bvh import BVH, intersect_bvh
    from .visibility import intersect_groups

    bvh = arrays["bvh"]
    trace = intersect_bvh if isinstance(bvh, BVH) else intersect_groups
    shape = o.shape[:-1]
    o = o.reshape(-1, 3)
    d = jnp.broadcast_to(d, shape + (3,)).reshape(-1, 3)
    n = o.shape[0]
    verts = jax.lax.stop_gradient(arrays["positions"]).astype(jnp.float32)
    tri = arrays["triangles"]
    v0, v1, v2 = verts[tri[:, 0]], verts[tri[:, 1]], verts[tri[:, 2]]
    face_normal = jnp.cross(v1 - v0, v2 - v0)
    cull = arrays["cull_back"]
    lanes = min(DEVICE_LANES, n)

    def body(state):
        k, prim, tnear, after, todo = state
        h = trace(bvh, o, d, tnear=tnear, tfar=jnp.where(todo, jnp.inf, -jnp.inf), after_prim=after, lanes=lanes)
        p = h.prim
        hit = todo & (p >= 0)
        q = jnp.maximum(p, 0)
        skip = hit & cull[q] & (jnp.sum(face_normal[q] * d, -1) > 0)
        prim = jnp.where(todo & ~skip, jnp.where(hit, p, -1), prim)
        tnear = jnp.where(skip, h.t, tnear)
        after = jnp.where(skip, p, after)
        return k + 1, prim, tnear, after, skip

    state = (jnp.int32(0), jnp.full(n, -1, jnp.int32), jnp.zeros(n, jnp.float32), jnp.full(n, -1, jnp.int32),
             jnp.ones(n, bool))
    state = jax.lax.while_loop(lambda s: (s[0] <= MAX_CULLED_HITS) & jnp.any(s[4]), body, state)
    return state[1].reshape(shape)


def device_occluded(arrays, o, d, tfar):
    """`_host_occluded` for opaque meshes in the program (`arrays["bvh"]`): whether the segment
    o + t d, 0 <= t <= tfar, meets a triangle (either face)."""
    from .bvh import BVH, occluded_bvh

    shape = jnp.broadcast_shapes(o.shape, d.shape)[:-1]
    n = int(np.prod(shape, dtype=np.int64))
    lanes = max(1, min(DEVICE_LANES, n))
    bvh = arrays["bvh"]
    if isinstance(bvh, BVH):
        return occluded_bvh(bvh, o, d, 0.0, tfar, lanes=lanes)
    out = occluded_bvh(bvh[0][0], o, d, 0.0, tfar, lanes=lanes)
    for group, _ in bvh[1:]:  # (a ray the first group blocks ends the others' traversal at once)
        out = out | occluded_bvh(group, o, d, 0.0, jnp.where(out, -jnp.inf, tfar), lanes=lanes)
    return out


def device_accel(meshes):
    """The JAX BVH (device arrays) of `meshes` concatenated as `concat_meshes` concatenates them
    (float32 positions, triangle ids in that order), or None where the in-program traversal does
    not apply: a mesh with a traced position, a MASK or BLEND mesh, a transmissive one (those
    walk their hits on the host). Built once per content (`ACCELS`)."""
    if not meshes or not device_traceable(meshes):
        return None
    if not all(is_concrete(m.positions) and is_concrete(m.triangles) for m in meshes):
        return None
    # The same arrays again (a render loop, an optimiser's steps): no host copy, concatenation or
    # hashing of the geometry per call (~30 ms at a million triangles). A Mesh's arrays are JAX
    # arrays or read-only NumPy arrays (`_frozen`): the same object is the same content.
    arrays = [a for m in meshes for a in (m.positions, m.triangles)]
    if not all(_immutable(a) for a in arrays):
        return _device_accel(meshes)
    key = tuple(id(a) for a in arrays)
    hit = _DEVICE_ACCELS.get(key)
    if hit is not None and all(ref() is a for ref, a in zip(hit[0], arrays, strict=True)):
        return hit[1]
    bvh = _device_accel(meshes)
    _DEVICE_ACCELS.clear()  # the latest scene only: a BVH's arrays are large
    _DEVICE_ACCELS[key] = ([weakref.ref(a) for a in arrays], bvh)
    return bvh


def device_traceable(meshes) -> bool:
    """Whether the in-program traversal (`_device_cast`) answers for these meshes: all opaque (MASK
    and BLEND meshes, and transmissive ones, walk their hits on the host)."""
    return all(m.alpha_mode == "OPAQUE" and not transmits(m.material) for m in meshes)


def _immutable(a) -> bool:
    return isinstance(a, jax.Array) or (isinstance(a, np.ndarray) and not a.flags.writeable)


#: `device_accel`'s latest result, by the identity of the meshes' position and triangle arrays.
_DEVICE_ACCELS: dict = {}


def _device_accel(meshes):
    """One BVH, or where some meshes moved since the previous call (`ACCELS.get(parts=)`) the
    groups ((BVH, the whole mesh's triangle ids of its rows (n,) int32 on the device), ...)."""
    offs = np.cumsum([0] + [m.num_vertices for m in meshes])
    verts = np.ascontiguousarray(np.concatenate([np.asarray(m.positions, np.float32) for m in meshes]))
    tris = np.ascontiguousarray(np.concatenate(
        [np.asarray(m.triangles, np.int64) + offs[k] for k, m in enumerate(meshes)]).astype(np.int32))
    accel = ACCELS.get(verts, tris, "jax", parts=mesh_parts(meshes))
    if not hasattr(accel, "groups"):
        return accel.bvh
    return accel.device_groups()


# ------------------------------------------------------------------------------------------
# Mesh pixels in JAX
# ------------------------------------------------------------------------------------------


def concat_geometry(meshes, dtype):
    """(positions (V, 3), triangles (T, 3) int32) of the meshes concatenated, the triangles' indices
    offset into the joined vertices (traced-friendly: offsets come from static shapes)."""
    offs = np.cumsum([0] + [m.num_vertices for m in meshes])
    positions = jnp.concatenate([jnp.asarray(m.positions, dtype) for m in meshes])
    # Concatenated, then offset by one per-mesh broadcast: an add per mesh before the concatenation
    # made XLA:CPU compile one kernel per mesh (0.54 s for the 49 meshes of the demo grid).
    tri_offset = jnp.concatenate([jnp.full((m.num_triangles, 1), int(offs[k]), jnp.int32) for k, m in enumerate(meshes)])
    return positions, jnp.concatenate([jnp.asarray(m.triangles, jnp.int32) for m in meshes]) + tri_offset


def concat_meshes(meshes, dtype):
    """Every mesh's arrays concatenated (traced-friendly: offsets come from static shapes):
    dict with positions (V, 3), triangles (T, 3) int32, and the optional attributes filled with
    neutral values for meshes that lack them (None when no mesh has them), plus `flat` (T,) bool
    for triangles of meshes without normals and `tri_object` (T,) int32 (index into `meshes`)."""
    out = {}
    out["positions"], out["triangles"] = concat_geometry(meshes, dtype)
    fills = {"normals": (0.0, 0.0, 1.0), "texcoords": (0.0, 0.0), "texcoords1": (0.0, 0.0), "tangents": (1.0, 0.0, 0.0, 1.0), "colors": (1.0, 1.0, 1.0, 1.0)}
    for name, fill in fills.items():
        if all(getattr(m, name) is None for m in meshes):
            out[name] = None
            continue
        out[name] = jnp.concatenate([
            jnp.asarray(getattr(m, name), dtype) if getattr(m, name) is not None
            else jnp.broadcast_to(jnp.asarray(fill, dtype), (m.num_vertices, len(fill)))
            for m in meshes
        ])
    # Per-triangle tables made in the program from per-mesh values (O(meshes) constants, not O(triangles)).
    counts = np.asarray([m.num_triangles for m in meshes])
    # One broadcast per mesh: `jnp.repeat` (a cumulative sum and a scatter) took XLA:CPU ~0.9 s to
    # compile in every program holding the tables.
    per_tri = lambda vals, dt: jnp.concatenate([jnp.full((int(c),), v, dt) for v, c in zip(vals, counts, strict=True)])  # noqa: E731
    out["tri_object"] = per_tri(range(len(meshes)), jnp.int32)
    out["flat"] = per_tri([m.normals is None for m in meshes], jnp.bool_)
    out["cull_back"] = per_tri([not m.double_sided for m in meshes], jnp.bool_)
    out["alpha"] = _alpha_arrays(meshes, out, dtype) if any(m.alpha_mode != "OPAQUE" for m in meshes) else None
    out["transmit"] = _transmit_arrays(meshes, out, dtype) if any(transmits(m.material) for m in meshes) else None
    out["parts"] = mesh_parts(meshes)  # (static: Python numbers)
    return out


_WRAPS = {"repeat": 0, "clamp": 1, "mirror": 2}


def transmits(material) -> bool:
    """Whether a material has KHR_materials_transmission (static: the group's presence)."""
    f = material.factors if isinstance(material, TexturedMaterial) else material
    return "transmission" in f.extensions


def _slot_tables(slots, channels, dtype):
    """What the host needs to look a material texture up at hits, per mesh (`_host_lookup`): the
    texels of level 0 in `channels` ((H, W, len(channels)); a 1x1 of ones for a mesh without the
    texture, or whose texture lacks those channels), its texture-coordinate set, wrap modes,
    transform and whether its magnification filter is nearest. A plain (H, W, C) array is sampled
    as the colour path samples it: bilinear, repeat."""
    from .textured import TextureSlot

    tex, tset, wrap, xform, nearest = [], [], [], [], []
    for x in slots:
        img, s, w, m, nn = None, 0, (0, 0), np.eye(3), False
        if isinstance(x, TextureSlot):
            lv = x.texture.levels[0]
            img = lv[..., list(channels)] if lv.shape[-1] > max(channels) else None
            s = x.texcoord
            w = (_WRAPS[x.texture.wrap_s], _WRAPS[x.texture.wrap_t])
            m = x.transform if x.transform is not None else np.eye(3)
            nn = x.texture.mag_filter == "nearest"
        elif x is not None and np.shape(x)[-1] > max(channels):
            img = jnp.asarray(x)[..., list(channels)]
        tex.append(jnp.asarray(img, dtype) if img is not None else jnp.ones((1, 1, len(channels)), dtype))
        tset.append(s)
        wrap.append(w)
        xform.append(jnp.asarray(m, dtype))
        nearest.append(nn)
    return {"textures": tuple(tex), "texcoord": jnp.asarray(tset, jnp.int32), "wrap": jnp.asarray(wrap, jnp.int32),
            "transform": jnp.stack(xform), "nearest": jnp.asarray(nearest)}


def _vertex_tables(arrays, dtype):
    V = arrays["positions"].shape[0]
    zeros2 = jnp.zeros((V, 2), dtype)
    return {
        "uv0": arrays["texcoords"] if arrays["texcoords"] is not None else zeros2,
        "uv1": arrays["texcoords1"] if arrays["texcoords1"] is not None else zeros2,
        "color": arrays["colors"] if arrays["colors"] is not None else jnp.ones((V, 4), dtype),
        "tri_mesh": arrays["tri_object"],
    }


def _base_color_texture(m):
    return m.material.base_color_texture if isinstance(m.material, TexturedMaterial) else None


def _alpha_arrays(meshes, arrays, dtype):
    """What the host needs to evaluate alpha at a hit (MASK cut-outs, BLEND layers): per mesh the
    mode (0 opaque, 1 mask, 2 blend), cutoff, factor and the base colour texture's A (`_slot_tables`);
    per vertex the texture coordinates and COLOR_0."""
    return dict(
        mode=jnp.asarray([ALPHA_MODES.index(m.alpha_mode) for m in meshes], jnp.int32),
        cutoff=jnp.asarray([m.alpha_cutoff for m in meshes], dtype),
        factor=jnp.stack([jnp.asarray(m.alpha, dtype) for m in meshes]),
        tex=_slot_tables([_base_color_texture(m) for m in meshes], (3,), dtype),
        **_vertex_tables(arrays, dtype),
    )


def _transmit_arrays(meshes, arrays, dtype):
    """What the host needs for the transmittance of a shadow ray's crossing of a surface
    (`host_transmittance`): per mesh the transmission factor (0 without the extension) and its
    texture's R, the base colour factor and its texture's RGB (`_slot_tables`); per vertex the
    texture coordinates and COLOR_0."""
    factors, base = [], []
    for m in meshes:
        f = m.material.factors if isinstance(m.material, TexturedMaterial) else m.material
        factors.append(jnp.asarray(f.transmission if transmits(m.material) else 0.0, dtype).reshape(()))
        base.append(jnp.broadcast_to(jnp.asarray(f.base_color, dtype), (3,)))
    ttex = [m.material.transmission_texture if isinstance(m.material, TexturedMaterial) else None for m in meshes]
    return dict(
        transmission=jnp.stack(factors), base_color=jnp.stack(base),
        transmission_tex=_slot_tables(ttex, (0,), dtype),
        base_color_tex=_slot_tables([_base_color_texture(m) for m in meshes], (0, 1, 2), dtype),
        **_vertex_tables(arrays, dtype),
    )


def _wrap_host(x, n, mode):
    if mode == 1:
        return np.clip(x, 0, n - 1)
    if mode == 2:
        period = 2 * n
        y = np.mod(x, period)
        return np.where(y >= n, period - 1 - y, y)
    return np.mod(x, n)


def _host_lookup(table, tables, ms, tri, w):
    """(n, C) float64 texels of the per-mesh textures `table` (`_slot_tables`) at n hits on meshes
    ms (n,) in triangles tri (n, 3) with barycentric weights w (n, 3): level 0, the sampler's
    magnification filter (nearest: the texel floor(u W), floor(v H); linear: bilinear between the
    four nearest texel centres), wrap modes and the slot's transform, as `texture.sample` magnifies."""
    C = np.asarray(table["textures"][0]).shape[-1]
    out = np.ones((len(ms), C), np.float64)
    for k in np.unique(ms):
        rows = ms == k
        img = np.asarray(table["textures"][k], np.float64)
        if img.shape[:2] == (1, 1) and np.all(img == 1.0):
            continue
        uvs = tables["uv0"] if table["texcoord"][k] == 0 else tables["uv1"]
        uv = np.sum(w[rows][..., None] * uvs[tri[rows]], 1)
        M = table["transform"][k]
        u = M[0, 0] * uv[:, 0] + M[0, 1] * uv[:, 1] + M[0, 2]
        v = M[1, 0] * uv[:, 0] + M[1, 1] * uv[:, 1] + M[1, 2]
        H, W = img.shape[:2]
        ws, wt = table["wrap"][k]
        if table["nearest"][k]:
            xi = _wrap_host(np.floor(u * W).astype(np.int64), W, ws)
            yi = _wrap_host(np.floor(v * H).astype(np.int64), H, wt)
            out[rows] = img[yi, xi]
            continue
        x, y = u * W - 0.5, v * H - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        xi = [_wrap_host(x0.astype(np.int64) + i, W, ws) for i in (0, 1)]
        yi = [_wrap_host(y0.astype(np.int64) + i, H, wt) for i in (0, 1)]
        out[rows] = ((1 - fx) * (1 - fy) * img[yi[0], xi[0]] + fx * (1 - fy) * img[yi[0], xi[1]]
                     + (1 - fx) * fy * img[yi[1], xi[0]] + fx * fy * img[yi[1], xi[1]])
    return out


def _numpy(tables):
    return {k: (_numpy(v) if isinstance(v, dict) else v if isinstance(v, tuple) else np.asarray(v)) for k, v in tables.items()}


def host_alpha(alpha, triangles, prim, b1, b2):
    """(mode, alpha) at hits (prim >= 0, barycentrics b1, b2) on the host, NumPy: the glTF alpha
    factor x the base colour texture's A (`_host_lookup`: level 0 with the sampler's magnification
    filter, wrap modes and the slot's transform) x the interpolated COLOR_0 A."""
    a = _numpy(alpha)
    p = np.maximum(prim, 0)
    mesh = a["tri_mesh"][p]
    mode = np.where(prim >= 0, a["mode"][mesh], 0)
    out = np.ones(prim.shape, np.float64)
    sel = mode > 0
    if not sel.any():
        return mode, out
    ps, ms = p[sel], mesh[sel]
    w = np.stack([1.0 - b1[sel] - b2[sel], b1[sel], b2[sel]], -1)
    tri = triangles[ps]
    ca = np.sum(w * a["color"][tri, 3], -1)
    out[sel] = a["factor"][ms] * ca * _host_lookup(a["tex"], a, ms, tri, w)[:, 0]
    return mode, out


def host_transmittance(transmit, triangles, prim, b1, b2):
    """(n, 3) the fraction of light a shadow ray keeps crossing the surface at hits (prim >= 0,
    barycentrics b1, b2) on the host, NumPy: thin-walled transmission lets transmission x base
    colour through (transmissionFactor x its texture's R; baseColorFactor x its texture's RGB x
    COLOR_0's RGB; textures as `_host_lookup`); 0 where the material has no transmission."""
    a = _numpy(transmit)
    p = np.maximum(prim, 0)
    ms = a["tri_mesh"][p]
    w = np.stack([1.0 - b1 - b2, b1, b2], -1)
    tri = triangles[p]
    t = a["transmission"][ms] * _host_lookup(a["transmission_tex"], a, ms, tri, w)[:, 0]
    base = a["base_color"][ms] * np.sum(w[..., None] * a["color"][tri, :3], 1)
    base = base * _host_lookup(a["base_color_tex"], a, ms, tri, w)
    out = np.clip(t, 0.0, 1.0)[:, None] * np.clip(base, 0.0, 1.0)
    return np.where((prim >= 0)[:, None], out, 0.0)


def triangle_hit(v0, v1, v2, o, d):
    """Distance and barycentrics (t, b1, b2) of rays o + t d on the planes of triangles v0 v1 v2
    (Vec3s, Moller-Trumbore), differentiable in every input. The ray is known to hit the triangle
    (the ray engine said so); the determinant is floored only to keep a degenerate triangle finite."""
    e1 = tuple(v1[i] - v0[i] for i in range(3))
    e2 = tuple(v2[i] - v0[i] for i in range(3))
    p = vcross(d, e2)
    det = vdot(e1, p)
    ok = det * det > small_sq(det.dtype)
    s = tuple(o[i] - v0[i] for i in range(3))
    q = vcross(s, e1)
    b1 = safe_div(vdot(s, p), det, ok)
    b2 = safe_div(vdot(d, q), det, ok)
    t = safe_div(vdot(e2, q), det, ok)
    return t, b1, b2


def _gather3(a, idx, k):
    return tuple(a[:, i][idx[..., k]] for i in range(a.shape[1]))


def mesh_surface(arrays, prim, o, d, *, need_uv: bool, ddir=None, dorig=None):
    """Surface of mesh pixels hit by primitive `prim` (..., int32, >= 0 where used):

    returns dict t, pos, n (shading normal, facing the viewer on double-sided back faces),
    ng (geometric normal, same side), object (index into the meshes), and when need_uv: uv, uv1,
    tangent (Vec3) and tangent_w (the bitangent sign), duv: per texture-coordinate set (0, 1) the
    screen derivatives (duv/dx, duv/dy), each (..., 2), from the ray differentials `ddir` =
    (dD/dx, dD/dy) (zero without them) and `dorig` = (dO/dx, dO/dy) (None: a fixed origin);
    colour (RGBA) when the meshes have colours.
    """
    p = jnp.maximum(prim, 0)
    tri = arrays["triangles"][p]  # (..., 3)
    P = arrays["positions"]
    v = [tuple(P[:, i][tri[..., k]] for i in range(3)) for k in range(3)]
    t, b1, b2 = triangle_hit(v[0], v[1], v[2], o, d)
    b0 = 1.0 - b1 - b2
    w = (b0, b1, b2)
    pos = tuple(o[i] + t * d[i] for i in range(3))
    e1 = tuple(v[1][i] - v[0][i] for i in range(3))
    e2 = tuple(v[2][i] - v[0][i] for i in range(3))
    ng = vnormalize(vcross(e1, e2))
    back = vdot(ng, d) > 0  # only double-sided meshes show back faces: glTF reverses the normals
    sign = jnp.where(back, -1.0, 1.0)
    ng = tuple(sign * c for c in ng)
    if arrays["normals"] is not None:
        N = arrays["normals"]
        ns = tuple(sum(w[k] * N[:, i][tri[..., k]] for k in range(3)) for i in range(3))
        ns = vnormalize(tuple(sign * c for c in ns))
        flat = arrays["flat"][p]
        n = tuple(jnp.where(flat, ng[i], ns[i]) for i in range(3))
    else:
        n = ng
    out = dict(t=t, pos=pos, n=n, ng=ng, object=arrays["tri_object"][p])
    if arrays["colors"] is not None:
        C = arrays["colors"]
        out["color"] = jnp.stack([sum(w[k] * C[:, i][tri[..., k]] for k in range(3)) for i in range(4)], -1)
    if not need_uv:
        return out
    uvs = []
    for name in ("texcoords", "texcoords1"):
        if arrays[name] is None:
            uvs.append(None)
            continue
        T = arrays[name]
        uvs.append(tuple(sum(w[k] * T[:, i][tri[..., k]] for k in range(3)) for i in range(2)))
    zero = jnp.zeros_like(t)
    out["uv"] = uvs[0] if uvs[0] is not None else (zero, zero)
    out["uv1"] = uvs[1] if uvs[1] is not None else out["uv"]
    duv = []
    for name in ("texcoords", "texcoords1"):
        if ddir is None or arrays[name] is None:
            duv.append((jnp.zeros(t.shape + (2,), t.dtype),) * 2)
            continue
        from .texture import uv_derivatives_on_triangle

        Tc = arrays[name]
        corners = [jnp.stack([Tc[:, i][tri[..., k]] for i in range(2)], -1) for k in range(3)]
        _, dx, dy = uv_derivatives_on_triangle(
            *(jnp.stack(v[k], -1) for k in range(3)), *corners, jnp.stack(o, -1), jnp.stack(d, -1),
            jnp.stack(ddir[0], -1), jnp.stack(ddir[1], -1),
            **({} if dorig is None else {"dorigin_dx": jnp.stack(dorig[0], -1), "dorigin_dy": jnp.stack(dorig[1], -1)}),
        )
        duv.append((dx, dy))
    if arrays["texcoords1"] is None:
        duv[1] = duv[0]
    out["duv"] = tuple(duv)
    if arrays["tangents"] is not None:
        Tg = arrays["tangents"]
        tan = tuple(sum(w[k] * Tg[:, i][tri[..., k]] for k in range(3)) for i in range(3))
        tw = jnp.where(Tg[:, 3][tri[..., 0]] < 0, -1.0, 1.0)
    else:
        tan, tw = _uv_tangent(v, arrays, tri, n)
    # Double-sided back faces: the normal was reversed; the tangent frame keeps T and flips B by
    # flipping the sign (B = w N x T with N reversed already reverses B: keep w).
    out["tangent"] = tan
    out["tangent_w"] = tw
    return out


def _uv_tangent(v, arrays, tri, n):
    """Per-triangle tangent dP/du (and the bitangent sign) from TEXCOORD_0, for meshes without
    TANGENT (anisotropy directions; normal maps get MikkTSpace tangents from the loader)."""
    if arrays["texcoords"] is None:
        from .._numerics import orthonormal_frame

        t, _ = orthonormal_frame(n)
        return t, jnp.ones_like(n[0])
    T = arrays["texcoords"]
    uv = [tuple(T[:, i][tri[..., k]] for i in range(2)) for k in range(3)]
    du1, dv1 = uv[1][0] - uv[0][0], uv[1][1] - uv[0][1]
    du2, dv2 = uv[2][0] - uv[0][0], uv[2][1] - uv[0][1]
    e1 = tuple(v[1][i] - v[0][i] for i in range(3))
    e2 = tuple(v[2][i] - v[0][i] for i in range(3))
    det = du1 * dv2 - du2 * dv1
    ok = det * det > small_sq(det.dtype)
    tan = tuple(safe_div(dv2 * e1[i] - dv1 * e2[i], det, ok) for i in range(3))
    bit = tuple(safe_div(du1 * e2[i] - du2 * e1[i], det, ok) for i in range(3))
    # glTF's v runs down the image and a normal map's +Y points up it: the bitangent
    # B = w (N x T) points along -dP/dv, so w = +1 where N x T already does.
    nt = vcross(n, tan)
    w = jnp.where(vdot(nt, bit) < 0, 1.0, -1.0)
    from .._numerics import orthonormal_frame

    fallback, _ = orthonormal_frame(n)
    tan = tuple(jnp.where(ok, tan[i], fallback[i]) for i in range(3))
    return tan, jnp.where(ok, w, 1.0)
