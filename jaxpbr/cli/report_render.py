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
and the run times. Outputs: a Markdown table, a JSON of the numbers and a PNG of the per-pixel
relative-error images (the PNG needs matplotlib: `pip install 'jaxpbr[report]'`).
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
from ..shading import lights as _lights
from ..shading.material import Material
from ..shading.shipped_luts import brdf_lut
from ._common import (
    have_matplotlib,
    positive_int_arg,
    require_environment,
    require_memory,
)
from .timing import time_calls

__all__ = ["DEFAULT_EXTENSION_ROUGHNESS", "DEFAULT_METALLIC", "DEFAULT_ROUGHNESS", "EXTENSION_ROWS", "add_command", "default_lights", "markdown", "plot", "render_report", "sphere_gbuffer", "write_report"]

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


def _ibl_parts(split_sum, furnace, terms, r, metallic, base_color, ibl, ref_ibl) -> dict:
    """The IBL term's error by part and by energy model, for one material.

    * bias: signed relative error of the IBL term (single scattering, the reference's model);
    * dielectrics (metallic 0): the diffuse and specular parts apart. The split sum is linear in
      base colour there, so the specular part is the IBL term at base colour 0 and the diffuse part
      the difference to base colour 1; the reference's are its F0 LA + LB and Ld sums;
    * energy models: the IBL term divided per pixel by the same model's white-furnace response (which
      removes the choice of energy compensation and leaves what the environment contributes), the
      single-scattering split sum and the multiple-scattering one (`multiscatter=True`, the renderer's
      default for glTF) each against the reference divided by its own furnace response. The
      reference's furnace is the LUT's single-scattering albedo (F0 A + B + (1 - metallic) base
      0.96 (1 - C)): the split sum under L = 1 is exact but for the LUT, converged to ~1e-5.
    """
    f32 = jnp.float32

    def mat(base):
        return Material(base_color=jnp.asarray(base, f32), metallic=jnp.asarray(metallic, f32), roughness=jnp.asarray(r, f32))

    out = dict(ibl_bias=_bias(ibl, ref_ibl))
    if metallic == 0.0:
        with jax.enable_x64(True):
            zero = Material(base_color=jnp.zeros(3), metallic=jnp.float64(0.0), roughness=jnp.float64(r))
            one = Material(base_color=jnp.ones(3), metallic=jnp.float64(0.0), roughness=jnp.float64(r))
        ref_s = reference_ibl_from_terms(terms, zero)
        ref_d = reference_ibl_from_terms(terms, one) - ref_s
        ss_s = split_sum(mat((0.0, 0.0, 0.0)))
        ss_d = split_sum(mat((1.0, 1.0, 1.0))) - ss_s
        out.update(
            ibl_diffuse_mean_rel_error=_errors(ss_d, ref_d)[0], ibl_diffuse_bias=_bias(ss_d, ref_d),
            ibl_specular_mean_rel_error=_errors(ss_s, ref_s)[0], ibl_specular_bias=_bias(ss_s, ref_s),
        )
    m = mat(base_color)
    ref_norm = ref_ibl / furnace(m, False)
    for name, ms in (("single", False), ("multi", True)):
        test = (ibl if not ms else split_sum(m, True)) / furnace(m, ms)
        out[f"ibl_{name}_scatter_furnace_normalised_error"] = _errors(test, ref_norm)[0]
    return out


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
    if isinstance(env, (str, Path)):
        env_name = env_name or str(env)
        env = load_environment([str(env)], face_size)
    elif env is None:
        env_name = env_name or "procedural sky+sun"
        env = envs.sky_with_sun_cubemap(face_size)
    elif not isinstance(env, Cubemap):
        raise TypeError(f"env must be None, a path or a Cubemap, got {type(env).__name__}")
    env_name = env_name or "environment"
    env = Cubemap((jnp.asarray(env.levels[0], jnp.float32),), env.metadata)
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
    t0 = time.perf_counter()
    ss_env, ss_lights, extracted = env, list(lights) if isinstance(lights, (list, tuple)) else [lights], []
    if extract_lights:
        ex = _extract.extract_lights(env)
        ss_env, extracted = ex.residual, ex.info["lights"]
        ss_lights = ss_lights + list(ex.lights)
    lut = brdf_lut(lut_size)
    irr = irradiance(ss_env, irradiance_size)
    pre = prefilter(ss_env, prefilter_size)
    jax.block_until_ready((lut, irr.levels, pre.levels))
    precompute_s = time.perf_counter() - t0
    for x in extracted:
        log(f"  extracted a disc light: radius {x['angular_radius_deg']:.2f} deg, {100 * x['power_share']:.1f} % of the environment's power")
    log(f"  precompute (LUT {lut_size}^2, irradiance {irradiance_size}^2, prefilter {pre.face_size}^2 x {pre.num_levels} mips): {precompute_s:.2f} s")

    f32 = jnp.float32
    n32, v32, p32 = (jnp.asarray(a, f32) for a in (n, v, p))
    lights32 = _lights_as(ss_lights[: len(ss_lights) - len(extracted)], f32)
    discs32 = _lights_as(ss_lights[len(ss_lights) - len(extracted):], f32) if extracted else None

    @functools.partial(jax.jit, static_argnames=("multiscatter",))
    def split_sum(p_, n_, v_, m_, irr_, pre_, lut_, lights_, discs_, multiscatter=False):
        # "IBL" = what the environment contributes: the split sum of the (residual) environment
        # plus its extracted disc lights (emission added once, by the scene lights' term), with
        # the multiple-scattering compensation of both when asked (as `render` does).
        ibl = shade_ibl(n_, v_, m_, irr_, pre_, lut_, multiscatter=multiscatter)
        if discs_ is not None:
            dark = m_.replace(emissive=jnp.zeros_like(m_.emissive))
            ibl = ibl + _lights.shade_direct(p_, n_, v_, dark, discs_, disc_lights=True)
            if multiscatter:
                ibl = ibl + disc_multiscatter(n_, v_, m_, lut_, discs_)
        return _lights.shade_direct(p_, n_, v_, m_, lights_) + ibl, ibl

    # The white furnace (L = 1 everywhere) of the split sum: the per-pixel response each energy
    # model divides by in the energy-model columns.
    ones = lambda c: Cubemap(tuple(jnp.ones_like(x) for x in c.levels), c.metadata)  # noqa: E731
    irr1, pre1 = ones(irr), ones(pre)
    furnace = jax.jit(lambda n_, v_, m_, ms: shade_ibl(n_, v_, m_, irr1, pre1, lut, multiscatter=ms), static_argnums=3)

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
            m32 = material(r, m, f32)
            (tot, ibl), timing = time_calls(lambda: split_sum(p32, n32, v32, m32, irr, pre, lut, lights32, discs32), rounds=repeats)
            ss_s = timing.best
            tot, ibl = np.asarray(tot, np.float64), np.asarray(ibl, np.float64)
            t0 = time.perf_counter()
            with jax.enable_x64(True):
                m64 = material(r, m, jnp.float64)
                ref_direct = np.asarray(direct64(m64))
            ref_ibl = reference_ibl_from_terms(terms, m64)
            ref = ref_direct + ref_ibl
            ref_s = terms_s + time.perf_counter() - t0
            mean, mx, per_pixel = _errors(tot, ref)
            ibl_mean, ibl_max, _ = _errors(ibl, ref_ibl)
            parts = _ibl_parts(lambda m_, ms=False: np.asarray(split_sum(p32, n32, v32, m_, irr, pre, lut, lights32, discs32, multiscatter=ms)[1], np.float64),
                               lambda m_, ms: np.asarray(furnace(n32, v32, m_, ms), np.float64), terms, r, m, base_color, ibl, ref_ibl)
            img = np.full(mask.shape, np.nan)
            img[mask] = per_pixel
            images[(r, m)] = img
            worst = int(np.argmax(per_pixel))
            rows.append(
                dict(
                    roughness=r,
                    metallic=m,
                    mean_rel_error=mean,
                    max_pixel_rel_error=mx,
                    worst_pixel_n_dot_v=float(n[worst, 2]),
                    ibl_mean_rel_error=ibl_mean,
                    ibl_max_pixel_rel_error=ibl_max,
                    ibl_share_of_radiance=float(np.abs(ref_ibl).sum() / np.abs(ref).sum()),
                    **parts,
                    split_sum_s=ss_s,
                    reference_s=ref_s,
                    reference_ibl_shared_s=terms_s,
                )
            )
            log(
                f"  r={r:g} metallic={m:g}: mean {100 * mean:.2f} %, max pixel {100 * mx:.1f} %, IBL mean {100 * ibl_mean:.2f} %; "
                f"split sum {1e3 * ss_s:.2f} ms, reference {ref_s:.1f} s"
            )
    ext_rows = _extension_rows(
        extensions, extension_roughness, base_color=base_color, env=env, ss_env=ss_env, n=n, v=v, p=p, mask=mask,
        lights=lights, lights32=lights32, discs32=discs32, irr=irr, pre=pre, lut=lut, repeats=repeats, log=log,
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
        extracted_lights=extracted,
        split_sum=("environment split into " + (f"{len(extracted)} disc light(s) + residual; " if extracted else "no disc light (none found); ") if extract_lights else "") + f"float32 shade_direct + shade_ibl (gltf), irradiance {irradiance_size}^2 exact, prefilter {pre.face_size}^2 x {pre.num_levels} mips (FIS defaults), BRDF LUT {lut_size}^2",
        reference="float64 shade_direct + reference_ibl (every texel of level 0, tiered sub-texel supersampling)",
        geometry="orthographic unit sphere, v = +Z, n = (x, y, sqrt(1 - x^2 - y^2)), position = n",
        timing=f"split sum: best of {repeats} jitted calls after a warm-up; reference: one call incl. compilation (its three environment sums are shared by the metallic values of one roughness)",
        device=str(jax.devices()[0].platform),
    )
    if extensions:
        config["extension_roughness"] = extension_roughness
        config["extension_rows"] = {e: dict(EXTENSION_ROWS[e][0], roughness_field=EXTENSION_ROWS[e][1]) for e in extensions}
        config["extension_reference"] = "float64 shade_direct + reference_layered (the layered BSDF over the whole sphere of directions, tiered sub-texel supersampling around each lobe)"
    return dict(config=config, precompute_s=precompute_s, materials=rows, images=images, mask=mask, extensions=ext_rows[0], extension_images=ext_rows[1])


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


# ------------------------------------------------------------------------------------------
# outputs
# ------------------------------------------------------------------------------------------


def markdown(result: dict) -> str:
    """The result as a Markdown section (config line + table)."""
    c = result["config"]
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
        "Bias: signed relative error of the IBL term. Diffuse / specular (dielectrics): the two parts apart (the split sum is "
        "linear in base colour: specular = the term at base colour 0, diffuse = the difference to base colour 1). "
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


def to_json(result: dict) -> str:
    """The numbers of the result (no images) as JSON text."""
    data = {k: v for k, v in result.items() if k not in ("images", "mask", "extension_images")}
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
        help="split-sum shading error vs the float64 reference render (Markdown table + JSON + PNG)",
        description="Shade one sphere per material (roughness x metallic) with the split sum and with the float64 "
        "reference (full reflectance integral over every environment texel), under an environment and two punctual "
        "lights; write render_report.md, render_report.json and render_report.png into --output-dir.",
    )
    p.add_argument("--env", default="procedural:sky", help=f"{ENVIRONMENT_HELP} (default: %(default)s)")
    p.add_argument("--output-dir", default=".", help="directory for render_report.md/.json/.png (default: current)")
    p.add_argument("--face-size", type=positive_int_arg, default=64, help="environment face size (default: %(default)s; the reference's roughness floor halves in alpha per doubling, its cost grows 4x)")
    p.add_argument("--pixels", type=positive_int_arg, default=48, help="sphere image size P x P (default: %(default)s)")
    p.add_argument("--roughness", type=_float_list, default=list(DEFAULT_ROUGHNESS), help="comma-separated roughness values (default: %(default)s)")
    p.add_argument("--metallic", type=_float_list, default=list(DEFAULT_METALLIC), help="comma-separated metallic values (default: %(default)s)")
    p.add_argument("--base-color", type=float, nargs=3, default=list(DEFAULT_BASE_COLOR), metavar=("R", "G", "B"), help="linear base colour (default: %(default)s)")
    p.add_argument("--irradiance-size", type=positive_int_arg, default=32)
    p.add_argument("--lut-size", type=positive_int_arg, default=128)
    p.add_argument("--no-extract-lights", dest="extract_lights", action="store_false", help="shade the whole environment with the split sum (no dominant-light extraction; the pre-issue-11 baseline)")
    p.add_argument(
        "--extensions", nargs="?", const="all", default=None, type=_name_list, metavar="NAMES",
        help="add rows per glTF material extension (comma-separated from " + ", ".join(n.replace(" ", "_") for n in EXTENSION_ROWS) + "; default all): "
        "the layered split sum against reference_layered (off by default: ~1 min per row at the default size, anisotropy several)",
    )
    p.add_argument("--no-extensions", dest="extensions", action="store_const", const=None, help="no extension rows (the default)")
    p.add_argument("--extension-roughness", type=_float_list, default=list(DEFAULT_EXTENSION_ROUGHNESS), help="roughness values of the extension rows (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_report_render)
    return p


def cmd_report_render(args) -> int:
    out_dir = Path(args.output_dir)
    if not out_dir.is_dir():
        raise InputError(f"--output-dir {str(out_dir)!r} does not exist; create it first")
    if any(not 0.0 <= c <= 1.0 for c in args.base_color):
        raise InputError(f"--base-color must lie in [0, 1], got {args.base_color}")
    # Before any work: the G-buffer and the per-material images are float64 per pixel (48^2 -> 144^2
    # raised the peak RSS by 56 MB for one material: ~3 kB per pixel), the environment as usual.
    materials = len(args.roughness) * len(args.metallic)
    require_memory(f"a {args.pixels}x{args.pixels} report of {materials} materials", args.pixels**2 * (3000.0 + 100.0 * materials), "lower --pixels")
    require_environment(args.face_size, procedural=args.env.startswith("procedural:"))
    env = load_environment([args.env], args.face_size)
    name = "procedural sky+sun" if args.env.startswith("procedural:") else Path(args.env).name
    log = (lambda m: None) if args.quiet else (lambda m: print(m, file=sys.stderr))
    result = render_report(
        env,
        env_name=name,
        roughness=args.roughness,
        metallic=args.metallic,
        base_color=tuple(args.base_color),
        pixels=args.pixels,
        irradiance_size=args.irradiance_size,
        lut_size=args.lut_size,
        extract_lights=args.extract_lights,
        extensions=args.extensions or (),
        extension_roughness=args.extension_roughness,
        log=log,
    )
    written = write_report(result, out_dir, log=log)
    print(markdown(result))
    print("wrote " + ", ".join(str(p) for p in written) + ("" if any(p.suffix == ".png" for p in written) else " (no figure: matplotlib is not installed)"))
    return 0
