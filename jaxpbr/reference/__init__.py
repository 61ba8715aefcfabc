"""Float64 references of whole renders: the ground truth a render is measured against.

`reference_render(scene, spp=...)`: Monte Carlo integration, in float64, of the direct light each
camera pixel's surface receives from the environment *with visibility* (rays through the scene's
ray engine), from the punctual lights with their shadows, plus its emission, with a per-pixel
standard error (`jaxpbr.reference.ground_truth`)."""

from .ground_truth import ReferenceImage, reference_render

__all__ = ["ReferenceImage", "reference_render"]
