"""`jaxpbr lut | irradiance | prefilter | ibl`: the IBL asset generator commands.

Every output gets a JSON sidecar (`<output>.json`) with the conventions, parameters, library
versions, run time and the measured error against the float64 reference. Inputs are validated
before any work starts; outputs are written atomically, and a command that fails removes the
files it already wrote, so there are never partial results.

`jaxpbr ibl` bakes the whole set into one folder: irradiance.ktx2, prefiltered.ktx2 (GGX),
charlie.ktx2 (the Charlie-prefiltered cube of KHR_materials_sheen's IBL term, `--no-sheen` leaves
it out), brdf_lut.exr (R = A, G = B: the GGX split sum; B = E_sheen, the Charlie sheen albedo, 0
with `--no-sheen`), optionally lights.json, and the index ibl.json (every output's sidecar plus
how an engine looks each one up).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from .._memory import check_samples, lut_bytes, prefilter_bytes, require
from ..conventions import cube_conventions, library_versions
from ..errors import Float16RangeError, InputError
from ..ibl.cubeio import ENVIRONMENT_HELP, load_environment, write_cubemap
from ..ibl.cubemap import mip_count, texel_directions
from ..ibl.diffuse import irradiance, sh9_project
from ..ibl.extract import extract_lights, lights_to_json
from ..ibl.measure import (
    brightest_direction,
    relative_error,
    irradiance_error,
    lut_error,
    prefilter_error,
    summarize,
    texel_subset,
)
from ..ibl.sheen_prefilter import (
    DEFAULT_CHARLIE_LEVELS,
    DEFAULT_CHARLIE_SIZE,
    charlie_level_roughness,
    charlie_reference,
    prefilter_charlie,
)
from ..ibl.specular import (
    DEFAULT_CHAIN_FLOOR,
    DEFAULT_EXACT_TEXELS,
    DEFAULT_LOD_BLEND,
    DEFAULT_SAMPLES,
    LOD_BLENDS,
    MAPPINGS,
    MIN_CHAIN_LEVELS,
    default_num_levels,
    default_sample_counts,
    prefilter,
)
from ..io import image
from ..io.atomic import OutputSet, write_json
from ..shading.lut import DEFAULT_SAMPLES as LUT_DEFAULT_SAMPLES
from ..shading.lut import SMITH_ALIASES, SMITH_VARIANTS, lut_shape
from ..shading.shipped_luts import brdf_lut
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
    p.add_argument("--out-dir", default=".", help="directory for irradiance.ktx2, prefiltered.ktx2, charlie.ktx2, brdf_lut.exr and ibl.json (default: current)")
    p.add_argument("--no-sheen", action="store_true", help="leave the sheen assets out (for engines without KHR_materials_sheen): no charlie.ktx2, and the LUT's B channel stays 0")
    p.add_argument("--charlie-size", type=positive_int_arg, default=None,
                   help=f"face size of the Charlie cube's level 0 (default: {DEFAULT_CHARLIE_SIZE}, or the environment's face size if smaller, as jaxpbr render)")
    p.add_argument("--charlie-levels", type=positive_int_arg, default=None,
                   help=f"levels M of the Charlie cube, sheen roughness r_m = m/(M-1) (default: {DEFAULT_CHARLIE_LEVELS}, fewer if the face size allows fewer)")
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
    p.add_argument("--exact-texels", type=int, default=None, help=f"brightest texels convolved exactly (default: {DEFAULT_EXACT_TEXELS} per 256^2 of face area, i.e. {DEFAULT_EXACT_TEXELS * 16} at 1024^2; 0 = off)")


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
    """--size must be the environment cube's face size divided by a power of two, --levels at most
    what that size holds, --samples below 2^32, and the whole within the memory (checked before
    the work, with the flags named; the library's messages name its API)."""
    _check_samples_and_levels(args, face_size)
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


def _check_samples_and_levels(args, face_size) -> None:
    check_samples("--samples", args.samples)
    if not face_size:
        return
    S = args.size or face_size
    if args.levels is not None and S <= face_size and args.levels > mip_count(S):
        raise InputError(f"--levels {args.levels}: a {S}^2 prefiltered cube has at most {mip_count(S)} levels (each halves the face); "
                         f"lower --levels (or raise --face-size)")
    if args.method == "fis" and S <= face_size:
        M = args.levels or default_num_levels(S)
        per_level = default_sample_counts(args.samples, S, M)
        require(f"a prefilter of a {face_size}^2 cube with up to {max(per_level[1:], default=0)} samples per texel",
                prefilter_bytes(face_size, S, per_level), names={"face_size": "--face-size", "samples": "--samples"})


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


#: The LUT file's channels (sidecar "channels"; the bake's B holds the sheen albedo).
LUT_CHANNELS = {"R": "A (GGX split sum, F0 weight)", "G": "B (F90 weight)", "B": "0 (unused)"}
SHEEN_CHANNEL = "E_sheen: Charlie sheen albedo / sheen IBL weight"


def _lut(args, outs: OutputSet, out_path: Path | None = None, sheen: dict | None = None) -> dict:
    """The split-sum LUT file; with `sheen` (from `_sheen_table`: the bake), its B channel holds the
    sheen albedo table and the sidecar records where that table came from."""
    out = _checked(outs, Path(out_path or args.output), (".exr",))
    n_r, n_nov = lut_shape(args.size)
    samples = args.samples or LUT_DEFAULT_SAMPLES
    check_samples("--samples", samples)
    flag = "--lut-size" if out_path is not None else "--size"
    require(f"a LUT of {n_r}x{n_nov} texels" + (f" with {samples} samples per texel" if args.samples else ""),
            lut_bytes(n_r, n_nov, samples), names={"size": flag, "samples": "--samples"})
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
    channels = dict(LUT_CHANNELS)
    third = np.zeros(lut.shape[:2], lut.dtype)
    if sheen is not None:
        table = np.asarray(sheen["table"], np.float32)
        if table.shape != lut.shape[:2]:  # both follow --lut-size; a mismatch is a bug
            raise RuntimeError(f"sheen table {table.shape} does not match the LUT {lut.shape[:2]}")
        third = table.astype(lut.dtype)
        channels["B"] = SHEEN_CHANNEL
        meta["quantity"] = ("split-sum BRDF LUT: int f_spec (n.l) dl = F0*A + F90*B; R = A, G = B; "
                            "B = E_sheen = int D_charlie V_charlie (n.l) dl (KHR_materials_sheen albedo scaling and sheen IBL weight)")
        meta["sheen_alpha"] = "B: alpha = max(r, 0.045)^2 (r perceptual sheen roughness; rows below r = 0.045 hold E at 0.045)"
    rgb = np.concatenate([lut, third[..., None]], -1)
    outs.add(out)  # registered before the write (see cubeio.write_cubemap)
    header = {f"jaxpbr:{k}": v for k, v in meta.items()} | {"jaxpbr:channels": "; ".join(f"{c} = {v}" for c, v in channels.items())}
    image.write(out, rgb, metadata=header | {"jaxpbr:max_abs_error": err["max"] if err else -1.0})
    side = {
        "kind": "brdf_lut",
        "file": out.name,
        **meta,
        "channels": channels,
        **({"sheen_albedo": {k: v for k, v in sheen.items() if k != "table"}} if sheen is not None else {}),
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
    """`jaxpbr lut --sheen`: the sheen albedo table (jaxpbr.shading.sheen_lut), as `_lut` writes the LUT."""
    from ..shading.sheen_lut import sheen_lut_error
    from ..shading.shipped_luts import sheen_lut

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
    _finish_cube(out, side, outs, rows, args, f"{pre.face_size}^2, {pre.num_levels} mips, {args.method}, {seconds:.2f} s")
    return side


def _sheen_table(args) -> dict:
    """The sheen albedo table E for the LUT's B channel (size --lut-size) and its provenance: the
    shipped file with its MANIFEST error when one matches, otherwise computed (and its error
    measured against the float64 reference unless --no-error)."""
    from ..shading.sheen_lut import DEFAULT_SAMPLES, sheen_lut_error
    from ..shading.shipped_luts import sheen_lut, shipped_manifest

    n_r, n_nov = lut_shape(args.lut_size)
    entry = next((e for e in shipped_manifest().get("sheen_luts", []) if e["size"] == [n_r, n_nov] and e["samples"] == DEFAULT_SAMPLES), None)
    t0 = time.perf_counter()
    table = np.asarray(sheen_lut(args.lut_size, progress=None if entry else Progress("sheen lut", args.quiet)), np.float32)
    info = {
        "channel": "B",
        "quantity": "E_sheen(NoV, r) = int D_charlie V_charlie (n.l) dl (KHR_materials_sheen): the albedo scaling "
                    "1 - max3(sheen_color) E_sheen and the sheen IBL weight sheen_color LD_charlie E_sheen",
        "layout": f"as R, G: row j: r = (j+0.5)/{n_r}, column i: NoV = (i+0.5)/{n_nov}; rows below r = 0.045 hold E at 0.045",
        "samples": DEFAULT_SAMPLES,
        "seconds": time.perf_counter() - t0,
    }
    if entry is not None:
        info |= {"source": "shipped", "shipped_file": f"jaxpbr/_luts/{entry['file']}",
                 **{k: entry[k] for k in ("max_abs_error", "mean_abs_error", "error_texels", "error_reference", "generated_by") if k in entry}}
    else:
        err = None if args.no_error else sheen_lut_error(table, texels=1024)
        info |= {"source": "computed (jaxpbr.shading.sheen_lut.compute_sheen_lut)", "error_vs_float64_reference": err}
    return info | {"table": table}


def _charlie_geometry(args, env) -> tuple[int, int]:
    """(size, levels) of the Charlie cube: --charlie-size / --charlie-levels or the defaults (the
    renderer's: DEFAULT_CHARLIE_SIZE, no larger than the environment), refused with the flags
    named before any work."""
    S = args.charlie_size or min(DEFAULT_CHARLIE_SIZE, env.face_size)
    most = mip_count(S)
    M = args.charlie_levels or min(DEFAULT_CHARLIE_LEVELS, most)
    if M > most:
        raise InputError(f"--charlie-levels {M}: a {S}^2 Charlie cube has at most {most} levels (each halves the face); "
                         f"lower --charlie-levels or raise --charlie-size")
    return S, M


#: Texels per level of the Charlie cube's error check, and on level 0: its float64 reference sums
#: every environment texel in 8x8 sub-texels there (the ring is 0.23 deg wide), 64x the cost of
#: the other levels (measured on the 256^2 sky, 2-core CPU: 36 texels of level 0 took 23 s, the
#: four other levels 4.5 s together).
CHARLIE_ERROR_TEXELS = 32
CHARLIE_ERROR_TEXELS_LEVEL0 = 8


def _charlie_error(env, ch, *, texels_per_level: int = CHARLIE_ERROR_TEXELS, texels_level0: int = CHARLIE_ERROR_TEXELS_LEVEL0,
                   progress=None) -> list[dict]:
    """Per level (level 0 included: it is filtered at the roughness floor, not the source): mean
    and max relative error of the Charlie cube against `charlie_reference` (float64, every texel
    of the environment's level 0) at a seeded texel subset that includes the texels nearest the
    brightest source direction."""
    rough = charlie_level_roughness(ch.num_levels)
    sun = brightest_direction(env)
    rows = []
    for m in range(ch.num_levels):
        Sm = ch.levels[m].shape[1]
        sel = texel_subset(Sm, count=texels_level0 if m == 0 else texels_per_level, toward=sun, seed=m)
        d = texel_directions(Sm).reshape(-1, 3)[sel]
        ref = charlie_reference(env, d, float(rough[m]))
        e = relative_error(np.asarray(ch.levels[m], np.float64).reshape(-1, ch.channels)[sel], ref)
        rows.append({"level": m, "roughness": float(rough[m]), "face_size": Sm, "texels": len(sel), "mean": float(e.mean()), "max": float(e.max())})
        if progress is not None:
            progress(m + 1, ch.num_levels)
    return rows


def _charlie(args, outs: OutputSet, env, out: Path, size: int, levels: int) -> dict:
    """The Charlie-prefiltered cube (`jaxpbr.ibl.sheen_prefilter.prefilter_charlie`) and its sidecar,
    written like the GGX cube (same container, metadata keys, rollback)."""
    out = _checked(outs, out, (".ktx2", ".exr"))
    t0 = time.perf_counter()
    ch = prefilter_charlie(env, size=size, num_levels=levels)
    [np.asarray(lv) for lv in ch.levels]
    seconds = time.perf_counter() - t0
    rows = None if args.no_error else _charlie_error(env, ch, progress=Progress("charlie error check (float64 reference)", args.quiet))
    meta = dict(ch.metadata)
    files = _write_cube(out, ch, args, meta, outs)
    side = {
        "kind": "prefiltered_charlie",
        "files": files,
        **meta,
        "lookup": f"{meta['lod_formula']}; trilinear; sample at the normal n (the filter assumes n = v = R)",
        "face_size": ch.face_size,
        "num_levels": ch.num_levels,
        "environment_face_size": env.face_size,
        "seconds": seconds,
        "error_vs_float64_reference": {"per_level": rows, "worst": summarize(rows)} if rows else None,
        "conventions": cube_conventions(),
        "versions": library_versions(),
    }
    _finish_cube(out, side, outs, rows, args,
                 f"{ch.face_size}^2, {ch.num_levels} mips, Charlie from a {meta['source_face_size']}^2 source, {seconds:.2f} s")
    return side


def _finish_cube(out, side, outs, rows, args, what: str) -> None:
    """Write a prefiltered cube's JSON sidecar and (unless --quiet) its one-line summary."""
    write_json(out.with_name(out.name + ".json"), side, outputs=outs)
    if not args.quiet:
        e = ""
        if rows:
            w = summarize(rows)
            e = f"; error vs reference (sampled texels): worst level mean {100 * w['mean']:.2f} %, worst texel {100 * w['max']:.2f} %"
        print(f"wrote {out} ({what}{e})")


def _engine_lookup(sheen: bool) -> dict:
    """How an engine reads each output (ibl.json "lookup")."""
    d = {
        "irradiance": "diffuse = c_diff * irradiance(n) (bilinear; the map stores E/pi)",
        "prefiltered": "specular = LD(R, lod) * (F0 * A + F90 * B), R = reflect(-v, n); lod from the roughness r: prefiltered.lod_formula "
                       "(or linear interpolation of prefiltered.lod_table), trilinear",
        "brdf_lut": ("(A, B, E_sheen) = (R, G, B)" if sheen else "(A, B) = (R, G)") + " bilinear at x = NoV, y = r (the sheen "
                    "roughness for B) with texel centres at (i+0.5)/n (y = 0 at the first, top, row of the EXR), clamp to edge",
    }
    if sheen:
        d["charlie"] = ("sheen = sheen_color * LD_charlie(n, lod_c) * E_sheen; lod_c from the sheen roughness: charlie.lod_formula "
                        "(or linear interpolation of charlie.lod_table), trilinear, sampled at the normal n")
        d["sheen_layering"] = "the layer below the sheen is scaled by 1 - max3(sheen_color) * E_sheen(NoV, sheen_roughness)"
    return d


def cmd_ibl(args) -> int:
    def go(outs):
        d = Path(args.out_dir)
        if d.exists() and not d.is_dir():
            raise InputError(f"--out-dir {str(d)!r} is a file, not a folder; give a folder")
        if not d.is_dir():
            raise InputError(f"--out-dir {str(d)!r} does not exist; create it first")
        # A complete set already there is kept until the new one is complete: an interrupted
        # or failed re-bake puts the old files back (issue 13: it left a mix naming a missing file).
        outs.protect(p for stem in ("irradiance", "prefiltered", "charlie", "brdf_lut", "ibl", "lights") for p in d.glob(f"{stem}*"))
        sheen = not args.no_sheen
        if not sheen and (args.charlie_size or args.charlie_levels):
            raise InputError("--charlie-size / --charlie-levels set the Charlie cube, which --no-sheen leaves out; drop one or the other")
        # Every output checked before any work (issue 13: the LUT's was checked after the cubes).
        for name, suffixes in (("irradiance.ktx2", (".ktx2",)), ("prefiltered.ktx2", (".ktx2",))) + ((("charlie.ktx2", (".ktx2",)),) if sheen else ()) + (
                               ("brdf_lut.exr", (".exr",)), ("ibl.json", (".json",))) + ((("lights.json", (".json",)),) if args.extract_lights else ()):
            _checked(outs, d / name, suffixes)
        n_r, n_nov = lut_shape(args.lut_size)
        require(f"a LUT of {n_r}x{n_nov} texels", lut_bytes(n_r, n_nov, LUT_DEFAULT_SAMPLES), names={"size": "--lut-size"})
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
        charlie_shape = _charlie_geometry(args, env) if sheen else None
        args.output = None
        irr = _irradiance(args, outs, env=env, out_path=d / "irradiance.ktx2", size=args.irradiance_size, method=args.irradiance_method)
        pre = _prefilter(args, outs, env=env, out_path=d / "prefiltered.ktx2")
        charlie = _charlie(args, outs, env, d / "charlie.ktx2", *charlie_shape) if sheen else None
        table = _sheen_table(args) if sheen else None
        args.size, args.samples = args.lut_size, None
        lut = _lut(args, outs, out_path=d / "brdf_lut.exr", sheen=table)
        index = {"sheen": sheen, "irradiance": irr, "prefiltered": pre}
        if charlie is not None:
            index["charlie"] = charlie
        index |= {"brdf_lut": lut, "lookup": _engine_lookup(sheen)}
        if lights is not None:
            write_json(d / "lights.json", lights, outputs=outs)
            index["lights"] = {"file": "lights.json", "count": len(lights["lights"]),
                               "note": "the cubes hold the residual environment; shade these disc lights with it"}
        write_json(d / "ibl.json", index, outputs=outs)
        return 0

    return _run(go)
