"""Validators for configuration values (sizes, counts, option names), shared by every module.

Configuration is static (it shapes the traced program), so it is always concrete and always checked.
Each raises `ValueError` naming the argument, the value and the fix.
"""

from __future__ import annotations

import numbers

__all__ = ["choice", "positive_int"]


def positive_int(name: str, value, *, minimum: int = 1) -> int:
    """`value` as an int >= `minimum` (default 1); bools and non-integers are refused."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def choice(name: str, value, options) -> str:
    """`value` if it is one of `options`, else a ValueError listing them."""
    if value not in options:
        raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(map(repr, options))}")
    return value
