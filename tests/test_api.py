"""The public API, in the style of dm_pix's API test: data positional, options keyword-only; one
model registry that every entry point reads; distinct Smith names; render options as a value.

The signature check walks `jaxpbr.__all__` and the `__all__` of the public modules, inspects every
function (and the constructors of the public classes) with `inspect.signature`, and fails for a
parameter that is an option but can be passed positionally. A positional parameter is taken to be
an option if it has a default value or an option's name (`OPTION_NAMES`); `DATA` is the declared
allow-list of positional parameters that are data (or the one leading size of a constructor users pass
positionally: `Cubemap.from_equirect(img, 256)`). The precomputes' sizes are options, keyword-only:
`jp.irradiance(env, size=32)`, `jp.prefilter(env, size=128)`, `jp.brdf_lut(size=128)`.
"""

import dataclasses
import importlib
import inspect
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.rendering.renderer import RenderOptions
from jaxpbr.shading.brdf_terms import MODEL_REGISTRY, OPTION_CHOICES, OPTION_DEFAULTS

MODULES = [
    "jaxpbr",
    "jaxpbr.io.atomic",
    "jaxpbr.shading.brdf_terms",
    "jaxpbr.color",
    "jaxpbr.ibl.cubemap",
    "jaxpbr.rendering.demo",
    "jaxpbr.ibl.diffuse",
    "jaxpbr.ibl.envs",
    "jaxpbr.ibl.shade",
    "jaxpbr.io.image",
    "jaxpbr.io.ktx2",
    "jaxpbr.shading.lights",
    "jaxpbr.shading.lut",
    "jaxpbr.ibl.measure",
    "jaxpbr.ibl.reference_render",
    "jaxpbr.rendering.renderer",
    "jaxpbr.rendering.scene",
    "jaxpbr.shading.shipped_luts",
    "jaxpbr.ibl.specular",
]

#: Names that are options wherever they appear (a positional parameter so named is flagged even
#: without a default).
OPTION_NAMES = frozenset(
    {
        "bits", "channels", "chunk", "count", "diffuse", "dtype", "encoding", "face_size", "fmt", "half",
        "height", "mapping", "max_texels", "method", "min_roughness", "model", "multiscatter",
        "num_levels", "operator", "options", "order", "outputs", "ratio", "refine", "samples", "seed",
        "shader_epsilon", "size", "smith", "supersample", "texels", "transfer", "use_shipped", "width",
        "xp",
    }
)

#: Positional parameters that are data, or the one leading size/name the documentation passes
#: positionally. Keyed by "<module>.<qualname>" of the definition.
DATA = {
    # the glTF sampler object is data read from the file, like the image
    "jaxpbr.rendering.texture.Texture.from_gltf": ("sampler",),
    # arrays of the formula, not switches
    "jaxpbr.shading.brdf_terms.d_ggx": ("sin2_h",),
    "jaxpbr.shading.brdf_terms.fresnel_mix": ("f0",),
    "jaxpbr.shading.brdf_terms.fresnel_schlick": ("f90",),
    "jaxpbr.color.gamma_encode": ("gamma",),  # differentiable (tests take d/d gamma)
    "jaxpbr.color.gamma_decode": ("gamma",),
    # the primary argument, positional in the README: tonemap(x, "aces"), encode(x, "srgb")
    "jaxpbr.color.tonemap": ("operator",),
    "jaxpbr.color.encode": ("transfer",),
    # the one leading size of a cube map's constructor
    "jaxpbr.ibl.cubemap.Cubemap.from_equirect": ("face_size",),
    "jaxpbr.ibl.cubemap.Cubemap.from_function": ("face_size",),
    "jaxpbr.ibl.envs.sky_with_sun_cubemap": ("face_size",),
    # the size/levels *is* the data these describe
    "jaxpbr.ibl.cubemap.texel_directions": ("size",),
    "jaxpbr.ibl.cubemap.texel_solid_angles": ("size",),
    "jaxpbr.ibl.cubemap.equirect_directions": ("height",),
    "jaxpbr.ibl.measure.texel_subset": ("size",),
    "jaxpbr.ibl.reference_render.min_reference_roughness": ("face_size",),
    "jaxpbr.ibl.lod.level_roughness": ("num_levels",),
    "jaxpbr.ibl.lod.roughness_to_lod": ("num_levels",),  # M of the map being looked up
    "jaxpbr.ibl.lod.levels_for_roughness": ("num_levels",),  # as roughness_to_lod
    "jaxpbr.ibl.lod.lookup_metadata": ("num_levels",),  # the chain it describes
    "jaxpbr.ibl.lod.default_num_levels": ("size",),
    # demo scenes: the image shape / grid shape
    "jaxpbr.rendering.demo.demo_scene": ("width", "height"),
    "jaxpbr.rendering.demo.learnopengl_scene": ("width", "height"),
    "jaxpbr.rendering.demo.sphere_grid": ("rows", "cols"),
    # where the text's relative paths resolve: the data's context
    "jaxpbr.rendering.scene_file.loads_scene": ("base_dir",),
}

_POSITIONAL = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)


def option_violations(fn, data=()) -> list[str]:
    """Parameters of `fn` that are options but positional-or-keyword (or positional-only)."""
    out = []
    for p in inspect.signature(fn).parameters.values():
        if p.kind not in _POSITIONAL or p.name in ("self", "cls") or p.name in data:
            continue
        if p.default is not inspect.Parameter.empty or p.name in OPTION_NAMES:
            out.append(p.name)
    return out


def _key(fn) -> str:
    return f"{fn.__module__}.{fn.__qualname__}"


def public_functions() -> dict:
    """{"<module>.<qualname>": function} for the public functions and public classes'
    classmethod/staticmethod constructors (pytree `tree_unflatten` excluded)."""
    found = {}
    for name in MODULES:
        mod = importlib.import_module(name)
        for attr in mod.__all__:
            obj = getattr(mod, attr)
            if inspect.isfunction(obj):
                found[_key(obj)] = obj
            elif inspect.isclass(obj):
                for k, v in vars(obj).items():
                    if isinstance(v, (classmethod, staticmethod)) and not k.startswith("_") and k != "tree_unflatten":
                        found[_key(v.__func__)] = v.__func__
    return found


PUBLIC = public_functions()


def test_the_walk_finds_the_public_api():
    for key in ("jaxpbr.shading.brdf_terms.brdf", "jaxpbr.shading.lights.shade_direct", "jaxpbr.ibl.shade.shade_ibl",
                "jaxpbr.shading.lut.compute_brdf_lut", "jaxpbr.shading.lut.lut_lookup", "jaxpbr.shading.lut.lut_reference",
                "jaxpbr.shading.shipped_luts.brdf_lut", "jaxpbr.ibl.diffuse.irradiance", "jaxpbr.ibl.diffuse.sh9_project",
                "jaxpbr.ibl.specular.prefilter", "jaxpbr.ibl.lod.roughness_to_lod", "jaxpbr.rendering.execute.render",
                "jaxpbr.rendering.batching.render_batch", "jaxpbr.rendering.plan.plan", "jaxpbr.color.tonemap",
                "jaxpbr.io.image.read", "jaxpbr.io.image.write", "jaxpbr.ibl.cubemap.Cubemap.from_equirect",
                "jaxpbr.ibl.cubemap.Cubemap.from_function", "jaxpbr.ibl.measure.lut_error",
                "jaxpbr.ibl.reference_render.reference_ibl", "jaxpbr.ibl.envs.sky_with_sun_cubemap"):
        assert key in PUBLIC, key
    assert len(PUBLIC) > 80


@pytest.mark.parametrize("key", sorted(PUBLIC))
def test_options_are_keyword_only(key):
    bad = option_violations(PUBLIC[key], DATA.get(key, ()))
    assert not bad, (
        f"{key}{inspect.signature(PUBLIC[key])}: option(s) {bad} can be passed positionally; make them "
        f"keyword-only (after `*`; `jaxpbr._api.keyword_only` keeps old positional calls working with a "
        f"DeprecationWarning), or declare them as data in DATA with the reason"
    )


def test_allow_list_is_not_stale():
    """Every DATA entry names a public function and positional parameters it really has."""
    for key, names in DATA.items():
        assert key in PUBLIC, f"DATA names {key}, which is not public (any more)"
        params = inspect.signature(PUBLIC[key]).parameters
        for n in names:
            assert n in params and params[n].kind in _POSITIONAL, f"{key}: {n} is not a positional parameter"


def test_the_check_can_fail():
    """The checker flags a deliberately wrong function (options positional) and passes the fix."""

    def wrong(img, size=3, smith="correlated"):
        return img

    def wrong_required(lut, smith):  # an option without a default is still an option
        return lut

    def right(img, *, size=3, smith="correlated"):
        return img

    assert option_violations(wrong) == ["size", "smith"]
    assert option_violations(wrong_required) == ["smith"]
    assert option_violations(wrong, data=("size",)) == ["smith"]
    assert option_violations(right) == []
    # ... and so does the parametrized test itself, on a wrong function put in the walk.
    PUBLIC["tests.wrong"] = wrong
    try:
        with pytest.raises(AssertionError, match="can be passed positionally"):
            test_options_are_keyword_only("tests.wrong")
    finally:
        del PUBLIC["tests.wrong"]


def _env():
    return jp.Cubemap([jnp.ones((6, 4, 4, 3), jnp.float32)])


@pytest.mark.parametrize(
    "call,old_name",
    [
        (lambda: jp.brdf_lut(8, "correlated"), "size, smith"),
        (lambda: jp.compute_brdf_lut(8, "correlated"), "size, smith"),
        (lambda: jp.brdf_lut(8), "size"),
        (lambda: jp.shading.shipped_luts.sheen_lut(8, samples=64, use_shipped=False), "size"),
        (lambda: jp.irradiance(_env(), 2), "size"),
        (lambda: jp.prefilter(_env(), 4, num_levels=1, samples=16), "size"),
        (lambda: jp.lut_reference(0.5, 0.5, "correlated"), "smith"),
        (lambda: jp.roughness_to_lod(0.5, 4, "linear"), "mapping"),
        (lambda: jp.ibl.specular.level_roughness(4, "linear"), "mapping"),
        (lambda: jp.rendering.renderer.plan(_scene(), RenderOptions()), "options"),
        (lambda: jp.rendering.scene.primary_rays(jp.Camera(width=2, height=2), jnp.float32), "dtype"),
        (lambda: jp.ibl.cubemap.equirect_directions(2, 4), "width"),
        (lambda: jp.ibl.cubemap.face_to_dir(np.array(0), np.array(0.5), np.array(0.5), np), "xp"),
        (lambda: importlib.import_module("jaxpbr.ibl.measure").texel_subset(2, 4), "count"),
    ],
)
def test_old_positional_calls_still_work_with_a_deprecation_warning(call, old_name):
    with pytest.warns(DeprecationWarning, match=f"passing {old_name}.* positionally is deprecated"):
        call()


def test_deprecated_positional_functions_declare_keyword_only_parameters():
    wrapped = {k: f for k, f in PUBLIC.items() if hasattr(f, "__deprecated_positional__")}
    assert len(wrapped) >= 15
    for key, f in wrapped.items():
        params = inspect.signature(f).parameters
        assert all(params[n].kind is inspect.Parameter.KEYWORD_ONLY for n in f.__deprecated_positional__), key


# ------------------------------------------------------------------------------------------
# One model registry
# ------------------------------------------------------------------------------------------


def _simple():
    n = jnp.asarray([0.3, 0.0, 1.0])
    return n, jnp.asarray([0.0, 0.2, 1.0]), jnp.asarray([0.2, 0.1, 1.0]), jp.Material((0.5, 0.4, 0.3), 0.2, 0.5)


def test_every_entry_point_reads_the_registry():
    from jaxpbr.cli import build_parser
    from jaxpbr.rendering import scene_file

    assert jp.MODELS == tuple(MODEL_REGISTRY) == jp.ibl.shade.IBL_MODELS
    assert scene_file.MODELS is jp.MODELS
    render_parser = build_parser()._subparsers._group_actions[0].choices["render"]
    model_action = next(a for a in render_parser._actions if a.dest == "model")
    assert tuple(model_action.choices) == jp.MODELS
    for model, spec in MODEL_REGISTRY.items():
        assert spec.options | spec.ibl_options <= set(OPTION_DEFAULTS), model
        assert spec.lut_smith in jp.shading.lut.SMITH_VARIANTS
    assert set(OPTION_CHOICES) <= set(OPTION_DEFAULTS)


def test_signature_defaults_are_the_registry_defaults():
    for fn in (jp.brdf, jp.shade_direct, jp.shade_ibl):
        for name, p in inspect.signature(fn).parameters.items():
            if name in OPTION_DEFAULTS:
                assert p.default == OPTION_DEFAULTS[name], (fn.__name__, name)
    # The kernels default to the single-scattering glTF BRDF; render compensates for glTF (docs/ibl.md,
    # "energy model"), and a model without the option keeps the registry's default.
    assert RenderOptions().compensates is True
    assert RenderOptions(model="learnopengl").compensates == OPTION_DEFAULTS["multiscatter"]


FOREIGN = [
    ("learnopengl", "smith", "separable"),
    ("learnopengl", "diffuse", "burley"),
    ("gltf", "shader_epsilon", 0.0),
]


@pytest.mark.parametrize("model,name,value", FOREIGN)
def test_an_option_the_model_does_not_use_is_an_error(model, name, value):
    with pytest.raises(ValueError) as e:
        jp.brdf(*_simple(), model=model, **{name: value})
    msg = str(e.value)
    assert name in msg and repr(model) in msg and "leave" in msg and "use model=" in msg, msg
    p, n, v, m = jnp.zeros(3), *_simple()[:2], _simple()[3]
    with pytest.raises(ValueError, match=f"{name} is defined for the"):
        jp.shade_direct(p, n, v, m, jp.PointLight(position=(0, 0, 2.0)), model=model, **{name: value})


@pytest.mark.parametrize("model,name,value", FOREIGN)
def test_an_unused_option_with_its_default_value_is_allowed(model, name, value):
    """Decision (documented in `brdf_terms.check_options`): only non-default values of an option
    the model does not use are errors; its default passes, so code can spell out every option."""
    default = OPTION_DEFAULTS[name]
    got = jp.brdf(*_simple(), model=model, **{name: default})
    np.testing.assert_array_equal(np.asarray(got), np.asarray(jp.brdf(*_simple(), model=model)))


def test_multiscatter_follows_the_registry_in_shade_ibl_and_render_options():
    env = jp.Cubemap([jnp.ones((6, 4 >> m, 4 >> m, 3)) for m in range(3)], {"roughness_mapping": "linear"})
    lut = jp.compute_brdf_lut(size=8, smith="schlick_ggx", dtype=jnp.float64)
    n = jnp.asarray([0.0, 0.0, 1.0])
    m = jp.Material()
    with pytest.raises(ValueError, match="multiscatter is defined for the gltf model only"):
        jp.shade_ibl(n, n, m, env, env, lut, model="learnopengl", multiscatter=True)
    jp.shade_ibl(n, n, m, env, env, lut, model="learnopengl", multiscatter=False)  # the default: fine
    with pytest.raises(ValueError, match="multiscatter is defined for the gltf model only"):
        RenderOptions(model="learnopengl", multiscatter=True)
    with pytest.raises(ValueError, match="unknown model"):
        RenderOptions(model="phong")


def test_learnopengl_render_uses_the_registrys_lut():
    assert MODEL_REGISTRY["learnopengl"].lut_smith == "schlick_ggx"
    assert MODEL_REGISTRY["gltf"].lut_smith == "correlated"


# ------------------------------------------------------------------------------------------
# Distinct Smith names
# ------------------------------------------------------------------------------------------


def test_brdf_and_lut_smith_vocabularies_are_distinct():
    assert set(OPTION_CHOICES["smith"]) == {"correlated", "separable"}
    assert set(jp.shading.lut.SMITH_VARIANTS) == {"correlated", "schlick_ggx", "separable"}
    # The shared names mean the same G in both: the height-correlated and the uncorrelated
    # (separable) Smith-GGX G2; the LUT's Schlick-GGX (k = alpha/2) is not a brdf choice.
    assert set(OPTION_CHOICES["smith"]) & set(jp.shading.lut.SMITH_VARIANTS) == {"correlated", "separable"}
    with pytest.raises(ValueError, match="smith must be one of"):
        jp.compute_brdf_lut(size=8, smith="schlick_k_r_plus_1")
    with pytest.raises(ValueError, match="unknown smith"):
        jp.brdf(*_simple(), smith="schlick_ggx")


# ------------------------------------------------------------------------------------------
# Render options as a value
# ------------------------------------------------------------------------------------------


def _scene():
    return jp.Scene(
        camera=jp.Camera(position=(0.0, 0.0, 3.0), width=6, height=4),
        objects=[jp.Sphere(material=jp.Material((0.8, 0.5, 0.3), metallic=0.2, roughness=0.4))],
        lights=[jp.PointLight(position=(1.0, 2.0, 3.0), intensity=20.0)],
    )


def test_render_takes_options_as_a_value_and_keyword_overrides_on_top():
    scene = _scene()
    by_value = np.asarray(jp.render(scene, options=RenderOptions(model="learnopengl", dtype="float64")))
    by_keywords = np.asarray(jp.render(scene, model="learnopengl", dtype="float64"))
    np.testing.assert_array_equal(by_value, by_keywords)
    assert by_value.dtype == np.float64
    # Overrides are applied on top of `options`.
    over = np.asarray(jp.render(scene, options=RenderOptions(model="learnopengl", dtype="float64"), model="gltf"))
    np.testing.assert_array_equal(over, np.asarray(jp.render(scene, model="gltf", dtype="float64")))
    assert not np.array_equal(over, by_value)
    opts = RenderOptions(model="learnopengl")
    assert jp.rendering.renderer.plan(scene, options=opts, model="gltf") == jp.rendering.renderer.plan(scene)


def test_render_options_errors_name_the_fix():
    scene = _scene()
    with pytest.raises(TypeError, match="options must be a jaxpbr.RenderOptions"):
        jp.render(scene, options={"model": "gltf"})
    with pytest.raises(TypeError, match="unknown render option"):
        jp.render(scene, visibility="separable")
    with pytest.raises(ValueError, match="multiscatter is defined for the gltf model only"):
        jp.render(scene, options=RenderOptions(model="learnopengl"), multiscatter=True)


def test_render_batch_takes_options_as_a_value():
    scene = _scene()
    mats = jp.Material(base_color=jnp.asarray([[0.8, 0.5, 0.3], [0.2, 0.3, 0.9]]), metallic=0.2, roughness=0.4)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        a = np.asarray(jp.render_batch(scene, materials=mats, options=RenderOptions(dtype="float64")))
    b = np.asarray(jp.render_batch(scene, materials=mats, dtype="float64"))
    np.testing.assert_array_equal(a, b)


def test_cli_render_passes_the_options_value(monkeypatch, tmp_path):
    from jaxpbr.cli import main
    from jaxpbr.cli import render as cli_render

    seen = {}

    def fake_render(scene, **kwargs):
        seen.update(kwargs)
        return jnp.zeros(scene.image_shape + (3,))

    monkeypatch.setattr(cli_render, "render", fake_render)
    assert main(["render", "-o", str(tmp_path / "x.png"), "--width", "8", "--height", "4", "--model", "learnopengl",
                 "--no-environment"]) == 0
    # options as one value; progress only (None here: one pass) besides it, no splatted fields
    assert set(seen) == {"options", "progress"} and seen["options"] == RenderOptions(model="learnopengl")
    assert seen["progress"] is None
    assert dataclasses.is_dataclass(seen["options"])


# ------------------------------------------------------------------------------------------
# One front door: what the README and the docs' examples use is a `jp.` name
# ------------------------------------------------------------------------------------------

_ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]


def _python_blocks(path):
    import re

    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def test_every_name_the_readme_and_docs_use_is_public():
    """Every `jp.NAME` in the Python examples of the README and docs/ is in `jaxpbr.__all__`, and
    the README's examples import nothing but `jaxpbr as jp` (no `from jaxpbr.x.y import ...`)."""
    import re

    docs = [_ROOT / "README.md"] + sorted((_ROOT / "docs").glob("*.md"))
    used, missing = set(), []
    for path in docs:
        for block in _python_blocks(path):
            for name in re.findall(r"\bjp\.([A-Za-z_]\w*)", block):
                used.add(name)
                if name not in jp.__all__:
                    missing.append(f"{path.name}: jp.{name}")
    assert not missing, missing
    assert {"load_environment", "render", "Scene", "load_gltf"} <= used  # the walk reads the examples
    readme_imports = [ln for b in _python_blocks(_ROOT / "README.md") for ln in b.splitlines()
                      if re.match(r"\s*(from jaxpbr|import jaxpbr\.)", ln)]
    assert not readme_imports, readme_imports
