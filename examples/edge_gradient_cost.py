"""What the outlines cost: the forward render and the gradient step with the edge stage
(`jaxpbr.rendering.edges`, analytic antialiasing; the default) against the same programs without it
(`antialias="none"`: the interior-only image and gradient), side by side in one process.

The scene: a 160,000-triangle UV sphere (smooth normals) and an analytic sphere before it, under a
directional light, at --size (default 512 x 512; 1920 x 1080 with --size 1080p). The loss is the
mean squared image; its gradient is taken with respect to the mesh's vertex positions. Both
variants are compiled first (each traces the render once inside `jax.jit`), then timed alternately
(--runs each, medians). The forward render is called as a user calls it (on the CPU: staged
programs, the edge stage one of them; its first call's time includes compiling); the step is one
`jax.jit(jax.grad(...))` program. Memory: XLA's account of the step's temporaries
(`memory_analysis().temp_size_in_bytes`), which is what the edge stage adds to a step's peak.

    python examples/edge_gradient_cost.py [--size 512 | --size 1080p] [--runs 5]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxpbr as jp
from jaxpbr.rendering.demo import uv_sphere


def scene(W: int, H: int):
    P, N, T = uv_sphere(200, n_lon=400)
    mesh = jp.Mesh(positions=P, triangles=T, normals=N, material=jp.Material(base_color=(0.7, 0.5, 0.3), roughness=0.4))
    return jp.Scene(camera=jp.Camera(position=(0.0, 0.5, 3.5), target=(0.0, 0.0, 0.0), width=W, height=H, fov_y_deg=40.0),
                    objects=[mesh, jp.Sphere(center=(1.2, -0.4, 0.6), radius=0.4)],
                    lights=[jp.DirectionalLight(direction=(-0.3, -0.5, -1.0), intensity=2.0)], background=(0.1, 0.2, 0.3))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="512", help="N (N x N) or 1080p")
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args(argv)
    W, H = (1920, 1080) if args.size == "1080p" else (int(args.size), int(args.size))
    sc = scene(W, H)
    mesh, ball = sc.objects
    P = jnp.asarray(mesh.positions)

    def image(p, edges):
        return jp.render(sc.replace(objects=[mesh.replace(positions=p), ball]), antialias=True if edges else "none")

    def loss(p, edges):
        return jnp.mean(image(p, edges) ** 2)

    fns, memory, compile_s = {}, {}, {}
    for edges in (True, False):
        # The forward render as it is called (staged programs on the CPU); the step as one program.
        t = time.perf_counter()
        jax.block_until_ready(image(P, edges))
        compile_s["forward", edges] = time.perf_counter() - t
        memory["forward", edges] = float("nan")
        fns["forward", edges] = lambda p, edges=edges: image(p, edges)
        t = time.perf_counter()
        compiled = jax.jit(jax.grad(loss), static_argnums=1).lower(P, edges).compile()
        compile_s["step", edges] = time.perf_counter() - t
        memory["step", edges] = compiled.memory_analysis().temp_size_in_bytes
        fns["step", edges] = compiled
    times = {key: [] for key in fns}
    for key in fns:  # a first run each (the ray engine's structure, first touch of memory)
        jax.block_until_ready(fns[key](P))
    for _ in range(args.runs):
        for key, f in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(f(P))
            times[key].append(time.perf_counter() - t)
    med = {key: float(np.median(v)) for key, v in times.items()}
    print(f"{W} x {H}, {mesh.num_triangles} triangles + an analytic sphere; medians of {args.runs} alternating runs")
    print(f"{'program':8s} {'with edges':>11s} {'interior only':>14s} {'ratio':>6s} {'temp MB with / without':>24s} {'first call s with / without':>28s}")
    for kind in ("forward", "step"):
        print(f"{kind:8s} {med[kind, True]:10.3f}s {med[kind, False]:13.3f}s {med[kind, True] / med[kind, False]:6.2f} "
              f"{memory[kind, True] / 1e6:11.1f} / {memory[kind, False] / 1e6:<10.1f} "
              f"{compile_s[kind, True]:12.1f} / {compile_s[kind, False]:<10.1f}")
    return {"times": med, "memory": memory, "compile_s": compile_s}


if __name__ == "__main__":
    main()
