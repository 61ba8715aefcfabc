"""The baked IBL set from Python: `jaxpbr.write_baked` writes what `jaxpbr ibl` writes, and
`jaxpbr.read_baked` reads it back into an `Environment` that renders as `jaxpbr.bake` of the same
environment does.

Tolerances. The maps are computed by the same functions with the same options in both paths, so
with float32 storage (KTX2 rgba32f, EXR) the maps read back are the computed ones bit for bit and
the renders are equal. The default KTX2 rgba16f rounds every stored value to float16: a relative
error of at most 2^-11 = 4.9e-4 per texel (the values here are far above float16's subnormals).
Every pixel is a combination with non-negative weights of such texels plus terms that are stored
exactly (the LUT is float32 EXR, the extracted suns are JSON floats), so a pixel is off by at most
2^-11 of its value too, up to float32 rounding of the shading arithmetic; the test allows 1e-3.

Files against the command line: the same arguments give byte-identical map files (KTX2, EXR: the
same float32 computations, serialised by the same writers; the library is given a progress
callback, as the command line always passes one, so the same programs are compiled) and sidecars
and ibl.json equal except where they must differ: the measured run times ("seconds") and the
folder in the "files" paths.
"""

from __future__ import annotations

import json
import shutil

import jax
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.errors import InputError
from jaxpbr.ibl import baked
from jaxpbr.io.ktx2 import read_ktx2

FACE = 16
#: Small and fast; the renderer's `bake` takes the same options under its own names.
WRITE = {"samples": 16, "lut_size": 8, "irradiance_size": 8, "measure_error": False}
BAKE = {"prefilter_samples": 16, "lut_size": 8, "irradiance_size": 8}
F16 = 2.0**-11


@pytest.fixture(scope="module")
def sky():
    return jp.envs.sky_with_sun_cubemap(FACE)


@pytest.fixture(scope="module")
def set32(sky, tmp_path_factory):
    """A set of the sky with sheen, float32 KTX2, and the index `write_baked` returned."""
    d = tmp_path_factory.mktemp("set32")
    index = jp.write_baked(jp.Environment(radiance=sky), d, ktx_format="rgba32f", **WRITE)
    return d, index


def _state(d):
    return {p.name: (None if p.is_dir() else p.read_bytes()) for p in sorted(d.iterdir())}


def _scene(env, *, sheen=True):
    mats = [jp.Material(base_color=(0.9, 0.6, 0.3), metallic=1.0, roughness=0.3),
            jp.Material(base_color=(0.2, 0.5, 0.8), metallic=0.0, roughness=0.7)]
    if sheen:
        mats.append(jp.Material(base_color=(0.3, 0.3, 0.3), roughness=0.5, sheen_color=(0.8, 0.4, 0.6), sheen_roughness=0.4))
    objs = [jp.Sphere(center=(2.0 * k - (len(mats) - 1), 0.0, 0.0), radius=0.9, material=m) for k, m in enumerate(mats)]
    camera = jp.Camera(position=(0.0, 0.5, 6.0), target=(0.0, 0.0, 0.0), width=12 * len(mats), height=12, fov_y_deg=40.0)
    # A rotation (applied at render time to both) keeps reflection vectors off the face diagonals.
    return jp.Scene(camera=camera, objects=objs, environment=env.replace(rotation=0.7))


# ------------------------------------------------------------------------------ round trip


def test_round_trip_float32_renders_as_bake(sky, set32):
    """rgba32f: the maps read back are bake's bit for bit, the Environments have one tree structure
    (the lookup keys compare equal: the render reuses bake's compiled programs), and the renders,
    background included, are equal."""
    d, index = set32
    read = jp.read_baked(d)
    ref = jp.bake(jp.Environment(radiance=sky), sheen=True, extract_lights=False, **BAKE)
    assert read.baked and read.lights is None and read.lut_smith == ref.lut_smith == "correlated"
    for name in ("irradiance", "prefiltered", "charlie"):
        a, b = getattr(read, name), getattr(ref, name)
        assert a.num_levels == b.num_levels
        for x, y in zip(a.levels, b.levels):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_array_equal(np.asarray(read.lut), np.asarray(ref.lut))
    np.testing.assert_array_equal(np.asarray(read.sheen_lut), np.asarray(ref.sheen_lut))
    np.testing.assert_array_equal(np.asarray(read.radiance.levels[0]), np.asarray(sky.levels[0]))
    assert jax.tree_util.tree_structure(read) == jax.tree_util.tree_structure(ref)
    np.testing.assert_array_equal(np.asarray(jp.render(_scene(read))), np.asarray(jp.render(_scene(ref))))
    # The returned index is ibl.json.
    assert json.loads(json.dumps(index)) == json.loads((d / "ibl.json").read_text())


def test_round_trip_float16_with_extracted_suns(sky, tmp_path):
    """The default rgba16f with the suns split out: the lights come back exactly, the maps within
    float16's rounding, and the surfaces render within 1e-3 (module docstring). The background is
    what the set stores: the residual without the sun, so it is left out of the comparison."""
    index = jp.write_baked(jp.Environment(radiance=sky), tmp_path, extract=True, sheen=False, **WRITE)
    assert index["lights"]["count"] == 1 and "charlie" not in index
    read = jp.read_baked(tmp_path)
    ref = jp.bake(jp.Environment(radiance=sky), extract_lights=True, **BAKE)
    assert read.charlie is None and read.sheen_lut is None
    (a,), (b,) = read.lights, ref.lights
    for f in ("direction", "color", "intensity", "angular_radius"):
        np.testing.assert_array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)))
    for name in ("irradiance", "prefiltered"):
        for x, y in zip(getattr(read, name).levels, getattr(ref, name).levels):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=F16, atol=0)
    imgs = [np.asarray(jp.render(_scene(e.replace(show_background=False), sheen=False))) for e in (read, ref)]
    assert np.abs(imgs[1]).max() > 0.1
    np.testing.assert_allclose(imgs[0], imgs[1], rtol=1e-3, atol=1e-6)


def test_a_set_with_the_radiance_draws_the_environment_itself(sky, tmp_path):
    """radiance=True stores the environment before the suns are split out (float32 here: bit for
    bit), and read_baked draws it as the background, as a render of the radiance does: the whole
    image, background included, equals the in-memory bake's."""
    index = jp.write_baked(jp.Environment(radiance=sky), tmp_path, extract=True, radiance=True, sheen=False,
                           ktx_format="rgba32f", **WRITE)
    assert index["radiance"]["files"] == [str(tmp_path / "radiance.ktx2")] and "radiance" in index["lookup"]
    read = jp.read_baked(tmp_path)
    np.testing.assert_array_equal(np.asarray(read.radiance.levels[0]), np.asarray(sky.levels[0]))
    ref = jp.bake(jp.Environment(radiance=sky), extract_lights=True, **BAKE)
    imgs = [np.asarray(jp.render(_scene(e, sheen=False))) for e in (read, ref)]
    np.testing.assert_allclose(imgs[0], imgs[1], rtol=1e-6, atol=1e-7)


def test_exr_container_reads_back_as_the_ktx2_set(sky, set32, tmp_path):
    """container="exr": one float32 EXR per mip and face; read back, the same maps and lookup
    metadata as the rgba32f KTX2 set."""
    jp.write_baked(sky, tmp_path, container="exr", **WRITE)
    names = {p.name for p in tmp_path.iterdir()}
    assert {"prefiltered_m0_px.exr", "prefiltered_m4_nz.exr", "irradiance_m0_nz.exr", "charlie_m4_px.exr", "brdf_lut.exr", "ibl.json"} <= names
    assert not any(n.endswith(".ktx2") for n in names)
    got, want = baked.read_baked_maps(tmp_path), baked.read_baked_maps(set32[0])
    for name in ("irradiance", "prefiltered", "charlie"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.info == b.info and a.metadata["lod_blend" if name != "irradiance" else "irradiance_method"]
        for x, y in zip(a.levels, b.levels, strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_an_environment_with_intensity_bakes_its_scaled_radiance(sky, set32, tmp_path):
    jp.write_baked(jp.Environment(radiance=sky, intensity=2.0), tmp_path, sheen=False, ktx_format="rgba32f", **WRITE)
    got, want = baked.read_baked_maps(tmp_path), baked.read_baked_maps(set32[0])
    for name in ("irradiance", "prefiltered"):
        for x, y in zip(getattr(got, name).levels, getattr(want, name).levels):
            np.testing.assert_allclose(np.asarray(x), 2.0 * np.asarray(y), rtol=1e-5)


# ----------------------------------------------------------------------- the command line


def test_the_files_are_the_command_lines(tmp_path):
    """`jaxpbr ibl` and `write_baked` with the same arguments: byte-identical maps, and sidecars and
    ibl.json equal but for the run times and the folder (module docstring)."""
    from jaxpbr.cli import main

    cli, lib = tmp_path / "cli", tmp_path / "lib"
    cli.mkdir()
    lib.mkdir()
    argv = ["ibl", "procedural:sky", "--face-size", "16", "--samples", "16", "--lut-size", "8", "--irradiance-size", "8",
            "--charlie-size", "8", "--charlie-levels", "3", "--extract-lights", "--radiance", "--no-error", "--quiet", "--out-dir", str(cli)]
    assert main(argv) == 0
    # (--quiet: no progress, so none here either; a program reporting progress runs its rows in
    # groups and its last bits may differ)
    index = jp.write_baked("procedural:sky", lib, face_size=16, samples=16, lut_size=8, irradiance_size=8, charlie_size=8,
                           charlie_levels=3, extract=True, radiance=True, measure_error=False)
    names = sorted(p.name for p in cli.iterdir())
    assert names == sorted(p.name for p in lib.iterdir())
    assert {"irradiance.ktx2", "prefiltered.ktx2", "charlie.ktx2", "brdf_lut.exr", "lights.json", "ibl.json", "radiance.ktx2"} <= set(names)
    # The stored radiance is the sky before the sun was split out (float16 storage), and the
    # background read_baked draws; the residual's chain lacks the sun.
    sky, env = jp.envs.sky_with_sun_cubemap(16), jp.read_baked(lib)
    np.testing.assert_allclose(np.asarray(env.radiance.levels[0]), np.asarray(sky.levels[0]), rtol=F16)
    assert float(np.max(env.radiance.levels[0])) > 1000.0 > float(np.max(env.prefiltered.levels[0]))

    def content(d, name):
        def norm(x):
            if isinstance(x, dict):
                return {k: norm(v) for k, v in x.items() if k != "seconds"}
            if isinstance(x, list):
                return [norm(v) for v in x]
            return x.replace(str(d), "<dir>") if isinstance(x, str) else x

        return norm(json.loads((d / name).read_text()))

    for name in names:
        if name.endswith(".json"):
            assert content(cli, name) == content(lib, name), name
        else:
            assert (cli / name).read_bytes() == (lib / name).read_bytes(), name
    assert json.loads(json.dumps(index)) == json.loads((lib / "ibl.json").read_text())


# ------------------------------------------------------------------------------- refusals


@pytest.mark.parametrize(
    "case, match",
    [
        ("no_folder", "does not exist"),
        ("a_file", "is a file, not a folder"),
        ("no_index", "ibl.json' is missing"),
        ("index_garbage", "cannot read '{d}/ibl.json'"),
        ("index_without_prefiltered", "no 'prefiltered' entry"),
        ("ktx2_truncated", "prefiltered.ktx2"),
        ("ktx2_not_ktx2", "irradiance.ktx2"),
        ("charlie_missing", "charlie.ktx2' (named by ibl.json) is missing"),
        ("lut_garbage", "brdf_lut.exr"),
        ("face_size_mismatch", "has face size 16, but ibl.json says 32"),
    ],
)
def test_read_refuses_a_bad_set_naming_the_file_and_the_fix(set32, tmp_path, case, match):
    d = tmp_path / "set"
    shutil.copytree(set32[0], d)
    if case == "no_folder":
        shutil.rmtree(d)
    elif case == "a_file":
        shutil.rmtree(d)
        d.write_text("x")
    elif case == "no_index":
        (d / "ibl.json").unlink()
    elif case == "index_garbage":
        (d / "ibl.json").write_text("{ not json")
    elif case == "index_without_prefiltered":
        index = json.loads((d / "ibl.json").read_text())
        del index["prefiltered"]
        (d / "ibl.json").write_text(json.dumps(index))
    elif case == "ktx2_truncated":
        data = (d / "prefiltered.ktx2").read_bytes()
        (d / "prefiltered.ktx2").write_bytes(data[: len(data) // 2])
    elif case == "ktx2_not_ktx2":
        (d / "irradiance.ktx2").write_bytes(b"\x89PNG\r\n\x1a\n not a cube")
    elif case == "charlie_missing":
        (d / "charlie.ktx2").unlink()
    elif case == "lut_garbage":
        (d / "brdf_lut.exr").write_bytes(b"not an exr")
    elif case == "face_size_mismatch":
        index = json.loads((d / "ibl.json").read_text())
        index["prefiltered"]["face_size"] = 32
        (d / "ibl.json").write_text(json.dumps(index))
    before = _state(d) if d.is_dir() else None
    with pytest.raises(InputError) as e:
        jp.read_baked(d)
    msg = str(e.value)
    assert match.format(d=d) in msg and len(msg.splitlines()) == 1, msg
    if case not in ("no_folder", "a_file"):
        assert "bake the set again" in msg and "write_baked" in msg and "jaxpbr ibl" in msg, msg
    assert (_state(d) if d.is_dir() else None) == before  # reading writes nothing


@pytest.fixture
def no_work(monkeypatch):
    """Every precompute of write_baked fails loudly: a refusal must come before them."""

    def started(*a, **k):
        raise AssertionError("the work started before the input was refused")

    for name in ("irradiance", "prefilter", "prefilter_charlie", "brdf_lut", "extract_lights"):
        monkeypatch.setattr(baked, name, started)


@pytest.mark.parametrize(
    "case, match",
    [
        ("missing_folder", "out_dir '{d}/nope' does not exist; create it first"),
        ("folder_is_a_file", "is a file, not a folder"),
        ("size_not_a_mip", "size=12 must be the environment cube's face size (16) divided by a power of two"),
        ("too_many_levels", "levels=9: a 16^2 prefiltered cube has at most 5 levels"),
        ("charlie_without_sheen", "charlie_size / charlie_levels set the Charlie cube, which sheen=False leaves out"),
        ("charlie_levels", "charlie_levels=5: a 8^2 Charlie cube has at most 4 levels"),
        ("rotated", "rotation=0.5"),
        ("already_baked", "already carries irradiance, prefiltered, lut"),
        ("container", "container='png' is not a cube container"),
        ("float16", "beyond the float16 range of ktx_format='rgba16f' (65504); use ktx_format='rgba32f'"),
        ("not_an_environment", "got int"),
        ("lut_output_is_a_folder", "brdf_lut.exr' is a directory"),
    ],
)
def test_write_refuses_before_any_work_and_writes_nothing(sky, tmp_path, no_work, case, match):
    d = tmp_path / "out"
    d.mkdir()
    env, out, kw = jp.Environment(radiance=sky), d, dict(WRITE)
    if case == "missing_folder":
        out = d / "nope"
    elif case == "folder_is_a_file":
        out = d / "file"
        out.write_text("x")
    elif case == "size_not_a_mip":
        kw["size"] = 12
    elif case == "too_many_levels":
        kw["levels"] = 9
    elif case == "charlie_without_sheen":
        kw |= {"sheen": False, "charlie_size": 8}
    elif case == "charlie_levels":
        kw |= {"charlie_size": 8, "charlie_levels": 5}
    elif case == "rotated":
        env = env.replace(rotation=0.5)
    elif case == "already_baked":
        env = env.replace(irradiance=sky, prefiltered=sky, lut=np.zeros((8, 8, 2), np.float32), lut_smith="correlated")
    elif case == "container":
        kw["container"] = "png"
    elif case == "float16":
        hot = np.asarray(sky.levels[0]).copy()
        hot[0, 3, 3] = 1e6
        env = jp.Cubemap(hot)
    elif case == "not_an_environment":
        env = 3
    elif case == "lut_output_is_a_folder":
        (d / "brdf_lut.exr").mkdir()
    before = _state(d)
    with pytest.raises(InputError) as e:
        jp.write_baked(env, out, **kw)
    assert match.format(d=d) in str(e.value), str(e.value)
    assert _state(d) == before


def test_a_failure_midway_leaves_the_previous_set(set32, tmp_path, monkeypatch):
    """The Charlie step fails after irradiance.ktx2, prefiltered.ktx2 and their sidecars were
    replaced: every file of the previous set is back, byte for byte, and nothing else is left."""
    d = tmp_path / "set"
    shutil.copytree(set32[0], d)
    before = _state(d)
    real, calls = baked.write_json, []

    def counted(path, data, **kw):
        calls.append(path.name)
        return real(path, data, **kw)

    def full(*a, **k):
        raise OSError("No space left on device")

    monkeypatch.setattr(baked, "write_json", counted)
    monkeypatch.setattr(baked, "prefilter_charlie", full)
    with pytest.raises(OSError, match="No space left"):
        jp.write_baked("procedural:sky", d, face_size=FACE, ktx_format="rgba16f", **WRITE)
    assert calls == ["irradiance.ktx2.json", "prefiltered.ktx2.json"]
    assert _state(d) == before
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(OSError, match="No space left"):
        jp.write_baked("procedural:sky", empty, face_size=FACE, **WRITE)
    assert list(empty.iterdir()) == []


def test_prefiltered_file_keeps_its_lookup_keys(set32):
    """The lookup keys travel in the KTX2 key/values and come back as the Cubemap's info."""
    d, index = set32
    _, meta, _ = read_ktx2(d / "prefiltered.ktx2")
    pre = jp.read_baked(d).prefiltered
    for k in ("roughness_mapping", "mapping_levels", "lod_blend"):
        assert pre.metadata[k] == meta[f"jaxpbr:{k}"] == index["prefiltered"][k]
    assert jp.read_baked(d).charlie.metadata["distribution"] == "charlie"


# ------------------------------------------------------------------------------------------
# The demo's sky, shipped baked (jaxpbr/_demo_sky)
# ------------------------------------------------------------------------------------------


def test_the_shipped_demo_sky_is_a_fresh_bake_of_the_procedural_sky():
    """The set in the package holds what a render of the demo's sky computes today: the sun split
    out, the residual (drawn as the background), its irradiance and GGX chain with their lookup
    metadata. Here (the machine that wrote the set) they are equal bit for bit; a backend that sums
    in another order (a GPU, another XLA) rounds the float32 sums differently, hence rtol 1e-5
    (about 80 float32 ulps, three orders below the maps' own error against their float64
    references, recorded in the sidecars). The demo's scene holds the shipped set, and a scene
    under it (at the demo's rotation) renders as under the sky's radiance, whose maps the
    renderer computes (the module's spheres: their programs are shared with the tests above)."""
    from jaxpbr.rendering import demo

    shipped = demo.shipped_demo_sky()
    assert shipped is not None, "jaxpbr/_demo_sky is missing from the package"
    fresh = jp.bake(jp.Environment(radiance=jp.envs.sky_with_sun_cubemap(demo.DEMO_FACE_SIZE)))
    assert shipped.lut is None and fresh.lights is not None and len(shipped.lights) == len(fresh.lights) == 1
    for a, b in zip(shipped.lights, fresh.lights):
        for f in ("direction", "color", "intensity", "angular_radius"):
            np.testing.assert_allclose(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)), rtol=1e-5, err_msg=f)
    pairs = [("radiance (the background)", shipped.radiance, fresh.radiance),
             ("irradiance", shipped.irradiance, fresh.irradiance), ("prefiltered", shipped.prefiltered, fresh.prefiltered)]
    for what, a, b in pairs:
        assert len(a.levels) == len(b.levels), what
        for m, (x, y) in enumerate(zip(a.levels, b.levels)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-7, err_msg=f"{what} level {m}")
    lookup = ("mapping_levels", "roughness_mapping", "lod_blend", "level_mean_cosine", "lod_table", "chain_floor")
    assert {k: shipped.prefiltered.metadata.get(k) for k in lookup} == {k: fresh.prefiltered.metadata.get(k) for k in lookup}

    demo_env = demo.demo_scene(32, 18).environment
    assert demo_env.prefiltered is shipped.prefiltered and np.float32(demo_env.rotation) == np.float32(demo.DEMO_ENV_ROTATION)
    radiance = jp.Environment(radiance=demo.demo_sky(demo.DEMO_FACE_SIZE), rotation=demo.DEMO_ENV_ROTATION)
    imgs = [np.asarray(jp.render(_scene(e, sheen=False).replace(environment=e))) for e in (demo_env, radiance)]
    np.testing.assert_allclose(imgs[0], imgs[1], rtol=1e-5, atol=1e-6)
