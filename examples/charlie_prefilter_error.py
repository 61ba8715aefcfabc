"""Error and run time of the Charlie-prefiltered sheen chain (`jaxpbr.sheen_prefilter`).

For each environment (the procedural sky with its 3000-radiance sun at 256^2, and the HDRs of
../shared/data at 256^2 when present), the float64 reference `charlie_reference` (every texel of
the full 256^2 environment, sub-texel supersampled) is computed at 48 random directions for each
of 10 random sheen roughnesses in [0, 1] and for the 5 roughnesses r = 0, .25, .5, .75, 1; then
each fast configuration (output size / source size / levels) is looked up there with
`charlie_lookup` ("mean_cosine" blend, and the engines' "roughness" blend at the random
roughnesses). Errors are |fast - ref| / ref per channel in %, mean / max; "low r" is r < 0.2.
Times: the warm run of `prefilter_charlie` (float32) divided by the warm run of the GGX
`specular.prefilter` of the same 256^2 environment in the same process.

Run: python examples/charlie_prefilter_error.py [--quick] [--refs refs.npz]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

from jaxpbr import envs, specular
from jaxpbr.cubeio import load_environment
from jaxpbr.sheen_prefilter import (
    charlie_level_roughness,
    charlie_lookup,
    charlie_reference,
    prefilter_charlie,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CONFIGS = [  # (output size, source size, levels)
    (16, 32, 3),
    (32, 32, 3),
    (32, 64, 3),
    (32, 64, 4),
    (64, 64, 4),
    (64, 64, 5),
]


def environments(quick: bool):
    out = [("sky", envs.sky_with_sun_cubemap(256))]
    if DATA.is_dir():
        names = sorted(p.name for p in DATA.glob("*.hdr"))
        for n in names[:1] if quick else names:
            out.append((n, load_environment([str(DATA / n)], 256)))
    return out


def timed(fn, reps=2):
    """(best wall time of reps runs, the last result): the first run compiles."""
    best = out = None
    for _ in range(reps):
        t = time.perf_counter()
        out = jax.block_until_ready(fn())
        dt = time.perf_counter() - t
        best = dt if best is None else min(best, dt)
    return best, out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="the sky and one HDR, 3 configurations")
    ap.add_argument("--refs", help="npz file to keep the references in (read if present)")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n_dirs = 48
    rand_r = np.sort(rng.uniform(0.0, 1.0, 10))
    level_r = charlie_level_roughness(5)
    rs = np.concatenate([rand_r, level_r])
    dirs = rng.normal(size=(len(rs), n_dirs, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    configs = CONFIGS[1:4] if args.quick else CONFIGS
    store = dict(np.load(args.refs)) if args.refs and Path(args.refs).exists() else {}
    print(f"random sheen roughnesses: {', '.join(f'{r:.3f}' for r in rand_r)}")
    summary = []
    for name, env in environments(args.quick):
        key = f"{name}:{env.face_size}"
        if key not in store:
            t = time.perf_counter()
            store[key] = np.stack([charlie_reference(env, dirs[i], float(r)) for i, r in enumerate(rs)])
            print(f"[{name}] reference: {time.perf_counter() - t:.1f} s")
            if args.refs:
                np.savez(args.refs, **store)
        ref = store[key]
        t_ggx = timed(lambda e=env: specular.prefilter(e).levels)[0]
        print(f"\n[{name}] {env.face_size}^2, GGX specular.prefilter warm: {t_ggx:.2f} s")
        print("  size src  M | random r, mean_cosine: all / low r | random r, lod=r(M-1) | at r = 0 | at r_m (5 levels) | time, x GGX")
        for S, src, M in configs:
            t, pre = timed(lambda e=env, S=S, src=src, M=M: prefilter_charlie(e, size=S, source_size=src, num_levels=M))
            e_mc, e_rl = [], []
            for i, r in enumerate(rs):
                for blend, acc in (("mean_cosine", e_mc), ("roughness", e_rl)):
                    got = np.asarray(charlie_lookup(pre, dirs[i], r, lod_blend=blend), np.float64)
                    acc.append(100 * np.abs(got - ref[i]) / ref[i])
            e_mc, e_rl = np.stack(e_mc), np.stack(e_rl)
            nr = len(rand_r)
            low = rand_r < 0.2
            f = lambda e: f"{e.mean():5.2f}/{e.max():6.2f}"
            row = (f"  {S:4d} {src:4d} {M:2d} | {f(e_mc[:nr])} / {f(e_mc[:nr][low])} | {f(e_rl[:nr])} | "
                   f"{f(e_mc[nr])} | {f(e_mc[nr:])} | {t:5.2f} s, {t / t_ggx:4.2f}x")
            print(row)
            summary.append((name, S, src, M, e_mc[:nr].mean(), e_mc[:nr].max(), t / t_ggx))
    print("\nmean over environments (random r, mean_cosine): mean / max error %, time x GGX")
    for S, src, M in configs:
        rows = [s for s in summary if s[1:4] == (S, src, M)]
        print(f"  {S:4d} {src:4d} {M:2d}: {np.mean([r[4] for r in rows]):5.2f} / {np.max([r[5] for r in rows]):6.2f}, "
              f"{np.mean([r[6] for r in rows]):4.2f}x")


if __name__ == "__main__":
    main()
