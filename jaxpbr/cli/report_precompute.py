"""`jaxpbr report precompute`: error against run time for every precompute.

For the BRDF LUT, each irradiance method and the prefiltered specular cube, a sweep of sample
counts / resolutions is timed (after a warm-up call, so JIT compilation is excluded and reported
apart) and compared with the float64 references of `jaxpbr.ibl.measure`. Environments: a procedural sky
with a 3000-radiance sun generated in code, plus any HDR panoramas given. Output: a Markdown table
and a PNG plot (the plot needs matplotlib: `pip install 'jaxpbr[report]'`).

The chain sweep (issue 11; `--chain-only` runs just it) measures the prefiltered chain's size and
lookup rather than its sampling: per source size, smallest face (floor), level mapping and lod blend,
lookups at random directions and roughnesses (not texel centres) (a) of chains holding the closed
form of an environment linear in direction, LD = a + b c(alpha) (R.d) (`specular.lobe_mean_cosine`),
and (b) of the FIS chains of each environment against `prefilter_reference` at the same (R, r).

The wide-sun case (`sun_rows`): the default prefilter of 0.5 + a 4-degree Gaussian sun of peak 400
(256^2 -> 128^2; 128^2 -> 64^2 with --quick) per level, near the sun and at random texels apart.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..ibl import envs
from ..ibl.cubeio import load_environment
from ..ibl.cubemap import Cubemap, texel_directions
from ..ibl.diffuse import irradiance
from ..ibl.measure import irradiance_error, lut_error, prefilter_error, summarize
from ..ibl.specular import (
    DEFAULT_CHAIN_FLOOR,
    DEFAULT_LOD_BLEND,
    LOD_BLENDS,
    MAPPINGS,
    MIN_CHAIN_LEVELS,
    default_num_levels,
    level_roughness,
    lobe_mean_cosine,
    lookup_of,
    prefilter,
    prefilter_reference,
    roughness_to_lod,
)
from ..io.atomic import OutputSet, atomic_write
from ..shading.lut import compute_brdf_lut
from ._common import have_matplotlib, positive_int_arg, require_environment
from .timing import time_calls, to_host

__all__ = ["add_command", "cmd_report_precompute", "precompute_report"]


def lut_rows(sizes=(64, 128, 256), samples=(None,), smiths=("correlated", "schlick_ggx"), log=print) -> list[dict]:
    rows = []
    for smith in smiths:
        for size in sizes:
            for n in samples:
                kw = {} if n is None else {"samples": n}
                lut, _t = time_calls(lambda: to_host(compute_brdf_lut(size=size, smith=smith, **kw)), rounds=2)
                first, best = _t.first, _t.best
                # Every texel up to 128^2; above that the edges + 4096 random texels (the every-texel
                # figures of the shipped 256^2 LUTs are in luts/MANIFEST.json).
                err = lut_error(lut, smith=smith, texels=None if size <= 128 else 4096)
                rows.append(dict(what="lut", env="-", variant=f"{smith} {size}^2", param=n or "default", seconds=best, compile_s=max(0.0, first - best), mean=err["mean"], max=err["max"], unit="abs"))
                log(f"  lut {smith} {size}^2 samples={n or 'default'}: max {err['max']:.2e} in {best:.2f} s")
    return rows


def irradiance_rows(env, env_name: str, size: int = 32, source_sizes=(16, 32, 64), log=print) -> list[dict]:
    rows = []
    configs = [("exact", s) for s in source_sizes if s <= env.face_size] + [("sh9", None)]
    for method, src in configs:
        irr, _t = time_calls(lambda: to_host(irradiance(env, size=size, method=method, source_size=src)), rounds=2)
        first, best = _t.first, _t.best
        err = irradiance_error(env, irr, texels=1024)
        rows.append(dict(what="irradiance", env=env_name, variant=method if src is None else f"exact src {src}^2", param=src or 9, seconds=best, compile_s=max(0.0, first - best), mean=err["mean"], max=err["max"], unit="rel"))
        log(f"  irradiance {env_name} {rows[-1]['variant']}: mean {100 * err['mean']:.3f} % max {100 * err['max']:.3f} % in {best:.2f} s")
    return rows


def prefilter_rows(env, env_name: str, samples=(64, 128, 256, 512), exact_texels=(0, None), texels_per_level=512, log=print) -> list[dict]:
    """exact_texels: 0 (plain FIS), None (the default budget) or a count."""
    rows = []
    for et in exact_texels:
        for n in samples:
            pre, _t = time_calls(lambda: to_host(prefilter(env, samples=n, exact_texels=et)), rounds=1)
            first, best = _t.first, _t.best
            w = summarize(prefilter_error(env, pre, texels_per_level=texels_per_level))
            rows.append(dict(what="prefilter", env=env_name, variant=f"FIS{' + exact sun' if et != 0 else ''}", param=n, seconds=best, compile_s=max(0.0, first - best), mean=w["mean"], max=w["max"], unit="rel"))
            log(f"  prefilter {env_name} {env.face_size}^2 samples={n} exact_texels={'default' if et is None else et}: mean {100 * w['mean']:.2f} % worst {100 * w['max']:.2f} % in {best:.2f} s")
    return rows


#: The wide-sun case of `sun_rows`: 0.5 + a Gaussian sun of this standard deviation (degrees) and peak.
SUN_SIGMA_DEG, SUN_PEAK, SUN_BASE = 4.0, 400.0, 0.5
_SUN_DIR = np.array([0.3, 0.6, 0.5]) / np.linalg.norm([0.3, 0.6, 0.5])


def gaussian_sun_cubemap(face_size: int) -> Cubemap:
    """0.5 + a smooth Gaussian sun (standard deviation 4 degrees, peak 400), area-filtered."""
    sigma = np.radians(SUN_SIGMA_DEG)

    def fn(d):
        ang = jnp.arccos(jnp.clip(d @ jnp.asarray(_SUN_DIR), -1.0, 1.0))
        return (SUN_BASE + SUN_PEAK * jnp.exp(-0.5 * (ang / sigma) ** 2))[..., None] * jnp.ones(3)

    return Cubemap.from_function(fn, face_size)


def sun_rows(face_size: int = 256, size: int = 128, near: int = 64, random: int = 256, seed: int = 0, log=print) -> list[dict]:
    """The default prefilter (`size`^2, default chain) of the wide Gaussian sun (`gaussian_sun_cubemap`
    at `face_size`^2) per level against `prefilter_reference`: the `near` texels nearest the sun and
    `random` seeded random ones apart, mean and worst relative error (goal: 0.5 % / 2 % at every
    level). A wide sun has thousands of texels above 4x the mean: those the exact pass leaves in
    the sampled part are what the sampling gets wrong."""
    env = gaussian_sun_cubemap(face_size)
    pre, _t = time_calls(lambda: to_host(prefilter(env, size=size)), rounds=1)
    M, mapping, _ = lookup_of(pre)
    rough = level_roughness(M, mapping=mapping)
    name = f"Gaussian sun {SUN_SIGMA_DEG:g}°, peak {SUN_PEAK:g}, {face_size}^2 -> {size}^2"
    rng = np.random.default_rng(seed)
    rows = []
    for m in range(1, pre.num_levels):
        d = texel_directions(pre.levels[m].shape[1]).reshape(-1, 3)
        got = np.asarray(pre.levels[m], np.float64).reshape(-1, pre.channels)
        for part, sel in (("near the sun", np.argsort(-(d @ _SUN_DIR))[:near]), ("random", rng.choice(len(d), min(random, len(d)), replace=False))):
            ref = prefilter_reference(env, d[sel], float(rough[m]))
            e = np.abs(got[sel] - ref).sum(-1) / np.abs(ref).sum(-1)
            rows.append(dict(what="prefilter (wide sun)", env=name, variant=f"level {m}, r = {rough[m]:.2f}, {part}", param=len(sel), seconds=_t.best, compile_s=max(0.0, _t.first - _t.best), mean=float(e.mean()), max=float(e.max()), unit="rel"))
            log(f"  prefilter wide sun level {m} (r = {rough[m]:.2f}) {part}: mean {100 * e.mean():.2f} % worst {100 * e.max():.2f} %")
    return rows


#: Chain floors (smallest face sizes) the chain sweep compares.
CHAIN_FLOORS = (1, 2, 4, 8, 16, 32)
#: The linear environment of the chain sweep, L(w) = a + b (w . d).
_LIN_A, _LIN_B = 1.0, 0.8
_LIN_DIR = np.array([0.2, 0.5, -0.7]) / np.linalg.norm([0.2, 0.5, -0.7])


def _random_lookups(n: int, seed: int):
    """n random unit directions and roughnesses, a tenth of them at r = 1 and a tenth at r = 0.85."""
    rng = np.random.default_rng(seed)
    R = rng.normal(size=(n, 3))
    R /= np.linalg.norm(R, axis=1, keepdims=True)
    rs = rng.uniform(0.0, 1.0, n)
    rs[: n // 10], rs[n // 10 : n // 5] = 1.0, 0.85
    return R, rs


def _chain_floors(S: int, floors):
    """(floor, M) for each requested floor that gives a new level count for an S^2 source."""
    seen = set()
    for floor in floors:
        M = default_num_levels(S, floor=floor, min_levels=1)
        if floor > S or M in seen:
            continue
        seen.add(M)
        yield floor, M


def _chain_row(env_name, S, floor, M, mapping, blend, err, rs, seconds=None) -> dict:
    e = np.asarray(err)
    at1 = e[rs == 1.0]
    return dict(
        what="chain", env=env_name, source=S, floor=S >> (M - 1), requested_floor=floor, levels=M, mapping=mapping,
        blend=blend, lookups=int(e.size), mean=float(e.mean()), max=float(e.max()),
        max_r1=float(at1.max()) if at1.size else float("nan"), seconds=seconds,
    )


def chain_rows(sizes=(64, 128, 256), floors=CHAIN_FLOORS, mappings=MAPPINGS, blends=LOD_BLENDS, lookups: int = 600, seed: int = 0, log=print) -> list[dict]:
    """The chain sweep on the linear-environment oracle: for each source size S, floor, mapping and
    blend, an M-level chain (S^2 down to the floor) holding a + b c(alpha(r_m)) (t.d)
    at its texel centres t, looked up (`roughness_to_lod`, trilinear) at `lookups` random (R, r)
    against a + b c(alpha(r)) (R.d); relative error. No sampling error: what is measured is the
    chain itself (coarse faces between texel centres) and the blend between levels."""
    R, rs = _random_lookups(lookups, seed)
    truth = _LIN_A + _LIN_B * lobe_mean_cosine(rs * rs) * (R @ _LIN_DIR)
    rows = []
    with jax.enable_x64(True):
        Rj, rj = jnp.asarray(R), jnp.asarray(rs)
        for S in sizes:
            for floor, M in _chain_floors(S, floors):
                for mapping in mappings:
                    rm = level_roughness(M, mapping=mapping)
                    cube = Cubemap(
                        [jnp.asarray((_LIN_A + _LIN_B * lobe_mean_cosine(rm[m] ** 2) * (texel_directions(S >> m) @ _LIN_DIR))[..., None]) for m in range(M)]
                    )
                    for blend in blends:
                        got = np.asarray(cube.sample(Rj, roughness_to_lod(rj, M, mapping=mapping, lod_blend=blend)))[:, 0]
                        rows.append(_chain_row("linear (closed form)", S, floor, M, mapping, blend, np.abs(got - truth) / truth, rs))
                        r = rows[-1]
                        log(f"  chain linear env {S}^2 to {r['floor']}^2 (M={M}) {mapping} {blend}: mean {100 * r['mean']:.2f} % max {100 * r['max']:.2f} % (r = 1: {100 * r['max_r1']:.2f} %)")
    return rows


def chain_env_rows(env, env_name: str, floors=CHAIN_FLOORS, mappings=MAPPINGS, blends=LOD_BLENDS, roughness=(0.07, 0.13, 0.2, 0.28, 0.37, 0.45, 0.55, 0.66, 0.78, 0.9, 1.0), directions: int = 48, seed: int = 1, log=print) -> list[dict]:
    """The chain sweep on a real environment: the default FIS prefilter of `env` (face size S) for
    each floor and mapping, looked up with each blend at `directions` random directions per
    roughness, against `prefilter_reference` (float64, every texel) at the same (R, r); relative L1
    error over the channels (as `jaxpbr.ibl.measure`). Includes the prefilters' sampling error."""
    S = env.face_size
    rng = np.random.default_rng(seed)
    R = rng.normal(size=(len(roughness), directions, 3))
    R /= np.linalg.norm(R, axis=-1, keepdims=True)
    ref = np.stack([prefilter_reference(env, R[i], float(r)) for i, r in enumerate(roughness)])
    rs = np.repeat(np.asarray(roughness, np.float64), directions)
    rows = []
    for floor, M in _chain_floors(S, floors):
        for mapping in mappings:
            t0 = time.perf_counter()
            pre = prefilter(env, num_levels=M, mapping=mapping)
            jax.block_until_ready(pre.levels)
            seconds = time.perf_counter() - t0
            for blend in blends:
                lod = roughness_to_lod(jnp.asarray(rs, jnp.float32), M, mapping=mapping, lod_blend=blend)
                got = np.asarray(pre.sample(jnp.asarray(R.reshape(-1, 3), jnp.float32), lod), np.float64)
                want = ref.reshape(-1, ref.shape[-1])
                err = np.abs(got - want).sum(-1) / np.maximum(np.abs(want).sum(-1), 1e-300)
                rows.append(_chain_row(env_name, S, floor, M, mapping, blend, err, rs, seconds))
                r = rows[-1]
                log(f"  chain {env_name} {S}^2 to {r['floor']}^2 (M={M}) {mapping} {blend}: mean {100 * r['mean']:.2f} % max {100 * r['max']:.1f} %")
    return rows


def chain_markdown(rows: list[dict]) -> str:
    """The chain sweep as a Markdown table (the default chain in bold)."""
    out = [
        f"Chain sweep: lookups at random directions and roughnesses; default: floor {DEFAULT_CHAIN_FLOOR}^2 with at "
        f"least {MIN_CHAIN_LEVELS} levels (bold), mapping linear, lod blend {DEFAULT_LOD_BLEND}.",
        "",
        "| environment | source | floor | levels | mapping | lod blend | lookups | mean error | max error | max at r = 1 |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        default = r["levels"] == default_num_levels(r["source"]) and r["mapping"] == "linear" and r["blend"] == DEFAULT_LOD_BLEND
        b = "**" if default else ""
        out.append(
            f"| {r['env']} | {r['source']}^2 | {b}{r['floor']}^2{b} | {r['levels']} | {r['mapping']} | {b}{r['blend']}{b} | {r['lookups']} | "
            f"{100 * r['mean']:.2f} % | {100 * r['max']:.2f} % | {100 * r['max_r1']:.2f} % |"
        )
    return "\n".join(out) + "\n"


def markdown(rows: list[dict]) -> str:
    rows = [r for r in rows if r["what"] != "chain"]
    out = [
        "| precompute | environment | variant | samples / size | run time (s) | compile (s) | mean error | max error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        fmt = (lambda x: f"{x:.1e}") if r["unit"] == "abs" else (lambda x: f"{100 * x:.3g} %")
        out.append(
            f"| {r['what']} | {r['env']} | {r['variant']} | {r['param']} | {r['seconds']:.3f} | {r['compile_s']:.2f} | {fmt(r['mean'])} | {fmt(r['max'])} |"
        )
    return "\n".join(out) + "\n"


def _family(r: dict) -> str:
    """Curve a row belongs to: one line per environment and method family, sorted by run time."""
    if r["what"] == "lut":
        smith = r["variant"].split()[0]
        return f"{smith}, sizes 64-256" if r["param"] == "default" else f"{smith} 256^2, samples"
    if r["what"] == "irradiance":
        return f"{r['env']}: {'exact (src 16-64)' if r['variant'].startswith('exact') else 'sh9'}"
    return f"{r['env']}: {r['variant']}"


def plot(rows: list[dict], path: Path) -> bool:
    """Error-vs-time plot to `path` (PNG); False (nothing written) without matplotlib."""
    if not have_matplotlib():
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = [k for k in ("lut", "irradiance", "prefilter") if any(r["what"] == k for r in rows)]
    fig, axes = plt.subplots(1, len(kinds), figsize=(6.0 * len(kinds), 6.5), squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        groups: dict = {}
        for r in rows:
            if r["what"] == kind:
                groups.setdefault(_family(r), []).append(r)
        for i, (label, rs) in enumerate(groups.items()):
            rs = sorted(rs, key=lambda r: r["seconds"])
            t = [r["seconds"] for r in rs]
            (line,) = ax.loglog(t, [r["max"] for r in rs], "o-", label=f"{label} (max)")
            if kind != "lut":
                ax.loglog(t, [r["mean"] for r in rs], "s:", color=line.get_color(), alpha=0.7, label=f"{label} (mean)")
        ax.set_xlabel("run time (s, after compile)")
        ax.set_ylabel("max |error| at every texel" if kind == "lut" else "relative error vs float64 reference")
        ax.set_title({"lut": "BRDF LUT", "irradiance": "irradiance 32^2", "prefilter": "prefiltered mips (worst level)"}[kind])
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, frameon=False)
    fig.tight_layout()
    atomic_write(Path(path), lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)
    return True


def precompute_report(env_paths=(), *, out_prefix="precompute_report", face_size: int = 256, quick: bool = False, chain_only: bool = False, log=print) -> tuple[str, list[dict]]:
    """Run the sweeps, write `<out_prefix>.md` and `<out_prefix>.png`; return (markdown, rows).
    chain_only: only the chain sweep (no plot). The chain sweep's real-environment part runs at
    `face_size`; `quick` leaves it out of the full report and shortens it with chain_only."""
    environments = [("procedural sky+sun", envs.sky_with_sun_cubemap(face_size))]
    for p in env_paths:
        environments.append((Path(p).name, load_environment([str(p)], face_size=face_size)))
    log("prefiltered chain: floor x mapping x lod blend, linear environment (closed form)")
    chain = chain_rows(sizes=(64, 128) if quick else (64, 128, 256), lookups=300 if quick else 600, log=log)
    for name, env in environments:
        if not quick or chain_only:
            log(f"prefiltered chain: {name}")
            chain += chain_env_rows(
                env, name, floors=(1, 4, 8, 16) if quick else CHAIN_FLOORS, directions=16 if quick else 48, log=log
            )
    chain_md = "## Prefiltered chain: size and lookup\n\n" + chain_markdown(chain)
    if chain_only:
        md = "# jaxpbr prefiltered chain sweep\n\n" + chain_md
        atomic_write(Path(f"{out_prefix}.md"), lambda tmp: Path(tmp).write_text(md))
        return md, chain
    rows = []
    log("BRDF LUT")
    rows += lut_rows(sizes=(32, 64) if quick else (64, 128, 256), log=log)
    if not quick:
        rows += lut_rows(sizes=(256,), samples=(216, 384, 600, 1176), log=log)
    for name, env in environments:
        log(f"irradiance: {name}")
        rows += irradiance_rows(env, name, source_sizes=(16, 32) if quick else (16, 32, 64), log=log)
        log(f"prefilter: {name}")
        rows += prefilter_rows(env, name, samples=(64, 128) if quick else (64, 128, 256, 512), texels_per_level=128 if quick else 512, log=log)
    log("prefilter: a wide Gaussian sun, per level")
    rows += sun_rows(128, 64, near=16, random=64, log=log) if quick else sun_rows(log=log)
    md = "# jaxpbr precompute error vs run time\n\n" + markdown(rows) + "\n" + chain_md
    rows += chain
    md_path = Path(f"{out_prefix}.md")

    def w(tmp):
        Path(tmp).write_text(md)

    atomic_write(md_path, w)
    png = Path(f"{out_prefix}.png")
    if not plot(rows, png):
        log("matplotlib is not installed: wrote the table only (pip install 'jaxpbr[report]' for the plot)")
    return md, rows


def add_command(rsub) -> None:
    """Register `jaxpbr report precompute`."""
    p = rsub.add_parser("precompute", help="LUT / irradiance / prefilter error vs run time (Markdown table + PNG plot)")
    p.add_argument("env", nargs="*", metavar="HDR", help="extra equirect panoramas to measure on (the procedural sky+sun is always included)")
    p.add_argument("--out", default="precompute_report", help="output prefix: <out>.md and <out>.png (default: %(default)s)")
    p.add_argument("--face-size", type=positive_int_arg, default=256, help="environment face size (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="a smaller sweep (for a first look)")
    p.add_argument(
        "--chain-only", action="store_true",
        help="only the prefiltered chain sweep: smallest face x level mapping x lod blend, lookups at random directions "
        "on a linear environment (closed form) and on the environments (vs the float64 reference); writes <out>.md",
    )
    p.set_defaults(func=cmd_report_precompute)


def cmd_report_precompute(args) -> int:
    require_environment(args.face_size)
    for p in args.env:
        if not Path(p).exists():
            raise InputError(f"environment file {p!r} does not exist")
    # The outputs checked before the sweep (issue 13: a bad --out was found after 20-38 s of it).
    for suffix in (".md", ".png"):
        OutputSet().check(Path(f"{args.out}{suffix}"), (suffix,))
    md, _ = precompute_report(
        args.env, out_prefix=args.out, face_size=args.face_size, quick=args.quick, chain_only=args.chain_only,
        log=lambda m: print(m, file=sys.stderr),
    )
    print(md)
    png = Path(f"{args.out}.png")
    if args.chain_only:
        print(f"wrote {args.out}.md")
        return 0
    print(f"wrote {args.out}.md" + (f" and {png}" if png.exists() else " (no plot: matplotlib is not installed)"))
    return 0
