"""Diffuse irradiance with the sun split out (issue 11): SH9 / exact irradiance of the residual plus
the extracted discs' exact cap irradiance, against the exact (float64) irradiance of the whole
environment, at the 6 x 32^2 texel directions. Relative error per direction (sum over RGB),
mean and max.

Run: python examples/extract_irradiance_error.py [ENV ...]   (default: the procedural sky+sun and,
if present, ../shared/data/spruit_sunrise_1k.hdr; 64^2 faces)
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import jax
import numpy as np

import jaxpbr as jp
from jaxpbr.ibl.cubeio import load_environment
from jaxpbr.ibl.cubemap import texel_directions
from jaxpbr.ibl.diffuse import irradiance_at
from jaxpbr.ibl.extract import extract_lights


def disc_irradiance(lights, d):
    """E/pi of the disc lights at unit normals d (N, 3), (N, 3)."""
    out = np.zeros((len(d), 3))
    for light in lights:
        s = math.sin(float(light.angular_radius))
        towards = -np.asarray(light.direction, np.float64)
        radiance = np.asarray(light.color, np.float64) * float(light.intensity) / (math.pi * s * s)
        out += np.asarray(jp.shading.lights.cap_irradiance(d @ towards, s))[:, None] * radiance / math.pi
    return out


def main(names):
    d = texel_directions(32).reshape(-1, 3)
    for name in names:
        env = load_environment([name], face_size=64)
        ex = extract_lights(env)
        with jax.enable_x64(True):
            ref = np.asarray(irradiance_at(jp.Cubemap((np.asarray(env.levels[0], np.float64),)), d, method="exact", chunk=16))
        flat = lambda c: np.asarray(c.levels[0], np.float64).reshape(-1, 3)  # noqa: E731
        discs = disc_irradiance(ex.lights, d)

        def err(x):
            e = np.abs(x - ref).sum(1) / np.abs(ref).sum(1)
            return f"{100 * e.mean():.2f} / {100 * e.max():.1f} %"

        print(
            f"{Path(name).name}: {len(ex.lights)} light(s); SH9 of the whole map {err(flat(jp.irradiance(env, size=32, method='sh9')))}; "
            f"SH9 of the residual + discs {err(flat(jp.irradiance(ex.residual, size=32, method='sh9')) + discs)}; "
            f"exact residual + discs {err(flat(jp.irradiance(ex.residual, size=32)) + discs)}"
        )


if __name__ == "__main__":
    default = ["procedural:sky"]
    spruit = Path(__file__).resolve().parents[2] / "shared" / "data" / "spruit_sunrise_1k.hdr"
    if spruit.is_file():
        default.append(str(spruit))
    main(sys.argv[1:] or default)
