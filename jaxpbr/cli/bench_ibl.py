"""`jaxpbr bench ibl`: IBL precompute timings with errors, next to the peers' recipes run side by side
in the same process (JIT compile reported apart; run times are the best of repeated calls).

* prefilter (full mip chain): jaxpbr's default (FIS with per-level sample counts + the brightest
  texels convolved exactly) vs plain filtered importance sampling with a fixed sample count on every
  level (Filament cmgen's recipe: GGX NDF sampling, Hammersley, PDF-based source mip with K = 4).
* BRDF LUT 256^2: the converged quadrature vs the classic 1024-sample Hammersley estimate (Karis).
* irradiance 32^2: exact convolution on the default 64^2 moment level vs the full-resolution
  exact convolution (the reference itself) and SH9.
Errors are against the float64 references of `jaxpbr.ibl.measure` (sampled texels for the cubes,
every texel for the LUT).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..ibl.cubeio import load_environment
from ..ibl.diffuse import irradiance
from ..ibl.measure import irradiance_error, lut_error, prefilter_error, summarize
from ..ibl.specular import prefilter
from ..shading.brdf_terms import schlick_weight, v_smith_correlated
from ..shading.lut import compute_brdf_lut
from ..shading.sampling import hammersley, sample_ggx_h
from ._common import positive_int_arg, require_environment
from .timing import time_calls, to_host

__all__ = ["add_command", "bench_ibl", "cmd_bench_ibl", "hammersley_lut"]


@jax.jit
def _hammersley_lut_kernel(mu, alpha, xi):
    """Karis 2013 `IntegrateBRDF` (height-correlated V form): (A, B) per (mu, alpha) from the
    same N Hammersley points. mu, alpha (T,); xi (N, 2)."""
    h = sample_ggx_h(xi[None, :, :], alpha[:, None])  # (T, N, 3)
    cos_h = h[..., 2]
    v = jnp.stack([jnp.sqrt(1.0 - mu * mu), jnp.zeros_like(mu), mu], -1)[:, None, :]
    voh = jnp.sum(v * h, -1)
    nol = 2.0 * voh * cos_h - mu[:, None]
    ok = nol > 0
    V = v_smith_correlated(mu[:, None], jnp.where(ok, nol, 1.0), alpha[:, None])
    w = jnp.where(ok, 4.0 * V * nol * voh / cos_h, 0.0)
    fc = schlick_weight(voh)
    return jnp.stack([jnp.mean(w * (1.0 - fc), -1), jnp.mean(w * fc, -1)], -1)


def hammersley_lut(size: int, samples: int = 1024) -> np.ndarray:
    """The peers' LUT: `samples` Hammersley points of GGX NDF sampling per texel (correlated V)."""
    c = (np.arange(size) + 0.5) / size
    rr, mm = np.meshgrid(c, c, indexing="ij")
    xi = hammersley(samples, jnp.float32)
    out = _hammersley_lut_kernel(jnp.asarray(mm.reshape(-1), jnp.float32), jnp.asarray(rr.reshape(-1) ** 2, jnp.float32), xi)
    return np.asarray(out).reshape(size, size, 2)


def bench_ibl(env, env_name: str, *, baseline_samples: int = 4096, texels_per_level: int = 512) -> str:
    lines = [f"jaxpbr bench ibl: {env_name}, {env.face_size}^2 faces, device {jax.devices()[0].device_kind}"]

    # prefilter --------------------------------------------------------------------------------
    pre, _t = time_calls(lambda: to_host(prefilter(env)), rounds=2)
    first, t_ours = _t.first, _t.best
    e_ours = summarize(prefilter_error(env, pre, texels_per_level=texels_per_level))
    M = pre.num_levels
    lines += [
        f"prefilter {pre.face_size}^2, {M} mips (error vs float64 reference at <= {texels_per_level} texels/level; worst level):",
        f"  jaxpbr default ({pre.metadata['fis_samples']} samples, {pre.metadata['exact_texels']} exact texels): "
        f"{t_ours:.2f} s (compile {max(0.0, first - t_ours):.2f} s), mean {100 * e_ours['mean']:.2f} %, worst texel {100 * e_ours['max']:.2f} %",
    ]
    for n in sorted({256, baseline_samples}):
        base, _t = time_calls(lambda: to_host(prefilter(env, samples=[n] * M, exact_texels=0, lod_bias=1.0)), rounds=1)
        _, t_base = _t.first, _t.best
        e_base = summarize(prefilter_error(env, base, texels_per_level=texels_per_level))
        lines += [
            f"  baseline plain FIS (Filament recipe: NDF sampling, K=4), {n} samples every level: {t_base:.2f} s, "
            f"mean {100 * e_base['mean']:.2f} %, worst texel {100 * e_base['max']:.2f} %",
            f"    -> run time ratio baseline/default {t_base / t_ours:.2f}; worst-texel error ratio baseline/default "
            f"{e_base['max'] / max(e_ours['max'], 1e-12):.2f}; mean-error ratio {e_base['mean'] / max(e_ours['mean'], 1e-12):.2f}",
        ]

    # LUT --------------------------------------------------------------------------------------
    lut, _t = time_calls(lambda: np.asarray(compute_brdf_lut(size=256)), rounds=2)
    lfirst, t_lut = _t.first, _t.best
    e_lut = lut_error(lut, smith="correlated", texels=None)
    hl, _t = time_calls(lambda: hammersley_lut(256, 1024), rounds=2)
    _, t_h = _t.first, _t.best
    e_h = lut_error(hl, smith="correlated", texels=None)
    lines += [
        "BRDF LUT 256^2, height-correlated (max |error| at every texel vs float64 quadrature):",
        f"  jaxpbr converged quadrature: {t_lut:.2f} s (compile {max(0.0, lfirst - t_lut):.2f} s), max {e_lut['max']:.1e}, mean {e_lut['mean']:.1e}",
        f"  baseline 1024-sample Hammersley: {t_h:.2f} s, max {e_h['max']:.1e}, mean {e_h['mean']:.1e}",
        f"  -> run time ratio baseline/jaxpbr {t_h / t_lut:.2f}; max-error ratio baseline/jaxpbr {e_h['max'] / max(e_lut['max'], 1e-15):.0f}",
    ]

    # irradiance -------------------------------------------------------------------------------
    irr, _t = time_calls(lambda: to_host(irradiance(env, size=32)), rounds=2)
    ifirst, t_irr = _t.first, _t.best
    e_irr = irradiance_error(env, irr, texels=1024)
    full, _t = time_calls(lambda: to_host(irradiance(env, size=32, source_size=env.face_size)), rounds=1)
    _, t_full = _t.first, _t.best
    sh, _t = time_calls(lambda: to_host(irradiance(env, size=32, method="sh9")), rounds=2)
    _, t_sh = _t.first, _t.best
    e_sh = irradiance_error(env, sh, texels=1024)
    lines += [
        "irradiance 32^2 (relative error vs full-resolution exact convolution in float64):",
        f"  jaxpbr exact (64^2 moment level): {t_irr:.2f} s (compile {max(0.0, ifirst - t_irr):.2f} s), mean {100 * e_irr['mean']:.4f} %, max {100 * e_irr['max']:.4f} %",
        f"  full-resolution exact ({env.face_size}^2 source, float32): {t_full:.2f} s -> {t_full / t_irr:.1f}x slower",
        f"  SH9: {t_sh:.3f} s, mean {100 * e_sh['mean']:.2f} %, max {100 * e_sh['max']:.2f} %",
    ]
    return "\n".join(lines)


def add_command(bsub) -> None:
    """Register `jaxpbr bench ibl`."""
    p = bsub.add_parser("ibl", help="IBL precompute timings and errors vs a Filament-style FIS baseline, side by side")
    p.add_argument("--env", default=None, help="equirect panorama (default: the procedural sky+sun)")
    p.add_argument("--face-size", type=positive_int_arg, default=256)
    p.add_argument("--baseline-samples", type=positive_int_arg, default=4096, help="samples of the plain-FIS baseline (default: %(default)s)")
    p.set_defaults(func=cmd_bench_ibl)


def cmd_bench_ibl(args) -> int:
    require_environment(args.face_size, procedural=not args.env)
    require_environment(args.face_size, procedural=not args.env, samples=args.baseline_samples, samples_flag="--baseline-samples")
    env = load_environment([args.env] if args.env else ["procedural:sky"], face_size=args.face_size)
    print(bench_ibl(env, args.env or "procedural sky+sun", baseline_samples=args.baseline_samples))
    return 0
