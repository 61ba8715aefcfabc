"""Dominant-light extraction: split an environment into disc lights (suns) and a residual.

`extract_lights(env)` finds compact, very bright regions of an environment map, fits each as a
uniform distant disc (a `DirectionalLight` with an `angular_radius`) and returns the lights and the
residual environment with those regions removed. The split sum is poor exactly for such sources
(n = v = R fails for a small, very bright lobe; issue 11), while a disc is shaded analytically by
`shade_direct`; `render` uses this split by default (`RenderOptions.extract_lights`).

Algorithm (float64, on the host; the decision which texels form a light is discrete, so this is
not traced or differentiated):

1. luminance Y (Rec. 709 weights) of level 0 and the texels' solid angles; the reference level
   is the solid-angle-weighted median luminance Y_med (the "sky"); a texel is bright where
   Y > threshold * Y_med (`DEFAULT_THRESHOLD`);
2. bright texels are grouped into 8-connected regions across face seams;
3. per region, its background B (per channel) is the solid-angle-weighted mean of the non-bright
   texels bordering it; the residual keeps min(L, B) there and the light receives the excess
   e = L - min(L, B) >= 0;
4. the excess is fitted by moments: with the texels' exact first moments m_i = int_texel w dw,
   M0 = sum_i Y(e_i) omega_i and M1 = sum_i Y(e_i) m_i, the disc's direction is M1 / |M1|, its
   angular radius sigma solves (1 + cos sigma) / 2 = |M1| / M0 (the mean cosine of a uniform
   disc) and its radiance per channel is sum_i e_i omega_i / (2 pi (1 - cos sigma));
5. a region becomes a light if sigma <= max_angular_radius and its excess carries at least
   min_power_share of the environment's power; at most max_lights, largest power first.

Energy identities (tested): per channel, total power (sum L omega) of residual + lights equals the
original's exactly (up to rounding); for luminance, irradiance at every normal that sees the
whole region above its horizon equals the original's exactly (the disc's irradiance is
pi sin^2 sigma L_Y (n.d) = n . M1). Where the region straddles the horizon the disc's irradiance
is computed exactly for the disc (`lights.cap_irradiance`) and differs from the region's by its
shape (measured in docs/ibl.md). An environment without a dominant source yields no lights and
the same environment object back.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .._numerics import is_concrete
from .._validate import check_radiance
from ..shading.lights import MAX_ANGULAR_RADIUS, DirectionalLight
from .cubemap import _FACE_TABLE, Cubemap, dir_to_face, face_to_dir, texel_solid_angles
from .diffuse import _face_moments

__all__ = [
    "DEFAULT_MAX_ANGULAR_RADIUS",
    "DEFAULT_MAX_LIGHTS",
    "DEFAULT_MIN_POWER_SHARE",
    "DEFAULT_THRESHOLD",
    "ExtractedLights",
    "extract_lights",
    "lights_to_json",
]

#: A texel is bright above this multiple of the environment's solid-angle-weighted median
#: luminance (see docs/ibl.md, "Suns as disc lights", for the measurements behind the defaults).
DEFAULT_THRESHOLD = 100.0
#: A region becomes a light only if its excess carries at least this share of the total power.
DEFAULT_MIN_POWER_SHARE = 0.005
#: ... and if its fitted disc is at most this wide (radians; 8 degrees).
DEFAULT_MAX_ANGULAR_RADIUS = math.radians(8.0)
#: At most this many lights (largest power first).
DEFAULT_MAX_LIGHTS = 4

_LUMA = np.array([0.2126, 0.7152, 0.0722])


class ExtractedLights(NamedTuple):
    """lights: tuple of `DirectionalLight` (with angular_radius), largest power first;
    residual: the environment without them (`Cubemap`, level 0 only; `env` itself when no light
    was found); info: one dict per light (direction towards the light, angular radius in degrees,
    radiance RGB, power share, texels, background RGB) plus the thresholds used."""

    lights: tuple
    residual: Cubemap
    info: dict


def _neighbours(flat: np.ndarray, S: int) -> np.ndarray:
    """8-neighbourhood of texels (flat indices (f*S + i)*S + j) across face seams: (n, 8)."""
    f, rem = np.divmod(flat, S * S)
    i, j = np.divmod(rem, S)
    out = np.empty((len(flat), 8), np.int64)
    k = 0
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == 0 and dj == 0:
                continue
            s = (j + 0.5 + dj) / S
            t = (i + 0.5 + di) / S
            d = face_to_dir(f, s, t, xp=np)  # off the face: the face's plane, seen on the next face
            f2, s2, t2 = dir_to_face(d, xp=np)
            j2 = np.clip(np.floor(s2 * S).astype(np.int64), 0, S - 1)
            i2 = np.clip(np.floor(t2 * S).astype(np.int64), 0, S - 1)
            out[:, k] = (f2.astype(np.int64) * S + i2) * S + j2
            k += 1
    return out


def _components(bright_flat: np.ndarray, S: int):
    """Connected components of the bright texels: (labels (n,) in 0..k-1, neighbours (n, 8))."""
    n = len(bright_flat)
    nb = _neighbours(bright_flat, S)
    pos = np.full(6 * S * S, -1, np.int32)
    pos[bright_flat] = np.arange(n)
    nb_pos = pos[nb]  # -1: not bright
    a = np.repeat(np.arange(n), 8)
    b = nb_pos.reshape(-1)
    keep = b >= 0
    a, b = a[keep], b[keep]
    label = np.arange(n)
    while True:  # min-label propagation with pointer jumping
        new = label.copy()
        np.minimum.at(new, a, label[b])
        np.minimum.at(new, b, label[a])
        new = new[new]
        if np.array_equal(new, label):
            break
        label = new
    _, label = np.unique(label, return_inverse=True)
    return label, nb


def _moments(flat: np.ndarray, S: int) -> np.ndarray:
    """Exact first moments int_texel w dw of the texels `flat` ((f*S + i)*S + j), float64 (n, 3)."""
    f, rem = np.divmod(flat, S * S)
    i, j = np.divmod(rem, S)
    return np.einsum("nab,nb->na", _FACE_TABLE[f], _face_moments(S)[i, j])


def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cw, 0.5 * cw[-1])])


def extract_lights(
    env: Cubemap,
    *,
    threshold: float = DEFAULT_THRESHOLD,
    min_power_share: float = DEFAULT_MIN_POWER_SHARE,
    max_angular_radius: float = DEFAULT_MAX_ANGULAR_RADIUS,
    max_lights: int = DEFAULT_MAX_LIGHTS,
) -> ExtractedLights:
    """Split `env` into disc lights and a residual environment (see the module docstring).

    env: a concrete environment `Cubemap` (level 0 is read; RGB or RGBA, alpha kept).
    threshold: bright texels have luminance > threshold x the solid-angle-weighted median.
    min_power_share: a region's excess must carry at least this share of the total power.
    max_angular_radius: largest fitted disc radius accepted (radians, < 89 degrees).
    max_lights: at most this many lights (0 turns extraction off).
    Returns `ExtractedLights(lights, residual, info)`; the lights' dtype is the environment's.
    """
    if not isinstance(env, Cubemap):
        raise TypeError(f"extract_lights needs a Cubemap, got {type(env).__name__}")
    if not is_concrete(env.levels[0]):
        raise TypeError(
            "extract_lights needs concrete texel values (it decides which texels form a light): call it "
            "outside jax.jit / grad, e.g. once per environment before a traced render"
        )
    check_radiance("extract_lights: env", env)
    for name, x, lo in (("threshold", threshold, 1.0), ("min_power_share", min_power_share, 0.0)):
        if not (isinstance(x, (int, float)) and math.isfinite(x) and x >= lo):
            raise ValueError(f"{name} must be a finite number >= {lo:g}, got {x!r}")
    if not (isinstance(max_angular_radius, (int, float)) and 0.0 < max_angular_radius <= MAX_ANGULAR_RADIUS):
        raise ValueError(f"max_angular_radius must be in (0, {MAX_ANGULAR_RADIUS:.4f}] radians, got {max_angular_radius!r}")
    if isinstance(max_lights, bool) or not isinstance(max_lights, (int, np.integer)) or max_lights < 0:
        raise ValueError(f"max_lights must be an integer >= 0, got {max_lights!r}")
    config = dict(
        threshold=float(threshold),
        min_power_share=float(min_power_share),
        max_angular_radius_deg=math.degrees(max_angular_radius),
        max_lights=int(max_lights),
    )
    level = np.asarray(env.levels[0])
    if level.shape[-1] < 3:
        raise ValueError(f"extract_lights needs RGB texels, got {level.shape[-1]} channel(s)")
    S = env.face_size
    # Whole-map arrays stay in the map's dtype (a float64 copy is 600 MB at 2048^2); the texels of
    # a region and its border are read in float64.
    flat = level.reshape(-1, level.shape[-1])
    L = lambda idx: flat[idx, :3].astype(np.float64)  # noqa: E731
    omega = texel_solid_angles(S).reshape(-1)
    Y = (flat[:, :3] @ _LUMA.astype(flat.dtype)).astype(np.float64)
    total = float((Y * omega).sum())
    y_med = _weighted_median(Y, omega)
    info = dict(config, median_luminance=y_med, lights=[])
    cut = threshold * y_med if y_med > 0 else threshold * total / (4 * math.pi)
    bright = np.flatnonzero(Y > cut) if max_lights and total > 0 else np.zeros(0, np.int64)
    if len(bright) == 0:
        return ExtractedLights((), env, info)
    label, nb = _components(bright, S)
    is_bright = np.zeros(len(Y), bool)
    is_bright[bright] = True
    found = []
    for k in range(int(label.max()) + 1):
        sel = label == k
        tex = bright[sel]
        ring = np.unique(nb[sel].reshape(-1))
        ring = ring[~is_bright[ring]]
        if len(ring):
            back = (L(ring) * omega[ring, None]).sum(0) / omega[ring].sum()
        else:
            back = np.zeros(3)
        kept = np.minimum(L(tex), back)
        excess = L(tex) - kept
        ey = excess @ _LUMA
        m0 = float((ey * omega[tex]).sum())
        m1 = (ey[:, None] * _moments(tex, S)).sum(0)
        norm1 = float(np.linalg.norm(m1))
        if m0 <= 0 or norm1 <= 0:
            continue
        cos_sigma = min(1.0, max(-1.0, 2.0 * norm1 / m0 - 1.0))
        sigma = math.acos(cos_sigma)
        share = m0 / total
        found.append((m0, tex, kept, excess, m1 / norm1, sigma, cos_sigma, share, back))
    found.sort(key=lambda x: -x[0])
    lights, out = [], None
    for m0, tex, kept, excess, d, sigma, cos_sigma, share, back in found:
        if len(lights) == max_lights:
            break
        if sigma > max_angular_radius or share < min_power_share or sigma <= 0:
            continue
        if out is None:
            out = flat.copy()
        out[tex, :3] = kept
        radiance = (excess * omega[tex, None]).sum(0) / (2.0 * math.pi * (1.0 - cos_sigma))
        peak = float(radiance.max())
        e_perp = math.pi * math.sin(sigma) ** 2 * peak  # lux: irradiance on a facing plane
        dtype = env.dtype
        lights.append(
            DirectionalLight(
                direction=np.asarray(-d, dtype),
                color=np.asarray(radiance / peak, dtype),
                intensity=np.asarray(e_perp, dtype),
                angular_radius=np.asarray(sigma, dtype),
            )
        )
        info["lights"].append(
            dict(
                direction=[float(x) for x in d],
                angular_radius_deg=math.degrees(sigma),
                radiance=[float(x) for x in radiance],
                power_share=share,
                texels=int(len(tex)),
                background=[float(x) for x in back],
            )
        )
    if not lights:
        return ExtractedLights((), env, info)
    out = out.reshape(level.shape)
    meta = dict(env.metadata)
    meta["extracted_lights"] = str(len(lights))
    return ExtractedLights(tuple(lights), Cubemap((out,), meta), info)


def lights_to_json(extracted: ExtractedLights) -> dict:
    """The extracted lights as JSON-ready data: jaxpbr's own fields per light and a glTF-style
    `KHR_lights_punctual` light list (type "directional", color, intensity in lux) whose entries
    carry the angular radius in `extras.angular_radius` (radians; KHR has no field for it) and
    the direction the light travels (a glTF node's -Z) in `extras.direction`."""
    khr = []
    for i, (light, rec) in enumerate(zip(extracted.lights, extracted.info["lights"])):
        khr.append(
            dict(
                name=f"extracted_light_{i}",
                type="directional",
                color=[float(x) for x in np.asarray(light.color)],
                intensity=float(np.asarray(light.intensity)),
                extras=dict(
                    angular_radius=float(np.asarray(light.angular_radius)),
                    direction=[float(x) for x in np.asarray(light.direction)],
                    power_share=rec["power_share"],
                ),
            )
        )
    cfg = {k: v for k, v in extracted.info.items() if k != "lights"}
    return dict(
        conventions="direction: unit vector towards the light, jaxpbr world axes (+Y up); radiance: linear RGB "
        "per sr; intensity: lux on a plane facing the light = pi sin^2(angular_radius) max(radiance)",
        extraction=cfg,
        lights=extracted.info["lights"],
        KHR_lights_punctual=dict(lights=khr),
    )
