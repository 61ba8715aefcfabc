"""Animated glTF 2.0 test fixtures, written in code (tests/gltf_writer.py's Builder), each with its
expected world-space vertex positions at any time computed here in NumPy float64 from the closed
forms of the glTF 2.0 specification (§3.7.2.2 morph targets, §3.7.3 skins, §3.11 animations,
Appendix C interpolation), independent of jaxpbr's reader:

    trs_animation    a tetrahedron under a parent with a static non-uniform TRS. Animation 0
                     "trs": translation LINEAR, rotation LINEAR (slerp: 0 -> 120 degrees, then a
                     key pair whose quaternion dot is negative), scale STEP, keys in [0.5, 2.0].
                     Animation 1 "cubic": CUBICSPLINE translation of the child and CUBICSPLINE
                     rotation of the parent.
    morph_animation  a 3 x 3 grid with 2 morph targets (target 0: POSITION and NORMAL deltas,
                     target 1: a sparse POSITION accessor without bufferView), mesh.weights
                     [0.25, 0], drawn by two nodes, the second with its own node.weights.
                     Animation 0 "weights linear" (LINEAR, the first node), animation 1
                     "weights step" (STEP, the second node).
    skinned          two strips of quads along +Y skinned by a chain of 3 joints under a transformed
                     armature node; 8 influences (JOINTS_0/WEIGHTS_0 + JOINTS_1/WEIGHTS_1), the first
                     primitive UNSIGNED_BYTE joints and FLOAT weights, the second UNSIGNED_SHORT
                     joints and normalized UNSIGNED_BYTE weights; the skinned mesh node has its own
                     TRS and a transformed parent (both ignored); the joints' rest pose is not the
                     bind pose. Animation 0 "bend": the middle joint's rotation, LINEAR.
    morph_and_skin   one strip with 2 morph targets and a skin of the same chain: morphing before
                     skinning. Animation 0 "morph and bend": the weights CUBICSPLINE, the middle
                     joint's rotation STEP.

Each builder takes a folder and returns (path, expected). `expected` is an `AnimatedScene`: the
scene as written (every number float32-exact, so that the file and the oracle hold the same values)
and its evaluation,

    expected(time=None, animation=0) -> {(node, mesh, primitive): (V, 3) float64 world positions}

`time=None` is the rest pose (no animation: the nodes' TRS, node.weights else mesh.weights);
otherwise animation `animation` (index or name) is applied at `time` seconds, every other animation
not playing. Times before an animation's first key and after its last clamp to the end keys (§3.11),
so any time >= 0 is meaningful; `expected.animations[k].times` lists those the tests compare at (on
keys, between keys, before and after), `expected.animations[k].key_times` the keys.

Regenerate and validate them with the Khronos glTF Validator:

    python tests/gltf_animated.py --out DIR
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gltf_writer import ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, FLOAT, UBYTE, USHORT, Builder, print_validation

GENERATOR = "jaxpbr animated test fixtures"


def f32(a) -> np.ndarray:
    """`a` rounded to float32 and back to float64: the value a float32 buffer (or a JSON number that
    a reader parses as float32) holds."""
    return np.asarray(a, np.float32).astype(np.float64)


# ---------------------------------------------------------------------------------------------
# The specification's closed forms (float64)
# ---------------------------------------------------------------------------------------------
def quat_axis_angle(axis, degrees) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation by `degrees` about `axis` (right-handed)."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    h = math.radians(degrees) / 2
    return np.array([*(a * math.sin(h)), math.cos(h)])


def quat_matrix(q) -> np.ndarray:
    """3 x 3 rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(q, np.float64)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def trs_matrix(t=(0, 0, 0), r=(0, 0, 0, 1), s=(1, 1, 1)) -> np.ndarray:
    """A node's local matrix T * R * S (§3.5.3: scale first, then rotation, then translation)."""
    m = np.eye(4)
    m[:3, :3] = quat_matrix(r) @ np.diag(np.asarray(s, np.float64))
    m[:3, 3] = t
    return m


def affine_inverse(m) -> np.ndarray:
    """Inverse of an affine 4 x 4 matrix, its last row exactly (0, 0, 0, 1)."""
    out = np.eye(4)
    out[:3, :3] = np.linalg.inv(m[:3, :3])
    out[:3, 3] = -out[:3, :3] @ m[:3, 3]
    return out


def slerp(q0, q1, s: float) -> np.ndarray:
    """Appendix C's spherical linear interpolation of unit quaternions, shortest path:
    a = arccos(|q0 . q1|), sign = sign(q0 . q1),
    q(s) = sin(a (1 - s)) / sin(a) q0 + sign sin(a s) / sin(a) q1
    (linear interpolation, normalised, where a is ~0)."""
    q0, q1 = np.asarray(q0, np.float64), np.asarray(q1, np.float64)
    d = float(np.dot(q0, q1))
    sign = 1.0 if d >= 0 else -1.0
    a = math.acos(min(abs(d), 1.0))
    if a < 1e-9:
        q = (1 - s) * q0 + s * sign * q1
        return q / np.linalg.norm(q)
    return (math.sin(a * (1 - s)) * q0 + sign * math.sin(a * s) * q1) / math.sin(a)


def hermite(v0, b0, v1, a1, td: float, s: float) -> np.ndarray:
    """Appendix C's cubic spline between keys k and k + 1 at s = (t - t_k) / td:
    p = (2s^3 - 3s^2 + 1) v_k + td (s^3 - 2s^2 + s) b_k + (-2s^3 + 3s^2) v_k+1 + td (s^3 - s^2) a_k+1,
    b_k the out-tangent of key k, a_k+1 the in-tangent of key k + 1."""
    s2, s3 = s * s, s * s * s
    return ((2 * s3 - 3 * s2 + 1) * np.asarray(v0, np.float64) + td * (s3 - 2 * s2 + s) * np.asarray(b0, np.float64)
            + (-2 * s3 + 3 * s2) * np.asarray(v1, np.float64) + td * (s3 - s2) * np.asarray(a1, np.float64))


def morph(base, deltas, weights) -> np.ndarray:
    """§3.7.2.2: base + sum_k w_k delta_k."""
    out = np.array(base, np.float64)
    for w, d in zip(weights, deltas):
        out = out + float(w) * np.asarray(d, np.float64)
    return out


def skin(positions, joints, weights, joint_matrices) -> np.ndarray:
    """§3.7.3: v' = sum_i w_i (jointWorld_i . inverseBind_i) v over every influence of each vertex
    (joint_matrices: (J, 4, 4) jointWorld_j . IBM_j; joints, weights: (V, 4 n))."""
    p = np.concatenate([np.asarray(positions, np.float64), np.ones((len(positions), 1))], 1)
    m = np.einsum("vi,vijk->vjk", np.asarray(weights, np.float64), np.asarray(joint_matrices)[np.asarray(joints)])
    return np.einsum("vjk,vk->vj", m, p)[:, :3]


def transform(m, positions) -> np.ndarray:
    return np.asarray(positions, np.float64) @ m[:3, :3].T + m[:3, 3]


# ---------------------------------------------------------------------------------------------
# The scene as written, and its evaluation
# ---------------------------------------------------------------------------------------------
@dataclass
class Node:
    name: str
    parent: int | None = None
    translation: tuple = (0.0, 0.0, 0.0)
    rotation: tuple = (0.0, 0.0, 0.0, 1.0)
    scale: tuple = (1.0, 1.0, 1.0)
    mesh: int | None = None
    skin: int | None = None
    weights: tuple | None = None


@dataclass
class Primitive:
    positions: np.ndarray  # (V, 3)
    triangles: np.ndarray  # (F, 3)
    normals: np.ndarray | None = None
    targets: list = field(default_factory=list)  # [{"POSITION": (V, 3), "NORMAL": (V, 3)}, ...]
    joints: np.ndarray | None = None  # (V, 4 n) joint indices (into skin.joints)
    weights: np.ndarray | None = None  # (V, 4 n) weights as a reader decodes them
    joints_type: int = UBYTE
    weights_type: int = FLOAT  # FLOAT, or UBYTE / USHORT normalized
    sparse_targets: tuple = ()  # targets whose POSITION accessor is sparse (no bufferView)


@dataclass
class Mesh:
    name: str
    primitives: list
    weights: tuple | None = None


@dataclass
class Skin:
    joints: list
    inverse_bind_matrices: np.ndarray  # (J, 4, 4)
    skeleton: int | None = None


@dataclass
class Sampler:
    input: np.ndarray  # (K,) key times
    output: np.ndarray  # (K, n); CUBICSPLINE (K, 3, n): in-tangent, value, out-tangent of each key
    interpolation: str = "LINEAR"


@dataclass
class Channel:
    node: int
    path: str  # translation, rotation, scale, weights
    sampler: Sampler


@dataclass
class Animation:
    name: str
    channels: list
    times: tuple = ()  # times the tests compare at

    @property
    def key_times(self) -> np.ndarray:
        return np.unique(np.concatenate([c.sampler.input for c in self.channels]))


def sample(channel: Channel, t: float) -> np.ndarray:
    """A channel's value at time t (§3.11, Appendix C): clamped to the first / last key outside the
    keys; STEP holds key k on [t_k, t_k+1); LINEAR is slerp for rotations and lerp otherwise;
    CUBICSPLINE is the Hermite spline (rotations normalised after)."""
    smp = channel.sampler
    x = np.asarray(smp.input, np.float64)
    cubic = smp.interpolation == "CUBICSPLINE"
    values = smp.output[:, 1] if cubic else smp.output
    if t <= x[0]:
        return np.array(values[0], np.float64)
    if t >= x[-1]:
        return np.array(values[-1], np.float64)
    k = int(np.searchsorted(x, t, side="right")) - 1  # x[k] <= t < x[k + 1]
    td = x[k + 1] - x[k]
    s = (t - x[k]) / td
    if smp.interpolation == "STEP":
        return np.array(values[k], np.float64)
    if smp.interpolation == "LINEAR":
        if channel.path == "rotation":
            return slerp(values[k], values[k + 1], s)
        return (1 - s) * values[k] + s * values[k + 1]
    assert cubic, smp.interpolation
    p = hermite(smp.output[k, 1], smp.output[k, 2], smp.output[k + 1, 1], smp.output[k + 1, 0], td, s)
    return p / np.linalg.norm(p) if channel.path == "rotation" else p


@dataclass
class AnimatedScene:
    """A scene as written (one glTF scene, `roots` its root nodes) and its expected world
    positions: call it with (time=None, animation=0)."""

    nodes: list
    meshes: list
    roots: list
    skins: list = field(default_factory=list)
    animations: list = field(default_factory=list)

    def animation(self, animation) -> Animation:
        if isinstance(animation, str):
            (a,) = [a for a in self.animations if a.name == animation]
            return a
        return self.animations[animation]

    def pose(self, time=None, animation=0):
        """Per node: (translation, rotation, scale) and morph weights (None without a mesh with
        targets): the rest pose (node.weights, else mesh.weights, else zeros) with the animation's
        channels at `time` in place of what they target."""
        trs = [[np.asarray(n.translation, np.float64), np.asarray(n.rotation, np.float64),
                np.asarray(n.scale, np.float64)] for n in self.nodes]
        weights = []
        for n in self.nodes:
            w = None
            if n.mesh is not None and self.meshes[n.mesh].primitives[0].targets:
                m = self.meshes[n.mesh]
                w = n.weights if n.weights is not None else m.weights
                w = np.zeros(len(m.primitives[0].targets)) if w is None else np.asarray(w, np.float64)
            weights.append(w)
        if time is not None:
            for c in self.animation(animation).channels:
                v = sample(c, float(time))
                if c.path == "weights":
                    weights[c.node] = v
                else:
                    trs[c.node][("translation", "rotation", "scale").index(c.path)] = v
        return trs, weights

    def world_matrices(self, time=None, animation=0) -> list:
        """Each node's world matrix: its parent's world matrix times its local T R S."""
        trs, _ = self.pose(time, animation)
        world = [None] * len(self.nodes)

        def get(i):
            if world[i] is None:
                p = self.nodes[i].parent
                world[i] = (np.eye(4) if p is None else get(p)) @ trs_matrix(*trs[i])
            return world[i]

        return [get(i) for i in range(len(self.nodes))]

    def __call__(self, time=None, animation=0) -> dict:
        """{(node, mesh, primitive): (V, 3) world positions}: morphed (§3.7.2.2), then skinned
        (§3.7.3: sum_i w_i jointWorld_i IBM_i v; the skinned node's own world matrix is not applied)
        or placed by the node's world matrix."""
        _, weights = self.pose(time, animation)
        world = self.world_matrices(time, animation)
        out = {}
        for i, n in enumerate(self.nodes):
            if n.mesh is None:
                continue
            for j, p in enumerate(self.meshes[n.mesh].primitives):
                v = p.positions
                if p.targets:
                    v = morph(v, [t["POSITION"] for t in p.targets], weights[i])
                if n.skin is not None:
                    sk = self.skins[n.skin]
                    jm = np.stack([world[k] @ ibm for k, ibm in zip(sk.joints, sk.inverse_bind_matrices)])
                    v = skin(v, p.joints, p.weights, jm)
                else:
                    v = transform(world[i], v)
                out[(i, n.mesh, j)] = v
        return out


# ---------------------------------------------------------------------------------------------
# Writing an AnimatedScene with the Builder
# ---------------------------------------------------------------------------------------------
def _floats(a) -> list:
    return [float(v) for v in np.asarray(a, np.float64).ravel()]


def _sparse_accessor(b: Builder, dense: np.ndarray) -> int:
    """A FLOAT VEC3 accessor without bufferView (zeros) and a sparse substitution of its non-zero
    rows (UNSIGNED_BYTE indices)."""
    idx = np.flatnonzero(np.any(dense != 0, axis=1))
    sparse = {"count": int(len(idx)),
              "indices": {"bufferView": b.view(idx.astype(np.uint8).tobytes()), "componentType": UBYTE},
              "values": {"bufferView": b.view(dense[idx].astype(np.float32).tobytes())}}
    return b.add("accessors", {"componentType": FLOAT, "type": "VEC3", "count": int(len(dense)), "sparse": sparse,
                               "min": _floats(dense.min(0)), "max": _floats(dense.max(0))})


def _write_primitive(b: Builder, p: Primitive) -> dict:
    attrs = {"POSITION": b.accessor(p.positions.astype(np.float32), FLOAT, "VEC3", minmax=True, target=ARRAY_BUFFER)}
    if p.normals is not None:
        attrs["NORMAL"] = b.accessor(p.normals.astype(np.float32), FLOAT, "VEC3", target=ARRAY_BUFFER)
    if p.joints is not None:
        dtype = {UBYTE: np.uint8, USHORT: np.uint16}
        for s in range(p.joints.shape[1] // 4):
            attrs[f"JOINTS_{s}"] = b.accessor(p.joints[:, 4 * s:4 * s + 4].astype(dtype[p.joints_type]),
                                              p.joints_type, "VEC4", target=ARRAY_BUFFER)
            w = p.weights[:, 4 * s:4 * s + 4]
            if p.weights_type == FLOAT:
                attrs[f"WEIGHTS_{s}"] = b.accessor(w.astype(np.float32), FLOAT, "VEC4", target=ARRAY_BUFFER)
            else:
                scale = {UBYTE: 255, USHORT: 65535}[p.weights_type]
                attrs[f"WEIGHTS_{s}"] = b.accessor(np.round(w * scale).astype(dtype[p.weights_type]), p.weights_type,
                                                   "VEC4", normalized=True, target=ARRAY_BUFFER)
    prim = {"attributes": attrs}
    t = np.asarray(p.triangles).ravel()
    prim["indices"] = b.accessor(t.astype(np.uint16), USHORT, "SCALAR", target=ELEMENT_ARRAY_BUFFER)
    targets = []
    for k, tgt in enumerate(p.targets):
        out = {}
        for name, d in tgt.items():
            d = np.asarray(d, np.float64)
            if name == "POSITION" and k in p.sparse_targets:
                out[name] = _sparse_accessor(b, d)
            else:
                out[name] = b.accessor(d.astype(np.float32), FLOAT, "VEC3", minmax=name == "POSITION",
                                       target=ARRAY_BUFFER)
        targets.append(out)
    if targets:
        prim["targets"] = targets
    return prim


def write_scene(scene: AnimatedScene, path: Path, *, mode="bin") -> Path:
    """The scene as glTF 2.0 (Builder.write's mode: 'bin', 'data' or 'glb'); node TRS written only
    where it is not the default."""
    b = Builder(GENERATOR)
    for m in scene.meshes:
        mesh = {"name": m.name, "primitives": [_write_primitive(b, p) for p in m.primitives]}
        if m.weights is not None:
            mesh["weights"] = _floats(m.weights)
        n_targets = len(m.primitives[0].targets)
        if n_targets:
            mesh["extras"] = {"targetNames": [f"target {k}" for k in range(n_targets)]}
        b.add("meshes", mesh)
    for s in scene.skins:
        ibm = np.asarray(s.inverse_bind_matrices).transpose(0, 2, 1).reshape(len(s.joints), 16)  # column-major
        skin_ = {"joints": list(s.joints), "inverseBindMatrices": b.accessor(ibm.astype(np.float32), FLOAT, "MAT4")}
        if s.skeleton is not None:
            skin_["skeleton"] = s.skeleton
        b.add("skins", skin_)
    for i, n in enumerate(scene.nodes):
        node = {"name": n.name}
        children = [k for k, c in enumerate(scene.nodes) if c.parent == i]
        if children:
            node["children"] = children
        for key, default in (("translation", (0, 0, 0)), ("rotation", (0, 0, 0, 1)), ("scale", (1, 1, 1))):
            if not np.array_equal(getattr(n, key), default):
                node[key] = _floats(getattr(n, key))
        for key in ("mesh", "skin"):
            if getattr(n, key) is not None:
                node[key] = getattr(n, key)
        if n.weights is not None:
            node["weights"] = _floats(n.weights)
        b.add("nodes", node)
    vec = {"translation": "VEC3", "rotation": "VEC4", "scale": "VEC3", "weights": "SCALAR"}
    for a in scene.animations:
        samplers, channels = [], []
        for c in a.channels:
            x = np.asarray(c.sampler.input, np.float32)
            out = np.asarray(c.sampler.output, np.float32)
            out = out.reshape(-1) if c.path == "weights" else out.reshape(-1, out.shape[-1])
            samplers.append({"input": b.accessor(x, FLOAT, "SCALAR", minmax=True),
                             "output": b.accessor(out, FLOAT, vec[c.path]),
                             "interpolation": c.sampler.interpolation})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": c.node, "path": c.path}})
        b.add("animations", {"name": a.name, "samplers": samplers, "channels": channels})
    b.add("scenes", {"nodes": list(scene.roots)})
    b.doc["scene"] = 0
    return b.write(Path(path), mode=mode)


# ---------------------------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------------------------
TETRA = np.array([[0.5, 0.0, 0.0], [-0.25, 0.0, 0.43], [-0.25, 0.0, -0.43], [0.0, 0.6, 0.0]])
TETRA_TRIANGLES = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]])  # counter-clockwise from outside


def grid(n: int = 3, half: float = 1.0):
    """(positions, triangles): an n x n vertex grid over [-half, half]^2 in the XY plane (z = 0),
    counter-clockwise seen from +Z; vertex (i, j) (row i along +Y, column j along +X) is i n + j."""
    s = np.linspace(-half, half, n)
    x, y = np.meshgrid(s, s)
    pos = np.stack([x, y, np.zeros_like(x)], -1).reshape(-1, 3)
    tri = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b_, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j
            tri += [(a, b_, c), (a, c, d)]
    return pos, np.array(tri)


STRIP_ROWS, STRIP_SPACING, STRIP_WIDTH = 7, 0.5, 0.4  # the finger: rows at y = 0, 0.5, ..., 3


def strip(x0: float = 0.0):
    """(positions, triangles): a strip of quads along +Y in the plane z = 0, x in
    [x0 - w/2, x0 + w/2], STRIP_ROWS rows of two vertices (row r: vertices 2r, 2r + 1) at
    y = r STRIP_SPACING, counter-clockwise seen from +Z."""
    pos = []
    for r in range(STRIP_ROWS):
        y = r * STRIP_SPACING
        pos += [(x0 - STRIP_WIDTH / 2, y, 0.0), (x0 + STRIP_WIDTH / 2, y, 0.0)]
    tri = []
    for r in range(STRIP_ROWS - 1):
        a, b_, c, d = 2 * r, 2 * r + 1, 2 * r + 3, 2 * r + 2
        tri += [(a, b_, c), (a, c, d)]
    return np.array(pos), np.array(tri)


# ---------------------------------------------------------------------------------------------
# (1) TRS animation: LINEAR / slerp / STEP, and CUBICSPLINE translation and rotation
# ---------------------------------------------------------------------------------------------
TRS_PARENT = dict(translation=(0.5, -1.0, 2.0), rotation=quat_axis_angle((1, 1, 0), 30), scale=(1.5, 1.0, 0.5))
#: The child's rest TRS (not any key: before the first key the first key holds, not the rest pose).
TRS_CHILD = dict(translation=(0.0, 0.75, 0.0), rotation=quat_axis_angle((0, 1, 0), 45), scale=(1.25, 1.25, 1.25))
TRS_TRANSLATION_KEYS = ((0.5, 1.0, 2.0), ((0, 1, 0), (1, 2, 0), (-1, 0.5, 1)))
#: 0 -> 120 degrees about Z (slerp and nlerp differ but at the midpoint), then 120 degrees about Z
#: -> 150 degrees about X written with w < 0: that pair's dot is negative, so the shortest path
#: interpolates towards the negated key.
TRS_ROTATION_KEYS = ((0.5, 1.25, 2.0), (quat_axis_angle((0, 0, 1), 0), quat_axis_angle((0, 0, 1), 120),
                                        -quat_axis_angle((1, 0, 0), 150)))
TRS_SCALE_KEYS = ((0.5, 1.0, 1.75), ((1, 1, 1), (2, 0.5, 1), (0.5, 0.5, 1.5)))
TRS_TIMES = (0.0, 0.25, 0.5, 0.6875, 0.75, 0.875, 1.0, 1.25, 1.4375, 1.625, 1.75, 1.875, 2.0, 3.0)
#: CUBICSPLINE keys: times, then (in-tangent, value, out-tangent) per key; the first in-tangent and
#: the last out-tangent are zero (unused). Translation of the child; uneven intervals (td matters).
CUBIC_TRANSLATION_KEYS = ((0.0, 1.0, 3.0), (((0, 0, 0), (0, 1, 0), (3, 0, 0)),
                                            ((1, 2, 0), (2, 1, 0), (-1, 1, 0)),
                                            ((0, 1, 1), (2, 3, -1), (0, 0, 0))))
_Q0, _Q1, _Q2 = quat_axis_angle((0, 0, 1), 0), quat_axis_angle((0, 0, 1), 90), quat_axis_angle((0, 1, 0), 60)
#: Rotation of the parent: values unit quaternions, tangents chosen freely (the result is normalised).
CUBIC_ROTATION_KEYS = ((0.25, 1.0, 2.0), ((np.zeros(4), _Q0, 0.6 * (_Q1 - _Q0)),
                                          (0.5 * (_Q2 - _Q0), _Q1, 0.5 * (_Q2 - _Q0)),
                                          (0.4 * (_Q2 - _Q1), _Q2, np.zeros(4))))
CUBIC_TIMES = (0.0, 0.1, 0.25, 0.5, 0.625, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0)


def _sampler(keys, interpolation="LINEAR") -> Sampler:
    times, values = keys
    return Sampler(f32(times), f32(values), interpolation)


def trs_animation(out: Path) -> tuple[Path, AnimatedScene]:
    """Nodes: 0 'parent' (static TRS), 1 'child' (the tetrahedron, mesh 0). Animation 0 'trs' on the
    child: translation LINEAR, rotation LINEAR (slerp), scale STEP; animation 1 'cubic':
    CUBICSPLINE translation of the child, CUBICSPLINE rotation of the parent. External .bin."""
    nodes = [Node("parent", **{k: tuple(f32(v)) for k, v in TRS_PARENT.items()}),
             Node("child", parent=0, mesh=0, **{k: tuple(f32(v)) for k, v in TRS_CHILD.items()})]
    meshes = [Mesh("tetra", [Primitive(f32(TETRA), TETRA_TRIANGLES)])]
    anims = [
        Animation("trs", [Channel(1, "translation", _sampler(TRS_TRANSLATION_KEYS)),
                          Channel(1, "rotation", _sampler(TRS_ROTATION_KEYS)),
                          Channel(1, "scale", _sampler(TRS_SCALE_KEYS, "STEP"))], TRS_TIMES),
        Animation("cubic", [Channel(1, "translation", _sampler(CUBIC_TRANSLATION_KEYS, "CUBICSPLINE")),
                            Channel(0, "rotation", _sampler(CUBIC_ROTATION_KEYS, "CUBICSPLINE"))], CUBIC_TIMES),
    ]
    scene = AnimatedScene(nodes, meshes, roots=[0], animations=anims)
    return write_scene(scene, Path(out) / "trs_animation.gltf", mode="bin"), scene


# ---------------------------------------------------------------------------------------------
# (2) Morph targets: mesh.weights, node.weights, a sparse target, weights LINEAR and STEP
# ---------------------------------------------------------------------------------------------
MORPH_MESH_WEIGHTS = (0.25, 0.0)
MORPH_NODE_WEIGHTS = (0.75, 0.5)  # the second node's own weights
#: Target 1 (sparse): vertex -> POSITION delta; the other vertices do not move.
MORPH_SPARSE = {1: (0.0, 0.5, 0.0), 5: (0.5, 0.0, 0.25), 6: (-0.25, -0.25, 0.5)}
MORPH_LINEAR_KEYS = ((0.5, 1.0, 2.0), ((0.0, 0.0), (1.0, 0.5), (0.25, 1.0)))  # keys x targets
MORPH_STEP_KEYS = ((0.0, 1.0, 1.5), ((1.0, 0.0), (0.0, 1.0), (0.5, 0.5)))
MORPH_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0, 3.0)


def morph_targets():
    """(positions, normals, triangles, [target 0, target 1]) of the morphing grid: target 0 a dome
    (z delta 1 - (x^2 + y^2) / 2) with NORMAL deltas, target 1 MORPH_SPARSE."""
    pos, tri = grid(3)
    nrm = np.tile([0.0, 0.0, 1.0], (len(pos), 1))
    dome = np.stack([np.zeros(len(pos)), np.zeros(len(pos)), 1 - 0.5 * (pos[:, 0] ** 2 + pos[:, 1] ** 2)], -1)
    dn = np.stack([0.5 * pos[:, 0], 0.5 * pos[:, 1], np.zeros(len(pos))], -1)
    sparse = np.zeros_like(pos)
    for k, d in MORPH_SPARSE.items():
        sparse[k] = d
    return pos, nrm, tri, [{"POSITION": f32(dome), "NORMAL": f32(dn)}, {"POSITION": f32(sparse)}]


def morph_animation(out: Path) -> tuple[Path, AnimatedScene]:
    """Nodes: 0 'mesh weights' (mesh 0, rest weights = mesh.weights), 1 'node weights' (mesh 0, its
    own node.weights). Animation 0 'weights linear' on node 0 (LINEAR), animation 1 'weights step'
    on node 1 (STEP). GLB."""
    pos, nrm, tri, targets = morph_targets()
    prim = Primitive(f32(pos), tri, normals=f32(nrm), targets=targets, sparse_targets=(1,))
    nodes = [Node("mesh weights", mesh=0, translation=(-2.5, 0.0, 0.0)),
             Node("node weights", mesh=0, translation=(2.5, 0.0, 0.0), rotation=tuple(f32(quat_axis_angle((0, 1, 0), 30))),
                  weights=MORPH_NODE_WEIGHTS)]
    anims = [Animation("weights linear", [Channel(0, "weights", _sampler(MORPH_LINEAR_KEYS))], MORPH_TIMES),
             Animation("weights step", [Channel(1, "weights", _sampler(MORPH_STEP_KEYS, "STEP"))], MORPH_TIMES)]
    scene = AnimatedScene(nodes, [Mesh("morphing grid", [prim], weights=MORPH_MESH_WEIGHTS)], roots=[0, 1],
                          animations=anims)
    return write_scene(scene, Path(out) / "morph_animation.glb", mode="glb"), scene


# ---------------------------------------------------------------------------------------------
# (3) Skins: a chain of 3 joints, 8 influences, the rest pose not the bind pose
# ---------------------------------------------------------------------------------------------
ARMATURE = dict(translation=(1.0, 0.5, -0.5), rotation=quat_axis_angle((0, 1, 0), 20), scale=(1.25, 1.25, 1.25))
JOINT_NAMES = ("joint 0", "joint 1", "joint 2")
#: The joints' local TRS when bound (the inverse bind matrices are their world matrices' inverses):
#: a straight chain up +Y, one joint per unit.
BIND_POSE = {"joint 0": dict(), "joint 1": dict(translation=(0, 1, 0)), "joint 2": dict(translation=(0, 1, 0))}
#: The joints' rest TRS, written in the nodes: not the bind pose.
REST_POSE = {"joint 0": dict(translation=(0.0, 0.0, 0.25), rotation=quat_axis_angle((0, 0, 1), 10)),
             "joint 1": dict(translation=(0, 1, 0), rotation=quat_axis_angle((0, 0, 1), 30)),
             "joint 2": dict(translation=(0, 1, 0), rotation=quat_axis_angle((1, 0, 0), -20), scale=(1.0, 1.2, 1.0))}
#: The skinned mesh node (its TRS is ignored, §3.7.3) and its parent (whose transform is ignored too).
SKINNED_NODE = dict(translation=(0.0, -5.0, 0.0), rotation=quat_axis_angle((1, 0, 0), 90), scale=(3.0, 3.0, 3.0))
SKINNED_PARENT = dict(translation=(10.0, 0.0, 0.0), rotation=quat_axis_angle((0, 1, 0), 90))
#: The middle joint's rotation (LINEAR, slerp).
BEND_KEYS = ((0.25, 1.0, 2.0), (quat_axis_angle((0, 0, 1), 60), quat_axis_angle((0, 0, 1), -30),
                                quat_axis_angle((1, 0, 0), 45)))
BEND_TIMES = (0.0, 0.25, 0.5, 0.625, 1.0, 1.5, 2.0, 2.5)
#: Per strip row r (y = r / 2 along the bound chain): the weights of joints 0, 1, 2, in 64ths
#: (FLOAT weights: dyadic, so that they sum to exactly 1 in float32) and in 255ths (normalized
#: UNSIGNED_BYTE); row 3 has three non-zero weights, the ends one.
ROW_WEIGHTS_64 = ((64, 0, 0), (48, 16, 0), (32, 32, 0), (8, 48, 8), (0, 32, 32), (0, 16, 48), (0, 0, 64))
ROW_WEIGHTS_255 = ((255, 0, 0), (191, 64, 0), (128, 127, 0), (32, 191, 32), (0, 128, 127), (0, 64, 191), (0, 0, 255))


def influences(row_weights, denominator: float, n_vertices: int):
    """(joints, weights), (V, 8) each: vertex v (row v // 2) puts joint j's weight in slot
    (v + 3 j) % 8, so that the non-zero weights fall in JOINTS_0/WEIGHTS_0 and in JOINTS_1/WEIGHTS_1
    alike; every other slot is joint 0 with weight 0 (a zero weight on a non-zero joint index is a
    validator warning, and a non-zero weight on a repeated joint an error, so 3 joints allow 3
    non-zero influences a vertex)."""
    joints = np.zeros((n_vertices, 8), np.int64)
    weights = np.zeros((n_vertices, 8))
    for v in range(n_vertices):
        for j, w in enumerate(row_weights[v // 2]):
            if w:
                joints[v, (v + 3 * j) % 8] = j
                weights[v, (v + 3 * j) % 8] = w / denominator
    return joints, weights


def _chain(scene_nodes: list, pose: dict, parent: int) -> list:
    """Append the joint chain (JOINT_NAMES, each the child of the one before) under `parent` with
    the local TRS of `pose`; returns the joints' node indices."""
    out = []
    for name in JOINT_NAMES:
        scene_nodes.append(Node(name, parent=out[-1] if out else parent,
                                **{k: tuple(f32(v)) for k, v in pose[name].items()}))
        out.append(len(scene_nodes) - 1)
    return out


def bind_world_matrices() -> np.ndarray:
    """(3, 4, 4): the joints' world matrices in the bind pose (under the armature)."""
    m = trs_matrix(*(f32(ARMATURE[k]) for k in ("translation", "rotation", "scale")))
    out = []
    for name in JOINT_NAMES:
        p = BIND_POSE[name]
        m = m @ trs_matrix(f32(p.get("translation", (0, 0, 0))), f32(p.get("rotation", (0, 0, 0, 1))),
                           f32(p.get("scale", (1, 1, 1))))
        out.append(m)
    return np.stack(out)


def _skeleton(nodes: list) -> tuple[list, Skin]:
    """Append the armature (a root) and its joint chain in the rest pose; returns (joint node
    indices, the skin: inverse bind matrices the inverses of bind_world_matrices)."""
    nodes.append(Node("armature", **{k: tuple(f32(v)) for k, v in ARMATURE.items()}))
    joints = _chain(nodes, REST_POSE, len(nodes) - 1)
    ibm = f32(np.stack([affine_inverse(m) for m in bind_world_matrices()]))
    return joints, Skin(joints, ibm, skeleton=joints[0])


def bound_strip(x0: float):
    """(positions, triangles): a strip in armature space placed where the bound chain is (world
    space): the bind pose is the mesh as written."""
    pos, tri = strip(x0)
    a = trs_matrix(*(f32(ARMATURE[k]) for k in ("translation", "rotation", "scale")))
    return f32(transform(a, pos)), tri


def skinned(out: Path) -> tuple[Path, AnimatedScene]:
    """Nodes: 0 'armature' (root, TRS), 1..3 the joints (a chain, rest pose != bind pose), 4 'mesh
    parent' (root, TRS), 5 'skinned mesh' (under 4, its own TRS, mesh 0, skin 0). Mesh 0: primitive 0
    UNSIGNED_BYTE joints / FLOAT weights, primitive 1 UNSIGNED_SHORT joints / normalized
    UNSIGNED_BYTE weights, both with JOINTS_0, WEIGHTS_0, JOINTS_1, WEIGHTS_1. Animation 0 'bend':
    joint 1's rotation, LINEAR. .gltf with a data URI."""
    nodes = []
    joints, sk = _skeleton(nodes)
    nodes.append(Node("mesh parent", **{k: tuple(f32(v)) for k, v in SKINNED_PARENT.items()}))
    nodes.append(Node("skinned mesh", parent=len(nodes) - 1, mesh=0, skin=0,
                      **{k: tuple(f32(v)) for k, v in SKINNED_NODE.items()}))
    p0, tri = bound_strip(0.0)
    p1, _ = bound_strip(0.6)
    j0, w0 = influences(ROW_WEIGHTS_64, 64.0, len(p0))
    j1, w1 = influences(ROW_WEIGHTS_255, 255.0, len(p1))
    prims = [Primitive(p0, tri, joints=j0, weights=w0, joints_type=UBYTE, weights_type=FLOAT),
             Primitive(p1, tri, joints=j1, weights=w1, joints_type=USHORT, weights_type=UBYTE)]
    anims = [Animation("bend", [Channel(joints[1], "rotation", _sampler(BEND_KEYS))], BEND_TIMES)]
    scene = AnimatedScene(nodes, [Mesh("finger", prims)], roots=[0, 4], skins=[sk], animations=anims)
    return write_scene(scene, Path(out) / "skinned.gltf", mode="data"), scene


# ---------------------------------------------------------------------------------------------
# (4) Morph targets and a skin on one mesh
# ---------------------------------------------------------------------------------------------
MS_MESH_WEIGHTS = (0.5, 0.0)
#: Weights, CUBICSPLINE: per key (in-tangents, values, out-tangents), each one weight per target.
MS_WEIGHT_KEYS = ((0.0, 1.0, 2.0), (((0, 0), (0, 0), (1, 2)),
                                    ((0.5, -1), (1, 1), (-0.5, 0.5)),
                                    ((2, 0), (0.5, 0.25), (0, 0))))
MS_BEND_KEYS = ((0.5, 1.5), (quat_axis_angle((0, 0, 1), 45), quat_axis_angle((0, 0, 1), -60)))  # STEP
MS_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0, 2.5)


def morph_and_skin(out: Path) -> tuple[Path, AnimatedScene]:
    """Nodes: 0 'armature', 1..3 the joints (as in `skinned`), 4 'morphed skinned mesh' (a root, mesh
    0, skin 0). Mesh 0: one strip, JOINTS_0 (UNSIGNED_BYTE) / WEIGHTS_0 (FLOAT; slots 0..3 of
    `influences`' layout are not enough, so here joint j's weight is in slot j), 2 morph targets in
    mesh space (target 0 widens the strip along X towards its tip, target 1 pushes it along +Z),
    mesh.weights (0.5, 0). Animation 0 'morph and bend': weights CUBICSPLINE, joint 1's rotation
    STEP. GLB."""
    nodes = []
    joints, sk = _skeleton(nodes)
    nodes.append(Node("morphed skinned mesh", mesh=0, skin=0))
    pos, tri = bound_strip(0.0)
    local, _ = strip(0.0)
    a = trs_matrix(*(f32(ARMATURE[k]) for k in ("translation", "rotation", "scale")))
    widen = np.sign(local[:, 0:1]) * np.array([[0.1, 0.0, 0.0]]) * local[:, 1:2]  # armature space
    push = np.array([[0.0, 0.0, 0.3]]) * (local[:, 1:2] / 3.0) ** 2
    targets = [{"POSITION": f32(widen @ a[:3, :3].T)}, {"POSITION": f32(push @ a[:3, :3].T)}]
    jw = np.zeros((len(pos), 4), np.int64)
    ww = np.zeros((len(pos), 4))
    for v in range(len(pos)):
        for j, w in enumerate(ROW_WEIGHTS_64[v // 2]):
            if w:
                jw[v, j], ww[v, j] = j, w / 64.0
    prim = Primitive(pos, tri, targets=targets, joints=jw, weights=ww)
    anims = [Animation("morph and bend", [Channel(4, "weights", _sampler(MS_WEIGHT_KEYS, "CUBICSPLINE")),
                                          Channel(joints[1], "rotation", _sampler(MS_BEND_KEYS, "STEP"))], MS_TIMES)]
    scene = AnimatedScene(nodes, [Mesh("morphing finger", [prim], weights=MS_MESH_WEIGHTS)], roots=[0, 4],
                          skins=[sk], animations=anims)
    return write_scene(scene, Path(out) / "morph_and_skin.glb", mode="glb"), scene


FIXTURES = {
    "trs_animation": trs_animation,
    "morph_animation": morph_animation,
    "skinned": skinned,
    "morph_and_skin": morph_and_skin,
}
#: The validator warnings each fixture has on purpose (codes): the skinned mesh node has a
#: transformed parent and its own TRS, which skinning ignores (the point of the check).
EXPECTED_WARNINGS = {"skinned": ["NODE_SKINNED_MESH_LOCAL_TRANSFORMS", "NODE_SKINNED_MESH_NON_ROOT"]}


def write_all(out: Path) -> dict[str, tuple[Path, AnimatedScene]]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return {name: f(out) for name, f in FIXTURES.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Write jaxpbr's animated glTF test fixtures and validate them.")
    ap.add_argument("--out", required=True, help="folder to write the fixtures into")
    args = ap.parse_args(argv)
    return print_validation([p for p, _ in write_all(Path(args.out)).values()])


if __name__ == "__main__":
    sys.exit(main())
