"""Tests for jaxpbr.io.ktx2: byte layout checked against the KTX 2.0 / Khronos Data Format specs, round trips, bad input.

The byte-level oracles below are written from the specification text (ktxspec.adoc "File Structure", "Index",
"Level Index", "Data Format Descriptor", "Key/Value Data", "Mip Level Array", "mipPadding"; KDF 1.4 "Khronos
Basic Data Format Descriptor Block"), with struct offsets spelled out here, not taken from jaxpbr.io.ktx2.
"""

import os
import pathlib
import struct

import numpy as np
import pytest

import jaxpbr
from jaxpbr.io import ktx2
from jaxpbr.io.ktx2 import read_ktx2, write_ktx2

# "identifier": '«', 'K', 'T', 'X', ' ', '2', '0', '»', '\r', '\n', '\x1A', '\n'
SPEC_IDENTIFIER = b"\xabKTX 20\xbb\r\n\x1a\n"
# Vulkan VkFormat enum values and per-component byte size (typeSize) of the formats under test.
VK = {"rgba16f": (97, 2, 4), "rgba32f": (109, 4, 4), "rg16f": (83, 2, 2), "rg32f": (103, 4, 2)}
NP_DTYPE = {2: "<f2", 4: "<f4"}


def rand(shape, lo=-2.0, hi=50.0, seed=0):
    return np.random.default_rng(seed).uniform(lo, hi, shape).astype(np.float32)


def cube_chain(size=16, channels=4, seed=0):
    """Full mip chain of a cubemap, (6, S, S, C) per level, S = size, size/2, ..., 1."""
    sizes = []
    s = size
    while True:
        sizes.append(s)
        if s == 1:
            break
        s //= 2
    return [rand((6, s, s, channels), seed=seed + m) for m, s in enumerate(sizes)]


def listing(d):
    return sorted(p.name for p in pathlib.Path(d).iterdir())


def parse(buf: bytes) -> dict:
    """Independent KTX2 parse from the spec's field offsets (no code from jaxpbr.io.ktx2)."""
    f = {}
    f["identifier"] = buf[:12]
    (f["vkFormat"], f["typeSize"], f["pixelWidth"], f["pixelHeight"], f["pixelDepth"], f["layerCount"],
     f["faceCount"], f["levelCount"], f["supercompressionScheme"]) = struct.unpack_from("<9I", buf, 12)
    f["dfdByteOffset"], f["dfdByteLength"], f["kvdByteOffset"], f["kvdByteLength"] = struct.unpack_from("<4I", buf, 48)
    f["sgdByteOffset"], f["sgdByteLength"] = struct.unpack_from("<2Q", buf, 64)
    f["levels"] = [struct.unpack_from("<3Q", buf, 80 + 24 * p) for p in range(max(1, f["levelCount"]))]
    return f


def kv_entries(buf: bytes, f: dict) -> list[tuple[int, int, bytes]]:
    """(file offset of keyAndValueByteLength, keyAndValueByteLength, keyAndValue bytes) for each pair."""
    out, pos, end = [], f["kvdByteOffset"], f["kvdByteOffset"] + f["kvdByteLength"]
    while pos < end:
        (n,) = struct.unpack_from("<I", buf, pos)
        out.append((pos, n, buf[pos + 4:pos + 4 + n]))
        pos += 4 + n + (-n % 4)
    assert pos == end, "pairs + valuePadding must add up to kvdByteLength"
    return out


def written(tmp_path, levels, fmt, name="t.ktx2", **kw):
    path = tmp_path / name
    write_ktx2(path, levels, fmt=fmt, **kw)
    return path, path.read_bytes()


# ------------------------------------------------------------------------------------------- header and index


@pytest.mark.parametrize("fmt", ["rgba16f", "rgba32f"])
def test_cubemap_header_fields_at_spec_offsets(tmp_path, fmt):
    levels = cube_chain(16)
    _, buf = written(tmp_path, levels, fmt)
    vk, type_size, _ = VK[fmt]
    assert buf[:12] == SPEC_IDENTIFIER
    f = parse(buf)
    assert (f["vkFormat"], f["typeSize"]) == (vk, type_size)
    assert (f["pixelWidth"], f["pixelHeight"], f["pixelDepth"], f["layerCount"]) == (16, 16, 0, 0)
    assert (f["faceCount"], f["levelCount"], f["supercompressionScheme"]) == (6, 5, 0)
    # Index: the DFD follows the level index directly; KTX requires dfdTotalSize == kvdByteOffset - dfdByteOffset.
    assert f["dfdByteOffset"] == 80 + 24 * 5
    assert struct.unpack_from("<I", buf, f["dfdByteOffset"])[0] == f["dfdByteLength"] == 4 + 24 + 16 * 4
    assert f["kvdByteOffset"] - f["dfdByteOffset"] == f["dfdByteLength"]
    assert (f["sgdByteOffset"], f["sgdByteLength"]) == (0, 0)


@pytest.mark.parametrize("fmt", ["rgba16f", "rgba32f"])
def test_level_index_smallest_first_aligned_and_sized(tmp_path, fmt):
    levels = cube_chain(16)
    _, buf = written(tmp_path, levels, fmt, metadata={"k": "abc"})  # 3-char value: forces valuePadding
    _, type_size, _ = VK[fmt]
    texel = 4 * type_size
    align = np.lcm(texel, 4)  # "mipPadding": lcm(texel_block_size, 4)
    f = parse(buf)
    offs = [e[0] for e in f["levels"]]
    lens = [e[1] for e in f["levels"]]
    for p, (off, length, ulength) in enumerate(f["levels"]):
        s = 16 >> p
        assert length == ulength == 6 * s * s * 4 * type_size
        assert off % align == 0
    # Mip Level Array stores the smallest level first: byteOffsets increase from the last level to the first,
    # each level ends before the next larger one starts, the first stored level follows the key/value data,
    # and level 0 ends the file.
    assert all(offs[p] < offs[p - 1] for p in range(1, 5))
    assert all(offs[p] + lens[p] <= offs[p - 1] for p in range(1, 5))
    kvd_end = f["kvdByteOffset"] + f["kvdByteLength"]
    assert kvd_end <= offs[4] < kvd_end + align
    assert set(buf[kvd_end:offs[4]]) <= {0}  # mipPadding is zeros
    assert offs[0] + lens[0] == len(buf)


@pytest.mark.parametrize("value_len", [0, 1, 2, 3, 4, 5, 6, 7])
def test_rgba32f_levels_16_byte_aligned_whatever_the_metadata_length(tmp_path, value_len):
    _, buf = written(tmp_path, cube_chain(4), "rgba32f", metadata={"note": "x" * value_len})
    f = parse(buf)
    assert all(off % 16 == 0 for off, _, _ in f["levels"])  # lcm(16, 4)


def test_2d_rg_texture_header_and_layout(tmp_path):
    # Non-square 2D, H=8 rows x W=4 columns: pixelWidth is the column count.
    levels = [rand((8, 4, 2), 0, 1, seed=1), rand((4, 2, 2), 0, 1, seed=2), rand((2, 1, 2), 0, 1, seed=3),
              rand((1, 1, 2), 0, 1, seed=4)]
    for fmt in ("rg16f", "rg32f"):
        _, buf = written(tmp_path, levels, fmt, name=f"{fmt}.ktx2")
        vk, type_size, _ = VK[fmt]
        f = parse(buf)
        assert (f["vkFormat"], f["typeSize"], f["pixelWidth"], f["pixelHeight"]) == (vk, type_size, 4, 8)
        assert (f["pixelDepth"], f["layerCount"], f["faceCount"], f["levelCount"]) == (0, 0, 1, 4)
        assert f["dfdByteLength"] == 4 + 24 + 16 * 2
        for p, (off, length, _) in enumerate(f["levels"]):
            h, w = levels[p].shape[:2]
            assert length == h * w * 2 * type_size
            assert off % np.lcm(2 * type_size, 4) == 0
            stored = np.frombuffer(buf, NP_DTYPE[type_size], count=h * w * 2, offset=off).reshape(h, w, 2)
            np.testing.assert_array_equal(stored, levels[p].astype(NP_DTYPE[type_size]))


# -------------------------------------------------------------------------------------- data format descriptor


def test_dfd_words_match_spec_for_rgba16f_and_rg32f(tmp_path):
    # Khronos Basic DFD: word0 vendorId(17) | descriptorType(15); word1 versionNumber(16) | blockSize(16);
    # word2 colorModel | primaries<<8 | transfer<<16 | flags<<24; word3 texelBlockDimension0..3 (size-1);
    # word4/5 bytesPlane0..7; per sample: bitOffset | (bitLength-1)<<16 | (qualifiers|channel)<<24, samplePosition,
    # sampleLower, sampleUpper. Float samples: qualifiers F|S = 0xC0, lower/upper = -1.0f/1.0f as float bits.
    RGBSDA, BT709, UNSPECIFIED, LINEAR = 1, 1, 0, 1
    cases = {
        "rgba16f": (16, 8, BT709, (0, 1, 2, 15)),
        "rg32f": (32, 8, UNSPECIFIED, (0, 1)),
    }
    for fmt, (bits, bytes_plane0, primaries, channels) in cases.items():
        levels = [rand((4, 4, len(channels)))]
        _, buf = written(tmp_path, levels, fmt, name=f"{fmt}.ktx2")
        f = parse(buf)
        n = f["dfdByteLength"] // 4
        words = struct.unpack_from(f"<{n}I", buf, f["dfdByteOffset"])
        expected = [4 + 24 + 16 * len(channels), 0, 2 | ((24 + 16 * len(channels)) << 16),
                    RGBSDA | primaries << 8 | LINEAR << 16, 0, bytes_plane0, 0]
        for k, ch in enumerate(channels):
            expected += [k * bits | (bits - 1) << 16 | (0xC0 | ch) << 24, 0, 0xBF800000, 0x3F800000]
        assert list(words) == expected, fmt
        assert struct.unpack("<f", struct.pack("<I", 0xBF800000))[0] == -1.0


# ------------------------------------------------------------------------------------------------ key/value data


def test_key_value_data_sorted_terminated_padded(tmp_path):
    md = {"zeta": "last", "jaxpbr:kind": "prefiltered specular", "Alpha": "upper case sorts first", "é": "utf8"}
    _, buf = written(tmp_path, [rand((2, 2, 4))], "rgba16f", metadata=md)
    f = parse(buf)
    entries = kv_entries(buf, f)
    pairs = {}
    keys = []
    for pos, n, kv in entries:
        assert pos % 4 == 0  # every keyAndValueByteLength is 4-byte aligned
        key, _, value = kv.partition(b"\x00")
        assert value.endswith(b"\x00") and b"\x00" not in value[:-1]  # NUL-terminated UTF-8 string
        pad = buf[pos + 4 + n:pos + 4 + n + (-n % 4)]
        assert set(pad) <= {0}
        keys.append(key.decode("utf-8"))
        pairs[keys[-1]] = value[:-1].decode("utf-8")
    assert keys == sorted(keys, key=lambda k: [ord(c) for c in k])  # by Unicode code point
    assert pairs["KTXwriter"] == f"jaxpbr {jaxpbr.__version__}"
    assert pairs["KTXorientation"] == "rd"
    for k, v in md.items():
        assert pairs[k] == v
    assert len(pairs) == len(md) + 2


def test_spec_example_ktxorientation_entry_bytes(tmp_path):
    # The spec's example file spells out this exact entry: length 18, "KTXorientation\0rd\0", 2 padding bytes.
    _, buf = written(tmp_path, [rand((6, 2, 2, 4))], "rgba16f")
    f = parse(buf)
    entry = [e for e in kv_entries(buf, f) if e[2].startswith(b"KTXorientation\x00")]
    assert len(entry) == 1
    pos = entry[0][0]
    assert buf[pos:pos + 24] == b"\x12\x00\x00\x00KTXorientation\x00rd\x00\x00\x00"


# --------------------------------------------------------------------------------------- texel data and layout


def test_cube_face_row_column_order_in_file(tmp_path):
    # R encodes (f, i, j); per the KTX layout level data is face-major, then rows, then texels in a row.
    S = 4
    f_, i_, j_ = np.meshgrid(np.arange(6), np.arange(S), np.arange(S), indexing="ij")
    level = np.zeros((6, S, S, 4), np.float32)
    level[..., 0] = 10000 * f_ + 100 * i_ + j_
    level[..., 3] = 0.5
    _, buf = written(tmp_path, [level], "rgba32f")
    off = parse(buf)["levels"][0][0]
    for f, i, j in [(0, 0, 0), (0, 0, 1), (0, 1, 0), (1, 0, 0), (5, 3, 2), (3, 2, 3)]:
        texel = struct.unpack_from("<4f", buf, off + 16 * ((f * S + i) * S + j))
        assert texel == (10000 * f + 100 * i + j, 0.0, 0.0, 0.5)


@pytest.mark.parametrize("fmt", ["rgba16f", "rgba32f"])
def test_cube_levels_decoded_by_hand_equal_input(tmp_path, fmt):
    levels = cube_chain(16)
    _, buf = written(tmp_path, levels, fmt)
    _, type_size, _ = VK[fmt]
    f = parse(buf)
    for p, (off, length, _) in enumerate(f["levels"]):
        s = 16 >> p
        stored = np.frombuffer(buf, NP_DTYPE[type_size], count=6 * s * s * 4, offset=off).reshape(6, s, s, 4)
        np.testing.assert_array_equal(stored, levels[p].astype(NP_DTYPE[type_size]))


# ------------------------------------------------------------------------------------------------- round trips


def test_roundtrip_cubemap_rgba32f_exact(tmp_path):
    levels = cube_chain(16)
    path, _ = written(tmp_path, levels, "rgba32f", metadata={"jaxpbr:mips": "r_m = m/(M-1)"})
    back, md, info = read_ktx2(path)
    assert len(back) == 5
    for a, b in zip(back, levels):
        assert a.dtype == np.float32 and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    assert md == {"KTXorientation": "rd", "KTXwriter": f"jaxpbr {jaxpbr.__version__}", "jaxpbr:mips": "r_m = m/(M-1)"}
    assert (info["vk_format"], info["face_count"], info["level_count"]) == (109, 6, 5)
    assert (info["pixel_width"], info["pixel_height"]) == (16, 16)
    assert isinstance(info["dfd"], bytes) and len(info["dfd"]) == 92


def test_roundtrip_cubemap_rgba16f_equals_float16_rounding(tmp_path):
    levels = cube_chain(16)
    levels[0][0, 0, 0, :] = [65504.0, -65504.0, 1e-8, -0.0]  # extremes: max half, tiny (flushes/subnormal), -0
    path, _ = written(tmp_path, levels, "rgba16f")
    back, _, info = read_ktx2(path)
    for a, b in zip(back, levels):
        expected = b.astype(np.float16).astype(np.float32)
        np.testing.assert_array_equal(a, expected)
        assert np.array_equal(np.signbit(a), np.signbit(expected))
    assert back[0][0, 0, 0, 0] == 65504.0
    assert info["vk_format"] == 97


def test_roundtrip_2d_rg_texture(tmp_path):
    lut = [rand((32, 32, 2), 0, 1, seed=7)]
    for fmt in ("rg16f", "rg32f"):
        path, _ = written(tmp_path, lut, fmt, name=f"lut_{fmt}.ktx2")
        back, _, info = read_ktx2(path)
        assert back[0].shape == (32, 32, 2) and info["face_count"] == 1
        np.testing.assert_array_equal(back[0], lut[0].astype(np.float16 if fmt == "rg16f" else np.float32))


def test_rgb_input_is_padded_with_alpha_one(tmp_path):
    levels = cube_chain(4, channels=3)
    path, _ = written(tmp_path, levels, "rgba16f")
    back, _, _ = read_ktx2(path)
    for a, b in zip(back, levels):
        assert a.shape == b.shape[:-1] + (4,)
        np.testing.assert_array_equal(a[..., :3], b.astype(np.float16))
        assert np.all(a[..., 3] == 1.0)


def test_partial_chain_and_nonsquare_npot_2d(tmp_path):
    # 2D 5x3 -> 2x1 -> 1x1 (floor halving, min 1); a partial chain of only level 0 is also valid.
    levels = [rand((5, 3, 4)), rand((2, 1, 4)), rand((1, 1, 4))]
    path, buf = written(tmp_path, levels, "rgba32f")
    back, _, _ = read_ktx2(path)
    for a, b in zip(back, levels):
        np.testing.assert_array_equal(a, b)
    path, buf = written(tmp_path, levels[:1], "rgba32f", name="one.ktx2")
    assert parse(buf)["levelCount"] == 1


def test_overwrite_replaces_existing_file(tmp_path):
    path = tmp_path / "env.ktx2"
    path.write_bytes(b"old contents")
    write_ktx2(path, [rand((6, 2, 2, 4))], fmt="rgba32f")
    assert path.read_bytes()[:12] == SPEC_IDENTIFIER
    assert listing(tmp_path) == ["env.ktx2"]


# ------------------------------------------------------------------------------------------------- bad inputs


def _expect_nothing_written(tmp_path, levels, match, **kw):
    with pytest.raises(ValueError, match=match):
        write_ktx2(tmp_path / "bad.ktx2", levels, **kw)
    assert listing(tmp_path) == []


def test_wrong_level_sizes_rejected(tmp_path):
    _expect_nothing_written(tmp_path, [rand((6, 8, 8, 4)), rand((6, 5, 5, 4))], r"level 1 .*half")
    _expect_nothing_written(tmp_path, [rand((6, 8, 8, 4)), rand((6, 4, 4, 4)), rand((6, 4, 4, 4))], r"level 2")
    _expect_nothing_written(tmp_path, [rand((8, 6, 4)), rand((4, 4, 4))], r"level 1")  # 2D: width 6 -> 3
    _expect_nothing_written(tmp_path, [rand((6, 8, 4, 4))], r"\(6, S, S, C\)")  # non-square faces
    _expect_nothing_written(tmp_path, [rand((5, 8, 8, 4))], r"\(6, S, S, C\)")  # not 6 faces
    _expect_nothing_written(tmp_path, [rand((6, 2, 2, 4)), rand((6, 1, 1, 4)), rand((6, 1, 1, 4))], r"at most 2")
    _expect_nothing_written(tmp_path, [rand((6, 4, 4, 4)), rand((2, 2, 4))], r"level 1")  # cube then 2D
    _expect_nothing_written(tmp_path, [], r"empty")
    _expect_nothing_written(tmp_path, rand((6, 4, 4, 4)), r"sequence")  # a bare array, not a list of levels


def test_nan_and_inf_rejected_with_texel_count(tmp_path):
    levels = cube_chain(4)
    levels[0][2, 1, 1, 0] = np.nan
    levels[0][2, 1, 1, 2] = np.nan  # same texel: still 1 texel
    levels[1][0, 0, 0, 3] = np.inf
    levels[2][5, 0, 0, 1] = -np.inf
    _expect_nothing_written(tmp_path, levels, r"^3 texel\(s\) hold NaN or Inf \(level 0: 1, level 1: 1, level 2: 1\)")
    _expect_nothing_written(tmp_path, levels, r"3 texel", fmt="rgba32f")


def test_half_overflow_rejected_but_fits_rgba32f(tmp_path):
    levels = cube_chain(4)
    levels[0][1, 0, 0, 0] = 70000.0
    levels[1][1, 0, 0, 2] = -65520.0  # rounds to -inf in float16
    with pytest.raises(ValueError, match=r"2 value\(s\) exceed the float16 range") as e:
        write_ktx2(tmp_path / "bad.ktx2", levels, fmt="rgba16f")
    assert "65504" in str(e.value) and "pre-expose" in str(e.value).lower() and "'rgba32f'" in str(e.value)
    assert listing(tmp_path) == []
    lut = [np.full((2, 2, 2), 1e5, np.float32)]
    _expect_nothing_written(tmp_path, lut, r"rg32f", fmt="rg16f")
    # The boundary value itself is representable and stored exactly; the same data fits rgba32f.
    ok = [np.full((6, 1, 1, 4), 65504.0, np.float32)]
    write_ktx2(tmp_path / "max.ktx2", ok, fmt="rgba16f")
    assert read_ktx2(tmp_path / "max.ktx2")[0][0].max() == 65504.0
    write_ktx2(tmp_path / "wide.ktx2", levels, fmt="rgba32f")
    assert read_ktx2(tmp_path / "wide.ktx2")[0][0][1, 0, 0, 0] == 70000.0
    # float64 beyond float32 would become inf in rgba32f too.
    with pytest.raises(ValueError, match="float32 range"):
        write_ktx2(tmp_path / "huge.ktx2", [np.full((1, 1, 4), 1e39)], fmt="rgba32f")


@pytest.mark.parametrize(
    "channels, fmt",
    [(2, "rgba16f"), (1, "rgba32f"), (4, "rg16f"), (3, "rg32f"), (1, "rg16f"), (5, "rgba16f")],
)
def test_channel_count_that_does_not_fit_format_rejected(tmp_path, channels, fmt):
    with pytest.raises(ValueError) as e:
        write_ktx2(tmp_path / "bad.ktx2", [rand((4, 4, channels))], fmt=fmt)
    msg = str(e.value)
    assert f"'{fmt}'" in msg and f"{channels} channel" in msg
    assert listing(tmp_path) == []


def test_unknown_format_and_bad_metadata_rejected(tmp_path):
    lv = [rand((2, 2, 4))]
    _expect_nothing_written(tmp_path, lv, r"unknown KTX2 format 'rgb9e5'", fmt="rgb9e5")
    _expect_nothing_written(tmp_path, lv, r"reserved", metadata={"KTXwriter": "me"})
    _expect_nothing_written(tmp_path, lv, r"reserved", metadata={"ktxAnything": "x"})
    _expect_nothing_written(tmp_path, lv, r"must be str.*json", metadata={"jaxpbr:conventions": {"a": 1}})
    _expect_nothing_written(tmp_path, lv, r"NUL", metadata={"a\x00b": "x"})
    _expect_nothing_written(tmp_path, lv, r"NUL", metadata={"a": "x\x00y"})
    _expect_nothing_written(tmp_path, [np.zeros((2, 2, 4), bool)], r"real numbers")


def test_missing_directory_leaves_nothing(tmp_path):
    target = tmp_path / "no_such_dir" / "env.ktx2"
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_ktx2(target, [rand((6, 2, 2, 4))])
    assert listing(tmp_path) == []
    (tmp_path / "afile").write_bytes(b"x")
    with pytest.raises(NotADirectoryError):
        write_ktx2(tmp_path / "afile" / "env.ktx2", [rand((6, 2, 2, 4))])
    assert listing(tmp_path) == ["afile"]


def test_failed_write_leaves_no_temp_and_keeps_old_file(tmp_path, monkeypatch):
    path = tmp_path / "env.ktx2"
    path.write_bytes(b"previous good file")

    def broken_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError):
        write_ktx2(path, cube_chain(4))
    assert listing(tmp_path) == ["env.ktx2"]
    assert path.read_bytes() == b"previous good file"


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="needs a non-root POSIX user for chmod")
def test_unwritable_directory_leaves_nothing(tmp_path):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    try:
        with pytest.raises(PermissionError):
            write_ktx2(d / "env.ktx2", cube_chain(2))
        assert listing(d) == []
    finally:
        d.chmod(0o700)


# ------------------------------------------------------------------------------------------------------ reader


def _patched(buf: bytes, offset: int, fmt: str, value) -> bytes:
    b = bytearray(buf)
    struct.pack_into(fmt, b, offset, value)
    return bytes(b)


@pytest.mark.parametrize(
    "offset, fmt, value, match",
    [
        (0, "<B", 0xAC, "identifier"),
        (12, "<I", 37, "vkFormat 37 is not supported"),  # VK_FORMAT_R8G8B8A8_UNORM
        (16, "<I", 4, "typeSize is 4"),
        (28, "<I", 4, "3D textures"),
        (32, "<I", 2, "array textures"),
        (36, "<I", 2, "faceCount"),
        (40, "<I", 9, "levelCount 9"),
        (44, "<I", 2, "supercompressionScheme 2"),  # Zstandard
        (52, "<I", 91, "dfdTotalSize"),
        (60, "<I", 100, "kvdByteLength|key/value"),
        (80 + 24 * 1, "<Q", 10**9, "lies outside"),
    ],
)
def test_reader_rejects_invalid_files(tmp_path, offset, fmt, value, match):
    _, buf = written(tmp_path, cube_chain(4), "rgba16f")  # 3 levels: 4, 2, 1
    bad = tmp_path / "bad.ktx2"
    bad.write_bytes(_patched(buf, offset, fmt, value))
    with pytest.raises(ValueError, match=match):
        read_ktx2(bad)


def test_reader_rejects_truncated_and_foreign_files(tmp_path):
    _, buf = written(tmp_path, cube_chain(4), "rgba32f")
    (tmp_path / "short.ktx2").write_bytes(buf[:-1])
    with pytest.raises(ValueError, match="level 0"):
        read_ktx2(tmp_path / "short.ktx2")
    (tmp_path / "head.ktx2").write_bytes(buf[:40])
    with pytest.raises(ValueError, match="truncated"):
        read_ktx2(tmp_path / "head.ktx2")
    ktx1 = b"\xabKTX 11\xbb\r\n\x1a\n" + bytes(64)
    (tmp_path / "v1.ktx").write_bytes(ktx1)
    with pytest.raises(ValueError, match="identifier"):
        read_ktx2(tmp_path / "v1.ktx")
    with pytest.raises(FileNotFoundError):
        read_ktx2(tmp_path / "missing.ktx2")


def test_reader_level_count_zero_means_base_level_only(tmp_path):
    # "levelCount = 0 ... means that a file contains only the base level"; the level index then has one entry.
    lv = [rand((6, 4, 4, 4))]
    _, buf = written(tmp_path, lv, "rgba32f")
    p = tmp_path / "zero.ktx2"
    p.write_bytes(_patched(buf, 40, "<I", 0))
    back, _, info = read_ktx2(p)
    assert info["level_count"] == 0 and len(back) == 1
    np.testing.assert_array_equal(back[0], lv[0])


def test_formats_table_matches_vulkan_enum_values():
    assert ktx2.FORMATS == {k: (vk, ch, ts) for k, (vk, ts, ch) in VK.items()}
