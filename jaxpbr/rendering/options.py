"""`RenderOptions`: the static options of a render (hashable; part of each compiled program's
identity), and how a call's `options=` value and keyword overrides combine into one."""

from __future__ import annotations

import dataclasses

import numpy as np

from .._validate import positive_int
from ..shading.brdf_terms import MODEL_REGISTRY, check_options


#: Upper bounds of `RenderOptions.transmission_depth` and `transmission_samples`.
MAX_TRANSMISSION_DEPTH = 8
MAX_TRANSMISSION_SAMPLES = 64
#: The rungs of image-based light's visibility (`RenderOptions.ibl_visibility`), cheapest first.
IBL_VISIBILITY = ("none", "occlusion", "ao", "ratio")
MAX_IBL_SAMPLES = 256


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    """Static render options (hashable; part of the compiled program's identity).

    model: a `brdf_terms.MODEL_REGISTRY` name, "gltf" | "learnopengl" (direct BRDF and IBL
        combination; each model's IBL reads the LUT of its `lut_smith`, "schlick_ggx" for learnopengl).
    multiscatter: Fdez-Aguera energy compensation of the IBL term (None, the default: on for the
        gltf model, as the Khronos glTF Sample Viewer, three.js and Filament render glTF assets;
        rough metals are otherwise up to ~2.8x darker than in those viewers. False gives the
        single-scattering glTF BRDF that the float64 references (and Mitsuba) integrate. gltf only:
        True with another model raises ValueError). The suns split out of the environment get the
        same compensation (`ibl.multiscatter_weight` times their irradiance); punctual lights none (as the
        Sample Viewer and three.js; Filament compensates direct lights too).
    smith: gltf only: "correlated" (the glTF spec, default) or "separable" Smith-GGX G2, for the
        direct lighting (`brdf(smith=)`) and the IBL term alike (the split-sum LUT of that G,
        computed on first use: only the correlated and Schlick-GGX tables are shipped).
    irradiance_size / irradiance_method: `jaxpbr.irradiance` parameters (exact convolution default).
    prefilter_size: face size of the prefiltered map (default: min(env face size, 128), a
        power-of-two divisor of it); prefilter_samples: `jaxpbr.prefilter` samples (None = default).
    lut_size: split-sum LUT resolution (shipped 128 / 256 load instantly).
    mapping: roughness -> mip mapping of the prefiltered map ("linear" | "quadratic").
    dtype: float32 | float64 for the shading: a name, a NumPy or a JAX dtype (stored as its name).
    extract_lights: split dominant lights (suns) out of a concrete environment whose maps are
        computed here (`jaxpbr.ibl.extract.extract_lights`, defaults), shade them as analytic disc
        lights and the residual with the split sum (default True; the split sum alone is off by
        30-60 % on metals under a sun, issue 11). Once per environment content (cached). An
        environment with given maps uses its own `lights` (None: nothing is split).
    shadows: shadow rays from every lit pixel towards each light and each sun split out of the
        environment (`jaxpbr.rendering.shadows`; hard-edged). None (default): on for scenes with
        meshes (glTF assets), off for scenes of spheres and planes only; True / False force it.
        Image-based lighting itself is not shadowed (the materials' occlusion textures darken it).
    transmission_depth: how many transmissive surfaces (KHR_materials_transmission) one after another
        a transmitted ray passes and still sees the scene behind (default 2: both walls of a closed
        thin-walled object, an analytic sphere or a double-sided mesh; a single-sided mesh's back
        faces let rays through, so it takes one). At each level rays continue through the surface
        (straight through thin walls; out of a volume sphere along its refracted chord's exit
        direction; along the view through a volume slab) and the first surface they meet is shaded
        by the same stages; rays that escape, and the transmission of surfaces past the last level,
        see the prefiltered environment. A level none of whose rays meets a transmissive surface
        traces nothing more. 0: the environment only (the split sum's lobe; nothing traced). Needs
        an environment (the lobe's weights are the split sum's).
    transmission_samples: rays per pixel at the first level (default 4; deeper levels continue each
        ray with one), drawn from the transmission lobe (stratified, per-pixel rotated,
        deterministic). The prefiltered environment stays the lobe's unoccluded value and the rays
        add what the scene changes (a control variate): where nothing stands behind there is no
        noise, and smooth transmission is exact with one ray (the plan takes one where every
        transmissive material has roughness 0). Rough transmission before a high-contrast backdrop
        is noisy at few rays: docs/extensions.md measures error against rays and time.
    ibl_visibility: what the image-based light knows of what occludes it (docs/visibility.md):
        "none": nothing (the unshadowed split sum; the materials' occlusion textures left out);
        "occlusion" (default): the glTF occlusion texture only, where a material has one;
        "ao": ibl_samples rays per pixel from the surface (cosine and GGX-lobe directions, in turn),
        the diffuse term scaled by the cosine rays' visible fraction and the specular term by the
        lobe rays'; "ratio": the ratio estimator of Heitz, Hill and McGuire (2018): the split sum
        times sum_k w_k V_k / sum_k w_k over the same rays, w_k = f L cos / p (the BRDF, the
        environment along the ray, the rays' mixture density), which converges to the shadowed
        integral as the rays grow. The ray-traced rungs leave the occlusion texture out (the rays
        see what it guesses) and shadow the residual environment (the suns split out of it have
        shadow rays of their own).
    ibl_samples: rays per pixel of the "ao" and "ratio" rungs (deterministic per pixel).
    antialias: blend each sample pass's outlines -- silhouettes, occlusion edges between objects,
        a plane's horizon -- by where they cross between neighbouring samples (analytic
        antialiasing, `jaxpbr.rendering.edges`; default True). This is also what differentiates
        the image with respect to where the outlines are (vertex positions, object parameters, the
        camera). False keeps each pass's point samples as they are (to compare with point-sampled
        references); the gradient then still carries the outlines' motion (the blend's derivative,
        without its value). "none": neither the blend nor its derivative -- the point samples and the
        interior-only gradient, the control against which what the outlines add is measured.
    """

    model: str = "gltf"
    multiscatter: bool | None = None
    smith: str = "correlated"
    irradiance_size: int = 32
    irradiance_method: str = "exact"
    prefilter_size: int | None = None
    prefilter_samples: int | None = None
    lut_size: int = 128
    mapping: str = "linear"
    dtype: str = "float32"
    extract_lights: bool = True
    shadows: bool | None = None
    transmission_depth: int = 2
    transmission_samples: int = 4
    ibl_visibility: str = "occlusion"
    ibl_samples: int = 4
    antialias: bool | str = True

    @property
    def compensates(self) -> bool:
        """Whether the IBL term is compensated for multiple scattering: `multiscatter`, or when it
        is None the model's default (on for gltf, the models with the option)."""
        if self.multiscatter is not None:
            return bool(self.multiscatter)
        spec = MODEL_REGISTRY.get(self.model)
        return spec is not None and "multiscatter" in spec.ibl_options

    def __post_init__(self):
        # multiscatter=None stays None (the model's default, resolved by `compensates`), so that
        # replacing only the model keeps meaning "the model's default".
        check_options(self.model, multiscatter=bool(self.compensates), smith=self.smith)
        try:
            name = np.dtype(self.dtype).name  # "float32", np.float64, jnp.float32, np.dtype(...)
        except TypeError:
            name = None
        if name not in ("float32", "float64"):
            raise ValueError(f"dtype must be float32 or float64 (a name, NumPy or JAX dtype), got {self.dtype!r}")
        object.__setattr__(self, "dtype", name)  # normalised: equal options hash alike
        for name in ("irradiance_size", "lut_size", "transmission_samples"):
            positive_int(name, getattr(self, name))
        positive_int("transmission_depth", self.transmission_depth, minimum=0)
        positive_int("ibl_samples", self.ibl_samples)
        if self.antialias not in (True, False, "none") or not isinstance(self.antialias, (bool, str)):
            raise ValueError(f"antialias must be True, False or 'none', got {self.antialias!r}")
        if self.ibl_visibility not in IBL_VISIBILITY:
            raise ValueError(f"ibl_visibility must be one of {', '.join(map(repr, IBL_VISIBILITY))}, got {self.ibl_visibility!r}")
        if self.ibl_samples > MAX_IBL_SAMPLES:
            raise ValueError(f"ibl_samples must be at most {MAX_IBL_SAMPLES}, got {self.ibl_samples}")
        for name, cap in (("transmission_depth", MAX_TRANSMISSION_DEPTH), ("transmission_samples", MAX_TRANSMISSION_SAMPLES)):
            if getattr(self, name) > cap:
                raise ValueError(f"{name} must be at most {cap} (each level and each sample is one more pass over the image), "
                                 f"got {getattr(self, name)}")


_OPTION_FIELDS = tuple(f.name for f in dataclasses.fields(RenderOptions))


def _options(options, overrides: dict, fn: str) -> RenderOptions:
    """`options` (a RenderOptions, or None for the defaults) with the keyword `overrides` applied
    on top (`dataclasses.replace`, so the result is validated again)."""
    if options is not None and not isinstance(options, RenderOptions):
        raise TypeError(
            f"{fn}: options must be a jaxpbr.RenderOptions, got {type(options).__name__}; pass "
            f"options=RenderOptions(...), or the fields as keywords, e.g. {fn}(scene, model='gltf')"
        )
    unknown = sorted(set(overrides) - set(_OPTION_FIELDS))
    if unknown:
        raise TypeError(f"{fn}: unknown render option(s) {unknown}; the RenderOptions fields are {list(_OPTION_FIELDS)}")
    if options is None:
        return RenderOptions(**overrides)
    return dataclasses.replace(options, **overrides) if overrides else options


def _lut_smith(opts: RenderOptions) -> str:
    """The LUT's Smith term: the model's (`MODEL_REGISTRY`), or the separable Smith-GGX when the
    direct lighting uses it, so that both terms of a render shade with one G."""
    return "separable" if opts.smith == "separable" else MODEL_REGISTRY[opts.model].lut_smith


