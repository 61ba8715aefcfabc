"""The conventions jaxpbr follows, as data: written into every output file's metadata."""

from __future__ import annotations

CONVENTIONS: dict[str, str] = {
    "axes": "right-handed, +Y up, camera looks down -Z (glTF/OpenGL)",
    "directions": "n, v, l unit vectors pointing away from the surface; h = normalize(v + l)",
    "roughness": "perceptual r in [0, 1]; GGX alpha = r^2",
    "color": "linear scene-referred RGB, Rec.709/sRGB primaries; encoding only at output",
    "light_units": "KHR_lights_punctual: point/spot intensity in cd, directional in lux",
    "brdf_models": "gltf = glTF 2.0 App. B (height-correlated Smith); "
    "learnopengl = UE4/Karis Schlick-GGX k=(r+1)^2/8",
    "min_roughness_punctual": "0.045 (perceptual; Filament desktop floor)",
}
