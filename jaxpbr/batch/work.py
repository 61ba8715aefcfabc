"""Running jobs: `Worker` turns a validated job into its output files and completion record.

Both engines run jobs through a `Worker` (the in-process engine in the driver, the Ray engine in
one per actor), so a job's files are the same bytes whichever engine ran it. A worker keeps what
consecutive jobs share: scenes by source and size, environments by file (their precomputes are
cached by content in the renderer's asset cache) and, through JAX, the compiled programs.

A render job is split in two: `compute` (on the device: the render, the display transform, the
AOVs; returns device arrays without waiting) and `write` (on the host: one copy of each image, the
files written as one atomic set, then the record). The in-process engine overlaps the `write` of
one job with the `compute` of the next.
"""

from __future__ import annotations

import importlib
import math
import os
import socket
import sys
import time
import traceback
from collections import OrderedDict
from pathlib import Path

import jax
import numpy as np

from .. import color
from ..conventions import CONVENTIONS
from ..errors import InputError
from ..ibl.baked import STEMS, write_baked
from ..io import image
from ..io.atomic import OutputSet
from ..rendering.aovs import exr_layers, render_with_aovs
from ..rendering.demo import demo_scene
from ..rendering.gltf_scene import environment_from, load_gltf
from ..rendering.renderer import RenderOptions, check_memory, plan, render
from ..rendering.scene import Scene
from ..rendering.scene_file import load_scene
from ..rendering.textured import TexturedMaterial
from ..shading.material import Material
from .jobs import BakeJob, RenderJob, factory_module_file
from .store import OutputFolder

__all__ = ["Worker", "failure"]

#: Scenes and environments a worker keeps (least recently used dropped first).
KEEP = 4


class _LRU(OrderedDict):
    def get_or(self, key, make):
        if key in self:
            self.move_to_end(key)
            return self[key]
        value = make()
        self[key] = value
        while len(self) > KEEP:
            self.popitem(last=False)
        return value


def _is_gltf(source) -> bool:
    return isinstance(source, (str, Path)) and Path(source).suffix.lower() in (".gltf", ".glb")


class Worker:
    """Runs jobs into an output folder (`OutputFolder`); see the module docstring."""

    def __init__(self, out, *, name: str | None = None):
        self.folder = out if isinstance(out, OutputFolder) else OutputFolder(out)
        self.name = name or f"{socket.gethostname()}:{os.getpid()}"
        self._scenes = _LRU()
        self._envs = _LRU()

    # -- the whole job ------------------------------------------------------------------------

    def run(self, job, *, attempt: int = 1) -> dict:
        """Run one job to its files and record -> the record."""
        t0 = time.perf_counter()
        if isinstance(job, BakeJob):
            files = self.bake(job)
            return self.folder.commit(job, files, seconds=time.perf_counter() - t0, worker=self.name, attempt=attempt)
        pending = self.compute(job)
        return self.write(job, pending, t0=t0, attempt=attempt)

    # -- render jobs --------------------------------------------------------------------------

    def compute(self, job: RenderJob) -> dict:
        """Dispatch a render job's device work; returns the device arrays and what `write` needs."""
        scene, file_options, file_display = self.scene(job)
        opts = RenderOptions(**{**file_options, **job.options})
        if opts.dtype == "float64" and not jax.config.jax_enable_x64:
            raise InputError(f"job {job.name!r}: options.dtype float64 needs JAX's 64-bit mode; "
                             f"set JAX_ENABLE_X64=1 for the run")
        check_memory(scene, options=opts, where=f"job {job.name!r}")
        display = {"exposure": 0.0, "bits": 8, **file_display, **job.display}
        display.setdefault("tonemap", "reinhard" if opts.model == "learnopengl" else "aces")
        display.setdefault("encoding", "gamma2.2" if opts.model == "learnopengl" else "srgb")
        if job.aovs:  # one geometry pass for the image and its AOVs where it can be shared
            hdr, job_aovs = render_with_aovs(scene, job.aovs, options=opts)
        else:
            hdr = render(scene, options=opts)
        out = {"hdr": hdr, "display": display, "options": opts, "plan": plan(scene, options=opts).describe()}
        if "png" in job.formats:
            out["ldr"] = color.display(hdr, float(display["exposure"]), tonemap=display["tonemap"],
                                           encoding=display["encoding"])
        if job.aovs:
            out["aovs"] = job_aovs
        return out

    def write(self, job: RenderJob, pending: dict, *, t0: float, attempt: int = 1) -> dict:
        """Copy a computed job to the host, write its files as one atomic set, then its record."""
        hdr = np.asarray(pending["hdr"])
        if not np.all(np.isfinite(hdr)):
            raise RuntimeError(f"job {job.name!r}: the render produced non-finite values; this is a bug, please report it")
        display, opts = pending["display"], pending["options"]
        metadata = {
            "software": "jaxpbr",
            "jaxpbr:job": job.name,
            "jaxpbr:plan": pending["plan"],
            "jaxpbr:model": opts.model,
            "jaxpbr:render_options": repr(opts),
            "jaxpbr:conventions": CONVENTIONS,
        }
        root = self.folder.root
        files = []
        (root / job.name).parent.mkdir(parents=True, exist_ok=True)
        with OutputSet() as outs:
            if "png" in job.formats:
                path = root / f"{job.name}.png"
                outs.add(path)
                meta = {**metadata, "jaxpbr:exposure_ev": float(display["exposure"]),
                        "jaxpbr:tonemap": display["tonemap"], "jaxpbr:encoding": display["encoding"]}
                image.write(path, np.asarray(pending["ldr"]), bits=display["bits"], encoding=display["encoding"],
                            encoded=True, metadata=meta)
                files.append(f"{job.name}.png")
            if "exr" in job.formats:
                path = root / f"{job.name}.exr"
                meta = {**metadata, "jaxpbr:content": "linear scene-referred radiance, Rec.709 primaries"}
                layers, aov_meta = exr_layers(pending["aovs"], job.aovs) if job.aovs else ({}, {})
                meta |= aov_meta
                outs.add(path)
                image.write(path, hdr, metadata=meta, layers=layers)
                files.append(f"{job.name}.exr")
        return self.folder.commit(job, files, seconds=time.perf_counter() - t0, worker=self.name, attempt=attempt)

    def scene(self, job: RenderJob):
        """The job's scene -> (Scene, the scene file's render options, its display settings)."""
        W, H = job.width, job.height
        own_env = job.environment is None  # the demo's sky is not built for a job that replaces it
        # A glTF asset's camera follows `load_gltf`'s rules with the job's overrides (as `jaxpbr render
        # ASSET --camera-position ...` does): they are part of what is loaded.
        c = job.camera or {}
        view = tuple((k, tuple(np.ravel(c[k]).tolist())) for k in ("position", "target", "fov_y") if k in c) if _is_gltf(job.scene) else ()
        pose = (job.time, job.animation)
        base, file_options, file_display = self._scenes.get_or(
            (repr(job.scene), W, H, own_env, view, pose),
            lambda: self._load_scene(job.scene, W, H, environment=own_env, view=dict(view), pose=pose))
        cam = base.camera
        if cam is not None:
            changes = {}
            if W is not None:
                changes["width"] = W
            if H is not None:
                changes["height"] = H
            if job.supersample is not None:
                changes["supersample"] = job.supersample
            c = job.camera or {}
            for k, field in (("position", "position"), ("target", "target"), ("up", "up"), ("fov_y", "fov_y_deg"), ("ymag", "ymag")):
                if k in c:
                    changes[field] = c[k]
            if changes:
                base = base.replace(camera=cam.replace(**changes))
        elif job.camera:
            raise InputError(f"job {job.name!r}: camera: the scene has no camera to change (a G-buffer scene)")
        env = base.environment
        if job.environment is not None:
            # (the same environment as `jaxpbr render --environment` and `load_gltf` read: the demo's
            # baked sky for procedural:sky)
            env = self._envs.get_or(job.environment, lambda: environment_from(job.environment))
        if env is not None and (job.environment_intensity is not None or job.environment_rotation is not None):
            changes = {}
            if job.environment_intensity is not None:
                changes["intensity"] = job.environment_intensity
            if job.environment_rotation is not None:
                changes["rotation"] = math.radians(job.environment_rotation)
            env = env.replace(**changes)
        elif job.environment_intensity is not None or job.environment_rotation is not None:
            raise InputError(f"job {job.name!r}: environment_intensity/environment_rotation: the scene has no environment")
        if env is not base.environment:
            base = base.replace(environment=env)
        if job.material:
            base = base.replace(objects=[_with_material(o, job.material) for o in base.objects])
        return base, file_options, file_display

    def _load_scene(self, source, W, H, *, environment: bool = True, view=None, pose=(None, None)):
        if source == "demo":
            return demo_scene(W or 1280, H or 720, environment=environment), {}, {}
        if isinstance(source, tuple):  # ("factory", "module:function", args-json, folder)
            _, target, args, folder = source
            import json

            mod_name, fn_name = target.split(":")
            source_file = factory_module_file(target, folder)
            if source_file is None:
                raise InputError(f"scene factory {target!r}: the module is not a Python file in the job file's folder ({folder})")
            # The job file's folder first on the path, and a module of that name imported from
            # elsewhere (another job file's folder) forgotten: each job gets its own folder's module.
            if folder in sys.path:
                sys.path.remove(folder)
            sys.path.insert(0, folder)
            top = mod_name.partition(".")[0]
            held = sys.modules.get(mod_name)
            if held is not None and os.path.realpath(getattr(held, "__file__", "") or "") != os.path.realpath(source_file):
                for name in [n for n in sys.modules if n == top or n.startswith(top + ".")]:
                    del sys.modules[name]
                importlib.invalidate_caches()
            try:
                module = importlib.import_module(mod_name)
                fn = getattr(module, fn_name)
            except (ImportError, AttributeError) as e:
                raise InputError(f"scene factory {target!r}: {e}; the module is imported with the job file's folder on sys.path") from None
            loaded = getattr(module, "__file__", None)
            if loaded is None or os.path.realpath(loaded) != os.path.realpath(source_file):
                raise InputError(f"scene factory {target!r}: the module is not the Python file in the job file's folder "
                                 f"({folder}) (a module of that name was imported from {loaded or 'the interpreter'}); "
                                 "rename the factory's module")
            scene = fn(**json.loads(args))
            if not isinstance(scene, Scene):
                raise InputError(f"scene factory {target!r} returned {type(scene).__name__}, not a jaxpbr.Scene")
            return scene, {}, {}
        path = Path(source)
        if path.suffix.lower() == ".toml":
            sf = load_scene(path)
            return sf.scene, dict(sf.options), dict(sf.output)
        view = view or {}
        fov = view.get("fov_y")
        return load_gltf(path, width=W or 1280, height=H or 720, camera_position=view.get("position"), camera_target=view.get("target"),
                         fov_y_deg=None if fov is None else float(fov[0]), time=pose[0], animation=pose[1]), {}, {}

    # -- bake jobs ----------------------------------------------------------------------------

    def bake(self, job: BakeJob) -> list[str]:
        """`write_baked` into the job's folder -> the files written (relative to the output folder)."""
        d = self.folder.root / job.name
        d.mkdir(parents=True, exist_ok=True)
        write_baked(job.environment, d, **job.options)
        # The set: the files of the baked-set stems (a stale file of another container or of an
        # earlier bake with other options stays out of the record only if it has another stem).
        files = sorted(p for stem in STEMS for p in d.glob(f"{stem}*") if p.is_file())
        return [str(p.relative_to(self.folder.root)) for p in files]


def _with_material(obj, fields: dict):
    m = getattr(obj, "material", None)
    if isinstance(m, Material):
        return obj.replace(material=m.replace(**fields))
    if isinstance(m, TexturedMaterial):
        return obj.replace(material=m.replace(factors=m.factors.replace(**fields)))
    return obj


def failure(e: BaseException, attempts: int) -> dict:
    """A failed job's result: the cause in one line (and the traceback of an unexpected error)."""
    msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    cause = f"{type(e).__name__}: {msg}" if not isinstance(e, InputError) else msg
    out = {"status": "failed", "error": cause, "attempts": attempts}
    if not isinstance(e, (InputError, MemoryError, OSError)):
        out["traceback"] = "".join(traceback.format_exception(e))[-4000:]
    return out
