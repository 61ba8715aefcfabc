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
3. The same asset standing on a static set (a bumpy ground of SET triangles, default 1 M, one
   mesh made once): the per-frame acceleration-structure work when only the moving meshes are
   rebuilt and the set keeps its structure (`ACCELS.get(parts=)`, what `render` does) against
   rebuilding the whole scene (`ACCELS.split = False`), both timed on the same posed frames, and
   the rendered sequence both ways.
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


def ground(lo, hi, triangles: int, material) -> jp.Mesh:
    """A bumpy square ground of about `triangles` triangles under the box (lo, hi), 4 times its size."""
    n = max(2, int(round((triangles / 2) ** 0.5)))
    c, size = (lo + hi) / 2, 2.0 * float(np.max(hi - lo))
    u = np.linspace(-size, size, n + 1)
    x, z = np.meshgrid(u + c[0], u + c[2], indexing="ij")
    y = lo[1] - 0.01 * size + 0.02 * size * np.sin(7 * x / size) * np.cos(5 * z / size)
    pos = np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
    k = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, c2, d = k, k + 1, k + n + 1, k + n + 2
    tri = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c2], -1).reshape(-1, 3)]).astype(np.int32)
    return jp.Mesh(positions=pos, triangles=tri, material=material)


def on_a_set(path: Path, frames: int, width: int, height: int, environment, set_triangles: int) -> dict:
    from jaxpbr.rendering.mesh import ACCELS, mesh_parts
    from jaxpbr.rendering.stages import scene_host_arrays

    rest = read_gltf(path, ray_engine=mesh_engine())
    times = np.linspace(0.0, rest.animations[0].duration, frames)
    env = environment_from(environment)
    cache: dict = {}
    gs = scene_from_asset(rest, width=width, height=height, environment=env, material_cache=cache)
    lo, hi = rest.bounds
    floor = ground(np.asarray(lo), np.asarray(hi), set_triangles, jp.Material(base_color=(0.5, 0.5, 0.5), roughness=0.7))
    camera = gs.scene.camera

    def scene_at(t):
        sc = scene_from_asset(posed_asset(rest, float(t), 0), camera=camera, environment=env, material_cache=cache).scene
        return sc.replace(objects=tuple(sc.objects) + (floor,))

    scenes = [scene_at(t) for t in times]  # posed and made beforehand: the timings below are the render's
    jp.render(scenes[0]).block_until_ready()  # (compiles; the IBL maps)
    engine = mesh_engine()
    still = []  # the rest pose on the set, FRAMES times: its structures kept
    for _ in range(frames):
        t0 = time.perf_counter()
        np.asarray(jp.render(scenes[0]))
        still.append(time.perf_counter() - t0)
    rows = {}
    for split in (True, False):
        ACCELS.split = split
        ACCELS.entries.clear()
        ACCELS.seen = set()
        ts, built = [], ACCELS.built_triangles
        for sc in scenes:
            t0 = time.perf_counter()
            np.asarray(jp.render(sc))
            ts.append(time.perf_counter() - t0)
        rows[split] = (statistics.median(ts[2:]), (ACCELS.built_triangles - built) / frames)
    ACCELS.split = True
    # the structure alone, per posed frame: split and whole, alternately on the same arrays
    acc = {True: [], False: []}
    for sc in scenes[1:]:
        host = scene_host_arrays(sc, "float32")
        for split in (True, False):
            ACCELS.split = split
            t0 = time.perf_counter()
            ACCELS.get(host["positions"], host["triangles"], engine, parts=mesh_parts(
                [ob for ob in sc.objects if isinstance(ob, jp.Mesh)]))
            acc[split].append(time.perf_counter() - t0)
    ACCELS.split = True
    n_set, n_all = floor.num_triangles, floor.num_triangles + rest.summary()["triangles"]
    a_split, a_whole = statistics.median(acc[True][1:]), statistics.median(acc[False])
    print(f"{path.name} on a set of {n_set} triangles ({n_all} in all), {frames} frames at {width}x{height}:")
    print(f"  structure per frame: moved meshes only {a_split * 1e3:.1f} ms, whole scene {a_whole * 1e3:.1f} ms "
          f"({a_whole / a_split:.1f}x)")
    st = statistics.median(still)
    print(f"  render per frame (median of frames 3..): moved meshes only {rows[True][0] * 1e3:.1f} ms "
          f"({rows[True][1]:.0f} triangles built per frame, {rows[True][0] / st:.2f}x the static asset on the set, "
          f"{st * 1e3:.1f} ms), whole scene {rows[False][0] * 1e3:.1f} ms ({rows[False][1]:.0f}): "
          f"{rows[False][0] / rows[True][0]:.2f}x")
    return {"set_triangles": n_set, "accel_split_ms": a_split * 1e3, "accel_whole_ms": a_whole * 1e3, "static_ms": st * 1e3,
            "render_split_ms": rows[True][0] * 1e3, "render_whole_ms": rows[False][0] * 1e3}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("asset", nargs="?", type=Path, default=None)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--vertices", type=int, default=1_000_000)
    ap.add_argument("--environment", default="procedural:sky")
    ap.add_argument("--set", type=int, default=1_000_000, dest="set_triangles", help="triangles of the static set (0: none)")
    args = ap.parse_args(argv)
    skinning(args.vertices)
    path = args.asset
    if path is None:
        sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
        import tempfile

        from gltf_animated import skinned

        path = skinned(Path(tempfile.mkdtemp()))[0]
    sequence(path, args.frames, args.width, args.height, args.environment)
    if args.set_triangles:
        on_a_set(path, args.frames, args.width, args.height, args.environment, args.set_triangles)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
