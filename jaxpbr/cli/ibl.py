"""`jaxpbr lut | irradiance | prefilter | ibl`: the IBL asset generator commands.

Every output gets a JSON sidecar (`<output>.json`) with the conventions, parameters, library
versions, run time and the measured error against the float64 reference. Inputs are validated
before any work starts; outputs are written atomically, and a command that fails removes the
files it already wrote, so there are never partial results.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from .. import image
from ..atomic import OutputSet, write_json
from ..extract import extract_lights, lights_to_json
from ..conventions import cube_conventions, library_versions
from ..cubeio import ENVIRONMENT_HELP, load_environment, write_cubemap
from ..diffuse import irradiance, sh9_project
from ..errors import Float16RangeError, InputError
from ..lut import SMITH_ALIASES, SMITH_VARIANTS, _lut_shape
from ..measure import irradiance_error, lut_error, prefilter_error, summarize
from ..shipped_luts import brdf_lut
from ..specular import DEFAULT_CHAIN_FLOOR, DEFAULT_EXACT_TEXELS, DEFAULT_LOD_BLEND, DEFAULT_SAMPLES, LOD_BLENDS, MAPPINGS, MIN_CHAIN_LEVELS, prefilter
from ._common import Progress, positive_int_arg, raise_pending, require_memory

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
        p.add_argument("--face-size", type=positive_int_arg, default=None, help="face size of the environment cube (default: from the panorama, 256 for procedural)")
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
    p.add_argument("--out-dir", default=".", help="directory for irradiance.ktx2, prefiltered.ktx2, brdf_lut.exr and ibl.json (default: current)")
    p.add_argument("--extract-lights", action="store_true", help="split dominant lights (suns) out of the environment first: the cubes hold the residual and lights.json the disc lights "
                   "(jaxpbr's fields and a glTF KHR_lights_punctual list), for engines that shade the sun analytically")
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
    p.add_argument("--exact-texels", type=int, default=None, help=f"brightest texels convolved exactly (default: {DEFAULT_EXACT_TEXELS} per 256^2 of face area, i.e. 4096 at 1024^2; 0 = off)")


#: Peak memory per unit, measured on the CPU backend (`/usr/bin/time -v`, issue 13, after the
#: memory fixes) and rounded up: a prefilter of a 4096x2048 panorama ~140-165 B per source texel
#: (1024^2: 1.43 GB, 2048^2: 3.84 GB peak RSS, loading included); loading and the irradiance
#: ~50 B per source texel (2048^2: 1.63 GB); the LUT ~13 B per texel at 30000^2 (12 GB); plus
#: ~0.4 GB for the process itself.
_BASE = 0.4e9
_PER_TEXEL = {"prefilter": 200.0, "irradiance": 80.0}


def _guard_cube(kind: str, face_size) -> None:
    if face_size:
        require_memory(f"a {kind} of a {face_size}^2 cube", _BASE + _PER_TEXEL[kind] * 6 * face_size**2, "lower --face-size")


def _load(args, kind: str):
    """The environment, with the memory its processing needs checked before and after loading (the
    face size may come from the panorama)."""
    _guard_cube(kind, args.face_size)
    env = load_environment(args.env, args.face_size, clamp_negative=args.clamp_negative)
    _guard_cube(kind, env.face_size)
    return env


def _checked(outs: OutputSet, path: Path, suffixes) -> Path:
    """The output path validated before any work, and what it will replace protected: the file,
    its JSON sidecar and, for EXR cubes, its per-mip face files keep their old content until the
    command succeeds (a failure or a signal puts them back)."""
    out = outs.check(path, suffixes)
    outs.protect([out, out.with_name(out.name + ".json"), *out.parent.glob(f"{out.stem}_m*_*.exr")])
    return out


def _check_prefilter_size(args, face_size) -> None:
    """--size must be the environment cube's face size divided by a power of two (checked before
    the work, with the flags named; the library's message names its API)."""
    S = args.size
    if not face_size or S is None:
        return
    ratio = face_size // S if S <= face_size else 0
    if ratio == 0 or face_size % S or ratio & (ratio - 1):
        sizes = ", ".join(str(face_size >> i) for i in range(min(4, face_size.bit_length())))
        raise InputError(
            f"--size {S} must be the environment cube's face size ({face_size}) divided by a power of two "
            f"({sizes}, ...); choose one of those, or set --face-size to a multiple of {S} by a power of two"
        )


def _check_half_range(args, out: Path, peak: float, what: str) -> None:
    """Refuse, before the work, values that a float16 KTX2 file cannot hold."""
    if out.suffix.lower() == ".ktx2" and args.ktx_format == "rgba16f" and peak > 65504.0:
        raise InputError(
            f"{what} reaches {peak:.6g}, beyond the float16 range of --ktx-format rgba16f (65504); "
            f"use --ktx-format rgba32f, or scale the environment down"
        )


def _prefilter_checks(args, env, out: Path) -> None:
    """What a prefilter of `env` into `out` can be refused for, once the environment is loaded."""
    _check_prefilter_size(args, env.face_size)
    # Level 0 is the environment at the output size; every other level averages it.
    top = env.level_cube(0)
    if args.size and args.size < env.face_size:
        top = top.with_mips(env.face_size.bit_length() - args.size.bit_length() + 1)
    _check_half_range(args, out, float(np.max(np.abs(np.asarray(top.levels[-1])))), "the environment's radiance" + (" at --size" if args.size else ""))


def _write_cube(out: Path, cube, args, meta, outs: OutputSet):
    """`write_cubemap`, with a float16 range failure reported in terms of the flags."""
    try:
        return write_cubemap(out, cube, fmt=args.ktx_format, metadata=meta, outputs=outs)
    except Float16RangeError as exc:
        raise InputError(
            f"{exc.count} value(s) of {out.name} reach {exc.peak:.6g}, beyond the float16 range of "
            f"--ktx-format {exc.fmt} (65504); use --ktx-format {exc.wide}, or scale the environment down"
        ) from None


def _run(fn):
    with OutputSet() as outs:
        code = fn(outs)
        raise_pending()  # an interrupt whose exception was swallowed: roll back, do not commit
        return code


def cmd_lut(args) -> int:
    return _run(lambda outs: _lut(args, outs) and 0)


def _lut(args, outs: OutputSet, out_path: Path | None = None) -> dict:
    out = _checked(outs, Path(out_path or args.output), (".exr",))
    n_r, n_nov = _lut_shape(args.size)
    require_memory(f"a {n_r}x{n_nov} LUT", _BASE + 16.0 * n_r * n_nov, "lower --size")
    if getattr(args, "sheen", False):
        return _sheen_lut(args, outs, out)
    t0 = time.perf_counter()
    smith = SMITH_ALIASES.get(args.smith, args.smith)
    if smith != args.smith:
        print(f"jaxpbr: warning: --smith {args.smith} is deprecated; use --smith {smith}", file=sys.stderr)
    lut = np.asarray(brdf_lut(args.size, smith=smith, samples=args.samples, use_shipped=False, progress=Progress("lut", args.quiet)))
    seconds = time.perf_counter() - t0
    err = None if args.no_error else lut_error(lut, smith=smith, texels=None if getattr(args, "full_check", False) else 1024)
    meta = {
        "quantity": "split-sum BRDF LUT: int f_spec (n.l) dl = F0*A + F90*B; R = A, G = B, B = 0",
        "layout": f"row j: r = (j+0.5)/{lut.shape[0]} (row 0 at the top), column i: NoV = (i+0.5)/{lut.shape[1]}; bilinear, clamp to edge",
        "smith": smith,
        "alpha": "alpha = r^2 (r perceptual roughness)",
    }
    rgb = np.concatenate([lut, np.zeros(lut.shape[:2] + (1,), lut.dtype)], -1)
    outs.add(out)  # registered before the write (see cubeio.write_cubemap)
    image.write(out, rgb, metadata={f"jaxpbr:{k}": v for k, v in meta.items()} | {"jaxpbr:max_abs_error": err["max"] if err else -1.0})
    side = {
        "kind": "brdf_lut",
        "file": out.name,
        **meta,
        "size": list(lut.shape[:2]),
        "samples": args.samples,
        "seconds": seconds,
        "error_vs_float64_reference": err,
        "conventions": cube_conventions(),
        "versions": library_versions(),
    }
    write_json(out.with_name(out.name + ".json"), side, outputs=outs)
    if not args.quiet:
        e = f"; max |error| {err['max']:.2e} over {err['texels']} texels" if err else ""
        print(f"wrote {out} ({lut.shape[0]}x{lut.shape[1]}, smith {smith}, {seconds:.2f} s{e})")
    return side


def _sheen_lut(args, outs: OutputSet, out: Path) -> dict:
    """`jaxpbr lut --sheen`: the sheen albedo table (jaxpbr.sheen_lut), as `_lut` writes the LUT."""
    from ..sheen_lut import sheen_lut_error
    from ..shipped_luts import sheen_lut

    t0 = time.perf_counter()
    lut = np.asarray(sheen_lut(args.size, samples=args.samples, use_shipped=False, progress=Progress("lut", args.quiet)))
    seconds = time.perf_counter() - t0
    err = None if args.no_error else sheen_lut_error(lut, texels=None if getattr(args, "full_check", False) else 1024)
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


def _irradiance(args, outs: OutputSet, env=None, out_path: Path | None = None, size=None, method=None) -> dict:

    out = _checked(outs, Path(out_path or args.output), (".ktx2", ".exr"))
    size = size or args.size
    require_memory(f"a {size}^2 irradiance map", _BASE + 50.0 * 6 * size**2, "lower --size")
    env = env if env is not None else _load(args, "irradiance")
    method = method or args.method
    t0 = time.perf_counter()
    irr = irradiance(env, size, method=method, progress=Progress("irradiance", args.quiet))
    np.asarray(irr.levels[0])
    seconds = time.perf_counter() - t0
    err = None if args.no_error else irradiance_error(env, irr, progress=Progress("irradiance error check", args.quiet))
    meta = {"quantity": "Ebar = E/pi (cosine-weighted mean radiance) at texel centres", "method": method, **irr.metadata}
    files = _write_cube(out, irr, args, meta, outs)
    side = {
        "kind": "irradiance",
        "files": files,
        **meta,
        "face_size": size,
        "environment_face_size": env.face_size,
        "seconds": seconds,
        "error_vs_float64_exact_full_resolution": err,
        "conventions": cube_conventions(),
        "versions": library_versions(),
    }
    if method == "sh9":
        side["sh9_radiance_coefficients"] = {
            "convention": "R&H 2001 real SH, no Condon-Shortley sign; L_lm = sum L Y_lm Omega (radiance); "
            "E/pi = max(0, sum A_l L_lm Y_lm(n))/pi with A = (pi, 2pi/3, pi/4); order (0,0),(1,-1),(1,0),(1,1),(2,-2),(2,-1),(2,0),(2,1),(2,2)",
            "values": np.asarray(sh9_project(env)).tolist(),
        }
    write_json(out.with_name(out.name + ".json"), side, outputs=outs)
    if not args.quiet:
        e = f"; error vs exact: mean {100 * err['mean']:.3f} %, max {100 * err['max']:.3f} %" if err else ""
        print(f"wrote {out} ({size}^2 irradiance, {method}, {seconds:.2f} s{e})")
    return side


def cmd_prefilter(args) -> int:
    return _run(lambda outs: _prefilter(args, outs) and 0)


def _prefilter(args, outs: OutputSet, env=None, out_path: Path | None = None) -> dict:
    out = _checked(outs, Path(out_path or args.output), (".ktx2", ".exr"))
    if args.exact_texels is not None and args.exact_texels < 0:
        raise InputError(f"--exact-texels must be >= 0, got {args.exact_texels}")
    _check_prefilter_size(args, args.face_size)
    env = env if env is not None else _load(args, "prefilter")
    _prefilter_checks(args, env, out)
    t0 = time.perf_counter()
    pre = prefilter(
        env,
        args.size,
        num_levels=args.levels,
        mapping=args.mapping,
        lod_blend=args.lod_blend,
        method=args.method,
        samples=args.samples,
        exact_texels=args.exact_texels,
        progress=Progress("prefilter", args.quiet),
    )
    [np.asarray(lv) for lv in pre.levels]
    seconds = time.perf_counter() - t0
    check = Progress("prefilter error check (float64 reference)", args.quiet)
    rows = None if args.no_error or args.method == "reference" else prefilter_error(env, pre, progress=check)
    meta = dict(pre.metadata)
    files = _write_cube(out, pre, args, meta, outs)
    side = {
        "kind": "prefiltered_specular",
        "files": files,
        **meta,
        "lookup": f"{meta['lod_formula']}; trilinear",
        "face_size": pre.face_size,
        "num_levels": pre.num_levels,
        "seconds": seconds,
        "error_vs_float64_reference": {"per_level": rows, "worst": summarize(rows)} if rows else None,
        "conventions": cube_conventions(),
        "versions": library_versions(),
    }
    write_json(out.with_name(out.name + ".json"), side, outputs=outs)
    if not args.quiet:
        e = ""
        if rows:
            w = summarize(rows)
            e = f"; error vs reference (sampled texels): worst level mean {100 * w['mean']:.2f} %, worst texel {100 * w['max']:.2f} %"
        print(f"wrote {out} ({pre.face_size}^2, {pre.num_levels} mips, {args.method}, {seconds:.2f} s{e})")
    return side


def cmd_ibl(args) -> int:
    def go(outs):
        d = Path(args.out_dir)
        if d.exists() and not d.is_dir():
            raise InputError(f"--out-dir {str(d)!r} is a file, not a folder; give a folder")
        if not d.is_dir():
            raise InputError(f"--out-dir {str(d)!r} does not exist; create it first")
        # A complete set already there is kept until the new one is complete: an interrupted
        # or failed re-bake puts the old files back (issue 13: it left a mix naming a missing file).
        outs.protect(p for stem in ("irradiance", "prefiltered", "brdf_lut", "ibl", "lights") for p in d.glob(f"{stem}*"))
        # Every output checked before any work (issue 13: the LUT's was checked after the cubes).
        for name, suffixes in (("irradiance.ktx2", (".ktx2",)), ("prefiltered.ktx2", (".ktx2",)),
                               ("brdf_lut.exr", (".exr",)), ("ibl.json", (".json",))) + ((("lights.json", (".json",)),) if args.extract_lights else ()):
            _checked(outs, d / name, suffixes)
        n_r, n_nov = _lut_shape(args.lut_size)
        require_memory(f"a {n_r}x{n_nov} LUT", _BASE + 16.0 * n_r * n_nov, "lower --lut-size")
        _check_prefilter_size(args, args.face_size)
        env = _load(args, "prefilter")
        lights = None
        if args.extract_lights:
            ex = extract_lights(env)
            env, lights = ex.residual, lights_to_json(ex)
            if not args.quiet:
                found = ", ".join(f"radius {x['angular_radius_deg']:.2f} deg, {100 * x['power_share']:.1f} % of the power" for x in ex.info["lights"])
                print(f"extracted {len(ex.lights)} disc light(s)" + (f": {found}" if found else " (no dominant source)"), file=sys.stderr)
        _prefilter_checks(args, env, d / "prefiltered.ktx2")
        args.output = None
        irr = _irradiance(args, outs, env=env, out_path=d / "irradiance.ktx2", size=args.irradiance_size, method=args.irradiance_method)
        pre = _prefilter(args, outs, env=env, out_path=d / "prefiltered.ktx2")
        args.size, args.samples = args.lut_size, None
        lut = _lut(args, outs, out_path=d / "brdf_lut.exr")
        index = {"irradiance": irr, "prefiltered": pre, "brdf_lut": lut}
        if lights is not None:
            write_json(d / "lights.json", lights, outputs=outs)
            index["lights"] = {"file": "lights.json", "count": len(lights["lights"]),
                               "note": "the cubes hold the residual environment; shade these disc lights with it"}
        write_json(d / "ibl.json", index, outputs=outs)
        return 0

    return _run(go)
