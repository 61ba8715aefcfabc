"""`jaxpbr bench grad`: the differentiable path against the forward render, side by side.

A jitted `value_and_grad` step of a sphere render (2 point lights + split-sum IBL under the
procedural sky with a 3000-radiance sun) with respect to the material (base colour, metallic,
roughness, unconstrained as in `examples/fit_material.py`), against the jitted forward render of
the same scene (as one jitted program and as `jaxpbr.render` runs it, staged on XLA:CPU), in one
process, each timed back to back (`timing.time_calls`), compilation
reported apart. The environment is baked once (`jaxpbr.bake`, timed apart too) and passed to both
programs as an argument; the step is also run with the unbaked environment closed over (the
renderer's cache then supplies the same assets) and the number of precomputes during the timed
steps is counted: it must be 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .._memory import render_bytes
from ..ibl import diffuse, specular
from ..ibl.envs import sky_with_sun_cubemap
from ..rendering.renderer import bake, render
from ..rendering.scene import Camera, Environment, Scene, Sphere
from ..shading.lights import PointLight
from ..shading.material import Material
from ._common import positive_int_arg, require_environment, require_memory
from .timing import time_calls

__all__ = ["GradBenchResult", "bench_grad"]

#: Target of issue 10: a gradient step costs at most this many forward renders.
TARGET_RATIO = 8.0
R_MIN = 0.05


def scene_for(material: Material, env: Environment, size: int) -> Scene:
    return Scene(
        camera=Camera(position=(0.0, 0.0, 3.2), width=size, height=size, fov_y_deg=45.0),
        objects=(Sphere(center=(0.0, 0.0, 0.0), radius=1.0, material=material),),
        lights=(
            PointLight(position=(3.0, 3.0, 3.0), intensity=25.0),
            PointLight(position=(-3.0, 1.0, 2.0), color=(0.6, 0.7, 1.0), intensity=12.0),
        ),
        environment=env,
    )


def unpack(theta) -> Material:
    """Unconstrained parameters (5,) -> a Material in range (roughness in [R_MIN, 1])."""
    s = jax.nn.sigmoid(theta)
    return Material(base_color=s[:3], metallic=s[3], roughness=R_MIN + (1.0 - R_MIN) * s[4])


@dataclass
class GradBenchResult:
    size: int
    face_size: int
    device: str
    bake_s: float
    forward_s: float
    forward_compile_s: float
    staged_s: float
    step_s: float
    step_compile_s: float
    closure_step_s: float
    precomputes_during_steps: int
    forward_single_s: float
    step_single_s: float

    @property
    def ratio(self) -> float:
        """Step time over the faster of the two forward renders."""
        return self.step_s / min(self.forward_s, self.staged_s)

    def report(self) -> str:
        ok = "meets" if self.ratio <= TARGET_RATIO else "misses"
        return "\n".join(
            [
                f"jaxpbr bench grad: {self.size}^2 sphere, 2 point lights + IBL (sky with sun, {self.face_size}^2 faces), "
                f"float32, JAX device {self.device}",
                f"  bake (irradiance + prefiltered chain + LUT, once, incl. compile): {self.bake_s:6.2f} s",
                f"  {'program':<44}{'ms/call':>10}{'compile s':>11}{'ms alone':>10}",
                f"  {'forward render (jit, one program)':<44}{self.forward_s * 1e3:10.3f}{self.forward_compile_s:11.2f}"
                f"{self.forward_single_s * 1e3:10.3f}",
                f"  {'forward render (jaxpbr.render, staged)':<44}{self.staged_s * 1e3:10.3f}",
                f"  {'value_and_grad wrt material (jit, baked env)':<44}{self.step_s * 1e3:10.3f}{self.step_compile_s:11.2f}"
                f"{self.step_single_s * 1e3:10.3f}",
                f"  {'same, environment closed over (cached)':<44}{self.closure_step_s * 1e3:10.3f}",
                "  ms/call: back to back (one sync per round); ms alone: one call synchronised on its own (with dispatch)",
                f"  step / faster forward = {self.ratio:.2f} ({ok} the target <= {TARGET_RATIO:g}); "
                f"precomputes during the timed steps: {self.precomputes_during_steps}",
            ]
        )


def bench_grad(size: int = 64, *, face_size: int = 64, repeats: int = 20) -> GradBenchResult:
    env = Environment(radiance=sky_with_sun_cubemap(face_size))
    _, t_bake = time_calls(lambda: bake(env), rounds=1)
    baked = bake(env)  # the cache returns the same maps: the bake above computed them
    target = render(scene_for(Material(base_color=(0.85, 0.35, 0.12), metallic=0.75, roughness=0.35), baked, size))
    theta = jnp.zeros(5, jnp.float32)

    def image(theta, e):
        return render(scene_for(unpack(theta), e, size))

    def loss(theta, e):
        return jnp.mean((jnp.log1p(image(theta, e)) - jnp.log1p(target)) ** 2)

    forward = jax.jit(image)
    step = jax.jit(jax.value_and_grad(loss))
    closure_step = jax.jit(jax.value_and_grad(lambda t: loss(t, env)))

    calls = {"n": 0}
    real = (diffuse.irradiance, specular.prefilter)

    def counting(fn):
        def wrapped(*a, **k):
            calls["n"] += 1
            return fn(*a, **k)

        return wrapped

    _, t_fwd = time_calls(lambda: forward(theta, baked), rounds=3, number=repeats, single=5)
    _, t_staged = time_calls(lambda: image(theta, baked), rounds=3, number=repeats)
    (v, g), t_step = time_calls(lambda: step(theta, baked), rounds=3, number=repeats, single=5)
    closure_step(theta)  # compile (and bake through the cache: already there)
    diffuse.irradiance, specular.prefilter = counting(real[0]), counting(real[1])
    try:
        _, t_closure = time_calls(lambda: closure_step(theta), rounds=3, number=repeats)
        for k in range(5):  # new values, new traces of the loss: still no precompute
            jax.jit(jax.value_and_grad(lambda t: loss(t, env)))(theta + 0.1 * k)
    finally:
        diffuse.irradiance, specular.prefilter = real
    if not (np.isfinite(float(v)) and np.all(np.isfinite(np.asarray(g)))):
        raise RuntimeError("the gradient step produced non-finite values; this is a bug, please report it")
    return GradBenchResult(
        size=size,
        face_size=face_size,
        device=str(jax.devices()[0].device_kind),
        bake_s=t_bake.first,
        forward_s=t_fwd.median,
        forward_compile_s=t_fwd.compile,
        staged_s=t_staged.median,
        step_s=t_step.median,
        step_compile_s=t_step.compile,
        closure_step_s=t_closure.median,
        precomputes_during_steps=calls["n"],
        forward_single_s=t_fwd.single_median,
        step_single_s=t_step.single_median,
    )


def add_command(bsub) -> None:
    """Register `jaxpbr bench grad`."""
    bg = bsub.add_parser(
        "grad",
        help="jitted value_and_grad of a 64^2 sphere render wrt the material vs the forward render",
    )
    bg.add_argument("--size", type=positive_int_arg, default=64, help="image size in pixels (default 64)")
    bg.add_argument("--face-size", type=positive_int_arg, default=64, help="environment face size (default 64)")
    bg.add_argument("--repeats", type=positive_int_arg, default=20, help="back-to-back calls per timed round")
    bg.set_defaults(func=cmd_bench_grad)


def cmd_bench_grad(args) -> int:
    require_environment(args.face_size)
    require_memory(f"rendering {args.size}x{args.size}", render_bytes(args.size, args.size)["width/height"], "lower --size")
    print(bench_grad(args.size, face_size=args.face_size, repeats=args.repeats).report())
    return 0
