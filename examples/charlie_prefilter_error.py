"""Error and run time of the Charlie-prefiltered sheen chain (`jaxpbr.ibl.sheen_prefilter`): the zonal
method (rings in c = R.l, footprint-matched pyramid lookups) against the older box method (every
texel of one source level), side by side in one process.

Environments (256^2): the procedural sky with its 2-degree 3000-radiance sun; its sun-extracted
residual (`extract.extract_lights(sky).residual`, what `jaxpbr.render` Charlie-filters by default);
a soft sky (no sun). The float64 reference `charlie_reference` (every texel of the full 256^2
environment, sub-texel supersampled) is computed at 48 random directions for each of 10 random
sheen roughnesses in [0, 1] and for the 5 level roughnesses r = 0, .25, .5, .75, 1; each
configuration is looked up there with `charlie_lookup` ("mean_cosine" blend). Errors are
|fast - ref| / ref per channel in %, mean / max. Times: warm run of `prefilter_charlie` (float32)
divided by the warm run of the GGX `specular.prefilter` of the same environment, and by the box
method's default configuration (the first row).

Run: python examples/charlie_prefilter_error.py [--quick] [--refs refs.npz]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

from jaxpbr.ibl import envs, specular
from jaxpbr.ibl.extract import extract_lights
from jaxpbr.ibl.sheen_prefilter import (
    charlie_level_roughness,
    charlie_lookup,
    charlie_reference,
    prefilter_charlie,
)

CONFIGS = [  # (label, keyword arguments of prefilter_charlie)
    ("box (old default)", dict(method="box", size=64, source_size=64, num_levels=5)),
    ("zonal L0 src 256 (def)", dict(size=64, num_levels=5)),
    ("zonal L0 src 128", dict(size=64, num_levels=5, zonal_source_size=128)),
    ("zonal L0-1 src 256", dict(size=64, num_levels=5, zonal_levels=2, rings=16)),
]


def environments():
    sky = envs.sky_with_sun_cubemap(256)
    return [
        ("sky", sky),
        ("sky residual", extract_lights(sky).residual),
        ("soft sky", envs.sky_with_sun_cubemap(256, sun_radiance=0.0)),
    ]


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
    ap.add_argument("--quick", action="store_true", help="the first two configurations and the chosen default")
    ap.add_argument("--refs", help="npz file to keep the references in (read if present)")
    ap.add_argument("--only", nargs="*", help="configuration labels to run (default: all)")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n_dirs = 48
    rand_r = np.sort(rng.uniform(0.0, 1.0, 10))
    level_r = charlie_level_roughness(5)
    rs = np.concatenate([rand_r, level_r])
    dirs = rng.normal(size=(len(rs), n_dirs, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    configs = [c for c in CONFIGS if not args.only or c[0] in args.only]
    store = dict(np.load(args.refs)) if args.refs and Path(args.refs).exists() else {}
    print(f"random sheen roughnesses: {', '.join(f'{r:.3f}' for r in rand_r)}")
    for name, env in environments():
        key = f"{name}:{env.face_size}"
        if key not in store:
            t = time.perf_counter()
            store[key] = np.stack([charlie_reference(env, dirs[i], float(r)) for i, r in enumerate(rs)])
            print(f"[{name}] reference: {time.perf_counter() - t:.1f} s", flush=True)
            if args.refs:
                np.savez(args.refs, **store)
        ref = store[key]
        t_ggx = timed(lambda e=env: specular.prefilter(e).levels)[0]
        print(f"\n[{name}] {env.face_size}^2, GGX specular.prefilter warm: {t_ggx:.2f} s")
        print("  config                 | random r: all        | r=0            | r=.25          | r=.5           | r=.75          | r=1            | time  x GGX  x box")
        t_box = None
        for label, kw in configs:
            t, pre = timed(lambda e=env, kw=kw: prefilter_charlie(e, **kw))
            t_box = t if t_box is None else t_box
            e = np.stack([100 * np.abs(np.asarray(charlie_lookup(pre, dirs[i], r), np.float64) - ref[i]) / ref[i]
                          for i, r in enumerate(rs)])
            nr = len(rand_r)
            f = lambda x: f"{x.mean():5.2f}/{x.max():7.2f}"  # noqa: E731
            print(f"  {label:22s} | {f(e[:nr])} | " + " | ".join(f(e[nr + m]) for m in range(5))
                  + f" | {t:5.2f} {t / t_ggx:5.2f} {t / t_box:5.2f}", flush=True)


if __name__ == "__main__":
    main()
