"""jaxpbr.rendering.texture against independent oracles.

* level-0 lookups: `jaxpbr._interp.bilinear`, and a NumPy GL sampler written here from the OpenGL
  4.6 spec (§8.14.2, Table 8.20 wrap functions), at texel centres, midpoints and borders;
* the pyramid: constants stay constant, means are preserved, the odd-size filter equals the exact
  box average over each output texel's interval (computed here from interval overlaps), sRGB
  textures are averaged in linear space (the sRGB EOTF written here from IEC 61966-2-1);
* LOD: lambda = log2 k for footprints of k texels per pixel (isotropic and anisotropic);
* gradients: finite differences in float64 (texels, uv, footprint), finite at zero and huge
  derivatives;
* ray differentials: a camera above a plane, against the closed-form derivative of the hit point;
* KHR_texture_transform: the extension's own examples.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpbr._interp import bilinear
from jaxpbr.errors import InputError
from jaxpbr.rendering import texture as T

RNG = np.random.RandomState(7)


# ------------------------------------------------------------------------------------------
# NumPy oracles
# ------------------------------------------------------------------------------------------


def gl_wrap(i, size, mode):
    """OpenGL 4.6 Table 8.20, on integer texel indices."""
    if mode == "repeat":
        return np.mod(i, size)
    if mode == "clamp":  # CLAMP_TO_EDGE
        return np.clip(i, 0, size - 1)

    def mirror(a):
        return np.where(a >= 0, a, -(1 + a))

    return (size - 1) - mirror(np.mod(i, 2 * size) - size)  # MIRRORED_REPEAT


def gl_sample(img, u, v, wrap_s, wrap_t, filt):
    """GL NEAREST / LINEAR lookup of one level (§8.14.2) with u' = u W, v' = v H."""
    img = np.asarray(img, np.float64)
    H, W = img.shape[:2]
    if filt == "nearest":
        i = gl_wrap(np.floor(v * H).astype(int), H, wrap_t)
        j = gl_wrap(np.floor(u * W).astype(int), W, wrap_s)
        return img[i, j]
    x, y = u * W - 0.5, v * H - 0.5
    j0, i0 = np.floor(x).astype(int), np.floor(y).astype(int)
    a, b = (x - j0)[..., None], (y - i0)[..., None]
    ja, jb = gl_wrap(j0, W, wrap_s), gl_wrap(j0 + 1, W, wrap_s)
    ia, ib = gl_wrap(i0, H, wrap_t), gl_wrap(i0 + 1, H, wrap_t)
    return (1 - a) * (1 - b) * img[ia, ja] + a * (1 - b) * img[ia, jb] + (1 - a) * b * img[ib, ja] + a * b * img[ib, jb]


def srgb_eotf(c):
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def box_downsample_1d(x, m):
    """Exact box average of a piecewise-constant signal x (n samples, sample k on [k, k+1)) over
    m equal output intervals [i n/m, (i+1) n/m)."""
    n = len(x)
    out = np.zeros((m,) + x.shape[1:])
    for i in range(m):
        a, b = i * n / m, (i + 1) * n / m
        for k in range(n):
            overlap = max(0.0, min(b, k + 1) - max(a, k))
            out[i] += overlap * x[k]
        out[i] /= b - a
    return out


def tex_of(img, **kw):
    """A data texture, isotropic unless asked (smaller programs: faster tests)."""
    kw.setdefault("max_anisotropy", 1)
    return T.Texture.from_image(np.asarray(img), srgb=kw.pop("srgb", False), **kw)


def assert_grad_matches_fd(f, x, coords, *, step, atol, rtol):
    """jax.grad(f)(x) at the flat indices `coords` equals the central difference with `step`,
    |g - fd| <= atol + rtol |fd| (f jitted: one program for the values, one for the gradient)."""
    x = np.asarray(x, np.float64)
    g = np.asarray(jax.jit(jax.grad(f))(x)).reshape(-1)
    fj = jax.jit(f)
    for k in coords:
        e = np.zeros(x.size)
        e[k] = step
        fd = (float(fj(x + e.reshape(x.shape))) - float(fj(x - e.reshape(x.shape)))) / (2 * step)
        assert abs(g[k] - fd) <= atol + rtol * abs(fd), (k, g[k], fd)
    return g


# ------------------------------------------------------------------------------------------
# Level 0 and wrap modes
# ------------------------------------------------------------------------------------------


def test_level0_linear_matches_interp_bilinear():
    img = RNG.rand(6, 10, 3)
    u = RNG.uniform(-2.5, 3.5, 200)
    v = RNG.uniform(-2.5, 3.5, 200)
    # plus texel centres and midpoints between them
    u = np.concatenate([u, (np.arange(10) + 0.5) / 10, np.arange(11) / 10])
    v = np.concatenate([v, (np.arange(10) % 6 + 0.5) / 6, np.arange(11) % 7 / 6])
    for mode, wrap in (("repeat", True), ("clamp", False)):
        tex = tex_of(img, wrap_s=mode, wrap_t=mode)
        got = T.sample(tex, np.stack([u, v], -1))  # no derivatives: magnification, level 0
        want = bilinear(jnp.asarray(img), u * 10 - 0.5, v * 6 - 0.5, wrap_x=wrap, wrap_y=wrap)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("filt", ["nearest", "linear"])
def test_wrap_modes_at_and_beyond_borders_match_gl(filt):
    # power-of-two sizes: the dyadic sample points (texel centres, borders, midpoints) are exact
    img = RNG.rand(4, 8, 2)
    k = np.arange(-40, 57)
    # u - floor(u) rounds to exactly 1 for a tiny negative u (the index after the last texel)
    edge = np.array([-1e-20, 1.0 - 1e-17, -2.0 - 1e-17])
    u = np.concatenate([k / 16.0, RNG.uniform(-3, 4, 57), edge])
    v = np.concatenate([k[::-1] / 8.0, RNG.uniform(-3, 4, 57), [0.3, 0.6, 0.1]])
    uv = np.stack([u, v], -1)
    # every mode on each axis, next to each other mode (one compiled program per sampler)
    for ws, wt in (("repeat", "clamp"), ("clamp", "mirror"), ("mirror", "repeat")):
        if True:
            tex = tex_of(img, wrap_s=ws, wrap_t=wt, mag_filter=filt, max_anisotropy=1)
            got = np.asarray(T.sample(tex, uv))
            want = gl_sample(img, u, v, ws, wt, filt)
            if filt == "nearest":  # on a texel border (to rounding) either side is right
                other = gl_sample(img, u[-3:] + 1e-9, v[-3:], ws, wt, filt)
                want[-3:] = np.where(np.isclose(got[-3:], other, rtol=0, atol=0), other, want[-3:])
            np.testing.assert_allclose(got, want, atol=1e-12, err_msg=f"{ws}/{wt}")


def test_wrap_index_pairs_on_the_reduced_range():
    # the sampler wraps (i0, i0 + 1) by compare/select on the range a reduced coordinate gives
    cases = [(mode, n, period) for mode, period in (("repeat", 1), ("mirror", 2), ("clamp", 1)) for n in (1, 2, 3, 8)]
    i0 = np.arange(-1, 18)
    pairs = jax.jit(lambda i: [T._wrap_pair(i, n, mode) for mode, n, _ in cases])(jnp.asarray(i0))
    for (mode, n, period), (a, b) in zip(cases, pairs):
        r = i0 <= period * n  # i0 in [-1, period n]
        np.testing.assert_array_equal(np.asarray(a)[r], gl_wrap(i0[r], n, mode), err_msg=f"{mode} {n}")
        np.testing.assert_array_equal(np.asarray(b)[r], gl_wrap(i0[r] + 1, n, mode), err_msg=f"{mode} {n}")


def test_wrap_applies_at_every_level():
    img = RNG.rand(16, 8, 1)
    u = RNG.uniform(-2, 3, 300)
    v = RNG.uniform(-2, 3, 300)
    for mode in T.WRAP_MODES:
        tex = tex_of(img, wrap_s=mode, wrap_t=mode)
        for lvl in (1, 2, 3):
            got = T.sample_lod(tex, np.stack([u, v], -1), float(lvl))
            want = gl_sample(tex.levels[lvl], u, v, mode, mode, "linear")
            np.testing.assert_allclose(got, want, atol=1e-12, err_msg=f"{mode} level {lvl}")


def test_mag_and_min_filters_are_chosen_by_lod():
    img = RNG.rand(8, 8, 1)
    uv = np.stack([RNG.rand(50), RNG.rand(50)], -1)
    tiny = np.full((50, 2), 0.25 / 8) * [1, 0]  # lambda = -2: magnification
    big = np.full((50, 2), 4.0 / 8) * [1, 0]  # lambda = 2: minification
    tex = tex_of(img, mag_filter="nearest", min_filter="linear")  # non-mipmapped min: level 0
    np.testing.assert_allclose(T.sample(tex, uv, tiny, tiny[:, ::-1]), gl_sample(img, *uv.T, "repeat", "repeat", "nearest"), atol=1e-12)
    np.testing.assert_allclose(T.sample(tex, uv, big, big[:, ::-1]), gl_sample(img, *uv.T, "repeat", "repeat", "linear"), atol=1e-12)
    tex = tex_of(img, mag_filter="linear", min_filter="nearest")
    np.testing.assert_allclose(T.sample(tex, uv, tiny, tiny[:, ::-1]), gl_sample(img, *uv.T, "repeat", "repeat", "linear"), atol=1e-12)
    np.testing.assert_allclose(T.sample(tex, uv, big, big[:, ::-1]), gl_sample(img, *uv.T, "repeat", "repeat", "nearest"), atol=1e-12)


def test_mipmap_level_selection():
    img = RNG.rand(32, 32, 2)
    uv = np.stack([RNG.rand(40), RNG.rand(40)], -1)
    L = [np.asarray(x) for x in tex_of(img).levels]

    def look(lvl, filt):
        return gl_sample(L[lvl], *uv.T, "repeat", "repeat", filt)

    cases = {  # min_filter: [(lambda, expected)], one compiled program per sampler
        "linear_mipmap_nearest": [(1.4, look(1, "linear")), (1.6, look(2, "linear")), (0.3, look(0, "linear"))],
        "nearest_mipmap_nearest": [
            (2.4, look(2, "nearest")),
            (2.5, look(2, "nearest")),  # exact halves round down: level ceil(lambda + 1/2) - 1
            (2.6, look(3, "nearest")),
            (9.0, look(5, "nearest")),  # clamped to the 1x1 level
        ],
        "linear_mipmap_linear": [(1.25, 0.75 * look(1, "linear") + 0.25 * look(2, "linear")), (30.0, look(5, "linear"))],
        "nearest_mipmap_linear": [(2.5, 0.5 * look(2, "nearest") + 0.5 * look(3, "nearest"))],
    }
    for mode, pairs in cases.items():
        tex = tex_of(img, min_filter=mode)
        lam = np.repeat([p[0] for p in pairs], 40)
        got = T.sample_lod(tex, np.tile(uv, (len(pairs), 1)), lam)
        np.testing.assert_allclose(got, np.concatenate([p[1] for p in pairs]), atol=1e-12, err_msg=mode)
    # the same through the footprint (lambda = log2 of k texels per pixel)
    tex = tex_of(img, min_filter="linear_mipmap_linear")
    d = np.full((40, 2), 2.0**1.25 / 32) * [1, 0]
    np.testing.assert_allclose(T.sample(tex, uv, d, d[:, ::-1]), cases["linear_mipmap_linear"][0][1], atol=1e-12)


# ------------------------------------------------------------------------------------------
# The pyramid
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(16, 16), (13, 7), (5, 1), (1, 9), (12, 20)])
def test_mips_constant_and_mean(shape):
    H, W = shape
    assert T.mip_count(H, W) == int(np.floor(np.log2(max(H, W)))) + 1
    c = np.array([0.3, 0.71, 0.05])
    tex = tex_of(np.broadcast_to(c, shape + (3,)))
    assert tex.num_levels == T.mip_count(H, W) and tex.levels[-1].shape[:2] == (1, 1)
    for m, lv in enumerate(tex.levels):
        assert lv.shape[:2] == (max(1, H >> m), max(1, W >> m))
        np.testing.assert_array_equal(np.asarray(lv), np.broadcast_to(c, lv.shape))  # exactly
    img = RNG.rand(H, W, 3)
    for dtype, rtol in ((np.float64, 1e-13), (np.float32, 3e-6)):
        tex = tex_of(img.astype(dtype))
        for lv in tex.levels:
            assert lv.dtype == dtype
            np.testing.assert_allclose(np.asarray(lv, np.float64).mean((0, 1)), img.astype(dtype).mean((0, 1)), rtol=rtol)


@pytest.mark.parametrize("n", [3, 5, 7, 9, 15])
def test_odd_downsample_is_the_exact_box(n):
    x = RNG.rand(n, 2)
    want = box_downsample_1d(x, n // 2)
    got = T.build_mips(x[:, None, :], 2)[1][:, 0, :]  # (n, 1, 2) -> (n // 2, 1, 2)
    np.testing.assert_allclose(got, want, rtol=1e-13)
    img = RNG.rand(n, n + 1, 1)  # odd rows, even columns: both filters in one level
    want2 = box_downsample_1d(box_downsample_1d(img, n // 2).transpose(1, 0, 2), (n + 1) // 2).transpose(1, 0, 2)
    np.testing.assert_allclose(T.build_mips(img, 2)[1], want2, rtol=1e-13)


def test_srgb_checker_level1_is_the_linear_mean():
    lo, hi = 50, 200
    checker = np.where((np.arange(8)[:, None] + np.arange(8)[None, :]) % 2 == 0, lo, hi).astype(np.uint8)
    alpha = np.where(np.arange(8)[None, :] % 2 == 0, 0, 255).astype(np.uint8) * np.ones((8, 1), np.uint8)
    img = np.stack([checker, checker, checker, alpha], -1)
    tex = T.Texture.from_image(img, srgb=True, dtype=jnp.float64)
    linear_mean = 0.5 * (srgb_eotf(lo / 255) + srgb_eotf(hi / 255))
    wrong = srgb_eotf(0.5 * (lo + hi) / 255)  # decoding the mean of the encoded values
    assert abs(linear_mean - wrong) > 0.05
    l1 = np.asarray(tex.levels[1])
    np.testing.assert_allclose(l1[..., :3], linear_mean, rtol=1e-12)
    np.testing.assert_allclose(l1[..., 3], 0.5, rtol=1e-12)  # alpha is linear: not decoded
    np.testing.assert_allclose(tex.levels[0][..., 0], srgb_eotf(checker / 255), rtol=1e-12)
    data = T.Texture.from_image(img, srgb=False, dtype=jnp.float64)  # a data texture: as stored
    np.testing.assert_allclose(data.levels[1][..., 0], 0.5 * (lo + hi) / 255, rtol=1e-12)


# ------------------------------------------------------------------------------------------
# LOD and anisotropy
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("K", [1, 16])
def test_isotropic_lod_is_log2_k(K):
    tex = tex_of(np.zeros((64, 32, 1)), max_anisotropy=K)
    k = np.array([0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 8.0, 100.0])
    theta = RNG.uniform(0, 2 * np.pi, k.size)  # any orientation: a rotated square footprint
    dx = np.stack([k * np.cos(theta) / 32, k * np.sin(theta) / 64], -1)
    dy = np.stack([-k * np.sin(theta) / 32, k * np.cos(theta) / 64], -1)
    fp = T.footprint(tex, dx, dy)
    np.testing.assert_allclose(fp.lod, np.log2(k), atol=1e-12)
    np.testing.assert_array_equal(fp.taps, 1.0)


def test_anisotropic_lod_uses_the_minor_axis():
    tex = tex_of(np.zeros((64, 128, 1)), max_anisotropy=8)
    k = np.array([0.5, 1.0, 2.0, 4.0, 2.0, 2.0, 3.0])
    a = np.array([2.0, 4.0, 8.0, 3.0, 16.0, 64.0, 1.0])  # major / minor
    theta = RNG.uniform(0, 2 * np.pi, k.size)
    c, s = np.cos(theta), np.sin(theta)
    dx = np.stack([a * k * c / 128, a * k * s / 64], -1)  # major axis along x
    dy = np.stack([-k * s / 128, k * c / 64], -1)
    fp = T.footprint(tex, dx, dy)
    want_taps = np.minimum(a, 8)
    np.testing.assert_allclose(fp.lod, np.log2(k * a / want_taps), atol=1e-12)  # log2 k while a <= 8
    np.testing.assert_array_equal(fp.taps, want_taps)
    aniso = a > 1  # (a square footprint's major axis is either one)
    np.testing.assert_allclose(fp.major[aniso], dx[aniso], atol=1e-15)
    fp = T.footprint(tex, dy, dx)  # major axis along y
    np.testing.assert_allclose(fp.lod, np.log2(k * a / want_taps), atol=1e-12)
    np.testing.assert_allclose(fp.major[aniso], dx[aniso], atol=1e-15)
    iso = T.footprint(tex_of(np.zeros((64, 128, 1)), max_anisotropy=1), dx, dy)
    np.testing.assert_allclose(iso.lod, np.log2(k * a), atol=1e-12)  # GL rho = max axis


def test_anisotropic_taps_average_along_the_major_axis():
    # columns alternate 0/1 (detail along u only), rows carry a smooth ramp (detail along v)
    H, W = 64, 64
    ramp = np.sin(2 * np.pi * np.arange(H) / H)
    img = ((np.arange(W) % 2)[None, :] + ramp[:, None])[..., None]
    uv = np.stack([RNG.rand(64), RNG.rand(64)], -1)
    dx = np.array([16.0 / W, 0.0])  # 16 texels across u per pixel
    dy = np.array([0.0, 1.0 / H])  # 1 texel down v
    aniso = T.sample(tex_of(img, max_anisotropy=16), uv, dx, dy)[..., 0]
    want = 0.5 + np.interp(uv[:, 1] * H - 0.5, np.arange(-1, H + 1), np.concatenate([ramp[-1:], ramp, ramp[:1]]))
    np.testing.assert_allclose(aniso, want, atol=1e-12)  # the column pattern averaged, rows sharp
    iso = T.sample(tex_of(img, max_anisotropy=1), uv, dx, dy)[..., 0]  # lambda = 4: the ramp blurs
    assert np.max(np.abs(iso - want)) > 0.01


# ------------------------------------------------------------------------------------------
# Gradients
# ------------------------------------------------------------------------------------------

_UV = np.array([[0.31, 0.62], [0.77, 0.18], [0.05, 0.93], [0.52, 0.47]])
_DX = np.array([[0.0, 0.0], [2.6 / 16, 0.4 / 8], [1.3 / 16, 0.0], [9.0 / 16, 3.0 / 8]])
_DY = np.array([[0.0, 0.0], [-0.3 / 16, 1.9 / 8], [5.1 / 16, 0.2 / 8], [1e9, 0.0]])


def test_grad_wrt_texels_matches_finite_differences():
    with jax.enable_x64(True):
        img = RNG.uniform(0.05, 0.95, (8, 16, 3))
        w = RNG.rand(4, 3)

        def f(x):  # the texture is built inside: the gradient runs through decode and pyramid
            tex = T.Texture.from_image(x, srgb=True, wrap_s="mirror", max_anisotropy=4)
            return jnp.sum(w * T.sample(tex, _UV, _DX, _DY))

        g = jax.jit(jax.grad(f))(img)
        assert np.all(np.isfinite(g)) and np.count_nonzero(g) > 20
        coords = list(RNG.choice(img.size, 8, replace=False)) + list(np.flatnonzero(np.asarray(g))[::9][:16])
        assert_grad_matches_fd(f, img, coords, step=1e-6, atol=1e-9, rtol=1e-6)


def test_grad_wrt_uv_and_footprint_matches_finite_differences():
    with jax.enable_x64(True):
        tex = tex_of(RNG.rand(16, 16, 2), wrap_t="clamp", max_anisotropy=4)

        def f(uv, dx, dy):
            return jnp.sum(T.sample(tex, uv, dx, dy) * jnp.array([1.0, -0.7]))

        g = assert_grad_matches_fd(lambda uv: f(uv, _DX, _DY), _UV, range(_UV.size), step=1e-7, atol=1e-7, rtol=1e-6)
        assert np.count_nonzero(g[:6]) == 6
        # footprint: pixel 1 is anisotropic (2 taps, lambda ~ 0.94), pixel 2 (4 taps, lambda ~
        # 0.38); away from the tap-count steps the result is smooth in the derivatives
        g = assert_grad_matches_fd(lambda dx: f(_UV, dx, _DY), _DX, [2, 3, 4], step=1e-8, atol=1e-6, rtol=1e-5)
        assert np.all(g[[2, 3, 4]] != 0)
        assert_grad_matches_fd(lambda dy: f(_UV, _DX, dy), _DY, [2, 3, 5], step=1e-8, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("K", [1, 8])
def test_gradients_finite_at_zero_and_huge_derivatives(K):
    img = RNG.rand(8, 8, 3).astype(np.float32)
    tex = tex_of(img, max_anisotropy=K)
    uv = np.array([[0.3, 0.4], [0.6, 0.1], [1e6, -3e7], [0.5, 0.5]], np.float32)
    dx = np.array([[0, 0], [3e37, 0], [1e-30, 0], [np.inf, 0]], np.float32)
    dy = np.array([[0, 0], [0, 3e37], [0, 0], [0, 1e-3]], np.float32)

    def f(levels, uv, dx, dy):
        return jnp.sum(T.sample(T.Texture(levels, max_anisotropy=K), uv, dx, dy))

    out = T.sample(tex, uv, dx, dy)
    assert out.dtype == jnp.float32 and np.all(np.isfinite(out))
    np.testing.assert_allclose(out[1], img.mean((0, 1)), rtol=1e-5)  # huge footprint: the 1x1 level
    grads = jax.jit(jax.grad(f, argnums=(0, 1, 2, 3)))(tex.levels, uv, dx, dy)
    for g in jax.tree_util.tree_leaves(grads):
        assert np.all(np.isfinite(g))


# ------------------------------------------------------------------------------------------
# Ray differentials and texture transforms
# ------------------------------------------------------------------------------------------


def _plane_closed_form(h, pitch_deg, fov_deg, W, H, A, c):
    """A camera at (0, h, 0) looking down by `pitch` towards +z at the plane y = 0 with
    uv = A (X, Z) + c: uv and its pixel derivatives by the quotient rule, in float64."""
    p = np.deg2rad(pitch_deg)
    f = np.array([0.0, -np.sin(p), np.cos(p)])
    r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    up = np.cross(r, f)
    t = np.tan(np.deg2rad(fov_deg) / 2)
    x = (2 * (np.arange(W) + 0.5) / W - 1) * t * W / H
    y = (1 - 2 * (np.arange(H) + 0.5) / H) * t
    d = f + x[None, :, None] * r + y[:, None, None] * up  # unnormalised: the hit is scale-free
    ddx, ddy = (2 * t / H) * r, -(2 * t / H) * up
    s = h / -d[..., 1]  # X = h dx / -dy, Z = h dz / -dy
    XZ = np.stack([d[..., 0] * s, d[..., 2] * s], -1)

    def deriv(dd):  # d/dp (h d_a / -d_y) = h (dd_a (-d_y) + d_a dd_y) / d_y^2
        return np.stack([h * (dd[i] * -d[..., 1] + d[..., i] * dd[1]) / d[..., 1] ** 2 for i in (0, 2)], -1)

    uv = XZ @ A.T + c
    return uv, deriv(ddx) @ A.T, deriv(ddy) @ A.T


def test_ray_differentials_on_a_plane_match_the_closed_form():
    h, pitch, fov, W, H = 1.3, 25.0, 50.0, 24, 16
    A = np.array([[0.7, 0.2], [-0.3, 0.45]])
    c = np.array([0.1, -0.4])
    P = np.array([[0.3, 0.0, 0.5], [2.0, 0.0, 1.0], [-1.0, 0.0, 4.0]])  # any triangle on y = 0
    UV = P[:, [0, 2]] @ A.T + c
    p = np.deg2rad(pitch)
    target = (0.0, h - np.sin(p), np.cos(p))
    cam = jax.jit(T.pinhole_ray_differentials, static_argnums=(4, 5), static_argnames="dtype")
    o, d, ddx, ddy = cam((0.0, h, 0.0), target, (0.0, 1.0, 0.0), fov, W, H, dtype=jnp.float64, offset=jnp.array([0.5, 0.5]))
    uv, dudx, dudy = jax.jit(T.uv_derivatives_on_triangle)(*P, *UV, o, d, ddx, ddy)
    uv_w, dudx_w, dudy_w = _plane_closed_form(h, pitch, fov, W, H, A, c)
    below = np.asarray(d[..., 1]) < -1e-3  # rows that see the plane
    assert below.sum() > 100
    for got, want in ((uv, uv_w), (dudx, dudx_w), (dudy, dudy_w)):
        np.testing.assert_allclose(np.asarray(got)[below], want[below], rtol=1e-9, atol=1e-12)
    # the pixel-derivative of the direction against finite differences of the pixel offset
    cam = jax.jit(T.pinhole_ray_differentials, static_argnums=(4, 5), static_argnames="dtype")
    e = 1e-6
    _, d1, _, _ = cam((0.0, h, 0.0), target, (0, 1, 0), fov, W, H, dtype=jnp.float64, offset=jnp.array([0.5, 0.5 + e]))
    _, d0, _, _ = cam((0.0, h, 0.0), target, (0, 1, 0), fov, W, H, dtype=jnp.float64, offset=jnp.array([0.5, 0.5 - e]))
    np.testing.assert_allclose((d1 - d0) / (2 * e), ddy, atol=1e-8)


def test_orthographic_ray_differentials_give_the_texel_footprint_in_closed_form():
    """An orthographic camera's rays move with the pixel, not turn: on a square of side 2 with uv
    running 0..1 across it, facing the camera at any tilt of the view about its normal, a pixel of
    2 ymag / H world units covers du = (2 ymag / H) / 2 along the image's x and dv the same along
    its y (with the signs of the square's axes as the image sees them)."""
    import jaxpbr as jp
    from jaxpbr.rendering import stages
    from jaxpbr.rendering.mesh import Mesh, cast, concat_meshes, mesh_surface
    from jaxpbr.rendering.scene import primary_rays
    from jaxpbr.rendering.visibility import embree_available

    if not embree_available():
        pytest.skip("embreex not installed")
    quad = Mesh(positions=np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32),
                triangles=np.array([[0, 1, 2], [0, 2, 3]], np.int32),
                texcoords=np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32), material=jp.Material())
    ymag, n = 0.75, 24
    cam = jp.Camera(position=(0.0, 0.0, 4.0), target=(0.0, 0.0, 0.0), projection="orthographic", ymag=ymag, width=n, height=n)
    arrays = concat_meshes([quad], jnp.float32)
    o_px, d_px = primary_rays(cam)
    prim = cast(arrays, o_px, d_px)
    @jax.jit
    def duv(o_px, d_px, prim):
        o, d = tuple(o_px[..., i] for i in range(3)), tuple(d_px[..., i] for i in range(3))
        ddir, dorig = stages._ray_differentials(cam, d, jnp.float32)
        return mesh_surface(arrays, prim, o, d, need_uv=True, ddir=ddir, dorig=dorig)["duv"][0]

    hit = np.asarray(prim) >= 0
    assert hit.all()  # the 1.5 x 1.5 view lies inside the square
    step = 2 * ymag / n / 2  # world units per pixel, over the square's 2 units per uv unit
    dx, dy = (np.asarray(a) for a in duv(o_px, d_px, prim))
    np.testing.assert_allclose(dx[hit], np.broadcast_to([step, 0.0], dx[hit].shape), atol=1e-6)
    np.testing.assert_allclose(dy[hit], np.broadcast_to([0.0, step], dy[hit].shape), atol=1e-6)
    # The same footprint everywhere: no perspective foreshortening.
    assert np.ptp(dx[hit][:, 0]) < 1e-6


def test_ray_differentials_finite_on_grazing_and_degenerate_triangles():
    P = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], np.float32)
    UV = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], np.float32)
    o = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], np.float32)
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], np.float32)  # parallel, in-plane, normal
    dd = np.full((3, 3), 1e-3, np.float32)

    def f(P, o, d):
        out = T.uv_derivatives_on_triangle(*P, *UV, o, d, dd, -dd)
        return sum(jnp.sum(x) for x in out), out

    vg = jax.jit(jax.value_and_grad(f, argnums=(0, 1, 2), has_aux=True))
    for tri in (P, np.stack([P[0], P[1], P[1]]), np.stack([P[0], P[0], P[0]]), np.stack([P[0], P[1], 2 * P[1]])):
        (_val, out), grads = vg(tri, o, d)
        for x in jax.tree_util.tree_leaves((out, grads)):
            assert np.all(np.isfinite(x)), tri
    _, (uv, dudx, dudy) = jax.jit(f)(np.stack([P[0], P[1], P[1]]), o, d)  # degenerate: uv0, no footprint
    np.testing.assert_array_equal(uv, np.broadcast_to(UV[0], (3, 2)))
    np.testing.assert_array_equal(dudx, 0.0)
    np.testing.assert_array_equal(dudy, 0.0)


def test_khr_texture_transform_examples_and_derivatives():
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    # "utilizes only the lower left quadrant of the source image, rotated clockwise 90 degrees"
    M = T.texture_transform_matrix(offset=(0.0, 1.0), rotation=np.pi / 2, scale=(0.5, 0.5))
    uv, _, _ = T.apply_texture_transform(M, corners)
    np.testing.assert_allclose(uv, [[0.0, 1.0], [0.0, 0.5], [0.5, 1.0], [0.5, 0.5]], atol=1e-12)
    # "inverts the T axis, effectively defining a bottom-left origin"
    uv, _, _ = T.apply_texture_transform(T.texture_transform_matrix((0.0, 1.0), 0.0, (1.0, -1.0)), corners)
    np.testing.assert_allclose(uv, [[0.0, 1.0], [1.0, 1.0], [0.0, 0.0], [1.0, 0.0]], atol=1e-12)
    # derivatives: the Jacobian of the uv map (autodiff of the transform of uv)
    M = T.texture_transform_matrix((0.3, -0.2), 0.7, (2.0, 0.5))
    pts = RNG.rand(5, 2)
    dx, dy = RNG.randn(5, 2), RNG.randn(5, 2)
    _, tdx, tdy = T.apply_texture_transform(M, pts, dx, dy)
    J = jax.jacfwd(lambda p: T.apply_texture_transform(M, p)[0])(pts[0])
    np.testing.assert_allclose(tdx, dx @ np.asarray(J).T, atol=1e-12)
    np.testing.assert_allclose(tdy, dy @ np.asarray(J).T, atol=1e-12)


# ------------------------------------------------------------------------------------------
# Sampler construction, validation, transformations
# ------------------------------------------------------------------------------------------


def test_gltf_sampler_enums():
    assert T.sampler_from_gltf(None) == {
        "wrap_s": "repeat", "wrap_t": "repeat", "mag_filter": "linear", "min_filter": "linear_mipmap_linear"
    }
    s = T.sampler_from_gltf({"magFilter": 9728, "minFilter": 9986, "wrapS": 33071, "wrapT": 33648})
    assert s == {"wrap_s": "clamp", "wrap_t": "mirror", "mag_filter": "nearest", "min_filter": "nearest_mipmap_linear"}
    for enum, name in T.GLTF_MIN_FILTERS.items():
        assert T.Texture.from_gltf(np.zeros((4, 4, 3)), {"minFilter": enum}, srgb=False).min_filter == name
    with pytest.raises(InputError, match="minFilter"):
        T.sampler_from_gltf({"minFilter": 1234})
    tex = T.Texture.from_gltf(np.zeros((4, 4, 3), np.uint8), {"wrapS": 33648}, srgb=True, max_anisotropy=4)
    assert (tex.wrap_s, tex.wrap_t, tex.srgb, tex.max_anisotropy, tex.num_levels) == ("mirror", "repeat", True, 4, 3)


def test_validation():
    with pytest.raises(ValueError, match="wrap_s"):
        tex_of(np.zeros((4, 4, 1)), wrap_s="border")
    with pytest.raises(ValueError, match="min_filter"):
        tex_of(np.zeros((4, 4, 1)), min_filter="trilinear")
    with pytest.raises(ValueError, match="max_anisotropy"):
        tex_of(np.zeros((4, 4, 1)), max_anisotropy=0)
    with pytest.raises(ValueError, match="level 1"):
        T.Texture((np.zeros((4, 4, 1)), np.zeros((3, 2, 1))))
    with pytest.raises(TypeError, match="srgb"):
        T.Texture.from_image(np.zeros((4, 4, 3)), srgb=None)
    two = T.Texture.from_image(np.zeros((8, 8, 1)), srgb=False, num_levels=2)  # a truncated chain
    assert two.num_levels == 2 and np.all(np.isfinite(T.sample_lod(two, np.array([0.5, 0.5]), 5.0)))


def test_jit_and_vmap_over_textures_and_pixels():
    imgs = RNG.rand(3, 8, 8, 2)
    uv = RNG.rand(3, 10, 2)
    dx = np.full((3, 10, 2), [3.0 / 8, 0.0])
    dy = np.full((3, 10, 2), [0.0, 0.7 / 8])

    def one(img, uv, dx, dy):
        return T.sample(T.Texture.from_image(img, srgb=True, max_anisotropy=4), uv, dx, dy)

    batched = jax.jit(jax.vmap(one))(imgs, uv, dx, dy)
    for b in range(3):
        np.testing.assert_allclose(batched[b], one(imgs[b], uv[b], dx[b], dy[b]), atol=1e-12)
    # a batch of textures as one pytree (leading batch axis on every level)
    texs = jax.vmap(lambda im: T.Texture.from_image(im, srgb=True, max_anisotropy=4))(imgs)
    assert texs.levels[1].shape == (3, 4, 4, 2)
    out = jax.jit(jax.vmap(T.sample))(texs, uv, dx, dy)
    np.testing.assert_allclose(out, batched, atol=1e-12)
