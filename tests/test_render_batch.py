"""render_batch: batch == loop of single renders, chunking, sharding over 4 CPU devices."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp

ENV = None


def env():
    global ENV
    if ENV is None:
        # No sun: next to its edge neighbouring texels differ 1000x, which turns a 1-ulp difference
        # of a lookup direction (rotation computed batched vs single) into a 3e-4 pixel difference.
        ENV = jp.envs.sky_with_sun_cubemap(16, sun_radiance=0.0)
    return ENV


def base_scene(with_env=True):
    return jp.Scene(
        camera=jp.Camera(position=(0.0, 0.5, 5.0), width=12, height=10),
        objects=[
            jp.Sphere(center=(-0.8, 0.0, 0.0), radius=0.7, material=jp.Material((0.9, 0.2, 0.2), 0.0, 0.5)),
            jp.Sphere(center=(0.8, 0.0, 0.0), radius=0.7, material=jp.Material((0.2, 0.9, 0.2), 1.0, 0.3)),
            jp.Plane(point=(0.0, -0.7, 0.0), normal=(0.0, 1.0, 0.0), material=jp.Material((0.5, 0.5, 0.5), 0.0, 0.9)),
        ],
        lights=[jp.PointLight(position=(2.0, 3.0, 4.0), intensity=40.0)],
        environment=jp.Environment(radiance=env()) if with_env else None,
    )


def batched_materials(B=5):
    rng = np.random.default_rng(0)
    return jp.Material(
        base_color=rng.uniform(size=(B, 3)).astype(np.float32),
        metallic=rng.uniform(size=B).astype(np.float32),
        roughness=rng.uniform(size=B).astype(np.float32),
        occlusion=np.ones(B, np.float32),
        emissive=np.zeros((B, 3), np.float32),
    )


def take(tree, i):
    from jaxpbr.rendering.batching import _batched

    return jax.tree_util.tree_map(lambda x: x[i], _batched("batch", tree)[1])


# Same program per image, vmapped or not: XLA may fuse/vectorise the batched and single programs
# differently (e.g. FMA contraction), so images agree to float32 rounding of the shading, not
# bitwise: rtol 1e-5 (~100 ulps) covers that and fails on any real difference.
RTOL, ATOL = 1e-5, 1e-6


def test_materials_batch_equals_loop_of_single_renders():
    scene = base_scene()
    mats = batched_materials()
    out = np.asarray(jp.render_batch(scene, materials=mats, objects=[0], chunk=2))
    assert out.shape == (5, 10, 12, 3)
    for i in range(5):
        objs = list(scene.objects)
        objs[0] = jp.Sphere(center=objs[0].center, radius=objs[0].radius, material=take(mats, i))
        single = np.asarray(jp.render(scene.replace(objects=objs)))
        np.testing.assert_allclose(out[i], single, rtol=RTOL, atol=ATOL)


def test_cameras_lights_and_env_rotations_batch_equals_loop():
    scene = base_scene()
    B = 3
    ang = np.array([0.0, 0.4, -1.1], np.float32)
    cams = jp.Camera(
        position=np.stack([5 * np.sin(ang), np.full(B, 0.5), 5 * np.cos(ang)], -1).astype(np.float32),
        target=np.zeros((B, 3), np.float32),
        up=np.tile(np.array([0.0, 1.0, 0.0], np.float32), (B, 1)),
        fov_y_deg=np.full(B, 45.0, np.float32),
        jitter=np.zeros((B, 2), np.float32),
        width=12,
        height=10,
    )
    lights = [jp.PointLight(position=np.array([[2.0, 3.0, 4.0], [-2.0, 3.0, 4.0], [0.0, 5.0, 1.0]], np.float32), intensity=np.array([40.0, 20.0, 60.0], np.float32))]
    rot = np.array([0.0, 1.0, 2.5], np.float32)
    # float64: these inputs move ray directions, so a 1-ulp difference between the batched and the
    # single program is amplified by sharp edges (sphere-plane contact, horizon step of the sky);
    # in float64 that stays far below the tolerance (float32 showed 1e-4 at one such pixel).
    out = np.asarray(jp.render_batch(scene, cameras=cams, lights=lights, env_rotation=rot, dtype="float64"))
    for i in range(B):
        s = scene.replace(
            camera=take(cams, i),
            lights=[take(lights[0], i)],
            environment=jp.Environment(radiance=env(), rotation=rot[i]),
        )
        np.testing.assert_allclose(out[i], np.asarray(jp.render(s, dtype="float64")), rtol=1e-9, atol=1e-12)


def test_chunk_size_does_not_change_the_result_and_bad_inputs_fail():
    scene = base_scene(with_env=False)
    mats = batched_materials(4)
    a = np.asarray(jp.render_batch(scene, materials=mats, chunk=1))
    b = np.asarray(jp.render_batch(scene, materials=mats, chunk=3))
    np.testing.assert_allclose(a, b, rtol=RTOL, atol=ATOL)
    with pytest.raises(ValueError, match="at least one batched input"):
        jp.render_batch(scene)
    # Unbatched fields broadcast over the batch (occlusion, emissive left scalar / (3,)):
    partial = jp.Material(base_color=np.asarray(mats.base_color), metallic=np.asarray(mats.metallic), roughness=np.asarray(mats.roughness))
    np.testing.assert_allclose(np.asarray(jp.render_batch(scene, materials=partial, chunk=3)), b, rtol=0, atol=0)
    with pytest.raises(ValueError, match="same leading batch axis"):
        jp.render_batch(scene, materials=jp.Material(base_color=np.ones((3, 3)), metallic=np.ones(2), roughness=np.ones(3)))
    with pytest.raises(ValueError, match="need a scene with an environment"):
        jp.render_batch(scene, env_rotation=np.zeros(2))
    with pytest.raises(ValueError, match="chunk"):
        jp.render_batch(scene, materials=mats, chunk=0)


SHARD_SCRIPT = textwrap.dedent(
    """
    import numpy as np, jax, json, sys
    sys.path.insert(0, {tests!r})
    import jaxpbr as jp
    from test_render_batch import base_scene, batched_materials
    assert len(jax.devices()) == 4, jax.devices()
    scene = base_scene()
    mats = batched_materials(7)  # not a multiple of 4: padding path
    sharded = jp.render_batch(scene, materials=mats, chunk=2)
    # The sharded path runs each device's share as one program per chunk; on one device XLA:CPU
    # runs the stages as separate programs (renderer.EXECUTION.staged = None). Compare like with like:
    jp.rendering.renderer.EXECUTION.staged = False
    single = jp.render_batch(scene, materials=mats, chunk=2, devices=1)
    jp.rendering.renderer.EXECUTION.staged = None
    staged = jp.render_batch(scene, materials=mats, chunk=2, devices=1)
    a, b, c = np.asarray(sharded), np.asarray(single), np.asarray(staged)
    rel = float((np.abs(a - b) / np.maximum(np.abs(b), 1e-6)).max())
    rel_staged = float((np.abs(c - b) / np.maximum(np.abs(b), 1e-6)).max())
    print(json.dumps(dict(shape=a.shape, max_abs=float(np.abs(a - b).max()), max_rel=rel, equal=bool((a == b).all()),
                          max_rel_staged=rel_staged)))
    """
)


def test_sharded_over_four_cpu_devices_equals_single_device():
    env_vars = dict(os.environ)
    env_vars["XLA_FLAGS"] = env_vars.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
    env_vars["JAX_PLATFORMS"] = "cpu"
    tests = str(Path(__file__).parent)
    root = str(Path(__file__).parent.parent)
    env_vars["PYTHONPATH"] = root + os.pathsep + env_vars.get("PYTHONPATH", "")
    r = subprocess.run(
        [sys.executable, "-c", SHARD_SCRIPT.format(tests=tests)], capture_output=True, text=True, timeout=300, env=env_vars
    )
    assert r.returncode == 0, r.stderr[-3000:]
    import json

    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["shape"] == [7, 10, 12, 3]
    # Each device runs the same per-image math on its share, compiled as a separate program: XLA
    # may fuse it differently (measured: 1 ulp at a few pixels, not bitwise). Bound: 4 float32 ulps.
    assert res["max_rel"] <= 4 * 2.0**-23, res
    # The staged single-device batch (XLA:CPU's default) against the one-program batch: float32
    # rounding of differently fused programs (as tests/test_bake.py bounds for render).
    assert res["max_rel_staged"] <= 2e-5, res


def test_staged_batch_equals_a_loop_of_renders(monkeypatch):
    """Staged (the XLA:CPU default) render_batch runs the stages as separate programs vmapped over
    each chunk: the same programs' math as `render` per image (bitwise here; bounded by float32
    rounding)."""
    from jaxpbr.rendering import renderer

    monkeypatch.setattr(renderer.EXECUTION, "staged", True)
    scene = base_scene()
    mats = batched_materials(5)
    imgs = np.asarray(jp.render_batch(scene, materials=mats, chunk=2))
    for i in range(5):
        m = jax.tree_util.tree_map(lambda x: x[i], mats)
        objs = [o.replace(material=m) for o in scene.objects]
        one = np.asarray(jp.render(scene.replace(objects=objs)))
        np.testing.assert_allclose(imgs[i], one, rtol=2e-6, atol=1e-7)


def test_staged_batch_shadows_the_suns_split_out_of_the_environment(monkeypatch):
    """A sun split out of the environment casts shadows in render_batch as in render (staged: the
    suns' shadow stage runs per chunk, as `render`'s does)."""
    from jaxpbr.rendering import renderer

    monkeypatch.setattr(renderer.EXECUTION, "staged", True)
    sky = jp.envs.sky_with_sun_cubemap(16)
    scene = base_scene().replace(environment=jp.Environment(radiance=sky), lights=[])
    from jaxpbr.rendering.options import RenderOptions
    from jaxpbr.rendering.plan import plan

    opts = RenderOptions(shadows=True)
    p = plan(scene, options=opts)
    assert p.shadows and p.env_lights
    imgs = np.asarray(jp.render_batch(scene, env_intensity=np.asarray([1.0, 0.5], np.float32), options=opts))
    one = np.asarray(jp.render(scene, options=opts))
    np.testing.assert_allclose(imgs[0], one, rtol=2e-6, atol=1e-6)
    unshadowed = np.asarray(jp.render(scene))
    assert np.abs(one - unshadowed).max() > 0.05 * np.abs(unshadowed).max()  # the shadows are visible


def test_staged_batch_of_meshes_casts_every_ray_on_the_host_as_render_does(monkeypatch):
    """With meshes, the staged batch casts each chunk's primary rays, the lights' and the suns'
    shadow rays and the IBL visibility rays on the host ray engine, all images in one call each,
    and gives each image what `render` gives it (cameras batched: every image its own rays)."""
    from jaxpbr.rendering import batching, renderer
    from jaxpbr.rendering.demo import concave_scene

    monkeypatch.setattr(renderer.EXECUTION, "staged", True)
    scene = concave_scene(24, 18).replace(lights=[jp.PointLight((0.5, 1.5, 1.0), intensity=20.0)])
    cam = scene.camera
    pos = np.asarray(cam.position, np.float32)
    P = np.stack([pos, pos + np.float32([0.8, 0.2, 0.0]), pos + np.float32([-0.6, -0.3, 0.4])])
    opts = jp.RenderOptions(shadows=True, ibl_visibility="ratio", ibl_samples=2)
    calls = []
    real = batching.host_mesh_hits
    monkeypatch.setattr(batching, "host_mesh_hits", lambda *a, **k: calls.append(1) or real(*a, **k))
    imgs = np.asarray(jp.render_batch(scene, cameras=cam.replace(position=jnp.asarray(P)), options=opts))
    assert len(calls) == 3  # lights, suns, IBL rays: one engine call each for the whole chunk
    for i in range(3):
        one = np.asarray(jp.render(scene.replace(camera=cam.replace(position=tuple(P[i]))), options=opts))
        np.testing.assert_allclose(imgs[i], one, rtol=2e-5, atol=1e-6)
    # not vacuous: the point light's and the sun's shadows are in the image
    plain = np.asarray(jp.render(scene.replace(camera=cam.replace(position=tuple(P[0]))), options=dataclasses.replace(opts, shadows=False)))
    assert (np.abs(plain - imgs[0]).max(-1) > 1e-3).mean() > 0.05


def _floor_and_occluder(occluder_material, sphere=False):
    grey = jp.Material(base_color=(0.7, 0.7, 0.7), metallic=0.0, roughness=0.8)
    floor = jp.Mesh(positions=np.float32([[-3, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3]]),
                    triangles=np.int32([[0, 2, 1], [0, 3, 2]]), material=grey)
    if sphere:
        occ = jp.Sphere(center=(0.0, 0.8, 0.0), radius=0.4, material=occluder_material)
    else:
        occ = jp.Mesh(positions=np.float32([[-0.6, 0.8, -0.6], [0.6, 0.8, -0.6], [0.6, 0.8, 0.6], [-0.6, 0.8, 0.6]]),
                      triangles=np.int32([[0, 2, 1], [0, 3, 2]]), material=occluder_material, double_sided=True)
    cam = jp.Camera(position=(0.0, 4.0, 4.0), target=(0.0, 0.0, 0.0), width=16, height=12)
    return jp.Scene(camera=cam, objects=(floor, occ), lights=[jp.PointLight((0.1, 3.0, 0.1), intensity=30.0)])


@pytest.mark.parametrize("case", ["adds", "removes"])
def test_batched_materials_that_change_transmission_shadow_as_render_does(monkeypatch, case):
    """Transmission is a static part of a material: batched materials can add it to an occluder or
    take it away, which changes what its shadow lets through; each image equals `render`'s."""
    from jaxpbr.rendering import renderer

    monkeypatch.setattr(renderer.EXECUTION, "staged", True)
    if case == "adds":
        scene = _floor_and_occluder(jp.Material(base_color=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.5))
        mats = jp.Material(base_color=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.5, transmission=np.float32([1.0, 0.6]))
    else:
        scene = _floor_and_occluder(jp.Material(base_color=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.5, transmission=1.0), sphere=True)
        mats = jp.Material(base_color=np.float32([[0.8, 0.8, 0.8], [0.3, 0.6, 0.9]]), metallic=0.0, roughness=0.5)
    opts = jp.RenderOptions(shadows=True)
    imgs = np.asarray(jp.render_batch(scene, materials=mats, objects=[1], options=opts))
    for i in range(2):
        m = jax.tree_util.tree_map(lambda x: x[i] if np.ndim(x) and np.shape(x)[0] == 2 else x, mats)
        objs = list(scene.objects)
        objs[1] = objs[1].replace(material=m)
        one = np.asarray(jp.render(scene.replace(objects=objs), options=opts))
        np.testing.assert_allclose(imgs[i], one, rtol=2e-5, atol=1e-6)
