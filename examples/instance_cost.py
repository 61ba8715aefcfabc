"""What an instance costs: N nodes instancing one small mesh, loaded, made a scene and rendered.

    python examples/instance_cost.py                 # N = 10^3, 10^4, 10^5
    python examples/instance_cost.py 1000 1000000    # any counts

For each N, one process times `read_gltf` (the JSON, the node walk, the batched transforms),
`scene_from_asset` (one Mesh per material: the instances concatenated) and a 64 x 64 `jp.render`
(the ray engine's build over N x 12 triangles: a first call, which compiles for the new size, and a
warm one), and prints load and warm render per instance and as a ratio to the smallest N: linear
cost reads as a ratio equal to N / N_min. Peak RSS is the process's (ru_maxrss), so it only grows down the table.
"""

from __future__ import annotations

import json
import resource
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def cube_asset(path: Path, n: int) -> Path:
    """A glTF of n nodes on a grid, each instancing the same 12-triangle cube (flat normals)."""
    import base64

    v = np.float32([[x, y, z] for x in (0, 0.4) for y in (0, 0.4) for z in (0, 0.4)])
    t = np.uint16([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                   [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    data = v.tobytes() + t.tobytes()
    side = int(np.ceil(np.sqrt(n)))
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(data), "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
        "bufferViews": [{"buffer": 0, "byteLength": 96}, {"buffer": 0, "byteOffset": 96, "byteLength": 72}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3", "min": [0, 0, 0], "max": [0.4, 0.4, 0.4]},
                      {"bufferView": 1, "componentType": 5123, "count": 36, "type": "SCALAR"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0, "translation": [float(k % side), 0.0, float(k // side)]} for k in range(n)],
        "scenes": [{"nodes": list(range(n))}],
        "scene": 0,
    }
    path.write_text(json.dumps(doc))
    return path


def main(counts) -> None:
    import jaxpbr as jp
    from jaxpbr.io.gltf import read_gltf
    from jaxpbr.rendering.gltf_scene import scene_from_asset

    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        rows = []
        for i, n in enumerate(counts):
            path = cube_asset(Path(tmp) / f"cubes{n}.gltf", n)
            if i == 0:  # compile the render's programs once, outside the timings
                jp.render(scene_from_asset(read_gltf(path), width=64, height=64).scene).block_until_ready()
            t0 = time.perf_counter()
            asset = read_gltf(path)
            t1 = time.perf_counter()
            scene = scene_from_asset(asset, width=64, height=64).scene
            t2 = time.perf_counter()
            jp.render(scene).block_until_ready()
            t3 = time.perf_counter()
            jp.render(scene).block_until_ready()
            t4 = time.perf_counter()
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
            rows.append((n, t1 - t0, t2 - t1, t3 - t2, t4 - t3, rss))
            del asset, scene
    n0, l0, _, _, w0, _ = rows[0]
    print(f"{'instances':>10} {'load s':>8} {'us/inst':>8} {'ratio':>7} {'scene s':>8} {'1st render s':>13} "
          f"{'warm render s':>14} {'us/inst':>8} {'ratio':>7} {'peak GB':>8}")
    for n, lo, sc, first, warm, rss in rows:
        print(f"{n:>10} {lo:>8.2f} {1e6 * lo / n:>8.1f} {lo / l0:>7.1f} {sc:>8.2f} {first:>13.2f} "
              f"{warm:>14.2f} {1e6 * warm / n:>8.2f} {warm / w0:>7.1f} {rss:>8.2f}")
    print(f"(linear cost: a ratio of N / {n0}; a first render of a new size compiles its programs)")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [1000, 10_000, 100_000])
