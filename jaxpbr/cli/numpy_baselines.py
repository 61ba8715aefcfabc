"""NumPy baselines of the benchmarks: vectorised float32 NumPy implementations of the same math
as the library's kernels, written independently of JAX, plus the G-buffers they shade.

* `make_gbuffer`, `bench_lights`, `shade_numpy`: a random G-buffer and four point lights shaded
  with the glTF model (height-correlated Smith, Lambert), as `shade_direct(..., model="gltf")`.
* `NumpyCube`, `lut_lookup_numpy`, `NumpyIBL`, `shade_ibl_numpy`, `shade_render_numpy`: ports of
  the seam-padded cube pyramid lookup of `Cubemap.sample`, of `lut_lookup` and of the split sum of
  `shade_ibl`.
* `make_sphere_gbuffer`: a sphere grid in front of a wall, ray-cast in NumPy.

G-buffers are dicts of float32 (H, W, ...) arrays (keys `GBUFFER_KEYS`); normals and view vectors
must be unit length (JAX renormalises them, a difference of an ulp); no emissive, occlusion 1
unless the dict has an `occlusion` plane. These are benchmark baselines and test oracles; the
library never imports them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..ibl.cubemap import Cubemap, corner_mask, pad_index
from ..ibl.shade import MIN_N_DOT_V
from ..ibl.specular import lookup_of, roughness_to_lod
from ..shading.lut import lut_coordinates, lut_padded, lut_r0
from ..shading.material import F0_DIELECTRIC
from ..shading.split_sum import SCHLICK_LAMBERT_FIT

__all__ = [
    "GBUFFER_KEYS",
    "NumpyCube",
    "NumpyIBL",
    "bench_lights",
    "lut_lookup_numpy",
    "make_gbuffer",
    "make_sphere_gbuffer",
    "shade_ibl_numpy",
    "shade_numpy",
    "shade_render_numpy",
]

_F32 = np.float32
GBUFFER_KEYS = ("position", "normal", "view", "base_color", "metallic", "roughness")


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


# ------------------------------------------------------------------------------------------
# NumPy IBL
# ------------------------------------------------------------------------------------------


def _pad_level_np(level: np.ndarray) -> np.ndarray:
    """NumPy port of `cubemap._pad_level`: (6, S, S, C) -> (6, S+2, S+2, C) seam pad."""
    S, C = level.shape[1], level.shape[3]
    g = level.reshape(6 * S * S, C)[pad_index(S)]  # (6, S+2, S+2, 3, C)
    corner = corner_mask(S)[..., None]
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
    """NumPy port of `jaxpbr.shading.lut.lut_lookup` (split-sum edges: the closed form at r = 0, the table
    extended to r = 1 and NoV = 1, bilinear, clamped beyond) for float32 (P,) inputs."""
    table = lut_padded(np.asarray(lut), xp=np)
    n_r, n_nov = lut.shape[:2]
    H, W, C = table.shape
    flat = table.reshape(H * W, C)
    x, y, t = lut_coordinates(n_dot_v, roughness, n_r, n_nov, xp=np)

    def axis(c, n):
        c = np.clip(c, 0.0, n - 1.0)
        i0 = np.clip(np.floor(c), 0, max(n - 2, 0)).astype(np.intp)
        return i0, np.minimum(i0 + 1, n - 1), (c - i0).astype(_F32)

    j0, j1, fr = axis(y, H)
    i0, i1, fm = axis(x, W)
    fm, fr = fm[:, None], fr[:, None]
    r0, r1 = j0 * W, j1 * W
    top = flat.take(r0 + i0, axis=0) * (1.0 - fm) + flat.take(r0 + i1, axis=0) * fm
    bot = flat.take(r1 + i0, axis=0) * (1.0 - fm) + flat.take(r1 + i1, axis=0) * fm
    ab = top * (1.0 - fr) + bot * fr
    edge = lut_r0(n_dot_v, xp=np).astype(_F32)
    return edge + (ab - edge) * t.astype(_F32)[:, None]


@dataclass(frozen=True)
class NumpyIBL:
    """The IBL tables in NumPy form: irradiance and prefiltered pyramids, the (A, B) LUT and the
    prefiltered map's roughness -> mip mapping."""

    irr: NumpyCube
    pre: NumpyCube
    lut: np.ndarray  # (n_r, n_nov, 2) float32
    mapping: str = "linear"
    lod_blend: str = "roughness"  # `specular.roughness_to_lod`; "roughness": lod = r (M-1)
    mapping_levels: int | None = None  # M of the lookup (None: the map's level count)

    @classmethod
    def from_tables(cls, irr: Cubemap, pre: Cubemap, lut) -> NumpyIBL:
        M, mapping, blend = lookup_of(pre)
        return cls(
            NumpyCube.from_cubemap(irr),
            NumpyCube.from_cubemap(pre),
            np.ascontiguousarray(np.asarray(lut, _F32)),
            mapping,
            blend,
            M,
        )


def shade_ibl_numpy(g: dict[str, np.ndarray], ibl: NumpyIBL) -> np.ndarray:
    """`shade_ibl(model="gltf", multiscatter=False)` in NumPy on a float32 G-buffer -> (H, W, 3):
    `c_diff 0.96 (1 - C(n.v)) Ebar(n) + LD(d, lod(r)) * (F0 A + B)`, R = 2 (n.v) n - v, d its
    dominant direction (`jaxpbr.ibl.shade`)."""
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
    M = ibl.pre.num_levels if ibl.mapping_levels is None else ibl.mapping_levels
    lod = roughness_to_lod(r, M, mapping=ibl.mapping, lod_blend=ibl.lod_blend, xp=np).astype(r.dtype)
    a2 = r * r
    s_ = 1.0 - a2
    t = s_ * (np.sqrt(s_) + a2)
    dx, dy, dz = nx + (k * nx - vx - nx) * t, ny + (k * ny - vy - ny) * t, nz + (k * nz - vz - nz) * t
    ld = ibl.pre.sample(dx, dy, dz, lod)  # the sampler normalises
    ebar = ibl.irr.sample(nx, ny, nz)
    base = g["base_color"].reshape(-1, 3)
    m = g["metallic"].reshape(-1, 1)
    f0 = F0_DIELECTRIC * (1.0 - m) + base * m
    c = np.polynomial.polynomial.polyval(1.0 - nov, SCHLICK_LAMBERT_FIT).astype(nov.dtype)
    kd = ((1.0 - F0_DIELECTRIC) * (1.0 - c)).reshape(-1, 1)
    out = (base * (1.0 - m)) * kd * ebar + ld * (f0 * ab[:, 0:1] + ab[:, 1:2])
    if "occlusion" in g:
        out *= g["occlusion"].reshape(-1, 1)
    return out.reshape(shape + (3,))


def shade_render_numpy(g: dict[str, np.ndarray], lights: list[dict], ibl: NumpyIBL) -> np.ndarray:
    """NumPy equivalent of `shade_direct(model="gltf") + shade_ibl(model="gltf")`, (H, W, 3)."""
    return shade_numpy(g, lights) + shade_ibl_numpy(g, ibl)


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
