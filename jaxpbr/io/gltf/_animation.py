"""Animations, skins and node transforms of a glTF 2.0 file, read and checked (§3.7.3 skins,
§3.11 animations): `GltfAnimation` (channels with their key times and values), `GltfSkin` (joints
and inverse bind matrices), `GltfNodes` (every node's parent and rest transform), and the local
matrices of the nodes at a time of an animation (`NodePose`), evaluated with `jaxpbr.geometry`."""

from __future__ import annotations

import numpy as np

from ...geometry.animation import PATHS, sample
from ...geometry.pose import deform, hierarchy_levels, place, skin_matrices, trs_matrices, world_matrices
from ._binary import fail, get, loc, pointer
from ._geometry import node_matrix
from ._types import GltfAnimation, GltfChannel, GltfNodes, GltfSkin

__all__ = ["AnimationReader", "choose_animation", "node_weights", "nodes_at", "pose_primitives", "posed_asset"]

_FIX = "repair or re-export the asset (the Khronos glTF-Validator names the problem)"
#: Output components per path (weights: the node's morph targets) and the accessor types allowed
#: (glTF 2.0 §3.11, the table of animated properties).
_OUTPUT = {
    "translation": (("VEC3",), (5126,)),
    "rotation": (("VEC4",), (5126, 5120, 5121, 5122, 5123)),
    "scale": (("VEC3",), (5126,)),
    "weights": (("SCALAR",), (5126, 5120, 5121, 5122, 5123)),
}


class AnimationReader:
    """Reads the nodes' rest transforms, the skins and the animations of a loader's file."""

    def __init__(self, loader):
        self.loader = loader
        self.gltf = loader.gltf
        self.path = loader.path
        self.buffers = loader.buffers
        self._skins: dict[int, GltfSkin] = {}

    # -- nodes ------------------------------------------------------------------------------------
    def nodes(self, parents: list[int]) -> GltfNodes:
        """Every node's parent and rest transform (T, R, S, or its matrix)."""
        nodes = self.gltf.nodes or []
        n = len(nodes)
        t = np.zeros((n, 3))
        r = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        s = np.ones((n, 3))
        matrix = np.tile(np.eye(4), (n, 1, 1))
        has_matrix = np.zeros(n, bool)
        for i, node in enumerate(nodes):
            m = get(node, "matrix")
            if m is not None:
                has_matrix[i] = True
                matrix[i] = node_matrix(m)
                continue
            for arr, key in ((t, "translation"), (r, "rotation"), (s, "scale")):
                v = get(node, key)
                if v is not None:
                    arr[i] = v
            matrix[i] = node_matrix(None, t[i], r[i], s[i])
        parents = np.asarray(parents, np.int64)
        out = GltfNodes(parents=parents, translation=t, rotation=r, scale=s, matrix=matrix, has_matrix=has_matrix,
                        levels=hierarchy_levels(parents))
        for a in (t, r, s, matrix, has_matrix, parents):
            a.flags.writeable = False
        return out

    # -- skins ------------------------------------------------------------------------------------
    def skin(self, index: int) -> GltfSkin:
        if index in self._skins:
            return self._skins[index]
        skins = self.gltf.skins or []
        at = pointer("skins", index)
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(skins):
            fail(self.path, at, f"skin {index!r:.40} does not exist (the file has {len(skins)})", _FIX)
        sk = skins[index]
        joints = np.asarray(get(sk, "joints", []), np.int64)
        if len(set(joints.tolist())) != joints.size:
            fail(self.path, loc(f"skin {index}", at + "/joints"), "lists a joint node twice", _FIX)
        ibm_index = get(sk, "inverseBindMatrices")
        if ibm_index is None:
            ibm = np.tile(np.eye(4), (joints.size, 1, 1))
        else:
            raw = self.buffers.accessor(ibm_index, f"skin {index} inverseBindMatrices", at + "/inverseBindMatrices",
                                        allowed_types=("MAT4",), allowed_components=(5126,), finite=True)
            if raw.shape[0] < joints.size:
                fail(self.path, loc(f"skin {index} inverseBindMatrices", at + "/inverseBindMatrices"),
                     f"holds {raw.shape[0]} matrices for {joints.size} joints", _FIX)
            ibm = np.asarray(raw[: joints.size], np.float64).reshape(-1, 4, 4)  # (decoded as matrices, M[row, col])
        name = get(sk, "name")
        out = GltfSkin(index=index, name=name if isinstance(name, str) else "", joints=joints, inverse_bind=ibm)
        self._skins[index] = out
        return out

    # -- animations -------------------------------------------------------------------------------
    def animations(self, target_counts) -> tuple[GltfAnimation, ...]:
        """Every animation of the file. target_counts(node) -> the number of morph targets of the
        node's mesh (0 without one): a weights channel's values are split by it."""
        out = []
        for a, anim in enumerate(self.gltf.animations or []):
            at = pointer("animations", a)
            name = get(anim, "name")
            name = name if isinstance(name, str) else ""
            where = f"animation {a}" + (f" ({name!r:.60})" if name else "")
            samplers = get(anim, "samplers", []) or []
            read: dict[int, tuple] = {}
            channels = []
            for c, ch in enumerate(get(anim, "channels", []) or []):
                cat = f"{at}/channels/{c}"
                target = get(ch, "target", {}) or {}
                node, path = get(target, "node"), get(target, "path")
                if node is None:
                    continue  # (the spec: a channel without a target node is ignored)
                if path not in PATHS:
                    self.loader.notes.append(f"{loc(where, cat)}: target path {path!r:.40} is not animated "
                                             f"(jaxpbr animates {', '.join(PATHS)})")
                    continue
                k = get(ch, "sampler")
                if not 0 <= k < len(samplers):
                    fail(self.path, loc(where, cat + "/sampler"), f"sampler {k} does not exist (the animation has "
                         f"{len(samplers)})", _FIX)
                if path != "weights" and bool(self.loader.node_has_matrix(node)):
                    fail(self.path, loc(where, cat + "/target"), f"animates the {path} of node {node}, which has a "
                         f"matrix ({pointer('nodes', node, 'matrix')}); an animated node must use TRS", _FIX)
                width = PATHS[path]
                if path == "weights":
                    width = target_counts(node)
                    if width == 0:
                        self.loader.notes.append(f"{loc(where, cat)}: animates the morph weights of node {node}, "
                                                 "whose mesh has no morph targets (ignored)")
                        continue
                key = (k, path, width)
                if key not in read:
                    read[key] = self._sampler(samplers[k], f"{where} sampler {k}", f"{at}/samplers/{k}", path, width)
                times, values, interp = read[key]
                channels.append(GltfChannel(node=int(node), path=path, interpolation=interp, times=times, values=values))
            out.append(GltfAnimation(index=a, name=name, channels=tuple(channels)))
        return tuple(out)

    def _sampler(self, smp, where, at, path, width):
        interp = get(smp, "interpolation", "LINEAR")
        times = self.buffers.accessor(get(smp, "input"), f"{where} input", at + "/input", allowed_types=("SCALAR",),
                                      allowed_components=(5126,), finite=True)
        times = np.asarray(times, np.float64)
        if times.size == 0:
            fail(self.path, loc(f"{where} input", at + "/input"), "holds no key times", _FIX)
        if times.size > 1 and not np.all(np.diff(times) > 0):
            first = int(np.argmax(~(np.diff(times) > 0)))
            fail(self.path, loc(f"{where} input", at + "/input"),
                 f"key times are not strictly increasing (keys {first} and {first + 1})", _FIX)
        types, comps = _OUTPUT[path]
        raw = self.buffers.accessor(get(smp, "output"), f"{where} output", at + "/output", allowed_types=types,
                                    allowed_components=comps, finite=True)
        if raw.dtype.kind != "f":
            fail(self.path, loc(f"{where} output", at + "/output"), "is an integer accessor without normalized: true", _FIX)
        per_key = (3 if interp == "CUBICSPLINE" else 1) * (width if path == "weights" else 1)
        K = times.size
        if raw.shape[0] != K * per_key:
            what = f"{K} keys" + (" x 3 (in-tangent, value, out-tangent)" if interp == "CUBICSPLINE" else "") + \
                (f" x {width} morph targets" if path == "weights" else "")
            fail(self.path, loc(f"{where} output", at + "/output"),
                 f"holds {raw.shape[0]} values where {what} need {K * per_key}", _FIX)
        values = np.asarray(raw, np.float64).reshape(K, 3, width) if interp == "CUBICSPLINE" else \
            np.asarray(raw, np.float64).reshape(K, width)
        for arr in (times, values):
            arr.flags.writeable = False
        return times, values, interp


def choose_animation(file, animations, animation):
    """The `GltfAnimation` named by `animation` (an index, a name, or None: the first), or an error
    listing the file's animations."""
    if not animations:
        fail(file, "/animations", "has no animations, but a time or an animation was asked for",
             "leave out time= / --time / --animation for a static asset")
    if animation is None:
        return animations[0]
    if isinstance(animation, (int, np.integer)) and not isinstance(animation, bool):
        if 0 <= int(animation) < len(animations):
            return animations[int(animation)]
    elif isinstance(animation, str):
        named = [a for a in animations if a.name == animation]
        if named:
            return named[0]
        if animation.isdigit() and int(animation) < len(animations):
            return animations[int(animation)]
    listing = ", ".join(f"{a.index}" + (f" ({a.name!r})" if a.name else "") for a in animations[:20])
    fail(file, f"animation={animation!r:.60}", f"names no animation of the file (it has {len(animations)}: {listing})",
         "pass an index or a name from that list")


def nodes_at(nodes: GltfNodes, animation: GltfAnimation | None, time, xp=np, rest=None):
    """(world matrices (N, 4, 4), local matrices (N, 4, 4), {node: morph weights}) of every node at
    `time` of `animation` (None: the rest pose). xp: numpy (float64 at load) or jax.numpy.

    rest: None, or (translation (N, 3), rotation (N, 4), scale (N, 3)) replacing the nodes' rest
    transforms (the parameters of a pose fit; nodes given by a matrix keep it); the animation's
    channels then replace what they animate."""
    if rest is None:
        t, r, s = (xp.asarray(a) for a in (nodes.translation, nodes.rotation, nodes.scale))
    else:
        t, r, s = (xp.asarray(a) for a in rest)
    weights = {}
    trs_nodes = set() if rest is None else set(np.flatnonzero(~nodes.has_matrix).tolist())
    if animation is not None:
        for ch in animation.channels:
            v = sample(xp.asarray(ch.times), xp.asarray(ch.values), ch.interpolation, time,
                       rotation=ch.path == "rotation", xp=xp)
            if ch.path == "weights":
                weights[ch.node] = v
                continue
            arr = {"translation": t, "rotation": r, "scale": s}[ch.path]
            arr = arr.at[ch.node].set(v) if xp is not np else _set_row(arr, ch.node, v)
            if ch.path == "translation":
                t = arr
            elif ch.path == "rotation":
                r = arr
            else:
                s = arr
            trs_nodes.add(ch.node)
    local = xp.asarray(nodes.matrix)
    if trs_nodes:
        idx = np.asarray(sorted(trs_nodes))
        m = trs_matrices(t[idx], r[idx], s[idx], xp)
        local = local.at[idx].set(m) if xp is not np else _set_row(local, idx, m)
    return world_matrices(local, nodes.parents, nodes.levels, xp), local, weights


def _set_row(a, i, v):
    a = np.array(a, copy=True)
    a[i] = v
    return a


def node_weights(gltf, node: int, mesh: int, count: int, animated: dict):
    """The morph weights of a node's mesh: animated at the time, else the node's `weights`, else
    the mesh's `weights`, else zeros (§3.7.2.2)."""
    if node in animated:
        return animated[node]
    for obj in ((gltf.nodes or [])[node], (gltf.meshes or [])[mesh]):
        w = get(obj, "weights")
        if w is not None:
            w = np.asarray(w, np.float64)
            if w.shape == (count,):
                return w
    return np.zeros(count)


def pose_primitives(asset, time=None, animation=None, *, xp=np, rest=None, morph_weights=None) -> dict:
    """{k: (positions (V, 3), normals (V, 3), tangents (V, 4) or None)} in world space of every
    primitive k of `asset` that can move (`GltfPrimitive.deform`), posed at `time` of `animation`
    (both None: the rest pose). With xp=jax.numpy this runs traced: gradients reach `time`, `rest`
    (see `nodes_at`), `morph_weights` ({node: (K,)}, replacing the animated or default weights) and
    key values of channels replaced in the animation."""
    playing = None
    if time is not None or animation is not None:
        playing = animation if isinstance(animation, GltfAnimation) else choose_animation(asset.path, asset.animations, animation)
    if asset.nodes is None:  # (no animations nor skins: the nodes stay where they were loaded)
        worlds, weights = None, {}
    else:
        worlds, _, weights = nodes_at(asset.nodes, playing, 0.0 if time is None else time, xp, rest)
    weights.update(morph_weights or {})
    mats: dict = {}
    out = {}
    for k, p in enumerate(asset.primitives):
        d = p.deform
        if d is None:
            continue
        w = weights.get(p.node, d.morph_weights) if d.targets else None
        if d.skin is not None:
            if d.skin not in mats:
                sk = asset.skins[d.skin]
                mats[d.skin] = skin_matrices(worlds, sk.joints, xp.asarray(sk.inverse_bind), xp)
            jm = mats[d.skin]
            m = xp.asarray(d.instance)
        elif worlds is None:
            jm = None
            m = xp.asarray(p.world_matrix)
        else:
            jm = None
            m = worlds[p.node] @ xp.asarray(d.instance) if xp is np else \
                xp.einsum("ab,bc->ac", worlds[p.node], xp.asarray(d.instance), precision="highest")
        joints = None if d.joints is None else np.where(d.weights > 0, d.joints, 0)
        pos, nrm, tan = deform(xp.asarray(d.positions), xp.asarray(d.normals), None if d.tangents is None else xp.asarray(d.tangents),
                               tris=d.tris, flat_normals=p.flat_normals, targets={n: xp.asarray(v) for n, v in d.targets.items()},
                               weights=None if w is None else xp.asarray(w), joint_mats=jm, joints=joints,
                               joint_weights=None if d.weights is None else xp.asarray(d.weights), xp=xp)
        out[k] = place(m, pos, nrm, tan, xp)
    return out


def posed_asset(asset, time=None, animation=None):
    """`asset` (a `GltfAsset`) with its moving primitives posed at `time` of `animation` in NumPy
    (float64, stored float32), without reading the file again: what `jaxpbr render --frames` draws
    frame by frame. The bounds are those of the new pose."""
    import dataclasses

    playing = None
    if time is not None or animation is not None:
        playing = choose_animation(asset.path, asset.animations, animation)
        if isinstance(time, bool) or not isinstance(time, (int, float, np.integer, np.floating)) or not np.isfinite(time):
            fail(asset.path, f"time={time!r:.40}", "is not a finite number of seconds", "pass the time in seconds, e.g. time=1.5")
    posed = pose_primitives(asset, None if playing is None else float(time), playing)
    if asset.nodes is None:
        return asset  # (nothing moves it)
    worlds = nodes_at(asset.nodes, playing, 0.0 if playing is None else float(time))[0]
    prims = list(asset.primitives)
    for k, (pos, nrm, tan) in posed.items():
        p = prims[k]
        if not np.isfinite(pos).all():
            fail(asset.path, loc(f"node {p.node}", pointer("nodes", p.node)), f"the pose at time {time} is not finite", _FIX)
        arrs = [np.asarray(a, np.float32) if a is not None else None for a in (pos, nrm, tan)]
        for a in arrs:
            if a is not None:
                a.flags.writeable = False
        prims[k] = dataclasses.replace(p, positions=arrs[0], normals=arrs[1], tangents=arrs[2] if p.tangents is not None else None,
                                       world_matrix=worlds[p.node] @ p.deform.instance)
    # cameras and lights on animated nodes move with them
    cameras = [dataclasses.replace(c, world_matrix=worlds[c.node].copy()) for c in asset.cameras]
    lights = []
    for lt in asset.lights:
        w = worlds[lt.node]
        d = w[:3, :3] @ np.array([0.0, 0.0, -1.0])
        lights.append(dataclasses.replace(lt, position=w[:3, 3].copy(), direction=d / max(float(np.linalg.norm(d)), 1e-300)))
    lo = np.min([p.positions.min(axis=0) for p in prims if p.num_vertices], axis=0) if prims else None
    hi = np.max([p.positions.max(axis=0) for p in prims if p.num_vertices], axis=0) if prims else None
    return dataclasses.replace(asset, primitives=prims, cameras=cameras, lights=lights, bounds=None if lo is None else np.stack([lo, hi]).astype(np.float64),
                               time=None if playing is None else float(time), animation=None if playing is None else playing.index)
