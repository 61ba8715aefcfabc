"""The stages of a render, as traced functions and as separately compiled programs: geometry
(the G-buffer: ray casts, surfaces, materials), each textured object, direct lighting, IBL +
background; BLEND layers composited; one pass per sub-pixel sample; `gbuffer`.

Shading = `shade_direct` (punctual lights, emissive) + `Environment.intensity * shade_ibl` (split
sum) on the first surface hit, with shadow rays when the plan asks for them; misses show the
environment at mip 0 (or `Scene.background`)."""

from __future__ import annotations

import contextvars
import dataclasses
import functools
import math
import weakref
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._api import keyword_only
from .._numerics import cpu_cond, pack3, safe_normalize, safe_sqrt, small_sq, unpack3, vcross, vdot, vnormalize
from .._program_cache import LOOP_EMITTERS, cached_jit, is_ahead, running_now
from .._pytree import evolve, fields_of, leaf, static, subtree, unchecked
from ..ibl.cubemap import padded
from ..ibl.shade import disc_multiscatter, shade_ibl
from ..shading.layered import emission_soa
from ..shading.lights import shade_direct
from ..shading.material import Material
from . import texture
from .assets import PendingAssets
from .bvh import refit_bvh
from .edges import NEIGHBOURS, antialias_pass, check_topology
from .execution import EXECUTION
from .mesh import Mesh, _host_cast, cast, concat_meshes, mesh_parts, mesh_surface, transmits
from .options import RenderOptions, _options
from .plan import RenderPlan, plan
from .scene import (
    Environment,
    GBuffer,
    Plane,
    Scene,
    Sphere,
    TexturedMaterial,
    TextureSlot,
    apply_extension_textures,
    intersect_plane,
    intersect_sphere,
    primary_rays,
    sample_texture,
)
from .shadows import (
    _mesh_occluded,
    colored_shadows,
    host_mesh_hit_shapes,
    host_mesh_hits,
    shadow_combine,
    shadow_segments,
    shadow_visibility,
)

#: Up to this many spheres the ray cast is unrolled (fused by XLA); beyond, a fori_loop.
UNROLL_MAX_SPHERES = 8


def _stack_materials(objects, dtype, extensions=()):
    """Per-object constant materials (textured objects contribute their factors), leaves (K, ...).
    The extension groups in `extensions` are completed with their neutral values on every object
    (one material structure for all pixels); other extension fields are left out (None)."""
    mats = [ob.material.factors if isinstance(ob.material, TexturedMaterial) else ob.material for ob in objects]
    mats = [m.complete(extensions) for m in mats]
    out = {}
    for f in fields_of(Material):
        if getattr(mats[0], f.name) is None:
            continue
        tail = (3,) * f.rank  # RGB
        out[f.name] = jnp.stack([jnp.broadcast_to(jnp.asarray(getattr(m, f.name), dtype), tail) for m in mats])
    return out


def _gather_material(stack, idx) -> Material:
    return unchecked(Material, **{f.name: (stack[f.name][idx] if f.name in stack else None) for f in fields_of(Material)})


def _cast(objects, o, d, dtype):
    """Nearest hit over all objects: (t, idx, hit), memory O(pixels).

    Each object's hit distance (`big` where it misses) is a conditional's branch: XLA:CPU then
    computes it once per ray, where fused it recomputed the intersection in each of the arrays the
    nearest-hit update writes (t and idx), in the sphere loop as in the unrolled sums. The
    predicate (a parameter of the object is not NaN; with a NaN one the intersection misses too)
    gives the same value either way. 1280x720, the demo's 49 spheres: 36 against 87 ms."""
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)
    shape = d[0].shape
    t_best = jnp.full(shape, big, dtype)
    idx = jnp.zeros(shape, jnp.int32)
    spheres = [k for k, ob in enumerate(objects) if isinstance(ob, Sphere)]
    planes = [k for k, ob in enumerate(objects) if isinstance(ob, Plane)]

    def distance(intersect, guard, *params):
        def near(p):
            t, ok = intersect(o, d, *p)
            return jnp.where(ok, t, big)

        return cpu_cond(~jnp.isnan(guard), near, lambda p: jnp.full(shape, big, dtype), params)

    def take(key, k, t_best, idx):
        better = key < t_best
        return jnp.where(better, key, t_best), jnp.where(better, k, idx)

    if len(spheres) <= UNROLL_MAX_SPHERES:
        for k in spheres:
            c = tuple(jnp.asarray(objects[k].center, dtype)[i] for i in range(3))
            r = jnp.asarray(objects[k].radius, dtype)
            t_best, idx = take(distance(intersect_sphere, r, c, r), k, t_best, idx)
    else:
        centers = jnp.stack([jnp.asarray(objects[k].center, dtype) for k in spheres])
        radii = jnp.stack([jnp.asarray(objects[k].radius, dtype) for k in spheres])
        ids = jnp.asarray(spheres, jnp.int32)

        def body(i, carry):
            c = tuple(centers[i, j] for j in range(3))
            return take(distance(intersect_sphere, radii[i], c, radii[i]), ids[i], *carry)

        t_best, idx = jax.lax.fori_loop(0, len(spheres), body, (t_best, idx))
    for k in planes:
        pt = tuple(jnp.asarray(objects[k].point, dtype)[i] for i in range(3))
        nn = tuple(jnp.asarray(objects[k].normal, dtype)[i] for i in range(3))
        t_best, idx = take(distance(intersect_plane, vdot(nn, nn), pt, nn), k, t_best, idx)
    hit = t_best < big
    return jnp.where(hit, t_best, 0.0), idx, hit


def _surface(objects, o, d, t, idx, dtype, need_uv: bool):
    """Position, geometric normal (facing the viewer for planes), and if asked uv + tangent."""
    K = len(objects)
    is_plane = jnp.asarray([isinstance(ob, Plane) for ob in objects])
    anchor = jnp.stack([jnp.asarray(ob.center if isinstance(ob, Sphere) else ob.point, dtype) for ob in objects])
    pn = jnp.stack(
        [jnp.asarray(ob.normal, dtype) if isinstance(ob, Plane) else jnp.zeros(3, dtype) for ob in objects]
    )
    p = tuple(o[i] + t * d[i] for i in range(3))
    a = tuple(anchor[:, i][idx] if K > 1 else anchor[0, i] for i in range(3))
    rel = tuple(p[i] - a[i] for i in range(3))
    n_sph = vnormalize(rel)
    # A sphere seen from inside (a ray transmitted through its wall) shades its inner side.
    inside = jnp.where(vdot(n_sph, d) > 0, -1.0, 1.0)
    n_in = tuple(c * inside for c in n_sph)
    plane_px = is_plane[idx] if K > 1 else is_plane[0]
    n_pl = vnormalize(tuple((pn[:, i][idx] if K > 1 else pn[0, i]) for i in range(3)))
    facing = jnp.where(vdot(n_pl, d) > 0, -1.0, 1.0)  # planes are two-sided
    n_pl = tuple(c * facing for c in n_pl)
    n = tuple(jnp.where(plane_px, n_pl[i], n_in[i]) for i in range(3))
    if not need_uv:
        return p, n, None, None
    # Sphere: u = 0.5 + atan2(x, z)/(2 pi), v = 0.5 - atan2(y, rho)/pi, T = (z, 0, -x)/rho.
    x, y, z = n_sph
    rho2 = x * x + z * z
    ok = rho2 > small_sq(rho2.dtype)  # off the poles, where atan2 and T are defined
    rho = jnp.sqrt(jnp.where(ok, rho2, 1.0))
    u_s = 0.5 + jnp.arctan2(jnp.where(ok, x, 0.0), jnp.where(ok, z, 1.0)) / (2 * math.pi)
    v_s = 0.5 - jnp.arctan2(y, jnp.where(ok, rho, 0.0)) / math.pi
    t_s = (jnp.where(ok, z / rho, 1.0), jnp.zeros_like(x), jnp.where(ok, -x / rho, 0.0))
    # Plane: T = tangent, B = N x T (with the un-flipped normal), uv = (rel.T, -rel.B) * scale.
    tan = jnp.stack(
        [jnp.asarray(ob.tangent, dtype) if isinstance(ob, Plane) else jnp.zeros(3, dtype) for ob in objects]
    )
    scale = jnp.stack([jnp.asarray(ob.uv_scale if isinstance(ob, Plane) else 1.0, dtype) for ob in objects])
    t_p = vnormalize(tuple((tan[:, i][idx] if K > 1 else tan[0, i]) for i in range(3)))
    n_raw = tuple(c * facing for c in n_pl)
    tn = vdot(t_p, n_raw)
    t_p = vnormalize(tuple(t_p[i] - tn * n_raw[i] for i in range(3)))
    b_p = vcross(n_raw, t_p)
    sc = scale[idx] if K > 1 else scale[0]
    u_p = vdot(rel, t_p) * sc
    v_p = -vdot(rel, b_p) * sc
    u = jnp.where(plane_px, u_p, u_s)
    v = jnp.where(plane_px, v_p, v_s)
    tangent = tuple(jnp.where(plane_px, t_p[i], t_s[i]) for i in range(3))
    return p, n, (u, v), tangent


def _lookup(x, *, uv, uv1, duv, dtype):
    """Samples (..., C) of a material texture: a `TextureSlot` filtered by its footprint (its
    texture-coordinate set, KHR_texture_transform, mips, sampler), a plain array bilinearly."""
    if not isinstance(x, TextureSlot):
        return sample_texture(jnp.asarray(x, dtype), uv[0], uv[1])
    s = x.texcoord
    st = jnp.stack(uv if s == 0 or uv1 is None else uv1, -1)
    if duv is None:
        dx = dy = jnp.zeros_like(st)
    else:
        dx, dy = duv[s]
    if x.transform is not None:
        st, dx, dy = texture.apply_texture_transform(jnp.asarray(x.transform, dtype), st, dx, dy)
    return texture.sample(_cast_floats(x.texture, dtype), st, dx, dy)


def _apply_texture(objects, k, idx, uv, tangent, n, m: Material, dtype, coat_n=None, aniso_t=None, tangent_w=None, uv1=None, duv=None, alpha=None):
    """Override the gathered constant material (and normal) on the pixels of textured object k;
    with the extension textures (`scene.apply_extension_textures`) also the clear-coat normal and
    the anisotropy direction. Returns (material, normal, coat normal | None, anisotropy direction
    | None); the surface tangent itself is left as it is (normal maps are in its frame)."""
    u, v = uv
    base, metallic, rough, occ, emis = m.base_color, m.metallic, m.roughness, m.occlusion, m.emissive
    lookup = functools.partial(_lookup, uv=uv, uv1=uv1, duv=duv, dtype=dtype)
    if True:
        tm = objects[k].material
        f = tm.factors
        sel = idx == k
        if tm.base_color_texture is not None:
            tex4 = lookup(tm.base_color_texture)
            if alpha is not None and tex4.shape[-1] == 4 and getattr(objects[k], "alpha_mode", "OPAQUE") == "BLEND":
                alpha = jnp.where(sel, alpha * tex4[..., 3], alpha)
            tex = tex4[..., :3]
            base = jnp.where(sel[..., None], jnp.asarray(f.base_color, dtype) * tex, base)
        if tm.metallic_roughness_texture is not None:
            tex = lookup(tm.metallic_roughness_texture)[..., 1:3]
            rough = jnp.where(sel, jnp.asarray(f.roughness, dtype) * tex[..., 0], rough)
            metallic = jnp.where(sel, jnp.asarray(f.metallic, dtype) * tex[..., 1], metallic)
        if tm.occlusion_texture is not None:
            tex = lookup(tm.occlusion_texture)[..., :1]
            occ = jnp.where(sel, jnp.asarray(f.occlusion, dtype) * tex[..., 0], occ)
        if tm.emissive_texture is not None:
            tex = lookup(tm.emissive_texture)[..., :3]
            emis = jnp.where(sel[..., None], jnp.asarray(f.emissive, dtype) * tex, emis)
        if tm.extension_textures:
            m = evolve(m, base_color=base, metallic=metallic, roughness=rough, occlusion=occ, emissive=emis)
            m, cn, tan_k = apply_extension_textures(tm, m, u, v, sel, n, tangent, dtype=dtype, lookup=lookup)
            base, metallic, rough, occ, emis = m.base_color, m.metallic, m.roughness, m.occlusion, m.emissive
            if cn is not None:
                prev = n if coat_n is None else coat_n
                coat_n = tuple(jnp.where(sel, cn[i], prev[i]) for i in range(3))
            if tan_k is not None:  # the anisotropy direction (the normal map keeps the surface frame)
                prev = tangent if aniso_t is None else aniso_t
                aniso_t = tuple(jnp.where(sel, tan_k[i], prev[i]) for i in range(3))
        if tm.normal_texture is not None:
            tex = lookup(tm.normal_texture)[..., :3]
            s = jnp.asarray(tm.normal_scale, dtype)
            tx, ty, tz = (2.0 * tex[..., 0] - 1.0) * s, (2.0 * tex[..., 1] - 1.0) * s, 2.0 * tex[..., 2] - 1.0
            # Gram-Schmidt T against the normal, B = w (N x T) (glTF; w = +1 off meshes).
            tn = vdot(tangent, n)
            T = vnormalize(tuple(tangent[i] - tn * n[i] for i in range(3)))
            B = vcross(n, T)
            if tangent_w is not None:
                B = tuple(tangent_w * c for c in B)
            pert = vnormalize(tuple(T[i] * tx + B[i] * ty + n[i] * tz for i in range(3)))
            n = tuple(jnp.where(sel, pert[i], n[i]) for i in range(3))
    return evolve(m, base_color=base, metallic=metallic, roughness=rough, occlusion=occ, emissive=emis), n, coat_n, aniso_t, alpha


def _cast_floats(tree, dtype):
    """Floating leaves of a pytree cast to the render dtype (user inputs may be float64 under x64)."""
    return jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, dtype) if jnp.issubdtype(jnp.result_type(x), jnp.floating) else x, tree
    )


def _rotate_y(d, angle):
    """R_y(angle) applied to Vec3 d: (c x + s z, y, -s x + c z)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return (c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2])


def _shade_direct(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, g):
    """Direct lighting + ambient + emissive (H, W, 3), or None when the plan has none of them."""
    dtype = jnp.dtype(opts.dtype)
    pos, n, view, m = g["pos"], g["n"], g["view"], g["m"]
    if p_plan.direct:
        lights = _cast_floats(list(scene.lights), dtype)
        kw = _layer_kwargs(g, m, dtype) if p_plan.extensions else {}
        kw.pop("transmit_direction", None)
        if "vis" in g:
            kw["visibility"] = g["vis"]
        return shade_direct(pack3(pos), pack3(n), pack3(view), m, lights, model=opts.model, ambient=scene.ambient, smith=opts.smith, **kw)
    out = None
    if scene.ambient:
        out = scene.ambient * m.base_color * m.occlusion[..., None]
    if p_plan.emissive:
        e = emission_soa(m, g["n"], g["view"], g.get("coat_n"))
        out = e if out is None else out + e
    return out


def _mesh_arrays(scene: Scene, dtype):
    """The scene's meshes concatenated (`mesh.concat_meshes`), or None without meshes; with the
    device BVH of an `AccelScene` as "bvh"."""
    meshes = [ob for ob in scene.objects if isinstance(ob, Mesh)]
    if not meshes:
        return None
    arrays = concat_meshes(meshes, dtype)
    arrays["bvh"] = scene.accel if isinstance(scene, AccelScene) else None
    if isinstance(scene, AccelScene) and scene.refit:
        check_topology(scene.neighbours, arrays["triangles"].shape[0])
        if arrays["bvh"] is not None:
            arrays["bvh"] = refit_bvh(arrays["bvh"], arrays["positions"], arrays["triangles"]) if EXECUTION.traces_on_device() else None
    return arrays


class AccelScene(Scene):
    """A scene carrying the device BVH of its meshes (`mesh.device_accel`) as arrays of the pytree:
    `render` makes one where it runs as one program off the CPU, so that its opaque meshes are traced
    in the program rather than through a host callback (`execute.Execution.device_visibility`).
    refit: the meshes' positions may differ from those the BVH and the topology (`neighbours`)
    were made from (`execute.deformable`): the BVH is refitted to them in the program."""

    accel: Any = subtree(None)
    neighbours: Any = leaf(None, rank=2)
    refit: bool = static(False)


def _layer_kwargs(g, m: Material, dtype) -> dict:
    """The per-pixel inputs of the material extensions (world space) from the G-buffer."""
    kw = {}
    if "anisotropy" in m.extensions and g.get("tangent") is not None:
        kw["tangent"] = pack3(g.get("aniso_t", g["tangent"]))
    if "clearcoat" in m.extensions and g.get("coat_n") is not None:
        kw["coat_normal"] = pack3(g["coat_n"])
    dist, d_t = _volume_inputs(g, m, dtype)
    if dist is not None:
        kw["volume_distance"] = dist
        kw["transmit_direction"] = d_t
    return kw


def _env_frame(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, g):
    """(n, v, the extensions' inputs) of the G-buffer in the environment's frame."""
    dtype = jnp.dtype(opts.dtype)
    rot = -jnp.asarray(scene.environment.rotation, dtype)
    n_e = pack3(_rotate_y(g["n"], rot))
    v_e = pack3(_rotate_y(g["view"], rot))
    kw = {}
    if p_plan.extensions:
        # Vector inputs of the extensions in the environment's frame.
        kw = {k: (pack3(_rotate_y(unpack3(x), rot)) if k in ("tangent", "coat_normal", "transmit_direction") else x)
              for k, x in _layer_kwargs(g, g["m"], dtype).items()}
    return n_e, v_e, kw


def _shade_suns(scene: Scene, suns, p_plan: RenderPlan, opts: RenderOptions, g):
    """The suns split out of the environment, shaded as disc lights in its frame (emission is
    added once, by the direct stage), before the environment's intensity: (disc lighting, its
    multiple-scattering compensation or None), each (H, W, 3). suns: (LUT, disc lights, sheen
    albedo table or None).

    Staged, a program of its own (`_shade_suns_jit`), compiled beside the IBL stage's: the disc
    lobe is most of their code (1280x720 demo: about 0.9 of 1.35 s compiling them as one)."""
    lut, env_lights, sheen_lut = suns
    dtype = jnp.dtype(opts.dtype)
    m = g["m"]
    n_e, v_e, kw = _env_frame(scene, p_plan, opts, g)
    ls = _cast_floats(list(env_lights), dtype)
    dark = evolve(m, emissive=jnp.zeros_like(m.emissive))
    kw.pop("transmit_direction", None)
    if "vis_env" in g:
        kw["visibility"] = g["vis_env"]
    sheen_kw = {} if sheen_lut is None else {"sheen_lut": sheen_lut}
    disc = shade_direct(jnp.zeros_like(n_e), n_e, v_e, dark, ls, model=opts.model, smith=opts.smith, disc_lights=True, **kw, **sheen_kw)
    ms = disc_multiscatter(n_e, v_e, m, lut, ls, visibility=kw.get("visibility")) if opts.compensates else None
    return disc, ms


def _suns_inputs(assets):
    """What `_shade_suns` reads of the environment's assets."""
    _, _, lut, env_lights, sheen = assets
    return lut, env_lights, None if sheen is None else sheen[0]


def _shade_rest(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions, g, direct, suns=None):
    """direct + environment IBL on hits, background elsewhere -> (H, W, 3). suns: what
    `_shade_suns` returned for the plan's suns, or None to shade them here."""
    dtype = jnp.dtype(opts.dtype)
    m, hit, ray_dir = g["m"], g["hit"], g["ray"]
    shape = hit.shape
    out = direct
    env = scene.environment
    if p_plan.ibl:
        irr, pre, lut, _, sheen = assets
        n_e, v_e, kw = _env_frame(scene, p_plan, opts, g)
        sheen_kw = {} if sheen is None else {"sheen_lut": sheen[0], "charlie": sheen[1]}
        m_ibl = m if p_plan.ibl_visibility == "occlusion" else evolve(m, occlusion=jnp.ones_like(m.occlusion))
        if "behind" in g:
            ibl, tw = shade_ibl(n_e, v_e, m_ibl, irr, pre, lut, model=opts.model, multiscatter=opts.compensates, transmit_weight=True,
                                **kw, **sheen_kw)
        else:
            ibl = shade_ibl(n_e, v_e, m_ibl, irr, pre, lut, model=opts.model, multiscatter=opts.compensates, **kw, **sheen_kw)
        if "ibl_vis" in g:
            ibl = _visible_ibl(scene, pre, p_plan, opts, g, ibl, (n_e, v_e, m_ibl, lut, kw, sheen_kw))
        if p_plan.env_lights:
            disc, ms = suns if suns is not None else _shade_suns(scene, _suns_inputs(assets), p_plan, opts, g)
            ibl = ibl + disc
            if ms is not None:
                ibl = ibl + ms
        ibl = jnp.asarray(env.intensity, dtype) * ibl
        if "behind" in g:
            ibl = ibl + tw * _behind_change(scene, pre, p_plan, g["behind"], dtype)
        out = ibl if out is None else out + ibl
    if out is None:
        out = jnp.zeros(shape + (3,), dtype)
    if "unlit" in g:  # (KHR_materials_unlit: the colour, as the emission, and nothing else)
        out = jnp.where(g["unlit"][..., None], jnp.broadcast_to(m.emission(), shape + (3,)).astype(dtype), out)
    if p_plan.env_background:
        bg_dir = pack3(_rotate_y(ray_dir, -jnp.asarray(env.rotation, dtype)))
        bg = jnp.asarray(env.intensity, dtype) * env.radiance.sample(bg_dir.astype(env.radiance.dtype), 0.0).astype(dtype)
    else:
        bg = jnp.broadcast_to(jnp.asarray(scene.background, dtype), shape + (3,))
    return jnp.where(hit[..., None], out, bg)


def _geometry(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, offset, prim=None, light_shadows: bool = True):
    """G-buffer of the scene (dict of Vec3 / arrays), before textures. `prim`: the meshes'
    primitive per pixel when cast already; light_shadows=False leaves the lights' shadow rays
    (g["vis"]) to `_staged_shadows`."""
    dtype = jnp.dtype(opts.dtype)
    if scene.gbuffer is not None:
        gb = scene.gbuffer
        view = vnormalize(unpack3(jnp.asarray(gb.view, dtype)))
        return {
            "pos": unpack3(jnp.asarray(gb.position, dtype)),
            "n": vnormalize(unpack3(jnp.asarray(gb.normal, dtype))),
            "view": view,
            "m": jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), gb.material),
            "hit": gb.hit,
            "ray": tuple(-c for c in view),
        }
    o_px, d_px = _pass_rays(scene, p_plan, dtype, offset)
    o, d = unpack3(o_px), unpack3(d_px)
    objects = scene.objects
    ext = p_plan.extensions
    need_uv = bool(p_plan.textured) or "anisotropy" in ext
    analytic = [k for k, ob in enumerate(objects) if not isinstance(ob, Mesh)]
    meshes = [k for k, ob in enumerate(objects) if isinstance(ob, Mesh)]
    tw = None
    if analytic:
        sub = [objects[k] for k in analytic]
        t, idx, hit = _cast(sub, o, d, dtype)
        pos, n, uv, tangent = _surface(sub, o, d, t, idx, dtype, need_uv)
        n_an = n
        idx = jnp.asarray(analytic, jnp.int32)[idx] if len(analytic) < len(objects) else idx
    if meshes:
        arrays = _mesh_arrays(scene, dtype)
        if prim is None:  # (BLEND layers pass the layer's primitives, cast once for all layers)
            prim = cast(arrays, o_px, d_px)
        ddir, dorig = _pass_differentials(scene.camera, offset, d, dtype) if need_uv else (None, None)
        ms = mesh_surface(arrays, prim, o, d, need_uv=need_uv, ddir=ddir, dorig=dorig)
        on_mesh = prim >= 0
        idx_m = jnp.asarray(meshes, jnp.int32)[ms["object"]]
        if analytic:
            on_mesh = on_mesh & (~hit | (ms["t"] < t))
            pick = lambda a, b: tuple(jnp.where(on_mesh, a[i], b[i]) for i in range(len(a)))
            t, idx, hit = jnp.where(on_mesh, ms["t"], t), jnp.where(on_mesh, idx_m, idx), hit | on_mesh
            pos, n = pick(ms["pos"], pos), pick(ms["n"], n)
            if need_uv:
                uv, tangent = pick(ms["uv"], uv), pick(ms["tangent"], tangent)
                tw = jnp.where(on_mesh, ms["tangent_w"], 1.0)
                uv1 = pick(ms["uv1"], uv)
                duv = tuple(tuple(jnp.where(on_mesh[..., None], a, 0.0) for a in ms["duv"][s]) for s in (0, 1))
        else:
            t, idx, hit = ms["t"], idx_m, on_mesh
            pos, n = ms["pos"], ms["n"]
            if need_uv:
                uv, tangent, tw, uv1, duv = ms["uv"], ms["tangent"], ms["tangent_w"], ms["uv1"], ms["duv"]
    if p_plan.shadows or p_plan.transmission_depth or p_plan.ibl_samples:
        # The geometric normal (before normal maps): shadow rays leave the surface along it.
        ng = n if not meshes else (ms["ng"] if not analytic else tuple(jnp.where(on_mesh, ms["ng"][i], n_an[i]) for i in range(3)))
    m = _gather_material(_stack_materials(objects, dtype, ext), idx)
    # The pixels of unlit meshes (`Mesh.unlit`), or None: `_shade_rest` shows their emission alone.
    unlit = (jnp.asarray([isinstance(ob, Mesh) and ob.unlit for ob in objects])[idx] & hit
             if any(isinstance(ob, Mesh) and ob.unlit for ob in objects) else None)
    if meshes and "color" in ms:
        # COLOR_0 multiplies the base colour (glTF); 1 on other objects. On an unlit mesh, whose
        # colour is its emission, it multiplies the emission.
        rgb = jnp.where(on_mesh[..., None], ms["color"][..., :3], 1.0)
        m = evolve(m, base_color=m.base_color * rgb)
        if unlit is not None:
            m = evolve(m, emissive=m.emissive * jnp.where(unlit[..., None], rgb, 1.0))
    g = {"pos": pos, "n": n, "view": tuple(-c for c in d), "m": m, "hit": hit, "ray": d, "t": t, "idx": idx}
    if unlit is not None:
        g["unlit"] = unlit
    if meshes:
        g["prim"] = jnp.where(on_mesh, prim, -1)
    if p_plan.blend_layers > 1:
        # Coverage of the layer: a BLEND mesh's alpha factor x COLOR_0's A (the base colour
        # texture's A multiplies it in the texture stage); 1 on everything else.
        blend_k = jnp.asarray([isinstance(ob, Mesh) and ob.alpha_mode == "BLEND" for ob in objects])[idx]
        a = jnp.stack([jnp.asarray(ob.alpha if isinstance(ob, Mesh) else 1.0, dtype) for ob in objects])[idx]
        if "color" in ms:
            a = a * jnp.where(on_mesh, ms["color"][..., 3], 1.0)
        g["alpha"] = jnp.where(hit & blend_k, a, 1.0)
    if p_plan.shadows or p_plan.transmission_depth or p_plan.ibl_samples:
        g["ng"] = ng
    if p_plan.shadows:
        if p_plan.direct and light_shadows:
            lights = _cast_floats(list(scene.lights), dtype)
            g["vis"] = shadow_visibility(objects, arrays if meshes else None, pos, ng, lights, dtype)
    if need_uv:
        g.update(idx=idx, uv=uv, tangent=tangent)
        if tw is not None:
            g.update(tangent_w=tw, uv1=uv1, duv=duv)
    if "volume" in ext:
        # Sphere radius per pixel (0 on planes): the volume's path is the sphere's chord.
        radii = jnp.asarray([0.0 if isinstance(ob, Plane) else 1.0 for ob in objects], dtype)
        rad = jnp.stack([jnp.asarray(ob.radius if isinstance(ob, Sphere) else 0.0, dtype) for ob in objects]) * radii
        g["radius"] = rad[idx] if len(objects) > 1 else jnp.broadcast_to(rad[0], idx.shape)
    return g


class Rays(NamedTuple):
    """Rays a pass casts in place of the camera's (`offset` of the stages): the transmitted rays
    (`_transmit_rays`). o, d: (..., 3) origins and unit directions; diff: (..., 4, 3) their ray
    differentials dD/dx, dD/dy, dO/dx, dO/dy (texture filtering); key: (...) uint32, the ray's
    index hashed (the next level's samples are drawn from it)."""

    o: Any
    d: Any
    diff: Any
    key: Any


def _pass_rays(scene: Scene, p_plan: RenderPlan, dtype, offset):
    """(origins, directions) (..., 3) of a pass: the camera's primary rays at sub-pixel `offset`,
    or the given `Rays`."""
    if isinstance(offset, Rays):
        return offset.o.astype(dtype), offset.d.astype(dtype)
    return primary_rays(scene.camera, dtype=dtype, offset=offset, rows=p_plan.band_rows)


def _pass_differentials(cam, offset, d, dtype):
    """`_ray_differentials` of a pass's rays: the camera's, or those the `Rays` carry."""
    if isinstance(offset, Rays):
        df = offset.diff.astype(dtype)
        return (unpack3(df[..., 0, :]), unpack3(df[..., 1, :])), (unpack3(df[..., 2, :]), unpack3(df[..., 3, :]))
    return _ray_differentials(cam, d, dtype)


def _ray_differentials(cam, d, dtype):
    """The camera's ray differentials per pixel (Igehy 1999): ((dD/dx, dD/dy), (dO/dx, dO/dy)) of
    the unit ray directions d and the origins (Vec3s; None where they do not move).

    Perspective: the origin is fixed; the unnormalised direction f + x r + y u moves by
    (2 tan(fov/2)/H) r per column and -(2 tan(fov/2)/H) u per row, and has length 1/(D.f);
    dD = (dd - D (D.dd)) / |d|. Orthographic: the direction is fixed and the origin moves by
    (2 ymag/H) r per column and -(2 ymag/H) u per row."""
    from .scene import camera_basis

    _, f, r, u = camera_basis(cam, dtype)
    if cam.projection == "orthographic":
        k = 2.0 * jnp.asarray(cam.ymag, dtype) / cam.height
        zero = tuple(jnp.zeros_like(c) for c in d)
        return (zero, zero), (tuple(k * c for c in r), tuple(-k * c for c in u))
    k = 2.0 * jnp.tan(jnp.deg2rad(jnp.asarray(cam.fov_y_deg, dtype)) / 2) / cam.height
    inv_len = vdot(d, f)  # 1/|d|
    out = []
    for dd in (tuple(k * c for c in r), tuple(-k * c for c in u)):
        dn = vdot(d, dd)
        out.append(tuple((dd[i] - d[i] * dn) * inv_len for i in range(3)))
    return tuple(out), None


def _volume_inputs(g, m: Material, dtype):
    """(path length in the medium, direction the transmitted environment light comes from) per
    pixel for the volume extension, in world space; (None, None) without it.

    Spheres: the refracted ray t = refract(-v, n, 1/ior) crosses the chord 2 R cos(theta_t) and
    leaves through the far side, where it refracts back with the same angle (no total internal
    reflection on a sphere): the exact exit direction is refract(t, -n', ior) with
    n' = n + 2 cos(theta_t) t. Planes (R = 0): a slab of the material's thickness, whose exit
    direction is -v."""
    if "radius" not in g or "volume" not in m.extensions:
        return None, None
    from ..ibl.layered_ibl import refract

    mc = m.complete(("ior", "volume"))
    n = pack3(g["n"])
    v = pack3(g["view"])
    R = g["radius"]
    ior = jnp.maximum(mc.ior, 1.0)
    t_in = refract(-v, n, 1.0 / ior)
    cos_t = -jnp.sum(t_in * n, -1)
    chord = 2.0 * R * cos_t
    n_far = n + (2.0 * cos_t)[..., None] * t_in
    n_far = n_far / jnp.maximum(jnp.linalg.norm(n_far, axis=-1, keepdims=True), small_sq(dtype))
    d_out = refract(t_in, -n_far, ior)
    sphere = R > 0
    dist = jnp.where(sphere, chord, mc.thickness)
    d_t = jnp.where(sphere[..., None], d_out, -v)
    return dist, d_t


def _ibl_directions(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, g, offset):
    """(K, ..., 3) world directions of the IBL visibility rays of a pass's pixels, K = the plan's
    ibl_samples: in turn cosine-distributed about the shading normal (even k) and reflected about
    GGX visible normals of the view at the pixel's roughness (odd k; `sampling.sample_ggx_vndf`),
    from a K-point Hammersley set rotated per pixel by its hashed key (deterministic)."""
    from ..shading.brdf_terms import MIN_ROUGHNESS
    from ..shading.sampling import hammersley, sample_cosine, sample_ggx_vndf, tangent_frame

    dtype = jnp.dtype(opts.dtype)
    K = p_plan.ibl_samples
    n, v = pack3(g["n"]), pack3(g["view"])
    shape = g["hit"].shape
    key = offset.key if isinstance(offset, Rays) else _pixel_keys(shape, offset)
    rot = jnp.stack([_unit_float(_mix32(key ^ jnp.uint32(0x2545F491)), dtype), _unit_float(_mix32(key ^ jnp.uint32(0x9E3779B9)), dtype)], -1)
    xi = jnp.mod(hammersley(K, dtype).reshape((K,) + (1,) * len(shape) + (2,)) + rot, 1.0)
    t, b = tangent_frame(n)
    r = jnp.maximum(jnp.broadcast_to(jnp.clip(g["m"].roughness, 0.0, 1.0), shape), MIN_ROUGHNESS)
    v_loc = jnp.stack([jnp.sum(v * t, -1), jnp.sum(v * b, -1), jnp.maximum(jnp.sum(v * n, -1), 1e-4)], -1)
    out = []
    for k in range(K):
        if k % 2 == 0:
            loc = sample_cosine(xi[k])
            out.append(loc[..., 0:1] * t + loc[..., 1:2] * b + loc[..., 2:3] * n)
        else:
            h = sample_ggx_vndf(v_loc, xi[k], r * r)
            h = h[..., 0:1] * t + h[..., 1:2] * b + h[..., 2:3] * n
            out.append(2.0 * jnp.sum(v * h, -1, keepdims=True) * h - v)
    return jnp.stack(out)


def _ibl_segments(scene: Scene, opts: RenderOptions, pos, ng, dirs):
    """`_light_segments` of the IBL visibility rays (directions (K, ..., 3))."""
    dtype = jnp.dtype(opts.dtype)
    return shadow_segments(scene.objects, pos, ng, [unpack3(dirs[k]) for k in range(dirs.shape[0])], dtype, directions_only=True)


def _ibl_visibility(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, g, offset, staged: bool):
    """{"d": (K, ..., 3) directions, "vis": (K, ..., C) visibility (C = 1, or 3 through transmissive
    surfaces)} of the IBL visibility rays (`_ibl_directions`), traced like the lights' shadow rays."""
    dirs = (_ibl_directions_jit if staged else _ibl_directions)(_lean(_stage_view(scene)) if staged else scene, p_plan, opts, g, offset)
    if staged:
        vis = _staged_shadows(_ibl_segments_jit, _stage_view(scene), opts, g["pos"], g["ng"], dirs, hit=g["hit"])
    else:
        dtype = jnp.dtype(opts.dtype)
        vis = shadow_visibility(scene.objects, _mesh_arrays(scene, dtype), g["pos"], g["ng"],
                                [unpack3(dirs[k]) for k in range(dirs.shape[0])], dtype, directions_only=True)
    vis = vis if vis.ndim == len(g["hit"].shape) + 2 else vis[..., None]  # (..., K, C)
    return {"d": dirs, "vis": jnp.moveaxis(vis, -2, 0)}


def _visible_ibl(scene: Scene, pre, p_plan: RenderPlan, opts: RenderOptions, g, ibl, inputs):
    """The IBL term with the visibility rung of the plan applied (`RenderOptions.ibl_visibility`).

    "ratio": ibl x sum_k w_k V_k / sum_k w_k, w_k = f(v, l_k) (n.l_k)+ L(l_k) / p(l_k), L the
    environment (the prefiltered map's level 0 along the ray, times the intensity: the residual the
    split sum shades), p the rays' mixture density (the balance of cosine and GGX-visible-normal
    sampling, half each; cosine alone for one ray). "ao": the diffuse part (the split sum less its
    specular lobes, `shade_ibl` without irradiance) times the cosine rays' visible fraction, the
    specular part times the lobe rays' (over the rays above the surface)."""
    dtype = jnp.dtype(opts.dtype)
    n_e, v_e, m, lut, kw, sheen_kw = inputs
    K = p_plan.ibl_samples
    b = g["ibl_vis"]
    dirs, vis = b["d"], b["vis"]
    n = pack3(g["n"])
    nl = jnp.sum(dirs * n, -1)  # (K, ...)
    above = (nl > 0).astype(dtype)[..., None]
    if p_plan.ibl_visibility == "ao":
        cos_k = [k for k in range(K) if k % 2 == 0]
        lobe_k = [k for k in range(K) if k % 2 == 1] or cos_k

        def frac(ks):
            num = sum(vis[k] * above[k] for k in ks)
            den = sum(above[k] for k in ks)
            return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 1.0)

        spec = shade_ibl(n_e, v_e, m, None, pre, lut, model=opts.model, multiscatter=False,
                         **{k: x for k, x in kw.items() if k != "transmit_direction"}, **sheen_kw)
        spec = jnp.minimum(spec, ibl)
        return frac(lobe_k) * spec + frac(cos_k) * (ibl - spec)
    w = b["w"]  # (K, ..., 3) (`_ratio_weights`)
    num = jnp.sum(w * vis, 0)
    den = jnp.sum(w, 0)
    ratio = jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 1.0)
    return ibl * ratio


def _ratio_weights(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, g, dirs, pre):
    """(K, ..., 3) the ratio estimator's weights f(v, l_k) (n.l_k)+ L(l_k) / p(l_k) of the IBL
    visibility rays (`_visible_ibl`): a stage of its own (fused into the IBL stage, XLA:CPU
    evaluated the K BRDFs there several times over)."""
    from ..shading.brdf_terms import MIN_ROUGHNESS
    from ..shading.layered import brdf
    from ..shading.sampling import pdf_cosine, pdf_ggx_vndf, pdf_reflect

    dtype = jnp.dtype(opts.dtype)
    K = dirs.shape[0]
    n, v = pack3(g["n"]), pack3(g["view"])
    env = scene.environment
    rot = -jnp.asarray(env.rotation, dtype)
    r = jnp.maximum(jnp.clip(g["m"].roughness, 0.0, 1.0), MIN_ROUGHNESS)
    a = r * r
    nv = jnp.maximum(jnp.sum(n * v, -1), 1e-4)
    bk = {k: x for k, x in _layer_kwargs(g, g["m"], dtype).items() if k in ("tangent", "coat_normal")}
    out = []
    for k in range(K):
        lk = dirs[k]
        nl = jnp.maximum(jnp.sum(lk * n, -1), 0.0)
        h = safe_normalize(lk + v)
        p_cos = pdf_cosine(nl)
        p_ggx = pdf_reflect(pdf_ggx_vndf(nv, jnp.sum(n * h, -1), jnp.sum(v * h, -1), a), jnp.sum(v * h, -1))
        p = p_cos if K == 1 else 0.5 * (p_cos + p_ggx)
        f = brdf(n, v, lk, g["m"], **bk)
        l_env = pre.sample(pack3(_rotate_y(unpack3(lk), rot)), 0.0).astype(dtype)
        w = jnp.where((p > 0)[..., None], f * nl[..., None] * l_env / jnp.where(p > 0, p, 1.0)[..., None], 0.0)
        out.append(jnp.where(jnp.isfinite(w), w, 0.0))
    return jnp.stack(out)


def _mix32(x):
    """A 32-bit integer hash (uint32 in and out; Wellons' lowbias32)."""
    x = x.astype(jnp.uint32)
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x7FEB352D)
    x = x ^ (x >> 15)
    x = x * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def _pixel_keys(shape, offset):
    """uint32 keys of a camera pass's pixels: the pixel's index (the band's rows counted from its
    first row) and the sub-pixel offset, hashed."""
    H, W = shape
    row0 = offset[2].astype(jnp.int32) if offset.shape[0] > 2 else 0
    idx = (jnp.arange(H, dtype=jnp.int32)[:, None] + row0) * W + jnp.arange(W, dtype=jnp.int32)[None, :]
    sub = (jnp.floor(offset[0] * 4096.0).astype(jnp.uint32) * jnp.uint32(4096) + jnp.floor(offset[1] * 4096.0).astype(jnp.uint32))
    return _mix32(idx.astype(jnp.uint32) ^ _mix32(sub + jnp.uint32(0x9E3779B9)))


def _unit_float(key, dtype):
    return (key >> jnp.uint32(8)).astype(dtype) * (2.0**-24)


def _transmit_rays(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, g, offset):
    """The transmitted rays of a pass's surfaces: (`Rays` of shape (K * rows, ...), weights (K * rows, ...)),
    K = the plan's transmission_samples, each sample's rays stacked along the first axis.

    Each ray starts on the far side of the surface (`visibility.offset_ray_origin` along -ng) and
    leaves along a direction drawn from the lobe the split sum prefilters for the transmission:
    GGX half vectors about the lobe's centre d_c (n = v = d_c; `sampling.sample_ggx_h`) at the
    lobe's roughness, mirrored about them, weighted by their cosine to d_c (the prefilter's
    weight). The centre and roughness are the IBL term's (`layered_ibl`): thin walls d_c = the
    ray's own direction at the base roughness; a volume sphere (thickness > 0) leaves from the exit
    point of its refracted chord along the exact exit direction, a volume slab (planes, meshes)
    along the ray, both at the refracted lobe's roughness. The samples are a K-point Hammersley set
    rotated per ray by its hashed key (Cranley-Patterson): deterministic, stratified per pixel.
    Weight 0 where the pixel has no transmission (or no hit)."""
    from ..ibl.layered_ibl import refract
    from ..shading.layered import refractive_index
    from ..shading.sampling import hammersley, sample_ggx_h, tangent_frame
    from .visibility import offset_ray_origin

    dtype = jnp.dtype(opts.dtype)
    K = p_plan.transmission_samples
    m = g["m"]
    ext = m.extensions
    mc = m.complete(("transmission", "ior", "volume") if "volume" in ext else ("transmission",))
    n, ng, pos, d = pack3(g["n"]), pack3(g["ng"]), pack3(g["pos"]), pack3(g["ray"])
    shape = g["hit"].shape
    tr = jnp.clip(mc.transmission, 0.0, 1.0) * (1.0 - jnp.clip(mc.metallic, 0.0, 1.0))
    active = g["hit"] & (jnp.broadcast_to(tr, shape) > 0)
    r = jnp.broadcast_to(jnp.clip(mc.roughness, 0.0, 1.0), shape)
    centre = d
    start = pos
    leave = -ng  # (ng faces the viewer)
    rt = r
    if "volume" in ext:
        thick = jnp.broadcast_to(mc.thickness > 0, shape)
        ior = jnp.broadcast_to(jnp.maximum(refractive_index(mc), 1.0), shape)
        rt = jnp.where(thick, r * safe_sqrt(0.75 * (1.0 - 1.0 / ior)), r)  # (sqrt'(0) at ior 1: safe_sqrt)
        if "radius" in g:
            # The sphere's exit point and direction (`_volume_inputs`: the refracted chord).
            t_in = refract(d, n, 1.0 / ior)
            cos_t = -jnp.sum(t_in * n, -1)
            exit_p = pos + (2.0 * g["radius"] * cos_t)[..., None] * t_in
            n_far = n + (2.0 * cos_t)[..., None] * t_in
            n_far = n_far / jnp.maximum(jnp.linalg.norm(n_far, axis=-1, keepdims=True), small_sq(dtype))
            d_out = refract(t_in, -n_far, ior)
            sphere = thick & (g["radius"] > 0) & (jnp.sum(d_out * d_out, -1) > 0)
            centre = jnp.where(sphere[..., None], d_out, centre)
            start = jnp.where(sphere[..., None], exit_p, start)
            leave = jnp.where(sphere[..., None], n_far, leave)
    origin = offset_ray_origin(start.astype(jnp.float32), safe_normalize(leave).astype(jnp.float32)).astype(dtype)
    # Ray differentials carried to the surface (dO' = dO + t dD; the directions' unchanged).
    if isinstance(offset, Rays):
        df = offset.diff.astype(dtype)
        key = offset.key
    else:
        (dx, dy), dorig = _ray_differentials(scene.camera, g["ray"], dtype)
        zero = jnp.zeros(shape + (3,), dtype)
        o_x, o_y = (zero, zero) if dorig is None else (pack3(dorig[0]) + zero, pack3(dorig[1]) + zero)
        df = jnp.stack([pack3(dx) + zero, pack3(dy) + zero, o_x, o_y], -2)
        key = _pixel_keys(shape, offset)
    t = g["t"][..., None]
    df = jnp.stack([df[..., 0, :], df[..., 1, :], df[..., 2, :] + t * df[..., 0, :], df[..., 3, :] + t * df[..., 1, :]], -2)
    # K stratified lobe samples per ray.
    xi = hammersley(K, dtype)  # (K, 2)
    rot = jnp.stack([_unit_float(_mix32(key ^ jnp.uint32(0x68E31DA4)), dtype), _unit_float(_mix32(key ^ jnp.uint32(0xB5297A4D)), dtype)], -1)
    u = jnp.mod(xi.reshape((K,) + (1,) * len(shape) + (2,)) + rot, 1.0)
    h_local = sample_ggx_h(u, (rt * rt)[None])  # (K, ..., 3)
    tb = tangent_frame(jnp.broadcast_to(centre, shape + (3,)))
    h = h_local[..., 0:1] * tb[0] + h_local[..., 1:2] * tb[1] + h_local[..., 2:3] * centre
    cos_h = jnp.sum(centre * h, -1, keepdims=True)
    w_dir = 2.0 * cos_h * h - centre
    w = jnp.where(active, jnp.maximum(jnp.sum(w_dir * centre, -1), 0.0), 0.0)
    child = _mix32(key[None] * jnp.uint32(K) + jnp.arange(K, dtype=jnp.uint32).reshape((K,) + (1,) * len(shape)) + jnp.uint32(0x9E3779B9))
    flat = lambda x: x.reshape((K * shape[0],) + x.shape[2:])  # noqa: E731
    rays = Rays(o=flat(jnp.broadcast_to(origin, (K,) + origin.shape)), d=flat(w_dir), diff=flat(jnp.broadcast_to(df, (K,) + df.shape)),
                key=flat(child))
    return rays, flat(w)


def _transmitted(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions, g, offset, staged: bool):
    """What the transmitted rays of a pass's surfaces see (`_transmit_rays`): the scene's surfaces
    shaded by the same stages one level deeper (that level's transmission traced again while levels
    are left, one ray per ray), as {"L": radiance, "hit", "d": directions, "w": weights}, each (K * rows, ...)."""
    if staged and is_ahead():
        # (the rays' count is known only once they are cast: the look-ahead stops here, before
        # compiling programs for buffers no pass would use)
        from .._program_cache import NotAhead

        raise NotAhead("the transmitted rays are counted when cast")
    rays, w = (_transmit_rays_jit if staged else _transmit_rays)(_lean(_stage_view(scene)) if staged else scene, p_plan, opts, g, offset)
    # Deeper levels continue each ray with one ray of its own (a path per sample: K rays per level,
    # not K^depth).
    child = dataclasses.replace(p_plan, transmission_depth=p_plan.transmission_depth - 1, transmission_samples=1, band_rows=0)
    if staged and not _traced((rays, w)):
        # Only the rays of transmissive pixels are cast and shaded, gathered into a buffer of a
        # power-of-two size (a few programs serve every count); none: nothing is traced.
        active = np.flatnonzero(np.asarray(w).reshape(-1) > 0)
        if active.size == 0:
            return None
        size = max(_MIN_TRANSMIT_BUFFER, 1 << int(active.size - 1).bit_length())
        idx = jax.device_put(np.concatenate([active, np.full(size - active.size, active[0])]).astype(np.int32))
        sub = _gather_rays_jit(rays, idx)
        c, hit = _render_pass(scene, assets, child, opts, sub, staged, with_hit=True)
        c, hit = _scatter_jit(c, hit, idx, jnp.int32(active.size), w.shape)
        return {"L": c, "hit": hit, "d": rays.d, "w": w}
    c, hit = _render_pass(scene, assets, child, opts, rays, staged, with_hit=True)
    return {"L": c, "hit": hit, "d": rays.d, "w": w}


#: Smallest buffer of transmitted rays a staged pass gathers (`_transmitted`).
_MIN_TRANSMIT_BUFFER = 1024


def _gather_rays(rays: Rays, idx):
    return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[len(rays.key.shape):])[idx], rays)


def _scatter(c, hit, idx, n, shape):
    """The gathered rays' (radiance, hit) back in their places (..., 3), (...); 0 / False elsewhere
    (only the first n entries of idx are rays: the rest repeat the first)."""
    total = int(np.prod(shape))
    keep = jnp.arange(idx.shape[0]) < n
    L = jnp.zeros((total, 3), c.dtype).at[idx].add(jnp.where(keep[:, None], c, 0.0))
    h = jnp.zeros((total,), bool).at[idx].max(keep & hit)
    return L.reshape(tuple(shape) + (3,)), h.reshape(shape)


_gather_rays_jit = cached_jit(_gather_rays)
_scatter_jit = cached_jit(_scatter, static_argnums=(4,))  # (the count is an argument: no program per count)


def _behind_change(scene: Scene, pre, p_plan: RenderPlan, b, dtype):
    """(..., 3) what the scene changes in the transmission lobe's incoming radiance: the mean over
    the K rays (weighted) of (radiance of the surface hit - the environment's along the ray), 0 for
    rays that escape: added to the prefiltered environment's lobe value, it is the lobe integral of
    the scene's radiance (a control variate: no noise where nothing stands behind)."""
    K = p_plan.transmission_samples
    env = scene.environment
    rot = -jnp.asarray(env.rotation, dtype)
    d_env = pack3(_rotate_y(unpack3(b["d"]), rot))
    l_env = jnp.asarray(env.intensity, dtype) * pre.sample(d_env, 0.0).astype(dtype)
    w = jnp.where(b["hit"], b["w"], 0.0)[..., None]
    delta = w * (b["L"] - l_env)
    rows = b["L"].shape[0] // K
    delta = delta.reshape((K, rows) + delta.shape[1:]).sum(0)
    wsum = b["w"][..., None].reshape((K, rows) + b["w"].shape[1:] + (1,)).sum(0)
    return jnp.where(wsum > 0, delta / jnp.where(wsum > 0, wsum, 1.0), 0.0)


def _texture(scene: Scene, k: int, opts: RenderOptions, g):
    m, n, coat_n, aniso_t, alpha = _apply_texture(
        scene.objects, k, g["idx"], g["uv"], g["tangent"], g["n"], g["m"], jnp.dtype(opts.dtype), g.get("coat_n"),
        g.get("aniso_t"), g.get("tangent_w"), g.get("uv1"), g.get("duv"), g.get("alpha"),
    )
    out = {**g, "m": m, "n": n}
    if alpha is not None:
        out["alpha"] = alpha
    if coat_n is not None:
        out["coat_n"] = coat_n
    if aniso_t is not None:
        out["aniso_t"] = aniso_t
    return out


def _render_pass(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions, offset, staged: bool = False, with_hit: bool = False,
                 with_surface: bool = False):
    """One sample per pixel at sub-pixel `offset`.

    staged=True runs the stages -- geometry, each textured object, direct lighting, IBL +
    background -- as separate compiled programs (what `render` does outside transformations).
    XLA:CPU otherwise fuses producers into every consumer and recomputes them there (each
    light, lookup and colour channel): measured 2.7x slower for direct + IBL at 1080p and 1000x
    slower with two normal-mapped objects; `lax.optimization_barrier` does not prevent it (it is
    expanded away before fusion). Under an outer jit/vmap the stages inline into one program.
    """
    if staged:
        p_plan = p_plan.for_stages()
    if p_plan.blend_layers > 1:
        return _blended_pass(scene, assets, p_plan, opts, offset, staged, with_hit=with_hit, with_surface=with_surface)
    g = staged_geometry(scene, p_plan, opts, offset) if staged else _geometry(scene, p_plan, opts, offset)
    c = _shade_pass(scene, assets, p_plan, opts, g, staged, rays=offset)
    if with_surface:
        return c, _surface_ids(g)
    return (c, g["hit"]) if with_hit else c


def _surface_ids(g) -> dict:
    """What `edges.antialias_pass` reads of a pass's G-buffer: hit, object index, distance, and the
    meshes' triangle (with meshes)."""
    out = {"hit": g["hit"], "idx": g["idx"], "t": g["t"]}
    if "prim" in g:
        out["prim"] = g["prim"]
    return out


def staged_geometry(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, offset, *, light_shadows: bool = True):
    """The geometry stage as compiled programs (outside transformations): with meshes, their
    primary rays cast by the host ray engine first (`_host_prims`, `_mesh_geometry`).
    light_shadows=False leaves the lights' shadow rays out (the G-buffer and AOVs do not need them)."""
    p_plan = p_plan.for_stages()
    if scene.gbuffer is None and any(isinstance(ob, Mesh) for ob in scene.objects):
        prim = _host_prims(scene, p_plan, opts, offset, 1)
        return _mesh_geometry(scene, p_plan, opts, offset, prim, light_shadows=light_shadows)
    return _geometry_jit(_stage_view(scene), p_plan, opts, offset, light_shadows=light_shadows)


def _mesh_geometry(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, offset, prim, *, light_shadows: bool = True):
    """The staged geometry of a scene with meshes, `prim` cast already: the geometry program (a
    large one, measured 3.9 s to compile at 1 M triangles) holds no call back to the host, so it is
    kept on disk, and the lights' shadow rays go to the host ray engine between stored programs
    (`_staged_shadows`): a program holding a callback would be compiled again in every process (its
    cache key names the callback)."""
    scene = _stage_view(scene)
    g = _geometry_jit(scene, p_plan, opts, offset, prim, light_shadows=False)
    if light_shadows and p_plan.shadows and p_plan.direct:
        # (the shading normal is final here without normal maps)
        facing = g["n"] if _culls_facing(p_plan) and not p_plan.normal_maps else None
        g = {**g, "vis": _staged_shadows(_light_segments_jit, scene, opts, g["pos"], g["ng"], facing, hit=g["hit"])}
    return g


#: Material extensions under which a light can add something where the shading normal faces away
#: from it: transmission (and its volume), and a clear coat (whose normal can be a texture of its own).
_LIT_FROM_BELOW = frozenset({"transmission", "volume", "clearcoat"})


def _culls_facing(p_plan: RenderPlan) -> bool:
    """Whether a light adds exactly 0 wherever the shading normal faces away from it (the core BRDF
    and the other extensions are 0 below the horizon; a disc's cap factor once the whole disc is
    below it), so that the meshes' shadow rays from there are left out
    (`shadows.shadow_segments(normal=)`)."""
    return not (_LIT_FROM_BELOW & set(p_plan.extensions))


def _light_segments(scene: Scene, opts: RenderOptions, pos, ng, facing=None):
    """The lights' shadow segments from the surface points (`shadows.shadow_segments`); facing:
    the shading normal, where the rays of points facing away from a light may be left out."""
    dtype = jnp.dtype(opts.dtype)
    lights = _cast_floats(list(scene.lights), dtype)
    return shadow_segments(scene.objects, pos, ng, lights, dtype, normal=facing)


def _sun_segments(scene: Scene, opts: RenderOptions, pos, ng, env_lights, facing=None):
    """`_light_segments` of the suns split out of the environment (`_sun_shadows`)."""
    dtype = jnp.dtype(opts.dtype)
    radii = [jnp.sin(jnp.asarray(s.angular_radius, dtype)) for s in _cast_floats(list(env_lights), dtype)]
    return shadow_segments(scene.objects, pos, ng, _sun_directions(scene, env_lights, dtype), dtype, directions_only=True,
                           normal=facing, sin_radii=radii)


def _host_arrays(meshes: tuple, dtype_name: str):
    """What the host ray engine reads of the meshes (`mesh.concat_meshes`): float32 positions,
    triangles, back-face culling, and the MASK / BLEND and transmission tables (None without)."""
    arrays = concat_meshes(list(meshes), jnp.dtype(dtype_name))
    return {"positions": arrays["positions"].astype(jnp.float32), "triangles": arrays["triangles"],
            "cull_back": arrays["cull_back"], "alpha": arrays["alpha"], "transmit": arrays["transmit"]}


_host_arrays_jit = cached_jit(_host_arrays, static_argnums=(1,))

#: `scene_host_arrays`' latest result: [(key, what the leaves were, NumPy arrays)], one tuple
#: replaced whole (renders on several threads read a consistent entry).
_HOST_ARRAYS: list = []


def scene_host_arrays(scene: Scene, dtype):
    """`_host_arrays` of the scene's meshes as NumPy arrays, made once per mesh content: a render
    loop, a second frame and each light's shadow rays read the same arrays (no program, copy or
    hashing of the geometry per query). None without meshes, or where a mesh's leaf is traced.

    Kept by the identity of the meshes' leaves: a Mesh holds read-only NumPy arrays or JAX arrays
    (both immutable, `mesh._frozen`), so the same objects are the same content; Python numbers
    are compared by value."""
    meshes = tuple(ob for ob in scene.objects if isinstance(ob, Mesh))
    if not meshes:
        return None
    leaves, treedef = jax.tree_util.tree_flatten(meshes)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return None
    name = jnp.dtype(dtype).name
    is_array = [isinstance(x, (np.ndarray, jax.Array)) for x in leaves]
    if any(a and isinstance(x, np.ndarray) and x.flags.writeable for a, x in zip(is_array, leaves, strict=True)):
        kept = None  # a writeable NumPy leaf (its content can change in place): not remembered
    else:
        kept = [weakref.ref(x) if a else x for a, x in zip(is_array, leaves, strict=True)]
    key = (treedef, name, tuple(id(x) if a else None for a, x in zip(is_array, leaves, strict=True)))
    entry = _HOST_ARRAYS[0] if _HOST_ARRAYS else None
    if kept is not None and entry is not None and entry[0] == key and all(
        (k() is x) if a else _same_value(k, x) for a, k, x in zip(is_array, entry[1], leaves, strict=True)
    ):
        return entry[2]
    if all(ob.alpha_mode == "OPAQUE" and not transmits(ob.material) for ob in meshes):
        out = _host_arrays_opaque(meshes)
    else:
        out = jax.tree_util.tree_map(np.asarray, _host_arrays_jit(meshes, name))
    out["parts"] = mesh_parts(meshes)
    if kept is not None:
        _HOST_ARRAYS[:] = [(key, kept, out)]  # the latest scene only: the arrays are large
    return out


def _host_arrays_opaque(meshes: tuple) -> dict:
    """`_host_arrays` of opaque meshes without transmission, in NumPy (no program to compile): the
    same positions, triangles and culling flags, no alpha or transmission tables."""
    offs = np.cumsum([0] + [m.num_vertices for m in meshes])
    out = {
        "positions": np.concatenate([np.asarray(m.positions, np.float32) for m in meshes]),
        "triangles": np.concatenate([np.asarray(m.triangles, np.int32) + np.int32(o) for m, o in zip(meshes, offs, strict=False)]),
        "cull_back": np.concatenate([np.full(m.num_triangles, not m.double_sided) for m in meshes]),
    }
    for a in out.values():
        a.setflags(write=False)  # (immutable: the ray engine's caches keep their digests per array)
    return {**out, "alpha": None, "transmit": None}


def _same_value(a, b) -> bool:
    try:
        return type(a) is type(b) and bool(a == b)
    except (TypeError, ValueError):
        return False


def _combine(rgb: bool, dtype: str, parts, hits):
    return shadow_combine(rgb, parts, hits, jnp.dtype(dtype))


_light_segments_jit = cached_jit(_light_segments, static_argnums=(1,))
_sun_segments_jit = cached_jit(_sun_segments, static_argnums=(1,))
_combine_jit = cached_jit(_combine, static_argnums=(0, 1))


def _staged_shadows(segments, scene: Scene, opts: RenderOptions, *args, hit=None):
    """Shadow visibility in a staged render: the segments from a stored program, the meshes' part
    from the host ray engine called directly (`shadows.host_mesh_hits`) on the meshes' arrays made
    once per scene (`scene_host_arrays`), the two combined by a stored program; no program holding
    a callback is compiled in every process."""
    parts = segments(scene, opts, *args)
    rgb = colored_shadows(scene.objects)
    meshes = tuple(ob for ob in scene.objects if isinstance(ob, Mesh))
    if is_ahead():  # (the hits' shapes, no ray traced: `_program_cache.ahead`)
        with running_now():
            arrays = scene_host_arrays(scene, opts.dtype) if meshes else None
        hits = [None] * len(parts) if arrays is None else host_mesh_hit_shapes(arrays, parts)
        return _combine_jit(rgb, jnp.dtype(opts.dtype).name, parts, hits)
    arrays = None if not meshes or _traced(parts) else scene_host_arrays(scene, opts.dtype)
    if meshes and arrays is None:
        # A render under jit / grad: the rays go through the callback. (The segments alone can be
        # concrete there, being free of gradients, while the meshes' vertices are traced.)
        arrays = _host_arrays(meshes, jnp.dtype(opts.dtype).name)
        hits = [_mesh_occluded(arrays, p["o32"], p["l"], p["tfar"]) for p in parts]
        return shadow_combine(rgb, parts, hits, jnp.dtype(opts.dtype))
    if arrays is None:  # (no meshes: the segments alone; under jit the hit mask is traced too)
        hits = [None] * len(parts)
    else:
        # Only the pixels that hit a surface are traced (the others show the background).
        mask = None if hit is None or _traced(hit) else np.asarray(hit)
        hits = [jax.device_put(h) for h in host_mesh_hits(arrays, parts, mask)]
    return _combine_jit(rgb, jnp.dtype(opts.dtype).name, parts, hits)


def _traced(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def _blended_pass(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions, offset, staged: bool, with_hit: bool = False,
                  with_surface: bool = False):
    """BLEND meshes: the nearest `blend_layers` surfaces of each pixel (cast once), each shaded as
    an image of its own by the same compiled stages, composited front to back with their alpha
    (C = sum_k a_k prod_{j<k} (1 - a_j) C_k; an opaque surface or the background ends the pixel)."""
    prims = _host_prims(scene, p_plan, opts, offset) if staged else _layer_prims(scene, p_plan, opts, offset)
    out, keep, hit, surf = None, None, None, None
    for k in range(p_plan.blend_layers):
        if staged:
            g = _mesh_geometry(scene, p_plan, opts, offset, prims[..., k])
        else:
            g = _geometry(scene, p_plan, opts, offset, prims[..., k])
        hit = g["hit"] if hit is None else hit
        surf = _surface_ids(g) if surf is None else surf  # (the outlines of the nearest layer)
        # The coverage as the texture stage leaves it: the geometry's alpha (factor x COLOR_0's A)
        # times the base colour texture's A. (The geometry's own alpha, read here before, left the
        # texture's A out: a BLEND surface whose alpha came from its texture was drawn opaque.)
        c, a = _shade_pass(scene, assets, p_plan, opts, g, staged, coverage=True, rays=offset)
        a = a[..., None]
        if k == p_plan.blend_layers - 1:
            a = jnp.ones_like(a)  # the last layer covers what is left
        out = a * c if out is None else out + keep * a * c
        keep = (1.0 - a) if keep is None else keep * (1.0 - a)
    if with_surface:
        return out, surf
    return (out, hit) if with_hit else out


def _layer_prims(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, offset, layers: int | None = None):
    """The meshes' primitives of the primary rays: (...) with layers=1, else (..., layers) (BLEND;
    default the plan's layers)."""
    dtype = jnp.dtype(opts.dtype)
    o_px, d_px = _pass_rays(scene, p_plan, dtype, offset)
    return cast(_mesh_arrays(scene, dtype), o_px, d_px, layers=p_plan.blend_layers if layers is None else layers)


def _cast_inputs(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, offset):
    """The primary rays the host ray engine casts (`mesh.cast`'s callback arguments), float32 as
    the engine traces them; the meshes' arrays come from `scene_host_arrays`."""
    dtype = jnp.dtype(opts.dtype)
    o_px, d_px = _pass_rays(scene, p_plan, dtype, offset)
    return {"o": o_px.astype(jnp.float32), "d": d_px.astype(jnp.float32)}


_cast_inputs_jit = cached_jit(_cast_inputs, static_argnums=(1, 2))


def _host_prims(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, offset, layers: int | None = None):
    """`_layer_prims` of a staged render: the rays from a stored program (`_cast_inputs`), the
    meshes' arrays made once per scene (`scene_host_arrays`), the host ray engine called directly
    rather than through a callback, so no program holding a callback is compiled in every process
    (it cannot be kept: its cache key names a Python object of its process)."""
    layers = p_plan.blend_layers if layers is None else layers
    x = _cast_inputs_jit(_stage_view(scene), p_plan, opts, offset)
    if is_ahead():  # (the primitives' shape, no ray cast: `_program_cache.ahead`)
        return jax.ShapeDtypeStruct(tuple(x["o"].shape[:-1]) + ((layers,) if layers > 1 else ()), jnp.int32)
    arrays = None if _traced(x) else scene_host_arrays(scene, opts.dtype)
    if arrays is None:  # (a render under jit / grad: the cast goes through the callback in the trace)
        return _layer_prims(scene, p_plan, opts, offset, layers)
    prim = _host_cast(arrays["positions"], arrays["triangles"], arrays["cull_back"],
                      np.asarray(x["o"]), np.asarray(x["d"]), arrays["alpha"], layers=layers, parts=arrays["parts"])
    return jax.device_put(prim)


def _shade_pass(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions, g, staged: bool, *, coverage: bool = False, rays=None):
    """Textures, direct lighting, the environment's suns and IBL + background of the G-buffer `g`;
    coverage=True (a BLEND layer): (colour, alpha), the alpha after the texture stage. rays: the
    pass's `offset` (sub-pixel offset or `Rays`), from which transmitted rays continue."""
    # The later stages see the pixels, not the meshes' arrays: meshes of other sizes reuse them.
    lean = _lean(scene)
    if staged:
        full, lean = lean, _stage_view(lean)
    for k in p_plan.textured:
        g = (_texture_jit if staged else _texture)(lean, k, opts, g)
    sink = GEOMETRY_SINK.get()
    if sink is not None and staged and not is_ahead() and not isinstance(rays, Rays):
        sink.append(g)  # the textured G-buffer, for AOVs of the same pass (`aovs.render_with_aovs`)
    direct = (_shade_direct_jit if staged else _shade_direct)(lean, p_plan, opts, g)
    if p_plan.shadows and p_plan.env_lights:
        # The suns are known before the maps: their shadow rays run while the maps are still being
        # computed on the worker threads (staged: `PendingAssets`).
        env_lights = assets.env_lights if isinstance(assets, PendingAssets) else assets[3]
        facing = g["n"] if _culls_facing(p_plan) else None  # (after the normal maps)
        vis_env = (_staged_shadows(_sun_segments_jit, _stage_view(scene), opts, g["pos"], g["ng"], env_lights, facing, hit=g["hit"])
                   if staged else _sun_shadows(scene, opts, g, env_lights))
        g = {**g, "vis_env": vis_env}
    if isinstance(assets, PendingAssets):
        assets = assets.shapes() if is_ahead() else assets()
    if p_plan.ibl_samples:
        g = {**g, "ibl_vis": _ibl_visibility(scene, p_plan, opts, g, rays, staged)}
    if p_plan.ibl_samples and p_plan.ibl_visibility == "ratio":
        pre = assets[1]
        wfn = _ratio_weights_jit if staged else _ratio_weights
        g = {**g, "ibl_vis": {**g["ibl_vis"], "w": wfn(_lean(_stage_view(scene)) if staged else scene, p_plan, opts, g, g["ibl_vis"]["d"], pre)}}
    if p_plan.transmission_depth and p_plan.ibl and rays is not None:
        behind = _transmitted(scene, assets, p_plan, opts, g, rays, staged)
        if behind is not None:
            g = {**g, "behind": behind}
    if not staged:
        c = _shade_rest(lean, assets, p_plan, opts, g, direct)
    else:
        suns = None
        if p_plan.ibl and p_plan.env_lights:
            suns = _shade_suns_jit(lean, _suns_inputs(assets), p_plan, opts, g)
        assets, lean = _padded_cubes(assets, _stage_view(full, radiance=p_plan.env_background), p_plan)
        c = _shade_rest_jit(lean, assets, p_plan, opts, g, direct, suns)
    return (c, g["alpha"]) if coverage else c


def _padded_cubes(assets, scene: Scene, p_plan: RenderPlan):
    """The IBL stage's inputs with the cube maps it samples (irradiance, prefiltered, the
    background's radiance) padded once on the host (`cubemap.padded`), not in the stage."""
    if assets is not None:
        irr, pre, lut, lights, sheen = assets
        assets = (None if irr is None else padded(irr), padded(pre), lut, lights, sheen)
    env = scene.environment
    if env is not None and p_plan.env_background:
        scene = evolve(scene, environment=evolve(env, radiance=padded(env.radiance)))
    return assets, scene


#: A list that staged passes append their textured G-buffer to (None: not kept); set only by
#: `aovs.render_with_aovs` around one render, on the caller's thread.
GEOMETRY_SINK: contextvars.ContextVar[list | None] = contextvars.ContextVar("jaxpbr_geometry_sink", default=None)


def _stage_view(scene: Scene, *, radiance: bool = False) -> Scene:
    """The scene as a staged program reads it: of its environment only the rotation and the
    intensity (and its radiance with radiance=True, for the background); the maps, LUT and suns
    reach the stages that read them as arguments of their own (`assets`). So scenes under
    environments of other sizes, contents' provenance or lookup metadata share the geometry,
    texture, direct-lighting and shadow programs (their keys hold the scene's tree and shapes)."""
    env = scene.environment
    if env is None:
        return scene
    stub = unchecked(Environment, radiance=env.radiance if radiance else None, intensity=env.intensity,
                     rotation=env.rotation, show_background=env.show_background, irradiance=None,
                     prefiltered=None, lut=None, lut_smith=None, lights=None, charlie=None, sheen_lut=None)
    return evolve(scene, environment=stub)


def _lean(scene: Scene) -> Scene:
    """The scene with its meshes' geometry left out (their materials kept): what the shading
    stages read."""
    if scene.gbuffer is not None or not any(isinstance(ob, Mesh) for ob in scene.objects):
        return scene
    objs = tuple(
        unchecked(Mesh, **{f.name: (getattr(ob, f.name) if f.static or f.name == "material" else None) for f in fields_of(Mesh)})
        if isinstance(ob, Mesh) else ob
        for ob in scene.objects
    )
    return evolve(scene, objects=objs)


def _sun_directions(scene: Scene, env_lights, dtype) -> list:
    """World directions to the suns split out of the environment (its frame turned by +rotation)."""
    rot = jnp.asarray(scene.environment.rotation, dtype)
    ls = _cast_floats(list(env_lights), dtype)
    return [_rotate_y(tuple(-jnp.asarray(s.direction, dtype)[i] for i in range(3)), rot) for s in ls]


def _sun_shadows(scene: Scene, opts: RenderOptions, g, env_lights):
    """(H, W, L) visibility of the suns split out of the environment."""
    dtype = jnp.dtype(opts.dtype)
    return shadow_visibility(scene.objects, _mesh_arrays(scene, dtype), g["pos"], g["ng"], _sun_directions(scene, env_lights, dtype),
                             dtype, directions_only=True)


# The staged programs, kept on disk where a trace cache directory is set (the command line's):
# a later process loads them instead of tracing, lowering and compiling them (`_program_cache`).
_geometry_jit = cached_jit(_geometry, static_argnums=(1, 2), static_argnames=("light_shadows",))
_texture_jit = cached_jit(_texture, static_argnums=(1, 2))
_shade_direct_jit = cached_jit(_shade_direct, static_argnums=(1, 2))
_shade_suns_jit = cached_jit(_shade_suns, static_argnums=(2, 3))
_shade_rest_jit = cached_jit(_shade_rest, static_argnums=(2, 3), cpu_options=LOOP_EMITTERS)
_transmit_rays_jit = cached_jit(_transmit_rays, static_argnums=(1, 2))
_ibl_directions_jit = cached_jit(_ibl_directions, static_argnums=(1, 2))
_ibl_segments_jit = cached_jit(_ibl_segments, static_argnums=(1,))
_ratio_weights_jit = cached_jit(_ratio_weights, static_argnums=(1, 2))


def outlined_pass(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions, offset, samples: int, staged: bool = False):
    """One pass (`_render_pass`) with its silhouettes and occlusion edges blended
    (`edges.antialias_pass`: the image's derivative with respect to where the edges are); a scene
    given as a G-buffer has no outlines to blend."""
    if scene.gbuffer is not None or opts.antialias == "none":
        return _render_pass(scene, assets, p_plan, opts, offset, staged)
    c, surf = _render_pass(scene, assets, p_plan, opts, offset, staged, with_surface=True)
    return antialias_pass(scene, opts.dtype, offset, c, surf, samples, blend=opts.antialias)


def _render_traced(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions):
    s = 1 if scene.gbuffer is not None else scene.camera.supersample
    dtype = jnp.dtype(opts.dtype)
    if s == 1:
        return outlined_pass(scene, assets, p_plan, opts, jnp.asarray((0.5, 0.5), dtype), 1)

    def body(k, acc):
        off = jnp.stack([((k % s).astype(dtype) + 0.5) / s, ((k // s).astype(dtype) + 0.5) / s])
        return acc + outlined_pass(scene, assets, p_plan, opts, off, s)

    H, W = scene.image_shape
    acc = jax.lax.fori_loop(0, s * s, body, jnp.zeros((H, W, 3), dtype))
    return acc / (s * s)


_render_jit = jax.jit(_render_traced, static_argnums=(2, 3))


def _antialias_stage(scene: Scene, dtype_name: str, offset, c, surf, samples: int, nbr, blend: bool):
    return antialias_pass(scene, dtype_name, offset, c, surf, samples, nbr, blend=blend)


_antialias_jit = cached_jit(_antialias_stage, static_argnums=(1, 5, 7))


def staged_outlines(scene: Scene, opts: RenderOptions, offset, c, surf, samples: int):
    """`edges.antialias_pass` of a staged pass (the whole image's, its bands joined) as a stored
    program, the meshes' topology computed on the host once per content (`edges.NEIGHBOURS`) and
    passed in (under jit / grad, where the meshes' arrays are traced, from a callback in the trace)."""
    if surf is None or opts.antialias == "none":  # (a scene given as a G-buffer; the control without outlines)
        return c
    nbr = None
    if any(isinstance(ob, Mesh) for ob in scene.objects) and not _traced((c, surf, offset)):
        arrays = scene_host_arrays(scene, opts.dtype)
        if arrays is not None:
            nbr = jax.device_put(NEIGHBOURS.get(arrays["positions"], arrays["triangles"], arrays["parts"]))
    view = _stage_view(evolve(scene, camera=evolve(scene.camera, supersample=1)))
    return _antialias_jit(view, jnp.dtype(opts.dtype).name, offset, c, surf, samples, nbr, opts.antialias)


@keyword_only("options")
def gbuffer(scene: Scene, *, options: RenderOptions | None = None, **overrides):
    """The G-buffer `render` shades: the nearest surface at each pixel centre of the camera (its
    `supersample` is not used), materials after textures, COLOR_0 and normal maps -> `GBuffer`
    with (H, W) / (H, W, 3) leaves in the options' dtype: hit, position, normal (the shading
    normal), view (unit, towards the camera) and a per-pixel `Material` (the extension fields of
    the groups some object uses, the others None). Off the surfaces (hit False) the values are
    undefined. A scene given as a G-buffer returns its own. Lights and environment are not read
    (nothing is precomputed); options as for `render` (only dtype matters)."""
    if not isinstance(scene, Scene):
        raise TypeError(f"gbuffer expects a jaxpbr.Scene, got {type(scene).__name__}")
    opts = _options(options, overrides, "gbuffer")
    if scene.gbuffer is not None:
        return scene.gbuffer
    bare = evolve(scene, lights=(), environment=None, camera=evolve(scene.camera, supersample=1))
    gb, _ = surface_buffer(bare, opts)
    return gb


def surface_of_rays(scene: Scene, opts: RenderOptions, origins, directions):
    """The surfaces rays meet: (`GBuffer` of shape (N, 1), (N, 1, 3) geometric normals facing the
    ray's origin) for origins, directions (N, 3) (origins already off any surface they leave; no
    ray differentials: textures at their finest level). What `gbuffer` gives for the camera's
    pixels, for any rays (the ground truth's paths, `jaxpbr.reference`)."""
    bare = evolve(scene, lights=(), environment=None, camera=evolve(scene.camera, supersample=1))
    p = dataclasses.replace(plan(bare, options=opts), shadows=True, transmission_depth=0, transmission_samples=0, ibl_samples=0)
    dtype = jnp.dtype(opts.dtype)
    n = np.shape(origins)[0]
    rays = Rays(o=jnp.asarray(np.reshape(origins, (n, 1, 3)), dtype), d=jnp.asarray(np.reshape(directions, (n, 1, 3)), dtype),
                diff=jnp.zeros((n, 1, 4, 3), dtype), key=jnp.zeros((n, 1), jnp.uint32))
    g = staged_geometry(bare, p, opts, rays, light_shadows=False)
    lean = _lean(bare)
    for k in p.textured:
        g = _texture_jit(lean, k, opts, g)
    gb = GBuffer(hit=g["hit"], position=pack3(g["pos"]), normal=pack3(g["n"]), view=pack3(g["view"]), material=g["m"])
    return gb, pack3(g["ng"])


def surface_buffer(scene: Scene, opts: RenderOptions):
    """(`GBuffer` of the camera's pixel centres, (H, W, 3) geometric normals facing the viewer): what
    `gbuffer` returns, with the normal secondary rays leave the surface along (the ground truth's,
    `jaxpbr.reference`). scene: a Scene of objects (not a user G-buffer)."""
    bare = evolve(scene, lights=(), environment=None, camera=evolve(scene.camera, supersample=1))
    p = dataclasses.replace(plan(bare, options=opts), shadows=True)  # (shadows: the geometric normal)
    dtype = jnp.dtype(opts.dtype)
    g = staged_geometry(bare, p, opts, jax.device_put(np.asarray((0.5, 0.5), dtype)), light_shadows=False)
    lean = _lean(bare)
    for k in p.textured:
        g = _texture_jit(lean, k, opts, g)
    gb = GBuffer(hit=g["hit"], position=pack3(g["pos"]), normal=pack3(g["n"]), view=pack3(g["view"]), material=g["m"])
    return gb, pack3(g["ng"])
