"""Static meshes keep their acceleration structure while moved ones are rebuilt.

`visibility.GroupedAccel` (one `TriangleAccel` per group of triangles, the hits merged in the one
(t, id) order) must answer exactly as one structure over the whole mesh: the same triangle ids and
float32 t for closest hits, continuation through coplanar copies split across groups, and shadow
rays. `mesh.ACCELS.get(parts=...)` splits a scene into the meshes unchanged since the previous call
and those that moved; a sequence of frames then builds only the moving triangles."""

from __future__ import annotations

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.rendering import mesh as mesh_mod
from jaxpbr.rendering.mesh import Mesh, _Accels
from jaxpbr.rendering.visibility import GroupedAccel, TriangleAccel, embree_available

from gltf_writer import uv_sphere

BACKENDS = ["jax"] + (["embree"] if embree_available() else [])
backends = pytest.mark.parametrize("backend", BACKENDS)


def _soup(rng, parts):
    """Triangles in three meshes (rows `parts`), with one triangle copied exactly into all three
    (coplanar copies at equal t, in different groups) and two meshes interpenetrating."""
    vs = []
    for n, off in zip((200, 150, 100), (0.0, 0.2, -0.1), strict=True):
        c = rng.uniform(-1, 1, (n, 1, 3))
        vs.append((c + 0.3 * rng.normal(size=(n, 3, 3))).reshape(-1, 3) + off)
    vs[0][-3:] = vs[2][:3]
    vs[1][:3] = vs[2][:3]
    v = np.concatenate(vs).astype(np.float32)
    return v, np.arange(len(v), dtype=np.int32).reshape(-1, 3)


PARTS = [(0, 0), (600, 200), (1050, 350), (1350, 450)]


def _rays(rng, v, tri, n=3000):
    o = rng.uniform(-3, 3, (n, 3))
    d = -o + 0.5 * rng.normal(size=o.shape)
    centre = v[tri[350]].astype(np.float64).mean(0)  # the triangle copied into every mesh
    o[:300] = centre + np.array([0.3, 0.2, 2.0])
    d[:300] = centre + 0.01 * rng.normal(size=(300, 3)) - o[:300]
    return o, d


def _build(v, tri, backend):
    # (the jax backend's BVHs padded to one size: one compiled traversal per query kind)
    return TriangleAccel.build(v, tri, backend=backend, **({"min_triangles": 1024} if backend == "jax" else {}))


def _grouped(v, tri, groups, backend):
    out = []
    for which in groups:
        ids = np.concatenate([np.arange(PARTS[k][1], PARTS[k + 1][1]) for k in which])
        out.append((_build(v, tri[ids], backend), ids))
    return GroupedAccel(out, len(tri))


@pytest.mark.parametrize("backend,dtype", [("jax", np.float64)] + [("embree", dt) for dt in (np.float32, np.float64) if embree_available()])
def test_grouped_structure_answers_as_one_structure(backend, dtype):
    """Every hit along every ray (12 continuations), the closest hit and shadow rays: the same
    triangle ids and bit-identical t as one structure over the whole mesh."""
    rng = np.random.default_rng(1)
    v, tri = _soup(rng, PARTS)
    o, d = (x.astype(dtype) for x in _rays(rng, v, tri, n=1000))  # (one ray bucket of the jax traversal)
    whole = _build(v, tri, backend)
    grouped = _grouped(v, tri, [[0, 2], [1]], backend)
    a, b = whole.first_k_hits(o, d, 12), grouped.first_k_hits(o, d, 12)
    prim_a = np.asarray(a.prim)
    np.testing.assert_array_equal(prim_a, np.asarray(b.prim))
    np.testing.assert_array_equal(np.asarray(a.t), np.asarray(b.t))
    # The copies: three triangles at one t, reported once each, in id order, across the groups.
    copies = np.isin(prim_a[:300], [199, 200, 350])
    assert (copies.sum(1) == 3).mean() > 0.9
    ha, hb = whole.intersect(o, d), grouped.intersect(o, d)
    np.testing.assert_array_equal(np.asarray(ha.prim), np.asarray(hb.prim))
    np.testing.assert_array_equal(np.asarray(ha.t), np.asarray(hb.t))
    np.testing.assert_allclose(np.asarray(hb.b1), np.asarray(ha.b1), atol=1e-6)
    tfar = rng.uniform(0.0, 4.0, len(o))
    np.testing.assert_array_equal(np.asarray(whole.occluded(o, d, 0.0, tfar)), grouped.occluded(o, d, 0.0, tfar))


@backends
def test_a_hit_exactly_at_tnear_counts_without_a_previous_hit(backend):
    """(t, id) > (tnear, -1) holds at t = tnear: a ray from z = 1 down to a triangle in z = 0 hits
    it at t = 1 exactly, and a query from tnear = 1 (no previous hit) still reports it; from
    tnear = 1 after that triangle, the copy of it with the larger id."""
    v = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0]] * 2, np.float32)
    tri = np.arange(6, dtype=np.int32).reshape(2, 3)
    acc = TriangleAccel.build(v, tri, backend=backend)
    o, d = np.array([[0.1, -0.2, 1.0]]), np.array([[0.0, 0.0, -1.0]])
    h = acc.intersect(o, d)
    assert int(h.prim[0]) == 0 and float(h.t[0]) == 1.0
    h = acc.intersect(o, d, tnear=np.array([1.0]), after_prim=np.array([-1]))
    assert int(h.prim[0]) == 0 and float(h.t[0]) == 1.0
    h = acc.intersect(o, d, tnear=np.array([1.0]), after_prim=np.array([0]))
    assert int(h.prim[0]) == 1
    h = acc.intersect(o, d, tnear=np.array([1.0]), after_prim=np.array([1]))
    assert int(h.prim[0]) == -1


def test_frames_rebuild_only_the_meshes_that_moved():
    """A static set (2560 triangles) beside a small moving mesh: the first frame builds the whole,
    the second the static set once and the moving mesh, every later frame the moving mesh only;
    the primitives cast are those of one structure over the frame's whole mesh."""
    backend = "embree" if embree_available() else "jax"
    accels = _Accels()
    P, _, _, T = uv_sphere(32, 41)  # the static set
    p_small, _, _, t_small = uv_sphere(4, 6)
    static_v = np.ascontiguousarray(P * 2.0, np.float32)
    n_static, n_moving = len(T), len(t_small)
    rng = np.random.default_rng(2)
    o = rng.uniform(-4, 4, (2000, 3)).astype(np.float32)
    d = (rng.uniform(-1, 1, (2000, 3)) - o).astype(np.float32)
    built = []
    for frame in range(5):
        moving_v = (p_small * 0.5 + np.array([0.0, 2.2 + 0.1 * frame, 0.0])).astype(np.float32)
        v = np.concatenate([static_v, moving_v])
        tri = np.concatenate([T, t_small + len(P)]).astype(np.int32)
        parts = ((0, 0), (len(P), n_static), (len(v), len(tri)))
        before = accels.built_triangles
        acc = accels.get(v, tri, backend, parts=parts)
        built.append(accels.built_triangles - before)
        whole = TriangleAccel.build(v, tri, backend=backend)
        a, b = whole.first_k_hits(o, d, 4), acc.first_k_hits(o, d, 4)
        np.testing.assert_array_equal(np.asarray(a.prim), np.asarray(b.prim))
        np.testing.assert_array_equal(np.asarray(a.t), np.asarray(b.t))
        assert (np.asarray(a.prim) >= n_static).any()  # the moving mesh is seen
    assert built == [n_static + n_moving, n_static + n_moving] + [n_moving] * 3
    assert isinstance(acc, GroupedAccel)


def test_renders_of_a_moving_mesh_beside_a_static_one_rebuild_the_moving_mesh():
    """`jp.render` of frames where one mesh moves and one stays (the same arrays): after the first
    two frames only the moving mesh's triangles are built, and each image equals the one a fresh
    structure over the whole scene gives (rendered after clearing the kept structures)."""
    mat = jp.Material(base_color=(0.7, 0.6, 0.5), metallic=0.0, roughness=0.5)
    cam = jp.Camera(position=(0.3, 1.5, 5.0), target=(0.0, 0.5, 0.0), fov_y_deg=45.0, width=40, height=32)
    P, N, _, T = uv_sphere(24, 32)
    ground = Mesh(positions=P * np.float32([3.0, 0.2, 3.0]), triangles=T, normals=N, material=mat)
    small_p, small_n, _, small_t = uv_sphere(6, 8)
    sun = jp.DirectionalLight(direction=(-0.3, -0.8, -0.5), color=(1.0, 1.0, 1.0), intensity=3.0)

    def frame(k):
        ball = Mesh(positions=small_p * 0.4 + np.float32([0.2 * k, 0.9, 0.0]), triangles=small_t, normals=small_n, material=mat)
        return jp.Scene(camera=cam, objects=[ground, ball], lights=[sun])

    accels = mesh_mod.ACCELS
    built, img = [], None
    for k in range(4):
        before = accels.built_triangles
        img = np.asarray(jp.render(frame(k), shadows=True))
        built.append(accels.built_triangles - before)
    assert built[2] == built[3] == len(small_t)
    assert isinstance(next(reversed(accels.entries.values())), GroupedAccel)
    with accels.lock:  # forget the kept structures: the last frame again, as one structure
        accels.entries.clear()
        accels.seen = set()
    before = accels.built_triangles
    fresh = np.asarray(jp.render(frame(3), shadows=True))
    assert accels.built_triangles - before == len(T) + len(small_t)
    assert np.isfinite(img).all() and img.std() > 0
    np.testing.assert_array_equal(img, fresh)


def test_grouped_bvhs_traced_in_the_program_answer_as_one_bvh():
    """`intersect_groups` (the in-program traversal of the groups' BVHs): the first 12 hits along
    each ray, by continuation, equal one BVH's over the whole mesh (ids and t)."""
    import jax
    import jax.numpy as jnp

    from jaxpbr.rendering.visibility import intersect_bvh, intersect_groups

    rng = np.random.default_rng(3)
    v, tri = _soup(rng, PARTS)
    o, d = (jnp.asarray(x, jnp.float32) for x in _rays(rng, v, tri, n=1024))
    whole = _build(v, tri, "jax").bvh
    groups = _grouped(v, tri, [[0, 2], [1]], "jax").device_groups()

    @jax.jit
    def step(groups, whole, ta, pa, tb, pb):  # the next hit after (t, prim) of each ray
        ha = intersect_bvh(whole, o, d, ta, jnp.inf, pa, lanes=256)
        hb = intersect_groups(groups, o, d, tb, jnp.inf, pb, lanes=256)
        return ha.t, ha.prim, hb.t, hb.prim

    n = o.shape[0]
    state = (jnp.zeros(n, jnp.float32), jnp.full(n, -1, jnp.int32)) * 2
    for _ in range(12):
        state = step(groups, whole, *state)
        ta, pa, tb, pb = (np.asarray(x) for x in state)
        np.testing.assert_array_equal(pa, pb)
        np.testing.assert_array_equal(ta, tb)
    assert (pa >= 0).any()


def test_device_visibility_of_moving_frames_uses_the_groups(monkeypatch):
    """Opaque meshes traced in the program (`Execution.device_visibility`, forced on the CPU):
    frames of a moving mesh beside a static one carry the groups' BVHs after the first frame, and
    render what the host engine renders."""
    from jaxpbr.rendering import execute

    saved = (execute.EXECUTION.staged, execute.EXECUTION.device_visibility)
    mat = jp.Material(base_color=(0.7, 0.6, 0.5), metallic=0.0, roughness=0.5)
    cam = jp.Camera(position=(0.3, 1.5, 5.0), target=(0.0, 0.5, 0.0), fov_y_deg=45.0, width=32, height=24)
    P, N, _, T = uv_sphere(16, 24)
    ground = Mesh(positions=P * np.float32([3.0, 0.2, 3.0]), triangles=T, normals=N, material=mat)
    small_p, small_n, _, small_t = uv_sphere(6, 8)
    light = jp.PointLight((0.5, 3.0, 1.0), intensity=30.0)

    def frame(k):
        ball = Mesh(positions=small_p * 0.4 + np.float32([0.2 * k, 0.9, 0.0]), triangles=small_t, normals=small_n, material=mat)
        return jp.Scene(camera=cam, objects=[ground, ball], lights=[light])

    try:
        execute.EXECUTION.staged = False
        kinds = []
        for k in range(3):
            execute.EXECUTION.device_visibility = True
            kinds.append(type(mesh_mod.device_accel([ground, frame(k).objects[1]])).__name__)
            dev = np.asarray(jp.render(frame(k), shadows=True))
            execute.EXECUTION.device_visibility = False
            host = np.asarray(jp.render(frame(k), shadows=True))
            np.testing.assert_allclose(dev, host, rtol=1e-5, atol=1e-6)
    finally:
        execute.EXECUTION.staged, execute.EXECUTION.device_visibility = saved
    assert kinds[0] == "BVH" and kinds[2] == "tuple"


def test_edge_topology_of_several_meshes_is_kept_per_mesh():
    """The antialiasing's neighbour table (`edges.NEIGHBOURS`) of several meshes: made from each
    mesh's own table and the open edges where two meshes meet, it equals the table of the whole
    (a sphere cut into two meshes with their own copies of the vertices, beside a third mesh);
    when one mesh moves, only its table is computed again."""
    from jaxpbr.rendering.edges import _Neighbours, edge_neighbours

    P, _, _, T = uv_sphere(12, 16)
    P, T = P.astype(np.float32), T.astype(np.int32)
    half = len(T) // 2
    q, _, _, u = uv_sphere(5, 7)

    def scene(shift):
        v = np.concatenate([P, P, q.astype(np.float32) * 0.3 + np.float32([shift, 2.0, 0.0])])
        tri = np.concatenate([T[:half], T[half:] + len(P), u.astype(np.int32) + 2 * len(P)])
        parts = ((0, 0), (len(P), half), (2 * len(P), len(T)), (len(v), len(tri)))
        return v, tri, parts

    table = _Neighbours()
    v, tri, parts = scene(0.0)
    want = edge_neighbours(v, tri)
    assert (want[:half] >= half).any()  # the cut: edges joined across the two meshes
    np.testing.assert_array_equal(table.get(v, tri, parts), want)
    assert table.computed == 4  # three meshes and their assembly
    v, tri, parts = scene(0.5)
    np.testing.assert_array_equal(table.get(v, tri, parts), edge_neighbours(v, tri))
    assert table.computed == 6  # the moved mesh and the assembly
