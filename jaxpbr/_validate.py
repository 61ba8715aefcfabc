"""Validators for configuration values (sizes, counts, option names), shared by every module.

Configuration is static (it shapes the traced program), so it is always concrete and always checked.
Array inputs (colours, positions, intensities) may be tracers under jit/vmap/grad: their shapes are
always checked, their values only when concrete (`check_values`). Each raises `ValueError` naming
the argument, the value and the fix.
"""

from __future__ import annotations

import numbers

import jax
import jax.numpy as jnp
import numpy as np

from ._numerics import as_float, is_concrete, outside_traces, remember_per_array
from ._pytree import fields_of

__all__ = ["batch_shape", "check_radiance", "check_values", "choice", "positive_int", "vector"]


def positive_int(name: str, value, *, minimum: int = 1, where: str | None = None, fix: str | None = None) -> int:
    """`value` as an int >= `minimum` (default 1); bools, floats and strings are refused.

    The message names the argument (prefixed by `where`, e.g. the function, if given), the value
    and, if given, the fix.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        what = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
        prefix = f"{where}: " if where else ""
        suffix = f"; {fix}" if fix else ""
        raise ValueError(f"{prefix}{name} must be {what}, got {value!r}{suffix}")
    return int(value)


def choice(name: str, value, options) -> str:
    """`value` if it is one of `options`, else a ValueError listing them."""
    if value not in options:
        raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(map(repr, options))}")
    return value


def vector(name: str, x, n: int = 3):
    """`x` as a float array (`as_float`: Python numbers stay weakly typed) with a trailing axis of `n`."""
    x = as_float(x)
    if x.ndim == 0 or x.shape[-1] != n:
        raise ValueError(f"{name} must have a trailing axis of {n}, got shape {x.shape}.")
    return x


def check_values(name: str, x, *, lo=None, hi=None, open_lo: bool = False, finite: bool = True):
    """Check the values of a concrete array (finite; >= lo, or > lo with `open_lo`; <= hi);
    tracers pass unchecked (their values do not exist yet). Returns `x`."""
    if not is_concrete(x):
        return x
    a = np.asarray(x)
    if finite and not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or Inf; pass finite values.")
    if lo is not None and a.size and (np.any(a <= lo) if open_lo else np.any(a < lo)):
        raise ValueError(f"{name} must be {'>' if open_lo else '>='} {lo:g}, got {a.min():g}.")
    if hi is not None and a.size and np.any(a > hi):
        raise ValueError(f"{name} must be <= {hi:g}, got {a.max():g}.")
    return x


def batch_shape(where: str, *named, material=None) -> tuple:
    """The broadcast of the inputs' batch axes, or a ValueError naming the inputs that disagree.

    named: (name, array, rank) triples (rank: the trailing axes that are not batch axes, 1 for a
    3-vector); material: a `Pytree` whose array leaves are added as "m.<field>" with their declared
    ranks. Shapes are static, so this works on tracers too (a JAX broadcasting TypeError named
    neither the function nor the field)."""
    items = [(name, np.shape(x), rank) for name, x, rank in named]
    if material is not None:
        items += [(f"m.{f.name}", np.shape(getattr(material, f.name)), f.rank) for f in fields_of(material) if f.is_array]
    batches = [(name, shape[: len(shape) - rank] if len(shape) >= rank else shape) for name, shape, rank in items]
    try:
        return np.broadcast_shapes(*(b for _, b in batches))
    except ValueError:
        listed = ", ".join(f"{name} {b}" for name, b in batches if b)
        raise ValueError(
            f"{where}: the inputs' batch axes do not broadcast ({listed}); give them equal leading axes, "
            f"or size-1 / no batch axes for the ones shared by all"
        ) from None


_RADIANCE_OK: dict = {}  # arrays already found finite and >= 0 (`remember_per_array`)


def check_radiance(name: str, x):
    """Radiance must be finite and non-negative: raise a ValueError naming `name` (for a Cubemap,
    each level as "<name>.levels[m]") and the fix; tracers pass unchecked. Returns `x`.

    The one check of environment texels: `Environment` and every public function that takes an
    environment Cubemap (a NaN or negative texel otherwise came out as NaN pixels of `render`, NaN
    texels of `prefilter`, or was silently dropped by `irradiance`). Each concrete array is checked
    once for as long as it lives; on an accelerator by two reductions on the device (two scalars
    come back, not the array), on the CPU in place with NumPy (`np.asarray` is a view there)."""
    levels = getattr(x, "levels", None)
    if levels is not None:
        for m, lv in enumerate(levels):
            check_radiance(f"{name}.levels[{m}]", lv)
        return x
    if is_concrete(x):
        remember_per_array(_RADIANCE_OK, x, "radiance", lambda: _radiance_ok(name, x))
    return x


def _on_host(x) -> bool:
    """Whether x's memory is host memory (a NumPy array or a CPU-device array)."""
    return isinstance(x, np.ndarray) or all(d.platform == "cpu" for d in getattr(x, "devices", lambda: ())())


def _radiance_ok(name: str, x) -> bool:
    if _on_host(x):
        a = np.asarray(x)
        lo, hi = (a.min(), a.max()) if a.size else (0.0, 0.0)
    else:
        # Two reductions on the device and two numbers back; on another thread, so that a call
        # made while tracing (a constant environment under an outer jit) runs them concretely.
        lo, hi = outside_traces(lambda: jax.device_get((jnp.min(x), jnp.max(x)))) if x.size else (0.0, 0.0)
    if np.isfinite(lo) and np.isfinite(hi) and lo >= 0:  # NaN, -Inf and +Inf reach lo or hi
        return True
    a = np.asarray(x)  # the error path: count them on the host
    finite = np.isfinite(a)
    if not finite.all():
        raise ValueError(
            f"{name} has {int(a.size - np.count_nonzero(finite))} NaN/Inf values; radiance must be finite "
            "(find where they come from, or replace them explicitly, e.g. np.nan_to_num)"
        )
    raise ValueError(
        f"{name} has {int(np.count_nonzero(a < 0))} negative values (min {float(a.min()):g}); radiance cannot be "
        "negative (clamp them with np.maximum(x, 0), or use --clamp-negative on the command line)"
    )
