"""`read_gltf`: a glTF 2.0 file (.gltf or .glb) -> `GltfAsset` flattened to world space."""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import os
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ... import _memory
from ...errors import InputError
from ._binary import (
    Buffers,
    JsonDocument,
    UriRefused,
    asset_roots,
    fail,
    get,
    loc,
    open_regular,
    pointer,
    primitive_attributes,
)
from ...geometry.pose import deform, skin_matrices
from ._animation import AnimationReader, choose_animation, node_weights, nodes_at
from ._budget import check_asset_memory
from ._draco import DracoGeometry, decode_primitive, draco_extension
from ._geometry import (
    MODE_NAMES,
    face_normals,
    node_matrix,
    normalize_rows,
    triangle_list,
    weld,
)
from ._images import make_images
from ._materials import MATERIAL_EXTENSIONS, MaterialReader
from ._schema import check_schema
from ._types import GltfAsset, GltfCamera, GltfDeform, GltfLight, GltfMaterial, GltfPrimitive

__all__ = ["SUPPORTED_EXTENSIONS", "read_gltf"]

#: The extensions `read_gltf` implements; others in extensionsRequired are refused, others in
#: extensionsUsed are ignored with a warning.
SUPPORTED_EXTENSIONS = (
    *MATERIAL_EXTENSIONS,
    "KHR_materials_unlit",
    "KHR_texture_transform",
    "KHR_lights_punctual",
    "KHR_mesh_quantization",
    "KHR_draco_mesh_compression",
    "EXT_mesh_gpu_instancing",
    "EXT_texture_webp",
)

#: How far outside [0, 1] a float COLOR_0 component may be and be clamped (exporters' rounding).
_COLOR_SLACK = 1e-3
_FLOATISH = (5120, 5121, 5122, 5123, 5126)  # FLOAT, or integers read as (normalized) numbers
_FIX = "repair or re-export the asset (the Khronos glTF-Validator names the problem)"


@dataclass
class _Shape:
    """A mesh primitive in object space, ready to be instanced (shared by the nodes using the mesh)."""

    positions: np.ndarray  # (V, 3) float64
    normals: np.ndarray  # (V, 3) float64
    tris: np.ndarray  # (T, 3) int64
    tangents: np.ndarray | None
    texcoords: dict
    color: np.ndarray | None
    flat_normals: bool
    generated_tangents: bool
    targets: dict  # morph-target deltas {'POSITION'|'NORMAL'|'TANGENT': (K, V, 3) float64}
    joints: np.ndarray | None = None  # (V, 4n) int64 (JOINTS_0..n-1)
    weights: np.ndarray | None = None  # (V, 4n) float64 (WEIGHTS_0..n-1), rows summing to 1


def _json_error(e: ValueError) -> str:
    """Where a JSON syntax error is: 'line L, column C' (no JSON location exists yet)."""
    return f"line {e.lineno}, column {e.colno}" if isinstance(e, json.JSONDecodeError) else "its text"


#: Peak bytes of the parsed JSON per byte of its text (Python's dicts, lists, floats and strings):
#: measured 7-9x on scenes of 10^5-10^6 nodes; rounded up.
_JSON_FACTOR = 12.0


def _require_json(path: Path, nbytes: int, what: str) -> None:
    """The memory guard, before the JSON is read: its text and its parsed objects."""
    _memory.require(f"reading the JSON ({nbytes} bytes)", {"json": float(nbytes) * (1.0 + _JSON_FACTOR)},
                    where=f"glTF file {str(path)!r}", names={"json": f"the size of {what}"})


def _loads(text: str):
    """json.loads, a nesting too deep for Python's reader a ValueError like any other syntax error
    (the reader recurses: a few hundred kilobytes of '[' exhaust the stack)."""
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError("arrays or objects nested too deep") from None


def _read_document(path: Path):
    """(the document's top-level view (`JsonDocument`), the JSON as Python objects, (offset, length)
    of the GLB's BIN chunk or None), or InputError. Of a .glb only the header and the JSON chunk are
    read; the BIN chunk is read when a buffer needs it (after the memory check)."""
    try:
        f = os.fdopen(open_regular(path), "rb")  # a regular file only: a FIFO or a device never ends
    except FileNotFoundError:
        raise InputError(f"glTF file {str(path)!r} not found. Fix: check the path") from None
    except UriRefused as e:
        raise InputError(f"glTF file {str(path)!r} {e}. Fix: give the path of a .gltf or .glb file") from None
    except OSError as e:
        raise InputError(f"glTF file {str(path)!r} cannot be read: {e.strerror or e}. Fix: check the path and permissions") from None
    with f:
        try:
            size = os.fstat(f.fileno()).st_size
            head = f.read(12)
            if head[:4] == b"glTF":
                return _read_glb(path, f, head, size)
            _require_json(path, size, "the .gltf file")
            data = head + f.read(size - len(head))
        except OSError as e:
            raise InputError(f"glTF file {str(path)!r} cannot be read: {e}. Fix: check the path and permissions") from None
    try:
        text = data.decode("utf-8-sig")
        doc = _loads(text)
    except (ValueError, UnicodeDecodeError) as e:
        fail(path, f"JSON {_json_error(e)}", f"is neither GLB nor valid JSON ({e})",
             "check that the file is a glTF 2.0 asset (.gltf JSON or .glb binary) and not truncated")
    if not isinstance(doc, dict):
        fail(path, "JSON root (pointer '')", "the JSON is not an object", _FIX)
    _check_version(path, doc)
    check_schema(path, doc)
    return JsonDocument(doc), doc, None


def _check_version(path: Path, doc: dict) -> None:
    """Refuse anything but glTF 2.x before the document is read: a glTF 1.x file keeps its
    objects in dictionaries keyed by id."""
    asset = doc.get("asset")
    version = str(get(asset, "version", "")) if isinstance(asset, dict) else ""
    if not version.startswith("2."):
        fail(path, loc("asset.version", "/asset/version" if isinstance(asset, dict) else "/asset"),
             f"is {version or 'missing'!r}; only glTF 2.x is read",
             "convert the asset to glTF 2.0 (glTF 1.0 files can be upgraded with gltf-pipeline or Blender)")


def _read_glb(path: Path, f, head: bytes, size: int):
    if len(head) < 12 or size < 20:
        fail(path, "GLB header (bytes 0-11)", f"the file has only {size} bytes", "the file is truncated: re-export it")
    version, length = struct.unpack_from("<II", head, 4)
    if version != 2:
        fail(path, "GLB header (bytes 0-11)", f"container version {version}, only version 2 (glTF 2.0) is read",
             "convert the asset to glTF 2.0 (e.g. with the Khronos glTF converters or Blender)")
    if length > size:
        fail(path, "GLB header (bytes 0-11)", f"declares {length} bytes but the file has {size}",
             "the file is truncated: download or export it again")
    offset, chunks = 12, []
    while offset + 8 <= length:
        f.seek(offset)
        clen, ctype = struct.unpack("<II", f.read(8))
        if offset + 8 + clen > length:
            fail(path, f"GLB chunk {len(chunks)} (bytes {offset}-{offset + 7})",
                 f"runs past the end of the file ({offset + 8 + clen} > {length})",
                 "the file is truncated: download or export it again")
        chunks.append((ctype, offset + 8, clen))
        offset += 8 + clen
    if not chunks or chunks[0][0] != 0x4E4F534A:  # 'JSON'
        fail(path, "GLB chunk 0 (bytes 12-19)", "the first chunk is not the JSON chunk", _FIX)
    _require_json(path, chunks[0][2], "the GLB's JSON chunk")
    f.seek(chunks[0][1])
    raw = f.read(chunks[0][2])
    try:
        text = raw.decode("utf-8")
        doc = _loads(text)
    except (ValueError, UnicodeDecodeError) as e:
        fail(path, f"GLB JSON chunk, {_json_error(e)}", f"is not valid JSON ({e})", _FIX)
    if not isinstance(doc, dict):
        fail(path, "GLB JSON chunk, root (pointer '')", "the JSON is not an object", _FIX)
    _check_version(path, doc)
    check_schema(path, doc)
    blob = next(((o, n) for t, o, n in chunks[1:] if t == 0x004E4942), None)  # 'BIN\0'
    return JsonDocument(doc), doc, blob


class _Visit:
    """A node reached by the scene traversal: its index, JSON object and world matrix; its
    readable name and pointer are made when a message needs them."""

    __slots__ = ("index", "node", "world")

    def __init__(self, index: int, node, world: np.ndarray):
        self.index, self.node, self.world = index, node, world

    @property
    def at(self) -> str:
        return pointer("nodes", self.index)

    @property
    def where(self) -> str:
        name = get(self.node, "name")
        return f"node {self.index}" + (f" ({name!r:.60})" if isinstance(name, str) and name else "")


class _Loader:
    def __init__(self, path: Path, scene: int | None, lazy_images: bool, roots=(), ray_engine=None, time=None,
                 animation=None):
        self.path = path
        self.time = time
        self.animation_arg = animation
        self.ray_engine = ray_engine
        self.roots = asset_roots(path, roots)
        self.scene_arg = scene
        self.lazy_images = lazy_images
        self.notes: list[str] = []
        self.ignored_features: dict[str, set] = {}
        #: The JSON pointer (or the `_Visit`) of what is being read (named by errors the checks did
        #: not foresee).
        self.context = ""

    # ------------------------------------------------------------------------------------------
    def run(self) -> GltfAsset:
        gltf, doc, glb_bin = _read_document(self.path)
        self.gltf = gltf
        self.doc = doc
        asset = doc["asset"]  # (a 2.x version: `_check_version`)
        version = str(get(asset, "version", ""))
        self._check_extensions()
        self.buffers = Buffers(gltf, self.path, glb_bin, self.roots)
        self.materials_reader = MaterialReader(gltf, self.path, self.notes)
        materials = []
        for i in range(len(gltf.materials or [])):
            self.context = pointer("materials", i)
            materials.append(self.materials_reader.material(i))
        self.materials = materials
        self.default_material: int | None = None
        self.primitives: list[GltfPrimitive] = []
        self.lights: list[GltfLight] = []
        self.cameras: list[GltfCamera] = []
        scene_index, roots, roots_at = self._scene()
        visits = self._walk(roots, roots_at)
        # One memory check of everything the load will decode, before any buffer is read.
        self.context = ""
        check_asset_memory(self, visits, self.ray_engine)
        self._pose(visits)
        self._place_meshes(visits)
        for v in visits:
            self._visit(v)
        self.context = "/images"
        images = make_images(gltf, self.buffers, self.path)
        if not self.lazy_images:
            for i in self.used_images():
                self.context = pointer("images", i)
                images[i].pixels  # noqa: B018 - decode now, so that a bad image fails the load
        self.context = ""
        if self.primitives:
            lo = np.min([p.positions.min(axis=0) for p in self.primitives if p.num_vertices], axis=0)
            hi = np.max([p.positions.max(axis=0) for p in self.primitives if p.num_vertices], axis=0)
            bounds = np.stack([lo, hi]).astype(np.float64)
        else:
            bounds = None
        for feature, items in self.ignored_features.items():
            self.notes.append(f"ignored (not supported): {feature}: {', '.join(sorted(items))}")
        return GltfAsset(
            path=self.path,
            generator=str(get(asset, "generator", "")),
            version=version,
            scene=scene_index,
            primitives=self.primitives,
            materials=self.materials,
            images=images,
            lights=self.lights,
            cameras=self.cameras,
            bounds=bounds,
            extensions_used=tuple(self.gltf.extensionsUsed or ()),
            warnings=tuple(self.notes),
            animations=self.animations,
            skins=dict(self.anim._skins),
            nodes=self.nodes,
            time=None if self.playing is None else float(self.time_at),
            animation=None if self.playing is None else self.playing.index,
        )

    def used_images(self) -> list[int]:
        """The images the materials' texture slots sample (decoded by the load unless lazy)."""
        return sorted({t.image for m in self.materials for t in m.textures.values()})

    def _ignore(self, feature: str, item: str):
        self.ignored_features.setdefault(feature, set()).add(item)

    def _check_extensions(self):
        required = list(self.gltf.extensionsRequired or [])
        used = list(self.gltf.extensionsUsed or [])
        missing = [(k, e) for k, e in enumerate(required) if e not in SUPPORTED_EXTENSIONS]
        if missing:
            named = ", ".join(f"{e} ({pointer('extensionsRequired', k)})" for k, e in missing)
            fail(self.path, loc("extensionsRequired", "/extensionsRequired"),
                 f"needs {named}, "
                 f"which jaxpbr does not implement (supported: {', '.join(SUPPORTED_EXTENSIONS)})",
                 "re-export without those extensions (e.g. with gltf-transform: meshopt-compressed geometry as "
                 "plain or Draco, KTX2 textures as PNG, JPEG or WebP), or make them optional")
        ignored = [e for e in used if e not in SUPPORTED_EXTENSIONS]
        if ignored:
            self.notes.append(f"extensionsUsed not implemented, ignored: {', '.join(ignored)} "
                              f"(supported: {', '.join(SUPPORTED_EXTENSIONS)})")

    # -- scene graph -------------------------------------------------------------------------------
    def _scene(self):
        """(scene index or None, root node indices, the pointer of the list naming them)."""
        scenes = self.gltf.scenes or []
        nodes = self.gltf.nodes or []
        index = self.scene_arg
        where = f"scene={index!r} (the argument; the file's scenes are /scenes)"
        if index is None:
            index = self.gltf.scene
            where = loc("scene", "/scene")
        if index is None and scenes:
            index = 0
        if index is None:  # no scenes: every root node
            children = {c for n in nodes for c in (get(n, "children", []) or []) if isinstance(c, int)}
            return None, [i for i in range(len(nodes)) if i not in children], "/nodes"
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(scenes):
            fail(self.path, where, f"scene {index!r} does not exist (the file has {len(scenes)})",
                 f"pick a scene index in [0, {len(scenes)})" if scenes else _FIX)
        return index, list(get(scenes[index], "nodes", []) or []), pointer("scenes", index, "nodes")

    def _walk(self, roots, roots_at: str) -> list[_Visit]:
        """The nodes of the scene in traversal order (depth first, children in their listed order)
        with their world matrices; structural errors (missing nodes, a node with two parents, a
        cycle, a scene listing a child node, bad transforms) are raised here, before any buffer is
        read. Linear in the nodes: each node is visited once (the spec's hierarchy is a set of
        disjoint trees, each node one parent at most), with no per-node copy of its ancestry."""
        nodes = self.gltf.nodes or []
        parent = self._parents(nodes)
        self.parent = parent
        no_scene = roots_at == "/nodes"
        # (the schema check has made the roots existing, distinct node indices)
        for k, r in enumerate(roots):
            if parent[r] >= 0:
                ref = roots_at if no_scene else f"{roots_at}/{k}"
                fail(self.path, loc("scene graph", ref), f"lists node {r}, which is a child of node {parent[r]} "
                     f"({pointer('nodes', parent[r], 'children')}); a scene lists root nodes only", _FIX)
        out: list[_Visit] = []
        eye = np.eye(4)
        eye.flags.writeable = False
        stack = [(r, eye) for r in reversed(list(roots))]
        while stack:
            i, world_parent = stack.pop()  # (each node once: one parent each, the roots parentless)
            node = nodes[i]
            matrix, t, r, sc = (get(node, k) for k in ("matrix", "translation", "rotation", "scale"))
            if matrix is None and t is None and r is None and sc is None:
                world = world_parent  # (shared: world matrices are never written to)
            else:
                v = _Visit(i, node, world_parent)
                self.context = v
                try:
                    local = node_matrix(matrix, t, r, sc)
                except (ValueError, TypeError) as e:
                    fail(self.path, loc(v.where, v.at + "/matrix" if matrix is not None else v.at), f"invalid transform ({e})", _FIX)
                world = world_parent @ local
                if not np.isfinite(world).all():
                    t_at = v.at + "/matrix" if matrix is not None else v.at
                    what = "transform has non-finite values" if not np.isfinite(local).all() else \
                        "world transform overflows (the product of its ancestors' transforms is not finite)"
                    fail(self.path, loc(v.where, t_at), what, _FIX)
            out.append(_Visit(i, node, world))
            children = get(node, "children")
            if children:
                stack.extend((c, world) for c in reversed(children))
        return out

    def _parents(self, nodes) -> list[int]:
        """parent[i]: the node listing node i among its children, or -1. A node that is its own
        child and a node listed by two parents are refused: the spec's node hierarchy is a set of
        disjoint strict trees. (The schema check has made each children list an array of distinct
        node indices.)"""
        parent = [-1] * len(nodes)
        for i, node in enumerate(nodes):
            for k, c in enumerate(get(node, "children", []) or []):
                ref = pointer("nodes", i, "children", k)
                if c == i:
                    fail(self.path, loc(f"node {i}", ref), "is its own child (a cycle in the node hierarchy)", _FIX)
                if parent[c] >= 0:
                    fail(self.path, loc(f"node {c}", ref), f"is listed as a child also by node {parent[c]} "
                         f"({pointer('nodes', parent[c], 'children')}); a node has one parent at most "
                         "(the node hierarchy must be a set of disjoint trees)", _FIX)
                parent[c] = i
        # A cycle with one parent per node has no root: it is never reached from a scene, and a
        # file without scenes would lose it silently.
        root_of = self._cycle_check(parent)
        if root_of is not None:
            fail(self.path, loc(f"node {root_of}", pointer("nodes", root_of, "children")),
                 "is its own ancestor (a cycle in the node hierarchy)", _FIX)
        return parent

    @staticmethod
    def _cycle_check(parent) -> int | None:
        """A node on a cycle of the parent links, or None (iterative, linear: each node is
        resolved once)."""
        state = bytearray(len(parent))  # 0 unknown, 1 on the current path, 2 resolved (reaches a root)
        for s in range(len(parent)):
            path = []
            i = s
            while i >= 0 and state[i] == 0:
                state[i] = 1
                path.append(i)
                i = parent[i]
            if i >= 0 and state[i] == 1:
                return i
            for j in path:
                state[j] = 2
        return None

    def _visit(self, v: _Visit):
        self.context = v
        node = v.node
        if get(node, "camera") is not None:
            self._camera(v)
        light = (get(node, "extensions", {}) or {}).get("KHR_lights_punctual")
        if light is not None and get(light, "light") is not None:
            self._light(v, get(light, "light"))
        if get(node, "skin") is not None and get(node, "mesh") is None:
            self.notes.append(f"{loc(v.where, v.at + '/skin')}: a skin without a mesh is ignored")

    # -- animation and skins -------------------------------------------------------------------
    def node_has_matrix(self, node: int) -> bool:
        return get((self.gltf.nodes or [])[node], "matrix") is not None

    def _target_count(self, node: int) -> int:
        """The morph targets of a node's mesh (every primitive of a mesh has the same number)."""
        m = get((self.gltf.nodes or [])[node], "mesh")
        if not isinstance(m, int) or not 0 <= m < len(self.gltf.meshes or []):
            return 0
        prims = get(self.gltf.meshes[m], "primitives", []) or []
        return max((len(get(p, "targets", []) or []) for p in prims), default=0)

    def _pose(self, visits: list[_Visit]) -> None:
        """Read the nodes, skins and animations; with a time (or an animation) asked for, move the
        visited nodes' world matrices to the pose at that time. Sets self.worlds (every node's world
        matrix at the pose, for the skins' joints), self.morph_weights ({node: weights} animated)
        and self.moving (the nodes whose world matrix the animations change)."""
        self.context = ""
        self.anim = AnimationReader(self)
        self.playing = None
        self.time_at = None
        self.morph_weights: dict = {}
        n_nodes = len(self.gltf.nodes or [])
        if not self.gltf.animations and not self.gltf.skins:
            # nothing moves the nodes (a static asset; morph weights come from the JSON): no pass
            # over every node (an asset of a million nodes loads as before)
            self.nodes, self.animations, self.worlds = None, (), None
            self.moving = np.zeros(n_nodes, bool)
            if self.time is not None or self.animation_arg is not None:
                choose_animation(self.path, (), self.animation_arg)
            return
        self.nodes = self.anim.nodes(self.parent)
        self.animations = self.anim.animations(self._target_count)
        if self.time is not None or self.animation_arg is not None:
            t = 0.0 if self.time is None else self.time
            if isinstance(t, bool) or not isinstance(t, (int, float, np.integer, np.floating)) or not math.isfinite(float(t)):
                fail(self.path, f"time={t!r:.40}", "is not a finite number of seconds", "pass the time in seconds, e.g. time=1.5")
            self.playing = choose_animation(self.path, self.animations, self.animation_arg)
            self.time_at = float(t)
        worlds, _, weights = nodes_at(self.nodes, self.playing, self.time_at or 0.0)
        if not np.isfinite(worlds).all():
            bad = int(np.argmax(~np.isfinite(worlds).reshape(len(worlds), -1).all(axis=1)))
            fail(self.path, loc(f"node {bad}", pointer("nodes", bad)), "its world transform at the time asked for "
                 "is not finite (the product of its ancestors' animated transforms overflows)", _FIX)
        self.worlds = worlds
        self.morph_weights = {k: np.asarray(w, np.float64) for k, w in weights.items()}
        if self.playing is not None:
            for v in visits:
                v.world = worlds[v.index]
        # the nodes some animation moves: their animated ancestors' descendants included
        animated = {c.node for a in self.animations for c in a.channels if c.path != "weights"}
        moving = np.zeros(n_nodes, bool)
        for lvl in self.nodes.levels:
            for i in lvl:
                moving[i] = i in animated or (self.parent[i] >= 0 and moving[self.parent[i]])
        self.moving = moving

    # -- meshes ------------------------------------------------------------------------------------
    def mesh_of(self, v: _Visit):
        """(mesh index, mesh) of a node, or InputError naming /nodes/i/mesh."""
        meshes = self.gltf.meshes or []
        m = get(v.node, "mesh")
        if not isinstance(m, int) or isinstance(m, bool) or not 0 <= m < len(meshes):
            fail(self.path, loc(v.where, v.at + "/mesh"), f"mesh {m!r:.40} does not exist (the file has {len(meshes)})", _FIX)
        return m, meshes[m]

    def _place_meshes(self, visits: list[_Visit]) -> None:
        """Every (node, instance, mesh primitive) of the scene as a `GltfPrimitive` in traversal
        order, appended to self.primitives. All instances of a mesh primitive that are not
        deformed (the nodes using the mesh and their EXT_mesh_gpu_instancing instances) are
        transformed by one batched NumPy product, and each `GltfPrimitive` holds views of the
        results and shares the primitive's triangles and texture coordinates: an instance costs its
        float32 world-space positions, normals and tangents and one small object. A node whose
        mesh is skinned or has non-zero morph weights is posed on its own (`_posed`); primitives
        that animations, skins or morph targets can move carry their object-space data
        (`GltfPrimitive.deform`, shared arrays)."""
        uses: dict[int, list] = {}  # mesh -> the (n, 4, 4) world matrices of its static instances, in order
        entries = []  # traversal order: (visit, mesh, first row, count, instanced?, instance matrices, deformation)
        filled: dict[int, int] = {}  # mesh -> static instances so far
        for v in visits:
            if get(v.node, "mesh") is None:
                continue
            self.context = v
            m, mesh = self.mesh_of(v)
            inst = (get(v.node, "extensions", {}) or {}).get("EXT_mesh_gpu_instancing")
            local = np.eye(4)[None] if inst is None else self._instance_matrices(inst, v)
            sk = get(v.node, "skin")
            ntargets = self._target_count(v.index)
            w = node_weights(self.gltf, v.index, m, ntargets, self.morph_weights) if ntargets else None
            deformed = sk is not None or (w is not None and np.any(w != 0))
            if deformed:
                entries.append((v, m, -1, local.shape[0], inst is not None, local, (sk, w)))
                continue
            worlds = v.world @ local
            rows = uses.setdefault(m, [])
            entries.append((v, m, filled.get(m, 0), worlds.shape[0], inst is not None, local, (sk, w)))
            filled[m] = filled.get(m, 0) + worlds.shape[0]
            rows.append(worlds)
        shapes: dict[tuple[int, int], tuple] = {}  # (mesh, primitive) -> (material, shape, windings)
        for v, m, *_ in entries:
            mesh = self.gltf.meshes[m]
            for p, prim in enumerate(get(mesh, "primitives", []) or []):
                if (m, p) in shapes:
                    continue
                self.context = pointer("meshes", m, "primitives", p)
                material_index = self._material_index(prim, m, p)
                shape = self._shape(m, mesh, p, prim, self.materials[material_index])
                if shape is not None:
                    ccw = np.ascontiguousarray(shape.tris, np.int32)
                    cw = np.ascontiguousarray(ccw[:, [0, 2, 1]])
                    ccw.flags.writeable = cw.flags.writeable = False
                    shapes[m, p] = (material_index, shape, (ccw, cw))
                else:
                    shapes[m, p] = None
        placed: dict[tuple[int, int], tuple] = {}  # (mesh, primitive) -> its static instances, batched
        for m, rows in uses.items():
            worlds = np.concatenate(rows) if len(rows) > 1 else rows[0]
            for p in range(len(get(self.gltf.meshes[m], "primitives", []) or [])):
                if shapes.get((m, p)) is not None:
                    placed[m, p] = self._transform(shapes[m, p][1], worlds)
        self.context = ""
        for v, m, first, count, instanced, local, (sk, w) in entries:
            mesh = self.gltf.meshes[m]
            name = get(mesh, "name")
            mesh_name = name if isinstance(name, str) and name else f"mesh{m}"
            prims = [(p, shapes[m, p]) for p in range(len(get(mesh, "primitives", []) or [])) if shapes.get((m, p)) is not None]
            posable = sk is not None or w is not None or bool(self.moving[v.index])
            rest_w = None if w is None else node_weights(self.gltf, v.index, m, w.shape[0], {})
            for p, (material_index, shape, windings) in prims:
                if first < 0:
                    self.context = v
                    pos, nrm, tan, mirrored, worlds = self._posed(v, m, p, shape, local, sk, w)
                    rows = range(count)
                else:
                    pos, nrm, tan, mirrored, worlds = placed[m, p]
                    rows = range(first, first + count)
                for k, row in enumerate(rows):
                    deform = None
                    if posable:
                        deform = GltfDeform(positions=shape.positions, normals=shape.normals, tangents=shape.tangents,
                                            targets=shape.targets, skin=sk, joints=shape.joints if sk is not None else None,
                                            weights=shape.weights if sk is not None else None, instance=local[k],
                                            tris=shape.tris, morph_weights=rest_w)
                    self.primitives.append(GltfPrimitive(
                        positions=pos[row], normals=nrm[row], indices=windings[int(mirrored[row])],
                        material=material_index, node=v.index, mesh=m, primitive=p,
                        name=f"{mesh_name}/{p}" + (f"#{k}" if instanced else ""),
                        instance=k if instanced else None, world_matrix=worlds[row],
                        tangents=None if tan is None else tan[row],
                        texcoord_0=shape.texcoords.get(0), texcoord_1=shape.texcoords.get(1), color_0=shape.color,
                        flat_normals=shape.flat_normals, generated_tangents=shape.generated_tangents, deform=deform,
                    ))

    def _posed(self, v: _Visit, m: int, p: int, shape: _Shape, local: np.ndarray, sk, w):
        """`_transform`'s outputs for a node whose mesh primitive is morphed (weights w) and/or
        skinned (skin index sk) at the loaded pose: morph targets first, then the skin (whose
        joints place the mesh: the node's own transform is not applied), then the instances."""
        if sk is not None:
            skin_ = self.anim.skin(sk)
            where = f"{v.where} skin {sk}"
            if shape.joints is None:
                fail(self.path, loc(where, v.at + "/skin"), f"is skinned but mesh {m} primitive {p} has no JOINTS_0 "
                     "and WEIGHTS_0 attributes", _FIX)
            used = np.where(shape.weights > 0, shape.joints, 0)
            if used.size and used.max() >= skin_.joints.size:
                first = int(np.argmax((used >= skin_.joints.size).any(axis=1)))
                fail(self.path, loc(where, pointer("meshes", m, "primitives", p, "attributes")),
                     f"a vertex names a joint past the skin's {skin_.joints.size} joints (the first such "
                     f"vertex: {first})", _FIX)
            mats = skin_matrices(self.worlds, skin_.joints, skin_.inverse_bind)
            worlds = local
        else:
            mats = used = None
            worlds = v.world @ local
        pos, nrm, tan = deform(shape.positions, shape.normals, shape.tangents, tris=shape.tris, flat_normals=shape.flat_normals,
                               targets=shape.targets, weights=w, joint_mats=mats, joints=used, joint_weights=shape.weights)
        return self._transform(dataclasses.replace(shape, positions=pos, normals=nrm, tangents=tan), worlds)

    @staticmethod
    def _transform(shape: "_Shape", worlds: np.ndarray):
        """(positions (N, V, 3), normals (N, V, 3), tangents (N, V, 4) or None, mirrored (N,),
        worlds (N, 4, 4)): the shape placed by each world matrix, float32, computed in float64 in
        chunks of instances (the temporaries stay near 2^20 vertices)."""
        n, nv = worlds.shape[0], shape.positions.shape[0]
        pos = np.empty((n, nv, 3), np.float32)
        nrm = np.empty((n, nv, 3), np.float32)
        tan = None if shape.tangents is None else np.empty((n, nv, 4), np.float32)
        a_all = worlds[:, :3, :3]
        det = np.linalg.det(a_all)
        regular = np.abs(det) > 1e-300
        normal_all = np.empty_like(a_all)
        if regular.any():
            normal_all[regular] = np.linalg.inv(a_all[regular]).transpose(0, 2, 1)
        for j in np.flatnonzero(~regular):
            normal_all[j] = np.linalg.pinv(a_all[j]).T
        step = max(1, (1 << 20) // max(nv, 1))
        for s in range(0, n, step):
            a, w = a_all[s : s + step], worlds[s : s + step]
            pos[s : s + step] = np.einsum("vj,nij->nvi", shape.positions, a) + w[:, None, :3, 3]
            nrm[s : s + step] = normalize_rows(np.einsum("vj,nij->nvi", shape.normals, normal_all[s : s + step]))
            if tan is not None:
                xyz = normalize_rows(np.einsum("vj,nij->nvi", shape.tangents[:, :3], a))
                sign = np.where(det[s : s + step] >= 0, 1.0, -1.0)[:, None, None]
                tan[s : s + step, :, :3] = xyz
                tan[s : s + step, :, 3:] = shape.tangents[None, :, 3:4] * sign
        for arr in (pos, nrm, tan, worlds):
            if arr is not None:
                arr.flags.writeable = False
        return pos, nrm, tan, det < 0, worlds

    def _instance_matrices(self, inst, v: _Visit) -> np.ndarray:
        """(N, 4, 4) EXT_mesh_gpu_instancing transforms T @ R @ S, one per instance."""
        attrs = get(inst, "attributes", {}) or {}
        where = f"{v.where} EXT_mesh_gpu_instancing"
        at = v.at + "/extensions/EXT_mesh_gpu_instancing/attributes"
        cols = {}
        for name, atype, comps in (("TRANSLATION", "VEC3", (5126,)), ("ROTATION", "VEC4", (5126, 5120, 5122)),
                                   ("SCALE", "VEC3", (5126,))):
            if attrs.get(name) is not None:
                cols[name] = np.asarray(self.buffers.accessor(attrs[name], f"{where} {name}", f"{at}/{name}",
                                                              allowed_types=(atype,), allowed_components=comps,
                                                              finite=True), np.float64)
        counts = {c.shape[0] for c in cols.values()}
        if len(counts) != 1:
            fail(self.path, loc(where, at), "needs TRANSLATION, ROTATION or SCALE accessors, all of the same count", _FIX)
        n = counts.pop()
        out = np.tile(np.eye(4), (n, 1, 1))
        if "ROTATION" in cols:
            x, y, z, w = normalize_rows(cols["ROTATION"]).T
            out[:, :3, :3] = np.stack([
                np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], axis=1)
        if "SCALE" in cols:
            out[:, :3, :3] *= cols["SCALE"][:, None, :]
        if "TRANSLATION" in cols:
            out[:, :3, 3] = cols["TRANSLATION"]
        return out

    def _material_index(self, prim, m, p) -> int:
        i = get(prim, "material")
        if i is None:
            if self.default_material is None:
                self.materials.append(self.materials_reader.material(None))
                self.default_material = len(self.materials) - 1
            return self.default_material
        if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < len(self.gltf.materials or []):
            fail(self.path, loc(f"mesh {m} primitive {p}", pointer("meshes", m, "primitives", p, "material")),
                 f"material {i!r} does not exist (the file has {len(self.gltf.materials or [])})", _FIX)
        return i

    def _attribute(self, attrs, name, where, at, types, components, draco: DracoGeometry | None = None):
        """Attribute `name` of a primitive (`at`: the primitive's pointer) decoded, or None; NaN
        and infinite values are refused (they would poison the bounds, normals and the render).
        draco: the primitive's decoded Draco geometry, which holds the attributes it names."""
        i = attrs.get(name)
        if i is None:
            return None
        if draco is not None and name in draco.attributes:
            return self.buffers.accessor_of_decoded(i, draco.attributes[name], f"{where} {name}", f"{at}/attributes/{name}",
                                                    allowed_types=types, allowed_components=components, finite=True)
        return self.buffers.accessor(i, f"{where} {name}", f"{at}/attributes/{name}", allowed_types=types,
                                     allowed_components=components, finite=True)

    def _shape(self, m, mesh, p, prim, material: GltfMaterial) -> _Shape | None:
        mesh_name = get(mesh, "name")
        where = f"mesh {m}" + (f" ({mesh_name!r})" if mesh_name else "") + f" primitive {p}"
        at = pointer("meshes", m, "primitives", p)
        mode = get(prim, "mode", 4)
        if mode not in (4, 5, 6):
            name = MODE_NAMES.get(mode, f"unknown mode {mode}")
            fail(self.path, loc(where, at + "/mode"), f"has mode {name}; jaxpbr renders triangles only "
                 "(TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN)",
                 "remove the point/line primitives from the asset (or convert them to triangle geometry) and re-export")
        attrs = primitive_attributes(prim)
        if "POSITION" not in attrs:
            self.notes.append(f"{loc(where, at)} has no POSITION attribute and is skipped (as the spec says)")
            return None
        ext = draco_extension(prim)
        draco = decode_primitive(self.buffers, ext, self.path, where, at, mode) if ext is not None else None
        positions = self._attribute(attrs, "POSITION", where, at, ("VEC3",), _FLOATISH + (5125,), draco)
        positions = np.asarray(positions, np.float64)
        n = positions.shape[0]
        normals = self._attribute(attrs, "NORMAL", where, at, ("VEC3",), _FLOATISH, draco)
        tangents = self._attribute(attrs, "TANGENT", where, at, ("VEC4",), _FLOATISH, draco)
        texcoords = {}
        for s in (0, 1):
            uv = self._attribute(attrs, f"TEXCOORD_{s}", where, at, ("VEC2",), _FLOATISH, draco)
            if uv is not None:
                texcoords[s] = np.asarray(uv, np.float32)
        color = self._attribute(attrs, "COLOR_0", where, at, ("VEC3", "VEC4"), (5121, 5123, 5126), draco)
        for name, arr in (("NORMAL", normals), ("TANGENT", tangents), ("COLOR_0", color)):
            if arr is not None and arr.dtype.kind != "f":
                fail(self.path, f"{loc(f'{where} {name}', f'{at}/attributes/{name}')}: "
                     f"{loc(f'accessor {attrs[name]}', pointer('accessors', attrs[name]))}",
                     "is an integer accessor without normalized: true (glTF needs FLOAT or normalized integers)", _FIX)
        for name, arr in (("NORMAL", normals), ("TANGENT", tangents), ("COLOR_0", color),
                          *((f"TEXCOORD_{s}", uv) for s, uv in texcoords.items())):
            if arr is not None and arr.shape[0] != n:
                fail(self.path, loc(f"{where} {name}", f"{at}/attributes/{name}"),
                     f"has {arr.shape[0]} elements but POSITION ({at}/attributes/POSITION) has {n}", _FIX)
        if color is not None:
            color = np.asarray(color, np.float32)
            # COLOR_0 multiplies the base colour (a reflectance in [0, 1]): a value far outside
            # that would carry an HDR sun past float32 (1e30: infinite pixels). Float rounding of
            # exporters (1.0000001) is clamped; the message names the element, not the value.
            outside = (color < -_COLOR_SLACK) | (color > 1.0 + _COLOR_SLACK)
            if outside.any():
                first = int(np.argmax(outside.any(axis=1)))
                ci = attrs["COLOR_0"]
                fail(self.path, f"{loc(f'{where} COLOR_0', f'{at}/attributes/COLOR_0')}: "
                     f"{loc(f'accessor {ci}', pointer('accessors', ci))}",
                     f"{int(outside.any(axis=1).sum())} of its {n} colours have components outside [0, 1] (the first in "
                     f"element {first}): COLOR_0 is a linear multiplier of the base colour",
                     "clamp the vertex colours to [0, 1] (or store them as normalized integers) and re-export")
            color = np.clip(color, 0.0, 1.0)
            if color.shape[1] == 3:
                color = np.concatenate([color, np.ones((n, 1), np.float32)], axis=1)
        if draco is not None:
            # The triangles as decoded; an `indices` accessor describes them (count, type).
            idx = draco.indices
            if get(prim, "indices") is not None:
                self.buffers.accessor_of_decoded(get(prim, "indices"), idx, f"{where} indices", f"{at}/indices",
                                                 allowed_types=("SCALAR",), allowed_components=(5121, 5123, 5125))
            if idx.size and idx.max() >= n:
                fail(self.path, loc(f"{where} indices", f"{at}/extensions/KHR_draco_mesh_compression"),
                     f"the decoded triangles index a vertex past the {n} of POSITION (the first at position "
                     f"{int(np.argmax(idx.ravel() >= n))})",
                     "the accessors and the compressed data do not match: re-export the asset")
        elif get(prim, "indices") is not None:
            ia = get(prim, "indices")
            idx = self.buffers.accessor(ia, f"{where} indices", f"{at}/indices", allowed_types=("SCALAR",),
                                        allowed_components=(5121, 5123, 5125))
            idx = np.asarray(idx, np.int64)
            if idx.size and idx.max() >= n:
                bad = idx >= n
                first = int(np.argmax(bad))
                fail(self.path, f"{loc(f'{where} indices', f'{at}/indices')}: {loc(f'accessor {ia}', pointer('accessors', ia))}",
                     f"{int(bad.sum())} of its {idx.size} indices are out of range (the first at position {first}): "
                     f"the vertex attributes have {n} elements",
                     "the indices and vertex accessors do not match: re-export the asset")
        else:
            idx = np.arange(n, dtype=np.int64)
        count = idx.shape[0]
        if (mode == 4 and count % 3) or (mode in (5, 6) and count < 3) or count == 0:
            what = f"{at}/indices" if get(prim, "indices") is not None else f"{at}/attributes/POSITION"
            fail(self.path, loc(where, what), f"{count} vertex indices do not make {MODE_NAMES[mode]} "
                 "(TRIANGLES needs a non-zero multiple of 3, strips and fans at least 3)", _FIX)
        tris = triangle_list(idx, mode)
        arrays = {"positions": positions}
        arrays.update(self._targets(prim, where, at, n))
        arrays.update(self._skin_attributes(attrs, where, at, n, draco))
        if tangents is not None:
            arrays["tangents"] = np.asarray(tangents, np.float64)
        for s, uv in texcoords.items():
            arrays[f"uv{s}"] = uv
        if color is not None:
            arrays["color"] = color
        flat = normals is None
        unwelded = False
        if flat:
            # The spec: flat normals, and the file's tangents are ignored.
            arrays.pop("tangents", None)
            arrays = {k: v[tris.ravel()] for k, v in arrays.items()}
            normals = np.repeat(face_normals(positions, tris), 3, axis=0)
            tris = np.arange(3 * tris.shape[0], dtype=np.int64).reshape(-1, 3)
            unwelded = True
        arrays["normals"] = normalize_rows(np.asarray(normals, np.float64))
        generated = False
        if "tangents" not in arrays and material.needs_tangents:
            generated, tris = self._generate_tangents(arrays, tris, material, loc(where, at), unwelded)
            if generated:
                keys = list(arrays)
                welded, tris = weld([arrays[k] for k in keys], tris)
                arrays = dict(zip(keys, welded))
        targets = {}
        for name in ("POSITION", "NORMAL", "TANGENT"):
            keys = sorted((k for k in arrays if k.startswith("target ") and k.endswith(" " + name)),
                          key=lambda k: int(k.split()[1]))
            if keys and not (flat and name != "POSITION"):  # (flat normals are made from the posed positions)
                targets[name] = np.stack([arrays[k] for k in keys])
                targets[name].flags.writeable = False
        return _Shape(
            targets=targets,
            joints=arrays.get("joints"),
            weights=arrays.get("weights"),
            positions=arrays["positions"],
            normals=arrays["normals"],
            tris=tris,
            tangents=arrays.get("tangents"),
            texcoords={s: np.ascontiguousarray(arrays[f"uv{s}"], np.float32) for s in (0, 1) if f"uv{s}" in arrays},
            color=None if "color" not in arrays else np.ascontiguousarray(arrays["color"], np.float32),
            flat_normals=flat,
            generated_tangents=generated,
        )

    def _targets(self, prim, where, at, n) -> dict:
        """The primitive's morph targets as {'target k NAME': (V, 3) float64 deltas}."""
        out = {}
        targets = get(prim, "targets", []) or []
        for k, tgt in enumerate(targets):
            for name, i in tgt.items():
                if name not in ("POSITION", "NORMAL", "TANGENT"):
                    continue  # (TEXCOORD_n and COLOR_n targets: not animated)
                d = self.buffers.accessor(i, f"{where} target {k} {name}", f"{at}/targets/{k}/{name}",
                                          allowed_types=("VEC3",), allowed_components=(5126, 5120, 5122), finite=True)
                if d.dtype.kind != "f":
                    fail(self.path, loc(f"{where} target {k} {name}", f"{at}/targets/{k}/{name}"),
                         "is an integer accessor without normalized: true", _FIX)
                if d.shape[0] != n:
                    fail(self.path, loc(f"{where} target {k} {name}", f"{at}/targets/{k}/{name}"),
                         f"has {d.shape[0]} elements but POSITION has {n}", _FIX)
                out[f"target {k} {name}"] = np.asarray(d, np.float64)
        return out

    def _skin_attributes(self, attrs, where, at, n, draco) -> dict:
        """{'joints': (V, 4s) int64, 'weights': (V, 4s) float64} from JOINTS_0..s-1 and
        WEIGHTS_0..s-1 (weights normalised to sum 1; a vertex without weight follows its first
        joint), or {} without them."""
        sets = 0
        while f"JOINTS_{sets}" in attrs and f"WEIGHTS_{sets}" in attrs:
            sets += 1
        if sets == 0:
            return {}
        joints, weights = [], []
        for k in range(sets):
            j = self._attribute(attrs, f"JOINTS_{k}", where, at, ("VEC4",), (5121, 5123), draco)
            w = self._attribute(attrs, f"WEIGHTS_{k}", where, at, ("VEC4",), (5126, 5121, 5123), draco)
            if w.dtype.kind != "f":
                fail(self.path, loc(f"{where} WEIGHTS_{k}", f"{at}/attributes/WEIGHTS_{k}"),
                     "is an integer accessor without normalized: true", _FIX)
            for name, arr in ((f"JOINTS_{k}", j), (f"WEIGHTS_{k}", w)):
                if arr.shape[0] != n:
                    fail(self.path, loc(f"{where} {name}", f"{at}/attributes/{name}"),
                         f"has {arr.shape[0]} elements but POSITION has {n}", _FIX)
            joints.append(np.asarray(j, np.int64))
            weights.append(np.asarray(w, np.float64))
        j = np.concatenate(joints, axis=1)
        w = np.concatenate(weights, axis=1)
        if (w < 0).any():
            first = int(np.argmax((w < 0).any(axis=1)))
            fail(self.path, loc(f"{where} WEIGHTS_n", f"{at}/attributes"), f"has negative skin weights (the first at "
                 f"vertex {first})", _FIX)
        total = w.sum(axis=1, keepdims=True)
        empty = total[:, 0] <= 0
        w = np.where(total > 0, w / np.where(total > 0, total, 1.0), 0.0)
        w[empty, 0] = 1.0
        return {"joints": j, "weights": w}

    def _generate_tangents(self, arrays, tris, material, where, unwelded):
        """MikkTSpace tangents (object space) into arrays['tangents'], unwelding arrays first.

        Returns (whether tangents were made, the triangles)."""
        ref = next((material.textures[r] for r in ("normal", "clearcoat_normal", "anisotropy") if r in material.textures), None)
        s = ref.texcoord if ref is not None else 0
        if f"uv{s}" not in arrays:
            self.notes.append(f"{where}: material {material.name!r} needs tangents but the primitive has neither "
                              f"TANGENT nor TEXCOORD_{s} to generate them from; tangents are left out")
            return False, tris
        try:
            from .mikktspace import mikktspace_tangents
        except ModuleNotFoundError as e:
            if e.name != f"{__package__}.mikktspace":
                raise
            self.notes.append(f"{where}: tangents are needed but the MikkTSpace generator "
                              f"({__package__}.mikktspace) is not available; tangents are left out")
            return False, tris
        if not unwelded:
            corners = tris.ravel()
            for k in list(arrays):
                arrays[k] = arrays[k][corners]
            tris = np.arange(corners.size, dtype=np.int64).reshape(-1, 3)
        # The generator takes an unwelded triangle soup (corner k of triangle t at row 3t + k, glTF
        # texcoords as stored) and returns glTF-convention tangents per corner.
        try:
            t = np.asarray(mikktspace_tangents(
                np.asarray(arrays["positions"], np.float32), np.asarray(arrays["normals"], np.float32),
                np.asarray(arrays[f"uv{s}"], np.float32)), np.float64)
        except InputError as e:
            fail(self.path, where, f"MikkTSpace tangents cannot be made ({e})", _FIX)
        except Exception as e:  # a generator bug, not bad input: keep it distinguishable
            raise RuntimeError(f"{self.path}: {where}: mikktspace_tangents failed: {e}") from e
        if t.shape != (arrays["positions"].shape[0], 4):
            raise RuntimeError(f"mikktspace_tangents returned shape {t.shape}, expected "
                               f"({arrays['positions'].shape[0]}, 4) per corner")
        arrays["tangents"] = t
        return True, tris

    # -- cameras and lights -----------------------------------------------------------------------
    def _camera(self, v: _Visit):
        cameras = self.gltf.cameras or []
        c = get(v.node, "camera")
        if not isinstance(c, int) or isinstance(c, bool) or not 0 <= c < len(cameras):
            fail(self.path, loc(v.where, v.at + "/camera"), f"camera {c!r} does not exist (the file has {len(cameras)})", _FIX)
        cam = cameras[c]
        at = pointer("cameras", c)
        kind = get(cam, "type")
        name = get(cam, "name", "")
        world, node_index = v.world, v.index
        if kind == "perspective":
            pp = get(cam, "perspective")
            if pp is None or get(pp, "yfov") is None or get(pp, "znear") is None:
                fail(self.path, loc(f"camera {c}", at + "/perspective"), "perspective camera without yfov/znear", _FIX)
            self.cameras.append(GltfCamera(
                type=kind, world_matrix=world.copy(), camera=c, node=node_index, name=name,
                yfov=float(get(pp, "yfov")), aspect_ratio=None if get(pp, "aspectRatio") is None else float(get(pp, "aspectRatio")),
                znear=float(get(pp, "znear")), zfar=float(get(pp, "zfar", math.inf))))
        elif kind == "orthographic":
            op = get(cam, "orthographic")
            if op is None or any(get(op, k) is None for k in ("xmag", "ymag", "znear", "zfar")):
                fail(self.path, loc(f"camera {c}", at + "/orthographic"), "orthographic camera without xmag/ymag/znear/zfar", _FIX)
            for k in ("xmag", "ymag"):
                x = get(op, k)
                if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x == 0:
                    fail(self.path, loc(f"camera {c}", at + f"/orthographic/{k}"), f"orthographic {k} must be a finite non-zero number, got {x!r}", _FIX)
            self.cameras.append(GltfCamera(
                type=kind, world_matrix=world.copy(), camera=c, node=node_index, name=name,
                xmag=float(get(op, "xmag")), ymag=float(get(op, "ymag")),
                znear=float(get(op, "znear")), zfar=float(get(op, "zfar"))))
        else:
            fail(self.path, loc(f"camera {c}", at + "/type"), f"type {kind!r} is neither 'perspective' nor 'orthographic'", _FIX)

    def _light(self, v: _Visit, li):
        ext = (get(self.gltf, "extensions", {}) or {}).get("KHR_lights_punctual") or {}
        lights = get(ext, "lights", []) or []
        if not isinstance(li, int) or isinstance(li, bool) or not 0 <= li < len(lights):
            fail(self.path, loc(f"{v.where} KHR_lights_punctual", v.at + "/extensions/KHR_lights_punctual/light"),
                 f"light {li!r} does not exist (the file has {len(lights)})", _FIX)
        light = lights[li]
        at = pointer("extensions", "KHR_lights_punctual", "lights", li)
        what = f"KHR_lights_punctual light {li}"
        kind = get(light, "type")
        if kind not in ("directional", "point", "spot"):
            fail(self.path, loc(what, at + "/type"), f"type {kind!r} is not directional, point or spot", _FIX)
        color = np.asarray(get(light, "color", (1.0, 1.0, 1.0)), np.float64)
        if color.shape != (3,) or not np.all(np.isfinite(color)):
            fail(self.path, loc(what, at + "/color"), f"color {color.tolist()} is not 3 finite numbers", _FIX)
        world = v.world
        direction = normalize_rows((world[:3, :3] @ np.array([0.0, 0.0, -1.0]))[None])[0]
        inner = outer = None
        if kind == "spot":
            spot = get(light, "spot", {}) or {}
            inner = float(get(spot, "innerConeAngle", 0.0))
            outer = float(get(spot, "outerConeAngle", math.pi / 4))
        self.lights.append(GltfLight(
            type=kind, color=color, intensity=float(get(light, "intensity", 1.0)),
            range=float(get(light, "range", math.inf)), position=world[:3, 3].copy(), direction=direction,
            light=li, node=v.index, name=get(light, "name", ""),
            inner_cone_angle=inner, outer_cone_angle=outer))


def read_gltf(path, *, scene: int | None = None, lazy_images: bool = False, roots=(),
              ray_engine: str | None = None, time: float | None = None, animation=None) -> GltfAsset:
    """Load a glTF 2.0 asset (.gltf with external or data: URIs, or .glb) flattened to world space.

    Args:
        path: the .gltf or .glb file.
        scene: index of the scene to load; default the file's `scene`, else scene 0 (a file
            without scenes: all root nodes).
        lazy_images: leave images undecoded until `GltfImage.pixels` is read (default: decode the
            images that materials use now, so that a broken image fails the load).
        roots: folders besides the asset's own whose files its buffer and image URIs may name. By
            default an asset reads only regular files inside its own folder (symbolic links
            resolved): absolute paths, `..` or a link leading out, `file:` and other schemes,
            devices and FIFOs are refused (docs/gltf.md, "Untrusted assets").
        ray_engine: "embree" or "jax" when the asset is loaded to be rendered: the memory check
            made before any buffer is read then also counts that engine's acceleration structure
            over every instanced triangle (`jaxpbr.load_gltf` and `jaxpbr render` pass it).
        time: seconds into `animation`: the nodes' transforms and morph weights at that time
            (glTF 2.0 §3.11: keys clamped at both ends; STEP, LINEAR with quaternion slerp,
            CUBICSPLINE). None with animation None: the rest pose. Skins and morph weights apply
            in every pose (the rest pose uses the nodes' and meshes' `weights`).
        animation: which animation (an index or a name; default the first when a time is given).

    Returns:
        `GltfAsset`: one `GltfPrimitive` per (node, mesh primitive) of the scene, in world space
        (see its docstring); materials (plus the spec's default material when needed), images,
        KHR_lights_punctual lights and cameras.

    Raises:
        InputError: unreadable/malformed files, missing buffer or image files, accessors outside
        their buffer, indices outside the vertex range, point/line primitives, unsupported image
        types, and extensionsRequired the loader does not implement (`SUPPORTED_EXTENSIONS`, all
        named in one error). Nothing is returned half-loaded.

    Warns (one `UserWarning` per kind, listed in `GltfAsset.warnings`): extensionsUsed that are
    ignored; animation channels of properties not animated (KHR_animation_pointer); texture
    slots without a decodable image; tangents that cannot be generated.
    """
    path = Path(path)
    if ray_engine not in (None, "embree", "jax"):
        raise ValueError(f"ray_engine must be None, 'embree' or 'jax', got {ray_engine!r}")
    loader = _Loader(path, scene, lazy_images, roots, ray_engine, time, animation)
    # The load makes a few objects per node and per instance and keeps them all: Python's cyclic
    # collector would walk them again and again (a million instances: 68 s with it, ... without).
    collecting = gc.isenabled()
    gc.disable()
    try:
        asset = loader.run()
    except InputError:
        raise
    except (TypeError, KeyError, IndexError, AttributeError, ValueError) as e:
        context = loader.context.at if isinstance(loader.context, _Visit) else loader.context
        near = f"{context}: " if context else ""
        msg = f"glTF file {str(path)!r}: {near}malformed content ({type(e).__name__}: {e}). Fix: {_FIX}"
        raise InputError(" ".join(msg.split())) from e
    finally:
        if collecting:
            gc.enable()
    for note in asset.warnings:
        warnings.warn(f"{path.name}: {note}", UserWarning, stacklevel=2)
    return asset
