"""Numerically safe building blocks shared by every kernel.

Each helper states *why* it exists. The recurring pattern is the "double where": masking only the
output of `jnp.where(ok, f(x), 0)` still evaluates `f` (and its derivative) on the bad lanes, and
because NaN * 0 = NaN the NaN leaks into the gradient. So the *input* is first replaced by a benign
value on the bad lanes, then the output is masked (docs/math.md §8.10; JAX FAQ "gradients contain NaN
where using where").
"""

from __future__ import annotations

import contextlib
import itertools
import threading
import weakref
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from ._program_cache import cached_jit, trace_state_clean, with_callers_context

__all__ = [
    "HIGHEST",
    "Vec3",
    "as_float",
    "computed_once",
    "cpu_cond",
    "cross",
    "cross_rows",
    "dot",
    "eps",
    "is_concrete",
    "map_row_chunks",
    "orthonormal_frame",
    "progress_token",
    "outside_traces",
    "remember_per_array",
    "trace_state_clean",
    "with_callers_context",
    "pack3",
    "safe_div",
    "safe_normalize",
    "safe_sqrt",
    "small_sq",
    "saturate",
    "unpack3",
    "vcross",
    "vdot",
    "vnormalize",
]


#: The precision of every matmul / einsum / dot in jaxpbr. The default lets a backend trade
#: accuracy for speed (on NVIDIA GPUs XLA runs default-precision float32 matmuls in TF32, a
#: 10-bit mantissa: 3.8e-4 relative errors in the irradiance measured on an H100);
#: `tests/test_precision.py` walks the jaxprs and fails on any dot_general without it.
HIGHEST = jax.lax.Precision.HIGHEST


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.cross of two (N, 3) NumPy arrays, row by row: the same products and differences in the
    same order (bit-identical), about 6x faster at a million rows than np.cross's general path."""
    a, b = np.asarray(a), np.asarray(b)
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), np.result_type(a, b))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def as_float(x) -> jax.Array:
    """`jnp.asarray` for user inputs: float arrays unchanged, ints/bools -> default float, and
    Python numbers *or short sequences of Python numbers* (e.g. `base_color=(0.9, 0.6, 0.2)`)
    kept weakly typed.

    Why: a tuple would otherwise become a strongly typed float64 array when x64 is enabled and
    silently promote a float32 computation to float64; weakly typed values take the dtype of the
    arrays they meet, like Python scalars do.
    """
    if isinstance(x, (list, tuple)):
        flat = _python_numbers(x)
        if flat is not None and 0 < len(flat) <= 16:
            key = (tuple(float(e).hex() for e in flat), np.shape(x), *_memo_context())
            out = _WEAK.get(key)
            if out is None:
                out = _remember(key, _weak_array(flat, np.shape(x)))
            return out
    if type(x) is float:  # (not NumPy scalars, whose dtype is strong; ints take the path below)
        key = (x.hex(), *_memo_context())
        out = _WEAK.get(key)
        # (device_put makes the weakly typed array of a Python float without an XLA program)
        return out if out is not None else _remember(key, jax.device_put(x))
    # A NumPy array or scalar (a baked set's light intensities) is copied to the device as it is:
    # jnp.asarray would run an XLA program for it (one per shape and dtype, each traced, lowered and
    # looked up in the compilation cache).
    x = jax.device_put(x) if isinstance(x, (np.ndarray, np.generic)) and x.dtype != object else jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise TypeError(f"expected real values, got a {x.dtype} array (take .real explicitly if that is meant)")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _stack(*xs):
    return jnp.stack(xs)


#: Weakly typed scalars stacked into a weakly typed vector: a stored program where the command
#: line keeps them (`_program_cache`), so a warm start lowers none. Used where `_weak_array`'s
#: direct construction is not available.
_weak_stack = cached_jit(_stack)


def _weak_array(flat, shape) -> jax.Array:
    """Python numbers as the weakly typed array `jnp.stack` of their weakly typed scalars gives
    (same values, dtype and weak type), without an XLA program: the NumPy array is put on the
    device and wrapped as a `jax.Array` of the weakly typed shape. JAX has no public constructor
    for a weakly typed array; where this one is missing or gives something else, the compiled stack
    (`_weak_stack`; a command's cold start compiled two of them on its one busy core, 0.13-0.18 s),
    which is also what a call inside a trace binds there."""
    if _WEAK_DIRECT[0] and trace_state_clean():  # (inside a trace device_put gives a traced value)
        try:
            from jax._src.array import ArrayImpl
            from jax._src.core import ShapedArray

            dtype = jax.dtypes.canonicalize_dtype(float)
            buf = jax.device_put(np.asarray(flat, dtype).reshape(shape))
            out = ArrayImpl(ShapedArray(buf.shape, buf.dtype, weak_type=True), buf.sharding, [buf], committed=False)
            ok = out.weak_type and out.dtype == dtype and out.shape == tuple(shape)
        except Exception:  # noqa: BLE001 (a JAX without this constructor: the compiled stack from now on)
            ok = False
        if ok:
            return out
        _WEAK_DIRECT[0] = False
    return _weak_stack(*(jax.device_put(float(e)) for e in flat)).reshape(shape)


#: Whether `_weak_array` builds its arrays directly (False once that failed in this process).
_WEAK_DIRECT = [True]


#: The weakly typed arrays of Python numbers and short tuples already converted (scene objects repeat
#: the same colours and factors; each conversion is a few eager dispatches): arrays are immutable,
#: so one array serves every object that gave the same values. Keyed by the exact values (float hex:
#: -0.0 and 0.0 apart), the default float width and the default device; tracers are not kept.
_WEAK: dict = {}


def _memo_context() -> tuple:
    return bool(jax.config.jax_enable_x64), str(jax.config.jax_default_device)


def _remember(key, value):
    if not isinstance(value, jax.core.Tracer) and len(_WEAK) < 4096:
        _WEAK[key] = value
    return value


def _python_numbers(x) -> list | None:
    """The flattened Python numbers of a nested list/tuple, or None if anything else is inside."""
    out = []
    for e in x:
        if isinstance(e, (list, tuple)):
            sub = _python_numbers(e)
            if sub is None:
                return None
            out.extend(sub)
        elif isinstance(e, (int, float)) and not isinstance(e, bool):
            out.append(e)
        else:
            return None
    return out


def eps(dtype) -> float:
    """Machine epsilon of a float dtype (1.19e-7 for float32, 2.2e-16 for float64)."""
    return float(jnp.finfo(dtype).eps)


def small_sq(dtype) -> float:
    """eps(dtype)^2: the floor below which a *squared* length of an O(1) vector is rounding noise
    (1.4e-14 for float32, 4.9e-32 for float64).

    Why one named floor: a literal such as 1e-12 is below float32 resolution for O(1) values and
    far above float64's, so it means different things in the two precisions; `vnormalize`, the
    ray-plane test and the sphere's pole test all use this one.
    """
    return eps(dtype) ** 2


def safe_div(a, b, ok=None, *, fill=0.0):
    """a / b on the lanes where `ok` (default: b != 0), `fill` elsewhere, finite in value and gradient.

    Why: `jnp.where(ok, a / b, fill)` still differentiates a / b on the masked lanes, and the
    infinite derivative times the zero mask is NaN. Double where: the division sees a benign 1 there.
    """
    if ok is None:
        ok = b != 0
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), fill)


# ------------------------------------------------------------------------------------------
# 3-vectors as structures of arrays.
#
# Why: kernels written on (..., 3) arrays reduce over a size-3 minor axis (`jnp.sum(a*b, -1)`),
# and mix (..., 3) with (...) shapes; XLA:CPU then splits a shading kernel into ~50-100 separate
# passes over memory. Carrying a vector as a tuple of three (...) planes keeps every
# intermediate the same shape, so the whole kernel fuses into one loop (measured 13x faster on a
# 1080p G-buffer). Public functions take (..., 3) arrays and convert at the boundary.
# ------------------------------------------------------------------------------------------

Vec3 = tuple  # (x, y, z), each an array of the same broadcastable batch shape


def unpack3(x: jax.Array) -> Vec3:
    """(..., 3) array -> tuple of three (...) arrays. Any other trailing size is a ValueError (an
    index past the end would otherwise be clamped silently: a (1,) or (2,) vector padded, a (4,)
    one truncated)."""
    shape = jnp.shape(x)
    if not shape or shape[-1] != 3:
        raise ValueError(f"expected a 3-vector (..., 3), got an array of shape {tuple(shape)}")
    return (x[..., 0], x[..., 1], x[..., 2])


def pack3(t: Vec3) -> jax.Array:
    """Tuple of three broadcastable (...) arrays -> (..., 3) array."""
    shape = jnp.broadcast_shapes(*(jnp.shape(c) for c in t))
    return jnp.stack([jnp.broadcast_to(c, shape) for c in t], axis=-1)


def vdot(a: Vec3, b: Vec3) -> jax.Array:
    """Dot product of two Vec3 -> (...)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def vcross(a: Vec3, b: Vec3) -> Vec3:
    """Cross product of two Vec3."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def vnormalize(a: Vec3) -> Vec3:
    """a / |a| for a Vec3; vectors shorter than the dtype's epsilon map to the zero vector.

    Why: `x / jnp.linalg.norm(x)` is NaN in value *and* gradient at x = 0 (e.g. the half vector
    v + l when v = -l, or a zero-length normal). Below |x| = eps the direction is rounding noise;
    the threshold also keeps d(x/|x|)/dx ~ 1/|x| far from float overflow (a `tiny`-based threshold
    would make the rsqrt derivative |x|^-3 overflow float32). Double where: the rsqrt is taken of
    a benign 1 on the zero lanes so its derivative is finite there.
    """
    sq = vdot(a, a)
    ok = sq > eps(jnp.result_type(*a)) ** 2
    inv = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, sq, 1.0)), 0.0)
    return (a[0] * inv, a[1] * inv, a[2] * inv)


def orthonormal_frame(n: Vec3) -> tuple[Vec3, Vec3]:
    """Two unit tangents completing unit n to an orthonormal frame, branch-free (Duff et al. 2017)."""
    sign = jnp.where(n[2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    return (1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]), (b, sign + n[1] * n[1] * a, -n[1])


def dot(a: jax.Array, b: jax.Array) -> jax.Array:
    """Dot product of (..., 3) arrays -> (...), per component (fusion-friendly, see Vec3)."""
    return vdot(unpack3(a), unpack3(b))


def cross(a: jax.Array, b: jax.Array) -> jax.Array:
    """Cross product of (..., 3) arrays, per component."""
    return pack3(vcross(unpack3(a), unpack3(b)))


def safe_normalize(x: jax.Array) -> jax.Array:
    """x / |x| over the last axis of a (..., 3) array; see `vnormalize` for the zero case."""
    return pack3(vnormalize(unpack3(x)))


def saturate(x: jax.Array) -> jax.Array:
    """Clamp to [0, 1] (GLSL `clamp(x, 0, 1)`); the gradient is 0 outside the interval."""
    return jnp.clip(x, 0.0, 1.0)


def safe_sqrt(x: jax.Array) -> jax.Array:
    """sqrt(max(x, 0)) with a finite gradient everywhere.

    Why: d sqrt/dx = inf at 0 and 0 * inf = NaN in the backward pass, even when the value is masked.
    The gradient at x <= 0 is defined as 0.
    """
    ok = x > 0
    safe = jnp.where(ok, x, 1.0)
    return jnp.where(ok, jnp.sqrt(safe), 0.0)


def is_concrete(x) -> bool:
    """True if `x` holds actual values (not a tracer under jit/vmap/grad), so it can be validated."""
    return not isinstance(x, jax.core.Tracer)


def computed_once(fn, operands, guard):
    """`fn(operands)`, which XLA:CPU computes once, as arrays of its own.

    XLA:CPU fuses elementwise producers into each of their consumers and recomputes them there (it
    makes no multi-output loop fusions): a (..., 3) colour made from per-pixel terms evaluates them
    once per channel, and arrays written side by side each evaluate their shared inputs again. A
    conditional's branch is computed once. The predicate is always true but computed from `guard`
    (a scalar array), so XLA cannot fold the conditional away, and the other branch is a
    constant: fn's code is compiled once, and the value is fn's whatever guard holds. Take `guard`
    from an input that is not batched: under vmap a batched predicate makes the conditional a
    select of both branches. Elsewhere than on the CPU (`cpu_cond`) fn is inlined, and outside any
    trace it is called as it is."""
    if _eager(operands):
        return fn(operands)
    run, shapes = _traced_once(fn, operands)
    return _platform_cond(_true_at_run_time(guard), run, lambda _: jax.tree_util.tree_map(
        lambda s: jnp.zeros(s.shape, s.dtype), shapes), operands)


def _traced_once(fn, operands):
    """(a function that replays fn's jaxpr, fn's output shapes), fn traced once for `operands`.

    A conditional traces its branch, and `lax.platform_dependent` traces its CPU and default forms,
    so fn would be traced (its Python run) two or three times; replaying the jaxpr binds the same
    primitives again without that Python work (the same program, the same image bit for bit): the
    demo's IBL stage traces in 117 against 135 ms."""
    from jax.extend.core import jaxpr_as_fun

    closed, shapes = jax.make_jaxpr(fn, return_shape=True)(operands)
    out_tree, replay = jax.tree_util.tree_structure(shapes), jaxpr_as_fun(closed)

    def run(ops):
        return jax.tree_util.tree_unflatten(out_tree, replay(*jax.tree_util.tree_leaves(ops)))

    return run, shapes


def _true_at_run_time(guard) -> jax.Array:
    """A predicate that is always true, computed from `guard` (a scalar array) so that XLA cannot
    fold it: guard's bits with the lowest one set are never all zero."""
    g = jnp.asarray(guard)
    bits = jax.lax.bitcast_convert_type(g, jnp.dtype(f"int{8 * g.dtype.itemsize}"))
    return (bits | 1) != 0


def cpu_cond(pred, fn, other, operands):
    """`lax.cond(pred, fn, other, operands)` on XLA:CPU, `fn(operands)` inline on other platforms.

    For conditionals that are there for XLA:CPU's sake: a branch is computed once rather than in
    every consumer (`computed_once`), and `other` skips work whose result is not used (it must
    equal fn's result wherever the caller reads it, so both forms give the same image). GPU
    compilers fuse a term into several outputs at once, and a conditional there waits for its
    predicate on the host, so the plain expression is what they get (`lax.platform_dependent`
    lowers only the one for the platform compiled for).

    Outside any trace (a kernel called eagerly) the branch that pred picks is called as it is:
    eager operations are dispatched one by one, so there is nothing to fuse, and a conditional
    would be one more program to lower and compile at every call (its branches are new closures
    each time: the default test suite, which calls many kernels eagerly, measured 0.94x the CPU
    time cold)."""
    if _eager((pred, operands)):
        return fn(operands) if bool(pred) else other(operands)
    return _platform_cond(pred, _traced_once(fn, operands)[0], other, operands)


def _platform_cond(pred, fn, other, operands):
    return jax.lax.platform_dependent(operands, cpu=lambda ops: jax.lax.cond(pred, fn, other, ops), default=fn)


def _eager(operands) -> bool:
    """Whether no JAX trace is active and no leaf of `operands` is a tracer."""
    return trace_state_clean() and not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(operands))


def outside_traces(compute):
    """compute() run on a fresh thread and returned: concrete arrays even while the caller traces.

    For work that depends on concrete inputs only (the renderer's cached precomputes of a
    concrete environment, a prefilter's sample tables) but may be reached in the middle of tracing
    (render under jit / grad / vmap of a scene whose environment is a constant): called there,
    jitted programs would be inlined into that trace and return its tracers. JAX's trace state is per
    thread, so on another thread they compile and run as their own programs and return concrete
    arrays. (`jax.ensure_compile_time_eval` would also give concrete values, but it evaluates jitted
    functions op by op: hundreds of dispatches and compilations.) The caller's thread-local x64
    mode and default device are carried over.

    Outside any trace (the common case: `render` of a concrete scene) compute() runs right here, on
    the caller's thread: no thread is started."""
    if trace_state_clean():
        return compute()
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="jaxpbr-assets") as pool:
        return pool.submit(with_callers_context(compute)).result()


def remember_per_array(cache: dict, x, tag, compute):
    """compute(), remembered per (array object, tag) in `cache` for as long as the array lives.

    JAX arrays and read-only NumPy arrays (a Mesh's) are immutable, so a value derived from one (a
    content hash, a range, a validity check) holds while the object exists: the weak reference
    drops the entry with the array, and the identity test guards against a new array that reuses a
    freed one's id. Writeable NumPy arrays (their content can change in place) and objects that are
    not weak-referenceable are not remembered."""
    if isinstance(x, np.ndarray) and x.flags.writeable:
        return compute()
    key = (id(x), tag)
    hit = cache.get(key)
    if hit is not None and hit[0]() is x:
        return hit[1]
    value = compute()
    try:
        cache[key] = (weakref.ref(x, lambda _, k=key: cache.pop(k, None)), value)
    except TypeError:
        pass
    return value


#: At most this many progress reports per `map_row_chunks` (a host callback costs ~0.1-0.5 ms).
MAX_REPORTS = 200


def _report_groups(N: int, chunk: int) -> tuple[int, int]:
    """(chunks per report, reports) for N rows in chunks of `chunk` (<= N)."""
    n = -(-N // chunk)
    group = -(-n // MAX_REPORTS)
    return group, -(-n // group)


def map_row_chunks(fn, chunk: int, *xs, token=None):
    """fn(*chunks) over fixed-size chunks of the leading axis of the arrays xs (all of length N),
    with `lax.map` (one compiled loop body, not an unrolled Python loop); the last chunk is padded
    with copies of the first row and the padding dropped again. -> (N, ...).

    token: a traced int32 scalar from `progress_token` (or None): the chunks then run in groups
    (an outer `lax.map` over at most MAX_REPORTS groups), each group reporting itself to the host
    (`jax.debug.callback`), which is how one long program shows progress; `row_chunk_count` is
    the number of reports."""
    N = xs[0].shape[0]
    if N == 0:  # no rows: fn's output shape for one row, with none of them
        one = jax.eval_shape(fn, *(jax.ShapeDtypeStruct((1,) + x.shape[1:], x.dtype) for x in xs))
        return jnp.zeros((0,) + one.shape[1:], one.dtype)
    chunk = min(chunk, N)
    group, reports = _report_groups(N, chunk) if token is not None else (1, 0)
    pad = (-N) % (chunk * group)

    def prep(x):
        if pad:
            x = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad,) + x.shape[1:])])
        x = x.reshape((-1, chunk) + x.shape[1:])
        return x if token is None else x.reshape((-1, group) + x.shape[1:])

    if token is None:
        out = jax.lax.map(lambda c: fn(*c), tuple(prep(x) for x in xs))
        return out.reshape((-1,) + out.shape[2:])[:N]

    def outer(g):
        out = jax.lax.map(lambda c: fn(*c), g)
        # A scalar that needs the whole group: the report comes after the group's work, and
        # only 4 bytes go to the host (not the group's results).
        jax.debug.callback(_progress_tick, token, jnp.sum(out))
        return out

    out = jax.lax.map(outer, tuple(prep(x) for x in xs))
    return out.reshape((-1,) + out.shape[3:])[:N]


def row_chunk_count(N: int, chunk: int) -> int:
    """How many progress reports `map_row_chunks(..., token=)` makes for N rows."""
    return _report_groups(N, min(chunk, N))[1] if N else 0


class _ProgressSink:
    """Counts chunk reports and forwards them to a `progress(done, total)` callable at most once
    per percent. Reports arrive on XLA's callback thread; an exception from `progress` is kept
    and re-raised on the caller's thread when the computation returns."""

    def __init__(self, progress, total: int):
        self.progress, self.total, self.done, self.shown = progress, max(1, total), 0, -1
        self.lock, self.error = threading.Lock(), None

    def add(self, n: int = 1) -> None:
        with self.lock:
            self.done = min(self.total, self.done + n)
            pct = 100 * self.done // self.total
            if pct == self.shown or self.error is not None:
                return
            self.shown = pct
            try:
                self.progress(self.done, self.total)
            except BaseException as exc:  # noqa: BLE001  (kept for the caller's thread)
                self.error = exc


_SINKS: dict[int, _ProgressSink] = {}
_TOKENS = itertools.count(1)


def _progress_tick(token, _done) -> None:
    # `_done` (a sum over the group's results) makes the report depend on the group's work, so
    # XLA cannot issue it before the group ran.
    sink = _SINKS.get(int(token))
    if sink is not None:
        sink.add()


@contextlib.contextmanager
def progress_token(progress, total: int):
    """A token for `map_row_chunks(..., token=)` that reports `total` chunks to `progress(done,
    total)` (None when progress is None: no callbacks are compiled in). Programs with host
    callbacks are left out of JAX's persistent compilation cache, so only pass a token when
    someone is watching. At the end `progress(total, total)` is called on the caller's thread."""
    if progress is None:
        yield None
        return
    key = next(_TOKENS)
    sink = _SINKS[key] = _ProgressSink(progress, total)
    try:
        yield jnp.asarray(key, jnp.int32)
        if sink.error is not None:
            raise sink.error
        if sink.shown < 100:  # the last report may have been throttled
            progress(sink.total, sink.total)
    finally:
        _SINKS.pop(key, None)
