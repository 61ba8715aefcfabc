"""`check_schema`: the glTF 2.0 JSON checked against the schema's types and ranges before the loader
reads it. In process, no rendering: a valid document is built here (a triangle with
everything the checker covers), one value is changed per case, and the error must name the exact
JSON pointer and the problem. The unchanged document and the named test assets (written by
tests/gltf_assets.py, which the Khronos glTF-Validator passes in tests/test_gltf_assets.py) must
pass; when the validator is installed, it must also pass the document built here and report an
error for every change that the schema forbids (the independent oracle in both directions)."""

from __future__ import annotations

import base64
import json
import math
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from gltf_writer import png_bytes, validate, validator_missing

from jaxpbr.errors import InputError
from jaxpbr.io.gltf._schema import check_schema


# ---------------------------------------------------------------------------------------------
# A valid document touching every checked kind
# ---------------------------------------------------------------------------------------------
def _document() -> dict:
    """A triangle (POSITION, NORMAL, TEXCOORD_0, indices), a sparse accessor, a textured material
    with extensions, two cameras, a point and a spot light, in one buffer as a base64 data URI."""
    chunks = [
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], "<f4").tobytes(),  # 0 POSITION
        np.array([[0, 0, 1]] * 3, "<f4").tobytes(),  # 1 NORMAL
        np.array([[0, 0], [1, 0], [0, 1]], "<f4").tobytes(),  # 2 TEXCOORD_0
        np.array([0, 1, 2], "<u2").tobytes(),  # 3 indices
        np.array([1], "<u1").tobytes(),  # 4 sparse indices
        np.array([2.0], "<f4").tobytes(),  # 5 sparse values
        png_bytes(np.full((2, 2, 3), 200, np.uint8)),  # 6 image
    ]
    data, views = b"", []
    for k, c in enumerate(chunks):
        data += b"\0" * (-len(data) % 4)
        v = {"buffer": 0, "byteOffset": len(data), "byteLength": len(c)}
        if k <= 2:
            v["target"] = 34962
        if k == 3:
            v["target"] = 34963
        views.append(v)
        data += c
    views[0]["byteStride"] = 12
    return {
        "asset": {"version": "2.0", "generator": "jaxpbr tests (test_gltf_schema)"},
        "extensionsUsed": ["KHR_lights_punctual", "KHR_texture_transform", "KHR_materials_ior",
                           "KHR_materials_emissive_strength", "KHR_materials_clearcoat"],
        "scene": 0,
        "scenes": [{"name": "scene", "nodes": [0, 2, 3, 4]}],
        "nodes": [
            {"name": "triangle", "mesh": 0, "children": [1], "translation": [0.0, 0.0, -3.0],
             "rotation": [0.0, 0.0, 0.0, 1.0], "scale": [1.0, 1.0, 1.0]},
            {"camera": 0, "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 5, 1]},
            {"camera": 1, "translation": [0, 0, 5]},
            {"extensions": {"KHR_lights_punctual": {"light": 0}}, "translation": [1.0, 1.0, 1.0]},
            {"extensions": {"KHR_lights_punctual": {"light": 1}}},
        ],
        "meshes": [{"name": "triangle", "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "indices": 3, "material": 0, "mode": 4}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": 3, "type": "VEC2"},
            {"bufferView": 3, "byteOffset": 0, "componentType": 5123, "count": 3, "type": "SCALAR"},
            {"componentType": 5126, "count": 3, "type": "SCALAR", "normalized": False,
             "sparse": {"count": 1, "indices": {"bufferView": 4, "componentType": 5121},
                        "values": {"bufferView": 5, "byteOffset": 0}}},
        ],
        "bufferViews": views,
        "buffers": [{"byteLength": len(data),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
        "images": [{"bufferView": 6, "mimeType": "image/png"}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 33071}],
        "textures": [{"sampler": 0, "source": 0}],
        "materials": [{
            "name": "textured",
            "pbrMetallicRoughness": {
                "baseColorFactor": [1.0, 0.5, 0.25, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.5,
                "baseColorTexture": {"index": 0, "texCoord": 0, "extensions": {"KHR_texture_transform": {
                    "offset": [0.5, 0.0], "rotation": 0.25, "scale": [2.0, 2.0]}}}},
            "normalTexture": {"index": 0, "scale": 1.0},
            "occlusionTexture": {"index": 0, "strength": 0.5},
            "emissiveTexture": {"index": 0},
            "emissiveFactor": [0.1, 0.1, 0.1],
            "alphaMode": "MASK", "alphaCutoff": 0.5, "doubleSided": True,
            "extensions": {
                "KHR_materials_ior": {"ior": 1.4},
                "KHR_materials_emissive_strength": {"emissiveStrength": 2.0},
                "KHR_materials_clearcoat": {"clearcoatFactor": 1.0, "clearcoatRoughnessFactor": 0.2},
            },
        }],
        "cameras": [
            {"name": "perspective", "type": "perspective",
             "perspective": {"yfov": 0.8, "znear": 0.1, "zfar": 100.0, "aspectRatio": 1.5}},
            {"type": "orthographic", "orthographic": {"xmag": 2.0, "ymag": 1.5, "znear": 0.0, "zfar": 10.0}},
        ],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"name": "point", "type": "point", "color": [1.0, 0.9, 0.8], "intensity": 5.0, "range": 10.0},
            {"type": "spot", "intensity": 2, "spot": {"innerConeAngle": 0.3, "outerConeAngle": 0.6}},
        ]}},
    }


def _at(doc, path: str):
    """(the object holding the last key of a JSON pointer, that key)."""
    parts = [int(p) if p.isdigit() else p for p in path.strip("/").split("/")]
    obj = doc
    for p in parts[:-1]:
        obj = obj[p]
    return obj, parts[-1]


def _set(path, value):
    def edit(doc):
        obj, key = _at(doc, path)
        obj[key] = value
    return edit


def _delete(path):
    def edit(doc):
        obj, key = _at(doc, path)
        del obj[key]
    return edit


def _add_primitive_extension(name, value):
    def edit(doc):
        doc["meshes"][0]["primitives"][0]["extensions"] = {name: value}
        doc["extensionsUsed"].append(name)
    return edit


def _add_node_extension(name, value):
    def edit(doc):
        doc["nodes"][0].setdefault("extensions", {})[name] = value
        doc["extensionsUsed"].append(name)
    return edit


def _add_material_extension(name, value):
    def edit(doc):
        doc["materials"][0]["extensions"][name] = value
        doc["extensionsUsed"].append(name)
    return edit


NAN, INF = float("nan"), float("inf")

#: (id, the change, the JSON pointer the error must name, words of the problem it must state, what
#: the Khronos glTF-Validator (2.0.0-dev.3.x) reports at or next to that pointer: "error"; "warning"
#: for a value outside an enum, which the schema leaves open for later versions (anyOf with any
#: integer / string) but which jaxpbr cannot read, and for yfov >= pi; None where it reports
#: nothing: 3.0 for an integer (the validator reads it as 3; the schema's JSON Schema draft 4 says
#: an integer has no fraction) and the extensions it does not check (instancing, Draco)).
CASES = [
    ("count-string", _set("/accessors/0/count", "3"), "/accessors/0/count", 'count "3" is a string; expected an integer >= 1', "error"),
    ("count-fraction", _set("/accessors/0/count", 3.5), "/accessors/0/count", "is not an integer", "error"),
    ("count-float-integral", _set("/accessors/0/count", 3.0), "/accessors/0/count", "count 3.0 is not an integer", None),
    ("count-zero", _set("/accessors/0/count", 0), "/accessors/0/count", "count 0 is out of range; expected an integer >= 1", "error"),
    ("count-bool", _set("/accessors/0/count", True), "/accessors/0/count", "count true is a boolean", "error"),
    ("count-missing", _delete("/accessors/1/count"), "/accessors/1", "the required property count is missing", "error"),
    ("componentType", _set("/accessors/0/componentType", 1), "/accessors/0/componentType",
     "componentType 1 is not a valid value; expected one of 5120 (BYTE)", "warning"),
    ("accessor-type", _set("/accessors/2/type", "VEC5"), "/accessors/2/type", 'type "VEC5" is not a valid value', "warning"),
    ("accessor-byteOffset", _set("/accessors/3/byteOffset", -4), "/accessors/3/byteOffset", "is out of range; expected an integer >= 0", "error"),
    ("normalized", _set("/accessors/4/normalized", 0), "/accessors/4/normalized", "normalized 0 is an integer; expected true or false", "error"),
    ("max-nan", _set("/accessors/0/max", [1, NAN, 0]), "/accessors/0/max/1", "max[1] NaN is not a finite number", "error"),
    ("max-too-long", _set("/accessors/0/max", [0] * 17), "/accessors/0/max", "has 17 items; expected an array of 1 to 16", "error"),
    ("sparse-count", _set("/accessors/4/sparse/count", 0), "/accessors/4/sparse/count", "out of range", "error"),
    ("sparse-componentType", _set("/accessors/4/sparse/indices/componentType", 5126),
     "/accessors/4/sparse/indices/componentType", "5126 is not a valid value", "warning"),
    ("sparse-values-view", _set("/accessors/4/sparse/values/bufferView", 70), "/accessors/4/sparse/values/bufferView",
     "names bufferView 70, which does not exist (the file has 7)", "error"),
    ("accessor-view-range", _set("/accessors/1/bufferView", 7), "/accessors/1/bufferView",
     "names bufferView 7, which does not exist (the file has 7)", "error"),
    ("byteStride-3", _set("/bufferViews/0/byteStride", 3), "/bufferViews/0/byteStride",
     "byteStride 3 is out of range; expected an integer in [4, 252] and a multiple of 4", "error"),
    ("byteStride-6", _set("/bufferViews/0/byteStride", 6), "/bufferViews/0/byteStride", "multiple of 4", "error"),
    ("byteStride-256", _set("/bufferViews/0/byteStride", 256), "/bufferViews/0/byteStride", "out of range", "error"),
    ("view-byteLength", _set("/bufferViews/1/byteLength", 0), "/bufferViews/1/byteLength", "expected an integer >= 1", "error"),
    ("view-target", _set("/bufferViews/1/target", 1), "/bufferViews/1/target", "expected one of 34962", "warning"),
    ("view-buffer", _set("/bufferViews/1/buffer", 1), "/bufferViews/1/buffer",
     "names buffer 1, which does not exist (the file has 1)", "error"),
    ("buffer-byteLength", _set("/buffers/0/byteLength", "100"), "/buffers/0/byteLength", "is a string", "error"),
    ("buffer-uri", _set("/buffers/0/uri", 7), "/buffers/0/uri", "uri 7 is an integer; expected a string", "error"),
    ("mode-9", _set("/meshes/0/primitives/0/mode", 9), "/meshes/0/primitives/0/mode",
     "mode 9 is not a valid value; expected one of 0 (POINTS)", "error"),
    ("primitives-empty", _set("/meshes/0/primitives", []), "/meshes/0/primitives", "primitives [] is an empty array", "error"),
    ("primitives-missing", _delete("/meshes/0/primitives"), "/meshes/0", "the required property primitives is missing", "error"),
    ("attributes-string", _set("/meshes/0/primitives/0/attributes", "POSITION"), "/meshes/0/primitives/0/attributes",
     'attributes "POSITION" is a string; expected a non-empty object', "error"),
    ("attributes-empty", _set("/meshes/0/primitives/0/attributes", {}), "/meshes/0/primitives/0/attributes",
     "is an empty object", "error"),
    ("attribute-range", _set("/meshes/0/primitives/0/attributes/NORMAL", 12), "/meshes/0/primitives/0/attributes/NORMAL",
     "names accessor 12, which does not exist (the file has 5)", "error"),
    ("indices-range", _set("/meshes/0/primitives/0/indices", 12), "/meshes/0/primitives/0/indices",
     "names accessor 12, which does not exist (the file has 5)", "error"),
    ("indices-bool", _set("/meshes/0/primitives/0/indices", True), "/meshes/0/primitives/0/indices", "is a boolean", "error"),
    ("material-range", _set("/meshes/0/primitives/0/material", 1), "/meshes/0/primitives/0/material",
     "names material 1, which does not exist (the file has 1)", "error"),
    ("targets-empty", _set("/meshes/0/primitives/0/targets", []), "/meshes/0/primitives/0/targets", "is an empty array", "error"),
    ("targets-range", _set("/meshes/0/primitives/0/targets", [{"POSITION": 9}]), "/meshes/0/primitives/0/targets/0/POSITION",
     "names accessor 9", "error"),
    ("mesh-weights", _set("/meshes/0/weights", ["1"]), "/meshes/0/weights/0", 'weights[0] "1" is a string', "error"),
    ("scene-range", _set("/scene", 3), "/scene", "names scene 3, which does not exist (the file has 1)", "error"),
    ("scene-nodes-range", _set("/scenes/0/nodes", [0, 9]), "/scenes/0/nodes/1", "names node 9", "error"),
    ("scene-nodes-duplicate", _set("/scenes/0/nodes", [0, 2, 0]), "/scenes/0/nodes/2", "repeats an earlier item", "error"),
    ("children-non-int", _set("/nodes/0/children", [1, "2"]), "/nodes/0/children/1",
     'children[1] "2" is a string; expected an integer >= 0', "error"),
    ("children-negative", _set("/nodes/0/children", [-1]), "/nodes/0/children/0", "out of range", "error"),
    ("children-object", _set("/nodes/0/children", {"0": 1}), "/nodes/0/children", "is an object; expected an array", "error"),
    ("node-mesh-bool", _set("/nodes/0/mesh", True), "/nodes/0/mesh", "mesh true is a boolean; expected an integer >= 0", "error"),
    ("node-mesh-range", _set("/nodes/0/mesh", 4), "/nodes/0/mesh", "names mesh 4, which does not exist (the file has 1)", "error"),
    ("node-camera-range", _set("/nodes/1/camera", 2), "/nodes/1/camera", "names camera 2", "error"),
    ("node-skin-range", _set("/nodes/0/skin", 0), "/nodes/0/skin", "names skin 0, which does not exist (the file has 0)", "error"),
    ("matrix-15", _set("/nodes/1/matrix", [1.0] * 15), "/nodes/1/matrix", "has 15 items; expected an array of 16", "error"),
    ("rotation-range", _set("/nodes/0/rotation", [0.0, 0.0, 2.0, 1.0]), "/nodes/0/rotation/2",
     "rotation[2] 2.0 is out of range; expected a number in [-1, 1]", "error"),
    ("translation-2", _set("/nodes/0/translation", [0.0, 1.0]), "/nodes/0/translation", "has 2 items", "error"),
    ("scale-infinity", _set("/nodes/0/scale", [1.0, INF, 1.0]), "/nodes/0/scale/1", "Infinity is not a finite number", "error"),
    ("node-name", _set("/nodes/0/name", 5), "/nodes/0/name", "name 5 is an integer; expected a string", "error"),
    ("node-string", _set("/nodes/2", "node"), "/nodes/2", 'nodes[2] "node" is a string; expected an object', "error"),
    ("nodes-object", _set("/nodes", {"a": {}}), "/nodes", "is an object; expected an array of objects", "error"),
    ("asset-string", _set("/asset", "2.0"), "/asset", 'asset "2.0" is a string; expected an object', "error"),
    ("asset-version-number", _set("/asset/version", 2.0), "/asset/version", "version 2.0 is a number; expected a string", "error"),
    ("asset-generator", _set("/asset/generator", ["x"]), "/asset/generator", "is an array; expected a string", "error"),
    ("extensionsUsed-duplicate", _set("/extensionsUsed", ["KHR_lights_punctual", "KHR_lights_punctual"]),
     "/extensionsUsed/1", "repeats an earlier item", "error"),
    ("extensionsRequired-int", _set("/extensionsRequired", [3]), "/extensionsRequired/0", "is an integer; expected a string", "error"),
    ("extensions-array", _set("/nodes/0/extensions", []), "/nodes/0/extensions", "is an array; expected an object", "error"),
    ("image-view-range", _set("/images/0/bufferView", 9), "/images/0/bufferView", "names bufferView 9", "error"),
    ("image-mimeType", _set("/images/0/mimeType", 5), "/images/0/mimeType", "is an integer; expected a string", "error"),
    ("magFilter", _set("/samplers/0/magFilter", 9987), "/samplers/0/magFilter", "9987 is not a valid value", "warning"),
    ("minFilter", _set("/samplers/0/minFilter", 0), "/samplers/0/minFilter", "expected one of 9728 (NEAREST)", "warning"),
    ("wrapS", _set("/samplers/0/wrapS", 1), "/samplers/0/wrapS", "wrapS 1 is not a valid value", "warning"),
    ("texture-source", _set("/textures/0/source", 1), "/textures/0/source", "names image 1, which does not exist (the file has 1)", "error"),
    ("texture-sampler", _set("/textures/0/sampler", 2), "/textures/0/sampler", "names sampler 2", "error"),
    ("baseColorFactor", _set("/materials/0/pbrMetallicRoughness/baseColorFactor", [2, 0, 0, 1]),
     "/materials/0/pbrMetallicRoughness/baseColorFactor/0", "baseColorFactor[0] 2 is out of range; expected a number in [0, 1]", "error"),
    ("baseColorFactor-3", _set("/materials/0/pbrMetallicRoughness/baseColorFactor", [1, 1, 1]),
     "/materials/0/pbrMetallicRoughness/baseColorFactor", "has 3 items", "error"),
    ("metallicFactor", _set("/materials/0/pbrMetallicRoughness/metallicFactor", -0.5),
     "/materials/0/pbrMetallicRoughness/metallicFactor", "out of range", "error"),
    ("roughnessFactor-string", _set("/materials/0/pbrMetallicRoughness/roughnessFactor", "0.5"),
     "/materials/0/pbrMetallicRoughness/roughnessFactor", "is a string; expected a number in [0, 1]", "error"),
    ("texture-index-range", _set("/materials/0/pbrMetallicRoughness/baseColorTexture/index", 4),
     "/materials/0/pbrMetallicRoughness/baseColorTexture/index", "names texture 4, which does not exist (the file has 1)", "error"),
    ("texture-index-missing", _delete("/materials/0/emissiveTexture/index"), "/materials/0/emissiveTexture",
     "the required property index is missing", "error"),
    ("texCoord", _set("/materials/0/normalTexture/texCoord", -1), "/materials/0/normalTexture/texCoord", "out of range", "error"),
    ("normal-scale", _set("/materials/0/normalTexture/scale", "1"), "/materials/0/normalTexture/scale", "is a string", "error"),
    ("occlusion-strength", _set("/materials/0/occlusionTexture/strength", 1.5), "/materials/0/occlusionTexture/strength",
     "expected a number in [0, 1]", "error"),
    ("emissiveFactor", _set("/materials/0/emissiveFactor", [0, 0, 1.5]), "/materials/0/emissiveFactor/2", "out of range", "error"),
    ("alphaMode", _set("/materials/0/alphaMode", "SEMI"), "/materials/0/alphaMode",
     'alphaMode "SEMI" is not a valid value; expected one of "OPAQUE", "MASK", "BLEND"', "warning"),
    ("alphaCutoff", _set("/materials/0/alphaCutoff", -0.5), "/materials/0/alphaCutoff", "expected a number >= 0", "error"),
    ("doubleSided", _set("/materials/0/doubleSided", "yes"), "/materials/0/doubleSided", "expected true or false", "error"),
    ("texture-transform-offset", _set("/materials/0/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/offset", [1]),
     "/materials/0/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/offset", "has 1 items", "error"),
    ("texture-transform-texCoord", _set("/materials/0/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/texCoord", 0.5),
     "/materials/0/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/texCoord", "is not an integer", "error"),
    ("texture-transform-rotation", _set("/materials/0/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/rotation", NAN),
     "/materials/0/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/rotation", "NaN is not a finite number", "error"),
    ("ior", _set("/materials/0/extensions/KHR_materials_ior/ior", 0.5), "/materials/0/extensions/KHR_materials_ior/ior",
     "ior 0.5 is out of range; expected 0 or a number >= 1", "error"),
    ("emissiveStrength", _set("/materials/0/extensions/KHR_materials_emissive_strength/emissiveStrength", -1),
     "/materials/0/extensions/KHR_materials_emissive_strength/emissiveStrength", "expected a number >= 0", "error"),
    ("clearcoatFactor", _set("/materials/0/extensions/KHR_materials_clearcoat/clearcoatFactor", 2.0),
     "/materials/0/extensions/KHR_materials_clearcoat/clearcoatFactor", "out of range", "error"),
    ("clearcoat-string", _set("/materials/0/extensions/KHR_materials_clearcoat", "on"),
     "/materials/0/extensions/KHR_materials_clearcoat", "is a string; expected an object", "error"),
    ("transmissionFactor", _add_material_extension("KHR_materials_transmission", {"transmissionFactor": 1.5}),
     "/materials/0/extensions/KHR_materials_transmission/transmissionFactor", "out of range", "error"),
    ("attenuationDistance", _add_material_extension("KHR_materials_volume", {"attenuationDistance": 0}),
     "/materials/0/extensions/KHR_materials_volume/attenuationDistance", "expected a number > 0", "error"),
    ("thicknessFactor", _add_material_extension("KHR_materials_volume", {"thicknessFactor": -1}),
     "/materials/0/extensions/KHR_materials_volume/thicknessFactor", "expected a number >= 0", "error"),
    ("specularColorFactor", _add_material_extension("KHR_materials_specular", {"specularColorFactor": [1, -1, 1]}),
     "/materials/0/extensions/KHR_materials_specular/specularColorFactor/1", "out of range", "error"),
    ("sheenRoughnessFactor", _add_material_extension("KHR_materials_sheen", {"sheenRoughnessFactor": 1.01}),
     "/materials/0/extensions/KHR_materials_sheen/sheenRoughnessFactor", "out of range", "error"),
    ("anisotropyStrength", _add_material_extension("KHR_materials_anisotropy", {"anisotropyStrength": -0.1}),
     "/materials/0/extensions/KHR_materials_anisotropy/anisotropyStrength", "out of range", "error"),
    ("iridescenceIor", _add_material_extension("KHR_materials_iridescence", {"iridescenceIor": 0.9}),
     "/materials/0/extensions/KHR_materials_iridescence/iridescenceIor", "expected a number >= 1", "error"),
    ("yfov-zero", _set("/cameras/0/perspective/yfov", 0), "/cameras/0/perspective/yfov",
     "yfov 0 is out of range; expected a number in (0, pi)", "error"),
    ("yfov-nan", _set("/cameras/0/perspective/yfov", NAN), "/cameras/0/perspective/yfov", "yfov NaN is not a finite number", "error"),
    ("yfov-overflow", _set("/cameras/0/perspective/yfov", 10**400), "/cameras/0/perspective/yfov",
     "is beyond the range of a 64-bit float", "error"),  # (an integer literal: the validator reads Infinity)
    ("yfov-pi", _set("/cameras/0/perspective/yfov", math.pi), "/cameras/0/perspective/yfov", "out of range", "warning"),
    ("znear-negative", _set("/cameras/0/perspective/znear", -1), "/cameras/0/perspective/znear",
     "znear -1 is out of range; expected a number > 0", "error"),
    ("zfar-below-znear", _set("/cameras/0/perspective/zfar", 0.05), "/cameras/0/perspective/zfar",
     "zfar 0.05 is not greater than znear 0.1", "error"),
    ("aspectRatio", _set("/cameras/0/perspective/aspectRatio", 0), "/cameras/0/perspective/aspectRatio", "expected a number > 0", "error"),
    ("yfov-missing", _delete("/cameras/0/perspective/yfov"), "/cameras/0/perspective", "the required property yfov is missing", "error"),
    ("perspective-missing", _delete("/cameras/0/perspective"), "/cameras/0/type", "needs the camera's perspective object", "error"),
    ("camera-type", _set("/cameras/0/type", "fisheye"), "/cameras/0/type", 'type "fisheye" is not a valid value', "warning"),
    ("xmag-zero", _set("/cameras/1/orthographic/xmag", 0), "/cameras/1/orthographic/xmag",
     "xmag 0 is out of range; expected a finite non-zero number", "error"),
    ("ortho-znear-negative", _set("/cameras/1/orthographic/znear", -1.0), "/cameras/1/orthographic/znear", "expected a number >= 0", "error"),
    ("ortho-zfar-zero", _set("/cameras/1/orthographic/zfar", 0), "/cameras/1/orthographic/zfar", "expected a number > 0", "error"),
    ("ortho-zfar-below-znear", _set("/cameras/1/orthographic/znear", 20.0), "/cameras/1/orthographic/zfar",
     "zfar 10.0 is not greater than znear 20.0", "error"),
    ("light-intensity-nan", _set("/extensions/KHR_lights_punctual/lights/0/intensity", NAN),
     "/extensions/KHR_lights_punctual/lights/0/intensity", "intensity NaN is not a finite number", "error"),
    ("light-intensity-negative", _set("/extensions/KHR_lights_punctual/lights/0/intensity", -1),
     "/extensions/KHR_lights_punctual/lights/0/intensity", "intensity -1 is out of range; expected a number >= 0", "error"),
    ("light-range-zero", _set("/extensions/KHR_lights_punctual/lights/0/range", 0),
     "/extensions/KHR_lights_punctual/lights/0/range", "range 0 is out of range; expected a number > 0", "error"),
    ("light-color", _set("/extensions/KHR_lights_punctual/lights/0/color", [1, 2, 1]),
     "/extensions/KHR_lights_punctual/lights/0/color/1", "out of range", "error"),
    ("light-type", _set("/extensions/KHR_lights_punctual/lights/0/type", "area"),
     "/extensions/KHR_lights_punctual/lights/0/type", 'type "area" is not a valid value', "warning"),
    ("spot-inner-equals-outer", _set("/extensions/KHR_lights_punctual/lights/1/spot/innerConeAngle", 0.6),
     "/extensions/KHR_lights_punctual/lights/1/spot/innerConeAngle", "innerConeAngle 0.6 is not smaller than outerConeAngle 0.6", "error"),
    ("spot-outer-default", _set("/extensions/KHR_lights_punctual/lights/1/spot", {"innerConeAngle": 1.0}),
     "/extensions/KHR_lights_punctual/lights/1/spot/innerConeAngle", "is not smaller than outerConeAngle", "error"),
    ("spot-outer-beyond", _set("/extensions/KHR_lights_punctual/lights/1/spot/outerConeAngle", 2.0),
     "/extensions/KHR_lights_punctual/lights/1/spot/outerConeAngle", "expected a number in (0, pi/2]", "error"),
    ("spot-inner-negative", _set("/extensions/KHR_lights_punctual/lights/1/spot/innerConeAngle", -0.1),
     "/extensions/KHR_lights_punctual/lights/1/spot/innerConeAngle", "expected a number in [0, pi/2)", "error"),
    ("node-light-range", _set("/nodes/3/extensions/KHR_lights_punctual/light", 2),
     "/nodes/3/extensions/KHR_lights_punctual/light", "names KHR_lights_punctual light 2, which does not exist (the file has 2)", "error"),
    ("node-light-missing", _set("/nodes/3/extensions/KHR_lights_punctual", {}),
     "/nodes/3/extensions/KHR_lights_punctual", "the required property light is missing", "error"),
    ("lights-string", _set("/extensions/KHR_lights_punctual/lights", "all"), "/extensions/KHR_lights_punctual/lights",
     "is a string; expected an array of objects", "error"),
    ("instancing-range", _add_node_extension("EXT_mesh_gpu_instancing", {"attributes": {"TRANSLATION": 99}}),
     "/nodes/0/extensions/EXT_mesh_gpu_instancing/attributes/TRANSLATION", "names accessor 99", None),
    ("instancing-string", _add_node_extension("EXT_mesh_gpu_instancing", {"attributes": {"SCALE": "0"}}),
     "/nodes/0/extensions/EXT_mesh_gpu_instancing/attributes/SCALE", 'SCALE "0" is a string', None),
    ("draco-view", _add_primitive_extension("KHR_draco_mesh_compression", {"bufferView": 99, "attributes": {"POSITION": 0}}),
     "/meshes/0/primitives/0/extensions/KHR_draco_mesh_compression/bufferView", "names bufferView 99", None),
    ("draco-attributes", _add_primitive_extension("KHR_draco_mesh_compression", {"bufferView": 0, "attributes": {"POSITION": 0.5}}),
     "/meshes/0/primitives/0/extensions/KHR_draco_mesh_compression/attributes/POSITION", "is not an integer", None),
    ("webp-source", lambda d: (d["textures"][0].update(extensions={"EXT_texture_webp": {"source": 3}}),
                               d["extensionsUsed"].append("EXT_texture_webp")),
     "/textures/0/extensions/EXT_texture_webp/source", "names image 3", "error"),
    ("skin-joints", _set("/skins", [{"joints": [0, 0]}]), "/skins/0/joints/1", "repeats an earlier item", "error"),
]


def _mutated(change) -> dict:
    doc = _document()
    change(doc)
    return doc


def _message(doc) -> str:
    with pytest.raises(InputError) as e:
        check_schema(Path("asset.gltf"), doc)
    return str(e.value)


def test_the_valid_document_passes():
    check_schema("asset.gltf", _document())


@pytest.mark.parametrize("change,at,problem", [c[1:4] for c in CASES], ids=[c[0] for c in CASES])
def test_a_bad_value_is_refused_with_its_pointer(change, at, problem):
    msg = _message(_mutated(change))
    assert f"({at}): " in msg, msg
    assert problem in msg, msg
    assert msg.startswith("glTF file 'asset.gltf': ") and msg.endswith(
        "Fix: repair or re-export the asset (the Khronos glTF-Validator names the problem)"), msg


def test_json_text_with_nan_literals_is_refused():
    """The NaN / Infinity literals Python's json reads (they are not JSON)."""
    doc = _document()
    doc["cameras"][0]["perspective"]["yfov"] = NAN
    parsed = json.loads(json.dumps(doc, allow_nan=True))
    assert "/cameras/0/perspective/yfov" in _message(parsed)
    text = json.dumps(_document()).replace('"intensity": 5.0', '"intensity": Infinity')
    assert "(/extensions/KHR_lights_punctual/lights/0/intensity): intensity Infinity is not a finite number" in _message(json.loads(text))
    text = json.dumps(_document()).replace('"yfov": 0.8', '"yfov": 1e400')  # a float literal beyond float64: inf
    assert "yfov Infinity is not a finite number" in _message(json.loads(text))


def test_what_the_schema_allows_passes():
    """A primitive without POSITION (the loader skips it with a note), unknown properties, extras
    and unknown extensions (not checked), empty top-level arrays, an unused sampler left at its
    defaults, integer-valued numbers, zfar absent, ior 0."""
    doc = _document()
    del doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    doc["nodes"][0]["extras"] = {"anything": [float("nan"), "x", None]}
    doc["nodes"][0]["unknownProperty"] = "x"
    doc["nodes"][0]["extensions"] = {"VENDOR_unknown": "not an object, not checked"}
    doc["animations"] = []
    doc["skins"] = []
    doc["samplers"].append({})
    doc["cameras"][0]["perspective"] = {"yfov": 1, "znear": 1}
    doc["materials"][0]["extensions"]["KHR_materials_ior"]["ior"] = 0
    doc["materials"][0]["extensions"]["KHR_materials_unlit"] = {}
    doc["extensions"]["KHR_lights_punctual"]["lights"][1]["spot"] = {}
    check_schema("asset.gltf", doc)


def test_messages_abbreviate_the_value():
    doc = _document()
    doc["nodes"][0]["name"] = ["x" * 10_000] * 10_000
    msg = _message(doc)
    assert "(/nodes/0/name): name [" in msg and '... is an array; expected a string' in msg, msg
    assert len(msg) < 300, msg
    doc = _document()
    deep: list = []
    for _ in range(100_000):  # nested far deeper than the recursion limit: the rendering stops early
        deep = [deep]
    doc["accessors"][0]["count"] = deep
    msg = _message(doc)
    assert "(/accessors/0/count): count [[[[" in msg and "is an array" in msg and len(msg) < 300, msg
    doc = _document()
    doc["materials"][0]["alphaMode"] = "Z" * 5000
    msg = _message(doc)
    assert 'alphaMode "ZZZZ' in msg and len(msg) < 300, msg


def test_a_long_reference_list_is_checked_quickly():
    """10^5 nodes (a children list of 10^5 entries; TRS, name and mesh on every node) in well under
    a second (measured, 10^6 such nodes: 1.5 s; 10^6 nodes naming a mesh: 0.3 s); the last entry,
    out of range, is found."""
    n = 100_000
    doc = _document()
    doc["nodes"] = [{"children": list(range(1, n))}] + [
        {"mesh": 0, "name": f"n{i}", "translation": [float(i), 0.0, 0.0], "rotation": [0, 0, 0, 1], "scale": [1, 1, 1]}
        for i in range(1, n)]
    doc["scenes"] = [{"nodes": [0]}]
    doc["cameras"] = []
    doc["extensions"] = {}
    t = time.perf_counter()
    check_schema("big.gltf", doc)
    assert time.perf_counter() - t < 2.0
    doc["nodes"][0]["children"][-1] = n
    assert f"(/nodes/0/children/{n - 2}): names node {n}, which does not exist (the file has {n})" in _message(doc)


def _json_of(path: Path) -> dict:
    data = path.read_bytes()
    if data[:4] == b"glTF":
        length, kind = struct.unpack_from("<I4s", data, 12)
        assert kind == b"JSON"
        return json.loads(data[20 : 20 + length])
    return json.loads(data)


def test_the_named_test_assets_pass(tmp_path):
    """The assets tests/gltf_assets.py writes (validated by the Khronos glTF-Validator in
    tests/test_gltf_assets.py): an independent check that valid files are not refused."""
    from gltf_assets import write_all

    paths = write_all(tmp_path)
    assert len(paths) >= 7
    for p in paths.values():
        check_schema(p, _json_of(p))


@pytest.mark.parametrize("suffix", [".gltf", ".glb"])
def test_the_render_tests_writer_output_passes(tmp_path, suffix):
    """tests/gltf_writer.py's Writer (the render tests' files): a textured sphere, a second material,
    a perspective camera, a spot light; validated here too when the validator is installed."""
    from gltf_writer import Writer, assert_valid, uv_sphere

    w = Writer()
    t = w.image_png(np.full((4, 4, 3), 0.5, np.float32))
    m = w.material(pbrMetallicRoughness={"baseColorTexture": {"index": t}, "metallicFactor": 0.0, "roughnessFactor": 0.6})
    m2 = w.material(alphaMode="MASK", alphaCutoff=0.25, pbrMetallicRoughness={"baseColorFactor": [1, 1, 1, 0.8]})
    pos, nrm, uv, tri = uv_sphere(6, 12)
    w.node(mesh=w.mesh(pos, tri, normals=nrm, uv=uv, material=m))
    w.node(mesh=w.mesh(pos + np.float32([3, 0, 0]), tri, normals=nrm, material=m2), translation=[0.0, 1.0, 0.0])
    cam = w.camera(type="perspective", perspective={"yfov": math.radians(50), "znear": 0.01})
    q = [-math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4)]
    w.node(camera=cam, translation=[0.0, 3.0, 0.0], rotation=q)
    lt = w.light(type="spot", intensity=40.0, spot={"innerConeAngle": 0.1, "outerConeAngle": 0.3})
    w.node(translation=[0.0, 3.0, 0.0], rotation=q, extensions={"KHR_lights_punctual": {"light": lt}})
    path = w.save(tmp_path / f"writer{suffix}")
    assert_valid(path)
    check_schema(path, _json_of(path))


def _related(issue: str, at: str) -> bool:
    """Whether a validator issue ('CODE message pointer') is about the value at `at`: the same
    pointer, one containing the other, or a sibling (a cross-property check names either value);
    a JSON syntax error (NaN, Infinity) has no pointer."""
    if issue.startswith("INVALID_JSON"):
        return True
    p = issue.rsplit(" ", 1)[-1]
    return p == at or at.startswith(p + "/") or p.startswith(at + "/") or p.rsplit("/", 1)[0] == at.rsplit("/", 1)[0]


def test_the_khronos_validator_agrees(tmp_path):
    """The Khronos glTF-Validator passes the document built here and reports each change as the
    case says (an error, or a warning, about the same value)."""
    why = validator_missing()
    if why:
        pytest.skip(why)
    files = {"valid": tmp_path / "valid.gltf"}
    files["valid"].write_text(json.dumps(_document()))
    for name, change, *_ in CASES:
        files[name] = tmp_path / f"{name}.gltf"
        files[name].write_text(json.dumps(_mutated(change), allow_nan=True))
    report = validate(*files.values())
    assert report[str(files["valid"])]["numErrors"] == 0, report[str(files["valid"])]["errors"]
    wrong = {}
    for name, _, at, _, expected in CASES:
        r = report[str(files[name])]
        errors = [i for i in r["errors"] if _related(i, at)]
        warnings = [i for i in r["warnings"] if _related(i, at)]
        got = "error" if errors else "warning" if warnings else None
        if got != expected:
            wrong[name] = (expected, got, r["errors"][:2], r["warnings"][:2])
    assert not wrong, wrong


def test_read_gltf_refuses_a_string_count(tmp_path):
    from jaxpbr.io.gltf import read_gltf

    doc = _document()
    doc["accessors"][0]["count"] = "3"
    path = tmp_path / "count.gltf"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="/accessors/0/count"):
        read_gltf(path)


def test_cases_are_distinct_and_change_the_document():
    assert len({c[0] for c in CASES}) == len(CASES)
    valid = json.dumps(_document())
    for c in CASES:
        assert json.dumps(_mutated(c[1]), allow_nan=True) != valid, c[0]
