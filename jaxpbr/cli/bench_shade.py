"""Benchmarks, run side by side in one process (`jaxpbr bench shade`).

`bench_shade` shades a full-HD G-buffer (every pixel a surface) with 4 point lights using the
`gltf` model twice: the jitted JAX kernel and a vectorised NumPy implementation of the same math
(float32 both), checks they agree, and reports time per frame, samples/s (pixel-light
evaluations per second), the speed-up ratio and the JIT compile time separately.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ..shading.lights import PointLight, shade_direct
from ..shading.material import Material
from ._common import positive_int_arg, require_memory
from .numpy_baselines import bench_lights, make_gbuffer, shade_numpy
from .timing import time_calls

__all__ = ["make_gbuffer", "shade_numpy", "bench_shade", "ShadeBenchResult"]

# Peak DRAM bandwidth (bytes/s) of GPUs we know, for the roofline fraction.
_PEAK_BANDWIDTH = {"H100": 3.35e12, "H200": 4.8e12, "A100": 2.0e12}


class VersusNumpy:
    """Shared by the JAX-vs-NumPy results: `width`, `height`, `jax_s`, `numpy_s` fields."""

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def ratio(self) -> float:
        return self.numpy_s / self.jax_s


@dataclass
class ShadeBenchResult(VersusNumpy):
    width: int
    height: int
    num_lights: int
    device: str
    compile_s: float
    jax_s: float
    numpy_s: float
    max_rel_diff: float
    bytes_per_pixel: int
    jax_single_s: float = float("nan")

    def report(self) -> str:
        samples = self.pixels * self.num_lights
        gbs = self.pixels * self.bytes_per_pixel / self.jax_s / 1e9
        lines = [
            f"jaxpbr bench shade: {self.width}x{self.height} G-buffer, {self.num_lights} point lights, "
            f"model gltf, float32, JAX device {self.device}",
            f"  {'implementation':<16}{'ms/frame':>12}{'Msamples/s':>14}",
            f"  {'numpy':<16}{self.numpy_s * 1e3:>12.1f}{samples / self.numpy_s / 1e6:>14.1f}",
            f"  {'jax.jit':<16}{self.jax_s * 1e3:>12.1f}{samples / self.jax_s / 1e6:>14.1f}   (back to back; "
            f"one synchronised call with dispatch: {self.jax_single_s * 1e3:.1f} ms)",
            f"  speed-up jax/numpy: {self.ratio:.1f}x   (JIT compile, once: {self.compile_s:.2f} s)",
            f"  max relative difference jax vs numpy: {self.max_rel_diff:.2e}",
            f"  effective memory traffic: {gbs:.1f} GB/s ({self.bytes_per_pixel} B in+out per pixel)",
        ]
        peak = next((bw for k, bw in _PEAK_BANDWIDTH.items() if k in self.device), None)
        if peak is not None:
            lines.append(f"  fraction of {self.device} peak bandwidth: {gbs * 1e9 / peak:.1%}")
        return "\n".join(lines)


def bench_shade(width: int = 1920, height: int = 1080, repeats: int = 5, numpy_repeats: int = 3) -> ShadeBenchResult:
    """Time the jitted `shade_direct` against `shade_numpy` on the same G-buffer, in this process."""
    if width <= 0 or height <= 0 or repeats <= 0 or numpy_repeats <= 0:
        raise ValueError("width, height and repeat counts must be positive integers.")
    g = make_gbuffer(width, height)
    lights = bench_lights()
    device = jax.devices()[0]
    jl = [PointLight(position=x["position"], color=np.ones(3, np.float32), intensity=np.float32(300.0)) for x in lights]
    gd = {k: jax.device_put(x, device) for k, x in g.items()}

    def run(gd, jl):
        m = Material(base_color=gd["base_color"], metallic=gd["metallic"], roughness=gd["roughness"],
                     occlusion=jnp.ones((), jnp.float32), emissive=jnp.zeros(3, jnp.float32))
        return shade_direct(gd["position"], gd["normal"], gd["view"], m, jl, model="gltf")

    t0 = time.perf_counter()
    compiled = jax.jit(run).lower(gd, jl).compile()
    compile_s = time.perf_counter() - t0
    # `repeats` calls back to back (one sync per round of calls), in three rounds: median per call.
    out, jt = time_calls(lambda: compiled(gd, jl), rounds=min(3, repeats), number=max(1, repeats // 3), single=3)
    ref, nt = time_calls(lambda: shade_numpy(g, lights), rounds=numpy_repeats)
    jax_s, numpy_s = jt.median, nt.median
    out = np.asarray(out)
    max_rel = float(np.max(np.abs(out - ref) / np.maximum(np.abs(ref), 1e-3)))
    # float32 in: position, normal, view, base colour (3 each), metallic, roughness; out: RGB.
    bytes_per_pixel = 4 * (3 + 3 + 3 + 3 + 1 + 1) + 4 * 3
    return ShadeBenchResult(
        width=width,
        height=height,
        num_lights=len(lights),
        device=getattr(device, "device_kind", str(device)),
        compile_s=compile_s,
        jax_s=jax_s,
        numpy_s=numpy_s,
        max_rel_diff=max_rel,
        bytes_per_pixel=bytes_per_pixel,
        jax_single_s=jt.single_median,
    )


def add_command(bsub) -> None:
    """Register `jaxpbr bench shade`."""
    bs = bsub.add_parser(
        "shade",
        help="shade a 1920x1080 G-buffer with 4 point lights: jitted JAX vs vectorised NumPy",
    )
    bs.add_argument("--width", type=positive_int_arg, default=1920)
    bs.add_argument("--height", type=positive_int_arg, default=1080)
    bs.add_argument("--repeats", type=positive_int_arg, default=10, help="timed JAX calls (back to back, median per call)")
    bs.add_argument("--numpy-repeats", type=positive_int_arg, default=3, help="timed NumPy runs (median)")
    bs.set_defaults(func=cmd_bench_shade)


#: Peak bytes per G-buffer pixel (the NumPy G-buffer and shading's float32 temporaries, the JAX
#: copies): 480x270 -> 960x540 raised the peak RSS by 197 MB, ~510 B per pixel.
BYTES_PER_PIXEL = 600.0


def cmd_bench_shade(args) -> int:
    require_memory(f"a {args.width}x{args.height} G-buffer", BYTES_PER_PIXEL * args.width * args.height, "lower --width/--height")
    result = bench_shade(args.width, args.height, repeats=args.repeats, numpy_repeats=args.numpy_repeats)
    print(result.report())
    return 0
