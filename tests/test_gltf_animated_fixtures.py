"""Self-checks of the animated glTF fixtures (tests/gltf_animated.py), none of them through jaxpbr:
each file passes the Khronos glTF Validator and holds the scene its oracle evaluates (read back here
with a small accessor decoder), and the oracle's closed forms (quaternions, T R S, slerp, the cubic
Hermite spline, clamping, morphing, skinning) give the values worked out by hand."""

from __future__ import annotations

import base64
import json
import math
import struct
from dataclasses import replace
from pathlib import Path

import gltf_animated as G
import numpy as np
import pytest
from gltf_writer import _NP, validate, validator_missing


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory):
    return G.write_all(tmp_path_factory.mktemp("animated"))


def angle_between(q0, q1) -> float:
    """Degrees of the rotation taking unit quaternion q0 to q1."""
    return math.degrees(2 * math.acos(min(1.0, abs(float(np.dot(q0, q1))))))


# ---------------------------------------------------------------------------------------------
# The files: valid, and holding what the oracles evaluate
# ---------------------------------------------------------------------------------------------
def test_every_fixture_passes_the_khronos_validator(fixtures):
    why = validator_missing()
    if why:
        pytest.skip(why)
    report = validate(*(p for p, _ in fixtures.values()))
    for name, (path, _) in fixtures.items():
        r = report[str(path)]
        assert r["numErrors"] == 0, (name, r["errors"])
        assert sorted(w.split()[0] for w in r["warnings"]) == G.EXPECTED_WARNINGS.get(name, []), (name, r["warnings"])


def _load(path: Path):
    """(JSON, binary buffer) of a .gltf (external .bin or data URI) or .glb."""
    if path.suffix == ".glb":
        data = path.read_bytes()
        (n,) = struct.unpack_from("<I", data, 12)
        return json.loads(data[20:20 + n]), data[20 + n + 8:]
    doc = json.loads(path.read_text())
    uri = doc["buffers"][0]["uri"]
    return doc, (base64.b64decode(uri.split(",", 1)[1]) if uri.startswith("data:") else (path.parent / uri).read_bytes())


_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def _view(doc, buf, view, offset, count, dtype, n):
    v = doc["bufferViews"][view]
    stride = v.get("byteStride", n * dtype.itemsize)
    start = v.get("byteOffset", 0) + offset
    return np.ndarray((count, n), dtype, buf, start, (stride, dtype.itemsize)).copy()


def _accessor(doc, buf, i) -> np.ndarray:
    """Accessor i as float64 (count, components): bufferView (or zeros), sparse substitution,
    normalized integers divided by their maximum."""
    a = doc["accessors"][i]
    dtype, n = np.dtype(_NP[a["componentType"]]), _WIDTH[a["type"]]
    out = (_view(doc, buf, a["bufferView"], a.get("byteOffset", 0), a["count"], dtype, n) if "bufferView" in a
           else np.zeros((a["count"], n), dtype))
    if "sparse" in a:
        s = a["sparse"]
        idx = _view(doc, buf, s["indices"]["bufferView"], s["indices"].get("byteOffset", 0), s["count"],
                    np.dtype(_NP[s["indices"]["componentType"]]), 1)[:, 0]
        out[idx] = _view(doc, buf, s["values"]["bufferView"], s["values"].get("byteOffset", 0), s["count"], dtype, n)
    out = out.astype(np.float64)
    if a.get("normalized"):
        out /= np.iinfo(dtype).max
    return out


@pytest.mark.parametrize("name", list(G.FIXTURES))
def test_the_file_holds_the_scene_the_oracle_evaluates(fixtures, name):
    """Decoded from the file: node TRS, parents, weights; positions, morph targets (the sparse one
    too), joints and weights of all sets; inverse bind matrices; animation samplers."""
    path, scene = fixtures[name]
    doc, buf = _load(path)
    acc = lambda i: _accessor(doc, buf, i)
    assert doc["scenes"][doc["scene"]]["nodes"] == scene.roots
    assert len(doc["nodes"]) == len(scene.nodes)
    for i, (n, jn) in enumerate(zip(scene.nodes, doc["nodes"])):
        assert jn.get("mesh") == n.mesh and jn.get("skin") == n.skin and jn.get("weights") == (
            None if n.weights is None else list(n.weights))
        parents = [k for k, c in enumerate(doc["nodes"]) if i in c.get("children", [])]
        assert parents == ([] if n.parent is None else [n.parent])
        np.testing.assert_array_equal(jn.get("translation", [0, 0, 0]), n.translation)
        np.testing.assert_array_equal(jn.get("rotation", [0, 0, 0, 1]), n.rotation)
        np.testing.assert_array_equal(jn.get("scale", [1, 1, 1]), n.scale)
    for m, jm in zip(scene.meshes, doc["meshes"], strict=True):
        assert jm.get("weights") == (None if m.weights is None else list(m.weights))
        for p, jp in zip(m.primitives, jm["primitives"], strict=True):
            np.testing.assert_array_equal(acc(jp["attributes"]["POSITION"]), p.positions)
            np.testing.assert_array_equal(acc(jp["indices"]).reshape(-1, 3), p.triangles)
            assert len(jp.get("targets", [])) == len(p.targets)
            for t, jt in zip(p.targets, jp.get("targets", [])):
                assert set(jt) == set(t)
                for attr, d in t.items():
                    np.testing.assert_array_equal(acc(jt[attr]), d)
            if p.joints is not None:
                sets = p.joints.shape[1] // 4
                assert {k for k in jp["attributes"] if k[:6] in ("JOINTS", "WEIGHT")} == {
                    f"{k}_{s}" for k in ("JOINTS", "WEIGHTS") for s in range(sets)}
                joints = np.hstack([acc(jp["attributes"][f"JOINTS_{s}"]) for s in range(sets)])
                np.testing.assert_array_equal(joints, p.joints)
                np.testing.assert_allclose(np.hstack([acc(jp["attributes"][f"WEIGHTS_{s}"]) for s in range(sets)]),
                                           p.weights, rtol=0, atol=1e-15)
    for s, js in zip(scene.skins, doc.get("skins", []), strict=True):
        assert js["joints"] == s.joints and js.get("skeleton") == s.skeleton
        np.testing.assert_array_equal(acc(js["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1),
                                      s.inverse_bind_matrices)
    assert [a["name"] for a in doc.get("animations", [])] == [a.name for a in scene.animations]
    for a, ja in zip(scene.animations, doc.get("animations", [])):
        for c, jc in zip(a.channels, ja["channels"], strict=True):
            assert jc["target"] == {"node": c.node, "path": c.path}
            smp = ja["samplers"][jc["sampler"]]
            assert smp["interpolation"] == c.sampler.interpolation
            np.testing.assert_array_equal(acc(smp["input"])[:, 0], c.sampler.input)
            np.testing.assert_array_equal(acc(smp["output"]).ravel(), c.sampler.output.ravel())


@pytest.mark.parametrize("name", list(G.FIXTURES))
def test_compared_times_cover_clamping_keys_and_between(fixtures, name):
    """Every animation is compared before its first key, exactly on each key, between keys and
    after its last key, and all its expected positions are finite and move."""
    _, scene = fixtures[name]
    for a in scene.animations:
        keys, times = a.key_times, np.asarray(a.times)
        assert times.min() < keys.min() or keys.min() == 0
        assert times.max() > keys.max()
        assert set(keys) <= set(times)
        assert len(set(times) - set(keys)) >= len(keys)
        poses = [scene(t, a.name) for t in times]
        for p in poses:
            assert all(np.isfinite(v).all() for v in p.values())
        spread = max(np.abs(p[k] - poses[0][k]).max() for p in poses for k in p)
        assert spread > 0.1, a.name


# ---------------------------------------------------------------------------------------------
# The closed forms themselves
# ---------------------------------------------------------------------------------------------
def test_quaternion_matrix_is_rodrigues():
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    th = math.radians(73)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    np.testing.assert_allclose(G.quat_matrix(G.quat_axis_angle(axis, 73)), np.eye(3) + math.sin(th) * k
                               + (1 - math.cos(th)) * k @ k, atol=1e-15)
    np.testing.assert_allclose(G.quat_matrix(G.quat_axis_angle((0, 0, 1), 90)) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_trs_scales_then_rotates_then_translates():
    m = G.trs_matrix((1, 2, 3), G.quat_axis_angle((0, 0, 1), 90), (2, 3, 4))
    np.testing.assert_allclose(m @ [1, 0, 0, 1], [1, 4, 3, 1], atol=1e-15)  # x 2 -> (0, 2, 0) -> + t
    np.testing.assert_allclose(m @ [0, 1, 0, 1], [-2, 2, 3, 1], atol=1e-15)


def test_slerp_halfway_and_quarter_and_its_difference_from_nlerp():
    q0, q1 = G.quat_axis_angle((0, 0, 1), 0), G.quat_axis_angle((0, 0, 1), 120)
    np.testing.assert_allclose(G.slerp(q0, q1, 0.5), G.quat_axis_angle((0, 0, 1), 60), atol=1e-15)
    np.testing.assert_allclose(G.slerp(q0, q1, 0.25), G.quat_axis_angle((0, 0, 1), 30), atol=1e-15)
    np.testing.assert_allclose(G.slerp(q0, q1, 0.0), q0, atol=1e-15)
    np.testing.assert_allclose(G.slerp(q0, q1, 1.0), q1, atol=1e-15)
    nlerp = 0.75 * q0 + 0.25 * q1
    assert angle_between(nlerp / np.linalg.norm(nlerp), q0) == pytest.approx(27.8, abs=0.05)  # not 30


def test_slerp_takes_the_shortest_path():
    """The pair of keys with a negative dot (the fixture's): the same as towards the negated key,
    and the rotation turns through the short angle at a constant rate."""
    _, q1, q2 = G.TRS_ROTATION_KEYS[1]
    assert np.dot(q1, q2) < 0
    short = angle_between(q1, q2)
    assert short < 180
    for s in (0.25, 0.5, 0.8):
        q = G.slerp(q1, q2, s)
        np.testing.assert_allclose(q, G.slerp(q1, -q2, s), atol=1e-15)
        assert angle_between(q1, q) == pytest.approx(s * short, abs=1e-9)
        assert angle_between(q, q2) == pytest.approx((1 - s) * short, abs=1e-9)
        np.testing.assert_allclose(np.linalg.norm(q), 1, atol=1e-15)
    long_way = (q1 + q2) / np.linalg.norm(q1 + q2)  # what a slerp without the sign flip passes at s = 1/2
    assert angle_between(long_way, G.slerp(q1, q2, 0.5)) > 90


def test_hermite_zero_tangents_is_smoothstep_and_it_reproduces_cubics():
    for s in np.linspace(0, 1, 9):
        assert G.hermite(2.0, 0.0, 5.0, 0.0, 3.7, s) == pytest.approx(2 + 3 * (3 * s * s - 2 * s ** 3), abs=1e-14)
    # p(t) = t^3 - 2 t on [1.5, 4]: values and derivatives at the keys give p back (tangents are per
    # second; td scales them).
    p, dp = (lambda t: t ** 3 - 2 * t), (lambda t: 3 * t * t - 2)
    for t in np.linspace(1.5, 4.0, 7):
        s = (t - 1.5) / 2.5
        assert G.hermite(p(1.5), dp(1.5), p(4.0), dp(4.0), 2.5, s) == pytest.approx(p(t), rel=1e-13)


def test_sampling_clamps_steps_and_interpolates():
    lin = G.Channel(0, "translation", G.Sampler(np.array([1.0, 2.0, 4.0]), np.array([[0.0], [10.0], [30.0]])))
    step = G.Channel(0, "scale", replace(lin.sampler, interpolation="STEP"))
    cases = {0.0: (0, 0), 1.0: (0, 0), 1.5: (5, 0), 2.0: (10, 10), 3.0: (20, 10), 3.999: (29.99, 10), 4.0: (30, 30),
             9.0: (30, 30)}
    for t, (want_lin, want_step) in cases.items():
        assert G.sample(lin, t)[0] == pytest.approx(want_lin)
        assert G.sample(step, t)[0] == want_step
    # CUBICSPLINE rotations: the Hermite of the 4 components, normalised; the keys are reached.
    q0, q1 = G.quat_axis_angle((0, 1, 0), 10), G.quat_axis_angle((0, 1, 0), 80)
    cub = G.Channel(0, "rotation", G.Sampler(np.array([0.0, 1.0]), np.array([[0 * q0, q0, q1 - q0], [q1 - q0, q1, 0 * q1]]),
                                             "CUBICSPLINE"))
    np.testing.assert_allclose(G.sample(cub, 0.0), q0)
    np.testing.assert_allclose(G.sample(cub, 1.0), q1)
    h = G.hermite(q0, q1 - q0, q1, q1 - q0, 1.0, 0.3)
    np.testing.assert_allclose(G.sample(cub, 0.3), h / np.linalg.norm(h), atol=1e-15)


def test_trs_fixture_by_hand(tmp_path):
    """The child's tetrahedron: parent P (static) . child T R S, worked out from the keys."""
    p = G.trs_matrix(*(G.f32(G.TRS_PARENT[k]) for k in ("translation", "rotation", "scale")))
    _, scene = G.trs_animation(tmp_path)
    v = G.f32(G.TETRA)
    tk, rk, sk = G.TRS_TRANSLATION_KEYS[1], G.f32(G.TRS_ROTATION_KEYS[1]), G.TRS_SCALE_KEYS[1]
    child_rest = G.trs_matrix(*(G.f32(G.TRS_CHILD[k]) for k in ("translation", "rotation", "scale")))
    want = {
        None: p @ child_rest,
        0.0: p @ G.trs_matrix(tk[0], rk[0], sk[0]),  # clamped to the first keys, not the rest pose
        0.875: p @ G.trs_matrix((0.75, 1.75, 0), G.quat_axis_angle((0, 0, 1), 60), sk[0]),  # slerp at 1/2, STEP holds
        1.0: p @ G.trs_matrix(tk[1], G.slerp(rk[0], rk[1], 2 / 3), sk[1]),  # on a translation and a scale key
        1.25: p @ G.trs_matrix((0.5, 1.625, 0.25), rk[1], sk[1]),  # on the rotation key
        3.0: p @ G.trs_matrix(tk[2], rk[2], sk[2]),
    }
    for t, m in want.items():
        np.testing.assert_allclose(scene(t)[(1, 0, 0)], G.transform(m, v), atol=1e-6)
    # 'cubic' at t = 0.5: translation s = 1/2 on [0, 1]: (v0 + v1) / 2 + (b0 - a1) / 8 = (1.25, 0.75, 0);
    # at 0.1 the parent's rotation is still clamped to its first key (identity).
    c = G.CUBIC_TRANSLATION_KEYS[1]
    s = 0.1
    tr = ((2 * s ** 3 - 3 * s ** 2 + 1) * np.array(c[0][1]) + (s ** 3 - 2 * s ** 2 + s) * np.array(c[0][2])
          + (-2 * s ** 3 + 3 * s ** 2) * np.array(c[1][1]) + (s ** 3 - s ** 2) * np.array(c[1][0]))
    p_identity_rot = G.trs_matrix(G.f32(G.TRS_PARENT["translation"]), (0, 0, 0, 1), G.f32(G.TRS_PARENT["scale"]))
    m = p_identity_rot @ G.trs_matrix(tr, *(G.f32(G.TRS_CHILD[k]) for k in ("rotation", "scale")))
    np.testing.assert_allclose(scene(0.1, "cubic")[(1, 0, 0)], G.transform(m, v), atol=1e-6)
    ch = scene.animation("cubic").channels[0]
    np.testing.assert_allclose(G.sample(ch, 0.5), [1.25, 0.75, 0], atol=1e-7)


def test_morph_fixture_by_hand(tmp_path):
    _, scene = G.morph_animation(tmp_path)
    pos, _, _, (t0, t1) = G.morph_targets()
    dome, sparse = t0["POSITION"], t1["POSITION"]
    assert np.count_nonzero(np.any(sparse != 0, axis=1)) == len(G.MORPH_SPARSE)
    r = G.quat_matrix(G.f32(G.quat_axis_angle((0, 1, 0), 30)))
    node0 = lambda w0, w1: pos + w0 * dome + w1 * sparse + [-2.5, 0, 0]
    node1 = lambda w0, w1: (pos + w0 * dome + w1 * sparse) @ r.T + [2.5, 0, 0]
    rest = scene()
    np.testing.assert_allclose(rest[(0, 0, 0)], node0(0.25, 0), atol=1e-7)  # mesh.weights
    np.testing.assert_allclose(rest[(1, 0, 0)], node1(0.75, 0.5), atol=1e-7)  # node.weights override them
    # 'weights linear' (node 0; node 1 at rest): clamped, on a key, between keys.
    for t, w in {0.0: (0, 0), 0.75: (0.5, 0.25), 1.0: (1, 0.5), 1.5: (0.625, 0.75), 3.0: (0.25, 1)}.items():
        e = scene(t, "weights linear")
        np.testing.assert_allclose(e[(0, 0, 0)], node0(*w), atol=1e-7)
        np.testing.assert_allclose(e[(1, 0, 0)], node1(0.75, 0.5), atol=1e-7)
    # 'weights step' (node 1; node 0 at rest).
    for t, w in {0.0: (1, 0), 0.99: (1, 0), 1.0: (0, 1), 1.25: (0, 1), 1.5: (0.5, 0.5), 3.0: (0.5, 0.5)}.items():
        e = scene(t, "weights step")
        np.testing.assert_allclose(e[(1, 0, 0)], node1(*w), atol=1e-7)
        np.testing.assert_allclose(e[(0, 0, 0)], node0(0.25, 0), atol=1e-7)


def test_skinning_one_joint_is_its_joint_matrix():
    """A single joint, weight 1 (hand-built, not a fixture): v' = jointWorld . IBM . v, whatever the
    skinned node's own transform and the other slots (weight 0)."""
    bind = G.trs_matrix((0, 1, 0))
    pose = G.trs_matrix((1, 1, 0), G.quat_axis_angle((0, 0, 1), 90))
    v = np.array([[0.0, 2.0, 0.0], [1.0, 1.0, 0.0]])
    scene = G.AnimatedScene(
        nodes=[G.Node("joint", translation=(1, 1, 0), rotation=tuple(G.quat_axis_angle((0, 0, 1), 90))),
               G.Node("skinned", translation=(5, 5, 5), scale=(2, 2, 2), mesh=0, skin=0)],
        meshes=[G.Mesh("m", [G.Primitive(v, np.array([[0, 1, 0]]), joints=np.zeros((2, 4), int),
                                         weights=np.array([[0, 1.0, 0, 0], [1.0, 0, 0, 0]]))])],
        roots=[0, 1], skins=[G.Skin([0], np.stack([G.affine_inverse(bind)]))])
    # bone-space (0, 1, 0) and (1, 0, 0), turned 90 degrees about Z at (1, 1, 0)
    np.testing.assert_allclose(scene()[(1, 0, 0)], [[0, 1, 0], [1, 2, 0]], atol=1e-15)
    np.testing.assert_allclose(scene()[(1, 0, 0)], G.transform(pose @ np.linalg.inv(bind), v), atol=1e-15)


def test_skinned_fixture_in_the_bind_pose_is_the_mesh_and_the_rest_pose_is_not(tmp_path):
    _, scene = G.skinned(tmp_path)
    joints = scene.skins[0].joints
    assert [scene.nodes[j].name for j in joints] == list(G.JOINT_NAMES)
    nodes = list(scene.nodes)
    for j, name in zip(joints, G.JOINT_NAMES):
        pose = {"translation": (0, 0, 0), "rotation": (0, 0, 0, 1), "scale": (1, 1, 1), **G.BIND_POSE[name]}
        nodes[j] = replace(nodes[j], **{k: tuple(G.f32(v)) for k, v in pose.items()})
    bound = replace(scene, nodes=nodes)
    rest = scene()
    for key, got in bound().items():
        p = scene.meshes[key[1]].primitives[key[2]]
        np.testing.assert_allclose(got, p.positions, atol=2e-6)
        assert np.abs(rest[key] - p.positions).max() > 0.3
        np.testing.assert_allclose(p.weights.sum(1), 1.0, rtol=0, atol=1e-15)
        assert (p.weights == 0).sum(1).min() >= 5 and np.count_nonzero(p.weights[:, 4:]) > 0


def test_skinned_fixture_by_hand(tmp_path):
    """Rows held by one joint only: the armature A, the joints' rest (or animated) locals L_j, the
    bind world B_j: v' = A L_0 .. L_j B_j^-1 v; and v' is a weighted sum of those for the others."""
    _, scene = G.skinned(tmp_path)
    a = G.trs_matrix(*(G.f32(G.ARMATURE[k]) for k in ("translation", "rotation", "scale")))
    local = {n: G.trs_matrix(*(G.f32(G.REST_POSE[n].get(k, d)) for k, d in
                               (("translation", (0, 0, 0)), ("rotation", (0, 0, 0, 1)), ("scale", (1, 1, 1)))))
             for n in G.JOINT_NAMES}
    b_inv = [np.linalg.inv(b) for b in G.bind_world_matrices()]
    keys = G.f32(G.BEND_KEYS[1])
    # joint 1's rotation: its rest one; clamped to the first key; halfway from 60 to -30 degrees
    # about Z (keys at 0.25 and 1.0): 15 degrees; clamped to the last key.
    bend = {None: None, 0.0: keys[0], 0.625: G.quat_axis_angle((0, 0, 1), 15), 2.5: keys[2]}
    for t, q in bend.items():
        l1 = local["joint 1"] if q is None else G.trs_matrix(G.f32(G.REST_POSE["joint 1"]["translation"]), q)
        w = [a @ local["joint 0"], a @ local["joint 0"] @ l1, a @ local["joint 0"] @ l1 @ local["joint 2"]]
        m = [w[j] @ b_inv[j] for j in range(3)]
        got = scene(t)
        for prim in (0, 1):
            p = scene.meshes[0].primitives[prim]
            v = p.positions
            np.testing.assert_allclose(got[(5, 0, prim)][:2], G.transform(m[0], v[:2]), atol=2e-6)  # row 0
            np.testing.assert_allclose(got[(5, 0, prim)][12:], G.transform(m[2], v[12:]), atol=2e-6)  # row 6
            wj = np.array(G.ROW_WEIGHTS_64[3] if prim == 0 else G.ROW_WEIGHTS_255[3]) / (64.0 if prim == 0 else 255.0)
            mix = sum(wj[j] * G.transform(m[j], v[6:8]) for j in range(3))  # row 3: three joints
            np.testing.assert_allclose(got[(5, 0, prim)][6:8], mix, atol=2e-6)


def test_morph_and_skin_morphs_before_skinning(tmp_path):
    _, scene = G.morph_and_skin(tmp_path)
    p = scene.meshes[0].primitives[0]
    sk = scene.skins[0]
    for t in (None, 0.25, 1.75):
        _, weights = scene.pose(t)
        world = scene.world_matrices(t)
        jm = np.stack([world[j] @ ibm for j, ibm in zip(sk.joints, sk.inverse_bind_matrices)])
        morphed = p.positions + weights[4][0] * p.targets[0]["POSITION"] + weights[4][1] * p.targets[1]["POSITION"]
        want = np.stack([sum(p.weights[v, k] * G.transform(jm[p.joints[v, k]], morphed[v:v + 1])[0] for k in range(4))
                         for v in range(len(morphed))])
        np.testing.assert_allclose(scene(t)[(4, 0, 0)], want, atol=1e-12)
    # the rest weights are mesh.weights; CUBICSPLINE weights at t = 0.25: Hermite on [0, 1]
    np.testing.assert_allclose(scene.pose()[1][4], G.MS_MESH_WEIGHTS)
    keys = np.array(G.MS_WEIGHT_KEYS[1], np.float64)
    np.testing.assert_allclose(scene.pose(0.25)[1][4], G.hermite(keys[0, 1], keys[0, 2], keys[1, 1], keys[1, 0], 1.0, 0.25))
