"""Exception types for bad user input."""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Bad input (file, argument, image contents): the message names the problem and the fix."""
