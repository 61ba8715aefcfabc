"""How small may the prefiltered chain's last mip be, and how should the lookup blend levels?

The measurement behind issue 11, item 1 (a probe, not yet a default). Oracle: for a linear
environment L(w) = a + b (w . d) the prefiltered value is exactly LD(R, r) = a + b c(alpha) (R . d)
with c(alpha) = int K (R.l)^2 dl / int K (R.l) dl, K = D(h) (R.l)+ (the lobe is symmetric about R).
Each chain below holds that closed form at its texel centres (no sampling error), so what is
measured is the chain itself: the coarse faces (a 2x2 face cannot hold the convolved signal) and
the blend between two levels' roughness. Lookups at 600 random directions and roughnesses (60 at
r = 1 and 60 at r = 0.85), relative error mean / max in %.

Blends: "linear" (lod = r (M - 1), glTF viewer / Khronos sampler), "quadratic" (Filament), and
"blur": the same levels as "linear", the weight between two levels linear in c(alpha(r)) instead
of r, which is exact for a linear environment between levels.

"blur" is what became the default lookup (`lod_blend="mean_cosine"`); the product's version of this
sweep is `jaxpbr report precompute --chain-only`.

Run: python examples/prefilter_chain_sweep.py   (needs scipy: pip install 'jaxpbr[test]')
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from scipy import integrate

from jaxpbr.ibl.cubemap import Cubemap, texel_directions
from jaxpbr.ibl.specular import level_roughness, roughness_to_lod

jax.config.update("jax_enable_x64", True)

A, B = 1.0, 0.8
DIR = np.array([0.2, 0.5, -0.7]) / np.linalg.norm([0.2, 0.5, -0.7])


def d_ggx(cos_h, alpha):
    a2 = alpha * alpha
    return a2 / (math.pi * (cos_h * cos_h * (a2 - 1.0) + 1.0) ** 2)


def lobe_moment(alpha, power):
    """2 pi int_0^{pi/2} D(h) (R.l)^power sin dtheta_l, the l-space moment of the lobe about R."""
    f = lambda t: d_ggx(math.cos(t / 2), alpha) * math.cos(t) ** power * math.sin(t)  # noqa: E731
    pts = [p for p in (alpha, 2 * alpha, 4 * alpha, 8 * alpha) if p < math.pi / 2]
    return integrate.quad(f, 0, math.pi / 2, points=pts or None, epsabs=0, epsrel=1e-11, limit=400)[0]


def c_alpha(alpha):
    return 1.0 if alpha == 0 else lobe_moment(alpha, 2) / lobe_moment(alpha, 1)


def chain(S, floor, mapping):
    """The closed-form chain from S^2 down to floor^2 faces, and its level count M."""
    M = int(round(math.log2(S / floor))) + 1
    r = level_roughness(M, mapping=mapping)
    levels = [jnp.asarray((A + B * c_alpha(r[m] ** 2) * (texel_directions(S >> m) @ DIR))[..., None]) for m in range(M)]
    return Cubemap(levels), M


def main():
    rng = np.random.default_rng(0)
    n = 600
    R = rng.normal(size=(n, 3))
    R /= np.linalg.norm(R, axis=1, keepdims=True)
    rs = rng.uniform(0, 1, n)
    rs[:60], rs[60:120] = 1.0, 0.85
    truth = A + B * np.array([c_alpha(r * r) for r in rs]) * (R @ DIR)
    grid = np.linspace(0, 1, 2049)
    c_grid = np.array([c_alpha(r * r) for r in grid])

    def show(name, S, floor, M, got):
        e = 100 * np.abs(got - truth) / truth

        def band(lo, hi):
            k = (rs >= lo) & (rs <= hi)
            return f"{e[k].mean():.2f}/{e[k].max():.2f}"

        print(f"{name:9s} {S:3d}^2 to {floor:2d}^2 M={M:2d}  all {e.mean():.2f}/{e.max():.2f}  r=1 {band(1, 1)}  "
              f"r=0.85 {band(0.85, 0.85)}  r<=0.5 {band(0, 0.5)}  0.5-0.8 {band(0.5, 0.8)}")

    for S in (64, 128, 256):
        for floor in (1, 2, 4, 8, 16, 32):
            if floor > S // 4:
                continue
            for mapping in ("linear", "quadratic", "blur"):
                cube, M = chain(S, floor, "linear" if mapping == "blur" else mapping)
                if mapping == "blur":
                    rm = level_roughness(M)
                    cm, cr = np.interp(rm, grid, c_grid), np.interp(rs, grid, c_grid)
                    m = np.clip(np.searchsorted(rm, rs, side="right") - 1, 0, M - 2)
                    lod = jnp.asarray(m + (cm[m] - cr) / (cm[m] - cm[m + 1]))
                else:
                    lod = roughness_to_lod(jnp.asarray(rs), M, mapping=mapping, lod_blend="roughness")
                show(mapping, S, floor, M, np.asarray(cube.sample(jnp.asarray(R), lod))[:, 0])


if __name__ == "__main__":
    main()
