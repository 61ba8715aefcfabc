"""`jaxpbr.cli.bench_render`: the NumPy shading equals JAX `shade_direct + shade_ibl` to float32 rounding,
and the benchmark / CLI machinery runs on a tiny configuration.

Tolerance (used by every equivalence test below). Both sides evaluate the same formulas in float32
with a different order / fusion of operations (JAX renormalises n and v with rsqrt, XLA fuses), so
each is within its own forward error of the exact value y(x) of the formulas on the float32 inputs:

    |y32 - y| <= K u |y| + cond,    u = 2^-24 (float32 unit roundoff),

* `K u |y|` with K = 32: every output is a sum of non-negative terms (lights, diffuse and specular
  IBL), each a product/quotient chain of at most ~30 correctly rounded operations, so there is no
  cancellation and the first-order relative error is at most (chain length) u. (Measured at the
  well-conditioned pixels: <= 10 u.)
* `cond`: the amplification of input-sized roundings by ill-conditioned steps -- texel coordinates
  x = s S + 0.5 where neighbouring texels differ by 10^3 (the sun's edge), the GGX peak at small
  alpha (relative sensitivity ~ 1/alpha to the half vector), grazing views. The two programs round
  their intermediates differently (JAX renormalises n and v with rsqrt, normalises h by rsqrt times
  instead of a division, XLA reorders and fuses); each is taken to be backward stable with a
  backward error of at most 4 u per input component (a couple of roundings in n, v, h, R before the
  sensitive steps). `cond` is the first-order worst case over that box,
  sum_i max(|y(x + h_i e_i) - y(x)|, |y(x - h_i e_i) - y(x)|), h_i = 4 u |x_i|, every scalar input
  component i of the pixel, y evaluated in float64. (A random-perturbation estimate is not enough:
  XLA's fused program exceeds it by 5 % near the sun's edge.)

Hence |jax - numpy| <= 2 (K u |y| + cond), with y the float64 evaluation of the NumPy code on the
float32 inputs and float64 copies of the tables. Pixels where the model itself is discontinuous
within rounding (n.v within ~1e-7 of 0: the direct-light Smith term jumps from 0.5/alpha to 0) are
kept out by construction: grazing views have |n.v| >= 1e-5.
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.cli import bench_render as br
from jaxpbr.cli import numpy_baselines as nb
from jaxpbr.cli.numpy_baselines import bench_lights
from jaxpbr.ibl.cubemap import Cubemap, _Pyramid
from jaxpbr.ibl.shade import shade_ibl

U = 2.0**-24
K_ARITH = 32
PERTURB = 4 * U


def _f64_tables(ibl: nb.NumpyIBL) -> nb.NumpyIBL:
    cube = lambda c: nb.NumpyCube(c.flat.astype(np.float64), c.offsets, c.sizes)
    return nb.NumpyIBL(cube(ibl.irr), cube(ibl.pre), ibl.lut.astype(np.float64), ibl.mapping)


def _bound(f, inputs: dict):
    """(y, bound): y = f(float64 inputs); bound = K u |y| + cond (see the module docstring), with
    cond the first-order worst case of |f| over relative input perturbations of up to 4 u per scalar
    component. `f` maps a dict of (P, ...) arrays to (P, ...) values."""
    x64 = {k: np.asarray(x, np.float64) for k, x in inputs.items()}
    y = f(x64)
    cond = np.zeros_like(y)
    for key, x in x64.items():
        for c in np.ndindex(x.shape[1:]):
            idx = (slice(None),) + c
            worst = np.zeros_like(y)
            for sign in (1.0, -1.0):
                xp = dict(x64)
                xp[key] = x.copy()
                xp[key][idx] = x[idx] * (1.0 + sign * PERTURB)
                worst = np.maximum(worst, np.abs(f(xp) - y))
            cond += worst
    return y, K_ARITH * U * np.abs(y) + cond


def _assert_within(a, b, bound, what):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b)), what
    ratio = np.abs(a - b) / (2.0 * bound + 1e-300)
    i = np.unravel_index(np.argmax(ratio), ratio.shape)
    assert ratio.max() <= 1.0, f"{what}: |a - b| = {abs(a[i] - b[i]):.3g} exceeds 2 x bound {bound[i]:.3g} at {i}"


# ------------------------------------------------------------------------------------------
# fixtures
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def env32():
    return jp.envs.sky_with_sun_cubemap(32)


@pytest.fixture(scope="module")
def tables(env32):
    """irradiance 16^2; as the 'prefiltered' map the environment's own mip pyramid (the lookup is the
    same whatever the levels hold, and the unblurred sun, 3000 vs ~1, is the stiffest content for
    it); the shipped 128^2 LUT."""
    irr = jp.irradiance(env32, size=16)
    pre = Cubemap(env32.with_mips().levels, {"roughness_mapping": "linear"})
    lut = jp.brdf_lut(size=128)
    return irr, pre, lut


@pytest.fixture(scope="module")
def tiny_ibl():
    return br.make_ibl(8)


def _unit32(x):
    x = np.asarray(x, np.float64)
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def _random_gbuffer(P=4096, seed=1):
    """Random normals; views: 1/4 grazing (|n.v| log-uniform in [1e-5, 1e-2], both signs), 1/8
    mirroring the sun's neighbourhood (R within ~2 degrees of the sun: the sun disc edge), the rest
    uniform on the sphere (half of them back-facing); roughness 0 and the punctual floor 0.045 on
    1/8 each, metallic in {0, 0.5, 1}; positions in [-3, 3]^3 (lights at +-10)."""
    rng = np.random.default_rng(seed)
    n = _unit32(rng.standard_normal((P, 3)))
    n64 = n.astype(np.float64)
    v = rng.standard_normal((P, 3))
    k = P // 4
    t = v[:k] - np.sum(v[:k] * n64[:k], -1, keepdims=True) * n64[:k]
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    c = 10.0 ** rng.uniform(-5, -2, k) * rng.choice([-1.0, 1.0], k)
    v[:k] = c[:, None] * n64[:k] + np.sqrt(1.0 - c * c)[:, None] * t
    s = np.asarray(jp.envs.SUN_DIRECTION) + 0.035 * rng.standard_normal((P // 8, 3))
    s /= np.linalg.norm(s, axis=-1, keepdims=True)
    sl = slice(k, k + P // 8)
    v[sl] = 2.0 * np.sum(n64[sl] * s, -1, keepdims=True) * n64[sl] - s
    v = _unit32(v)
    rough = rng.uniform(0.0, 1.0, P)
    rough[: P // 8] = 0.0
    rough[P // 8 : P // 4] = 0.045
    rng.shuffle(rough)
    g = {
        "position": rng.uniform(-3.0, 3.0, (P, 3)).astype(np.float32),
        "normal": n,
        "view": v,
        "base_color": rng.uniform(0.0, 1.0, (P, 3)).astype(np.float32),
        "metallic": rng.choice([0.0, 0.5, 1.0], P).astype(np.float32),
        "roughness": rough.astype(np.float32),
    }
    nv = np.sum(n.astype(np.float64) * v, -1)
    assert np.abs(nv).min() >= 0.9e-5 and (nv < 0).mean() > 0.3 and (np.abs(nv) < 1e-3).sum() > 300
    return g


# ------------------------------------------------------------------------------------------
# components
# ------------------------------------------------------------------------------------------


def test_padded_pyramid_is_the_jax_one(tables):
    _, pre, _ = tables
    nc = nb.NumpyCube.from_cubemap(pre)
    p = _Pyramid(pre.levels)
    assert nc.flat.dtype == np.float32
    np.testing.assert_array_equal(nc.flat, np.asarray(p.flat))
    np.testing.assert_array_equal(nc.offsets, p.offsets)
    np.testing.assert_array_equal(nc.sizes, p.sizes)


def test_cube_sample_matches_cubemap_sample(tables):
    """Trilinear seam-aware lookups: random directions, plus directions on face edges and cube
    corners (ties between axes), lods below 0, between levels and above the last."""
    _, pre, _ = tables
    rng = np.random.default_rng(3)
    d = rng.standard_normal((3000, 3))
    special = np.array([[1, 1, 0.3], [1, -1, 1], [-1, 1, 1], [1, 1, 1], [-1, -1, -1], [0, 0, 1], [1, 0, 0], [0, -1, 0]], float)
    d = _unit32(np.concatenate([d, special, special * [1, 1, -1]]))
    lod = rng.uniform(-0.5, pre.num_levels - 0.5, len(d)).astype(np.float32)
    lod[-16:] = np.arange(16) % (pre.num_levels + 1)
    out = np.asarray(pre.sample(jnp.asarray(d), jnp.asarray(lod)))
    nc = nb.NumpyCube.from_cubemap(pre)
    ref = nc.sample(d[:, 0].copy(), d[:, 1].copy(), d[:, 2].copy(), lod)
    assert out.dtype == ref.dtype == np.float32
    nc64 = nb.NumpyCube(nc.flat.astype(np.float64), nc.offsets, nc.sizes)
    y, bound = _bound(lambda x: nc64.sample(x["d"][:, 0], x["d"][:, 1], x["d"][:, 2], x["lod"]), {"d": d, "lod": lod})
    _assert_within(out, ref, bound, "cube sample")
    _assert_within(out, y, bound / 2, "cube sample (jax vs float64)")


def test_lut_lookup_matches(tables):
    _, _, lut = tables
    rng = np.random.default_rng(4)
    mu = np.concatenate([rng.uniform(-0.1, 1.1, 2000), [0.0, 1e-4, 1.0, 0.5 / 128, 1 - 0.5 / 128]]).astype(np.float32)
    r = np.concatenate([rng.uniform(-0.1, 1.1, 2000), [0.0, 1.0, 1.0, 0.0, 0.5]]).astype(np.float32)
    out = np.asarray(jp.lut_lookup(lut, jnp.asarray(mu), jnp.asarray(r)))
    ref = nb.lut_lookup_numpy(np.asarray(lut), mu, r)
    assert out.dtype == ref.dtype == np.float32
    lut64 = np.asarray(lut, np.float64)
    y, bound = _bound(lambda x: nb.lut_lookup_numpy(lut64, x["mu"], x["r"]), {"mu": mu, "r": r})
    _assert_within(out, ref, bound, "LUT lookup")
    _assert_within(out, y, bound / 2, "LUT lookup (jax vs float64)")


# ------------------------------------------------------------------------------------------
# the full shading
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mapping", ["linear", "quadratic"])
def test_numpy_shading_equals_jax_direct_plus_ibl(tables, mapping):
    irr, pre, lut = tables
    pre = pre.replace(info={"roughness_mapping": mapping})
    g = _random_gbuffer()
    lights = bench_lights()
    nibl = nb.NumpyIBL.from_tables(irr, pre, lut)
    assert nibl.mapping == mapping

    ref = nb.shade_render_numpy(g, lights, nibl)
    out = np.asarray(jax.jit(br.shade_render_jax)(g, br.jax_point_lights(lights), irr, pre, lut))
    assert out.dtype == ref.dtype == np.float32 and out.shape == ref.shape == (4096, 3)

    # Same JAX expression as the benchmark's, spelled out with the public API.
    m = jp.Material(base_color=g["base_color"], metallic=g["metallic"], roughness=g["roughness"])
    jl = [jp.PointLight(position=x["position"], intensity=np.float32(300.0)) for x in lights]
    spelled = jp.shade_direct(g["position"], g["normal"], g["view"], m, jl, model="gltf") + shade_ibl(
        g["normal"], g["view"], m, irr, pre, lut, model="gltf"
    )
    assert spelled.dtype == jnp.float32

    l64 = [{k: np.asarray(x, np.float64) for k, x in light.items()} for light in lights]
    t64 = _f64_tables(nibl)
    y, bound = _bound(lambda x: nb.shade_render_numpy(x, l64, t64), g)
    _assert_within(out, ref, bound, "jit(shade_direct + shade_ibl) vs NumPy")
    _assert_within(np.asarray(spelled), ref, bound, "shade_direct + shade_ibl (op by op) vs NumPy")
    # Each float32 side alone is within its one-sided bound of the float64 evaluation.
    _assert_within(out, y, bound / 2, "JAX vs float64")
    _assert_within(ref, y, bound / 2, "NumPy vs float64")
    # Sanity of the bound itself: it is at float32 level except at the few stiff pixels.
    rel = bound / np.abs(y)
    assert np.median(rel) < 64 * U and np.mean(rel > 1e-4) < 0.01
    # and the case mix reached them: back-facing pixels still get IBL, the sun was mirrored.
    assert np.all(ref > 0) and y.max() > 100.0


def test_numpy_shading_on_the_sphere_gbuffer(tables):
    """The benchmark's own G-buffer (sphere grid + wall), small."""
    irr, pre, lut = tables
    g = nb.make_sphere_gbuffer(96, 54)
    assert all(g[k].dtype == np.float32 for k in nb.GBUFFER_KEYS) and g["sphere"].any() and not g["sphere"].all()
    np.testing.assert_allclose(np.linalg.norm(g["normal"], axis=-1), 1.0, atol=4 * U)
    gs = {k: g[k].reshape((96 * 54,) + g[k].shape[2:]) for k in nb.GBUFFER_KEYS}  # (P, ...) for _bound
    lights = bench_lights()
    nibl = nb.NumpyIBL.from_tables(irr, pre, lut)
    ref = nb.shade_render_numpy(gs, lights, nibl)
    out = np.asarray(jax.jit(br.shade_render_jax)(gs, br.jax_point_lights(lights), irr, pre, lut))
    l64 = [{k: np.asarray(x, np.float64) for k, x in light.items()} for light in lights]
    y, bound = _bound(lambda x: nb.shade_render_numpy(x, l64, _f64_tables(nibl)), gs)
    _assert_within(out, ref, bound, "sphere G-buffer")
    _assert_within(ref, y, bound / 2, "sphere G-buffer (numpy vs float64)")


# ------------------------------------------------------------------------------------------
# benchmark machinery and CLI (tiny configurations: they check the plumbing, not speed)
# ------------------------------------------------------------------------------------------


def test_bench_render_gbuffer_tiny(tiny_ibl):
    r = br.bench_render_gbuffer(48, 27, repeats=1, numpy_repeats=1, face_size=8, ibl=tiny_ibl)
    text = r.report()
    for s in ("48x27", "ms/frame", "frames/s", "speed-up jax/numpy", "JIT compile", "prefilter", "max "):
        assert s in text
    assert r.jax_s > 0 and r.numpy_s > 0 and r.compile_s > 0 and r.ratio > 0
    # Frame-level summary only (the bounded check is above); float32 both sides.
    assert r.max_rel_diff < 1e-3 and r.p999_rel_diff < 1e-4


@pytest.mark.slow  # benchmark machinery; render_batch correctness is in test_render_batch.py
def test_bench_batch_tiny(tiny_ibl):
    r = br.bench_batch(5, 16, 2, repeats=1, ibl=tiny_ibl)
    text = r.report()
    assert "5 materials x 16x16" in text and "images/s" in text and "chunk=2" in text
    assert r.batch_s > 0 and r.loop_s > 0 and r.max_rel_diff < 1e-4


def test_bench_rejects_bad_sizes(tiny_ibl):
    with pytest.raises(ValueError, match="width"):
        br.bench_render_gbuffer(0, 10, ibl=tiny_ibl)
    with pytest.raises(ValueError, match="chunk"):
        br.bench_batch(4, 8, 0, ibl=tiny_ibl)


def _parser():
    p = argparse.ArgumentParser(prog="jaxpbr")
    sub = p.add_subparsers(dest="command")
    b = sub.add_parser("bench")
    bsub = b.add_subparsers(dest="bench")
    assert br.add_command(bsub) is not None
    return p


@pytest.mark.slow
def test_cli_bench_render_tiny(capsys):
    args = _parser().parse_args(
        ["bench", "render", "--width", "32", "--height", "18", "--repeats", "1", "--numpy-repeats", "1",
         "--face-size", "8", "--batch", "3", "--batch-size", "16", "--chunk", "2"]
    )
    assert (args.width, args.height, args.batch, args.batch_size, args.chunk) == (32, 18, 3, 16, 2)
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "jaxpbr bench render: 32x18" in out and "speed-up jax/numpy" in out
    assert "3 materials x 16x16" in out and "speed-up batched/loop" in out


def test_cli_bench_render_defaults_and_errors(capsys):
    p = _parser()
    a = p.parse_args(["bench", "render"])
    assert (a.width, a.height, a.batch, a.batch_size, a.face_size) == (1920, 1080, 256, 256, 128)
    assert p.parse_args(["bench", "render", "--batch", "0"]).batch == 0
    for bad in (["--width", "0"], ["--chunk", "-1"], ["--batch", "x"]):
        with pytest.raises(SystemExit) as e:
            p.parse_args(["bench", "render", *bad])
        assert e.value.code == 2
    assert "integer" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------
# --gltf: the demo grid as a glTF asset of meshes against the analytic spheres
# ------------------------------------------------------------------------------------------


def _read_glb(path):
    """(JSON document, BIN chunk) of a .glb, parsed with struct alone (independent of jaxpbr's reader)."""
    import json
    import struct

    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    jlen, jtype = struct.unpack_from("<II", data, 12)
    assert jtype == 0x4E4F534A and jlen % 4 == 0
    doc = json.loads(data[20 : 20 + jlen])
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    assert btype == 0x004E4942 and 28 + jlen + blen == len(data)
    return doc, data[28 + jlen :]


def test_write_demo_glb_is_the_demo_grid(tmp_path):
    from gltf_writer import assert_valid

    from jaxpbr.rendering.demo import demo_grid_lat, demo_scene, write_demo_glb

    # The tessellation closest to the count asked for: 4 n (n - 1) triangles a sphere, 49 spheres.
    assert [demo_grid_lat(t) for t in (0, 1000, 196 * 12 * 11, 1_000_000, 10_000_000)] == [2, 3, 12, 72, 226]
    a = write_demo_glb(tmp_path / "grid.glb", lat=6)
    assert_valid(a.path)  # the Khronos glTF Validator, when installed
    doc, binary = _read_glb(a.path)
    assert (a.lat, a.triangles, a.vertices) == (6, 49 * 4 * 6 * 5, 49 * 7 * 13)

    def read(i, dtype, width):
        acc = doc["accessors"][i]
        view = doc["bufferViews"][acc["bufferView"]]
        x = np.frombuffer(binary, dtype, acc["count"] * width, view["byteOffset"] + acc.get("byteOffset", 0))
        return x.reshape(acc["count"], width)

    ref = demo_scene(16, 16)
    spheres = [n for n in doc["nodes"] if "mesh" in n]
    assert len(spheres) == 49 == len(ref.objects)
    for node, s in zip(spheres, ref.objects):
        np.testing.assert_allclose(node["translation"], np.asarray(s.center), atol=0)
        prim = doc["meshes"][node["mesh"]]["primitives"][0]
        pbr = doc["materials"][prim["material"]]["pbrMetallicRoughness"]
        np.testing.assert_allclose(pbr["baseColorFactor"][:3], np.asarray(s.material.base_color), rtol=1e-7)
        assert pbr["metallicFactor"] == pytest.approx(float(s.material.metallic))
        assert pbr["roughnessFactor"] == pytest.approx(float(s.material.roughness))
        P = read(prim["attributes"]["POSITION"], "<f4", 3).astype(np.float64)
        N = read(prim["attributes"]["NORMAL"], "<f4", 3).astype(np.float64)
        T = read(prim["indices"], "<u4", 1).reshape(-1, 3)
        assert len(T) == 4 * 6 * 5 and T.max() < len(P)
        np.testing.assert_allclose(np.linalg.norm(P, axis=1), 1.0, atol=1e-6)  # on the unit sphere
        np.testing.assert_allclose(N, P, atol=1e-6)  # smooth normals of a unit sphere
        tri = P[T]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        assert np.all(np.einsum("ij,ij->i", cross, tri.mean(1)) > 0)  # counter-clockwise seen from outside
    lights = doc["extensions"]["KHR_lights_punctual"]["lights"]
    placed = {tuple(n["translation"]): lights[n["extensions"]["KHR_lights_punctual"]["light"]] for n in doc["nodes"] if "extensions" in n}
    assert placed == {tuple(float(c) for c in np.asarray(lt.position)): {"type": "point", "color": [1.0, 1.0, 1.0], "intensity": 300.0}
                      for lt in ref.lights}
    cam = next(n for n in doc["nodes"] if "camera" in n)
    assert cam["translation"] == [0.0, 0.0, 24.0] and "rotation" not in cam  # looks down -Z
    assert doc["cameras"][0]["perspective"]["yfov"] == pytest.approx(np.radians(45.0))


def test_bench_gltf_tiny(tmp_path):
    from jaxpbr.cli import bench_gltf as bg

    r = bg.bench_gltf(3000, 40, 24, repeats=1, cold_runs=0)
    assert (r.triangles, r.vertices, r.rays) == (2352, 2205, 40 * 24)
    values = [*r.steps.values(), r.visibility_s, r.mesh_s, r.mesh_shadows_s, r.analytic_s, r.analytic_shadows_s,
              r.ratio, r.ratio_shadows, r.peak_rss]
    assert all(np.isfinite(v) and v > 0 for v in values), values
    assert set(r.steps) == {"write", "load", "build", "first_mesh", "first_analytic"}
    text = r.report()
    assert "jaxpbr bench render --gltf: the demo grid as 2,352 triangles" in text and "40x24" in text
    for s in ("load_gltf", "acceleration structure", "visibility of 960 primary rays", "without shadows", "with shadows",
              "target <= 0.5 s", "<= 1.5x", "peak resident memory"):
        assert s in text, s
    assert "whole process" not in text  # cold_runs=0
    # A whole-process run, here one the command line refuses at once: wall time, own peak memory, message.
    run = bg.run_process(["render", "--width", "0"], cache_dir=tmp_path, log_dir=tmp_path)
    assert run.returncode == 2 and "--width" in run.message
    assert np.isfinite(run.peak_rss) and run.peak_rss > 0 and run.wall_s > 0
    with pytest.raises(ValueError, match="triangles"):
        bg.bench_gltf(0)


def test_cli_bench_gltf_arguments(capsys):
    p = _parser()
    a = p.parse_args(["bench", "render", "--gltf"])
    assert (a.gltf, a.triangles, a.cold_runs, a.process_width, a.process_height, a.memory_triangles, a.repeats) == (
        True, 1_000_000, 3, 1280, 720, [], None)
    a = p.parse_args(["bench", "render", "--gltf", "--triangles", "5000", "--memory-triangles", "1000000,10_000_000"])
    assert (a.triangles, a.memory_triangles) == (5000, [1_000_000, 10_000_000])
    for bad in (["--memory-triangles", "0"], ["--triangles", "x"], ["--cold-runs", "-1"]):
        with pytest.raises(SystemExit) as e:
            p.parse_args(["bench", "render", "--gltf", *bad])
        assert e.value.code == 2


@pytest.mark.slow  # four cold and warm `jaxpbr render` processes and one more for the memory row
def test_cli_bench_gltf_processes(capsys, monkeypatch):
    from jaxpbr.cli import bench_gltf as bg

    args = _parser().parse_args(["bench", "render", "--gltf", "--triangles", "2000", "--width", "32", "--height", "18",
                                 "--repeats", "1", "--cold-runs", "1", "--process-width", "32", "--process-height", "18",
                                 "--memory-triangles", "5000"])
    results = []
    real = bg.bench_gltf
    monkeypatch.setattr(bg, "bench_gltf", lambda *a, **k: results.append(real(*a, **k)) or results[-1])
    assert args.func(args) == 0
    (r,) = results
    assert r.report() in capsys.readouterr().out
    for store in (r.cold, r.warm):
        assert set(store) == {"demo", "asset"}
        for runs in store.values():
            assert len(runs) == 1 and runs[0].returncode == 0 and runs[0].wall_s > 0 and runs[0].peak_rss > 0
    (m,) = r.memory
    assert (m.triangles, m.width, m.height) == (49 * 4 * 6 * 5, 32, 18) and m.run.returncode == 0 and m.run.peak_rss > 0
    text = r.report()
    for s in ("jaxpbr render --width 32 --height 18", "jaxpbr render ASSET.glb --environment procedural:sky", "cold", "warm",
              "asset - demo", "target <= 2.0 s", "memory, 5,880 triangles"):
        assert s in text, s


def test_extension_scenes_carry_their_group_on_every_sphere():
    from jaxpbr.cli.bench_extensions import (
        EXTENSION_MATERIALS,
        bench_extensions,
        extension_scene,
    )
    from jaxpbr.shading.material import EXTENSIONS

    assert set(EXTENSION_MATERIALS) == set(EXTENSIONS)  # every group the materials know is measured
    core = extension_scene(8, 6, ())
    assert all(ob.material.extensions == () for ob in core.objects)
    for g in EXTENSION_MATERIALS:
        sc = extension_scene(8, 6, (g,))
        assert len(sc.objects) == len(core.objects) == 49
        # the group's fields are set (volume acts through transmission, so it carries both), the
        # grid's metallic/roughness kept
        want = {"transmission", "volume"} if g == "volume" else {g}
        assert all(set(ob.material.extensions) == want for ob in sc.objects)
        assert [float(ob.material.roughness) for ob in sc.objects] == [float(ob.material.roughness) for ob in core.objects]
    with pytest.raises(ValueError, match="unknown extension group"):
        bench_extensions(8, 6, groups=("iridescence",))
    args = _parser().parse_args(["bench", "render", "--extensions", "--width", "64", "--height", "36"])
    assert args.extensions and (args.width, args.height) == (64, 36)


@pytest.mark.slow  # compiles a render per material
def test_bench_extensions_tiny():
    from jaxpbr.cli.bench_extensions import bench_extensions

    r = bench_extensions(24, 16, repeats=1, groups=("anisotropy", "sheen"))
    assert list(r.frame_s) == ["core", "anisotropy", "sheen"]
    assert all(r.finite.values()) and all(v > 0 for v in r.frame_s.values())
    assert r.ratio("core") == 1.0 and r.ratio("sheen") == r.frame_s["sheen"] / r.frame_s["core"]
    text = r.report()
    assert "24x16" in text and "anisotropy" in text and "x core" in text
