"""Animated glTF scenes posed inside JAX: `posed_scene(gltf_scene, time, ...)` -> a `Scene` whose
meshes hold the asset's vertices at that time of an animation (node transforms, morph targets,
skins; glTF 2.0 §3.7.2.2, §3.7.3, §3.11), computed by `jaxpbr.io.gltf.pose_primitives` traced with
jax.numpy. It runs under `jax.jit`, `jax.vmap` (over times) and `jax.grad`: image gradients reach
the time, the nodes' rest transforms (`rest`: the joint rotations of a pose fit), the morph weights
and the key values of an animation given as a `GltfAnimation`. Meshes no animation moves keep their
arrays (constants of the trace).

What is not re-posed here: the winding of a primitive whose transform changes handedness over the
animation (a mirroring scale keyed in), and the asset's cameras and lights (`load_gltf(time=)` and
`jaxpbr.io.gltf.posed_asset` pose those, on the host).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._pytree import evolve
from ..errors import InputError
from ..io.gltf import pose_primitives
from .gltf_scene import GltfScene

__all__ = ["posed_geometry", "posed_scene"]

_FILL = {"normals": (0.0, 0.0, 1.0), "tangents": (1.0, 0.0, 0.0, 1.0)}


def posed_scene(gltf_scene: GltfScene, time, *, animation=None, rest=None, morph_weights=None):
    """`gltf_scene.scene` with the asset's moving meshes posed at `time` of `animation` (an index,
    a name, a `GltfAnimation`, or None: the first when a time is given; both None: the rest pose).

    rest: None, or (translation (N, 3), rotation (N, 4) x y z w, scale (N, 3)) for every node of
        the file (start from `asset.nodes.translation`, `.rotation`, `.scale`): the nodes' rest
        transforms, which the animation's channels then override.
    morph_weights: {node: (K,) weights} replacing the animated or default morph weights.
    Every argument may be traced (jit, vmap, grad)."""
    if not isinstance(gltf_scene, GltfScene):
        raise InputError(f"posed_scene takes the GltfScene of `scene_from_asset` (or `jaxpbr.io.gltf` + "
                         f"`scene_from_asset`), got {type(gltf_scene).__name__}")
    asset = gltf_scene.asset
    posed = pose_primitives(asset, time, animation, xp=jnp, rest=rest, morph_weights=morph_weights)
    if not posed:
        return gltf_scene.scene
    objects = list(gltf_scene.scene.objects)
    for k, idx in enumerate(gltf_scene.layout):
        if not any(i in posed for i in idx):
            continue
        mesh = objects[k]
        dtype = jnp.asarray(mesh.positions).dtype
        changes = {}
        for name, slot, field_ in (("positions", 0, "positions"), ("normals", 1, "normals"), ("tangents", 2, "tangents")):
            if getattr(mesh, field_) is None:
                continue
            parts = []
            for i in idx:
                p = asset.primitives[i]
                if i in posed and posed[i][slot] is not None:
                    parts.append(jnp.asarray(posed[i][slot], dtype))
                else:
                    a = getattr(p, name)
                    parts.append(jnp.asarray(a if a is not None else np.broadcast_to(np.float32(_FILL[name]), (p.num_vertices, len(_FILL[name]))), dtype))
            changes[field_] = jnp.concatenate(parts) if len(parts) > 1 else parts[0]
        objects[k] = evolve(mesh, **changes)
    return evolve(gltf_scene.scene, objects=tuple(objects))


def posed_geometry(gltf_scene: GltfScene, times, *, animation=None) -> dict:
    """The moving meshes of `posed_scene` at each of `times` (B,): {object index: {"positions":
    (B, V, 3), and "normals" / "tangents" where the mesh has them}}, the `geometry` of
    `render_batch` (`render_batch(gltf_scene, times=...)` calls this). Meshes no animation moves
    are left out (they keep their arrays and their acceleration structure for the whole batch).
    Traceable (one `jax.vmap` of `posed_scene` over the times)."""
    times = jnp.asarray(times)
    if times.ndim != 1 or times.shape[0] == 0:
        raise InputError(f"times must be a non-empty 1-D array (B,), got shape {times.shape}")
    base = gltf_scene.scene.objects
    first = posed_scene(gltf_scene, times[0], animation=animation).objects
    moving = [k for k, (a, b) in enumerate(zip(base, first, strict=True)) if a is not b]
    if not moving:
        raise InputError("posed_geometry: no mesh of the scene moves in this animation (nothing to batch over times)")

    def one(t):
        objs = posed_scene(gltf_scene, t, animation=animation).objects
        return {str(k): {name: getattr(objs[k], name) for name in ("positions", "normals", "tangents")
                         if getattr(objs[k], name) is not None} for k in moving}

    return jax.vmap(one)(times)
