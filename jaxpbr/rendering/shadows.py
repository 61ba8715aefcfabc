"""Shadows: one shadow ray per pixel and light, towards the light, against every object of the scene.

A point or spot light is blocked when something lies between the surface and the light's position;
a directional light (and a sun split out of the environment) when anything lies along the direction
towards it. Disc lights are tested along their centre direction: shadows are hard-edged (the
penumbra of a sun, 0.27 degrees, is under a pixel at the distances of most scenes).

Spheres and planes are intersected in JAX; meshes by the host ray engine's occlusion query
(`jax.pure_callback`, as primary visibility). Shadow rays start at the surface point moved off the
surface along the geometric normal, on the light's side, by the float-aware offset of Waechter and
Binder (`visibility.offset_ray_origin`: 256 float32 units in the last place of each coordinate),
so that neither a tiny object nor a far one self-shadows; the rays are float32, the ray engine's
precision, also in float64 renders. Visibility has no derivative (the blocked/unblocked choice);
the gradient of a shadowed image flows through the lit pixels' shading.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._numerics import vdot, vnormalize
from ..shading.lights import pack_lights
from .mesh import ACCELS, MAX_CULLED_HITS, Mesh, _embree, host_alpha
from .scene import Plane, Sphere, intersect_plane, intersect_sphere
from .visibility import offset_ray_origin

__all__ = ["shadow_visibility"]

def _host_occluded(vertices, triangles, o, d, tfar, alpha=None):
    vertices = np.ascontiguousarray(vertices, np.float32)
    triangles = np.ascontiguousarray(triangles, np.int32)
    accel = ACCELS.get(vertices, triangles, "embree" if _embree() else "jax", exact_ties=alpha is not None)
    shape = np.shape(o)[:-1]
    o = np.asarray(o, np.float32).reshape(-1, 3)
    d = np.asarray(d, np.float32).reshape(-1, 3)
    tfar = np.asarray(tfar, np.float32).reshape(-1)
    if alpha is None:
        return np.asarray(accel.occluded(o, d, tnear=0.0, tfar=tfar), bool).reshape(shape)
    # Cut-outs (MASK below the cutoff) and blended surfaces let the light through: walk the hits.
    blocked = np.zeros(len(o), bool)
    todo = np.arange(len(o))
    tnear = np.zeros(len(o), np.float32)
    after = np.full(len(o), -1, np.int32)
    cutoff = np.asarray(alpha["cutoff"])
    tri_mesh = np.asarray(alpha["tri_mesh"])
    for _ in range(MAX_CULLED_HITS + 1):
        if todo.size == 0:
            break
        h = accel.intersect(o[todo], d[todo], tnear=tnear[todo], tfar=tfar[todo], after_prim=after[todo])
        p = np.asarray(h.prim, np.int32)
        hit = p >= 0
        mode, a = host_alpha(alpha, triangles, p, np.asarray(h.b1), np.asarray(h.b2))
        through = hit & ((mode == 2) | ((mode == 1) & (a < cutoff[tri_mesh[np.maximum(p, 0)]])))
        blocked[todo[hit & ~through]] = True
        nxt = todo[through]
        tnear[nxt] = np.asarray(h.t, np.float32)[through]
        after[nxt] = p[through]
        todo = nxt
    return blocked.reshape(shape)


def _mesh_occluded(arrays, o, d, tfar):
    """(...,) bool: the segment o + t d, 0 < t < tfar, meets an opaque point of a mesh triangle
    (either face; MASK cut-outs and BLEND surfaces let the light through)."""
    o = jax.lax.stop_gradient(o).astype(jnp.float32)
    d = jax.lax.stop_gradient(d).astype(jnp.float32)
    tfar = jax.lax.stop_gradient(tfar).astype(jnp.float32)
    verts = jax.lax.stop_gradient(arrays["positions"]).astype(jnp.float32)
    alpha = jax.lax.stop_gradient(arrays["alpha"]) if arrays["alpha"] is not None else None
    out = jax.ShapeDtypeStruct(o.shape[:-1], jnp.bool_)
    return jax.pure_callback(_host_occluded, out, verts, arrays["triangles"], o, d, tfar, alpha, vmap_method="sequential")


def _analytic_occluded(objects, o, d, tfar, dtype):
    blocked = jnp.zeros(tfar.shape, bool)
    for ob in objects:
        if isinstance(ob, Sphere):
            c = tuple(jnp.asarray(ob.center, dtype)[i] for i in range(3))
            t, ok = intersect_sphere(o, d, c, jnp.asarray(ob.radius, dtype))
        elif isinstance(ob, Plane):
            pt = tuple(jnp.asarray(ob.point, dtype)[i] for i in range(3))
            nn = tuple(jnp.asarray(ob.normal, dtype)[i] for i in range(3))
            t, ok = intersect_plane(o, d, pt, nn)
        else:
            continue
        blocked = blocked | (ok & (t < tfar))
    return blocked


def shadow_visibility(objects, arrays, pos, ng, lights, dtype, *, directions_only: bool = False):
    """(..., L) visibility (1 lit, 0 shadowed) of each light from the surface points `pos` with
    geometric normals `ng` (Vec3s): lights as for `shade_direct` (their packed order). arrays: the
    meshes' concatenated arrays (`mesh.concat_meshes`) or None. directions_only: the lights are
    directions to the light (Vec3 list, e.g. rotated suns) rather than light objects."""
    if directions_only:
        dirs = [(vnormalize(lt), None) for lt in lights]
    else:
        ls = pack_lights(list(lights) if isinstance(lights, (list, tuple)) else lights)
        dirs = []
        for i in range(ls.num_lights):
            light = jax.tree_util.tree_map(lambda x, i=i: x[i], ls)
            to = tuple(jnp.asarray(light.position[j], dtype) - pos[j] for j in range(3))
            dist = jnp.sqrt(vdot(to, to))
            axis = vnormalize(tuple(jnp.asarray(light.direction[j], dtype) for j in range(3)))
            directional = light.directional
            l = tuple(jnp.where(directional, -axis[j], to[j] / jnp.maximum(dist, 1e-30)) for j in range(3))
            dirs.append((l, jnp.where(directional, jnp.inf, dist)))
    analytic = [ob for ob in objects if not isinstance(ob, Mesh)]
    out = []
    for l, dist in dirs:
        side = jnp.where(vdot(ng, l) < 0, -1.0, 1.0)
        # Rays are traced in float32 (the ray engine's precision): the offset is float32's.
        o32 = offset_ray_origin(jax.lax.stop_gradient(jnp.stack(pos, -1)), jax.lax.stop_gradient(jnp.stack(tuple(side * c for c in ng), -1)))
        o = tuple(o32[..., i].astype(dtype) for i in range(3))
        l = tuple(jax.lax.stop_gradient(c) for c in l)
        big = jnp.asarray(jnp.finfo(dtype).max, dtype)
        tfar = jnp.broadcast_to(big if dist is None else jnp.minimum(jax.lax.stop_gradient(dist), big), pos[0].shape)
        # A point light's own position is not an occluder: stop a hair short of it.
        tfar = tfar * (1 - 8 * jnp.finfo(dtype).eps)
        blocked = _analytic_occluded(analytic, o, l, tfar, dtype) if analytic else jnp.zeros(pos[0].shape, bool)
        if arrays is not None:
            blocked = blocked | _mesh_occluded(arrays, o32, jnp.stack(l, -1), tfar)
        out.append(jnp.where(blocked, 0.0, 1.0).astype(dtype))
    return jnp.stack(out, -1)
