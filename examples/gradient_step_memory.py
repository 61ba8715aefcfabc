"""Where the memory of a gradient step goes: the demo grid as a glTF asset of triangle meshes
under a panorama the package has never seen, at 512 x 512, forward and differentiated.

One process, phase by phase, each with the process's resident memory (VmRSS) and its peak so
far (VmHWM) read from /proc:

1. jaxpbr imported and JAX's CPU client started;
2. the asset loaded (`jaxpbr.load_gltf`) and its environment baked (`jaxpbr.bake`);
3. a forward render (`jaxpbr.render`, staged on the CPU): the target image;
4. the gradient step compiled: `jax.jit(jax.value_and_grad(loss))` of the mean squared error
   against the target, with respect to one factor scaling every material's base colour (the
   rays' hits come from the host's ray engine through a callback; the shading is differentiated);
   XLA's own account of the step's temporaries (`Compiled.memory_analysis`);
5. the step run `--steps` times.

    python examples/gradient_step_memory.py [--size 512] [--triangles 100000] [--steps 3] [--hdr FILE]

Read the increments: what a gradient step adds over a forward process is the compiled step
(its code and the compiler's retained memory) and its temporaries (the residuals of the
backward pass, about 580 bytes a pixel at 512^2).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from pathlib import Path


def memory() -> tuple[float, float]:
    """(VmRSS, VmHWM) of this process in GB (NaN where /proc is not)."""
    got = {}
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(("VmRSS:", "VmHWM:")):
                    got[line[:5]] = float(line.split()[1]) * 1024 / 1e9
    except OSError:
        pass
    return got.get("VmRSS", float("nan")), got.get("VmHWM", float("nan"))


def _panorama_writer():
    """`write_panorama` of examples/first_image_vs_mitsuba.py (fresh random detail per call)."""
    path = Path(__file__).resolve().parent / "first_image_vs_mitsuba.py"
    spec = importlib.util.spec_from_file_location("first_image_vs_mitsuba", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.write_panorama


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512, help="image width and height in pixels")
    ap.add_argument("--triangles", type=int, default=100_000, help="about this many triangles in the asset")
    ap.add_argument("--steps", type=int, default=3, help="gradient steps run after compiling")
    ap.add_argument("--hdr", type=Path, default=None, help="an equirect HDR (default: a procedural panorama)")
    args = ap.parse_args(argv)
    rows = []

    def phase(name, **extra):
        rss, hwm = memory()
        rows.append({"phase": name, "rss_gb": rss, "peak_gb": hwm, **extra})
        print(f"{name:<34s} RSS {rss:5.2f} GB   peak {hwm:5.2f} GB" + "".join(f"   {k} {v}" for k, v in extra.items()), flush=True)

    import jax
    import jax.numpy as jnp

    import jaxpbr as jp
    from jaxpbr._pytree import evolve
    from jaxpbr.rendering.demo import write_demo_glb

    jax.numpy.zeros(1).block_until_ready()
    phase("imported, JAX started")
    with tempfile.TemporaryDirectory(prefix="jaxpbr-grad-memory-") as tmp:
        d = Path(tmp)
        asset = write_demo_glb(d / "grid.glb", triangles=args.triangles)
        hdr = args.hdr or _panorama_writer()(d / "panorama.hdr")
        scene = jp.load_gltf(asset.path, width=args.size, height=args.size, environment=hdr)
        scene = scene.replace(environment=jp.bake(scene.environment))
        phase("asset loaded, environment baked", triangles=asset.triangles)
        target = jax.block_until_ready(jp.render(scene))
        phase("forward render")

        def loss(scale):
            objects = tuple(evolve(o, material=evolve(o.material, base_color=jnp.asarray(o.material.base_color) * scale))
                            for o in scene.objects)
            return jnp.mean((jp.render(scene.replace(objects=objects)) - target) ** 2)

        t = time.perf_counter()
        step = jax.jit(jax.value_and_grad(loss)).lower(jnp.float32(0.9)).compile()
        ma = step.memory_analysis()
        phase("gradient step compiled", compile_s=round(time.perf_counter() - t, 2),
              xla_temp_gb=round(ma.temp_size_in_bytes / 1e9, 3))
        for _ in range(args.steps):
            value, grad = jax.block_until_ready(step(jnp.float32(0.9)))
        phase(f"{args.steps} gradient step(s) run", loss=f"{float(value):.3g}", grad=f"{float(grad):.3g}")
    return {"rows": rows, "loss": float(value), "grad": float(grad), "xla_temp_bytes": int(ma.temp_size_in_bytes)}


if __name__ == "__main__":
    main(sys.argv[1:])
