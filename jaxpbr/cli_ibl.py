"""`jaxpbr lut | irradiance | prefilter | ibl`: the IBL asset generator commands.

Every output gets a JSON sidecar (`<output>.json`) with the conventions, parameters, library
versions, run time and the measured error against the float64 reference. Inputs are validated
before any work starts; outputs are written atomically, and a command that fails removes the
files it already wrote, so there are never partial results.
"""

from __future__ import annotations

import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["add_commands", "load_environment", "ENV_HELP"]

ENV_HELP = (
    "environment: one equirect panorama (.hdr/.exr, width = 2 x height), six square face images "
    "in the order +X -X +Y -Y +Z -Z, or 'procedural:sky' (a clear sky with a 3000-radiance sun, "
    "generated in code)"
)
_FACE_FILE_NAMES = ("px", "nx", "py", "ny", "pz", "nz")


class _Progress:
    """A one-line progress indicator on stderr (silent with --quiet)."""

    def __init__(self, label: str, quiet: bool):
        self.label, self.quiet, self.t0 = label, quiet, time.perf_counter()

    def __call__(self, done: int, total: int) -> None:
        if self.quiet:
            return
        width = 24
        fill = int(width * done / max(total, 1))
        end = "\n" if done >= total else ""
        print(
            f"\r{self.label}: [{'#' * fill}{'.' * (width - fill)}] {done}/{total}  {time.perf_counter() - self.t0:.1f} s",
            end=end,
            file=sys.stderr,
            flush=True,
        )


# ------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------


def load_environment(paths: list[str], face_size: int | None, *, clamp_negative: bool = False):
    """Read an environment given on the command line -> float32 Cubemap (level 0 only)."""
    from . import envs, image
    from .cubemap import Cubemap
    from .errors import InputError

    if len(paths) == 1 and paths[0].startswith("procedural:"):
        name = paths[0].split(":", 1)[1]
        if name != "sky":
            raise InputError(f"unknown procedural environment {name!r}; the one available is 'procedural:sky'")
        return envs.sky_with_sun_cubemap(face_size or 256)
    if len(paths) not in (1, 6):
        raise InputError(
            f"expected one equirect panorama or six face images (+X -X +Y -Y +Z -Z), got {len(paths)} paths"
        )
    imgs = []
    for p in paths:
        path = Path(p)
        if not path.exists():
            raise InputError(f"environment file {p!r} does not exist")
        if path.suffix.lower() not in (".hdr", ".exr"):
            raise InputError(f"environment file {p!r} must be a linear HDR image (.hdr or .exr)")
        try:
            img = image.read(path)
        except Exception as e:  # unreadable / corrupt
            raise InputError(f"cannot read environment file {p!r}: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from e
        img = np.asarray(img, np.float32)
        if img.ndim == 2:
            img = img[..., None]
        if img.shape[-1] == 4:
            img = img[..., :3]
        bad = ~np.isfinite(img)
        if bad.any():
            raise InputError(f"{p!r} has {int(bad.any(-1).sum())} pixels with NaN/Inf values; fix the image first")
        neg = img < 0
        if neg.any():
            if not clamp_negative:
                raise InputError(
                    f"{p!r} has {int(neg.any(-1).sum())} pixels with negative radiance; "
                    "pass --clamp-negative to set them to 0"
                )
            print(f"jaxpbr: warning: clamped {int(neg.any(-1).sum())} negative pixels of {p!r} to 0", file=sys.stderr)
            img = np.maximum(img, 0.0)
        imgs.append(img)
    if len(imgs) == 1:
        img = imgs[0]
        H, W = img.shape[:2]
        if W != 2 * H:
            raise InputError(
                f"{paths[0]!r} is {W}x{H}; an equirect panorama must be exactly twice as wide as high "
                "(or give six square face images)"
            )
        S = face_size or _default_face_size(H)
        return Cubemap.from_equirect(img, S)
    shapes = {im.shape for im in imgs}
    if len(shapes) != 1 or imgs[0].shape[0] != imgs[0].shape[1]:
        raise InputError(f"the six face images must be square and the same size, got {[im.shape[:2] for im in imgs]}")
    cube = Cubemap(np.stack(imgs))
    if face_size and face_size != cube.face_size:
        from .cubemap import downsample

        lv = cube.levels[0]
        while lv.shape[1] > face_size and lv.shape[1] % 2 == 0:
            lv = downsample(lv)
        if lv.shape[1] != face_size:
            raise InputError(f"--face-size {face_size} must be the faces' size {cube.face_size} divided by a power of two")
        cube = Cubemap(lv)
    return cube


def _default_face_size(height: int) -> int:
    """Power of two nearest to the panorama's texel density (a face spans a quarter of the width)."""
    return int(min(2048, max(16, 2 ** round(math.log2(max(height / 2, 1))))))


# ------------------------------------------------------------------------------------------
# outputs
# ------------------------------------------------------------------------------------------


class _Outputs:
    """Collects written files; removes all of them if the command fails."""

    def __init__(self):
        self.written: list[Path] = []

    def check(self, path: Path, suffixes: tuple[str, ...]) -> Path:
        from .errors import InputError

        path = Path(path)
        if path.suffix.lower() not in suffixes:
            raise InputError(f"output {str(path)!r} must end in one of {', '.join(suffixes)}")
        parent = path.resolve().parent
        if not parent.is_dir():
            raise InputError(f"output directory {str(parent)!r} does not exist; create it first")
        if path.is_dir():
            raise InputError(f"output {str(path)!r} is a directory")
        import os

        if not os.access(parent, os.W_OK):
            raise InputError(f"output directory {str(parent)!r} is not writable")
        return path

    def add(self, path: Path) -> None:
        self.written.append(Path(path))

    def rollback(self) -> None:
        for p in self.written:
            try:
                p.unlink()
            except FileNotFoundError:
                pass


def _versions() -> dict:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for pkg in ("jaxpbr", "jax", "jaxlib", "numpy", "OpenEXR", "colour-science", "OpenImageIO"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    return out


def _cube_conventions() -> dict:
    from .conventions import CONVENTIONS

    return {**CONVENTIONS, "ktx2_layout": "KTX2 face f = levels[m][f]; file rows i, columns j; no flip"}


def _write_json(path: Path, data: dict, outs: _Outputs) -> None:
    from .image import _atomic_write

    text = json.dumps(data, indent=2, sort_keys=False) + "\n"

    def writer(tmp):
        with open(tmp, "w") as f:
            f.write(text)

    _atomic_write(path, writer)
    outs.add(path)


def _write_cube(path: Path, cube, fmt: str, metadata: dict, outs: _Outputs) -> list[str]:
    """KTX2 (all mips in one file) or EXR (one file per mip and face: <stem>_m<m>_<face>.exr)."""
    from . import image
    from .ktx2 import write_ktx2

    levels = [np.asarray(lv, np.float32) for lv in cube.levels]
    flat_meta = {f"jaxpbr:{k}": (v if isinstance(v, str) else json.dumps(v)) for k, v in metadata.items()}
    if path.suffix.lower() == ".ktx2":
        write_ktx2(path, levels, fmt=fmt, metadata=flat_meta)
        outs.add(path)
        return [str(path)]
    names = []
    for m, lv in enumerate(levels):
        for f in range(6):
            p = path.with_name(f"{path.stem}_m{m}_{_FACE_FILE_NAMES[f]}.exr")
            image.write(p, lv[f], metadata={**metadata, "jaxpbr:mip": m, "jaxpbr:face": _FACE_FILE_NAMES[f]})
            outs.add(p)
            names.append(str(p))
    return names


# ------------------------------------------------------------------------------------------
# commands
# ------------------------------------------------------------------------------------------


def add_commands(sub, positive_int, bench_sub=None) -> None:
    """Register the IBL commands on the `jaxpbr` sub-parser (and `bench ibl` on `bench_sub`)."""

    def common_env(p):
        p.add_argument("env", nargs="+", metavar="ENV", help=ENV_HELP)
        p.add_argument("--face-size", type=positive_int, default=None, help="face size of the environment cube (default: from the panorama, 256 for procedural)")
        p.add_argument("--clamp-negative", action="store_true", help="set negative input pixels to 0 (with a warning) instead of failing")

    def common_out(p, default, suffixes):
        p.add_argument("-o", "--output", default=default, help=f"output file ({' or '.join(suffixes)}; default: %(default)s); a JSON sidecar is written next to it")
        p.add_argument("--ktx-format", choices=("rgba16f", "rgba32f"), default="rgba16f", help="KTX2 texel format (default: %(default)s)")
        p.add_argument("--no-error", action="store_true", help="skip measuring the error against the float64 reference")
        p.add_argument("--quiet", action="store_true", help="no progress output")

    p = sub.add_parser("lut", help="generate the split-sum BRDF LUT (EXR)", description="Converged split-sum LUT (A, B) with (n_r, n_nov) texels; the EXR's R = A, G = B, B = 0; row j at r = (j+0.5)/n_r (row 0 at the top), column i at NoV = (i+0.5)/n_nov.")
    p.add_argument("--size", type=positive_int, default=128, help="texels per side (default: %(default)s)")
    p.add_argument("--smith", choices=("correlated", "schlick"), default="correlated", help="Smith term: height-correlated (glTF/Filament) or Schlick-GGX k=alpha/2 (Karis/LearnOpenGL)")
    p.add_argument("--samples", type=positive_int, default=None, help="quadrature samples per texel (default: the library default)")
    p.add_argument("-o", "--output", default="brdf_lut.exr", help="output .exr (default: %(default)s)")
    p.add_argument("--full-check", action="store_true", help="measure the error at every texel (slower) instead of the edges + 1024 random texels")
    p.add_argument("--no-error", action="store_true", help="skip measuring the error")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_lut)

    p = sub.add_parser("irradiance", help="diffuse irradiance cube (E/pi) from an environment")
    common_env(p)
    p.add_argument("--size", type=positive_int, default=32, help="output face size (default: %(default)s)")
    p.add_argument("--method", choices=("exact", "sh9"), default="exact", help="exact cosine convolution or SH9 (default: %(default)s)")
    common_out(p, "irradiance.ktx2", (".ktx2", ".exr"))
    p.set_defaults(func=cmd_irradiance)

    p = sub.add_parser("prefilter", help="GGX-prefiltered specular cube with all mips")
    common_env(p)
    _prefilter_args(p, positive_int)
    common_out(p, "prefiltered.ktx2", (".ktx2", ".exr"))
    p.set_defaults(func=cmd_prefilter)

    p = sub.add_parser("ibl", help="irradiance + prefiltered cube + BRDF LUT in one go")
    common_env(p)
    _prefilter_args(p, positive_int)
    p.add_argument("--irradiance-size", type=positive_int, default=32)
    p.add_argument("--irradiance-method", choices=("exact", "sh9"), default="exact")
    p.add_argument("--lut-size", type=positive_int, default=128)
    p.add_argument("--smith", choices=("correlated", "schlick"), default="correlated")
    p.add_argument("--out-dir", default=".", help="directory for irradiance.ktx2, prefiltered.ktx2, brdf_lut.exr and ibl.json (default: current)")
    p.add_argument("--ktx-format", choices=("rgba16f", "rgba32f"), default="rgba16f")
    p.add_argument("--no-error", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_ibl)

    rp = sub.add_parser("report", help="error-vs-run-time reports")
    rsub = rp.add_subparsers(dest="report", metavar="REPORT")
    p = rsub.add_parser("precompute", help="LUT / irradiance / prefilter error vs run time (Markdown table + PNG plot)")
    p.add_argument("env", nargs="*", metavar="HDR", help="extra equirect panoramas to measure on (the procedural sky+sun is always included)")
    p.add_argument("--out", default="precompute_report", help="output prefix: <out>.md and <out>.png (default: %(default)s)")
    p.add_argument("--face-size", type=positive_int, default=256, help="environment face size (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="a smaller sweep (for a first look)")
    p.set_defaults(func=cmd_report_precompute)
    rp.set_defaults(func=lambda args: rp.print_help() or 0)
    from .report_render import add_report_render_command

    add_report_render_command(rsub)

    if bench_sub is not None:
        p = bench_sub.add_parser("ibl", help="IBL precompute timings and errors vs a Filament-style FIS baseline, side by side")
        p.add_argument("--env", default=None, help="equirect panorama (default: the procedural sky+sun)")
        p.add_argument("--face-size", type=positive_int, default=256)
        p.add_argument("--baseline-samples", type=positive_int, default=4096, help="samples of the plain-FIS baseline (default: %(default)s)")
        p.set_defaults(func=cmd_bench_ibl)


def _prefilter_args(p, positive_int):
    from .specular import DEFAULT_EXACT_TEXELS, DEFAULT_SAMPLES

    p.add_argument("--size", type=positive_int, default=None, help="face size of mip 0 (default: the environment's)")
    p.add_argument("--levels", type=positive_int, default=None, help="number of mips M (default: down to 1x1)")
    p.add_argument("--mapping", choices=("linear", "quadratic"), default="linear", help="roughness->mip: r_m = m/(M-1) or Filament's (default: %(default)s)")
    p.add_argument("--method", choices=("fis", "reference"), default="fis", help="filtered importance sampling or the float64 brute-force reference (slow)")
    p.add_argument("--samples", type=positive_int, default=DEFAULT_SAMPLES, help="FIS samples on the large levels (default: %(default)s; small levels get more)")
    p.add_argument("--exact-texels", type=int, default=DEFAULT_EXACT_TEXELS, help="brightest texels convolved exactly (default: %(default)s; 0 = off)")


def _run(fn):
    outs = _Outputs()
    try:
        return fn(outs)
    except BaseException:
        outs.rollback()
        raise


def cmd_lut(args) -> int:
    return _run(lambda outs: _lut(args, outs) and 0)


def _lut(args, outs: _Outputs, out_path: Path | None = None) -> dict:
    from . import image
    from .shipped_luts import brdf_lut
    from .measure import lut_error

    out = outs.check(Path(out_path or args.output), (".exr",))
    t0 = time.perf_counter()
    lut = np.asarray(brdf_lut(args.size, smith=args.smith, samples=args.samples, use_shipped=False))
    seconds = time.perf_counter() - t0
    err = None if args.no_error else lut_error(lut, args.smith, texels=None if getattr(args, "full_check", False) else 1024)
    meta = {
        "quantity": "split-sum BRDF LUT: int f_spec (n.l) dl = F0*A + F90*B; R = A, G = B, B = 0",
        "layout": f"row j: r = (j+0.5)/{lut.shape[0]} (row 0 at the top), column i: NoV = (i+0.5)/{lut.shape[1]}; bilinear, clamp to edge",
        "smith": args.smith,
        "alpha": "alpha = r^2 (r perceptual roughness)",
    }
    rgb = np.concatenate([lut, np.zeros(lut.shape[:2] + (1,), lut.dtype)], -1)
    image.write(out, rgb, metadata={f"jaxpbr:{k}": v for k, v in meta.items()} | {"jaxpbr:max_abs_error": err["max"] if err else -1.0})
    outs.add(out)
    side = {
        "kind": "brdf_lut",
        "file": out.name,
        **meta,
        "size": list(lut.shape[:2]),
        "samples": args.samples,
        "seconds": seconds,
        "error_vs_float64_reference": err,
        "conventions": _cube_conventions(),
        "versions": _versions(),
    }
    _write_json(out.with_name(out.name + ".json"), side, outs)
    if not args.quiet:
        e = f"; max |error| {err['max']:.2e} over {err['texels']} texels" if err else ""
        print(f"wrote {out} ({lut.shape[0]}x{lut.shape[1]}, smith {args.smith}, {seconds:.2f} s{e})")
    return side


def cmd_irradiance(args) -> int:
    return _run(lambda outs: _irradiance(args, outs) and 0)


def _irradiance(args, outs: _Outputs, env=None, out_path: Path | None = None, size=None, method=None) -> dict:
    from .diffuse import irradiance, sh9_project
    from .measure import irradiance_error

    out = outs.check(Path(out_path or args.output), (".ktx2", ".exr"))
    env = env if env is not None else load_environment(args.env, args.face_size, clamp_negative=args.clamp_negative)
    size = size or args.size
    method = method or args.method
    t0 = time.perf_counter()
    irr = irradiance(env, size, method=method)
    np.asarray(irr.levels[0])
    seconds = time.perf_counter() - t0
    err = None if args.no_error else irradiance_error(env, irr)
    meta = {"quantity": "Ebar = E/pi (cosine-weighted mean radiance) at texel centres", "method": method, **irr.metadata}
    files = _write_cube(out, irr, args.ktx_format, meta, outs)
    side = {
        "kind": "irradiance",
        "files": files,
        **meta,
        "face_size": size,
        "environment_face_size": env.face_size,
        "seconds": seconds,
        "error_vs_float64_exact_full_resolution": err,
        "conventions": _cube_conventions(),
        "versions": _versions(),
    }
    if method == "sh9":
        side["sh9_radiance_coefficients"] = {
            "convention": "R&H 2001 real SH, no Condon-Shortley sign; L_lm = sum L Y_lm Omega (radiance); "
            "E/pi = max(0, sum A_l L_lm Y_lm(n))/pi with A = (pi, 2pi/3, pi/4); order (0,0),(1,-1),(1,0),(1,1),(2,-2),(2,-1),(2,0),(2,1),(2,2)",
            "values": np.asarray(sh9_project(env)).tolist(),
        }
    _write_json(out.with_name(out.name + ".json"), side, outs)
    if not args.quiet:
        e = f"; error vs exact: mean {100 * err['mean']:.3f} %, max {100 * err['max']:.3f} %" if err else ""
        print(f"wrote {out} ({size}^2 irradiance, {method}, {seconds:.2f} s{e})")
    return side


def cmd_prefilter(args) -> int:
    return _run(lambda outs: _prefilter(args, outs) and 0)


def _prefilter(args, outs: _Outputs, env=None, out_path: Path | None = None) -> dict:
    from .measure import prefilter_error, summarize
    from .specular import prefilter

    out = outs.check(Path(out_path or args.output), (".ktx2", ".exr"))
    if args.exact_texels < 0:
        from .errors import InputError

        raise InputError(f"--exact-texels must be >= 0, got {args.exact_texels}")
    env = env if env is not None else load_environment(args.env, args.face_size, clamp_negative=args.clamp_negative)
    t0 = time.perf_counter()
    pre = prefilter(
        env,
        args.size,
        num_levels=args.levels,
        mapping=args.mapping,
        method=args.method,
        samples=args.samples,
        exact_texels=args.exact_texels,
        progress=_Progress("prefilter", args.quiet),
    )
    [np.asarray(lv) for lv in pre.levels]
    seconds = time.perf_counter() - t0
    rows = None if args.no_error or args.method == "reference" else prefilter_error(env, pre)
    meta = dict(pre.metadata)
    files = _write_cube(out, pre, args.ktx_format, meta, outs)
    side = {
        "kind": "prefiltered_specular",
        "files": files,
        **meta,
        "lookup": "lod = r*(M-1) (linear) or (M-1)*r*(2-r) (quadratic); trilinear",
        "face_size": pre.face_size,
        "num_levels": pre.num_levels,
        "seconds": seconds,
        "error_vs_float64_reference": {"per_level": rows, "worst": summarize(rows)} if rows else None,
        "conventions": _cube_conventions(),
        "versions": _versions(),
    }
    _write_json(out.with_name(out.name + ".json"), side, outs)
    if not args.quiet:
        e = ""
        if rows:
            w = summarize(rows)
            e = f"; error vs reference (sampled texels): worst level mean {100 * w['mean']:.2f} %, worst texel {100 * w['max']:.2f} %"
        print(f"wrote {out} ({pre.face_size}^2, {pre.num_levels} mips, {args.method}, {seconds:.2f} s{e})")
    return side


def cmd_ibl(args) -> int:
    def go(outs):
        from .errors import InputError

        d = Path(args.out_dir)
        if not d.is_dir():
            raise InputError(f"--out-dir {str(d)!r} does not exist; create it first")
        env = load_environment(args.env, args.face_size, clamp_negative=args.clamp_negative)
        args.output = None
        irr = _irradiance(args, outs, env=env, out_path=d / "irradiance.ktx2", size=args.irradiance_size, method=args.irradiance_method)
        pre = _prefilter(args, outs, env=env, out_path=d / "prefiltered.ktx2")
        args.size, args.samples = args.lut_size, None
        lut = _lut(args, outs, out_path=d / "brdf_lut.exr")
        _write_json(d / "ibl.json", {"irradiance": irr, "prefiltered": pre, "brdf_lut": lut}, outs)
        return 0

    return _run(go)


def cmd_report_precompute(args) -> int:
    from .report import precompute_report

    for p in args.env:
        if not Path(p).exists():
            from .errors import InputError

            raise InputError(f"environment file {p!r} does not exist")
    md, _ = precompute_report(args.env, out_prefix=args.out, face_size=args.face_size, quick=args.quick, log=lambda m: print(m, file=sys.stderr))
    print(md)
    png = Path(f"{args.out}.png")
    print(f"wrote {args.out}.md" + (f" and {png}" if png.exists() else " (no plot: matplotlib is not installed)"))
    return 0


def cmd_bench_ibl(args) -> int:
    from .bench_ibl import bench_ibl

    env = load_environment([args.env] if args.env else ["procedural:sky"], args.face_size)
    print(bench_ibl(env, args.env or "procedural sky+sun", baseline_samples=args.baseline_samples))
    return 0
