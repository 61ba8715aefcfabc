"""A glTF asset of about a million triangles rendered at 1080p with 4 point lights and split-sum IBL,
against the same scene with analytic spheres, side by side in one process: `jaxpbr bench render --gltf`.

The asset is the demo's 7x7 sphere grid written as UV-sphere meshes (`jaxpbr.rendering.demo.write_demo_glb`),
with the tessellation chosen for the requested triangle count. Reported: loading, the acceleration
structure's build, one visibility query of the primary rays, the first renders, the warm frame times of
the meshes and the analytic spheres with and without shadows and their ratios, the peak memory; then, as
whole processes, the cold and warm start of `jaxpbr render ASSET.glb --environment procedural:sky` against
the demo's `jaxpbr render` (skip with --cold-runs 0) and, with --memory-triangles, the peak memory of
larger assets. Every option of `jaxpbr bench render --gltf` is accepted.

    python examples/bench_gltf_render.py [--triangles 1000000] [--width 1920 --height 1080] [--repeats 3]
        [--cold-runs 3] [--memory-triangles 10000000]
"""

from __future__ import annotations

import sys

from jaxpbr.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "render", "--gltf", *sys.argv[1:]]))
