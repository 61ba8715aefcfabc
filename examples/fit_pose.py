"""Recover a pose from images: the joint rotations of a rigged glTF asset fitted by gradient.

A rigged tube (a glTF 2.0 file written here: 3 joints in a chain, 4 influences per vertex, a
skin with inverse bind matrices) is rendered from VIEWS cameras in a hidden pose (the joints bent
by known rotations). Starting from the rest pose, the joints' rotations (bends about x and z, 2 numbers a
joint) are fitted with optax's Adam to the images: each step poses the asset inside JAX
(`jaxpbr.posed_scene(..., rest=(t, r, s))`: the joints' rest rotations replaced by the
parameters, skinning traced), renders every view (`jaxpbr.render_batch`, outlines
differentiated: the silhouettes move the joints) and differentiates an image loss (the squared
difference of log(1 + radiance), summed over the images and their 2x, 4x and 8x box-filtered copies).

    python examples/fit_pose.py [--views 6] [--size 64] [--steps 150] [--out fit_pose_out]

Prints the loss and the joints' angle error (degrees, the angle of R_fit^T R_hidden) per step,
the time per step against a forward render of the views, and writes the targets, the start and
the fit as PNG rows.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxpbr as jp
from jaxpbr.io.gltf import read_gltf
from jaxpbr.rendering.gltf_scene import scene_from_asset

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from gltf_writer import Builder  # noqa: E402

FLOAT, UBYTE = 5126, 5121
JOINT_Y = (0.0, 1.0, 2.0)  # the joints along +Y (the tube runs from y = 0 to 3)
#: The hidden pose: each joint's rotation as axis-angle (radians), bends about x and z.
HIDDEN = np.array([[0.0, 0.0, 0.25], [0.3, 0.0, -0.15], [-0.2, 0.0, 0.35]])


def tube(rings: int = 24, sides: int = 16, radius: float = 0.22, height: float = 3.0):
    """(positions, normals, triangles, joints, weights) of a capped-free tube along +Y, each vertex
    weighted to its two nearest joints (4 influences, the other two zero)."""
    y = np.linspace(0.0, height, rings + 1)
    a = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    yy, aa = np.meshgrid(y, a, indexing="ij")
    r = radius * (1.0 - 0.25 * yy / height)
    pos = np.stack([r * np.cos(aa), yy, r * np.sin(aa)], -1).reshape(-1, 3)
    nrm = np.stack([np.cos(aa), np.zeros_like(aa), np.sin(aa)], -1).reshape(-1, 3)
    tris = []
    for i in range(rings):
        for j in range(sides):
            v0, v1 = i * sides + j, i * sides + (j + 1) % sides
            v2, v3 = v0 + sides, v1 + sides
            tris += [[v0, v2, v1], [v1, v2, v3]]
    t = np.clip(pos[:, 1], 0.0, JOINT_Y[-1] + 1e-9)
    k = np.minimum(np.floor(t).astype(int), 2)
    f = np.clip(t - k, 0.0, 1.0)
    joints = np.zeros((len(pos), 4), np.uint8)
    weights = np.zeros((len(pos), 4), np.float32)
    nxt = np.minimum(k + 1, 2)
    joints[:, 0], joints[:, 1] = k, nxt
    weights[:, 0] = np.where(nxt == k, 1.0, 1.0 - f)
    weights[:, 1] = np.where(nxt == k, 0.0, f)
    joints[:, 1] = np.where(weights[:, 1] > 0, joints[:, 1], 0)
    return pos.astype(np.float32), nrm.astype(np.float32), np.asarray(tris, np.uint16), joints, weights


def write_asset(path: Path) -> Path:
    pos, nrm, tris, joints, weights = tube()
    b = Builder("jaxpbr examples/fit_pose.py")
    mat = b.add("materials", {"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.5, 0.3, 1.0], "metallicFactor": 0.0,
                                                       "roughnessFactor": 0.8}})
    attrs = {"POSITION": b.accessor(pos, FLOAT, "VEC3", minmax=True), "NORMAL": b.accessor(nrm, FLOAT, "VEC3"),
             "JOINTS_0": b.accessor(joints, UBYTE, "VEC4"), "WEIGHTS_0": b.accessor(weights, FLOAT, "VEC4")}
    b.add("meshes", {"primitives": [{"attributes": attrs, "indices": b.accessor(tris.ravel(), 5123, "SCALAR"), "material": mat}]})
    # nodes: 0 the skinned mesh, 1-3 the joint chain (each 1 above its parent)
    b.add("nodes", {"mesh": 0, "skin": 0})
    b.add("nodes", {"name": "j0", "children": [2]})
    b.add("nodes", {"name": "j1", "translation": [0.0, 1.0, 0.0], "children": [3]})
    b.add("nodes", {"name": "j2", "translation": [0.0, 1.0, 0.0]})
    ibm = np.stack([np.eye(4) for _ in JOINT_Y]).astype(np.float32)
    for k, y in enumerate(JOINT_Y):
        ibm[k, 1, 3] = -y
    b.add("skins", {"joints": [1, 2, 3], "inverseBindMatrices": b.accessor(ibm.transpose(0, 2, 1).reshape(-1, 16), FLOAT, "MAT4")})
    b.add("scenes", {"nodes": [0, 1]})
    b.doc["scene"] = 0
    return b.write(path, mode="glb")


def quaternions(axis_angle):
    """(J, 4) unit quaternions x y z w of axis-angle rotations (J, 3) (finite gradient at 0)."""
    th2 = jnp.sum(axis_angle * axis_angle, -1, keepdims=True)
    th = jnp.sqrt(th2 + 1e-24)
    s = jnp.where(th2 > 1e-12, jnp.sin(th / 2) / th, 0.5 - th2 / 48)
    return jnp.concatenate([axis_angle * s, jnp.cos(th / 2)], -1)


def axis_angle(bends):
    """(J, 3) axis-angle rotations of (J, 2) bends about x and z: a twist about the tube's own axis
    (y) would not show in the images of a round tube, so the fit leaves it out."""
    return jnp.stack([bends[:, 0], jnp.zeros_like(bends[:, 0]), bends[:, 1]], -1)


def angle_errors(fit, hidden) -> np.ndarray:
    """Degrees between each joint's fitted and hidden rotation."""
    qa, qb = np.asarray(quaternions(jnp.asarray(fit))), np.asarray(quaternions(jnp.asarray(hidden)))
    d = np.clip(np.abs(np.sum(qa * qb, -1)), 0.0, 1.0)
    return np.degrees(2 * np.arccos(d))


def cameras(views: int, size: int):
    ang = np.linspace(0.0, 2 * np.pi, views, endpoint=False) + 0.3
    pos = np.stack([5.0 * np.sin(ang), 1.8 + 0.8 * np.cos(2 * ang), 5.0 * np.cos(ang)], -1)
    tgt = np.tile([0.0, 1.4, 0.0], (views, 1))
    return jp.Camera(position=pos.astype(np.float32), target=tgt.astype(np.float32), width=size, height=size, fov_y_deg=40.0)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--lr", type=float, default=0.01)
    ap.add_argument("--print-every", type=int, default=10)
    ap.add_argument("--out", default="fit_pose_out")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = write_asset(Path(tempfile.mkdtemp()) / "tube.glb")
    asset = read_gltf(path)
    env = jp.bake(jp.Environment(radiance=jp.load_environment("procedural:sky"), show_background=False))
    gs = scene_from_asset(asset, width=args.size, height=args.size, environment=env)
    cams = cameras(args.views, args.size)
    nodes = asset.nodes
    joint_nodes = np.asarray(asset.skins[0].joints)
    t_rest, r_rest, s_rest = (jnp.asarray(a, jnp.float32) for a in (nodes.translation, nodes.rotation, nodes.scale))

    def scene_of(bends):
        r = r_rest.at[joint_nodes].set(quaternions(axis_angle(bends)))
        return jp.posed_scene(gs, None, rest=(t_rest, r, s_rest))

    def images(axis_angle):
        return jp.render_batch(scene_of(axis_angle), cameras=cams)

    targets = jax.jit(images)(jnp.asarray(HIDDEN[:, [0, 2]], jnp.float32))
    targets.block_until_ready()

    def pyramid(x):
        """The images and their 2x, 4x and 8x box-filtered copies: where the fit and the target do not
        overlap yet, the coarse levels still see one from the other."""
        out = [x]
        for _ in range(3):
            B, H, W, C = x.shape
            x = x.reshape(B, H // 2, 2, W // 2, 2, C).mean((2, 4))
            out.append(x)
        return out

    target_levels = pyramid(jnp.log1p(targets))

    def loss_fn(p):
        imgs = images(p)
        levels = pyramid(jnp.log1p(imgs))
        return sum(jnp.mean((a - b) ** 2) for a, b in zip(levels, target_levels)), imgs

    opt = optax.adam(args.lr)

    @jax.jit
    def step(p, state):
        (loss, imgs), g = jax.value_and_grad(loss_fn, has_aux=True)(p)
        upd, state = opt.update(g, state, p)
        return optax.apply_updates(p, upd), state, loss, imgs

    forward = jax.jit(images)
    p = jnp.zeros((3, 2), jnp.float32)
    state = opt.init(p)
    t0 = time.perf_counter()
    p, state, loss, start = step(p, state)
    loss.block_until_ready()
    compile_s = time.perf_counter() - t0
    history = [(0, float(loss), angle_errors(np.zeros((3, 3)), HIDDEN))]
    print(f"start: loss {float(loss):.3e}, joint errors {np.round(history[0][2], 1)} deg (first step incl. compile {compile_s:.1f} s)")
    step_times = []
    for k in range(1, args.steps):
        t0 = time.perf_counter()
        p, state, loss, imgs = step(p, state)
        loss.block_until_ready()
        step_times.append(time.perf_counter() - t0)
        if k % args.print_every == 0 or k == args.steps - 1:
            err = angle_errors(np.asarray(axis_angle(p)), HIDDEN)
            history.append((k, float(loss), err))
            print(f"step {k:4d}: loss {float(loss):.3e}, joint errors {np.round(err, 2)} deg")
    forward(p).block_until_ready()
    fwd = []
    for _ in range(5):
        t0 = time.perf_counter()
        forward(p).block_until_ready()
        fwd.append(time.perf_counter() - t0)
    step_ms, fwd_ms = 1e3 * float(np.median(step_times)), 1e3 * float(np.median(fwd))
    print(f"time per step {step_ms:.0f} ms = {step_ms / fwd_ms:.2f}x the forward render of the {args.views} views ({fwd_ms:.0f} ms)")
    rows = [np.asarray(targets), np.asarray(start), np.asarray(forward(p))]
    grid = np.concatenate([np.concatenate(list(r), axis=1) for r in rows], axis=0)
    jp.image.write(out / "fit_pose.png", jp.color.tonemap(grid, "aces"), encoding="srgb")
    final = angle_errors(np.asarray(axis_angle(p)), HIDDEN)
    print(f"final joint errors {np.round(final, 2)} deg (start {np.round(history[0][2], 1)}); wrote {out / 'fit_pose.png'}")
    return {"history": history, "final_errors": final, "step_ms": step_ms, "forward_ms": fwd_ms}


if __name__ == "__main__":
    main()
