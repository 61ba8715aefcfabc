"""Recover a glTF asset's base-colour texture and roughness from a few views by gradient descent.

A small glTF 2.0 asset is written in code with pygltflib (a UV sphere of 2,208 triangles whose
material has a 64 x 64 base-colour texture, a checker times a colour gradient stored as an sRGB PNG,
roughness 0.35, metallic 0), loaded with `jaxpbr.load_gltf` and rendered from 4 cameras around it
under an HDR environment (`../shared/data/*.hdr` when there is one, else the procedural sky with
its sun): these are the targets. The fit starts from a grey texture (0.5) and roughness 0.8 and
follows the gradient of all views at once (`jaxpbr.render_batch` over the cameras, inside
`jax.jit(jax.value_and_grad(...))`) with Adam (optax).

Texels and roughness are unconstrained parameters mapped into range by a sigmoid: texels into
(0, 1) (linear: the texture the renderer filters), roughness into [0.05, 1] (docs/math.md 8.8). The
texture's mip pyramid is built inside the step (`jaxpbr.Texture.from_image` is traceable), so the
gradient reaches the texels through the trilinear / anisotropic filtering. Which triangle each
pixel sees (and whether a shadow ray is blocked) is decided on the host (Embree, through
`jax.pure_callback` inside the compiled step) and has no gradient; the surface, the texture
lookups and the shading are JAX. The roughness is held for the first `--warmup` steps: from the
grey start, brighter than the texture on average, its gradient first points the wrong way
(rougher), and past ~0.9 the loss is nearly flat in it while the texture compensates.

The texture error is reported over all texels, over the texels some view sees (a texel holds the
centre of a hit pixel) and over those seen *sharply* (such a pixel reads it from mip level 0). The
renderer's own footprints tell which: the mesh is rendered once with an emissive texture whose
levels encode texel coordinates and level number, nearest filtering within and between levels.
Texels seen only minified (near the silhouettes and the poles) enter the images through averages
of 2 x 2, 4 x 4, ... texels, which the views cannot undo: their error stays large.

Measured on the 2-core CPU this project runs on, defaults (96 x 96, 4 views, 200 steps; the
machine was shared with other jobs, load average 6: times vary by +-50 %):

    environment             roughness  loss (log1p MSE)   texture RMSE all / seen / sharp  per step
    newport_loft.hdr        0.3516     3.45e-3 -> 2.8e-7  0.068 / 0.027 / 0.020            110-180 ms
    procedural:sky + sun    0.3977     3.69e-2 -> 2.2e-5  0.070 / 0.034 / 0.030            320-380 ms

(initial texture RMSE 0.28; 84 % of the texels seen, 81 % sharply; compiling the step 15-30 s; 1.5-2 min in all).
Under the sky the sun, split out as a disc light with a shadow ray per pixel, costs the extra time
per step, and the roughness converges more slowly (more `--steps`).

    pip install 'jaxpbr[examples]'      # optax
    python examples/fit_gltf_material.py [--environment ENV.hdr | procedural:sky] [--steps 200] [--size 96] [--out DIR]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pygltflib

import jaxpbr as jp
from jaxpbr.ibl.cubeio import load_environment
from jaxpbr.rendering.demo import uv_sphere as _uv_sphere

TRUE_ROUGHNESS = 0.35
START_ROUGHNESS = 0.8
R_MIN = 0.05
SHARED_DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"


# ------------------------------------------------------------------------------------------
# The asset
# ------------------------------------------------------------------------------------------


def uv_sphere(n_lat: int = 24, n_lon: int = 48):
    """(positions, normals, uv, triangles) of the library's unit UV sphere (`jaxpbr.rendering.demo.uv_sphere`)
    with texture coordinates u = longitude / 2 pi, v = colatitude / pi (glTF: v runs down the image, v = 0
    at the north pole), on its (n_lat + 1) x (n_lon + 1) vertex grid."""
    pos, nrm, tris = _uv_sphere(n_lat, n_lon=n_lon)
    v, u = np.meshgrid(np.linspace(0.0, 1.0, n_lat + 1), np.linspace(0.0, 1.0, n_lon + 1), indexing="ij")
    return pos, nrm, np.stack([u, v], -1).reshape(-1, 2).astype(np.float32), tris


def pattern(n: int) -> np.ndarray:
    """An (n, n, 3) linear base colour: an 8 x 8 checker times a colour gradient, in [0.03, 0.9]."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    u, v = (j + 0.5) / n, (i + 0.5) / n
    grad = np.stack([0.15 + 0.75 * u, 0.2 + 0.6 * v, 0.9 - 0.7 * u], -1)
    checker = ((np.floor(u * 8) + np.floor(v * 8)) % 2)[..., None]
    return np.clip(grad * (0.3 + 0.7 * checker), 0.03, 0.9).astype(np.float32)


def write_asset(path: Path, texels: np.ndarray, roughness: float) -> Path:
    """A binary glTF (.glb): the UV sphere, one material (baseColorTexture = `texels` written as an
    8-bit sRGB PNG, roughnessFactor, metallicFactor 0) and the default sampler."""
    pos, nrm, uv, tris = uv_sphere()
    with tempfile.TemporaryDirectory() as d:
        png = Path(d) / "base_color.png"
        jp.image.write(png, texels, encoding="srgb")  # linear -> sRGB code values
        png_bytes = png.read_bytes()
    blob = bytearray()
    views, accessors = [], []

    def add(data: bytes, target=None) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), target=target))
        blob.extend(data)
        return len(views) - 1

    def accessor(a: np.ndarray, kind: str, ctype: int, target: int) -> int:
        view = add(np.ascontiguousarray(a).tobytes(), target)
        extra = {"min": a.min(0).tolist(), "max": a.max(0).tolist()} if kind == "VEC3" else {}
        accessors.append(pygltflib.Accessor(bufferView=view, componentType=ctype, count=len(a), type=kind, **extra))
        return len(accessors) - 1

    F, U32, AB, EAB = pygltflib.FLOAT, pygltflib.UNSIGNED_INT, pygltflib.ARRAY_BUFFER, pygltflib.ELEMENT_ARRAY_BUFFER
    attrs = pygltflib.Attributes(
        POSITION=accessor(pos, "VEC3", F, AB), NORMAL=accessor(nrm, "VEC3", F, AB), TEXCOORD_0=accessor(uv, "VEC2", F, AB)
    )
    indices = accessor(tris.reshape(-1), "SCALAR", U32, EAB)
    image_view = add(png_bytes)
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="jaxpbr examples/fit_gltf_material.py"),
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[pygltflib.Node(mesh=0)],
        meshes=[pygltflib.Mesh(primitives=[pygltflib.Primitive(attributes=attrs, indices=indices, material=0)])],
        materials=[pygltflib.Material(pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
            baseColorTexture=pygltflib.TextureInfo(index=0), metallicFactor=0.0, roughnessFactor=roughness,
        ))],
        textures=[pygltflib.Texture(source=0, sampler=0)],
        samplers=[pygltflib.Sampler()],
        images=[pygltflib.Image(bufferView=image_view, mimeType="image/png")],
        accessors=accessors,
        bufferViews=views,
        buffers=[pygltflib.Buffer(byteLength=len(blob))],
    )
    gltf.set_binary_blob(bytes(blob))
    gltf.save_binary(str(path))
    return path


# ------------------------------------------------------------------------------------------
# Views, parameters, texture coverage
# ------------------------------------------------------------------------------------------


def cameras(n: int, size: int) -> jp.Camera:
    """n cameras around the origin (azimuths evenly spaced, elevations alternating +30 / -20 deg),
    as one Camera with batched positions (render_batch's `cameras`)."""
    pos = []
    for k in range(n):
        az = math.radians(30.0 + 360.0 * k / n)
        el = math.radians(30.0 if k % 2 == 0 else -20.0)
        pos.append((3.2 * math.cos(el) * math.sin(az), 3.2 * math.sin(el), 3.2 * math.cos(el) * math.cos(az)))
    return jp.Camera(position=np.asarray(pos, np.float32), target=(0.0, 0.0, 0.0), fov_y_deg=40.0, width=size, height=size)


def logit(p):
    p = np.asarray(p, np.float64)
    return np.log(p / (1.0 - p))


def unpack(theta):
    """Unconstrained parameters -> (texels (T, T, 3) in (0, 1), roughness in [R_MIN, 1])."""
    return jax.nn.sigmoid(theta["texels"]), R_MIN + (1.0 - R_MIN) * jax.nn.sigmoid(theta["roughness"])


def with_material(scene: jp.Scene, like: jp.Texture, texels, roughness) -> jp.Scene:
    """`scene` with its one mesh's material replaced: base colour `texels` (linear; the pyramid is
    built here, traceably) sampled like the texture `like`, roughness `roughness`, metallic 0."""
    tex = jp.Texture.from_image(
        texels, srgb=False, wrap_s=like.wrap_s, wrap_t=like.wrap_t, mag_filter=like.mag_filter,
        min_filter=like.min_filter, max_anisotropy=like.max_anisotropy,
    )
    mat = jp.TexturedMaterial(
        factors=jp.Material(base_color=(1.0, 1.0, 1.0), metallic=0.0, roughness=roughness),
        base_color_texture=jp.TextureSlot(texture=tex, texcoord=0),
    )
    (mesh,) = scene.objects
    return scene.replace(objects=(mesh.replace(material=mat),))


def seen_texels(scene: jp.Scene, cams: jp.Camera, like: jp.Texture) -> tuple[np.ndarray, np.ndarray]:
    """Which texels of the base-colour texture the views see: (seen, sharp), each (n, n) bool.

    seen: the texel holds the centre of a hit pixel in some view; sharp: in some view such a pixel
    reads it from mip level 0 (a footprint of about a texel or less; lambda <= 1/2), not only
    blurred through coarser levels (minified: near the silhouette and the poles, where the fit
    only constrains averages of texels).

    Found with the renderer's own footprints: the mesh is rendered with an emissive texture
    sampled as the base colour is (same anisotropy), whose level m holds the coordinates of its
    texel centres (R = u, G = v) and B = 1 - m / 64, with nearest filtering within and between
    levels, no lights and no environment."""
    from jaxpbr.rendering.texture import mip_count

    n = like.width
    levels = []
    for m in range(mip_count(n, n)):
        k = max(1, n >> m)
        i, j = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
        levels.append(np.stack([(j + 0.5) / k, (i + 0.5) / k, np.full((k, k), 1.0 - m / 64)], -1).astype(np.float32))
    code = jp.Texture(levels=tuple(levels), wrap_s=like.wrap_s, wrap_t=like.wrap_t, mag_filter="nearest",
                      min_filter="nearest_mipmap_nearest", max_anisotropy=like.max_anisotropy)
    mat = jp.TexturedMaterial(
        factors=jp.Material(base_color=(0.0, 0.0, 0.0), metallic=0.0, roughness=1.0, emissive=(1.0, 1.0, 1.0)),
        emissive_texture=jp.TextureSlot(texture=code, texcoord=0),
    )
    (mesh,) = scene.objects
    flat = scene.replace(objects=(mesh.replace(material=mat),), environment=None, lights=(), background=(0.0, 0.0, 0.0))
    img = np.asarray(jp.render_batch(flat, cameras=cams, shadows=False))
    hit = img[..., 2] > 0.5
    level = np.rint((1.0 - img[..., 2][hit]) * 64).astype(int)
    cols = np.clip(np.floor(img[..., 0][hit] * n), 0, n - 1).astype(int)
    rows = np.clip(np.floor(img[..., 1][hit] * n), 0, n - 1).astype(int)
    seen = np.zeros((n, n), bool)
    seen[rows, cols] = True
    sharp = np.zeros((n, n), bool)
    sharp[rows[level == 0], cols[level == 0]] = True
    return seen, sharp


# ------------------------------------------------------------------------------------------
# Output
# ------------------------------------------------------------------------------------------


def display(hdr) -> np.ndarray:
    """Linear HDR -> display-referred [0, 1] (Reinhard tone map; the PNG writer sRGB-encodes)."""
    x = np.asarray(hdr, np.float32)
    return np.clip(x / (1.0 + x), 0.0, 1.0)


def save_grid(path: Path, rows, gap: int = 2) -> None:
    """A PNG of rows of equally sized (H, W, 3) linear images, separated by `gap` white pixels."""
    H, W = rows[0][0].shape[:2]
    out = np.ones((len(rows) * (H + gap) - gap, len(rows[0]) * (W + gap) - gap, 3), np.float32)
    for r, row in enumerate(rows):
        for c, img in enumerate(row):
            out[r * (H + gap) : r * (H + gap) + H, c * (W + gap) : c * (W + gap) + W] = img
    jp.image.write(path, out, encoding="srgb")


def upscale(tex: np.ndarray, size: int) -> np.ndarray:
    """Nearest-neighbour resize of an (n, n, 3) texture to (size, size, 3) (for the grid)."""
    idx = np.minimum((np.arange(size) * tex.shape[0]) // size, tex.shape[0] - 1)
    return tex[idx][:, idx]


# ------------------------------------------------------------------------------------------
# Main
# ------------------------------------------------------------------------------------------


def default_environment() -> str:
    hdrs = sorted(SHARED_DATA.glob("*.hdr")) if SHARED_DATA.is_dir() else []
    return str(hdrs[0]) if hdrs else "procedural:sky"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--environment", default=None,
                    help="equirect .hdr/.exr, or procedural:sky (default: ../shared/data/*.hdr if present, else procedural:sky)")
    ap.add_argument("--face-size", type=int, default=64, help="environment cube face size")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--size", type=int, default=96, help="image size in pixels (square)")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--texture", type=int, default=64, help="texture size in texels (square)")
    ap.add_argument("--lr", type=float, default=0.1, help="Adam step size of the texel logits")
    ap.add_argument("--lr-roughness", type=float, default=None, help="Adam step size of the roughness logit (default: --lr)")
    ap.add_argument("--warmup", type=int, default=25, help="steps that fit the texture alone before the roughness moves")
    ap.add_argument("--loss", choices=("log1p", "linear"), default="log1p")
    ap.add_argument("--print-every", type=int, default=25)
    ap.add_argument("--out", default="fit_gltf_out", help="output folder (PNG grids, the asset)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    # The asset and its targets.
    true_texels = pattern(args.texture)
    asset = write_asset(out / "sphere.glb", true_texels, TRUE_ROUGHNESS)
    env_name = args.environment or default_environment()
    t0 = time.perf_counter()
    env = jp.bake(jp.Environment(radiance=load_environment(env_name, face_size=args.face_size)))
    print(f"environment {env_name} ({args.face_size}^2 faces) baked in {time.perf_counter() - t0:.2f} s")
    cams = cameras(args.views, args.size)
    # load_gltf's camera is the scene's (its width / height); render_batch replaces it per view.
    cam0 = jp.Camera(position=np.asarray(cams.position)[0], target=(0.0, 0.0, 0.0), fov_y_deg=40.0, width=args.size, height=args.size)
    scene = jp.load_gltf(asset, camera=cam0, width=args.size, height=args.size, environment=env)
    (mesh,) = scene.objects
    slot = mesh.material.base_color_texture
    truth = np.asarray(slot.texture.levels[0])[..., :3]  # what the loader decoded (sRGB PNG -> linear)
    print(f"asset: {mesh.num_triangles} triangles, {args.texture}^2 base-colour texture; {args.views} views of {args.size}^2")
    t0 = time.perf_counter()
    targets = jp.render_batch(scene, cameras=cams)
    targets.block_until_ready()
    print(f"targets rendered in {time.perf_counter() - t0:.2f} s")
    seen, sharp = seen_texels(scene, cams, slot.texture)

    def loss_fn(theta, env):
        texels, rough = unpack(theta)
        sc = with_material(scene.replace(environment=env), slot.texture, texels, rough)
        imgs = jp.render_batch(sc, cameras=cams)  # (views, H, W, 3)
        if args.loss == "linear":
            return jnp.mean((imgs - targets) ** 2), imgs
        # log1p: the sun's highlight would otherwise outweigh the rest of the image.
        return jnp.mean((jnp.log1p(imgs) - jnp.log1p(targets)) ** 2), imgs

    lr_r = args.lr if args.lr_roughness is None else args.lr_roughness
    # The roughness waits until the texture is roughly right: from the grey start (brighter than
    # the texture on average) its gradient first points the wrong way, rougher, and past ~0.9 the
    # loss is nearly flat in it (the texture compensates).
    lr_r = optax.join_schedules([optax.constant_schedule(0.0), optax.constant_schedule(lr_r)], [args.warmup])
    opt = optax.multi_transform({"texels": optax.adam(args.lr), "roughness": optax.adam(lr_r)},
                                {"texels": "texels", "roughness": "roughness"})

    @jax.jit
    def step(theta, state, env):
        """One Adam step; the loss, gradient and images are those of the parameters passed in."""
        (loss, imgs), g = jax.value_and_grad(loss_fn, has_aux=True)(theta, env)
        updates, state = opt.update(g, state, theta)
        return optax.apply_updates(theta, updates), state, loss, g, imgs

    theta = {
        "texels": jnp.zeros((args.texture, args.texture, 3), jnp.float32),  # sigmoid(0) = 0.5: grey
        "roughness": jnp.asarray(logit((START_ROUGHNESS - R_MIN) / (1.0 - R_MIN)), jnp.float32),
    }
    state = opt.init(theta)
    t0 = time.perf_counter()
    theta, state, loss, g, initial = step(theta, state, env)
    loss.block_until_ready()
    compile_s = time.perf_counter() - t0
    losses = [(0, float(loss))]
    print(f"step {0:4d}  loss {float(loss):.4e}  roughness {START_ROUGHNESS:.4f}   "
          f"(compilation and the first step: {compile_s:.1f} s)")
    t0 = time.perf_counter()
    for k in range(1, args.steps):
        theta, state, loss, g, _ = step(theta, state, env)
        if k % args.print_every == 0:
            losses.append((k, float(loss)))
            if not all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(g)):
                raise SystemExit(f"non-finite gradient at step {k}")
            # the loss of the parameters after k updates; the roughness after k + 1
            print(f"step {k:4d}  loss {losses[-1][1]:.4e}  roughness {float(unpack(theta)[1]):.4f}")
    jax.block_until_ready(theta)
    per_step = (time.perf_counter() - t0) / max(1, args.steps - 1)
    # The loss and images of the final parameters (one more step, its update discarded: no new program).
    _, _, loss, _, fitted = step(theta, state, env)
    losses.append((args.steps, float(loss)))
    print(f"step {args.steps:4d}  loss {losses[-1][1]:.4e}  roughness {float(unpack(theta)[1]):.4f}")
    compiled = step._cache_size() if hasattr(step, "_cache_size") else None  # 1: no recompilation
    texels, rough = (np.asarray(x) for x in unpack(theta))
    initial, fitted, targets = np.asarray(initial), np.asarray(fitted), np.asarray(targets)

    def rmse(a, mask=None):
        d = (a - truth) ** 2
        return float(np.sqrt(d[mask].mean() if mask is not None else d.mean()))

    grey = np.full_like(truth, 0.5)
    res = {
        "losses": losses, "loss_initial": losses[0][1], "loss_final": losses[-1][1], "roughness_initial": START_ROUGHNESS,
        "roughness": float(rough), "compiled_programs": compiled,
        "rmse_all": rmse(texels), "rmse_seen": rmse(texels, seen), "rmse_sharp": rmse(texels, sharp),
        "rmse_all_initial": rmse(grey), "rmse_seen_initial": rmse(grey, seen), "rmse_sharp_initial": rmse(grey, sharp),
        "seen_fraction": float(seen.mean()), "sharp_fraction": float(sharp.mean()), "compile_s": compile_s, "step_s": per_step,
    }

    rows = [[display(targets[v]), display(initial[v]), display(fitted[v])] for v in range(args.views)]
    rows.append([upscale(truth, args.size), upscale(grey, args.size), upscale(texels, args.size)])
    save_grid(out / "fit.png", rows)
    jp.image.write(out / "fitted_base_color.png", texels, encoding="srgb")  # as the asset stores it

    print(f"\n{'':<28}{'true':>10}{'initial':>10}{'fitted':>10}")
    print(f"{'roughness':<28}{TRUE_ROUGHNESS:>10.4f}{START_ROUGHNESS:>10.4f}{res['roughness']:>10.4f}")
    print(f"{'loss (' + args.loss + ' MSE)':<28}{0.0:>10.2e}{res['loss_initial']:>10.2e}{res['loss_final']:>10.2e}")
    print(f"{'texture RMSE, all texels':<28}{0.0:>10.4f}{res['rmse_all_initial']:>10.4f}{res['rmse_all']:>10.4f}")
    print(f"{'texture RMSE, seen texels':<28}{0.0:>10.4f}{res['rmse_seen_initial']:>10.4f}{res['rmse_seen']:>10.4f}")
    print(f"{'texture RMSE, sharp texels':<28}{0.0:>10.4f}{res['rmse_sharp_initial']:>10.4f}{res['rmse_sharp']:>10.4f}")
    print(f"seen texels: {100 * res['seen_fraction']:.1f} % (hold the centre of a hit pixel in some view); "
          f"sharp: {100 * res['sharp_fraction']:.1f} % (read from mip level 0 by such a pixel)")
    print(f"compilation + first step {compile_s:.1f} s; then {1e3 * per_step:.0f} ms per step "
          f"({args.steps - 1} steps back to back; compiled step programs: {compiled})")
    print(f"wrote {out / 'fit.png'} (rows: views, then the texture; columns: target | initial | fitted), "
          f"{out / 'fitted_base_color.png'}, {asset}")
    return res


if __name__ == "__main__":
    main()
