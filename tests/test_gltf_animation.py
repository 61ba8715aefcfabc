"""glTF animation, skins and morph targets (glTF 2.0 §3.7.2.2, §3.7.3, §3.11, Appendix C):
`read_gltf(path, time=, animation=)` and the re-posing of a loaded asset (`posed_asset`, NumPy;
`pose_primitives` traced by JAX) against the closed-form poses of the fixtures written in
`tests/gltf_animated.py` (float64 NumPy of the spec's formulas, independent of jaxpbr), and the
keyframe sampler against closed forms. Tolerance: the loader stores float32 world positions of
O(1) coordinates: 2e-6 absolute (a few float32 ulps of the composed matrices)."""

from __future__ import annotations

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gltf_animated import FIXTURES
from jaxpbr.errors import InputError
from jaxpbr.geometry.animation import sample, slerp
from jaxpbr.io.gltf import read_gltf
from jaxpbr.io.gltf import pose_primitives, posed_asset

ATOL = 2e-6


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory):
    out = tmp_path_factory.mktemp("animated")
    return {name: build(out) for name, build in FIXTURES.items()}


def _corners(positions, triangles) -> np.ndarray:
    """(T, 3, 3) the triangles' corner positions, each triangle's corners in a canonical order (a
    primitive without normals is unwelded into corners, and a mirroring transform turns the winding)."""
    c = np.asarray(positions, np.float64)[np.asarray(triangles)]
    order = np.lexsort(np.round(c, 4).transpose(2, 0, 1)[::-1], axis=-1)
    c = np.take_along_axis(c, order[..., None], axis=1)
    return c[np.lexsort(np.round(c.reshape(len(c), -1), 4).T[::-1])]


def _by_key(asset) -> dict:
    return {(p.node, p.mesh, p.primitive): _corners(p.positions, p.indices) for p in asset.primitives}


def _want(scene, time=None, animation=0) -> dict:
    tris = {(i, n.mesh, j): pr.triangles for i, n in enumerate(scene.nodes) if n.mesh is not None
            for j, pr in enumerate(scene.meshes[n.mesh].primitives)}
    return {k: _corners(v, tris[k]) for k, v in scene(time, animation).items()}


def _cases(fixtures):
    for name, (path, scene) in fixtures.items():
        for a, anim in enumerate(scene.animations):
            for t in anim.times:
                yield name, path, scene, a, float(t)


@pytest.mark.parametrize("name", list(FIXTURES))
def test_rest_pose(fixtures, name):
    """No time: the nodes' rest transforms, skins applied, the node's (else the mesh's) morph weights."""
    path, scene = fixtures[name]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        asset = read_gltf(path)
    got, want = _by_key(asset), _want(scene, None)
    assert set(got) == set(want)
    for k in want:
        np.testing.assert_allclose(got[k], want[k], atol=ATOL, err_msg=f"{name} {k}")


@pytest.mark.parametrize("name", list(FIXTURES))
def test_every_key_and_between(fixtures, name):
    """Each animation (by index and by name) at times before, on, between and after its keys:
    read_gltf(time=) and the re-pose of the rest-pose asset agree with the closed forms."""
    path, scene = fixtures[name]
    rest = read_gltf(path)
    for a, anim in enumerate(scene.animations):
        for t in anim.times:
            want = _want(scene, float(t), a)
            loaded = read_gltf(path, time=float(t), animation=anim.name if a % 2 else a)
            assert loaded.time == float(t) and loaded.animation == a
            reposed = posed_asset(rest, float(t), a)
            for asset, how in ((loaded, "read_gltf"), (reposed, "posed_asset")):
                got = _by_key(asset)
                for k in want:
                    np.testing.assert_allclose(got[k], want[k], atol=ATOL, err_msg=f"{name} {how} animation {a} t={t} {k}")


def test_jax_pose_matches_numpy_and_differentiates(fixtures):
    """The same posing traced by JAX (float32): equal to the NumPy pose, jit-compiled and vmapped
    over time, with finite derivatives in time that match central differences of the closed form."""
    path, scene = fixtures["skinned"]
    asset = read_gltf(path)

    def positions(t):
        posed = pose_primitives(asset, t, 0, xp=jnp)
        return jnp.concatenate([posed[k][0] for k in sorted(posed)])

    # the loader's vertices (unwelded corners: the strips have no normals) -> the fixture's, by
    # their rest positions (distinct)
    moving = [k for k, p in enumerate(asset.primitives) if p.deform is not None]
    rest = scene(None)
    order = []
    for k in moving:
        p = asset.primitives[k]
        want_rest = rest[(p.node, p.mesh, p.primitive)]
        d = np.linalg.norm(np.asarray(p.positions, np.float64)[:, None] - want_rest[None], axis=-1)
        assert np.all(d.min(axis=1) < ATOL)
        order.append(((p.node, p.mesh, p.primitive), d.argmin(axis=1)))

    def expected(t):
        w = scene(float(t), 0)
        return np.concatenate([w[key][idx] for key, idx in order])

    ts = jnp.asarray([0.0, 0.5, 0.625, 1.5, 2.5], jnp.float32)
    batch = jax.jit(jax.vmap(positions))(ts)
    for i, t in enumerate(np.asarray(ts)):
        np.testing.assert_allclose(np.asarray(batch[i]), expected(t), atol=1e-5)
    # d positions / d t inside a key interval against central differences of the closed form
    t0, h = 0.625, 1e-4
    jac = np.asarray(jax.jit(jax.jacfwd(positions))(jnp.float32(t0)))
    fd = (expected(t0 + h) - expected(t0 - h)) / (2 * h)
    assert np.isfinite(jac).all() and np.abs(fd).max() > 0.1
    np.testing.assert_allclose(jac, fd, atol=2e-3 * np.abs(fd).max())


def test_rotation_gradient_finite_at_equal_keys():
    """slerp of equal (and opposite: the same rotation) quaternions: finite values and gradients."""
    q = jnp.asarray([0.0, 0.0, math.sin(0.3), math.cos(0.3)])

    @jax.jit
    def grads(q1):
        g = jax.grad(lambda s: jnp.sum(slerp(q, q1, s, jnp) * jnp.arange(4.0)))(0.3)
        gq = jax.grad(lambda a: jnp.sum(slerp(a, q1, 0.3, jnp)))(q)
        return g, gq

    for q1 in (q, -q, q + 1e-8):
        g, gq = grads(q1)
        assert np.isfinite(float(g)) and np.isfinite(np.asarray(gq)).all()


def test_sampler_closed_forms():
    """STEP holds each key until the next (the next at exactly its time); LINEAR of rotations is
    constant-speed slerp on the short arc; CUBICSPLINE is the Hermite with tangents times the key
    interval; both ends clamp."""
    times = np.array([1.0, 2.0, 4.0])
    v = np.array([[0.0], [10.0], [30.0]])
    assert [float(sample(times, v, "STEP", t)[0]) for t in (0.0, 1.0, 1.999, 2.0, 3.9, 4.0, 9.0)] == [0, 0, 0, 10, 10, 30, 30]
    assert [float(sample(times, v, "LINEAR", t)[0]) for t in (0.5, 1.5, 3.0, 5.0)] == [0, 5, 20, 30]
    # slerp: the angle grows linearly (z rotation from 0 to 120 degrees, and a negative-dot key pair)
    q0 = np.array([[0, 0, 0, 1.0], [0, 0, math.sin(math.radians(60)), math.cos(math.radians(60))]])
    for s in (0.1, 0.25, 0.5, 0.9):
        q = sample(np.array([0.0, 1.0]), q0, "LINEAR", s, rotation=True)
        assert math.isclose(2 * math.degrees(math.atan2(q[2], q[3])), 120 * s, abs_tol=1e-9)
    flipped = q0 * np.array([[1.0], [-1.0]])
    q = sample(np.array([0.0, 1.0]), flipped, "LINEAR", 0.25, rotation=True)
    assert math.isclose(abs(2 * math.degrees(math.atan2(q[2], q[3]))), 30.0, abs_tol=1e-9)
    # Hermite with known tangents: p(s) = s^3 on [0, 2] (td = 2): v0 = 0, v1 = 8, dp/dt = 3 t^2 -> b0 = 0, a1 = 12
    cubic = np.array([[[0.0], [0.0], [0.0]], [[12.0], [8.0], [0.0]]])
    for t in (0.0, 0.5, 1.3, 2.0, 3.0):
        assert math.isclose(float(sample(np.array([0.0, 2.0]), cubic, "CUBICSPLINE", t)[0]), min(t, 2.0) ** 3, abs_tol=1e-12)


def test_bad_requests(fixtures):
    path, _ = fixtures["trs_animation"]
    with pytest.raises(InputError, match=r"animation='nope'.*names no animation.*0 \('trs'\), 1 \('cubic'\)"):
        read_gltf(path, time=1.0, animation="nope")
    with pytest.raises(InputError, match=r"time=nan.*finite"):
        read_gltf(path, time=float("nan"))


@pytest.mark.parametrize("name", ["trs_animation", "morph_animation", "morph_and_skin"])
def test_against_threejs(fixtures, name):
    """An independent implementation: three.js r170 (GLTFLoader + AnimationMixer, tests/three_pose.mjs)
    at every test time of every animation, and at rest. (The `skinned` fixture uses a second
    JOINTS_1/WEIGHTS_1 set, which three ignores: it is checked against the closed forms only.)
    Tolerance: float32 storage on both sides, 2e-6."""
    from three_oracle import three_missing, three_pose

    why = three_missing()
    if why:
        pytest.skip(why)
    path, scene = fixtures[name]
    rest = read_gltf(path)
    runs = [(None, [0.0])] + [(a, [float(t) for t in anim.times]) for a, anim in enumerate(scene.animations)]
    for anim, times in runs:
        ref = three_pose(path, anim, times)
        for i, t in enumerate(times):
            asset = rest if anim is None else posed_asset(rest, t, anim)
            got = {(p.node, p.mesh, p.primitive): p for p in asset.primitives}
            assert set(ref["positions"]) == set(got)
            for key, pos in ref["positions"].items():
                p = got[key]
                want = pos[i]
                if p.flat_normals:  # (jaxpbr unwelds the corners of a primitive without normals)
                    np.testing.assert_allclose(_corners(p.positions, p.indices), _corners(want, _file_triangles(scene, key)), atol=ATOL)
                else:
                    np.testing.assert_allclose(np.asarray(p.positions, np.float64), want, atol=ATOL,
                                               err_msg=f"{name} animation {anim} t={t} {key}")


def _file_triangles(scene, key):
    node, mesh, prim = key
    return scene.meshes[mesh].primitives[prim].triangles


# ---------------------------------------------------------------------------------------------
# Malformed and hostile animation data: clear errors naming the JSON location, before any pose
# ---------------------------------------------------------------------------------------------
def _animated_triangle(times, values, *, interpolation="LINEAR", path="translation", joints=None, weights=None):
    from gltf_writer import Builder

    FLOAT = 5126
    b = Builder()
    attrs = {"POSITION": b.accessor(np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), FLOAT, "VEC3", minmax=True)}
    if joints is not None:
        attrs["JOINTS_0"] = b.accessor(np.uint8(joints), 5121, "VEC4")
        attrs["WEIGHTS_0"] = b.accessor(np.float32(weights), FLOAT, "VEC4")
    b.add("meshes", {"primitives": [{"attributes": attrs}]})
    b.add("nodes", {"mesh": 0, **({"skin": 0} if joints is not None else {})})
    b.add("nodes", {"name": "joint"})
    b.add("scenes", {"nodes": [0, 1]})
    if joints is not None:
        b.add("skins", {"joints": [1]})
    kind = {"translation": "VEC3", "rotation": "VEC4", "scale": "VEC3"}[path]
    b.add("animations", {"channels": [{"sampler": 0, "target": {"node": 1 if joints is not None else 0, "path": path}}],
                         "samplers": [{"input": b.accessor(np.float32(times), FLOAT, "SCALAR", minmax=True),
                                       "output": b.accessor(np.float32(values), FLOAT, kind), "interpolation": interpolation}]})
    return b


def test_key_times_must_increase(tmp_path):
    path = _animated_triangle([0.0, 1.0, 1.0], [[0, 0, 0]] * 3).write(tmp_path / "a.gltf")
    with pytest.raises(InputError, match=r"animation 0 sampler 0 input \(/animations/0/samplers/0/input\): key times are "
                                         r"not strictly increasing \(keys 1 and 2"):
        read_gltf(path)


def test_output_count_must_match(tmp_path):
    path = _animated_triangle([0.0, 1.0], [[0, 0, 0]] * 3, interpolation="CUBICSPLINE").write(tmp_path / "a.gltf")
    with pytest.raises(InputError, match=r"/animations/0/samplers/0/output.*holds 3 values where 2 keys x 3 .* need 6"):
        read_gltf(path)


def test_joint_index_outside_the_skin(tmp_path):
    path = _animated_triangle([0.0, 1.0], [[0, 0, 0]] * 2, joints=[[0, 0, 0, 0], [3, 0, 0, 0], [0, 0, 0, 0]],
                              weights=[[1, 0, 0, 0]] * 3).write(tmp_path / "a.gltf")
    with pytest.raises(InputError, match=r"skin 0.*names a joint past the skin's 1 joints \(the first such vertex: 1\)"):
        read_gltf(path)


def test_huge_declared_animation_refused_before_reading(tmp_path):
    """A key count of billions (a hostile file of a few hundred bytes) is refused by the memory
    check that runs before any buffer is read, naming the animation."""
    from jaxpbr._memory import MemoryLimitError

    b = _animated_triangle([0.0, 1.0], [[0, 0, 0]] * 2)
    acc = b.doc["animations"][0]["samplers"][0]["output"]
    b.doc["accessors"][acc]["count"] = 3_000_000_000
    b.doc["accessors"][acc].pop("bufferView", None)  # (no bufferView: zeros, its size unbounded by a buffer)
    path = b.write(tmp_path / "huge.gltf")
    with pytest.raises(MemoryLimitError, match=r"/animations/0"):
        read_gltf(path)


# ---------------------------------------------------------------------------------------------
# Gradients of the pose: joint rotations, morph weights, key values (against central differences
# of the same pose in float64 NumPy: the derivative of the function, not of its float32 rounding)
# ---------------------------------------------------------------------------------------------
def _jac_vs_fd(f_jax, f_np, x0, h=1e-4, rtol=2e-3):
    J = np.asarray(jax.jit(jax.jacfwd(f_jax))(jnp.asarray(x0, jnp.float32)))
    x0 = np.asarray(x0, np.float64)
    flat = x0.ravel()
    for i in range(flat.size):
        e = np.zeros_like(flat)
        e[i] = h
        fd = (f_np((flat + e).reshape(x0.shape)) - f_np((flat - e).reshape(x0.shape))) / (2 * h)
        got = J.reshape(J.shape[: J.ndim - x0.ndim] + (-1,))[..., i]
        scale = max(np.abs(fd).max(), 1e-3)
        np.testing.assert_allclose(got, fd, atol=rtol * scale, err_msg=f"parameter {i}")


def _stack(posed):
    return [posed[k][0] for k in sorted(posed)]


def test_gradient_joint_rotations(fixtures):
    """d(skinned vertices)/d(the joints' rest rotations), through the hierarchy and the skin."""
    path, _ = fixtures["skinned"]
    asset = read_gltf(path)
    joints = np.asarray(asset.skins[0].joints)
    n = asset.nodes

    def rest(q, xp):
        r = xp.asarray(n.rotation)
        r = r.at[joints].set(q) if xp is jnp else np.concatenate([r[: joints[0]], q, r[joints[-1] + 1:]])
        return (xp.asarray(n.translation), r, xp.asarray(n.scale))

    assert np.all(np.diff(joints) == 1)
    f_jax = lambda q: jnp.concatenate(_stack(pose_primitives(asset, xp=jnp, rest=rest(q, jnp))))  # noqa: E731
    f_np = lambda q: np.concatenate(_stack(pose_primitives(asset, rest=rest(q, np))))  # noqa: E731
    _jac_vs_fd(f_jax, f_np, n.rotation[joints])


def test_gradient_morph_weights_and_key_values(fixtures):
    """d(vertices)/d(morph weights) (the targets' deltas) and d(vertices)/d(an animation's key values)."""
    import dataclasses

    path, _ = fixtures["morph_and_skin"]
    asset = read_gltf(path)
    node = next(p.node for p in asset.primitives if p.deform is not None and p.deform.targets)
    K = next(p.deform.targets["POSITION"].shape[0] for p in asset.primitives if p.node == node)
    f_jax = lambda w: jnp.concatenate(_stack(pose_primitives(asset, 0.7, 0, xp=jnp, morph_weights={node: w})))  # noqa: E731
    f_np = lambda w: np.concatenate(_stack(pose_primitives(asset, 0.7, 0, morph_weights={node: w})))  # noqa: E731
    _jac_vs_fd(f_jax, f_np, np.full(K, 0.3))
    anim = asset.animations[0]
    k = next(i for i, c in enumerate(anim.channels) if c.path == "rotation")
    ch = anim.channels[k]

    def with_values(v):
        chans = list(anim.channels)
        chans[k] = dataclasses.replace(ch, values=v)
        return dataclasses.replace(anim, channels=tuple(chans))

    t = float(0.5 * (ch.times[0] + ch.times[-1])) if ch.interpolation != "STEP" else float(ch.times[0])
    f_jax = lambda v: jnp.concatenate(_stack(pose_primitives(asset, t, with_values(v), xp=jnp)))  # noqa: E731
    f_np = lambda v: np.concatenate(_stack(pose_primitives(asset, t, with_values(v))))  # noqa: E731
    _jac_vs_fd(f_jax, f_np, ch.values)


def test_morphed_without_animations_or_skins(tmp_path):
    """A file with morph targets and no animations or skins takes the loader's static path (no pass
    over the nodes): the rest pose holds the node's and mesh's weights, and `pose_primitives`
    re-poses it with other weights (the morph's own derivative checked above)."""
    import dataclasses

    from gltf_animated import morph_animation, write_scene

    _, scene = morph_animation(tmp_path)
    still = dataclasses.replace(scene, animations=[])
    path = write_scene(still, tmp_path / "still.glb", mode="glb")
    asset = read_gltf(path)
    assert asset.nodes is None and asset.animations == ()
    got, want = _by_key(asset), _want(still, None)
    for k in want:
        np.testing.assert_allclose(got[k], want[k], atol=ATOL)
    assert posed_asset(asset) is asset
    node = next(p.node for p in asset.primitives if p.deform is not None)
    K = next(p.deform.targets["POSITION"].shape[0] for p in asset.primitives if p.node == node)
    posed = pose_primitives(asset, morph_weights={node: np.zeros(K)})
    k = next(i for i, p in enumerate(asset.primitives) if p.node == node)
    base = asset.primitives[k].deform.positions @ asset.primitives[k].world_matrix[:3, :3].T + asset.primitives[k].world_matrix[:3, 3]
    np.testing.assert_allclose(posed[k][0], base, atol=1e-12)
    with pytest.raises(InputError, match="has no animations"):
        read_gltf(path, time=1.0)
