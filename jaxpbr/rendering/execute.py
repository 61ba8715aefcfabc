"""`render` and how it runs: staged (one compiled program per stage, on XLA:CPU) or as one
program (elsewhere, and under transformations), in bands of rows for large images, one pass per
sub-pixel sample, with the assets of a concrete environment computed on the process's worker pool
while the first stages compile and run.

`Execution` holds the settings (`EXECUTION`, the process's: `renderer.EXECUTION.staged` and
`.band_pixels`); `worker_pool` is the one pool of worker threads,
started on first use and kept for the life of the process."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from .. import _program_cache
from .._numerics import with_callers_context
from .._program_cache import release_programs
from .._pytree import evolve, fields_of, unchecked
from .assets import PendingAssets, ibl_assets
from .cache import AssetCache, cache_or_default
from .execution import EXECUTION, Execution
from .options import RenderOptions, _options
from .plan import RenderPlan, check_memory, plan_for, split_environment
from .scene import Scene
from ..errors import InputError
from .bvh import build_bvh
from .mesh import Mesh, device_accel, device_traceable
from .edges import NEIGHBOURS
from .stages import AccelScene, _render_jit, _render_pass, scene_host_arrays, staged_outlines


def render(
    scene: Scene, *, options: RenderOptions | None = None, progress=None, cache: AssetCache | None = None, **overrides
) -> jax.Array:
    """Render `scene` to linear HDR radiance (H, W, 3) (Rec.709 primaries, scene-referred).

    options: a `RenderOptions` value (default: `RenderOptions()`).
    progress: optional callable(done, total) in passes (bands of rows x sub-pixel samples), called
      on the caller's thread as each pass is dispatched and once when the image is ready (staged
      renders, i.e. on the CPU outside jit; a one-program render reports only its end).
    **overrides: `RenderOptions` fields as keywords (model, multiscatter, smith, irradiance_size,
      irradiance_method, prefilter_size, prefilter_samples, lut_size, mapping, dtype,
      extract_lights), applied on top of `options`: `render(scene, options=opts, model="learnopengl")` renders with
      `dataclasses.replace(opts, model="learnopengl")`.
    cache: the `AssetCache` the environment's precomputed maps come from and go into (None: the
      process's default, `ASSETS`).
    Differentiable with respect to every array in the scene (materials, textures, lights, camera,
    environment texels).

    The pipeline: the memory guard (before any work), the suns split out of the environment, the
    plan, the IBL assets (computed on the worker pool while a staged render runs its first
    stages), then the passes.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"render expects a jaxpbr.Scene, got {type(scene).__name__}")
    opts = _options(options, overrides, "render")
    cache = cache_or_default(cache)
    check_memory(scene, options=opts)  # before any work (a huge size aborted inside XLA)
    split = split_environment(scene.environment, opts, cache)
    p = plan_for(scene, opts, suns=len(split.suns or ()))
    execution = EXECUTION
    staged = execution.is_staged()
    submit = (lambda job: worker_pool().submit(with_callers_context(job))) if staged else None
    assets = ibl_assets(split, p, opts, cache, submit=submit) if p.ibl else None
    try:
        if staged:
            return _run_staged(scene, assets, p, opts, progress, execution)
        out = _render_jit(_with_device_accel(scene, execution), assets, p, opts)
        if progress is not None:
            progress(1, 1)
        return out
    finally:
        # On success every map was used; on an error or an interrupt the precomputes not started
        # yet are dropped, and one still running is not waited for.
        if isinstance(assets, PendingAssets):
            assets.cancel()


def _run_staged(scene: Scene, assets, p: RenderPlan, opts: RenderOptions, progress, execution: Execution):
    """The passes of a staged render (`_banded`), their stages compiled ahead on a cold start. With
    `PendingAssets` the geometry and direct-lighting stages compile and run while the maps are
    computed on the worker threads (XLA compiles and runs without holding the GIL)."""
    one_pass = lambda sc, pb, off: _render_pass(sc, assets, pb, opts, off, staged=True, with_surface=scene.gbuffer is None)
    _compile_ahead(scene, opts, p, one_pass, execution, computing=isinstance(assets, PendingAssets))
    return _banded(scene, opts, p, one_pass, progress, execution)


def _layout(scene: Scene, execution: Execution | None):
    """(sub-pixel samples per axis, whole image in one pass, rows per band) of `_banded`."""
    band_pixels = (EXECUTION if execution is None else execution).band_pixels
    H, W = scene.image_shape
    s = 1 if scene.gbuffer is not None else scene.camera.supersample
    whole = scene.gbuffer is not None or H * W <= band_pixels
    return s, whole, (H if whole else max(1, band_pixels // W))


def _compile_ahead(scene: Scene, opts: RenderOptions, p: RenderPlan, one_pass, execution: Execution | None, *, computing: bool) -> None:
    """Start compiling every stage of the render's passes at once (`_program_cache.ahead`): the
    stages are traced here, one after another, and compiled on the compiler threads while the
    first ones run; without it each stage's compilation waits for the previous stage to compile
    and run, and the IBL stage's for the maps. Only on a cold start of the command line (stored
    programs on, none recalled); a pass that cannot be looked ahead (a render under a
    transformation, BLEND layers, sheen maps still to compute) runs as usual. Two compiler threads
    where nothing else runs beside the compilations (no IBL map to compute, no ray engine to build),
    else one (`_program_cache.MAX_COMPILERS`). computing: the IBL maps are being computed on the
    worker threads."""
    if _program_cache.directory() is None or _program_cache.was_recalled() or jax.default_backend() != "cpu":
        return
    env = scene.environment
    busy = scene.gbuffer is None and any(isinstance(ob, Mesh) for ob in scene.objects)
    if p.ibl and computing:
        busy = busy or env.prefiltered is None or (p.ibl_diffuse and env.irradiance is None)
        busy = busy or ("sheen" in p.extensions and env.charlie is None)
    compilers = 1 if busy else _program_cache.MAX_COMPILERS
    s, whole, rows = _layout(scene, execution)
    sc = evolve(scene, camera=evolve(scene.camera, supersample=1)) if s > 1 else scene
    pb = p if whole else dataclasses.replace(p, band_rows=rows)
    offset = jax.ShapeDtypeStruct((2,) if whole else (3,), jnp.dtype(opts.dtype))
    try:
        with _program_cache.ahead(compilers=compilers):
            one_pass(sc, pb, offset)
    except Exception:  # noqa: BLE001 (NotAhead, or a pass the look-ahead cannot follow: as usual)
        return
    for call in _program_cache.calls_also_ahead():
        with contextlib.suppress(Exception), _program_cache.ahead(compilers=compilers):  # (as above)
            call()


def _banded(scene: Scene, opts: RenderOptions, p: RenderPlan, one_pass, progress=None, execution: Execution | None = None):
    """The mean of the camera's s x s passes (one per sub-pixel offset, run from the host one after
    another), each over the whole image or band by band (rows of ~`execution.band_pixels` pixels,
    one compiled program per stage for every band: the band's first row is an argument) and then
    joined, its outlines blended over the whole image (`stages.staged_outlines`); a user G-buffer
    is rendered whole, once. one_pass(scene, plan, offset) -> (colour, surface ids) (ids None for a
    G-buffer). progress: per pass (bands x sub-pixel samples), the last once the image is ready.

    The offset is an argument, not a static value, and the passes get the scene with
    supersample = 1 (a static field the stages do not read): one compiled program per stage
    whatever s (before: one per offset, s^2 of them)."""
    H = scene.image_shape[0]
    s, whole, rows = _layout(scene, execution)
    starts = [None] if whole else list(range(0, H, rows))
    total = len(starts) * s * s
    pb = p if whole else dataclasses.replace(p, band_rows=rows)
    sc = evolve(scene, camera=evolve(scene.camera, supersample=1)) if s > 1 else scene
    dtype = jnp.dtype(opts.dtype)
    acc, done = None, 0
    for k in range(s * s):
        off = ((k % s + 0.5) / s, (k // s + 0.5) / s)
        parts = []
        for y0 in starts:
            parts.append(one_pass(sc, pb, jax.device_put(np.asarray(off + (() if y0 is None else (y0,)), dtype))))
            done += 1
            if progress is not None and done < total:
                progress(done, total)
        if scene.gbuffer is not None:  # (no outlines: the pass's colour alone)
            c, surf = parts[0], None
        elif whole:
            c, surf = parts[0]
        else:
            # Bands stay on the device (and traceable: `render` under jit/grad on the CPU takes this
            # path too) and are joined once; the last band's rows past the image are cut off.
            c = jnp.concatenate([x[0] for x in parts])[:H]
            surf = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs)[:H], *(x[1] for x in parts))
        c = staged_outlines(sc, opts, jax.device_put(np.asarray(off, dtype)), c, surf, s)
        acc = c if acc is None else acc + c
    out = acc if s == 1 else acc / (s * s)
    if progress is not None:
        out = jax.block_until_ready(out)
        progress(total, total)
    return out


def _supersampled(scene: Scene, opts: RenderOptions, one_pass):
    """The mean of one_pass(scene, offset) over the camera's s x s sub-pixel offsets, run from the
    host one after another (`render_batch` outside transformations; `render` runs `_banded`)."""
    s = 1 if scene.gbuffer is not None else scene.camera.supersample
    if s > 1:
        scene = evolve(scene, camera=evolve(scene.camera, supersample=1))
    dtype = jnp.dtype(opts.dtype)
    acc = None
    for k in range(s * s):
        off = jax.device_put(np.asarray(((k % s + 0.5) / s, (k // s + 0.5) / s), dtype))
        one = one_pass(scene, off)
        acc = one if acc is None else acc + one
    return acc if s == 1 else acc / (s * s)


def _with_device_accel(scene: Scene, execution: Execution) -> Scene:
    """The scene with its opaque meshes' device BVH (`stages.AccelScene`) where `execution` traces
    on the device and the meshes allow it (`mesh.device_accel`), else the scene itself."""
    if scene.gbuffer is not None or not execution.traces_on_device() or isinstance(scene, AccelScene):
        return scene
    accel = device_accel([ob for ob in scene.objects if isinstance(ob, Mesh)])
    if accel is None:
        return scene
    host = scene_host_arrays(scene, jnp.float32)
    nbr = None if host is None else jax.device_put(NEIGHBOURS.get(host["positions"], host["triangles"], host["parts"]))
    return unchecked(AccelScene, **{f.name: getattr(scene, f.name) for f in fields_of(Scene)}, accel=accel, neighbours=nbr, refit=False)


def deformable(scene: Scene) -> Scene:
    """`scene` prepared for renders whose meshes change shape -- their vertices' positions move,
    their triangles stay -- under `jax.jit` / `jax.grad` (a shape fit's steps, a pose of a skinned
    mesh): it carries what `render` otherwise makes per mesh content on the host, made once here
    from the meshes as they are:
    - the meshes' topology (neighbours across edges, vertices welded by position), which the
      outlines' antialiasing and derivatives (`edges`) read: with positions traced it would come
      from a host callback every step;
    - where rays of opaque meshes are traced in the program (`Execution.device_visibility`, the
      default off the CPU), their BVH, built keeping zero-area triangles and refitted in the
      program to the positions each render is given (`bvh.refit_bvh`): no host round trip and no
      rebuild per step. On the CPU the host's ray engine (Embree) answers instead, faster there.
    Render the result with new positions as any scene: `render(s.replace(objects=[mesh.replace(
    positions=p)]))`. Only positions may change: a mesh with another triangle count is refused
    at render time; other triangles of the same count are not detected (their topology would be
    the old one's). The topology is the starting shape's: vertices welded at the start stay one."""
    if not isinstance(scene, Scene):
        raise TypeError(f"deformable expects a jaxpbr.Scene, got {type(scene).__name__}")
    meshes = [ob for ob in scene.objects if isinstance(ob, Mesh)]
    if not meshes or scene.gbuffer is not None:
        return scene
    host = scene_host_arrays(scene, jnp.float32)
    if host is None:
        raise InputError("deformable needs the meshes' arrays themselves, not traced values: call it once outside "
                         "jax.jit / jax.grad, on the meshes' starting shape, and render the result with new positions inside")
    nbr = jax.device_put(NEIGHBOURS.get(host["positions"], host["triangles"], host["parts"]))
    accel = None
    if EXECUTION.traces_on_device() and device_traceable(meshes):
        accel = build_bvh(host["positions"], host["triangles"], keep_degenerate=True).to_device()
    fields = {f.name: getattr(scene, f.name) for f in fields_of(Scene)}
    return unchecked(AccelScene, **fields, accel=accel, neighbours=nbr, refit=True)


def _staged() -> bool:
    return EXECUTION.is_staged()


#: Threads of the worker pool: one render submits up to three precomputes (prefiltered,
#: irradiance, sheen maps); two run at once while the render's own thread compiles and runs stages.
WORKERS = 2
_pool: ThreadPoolExecutor | None = None
_pool_pid = 0
_pool_lock = threading.Lock()


def clear_caches() -> None:
    """Drop every compiled program this process holds: JAX's (`jax.clear_caches`) and the render
    stages jaxpbr keeps in memory (`_program_cache.release_programs`). The next render loads its
    programs from the disk caches again, or compiles them; precomputed maps, the asset cache and
    the ray engines' structures are kept.

    For long-running processes that render many differently shaped scenes: each XLA:CPU program
    holds its own memory mappings (hundreds for a render stage), and Linux ends a process that
    reaches `vm.max_map_count` (65,530 by default) mappings: a worker of the slow test set died
    at 64,718."""
    jax.clear_caches()
    release_programs()


def finish_work() -> None:
    """Wait for the worker pool's jobs (a map still being computed and written to the asset
    cache): what a process that ends now must do first (`cli.main`)."""
    global _pool
    with _pool_lock:
        pool, _pool = (_pool if _pool_pid == os.getpid() else None), None  # (a later use starts a new one)
    if pool is not None:
        pool.shutdown(wait=True)


def worker_pool() -> ThreadPoolExecutor:
    """The process's worker pool, started on first use and reused by every render (no threads are
    started per call; idle workers cost nothing). A forked child starts its own (the parent's
    threads do not exist there). Work submitted to it must not wait for other work submitted to it:
    with all workers waiting, nothing would run."""
    global _pool, _pool_pid
    with _pool_lock:
        if _pool is None or _pool_pid != os.getpid():
            _pool = ThreadPoolExecutor(max_workers=WORKERS, thread_name_prefix="jaxpbr-render")
            _pool_pid = os.getpid()
        return _pool

