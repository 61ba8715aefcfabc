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
sum), on the first surface hit; no shadows or inter-reflections. Misses show the environment at
mip 0 (or `Scene.background`).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import _memory
from .._api import keyword_only
from .._numerics import (
    is_concrete,
    outside_traces,
    pack3,
    remember_per_array,
    small_sq,
    unpack3,
    vcross,
    vdot,
    vnormalize,
    with_callers_context,
)
from .._pytree import Pytree, evolve, fields_of, unchecked
from .._validate import check_values, positive_int
from .._version import __version__

# called through the modules: tests count precompute calls
from ..ibl import diffuse, extract, specular
from ..ibl.cubemap import Cubemap
from ..ibl.shade import disc_multiscatter, shade_ibl
from ..io.atomic import atomic_write
from ..shading import shipped_luts
from ..shading.brdf_terms import MODEL_REGISTRY, check_options
from ..shading.layered import emission_soa
from ..shading.lights import shade_direct
from ..shading.lut import DEFAULT_SAMPLES as DEFAULT_LUT_SAMPLES
from ..shading.material import EXTENSIONS, Material
from . import texture
from .mesh import MAX_BLEND_LAYERS, Mesh, cast, concat_meshes, mesh_surface
from .shadows import shadow_visibility
from .scene import (
    Environment,
    Plane,
    Scene,
    Sphere,
    TexturedMaterial,
    TextureSlot,
    apply_extension_textures,
    texels,
    intersect_plane,
    intersect_sphere,
    primary_rays,
    sample_texture,
)

__all__ = [
    "ASSETS",
    "bake",
    "gbuffer",
    "RenderOptions",
    "RenderPlan",
    "plan",
    "render",
    "render_batch",
]

#: Up to this many spheres the ray cast is unrolled (fused by XLA); beyond, a fori_loop.
UNROLL_MAX_SPHERES = 8
#: Default pixels per chunk of `render_batch` (images x pixels x samples), bounding memory.
BATCH_CHUNK_PIXELS = 1 << 21
#: Largest default prefiltered face size.
DEFAULT_PREFILTER_SIZE = 128


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    """Static render options (hashable; part of the compiled program's identity).

    model: a `brdf_terms.MODEL_REGISTRY` name, "gltf" | "learnopengl" (direct BRDF and IBL
        combination; each model's IBL reads the LUT of its `lut_smith`, "schlick_ggx" for learnopengl).
    multiscatter: Fdez-Aguera energy compensation of the IBL term (None, the default: on for the
        gltf model, as the Khronos glTF Sample Viewer, three.js and Filament render glTF assets;
        rough metals are otherwise up to ~2.8x darker than in those viewers. False gives the
        single-scattering glTF BRDF that the float64 references (and Mitsuba) integrate. gltf only:
        True with another model raises ValueError). The suns split out of the environment get the
        same compensation (`ibl.multiscatter_weight` times their irradiance); punctual lights none (as the
        Sample Viewer and three.js; Filament compensates direct lights too).
    smith: gltf only: "correlated" (the glTF spec, default) or "separable" Smith-GGX G2, for the
        direct lighting (`brdf(smith=)`) and the IBL term alike (the split-sum LUT of that G,
        computed on first use: only the correlated and Schlick-GGX tables are shipped).
    irradiance_size / irradiance_method: `jaxpbr.irradiance` parameters (exact convolution default).
    prefilter_size: face size of the prefiltered map (default: min(env face size, 128), a
        power-of-two divisor of it); prefilter_samples: `jaxpbr.prefilter` samples (None = default).
    lut_size: split-sum LUT resolution (shipped 128 / 256 load instantly).
    mapping: roughness -> mip mapping of the prefiltered map ("linear" | "quadratic").
    dtype: float32 | float64 for the shading: a name, a NumPy or a JAX dtype (stored as its name).
    extract_lights: split dominant lights (suns) out of a concrete environment whose maps are
        computed here (`jaxpbr.ibl.extract.extract_lights`, defaults), shade them as analytic disc
        lights and the residual with the split sum (default True; the split sum alone is off by
        30-60 % on metals under a sun, issue 11). Once per environment content (cached). An
        environment with given maps uses its own `lights` (None: nothing is split).
    shadows: shadow rays from every lit pixel towards each light and each sun split out of the
        environment (`jaxpbr.rendering.shadows`; hard-edged). None (default): on for scenes with
        meshes (glTF assets), off for scenes of spheres and planes only; True / False force it.
        Image-based lighting itself is not shadowed (the materials' occlusion textures darken it).
    """

    model: str = "gltf"
    multiscatter: bool | None = None
    smith: str = "correlated"
    irradiance_size: int = 32
    irradiance_method: str = "exact"
    prefilter_size: int | None = None
    prefilter_samples: int | None = None
    lut_size: int = 128
    mapping: str = "linear"
    dtype: str = "float32"
    extract_lights: bool = True
    shadows: bool | None = None

    @property
    def compensates(self) -> bool:
        """Whether the IBL term is compensated for multiple scattering: `multiscatter`, or when it
        is None the model's default (on for gltf, the models with the option)."""
        if self.multiscatter is not None:
            return bool(self.multiscatter)
        spec = MODEL_REGISTRY.get(self.model)
        return spec is not None and "multiscatter" in spec.ibl_options

    def __post_init__(self):
        # multiscatter=None stays None (the model's default, resolved by `compensates`), so that
        # replacing only the model keeps meaning "the model's default".
        check_options(self.model, multiscatter=bool(self.compensates), smith=self.smith)
        try:
            name = np.dtype(self.dtype).name  # "float32", np.float64, jnp.float32, np.dtype(...)
        except TypeError:
            name = None
        if name not in ("float32", "float64"):
            raise ValueError(f"dtype must be float32 or float64 (a name, NumPy or JAX dtype), got {self.dtype!r}")
        object.__setattr__(self, "dtype", name)  # normalised: equal options hash alike
        for name in ("irradiance_size", "lut_size"):
            positive_int(name, getattr(self, name))


@dataclasses.dataclass(frozen=True)
class RenderPlan:
    """What a render traces and precomputes (static; see the module docstring)."""

    direct: bool
    ibl: bool
    ibl_diffuse: bool
    env_background: bool
    emissive: bool
    textured: tuple[int, ...]
    normal_maps: bool
    # Reporting only: left out of equality/hash so that materials differing only in roughness
    # reuse the compiled program (a continuous value in the static key recompiled per material).
    max_roughness: float = dataclasses.field(compare=False)
    prefilter_size: int
    prefilter_levels: int  # levels computed (0 without IBL)
    mapping_levels: int  # M of the roughness -> lod mapping
    band_rows: int = 0  # the stages render bands of this many rows (0: the whole image)
    env_lights: int = 0  # disc lights split out of the environment (shaded analytically)
    extensions: tuple[str, ...] = ()  # glTF material extensions some material uses (traced code)
    charlie_size: int = 0  # face size of the Charlie-prefiltered cube (sheen under IBL), 0: none
    shadows: bool = False  # shadow rays towards the lights and the extracted suns
    blend_layers: int = 1  # surfaces composited per pixel (> 1 with BLEND meshes)

    def describe(self) -> str:
        parts = [
            "direct lighting" if self.direct else "no direct lighting",
            (
                f"IBL (specular: {self.prefilter_levels}/{self.mapping_levels} mips of {self.prefilter_size}^2 for "
                f"r <= {self.max_roughness:.3g}; diffuse: {'yes' if self.ibl_diffuse else 'no (metals only)'})"
            )
            if self.ibl
            else "no IBL",
        ]
        if self.env_lights:
            parts.append(f"{self.env_lights} sun(s) split out of the environment as disc light(s)")
        if self.shadows:
            parts.append("shadows")
        if self.extensions:
            parts.append("material extensions: " + ", ".join(self.extensions))
        if self.charlie_size:
            parts.append(f"Charlie-prefiltered cube {self.charlie_size}^2 (sheen)")
        if self.textured:
            parts.append(f"{len(self.textured)} textured object(s)" + (" with normal maps" if self.normal_maps else ""))
        return "; ".join(parts)


# ------------------------------------------------------------------------------------------
# Planning
# ------------------------------------------------------------------------------------------


_RANGES: dict = {}  # (id(array), (op, channel)) -> (weakref to the array, value)
#: Arrays up to this many elements are reduced on the host (copying them costs less than a program).
_HOST_REDUCE_MAX = 64


@functools.partial(jax.jit, static_argnames=("op", "channel"))
def _reduce(x, *, op: str, channel):
    x = x if channel is None else x[..., channel]
    return jnp.max(x) if op == "max" else jnp.min(x)


def _bound(x, op: str, fallback: float, channel: int | None = None) -> float:
    """max / min of the concrete values of x (a channel of its last axis if given), or the
    fallback for traced values and None.

    A device array is reduced on the device and only the scalar comes back (the per-pixel maps of
    a G-buffer never travel to the host), and the result is remembered per array object (arrays are
    immutable): rendering the same scene again copies nothing."""
    if x is None or not is_concrete(x):
        return fallback

    def host():
        a = np.asarray(x)
        a = a if channel is None else a[..., channel]
        return float(a.max() if op == "max" else a.min())

    if not isinstance(x, jax.Array):
        return host()
    if x.size <= _HOST_REDUCE_MAX:  # a material constant: a few bytes to copy
        return remember_per_array(_RANGES, x, (op, channel), host)
    # Per-pixel maps: on the device, outside any trace the caller may be in (plan runs at trace time).
    return remember_per_array(_RANGES, x, (op, channel), lambda: outside_traces(lambda: float(_reduce(x, op=op, channel=channel))))


def _material_ranges(m) -> tuple[float, float, bool]:
    """(max roughness, min metallic, may emit) of a Material or TexturedMaterial."""
    if isinstance(m, TexturedMaterial):
        f = m.factors
        r = _bound(f.roughness, "max", 1.0)
        met = _bound(f.metallic, "min", 0.0)
        mr = texels(m.metallic_roughness_texture) if m.metallic_roughness_texture is not None else None
        if mr is not None:
            r *= _bound(mr, "max", 1.0, channel=1)
            met *= _bound(mr, "min", 0.0, channel=2)
        emits = _bound(f.emissive, "max", 1.0) > 0
        return r, met, emits
    return (
        _bound(m.roughness, "max", 1.0),
        _bound(m.metallic, "min", 0.0),
        _bound(m.emissive, "max", 1.0) > 0,
    )


def _material_extensions(m) -> tuple[tuple[str, ...], float]:
    """(extension groups present, max clear-coat roughness or 0) of a Material or TexturedMaterial."""
    f = m.factors if isinstance(m, TexturedMaterial) else m
    groups = f.extensions
    rc = 0.0
    if "clearcoat" in groups:
        rc = _bound(f.clearcoat_roughness, "max", 1.0) if f.clearcoat_roughness is not None else 0.0
    return groups, rc


def _union_extensions(mats) -> tuple[str, ...]:
    present = set()
    for m in mats:
        present.update(_material_extensions(m)[0])
    return tuple(g for g in EXTENSIONS if g in present)


def _prefilter_size(env: Environment, opts: RenderOptions) -> int:
    if env.prefiltered is not None:
        return env.prefiltered.face_size
    S0 = env.radiance.face_size
    if opts.prefilter_size is not None:
        return int(opts.prefilter_size)
    S = S0
    while S > DEFAULT_PREFILTER_SIZE and S % 2 == 0:
        S //= 2
    return S


@keyword_only("options")
def plan(scene: Scene, *, options: RenderOptions | None = None, **overrides) -> RenderPlan:
    """The RenderPlan of `scene` (what `render` will trace and precompute); options as for `render`."""
    opts = _options(options, overrides, "plan")
    if scene.gbuffer is not None:
        mats = [scene.gbuffer.material]
    else:
        mats = [ob.material for ob in scene.objects]
    ranges = [_material_ranges(m) for m in mats]
    extensions = _union_extensions(mats)
    # The clear coat reads the prefiltered map at its own roughness.
    r_max = max([r for r, _, _ in ranges] + [_material_extensions(m)[1] for m in mats])
    met_min = min(mt for _, mt, _ in ranges)
    emissive = any(e for _, _, e in ranges)
    textured = tuple(
        k for k, ob in enumerate(scene.objects) if isinstance(ob.material, TexturedMaterial)
    )
    normal_maps = any(scene.objects[k].material.has_normal_map for k in textured)
    env = scene.environment
    ibl = env is not None
    if ibl:
        size = _prefilter_size(env, opts)
        if env.prefiltered is not None:
            M = int(env.prefiltered.metadata.get("mapping_levels", env.prefiltered.num_levels))
            levels = env.prefiltered.num_levels
        else:
            M = specular.default_num_levels(size)
            # The lookup of the map `_asset_prefiltered` makes (prefilter's default lod_blend), in
            # NumPy: this runs at trace time, possibly inside a jit.
            levels = specular.levels_for_roughness(r_max, M, mapping=opts.mapping)
        diffuse = opts.compensates or met_min < 1.0
        env_lights = _env_split(env, opts)[0]
        n_env_lights = 0 if env_lights is None else len(env_lights)
        charlie_size = _charlie_size(env) if "sheen" in extensions else 0
    else:
        size, M, levels, diffuse, n_env_lights, charlie_size = 0, 0, 0, False, 0, 0
    objects = () if scene.gbuffer is not None else scene.objects
    has_mesh = any(isinstance(ob, Mesh) for ob in objects)
    shadows = opts.shadows if opts.shadows is not None else has_mesh
    shadows = bool(shadows and objects and (len(scene.lights) > 0 or n_env_lights > 0))
    blend = any(isinstance(ob, Mesh) and ob.alpha_mode == "BLEND" for ob in objects)
    return RenderPlan(
        blend_layers=MAX_BLEND_LAYERS if blend else 1,
        shadows=shadows,
        direct=len(scene.lights) > 0,
        ibl=ibl,
        ibl_diffuse=bool(ibl and diffuse),
        env_background=bool(ibl and env.show_background),
        emissive=emissive,
        textured=textured,
        normal_maps=normal_maps,
        max_roughness=r_max,
        prefilter_size=size,
        prefilter_levels=levels,
        mapping_levels=M,
        env_lights=n_env_lights,
        extensions=extensions,
        charlie_size=charlie_size,
    )


def _charlie_size(env: Environment) -> int:
    """Face size of the Charlie cube the plan reads: the environment's own, or the default."""
    if env.charlie is not None:
        return env.charlie.face_size
    from ..ibl import sheen_prefilter

    return min(sheen_prefilter.DEFAULT_CHARLIE_SIZE, env.radiance.face_size)


# ------------------------------------------------------------------------------------------
# Precomputed assets: a content-addressed cache
# ------------------------------------------------------------------------------------------


class AssetCache:
    """LRU cache of precomputed IBL maps keyed by (environment content hash, kind, parameters).

    It only ever holds concrete arrays: `get` runs the precompute outside any trace
    (`_numerics.outside_traces`), and the renderer caches nothing for a traced environment.

    `stats[kind]` counts hits and misses ("irradiance", "prefilter", "lut"), which is how tests
    and users check what a render actually computed.

    `directory`: optionally a folder where computed cube maps are also kept across processes
    (`use_directory`; the command line turns it on, under the user's cache dir): a map found
    there is loaded instead of computed. Files are keyed by the SHA-1 of (kind, key, jaxpbr and
    jax versions), written atomically, and a file that cannot be read is recomputed; failing to
    write one never fails the render. `stats[kind]["disk"]` counts the maps loaded from it.
    """

    DISK_KINDS = ("irradiance", "prefilter")

    def __init__(self, maxsize: int = 16, directory=None):
        self.maxsize = maxsize
        self._store: OrderedDict = OrderedDict()
        self.stats: dict[str, dict[str, int]] = {}
        self.directory = None if directory is None else Path(directory)
        # The renderer fills the cache from worker threads: the store and the counters are
        # updated under this lock (the precomputes themselves run outside it, concurrently).
        self._lock = threading.RLock()

    def use_directory(self, directory) -> None:
        """Keep computed maps in `directory` too (None: memory only)."""
        self.directory = None if directory is None else Path(directory)

    def clear(self) -> None:
        with self._lock:
            self._store.clear()
            self.stats.clear()

    def find(self, kind: str, match):
        """A cached value of `kind` whose key satisfies match(key), counted as a hit; else None."""
        with self._lock:
            for (k, key), value in self._store.items():
                if k == kind and match(key):
                    self.stats.setdefault(kind, {"hits": 0, "misses": 0})["hits"] += 1
                    return value
        return None

    def get(self, kind: str, key, compute):
        full = (kind, key)
        with self._lock:
            st = self.stats.setdefault(kind, {"hits": 0, "misses": 0})
            if full in self._store:
                st["hits"] += 1
                self._store.move_to_end(full)
                return self._store[full]
            st["misses"] += 1
        # Loaded on another thread too: inside a caller's trace device_put returns a tracer.
        value = outside_traces(lambda: self._load(kind, key))
        if value is not None:
            with self._lock:
                st["disk"] = st.get("disk", 0) + 1
        else:
            # On another thread: a compute that closed over a tracer raises UnexpectedTracerError
            # there instead of returning it, so the store never holds one.
            value = outside_traces(compute)
            self._save(kind, key, value)
        with self._lock:
            self._store[full] = value
            while len(self._store) > self.maxsize:
                self._store.popitem(last=False)
        return value

    def _path(self, kind, key):
        if self.directory is None or kind not in self.DISK_KINDS:
            return None
        name = hashlib.sha1(repr((kind, key, __version__, jax.__version__)).encode()).hexdigest()
        return self.directory / f"{kind}-{name}.npz"

    def _load(self, kind, key):
        path = self._path(kind, key)
        if path is None or not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                n = int(z["num_levels"])
                levels = [jax.device_put(z[f"level{i}"]) for i in range(n)]
                info = json.loads(str(z["info"]))
            return Cubemap(levels, info)
        except Exception:  # unreadable or from an incompatible writer: compute it again
            return None

    def _save(self, kind, key, value) -> None:
        path = self._path(kind, key)
        if path is None or not isinstance(value, Cubemap):
            return
        arrays = {f"level{i}": np.asarray(lv) for i, lv in enumerate(value.levels)}
        arrays["num_levels"] = np.asarray(len(value.levels))
        arrays["info"] = np.asarray(json.dumps(dict(value.info)))
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, lambda tmp: np.savez(tmp, **arrays))
        except OSError:  # full disk, read-only cache dir: the render goes on uncached
            pass


ASSETS = AssetCache()


_KEYS: dict = {}  # (id(level-0 array), "sha1") -> (weakref to it, content key)


def content_key(cube: Cubemap) -> str:
    """SHA-1 of a cube map's level-0 texels, shape and dtype (what its precomputes depend on).

    Remembered per array object (arrays are immutable), so rendering the same environment again
    neither copies it to the host nor hashes it again."""
    lv = cube.levels[0]

    def digest():
        a = np.ascontiguousarray(np.asarray(lv))
        h = hashlib.sha1(a.tobytes())
        h.update(repr((a.shape, str(a.dtype))).encode())
        return h.hexdigest()

    return remember_per_array(_KEYS, lv, "sha1", digest)


def _lut_smith(opts: RenderOptions) -> str:
    """The LUT's Smith term: the model's (`MODEL_REGISTRY`), or the separable Smith-GGX when the
    direct lighting uses it, so that both terms of a render shade with one G."""
    return "separable" if opts.smith == "separable" else MODEL_REGISTRY[opts.model].lut_smith


def _env_split(env: Environment, opts: RenderOptions):
    """(tuple of disc `DirectionalLight`s | None, the environment whose maps the split sum reads).

    The environment's own `lights` when it has them; else, for a concrete environment without
    given maps and `opts.extract_lights`, `extract.extract_lights` (cached per content in
    `ASSETS`); else (None, env)."""
    if env.lights is not None:
        return env.lights, env
    given = env.irradiance is not None or env.prefiltered is not None
    if not opts.extract_lights or given or not all(is_concrete(lv) for lv in env.radiance.levels):
        return None, env
    src = env.radiance

    def compute():
        ex = extract.extract_lights(src)
        return (ex.lights or None), ex.residual

    lights, residual = ASSETS.get("extract", (content_key(src), extract.DEFAULT_THRESHOLD, extract.DEFAULT_MIN_POWER_SHARE,
                                              extract.DEFAULT_MAX_ANGULAR_RADIUS, extract.DEFAULT_MAX_LIGHTS), compute)
    if lights is None:
        return None, env
    return lights, env.replace(radiance=residual)


def _env_assets(env: Environment, p: RenderPlan, opts: RenderOptions):
    """(irradiance | None, prefiltered, lut, disc lights | None) for the plan, in the render dtype.

    Maps the environment carries (`bake`, or loaded from disk) are used as they are. Missing ones
    are computed: for a concrete environment through the content-addressed `ASSETS` cache (once
    per environment content and parameters, concrete even under an outer jit / grad / vmap); for
    a traced environment (differentiating wrt its texels) inside the trace, never cached."""
    lights, env = _env_split(env, opts) if p.env_lights else (None, env)
    key = _env_key(env, p)
    return (
        _asset_irradiance(env, p, opts, key), _asset_prefiltered(env, p, opts, key), _asset_lut(env, opts), lights,
        _asset_sheen(env, p, opts),
    )


def _asset_sheen(env: Environment, p: RenderPlan, opts: RenderOptions):
    """(sheen albedo table, Charlie-prefiltered cube) when the plan shades sheen under IBL, else None."""
    if not p.charlie_size:
        return None
    dtype = jnp.dtype(opts.dtype)
    table = env.sheen_lut
    if table is None:
        table = ASSETS.get("sheen_lut", (opts.lut_size, dtype.name), lambda: shipped_luts.sheen_lut(opts.lut_size))
    charlie = env.charlie
    if charlie is None:
        from ..ibl import sheen_prefilter

        src = env.radiance
        compute = lambda: sheen_prefilter.prefilter_charlie(src, size=p.charlie_size)  # noqa: E731
        if all(is_concrete(lv) for lv in src.levels):
            charlie = ASSETS.get("charlie", (content_key(src), p.charlie_size), compute)
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


def _asset_lut(env: Environment, opts: RenderOptions):
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
        lut = ASSETS.get(
            "lut", (opts.lut_size, smith, dtype.name), lambda: shipped_luts.brdf_lut(opts.lut_size, smith=smith, dtype=dtype)
        )
    return jnp.asarray(lut, dtype)


def _asset_irradiance(env: Environment, p: RenderPlan, opts: RenderOptions, key):
    if not p.ibl_diffuse:
        return None
    irr = env.irradiance
    if irr is None:
        src = env.radiance
        params = (opts.irradiance_size, opts.irradiance_method)
        compute = lambda: diffuse.irradiance(src, opts.irradiance_size, method=opts.irradiance_method)  # noqa: E731
        irr = compute() if key is None else ASSETS.get("irradiance", (key,) + params, compute)
    return _in_dtype(irr, opts)


def _asset_prefiltered(env: Environment, p: RenderPlan, opts: RenderOptions, key):
    pre = env.prefiltered
    if pre is None:
        src = env.radiance
        params = (p.prefilter_size, p.prefilter_levels, p.mapping_levels, opts.mapping, opts.prefilter_samples)

        def compute():
            kw = {} if opts.prefilter_samples is None else {"samples": opts.prefilter_samples}
            return specular.prefilter(
                src,
                p.prefilter_size,
                num_levels=p.mapping_levels,
                max_level=p.prefilter_levels - 1,
                mapping=opts.mapping,
                **kw,
            )

        if key is None:
            pre = compute()
        else:
            # A longer chain of the same map already cached: its first levels are this one.
            longer = ASSETS.find(
                "prefilter", lambda k: k[0] == key and k[1] == params[0] and k[3:] == params[2:] and k[2] > params[1]
            )
            if longer is not None:
                pre = Cubemap(longer.levels[: p.prefilter_levels], longer.info)
            else:
                pre = ASSETS.get("prefilter", (key,) + params, compute)
    return _in_dtype(pre, opts)


@keyword_only("options")
def bake(environment: Environment, *, options: RenderOptions | None = None, sheen: bool = False, **overrides) -> Environment:
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

    For a concrete environment the assets come from (and go into) the content-addressed cache
    `ASSETS`: baking the same texels twice computes once. A traced environment (differentiating
    with respect to its texels) is baked inside the trace, differentiably, and not cached.

    sheen: also bake what KHR_materials_sheen reads under IBL, the Charlie-prefiltered cube and the
    sheen albedo table (`Environment.charlie`, `.sheen_lut`). Off by default: the cube costs ~5x the
    GGX prefilter, and a render of a sheen material on an environment without it computes (and
    caches) it then.
    """
    if not isinstance(environment, Environment):
        raise TypeError(f"bake expects a jaxpbr.Environment, got {type(environment).__name__}")
    opts = _options(options, overrides, "bake")
    size = _prefilter_size(environment, opts)
    if environment.prefiltered is not None:
        levels = environment.prefiltered.num_levels
        M = int(environment.prefiltered.metadata.get("mapping_levels", levels))
    else:
        levels = M = specular.default_num_levels(size)
    probe = RenderPlan(direct=False, ibl=True, ibl_diffuse=True, env_background=False, emissive=False, textured=(),
                       normal_maps=False, max_roughness=1.0, prefilter_size=size, prefilter_levels=levels, mapping_levels=M, env_lights=0)
    _memory.require("baking the environment", _asset_bytes(environment, probe, opts, "bake"), where="bake")  # before any work
    lights = _env_split(environment, opts)[0]
    full = RenderPlan(
        direct=False, ibl=True, ibl_diffuse=True, env_background=environment.show_background, emissive=False,
        textured=(), normal_maps=False, max_roughness=1.0, prefilter_size=size, prefilter_levels=levels,
        mapping_levels=M, env_lights=0 if lights is None else len(lights),
    )
    if sheen:
        full = dataclasses.replace(full, extensions=("sheen",), charlie_size=_charlie_size(environment))
    irr, pre, lut, lights, sheen_assets = _env_assets(environment, full, opts)
    table, charlie = sheen_assets if sheen_assets is not None else (environment.sheen_lut, environment.charlie)
    return environment.replace(
        irradiance=irr, prefiltered=pre, lut=lut, lut_smith=_lut_smith(opts), lights=lights, charlie=charlie,
        sheen_lut=table,
    )


# ------------------------------------------------------------------------------------------
# Geometry -> G-buffer
# ------------------------------------------------------------------------------------------


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
    """Nearest hit over all objects: (t, idx, hit), memory O(pixels)."""
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)
    shape = d[0].shape
    t_best = jnp.full(shape, big, dtype)
    idx = jnp.zeros(shape, jnp.int32)
    spheres = [k for k, ob in enumerate(objects) if isinstance(ob, Sphere)]
    planes = [k for k, ob in enumerate(objects) if isinstance(ob, Plane)]

    def take(t, ok, k, t_best, idx):
        better = ok & (t < t_best)
        return jnp.where(better, t, t_best), jnp.where(better, k, idx)

    if len(spheres) <= UNROLL_MAX_SPHERES:
        for k in spheres:
            c = tuple(jnp.asarray(objects[k].center, dtype)[i] for i in range(3))
            t, ok = intersect_sphere(o, d, c, jnp.asarray(objects[k].radius, dtype))
            t_best, idx = take(t, ok, k, t_best, idx)
    else:
        centers = jnp.stack([jnp.asarray(objects[k].center, dtype) for k in spheres])
        radii = jnp.stack([jnp.asarray(objects[k].radius, dtype) for k in spheres])
        ids = jnp.asarray(spheres, jnp.int32)

        def body(i, carry):
            c = tuple(centers[i, j] for j in range(3))
            t, ok = intersect_sphere(o, d, c, radii[i])
            return take(t, ok, ids[i], *carry)

        t_best, idx = jax.lax.fori_loop(0, len(spheres), body, (t_best, idx))
    for k in planes:
        pt = tuple(jnp.asarray(objects[k].point, dtype)[i] for i in range(3))
        nn = tuple(jnp.asarray(objects[k].normal, dtype)[i] for i in range(3))
        t, ok = intersect_plane(o, d, pt, nn)
        t_best, idx = take(t, ok, k, t_best, idx)
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
    plane_px = is_plane[idx] if K > 1 else is_plane[0]
    n_pl = vnormalize(tuple((pn[:, i][idx] if K > 1 else pn[0, i]) for i in range(3)))
    facing = jnp.where(vdot(n_pl, d) > 0, -1.0, 1.0)  # planes are two-sided
    n_pl = tuple(c * facing for c in n_pl)
    n = tuple(jnp.where(plane_px, n_pl[i], n_sph[i]) for i in range(3))
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
    """The scene's meshes concatenated (`mesh.concat_meshes`), or None without meshes."""
    meshes = [ob for ob in scene.objects if isinstance(ob, Mesh)]
    return concat_meshes(meshes, dtype) if meshes else None


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


def _shade_rest(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions, g, direct):
    """direct + environment IBL on hits, background elsewhere -> (H, W, 3)."""
    dtype = jnp.dtype(opts.dtype)
    n, view, m, hit, ray_dir = g["n"], g["view"], g["m"], g["hit"], g["ray"]
    shape = hit.shape
    out = direct
    env = scene.environment
    if p_plan.ibl:
        irr, pre, lut, env_lights, sheen = assets
        rot = -jnp.asarray(env.rotation, dtype)
        n_e = pack3(_rotate_y(n, rot))
        v_e = pack3(_rotate_y(view, rot))
        kw = {}
        if p_plan.extensions:
            # Vector inputs of the extensions in the environment's frame.
            kw = {k: (pack3(_rotate_y(unpack3(x), rot)) if k in ("tangent", "coat_normal", "transmit_direction") else x)
                  for k, x in _layer_kwargs(g, m, dtype).items()}
        sheen_kw = {} if sheen is None else {"sheen_lut": sheen[0], "charlie": sheen[1]}
        ibl = shade_ibl(n_e, v_e, m, irr, pre, lut, model=opts.model, multiscatter=opts.compensates, **kw, **sheen_kw)
        if p_plan.env_lights:
            # The suns split out of the environment, as disc lights in its frame (emission is
            # added once, by the direct stage).
            ls = _cast_floats(list(env_lights), dtype)
            dark = evolve(m, emissive=jnp.zeros_like(m.emissive))
            zero = jnp.zeros_like(n_e)
            kw.pop("transmit_direction", None)
            sheen_kw.pop("charlie", None)
            if "vis_env" in g:
                kw["visibility"] = g["vis_env"]
            ibl = ibl + shade_direct(zero, n_e, v_e, dark, ls, model=opts.model, smith=opts.smith, disc_lights=True, **kw, **sheen_kw)
            if opts.compensates:
                ibl = ibl + disc_multiscatter(n_e, v_e, m, lut, ls, visibility=kw.get("visibility"))
        ibl = jnp.asarray(env.intensity, dtype) * ibl
        out = ibl if out is None else out + ibl
    if out is None:
        out = jnp.zeros(shape + (3,), dtype)
    if p_plan.env_background:
        bg_dir = pack3(_rotate_y(ray_dir, -jnp.asarray(env.rotation, dtype)))
        bg = jnp.asarray(env.intensity, dtype) * env.radiance.sample(bg_dir.astype(env.radiance.dtype), 0.0).astype(dtype)
    else:
        bg = jnp.broadcast_to(jnp.asarray(scene.background, dtype), shape + (3,))
    return jnp.where(hit[..., None], out, bg)


def _geometry(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, offset, prim=None):
    """G-buffer of the scene (dict of Vec3 / arrays), before textures."""
    dtype = jnp.dtype(opts.dtype)
    if scene.gbuffer is not None:
        gb = scene.gbuffer
        view = vnormalize(unpack3(jnp.asarray(gb.view, dtype)))
        return dict(
            pos=unpack3(jnp.asarray(gb.position, dtype)),
            n=vnormalize(unpack3(jnp.asarray(gb.normal, dtype))),
            view=view,
            m=jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), gb.material),
            hit=gb.hit,
            ray=tuple(-c for c in view),
        )
    o_px, d_px = primary_rays(scene.camera, dtype=dtype, offset=offset, rows=p_plan.band_rows)
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
        arrays = concat_meshes([objects[k] for k in meshes], dtype)
        if prim is None:  # (BLEND layers pass the layer's primitives, cast once for all layers)
            prim = cast(arrays, o_px, d_px)
        ddir = _ray_differentials(scene.camera, d, dtype) if need_uv else None
        ms = mesh_surface(arrays, prim, o, d, need_uv=need_uv, ddir=ddir)
        on_mesh = prim >= 0
        idx_m = jnp.asarray(meshes, jnp.int32)[ms["object"]]
        if analytic:
            on_mesh = on_mesh & (~hit | (ms["t"] < t))
            pick = lambda a, b: tuple(jnp.where(on_mesh, a[i], b[i]) for i in range(len(a)))  # noqa: E731
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
    if p_plan.shadows:
        # The geometric normal (before normal maps): shadow rays leave the surface along it.
        ng = n if not meshes else (ms["ng"] if not analytic else tuple(jnp.where(on_mesh, ms["ng"][i], n_an[i]) for i in range(3)))
    m = _gather_material(_stack_materials(objects, dtype, ext), idx)
    if meshes and "color" in ms:
        # COLOR_0 multiplies the base colour (glTF); 1 on other objects.
        rgb = jnp.where(on_mesh[..., None], ms["color"][..., :3], 1.0)
        m = evolve(m, base_color=m.base_color * rgb)
    g = dict(pos=pos, n=n, view=tuple(-c for c in d), m=m, hit=hit, ray=d, t=t, idx=idx)
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
    if p_plan.shadows:
        g["ng"] = ng
        if p_plan.direct:
            lights = _cast_floats(list(scene.lights), dtype)
            g["vis"] = shadow_visibility(objects, arrays if meshes else None, pos, ng, lights, dtype)
    if need_uv:
        g.update(idx=idx, uv=uv, tangent=tangent)
        if tw is not None:
            g.update(tangent_w=tw, uv1=uv1, duv=duv)
    if "volume" in ext:
        # Sphere radius per pixel (0 on planes): the volume's path is the sphere's chord.
        radii = jnp.asarray([float(0.0) if isinstance(ob, Plane) else 1.0 for ob in objects], dtype)
        rad = jnp.stack([jnp.asarray(ob.radius if isinstance(ob, Sphere) else 0.0, dtype) for ob in objects]) * radii
        g["radius"] = rad[idx] if len(objects) > 1 else jnp.broadcast_to(rad[0], idx.shape)
    return g


def _ray_differentials(cam, d, dtype):
    """dD/dx, dD/dy (Vec3s) of the pinhole camera's unit ray directions d per pixel (Igehy 1999):
    the unnormalised direction f + x r + y u moves by (2 tan(fov/2)/H) r per column and
    -(2 tan(fov/2)/H) u per row, and has length 1/(D.f); dD = (dd - D (D.dd)) / |d|."""
    from .scene import camera_basis

    _, f, r, u = camera_basis(cam, dtype)
    k = 2.0 * jnp.tan(jnp.deg2rad(jnp.asarray(cam.fov_y_deg, dtype)) / 2) / cam.height
    inv_len = vdot(d, f)  # 1/|d|
    out = []
    for dd in (tuple(k * c for c in r), tuple(-k * c for c in u)):
        dn = vdot(d, dd)
        out.append(tuple((dd[i] - d[i] * dn) * inv_len for i in range(3)))
    return tuple(out)


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


def _render_pass(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions, offset, staged: bool = False):
    """One sample per pixel at sub-pixel `offset`.

    staged=True runs the stages -- geometry, each textured object, direct lighting, IBL +
    background -- as separate compiled programs (what `render` does outside transformations).
    XLA:CPU otherwise fuses producers into every consumer and recomputes them there (each
    light, lookup and colour channel): measured 2.7x slower for direct + IBL at 1080p and 1000x
    slower with two normal-mapped objects; `lax.optimization_barrier` does not prevent it (it is
    expanded away before fusion). Under an outer jit/vmap the stages inline into one program.
    """
    if p_plan.blend_layers > 1:
        return _blended_pass(scene, assets, p_plan, opts, offset, staged)
    g = (_geometry_jit if staged else _geometry)(scene, p_plan, opts, offset)
    return _shade_pass(scene, assets, p_plan, opts, g, staged)


def _blended_pass(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions, offset, staged: bool):
    """BLEND meshes: the nearest `blend_layers` surfaces of each pixel (cast once), each shaded as
    an image of its own by the same compiled stages, composited front to back with their alpha
    (C = sum_k a_k prod_{j<k} (1 - a_j) C_k; an opaque surface or the background ends the pixel)."""
    prims = (_layer_prims_jit if staged else _layer_prims)(scene, p_plan, opts, offset)
    out, keep = None, None
    for k in range(p_plan.blend_layers):
        g = (_geometry_jit if staged else _geometry)(scene, p_plan, opts, offset, prims[..., k])
        c = _shade_pass(scene, assets, p_plan, opts, g, staged)
        a = g["alpha"][..., None]
        if k == p_plan.blend_layers - 1:
            a = jnp.ones_like(a)  # the last layer covers what is left
        out = a * c if out is None else out + keep * a * c
        keep = (1.0 - a) if keep is None else keep * (1.0 - a)
    return out


def _layer_prims(scene: Scene, p_plan: RenderPlan, opts: RenderOptions, offset):
    dtype = jnp.dtype(opts.dtype)
    o_px, d_px = primary_rays(scene.camera, dtype=dtype, offset=offset, rows=p_plan.band_rows)
    return cast(_mesh_arrays(scene, dtype), o_px, d_px, layers=p_plan.blend_layers)


_layer_prims_jit = jax.jit(_layer_prims, static_argnums=(1, 2))


def _shade_pass(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions, g, staged: bool):
    """Textures, direct lighting and IBL + background of the G-buffer `g`."""
    # The later stages see the pixels, not the meshes' arrays: meshes of other sizes reuse them.
    lean = _lean(scene)
    for k in p_plan.textured:
        g = (_texture_jit if staged else _texture)(lean, k, opts, g)
    direct = (_shade_direct_jit if staged else _shade_direct)(lean, p_plan, opts, g)
    if callable(assets):  # staged: assets still being computed on another thread
        assets = assets()
    if p_plan.shadows and p_plan.env_lights:
        g = {**g, "vis_env": (_sun_shadows_jit if staged else _sun_shadows)(scene, opts, g, assets[3])}
    return (_shade_rest_jit if staged else _shade_rest)(lean, assets, p_plan, opts, g, direct)


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


def _sun_shadows(scene: Scene, opts: RenderOptions, g, env_lights):
    """(H, W, L) visibility of the suns split out of the environment (world directions: the
    environment's frame turned by +rotation)."""
    dtype = jnp.dtype(opts.dtype)
    rot = jnp.asarray(scene.environment.rotation, dtype)
    ls = _cast_floats(list(env_lights), dtype)
    to_sun = [_rotate_y(tuple(-jnp.asarray(s.direction, dtype)[i] for i in range(3)), rot) for s in ls]
    return shadow_visibility(scene.objects, _mesh_arrays(scene, dtype), g["pos"], g["ng"], to_sun, dtype, directions_only=True)


_sun_shadows_jit = jax.jit(_sun_shadows, static_argnums=(1,))
_geometry_jit = jax.jit(_geometry, static_argnums=(1, 2))
_texture_jit = jax.jit(_texture, static_argnums=(1, 2))
_shade_direct_jit = jax.jit(_shade_direct, static_argnums=(1, 2))
_shade_rest_jit = jax.jit(_shade_rest, static_argnums=(2, 3))


def _render_traced(scene: Scene, assets, p_plan: RenderPlan, opts: RenderOptions):
    s = 1 if scene.gbuffer is not None else scene.camera.supersample
    dtype = jnp.dtype(opts.dtype)
    if s == 1:
        return _render_pass(scene, assets, p_plan, opts, jnp.asarray((0.5, 0.5), dtype))

    def body(k, acc):
        off = jnp.stack([((k % s).astype(dtype) + 0.5) / s, ((k // s).astype(dtype) + 0.5) / s])
        return acc + _render_pass(scene, assets, p_plan, opts, off)

    H, W = scene.image_shape
    acc = jax.lax.fori_loop(0, s * s, body, jnp.zeros((H, W, 3), dtype))
    return acc / (s * s)


_render_jit = jax.jit(_render_traced, static_argnums=(2, 3))


_OPTION_FIELDS = tuple(f.name for f in dataclasses.fields(RenderOptions))


def _options(options, overrides: dict, fn: str) -> RenderOptions:
    """`options` (a RenderOptions, or None for the defaults) with the keyword `overrides` applied
    on top (`dataclasses.replace`, so the result is validated again)."""
    if options is not None and not isinstance(options, RenderOptions):
        raise TypeError(
            f"{fn}: options must be a jaxpbr.RenderOptions, got {type(options).__name__}; pass "
            f"options=RenderOptions(...), or the fields as keywords, e.g. {fn}(scene, model='gltf')"
        )
    unknown = sorted(set(overrides) - set(_OPTION_FIELDS))
    if unknown:
        raise TypeError(f"{fn}: unknown render option(s) {unknown}; the RenderOptions fields are {list(_OPTION_FIELDS)}")
    if options is None:
        return RenderOptions(**overrides)
    return dataclasses.replace(options, **overrides) if overrides else options


def check_memory(scene: Scene, *, options: RenderOptions | None = None, where: str = "render", names: dict | None = None) -> None:
    """Refuse, before any work, a render of `scene` whose image, textures or IBL precomputes (those
    its environment does not carry) would need more memory than is available: a ValueError
    (`_memory.MemoryLimitError`) naming the field to lower (`names` maps the fields to a front
    end's own flags or keys)."""
    opts = options if options is not None else RenderOptions()
    H, W = scene.image_shape
    textures = {}
    for obj in scene.objects:
        m = getattr(obj, "material", None)
        if isinstance(m, TexturedMaterial):
            for f in fields_of(m):
                x = getattr(m, f.name)
                if f.name.endswith("_texture") and x is not None:
                    textures[id(x)] = np.shape(texels(x))
    parts = _memory.render_bytes(W, H, textures.values())
    meshes = [ob for ob in scene.objects if isinstance(ob, Mesh)] if scene.gbuffer is None else []
    parts |= _memory.mesh_bytes(sum(m.num_vertices for m in meshes), sum(m.num_triangles for m in meshes))
    parts = {
        ("Camera.width/height" if k == "width/height" else "the textures' resolution" if k == "textures"
         else "the meshes' triangle count" if k == "triangles" else k): v
        for k, v in parts.items()
    }
    env = scene.environment
    if env is not None:
        # (the plan without the light extraction, which is work; the maps' sizes are the same)
        parts |= _asset_bytes(env, plan(scene, options=dataclasses.replace(opts, extract_lights=False)), opts, where)
    what = f"rendering {W}x{H}" + (f" with {len(textures)} texture(s)" if textures else "") + (" and the environment's IBL maps" if env is not None else "")
    _memory.require(what, parts, where=where, names=names)


def _asset_bytes(env: Environment, p: RenderPlan, opts: RenderOptions, where: str) -> dict:
    """The memory of the IBL precomputes a render (or bake) of `env` would run, by option."""
    parts: dict = {}
    if not p.ibl:
        return parts
    if env.prefiltered is None:
        n = specular.DEFAULT_SAMPLES if opts.prefilter_samples is None else positive_int("prefilter_samples", opts.prefilter_samples)
        _memory.check_samples("prefilter_samples", n, where=where)
        counts = specular.default_sample_counts(n, p.prefilter_size, p.mapping_levels)[: p.prefilter_levels]
        pre = _memory.prefilter_bytes(env.radiance.face_size, p.prefilter_size, counts)
        parts["the environment's face size"] = pre["face_size"]
        parts["prefilter_samples"] = pre["samples"]
    if p.ibl_diffuse and env.irradiance is None:
        parts["irradiance_size"] = _memory.irradiance_bytes(opts.irradiance_size)["size"]
    if env.lut is None and shipped_luts._shipped_entry(opts.lut_size, opts.lut_size, _lut_smith(opts), DEFAULT_LUT_SAMPLES) is None:
        parts["lut_size"] = sum(_memory.lut_bytes(opts.lut_size, opts.lut_size, DEFAULT_LUT_SAMPLES).values())
    return parts


def render(scene: Scene, *, options: RenderOptions | None = None, progress=None, **overrides) -> jax.Array:
    """Render `scene` to linear HDR radiance (H, W, 3) (Rec.709 primaries, scene-referred).

    options: a `RenderOptions` value (default: `RenderOptions()`).
    progress: optional callable(done, total) in passes (bands of rows x sub-pixel samples), called
      on the caller's thread as each pass is dispatched and once when the image is ready (staged
      renders, i.e. on the CPU outside jit; a one-program render reports only its end).
    **overrides: `RenderOptions` fields as keywords (model, multiscatter, smith, irradiance_size,
      irradiance_method, prefilter_size, prefilter_samples, lut_size, mapping, dtype,
      extract_lights), applied on top of `options`: `render(scene, options=opts, model="learnopengl")` renders with
      `dataclasses.replace(opts, model="learnopengl")`.
    Differentiable with respect to every array in the scene (materials, textures, lights, camera,
    environment texels).
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"render expects a jaxpbr.Scene, got {type(scene).__name__}")
    opts = _options(options, overrides, "render")
    check_memory(scene, options=opts)  # before any work (a huge size aborted inside XLA)
    p = plan(scene, options=opts)
    env = scene.environment
    if not _staged():
        out = _render_jit(scene, _env_assets(env, p, opts) if p.ibl else None, p, opts)
        if progress is not None:
            progress(1, 1)
        return out
    if p.ibl and all(is_concrete(lv) for lv in env.radiance.levels):
        # The prefiltered and irradiance maps of a concrete environment are computed (or loaded)
        # on two worker threads while this one traces, compiles and runs the geometry and
        # direct-lighting stages, which do not need them: on a cold start the compilations and
        # runs overlap (XLA compiles and runs without holding the GIL).
        env_lights, env = _env_split(env, opts) if p.env_lights else (None, env)
        key = _env_key(env, p)
        pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="jaxpbr-assets")
        try:
            pre = pool.submit(with_callers_context(lambda: _asset_prefiltered(env, p, opts, key)))
            irr = pool.submit(with_callers_context(lambda: _asset_irradiance(env, p, opts, key)))
            sheen = pool.submit(with_callers_context(lambda: _asset_sheen(env, p, opts)))
            lut = _asset_lut(env, opts)
            return _banded(scene, opts, p, lambda sc, pb, off: _render_pass(
                sc, lambda: (irr.result(), pre.result(), lut, env_lights, sheen.result()), pb, opts, off, staged=True), progress)
        finally:
            # On success both maps were used; on an error or an interrupt do not wait for a
            # precompute still running (`with` would join it).
            pool.shutdown(wait=False, cancel_futures=True)
    assets = _env_assets(env, p, opts) if p.ibl else None
    return _banded(scene, opts, p, lambda sc, pb, off: _render_pass(sc, assets, pb, opts, off, staged=True), progress)


#: `render` (staged) renders images larger than this in bands of about this many pixels, so its
#: memory is the image plus one band's G-buffer (~150 bytes per pixel on the CPU) at any size.
BAND_PIXELS = 1 << 21


def _banded(scene: Scene, opts: RenderOptions, p: RenderPlan, one_pass, progress=None):
    """`_supersampled` over the whole image, or band by band (rows of ~BAND_PIXELS pixels, one
    compiled program per stage for every band: the band's first row is an argument) into one
    host buffer when the image is larger; a user G-buffer is rendered whole. progress: per pass
    (bands x sub-pixel samples), the last once the image is ready."""
    H, W = scene.image_shape
    s = 1 if scene.gbuffer is not None else scene.camera.supersample
    whole = scene.gbuffer is not None or H * W <= BAND_PIXELS
    rows = H if whole else max(1, BAND_PIXELS // W)
    total = -(-H // rows) * s * s
    if whole:
        out = _supersampled(scene, opts, lambda sc, off: one_pass(sc, p, off), progress=_passes(progress, 0, total))
    else:
        # Bands stay on the device (and traceable: `render` under jit/grad on the CPU takes this
        # path too) and are joined once; the last band's rows past the image are cut off.
        pb = dataclasses.replace(p, band_rows=rows)
        bands = [
            _supersampled(scene, opts, lambda sc, off: one_pass(sc, pb, off), row0=y0, progress=_passes(progress, b * s * s, total))
            for b, y0 in enumerate(range(0, H, rows))
        ]
        out = jnp.concatenate(bands)[:H]
    if progress is not None:
        out = jax.block_until_ready(out)
        progress(total, total)
    return out


def _passes(progress, offset: int, total: int):
    """progress(done, total) of the whole render for one `_supersampled` call's passes (None: none)."""
    if progress is None:
        return None
    return lambda k: progress(offset + k, total) if offset + k < total else None


def _supersampled(scene: Scene, opts: RenderOptions, one_pass, row0: int | None = None, progress=None):
    """The mean of one_pass(scene, offset) over the camera's s x s sub-pixel offsets, run from the
    host one after another (`render` and `render_batch` outside transformations).

    The offset is an argument, not a static value, and the passes get the scene with
    supersample = 1 (a static field the stages do not read): one compiled program per stage
    whatever s (before: one per offset, s^2 of them). row0: the first row of a band (`_banded`),
    passed as the offset's third entry."""
    s = 1 if scene.gbuffer is not None else scene.camera.supersample
    if s > 1:
        scene = evolve(scene, camera=evolve(scene.camera, supersample=1))
    dtype = jnp.dtype(opts.dtype)
    acc = None
    for k in range(s * s):
        off = ((k % s + 0.5) / s, (k // s + 0.5) / s) + (() if row0 is None else (row0,))
        off = jax.device_put(np.asarray(off, dtype))
        one = one_pass(scene, off)
        acc = one if acc is None else acc + one
        if progress is not None:
            progress(k + 1)
    return acc if s == 1 else acc / (s * s)


#: How `render` runs outside transformations: True = staged (geometry, textures, direct, IBL as
#: separate programs), False = one program, None = the backend decides (staged on XLA:CPU only).
STAGED: bool | None = None


def _staged() -> bool:
    """XLA:CPU fuses producers into every consumer and recomputes them there (see `_render_pass`),
    so on the CPU the stages run as separate programs. GPUs do not pay that: one program per render
    there, no intermediate G-buffer round trips through memory and one dispatch instead of four
    (issue 10 measured 2.24 ms staged against 0.33 ms fused for a 1080p G-buffer on an H100)."""
    if STAGED is not None:
        return bool(STAGED)
    return jax.default_backend() == "cpu"


# ------------------------------------------------------------------------------------------
# Batches
# ------------------------------------------------------------------------------------------


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
    return evolve(scene, **changes)


@functools.partial(jax.jit, static_argnums=(3, 4, 5, 6, 7))
def _batch_jit(scene, assets, b, p_plan, opts, objects_idx, chunk, mesh):
    def run(scene, assets, b):
        one = lambda x: _render_traced(_substitute(scene, x, objects_idx), assets, p_plan, opts)  # noqa: E731
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
    **overrides,
) -> jax.Array:
    """Render B variants of `scene` in one jitted, vmapped call -> (B, H, W, 3).

    Batched inputs (each with a leading axis B; give any combination):
      materials: a Material whose leaves are (B, ...): replaces the material of the objects listed
        in `objects` (default: all; for a TexturedMaterial its factors), or of a G-buffer scene.
      cameras: a Camera whose array fields are (B, ...) (same width/height/supersample).
      lights: a list of lights whose fields are (B, ...); replaces the scene's lights.
      env_rotation, env_intensity: (B,) environment rotations about +Y (radians) / intensities.
    chunk: images rendered together per step (`lax.map` batch size), bounding memory; default
      keeps about 2M pixel samples per step.
    devices: None (all local devices), a list of devices, or 1: the batch is sharded over them
      with `jax.sharding` (shard_map over a 1-D mesh "batch"); each device renders its share in
      chunks. Results equal the single-device path to float rounding (measured: at most 1 ulp;
      the per-device programs are compiled separately and XLA may fuse them differently).
    options, **overrides: as for `render`. Precomputes are shared by the whole batch (rotations and
    intensities need none).
    """
    from jax.sharding import Mesh

    opts = _options(options, overrides, "render_batch")
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
    if not b:
        raise ValueError("render_batch needs at least one batched input (materials, cameras, lights, env_rotation, env_intensity)")
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
    p_plan = plan(plan_scene, options=opts)
    assets = _env_assets(base.environment, p_plan, opts) if p_plan.ibl else None

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
    out = _batch_jit(base, assets, b, p_plan, opts, objects_idx, chunk, mesh)
    return out[:B]


_CHUNK_STATIC = ("p_plan", "opts", "objects_idx")


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _geometry_chunk(scene, bc, off, *, p_plan, opts, objects_idx):
    """The geometry stage vmapped over a chunk of batched inputs bc (the sub-pixel offset shared)."""
    return jax.vmap(lambda x: _geometry(_substitute(scene, x, objects_idx), p_plan, opts, off))(bc)


@functools.partial(jax.jit, static_argnames=("k",) + _CHUNK_STATIC)
def _texture_chunk(scene, bc, g, *, k, p_plan, opts, objects_idx):
    return jax.vmap(lambda x, gx: _texture(_substitute(scene, x, objects_idx), k, opts, gx))(bc, g)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _direct_chunk(scene, bc, g, *, p_plan, opts, objects_idx):
    return jax.vmap(lambda x, gx: _shade_direct(_substitute(scene, x, objects_idx), p_plan, opts, gx))(bc, g)


@functools.partial(jax.jit, static_argnames=_CHUNK_STATIC)
def _rest_chunk(scene, bc, g, assets, direct, *, p_plan, opts, objects_idx):
    def one(x, gx, dx):
        return _shade_rest(_substitute(scene, x, objects_idx), assets, p_plan, opts, gx, dx)

    return jax.vmap(one)(bc, g, direct)


def _render_batch_staged(scene, assets, b, p_plan, opts, objects_idx, chunk):
    """`render_batch` on XLA:CPU: for each chunk of `chunk` images, the render's stages as
    separate programs, each vmapped over the chunk (one program over the whole chunk fuses and
    recomputes producers on XLA:CPU, measured 3x slower than a Python loop of `render`; see
    `_render_pass`). Host loop over the chunks."""
    kw = dict(p_plan=p_plan, opts=opts, objects_idx=objects_idx)
    b = jax.device_put(b)  # once (set up on the host): each chunk is then cut on the device
    total = jax.tree_util.tree_leaves(b)[0].shape[0]

    def one_pass(bc):
        def run(sc, off):
            g = _geometry_chunk(sc, bc, off, **kw)
            for t in p_plan.textured:
                g = _texture_chunk(sc, bc, g, k=t, **kw)
            return _rest_chunk(sc, bc, g, assets, _direct_chunk(sc, bc, g, **kw), **kw)

        return run

    # The chunk is cut on the device by one program (its start is an argument).
    outs = [_supersampled(scene, opts, one_pass(_take_chunk(b, i, n=chunk))) for i in range(0, total, chunk)]
    return jnp.concatenate(outs) if len(outs) > 1 else outs[0]


@functools.partial(jax.jit, static_argnames=("n",))
def _take_chunk(b, start, *, n):
    return jax.tree_util.tree_map(lambda x: jax.lax.dynamic_slice_in_dim(x, start, n), b)


# ------------------------------------------------------------------------------------------
# G-buffer
# ------------------------------------------------------------------------------------------


@keyword_only("options")
def gbuffer(scene: Scene, *, options: RenderOptions | None = None, **overrides):
    """The G-buffer `render` shades: the nearest surface at each pixel centre of the camera (its
    `supersample` is not used), materials after textures, COLOR_0 and normal maps -> `GBuffer`
    with (H, W) / (H, W, 3) leaves in the options' dtype: hit, position, normal (the shading
    normal), view (unit, towards the camera) and a per-pixel `Material` (the extension fields of
    the groups some object uses, the others None). Off the surfaces (hit False) the values are
    undefined. A scene given as a G-buffer returns its own. Lights and environment are not read
    (nothing is precomputed); options as for `render` (only dtype matters)."""
    from .scene import GBuffer

    if not isinstance(scene, Scene):
        raise TypeError(f"gbuffer expects a jaxpbr.Scene, got {type(scene).__name__}")
    opts = _options(options, overrides, "gbuffer")
    if scene.gbuffer is not None:
        return scene.gbuffer
    bare = evolve(scene, lights=(), environment=None, camera=evolve(scene.camera, supersample=1))
    p = plan(bare, options=opts)
    dtype = jnp.dtype(opts.dtype)
    g = _geometry_jit(bare, p, opts, jax.device_put(np.asarray((0.5, 0.5), dtype)))
    lean = _lean(bare)
    for k in p.textured:
        g = _texture_jit(lean, k, opts, g)
    return GBuffer(hit=g["hit"], position=pack3(g["pos"]), normal=pack3(g["n"]), view=pack3(g["view"]), material=g["m"])
