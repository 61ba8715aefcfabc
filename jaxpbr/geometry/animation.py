"""Keyframe sampling of glTF 2.0 animations (§3.11, Appendix C), for NumPy and JAX alike.

A sampler is its key times (K,), strictly increasing, and its output values: (K, C) for STEP and
LINEAR, (K, 3, C) for CUBICSPLINE (in-tangent a_k, value v_k, out-tangent b_k of each key). The
value at time t:

* before the first key and after the last, the first and the last value (clamped);
* STEP: v_k of the last key with t_k <= t;
* LINEAR: (1 - s) v_k + s v_k+1 with s = (t - t_k) / (t_k+1 - t_k); rotations (unit quaternions,
  x y z w) by spherical linear interpolation along the shorter arc:
  q = sin((1 - s) a) / sin a · q_k + sign(q_k·q_k+1) sin(s a) / sin a · q_k+1, a = acos |q_k·q_k+1|;
* CUBICSPLINE: the cubic Hermite spline with tangents scaled by the key interval t_d:
  p = (2s³ - 3s² + 1) v_k + t_d (s³ - 2s² + s) b_k + (-2s³ + 3s²) v_k+1 + t_d (s³ - s²) a_k+1;
* rotations are normalised after interpolation (CUBICSPLINE's are not unit on their own; LINEAR's
  keys may be normalised integers, unit only to their quantisation).

Every function takes `xp` (numpy or jax.numpy): the loader poses an asset at a time in NumPy
float64, and the same code traced by JAX poses it inside a jit-compiled, vmapped or differentiated
function (gradients reach the key values and the time). Near-equal quaternions (a -> 0) fall back to
the normalised linear blend, which agrees with slerp to O(a²) there; the angle is never taken of
a value at or above 1, so gradients stay finite (the double-`where` pattern, docs/math.md §8.10).
"""

from __future__ import annotations

import numpy as np

from .pose import unit_rows

__all__ = ["INTERPOLATIONS", "PATHS", "normalize_quaternion", "sample", "slerp"]

#: The samplers' interpolation modes (glTF 2.0 §3.11, `animation.sampler.interpolation`).
INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")
#: The animated properties of a node (`animation.channel.target.path`) and their components
#: (weights: one per morph target).
PATHS = {"translation": 3, "rotation": 4, "scale": 3, "weights": None}

#: Below this 1 - |cos a| two quaternions are blended linearly (then normalised): slerp's
#: sin((1 - s) a) / sin a differs from 1 - s by O(a²) ≈ 2e-7 there, under float32's resolution.
_SLERP_LINEAR = 1e-7


def normalize_quaternion(q, xp=np):
    """q / |q| along the last axis (a zero quaternion stays zero, with a finite gradient)."""
    return unit_rows(q, xp)


def slerp(q0, q1, s, xp=np):
    """Spherical linear interpolation of unit quaternions (..., 4) along the shorter arc, s in [0, 1]
    (broadcast against q's leading axes)."""
    d = xp.sum(q0 * q1, axis=-1, keepdims=True)
    sign = xp.where(d < 0, -1.0, 1.0).astype(q0.dtype)
    c = xp.abs(d)
    s = xp.asarray(s, q0.dtype)[..., None] if xp.ndim(s) == q0.ndim - 1 else xp.asarray(s, q0.dtype)
    near = c > 1.0 - _SLERP_LINEAR
    a = xp.arccos(xp.where(near, 0.5, xp.minimum(c, 1.0)))
    sin_a = xp.sin(a)
    w0 = xp.where(near, 1.0 - s, xp.sin((1.0 - s) * a) / sin_a)
    w1 = xp.where(near, s, xp.sin(s * a) / sin_a)
    return normalize_quaternion(w0 * q0 + (sign * w1) * q1, xp)


def _locate(times, t, xp):
    """(k, s, last): the interval [t_k, t_k+1] holding t (clamped to the keys), the fraction s in
    [0, 1] within it, and the index of the last key at or before t (STEP)."""
    K = times.shape[0]
    last = xp.clip(xp.searchsorted(times, t, side="right") - 1, 0, K - 1)
    k = xp.clip(last, 0, max(K - 2, 0))
    if K < 2:
        return k, xp.zeros_like(xp.asarray(t, times.dtype)), last
    t0, t1 = times[k], times[k + 1]
    s = xp.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    return k, s, last


def sample(times, values, interpolation: str, t, *, rotation: bool = False, xp=np):
    """The sampler's value at time t (a scalar): (C,) for values (K, C) or (K, 3, C) (CUBICSPLINE).

    times: (K,) strictly increasing key times in seconds. rotation: the values are quaternions
    (slerp for LINEAR, the result normalised for every mode)."""
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
    t = xp.asarray(t, times.dtype)
    k, s, last = _locate(times, t, xp)
    K = times.shape[0]
    if interpolation == "CUBICSPLINE":
        v = values[:, 1]
        if K < 2:
            out = v[0]
        else:
            td = times[k + 1] - times[k]
            s2, s3 = s * s, s * s * s
            out = ((2 * s3 - 3 * s2 + 1) * v[k] + td * (s3 - 2 * s2 + s) * values[k, 2]
                   + (-2 * s3 + 3 * s2) * v[k + 1] + td * (s3 - s2) * values[k + 1, 0])
            # (outside the keys s is clamped to 0 or 1: the first or the last value exactly)
    elif interpolation == "STEP" or K < 2:
        out = values[last]
    elif rotation:
        return slerp(values[k], values[k + 1], s, xp)
    else:
        out = (1.0 - s) * values[k] + s * values[k + 1]
    return normalize_quaternion(out, xp) if rotation else out
