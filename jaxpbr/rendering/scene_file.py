"""Scene files: a small, explicit TOML format -> `Scene` + render options + display settings.

    sf = load_scene("examples/scenes/spheres.toml")
    hdr = jaxpbr.render(sf.scene, **sf.options)              # linear HDR (H, W, 3)
    sf.output  # {"exposure": 0.0, "tonemap": "aces", "encoding": "srgb"}

The format is documented in docs/scene_format.md. Tables: [render] (RenderOptions keywords),
[output] (exposure / tone map / encoding), [camera], [scene] (background, ambient), [environment],
[[lights]], [materials.NAME], [[objects]]. Paths are relative to the TOML file's folder. Colours are
linear [r, g, b] lists or sRGB hex strings "#rrggbb" (decoded to linear with the IEC 61966-2-1
EOTF). Angles are in degrees and named `*_deg`. 8-bit/16-bit PNG colour textures (base colour,
emissive, sheen colour, specular colour) are sRGB-decoded to linear; the data textures
(metallic-roughness, occlusion, normal maps and the other extension textures) are linear. The glTF
material extensions (KHR_materials_clearcoat, _sheen, _specular, _ior, _anisotropy,
_emissive_strength, _transmission, _volume) are material keys named after the `Material` fields.

Every problem raises `jaxpbr.errors.InputError` (a ValueError) with one line:
"<file>: <key path>: <problem>; <fix>", e.g. "scene.toml: objects[2].radius: expected a number, got
a string ('1')". Key paths index arrays of tables from 0 (objects[0] is the first [[objects]]).
Loading reads every file it needs and builds every object before returning, so nothing is
rendered or written when it fails.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import stat
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from .._memory import MemoryLimitError, cube_bytes, require, texture_load_bytes
from ..color import TONEMAP_OPERATORS, TRANSFERS, srgb_decode, srgb_decode_np
from ..errors import InputError
from ..ibl.cubeio import load_environment
from ..ibl.diffuse import IRRADIANCE_METHODS
from ..ibl.specular import MAPPINGS
from ..io import image
from .renderer import RenderOptions
from .scene import (
    EXTENSION_TEXTURES,
    PROJECTIONS,
    Camera,
    Environment,
    Plane,
    Scene,
    Sphere,
    TexturedMaterial,
)
from ..shading.brdf_terms import MODELS, OPTION_CHOICES
from ..shading.lights import DirectionalLight, PointLight, SpotLight
from ..shading.material import EXTENSION_FIELDS, UNIT_FIELDS, Material

__all__ = ["MAX_NESTING", "MAX_SCENE_BYTES", "SceneFile", "hex_to_linear", "load_scene", "loads_scene"]

#: The largest scene file read, in bytes (8 MiB). A scene file describes a scene and names the files
#: of its meshes and images, so real ones are a few KB (the examples: under 4 KB); the cap keeps a
#: mistaken or hostile file (a multi-GB log renamed .toml) from being read whole into memory.
MAX_SCENE_BYTES = 8 << 20
#: The deepest nesting of tables and arrays read (the format's own deepest is 4: a colour in an
#: inline material of an [[objects]] entry). tomllib parses nested arrays and inline tables by
#: recursion and Python's stack ends a few hundred levels down, so deeper text is refused with a
#: message before it is parsed (a scan of its brackets outside strings and comments), and a document
#: nested deeper by table headers or dotted keys ([a.b.c...]) once parsed.
MAX_NESTING = 64

# Keys of each table (the documented format; docs/scene_format.md).
_TOP = ("render", "output", "camera", "scene", "environment", "lights", "materials", "objects")
# [render] is every RenderOptions keyword, [camera] every Camera field but the per-frame jitter, and
# the [0, 1] factors are Material's own list: derived, so that a new option is in the format at once.
_RENDER = tuple(f.name for f in dataclasses.fields(RenderOptions))
_RENDER_BOOLEANS = tuple(f.name for f in dataclasses.fields(RenderOptions) if "bool" in str(f.type))
_OUTPUT = ("exposure", "tonemap", "encoding")
_CAMERA = tuple(f.name for f in dataclasses.fields(Camera) if f.name != "jitter")
_SCENE = ("background", "ambient")
_ENVIRONMENT = ("file", "files", "face_size", "intensity", "rotation_deg", "show_background", "clamp_negative")
_LIGHTS = {
    "point": ("type", "position", "color", "intensity", "range"),
    "directional": ("type", "direction", "color", "intensity"),
    "spot": ("type", "position", "direction", "color", "intensity", "inner_cone_deg", "outer_cone_deg", "range"),
}
# The glTF material extensions' factors (KHR_materials_<group>): key -> Material field. Angles
# are in degrees in the file (anisotropy_rotation_deg -> Material.anisotropy_rotation, radians).
_EXT_FACTORS = {f: f for fs in EXTENSION_FIELDS.values() for f in fs}
_EXT_FACTORS["anisotropy_rotation_deg"] = _EXT_FACTORS.pop("anisotropy_rotation")
_UNIT_KEYS = UNIT_FIELDS
_TEXTURES = {
    # key: (decode sRGB for PNG, minimum channels, what it holds)
    "base_color_texture": (True, 3, "RGB base colour"),
    "metallic_roughness_texture": (False, 3, "glTF packing G = roughness, B = metallic in an RGB image"),
    "occlusion_texture": (False, 1, "R = ambient occlusion"),
    "normal_texture": (False, 3, "a tangent-space normal map (n + 1)/2 in an RGB image"),
    "emissive_texture": (True, 3, "RGB emission"),
}
# The extensions' textures, from TexturedMaterial's table (the KHR specs: sheen and specular colour
# are sRGB-encoded colour, the other extension textures linear data).
_TEXTURES |= {
    key: (any(ch == "rgb" for _field, ch in targets), n_min, what)
    for key, (_group, n_min, targets, what) in EXTENSION_TEXTURES.items()
}
_MATERIAL = (
    ("base_color", "metallic", "roughness", "occlusion", "emissive")
    + tuple(_EXT_FACTORS)
    + tuple(_TEXTURES)
    + ("normal_scale", "clearcoat_normal_scale")
)
_OBJECTS = {
    "sphere": ("type", "center", "radius", "material"),
    "plane": ("type", "point", "normal", "tangent", "uv_scale", "material"),
    "gltf": ("type", "path", "scene", "lights"),
}
# Keys that live in another table: a targeted hint beats a spelling suggestion.
_MOVED = {
    ("render", "exposure"): "[output]",
    ("render", "tonemap"): "[output]",
    ("render", "encoding"): "[output]",
    ("output", "model"): "[render]",
    ("camera", "background"): "[scene]",
    ("render", "background"): "[scene]",
    ("render", "ambient"): "[scene]",
}
_RENAMED = {
    ("environment", "background"): "show_background",
    ("environment", "rotation"): "rotation_deg",
    ("camera", "fov"): "fov_y_deg",
    ("camera", "fov_y"): "fov_y_deg",
    ("lights", "inner_cone_angle"): "inner_cone_deg",
    ("lights", "outer_cone_angle"): "outer_cone_deg",
}

_TOML_TYPES = {
    bool: "a boolean",
    int: "an integer",
    float: "a float",
    str: "a string",
    list: "an array",
    dict: "a table",
}


@dataclasses.dataclass(frozen=True)
class SceneFile:
    """A loaded scene file.

    scene: the `jaxpbr.Scene`.
    options: `RenderOptions` keywords given in [render] (only those given; pass as
        `render(scene, **options)`).
    output: display settings, resolved with their defaults: {"exposure": EV stops (float),
        "tonemap": a `jaxpbr.color.TONEMAP_OPERATORS` name, "encoding": a `jaxpbr.color.TRANSFERS`
        name}. Defaults: exposure 0, and aces + srgb (gltf) or reinhard + gamma2.2 (learnopengl).
    materials: the named materials of [materials.*] (Material or TexturedMaterial), by name.
    path: the TOML file (None for `loads_scene`).
    """

    scene: Any
    options: dict
    output: dict
    materials: dict = dataclasses.field(default_factory=dict)
    path: Path | None = None


def load_scene(path) -> SceneFile:
    """Read a scene TOML file (see docs/scene_format.md); paths inside it are relative to its folder.

    Raises `InputError` with a one-line message naming the file, the key path and the fix. Only a
    regular file of at most `MAX_SCENE_BYTES` is read (a FIFO or a device is refused without
    waiting on it).
    """
    p = Path(os.fspath(path))
    text = read_scene_text(p)
    sf = loads_scene(text, p.parent, name=str(p))
    return dataclasses.replace(sf, path=p)


def read_scene_text(path) -> str:
    """The text of a scene file: a regular file of at most `MAX_SCENE_BYTES` bytes of UTF-8, not an
    image (by name or by content); else `InputError` naming the file and the fix."""
    p = Path(os.fspath(path))
    if p.suffix.lower() in image.SUPPORTED_EXTENSIONS:
        raise InputError(_an_image(p))

    def not_an_image(head: bytes) -> None:
        if head.startswith(_IMAGE_MAGIC):
            raise InputError(_an_image(p))

    data = read_regular_file(p, limit=MAX_SCENE_BYTES, what="scene file", head=not_an_image,
                             missing="check the path", other="pass a .toml scene file",
                             smaller="a scene file names its meshes and images, which are read from their own files")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{p}: not UTF-8 text ({e.reason} at byte {e.start}); save the file as UTF-8") from None


def _an_image(p: Path) -> str:
    return (f"{str(p)!r} is an image, not a scene file; jaxpbr render takes a .toml scene description "
            f"(docs/scene_format.md): put the image in one, e.g. [environment] file = {p.name!r}")


#: The first bytes of the image formats jaxpbr reads (EXR, PNG, Radiance HDR).
_IMAGE_MAGIC = (b"\x76\x2f\x31\x01", b"\x89PNG", b"#?RADIANCE", b"#?RGBE")
_NONBLOCK = getattr(os, "O_NONBLOCK", 0)  # POSIX: opening a FIFO for reading does not wait for a writer
_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def read_regular_file(path, *, limit: int, what: str, missing: str, other: str, smaller: str, head=None) -> bytes:
    """The bytes of an input file that must be a regular file of at most `limit` bytes, read with
    a bounded read; anything else raises `InputError` naming `what` and the fix.

    The file is opened without blocking (a FIFO with no writer does not hold up the open), checked
    on the open descriptor (fstat: a regular file, its declared size), then read to at most
    `limit + 1` bytes (a file that grows while it is read, or a /proc-like file that declares no
    size, is still refused). `missing`, `other`, `smaller`: the fixes for a path that does not
    exist, is not a regular file, or is too large. `head`: optional callable given the file's
    first bytes (up to 16) before its size is checked, to refuse a file by its content.
    """
    p = os.fspath(path)
    flags = os.O_RDONLY | _NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(p, flags)
    except FileNotFoundError:
        raise InputError(f"{what} {p!r} does not exist; {missing}") from None
    except IsADirectoryError:  # Windows
        raise InputError(f"{what} {p!r} is a folder, not a regular file; {other}") from None
    except OSError as e:
        raise InputError(f"cannot read {what} {p!r}: {e.strerror or e}; check its permissions") from None
    too_big = (f"{what} {p!r} is larger than {limit >> 20} MiB ({limit} bytes), the most a {what} may "
               f"hold; {smaller}")
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = next((k for test, k in _KINDS if test(st.st_mode)), "not a regular file")
            raise InputError(f"{what} {p!r} is {kind}, not a regular file; {other}")
        data = _read_at_most(fd, 16)
        if head is not None:
            head(data)
        if st.st_size > limit:
            raise InputError(too_big)
        data += _read_at_most(fd, limit + 1 - len(data))
    except OSError as e:
        raise InputError(f"cannot read {what} {p!r}: {e.strerror or e}; check the file") from None
    finally:
        os.close(fd)
    if len(data) > limit:
        raise InputError(too_big)
    return data


def _read_at_most(fd: int, n: int) -> bytes:
    parts, left = [], n
    while left > 0:
        b = os.read(fd, min(left, 1 << 20))
        if not b:
            break
        parts.append(b)
        left -= len(b)
    return b"".join(parts)


# The strings and comments of TOML text, whose brackets nest nothing: multi-line basic and literal
# strings (up to two quotes of their content may stand before the closing three), one-line basic
# and literal strings, comments (each replaced by a letter for the scans). A quote left over opens
# an unterminated string: the scans stop there, where tomllib stops with a syntax error.
_TOML_INERT = re.compile(
    r'"""[^"\\]*(?:(?:\\.|"(?!""))[^"\\]*)*"""(?:""?)?'
    r"|'''[^']*(?:'(?!'')[^']*)*'''(?:''?)?"
    r'|"[^"\\\n]*(?:\\.[^"\\\n]*)*"'
    r"|'[^'\n]*'"
    r"|#[^\n]*",
    re.DOTALL,
)
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")
# A dotted key (or table header) of more than MAX_NESTING parts, in text whose strings are replaced
# by a letter: tomllib checks each prefix of a dotted key, in time and memory quadratic in its parts
# (a key of 100,000 parts took all the memory of the machine).
_LONG_KEY = re.compile(rf"(?<![\w-])(?:[\w-]+[ \t]*\.[ \t]*){{{MAX_NESTING},}}[\w-]", re.ASCII)


def bracket_depth(brackets: str, *, stop: int | None = None) -> int:
    """The deepest nesting of a string of brackets ('[' and '{' open, ']' and '}' close): the
    largest count of opens less closes over its prefixes, summed in blocks with NumPy (no
    recursion, no Python loop per character). `stop`: return once the depth passes it."""
    depth = best = 0
    for i in range(0, len(brackets), 1 << 20):
        a = np.frombuffer(brackets[i : i + (1 << 20)].encode("ascii"), np.uint8)
        run = np.cumsum(np.where((a == ord("[")) | (a == ord("{")), 1, -1)) + depth
        best = max(best, int(run.max()))
        depth = int(run[-1])
        if stop is not None and best > stop:
            break
    return best


def parse_toml(text: str, *, name: str) -> dict:
    """TOML text -> its document, nested at most `MAX_NESTING` levels (the brackets are checked
    before tomllib, which recurses, parses them), a key or table given twice refused (by tomllib);
    else `InputError` "<name>: ...". """
    # Fewer brackets (dots) than the cap cannot nest deeper (make a longer dotted key).
    if text.count("[") + text.count("{") > MAX_NESTING or text.count(".") >= MAX_NESTING:
        inert = _TOML_INERT.sub("s", text)
        inert = inert[: min((k for k in (inert.find('"'), inert.find("'")) if k >= 0), default=len(inert))]
        if bracket_depth(_NOT_BRACKET.sub("", inert), stop=MAX_NESTING) > MAX_NESTING:
            raise InputError(_too_deep(name, f"more than {MAX_NESTING}"))
        if _LONG_KEY.search(inert):
            raise InputError(f"{name}: a dotted key or table name of more than {MAX_NESTING} parts (tables nested "
                             f"that deep are not read, and a scene nests 4: docs/scene_format.md); fix the file")
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{name}: invalid TOML: {_one_line(e)}; fix the syntax (format: docs/scene_format.md)") from None
    except RecursionError:  # a backstop: the scan above finds any nesting that gets this deep
        raise InputError(_too_deep(name, "too many")) from None
    depth = _document_depth(doc)
    if depth > MAX_NESTING:
        raise InputError(_too_deep(name, f"more than {MAX_NESTING}"))
    return doc


def _too_deep(name: str, levels: str) -> str:
    return (f"{name}: tables and arrays nested {levels} levels deep (at most {MAX_NESTING} are read, and a "
            f"scene nests 4: docs/scene_format.md); fix the file")


def _document_depth(doc) -> int:
    """The nesting depth of a parsed document (its tables and arrays are level 1, what they hold
    level 2, ...), walked with a stack; stops once past `MAX_NESTING`."""
    best = 0
    stack = [(doc, 0)]
    while stack:
        x, d = stack.pop()
        best = max(best, d)
        if best > MAX_NESTING:
            break
        for v in x.values() if isinstance(x, dict) else x:
            if isinstance(v, (dict, list)):
                stack.append((v, d + 1))
    return best


def loads_scene(text: str, base_dir=".", *, name: str = "<string>") -> SceneFile:
    """Parse scene TOML `text`; relative paths resolve against `base_dir`; `name` prefixes errors."""
    return _Loader(name, Path(os.fspath(base_dir))).load(text)


def hex_to_linear(s: str) -> tuple[float, float, float]:
    """sRGB hex colour "#rrggbb" -> linear RGB floats by the IEC 61966-2-1 EOTF of
    `jaxpbr.color.srgb_decode_np` (colour-science), with v = code/255."""
    if not isinstance(s, str) or not re.fullmatch(r"#[0-9a-fA-F]{6}", s):
        raise ValueError(f'expected an sRGB hex colour "#rrggbb", got {s!r}')
    codes = np.array([int(s[i : i + 2], 16) for i in (1, 3, 5)], np.float64) / 255.0
    return tuple(float(c) for c in srgb_decode_np(codes))


# ------------------------------------------------------------------------------------------
# The loader
# ------------------------------------------------------------------------------------------


def _type_name(x) -> str:
    for t, n in _TOML_TYPES.items():
        if type(x) is t:
            return n
    return f"a {type(x).__name__}"


def _shown(x) -> str:
    r = repr(x)
    return r if len(r) <= 40 else r[:37] + "..."


def _one_line(e: BaseException) -> str:
    s = str(e).strip() or type(e).__name__
    return " ".join(s.split())


def _join(path: str, key) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else str(key)


class _Loader:
    def __init__(self, name: str, base_dir: Path):
        self.name = name
        self.base_dir = base_dir
        self._images: dict = {}

    # -- errors ---------------------------------------------------------------------------

    def fail(self, path: str, msg: str):
        raise InputError(f"{self.name}: {path}: {msg}" if path else f"{self.name}: {msg}")

    def build(self, path: str, fn, *args, **kwargs):
        """Call a constructor; its ValueError/TypeError comes back prefixed with the key path of
        the field it names (e.g. "Sphere.radius ..." -> "objects[0].radius: Sphere.radius ...")."""
        try:
            return fn(*args, **kwargs)
        except (ValueError, TypeError) as e:
            msg = _one_line(e)
            m = re.match(r"(?:\w+\.)?(\w+)\b", msg)
            key = m.group(1) if m else None
            if key and key in kwargs:
                self.fail(_join(path, key), msg)
            self.fail(path, msg)

    def check_keys(self, table: dict, allowed, path: str, kind: str | None = None):
        section = re.sub(r"\[\d+\]$", "", path).split(".")[0]
        for key in table:
            if key in allowed:
                continue
            where = f"a key of {kind}" if kind else f"a key of [{path}]" if path else "a top-level table"
            hint = ""
            if (section, key) in _MOVED:
                hint = f"; {key!r} belongs in {_MOVED[(section, key)]}"
            elif (section, key) in _RENAMED and _RENAMED[(section, key)] in allowed:
                hint = f"; did you mean {_RENAMED[(section, key)]!r}?"
            else:
                close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
                if not close:
                    close = [a for a in allowed if a.startswith(key) or key.startswith(a)][:1]
                if close:
                    hint = f"; did you mean {close[0]!r}?"
                else:
                    hint = f"; valid keys: {', '.join(allowed)}"
            if not path:
                self.fail(key, f"unknown table{hint.replace('valid keys', 'valid tables')}")
            self.fail(_join(path, key), f"unknown key (not {where}){hint}")

    # -- typed values ---------------------------------------------------------------------

    def table(self, x, path: str, what: str = "a table") -> dict:
        if not isinstance(x, dict):
            self.fail(path, f"expected {what}, got {_type_name(x)}")
        return x

    def number(self, x, path: str, *, lo=None, hi=None, open_lo=False, allow_inf=False) -> float:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            self.fail(path, f"expected a number, got {_type_name(x)} ({_shown(x)})")
        x = float(x)
        if math.isnan(x) or (math.isinf(x) and not allow_inf):
            self.fail(path, f"expected a finite number, got {x}")
        if lo is not None and (x <= lo if open_lo else x < lo):
            self.fail(path, f"must be {'>' if open_lo else '>='} {lo:g}, got {x:g}")
        if hi is not None and x > hi:
            self.fail(path, f"must be <= {hi:g}, got {x:g}")
        return x

    def integer(self, x, path: str, lo: int = 1) -> int:
        if isinstance(x, bool) or not isinstance(x, int):
            if isinstance(x, float) and x.is_integer():
                self.fail(path, f"expected an integer, got a float ({x!r}); write {int(x)}")
            self.fail(path, f"expected an integer, got {_type_name(x)} ({_shown(x)})")
        if x < lo:
            self.fail(path, f"must be an integer >= {lo}, got {x}")
        return x

    def boolean(self, x, path: str) -> bool:
        if not isinstance(x, bool):
            self.fail(path, f"expected true or false, got {_type_name(x)} ({_shown(x)})")
        return x

    def choice(self, x, path: str, choices) -> str:
        if not isinstance(x, str):
            self.fail(path, f"expected a string, one of {', '.join(map(repr, choices))}; got {_type_name(x)}")
        if x not in choices:
            close = difflib.get_close_matches(x, choices, n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            self.fail(path, f"unknown value {x!r}; choose one of {', '.join(map(repr, choices))}{hint}")
        return x

    def vector(self, x, path: str, n: int = 3) -> tuple[float, ...]:
        if not isinstance(x, list):
            self.fail(path, f"expected an array of {n} numbers, got {_type_name(x)} ({_shown(x)})")
        if len(x) != n:
            self.fail(path, f"expected an array of {n} numbers, got {len(x)} ({_shown(x)})")
        return tuple(self.number(v, _join(path, i)) for i, v in enumerate(x))

    def direction(self, x, path: str) -> tuple[float, ...]:
        v = self.vector(x, path)
        if not any(v):
            self.fail(path, "must be a non-zero vector")
        return v

    def colour(self, x, path: str, *, hi=None) -> tuple[float, ...]:
        if isinstance(x, str):
            try:
                return hex_to_linear(x)
            except ValueError:
                self.fail(path, f'expected [r, g, b] (linear) or an sRGB hex string "#rrggbb", got {x!r}')
        if not isinstance(x, list) or len(x) != 3:
            got = f"{len(x)} numbers" if isinstance(x, list) else f"{_type_name(x)} ({_shown(x)})"
            self.fail(path, f'expected [r, g, b] (linear) or an sRGB hex string "#rrggbb", got {got}')
        return tuple(self.number(v, _join(path, i), lo=0.0, hi=hi) for i, v in enumerate(x))

    def string(self, x, path: str) -> str:
        if not isinstance(x, str):
            self.fail(path, f"expected a string, got {_type_name(x)} ({_shown(x)})")
        return x

    def file(self, x, path: str) -> Path:
        s = self.string(x, path)
        p = Path(os.path.expanduser(s))
        if not p.is_absolute():
            p = self.base_dir / p
        p = p.resolve()
        if not p.is_file():
            what = "is not a file" if p.exists() else "does not exist"
            self.fail(path, f"file {str(p)!r} {what} (paths are relative to the scene file's folder); fix the path")
        return p

    # -- tables ---------------------------------------------------------------------------

    def load(self, text: str) -> SceneFile:
        if not isinstance(text, str):
            raise TypeError(f"loads_scene expects TOML text (str), got {type(text).__name__}")
        doc = parse_toml(text, name=self.name)
        self.check_keys(doc, _TOP, "")
        options = self.render_options(self.table(doc.get("render", {}), "render"))
        output = self.output(self.table(doc.get("output", {}), "output"), options.get("model", "gltf"))
        camera = self.camera(self.table(doc.get("camera", {}), "camera"))
        world = self.table(doc.get("scene", {}), "scene")
        self.check_keys(world, _SCENE, "scene")
        background = self.colour(world.get("background", [0.0, 0.0, 0.0]), "scene.background")
        ambient = self.number(world.get("ambient", 0.0), "scene.ambient", lo=0.0)
        lights = self.lights(doc.get("lights", []))
        materials = self.materials(self.table(doc.get("materials", {}), "materials"))
        self.asset_lights: list = []
        objects = self.objects(doc.get("objects", []), materials)
        lights = tuple(lights) + tuple(self.asset_lights)
        env = None
        if "environment" in doc:
            env = self.environment(self.table(doc["environment"], "environment"), options)
        scene = self.build(
            "", Scene, camera=camera, objects=objects, lights=lights, environment=env,
            background=background, ambient=ambient,
        )
        return SceneFile(scene=scene, options=options, output=output, materials=materials)

    def render_options(self, t: dict) -> dict:
        self.check_keys(t, _RENDER, "render")
        out: dict = {}
        for key, x in t.items():
            p = _join("render", key)
            if key == "model":
                out[key] = self.choice(x, p, MODELS)
            elif key in _RENDER_BOOLEANS:
                out[key] = self.boolean(x, p)
            elif key == "smith":
                out[key] = self.choice(x, p, OPTION_CHOICES["smith"])
            elif key == "irradiance_method":
                out[key] = self.choice(x, p, IRRADIANCE_METHODS)
            elif key == "mapping":
                out[key] = self.choice(x, p, MAPPINGS)
            elif key == "dtype":
                out[key] = self.choice(x, p, ("float32", "float64"))
            else:  # sizes and sample counts
                out[key] = self.integer(x, p)
        self.build("render", RenderOptions, **out)
        return out

    def output(self, t: dict, model: str) -> dict:
        self.check_keys(t, _OUTPUT, "output")
        lo = model == "learnopengl"
        out = {
            "exposure": 0.0,
            "tonemap": "reinhard" if lo else "aces",
            "encoding": "gamma2.2" if lo else "srgb",
        }
        if "exposure" in t:
            out["exposure"] = self.number(t["exposure"], "output.exposure")
        if "tonemap" in t:
            out["tonemap"] = self.choice(t["tonemap"], "output.tonemap", TONEMAP_OPERATORS)
        if "encoding" in t:
            out["encoding"] = self.choice(t["encoding"], "output.encoding", TRANSFERS)
        return out

    def camera(self, t: dict):
        self.check_keys(t, _CAMERA, "camera")
        kw: dict = {}
        for key in ("position", "target", "up"):
            if key in t:
                kw[key] = self.vector(t[key], f"camera.{key}")
        if "fov_y_deg" in t:
            kw["fov_y_deg"] = self.number(t["fov_y_deg"], "camera.fov_y_deg", lo=0.0, open_lo=True, hi=179.0)
        if "projection" in t:
            kw["projection"] = self.choice(t["projection"], "camera.projection", PROJECTIONS)
        if "ymag" in t:
            kw["ymag"] = self.number(t["ymag"], "camera.ymag", lo=0.0, open_lo=True)
        for key in ("width", "height", "supersample"):
            if key in t:
                kw[key] = self.integer(t[key], f"camera.{key}")
        return self.build("camera", Camera, **kw)

    def environment(self, t: dict, options: dict):
        self.check_keys(t, _ENVIRONMENT, "environment")
        if ("file" in t) == ("files" in t):
            self.fail(
                "environment",
                'give exactly one of file = "panorama.hdr" (or "procedural:sky") and files = [6 face images]'
                + ("" if "file" not in t else ", not both"),
            )
        face_size = None
        if "face_size" in t:
            face_size = self.integer(t["face_size"], "environment.face_size")
            procedural = str(t.get("file", "")).startswith("procedural:")
            try:  # before any work (a huge size aborted inside XLA)
                require(f"a {face_size}^2 environment cube", cube_bytes(face_size, supersample=4 if procedural else None),
                        names={"face_size": "it"})
            except MemoryLimitError as e:
                self.fail("environment.face_size", _one_line(e))
        clamp = self.boolean(t.get("clamp_negative", False), "environment.clamp_negative")
        if "file" in t:
            src = self.string(t["file"], "environment.file")
            key = "environment.file"
            if src.startswith("procedural:"):
                paths = [src]
                if src != "procedural:sky":
                    self.fail(key, f"unknown procedural environment {src!r}; the one available is 'procedural:sky'")
            else:
                paths = [str(self.file(src, key))]
        else:
            key = "environment.files"
            files = t["files"]
            if not isinstance(files, list) or len(files) != 6:
                got = f"{len(files)} paths" if isinstance(files, list) else _type_name(files)
                self.fail(key, f"expected an array of 6 face images (+X, -X, +Y, -Y, +Z, -Z), got {got}")
            paths = [str(self.file(f, _join(key, i))) for i, f in enumerate(files)]
        intensity = self.number(t.get("intensity", 1.0), "environment.intensity", lo=0.0)
        rotation = self.number(t.get("rotation_deg", 0.0), "environment.rotation_deg")
        show = self.boolean(t.get("show_background", True), "environment.show_background")
        try:
            cube = load_environment(paths, face_size=face_size, clamp_negative=clamp)
        except InputError as e:
            msg = _one_line(e).replace("--clamp-negative", "clamp_negative = true").replace("--face-size", "face_size")
            self.fail(key, msg)
        except (ValueError, OSError) as e:
            self.fail(key, f"cannot load the environment: {_one_line(e)}")
        ps = options.get("prefilter_size")
        S = cube.face_size
        if ps is not None and (ps > S or S % ps or (S // ps) & (S // ps - 1)):
            self.fail(
                "render.prefilter_size",
                f"{ps} must be the environment's face size {S} divided by a power of two (e.g. {max(S // 2, 1)})",
            )
        return self.build(
            "environment", Environment, radiance=cube, intensity=intensity,
            rotation=math.radians(rotation), show_background=show,
        )

    def lights(self, arr) -> tuple:
        if isinstance(arr, dict):
            self.fail("lights", "expected an array of tables: write each light as [[lights]], not [lights]")
        if not isinstance(arr, list):
            self.fail("lights", f"expected an array of tables ([[lights]]), got {_type_name(arr)}")
        out = []
        for i, t in enumerate(arr):
            path = f"lights[{i}]"
            t = self.table(t, path, "a table ([[lights]])")
            if "type" not in t:
                self.fail(path, 'missing key "type"; add type = "point", "directional" or "spot"')
            kind = self.choice(t["type"], f"{path}.type", tuple(_LIGHTS))
            self.check_keys(t, _LIGHTS[kind], path, f"a {kind} light")
            kw: dict = {}
            if "color" in t:
                kw["color"] = self.colour(t["color"], f"{path}.color")
            if "intensity" in t:
                kw["intensity"] = self.number(t["intensity"], f"{path}.intensity", lo=0.0)
            if "range" in t:
                kw["range"] = self.number(t["range"], f"{path}.range", lo=0.0, open_lo=True, allow_inf=True)
            for key in ("position", "direction"):
                if key in _LIGHTS[kind]:
                    if key not in t:
                        self.fail(path, f"a {kind} light needs {key} = [x, y, z]")
                    kw[key] = (self.direction if key == "direction" else self.vector)(t[key], f"{path}.{key}")
            if kind == "point":
                out.append(self.build(path, PointLight, **kw))
            elif kind == "directional":
                out.append(self.build(path, DirectionalLight, **kw))
            else:
                inner = self.number(t.get("inner_cone_deg", 0.0), f"{path}.inner_cone_deg", lo=0.0)
                outer = self.number(t.get("outer_cone_deg", 45.0), f"{path}.outer_cone_deg", lo=0.0, open_lo=True, hi=90.0)
                if inner >= outer:
                    self.fail(
                        f"{path}.inner_cone_deg",
                        f"must be smaller than outer_cone_deg ({outer:g}), got {inner:g}; both are in degrees",
                    )
                kw.update(inner_cone_angle=math.radians(inner), outer_cone_angle=math.radians(outer))
                out.append(self.build(path, SpotLight, **kw))
        return tuple(out)

    def materials(self, t: dict) -> dict:
        what = "a table: define each material as [materials.NAME] with its keys inside"
        return {name: self.material(self.table(m, f"materials.{name}", what), f"materials.{name}") for name, m in t.items()}

    def material(self, t: dict, path: str):
        if "anisotropy_rotation" in t:
            self.fail(
                f"{path}.anisotropy_rotation",
                "unknown key: angles are in degrees in scene files; write anisotropy_rotation_deg = <degrees>",
            )
        self.check_keys(t, _MATERIAL, path, "a material")
        kw: dict = {}
        if "base_color" in t:
            kw["base_color"] = self.colour(t["base_color"], f"{path}.base_color", hi=1.0)
        for key in _UNIT_KEYS:
            if key in t:
                kw[key] = self.number(t[key], f"{path}.{key}", lo=0.0, hi=1.0)
        for key in ("sheen_color", "attenuation_color"):
            if key in t:
                kw[key] = self.colour(t[key], f"{path}.{key}", hi=1.0)
        if "specular_color" in t:
            kw["specular_color"] = self.colour(t["specular_color"], f"{path}.specular_color")
        for key in ("emissive_strength", "thickness"):
            if key in t:
                kw[key] = self.number(t[key], f"{path}.{key}", lo=0.0)
        if "ior" in t:
            ior = self.number(t["ior"], f"{path}.ior")
            if ior != 0.0 and ior < 1.0:
                self.fail(
                    f"{path}.ior",
                    f"must be >= 1 (an index of refraction; 1.5 is glass and plastic), or 0 for glTF's "
                    f"specular-glossiness mode, got {ior:g}",
                )
            kw["ior"] = ior
        if "anisotropy_rotation_deg" in t:
            deg = self.number(t["anisotropy_rotation_deg"], f"{path}.anisotropy_rotation_deg")
            kw["anisotropy_rotation"] = math.radians(deg)
        if "attenuation_distance" in t:
            kw["attenuation_distance"] = self.number(
                t["attenuation_distance"], f"{path}.attenuation_distance", lo=0.0, open_lo=True, allow_inf=True
            )
        # KHR_materials_emissive_strength stays its own field (Material.emission() = emissive x
        # strength); alone it keeps the core shading path (Material.layered is False), so every
        # model and multiscatter shade it.
        if "emissive" in t:
            kw["emissive"] = self.colour(t["emissive"], f"{path}.emissive")
        elif "emissive_texture" in t:
            kw["emissive"] = (1.0,) * 3  # a texture alone emits its own colour (factor 1)
        self.extension_texture_factors(t, path, kw)
        factors = self.build(path, Material, **kw)
        tex = {key: self.texture(t[key], f"{path}.{key}", key) for key in _TEXTURES if key in t}
        for scale, needs in (("normal_scale", "normal_texture"), ("clearcoat_normal_scale", "clearcoat_normal_texture")):
            if scale in t:
                if needs not in t:
                    self.fail(f"{path}.{scale}", f"has no effect without {needs}; add one or remove it")
                tex[scale] = self.number(t[scale], f"{path}.{scale}")
        if not tex:
            return factors
        return self.build(path, TexturedMaterial, factors=factors, **tex)

    def extension_texture_factors(self, t: dict, path: str, kw: dict):
        """An extension texture multiplies its factor (glTF). A factor whose default is 0 must be
        given (the texture would have no effect); one whose default is not (specular = 1,
        specular_color = [1, 1, 1]) takes it, which makes the extension present."""
        for key, (group, _c, targets, _h) in EXTENSION_TEXTURES.items():
            if key not in t:
                continue
            fields = [f for f, _ in targets] or [next(iter(EXTENSION_FIELDS[group]))]  # the coat normal: clearcoat
            for field in fields:
                if field in t:
                    continue
                neutral = EXTENSION_FIELDS[group][field]
                if not np.any(neutral):
                    one = "[1.0, 1.0, 1.0]" if isinstance(neutral, tuple) else "1.0"
                    what = "the texture multiplies it" if targets else "it scales the coat"
                    self.fail(
                        f"{path}.{key}",
                        f"has no effect without {field}, which defaults to 0 (KHR_materials_{group}; {what}); "
                        f"add {field} = {one} or remove the texture",
                    )
                kw[field] = neutral

    def texture(self, x, path: str, key: str):
        srgb, min_c, holds = _TEXTURES[key]
        p = self.file(x, path)
        ext = p.suffix.lower()
        if ext not in image.SUPPORTED_EXTENSIONS:
            self.fail(path, f"{str(p)!r} has an unsupported extension; use one of {', '.join(image.SUPPORTED_EXTENSIONS)}")
        decode = srgb and ext == ".png"
        cache_key = (p, decode, srgb)
        if cache_key in self._images:
            return self._images[cache_key]
        dims = image.dimensions(p)
        if dims is not None:  # before reading it: the load's float copies are ~60 B per value
            try:
                require(f"loading a {dims[1]}x{dims[0]} texture", texture_load_bytes(dims), names={"texture": "its resolution"})
            except MemoryLimitError as e:
                self.fail(path, _one_line(e))
        try:
            img = np.asarray(image.read(p), np.float32)
        except Exception as e:  # noqa: BLE001 -- corrupt / unreadable: any reader error becomes one line
            self.fail(path, f"cannot read {str(p)!r}: {_one_line(e)}")
        if img.ndim == 2:
            img = img[..., None]
        C = img.shape[-1]
        if min_c == 3 and srgb:
            img = img[..., :3] if C >= 3 else np.repeat(img[..., :1], 3, axis=-1)  # drop alpha / grey -> RGB
        elif C < min_c:
            self.fail(path, f"{str(p)!r} has {C} channel(s); it must hold {holds}")
        if not np.all(np.isfinite(img)):
            self.fail(path, f"{str(p)!r} contains NaN or Inf; fix the image")
        if decode:
            img = np.asarray(srgb_decode(img), np.float32)
        self._images[cache_key] = img
        return img

    def objects(self, arr, materials: dict) -> tuple:
        if isinstance(arr, dict):
            self.fail("objects", "expected an array of tables: write each object as [[objects]], not [objects]")
        if not isinstance(arr, list):
            self.fail("objects", f"expected an array of tables ([[objects]]), got {_type_name(arr)}")
        if not arr:
            self.fail("objects", 'the scene has no objects; add at least one [[objects]] with type = "sphere", "plane" or "gltf"')
        out = []
        for i, t in enumerate(arr):
            path = f"objects[{i}]"
            t = self.table(t, path, "a table ([[objects]])")
            if "type" not in t:
                self.fail(path, 'missing key "type"; add type = "sphere", "plane" or "gltf"')
            kind = self.choice(t["type"], f"{path}.type", tuple(_OBJECTS))
            self.check_keys(t, _OBJECTS[kind], path, f"a {kind}")
            if kind == "gltf":
                out.extend(self.gltf(t, path))
                continue
            kw: dict = {}
            if "material" in t:
                kw["material"] = self.object_material(t["material"], f"{path}.material", materials)
            if kind == "sphere":
                if "center" in t:
                    kw["center"] = self.vector(t["center"], f"{path}.center")
                if "radius" in t:
                    kw["radius"] = self.number(t["radius"], f"{path}.radius", lo=0.0, open_lo=True)
                out.append(self.build(path, Sphere, **kw))
            else:
                if "point" in t:
                    kw["point"] = self.vector(t["point"], f"{path}.point")
                if "normal" in t:
                    kw["normal"] = self.direction(t["normal"], f"{path}.normal")
                if "tangent" in t:
                    kw["tangent"] = self.direction(t["tangent"], f"{path}.tangent")
                if "uv_scale" in t:
                    kw["uv_scale"] = self.number(t["uv_scale"], f"{path}.uv_scale", lo=0.0, open_lo=True)
                out.append(self.build(path, Plane, **kw))
        return tuple(out)

    def gltf(self, t: dict, path: str) -> list:
        """The meshes of a glTF asset (world space, its own materials), and its lights when
        `lights` (default true) -- the same conversion as `jaxpbr.load_gltf`."""
        from ..io.gltf import read_gltf
        from .gltf_scene import lights_from_asset, meshes_from_asset

        if "path" not in t:
            self.fail(path, 'missing key "path"; add path = "model.glb" (relative to the scene file)')
        f = self.file(t["path"], f"{path}.path")
        which = None
        if "scene" in t:
            which = int(self.number(t["scene"], f"{path}.scene", lo=0.0))
        try:
            asset = read_gltf(f, scene=which)
        except InputError as e:
            self.fail(f"{path}.path", str(e))
        if not asset.primitives:
            self.fail(f"{path}.path", f"{f.name} has no triangle geometry in the scene loaded; pick another scene (scene = N)")
        meshes = meshes_from_asset(asset, set())
        if self.boolean(t.get("lights", True), f"{path}.lights"):
            self.asset_lights.extend(lights_from_asset(asset))
        return meshes

    def object_material(self, x, path: str, materials: dict):
        if isinstance(x, dict):
            return self.material(x, path)
        if not isinstance(x, str):
            self.fail(path, f"expected a material name (string) or an inline table, got {_type_name(x)}")
        if x not in materials:
            if not materials:
                self.fail(path, f"unknown material {x!r}: no [materials.*] are defined; add [materials.{x}]")
            close = difflib.get_close_matches(x, list(materials), n=1, cutoff=0.6)
            hint = f"did you mean {close[0]!r}? " if close else ""
            self.fail(path, f"unknown material {x!r}; {hint}defined: {', '.join(map(repr, materials))}")
        return materials[x]
