"""Textures of the glTF material extensions on TexturedMaterial (jaxpbr.rendering.scene.apply_extension_textures):
channels and factor x texture per the KHR specs, the clear-coat normal map, the anisotropy direction
texture, validation, jit and grad."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr._pytree import evolve
from jaxpbr.rendering.scene import EXTENSION_TEXTURES, apply_extension_textures

H, W = 3, 4
DT = jnp.float32


def _frame():
    """(u, v, sel, n, tangent): uv spread over the image, a selection mask, unit normals and
    tangents that are not orthogonal to them (so Gram-Schmidt matters)."""
    rng = np.random.default_rng(0)
    u = jnp.asarray(rng.uniform(0, 1, (H, W)), DT)
    v = jnp.asarray(rng.uniform(0, 1, (H, W)), DT)
    sel = jnp.asarray(rng.uniform(0, 1, (H, W)) < 0.6).at[0, 0].set(True).at[0, 1].set(False)
    n = rng.normal(size=(H, W, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    t = rng.normal(size=(H, W, 3)) * 2.0
    n3 = tuple(jnp.asarray(n[..., i], DT) for i in range(3))
    t3 = tuple(jnp.asarray(t[..., i], DT) for i in range(3))
    return u, v, sel, n3, t3


def _per_pixel(m: jp.Material, groups=None) -> jp.Material:
    """The gathered material: m's (completed) leaves broadcast to (H, W[, 3]), as the renderer does."""
    m = m.complete(groups)
    kw = {}
    for f in jp.Material.__dataclass_fields__:
        x = getattr(m, f)
        if x is None:
            continue
        x = jnp.asarray(x, DT)
        kw[f] = jnp.broadcast_to(x, (H, W) + x.shape[-1:] if x.ndim else (H, W))
    return jp.Material(**kw)


def _np(x):
    return np.asarray(x, np.float64)


def _frame_np(n, t):
    n = np.stack([_np(c) for c in n], -1)
    t = np.stack([_np(c) for c in t], -1)
    T = t - np.sum(t * n, -1, keepdims=True) * n
    T /= np.linalg.norm(T, axis=-1, keepdims=True)
    return n, T, np.cross(n, T)


ALL_FACTORS = jp.Material(
    clearcoat=0.8, clearcoat_roughness=0.6, sheen_color=(0.9, 0.5, 0.3), sheen_roughness=0.7, specular=0.9,
    specular_color=(1.5, 1.0, 0.5), anisotropy_strength=0.75, anisotropy_rotation=0.3, transmission=0.65,
    thickness=2.5, attenuation_distance=3.0, attenuation_color=(0.9, 0.8, 0.7), ior=1.4,
)
# One constant per channel (R, G, B, A), distinct, so reading the wrong channel shows.
CHANNELS = np.array([0.2, 0.45, 0.7, 0.95])


def _const(c=4, values=CHANNELS):
    return np.broadcast_to(np.asarray(values[:c], np.float32), (5, 7, c)).copy()


# ------------------------------------------------------------------------------------------
# Factor x texture channel
# ------------------------------------------------------------------------------------------


def test_constant_textures_give_factor_times_channel():
    textures = {name: _const(4) for name in EXTENSION_TEXTURES if name != "clearcoat_normal_texture"}
    tm = jp.TexturedMaterial(factors=ALL_FACTORS, **textures)
    u, v, sel, n, t = _frame()
    m = _per_pixel(ALL_FACTORS)
    out, coat, tan = apply_extension_textures(tm, m, u, v, sel, n, t, dtype=DT)
    assert coat is None  # no clear-coat normal map, no base normal map
    assert tan is not None  # the anisotropy texture gives a direction
    s = np.asarray(sel)
    R, G, B, A = CHANNELS
    expect = {
        "clearcoat": 0.8 * R,
        "clearcoat_roughness": 0.6 * G,
        "sheen_color": np.array([0.9, 0.5, 0.3]) * CHANNELS[:3],
        "sheen_roughness": 0.7 * A,
        "specular": 0.9 * A,
        "specular_color": np.array([1.5, 1.0, 0.5]) * CHANNELS[:3],
        "anisotropy_strength": 0.75 * B,
        "transmission": 0.65 * R,
        "thickness": 2.5 * G,
    }
    for field, e in expect.items():
        got = _np(getattr(out, field))
        ref = _np(getattr(m, field))
        np.testing.assert_allclose(got[s], np.broadcast_to(e, got[s].shape), rtol=1e-6, err_msg=field)
        np.testing.assert_array_equal(got[~s], ref[~s], err_msg=field)  # other objects' pixels untouched
    # Fields without a texture are passed through.
    for field in ("anisotropy_rotation", "ior", "attenuation_distance", "attenuation_color", "base_color", "roughness"):
        np.testing.assert_array_equal(_np(getattr(out, field)), _np(getattr(m, field)), err_msg=field)


def test_textures_are_sampled_at_uv():
    """A varying texture is looked up bilinearly at (u, v) (`sample_texture`), channel by channel."""
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 1, (6, 5, 4)).astype(np.float32)
    f = jp.Material(specular=0.5, specular_color=(1.0, 1.0, 1.0))
    tm = jp.TexturedMaterial(factors=f, specular_texture=img, specular_color_texture=img)
    u, v, sel, n, t = _frame()
    out, _, _ = apply_extension_textures(tm, _per_pixel(f), u, v, sel, n, t, dtype=DT)
    ref = np.asarray(jp.rendering.scene.sample_texture(jnp.asarray(img), u, v))
    s = np.asarray(sel)
    np.testing.assert_allclose(_np(out.specular)[s], 0.5 * ref[..., 3][s], rtol=1e-6)
    np.testing.assert_allclose(_np(out.specular_color)[s], ref[..., :3][s], rtol=1e-6)


def test_unset_factor_of_a_present_group_takes_its_neutral_value():
    """glTF: a texture multiplies its factor, whose default is the extension's (clearcoat_roughness
    0: the roughness texture then has no effect; specular_color 1: the texture is the colour)."""
    f = jp.Material(clearcoat=1.0, specular=1.0)
    tm = jp.TexturedMaterial(
        factors=f, clearcoat_roughness_texture=_const(3), specular_color_texture=_const(3)
    )
    u, v, sel, n, t = _frame()
    out, _, _ = apply_extension_textures(tm, _per_pixel(f), u, v, sel, n, t, dtype=DT)
    s = np.asarray(sel)
    np.testing.assert_array_equal(_np(out.clearcoat_roughness)[s], 0.0)
    np.testing.assert_allclose(_np(out.specular_color)[s], np.broadcast_to(CHANNELS[:3], (s.sum(), 3)), rtol=1e-6)


def test_group_missing_from_the_gathered_material_is_neutral_elsewhere():
    f = jp.Material(transmission=1.0)
    tm = jp.TexturedMaterial(factors=f, transmission_texture=_const(1))
    u, v, sel, n, t = _frame()
    out, _, _ = apply_extension_textures(tm, _per_pixel(jp.Material()), u, v, sel, n, t, dtype=DT)
    s = np.asarray(sel)
    np.testing.assert_allclose(_np(out.transmission)[s], CHANNELS[0], rtol=1e-6)
    np.testing.assert_array_equal(_np(out.transmission)[~s], 0.0)


def test_no_extension_textures_changes_nothing():
    f = jp.Material(clearcoat=1.0)
    tm = jp.TexturedMaterial(factors=f, base_color_texture=_const(3))
    u, v, sel, n, t = _frame()
    m = _per_pixel(f)
    out, coat, tan = apply_extension_textures(tm, m, u, v, sel, n, t, dtype=DT)
    assert out is m and coat is None and tan is None


# ------------------------------------------------------------------------------------------
# Clear-coat normal
# ------------------------------------------------------------------------------------------


def test_flat_coat_normal_map_gives_the_normal():
    f = jp.Material(clearcoat=1.0)
    tm = jp.TexturedMaterial(factors=f, clearcoat_normal_texture=np.full((4, 4, 3), [0.5, 0.5, 1.0]))
    u, v, sel, n, t = _frame()
    _, coat, tan = apply_extension_textures(tm, _per_pixel(f), u, v, sel, n, t, dtype=DT)
    assert tan is None
    np.testing.assert_allclose(np.stack([_np(c) for c in coat], -1), np.stack([_np(c) for c in n], -1), atol=1e-6)


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_tilted_coat_normal_map(scale):
    """Texel (x, y, z) -> normalize(T x s + B y s + N z) with (x, y, z) = 2 texel - 1, T
    Gram-Schmidt-orthogonalised against N and B = N x T (the base normal map's convention)."""
    texel = np.array([0.8, 0.35, 0.9])
    f = jp.Material(clearcoat=1.0)
    tm = jp.TexturedMaterial(
        factors=f, clearcoat_normal_texture=np.full((4, 4, 3), texel), clearcoat_normal_scale=scale
    )
    u, v, sel, n, t = _frame()
    _, coat, _ = apply_extension_textures(tm, _per_pixel(f), u, v, sel, n, t, dtype=DT)
    N, T, B = _frame_np(n, t)
    x, y, z = 2 * texel - 1
    e = T * x * scale + B * y * scale + N * z
    e /= np.linalg.norm(e, axis=-1, keepdims=True)
    s = np.asarray(sel)
    got = np.stack([_np(c) for c in coat], -1)
    np.testing.assert_allclose(got[s], e[s], atol=2e-6)
    np.testing.assert_allclose(got[~s], N[~s], atol=1e-7)  # other objects: the normal


def test_coat_ignores_the_base_normal_map():
    """KHR_materials_clearcoat: without clearcoatNormalTexture no normal mapping applies to the
    coat, even if the base has a normal map: the coat normal is then the unmapped normal."""
    f = jp.Material(clearcoat=1.0)
    tm = jp.TexturedMaterial(factors=f, normal_texture=np.full((4, 4, 3), [0.9, 0.5, 0.6]))
    u, v, sel, n, t = _frame()
    _, coat, _ = apply_extension_textures(tm, _per_pixel(f), u, v, sel, n, t, dtype=DT)
    np.testing.assert_array_equal(np.stack(coat, -1), np.stack(n, -1))
    # No clear coat: no coat normal at all.
    tm = jp.TexturedMaterial(factors=jp.Material(sheen_color=(1, 1, 1)), normal_texture=np.full((4, 4, 3), 0.5))
    assert apply_extension_textures(tm, _per_pixel(tm.factors), u, v, sel, n, t, dtype=DT)[1] is None


# ------------------------------------------------------------------------------------------
# Anisotropy direction
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("phi", [0.0, 0.4, math.pi / 2, 2.5, -2.0])
def test_direction_texture_rotates_the_tangent(phi):
    """RG = (cos phi, sin phi) stored as (d + 1)/2 -> T' = cos phi T + sin phi B; B = strength."""
    texel = np.array([(math.cos(phi) + 1) / 2, (math.sin(phi) + 1) / 2, 0.6])
    f = jp.Material(anisotropy_strength=0.5)
    tm = jp.TexturedMaterial(factors=f, anisotropy_texture=np.full((4, 4, 3), texel))
    u, v, sel, n, t = _frame()
    out, coat, tan = apply_extension_textures(tm, _per_pixel(f), u, v, sel, n, t, dtype=DT)
    assert coat is None
    N, T, B = _frame_np(n, t)
    s = np.asarray(sel)
    got = np.stack([_np(c) for c in tan], -1)
    np.testing.assert_allclose(got[s], (math.cos(phi) * T + math.sin(phi) * B)[s], atol=2e-6)
    np.testing.assert_array_equal(got[~s], np.stack([_np(c) for c in t], -1)[~s])  # input tangent elsewhere
    np.testing.assert_allclose(_np(out.anisotropy_strength)[s], 0.5 * 0.6, rtol=1e-6)


@pytest.mark.parametrize("rotation", [0.0, 0.7, -1.9])
def test_rotation_on_top_of_the_texture_is_the_spec_sample_code(rotation):
    """The extension's sample code rotates the (normalised) texture direction by
    mat2(c, s, -s, c) (GLSL column-major: counter-clockwise) and maps it with TBN. Applying the
    rotation in the frame (T', N x T') of the returned tangent, as the shading does, is the same."""
    d = np.array([0.3, -0.8])
    texel = np.array([(d[0] + 1) / 2, (d[1] + 1) / 2, 1.0])
    f = jp.Material(anisotropy_strength=1.0, anisotropy_rotation=rotation)
    tm = jp.TexturedMaterial(factors=f, anisotropy_texture=np.full((2, 2, 3), texel))
    u, v, sel, n, t = _frame()
    _, _, tan = apply_extension_textures(tm, _per_pixel(f), u, v, sel, n, t, dtype=DT)
    N, T, B = _frame_np(n, t)
    c, s_ = math.cos(rotation), math.sin(rotation)
    dn = d / np.linalg.norm(d)
    spec = np.array([c * dn[0] - s_ * dn[1], s_ * dn[0] + c * dn[1]])  # mat2(c, s, -s, c) * dir
    spec_T = spec[0] * T + spec[1] * B
    Tp = np.stack([_np(x) for x in tan], -1)
    ours = c * Tp + s_ * np.cross(N, Tp)
    sel_np = np.asarray(sel)
    np.testing.assert_allclose(ours[sel_np], spec_T[sel_np], atol=3e-6)


def test_zero_direction_falls_back_to_the_tangent():
    f = jp.Material(anisotropy_strength=1.0)
    tm = jp.TexturedMaterial(factors=f, anisotropy_texture=np.full((2, 2, 3), [0.5, 0.5, 1.0]))
    u, v, sel, n, t = _frame()
    _, _, tan = apply_extension_textures(tm, _per_pixel(f), u, v, sel, n, t, dtype=DT)
    _, T, _ = _frame_np(n, t)
    s = np.asarray(sel)
    np.testing.assert_allclose(np.stack([_np(c) for c in tan], -1)[s], T[s], atol=1e-6)


# ------------------------------------------------------------------------------------------
# Validation
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(clearcoat_texture=_const(1)), r"clearcoat_texture needs the KHR_materials_clearcoat factors.*clearcoat=1.0"),
        (dict(sheen_color_texture=_const(3)), r"KHR_materials_sheen.*sheen_color=\(1.0, 1.0, 1.0\)"),
        (dict(thickness_texture=_const(2)), r"KHR_materials_volume.*thickness=1.0"),
        (dict(factors=jp.Material(specular=1.0), specular_texture=_const(3)), r"specular_texture must be an \(H, W, C\) image with C >= 4 \(A = specular"),
        (dict(factors=jp.Material(sheen_roughness=1.0), sheen_roughness_texture=_const(3)), r"C >= 4"),
        (dict(factors=jp.Material(clearcoat=1.0), clearcoat_roughness_texture=_const(1)), r"C >= 2 \(G = clear coat roughness"),
        (dict(factors=jp.Material(transmission=1.0), transmission_texture=np.full((2, 2, 1), 1.5)), r"transmission_texture must hold linear values in \[0.0, 1.0\]"),
        (dict(factors=jp.Material(anisotropy_strength=1.0), anisotropy_texture=np.full((2, 2, 3), -0.1)), r"anisotropy_texture must hold linear values"),
        (dict(factors=jp.Material(clearcoat=1.0), clearcoat_normal_texture=np.full((2, 2, 3), np.nan)), r"clearcoat_normal_texture contains NaN"),
        (dict(factors=jp.Material(clearcoat=1.0), clearcoat_normal_texture=np.zeros((2, 2))), r"\(H, W, C\)"),
        (dict(clearcoat_normal_scale=np.nan), r"clearcoat_normal_scale"),
    ],
)
def test_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jp.TexturedMaterial(**kwargs)


def test_extension_textures_property():
    tm = jp.TexturedMaterial(factors=ALL_FACTORS, thickness_texture=_const(2), clearcoat_texture=_const(1))
    assert tm.extension_textures == ("clearcoat_texture", "thickness_texture")
    assert jp.TexturedMaterial().extension_textures == ()


# ------------------------------------------------------------------------------------------
# jit and grad
# ------------------------------------------------------------------------------------------


def _all_textures():
    rng = np.random.default_rng(2)
    return {name: rng.uniform(0.05, 0.95, (4, 3, 4)).astype(np.float32) for name in EXTENSION_TEXTURES}


def test_jit_matches_eager():
    tm = jp.TexturedMaterial(factors=ALL_FACTORS, **_all_textures())
    u, v, sel, n, t = _frame()
    m = _per_pixel(ALL_FACTORS)
    eager = apply_extension_textures(tm, m, u, v, sel, n, t, dtype=DT)
    jitted = jax.jit(lambda tm, m, u, v, sel, n, t: apply_extension_textures(tm, m, u, v, sel, n, t, dtype=DT))(
        tm, m, u, v, sel, n, t
    )
    for a, b in zip(jax.tree_util.tree_leaves(eager), jax.tree_util.tree_leaves(jitted)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)


def test_gradients_are_finite_and_right():
    tm0 = jp.TexturedMaterial(factors=ALL_FACTORS, **_all_textures())
    u, v, sel, n, t = _frame()
    m = _per_pixel(ALL_FACTORS)

    def loss(tm):
        out, coat, tan = apply_extension_textures(tm, m, u, v, sel, n, t, dtype=DT)
        total = sum(jnp.sum(getattr(out, f) ** 2) for f in (
            "clearcoat", "clearcoat_roughness", "sheen_color", "sheen_roughness", "specular", "specular_color",
            "anisotropy_strength", "transmission", "thickness"))
        w = jnp.arange(1.0, 4.0)
        return total + jnp.sum(jnp.stack(coat, -1) * w) + jnp.sum(jnp.stack(tan, -1) * w)

    g = jax.jit(jax.grad(loss))(tm0)
    leaves = jax.tree_util.tree_leaves(g)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    # d/d factor of sum_sel (factor * tex)^2 = 2 factor sum_sel tex^2 (clearcoat: R channel).
    s = np.asarray(sel)
    tex = np.asarray(jp.rendering.scene.sample_texture(jnp.asarray(tm0.clearcoat_texture), u, v))[..., 0]
    np.testing.assert_allclose(float(g.factors.clearcoat), 2 * 0.8 * np.sum(tex[s] ** 2), rtol=1e-5)
    # The textures and the normal scale get gradients (the normal map and direction ones too).
    for name in ("clearcoat_texture", "sheen_roughness_texture", "clearcoat_normal_texture", "anisotropy_texture"):
        assert np.any(np.asarray(getattr(g, name)) != 0), name
    assert float(g.clearcoat_normal_scale) != 0


def test_gradient_matches_finite_differences():
    f = jp.Material(specular=0.7, specular_color=(0.8, 0.9, 1.0), anisotropy_strength=0.5)
    tex = _all_textures()
    tm0 = jp.TexturedMaterial(factors=f, specular_texture=tex["specular_texture"], anisotropy_texture=tex["anisotropy_texture"])
    u, v, sel, n, t = _frame()
    m = _per_pixel(f)

    def loss(spec, aniso):
        tm = evolve(tm0, factors=evolve(f, specular=spec), anisotropy_texture=aniso)
        out, _, tan = apply_extension_textures(tm, m, u, v, sel, n, t, dtype=DT)
        return jnp.sum(out.specular ** 2) + jnp.sum(jnp.stack(tan, -1) * jnp.arange(1.0, 4.0))

    a0 = jnp.asarray(tex["anisotropy_texture"])
    gs, ga = jax.grad(loss, argnums=(0, 1))(jnp.asarray(0.7, DT), a0)
    h = 1e-3
    fd = (loss(jnp.asarray(0.7 + h, DT), a0) - loss(jnp.asarray(0.7 - h, DT), a0)) / (2 * h)
    np.testing.assert_allclose(float(gs), float(fd), rtol=2e-3)
    e = jnp.zeros_like(a0).at[1, 1, 0].set(h)
    fd = (loss(jnp.asarray(0.7, DT), a0 + e) - loss(jnp.asarray(0.7, DT), a0 - e)) / (2 * h)
    np.testing.assert_allclose(float(ga[1, 1, 0]), float(fd), rtol=2e-2, atol=1e-3)
