"""Recover a sphere's base colour, metallic and roughness from a target render by gradient descent.

The target is rendered with a known material under an HDR environment (an .hdr/.exr given on the
command line, or the procedural sky + sun) plus two point lights; the fit starts from grey,
metallic 0.5, roughness 0.5 and follows the gradient of the rendered image (through the split-sum
IBL lookups and the direct-lighting BRDF) with Adam (optax). Parameters are unconstrained and mapped
into their valid ranges (sigmoid), roughness into [0.05, 1] (docs/math.md 8.8: a learnable roughness must
not reach the singular r = 0).

The environment is baked once (`jaxpbr.bake`: irradiance, prefiltered chain, LUT) and passed to the
jitted step as an argument, so a step renders and differentiates and precomputes nothing.

    pip install 'jaxpbr[examples]'      # optax
    python examples/fit_material.py [ENV.hdr] [--steps 300]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxpbr as jp

TRUE = dict(base_color=(0.85, 0.35, 0.12), metallic=0.75, roughness=0.35)
R_MIN = 0.05


def scene_for(material: jp.Material, env: jp.Environment, size: int) -> jp.Scene:
    return jp.Scene(
        camera=jp.Camera(position=(0.0, 0.0, 3.2), width=size, height=size, fov_y_deg=45.0),
        objects=[jp.Sphere(center=(0.0, 0.0, 0.0), radius=1.0, material=material)],
        lights=[
            jp.PointLight(position=(3.0, 3.0, 3.0), intensity=25.0),
            jp.PointLight(position=(-3.0, 1.0, 2.0), color=(0.6, 0.7, 1.0), intensity=12.0),
        ],
        environment=env,
    )


def unpack(theta):
    """Unconstrained parameters (5,) -> Material with values in range."""
    s = jax.nn.sigmoid(theta)
    return jp.Material(base_color=s[:3], metallic=s[3], roughness=R_MIN + (1.0 - R_MIN) * s[4])


def pack(base_color, metallic, roughness):
    logit = lambda p: np.log(p / (1.0 - p))  # noqa: E731
    return jnp.asarray(np.r_[logit(np.asarray(base_color)), logit(metallic), logit((roughness - R_MIN) / (1 - R_MIN))], jnp.float32)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("env", nargs="?", default=None, help="equirect .hdr/.exr (default: procedural sky + sun)")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--size", type=int, default=48, help="image size in pixels")
    ap.add_argument("--lr", type=float, default=0.05)
    args = ap.parse_args(argv)

    if args.env:
        cube = jp.Cubemap.from_equirect(jp.image.read(args.env), face_size=64)
    else:
        cube = jp.envs.sky_with_sun_cubemap(64)
    t0 = time.perf_counter()
    env = jp.bake(jp.Environment(radiance=cube))
    print(f"baked the environment in {time.perf_counter() - t0:.2f} s")
    target = jp.render(scene_for(jp.Material(**TRUE), env, args.size))

    def loss_fn(theta, env):
        img = jp.render(scene_for(unpack(theta), env, args.size))
        # Compare in log space so the sun's highlight does not dominate the fit.
        return jnp.mean((jnp.log1p(img) - jnp.log1p(target)) ** 2)

    opt = optax.adam(args.lr)

    @jax.jit
    def step(theta, state, env):
        loss, g = jax.value_and_grad(loss_fn)(theta, env)
        updates, state = opt.update(g, state, theta)
        return optax.apply_updates(theta, updates), state, loss, g

    theta = pack((0.5, 0.5, 0.5), 0.5, 0.5)
    state = opt.init(theta)
    t0 = time.perf_counter()
    for k in range(1, args.steps + 1):
        theta, state, loss, g = step(theta, state, env)
        if k == 1 or k % 50 == 0 or k == args.steps:
            if not np.all(np.isfinite(np.asarray(g))):
                raise SystemExit(f"non-finite gradient at step {k}: {g}")
            print(f"step {k:4d}  loss {float(loss):.3e}")
    elapsed = time.perf_counter() - t0
    fit = unpack(theta)
    print(f"\n{args.steps} steps in {elapsed:.1f} s (first step includes compilation)")
    print(f"{'parameter':<12}{'true':>24}{'recovered':>24}")
    rec_bc = np.asarray(fit.base_color)
    print(f"{'base_color':<12}{str(np.round(TRUE['base_color'], 3)):>24}{str(np.round(rec_bc, 3)):>24}")
    print(f"{'metallic':<12}{TRUE['metallic']:>24.3f}{float(fit.metallic):>24.3f}")
    print(f"{'roughness':<12}{TRUE['roughness']:>24.3f}{float(fit.roughness):>24.3f}")
    err = max(
        np.abs(rec_bc - np.asarray(TRUE["base_color"])).max(),
        abs(float(fit.metallic) - TRUE["metallic"]),
        abs(float(fit.roughness) - TRUE["roughness"]),
    )
    print(f"largest parameter error: {err:.4f}")
    return err


if __name__ == "__main__":
    main()
