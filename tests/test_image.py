"""Tests for jaxpbr.io.image: EXR / Radiance .hdr / PNG round trips, metadata, atomic writes, bad input."""

import jax

jax.config.update("jax_enable_x64", True)

import json  # noqa: E402
import os  # noqa: E402
import pathlib  # noqa: E402
import struct  # noqa: E402
import zlib  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import OpenEXR  # noqa: E402
import pytest  # noqa: E402

from jaxpbr.io import image  # noqa: E402

DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data"


def rand(shape, lo=0.0, hi=1.0, seed=0, dtype=np.float32):
    return np.random.default_rng(seed).uniform(lo, hi, shape).astype(dtype)


def listing(d):
    return sorted(p.name for p in pathlib.Path(d).iterdir())


# --------------------------------------------------------------------------------------------------------- EXR


@pytest.mark.parametrize("half", [False, True], ids=["float32", "half"])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_exr_round_trip(tmp_path, channels, half):
    img = rand((7, 5, channels), -3.0, 1000.0, seed=channels)
    path = tmp_path / "a.exr"
    image.write(path, img, half=half)
    back = image.read(path)
    assert back.dtype == np.float32 and back.shape == (7, 5, channels)
    expect = img.astype(np.float16).astype(np.float32) if half else img
    np.testing.assert_array_equal(back, expect)  # bit-exact: only the half conversion rounds
    # the file itself: channel names, pixel type and compression as documented
    with OpenEXR.File(str(path), separate_channels=True) as f:
        names = sorted(f.channels())
        dtypes = {ch.pixels.dtype for ch in f.channels().values()}
        compression = f.header()["compression"]
    assert names == sorted({1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}[channels])
    assert dtypes == {np.dtype(np.float16 if half else np.float32)}
    assert compression == OpenEXR.ZIP_COMPRESSION
    assert listing(tmp_path) == ["a.exr"]  # no temporary file left behind


def test_exr_strided_views_are_written_correctly(tmp_path):
    # the OpenEXR binding reads raw memory and ignores strides; write() must hand it contiguous data
    img = rand((6, 8, 4), seed=3)
    for name, view in {"flipped": img[::-1, ::-2], "rgb": img[..., :3], "grey": img[..., 1:2]}.items():
        image.write(tmp_path / f"{name}.exr", view)
        np.testing.assert_array_equal(image.read(tmp_path / f"{name}.exr"), view, err_msg=name)


def test_exr_accepts_2d_float64_and_jax_arrays(tmp_path):
    grey = rand((4, 6), dtype=np.float64)
    image.write(tmp_path / "g.exr", grey)
    np.testing.assert_array_equal(image.read(tmp_path / "g.exr"), grey.astype(np.float32)[..., None])
    rgb = jnp.asarray(rand((4, 6, 3), seed=1))
    image.write(str(tmp_path / "j.exr"), rgb)
    np.testing.assert_array_equal(image.read(str(tmp_path / "j.exr")), np.asarray(rgb))


def test_exr_metadata_round_trip(tmp_path):
    meta = {
        "jaxpbr:convention": "+Y up, camera looks down -Z",
        "unicode": "Ω ≈ 4π sr",
        "roughness": 0.1,  # not representable in float32: must come back exactly (stored as double)
        "tiny": 1e-300,
        "size": 128,
        "negative": -(2**31),
        "params": {"smith": "correlated", "sizes": [32, 64]},
        "levels": [0.0, 0.25, 1.0],
        "flag": True,
    }
    image.write(tmp_path / "m.exr", rand((2, 3, 3)), metadata=meta)
    img, back = image.read_with_metadata(tmp_path / "m.exr")
    assert img.shape == (2, 3, 3)
    for key in ("jaxpbr:convention", "unicode", "roughness", "tiny", "size", "negative"):
        assert back[key] == meta[key] and type(back[key]) is type(meta[key]), key
    assert json.loads(back["params"]) == meta["params"]
    assert json.loads(back["levels"]) == meta["levels"]
    assert json.loads(back["flag"]) is True
    # structural header attributes are not reported as metadata
    assert not {"channels", "compression", "dataWindow", "displayWindow", "lineOrder"} & set(back)


def test_exr_metadata_bad_values_raise_and_write_nothing(tmp_path):
    img = rand((2, 2, 3))
    for meta, match in [
        ({"big": 2**40}, "32-bit"),
        ({"channels": "x"}, "structural"),
        ({"obj": object()}, "cannot be stored"),
        ({"nan_in_list": [float("nan")]}, "cannot be stored"),
        ({"": "empty key"}, "non-empty"),
        ({3: "int key"}, "non-empty strings"),
        ({"oiio:ColorSpace": "x"}, "reserved"),
        (["not", "a", "dict"], "must be a dict"),
    ]:
        with pytest.raises(ValueError, match=match):
            image.write(tmp_path / "m.exr", img, metadata=meta)
    assert listing(tmp_path) == []


def test_exr_half_overflow_raises(tmp_path):
    ok = np.full((2, 2, 3), 65504.0, np.float32)  # the largest finite half is fine
    image.write(tmp_path / "ok.exr", ok, half=True)
    np.testing.assert_array_equal(image.read(tmp_path / "ok.exr"), ok)
    bad = ok.copy()
    bad[0, 0, 1] = 70000.0
    bad[1, 1, 2] = -1e5
    with pytest.raises(ValueError, match=r"2 pixels .* float16 \(half\) maximum 65504.*half=False"):
        image.write(tmp_path / "bad.exr", bad, half=True)
    image.write(tmp_path / "bad.exr", bad)  # float32 holds them
    np.testing.assert_array_equal(image.read(tmp_path / "bad.exr"), bad)
    with pytest.raises(ValueError, match="float32 maximum"):
        image.write(tmp_path / "huge.exr", np.full((1, 1, 3), 1e39))
    assert listing(tmp_path) == ["bad.exr", "ok.exr"]


def test_exr_other_channel_sets(tmp_path):
    z = rand((3, 4), seed=5)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Z": z}) as f:
        f.write(str(tmp_path / "z.exr"))
    np.testing.assert_array_equal(image.read(tmp_path / "z.exr"), z[..., None])

    layer = rand((3, 4, 3), seed=6)
    # (the OpenEXR binding ignores NumPy strides: hand it contiguous planes)
    chans = {f"diffuse.{c}": np.ascontiguousarray(layer[..., i]) for i, c in enumerate("RGB")}
    chans["depth.Z"] = z
    with OpenEXR.File(header, chans) as f:
        f.write(str(tmp_path / "layers.exr"))
    np.testing.assert_array_equal(image.read(tmp_path / "layers.exr"), layer)  # the one RGB layer
    np.testing.assert_array_equal(image.read(tmp_path / "layers.exr", channels=["depth.Z"]), z[..., None])

    with OpenEXR.File(header, {"Z": z, "N": z}) as f:
        f.write(str(tmp_path / "two.exr"))
    with pytest.raises(ValueError, match=r"channels are \['N', 'Z'\].*channels=\["):
        image.read(tmp_path / "two.exr")
    with pytest.raises(ValueError, match="no channel"):
        image.read(tmp_path / "two.exr", channels=["R"])


# ------------------------------------------------------------------------------------------------------ PNG


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_png_round_trip_code_values(tmp_path, bits, channels):
    top = 2**bits - 1
    rng = np.random.default_rng(bits + channels)
    codes = rng.integers(0, top + 1, (6, 9, channels))
    codes[0, 0] = 0
    codes[0, 1] = top
    if channels == 4:
        codes[1, :, 3] = 0  # fully transparent pixels keep their colour (no premultiplication)
    path = tmp_path / "a.png"
    image.write(path, codes / top, bits=bits, encoding="linear")
    back = image.read(path)
    assert back.dtype == np.float32 and back.shape == codes.shape
    np.testing.assert_array_equal(np.rint(back.astype(np.float64) * top), codes)
    np.testing.assert_array_equal(back, (codes / top).astype(np.float32))
    assert listing(tmp_path) == ["a.png"]


@pytest.mark.parametrize("bits", [8, 16])
def test_png_encodings_of_half_linear(tmp_path, bits):
    top = 2**bits - 1
    srgb_half = 1.055 * 0.5 ** (1 / 2.4) - 0.055  # IEC 61966-2-1 at linear 0.5 (= 0.7353569830524495)
    expect = {
        "srgb": round(top * srgb_half),  # 188 (8-bit), 48192 (16-bit)
        "gamma2.2": round(top * 0.5 ** (1 / 2.2)),  # 186, 47824
        "linear": round(top * 0.5),  # 0.5 * 255 = 127.5 rounds to the even 128
    }
    assert (expect["srgb"], expect["gamma2.2"]) == ((188, 186) if bits == 8 else (48192, 47824))
    rgba = np.full((2, 3, 4), 0.5)
    rgba[0, 0, :3] = [-0.5, 1.0, 7.0]  # clipped to [0, 1] after encoding
    for enc, code in expect.items():
        image.write(tmp_path / f"{enc}.png", rgba, bits=bits, encoding=enc)
        back = np.rint(image.read(tmp_path / f"{enc}.png").astype(np.float64) * top)
        assert np.all(back[..., :3].reshape(-1, 3)[1:] == code), enc
        np.testing.assert_array_equal(back[0, 0, :3], [0, top, top])
        np.testing.assert_array_equal(back[..., 3], round(top * 0.5))  # alpha is never transfer-encoded
    # the files are tagged accordingly: sRGB chunk, or gAMA = 1/2.2 (stored as 45455)
    assert b"sRGB" in (tmp_path / "srgb.png").read_bytes()[:200]
    gamma_png = (tmp_path / "gamma2.2.png").read_bytes()[:200]
    assert b"sRGB" not in gamma_png and b"gAMA" + (45455).to_bytes(4, "big") in gamma_png


def test_png_metadata_round_trip(tmp_path):
    meta = {"Software": "jaxpbr", "note": "Ω ≈ 4π sr", "size": 64, "ev": 0.1, "params": {"a": [1, 2]}}
    image.write(tmp_path / "m.png", rand((2, 2, 3)), metadata=meta)
    _, back = image.read_with_metadata(tmp_path / "m.png")
    assert back["Software"] == "jaxpbr" and back["note"] == "Ω ≈ 4π sr"
    # PNG text chunks hold strings only: numbers come back as their repr
    assert back["size"] == "64" and float(back["ev"]) == 0.1
    assert json.loads(back["params"]) == {"a": [1, 2]}
    assert not any(k.lower().startswith("oiio:") for k in back)


def test_png_bad_options(tmp_path):
    img = rand((2, 2, 3))
    with pytest.raises(ValueError, match="bits must be 8 or 16"):
        image.write(tmp_path / "a.png", img, bits=12)
    with pytest.raises(ValueError, match="'srgb', 'gamma2.2', 'linear'"):
        image.write(tmp_path / "a.png", img, encoding="rec709")
    with pytest.raises(ValueError, match="half=True only applies to .exr"):
        image.write(tmp_path / "a.png", img, half=True)
    with pytest.raises(ValueError, match="divide 8-bit code values by 255"):
        image.write(tmp_path / "a.png", (img * 255).astype(np.uint8))
    assert listing(tmp_path) == []


# -------------------------------------------------------------------------------------------------- Radiance


def test_hdr_round_trip(tmp_path):
    # RGBE stores one shared 8-bit exponent e per pixel (2**(e-1) <= max channel < 2**e) and an 8-bit mantissa
    # per channel, truncated: every channel is stored to within 2**e / 256 <= (max channel) / 128 -- relative to
    # the pixel's brightest channel, i.e. ~0.8 % of it, and far worse relative to a dim channel beside a bright one.
    img = rand((8, 16, 3), 0.0, 1.0, seed=7) * np.float32(10.0) ** rand((8, 16, 1), -3, 3, seed=8)
    img[0, 0] = [1.0, 0.5, 0.25]  # mantissa * 2**k values are stored exactly
    img[0, 1] = 0.0
    path = tmp_path / "a.hdr"
    image.write(path, img)
    back = image.read(path)
    assert back.dtype == np.float32 and back.shape == img.shape
    bound = img.max(axis=-1, keepdims=True) / 128.0
    assert np.all(np.abs(back - img) <= bound)
    np.testing.assert_array_equal(back[0, :2], img[0, :2])
    assert listing(tmp_path) == ["a.hdr"]


def test_hdr_rejects_what_rgbe_cannot_store(tmp_path):
    with pytest.raises(ValueError, match="negative"):
        image.write(tmp_path / "n.hdr", -rand((2, 2, 3)))
    with pytest.raises(ValueError, match="RGB only"):
        image.write(tmp_path / "a.hdr", rand((2, 2, 4)))
    with pytest.warns(UserWarning, match="cannot store metadata"):
        image.write(tmp_path / "m.hdr", rand((2, 2, 3)), metadata={"a": "b"})
    assert image.read_with_metadata(tmp_path / "m.hdr")[1] == {}
    assert listing(tmp_path) == ["m.hdr"]


def test_real_hdr_environment():
    path = DATA / "spruit_sunrise_1k.hdr"
    if not path.exists():
        pytest.skip(f"{path} not available")
    img = image.read(path)
    assert img.shape == (512, 1024, 3) and img.dtype == np.float32
    assert np.all(np.isfinite(img)) and img.min() >= 0.0
    assert img.max() == pytest.approx(828.0, rel=0.01)


# ---------------------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("ext", [".exr", ".hdr", ".png"])
def test_nan_and_inf_raise_and_leave_nothing(tmp_path, ext):
    img = rand((4, 5, 3))
    img[1, 2, 0] = np.nan
    img[3, 3, 1] = np.inf
    img[3, 3, 2] = -np.inf  # same pixel: 2 bad pixels in all
    with pytest.raises(ValueError, match=r"2 of 20 pixels .*\(1 NaN and 2 Inf values\)"):
        image.write(tmp_path / f"x{ext}", img)
    assert listing(tmp_path) == []


def test_failed_write_keeps_previous_file_and_removes_temp(tmp_path, monkeypatch):
    path = tmp_path / "x.exr"
    old = rand((2, 2, 3), seed=1)
    image.write(path, old)
    before = path.read_bytes()

    def broken(tmp, channels, header):
        pathlib.Path(tmp).write_bytes(b"half a file")
        raise OSError("disk full")

    monkeypatch.setattr(image, "_write_exr", broken)
    with pytest.raises(OSError, match="disk full"):
        image.write(path, rand((2, 2, 3), seed=2))
    assert listing(tmp_path) == ["x.exr"] and path.read_bytes() == before
    monkeypatch.undo()
    image.write(path, rand((2, 2, 3), seed=3))  # a successful write replaces the file
    np.testing.assert_array_equal(image.read(path), rand((2, 2, 3), seed=3))
    assert listing(tmp_path) == ["x.exr"]


def test_missing_file(tmp_path):
    for ext in (".exr", ".hdr", ".png"):
        with pytest.raises(FileNotFoundError, match="does not exist"):
            image.read(tmp_path / f"nope{ext}")
        with pytest.raises(FileNotFoundError, match="does not exist"):
            image.read_with_metadata(tmp_path / f"nope{ext}")


@pytest.mark.parametrize("ext", [".exr", ".hdr", ".png"])
def test_corrupt_file(tmp_path, ext):
    garbage = tmp_path / f"x{ext}"
    garbage.write_bytes(b"this is not an image \x00\x01\x02" * 8)
    with pytest.raises(ValueError, match=f"x{ext}"):
        image.read(garbage)
    # a good file cut in half
    good = tmp_path / f"good{ext}"
    image.write(good, rand((32, 32, 3), seed=9))
    cut = tmp_path / f"cut{ext}"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ValueError, match=f"cut{ext}.*corrupt or truncated"):
        image.read(cut)



def _png(raw_rows: bytes, width: int, height: int, *, chunk_crc_ok=True, kind=b"IDAT") -> bytes:
    """A minimal 8-bit RGB PNG written here with struct and zlib (PNG specification 5.3, 11.2.2)."""

    def chunk(k, body, ok=True):
        crc = zlib.crc32(k + body) ^ (0 if ok else 1)
        return struct.pack(">I", len(body)) + k + body + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(kind, zlib.compress(raw_rows), chunk_crc_ok)
        + chunk(b"IEND", b"")
    )


def test_png_written_by_hand_reads_back(tmp_path):
    codes = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3) * 13
    rows = b"".join(b"\x00" + codes[y].tobytes() for y in range(2))  # filter type 0 (None) on each row
    (tmp_path / "hand.png").write_bytes(_png(rows, 3, 2))
    np.testing.assert_array_equal(image.read(tmp_path / "hand.png"), codes / np.float32(255.0))
    assert image.dimensions(tmp_path / "hand.png") == (2, 3, 3)


def _broken_files(tmp_path):
    """Corrupt and truncated files of each format, among them those the decoders used to print about."""
    files = {}
    for ext in (".exr", ".hdr", ".png"):
        good = tmp_path / f"good{ext}"
        image.write(good, rand((32, 32, 3), seed=9))
        data = good.read_bytes()
        for frac in (0.3, 0.5, 0.9):
            files[f"cut{int(frac * 100)}{ext}"] = data[: int(len(data) * frac)]
        flipped = bytearray(data)
        flipped[len(data) // 2] ^= 0xFF
        files[f"flipped{ext}"] = bytes(flipped)
    rows = b"".join(b"\x00" + bytes(9) for _ in range(4))
    files["short_data.png"] = _png(rows[:-5], 3, 4)  # the zlib stream holds too few rows
    files["bad_filter.png"] = _png(rows.replace(b"\x00", b"\x07", 1), 3, 4)  # filter types are 0..4
    files["bad_crc.png"] = _png(rows, 3, 4, chunk_crc_ok=False)
    files["bad_type.png"] = _png(rows, 3, 4, kind=b"ID\x01T")
    return files


def test_broken_files_print_nothing_and_leave_descriptors_alone(tmp_path, capfd, monkeypatch):
    # The libraries print for broken files (the OpenEXR binding on stdout, libOpenEXR and libpng on
    # stderr). capfd sees the process's file descriptors 1 and 2, so C-level output is caught too;
    # silencing by swapping descriptors would call os.dup2, which raises here.
    files = _broken_files(tmp_path)
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    capfd.readouterr()

    def no_dup2(*args):
        raise AssertionError("os.dup2 called while reading an image")

    failed = []
    with monkeypatch.context() as m:
        m.setattr(os, "dup2", no_dup2)
        for name in files:
            for fn in (image.read, image.read_with_metadata):
                try:
                    fn(tmp_path / name)
                except ValueError as e:
                    assert name in str(e)
                    failed.append(name)
            image.dimensions(tmp_path / name)
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    assert len(failed) >= 2 * (len(files) - 3)  # a flipped byte may fall where a decoder does not look
    for name in ("short_data.png", "bad_filter.png", "bad_crc.png", "bad_type.png", "cut50.exr", "cut50.png"):
        with pytest.raises(ValueError, match="corrupt or truncated"):
            image.read(tmp_path / name)


def test_unsupported_extension(tmp_path):
    (tmp_path / "x.jpg").write_bytes(b"\xff\xd8")
    with pytest.raises(ValueError, match=r"'\.jpg'.*supported: \.exr, \.hdr, \.png"):
        image.read(tmp_path / "x.jpg")
    with pytest.raises(ValueError, match=r"'\.tiff'.*supported: \.exr, \.hdr, \.png"):
        image.write(tmp_path / "x.tiff", rand((2, 2, 3)))
    with pytest.raises(ValueError, match="supported"):
        image.write(tmp_path / "noext", rand((2, 2, 3)))
    assert listing(tmp_path) == ["x.jpg"]


@pytest.mark.parametrize(
    "shape", [(4,), (2, 2, 2), (2, 2, 5), (1, 2, 2, 3), (0, 3, 3), (2, 0)], ids=lambda s: "x".join(map(str, s))
)
def test_bad_shapes(tmp_path, shape):
    with pytest.raises(ValueError, match=r"shape|channels|empty"):
        image.write(tmp_path / "x.exr", np.zeros(shape, np.float32))
    assert listing(tmp_path) == []


def test_bad_dtypes(tmp_path):
    with pytest.raises(ValueError, match="real float or integer"):
        image.write(tmp_path / "x.exr", np.zeros((2, 2, 3), complex))
    with pytest.raises(ValueError, match="real float or integer"):
        image.write(tmp_path / "x.exr", np.zeros((2, 2, 3), bool))


def test_output_directory_missing_or_not_a_directory(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nodir.*does not exist"):
        image.write(tmp_path / "nodir" / "x.exr", rand((2, 2, 3)))
    (tmp_path / "file").write_text("")
    with pytest.raises(NotADirectoryError, match="file.*is not a directory"):
        image.write(tmp_path / "file" / "x.png", rand((2, 2, 3)))
    (tmp_path / "d.exr").mkdir()
    with pytest.raises(IsADirectoryError, match="existing directory"):
        image.write(tmp_path / "d.exr", rand((2, 2, 3)))


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root ignores directory permissions")
def test_unwritable_directory(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(PermissionError, match=r"ro.*not writable"):
            image.write(ro / "x.exr", rand((2, 2, 3)))
        assert listing(ro) == []
    finally:
        ro.chmod(0o700)


def test_written_file_gets_normal_permissions(tmp_path):
    # the temporary file is created like any new file (mode 0o666 minus the umask), not 0o600 like mkstemp's
    image.write(tmp_path / "p.png", rand((2, 2, 3)))
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "p.png").stat().st_mode & 0o777 == 0o666 & ~umask


def test_unwritable_directory_message(tmp_path, monkeypatch):
    # Runs even as root (which ignores permissions): the OS refusing the temporary file becomes a
    # PermissionError that names the destination and its directory.
    def refuse(path, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(image.os, "open", refuse)
    with pytest.raises(PermissionError, match=r"cannot write .*x\.hdr.*directory .* is not writable"):
        image.write(tmp_path / "x.hdr", rand((2, 2, 3)))
    monkeypatch.undo()
    assert listing(tmp_path) == []
