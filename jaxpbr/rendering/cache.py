"""`AssetCache`: the content-addressed cache of precomputed IBL maps (memory, optionally a
directory), and `content_key`, the SHA-1 of an environment's texels that keys it.

`ASSETS` is the process's default cache; the renderer uses it unless a call passes its own."""

from __future__ import annotations

import hashlib
import json
import os
import threading
from collections import OrderedDict
from pathlib import Path

import jax
import numpy as np

from .._numerics import outside_traces, remember_per_array
from .._version import __version__
from ..ibl.cubemap import Cubemap
from ..io.atomic import atomic_write
from ..shading.lights import DirectionalLight


class AssetCache:
    """LRU cache of precomputed IBL maps keyed by (environment content hash, kind, parameters).

    `render`, `render_batch`, `bake` and `plan` take one as `cache=`; without it they use the
    process's default instance, `ASSETS`. Each cache keeps its own entries and counts.

    It only ever holds concrete arrays: `get` runs the precompute outside any trace
    (`_numerics.outside_traces`), and the renderer caches nothing for a traced environment.

    `stats[kind]` counts hits and misses ("irradiance", "prefilter", "lut"), which is how tests
    and users check what a render actually computed.

    `directory`: optionally a folder where computed cube maps are also kept across processes
    (`use_directory`; the command line turns it on, under the user's cache dir): a map found
    there is loaded instead of computed, and so are the suns split out of an environment with
    their residual map (kind "extract"). Files are keyed by the SHA-1 of (kind, key, jaxpbr and
    jax versions), written atomically, and a file that cannot be read is recomputed; failing to
    write one never fails the render. `stats[kind]["disk"]` counts the maps loaded from it.
    """

    DISK_KINDS = ("irradiance", "prefilter", "sky", "extract")

    def __init__(self, maxsize: int = 16, directory=None):
        self.maxsize = maxsize
        self._store: OrderedDict = OrderedDict()
        self.stats: dict[str, dict[str, int]] = {}
        self.directory = None if directory is None else Path(directory)
        # The renderer fills the cache from worker threads: the store and the counters are
        # updated under this lock (the precomputes themselves run outside it, concurrently).
        self._lock = threading.RLock()

    def use_directory(self, directory) -> None:
        """Keep computed maps in `directory` too (None: memory only)."""
        self.directory = None if directory is None else Path(directory)

    def clear(self) -> None:
        with self._lock:
            self._store.clear()
            self.stats.clear()

    def find(self, kind: str, match):
        """A cached value of `kind` whose key satisfies match(key), counted as a hit; else None."""
        with self._lock:
            for (k, key), value in self._store.items():
                if k == kind and match(key):
                    self.stats.setdefault(kind, {"hits": 0, "misses": 0})["hits"] += 1
                    return value
        return None

    def get(self, kind: str, key, compute):
        full = (kind, key)
        with self._lock:
            st = self.stats.setdefault(kind, {"hits": 0, "misses": 0})
            if full in self._store:
                st["hits"] += 1
                self._store.move_to_end(full)
                return self._store[full]
            st["misses"] += 1
        # Loaded on another thread too: inside a caller's trace device_put returns a tracer.
        value = outside_traces(lambda: self._load(kind, key))
        if value is not None:
            with self._lock:
                st["disk"] = st.get("disk", 0) + 1
        else:
            # On another thread: a compute that closed over a tracer raises UnexpectedTracerError
            # there instead of returning it, so the store never holds one.
            value = outside_traces(compute)
            self._save(kind, key, value)
        with self._lock:
            self._store[full] = value
            while len(self._store) > self.maxsize:
                self._store.popitem(last=False)
        return value

    def _path(self, kind, key):
        if self.directory is None or kind not in self.DISK_KINDS:
            return None
        name = hashlib.sha1(repr((kind, key, __version__, jax.__version__)).encode()).hexdigest()
        return self.directory / f"{kind}-{name}.npz"

    def _load(self, kind, key):
        path = self._path(kind, key)
        if path is None or not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                value = _decode(z)
        except Exception:  # noqa: BLE001 -- unreadable or from an incompatible writer: compute it again
            return None
        _touch(path)
        return value

    def _save(self, kind, key, value) -> None:
        path = self._path(kind, key)
        arrays = None if path is None else _encode(value)
        if arrays is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, lambda tmp: np.savez(tmp, **arrays))
        except OSError:  # full disk, read-only cache dir: the render goes on uncached
            pass


#: Fields of the disc lights kept with an "extract" entry, in `DirectionalLight`'s order.
_LIGHT_FIELDS = ("direction", "color", "intensity", "angular_radius")


def _encode(value) -> dict | None:
    """The arrays of a disk entry: a `Cubemap`, or the (lights | None, residual) pair of
    `plan.split_environment`'s extraction; None for anything else (kept in memory only)."""
    if isinstance(value, Cubemap):
        arrays = {f"level{i}": np.asarray(lv) for i, lv in enumerate(value.levels)}
        arrays["num_levels"] = np.asarray(len(value.levels))
        arrays["info"] = np.asarray(json.dumps(dict(value.info)))
        return arrays
    if isinstance(value, tuple) and len(value) == 2 and (value[0] is None or isinstance(value[0], tuple)):
        lights, residual = value
        if lights is None:  # nothing split off: the caller keeps its own environment
            return {"num_lights": np.asarray(0)}
        if not isinstance(residual, Cubemap) or not all(isinstance(x, DirectionalLight) for x in lights):
            return None
        arrays = {f"residual_{k}": v for k, v in _encode(residual).items()}
        arrays["num_lights"] = np.asarray(len(lights))
        for f in _LIGHT_FIELDS:
            arrays[f"light_{f}"] = np.stack([np.asarray(getattr(x, f)) for x in lights])
        return arrays
    return None


def _decode(z):
    if "num_lights" not in z:
        n = int(z["num_levels"])
        return Cubemap([jax.device_put(z[f"level{i}"]) for i in range(n)], json.loads(str(z["info"])))
    n = int(z["num_lights"])
    if n == 0:
        return None, None
    residual = _decode({k[len("residual_"):]: z[k] for k in z.files if k.startswith("residual_")})
    fields = {f: z[f"light_{f}"] for f in _LIGHT_FIELDS}
    # (0-d arrays, not NumPy scalars: jnp.asarray would run a program for a scalar)
    return tuple(DirectionalLight(**{f: np.asarray(fields[f][i]) for f in _LIGHT_FIELDS}) for i in range(n)), residual


#: The process's default cache: `render`, `render_batch`, `bake` and `plan` use it unless given
#: another (`cache=`).
ASSETS = AssetCache()


def cache_or_default(cache: AssetCache | None) -> AssetCache:
    """`cache`, or the default `ASSETS` when it is None."""
    if cache is None:
        return ASSETS
    if not isinstance(cache, AssetCache):
        raise TypeError(f"cache must be a jaxpbr.rendering.cache.AssetCache or None, got {type(cache).__name__}")
    return cache


_KEYS: dict = {}  # (id(level-0 array), "sha1") -> (weakref to it, content key)


def content_key(cube: Cubemap) -> str:
    """SHA-1 of a cube map's level-0 texels, shape and dtype (what its precomputes depend on).

    Remembered per array object (arrays are immutable), so rendering the same environment again
    neither copies it to the host nor hashes it again."""
    lv = cube.levels[0]

    def digest():
        a = np.ascontiguousarray(np.asarray(lv))
        h = hashlib.sha1(a.tobytes())
        h.update(repr((a.shape, str(a.dtype))).encode())
        return h.hexdigest()

    return remember_per_array(_KEYS, lv, "sha1", digest)


def _touch(path) -> None:
    """Mark a file of the cache as just used: the command line's pruning (`cli._cache.prune`) deletes
    the oldest modification times first, so a map or BVH read often stays."""
    try:
        os.utime(path)
    except OSError:  # a read-only cache: nothing to mark
        pass
