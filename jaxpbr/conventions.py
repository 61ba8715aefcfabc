"""The conventions jaxpbr follows, as data: written into every output file's metadata."""

from __future__ import annotations

import importlib.metadata
import platform

#: Rec.709 / sRGB luminance weights of linear RGB (ITU-R BT.709, Y = 0.2126 R + 0.7152 G + 0.0722 B).
REC709_LUMA = (0.2126, 0.7152, 0.0722)


def luminance(rgb):
    """Luminance (...) of linear Rec.709 RGB (..., 3) (NumPy or JAX); the channel mean for other
    channel counts (a grey or non-RGB map has no primaries to weight)."""
    if rgb.shape[-1] == 3:
        # A weighted sum, not `rgb @ w`: a matmul would run at the backend's default precision
        # (TF32 on NVIDIA GPUs), and three multiply-adds fuse with their neighbours anyway.
        r, g, b = REC709_LUMA
        return rgb[..., 0] * r + rgb[..., 1] * g + rgb[..., 2] * b
    return rgb.mean(-1)


CONVENTIONS: dict[str, str] = {
    "axes": "right-handed, +Y up, camera looks down -Z (glTF/OpenGL)",
    "directions": "n, v, l unit vectors pointing away from the surface; h = normalize(v + l)",
    "roughness": "perceptual r in [0, 1]; GGX alpha = r^2",
    "color": "linear scene-referred RGB, Rec.709/sRGB primaries; encoding only at output",
    "light_units": "KHR_lights_punctual: point/spot intensity in cd, directional in lux",
    "brdf_models": "gltf = glTF 2.0 App. B (height-correlated Smith); "
    "learnopengl = UE4/Karis Schlick-GGX k=(r+1)^2/8",
    "min_roughness_punctual": "0.045 (perceptual; Filament desktop floor)",
    "cube_faces": "+X,-X,+Y,-Y,+Z,-Z with the OpenGL/KTX orientation (GL major-axis table); "
    "levels[m][f,i,j] at s=(j+0.5)/S_m, t=(i+0.5)/S_m",
    "equirect": "u = 0.5 + atan2(d.z, d.x)/(2 pi), v_up = 0.5 + asin(d.y)/pi, row 0 = +Y",
    "irradiance": "stores Ebar = E/pi (cosine-weighted mean radiance); Lambert radiance = c_diff * Ebar",
    "prefiltered": "level m stores LD(R, r_m) (n = v = R, Karis); r_m = m/(M-1) by default, chain down to 16^2 "
    "faces; lookup per the map's lod_blend: mean_cosine (default; between levels linear in the lobe's mean "
    "cosine c(r)) or roughness (lod = r (M-1)); trilinear; level 0 = source",
    "brdf_lut": "(n_r, n_nov, 2) = (A, B), [j, i] at r = (j+0.5)/n_r, NoV = (i+0.5)/n_nov; "
    "int f_spec (n.l) dl = F0 A + F90 B; bilinear, clamp to edge",
}


def cube_conventions() -> dict[str, str]:
    """`CONVENTIONS` plus the KTX2 layout, for the metadata of cube-map files."""
    return {**CONVENTIONS, "ktx2_layout": "KTX2 face f = levels[m][f]; file rows i, columns j; no flip"}


def library_versions() -> dict[str, str]:
    """Python and library versions, for output provenance (JSON sidecars, reports)."""
    out = {"python": platform.python_version()}
    for pkg in ("jaxpbr", "jax", "jaxlib", "numpy", "OpenEXR", "colour-science", "OpenImageIO"):
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            pass
    return out
