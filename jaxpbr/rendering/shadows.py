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

MASK cut-outs and BLEND surfaces let the light through. Transmissive surfaces (KHR_materials_transmission,
thin-walled) let part of it through: each crossing multiplies it by transmission x base colour (on meshes
with their textures and COLOR_0, looked up on the host as the MASK alpha is; on spheres, crossed twice,
and planes, the factors), up to the first opaque surface. Fresnel reflection at the wall, the spread of
rough transmission and a volume's attenuation are left out. Visibility is then (..., L, 3), one factor per
light and channel (`shade_direct` takes either form); without transmissive objects it is (..., L).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._numerics import vdot, vnormalize
from ..shading.lights import pack_lights
from .mesh import (
    ACCELS,
    MAX_CULLED_HITS,
    Mesh,
    _embree,
    device_occluded,
    host_alpha,
    host_transmittance,
    transmits,
)
from .scene import Plane, Sphere, intersect_plane, intersect_sphere
from .textured import TexturedMaterial
from .visibility import offset_ray_origin

__all__ = ["colored_shadows", "host_mesh_hits", "shadow_combine", "shadow_segments", "shadow_visibility"]

def _host_occluded(vertices, triangles, o, d, tfar, alpha=None, transmit=None, parts=None):
    """Without `transmit`: (...,) bool, the segment meets an opaque point. With it: (..., 3) the
    fraction of the light left after every crossing of the segment (0 where an opaque point
    blocks it; transmissive crossings multiply it by `host_transmittance`)."""
    vertices = np.ascontiguousarray(vertices, np.float32)
    triangles = np.ascontiguousarray(triangles, np.int32)
    walk = alpha is not None or transmit is not None
    # The primary rays' structure (exact ties where cut-outs and blended layers need them).
    accel = ACCELS.get(vertices, triangles, "embree" if _embree() else "jax", exact_ties=alpha is not None, parts=parts)
    shape = np.shape(o)[:-1]
    o = np.asarray(o, np.float32).reshape(-1, 3)
    # A direction (3,) shared by every ray (a sun) is one per ray in the walk below.
    d = np.broadcast_to(np.asarray(d, np.float32), shape + (3,)).reshape(-1, 3)
    tfar = np.broadcast_to(np.asarray(tfar, np.float32), shape).reshape(-1)
    if not walk:
        return np.asarray(accel.occluded(o, d, tnear=0.0, tfar=tfar), bool).reshape(shape)
    # Cut-outs (MASK below the cutoff) and blended surfaces let the light through, transmissive
    # ones part of it: walk the hits.
    n = len(o)
    left = np.ones((n, 3), np.float64)
    todo = np.arange(n)
    tnear = np.zeros(n, np.float32)
    after = np.full(n, -1, np.int32)
    tri_mesh = np.asarray((alpha if alpha is not None else transmit)["tri_mesh"])
    for _ in range(MAX_SHADOW_CROSSINGS):
        if todo.size == 0:
            break
        h = accel.intersect(o[todo], d[todo], tnear=tnear[todo], tfar=tfar[todo], after_prim=after[todo])
        p = np.asarray(h.prim, np.int32)
        t = np.asarray(h.t, np.float32)
        b1, b2 = np.asarray(h.b1), np.asarray(h.b2)
        hit = p >= 0
        through = np.zeros_like(hit)
        if alpha is not None:
            mode, a = host_alpha(alpha, triangles, p, b1, b2)
            cutoff = np.asarray(alpha["cutoff"])
            through = hit & ((mode == 2) | ((mode == 1) & (a < cutoff[tri_mesh[np.maximum(p, 0)]])))
        factor = np.zeros((len(p), 3))
        if transmit is not None:
            factor = host_transmittance(transmit, triangles, p, b1, b2)
            # A segment through the edge shared by two triangles of one surface meets both at the
            # same distance: one crossing, not two.
            prev = after[todo]
            same = (prev >= 0) & (tri_mesh[np.maximum(prev, 0)] == tri_mesh[np.maximum(p, 0)]) & (
                np.abs(t - tnear[todo]) <= 1e-6 * np.maximum(1.0, np.abs(t)))
            factor[same] = 1.0
        factor[through] = 1.0
        rows = todo[hit]
        left[rows] *= factor[hit]
        go = hit & np.any(factor > 0, -1)
        nxt = todo[go]
        tnear[nxt] = t[go]
        after[nxt] = p[go]
        todo = nxt
    if transmit is None:
        return np.all(left == 0.0, -1).reshape(shape)
    return left.astype(np.float32).reshape(shape + (3,))


#: Most surfaces a shadow ray crosses (cut-outs, blended and transmissive surfaces) before it is
#: taken as reaching the light.
MAX_SHADOW_CROSSINGS = MAX_CULLED_HITS + 1


def _mesh_occluded(arrays, o, d, tfar):
    """(...,) bool: the segment o + t d, 0 < t < tfar, meets an opaque point of a mesh triangle
    (either face; MASK cut-outs and BLEND surfaces let the light through). With transmissive meshes
    (`arrays["transmit"]`): (..., 3) float32, the fraction of the light left along the segment."""
    o = jax.lax.stop_gradient(o).astype(jnp.float32)
    d = jax.lax.stop_gradient(d).astype(jnp.float32)
    tfar = jax.lax.stop_gradient(tfar).astype(jnp.float32)
    if arrays.get("bvh") is not None and arrays["alpha"] is None and arrays.get("transmit") is None:
        return device_occluded(arrays, o, d, tfar)
    verts = jax.lax.stop_gradient(arrays["positions"]).astype(jnp.float32)
    alpha = jax.lax.stop_gradient(arrays["alpha"]) if arrays["alpha"] is not None else None
    transmit = arrays.get("transmit")
    transmit = jax.lax.stop_gradient(transmit) if transmit is not None else None
    if transmit is None:
        out = jax.ShapeDtypeStruct(o.shape[:-1], jnp.bool_)
    else:
        out = jax.ShapeDtypeStruct(o.shape[:-1] + (3,), jnp.float32)
    return jax.pure_callback(functools.partial(_host_occluded, parts=arrays.get("parts")), out, verts, arrays["triangles"], o, d, tfar, alpha, transmit,
                             vmap_method="sequential")


def _transmittance(material, dtype):
    """(3,) what one crossing of a transmissive analytic surface lets through: transmission x
    base colour (the factors; textures are not looked up for shadow rays on spheres and planes)."""
    f = material.factors if isinstance(material, TexturedMaterial) else material
    t = jnp.clip(jnp.asarray(f.transmission, dtype), 0.0, 1.0)
    return t * jnp.clip(jnp.broadcast_to(jnp.asarray(f.base_color, dtype), (3,)), 0.0, 1.0)


def _analytic_occluded(objects, o, d, tfar, dtype):
    """(blocked (...) bool, left (..., 3) or None): opaque spheres and planes met by the segment,
    and the light left after crossing transmissive ones (None without any)."""
    blocked = jnp.zeros(tfar.shape, bool)
    left = None
    for ob in objects:
        if isinstance(ob, Sphere):
            c = tuple(jnp.asarray(ob.center, dtype)[i] for i in range(3))
            r = jnp.asarray(ob.radius, dtype)
            if transmits(ob.material):
                # Both crossings of the sphere: the roots t0 <= t1 (intersect_sphere's forms).
                oc = tuple(o[i] - c[i] for i in range(3))
                b = vdot(oc, d)
                cc = vdot(oc, oc) - r * r
                disc = b * b - cc
                t1 = -b + jnp.sqrt(jnp.maximum(disc, 0.0))
                t0 = jnp.where(t1 != 0, cc / jnp.where(t1 != 0, t1, 1.0), 0.0)
                ins = [((disc > 0) & (x > 0) & (x < tfar))[..., None] for x in (t0, t1)]
                tr = _transmittance(ob.material, dtype)
                k = jnp.where(ins[0], tr, 1.0) * jnp.where(ins[1], tr, 1.0)
                left = k if left is None else left * k
                continue
            t, ok = intersect_sphere(o, d, c, r)
        elif isinstance(ob, Plane):
            pt = tuple(jnp.asarray(ob.point, dtype)[i] for i in range(3))
            nn = tuple(jnp.asarray(ob.normal, dtype)[i] for i in range(3))
            t, ok = intersect_plane(o, d, pt, nn)
            if transmits(ob.material):
                k = jnp.where((ok & (t < tfar))[..., None], _transmittance(ob.material, dtype), 1.0)
                left = k if left is None else left * k
                continue
        else:
            continue
        blocked = blocked | (ok & (t < tfar))
    return blocked, left


def shadow_visibility(objects, arrays, pos, ng, lights, dtype, *, directions_only: bool = False):
    """(..., L) visibility (1 lit, 0 shadowed) of each light from the surface points `pos` with
    geometric normals `ng` (Vec3s), or (..., L, 3) per channel when some object is transmissive
    (see the module docstring): lights as for `shade_direct` (their packed order). arrays: the
    meshes' concatenated arrays (`mesh.concat_meshes`) or None. directions_only: the lights are
    directions to the light (Vec3 list, e.g. rotated suns) rather than light objects."""
    parts = shadow_segments(objects, pos, ng, lights, dtype, directions_only=directions_only)
    hits = [None if arrays is None else _mesh_occluded(arrays, p["o32"], p["l"], p["tfar"]) for p in parts]
    return shadow_combine(colored_shadows(objects), parts, hits, dtype)


def colored_shadows(objects) -> bool:
    """Whether visibility is per colour channel: some surface lets part of the light through."""
    return any(transmits(ob.material) for ob in objects if isinstance(ob, (Mesh, Sphere, Plane)))


#: How far below its horizon (in n.l, beyond a disc's sin radius) the light must be for a point's
#: shadow ray to be left out (`shadow_segments(normal=)`): a margin over the rounding by which the
#: shading's n.l can differ from the segment's.
FACING_MARGIN = 1e-3


def shadow_segments(objects, pos, ng, lights, dtype, *, directions_only: bool = False, normal=None,
                    sin_radii=None) -> list[dict]:
    """Per light (their packed order), the shadow segment from each surface point and what the
    analytic objects do to it: {"o32": (..., 3) float32 origins, "l": (..., 3) float32 directions,
    "tfar": (...) float32 lengths, "blocked": (...) bool, "left": (..., 3) light left or None}. The
    meshes' part (`_mesh_occluded`, or `host_mesh_hits` outside a trace) and `shadow_combine` make
    the visibility.

    normal: the shading normal, given where a light adds exactly 0 at a point whose normal faces
    away from it (materials without extensions: the BRDF is 0 below the horizon, and a disc light's
    cap factor is 0 once the whole disc is below it), adds "trace": (...) bool, False where n.l <
    -(sin radius) - FACING_MARGIN; `host_mesh_hits` traces no ray there (the visibility it reports,
    "not blocked", multiplies 0). sin_radii: the discs' sin radii with directions_only (default 0)."""
    if directions_only:
        dirs = [(vnormalize(lt), None) for lt in lights]
        radii = list(sin_radii) if sin_radii is not None else [0.0] * len(dirs)
    else:
        ls = pack_lights(list(lights) if isinstance(lights, (list, tuple)) else lights)
        dirs, radii = [], []
        for i in range(ls.num_lights):
            light = jax.tree_util.tree_map(lambda x, i=i: x[i], ls)
            to = tuple(jnp.asarray(light.position[j], dtype) - pos[j] for j in range(3))
            dist = jnp.sqrt(vdot(to, to))
            axis = vnormalize(tuple(jnp.asarray(light.direction[j], dtype) for j in range(3)))
            directional = light.directional
            l = tuple(jnp.where(directional, -axis[j], to[j] / jnp.maximum(dist, 1e-30)) for j in range(3))
            dirs.append((l, jnp.where(directional, jnp.inf, dist)))
            radii.append(light.sin_radius)
    analytic = [ob for ob in objects if not isinstance(ob, Mesh)]
    n_unit = None if normal is None else vnormalize(tuple(jax.lax.stop_gradient(c) for c in normal))
    parts = []
    for (l, dist), sin_radius in zip(dirs, radii, strict=True):
        side = jnp.where(vdot(ng, l) < 0, -1.0, 1.0)
        # Rays are traced in float32 (the ray engine's precision): the offset is float32's.
        o32 = offset_ray_origin(jax.lax.stop_gradient(jnp.stack(pos, -1)), jax.lax.stop_gradient(jnp.stack(tuple(side * c for c in ng), -1)))
        o = tuple(o32[..., i].astype(dtype) for i in range(3))
        l = tuple(jax.lax.stop_gradient(c) for c in l)
        big = jnp.asarray(jnp.finfo(dtype).max, dtype)
        tfar = jnp.broadcast_to(big if dist is None else jnp.minimum(jax.lax.stop_gradient(dist), big), pos[0].shape)
        # A point light's own position is not an occluder: stop a hair short of it.
        tfar = tfar * (1 - 8 * jnp.finfo(dtype).eps)
        blocked, left = _analytic_occluded(analytic, o, l, tfar, dtype) if analytic else (jnp.zeros(pos[0].shape, bool), None)
        part = {"o32": o32.astype(jnp.float32), "l": jnp.stack(l, -1).astype(jnp.float32), "tfar": tfar.astype(jnp.float32),
                "blocked": blocked, "left": left}
        if n_unit is not None:
            part["trace"] = vdot(n_unit, l) >= -(jnp.asarray(sin_radius, dtype) + FACING_MARGIN)
        parts.append(part)
    return parts


def host_mesh_hits(arrays, parts, mask=None) -> list:
    """`_mesh_occluded` of each segment of `parts` on the host, outside any trace (NumPy in, NumPy
    out): the staged render calls the ray engine directly instead of compiling a program that
    calls back to it. arrays: the meshes' concatenated arrays (NumPy or concrete). mask: optional
    (...) bool, the points to trace (the pixels that hit a surface); the others, and those a part's
    "trace" leaves out (`shadow_segments(normal=)`), are given "not blocked" (their visibility
    multiplies nothing or 0). The rays of every part go to the ray engine in one call (every light,
    every IBL visibility sample of a pass), which spreads them over its threads at once."""
    tree = lambda x: None if x is None else jax.tree_util.tree_map(np.asarray, x)  # noqa: E731
    verts, tris = np.asarray(arrays["positions"], np.float32), np.asarray(arrays["triangles"])
    alpha, transmit = tree(arrays["alpha"]), tree(arrays.get("transmit"))
    pieces, spans = [], []
    for p in parts:
        o, d, tfar = np.asarray(p["o32"], np.float32), np.asarray(p["l"], np.float32), np.asarray(p["tfar"], np.float32)
        shape = tfar.shape
        sel = mask
        if p.get("trace") is not None:
            sel = np.asarray(p["trace"], bool) if mask is None else np.asarray(mask, bool) & np.asarray(p["trace"], bool)
        o = o.reshape(-1, 3)
        d = np.broadcast_to(d, shape + (3,)).reshape(-1, 3)
        tfar = tfar.reshape(-1)
        rows = None if sel is None else np.flatnonzero(np.broadcast_to(np.asarray(sel, bool), shape).reshape(-1))
        if rows is not None:
            o, d, tfar = o[rows], d[rows], tfar[rows]
        pieces.append((o, d, tfar))
        spans.append((shape, rows, len(tfar)))
    if not pieces:
        return []
    if len(pieces) == 1:
        o, d, tfar = pieces[0]
    else:
        o, d, tfar = (np.concatenate([pc[i] for pc in pieces]) for i in range(3))
    hit = _host_occluded(verts, tris, o, d, tfar, alpha, transmit, parts=arrays.get("parts")) if len(tfar) else np.zeros((0,) + (() if transmit is None else (3,)))
    out, start = [], 0
    for shape, rows, n in spans:
        h = hit[start:start + n]
        start += n
        if rows is None:
            out.append(np.asarray(h).reshape(shape + (() if transmit is None else (3,))))
            continue
        full = np.zeros(shape, bool) if transmit is None else np.ones(shape + (3,), np.float32)
        full.reshape((-1,) + full.shape[len(shape):])[rows] = h
        out.append(full)
    return out


def host_mesh_hit_shapes(arrays, parts) -> list:
    """The shapes of `host_mesh_hits`' results with a mask (`jax.ShapeDtypeStruct`s), no ray traced."""
    if arrays.get("transmit") is None:
        return [jax.ShapeDtypeStruct(tuple(p["tfar"].shape), jnp.bool_) for p in parts]
    return [jax.ShapeDtypeStruct(tuple(p["tfar"].shape) + (3,), jnp.float32) for p in parts]


def shadow_combine(rgb: bool, parts, hits, dtype):
    """The (..., L) or (rgb) (..., L, 3) visibility from `shadow_segments` and the meshes' hits
    (bool (...) or float (..., 3) light left; None without meshes)."""
    out = []
    for p, m in zip(parts, hits):
        blocked, left = p["blocked"], p["left"]
        if m is not None:
            if m.dtype == jnp.bool_:
                blocked = blocked | m
            else:
                left = m.astype(dtype) if left is None else left * m.astype(dtype)
        vis = jnp.where(blocked, 0.0, 1.0).astype(dtype)
        out.append(vis if not rgb else vis[..., None] * (left if left is not None else 1.0))
    return jnp.stack(out, -2 if rgb else -1)
