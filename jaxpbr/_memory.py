"""Memory estimates of the precomputes and renders, and the one guard that refuses, before any work,
what would not fit (a huge size or sample count aborted inside XLA with a C++ stack, or ran the
machine out of memory).

Every estimator returns its parts: {argument name: bytes}, the bytes that argument is responsible
for; `require` sums them and, when the total exceeds `available_memory()`, raises
`MemoryLimitError` (a `ValueError`) naming the argument with the largest part as the one to lower
(front ends pass `names` to name their own flags or keys instead). The per-unit costs are peak
RSS increments measured on the CPU backend (float32 data, one process, `/proc/self/status`
VmHWM minus VmRSS before the call) and rounded up; they are upper bounds of real work, not caps:
whatever fits in memory runs.
"""

from __future__ import annotations

import math
import os

from .errors import InputError

__all__ = [
    "MAX_SAMPLES",
    "MEMORY_ENV",
    "MemoryLimitError",
    "available_memory",
    "cube_bytes",
    "image_bytes",
    "irradiance_bytes",
    "lut_bytes",
    "mesh_bytes",
    "prefilter_bytes",
    "render_bytes",
    "require",
]

#: Memory limit override in GB: `JAXPBR_MEMORY_LIMIT=64` (default: the memory available now).
MEMORY_ENV = "JAXPBR_MEMORY_LIMIT"

#: Most quadrature / importance samples per texel any precompute takes: the Hammersley points
#: are a 32-bit radical inverse (`sampling.hammersley`), and 2^32 samples per texel would be
#: hundreds of GB of sample tables anyway.
MAX_SAMPLES = 2**32 - 1

# Peak bytes per unit (CPU backend, measured, rounded up):
#: XLA's compilation and the program's buffers, whatever the sizes (a 64^2 prefilter with the
#: default samples: +142 MB; an 8x8 LUT: +93 MB).
_PROGRAM = 150e6
#: Cubemap.from_function: float64 sub-texel points, values and weights (the procedural sky at
#: supersample 4: 256^2 +511 MB, 1024^2 +7.2 GB, i.e. ~72 B per sub-texel point).
_PER_SUBTEXEL = 80.0
#: Cubemap.from_equirect (rows of sub-texels in blocks: the cube and its copies): per cube texel.
_PER_EQUIRECT_TEXEL = 60.0
#: prefilter: per texel of the environment (pyramid, flat padded copy, bright-texel split).
_PER_SOURCE_TEXEL = 200.0
#: prefilter: per FIS sample of a level (float64 tables while they are made, cached float64
#: local frame / weight / LOD, float32 device copies): 4 levels x 2^20 samples +~310 MB.
_PER_SAMPLE = 100.0
#: prefilter: per row of work (one output direction x 256 samples: float64 directions and their
#: repeats on the host, float32 and int32 device copies): 2.1 M rows +~200 MB.
_PER_ROW = 120.0
#: compute_brdf_lut: per quadrature node of one chunk of rows (8x8 LUT: 864000 samples +562 MB,
#: 86400 +178 MB, i.e. ~7.7 B per node), and per texel of the table.
_PER_LUT_NODE = 10.0
_PER_LUT_TEXEL = 16.0
#: irradiance: per output texel (exact convolution in chunks; float32 output and moments).
_PER_IRRADIANCE_TEXEL = 50.0
#: render: per pixel (staged in bands; the frame's float32 copies), measured 3840x2160 +1.52 GB.
_PER_PIXEL = 150.0
#: render: per texture value (texel x channel): the float32 array and the render's copies (a 32x18
#: render with a 2048^2 RGB texture: +57 MB over the array's own 50 MB, ~8.5 B per value).
_PER_TEXTURE_VALUE = 10.0


#: reading a texture file: per value (see `texture_load_bytes`).
_PER_TEXTURE_LOAD_VALUE = 64.0
#: render: the scene's triangle meshes, by the engine that answers their rays. Measured 2026-11-25
#: (`write_demo_glb` grids rendered at 64x36, peak RSS above the same process with a 22 k-triangle
#: grid): Embree +0.09 / 0.55 / 2.49 / 6.26 GB at 0.25 / 1.0 / 4.0 / 10.0 M triangles with half as
#: many vertices, ~0.64 kB per triangle with its vertices; the JAX BVH's NumPy build alone peaks at
#: +4.47 GB for 4.0 M triangles (1.12 kB each), and its arrays (~110 B per triangle) stay on the
#: device. Rounded up by about a quarter.
_MESH_FIXED = 300e6
_PER_TRIANGLE = {"embree": 700.0, "jax": 1400.0}
_PER_MESH_VERTEX = 160.0


class MemoryLimitError(InputError):
    """A size or sample count whose work would need more memory than is available."""


def available_memory() -> float:
    """Bytes a computation may use: $JAXPBR_MEMORY_LIMIT (GB) if set, else MemAvailable from
    /proc/meminfo (else the physical memory, else unlimited), at most what the cgroup allows."""
    own = os.environ.get(MEMORY_ENV)
    if own:
        try:
            value = float(own)
        except ValueError:
            value = float("nan")
        if not value > 0:  # NaN, 0 and negatives too
            raise InputError(f"{MEMORY_ENV} must be a number of gigabytes > 0, got {own!r}")
        return value * 1e9
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = float(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if avail is None:
        try:
            avail = float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            avail = float("inf")
    return min(avail, _cgroup_room())


def _cgroup_room() -> float:
    """What the process's cgroup (v2) still allows, memory.max - memory.current (a container or a
    CI runner limits memory below what /proc/meminfo reports); inf without a limit."""
    try:
        with open("/sys/fs/cgroup/memory.max") as f:
            limit = f.read().strip()
        if limit == "max":
            return float("inf")
        with open("/sys/fs/cgroup/memory.current") as f:
            used = float(f.read().strip())
        return max(float(limit) - used, 0.0)
    except (OSError, ValueError):
        return float("inf")


def require(what: str, parts: dict, *, where: str | None = None, names: dict | None = None) -> None:
    """Raise `MemoryLimitError` if the parts of `what` ({argument: bytes}) add up to more than
    `available_memory()`. The message names the argument with the largest part (through `names`,
    e.g. {"size": "--size"}, when given) as the one to lower."""
    total = float(sum(parts.values()))
    limit = available_memory()
    if not total > limit:
        return
    arg = max(parts, key=lambda k: parts[k])
    flag = (names or {}).get(arg, arg)
    prefix = f"{where}: " if where else ""
    raise MemoryLimitError(
        f"{prefix}{what} needs about {total / 1e9:.3g} GB of memory, more than the {limit / 1e9:.3g} GB available; "
        f"lower {flag}, or set {MEMORY_ENV}=<GB> to allow more"
    )


def check_samples(name: str, n: int, *, where: str | None = None) -> int:
    """`n` if it is at most MAX_SAMPLES, else a ValueError naming `name`."""
    if n > MAX_SAMPLES:
        prefix = f"{where}: " if where else ""
        raise InputError(
            f"{prefix}{name} must be < 2**32 (the sample points are a 32-bit sequence), got {n}; "
            f"a few thousand is already converged for any texel"
        )
    return n


def cube_bytes(face_size: int, *, supersample: int | None = None) -> dict:
    """Building a cube of `face_size`: `Cubemap.from_function` at `supersample` (an int), or
    `Cubemap.from_equirect` (None)."""
    texels = 6.0 * face_size * face_size
    if supersample is None:
        return {"face_size": texels * _PER_EQUIRECT_TEXEL}
    return {"face_size": texels * supersample * supersample * _PER_SUBTEXEL}


def prefilter_bytes(source_size: int, size: int, samples) -> dict:
    """`prefilter` of a `source_size`^2 environment to a `size`^2 chain; samples: the FIS samples
    of each computed level (index 0, the source itself, is not sampled)."""
    rows = 0
    for m, n in enumerate(samples):
        if m:
            rows += 6 * max(1, size >> m) ** 2 * -(-int(n) // 256)
    return {
        "face_size": _PROGRAM + 6.0 * source_size * source_size * _PER_SOURCE_TEXEL,
        "samples": float(sum(samples[1:])) * _PER_SAMPLE + rows * _PER_ROW,
    }


def lut_bytes(n_r: int, n_nov: int, samples: int) -> dict:
    """`compute_brdf_lut` of (n_r, n_nov) texels at `samples` per texel (its Gauss-Legendre rule
    evaluates 6 m^2 <= samples nodes per texel, a chunk of rows of at most 4096 texels at a time)."""
    m = max(1, math.isqrt(samples // 6))
    rows = max(1, min(n_r, 4096 // n_nov))
    return {
        "size": _PROGRAM + float(n_r) * n_nov * _PER_LUT_TEXEL,
        "samples": float(rows) * n_nov * 6 * m * m * _PER_LUT_NODE,
    }


def irradiance_bytes(size: int) -> dict:
    """`irradiance` to a `size`^2 map."""
    return {"size": _PROGRAM + 6.0 * size * size * _PER_IRRADIANCE_TEXEL}


def image_bytes(width: int, height: int) -> dict:
    """A render of width x height pixels (the supersampling passes run one after another)."""
    return {"width/height": float(width) * height * _PER_PIXEL}


def texture_bytes(shapes) -> float:
    """The textures of a render: `shapes` of (H, W, C) arrays."""
    return float(sum(math.prod(s) for s in shapes)) * _PER_TEXTURE_VALUE


def texture_load_bytes(shape) -> dict:
    """Reading an (H, W, C) texture file into float32 (a PNG's integer codes, their float64 and
    float32 conversions, the sRGB decode; 2048^2 RGB: +748 MB, 3072^2: +1.69 GB, ~60 B per value)."""
    return {"texture": float(math.prod(shape)) * _PER_TEXTURE_LOAD_VALUE}


def mesh_bytes(vertices: int, triangles: int, engine: str = "jax") -> dict:
    """A render's triangle meshes: `vertices` and `triangles` summed over the scene's meshes (the
    ray engine, its acceleration structure and the meshes' copies); {} without triangles. engine:
    "embree" (the host engine on the CPU) or "jax" (the NumPy-built BVH: the larger)."""
    if not triangles:
        return {}
    return {"triangles": _MESH_FIXED + float(triangles) * _PER_TRIANGLE[engine] + float(vertices) * _PER_MESH_VERTEX}


def render_bytes(width: int, height: int, texture_shapes=()) -> dict:
    """A render's image and its textures (the IBL assets are the precomputes' own estimates)."""
    parts = image_bytes(width, height)
    tex = texture_bytes(texture_shapes)
    if tex:
        parts["textures"] = tex
    return parts
