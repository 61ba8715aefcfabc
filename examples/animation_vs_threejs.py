"""jaxpbr's glTF animation, skinning and morph targets against three.js (an independent reader).

For every .gltf/.glb under a folder (e.g. the Khronos sample models with animations: BoxAnimated,
AnimatedCube, InterpolationTest, AnimatedMorphCube, RiggedSimple, RiggedFigure, CesiumMan, Fox,
BrainStem) and each of its animations, the world-space position of every vertex at several times
(before the first key, inside, at the end, past the end) and in the rest pose, from
`jaxpbr.io.gltf.read_gltf(path, time=t, animation=k)` and from three.js r170
(tests/three_pose.mjs: GLTFLoader + AnimationMixer in Node). Reports the largest distance over all
vertices and times, relative to the diagonal of the asset's rest bounds.

three.js reads JOINTS_0/WEIGHTS_0 only (jaxpbr every set) and slerps non-unit keyed quaternions
without normalising them (jaxpbr normalises): assets that use either differ by that.

    python examples/animation_vs_threejs.py FOLDER [--times 0,0.25,0.5,1,1.5] [--json out.json]

(times are fractions of each animation's duration; needs Node.js and `npm install three@0.170.0`)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from three_oracle import three_missing, three_pose  # noqa: E402

from jaxpbr.io.gltf import read_gltf  # noqa: E402


def _positions(asset) -> dict:
    """{(node, mesh, primitive): (V, 3)} in the file's vertex order (jaxpbr unwelds the vertices of
    primitives without normals into triangle corners: those are mapped back by the triangles)."""
    return {(p.node, p.mesh, p.primitive): p for p in asset.primitives if p.instance is None}


def _compare(prim, ref: np.ndarray) -> float:
    """Largest distance between jaxpbr's vertices and three's (V_file, 3), matched by position of
    the same vertex: an unwelded jaxpbr vertex is compared with the nearest of three's."""
    got = np.asarray(prim.positions, np.float64)
    if got.shape == ref.shape:
        return float(np.linalg.norm(got - ref, axis=1).max())
    # unwelded corners: each jaxpbr vertex is some file vertex; the nearest one is the match
    best = np.full(got.shape[0], np.inf)
    for s in range(0, ref.shape[0], 4096):
        d = np.linalg.norm(got[:, None] - ref[None, s:s + 4096], axis=-1)
        best = np.minimum(best, d.min(axis=1))
    return float(best.max())


def check(path: Path, fractions) -> list[dict]:
    rest = read_gltf(path, lazy_images=True)
    diag = float(np.linalg.norm(rest.bounds[1] - rest.bounds[0])) if rest.bounds is not None else 1.0
    rows = []
    runs = [(None, [0.0])] + [(a.index, [f * a.duration for f in fractions]) for a in rest.animations]
    for anim, times in runs:
        t0 = time.perf_counter()
        ref = three_pose(path, anim, times)
        t_three = time.perf_counter() - t0
        worst = 0.0
        t_jax = 0.0
        for i, t in enumerate(times):
            t0 = time.perf_counter()
            asset = rest if anim is None else read_gltf(path, time=t, animation=anim, lazy_images=True)
            t_jax += time.perf_counter() - t0
            got = _positions(asset)
            for key, pos in ref["positions"].items():
                if key not in got:
                    raise AssertionError(f"{path.name}: three has primitive {key}, jaxpbr has not")
                worst = max(worst, _compare(got[key], pos[i]))
        name = "rest pose" if anim is None else f"{anim} {rest.animations[anim].name!r}"
        rows.append({"asset": path.name, "animation": name, "times": [round(t, 4) for t in times],
                     "vertices": int(sum(p.num_vertices for p in rest.primitives)),
                     "max_distance": worst, "relative": worst / diag, "jaxpbr_s": t_jax, "three_s": t_three})
        print(f"{path.name:28s} {name:34s} max |jaxpbr - three| {worst:.3g} ({worst / diag:.2e} of the diagonal)")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--times", default="0,0.25,0.5,1,1.5", help="fractions of each animation's duration")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    why = three_missing()
    if why:
        print(f"three.js is not available: {why}", file=sys.stderr)
        return 2
    fractions = [float(x) for x in args.times.split(",")]
    rows = []
    for path in sorted(p for p in args.folder.rglob("*") if p.suffix.lower() in (".gltf", ".glb")
                       and not any(part.startswith("_") for part in p.relative_to(args.folder).parts)):
        rows += check(path, fractions)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
