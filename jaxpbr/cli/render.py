"""`jaxpbr render`: render the demo, a TOML scene file or a glTF 2.0 asset to PNG (and EXR)."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .. import _program_cache, color
from ..conventions import CONVENTIONS, luminance
from ..errors import InputError
from ..io import image
from ..io.atomic import OutputSet
from ..rendering.demo import demo_scene
from ..rendering.renderer import EXECUTION, RenderOptions, check_memory, plan, render
from ..rendering.scene import MAX_SUPERSAMPLE
from ..rendering.scene_file import load_scene
from ..shading.brdf_terms import MODELS
from ._common import (
    FLOAT32_MAX,
    CLIError,
    Progress,
    float32_arg,
    nonnegative_int_arg,
    positive_int_arg,
    raise_pending,
)

__all__ = ["add_command", "cmd_render"]

_TONEMAPS = ("reinhard", "aces", "aces_narkowicz", "clamp")
_ENCODINGS = ("srgb", "gamma2.2", "linear")

#: --fov-y's range in degrees. 179 is `Camera`'s own limit. The floor keeps the rays of
#: neighbouring pixels apart in float32: a ray's direction is forward + x right + y up, whose
#: components near 1 float32 carries to about 1.2e-7 (its epsilon), and the rows of an H-row image
#: step y by 2 tan(fov/2) / H. At 0.5 degrees that is 8.7e-3 / H, at least 4 epsilons per row up
#: to 18,000 rows; at 1e-3 degrees it is 1.7e-5 / H, a fifth of an epsilon per row of a 720-row
#: image: runs of rows got the same direction (and `--fov-y 0` rendered at 45 degrees).
FOV_Y_RANGE = (0.5, 179.0)


def add_command(sub) -> None:
    """Register `jaxpbr render` on the top-level sub-parsers."""
    r = sub.add_parser(
        "render",
        help="render the demo scene (or a scene.toml) to a PNG",
        description="Render a scene to linear HDR, tone-map it and write a PNG (and an EXR with --hdr). "
        "Without SCENE: the demo, a 7x7 sphere grid (metallic by row, roughness 0..1 by column) under a "
        "procedural sky with a bright sun, plus four point lights. SCENE is a TOML scene description "
        "(see docs/scene_format.md) or a glTF 2.0 asset (.gltf, .glb; see docs/gltf.md).",
    )
    r.add_argument("scene", nargs="?", default=None, help="scene description (.toml) or glTF asset (.gltf, .glb); default: the demo")
    r.add_argument("-o", "--output", default="jaxpbr_demo.png", help="output PNG path (default: %(default)s)")
    r.add_argument("--width", type=positive_int_arg, default=None, help="image width (default: 1280, or the scene's)")
    r.add_argument("--height", type=positive_int_arg, default=None, help="image height (default: 720, or the scene's)")
    r.add_argument("--supersample", type=positive_int_arg, default=None, help="s x s samples per pixel (default: 1, or the scene's)")
    r.add_argument("--model", choices=MODELS, default=None, help="BRDF model (default: gltf, or the scene's)")
    r.add_argument("--smith", choices=("correlated", "separable"), default=None, help="gltf model: height-correlated (default, the glTF spec) or separable Smith-GGX G2, in the direct lighting and the IBL LUT alike")
    r.add_argument("--no-extract-lights", dest="extract_lights", action="store_false", default=None, help="shade the whole environment with the split sum (no sun extraction; default: suns are split out and shaded as disc lights)")
    r.add_argument("--transmission-depth", type=nonnegative_int_arg, default=None,
                   help="transmissive surfaces a transmitted ray passes and still sees the scene behind (default: 2; 0: the environment only)")
    r.add_argument("--transmission-samples", type=positive_int_arg, default=None,
                   help="transmitted rays per pixel drawn from a rough transmission lobe (default: 4)")
    r.add_argument("--ibl-visibility", choices=("none", "occlusion", "ao", "ratio"), default=None,
                   help="what the environment's light knows of what occludes it (default: occlusion, the glTF occlusion texture; docs/visibility.md)")
    r.add_argument("--ibl-samples", type=positive_int_arg, default=None, help="rays per pixel of --ibl-visibility ao / ratio (default: 4)")
    r.add_argument("--reference", action="store_true",
                   help="render the float64 ground truth of the direct light instead (environment with visibility, lights with shadows; "
                   "jaxpbr.reference_render); with --hdr the EXR gets its per-pixel standard error as a layer")
    r.add_argument("--spp", type=positive_int_arg, default=64, help="--reference: samples per pixel (default: %(default)s)")
    r.add_argument("--bounces", type=nonnegative_int_arg, default=0,
                   help="--reference: interreflection, paths of up to this many further vertices (default: 0, the direct light)")
    r.add_argument("--exposure", type=float32_arg(), default=None, help="exposure in EV stops (default: 0, or the scene's)")
    r.add_argument(
        "--tonemap",
        choices=_TONEMAPS,
        default=None,
        help="tone map (default: aces for gltf, reinhard for learnopengl as in the tutorial)",
    )
    r.add_argument(
        "--encoding",
        choices=_ENCODINGS,
        default=None,
        help="display encoding (default: srgb for gltf, gamma2.2 for learnopengl)",
    )
    r.add_argument("--bits", type=int, choices=(8, 16), default=8, help="PNG bit depth (default: %(default)s)")
    r.add_argument("--hdr", action="store_true", help="also write the linear HDR image as EXR next to the PNG")
    r.add_argument("--aov", default=None, metavar="LIST", help="also write arbitrary output variables as layers of the EXR (implies --hdr): comma-separated from depth, distance, normal, position, base_color, mask, object_id, primitive_id, or 'all' (docs/gltf.md)")
    r.add_argument("--no-environment", action="store_true", help="demo only: leave out the sky (no IBL)")
    g = r.add_argument_group("glTF assets")
    g.add_argument("--environment", default=None, metavar="FILE", help="glTF: environment lighting and background: an equirect .hdr/.exr panorama or procedural:sky (the demo's sky, 128^2 faces) (default: none)")
    g.add_argument("--environment-intensity", type=float32_arg(0.0), default=1.0, help="glTF: multiplier of the environment, >= 0 (default: %(default)s)")
    g.add_argument("--camera-position", type=_vec3_arg, default=None, metavar="X,Y,Z", help="glTF: camera position (default: the asset's first camera, else a framing of its bounds)")
    g.add_argument("--camera-target", type=_vec3_arg, default=None, metavar="X,Y,Z", help="glTF: the point the camera looks at (default: the centre of the asset's bounds)")
    g.add_argument("--fov-y", type=float32_arg(*FOV_Y_RANGE, unit="degrees", why="a narrower view leaves neighbouring pixels' float32 rays nearly equal; 179 is the camera's limit"),
                   default=None, metavar="DEG", help=f"glTF: vertical field of view in degrees, {FOV_Y_RANGE[0]:g} to {FOV_Y_RANGE[1]:g} (default: the asset camera's, else 45)")
    g.add_argument("--asset-root", action="append", default=None, metavar="DIR",
                   help="glTF: a folder besides the asset's own whose files its buffer and image URIs may name; repeat for "
                        "more (default: an asset reads only regular files inside its own folder; docs/gltf.md, 'Untrusted assets')")
    g.add_argument("--time", type=_time_arg, default=None, metavar="SECONDS",
                   help="glTF: pose the asset at this time of an animation (node transforms, skins, morph weights; keys "
                        "clamped at both ends) (default: the rest pose)")
    g.add_argument("--animation", default=None, metavar="NAME|INDEX",
                   help="glTF: the animation --time and --frames play (default: the first)")
    g.add_argument("--motion-dt", type=_time_arg, default=None, metavar="SECONDS",
                   help="glTF: --aov motion's time step: the motion vectors carry each pixel's surface point from t to "
                        "t + SECONDS (default: the --frames STEP, else 1/60 s)")
    g.add_argument("--frames", type=_frames_arg, default=None, metavar="START:END:STEP",
                   help="glTF: render a sequence at times START, START+STEP, ... up to END (seconds), one file per frame: "
                        "-o must hold a frame-number pattern such as frame_%%04d.png")
    r.add_argument("--no-lights", action="store_true", help="demo only: leave out the point lights")
    r.set_defaults(func=cmd_render)


#: The most frames one --frames run renders (each is a whole render).
MAX_FRAMES = 100_000


#: --time and --motion-dt: seconds, finite, in float32's range.
_time_arg = float32_arg(unit="seconds")


def _frames_arg(text: str) -> tuple[float, ...]:
    """START:END:STEP -> the times START + k STEP <= END (END included to a millionth of STEP)."""
    parts = text.split(":")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"{text!r} is not START:END:STEP (seconds), e.g. 0:2:0.04")
    start, end, step = (_time_arg(p) for p in parts)
    if step <= 0 or end < start:
        raise argparse.ArgumentTypeError(f"{text!r}: STEP must be > 0 and END >= START")
    n = int((end - start) / step + 1e-6) + 1
    if n > MAX_FRAMES:
        raise argparse.ArgumentTypeError(f"{text!r} makes {n} frames; at most {MAX_FRAMES} (use a larger STEP)")
    return tuple(start + k * step for k in range(n))


#: What to lower, named as the command line (demo) or the scene file spells it.
_MEMORY_NAMES = {"Camera.width/height": "--width/--height"}
_SCENE_MEMORY_NAMES = {
    "Camera.width/height": "--width/--height (or camera.width/height)",
    "the environment's face size": "environment.face_size",
    "prefilter_samples": "render.prefilter_samples",
    "irradiance_size": "render.irradiance_size",
    "lut_size": "render.lut_size",
    "the textures' resolution": "the textures' resolution (materials.*_texture)",
}


def _check_output_path(outs: OutputSet, path: Path, hdr: bool) -> None:
    """Every output validated before any work (issue 13: a read-only folder or an output that is a
    directory was found only after the whole render): suffix, existing writable folder, not a
    directory; with --hdr the EXR as well. The files they replace are protected (a failure puts
    them back)."""
    if path.suffix.lower() != ".png":
        raise CLIError(f"--output must end in .png, got {path.name!r}")
    paths = [path] + ([path.with_suffix(".exr")] if hdr else [])
    for p in paths:
        try:
            outs.check(p, (p.suffix.lower(),))
        except ValueError as e:
            raise CLIError(f"{e} (--output{' with --hdr' if p.suffix.lower() == '.exr' else ''})") from None
    outs.protect(paths)


def _vec3_arg(text: str) -> tuple[float, float, float]:
    """argparse type: three finite numbers separated by commas, each within float32's range."""
    parts = text.split(",")
    try:
        vals = tuple(float(x) for x in parts)
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z, got {text!r}")
    if any(abs(v) > FLOAT32_MAX for v in vals):
        raise argparse.ArgumentTypeError(f"{text!r} is outside float32's range (|x| <= {FLOAT32_MAX:.4g}), which the renderer computes in")
    return vals


def _gltf_scene(args):
    """The scene of a glTF asset with the command line's environment and camera (the rules of
    `jaxpbr.load_gltf`, `gltf_scene.scene_from_asset`)."""
    import warnings

    from ..io.gltf import read_gltf
    from ..rendering.gltf_scene import scene_from_asset
    from ..rendering.plan import mesh_engine

    from ..io.gltf import posed_asset

    loaded = getattr(args, "_loaded", None)
    if loaded is None:  # (read once: the frames of --frames re-pose it)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rest = read_gltf(args.scene, roots=args.asset_root or (), ray_engine=mesh_engine())
        for w in caught:
            print(f"jaxpbr: warning: {w.message}")
        from ..rendering.gltf_scene import environment_from

        loaded = args._loaded = {"rest": rest, "camera": None, "materials": {},
                                 "environment": environment_from(args.environment, intensity=args.environment_intensity)}
    rest = loaded["rest"]
    posing = args.time is not None or args.animation is not None
    animation = args.animation
    if isinstance(animation, str) and animation.isdigit():
        animation = int(animation)
    try:
        asset = posed_asset(rest, 0.0 if args.time is None else args.time, animation) if posing else rest
    except InputError as e:
        raise CLIError(str(e).replace("time=", "--time ").replace("animation=", "--animation ")) from None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gs = scene_from_asset(
            asset, camera=loaded["camera"], width=args.width or 1280, height=args.height or 720, camera_position=args.camera_position,
            camera_target=args.camera_target, fov_y_deg=args.fov_y, supersample=args.supersample or 1,
            environment=loaded["environment"], material_cache=loaded["materials"],
        )
    if (getattr(args, "frames", None) is not None or "motion" in (getattr(args, "aov", None) or ())) and not asset.cameras:
        loaded["camera"] = gs.scene.camera  # (a framing of the first frame's bounds, kept for the sequence)
    if getattr(args, "_frame", 0) == 0:
        for w in caught:
            print(f"jaxpbr: warning: {w.message}")
        for note in gs.notes:
            print(f"jaxpbr: note: {note}")
    s = asset.summary()
    when = "" if not posing else f", animation {asset.animation} ({rest.animations[asset.animation].name or 'unnamed'}) at {asset.time:g} s"
    return gs.scene, f"glTF {Path(args.scene).name}: {s['triangles']} triangles, {s['materials']} materials{when}"


def _aov_names(text: str | None) -> tuple[str, ...]:
    from ..rendering.aovs import AOVS

    if text is None:
        return ()
    names = tuple(a for a in AOVS if a != "motion") if text.strip() == "all" else \
        tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in AOVS]
    if bad or not names:
        raise CLIError(f"--aov: unknown AOV(s) {bad or [text]}; choose from {', '.join(AOVS)} or 'all'")
    return names


def cmd_render(args) -> int:
    args.aov = _aov_names(args.aov)
    if args.aov:
        args.hdr = True
    gltf = args.scene is not None and Path(args.scene).suffix.lower() in (".gltf", ".glb")
    used = [f for f, v in (("--time", args.time), ("--animation", args.animation), ("--frames", args.frames),
                           ("--motion-dt", args.motion_dt)) if v is not None]
    if "motion" in args.aov and args.time is None and args.frames is None:
        raise CLIError("--aov motion needs the asset's motion: give --time (with --motion-dt) or --frames")
    if used and not gltf:
        raise CLIError(f"{', '.join(used)} apply to glTF assets (.gltf, .glb)")
    if args.frames is None:
        out = Path(args.output)
        with OutputSet() as outs:
            _check_output_path(outs, out, args.hdr)
            return _render_to(args, out, outs)
    if args.time is not None:
        raise CLIError("--time and --frames exclude each other (--frames START:END:STEP sets the times)")
    try:
        outs_named = [Path(args.output % k) for k in range(len(args.frames))]
    except (TypeError, ValueError):
        raise CLIError(f"--frames writes one file per frame: --output needs one frame-number pattern such as frame_%04d.png, "
                       f"got {args.output!r}") from None
    if len(set(outs_named)) != len(outs_named):
        raise CLIError(f"--output {args.output!r} names the same file for several frames; use a pattern such as frame_%04d.png")
    with OutputSet() as outs:
        for out in outs_named:
            _check_output_path(outs, out, args.hdr)
        for k, (t, out) in enumerate(zip(args.frames, outs_named)):
            args.time, args._frame = t, k
            _render_to(args, out, outs)
    return 0


def _render_to(args, out: Path, outs: OutputSet) -> int:
    display_opts: dict = {}
    if args.supersample is not None and args.supersample > MAX_SUPERSAMPLE:
        raise CLIError(f"--supersample {args.supersample} asks for {args.supersample}^2 passes of the whole image; "
                       f"at most {MAX_SUPERSAMPLE} is allowed and 4 to 16 is plenty for anti-aliasing")
    if args.scene is None:
        scene = demo_scene(
            args.width or 1280,
            args.height or 720,
            supersample=args.supersample or 1,
            lights=not args.no_lights,
            environment=not args.no_environment,
        )
        options: dict = {}
        description = "demo: 7x7 sphere grid (metallic by row, roughness 0..1 by column), procedural sky + sun"
        description += ", 4 point lights" if not args.no_lights else ""
    elif Path(args.scene).suffix.lower() in (".gltf", ".glb"):
        if args.no_lights or args.no_environment:
            raise CLIError("--no-lights/--no-environment apply to the demo only; a glTF asset has no environment unless --environment is given")
        scene, description = _gltf_scene(args)
        options = {}
    else:
        if args.no_lights or args.no_environment:
            raise CLIError("--no-lights/--no-environment apply to the demo only; edit the scene file instead")
        gltf_flags = [f for f, v in (("--environment", args.environment), ("--camera-position", args.camera_position), ("--camera-target", args.camera_target), ("--fov-y", args.fov_y), ("--asset-root", args.asset_root)) if v is not None]
        if gltf_flags:
            raise CLIError(f"{', '.join(gltf_flags)} apply to glTF assets (.gltf, .glb); a scene file sets its own environment and camera")
        loaded = load_scene(args.scene)
        scene, options, display_opts = loaded.scene, dict(loaded.options), dict(loaded.output)
        if scene.camera is not None and (args.width or args.height or args.supersample):
            cam = scene.camera
            scene = scene.replace(
                camera=cam.replace(
                    width=args.width or cam.width,
                    height=args.height or cam.height,
                    supersample=args.supersample or cam.supersample,
                )
            )
        description = f"scene file {Path(args.scene).name}"
    if args.model is not None:
        options["model"] = args.model
    if args.smith is not None:
        if args.smith != "correlated" and options.get("model", "gltf") != "gltf":
            raise CLIError(f"--smith {args.smith} is a gltf-model option; the {options['model']} model has its own G (use --model gltf)")
        options["smith"] = args.smith
    if args.extract_lights is not None:
        options["extract_lights"] = args.extract_lights
    from ..rendering.options import MAX_IBL_SAMPLES, MAX_TRANSMISSION_DEPTH, MAX_TRANSMISSION_SAMPLES

    if args.ibl_visibility is not None:
        options["ibl_visibility"] = args.ibl_visibility
    if args.ibl_samples is not None:
        if args.ibl_samples > MAX_IBL_SAMPLES:
            raise CLIError(f"--ibl-samples must be at most {MAX_IBL_SAMPLES}, got {args.ibl_samples}")
        options["ibl_samples"] = args.ibl_samples
    for name, cap in (("transmission_depth", MAX_TRANSMISSION_DEPTH), ("transmission_samples", MAX_TRANSMISSION_SAMPLES)):
        value = getattr(args, name)
        if value is not None:
            if value > cap:
                raise CLIError(f"--{name.replace('_', '-')} must be at most {cap} (each is one more pass over the image), got {value}")
            options[name] = value
    opts = RenderOptions(**options)
    if opts.dtype == "float64":
        # A float64 render needs JAX's 64-bit mode (off by default): without it every float64
        # request is silently truncated to float32 (issue 13: a scene asking for float64 rendered in
        # float32 with a screen of warnings).
        jax.config.update("jax_enable_x64", True)
    H, W = scene.image_shape
    # The library's guard (image, textures, the IBL precomputes) with the flags and keys named.
    check_memory(scene, options=opts, where="", names=_MEMORY_NAMES if args.scene is None else _SCENE_MEMORY_NAMES)
    model = opts.model
    tonemap = args.tonemap or display_opts.get("tonemap") or ("reinhard" if model == "learnopengl" else "aces")
    encoding = args.encoding or display_opts.get("encoding") or ("gamma2.2" if model == "learnopengl" else "srgb")
    ev = args.exposure if args.exposure is not None else float(display_opts.get("exposure", 0.0))

    t0 = time.perf_counter()
    the_plan = plan(scene, options=opts)
    # A bar only when there is more than one pass (bands of a large image, sub-pixel samples).
    band = EXECUTION.band_pixels
    passes = scene.camera.supersample ** 2 * (1 if W * H <= band else -(-H // max(1, band // W)))
    progress = Progress("render") if passes > 1 else None
    # The display program is compiled ahead with a cold render's stages (`_program_cache.also_ahead`).
    frame = jax.ShapeDtypeStruct((H, W, 3), np.dtype(opts.dtype))
    with _program_cache.also_ahead(lambda: color.display(frame, ev, tonemap=tonemap, encoding=encoding)):
        if args.reference:
            from ..reference import reference_render

            if args.aov:
                raise CLIError("--reference writes the ground truth and its standard error; leave out --aov")
            if args.spp < 2:
                raise CLIError("--spp must be at least 2 with --reference (the standard error needs two samples)")
            if args.bounces > 16:
                raise CLIError(f"--bounces must be at most 16, got {args.bounces}")
            truth = reference_render(scene, spp=args.spp, bounces=args.bounces, options=opts, progress=Progress("reference"))
            hdr_device = jnp.asarray(truth.image.astype(np.float32))
        elif args.aov:  # one geometry pass for the image and its AOVs where it can be shared
            from ..rendering.aovs import render_with_aovs

            next_scene = None
            if "motion" in args.aov:
                dt = args.motion_dt if args.motion_dt is not None else (
                    args.frames[1] - args.frames[0] if args.frames is not None and len(args.frames) > 1 else 1 / 60)
                now, frame = args.time, getattr(args, "_frame", 0)
                args.time, args._frame = now + dt, -1  # (quiet: its notes were printed with this frame's)
                try:
                    next_scene = _gltf_scene(args)[0]
                finally:
                    args.time, args._frame = now, frame
                description += f"; motion vectors to t + {dt:g} s"
            hdr_device, aov_values = render_with_aovs(scene, args.aov, options=opts, progress=progress, next_scene=next_scene)
        else:
            hdr_device = render(scene, options=opts, progress=progress)
    display = np.asarray(color.display(hdr_device, ev, tonemap=tonemap, encoding=encoding))
    hdr = np.asarray(hdr_device)  # one device -> host copy of each image
    t_render = time.perf_counter() - t0
    if not np.all(np.isfinite(hdr)):
        raise CLIError("the render produced non-finite values; this is a bug, please report it")
    H, W = hdr.shape[:2]
    metadata = {
        "software": "jaxpbr",
        "jaxpbr:scene": description,
        "jaxpbr:plan": the_plan.describe(),
        "jaxpbr:model": model,
        "jaxpbr:render_options": repr(opts),
        "jaxpbr:exposure_ev": float(ev),
        "jaxpbr:tonemap": tonemap,
        "jaxpbr:encoding": encoding,
        "jaxpbr:conventions": CONVENTIONS,
    }
    raise_pending()
    outs.add(out)
    image.write(out, display, bits=args.bits, encoding=encoding, encoded=True, metadata=metadata)
    print(f"wrote {out} ({W}x{H}, model {model}, {tonemap} + {encoding}; render {t_render:.2f} s incl. precompute and compile)")
    if args.reference:
        surf = truth.hit
        rel = float(np.mean(luminance(truth.stderr[surf])) / max(np.mean(luminance(truth.image[surf])), 1e-30)) if surf.any() else 0.0
        what = "direct light" if args.bounces == 0 else f"direct light and {args.bounces} bounce(s)"
        print(f"  ground truth (float64, {what} with visibility): {truth.spp} spp in {truth.seconds:.2f} s; "
              f"mean standard error {rel:.2%} of the surfaces' mean luminance; "
              f"{np.mean(truth.visible[surf] < 0.9):.0%} of the surface pixels see under 90 % of the sky")
    else:
        print(f"  {the_plan.describe()}")
    if args.hdr:
        exr = out.with_suffix(".exr")
        hdr_meta = {k: v for k, v in metadata.items() if k not in ("jaxpbr:tonemap", "jaxpbr:encoding", "jaxpbr:exposure_ev")}
        hdr_meta["jaxpbr:content"] = "linear scene-referred radiance, Rec.709 primaries"
        layers = {}
        if args.reference:
            layers = {f"stderr.{c}": truth.stderr[..., i].astype(np.float32) for i, c in enumerate("RGB")}
            hdr_meta["jaxpbr:content"] = "ground truth of the direct light, float64 Monte Carlo (layer stderr: its standard error)"
        if args.aov:
            from ..rendering.aovs import exr_layers

            layers, aov_meta = exr_layers(aov_values, args.aov)
            hdr_meta |= aov_meta
        outs.add(exr)
        image.write(exr, hdr, metadata=hdr_meta, layers=layers)  # a failure here removes the PNG too
        print(f"wrote {exr} (linear HDR, float32{'; AOVs ' + ', '.join(args.aov) if args.aov else ''})")
    return 0
