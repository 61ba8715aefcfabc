"""Texture aliasing at grazing angles: bilinear without mips vs trilinear vs anisotropic filtering.

A camera 1 unit above an infinite plane looks towards the horizon; the plane carries a 512 x 512
checker texture (8 x 8 squares of 64 texels, uv = (X, Z) / 4: 128 texels per world unit), repeated
across the whole plane. Each pixel is rendered with

  (a) bilinear, level 0 only (what `jaxpbr.scene.sample_texture` does today: `_interp.bilinear`),
  (b) trilinear mips (`Texture`, linear_mipmap_linear, max_anisotropy=1),
  (c) anisotropic filtering with 4, 8 and 16 taps (same pyramid),

with uv and its pixel derivatives from `pinhole_ray_differentials` + `uv_derivatives_on_triangle`,
all in float32, and compared with a reference.

The reference. What the texture *is*, as a function on the plane, is its level-0 bilinear
reconstruction T(s, t) = (1 + S(s) S(t)) / 2 (s, t level-0 texel coordinates; S the piecewise-
linear interpolation of the +-1 square wave of the checker rows / columns: bilinear interpolation
of a separable texture is separable). The ideal anti-aliased pixel is T box-filtered over the
pixel's preimage. The reference splits each pixel into nx x ny stratified sub-pixels and gives
each the *exact* box integral of T over its own footprint (the axis-aligned box of the
sub-pixel's ds/dx, dt/dy extents; the integral of S is a closed-form piecewise quadratic, so a
sub-sample covering 10^4 texels costs the same as one covering 0.1), in float64. A box drops the
footprint's shear (ds/dy: off-centre columns see the plane obliquely), and a sheared footprint
that runs along the checker's diagonals can see far more contrast than an upright box of the same
size: so nx, ny are chosen per row (at least 8 x 8) such that no sub-pixel spans more than
`--limit` (8) texels along any axis, including the shear -- up to ~12000 sub-rows per pixel in
the row just below the horizon. The script recomputes the reference with twice that limit; the
difference (the first row of the table) estimates its error.

Why not 64 point samples of level-0 bilinear (the brief's other candidate): near the horizon a
pixel covers thousands of checker squares, each point sample is 0 or 1 nearly at random, and 64
of them leave a standard error of ~0.5/8 = 0.06 per pixel -- the size of the errors being
measured -- shrinking only as 1/sqrt(n) (and stratified samples on a periodic pattern can alias
coherently instead: moire). It does converge, but too slowly to be a reference; the table scores
it like the filters.

Pixels that see only the plane (their top edge below the horizon) are scored, in three bands of
hit distance: near (< 3 units), mid (3-15) and far (>= 15, up to the horizon). Timings: each method
is one jitted program from camera rays to pixel values, all timed in this process in interleaved
rounds after a warm-up (best and median of --repeats).

Run: python examples/texture_aliasing.py [--size 256] [--repeats 9] [--limit 8]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxpbr._interp import bilinear
from jaxpbr.rendering.texture import (
    Texture,
    pinhole_ray_differentials,
    sample,
    uv_derivatives_on_triangle,
)

TEX = 512  # texels per side
SQUARE = 64  # texels per checker square
PERIOD = 4.0  # world units per texture repeat
HEIGHT = 1.0  # camera above the plane
PITCH_DEG = 22.0  # looking down by this much: the horizon sits ~1/7 from the top
FOV_DEG = 60.0
BANDS = (("near", 0.0, 3.0), ("mid", 3.0, 15.0), ("far", 15.0, np.inf))


def checker_texels():
    c = np.where((np.arange(TEX) // SQUARE) % 2 == 0, 1.0, -1.0)
    return ((1.0 + c[:, None] * c[None, :]) / 2.0)[..., None].astype(np.float32)


def camera():
    p = np.deg2rad(PITCH_DEG)
    position = np.array([0.0, HEIGHT, 0.0])
    return position, position + np.array([0.0, -np.sin(p), np.cos(p)]), np.array([0.0, 1.0, 0.0])


# ------------------------------------------------------------------------------------------
# Reference (NumPy, float64)
# ------------------------------------------------------------------------------------------


def _G(r):
    """Antiderivative over one period of S (r = s - 1/2 mod 2 SQUARE, S(r) = +1 on [0, 63],
    a linear ramp to -1 on [63, 64], -1 on [64, 127], a ramp back on [127, 128]; G(0) = G(128) = 0)."""
    n = SQUARE
    a = r - (n - 1)
    b = r - (2 * n - 1)
    return np.select(
        [r <= n - 1, r <= n, r <= 2 * n - 1],
        [r, (n - 1) + a - a * a, (n - 1) - (r - n)],
        -b + b * b,
    )


def _box_S(s, w):
    """Average of S over [s - w/2, s + w/2] (w > 0 texels), exact."""
    def F(x):  # an antiderivative of S; S has zero mean, so F is periodic
        return _G(np.mod(x - 0.5, 2 * SQUARE))

    return (F(s + w / 2) - F(s - w / 2)) / w


def _S_point(s):
    """S at s (level-0 bilinear reconstruction of the +-1 wave): the derivative of G."""
    r = np.mod(s - 0.5, 2 * SQUARE)
    n = SQUARE
    return np.select([r <= n - 1, r <= n, r <= 2 * n - 1], [1.0, 1.0 - 2.0 * (r - (n - 1)), -1.0], -1.0 + 2.0 * (r - (2 * n - 1)))


def _basis():
    pos, tgt, upv = camera()
    f = (tgt - pos) / np.linalg.norm(tgt - pos)
    r = np.cross(f, upv)
    r /= np.linalg.norm(r)
    return f, r, np.cross(r, f), np.tan(np.deg2rad(FOV_DEG) / 2)


def hits(size, px, py):
    """Plane hits of the rays through continuous pixel coordinates px (column), py (row)
    (broadcasting, float64): level-0 texel coordinates s, t, their pixel derivatives ds/dx,
    dt/dy, ds/dy (texels per pixel), the hit distance and whether the ray meets the plane."""
    f, r, u, tn = _basis()
    x = (2 * px / size - 1) * tn
    y = (1 - 2 * py / size) * tn
    d = [f[i] + x * r[i] + y * u[i] for i in range(3)]
    down = -d[1]
    valid = down > 0
    k = HEIGHT / np.where(valid, down, 1.0)  # hit = camera + k d: X = k d_x, Z = k d_z
    ddx, ddy = (2 * tn / size) * r, -(2 * tn / size) * u
    scale = TEX / PERIOD

    def deriv(dd, a):  # d/dp (h d_a / -d_y), quotient rule
        return HEIGHT * (dd[a] * down + d[a] * dd[1]) * (k / HEIGHT) ** 2 * scale

    dist = k * np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
    return k * d[0] * scale, k * d[2] * scale, deriv(ddx, 0), deriv(ddy, 2), deriv(ddy, 0), dist, valid


def scored_pixels(size):
    """Rows whose top edge is below the horizon (every sub-sample sees the plane); pixel-centre
    hit distance."""
    rows = np.arange(size)
    ok_row = hits(size, np.array([0.0, float(size)])[None, :], rows[:, None].astype(float))[6].all(-1)
    dist = hits(size, np.arange(size)[None, :] + 0.5, rows[:, None] + 0.5)[5]
    return np.broadcast_to(ok_row[:, None], (size, size)), np.where(ok_row[:, None], dist, np.inf)


def reference(size, limit, max_block=1 << 22):
    """Per pixel, the mean over ny x nx stratified sub-samples of the exact box integral of the
    bilinear reconstruction over each sub-sample's footprint (s-extent |ds/dx| / nx, t-extent
    |dt/dy| / ny). Per row, nx and ny (>= 8) are chosen so that no sub-sample is longer than
    `limit` texels along any axis, including the shear ds/dy the axis-aligned box leaves out
    (which is what makes the checker's diagonals alias: they need thin sub-samples)."""
    ok, _ = scored_pixels(size)
    out = np.zeros((size, size))
    cols = np.arange(size, dtype=np.float64)
    for i in np.flatnonzero(ok[:, 0]):
        # derivatives are largest at the row's top edge (farthest), at the image's side columns
        _, _, sx, ty, sy, _, _ = hits(size, np.array([0.0, size]), np.array([float(i), float(i)]))
        ny = max(8, int(np.ceil(max(np.abs(ty).max(), np.abs(sy).max()) / limit)))
        nx = max(8, int(np.ceil(np.abs(sx).max() / limit)))
        ox = (np.arange(nx) + 0.5) / nx
        px = (cols[:, None] + ox[None, :]).reshape(1, -1)
        acc = np.zeros(size * nx)
        step = max(1, max_block // (size * nx))
        for b0 in range(0, ny, step):
            py = i + (np.arange(b0, min(ny, b0 + step)) + 0.5)[:, None] / ny
            s, t, sx, ty, _, _, _ = hits(size, px, py)
            acc += ((1.0 + _box_S(s, np.abs(sx) / nx) * _box_S(t, np.abs(ty) / ny)) / 2.0).sum(0)
        out[i] = acc.reshape(size, nx).sum(-1) / (nx * ny)
    return out


def point_sampled(size, n):
    """n x n stratified point samples per pixel of the level-0 bilinear reconstruction."""
    ok, _ = scored_pixels(size)
    o = (np.arange(n) + 0.5) / n
    px = (np.arange(size)[:, None] + o).reshape(1, -1)
    py = (np.arange(size)[:, None] + o).reshape(-1, 1)
    s, t, *_ , valid = hits(size, px, py)
    v = np.where(valid, (1.0 + _S_point(s) * _S_point(t)) / 2.0, 0.0)
    return np.where(ok, v.reshape(size, n, size, n).mean((1, 3)), 0.0)


# ------------------------------------------------------------------------------------------
# The renderers (JAX, float32)
# ------------------------------------------------------------------------------------------


def frame_uv(size):
    pos, tgt, upv = camera()
    o, d, ddx, ddy = pinhole_ray_differentials(pos, tgt, upv, FOV_DEG, size, size)
    tri = np.array([[0.0, 0.0, 0.0], [PERIOD, 0.0, 0.0], [0.0, 0.0, PERIOD]], np.float32)
    uvs = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], np.float32)
    return uv_derivatives_on_triangle(*tri, *uvs, o, d, ddx, ddy)


def make_renderers(size, texels):
    level0 = jnp.asarray(texels)

    def bilinear_no_mips():
        uv, _, _ = frame_uv(size)
        return bilinear(level0, uv[..., 0] * TEX - 0.5, uv[..., 1] * TEX - 0.5, wrap_x=True, wrap_y=True)[..., 0]

    def filtered(K):
        tex = Texture.from_image(texels, srgb=False, max_anisotropy=K)

        def render(tex):
            uv, dx, dy = frame_uv(size)
            return sample(tex, uv, dx, dy)[..., 0]

        f = jax.jit(render)
        return lambda: f(tex)

    return {
        "(a) bilinear, no mips": jax.jit(bilinear_no_mips),
        "(b) trilinear": filtered(1),
        "(c) aniso 4 taps": filtered(4),
        "(c) aniso 8 taps": filtered(8),
        "(c) aniso 16 taps": filtered(16),
    }


def timed_round_robin(fns, repeats):
    """{name: (image, best seconds, median seconds)}: every program compiled and run once, then
    `repeats` rounds that each time every program once (interleaved, so a slow spell of a shared
    machine hits all of them alike)."""
    out = {name: np.asarray(jax.block_until_ready(fn()), np.float64) for name, fn in fns.items()}
    ts = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            ts[name].append(time.perf_counter() - t0)
    return {name: (out[name], min(ts[name]), float(np.median(ts[name]))) for name in fns}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--limit", type=float, default=8.0, help="reference sub-sample size, texels")
    args = ap.parse_args()
    size = args.size

    ok, dist = scored_pixels(size)
    t0 = time.perf_counter()
    ref = reference(size, args.limit)
    t_ref = time.perf_counter() - t0
    ref_coarse = reference(size, 2 * args.limit)  # the reference's own error, estimated
    t0 = time.perf_counter()
    point64 = point_sampled(size, 8)
    t_point = time.perf_counter() - t0
    bands = [(name, ok & (dist >= lo) & (dist < hi)) for name, lo, hi in BANDS]

    results = [
        (f"reference, {2 * args.limit:g}-texel sub-samples", ref_coarse, np.nan, np.nan),
        ("64-spp point-sampled bilinear (NumPy)", point64, t_point, t_point),
    ]
    for name, (img, best, med) in timed_round_robin(make_renderers(size, checker_texels()), args.repeats).items():
        results.append((name, np.where(ok, img, 0.0), best, med))

    print(
        f"{size}x{size} pixels, camera {HEIGHT:g} above the plane, pitch {PITCH_DEG:g} deg down, fov {FOV_DEG:g} deg; "
        f"{TEX}^2 checker ({SQUARE}-texel squares), {TEX / PERIOD:.0f} texels per unit; JAX on {jax.devices()[0].platform}"
    )
    print(f"reference: box-filtered sub-samples of <= {args.limit:g} texels (NumPy float64, {t_ref:.1f} s)")
    for name, m in bands:
        print(f"  {name:4s}: {m.sum():6d} px, centre distance {dist[m].min():7.2f} .. {dist[m].max():7.2f}")
    print(f"  scored: {ok.sum()} px (the rest see the sky or the horizon)\n")
    head = f"{'method':40s}" + "".join(f"{b + ' RMSE':>10s}{b + ' max':>9s}" for b, _ in bands)
    head += f"{'all RMSE':>10s}{'ms best':>9s}{'ms med':>9s}"
    print(head)
    print("-" * len(head))
    for name, img, best, med in results:
        err = img - ref
        row = f"{name:40s}"
        for _, m in bands:
            row += f"{np.sqrt(np.mean(err[m] ** 2)):10.4f}{np.max(np.abs(err[m])):9.4f}"
        row += f"{np.sqrt(np.mean(err[ok] ** 2)):10.4f}"
        row += f"{best * 1e3:9.1f}{med * 1e3:9.1f}" if np.isfinite(best) else ""
        print(row)


if __name__ == "__main__":
    main()
