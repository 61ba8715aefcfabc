"""Recover a mesh's shape from images of it: gradient descent on vertex positions, driven by the
silhouettes and the shading.

The hidden shape is written in code: an icosphere of 2,562 vertices pushed in and out by smooth
functions of the direction (a lumpy, squashed blob, not star-shaped around any axis-aligned
ellipsoid), rendered from `--views` cameras around it (azimuths evenly spaced, elevations
alternating +35 / -25 deg) under the procedural sky (its shipped maps, sun split out as a disc
light). The fit starts from a sphere of a *different* tessellation (an icosphere of 642
vertices, radius 1) and moves its vertices to match the images with Adam (optax), all views at
once (`jaxpbr.render_batch` over the cameras inside `jax.jit(jax.value_and_grad(...))`), the scene
prepared once by `jaxpbr.deformable` (the mesh's topology, and off the CPU its BVH refitted in the
program: no host round trip per step there).

The silhouettes move because `jaxpbr.render` differentiates where the outlines are (analytic
antialiasing, docs/gltf.md): without it the image's gradient with respect to a vertex is only its
shading, and a sphere cannot grow a lump. The vertices are parametrised as in "Large Steps in
Inverse Rendering of Geometry" (Nicolet, Jacobson and Jakob, SIGGRAPH Asia 2021): u = (I + lambda L)
x with L the mesh's uniform graph Laplacian, x = (I + lambda L)^-1 u (a dense inverse: 642
vertices), and Adam moves u; a gradient step in u is a smoothed step in x, so the mesh stays a
surface instead of tangling.

Reported per `--print-every` steps: the loss, the symmetric Chamfer distance between the two
meshes' vertices (mean squared nearest distance, both ways, in scene units squared) and the
silhouette IoU over all views (the pixel centres each mesh covers), the time per step against a forward
render of the same views, and a picture: targets, start and fit for four views.

Measured on the 2-core CPU this project runs on (defaults: 12 views of 64 x 64, 150 steps):
see docs/gltf.md ("Shape from images") for the table.

    pip install 'jaxpbr[examples]'      # optax
    python examples/fit_shape.py [--views 12] [--size 64] [--steps 150] [--out DIR]
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxpbr as jp

# ------------------------------------------------------------------------------------------
# Meshes
# ------------------------------------------------------------------------------------------


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """(positions (V, 3) on the unit sphere, triangles (T, 3) counter-clockwise from outside) of an
    icosahedron split `subdivisions` times (each triangle into four, midpoints pushed onto the
    sphere; shared midpoints made once: a welded mesh)."""
    p = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [(-1, p, 0), (1, p, 0), (-1, -p, 0), (1, -p, 0), (0, -1, p), (0, 1, p), (0, -1, -p), (0, 1, -p),
             (p, 0, -1), (p, 0, 1), (-p, 0, -1), (-p, 0, 1)]
    verts = [np.asarray(v, np.float64) / np.linalg.norm(v) for v in verts]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6),
             (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7),
             (9, 8, 1)]
    for _ in range(subdivisions):
        mid: dict[tuple[int, int], int] = {}

        def midpoint(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in mid:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                mid[key] = len(verts) - 1
            return mid[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return np.asarray(verts), np.asarray(faces, np.int32)


def hidden_positions(unit: np.ndarray) -> np.ndarray:
    """The hidden shape: directions n -> r(n) n scaled by (1.05, 0.8, 0.95), with
    r = 1 + 0.22 sin(3 n_x) cos(2 n_y) + 0.15 n_z^2 - 0.12 n_y^3 (lumps, a dent, a flattened top)."""
    x, y, z = unit[:, 0], unit[:, 1], unit[:, 2]
    r = 1.0 + 0.22 * np.sin(3.0 * x) * np.cos(2.0 * y) + 0.15 * z * z - 0.12 * y ** 3
    return unit * r[:, None] * np.asarray([1.05, 0.8, 0.95])


def laplacian(n: int, triangles: np.ndarray) -> np.ndarray:
    """The uniform graph Laplacian L = D - A of the mesh's edges, dense (n, n)."""
    A = np.zeros((n, n))
    for i, j in ((0, 1), (1, 2), (2, 0)):
        A[triangles[:, i], triangles[:, j]] = 1.0
        A[triangles[:, j], triangles[:, i]] = 1.0
    return np.diag(A.sum(1)) - A


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance of two point sets: mean squared distance to the nearest point of
    the other set, both ways, summed."""
    d = np.sum((a[:, None, :] - b[None, :, :]) ** 2, -1)
    return float(d.min(1).mean() + d.min(0).mean())


# ------------------------------------------------------------------------------------------
# Views
# ------------------------------------------------------------------------------------------


def cameras(n: int, size: int) -> jp.Camera:
    """n cameras around the origin, as one Camera with batched positions (render_batch's `cameras`)."""
    pos = []
    for k in range(n):
        az = math.radians(20.0 + 360.0 * k / n)
        el = math.radians(35.0 if k % 2 == 0 else -25.0)
        pos.append((3.6 * math.cos(el) * math.sin(az), 3.6 * math.sin(el), 3.6 * math.cos(el) * math.cos(az)))
    return jp.Camera(position=np.asarray(pos, np.float32), target=(0.0, 0.0, 0.0), fov_y_deg=40.0, width=size, height=size)


MATERIAL = jp.Material(base_color=(0.75, 0.62, 0.45), metallic=0.0, roughness=0.45)


def make_scene(positions, triangles, env, size: int) -> jp.Scene:
    mesh = jp.Mesh(positions=positions, triangles=triangles, material=MATERIAL)
    cam = jp.Camera(position=(0.0, 0.0, 3.6), target=(0.0, 0.0, 0.0), fov_y_deg=40.0, width=size, height=size)
    return jp.Scene(camera=cam, objects=[mesh], environment=env, background=(0.0, 0.0, 0.0))


def masks(positions, triangles, cams: jp.Camera, size: int) -> np.ndarray:
    """(views, H, W) bool: which pixel centres of each view see the mesh (an unlit white mesh over
    black, point-sampled)."""
    white = jp.Mesh(positions=np.asarray(positions, np.float32), triangles=triangles, unlit=True,
                    material=jp.Material(base_color=(0.0, 0.0, 0.0), emissive=(1.0, 1.0, 1.0)))
    cam = jp.Camera(position=(0.0, 0.0, 3.6), target=(0.0, 0.0, 0.0), fov_y_deg=40.0, width=size, height=size)
    scene = jp.Scene(camera=cam, objects=[white], background=(0.0, 0.0, 0.0))
    return np.asarray(jp.render_batch(scene, cameras=cams, antialias=False))[..., 0] > 0.5


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.count_nonzero(a & b) / max(1, np.count_nonzero(a | b)))


def display(hdr) -> np.ndarray:
    x = np.asarray(hdr, np.float32)
    return np.clip(x / (1.0 + x), 0.0, 1.0)


def save_grid(path: Path, rows, gap: int = 2) -> None:
    H, W = rows[0][0].shape[:2]
    out = np.ones((len(rows) * (H + gap) - gap, len(rows[0]) * (W + gap) - gap, 3), np.float32)
    for r, row in enumerate(rows):
        for c, img in enumerate(row):
            out[r * (H + gap): r * (H + gap) + H, c * (W + gap): c * (W + gap) + W] = img
    jp.image.write(path, out, encoding="srgb")


# ------------------------------------------------------------------------------------------
# Main
# ------------------------------------------------------------------------------------------


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--size", type=int, default=64, help="image size in pixels (square)")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--lr", type=float, default=0.02, help="Adam step size of u = (I + lambda L) x")
    ap.add_argument("--smoothing", type=float, default=20.0, help="lambda of the large-steps parametrisation")
    ap.add_argument("--print-every", type=int, default=25)
    ap.add_argument("--interior-only", action="store_true",
                    help='the control: the same fit rendered with antialias="none" (no outline gradients)')
    ap.add_argument("--out", default="fit_shape_out", help="output folder (PNG)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    # The sky lights the mesh but is not drawn behind it (black background): the images hold the
    # mesh alone, and its silhouettes are steps against black.
    env = jp.bake(jp.Environment(radiance=jp.load_environment("procedural:sky"), show_background=False))
    print(f"environment baked in {time.perf_counter() - t0:.2f} s")
    cams = cameras(args.views, args.size)
    unit_h, tri_h = icosphere(4)
    hidden = hidden_positions(unit_h).astype(np.float32)
    start, tri = icosphere(3)
    start = start.astype(np.float32)
    print(f"hidden mesh: {len(hidden)} vertices, {len(tri_h)} triangles; fitted mesh: {len(start)} vertices, {len(tri)} triangles; "
          f"{args.views} views of {args.size}^2")
    t0 = time.perf_counter()
    targets = jp.render_batch(make_scene(hidden, tri_h, env, args.size), cameras=cams)
    targets.block_until_ready()
    print(f"targets rendered in {time.perf_counter() - t0:.2f} s")
    target_masks = masks(hidden, tri_h, cams, args.size)

    M = np.eye(len(start)) + args.smoothing * laplacian(len(start), tri)
    M_inv = jnp.asarray(np.linalg.inv(M), jnp.float32)
    u0 = jnp.asarray(M @ start, jnp.float32)

    def positions(u):
        return M_inv @ u

    # The fitted mesh changes shape, its triangles stay: its topology (and where rays are traced in
    # the program, as on a GPU, its BVH, refitted each step) is made once here, not per step.
    base = jp.deformable(make_scene(start, tri, env, args.size))

    def scene_at(u):
        return base.replace(objects=[base.objects[0].replace(positions=positions(u))])

    # The control (--interior-only) renders its steps with antialias="none": the same images without the
    # outlines' blend, and gradients without their motion.
    edges = "none" if args.interior_only else True

    def loss_fn(u):
        imgs = jp.render_batch(scene_at(u), cameras=cams, antialias=edges)
        # log1p: the sun's highlights would otherwise outweigh the rest of the images.
        return jnp.mean((jnp.log1p(imgs) - jnp.log1p(targets)) ** 2), imgs

    opt = optax.adam(args.lr)

    def step_fn(u, state):
        (loss, imgs), g = jax.value_and_grad(loss_fn, has_aux=True)(u)
        updates, state = opt.update(g, state, u)
        return optax.apply_updates(u, updates), state, loss, imgs

    step = jax.jit(step_fn)

    @jax.jit
    def forward(u):
        return jp.render_batch(scene_at(u), cameras=cams)

    u, state = u0, opt.init(u0)
    t0 = time.perf_counter()
    u, state, loss, initial = step(u, state)
    loss.block_until_ready()
    compile_s = time.perf_counter() - t0
    forward(u).block_until_ready()
    history = []

    def report(k: int, loss_value: float, x) -> None:
        x = np.asarray(x)
        cd = chamfer(x, hidden)
        m = iou(masks(x, tri, cams, args.size), target_masks)
        history.append({"step": k, "loss": loss_value, "chamfer": cd, "iou": m})
        print(f"step {k:4d}  loss {loss_value:.3e}  chamfer {cd:.4e}  silhouette IoU {m:.4f}", flush=True)

    report(0, float(loss), positions(u0))
    step_s = []
    for k in range(1, args.steps):
        t = time.perf_counter()
        u, state, loss, imgs = step(u, state)
        loss.block_until_ready()
        step_s.append(time.perf_counter() - t)
        if k % args.print_every == 0 or k == args.steps - 1:
            report(k, float(loss), positions(u))
    fwd_s = []
    for _ in range(5):
        t = time.perf_counter()
        forward(u).block_until_ready()
        fwd_s.append(time.perf_counter() - t)
    step_med, fwd_med = float(np.median(step_s)), float(np.median(fwd_s))
    print(f"compiling the step: {compile_s:.1f} s; per step {step_med * 1e3:.0f} ms (median), a forward render of the "
          f"{args.views} views {fwd_med * 1e3:.0f} ms: {step_med / fwd_med:.2f}x")
    final = forward(u)
    views = np.linspace(0, args.views, 4, endpoint=False).astype(int)
    save_grid(out / "fit_shape.png", [[display(targets[v]) for v in views], [display(initial[v]) for v in views],
                                      [display(final[v]) for v in views]])
    print(f"wrote {out / 'fit_shape.png'} (rows: targets, start, fit)")
    return {"history": history, "step_s": step_med, "forward_s": fwd_med, "compile_s": compile_s}


if __name__ == "__main__":
    main()
