"""`jaxpbr bench render`: full shading (4 point lights + split-sum IBL), jitted JAX vs NumPy.

`bench_render_gbuffer` shades a G-buffer of a sphere grid in front of a backdrop wall (every pixel
a surface) with `shade_direct(..., model="gltf") + shade_ibl(..., model="gltf")` twice, in one
process: `jp.render` of the G-buffer scene (the library's staged jitted programs) and
`shade_render_numpy`, a vectorised float32 NumPy implementation
of the same math (`jaxpbr.cli.numpy_baselines`: direct lights `shade_numpy`; IBL: a NumPy port of the seam-padded
cube pyramid lookup of `Cubemap.sample`, the LUT lookup of `lut_lookup` and the split sum of
`shade_ibl`). The IBL precompute (environment, irradiance, prefiltered mips, BRDF LUT) is timed
separately; JIT compile time is reported apart from the median run time.

`--extensions` (`jaxpbr.cli.bench_extensions`) renders the demo's sphere grid with each glTF material
extension group against the core material.

`--gltf` (`jaxpbr.cli.bench_gltf`) renders the same sphere grid as a glTF asset of triangle meshes
against the analytic spheres, with the asset's cold start and memory as whole processes.

`bench_batch` measures material-batch throughput: N materials on one ray-cast sphere under IBL +
lights as one `jp.render_batch` call (a jitted `vmap` over materials, chunked by
`jax.lax.map(..., batch_size=)` to bound memory), against a Python loop of `jp.render` calls.

NumPy conventions: the G-buffer is a dict of float32 (H, W, ...) arrays (keys as
`jaxpbr.cli.numpy_baselines.make_gbuffer`); normals and view vectors must be unit length (JAX renormalises them,
a difference of an ulp); no emissive, occlusion 1 unless the dict has an `occlusion` plane.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .._memory import render_bytes
from .._validate import positive_int
from ..ibl import envs
from ..ibl.cubemap import Cubemap
from ..ibl.diffuse import irradiance
from ..ibl.shade import shade_ibl
from ..ibl.specular import prefilter
from ..rendering.renderer import render, render_batch
from ..rendering.scene import Camera, Environment, GBuffer, Scene, Sphere
from ..shading.lights import PointLight, shade_direct
from ..shading.material import Material
from ..shading.shipped_luts import brdf_lut
from ._common import (
    nonnegative_int_arg,
    positive_int_arg,
    require_environment,
    require_memory,
)
from .bench_shade import _PEAK_BANDWIDTH, VersusNumpy
from .numpy_baselines import (
    GBUFFER_KEYS,
    NumpyIBL,
    bench_lights,
    make_sphere_gbuffer,
    shade_render_numpy,
)
from .timing import time_calls

__all__ = [
    "BatchBenchResult",
    "RenderBenchResult",
    "add_command",
    "bench_batch",
    "bench_render_gbuffer",
    "jax_point_lights",
    "make_ibl",
    "shade_render_jax",
]



# ------------------------------------------------------------------------------------------
# JAX side
# ------------------------------------------------------------------------------------------


def _material(base, metallic, roughness, dtype=jnp.float32) -> Material:
    return Material(
        base_color=base,
        metallic=metallic,
        roughness=roughness,
        occlusion=jnp.ones((), dtype),
        emissive=jnp.zeros(3, dtype),
    )


def shade_render_jax(g, lights, irr: Cubemap, pre: Cubemap, lut) -> jax.Array:
    """`shade_direct(model="gltf") + shade_ibl(model="gltf")` on a G-buffer dict (jit it)."""
    m = _material(g["base_color"], g["metallic"], g["roughness"])
    direct = shade_direct(g["position"], g["normal"], g["view"], m, lights, model="gltf")
    return direct + shade_ibl(g["normal"], g["view"], m, irr, pre, lut, model="gltf")


def jax_point_lights(lights: list[dict]) -> list[PointLight]:
    """`bench_lights()`-style dicts -> PointLights (float32; radiant = color * intensity)."""
    return [
        PointLight(position=jnp.asarray(x["position"], jnp.float32), color=jnp.ones(3, jnp.float32),
                   intensity=jnp.asarray(np.max(x["radiant"]), jnp.float32))
        for x in lights
    ]


@dataclass
class IBLTables:
    """The IBL environment and its precomputed tables, with the time each step took (seconds,
    first call: JIT compilation included)."""

    env: Cubemap
    irr: Cubemap
    pre: Cubemap
    lut: jax.Array
    times: dict


def make_ibl(face_size: int = 128, *, irradiance_size: int = 32, lut_size: int = 128) -> IBLTables:
    """`sky_with_sun_cubemap(face_size)` + `irradiance` + `prefilter` + `brdf_lut`, each timed."""
    def timed(fn):  # one call each: the first call is the cost a user pays (compile included)
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        return out, time.perf_counter() - t0

    times = {}
    env, times["environment"] = timed(lambda: envs.sky_with_sun_cubemap(face_size))
    irr, times["irradiance"] = timed(lambda: irradiance(env, size=min(irradiance_size, face_size)))
    pre, times["prefilter"] = timed(lambda: prefilter(env))
    lut, times["brdf_lut"] = timed(lambda: brdf_lut(size=lut_size))
    return IBLTables(env, irr, pre, jnp.asarray(lut, jnp.float32), times)


# ------------------------------------------------------------------------------------------
# Benchmarks
# ------------------------------------------------------------------------------------------


def _device_kind() -> str:
    d = jax.devices()[0]
    return getattr(d, "device_kind", str(d))


def _max_rel(a: np.ndarray, ref: np.ndarray, floor: float = 1e-3) -> float:
    return float(np.max(np.abs(np.asarray(a) - ref) / np.maximum(np.abs(ref), floor)))


@dataclass
class RenderBenchResult(VersusNumpy):
    width: int
    height: int
    num_lights: int
    face_size: int
    prefilter_levels: int
    device: str
    precompute_s: dict
    compile_s: float
    jax_s: float
    numpy_s: float
    numpy_ibl_setup_s: float
    max_rel_diff: float
    p999_rel_diff: float
    bytes_per_pixel: int

    def report(self) -> str:
        pre = ", ".join(f"{k} {v:.2f} s" for k, v in self.precompute_s.items())
        gbs = self.pixels * self.bytes_per_pixel / self.jax_s / 1e9
        lines = [
            (
                f"jaxpbr bench render: {self.width}x{self.height} sphere-grid G-buffer, {self.num_lights} point lights "
                f"+ split-sum IBL (sky with sun {self.face_size}^2, {self.prefilter_levels} prefiltered mips), "
                f"model gltf, float32, JAX device {self.device}"
            ),
            f"  IBL precompute (first calls, JIT included): {pre}; NumPy table setup {self.numpy_ibl_setup_s * 1e3:.1f} ms",
            f"  {'implementation':<16}{'ms/frame':>12}{'frames/s':>12}{'Mpixels/s':>12}",
            f"  {'numpy':<16}{self.numpy_s * 1e3:>12.1f}{1.0 / self.numpy_s:>12.2f}{self.pixels / self.numpy_s / 1e6:>12.1f}",
            f"  {'jax.jit':<16}{self.jax_s * 1e3:>12.1f}{1.0 / self.jax_s:>12.2f}{self.pixels / self.jax_s / 1e6:>12.1f}",
            f"  speed-up jax/numpy: {self.ratio:.1f}x   (JIT compile, once: {self.compile_s:.2f} s)",
            f"  relative difference jax vs numpy: max {self.max_rel_diff:.2e}, 99.9th percentile {self.p999_rel_diff:.2e}",
        ]
        peak = next((bw for k, bw in _PEAK_BANDWIDTH.items() if k in self.device), None)
        if peak is not None:
            lines.append(
                f"  G-buffer traffic {gbs:.1f} GB/s ({self.bytes_per_pixel} B/pixel, texture gathers not counted): "
                f"{gbs * 1e9 / peak:.1%} of {self.device} peak"
            )
        return "\n".join(lines)


def bench_render_gbuffer(
    width: int = 1920,
    height: int = 1080,
    *,
    repeats: int = 5,
    numpy_repeats: int = 3,
    face_size: int = 128,
    ibl: IBLTables | None = None,
) -> RenderBenchResult:
    """Time jitted `shade_direct + shade_ibl` against `shade_render_numpy` on the same sphere-grid
    G-buffer, in this process (see the module docstring)."""
    for name, x in (("width", width), ("height", height), ("repeats", repeats), ("numpy_repeats", numpy_repeats), ("face_size", face_size)):
        positive_int(name, x)
    if ibl is None:
        ibl = make_ibl(face_size)
    g = make_sphere_gbuffer(width, height)
    gs = {k: g[k] for k in GBUFFER_KEYS}
    lights = bench_lights()
    device = jax.devices()[0]
    gd = {k: jax.device_put(x, device) for k, x in gs.items()}
    jl = jax_point_lights(lights)

    # The library's own path: jp.render of a G-buffer scene (staged programs: direct lighting,
    # then IBL; see stages._render_pass). The LUT is the shipped one render loads. Single
    # scattering, the model the NumPy port computes (render's default compensates it).
    scene = Scene(
        gbuffer=GBuffer(
            hit=jnp.ones(gd["position"].shape[:2], bool),
            position=gd["position"],
            normal=gd["normal"],
            view=gd["view"],
            material=_material(gd["base_color"], gd["metallic"], gd["roughness"]),
        ),
        lights=jl,
        environment=Environment(radiance=ibl.env, irradiance=ibl.irr, prefiltered=ibl.pre),
    )
    out, jt = time_calls(lambda: render(scene, multiscatter=False), rounds=min(3, repeats), number=max(1, repeats // 3))
    compile_s, jax_s = jt.first, jt.median

    t0 = time.perf_counter()
    nibl = NumpyIBL.from_tables(ibl.irr, ibl.pre, ibl.lut)
    setup_s = time.perf_counter() - t0
    ref, nt = time_calls(lambda: shade_render_numpy(gs, lights, nibl), rounds=numpy_repeats)
    numpy_s = nt.median

    out = np.asarray(out)
    rel = np.abs(out - ref) / np.maximum(np.abs(ref), 1e-3)
    return RenderBenchResult(
        width=width,
        height=height,
        num_lights=len(lights),
        face_size=face_size,
        prefilter_levels=ibl.pre.num_levels,
        device=_device_kind(),
        precompute_s=dict(ibl.times),
        compile_s=compile_s,
        jax_s=jax_s,
        numpy_s=numpy_s,
        numpy_ibl_setup_s=setup_s,
        max_rel_diff=float(rel.max()),
        p999_rel_diff=float(np.quantile(rel, 0.999)),
        # float32 in: position, normal, view, base colour (3 each), metallic, roughness; out: RGB.
        bytes_per_pixel=4 * (3 + 3 + 3 + 3 + 1 + 1) + 4 * 3,
    )


@dataclass
class BatchBenchResult:
    num_materials: int
    size: int
    chunk: int
    num_lights: int
    device: str
    compile_s: float
    loop_compile_s: float
    batch_s: float
    loop_s: float
    max_rel_diff: float

    @property
    def ratio(self) -> float:
        return self.loop_s / self.batch_s

    def report(self) -> str:
        n = self.num_materials
        return "\n".join(
            [
                (
                    f"jaxpbr bench render --batch: {n} materials x {self.size}x{self.size} ray-cast sphere scene, "
                    f"{self.num_lights} point lights + IBL, float32, JAX device {self.device}"
                ),
                f"  {'implementation':<36}{'s/batch':>10}{'images/s':>12}{'Mpixels/s':>12}",
                (
                    f"  {'python loop of jp.render':<36}{self.loop_s:>10.3f}{n / self.loop_s:>12.1f}"
                    f"{n * self.size**2 / self.loop_s / 1e6:>12.1f}"
                ),
                (
                    f"  {f'jp.render_batch(chunk={self.chunk})':<36}{self.batch_s:>10.3f}"
                    f"{n / self.batch_s:>12.1f}{n * self.size**2 / self.batch_s / 1e6:>12.1f}"
                ),
                (
                    f"  speed-up batched/loop: {self.ratio:.2f}x   (JIT compile, once: batched {self.compile_s:.2f} s, "
                    f"single {self.loop_compile_s:.2f} s)"
                ),
                f"  max relative difference batched vs loop: {self.max_rel_diff:.2e}",
            ]
        )


def _batch_materials(num: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "base_color": rng.uniform(0.05, 0.95, (num, 3)).astype(np.float32),
        "metallic": rng.uniform(0.0, 1.0, num).astype(np.float32),
        "roughness": rng.uniform(0.0, 1.0, num).astype(np.float32),
    }


def bench_batch(
    num_materials: int = 256,
    size: int = 256,
    chunk: int = 16,
    *,
    repeats: int = 3,
    face_size: int = 128,
    ibl: IBLTables | None = None,
) -> BatchBenchResult:
    """Material-batch throughput: `num_materials` materials on one ray-cast `size`^2 sphere scene,
    4 point lights + IBL. Batched: `jp.render_batch(scene, materials=..., chunk=chunk)` (one jitted
    `lax.map` with a vmap inside each chunk). Baseline: a Python loop of `jp.render` with one
    material each (all dispatched, then waited for). Median of `repeats` timed runs each; the first
    calls (compile) are reported apart."""
    for name, x in (("num_materials", num_materials), ("size", size), ("chunk", chunk), ("repeats", repeats)):
        positive_int(name, x)
    if ibl is None:
        ibl = make_ibl(face_size)
    # The library's path: one Scene (a sphere ray-cast at size^2, 4 point lights, the IBL maps
    # passed in), `render_batch` over a Material with a leading batch axis vs a Python loop of
    # `render` calls with one material each.
    jl = jax_point_lights(bench_lights())
    mats = _batch_materials(num_materials)
    batch_mat = Material(
        base_color=jnp.asarray(mats["base_color"], jnp.float32),
        metallic=jnp.asarray(mats["metallic"], jnp.float32),
        roughness=jnp.asarray(mats["roughness"], jnp.float32),
        occlusion=jnp.ones(num_materials, jnp.float32),
        emissive=jnp.zeros((num_materials, 3), jnp.float32),
    )
    scene = Scene(
        camera=Camera(position=(0.0, 0.0, 3.0), width=size, height=size, fov_y_deg=45.0),
        objects=[Sphere()],
        lights=jl,
        environment=Environment(radiance=ibl.env, irradiance=ibl.irr, prefiltered=ibl.pre),
    )
    c = min(chunk, num_materials)

    out_b, bt = time_calls(lambda: render_batch(scene, materials=batch_mat, chunk=c), rounds=repeats)
    compile_s, batch_s = bt.first, bt.median

    singles = [
        scene.replace(objects=[Sphere(material=jax.tree_util.tree_map(lambda x, i=i: x[i], batch_mat))])
        for i in range(num_materials)
    ]
    t0 = time.perf_counter()
    render(singles[0]).block_until_ready()
    loop_compile_s = time.perf_counter() - t0
    out_l, lt = time_calls(lambda: [render(sc) for sc in singles], rounds=repeats)
    loop_s = lt.median
    ref = np.stack([np.asarray(x) for x in out_l])
    return BatchBenchResult(
        num_materials=num_materials,
        size=size,
        chunk=min(chunk, num_materials),
        num_lights=len(jl),
        device=_device_kind(),
        compile_s=compile_s,
        loop_compile_s=loop_compile_s,
        batch_s=batch_s,
        loop_s=loop_s,
        max_rel_diff=_max_rel(out_b, ref),
    )


# ------------------------------------------------------------------------------------------
# CLI
# ------------------------------------------------------------------------------------------




#: Peak bytes per G-buffer pixel (NumPy G-buffer and shading temporaries, the JAX copies):
#: 480x270 -> 960x540 raised the peak RSS by 170 MB, ~440 B per pixel.
BYTES_PER_PIXEL = 600.0


def _cmd_bench_render(args) -> int:
    if args.gltf:
        return _cmd_bench_gltf(args)
    if args.extensions:
        from .bench_extensions import bench_extensions

        require_memory(f"a {args.width}x{args.height} render", BYTES_PER_PIXEL * args.width * args.height, "lower --width/--height")
        print(bench_extensions(args.width, args.height, repeats=args.repeats or 3).report(), flush=True)
        return 0
    repeats = args.repeats or 10
    require_environment(args.face_size)
    require_memory(f"a {args.width}x{args.height} G-buffer", BYTES_PER_PIXEL * args.width * args.height, "lower --width/--height")
    if args.batch:
        require_memory(f"a batch of {args.chunk} {args.batch_size}x{args.batch_size} renders",
                       render_bytes(args.batch_size, args.batch_size)["width/height"] * min(args.chunk, args.batch), "lower --batch-size/--chunk")
    ibl = make_ibl(args.face_size)
    result = bench_render_gbuffer(
        args.width, args.height, repeats=repeats, numpy_repeats=args.numpy_repeats, face_size=args.face_size, ibl=ibl
    )
    print(result.report(), flush=True)
    if args.batch:
        res = bench_batch(args.batch, args.batch_size, args.chunk, repeats=repeats, face_size=args.face_size, ibl=ibl)
        print(res.report(), flush=True)
    return 0


def _cmd_bench_gltf(args) -> int:
    import sys

    from ..rendering.demo import demo_grid_lat
    from .bench_gltf import bench_gltf, estimate_bytes, grid_counts

    tri, vert = grid_counts(demo_grid_lat(args.triangles))
    # This process holds the mesh scene and renders it (the memory asked for by --memory-triangles
    # is the child processes' own, refused there by `jaxpbr render`'s guard if it does not fit).
    require_memory(f"a {tri:,}-triangle asset rendered at {args.width}x{args.height}",
                   estimate_bytes(tri, vert, args.width, args.height), "lower --triangles")
    result = bench_gltf(
        args.triangles, args.width, args.height, repeats=args.repeats or 3, cold_runs=args.cold_runs,
        process_size=(args.process_width, args.process_height), memory_triangles=tuple(args.memory_triangles),
        log=lambda text: print(f"bench render --gltf: {text}", file=sys.stderr, flush=True),
    )
    print(result.report(), flush=True)
    return 0


def _int_list_arg(text: str) -> list[int]:
    """argparse type: comma-separated positive integers (an empty string: none)."""
    out = [positive_int_arg(x.strip().replace("_", "")) for x in text.split(",") if x.strip()]
    return out


def add_command(bench_subparsers) -> argparse.ArgumentParser:
    """Register `jaxpbr bench render` on the `bench` sub-parsers; returns the new parser."""
    p = bench_subparsers.add_parser(
        "render",
        help="shade a 1920x1080 sphere-grid G-buffer with 4 point lights + split-sum IBL: jitted JAX vs "
        "vectorised NumPy; and a material-batch throughput run",
        description="Direct (4 point lights) + split-sum IBL shading of a sphere-grid G-buffer, jitted "
        "JAX vs vectorised NumPy in one process (IBL precompute and JIT compile timed apart); then N "
        "materials on a sphere as one jitted vmap (chunked by lax.map) vs a Python loop of jitted calls.",
    )
    p.add_argument("--width", type=positive_int_arg, default=1920)
    p.add_argument("--height", type=positive_int_arg, default=1080)
    p.add_argument("--repeats", type=positive_int_arg, default=None, help="timed JAX runs (median; default 10, with --gltf 3)")
    p.add_argument("--numpy-repeats", type=positive_int_arg, default=3, help="timed NumPy runs (median)")
    p.add_argument("--face-size", type=positive_int_arg, default=128, help="environment cube face size")
    p.add_argument("--batch", type=nonnegative_int_arg, default=256, metavar="N",
                   help="materials in the batch-throughput run (0: skip it)")
    p.add_argument("--batch-size", type=positive_int_arg, default=256, metavar="S", help="batch image size S x S")
    p.add_argument("--chunk", type=positive_int_arg, default=16, help="materials per vmapped chunk (lax.map batch_size)")
    g = p.add_argument_group(
        "glTF asset (--gltf)",
        "The demo grid written as a .glb of UV-sphere meshes (in a temporary folder) against the analytic spheres at "
        "--width x --height, 4 point lights + IBL: load, acceleration structure, visibility of the primary rays, warm "
        "frame times and their ratios with and without shadows; then whole processes: cold and warm start of "
        "`jaxpbr render ASSET.glb --environment procedural:sky` against the demo's `jaxpbr render`, peak memory. "
        "Replaces the G-buffer and batch runs.",
    )
    p.add_argument("--extensions", action="store_true",
                   help="instead: the demo's sphere grid at --width x --height with each glTF material extension group on "
                   "every sphere against the core material, warm frames interleaved (jaxpbr.cli.bench_extensions)")
    g.add_argument("--gltf", action="store_true", help="run the glTF asset benchmark instead")
    g.add_argument("--triangles", type=positive_int_arg, default=1_000_000, metavar="N", help="triangles of the asset, about (default: %(default)s)")
    g.add_argument("--cold-runs", type=nonnegative_int_arg, default=3, metavar="K",
                   help="cold + warm whole-process runs of the asset and the demo each (0: skip; default: %(default)s)")
    g.add_argument("--process-width", type=positive_int_arg, default=1280, help="image width of the whole-process runs (default: jaxpbr render's %(default)s)")
    g.add_argument("--process-height", type=positive_int_arg, default=720, help="image height of the whole-process runs (default: %(default)s)")
    g.add_argument("--memory-triangles", type=_int_list_arg, default=[], metavar="N[,N...]",
                   help="also render assets of these triangle counts in processes of their own and report their peak "
                   "memory, or the memory guard's refusal (e.g. 10000000)")
    p.set_defaults(func=_cmd_bench_render)
    return p
