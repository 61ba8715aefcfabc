"""The one pytree mechanism (`jaxpbr._pytree`) behind every data type: round trips (also with
tracers under jit and vmap), static fields as auxiliary data, validated vs unchecked replace,
declared ranks against the documented shapes, one compile per structure."""

from __future__ import annotations

import dataclasses
import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr._pytree import Pytree, evolve, fields_of, leaf, static, unchecked
from jaxpbr.shading.lights import LightSet, pack_lights

H, W = 2, 3


def _cube(scale=1.0):
    return jp.Cubemap(scale * jnp.linspace(0.1, 1.0, 6 * 4 * 4 * 3).reshape(6, 4, 4, 3)).with_mips()


def _gbuffer():
    mat = jp.Material(
        base_color=jnp.full((H, W, 3), 0.5),
        metallic=jnp.zeros((H, W)),
        roughness=jnp.full((H, W), 0.5),
        occlusion=jnp.ones((H, W)),
        emissive=jnp.zeros((H, W, 3)),
    )
    n = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0]), (H, W, 3))
    return jp.GBuffer(hit=jnp.ones((H, W), bool), position=jnp.zeros((H, W, 3)), normal=n, view=n, material=mat)


def _camera():
    return jp.Camera(position=(0.0, 0.0, 5.0), width=8, height=6)


# name -> factory of one (unbatched) example of every data type
EXAMPLES = {
    "Material": lambda: jp.Material((0.9, 0.6, 0.2), metallic=1.0, roughness=0.4),
    "LayeredMaterial": lambda: jp.Material(
        (0.9, 0.6, 0.2), roughness=0.4, clearcoat=1.0, clearcoat_roughness=0.1, sheen_color=(0.5, 0.5, 0.5),
        sheen_roughness=0.3, specular=0.8, specular_color=(1.0, 0.9, 0.9), ior=1.4, anisotropy_strength=0.5,
        anisotropy_rotation=0.3, emissive_strength=2.0, transmission=0.5, thickness=0.1, attenuation_distance=2.0,
        attenuation_color=(0.9, 0.8, 0.7),
    ),
    "PointLight": lambda: jp.PointLight((1.0, 2.0, 3.0), (1.0, 0.9, 0.8), 5.0, range=10.0),
    "DirectionalLight": lambda: jp.DirectionalLight((0.0, -1.0, 0.0), intensity=3.0),
    "SpotLight": lambda: jp.SpotLight((0.0, 2.0, 0.0), (0.0, -1.0, 0.0), inner_cone_angle=0.2, outer_cone_angle=0.5),
    "LightSet": lambda: pack_lights([jp.PointLight((1.0, 2.0, 3.0)), jp.DirectionalLight((0.0, -1.0, 0.0))]),
    "Camera": _camera,
    "TexturedMaterial": lambda: jp.TexturedMaterial(
        factors=jp.Material(roughness=0.5), base_color_texture=jnp.full((4, 4, 3), 0.5), normal_scale=0.8
    ),
    "Sphere": lambda: jp.Sphere(center=(0.0, 1.0, 0.0), radius=2.0, material=jp.Material(roughness=0.3)),
    "Plane": lambda: jp.Plane(point=(0.0, -1.0, 0.0), normal=(0.0, 1.0, 0.0)),
    "Environment": lambda: jp.Environment(radiance=_cube(), intensity=2.0, rotation=0.5),
    "BakedEnvironment": lambda: jp.Environment(radiance=_cube(), lut=np.zeros((8, 4, 2)), lut_smith="correlated"),
    "GBuffer": _gbuffer,
    "Scene": lambda: jp.Scene(
        camera=_camera(),
        objects=[jp.Sphere(material=jp.Material(roughness=0.3)), jp.Plane()],
        lights=[jp.PointLight((0.0, 3.0, 3.0))],
        environment=jp.Environment(radiance=_cube()),
        ambient=0.1,
    ),
    "GBufferScene": lambda: jp.Scene(gbuffer=_gbuffer(), lights=[jp.DirectionalLight((0.0, 0.0, -1.0))]),
    "Cubemap": lambda: jp.Cubemap(_cube().levels, {"quantity": "test"}),
}
NAMES = sorted(EXAMPLES)

# The shapes the docstrings document for the array fields of one unbatched object, core axes only
# (-1: any size). LightSet's documented (N, ...) shapes carry the light axis N as a batch axis.
DOCUMENTED = {
    jp.Material: dict(
        base_color=(3,), metallic=(), roughness=(), occlusion=(), emissive=(3,), clearcoat=(), clearcoat_roughness=(),
        sheen_color=(3,), sheen_roughness=(), specular=(), specular_color=(3,), ior=(), anisotropy_strength=(),
        anisotropy_rotation=(), emissive_strength=(), transmission=(), thickness=(), attenuation_distance=(),
        attenuation_color=(3,),
    ),
    jp.PointLight: dict(position=(3,), color=(3,), intensity=(), inv_range=()),
    jp.DirectionalLight: dict(direction=(3,), color=(3,), intensity=(), angular_radius=()),
    jp.SpotLight: dict(
        position=(3,), direction=(3,), color=(3,), intensity=(), inner_cone_angle=(), outer_cone_angle=(), inv_range=()
    ),
    LightSet: dict(
        position=(3,), direction=(3,), radiant=(3,), inv_range=(), cone_scale=(), cone_offset=(), directional=(),
        sin_radius=(),
    ),
    jp.Camera: dict(position=(3,), target=(3,), up=(3,), fov_y_deg=(), ymag=(), jitter=(2,)),
    jp.TexturedMaterial: dict(
        base_color_texture=(-1, -1, -1),
        metallic_roughness_texture=(-1, -1, -1),
        occlusion_texture=(-1, -1, -1),
        normal_texture=(-1, -1, 3),
        emissive_texture=(-1, -1, 3),
        normal_scale=(),
        clearcoat_texture=(-1, -1, -1), clearcoat_roughness_texture=(-1, -1, -1), clearcoat_normal_texture=(-1, -1, 3),
        clearcoat_normal_scale=(), sheen_color_texture=(-1, -1, -1), sheen_roughness_texture=(-1, -1, -1),
        specular_texture=(-1, -1, -1), specular_color_texture=(-1, -1, -1), anisotropy_texture=(-1, -1, -1),
        transmission_texture=(-1, -1, -1), thickness_texture=(-1, -1, -1),
    ),
    jp.Sphere: dict(center=(3,), radius=()),
    jp.Plane: dict(point=(3,), normal=(3,), tangent=(3,), uv_scale=()),
    jp.Environment: dict(intensity=(), rotation=(), lut=(-1, -1, 2), sheen_lut=(-1, -1)),
    jp.GBuffer: dict(hit=(-1, -1), position=(-1, -1, 3), normal=(-1, -1, 3), view=(-1, -1, 3)),
    jp.Scene: dict(background=(3,)),
    jp.Cubemap: dict(levels=(6, -1, -1, -1)),
}
STATIC = {
    jp.Camera: {"projection", "width", "height", "supersample"},
    jp.Environment: {"show_background", "lut_smith"},
    jp.Scene: {"ambient"},
    jp.Cubemap: {"info"},
}
SUBTREES = {
    jp.TexturedMaterial: {"factors"},
    jp.Sphere: {"material"},
    jp.Plane: {"material"},
    jp.Environment: {"radiance", "irradiance", "prefiltered", "lights", "charlie"},
    jp.GBuffer: {"material"},
    jp.Scene: {"camera", "objects", "lights", "environment", "gbuffer"},
}


def _arrays(value):
    """The arrays of an array-leaf field's value (None -> none; a tuple -> each)."""
    if value is None:
        return []
    return list(value) if isinstance(value, tuple) else [value]


def _first_array_field(obj):
    return next(f for f in fields_of(obj) if f.is_array and getattr(obj, f.name) is not None)


def _same_leaves(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _rescaled(obj):
    """Same structure, other leaf values (float leaves halved)."""
    return jax.tree_util.tree_map(lambda x: x * 0.5 if jnp.issubdtype(x.dtype, jnp.floating) else x, obj)


# ----------------------------------------------------------------------------------------------
# Declarations
# ----------------------------------------------------------------------------------------------


def test_every_type_declares_its_fields():
    for cls, shapes in DOCUMENTED.items():
        assert issubclass(cls, Pytree)
        infos = {f.name: f for f in fields_of(cls)}
        assert [f.name for f in dataclasses.fields(cls)] == list(infos)
        assert {n for n, f in infos.items() if f.static} == STATIC.get(cls, set()), cls.__name__
        assert {n for n, f in infos.items() if not f.static and f.rank is None} == SUBTREES.get(cls, set())
        for name, shape in shapes.items():
            assert infos[name].is_array and infos[name].rank == len(shape), f"{cls.__name__}.{name}"


@pytest.mark.parametrize("name", NAMES)
def test_declared_ranks_match_the_documented_shapes(name):
    obj = EXAMPLES[name]()
    batch = 1 if isinstance(obj, LightSet) else 0  # the light axis N
    for f in fields_of(obj):
        if not f.is_array:
            continue
        core = DOCUMENTED[type(obj)][f.name]
        for x in _arrays(getattr(obj, f.name)):
            assert np.ndim(x) == f.rank + batch, f"{name}.{f.name}: {np.shape(x)} vs rank {f.rank}"
            tail = np.shape(x)[batch:]
            assert all(c in (-1, s) for c, s in zip(core, tail)), f"{name}.{f.name}: {tail} vs {core}"


def test_a_field_without_a_declaration_is_refused():
    with pytest.raises(TypeError, match="declare every field"):

        class Bad(Pytree):  # noqa: F841
            x: int = 3


def test_fields_of_refuses_other_types():
    with pytest.raises(TypeError, match="not a jaxpbr pytree"):
        fields_of({"a": 1})


# ----------------------------------------------------------------------------------------------
# Round trips
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_flatten_unflatten_round_trip(name):
    obj = EXAMPLES[name]()
    leaves, tree = jax.tree_util.tree_flatten(obj)
    back = jax.tree_util.tree_unflatten(tree, leaves)
    assert type(back) is type(obj)
    for f in fields_of(obj):
        if f.static:
            assert getattr(back, f.name) == getattr(obj, f.name)
    _same_leaves(back, obj)
    # unflatten bypasses validation: sentinels and None are accepted as leaves
    sentinel = object()
    odd = jax.tree_util.tree_unflatten(tree, [sentinel] * len(leaves))
    assert type(odd) is type(obj) and jax.tree_util.tree_leaves(odd) == [sentinel] * len(leaves)
    assert type(jax.tree_util.tree_unflatten(tree, [None] * len(leaves))) is type(obj)


def test_key_paths_name_the_fields():
    scene = EXAMPLES["Scene"]()
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(scene)[0]]
    assert ".objects[0].material.roughness" in paths
    assert ".camera.position" in paths and ".environment.radiance.levels[0]" in paths
    assert ".camera.width" not in paths  # static


@pytest.mark.parametrize("name", NAMES)
def test_round_trip_with_tracers_under_jit(name):
    obj = EXAMPLES[name]()
    seen = []

    def f(o):
        seen.append((type(o), [isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(o)]))
        repr(o)  # readable with tracers too
        return o

    out = jax.jit(f)(obj)
    assert type(out) is type(obj)
    _same_leaves(out, obj)
    (cls, tracer), = seen
    assert cls is type(obj) and all(tracer)


@pytest.mark.parametrize("name", NAMES)
def test_vmap_over_a_batched_leaf(name):
    obj = EXAMPLES[name]()
    field = _first_array_field(obj)
    value = getattr(obj, field.name)
    stack = lambda x: jnp.stack([x, 2 * x]) if jnp.issubdtype(x.dtype, jnp.floating) else jnp.stack([x, x])  # noqa: E731
    batched_value = tuple(map(stack, value)) if isinstance(value, tuple) else stack(value)
    batched = evolve(obj, **{field.name: batched_value})
    paths, tree = jax.tree_util.tree_flatten_with_path(batched)
    axes = [0 if p[0] == jax.tree_util.GetAttrKey(field.name) else None for p, _ in paths]
    in_axes = jax.tree_util.tree_unflatten(tree, axes)
    inside = []

    def f(o):
        inside.append((type(o), [np.shape(x) for x in _arrays(getattr(o, field.name))]))
        return getattr(o, field.name)

    out = jax.vmap(f, in_axes=(in_axes,))(batched)
    (cls, shapes), = inside
    assert cls is type(obj) and shapes == [np.shape(x) for x in _arrays(value)]
    for got, want in zip(_arrays(out), _arrays(batched_value)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_material_through_grad_keeps_its_type():
    m = jp.Material(roughness=0.5)
    g = jax.grad(lambda mm: jnp.sum(mm.f0()) + mm.roughness)(m)
    assert isinstance(g, jp.Material) and float(g.roughness) == 1.0


# ----------------------------------------------------------------------------------------------
# Static fields, compilation
# ----------------------------------------------------------------------------------------------

STATIC_CHANGES = {
    "Camera": dict(width=16),
    "Environment": dict(show_background=False),
    "Scene": dict(ambient=0.2),
    # a lookup key: only those are part of a Cubemap's identity (provenance keys are not, cubemap.CubeInfo)
    "Cubemap": dict(info=(("quantity", "test"), ("roughness_mapping", "quadratic"))),
}


@pytest.mark.parametrize("name", sorted(STATIC_CHANGES))
def test_static_fields_are_aux_data(name):
    obj = EXAMPLES[name]()
    tree = jax.tree_util.tree_structure(obj)
    other = obj.replace(**STATIC_CHANGES[name])
    assert jax.tree_util.tree_structure(other) != tree
    assert len(jax.tree_util.tree_leaves(other)) == len(jax.tree_util.tree_leaves(obj))


@pytest.mark.parametrize("name", NAMES)
def test_changing_a_leaf_keeps_the_treedef(name):
    obj = EXAMPLES[name]()
    assert jax.tree_util.tree_structure(_rescaled(obj)) == jax.tree_util.tree_structure(obj)
    field = _first_array_field(obj)
    value = getattr(obj, field.name)
    new = tuple(x + 0 for x in value) if isinstance(value, tuple) else jnp.asarray(value) * 1
    assert jax.tree_util.tree_structure(evolve(obj, **{field.name: new})) == jax.tree_util.tree_structure(obj)


@pytest.mark.parametrize("name", NAMES)
def test_jit_compiles_once_for_two_leaf_values(name):
    obj = EXAMPLES[name]()
    traces = [0]

    @jax.jit
    def f(o):
        traces[0] += 1  # runs only when tracing
        return [x for x in jax.tree_util.tree_leaves(o) if jnp.issubdtype(x.dtype, jnp.floating)][0].sum()

    a = f(obj)
    b = f(_rescaled(obj))
    assert traces[0] == 1
    np.testing.assert_allclose(float(b), 0.5 * float(a), rtol=1e-6)
    if name in STATIC_CHANGES:
        f(obj.replace(**STATIC_CHANGES[name]))
        assert traces[0] == 2  # a static field is part of the compiled program


def test_constructed_values_share_one_program():
    traces = [0]

    @jax.jit
    def f(m, light, cam):
        traces[0] += 1
        return m.roughness + light.intensity + cam.fov_y_deg

    f(jp.Material(roughness=0.3), jp.PointLight((0, 1, 2), intensity=2.0), jp.Camera(fov_y_deg=40.0, width=4, height=4))
    f(jp.Material(roughness=0.7), jp.PointLight((3, 1, 2), intensity=5.0), jp.Camera(fov_y_deg=60.0, width=4, height=4))
    assert traces[0] == 1


# ----------------------------------------------------------------------------------------------
# replace / evolve / unchecked, immutability, repr
# ----------------------------------------------------------------------------------------------

INVALID = [
    ("Material", dict(roughness=2.0), "roughness must lie in"),
    ("PointLight", dict(intensity=-1.0), "intensity must be >= 0"),
    ("PointLight", dict(inv_range=-1.0), "inv_range must be >= 0"),
    ("DirectionalLight", dict(direction=(0.0, 0.0, 0.0)), "non-zero"),
    ("SpotLight", dict(inner_cone_angle=0.6), "smaller than outer_cone_angle"),
    ("Camera", dict(width=0), "Camera.width"),
    ("Camera", dict(target=(0.0, 0.0, 5.0)), "must differ"),
    ("TexturedMaterial", dict(base_color_texture=jnp.full((4, 4, 3), 2.0)), r"\[0.0, 1.0\]"),
    ("Sphere", dict(radius=-1.0), "Sphere.radius must be > 0"),
    ("Plane", dict(normal=(0.0, 0.0, 0.0)), "non-zero"),
    ("Environment", dict(intensity=-1.0), "Environment.intensity"),
    ("GBuffer", dict(position=jnp.zeros((H, W, 2))), "trailing axis of 3"),
    ("Scene", dict(ambient=-1.0), "ambient"),
]


@pytest.mark.parametrize("name,changes,match", INVALID)
def test_replace_validates_and_evolve_does_not(name, changes, match):
    obj = EXAMPLES[name]()
    with pytest.raises(ValueError, match=match):
        obj.replace(**changes)
    unchecked_copy = evolve(obj, **changes)
    for k, v in changes.items():
        assert getattr(unchecked_copy, k) is v  # stored as given: not even converted
    for f in fields_of(obj):
        if f.name not in changes:
            assert getattr(unchecked_copy, f.name) is getattr(obj, f.name)


@pytest.mark.parametrize("name", NAMES)
def test_replace_converts_like_the_constructor(name):
    obj = EXAMPLES[name]()
    field = _first_array_field(obj)
    if name == "LightSet":  # built by pack_lights and taken as given: nothing to convert
        assert obj.replace(inv_range=[1.0, 2.0]).inv_range == [1.0, 2.0]
        return
    if name == "Cubemap":
        new = obj.replace(levels=np.asarray(obj.levels[0]))  # Cubemap.replace: an array -> one level
        assert isinstance(new.levels, tuple) and len(new.levels) == 1
        return
    value = np.asarray(getattr(obj, field.name)).tolist()  # Python numbers (bool for hit/directional)
    new = obj.replace(**{field.name: value})
    assert type(new) is type(obj) and isinstance(getattr(new, field.name), jax.Array)
    np.testing.assert_array_equal(np.asarray(getattr(new, field.name)), np.asarray(getattr(obj, field.name)))


def test_replace_keeps_weak_types_and_rejects_unknown_fields():
    cam = jp.Camera().replace(position=(1.0, 2.0, 3.0))
    assert cam.position.weak_type and (cam.position * jnp.float32(1)).dtype == jnp.float32
    light = jp.PointLight((0.0, 1.0, 2.0), (1.0, 1.0, 1.0), 2.0)
    assert light.color.weak_type and light.intensity.weak_type
    for obj in (jp.Material(), jp.Camera(), light):
        with pytest.raises(TypeError, match="has no field"):
            obj.replace(shininess=2)
        with pytest.raises(TypeError, match="has no field"):
            evolve(obj, shininess=2)


def test_constructors_are_unchanged():
    m = jp.Material((0.9, 0.6, 0.2), metallic=1.0)
    np.testing.assert_allclose(m.base_color, [0.9, 0.6, 0.2])
    light = jp.PointLight((0.0, 1.0, 2.0), (1.0, 0.5, 0.5), 3.0, 4.0)
    assert float(light.inv_range) == 0.25 and float(jp.PointLight((0, 0, 0)).inv_range) == 0.0
    spot = jp.SpotLight((0, 0, 0), (0, -1, 0), (1, 1, 1), 2.0, 0.1, 0.3, 2.0)
    assert float(spot.inv_range) == 0.5 and float(spot.outer_cone_angle) == pytest.approx(0.3)
    assert float(jp.SpotLight((0, 0, 0), (0, -1, 0)).outer_cone_angle) == pytest.approx(math.pi / 4)
    with pytest.raises(ValueError, match="light range must be > 0"):
        jp.PointLight((0, 0, 0), range=0.0)
    scene = EXAMPLES["Scene"]()
    assert isinstance(scene.objects, tuple) and isinstance(scene.lights, tuple) and scene.ambient == 0.1
    # dataclasses.replace goes through the constructor (validated)
    assert dataclasses.replace(scene.camera, width=10).width == 10
    with pytest.raises(ValueError):
        dataclasses.replace(scene.camera, width=0)
    assert float(dataclasses.replace(m, roughness=0.5).roughness) == 0.5


def test_unchecked_builds_without_validation_and_needs_every_field():
    ext = {f: None for fs in jp.shading.material.EXTENSION_FIELDS.values() for f in fs}
    m = unchecked(jp.Material, base_color=1, metallic=2, roughness=3, occlusion=4, emissive=None, **ext)
    assert m.roughness == 3 and m.emissive is None
    with pytest.raises(TypeError, match="missing"):
        unchecked(jp.Material, roughness=0.5)


@pytest.mark.parametrize("name", NAMES)
def test_immutable(name):
    obj = EXAMPLES[name]()
    field = fields_of(obj)[0].name
    with pytest.raises(AttributeError, match=r"immutable; use .*\.replace"):
        setattr(obj, field, None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        delattr(obj, field)


def test_material_immutability_message_is_unchanged():
    with pytest.raises(AttributeError, match=r"^Material is immutable; use material\.replace\(field=value\)\.$"):
        jp.Material().roughness = 0.5


def test_repr_is_readable():
    s = repr(jp.Sphere(material=jp.Material(roughness=0.5)))
    assert s.startswith("Sphere(center=[0.0, 0.0, 0.0], radius=1.0, material=Material(base_color=[1.0, 1.0, 1.0]")
    assert "roughness=0.5" in s
    t = repr(EXAMPLES["TexturedMaterial"]())
    assert re.search(r"base_color_texture=float(32|64)\[4, 4, 3\]", t) and "normal_texture=None" in t
    c = repr(_camera())
    assert "width=8" in c and "fov_y_deg=45.0" in c
    assert repr(_cube()).startswith("Cubemap(face_size=4, num_levels=3")  # its own summary
    seen = []
    jax.jit(lambda m: seen.append(repr(m)) or m.roughness)(jp.Material(roughness=jnp.zeros(5)))
    assert re.search(r"roughness=float(32|64)\[5\]", seen[0])


class _Toy(Pytree):
    """A minimal type built on the mechanism (as documented in jaxpbr._pytree)."""

    x: object = leaf(rank=1)
    n: int = static(2)

    def _validate(self):
        self._set(x=jnp.asarray(self.x, jnp.float32))
        if self.x.shape[-1] != self.n:
            raise ValueError("x must end in n")


def test_a_new_type_gets_the_whole_mechanism():
    t = _Toy([1.0, 2.0])
    assert t.x.dtype == jnp.float32 and fields_of(t) == (("x", False, 1), ("n", True, None))
    with pytest.raises(ValueError, match="end in n"):
        _Toy([1.0, 2.0, 3.0])
    assert jax.tree_util.tree_structure(t) != jax.tree_util.tree_structure(_Toy([1.0, 2.0, 3.0], n=3))
    doubled = jax.jit(lambda t: jax.tree_util.tree_map(lambda x: 2 * x, t))(t)
    assert isinstance(doubled, _Toy) and doubled.n == 2
    np.testing.assert_array_equal(doubled.x, [2.0, 4.0])
