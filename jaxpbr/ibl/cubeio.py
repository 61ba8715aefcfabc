"""Cube maps to and from files: environments in (an equirect panorama, six face images or a
procedural sky), cube maps with all their mips out (KTX2 or per-face EXR)."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np

from .._api import keyword_only
from .._memory import cube_bytes, require
from .._validate import positive_int
from ..errors import InputError
from ..io import image
from ..io.atomic import OutputSet
from ..io.ktx2 import write_ktx2
from . import envs
from .cubemap import Cubemap, downsample

__all__ = ["ENVIRONMENT_HELP", "FACE_FILE_NAMES", "PROCEDURAL_FACE_SIZE", "default_face_size", "load_environment", "write_cubemap"]

ENVIRONMENT_HELP = (
    "environment: one equirect panorama (.hdr/.exr, width = 2 x height), six square face images "
    "in the order +X -X +Y -Y +Z -Z, or 'procedural:sky' (a clear sky with a 3000-radiance sun, "
    "generated in code)"
)
#: File-name suffixes of the six faces, in KTX order +X -X +Y -Y +Z -Z.
FACE_FILE_NAMES = ("px", "nx", "py", "ny", "pz", "nz")


#: Face size of "procedural:sky" when none is given: one sky everywhere, the demo's (`jaxpbr render`'s
#: default scene and `--environment procedural:sky`, batch jobs, `jaxpbr ibl`, scene files, and
#: `load_environment`), whose baked set the package ships (`jaxpbr/_demo_sky`).
PROCEDURAL_FACE_SIZE = 128


@keyword_only("face_size")
def load_environment(paths, *, face_size: int | None = None, clamp_negative: bool = False) -> Cubemap:
    """Read an environment -> float32 `Cubemap` (level 0 only).

    paths: one equirect panorama (.hdr/.exr, width = 2 x height), six square face images in the
        order +X -X +Y -Y +Z -Z, or ["procedural:sky"] (`envs.sky_with_sun_cubemap`).
    face_size: cube face size; default: the power of two nearest to a quarter of the panorama's
        width (`PROCEDURAL_FACE_SIZE`, 128, for the procedural sky: the demo's). Six faces can only be reduced by powers of two.
    clamp_negative: set negative pixels to 0 with a `UserWarning` instead of failing.

    Raises `InputError` (naming the problem and the fix) for a missing or unreadable file, a
    panorama that is not 2:1, faces that are not equal squares, NaN/Inf or negative pixels.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [str(p) for p in paths]
    procedural = len(paths) == 1 and paths[0].startswith("procedural:")
    if face_size is not None:  # before any work (a huge size aborted inside XLA)
        S = positive_int("--face-size", face_size)
        require(f"a {S}^2 environment cube", cube_bytes(S, supersample=4 if procedural else None), names={"face_size": "--face-size"})
    if procedural:
        name = paths[0].split(":", 1)[1]
        if name != "sky":
            raise InputError(f"unknown procedural environment {name!r}; the one available is 'procedural:sky'")
        return envs.sky_with_sun_cubemap(face_size or PROCEDURAL_FACE_SIZE)
    if len(paths) not in (1, 6):
        raise InputError(
            f"expected one equirect panorama or six face images (+X -X +Y -Y +Z -Z), got {len(paths)} paths"
        )
    imgs = []
    for p in paths:
        path = Path(p)
        if not path.exists():
            raise InputError(f"environment file {p!r} does not exist")
        if path.suffix.lower() not in (".hdr", ".exr"):
            raise InputError(f"environment file {p!r} must be a linear HDR image (.hdr or .exr)")
        try:
            img = image.read(path)
        except Exception as e:  # unreadable / corrupt
            raise InputError(f"cannot read environment file {p!r}: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from e
        img = np.asarray(img, np.float32)
        if img.ndim == 2:
            img = img[..., None]
        if img.shape[-1] == 4:
            img = img[..., :3]
        elif img.shape[-1] in (1, 2):  # grey (+ alpha): the same radiance in R, G and B
            # (issue 13: a 1-channel EXR passed here and failed at the KTX2 write after the work)
            img = np.repeat(img[..., :1], 3, axis=-1)
        bad = ~np.isfinite(img)
        if bad.any():
            raise InputError(f"{p!r} has {int(bad.any(-1).sum())} pixels with NaN/Inf values; fix the image first")
        neg = img < 0
        if neg.any():
            if not clamp_negative:
                raise InputError(
                    f"{p!r} has {int(neg.any(-1).sum())} pixels with negative radiance; "
                    "pass --clamp-negative to set them to 0"
                )
            warnings.warn(f"clamped {int(neg.any(-1).sum())} negative pixels of {p!r} to 0", UserWarning, stacklevel=2)
            img = np.maximum(img, 0.0)
        imgs.append(img)
    if len(imgs) == 1:
        img = imgs[0]
        H, W = img.shape[:2]
        if W != 2 * H:
            raise InputError(
                f"{paths[0]!r} is {W}x{H}; an equirect panorama must be exactly twice as wide as high "
                "(or give six square face images)"
            )
        S = face_size or default_face_size(H)
        return Cubemap.from_equirect(img, S)
    shapes = {im.shape for im in imgs}
    if len(shapes) != 1 or imgs[0].shape[0] != imgs[0].shape[1]:
        raise InputError(f"the six face images must be square and the same size, got {[im.shape[:2] for im in imgs]}")
    cube = Cubemap(np.stack(imgs))
    if face_size and face_size != cube.face_size:
        lv = cube.levels[0]
        while lv.shape[1] > face_size and lv.shape[1] % 2 == 0:
            lv = downsample(lv)
        if lv.shape[1] != face_size:
            raise InputError(f"--face-size {face_size} must be the faces' size {cube.face_size} divided by a power of two")
        cube = Cubemap(lv)
    return cube


def _default_face_size(height: int) -> int:
    """Power of two nearest to the panorama's texel density (a face spans a quarter of the width)."""
    return int(min(2048, max(16, 2 ** round(math.log2(max(height / 2, 1))))))


def default_face_size(height: int) -> int:
    """Power of two nearest to the panorama's texel density (a face spans a quarter of the width)."""
    return int(min(2048, max(16, 2 ** round(math.log2(max(height / 2, 1))))))


def write_cubemap(path, cube: Cubemap, *, fmt: str = "rgba16f", metadata: dict | None = None,
                  outputs: OutputSet | None = None) -> list[str]:
    """Write every mip of a cube map: KTX2 (all mips in one file, faces in KTX order, `fmt`
    rgba16f | rgba32f, metadata as `jaxpbr:` key/values) or EXR (one file per mip and face:
    `<stem>_m<m>_<px|nx|py|ny|pz|nz>.exr`, metadata in each header). Every file is written
    atomically and registered with `outputs` (for rollback) as soon as it exists; without
    `outputs`, a failure midway removes the files this call already wrote (no partial cube)."""
    path = Path(path)
    metadata = metadata or {}
    if outputs is None:
        with OutputSet() as own:
            return write_cubemap(path, cube, fmt=fmt, metadata=metadata, outputs=own)
    levels = [np.asarray(lv, np.float32) for lv in cube.levels]
    flat_meta = {f"jaxpbr:{k}": (v if isinstance(v, str) else json.dumps(v)) for k, v in metadata.items()}
    # Each file is registered before it is written, so that a failure or a signal at any point
    # (even between the rename into place and the registration) removes it.
    if path.suffix.lower() == ".ktx2":
        outputs.add(path)
        write_ktx2(path, levels, fmt=fmt, metadata=flat_meta)
        return [str(path)]
    names = []
    for m, lv in enumerate(levels):
        for f in range(6):
            p = path.with_name(f"{path.stem}_m{m}_{FACE_FILE_NAMES[f]}.exr")
            outputs.add(p)
            image.write(p, lv[f], metadata={**metadata, "jaxpbr:mip": m, "jaxpbr:face": FACE_FILE_NAMES[f]})
            names.append(str(p))
    return names
