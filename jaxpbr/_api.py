"""Keyword-only options, with a deprecation period for callers that still pass them positionally.

Public functions take their data positionally and every option (size, count, method, model name,
flag) by keyword (`tests/test_api.py` checks this). Functions whose options used to be positional
are wrapped with `keyword_only(...)`: their signature (what `inspect.signature`, `help` and jit's
`static_argnames` see) is the keyword-only one, and a call that still passes those options
positionally keeps working but emits a `DeprecationWarning` naming the keyword to use.
"""

from __future__ import annotations

import functools
import inspect
import warnings

__all__ = ["keyword_only"]

_POSITIONAL = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)


def keyword_only(*legacy: str):
    """Decorator for a function whose options `legacy` (keyword-only now) were positional before,
    in that order right after its positional parameters."""

    def wrap(fn):
        sig = inspect.signature(fn)
        n_pos = sum(p.kind in _POSITIONAL for p in sig.parameters.values())
        for name in legacy:
            if name not in sig.parameters or sig.parameters[name].kind is not inspect.Parameter.KEYWORD_ONLY:
                raise TypeError(f"keyword_only: {fn.__qualname__} has no keyword-only parameter {name!r}")
        qualname = fn.__qualname__

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            if len(args) > n_pos:
                extra = args[n_pos:]
                if len(extra) > len(legacy):
                    raise TypeError(f"{qualname}() takes {n_pos} positional argument(s) but {len(args)} were given")
                names = legacy[: len(extra)]
                for name in names:
                    if name in kwargs:
                        raise TypeError(f"{qualname}() got multiple values for argument {name!r}")
                warnings.warn(
                    f"{qualname}: passing {', '.join(names)} positionally is deprecated; pass "
                    + ", ".join(f"{n}=..." for n in names)
                    + " by keyword (options are keyword-only)",
                    DeprecationWarning,
                    stacklevel=2,
                )
                kwargs.update(zip(names, extra))
                args = args[:n_pos]
            return fn(*args, **kwargs)

        wrapper.__deprecated_positional__ = tuple(legacy)
        return wrapper

    return wrap
