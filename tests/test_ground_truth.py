"""The ground truth of a render (`jaxpbr.reference.reference_render`): float64 Monte Carlo of the
direct light with visibility, checked against closed forms and float64 quadratures written here:

* a Lambertian floor beside an infinite wall under a uniform sky: every direction towards the wall
  is blocked, so exactly half of the cosine-weighted hemisphere is open wherever the point is
  (Lo = albedo x L / 2 on the floor and on the wall alike), where the split sum gives albedo x L;
* a Lambertian floor beside a finite wall (a mesh quad, traced by the ray engine): Lo = albedo x L x
  (1 - F), F the view factor from the floor point to the wall rectangle, the float64 Gauss-Legendre
  quadrature of cos1 cos2 / (pi r^2) over it;
* a convex object (nothing to occlude its light) under the sky with its sun: the ground truth
  equals the unoccluded float64 quadrature of `jaxpbr.ibl.reference_render.reference_ibl` on the
  same G-buffer;
* the point lights' shadows: a sphere's shadow on the floor is black where the light alone lights it.

A material with specular = 0 (KHR_materials_specular) is an exact Lambertian (`jaxpbr.shading.layered`)."""

from __future__ import annotations

import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.errors import InputError
from jaxpbr.ibl.cubemap import Cubemap
from jaxpbr.reference import reference_render

ALBEDO = 0.5
LAMBERT = dict(base_color=(ALBEDO, ALBEDO, ALBEDO), metallic=0.0, roughness=1.0, specular=0.0)


def uniform_sky(face=16, value=1.0):
    return jp.Environment(radiance=Cubemap.from_function(lambda d: 0.0 * d + value, face))


def within(ref, expect, mask, k=4.0):
    """Fraction of the masked pixels whose reference is within k standard errors (+ float64 slack)
    of the expected value, and the mean signed relative error there."""
    err = np.abs(ref.image[..., 0] - expect)[mask]
    se = ref.stderr[..., 0][mask]
    return np.mean(err <= k * se + 1e-9), np.mean((ref.image[..., 0] - expect)[mask]) / np.mean(expect[mask])


def test_floor_beside_an_infinite_wall_sees_half_the_sky():
    m = jp.Material(**LAMBERT)
    floor = jp.Plane(point=(0, 0, 0), normal=(0, 1, 0), material=m)
    wall = jp.Plane(point=(0, 0, 0), normal=(0, 0, 1), material=m)
    cam = jp.Camera(position=(0.7, 3.0, 4.0), target=(0.0, 0.6, 0.0), width=24, height=18)
    scene = jp.Scene(camera=cam, objects=(floor, wall), environment=uniform_sky())
    ref = reference_render(scene, spp=64, seed=1)
    assert ref.hit.all()
    expect = np.full(ref.hit.shape, ALBEDO * 0.5)
    frac, bias = within(ref, expect, ref.hit)
    assert frac > 0.97 and abs(bias) < 0.01, (frac, bias)
    assert np.all(np.abs(ref.visible[ref.hit] - 0.5) < 0.25) and abs(ref.visible[ref.hit].mean() - 0.5) < 0.03
    # the split sum does not see the wall: twice the light
    img = np.asarray(jp.render(scene, extract_lights=False, multiscatter=False))[..., 0]
    np.testing.assert_allclose(img, ALBEDO, rtol=2e-3)


@pytest.mark.parametrize("bounces", [1, 3])
def test_interreflection_between_a_floor_and_a_wall_sums_the_series(bounces):
    """With bounces, each point sees half sky and half the other plane, whose radiance is the
    previous order's: L_B = (a/2) sum_{j<=B} (a/2)^j (-> a / (2 - a), the converged radiosity)."""
    m = jp.Material(**LAMBERT)
    cam = jp.Camera(position=(0.7, 3.0, 4.0), target=(0.0, 0.6, 0.0), width=16, height=12)
    scene = jp.Scene(camera=cam, objects=(jp.Plane(point=(0, 0, 0), normal=(0, 1, 0), material=m),
                                          jp.Plane(point=(0, 0, 0), normal=(0, 0, 1), material=m)), environment=uniform_sky())
    ref = reference_render(scene, spp=64, bounces=bounces, seed=5)
    h = ALBEDO / 2
    expect = h * sum(h ** j for j in range(bounces + 1))
    got = ref.image[ref.hit][:, 0]
    se_mean = np.sqrt(np.sum(ref.stderr[ref.hit][:, 0] ** 2)) / got.size
    assert abs(got.mean() - expect) < 4 * se_mean + 1e-3, (got.mean(), expect, se_mean)
    assert abs(got.mean() - expect) < 0.015 * expect


def _wall_factor(x, z, half=1.0, height=1.0, n=64):
    """View factor from the floor point (x, 0, z) (normal +y) to the wall rectangle
    [-half, half] x [0, height] in the plane z = 0 (normal +z): Gauss-Legendre in float64."""
    g, w = np.polynomial.legendre.leggauss(n)
    X = half * g
    Y = 0.5 * height * (g + 1.0)
    WX, WY = np.meshgrid(w * half, w * 0.5 * height, indexing="ij")
    PX, PY = np.meshgrid(X, Y, indexing="ij")
    out = np.empty(np.shape(x))
    for i, (xi, zi) in enumerate(zip(np.ravel(x), np.ravel(z), strict=True)):
        rx, ry, rz = PX - xi, PY, -zi
        r2 = rx * rx + ry * ry + rz * rz
        out.flat[i] = np.sum(WX * WY * (ry * zi) / (np.pi * r2 * r2))
    return out


def test_floor_beside_a_mesh_wall_matches_the_view_factor_quadrature():
    m = jp.Material(**LAMBERT)
    floor = jp.Plane(point=(0, 0, 0), normal=(0, 1, 0), material=m)
    quad = np.array([[-1, 0, 0], [1, 0, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    wall = jp.Mesh(positions=quad, triangles=np.array([[0, 1, 2], [0, 2, 3]], np.int32), material=m, double_sided=True)
    W, H = 24, 16
    cam = jp.Camera(position=(0.0, 5.0, 0.8), target=(0.0, 0.0, 0.8), up=(0.0, 0.0, -1.0), projection="orthographic",
                    ymag=0.75, width=W, height=H)
    scene = jp.Scene(camera=cam, objects=(floor, wall), environment=uniform_sky())
    ref = reference_render(scene, spp=96, seed=2)
    x = (2 * (np.arange(W) + 0.5) / W - 1) * 0.75 * W / H
    z = 0.8 - (1 - 2 * (np.arange(H) + 0.5) / H) * 0.75  # up = -z: image rows run towards +z
    Z, X = np.meshgrid(z, x, indexing="ij")
    on_floor = ref.hit & (Z > 0.02)
    expect = ALBEDO * (1.0 - _wall_factor(X, Z))
    frac, bias = within(ref, expect, on_floor)
    assert frac > 0.97 and abs(bias) < 0.01, (frac, bias)
    # the wall matters: up to a third of the sky is gone near it
    assert expect[on_floor].min() < 0.8 * ALBEDO


def test_the_device_bvh_traces_the_ground_truth_as_the_host_engine_does(monkeypatch):
    """Off the CPU the ground truth's rays go through the JAX BVH (`TriangleAccel.build`'s "auto"):
    forced here on the CPU, the same image as Embree's (the same seed draws the same rays)."""
    from jaxpbr.rendering import visibility
    from jaxpbr.rendering.demo import concave_scene

    scene = concave_scene(24, 18)
    host = reference_render(scene, spp=8, seed=3)
    build = visibility.TriangleAccel.build.__func__
    backends = []

    def jax_build(cls, *a, **k):
        backends.append("jax")
        return build(cls, *a, **{**k, "backend": "jax"})

    monkeypatch.setattr(visibility.TriangleAccel, "build", classmethod(jax_build))
    device = reference_render(scene, spp=8, seed=3)
    assert backends  # the JAX BVH was built and traced
    # float32 ties (a ray grazing an edge) may resolve differently: nearly every pixel is equal
    same = np.all(np.isclose(device.image, host.image, rtol=1e-9, atol=1e-12), -1)
    assert same[host.hit].mean() > 0.99, same[host.hit].mean()
    np.testing.assert_allclose(device.visible, host.visible, atol=0.02)
    assert (host.visible[host.hit] < 0.9).mean() > 0.2  # not vacuous: the box does occlude


def test_a_convex_object_equals_the_unoccluded_quadrature():
    from jaxpbr.ibl.envs import sky_with_sun_cubemap
    from jaxpbr.ibl.reference_render import reference_ibl

    sky = jp.Environment(radiance=sky_with_sun_cubemap(32))
    metal = jp.Material(base_color=(0.9, 0.6, 0.3), metallic=1.0, roughness=0.4)
    cam = jp.Camera(position=(0, 0, 4.0), target=(0, 0, 0), width=16, height=16, fov_y_deg=35.0)
    scene = jp.Scene(camera=cam, objects=(jp.Sphere(center=(0, 0, 0), radius=1.0, material=metal),), environment=sky)
    ref = reference_render(scene, spp=128, seed=3)
    from jaxpbr.rendering.renderer import gbuffer

    gb = gbuffer(scene)
    quad = reference_ibl(np.asarray(gb.normal, np.float64), np.asarray(gb.view, np.float64), metal, sky.radiance)
    mask = ref.hit & (np.sum(np.asarray(gb.normal) * np.asarray(gb.view), -1) > 0.2)
    for c in range(3):
        err = np.abs(ref.image[..., c] - quad[..., c])[mask]
        assert np.mean(err <= 4 * ref.stderr[..., c][mask] + 1e-3 * quad[..., c][mask]) > 0.95
    assert abs(np.mean(ref.image[mask] - quad[mask]) / np.mean(quad[mask])) < 0.01
    assert np.all(ref.visible[ref.hit] == 1.0)


def test_point_lights_with_their_shadow_rays():
    m = jp.Material(**LAMBERT)
    floor = jp.Plane(point=(0, 0, 0), normal=(0, 1, 0), material=m)
    ball = jp.Sphere(center=(0, 1.0, 0), radius=0.5, material=m)
    light = jp.PointLight(position=(0.0, 3.0, 0.0), intensity=30.0)
    cam = jp.Camera(position=(0.0, 6.0, 0.01), target=(0, 0, 0), width=16, height=16, fov_y_deg=60.0)
    scene = jp.Scene(camera=cam, objects=(floor, ball), lights=(light,), environment=uniform_sky(value=0.0))
    ref = reference_render(scene, spp=2, seed=0)
    # (point samples: the ground truth's rays leave the pixel centres)
    img = np.asarray(jp.render(scene, shadows=True, extract_lights=False, antialias=False), np.float64)
    # no environment light: the reference is the lights' exact term, with its shadow rays
    np.testing.assert_allclose(ref.image, img, rtol=2e-3, atol=1e-6)
    # the ring of the sphere's shadow seen around it is black (without the shadow rays it would be lit)
    unshadowed = np.asarray(jp.render(scene, shadows=False, extract_lights=False, antialias=False), np.float64)
    ring = (ref.image[..., 0] == 0) & (unshadowed[..., 0] > 0.1)
    assert ring.sum() >= 8


def test_the_same_seed_gives_the_same_image_and_another_seed_another():
    m = jp.Material(**LAMBERT)
    scene = jp.Scene(camera=jp.Camera(position=(0, 3, 3), target=(0, 0, 0), width=8, height=8),
                     objects=(jp.Plane(point=(0, 0, 0), normal=(0, 1, 0), material=m), jp.Sphere(center=(0, 0.5, 0), radius=0.5, material=m)),
                     environment=uniform_sky())
    a, b, c = (reference_render(scene, spp=4, seed=s) for s in (7, 7, 8))
    np.testing.assert_array_equal(a.image, b.image)
    assert np.any(a.image != c.image)


def test_what_has_no_ground_truth_is_refused():
    glass = jp.Material(base_color=(1, 1, 1), metallic=0.0, roughness=0.1, transmission=1.0)
    scene = jp.Scene(camera=jp.Camera(position=(0, 0, 3), target=(0, 0, 0), width=4, height=4),
                     objects=(jp.Sphere(center=(0, 0, 0), radius=1.0, material=glass),), environment=uniform_sky())
    with pytest.raises(InputError, match="KHR_materials_transmission"):
        reference_render(scene, spp=2)
    with pytest.raises(ValueError, match="spp"):
        reference_render(scene, spp=1)


def test_a_disc_light_on_a_lambertian_floor_is_its_cap_irradiance():
    """A disc light (a sun of 10 degrees' radius, 40 degrees above the horizon) and no environment:
    the ground truth samples the disc; a Lambertian floor receives albedo/pi x the disc's exact
    irradiance (the renderer's closed form, `lights.cap_irradiance`), the same everywhere."""
    m = jp.Material(**LAMBERT)
    d = np.array([0.0, -np.sin(np.radians(40)), -np.cos(np.radians(40))])
    sun = jp.DirectionalLight(direction=d, intensity=3.0, angular_radius=float(np.radians(10)))
    cam = jp.Camera(position=(0.0, 4.0, 3.0), target=(0, 0, 0), width=12, height=8)
    scene = jp.Scene(camera=cam, objects=(jp.Plane(point=(0, 0, 0), normal=(0, 1, 0), material=m),), lights=(sun,))
    ref = reference_render(scene, spp=64, seed=4)
    expect = ALBEDO / np.pi * 3.0 * np.sin(np.radians(40))  # a disc fully above the horizon: E = E_n cos
    frac, bias = within(ref, np.full(ref.hit.shape, expect), ref.hit)
    assert frac > 0.97 and abs(bias) < 0.01, (frac, bias)


def test_command_line_writes_the_ground_truth_and_its_standard_error(tmp_path, capsys):
    from jaxpbr.cli import main
    from jaxpbr.io import image

    scene = tmp_path / "s.toml"
    scene.write_text(
        '[camera]\nposition = [0, 2, 4]\ntarget = [0, 0, 0]\nwidth = 12\nheight = 8\n\n'
        '[[objects]]\ntype = "sphere"\ncenter = [0, 0.5, 0]\nradius = 0.5\n[objects.material]\nbase_color = [0.5, 0.5, 0.5]\nmetallic = 0.0\n\n'
        '[[objects]]\ntype = "plane"\npoint = [0, 0, 0]\nnormal = [0, 1, 0]\n\n'
        '[environment]\nfile = "procedural:sky"\n')
    out = tmp_path / "gt.png"
    assert main(["render", str(scene), "--reference", "--spp", "4", "--hdr", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "ground truth" in printed and "4 spp" in printed
    hdr = np.asarray(image.read(out.with_suffix(".exr")))
    se = np.asarray(image.read(out.with_suffix(".exr"), channels=["stderr.R", "stderr.G", "stderr.B"]))
    assert hdr.shape == se.shape == (8, 12, 3) and np.all(np.isfinite(hdr))
    assert np.all(se >= 0) and se.max() > 0  # 4 samples: noisy, and said so
    assert main(["render", str(scene), "--reference", "--spp", "1", "-o", str(out)]) == 2


@pytest.mark.slow  # ~15 s; needs Mitsuba 3 (pip install mitsuba), an independent renderer
def test_the_ground_truth_agrees_with_mitsuba_on_the_same_triangles():
    pytest.importorskip("mitsuba")
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "examples" / "mitsuba_ground_truth.py"
    spec = importlib.util.spec_from_file_location("mitsuba_ground_truth", path)
    ex = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ex)
    out = ex.main(["--size", "64", "48", "--spp", "256", "--bounces", "2"])
    median, _, _, bias = out["jp.reference_render"]
    assert abs(bias) < 0.01 and median < 0.04, out["jp.reference_render"]
    # the unshadowed split sum is far off on this concave scene; the ratio estimator is not biased
    assert out["jp.render ibl_visibility=none"][3] > 0.08
    assert abs(out["jp.render ibl_visibility=ratio K=16"][3]) < 0.02
    # with two bounces, against Mitsuba's path tracer
    assert abs(out["reference_render bounces=2"][3]) < 0.015, out["reference_render bounces=2"]
