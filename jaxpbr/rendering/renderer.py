"""`render` and `render_batch`: compose only what a scene needs into one jitted program.

`render(scene)` first reads the scene's *static structure* and concrete values into a `RenderPlan`
(what to trace and what to precompute), then fetches the precomputed IBL assets it needs from a
content-addressed cache, then runs one jitted program:

* no lights -> no direct-lighting code is traced;
* no environment -> no IBL lookups and no precompute at all;
* only metals (metallic == 1 everywhere, no multiscatter) -> no irradiance map;
* maximum roughness r_max -> the prefiltered chain is computed only up to the mip that
  lod(r_max) reaches (`specular.levels_for_roughness`; the lookup still refers to the full chain of
  M levels);
* no textures / normal maps / emissive -> none of their code.

Values that are traced (inside `jax.grad`, `jax.vmap`) cannot be inspected; the plan then assumes
the general case for them (e.g. a traced roughness may reach 1, so every mip is prefiltered), and
a traced environment is precomputed inside the trace (differentiable, not cached).

Shading = `shade_direct` (punctual lights, emissive) + `Environment.intensity * shade_ibl` (split
sum), on the first surface hit, with shadow rays towards the lights when the plan has them; no
inter-reflections. Misses show the environment at mip 0 (or `Scene.background`).

The renderer is split by responsibility; this module is its public face and re-exports the names
other modules and users import from it:

* `options`: `RenderOptions` and how `options=` and keyword overrides combine;
* `plan`: `RenderPlan` / `plan` (what a scene needs) and `check_memory`;
* `cache`: `AssetCache`, the default cache `ASSETS`, `content_key`;
* `assets`: the IBL assets a plan reads, through the cache, and `bake`;
* `stages`: the stages as traced functions and compiled programs, and `gbuffer`;
* `execute`: `render` and how it runs (staged or one program, bands, sub-pixel passes, workers);
* `batching`: `render_batch`.

How `render` runs (staged or one program, the band size, the rays on the device) is the process's
`EXECUTION` (`execution.Execution`): `renderer.EXECUTION.staged = False` runs one program per render.
"""

from __future__ import annotations

from .assets import bake  # noqa: F401
from .batching import BATCH_CHUNK_PIXELS, render_batch  # noqa: F401
from .cache import ASSETS, AssetCache, content_key  # noqa: F401
from .execute import EXECUTION, Execution, clear_caches, deformable, render  # noqa: F401
from .options import RenderOptions  # noqa: F401
from .plan import DEFAULT_PREFILTER_SIZE, RenderPlan, check_memory, plan, prefilter_size  # noqa: F401
from .stages import UNROLL_MAX_SPHERES, gbuffer  # noqa: F401

__all__ = [
    "ASSETS",
    "RenderOptions",
    "RenderPlan",
    "bake",
    "clear_caches",
    "deformable",
    "gbuffer",
    "plan",
    "render",
    "render_batch",
]
