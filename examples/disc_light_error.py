"""Error of the analytic disc light (`DirectionalLight(angular_radius=...)` in `shade_direct`)
against quadrature over the disc, per roughness (issue 11, item 3).

Reference: integral over the disc of f_r(v, l) L max(n.l, 0) dl, float64, with the same BRDF
(`jaxpbr.brdf`, roughness floored at MIN_ROUGHNESS as `shade_direct` does), on a polar grid
(Gauss-Legendre in the cosine of the angle from the disc centre, uniform in azimuth) fine enough
to resolve the sharpest lobe. Configurations: random unit n, v (n.v > 0.05) and the disc centre
within 60 degrees of the mirror direction, half of them with the disc within 1.5 sigma of R
(where the specular highlight is). Printed per angular radius and roughness: the mean and
largest relative error of the total radiance over the configurations with a non-negligible
reference, and the same for the specular-dominated metal (base colour 1, metallic 1).

Run: python examples/disc_light_error.py [--quick]
"""

from __future__ import annotations

import math
import sys

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from jaxpbr import DirectionalLight, Material, brdf, shade_direct  # noqa: E402

ROUGHNESS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0)
RADII_DEG = (0.27, 2.0, 5.0)


def basis(d):
    a = np.where(np.abs(d[..., :1]) < 0.9, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    t = np.cross(d, a)
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    return t, np.cross(d, t)


def disc_directions(d, sigma, n_rad, n_az):
    """Quadrature nodes l (n_rad * n_az, 3) and weights (sum = disc solid angle) over the cap."""
    x, w = np.polynomial.legendre.leggauss(n_rad)
    cmin = math.cos(sigma)
    cos_t = 0.5 * (x + 1) * (1 - cmin) + cmin
    wc = 0.5 * w * (1 - cmin)
    phi = (np.arange(n_az) + 0.5) / n_az * 2 * math.pi
    sin_t = np.sqrt(1 - cos_t**2)
    t, b = basis(d)
    l = (cos_t[:, None, None] * d + sin_t[:, None, None] * (np.cos(phi)[None, :, None] * t + np.sin(phi)[None, :, None] * b)).reshape(-1, 3)
    wt = np.repeat(wc, n_az) * (2 * math.pi / n_az)
    return l, wt


def configs(k, sigma, rng):
    n = rng.normal(size=(k, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    out = []
    while len(out) < k:
        i = len(out)
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
        if v @ n[i] < 0.05:
            continue
        R = 2 * (v @ n[i]) * n[i] - v
        near = i % 2 == 0
        ang = rng.uniform(0, 1.5 * sigma) if near else rng.uniform(0, math.radians(60))
        t, b = basis(R)
        phi = rng.uniform(0, 2 * math.pi)
        d = math.cos(ang) * R + math.sin(ang) * (math.cos(phi) * t + math.sin(phi) * b)
        out.append((n[i], v, d))
    return out


def main(quick=False):
    rng = np.random.default_rng(1)
    k = 40 if quick else 120
    f64 = jnp.float64
    for deg in RADII_DEG:
        sigma = math.radians(deg)
        cs = configs(k, sigma, rng)
        n = np.array([c[0] for c in cs])
        v = np.array([c[1] for c in cs])
        d = np.array([c[2] for c in cs])
        E = 1.0  # perpendicular irradiance (lux); radiance L = E / (pi sin^2 sigma)
        L = E / (math.pi * math.sin(sigma) ** 2)
        for label, base, metal in (("dielectric", (0.8, 0.5, 0.3), 0.0), ("metal", (1.0, 1.0, 1.0), 1.0)):
            row = []
            for r in ROUGHNESS:
                m = Material(base_color=jnp.asarray(base, f64), metallic=jnp.asarray(metal, f64), roughness=jnp.asarray(r, f64))
                one = lambda n_, v_, d_, m=m: shade_direct(n_, n_, v_, m, DirectionalLight(direction=-d_, intensity=jnp.asarray(E, f64), angular_radius=jnp.asarray(sigma, f64)))  # noqa: E731
                got = np.asarray(jax.vmap(one)(jnp.asarray(n, f64), jnp.asarray(v, f64), jnp.asarray(d, f64)))
                ref = np.zeros_like(got)
                n_rad = 96 if quick else 256
                for i in range(k):
                    l, w = disc_directions(d[i], sigma, n_rad, 2 * n_rad)
                    f = np.asarray(brdf(jnp.asarray(n[i], f64), jnp.asarray(v[i], f64), jnp.asarray(l, f64), m))
                    ref[i] = (f * (L * np.maximum(l @ n[i], 0.0) * w)[:, None]).sum(0)
                diff = np.abs(got - ref).sum(1)
                keep = ref.sum(1) > 1e-2 * ref.sum(1).max()
                rel = diff[keep] / ref.sum(1)[keep]
                row.append(f"{r:g}: {100 * diff.sum() / ref.sum():.2f}/{100 * rel.max():.0f}")
            print(f"sigma {deg:g} deg, {label:10s} " + "  ".join(row), flush=True)


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
