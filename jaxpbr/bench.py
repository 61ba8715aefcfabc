"""Benchmarks, run side by side in one process (`jaxpbr bench shade`).

`bench_shade` shades a full-HD G-buffer (every pixel a surface) with 4 point lights using the
`gltf` model twice: the jitted JAX kernel and a vectorised NumPy implementation of the same math
(float32 both), checks they agree, and reports time per frame, samples/s (pixel-light
evaluations per second), the speed-up ratio and the JIT compile time separately.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .lights import PointLight, shade_direct
from .material import Material

__all__ = ["make_gbuffer", "shade_numpy", "bench_shade", "ShadeBenchResult"]

# Peak DRAM bandwidth (bytes/s) of GPUs we know, for the roofline fraction.
_PEAK_BANDWIDTH = {"H100": 3.35e12, "H200": 4.8e12, "A100": 2.0e12}


def make_gbuffer(width: int, height: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A synthetic float32 G-buffer where every pixel is a surface: a bumpy plane z ~ 0 seen from
    (0, 0, 3), normals from a smooth height field, roughness varying along x in [0.05, 1], metallic
    along y, base colour a smooth colour ramp. Returned arrays are (H, W, ...)."""
    rng = np.random.default_rng(seed)
    aspect = width / height
    x = np.linspace(-aspect, aspect, width, dtype=np.float32)
    y = np.linspace(1.0, -1.0, height, dtype=np.float32)
    X, Y = np.meshgrid(x, y)
    fx, fy = 7.0, 5.0
    dzdx = 0.3 * fx * np.cos(fx * X) * np.cos(fy * Y)
    dzdy = -0.3 * fy * np.sin(fx * X) * np.sin(fy * Y)
    n = np.stack([-dzdx, -dzdy, np.ones_like(X)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    p = np.stack([X, Y, 0.3 * np.sin(fx * X) * np.cos(fy * Y)], -1)
    v = np.array([0.0, 0.0, 3.0], np.float32) - p
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    u = (X - X.min()) / (X.max() - X.min())
    w = (Y - Y.min()) / (Y.max() - Y.min())
    base = np.stack([0.2 + 0.7 * u, 0.3 + 0.5 * w, 0.9 - 0.6 * u * w], -1)
    base += 0.02 * rng.standard_normal(base.shape)
    return dict(
        position=p.astype(np.float32),
        normal=n.astype(np.float32),
        view=v.astype(np.float32),
        base_color=np.clip(base, 0.0, 1.0).astype(np.float32),
        metallic=w.astype(np.float32),
        roughness=(0.05 + 0.95 * u).astype(np.float32),
    )


def bench_lights() -> list[dict]:
    """The four point lights of the LearnOpenGL scene (300 cd, white)."""
    return [
        dict(position=np.array(pos, np.float32), radiant=np.full(3, 300.0, np.float32))
        for pos in [(-10.0, 10.0, 10.0), (10.0, 10.0, 10.0), (-10.0, -10.0, 10.0), (10.0, -10.0, 10.0)]
    ]


def shade_numpy(g: dict[str, np.ndarray], lights: list[dict], min_roughness: float = 0.045) -> np.ndarray:
    """Vectorised NumPy implementation of `shade_direct(model="gltf")` for point lights without a
    range: GGX D (cancellation-free form), height-correlated Smith V, glTF fresnel_mix /
    conductor_fresnel, Lambert diffuse, inverse-square falloff. Same float dtype as the inputs."""
    n, v, p = g["normal"], g["view"], g["position"]
    base, metal = g["base_color"], g["metallic"][..., None]
    r = np.clip(g["roughness"], min_roughness, 1.0)
    a = r * r
    a2 = a * a
    nv = np.sum(n * v, axis=-1)
    diffuse = base * (1.0 / math.pi)
    out = np.zeros_like(base)
    for light in lights:
        to_l = light["position"] - p
        d2 = np.sum(to_l * to_l, axis=-1)
        l = to_l / np.sqrt(d2)[..., None]
        nl = np.sum(n * l, axis=-1)
        hv = v + l
        h = hv / np.sqrt(np.sum(hv * hv, axis=-1))[..., None]
        nh = np.sum(n * h, axis=-1)
        vh = np.clip(np.sum(v * h, axis=-1), 0.0, 1.0)
        c = np.cross(n, h)
        s2 = np.sum(c * c, axis=-1)
        front = (nv > 0) & (nl > 0)
        nv_s = np.where(front, np.minimum(nv, 1.0), 1.0)
        nl_s = np.where(front, np.minimum(nl, 1.0), 1.0)
        dd = a / (s2 + (nh * a) ** 2)
        d = dd * dd * (1.0 / math.pi)
        vis = 0.5 / (nl_s * np.sqrt(nv_s * nv_s * (1.0 - a2) + a2) + nv_s * np.sqrt(nl_s * nl_s * (1.0 - a2) + a2))
        spec = (d * vis)[..., None]
        x = 1.0 - vh
        w = ((x * x) * (x * x) * x)[..., None]
        fd = 0.04 + 0.96 * w
        dielectric = diffuse * (1.0 - fd) + spec * fd
        metal_brdf = spec * (base + (1.0 - base) * w)
        f = dielectric * (1.0 - metal) + metal_brdf * metal
        e = light["radiant"] / d2[..., None]
        out += np.where(front[..., None], f * e * nl_s[..., None], 0.0)
    return out


@dataclass
class ShadeBenchResult:
    width: int
    height: int
    num_lights: int
    device: str
    compile_s: float
    jax_s: float
    numpy_s: float
    max_rel_diff: float
    bytes_per_pixel: int

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def ratio(self) -> float:
        return self.numpy_s / self.jax_s

    def report(self) -> str:
        samples = self.pixels * self.num_lights
        gbs = self.pixels * self.bytes_per_pixel / self.jax_s / 1e9
        lines = [
            f"jaxpbr bench shade: {self.width}x{self.height} G-buffer, {self.num_lights} point lights, "
            f"model gltf, float32, JAX device {self.device}",
            f"  {'implementation':<16}{'ms/frame':>12}{'Msamples/s':>14}",
            f"  {'numpy':<16}{self.numpy_s * 1e3:>12.1f}{samples / self.numpy_s / 1e6:>14.1f}",
            f"  {'jax.jit':<16}{self.jax_s * 1e3:>12.1f}{samples / self.jax_s / 1e6:>14.1f}",
            f"  speed-up jax/numpy: {self.ratio:.1f}x   (JIT compile, once: {self.compile_s:.2f} s)",
            f"  max relative difference jax vs numpy: {self.max_rel_diff:.2e}",
            f"  effective memory traffic: {gbs:.1f} GB/s ({self.bytes_per_pixel} B in+out per pixel)",
        ]
        peak = next((bw for k, bw in _PEAK_BANDWIDTH.items() if k in self.device), None)
        if peak is not None:
            lines.append(f"  fraction of {self.device} peak bandwidth: {gbs * 1e9 / peak:.1%}")
        return "\n".join(lines)


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


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
    out = compiled(gd, jl).block_until_ready()
    jax_s = _median_time(lambda: compiled(gd, jl).block_until_ready(), repeats)

    ref = shade_numpy(g, lights)
    numpy_s = _median_time(lambda: shade_numpy(g, lights), numpy_repeats)
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
    )
