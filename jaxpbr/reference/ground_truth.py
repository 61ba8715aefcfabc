"""The ground truth of a render: direct lighting with visibility, integrated in float64.

For each camera pixel centre (the surface `jaxpbr.gbuffer` gives: the same hit, shading normal and
per-pixel material after textures as `render` shades) the reference estimates

    Lo = emission + sum_lights f(v, l_k) (n.l_k)+ E_k V(l_k)
         + integral over the sphere of f(v, l) (n.l)+ L_dist(l) V(l) dl

with f the glTF BRDF of `jaxpbr.brdf` (single scattering, no roughness floor beyond 0.001, the
roughness at which a lobe is narrower than any environment's texel), L_dist the distant light:
the environment's level 0 as a piecewise-constant function of its texels (the definition the
float64 IBL references use) turned and scaled as the scene asks, plus the suns split out of it
(`Environment.lights`) where its radiance no longer holds them (a baked set keeps its source as the
radiance: the suns are in it), and the scene's disc lights, as uniform discs, and V the visibility of the environment along l: 0 when
a ray from the surface (offset along the geometric normal, `visibility.offset_ray_origin`) meets a
mesh triangle (either side: a surface blocks light from behind too), a sphere or a plane.
The punctual lights are evaluated exactly (deltas), with shadow rays to them.

The environment integral is estimated by multiple importance sampling with the balance heuristic,
one direction per technique per sample (Veach 1997, the multi-sample model):

* the distant light: a part drawn by its power (the texels, each disc), then a texel drawn from the
  luminance x solid-angle distribution of level 0 and a point uniformly in its face coordinates
  (density (1 + a^2 + b^2)^(3/2) / texel area per steradian), or a direction uniformly in a disc;
* the specular lobe: GGX visible normals (Heitz 2018) at the pixel's roughness, mirrored about them;
* the diffuse lobe: cosine-weighted directions.

Each sample's estimate is sum_t f L cos V / (p_env + p_ggx + p_cos) over the three directions; the
image is the mean over `spp` samples (float64 accumulation) and `stderr` its standard error (the
sample standard deviation / sqrt(spp)), per pixel and channel. Deterministic per `seed`.

Not integrated (each refused with a message, not approximated): the transmission, volume and
anisotropy extensions (their lobes need inputs the G-buffer does not carry: what lies below the
surface, a tangent) and user G-buffers. Alpha-blended, masked and transmissive occluders block
light as opaque ones. Interreflection is an option (`bounces`, default 0: the direct light): paths
continued by BRDF sampling through the surfaces they meet (the renderer's own hits, normals and
textured materials, `stages.surface_of_rays`), each vertex adding its own light.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..conventions import luminance
from ..errors import InputError
from ..ibl.cubemap import dir_to_face, face_to_dir, texel_directions, texel_solid_angles
from ..rendering.mesh import Mesh
from ..rendering.options import RenderOptions
from ..rendering.scene import Plane, Scene, Sphere
from ..rendering.stages import scene_host_arrays, surface_buffer, surface_of_rays
from ..rendering.visibility import TriangleAccel, offset_ray_origin
from .._numerics import safe_normalize
from ..shading.layered import brdf
from ..shading.sampling import pdf_cosine, pdf_ggx_vndf, pdf_reflect, sample_cosine, sample_ggx_vndf, tangent_frame
from ..shading.lights import DirectionalLight, PointLight, SpotLight, shade_direct

__all__ = ["MIN_REFERENCE_ROUGHNESS", "ReferenceImage", "reference_render"]

#: Roughness floor of the ground truth's BRDF (alpha = 1e-6: a mirror for any environment texel).
MIN_REFERENCE_ROUGHNESS = 1e-3
#: Pixels per block of the integration (one compiled BRDF program per block shape).
BLOCK = 4096
#: Samples of a block's distant light estimated together (3 rays each: one call of the ray engine).
SAMPLE_CHUNK = 8
#: Extensions whose lobes the ground truth does not integrate.
_UNSUPPORTED = ("transmission", "volume", "anisotropy")


@dataclasses.dataclass(frozen=True)
class ReferenceImage:
    """A ground-truth render: image (H, W, 3) float64 linear radiance (the background where no
    surface is hit), stderr (H, W, 3) its per-pixel standard error (0 off the surfaces), hit (H, W),
    visible (H, W) the estimated cosine-weighted visible fraction of the sky at each surface
    pixel (1 in the open, 0 fully enclosed; from the cosine-sampled directions), spp and the
    seconds the integration took."""

    image: np.ndarray
    stderr: np.ndarray
    hit: np.ndarray
    visible: np.ndarray
    spp: int
    seconds: float


def reference_render(scene: Scene, *, spp: int = 64, bounces: int = 0, seed: int = 0, options: RenderOptions | None = None,
                     progress=None, **overrides) -> ReferenceImage:
    """The ground truth of `render(scene)`'s direct lighting (module docstring): float64 Monte Carlo
    over the environment with visibility, the punctual lights with shadows, the emission.

    spp: samples per pixel (each one direction per technique: environment, GGX, cosine).
    bounces: 0 (default) the direct light; B > 0 adds the light reflected by the scene's surfaces
        along paths of up to B further vertices (interreflection; each vertex's own direct light
        estimated the same way, paths continued by BRDF sampling).
    seed: the random sequence (the same seed gives the same image).
    options / overrides: `RenderOptions`; only `smith` (the BRDF's G) is read.
    progress: optional callable(done, total) over the pixel blocks.
    """
    t0 = time.perf_counter()
    if not isinstance(scene, Scene):
        raise TypeError(f"reference_render expects a jaxpbr.Scene, got {type(scene).__name__}")
    if isinstance(spp, bool) or not isinstance(spp, int) or spp < 2:
        raise ValueError(f"spp must be an int >= 2 (the standard error needs two samples), got {spp!r}")
    if isinstance(bounces, bool) or not isinstance(bounces, int) or not 0 <= bounces <= 16:
        raise ValueError(f"bounces must be an int in [0, 16], got {bounces!r}")
    if options is not None and not isinstance(options, RenderOptions):
        raise TypeError(f"reference_render: options must be a jaxpbr.RenderOptions, got {type(options).__name__}")
    opts = dataclasses.replace(options or RenderOptions(), **overrides)
    if opts.model != "gltf":
        raise ValueError(f"reference_render integrates the glTF BRDF; model {opts.model!r} has no ground truth here (use model='gltf')")
    _check_scene(scene)
    with jax.enable_x64(True):
        gb, ng = surface_buffer(scene, dataclasses.replace(opts, dtype="float64"))
        m = gb.material
        for g in _UNSUPPORTED:
            if g in m.extensions:
                raise InputError(
                    f"reference_render does not integrate KHR_materials_{g} (its lobe needs what the G-buffer does not carry); "
                    f"render the scene without it to compare, or use jaxpbr.ibl.reference_render for spheres")
        hit = np.asarray(gb.hit)
        H, W = hit.shape
        pos = np.asarray(gb.position, np.float64)
        n = np.asarray(gb.normal, np.float64)
        v = np.asarray(gb.view, np.float64)
        ng = np.asarray(ng, np.float64)
        leaves = jax.tree_util.tree_map(np.asarray, m)
        occ = _Occluders(scene)
        discs = [x for x in scene.lights if _is_disc(x)]
        env = _EnvSampler(scene.environment, discs) if (scene.environment is not None or discs) else None
        idx = np.flatnonzero(hit.reshape(-1))
        mean = np.zeros((H * W, 3))
        sq = np.zeros((H * W, 3))
        vis = np.zeros(H * W)
        rng = np.random.default_rng(seed)
        blocks = range(0, idx.size, BLOCK)
        for b, start in enumerate(blocks):
            sel = idx[start:start + BLOCK]
            mb = jax.tree_util.tree_map(lambda x, sel=sel: _take(x, sel, H, W), leaves)
            P, N, V, NG = (a.reshape(-1, 3)[sel] for a in (pos, n, v, ng))
            est, est_sq, visible = _integrate_block(P, N, V, NG, mb, env, occ, scene, opts, spp, rng, bounces)
            mean[sel], sq[sel], vis[sel] = est, est_sq, visible
            if progress is not None:
                progress(b + 1, len(blocks))
        var = np.maximum(sq - mean * mean, 0.0) * spp / (spp - 1)
        stderr = np.sqrt(var / spp)
        img = mean.reshape(H, W, 3)
        bg = _background(scene, -v, hit)
        img = np.where(hit[..., None], img, bg)
        stderr = np.where(hit[..., None], stderr.reshape(H, W, 3), 0.0)
    return ReferenceImage(image=img, stderr=stderr, hit=hit, visible=np.where(hit, vis.reshape(H, W), 0.0), spp=spp,
                          seconds=time.perf_counter() - t0)


def _check_scene(scene: Scene) -> None:
    if scene.gbuffer is not None:
        raise InputError("reference_render traces the scene's objects; a user G-buffer has none to occlude the light")
    for light in scene.lights:
        if not isinstance(light, (PointLight, DirectionalLight, SpotLight)):
            raise InputError(f"reference_render takes point, directional and spot lights, got a {type(light).__name__} "
                             "(pass the lights one by one)")


def _is_disc(light) -> bool:
    return isinstance(light, DirectionalLight) and bool(np.any(np.asarray(light.angular_radius) > 0))


def _take(x, sel, H, W):
    """A per-pixel material leaf's values at the flat pixel indices sel."""
    x = np.asarray(x, np.float64)
    x = np.broadcast_to(x, (H, W) + x.shape[2:]) if x.shape[:2] != (H, W) else x
    return x.reshape((H * W,) + x.shape[2:])[sel]


# --------------------------------------------------------------------------------------------------
# visibility


class _Occluders:
    """Rays against every object of the scene: the meshes through the ray engine (`TriangleAccel`,
    every triangle blocks), spheres and planes in float64 here."""

    def __init__(self, scene: Scene):
        arrays = scene_host_arrays(scene, jnp.float32) if any(isinstance(o, Mesh) for o in scene.objects) else None
        self.accel = None
        if arrays is not None:
            self.accel = TriangleAccel.build(np.asarray(arrays["positions"], np.float32), np.asarray(arrays["triangles"], np.int32))
        self.spheres = [(np.asarray(o.center, np.float64), float(o.radius)) for o in scene.objects if isinstance(o, Sphere)]
        self.planes = [(np.asarray(o.point, np.float64), np.asarray(o.normal, np.float64)) for o in scene.objects
                       if isinstance(o, Plane)]

    def occluded(self, o, d, tfar):
        """bool (N,): something lies along o + t d, 0 < t < tfar (o already offset off its surface)."""
        out = np.zeros(len(o), bool)
        if self.accel is not None:
            out |= np.asarray(self.accel.occluded(o.astype(np.float32), d.astype(np.float32), 0.0, tfar.astype(np.float32)))
        for c, r in self.spheres:
            oc = o - c
            b = np.sum(oc * d, -1)
            cc = np.sum(oc * oc, -1) - r * r
            disc = b * b - cc
            sq = np.sqrt(np.maximum(disc, 0.0))
            t0, t1 = -b - sq, -b + sq
            # the ray's origin sits on a sphere's surface when the sphere is the shaded object:
            # only a crossing beyond a small fraction of the radius counts
            eps = 1e-7 * max(r, 1.0)
            t = np.where(t0 > eps, t0, t1)
            out |= (disc > 0) & (t > eps) & (t < tfar)
        for p, nn in self.planes:
            den = d @ nn
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((p - o) @ nn) / den
            out |= (np.abs(den) > 1e-300) & (t > 1e-7) & (t < tfar)
        return out


# --------------------------------------------------------------------------------------------------
# the environment


class _EnvSampler:
    """The distant light in the world: the environment's level 0 (piecewise constant per texel),
    the suns split out of it (`Environment.lights`) and the scene's disc lights, each a uniform
    disc of radiance color x intensity / (pi sin^2 radius); their radiance along directions, and
    directions drawn from their power (texels by luminance x solid angle, discs uniformly inside)
    with the density of the whole mixture."""

    def __init__(self, env, discs=()):
        self.rot = float(np.asarray(env.rotation)) if env is not None else 0.0
        scale = float(np.asarray(env.intensity)) if env is not None else 0.0
        suns = []  # (unit direction towards the disc, cos radius, solid angle, radiance (3,))
        split = list(env.lights or ()) if env is not None else []
        if split and self._holds_suns(env, split):
            split = []  # (a baked set's radiance is its source, suns included; its maps are the residual)
        for light, frame in [(x, True) for x in split] + [(x, False) for x in discs]:
            d = -np.asarray(light.direction, np.float64)
            d = d / np.linalg.norm(d)
            if frame:
                d = _rotate_y(d[None], self.rot)[0]
            th = float(np.asarray(light.angular_radius))
            rad = np.asarray(light.color, np.float64) * float(np.asarray(light.intensity)) / (math.pi * math.sin(th) ** 2)
            suns.append((d, math.cos(th), 2.0 * math.pi * (1.0 - math.cos(th)), rad * (scale if frame else 1.0)))
        self.suns = suns
        if env is not None:
            lv = np.asarray(env.radiance.levels[0], np.float64)[..., :3]  # (6, S, S, 3)
            self.S = lv.shape[1]
            self.L = lv * scale
        else:
            self.S = 1
            self.L = np.zeros((6, 1, 1, 3))
        om = texel_solid_angles(self.S)
        w = np.maximum(luminance(self.L), 0.0) * om
        if not np.isfinite(w.sum()) or not all(np.all(np.isfinite(x[3])) for x in suns):
            raise InputError("the environment's radiance is not finite; it has no ground truth")
        powers = np.array([w.sum()] + [max(float(luminance(x[3])), 0.0) * x[2] for x in suns])
        if powers.sum() <= 0:  # nothing shines: sample the sphere uniformly (every estimate is 0)
            w, powers = om, np.array([1.0] + [0.0] * len(suns))
        self.p_part = powers / powers.sum()
        w = w if w.sum() > 0 else om  # (black texels: never drawn, p_part[0] = 0)
        self.p_texel = (w / w.sum()).reshape(-1)
        self.cdf = np.cumsum(self.p_texel)
        self.cdf[-1] = 1.0
        self._arrays = None

    @staticmethod
    def _holds_suns(env, lights) -> bool:
        """Whether the environment's radiance still holds the suns split out of it (`bake` keeps the
        source as the radiance and the residual in its maps; a user's split can pass the residual):
        the texels within a sun's disc (widened by two texels) carry at least half of its luminous
        power above the map's median."""
        lv = np.asarray(env.radiance.levels[0], np.float64)[..., :3]
        S = lv.shape[1]
        y = luminance(lv)
        om = texel_solid_angles(S)
        dirs = texel_directions(S)
        med = float(np.median(y))
        for light in lights:
            c = -np.asarray(light.direction, np.float64)
            c = c / np.linalg.norm(c)
            widen = float(np.asarray(light.angular_radius)) + 2.0 * (math.pi / 2) / S
            inside = dirs @ c >= math.cos(widen)
            held = float(np.sum((y[inside] - med) * om[inside]))
            power = float(luminance(np.asarray(light.color, np.float64))) * float(np.asarray(light.intensity))
            if held < 0.5 * power:
                return False
        return True

    def arrays(self) -> dict:
        """The tables as float64 device arrays, for the compiled estimator (`_distant_proposals`)."""
        if self._arrays is None:
            ns = len(self.suns)
            edges = np.cumsum(self.p_part)
            self._arrays = {k: jnp.asarray(v, jnp.float64) for k, v in {
                "L": self.L, "p_texel": self.p_texel, "cdf": self.cdf, "p_part": self.p_part, "edges": edges,
                "lo": np.concatenate([[0.0], edges[:-1]]), "rot": np.array([math.cos(self.rot), math.sin(self.rot)]),
                "sun_c": np.array([x[0] for x in self.suns]).reshape(ns, 3), "sun_cmax": np.array([x[1] for x in self.suns]),
                "sun_om": np.array([x[2] for x in self.suns]), "sun_rad": np.array([x[3] for x in self.suns]).reshape(ns, 3)}.items()}
        return self._arrays


# The distant light's sampling, density and radiance on the tables of `_EnvSampler.arrays` (E), in
# JAX (float64 inside `_distant_proposals`).


def _turn(d, E, sign):
    """Directions (N, 3) turned by sign x the environment's rotation about +Y (+1: environment ->
    world, -1: world -> environment)."""
    c, s = E["rot"][0], sign * E["rot"][1]
    return jnp.stack([c * d[:, 0] + s * d[:, 2], d[:, 1], -s * d[:, 0] + c * d[:, 2]], -1)


def _env_texel(E, d_env):
    S = E["L"].shape[1]
    face, s, t = dir_to_face(d_env, xp=jnp)
    j = jnp.minimum((s * S).astype(jnp.int32), S - 1)
    i = jnp.minimum((t * S).astype(jnp.int32), S - 1)
    return face, i, j, 2.0 * s - 1.0, 2.0 * t - 1.0


def _env_radiance(E, d):
    face, i, j, _, _ = _env_texel(E, _turn(d, E, -1.0))
    inside = d @ E["sun_c"].T >= E["sun_cmax"]  # (N, suns)
    return E["L"][face, i, j] + inside.astype(d.dtype) @ E["sun_rad"]


def _env_pdf(E, d):
    S = E["L"].shape[1]
    face, i, j, sc, tc = _env_texel(E, _turn(d, E, -1.0))
    p = E["p_texel"].reshape(6, S, S)[face, i, j]
    out = E["p_part"][0] * p * (1.0 + sc * sc + tc * tc) ** 1.5 / (2.0 / S) ** 2
    inside = d @ E["sun_c"].T >= E["sun_cmax"]
    return out + inside.astype(d.dtype) @ (E["p_part"][1:] / jnp.maximum(E["sun_om"], 1e-300))


def _env_sample(E, u):
    """(N, 3) unit world directions from (N, 3) uniform numbers (u[:, 0] also picks the part:
    the texels or a disc, by power)."""
    S = E["L"].shape[1]
    n_parts = E["p_part"].shape[0]
    part = jnp.minimum(jnp.searchsorted(E["edges"], u[:, 0], side="right"), n_parts - 1)
    u0 = jnp.clip((u[:, 0] - E["lo"][part]) / jnp.maximum(E["p_part"][part], 1e-300), 0.0, 1.0 - 1e-16)  # reused within the part
    k = jnp.minimum(jnp.searchsorted(E["cdf"], u0, side="right"), E["cdf"].shape[0] - 1)
    face, rem = jnp.divmod(k, S * S)
    i, j = jnp.divmod(rem, S)
    d = face_to_dir(face, (j + u[:, 1]) / S, (i + u[:, 2]) / S, xp=jnp)
    d = _turn(d / jnp.linalg.norm(d, axis=-1, keepdims=True), E, 1.0)
    for n_s in range(n_parts - 1):
        c, cmax = E["sun_c"][n_s], E["sun_cmax"][n_s]
        ct = 1.0 - u[:, 1] * (1.0 - cmax)
        st = jnp.sqrt(jnp.maximum(1.0 - ct * ct, 0.0))
        phi = 2.0 * math.pi * u[:, 2]
        t, b = tangent_frame(jnp.broadcast_to(c, d.shape))
        on_disc = (st * jnp.cos(phi))[:, None] * t + (st * jnp.sin(phi))[:, None] * b + ct[:, None] * c
        d = jnp.where((part == n_s + 1)[:, None], on_disc, d)
    return d


def _rotate_y(d, angle: float):
    """Directions (N, 3) turned by `angle` about +Y (the environment's rotation, `Environment`)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.stack([c * d[:, 0] + s * d[:, 2], d[:, 1], -s * d[:, 0] + c * d[:, 2]], -1)


def _background(scene: Scene, d, hit):
    env = scene.environment
    if env is not None and env.show_background:
        with jax.enable_x64(False):
            de = _rotate_y(d.reshape(-1, 3), -float(np.asarray(env.rotation)))
            bg = np.asarray(env.radiance.sample(jnp.asarray(de, jnp.float32), 0.0), np.float64)[:, :3] * float(np.asarray(env.intensity))
        return bg.reshape(d.shape)
    return np.broadcast_to(np.asarray(scene.background, np.float64), d.shape)


# --------------------------------------------------------------------------------------------------
# the integral


def _to_world(loc, t, b, n):
    return loc[..., 0:1] * t + loc[..., 1:2] * b + loc[..., 2:3] * n


def _sample_ggx(n, v, a, u):
    """l = reflect(v, h), h a GGX visible normal (alpha a) of view v about n (`sampling.sample_ggx_vndf`), world."""
    t, b = tangent_frame(n)
    v_loc = jnp.stack([jnp.sum(v * t, -1), jnp.sum(v * b, -1), jnp.maximum(jnp.sum(v * n, -1), 1e-12)], -1)
    h = _to_world(sample_ggx_vndf(v_loc, u, a), t, b, n)
    return 2.0 * jnp.sum(v * h, -1, keepdims=True) * h - v


def _sample_cos(n, u):
    t, b = tangent_frame(n)
    return _to_world(sample_cosine(u), t, b, n)


def _pdf_ggx(n, v, l, a):
    """Density (per steradian) of `_sample_ggx`'s l (`sampling.pdf_ggx_vndf`, `pdf_reflect`); 0 below n."""
    h = safe_normalize(v + l)
    vh = jnp.sum(v * h, -1)
    p = pdf_reflect(pdf_ggx_vndf(jnp.sum(n * v, -1), jnp.sum(n * h, -1), vh, a), vh)
    return jnp.where(jnp.sum(n * l, -1) > 0, p, 0.0)


@jax.jit
def _continuations(N, V, a, u):
    """(directions, densities) of one path continuation per vertex: cosine or GGX visible normals
    with probability 1/2 each (u (k, 3))."""
    l = jnp.where((u[:, 0] < 0.5)[:, None], _sample_cos(N, u[:, 1:3]), _sample_ggx(N, V, a, u[:, 1:3]))
    return l, 0.5 * (pdf_cosine(jnp.sum(N * l, -1)) + _pdf_ggx(N, V, l, a))


@functools.partial(jax.jit, static_argnames=("smith",))
def _brdf64(n, v, l, m, *, smith):
    return brdf(n, v, l, m, min_roughness=MIN_REFERENCE_ROUGHNESS, smith=smith)


@functools.partial(jax.jit, static_argnames=("smith",))
def _punctual64(p, n, v, m, lights, vis, *, smith):
    return shade_direct(p, n, v, m, lights, visibility=vis, smith=smith)


@functools.partial(jax.jit, static_argnames=("smith",))
def _distant_proposals(N, V, NG, a, m, E, u, *, smith):
    """The distant light's three proposals per sample (the environment, GGX visible normals, the
    cosine) for S samples of k pixels (u (S, k, 7); N, V, NG (k, 3), a (k,), m per pixel) ->
    directions (3, S, k, 3), live (3, S, k) (above both normals, density > 0: to be traced),
    contributions (3, S, k, 3) f L cos / (p_env + p_ggx + p_cos) as if unblocked, and up (3, S, k)
    (on the viewer's side of the geometric normal)."""
    S, k = u.shape[:2]
    tile = lambda x: jnp.broadcast_to(x, (S,) + x.shape).reshape((S * k,) + x.shape[1:])  # noqa: E731
    N, V, NG, a = tile(N), tile(V), tile(NG), tile(a)
    m = jax.tree_util.tree_map(tile, m)
    u = u.reshape(S * k, 7)
    dirs, lives, cs, ups = [], [], [], []
    for l in (_env_sample(E, u[:, 0:3]), _sample_ggx(N, V, a, u[:, 3:5]), _sample_cos(N, u[:, 5:7])):
        nl = jnp.sum(N * l, -1)
        p = _env_pdf(E, l) + _pdf_ggx(N, V, l, a) + pdf_cosine(nl)
        up = jnp.sum(NG * l, -1) * jnp.sum(NG * V, -1) > 0
        live = (nl > 0) & up & (p > 0)
        w = jnp.where(live, jnp.maximum(nl, 0.0) / jnp.where(live, p, 1.0), 0.0)
        f = brdf(N, V, l, m, min_roughness=MIN_REFERENCE_ROUGHNESS, smith=smith)
        c = jnp.where(live[:, None], f * _env_radiance(E, l) * w[:, None], 0.0)
        dirs.append(l)
        lives.append(live)
        cs.append(c)
        ups.append(up)
    shape = lambda xs: jnp.stack(xs).reshape((3, S, k) + xs[0].shape[1:])  # noqa: E731
    return shape(dirs), shape(lives), shape(cs), shape(ups)


class _Vertex:
    """A block of path vertices (surface points) with what the estimators need: positions P,
    shading normals N, directions to the previous vertex V, geometric normals NG (any side), the
    material (per-vertex leaves), padded to BLOCK times a power of two for the compiled programs
    (a few shapes serve every count)."""

    def __init__(self, P, N, V, NG, m, opts):
        self.k = k = len(P)
        self.size = BLOCK * (1 << max(0, -(-k // BLOCK) - 1).bit_length())
        pad = self.size - k
        self.padf = (lambda x: np.concatenate([x, np.repeat(x[-1:], pad, 0)])) if pad > 0 else (lambda x: x)  # noqa: E731
        self.P, self.N, self.V, self.NG, self.m = P, N, V, NG, m
        self.mj = jax.tree_util.tree_map(lambda x: jnp.asarray(self.padf(np.asarray(x))), m)
        self.nj, self.vj = jnp.asarray(self.padf(N)), jnp.asarray(self.padf(V))
        self.ngj = jnp.asarray(self.padf(NG))
        self.smith = opts.smith
        side = np.where(np.sum(NG * V, -1, keepdims=True) < 0, -NG, NG)  # the viewer's side
        self.up_origin = offset_ray_origin(P.astype(np.float32), side.astype(np.float32)).astype(np.float64)
        r = np.clip(np.broadcast_to(np.asarray(m.roughness, np.float64).reshape(-1)[:k], (k,)), 0.0, 1.0)
        self.a = np.maximum(r, MIN_REFERENCE_ROUGHNESS) ** 2
        self.aj = jnp.asarray(self.padf(self.a))

    def f(self, l):
        return np.asarray(_brdf64(self.nj, self.vj, jnp.asarray(self.padf(l)), self.mj, smith=self.smith))[: self.k]

    def leaves_up(self, l):
        """bool (k,): l leaves on the viewer's side of the surface, above the shading normal's horizon."""
        return (np.sum(self.NG * l, -1) * np.sum(self.NG * self.V, -1) > 0) & (np.sum(self.N * l, -1) > 0)

    def fixed_light(self, scene, occ, opts):
        """(k, 3) the emission and the punctual lights (exact, with shadow rays) at the vertices."""
        out = np.asarray(jax.device_get(_emission(self.mj)))[: self.k]
        punctual = [x for x in scene.lights if not _is_disc(x)]
        if not punctual:
            return out
        P, NG = self.P, self.NG
        vis = []
        for light in punctual:
            if isinstance(light, DirectionalLight):
                dl = -np.asarray(light.direction, np.float64)
                dl = np.broadcast_to(dl / np.linalg.norm(dl), P.shape)
                tfar = np.full(self.k, np.inf)
            else:
                dl = np.asarray(light.position, np.float64) - P
                tfar = np.linalg.norm(dl, axis=-1)
                dl = dl / np.maximum(tfar, 1e-300)[:, None]
                tfar = tfar * (1.0 - 1e-6)
            o = offset_ray_origin(P.astype(np.float32), np.where(np.sum(NG * dl, -1, keepdims=True) < 0, -NG, NG).astype(np.float32))
            vis.append(~occ.occluded(o.astype(np.float64), dl, tfar))
        vis = np.stack(vis, -1).astype(np.float64)
        direct = _punctual64(jnp.asarray(self.padf(P)), self.nj, self.vj, _dark(self.mj), punctual,
                             jnp.asarray(self.padf(vis)), smith=opts.smith)
        return out + np.asarray(direct)[: self.k]

    def distant_light(self, env, occ, u):
        """((S, k, 3) the distant light's estimates, (S, k) whether the cosine direction is open) of
        S samples at once: one direction per technique per sample from the uniform numbers u
        (S, k, 7), balance heuristic; the proposals compiled (`_distant_proposals`), the 3 S k rays
        in one call of the ray engine."""
        S, k = u.shape[0], self.k
        # padded to a whole chunk of samples and a whole block of pixels: one compiled program
        rows = SAMPLE_CHUNK if S > 1 else 1
        u = jnp.asarray(np.pad(u, ((0, rows - S), (0, self.size - k), (0, 0)), constant_values=0.5))
        d, live, c, up = jax.device_get(_distant_proposals(self.nj, self.vj, self.ngj, self.aj, self.mj, env.arrays(), u,
                                                           smith=self.smith))
        d, live, c, up = d[:, :S, :k], live[:, :S, :k], c[:, :S, :k], up[:, :S, :k]  # (3, S, k, ...)
        blocked = np.zeros(live.shape, bool)
        if live.any():
            o = np.broadcast_to(self.up_origin, live.shape + (3,))
            blocked[live] = occ.occluded(o[live], d[live], np.full(int(live.sum()), np.inf))
        est = np.sum(np.where(blocked[..., None], 0.0, c), 0)
        return est, up[2] & ~blocked[2]

    def continue_path(self, u):
        """(directions (k, 3), throughput f cos / p (k, 3)) of one continuation per vertex: cosine or
        GGX visible normals with probability 1/2 each (u (k, 3)); 0 below the surface."""
        l, p = (np.asarray(x)[: self.k] for x in _continuations(self.nj, self.vj, self.aj, jnp.asarray(self.padf(u))))
        nl = np.sum(self.N * l, -1)
        ok = self.leaves_up(l) & (p > 0)
        w = np.where(ok, np.maximum(nl, 0.0) / np.where(ok, p, 1.0), 0.0)
        return l, self.f(l) * w[:, None]


def _integrate_block(P, N, V, NG, m, env, occ, scene, opts, spp, rng, bounces=0):
    """(mean, mean of squares, visible fraction) over spp samples of one block of pixels. Each
    sample: the pixel's fixed light (emission, punctual lights) and distant light, and with bounces
    a path continued `bounces` times by BRDF sampling through the surfaces it meets, each vertex
    adding its own fixed and distant light times the path's throughput (the distant light counts
    only directions that escape and the continuation only those that hit: no light twice)."""
    first = _Vertex(P, N, V, NG, m, opts)
    k = first.k
    base = first.fixed_light(scene, occ, opts)
    acc = np.zeros((k, 3))
    acc2 = np.zeros((k, 3))
    visible = np.zeros(k)
    # Latin hypercube per pixel: each of the 7 dimensions stratified over the spp samples (its own
    # random permutation of the strata per pixel), jittered within each stratum.
    strata = rng.permuted(np.broadcast_to(np.arange(spp)[:, None, None], (spp, k, 7)), axis=0)
    uu = (strata + rng.random((spp, k, 7))) / spp
    for c0 in range(0, spp, SAMPLE_CHUNK):  # the distant light of SAMPLE_CHUNK samples together
        n_c = min(SAMPLE_CHUNK, spp - c0)
        x = np.broadcast_to(base, (n_c, k, 3)).copy()
        if env is not None:
            ests, opens = first.distant_light(env, occ, uu[c0:c0 + n_c])
            x += ests
            visible += opens.sum(0)
        if bounces:
            # every sample's path at once, each through its own surfaces (rows of x flattened)
            flat = x.reshape(n_c * k, 3)
            tile = lambda a: np.concatenate([a] * n_c)  # noqa: E731
            vert = _Vertex(tile(P), tile(N), tile(V), tile(NG), jax.tree_util.tree_map(tile, m), opts)
            through, rows = np.ones((n_c * k, 3)), np.arange(n_c * k)
            for _ in range(bounces):
                l, w = vert.continue_path(rng.random((vert.k, 3)))
                through = through * w
                live = np.any(through > 0, -1)
                if not live.any():
                    break
                hit = _surface_hits(scene, opts, vert.up_origin[live], l[live])
                if hit is None:
                    break
                sel, nxt = hit
                rows = rows[live][sel]
                through = through[live][sel]
                vert = nxt
                add = vert.fixed_light(scene, occ, opts)
                if env is not None:
                    add = add + vert.distant_light(env, occ, rng.random((1, vert.k, 7)))[0][0]
                np.add.at(flat, rows, through * add)
        acc += x.sum(0)
        acc2 += np.sum(x * x, 0)
    return acc / spp, acc2 / spp, visible / spp


def _surface_hits(scene, opts, o, d):
    """The surfaces rays o + t d (t > 0) meet: (indices of the rays that hit, their `_Vertex`), or
    None when none does (`stages.surface_of_rays`: the renderer's own hit, normals and textured
    materials)."""
    if len(o) == 0:
        return None
    hits, P, N, NG, m = [], [], [], [], []
    for s0 in range(0, len(o), BLOCK):
        oo, dd = o[s0:s0 + BLOCK], d[s0:s0 + BLOCK]
        n_b = len(oo)
        pad = BLOCK - n_b
        if pad:
            oo = np.concatenate([oo, np.repeat(oo[-1:], pad, 0)])
            dd = np.concatenate([dd, np.repeat(dd[-1:], pad, 0)])
        gb, ng = surface_of_rays(scene, dataclasses.replace(opts, dtype="float64"), oo, dd)
        h = np.asarray(gb.hit).reshape(-1)[:n_b]
        idx = np.flatnonzero(h)
        hits.append(idx + s0)
        P.append(np.asarray(gb.position, np.float64).reshape(-1, 3)[idx])
        N.append(np.asarray(gb.normal, np.float64).reshape(-1, 3)[idx])
        NG.append(np.asarray(ng, np.float64).reshape(-1, 3)[idx])
        m.append(jax.tree_util.tree_map(lambda x, idx=idx, n=BLOCK: _flat_leaf(x, n)[idx], gb.material))
    sel = np.concatenate(hits)
    if sel.size == 0:
        return None
    mm = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *m)
    P, N, NG = np.concatenate(P), np.concatenate(N), np.concatenate(NG)
    return sel, _Vertex(P, N, -d[sel], NG, mm, opts)


def _flat_leaf(x, n):
    x = np.asarray(x, np.float64)
    x = np.broadcast_to(x, (n, 1) + x.shape[2:]) if x.shape[:2] != (n, 1) else x
    return x.reshape((n,) + x.shape[2:])


@jax.jit
def _emission(m):
    return m.emission()


def _dark(m):
    return m.replace(emissive=jnp.zeros_like(m.emissive))  # (the emission is added once, apart)
