"""`jaxpbr report render`: the error of split-sum shading against the float64 reference render.

For a grid of materials (roughness x metallic, one base colour) one sphere per material is shaded
from an orthographic G-buffer of P x P pixels (n = (x, y, sqrt(1 - x^2 - y^2)) on the unit disc,
v = +Z, position = n) under an environment plus a point and a directional light:

* split sum: `shade_direct + shade_ibl` in float32 with the default precomputes
  (`irradiance(env, 32)`, `prefilter(env)`, `brdf_lut(128)`), jitted, timed after a warm-up call;
* reference: `shade_direct` in float64 + `reference_render.reference_ibl` (the full reflectance
  integral over every environment texel, float64).

Per material: mean relative error sum|diff| / sum ref over the disc (all channels), the largest
per-pixel relative error (per pixel sum_c |diff| / sum_c ref), the same two for the IBL term alone,
the IBL term by part (diffuse, specular, energy models; per-pixel relative luminance error
statistics in the JSON) and the run times. Outputs: a Markdown table, a JSON of the numbers and a
PNG of the per-pixel relative-error images (the PNG needs matplotlib: `pip install 'jaxpbr[report]'`).

`asset_report` (`jaxpbr report render ASSET --environment FILE`) measures the same on the pixels of
a glTF asset: its G-buffer (`jaxpbr.rendering.renderer.gbuffer`, materials after textures) is
shaded by the same split sum and by the reference (a fixed random subset of pixels when there are
many), IBL only; per part, the mean and percentiles of the per-pixel relative luminance error.
Both paths share the precomputes and split sum (`_SplitSum`), the measurement (`_measure`) and
the parts (`_ibl_parts`).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._validate import positive_int
from ..conventions import luminance
from ..errors import InputError
from ..ibl import envs
from ..ibl import extract as _extract
from ..ibl.cubeio import ENVIRONMENT_HELP, load_environment
from ..ibl.cubemap import Cubemap
from ..ibl.diffuse import irradiance
from ..ibl.reference_render import (
    min_reference_roughness,
    reference_ibl_from_terms,
    reference_ibl_terms,
    reference_layered,
)
from ..ibl.shade import disc_multiscatter, shade_ibl
from ..ibl.specular import prefilter
from ..io.atomic import OutputSet, atomic_write
from ..rendering import renderer as _renderer
from ..rendering.gltf_scene import load_gltf
from ..rendering.scene import Environment, Scene
from ..shading import lights as _lights
from ..shading.material import Material
from ..shading.shipped_luts import brdf_lut
from ._common import (
    CLIError,
    have_matplotlib,
    positive_int_arg,
    require_environment,
    require_memory,
)
from .timing import time_calls

__all__ = ["DEFAULT_ASSET_PIXELS", "DEFAULT_EXTENSION_ROUGHNESS", "DEFAULT_METALLIC", "DEFAULT_ROUGHNESS", "EXTENSION_ROWS", "PARTS", "add_command", "asset_report", "default_lights", "markdown", "plot", "render_report", "sphere_gbuffer", "write_report"]

DEFAULT_ROUGHNESS = (0.05, 0.15, 0.3, 0.5, 0.75, 1.0)
DEFAULT_METALLIC = (0.0, 1.0)
DEFAULT_BASE_COLOR = (0.9, 0.6, 0.3)
DEFAULT_EXTENSION_ROUGHNESS = (0.15, 0.5, 1.0)

#: One row group per glTF material extension: (Material fields besides base_color, the field that
#: takes the row's roughness). The base colour is the report's; the tangent (anisotropy) is the
#: sphere's latitude direction, the coat normal the shading normal.
EXTENSION_ROWS = {
    "clearcoat": (dict(metallic=0.0, roughness=0.5, clearcoat=1.0), "clearcoat_roughness"),
    "sheen": (dict(metallic=0.0, roughness=0.5, sheen_color=(1.0, 1.0, 1.0)), "sheen_roughness"),
    "specular": (dict(metallic=0.0, specular=0.7, specular_color=(1.5, 1.0, 0.5)), "roughness"),
    "ior": (dict(metallic=0.0, ior=2.0), "roughness"),
    "anisotropy": (dict(metallic=1.0, anisotropy_strength=0.7), "roughness"),
    "thin transmission": (dict(metallic=0.0, transmission=1.0), "roughness"),
    "volume": (dict(metallic=0.0, transmission=1.0, thickness=0.5, ior=1.5, attenuation_color=(0.9, 0.7, 0.5), attenuation_distance=1.0), "roughness"),
}


def sphere_tangent(n):
    """The sphere's latitude direction (z, 0, -x)/|.| at normals n (N, 3) with n_z > 0 (the
    anisotropy tangent of the extension rows)."""
    t = np.stack([n[:, 2], np.zeros(len(n)), -n[:, 0]], -1)
    return t / np.linalg.norm(t, axis=-1, keepdims=True)


def sphere_gbuffer(pixels: int):
    """Orthographic unit sphere seen from +Z: (mask (P, P) bool, n (N, 3), v (N, 3), p (N, 3)) float64,
    N the pixels whose centre lies inside the unit disc; row 0 is the top (+Y)."""
    c = (np.arange(pixels) + 0.5) / pixels * 2.0 - 1.0
    x, y = np.meshgrid(c, -c)
    mask = x * x + y * y < 1.0
    n = np.stack([x, y, np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, 1.0))], -1)[mask]
    v = np.broadcast_to(np.array([0.0, 0.0, 1.0]), n.shape).copy()
    return mask, n, v, n.copy()


def default_lights():
    """A warm point light up-right in front of the sphere and a cool directional light from the
    upper left: (list of lights, description)."""
    lights = [
        _lights.PointLight(position=(2.0, 2.0, 3.0), color=(1.0, 0.9, 0.8), intensity=20.0),
        _lights.DirectionalLight(direction=(0.5, -0.6, -0.6), color=(0.8, 0.9, 1.0), intensity=2.0),
    ]
    desc = "point light at (2, 2, 3), colour (1, 0.9, 0.8), 20 cd; directional light travelling (0.5, -0.6, -0.6), colour (0.8, 0.9, 1), 2 lux"
    return lights, desc


def _lights_as(lights, dtype):
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else a, lights)


def _errors(test, ref):
    """(mean relative error over all pixels and channels, largest per-pixel relative error,
    per-pixel relative error (N,))."""
    diff = np.abs(test - ref).sum(-1)
    den = np.abs(ref).sum(-1)
    per_pixel = diff / np.maximum(den, 1e-300)
    return float(diff.sum() / max(den.sum(), 1e-300)), float(per_pixel.max(initial=0.0)), per_pixel


def _bias(test, ref) -> float:
    """Signed relative error sum(test - ref) / sum(ref) over all pixels and channels."""
    return float((test - ref).sum() / max(np.abs(ref).sum(), 1e-300))


def _part_stats(test, ref) -> dict:
    """One part's error, test against ref (N, 3): the mean relative error over all pixels and
    channels (sum |diff| / sum ref, the tables' "mean rel. error"), and the per-pixel relative
    luminance error |Y(test) - Y(ref)| / Y(ref) over the pixels where the part is present
    (Y(ref) above 1e-9 of its largest value): mean, median, 90th and 99th percentile, largest, the
    signed luminance bias sum(Y(test) - Y(ref)) / sum Y(ref), that pixel count and the mean
    reference luminance over them (ref_lum_mean)."""
    yt, yr = luminance(np.asarray(test, np.float64)), luminance(np.asarray(ref, np.float64))
    on = yr > 1e-9 * float(yr.max(initial=0.0))
    e = np.abs(yt - yr)[on] / yr[on]
    q = np.percentile(e, (50, 90, 99)) if e.size else (np.nan,) * 3
    return dict(
        mean_rel_error=_errors(test, ref)[0],
        lum_mean=float(e.mean()) if e.size else float("nan"),
        lum_p50=float(q[0]), lum_p90=float(q[1]), lum_p99=float(q[2]),
        lum_max=float(e.max(initial=0.0)) if e.size else float("nan"),
        lum_bias=float((yt - yr).sum() / max(yr.sum(), 1e-300)),
        pixels=int(on.sum()),
        ref_lum_mean=float(yr[on].mean()) if e.size else float("nan"),
    )


#: The parts of the IBL term each report measures (keys of a row's "parts"), in table order.
PARTS = {
    "ibl": "IBL, single scattering (the reference's model)",
    "diffuse": "diffuse part",
    "specular": "specular part",
    "single_scatter_furnace_normalised": "single scattering, furnace-normalised",
    "multi_scatter_furnace_normalised": "multiple scattering, furnace-normalised",
    "multi_scatter": "IBL, multiple scattering (`render`'s default for glTF)",
}


def _ibl_parts(ss, p32, n32, v32, m32, m64, terms, ibl, ref_ibl) -> dict:
    """The IBL term's error by part and by energy model, for per-pixel (or uniform) materials.

    * ibl: the IBL term (single scattering, the reference's model);
    * diffuse / specular: the two lobes apart. The glTF BRDF is linear in the diffuse colour
      (1 - metallic) base at fixed F0, so the specular part is the term of the same F0 without
      diffuse colour (base_color = F0, metallic = 1) and the diffuse part the rest; the
      reference's are its own (1 - metallic) base Ld and F0 LA + LB sums (`reference_render`).
      A part absent from every pixel (the diffuse part of metals) is left out;
    * energy models: the IBL term divided per pixel by the same model's white-furnace response (which
      removes the choice of energy compensation and leaves what the environment contributes), the
      single-scattering split sum and the multiple-scattering one (`multiscatter=True`, the renderer's
      default for glTF) each against the reference divided by its own furnace response. The
      reference's furnace is the LUT's single-scattering albedo (F0 A + B + (1 - metallic) base
      0.96 (1 - C)): the split sum under L = 1 is exact but for the LUT, converged to ~1e-5;
    * multi_scatter: the multiple-scattering IBL term itself against the (single-scattering)
      reference: the error of what `render` draws, the energy model's difference included.
    Returns the flat keys of the sphere tables (ibl_bias, ibl_diffuse_mean_rel_error, ...) and
    "parts": {part: `_part_stats`}.
    """

    def run(m_, ms=False):
        return np.asarray(ss.run(p32, n32, v32, m_, multiscatter=ms)[1], np.float64)

    def furnace(m_, ms):
        return np.asarray(ss.furnace(n32, v32, m_, ms), np.float64)

    t = np.asarray(terms, np.float64)
    ref_d = reference_ibl_from_terms(t * np.array([1.0, 0.0, 0.0])[:, None], m64)
    ref_s = reference_ibl_from_terms(t * np.array([0.0, 1.0, 1.0])[:, None], m64)
    spec = m32.replace(base_color=m32.f0(), metallic=jnp.ones_like(m32.metallic))
    ss_s = run(spec)
    ss_d = ibl - ss_s
    ref_norm = ref_ibl / furnace(m32, False)
    multi = run(m32, True)
    parts = dict(ibl=_part_stats(ibl, ref_ibl))
    out = dict(ibl_bias=_bias(ibl, ref_ibl))
    for name, test, ref in (("diffuse", ss_d, ref_d), ("specular", ss_s, ref_s)):
        if np.abs(ref).sum() > 0:
            parts[name] = _part_stats(test, ref)
            out[f"ibl_{name}_mean_rel_error"] = parts[name]["mean_rel_error"]
            out[f"ibl_{name}_bias"] = _bias(test, ref)
    for name, test in (("single", ibl), ("multi", multi)):
        key = f"{name}_scatter_furnace_normalised"
        parts[key] = _part_stats(test / furnace(m32, name == "multi"), ref_norm)
        out[f"ibl_{key}_error"] = parts[key]["mean_rel_error"]
    parts["multi_scatter"] = _part_stats(multi, ref_ibl)
    out["parts"] = parts
    return out


@functools.partial(jax.jit, static_argnames=("multiscatter",))
def _split_sum(p_, n_, v_, m_, irr_, pre_, lut_, lights_, discs_, multiscatter=False):
    """(direct + IBL, IBL) by the split sum. "IBL" = what the environment contributes: the split
    sum of the (residual) environment plus its extracted disc lights (emission added once, by the
    lights' term; none without lights), with the multiple-scattering compensation of both when
    asked (as `render` does)."""
    ibl = shade_ibl(n_, v_, m_, irr_, pre_, lut_, multiscatter=multiscatter)
    if discs_ is not None:
        dark = m_.replace(emissive=jnp.zeros_like(m_.emissive))
        ibl = ibl + _lights.shade_direct(p_, n_, v_, dark, discs_, disc_lights=True)
        if multiscatter:
            ibl = ibl + disc_multiscatter(n_, v_, m_, lut_, discs_)
    if not lights_:
        return ibl, ibl
    return _lights.shade_direct(p_, n_, v_, m_, lights_) + ibl, ibl


@functools.partial(jax.jit, static_argnames=("multiscatter",))
def _furnace(n_, v_, m_, irr1, pre1, lut_, multiscatter=False):
    """The split sum's white-furnace response (L = 1 everywhere): what each energy model's IBL
    term is divided by in the furnace-normalised parts."""
    return shade_ibl(n_, v_, m_, irr1, pre1, lut_, multiscatter=multiscatter)


class _SplitSum:
    """The split sum as the reports run it: the environment's precomputes (once, float32 as users
    run them; dominant lights extracted first when asked, as `render` does), then `run` (jitted
    `_split_sum`) and `furnace` on G-buffer pixels."""

    def __init__(self, env: Cubemap, lights, *, extract_lights: bool, irradiance_size: int, prefilter_size, lut_size: int):
        t0 = time.perf_counter()
        lights = list(lights) if isinstance(lights, (list, tuple)) else [lights]
        ss_env, self.extracted, discs = env, [], []
        if extract_lights:
            ex = _extract.extract_lights(env)
            ss_env, self.extracted, discs = ex.residual, ex.info["lights"], list(ex.lights)
        self.ss_env = ss_env
        self.lut = brdf_lut(size=lut_size)
        self.irr = irradiance(ss_env, size=irradiance_size)
        self.pre = prefilter(ss_env, size=prefilter_size)
        jax.block_until_ready((self.lut, self.irr.levels, self.pre.levels))
        self.precompute_s = time.perf_counter() - t0
        f32 = jnp.float32
        self.lights32 = _lights_as(lights, f32)
        self.discs32 = _lights_as(discs, f32) if discs else None
        ones = lambda c: Cubemap(tuple(jnp.ones_like(x) for x in c.levels), c.metadata)  # noqa: E731
        self._irr1, self._pre1 = ones(self.irr), ones(self.pre)
        self.description = (
            ("environment split into " + (f"{len(self.extracted)} disc light(s) + residual; " if self.extracted else "no disc light (none found); ") if extract_lights else "")
            + f"float32 shade_direct + shade_ibl (gltf), irradiance {irradiance_size}^2 exact, prefilter {self.pre.face_size}^2 x {self.pre.num_levels} mips (FIS defaults), BRDF LUT {lut_size}^2"
        )

    def run(self, p, n, v, m, multiscatter: bool = False):
        return _split_sum(p, n, v, m, self.irr, self.pre, self.lut, self.lights32, self.discs32, multiscatter=multiscatter)

    def furnace(self, n, v, m, multiscatter: bool):
        return _furnace(n, v, m, self._irr1, self._pre1, self.lut, multiscatter=multiscatter)

    def log_setup(self, log) -> None:
        for x in self.extracted:
            log(f"  extracted a disc light: radius {x['angular_radius_deg']:.2f} deg, {100 * x['power_share']:.1f} % of the environment's power")
        log(f"  precompute (LUT {self.lut.shape[0]}^2, irradiance {self.irr.face_size}^2, prefilter {self.pre.face_size}^2 x {self.pre.num_levels} mips): {self.precompute_s:.2f} s")


def _measure(ss: _SplitSum, p, n, v, m32, m64, terms, *, reference_direct=None, repeats: int) -> tuple[dict, np.ndarray, float, dict]:
    """Split sum against the reference on one set of G-buffer pixels (p, n, v float32 (N, 3), the
    material in float32 and float64, the reference's environment sums `terms` of these pixels):
    the split sum timed (best of `repeats` jitted calls after a warm-up), the reference's radiance
    (`reference_ibl_from_terms` + `reference_direct()`, the float64 direct lighting, if any).
    Returns (row: errors of the whole and of the IBL term, the IBL parts (`_ibl_parts`), the IBL
    share and split_sum_s; per-pixel relative error of the whole (N,); seconds of the reference's
    part after the terms; the IBL terms {"split_sum", "reference"} (N, 3) float64)."""
    (tot, ibl), timing = time_calls(lambda: ss.run(p, n, v, m32), rounds=repeats)
    tot, ibl = np.asarray(tot, np.float64), np.asarray(ibl, np.float64)
    t0 = time.perf_counter()
    ref_ibl = reference_ibl_from_terms(terms, m64)
    ref = ref_ibl if reference_direct is None else ref_ibl + reference_direct()
    ref_s = time.perf_counter() - t0
    mean, mx, per_pixel = _errors(tot, ref)
    ibl_mean, ibl_max, _ = _errors(ibl, ref_ibl)
    row = dict(
        mean_rel_error=mean,
        max_pixel_rel_error=mx,
        ibl_mean_rel_error=ibl_mean,
        ibl_max_pixel_rel_error=ibl_max,
        ibl_share_of_radiance=float(np.abs(ref_ibl).sum() / max(np.abs(ref).sum(), 1e-300)),
        **_ibl_parts(ss, p, n, v, m32, m64, terms, ibl, ref_ibl),
        split_sum_s=timing.best,
    )
    return row, per_pixel, ref_s, dict(split_sum=ibl, reference=ref_ibl)


def _environment(env, face_size: int, env_name: str | None):
    """(float32 level-0 Cubemap, its name) from None (the procedural sky + sun), a path /
    "procedural:sky" or a Cubemap."""
    if isinstance(env, (str, Path)):
        env_name = env_name or str(env)
        env = load_environment([str(env)], face_size=face_size)
    elif env is None:
        env_name = env_name or "procedural sky+sun"
        env = envs.sky_with_sun_cubemap(face_size)
    elif not isinstance(env, Cubemap):
        raise TypeError(f"env must be None, a path or a Cubemap, got {type(env).__name__}")
    return Cubemap((jnp.asarray(env.levels[0], jnp.float32),), env.metadata), env_name or "environment"


def render_report(
    env=None,
    *,
    roughness=DEFAULT_ROUGHNESS,
    metallic=DEFAULT_METALLIC,
    base_color=DEFAULT_BASE_COLOR,
    pixels: int = 48,
    face_size: int = 64,
    env_name: str | None = None,
    lights=None,
    irradiance_size: int = 32,
    prefilter_size: int | None = None,
    lut_size: int = 128,
    repeats: int = 5,
    extract_lights: bool = True,
    extensions=(),
    extension_roughness=DEFAULT_EXTENSION_ROUGHNESS,
    log=print,
) -> dict:
    """Render the material grid both ways and measure the split-sum error.

    env: None (the procedural sky + 3000-radiance sun of `jaxpbr.ibl.envs` at `face_size`), a
        `Cubemap`, or a path / "procedural:sky" (read with `jaxpbr.ibl.cubeio.load_environment`).
    roughness, metallic: the grid (every roughness >= `min_reference_roughness(face size)`).
    lights: punctual lights (default `default_lights()`).
    extract_lights: split dominant lights out of the environment first (`jaxpbr.ibl.extract`, as
        `render` does by default): the split sum then shades the residual and the disc lights.
    extensions: names of `EXTENSION_ROWS` (or "all") to add rows for, one per value of
        `extension_roughness` (the extension's own roughness where it has one): the layered split
        sum (`shade_ibl` with the extension; `shade_direct` for the lights) against
        `reference_layered` + float64 `shade_direct`, on the same sphere. The sheen row needs the
        sheen albedo table and the Charlie-prefiltered environment (computed here; reported as
        unavailable when their modules are missing). Result key "extensions".
    Returns a dict: "config", "precompute_s", "materials" (one dict of numbers per material),
    "images" (per-material per-pixel relative error (P, P), NaN off the disc; not JSON).
    """
    env, env_name = _environment(env, face_size, env_name)
    roughness = [float(r) for r in roughness]
    metallic = [float(m) for m in metallic]
    if not roughness or not metallic:
        raise ValueError("roughness and metallic need at least one value each")
    for name, vals in (("roughness", roughness), ("metallic", metallic)):
        if any(not 0.0 <= x <= 1.0 for x in vals):
            raise ValueError(f"{name} values must lie in [0, 1], got {vals}")
    r_floor = min_reference_roughness(env.face_size)
    if min(roughness) < r_floor:
        raise ValueError(
            f"the reference resolves roughness >= {r_floor:.3f} on a {env.face_size}^2-per-face environment; "
            f"got {min(roughness)} (use a larger --face-size or a larger roughness)"
        )
    pixels = positive_int("pixels", pixels)
    if lights is None:
        lights, lights_desc = default_lights()
    else:
        lights_desc = f"{len(lights) if isinstance(lights, (list, tuple)) else 1} user light(s)"

    if extensions == "all" or (isinstance(extensions, (list, tuple)) and "all" in extensions):
        extensions = tuple(EXTENSION_ROWS)
    extensions = tuple(extensions or ())
    unknown = [e for e in extensions if e not in EXTENSION_ROWS]
    if unknown:
        raise ValueError(f"unknown extension rows {unknown}; choose from {list(EXTENSION_ROWS)} or 'all'")
    extension_roughness = [float(r) for r in extension_roughness]
    if extensions and (not extension_roughness or min(extension_roughness) < r_floor or max(extension_roughness) > 1.0):
        raise ValueError(f"extension roughness values must lie in [{r_floor:.3f}, 1] (the reference resolves roughness >= {r_floor:.3f} here), got {extension_roughness}")

    mask, n, v, p = sphere_gbuffer(int(pixels))
    log(f"render report: {len(roughness)} x {len(metallic)} materials, {pixels}^2 px ({len(n)} on the sphere), {env_name} at {env.face_size}^2")

    # ---- precompute (once), float32 as users run it
    ss = _SplitSum(env, lights, extract_lights=extract_lights, irradiance_size=irradiance_size, prefilter_size=prefilter_size, lut_size=lut_size)
    ss.log_setup(log)
    f32 = jnp.float32
    n32, v32, p32 = (jnp.asarray(a, f32) for a in (n, v, p))

    def material(r, m, dtype):
        return Material(base_color=jnp.asarray(base_color, dtype), metallic=jnp.asarray(m, dtype), roughness=jnp.asarray(r, dtype))

    with jax.enable_x64(True):
        lights64 = _lights_as(lights, jnp.float64)
        n64, v64, p64 = (jnp.asarray(a, jnp.float64) for a in (n, v, p))
        direct64 = jax.jit(lambda m_: _lights.shade_direct(p64, n64, v64, m_, lights64))

    rows, images = [], {}
    for r in roughness:
        t0 = time.perf_counter()
        terms = reference_ibl_terms(n, v, r, env)
        terms_s = time.perf_counter() - t0
        for m in metallic:
            with jax.enable_x64(True):
                m64 = material(r, m, jnp.float64)

            def direct(m64=m64):
                with jax.enable_x64(True):
                    return np.asarray(direct64(m64))

            row, per_pixel, rest_s, _ = _measure(ss, p32, n32, v32, material(r, m, f32), m64, terms, reference_direct=direct, repeats=repeats)
            ref_s = terms_s + rest_s
            img = np.full(mask.shape, np.nan)
            img[mask] = per_pixel
            images[(r, m)] = img
            worst = int(np.argmax(per_pixel))
            rows.append(dict(roughness=r, metallic=m, worst_pixel_n_dot_v=float(n[worst, 2]), **row, reference_s=ref_s, reference_ibl_shared_s=terms_s))
            log(
                f"  r={r:g} metallic={m:g}: mean {100 * row['mean_rel_error']:.2f} %, max pixel {100 * row['max_pixel_rel_error']:.1f} %, "
                f"IBL mean {100 * row['ibl_mean_rel_error']:.2f} %; split sum {1e3 * row['split_sum_s']:.2f} ms, reference {ref_s:.1f} s"
            )
    ext_rows = _extension_rows(
        extensions, extension_roughness, base_color=base_color, env=env, ss_env=ss.ss_env, n=n, v=v, p=p, mask=mask,
        lights=lights, lights32=ss.lights32, discs32=ss.discs32, irr=ss.irr, pre=ss.pre, lut=ss.lut, repeats=repeats, log=log,
    ) if extensions else ([], {})
    config = dict(
        environment=env_name,
        environment_face_size=env.face_size,
        pixels=int(pixels),
        pixels_on_sphere=int(len(n)),
        base_color=[float(c) for c in base_color],
        roughness=roughness,
        metallic=metallic,
        lights=lights_desc,
        extracted_lights=ss.extracted,
        split_sum=ss.description,
        reference="float64 shade_direct + reference_ibl (every texel of level 0, tiered sub-texel supersampling)",
        geometry="orthographic unit sphere, v = +Z, n = (x, y, sqrt(1 - x^2 - y^2)), position = n",
        timing=f"split sum: best of {repeats} jitted calls after a warm-up; reference: one call incl. compilation (its three environment sums are shared by the metallic values of one roughness)",
        device=str(jax.devices()[0].platform),
    )
    if extensions:
        config["extension_roughness"] = extension_roughness
        config["extension_rows"] = {e: dict(EXTENSION_ROWS[e][0], roughness_field=EXTENSION_ROWS[e][1]) for e in extensions}
        config["extension_reference"] = "float64 shade_direct + reference_layered (the layered BSDF over the whole sphere of directions, tiered sub-texel supersampling around each lobe)"
    return dict(config=config, precompute_s=ss.precompute_s, materials=rows, images=images, mask=mask, extensions=ext_rows[0], extension_images=ext_rows[1])


def _extension_rows(names, roughness, *, base_color, env, ss_env, n, v, p, mask, lights, lights32, discs32, irr, pre, lut, repeats, log):
    """The per-extension rows of `render_report` -> (rows, images)."""
    f32 = jnp.float32
    slut = charlie = None
    sheen_missing = None
    if "sheen" in names:
        try:
            from ..ibl.sheen_prefilter import prefilter_charlie
            from ..shading.shipped_luts import sheen_lut

            t0 = time.perf_counter()
            slut = sheen_lut()
            charlie = prefilter_charlie(ss_env)
            jax.block_until_ready((slut, charlie.levels))
            log(f"  sheen assets (sheen albedo table {slut.shape[0]}^2, Charlie cube {charlie.face_size}^2 x {charlie.num_levels}): {time.perf_counter() - t0:.2f} s")
        except ImportError as e:  # the modules are not there (yet)
            sheen_missing = f"sheen assets unavailable ({e})"
    t = sphere_tangent(n)
    n32, v32, p32, t32 = (jnp.asarray(a, f32) for a in (n, v, p, t))

    @jax.jit
    def split_sum(p_, n_, v_, t_, m_, irr_, pre_, lut_, slut_, charlie_, lights_, discs_):
        ibl = shade_ibl(n_, v_, m_, irr_, pre_, lut_, tangent=t_, sheen_lut=slut_, charlie=charlie_)
        if discs_ is not None:
            dark = m_.replace(emissive=jnp.zeros_like(m_.emissive))
            ibl = ibl + _lights.shade_direct(p_, n_, v_, dark, discs_, disc_lights=True, tangent=t_, sheen_lut=slut_)
        return _lights.shade_direct(p_, n_, v_, m_, lights_, tangent=t_, sheen_lut=slut_) + ibl, ibl

    with jax.enable_x64(True):
        lights64 = _lights_as(lights, jnp.float64)
        n64, v64, p64, t64 = (jnp.asarray(a, jnp.float64) for a in (n, v, p, t))
        direct64 = jax.jit(lambda m_, slut_: _lights.shade_direct(p64, n64, v64, m_, lights64, tangent=t64, sheen_lut=slut_))

    rows, images = [], {}
    for name in names:
        fields, rfield = EXTENSION_ROWS[name]
        if name == "sheen" and sheen_missing:
            rows.append(dict(extension=name, unavailable=sheen_missing))
            log(f"  {name}: {sheen_missing}")
            continue
        for r in roughness:
            kw = dict(dict(roughness=0.5), **fields, **{rfield: r})

            def material(dtype, kw=kw):
                return Material(base_color=jnp.asarray(base_color, dtype), **{k: jnp.asarray(x, dtype) for k, x in kw.items()})

            m32 = material(f32)
            (tot, ibl), timing = time_calls(lambda: split_sum(p32, n32, v32, t32, m32, irr, pre, lut, slut, charlie, lights32, discs32), rounds=repeats)
            tot, ibl = np.asarray(tot, np.float64), np.asarray(ibl, np.float64)
            t0 = time.perf_counter()
            with jax.enable_x64(True):
                m64 = material(jnp.float64)
                ref_direct = np.asarray(direct64(m64, slut))
            ref_ibl = reference_layered(n, v, m64, env, tangent=t, sheen_lut=slut)
            ref = ref_direct + ref_ibl
            ref_s = time.perf_counter() - t0
            mean, mx, per_pixel = _errors(tot, ref)
            ibl_mean, ibl_max, _ = _errors(ibl, ref_ibl)
            img = np.full(mask.shape, np.nan)
            img[mask] = per_pixel
            images[(name, r)] = img
            rows.append(
                dict(
                    extension=name,
                    roughness_field=rfield,
                    roughness=r,
                    metallic=float(kw.get("metallic", 1.0)),
                    mean_rel_error=mean,
                    max_pixel_rel_error=mx,
                    ibl_mean_rel_error=ibl_mean,
                    ibl_max_pixel_rel_error=ibl_max,
                    ibl_share_of_radiance=float(np.abs(ref_ibl).sum() / np.abs(ref).sum()),
                    split_sum_s=timing.best,
                    reference_s=ref_s,
                )
            )
            log(f"  {name} {rfield}={r:g}: mean {100 * mean:.2f} %, max pixel {100 * mx:.1f} %, IBL mean {100 * ibl_mean:.2f} %; split sum {1e3 * timing.best:.2f} ms, reference {ref_s:.1f} s")
    return rows, images


#: Asset pixels the reference is computed for by default (a fixed random subset when there are more).
DEFAULT_ASSET_PIXELS = 2048
#: Default G-buffer size of an asset report (width, height).
DEFAULT_ASSET_SIZE = (320, 240)
#: Core glTF material fields the asset report reads from the G-buffer (emission is left out).
_CORE_FIELDS = ("base_color", "metallic", "roughness", "occlusion")


def asset_report(
    scene: Scene,
    env=None,
    *,
    env_name: str | None = None,
    asset_name: str = "asset",
    face_size: int = 64,
    pixels: int | None = DEFAULT_ASSET_PIXELS,
    seed: int = 0,
    irradiance_size: int = 32,
    lut_size: int = 128,
    repeats: int = 5,
    extract_lights: bool = True,
    log=print,
) -> dict:
    """The split-sum error on the pixels of a scene (a glTF asset: `jaxpbr.load_gltf`).

    The scene's G-buffer (`jaxpbr.rendering.renderer.gbuffer`: position, shading normal, view and
    the material after textures at each pixel centre of its camera) is shaded by the split sum of
    `env` as `render` shades it (dominant lights extracted, the renderer's default prefilter size;
    the same `_SplitSum` as the sphere report) and by the float64 reference (`reference_ibl_terms`
    of the same pixels); both measure the IBL term only: no punctual lights (the scene's are not
    read), no emission, and no shadows (image-based lighting is not shadowed). Occlusion (texture)
    multiplies the reference and the split sum's environment maps, not the suns it extracts (as in
    `render`): under a sun, occluded pixels show that difference too.

    env: as `render_report` (None: the procedural sky + sun at `face_size`; the scene's own
        environment is not read). Materials must be core glTF materials (ValueError otherwise:
        the layered reference is the sphere report's `extensions` rows).
    pixels: at most this many asset pixels are measured: a fixed random subset (`seed`) of the
        eligible ones when there are more (None: all). Eligible: roughness >= the reference's
        floor `min_reference_roughness(face size)` and n.v > 0 (the reference is 0 there, the
        split sum clamps n.v); the others are counted in the config.
    Returns a dict: "config", "gbuffer_s", "precompute_s", "asset" (the row of `render_report`'s
    materials: errors of the IBL term, "parts" by `PARTS`, split_sum_s and reference_s, both on
    the measured pixels, back to back in this process) and "samples" (flat pixel indices into
    the H x W image, per-pixel relative luminance error of the IBL term, the two IBL terms (N, 3);
    not JSON).
    """
    if not isinstance(scene, Scene) or scene.camera is None:
        raise TypeError(f"asset_report expects a jaxpbr.Scene with a camera (jaxpbr.load_gltf), got {type(scene).__name__}")
    env, env_name = _environment(env, face_size, env_name)
    if pixels is not None:
        pixels = positive_int("pixels", pixels)
    r_floor = min_reference_roughness(env.face_size)

    t0 = time.perf_counter()
    gb = jax.block_until_ready(_renderer.gbuffer(scene))
    gbuffer_s = time.perf_counter() - t0
    gm = gb.material
    if gm.layered:
        raise ValueError(
            f"{asset_name}: the asset uses glTF material extensions ({', '.join(g for g in gm.extensions if g != 'emissive_strength')}); "
            "the asset report's reference covers core materials (the extensions are measured on spheres: report render --extensions)"
        )
    hit = np.asarray(gb.hit)
    H, W = hit.shape
    flat = np.flatnonzero(hit)
    if flat.size == 0:
        raise ValueError(f"{asset_name}: no pixel of the {W}x{H} image shows the asset; check the camera")

    def per_pixel(x, tail=()):
        return np.broadcast_to(np.asarray(x, np.float64), hit.shape + tail).reshape((-1,) + tail)[flat]

    n, v, p = (per_pixel(getattr(gb, k), (3,)) for k in ("normal", "view", "position"))
    mat = {f: per_pixel(getattr(gm, f), (3,) if f == "base_color" else ()) for f in _CORE_FIELDS}
    mat["roughness"] = np.clip(mat["roughness"], 0.0, 1.0)
    smooth = mat["roughness"] < r_floor
    back = (np.sum(n * v, -1) <= 0.0) & ~smooth
    eligible = np.flatnonzero(~smooth & ~back)
    if eligible.size == 0:
        raise ValueError(
            f"{asset_name}: none of its {flat.size} pixels can be measured: roughness below the reference's floor "
            f"{r_floor:.3f} at {env.face_size}^2 ({int(smooth.sum())} px; use a larger --face-size) or n.v <= 0 ({int(back.sum())} px)"
        )
    idx = eligible
    if pixels is not None and eligible.size > pixels:
        idx = np.sort(np.random.default_rng(seed).choice(eligible, pixels, replace=False))
    log(f"render report: {asset_name}, {W}x{H} G-buffer ({gbuffer_s:.2f} s), {flat.size} px on the asset, {idx.size} measured; {env_name} at {env.face_size}^2")

    ss = _SplitSum(env, [], extract_lights=extract_lights, irradiance_size=irradiance_size,
                   prefilter_size=_renderer.prefilter_size(Environment(radiance=env), _renderer.RenderOptions()), lut_size=lut_size)
    ss.log_setup(log)
    f32 = jnp.float32
    n32, v32, p32 = (jnp.asarray(a[idx], f32) for a in (n, v, p))
    m32 = Material(**{f: jnp.asarray(x[idx], f32) for f, x in mat.items()})
    with jax.enable_x64(True):
        m64 = Material(**{f: jnp.asarray(x[idx], jnp.float64) for f, x in mat.items()})
    t0 = time.perf_counter()
    terms = reference_ibl_terms(n[idx], v[idx], mat["roughness"][idx], env)
    terms_s = time.perf_counter() - t0
    row, _, rest_s, arrays = _measure(ss, p32, n32, v32, m32, m64, terms, repeats=repeats)
    row["reference_s"] = terms_s + rest_s
    yt, yr = luminance(arrays["split_sum"]), luminance(arrays["reference"])
    lum_err = np.abs(yt - yr) / np.maximum(yr, 1e-300)
    ib = row["parts"]["ibl"]
    log(f"  IBL: mean {100 * ib['lum_mean']:.2f} %, p99 {100 * ib['lum_p99']:.1f} % (relative luminance); split sum {1e3 * row['split_sum_s']:.2f} ms, reference {row['reference_s']:.1f} s")
    config = dict(
        kind="asset",
        asset=asset_name,
        image=[int(W), int(H)],
        camera=dict(position=np.asarray(scene.camera.position, np.float64).tolist(), target=np.asarray(scene.camera.target, np.float64).tolist(),
                    **({"projection": "orthographic", "ymag": float(scene.camera.ymag)} if scene.camera.projection == "orthographic"
                       else {"fov_y_deg": float(scene.camera.fov_y_deg)})),
        pixels_on_asset=int(flat.size),
        pixels_measured=int(idx.size),
        pixels_limit=pixels,
        seed=int(seed),
        pixels_below_roughness_floor=int(smooth.sum()),
        pixels_back_facing=int(back.sum()),
        roughness_floor=r_floor,
        environment=env_name,
        environment_face_size=env.face_size,
        extracted_lights=ss.extracted,
        split_sum=ss.description,
        reference="float64 reference_ibl (every texel of level 0, tiered sub-texel supersampling) of the same G-buffer pixels",
        timing=f"split sum: best of {repeats} jitted calls after a warm-up; reference: one call incl. compilation; both on the measured pixels, back to back in this process",
        device=str(jax.devices()[0].platform),
    )
    samples = dict(pixel=flat[idx], rel_lum_error=lum_err, split_sum=arrays["split_sum"], reference=arrays["reference"])
    return dict(config=config, gbuffer_s=gbuffer_s, precompute_s=ss.precompute_s, asset=row, samples=samples, mask=hit)


# ------------------------------------------------------------------------------------------
# outputs
# ------------------------------------------------------------------------------------------


def markdown(result: dict) -> str:
    """The result as a Markdown section (config line + table)."""
    c = result["config"]
    if c.get("kind") == "asset":
        return _asset_markdown(result)
    out = [
        "# jaxpbr split-sum error vs float64 reference render",
        "",
        f"Environment: {c['environment']} ({c['environment_face_size']}^2 per face); sphere {c['pixels']}^2 px "
        f"({c['pixels_on_sphere']} on the disc); base colour {tuple(c['base_color'])}; lights: {c['lights']}.",
        f"Split sum: {c['split_sum']}. Reference: {c['reference']}.",
        f"Precompute (once): {result['precompute_s']:.2f} s. Timing: {c['timing']}; device {c['device']}.",
        "",
        "| roughness | metallic | mean rel. error | max pixel rel. error | IBL mean rel. error | IBL max pixel | IBL share | split sum (ms) | reference (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["materials"]:
        out.append(
            f"| {r['roughness']:g} | {r['metallic']:g} | {100 * r['mean_rel_error']:.2f} % | {100 * r['max_pixel_rel_error']:.1f} % | "
            f"{100 * r['ibl_mean_rel_error']:.2f} % | {100 * r['ibl_max_pixel_rel_error']:.1f} % | {100 * r['ibl_share_of_radiance']:.0f} % | "
            f"{1e3 * r['split_sum_s']:.2f} | {r['reference_s']:.2f} |"
        )
    out += [
        "",
        "## The IBL term by part and by energy model",
        "",
        "Bias: signed relative error of the IBL term. Diffuse / specular: the two lobes apart (the glTF BRDF is linear in the "
        "diffuse colour (1 - metallic) base at fixed F0: specular = the term at the same F0 without diffuse colour, diffuse = the "
        "rest; metals have no diffuse lobe). "
        "Furnace-normalised: each model's IBL term divided per pixel by its own white-furnace response, against the reference "
        "divided by its single-scattering albedo: single scattering (`multiscatter=False`, the reference's model) and Fdez-Aguera "
        "multiple scattering (`multiscatter=True`, the renderer's default for glTF).",
        "",
        "| roughness | metallic | IBL bias | diffuse mean (bias) | specular mean (bias) | single-scattering, furnace-normalised | multiple-scattering, furnace-normalised |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in result["materials"]:
        if "ibl_bias" not in r:
            continue
        d = (f"{100 * r['ibl_diffuse_mean_rel_error']:.2f} % ({100 * r['ibl_diffuse_bias']:+.2f} %)" if "ibl_diffuse_bias" in r else "-")
        sp = (f"{100 * r['ibl_specular_mean_rel_error']:.2f} % ({100 * r['ibl_specular_bias']:+.2f} %)" if "ibl_specular_bias" in r else "-")
        out.append(
            f"| {r['roughness']:g} | {r['metallic']:g} | {100 * r['ibl_bias']:+.2f} % | {d} | {sp} | "
            f"{100 * r['ibl_single_scatter_furnace_normalised_error']:.2f} % | {100 * r['ibl_multi_scatter_furnace_normalised_error']:.2f} % |"
        )
    ext = result.get("extensions") or []
    if ext:
        out += [
            "",
            "## glTF material extensions",
            "",
            f"Layered split sum (`shade_ibl` / `shade_direct` with the extension) against {c.get('extension_reference', 'reference_layered')}; "
            "roughness is the extension's own (clearcoat_roughness, sheen_roughness) or the base roughness.",
            "",
            "| extension | roughness | metallic | mean rel. error | max pixel rel. error | IBL mean rel. error | IBL max pixel | IBL share | split sum (ms) | reference (s) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in ext:
            if "unavailable" in r:
                out.append(f"| {r['extension']} | - | - | {r['unavailable']} | | | | | | |")
                continue
            out.append(
                f"| {r['extension']} | {r['roughness_field']} {r['roughness']:g} | {r['metallic']:g} | {100 * r['mean_rel_error']:.2f} % | {100 * r['max_pixel_rel_error']:.1f} % | "
                f"{100 * r['ibl_mean_rel_error']:.2f} % | {100 * r['ibl_max_pixel_rel_error']:.1f} % | {100 * r['ibl_share_of_radiance']:.0f} % | "
                f"{1e3 * r['split_sum_s']:.2f} | {r['reference_s']:.2f} |"
            )
    return "\n".join(out) + "\n"


def _asset_markdown(result: dict) -> str:
    """The table of `asset_report`: one row per part of the IBL term."""
    c, row = result["config"], result["asset"]
    skipped = []
    if c["pixels_below_roughness_floor"]:
        skipped.append(f"{c['pixels_below_roughness_floor']} with roughness below the reference's floor {c['roughness_floor']:.3f}")
    if c["pixels_back_facing"]:
        skipped.append(f"{c['pixels_back_facing']} with n.v <= 0")
    eligible = c["pixels_on_asset"] - c["pixels_below_roughness_floor"] - c["pixels_back_facing"]
    subset = f"a fixed random subset (seed {c['seed']}) of the {eligible} eligible" if c["pixels_measured"] < eligible else "every eligible pixel"
    per_px = row["reference_s"] / c["pixels_measured"]
    out = [
        f"# jaxpbr split-sum error on {c['asset']} vs float64 reference render",
        "",
        f"Asset: {c['asset']}, {c['image'][0]}x{c['image'][1]} G-buffer (pixel centres) with {c['pixels_on_asset']} px on the asset; "
        f"measured: {c['pixels_measured']} px, {subset}" + (f"; not eligible: {'; '.join(skipped)}" if skipped else "") + ".",
        f"Environment: {c['environment']} ({c['environment_face_size']}^2 per face); IBL only: no punctual lights, no emission, no shadows.",
        f"Split sum: {c['split_sum']}. Reference: {c['reference']}.",
        f"Run times (same process, back to back, on the {c['pixels_measured']} px): split sum {1e3 * row['split_sum_s']:.2f} ms, "
        f"reference {row['reference_s']:.2f} s ({1e3 * per_px:.2f} ms/px); G-buffer {result['gbuffer_s']:.2f} s, precompute (once) {result['precompute_s']:.2f} s. "
        f"Timing: {c['timing']}; device {c['device']}.",
        "",
        "Per-pixel relative luminance error |Y(split sum) - Y(reference)| / Y(reference) over the pixels where the part is present: "
        "mean and percentiles; bias: sum(Y(split sum) - Y(reference)) / sum Y(reference); RGB: sum |diff| / sum reference over "
        "pixels and channels (the sphere tables' mean rel. error). Parts as in the sphere report: diffuse and specular lobes "
        "(the specular one at the pixel's F0 without diffuse colour), each energy model divided by its white-furnace response, "
        "and the multiple-scattering term `render` draws against the single-scattering reference. "
        "Occlusion (texture) scales the reference and the split sum's maps, not its extracted suns (as in `render`).",
        "",
        "| part | pixels | mean | p50 | p90 | p99 | max | bias | RGB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key, label in PARTS.items():
        st = row["parts"].get(key)
        if st is None:
            out.append(f"| {label} | 0 | - | - | - | - | - | - | - |")
            continue
        out.append(
            f"| {label} | {st['pixels']} | {100 * st['lum_mean']:.2f} % | {100 * st['lum_p50']:.2f} % | {100 * st['lum_p90']:.2f} % | "
            f"{100 * st['lum_p99']:.1f} % | {100 * st['lum_max']:.1f} % | {100 * st['lum_bias']:+.2f} % | {100 * st['mean_rel_error']:.2f} % |"
        )
    return "\n".join(out) + "\n"


def to_json(result: dict) -> str:
    """The numbers of the result (no images) as JSON text."""
    data = {k: v for k, v in result.items() if k not in ("images", "mask", "extension_images", "samples")}
    return json.dumps(data, indent=2) + "\n"


def plot(result: dict, path) -> bool:
    """Per-pixel relative-error images, one per material (rows: metallic, columns: roughness), on
    one logarithmic colour scale with a colour bar -> PNG at `path`. False (nothing written)
    without matplotlib."""
    if not have_matplotlib():
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    if result["config"].get("kind") == "asset":
        return _asset_plot(result, path, plt, LogNorm)
    rough = result["config"]["roughness"]
    metal = result["config"]["metallic"]
    imgs = result["images"]
    vals = np.concatenate([im[np.isfinite(im)] for im in imgs.values()])
    hi = max(float(np.max(vals, initial=1e-3)), 1e-3)
    norm = LogNorm(vmin=max(hi * 1e-4, 1e-5), vmax=hi)
    fig, axes = plt.subplots(len(metal), len(rough), figsize=(2.0 * len(rough) + 1.2, 2.1 * len(metal) + 0.6), squeeze=False)
    rows = {(r["roughness"], r["metallic"]): r for r in result["materials"]}
    im = None
    for a, m in enumerate(metal):
        for b, r in enumerate(rough):
            ax = axes[a][b]
            img = np.clip(imgs[(r, m)], norm.vmin, None)
            im = ax.imshow(img, norm=norm, cmap="magma", interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            row = rows[(r, m)]
            ax.set_title(f"r={r:g} m={m:g}\nmean {100 * row['mean_rel_error']:.2f} %", fontsize=8)
    fig.colorbar(im, ax=axes, shrink=0.8, label="per-pixel relative error |split sum - reference| / reference")
    fig.suptitle(f"split-sum error, {result['config']['environment']}", fontsize=10)
    atomic_write(Path(path), lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)
    return True


def _asset_plot(result: dict, path, plt, LogNorm) -> bool:
    """The asset's per-pixel relative luminance error of the IBL term at its measured pixels (dots)
    over its coverage (grey)."""
    c, smp = result["config"], result["samples"]
    W, H = c["image"]
    err = np.asarray(smp["rel_lum_error"])
    hi = max(float(np.max(err[np.isfinite(err)], initial=1e-3)), 1e-3)
    norm = LogNorm(vmin=max(hi * 1e-4, 1e-5), vmax=hi)
    fig, ax = plt.subplots(figsize=(6.4, 6.4 * H / W + 0.6))
    ax.imshow(np.where(result["mask"], 0.85, 1.0), cmap="gray", vmin=0.0, vmax=1.0, interpolation="nearest")
    y, x = np.divmod(np.asarray(smp["pixel"]), W)
    dots = ax.scatter(x, y, c=np.clip(err, norm.vmin, None), norm=norm, cmap="magma", s=max(1.0, (1.5 * 6.4 * 72 / W) ** 2), linewidths=0)  # ~1.5 pixels wide
    ax.set_xlim(-0.5, W - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])
    fig.colorbar(dots, ax=ax, shrink=0.8, label="|Y(split sum) - Y(reference)| / Y(reference), IBL")
    ax.set_title(f"{c['asset']}, {c['environment']}: {c['pixels_measured']} px, mean {100 * result['asset']['parts']['ibl']['lum_mean']:.2f} %", fontsize=9)
    atomic_write(Path(path), lambda tmp: fig.savefig(tmp, dpi=110, format="png", bbox_inches="tight"))
    plt.close(fig)
    return True


def write_report(result: dict, output_dir, *, prefix: str = "render_report", log=print) -> list[Path]:
    """Write <prefix>.md, <prefix>.json and (with matplotlib) <prefix>.png into output_dir."""
    d = Path(output_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"output directory {str(d)!r} does not exist; create it first")
    with OutputSet() as outs:  # all of them or none: a failure removes what was already written
        for suffix, text in ((".md", markdown(result)), (".json", to_json(result))):
            path = d / f"{prefix}{suffix}"
            outs.add(path)
            atomic_write(path, lambda tmp, text=text: Path(tmp).write_text(text))
        png = d / f"{prefix}.png"
        if have_matplotlib():
            outs.add(png)
            plot(result, png)
        else:
            log("matplotlib is not installed: wrote the table and JSON only, no figure (pip install 'jaxpbr[report]')")
    return list(outs.written)


# ------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------


def _float_list(text: str) -> list[float]:
    try:
        vals = [float(x) for x in text.replace(",", " ").split()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not vals or any(not (math.isfinite(x) and 0.0 <= x <= 1.0) for x in vals):
        raise argparse.ArgumentTypeError(f"expected numbers in [0, 1], got {text!r}")
    return vals


def _name_list(text: str):
    if text.strip() == "all":
        return "all"
    names = [x.strip().replace("_", " ") for x in text.split(",") if x.strip()]
    bad = [x for x in names if x not in EXTENSION_ROWS]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"unknown extension(s) {bad or text!r}; choose from " + ", ".join(n.replace(" ", "_") for n in EXTENSION_ROWS) + " or all")
    return names


def add_command(report_subparsers):
    """Register `render` under the `jaxpbr report` sub-command group (the `add_subparsers()`
    object of `report`). Returns the new sub-parser."""
    p = report_subparsers.add_parser(
        "render",
        help="split-sum shading error vs the float64 reference render, on spheres or a glTF asset (Markdown table + JSON + PNG)",
        description="Shade one sphere per material (roughness x metallic) with the split sum and with the float64 "
        "reference (full reflectance integral over every environment texel), under an environment and two punctual "
        "lights; write render_report.md, render_report.json and render_report.png into --output-dir. "
        "With ASSET (.gltf, .glb) and --environment: the same on the asset's own pixels (its G-buffer, materials after "
        "textures), IBL only; write render_report_<asset name>.md/.json/.png.",
    )
    p.add_argument("asset", nargs="?", default=None, metavar="ASSET", help="a glTF 2.0 asset (.gltf, .glb) to measure instead of the spheres (needs --environment)")
    p.add_argument("--environment", "--env", dest="env", default=None, metavar="FILE", help=f"{ENVIRONMENT_HELP} (default for the spheres: procedural:sky; required with ASSET)")
    p.add_argument("--output-dir", default=".", help="directory for the .md/.json/.png (default: current)")
    p.add_argument("--face-size", type=positive_int_arg, default=64, help="environment face size (default: %(default)s; the reference's roughness floor halves in alpha per doubling, its cost grows 4x)")
    p.add_argument("--pixels", type=positive_int_arg, default=None, help=f"spheres: image size P x P (default: 48); ASSET: at most this many of its pixels, a fixed random subset, go to the reference (default: {DEFAULT_ASSET_PIXELS})")
    p.add_argument("--width", type=positive_int_arg, default=None, help=f"ASSET: G-buffer width (default: {DEFAULT_ASSET_SIZE[0]})")
    p.add_argument("--height", type=positive_int_arg, default=None, help=f"ASSET: G-buffer height (default: {DEFAULT_ASSET_SIZE[1]})")
    p.add_argument("--roughness", type=_float_list, default=None, help="spheres: comma-separated roughness values (default: " + ",".join(f"{x:g}" for x in DEFAULT_ROUGHNESS) + ")")
    p.add_argument("--metallic", type=_float_list, default=None, help="spheres: comma-separated metallic values (default: " + ",".join(f"{x:g}" for x in DEFAULT_METALLIC) + ")")
    p.add_argument("--base-color", type=float, nargs=3, default=None, metavar=("R", "G", "B"), help="spheres: linear base colour (default: " + " ".join(f"{x:g}" for x in DEFAULT_BASE_COLOR) + ")")
    p.add_argument("--irradiance-size", type=positive_int_arg, default=32)
    p.add_argument("--lut-size", type=positive_int_arg, default=128)
    p.add_argument("--no-extract-lights", dest="extract_lights", action="store_false", help="shade the whole environment with the split sum (no dominant-light extraction; the pre-issue-11 baseline)")
    p.add_argument(
        "--extensions", nargs="?", const="all", default=None, type=_name_list, metavar="NAMES",
        help="spheres: add rows per glTF material extension (comma-separated from " + ", ".join(n.replace(" ", "_") for n in EXTENSION_ROWS) + "; default all): "
        "the layered split sum against reference_layered (off by default: ~1 min per row at the default size, anisotropy several)",
    )
    p.add_argument("--no-extensions", dest="extensions", action="store_const", const=None, help="no extension rows (the default)")
    p.add_argument("--extension-roughness", type=_float_list, default=None, help="spheres: roughness values of the extension rows (default: " + ",".join(f"{x:g}" for x in DEFAULT_EXTENSION_ROUGHNESS) + ")")
    p.add_argument("--visibility", action="store_true",
                   help="ASSET (or builtin:concave, a concave test scene): measure every rung of the IBL's visibility "
                   "(none, occlusion, ao, ratio at --samples rays) against the float64 ground truth with visibility, with the time per frame")
    p.add_argument("--samples", type=_int_list, default=None, help="--visibility: rays per pixel of the traced rungs (default: 1,4,16,64)")
    p.add_argument("--spp", type=positive_int_arg, default=256, help="--visibility: the ground truth's samples per pixel (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_report_render)
    return p


def _env_name(env: str) -> str:
    return "procedural sky+sun" if env.startswith("procedural:") else Path(env).name


def cmd_report_render(args) -> int:
    out_dir = Path(args.output_dir)
    if not out_dir.is_dir():
        raise InputError(f"--output-dir {str(out_dir)!r} does not exist; create it first")
    log = (lambda m: None) if args.quiet else (lambda m: print(m, file=sys.stderr))
    if args.visibility:
        return _cmd_visibility(args, out_dir, log)
    if args.asset is not None:
        return _cmd_asset(args, out_dir, log)
    if args.width is not None or args.height is not None:
        raise CLIError("--width/--height size an ASSET's G-buffer; the spheres' size is --pixels")
    roughness = args.roughness or list(DEFAULT_ROUGHNESS)
    metallic = args.metallic or list(DEFAULT_METALLIC)
    base_color = args.base_color or list(DEFAULT_BASE_COLOR)
    pixels = args.pixels or 48
    env_arg = args.env or "procedural:sky"
    if any(not 0.0 <= c <= 1.0 for c in base_color):
        raise InputError(f"--base-color must lie in [0, 1], got {base_color}")
    # Before any work: the G-buffer and the per-material images are float64 per pixel (48^2 -> 144^2
    # raised the peak RSS by 56 MB for one material: ~3 kB per pixel), the environment as usual.
    materials = len(roughness) * len(metallic)
    require_memory(f"a {pixels}x{pixels} report of {materials} materials", pixels**2 * (3000.0 + 100.0 * materials), "lower --pixels")
    require_environment(args.face_size, procedural=env_arg.startswith("procedural:"))
    env = load_environment([env_arg], face_size=args.face_size)
    result = render_report(
        env,
        env_name=_env_name(env_arg),
        roughness=roughness,
        metallic=metallic,
        base_color=tuple(base_color),
        pixels=pixels,
        irradiance_size=args.irradiance_size,
        lut_size=args.lut_size,
        extract_lights=args.extract_lights,
        extensions=args.extensions or (),
        extension_roughness=args.extension_roughness or list(DEFAULT_EXTENSION_ROUGHNESS),
        log=log,
    )
    return _write_and_print(result, out_dir, "render_report", log)


def _cmd_asset(args, out_dir: Path, log) -> int:
    """`report render ASSET --environment FILE`: inputs checked before any work, then `asset_report`."""
    path = Path(args.asset)
    if path.suffix.lower() not in (".gltf", ".glb"):
        raise CLIError(f"ASSET must be a glTF 2.0 file (.gltf or .glb), got {path.name!r}")
    if not path.is_file():
        raise CLIError(f"ASSET {str(path)!r} does not exist")
    if args.env is None:
        raise CLIError("an ASSET is measured under an environment: add --environment FILE (an equirect .hdr/.exr panorama) or --environment procedural:sky")
    sphere_only = [f for f, v in (("--roughness", args.roughness), ("--metallic", args.metallic), ("--base-color", args.base_color),
                                  ("--extensions", args.extensions), ("--extension-roughness", args.extension_roughness)) if v is not None]
    if sphere_only:
        raise CLIError(f"{', '.join(sphere_only)} set the spheres' materials; an ASSET brings its own")
    W, H = args.width or DEFAULT_ASSET_SIZE[0], args.height or DEFAULT_ASSET_SIZE[1]
    pixels = args.pixels or DEFAULT_ASSET_PIXELS
    # The G-buffer (~300 bytes per pixel with its stages) and the reference's float64 work per measured pixel (~3 kB).
    require_memory(f"a {W}x{H} G-buffer and {pixels} reference pixels", W * H * 300.0 + pixels * 3000.0, "lower --width/--height or --pixels")
    require_environment(args.face_size, procedural=args.env.startswith("procedural:"))
    scene = load_gltf(path, width=W, height=H, asset_lights=False)
    env = load_environment([args.env], face_size=args.face_size)
    result = asset_report(
        scene, env, env_name=_env_name(args.env), asset_name=path.name, face_size=args.face_size, pixels=pixels,
        irradiance_size=args.irradiance_size, lut_size=args.lut_size, extract_lights=args.extract_lights, log=log,
    )
    return _write_and_print(result, out_dir, f"render_report_{path.stem}", log)


def _int_list(text: str) -> list[int]:
    try:
        vals = [int(x) for x in text.replace(",", " ").split()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not vals or any(not 1 <= x <= 256 for x in vals):
        raise argparse.ArgumentTypeError(f"expected integers in [1, 256], got {text!r}")
    return vals


def _cmd_visibility(args, out_dir: Path, log) -> int:
    """`report render ASSET --visibility`: the rungs against the ground truth (`report_visibility`)."""
    from ..rendering.demo import concave_scene
    from .report_visibility import DEFAULT_SAMPLES, visibility_markdown, visibility_report, write_visibility_report

    if args.asset is None:
        raise CLIError("--visibility measures an ASSET: a glTF file, or builtin:concave (a concave scene written in code)")
    W, H = args.width or 320, args.height or 240
    if args.spp < 2:
        raise CLIError("--spp must be at least 2 (the ground truth's standard error needs two samples)")
    if args.asset == "builtin:concave":
        env = None
        if args.env is not None:
            require_environment(args.face_size, procedural=args.env.startswith("procedural:"))
            env = Environment(radiance=load_environment([args.env], face_size=args.face_size))
        scene, name = concave_scene(W, H, environment=env), "concave scene (builtin)"
    else:
        path = Path(args.asset)
        if path.suffix.lower() not in (".gltf", ".glb") or not path.is_file():
            raise CLIError(f"ASSET must be an existing glTF 2.0 file (.gltf or .glb) or builtin:concave, got {args.asset!r}")
        if args.env is None:
            raise CLIError("an ASSET is measured under an environment: add --environment FILE or --environment procedural:sky")
        require_environment(args.face_size, procedural=args.env.startswith("procedural:"))
        env = Environment(radiance=load_environment([args.env], face_size=args.face_size))
        scene, name = load_gltf(path, width=W, height=H, asset_lights=False, environment=env), path.name
    require_memory(f"a {W}x{H} ground truth", W * H * 2000.0, "lower --width/--height")
    result = visibility_report(scene, name=name, samples=tuple(args.samples or DEFAULT_SAMPLES), spp=args.spp, log=log)
    prefix = "visibility_report" if args.asset == "builtin:concave" else f"visibility_report_{Path(args.asset).stem}"
    written = write_visibility_report(result, out_dir, prefix)
    print(visibility_markdown(result))
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


def _write_and_print(result: dict, out_dir: Path, prefix: str, log) -> int:
    written = write_report(result, out_dir, prefix=prefix, log=log)
    print(markdown(result))
    print("wrote " + ", ".join(str(p) for p in written) + ("" if any(p.suffix == ".png" for p in written) else " (no figure: matplotlib is not installed)"))
    return 0
