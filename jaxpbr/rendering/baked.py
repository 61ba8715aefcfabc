"""A baked IBL set on disk read back as a baked `Environment` (`jaxpbr.read_baked`).

The files are read by `jaxpbr.ibl.baked.read_baked_maps` (what `jaxpbr.write_baked` and
`jaxpbr ibl` write); this module only builds the scene's `Environment` from them, as
`gltf_scene.load_gltf` builds a `Scene` from what `jaxpbr.io.gltf` reads.
"""

from __future__ import annotations

from ..ibl.baked import read_baked_maps
from ..ibl.cubemap import Cubemap
from .scene import Environment

__all__ = ["read_baked"]


def read_baked(directory) -> Environment:
    """The baked `Environment` of the set in `directory` (written by `jaxpbr.write_baked` or
    `jaxpbr ibl`): irradiance, prefiltered (with the lookup metadata of its file), lut and
    lut_smith, lights (the suns `extract=True` split out, else None), charlie and sheen_lut (when
    the set has sheen). A render with it precomputes nothing and equals a render with
    `jaxpbr.bake` of the same environment and options up to the files' storage (float16 KTX2:
    2^-11 relative per texel; rgba32f and EXR: exact).

    radiance, drawn as the background: the environment itself where the set stores it
    (`write_baked(radiance=True)`, `jaxpbr ibl --radiance`), else the prefiltered map's level 0
    (the environment at the prefiltered face size; without the suns when they were extracted,
    which `lights` then shades). `intensity` and `rotation` apply as to any Environment.
    Raises InputError naming the file and the fix for a missing, unreadable or inconsistent set."""
    maps = read_baked_maps(directory)
    return Environment(
        radiance=maps.radiance if maps.radiance is not None else Cubemap(maps.prefiltered.levels[0]),
        irradiance=maps.irradiance,
        prefiltered=maps.prefiltered,
        lut=maps.lut,
        lut_smith=maps.lut_smith,
        lights=maps.lights,
        charlie=maps.charlie,
        sheen_lut=maps.sheen_lut,
    )
