"""Scene TOML files (jaxpbr.rendering.scene_file): the examples load and render, values round-trip into the
Scene, every class of bad input gives a one-line message naming file, key path and fix."""

import math
from pathlib import Path

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.rendering.scene_file import SceneFile, hex_to_linear, load_scene, loads_scene
from jaxpbr.errors import InputError
from jaxpbr.io import image
from jaxpbr.rendering.scene import TexturedMaterial
from jaxpbr.shading.material import Material

EXAMPLES = Path(__file__).resolve().parent.parent / "examples" / "scenes"


def _srgb_to_linear(v):
    """IEC 61966-2-1 EOTF, written out independently of the code under test."""
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def _np(x):
    return np.asarray(x, np.float64)


# ------------------------------------------------------------------------------------------
# Examples
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def examples():
    return {name: load_scene(EXAMPLES / f"{name}.toml") for name in ("spheres", "textured", "extensions")}


@pytest.mark.parametrize("name", ["spheres", "textured", "extensions"])
def test_example_loads_and_renders(examples, name):
    sf = examples[name]
    assert isinstance(sf, SceneFile) and sf.path == EXAMPLES / f"{name}.toml"
    scene = sf.scene.replace(camera=sf.scene.camera.replace(width=24, height=16))
    # Tiny precompute: a 1x1 prefiltered face (no FIS levels) and a 4x4 irradiance map keep this fast.
    options = {**sf.options, "prefilter_size": 1, "irradiance_size": 4}
    img = np.asarray(jp.render(scene, **options))
    assert img.shape == (16, 24, 3)
    assert np.all(np.isfinite(img)) and img.min() >= 0.0 and img.max() > 0.0
    assert set(sf.output) == {"exposure", "tonemap", "encoding"}


def test_textured_example_decodes_textures(examples):
    sf = examples["textured"]
    tiles = sf.materials["tiles"]
    assert isinstance(tiles, TexturedMaterial)
    raw_base = image.read(EXAMPLES / "textures" / "checker_base_color.png")
    raw_orm = image.read(EXAMPLES / "textures" / "checker_orm.png")
    # Base colour (8-bit sRGB) is decoded to linear; ORM and normal maps are linear data as stored.
    expect = np.vectorize(_srgb_to_linear)(_np(raw_base[..., :3]))
    np.testing.assert_allclose(_np(tiles.base_color_texture), expect, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(_np(tiles.metallic_roughness_texture), raw_orm, atol=1e-7)
    np.testing.assert_allclose(_np(tiles.occlusion_texture), raw_orm, atol=1e-7)
    assert tiles.normal_texture.shape == (64, 64, 3)
    floor = sf.scene.objects[1]
    np.testing.assert_allclose(_np(floor.tangent), [1, 0, 0])
    assert float(floor.uv_scale) == 0.25


def test_example_textures_are_small():
    files = sorted((EXAMPLES / "textures").glob("*.png"))
    assert len(files) == 3
    for f in files:
        assert f.stat().st_size < 50_000, f


# ------------------------------------------------------------------------------------------
# Round trip
# ------------------------------------------------------------------------------------------

ROUND_TRIP = """
[render]
model = "gltf"
multiscatter = true
irradiance_size = 16
irradiance_method = "sh9"
prefilter_size = 4
prefilter_samples = 64
lut_size = 128
mapping = "quadratic"
dtype = "float32"
extract_lights = false

[output]
exposure = 1.5
tonemap = "reinhard"
encoding = "linear"

[camera]
position = [1.0, 2.0, 3.0]
target = [0.0, 0.5, 0.0]
up = [0, 1, 0]
fov_y_deg = 50
width = 40
height = 30
supersample = 2

[scene]
background = [0.1, 0.2, 0.3]
ambient = 0.03

[environment]
file = "procedural:sky"
face_size = 128
intensity = 0.7
rotation_deg = 90.0
show_background = false

[[lights]]
type = "point"
position = [1, 2, 3]
color = "#ff8000"
intensity = 12.5
range = 7.0

[[lights]]
type = "directional"
direction = [0, -1, 0]
intensity = 3.0

[[lights]]
type = "spot"
position = [0, 5, 0]
direction = [0, -1, 0]
color = [0.5, 0.25, 1.0]
intensity = 40
inner_cone_deg = 10
outer_cone_deg = 30

[materials.gold]
base_color = "#ffcc88"
metallic = 1.0
roughness = 0.3
occlusion = 0.9
emissive = [0.1, 0.2, 0.0]
emissive_strength = 2.0

[materials.tex]
base_color = [0.5, 1.0, 1.0]
metallic = 0.0
roughness = 0.5
base_color_texture = "t/base.png"
metallic_roughness_texture = "t/orm.png"
occlusion_texture = "t/orm.png"
normal_texture = "t/n.png"
normal_scale = 0.5
emissive_texture = "t/base.png"

[[objects]]
type = "sphere"
center = [1, 0, -1]
radius = 0.5
material = "gold"

[[objects]]
type = "sphere"
material = { base_color = [0.2, 0.3, 0.4], metallic = 0.0, roughness = 0.6 }

[[objects]]
type = "plane"
point = [0, -1, 0]
normal = [0, 1, 0]
tangent = [0, 0, 1]
uv_scale = 2.0
material = "tex"
"""


def _write_textures(d: Path):
    (d / "t").mkdir()
    codes = np.array([[[0, 10, 128], [200, 255, 64]], [[1, 2, 3], [250, 40, 90]]], np.float64) / 255.0
    image.write(d / "t" / "base.png", codes, encoding="linear")
    image.write(d / "t" / "orm.png", codes[::-1], encoding="linear")
    image.write(d / "t" / "n.png", np.full((2, 2, 3), [0.5, 0.5, 1.0]), encoding="linear")
    return codes


def test_round_trip(tmp_path):
    codes = _write_textures(tmp_path)
    f = tmp_path / "scene.toml"
    f.write_text(ROUND_TRIP)
    sf = load_scene(f)
    s = sf.scene
    assert sf.options == {
        "model": "gltf", "multiscatter": True, "irradiance_size": 16, "irradiance_method": "sh9",
        "prefilter_size": 4, "prefilter_samples": 64, "lut_size": 128, "mapping": "quadratic", "dtype": "float32",
        "extract_lights": False,
    }
    jp.RenderOptions(**sf.options)  # valid keywords
    assert sf.output == {"exposure": 1.5, "tonemap": "reinhard", "encoding": "linear"}

    cam = s.camera
    np.testing.assert_allclose(_np(cam.position), [1, 2, 3])
    np.testing.assert_allclose(_np(cam.target), [0, 0.5, 0])
    assert float(cam.fov_y_deg) == 50 and (cam.width, cam.height, cam.supersample) == (40, 30, 2)
    np.testing.assert_allclose(_np(s.background), [0.1, 0.2, 0.3])
    assert s.ambient == 0.03

    env = s.environment
    assert env.radiance.face_size == 128 and not env.show_background
    assert float(env.intensity) == pytest.approx(0.7)
    assert float(env.rotation) == pytest.approx(math.pi / 2)  # degrees in the file, radians in the Scene

    point, sun, spot = s.lights
    assert isinstance(point, jp.PointLight) and isinstance(sun, jp.DirectionalLight) and isinstance(spot, jp.SpotLight)
    np.testing.assert_allclose(_np(point.color), [1.0, _srgb_to_linear(128 / 255), 0.0], rtol=1e-6)
    assert float(point.intensity) == 12.5 and float(point.inv_range) == pytest.approx(1 / 7)
    np.testing.assert_allclose(_np(sun.direction), [0, -1, 0])
    assert float(sun.intensity) == 3.0 and float(sun.color[0]) == 1.0
    assert float(spot.inner_cone_angle) == pytest.approx(math.radians(10))
    assert float(spot.outer_cone_angle) == pytest.approx(math.radians(30))
    np.testing.assert_allclose(_np(spot.color), [0.5, 0.25, 1.0])

    gold = s.objects[0].material
    assert isinstance(gold, Material) and gold is sf.materials["gold"]
    np.testing.assert_allclose(_np(gold.base_color), hex_to_linear("#ffcc88"), rtol=1e-6)
    np.testing.assert_allclose(
        [_np(gold.metallic), _np(gold.roughness), _np(gold.occlusion)], [1.0, 0.3, 0.9], rtol=1e-6
    )
    np.testing.assert_allclose(_np(gold.emission()), [0.2, 0.4, 0.0], rtol=1e-6)  # emissive * strength
    np.testing.assert_allclose(_np(s.objects[0].center), [1, 0, -1])
    assert float(s.objects[0].radius) == 0.5

    inline = s.objects[1].material
    np.testing.assert_allclose(_np(inline.base_color), [0.2, 0.3, 0.4], rtol=1e-6)
    np.testing.assert_allclose(_np(s.objects[1].center), [0, 0, 0])  # Sphere defaults
    assert float(s.objects[1].radius) == 1.0

    plane = s.objects[2]
    np.testing.assert_allclose(_np(plane.point), [0, -1, 0])
    np.testing.assert_allclose(_np(plane.tangent), [0, 0, 1])
    assert float(plane.uv_scale) == 2.0
    tex = plane.material
    assert isinstance(tex, TexturedMaterial) and float(tex.normal_scale) == 0.5
    np.testing.assert_allclose(_np(tex.factors.base_color), [0.5, 1, 1], rtol=1e-6)
    # sRGB-decoded base colour and emissive; linear ORM (same file -> same array for both roles).
    np.testing.assert_allclose(_np(tex.base_color_texture), np.vectorize(_srgb_to_linear)(codes), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(_np(tex.emissive_texture), _np(tex.base_color_texture), rtol=1e-6)
    np.testing.assert_allclose(_np(tex.metallic_roughness_texture), codes[::-1], atol=1e-6)
    np.testing.assert_allclose(_np(tex.occlusion_texture), codes[::-1], atol=1e-6)
    np.testing.assert_allclose(_np(tex.normal_texture)[0, 0], [128 / 255, 128 / 255, 1.0], atol=1e-6)


def test_defaults_and_learnopengl_output():
    sf = loads_scene('[render]\nmodel = "learnopengl"\n[[objects]]\ntype = "sphere"\n', ".")
    assert sf.output == {"exposure": 0.0, "tonemap": "reinhard", "encoding": "gamma2.2"}
    assert sf.options == {"model": "learnopengl"} and sf.path is None
    s = sf.scene
    assert s.environment is None and s.lights == () and (s.camera.width, s.camera.height) == (1280, 720)
    m = s.objects[0].material  # glTF defaults
    assert float(m.metallic) == 1.0 and float(m.roughness) == 1.0
    sf = loads_scene('[[objects]]\ntype = "plane"\n', ".")
    assert sf.output == {"exposure": 0.0, "tonemap": "aces", "encoding": "srgb"}


# ------------------------------------------------------------------------------------------
# Hex colours
# ------------------------------------------------------------------------------------------


def test_orthographic_camera_keys():
    sf = loads_scene('[camera]\nprojection = "orthographic"\nymag = 2.5\n' + SPHERE, ".")
    assert sf.scene.camera.projection == "orthographic" and float(sf.scene.camera.ymag) == 2.5
    with pytest.raises(Exception, match="camera.projection"):
        loads_scene('[camera]\nprojection = "fisheye"\n' + SPHERE, ".")
    with pytest.raises(Exception, match="camera.ymag"):
        loads_scene('[camera]\nymag = 0\n' + SPHERE, ".")


@pytest.mark.parametrize("hexstr", ["#ffcc88", "#000000", "#FFFFFF", "#0a0b0c", "#808080", "#0B1F2e"])
def test_hex_colour_decoding(hexstr):
    codes = [int(hexstr[i : i + 2], 16) / 255 for i in (1, 3, 5)]
    expect = [_srgb_to_linear(v) for v in codes]
    np.testing.assert_allclose(hex_to_linear(hexstr), expect, rtol=1e-12, atol=0)
    # and against the library's sRGB EOTF
    np.testing.assert_allclose(hex_to_linear(hexstr), np.asarray(jp.color.srgb_decode(np.array(codes))), rtol=1e-6)


def test_hex_colour_known_value():
    # 0x80 = 128 -> ((128/255 + 0.055)/1.055)^2.4 = 0.2158605...
    assert hex_to_linear("#808080") == pytest.approx((0.21586050011389926,) * 3, rel=1e-12)


# ------------------------------------------------------------------------------------------
# Errors
# ------------------------------------------------------------------------------------------

SPHERE = '[[objects]]\ntype = "sphere"\n'
GOLD = "[materials.gold]\nmetallic = 1.0\nroughness = 0.2\n"

ERRORS = {
    "syntax": ("[camera]\nwidth = = 3\n" + SPHERE, ["invalid TOML", "line 2", "fix the syntax"]),
    "syntax_dup": ("[camera]\nwidth = 1\nwidth = 2\n" + SPHERE, ["invalid TOML", "line 3"]),
    "unknown_table": ("[camra]\nwidth = 10\n" + SPHERE, ["camra: unknown table; did you mean 'camera'?"]),
    "unknown_key": (
        "[materials.gold]\nroughnes = 0.3\n" + SPHERE,
        ["materials.gold.roughnes: unknown key (not a key of a material); did you mean 'roughness'?"],
    ),
    "unknown_key_object": (
        SPHERE + "centre = [0, 0, 0]\n", ["objects[0].centre: unknown key (not a key of a sphere); did you mean 'center'?"]
    ),
    "moved_key": ("[render]\nexposure = 1.0\n" + SPHERE, ["render.exposure: unknown key", "belongs in [output]"]),
    "renamed_key": ("[environment]\nfile = 'procedural:sky'\nbackground = false\n" + SPHERE,
                    ["environment.background: unknown key", "did you mean 'show_background'?"]),
    "unknown_key_light": (
        '[[lights]]\ntype = "point"\nposition = [0, 1, 0]\ndirection = [0, -1, 0]\n' + SPHERE,
        ["lights[0].direction: unknown key (not a key of a point light)"],
    ),
    "wrong_type_radius": (
        SPHERE * 2 + SPHERE + 'radius = "1"\n', ["objects[2].radius: expected a number, got a string ('1')"]
    ),
    "wrong_type_width": ("[camera]\nwidth = 64.0\n" + SPHERE, ["camera.width: expected an integer, got a float (64.0); write 64"]),
    "wrong_type_bool": ("[render]\nmultiscatter = 1\n" + SPHERE, ["render.multiscatter: expected true or false, got an integer"]),
    "wrong_type_extract": ('[render]\nextract_lights = "no"\n' + SPHERE, ["render.extract_lights: expected true or false"]),
    "wrong_type_table": ("[objects]\ntype = 'sphere'\n", ["objects: expected an array of tables", "[[objects]]"]),
    "wrong_type_material_table": ("[materials]\nroughness = 0.5\n" + SPHERE, ["materials.roughness: expected a table", "[materials.NAME]"]),
    "vector_length": ("[camera]\nposition = [0, 1]\n" + SPHERE, ["camera.position: expected an array of 3 numbers, got 2"]),
    "vector_element": ("[camera]\ntarget = [0, 'a', 0]\n" + SPHERE, ["camera.target[1]: expected a number, got a string"]),
    "colour_length": (GOLD + "base_color = [1, 0]\n" + SPHERE, ["materials.gold.base_color: expected [r, g, b] (linear) or an sRGB hex"]),
    "bad_hex": (GOLD + 'base_color = "#ffcc8"\n' + SPHERE, ["materials.gold.base_color:", "'#ffcc8'", '"#rrggbb"']),
    "range_roughness": ("[materials.gold]\nroughness = 1.5\n" + SPHERE, ["materials.gold.roughness: must be <= 1, got 1.5"]),
    "range_radius": (SPHERE + "radius = 0\n", ["objects[0].radius: must be > 0, got 0"]),
    "range_intensity": ('[[lights]]\ntype = "directional"\ndirection = [0, -1, 0]\nintensity = -2\n' + SPHERE,
                        ["lights[0].intensity: must be >= 0, got -2"]),
    "range_fov": ("[camera]\nfov_y_deg = 180\n" + SPHERE, ["camera.fov_y_deg: must be <= 179"]),
    "range_nan": ("[camera]\nfov_y_deg = nan\n" + SPHERE, ["camera.fov_y_deg: expected a finite number"]),
    "zero_direction": ('[[lights]]\ntype = "directional"\ndirection = [0, 0, 0]\n' + SPHERE,
                       ["lights[0].direction: must be a non-zero vector"]),
    "spot_cones": ('[[lights]]\ntype = "spot"\nposition = [0, 1, 0]\ndirection = [0, -1, 0]\n'
                   "inner_cone_deg = 40\nouter_cone_deg = 30\n" + SPHERE,
                   ["lights[0].inner_cone_deg: must be smaller than outer_cone_deg (30)", "degrees"]),
    "light_missing_field": ('[[lights]]\ntype = "spot"\nposition = [0, 1, 0]\n' + SPHERE,
                            ["lights[0]: a spot light needs direction = [x, y, z]"]),
    "light_unknown_type": ('[[lights]]\ntype = "area"\n' + SPHERE, ["lights[0].type: unknown value 'area'", "'point'"]),
    # Constructors' ValueErrors come back with the key path prefixed.
    "ctor_camera_up": ("[camera]\nposition = [0, 5, 0]\ntarget = [0, 0, 0]\nup = [0, 1, 0]\n" + SPHERE,
                       ["camera.up: Camera.up must not be parallel to the viewing direction"]),
    "ctor_camera_target": ("[camera]\nposition = [1, 1, 1]\ntarget = [1, 1, 1]\n" + SPHERE,
                           ["camera.target: Camera.target must differ from Camera.position"]),
    "ctor_render_options": ('[render]\nmodel = "learnopengl"\nmultiscatter = true\n' + SPHERE,
                            ["render.multiscatter: multiscatter is defined for the gltf model only"]),
    "unknown_model": ('[render]\nmodel = "gltf2"\n' + SPHERE, ["render.model: unknown value 'gltf2'", "did you mean 'gltf'?"]),
    "unknown_material": (GOLD + SPHERE + 'material = "gld"\n',
                         ["objects[0].material: unknown material 'gld'; did you mean 'gold'? defined: 'gold'"]),
    "unknown_material_none": (SPHERE + 'material = "gold"\n',
                              ["objects[0].material: unknown material 'gold': no [materials.*] are defined"]),
    "inline_material_error": (SPHERE + "material = { metallic = 2.0 }\n", ["objects[0].material.metallic: must be <= 1, got 2"]),
    "missing_object_type": ("[[objects]]\nradius = 1.0\n", ['objects[0]: missing key "type"', 'type = "sphere", "plane" or "gltf"']),
    "unknown_object_type": ('[[objects]]\ntype = "spher"\n', ["objects[0].type: unknown value 'spher'", "did you mean 'sphere'?"]),
    "no_objects": ("[camera]\nwidth = 10\n", ["objects: the scene has no objects; add at least one [[objects]]"]),
    "missing_texture": (GOLD + 'base_color_texture = "tex/albedo.png"\n' + SPHERE,
                        ["materials.gold.base_color_texture: file '{dir}/tex/albedo.png' does not exist",
                         "relative to the scene file's folder"]),
    "missing_env": ('[environment]\nfile = "skies/sky.hdr"\n' + SPHERE,
                    ["environment.file: file '{dir}/skies/sky.hdr' does not exist"]),
    "missing_env_face": ("[environment]\nfiles = ['a.hdr', 'b.hdr', 'c.hdr', 'd.hdr', 'e.hdr', 'f.hdr']\n" + SPHERE,
                         ["environment.files[0]: file '{dir}/a.hdr' does not exist"]),
    "env_face_count": ("[environment]\nfiles = ['a.hdr', 'b.hdr']\n" + SPHERE,
                       ["environment.files: expected an array of 6 face images (+X, -X, +Y, -Y, +Z, -Z), got 2 paths"]),
    "env_both": ("[environment]\nfile = 'procedural:sky'\nfiles = []\n" + SPHERE, ["environment: give exactly one of file", "not both"]),
    "env_unknown_procedural": ('[environment]\nfile = "procedural:sunset"\n' + SPHERE,
                               ["environment.file: unknown procedural environment 'procedural:sunset'"]),
    "normal_scale_alone": (GOLD + "normal_scale = 2.0\n" + SPHERE, ["materials.gold.normal_scale: has no effect without normal_texture"]),
}


@pytest.mark.parametrize("case", sorted(ERRORS))
def test_error_messages(tmp_path, case):
    text, expected = ERRORS[case]
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(InputError) as info:
        load_scene(f)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(f"{f}: "), msg
    for part in expected:
        assert part.format(dir=tmp_path.resolve()) in msg, msg
    assert isinstance(info.value, ValueError)


def test_error_prefilter_size_vs_environment():
    text = '[render]\nprefilter_size = 48\n[environment]\nfile = "procedural:sky"\nface_size = 128\n' + SPHERE
    with pytest.raises(InputError, match=r"^s\.toml: render\.prefilter_size: 48 must be the environment's face size 128 divided by a power of two"):
        loads_scene(text, ".", name="s.toml")


def test_error_texture_channels_and_range(tmp_path):
    image.write(tmp_path / "grey.png", np.full((2, 2), 0.5), encoding="linear")
    text = GOLD + 'metallic_roughness_texture = "grey.png"\n' + SPHERE
    with pytest.raises(InputError, match=r"materials\.gold\.metallic_roughness_texture: .*grey\.png' has 1 channel\(s\); it must hold glTF packing G = roughness, B = metallic"):
        loads_scene(text, tmp_path, name="t.toml")
    # A constructor's range check (linear EXR base colour above 1) is prefixed with the key path.
    image.write(tmp_path / "hot.exr", np.full((2, 2, 3), 2.0, np.float32))
    text = GOLD + 'base_color_texture = "hot.exr"\n' + SPHERE
    with pytest.raises(InputError, match=r"^t\.toml: materials\.gold\.base_color_texture: base_color_texture must hold linear values in \[0.0, 1.0\]"):
        loads_scene(text, tmp_path, name="t.toml")
    # An unreadable (corrupt) texture.
    (tmp_path / "junk.png").write_bytes(b"not a png")
    text = GOLD + 'normal_texture = "junk.png"\n' + SPHERE
    with pytest.raises(InputError, match=r"materials\.gold\.normal_texture: cannot read .*junk\.png"):
        loads_scene(text, tmp_path, name="t.toml")


def test_error_scene_file_missing(tmp_path):
    with pytest.raises(InputError, match=r"scene file .*nope\.toml' does not exist"):
        load_scene(tmp_path / "nope.toml")


# ------------------------------------------------------------------------------------------
# glTF material extensions (KHR_materials_*): factors, textures, errors, the example
# ------------------------------------------------------------------------------------------

# key = TOML value -> (Material field, expected value)
EXT_KEYS = {
    "clearcoat": ("0.8", "clearcoat", 0.8),
    "clearcoat_roughness": ("0.3", "clearcoat_roughness", 0.3),
    "sheen_color": ("[0.9, 0.2, 0.2]", "sheen_color", (0.9, 0.2, 0.2)),
    "sheen_roughness": ("0.45", "sheen_roughness", 0.45),
    "specular": ("0.6", "specular", 0.6),
    "specular_color": ("[1.5, 1.0, 0.25]", "specular_color", (1.5, 1.0, 0.25)),  # > 1 allowed (spec)
    "ior": ("1.33", "ior", 1.33),
    "anisotropy_strength": ("0.7", "anisotropy_strength", 0.7),
    "anisotropy_rotation_deg": ("90", "anisotropy_rotation", math.pi / 2),  # degrees -> radians
    "transmission": ("1.0", "transmission", 1.0),
    "thickness": ("2.5", "thickness", 2.5),
    "attenuation_distance": ("inf", "attenuation_distance", math.inf),
    "attenuation_color": ('"#ff8000"', "attenuation_color", (1.0, _srgb_to_linear(128 / 255), 0.0)),
}


@pytest.mark.parametrize("key", sorted(EXT_KEYS))
def test_extension_key_sets_its_material_field(key):
    value, field, expect = EXT_KEYS[key]
    sf = loads_scene(f"[materials.m]\n{key} = {value}\n" + SPHERE + 'material = "m"\n', ".")
    m = sf.materials["m"]
    assert isinstance(m, Material)
    np.testing.assert_allclose(_np(getattr(m, field)), expect, rtol=1e-6)
    # Only that extension is present; the others are absent (None: no code compiled for them).
    from jaxpbr.shading.material import EXTENSION_FIELDS

    group = next(g for g, fs in EXTENSION_FIELDS.items() if field in fs)
    assert m.extensions == (group,)
    assert sum(getattr(m, f) is not None for fs in EXTENSION_FIELDS.values() for f in fs) == 1
    assert sf.scene.objects[0].material is m


def test_material_without_extension_keys_has_none():
    m = loads_scene(GOLD + SPHERE, ".").materials["gold"]
    assert m.extensions == ()


def test_emissive_strength_multiplies_the_emission():
    """KHR_materials_emissive_strength is its own field; alone it keeps the core shading path
    (Material.layered is False: every model, multiscatter)."""
    sf = loads_scene('[materials.m]\nemissive = [0.1, 0.2, 0.0]\nemissive_strength = 20.0\n' + SPHERE, ".")
    m = sf.materials["m"]
    np.testing.assert_allclose(_np(m.emission()), [2.0, 4.0, 0.0], rtol=1e-6)
    assert m.extensions == ("emissive_strength",) and not m.layered
    # Without an emissive factor or texture (black) the strength changes nothing.
    sf = loads_scene('[materials.m]\nemissive_strength = 3.0\n' + SPHERE, ".")
    np.testing.assert_allclose(_np(sf.materials["m"].emission()), [0.0, 0.0, 0.0])


def _toml_value(x, field):
    """A Material field's value as TOML (the writer side of the round trip)."""
    a = np.asarray(x, np.float64)
    if field == "anisotropy_rotation":
        return repr(math.degrees(float(a)))
    if a.ndim:
        return "[" + ", ".join(repr(float(c)) for c in a) + "]"
    return "inf" if np.isinf(a) else repr(float(a))


def _material_toml(m: Material) -> str:
    lines = []
    for f in jp.Material.__dataclass_fields__:
        x = getattr(m, f)
        if x is not None:
            key = "anisotropy_rotation_deg" if f == "anisotropy_rotation" else f
            lines.append(f"{key} = {_toml_value(x, f)}")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("seed", range(3))
def test_every_material_field_round_trips(seed):
    """Every Material field, written as its TOML key and read back, is the same (no field is
    inexpressible; degrees <-> radians and inf survive)."""
    rng = np.random.default_rng(seed)
    u = lambda: float(rng.uniform(0, 1))  # noqa: E731
    rgb = lambda: tuple(float(c) for c in rng.uniform(0, 1, 3))  # noqa: E731
    m = Material(
        base_color=rgb(), metallic=u(), roughness=u(), occlusion=u(), emissive=rgb(), clearcoat=u(),
        clearcoat_roughness=u(), sheen_color=rgb(), sheen_roughness=u(), specular=u(),
        specular_color=tuple(2 * c for c in rgb()), ior=1 + 2 * u(), anisotropy_strength=u(),
        anisotropy_rotation=float(rng.uniform(-3, 3)), emissive_strength=10 * u(), transmission=u(),
        thickness=5 * u(), attenuation_distance=math.inf if seed == 0 else 0.1 + u(), attenuation_color=rgb(),
    )
    back = loads_scene("[materials.m]\n" + _material_toml(m) + SPHERE, ".").materials["m"]
    assert back.extensions == m.extensions
    np.testing.assert_allclose(_np(back.emission()), _np(m.emission()), rtol=1e-6)
    for f in jp.Material.__dataclass_fields__:
        if True:
            np.testing.assert_allclose(_np(getattr(back, f)), _np(getattr(m, f)), rtol=1e-6, err_msg=f)


def _write_ext_textures(d: Path):
    """RGBA PNG codes (so each channel differs), a 3-channel PNG, and an RGBA EXR."""
    codes = np.array([[[0, 60, 128, 255], [200, 255, 64, 30]], [[1, 2, 3, 4], [250, 40, 90, 170]]], np.float64) / 255.0
    image.write(d / "rgba.png", codes, encoding="linear")
    image.write(d / "rgb.png", codes[..., :3], encoding="linear")
    image.write(d / "flat_n.png", np.full((2, 2, 3), [0.5, 0.5, 1.0]), encoding="linear")
    image.write(d / "rgba.exr", codes.astype(np.float32))
    return codes


EXT_TEXTURE_TOML = """
[materials.t]
clearcoat = 1.0
clearcoat_roughness = 0.5
clearcoat_texture = "rgba.png"
clearcoat_roughness_texture = "rgba.png"
clearcoat_normal_texture = "flat_n.png"
clearcoat_normal_scale = 0.7
sheen_color = [1.0, 1.0, 1.0]
sheen_roughness = 1.0
sheen_color_texture = "rgba.png"
sheen_roughness_texture = "rgba.png"
specular_texture = "rgba.png"
specular_color_texture = "rgb.png"
anisotropy_strength = 1.0
anisotropy_rotation_deg = 30
anisotropy_texture = "rgb.png"
transmission = 1.0
transmission_texture = "rgba.exr"
thickness = 2.0
thickness_texture = "rgb.png"
"""


def test_extension_textures_parse(tmp_path):
    codes = _write_ext_textures(tmp_path)
    sf = loads_scene(EXT_TEXTURE_TOML + SPHERE + 'material = "t"\n', tmp_path)
    tm = sf.materials["t"]
    assert isinstance(tm, TexturedMaterial) and sf.scene.objects[0].material is tm
    srgb = np.vectorize(_srgb_to_linear)
    # Colour textures (sheen colour, specular colour) are sRGB-decoded PNGs, RGB only.
    np.testing.assert_allclose(_np(tm.sheen_color_texture), srgb(codes[..., :3]), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(_np(tm.specular_color_texture), srgb(codes[..., :3]), rtol=1e-5, atol=1e-7)
    # Data textures are linear, all their channels kept (the alpha of the A-channel ones).
    for name in ("clearcoat_texture", "clearcoat_roughness_texture", "sheen_roughness_texture", "specular_texture",
                 "transmission_texture"):
        np.testing.assert_allclose(_np(getattr(tm, name)), codes, atol=1e-6, err_msg=name)
    for name in ("anisotropy_texture", "thickness_texture"):
        np.testing.assert_allclose(_np(getattr(tm, name)), codes[..., :3], atol=1e-6, err_msg=name)
    np.testing.assert_allclose(_np(tm.clearcoat_normal_texture)[0, 0], [128 / 255, 128 / 255, 1.0], atol=1e-6)
    assert float(tm.clearcoat_normal_scale) == pytest.approx(0.7)
    assert float(tm.normal_scale) == 1.0 and tm.normal_texture is None
    f = tm.factors
    # specular / specular_color were not given: their textures make the extension present with the
    # glTF default factors (1, [1, 1, 1]).
    assert float(f.specular) == 1.0 and tuple(_np(f.specular_color)) == (1.0, 1.0, 1.0)
    assert float(f.anisotropy_rotation) == pytest.approx(math.radians(30))
    assert set(f.extensions) == {"clearcoat", "sheen", "specular", "anisotropy", "transmission", "volume"}
    assert f.attenuation_distance is None  # volume present; its unset fields take neutral values later


EXT_ERRORS = {
    "range_clearcoat": ("clearcoat = 1.5\n", "materials.gold.clearcoat: must be <= 1, got 1.5"),
    "range_clearcoat_roughness": ("clearcoat_roughness = -0.1\n", "materials.gold.clearcoat_roughness: must be >= 0, got -0.1"),
    "range_sheen_color": ("sheen_color = [1.2, 0, 0]\n", "materials.gold.sheen_color[0]: must be <= 1, got 1.2"),
    "range_sheen_roughness": ("sheen_roughness = 2\n", "materials.gold.sheen_roughness: must be <= 1, got 2"),
    "range_specular": ("specular = 1.01\n", "materials.gold.specular: must be <= 1"),
    "range_specular_color": ("specular_color = [1, -1, 1]\n", "materials.gold.specular_color[1]: must be >= 0, got -1"),
    "range_ior": ("ior = 0.5\n", "materials.gold.ior: must be >= 1 (an index of refraction"),
    "range_anisotropy": ("anisotropy_strength = -1\n", "materials.gold.anisotropy_strength: must be >= 0"),
    "range_emissive_strength": ("emissive_strength = -2\n", "materials.gold.emissive_strength: must be >= 0, got -2"),
    "range_transmission": ("transmission = 3\n", "materials.gold.transmission: must be <= 1, got 3"),
    "range_thickness": ("thickness = -0.5\n", "materials.gold.thickness: must be >= 0, got -0.5"),
    "range_attenuation_distance": ("attenuation_distance = 0\n", "materials.gold.attenuation_distance: must be > 0, got 0"),
    "neg_inf_attenuation_distance": ("attenuation_distance = -inf\n", "materials.gold.attenuation_distance: must be > 0"),
    "inf_thickness": ("thickness = inf\n", "materials.gold.thickness: expected a finite number, got inf"),
    "range_attenuation_color": ("attenuation_color = [0.5, 0.5, 2]\n", "materials.gold.attenuation_color[2]: must be <= 1, got 2"),
    "type_clearcoat": ('clearcoat = "1"\n', "materials.gold.clearcoat: expected a number, got a string ('1')"),
    "type_sheen_color": ("sheen_color = 0.5\n", 'materials.gold.sheen_color: expected [r, g, b] (linear) or an sRGB hex'),
    "type_rotation": ("anisotropy_rotation_deg = true\n", "materials.gold.anisotropy_rotation_deg: expected a number, got a boolean"),
    "radians_name": ("anisotropy_rotation = 1.57\n", "materials.gold.anisotropy_rotation: unknown key: angles are in degrees in scene files; write anisotropy_rotation_deg"),
    "misspelt": ("clearcoat_roughnes = 0.2\n", "materials.gold.clearcoat_roughnes: unknown key (not a key of a material); did you mean 'clearcoat_roughness'?"),
    "misspelt_texture": ('sheen_colour_texture = "a.png"\n', "did you mean 'sheen_color_texture'?"),
    "texture_without_factor": ('clearcoat_texture = "rgba.png"\n', "materials.gold.clearcoat_texture: has no effect without clearcoat, which defaults to 0 (KHR_materials_clearcoat; the texture multiplies it); add clearcoat = 1.0"),
    "texture_without_colour_factor": ('sheen_color_texture = "rgba.png"\n', "materials.gold.sheen_color_texture: has no effect without sheen_color", ),
    "colour_factor_hint": ('sheen_color_texture = "rgba.png"\n', "add sheen_color = [1.0, 1.0, 1.0]"),
    "coat_normal_without_coat": ('clearcoat_normal_texture = "flat_n.png"\n', "materials.gold.clearcoat_normal_texture: has no effect without clearcoat"),
    "thickness_texture_without_thickness": ('transmission = 1.0\nthickness_texture = "rgb.png"\n', "materials.gold.thickness_texture: has no effect without thickness, which defaults to 0 (KHR_materials_volume"),
    "coat_scale_alone": ("clearcoat = 1.0\nclearcoat_normal_scale = 2.0\n", "materials.gold.clearcoat_normal_scale: has no effect without clearcoat_normal_texture"),
    "alpha_channel_missing": ('specular_texture = "rgb.png"\n', "materials.gold.specular_texture: '{dir}/rgb.png' has 3 channel(s); it must hold A = specular: an RGBA image"),
    "alpha_channel_missing_sheen": ('sheen_roughness = 1.0\nsheen_roughness_texture = "rgb.png"\n', "it must hold A = sheen roughness: an RGBA image"),
    "texture_range_exr": ('transmission = 1.0\ntransmission_texture = "hot.exr"\n', "materials.gold.transmission_texture: transmission_texture must hold linear values in [0.0, 1.0]"),
    "missing_texture_file": ('clearcoat = 1.0\nclearcoat_texture = "nope.png"\n', "materials.gold.clearcoat_texture: file '{dir}/nope.png' does not exist"),
}


@pytest.mark.parametrize("case", sorted(EXT_ERRORS))
def test_extension_error_messages(tmp_path, case):
    _write_ext_textures(tmp_path)
    image.write(tmp_path / "hot.exr", np.full((2, 2, 3), 2.0, np.float32))
    keys, expected = EXT_ERRORS[case]
    f = tmp_path / "bad.toml"
    f.write_text(GOLD + keys + SPHERE)
    with pytest.raises(InputError) as info:
        load_scene(f)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{f}: "), msg
    assert expected.format(dir=tmp_path.resolve()) in msg, msg


def test_inline_material_extension_errors_name_the_object():
    with pytest.raises(InputError, match=r"objects\[0\]\.material\.anisotropy_rotation: unknown key: angles are in degrees"):
        loads_scene(SPHERE + "material = { anisotropy_rotation = 1.0 }\n", ".", name="s.toml")
    with pytest.raises(InputError, match=r"objects\[0\]\.material\.ior: must be >= 1"):
        loads_scene(SPHERE + "material = { ior = 0.9 }\n", ".", name="s.toml")
    # ior = 0 is glTF's specular-glossiness mode (F = 1): allowed.
    m = loads_scene(SPHERE + "material = { ior = 0.0 }\n", ".").scene.objects[0].material
    assert float(m.ior) == 0.0


def test_extensions_example_parses():
    """examples/scenes/extensions.toml: a 5 x 8 grid, one row per extension, under the sky."""
    sf = load_scene(EXAMPLES / "extensions.toml")
    objs = sf.scene.objects
    assert len(objs) == 40 and all(isinstance(o, jp.Sphere) for o in objs)
    rows = [objs[5 * r : 5 * r + 5] for r in range(8)]
    expect = ["clearcoat", "sheen", "specular", "ior", "anisotropy", "transmission", "volume", "emissive_strength"]
    for name, row in zip(expect, rows):
        groups = {o.material.extensions for o in row}
        if name == "emissive_strength":  # emission beyond 1, on the core shading path
            assert groups == {("emissive_strength",)} and max(float(np.max(_np(o.material.emission()))) for o in row) > 1
        else:
            assert len(groups) == 1 and name in groups.pop(), name
        ys = {float(o.center[1]) for o in row}
        assert len(ys) == 1  # a row
        # the main parameter varies across the row
        assert len({repr(o.material) for o in row}) == 5, name
    assert sf.options["model"] == "gltf" and sf.scene.environment is not None
    cam = sf.scene.camera
    assert cam.width * cam.height <= 480 * 768
