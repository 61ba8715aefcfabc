"""Validators for configuration values (sizes, counts, option names), shared by every module.

Configuration is static (it shapes the traced program), so it is always concrete and always checked.
Each raises `ValueError` naming the argument, the value and the fix.
"""

from __future__ import annotations

import numbers

__all__ = ["choice", "positive_int"]


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
