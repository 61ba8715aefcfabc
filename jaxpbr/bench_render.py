"""`jaxpbr bench render`: full shading (4 point lights + split-sum IBL), jitted JAX vs NumPy.

`bench_render_gbuffer` shades a G-buffer of a sphere grid in front of a backdrop wall (every pixel
a surface) with `shade_direct(..., model="gltf") + shade_ibl(..., model="gltf")` twice, in one
process: `jp.render` of the G-buffer scene (the library's staged jitted programs) and
`shade_render_numpy`, a vectorised float32 NumPy implementation
of the same math (direct lights: `jaxpbr.bench.shade_numpy`; IBL: a NumPy port of the seam-padded
cube pyramid lookup of `Cubemap.sample`, the LUT lookup of `lut_lookup` and the split sum of
`shade_ibl`). The IBL precompute (environment, irradiance, prefiltered mips, BRDF LUT) is timed
separately; JIT compile time is reported apart from the median run time.

`bench_batch` measures material-batch throughput: N materials on one ray-cast sphere under IBL +
lights as one `jp.render_batch` call (a jitted `vmap` over materials, chunked by
`jax.lax.map(..., batch_size=)` to bound memory), against a Python loop of `jp.render` calls.

NumPy conventions: the G-buffer is a dict of float32 (H, W, ...) arrays (keys as
`jaxpbr.bench.make_gbuffer`); normals and view vectors must be unit length (JAX renormalises them,
a difference of an ulp); no emissive, occlusion 1 unless the dict has an `occlusion` plane.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .bench import _PEAK_BANDWIDTH, bench_lights, shade_numpy
from .cubemap import Cubemap, _corner_mask, _pad_index
from .ibl import MIN_N_DOT_V, shade_ibl
from .lights import PointLight, shade_direct
from .material import F0_DIELECTRIC, Material

__all__ = [
    "BatchBenchResult",
    "NumpyCube",
    "NumpyIBL",
    "RenderBenchResult",
    "add_bench_render_command",
    "bench_batch",
    "bench_render_gbuffer",
    "jax_point_lights",
    "lut_lookup_numpy",
    "make_ibl",
    "make_sphere_gbuffer",
    "shade_ibl_numpy",
    "shade_render_jax",
    "shade_render_numpy",
]

_F32 = np.float32
GBUFFER_KEYS = ("position", "normal", "view", "base_color", "metallic", "roughness")


# ------------------------------------------------------------------------------------------
# NumPy IBL
# ------------------------------------------------------------------------------------------


def _pad_level_np(level: np.ndarray) -> np.ndarray:
    """NumPy port of `cubemap._pad_level`: (6, S, S, C) -> (6, S+2, S+2, C) seam pad."""
    S, C = level.shape[1], level.shape[3]
    g = level.reshape(6 * S * S, C)[_pad_index(S)]  # (6, S+2, S+2, 3, C)
    corner = _corner_mask(S)[..., None]
    return np.where(corner, (g[..., 0, :] + g[..., 1, :] + g[..., 2, :]) * _F32(1.0 / 3.0), g[..., 0, :])


def _dir_to_face_np(x, y, z):
    """`cubemap.dir_to_face` on float32 planes of unit directions -> (face intp, s, t)."""
    ax, ay, az = np.abs(x), np.abs(y), np.abs(z)
    is_x = (ax >= ay) & (ax >= az)
    is_y = ~is_x & (ay >= az)
    ma = np.where(is_x, ax, np.where(is_y, ay, az))
    face = np.where(is_x, x < 0, np.where(is_y, 2 + (y < 0), 4 + (z < 0))).astype(np.intp)
    sc = np.where(is_x, np.where(x >= 0, -z, z), np.where(is_y, x, np.where(z >= 0, x, -x)))
    tc = np.where(is_x, -y, np.where(is_y, np.where(y >= 0, z, -z), -y))
    inv = _F32(1.0) / ma  # unit directions: ma >= 1/sqrt(3)
    s = np.clip(0.5 * (sc * inv + 1.0), 0.0, 1.0)
    t = np.clip(0.5 * (tc * inv + 1.0), 0.0, 1.0)
    return face, s, t


@dataclass(frozen=True)
class NumpyCube:
    """A cube map's levels padded (seam-aware, as `cubemap._Pyramid`) and concatenated into one flat
    (N, C) float32 array; `sample` reproduces `Cubemap.sample` (bilinear within a level, linear
    between levels)."""

    flat: np.ndarray
    offsets: np.ndarray  # (M,) intp: start of each padded level in `flat`
    sizes: np.ndarray  # (M,) intp: face size of each level

    @classmethod
    def from_cubemap(cls, cube: Cubemap) -> NumpyCube:
        levels = [np.asarray(lv, _F32) for lv in cube.levels]
        pads = [_pad_level_np(lv).reshape(-1, lv.shape[-1]) for lv in levels]
        sizes = np.array([lv.shape[1] for lv in levels], np.intp)
        offsets = np.cumsum([0] + [len(p) for p in pads])[:-1].astype(np.intp)
        return cls(np.ascontiguousarray(np.concatenate(pads)), offsets, sizes)

    @property
    def num_levels(self) -> int:
        return len(self.sizes)

    def _bilinear(self, face, s, t, level):
        if level is None:  # one level: scalar size and offset
            Si = int(self.sizes[0])
            S, W, off = _F32(Si), Si + 2, 0
        else:
            Si = self.sizes[level]
            S, W, off = Si.astype(_F32), Si + 2, self.offsets[level]
        x = s * S + 0.5
        y = t * S + 0.5
        x0f = np.clip(np.floor(x), 0, S)
        y0f = np.clip(np.floor(y), 0, S)
        fx = (x - x0f)[:, None]
        fy = (y - y0f)[:, None]
        base = off + (face * W + y0f.astype(np.intp)) * W + x0f.astype(np.intp)
        f = self.flat
        v00 = f.take(base, axis=0)
        v01 = f.take(base + 1, axis=0)
        v10 = f.take(base + W, axis=0)
        v11 = f.take(base + (W + 1), axis=0)
        top = v00 + (v01 - v00) * fx
        bot = v10 + (v11 - v10) * fx
        return top + (bot - top) * fy

    def sample(self, x, y, z, lod=None):
        """Radiance (P, C) in unit directions given as float32 planes x, y, z (P,); `lod` (P,) or None
        (level 0)."""
        face, s, t = _dir_to_face_np(x, y, z)
        if lod is None or self.num_levels == 1:
            return self._bilinear(face, s, t, None)
        lod = np.clip(lod, 0.0, self.num_levels - 1)
        m0f = np.floor(lod)
        m0 = m0f.astype(np.intp)
        m1 = np.minimum(m0 + 1, self.num_levels - 1)
        w = (lod - m0f)[:, None]
        a = self._bilinear(face, s, t, m0)
        b = self._bilinear(face, s, t, m1)
        return a + (b - a) * w


def lut_lookup_numpy(lut: np.ndarray, n_dot_v: np.ndarray, roughness: np.ndarray) -> np.ndarray:
    """NumPy port of `jaxpbr.lut.lut_lookup` (bilinear, clamp to edge) for float32 (P,) inputs."""
    n_r, n_nov, C = lut.shape
    flat = lut.reshape(n_r * n_nov, C)

    def axis(u, n):
        x = np.clip(u * _F32(n) - 0.5, 0.0, n - 1.0)
        i0 = np.clip(np.floor(x), 0, max(n - 2, 0)).astype(np.intp)
        return i0, np.minimum(i0 + 1, n - 1), x - i0.astype(_F32)

    j0, j1, fr = axis(roughness, n_r)
    i0, i1, fm = axis(n_dot_v, n_nov)
    fm, fr = fm[:, None], fr[:, None]
    r0, r1 = j0 * n_nov, j1 * n_nov
    top = flat.take(r0 + i0, axis=0) * (1.0 - fm) + flat.take(r0 + i1, axis=0) * fm
    bot = flat.take(r1 + i0, axis=0) * (1.0 - fm) + flat.take(r1 + i1, axis=0) * fm
    return top * (1.0 - fr) + bot * fr


@dataclass(frozen=True)
class NumpyIBL:
    """The IBL tables in NumPy form: irradiance and prefiltered pyramids, the (A, B) LUT and the
    prefiltered map's roughness -> mip mapping."""

    irr: NumpyCube
    pre: NumpyCube
    lut: np.ndarray  # (n_r, n_nov, 2) float32
    mapping: str = "linear"

    @classmethod
    def from_tables(cls, irr: Cubemap, pre: Cubemap, lut) -> NumpyIBL:
        return cls(
            NumpyCube.from_cubemap(irr),
            NumpyCube.from_cubemap(pre),
            np.ascontiguousarray(np.asarray(lut, _F32)),
            pre.metadata.get("roughness_mapping", "linear"),
        )


def shade_ibl_numpy(g: dict[str, np.ndarray], ibl: NumpyIBL) -> np.ndarray:
    """`shade_ibl(model="gltf", multiscatter=False)` in NumPy on a float32 G-buffer -> (H, W, 3):
    `c_diff * Ebar(n) + LD(R, lod(r)) * (F0 A + B)`, R = 2 (n.v) n - v."""
    shape = g["normal"].shape[:-1]
    n = g["normal"].reshape(-1, 3)
    v = g["view"].reshape(-1, 3)
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    vx, vy, vz = v[:, 0], v[:, 1], v[:, 2]
    nov_raw = nx * vx + ny * vy + nz * vz
    k = 2.0 * nov_raw
    nov = np.clip(nov_raw, MIN_N_DOT_V, 1.0)
    r = np.clip(g["roughness"].reshape(-1), 0.0, 1.0)
    ab = lut_lookup_numpy(ibl.lut, nov, r)
    L = ibl.pre.num_levels - 1
    lod = r * L if ibl.mapping == "linear" else r * (2.0 - r) * L
    ld = ibl.pre.sample(k * nx - vx, k * ny - vy, k * nz - vz, lod)
    ebar = ibl.irr.sample(nx, ny, nz)
    base = g["base_color"].reshape(-1, 3)
    m = g["metallic"].reshape(-1, 1)
    f0 = F0_DIELECTRIC * (1.0 - m) + base * m
    out = (base * (1.0 - m)) * ebar + ld * (f0 * ab[:, 0:1] + ab[:, 1:2])
    if "occlusion" in g:
        out *= g["occlusion"].reshape(-1, 1)
    return out.reshape(shape + (3,))


def shade_render_numpy(g: dict[str, np.ndarray], lights: list[dict], ibl: NumpyIBL) -> np.ndarray:
    """NumPy equivalent of `shade_direct(model="gltf") + shade_ibl(model="gltf")`, (H, W, 3)."""
    return shade_numpy(g, lights) + shade_ibl_numpy(g, ibl)


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


# ------------------------------------------------------------------------------------------
# Scene: a sphere grid in front of a wall, ray-cast in NumPy
# ------------------------------------------------------------------------------------------


def make_sphere_gbuffer(
    width: int,
    height: int,
    *,
    rows: int = 5,
    cols: int | None = None,
    spacing: float = 2.5,
    radius: float = 1.0,
    camera_distance: float | None = None,
    fov_y_deg: float = 45.0,
    wall_z: float = -2.5,
) -> dict[str, np.ndarray]:
    """A float32 G-buffer (H, W, ...) of a rows x cols grid of spheres (centres in the plane z = 0,
    metallic 1 -> 0 from the top row down, roughness 0 -> 1 left to right, base colour by hue)
    in front of a grey wall z = `wall_z` (dielectric, r = 0.7), seen by a pinhole camera at
    (0, 0, camera_distance) looking down -z, so every pixel is a surface. Ray-cast per sphere
    inside its projected bounding box (float64, then rounded). Extra key `sphere` (H, W) bool."""
    if width <= 0 or height <= 0 or rows <= 0:
        raise ValueError("width, height and rows must be positive.")
    aspect = width / height
    cols = max(1, round(rows * aspect * 0.9)) if cols is None else cols
    tan_half = math.tan(math.radians(fov_y_deg) / 2.0)
    half_h = (rows - 1) / 2 * spacing + radius
    half_w = (cols - 1) / 2 * spacing + radius
    if camera_distance is None:
        camera_distance = 1.08 * max(half_h, half_w / aspect) / tan_half + radius
    cam = np.array([0.0, 0.0, camera_distance])
    xs = (2.0 * (np.arange(width) + 0.5) / width - 1.0) * tan_half * aspect
    ys = (1.0 - 2.0 * (np.arange(height) + 0.5) / height) * tan_half
    d = np.empty((height, width, 3))
    d[..., 0] = xs[None, :]
    d[..., 1] = ys[:, None]
    d[..., 2] = -1.0
    d /= np.linalg.norm(d, axis=-1, keepdims=True)

    # Wall everywhere first, then spheres where they are hit.
    t_best = (wall_z - cam[2]) / d[..., 2]
    normal = np.broadcast_to(np.array([0.0, 0.0, 1.0]), d.shape).copy()
    base = np.broadcast_to(np.array([0.6, 0.6, 0.6]), d.shape).copy()
    metallic = np.zeros((height, width))
    rough = np.full((height, width), 0.7)
    sphere = np.zeros((height, width), bool)

    def to_pixel(q):  # world points (..., 3) -> continuous (col, row)
        rel = q - cam
        px = rel[..., 0] / -rel[..., 2] / (tan_half * aspect)
        py = rel[..., 1] / -rel[..., 2] / tan_half
        return (px + 1.0) * width / 2.0 - 0.5, (1.0 - py) * height / 2.0 - 0.5

    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * radius
    for i in range(rows):
        for j in range(cols):
            c = np.array([(j - (cols - 1) / 2) * spacing, ((rows - 1) / 2 - i) * spacing, 0.0])
            cj, ci = to_pixel(c + corners)
            j0, j1 = max(0, int(np.floor(cj.min())) - 1), min(width, int(np.ceil(cj.max())) + 2)
            i0, i1 = max(0, int(np.floor(ci.min())) - 1), min(height, int(np.ceil(ci.max())) + 2)
            if j0 >= j1 or i0 >= i1:
                continue
            dd = d[i0:i1, j0:j1]
            oc = cam - c
            b = dd @ oc
            disc = b * b - (oc @ oc - radius * radius)
            t = -b - np.sqrt(np.maximum(disc, 0.0))
            hit = (disc > 0) & (t > 0) & (t < t_best[i0:i1, j0:j1])
            if not hit.any():
                continue
            win = (slice(i0, i1), slice(j0, j1))
            t_best[win] = np.where(hit, t, t_best[win])
            p = cam + t[..., None] * dd
            normal[win] = np.where(hit[..., None], (p - c) / radius, normal[win])
            hue = (i * cols + j) / max(rows * cols, 1)
            col = 0.5 + 0.45 * np.cos(2.0 * math.pi * (hue + np.array([0.0, 1.0 / 3.0, 2.0 / 3.0])))
            base[win] = np.where(hit[..., None], col, base[win])
            metallic[win] = np.where(hit, 1.0 - i / max(rows - 1, 1), metallic[win])
            rough[win] = np.where(hit, j / max(cols - 1, 1), rough[win])
            sphere[win] |= hit

    p = cam + t_best[..., None] * d
    n = normal.astype(_F32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    v = (-d).astype(_F32)
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return {
        "position": p.astype(_F32),
        "normal": n,
        "view": v,
        "base_color": np.clip(base, 0.0, 1.0).astype(_F32),
        "metallic": metallic.astype(_F32),
        "roughness": rough.astype(_F32),
        "sphere": sphere,
    }


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
    from . import envs
    from .diffuse import irradiance
    from .shipped_luts import brdf_lut
    from .specular import prefilter

    def timed(fn):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        return out, time.perf_counter() - t0

    times = {}
    env, times["environment"] = timed(lambda: envs.sky_with_sun_cubemap(face_size))
    irr, times["irradiance"] = timed(lambda: irradiance(env, min(irradiance_size, face_size)))
    pre, times["prefilter"] = timed(lambda: prefilter(env))
    lut, times["brdf_lut"] = timed(lambda: brdf_lut(lut_size))
    return IBLTables(env, irr, pre, jnp.asarray(lut, jnp.float32), times)


# ------------------------------------------------------------------------------------------
# Benchmarks
# ------------------------------------------------------------------------------------------


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _device_kind() -> str:
    d = jax.devices()[0]
    return getattr(d, "device_kind", str(d))


def _max_rel(a: np.ndarray, ref: np.ndarray, floor: float = 1e-3) -> float:
    return float(np.max(np.abs(np.asarray(a) - ref) / np.maximum(np.abs(ref), floor)))


@dataclass
class RenderBenchResult:
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

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def ratio(self) -> float:
        return self.numpy_s / self.jax_s

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
        if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x <= 0:
            raise ValueError(f"{name} must be a positive integer, got {x!r}.")
    if ibl is None:
        ibl = make_ibl(face_size)
    g = make_sphere_gbuffer(width, height)
    gs = {k: g[k] for k in GBUFFER_KEYS}
    lights = bench_lights()
    device = jax.devices()[0]
    gd = {k: jax.device_put(x, device) for k, x in gs.items()}
    jl = jax_point_lights(lights)

    # The library's own path: jp.render of a G-buffer scene (staged programs: direct lighting,
    # then IBL; see renderer._render_pass). The LUT is the shipped one render loads.
    from .renderer import render
    from .scene import Environment, GBuffer, Scene

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
    t0 = time.perf_counter()
    out = render(scene).block_until_ready()
    compile_s = time.perf_counter() - t0
    jax_s = _median_time(lambda: render(scene).block_until_ready(), repeats)

    t0 = time.perf_counter()
    nibl = NumpyIBL.from_tables(ibl.irr, ibl.pre, ibl.lut)
    setup_s = time.perf_counter() - t0
    ref = shade_render_numpy(gs, lights, nibl)
    numpy_s = _median_time(lambda: shade_render_numpy(gs, lights, nibl), numpy_repeats)

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
        "base_color": rng.uniform(0.05, 0.95, (num, 3)).astype(_F32),
        "metallic": rng.uniform(0.0, 1.0, num).astype(_F32),
        "roughness": rng.uniform(0.0, 1.0, num).astype(_F32),
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
        if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x <= 0:
            raise ValueError(f"{name} must be a positive integer, got {x!r}.")
    if ibl is None:
        ibl = make_ibl(face_size)
    # The library's path: one Scene (a sphere ray-cast at size^2, 4 point lights, the IBL maps
    # passed in), `render_batch` over a Material with a leading batch axis vs a Python loop of
    # `render` calls with one material each.
    from .material import Material
    from .renderer import render, render_batch
    from .scene import Camera, Environment, Scene, Sphere

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

    t0 = time.perf_counter()
    out_b = render_batch(scene, materials=batch_mat, chunk=c).block_until_ready()
    compile_s = time.perf_counter() - t0
    batch_s = _median_time(lambda: render_batch(scene, materials=batch_mat, chunk=c).block_until_ready(), repeats)

    singles = [
        scene.replace(objects=[Sphere(material=jax.tree_util.tree_map(lambda x: x[i], batch_mat))])
        for i in range(num_materials)
    ]
    t0 = time.perf_counter()
    render(singles[0]).block_until_ready()
    loop_compile_s = time.perf_counter() - t0

    def loop():
        return jax.block_until_ready([render(sc) for sc in singles])

    out_l = loop()
    loop_s = _median_time(loop, repeats)
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


from .cli import _positive_int  # noqa: E402  (the CLI's own argument type)


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {value}")
    return value


def _cmd_bench_render(args) -> int:
    ibl = make_ibl(args.face_size)
    result = bench_render_gbuffer(
        args.width, args.height, repeats=args.repeats, numpy_repeats=args.numpy_repeats, face_size=args.face_size, ibl=ibl
    )
    print(result.report(), flush=True)
    if args.batch:
        res = bench_batch(args.batch, args.batch_size, args.chunk, repeats=args.repeats, face_size=args.face_size, ibl=ibl)
        print(res.report(), flush=True)
    return 0


def add_bench_render_command(bench_subparsers) -> argparse.ArgumentParser:
    """Register `jaxpbr bench render` on the `bench` sub-parsers; returns the new parser."""
    p = bench_subparsers.add_parser(
        "render",
        help="shade a 1920x1080 sphere-grid G-buffer with 4 point lights + split-sum IBL: jitted JAX vs "
        "vectorised NumPy; and a material-batch throughput run",
        description="Direct (4 point lights) + split-sum IBL shading of a sphere-grid G-buffer, jitted "
        "JAX vs vectorised NumPy in one process (IBL precompute and JIT compile timed apart); then N "
        "materials on a sphere as one jitted vmap (chunked by lax.map) vs a Python loop of jitted calls.",
    )
    p.add_argument("--width", type=_positive_int, default=1920)
    p.add_argument("--height", type=_positive_int, default=1080)
    p.add_argument("--repeats", type=_positive_int, default=10, help="timed JAX runs (median)")
    p.add_argument("--numpy-repeats", type=_positive_int, default=3, help="timed NumPy runs (median)")
    p.add_argument("--face-size", type=_positive_int, default=128, help="environment cube face size")
    p.add_argument("--batch", type=_non_negative_int, default=256, metavar="N",
                   help="materials in the batch-throughput run (0: skip it)")
    p.add_argument("--batch-size", type=_positive_int, default=256, metavar="S", help="batch image size S x S")
    p.add_argument("--chunk", type=_positive_int, default=16, help="materials per vmapped chunk (lax.map batch_size)")
    p.set_defaults(func=_cmd_bench_render)
    return p
