"""The baked IBL set on disk: the files `jaxpbr ibl` writes, written and read from Python.

`write_baked(environment, out_dir)` computes an environment's IBL assets and writes them into one
folder: irradiance.ktx2 (E/pi), prefiltered.ktx2 (GGX, every mip), charlie.ktx2 (the Charlie cube of
KHR_materials_sheen; `sheen=False` leaves it out), brdf_lut.exr (R = A, G = B: the GGX split sum;
B = E_sheen, the sheen albedo, 0 without sheen), lights.json (with `extract=True`: the suns split
out of the environment), a JSON sidecar per file (`<file>.json`: conventions, parameters, versions,
run time, the error against the float64 reference) and the index ibl.json (every sidecar, and how
an engine looks each file up). Everything goes through one `jaxpbr.io.atomic.OutputSet`: a failure
or a signal leaves the folder as it was (files it replaces get their old content back).

`read_baked_maps(directory)` reads such a set back (`BakedMaps`: the cubes with the metadata their
lookups read, the LUT, the sheen table, the lights, the index); `jaxpbr.read_baked` builds the
baked `jaxpbr.Environment` from it. `jaxpbr.bake` computes the same maps in memory with the
renderer's defaults (prefiltered face size at most 128, suns extracted); `write_baked` has the
command line's (the environment's face size, no extraction), so the two agree when the options do.

The pieces (`irradiance_asset`, `prefiltered_asset`, `lut_asset`, `write_asset`, the checks) are
what `jaxpbr irradiance | prefilter | lut` write single files with.

Messages name the function's keywords; a front end passes `names` ({keyword: its own flag}, and
"sheen=False" for the switch that leaves the sheen out) to have its own flags named instead.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from .._memory import check_samples, lut_bytes, prefilter_bytes, require
from .._validate import check_radiance
from ..conventions import cube_conventions, library_versions
from ..errors import Float16RangeError, InputError
from ..io import image
from ..io.atomic import OutputSet, write_json
from ..io.ktx2 import FORMATS, read_ktx2
from ..shading.lights import DirectionalLight
from ..shading.lut import DEFAULT_SAMPLES as LUT_DEFAULT_SAMPLES
from ..shading.lut import lut_shape, resolve_smith
from ..shading.shipped_luts import brdf_lut
from .cubeio import FACE_FILE_NAMES, load_environment, write_cubemap
from .cubemap import Cubemap, mip_count, texel_directions
from .diffuse import irradiance, sh9_project
from .extract import extract_lights, lights_to_json
from .measure import (
    brightest_direction,
    irradiance_error,
    lut_error,
    prefilter_error,
    relative_error,
    summarize,
    texel_subset,
)
from .sheen_prefilter import (
    DEFAULT_CHARLIE_LEVELS,
    DEFAULT_CHARLIE_SIZE,
    charlie_level_roughness,
    charlie_reference,
    prefilter_charlie,
)
from .specular import (
    DEFAULT_LOD_BLEND,
    DEFAULT_SAMPLES,
    default_num_levels,
    default_sample_counts,
    prefilter,
)

__all__ = [
    "CHARLIE_ERROR_TEXELS",
    "CHARLIE_ERROR_TEXELS_LEVEL0",
    "INDEX",
    "LUT_CHANNELS",
    "SHEEN_CHANNEL",
    "STEMS",
    "Asset",
    "BakedMaps",
    "check_float16",
    "check_prefilter_options",
    "guard_irradiance",
    "irradiance_asset",
    "load_source",
    "lut_asset",
    "prefiltered_asset",
    "prepare_output",
    "read_baked_maps",
    "write_asset",
    "write_baked",
]

#: The index of a baked set.
INDEX = "ibl.json"
#: The file stems of a baked set (a re-bake protects every file starting with one of them).
STEMS = ("irradiance", "prefiltered", "charlie", "brdf_lut", "ibl", "lights", "radiance")
#: The LUT file's channels (sidecar "channels"; a baked set's B holds the sheen albedo).
LUT_CHANNELS = {"R": "A (GGX split sum, F0 weight)", "G": "B (F90 weight)", "B": "0 (unused)"}
SHEEN_CHANNEL = "E_sheen: Charlie sheen albedo / sheen IBL weight"
#: Texels per level of the Charlie cube's error check, and on level 0: its float64 reference sums
#: every environment texel in 8x8 sub-texels there (the ring is 0.23 deg wide), 64x the cost of
#: the other levels (measured on the 256^2 sky, 2-core CPU: 36 texels of level 0 took 23 s, the
#: four other levels 4.5 s together).
CHARLIE_ERROR_TEXELS = 32
CHARLIE_ERROR_TEXELS_LEVEL0 = 8

#: Peak memory per unit, measured on the CPU backend (`/usr/bin/time -v`, issue 13, after the
#: memory fixes) and rounded up: a prefilter of a 4096x2048 panorama ~140-165 B per source texel
#: (1024^2: 1.43 GB, 2048^2: 3.84 GB peak RSS, loading included); loading and the irradiance
#: ~50 B per source texel (2048^2: 1.63 GB); plus ~0.4 GB for the process itself.
_BASE = 0.4e9
_PER_TEXEL = {"prefilter": 200.0, "irradiance": 80.0}
_PER_IRRADIANCE_TEXEL = 50.0


class Asset(NamedTuple):
    """One file of a set, computed and described, not yet written (`write_asset` writes it).

    data: a `Cubemap` (written as KTX2 or per-face EXR) or the LUT's (n_r, n_nov, 3) array (EXR);
    header: the file's own metadata (a cube's key/values without the "jaxpbr:" prefix, which
    `write_cubemap` adds; the LUT's EXR header as written); sidecar: the `<file>.json` content,
    its "files" / "file" entry filled in by `write_asset`."""

    kind: str
    data: Any
    header: dict
    sidecar: dict


class BakedMaps(NamedTuple):
    """A baked set read back (`read_baked_maps`): float32 maps ready for a `jaxpbr.Environment`.

    irradiance, prefiltered, charlie (None without sheen): `Cubemap`s whose info is the file's
    metadata (the lookup keys included, so `shade_ibl` and the renderer read them as written);
    lut: (n_r, n_nov, 2) split-sum LUT for `lut_smith`; sheen_lut: (n_r, n_nov) sheen albedo
    table or None; lights: tuple of disc `DirectionalLight`s split out of the environment, or None
    (none extracted: the cubes hold the whole environment); index: ibl.json as read; radiance: the
    environment itself (level 0, before any extraction) where the set stores it (`radiance=True`),
    else None."""

    irradiance: Cubemap
    prefiltered: Cubemap
    lut: Any
    lut_smith: str
    sheen_lut: Any
    charlie: Cubemap | None
    lights: tuple | None
    index: dict
    radiance: Cubemap | None = None


# ------------------------------------------------------------------------------------------
# names in messages
# ------------------------------------------------------------------------------------------


_UNSET = object()


def _say(names, key: str, value=_UNSET) -> str:
    """How a message names the option `key` (and its value): the front end's flag from `names`
    ("--size 48"), else the keyword ("size=48")."""
    flag = (names or {}).get(key)
    if value is _UNSET:
        return flag or key
    return f"{flag} {value}" if flag else f"{key}={value!r}"


def _step(progress, step: str):
    """The (done, total) callback of one step of a `progress(step, done, total)` callback."""
    if progress is None:
        return None
    return lambda done, total: progress(step, done, total)


# ------------------------------------------------------------------------------------------
# checks before the work
# ------------------------------------------------------------------------------------------


def prepare_output(outputs: OutputSet, path, suffixes) -> Path:
    """An output path validated before any work (suffix, existing writable folder), and what it
    will replace protected: the file, its JSON sidecar and, for EXR cubes, its per-mip face files
    keep their old content until the set is complete (a failure or a signal puts them back)."""
    out = outputs.check(path, tuple(suffixes))
    outputs.protect([out, out.with_name(out.name + ".json"), *out.parent.glob(f"{out.stem}_m*_*.exr")])
    return out


def _guard_cube(kind: str, face_size, names) -> None:
    if face_size:
        require(f"a {kind} of a {face_size}^2 cube", {"face_size": _BASE + _PER_TEXEL[kind] * 6 * face_size**2},
                names={"face_size": _say(names, "face_size")})


def guard_irradiance(size: int, *, key: str = "irradiance_size", names=None) -> None:
    """Refuse, before the work, an irradiance map of `size`^2 that does not fit in memory (the
    option named as `key`)."""
    require(f"a {size}^2 irradiance map", {key: _BASE + _PER_IRRADIANCE_TEXEL * 6 * size**2}, names={key: _say(names, key)})


def load_source(environment, *, face_size=None, clamp_negative: bool = False, kind: str = "prefilter", names=None) -> Cubemap:
    """The environment to bake, level 0, with the memory its `kind` ("prefilter" | "irradiance")
    needs checked before and after loading (the face size may come from a panorama).

    environment: what `cubeio.load_environment` reads (a panorama, six face images, "procedural:sky";
    `face_size` and `clamp_negative` apply), a `Cubemap`, or a `jaxpbr.Environment` (its radiance
    times its intensity; a rotation, or maps it already carries, are refused: they would not be in
    the files)."""
    if isinstance(environment, (str, Path)) or (isinstance(environment, (list, tuple)) and environment
                                                and all(isinstance(p, (str, Path)) for p in environment)):
        _guard_cube(kind, face_size, names)
        env = load_environment(environment, face_size=face_size, clamp_negative=clamp_negative)
        _guard_cube(kind, env.face_size, names)
        return env
    cube = _radiance_of(environment)
    if face_size is not None and face_size != cube.face_size:
        raise InputError(f"{_say(names, 'face_size', face_size)} applies to environment files; this cube's faces are "
                         f"{cube.face_size}^2 (pass {_say(names, 'size')} for a smaller prefiltered map, or resample the cube)")
    _guard_cube(kind, cube.face_size, names)
    return check_radiance("the environment to bake", cube.level_cube(0))


def _radiance_of(environment) -> Cubemap:
    if isinstance(environment, Cubemap):
        return environment
    radiance = getattr(environment, "radiance", None)
    if not isinstance(radiance, Cubemap):
        raise InputError(
            f"the environment to bake must be a jaxpbr.Environment, a Cubemap, environment file paths or "
            f"'procedural:sky'; got {type(environment).__name__}"
        )
    carried = [k for k in ("irradiance", "prefiltered", "lut", "lights", "charlie", "sheen_lut") if getattr(environment, k, None) is not None]
    if carried:
        raise InputError(
            f"this Environment already carries {', '.join(carried)} (a jaxpbr.bake result?); the set is computed from "
            "its radiance: pass jaxpbr.Environment(radiance=...) or the radiance Cubemap"
        )
    rotation = float(np.asarray(environment.rotation))
    if rotation != 0.0:
        raise InputError(
            f"the Environment is rotated (rotation={rotation:g}); the files hold the unrotated environment: bake "
            "Environment(radiance=...) and set rotation on the Environment that jaxpbr.read_baked returns"
        )
    intensity = float(np.asarray(environment.intensity))
    if intensity == 1.0:
        return radiance
    return Cubemap([lv * np.float32(intensity) for lv in radiance.levels], radiance.info)


def check_prefilter_options(face_size, *, size=None, levels=None, method: str = "fis", samples=DEFAULT_SAMPLES, names=None) -> None:
    """`size` must be the environment's face size divided by a power of two, `levels` at most what
    that size holds, `samples` below 2^32, and the whole within the memory: refused before the
    work (also before loading, when the face size is known), the options named (`names`)."""
    if samples is not None:
        check_samples(_say(names, "samples"), samples)
    if not face_size:
        return
    S = size or face_size
    if levels is not None and S <= face_size and levels > mip_count(S):
        raise InputError(f"{_say(names, 'levels', levels)}: a {S}^2 prefiltered cube has at most {mip_count(S)} levels "
                         f"(each halves the face); lower {_say(names, 'levels')} (or raise {_say(names, 'face_size')})")
    if method == "fis" and S <= face_size:
        M = levels or default_num_levels(S)
        per_level = default_sample_counts(samples or DEFAULT_SAMPLES, S, M)
        require(f"a prefilter of a {face_size}^2 cube with up to {max(per_level[1:], default=0)} samples per texel",
                prefilter_bytes(face_size, S, per_level), names={"face_size": _say(names, "face_size"), "samples": _say(names, "samples")})
    if size is None:
        return
    ratio = face_size // size if size <= face_size else 0
    if ratio == 0 or face_size % size or ratio & (ratio - 1):
        sizes = ", ".join(str(face_size >> i) for i in range(min(4, face_size.bit_length())))
        raise InputError(
            f"{_say(names, 'size', size)} must be the environment cube's face size ({face_size}) divided by a power of two "
            f"({sizes}, ...); choose one of those, or set {_say(names, 'face_size')} to a multiple of {size} by a power of two"
        )


def check_float16(env: Cubemap, out, *, size=None, ktx_format: str = "rgba16f", names=None) -> None:
    """Refuse, before the work, a prefiltered map of `env` (at face `size`) whose values a float16
    KTX2 file `out` cannot hold: level 0 is the environment at that size, every other level
    averages it."""
    if Path(out).suffix.lower() != ".ktx2" or ktx_format != "rgba16f":
        return
    top = env.level_cube(0)
    if size and size < env.face_size:
        top = top.with_mips(env.face_size.bit_length() - size.bit_length() + 1)
    peak = float(np.max(np.abs(np.asarray(top.levels[-1]))))
    if peak > 65504.0:
        what = "the environment's radiance" + (f" at {_say(names, 'size')}" if size else "")
        raise InputError(
            f"{what} reaches {peak:.6g}, beyond the float16 range of {_say(names, 'ktx_format', 'rgba16f')} (65504); "
            f"use {_say(names, 'ktx_format', 'rgba32f')}, or scale the environment down"
        )


def _charlie_geometry(env: Cubemap, size, levels, names) -> tuple[int, int]:
    """(size, levels) of the Charlie cube: the ones given or the defaults (the renderer's:
    DEFAULT_CHARLIE_SIZE, no larger than the environment), refused before any work."""
    S = size or min(DEFAULT_CHARLIE_SIZE, env.face_size)
    most = mip_count(S)
    M = levels or min(DEFAULT_CHARLIE_LEVELS, most)
    if M > most:
        raise InputError(f"{_say(names, 'charlie_levels', M)}: a {S}^2 Charlie cube has at most {most} levels (each halves the face); "
                         f"lower {_say(names, 'charlie_levels')} or raise {_say(names, 'charlie_size')}")
    return S, M


# ------------------------------------------------------------------------------------------
# the assets
# ------------------------------------------------------------------------------------------


def irradiance_asset(env: Cubemap, irr: Cubemap, *, method: str, seconds=None, measure_error: bool = True, progress=None) -> Asset:
    """The irradiance map `irr` of `env` (computed with `method`, in `seconds`) as a file: its
    metadata and sidecar, with its error against the full-resolution exact convolution (float64,
    sampled texels) unless not `measure_error`; "sh9" adds the radiance SH coefficients.
    progress: optional callable(step, done, total) ("irradiance error check")."""
    err = irradiance_error(env, irr, progress=_step(progress, "irradiance error check")) if measure_error else None
    meta = {"quantity": "Ebar = E/pi (cosine-weighted mean radiance) at texel centres", "method": method, **irr.metadata}
    side = {
        "kind": "irradiance",
        "files": None,
        **meta,
        "face_size": irr.face_size,
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
    return Asset("irradiance", irr, meta, side)


def radiance_asset(env: Cubemap) -> Asset:
    """The environment's radiance `env` (level 0) as a file: what a renderer draws as the
    background (with any suns the set's other maps leave out)."""
    meta = {"quantity": "L, the environment's radiance (level 0, before any light extraction)"}
    side = {"kind": "radiance", "files": None, **meta, "face_size": env.face_size, "conventions": cube_conventions(),
            "versions": library_versions()}
    return Asset("radiance", env.level_cube(0), meta, side)


def prefiltered_asset(env: Cubemap, pre: Cubemap, *, method: str = "fis", seconds=None, measure_error: bool = True, progress=None) -> Asset:
    """The GGX-prefiltered chain `pre` of `env` as a file: its metadata (the lookup keys) and
    sidecar, with the per-level error against the float64 reference (sampled texels) unless not
    `measure_error` or `method` is the reference itself. progress: optional callable(step, done,
    total) ("prefilter error check (float64 reference)")."""
    check = _step(progress, "prefilter error check (float64 reference)")
    rows = prefilter_error(env, pre, progress=check) if measure_error and method != "reference" else None
    meta = dict(pre.metadata)
    side = {
        "kind": "prefiltered_specular",
        "files": None,
        **meta,
        "lookup": f"{meta['lod_formula']}; trilinear",
        "face_size": pre.face_size,
        "num_levels": pre.num_levels,
        "seconds": seconds,
        "error_vs_float64_reference": {"per_level": rows, "worst": summarize(rows)} if rows else None,
        "conventions": cube_conventions(),
        "versions": library_versions(),
    }
    return Asset("prefiltered_specular", pre, meta, side)


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


def _charlie_asset(env: Cubemap, *, size: int, levels: int, measure_error: bool, progress) -> Asset:
    """The Charlie-prefiltered cube (`sheen_prefilter.prefilter_charlie`) and its sidecar, described
    like the GGX cube (same container, metadata keys)."""
    t0 = time.perf_counter()
    ch = prefilter_charlie(env, size=size, num_levels=levels)
    [np.asarray(lv) for lv in ch.levels]
    seconds = time.perf_counter() - t0
    rows = _charlie_error(env, ch, progress=_step(progress, "charlie error check (float64 reference)")) if measure_error else None
    meta = dict(ch.metadata)
    side = {
        "kind": "prefiltered_charlie",
        "files": None,
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
    return Asset("prefiltered_charlie", ch, meta, side)


def _sheen_table(lut_size: int, *, measure_error: bool, progress) -> dict:
    """The sheen albedo table E for the LUT's B channel and its provenance: the shipped file with
    its MANIFEST error when one matches, otherwise computed (and its error measured against the
    float64 reference when `measure_error`)."""
    from ..shading.sheen_lut import DEFAULT_SAMPLES as SHEEN_SAMPLES
    from ..shading.sheen_lut import sheen_lut_error
    from ..shading.shipped_luts import sheen_lut, shipped_manifest

    n_r, n_nov = lut_shape(lut_size)
    entry = next((e for e in shipped_manifest().get("sheen_luts", []) if e["size"] == [n_r, n_nov] and e["samples"] == SHEEN_SAMPLES), None)
    t0 = time.perf_counter()
    table = np.asarray(sheen_lut(size=lut_size, progress=None if entry else _step(progress, "sheen lut")), np.float32)
    info = {
        "channel": "B",
        "quantity": "E_sheen(NoV, r) = int D_charlie V_charlie (n.l) dl (KHR_materials_sheen): the albedo scaling "
                    "1 - max3(sheen_color) E_sheen and the sheen IBL weight sheen_color LD_charlie E_sheen",
        "layout": f"as R, G: row j: r = (j+0.5)/{n_r}, column i: NoV = (i+0.5)/{n_nov}; rows below r = 0.045 hold E at 0.045",
        "samples": SHEEN_SAMPLES,
        "seconds": time.perf_counter() - t0,
    }
    if entry is not None:
        info |= {"source": "shipped", "shipped_file": f"jaxpbr/_luts/{entry['file']}",
                 **{k: entry[k] for k in ("max_abs_error", "mean_abs_error", "error_texels", "error_reference", "generated_by") if k in entry}}
    else:
        err = sheen_lut_error(table, texels=1024) if measure_error else None
        info |= {"source": "computed (jaxpbr.shading.sheen_lut.compute_sheen_lut)", "error_vs_float64_reference": err}
    return info | {"table": table}


def lut_asset(lut, *, smith: str, samples=None, seconds=None, sheen: dict | None = None, measure_error: bool = True,
              full_check: bool = False) -> Asset:
    """The split-sum LUT (n_r, n_nov, 2) for `smith` as an EXR file (R = A, G = B, B = 0): its
    header and sidecar, with its error against the float64 reference (every texel with
    `full_check`, else the edges + 1024 random texels) unless not `measure_error`.
    sheen: a baked set's sheen albedo table and its provenance ({"table": (n_r, n_nov), ...}): it
    goes into B, and the sidecar records where it came from."""
    lut = np.asarray(lut)
    err = lut_error(lut, smith=smith, texels=None if full_check else 1024) if measure_error else None
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
        if table.shape != lut.shape[:2]:  # both follow the LUT size; a mismatch is a bug
            raise RuntimeError(f"sheen table {table.shape} does not match the LUT {lut.shape[:2]}")
        third = table.astype(lut.dtype)
        channels["B"] = SHEEN_CHANNEL
        meta["quantity"] = ("split-sum BRDF LUT: int f_spec (n.l) dl = F0*A + F90*B; R = A, G = B; "
                            "B = E_sheen = int D_charlie V_charlie (n.l) dl (KHR_materials_sheen albedo scaling and sheen IBL weight)")
        meta["sheen_alpha"] = "B: alpha = max(r, 0.045)^2 (r perceptual sheen roughness; rows below r = 0.045 hold E at 0.045)"
    rgb = np.concatenate([lut, third[..., None]], -1)
    header = {f"jaxpbr:{k}": v for k, v in meta.items()} | {"jaxpbr:channels": "; ".join(f"{c} = {v}" for c, v in channels.items())}
    side = {
        "kind": "brdf_lut",
        "file": None,
        **meta,
        "channels": channels,
        **({"sheen_albedo": {k: v for k, v in sheen.items() if k != "table"}} if sheen is not None else {}),
        "size": list(lut.shape[:2]),
        "samples": samples,
        "seconds": seconds,
        "error_vs_float64_reference": err,
        "conventions": cube_conventions(),
        "versions": library_versions(),
    }
    return Asset("brdf_lut", rgb, header | {"jaxpbr:max_abs_error": err["max"] if err else -1.0}, side)


def write_asset(path, asset: Asset, *, ktx_format: str = "rgba16f", outputs: OutputSet | None = None, names=None) -> dict:
    """Write an asset's file(s) (a cube: KTX2 or per-face EXR by `path`'s suffix, `ktx_format`
    rgba16f | rgba32f; the LUT: EXR), registered with `outputs` before each write. -> its sidecar,
    "files" (the cube's paths) or "file" (the LUT's name) filled in; the caller writes it as
    `<path>.json`. A float16 overflow is an InputError naming `ktx_format` (through `names`)."""
    path = Path(path)
    side = dict(asset.sidecar)
    if isinstance(asset.data, Cubemap):
        try:
            side["files"] = write_cubemap(path, asset.data, fmt=ktx_format, metadata=asset.header, outputs=outputs)
        except Float16RangeError as exc:
            raise InputError(
                f"{exc.count} value(s) of {path.name} reach {exc.peak:.6g}, beyond the float16 range of "
                f"{_say(names, 'ktx_format', exc.fmt)} (65504); use {_say(names, 'ktx_format', exc.wide)}, or scale the environment down"
            ) from None
        return side
    if outputs is None:
        with OutputSet() as own:
            return write_asset(path, asset, ktx_format=ktx_format, outputs=own, names=names)
    outputs.add(path)  # registered before the write (see cubeio.write_cubemap)
    image.write(path, asset.data, metadata=asset.header)
    side["file"] = path.name
    return side


def _engine_lookup(sheen: bool, *, radiance: bool = False) -> dict:
    """How an engine reads each output (ibl.json "lookup")."""
    d = {"radiance": "background = radiance(d) (level 0, bilinear); the environment before any light extraction"} if radiance else {}
    d |= {
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


# ------------------------------------------------------------------------------------------
# the set
# ------------------------------------------------------------------------------------------


def write_baked(
    environment,
    out_dir,
    *,
    face_size: int | None = None,
    clamp_negative: bool = False,
    size: int | None = None,
    levels: int | None = None,
    mapping: str = "linear",
    lod_blend: str = DEFAULT_LOD_BLEND,
    method: str = "fis",
    samples: int = DEFAULT_SAMPLES,
    exact_texels: int | None = None,
    irradiance_size: int = 32,
    irradiance_method: str = "exact",
    lut_size: int = 128,
    smith: str = "correlated",
    sheen: bool = True,
    charlie_size: int | None = None,
    charlie_levels: int | None = None,
    extract: bool = False,
    radiance: bool = False,
    container: str = "ktx2",
    ktx_format: str = "rgba16f",
    measure_error: bool = True,
    progress=None,
    outputs: OutputSet | None = None,
    names: dict | None = None,
) -> dict:
    """Compute an environment's IBL set and write it into the folder `out_dir`: the files of
    `jaxpbr ibl ENV --out-dir DIR` (docs/cli.md), with the same content. -> the index (ibl.json).

        index = jaxpbr.write_baked("procedural:sky", "ibl/")        # or a panorama, a Cubemap, an Environment
        env = jaxpbr.read_baked("ibl/")                            # the baked Environment back

    environment: a panorama path (.hdr/.exr), six face paths, "procedural:sky" (`face_size`,
        `clamp_negative` as in `cubeio.load_environment`), a `Cubemap`, or a `jaxpbr.Environment`
        without maps (its radiance x intensity; not rotated).
    size, levels, mapping, lod_blend, method, samples, exact_texels: the GGX prefilter
        (`jaxpbr.prefilter`; size defaults to the environment's face size).
    irradiance_size, irradiance_method: `jaxpbr.irradiance` ("exact" | "sh9"; sh9 also records
        the SH coefficients). lut_size, smith: the split-sum LUT (computed, not the shipped table).
    sheen: bake the Charlie cube (`charlie_size` default min(64, face size), `charlie_levels`
        default up to 5) and put the sheen albedo in the LUT's B channel; False leaves both out.
    extract: split the suns out first (`extract.extract_lights`): the cubes hold the residual and
        lights.json the disc lights.

    The defaults differ from `jaxpbr.bake`'s on purpose, and `jaxpbr ibl` follows these. The set is
    for an engine that reads files: the sheen cube is in it (an engine cannot compute it later,
    where a render computes it when a scene needs it), and the suns stay in the cubes unless asked
    (`extract=True`, `--extract-lights`), since an engine that reads only the cubes would lose the
    suns' light. `jaxpbr.bake` prepares an `Environment` for `jaxpbr.render`: it splits the suns
    as a render does (`RenderOptions.extract_lights`, on by default) and leaves the sheen cube out.
    radiance: also store the environment itself (level 0, before any extraction) as
        `radiance.<container>`: `read_baked` then draws it as the background (without it, the
        prefiltered map's level 0, which lacks the extracted suns).
    container: "ktx2" (one file per cube, `ktx_format` rgba16f | rgba32f) or "exr" (one float32 file
        per mip and face, `<stem>_m<m>_<face>.exr`). The LUT is always brdf_lut.exr.
    measure_error: record each map's error against its float64 reference in the sidecars (the
        slow part at small sizes).
    progress: optional callable(step, done, total); steps: "irradiance", "irradiance error check",
        "prefilter", "prefilter error check (float64 reference)", "charlie error check (float64
        reference)", "sheen lut", "lut".
    outputs: an `OutputSet` to register the files with (the caller commits or rolls back);
        default: one of its own, so that an exception leaves the folder as it was.
    names: {keyword: flag} for messages (see the module docstring).

    Every output and option is checked before any work (InputError naming the problem and the
    fix); values beyond float16 with rgba16f are refused before the prefilter.
    `jaxpbr.bake` computes the same maps in memory without writing them.
    """
    if outputs is None:
        with OutputSet() as own:
            return write_baked(
                environment, out_dir, face_size=face_size, clamp_negative=clamp_negative, size=size, levels=levels,
                mapping=mapping, lod_blend=lod_blend, method=method, samples=samples, exact_texels=exact_texels,
                irradiance_size=irradiance_size, irradiance_method=irradiance_method, lut_size=lut_size, smith=smith,
                sheen=sheen, charlie_size=charlie_size, charlie_levels=charlie_levels, extract=extract,
                radiance=radiance, container=container, ktx_format=ktx_format, measure_error=measure_error, progress=progress,
                outputs=own, names=names,
            )
    d = Path(out_dir)
    where = _say(names, "out_dir")
    if d.exists() and not d.is_dir():
        raise InputError(f"{where} {str(d)!r} is a file, not a folder; give a folder")
    if not d.is_dir():
        raise InputError(f"{where} {str(d)!r} does not exist; create it first")
    # A complete set already there is kept until the new one is complete: an interrupted or
    # failed re-bake puts the old files back.
    outputs.protect(p for stem in STEMS for p in d.glob(f"{stem}*"))
    if not sheen and (charlie_size or charlie_levels):
        raise InputError(f"{_say(names, 'charlie_size')} / {_say(names, 'charlie_levels')} set the Charlie cube, which "
                         f"{(names or {}).get('sheen=False', 'sheen=False')} leaves out; drop one or the other")
    if container not in ("ktx2", "exr"):
        raise InputError(f"{_say(names, 'container', container)} is not a cube container; choose 'ktx2' or 'exr'")
    if ktx_format not in FORMATS or not ktx_format.startswith("rgba"):
        raise InputError(f"{_say(names, 'ktx_format', ktx_format)} is not a KTX2 cube format; choose 'rgba16f' or 'rgba32f'")
    if exact_texels is not None and exact_texels < 0:
        raise InputError(f"{_say(names, 'exact_texels')} must be >= 0, got {exact_texels}")
    smith = resolve_smith(smith, "write_baked")
    ext = "." + container
    paths = {"irradiance": d / f"irradiance{ext}", "prefiltered": d / f"prefiltered{ext}"}
    if sheen:
        paths["charlie"] = d / f"charlie{ext}"
    paths |= {"brdf_lut": d / "brdf_lut.exr", "index": d / INDEX}
    if extract:
        paths["lights"] = d / "lights.json"
    if radiance:
        paths["radiance"] = d / f"radiance{ext}"
    for p in paths.values():  # every output checked before any work
        prepare_output(outputs, p, (p.suffix,))
    n_r, n_nov = lut_shape(lut_size)
    require(f"a LUT of {n_r}x{n_nov} texels", lut_bytes(n_r, n_nov, LUT_DEFAULT_SAMPLES), names={"size": _say(names, "lut_size")})
    check_prefilter_options(face_size, size=size, levels=levels, method=method, samples=samples, names=names)
    env = load_source(environment, face_size=face_size, clamp_negative=clamp_negative, kind="prefilter", names=names)
    source, lights = env, None
    if radiance:
        check_float16(source, paths["radiance"], ktx_format=ktx_format, names=names)
    if extract:
        ex = extract_lights(env)
        env, lights = ex.residual, lights_to_json(ex)
    check_prefilter_options(env.face_size, size=size, levels=levels, method=method, samples=samples, names=names)
    check_float16(env, paths["prefiltered"], size=size, ktx_format=ktx_format, names=names)
    charlie_shape = _charlie_geometry(env, charlie_size, charlie_levels, names) if sheen else None

    def put(key: str, asset: Asset) -> dict:
        side = write_asset(paths[key], asset, ktx_format=ktx_format, outputs=outputs, names=names)
        write_json(paths[key].with_name(paths[key].name + ".json"), side, outputs=outputs)
        return side

    guard_irradiance(irradiance_size, names=names)
    t0 = time.perf_counter()
    irr = irradiance(env, size=irradiance_size, method=irradiance_method, progress=_step(progress, "irradiance"))
    np.asarray(irr.levels[0])
    seconds = time.perf_counter() - t0
    index = {"sheen": sheen, "irradiance": put("irradiance", irradiance_asset(
        env, irr, method=irradiance_method, seconds=seconds, measure_error=measure_error, progress=progress))}
    if radiance:
        index["radiance"] = put("radiance", radiance_asset(source))

    t0 = time.perf_counter()
    pre = prefilter(env, size=size, num_levels=levels, mapping=mapping, lod_blend=lod_blend, method=method, samples=samples,
                    exact_texels=exact_texels, progress=_step(progress, "prefilter"))
    [np.asarray(lv) for lv in pre.levels]
    seconds = time.perf_counter() - t0
    index["prefiltered"] = put("prefiltered", prefiltered_asset(env, pre, method=method, seconds=seconds,
                                                                measure_error=measure_error, progress=progress))
    if sheen:
        S, M = charlie_shape
        index["charlie"] = put("charlie", _charlie_asset(env, size=S, levels=M, measure_error=measure_error, progress=progress))
    table = _sheen_table(lut_size, measure_error=measure_error, progress=progress) if sheen else None

    t0 = time.perf_counter()
    lut = np.asarray(brdf_lut(size=lut_size, smith=smith, samples=None, use_shipped=False, progress=_step(progress, "lut")))
    seconds = time.perf_counter() - t0
    index["brdf_lut"] = put("brdf_lut", lut_asset(lut, smith=smith, samples=None, seconds=seconds, sheen=table,
                                                  measure_error=measure_error))
    index["lookup"] = _engine_lookup(sheen, radiance=radiance)
    if lights is not None:
        write_json(paths["lights"], lights, outputs=outputs)
        index["lights"] = {"file": "lights.json", "count": len(lights["lights"]),
                           "note": "the cubes hold the residual environment; shade these disc lights with it"}
    write_json(paths["index"], index, outputs=outputs)
    return index


# ------------------------------------------------------------------------------------------
# reading a set back
# ------------------------------------------------------------------------------------------


_FACE_FILE = re.compile(r"^(?P<stem>.+)_m(?P<mip>\d+)_(?P<face>px|nx|py|ny|pz|nz)\.exr$")


def _rebake(d: Path) -> str:
    return f"bake the set again (jaxpbr.write_baked(environment, {str(d)!r}) or `jaxpbr ibl ENV --out-dir {d}`)"


def read_baked_maps(directory) -> BakedMaps:
    """Read the baked set in `directory` (what `write_baked` and `jaxpbr ibl` write: ibl.json and
    the KTX2 or per-face EXR cubes, brdf_lut.exr, lights.json) -> `BakedMaps`, float32.

    The cubes' metadata (the lookup keys: "mapping_levels", "roughness_mapping", "lod_blend",
    "distribution", "min_roughness", ...) comes from the files, so they are looked up as they were
    written. A missing folder or index, a file the index names that is missing or unreadable, or
    one that does not match the index raises one InputError naming the file and the fix."""
    d = Path(directory)
    if not d.exists():
        raise InputError(f"baked IBL folder {str(d)!r} does not exist; give the folder that holds {INDEX}")
    if not d.is_dir():
        raise InputError(f"baked IBL folder {str(d)!r} is a file, not a folder; give the folder that holds {INDEX}")
    path = d / INDEX
    if not path.is_file():
        raise InputError(f"{str(path)!r} is missing: {str(d)!r} holds no baked IBL set; {_rebake(d)}")
    try:
        index = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise InputError(f"cannot read {str(path)!r} ({str(e).splitlines()[0] if str(e) else type(e).__name__}); {_rebake(d)}") from None
    for key in ("irradiance", "prefiltered", "brdf_lut"):
        if not isinstance(index, dict) or not isinstance(index.get(key), dict):
            raise InputError(f"{str(path)!r} is not a baked set's index (no {key!r} entry); {_rebake(d)}")
    irr = _read_cube(d, index["irradiance"], "irradiance")
    pre = _read_cube(d, index["prefiltered"], "prefiltered")
    charlie = _read_cube(d, index["charlie"], "charlie") if isinstance(index.get("charlie"), dict) else None
    lut, smith, table = _read_lut(d, index["brdf_lut"], sheen=bool(index.get("sheen")) and charlie is not None)
    lights = _read_lights(d, index["lights"]) if isinstance(index.get("lights"), dict) else None
    radiance = _read_cube(d, index["radiance"], "radiance") if isinstance(index.get("radiance"), dict) else None
    return BakedMaps(irr, pre, lut, smith, table, charlie, lights, index, radiance)


def _files(d: Path, entry: dict, what: str) -> list[Path]:
    files = entry.get("files")
    if not isinstance(files, list) or not files or not all(isinstance(f, str) for f in files):
        raise InputError(f"{str(d / INDEX)!r} names no files for {what!r}; {_rebake(d)}")
    out = [d / Path(f).name for f in files]  # the set may have moved: the names, in this folder
    for p in out:
        if not p.is_file():
            raise InputError(f"{str(p)!r} (named by {INDEX}) is missing; {_rebake(d)}")
    return out


def _read_cube(d: Path, entry: dict, what: str) -> Cubemap:
    files = _files(d, entry, what)
    if len(files) == 1 and files[0].suffix.lower() == ".ktx2":
        path = files[0]
        try:
            levels, meta, info = read_ktx2(path)
        except (OSError, ValueError) as e:
            raise InputError(f"{str(e).splitlines()[0]}; {_rebake(d)}") from None
        if info["face_count"] != 6:
            raise InputError(f"{str(path)!r} is a 2D texture, not a cube map; {_rebake(d)}")
        levels = [lv[..., :3] for lv in levels]
        info = {k.removeprefix("jaxpbr:"): v for k, v in meta.items() if k.startswith("jaxpbr:")}
    else:
        levels, info, path = _read_exr_cube(d, files, what)
    # In the order the sidecar lists them (the order the map was made with: a KTX2 file sorts its
    # keys), so that the lookup keys compare equal to the computed map's (`CubeInfo`) and a render
    # reuses the programs compiled for it.
    info = {k: info[k] for k in [k for k in entry if k in info] + [k for k in info if k not in entry]}
    _match(d, path, "face size", levels[0].shape[1], entry.get("face_size"))
    if "num_levels" in entry:
        _match(d, path, "level count", len(levels), entry["num_levels"])
    try:
        return Cubemap([jax.device_put(np.ascontiguousarray(lv, np.float32)) for lv in levels], info)
    except ValueError as e:
        raise InputError(f"{str(path)!r}: {str(e).splitlines()[0]}; {_rebake(d)}") from None


def _read_exr_cube(d: Path, files: list[Path], what: str):
    faces: dict[tuple[int, str], Path] = {}
    for p in files:
        m = _FACE_FILE.match(p.name)
        if m is None:
            raise InputError(f"{str(p)!r} (named by {INDEX} for {what!r}) is neither a .ktx2 cube nor a <stem>_m<mip>_<face>.exr face; {_rebake(d)}")
        faces[int(m["mip"]), m["face"]] = p
    count = 1 + max(m for m, _ in faces)
    levels, info = [], {}
    for m in range(count):
        stack = []
        for f in FACE_FILE_NAMES:
            p = faces.get((m, f))
            if p is None:
                raise InputError(f"{str(d / INDEX)!r} names no {f} face of mip {m} of {what!r}; {_rebake(d)}")
            try:
                img, meta = image.read_with_metadata(p)
            except (OSError, ValueError) as e:
                raise InputError(f"cannot read {str(p)!r} ({str(e).splitlines()[0] if str(e) else type(e).__name__}); {_rebake(d)}") from None
            if m == 0 and f == "px":
                info = {k: v for k, v in meta.items() if k not in ("jaxpbr:mip", "jaxpbr:face")}
            stack.append(np.asarray(img, np.float32)[..., :3])
        if len({s.shape for s in stack}) != 1:
            raise InputError(f"the faces of mip {m} of {what!r} in {str(d)!r} differ in size; {_rebake(d)}")
        levels.append(np.stack(stack))
    return levels, info, faces[0, "px"]


def _match(d: Path, path: Path, what: str, got, want) -> None:
    if want is not None and got != want:
        raise InputError(f"{str(path)!r} has {what} {got}, but {INDEX} says {want}; the set is mixed up: {_rebake(d)}")


def _read_lut(d: Path, entry: dict, *, sheen: bool):
    name = entry.get("file")
    path = d / Path(name if isinstance(name, str) else "brdf_lut.exr").name
    if not path.is_file():
        raise InputError(f"{str(path)!r} (named by {INDEX}) is missing; {_rebake(d)}")
    try:
        img = np.asarray(image.read(path), np.float32)
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read {str(path)!r} ({str(e).splitlines()[0] if str(e) else type(e).__name__}); {_rebake(d)}") from None
    if img.ndim != 3 or img.shape[-1] < 3:
        raise InputError(f"{str(path)!r} is not a 3-channel LUT (shape {img.shape}); {_rebake(d)}")
    _match(d, path, "size", list(img.shape[:2]), entry.get("size"))
    smith = entry.get("smith")
    if not isinstance(smith, str):
        raise InputError(f"{str(d / INDEX)!r} does not say which Smith term brdf_lut.exr holds; {_rebake(d)}")
    lut = jax.device_put(np.ascontiguousarray(img[..., :2]))
    table = jax.device_put(np.ascontiguousarray(img[..., 2])) if sheen else None
    return lut, smith, table


def _read_lights(d: Path, entry: dict):
    path = d / Path(entry.get("file") or "lights.json").name
    try:
        data = json.loads(path.read_text())
        khr = data["KHR_lights_punctual"]["lights"]
        lights = tuple(
            DirectionalLight(direction=np.asarray(x["extras"]["direction"], np.float32), color=np.asarray(x["color"], np.float32),
                             intensity=np.float32(x["intensity"]), angular_radius=np.float32(x["extras"]["angular_radius"]))
            for x in khr
        )
    except FileNotFoundError:
        raise InputError(f"{str(path)!r} (named by {INDEX}) is missing; {_rebake(d)}") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"cannot read the lights of {str(path)!r} ({type(e).__name__}: {e}); {_rebake(d)}") from None
    return lights or None
