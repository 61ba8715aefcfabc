"""The command line's caches on disk: JAX's persistent compilation cache and the baked IBL maps.

Most of a cold `jaxpbr` run is XLA compilation; the compiled programs are the same from run to
run, so the CLI keeps them on disk (JAX's persistent compilation cache): a warm rerun skips the
compiler. Where the cache lives, in order:

1. `JAXPBR_COMPILATION_CACHE`: a directory, or "0" / "off" / "" to switch the cache off;
2. `JAX_COMPILATION_CACHE_DIR` (JAX's own setting), if the user set it;
3. `$XDG_CACHE_HOME/jaxpbr/jax-compilation-cache-lru` (default `~/.cache/...`; on Windows
   `%LOCALAPPDATA%\\jaxpbr\\...`).

JAX's own size limit (`jax_compilation_cache_max_size`, least recently used first) keeps jaxpbr's
directories (1 and 3) to `MAX_BYTES`; a directory the user gave JAX (2) is left to the user's
settings (it may be shared with other projects). The cache key is the program, the
compile options, the backend and the jax/jaxlib versions, so a stale entry is never used; a
directory that cannot be created or written leaves the run uncached (JAX warns), never failing it.

The irradiance and prefiltered maps the renderer computes are kept too (`renderer.ASSETS`, keyed by
the environment's content, the parameters and the jaxpbr / jax versions), so rendering a scene
again with the same environment loads them instead of computing them:
`JAXPBR_ASSET_CACHE` (a directory, or "0" / "off") else `<cache base>/jaxpbr/assets`.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import jax

from .. import _program_cache

#: Largest cache size kept; beyond it the oldest files are deleted down to half.
MAX_BYTES = 1 << 30

ENV = "JAXPBR_COMPILATION_CACHE"
ASSET_ENV = "JAXPBR_ASSET_CACHE"
_OFF = ("", "0", "off", "false", "no")


def _base() -> Path:
    if sys.platform == "win32" and os.environ.get("LOCALAPPDATA"):
        return Path(os.environ["LOCALAPPDATA"]) / "jaxpbr"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "jaxpbr"


def default_dir() -> Path:
    # "-lru": entries written under JAX's size limit carry access-time files; a directory filled
    # without the limit (older jaxpbr, or JAX without filelock) made every write under it warn.
    return _base() / "jax-compilation-cache-lru"


def asset_dir() -> Path | None:
    """Where baked maps are kept, or None when switched off."""
    own = os.environ.get(ASSET_ENV)
    if own is not None:
        return None if own.strip().lower() in _OFF else Path(own).expanduser()
    return _base() / "assets"


def cache_dir() -> Path | None:
    """The directory the CLI uses, or None when switched off (see the module docstring)."""
    own = os.environ.get(ENV)
    if own is not None:
        return None if own.strip().lower() in _OFF else Path(own).expanduser()
    jax_dir = os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir
    if jax_dir:
        return Path(jax_dir).expanduser()
    return default_dir()


def prune(path: Path, max_bytes: int = MAX_BYTES) -> None:
    """Delete the oldest files until the directory holds at most max_bytes / 2 (when over max_bytes)."""
    try:
        files = [(p.stat().st_mtime, p.stat().st_size, p) for p in Path(path).iterdir() if p.is_file()]
    except OSError:
        return
    total = sum(s for _, s, _ in files)
    if total <= max_bytes:
        return
    for _, size, p in sorted(files):
        try:
            p.unlink()
        except OSError:
            continue
        total -= size
        if total <= max_bytes // 2:
            break


def enable_assets() -> Path | None:
    """Keep the renderer's computed IBL maps on disk; returns the directory or None."""
    from ..rendering.mesh import ACCELS
    from ..rendering.renderer import ASSETS

    path = asset_dir()
    if path is not None:
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:
            return None
        prune(path)
    ASSETS.use_directory(path)
    ACCELS.use_directory(path)  # the JAX backend's mesh BVHs beside the maps (pruned with them)
    # the render stages' compiled programs too (`jaxpbr._program_cache`): a warm run loads them
    # instead of tracing, lowering and compiling them
    _program_cache.use_directory(path)
    return path


def enable(path: Path | None = None) -> Path | None:
    """Turn the persistent compilation cache on (before the first compilation); returns the
    directory or None."""
    path = cache_dir() if path is None else path
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # unwritable location: run uncached
    users = os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir
    if not (users and Path(users).expanduser() == path and os.environ.get(ENV) is None):
        # jaxpbr's own directory: JAX evicts the least recently used entries beyond the limit.
        # JAX needs filelock for that (a dependency); without it a size limit made every cache
        # read fail with a warning, so the limit is only set where filelock imports.
        try:
            import filelock  # noqa: F401
        except ImportError:
            pass
        else:
            jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    jax.config.update("jax_compilation_cache_dir", str(path))
    # Every program: the CLI's are many small ones, and reading one back is far cheaper than
    # compiling it (JAX's default caches only those that took over a second).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
