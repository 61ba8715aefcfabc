"""Arbitrary output variables (AOVs) for datasets: per-pixel depth, normal, base colour, coverage,
object and primitive ids of a scene, from the same geometry and texture stages `render` runs.

AOVs are taken at the pixel centres (no supersampling, no blending: the nearest surface), in world
space, and are not differentiated (they are labels). `jaxpbr render --aov ...` writes them as
layers of the EXR next to the image.

Motion vectors (`motion`) need the scene a time step later (`next_scene`: the same objects, posed
at t + dt, e.g. `jaxpbr.load_gltf(path, time=t + dt)`): each pixel's surface point is carried to
the next frame on its own triangle (P' = P + Σ b_i (V'_i - V_i), b the barycentrics of P in the
triangle at t; a sphere moves with its centre, planes stay) and projected by the next frame's
camera; the AOV is that position minus the point's position in this frame, in pixels (x right,
y down). A static scene under a static camera gives exactly 0.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._numerics import vdot
from .mesh import Mesh
from .options import RenderOptions, _options
from .plan import plan
from .scene import Scene, Sphere, camera_basis
from .stages import GEOMETRY_SINK, _lean, _stage_view, _texture_jit, staged_geometry

__all__ = ["AOVS", "aovs", "exr_layers", "render_with_aovs"]

#: The AOVs: name -> (EXR channel names, what they hold).
AOVS: dict[str, tuple[tuple[str, ...], str]] = {
    "depth": (("Z",), "camera-space depth: distance along the viewing axis (0 where nothing is hit)"),
    "distance": (("distance.Y",), "distance from the camera along the ray (0 where nothing is hit)"),
    "normal": (("N.X", "N.Y", "N.Z"), "world-space shading normal, after normal maps, facing the viewer (0 off surfaces)"),
    "position": (("P.X", "P.Y", "P.Z"), "world-space position of the surface (0 off surfaces)"),
    "base_color": (("albedo.R", "albedo.G", "albedo.B"), "linear base colour after textures and vertex colours"),
    "mask": (("mask.Y",), "1 where a surface is hit, 0 on the background"),
    "object_id": (("object_id.Y",), "index of the object in Scene.objects, -1 on the background"),
    "primitive_id": (("primitive_id.Y",), "triangle index within the scene's meshes (in Scene.objects order), -1 elsewhere"),
    "motion": (("motion.X", "motion.Y"), "screen-space motion of the surface point from this frame to the next (t + dt), "
               "in pixels, x right, y down (0 off surfaces)"),
}


def aovs(scene: Scene, names=tuple(a for a in AOVS if a != "motion"), *, options: RenderOptions | None = None,
         next_scene: Scene | None = None, **overrides) -> dict[str, np.ndarray]:
    """The AOVs `names` (keys of `AOVS`) of a scene with a camera, as float32 NumPy arrays (H, W),
    (H, W, 2) or (H, W, 3). Ids are exact integers in float32 (up to 2^24). next_scene: the scene a
    time step later, for `motion`."""
    _check_names(scene, names, next_scene)
    opts = _options(options, overrides, "aovs")
    p = plan(scene, options=opts)
    dtype = jnp.dtype(opts.dtype)
    g = staged_geometry(scene, p, opts, jnp.asarray((0.5, 0.5), dtype), light_shadows=False)
    if "base_color" in names or "normal" in names:
        lean = _stage_view(_lean(scene))  # (the render's texture programs)
        for k in p.textured:
            g = _texture_jit(lean, k, opts, g)
    return _values(scene, names, g, dtype, next_scene)


def render_with_aovs(scene: Scene, names, *, options: RenderOptions | None = None, cache=None, progress=None,
                     next_scene: Scene | None = None):
    """(`render(scene)`, `aovs(scene, names)`), equal to the two calls, from one geometry pass where
    the render's pass is the AOVs' own: staged (XLA:CPU), one sample per pixel, the image in one
    band and no blended layers; otherwise the two calls. Saves the primary rays' cast and the
    geometry and texture stages (with a million triangles at 1080p, the larger part of a frame)."""
    from .execute import EXECUTION, render

    _check_names(scene, names, next_scene)
    opts = _options(options, {}, "render_with_aovs")
    H, W = scene.image_shape
    p = plan(scene, options=opts)
    shared = (EXECUTION.is_staged() and scene.camera.supersample == 1 and H * W <= EXECUTION.band_pixels
              and p.blend_layers == 1)
    if not shared:
        return render(scene, options=opts, cache=cache, progress=progress), aovs(scene, names, options=opts, next_scene=next_scene)
    kept: list = []
    token = GEOMETRY_SINK.set(kept)
    try:
        hdr = render(scene, options=opts, cache=cache, progress=progress)
    finally:
        GEOMETRY_SINK.reset(token)
    if len(kept) != 1:  # (a path that did not pass through one staged pass)
        return hdr, aovs(scene, names, options=opts, next_scene=next_scene)
    return hdr, _values(scene, names, kept[0], jnp.dtype(opts.dtype), next_scene)


def _check_names(scene: Scene, names, next_scene=None) -> None:
    unknown = [n for n in names if n not in AOVS]
    if unknown:
        raise ValueError(f"unknown AOV(s) {unknown}; available: {list(AOVS)}")
    if scene.gbuffer is not None:
        raise ValueError("aovs needs a scene with a camera and objects, not a G-buffer")
    if "motion" in names:
        if next_scene is None:
            raise ValueError("the motion AOV needs next_scene: the same scene a time step later (e.g. "
                             "jaxpbr.load_gltf(path, time=t + dt)); jaxpbr render --aov motion takes it from --time/--frames")
        a, b = scene.objects, next_scene.objects
        same = len(a) == len(b) and all(type(x) is type(y) for x, y in zip(a, b)) and all(
            np.shape(x.triangles) == np.shape(y.triangles) and np.shape(x.positions) == np.shape(y.positions)
            for x, y in zip(a, b) if isinstance(x, Mesh))
        if not same or next_scene.camera is None:
            raise ValueError("next_scene must hold the same objects (types, vertex and triangle counts) and a camera: "
                             "the scene posed a time step later")


def _project(cam, p: np.ndarray) -> np.ndarray:
    """(..., 2) continuous pixel coordinates (x right, y down; pixel (i, j)'s centre at (j + 0.5, i + 0.5))
    of world points p (..., 3) seen by `cam` (float64; the inverse of `primary_rays`)."""
    pos, tgt, up = (np.asarray(v, np.float64) for v in (cam.position, cam.target, cam.up))
    fwd = (tgt - pos) / np.linalg.norm(tgt - pos)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    upv = np.cross(right, fwd)
    W, H = cam.width, cam.height
    rel = p - pos
    x, y = rel @ right, rel @ upv
    if cam.projection == "orthographic":
        t = float(cam.ymag)
    else:
        t = math.tan(math.radians(float(cam.fov_y_deg)) / 2)
        z = rel @ fwd
        z = np.where(np.abs(z) > 1e-300, z, 1e-300)
        x, y = x / z, y / z
    jit = np.asarray(cam.jitter, np.float64)
    return np.stack([(x / (t * W / H) + 1.0) * W / 2 - jit[0], (1.0 - y / t) * H / 2 - jit[1]], -1)


def _motion(scene: Scene, next_scene: Scene, g) -> np.ndarray:
    """(H, W, 2) float64 motion vectors in pixels (see the module docstring)."""
    hit = np.asarray(g["hit"])
    p0 = np.stack([np.asarray(c, np.float64) for c in g["pos"]], -1)
    p1 = p0.copy()
    idx = np.asarray(g["idx"])
    meshes = [k for k, ob in enumerate(scene.objects) if isinstance(ob, Mesh)]
    if meshes and "prim" in g:
        prim = np.asarray(g["prim"])
        v0, v1, tris, off = [], [], [], 0
        for k in meshes:
            a, b = scene.objects[k], next_scene.objects[k]
            v0.append(np.asarray(a.positions, np.float64))
            v1.append(np.asarray(b.positions, np.float64))
            tris.append(np.asarray(a.triangles, np.int64) + off)
            off += v0[-1].shape[0]
        v0, v1, tris = np.concatenate(v0), np.concatenate(v1), np.concatenate(tris)
        on = hit & (prim >= 0)
        t = tris[prim[on]]
        a, b, c = v0[t[:, 0]], v0[t[:, 1]], v0[t[:, 2]]
        p = p0[on]
        n = np.cross(b - a, c - a)
        nn = np.einsum("ij,ij->i", n, n)
        ok = nn > 0
        safe = np.where(ok, nn, 1.0)
        wa = np.einsum("ij,ij->i", np.cross(c - b, p - b), n) / safe
        wb = np.einsum("ij,ij->i", np.cross(a - c, p - c), n) / safe
        bary = np.where(ok[:, None], np.stack([wa, wb, 1.0 - wa - wb], -1), 1.0 / 3.0)
        d = v1[t] - v0[t]  # (n, 3 corners, 3)
        p1[on] = p + np.einsum("ik,ikj->ij", bary, d)
    for k, ob in enumerate(scene.objects):
        if isinstance(ob, Sphere):
            m = hit & (idx == k)
            p1[m] += np.asarray(next_scene.objects[k].center, np.float64) - np.asarray(ob.center, np.float64)
    out = _project(next_scene.camera, p1) - _project(scene.camera, p0)
    return np.where(hit[..., None], out, 0.0)


def _values(scene: Scene, names, g, dtype, next_scene=None) -> dict[str, np.ndarray]:
    """The AOVs `names` of the (textured) G-buffer `g` of the pixel centres."""
    hit = g["hit"]
    out = {}
    zero = lambda x: jnp.where(hit, x, 0.0)  # noqa: E731
    if "depth" in names:
        _, fwd, _, _ = camera_basis(scene.camera, dtype)
        out["depth"] = zero(g["t"] * vdot(g["ray"], fwd))
    if "distance" in names:
        out["distance"] = zero(g["t"])
    if "normal" in names:
        out["normal"] = jnp.stack([zero(c) for c in g["n"]], -1)
    if "position" in names:
        out["position"] = jnp.stack([zero(c) for c in g["pos"]], -1)
    if "base_color" in names:
        out["base_color"] = jnp.where(hit[..., None], g["m"].base_color, 0.0)
    if "mask" in names:
        out["mask"] = hit.astype(dtype)
    if "object_id" in names:
        out["object_id"] = jnp.where(hit, g["idx"], -1).astype(dtype)
    if "primitive_id" in names:
        prim = g.get("prim")
        out["primitive_id"] = (jnp.full(hit.shape, -1, dtype) if prim is None else jnp.where(hit, prim, -1).astype(dtype))
    if "motion" in names:
        out["motion"] = _motion(scene, next_scene, g)
    return {k: np.asarray(v, np.float32) for k, v in out.items()}


def exr_layers(values: dict, names) -> tuple[dict, dict]:
    """AOV arrays (`aovs`) as EXR layers -> ({channel: (H, W) array}, {"jaxpbr:aov:<name>": what the
    channels hold}), the layers and header attributes `jaxpbr.io.image.write(..., layers=)` takes."""
    layers, meta = {}, {}
    for name in names:
        chans, what = AOVS[name]
        v = np.asarray(values[name])
        for i, ch in enumerate(chans):
            layers[ch] = v if v.ndim == 2 else v[..., i]
        meta[f"jaxpbr:aov:{name}"] = f"{', '.join(chans)}: {what}"
    return layers, meta
