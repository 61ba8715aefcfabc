"""Size, sample-count and memory guards at every entry (command line, scene files, API), and
messages that name the flag or argument and the fix.

Huge sizes or sample counts aborted inside XLA (exit 134, `Check failed: buffer_.IsConcrete()`),
or ran the machine's memory up for minutes; every case here is refused before any work with one
line that names what to lower. The limit is pinned with JAXPBR_MEMORY_LIMIT so that the refusals
do not depend on this machine's free memory; each test takes milliseconds.
"""

from __future__ import annotations

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr import _memory
from jaxpbr.cli import main
from jaxpbr.ibl import envs
from jaxpbr.io import image

LIMIT_GB = "8"


@pytest.fixture(autouse=True)
def _limit(monkeypatch):
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", LIMIT_GB)


@pytest.fixture
def no_work(monkeypatch):
    """Every precompute and render fails loudly: a refusal must come before them."""
    import jaxpbr.cli.bench_grad as bench_grad
    import jaxpbr.cli.bench_ibl as bench_ibl
    import jaxpbr.cli.bench_render as bench_render
    import jaxpbr.cli.bench_shade as bench_shade
    import jaxpbr.cli.ibl as cli_ibl
    import jaxpbr.cli.render as cli_render
    import jaxpbr.cli.report_precompute as report_precompute
    import jaxpbr.cli.report_render as report_render

    def started(*a, **k):
        raise AssertionError("the work started before the input was refused")

    for mod, names in (
        (cli_ibl, ("prefilter", "irradiance", "brdf_lut")),
        (cli_render, ("render",)),
        (bench_shade, ("bench_shade",)),
        (bench_grad, ("bench_grad",)),
        (bench_ibl, ("bench_ibl", "load_environment")),
        (bench_render, ("make_ibl",)),
        (report_precompute, ("precompute_report",)),
        (report_render, ("render_report", "load_environment")),
    ):
        for name in names:
            monkeypatch.setattr(mod, name, started)


@pytest.fixture
def panorama(tmp_path):
    p = tmp_path / "in.exr"
    image.write(p, np.ones((16, 32, 3), np.float32))
    return p


def _one_error_line(capsys) -> str:
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("jaxpbr: error: "), err
    assert "Traceback" not in err[0] and "Check failed" not in err[0]
    return err[0]


# ------------------------------------------------------------------ command line: memory


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["prefilter", "{pano}", "--samples=4000000000", "-o", "{d}/p.ktx2"], "--samples"),
        (["prefilter", "{pano}", "--face-size", "16", "--samples=4000000000", "-o", "{d}/p.ktx2"], "--samples"),
        (["ibl", "{pano}", "--samples=4000000000", "--out-dir", "{d}"], "--samples"),
        (["lut", "--size", "8", "--samples", "4000000000", "-o", "{d}/l.exr"], "--samples"),
        (["report", "precompute", "--face-size", "1000000", "--quick", "--out", "{d}/rep"], "--face-size"),
        (["report", "render", "--face-size", "1000000", "--output-dir", "{d}"], "--face-size"),
        (["report", "render", "--pixels", "1000000", "--output-dir", "{d}"], "--pixels"),
        (["bench", "grad", "--face-size", "1000000"], "--face-size"),
        (["bench", "ibl", "--face-size", "1000000"], "--face-size"),
        (["bench", "ibl", "--baseline-samples", "4000000000"], "--baseline-samples"),
        (["bench", "render", "--face-size", "1000000"], "--face-size"),
        (["bench", "render", "--width", "1000000000", "--height", "1000000000"], "--width/--height"),
        (["bench", "shade", "--width", "1000000000", "--height", "1000000000"], "--width/--height"),
        (["render", "--width", "100000", "--height", "100000", "-o", "{d}/x.png"], "--width/--height"),
    ],
)
def test_huge_sizes_and_sample_counts_are_refused_naming_the_flag(tmp_path, panorama, capsys, no_work, argv, flag):
    out = tmp_path / "out"
    out.mkdir()
    argv = [a.format(d=out, pano=panorama) for a in argv]
    assert main(argv) == 2
    line = _one_error_line(capsys)
    assert "GB of memory" in line and f"lower {flag}" in line and "JAXPBR_MEMORY_LIMIT" in line, line
    assert list(out.iterdir()) == []


def test_scene_file_face_size_is_refused_naming_the_key(tmp_path, capsys, no_work):
    scene = tmp_path / "s.toml"
    scene.write_text('[camera]\nwidth = 32\nheight = 18\n[environment]\nfile = "procedural:sky"\nface_size = 1000000\n'
                     '[[objects]]\ntype = "sphere"\n')
    assert main(["render", str(scene), "-o", str(tmp_path / "x.png")]) == 2
    line = _one_error_line(capsys)
    assert "environment.face_size" in line and "GB of memory" in line and "JAXPBR_MEMORY_LIMIT" in line, line
    assert not (tmp_path / "x.png").exists()


def test_scene_file_prefilter_samples_are_refused_naming_the_key(tmp_path, capsys, no_work):
    scene = tmp_path / "s.toml"
    scene.write_text('[camera]\nwidth = 32\nheight = 18\n[render]\nprefilter_samples = 4000000000\n'
                     '[environment]\nfile = "procedural:sky"\nface_size = 16\n[[objects]]\ntype = "sphere"\n')
    assert main(["render", str(scene), "-o", str(tmp_path / "x.png")]) == 2
    line = _one_error_line(capsys)
    assert "lower render.prefilter_samples" in line and "GB of memory" in line, line


def test_a_texture_too_large_for_the_limit_is_refused_before_it_is_read(tmp_path, capsys, monkeypatch, no_work):
    """A 32x18 render with a large base-colour texture peaked far above JAXPBR_MEMORY_LIMIT: the
    texture's size (from its header) is part of the estimate."""
    tex = tmp_path / "tex.png"
    image.write(tex, np.zeros((512, 512, 3), np.float32))
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "0.01")  # 10 MB: a 512^2 RGB texture needs ~50 MB to load

    def read(*a, **k):
        raise AssertionError("the texture was read before the refusal")

    monkeypatch.setattr(image, "read", read)
    scene = tmp_path / "s.toml"
    scene.write_text('[camera]\nwidth = 32\nheight = 18\n[materials.m]\nbase_color_texture = "tex.png"\n'
                     '[[objects]]\ntype = "sphere"\nmaterial = "m"\n')
    assert main(["render", str(scene), "-o", str(tmp_path / "x.png")]) == 2
    line = _one_error_line(capsys)
    assert "base_color_texture" in line and "512x512 texture" in line and "GB of memory" in line, line


def test_textures_count_in_the_render_estimate(monkeypatch):
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "0.1")
    tex = np.zeros((4096, 4096, 3), np.float32)  # 50 MB as an array, ~0.5 GB in the render's estimate
    scene = jp.Scene(camera=jp.Camera(width=32, height=18),
                     objects=(jp.Sphere(material=jp.TexturedMaterial(base_color_texture=tex)),))
    with pytest.raises(ValueError, match=r"render: rendering 32x18 with 1 texture\(s\) needs about .* GB of memory.*lower the textures' resolution"):
        jp.render(scene)
    plain = jp.Scene(camera=jp.Camera(width=32, height=18), objects=(jp.Sphere(),))
    jp.rendering.renderer.check_memory(plain)  # the same image without the texture fits


# --------------------------------------------------------------------- command line: messages


def test_supersample_beyond_the_cap_is_refused_naming_the_flag(tmp_path, capsys, no_work):
    assert main(["render", "--supersample", "100000", "-o", str(tmp_path / "x.png")]) == 2
    line = _one_error_line(capsys)
    assert "--supersample 100000" in line and f"at most {jp.rendering.scene.MAX_SUPERSAMPLE}" in line, line
    with pytest.raises(ValueError, match=r"Camera.supersample must be <= 64"):
        jp.Camera(supersample=65)
    assert jp.Camera(supersample=64).supersample == 64


@pytest.mark.parametrize("samples", ["1000000000000", "4294967296"])
def test_samples_beyond_32_bits_name_the_flag_not_the_sampler(tmp_path, panorama, capsys, no_work, samples):
    assert main(["prefilter", str(panorama), f"--samples={samples}", "-o", str(tmp_path / "p.ktx2")]) == 2
    line = _one_error_line(capsys)
    assert f"--samples must be < 2**32, got {samples}" in line.replace(" (the sample points are a 32-bit sequence)", ""), line
    assert "hammersley" not in line


def test_too_many_levels_name_the_flag(tmp_path, panorama, capsys, no_work):
    assert main(["prefilter", str(panorama), "--levels=100", "-o", str(tmp_path / "p.ktx2")]) == 2
    line = _one_error_line(capsys)
    assert "--levels 100" in line and "at most 5 levels" in line and "lower --levels" in line, line


def test_an_image_given_as_the_scene_file_says_so(tmp_path, panorama, capsys):
    assert main(["render", str(panorama), "-o", str(tmp_path / "x.png")]) == 2
    line = _one_error_line(capsys)
    assert "is an image, not a scene file" in line and ".toml" in line and "UTF-8" not in line, line
    renamed = tmp_path / "scene.toml"  # the content decides too
    renamed.write_bytes(panorama.read_bytes())
    assert main(["render", str(renamed), "-o", str(tmp_path / "x.png")]) == 2
    assert "is an image, not a scene file" in _one_error_line(capsys)


# ------------------------------------------------------------------------------------ the API


@pytest.fixture(scope="module")
def small_env():
    return envs.sky_with_sun_cubemap(16, supersample=1)


def test_api_prefilter_refuses_huge_samples_naming_the_argument(small_env):
    with pytest.raises(ValueError, match=r"^prefilter: .* needs about .* GB of memory.*lower samples, or set JAXPBR_MEMORY_LIMIT"):
        jp.prefilter(small_env, samples=4_000_000_000)
    with pytest.raises(ValueError, match=r"^prefilter: samples must be < 2\*\*32 .* got 1000000000000"):
        jp.prefilter(small_env, samples=10**12)


def test_api_lut_irradiance_and_cubes_refuse_huge_sizes(small_env):
    with pytest.raises(ValueError, match=r"^compute_brdf_lut: .* GB of memory.*lower samples"):
        jp.brdf_lut(size=8, samples=4_000_000_000)
    with pytest.raises(ValueError, match=r"^compute_brdf_lut: .* GB of memory.*lower size"):
        jp.brdf_lut(size=100_000)
    with pytest.raises(ValueError, match=r"^irradiance: .* GB of memory.*lower size"):
        jp.irradiance(small_env, size=100_000)
    with pytest.raises(ValueError, match=r"^Cubemap.from_function: .* GB of memory.*lower face_size"):
        envs.sky_with_sun_cubemap(1_000_000)
    with pytest.raises(ValueError, match=r"^Cubemap.from_equirect: .* GB of memory.*lower face_size"):
        jp.Cubemap.from_equirect(np.ones((4, 8, 3), np.float32), 1_000_000)


def test_api_bake_and_render_refuse_before_any_work(small_env, monkeypatch):
    def started(*a, **k):
        raise AssertionError("a precompute started before the refusal")

    monkeypatch.setattr(jp.ibl.specular, "prefilter", started)
    monkeypatch.setattr(jp.ibl.extract, "extract_lights", started)
    env = jp.Environment(radiance=small_env)
    with pytest.raises(ValueError, match=r"^bake: .* GB of memory.*lower prefilter_samples"):
        jp.bake(env, prefilter_samples=4_000_000_000)
    with pytest.raises(ValueError, match=r"^bake: prefilter_samples must be < 2\*\*32"):
        jp.bake(env, prefilter_samples=10**12)
    with pytest.raises(ValueError, match=r"^bake: .* GB of memory.*lower lut_size"):
        jp.bake(env, lut_size=100_000)
    scene = jp.Scene(camera=jp.Camera(width=32, height=18), objects=(jp.Sphere(),), environment=env)
    with pytest.raises(ValueError, match=r"^render: .* GB of memory.*lower prefilter_samples"):
        jp.render(scene, prefilter_samples=4_000_000_000)
    huge = jp.Scene(camera=jp.Camera(width=100_000, height=100_000), objects=(jp.Sphere(),))
    with pytest.raises(ValueError, match=r"^render: rendering 100000x100000 needs .* lower Camera.width/height"):
        jp.render(huge)


def test_the_defaults_fit_in_modest_memory(monkeypatch):
    """The thresholds are measured costs, not caps that refuse real work: the default bake of a
    512^2 environment, the default demo render and the default LUT all pass a 2 GB limit."""
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "2")
    from jaxpbr.ibl.specular import (
        DEFAULT_SAMPLES,
        default_num_levels,
        default_sample_counts,
    )

    for S in (256, 512, 1024):
        counts = default_sample_counts(DEFAULT_SAMPLES, S, default_num_levels(S))
        _memory.require("prefilter", _memory.prefilter_bytes(S, S, counts))
    _memory.require("procedural sky", _memory.cube_bytes(256, supersample=4))
    _memory.require("panorama", _memory.cube_bytes(1024))
    _memory.require("lut", _memory.lut_bytes(256, 256, jp.shading.lut.DEFAULT_SAMPLES))
    _memory.require("irradiance", _memory.irradiance_bytes(64))
    demo = jp.demo.demo_scene(1280, 720)
    jp.rendering.renderer.check_memory(demo)
    # ... while the measured cost of a 1024^2 procedural sky (7.2 GB) is refused at 2 GB.
    with pytest.raises(ValueError, match="GB of memory"):
        _memory.require("procedural sky", _memory.cube_bytes(1024, supersample=4))


def test_the_limit_variable_is_checked(monkeypatch):
    for bad in ("lots", "0", "-1", "nan"):
        monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", bad)
        with pytest.raises(ValueError, match="JAXPBR_MEMORY_LIMIT must be a number of gigabytes"):
            _memory.available_memory()
    monkeypatch.setenv("JAXPBR_MEMORY_LIMIT", "1.5")
    assert _memory.available_memory() == 1.5e9


@pytest.mark.parametrize("field, value", [("roughness", "0.5"), ("base_color", ("a", "b", "c")), ("metallic", object())])
def test_material_with_a_non_number_names_the_field(field, value):
    with pytest.raises(TypeError, match=rf"^Material\.{field} must be a number or an array of numbers, got .*; pass e\.g\. {field}="):
        jp.Material(**{field: value})
