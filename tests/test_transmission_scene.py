"""Transmission that shows the scene behind (KHR_materials_transmission, thin-walled): a
transmissive sphere before a checkered quad, against a float64 reference of the same rays.

The asset is written here (a single-sided UV sphere of transmission 1, an unlit quad with a
checkered texture behind it; checked with the Khronos glTF-Validator when it is installed) and
lit by a uniform environment of radiance 1, so that every term of the reference is a closed form
or a float64 quadrature written here, independent of the renderer:

* the camera's rays and their hits on the sphere's triangles (Moeller-Trumbore, float64), the
  normal interpolated from the vertex normals (glTF);
* roughness 0: the pixel is F(n.v) (the mirror reflection of the uniform sky) plus
  (1 - F(n.v)) x what the straight ray sees behind the sphere: the quad's texel (sRGB-decoded;
  an unlit material shows its colour) or the sky (1); F = Schlick with f0 = 0.04;
* roughness > 0: the reflection and the thin-walled BTDF (1 - F(v.h)) D(h_T) V_T |n.l| (the
  reflection lobe mirrored through the tangent plane, separable Smith V_T; `jaxpbr.shading.layered`)
  integrated by importance sampling the GGX normal distribution in float64, every transmitted
  sample traced to the quad or the sky.

A single-sided sphere's back faces let the rays through (glTF: a single-sided triangle is not seen
from behind), so one transmissive surface stands between the camera and the quad."""

from __future__ import annotations

import numpy as np
import pytest
from gltf_writer import FLOAT, UINT, Builder, assert_valid, png_bytes, uv_sphere

import jaxpbr as jp
from jaxpbr.ibl.cubemap import Cubemap

W, H = 64, 48
CAM = dict(position=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), fov_y_deg=40.0)
QUAD_Z, QUAD_HALF = -2.0, 3.0
#: 8 x 8 texels of a checkerboard (sRGB 8-bit values), drawn with NEAREST filtering
CELLS = 8
DARK, LIGHT = 40, 230
F0 = 0.04


def checker_u8() -> np.ndarray:
    i, j = np.meshgrid(np.arange(CELLS), np.arange(CELLS), indexing="ij")
    v = np.where((i + j) % 2 == 0, LIGHT, DARK).astype(np.uint8)
    return np.stack([v, v, v, np.full_like(v, 255)], -1)


def srgb_to_linear(c):
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def sphere_before_quad(out, roughness: float):
    """The asset: a single-sided UV sphere (transmission 1, base colour white) at the origin and an
    unlit checkered quad at z = QUAD_Z facing +z."""
    b = Builder()
    b.add("images", {"bufferView": b.view(png_bytes(checker_u8())), "mimeType": "image/png"})
    b.add("samplers", {"magFilter": 9728, "minFilter": 9728, "wrapS": 33071, "wrapT": 33071})  # NEAREST, clamp
    b.add("textures", {"source": 0, "sampler": 0})
    glass = b.add("materials", {
        "name": "glass", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0,
                                                  "roughnessFactor": roughness},
        "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}}})
    backdrop = b.add("materials", {"name": "checker", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}},
                                   "extensions": {"KHR_materials_unlit": {}}})
    pos, nrm, uv, tri = sphere_mesh()
    sphere = {"attributes": {"POSITION": b.accessor(pos, FLOAT, "VEC3", minmax=True),
                             "NORMAL": b.accessor(nrm, FLOAT, "VEC3"), "TEXCOORD_0": b.accessor(uv, FLOAT, "VEC2")},
              "indices": b.accessor(tri.reshape(-1).astype(np.uint32), UINT, "SCALAR"), "material": glass}
    q = QUAD_HALF
    qpos = np.array([[-q, -q, QUAD_Z], [q, -q, QUAD_Z], [q, q, QUAD_Z], [-q, q, QUAD_Z]], np.float32)
    quad = {"attributes": {"POSITION": b.accessor(qpos, FLOAT, "VEC3", minmax=True),
                           "NORMAL": b.accessor(np.tile(np.float32([0, 0, 1]), (4, 1)), FLOAT, "VEC3"),
                           "TEXCOORD_0": b.accessor(np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32), FLOAT, "VEC2")},
            "indices": b.accessor(np.array([0, 1, 2, 0, 2, 3], np.uint32), UINT, "SCALAR"), "material": backdrop}
    b.add("meshes", {"primitives": [sphere, quad]})
    b.add("scenes", {"nodes": [b.add("nodes", {"mesh": 0})]})
    b.doc["scene"] = 0
    b.used("KHR_materials_transmission", "KHR_materials_unlit")
    path = b.write(out / f"glass_r{roughness:g}.glb", mode="glb")
    assert_valid(path)
    return path


def sphere_mesh():
    return uv_sphere(24, 48)


# ------------------------------------------------------------------------------------------------
# the float64 reference


def camera_rays():
    """Unit directions (H, W, 3) through the pixel centres (jaxpbr.Camera's convention: +x right,
    +y up, rows from the top) from CAM's position, float64."""
    t = np.tan(np.deg2rad(CAM["fov_y_deg"]) / 2)
    x = (2 * (np.arange(W) + 0.5) / W - 1) * t * W / H
    y = (1 - 2 * (np.arange(H) + 0.5) / H) * t
    d = np.stack(np.broadcast_arrays(x[None, :], y[:, None], -np.ones((H, W))), -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def hit_sphere(o, d):
    """Nearest front-face hit of rays (N, 3) on the sphere's triangles: (t, shading normal), t = inf
    where they miss. Moeller-Trumbore in float64."""
    pos, nrm, _, tri = sphere_mesh()
    P, N = pos.astype(np.float64), nrm.astype(np.float64)
    v0, v1, v2 = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    e1, e2 = v1 - v0, v2 - v0
    fn = np.cross(e1, e2)
    best_t = np.full(len(d), np.inf)
    best_n = np.zeros((len(d), 3))
    for s in range(0, len(d), 256):
        dd, oo = d[s:s + 256, None, :], o[s:s + 256, None, :]
        pv = np.cross(dd, e2[None])
        det = np.sum(e1[None] * pv, -1)
        front = np.sum(fn[None] * dd, -1) < 0
        inv = np.where(np.abs(det) > 1e-14, 1 / np.where(det == 0, 1, det), 0)
        tv = oo - v0[None]
        u = np.sum(tv * pv, -1) * inv
        qv = np.cross(tv, e1[None])
        v = np.sum(dd * qv, -1) * inv
        t = np.sum(e2[None] * qv, -1) * inv
        ok = front & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        t = np.where(ok, t, np.inf)
        k = np.argmin(t, 1)
        rows = np.arange(len(k))
        tk, uk, vk = t[rows, k], u[rows, k], v[rows, k]
        n = (1 - uk - vk)[:, None] * N[tri[k, 0]] + uk[:, None] * N[tri[k, 1]] + vk[:, None] * N[tri[k, 2]]
        best_t[s:s + 256] = tk
        best_n[s:s + 256] = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return best_t, best_n


def behind(p, d):
    """What rays from p along d see: the quad's linear texel, else the sky (1); and the distance of
    the hit's uv from the nearest texel border in texels (inf off the quad)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (QUAD_Z - p[..., 2]) / d[..., 2]
    x = p + t[..., None] * d
    on = (t > 0) & (np.abs(x[..., 0]) < QUAD_HALF) & (np.abs(x[..., 1]) < QUAD_HALF)
    s = (x[..., 0] + QUAD_HALF) / (2 * QUAD_HALF) * CELLS  # u in texels
    r = (QUAD_HALF - x[..., 1]) / (2 * QUAD_HALF) * CELLS  # v in texels (v = 0 at the top)
    ii = np.clip(np.floor(r), 0, CELLS - 1).astype(int)
    jj = np.clip(np.floor(s), 0, CELLS - 1).astype(int)
    texel = srgb_to_linear(checker_u8()[ii, jj, 0] / 255.0)
    edge = np.minimum(np.abs(s - np.round(s)), np.abs(r - np.round(r)))
    return np.where(on, texel, 1.0), np.where(on, edge, np.inf)


def schlick(c):
    return F0 + (1 - F0) * (1 - c) ** 5


def reference(roughness: float, samples: int = 2048, seed: int = 0):
    """(image (H, W), sphere mask, distance of what the centre ray sees behind from a texel border)."""
    d = camera_rays().reshape(-1, 3)
    o = np.broadcast_to(np.asarray(CAM["position"], np.float64), d.shape)
    t, n = hit_sphere(o, d)
    on = np.isfinite(t)
    img, edge = behind(o, d)
    p = o + np.where(on, t, 0)[:, None] * d
    v = -d
    nv = np.sum(n * v, -1)
    if roughness == 0:
        F = schlick(np.clip(nv, 0, 1))
        seen, edge_b = behind(p, d)
        img = np.where(on, F + (1 - F) * seen, img)
        edge = np.where(on, edge_b, edge)
        return img.reshape(H, W), on.reshape(H, W), edge.reshape(H, W)
    a = roughness ** 2
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(on)
    out = img.copy()
    _, edge_b = behind(p, d)
    edge = np.where(on, edge_b, edge)
    for k in idx:
        nk, vk = n[k], v[k]
        tvec = np.cross([0.0, 0.0, 1.0] if abs(nk[2]) < 0.999 else [1.0, 0.0, 0.0], nk)
        tvec /= np.linalg.norm(tvec)
        bvec = np.cross(nk, tvec)
        # stratified GGX normal-distribution samples
        u1 = (np.arange(samples) + rng.random(samples)) / samples
        u2 = rng.permutation(samples) / samples + rng.random(samples) / samples
        cos_t = np.sqrt((1 - u1) / (1 + (a * a - 1) * u1))
        sin_t = np.sqrt(1 - cos_t ** 2)
        phi = 2 * np.pi * u2
        h = (sin_t * np.cos(phi))[:, None] * tvec + (sin_t * np.sin(phi))[:, None] * bvec + cos_t[:, None] * nk
        vh = h @ vk
        lr = 2 * vh[:, None] * h - vk  # reflected
        nl = lr @ nk
        nvk = max(nv[k], 1e-9)
        ok = (nl > 0) & (vh > 0)

        def g1(c):
            return 2 * c / (c + np.sqrt(a * a + (1 - a * a) * c * c))

        nh = cos_t
        F = schlick(np.clip(vh, 0, 1))
        # reflection, height-correlated Smith (the core BRDF): f cos / pdf = F G2 (v.h) / (n.v n.h)
        lam = lambda c: (np.sqrt(a * a + (1 - a * a) * c * c) / np.maximum(c, 1e-300) - 1) / 2  # noqa: E731
        g2c = 1 / (1 + lam(np.maximum(nl, 1e-12)) + lam(nvk))
        refl = np.where(ok, F * g2c * vh / (nvk * nh), 0.0)
        # thin transmission: the mirrored lobe, separable Smith, (1 - F(v.h)); the sample's ray
        # leaves below the surface along l = lr mirrored through the tangent plane
        lt = lr - 2 * nl[:, None] * nk
        seen, _ = behind(np.broadcast_to(p[k], lt.shape), lt)
        trans = np.where(ok, (1 - F) * g1(np.maximum(nl, 1e-12)) * g1(nvk) * vh / (nvk * nh), 0.0) * seen
        out[k] = np.mean(refl) * 1.0 + np.mean(trans)
    return out.reshape(H, W), on.reshape(H, W), edge.reshape(H, W)


# ------------------------------------------------------------------------------------------------


def uniform_sky():
    return jp.Environment(radiance=Cubemap.from_function(lambda d: 0.0 * d + 1.0, 32))


def render(path, **options):
    cam = jp.Camera(**CAM, width=W, height=H)
    scene = jp.load_gltf(path, camera=cam, width=W, height=H, environment=uniform_sky())
    # antialias=False: the references sample the pixel centres (the outlines' blend would mix the
    # sphere's silhouette pixels with the quad behind).
    opts = dict(extract_lights=False, shadows=False, multiscatter=False, antialias=False)
    opts.update(options)
    return np.asarray(jp.render(scene, **opts), np.float64)[..., 0]


@pytest.fixture(scope="module")
def smooth_asset(tmp_path_factory):
    return sphere_before_quad(tmp_path_factory.mktemp("transmission"), 0.0)


def test_smooth_glass_shows_the_checkered_quad_behind_it(smooth_asset):
    ref, on, edge = reference(0.0)
    img = render(smooth_asset)
    # pixels whose ray through the sphere lands well inside a texel, away from the silhouette
    # (where one float32 hit decides between the sphere and the quad)
    keep = on & (edge > 0.05)
    err = np.abs(img - ref)[keep]
    assert keep.sum() > 300
    # the reference's F is Schlick's at n.v; the renderer's split-sum LUT at roughness 0 holds it
    # to its own resolution
    assert np.median(err) < 1e-5 and err.max() < 1e-4, (np.median(err), err.max())
    # both texel colours are seen through the glass, darkened by 1 - F
    seen = img[keep]
    assert seen.min() < 0.1 and seen.max() > 0.7
    # the environment-only split sum (transmission_depth=0) shows the sky instead
    old = render(smooth_asset, transmission_depth=0)
    dark = keep & (ref < 0.2)
    assert np.all(old[dark] > 0.9)
    # outside the sphere: the quad's texels and the sky, as they are
    keep = ~on & (edge > 0.05) & np.isfinite(edge)
    np.testing.assert_allclose(img[keep], ref[keep], rtol=1e-5)


def refract(d, n, eta):
    c = -np.sum(d * n, -1, keepdims=True)
    k = 1 - eta ** 2 * (1 - c ** 2)
    return eta * d + (eta * c - np.sqrt(np.maximum(k, 0))) * n


def test_a_volume_sphere_refracts_the_quad_through_its_chord(smooth_asset):
    """An analytic sphere with KHR_materials_volume (thickness > 0, ior 1.5, no attenuation):
    the ray refracts in, crosses the chord and refracts out (Snell, float64 here); the pixel is
    F(n.v) + (1 - F(n.v)) x what the exit ray sees (the entry interface's Fresnel; the volume's
    split sum carries 1 - E at the entry, `layered_ibl`)."""
    cam = jp.Camera(**CAM, width=W, height=H)
    loaded = jp.load_gltf(smooth_asset, camera=cam, width=W, height=H, environment=uniform_sky())
    quad = loaded.objects[1]
    R, ior = 1.0, 1.5
    glass = jp.Material(base_color=(1.0, 1.0, 1.0), metallic=0.0, roughness=0.0, transmission=1.0, thickness=1.0, ior=ior)
    scene = jp.Scene(camera=cam, objects=(jp.Sphere(center=(0.0, 0.0, 0.0), radius=R, material=glass), quad),
                     environment=uniform_sky())
    img = np.asarray(jp.render(scene, extract_lights=False, shadows=False, multiscatter=False, antialias=False), np.float64)[..., 0]

    d = camera_rays().reshape(-1, 3)
    o = np.broadcast_to(np.asarray(CAM["position"], np.float64), d.shape)
    b = np.sum(o * d, -1)
    disc = b * b - (np.sum(o * o, -1) - R * R)
    on = disc > 0
    t = -b - np.sqrt(np.maximum(disc, 0))
    p = o + t[:, None] * d
    n = p / R
    mu = np.clip(-np.sum(n * d, -1), 0, 1)
    t_in = refract(d, n, 1 / ior)
    chord = -2 * R * np.sum(t_in * n, -1)
    q = p + chord[:, None] * t_in
    d_out = refract(t_in, -q / R, ior)
    seen, edge = behind(q, d_out)
    F = schlick(mu)
    ref = np.where(on, F + (1 - F) * seen, 1.0).reshape(H, W)
    keep = (on & (mu > 0.3)).reshape(H, W) & (edge.reshape(H, W) > 0.05)
    assert keep.sum() > 200
    err = np.abs(img - ref)[keep]
    assert np.median(err) < 1e-4 and err.max() < 1e-3, (np.median(err), err.max())
    # the refraction turns the checkerboard over (the sphere is a lens): the straight rays' texels differ
    straight, _ = behind(p, d)
    assert np.mean(np.abs(straight.reshape(H, W)[keep] - seen.reshape(H, W)[keep]) > 0.5) > 0.2


def test_transmission_is_finite_and_differentiable_through_the_scene(smooth_asset):
    """Gradients of the image with respect to the glass's roughness and the quad's texels (seen
    only through the transmitted rays on the sphere's pixels) are finite, and the texels' one is
    non-zero there."""
    import jax
    import jax.numpy as jnp

    from jaxpbr._pytree import evolve

    cam = jp.Camera(**CAM, width=24, height=18)
    scene = jp.load_gltf(smooth_asset, camera=cam, width=24, height=18, environment=uniform_sky())
    sphere, quad = scene.objects

    slot = quad.material.base_color_texture

    def loss(rough, level0):
        m = sphere.material
        sph = evolve(sphere, material=evolve(m, roughness=rough))
        tex = evolve(slot.texture, levels=(level0,) + tuple(slot.texture.levels[1:]))
        # (an unlit material's colour is its emission: the texture is the emissive slot's too)
        q = evolve(quad, material=evolve(quad.material, base_color_texture=evolve(slot, texture=tex),
                                         emissive_texture=evolve(quad.material.emissive_texture, texture=tex)))
        img = jp.render(evolve(scene, objects=(sph, q)), extract_lights=False, shadows=False, transmission_samples=2)
        return jnp.sum(img[6:12, 8:16])

    g_r, g_t = jax.grad(loss, argnums=(0, 1))(jnp.asarray(0.3), jnp.asarray(slot.texture.levels[0]))
    assert np.isfinite(float(g_r)) and np.all(np.isfinite(np.asarray(g_t)))
    assert np.abs(np.asarray(g_t)).sum() > 0


@pytest.mark.slow  # ~30 s: five renders and a float64 quadrature of every sphere pixel
@pytest.mark.parametrize("roughness", [0.15, 0.4])
def test_rough_glass_converges_to_the_reference_as_rays_grow(tmp_path, roughness):
    """Rough thin-walled glass: the error against the float64 quadrature of the BTDF through the
    scene falls as the transmitted rays per pixel grow, with no bias beyond the split sum's, and
    every sampled level is far closer than the environment-only split sum."""
    path = sphere_before_quad(tmp_path, roughness)
    ref, on, _ = reference(roughness, samples=2048)
    mean = ref[on].mean()
    err = {}
    for k in (1, 4, 16, 64):
        img = render(path, transmission_samples=k)
        err[k] = (np.abs(img - ref)[on].mean() / mean, (img - ref)[on].mean() / mean)
    env_only = np.abs(render(path, transmission_depth=0) - ref)[on].mean() / mean
    means = [err[k][0] for k in (1, 4, 16, 64)]
    assert all(b < a for a, b in zip(means, means[1:], strict=False)), means
    assert means[-1] < 0.08 and means[1] < 0.4, means
    assert all(abs(err[k][1]) < 0.03 for k in (4, 16, 64)), err
    assert env_only > 1.0 and means[0] < 0.8 * env_only
    # deterministic: the same rays again
    np.testing.assert_array_equal(render(path, transmission_samples=4), render(path, transmission_samples=4))


def test_smooth_glass_under_an_orthographic_camera(smooth_asset):
    """The same closed form with parallel camera rays (origins on the plane z = 5, along -z): the
    transmitted rays carry the orthographic camera's origin differentials."""
    ymag = 1.5
    cam = jp.Camera(position=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), projection="orthographic", ymag=ymag, width=W, height=H)
    scene = jp.load_gltf(smooth_asset, camera=cam, width=W, height=H, environment=uniform_sky())
    img = np.asarray(jp.render(scene, extract_lights=False, shadows=False, multiscatter=False, antialias=False), np.float64)[..., 0]
    x = (2 * (np.arange(W) + 0.5) / W - 1) * ymag * W / H
    y = (1 - 2 * (np.arange(H) + 0.5) / H) * ymag
    o = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.full((H, W), 5.0)), -1).reshape(-1, 3)
    d = np.broadcast_to(np.array([0.0, 0.0, -1.0]), o.shape)
    t, n = hit_sphere(o, d)
    on = np.isfinite(t)
    p = o + np.where(on, t, 0)[:, None] * d
    F = schlick(np.clip(-(n @ np.array([0.0, 0.0, -1.0])), 0, 1))
    seen, edge = behind(p, d)
    ref = np.where(on, F + (1 - F) * seen, seen).reshape(H, W)
    keep = (on.reshape(H, W)) & (edge.reshape(H, W) > 0.05)
    assert keep.sum() > 200
    err = np.abs(img - ref)[keep]
    assert np.median(err) < 1e-5 and err.max() < 1e-4, (np.median(err), err.max())


def test_render_batch_and_one_program_trace_the_transmitted_rays(smooth_asset):
    """render_batch (staged on the CPU) and a render as one program (a GPU's path, run here on the
    CPU) see the quad through the glass as the staged render does. (Transmissive meshes walk their
    shadow rays' hits on the host engine: the device BVH leaves them to it, `mesh.device_accel`.)"""
    from jaxpbr.rendering import execute

    cam = jp.Camera(**CAM, width=24, height=18)
    scene = jp.load_gltf(smooth_asset, camera=cam, width=24, height=18, environment=uniform_sky())
    opts = dict(extract_lights=False, shadows=False, multiscatter=False)
    one = np.asarray(jp.render(scene, **opts))
    old = np.asarray(jp.render(scene, transmission_depth=0, **opts))
    assert np.abs(one - old).max() > 0.5  # the traced quad, not the sky, is behind the glass
    ints = np.asarray([1.0, 0.5], np.float32)
    batch = np.asarray(jp.render_batch(scene, env_intensity=ints, **opts))
    np.testing.assert_allclose(batch[0], one, rtol=1e-5, atol=1e-6)
    half = np.asarray(jp.render(scene.replace(environment=scene.environment.replace(intensity=0.5)), **opts))
    np.testing.assert_allclose(batch[1], half, rtol=1e-5, atol=1e-6)
    saved = (execute.EXECUTION.staged, execute.EXECUTION.device_visibility)
    try:
        execute.EXECUTION.staged, execute.EXECUTION.device_visibility = False, True
        assert execute._with_device_accel(scene, execute.EXECUTION) is scene
        device = np.asarray(jp.render(scene, **opts))
    finally:
        execute.EXECUTION.staged, execute.EXECUTION.device_visibility = saved
    np.testing.assert_allclose(device, one, rtol=1e-5, atol=1e-6)
