"""Meshes that change shape under jit / grad (`jaxpbr.deformable`): the BVH refitted in the program
(`bvh.refit_bvh`) answers as a tree built at the new positions, and a step of a shape fit runs
without a host callback where rays are traced in the program (the topology carried, the tree
refitted), with the image and gradient of the plain scene's callbacks."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.errors import InputError
from jaxpbr.rendering import edges, execute
from jaxpbr.rendering.bvh import build_bvh, intersect_bvh, refit_bvh
from jaxpbr.rendering.demo import uv_sphere


def _bumpy(P, amount=0.35, shift=(0.1, -0.2, 0.05)):
    d = P / np.linalg.norm(P, axis=1, keepdims=True)
    return (P * (1 + amount * np.sin(3 * d[:, :1]) * np.cos(2 * d[:, 1:2])) + np.asarray(shift)).astype(np.float32)


def _rays(n, seed=0):
    rng = np.random.default_rng(seed)
    o = (rng.normal(size=(n, 3)) * 3).astype(np.float32)
    return o, (rng.normal(size=(n, 3)) * 0.8 - o).astype(np.float32)


def test_refit_at_the_build_positions_gives_the_built_tree():
    P, _, T = uv_sphere(24, n_lon=48)
    P, T = np.asarray(P, np.float32), np.asarray(T, np.int32)
    b = build_bvh(P, T, keep_degenerate=True)
    r = jax.jit(refit_bvh)(b, P, T)
    used = ~np.all(b.links == np.array([-1, -1, 0, 0]), axis=1)  # (the padding nodes are never visited)
    assert np.array_equal(np.asarray(r.nodes)[used], b.nodes[used])
    assert np.array_equal(np.asarray(r.tri), b.tri)


def test_a_refitted_tree_answers_as_a_tree_built_at_the_new_positions():
    """Closest hits (triangle ids and distances, bit for bit) of 20,000 random rays on a sphere
    deformed by a third of its radius and moved; the stale tree (not refitted) misses many of them:
    the comparison can fail."""
    P, _, T = uv_sphere(40, n_lon=80)
    P, T = np.asarray(P, np.float32), np.asarray(T, np.int32)
    P1 = _bumpy(P)
    stale = build_bvh(P, T, keep_degenerate=True)
    fresh = build_bvh(P1, T, keep_degenerate=True)
    o, d = _rays(20000)
    want = intersect_bvh(fresh, o, d)
    got = intersect_bvh(jax.jit(refit_bvh)(stale, P1, T), o, d)
    assert int(np.sum(np.asarray(want.prim) >= 0)) > 5000
    np.testing.assert_array_equal(np.asarray(got.prim), np.asarray(want.prim))
    np.testing.assert_array_equal(np.asarray(got.t), np.asarray(want.t))
    assert np.sum(np.asarray(intersect_bvh(stale, o, d).prim) != np.asarray(want.prim)) > 1000


def test_keep_degenerate_keeps_the_zero_area_triangles_a_refit_may_open():
    """A UV sphere's pole triangles have two corners at one position: left out of a plain tree,
    kept with keep_degenerate, and hit once the refit pulls the corners apart."""
    P = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0]], np.float32)
    T = np.array([[0, 1, 2]], np.int32)
    assert (np.asarray(build_bvh(P, T).prim) >= 0).sum() == 0
    b = build_bvh(P, T, keep_degenerate=True)
    assert (np.asarray(b.prim) >= 0).sum() == 1
    P1 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    h = intersect_bvh(refit_bvh(b, P1, T), np.array([[0.2, 0.2, 1.0]], np.float32), np.array([[0, 0, -1.0]], np.float32))
    assert int(h.prim[0]) == 0 and float(h.t[0]) == pytest.approx(1.0)


def _scene():
    P, _, T = uv_sphere(16, n_lon=32)
    mesh = jp.Mesh(positions=P, triangles=T, material=jp.Material(base_color=(0.8, 0.4, 0.2), roughness=0.5))
    return jp.Scene(camera=jp.Camera(position=(0, 0.3, 3.0), target=(0, 0, 0), width=40, height=30, fov_y_deg=40.0),
                    objects=[mesh], lights=[jp.DirectionalLight(direction=(-0.3, -0.5, -1.0), intensity=2.0)],
                    background=(0.1, 0.2, 0.3))


def _callbacks(fn, *args) -> int:
    return str(jax.make_jaxpr(fn)(*args)).count("pure_callback")


@pytest.fixture
def execution():
    saved = (execute.EXECUTION.staged, execute.EXECUTION.device_visibility)
    yield execute.EXECUTION
    execute.EXECUTION.staged, execute.EXECUTION.device_visibility = saved


@pytest.mark.parametrize("batch", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["render", "render_batch"])
def test_a_fit_step_on_the_device_path_has_no_host_callback(execution, batch):
    """One program with rays traced in it (what a GPU runs; forced here): the gradient step of a
    deformed mesh holds no callback with `deformable` (the plain scene's holds the ray cast's, the
    shadows' and the topology's), and gives the plain scene's loss (the mean squared image) and
    gradient."""
    execution.staged, execution.device_visibility = False, True
    sc = _scene()
    P1 = _bumpy(np.asarray(sc.objects[0].positions, np.float32), amount=0.2, shift=(0, 0, 0))
    cams = jp.Camera(position=np.array([[0, 0.3, 3.0], [2.0, 0.5, 2.0]], np.float32), target=(0, 0, 0), width=40, height=30, fov_y_deg=40.0)

    def image(p, s):
        s = s.replace(objects=[s.objects[0].replace(positions=p)])
        return jp.render_batch(s, cameras=cams) if batch else jp.render(s)

    def loss(p, s):
        return jnp.mean(image(p, s) ** 2)

    d = jp.deformable(sc)
    assert d.accel is not None
    assert _callbacks(jax.grad(loss), P1, d) == 0
    assert _callbacks(jax.grad(loss), P1, sc) >= 2
    (l1, g1), (l0, g0) = jax.jit(jax.value_and_grad(loss))(P1, d), jax.jit(jax.value_and_grad(loss))(P1, sc)
    assert float(l1) == pytest.approx(float(l0), rel=1e-6)
    assert float(jnp.linalg.norm(g0)) > 0
    np.testing.assert_allclose(np.asarray(g1), np.asarray(g0), rtol=1e-5, atol=1e-9 * float(jnp.abs(g0).max()))


@pytest.mark.slow
def test_on_the_cpu_the_topology_is_not_fetched_per_step(execution, monkeypatch):
    """Staged on the CPU (the host's ray engine answers the rays): no topology is computed or looked
    up during the steps with `deformable`; without it, each step fetches it."""
    execution.staged, execution.device_visibility = None, None
    sc = _scene()
    P1 = _bumpy(np.asarray(sc.objects[0].positions, np.float32), amount=0.2, shift=(0, 0, 0))
    d = jp.deformable(sc)
    assert d.accel is None  # (Embree answers on the CPU)
    calls = []
    real = edges.NEIGHBOURS.get
    monkeypatch.setattr(edges.NEIGHBOURS, "get", lambda *a, **k: calls.append(1) or real(*a, **k))

    @jax.jit
    def step(p, s):
        return jax.grad(lambda q: jnp.mean(jp.render(s.replace(objects=[s.objects[0].replace(positions=q)])) ** 2))(p)

    g1 = step(P1, d)
    g1 = step(P1 * 1.01, d)
    assert calls == []
    g0 = step(P1 * 1.01, sc)
    assert len(calls) >= 1
    np.testing.assert_allclose(np.asarray(g1), np.asarray(g0), rtol=1e-5, atol=1e-9 * float(jnp.abs(g0).max()))


def test_deformable_refuses_traced_meshes_and_other_triangle_counts(execution):
    execution.staged, execution.device_visibility = False, True
    sc = _scene()
    with pytest.raises(InputError, match="outside"):
        jax.jit(lambda p: jp.deformable(sc.replace(objects=[sc.objects[0].replace(positions=p)])).accel)(sc.objects[0].positions)
    d = jp.deformable(sc)
    P, _, T = uv_sphere(12, n_lon=24)
    other = sc.objects[0].replace(positions=P, triangles=T)
    with pytest.raises(InputError, match="jaxpbr.deformable"):
        jp.render(d.replace(objects=[other]))
    execution.staged, execution.device_visibility = None, None  # (staged on the CPU: the edge stage refuses it)
    d = jp.deformable(sc)
    with pytest.raises(InputError, match="jaxpbr.deformable"):
        jp.render(d.replace(objects=[other]))
