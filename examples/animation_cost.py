"""What animation costs: skinning a million vertices, the per-frame acceleration-structure build,
and a rendered sequence of a rigged asset against rendering the same asset static.

    python examples/animation_cost.py [ASSET.glb] [--frames 60] [--width 640 --height 360]
           [--vertices 1000000] [--environment procedural:sky]

1. Skinning: `jaxpbr.geometry.pose.deform` of V vertices with 4 influences each (positions,
   normals, tangents) from 64 joint matrices, jit-compiled JAX (float32) against the same code in
   NumPy (float64, the loader's), medians of 5 runs after a warm-up.
2. A sequence: FRAMES frames evenly over the asset's first animation, each posed on the host
   (`posed_asset`), made a scene (materials and textures made once) and rendered, against the rest
   pose rendered FRAMES times (its acceleration structure built once and kept): the per-frame
   time of each, their ratio, and the part of an animated frame spent posing, building the scene
   and building the acceleration structure (the Embree build of the posed triangles, timed apart).
Without ASSET, the sequence uses a rigged strip written in code (tests/gltf_animated.py's
`skinned`: the fixed costs of a frame).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxpbr as jp
from jaxpbr.geometry.pose import deform
from jaxpbr.io.gltf import posed_asset, read_gltf
from jaxpbr.rendering.gltf_scene import environment_from, scene_from_asset
from jaxpbr.rendering.plan import mesh_engine


def _median(fn, runs=5):
    fn()
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def skinning(V: int) -> dict:
    rng = np.random.default_rng(0)
    J = 64
    pos = rng.normal(size=(V, 3))
    nrm = rng.normal(size=(V, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    tan = np.concatenate([nrm[:, [1, 2, 0]], np.ones((V, 1))], 1)
    joints = rng.integers(0, J, size=(V, 4))
    w = rng.random((V, 4))
    w /= w.sum(1, keepdims=True)
    mats = np.tile(np.eye(4), (J, 1, 1))
    mats[:, :3, :3] += 0.1 * rng.normal(size=(J, 3, 3))
    mats[:, :3, 3] = rng.normal(size=(J, 3))
    args32 = [jnp.asarray(a, jnp.float32) for a in (pos, nrm, tan, mats, w)] + [jnp.asarray(joints)]

    @jax.jit
    def f(p, n, t, m, ww, jj):
        return deform(p, n, t, joint_mats=m, joints=jj, joint_weights=ww, xp=jnp)

    t_jax = _median(lambda: jax.block_until_ready(f(*args32)))
    t_np = _median(lambda: deform(pos, nrm, tan, joint_mats=mats, joints=joints, joint_weights=w, xp=np), runs=3)
    print(f"skinning {V} vertices x 4 influences (positions, normals, tangents): JAX float32 {t_jax * 1e3:.1f} ms, "
          f"NumPy float64 {t_np * 1e3:.1f} ms ({t_np / t_jax:.1f}x)")
    return {"vertices": V, "jax_ms": t_jax * 1e3, "numpy_ms": t_np * 1e3}


def sequence(path: Path, frames: int, width: int, height: int, environment) -> dict:
    rest = read_gltf(path, ray_engine=mesh_engine())
    if not rest.animations:
        raise SystemExit(f"{path} has no animations")
    anim = rest.animations[0]
    times = np.linspace(0.0, anim.duration, frames)
    env = environment_from(environment)
    cache: dict = {}
    gs = scene_from_asset(rest, width=width, height=height, environment=env, material_cache=cache)
    camera = gs.scene.camera
    jp.render(gs.scene).block_until_ready()  # (compiles; the IBL maps)
    # static: the rest pose, FRAMES times
    static = []
    for _ in range(frames):
        t0 = time.perf_counter()
        np.asarray(jp.render(gs.scene))
        static.append(time.perf_counter() - t0)
    # animated: posed, a scene, rendered
    animated, posing, building, accel = [], [], [], []

    for t in times:
        t0 = time.perf_counter()
        asset = posed_asset(rest, float(t), 0)
        t1 = time.perf_counter()
        scene = scene_from_asset(asset, camera=camera, environment=env, material_cache=cache).scene
        t2 = time.perf_counter()
        np.asarray(jp.render(scene))
        t3 = time.perf_counter()
        animated.append(t3 - t0)
        posing.append(t1 - t0)
        building.append(t2 - t1)
    # the acceleration-structure build of a posed frame, apart (fresh content: not in the cache)
    from jaxpbr.rendering.mesh import ACCELS
    from jaxpbr.rendering.stages import scene_host_arrays

    for t in times[1::max(1, frames // 5)]:
        scene = scene_from_asset(posed_asset(rest, float(t) * 0.999, 0), camera=camera, environment=env,
                                 material_cache=cache).scene
        host = scene_host_arrays(scene, "float32")
        t0 = time.perf_counter()
        ACCELS.get(host["positions"], host["triangles"], mesh_engine())
        accel.append(time.perf_counter() - t0)
    s = rest.summary()
    st, an = statistics.median(static), statistics.median(animated)
    print(f"{path.name}: {s['triangles']} triangles, {s['vertices']} vertices, {frames} frames at {width}x{height}")
    print(f"  static   {st * 1e3:.1f} ms/frame (median)")
    print(f"  animated {an * 1e3:.1f} ms/frame (median): {an / st:.2f}x static; posing {statistics.median(posing) * 1e3:.1f} ms, "
          f"scene {statistics.median(building) * 1e3:.1f} ms, render {(an - statistics.median(posing) - statistics.median(building)) * 1e3:.1f} ms "
          f"(of which the acceleration structure's build {statistics.median(accel) * 1e3:.1f} ms)")
    return {"asset": path.name, "frames": frames, "static_ms": st * 1e3, "animated_ms": an * 1e3, "ratio": an / st,
            "posing_ms": statistics.median(posing) * 1e3, "scene_ms": statistics.median(building) * 1e3,
            "accel_ms": statistics.median(accel) * 1e3}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("asset", nargs="?", type=Path, default=None)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--vertices", type=int, default=1_000_000)
    ap.add_argument("--environment", default="procedural:sky")
    args = ap.parse_args(argv)
    skinning(args.vertices)
    path = args.asset
    if path is None:
        sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
        import tempfile

        from gltf_animated import skinned

        path = skinned(Path(tempfile.mkdtemp()))[0]
    sequence(path, args.frames, args.width, args.height, args.environment)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
