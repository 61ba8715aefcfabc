"""`plan`: what a scene needs, read from its static structure and concrete values before anything
is traced (`RenderPlan`: the code to trace, the precomputes to run), and `check_memory`: the
memory that work would take, refused before it starts.

Values that are traced (inside `jax.grad`, `jax.vmap`) cannot be inspected; the plan then assumes
the general case for them (e.g. a traced roughness may reach 1, so every mip is prefiltered)."""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _memory
from .._api import keyword_only
from .._numerics import is_concrete, outside_traces, remember_per_array
from .._program_cache import package_digest
from .._pytree import fields_of
from .._validate import positive_int

# called through the modules: tests count precompute calls
from ..ibl import extract, specular
from ..shading import shipped_luts
from ..shading.lut import DEFAULT_SAMPLES as DEFAULT_LUT_SAMPLES
from ..shading.material import EXTENSIONS
from .cache import AssetCache, cache_or_default, content_key
from .execution import EXECUTION
from .mesh import MAX_BLEND_LAYERS, Mesh, _embree
from .options import RenderOptions, _lut_smith, _options
from .scene import Environment, Scene, TexturedMaterial, texels

#: Largest default prefiltered face size.
DEFAULT_PREFILTER_SIZE = 128



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
    transmission_depth: int = 0  # levels of transmitted rays traced into the scene (0: none)
    transmission_samples: int = 0  # rays per pixel and level (0 without transmission tracing)
    ibl_visibility: str = "occlusion"  # the IBL's visibility rung (`RenderOptions.ibl_visibility`)
    ibl_samples: int = 0  # rays per pixel of the traced rungs (0 without them)

    def for_stages(self) -> RenderPlan:
        """The plan the staged programs are keyed by: the fields that only the precompute reads
        (the maps' sizes and levels, which reach the stages as the maps' own shapes, and the
        reported roughness) at one value, so that scenes under environments of other sizes share
        the programs that do not sample the maps, and the stored programs' keys (which name every
        field) do not follow the materials' roughness."""
        return dataclasses.replace(self, max_roughness=1.0, prefilter_size=0, prefilter_levels=0, mapping_levels=0, charlie_size=0)

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
        if self.ibl_samples:
            parts.append(f"IBL visibility {self.ibl_visibility!r} ({self.ibl_samples} ray(s) per pixel)")
        if self.transmission_depth:
            parts.append(f"transmission traced through the scene ({self.transmission_depth} level(s), "
                         f"{self.transmission_samples} ray(s) per pixel)")
        if self.extensions:
            parts.append("material extensions: " + ", ".join(self.extensions))
        if self.charlie_size:
            parts.append(f"Charlie-prefiltered cube {self.charlie_size}^2 (sheen)")
        if self.textured:
            parts.append(f"{len(self.textured)} textured object(s)" + (" with normal maps" if self.normal_maps else ""))
        return "; ".join(parts)


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


def prefilter_size(env: Environment, opts: RenderOptions) -> int:
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
def plan(scene: Scene, *, options: RenderOptions | None = None, cache: AssetCache | None = None, **overrides) -> RenderPlan:
    """The RenderPlan of `scene` (what `render` will trace and precompute); options and cache as for
    `render` (the suns split out of the environment are counted, and that extraction is cached)."""
    opts = _options(options, overrides, "plan")
    return plan_for(scene, opts, suns=len(split_environment(scene.environment, opts, cache).suns or ()))


def plan_for(scene: Scene, opts: RenderOptions, *, suns: int) -> RenderPlan:
    """`plan` with the count of suns split out of the environment given (`split_environment`):
    reads the scene's structure and the bounds of its concrete values (remembered per array), and runs no
    precompute."""
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
        size = prefilter_size(env, opts)
        if env.prefiltered is not None:
            M = int(env.prefiltered.metadata.get("mapping_levels", env.prefiltered.num_levels))
            levels = env.prefiltered.num_levels
        else:
            M = specular.default_num_levels(size)
            # The lookup of the map `_asset_prefiltered` makes (prefilter's default lod_blend), in
            # NumPy: this runs at trace time, possibly inside a jit.
            levels = specular.levels_for_roughness(r_max, M, mapping=opts.mapping)
        diffuse = opts.compensates or met_min < 1.0
        n_env_lights = suns
        charlie_size = _charlie_size(env) if "sheen" in extensions else 0
    else:
        size, M, levels, diffuse, n_env_lights, charlie_size = 0, 0, 0, False, 0, 0
    objects = () if scene.gbuffer is not None else scene.objects
    has_mesh = any(isinstance(ob, Mesh) for ob in objects)
    shadows = opts.shadows if opts.shadows is not None else has_mesh
    shadows = bool(shadows and objects and (len(scene.lights) > 0 or n_env_lights > 0))
    blend = any(isinstance(ob, Mesh) and ob.alpha_mode == "BLEND" for ob in objects)
    # Transmitted rays are traced where a material transmits, under an environment (the lobe's
    # weights are the split sum's), with objects to see (a user's G-buffer has none).
    tdepth = opts.transmission_depth if (ibl and objects and "transmission" in extensions) else 0
    # Smooth transmissive materials only (roughness 0 everywhere, traced values counting as rough):
    # the lobe is a direction, and one ray per pixel is exact.
    t_rough = max([r for (r, _, _), m in zip(ranges, mats, strict=True) if "transmission" in _material_extensions(m)[0]], default=1.0)
    traced_vis = ibl and bool(objects) and opts.ibl_visibility in ("ao", "ratio")
    if opts.ibl_visibility in ("ao", "ratio") and scene.gbuffer is not None:
        raise ValueError(f"ibl_visibility={opts.ibl_visibility!r} traces rays through the scene's objects; a scene given as a "
                         "G-buffer has none (use 'occlusion' or 'none')")
    return RenderPlan(
        ibl_visibility=opts.ibl_visibility if ibl else "occlusion",
        ibl_samples=opts.ibl_samples if traced_vis else 0,
        transmission_depth=tdepth,
        transmission_samples=(opts.transmission_samples if t_rough > 0 else 1) if tdepth else 0,
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


class EnvironmentSplit(NamedTuple):
    """The environment as a render lights with it: the suns split out of it as disc lights (None:
    none) and the environment whose maps the split sum reads (its residual after the split; None
    for a scene without an environment)."""

    suns: tuple | None
    env: Environment | None


def split_environment(env: Environment | None, opts: RenderOptions, cache: AssetCache | None = None) -> EnvironmentSplit:
    """The environment's own `lights` when it has them; else, for a concrete environment without
    given maps and `opts.extract_lights`, `extract.extract_lights` (cached per content in
    `cache`, default `ASSETS`); else no suns and the environment itself."""
    if env is None or env.lights is not None:
        return EnvironmentSplit(None if env is None else env.lights, env)
    given = env.irradiance is not None or env.prefiltered is not None
    if not opts.extract_lights or given or not all(is_concrete(lv) for lv in env.radiance.levels):
        return EnvironmentSplit(None, env)
    src = env.radiance

    def compute():
        ex = extract.extract_lights(src)
        return (ex.lights or None), ex.residual

    # The package's digest too: the extraction is kept on disk by the command line (kind "extract").
    key = (content_key(src), extract.DEFAULT_THRESHOLD, extract.DEFAULT_MIN_POWER_SHARE, extract.DEFAULT_MAX_ANGULAR_RADIUS,
           extract.DEFAULT_MAX_LIGHTS, package_digest())
    lights, residual = cache_or_default(cache).get("extract", key, compute)
    if lights is None:
        return EnvironmentSplit(None, env)
    return EnvironmentSplit(lights, env.replace(radiance=residual))


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
    parts |= _memory.mesh_bytes(sum(m.num_vertices for m in meshes), sum(m.num_triangles for m in meshes), mesh_engine())
    parts = {
        ("Camera.width/height" if k == "width/height" else "the textures' resolution" if k == "textures"
         else "the meshes' triangle count" if k == "triangles" else k): v
        for k, v in parts.items()
    }
    env = scene.environment
    if env is not None:
        # (the plan without the light extraction, which is work; the maps' sizes are the same)
        parts |= _asset_bytes(env, plan_for(scene, opts, suns=0), opts, where)
    what = f"rendering {W}x{H}" + (f" with {len(textures)} texture(s)" if textures else "") + (" and the environment's IBL maps" if env is not None else "")
    _memory.require(what, parts, where=where, names=names)


def mesh_engine() -> str:
    """The engine whose memory the guard counts for meshes: "embree" where renders run staged on
    the CPU (`execute.Execution`) and embreex imports, else "jax" (the NumPy-built BVH, which
    opaque meshes take when traced in the program)."""
    device = not EXECUTION.is_staged() and EXECUTION.traces_on_device()
    return "embree" if (jax.default_backend() == "cpu" and _embree() and not device) else "jax"


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
    if env.lut is None and shipped_luts.shipped_entry(opts.lut_size, opts.lut_size, _lut_smith(opts), DEFAULT_LUT_SAMPLES) is None:
        parts["lut_size"] = sum(_memory.lut_bytes(opts.lut_size, opts.lut_size, DEFAULT_LUT_SAMPLES).values())
    return parts

