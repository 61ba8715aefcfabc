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
import json
import os
import pickle
import platform
import threading
import types
import weakref
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import jax
import numpy as np

__all__ = ["cached_jit", "cpu_jit", "directory", "package_digest", "recall", "remember", "use_directory"]

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


#: Every `cached_jit` of the process (for `release_programs`).
_INSTANCES: weakref.WeakSet = weakref.WeakSet()


def release_programs() -> int:
    """Drop the compiled programs every `cached_jit` holds in memory, and the stored programs read
    ahead for this command (`recall`); -> how many programs were held. The files stay: a later call
    loads its program again."""
    held = 0
    for f in list(_INSTANCES):
        held += f._cache_size()
        f.clear_cache()
    _RECALLED.clear()
    return held


#: XLA:CPU's loop emitters (`xla_cpu_use_fusion_emitters=False`) for the programs that name them
#: (`cached_jit(cpu_options=LOOP_EMITTERS)`). XLA:CPU's default fusion emitters run each fused loop
#: through an MLIR pipeline and an LLVM module of its own, about 20 ms of compile CPU a loop
#: whatever it computes; the loop emitters cost less per loop. They are chosen for the programs
#: whose run time they leave as it is (the IBL stage, the display encode); the stages whose loops
#: they slow down keep the default (direct lighting ran 5x slower, the suns' disc light 1.7x, the
#: G-buffer 1.25x). Measured figures: docs/performance.md.
LOOP_EMITTERS = {"xla_cpu_use_fusion_emitters": False}


def trace_state_clean() -> bool:
    """Whether no JAX trace (jit, grad, vmap, ...) is active on this thread."""
    try:
        from jax._src.core import trace_state_clean as clean
    except ImportError:  # a JAX without it: take every call as traced (a thread each, always correct)
        return False
    return bool(clean())


def _jit_with(fn, statics, names, options):
    """jax.jit(fn) compiled with `options`, or without them where this JAX's jit takes none."""
    if options:
        try:
            return jax.jit(fn, static_argnums=statics, static_argnames=names, compiler_options=dict(options))
        except TypeError:  # (a JAX without jit's compiler_options: its defaults)
            pass
    return jax.jit(fn, static_argnums=statics, static_argnames=names)


class cpu_jit:
    """`jax.jit(fn, static_argnums=..., static_argnames=...)` compiled with `cpu_options` (default
    `LOOP_EMITTERS`) on XLA:CPU when called outside any trace; inside one (a caller's jit, grad,
    vmap) the plain jax.jit, whose program becomes part of the caller's. Other attributes (`lower`,
    `trace`, ...) are the plain jax.jit's. The environment bake's programs use it (the loop emitters
    compile them faster and run them as fast), and `cached_jit` for its jax.jit."""

    def __init__(self, fn: Callable, *, static_argnums=None, static_argnames=None, cpu_options=None):
        # (None, not (): jax.jit then finds the positions of static_argnames, and the names of
        # static_argnums, in fn's signature)
        options = LOOP_EMITTERS if cpu_options is None else cpu_options
        self._jit = jax.jit(fn, static_argnums=static_argnums, static_argnames=static_argnames)
        self._jit_cpu = _jit_with(fn, static_argnums, static_argnames, options) if options else self._jit
        functools.update_wrapper(self, fn)

    def _jitted(self):
        """The jax.jit to call: with the options on XLA:CPU outside any trace (inside one the
        program is part of the caller's, which JAX compiles with the caller's options)."""
        return self._jit_cpu if jax.default_backend() == "cpu" and trace_state_clean() else self._jit

    def __call__(self, *args, **kwargs):
        return self._jitted()(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._jit, name)

    def _cache_size(self) -> int:
        jits = {id(j): j for j in (self._jit, self._jit_cpu)}.values()
        return sum(j._cache_size() for j in jits)

    def clear_cache(self) -> None:
        self._jit.clear_cache()
        self._jit_cpu.clear_cache()


class cached_jit:
    """`jax.jit(fn, static_argnums=..., static_argnames=...)` whose compiled programs are kept in
    `directory()` (see the module docstring). cpu_options: XLA compile options for XLA:CPU (e.g.
    `LOOP_EMITTERS`), used for the stored programs and for jax.jit's alike, so that both give the
    same values; other backends compile with their defaults."""

    def __init__(self, fn: Callable, *, static_argnums=(), static_argnames=(), cpu_options=None):
        self._fn = fn
        self._static_argnums = tuple(static_argnums) if isinstance(static_argnums, (tuple, list)) else (static_argnums,)
        self._static_argnames = (static_argnames,) if isinstance(static_argnames, str) else tuple(static_argnames)
        self._cpu_options = dict(cpu_options or {})
        self._jit = cpu_jit(fn, static_argnums=self._static_argnums, static_argnames=self._static_argnames,
                            cpu_options=self._cpu_options)
        self._mem: dict[str, object] = {}  # key -> (compiled, out_tree), or None: through jax.jit
        self._lock = threading.Lock()
        _INSTANCES.add(self)
        self.__wrapped__ = fn
        self.__name__ = getattr(fn, "__name__", "cached_jit")
        self.__qualname__ = getattr(fn, "__qualname__", self.__name__)
        self.__doc__ = fn.__doc__

    def lower(self, *args, **kwargs):
        return self._jit._jitted().lower(*args, **kwargs)

    def _cache_size(self) -> int:
        """Programs this process holds: jax.jit's, plus the ones loaded or stored here."""
        return self._jit._cache_size() + sum(1 for v in self._mem.values() if v is not None)

    def clear_cache(self) -> None:
        self._jit.clear_cache()
        self._mem.clear()

    def __call__(self, *args, **kwargs):
        root = _STATE["dir"]
        if root is None or jax.default_backend() != "cpu":  # (measured and tested on XLA:CPU only)
            return self._jit(*args, **kwargs)
        statics = {i: args[i] for i in self._static_argnums if i < len(args)}
        static_kw = {k: v for k, v in kwargs.items() if k in self._static_argnames}
        dyn = (tuple(a for i, a in enumerate(args) if i not in statics),
               {k: v for k, v in kwargs.items() if k not in static_kw})
        leaves, treedef = jax.tree_util.tree_flatten(dyn)
        ahead = _AHEAD.get() is not None
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            if ahead:
                raise NotAhead(f"{self.__name__}: traced arguments")
            return self._jit(*args, **kwargs)
        # Python numbers as the weakly typed arrays jax.jit makes of them (device_put: without an
        # XLA program of its own)
        leaves = [jax.device_put(x) if isinstance(x, (bool, int, float, complex)) else x for x in leaves]
        try:
            parts = [
                f"{self._fn.__module__}.{self._fn.__qualname__}",
                _package_digest(),
                _environment_key(),
                _canon(sorted(statics.items())),
                _canon(sorted(static_kw.items())),
                _canon(sorted(self._cpu_options.items())),
                _canon_tree(treedef),
                ";".join(_aval(x) for x in leaves),
            ]
        except _Uncacheable as exc:
            if ahead:
                raise NotAhead(f"{self.__name__}: {exc}") from None
            return self._jit(*args, **kwargs)
        key = hashlib.sha256("\n".join(parts).encode()).hexdigest()
        if ahead:
            return self._ahead(root, key, len(args), statics, static_kw, leaves, treedef)
        entry = self._mem.get(key, False)
        if isinstance(entry, _Pending):
            entry = entry.future.result()
            self._mem[key] = entry
        if entry is False:
            with self._lock:
                entry = self._mem.get(key, False)
                if entry is False:
                    entry = self._load(root, key)
                    if entry is False:
                        entry = self._compile(root, key, len(args), statics, static_kw, leaves, treedef)
                    self._mem[key] = entry
        if entry is None:
            return self._jit(*args, **kwargs)
        compiled, out_tree = entry
        try:
            out = compiled(*leaves)
        except Exception:  # noqa: BLE001 (an executable that loads but does not run: dropped, jax.jit)
            self._mem[key] = None
            try:
                self._path(root, key).unlink()
            except OSError:
                pass
            return self._jit(*args, **kwargs)
        return jax.tree_util.tree_unflatten(out_tree, out)

    # -- disk ---------------------------------------------------------------------------------
    @staticmethod
    def _path(root: Path, key: str) -> Path:
        return root / f"{PREFIX}{key[:40]}.bin"

    def _load(self, root, key):
        path = self._path(root, key)
        pending = _RECALLED.pop(path.name, None)
        loaded = pending.result() if pending is not None else _read(path)
        if loaded is None or loaded[0] != key:
            return False
        try:
            os.utime(path)
        except OSError:
            pass
        _USED.append(path.name)
        return loaded[1], loaded[2]

    def _compile(self, root, key, n_args, statics, static_kw, leaves, treedef):
        """Trace, lower and compile the flat program of `leaves` (without JAX's persistent
        compilation cache, see `_finish`) and store it; a program with a host callback is compiled
        for this process only; None where it must go through jax.jit."""
        try:
            traced, trees = self._trace(n_args, statics, static_kw, leaves, treedef)
        except Exception:  # noqa: BLE001 (run through jax.jit)
            return None
        return self._finish(root, key, traced, trees)

    def _ahead(self, root, key, n_args, statics, static_kw, leaves, treedef):
        """`__call__` inside `ahead()`: the program found (in memory or on disk) or traced here and
        handed to the compiler threads; -> its results as `jax.ShapeDtypeStruct`s, nothing run."""
        calls = _AHEAD.get()
        calls[0] += 1
        compilers = calls[1]
        with self._lock:
            entry = self._mem.get(key, False)
            if calls[0] == 1 and entry is not False and not isinstance(entry, _Pending):
                # The chain's first program is held already: so, most likely, are the others (a
                # repeated render); looking further would only cost the keys' hashing.
                raise NotAhead(f"{self.__name__}: held already")
            if entry is False:
                entry = self._load(root, key)
                if entry is False:
                    traced, trees = self._trace(n_args, statics, static_kw, leaves, treedef)
                    outs = jax.tree_util.tree_unflatten(trees[-1], list(_result_avals(traced)))
                    # Lowered here (Python, holding the GIL), compiled there (XLA, without it).
                    lowered = traced.lower()
                    job = with_callers_context(functools.partial(self._finish, root, key, traced, trees, lowered))
                    entry = _Pending(_compiler(compilers).submit(job), outs)
                self._mem[key] = entry
        if isinstance(entry, _Pending):
            return entry.results
        if entry is None:
            raise NotAhead(f"{self.__name__}: runs through jax.jit")
        compiled, out_tree = entry
        avals = getattr(compiled, "jaxpbr_out_avals", None)
        if avals is None:
            raise NotAhead(f"{self.__name__}: stored without its result shapes")
        return jax.tree_util.tree_unflatten(out_tree, list(avals))

    def _trace(self, n_args, statics, static_kw, leaves, treedef):
        """(jax's `Traced` of the flat program of `leaves`, [its result tree])."""
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
        # holds in memory (possibly read from its persistent cache, see `_finish`).
        flat.__name__ = flat.__qualname__ = f"{self.__name__}_stored"
        return jax.jit(flat).trace(*leaves), trees

    def _finish(self, root, key, traced, trees, lowered=None):
        """Lower (unless `lowered` is given) and compile `traced` and store it (see `_compile`)
        -> (compiled, result tree), or None where it must go through jax.jit."""
        from jax.experimental import serialize_executable

        avals = _result_avals(traced)
        try:
            lowered = traced.lower() if lowered is None else lowered
            if _has_callback(traced.jaxpr):  # this process's program only (traced once, not twice)
                return _with_avals(lowered.compile(compiler_options=self._cpu_options or None), avals), trees[-1]
            # Compiled here, never read from JAX's persistent cache: an executable loaded from that
            # cache serializes without its kernels (a later process loads it and fails calling it,
            # "Function ... not found": measured with jax 0.10). JAX decides once per process
            # whether its cache is used (a thread-local `enable_compilation_cache(False)` is not
            # looked at again, and where it held during the process's first compilation it turned
            # the cache off for everything), so the program gets a cache key of its own (a compile
            # option set to its default value, `_OWN_KEY`) and is never written under it (the
            # thread-local minimum compile time): no entry can ever be read back for it.
            from jax._src.config import persistent_cache_min_compile_time_secs

            with persistent_cache_min_compile_time_secs(float("inf")):
                compiled = lowered.compile(compiler_options={**_OWN_KEY, **self._cpu_options})
            payload, in_tree, out_tree = serialize_executable.serialize(compiled)
            blob = pickle.dumps((key, payload, in_tree, out_tree, trees[-1], avals))
        except Exception:  # noqa: BLE001 (not serializable here: run through jax.jit)
            return None
        path = self._path(root, key)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        try:
            root.mkdir(parents=True, exist_ok=True)
            tmp.write_bytes(blob)
            os.replace(tmp, path)
            _USED.append(path.name)
        except OSError:
            try:
                tmp.unlink()
            except OSError:
                pass
        return _with_avals(compiled, avals), trees[-1]


#: A compile option at its default value: the stored programs' key in JAX's persistent compilation
#: cache differs from a plain `jax.jit` compilation of the same program (`cached_jit._finish`).
_OWN_KEY = {"xla_cpu_enable_fast_min_max": False}


def with_callers_context(compute):
    """compute wrapped to run, on another thread, under the calling thread's x64 mode and default
    device (both thread-local in JAX)."""
    x64 = bool(jax.config.jax_enable_x64)
    device = jax.config.jax_default_device

    def run():
        with jax.enable_x64(x64), jax.default_device(device):
            return compute()

    return run


# -- compiling ahead ------------------------------------------------------------------------------
#: Inside `ahead()`: [the number of calls looked ahead so far, the compiler threads to use]; else None.
_AHEAD: contextvars.ContextVar[list | None] = contextvars.ContextVar("jaxpbr_programs_ahead", default=None)


class NotAhead(Exception):
    """A call inside `ahead()` that cannot be compiled ahead (traced or uncacheable arguments, a
    program that runs through jax.jit, host work between programs): the caller stops looking ahead
    and runs as usual."""


class _Pending:
    """A program being compiled on a compiler thread, and its results' shapes."""

    __slots__ = ("future", "results")

    def __init__(self, future: Future, results):
        self.future = future
        self.results = results


@contextlib.contextmanager
def ahead(*, compilers: int = 1):
    """Within, a `cached_jit` call with the stored-program directory set runs nothing: it finds its
    program in memory or on disk, or traces it and hands the lowering and compilation to the
    compiler threads, and returns its results as `jax.ShapeDtypeStruct`s, which later calls accept
    as arguments. Running a chain of programs (a render's stages) this way first starts all of
    their compilations at once, where each would otherwise wait for the previous program to
    compile and run; the real calls then wait for their own program only. A call that cannot be
    compiled ahead raises `NotAhead`. Only while a directory is set (else a call raises NotAhead).

    compilers: the compiler threads (1 or `MAX_COMPILERS`) that compile the programs. XLA:CPU spreads
    one program's code generation over the cores, so a second thread pays only where nothing else
    runs beside the compilations (`execute._compile_ahead`)."""
    if _STATE["dir"] is None:
        raise NotAhead("no program directory")
    token = _AHEAD.set([0, max(1, min(int(compilers), MAX_COMPILERS))])
    try:
        yield
    finally:
        _AHEAD.reset(token)


@contextlib.contextmanager
def running_now():
    """Within `ahead()`: calls run as usual again (host work the look-ahead needs anyway)."""
    token = _AHEAD.set(None)
    try:
        yield
    finally:
        _AHEAD.reset(token)


def was_recalled() -> bool:
    """Whether the programs of this command's last run are being read (`recall`): a warm rerun."""
    return bool(_RECALLED)


#: Calls to look ahead after a render's stages (`also_ahead`), for the calling thread.
_ALSO: contextvars.ContextVar[tuple] = contextvars.ContextVar("jaxpbr_also_ahead", default=())


@contextlib.contextmanager
def also_ahead(call):
    """Within, a render that compiles its stages ahead (`rendering.execute`) then calls `call()`
    inside `ahead()` too: the command line's display program (tone map and encoding of the image)
    is compiled on the compiler thread after the stages, while they run, instead of after them."""
    token = _ALSO.set(_ALSO.get() + (call,))
    try:
        yield
    finally:
        _ALSO.reset(token)


def calls_also_ahead() -> tuple:
    """The calls `also_ahead` registered on this thread."""
    return _ALSO.get()


def is_ahead() -> bool:
    """Whether this thread is inside `ahead()`."""
    return _AHEAD.get() is not None


#: The most threads that compile programs ahead (`ahead(compilers=)`). XLA:CPU already spreads a
#: program's code generation over the cores; a second thread measured faster only where nothing
#: else ran beside the compilations (2-core CPU, whole cold processes: the demo with its shipped
#: sky 0.92x with two; the 1 M-triangle asset, whose ray engine is built meanwhile, 1.02x).
MAX_COMPILERS = 2
_COMPILER: dict = {"pools": {}, "pid": 0}


def _compiler(threads: int = 1) -> ThreadPoolExecutor:
    """The pool of `threads` compiler threads (one pool per count, made on first use)."""
    with _READER_LOCK:
        if _COMPILER["pid"] != os.getpid():
            _COMPILER["pools"], _COMPILER["pid"] = {}, os.getpid()
        pool = _COMPILER["pools"].get(threads)
        if pool is None:
            pool = _COMPILER["pools"][threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="jaxpbr-compile")
        return pool


def _result_avals(traced) -> tuple:
    """The flat results' `jax.ShapeDtypeStruct`s (weak types included) of a `Traced`."""
    return tuple(jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=bool(getattr(a, "weak_type", False)))
                 for a in traced.out_info)


def _with_avals(compiled, avals):
    """compiled, carrying its flat results' shapes for `ahead` (a compiled program's own
    `out_info` leaves out weak types)."""
    try:
        compiled.jaxpbr_out_avals = avals
    except AttributeError:
        pass
    return compiled


def _read(path: Path):
    """(stored key, executable, result tree) of a stored program file, or None (missing, damaged
    or foreign: the caller compiles it again and rewrites it)."""
    from jax.experimental import serialize_executable

    try:
        stored_key, payload, in_tree, out_tree, result_tree, avals = pickle.loads(path.read_bytes())
        compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
        return stored_key, _with_avals(compiled, avals), result_tree
    except Exception:  # noqa: BLE001
        return None


# -- recalling the programs of a repeated command -------------------------------------------------
#: File in the directory: for each of the last `RECALL_COMMANDS` command signatures, the program
#: files its last run used.
MANIFEST = "program_recall.json"
RECALL_COMMANDS = 32
_USED: list[str] = []  # program files this process loaded or stored, in order
_RECALLED: dict[str, Future] = {}  # file name -> Future of `_read`


def recall(signature: str) -> int:
    """Start reading the program files that the last run of the command `signature` used, on a
    background thread (XLA deserializes without the GIL), while this one builds the scene: a
    warm rerun then finds its stages loaded instead of loading each when first called (loading
    the demo's four takes about 0.2 s of its 1.6 s warm start on 2 cores). A call still checks the
    file's full key; a file recalled in vain costs only the background read. Returns the number of
    files recalled."""
    root = _STATE["dir"]
    _USED.clear()
    _RECALLED.clear()  # (a previous command that failed before `remember`)
    if root is None:
        return 0
    try:
        names = json.loads((root / MANIFEST).read_text()).get(signature, [])
    except (OSError, ValueError, AttributeError):
        return 0
    names = [n for n in names if isinstance(n, str) and n.startswith(PREFIX) and n.endswith(".bin") and "/" not in n]
    if not names:
        return 0
    reader = _reader()
    for name in names:
        _RECALLED[name] = reader.submit(_read, root / name)
    return len(names)


_READER: dict = {"pool": None, "pid": 0}
_READER_LOCK = threading.Lock()


def _reader() -> ThreadPoolExecutor:
    """The one background thread that reads recalled programs, started on first use and kept (a
    forked child starts its own)."""
    with _READER_LOCK:
        if _READER["pool"] is None or _READER["pid"] != os.getpid():
            _READER["pool"] = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jaxpbr-recall")
            _READER["pid"] = os.getpid()
        return _READER["pool"]


def finish_work() -> None:
    """Wait for the compiler threads' jobs (a program still being compiled and stored) and drop
    the recalled programs not read yet: what a process that ends now must do first (`cli.main`)."""
    with _READER_LOCK:
        compilers = list(_COMPILER["pools"].values()) if _COMPILER["pid"] == os.getpid() else []
        reader = _READER["pool"] if _READER["pid"] == os.getpid() else None
        _COMPILER["pools"], _READER["pool"] = {}, None  # (a later use starts new ones)
    if reader is not None:
        reader.shutdown(wait=True, cancel_futures=True)
    for pool in compilers:
        pool.shutdown(wait=True)


def remember(signature: str) -> None:
    """Record the program files this process used (since `recall`) as the command `signature`'s,
    for its next run (the last `RECALL_COMMANDS` commands are kept; written atomically)."""
    root = _STATE["dir"]
    _RECALLED.clear()
    if root is None or not _USED:
        return
    path = root / MANIFEST
    try:
        table = json.loads(path.read_text())
        if not isinstance(table, dict):
            table = {}
    except (OSError, ValueError):
        table = {}
    table.pop(signature, None)
    table[signature] = list(dict.fromkeys(_USED))
    while len(table) > RECALL_COMMANDS:
        table.pop(next(iter(table)))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(table))
        os.replace(tmp, path)
    except OSError:
        try:
            tmp.unlink()
        except OSError:
            pass


def _aval(x) -> str:
    if isinstance(x, (jax.Array, np.ndarray, np.generic, jax.ShapeDtypeStruct)):
        return f"{tuple(x.shape)}/{np.dtype(x.dtype).str}/{int(bool(getattr(x, 'weak_type', False)))}"
    raise _Uncacheable(type(x).__name__)
