"""`jaxpbr report render ASSET --environment FILE --visibility`: every rung of image-based light's
visibility against the ground truth, on the asset's own pixels, with the time per frame.

The rungs (`RenderOptions.ibl_visibility`): "none", "occlusion" (the glTF occlusion texture), and
the traced "ao" and "ratio" at K rays per pixel; each renders the scene as `jaxpbr render` does
(suns split out of the environment and shadowed, the residual by the split sum), single scattering
(`multiscatter=False`: the ground truth integrates the single-scattering glTF BRDF). The ground
truth is `jaxpbr.reference_render` (float64 Monte Carlo of the direct light with visibility) at
--spp samples per pixel; its own standard error is reported beside the rungs' errors.

Per rung, on the pixels where the truth sees a surface: the mean, median, 90th and 99th percentile
of the per-pixel relative luminance error |Y - Y_ref| / Y_ref (Y_ref floored at 1 % of its mean),
the image's relative L1 error sum |Y - Y_ref| / sum Y_ref (the per-pixel errors weighted by the
truth's luminance: dark pixels do not dominate it), the bias (mean signed luminance difference over
the mean reference luminance), each over all
surface pixels, the open ones (the truth's visible fraction of the sky >= 0.9) and the occluded
ones (< 0.9); the warm time per frame (median of --repeats renders) and its ratio to the "none"
frame in the same process. Pixels whose shading normal faces away from the viewer (n.v <= 0, where
normal maps bend it) are counted and left out: the glTF BRDF the truth integrates (`jp.brdf`) is 0
there, while the split sum, as Filament's and the glTF viewer's, clamps n.v and reflects; neither is a
truth to measure against. Outputs: Markdown and JSON tables and a PNG per rung of the per-pixel
relative error (black 0, white >= 50 %).
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import numpy as np

from ..conventions import luminance
from ..io import image
from ..io.atomic import OutputSet, atomic_write
from ..reference import reference_render
from ..rendering.renderer import RenderOptions, gbuffer, render

__all__ = ["DEFAULT_SAMPLES", "OPEN_VISIBLE", "visibility_markdown", "visibility_report", "write_visibility_report"]

#: K of the traced rungs measured by default.
DEFAULT_SAMPLES = (1, 4, 16, 64)
#: Pixels whose truth sees at least this fraction of the sky (cosine-weighted) count as open.
OPEN_VISIBLE = 0.9


def _luma(x):
    return luminance(np.asarray(x, np.float64)[..., :3])


def _stats(rel, diff, ref_y):
    if rel.size == 0:
        return None
    return {"pixels": int(rel.size), "mean": float(rel.mean()), "median": float(np.median(rel)),
            "p90": float(np.percentile(rel, 90)), "p99": float(np.percentile(rel, 99)),
            "l1": float(np.abs(diff).sum() / max(ref_y.sum(), 1e-300)), "bias": float(diff.mean() / max(ref_y.mean(), 1e-300))}


def visibility_report(scene, *, name: str = "scene", samples=DEFAULT_SAMPLES, spp: int = 256, seed: int = 0,
                      repeats: int = 3, log=print) -> dict:
    """The rungs against the ground truth (module docstring) -> {"config", "truth", "rungs": [...],
    "errors": {rung label: (H, W) relative error}} ("errors" is not JSON)."""
    t0 = time.perf_counter()
    truth = reference_render(scene, spp=spp, seed=seed)
    log(f"ground truth: {spp} spp in {truth.seconds:.1f} s")
    g = gbuffer(scene)
    facing = np.sum(np.asarray(g.normal, np.float64) * np.asarray(g.view, np.float64), -1) > 0
    back = truth.hit & ~facing
    hit = truth.hit & facing
    ref_y = _luma(truth.image)
    floor = 0.01 * ref_y[hit].mean() if hit.any() else 1e-300
    open_px = hit & (truth.visible >= OPEN_VISIBLE)
    occ_px = hit & (truth.visible < OPEN_VISIBLE)
    se = _luma(truth.stderr)[hit] / np.maximum(ref_y[hit], floor)
    rungs, errors = [], {}
    base_t = None
    ladder = [("none", 1), ("occlusion", 1)] + [(r, k) for r in ("ao", "ratio") for k in samples]
    for vis, k in ladder:
        opts = RenderOptions(multiscatter=False, ibl_visibility=vis, ibl_samples=k)
        t1 = time.perf_counter()
        img = np.asarray(render(scene, options=opts))
        first = time.perf_counter() - t1
        times = []
        for _ in range(repeats):
            t1 = time.perf_counter()
            np.asarray(render(scene, options=opts))
            times.append(time.perf_counter() - t1)
        t = statistics.median(times)
        base_t = t if base_t is None else base_t
        y = _luma(img)
        rel = np.abs(y - ref_y) / np.maximum(ref_y, floor)
        diff = y - ref_y
        label = vis if vis in ("none", "occlusion") else f"{vis} K={k}"
        errors[label] = np.where(hit, rel, 0.0)
        row = {"rung": vis, "samples": k if vis in ("ao", "ratio") else 0, "label": label, "seconds": t, "first_call_s": first,
               "x_none": t / base_t}
        for part, mask in (("all", hit), ("open", open_px), ("occluded", occ_px)):
            row[part] = _stats(rel[mask], diff[mask], ref_y[mask])
        rungs.append(row)
        log(f"{label}: mean {row['all']['mean']:.2%}, occluded {row['occluded']['mean'] if row['occluded'] else float('nan'):.2%}, {t:.3f} s")
    H, W = hit.shape
    return {"config": {"scene": name, "width": W, "height": H, "spp": spp, "seed": seed, "samples": list(samples),
                       "open_visible": OPEN_VISIBLE, "repeats": repeats, "seconds": time.perf_counter() - t0},
            "truth": {"seconds": truth.seconds, "surface_pixels": int(hit.sum()), "open_pixels": int(open_px.sum()),
                      "occluded_pixels": int(occ_px.sum()), "back_facing_pixels": int(back.sum()), "stderr_mean": float(se.mean()), "stderr_p90": float(np.percentile(se, 90))},
            "rungs": rungs, "errors": errors}


def visibility_markdown(result: dict) -> str:
    c, tr = result["config"], result["truth"]
    lines = [
        f"IBL visibility against the ground truth: {c['scene']}, {c['width']}x{c['height']}, truth {c['spp']} spp "
        f"({tr['seconds']:.1f} s; its standard error {tr['stderr_mean']:.2%} mean, {tr['stderr_p90']:.2%} p90 of the luminance); "
        f"{tr['surface_pixels']} surface pixels, {tr['open_pixels']} open (visible >= {c['open_visible']:g}), {tr['occluded_pixels']} occluded"
        + (f"; {tr['back_facing_pixels']} left out (shading normal facing away from the viewer)" if tr.get("back_facing_pixels") else ""),
        "",
        "| rung | mean | median | p90 | p99 | L1 | bias | open mean | occluded mean | occluded L1 | occluded bias | s/frame | x none |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rungs"]:
        a, o, q = r["all"], r["open"], r["occluded"]
        f = (lambda d, k: f"{d[k]:.1%}" if d else "-")  # noqa: E731
        signed = (lambda d: f"{d['bias']:+.1%}" if d else "-")  # noqa: E731
        lines.append(f"| {r['label']} | {a['mean']:.1%} | {a['median']:.1%} | {a['p90']:.1%} | {a['p99']:.1%} | {a['l1']:.1%} | {a['bias']:+.1%} | "
                     f"{f(o, 'mean')} | {f(q, 'mean')} | {f(q, 'l1')} | {signed(q)} | "
                     f"{r['seconds']:.3f} | {r['x_none']:.2f} |")
    return "\n".join(lines)


def write_visibility_report(result: dict, out_dir: Path, prefix: str) -> list[Path]:
    """<prefix>.md, .json and .png (the per-rung error strip) in out_dir: all of them or none."""
    d = Path(out_dir)
    errs = result["errors"]
    strip = np.concatenate([np.clip(e / 0.5, 0.0, 1.0) for e in errs.values()], 1)
    texts = ((".md", visibility_markdown(result) + "\n"), (".json", json.dumps({k: v for k, v in result.items() if k != "errors"}, indent=1) + "\n"))
    with OutputSet() as outs:
        for suffix, text in texts:
            path = d / f"{prefix}{suffix}"
            outs.add(path)
            atomic_write(path, lambda tmp, text=text: Path(tmp).write_text(text))
        png = d / f"{prefix}.png"
        outs.add(png)
        image.write(png, np.repeat(strip[..., None], 3, -1).astype(np.float32), encoding="linear",
                    metadata={"jaxpbr:content": "per-pixel relative luminance error, 0 black to 50 % white, rungs left to right: "
                              + ", ".join(errs)})
    return list(outs.written)
