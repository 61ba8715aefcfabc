"""Exception types for bad user input."""

from __future__ import annotations

__all__ = ["Float16RangeError", "InputError"]


class InputError(ValueError):
    """Bad input (file, argument, image contents): the message names the problem and the fix."""


class Float16RangeError(InputError):
    """Values beyond a 16-bit float format's range (|x| <= 65504) that would be stored as Inf.

    Carries `fmt` (the format asked for), `wide` (its 32-bit counterpart), `count` and `peak`, so
    that a front end can name its own option in the fix (the command line names `--ktx-format`)."""

    def __init__(self, message: str, *, fmt: str, wide: str, count: int, peak: float):
        super().__init__(message)
        self.fmt, self.wide, self.count, self.peak = fmt, wide, count, peak
