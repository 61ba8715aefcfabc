"""The one timer of the benchmarks and reports.

JAX dispatches asynchronously: timing one call and synchronising it measures dispatch + launch +
sync, which dominates small GPU kernels. `time_calls` instead runs `number` calls back to back
and synchronises once at the end of each round (`jax.block_until_ready` on every output), so the
per-call time is the steady-state throughput a loop of such calls gets. The first call (which
includes tracing and compilation) is timed and reported apart. NumPy functions are timed the same
way (synchronising them is a no-op).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import jax

__all__ = ["Timing", "time_calls", "time_interleaved"]


@dataclass(frozen=True)
class Timing:
    """Seconds per call: `first` (the first call, with compilation), then one figure per round
    (`per_call`), summarised as `best` and `median`."""

    first: float
    per_call: tuple[float, ...]
    #: Seconds of single calls each synchronised on its own (dispatch + launch + sync included):
    #: what one isolated call costs, as opposed to the back-to-back throughput of `per_call`.
    single: tuple[float, ...] = ()

    @property
    def single_median(self) -> float:
        return statistics.median(self.single) if self.single else float("nan")

    @property
    def best(self) -> float:
        return min(self.per_call)

    @property
    def median(self) -> float:
        return statistics.median(self.per_call)

    @property
    def compile(self) -> float:
        """First call minus the steady state: tracing + compilation (+ one-time transfers)."""
        return max(0.0, self.first - self.best)


def time_calls(fn, *, rounds: int = 3, number: int = 1, single: int = 0):
    """Call `fn()` once (timed as `first`), then `rounds` rounds of `number` back-to-back calls,
    then `single` calls each synchronised on its own (`Timing.single`, dispatch-inclusive).

    Returns `(last result, Timing)`; every result is synchronised with `jax.block_until_ready`.
    """
    if rounds < 1 or number < 1:
        raise ValueError(f"rounds and number must be >= 1, got {rounds} and {number}")
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    per_call = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        outs = [fn() for _ in range(number)]
        jax.block_until_ready(outs)
        per_call.append((time.perf_counter() - t0) / number)
        out = outs[-1]
    alone = []
    for _ in range(single):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        alone.append(time.perf_counter() - t0)
    return out, Timing(first, tuple(per_call), tuple(alone))


def time_interleaved(variants: dict, *, rounds: int = 3) -> dict:
    """Each of `variants` (name -> function of no arguments) called once (timed as `first`: it
    compiles and fills the caches), then `rounds` rounds in which every variant runs once in turn,
    each call synchronised (`jax.block_until_ready`). A load that changes during the benchmark
    (another job, the machine's clock) affects every variant alike, so their ratios hold where
    back-to-back blocks of each would drift apart. -> {name: Timing}."""
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    first, per_call = {}, {k: [] for k in variants}
    for k, fn in variants.items():
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        first[k] = time.perf_counter() - t0
    for _ in range(rounds):
        for k, fn in variants.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            per_call[k].append(time.perf_counter() - t0)
    return {k: Timing(first[k], tuple(per_call[k])) for k in variants}


def to_host(tree):
    """Copy every array of a pytree to the host (NumPy): precompute timings include the copy a
    caller makes to write the result to a file."""
    return jax.tree_util.tree_map(lambda a: jax.device_get(a), tree)
