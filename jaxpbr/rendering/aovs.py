"""Arbitrary output variables (AOVs) for datasets: per-pixel depth, normal, base colour, coverage,
object and primitive ids of a scene, from the same geometry and texture stages `render` runs.

AOVs are taken at the pixel centres (no supersampling, no blending: the nearest surface), in world
space, and are not differentiated (they are labels). `jaxpbr render --aov ...` writes them as
layers of the EXR next to the image.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._numerics import vdot
from .options import RenderOptions, _options
from .plan import plan
from .scene import Scene, camera_basis
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
}


def aovs(scene: Scene, names=tuple(AOVS), *, options: RenderOptions | None = None, **overrides) -> dict[str, np.ndarray]:
    """The AOVs `names` (keys of `AOVS`) of a scene with a camera, as float32 NumPy arrays (H, W) or
    (H, W, 3). Ids are exact integers in float32 (up to 2^24)."""
    _check_names(scene, names)
    opts = _options(options, overrides, "aovs")
    p = plan(scene, options=opts)
    dtype = jnp.dtype(opts.dtype)
    g = staged_geometry(scene, p, opts, jnp.asarray((0.5, 0.5), dtype), light_shadows=False)
    if "base_color" in names or "normal" in names:
        lean = _stage_view(_lean(scene))  # (the render's texture programs)
        for k in p.textured:
            g = _texture_jit(lean, k, opts, g)
    return _values(scene, names, g, dtype)


def render_with_aovs(scene: Scene, names, *, options: RenderOptions | None = None, cache=None, progress=None):
    """(`render(scene)`, `aovs(scene, names)`), equal to the two calls, from one geometry pass where
    the render's pass is the AOVs' own: staged (XLA:CPU), one sample per pixel, the image in one
    band and no blended layers; otherwise the two calls. Saves the primary rays' cast and the
    geometry and texture stages (with a million triangles at 1080p, the larger part of a frame)."""
    from .execute import EXECUTION, render

    _check_names(scene, names)
    opts = _options(options, {}, "render_with_aovs")
    H, W = scene.image_shape
    p = plan(scene, options=opts)
    shared = (EXECUTION.is_staged() and scene.camera.supersample == 1 and H * W <= EXECUTION.band_pixels
              and p.blend_layers == 1)
    if not shared:
        return render(scene, options=opts, cache=cache, progress=progress), aovs(scene, names, options=opts)
    kept: list = []
    token = GEOMETRY_SINK.set(kept)
    try:
        hdr = render(scene, options=opts, cache=cache, progress=progress)
    finally:
        GEOMETRY_SINK.reset(token)
    if len(kept) != 1:  # (a path that did not pass through one staged pass)
        return hdr, aovs(scene, names, options=opts)
    return hdr, _values(scene, names, kept[0], jnp.dtype(opts.dtype))


def _check_names(scene: Scene, names) -> None:
    unknown = [n for n in names if n not in AOVS]
    if unknown:
        raise ValueError(f"unknown AOV(s) {unknown}; available: {list(AOVS)}")
    if scene.gbuffer is not None:
        raise ValueError("aovs needs a scene with a camera and objects, not a G-buffer")


def _values(scene: Scene, names, g, dtype) -> dict[str, np.ndarray]:
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
