"""The IBL assets a plan reads (irradiance, prefiltered chain, split-sum LUT, suns, sheen tables),
taken from the environment when it carries them and otherwise computed through the asset cache,
and `bake`: an environment with all of them precomputed.

A concrete environment's maps are computed once per content and parameters (concrete even under
an outer jit / grad / vmap); a traced environment (differentiating wrt its texels) is precomputed
inside the trace, differentiably, and never cached."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .. import _memory
from .._api import keyword_only
from .._numerics import is_concrete
from .._pytree import unchecked

# called through the modules: tests count precompute calls
from ..ibl import diffuse, specular
from ..ibl.cubemap import Cubemap
from ..shading import shipped_luts
from .cache import AssetCache, cache_or_default, content_key
from .options import RenderOptions, _lut_smith, _options
from .plan import EnvironmentSplit, RenderPlan, _asset_bytes, _charlie_size, prefilter_size, split_environment
from .scene import Environment


def ibl_assets(split: EnvironmentSplit, p: RenderPlan, opts: RenderOptions, cache: AssetCache | None = None, *, submit=None):
    """The IBL assets the plan reads, (irradiance | None, prefiltered, LUT, suns | None, sheen |
    None), in the render dtype, for the environment as `split_environment` split it.

    Maps the environment carries (`bake`, or loaded from disk) are used as they are. Missing ones
    are computed: for a concrete environment through the content-addressed `cache` (default
    `ASSETS`; once per environment content and parameters, concrete even under an outer jit / grad
    / vmap); for a traced environment (differentiating wrt its texels) inside the trace, never
    cached.

    submit: a function that runs a job on a worker thread and returns its future. Given, the maps
    of a concrete environment are computed (or loaded) on the workers and a `PendingAssets` is
    returned at once: a staged render runs its geometry and direct-lighting stages meanwhile."""
    cache = cache_or_default(cache)
    suns, env = split
    key = _env_key(env, p)
    jobs = (
        lambda: _asset_irradiance(env, p, opts, key, cache),
        lambda: _asset_prefiltered(env, p, opts, key, cache),
        lambda: _asset_sheen(env, p, opts, cache),
    )
    if submit is None or not all(is_concrete(lv) for lv in env.radiance.levels):
        irr, pre, sheen = (job() for job in jobs)
        return irr, pre, _asset_lut(env, opts, cache), suns, sheen
    futures = [submit(job) for job in jobs]
    try:
        lut = _asset_lut(env, opts, cache)  # (here, while the maps are computed)
    except BaseException:
        for f in futures:  # (a refused LUT: the maps not started yet are dropped)
            f.cancel()
        raise
    return PendingAssets(suns, futures, lut, lambda: asset_shapes(env, p, opts, lut, suns))


class PendingAssets:
    """The IBL assets of a staged render while worker threads compute its maps: the suns
    (`env_lights`) now, the `ibl_assets` tuple when called (waiting for the maps), its shapes
    (`asset_shapes`) from `shapes()`; `cancel()` drops the jobs not started yet (a render that
    failed or was interrupted does not wait for a map still being computed)."""

    def __init__(self, env_lights, futures, lut, shapes):
        self.env_lights = env_lights
        self._futures = futures
        self._lut = lut
        self._shapes = shapes

    def __call__(self):
        irr, pre, sheen = (f.result() for f in self._futures)
        return irr, pre, self._lut, self.env_lights, sheen

    def shapes(self):
        return self._shapes()

    def cancel(self) -> None:
        for f in self._futures:
            f.cancel()


def asset_shapes(env: Environment, p: RenderPlan, opts: RenderOptions, lut, env_lights):
    """What `ibl_assets` returns for the plan, as `jax.ShapeDtypeStruct` leaves in the same tree
    (the maps' lookup metadata, which is part of a compiled program's identity, included),
    known before the maps are computed: a staged render compiles its IBL stage while the maps
    are still being computed (`_program_cache.ahead`). lut, env_lights: the LUT and suns (known
    then). Raises `NotAhead` where the plan reads a sheen map still to compute."""
    from .._program_cache import NotAhead
    from ..ibl.cubemap import CubeInfo

    dtype = jnp.dtype(opts.dtype)
    shape = lambda x: jax.ShapeDtypeStruct(x.shape, dtype)  # (after `_in_dtype`)
    C = env.radiance.channels

    def cube(sizes, info):
        return unchecked(Cubemap, levels=tuple(jax.ShapeDtypeStruct((6, n, n, C), dtype) for n in sizes), info=CubeInfo(info))

    irr = None
    if p.ibl_diffuse:
        irr = env.irradiance
        irr = cube([opts.irradiance_size], ()) if irr is None else jax.tree_util.tree_map(shape, irr)
    pre = env.prefiltered
    if pre is None:
        S = p.prefilter_size
        lookup = specular.prefilter_lookup(p.mapping_levels, mapping=opts.mapping, face_size=S)
        pre = cube([max(1, S >> m) for m in range(p.prefilter_levels)], tuple(lookup.items()))
    else:
        pre = jax.tree_util.tree_map(shape, pre)
    sheen = None
    if p.charlie_size:
        if env.charlie is None or env.sheen_lut is None:
            raise NotAhead("the sheen maps are still to compute")
        sheen = jax.ShapeDtypeStruct(np.shape(env.sheen_lut), dtype), jax.tree_util.tree_map(shape, env.charlie)
    return irr, pre, jnp.asarray(lut, dtype), env_lights, sheen


def _asset_sheen(env: Environment, p: RenderPlan, opts: RenderOptions, cache: AssetCache | None = None):
    """(sheen albedo table, Charlie-prefiltered cube) when the plan shades sheen under IBL, else None."""
    if not p.charlie_size:
        return None
    dtype = jnp.dtype(opts.dtype)
    table = env.sheen_lut
    if table is None:
        table = cache_or_default(cache).get("sheen_lut", (opts.lut_size, dtype.name), lambda: shipped_luts.sheen_lut(size=opts.lut_size))
    charlie = env.charlie
    if charlie is None:
        from ..ibl import sheen_prefilter

        src = env.radiance
        compute = lambda: sheen_prefilter.prefilter_charlie(src, size=p.charlie_size)
        if all(is_concrete(lv) for lv in src.levels):
            charlie = cache_or_default(cache).get("charlie", (content_key(src), p.charlie_size), compute)
        else:
            charlie = compute()
    return jnp.asarray(table, dtype), _in_dtype(charlie, opts)


def _env_key(env: Environment, p: RenderPlan):
    """The content key of a concrete environment with maps still to compute, else None."""
    missing = (p.ibl_diffuse and env.irradiance is None) or env.prefiltered is None
    if missing and all(is_concrete(lv) for lv in env.radiance.levels):
        return content_key(env.radiance)
    return None


def _in_dtype(c, opts: RenderOptions):
    dtype = jnp.dtype(opts.dtype)
    if c is None or all(lv.dtype == dtype for lv in c.levels):
        return c
    return Cubemap([lv.astype(dtype) for lv in c.levels], c.info)


def _asset_lut(env: Environment, opts: RenderOptions, cache: AssetCache | None = None):
    dtype = jnp.dtype(opts.dtype)
    smith = _lut_smith(opts)
    if env.lut is not None:
        if env.lut_smith != smith:
            raise ValueError(
                f"the environment's LUT was baked for Smith variant {env.lut_smith!r}, but model "
                f"{opts.model!r} reads a {smith!r} LUT; bake it with model={opts.model!r} (jaxpbr.bake)"
            )
        lut = env.lut
    else:
        lut = cache_or_default(cache).get(
            "lut", (opts.lut_size, smith, dtype.name), lambda: shipped_luts.brdf_lut(size=opts.lut_size, smith=smith, dtype=dtype)
        )
    return jnp.asarray(lut, dtype)


def _asset_irradiance(env: Environment, p: RenderPlan, opts: RenderOptions, key, cache: AssetCache | None = None):
    if not p.ibl_diffuse:
        return None
    irr = env.irradiance
    if irr is None:
        src = env.radiance
        params = (opts.irradiance_size, opts.irradiance_method)
        compute = lambda: diffuse.irradiance(src, size=opts.irradiance_size, method=opts.irradiance_method)
        irr = compute() if key is None else cache_or_default(cache).get("irradiance", (key,) + params, compute)
    return _in_dtype(irr, opts)


def _asset_prefiltered(env: Environment, p: RenderPlan, opts: RenderOptions, key, cache: AssetCache | None = None):
    pre = env.prefiltered
    if pre is None:
        src = env.radiance
        params = (p.prefilter_size, p.prefilter_levels, p.mapping_levels, opts.mapping, opts.prefilter_samples)

        def compute():
            kw = {} if opts.prefilter_samples is None else {"samples": opts.prefilter_samples}
            return specular.prefilter(
                src,
                size=p.prefilter_size,
                num_levels=p.mapping_levels,
                max_level=p.prefilter_levels - 1,
                mapping=opts.mapping,
                **kw,
            )

        if key is None:
            pre = compute()
        else:
            # A longer chain of the same map already cached: its first levels are this one.
            cache = cache_or_default(cache)
            longer = cache.find(
                "prefilter", lambda k: k[0] == key and k[1] == params[0] and k[3:] == params[2:] and k[2] > params[1]
            )
            if longer is not None:
                pre = Cubemap(longer.levels[: p.prefilter_levels], longer.info)
            else:
                pre = cache.get("prefilter", (key,) + params, compute)
    return _in_dtype(pre, opts)


@keyword_only("options")
def bake(
    environment: Environment, *, options: RenderOptions | None = None, sheen: bool = False, cache: AssetCache | None = None,
    **overrides,
) -> Environment:
    """The environment with every IBL asset a render can need precomputed: the irradiance map, the
    whole prefiltered chain (all roughnesses) and the split-sum LUT of the model's Smith variant.

        env = jaxpbr.bake(jaxpbr.Environment(radiance=cube))
        step = jax.jit(jax.value_and_grad(lambda m: loss(jaxpbr.render(scene(m, env)))))

    A render of a scene with a baked environment precomputes nothing, under `jit`, `grad` and
    `vmap` alike, and the baked environment is a pytree that can be passed into a jitted function
    as an argument (or closed over as a constant). Maps the environment already carries are kept.
    options, **overrides: as for `render` (irradiance_size / _method, prefilter_size / _samples,
    mapping, lut_size, dtype, and the model, which picks the LUT's Smith variant); a render
    with a model reading another LUT raises.

    For a concrete environment the assets come from (and go into) the content-addressed `cache` (an
    `AssetCache`; None: the process's default, `ASSETS`): baking the same texels twice computes
    once. A traced environment (differentiating with respect to its texels) is baked inside the
    trace, differentiably, and not cached.

    sheen: also bake what KHR_materials_sheen reads under IBL, the Charlie-prefiltered cube and the
    sheen albedo table (`Environment.charlie`, `.sheen_lut`). Off by default: the cube costs ~5x the
    GGX prefilter, and a render of a sheen material on an environment without it computes (and
    caches) it then.

    The suns are split out of the environment as a render splits them (`extract_lights`, on by
    default). `jaxpbr.write_baked` and `jaxpbr ibl` write files for an engine and default the other
    way on both counts (the sheen cube in, the suns left in the cubes); their docstring says why.
    """
    if not isinstance(environment, Environment):
        raise TypeError(f"bake expects a jaxpbr.Environment, got {type(environment).__name__}")
    opts = _options(options, overrides, "bake")
    size = prefilter_size(environment, opts)
    if environment.prefiltered is not None:
        levels = environment.prefiltered.num_levels
        M = int(environment.prefiltered.metadata.get("mapping_levels", levels))
    else:
        levels = M = specular.default_num_levels(size)
    probe = RenderPlan(direct=False, ibl=True, ibl_diffuse=True, env_background=False, emissive=False, textured=(),
                       normal_maps=False, max_roughness=1.0, prefilter_size=size, prefilter_levels=levels, mapping_levels=M, env_lights=0)
    _memory.require("baking the environment", _asset_bytes(environment, probe, opts, "bake"), where="bake")  # before any work
    cache = cache_or_default(cache)
    split = split_environment(environment, opts, cache)
    lights = split.suns
    full = RenderPlan(
        direct=False, ibl=True, ibl_diffuse=True, env_background=environment.show_background, emissive=False,
        textured=(), normal_maps=False, max_roughness=1.0, prefilter_size=size, prefilter_levels=levels,
        mapping_levels=M, env_lights=0 if lights is None else len(lights),
    )
    if sheen:
        full = dataclasses.replace(full, extensions=("sheen",), charlie_size=_charlie_size(environment))
    irr, pre, lut, lights, sheen_assets = ibl_assets(split, full, opts, cache)
    table, charlie = sheen_assets if sheen_assets is not None else (environment.sheen_lut, environment.charlie)
    return environment.replace(
        irradiance=irr, prefiltered=pre, lut=lut, lut_smith=_lut_smith(opts), lights=lights, charlie=charlie,
        sheen_lut=table,
    )

