"""The memory a load will need, estimated from the JSON (accessor counts, image headers, buffer
sizes) and checked once with `jaxpbr._memory.require` before any buffer is read or decoded: a
declared count of billions (a corrupt or hostile file) is refused with the JSON pointers of the
largest contributors instead of running the machine out of memory.

The unit is the decoded float32/int32 size: an accessor of `count` elements of n components is
4 n count bytes, an image of H x W x C values (its PNG/JPEG header) is 4 H W C bytes. The factors
below turn those into the loader's peak (measured, rounded up; see each)."""

from __future__ import annotations

from ... import _memory
from ._binary import (
    COMPONENT_TYPES,
    TYPE_SHAPES,
    get,
    loc,
    pointer,
    primitive_attributes,
)
from ._images import PER_DECODED_VALUE, image_source

__all__ = ["asset_parts", "check_asset_memory"]

#: Peak bytes of building one primitive, per 4 bytes of its arrays (the decoded attributes and the
#: normals, tangents and triangles made from them, over max(vertices, 3 x triangles) rows when
#: the corners are unwelded): the float64 working copies, the unwelded corners of flat normals and
#: MikkTSpace, NumPy temporaries. The world-space float32 copies, one per instance, are counted
#: apart. Measured (peak RSS, CPU, 0.5-2 M triangle grids with POSITION, TEXCOORD_0, UNSIGNED_INT
#: indices): 2.1x with NORMAL, 3.7x without (flat normals), 6.9x with MikkTSpace tangents; rounded up.
_WORK_FACTOR = {"welded": 3.0, "flat": 4.5, "tangents": 8.0}
#: Each instance of a mesh primitive (a node using the mesh, or one of its EXT_mesh_gpu_instancing
#: instances) besides its float32 arrays: its `GltfPrimitive`, the array views and its world
#: matrix. Measured (tracemalloc, 10^5 instances of a triangle): 840 B kept, arrays included;
#: rounded up with the JSON objects of its node.
_PER_INSTANCE = 1200.0
#: An image whose header cannot be read is refused by the decoder before it allocates pixels: its
#: encoded bytes and the temporary copy the decoder reads.
_UNREAD_IMAGE_FACTOR = 2.0


def _accessor_shape(gltf, i):
    """(count, components) of accessor i from the JSON, or None when it is invalid or its count does
    not fit its bufferView: its decode reports that, naming it, before it allocates anything."""
    accessors = gltf.accessors or []
    if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < len(accessors):
        return None
    a = accessors[i]
    count, atype, ctype = get(a, "count"), get(a, "type"), get(a, "componentType")
    if (not isinstance(count, int) or isinstance(count, bool) or count < 0 or atype not in TYPE_SHAPES
            or ctype not in COMPONENT_TYPES):
        return None
    cols, rows = TYPE_SHAPES[atype]
    vi, views = get(a, "bufferView"), gltf.bufferViews or []
    if isinstance(vi, int) and 0 <= vi < len(views):
        length = get(views[vi], "byteLength")
        if isinstance(length, int) and count * cols * rows * COMPONENT_TYPES[ctype].itemsize > length:
            return None
    return count, cols * rows


def _instances(gltf, node) -> int:
    """How many times a node draws its mesh (EXT_mesh_gpu_instancing: the attributes' count)."""
    inst = (get(node, "extensions", {}) or {}).get("EXT_mesh_gpu_instancing")
    if inst is None:
        return 1
    counts = [_accessor_shape(gltf, i) for i in (get(inst, "attributes", {}) or {}).values()]
    return max([c[0] for c in counts if c is not None], default=1)


def _primitive(loader, m, mesh, p, prim):
    """(work bytes, bytes per instance, the accessors' description, bufferViews read) of a
    primitive, or None when it is skipped or invalid (its decode reports that)."""
    gltf = loader.gltf
    attrs = primitive_attributes(prim)
    mode = get(prim, "mode", 4)
    if "POSITION" not in attrs or mode not in (4, 5, 6):
        return None
    shapes = {name: _accessor_shape(gltf, i) for name, i in attrs.items()
              if name in ("POSITION", "NORMAL", "TANGENT", "TEXCOORD_0", "TEXCOORD_1", "COLOR_0")
              or name.startswith(("JOINTS_", "WEIGHTS_"))}
    # Morph targets: their deltas follow the vertices (unwelded with them) and are kept in float64
    # object space with the posing data (`GltfDeform`).
    targets = get(prim, "targets", []) or []
    for k, tgt in enumerate(targets if isinstance(targets, list) else []):
        for name, i in (tgt.items() if isinstance(tgt, dict) else ()):
            if name in ("POSITION", "NORMAL", "TANGENT"):
                shapes[f"target {k} {name}"] = _accessor_shape(gltf, i)
    if shapes.get("POSITION") is None:
        return None
    v = shapes["POSITION"][0]
    n_idx = v
    if get(prim, "indices") is not None:
        ind = _accessor_shape(gltf, get(prim, "indices"))
        if ind is None:
            return None
        n_idx = ind[0]
    tris = n_idx // 3 if mode == 4 else max(n_idx - 2, 0)
    mi = get(prim, "material")
    mat = loader.materials[mi] if isinstance(mi, int) and 0 <= mi < len(loader.materials) else None
    flat = "NORMAL" not in attrs
    ref = None
    if mat is not None:
        ref = next((mat.textures[r] for r in ("normal", "clearcoat_normal", "anisotropy") if r in mat.textures), None)
    texcoord = f"TEXCOORD_{ref.texcoord if ref is not None else 0}"
    generate = (mat is not None and mat.needs_tangents and (flat or "TANGENT" not in attrs)
                and texcoord in attrs)
    tangents = generate or ("TANGENT" in attrs and not flat)
    v_out = 3 * tris if (flat or generate) else v
    extra = sum(c[1] for name, c in shapes.items() if c is not None and name not in ("POSITION", "NORMAL", "TANGENT"))
    per_vertex = 3 + 3 + (4 if tangents else 0)  # positions, normals, tangents: per instance
    values = max(v, v_out) * (per_vertex + extra) + 3 * tris + n_idx
    deform = bool(targets) or any(name.startswith("JOINTS_") for name in shapes)
    if deform:
        # posed primitives keep their object-space float64 data per instance (`GltfDeform`): twice
        # the float32 unit per value
        extra_posed = 2 * (per_vertex + sum(c[1] for name, c in shapes.items() if c is not None and
                                            name.startswith(("target ", "JOINTS_", "WEIGHTS_"))))
    kind = "tangents" if generate else "flat" if flat else "welded"
    work = 4.0 * values * _WORK_FACTOR[kind]
    per_instance = 4.0 * (v_out * (per_vertex + (extra_posed if deform else 0)) + 3 * tris) + _PER_INSTANCE
    named = [f"POSITION {pointer('accessors', attrs['POSITION'])} count {v}"]
    if get(prim, "indices") is not None:
        named.append(f"indices {pointer('accessors', get(prim, 'indices'))} count {n_idx}")
    views = set()
    target_accessors = [i for tgt in (targets if isinstance(targets, list) else []) if isinstance(tgt, dict)
                        for i in tgt.values()]
    for i in [*attrs.values(), get(prim, "indices"), *target_accessors]:
        if isinstance(i, int) and 0 <= i < len(gltf.accessors or []):
            a = gltf.accessors[i]
            views.add(get(a, "bufferView"))
            sparse = get(a, "sparse")
            if sparse is not None:
                views.add(get(get(sparse, "indices"), "bufferView"))
                views.add(get(get(sparse, "values"), "bufferView"))
    return work, per_instance, ", ".join(named), views, v_out, tris


def asset_parts(loader, visits, ray_engine: str | None = None) -> tuple[dict, dict]:
    """({part: bytes}, {part: what to lower}) of a load: one part per mesh primitive (its work and
    its world-space copies, one per instance), per image the load decodes and per buffer read;
    with `ray_engine` ("embree" or "jax"), the acceleration structure a render builds over every
    instanced triangle (`_memory.mesh_bytes`)."""
    gltf = loader.gltf
    parts: dict[str, float] = {}
    names: dict[str, str] = {}
    seen: dict = {}
    views: set = set()
    scene_vertices = scene_triangles = 0
    instanced: dict[str, int] = {}
    for v in visits:
        if get(v.node, "mesh") is None:
            continue
        m, mesh = loader.mesh_of(v)
        n = _instances(gltf, v.node)
        for p, prim in enumerate(get(mesh, "primitives", []) or []):
            if (m, p) not in seen:
                seen[m, p] = _primitive(loader, m, mesh, p, prim)
                if seen[m, p] is not None:
                    views |= seen[m, p][3]
            est = seen[m, p]
            if est is None:
                continue
            mesh_name = get(mesh, "name")
            key = loc(f"mesh {m}" + (f" ({mesh_name!r})" if mesh_name else "") + f" primitive {p}",
                      pointer("meshes", m, "primitives", p))
            if key not in parts:
                parts[key] = est[0]
                names[key] = f"the vertex and index counts of {pointer('meshes', m, 'primitives', p)} ({est[2]})"
            parts[key] += est[1] * n
            scene_vertices += est[4] * n
            scene_triangles += est[5] * n
            instanced[key] = instanced.get(key, 0) + est[5] * n
    if ray_engine is not None and scene_triangles:
        # shared by the primitives by their instanced triangles: the largest names the one to lower
        accel = _memory.mesh_bytes(scene_vertices, scene_triangles, ray_engine)["triangles"]
        for key, t in instanced.items():
            parts[key] += accel * t / scene_triangles
    # Animations and skins: key times and values, inverse bind matrices, decoded as float64.
    for a, anim in enumerate(gltf.animations or []):
        total = 0.0
        for smp in get(anim, "samplers", []) or []:
            for i in (get(smp, "input"), get(smp, "output")):
                sh = _accessor_shape(gltf, i)
                if sh is not None:
                    total += 12.0 * sh[0] * sh[1]  # (float32 decoded, float64 kept)
                    acc = gltf.accessors[i]
                    views.add(get(acc, "bufferView"))
        if total:
            key = loc(f"animation {a}", pointer("animations", a))
            parts[key] = total
            names[key] = f"the key counts of {pointer('animations', a)}'s samplers"
    for k, sk in enumerate(gltf.skins or []):
        sh = _accessor_shape(gltf, get(sk, "inverseBindMatrices"))
        if sh is not None:
            key = loc(f"skin {k}", pointer("skins", k))
            parts[key] = 12.0 * sh[0] * sh[1]
            names[key] = f"the inverse bind matrices of {pointer('skins', k)}"
            views.add(get(gltf.accessors[get(sk, 'inverseBindMatrices')], "bufferView"))
    if not loader.lazy_images:
        for i in loader.used_images():
            shape, size = image_source(gltf, loader.buffers, i)
            if shape is not None:
                nbytes = float(shape[0]) * shape[1] * shape[2] * PER_DECODED_VALUE
                what = f"{shape[1]}x{shape[0]}, {shape[2]} channels"
            elif size is not None:
                nbytes, what = float(size) * _UNREAD_IMAGE_FACTOR, f"{size} bytes encoded"
            else:
                continue
            im = gltf.images[i]
            key = loc(f"image {i}" + (f" ({get(im, 'name')!r})" if get(im, "name") else ""), pointer("images", i))
            parts[key] = nbytes
            names[key] = f"the resolution of {pointer('images', i)} ({what})"
            views.add(get(im, "bufferView"))
    buffers = set()
    for vi in views:
        if isinstance(vi, int) and 0 <= vi < len(gltf.bufferViews or []):
            buffers.add(get(gltf.bufferViews[vi], "buffer", 0))
    for b in sorted(x for x in buffers if isinstance(x, int)):
        size = loader.buffers.buffer_size(b)
        if size:
            key = loc(f"buffer {b}", pointer("buffers", b))
            parts[key] = float(size)
            names[key] = f"the size of {pointer('buffers', b)} ({size} bytes)"
    return parts, names


def _size(x: float) -> str:
    """Bytes as '480 GB', '1.2 MB', '516 B'."""
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if x >= scale:
            return f"{x / scale:.3g} {unit}"
    return f"{x:.0f} B"


def check_asset_memory(loader, visits, ray_engine: str | None = None) -> None:
    """Refuse (`_memory.MemoryLimitError`, an InputError) a load whose decoded meshes, images and
    buffers would need more memory than is available, before any of them is read; the message
    names the three largest parts by JSON pointer and the largest as the one to lower."""
    parts, names = asset_parts(loader, visits, ray_engine)
    if not parts:
        return
    top = sorted(parts, key=parts.get, reverse=True)[:3]
    largest = "; ".join(f"{k} {_size(parts[k])}" for k in top)
    what = f"loading its meshes, images and buffers (largest: {largest})"
    _memory.require(what, parts, where=f"glTF file {str(loader.path)!r}", names=names)
