"""The glTF 2.0 JSON document checked against the schema's types and ranges before the loader
reads any value of it (docs/gltf.md, "Untrusted assets").

`check_schema(path, doc)` walks the JSON as `json.loads` returned it, following a declarative table
of the glTF 2.0 schema (`_ROOT`: object kind -> property -> type, range, enum, reference) for the
properties jaxpbr reads, core and extensions, and raises `InputError` at the first value that does
not fit, naming its JSON pointer (RFC 6901), the value (abbreviated), what was expected and a fix:

    glTF file 'a.gltf': accessor 3 (/accessors/3/count): count "3" is a string; expected an
    integer >= 1. Fix: repair or re-export the asset (the Khronos glTF-Validator names the problem)

What is checked, as the schema says: JSON types (an integer is a JSON number without a fraction:
3.0 and true are not integers; numbers are finite: the NaN and Infinity literals that Python's json
accepts are refused, and so are integers beyond float64), ranges, enums, fixed array lengths,
unique items, required properties, `primitives` (minItems 1) and `attributes` (minProperties 1);
and the plain index references (an index below the length of the array it names: "names accessor
12, which does not exist (the file has 4)"). Beyond the schema: a perspective camera's yfov must be
below pi, its zfar above its znear, and a spot light's inner cone angle below its outer one.

What is left alone: unknown properties, `extras` and unknown extensions (not checked); the node
graph's shape (cycles, several parents: the loader's traversal refuses those); a primitive without
POSITION (the schema allows it; the loader skips it with a note); the schema's other structural
rules (an image with both or neither of uri and bufferView, a camera with both projections, a node
with both matrix and TRS, empty top-level arrays or scene/children lists: harmless, or refused by
the loader where it matters).

The walk follows the table, whose depth is fixed (at most 6 objects deep), never the document's own
nesting; arrays are iterated. Measured (one core, CPython 3.11), 10^6 nodes: 0.3 s when each names
a mesh, 0.6 s with a name and a translation, 1.5 s with translation, rotation, scale, name and
mesh or a 16-number matrix (json.loads of such a file takes longer than its check).
"""

from __future__ import annotations

import json
import math
import sys

from ._binary import fail, loc, pointer

__all__ = ["check_schema"]

_FIX = "repair or re-export the asset (the Khronos glTF-Validator names the problem)"
_FMAX = sys.float_info.max
_SHORT = 40  # characters of a value shown in a message


# ---------------------------------------------------------------------------------------------
# Messages
# ---------------------------------------------------------------------------------------------
def _render(v, budget: int) -> str:
    """A JSON rendering of v that stops soon after `budget` characters (containers are cut with
    '...'); each nesting level costs at least one character, so the recursion is shallow."""
    if v is None:
        return "null"
    if v is True or v is False:
        return "true" if v else "false"
    if type(v) is int:
        return str(v)
    if type(v) is float:
        if v != v:
            return "NaN"
        if math.isinf(v):
            return "Infinity" if v > 0 else "-Infinity"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v[: budget + 1], ensure_ascii=False)
    if isinstance(v, (list, dict)):
        opened, closed = ("[", "]") if isinstance(v, list) else ("{", "}")
        parts, used = [], 1
        items = v if isinstance(v, list) else v.items()
        for k, item in enumerate(items):
            if used > budget or k >= budget:
                parts.append("...")
                break
            if isinstance(v, dict):
                key, val = item
                s = f"{json.dumps(str(key)[:budget], ensure_ascii=False)}: {_render(val, budget - used)}"
            else:
                s = _render(item, budget - used)
            parts.append(s)
            used += len(s) + 2
        return opened + ", ".join(parts) + closed
    return repr(v)[:budget]


def _short(v) -> str:
    """v as JSON, cut to about 40 characters."""
    s = _render(v, _SHORT)
    return s if len(s) <= _SHORT else s[: _SHORT - 3] + "..."


def _type_word(v) -> str:
    if v is None:
        return "null"
    if v is True or v is False:
        return "a boolean"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return "an array"
    if isinstance(v, dict):
        return "an object"
    if type(v) is int:
        return "an integer"
    if type(v) is float:
        return "a number"
    return type(v).__name__


def _fmt(x) -> str:
    """A bound as written in a message (pi and pi/2 by name, 1.0 as 1)."""
    if x == math.pi:
        return "pi"
    if x == math.pi / 2:
        return "pi/2"
    if isinstance(x, float) and x.is_integer():
        return str(int(x))
    return str(x)


_SINGULAR = {
    "accessors": "accessor", "animations": "animation", "buffers": "buffer", "bufferViews": "bufferView",
    "cameras": "camera", "images": "image", "materials": "material", "meshes": "mesh", "nodes": "node",
    "samplers": "sampler", "scenes": "scene", "skins": "skin", "textures": "texture",
    "lights": "KHR_lights_punctual light",
}


def _label(path: tuple, doc=None) -> str:
    """The readable name of the object a path is in: 'accessor 3', "mesh 0 ('Body') primitive 2"
    (the object's name when it has a string one, as the loader's messages give it)."""

    def named(what, obj):
        name = obj.get("name") if type(obj) is dict else None
        return f"{what} ({_short_repr(name)})" if type(name) is str and name else what

    top = doc.get(path[0]) if type(doc) is dict and path else None
    if len(path) >= 2 and path[0] in _SINGULAR and type(path[1]) is int:
        obj = top[path[1]] if type(top) is list and 0 <= path[1] < len(top) else None
        out = named(f"{_SINGULAR[path[0]]} {path[1]}", obj)
        if path[0] == "meshes" and len(path) >= 4 and path[2] == "primitives" and type(path[3]) is int:
            out += f" primitive {path[3]}"
        return out
    if len(path) >= 4 and path[:3] == ("extensions", "KHR_lights_punctual", "lights") and type(path[3]) is int:
        try:  # (a list: checked before the walk)
            light = doc["extensions"]["KHR_lights_punctual"]["lights"][path[3]]
        except (TypeError, KeyError, IndexError):
            light = None
        return named(f"KHR_lights_punctual light {path[3]}", light)
    return str(path[0])


def _short_repr(name: str) -> str:
    s = repr(name)
    return s if len(s) <= _SHORT else s[: _SHORT - 4] + "...'"


def _name(path: tuple) -> str:
    """The property a (non-empty) path ends in: 'count', 'children[2]'."""
    if type(path[-1]) is int:
        return f"{path[-2]}[{path[-1]}]"
    return str(path[-1])


def _raise(ctx, path: tuple, problem: str):
    fail(ctx.file, loc(_label(path, ctx.doc), pointer(*path)), problem, _FIX)


def _bad(ctx, path: tuple, v, what: str, expect: str):
    """'<name> <value> <what>; expected <expect>' at path."""
    _raise(ctx, path, f"{_name(path)} {_short(v)} {what}; expected {expect}")


class _Ctx:
    __slots__ = ("counts", "doc", "file")

    def __init__(self, file, doc, counts):
        self.file = file
        self.doc = doc
        self.counts = counts


# ---------------------------------------------------------------------------------------------
# Value specs: each has `expect` (text) and `check(ctx, value, parent path, key)` (raises)
# ---------------------------------------------------------------------------------------------
class _Int:
    """A JSON integer (not a boolean, not 3.0): lo <= v [<= hi], [v % mult == 0], [v in enum],
    [v < the length of the top-level array `ref`]."""

    def __init__(self, lo=0, hi=None, *, enum=None, ref=None, mult=None, expect=None):
        self.lo, self.hi, self.ref, self.mult = lo, hi, ref, mult
        self.enum = dict(enum) if isinstance(enum, dict) else ({e: None for e in enum} if enum else None)
        if expect is None:
            if self.enum:
                expect = "one of " + ", ".join(f"{k} ({n})" if n else str(k) for k, n in self.enum.items())
            elif hi is not None:
                expect = f"an integer in [{lo}, {hi}]" + (f" and a multiple of {mult}" if mult else "")
            else:
                expect = f"an integer >= {lo}"
        self.expect = expect
        bad = self.bad
        if self.enum:
            allowed = frozenset(self.enum)

            def check(ctx, v, parent, key):
                if type(v) is not int or v not in allowed:
                    bad(ctx, v, parent + (key,))
        elif ref is not None:

            def check(ctx, v, parent, key):
                if type(v) is not int or v < 0 or v >= ctx.counts[ref]:
                    bad(ctx, v, parent + (key,))
        elif hi is None and mult is None:

            def check(ctx, v, parent, key):
                if type(v) is not int or v < lo:
                    bad(ctx, v, parent + (key,))
        else:

            def check(ctx, v, parent, key):
                if type(v) is not int or not self.ok(v):
                    bad(ctx, v, parent + (key,))

        self.check = check

    def ok(self, v) -> bool:
        return (v >= self.lo and (self.hi is None or v <= self.hi) and (self.mult is None or v % self.mult == 0)
                and (self.enum is None or v in self.enum))

    def bad(self, ctx, v, path):
        """Raise for v, which failed `check`."""
        if type(v) is not int:
            if type(v) is float and not math.isfinite(v):
                _bad(ctx, path, v, "is not a finite number", self.expect)
            if type(v) is float and v.is_integer():
                _bad(ctx, path, v, "is not an integer (JSON integers have no fraction or exponent)", self.expect)
            if type(v) is float:
                _bad(ctx, path, v, "is not an integer", self.expect)
            _bad(ctx, path, v, f"is {_type_word(v)}", self.expect)
        if not self.ok(v):
            _bad(ctx, path, v, "is not a valid value" if self.enum else "is out of range", self.expect)
        n = ctx.counts[self.ref]
        _raise(ctx, path, f"names {_SINGULAR[self.ref]} {_short(v)}, which does not exist (the file has {n})")


class _Num:
    """A finite JSON number (not a boolean): lo <= v <= hi, v > gt, v < lt, v != 0 (nonzero), or
    v == 0 besides the range (or_zero)."""

    def __init__(self, lo=-_FMAX, hi=_FMAX, *, gt=None, lt=None, nonzero=False, or_zero=False, expect=None):
        self.lo, self.hi, self.gt, self.lt, self.nonzero, self.or_zero = lo, hi, gt, lt, nonzero, or_zero
        if expect is None:
            low = f"[{_fmt(lo)}" if gt is None else f"({_fmt(gt)}"
            high = f"{_fmt(hi)}]" if lt is None else f"{_fmt(lt)})"
            has_low, has_high = lo != -_FMAX or gt is not None, hi != _FMAX or lt is not None
            if has_low and has_high:
                expect = f"a number in {low}, {high}"
            elif has_low:
                expect = f"a number >= {_fmt(lo)}" if gt is None else f"a number > {_fmt(gt)}"
            elif has_high:
                expect = f"a number <= {_fmt(hi)}" if lt is None else f"a number < {_fmt(lt)}"
            else:
                expect = "a finite non-zero number" if nonzero else "a finite number"
            if or_zero:
                expect = f"0 or {expect}"
        self.expect = expect
        self.simple = gt is None and lt is None and not nonzero and not or_zero
        bad = self.bad
        if self.simple:

            def check(ctx, v, parent, key):
                t = type(v)
                if (t is not float and t is not int) or not lo <= v <= hi:
                    bad(ctx, v, parent + (key,))
        else:

            def check(ctx, v, parent, key):
                t = type(v)
                if (t is not float and t is not int) or not self.ok(v):
                    bad(ctx, v, parent + (key,))

        self.check = check

    def ok(self, v) -> bool:
        """v (an int or a float) in range; NaN, infinities and ints beyond float64 are not."""
        if not -_FMAX <= v <= _FMAX:
            return False
        if self.or_zero and v == 0:
            return True
        return (self.lo <= v <= self.hi and (self.gt is None or v > self.gt) and (self.lt is None or v < self.lt)
                and not (self.nonzero and v == 0))

    def why(self, v) -> str | None:
        """What is wrong with v, or None."""
        t = type(v)
        if t is not float and t is not int:
            return f"is {_type_word(v)}"
        if t is float and not math.isfinite(v):
            return "is not a finite number"
        if not -_FMAX <= v <= _FMAX:
            return "is beyond the range of a 64-bit float"
        return None if self.ok(v) else "is out of range"

    def bad(self, ctx, v, path):
        _bad(ctx, path, v, self.why(v) or "is out of range", self.expect)


class _Str:
    def __init__(self, enum=None):
        self.enum = frozenset(enum) if enum else None
        self.expect = ("one of " + ", ".join(json.dumps(e) for e in enum)) if enum else "a string"
        allowed = self.enum

        def check(ctx, v, parent, key):
            if type(v) is not str or (allowed is not None and v not in allowed):
                path = parent + (key,)
                _bad(ctx, path, v, "is not a valid value" if isinstance(v, str) else f"is {_type_word(v)}", self.expect)

        self.check = check


class _Bool:
    expect = "true or false"

    @staticmethod
    def check(ctx, v, parent, key):
        if v is not True and v is not False:
            _bad(ctx, parent + (key,), v, f"is {_type_word(v)}", "true or false")


def _items_text(lo, hi, what):
    if lo == hi:
        return f"an array of {lo} {what}"
    if hi is None:
        return f"an array of {what}" if lo == 0 else f"an array of at least {lo} {what}"
    return f"an array of {lo} to {hi} {what}"


class _NumArray:
    """An array of lo..hi numbers, each an `item` (_Num)."""

    def __init__(self, lo, hi=None, item=None, *, fixed=False):
        self.lo, self.hi = lo, (lo if fixed else hi)
        self.item = item or _Num()
        self.expect = _items_text(self.lo, self.hi, f"numbers ({self.item.expect})" if self.item.expect != "a finite number"
                                  else "finite numbers")
        ilo, ihi, simple, n_lo, n_hi = self.item.lo, self.item.hi, self.item.simple, self.lo, self.hi
        bad = self.bad
        ok = self.item.ok

        def check(ctx, v, parent, key):
            if type(v) is not list or len(v) < n_lo or (n_hi is not None and len(v) > n_hi):
                bad(ctx, v, parent + (key,))
                return
            for x in v:
                t = type(x)
                if (t is not float and t is not int) or not ilo <= x <= ihi or not (simple or ok(x)):
                    bad(ctx, v, parent + (key,))
                    return

        self.check = check

    def bad(self, ctx, v, path):
        if type(v) is not list:
            _bad(ctx, path, v, f"is {_type_word(v)}", self.expect)
        if len(v) < self.lo or (self.hi is not None and len(v) > self.hi):
            _bad(ctx, path, v, f"has {len(v)} items", self.expect)
        for k, x in enumerate(v):
            why = self.item.why(x)
            if why:
                _bad(ctx, path + (k,), x, why, self.item.expect)


class _IntArray:
    """An array of at least `lo` integers, each an `item` (_Int), unique when `unique`."""

    def __init__(self, item: _Int, *, lo=0, unique=True):
        self.item, self.lo, self.unique = item, lo, unique
        self.expect = _items_text(lo, None, ("unique " if unique else "") + f"integers ({item.expect})")
        bad = self.bad
        ref, ilo = item.ref, item.lo
        plain = item.enum is None and item.hi is None and item.mult is None

        def check(ctx, v, parent, key):
            if type(v) is not list or len(v) < lo:
                bad(ctx, v, parent + (key,))
                return
            if not v:
                return
            if not plain or not all(type(x) is int for x in v):
                bad(ctx, v, parent + (key,))
                return
            if min(v) < ilo or (ref is not None and max(v) >= ctx.counts[ref]) or (unique and len(set(v)) != len(v)):
                bad(ctx, v, parent + (key,))

        self.check = check

    def bad(self, ctx, v, path):
        if type(v) is not list:
            _bad(ctx, path, v, f"is {_type_word(v)}", self.expect)
        if len(v) < self.lo:
            _bad(ctx, path, v, "is an empty array", self.expect)
        for k, x in enumerate(v):
            self.item.check(ctx, x, path, k)
        if self.unique:
            seen = set()
            for k, x in enumerate(v):
                if x in seen:
                    _bad(ctx, path + (k,), x, f"repeats an earlier item of {_name(path)}", self.expect)
                seen.add(x)


class _StrArray:
    """An array of unique strings."""

    expect = "an array of unique strings"

    def check(self, ctx, v, parent, key):
        if type(v) is not list:
            _bad(ctx, parent + (key,), v, f"is {_type_word(v)}", self.expect)
        seen = set()
        for k, x in enumerate(v):
            if type(x) is not str:
                _bad(ctx, parent + (key, k), x, f"is {_type_word(x)}", "a string")
            if x in seen:
                _bad(ctx, parent + (key, k), x, f"repeats an earlier item of {key}", self.expect)
            seen.add(x)


class _IntMap:
    """An object of at least `lo` properties whose values are `item`s (_Int): primitive attributes."""

    def __init__(self, item: _Int, *, lo=0):
        self.item, self.lo = item, lo
        self.expect = ("an object" if not lo else "a non-empty object") + f" of integers ({item.expect})"
        icheck = item.check
        bad = self.bad

        def check(ctx, v, parent, key):
            if type(v) is not dict or len(v) < lo:
                bad(ctx, v, parent + (key,))
            path = parent + (key,)
            for name, x in v.items():
                icheck(ctx, x, path, name)

        self.check = check

    def bad(self, ctx, v, path):
        if type(v) is not dict:
            _bad(ctx, path, v, f"is {_type_word(v)}", self.expect)
        _bad(ctx, path, v, "is an empty object", self.expect)


class _Kind:
    """An object kind of the schema: its properties' specs, its required properties and an optional
    check of the whole object (`post(ctx, obj, path)`, after its properties are checked)."""

    def __init__(self, props: dict, required=(), post=None, extensions=None, named=True):
        self.specs = dict(props)
        if named:
            self.specs.setdefault("name", _Str())
        self.specs["extensions"] = _Extensions(extensions or {})
        self.props = {k: s.check for k, s in self.specs.items()}
        self.required = tuple(required)
        self.post = post


def _walk(ctx, obj: dict, kind: _Kind, path: tuple):
    """Check one object (already known to be a dict) of `kind` at `path`."""
    props = kind.props
    for key, v in obj.items():
        c = props.get(key)
        if c is not None:
            c(ctx, v, path, key)
    for key in kind.required:
        if key not in obj:
            _raise(ctx, path, f"the required property {key} is missing; expected {kind.specs[key].expect}")
    if kind.post is not None:
        kind.post(ctx, obj, path)


class _Obj:
    """An object of a kind."""

    def __init__(self, kind: _Kind):
        self.kind = kind
        self.expect = "an object"

    def check(self, ctx, v, parent, key):
        path = parent + (key,)
        if type(v) is not dict:
            _bad(ctx, path, v, f"is {_type_word(v)}", "an object")
        _walk(ctx, v, self.kind, path)


class _ObjArray:
    """An array (at least `lo` items) of objects of a kind."""

    def __init__(self, kind: _Kind, *, lo=0):
        self.kind, self.lo = kind, lo
        self.expect = f"an array of {'at least one object' if lo else 'objects'}"

    def check(self, ctx, v, parent, key):
        path = parent + (key,)
        if type(v) is not list:
            _bad(ctx, path, v, f"is {_type_word(v)}", self.expect)
        if len(v) < self.lo:
            _bad(ctx, path, v, "is an empty array", self.expect)
        kind = self.kind
        props, required, post = kind.props, kind.required, kind.post
        for i, o in enumerate(v):
            if type(o) is not dict:
                _bad(ctx, path + (i,), o, f"is {_type_word(o)}", "an object")
            here = path + (i,)
            for k, x in o.items():
                c = props.get(k)
                if c is not None:
                    c(ctx, x, here, k)
            if required or post is not None:
                for r in required:
                    if r not in o:
                        _raise(ctx, here, f"the required property {r} is missing; expected {kind.specs[r].expect}")
                if post is not None:
                    post(ctx, o, here)


class _Extensions:
    """An `extensions` object: the known extensions' objects are checked, others are not."""

    expect = "an object"

    def __init__(self, known: dict):
        self.known = known

    def check(self, ctx, v, parent, key):
        path = parent + (key,)
        if type(v) is not dict:
            _bad(ctx, path, v, f"is {_type_word(v)}", "an object")
        for name, kind in self.known.items():
            x = v.get(name, _MISSING)
            if x is not _MISSING:
                if type(x) is not dict:
                    _bad(ctx, path + (name,), x, f"is {_type_word(x)}", f"an object ({name})")
                _walk(ctx, x, kind, path + (name,))


_MISSING = object()


# ---------------------------------------------------------------------------------------------
# Cross-property checks (beyond one value)
# ---------------------------------------------------------------------------------------------
def _camera(ctx, cam: dict, path: tuple):
    kind = cam.get("type")
    if kind not in cam:
        _raise(ctx, path + ("type",), f'type "{kind}" needs the camera\'s {kind} object, which is missing')
    p = cam[kind]
    znear, zfar = p.get("znear"), p.get("zfar")
    if zfar is not None and znear is not None and not zfar > znear:
        _raise(ctx, path + (kind, "zfar"), f"zfar {_short(zfar)} is not greater than znear {_short(znear)}; "
               "expected zfar > znear")


def _spot(ctx, spot: dict, path: tuple):
    inner, outer = spot.get("innerConeAngle", 0.0), spot.get("outerConeAngle", math.pi / 4)
    if not inner < outer:
        at = "innerConeAngle" if "innerConeAngle" in spot else "outerConeAngle"
        _raise(ctx, path + (at,), f"innerConeAngle {_fmt(inner)} is not smaller than outerConeAngle {_fmt(outer)}; "
               "expected innerConeAngle < outerConeAngle")


# ---------------------------------------------------------------------------------------------
# The schema (glTF 2.0 and the extensions jaxpbr reads)
# ---------------------------------------------------------------------------------------------
def _ref(name):
    return _Int(0, ref=name)


_INDEX = _Int(0)
_UNIT = _Num(0.0, 1.0)
_NONNEG = _Num(0.0)
_NUMBER = _Num()


def _nums(n, item=_NUMBER):
    return _NumArray(n, item=item, fixed=True)


_TEXTURE_TRANSFORM = _Kind({"offset": _nums(2), "rotation": _NUMBER, "scale": _nums(2), "texCoord": _INDEX},
                           named=False)
_TT_EXT = {"KHR_texture_transform": _TEXTURE_TRANSFORM}
_TEXTURE_INFO = _Obj(_Kind({"index": _ref("textures"), "texCoord": _INDEX}, ("index",), extensions=_TT_EXT, named=False))
_NORMAL_INFO = _Obj(_Kind({"index": _ref("textures"), "texCoord": _INDEX, "scale": _NUMBER}, ("index",),
                          extensions=_TT_EXT, named=False))
_OCCLUSION_INFO = _Obj(_Kind({"index": _ref("textures"), "texCoord": _INDEX, "strength": _UNIT}, ("index",),
                             extensions=_TT_EXT, named=False))


def _ext(props, required=()):
    """An extension's object kind."""
    return _Kind(props, required, named=False)


_MATERIAL_EXTENSIONS = {
    "KHR_materials_clearcoat": _ext({
        "clearcoatFactor": _UNIT, "clearcoatTexture": _TEXTURE_INFO, "clearcoatRoughnessFactor": _UNIT,
        "clearcoatRoughnessTexture": _TEXTURE_INFO, "clearcoatNormalTexture": _NORMAL_INFO}),
    "KHR_materials_sheen": _ext({
        "sheenColorFactor": _nums(3, _UNIT), "sheenColorTexture": _TEXTURE_INFO, "sheenRoughnessFactor": _UNIT,
        "sheenRoughnessTexture": _TEXTURE_INFO}),
    "KHR_materials_specular": _ext({
        "specularFactor": _UNIT, "specularTexture": _TEXTURE_INFO, "specularColorFactor": _nums(3, _NONNEG),
        "specularColorTexture": _TEXTURE_INFO}),
    "KHR_materials_ior": _ext({"ior": _Num(1.0, or_zero=True)}),
    "KHR_materials_anisotropy": _ext({
        "anisotropyStrength": _UNIT, "anisotropyRotation": _NUMBER, "anisotropyTexture": _TEXTURE_INFO}),
    "KHR_materials_emissive_strength": _ext({"emissiveStrength": _NONNEG}),
    "KHR_materials_transmission": _ext({"transmissionFactor": _UNIT, "transmissionTexture": _TEXTURE_INFO}),
    "KHR_materials_volume": _ext({
        "thicknessFactor": _NONNEG, "thicknessTexture": _TEXTURE_INFO, "attenuationDistance": _Num(gt=0.0),
        "attenuationColor": _nums(3, _UNIT)}),
    "KHR_materials_iridescence": _ext({
        "iridescenceFactor": _UNIT, "iridescenceTexture": _TEXTURE_INFO, "iridescenceIor": _Num(1.0),
        "iridescenceThicknessMinimum": _NONNEG, "iridescenceThicknessMaximum": _NONNEG,
        "iridescenceThicknessTexture": _TEXTURE_INFO}),
    "KHR_materials_unlit": _ext({}),
}

_ACCESSOR = _Kind({
    "bufferView": _ref("bufferViews"),
    "byteOffset": _INDEX,
    "componentType": _Int(enum={5120: "BYTE", 5121: "UNSIGNED_BYTE", 5122: "SHORT", 5123: "UNSIGNED_SHORT",
                                5125: "UNSIGNED_INT", 5126: "FLOAT"}),
    "normalized": _Bool,
    "count": _Int(1),
    "type": _Str(("SCALAR", "VEC2", "VEC3", "VEC4", "MAT2", "MAT3", "MAT4")),
    "max": _NumArray(1, 16),
    "min": _NumArray(1, 16),
    "sparse": _Obj(_Kind({
        "count": _Int(1),
        "indices": _Obj(_Kind({
            "bufferView": _ref("bufferViews"), "byteOffset": _INDEX,
            "componentType": _Int(enum={5121: "UNSIGNED_BYTE", 5123: "UNSIGNED_SHORT", 5125: "UNSIGNED_INT"}),
        }, ("bufferView", "componentType"), named=False)),
        "values": _Obj(_Kind({"bufferView": _ref("bufferViews"), "byteOffset": _INDEX}, ("bufferView",), named=False)),
    }, ("count", "indices", "values"), named=False)),
}, ("componentType", "count", "type"))

_BUFFER_VIEW = _Kind({
    "buffer": _ref("buffers"),
    "byteOffset": _INDEX,
    "byteLength": _Int(1),
    "byteStride": _Int(4, 252, mult=4),
    "target": _Int(enum={34962: "ARRAY_BUFFER", 34963: "ELEMENT_ARRAY_BUFFER"}),
}, ("buffer", "byteLength"))

_BUFFER = _Kind({"uri": _Str(), "byteLength": _Int(1)}, ("byteLength",))

_IMAGE = _Kind({"uri": _Str(), "mimeType": _Str(), "bufferView": _ref("bufferViews")})

_SAMPLER = _Kind({
    "magFilter": _Int(enum={9728: "NEAREST", 9729: "LINEAR"}),
    "minFilter": _Int(enum={9728: "NEAREST", 9729: "LINEAR", 9984: "NEAREST_MIPMAP_NEAREST",
                            9985: "LINEAR_MIPMAP_NEAREST", 9986: "NEAREST_MIPMAP_LINEAR", 9987: "LINEAR_MIPMAP_LINEAR"}),
    "wrapS": _Int(enum={33071: "CLAMP_TO_EDGE", 33648: "MIRRORED_REPEAT", 10497: "REPEAT"}),
    "wrapT": _Int(enum={33071: "CLAMP_TO_EDGE", 33648: "MIRRORED_REPEAT", 10497: "REPEAT"}),
})

_TEXTURE = _Kind({"sampler": _ref("samplers"), "source": _ref("images")},
                 extensions={"EXT_texture_webp": _ext({"source": _ref("images")})})

_MATERIAL = _Kind({
    "pbrMetallicRoughness": _Obj(_Kind({
        "baseColorFactor": _nums(4, _UNIT), "baseColorTexture": _TEXTURE_INFO, "metallicFactor": _UNIT,
        "roughnessFactor": _UNIT, "metallicRoughnessTexture": _TEXTURE_INFO}, named=False)),
    "normalTexture": _NORMAL_INFO,
    "occlusionTexture": _OCCLUSION_INFO,
    "emissiveTexture": _TEXTURE_INFO,
    "emissiveFactor": _nums(3, _UNIT),
    "alphaMode": _Str(("OPAQUE", "MASK", "BLEND")),
    "alphaCutoff": _NONNEG,
    "doubleSided": _Bool,
}, extensions=_MATERIAL_EXTENSIONS)

_ACCESSOR_MAP = _IntMap(_ref("accessors"), lo=1)


class _MapArray:
    """An array (at least one item) of accessor maps: morph targets."""

    expect = "an array of at least one object of accessor indices"

    def check(self, ctx, v, parent, key):
        path = parent + (key,)
        if type(v) is not list:
            _bad(ctx, path, v, f"is {_type_word(v)}", self.expect)
        if not v:
            _bad(ctx, path, v, "is an empty array", self.expect)
        for k, m in enumerate(v):
            _ACCESSOR_MAP.check(ctx, m, path, k)


_PRIMITIVE = _Kind({
    "attributes": _ACCESSOR_MAP,
    "indices": _ref("accessors"),
    "material": _ref("materials"),
    "mode": _Int(enum={0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP", 4: "TRIANGLES",
                       5: "TRIANGLE_STRIP", 6: "TRIANGLE_FAN"}),
    "targets": _MapArray(),
}, ("attributes",), named=False, extensions={
    "KHR_draco_mesh_compression": _ext({"bufferView": _ref("bufferViews"), "attributes": _IntMap(_INDEX)},
                                       ("bufferView", "attributes")),
})

_WEIGHTS = _NumArray(1)

_MESH = _Kind({"primitives": _ObjArray(_PRIMITIVE, lo=1), "weights": _WEIGHTS}, ("primitives",))

_NODE = _Kind({
    "camera": _ref("cameras"),
    "children": _IntArray(_ref("nodes")),
    "skin": _ref("skins"),
    "matrix": _nums(16),
    "mesh": _ref("meshes"),
    "rotation": _nums(4, _Num(-1.0, 1.0)),
    "scale": _nums(3),
    "translation": _nums(3),
    "weights": _WEIGHTS,
}, extensions={
    "KHR_lights_punctual": _ext({"light": _ref("lights")}, ("light",)),
    "EXT_mesh_gpu_instancing": _ext({"attributes": _ACCESSOR_MAP}, ("attributes",)),
})

_CAMERA = _Kind({
    "type": _Str(("perspective", "orthographic")),
    "perspective": _Obj(_Kind({
        "aspectRatio": _Num(gt=0.0), "yfov": _Num(gt=0.0, lt=math.pi), "zfar": _Num(gt=0.0), "znear": _Num(gt=0.0),
    }, ("yfov", "znear"), named=False)),
    "orthographic": _Obj(_Kind({
        "xmag": _Num(nonzero=True), "ymag": _Num(nonzero=True), "zfar": _Num(gt=0.0), "znear": _NONNEG,
    }, ("xmag", "ymag", "zfar", "znear"), named=False)),
}, ("type",), post=_camera)

_SKIN = _Kind({"inverseBindMatrices": _ref("accessors"), "skeleton": _ref("nodes"),
               "joints": _IntArray(_ref("nodes"), lo=1)}, ("joints",))

_SCENE = _Kind({"nodes": _IntArray(_ref("nodes"))})

_ANIMATION_CHANNEL = _Kind({
    "sampler": _Int(lo=0),  # (an index into the animation's own samplers: checked by the reader)
    "target": _Obj(_Kind({"node": _ref("nodes"), "path": _Str()}, ("path",), named=False)),
}, ("sampler", "target"), named=False)

_ANIMATION_SAMPLER = _Kind({
    "input": _ref("accessors"),
    "output": _ref("accessors"),
    "interpolation": _Str(("LINEAR", "STEP", "CUBICSPLINE")),
}, ("input", "output"), named=False)

_ANIMATION = _Kind({"channels": _ObjArray(_ANIMATION_CHANNEL, lo=1), "samplers": _ObjArray(_ANIMATION_SAMPLER, lo=1)},
                   ("channels", "samplers"))

_LIGHT = _Kind({
    "type": _Str(("directional", "point", "spot")),
    "color": _nums(3, _UNIT),
    "intensity": _NONNEG,
    "range": _Num(gt=0.0),
    "spot": _Obj(_Kind({"innerConeAngle": _Num(0.0, lt=math.pi / 2), "outerConeAngle": _Num(gt=0.0, hi=math.pi / 2)},
                       named=False, post=_spot)),
}, ("type",))

_ASSET = _Kind({"version": _Str(), "minVersion": _Str(), "generator": _Str(), "copyright": _Str()},
               ("version",), named=False)

#: The top-level arrays of objects, each with its kind (the index references count their lengths).
_ARRAYS = {
    "accessors": _ACCESSOR,
    "animations": _ANIMATION,
    "buffers": _BUFFER,
    "bufferViews": _BUFFER_VIEW,
    "cameras": _CAMERA,
    "images": _IMAGE,
    "materials": _MATERIAL,
    "meshes": _MESH,
    "nodes": _NODE,
    "samplers": _SAMPLER,
    "scenes": _SCENE,
    "skins": _SKIN,
    "textures": _TEXTURE,
}

_ROOT = _Kind({
    "asset": _Obj(_ASSET),
    "scene": _ref("scenes"),
    "extensionsUsed": _StrArray(),
    "extensionsRequired": _StrArray(),
    **{k: _ObjArray(kind) for k, kind in _ARRAYS.items()},
}, ("asset",), named=False, extensions={
    "KHR_lights_punctual": _ext({"lights": _ObjArray(_LIGHT)}, ("lights",)),
})


# ---------------------------------------------------------------------------------------------
def check_schema(path, doc: dict) -> None:
    """Check the glTF 2.0 JSON document `doc` (the object `json.loads` made of the file `path`,
    which names the file in messages) against the glTF 2.0 schema's types and ranges (see the
    module's docstring), before the loader uses any value; raise `InputError` naming the first bad
    value's JSON pointer, the value, what was expected and a fix."""
    if type(doc) is not dict:
        fail(path, "JSON root (pointer '')", f"the JSON is {_type_word(doc)}, not an object", _FIX)
    ctx = _Ctx(path, doc, {})
    # The top-level arrays' types first: the references count their lengths.
    counts = ctx.counts
    for key in _ARRAYS:
        v = doc.get(key, _MISSING)
        if v is not _MISSING and type(v) is not list:
            _bad(ctx, (key,), v, f"is {_type_word(v)}", "an array of objects")
        counts[key] = 0 if v is _MISSING else len(v)
    counts["lights"] = 0
    ext = doc.get("extensions", _MISSING)
    if ext is not _MISSING:
        if type(ext) is not dict:
            _bad(ctx, ("extensions",), ext, f"is {_type_word(ext)}", "an object")
        lp = ext.get("KHR_lights_punctual", _MISSING)
        if lp is not _MISSING:
            if type(lp) is not dict:
                _bad(ctx, ("extensions", "KHR_lights_punctual"), lp, f"is {_type_word(lp)}", "an object")
            lights = lp.get("lights", _MISSING)
            if lights is not _MISSING and type(lights) is not list:
                _bad(ctx, ("extensions", "KHR_lights_punctual", "lights"), lights, f"is {_type_word(lights)}",
                     "an array of objects")
            counts["lights"] = 0 if lights is _MISSING else len(lights)
    _walk(ctx, doc, _ROOT, ())
