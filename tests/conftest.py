"""Test configuration: float64 is enabled so references and float64 kernel paths can be checked;
float32 paths are exercised by passing float32 arrays explicitly.

Most of the suite's time is XLA compilation, so JAX's persistent compilation cache is on: compiled
programs are stored under `.pytest_cache/d/jax-compilation-cache` (`pytest --cache-clear` empties
it) or under $JAXPBR_TEST_CACHE (set it to "" to turn the cache off). Later sessions and the other
pytest-xdist workers load a program instead of compiling it again (measured: a file's second run
takes ~30% of its first); the cache key is the program, the compile options and the jax/jaxlib
version, so a stale entry is never used, only kept: past CACHE_MAX_BYTES the oldest entries go.

XLA:CPU compiles the suite's programs with its loop emitters (`--xla_cpu_use_fusion_emitters=false`
in XLA_FLAGS, for this process and the processes tests start) unless $JAXPBR_TEST_EMITTERS is
"fusion" or XLA_FLAGS names the option already. The suite's images are tiny, so compiling is most of
its time, and the loop emitters compile each fused loop for less (measured, one run after the other:
the default suite cold on 2 cores 158 s against 196 s). The library's programs compile with XLA's
default, the fusion emitters, except those that name the loop emitters
(`_program_cache.LOOP_EMITTERS`): the two write the same operations, with products contracted into
FMAs in different places, so results agree to float32 rounding. `tests/test_emitters.py` compiles
the layered BSDF (and, in the slow set, lights, the split sum and a whole render) with both and
holds each to the float64 reference; `JAXPBR_TEST_EMITTERS=fusion python3 -m pytest` runs the whole
suite on the fusion emitters. (XLA's GPU compiler ignores the option.)"""

import os
import threading
from pathlib import Path

EMITTERS = os.environ.get("JAXPBR_TEST_EMITTERS", "loop")
if EMITTERS not in ("loop", "fusion"):
    raise RuntimeError(f"JAXPBR_TEST_EMITTERS must be 'loop' or 'fusion', got {EMITTERS!r}")
if EMITTERS == "loop" and "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    # Before JAX starts its CPU backend, which reads XLA_FLAGS once.
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_cpu_use_fusion_emitters=false".strip()

import jax
import pytest

from jaxpbr.cli._cache import prune

jax.config.update("jax_enable_x64", True)

def pytest_configure(config):
    # The command line keeps baked IBL maps in the user's cache dir; tests that call it (in process
    # or as a subprocess) must neither read nor fill it (tests/test_compile.py uses its own dirs).
    os.environ["JAXPBR_ASSET_CACHE"] = "off"
    path = os.environ.get("JAXPBR_TEST_CACHE")
    if path is None:
        cache = getattr(config, "cache", None)  # None under `-p no:cacheprovider`
        if cache is None:
            return
        try:
            path = str(cache.mkdir("jax-compilation-cache"))
        except OSError:  # read-only checkout: compile as usual
            return
    if not path:
        return
    if "PYTEST_XDIST_WORKER" not in os.environ:  # the controlling process, before any worker starts
        Path(path).mkdir(parents=True, exist_ok=True)
        prune(path)
    # Set before the first compilation (JAX decides once per process whether the cache is used), and
    # in the environment for the Python subprocesses that tests start.
    _write_cache_entries_atomically()
    for name, value in (
        ("jax_compilation_cache_dir", path),
        ("jax_persistent_cache_min_compile_time_secs", 0.0),
        ("jax_persistent_cache_min_entry_size_bytes", 0),
    ):
        jax.config.update(name, value)
        os.environ[name.upper()] = str(value)


def _write_cache_entries_atomically():
    """Without a size limit JAX (0.10.2) writes a persistent-cache entry in place and reads entries
    without a lock, so a pytest-xdist worker could read an entry another worker is still writing.
    Each entry is written to a temporary file and renamed into place instead (a reader sees all of
    it or none). A size limit would lock every read and write, but JAX then lists the whole
    directory at each write (thousands of entries here). (The Python subprocesses that tests start
    are not patched.)"""
    try:
        from jax._src import lru_cache
    except ImportError:
        return
    put = getattr(lru_cache.LRUCache, "put", None)
    suffix = getattr(lru_cache, "_CACHE_SUFFIX", None)
    if put is None or suffix is None or getattr(put, "_atomic", False):
        return

    def atomic_put(self, key, value):
        if getattr(self, "eviction_enabled", True) or not isinstance(self.path, Path) or not key:
            return put(self, key, value)
        target = self.path / f"{key}{suffix}"
        if target.exists():
            return None
        tmp = target.with_name(f".{target.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        try:
            tmp.write_bytes(value)
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        return None

    atomic_put._atomic = True
    lru_cache.LRUCache.put = atomic_put


#: Node ids of the tests marked slow by list (tests/slow_tests.txt): the measured slowest ones.
SLOW_LIST = Path(__file__).with_name("slow_tests.txt")


#: Past this many memory mappings a worker drops the compiled programs it holds, after a test file.
#: Each XLA:CPU program holds its own mappings (hundreds for a render stage) and Linux ends a process
#: at `vm.max_map_count` (65,530 by default): the slow set's workers died at about 64,700
#: (segfaults while loading a program from the persistent cache, or silently). One test file of the
#: slow set adds about 25,000; the default suite's workers peak near 16,300 and never reach this.
MAPPINGS_HIGH = 20_000


def _mappings() -> int | None:
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux
        return None


@pytest.fixture(autouse=True)
def _cache_folders_as_they_were():
    """The folders the command line gives the renderer's caches (`cli._cache.enable_assets`, run by
    every in-process `jaxpbr.cli.main`) are set back after each test: a later test of the same
    worker that counts its precomputes would otherwise find maps on disk (which test ran before it
    depends on how the workers share the suite)."""
    from jaxpbr import _program_cache
    from jaxpbr.rendering.cache import ASSETS
    from jaxpbr.rendering.mesh import ACCELS

    saved = (ASSETS.directory, ACCELS.directory, _program_cache.directory())
    yield
    ASSETS.use_directory(saved[0])
    ACCELS.use_directory(saved[1])
    _program_cache.use_directory(saved[2])


@pytest.fixture(autouse=True, scope="module")
def _release_programs_when_mappings_run_high():
    yield
    n = _mappings()
    if n is not None and n > MAPPINGS_HIGH:
        import gc

        import jaxpbr

        jaxpbr.clear_caches()
        gc.collect()


#: The slice of the slow set CI runs with the default suite (tests/ci_slice.txt: the cheapest slow test
#: of every file that has slow tests, by measured duration; `python tests/ci_slice.py DURATIONS_LOG`
#: writes it). `JAXPBR_CI_SLICE=1` (set by .ci/run) adds it to the default selection.
CI_SLICE = Path(__file__).with_name("ci_slice.txt")


def _listed(path: Path) -> set:
    return {line.strip() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")}


def pytest_configure(config):
    if os.environ.get("JAXPBR_CI_SLICE") and config.option.markexpr == "not slow":
        config.option.markexpr = "not slow or ci_slice"


def pytest_sessionstart(session):
    """With JAXPBR_REQUIRE_ORACLES=1 (set by .ci/run) the independent oracles must be there: a missing
    one ends the session with an error instead of skipping the checks that need it."""
    if not os.environ.get("JAXPBR_REQUIRE_ORACLES") or hasattr(session.config, "workerinput"):
        return
    # (where the tests look for them: the checkout's node_modules, or the JAXPBR_* variables)
    from gltf_writer import gltf_transform_missing, validator_missing
    from three_oracle import three_missing

    missing = [why for why in (validator_missing(), gltf_transform_missing(), three_missing()) if why]
    mikk = Path(os.environ.get("JAXPBR_MIKKTSPACE_JS", Path(__file__).resolve().parent.parent / "node_modules" / "mikktspace"))
    if not (mikk / "package.json").is_file():
        missing.append(f"the npm package mikktspace ({mikk}; npm install --no-save mikktspace)")
    try:
        import ray  # noqa: F401
    except ImportError:
        missing.append("ray (pip install '.[ray]')")
    if missing:
        pytest.exit(f"JAXPBR_REQUIRE_ORACLES is set but these are missing: {', '.join(missing)}; "
                    "install them (.ci/run does) or unset it", returncode=3)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Mark the listed tests slow before `-m 'not slow'` deselects by marker, and the CI slice's
    `ci_slice`."""
    listed = _listed(SLOW_LIST)
    in_slice = _listed(CI_SLICE) if CI_SLICE.exists() else set()
    seen = set()
    for item in items:
        if item.nodeid in listed:
            item.add_marker(pytest.mark.slow)
            seen.add(item.nodeid)
        if item.nodeid in in_slice:
            item.add_marker(pytest.mark.ci_slice)
    # A renamed test or a changed parameter id would silently move a slow test into the default
    # suite: a run that collects every test file names the stale entries.
    if not config.args or [Path(a).resolve() for a in config.args] == [Path(config.rootpath, "tests").resolve()]:
        stale = sorted(listed - seen)
        if stale:
            raise pytest.UsageError(f"{SLOW_LIST.name} names {len(stale)} test(s) that were not collected "
                                    f"(renamed or removed? update the list): {stale[:5]}")
        # (a file skipped whole where an optional package is missing collects nothing: not stale)
        slow_ids = {item.nodeid for item in items if item.get_closest_marker("slow")}
        files = {item.nodeid.split("::")[0] for item in items}
        off = sorted(x for x in in_slice - slow_ids if x.split("::")[0] in files)
        if off:
            raise pytest.UsageError(f"{CI_SLICE.name} names {len(off)} test(s) that are not collected slow tests "
                                    f"(python tests/ci_slice.py rewrites it): {off[:5]}")
