"""Built-in scenes: the default demo (sphere grid under a procedural sky + sun, plus lights) and
the LearnOpenGL lighting-chapter scene. Everything is generated in code; the demo's sky at its
default size also ships baked (`jaxpbr/_demo_sky`, written by `write_demo_sky`), so that the first
render bakes nothing. `write_demo_glb` writes the demo grid as a glTF 2.0 asset of triangle meshes
(`jaxpbr bench render --gltf`)."""

from __future__ import annotations

import functools
import json
import math
import struct
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .._program_cache import package_digest
from ..ibl.baked import INDEX, write_baked
from ..ibl.cubeio import PROCEDURAL_FACE_SIZE
from ..ibl.cubemap import Cubemap
from ..ibl.envs import sky_with_sun_cubemap
from ..io.atomic import write_json
from ..shading.lights import PointLight
from ..shading.material import Material
from .baked import read_baked
from .cache import ASSETS
from .mesh import Mesh
from .scene import Camera, Environment, Scene, Sphere

__all__ = [
    "DEMO_BASE_COLOR", "DEMO_ENV_ROTATION", "DEMO_FACE_SIZE", "DEMO_SKY_BAKE", "DemoAsset", "demo_environment",
    "demo_grid_lat", "demo_scene", "learnopengl_scene", "shipped_demo_sky", "sphere_grid", "uv_sphere",
    "write_demo_glb", "write_demo_sky",
]

#: Base colour of the demo spheres (linear RGB; a warm gold-like albedo).
DEMO_BASE_COLOR = (0.95, 0.64, 0.37)
#: Rotation of the procedural sky about +Y that puts its sun behind the camera, to the right
#: (world azimuth atan2(z, x) = +40 degrees, 20 degrees up), so the spheres are front-lit.
DEMO_ENV_ROTATION = math.radians(-75.0)
#: Face size of the demo's sky (and of `jaxpbr render ASSET --environment procedural:sky`).
DEMO_FACE_SIZE = PROCEDURAL_FACE_SIZE
#: The options of `write_baked` the shipped demo sky was written with: the maps a render of the sky
#: computes with the default options (the suns split out, the GGX chain of the face size, the
#: irradiance) and the sky itself (the background), as exact float32 EXR faces; no sheen (the demo
#: has none).
DEMO_SKY_BAKE = {"face_size": DEMO_FACE_SIZE, "extract": True, "radiance": True, "sheen": False, "container": "exr"}


def sphere_grid(rows: int = 7, cols: int = 7, *, spacing: float = 2.5, base_color=DEMO_BASE_COLOR,
                metallic=None, roughness=None) -> tuple[Sphere, ...]:
    """rows x cols unit spheres in the z = 0 plane; metallic rises with the row (bottom to top),
    roughness with the column (left to right): metallic = row/(rows-1), roughness = col/(cols-1)
    unless given as arrays of length rows / cols."""
    met = np.linspace(0.0, 1.0, rows) if metallic is None else np.asarray(metallic, float)
    rough = np.linspace(0.0, 1.0, cols) if roughness is None else np.asarray(roughness, float)
    out = []
    for r in range(rows):
        for c in range(cols):
            center = ((c - (cols - 1) / 2) * spacing, (r - (rows - 1) / 2) * spacing, 0.0)
            m = Material(base_color=base_color, metallic=float(met[r]), roughness=float(rough[c]))
            out.append(Sphere(center=center, radius=1.0, material=m))
    return tuple(out)


def _four_lights(intensity: float = 300.0):
    return tuple(
        PointLight(position=pos, color=(1.0, 1.0, 1.0), intensity=intensity)
        for pos in [(-10.0, 10.0, 10.0), (10.0, 10.0, 10.0), (-10.0, -10.0, 10.0), (10.0, -10.0, 10.0)]
    )


def demo_scene(width: int = 1280, height: int = 720, *, face_size: int = DEMO_FACE_SIZE, supersample: int = 1,
               lights: bool = True, environment: bool = True) -> Scene:
    """The default demo: a 7x7 sphere grid (metallic by row, roughness 0..1 by column) under the
    procedural sky with a 3000-radiance sun (`jaxpbr.ibl.envs`), rotated to light the spheres from
    behind the camera, plus four point lights of 300 cd at (+-10, +-10, 10). The environment is
    `demo_environment(face_size=face_size)`: baked (the shipped set) at the default face size."""
    env = demo_environment(face_size=face_size, rotation=DEMO_ENV_ROTATION) if environment else None
    return Scene(
        camera=Camera(position=(0.0, 0.0, 24.0), fov_y_deg=45.0, width=width, height=height, supersample=supersample),
        objects=sphere_grid(),
        lights=_four_lights() if lights else (),
        environment=env,
    )


def demo_sky(face_size: int = DEMO_FACE_SIZE) -> Cubemap:
    """The demo's procedural sky (`sky_with_sun_cubemap(face_size)`) through the process's asset
    cache (`cache.ASSETS`, on disk where the command line keeps one), keyed by the face size and a
    digest of the package's code: a warm start reads the cube instead of filtering it again."""
    face_size = int(face_size)
    return ASSETS.get("sky", ("sky_with_sun", face_size, package_digest()), lambda: sky_with_sun_cubemap(face_size))


def demo_environment(*, face_size: int = DEMO_FACE_SIZE, rotation: float = 0.0, intensity: float = 1.0) -> Environment:
    """The demo's procedural sky as an `Environment`. At the default face size it is the shipped
    baked set (`shipped_demo_sky`: the sky, the sun split out of it as a disc light, the residual's
    irradiance and GGX chain; a render precomputes nothing); at other sizes, the radiance
    (`demo_sky`), whose maps the render computes and caches. Both render the same image (tested)."""
    face_size = int(face_size)
    env = shipped_demo_sky() if face_size == DEMO_FACE_SIZE else None
    if env is None:
        env = Environment(radiance=demo_sky(face_size))
    return env.replace(rotation=rotation, intensity=intensity)


def _demo_sky_dir():
    return resources.files("jaxpbr._demo_sky")


@functools.lru_cache(maxsize=1)
def shipped_demo_sky() -> Environment | None:
    """The baked set of the demo's sky shipped in the package (`jaxpbr/_demo_sky`, written by
    `write_demo_sky`) read back (`jaxpbr.read_baked`), without its LUT: a render reads the shipped
    split-sum table, as it does for the sky's radiance. None when the package has no such set."""
    folder = _demo_sky_dir()
    if not folder.joinpath(INDEX).is_file():
        return None
    with resources.as_file(folder) as path:
        env = read_baked(path)
    return env.replace(lut=None)


def write_demo_sky(out_dir, *, measure_error: bool = True) -> dict:
    """Write the demo sky's baked set into the folder `out_dir` (`jaxpbr.write_baked` of
    "procedural:sky" with `DEMO_SKY_BAKE`), the files' names in ibl.json and the sidecars relative
    to the folder. This is how `jaxpbr/_demo_sky` is made:

        python -c "from jaxpbr.rendering.demo import write_demo_sky; write_demo_sky('jaxpbr/_demo_sky')"

    -> the index (ibl.json)."""
    d = Path(out_dir)
    index = write_baked("procedural:sky", d, measure_error=measure_error, **DEMO_SKY_BAKE)

    def relative(entry):
        if isinstance(entry, dict):
            return {k: ([Path(f).name for f in v] if k == "files" else Path(v).name if k == "file" else relative(v))
                    for k, v in entry.items()}
        return entry

    for path in [d / INDEX, *d.glob("*.json")]:
        if path.name != "lights.json":
            write_json(path, relative(json.loads(path.read_text())))
    return relative(index)


def learnopengl_scene(width: int = 1280, height: int = 720) -> Scene:
    """The LearnOpenGL "PBR / Lighting" chapter: 7x7 spheres, albedo (0.5, 0, 0), metallic =
    row/7, roughness = clamp(col/7, 0.05, 1), four point lights of 300, constant ambient 0.03,
    black background."""
    rows = cols = 7
    spheres = sphere_grid(
        rows, cols, base_color=(0.5, 0.0, 0.0),
        metallic=np.arange(rows) / rows, roughness=np.clip(np.arange(cols) / cols, 0.05, 1.0),
    )
    return Scene(
        camera=Camera(width=width, height=height),
        objects=spheres,
        lights=_four_lights(),
        ambient=0.03,
        background=jnp.zeros(3),
    )


# ------------------------------------------------------------------------------------------
# The demo grid as a glTF asset
# ------------------------------------------------------------------------------------------


def uv_sphere(n_lat: int, *, n_lon: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions, normals, triangles) of a unit UV sphere: `n_lat` latitude bands, `n_lon`
    (default 2 n_lat) longitude segments, (n_lat + 1)(n_lon + 1) vertices (the seam column and
    the poles repeated), 2 n_lon (n_lat - 1) triangles, counter-clockwise seen from outside;
    float32 / uint32."""
    n_lat = int(n_lat)
    n_lon = 2 * n_lat if n_lon is None else int(n_lon)
    if n_lat < 2 or n_lon < 3:
        raise ValueError(f"a UV sphere needs n_lat >= 2 and n_lon >= 3, got {n_lat} and {n_lon}")
    th, ph = np.meshgrid(np.linspace(0.0, np.pi, n_lat + 1), np.linspace(0.0, 2.0 * np.pi, n_lon + 1), indexing="ij")
    n = np.stack([np.sin(th) * np.sin(ph), np.cos(th), np.sin(th) * np.cos(ph)], -1).reshape(-1, 3)
    W = n_lon + 1
    i, j = np.meshgrid(np.arange(n_lat), np.arange(n_lon), indexing="ij")
    a, b, c, d = i * W + j, (i + 1) * W + j, (i + 1) * W + j + 1, i * W + j + 1
    upper = np.stack([a, b, d], -1)[1:]  # the band touching the north pole has no (a, b, d) quad half
    lower = np.stack([b, c, d], -1)[:-1]  # nor the south pole's a (b, c, d) one
    tris = np.concatenate([upper.reshape(-1, 3), lower.reshape(-1, 3)])
    n = n.astype(np.float32)
    return n, n.copy(), tris.astype(np.uint32)


def demo_grid_lat(triangles: int) -> int:
    """The latitude bands of the UV spheres whose 7x7 grid comes closest to `triangles` triangles
    (49 spheres of 4 n (n - 1) triangles each; at least 2 bands)."""
    t = float(triangles) / 196.0
    n = max(2, round(0.5 + math.sqrt(0.25 + t)))
    return min((k for k in (n - 1, n, n + 1) if k >= 2), key=lambda k: abs(196 * k * (k - 1) - triangles))


@dataclass(frozen=True)
class DemoAsset:
    """What `write_demo_glb` wrote: the file, the latitude bands of each sphere and the totals."""

    path: Path
    lat: int
    triangles: int
    vertices: int


def write_demo_glb(path, *, triangles: int = 1_000_000, lat: int | None = None, lights: bool = True,
                   camera: bool = True) -> DemoAsset:
    """The demo's 7x7 sphere grid (`demo_scene`: centres, radii, materials) as a binary glTF 2.0
    file of triangle meshes: one UV sphere (`uv_sphere(lat)`, smooth normals) whose accessors the
    49 meshes share, each with its own metallic-roughness material, placed by 49 nodes. `lat`
    (default `demo_grid_lat(triangles)`) sets the tessellation. With `lights`, the demo's four
    point lights (KHR_lights_punctual, 300 cd each); with `camera`, the demo's camera (at
    (0, 0, 24) looking down -Z, 45 degrees vertical field of view). No environment: a glTF asset
    carries none (`jaxpbr render ASSET --environment procedural:sky`)."""
    n = demo_grid_lat(triangles) if lat is None else int(lat)
    P, N, T = uv_sphere(n)
    binary = bytearray()
    views: list = []
    accessors: list = []

    def accessor(data: np.ndarray, kind: str, component: int, target: int, bounds: bool = False) -> int:
        while len(binary) % 4:
            binary.append(0)
        views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": data.nbytes, "target": target})
        binary.extend(data.tobytes())
        acc = {"bufferView": len(views) - 1, "componentType": component, "count": int(data.shape[0]), "type": kind}
        if bounds:
            acc["min"], acc["max"] = data.min(0).tolist(), data.max(0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    pos = accessor(P, "VEC3", 5126, 34962, bounds=True)  # FLOAT, ARRAY_BUFFER
    nor = accessor(N, "VEC3", 5126, 34962)
    idx = accessor(T.reshape(-1), "SCALAR", 5125, 34963)  # UNSIGNED_INT, ELEMENT_ARRAY_BUFFER
    ref = demo_scene(16, 16)
    materials, meshes, nodes = [], [], []
    for k, s in enumerate(ref.objects):
        m = s.material
        materials.append({"name": f"sphere {k}", "pbrMetallicRoughness": {
            "baseColorFactor": [*(float(x) for x in np.asarray(m.base_color)), 1.0],
            "metallicFactor": float(m.metallic), "roughnessFactor": float(m.roughness)}})
        meshes.append({"primitives": [{"attributes": {"POSITION": pos, "NORMAL": nor}, "indices": idx, "material": k}]})
        nodes.append({"mesh": k, "translation": [float(c) for c in np.asarray(s.center)]})
    doc: dict = {"asset": {"version": "2.0", "generator": "jaxpbr write_demo_glb"}, "scene": 0}
    if camera:
        cam = ref.camera
        doc["cameras"] = [{"type": "perspective", "perspective": {"yfov": math.radians(cam.fov_y_deg), "znear": 0.01}}]
        nodes.append({"camera": 0, "translation": [float(c) for c in np.asarray(cam.position)]})
    if lights:
        doc["extensionsUsed"] = ["KHR_lights_punctual"]
        doc["extensions"] = {"KHR_lights_punctual": {"lights": [
            {"type": "point", "color": [float(c) for c in np.asarray(lt.color)], "intensity": float(lt.intensity)}
            for lt in ref.lights]}}
        nodes += [{"translation": [float(c) for c in np.asarray(lt.position)], "extensions": {"KHR_lights_punctual": {"light": i}}}
                  for i, lt in enumerate(ref.lights)]
    while len(binary) % 4:
        binary.append(0)
    doc |= {"scenes": [{"nodes": list(range(len(nodes)))}], "nodes": nodes, "meshes": meshes, "materials": materials,
            "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(binary)}]}
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    path = Path(path)
    with open(path, "wb") as f:
        f.write(struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(js) + 8 + len(binary)))  # "glTF", version 2
        f.write(struct.pack("<II", len(js), 0x4E4F534A) + js)  # JSON chunk
        f.write(struct.pack("<II", len(binary), 0x004E4942))  # BIN chunk
        f.write(binary)
    return DemoAsset(path=path, lat=n, triangles=49 * len(T), vertices=49 * len(P))


def concave_scene(width: int = 320, height: int = 240, *, environment: Environment | None = None) -> Scene:
    """A concave test scene written in code, all Lambertian meshes (specular 0): an open box (three
    walls 2 high around a 4 x 4 floor, open towards the camera and the sky) on a ground 8 x 8, a
    sphere in the box's back-left corner touching the floor and both walls, and two fins 0.3 apart
    standing on the floor in front of the right wall (a slot). Its contacts, corners and slot are
    where the environment's light is occluded; the ground in front of the box sees the whole sky. environment: default the demo's sky
    with its sun (128^2 faces), turned so that the sun comes from the front right."""
    grey = Material(base_color=(0.6, 0.6, 0.6), metallic=0.0, roughness=1.0, specular=0.0)
    red = Material(base_color=(0.7, 0.25, 0.2), metallic=0.0, roughness=1.0, specular=0.0)

    def quad(p0, p1, p2, p3, n=8):
        # an n x n grid over the quad p0 p1 p2 p3 (counter-clockwise seen from its front)
        u, v = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
        P = ((1 - u) * (1 - v))[..., None] * p0 + (u * (1 - v))[..., None] * p1 + (u * v)[..., None] * p2 + ((1 - u) * v)[..., None] * p3
        idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
        a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
        tri = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
        return P.reshape(-1, 3).astype(np.float32), tri.astype(np.int32)

    def mesh(parts, material):
        pos, tri, off = [], [], 0
        for P, T in parts:
            pos.append(P)
            tri.append(T + off)
            off += len(P)
        return Mesh(positions=np.concatenate(pos), triangles=np.concatenate(tri), material=material, double_sided=True)

    A = lambda *x: np.asarray(x, np.float64)  # noqa: E731
    box = mesh([
        quad(A(-4, 0, 6), A(4, 0, 6), A(4, 0, -2), A(-4, 0, -2), 32),  # ground, inside the box and out (normal +y)
        quad(A(-2, 0, -2), A(2, 0, -2), A(2, 2, -2), A(-2, 2, -2)),  # back wall (+z)
        quad(A(-2, 0, 2), A(-2, 0, -2), A(-2, 2, -2), A(-2, 2, 2)),  # left wall (+x)
        quad(A(2, 0, -2), A(2, 0, 2), A(2, 2, 2), A(2, 2, -2)),  # right wall (-x)
    ], grey)
    fins = mesh([
        quad(A(1.0, 0, -0.5), A(1.0, 0, 1.0), A(1.0, 1.0, 1.0), A(1.0, 1.0, -0.5)),
        quad(A(1.3, 0, 1.0), A(1.3, 0, -0.5), A(1.3, 1.0, -0.5), A(1.3, 1.0, 1.0)),
    ], grey)
    r = 0.6
    pos, nrm, tri = uv_sphere(24)
    ball = Mesh(positions=(np.asarray(pos) * r + np.array([-2 + r, r, -2 + r])).astype(np.float32), normals=np.asarray(nrm, np.float32),
                triangles=np.asarray(tri, np.int32), material=red)
    if environment is None:
        environment = demo_environment(rotation=math.radians(150.0))
    cam = Camera(position=(0.5, 5.0, 8.0), target=(0.0, 0.3, 0.5), fov_y_deg=45.0, width=width, height=height)
    return Scene(camera=cam, objects=(box, fins, ball), environment=environment)
