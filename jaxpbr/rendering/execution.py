"""How `render` and `render_batch` run outside transformations: `Execution`, and the process's
settings `EXECUTION` (read by `execute`, `batching` and the memory guard in `plan`)."""

from __future__ import annotations

import dataclasses

import jax

__all__ = ["EXECUTION", "Execution"]


@dataclasses.dataclass
class Execution:
    """How `render` and `render_batch` run outside transformations.

    staged: True = the stages (geometry, each textured object, direct lighting, the environment's suns, IBL + background)
      as separate programs, False = one program, None = the backend decides (`is_staged`).
    band_pixels: `render` (staged) renders images larger than this in bands of about this many
      pixels, so its memory is the image plus one band's G-buffer (~150 bytes per pixel on the
      CPU) at any size.
    """

    staged: bool | None = None
    band_pixels: int = 1 << 21
    device_visibility: bool | None = None

    def traces_on_device(self) -> bool:
        """`device_visibility`, or when it is None whether the backend is not the CPU: a render run
        as one program then traces the rays of opaque meshes in the program, through a BVH built on
        the host (`mesh.device_accel`), instead of calling the host's ray engine (Embree) through a
        callback, whose round trip of the rays dominated a GPU frame (measured on an H100 at 1 M
        triangles, 1080p: 0.44 s a frame against 0.009 s for analytic spheres). On the CPU Embree
        answers faster than the JAX traversal (4.4 against 0.6-0.8 M rays/s on 2 cores)."""
        if self.device_visibility is not None:
            return bool(self.device_visibility)
        return jax.default_backend() != "cpu"

    def is_staged(self) -> bool:
        """`staged`, or when it is None whether the backend is XLA:CPU. XLA:CPU fuses producers into
        every consumer and recomputes them there (see `stages._render_pass`), so on the CPU the
        stages run as separate programs. GPUs do not pay that: one program per render there, no
        intermediate G-buffer round trips through memory and one dispatch instead of four (measured
        2.24 ms staged against 0.33 ms fused for a 1080p G-buffer on an H100)."""
        if self.staged is not None:
            return bool(self.staged)
        return jax.default_backend() == "cpu"


#: The process's execution settings (also `jaxpbr.rendering.renderer.EXECUTION`).
EXECUTION = Execution()
