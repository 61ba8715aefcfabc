"""Hostile command-line values and damaged PNGs: one line on stderr, exit status 2,
nothing written, and nothing printed by a native library.

* `jaxpbr render --fov-y 0` rendered at 45 degrees (`args.fov_y or 45.0`) and overwrote the
  output; `--fov-y 1e-9` made a projection whose neighbouring pixels share one float32 ray
  direction; `--environment-intensity 1e39` printed NumPy's float32 overflow warning before the
  error. The parser now refuses them (`jaxpbr.cli._common.float32_arg`).
* A PNG whose IDAT zlib stream is corrupt (chunk CRCs intact), whose IHDR declares 0x0 pixels or
  whose zlib stream does not end made libpng print its own `libpng error: ...` line before
  jaxpbr's error. `jaxpbr.io.image.png_problem` refuses them first, for glTF images and for the
  PNG files `jaxpbr.io.image` reads (the textures of a scene file).

Each damaged PNG is first shown to make libpng complain when OpenImageIO is given it directly
(the oracle: the file is one libpng itself refuses, noisily), then to be refused by jaxpbr in
silence.
"""

from __future__ import annotations

import struct
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
from gltf_writer import FLOAT, Builder

from jaxpbr.cli import build_parser, main
from jaxpbr.errors import InputError
from jaxpbr.io import image
from jaxpbr.io.gltf import read_gltf

_KEEP = b"\x89PNG previous output, must survive\n"


def _cli(capfd, args):
    """`jaxpbr ARGS` in this process, output captured at the file descriptors -> (status, stdout, stderr)."""
    capfd.readouterr()
    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:  # argparse's refusals
        code = exc.code
    out, err = capfd.readouterr()
    return code, out, err


def _triangle(tmp_path: Path, *, camera: bool = False, image_data: bytes | None = None) -> Path:
    """A one-triangle glTF (.glb), optionally with a perspective camera (yfov 0.7 rad) or with
    `image_data` as its base colour texture (a bufferView image, image/png)."""
    b = Builder()
    attrs = {"POSITION": b.accessor(np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), FLOAT, "VEC3", minmax=True)}
    prim = {"attributes": attrs}
    if image_data is not None:
        attrs["TEXCOORD_0"] = b.accessor(np.float32([[0, 0], [1, 0], [0, 1]]), FLOAT, "VEC2")
        b.add("images", {"bufferView": b.view(image_data), "mimeType": "image/png"})
        b.add("textures", {"source": 0})
        prim["material"] = b.add("materials", {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}})
    b.add("meshes", {"primitives": [prim]})
    nodes = [b.add("nodes", {"mesh": 0})]
    if camera:
        b.add("cameras", {"type": "perspective", "perspective": {"yfov": 0.7, "znear": 0.01}})
        nodes.append(b.add("nodes", {"camera": 0, "translation": [0.3, 0.3, 3.0]}))
    b.add("scenes", {"nodes": nodes})
    return b.write(tmp_path / ("textured.glb" if image_data is not None else "tri.glb"), mode="glb")


def _output(tmp_path: Path) -> Path:
    out = tmp_path / "out.png"
    out.write_bytes(_KEEP)
    return out


# ------------------------------------------------------------------------------ flag values


@pytest.mark.parametrize("flag,value,says", [
    ("--fov-y", "0", "expected a number in [0.5, 179] degrees"),
    ("--fov-y", "1e-9", "expected a number in [0.5, 179] degrees"),
    ("--fov-y", "180", "expected a number in [0.5, 179] degrees"),
    ("--fov-y", "-45", "expected a number in [0.5, 179] degrees"),
    ("--environment-intensity", "1e39", "1e39 is outside float32's range"),
    ("--environment-intensity", "-1", "expected a number >= 0"),
    ("--exposure", "-1e39", "-1e39 is outside float32's range"),
    ("--camera-position", "1e39,0,0", "'1e39,0,0' is outside float32's range"),
])
def test_out_of_range_flag_one_line_exit_2_output_kept(tmp_path, capfd, flag, value, says):
    """The parser's one line (`jaxpbr render: error: argument FLAG: ...`, the form of every
    argparse refusal: `jaxpbr.cli._Parser.error`), status 2, before the asset is read or the output
    touched; no NumPy warning line before it."""
    asset, out = _triangle(tmp_path), _output(tmp_path)
    extra = ["--environment", "procedural:sky"] if flag == "--environment-intensity" else []
    code, stdout, err = _cli(capfd, ["render", asset, "-o", out, "--width", 8, "--height", 8, *extra, f"{flag}={value}"])
    lines = err.splitlines()
    assert code == 2 and stdout == "", (code, stdout, err)
    assert len(lines) == 1 and lines[0].startswith(f"jaxpbr render: error: argument {flag}: "), err
    assert says in lines[0], lines[0]
    assert out.read_bytes() == _KEEP
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.png", "tri.glb"]


@pytest.mark.parametrize("camera", [False, True])
@pytest.mark.parametrize("fov", [0.5, 179.0])
def test_fov_bounds_reach_the_camera(tmp_path, capfd, camera, fov):
    """The range's ends are accepted and are the camera's field of view (no `or 45.0`), with and
    without a camera in the asset; without --fov-y the asset's camera keeps its own (0.7 rad)."""
    from jaxpbr.cli.render import _gltf_scene

    asset = _triangle(tmp_path, camera=camera)
    args = build_parser().parse_args(["render", str(asset), "--width", "8", "--height", "8", "--fov-y", repr(fov)])
    scene, _ = _gltf_scene(args)
    assert float(scene.camera.fov_y_deg) == pytest.approx(fov, rel=1e-6)
    args = build_parser().parse_args(["render", str(asset), "--width", "8", "--height", "8"])
    scene, _ = _gltf_scene(args)
    assert float(scene.camera.fov_y_deg) == pytest.approx(np.degrees(0.7) if camera else 45.0, rel=1e-6)
    assert capfd.readouterr().err == ""


# ------------------------------------------------------------------------------ damaged PNGs


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def _png(width: int, height: int, stream: bytes) -> bytes:
    """An 8-bit RGB PNG from its IHDR size and its IDAT's zlib stream, every CRC valid."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", stream) + _chunk(b"IEND", b"")


def _damaged(kind: str) -> bytes:
    """A 4x4 RGB PNG damaged one way, its chunk structure and CRCs intact."""
    rows = b"".join(b"\0" + bytes(range(16 * y, 16 * y + 12)) for y in range(4))
    stream = zlib.compress(rows)
    if kind == "corrupt_idat":  # the first deflate block's header says BTYPE = 11 (reserved)
        return _png(4, 4, stream[:2] + bytes([stream[2] | 0b111]) + stream[3:])
    if kind == "zero_size":
        return _png(0, 0, stream)
    if kind == "unended_stream":  # every row's bytes there, the Adler-32 trailer cut off
        return _png(4, 4, stream[:-4])
    raise AssertionError(kind)


_DAMAGES = ("corrupt_idat", "zero_size", "unended_stream")
_SAYS = {
    "corrupt_idat": "the image data does not decompress",
    "zero_size": "image size 0 x 0 is outside 1..1000000",
    "unended_stream": "zlib stream does not end",
}


def _libpng_complains(data: bytes, tmp_path: Path, capfd) -> None:
    """The oracle: OpenImageIO (libpng) given the bytes directly fails and libpng prints its line."""
    import OpenImageIO as oiio

    path = tmp_path / "direct.png"
    path.write_bytes(data)
    capfd.readouterr()
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        failed = oiio.geterror()
    else:
        pixels = inp.read_image(0, 0, 0, inp.spec().nchannels, "float")
        failed = inp.geterror() if pixels is None else ""
        inp.close()
    err = capfd.readouterr().err
    path.unlink()
    assert failed and "libpng error" in err, (failed, err)


def _one_error_line(err: str) -> str:
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxpbr: error: "), err
    assert "libpng" not in err, err
    return lines[0]


@pytest.mark.parametrize("kind", _DAMAGES)
def test_damaged_gltf_png_refused_silently(tmp_path, capfd, kind):
    data = _damaged(kind)
    _libpng_complains(data, tmp_path, capfd)
    asset = _triangle(tmp_path, image_data=data)
    with pytest.raises(InputError) as e:
        read_gltf(asset)
    msg = str(e.value)
    assert "\n" not in msg and f"image 0 (/images/0): the PNG data ({len(data)} bytes) is corrupt: " in msg, msg
    assert _SAYS[kind] in msg, msg
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    # decoded later (lazy_images): the same refusal, still silent
    asset_lazy = read_gltf(asset, lazy_images=True)
    with pytest.raises(InputError, match=r"image 0 \(/images/0\): the PNG data"):
        asset_lazy.images[0].pixels  # noqa: B018
    assert capfd.readouterr() == ("", "")


@pytest.mark.parametrize("kind", _DAMAGES)
def test_damaged_gltf_png_one_line_through_the_cli(tmp_path, capfd, kind):
    asset, out = _triangle(tmp_path, image_data=_damaged(kind)), _output(tmp_path)
    code, stdout, err = _cli(capfd, ["render", asset, "-o", out, "--width", 8, "--height", 8])
    assert code == 2 and stdout == "", (code, stdout, err)
    line = _one_error_line(err)
    assert f"glTF file {str(asset)!r}: image 0 (/images/0): the PNG data" in line and _SAYS[kind] in line, line
    assert out.read_bytes() == _KEEP


@pytest.mark.parametrize("kind", _DAMAGES)
def test_damaged_png_texture_of_a_scene_file_one_line(tmp_path, capfd, kind):
    """`jaxpbr.io.image` (the PNG textures of a scene file): refused as silently, one line."""
    data = _damaged(kind)
    _libpng_complains(data, tmp_path, capfd)
    (tmp_path / "bad.png").write_bytes(data)
    with pytest.raises(ValueError, match="corrupt or truncated") as e:
        image.read(tmp_path / "bad.png")
    assert _SAYS[kind] in str(e.value)
    assert image.dimensions(tmp_path / "bad.png") == (None if kind == "zero_size" else (4, 4, 3))  # the header alone
    assert capfd.readouterr() == ("", "")
    scene = tmp_path / "scene.toml"
    scene.write_text('[materials.m]\nbase_color_texture = "bad.png"\n\n[[objects]]\ntype = "sphere"\nmaterial = "m"\n')
    out = _output(tmp_path)
    code, stdout, err = _cli(capfd, ["render", scene, "-o", out, "--width", 8, "--height", 8])
    assert code == 2 and stdout == "", (code, stdout, err)
    line = _one_error_line(err)
    assert "bad.png" in line and _SAYS[kind] in line, line
    assert out.read_bytes() == _KEEP


def test_png_check_inflates_in_bounded_steps():
    """The image-data check never holds the inflated stream: a header declaring 10^6 x 10^6 RGB
    pixels (3 TB of rows) over a stream of 32 MiB of zeros is refused as short, and a 1000 x 1000
    image whose stream holds 29 MiB beyond its rows (libpng reads such a file, ignoring the excess)
    passes, each with a traced peak under 8 MiB: the stream is inflated 1 MiB at a time (measured
    3.1 and 4.1 MiB: a step, the one before it and zlib's output buffer; inflating up to the
    declared size in one call held all 32 MiB)."""
    zeros = zlib.compress(bytes(32 << 20), 9)
    huge = _png(1_000_000, 1_000_000, zeros)
    extra = _png(1000, 1000, zeros)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        problem = image.png_problem(huge)
        peak_huge = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        assert image.png_problem(extra) is None
        peak_extra = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert problem == f"the image data holds {32 << 20} of the {1_000_000 * 3_000_001} bytes the image needs (truncated?)"
    assert peak_huge < 8 << 20 and peak_extra < 8 << 20, (peak_huge, peak_extra)
