"""`jaxpbr lut | irradiance | prefilter | ibl`: happy paths (files, sidecars, KTX2 contents) and
every bad input of the issue (one line on stderr, non-zero exit, no files left behind)."""

import json
import os

import numpy as np
import OpenEXR
import pytest

from jaxpbr.cli import main
from jaxpbr.ibl.cubemap import Cubemap, equirect_directions
from jaxpbr.io import image
from jaxpbr.io.ktx2 import read_ktx2


def _sky_equirect(H=32):
    d = equirect_directions(H)
    return (1.0 + 0.5 * d[..., 1:2] + 0.25 * d[..., 0:1] ** 2) * np.array([1.0, 0.9, 0.8])


@pytest.fixture
def pano(tmp_path):
    p = tmp_path / "sky.exr"
    image.write(p, _sky_equirect().astype(np.float32))
    return p


def _raw_exr(path, arr):
    """Write an EXR with OpenEXR directly (image.write refuses NaN, which is the point here)."""
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(hdr, {"RGB": np.ascontiguousarray(arr, np.float32)}) as f:
        f.write(str(path))


def _files(d):
    return sorted(p.name for p in d.iterdir())


def test_irradiance_ktx2_and_sidecar(tmp_path, pano, capsys):
    out = tmp_path / "irr.ktx2"
    assert main(["irradiance", str(pano), "--face-size", "16", "--size", "8", "-o", str(out), "--quiet"]) == 0
    levels, meta, info = read_ktx2(out)
    assert info["face_count"] == 6 and len(levels) == 1 and levels[0].shape == (6, 8, 8, 4)
    side = json.loads((tmp_path / "irr.ktx2.json").read_text())
    assert side["kind"] == "irradiance" and "E/pi" in side["quantity"]
    assert "cube_faces" in side["conventions"] and side["versions"]["jax"]
    err = side["error_vs_float64_exact_full_resolution"]
    assert err["max"] < 1e-3  # 16^2 source is the full resolution here: the same convolution
    # A panorama of 1 + 0.5 y + 0.25 x^2 is smooth: Ebar(+Y) from the closed forms (MATH 7.4):
    # linear part 1 + (2/3)(0.5)(n.y) = 4/3; x^2 part: E[x^2 cos]/pi over the hemisphere = 1/4 -> 1/16.
    py = levels[0][2, 3:5, 3:5, 0]  # +Y face centre texels (n ~ +Y)
    np.testing.assert_allclose(py, 4 / 3 + 0.25 * 0.25, rtol=0.01)


def test_prefilter_exr_faces_and_sh9_coefficients(tmp_path, pano):
    out = tmp_path / "pre.exr"
    assert main(["prefilter", str(pano), "--face-size", "16", "--samples", "16", "-o", str(out), "--quiet", "--no-error"]) == 0
    names = _files(tmp_path)
    assert sum(n.startswith("pre_m") for n in names) == 6 * 5  # the default chain: 16, 8, 4, 2, 1 (5 levels at least)
    img, meta = image.read_with_metadata(tmp_path / "pre_m0_px.exr")
    assert img.shape == (16, 16, 3)
    side = json.loads((tmp_path / "pre.exr.json").read_text())
    assert side["roughness_mapping"] == "linear" and side["num_levels"] == 5 and side["lod_blend"] == "mean_cosine"
    assert side["chain_floor"] == "1" and side["lookup"].startswith("lod = m + (c_m - c(r))")
    out2 = tmp_path / "irr.ktx2"
    assert main(["irradiance", str(pano), "--face-size", "16", "--size", "4", "--method", "sh9", "-o", str(out2), "--quiet"]) == 0
    coeffs = np.array(json.loads((tmp_path / "irr.ktx2.json").read_text())["sh9_radiance_coefficients"]["values"])
    assert coeffs.shape == (9, 3)


def test_lut_command_writes_exr_with_layout(tmp_path):
    out = tmp_path / "lut.exr"
    assert main(["lut", "--size", "16", "-o", str(out), "--quiet"]) == 0
    img, meta = image.read_with_metadata(out)
    assert img.shape == (16, 16, 3) and np.all(img[..., 2] == 0)
    from jaxpbr.shading.lut import lut_reference

    ref = lut_reference((np.arange(16) + 0.5) / 16, 0.5 / 16)  # row 0: r = 1/32
    np.testing.assert_allclose(img[0, :, :2], ref, atol=1e-4)
    side = json.loads((tmp_path / "lut.exr.json").read_text())
    assert side["error_vs_float64_reference"]["max"] < 1e-4


def test_ibl_all_in_one_procedural(tmp_path):
    assert main(["ibl", "procedural:sky", "--face-size", "16", "--samples", "16", "--lut-size", "8", "--out-dir", str(tmp_path), "--quiet", "--no-error"]) == 0
    assert {"irradiance.ktx2", "prefiltered.ktx2", "brdf_lut.exr", "ibl.json"} <= set(_files(tmp_path))
    levels, meta, info = read_ktx2(tmp_path / "prefiltered.ktx2")
    assert len(levels) == 5 and meta["jaxpbr:roughness_mapping"] == "linear" and meta["jaxpbr:mapping_levels"] == "5"
    # The lookup travels in the KTX2 key/values: blend, floor, level mean cosines, the engines' lod table.
    assert meta["jaxpbr:lod_blend"] == "mean_cosine" and meta["jaxpbr:chain_floor"] == "1"
    assert meta["jaxpbr:level_mean_cosine"].startswith("1,0.976") and meta["jaxpbr:level_mean_cosine"].endswith(",0.666666667")
    assert len(meta["jaxpbr:lod_table"].split(",")) == 33
    # rgba16f: the 3000-radiance sun is representable; values finite and non-negative
    assert all(np.isfinite(lv).all() and (lv >= 0).all() for lv in levels)
    # The Charlie cube (sheen) is baked by default, at the renderer's default size (64, or the
    # environment's face size if smaller) and the module's default levels.
    charlie, cmeta, _ = read_ktx2(tmp_path / "charlie.ktx2")
    assert len(charlie) == 5 and charlie[0].shape == (6, 16, 16, 4) and cmeta["jaxpbr:distribution"] == "charlie"
    assert all(np.isfinite(lv).all() and (lv >= 0).all() for lv in charlie)


@pytest.mark.parametrize("quiet", [True, False])
def test_ibl_compiles_progress_callbacks_only_when_progress_is_shown(tmp_path, monkeypatch, capsys, quiet):
    """A program holding a host callback is left out of JAX's persistent compilation cache: with
    --quiet no precompute reports progress, so a warm `jaxpbr ibl --quiet` reads its programs
    (face size 128: 7.99 s against 11.11 s warm). Without it the bars are drawn from the callbacks."""
    import jax

    jax.clear_caches()  # every program traced again: the callbacks are counted as they are traced
    calls = []
    real = jax.debug.callback
    monkeypatch.setattr(jax.debug, "callback", lambda *a, **k: calls.append(1) or real(*a, **k))
    if quiet:  # the whole bake
        argv = ["ibl", "procedural:sky", "--face-size", "16", "--samples", "16", "--lut-size", "8", "--no-sheen",
                "--out-dir", str(tmp_path), "--no-error", "--quiet"]
    else:  # one map (each program compiled with callbacks costs a compilation at every run)
        argv = ["irradiance", "procedural:sky", "--face-size", "16", "--size", "4", "--no-error", "-o", str(tmp_path / "i.ktx2")]
    assert main(argv) == 0
    err = capsys.readouterr().err
    if quiet:
        assert calls == [] and err == ""
    else:
        assert calls and "irradiance" in err


_SIDECAR_CHARLIE_KEYS = {"files", "face_size", "num_levels", "level_roughness", "level_alpha", "level_mean_cosine", "lod_blend",
                         "lod_formula", "lod_table", "lod_table_abscissa", "distribution", "min_roughness", "source_face_size",
                         "environment_face_size", "seconds", "lookup", "conventions", "versions"}


def test_ibl_bakes_the_charlie_cube_and_the_sheen_channel_of_the_lut(tmp_path):
    """One bake: GGX and Charlie cubes, a 3-channel LUT (R, G = the GGX split sum, B = the shipped
    sheen albedo table), and an ibl.json recording all of it and how an engine looks it up."""
    from jaxpbr.ibl.cubeio import load_environment
    from jaxpbr.ibl.sheen_prefilter import prefilter_charlie
    from jaxpbr.shading.shipped_luts import brdf_lut, sheen_lut, shipped_manifest

    argv = ["ibl", "procedural:sky", "--face-size", "16", "--samples", "16", "--lut-size", "128", "--charlie-size", "8",
            "--charlie-levels", "3", "--ktx-format", "rgba32f", "--out-dir", str(tmp_path), "--quiet", "--no-error"]
    assert main(argv) == 0
    assert {"irradiance.ktx2", "prefiltered.ktx2", "charlie.ktx2", "charlie.ktx2.json", "brdf_lut.exr", "ibl.json"} <= set(_files(tmp_path))

    # The Charlie cube read back is prefilter_charlie of the same environment (float32 file).
    levels, meta, info = read_ktx2(tmp_path / "charlie.ktx2")
    expect = prefilter_charlie(load_environment(["procedural:sky"], face_size=16), size=8, num_levels=3)
    assert info["face_count"] == 6 and len(levels) == 3
    for got, want in zip(levels, expect.levels):
        np.testing.assert_allclose(got[..., :3], np.asarray(want), rtol=1e-6, atol=0)
    for k in ("distribution", "lod_blend", "lod_table", "level_roughness", "min_roughness", "source_face_size"):
        assert meta[f"jaxpbr:{k}"] == expect.metadata[k]

    # LUT: R, G = the GGX split sum, B = the sheen albedo table, same layout.
    img, hdr = image.read_with_metadata(tmp_path / "brdf_lut.exr")
    assert img.shape == (128, 128, 3)
    np.testing.assert_allclose(img[..., :2], np.asarray(brdf_lut(size=128)), atol=1e-6)
    np.testing.assert_array_equal(img[..., 2], np.asarray(sheen_lut()))
    assert "B = E_sheen" in hdr["jaxpbr:channels"]

    index = json.loads((tmp_path / "ibl.json").read_text())
    assert index["sheen"] is True
    ch = index["charlie"]
    assert _SIDECAR_CHARLIE_KEYS <= set(ch), _SIDECAR_CHARLIE_KEYS - set(ch)
    assert ch["kind"] == "prefiltered_charlie" and ch["distribution"] == "charlie" and ch["files"] == [str(tmp_path / "charlie.ktx2")]
    assert (ch["face_size"], ch["num_levels"], ch["level_roughness"], ch["min_roughness"], ch["source_face_size"]) == (8, 3, "0,0.5,1", "0.045", "16")
    assert ch == json.loads((tmp_path / "charlie.ktx2.json").read_text())
    lut = index["brdf_lut"]
    assert lut["channels"] == {"R": "A (GGX split sum, F0 weight)", "G": "B (F90 weight)", "B": "E_sheen: Charlie sheen albedo / sheen IBL weight"}
    shipped = next(e for e in shipped_manifest()["sheen_luts"] if e["size"] == [128, 128])
    assert lut["sheen_albedo"]["source"] == "shipped" and lut["sheen_albedo"]["shipped_file"] == f"jaxpbr/_luts/{shipped['file']}"
    assert lut["sheen_albedo"]["max_abs_error"] == shipped["max_abs_error"]
    assert set(index["lookup"]) >= {"irradiance", "prefiltered", "charlie", "brdf_lut"}
    assert "lod_formula" in index["lookup"]["charlie"] and "NoV" in index["lookup"]["brdf_lut"]


def test_ibl_no_sheen_writes_no_charlie_cube_and_a_zero_b_channel(tmp_path, capsys):
    argv = ["ibl", "procedural:sky", "--face-size", "16", "--samples", "16", "--lut-size", "8", "--out-dir", str(tmp_path), "--quiet", "--no-error"]
    _bad(argv + ["--no-sheen", "--charlie-size", "8"], tmp_path, capsys, "--no-sheen")
    _bad(argv + ["--charlie-size", "8", "--charlie-levels", "5"], tmp_path, capsys, "--charlie-levels 5")
    assert main(argv + ["--no-sheen"]) == 0
    assert not any(n.startswith("charlie") for n in _files(tmp_path))
    img = image.read(tmp_path / "brdf_lut.exr")
    assert img.shape == (8, 8, 3) and np.all(img[..., 2] == 0) and np.all(img[..., 0] > 0)
    index = json.loads((tmp_path / "ibl.json").read_text())
    assert index["sheen"] is False and "charlie" not in index and "charlie" not in index["lookup"]
    assert index["brdf_lut"]["channels"]["B"] == "0 (unused)" and "sheen_albedo" not in index["brdf_lut"]


def test_ibl_failure_while_writing_the_charlie_cube_restores_the_folder(tmp_path, capsys, monkeypatch):
    """The disk fills up while charlie.ktx2 is being written (after the irradiance and GGX cubes
    are in place, and a partial charlie.ktx2 landed): no new file is left, and the previous
    set's files, charlie.ktx2 included, are back byte for byte."""
    from jaxpbr.ibl import cubeio

    old = {"irradiance.ktx2": b"old irr", "prefiltered.ktx2": b"old pre", "charlie.ktx2": b"old charlie",
           "charlie.ktx2.json": b"{}", "brdf_lut.exr": b"old lut", "ibl.json": b"{}"}
    for name, data in old.items():
        (tmp_path / name).write_bytes(data)
    real, calls = cubeio.write_ktx2, []

    def flaky(path, levels, **kw):
        calls.append(path.name)
        if path.name == "charlie.ktx2":  # a partial file renamed into place, then the failure
            part = path.with_name("partial.tmp")
            part.write_bytes(b"half a cube")
            os.replace(part, path)
            raise OSError("No space left on device")
        real(path, levels, **kw)

    monkeypatch.setattr(cubeio, "write_ktx2", flaky)
    argv = ["ibl", "procedural:sky", "--face-size", "16", "--samples", "16", "--lut-size", "8", "--charlie-size", "8",
            "--charlie-levels", "2", "--out-dir", str(tmp_path), "--quiet", "--no-error"]
    _bad(argv, tmp_path, capsys, "No space left")
    assert calls == ["irradiance.ktx2", "prefiltered.ktx2", "charlie.ktx2"]
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == old


def _bad(argv, tmp_path, capsys, match):
    before = _files(tmp_path)
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0
    assert len(err) == 1 and err[0].startswith("jaxpbr: error:") and match in err[0], err
    assert _files(tmp_path) == before  # nothing written, nothing half-written


def test_missing_file(tmp_path, capsys):
    _bad(["irradiance", str(tmp_path / "nope.hdr"), "-o", str(tmp_path / "o.ktx2")], tmp_path, capsys, "does not exist")


def test_unreadable_file(tmp_path, capsys):
    p = tmp_path / "garbage.exr"
    p.write_bytes(b"not an exr at all")
    _bad(["prefilter", str(p), "-o", str(tmp_path / "o.ktx2")], tmp_path, capsys, "cannot read")


def test_wrong_aspect(tmp_path, capsys):
    p = tmp_path / "wide.exr"
    image.write(p, np.ones((10, 30, 3), np.float32))
    _bad(["irradiance", str(p), "-o", str(tmp_path / "o.ktx2")], tmp_path, capsys, "twice as wide")


def test_nan_pixels(tmp_path, capsys):
    a = np.ones((8, 16, 3), np.float32)
    a[2, 3, 1] = np.nan
    p = tmp_path / "nan.exr"
    _raw_exr(p, a)
    _bad(["irradiance", str(p), "-o", str(tmp_path / "o.ktx2")], tmp_path, capsys, "NaN/Inf")


def test_negative_pixels_rejected_unless_clamped(tmp_path, capsys):
    a = np.ones((8, 16, 3), np.float32)
    a[1, 1, 0] = -0.5
    p = tmp_path / "neg.exr"
    _raw_exr(p, a)
    _bad(["irradiance", str(p), "-o", str(tmp_path / "o.ktx2")], tmp_path, capsys, "--clamp-negative")
    assert main(["irradiance", str(p), "--clamp-negative", "--size", "4", "-o", str(tmp_path / "o.ktx2"), "--quiet", "--no-error"]) == 0
    assert "clamped 1 negative" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["--size", "0"], ["--size", "-3"], ["--samples", "0"], ["--face-size", "0"]])
def test_nonpositive_sizes_and_samples(tmp_path, capsys, argv):
    with pytest.raises(SystemExit) as e:
        main(["prefilter", "procedural:sky", "-o", str(tmp_path / "o.ktx2")] + argv)
    assert e.value.code != 0
    assert "positive integer" in capsys.readouterr().err
    assert _files(tmp_path) == []


def test_output_directory_missing_or_not_a_directory(tmp_path, capsys, pano):
    _bad(["irradiance", str(pano), "-o", str(tmp_path / "no" / "o.ktx2")], tmp_path, capsys, "does not exist")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _bad(["lut", "--size", "4", "-o", str(blocker / "lut.exr")], tmp_path, capsys, "does not exist")
    _bad(["irradiance", str(pano), "-o", str(tmp_path / "o.png")], tmp_path, capsys, "must end in")


def test_failure_after_first_file_removes_everything(tmp_path, capsys, monkeypatch):
    """A failure while writing the sidecar (after the cube file exists) leaves no files."""
    import jaxpbr.cli.ibl as ci

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(ci, "write_json", boom)
    _bad(["irradiance", "procedural:sky", "--face-size", "16", "--size", "4", "-o", str(tmp_path / "o.ktx2"), "--no-error", "--quiet"], tmp_path, capsys, "disk full")


def test_six_face_input(tmp_path):
    rng = np.random.default_rng(0)
    faces = rng.uniform(0.5, 1.5, (6, 8, 8, 3)).astype(np.float32)
    paths = []
    for f in range(6):
        p = tmp_path / f"f{f}.exr"
        image.write(p, faces[f])
        paths.append(str(p))
    out = tmp_path / "irr.ktx2"
    assert main(["irradiance", *paths, "--size", "4", "-o", str(out), "--quiet", "--ktx-format", "rgba32f"]) == 0
    levels, _, _ = read_ktx2(out)
    from jaxpbr.ibl.diffuse import irradiance

    expect = np.asarray(irradiance(Cubemap(faces), size=4).levels[0])
    np.testing.assert_allclose(levels[0][..., :3], expect, rtol=1e-6)
    assert main(["irradiance", *paths[:5], "-o", str(out)]) != 0


def test_lut_smith_schlick_ggx_and_its_deprecated_alias(tmp_path, capsys):
    """--smith schlick_ggx is the LUT's Schlick-GGX (k = alpha/2); the old --smith schlick still
    works, with a one-line warning, and writes the current name into the metadata."""
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    assert main(["lut", "--size", "8", "--smith", "schlick_ggx", "-o", str(a), "--quiet", "--no-error"]) == 0
    assert "deprecated" not in capsys.readouterr().err
    assert main(["lut", "--size", "8", "--smith", "schlick", "-o", str(b), "--quiet", "--no-error"]) == 0
    assert "--smith schlick is deprecated; use --smith schlick_ggx" in capsys.readouterr().err
    np.testing.assert_array_equal(image.read(a), image.read(b))
    for p in (a, b):
        assert json.loads(p.with_name(p.name + ".json").read_text())["smith"] == "schlick_ggx"


def test_write_cubemap_failure_midway_leaves_no_faces(tmp_path, monkeypatch):
    """Per-face EXR output: if the 8th face fails (a full disk), the 7 already written are removed."""
    from jaxpbr.ibl import cubeio

    cube = Cubemap(np.ones((6, 4, 4, 3), np.float32)).with_mips(2)
    real_write, calls = cubeio.image.write, []

    def flaky(path, img, **kw):
        calls.append(path)
        if len(calls) == 8:
            raise OSError("No space left on device")
        real_write(path, img, **kw)

    monkeypatch.setattr(cubeio.image, "write", flaky)
    with pytest.raises(OSError, match="No space left"):
        cubeio.write_cubemap(tmp_path / "pre.exr", cube)
    assert len(calls) == 8 and _files(tmp_path) == []
    monkeypatch.setattr(cubeio.image, "write", real_write)
    names = cubeio.write_cubemap(tmp_path / "pre.exr", cube)
    assert len(names) == 12 and len(_files(tmp_path)) == 12
