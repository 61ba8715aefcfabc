"""`render_batch`: B variants of a scene (batched materials, cameras, lights, environment rotation
and intensity) in chunks, as vmapped stages on XLA:CPU or one program per chunk, optionally
sharded over devices."""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._numerics import is_concrete
from .._pytree import Pytree, evolve, fields_of
from .._validate import check_values, positive_int
from ..shading.material import Material
from .assets import ibl_assets
from .cache import AssetCache, cache_or_default
from .execute import EXECUTION, _staged, _supersampled, _with_device_accel
from .options import RenderOptions, _options
from .plan import plan_for, split_environment
from .scene import Scene, TexturedMaterial
from .mesh import Mesh, _host_cast, transmits
from .shadows import colored_shadows, host_mesh_hits
from .stages import (_cast_inputs, _combine_jit, _culls_facing, _geometry, _ibl_directions, _ibl_segments, _ibl_visibility, _light_segments,
                     _ratio_weights, _render_traced, _shade_direct, _shade_rest, _sun_segments, _sun_shadows, _surface_ids, _texture,
                     _transmitted, scene_host_arrays)
from .edges import NEIGHBOURS, antialias_pass

#: Default pixels per chunk of `render_batch` (images x pixels x samples), bounding memory.
BATCH_CHUNK_PIXELS = 1 << 21


# The batch set-up runs in NumPy for concrete inputs: each eager jnp operation would compile a
# program of its own (a dozen for one render_batch call).


def _broadcast_batch(x, shape):
    return np.broadcast_to(np.asarray(x), shape) if is_concrete(x) else jnp.broadcast_to(x, shape)


def _pad_last(x, pad: int):
    """x with its last entry along the leading axis repeated `pad` more times."""
    xp = np if is_concrete(x) else jnp
    x = np.asarray(x) if xp is np else x
    return xp.concatenate([x, xp.repeat(x[-1:], pad, axis=0)])


def _batched(name: str, obj):
    """(B or None, obj with every field broadcast to the leading batch axis B).

    A field is batched when it has one more axis than its declared rank (`leaf(rank=...)` in
    `jaxpbr._pytree`: vector fields (B, n), scalar fields (B,)); unbatched fields are broadcast.
    All batched fields must agree on B. Only objects whose children are all array leaves
    (materials, cameras, lights) can be batched."""
    fields = [f for f in fields_of(obj) if not f.static] if isinstance(obj, Pytree) else []
    if not fields or not all(f.is_array for f in fields):
        raise TypeError(f"{name}: unsupported batched object {type(obj).__name__}")
    sizes = {}
    fields = [f for f in fields if getattr(obj, f.name) is not None]  # absent optional fields stay None
    for f in fields:
        x = getattr(obj, f.name)
        if np.ndim(x) == f.rank + 1:
            sizes[f.name] = int(np.shape(x)[0])
        elif np.ndim(x) != f.rank:
            expected = "(B,)" if f.rank == 0 else "(B, n)" if f.rank == 1 else f"(B, +{f.rank} axes)"
            raise ValueError(f"{name}.{f.name} has shape {np.shape(x)}; expected {expected} or unbatched")
    if not sizes:
        raise ValueError(f"{name} has no batched field; give at least one field a leading batch axis")
    if len(set(sizes.values())) != 1:
        raise ValueError(f"{name}: every batched field must have the same leading batch axis, got {sizes}")
    B = next(iter(sizes.values()))
    out = {f.name: _broadcast_batch(getattr(obj, f.name), (B,) + np.shape(getattr(obj, f.name))) for f in fields if f.name not in sizes}
    return B, evolve(obj, **out)


def _substitute(scene: Scene, b: dict, objects_idx) -> Scene:
    """The scene with the (unbatched slice of the) batched inputs `b` put in place, unvalidated."""
    changes = {}
    if "materials" in b:
        mat = b["materials"]
        if scene.gbuffer is not None:
            changes["gbuffer"] = evolve(scene.gbuffer, material=mat)
        else:
            objs = list(scene.objects)
            for k in objects_idx:
                ob = objs[k]
                new_m = evolve(ob.material, factors=mat) if isinstance(ob.material, TexturedMaterial) else mat
                objs[k] = evolve(ob, material=new_m)
            changes["objects"] = tuple(objs)
    if "camera" in b:
        changes["camera"] = b["camera"]
    if "lights" in b:
        changes["lights"] = tuple(b["lights"])
    if "env" in b:
        changes["environment"] = evolve(scene.environment, **b["env"])
    if "geometry" in b:
        objs = list(changes.get("objects", scene.objects))
        for k, fields in b["geometry"].items():
            objs[int(k)] = evolve(objs[int(k)], **fields)
        changes["objects"] = tuple(objs)
    return evolve(scene, **changes)


_GEOMETRY_FIELDS = {"positions": 3, "normals": 3, "tangents": 4}


def _batched_geometry(scene: Scene, geometry) -> tuple[int, dict]:
    """(B, {object index (str): {field: (B, V, n) array}}) of `render_batch(geometry=)`, checked
    against the scene's meshes."""
    if not isinstance(geometry, dict) or not geometry:
        raise ValueError("geometry must be a non-empty dict {object index: {'positions': (B, V, 3), ...}}")
    out, sizes = {}, set()
    for k, fields in geometry.items():
        k = int(k)
        if not 0 <= k < len(scene.objects) or not isinstance(scene.objects[k], Mesh):
            raise ValueError(f"geometry: object {k} is not a mesh of the scene")
        mesh = scene.objects[k]
        if not isinstance(fields, dict) or not fields or set(fields) - set(_GEOMETRY_FIELDS):
            got = f"the fields {sorted(map(str, fields))}" if isinstance(fields, dict) else f"a {type(fields).__name__}"
            raise ValueError(f"geometry[{k}] must be a dict of {sorted(_GEOMETRY_FIELDS)}, got {got}")
        for name, x in fields.items():
            want = (mesh.num_vertices, _GEOMETRY_FIELDS[name])
            if np.ndim(x) != 3 or tuple(np.shape(x)[1:]) != want:
                raise ValueError(f"geometry[{k}][{name!r}] has shape {np.shape(x)}; expected (B, {want[0]}, {want[1]})")
            if getattr(mesh, name) is None:
                raise ValueError(f"geometry[{k}][{name!r}]: the scene's mesh has no {name} to replace")
            sizes.add(int(np.shape(x)[0]))
        out[str(k)] = {name: jnp.asarray(x, jnp.asarray(getattr(mesh, name)).dtype) for name, x in fields.items()}
    if len(sizes) != 1:
        raise ValueError(f"geometry: every array must have the same leading batch axis, got {sorted(sizes)}")
    return sizes.pop(), out


@functools.partial(jax.jit, static_argnums=(3, 4, 5, 6, 7))
def _batch_jit(scene, assets, b, p_plan, opts, objects_idx, chunk, mesh):
    def run(scene, assets, b):
        one = lambda x: _render_traced(_substitute(scene, x, objects_idx), assets, p_plan, opts)
        return jax.lax.map(one, b, batch_size=chunk)

    if mesh is None:
        return run(scene, assets, b)
    from jax.sharding import PartitionSpec as P

    return jax.shard_map(run, mesh=mesh, in_specs=(P(), P(), P("batch")), out_specs=P("batch"), check_vma=False)(
        scene, assets, b
    )


def render_batch(
    scene: Scene,
    *,
    materials: Material | None = None,
    objects=None,
    cameras=None,
    lights=None,
    env_rotation=None,
    env_intensity=None,
    chunk: int | None = None,
    devices=None,
    options: RenderOptions | None = None,
    cache: AssetCache | None = None,
    geometry=None,
    times=None,
    animation=None,
    **overrides,
) -> jax.Array:
    """Render B variants of `scene` in one jitted, vmapped call -> (B, H, W, 3).

    Batched inputs (each with a leading axis B; give any combination):
      materials: a Material whose leaves are (B, ...): replaces the material of the objects listed
        in `objects` (default: all; for a TexturedMaterial its factors), or of a G-buffer scene.
      cameras: a Camera whose array fields are (B, ...) (same width/height/supersample).
      lights: a list of lights whose fields are (B, ...); replaces the scene's lights.
      env_rotation, env_intensity: (B,) environment rotations about +Y (radians) / intensities.
      geometry: {object index: {"positions": (B, V, 3), "normals": (B, V, 3), "tangents": (B, V, 4)}}
        (any of the three): meshes whose vertices differ per image (same triangles). Each image's
        rays are cast against its own meshes; meshes not listed keep their structure for the
        whole batch (`mesh.ACCELS`: only the listed meshes are built per image).
      times (with `scene` a `GltfScene` of an animated asset; `animation` as for `posed_scene`):
        (B,) times, each image the asset posed at its time (the geometry of the moving meshes,
        `animated.posed_geometry`). Cameras and lights stay the scene's.
    chunk: images rendered together per step (`lax.map` batch size), bounding memory; default
      keeps about 2M pixel samples per step.
    devices: None (all local devices), a list of devices, or 1: the batch is sharded over them
      with `jax.sharding` (shard_map over a 1-D mesh "batch"); each device renders its share in
      chunks. Results equal the single-device path to float rounding (measured: at most 1 ulp;
      the per-device programs are compiled separately and XLA may fuse them differently).
    options, cache, **overrides: as for `render`, the traced IBL visibility rungs and transmission
      included. Precomputes are shared by the whole batch (rotations and intensities need none).
    On the CPU each chunk's rays (primary, shadow, IBL visibility) go to the host ray engine in one
    call per kind between the chunk's programs, as `render`'s staged stages cast them; elsewhere the
    opaque meshes' rays are traced in the program through the device BVH.
    """
    from jax.sharding import Mesh

    opts = _options(options, overrides, "render_batch")
    from .gltf_scene import GltfScene

    if times is not None:
        if not isinstance(scene, GltfScene):
            raise ValueError("render_batch(times=) takes the GltfScene of `load_gltf` / `scene_from_asset` as its scene")
        if geometry is not None:
            raise ValueError("render_batch: give times or geometry, not both")
        from .animated import posed_geometry

        geometry = posed_geometry(scene, times, animation=animation)
    elif animation is not None:
        raise ValueError("render_batch: animation needs times")
    if isinstance(scene, GltfScene):
        scene = scene.scene
    b: dict[str, Any] = {}
    sizes: list = []
    if materials is not None:
        if not isinstance(materials, Material):
            raise TypeError("materials must be a Material whose leaves have a leading batch axis")
        b["materials"] = materials
        sizes.append(_batched("materials", materials))
    if objects is None:
        objects_idx = tuple(range(len(scene.objects)))
    else:
        objects_idx = tuple(int(k) for k in objects)
        for k in objects_idx:
            if not 0 <= k < len(scene.objects):
                raise ValueError(f"objects index {k} out of range (scene has {len(scene.objects)} objects)")
    if cameras is not None:
        if scene.camera is None or (cameras.width, cameras.height) != (scene.camera.width, scene.camera.height):
            raise ValueError("batched cameras must have the scene camera's width and height")
        sizes.append(_batched("cameras", cameras))
        b["camera"] = sizes[-1][1]
    if lights is not None:
        lights = [lights] if not isinstance(lights, (list, tuple)) else list(lights)
        if not lights:
            raise ValueError("lights is empty; leave it out to keep the scene's lights")
        packed = [_batched(f"lights[{i}]", lt) for i, lt in enumerate(lights)]
        sizes.extend(packed)
        b["lights"] = tuple(x for _, x in packed)
    env_b = {}
    for key, val in (("rotation", env_rotation), ("intensity", env_intensity)):
        if val is not None:
            val = jnp.asarray(val)
            if val.ndim != 1:
                raise ValueError(f"env_{key} must be a 1-D array (B,), got shape {val.shape}")
            # Concrete values as Environment checks them (tracers pass: see check_values).
            env_b[key] = check_values(f"render_batch: env_{key}", val, lo=0.0 if key == "intensity" else None)
            sizes.append((val.shape[0], val))
    if env_b:
        if scene.environment is None:
            raise ValueError("env_rotation/env_intensity need a scene with an environment")
        b["env"] = env_b
    if geometry is not None:
        n, b["geometry"] = _batched_geometry(scene, geometry)
        sizes.append((n, None))
    if not b:
        raise ValueError("render_batch needs at least one batched input (materials, cameras, lights, env_rotation, env_intensity, geometry, times)")
    if len({n for n, _ in sizes}) != 1:
        raise ValueError(f"render_batch inputs must share the same leading batch axis, got sizes {sorted({n for n, _ in sizes})}")
    B = sizes[0][0]
    if B == 0:
        raise ValueError("render_batch got an empty batch (leading axis 0); pass at least one variant")
    if materials is not None:
        materials = sizes[0][1]
        b["materials"] = materials
    base = scene if "lights" not in b else scene.replace(lights=tuple(jax.tree_util.tree_map(lambda x: x[0], lt) for lt in b["lights"]))
    # Plan from the scene as the batch will see it (batched materials substituted, concrete).
    plan_scene = _substitute(base, {"materials": materials}, objects_idx) if materials is not None else base
    cache = cache_or_default(cache)
    split = split_environment(base.environment, opts, cache)
    p_plan = plan_for(plan_scene, opts, suns=len(split.suns or ()))
    assets = ibl_assets(split, p_plan, opts, cache) if p_plan.ibl else None

    if devices is None:
        devices = jax.local_devices()
    elif devices == 1:
        devices = jax.local_devices()[:1]
    devices = list(devices)
    ndev = len(devices)
    H, W = base.image_shape
    spp = 1 if base.gbuffer is not None else base.camera.supersample**2
    if chunk is None:
        chunk = max(1, BATCH_CHUNK_PIXELS // (H * W * spp))
    chunk = positive_int("chunk", chunk)
    per_dev = -(-B // ndev)
    chunk = min(chunk, per_dev)
    # Every step renders exactly `chunk` images (the batch is padded with copies of its last
    # entry), so each device runs the same compiled chunk program as the single-device path.
    per_dev = -(-per_dev // chunk) * chunk
    pad = per_dev * ndev - B
    if pad:
        b = jax.tree_util.tree_map(lambda x: _pad_last(x, pad), b)
    mesh = Mesh(np.asarray(devices), ("batch",)) if ndev > 1 else None
    leaves = jax.tree_util.tree_leaves((base, b))
    if mesh is None and _staged() and all(is_concrete(x) for x in leaves):
        return _render_batch_staged(base, assets, b, p_plan, opts, objects_idx, chunk)[:B]
    # Off the CPU, opaque meshes are traced in the program (the BVH is shared by every image;
    # not with per-image geometry, whose rays go to the host engine image by image).
    traced = base if "geometry" in b else _with_device_accel(base, EXECUTION)
    out = _batch_jit(traced, assets, b, p_plan, opts, objects_idx, chunk, mesh)
    return out[:B]


_CHUNK_STATIC = ("p_plan", "opts", "objects_idx")


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _geometry_chunk(scene, bc, off, *, p_plan, opts, objects_idx):
    """The geometry stage vmapped over a chunk of batched inputs bc (the sub-pixel offset shared)."""
    return jax.vmap(lambda x: _geometry(_substitute(scene, x, objects_idx), p_plan, opts, off))(bc)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _cast_chunk(scene, bc, off, *, p_plan, opts, objects_idx):
    """The primary rays of a chunk of images as the host ray engine casts them (`stages._cast_inputs`)."""
    return jax.vmap(lambda x: _cast_inputs(_substitute(scene, x, objects_idx), p_plan, opts, off))(bc)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _mesh_geometry_chunk(scene, bc, off, prim, *, p_plan, opts, objects_idx):
    """The geometry stage of a chunk with the meshes' primitives cast already (prim (B, H, W))."""
    return jax.vmap(lambda x, pr: _geometry(_substitute(scene, x, objects_idx), p_plan, opts, off, pr, light_shadows=False))(bc, prim)


def _chunk_geometry(scene, bc, off, kw):
    """The geometry of a chunk of images: with opaque-layer meshes, every image's primary rays cast
    by the host ray engine in one call (`mesh._host_cast` on the scene's arrays, as `render`'s staged
    geometry does), then the geometry program given the primitives; a program that called the
    engine back per image cost 2.3x a loop of `render` (16 cameras at 256^2, 100 k triangles)."""
    p_plan, opts = kw["p_plan"], kw["opts"]
    if _host_traced(scene, kw, bc):
        x = _cast_chunk(scene, bc, off, **kw)
        a = scene_host_arrays(scene, opts.dtype)
        prim = _host_cast(a["positions"], a["triangles"], a["cull_back"], np.asarray(x["o"]), np.asarray(x["d"]), a["alpha"], parts=a["parts"])
        g = _mesh_geometry_chunk(scene, bc, off, jax.device_put(prim), **kw)
        if p_plan.shadows and p_plan.direct:
            g = {**g, "vis": _host_shadows(scene, opts, _light_segments_chunk(scene, bc, g, **kw), g["hit"])}
        return g
    return _geometry_chunk(scene, bc, off, **kw)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _light_segments_chunk(scene, bc, g, *, p_plan, opts, objects_idx):
    facing = _culls_facing(p_plan) and not p_plan.normal_maps  # (the shading normal is final here without normal maps)
    return jax.vmap(lambda x, gx: _light_segments(_substitute(scene, x, objects_idx), opts, gx["pos"], gx["ng"],
                                                  gx["n"] if facing else None))(bc, g)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _sun_segments_chunk(scene, bc, g, env_lights, *, p_plan, opts, objects_idx):
    facing = _culls_facing(p_plan)
    return jax.vmap(lambda x, gx: _sun_segments(_substitute(scene, x, objects_idx), opts, gx["pos"], gx["ng"], env_lights,
                                                gx["n"] if facing else None))(bc, g)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _ibl_segments_chunk(scene, bc, g, off, *, p_plan, opts, objects_idx):
    """(directions (B, K, ..., 3), their shadow segments) of the IBL visibility rays of a chunk."""
    def one(x, gx):
        sc = _substitute(scene, x, objects_idx)
        dirs = _ibl_directions(sc, p_plan, opts, gx, off)
        return dirs, _ibl_segments(sc, opts, gx["pos"], gx["ng"], dirs)

    return jax.vmap(one)(bc, g)


def _host_shadows(scene, opts, parts, hit):
    """The visibility of a chunk's shadow segments (`parts`, leading batch axis) with the meshes'
    rays cast by the host ray engine in one call (`shadows.host_mesh_hits`, as `render`'s staged
    shadows), only from the pixels that hit a surface."""
    arrays = scene_host_arrays(scene, opts.dtype)

    def per_pixel(p):  # a direction per image (a sun's, a directional light's): (B, 3) -> (B, 1, ..., 1, 3)
        o, d = np.asarray(p["o32"]), np.asarray(p["l"])
        return {**p, "l": d.reshape(d.shape[:1] + (1,) * (o.ndim - d.ndim) + d.shape[1:])} if d.ndim < o.ndim else p

    hits = [jax.device_put(h) for h in host_mesh_hits(arrays, [per_pixel(p) for p in parts], np.asarray(hit))]
    return _combine_jit(colored_shadows(scene.objects), jnp.dtype(opts.dtype).name, parts, hits)


def _host_traced(scene, kw, bc) -> bool:
    """Whether a chunk's rays go to the host ray engine between programs: staged, with meshes of
    one layer (else they are traced in the chunk's programs). Not when the batch replaces materials
    that decide what the rays see (cut-outs, blending, transmission's coloured shadows): the host
    engine reads the scene's own."""
    meshes = [ob for ob in scene.objects if isinstance(ob, Mesh)]
    if scene.gbuffer is not None or kw["p_plan"].blend_layers != 1 or not meshes or "geometry" in bc:
        return False  # (per-image geometry: each image's rays cast against its own meshes, in the chunk's programs)
    if "materials" not in bc:
        return True
    # (transmission is static: batched materials can add it to or remove it from any object, which
    # changes whether shadows are coloured and what they let through)
    return (all(m.alpha_mode == "OPAQUE" for m in meshes) and not transmits(bc["materials"])
            and not any(transmits(ob.material) for ob in scene.objects if getattr(ob, "material", None) is not None))


@functools.partial(jax.jit, static_argnames=("k",) + _CHUNK_STATIC)
def _texture_chunk(scene, bc, g, *, k, p_plan, opts, objects_idx):
    return jax.vmap(lambda x, gx: _texture(_substitute(scene, x, objects_idx), k, opts, gx))(bc, g)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _direct_chunk(scene, bc, g, *, p_plan, opts, objects_idx):
    return jax.vmap(lambda x, gx: _shade_direct(_substitute(scene, x, objects_idx), p_plan, opts, gx))(bc, g)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _sun_chunk(scene, bc, g, env_lights, *, p_plan, opts, objects_idx):
    """The shadows of the suns split out of the environment (`stages._sun_shadows`), per image."""
    def one(x, gx):
        return {**gx, "vis_env": _sun_shadows(_substitute(scene, x, objects_idx), opts, gx, env_lights)}

    return jax.vmap(one)(bc, g)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _ibl_vis_chunk(scene, bc, g, off, pre, *, p_plan, opts, objects_idx):
    """The IBL visibility rays of the traced rungs (`stages._ibl_visibility`) and, for "ratio",
    their weights (`stages._ratio_weights`), per image: one program per chunk, the meshes' rays
    through the ray engine (the callback on the CPU, the device BVH in the program off it)."""
    def one(x, gx):
        sc = _substitute(scene, x, objects_idx)
        vis = _ibl_visibility(sc, p_plan, opts, gx, off, False)
        if p_plan.ibl_visibility == "ratio":
            vis = {**vis, "w": _ratio_weights(sc, p_plan, opts, gx, vis["d"], pre)}
        return {**gx, "ibl_vis": vis}

    return jax.vmap(one)(bc, g)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _ratio_chunk(scene, bc, g, pre, *, p_plan, opts, objects_idx):
    """The ratio estimator's weights of a chunk's IBL visibility rays (`stages._ratio_weights`)."""
    def one(x, gx):
        w = _ratio_weights(_substitute(scene, x, objects_idx), p_plan, opts, gx, gx["ibl_vis"]["d"], pre)
        return {**gx, "ibl_vis": {**gx["ibl_vis"], "w": w}}

    return jax.vmap(one)(bc, g)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _transmit_chunk(scene, bc, g, off, assets, *, p_plan, opts, objects_idx):
    """What the transmitted rays see (`stages._transmitted`: the surfaces behind shaded one level
    deeper), per image."""
    def one(x, gx):
        return {**gx, "behind": _transmitted(_substitute(scene, x, objects_idx), assets, p_plan, opts, gx, off, False)}

    return jax.vmap(one)(bc, g)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _rest_chunk(scene, bc, g, assets, direct, *, p_plan, opts, objects_idx):
    def one(x, gx, dx):
        return _shade_rest(_substitute(scene, x, objects_idx), assets, p_plan, opts, gx, dx)

    return jax.vmap(one)(bc, g, direct)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC + ("samples",))
def _outline_chunk(scene, bc, g, c, off, nbr, *, p_plan, opts, objects_idx, samples):
    def one(args):
        x, gx, cx = args
        return antialias_pass(_substitute(scene, x, objects_idx), opts.dtype, off[:2], cx, _surface_ids(gx), samples, nbr,
                              blend=opts.antialias)

    # One image after another (lax.map, not vmap): the edge stage's chunks past an image's
    # candidates are skipped by a conditional, which a batched predicate would turn into both branches.
    return jax.lax.map(one, (bc, g, c))


def _render_batch_staged(scene, assets, b, p_plan, opts, objects_idx, chunk):
    """`render_batch` on XLA:CPU: for each chunk of `chunk` images, the render's stages as
    separate programs, each vmapped over the chunk (one program over the whole chunk fuses and
    recomputes producers on XLA:CPU, measured 3x slower than a Python loop of `render`; see
    `_render_pass`). Host loop over the chunks."""
    kw = {"p_plan": p_plan.for_stages(), "opts": opts, "objects_idx": objects_idx}
    b = jax.device_put(b)  # once (set up on the host): each chunk is then cut on the device
    total = jax.tree_util.tree_leaves(b)[0].shape[0]

    def one_pass(bc):
        def run(sc, off):
            g = _chunk_geometry(sc, bc, off, kw)
            for t in p_plan.textured:
                g = _texture_chunk(sc, bc, g, k=t, **kw)
            direct = _direct_chunk(sc, bc, g, **kw)
            host = _host_traced(sc, kw, bc)
            if p_plan.shadows and p_plan.env_lights:  # as `stages._shade_pass` does
                if host:
                    g = {**g, "vis_env": _host_shadows(sc, kw["opts"], _sun_segments_chunk(sc, bc, g, assets[3], **kw), g["hit"])}
                else:
                    g = _sun_chunk(sc, bc, g, assets[3], **kw)
            if p_plan.ibl_samples and host:
                dirs, parts = _ibl_segments_chunk(sc, bc, g, off, **kw)
                vis = _host_shadows(sc, kw["opts"], parts, g["hit"])
                vis = vis if vis.ndim == g["hit"].ndim + 2 else vis[..., None]  # (B, ..., K, C)
                g = {**g, "ibl_vis": {"d": dirs, "vis": jnp.moveaxis(vis, -2, 1)}}
                if p_plan.ibl_visibility == "ratio":
                    g = _ratio_chunk(sc, bc, g, assets[1], **kw)
            elif p_plan.ibl_samples:
                g = _ibl_vis_chunk(sc, bc, g, off, assets[1], **kw)
            if p_plan.transmission_depth and p_plan.ibl:
                g = _transmit_chunk(sc, bc, g, off, assets, **kw)
            c = _rest_chunk(sc, bc, g, assets, direct, **kw)
            if opts.antialias == "none":
                return c
            # The outlines of each image (`edges.antialias_pass`); the meshes' topology is the
            # scene's (vertices welded by the scene's positions, not each image's).
            return _outline_chunk(sc, bc, g, c, off, nbr, samples=samples, **kw)

        return run

    samples = scene.camera.supersample
    nbr = None
    host = scene_host_arrays(scene, opts.dtype) if any(isinstance(ob, Mesh) for ob in scene.objects) else None
    if host is not None:
        nbr = jax.device_put(NEIGHBOURS.get(host["positions"], host["triangles"], host["parts"]))

    # The chunk is cut on the device by one program (its start is an argument).
    outs = [_supersampled(scene, opts, one_pass(_take_chunk(b, i, n=chunk))) for i in range(0, total, chunk)]
    return jnp.concatenate(outs) if len(outs) > 1 else outs[0]


@functools.partial(jax.jit, static_argnames=("n",))
def _take_chunk(b, start, *, n):
    return jax.tree_util.tree_map(lambda x: jax.lax.dynamic_slice_in_dim(x, start, n), b)

