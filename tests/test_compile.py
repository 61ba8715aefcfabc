"""Compile once (issue 10, item 2): the number of XLA programs a cold `jaxpbr render` compiles, the
CLI's persistent caches (compiled programs, baked IBL maps) and where they live."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.cli import _cache
from jaxpbr.rendering import renderer, stages

#: At most this many XLA programs for the demo from a cold start (issue 10: 221 before).
MAX_PROGRAMS = 25


def _cli_env(tmp_path, **extra):
    env = dict(os.environ)
    for name in ("JAX_COMPILATION_CACHE_DIR", "JAX_COMPILATION_CACHE_MAX_SIZE", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
                 "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"):
        env.pop(name, None)
    env.update(XDG_CACHE_HOME=str(tmp_path / "xdg"), **extra)
    return env


def test_cold_demo_render_compiles_few_programs(tmp_path):
    """The demo (49 spheres, 4 lights, IBL with a 128^2 sky: irradiance, 8 prefiltered mips, LUT),
    at a small image size, with every cache off: count the XLA compilations."""
    out = subprocess.run(
        [sys.executable, "-m", "jaxpbr", "render", "--width", "64", "--height", "36", "-o", str(tmp_path / "d.png")],
        capture_output=True, text=True, timeout=600,
        env=_cli_env(tmp_path, JAX_LOG_COMPILES="1", JAXPBR_COMPILATION_CACHE="off", JAXPBR_ASSET_CACHE="off"),
    )
    assert out.returncode == 0, out.stderr[-2000:]
    programs = [line for line in out.stderr.splitlines() if "Finished XLA compilation" in line]
    assert 0 < len(programs) <= MAX_PROGRAMS, "\n".join(programs)
    assert not (tmp_path / "xdg").exists()  # both caches off: nothing written


def test_cli_caches_default_location_and_switches(tmp_path, monkeypatch):
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.delenv(_cache.ENV, raising=False)
    monkeypatch.delenv(_cache.ASSET_ENV, raising=False)
    # As in a fresh process (the test session itself runs with a compilation cache configured).
    monkeypatch.setattr(_cache, "jax", SimpleNamespace(config=SimpleNamespace(jax_compilation_cache_dir=None)))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert _cache.cache_dir() == tmp_path / "jaxpbr" / "jax-compilation-cache-lru"
    assert _cache.asset_dir() == tmp_path / "jaxpbr" / "assets"
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "theirs"))  # the user's JAX setting wins
    assert _cache.cache_dir() == tmp_path / "theirs"
    monkeypatch.setenv(_cache.ENV, str(tmp_path / "mine"))  # ...and jaxpbr's own over it
    assert _cache.cache_dir() == tmp_path / "mine"
    for off in ("0", "off", "OFF", ""):
        monkeypatch.setenv(_cache.ENV, off)
        monkeypatch.setenv(_cache.ASSET_ENV, off)
        assert _cache.cache_dir() is None and _cache.asset_dir() is None


def test_prune_deletes_the_oldest_files(tmp_path):
    for i in range(10):
        p = tmp_path / f"f{i}"
        p.write_bytes(b"x" * 100)
        os.utime(p, (1000 + i, 1000 + i))
    _cache.prune(tmp_path, max_bytes=500)
    # 1000 bytes > 500: the oldest go until at most 250 bytes are left, the two newest.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f8", "f9"]
    _cache.prune(tmp_path, max_bytes=500)  # under the limit: nothing more goes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f8", "f9"]


@pytest.fixture
def disk_assets(tmp_path):
    renderer.ASSETS.clear()
    renderer.ASSETS.use_directory(tmp_path / "assets")
    yield tmp_path / "assets"
    renderer.ASSETS.use_directory(None)
    renderer.ASSETS.clear()


def _scene(env):
    return jp.Scene(
        camera=jp.Camera(position=(0.0, 0.0, 3.2), width=12, height=12),
        objects=[jp.Sphere(material=jp.Material(metallic=0.5, roughness=0.5))],
        environment=env,
    )


def test_asset_cache_on_disk_round_trip(disk_assets, monkeypatch):
    env = jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(16))
    first = np.asarray(jp.render(_scene(env)))
    files = sorted(p.name.split("-")[0] for p in disk_assets.iterdir())
    assert files == ["extract", "irradiance", "prefilter"]
    assert jp.rendering.renderer.plan(_scene(env)).env_lights == 1  # a sun was split out and kept
    # A new process (memory cache empty) loads the sun, its residual and the maps instead of
    # computing them, and marks the files as used (pruning deletes the oldest modification times first).
    renderer.ASSETS.clear()
    for p in disk_assets.iterdir():
        os.utime(p, (1000, 1000))
    monkeypatch.setattr(jp.ibl.extract, "extract_lights", lambda *a, **k: pytest.fail("sun extracted again"))
    monkeypatch.setattr(jp.ibl.specular, "prefilter", lambda *a, **k: pytest.fail("prefilter recomputed"))
    monkeypatch.setattr(jp.ibl.diffuse, "irradiance", lambda *a, **k: pytest.fail("irradiance recomputed"))
    again = np.asarray(jp.render(_scene(env)))
    np.testing.assert_array_equal(again, first)
    stats = renderer.ASSETS.stats
    assert stats["prefilter"]["disk"] == 1 and stats["irradiance"]["disk"] == 1 and stats["extract"]["disk"] == 1
    assert all(p.stat().st_mtime > 1000 for p in disk_assets.iterdir())


def test_the_demo_sky_is_kept_in_the_asset_cache(disk_assets, monkeypatch):
    from jaxpbr.rendering import demo

    first = demo.demo_sky(8)
    np.testing.assert_array_equal(first.levels[0], jp.envs.sky_with_sun_cubemap(8).levels[0])
    assert [p.name.split("-")[0] for p in disk_assets.iterdir()] == ["sky"]
    renderer.ASSETS.clear()  # a new process: read from the file, not filtered again
    monkeypatch.setattr(demo, "sky_with_sun_cubemap", lambda *a, **k: pytest.fail("sky filtered again"))
    again = demo.demo_sky(8)
    np.testing.assert_array_equal(again.levels[0], first.levels[0])
    assert dict(again.info) == dict(first.info) and renderer.ASSETS.stats["sky"]["disk"] == 1


def test_asset_cache_disk_hit_inside_a_trace_stores_no_tracer(disk_assets, monkeypatch):
    """A map loaded from disk while the caller traces (jit of a one-program render) is loaded on
    another thread: device_put on the tracing thread returned a tracer, which the cache kept."""
    import jax

    env = jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(16))

    def traced_render(r):  # the environment is concrete (closed over); the material may be traced
        sc = _scene(env)
        return jp.render(sc.replace(objects=[o.replace(material=jp.Material(metallic=0.5, roughness=r)) for o in sc.objects]))

    first = np.asarray(traced_render(1.0))  # r = 1: the whole chain, as a traced roughness needs
    renderer.ASSETS.clear()
    monkeypatch.setattr(renderer.EXECUTION, "staged", False)
    traced = np.asarray(jax.jit(traced_render)(1.0))
    assert renderer.ASSETS.stats["prefilter"]["disk"] == 1
    assert not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(list(renderer.ASSETS._store.values())))
    np.testing.assert_allclose(traced, first, rtol=2e-5, atol=2e-6)
    np.testing.assert_allclose(np.asarray(traced_render(1.0)), first, rtol=2e-5, atol=2e-6)  # no leaked tracer


def test_asset_cache_recomputes_an_unreadable_file_and_survives_an_unwritable_dir(disk_assets, tmp_path):
    env = jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(16))
    first = np.asarray(jp.render(_scene(env)))
    for p in disk_assets.iterdir():
        p.write_bytes(b"not an npz")  # truncated / foreign file
    renderer.ASSETS.clear()
    np.testing.assert_array_equal(np.asarray(jp.render(_scene(env))), first)
    assert "disk" not in renderer.ASSETS.stats["prefilter"]
    blocker = tmp_path / "file"
    blocker.write_text("")
    renderer.ASSETS.use_directory(blocker / "assets")  # cannot be created: renders uncached
    renderer.ASSETS.clear()
    np.testing.assert_array_equal(np.asarray(jp.render(_scene(env))), first)
    assert not Path(blocker / "assets").exists()


def test_environments_differing_in_content_and_provenance_share_every_program():
    """Two environments of one size (different texels, names and data-dependent metadata such as
    the prefilter's exact-texel count): the second render compiles no stage again, because only
    a map's lookup keys are part of its identity (cubemap.CubeInfo); its own metadata is kept.
    An environment of another size compiles the IBL stage only."""
    cam = jp.Camera(position=(0.0, 0.0, 4.0), target=(0.0, 0.0, 0.0), width=12, height=12, fov_y_deg=40.0)

    def scene(env):
        return jp.Scene(camera=cam, objects=[jp.Sphere(center=(0.0, 0.0, 0.0), radius=1.0,
                        material=jp.Material(base_color=(0.8, 0.5, 0.3), metallic=0.0, roughness=0.5))],
                        lights=[jp.PointLight(position=(2.0, 2.0, 3.0), intensity=10.0)], environment=env)

    a = jp.envs.sky_with_sun_cubemap(16, sun_radiance=0.0)
    b = jp.Cubemap(a.levels[0][..., ::-1] * 0.5 + 0.1, {"environment": "another one", "source": "test"})
    ea, eb = jp.bake(jp.Environment(radiance=a)), jp.bake(jp.Environment(radiance=b))
    assert dict(ea.radiance.info) != dict(eb.radiance.info)  # provenance differs ...
    assert eb.radiance.metadata["environment"] == "another one"  # ... and is kept
    programs = (stages._geometry_jit, stages._shade_direct_jit, stages._shade_suns_jit, stages._shade_rest_jit)
    jp.render(scene(ea))
    sizes = [f._cache_size() for f in programs]
    img = jp.render(scene(eb))
    assert [f._cache_size() for f in programs] == sizes
    assert np.isfinite(np.asarray(img)).all()
    # a different lookup rule is a different program
    from jaxpbr.ibl.cubemap import CubeInfo

    assert CubeInfo((("lod_blend", "roughness"),)) != CubeInfo((("lod_blend", "mean_cosine"),))
    assert CubeInfo((("lod_blend", "roughness"), ("environment", "x"))) == CubeInfo((("lod_blend", "roughness"),))
    # Only the IBL stage samples the maps: under maps of other sizes (the baked set's level 1 and
    # below, another lookup metadata, no LUT) the geometry and direct-lighting stages are reused and
    # the IBL stage is compiled for the new maps (no sun here: no sun stage).
    smaller = jp.Environment(radiance=jp.Cubemap(ea.radiance.levels[0][:, ::2, ::2]), rotation=0.3,
                             irradiance=jp.Cubemap(ea.irradiance.levels[0][:, ::2, ::2]),
                             prefiltered=jp.Cubemap(ea.prefiltered.levels[1:], {"lod_blend": "roughness"}))
    img = jp.render(scene(smaller))
    # (counts as deltas: jax.jit's caches are per process, and an earlier test in this worker may
    # have compiled a sun stage of its own)
    assert [f._cache_size() for f in programs] == [sizes[0], sizes[1], sizes[2], sizes[3] + 1]
    assert np.isfinite(np.asarray(img)).all()


def test_extraction_round_trips_through_the_disk_cache(tmp_path):
    """Kind "extract" (the suns split out of an environment and the residual map) is read back from
    disk equal to what was computed, also when no sun was found (the caller keeps its own map)."""
    from jaxpbr.ibl.extract import extract_lights
    from jaxpbr.rendering.cache import AssetCache

    sky = jp.envs.sky_with_sun_cubemap(16)
    uniform = jp.Cubemap([np.full((6, 8, 8, 3), 0.5, np.float32)])
    for name, env in (("sky", sky), ("uniform", uniform)):
        def compute(env=env):
            ex = extract_lights(env)
            return (ex.lights or None), ex.residual

        lights, residual = AssetCache(directory=tmp_path).get("extract", name, compute)
        again_lights, again_residual = AssetCache(directory=tmp_path).get(
            "extract", name, lambda: pytest.fail("extracted again"))
        if name == "uniform":
            assert lights is None and again_lights is None
            continue
        assert len(again_lights) == len(lights) == 1
        for f in ("direction", "color", "intensity", "angular_radius"):
            np.testing.assert_array_equal(np.asarray(getattr(again_lights[0], f)), np.asarray(getattr(lights[0], f)))
        np.testing.assert_array_equal(np.asarray(again_residual.levels[0]), np.asarray(residual.levels[0]))
        assert dict(again_residual.info) == dict(residual.info)
