"""A small glTF 2.0 writer for render tests: meshes, materials (with PNG textures), lights and
cameras written straight to JSON + one binary buffer (.glb or .gltf with a data URI), independent of
jaxpbr's reader. Only what the tests need; every file it writes passes the Khronos validator
(tests/test_gltf_render.py checks when node and the validator are installed)."""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

FLOAT, UINT32 = 5126, 5125


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
