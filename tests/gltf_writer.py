"""Small glTF 2.0 writers for the tests, independent of jaxpbr's reader, and the Khronos glTF
Validator runner.

* `Writer`: meshes, materials (with PNG textures), lights and cameras written straight to JSON + one
  binary buffer (.glb or .gltf with a data URI); what the render tests need.
* `Builder`: a glTF document built entry by entry (any component type, strides, sparse accessors,
  samplers, extensions) and written as .gltf (external .bin or data URI) or .glb; what the loader
  tests and `tests/gltf_assets.py` need.
* `png_bytes`: an 8-bit PNG encoded with zlib alone.
* `validate` / `assert_valid`: the Khronos glTF-Validator (npm package gltf-validator) run with node.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np

FLOAT, UINT32 = 5126, 5125
BYTE, UBYTE, SHORT, USHORT, UINT = 5120, 5121, 5122, 5123, 5125
_NP = {FLOAT: "<f4", BYTE: "<i1", UBYTE: "<u1", SHORT: "<i2", USHORT: "<u2", UINT: "<u4"}
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


class Writer:
    def __init__(self):
        self.bin = bytearray()
        self.doc = {"asset": {"version": "2.0", "generator": "jaxpbr tests"}, "buffers": [], "bufferViews": [],
                    "accessors": [], "meshes": [], "nodes": [], "scenes": [{"nodes": []}], "scene": 0}

    def _view(self, data: bytes, target=None) -> int:
        while len(self.bin) % 4:
            self.bin.append(0)
        off = len(self.bin)
        self.bin += data
        v = {"buffer": 0, "byteOffset": off, "byteLength": len(data)}
        if target:
            v["target"] = target
        self.doc["bufferViews"].append(v)
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, a: np.ndarray, kind: str) -> int:
        if kind == "SCALAR_U32":
            a = np.ascontiguousarray(a, np.uint32).reshape(-1)
            view = self._view(a.tobytes(), 34963)
            acc = {"bufferView": view, "componentType": UINT32, "count": int(a.size), "type": "SCALAR"}
        else:
            a = np.ascontiguousarray(a, np.float32)
            view = self._view(a.tobytes(), 34962)
            acc = {"bufferView": view, "componentType": FLOAT, "count": int(a.shape[0]), "type": kind}
            if kind == "VEC3":
                acc["min"] = a.min(0).tolist()
                acc["max"] = a.max(0).tolist()
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def image_png(self, pixels: np.ndarray) -> int:
        import OpenImageIO as oiio

        px = np.ascontiguousarray(np.clip(np.round(pixels * 255), 0, 255).astype(np.uint8))
        H, W, C = px.shape
        out = oiio.ImageOutput.create("x.png")
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            f = Path(d) / "t.png"
            out = oiio.ImageOutput.create(str(f))
            out.open(str(f), oiio.ImageSpec(W, H, C, oiio.UINT8))
            out.write_image(px)
            out.close()
            data = f.read_bytes()
        view = self._view(data)
        self.doc.setdefault("images", []).append({"bufferView": view, "mimeType": "image/png"})
        self.doc.setdefault("samplers", [{}])
        self.doc.setdefault("textures", []).append({"source": len(self.doc["images"]) - 1, "sampler": 0})
        return len(self.doc["textures"]) - 1

    def material(self, **m) -> int:
        self.doc.setdefault("materials", []).append(m)
        return len(self.doc["materials"]) - 1

    def mesh(self, positions, indices, *, normals=None, uv=None, material=None) -> int:
        attrs = {"POSITION": self.accessor(positions, "VEC3")}
        if normals is not None:
            attrs["NORMAL"] = self.accessor(normals, "VEC3")
        if uv is not None:
            attrs["TEXCOORD_0"] = self.accessor(uv, "VEC2")
        prim = {"attributes": attrs, "indices": self.accessor(indices, "SCALAR_U32")}
        if material is not None:
            prim["material"] = material
        self.doc["meshes"].append({"primitives": [prim]})
        return len(self.doc["meshes"]) - 1

    def node(self, root=True, **n) -> int:
        self.doc["nodes"].append(n)
        k = len(self.doc["nodes"]) - 1
        if root:
            self.doc["scenes"][0]["nodes"].append(k)
        return k

    def light(self, **lt) -> int:
        ext = self.doc.setdefault("extensions", {}).setdefault("KHR_lights_punctual", {"lights": []})
        ext["lights"].append(lt)
        used = self.doc.setdefault("extensionsUsed", [])
        if "KHR_lights_punctual" not in used:
            used.append("KHR_lights_punctual")
        return len(ext["lights"]) - 1

    def camera(self, **c) -> int:
        self.doc.setdefault("cameras", []).append(c)
        return len(self.doc["cameras"]) - 1

    def save(self, path: Path) -> Path:
        path = Path(path)
        while len(self.bin) % 4:
            self.bin.append(0)
        if path.suffix == ".glb":
            self.doc["buffers"] = [{"byteLength": len(self.bin)}]
            js = json.dumps(self.doc).encode()
            js += b" " * (-len(js) % 4)
            out = struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(js) + 8 + len(self.bin))
            out += struct.pack("<II", len(js), 0x4E4F534A) + js
            out += struct.pack("<II", len(self.bin), 0x004E4942) + bytes(self.bin)
            path.write_bytes(out)
        else:
            uri = "data:application/octet-stream;base64," + base64.b64encode(bytes(self.bin)).decode()
            self.doc["buffers"] = [{"byteLength": len(self.bin), "uri": uri}]
            path.write_text(json.dumps(self.doc))
        return path


class Builder:
    """A glTF document and its single binary buffer, written as .gltf (external .bin or data URI) or .glb."""

    def __init__(self, generator="jaxpbr tests"):
        self.doc = {"asset": {"version": "2.0", "generator": generator}}
        self.bin = bytearray()

    def add(self, key, obj) -> int:
        self.doc.setdefault(key, []).append(obj)
        return len(self.doc[key]) - 1

    def view(self, data: bytes, *, stride=None, target=None) -> int:
        while len(self.bin) % 4:
            self.bin.append(0)
        v = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(data)}
        if stride is not None:
            v["byteStride"] = stride
        if target is not None:
            v["target"] = target
        self.bin += data
        return self.add("bufferViews", v)

    def accessor(self, values, ctype, atype, *, view=None, offset=0, count=None, normalized=False,
                 minmax=False, target=None, sparse=None) -> int:
        values = np.asarray(values)
        if view is None and values.size:
            raw = np.ascontiguousarray(values.astype(_NP[ctype]).reshape(len(values), -1))
            stride = raw.shape[1] * raw.itemsize
            if atype != "SCALAR" and stride % 4:  # vertex attributes: elements 4-byte aligned
                padded = np.zeros((len(raw), stride + (-stride % 4)), np.uint8)
                padded[:, :stride] = raw.view(np.uint8)
                view = self.view(padded.tobytes(), stride=padded.shape[1], target=target)
            else:
                view = self.view(raw.tobytes(), target=target)
        acc = {"componentType": ctype, "type": atype, "count": int(count if count is not None else len(values))}
        if view is not None:
            acc["bufferView"] = view
            if offset:
                acc["byteOffset"] = offset
        if normalized:
            acc["normalized"] = True
        if minmax:
            flat = values.reshape(len(values), -1)
            acc["min"] = [v.item() for v in flat.min(axis=0)]
            acc["max"] = [v.item() for v in flat.max(axis=0)]
        if sparse is not None:
            acc["sparse"] = sparse
        return self.add("accessors", acc)

    def used(self, *names, required=()):
        for n in names:
            self.doc.setdefault("extensionsUsed", []).append(n)
        for n in required:
            self.doc.setdefault("extensionsRequired", []).append(n)

    def write(self, path: Path, *, mode="bin") -> Path:
        """mode: 'bin' (external .bin next to the .gltf), 'data' (base64 data URI) or 'glb'."""
        doc = json.loads(json.dumps(self.doc))
        data = bytes(self.bin) + b"\0" * (-len(self.bin) % 4)
        if self.bin:
            buf = {"byteLength": len(self.bin)}
            if mode == "bin":
                name = path.stem + ".bin"
                (path.parent / name).write_bytes(data)
                buf["uri"] = name
            elif mode == "data":
                buf["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(self.bin)).decode()
            doc["buffers"] = [buf]
        if mode == "glb":
            js = json.dumps(doc).encode()
            js += b" " * (-len(js) % 4)
            chunks = struct.pack("<I4s", len(js), b"JSON") + js
            if self.bin:
                chunks += struct.pack("<I4s", len(data), b"BIN\0") + data
            path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)
        else:
            path.write_text(json.dumps(doc, indent=1))
        return path


def png_bytes(pixels: np.ndarray) -> bytes:
    """A PNG (8-bit, no filtering) of uint8 (H, W, C) pixels, C in 1..4."""
    h, w, c = pixels.shape
    colour_type = {1: 0, 2: 4, 3: 2, 4: 6}[c]
    raw = b"".join(b"\0" + pixels[y].astype(np.uint8).tobytes() for y in range(h))

    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


# ---------------------------------------------------------------------------------------------
# gltf-transform (npm @gltf-transform/cli): an independent writer of compressed glTF content
# ---------------------------------------------------------------------------------------------
#: The gltf-transform command line: JAXPBR_GLTF_TRANSFORM, else the checkout's node_modules
#: (`npm install --no-save @gltf-transform/cli`, as .ci/run does). Its `draco` command encodes with
#: draco3dgltf (Google's encoder built for JavaScript), its `webp` command with sharp (libwebp).
_GLTF_TRANSFORM = Path(os.environ.get("JAXPBR_GLTF_TRANSFORM", Path(__file__).resolve().parent.parent / "node_modules" / ".bin" / "gltf-transform"))


def _npm_missing(path: Path, package: str) -> str | None:
    """Why the npm `package` installed at `path` cannot run here (None when it can)."""
    if shutil.which("node") is None:
        return "node is not installed"
    if not path.exists():
        return f"the npm package {package} is not installed ({path}; npm install --no-save {package})"
    return None


def gltf_transform_missing() -> str | None:
    """Why gltf-transform cannot run here (None when it can)."""
    return _npm_missing(_GLTF_TRANSFORM, "@gltf-transform/cli")


def gltf_transform(*args) -> None:
    """Run `gltf-transform ARGS` (raises with its output when it fails)."""
    run = subprocess.run([str(_GLTF_TRANSFORM), *map(str, args)], check=False, capture_output=True, text=True, timeout=180)
    if run.returncode != 0:
        raise RuntimeError(f"gltf-transform {' '.join(map(str, args))} failed: {run.stdout}{run.stderr}")


# ---------------------------------------------------------------------------------------------
# The Khronos validator (run when node and the gltf-validator package are there)
# ---------------------------------------------------------------------------------------------
# The Khronos glTF Validator (npm package gltf-validator): JAXPBR_GLTF_VALIDATOR, else the
# checkout's node_modules (`npm install --no-save gltf-validator`, as .ci/run does).
_VALIDATOR = Path(os.environ.get("JAXPBR_GLTF_VALIDATOR", Path(__file__).resolve().parent.parent / "node_modules" / "gltf-validator"))
_VALIDATE_JS = r"""
const fs = require('fs'); const path = require('path');
const validator = require(process.argv[1]);
(async () => {
  const out = {};
  for (const f of process.argv.slice(2)) {
    const r = await validator.validateBytes(new Uint8Array(fs.readFileSync(f)), {
      uri: path.basename(f), maxIssues: 0, writeTimestamp: false,
      externalResourceFunction: (uri) => new Promise((res, rej) => fs.readFile(
        path.resolve(path.dirname(f), decodeURIComponent(uri)), (e, d) => e ? rej(e.toString()) : res(d)))});
    const lines = (sev) => r.issues.messages.filter(m => m.severity === sev).map(m => `${m.code} ${m.message} ${m.pointer || ''}`);
    out[f] = {numErrors: r.issues.numErrors, numWarnings: r.issues.numWarnings, numInfos: r.issues.numInfos,
              numHints: r.issues.numHints, errors: lines(0), warnings: lines(1)};
  }
  console.log(JSON.stringify(out));
})();
"""


def validator_missing() -> str | None:
    """Why the validator cannot run here (None when it can)."""
    return _npm_missing(_VALIDATOR, "gltf-validator")


def validate(*paths) -> dict:
    """The Khronos glTF-Validator's report of each file: {path: {numErrors, numWarnings, numInfos,
    numHints, errors, warnings}} (errors and warnings as 'CODE message pointer' lines)."""
    run = subprocess.run([shutil.which("node"), "-e", _VALIDATE_JS, str(_VALIDATOR), *map(str, paths)],
                         check=False, capture_output=True, text=True, timeout=120)
    if run.returncode != 0:
        raise RuntimeError(f"gltf-validator failed: {run.stderr}")
    return json.loads(run.stdout)


def assert_valid(*paths):
    """No errors from the Khronos glTF-Validator (the check is skipped when it is not installed)."""
    if validator_missing():
        return
    report = validate(*paths)
    for p in paths:
        assert report[str(p)]["numErrors"] == 0, report[str(p)]["errors"]


#: The unit cube's faces: (normal, u axis, v axis) with u x v = normal, counter-clockwise seen from
#: outside (the cube fixtures of the loader tests and the named assets).
CUBE_FACES = (
    ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    ((-1, 0, 0), (0, 0, 1), (0, 1, 0)),
    ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
    ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
    ((0, 0, 1), (1, 0, 0), (0, 1, 0)),
    ((0, 0, -1), (0, 1, 0), (1, 0, 0)),
)


def uv_sphere(n_lat: int = 24, n_lon: int = 48, radius: float = 1.0):
    """(positions, normals, uv, triangles) of a UV sphere, counter-clockwise seen from outside."""
    lat = np.linspace(0, np.pi, n_lat + 1)
    lon = np.linspace(0, 2 * np.pi, n_lon + 1)
    th, ph = np.meshgrid(lat, lon, indexing="ij")
    n = np.stack([np.sin(th) * np.sin(ph), np.cos(th), np.sin(th) * np.cos(ph)], -1).reshape(-1, 3)
    uv = np.stack([ph / (2 * np.pi), th / np.pi], -1).reshape(-1, 2)
    idx = []
    W = n_lon + 1
    for i in range(n_lat):
        for j in range(n_lon):
            a, b, c, d = i * W + j, (i + 1) * W + j, (i + 1) * W + j + 1, i * W + j + 1
            if i != 0:
                idx.append((a, b, d))
            if i != n_lat - 1:
                idx.append((b, c, d))
    return (radius * n).astype(np.float32), n.astype(np.float32), uv.astype(np.float32), np.asarray(idx, np.int32)


def print_validation(paths) -> int:
    """Validate `paths` and print one line per file (and its errors and warnings): the exit status
    of the fixture scripts' `main` (1 when a file has errors; 0 without the validator)."""
    why = validator_missing()
    if why:
        for p in paths:
            print(f"{p}  {p.stat().st_size} bytes  (not validated: {why})")
        return 0
    report = validate(*paths)
    bad = 0
    for p in paths:
        r = report[str(p)]
        bad += r["numErrors"]
        print(f"{p}  {p.stat().st_size} bytes  errors {r['numErrors']}  warnings {r['numWarnings']}  "
              f"infos {r['numInfos']}  hints {r['numHints']}")
        for line in r["errors"] + r["warnings"]:
            print(f"    {line}")
    return 1 if bad else 0
