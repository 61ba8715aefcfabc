"""`jaxpbr bench render --extensions`: what each glTF material extension costs a render.

The demo's 7x7 sphere grid (`demo_scene`: metallic by row, roughness by column, 4 point lights, the
demo sky with its sun split out) is rendered at --width x --height once with the core material and
once per extension group with that group's fields set on every sphere (`EXTENSION_MATERIALS`, values
away from the neutral ones so that the group's code runs), and once with every group at once. The
warm frames are interleaved in one process (`timing.time_interleaved`), so the ratios against the
core material hold while the machine's speed drifts; the first call (tracing, compiling, the
sheen's Charlie map) is reported apart. Shadows are off, as `jaxpbr render` has them for spheres.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import numpy as np

from .._validate import positive_int
from ..rendering.demo import demo_scene
from ..rendering.execute import render
from ..shading.material import EXTENSIONS
from .timing import time_interleaved

__all__ = ["EXTENSION_MATERIALS", "ExtensionsBenchResult", "bench_extensions"]

#: Each extension group's fields as set on every sphere of the grid.
EXTENSION_MATERIALS: dict[str, dict] = {
    "clearcoat": {"clearcoat": 1.0, "clearcoat_roughness": 0.1},
    "sheen": {"sheen_color": (0.8, 0.3, 0.3), "sheen_roughness": 0.5},
    "specular": {"specular": 0.5, "specular_color": (1.0, 0.5, 0.2)},
    "ior": {"ior": 1.8},
    "anisotropy": {"anisotropy_strength": 0.7, "anisotropy_rotation": 0.3},
    "emissive_strength": {"emissive": (0.2, 0.1, 0.05), "emissive_strength": 4.0},
    "transmission": {"transmission": 0.8},
    "volume": {"transmission": 0.8, "thickness": 0.5, "attenuation_distance": 1.0, "attenuation_color": (0.8, 0.5, 0.3)},
}


@dataclass
class ExtensionsBenchResult:
    width: int
    height: int
    repeats: int
    device: str
    first_s: dict  # variant -> the first call (compile included), seconds
    frame_s: dict  # variant -> median warm frame, seconds
    finite: dict  # variant -> whether every pixel is finite

    def ratio(self, name: str) -> float:
        return self.frame_s[name] / self.frame_s["core"]

    def report(self) -> str:
        title = (
            f"jaxpbr bench render --extensions: the demo's 7x7 sphere grid at {self.width}x{self.height}, 4 point lights "
            f"+ IBL + the sky's sun, one extension group on every sphere ({self.device}; warm frames interleaved, "
            f"median of {self.repeats})"
        )
        lines = [title, f"  {'material':<20}{'first call s':>14}{'warm ms':>11}{'x core':>9}"]
        for name in self.frame_s:
            flag = "" if self.finite[name] else "  NON-FINITE PIXELS"
            lines.append(f"  {name:<20}{self.first_s[name]:>14.2f}{self.frame_s[name] * 1e3:>11.1f}{self.ratio(name):>9.2f}{flag}")
        return "\n".join(lines)


def extension_scene(width: int, height: int, groups: tuple[str, ...]):
    """`demo_scene(width, height)` with the fields of `groups` (`EXTENSION_MATERIALS`) on every sphere."""
    scene = demo_scene(width, height)
    fields = {}
    for g in groups:
        fields.update(EXTENSION_MATERIALS[g])
    if not fields:
        return scene
    return scene.replace(objects=[ob.replace(material=ob.material.replace(**fields)) for ob in scene.objects])


def bench_extensions(width: int = 1280, height: int = 720, *, repeats: int = 3, groups: tuple[str, ...] | None = None) -> ExtensionsBenchResult:
    """The measurements of the module docstring for `groups` (default: every group, then all at once)."""
    for name, x in (("width", width), ("height", height), ("repeats", repeats)):
        positive_int(name, x)
    names = tuple(EXTENSION_MATERIALS) if groups is None else tuple(groups)
    unknown = [g for g in names if g not in EXTENSION_MATERIALS]
    if unknown:
        raise ValueError(f"unknown extension group(s) {unknown}; choose from {sorted(EXTENSION_MATERIALS)}")
    variants = {"core": ()} | {g: (g,) for g in names}
    if groups is None:
        variants["all"] = tuple(g for g in EXTENSIONS if g in EXTENSION_MATERIALS)
    scenes = {k: extension_scene(width, height, v) for k, v in variants.items()}
    images = {}

    def frame(k):
        def run():
            images[k] = render(scenes[k])
            return images[k]

        return run

    t = time_interleaved({k: frame(k) for k in scenes}, rounds=repeats)
    d = jax.devices()[0]
    return ExtensionsBenchResult(
        width=width, height=height, repeats=repeats, device=getattr(d, "device_kind", str(d)),
        first_s={k: v.first for k, v in t.items()}, frame_s={k: v.median for k, v in t.items()},
        finite={k: bool(np.isfinite(np.asarray(images[k])).all()) for k in scenes},
    )
