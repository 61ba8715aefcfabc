"""The prefilter near a wide sun, against an independent float64 brute force.

The environment: 0.5 + a smooth Gaussian sun (standard deviation 4 degrees, peak 400), built here
in NumPy (each texel the solid-angle-weighted mean of the function over 4 x 4 sub-texels). The
oracle: LD(R, r) = sum L K Omega / sum K Omega over 4 x 4 sub-texels of every texel of the source
(K = D(h) (R.l)+, n = v = R, the definition of docs/conventions.md), with the sub-texels' exact
solid angles, in NumPy float64 -- no jaxpbr code but the cube-face convention, which is checked
against `texel_directions` first.

Measured at every level m >= 1 of the default chain, on the texels nearest the sun and on random
ones (goal: mean <= 0.5 %, worst <= 2 % in each group). The bright texels convolved exactly used to
be 256 per 256^2 of face area, which left most of such a sun in the sampled part (5795 texels above
4x the mean at 256^2): on random texels, worst 17.8 % at r = 0.25 (mean 3.3 %), 6.7 % at r = 0.5,
6.5 % at r = 1 (the 256^2 -> 128^2 case, `slow`); the 128^2 -> 64^2 default variant: worst 3.0 % at
r = 0.25 (mean 0.92 %), 4.1 % at r = 1. With 8192 per 256^2: 0.88 % / 0.19 % and 0.22 % / 0.06 %
at worst.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxpbr.ibl.cubemap import Cubemap, texel_directions
from jaxpbr.ibl.specular import default_num_levels, level_roughness, prefilter

SUN = np.array([0.3, 0.6, 0.5]) / np.linalg.norm([0.3, 0.6, 0.5])
SIGMA = math.radians(4.0)
PEAK, BASE = 400.0, 0.5
Q = 4  # sub-texels per texel side, in the environment and in the oracle


def face_dirs(face: int, s, t):
    """Unnormalised direction of face coordinates s, t in [0, 1] (OpenGL major-axis table, faces
    +X -X +Y -Y +Z -Z)."""
    a, b = 2.0 * s - 1.0, 2.0 * t - 1.0
    one = np.ones_like(a)
    return np.stack(
        [
            (one, -b, -a),
            (-one, -b, a),
            (a, one, b),
            (a, -one, -b),
            (a, -b, one),
            (-a, -b, -one),
        ][face],
        -1,
    )


def corner_area(x, y):
    return np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))


def subtexels(S: int, q: int):
    """Directions (6, S, S, q*q, 3) and exact solid angles (6, S, S, q*q) of every sub-texel."""
    n = S * q
    e = np.linspace(-1.0, 1.0, n + 1)  # sub-texel edges in [-1, 1]
    c = 0.5 * (e[:-1] + e[1:])
    x0, x1 = np.meshgrid(e[:-1], e[:-1], indexing="xy"), np.meshgrid(e[1:], e[1:], indexing="xy")
    om = corner_area(x0[0], x0[1]) - corner_area(x0[0], x1[1]) - corner_area(x1[0], x0[1]) + corner_area(x1[0], x1[1])
    st = (c + 1.0) / 2.0
    ss, tt = np.meshgrid(st, st, indexing="xy")  # [row (t), column (s)]
    d = np.stack([face_dirs(f, ss, tt) for f in range(6)])
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    # (6, n, n, ...) -> (6, S, S, q*q, ...): rows i*q + a, columns j*q + b
    d = d.reshape(6, S, q, S, q, 3).transpose(0, 1, 3, 2, 4, 5).reshape(6, S, S, q * q, 3)
    om = np.broadcast_to(np.abs(om), (6, n, n)).reshape(6, S, q, S, q).transpose(0, 1, 3, 2, 4).reshape(6, S, S, q * q)
    return d, om


def centres(S: int):
    s = (np.arange(S) + 0.5) / S
    ss, tt = np.meshgrid(s, s, indexing="xy")
    d = np.stack([face_dirs(f, ss, tt) for f in range(6)])
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def radiance(d):
    ang = np.arccos(np.clip(d @ SUN, -1.0, 1.0))
    return BASE + PEAK * np.exp(-0.5 * (ang / SIGMA) ** 2)


def sun_cube(S: int) -> np.ndarray:
    """(6, S, S) float32 texel means of the radiance."""
    d, om = subtexels(S, Q)
    return (np.sum(radiance(d) * om, -1) / np.sum(om, -1)).astype(np.float32)


def oracle(L: np.ndarray, R: np.ndarray, roughness: float) -> np.ndarray:
    """float64 LD at unit directions R (n, 3) of the piecewise-constant cube L (6, S, S)."""
    S = L.shape[1]
    d, om = subtexels(S, Q)
    d = d.reshape(-1, 3)
    w = om.reshape(-1)
    Lw = np.repeat(np.asarray(L, np.float64).reshape(-1), Q * Q) * w
    a2 = roughness**4
    out = []
    for Rc in np.array_split(R, max(1, len(R) // 8)):
        c = Rc @ d.T
        k = np.maximum(c, 0.0) / (0.5 * (1.0 - c) + 0.5 * (1.0 + c) * a2) ** 2  # D up to constants
        out.append((k @ Lw) / (k @ w))
    return np.concatenate(out)


def test_face_convention_matches_jaxpbr():
    for S in (4, 16):
        np.testing.assert_allclose(centres(S), np.asarray(texel_directions(S), np.float64), atol=1e-6)


def sun_errors(S0: int, size: int, near: int = 16, random: int = 48, seed: int = 0):
    """Per level m >= 1 of the default chain of a size^2 prefilter of the S0^2 sun cube: (r,
    near-sun relative errors, random-texel relative errors)."""
    L = sun_cube(S0)
    pre = prefilter(Cubemap(jnp.asarray(L[..., None])), size=size)
    M = default_num_levels(size)
    assert pre.num_levels == M
    rough = level_roughness(M)
    rng = np.random.default_rng(seed)
    out = []
    for m in range(1, M):
        Sm = size >> m
        d = centres(Sm).reshape(-1, 3)
        got = np.asarray(pre.levels[m], np.float64).reshape(-1)
        sel_near = np.argsort(-(d @ SUN))[:near]
        sel_rand = rng.choice(len(d), min(random, len(d)), replace=False)
        errs = []
        for sel in (sel_near, sel_rand):
            ref = oracle(L, d[sel], float(rough[m]))
            errs.append(np.abs(got[sel] - ref) / ref)
        out.append((float(rough[m]), *errs))
    return out


def check(rows):
    table = "; ".join(
        f"r={r:.2f}: near mean {100 * a.mean():.2f} % worst {100 * a.max():.2f} %, random mean {100 * b.mean():.2f} % worst {100 * b.max():.2f} %"
        for r, a, b in rows
    )
    for r, a, b in rows:
        for e in (a, b):
            assert e.mean() <= 0.005 and e.max() <= 0.02, table


def test_prefilter_near_a_wide_sun():
    """128^2 sun cube, prefiltered to 64^2 (default chain 64^2 .. 4^2, r = 0.25 .. 1)."""
    check(sun_errors(128, 64))


@pytest.mark.slow
def test_prefilter_near_a_wide_sun_256():
    """The case as measured: a 256^2 cube prefiltered to 128^2 (128^2 .. 8^2)."""
    check(sun_errors(256, 128, near=48, random=160))


def test_report_precompute_has_the_wide_sun_case():
    """`jaxpbr report precompute` measures the case per level, near the sun and at random texels."""
    from jaxpbr.cli import report_precompute as report

    rows = report.sun_rows(64, 32, near=8, random=16, log=lambda m: None)
    M = default_num_levels(32)
    assert len(rows) == 2 * (M - 1) and {r["what"] for r in rows} == {"prefilter (wide sun)"}
    assert all(r["mean"] <= 0.005 and r["max"] <= 0.02 for r in rows), [(r["variant"], r["mean"], r["max"]) for r in rows]
    md = report.markdown(rows)
    assert "level 1, r = 0.25, near the sun" in md and f"level {M - 1}, r = 1.00, random" in md
