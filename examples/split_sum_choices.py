"""The split sum's diffuse weight and lookup direction, measured against the float64 reference.

White spheres (dielectric and metal, roughness 1/6 ... 1) seen orthographically, IBL term only
(the residual environment's split sum plus the suns split out of it as disc lights, as `render`
does), float32 with the default precomputes, against `reference_render.reference_ibl` (every
texel of the environment, float64). Printed per environment and material: the mean relative
error of luminance over the sphere and, in brackets, its bias (signed), for

* "plain": the diffuse term c_diff Ebar(n) and the prefiltered map read at the mirror direction R;
* "jaxpbr": `shade_ibl` as it is: the diffuse term times the (1 - F) of the glTF BRDF averaged over
  the Lambertian lobe, 0.96 (1 - C(n.v)), and the map read at the dominant direction;
* "exact LD" (metals): the same lookup direction with the float64 GGX-prefiltered radiance
  (`specular.prefilter_reference`) in place of the map: what the split sum's factorisation
  itself costs, whatever the precompute.

Environments: the procedural sky with its 3000-radiance sun (always) and the shared HDR
spruit_sunrise_1k.hdr when ../shared/data holds it (or the path given with --hdr).

Run: python examples/split_sum_choices.py [--face-size 64] [--pixels 48] [--hdr PATH]
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxpbr as jp
from jaxpbr.cli.report_render import sphere_gbuffer
from jaxpbr.ibl import extract
from jaxpbr.ibl.cubeio import load_environment
from jaxpbr.ibl.cubemap import Cubemap
from jaxpbr.ibl.reference_render import reference_ibl_from_terms, reference_ibl_terms
from jaxpbr.ibl.shade import MIN_N_DOT_V, specular_dominant_direction, split_sum_weights
from jaxpbr.ibl.specular import lookup_of, prefilter_reference, roughness_to_lod
from jaxpbr.shading.lut import lut_lookup
from jaxpbr.shading.shipped_luts import brdf_lut

ROUGHNESS = (1 / 6, 2 / 6, 3 / 6, 4 / 6, 5 / 6, 1.0)
LUMA = np.array([0.2126, 0.7152, 0.0722])
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "spruit_sunrise_1k.hdr"


def plain(n, v, m, irr, pre, lut):
    """c_diff Ebar(n) + LD(R, r) (F0 A + B): the split sum without the diffuse Fresnel factor,
    looked up at the mirror direction."""
    nov_raw = jnp.sum(n * v, -1)
    R = 2 * nov_raw[..., None] * n - v
    nov = jnp.clip(nov_raw, MIN_N_DOT_V, 1.0)
    r = jnp.broadcast_to(m.roughness, nov.shape)
    ab = lut_lookup(lut, nov, r)
    M, mapping, blend = lookup_of(pre)
    ld = pre.sample(R, roughness_to_lod(r, M, mapping=mapping, lod_blend=blend))
    fss, _ = split_sum_weights(m.f0(), ab[..., 0], ab[..., 1])
    return ld * fss + m.diffuse_color() * irr.sample(n)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--face-size", type=int, default=64)
    ap.add_argument("--pixels", type=int, default=48)
    ap.add_argument("--hdr", default=str(SHARED) if SHARED.exists() else None)
    args = ap.parse_args(argv)
    envs = {"sky+sun": jp.envs.sky_with_sun_cubemap(args.face_size)}
    if args.hdr:
        envs[Path(args.hdr).stem] = load_environment([args.hdr], face_size=args.face_size)
    mask, n, v, p = sphere_gbuffer(args.pixels)
    n32, v32, p32 = (jnp.asarray(a, jnp.float32) for a in (n, v, p))
    lut = brdf_lut(size=128)
    print(f"IBL term, white spheres, {args.pixels}^2 px, environments at {args.face_size}^2; mean relative error of luminance (bias)")
    for name, env in envs.items():
        env = Cubemap((jnp.asarray(env.levels[0], jnp.float32),), env.metadata)
        ex = extract.extract_lights(env)
        irr, pre = jp.irradiance(ex.residual, size=32), jp.prefilter(ex.residual)
        discs = list(ex.lights)
        M, mapping, blend = lookup_of(pre)
        rows = {}
        for r in ROUGHNESS:
            terms = reference_ibl_terms(n, v, r, env)
            for metallic in (0.0, 1.0):
                m = jp.Material(base_color=jnp.ones(3, jnp.float32), metallic=jnp.float32(metallic), roughness=jnp.float32(r))
                with jax.enable_x64(True):
                    ref = reference_ibl_from_terms(terms, jp.Material(base_color=jnp.ones(3), metallic=jnp.float64(metallic), roughness=jnp.float64(r)))
                suns = 0.0
                if discs:
                    dark = m.replace(emissive=jnp.zeros_like(m.emissive))
                    suns = np.asarray(jp.shade_direct(p32, n32, v32, dark, discs, disc_lights=True), np.float64)
                variants = {
                    "plain": np.asarray(plain(n32, v32, m, irr, pre, lut), np.float64) + suns,
                    "jaxpbr": np.asarray(jp.shade_ibl(n32, v32, m, irr, pre, lut), np.float64) + suns,
                }
                if metallic == 1.0:
                    R = 2 * n[:, 2:3] * n - v
                    d = np.asarray(specular_dominant_direction(jnp.asarray(n), jnp.asarray(R), jnp.full(len(n), r)))
                    with jax.enable_x64(True):
                        ld = np.asarray(prefilter_reference(ex.residual, jnp.asarray(d), r))
                    ab = np.asarray(lut_lookup(lut, jnp.asarray(np.clip(n[:, 2], MIN_N_DOT_V, 1), jnp.float32), jnp.full(len(n), r, jnp.float32)))
                    variants["exact LD"] = ld * (ab[:, :1] + ab[:, 1:]) + suns
                for k, out in variants.items():
                    diff = (out - ref) @ LUMA
                    den = (ref @ LUMA).sum()
                    rows[(metallic, k, r)] = (np.abs(diff).sum() / den, diff.sum() / den)
        print(f"\n{name} ({len(discs)} sun(s) split out)")
        print("| material | variant | " + " | ".join(f"r = {r:.2f}" for r in ROUGHNESS) + " |")
        print("|---|---|" + "---|" * len(ROUGHNESS))
        for metallic in (0.0, 1.0):
            for k in ("plain", "jaxpbr", "exact LD"):
                if (metallic, k, ROUGHNESS[0]) in rows:
                    cells = " | ".join(f"{100 * rows[(metallic, k, r)][0]:.2f} ({100 * rows[(metallic, k, r)][1]:+.2f}) %" for r in ROUGHNESS)
                    print(f"| {'metal' if metallic else 'dielectric'} | {k} | {cells} |")


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        main()
