"""The suite compiles its programs with XLA:CPU's loop emitters (tests/conftest.py), the library's
users get XLA's default fusion emitters for most programs: here the same programs are compiled with
each (explicit compile options, whatever XLA_FLAGS says) and held to the same float64 reference.

The two emitters write the same operations but contract different products into FMAs, so their
float32 results differ in the last bits, amplified where the shading is steep (a sharp highlight):
they are not compared with each other but with the float64 evaluation of the same function, and
neither may be less accurate than the other: each one's largest and root-mean-square relative
errors are at most twice the other's (two roundings of one computation). An emitter that computes
something else, or less precisely, fails that; a suite verdict on the loop emitters then holds for
the fusion emitters. The default suite compiles the layered BSDF with every extension both ways; the
lights and the split sum, the extensions under lights and a whole render are in the slow set (the
fusion emitters take 3 to 7 s to compile each of them on 2 cores)."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.rendering.aovs import aovs
from jaxpbr.rendering.demo import uv_sphere
from jaxpbr.rendering.mesh import Mesh

EMITTERS = {"fusion": {"xla_cpu_use_fusion_emitters": True}, "loop": {"xla_cpu_use_fusion_emitters": False}}


def _both(fn, args32, args64):
    """{emitter: float32 output} of jit(fn) compiled with each emitter, and the float64 output."""
    low = jax.jit(fn).lower(*args32)
    out = {name: np.asarray(low.compile(compiler_options=opts)(*args32), np.float64) for name, opts in EMITTERS.items()}
    return out, np.asarray(jax.jit(fn)(*args64), np.float64)


def _check(out, ref, floor):
    """Each emitter's (largest, root-mean-square) relative error against ref, |out - ref| / (|ref| +
    floor), at most twice the other's."""
    rel = {name: np.abs(x - ref) / (np.abs(ref) + floor) for name, x in out.items()}
    err = {name: (float(r.max()), float(np.sqrt(np.mean(r * r)))) for name, r in rel.items()}
    assert np.isfinite(list(err.values())).all(), err
    for a, b in (("loop", "fusion"), ("fusion", "loop")):
        assert err[a][0] <= 2.0 * err[b][0] and err[a][1] <= 2.0 * err[b][1], err
    return err


def test_the_suite_runs_on_the_emitters_its_configuration_chose():
    """XLA_FLAGS (read by the CPU backend when it starts, inherited by the processes tests start)
    carries the loop emitters unless $JAXPBR_TEST_EMITTERS is "fusion"."""
    import conftest

    flags = os.environ.get("XLA_FLAGS", "")
    if conftest.EMITTERS == "loop":
        assert "xla_cpu_use_fusion_emitters" in flags, flags
    else:
        assert "--xla_cpu_use_fusion_emitters=false" not in flags, flags


def _layered_inputs(dtype, k=128, seed=0):
    rng = np.random.default_rng(seed)

    def unit(x):
        return x / np.linalg.norm(x, axis=-1, keepdims=True)

    n = unit(rng.normal(size=(k, 3)) * 0.3 + [0.0, 0.0, 1.0])
    v = unit(rng.normal(size=(k, 3)) * [1, 1, 0.6] + [0, 0, 0.7])
    t = unit(np.cross(n, [0.3, 1.0, 0.1]))
    rough = rng.uniform(0.05, 1.0, k)
    return tuple(jnp.asarray(x, dtype) for x in (n, v, t, rough))


def _layered_material(rough):
    return jp.Material(base_color=(0.8, 0.5, 0.2), metallic=0.3, roughness=rough, clearcoat=0.7, clearcoat_roughness=0.2,
                       sheen_color=(0.9, 0.4, 0.6), sheen_roughness=0.5, specular=0.8, specular_color=(1.0, 0.9, 0.8),
                       ior=1.7, anisotropy_strength=0.5, anisotropy_rotation=0.4, transmission=0.3, thickness=0.5,
                       attenuation_distance=2.0, attenuation_color=(0.9, 0.6, 0.3))


def _cast(x, dtype):
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), x)


def test_the_layered_bsdf_is_as_accurate_with_either_emitter():
    """Every KHR extension group at once (`brdf`, the Charlie sheen's albedo table included):
    float32 with each emitter against the float64 evaluation."""
    table = jp.shading.shipped_luts.sheen_lut()

    def bsdf(n, v, t, rough):
        return jp.brdf(n, v, v[::-1], _layered_material(rough), tangent=t, sheen_lut=_cast(table, n.dtype))

    out, ref = _both(bsdf, _layered_inputs(jnp.float32), _layered_inputs(jnp.float64))
    _check(out, ref, floor=1e-3 * np.abs(ref).max())


@pytest.fixture(scope="module")
def maps():
    env = jp.envs.sky_with_sun_cubemap(16)
    return env, jp.irradiance(env, size=8), jp.prefilter(env, size=16), jp.brdf_lut()


@pytest.mark.slow
def test_lights_and_the_split_sum_are_as_accurate_with_either_emitter(maps):
    """The core material under a point light and a disc light (the code of the render's direct and
    sun stages) plus the split sum with its multiple-scattering compensation (the IBL stage's)."""
    _, irr, pre, lut = maps
    lights = [jp.PointLight(position=(1.0, 2.0, 3.0), intensity=20.0),
              jp.DirectionalLight(direction=(-0.3, -0.2, -1.0), intensity=3.0, angular_radius=0.05)]

    def shade(n, v, t, rough):
        m = jp.Material(base_color=(0.8, 0.5, 0.2), metallic=0.3, roughness=rough)
        direct = jp.shade_direct(jnp.zeros_like(n), n, v, m, lights)
        return direct + jp.shade_ibl(n, v, m, irr, pre, _cast(lut, n.dtype), multiscatter=True)

    out, ref = _both(shade, _layered_inputs(jnp.float32), _layered_inputs(jnp.float64))
    _check(out, ref, floor=1e-3 * np.abs(ref).max())


@pytest.mark.slow
def test_layered_lights_and_split_sum_are_as_accurate_with_either_emitter(maps):
    """The same material under a point light, a disc light and the split sum with the Charlie map
    (XLA:CPU's fusion emitters take about 7 s to compile these on 2 cores)."""
    from jaxpbr.ibl import sheen_prefilter

    env, irr, pre, lut = maps
    charlie, table = sheen_prefilter.prefilter_charlie(env, size=8), jp.shading.shipped_luts.sheen_lut()
    lights = [jp.PointLight(position=(1.0, 2.0, 3.0), intensity=20.0),
              jp.DirectionalLight(direction=(-0.3, -0.2, -1.0), intensity=3.0, angular_radius=0.05)]

    def shade(n, v, t, rough):
        m, dt = _layered_material(rough), n.dtype
        direct = jp.shade_direct(jnp.zeros_like(n), n, v, m, lights, tangent=t, coat_normal=n, sheen_lut=_cast(table, dt))
        ibl = jp.shade_ibl(n, v, m, irr, pre, _cast(lut, dt), tangent=t, coat_normal=n, sheen_lut=_cast(table, dt), charlie=charlie)
        return direct + ibl

    out, ref = _both(shade, _layered_inputs(jnp.float32), _layered_inputs(jnp.float64))
    _check(out, ref, floor=1e-3 * np.abs(ref).max())


def _scene(env):
    pos, nrm, tri = uv_sphere(8)
    objs = [jp.Sphere(center=(-0.7, 0.0, 0.0), radius=0.5, material=jp.Material(base_color=(0.8, 0.3, 0.2), roughness=0.3)),
            Mesh(positions=pos * 0.5 + np.float32([0.7, 0.0, 0.0]), normals=nrm, triangles=tri,
                 material=jp.Material(base_color=(0.7, 0.6, 0.2), roughness=0.4, metallic=1.0)),
            jp.Plane(point=(0, -0.5, 0), normal=(0, 1, 0), material=jp.Material(roughness=0.9))]
    return jp.Scene(camera=jp.Camera(position=(0, 1.0, 4.0), target=(0, 0, 0), width=40, height=24, fov_y_deg=45.0),
                    objects=objs, lights=[jp.PointLight(position=(2, 3, 3), intensity=30.0)],
                    environment=env)


@pytest.mark.slow
def test_a_render_is_as_accurate_with_either_emitter(maps):
    """Every stage of a render (primary rays, an analytic sphere and plane, a triangle mesh through
    the ray engine's callback, a point light and the sun split out of the sky with shadows, the
    split sum, the background) compiled as one program with each emitter, against the float64
    render of the same scene and maps."""
    scene = _scene(jp.bake(jp.Environment(radiance=maps[0])))

    def render(s, dtype):
        return jp.render(s, shadows=True, dtype=dtype)

    low = jax.jit(lambda s: render(s, "float32")).lower(scene)
    out = {name: np.asarray(low.compile(compiler_options=opts)(scene), np.float64) for name, opts in EMITTERS.items()}
    ref = np.asarray(jax.jit(lambda s: render(s, "float64"))(scene), np.float64)
    # Pixels whose primary ray grazes an edge may hit in float32 and miss in float64: the primitive
    # ids of float32 and float64 must match where they are compared.
    ids = [aovs(scene, ("object_id", "primitive_id"), dtype=dt) for dt in ("float32", "float64")]
    same = (ids[0]["object_id"] == ids[1]["object_id"]) & (ids[0]["primitive_id"] == ids[1]["primitive_id"])
    assert same.mean() > 0.98
    out = {k: v[same] for k, v in out.items()}
    _check(out, ref[same], floor=1e-3 * np.abs(ref).max())
