"""Job files: JSON Lines rows of render and bake jobs, validated whole before any work.

One JSON object per line (blank lines are skipped). Render rows::

    {"name": "grid/front", "scene": "demo", "width": 256, "height": 256,
     "camera": {"position": [0, 0, 24], "target": [0, 0, 0], "fov_y": 45},
     "environment": "procedural:sky", "environment_intensity": 1.0, "environment_rotation": 30,
     "material": {"roughness": 0.3}, "options": {"model": "gltf"},
     "output": {"formats": ["png", "exr"], "aovs": ["depth", "normal"], "exposure": 0}}

`scene` is "demo" (the default), a TOML scene file, a glTF asset (.gltf/.glb) or
{"factory": "module:function", "args": {...}} (a function returning a `jaxpbr.Scene`; the module is
imported with the job file's folder on `sys.path`). Bake rows (``"kind": "bake"``) take an
environment and the keywords of `jaxpbr.write_baked` (`face_size`, `size`, `irradiance_size`,
`lut_size`, `container`, `ktx_format`, `sheen`, `extract`, ...) and write the set into the folder
named by `name`. Paths are relative to the job file's folder; names are relative to the output
folder. docs/batch.md has every field.

`load_jobs` checks every row and raises one `JobFileError` listing every problem, one line each:
"<file>:<row>: <field>: <problem>; <fix>" (rows count from 1, as editors number lines).

A job file is untrusted input: only a regular file of at most `MAX_JOB_FILE_BYTES` is read (a FIFO
or a device is refused without waiting on it), a row nested deeper than `MAX_NESTING` or giving a
key twice is refused, and job names stay inside the output folder and out of the run's own state
(`store.STATE_DIR`, the summary), at most `MAX_NAME` characters.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import os
import math
import re
from pathlib import Path
from typing import Any

from ..color import TONEMAP_OPERATORS, TRANSFERS
from ..errors import InputError
from ..ibl.baked import write_baked
from ..ibl.diffuse import IRRADIANCE_METHODS
from ..ibl.specular import LOD_BLENDS, MAPPINGS, PREFILTER_METHODS
from ..rendering.aovs import AOVS
from ..rendering.renderer import RenderOptions
from ..rendering.scene import MAX_SUPERSAMPLE
from ..rendering.scene_file import (
    MAX_NESTING,
    bracket_depth,
    parse_toml,
    read_regular_file,
    read_scene_text,
)
from ..shading.lut import SMITH_VARIANTS
from ..shading.material import Material
from .store import _LEFTOVER, STATE_DIR, SUMMARY

__all__ = ["BakeJob", "JobFileError", "RenderJob", "load_jobs", "parse_jobs"]

RENDER_FIELDS = ("kind", "name", "scene", "width", "height", "supersample", "camera", "environment",
                 "environment_intensity", "environment_rotation", "material", "options", "output", "time", "animation")
CAMERA_FIELDS = ("position", "target", "up", "fov_y", "ymag")
OUTPUT_FIELDS = ("formats", "aovs", "exposure", "tonemap", "encoding", "bits")
FORMATS = ("png", "exr")
TONEMAPS = TONEMAP_OPERATORS
ENCODINGS = TRANSFERS
#: `write_baked` keywords a bake row may set (everything but the environment, the folder and the
#: caller's hooks), with their defaults: derived from the function's signature.
BAKE_OPTIONS = {
    k: p.default for k, p in inspect.signature(write_baked).parameters.items()
    if p.kind is inspect.Parameter.KEYWORD_ONLY and k not in ("progress", "outputs", "names")
}
_RENDER_OPTIONS = {f.name: f for f in dataclasses.fields(RenderOptions)}
_NAME = re.compile(r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*$")
#: Images per job are capped like the command line's renders.
MAX_SIDE = 16384
#: The largest job file read, in bytes (64 MiB): a row is a few hundred bytes, so this is some
#: 200,000 jobs (more belong in several files, each run on its own); the cap keeps a mistaken or
#: hostile job file (/dev/zero, a multi-GB log) from being read whole into memory.
MAX_JOB_FILE_BYTES = 64 << 20
#: The longest job name, in characters (a 10,000-character name passed validation and failed when
#: its files were written).
MAX_NAME = 200
#: The longest part of a job name (between slashes), in bytes: a file name has at most 255, and the
#: engine adds up to 25 to the last part (".png", then the copy an output set keeps while it
#: replaces a file: "." + part + ".png" + ".jaxpbr-old-" + 8 hex digits), 30 with a margin. Names
#: are ASCII (`_NAME`), so MAX_NAME alone keeps to this today; the check stays if it is raised.
MAX_COMPONENT = 255 - 30


class JobFileError(InputError):
    """A job file with bad rows: the message has one line per problem."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


@dataclasses.dataclass(frozen=True)
class RenderJob:
    """One render row, validated. `key` identifies what it computes (the row and its input files'
    sizes and modification times): a completed job is redone only when its key changes."""

    row: int
    name: str
    scene: Any  # "demo" | Path (.toml/.gltf/.glb) | ("factory", "module:function", args-json, folder)
    width: int | None
    height: int | None
    supersample: int | None
    camera: dict | None
    environment: str | None  # "procedural:sky" or an absolute path
    environment_intensity: float | None
    environment_rotation: float | None
    material: dict | None
    options: dict
    formats: tuple[str, ...]
    aovs: tuple[str, ...]
    display: dict
    key: str
    time: float | None = None  # a glTF asset posed at this time of `animation` (docs/gltf.md)
    animation: int | str | None = None

    kind = "render"

    @property
    def outputs(self) -> tuple[str, ...]:
        """The output files, relative to the output folder."""
        return tuple(f"{self.name}.{f}" for f in self.formats)

    @property
    def group(self) -> tuple:
        """Jobs of one group share the loaded scene, the environment's precomputes and the compiled
        programs (same scene source, image size, options and outputs)."""
        return ("render", repr(self.scene), self.width, self.height, self.supersample, self.environment,
                json.dumps(self.options, sort_keys=True), self.aovs)


@dataclasses.dataclass(frozen=True)
class BakeJob:
    """One bake row, validated: `jaxpbr.write_baked(environment, out/name, **options)`."""

    row: int
    name: str
    environment: str
    options: dict
    key: str

    kind = "bake"

    @property
    def outputs(self) -> tuple[str, ...]:
        return ()  # a folder: the files are listed by the index the bake writes

    @property
    def group(self) -> tuple:
        return ("bake", self.environment, json.dumps({k: v for k, v in self.options.items() if k == "face_size"}))


def load_jobs(path) -> list:
    """Read and validate a job file -> [RenderJob | BakeJob] in file order (JobFileError lists
    every bad row). Only a regular file of at most `MAX_JOB_FILE_BYTES` of UTF-8 is read
    (InputError otherwise, before anything is read from a FIFO or a device)."""
    path = Path(path)
    data = read_regular_file(path, limit=MAX_JOB_FILE_BYTES, what="job file",
                             missing="give a JSON Lines file (docs/batch.md)",
                             other="give a JSON Lines file (docs/batch.md)",
                             smaller="split it into several job files")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"job file {str(path)!r} is not UTF-8 text ({e.reason} at byte {e.start}); "
                         f"save it as UTF-8 (JSON Lines)") from None
    return parse_jobs(text, base_dir=path.resolve().parent, source=path.name)


class _DuplicateKey(Exception):
    pass


def _unique_keys(pairs) -> dict:
    """json's object_pairs_hook: an object that gives a key twice is refused (json.loads keeps
    the last one without a word)."""
    out = {}
    for k, v in pairs:
        if k in out:
            raise _DuplicateKey(k)
        out[k] = v
    return out


_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"')
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")


def _row_too_deep(line: str) -> bool:
    """Whether a row nests arrays and objects deeper than MAX_NESTING, from its brackets outside
    strings (json.loads recurses, and a row nested 100,000 deep ended the run with a
    RecursionError), up to an unterminated string, where json.loads stops too."""
    if line.count("[") + line.count("{") <= MAX_NESTING:  # fewer brackets cannot nest deeper
        return False
    bare = _JSON_STRING.sub("", line)
    bare = bare[: bare.find('"')] if '"' in bare else bare
    return bracket_depth(_NOT_BRACKET.sub("", bare), stop=MAX_NESTING) > MAX_NESTING


def _shown(x, n: int = 60) -> str:
    """A value of a row in a message: its repr, cut to n characters."""
    r = repr(x)
    return r if len(r) <= n else r[: n - 3] + "..."


def parse_jobs(text: str, *, base_dir, source: str = "<jobs>") -> list:
    """Validate the rows of a job file's text (paths relative to `base_dir`)."""
    base_dir = Path(base_dir)
    problems: list[str] = []
    jobs: list = []
    names: dict[str, int] = {}
    stamps: dict[Path, Any] = {}
    for row, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        where = f"{source}:{row}"
        too_deep = (f"{where}: arrays and objects nested more than {MAX_NESTING} levels deep; a job row "
                    f"nests 3 (docs/batch.md): fix the row")
        if _row_too_deep(line):
            problems.append(too_deep)
            continue
        try:
            obj = json.loads(line, object_pairs_hook=_unique_keys)
        except json.JSONDecodeError as e:
            problems.append(f"{where}: not JSON ({e.msg} at column {e.colno}); write one JSON object per line")
            continue
        except _DuplicateKey as e:
            problems.append(f"{where}: {_shown(e.args[0])}: the key is given twice in one object (JSON readers "
                            f"keep one or the other); give it once")
            continue
        except RecursionError:  # a backstop: _row_too_deep finds any nesting that gets this deep
            problems.append(too_deep)
            continue
        except ValueError as e:  # e.g. an integer of more than 4300 digits
            problems.append(f"{where}: not JSON that can be read ({' '.join(str(e).split())[:120]}); "
                            f"write one JSON object per line")
            continue
        if not isinstance(obj, dict):
            problems.append(f"{where}: expected a JSON object, got {type(obj).__name__}; write one object per line")
            continue
        bad: list[str] = []
        job = _parse_row(obj, row, base_dir, bad, stamps)
        problems += [f"{where}: {b}" for b in bad]
        if job is None:
            continue
        if job.name in names:
            problems.append(f"{where}: name: {job.name!r} is already the name of row {names[job.name]}; give every job its own name")
            continue
        names[job.name] = row
        jobs.append(job)
    # An output of one job may not be a folder of another (a bake's folder is a name).
    owned = {n: r for n, r in names.items()}
    for j in jobs:
        parts = j.name.split("/")
        for k in range(1, len(parts)):
            prefix = "/".join(parts[:k])
            if prefix in owned:
                problems.append(f"{source}:{j.row}: name: {j.name!r} lies inside {prefix!r}, the output of row {owned[prefix]}; rename one")
    if not jobs and not problems:
        problems.append(f"{source}: no jobs; write one JSON object per line (docs/batch.md)")
    if problems:
        raise JobFileError(problems)
    return jobs


def _parse_row(obj: dict, row: int, base: Path, bad: list, stamps: dict):
    kind = obj.get("kind", "render")
    if kind not in ("render", "bake"):
        bad.append(f"kind: {kind!r} is not a job kind; use 'render' or 'bake'")
        return None
    name = obj.get("name")
    if name is None:
        bad.append("name: missing; give every job an output name (e.g. \"sky/front\")")
    else:
        problem = _name_problem(name, kind, obj.get("output"))
        if problem:
            bad.append(f"name: {problem}")
            name = None
    if kind == "bake":
        return _parse_bake(obj, row, name, base, bad, stamps)
    for k in obj:
        if k not in RENDER_FIELDS:
            bad.append(f"{k}: unknown field of a render job{_suggest(k, RENDER_FIELDS)}")
    scene = _scene(obj.get("scene", "demo"), base, bad)
    width = _int(obj, "width", None, bad, 1, MAX_SIDE)
    height = _int(obj, "height", None, bad, 1, MAX_SIDE)
    supersample = _int(obj, "supersample", None, bad, 1, MAX_SUPERSAMPLE)
    camera = _camera(obj.get("camera"), bad)
    env = obj.get("environment")
    environment = None
    if env is not None:
        environment = _input_file(env, base, "environment", (".hdr", ".exr"), bad, procedural=True)
    intensity = _number(obj, "environment_intensity", bad, minimum=0.0)
    rotation = _number(obj, "environment_rotation", bad)
    if env is None and (intensity is not None or rotation is not None):
        if scene == "demo":
            pass  # the demo has its own sky
        elif not (isinstance(scene, Path) and scene.suffix == ".toml"):
            bad.append("environment_intensity/environment_rotation: the job has no environment; add 'environment' or drop them")
    material = _material(obj.get("material"), bad)
    t = _number(obj, "time", bad)
    anim = obj.get("animation")
    if anim is not None and (isinstance(anim, bool) or not isinstance(anim, (int, str)) or (isinstance(anim, int) and anim < 0)):
        bad.append(f"animation: expected an animation's index (>= 0) or name, got {anim!r}")
        anim = None
    gltf = isinstance(scene, Path) and scene.suffix.lower() in (".gltf", ".glb")
    if (t is not None or anim is not None) and not gltf:
        bad.append("time/animation: apply to glTF assets (.gltf, .glb) only")
    options = _options(obj.get("options", {}), bad, _file_render(scene))
    formats, aovs, display = _output(obj.get("output", {}), bad)
    if bad or name is None:
        return None
    inputs = [scene if isinstance(scene, Path) else _factory_file(scene),
              Path(environment) if environment and not environment.startswith("procedural:") else None]
    key = _key(obj, inputs, stamps)
    return RenderJob(row=row, name=name, scene=scene, width=width, height=height, supersample=supersample,
                     camera=camera, environment=environment, environment_intensity=intensity,
                     environment_rotation=rotation, material=material, options=options, formats=formats,
                     aovs=aovs, display=display, key=key, time=t, animation=anim)


def _parse_bake(obj: dict, row: int, name, base: Path, bad: list, stamps: dict):
    for k in obj:
        if k not in ("kind", "name", "environment") and k not in BAKE_OPTIONS:
            bad.append(f"{k}: unknown field of a bake job{_suggest(k, tuple(BAKE_OPTIONS) + ('environment',))}")
    env = obj.get("environment")
    if env is None:
        bad.append("environment: missing; give an .hdr/.exr panorama or 'procedural:sky'")
        environment = None
    else:
        environment = _input_file(env, base, "environment", (".hdr", ".exr"), bad, procedural=True)
    options = {}
    for k, default in BAKE_OPTIONS.items():
        if k not in obj:
            continue
        v = obj[k]
        if isinstance(default, bool):
            ok = isinstance(v, bool)
            want = "true or false"
        elif isinstance(default, str):
            ok = isinstance(v, str)
            want = "a string"
        elif isinstance(default, int) or default is None:
            ok = v is None or (isinstance(v, int) and not isinstance(v, bool) and v >= 0)
            want = "a non-negative integer"
        else:
            ok, want = True, ""
        if not ok:
            bad.append(f"{k}: expected {want}, got {v!r}")
        else:
            options[k] = v
    for k, choices in (("container", ("ktx2", "exr")), ("ktx_format", ("rgba16f", "rgba32f")),
                       ("irradiance_method", IRRADIANCE_METHODS), ("smith", SMITH_VARIANTS),
                       ("mapping", MAPPINGS), ("lod_blend", LOD_BLENDS), ("method", PREFILTER_METHODS)):
        if k in options and options[k] not in choices:
            bad.append(f"{k}: {options[k]!r} is not one of {', '.join(choices)}")
    for k in ("face_size", "size", "irradiance_size", "lut_size"):
        if options.get(k) == 0:
            bad.append(f"{k}: must be positive")
    if bad or name is None or environment is None:
        return None
    key = _key(obj, [Path(environment) if not environment.startswith("procedural:") else None], stamps)
    return BakeJob(row=row, name=name, environment=environment, options=options, key=key)


def _name_problem(name, kind: str, output) -> str | None:
    """What keeps `name` from naming a job's outputs inside the output folder, or None."""
    if isinstance(name, str) and len(name) > MAX_NAME:
        return f"{len(name)} characters, more than the {MAX_NAME} a job name may have; give a shorter name"
    if not isinstance(name, str) or not _NAME.match(name) or any(p in (".", "..") for p in name.split("/")):
        return (f"expected a relative output name of letters, digits, '_', '-', '.' and '/' "
                f"(e.g. 'sky/front'), got {_shown(name)}")
    parts = name.split("/")
    long = next((p for p in parts if len(p.encode()) > MAX_COMPONENT), None)
    if long is not None:
        return (f"the part {_shown(long, 40)} is {len(long.encode())} bytes, more than the {MAX_COMPONENT} a "
                f"file name leaves it; split it with '/' or shorten it")
    # casefold: on a case-insensitive file system .JAXPBR-BATCH is the state folder too
    if any(p.casefold().startswith(STATE_DIR.casefold()) for p in parts):
        return (f"{name!r} lies in {STATE_DIR!r}, the folder where the run keeps its lock and records; "
                f"give a name outside it")
    if name.casefold() == SUMMARY.casefold():
        return f"{name!r} is the run's summary file; give another name"
    if kind == "render":
        formats = output.get("formats") if isinstance(output, dict) else None
        for f in formats if isinstance(formats, list) and formats else ["png"]:
            if isinstance(f, str) and _LEFTOVER.match(f"{parts[-1]}.{f}"):
                return (f"{name!r} has the form of the temporary files a run removes when it starts "
                        f"('.NAME.tmp-XXXXXXXX'), so its outputs would be removed; give another name")
    return None


def _suggest(word: str, choices) -> str:
    import difflib

    m = difflib.get_close_matches(word, list(choices), n=1)
    return f" (did you mean {m[0]!r}?)" if m else f"; known fields: {', '.join(choices)}"


def _input_file(value, base: Path, field: str, suffixes, bad: list, procedural=False):
    if not isinstance(value, str) or not value:
        bad.append(f"{field}: expected a file path string, got {value!r}")
        return None
    if procedural and value.startswith("procedural:"):
        if value != "procedural:sky":
            bad.append(f"{field}: unknown procedural environment {value!r}; the one available is 'procedural:sky'")
            return None
        return value
    p = (base / value).resolve()
    if p.suffix.lower() not in suffixes:
        bad.append(f"{field}: {value!r} is not one of {', '.join(suffixes)}{' or procedural:sky' if procedural else ''}")
        return None
    if not p.is_file():
        what = "is not a regular file" if p.exists() else "does not exist"
        bad.append(f"{field}: file {_shown(value)} {what} (paths are relative to the job file's folder)")
        return None
    return str(p)


def _scene(value, base: Path, bad: list):
    if value == "demo":
        return "demo"
    if isinstance(value, dict):
        extra = set(value) - {"factory", "args"}
        fac = value.get("factory")
        args = value.get("args", {})
        if extra:
            bad.append(f"scene: unknown key(s) {sorted(extra)} of a factory scene; use 'factory' and 'args'")
        if not isinstance(fac, str) or not re.match(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$", fac):
            bad.append(f"scene.factory: expected 'module:function', got {fac!r}")
            return None
        if not isinstance(args, dict):
            bad.append(f"scene.args: expected an object of keyword arguments, got {args!r}")
            return None
        if factory_module_file(fac, base) is None:
            bad.append(f"scene.factory: module {fac.partition(':')[0]!r} is not a Python file in the job file's folder "
                       f"({base}); a factory is imported from there only (an installed module such as subprocess:run "
                       "would let a job file run any command): put the module beside the job file")
            return None
        return ("factory", fac, json.dumps(args, sort_keys=True), str(base))
    p = _input_file(value, base, "scene", (".toml", ".gltf", ".glb"), bad)
    return None if p is None else Path(p)


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _int(obj, k, default, bad, lo, hi):
    if k not in obj:
        return default
    v = obj[k]
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        bad.append(f"{k}: expected an integer in [{lo}, {hi}], got {v!r}")
        return default
    return v


def _number(obj, k, bad, minimum=None):
    if k not in obj:
        return None
    v = obj[k]
    if not _finite(v) or (minimum is not None and v < minimum):
        bad.append(f"{k}: expected a finite number{f' >= {minimum:g}' if minimum is not None else ''}, got {v!r}")
        return None
    return float(v)


def _vec3(v) -> bool:
    return isinstance(v, list) and len(v) == 3 and all(_finite(x) for x in v)


def _camera(cam, bad):
    if cam is None:
        return None
    if not isinstance(cam, dict):
        bad.append(f"camera: expected an object with {', '.join(CAMERA_FIELDS)}, got {cam!r}")
        return None
    out = {}
    for k, v in cam.items():
        if k not in CAMERA_FIELDS:
            bad.append(f"camera.{k}: unknown field{_suggest(k, CAMERA_FIELDS)}")
        elif k == "fov_y":
            if not _finite(v) or not 0 < v < 180:
                bad.append(f"camera.fov_y: expected degrees in (0, 180), got {v!r}")
            else:
                out[k] = float(v)
        elif k == "ymag":
            if not _finite(v) or not v > 0:
                bad.append(f"camera.ymag: expected a positive number (an orthographic camera's half height), got {v!r}")
            else:
                out[k] = float(v)
        elif not _vec3(v):
            bad.append(f"camera.{k}: expected three numbers [x, y, z], got {v!r}")
        else:
            out[k] = tuple(float(x) for x in v)
    if "position" in out and "target" in out and out["position"] == out["target"]:
        bad.append("camera: position and target are the same point; move one")
    return out


def _material(mat, bad):
    if mat is None:
        return None
    if not isinstance(mat, dict) or not mat:
        bad.append(f"material: expected an object of Material fields (e.g. {{\"roughness\": 0.3}}), got {mat!r}")
        return None
    fields = [f.name for f in dataclasses.fields(Material)]
    unknown = [k for k in mat if k not in fields]
    for k in unknown:
        bad.append(f"material.{k}: not a Material field{_suggest(k, fields)}")
    if unknown:
        return None
    try:
        Material(**mat)
    except (TypeError, ValueError) as e:
        bad.append(f"material: {e}")
        return None
    return dict(mat)


def _file_render(scene) -> dict:
    """A TOML scene's [render] table (the job's options are merged over it), or {}; the scene file
    itself is checked when the job loads it."""
    if not (isinstance(scene, Path) and scene.suffix.lower() == ".toml"):
        return {}
    try:
        table = parse_toml(read_scene_text(scene), name=str(scene)).get("render", {})
    except InputError:  # reported when the job loads the file
        return {}
    return {k: v for k, v in table.items() if k in _RENDER_OPTIONS} if isinstance(table, dict) else {}


def _options(opts, bad, base=None):
    if not isinstance(opts, dict):
        bad.append(f"options: expected an object of RenderOptions keywords, got {opts!r}")
        return {}
    unknown = [k for k in opts if k not in _RENDER_OPTIONS]
    for k in unknown:
        bad.append(f"options.{k}: not a RenderOptions keyword{_suggest(k, tuple(_RENDER_OPTIONS))}")
    if unknown:
        return {}
    try:
        RenderOptions(**{**(base or {}), **opts})
    except (TypeError, ValueError) as e:
        with_file = " (merged over the scene file's [render] table)" if base else ""
        bad.append(f"options: {e}{with_file}")
        return {}
    return dict(opts)


def _output(out, bad):
    if not isinstance(out, dict):
        bad.append(f"output: expected an object with {', '.join(OUTPUT_FIELDS)}, got {out!r}")
        return ("png",), (), {}
    for k in out:
        if k not in OUTPUT_FIELDS:
            bad.append(f"output.{k}: unknown field{_suggest(k, OUTPUT_FIELDS)}")
    formats = out.get("formats", ["png"])
    if not isinstance(formats, list) or not formats or any(f not in FORMATS for f in formats) or len(set(formats)) != len(formats):
        bad.append(f"output.formats: expected a list of distinct formats from {', '.join(FORMATS)}, got {formats!r}")
        formats = ["png"]
    aovs = out.get("aovs", [])
    still = [a for a in AOVS if a != "motion"]  # (motion vectors need the next frame: `jaxpbr render --frames`)
    if isinstance(aovs, list) and "motion" in aovs:
        bad.append("output.aovs: 'motion' needs the next frame's scene; render sequences with motion vectors with "
                   "jaxpbr render ASSET --frames START:END:STEP --aov motion")
        aovs = []
    elif not isinstance(aovs, list) or any(a not in still for a in aovs):
        bad.append(f"output.aovs: expected a list from {', '.join(still)}, got {aovs!r}")
        aovs = []
    if aovs and "exr" not in formats:
        bad.append("output.aovs: AOVs are EXR layers; add 'exr' to output.formats")
    display = {}
    if "exposure" in out:
        if not _finite(out["exposure"]):
            bad.append(f"output.exposure: expected a finite number of EV stops, got {out['exposure']!r}")
        else:
            display["exposure"] = float(out["exposure"])
    for k, choices in (("tonemap", TONEMAPS), ("encoding", ENCODINGS)):
        if k in out:
            if out[k] not in choices:
                bad.append(f"output.{k}: {out[k]!r} is not one of {', '.join(choices)}")
            else:
                display[k] = out[k]
    if "bits" in out:
        if out["bits"] not in (8, 16) or isinstance(out["bits"], bool):
            bad.append(f"output.bits: expected 8 or 16, got {out['bits']!r}")
        else:
            display["bits"] = out["bits"]
    return tuple(formats), tuple(aovs), display


def factory_module_file(target: str, folder) -> Path | None:
    """The source file of a factory's module ('module:function') if it is a Python file inside
    `folder` (symbolic links resolved; found without importing it), else None: a factory runs code
    from the job file's folder, never an installed module."""
    import importlib.machinery

    top, _, rest = target.partition(":")[0].partition(".")
    spec = importlib.machinery.PathFinder.find_spec(top, [str(folder)])
    if spec is None or not spec.origin or spec.origin in ("built-in", "frozen"):
        return None
    p = Path(spec.origin)
    if rest:
        p = p.parent.joinpath(*rest.split(".")).with_suffix(".py")
    if not p.is_file():
        return None
    real, root = os.path.realpath(p), os.path.realpath(folder)
    return p if real.startswith(root.rstrip(os.sep) + os.sep) else None


def _factory_file(scene) -> Path | None:
    """The source file of a factory scene's module, for the key."""
    return factory_module_file(scene[1], scene[3]) if isinstance(scene, tuple) else None


def _key(obj: dict, files, stamps: dict) -> str:
    """What a job computes: its row and the size and modification time of each input file."""
    h = hashlib.sha256(json.dumps(obj, sort_keys=True).encode())
    for p in files:
        if p is None:
            continue
        if p not in stamps:
            st = p.stat()
            stamps[p] = (str(p), st.st_size, st.st_mtime_ns)
        h.update(repr(stamps[p]).encode())
    return h.hexdigest()
