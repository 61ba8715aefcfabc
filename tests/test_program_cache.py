"""jaxpbr._program_cache: compiled stages kept on disk give the programs jax.jit gives, are keyed by
everything they depend on, and are loaded by a later process instead of traced and compiled."""

import dataclasses
import math
import os
import pickle
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpbr import _program_cache as pc


#: Programs are stored on XLA:CPU only; elsewhere `cached_jit` is `jax.jit` and JAX's own cache.
stored_on_this_backend = pytest.mark.skipif(jax.default_backend() != "cpu", reason="programs are stored on XLA:CPU only")


@pytest.fixture
def cache_dir(tmp_path):
    pc.use_directory(tmp_path)
    yield tmp_path
    pc.use_directory(None)


@dataclasses.dataclass(frozen=True)
class _Opts:
    scale: float
    mode: str


def _f(x, opts, *, flip=False):
    y = jnp.sin(x) * opts.scale + (jnp.cos(x) if opts.mode == "cos" else 0.0)
    return {"y": -y if flip else y, "sum": jnp.sum(y)}


def _files(d):
    return sorted(p.name for p in d.iterdir() if p.name.startswith(pc.PREFIX))


@stored_on_this_backend
def test_stored_program_equals_jit_and_is_loaded_not_compiled(cache_dir, monkeypatch):
    f = pc.cached_jit(_f, static_argnums=(1,), static_argnames=("flip",))
    x = np.linspace(-3, 3, 101, dtype=np.float32)
    ref = jax.jit(_f, static_argnums=(1,), static_argnames=("flip",))(x, _Opts(2.0, "cos"), flip=True)
    out = f(x, _Opts(2.0, "cos"), flip=True)
    assert len(_files(cache_dir)) == 1
    np.testing.assert_array_equal(out["y"], ref["y"])
    np.testing.assert_array_equal(out["sum"], ref["sum"])
    # a new process is a fresh object: it must load the file, not compile
    g = pc.cached_jit(_f, static_argnums=(1,), static_argnames=("flip",))
    monkeypatch.setattr(pc.cached_jit, "_compile", lambda *a, **k: pytest.fail("compiled instead of loaded"))
    again = g(x, _Opts(2.0, "cos"), flip=True)
    np.testing.assert_array_equal(again["y"], ref["y"])
    assert again["y"].dtype == ref["y"].dtype and isinstance(again, dict)


@stored_on_this_backend
def test_the_key_follows_statics_shapes_dtypes_and_settings(cache_dir):
    f = pc.cached_jit(_f, static_argnums=(1,), static_argnames=("flip",))
    x = np.ones(8, np.float32)
    f(x, _Opts(2.0, "cos"))
    f(x, _Opts(2.0, "cos"))  # the same key: no new file
    assert len(_files(cache_dir)) == 1
    f(x, _Opts(2.0000002, "cos"))  # a float that differs in the last bits
    f(x, _Opts(2.0, "sin"))
    f(x, _Opts(2.0, "cos"), flip=True)
    f(np.ones(9, np.float32), _Opts(2.0, "cos"))
    f(np.ones(8, np.float64), _Opts(2.0, "cos"))
    f(jnp.asarray(1.0), _Opts(2.0, "cos"))  # weakly typed scalar
    f(jnp.asarray(1.0, jnp.float64), _Opts(2.0, "cos"))  # its strong twin
    with jax.numpy_rank_promotion("raise"):
        f(x, _Opts(2.0, "cos"))
    assert len(_files(cache_dir)) == 9
    # each call gives what jax.jit gives for its own inputs
    h = jax.jit(_f, static_argnums=(1,), static_argnames=("flip",))
    for xs, o, flip in [(np.ones(9, np.float32), _Opts(2.0, "cos"), False), (x, _Opts(2.0000002, "cos"), False)]:
        np.testing.assert_array_equal(f(xs, o, flip=flip)["y"], h(xs, o, flip=flip)["y"])


def test_what_cannot_be_named_exactly_or_stored_runs_through_jit(cache_dir):
    f = pc.cached_jit(_f, static_argnums=(1,))
    x = np.ones(4, np.float32)

    # a lambda among the static values cannot be named by its code: not stored
    assert f(x, _Opts(1.0, lambda: "cos"))["y"].shape == (4,)
    assert _files(cache_dir) == []
    # a host callback names objects of this process: not stored, and remembered as such
    cb = pc.cached_jit(lambda v: jax.pure_callback(lambda a: np.asarray(a) * 2, jax.ShapeDtypeStruct(v.shape, v.dtype), v))
    np.testing.assert_array_equal(cb(x), 2 * x)
    np.testing.assert_array_equal(cb(x), 2 * x)
    assert _files(cache_dir) == []
    # under a transformation the arguments are tracers: jax.jit, and gradients flow
    g = jax.grad(lambda v: f(v, _Opts(3.0, "sin"))["sum"])(x)
    np.testing.assert_allclose(g, 3.0 * np.cos(x), rtol=1e-6)
    assert _files(cache_dir) == []
    with pytest.raises(pc._Uncacheable):
        pc._canon(_Opts(1.0, lambda: 0))
    with pytest.raises(pc._Uncacheable):
        pc._canon((np.ones(3),))


@stored_on_this_backend
def test_a_damaged_or_foreign_file_is_compiled_again_and_rewritten(cache_dir):
    f = pc.cached_jit(_f, static_argnums=(1,))
    x = np.arange(5, dtype=np.float32)
    ref = np.asarray(f(x, _Opts(1.5, "cos"))["y"])
    (path,) = cache_dir.iterdir()
    for junk in (b"", b"not a pickle", path.read_bytes()[: len(path.read_bytes()) // 2]):
        path.write_bytes(junk)
        g = pc.cached_jit(_f, static_argnums=(1,))
        np.testing.assert_array_equal(g(x, _Opts(1.5, "cos"))["y"], ref)
        assert path.stat().st_size > 1000  # rewritten whole


def test_settings_that_change_a_trace_are_in_the_key():
    base = pc._environment_key()
    with jax.numpy_dtype_promotion("strict"):
        assert pc._environment_key() != base
    with jax.enable_x64(not jax.config.jax_enable_x64):
        assert pc._environment_key() != base
    assert pc._canon(0.1) != pc._canon(math.nextafter(0.1, 1.0))
    assert pc._canon((1, 2)) != pc._canon([1, 2]) != pc._canon((1.0, 2.0))
    assert pc._canon(pc._package_digest) == "function:jaxpbr._program_cache._package_digest"


@pytest.mark.slow  # two processes, the first compiling every stage without JAX's cache: 10-20 s
def test_a_warm_command_line_render_loads_its_stages(tmp_path):
    """Two `jaxpbr render` processes on one asset cache: the second lowers no program at all (the
    stages, the display and the small conversions are loaded, the sky is read from the asset
    cache, NumPy inputs are copied without programs of their own) and writes the same image."""
    env = dict(os.environ, JAXPBR_ASSET_CACHE=str(tmp_path / "assets"), JAX_LOG_COMPILES="1")
    outs, files = [], []
    for i in range(2):
        out = tmp_path / f"demo{i}.png"
        r = subprocess.run([sys.executable, "-c", "import sys; from jaxpbr.cli import main; sys.exit(main(sys.argv[1:]))",
                            "render", "--width", "48", "--height", "27", "--hdr", "-o", str(out)],
                           env=env, capture_output=True, text=True, check=False)
        assert r.returncode == 0, r.stderr[-2000:]
        outs.append((out, r.stderr))
        files.append(_files(tmp_path / "assets"))
    # The cold run compiles few XLA programs (`test_compile.MAX_PROGRAMS`; with every cache off the
    # same count is checked by the slow `test_cold_demo_render_compiles_few_programs`).
    from test_compile import MAX_PROGRAMS

    compiled = [line for line in outs[0][1].splitlines() if "Finished XLA compilation" in line]
    assert 0 < len(compiled) <= MAX_PROGRAMS, "\n".join(compiled)
    lowered = lambda log, name: re.search(rf"Finished jaxpr to MLIR module conversion jit\({name}(_stored)?\)", log) is not None  # noqa: E731
    for stage in ("_geometry", "_shade_direct", "_shade_suns", "_shade_rest", "_display"):
        assert lowered(outs[0][1], stage), stage
    for bake in ("_filtered_level", "_prefilter_fis", "_irradiance_at"):  # the demo's sky ships baked
        assert not lowered(outs[0][1], bake), bake
    assert "Finished jaxpr to MLIR module conversion" not in outs[1][1], outs[1][1][-3000:]
    assert len(files[0]) >= 5 and files[1] == files[0]  # the stages and display; nothing new
    from jaxpbr.io import image

    a = image.read(outs[0][0].with_suffix(".exr"))
    b = image.read(outs[1][0].with_suffix(".exr"))
    np.testing.assert_array_equal(a, b)


def _g(x):
    return jnp.tanh(x) * 3.0 + x * x


@stored_on_this_backend
def test_a_stored_program_is_compiled_afresh_whatever_jaxs_cache_holds(cache_dir):
    """An executable read from JAX's persistent compilation cache serializes without its kernels
    (loaded again, calling it failed: "Function ... not found"); the stored program must never be
    one. Here JAX's cache holds the same program (a plain jax.jit of it), and the stored file still
    loads and runs, and JAX's cache gains no entry of its own for it."""
    import jax
    from jax.experimental import serialize_executable

    x = np.linspace(-1.0, 1.0, 37, dtype=np.float32)
    cache = jax.config.jax_compilation_cache_dir
    if not cache:
        pytest.skip("JAX's persistent compilation cache is off in this run")
    jax.jit(_g)(x)  # (in JAX's cache now, where it was not already)

    def entries():  # this program's entries (other test workers write theirs beside them)
        return {n for n in os.listdir(cache) if n.startswith(("jit__g-", "jit__g_stored-"))}

    before = entries()
    assert before
    for _ in range(2):  # the second time as a later process would, its stored file gone
        for p in cache_dir.iterdir():
            p.unlink()
        f = pc.cached_jit(_g)
        want = np.asarray(f(x))
        np.testing.assert_allclose(want, np.tanh(x) * 3.0 + x * x, rtol=1e-6)
        assert entries() == before
        (path,) = [p for p in cache_dir.iterdir() if p.name.startswith(pc.PREFIX)]
        _, payload, in_tree, out_tree, _, _ = pickle.loads(path.read_bytes())
        loaded = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
        (got,) = jax.tree_util.tree_leaves(loaded(x))  # (the flat program: a list of its one result)
        np.testing.assert_array_equal(np.asarray(got), want)


@stored_on_this_backend
def test_a_loaded_program_that_fails_to_run_is_dropped_for_jit(cache_dir):
    f = pc.cached_jit(_f, static_argnums=(1,))
    x = np.arange(6, dtype=np.float32)
    ref = np.asarray(f(x, _Opts(0.5, "sin"))["y"])
    (key,) = f._mem
    (path,) = cache_dir.iterdir()

    def broken(*a):  # as an executable that loads but misses its kernels fails
        raise RuntimeError("NOT_FOUND: Function fusion not found")

    f._mem[key] = (broken, f._mem[key][1])
    np.testing.assert_array_equal(f(x, _Opts(0.5, "sin"))["y"], ref)
    assert f._mem[key] is None and not path.exists()


def test_the_command_line_keeps_stages_in_its_asset_cache_and_off_turns_it_off(tmp_path, monkeypatch):
    from jaxpbr.cli import _cache

    try:
        monkeypatch.setenv("JAXPBR_ASSET_CACHE", str(tmp_path / "assets"))
        assert _cache.enable_assets() == tmp_path / "assets"
        assert pc.directory() == tmp_path / "assets"
        monkeypatch.setenv("JAXPBR_ASSET_CACHE", "off")
        assert _cache.enable_assets() is None and pc.directory() is None
    finally:
        pc.use_directory(None)
        from jaxpbr.rendering.mesh import ACCELS
        from jaxpbr.rendering.renderer import ASSETS

        ASSETS.use_directory(None)
        ACCELS.use_directory(None)


def test_the_platform_part_of_the_key_is_read_once():
    pc._platform_key()
    before = pc._platform_key.cache_info().hits
    for _ in range(3):
        pc._environment_key()
    assert pc._platform_key.cache_info().hits == before + 3


def test_cube_metadata_is_named_by_its_lookup_part():
    """Two cubes whose metadata differs in provenance only share stored programs, as they share
    jax.jit's (`CubeInfo`); a lookup key that differs gives another program."""
    from jaxpbr.ibl.cubemap import CubeInfo

    a = CubeInfo((("exact_texels", "12"), ("roughness_mapping", "linear"), ("mapping_levels", "5")))
    b = CubeInfo((("mapping_levels", "5"), ("roughness_mapping", "linear"), ("source", "sky.hdr")))
    c = CubeInfo((("mapping_levels", "6"), ("roughness_mapping", "linear")))
    assert pc._canon(a) == pc._canon(b) != pc._canon(c)


@stored_on_this_backend
def test_a_command_recalls_the_programs_its_last_run_used(cache_dir, monkeypatch):
    f = pc.cached_jit(_f, static_argnums=(1,))
    x = np.arange(4, dtype=np.float32)
    pc.recall('["render"]')  # (the command's start: nothing recorded yet)
    ref = np.asarray(f(x, _Opts(1.5, "cos"))["y"])
    pc.remember('["render"]')
    assert pc.recall('["other"]') == 0  # another command: nothing recalled
    # a new process: nothing in memory; the recalled file is read on the background thread
    g = pc.cached_jit(_f, static_argnums=(1,))
    assert pc.recall('["render"]') == 1
    for fut in list(pc._RECALLED.values()):
        fut.result()
    monkeypatch.setattr(pc, "_read", lambda path: pytest.fail("read on the caller's thread"))
    monkeypatch.setattr(pc.cached_jit, "_compile", lambda *a, **k: pytest.fail("compiled"))
    np.testing.assert_array_equal(g(x, _Opts(1.5, "cos"))["y"], ref)
    assert not pc._RECALLED
    # a damaged record is ignored
    (cache_dir / pc.MANIFEST).write_text("{not json")
    assert pc.recall('["render"]') == 0


def test_clear_caches_drops_every_program_held_in_memory(cache_dir):
    """`jaxpbr.clear_caches` empties every stored stage's in-memory programs (and JAX's caches); the
    next call loads the program from its file and gives the same values."""
    import jaxpbr

    f = pc.cached_jit(_f, static_argnums=(1,))
    x = np.linspace(-1, 1, 16, dtype=np.float32)
    ref = np.asarray(f(x, _Opts(1.5, "cos"))["y"])
    assert f._cache_size() >= 1
    jaxpbr.clear_caches()
    assert all(g._cache_size() == 0 for g in list(pc._INSTANCES))
    np.testing.assert_array_equal(np.asarray(f(x, _Opts(1.5, "cos"))["y"]), ref)
    assert f._cache_size() >= 1


@stored_on_this_backend
def test_a_call_ahead_gives_the_results_shapes_and_the_real_call_runs_the_program_compiled_ahead(cache_dir, monkeypatch):
    """`ahead()`: the call traces its program once and hands the compilation to the compiler thread;
    its results come back as shapes equal to the real results' (weak types included); the real
    call then runs that program (no second trace); a later object finds it on disk."""
    traced = []
    orig = pc.cached_jit._trace
    monkeypatch.setattr(pc.cached_jit, "_trace", lambda self, *a: traced.append(self.__name__) or orig(self, *a))

    def g(x, opts, k):
        return {**_f(x, opts), "weak": k * 2.0, "n": jnp.arange(3)}

    f = pc.cached_jit(g, static_argnums=(1,))
    x = np.linspace(-3, 3, 101, dtype=np.float32)
    with pc.ahead():
        shapes = f(jax.ShapeDtypeStruct(x.shape, x.dtype), _Opts(2.0, "cos"), 1.5)
    assert traced == ["g"]
    out = f(x, _Opts(2.0, "cos"), 1.5)
    assert traced == ["g"]  # the program compiled ahead, not traced again
    ref = jax.jit(g, static_argnums=(1,))(x, _Opts(2.0, "cos"), 1.5)
    for k in ref:
        np.testing.assert_array_equal(out[k], ref[k])
        assert isinstance(shapes[k], jax.ShapeDtypeStruct)
        assert (shapes[k].shape, shapes[k].dtype, shapes[k].weak_type) == (ref[k].shape, ref[k].dtype, ref[k].weak_type), k
    assert ref["weak"].weak_type  # (the case the shapes must carry)
    # a fresh object (a later process) finds the stored program: shapes without a trace
    h = pc.cached_jit(g, static_argnums=(1,))
    with pc.ahead():
        again = h(jax.ShapeDtypeStruct(x.shape, x.dtype), _Opts(2.0, "cos"), 1.5)
    assert traced == ["g"]
    assert {k: (s.shape, s.dtype, s.weak_type) for k, s in again.items()} == {k: (s.shape, s.dtype, s.weak_type) for k, s in shapes.items()}
    # what cannot be looked ahead says so
    with pc.ahead(), pytest.raises(pc.NotAhead):
        f(jax.ShapeDtypeStruct(x.shape, x.dtype), lambda: None, 1.5)  # an uncacheable static value
    pc.use_directory(None)
    with pytest.raises(pc.NotAhead), pc.ahead():
        pass


def test_the_asset_shapes_known_before_the_bake_are_the_baked_assets():
    """`assets.asset_shapes` (what the IBL stage is compiled for while the maps are computed) has
    the tree, lookup metadata and leaf shapes of what `ibl_assets` returns, for several options."""
    import jaxpbr as jp
    from jaxpbr.ibl.cubeio import load_environment
    from jaxpbr.rendering.assets import asset_shapes, ibl_assets
    from jaxpbr.rendering.cache import AssetCache
    from jaxpbr.rendering.options import RenderOptions
    from jaxpbr.rendering.plan import plan, split_environment

    radiance = load_environment(["procedural:sky"], face_size=16)
    sphere = jp.Sphere(center=(0.0, 0.0, 0.0), radius=1.0, material=jp.Material(roughness=0.7))
    cam = jp.Camera(position=(0.0, 0.0, 4.0), target=(0.0, 0.0, 0.0), width=8, height=8, fov_y_deg=40.0)
    variants = [{"mapping": "quadratic", "irradiance_size": 8}, {"model": "learnopengl", "extract_lights": False}]
    for kw in variants:
        opts = RenderOptions(**kw)
        cache = AssetCache()
        env = jp.Environment(radiance=radiance)
        scene = jp.Scene(camera=cam, objects=[sphere], environment=env)
        p = plan(scene, options=opts, cache=cache)
        split = split_environment(env, opts, cache)
        real = ibl_assets(split, p, opts, cache)
        shapes = asset_shapes(split.env, p, opts, real[2], split.suns)
        assert jax.tree_util.tree_structure(shapes) == jax.tree_util.tree_structure(real), kw
        assert pc._canon_tree(jax.tree_util.tree_structure(shapes)) == pc._canon_tree(jax.tree_util.tree_structure(real)), kw
        got = [(tuple(x.shape), np.dtype(x.dtype)) for x in jax.tree_util.tree_leaves(shapes)]
        want = [(tuple(x.shape), np.dtype(x.dtype)) for x in jax.tree_util.tree_leaves(real)]
        assert got == want, kw


@stored_on_this_backend
def test_a_cold_render_with_nothing_beside_it_compiles_on_two_threads(cache_dir, monkeypatch):
    """Analytic objects under a baked environment (the demo's case): nothing is computed beside the
    compilations, so two compiler threads compile the stages; each stage is still compiled once.
    The plan's largest roughness is reported, not traced: the scene with a rougher material (as in
    a new process) loads the stored programs instead of tracing and storing its own."""
    import threading

    import jaxpbr as jp

    env = jp.bake(jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(16)))
    scene = jp.Scene(camera=jp.Camera(position=(0.0, 0.0, 4.0), width=32, height=20),
                     objects=[jp.Sphere(center=(0.0, 0.0, 0.0), radius=1.0, material=jp.Material(roughness=0.4))],
                     lights=[jp.PointLight(position=(2.0, 3.0, 3.0), intensity=20.0)], environment=env)
    rougher = scene.replace(objects=[scene.objects[0].replace(material=jp.Material(roughness=0.8))])
    jp.clear_caches()
    threads, orig_compiler = [], pc._compiler
    monkeypatch.setattr(pc, "_compiler", lambda n=1: threads.append(n) or orig_compiler(n))
    finished, orig_finish = [], pc.cached_jit._finish
    monkeypatch.setattr(pc.cached_jit, "_finish", lambda self, *a: finished.append((self.__name__, threading.current_thread().name))
                        or orig_finish(self, *a))
    out = np.asarray(jp.render(scene))
    assert threads and set(threads) == {pc.MAX_COMPILERS} == {2}
    names = [n for n, _ in finished]
    for stage in ("_geometry", "_shade_direct", "_shade_suns", "_shade_rest"):
        assert names.count(stage) == 1 and dict(finished)[stage].startswith("jaxpbr-compile"), finished
    assert np.isfinite(out).all() and out.max() > 0
    stored = _files(cache_dir)
    jp.clear_caches()
    monkeypatch.setattr(pc.cached_jit, "_trace", lambda *a, **k: pytest.fail("traced instead of loaded"))
    again = np.asarray(jp.render(rougher))
    assert _files(cache_dir) == stored and np.isfinite(again).all() and not np.array_equal(again, out)


@stored_on_this_backend
def test_a_cold_staged_render_traces_and_compiles_each_stage_once_ahead(cache_dir, monkeypatch):
    """A cold render with stored programs on (the command line's) looks ahead: every stage of a
    mesh scene with shadows and a sun split out of the sky is traced once, compiled once (on the
    compiler thread), and used (a stage whose shapes were predicted wrongly would be traced and
    compiled again by its real call)."""
    import threading

    import jaxpbr as jp
    from jaxpbr.ibl.cubeio import load_environment
    from jaxpbr.rendering import execute
    from jaxpbr.rendering.demo import uv_sphere

    pos, nrm, tri = uv_sphere(12)
    meshes = [jp.Mesh(positions=pos * 0.8 + np.array([x, 0.0, 0.0]), normals=nrm, triangles=tri,
                      material=jp.Material(base_color=(0.8, 0.5, 0.3), roughness=r)) for x, r in ((-1.0, 0.3), (1.0, 0.8))]
    floor = jp.Plane(point=(0.0, -0.8, 0.0), normal=(0.0, 1.0, 0.0), material=jp.Material(roughness=0.9))
    scene = jp.Scene(camera=jp.Camera(position=(0.0, 1.0, 5.0), target=(0.0, 0.0, 0.0), width=40, height=24, fov_y_deg=45.0),
                     objects=[*meshes, floor], lights=[jp.PointLight(position=(2.0, 4.0, 3.0), intensity=50.0)],
                     environment=jp.Environment(radiance=load_environment(["procedural:sky"], face_size=16)))
    jp.clear_caches()
    traced, finished = [], []
    orig_trace, orig_finish = pc.cached_jit._trace, pc.cached_jit._finish
    monkeypatch.setattr(pc.cached_jit, "_trace", lambda self, *a: traced.append(self.__name__) or orig_trace(self, *a))
    monkeypatch.setattr(pc.cached_jit, "_finish", lambda self, *a: finished.append((self.__name__, threading.current_thread().name))
                        or orig_finish(self, *a))
    looked = []
    orig_ahead = execute._compile_ahead
    monkeypatch.setattr(execute, "_compile_ahead", lambda *a, **k: looked.append(1) or orig_ahead(*a, **k))
    threads, orig_compiler = [], pc._compiler
    monkeypatch.setattr(pc, "_compiler", lambda n=1: threads.append(n) or orig_compiler(n))
    out = np.asarray(jp.render(scene, shadows=True))
    assert looked
    assert set(threads) == {1}  # the ray engine is built and the maps computed meanwhile: one compiler thread
    names = [n for n, _ in finished]
    for stage in ("_cast_inputs", "_geometry", "_light_segments", "_shade_direct", "_sun_segments", "_shade_suns", "_shade_rest"):
        assert traced.count(stage) == 1 and names.count(stage) == 1, (stage, traced, names)
        assert dict(finished)[stage].startswith("jaxpbr-compile"), finished
    assert sorted(traced) == sorted(names)  # nothing compiled twice or left uncompiled
    assert not any(isinstance(e, pc._Pending) for f in list(pc._INSTANCES) for e in f._mem.values())
    assert out.shape == (24, 40, 3) and np.isfinite(out).all() and out.max() > 0


def _compile_overrides(monkeypatch):
    """The XLA option overrides of every compilation from now on (a list of dicts)."""
    from jax._src import compiler

    seen = []
    real = compiler.get_compile_options

    def spy(*args, **kwargs):
        seen.append(dict(kwargs.get("env_options_overrides") or {}))
        return real(*args, **kwargs)

    monkeypatch.setattr(compiler, "get_compile_options", spy)
    return seen


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="cpu_options apply to XLA:CPU")
@pytest.mark.parametrize("stored", [True, False], ids=["stored", "jax.jit"])
def test_cpu_options_reach_xla_stored_and_through_jax_jit_and_stay_out_of_traces(stored, tmp_path, monkeypatch):
    if stored:
        pc.use_directory(tmp_path)
    try:
        f = pc.cached_jit(_f, static_argnums=(1,), cpu_options=pc.LOOP_EMITTERS)
        plain = pc.cached_jit(_f, static_argnums=(1,))
        x = np.linspace(-3, 3, 101, dtype=np.float32)
        seen = _compile_overrides(monkeypatch)
        out = f(x, _Opts(2.0, "cos"))
        with_options = [s for s in seen if s]
        assert with_options and all(s.get("xla_cpu_use_fusion_emitters") in (False, "false", "False") for s in with_options)
        seen.clear()
        ref = plain(x, _Opts(2.0, "cos"))
        assert not any("xla_cpu_use_fusion_emitters" in s for s in seen)
        np.testing.assert_allclose(out["y"], ref["y"], rtol=1e-6, atol=1e-6)
        if stored:  # a key of its own: the program compiled with other options is another file
            assert len(_files(tmp_path)) == 2
        # Inside a trace the program is the caller's (JAX refuses compile options on a nested jit).
        traced = jax.jit(lambda x: f(x, _Opts(2.0, "cos"))["y"])(x)
        np.testing.assert_allclose(traced, ref["y"], rtol=1e-6, atol=1e-6)
        g = jax.grad(lambda x: f(x, _Opts(2.0, "cos"))["sum"])(x)
        np.testing.assert_allclose(g, 2.0 * np.cos(x) - np.sin(x), rtol=1e-5, atol=1e-5)
    finally:
        pc.use_directory(None)


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="cpu_options apply to XLA:CPU")
def test_cpu_jit_compiles_with_its_options_outside_traces_and_as_plain_jit_inside(monkeypatch):
    def g(x, opts):  # (a function of its own: jax.jit's caches are per function)
        """g's docstring"""
        return _f(x, opts)

    f = pc.cpu_jit(g, static_argnums=(1,))
    x = np.linspace(-3, 3, 101, dtype=np.float32)
    seen = _compile_overrides(monkeypatch)
    out = f(x, _Opts(2.0, "sin"))
    assert seen and seen[-1].get("xla_cpu_use_fusion_emitters") in (False, "false", "False")
    assert f._cache_size() == 1 and f.__name__ == "g" and f.__doc__ == "g's docstring"
    ref = jax.jit(_f, static_argnums=(1,))(x, _Opts(2.0, "sin"))
    np.testing.assert_allclose(out["y"], ref["y"], rtol=1e-6, atol=1e-6)
    seen.clear()
    traced = jax.jit(lambda x: f(x, _Opts(2.0, "sin"))["y"])(x)  # no option on a nested jit
    assert not any("xla_cpu_use_fusion_emitters" in s for s in seen)
    np.testing.assert_allclose(traced, ref["y"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(jax.grad(lambda x: f(x, _Opts(2.0, "sin"))["sum"])(x), 2.0 * np.cos(x), rtol=1e-5, atol=1e-5)
    assert f.lower(x, _Opts(2.0, "sin")).compile() is not None
    f.clear_cache()
    assert f._cache_size() == 0
