"""Untrusted glTF assets: what a file may read (containment), and what a small file may cost.

Every buffer and image an asset names must be a regular file inside the asset's own folder (or a
folder the caller allows with `roots=` / `--asset-root`): absolute paths, '..' (plain or
percent-encoded), symbolic links leading out, file: and other URI schemes, devices and FIFOs are
refused with one line naming the JSON pointer, and no byte of a file outside reaches the asset,
an image or a message. The node graph costs one visit per node whatever its shape (a DAG or a
deep chain is refused or walked in linear time), and instances cost a batched transform.

The outside file ("the secret") holds a valid triangle, so that code that read it would load and
render it: each containment case would pass silently without the policy."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import struct
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from jaxpbr.errors import InputError
from jaxpbr.io.gltf import read_gltf

from gltf_writer import png_bytes

#: A triangle's POSITION data (36 bytes); the secret file holds it, followed by a marker.
TRIANGLE = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]).tobytes()
MARKER = b"SECRET-0123456789"


@contextlib.contextmanager
def _deadline(seconds: int):
    """Fail (instead of hanging the suite) if the block takes longer than `seconds`."""
    def boom(*_):
        raise TimeoutError(f"did not finish within {seconds} s")

    old = signal.signal(signal.SIGALRM, boom)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _doc(buffer_uri: str, *, image_uri: str | None = None, byte_length: int = 36) -> dict:
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"uri": buffer_uri, "byteLength": byte_length}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }
    if image_uri is not None:
        doc["images"] = [{"uri": image_uri}]
        doc["textures"] = [{"source": 0}]
        doc["materials"] = [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]
        doc["meshes"][0]["primitives"][0]["material"] = 0
        doc["accessors"].append({"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC2"})
        doc["bufferViews"].append({"buffer": 0, "byteOffset": 36, "byteLength": 24})
        doc["buffers"][0]["byteLength"] = 60
        doc["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"] = 1
    return doc


@pytest.fixture
def world(tmp_path):
    """tmp/asset/ (the asset's folder, with its own good buffer and image) and tmp/outside/ with
    the secret buffer and a secret image."""
    asset, outside = tmp_path / "asset", tmp_path / "outside"
    asset.mkdir()
    outside.mkdir()
    uv = np.float32([[0, 0], [1, 0], [0, 1]]).tobytes()
    (asset / "good.bin").write_bytes(TRIANGLE + uv)
    (asset / "good.png").write_bytes(png_bytes(np.full((2, 2, 3), 200, np.uint8)))
    (outside / "secret.bin").write_bytes(TRIANGLE + uv + MARKER)
    (outside / "secret.png").write_bytes(png_bytes(np.full((2, 2, 3), 7, np.uint8)))
    return asset, outside


def _write(asset: Path, doc: dict, name="a.gltf") -> Path:
    p = asset / name
    p.write_text(json.dumps(doc))
    return p


def _refused(path, pointer, *words, **kw) -> str:
    with _deadline(20), pytest.raises(InputError) as e:
        read_gltf(path, **kw)
    msg = str(e.value)
    assert "\n" not in msg and pointer in msg, msg
    for w in words:
        assert w in msg, msg
    assert MARKER.decode() not in msg
    return msg


# -- the containment matrix: buffers and images -----------------------------------------------------

def _outside_uris(asset: Path, outside: Path, name: str) -> dict:
    """The ways a URI can name outside/<name> from asset/a.gltf."""
    secret = outside / name
    (asset / f"link-{name}").symlink_to(secret)
    (asset / "sub").mkdir(exist_ok=True)
    return {
        "absolute": (str(secret), "absolute path"),
        "traversal": (f"../outside/{name}", "outside its own folder"),
        "traversal inside a folder": (f"sub/../../outside/{name}", "outside its own folder"),
        "percent-encoded traversal": (f"%2e%2e/outside/{name}", "outside its own folder"),
        "percent-encoded slash": (f"..%2foutside%2f{name}", "outside its own folder"),
        "symlink": (f"link-{name}", "outside its own folder"),
        "file: URI": (f"file://{secret}", "file: URI"),
        "file: URI with a host": (f"file://evil.example{secret}", "file: URI"),
        "network path": (f"//evil.example{secret}", "network path"),
        "http": ("https://evil.example/x.bin", "scheme"),
        "drive letter": ("C:/Windows/x.bin", "absolute path"),
    }


CASES = ["absolute", "traversal", "traversal inside a folder", "percent-encoded traversal", "percent-encoded slash",
         "symlink", "file: URI", "file: URI with a host", "network path", "http", "drive letter"]


@pytest.mark.parametrize("case", CASES)
def test_buffer_outside_the_asset_folder_is_refused(world, case):
    asset, outside = world
    uri, words = _outside_uris(asset, outside, "secret.bin")[case]
    _refused(_write(asset, _doc(uri)), "/buffers/0/uri", words)


@pytest.mark.parametrize("case", CASES)
def test_image_outside_the_asset_folder_is_refused(world, case):
    asset, outside = world
    uri, words = _outside_uris(asset, outside, "secret.png")[case]
    _refused(_write(asset, _doc("good.bin", image_uri=uri, byte_length=60)), "/images/0/uri", words)
    # also when images are decoded lazily: the URI is checked by the load itself
    _refused(_write(asset, _doc("good.bin", image_uri=uri, byte_length=60)), "/images/0/uri", words, lazy_images=True)


def test_the_same_asset_reads_its_own_files(world):
    """The control: the cases above fail for their URI, not for the document."""
    asset, _ = world
    a = read_gltf(_write(asset, _doc("good.bin", image_uri="good.png", byte_length=60)))
    np.testing.assert_array_equal(a.primitives[0].positions, np.frombuffer(TRIANGLE, np.float32).reshape(3, 3))
    assert a.images[0].pixels.shape == (2, 2, 3)
    # '..' that stays inside the folder is a relative path like any other
    (asset / "sub").mkdir()
    assert read_gltf(_write(asset, _doc("sub/../good.bin"))).primitives


def test_roots_allow_a_named_folder(world):
    asset, outside = world
    path = _write(asset, _doc("../outside/secret.bin", image_uri="../outside/secret.png", byte_length=60))
    a = read_gltf(path, roots=[outside])
    np.testing.assert_array_equal(a.primitives[0].positions, np.frombuffer(TRIANGLE, np.float32).reshape(3, 3))
    assert np.allclose(a.images[0].pixels, 7 / 255)
    # a root elsewhere allows nothing here; a root that is not a folder is refused
    other = outside.parent / "other"
    other.mkdir()
    _refused(path, "/buffers/0/uri", "outside its own folder and the 1 allowed by roots", roots=[other])
    with pytest.raises(InputError, match="not an existing folder"):
        read_gltf(path, roots=[outside / "secret.bin"])


def test_roots_do_not_make_devices_readable(world):
    """Inside an allowed folder only regular files are read: /dev/zero would never end."""
    asset, _ = world
    with _deadline(20):
        _refused(_write(asset, _doc("../../../../../../../dev/zero")), "/buffers/0/uri", "outside")
        msg = _refused(_write(asset, _doc("/dev/zero")), "/buffers/0/uri", "absolute path")
        rel = os.path.relpath("/dev/zero", asset)
        msg = _refused(_write(asset, _doc(rel)), "/buffers/0/uri", "a device, not a regular file", roots=["/dev"])
        assert "Fix:" in msg
        rel = os.path.relpath("/dev/urandom", asset)
        _refused(_write(asset, _doc("good.bin", image_uri=rel, byte_length=60)), "/images/0/uri",
                 "a device, not a regular file", roots=["/dev"])


def test_fifo_is_refused_without_blocking(world):
    asset, _ = world
    os.mkfifo(asset / "pipe.bin")
    os.mkfifo(asset / "pipe.png")
    _refused(_write(asset, _doc("pipe.bin")), "/buffers/0/uri", "a FIFO, not a regular file")
    _refused(_write(asset, _doc("good.bin", image_uri="pipe.png", byte_length=60)), "/images/0/uri",
             "a FIFO, not a regular file")


def test_folder_as_uri_is_refused(world):
    asset, _ = world
    (asset / "dir.bin").mkdir()
    _refused(_write(asset, _doc("dir.bin")), "/buffers/0/uri", "a folder, not a regular file")


def test_buffer_reads_exactly_byte_length(world):
    """A file longer than byteLength is read no further (a 256 MB sparse file behind a 36-byte
    buffer costs nothing); a shorter one is an error naming byteLength."""
    asset, _ = world
    big = asset / "big.bin"
    with open(big, "wb") as f:
        f.write(TRIANGLE)
        f.truncate(256 << 20)
    tracemalloc.start()
    try:
        a = read_gltf(_write(asset, _doc("big.bin")))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(a.primitives[0].positions, np.frombuffer(TRIANGLE, np.float32).reshape(3, 3))
    assert peak < 16 << 20, f"peak {peak / 1e6:.1f} MB: the file was read past byteLength"
    (asset / "short.bin").write_bytes(TRIANGLE[:20])
    _refused(_write(asset, _doc("short.bin")), "/buffers/0/byteLength", "byteLength is 36", "holds only 20 bytes")


def test_byte_length_is_checked_by_the_memory_guard_before_reading(world, monkeypatch):
    asset, _ = world
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "1")
    with open(asset / "huge.bin", "wb") as f:
        f.truncate(8 << 30)  # sparse: 8 GB declared and present, nothing on disk
    doc = _doc("huge.bin", byte_length=8 << 30)
    with _deadline(20), pytest.raises(InputError, match="GB of memory"):
        read_gltf(_write(asset, doc))


def test_data_uri_longer_than_byte_length_is_cut(world):
    import base64

    asset, _ = world
    uri = "data:application/octet-stream;base64," + base64.b64encode(TRIANGLE + MARKER).decode()
    a = read_gltf(_write(asset, _doc(uri)))
    np.testing.assert_array_equal(a.primitives[0].positions, np.frombuffer(TRIANGLE, np.float32).reshape(3, 3))


def test_messages_do_not_echo_buffer_bytes(world):
    """An index accessor over bytes the asset does not know (here: the marker) is refused by
    position, not by value: a message must not become a way to read a file two bytes at a time."""
    asset, outside = world
    doc = _doc("../outside/secret.bin", byte_length=60 + len(MARKER))
    doc["bufferViews"].append({"buffer": 0, "byteOffset": 60, "byteLength": 6})
    doc["accessors"].append({"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"})
    doc["meshes"][0]["primitives"][0]["indices"] = 1
    path = _write(asset, doc)
    msg = _refused(path, "/meshes/0/primitives/0/indices", "out of range (the first at position 0)", roots=[outside])
    for value in struct.unpack("<3H", MARKER[:6]):
        assert str(value) not in msg.split("/accessors/1")[1], msg


# -- through the command line and a batch job -------------------------------------------------------

def test_cli_refuses_an_outside_buffer_and_writes_nothing(world, capfd, tmp_path):
    from jaxpbr.cli import main

    asset, outside = world
    path = _write(asset, _doc(str(outside / "secret.bin")))
    out = tmp_path / "out.png"
    code = main(["render", str(path), "-o", str(out), "--width", "8", "--height", "8"])
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("jaxpbr: error:") and "/buffers/0/uri" in err[0], err
    assert MARKER.decode() not in err[0]
    assert not out.exists()


def test_cli_asset_root_allows_a_folder(world, capfd, tmp_path):
    from jaxpbr.cli import main

    asset, outside = world
    path = _write(asset, _doc("../outside/secret.bin"))
    out = tmp_path / "out.png"
    assert main(["render", str(path), "-o", str(out), "--width", "8", "--height", "8",
                 "--asset-root", str(outside)]) == 0, capfd.readouterr().err
    assert out.exists()


def test_batch_job_refuses_an_outside_buffer(world, capfd, tmp_path):
    from jaxpbr.cli import main

    asset, outside = world
    path = _write(asset, _doc(str(outside / "secret.bin")))
    jobs = tmp_path / "jobs.jsonl"
    jobs.write_text(json.dumps({"name": "hostile", "scene": str(path), "width": 8, "height": 8}) + "\n")
    out = tmp_path / "out"
    code = main(["batch", str(jobs), "--out", str(out), "--quiet"])
    captured = capfd.readouterr()
    text = captured.out + captured.err
    assert code != 0, text
    assert "/buffers/0/uri" in text and MARKER.decode() not in text, text
    assert not any(p.suffix in (".png", ".exr") for p in out.rglob("*")) if out.exists() else True


# -- bounded cost from the JSON alone ---------------------------------------------------------------

def _graph_doc(nodes, roots) -> dict:
    doc = _doc("data:application/octet-stream;base64," + __import__("base64").b64encode(TRIANGLE).decode())
    doc["nodes"] = nodes
    doc["scenes"] = [{"nodes": roots}]
    return doc


def test_dag_is_refused_at_once(tmp_path):
    """40 nodes each listing the next twice: 2^40 paths from the root. One parent per node."""
    n = 40
    nodes = [{"children": [i + 1, i + 1]} for i in range(n - 1)] + [{"mesh": 0}]
    _refused(_write(tmp_path, _graph_doc(nodes, [0])), "/nodes/0/children/1", "repeats an earlier item of children")
    nodes = [{"children": [i + 1, i + 2]} if i + 2 < n else {"children": [i + 1]} if i + 1 < n else {"mesh": 0}
             for i in range(n)]
    _refused(_write(tmp_path, _graph_doc(nodes, [0])), "/nodes/1/children/0", "also by node 0", "one parent at most")


def test_cycles_and_non_root_scene_nodes_are_refused(tmp_path):
    nodes = [{"children": [1]}, {"children": [2]}, {"children": [1], "mesh": 0}]
    _refused(_write(tmp_path, _graph_doc(nodes, [0])), "/nodes/2/children/0", "also by node 0")
    nodes = [{"children": [1]}, {"children": [2]}, {"children": [0], "mesh": 0}]  # a ring, no root
    _refused(_write(tmp_path, _graph_doc(nodes, [])), "/nodes/", "its own ancestor")
    nodes = [{"children": [1]}, {"mesh": 0}]
    _refused(_write(tmp_path, _graph_doc(nodes, [0, 1])), "/scenes/0/nodes/1", "a scene lists root nodes only")
    _refused(_write(tmp_path, _graph_doc(nodes, [0, 0])), "/scenes/0/nodes/1", "repeats an earlier item of nodes")


def test_deep_and_wide_graph_costs_memory_linear_in_nodes(tmp_path):
    """A chain of 3000 nodes whose last has 3000 children: a copy of the ancestry per child cost
    depth x width (72 MB here; 3.3 GB at 20 000 x 20 000); one visit per node costs a few MB."""
    depth = width = 3000
    nodes = [{"children": [i + 1]} for i in range(depth - 1)]
    nodes.append({"children": list(range(depth, depth + width))})
    nodes += [{"mesh": 0, "translation": [float(k), 0.0, 0.0]} for k in range(width)]
    path = _write(tmp_path, _graph_doc(nodes, [0]))
    tracemalloc.start()
    try:
        with _deadline(60):
            a = read_gltf(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(a.primitives) == width
    xs = np.array([p.positions[0, 0] for p in a.primitives])
    np.testing.assert_array_equal(xs, np.arange(width, dtype=np.float32))
    assert peak < 40 << 20, f"peak {peak / 1e6:.1f} MB"


def test_many_instances_share_one_batched_transform(tmp_path):
    """10 000 nodes instancing one mesh (and a mirrored one): each instance is placed exactly
    (positions against NumPy's own transform, winding flipped under a mirror)."""
    n = 10_000
    rng = np.random.default_rng(3)
    t = rng.uniform(-50, 50, (n, 3))
    s = rng.uniform(0.5, 2.0, (n, 3))
    s[::7, 0] *= -1  # every 7th mirrored
    nodes = [{"mesh": 0, "translation": t[k].tolist(), "scale": s[k].tolist()} for k in range(n)]
    path = _write(tmp_path, _graph_doc(nodes, list(range(n))))
    a = read_gltf(path)
    assert len(a.primitives) == n
    tri = np.frombuffer(TRIANGLE, np.float32).reshape(3, 3).astype(np.float64)
    want = tri[None] * s[:, None, :] + t[:, None, :]
    got = np.stack([p.positions for p in a.primitives])
    np.testing.assert_allclose(got, want.astype(np.float32), rtol=0, atol=1e-5)
    mirrored = np.array([p.indices.tolist() == [[0, 2, 1]] for p in a.primitives])
    np.testing.assert_array_equal(mirrored, np.prod(np.sign(s), axis=1) < 0)
    assert [p.node for p in a.primitives] == list(range(n))


def test_instances_are_counted_by_the_memory_guard_before_any_buffer_is_read(tmp_path, monkeypatch):
    """20 000 nodes instancing one triangle under a 20 MB limit: refused from the JSON alone,
    naming the mesh primitive, with no buffer read (each instance costs its arrays and ~1 kB)."""
    from jaxpbr._memory import MemoryLimitError
    from jaxpbr.io.gltf import _binary

    n = 20_000
    nodes = [{"mesh": 0, "translation": [float(k), 0.0, 0.0]} for k in range(n)]
    path = _write(tmp_path, _graph_doc(nodes, list(range(n))))
    assert len(read_gltf(path).primitives) == n  # it loads with the memory there is
    real = _binary.Buffers.buffer
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "0.02")
    monkeypatch.setattr(_binary.Buffers, "buffer", lambda *a, **k: pytest.fail("a buffer was read before the check"))
    with pytest.raises(MemoryLimitError) as e:
        read_gltf(path)
    assert "lower the vertex and index counts of /meshes/0/primitives/0" in str(e.value)
    # loaded to be rendered, the acceleration structure counts too (the engine's fixed cost
    # alone is above 0.1 GB): ten instances load, and are refused for a render
    monkeypatch.setattr(_binary.Buffers, "buffer", real)
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "0.1")
    small = _write(tmp_path, _graph_doc(nodes[:10], list(range(10))), name="small.gltf")
    assert len(read_gltf(small).primitives) == 10
    with pytest.raises(MemoryLimitError, match="/meshes/0/primitives/0"):
        read_gltf(small, ray_engine="embree")


@pytest.mark.parametrize("values, ok", [(1.0000001, True), (1e30, False), (-0.5, False), (2.0, False)])
def test_color_0_outside_the_unit_range_is_refused_before_work(tmp_path, values, ok):
    import base64

    data = TRIANGLE + np.float32([[values, 0.5, 0.5, 1.0]] * 3).tobytes()
    doc = _doc("data:application/octet-stream;base64," + base64.b64encode(data).decode(), byte_length=len(data))
    doc["bufferViews"].append({"buffer": 0, "byteOffset": 36, "byteLength": 48})
    doc["accessors"].append({"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC4"})
    doc["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"] = 1
    path = _write(tmp_path, doc)
    if ok:
        assert read_gltf(path).primitives[0].color_0.max() == 1.0
    else:
        msg = _refused(path, "/meshes/0/primitives/0/attributes/COLOR_0", "outside [0, 1] (the first in element 0)")
        assert repr(values) not in msg and str(values) not in msg


def test_the_asset_file_itself_must_be_a_regular_file(tmp_path):
    os.mkfifo(tmp_path / "pipe.gltf")
    with _deadline(20), pytest.raises(InputError, match="names a FIFO, not a regular file"):
        read_gltf(tmp_path / "pipe.gltf")
    with _deadline(20), pytest.raises(InputError, match="names a device, not a regular file"):
        read_gltf("/dev/zero")


def test_json_nested_too_deep_is_one_line(tmp_path):
    path = tmp_path / "deep.gltf"
    path.write_text('{"asset": {"version": "2.0"}, "extras": ' + "[" * 200_000 + "]" * 200_000 + "}")
    msg = _refused(path, "JSON", "nested too deep")
    assert "recursion" not in msg


def test_json_size_is_checked_by_the_memory_guard_before_reading(tmp_path, monkeypatch):
    from jaxpbr._memory import MemoryLimitError

    path = tmp_path / "big.gltf"
    with open(path, "wb") as f:
        f.write(b'{"asset": {"version": "2.0"}, "extras": "')
        f.truncate(200 << 20)  # 200 MB of JSON text (NUL bytes: never parsed)
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "1")
    with pytest.raises(MemoryLimitError, match="the size of the .gltf file"):
        read_gltf(path)
