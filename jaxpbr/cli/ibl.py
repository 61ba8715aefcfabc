"""`jaxpbr lut | irradiance | prefilter | ibl`: the IBL asset generator commands.

Every output gets a JSON sidecar (`<output>.json`) with the conventions, parameters, library
versions, run time and the measured error against the float64 reference. Inputs are validated
before any work starts; outputs are written atomically, and a command that fails removes the
files it already wrote, so there are never partial results.

`jaxpbr ibl` bakes the whole set into one folder through `jaxpbr.ibl.baked.write_baked` (the
library's `jaxpbr.write_baked`): irradiance.ktx2, prefiltered.ktx2 (GGX), charlie.ktx2 (the
Charlie-prefiltered cube of KHR_materials_sheen's IBL term, `--no-sheen` leaves it out),
brdf_lut.exr (R = A, G = B: the GGX split sum; B = E_sheen, the Charlie sheen albedo, 0 with
`--no-sheen`), optionally lights.json, and the index ibl.json. This module parses the flags, shows
the progress bars and prints one line per file; the single-file commands write their file with the
same pieces (`irradiance_asset`, `prefiltered_asset`, `lut_asset`, `write_asset`).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from .._memory import check_samples, lut_bytes, require
from ..conventions import cube_conventions, library_versions
from ..errors import InputError
from ..ibl.baked import (
    check_float16,
    check_prefilter_options,
    guard_irradiance,
    irradiance_asset,
    load_source,
    lut_asset,
    prefiltered_asset,
    prepare_output,
    write_asset,
    write_baked,
)
from ..ibl.cubeio import ENVIRONMENT_HELP
from ..ibl.diffuse import irradiance
from ..ibl.sheen_prefilter import DEFAULT_CHARLIE_LEVELS, DEFAULT_CHARLIE_SIZE
from ..ibl.specular import (
    DEFAULT_CHAIN_FLOOR,
    DEFAULT_EXACT_TEXELS,
    DEFAULT_LOD_BLEND,
    DEFAULT_SAMPLES,
    LOD_BLENDS,
    MAPPINGS,
    MIN_CHAIN_LEVELS,
    prefilter,
)
from ..io import image
from ..io.atomic import OutputSet, write_json
from ..shading.lut import DEFAULT_SAMPLES as LUT_DEFAULT_SAMPLES
from ..shading.lut import SMITH_ALIASES, SMITH_VARIANTS, lut_shape
from ..shading.shipped_luts import brdf_lut
from ._common import Progress, positive_int_arg, raise_pending

__all__ = ["add_commands", "cmd_ibl", "cmd_irradiance", "cmd_lut", "cmd_prefilter"]

# LUT Smith terms: the current names, then the deprecated aliases (still accepted).
_SMITH_CHOICES = SMITH_VARIANTS + tuple(SMITH_ALIASES)
_SMITH_HELP = (
    "LUT Smith term: correlated = height-correlated Smith (glTF/Filament, default), schlick_ggx = "
    "Schlick-GGX k=alpha/2 (Karis/LearnOpenGL); 'schlick' is a deprecated alias of schlick_ggx"
)


# ------------------------------------------------------------------------------------------
# commands
# ------------------------------------------------------------------------------------------


def add_commands(sub) -> None:
    """Register `lut`, `irradiance`, `prefilter` and `ibl` on the top-level sub-parsers."""

    def common_env(p):
        p.add_argument("env", nargs="+", metavar="ENV", help=ENVIRONMENT_HELP)
        p.add_argument("--face-size", type=positive_int_arg, default=None, help="face size of the environment cube (default: from the panorama, 128 for procedural: the demo's sky)")
        p.add_argument("--clamp-negative", action="store_true", help="set negative input pixels to 0 (with a warning) instead of failing")

    def common_out(p, default, suffixes):
        p.add_argument("-o", "--output", default=default, help=f"output file ({' or '.join(suffixes)}; default: %(default)s); a JSON sidecar is written next to it")
        p.add_argument("--ktx-format", choices=("rgba16f", "rgba32f"), default="rgba16f", help="KTX2 texel format (default: %(default)s)")
        p.add_argument("--no-error", action="store_true", help="skip measuring the error against the float64 reference")
        p.add_argument("--quiet", action="store_true", help="no progress output")

    p = sub.add_parser("lut", help="generate the split-sum BRDF LUT (EXR)", description="Converged split-sum LUT (A, B) with (n_r, n_nov) texels; the EXR's R = A, G = B, B = 0; row j at r = (j+0.5)/n_r (row 0 at the top), column i at NoV = (i+0.5)/n_nov.")
    p.add_argument("--size", type=positive_int_arg, default=128, help="texels per side (default: %(default)s)")
    p.add_argument("--smith", choices=_SMITH_CHOICES, default="correlated", help=_SMITH_HELP)
    p.add_argument("--samples", type=positive_int_arg, default=None, help="quadrature samples per texel (default: the library default)")
    p.add_argument("-o", "--output", default="brdf_lut.exr", help="output .exr (default: %(default)s)")
    p.add_argument("--full-check", action="store_true", help="measure the error at every texel (slower) instead of the edges + 1024 random texels")
    p.add_argument("--no-error", action="store_true", help="skip measuring the error")
    p.add_argument("--sheen", action="store_true", help="the sheen albedo table E of KHR_materials_sheen instead (R = E, G = B = 0; --smith is ignored)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_lut)

    p = sub.add_parser("irradiance", help="diffuse irradiance cube (E/pi) from an environment")
    common_env(p)
    p.add_argument("--size", type=positive_int_arg, default=32, help="output face size (default: %(default)s)")
    p.add_argument("--method", choices=("exact", "sh9"), default="exact", help="exact cosine convolution or SH9 (default: %(default)s)")
    common_out(p, "irradiance.ktx2", (".ktx2", ".exr"))
    p.set_defaults(func=cmd_irradiance)

    p = sub.add_parser("prefilter", help="GGX-prefiltered specular cube with all mips")
    common_env(p)
    _prefilter_args(p)
    common_out(p, "prefiltered.ktx2", (".ktx2", ".exr"))
    p.set_defaults(func=cmd_prefilter)

    p = sub.add_parser("ibl", help="irradiance + prefiltered cube + BRDF LUT in one go")
    common_env(p)
    _prefilter_args(p)
    p.add_argument("--irradiance-size", type=positive_int_arg, default=32)
    p.add_argument("--irradiance-method", choices=("exact", "sh9"), default="exact")
    p.add_argument("--lut-size", type=positive_int_arg, default=128)
    p.add_argument("--smith", choices=_SMITH_CHOICES, default="correlated", help=_SMITH_HELP)
    p.add_argument("--out-dir", default=".", help="directory for irradiance.ktx2, prefiltered.ktx2, charlie.ktx2, brdf_lut.exr and ibl.json (default: current)")
    p.add_argument("--no-sheen", action="store_true", help="leave the sheen assets out (for engines without KHR_materials_sheen): no charlie.ktx2, and the LUT's B channel stays 0")
    p.add_argument("--charlie-size", type=positive_int_arg, default=None,
                   help=f"face size of the Charlie cube's level 0 (default: {DEFAULT_CHARLIE_SIZE}, or the environment's face size if smaller, as jaxpbr render)")
    p.add_argument("--charlie-levels", type=positive_int_arg, default=None,
                   help=f"levels M of the Charlie cube, sheen roughness r_m = m/(M-1) (default: {DEFAULT_CHARLIE_LEVELS}, fewer if the face size allows fewer)")
    p.add_argument("--extract-lights", action="store_true", help="split dominant lights (suns) out of the environment first: the cubes hold the residual and lights.json the disc lights "
                   "(jaxpbr's fields and a glTF KHR_lights_punctual list), for engines that shade the sun analytically")
    p.add_argument("--radiance", action="store_true", help="also store the environment itself (level 0, before any extraction) as radiance.ktx2: "
                   "jaxpbr.read_baked draws it as the background")
    p.add_argument("--ktx-format", choices=("rgba16f", "rgba32f"), default="rgba16f")
    p.add_argument("--no-error", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_ibl)


def _prefilter_args(p):

    p.add_argument("--size", type=positive_int_arg, default=None, help="face size of mip 0 (default: the environment's)")
    p.add_argument("--levels", type=positive_int_arg, default=None, help=f"number of mips M (default: down to {DEFAULT_CHAIN_FLOOR}x{DEFAULT_CHAIN_FLOOR}, at least {MIN_CHAIN_LEVELS})")
    p.add_argument("--mapping", choices=MAPPINGS, default="linear", help="level roughness: r_m = m/(M-1) or Filament's (default: %(default)s)")
    p.add_argument("--lod-blend", choices=LOD_BLENDS, default=DEFAULT_LOD_BLEND, help="lookup between two mips, recorded in the metadata: linear in the lobe's mean cosine (exact for a smooth environment) or plain lod = r*(M-1) (default: %(default)s)")
    p.add_argument("--method", choices=("fis", "reference"), default="fis", help="filtered importance sampling or the float64 brute-force reference (slow)")
    p.add_argument("--samples", type=positive_int_arg, default=DEFAULT_SAMPLES, help="FIS samples on the large levels (default: %(default)s; small levels get more)")
    p.add_argument("--exact-texels", type=int, default=None, help=f"brightest texels convolved exactly (default: {DEFAULT_EXACT_TEXELS} per 256^2 of face area, i.e. {DEFAULT_EXACT_TEXELS * 16} at 1024^2; 0 = off)")


#: The library's keywords -> this command line's flags, for the messages of `jaxpbr.ibl.baked`.
_FLAGS = {
    "face_size": "--face-size", "size": "--size", "levels": "--levels", "samples": "--samples",
    "exact_texels": "--exact-texels", "ktx_format": "--ktx-format", "irradiance_size": "--irradiance-size",
    "lut_size": "--lut-size", "charlie_size": "--charlie-size", "charlie_levels": "--charlie-levels",
    "out_dir": "--out-dir", "sheen=False": "--no-sheen",
}


class _Bars:
    """The library's `progress(step, done, total)` as one progress bar per step on stderr."""

    def __init__(self):
        self.bars = {}

    def step(self, name: str) -> Progress:
        if name not in self.bars:
            self.bars[name] = Progress(name)
        return self.bars[name]

    def __call__(self, step: str, done: int, total: int) -> None:
        self.step(step)(done, total)


def _bars(quiet: bool) -> _Bars | None:
    """Progress bars, or None with --quiet: the precomputes then compile no progress callback, and a
    program without host callbacks is kept in JAX's persistent compilation cache (a warm `jaxpbr
    ibl --quiet` reads its programs instead of compiling them again)."""
    return None if quiet else _Bars()


def _bar(bars: _Bars | None, name: str) -> Progress | None:
    return None if bars is None else bars.step(name)


def _load(args, kind: str):
    """The environment, with the memory its processing needs checked before and after loading (the
    face size may come from the panorama)."""
    return load_source(args.env, face_size=args.face_size, clamp_negative=args.clamp_negative, kind=kind, names=_FLAGS)


def _checked(outs: OutputSet, path: Path, suffixes) -> Path:
    """The output path validated before any work, and what it will replace protected."""
    return prepare_output(outs, path, suffixes)


def _check_prefilter_size(args, face_size) -> None:
    """--size a power-of-two divisor of the face size, --levels at most what it holds, --samples
    below 2^32, the whole within the memory (before the work, the flags named)."""
    check_prefilter_options(face_size, size=args.size, levels=args.levels, method=args.method, samples=args.samples, names=_FLAGS)


def _prefilter_checks(args, env, out: Path) -> None:
    """What a prefilter of `env` into `out` can be refused for, once the environment is loaded."""
    _check_prefilter_size(args, env.face_size)
    check_float16(env, out, size=args.size, ktx_format=args.ktx_format, names=_FLAGS)


def _run(fn):
    with OutputSet() as outs:
        code = fn(outs)
        raise_pending()  # an interrupt whose exception was swallowed: roll back, do not commit
        return code


def _error_note(side: dict) -> str:
    """The error part of a prefiltered cube's one-line summary."""
    err = side.get("error_vs_float64_reference")
    if not err:
        return ""
    w = err["worst"]
    return f"; error vs reference (sampled texels): worst level mean {100 * w['mean']:.2f} %, worst texel {100 * w['max']:.2f} %"


def _said_irradiance(out, side: dict) -> str:
    err = side["error_vs_float64_exact_full_resolution"]
    e = f"; error vs exact: mean {100 * err['mean']:.3f} %, max {100 * err['max']:.3f} %" if err else ""
    return f"wrote {out} ({side['face_size']}^2 irradiance, {side['method']}, {side['seconds']:.2f} s{e})"


def _said_prefiltered(out, side: dict, method: str) -> str:
    return f"wrote {out} ({side['face_size']}^2, {side['num_levels']} mips, {method}, {side['seconds']:.2f} s{_error_note(side)})"


def _said_charlie(out, side: dict) -> str:
    return (f"wrote {out} ({side['face_size']}^2, {side['num_levels']} mips, Charlie from a {side['source_face_size']}^2 source, "
            f"{side['seconds']:.2f} s{_error_note(side)})")


def _said_lut(out, side: dict) -> str:
    err = side["error_vs_float64_reference"]
    e = f"; max |error| {err['max']:.2e} over {err['texels']} texels" if err else ""
    n_r, n_nov = side["size"]
    return f"wrote {out} ({n_r}x{n_nov}, smith {side['smith']}, {side['seconds']:.2f} s{e})"


def _smith(args) -> str:
    """--smith, a deprecated alias replaced by its current name with a one-line warning."""
    smith = SMITH_ALIASES.get(args.smith, args.smith)
    if smith != args.smith:
        print(f"jaxpbr: warning: --smith {args.smith} is deprecated; use --smith {smith}", file=sys.stderr)
    return smith


def cmd_lut(args) -> int:
    return _run(lambda outs: _lut(args, outs) and 0)


def _lut(args, outs: OutputSet) -> dict:
    """`jaxpbr lut`: the split-sum LUT file (`jaxpbr.ibl.baked.lut_asset`) and its sidecar."""
    out = _checked(outs, Path(args.output), (".exr",))
    n_r, n_nov = lut_shape(args.size)
    samples = args.samples or LUT_DEFAULT_SAMPLES
    check_samples("--samples", samples)
    require(f"a LUT of {n_r}x{n_nov} texels" + (f" with {samples} samples per texel" if args.samples else ""),
            lut_bytes(n_r, n_nov, samples), names={"size": "--size", "samples": "--samples"})
    if args.sheen:
        return _sheen_lut(args, outs, out)
    t0 = time.perf_counter()
    smith = _smith(args)
    lut = np.asarray(brdf_lut(size=args.size, smith=smith, samples=args.samples, use_shipped=False, progress=None if args.quiet else Progress("lut")))
    seconds = time.perf_counter() - t0
    asset = lut_asset(lut, smith=smith, samples=args.samples, seconds=seconds, measure_error=not args.no_error, full_check=args.full_check)
    side = write_asset(out, asset, outputs=outs)
    write_json(out.with_name(out.name + ".json"), side, outputs=outs)
    if not args.quiet:
        print(_said_lut(out, side))
    return side


def _sheen_lut(args, outs: OutputSet, out: Path) -> dict:
    """`jaxpbr lut --sheen`: the sheen albedo table (jaxpbr.shading.sheen_lut), as `_lut` writes the LUT."""
    from ..shading.sheen_lut import sheen_lut_error
    from ..shading.shipped_luts import sheen_lut

    t0 = time.perf_counter()
    lut = np.asarray(sheen_lut(size=args.size, samples=args.samples, use_shipped=False, progress=None if args.quiet else Progress("lut")))
    seconds = time.perf_counter() - t0
    err = None if args.no_error else sheen_lut_error(lut, texels=None if args.full_check else 1024)
    meta = {
        "quantity": "sheen albedo E = int D_charlie V_charlie (n.l) dl (KHR_materials_sheen); R = E, G = B = 0",
        "layout": f"row j: r = max((j+0.5)/{lut.shape[0]}, 0.045) (row 0 at the top), column i: NoV = (i+0.5)/{lut.shape[1]}; bilinear, clamp to edge",
        "alpha": "alpha = max(r, 0.045)^2 (r perceptual sheen roughness)",
    }
    rgb = np.stack([lut, np.zeros_like(lut), np.zeros_like(lut)], -1)
    outs.add(out)
    image.write(out, rgb, metadata={f"jaxpbr:{k}": v for k, v in meta.items()} | {"jaxpbr:max_abs_error": err["max"] if err else -1.0})
    side = {"kind": "sheen_lut", "file": out.name, **meta, "size": list(lut.shape), "samples": args.samples, "seconds": seconds,
            "error_vs_float64_reference": err, "conventions": cube_conventions(), "versions": library_versions()}
    write_json(out.with_name(out.name + ".json"), side, outputs=outs)
    if not args.quiet:
        e = f"; max |error| {err['max']:.2e} over {err['texels']} texels" if err else ""
        print(f"wrote {out} ({lut.shape[0]}x{lut.shape[1]} sheen albedo, {seconds:.2f} s{e})")
    return side


def cmd_irradiance(args) -> int:
    return _run(lambda outs: _irradiance(args, outs) and 0)


def _irradiance(args, outs: OutputSet) -> dict:
    """`jaxpbr irradiance`: the map (`jaxpbr.ibl.baked.irradiance_asset`) and its sidecar."""
    out = _checked(outs, Path(args.output), (".ktx2", ".exr"))
    guard_irradiance(args.size, key="size", names=_FLAGS)
    env = _load(args, "irradiance")
    bars = _bars(args.quiet)
    t0 = time.perf_counter()
    irr = irradiance(env, size=args.size, method=args.method, progress=_bar(bars, "irradiance"))
    np.asarray(irr.levels[0])
    seconds = time.perf_counter() - t0
    asset = irradiance_asset(env, irr, method=args.method, seconds=seconds, measure_error=not args.no_error, progress=bars)
    side = write_asset(out, asset, ktx_format=args.ktx_format, outputs=outs, names=_FLAGS)
    write_json(out.with_name(out.name + ".json"), side, outputs=outs)
    if not args.quiet:
        print(_said_irradiance(out, side))
    return side


def cmd_prefilter(args) -> int:
    return _run(lambda outs: _prefilter(args, outs) and 0)


def _prefilter(args, outs: OutputSet) -> dict:
    """`jaxpbr prefilter`: the GGX chain (`jaxpbr.ibl.baked.prefiltered_asset`) and its sidecar."""
    out = _checked(outs, Path(args.output), (".ktx2", ".exr"))
    if args.exact_texels is not None and args.exact_texels < 0:
        raise InputError(f"--exact-texels must be >= 0, got {args.exact_texels}")
    _check_prefilter_size(args, args.face_size)
    env = _load(args, "prefilter")
    _prefilter_checks(args, env, out)
    bars = _bars(args.quiet)
    t0 = time.perf_counter()
    pre = prefilter(env, size=args.size, num_levels=args.levels, mapping=args.mapping, lod_blend=args.lod_blend, method=args.method,
                    samples=args.samples, exact_texels=args.exact_texels, progress=_bar(bars, "prefilter"))
    [np.asarray(lv) for lv in pre.levels]
    seconds = time.perf_counter() - t0
    asset = prefiltered_asset(env, pre, method=args.method, seconds=seconds, measure_error=not args.no_error, progress=bars)
    side = write_asset(out, asset, ktx_format=args.ktx_format, outputs=outs, names=_FLAGS)
    write_json(out.with_name(out.name + ".json"), side, outputs=outs)
    if not args.quiet:
        print(_said_prefiltered(out, side, args.method))
    return side


def cmd_ibl(args) -> int:
    """`jaxpbr ibl`: `jaxpbr.ibl.baked.write_baked` with the flags, progress bars and one line per file."""

    def go(outs):
        d = Path(args.out_dir)
        index = write_baked(
            args.env, d, face_size=args.face_size, clamp_negative=args.clamp_negative, size=args.size, levels=args.levels,
            mapping=args.mapping, lod_blend=args.lod_blend, method=args.method, samples=args.samples,
            exact_texels=args.exact_texels, irradiance_size=args.irradiance_size, irradiance_method=args.irradiance_method,
            lut_size=args.lut_size, smith=_smith(args), sheen=not args.no_sheen, charlie_size=args.charlie_size,
            charlie_levels=args.charlie_levels, extract=args.extract_lights, radiance=args.radiance, ktx_format=args.ktx_format,
            measure_error=not args.no_error, progress=_bars(args.quiet), outputs=outs, names=_FLAGS,
        )
        if not args.quiet:
            if args.extract_lights:
                found = json.loads((d / "lights.json").read_text())["lights"]
                said = ", ".join(f"radius {x['angular_radius_deg']:.2f} deg, {100 * x['power_share']:.1f} % of the power" for x in found)
                print(f"extracted {len(found)} disc light(s)" + (f": {said}" if said else " (no dominant source)"), file=sys.stderr)
            print(_said_irradiance(d / "irradiance.ktx2", index["irradiance"]))
            print(_said_prefiltered(d / "prefiltered.ktx2", index["prefiltered"], args.method))
            if "charlie" in index:
                print(_said_charlie(d / "charlie.ktx2", index["charlie"]))
            print(_said_lut(d / "brdf_lut.exr", index["brdf_lut"]))
        return 0

    return _run(go)
