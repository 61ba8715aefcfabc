"""three.js as an independent oracle of glTF animation, skinning and morph targets.

tests/three_pose.mjs loads an asset with three's GLTFLoader, plays one animation with its
AnimationMixer and writes the world-space position of every vertex of every mesh primitive of the
default scene at the given times (morph targets, then skinning, then the node's world matrix).
three_pose() runs it and returns the positions as float64 arrays.

three is found at JAXPBR_THREE (the package's folder), else in the checkout's node_modules
(`npm install --no-save --no-package-lock three@0.170.0`, as .ci/run does).

Where three (r170) departs from the specification, and what the script does about it:
- a morph target without POSITION beside others that have one: GLTFLoader displaces by the base
  positions; the script replaces it by zeros (the specification: no displacement);
- skin weights: JOINTS_0/WEIGHTS_0 only (JOINTS_1/WEIGHTS_1 are ignored), renormalised to sum 1
  (all-zero weights become (1, 0, 0, 0)); the mesh node's own transform is ignored, as specified;
- a `weights` channel: GLTFLoader binds it to every object with morph targets under the node, so
  the meshes of descendant nodes follow it too; the script re-binds it to the node's own primitives;
- the keyed quaternions are used as stored (not normalised); between two equal keys three returns
  the key itself, a slerp of non-unit keys elsewhere differs from a normalising one by about the
  keys' deviation from unit length (SimpleSkin's (0, 0, 0.707, 0.707): 2e-4);
- EXT_mesh_gpu_instancing nodes are skipped (listed in "skipped"); Draco-compressed meshes fail;
- times: the clip is played once and clamped (t < 0 poses at 0, t past the clip's duration, the
  largest last key of its channels, at the duration); before its first key / after its last a
  channel holds its first / last value; LINEAR rotations are slerped along the shorter arc
  (Quaternion.slerpFlat; a plain normalised lerp where the two keys are nearly equal), CUBICSPLINE
  is glTF's Hermite with the tangents scaled by the key interval (rotations normalised after), STEP
  holds the key at or before t.
Key times and values, vertex data and skin weights are float32 as stored; the arithmetic is float64.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from gltf_writer import _npm_missing

_ROOT = Path(__file__).resolve().parent.parent
#: three (npm package three): JAXPBR_THREE, else the checkout's node_modules.
_THREE = Path(os.environ.get("JAXPBR_THREE", _ROOT / "node_modules" / "three"))
_SCRIPT = Path(__file__).resolve().parent / "three_pose.mjs"
#: The version .ci/run installs (the script works with others; this is the one it was checked with).
THREE_VERSION = "0.170.0"


def three_missing() -> str | None:
    """Why the three.js oracle cannot run here (None when it can)."""
    return _npm_missing(_THREE / "package.json", f"three@{THREE_VERSION}")


def three_pose(path, animation, times, *, timeout: float = 300) -> dict:
    """World-space vertex positions of every mesh primitive of the asset at `path` (.gltf or .glb)
    at `times` (seconds) of `animation` (an index, a name, or None / "none": the rest pose).

    Returns the script's document with "positions" replaced by
    {(node, mesh, primitive): float64 array of shape (len(times), V, 3)} and the per-primitive
    records (kind, count) in "primitives"; "animation" is {"index", "name", "duration"} or None."""
    why = three_missing()
    if why:
        raise RuntimeError(f"the three.js oracle cannot run: {why}")
    times = [float(t) for t in np.atleast_1d(np.asarray(times, dtype=np.float64))]
    if not times:
        raise ValueError("three_pose needs at least one time")
    anim = "none" if animation is None else str(animation)
    env = dict(os.environ, JAXPBR_THREE=str(_THREE))
    with tempfile.TemporaryDirectory(prefix="jaxpbr_three_") as tmp:
        out = Path(tmp) / "pose.json"
        run = subprocess.run(
            [shutil.which("node"), str(_SCRIPT), str(Path(path).resolve()), "--animation", anim,
             "--times", ",".join(repr(t) for t in times), "--out", str(out)],
            check=False, capture_output=True, text=True, timeout=timeout, env=env)
        if run.returncode != 0:
            raise RuntimeError(f"three_pose.mjs failed on {path} (exit {run.returncode}): {run.stderr}{run.stdout}")
        doc = json.loads(out.read_text())
    positions = {}
    for p in doc["primitives"]:
        a = np.asarray(p.pop("positions"), dtype=np.float64).reshape(len(times), p["count"], 3)
        positions[(p["node"], p["mesh"], p["primitive"])] = a
    doc["positions"] = positions
    return doc
