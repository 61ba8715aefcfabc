"""Opaque meshes traced in the program (`Execution.device_visibility`, the default off the CPU): the
same image as the host ray engine's callback, with no callback left in the program."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.rendering import execute, mesh, stages
from jaxpbr.rendering.assets import ibl_assets
from jaxpbr.rendering.demo import uv_sphere
from jaxpbr.rendering.options import RenderOptions
from jaxpbr.rendering.plan import plan, split_environment
from jaxpbr.rendering.scene import primary_rays


def _quad(z, half, normal_z):
    """Two triangles at depth z, facing +z (normal_z > 0) or -z."""
    p = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], np.float32)
    t = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    return p, (t if normal_z > 0 else t[:, ::-1].copy())


def _scene(width=40, height=30):
    """Seen from z = -6 looking along +z: a single-sided quad facing away (its back is culled and
    the rays continue), a double-sided quad behind it on the left (its back is seen), a
    single-sided sphere behind both; a point light between the camera and the quads (the culled
    quad still casts a shadow: shadow rays meet either face)."""
    red = jp.Material(base_color=(0.8, 0.1, 0.1), metallic=0.0, roughness=0.5)
    green = jp.Material(base_color=(0.1, 0.8, 0.1), metallic=0.0, roughness=0.5)
    grey = jp.Material(base_color=(0.7, 0.7, 0.7), metallic=0.0, roughness=0.4)
    p0, t0 = _quad(0.0, 0.6, +1)  # faces +z: the camera at -z sees its back
    p1, t1 = _quad(1.0, 0.5, +1)
    p1 = p1 + np.float32([-0.7, 0.0, 0.0])
    P, N, T = uv_sphere(12)
    objects = (
        jp.Mesh(positions=p0, triangles=t0, material=red),
        jp.Mesh(positions=p1, triangles=t1, material=green, double_sided=True),
        jp.Mesh(positions=P * 1.2 + np.float32([0.3, 0.0, 3.0]), normals=N, triangles=T.astype(np.int32), material=grey),
    )
    cam = jp.Camera(position=(0.0, 0.0, -6.0), target=(0.0, 0.0, 0.0), fov_y_deg=40.0, width=width, height=height)
    light = jp.PointLight((0.2, 0.3, -2.0), intensity=40.0)
    return jp.Scene(objects=objects, lights=[light], camera=cam)


@pytest.fixture
def one_program():
    saved = (execute.EXECUTION.staged, execute.EXECUTION.device_visibility)
    execute.EXECUTION.staged = False
    yield execute.EXECUTION
    execute.EXECUTION.staged, execute.EXECUTION.device_visibility = saved


def test_device_traversal_renders_what_the_host_engine_renders(one_program, monkeypatch):
    scene = _scene()
    one_program.device_visibility = False
    host = np.asarray(jp.render(scene))
    one_program.device_visibility = True
    accels, embree_calls = mesh.ACCELS, []

    class Counted:  # the host engine's casts ask for Embree's structure (the device path, the JAX BVH)
        def get(self, *a, **k):
            embree_calls.append(a[2] == "embree")
            return accels.get(*a, **k)

    monkeypatch.setattr(mesh, "ACCELS", Counted())
    device = np.asarray(jp.render(scene))
    monkeypatch.setattr(mesh, "ACCELS", accels)
    assert embree_calls and not any(embree_calls)  # the JAX BVH was fetched, no host cast ran
    assert np.isfinite(device).all()
    np.testing.assert_array_equal(device, host)
    # Not a vacuous equality: the rays went through the culled quad to the sphere, the double-sided
    # quad shows its back, and the culled quad's shadow falls on the sphere.
    prim = np.asarray(mesh.cast(stages._mesh_arrays(scene, jnp.float32), *primary_rays(scene.camera, dtype=jnp.float32)))
    tri_object = np.asarray(mesh.concat_meshes(list(scene.objects), jnp.float32)["tri_object"])
    assert set(tri_object[prim[prim >= 0]].tolist()) == {1, 2}  # the quad facing away is never seen
    sphere = (prim >= 0) & (tri_object[np.maximum(prim, 0)] == 2)
    dark = sphere & (device.sum(-1) == 0.0)  # no environment: a sphere pixel is black only in shadow
    assert 0 < dark.sum() < sphere.sum()
    # ... and the dark part is the culled quad's shadow: without the quad, those pixels are lit
    no_quad = np.asarray(jp.render(scene.replace(objects=tuple(scene.objects[1:]))))
    assert (no_quad.sum(-1)[dark] > 0).mean() > 0.9


def test_the_device_program_holds_no_host_callback(one_program):
    one_program.device_visibility = True
    scene = _scene(8, 6)
    opts = RenderOptions()
    p = plan(scene, options=opts)
    accel_scene = execute._with_device_accel(scene, one_program)
    assert isinstance(accel_scene, stages.AccelScene)
    text = str(jax.make_jaxpr(stages._render_traced, static_argnums=(2, 3))(accel_scene, None, p, opts))
    assert "callback" not in text
    # the same scene without the BVH calls the host engine (the check above can fail)
    text = str(jax.make_jaxpr(stages._render_traced, static_argnums=(2, 3))(scene, None, p, opts))
    assert "callback" in text


def test_meshes_that_walk_their_hits_keep_the_host_engine(one_program):
    one_program.device_visibility = True
    scene = _scene(8, 6)
    masked = scene.objects[0].replace(alpha_mode="MASK")
    s2 = scene.replace(objects=(masked,) + tuple(scene.objects[1:]))
    assert execute._with_device_accel(s2, one_program) is s2
    one_program.device_visibility = False
    assert execute._with_device_accel(scene, one_program) is scene


def test_a_stored_bvh_is_loaded_by_a_later_process_instead_of_built(tmp_path, monkeypatch):
    """`ACCELS.use_directory`: the JAX backend's BVH goes to disk once; a fresh cache (as a new
    process has) loads it, traces the same hits, and does not call the builder."""
    from jaxpbr.rendering import bvh as bvh_mod
    from jaxpbr.rendering import visibility

    P, _, T = uv_sphere(8)
    verts, tris = np.ascontiguousarray(P, np.float32), np.ascontiguousarray(T, np.int32)
    first = mesh._Accels()
    first.use_directory(tmp_path)
    built = first.get(verts, tris, "jax")
    files = list(tmp_path.glob("bvh-*.npz"))
    assert len(files) == 1
    later = mesh._Accels()
    later.use_directory(tmp_path)
    monkeypatch.setattr(visibility, "build_bvh", lambda *a, **k: pytest.fail("built again"))
    os.utime(files[0], (1000, 1000))
    loaded = later.get(verts, tris, "jax")
    assert files[0].stat().st_mtime > 1000  # marked as used: pruning (oldest first) keeps it
    for a, b in zip(built.bvh, loaded.bvh, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    o = np.tile(np.float32([[0.1, 0.2, 5.0]]), (16, 1))
    d = np.random.default_rng(0).normal(size=(16, 3)).astype(np.float32) * 0.05 + np.float32([0, 0, -1])
    np.testing.assert_array_equal(np.asarray(built.intersect(o, d).prim), np.asarray(loaded.intersect(o, d).prim))
    # a damaged file (garbage, or a truncated zip) is built again, not trusted
    good = files[0].read_bytes()
    monkeypatch.setattr(visibility, "build_bvh", bvh_mod.build_bvh)
    for bad in (b"not an npz", good[: len(good) // 2]):
        files[0].write_bytes(bad)
        again = mesh._Accels()
        again.use_directory(tmp_path)
        assert again.get(verts, tris, "jax").num_triangles == len(tris)


def test_render_batch_over_cameras_traces_on_the_device_as_single_renders_do(one_program, monkeypatch):
    """render_batch (one program off the CPU) carries the BVH too: no host cast, and each image
    equals the host engine's single render of that camera."""
    pytest.importorskip("embreex")  # the host engine counted below
    one_program.device_visibility = True
    scene = _scene(16, 12)
    cams = [scene.camera, scene.camera.replace(position=(0.5, 0.3, -6.0))]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *cams)
    calls = []
    accels = mesh.ACCELS

    class Counted:  # the host cast asks the structure cache for Embree's once per call
        def get(self, *a, **k):
            if a[2] == "embree":  # (the device path asks for the JAX BVH: not a host cast)
                calls.append(1)
            return accels.get(*a, **k)

    monkeypatch.setattr(mesh, "ACCELS", Counted())
    out = np.asarray(jp.render_batch(scene, cameras=batch))
    assert not calls
    one_program.device_visibility = False
    jp.render(scene.replace(camera=cams[1], lights=[]))
    assert calls  # (the counter sees the host engine when it is used)
    for k, cam in enumerate(cams):
        np.testing.assert_allclose(out[k], np.asarray(jp.render(scene.replace(camera=cam))), rtol=2e-6, atol=1e-7)


def test_device_accel_is_remembered_for_the_same_arrays_and_rebuilt_for_new_ones(monkeypatch):
    """A render loop over the same position arrays (JAX, or the read-only NumPy copies a Mesh keeps)
    fetches the BVH once; new positions or triangles go through the content-keyed cache again, and
    the caller's NumPy array changed in place after the Mesh was made does not change the Mesh."""
    P, _, T = uv_sphere(6)
    grey = jp.Material(base_color=(0.5, 0.5, 0.5))
    m = jp.Mesh(positions=jnp.asarray(P), triangles=jnp.asarray(T.astype(np.int32)), material=grey)
    accels, asked = mesh.ACCELS, []

    class Counted:
        def get(self, *a, **k):
            asked.append(1)
            return accels.get(*a, **k)

    monkeypatch.setattr(mesh, "ACCELS", Counted())
    first = mesh.device_accel([m])
    assert mesh.device_accel([m]) is first and len(asked) == 1
    moved = m.replace(positions=jnp.asarray(P) + 1.0)
    assert mesh.device_accel([moved]) is not first and len(asked) == 2
    assert mesh.device_accel([moved]) is not None and len(asked) == 2
    tri = np.array(moved.triangles)
    tri[0] = tri[0][::-1]
    mesh.device_accel([moved.replace(triangles=tri)])  # other triangles, the same positions
    assert len(asked) == 3
    mine = np.array(P, np.float32)
    host = jp.Mesh(positions=mine, triangles=T.astype(np.int32), material=grey)
    assert host.positions is not mine and not host.positions.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        host.positions[0, 0] = 5.0
    n = len(asked)
    kept = mesh.device_accel([host])
    mine += 1.0  # the caller's array, not the Mesh's
    np.testing.assert_array_equal(host.positions, P.astype(np.float32))
    assert mesh.device_accel([host]) is kept and len(asked) == n + 1


@pytest.mark.parametrize("vis", ["ao", "ratio"])
def test_the_ibl_visibility_rungs_trace_on_the_device_as_on_the_host(one_program, vis):
    """The traced IBL rungs with the device BVH in the program (a GPU's path, run here on the CPU):
    the image of the host engine's staged render, in render and in render_batch, and no callback
    left in the program."""
    from jaxpbr.rendering.demo import concave_scene

    scene = concave_scene(width=24, height=18)
    opts = RenderOptions(ibl_visibility=vis, ibl_samples=4)
    one_program.staged = True
    host = np.asarray(jp.render(scene, options=opts))
    one_program.staged, one_program.device_visibility = False, True
    device = np.asarray(jp.render(scene, options=opts))
    np.testing.assert_allclose(device, host, rtol=1e-5, atol=1e-6)
    batch = np.asarray(jp.render_batch(scene, env_intensity=np.asarray([1.0, 0.5], np.float32), options=opts))
    np.testing.assert_allclose(batch[0], host, rtol=1e-5, atol=1e-6)
    # not vacuous: the rays do shadow the box's inside against the unshadowed split sum
    plain = np.asarray(jp.render(scene, options=RenderOptions(ibl_visibility="none")))
    assert (host.sum(-1) < plain.sum(-1) - 1e-3).mean() > 0.2
    p = plan(scene, options=opts)
    accel_scene = execute._with_device_accel(scene, one_program)
    assert isinstance(accel_scene, stages.AccelScene)
    text = str(jax.make_jaxpr(stages._render_traced, static_argnums=(2, 3))(accel_scene, ibl_assets(split_environment(scene.environment, opts), p, opts), p, opts))
    assert "callback" not in text
