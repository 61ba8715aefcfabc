"""Compiled render stages kept on disk, so that a later process neither traces, lowers nor compiles
them: it loads the executable.

`cached_jit(fn, static_argnums=..., static_argnames=...)` behaves as `jax.jit(fn, ...)`. While a
directory is set (`use_directory`; the command line sets its asset cache, the library sets none),
a call outside any transformation looks for the compiled program under a key of everything the
program depends on:

* the function (module and qualified name) and a digest of every file of the jaxpbr package
  (sources and data: any change to the code gives new keys);
* jax / jaxlib versions, the backend, its devices (kind and count), the host's processor
  (architecture and instruction-set flags: an executable is compiled for them), `XLA_FLAGS`, and
  the JAX settings that change what a trace produces (`jax_enable_x64`, dtype and rank promotion,
  default matmul precision, ...);
* the static arguments and the tree structure of the others (their auxiliary data included),
  written out by a strict encoder that accepts only plain values (numbers, strings, booleans,
  None, tuples, lists, dicts, dataclasses, enums, dtypes, and jaxpbr's own module-level
  functions, whose code the digest covers): anything else, a closure or an array among the static
  values, makes the call uncached rather than risk two programs sharing a key;
* each array argument's shape, dtype and weak type.

Only XLA:CPU programs are kept (the staged execution that runs the stages one by one is the CPU's;
a GPU runs a render as one program through `jax.jit`). A program holding a host callback (the host
ray engine's) is never stored: it names Python objects of its process; it is compiled for the
process only. Anything that fails to serialize runs through `jax.jit`, and the process remembers
that; so does a loaded executable that fails to run (its file is deleted). A damaged or foreign
file is ignored and rewritten. Files are written atomically (a temporary file renamed over) and
marked as used when read (the command line prunes the directory oldest first).

`preparing()` / `prepare(fn, ...)`: a call on abstract arguments (inside `jax.eval_shape`) starts
the program on the compile threads (loading it, or tracing and lowering it on the caller's thread
and compiling it there) and returns zeros of its result's shapes; the concrete call waits for it. A
staged render runs its pass this way first (`rendering.stages.prepare_pass`), so its stages
compile or load side by side and beside the environment's precomputes; the command line prepares
the display transform before the render. A file holds the key, the executable, its trees and the
result's shapes (`_FORMAT`; a file of another layout is compiled again and rewritten).

The executable comes from `jax.experimental.serialize_executable`, the XLA backend's own
serialization (what JAX's persistent compilation cache stores), wrapped with the argument and
result trees. A stage is compiled for this cache without JAX's persistent compilation cache (an
executable read from that cache serializes incompletely), so the first run after a change of the
package compiles the stages even where JAX's cache holds them."""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import enum
import functools
import hashlib
import os
import pickle
import platform
import threading
import types
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import jax
import numpy as np

__all__ = ["active", "cached_jit", "directory", "is_preparing", "package_digest", "prepare", "preparing", "use_directory"]

_STATE: dict = {"dir": None}
_DIGEST: list[str] = []
_CONFIG = (
    "jax_enable_x64",
    "jax_numpy_rank_promotion",
    "jax_numpy_dtype_promotion",
    "jax_default_matmul_precision",
    "jax_enable_checks",
    "jax_debug_nans",
    "jax_debug_infs",
    "jax_default_prng_impl",
    "jax_threefry_partitionable",
)
#: File name prefix in the cache directory.
PREFIX = "program-"
#: Layout of a stored file (another is compiled again and rewritten).
_FORMAT = "jaxpbr-program-2"


def use_directory(path) -> None:
    """Keep compiled stages under `path` (None: off, the default)."""
    _STATE["dir"] = None if path is None else Path(path)


def directory() -> Path | None:
    return _STATE["dir"]


class _Uncacheable(Exception):
    pass


def _canon(x) -> str:
    """A string that names `x` exactly, for plain values only (else _Uncacheable). A value whose
    type defines `_program_key()` (static metadata whose equality sees part of it, `CubeInfo`) is
    named by that."""
    key_of = getattr(type(x), "_program_key", None)
    if key_of is not None:
        return f"{type(x).__module__}.{type(x).__qualname__}:{_canon(key_of(x))}"
    if x is None or isinstance(x, (bool, int, str)):
        return f"{type(x).__name__}:{x!r}"
    if isinstance(x, float):
        return f"float:{x.hex()}"
    if isinstance(x, np.generic):
        return f"{type(x).__name__}:{_canon(x.item())}"
    if isinstance(x, np.dtype):
        return f"dtype:{x.str}"
    if isinstance(x, type) and issubclass(x, np.generic):
        return f"dtype:{np.dtype(x).str}"
    if isinstance(x, enum.Enum):
        return f"{type(x).__module__}.{type(x).__qualname__}.{x.name}"
    if isinstance(x, (tuple, list, frozenset)):
        items = sorted(_canon(e) for e in x) if isinstance(x, frozenset) else [_canon(e) for e in x]
        return f"{type(x).__name__}({','.join(items)})"
    if isinstance(x, dict):
        pairs = sorted((_canon(k), _canon(v)) for k, v in x.items())
        return "dict(" + ",".join(f"{k}={v}" for k, v in pairs) + ")"
    if (isinstance(x, types.FunctionType) and x.__module__.startswith("jaxpbr.") and x.__closure__ is None
            and "<" not in x.__qualname__):
        # a module-level jaxpbr function: its code is in the package digest
        return f"function:{x.__module__}.{x.__qualname__}"
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        t = type(x)
        fields = ",".join(f"{f.name}={_canon(getattr(x, f.name))}" for f in dataclasses.fields(x))
        return f"{t.__module__}.{t.__qualname__}({fields})"
    raise _Uncacheable(type(x).__name__)


def _canon_tree(td) -> str:
    """The tree structure with every node's type and auxiliary data, through `_canon`."""
    data = td.node_data()
    if data is None:
        return "*"
    t, aux = data
    return f"{t.__module__}.{t.__qualname__}[{_canon(aux)}](" + ",".join(_canon_tree(c) for c in td.children()) + ")"


def package_digest() -> str:
    """sha256 over every file of the installed jaxpbr package (read once per process): a key part
    for anything computed by the package's code and kept across processes."""
    return _package_digest()


def _package_digest() -> str:
    """sha256 over the relative paths and contents of every file of the jaxpbr package."""
    if not _DIGEST:
        root = Path(__file__).resolve().parent
        h = hashlib.sha256()
        for p in sorted(root.rglob("*")):
            if p.is_file() and "__pycache__" not in p.parts:
                h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
        _DIGEST.append(h.hexdigest())
    return _DIGEST[0]


@functools.lru_cache(maxsize=1)
def _host_cpu() -> str:
    """The processor an executable is compiled for (read once per process)."""
    flags = ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    flags = " ".join(sorted(line.split(":", 1)[1].split()))
                    break
    except OSError:
        pass
    return f"{platform.machine()} {platform.processor()} {flags}"


@functools.lru_cache(maxsize=1)
def _platform_key() -> str:
    """What is fixed once JAX's backend is up: versions, devices, the host processor."""
    import jaxlib

    devs = jax.devices()
    return "\n".join([
        f"jax {jax.__version__} jaxlib {jaxlib.__version__}",
        f"{jax.default_backend()} {devs[0].device_kind} {len(devs)} {getattr(devs[0].client, 'platform_version', '')}",
        _host_cpu(),
    ])


def _environment_key() -> str:
    """`_platform_key` and what may change while a process runs: XLA_FLAGS (read when a backend
    starts, so in practice fixed too) and the JAX settings that change a trace (contexts such as
    `jax.enable_x64` included)."""
    cfg = ",".join(f"{n}={_canon(getattr(jax.config, n, None))}" for n in _CONFIG)
    return "\n".join([_platform_key(), f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')}", cfg])


def _has_callback(jaxpr) -> bool:
    """Whether a (closed) jaxpr or any jaxpr inside it calls back into Python."""
    from jax.extend.core import ClosedJaxpr, Jaxpr

    stack = [jaxpr.jaxpr if hasattr(jaxpr, "jaxpr") else jaxpr]
    while stack:
        j = stack.pop()
        for eqn in j.eqns:
            if "callback" in eqn.primitive.name:
                return True
            for v in eqn.params.values():
                for sub in v if isinstance(v, (tuple, list)) else (v,):
                    if isinstance(sub, ClosedJaxpr):
                        stack.append(sub.jaxpr)
                    elif isinstance(sub, Jaxpr):
                        stack.append(sub)
    return False


class _Entry:
    """A program of one key: `future` gives the executable (None: the call goes through jax.jit);
    `out_tree` and `out_avals` (flat (shape, dtype, weak) triples) are known before it is ready."""

    __slots__ = ("future", "out_tree", "out_avals")

    def __init__(self, future: Future, out_tree, out_avals):
        self.future, self.out_tree, self.out_avals = future, out_tree, out_avals


def _done(value) -> Future:
    f: Future = Future()
    f.set_result(value)
    return f


_POOL: dict = {"pool": None, "pid": 0}
_POOL_LOCK = threading.Lock()


def _compile_pool() -> ThreadPoolExecutor:
    """Threads that compile and load the programs started by `preparing` (XLA compiles without
    the GIL): one per core, started on first use and kept; a forked child starts its own."""
    with _POOL_LOCK:
        if _POOL["pool"] is None or _POOL["pid"] != os.getpid():
            _POOL["pool"] = ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 2), thread_name_prefix="jaxpbr-compile")
            _POOL["pid"] = os.getpid()
        return _POOL["pool"]


_PREPARING: contextvars.ContextVar[bool] = contextvars.ContextVar("jaxpbr_preparing", default=False)


def active() -> bool:
    """Whether calls of `cached_jit` functions use the directory (set, and XLA:CPU)."""
    return _STATE["dir"] is not None and jax.default_backend() == "cpu"


@contextlib.contextmanager
def preparing():
    """Within: a `cached_jit` function called on traced arguments (inside `jax.eval_shape`, say)
    starts loading or compiling its program for their shapes on the compile threads, and returns
    zeros of its result's shapes at once; the concrete call later waits for that program. A
    staged render runs its stages once this way before the first one (`stages.prepare_pass`): the
    programs then compile side by side, and beside the precomputes, instead of one after another."""
    token = _PREPARING.set(True)
    try:
        yield
    finally:
        _PREPARING.reset(token)


def is_preparing() -> bool:
    """Whether this thread is inside `preparing()`."""
    return _PREPARING.get()


def prepare(fn: Callable, *args, **kwargs):
    """fn(*args, **kwargs) run abstractly (`jax.eval_shape`, args: arrays or `jax.ShapeDtypeStruct`)
    within `preparing()`: the `cached_jit` programs it calls start loading or compiling on the
    compile threads. Returns the result's shapes; None (and nothing started) while no directory is
    in use."""
    if not active():
        return None
    abstract = lambda a: bool(jax.tree_util.tree_leaves(a)) and all(  # noqa: E731
        isinstance(x, (jax.ShapeDtypeStruct, jax.Array, np.ndarray)) for x in jax.tree_util.tree_leaves(a))
    pos = [i for i, a in enumerate(args) if abstract(a)]

    def call(*dyn):
        full = list(args)
        for i, x in zip(pos, dyn):
            full[i] = x
        return fn(*full, **kwargs)

    with preparing():  # (the other arguments, statics and numbers, as they are)
        return jax.eval_shape(call, *[args[i] for i in pos])


class cached_jit:
    """`jax.jit(fn, static_argnums=..., static_argnames=...)` whose compiled programs are kept in
    `directory()` (see the module docstring)."""

    def __init__(self, fn: Callable, *, static_argnums=(), static_argnames=()):
        self._fn = fn
        self._static_argnums = tuple(static_argnums) if isinstance(static_argnums, (tuple, list)) else (static_argnums,)
        self._static_argnames = (static_argnames,) if isinstance(static_argnames, str) else tuple(static_argnames)
        self._jit = jax.jit(fn, static_argnums=self._static_argnums, static_argnames=self._static_argnames)
        self._mem: dict[str, _Entry | None] = {}  # None: through jax.jit
        self._lock = threading.Lock()
        self.__wrapped__ = fn
        self.__name__ = getattr(fn, "__name__", "cached_jit")
        self.__qualname__ = getattr(fn, "__qualname__", self.__name__)
        self.__doc__ = fn.__doc__

    def lower(self, *args, **kwargs):
        return self._jit.lower(*args, **kwargs)

    def _cache_size(self) -> int:
        """Programs this process holds: jax.jit's, plus the ones loaded or stored here."""
        return self._jit._cache_size() + sum(1 for v in self._mem.values() if v is not None)

    def clear_cache(self) -> None:
        self._jit.clear_cache()
        self._mem.clear()

    def __call__(self, *args, **kwargs):
        if not active():  # (measured and tested on XLA:CPU only)
            return self._jit(*args, **kwargs)
        root = _STATE["dir"]
        statics = {i: args[i] for i in self._static_argnums if i < len(args)}
        static_kw = {k: v for k, v in kwargs.items() if k in self._static_argnames}
        dyn = (tuple(a for i, a in enumerate(args) if i not in statics),
               {k: v for k, v in kwargs.items() if k not in static_kw})
        leaves, treedef = jax.tree_util.tree_flatten(dyn)
        traced = any(isinstance(x, jax.core.Tracer) for x in leaves)
        preparing = traced and _PREPARING.get()
        if traced and not preparing:
            return self._jit(*args, **kwargs)
        # Python numbers as the weakly typed arrays jax.jit makes of them
        leaves = [jax.numpy.asarray(x) if isinstance(x, (bool, int, float, complex)) else x for x in leaves]
        try:
            parts = [
                f"{self._fn.__module__}.{self._fn.__qualname__}",
                _package_digest(),
                _environment_key(),
                _canon(sorted(statics.items())),
                _canon(sorted(static_kw.items())),
                _canon_tree(treedef),
                ";".join(_aval(x) for x in leaves),
            ]
        except _Uncacheable:
            return self._jit(*args, **kwargs)
        key = hashlib.sha256("\n".join(parts).encode()).hexdigest()
        entry = self._mem.get(key, False)
        if entry is False:
            with self._lock:
                entry = self._mem.get(key, False)
                if entry is False:
                    avals = [jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=_weak(x)) for x in leaves]
                    entry = self._start(root, key, len(args), statics, static_kw, avals, treedef, background=preparing)
                    self._mem[key] = entry
        if preparing:
            if entry is None:
                return self._jit(*args, **kwargs)
            return jax.tree_util.tree_unflatten(entry.out_tree, [_zeros(*a) for a in entry.out_avals])
        if entry is None:
            return self._jit(*args, **kwargs)
        try:
            compiled = entry.future.result()
        except Exception:  # noqa: BLE001 (a program that failed to compile or load here: jax.jit)
            compiled = None
        if compiled is None:
            self._mem[key] = None
            return self._jit(*args, **kwargs)
        try:
            out = compiled(*leaves)
        except Exception:  # noqa: BLE001 (an executable that loads but does not run: dropped, jax.jit)
            self._mem[key] = None
            try:
                self._path(root, key).unlink()
            except OSError:
                pass
            return self._jit(*args, **kwargs)
        return jax.tree_util.tree_unflatten(entry.out_tree, out)

    # -- disk ---------------------------------------------------------------------------------
    @staticmethod
    def _path(root: Path, key: str) -> Path:
        return root / f"{PREFIX}{key[:40]}.bin"

    def _start(self, root, key, n_args, statics, static_kw, avals, treedef, *, background: bool):
        """The entry of `key`: the stored program (loaded), else the program traced and lowered on
        this thread and compiled (and stored); the loading or compiling runs on the compile
        threads when `background`, else here. None where it must go through jax.jit."""
        run = _compile_pool().submit if background else (lambda f: _done(f()))
        stored = self._read(root, key)
        if stored is not None:
            payload, in_tree, out_tree, result_tree, out_avals = stored
            path = self._path(root, key)
            return _Entry(run(lambda: self._deserialize(path, payload, in_tree, out_tree)), result_tree, out_avals)
        return self._compile(root, key, n_args, statics, static_kw, avals, treedef, run)

    def _read(self, root, key):
        path = self._path(root, key)
        try:
            blob = path.read_bytes()
        except OSError:
            return None
        try:
            fmt, stored_key, payload, in_tree, out_tree, result_tree, out_avals = pickle.loads(blob)
        except Exception:  # noqa: BLE001 (a damaged or foreign file: compiled again and rewritten)
            return None
        if fmt != _FORMAT or stored_key != key:
            return None
        return payload, in_tree, out_tree, result_tree, out_avals

    @staticmethod
    def _deserialize(path, payload, in_tree, out_tree):
        from jax.experimental import serialize_executable

        compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
        try:
            os.utime(path)
        except OSError:
            pass
        return compiled

    def _compile(self, root, key, n_args, statics, static_kw, avals, treedef, run):
        """Trace and lower the flat program of the argument `avals` here, then (through `run`)
        compile it without JAX's persistent compilation cache (see below) and store it; a program
        with a host callback is compiled for this process only. None where it must go through
        jax.jit."""
        from jax.experimental import serialize_executable

        fn = self._fn
        trees = []

        def flat(*xs):
            dyn_args, dyn_kwargs = jax.tree_util.tree_unflatten(treedef, xs)
            it = iter(dyn_args)
            full = [statics[i] if i in statics else next(it) for i in range(n_args)]
            out, tree = jax.tree_util.tree_flatten(fn(*full, **dyn_kwargs, **static_kw))
            trees.append(tree)
            return out

        # A name of its own: the program must not be a jax.jit program of this process that JAX
        # holds in memory (possibly read from its persistent cache, see below).
        flat.__name__ = flat.__qualname__ = f"{self.__name__}_stored"
        try:
            traced = jax.jit(flat).trace(*avals)
            lowered = traced.lower()
        except Exception:  # noqa: BLE001 (not traceable here: jax.jit raises the error itself)
            return None
        result_tree = trees[-1]
        out_avals = tuple((tuple(o.shape), np.dtype(o.dtype).str, bool(o.weak_type)) for o in traced.out_info)
        if _has_callback(traced.jaxpr):  # this process's program only (traced once, not twice)
            return _Entry(run(lowered.compile), result_tree, out_avals)
        path = self._path(root, key)

        def compile_and_store():
            # Compiled here, not read from JAX's persistent cache: an executable loaded from that
            # cache serializes without its kernels (it fails when called after loading: measured
            # with jax 0.10). The context is thread-local.
            from jax._src.config import enable_compilation_cache

            with enable_compilation_cache(False):
                compiled = lowered.compile()
            try:
                payload, in_tree, out_tree = serialize_executable.serialize(compiled)
                blob = pickle.dumps((_FORMAT, key, payload, in_tree, out_tree, result_tree, out_avals))
            except Exception:  # noqa: BLE001 (not serializable: this process's program only)
                return compiled
            tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
            try:
                root.mkdir(parents=True, exist_ok=True)
                tmp.write_bytes(blob)
                os.replace(tmp, path)
            except OSError:
                try:
                    tmp.unlink()
                except OSError:
                    pass
            return compiled

        return _Entry(run(compile_and_store), result_tree, out_avals)


def _weak(x) -> bool:
    aval = getattr(x, "aval", None)
    return bool(getattr(aval if aval is not None else x, "weak_type", False))


def _zeros(shape, dtype, weak):
    """Zeros of an aval inside a trace, weak type included (the next stage's key reads it)."""
    z = jax.numpy.zeros(shape, dtype)
    if weak:
        from jax._src.lax.lax import _convert_element_type

        z = _convert_element_type(z, np.dtype(dtype), weak_type=True)
    return z


def _aval(x) -> str:
    if isinstance(x, (jax.Array, np.ndarray, np.generic, jax.core.Tracer)):
        return f"{tuple(x.shape)}/{np.dtype(x.dtype).str}/{int(_weak(x))}"
    raise _Uncacheable(type(x).__name__)
