"""MikkTSpace tangents (jaxpbr.io.gltf.mikktspace) against the reference implementation and by their
properties.

The reference is mikktspace.c as ported to Rust (gltf-rs/mikktspace) and built to WebAssembly: the
npm package `mikktspace` (donmccurdy/mikktspace-wasm, the generator glTF-Transform uses). It takes
texcoords as given and returns its own w; glTF-Transform negates w before storing TANGENT (glTF v
points down the image), which is what `mikktspace_tangents` returns by default. The comparison runs
when `node` and the package are there ($JAXPBR_MIKKTSPACE_JS, default
the checkout's node_modules/mikktspace, as .ci/run installs it) and is skipped otherwise; the property tests need neither.

Measured agreement (the reference's tangent projected onto the tangent plane, the angle to ours;
w compared after the glTF negation), on this suite's meshes:

  case            corners  max angle (deg)  signs equal  reference without a direction
  plane               288  0                all          0
  UV sphere          3072  2.7e-6           all          0
  cube (per face)     324  0                all          0
  mirrored UVs        192  1.3e-6           all          0
  z^2 fan (180 rule)  120  1.8e-6           all          0
  noisy grid         2400  3.5e-6           all          0
  degenerate          156  0                all          2
  random soup        1200  4.0e-6           all          5
  (the reference writes a zero vector where a group's weighted sum vanishes, here on collinear
  triangles whose corner angles are 0; ours is then the documented unit fallback. It writes
  (1,0,0) where a corner gets no frame: in the soup 356 such corners are not orthogonal to their
  normals, and ours is their projection.)
  100k-triangle noisy grid and random soup (slow test): 4.7e-6 and 4.8e-6, all signs equal;
  700 random soups and grids (seeds 0..399, 0..299; not in the suite): worst 4.9e-6.

What remains is float32 rounding: the reference's float32 arithmetic is replayed in its order
(sums included), and only arccos (another libm) and the final normalisation (float64 here) differ
by an ulp or so; a float32 unit vector itself is only good to ~3e-6 degrees. The bound asserted is
1e-4 degrees on every case, every sign equal, and the count of corners without a reference
direction exact.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from jaxpbr.errors import InputError
from jaxpbr.io.gltf import mikktspace as mk
from jaxpbr.io.gltf.mikktspace import mikktspace_tangents

# ---------------------------------------------------------------------------------------------
# meshes (indexed, then unwelded: corner k of triangle t at row 3t + k)
# ---------------------------------------------------------------------------------------------


def _unweld(pos, nrm, uv, tris):
    tris = np.asarray(tris).reshape(-1)
    return pos[tris], nrm[tris], uv[tris]


def _grid_tris(nx, ny):
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    a = i * (ny + 1) + j
    b, c, d = a + ny + 1, a + ny + 2, a + 1
    return np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], -2).reshape(-1, 3)


def plane(nx=8, ny=6):
    x, y = np.meshgrid(np.linspace(0, 2, nx + 1), np.linspace(0, 1, ny + 1), indexing="ij")
    pos = np.stack([x, y, np.zeros_like(x)], -1).reshape(-1, 3)
    nrm = np.tile([0.0, 0.0, 1.0], (len(pos), 1))
    uv = np.stack([x / 2, 1 - y], -1).reshape(-1, 2)  # glTF: v down the image
    return _unweld(pos, nrm, uv, _grid_tris(nx, ny))


def uv_sphere(nu=32, nv=16):
    """Latitude-longitude sphere: a seam at u = 0/1 and poles where triangles collapse."""
    u, v = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    th, ph = 2 * np.pi * u, np.pi * v
    nrm = np.stack([np.sin(ph) * np.cos(th), np.cos(ph), -np.sin(ph) * np.sin(th)], -1)
    nrm = nrm.reshape(-1, 3)
    uv = np.stack([u, v], -1).reshape(-1, 2)
    return _unweld(nrm.copy(), nrm, uv, _grid_tris(nu, nv))


def cube(n=3):
    """Six faces, each an n x n grid with its own normal and its own [0,1]^2 UVs."""
    eye = np.eye(3)
    parts = []
    for ax in range(3):
        for s in (1.0, -1.0):
            nrm, e1, e2 = eye[ax] * s, eye[(ax + 1) % 3] * s, eye[(ax + 2) % 3]
            x, y = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
            pos = (nrm + (2 * x[..., None] - 1) * e1 + (2 * y[..., None] - 1) * e2).reshape(-1, 3)
            uv = np.stack([x, 1 - y], -1).reshape(-1, 2)
            parts.append(_unweld(pos, np.tile(nrm, (len(pos), 1)), uv, _grid_tris(n, n)))
    return tuple(np.concatenate(p) for p in zip(*parts))


def mirrored(nx=8, ny=4):
    """A curved sheet with u = |x|: the UVs mirror at x = 0, where w flips."""
    x, y = np.meshgrid(np.linspace(-1, 1, nx + 1), np.linspace(0, 1, ny + 1), indexing="ij")
    z = 0.2 * np.sin(2 * x) * np.cos(3 * y)
    pos = np.stack([x, y, z], -1).reshape(-1, 3)
    nrm = np.stack([-0.4 * np.cos(2 * x) * np.cos(3 * y), 0.6 * np.sin(2 * x) * np.sin(3 * y),
                    np.ones_like(x)], -1).reshape(-1, 3)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    uv = np.stack([np.abs(x), 1 - y], -1).reshape(-1, 2)
    return _unweld(pos, nrm, uv, _grid_tris(nx, ny))


def fan_z2(n=40, bump=0.2):
    """A fan around one vertex mapped by uv = z^2: triangles k and k + n/2 have exactly opposite
    dP/du at the centre, which the reference's 180-degree rule leaves out of each other's sums."""
    phi = 2 * np.pi * np.arange(n) / n
    ring = np.stack([np.cos(phi), np.sin(phi), bump * np.cos(3 * phi)], -1)
    pos = np.vstack([[0.0, 0.0, 0.0], ring])
    uv = np.vstack([[0.0, 0.0], np.stack([np.cos(2 * phi), np.sin(2 * phi)], -1)]) * 0.5 + 0.5
    nrm = np.tile([0.0, 0.0, 1.0], (n + 1, 1))
    return _unweld(pos, nrm, uv, [[0, 1 + k, 1 + (k + 1) % n] for k in range(n)])


def noisy(nx=20, ny=20, seed=0):
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, 1, nx + 1), np.linspace(0, 1, ny + 1), indexing="ij")
    pos = np.stack([x, y, np.zeros_like(x)], -1).reshape(-1, 3) + rng.normal(0, 0.02, (x.size, 3))
    nrm = np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.3, pos.shape)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    uv = np.stack([x, 1 - y], -1).reshape(-1, 2) + rng.normal(0, 0.03, (x.size, 2))
    return _unweld(pos, nrm, uv, _grid_tris(nx, ny))


def degenerate(seed=2):
    """A plane with zero-UV-area triangles (collapsed and collinear UVs), zero-area triangles with
    repeated corners that share vertices with it, an isolated repeated-corner triangle and a
    collinear (zero-area, distinct corners) triangle."""
    P, N, UV = (a.copy() for a in plane(6, 4))
    rng = np.random.default_rng(seed)
    for t in rng.choice(len(P) // 3, 6, replace=False):
        UV[3 * t:3 * t + 3] = UV[3 * t]
    UV[3 * 5 + 2] = 2 * UV[3 * 5 + 1] - UV[3 * 5]
    k = [0, 0, 1, 4, 5, 5]
    extra = (P[k], N[k], UV[k])
    iso = (np.array([[5, 5, 5], [5, 5, 5], [6, 5, 5.0]]), np.tile([0, 1.0, 0], (3, 1)),
           np.zeros((3, 2)))
    col = (np.array([[0, 0, 1], [1, 0, 1], [2, 0, 1.0]]), np.tile([0, 0, 1.0], (3, 1)),
           np.array([[0, 0], [1, 0], [0, 1.0]]))
    return tuple(np.concatenate(p) for p in zip((P, N, UV), extra, iso, col))


def soup(n=400, seed=1):
    """Random triangles over 60 lattice vertices with random normals and coarse UVs: non-manifold
    and inconsistently wound edges, repeated corners, zero-UV-area triangles."""
    rng = np.random.default_rng(seed)
    pos = rng.integers(0, 4, (60, 3)).astype(float)
    nrm = rng.normal(size=(60, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    uv = rng.integers(0, 3, (60, 2)) / 2.0
    return _unweld(pos, nrm, uv, rng.integers(0, 60, (n, 3)))


CASES = {
    "plane": plane, "uv_sphere": uv_sphere, "cube": cube, "mirrored": mirrored, "fan_z2": fan_z2,
    "noisy": noisy, "degenerate": degenerate, "soup": soup,
}
# max angle (degrees) on corners where the reference has a direction; corners without one
BOUNDS = {"soup": (1e-4, 5), "degenerate": (1e-4, 2)}
DEFAULT_BOUND = (1e-4, 0)


# ---------------------------------------------------------------------------------------------
# the reference, through node
# ---------------------------------------------------------------------------------------------
_PACKAGE = Path(os.environ.get("JAXPBR_MIKKTSPACE_JS", Path(__file__).resolve().parent.parent / "node_modules" / "mikktspace"))
_NODE = shutil.which("node")
_HAVE_REFERENCE = _NODE is not None and (_PACKAGE / "package.json").is_file()
needs_reference = pytest.mark.skipif(
    not _HAVE_REFERENCE,
    reason="node or the npm package mikktspace is missing ($JAXPBR_MIKKTSPACE_JS)")

_REFERENCE_JS = r"""
const fs = require('fs');
const { generateTangents } = require(process.argv[1]);
for (const job of JSON.parse(fs.readFileSync(process.argv[2], 'utf8'))) {
  const b = fs.readFileSync(job.input);
  const a = new Float32Array(b.buffer, b.byteOffset, b.byteLength / 4);
  const n = a.length / 8;
  const t = generateTangents(a.slice(0, 3 * n), a.slice(3 * n, 6 * n), a.slice(6 * n));
  fs.writeFileSync(job.output, Buffer.from(t.buffer, t.byteOffset, t.byteLength));
}
"""


def reference_tangents(meshes, workdir):
    """The reference's (3T, 4) tangents (its own w) for each (positions, normals, texcoords)."""
    workdir = Path(workdir)
    jobs = []
    for k, (P, N, UV) in enumerate(meshes):
        data = np.concatenate([np.asarray(a, np.float32).ravel() for a in (P, N, UV)])
        data.tofile(workdir / f"in{k}.bin")
        jobs.append({"input": str(workdir / f"in{k}.bin"), "output": str(workdir / f"out{k}.bin")})
    (workdir / "jobs.json").write_text(json.dumps(jobs))
    run = subprocess.run([_NODE, "-e", _REFERENCE_JS, str(_PACKAGE), str(workdir / "jobs.json")],
                         capture_output=True, text=True, timeout=300, check=False)
    assert run.returncode == 0, run.stderr
    return [np.fromfile(j["output"], np.float32).reshape(-1, 4) for j in jobs]


def agreement(ours, ref, normals):
    """(max angle in degrees over corners where the reference has a direction, fraction of equal
    signs, number of corners where it has none). The reference's xyz is projected onto the tangent
    plane first (its (1,0,0) default need not be orthogonal to the normal; ours is the projection);
    its w is negated into the glTF convention."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    r = ref[:, :3].astype(np.float64)
    r -= (r * n).sum(1, keepdims=True) * n
    has = np.linalg.norm(r, axis=1) > 1e-3
    o = ours[:, :3].astype(np.float64)
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(o, r), axis=1), (o * r).sum(1)))
    max_angle = float(angle[has].max()) if has.any() else 0.0
    return max_angle, float(np.mean(ours[:, 3] == -ref[:, 3])), int((~has).sum())


@pytest.fixture(scope="module")
def references(tmp_path_factory):
    meshes = {name: make() for name, make in CASES.items()}
    refs = reference_tangents(list(meshes.values()), tmp_path_factory.mktemp("mikktspace"))
    return {name: (mesh, ref) for (name, mesh), ref in zip(meshes.items(), refs)}


def assert_unit_orthogonal(t, normals):
    assert t.dtype == np.float32 and t.shape == (normals.shape[0], 4)
    assert np.isfinite(t).all()
    xyz = t[:, :3].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(xyz, axis=1), 1.0, atol=1e-6)
    n = np.asarray(normals, np.float32).astype(np.float64)  # the normals as the function sees them
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    assert np.abs((xyz * n).sum(1)).max() < 1e-6
    assert set(np.unique(t[:, 3]).tolist()) <= {-1.0, 1.0}


# ---------------------------------------------------------------------------------------------
# against the reference
# ---------------------------------------------------------------------------------------------
@needs_reference
@pytest.mark.parametrize("name", list(CASES))
def test_matches_reference(references, name):
    (P, N, UV), ref = references[name]
    ours = mikktspace_tangents(P, N, UV)
    assert_unit_orthogonal(ours, N)
    max_angle, signs, without = agreement(ours, ref, N)
    bound, expected_without = BOUNDS.get(name, DEFAULT_BOUND)
    print(f"{name}: {len(P)} corners, max angle {max_angle:.2g} deg, signs {signs:.4f}, "
          f"reference without a direction {without}")
    assert signs == 1.0
    assert max_angle < bound
    assert without == expected_without
    if without:  # where the reference has no direction, ours is the fallback: (1,0,0) projected
        n = np.asarray(N, np.float32).astype(np.float64)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        r = ref[:, :3] - (ref[:, :3] * n).sum(1, keepdims=True) * n
        none = np.linalg.norm(r, axis=1) <= 1e-3
        fallback = mk._tangent_plane_unit(np.tile([1.0, 0.0, 0.0], (none.sum(), 1)), n[none])
        np.testing.assert_allclose(ours[none, :3], fallback, atol=1e-6)
    # the other sign convention is the reference's own
    mine = mikktspace_tangents(P, N, UV, convention="mikktspace")
    np.testing.assert_array_equal(mine[:, 3], ref[:, 3])


@needs_reference
def test_reference_flips_w_for_gltf_uvs(tmp_path):
    """The convention check behind the default: on a plane with glTF texcoords (v down the image)
    the reference says w = -1, glTF-Transform stores +1, and the glTF bitangent
    cross(n, t) * w is then -dP/dv (up the image)."""
    P, N, UV = plane(2, 2)
    (ref,) = reference_tangents([(P, N, UV)], tmp_path)
    np.testing.assert_allclose(ref[:, :3], np.tile([1.0, 0.0, 0.0], (len(P), 1)), atol=1e-7)
    assert (ref[:, 3] == -1).all()
    ours = mikktspace_tangents(P, N, UV)
    assert (ours[:, 3] == 1).all()
    bitangent = np.cross(N, ours[:, :3]) * ours[:, 3:]
    np.testing.assert_allclose(bitangent, np.tile([0.0, 1.0, 0.0], (len(P), 1)), atol=1e-7)


@needs_reference
@pytest.mark.slow
def test_matches_reference_large(tmp_path):
    """100k-triangle meshes: a noisy grid and a random soup (20k lattice vertices)."""
    rng = np.random.default_rng(5)
    pos = rng.integers(0, 30, (20000, 3)).astype(float)
    nrm = rng.normal(size=(20000, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    uv = rng.integers(0, 5, (20000, 2)) / 4
    big_soup = _unweld(pos, nrm, uv, rng.integers(0, 20000, (100000, 3)))
    meshes = [noisy(224, 224, seed=3), big_soup]
    refs = reference_tangents(meshes, tmp_path)
    for (P, N, UV), ref, bound in zip(meshes, refs, (1e-4, 1e-4)):
        start = time.perf_counter()
        ours = mikktspace_tangents(P, N, UV)
        seconds = time.perf_counter() - start
        max_angle, signs, _ = agreement(ours, ref, N)
        print(f"{len(P) // 3} triangles: {seconds:.2f} s, max angle {max_angle:.2g} deg, "
              f"signs {signs}")
        assert signs == 1.0 and max_angle < bound
        assert_unit_orthogonal(ours, N)


# ---------------------------------------------------------------------------------------------
# properties (no reference needed)
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("flip", [False, True])
def test_affine_uv_plane_closed_form(flip):
    """A tilted plane with an affine UV map uv = A (a, b) + c in plane coordinates (a, b): every
    tangent is dP/du normalised, and w makes cross(n, t) * w point along -dP/dv (glTF), whatever the
    orientation of the map."""
    rng = np.random.default_rng(7 + flip)
    frame, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    e1, e2 = frame.T[:2]
    n = np.cross(e1, e2)  # a right-handed frame
    A = rng.normal(size=(2, 2))
    if (np.linalg.det(A) < 0) != flip:
        A[:, 0] *= -1
    ab = np.stack(np.meshgrid(np.linspace(0, 1, 7), np.linspace(0, 1, 5), indexing="ij"), -1)
    ab = ab.reshape(-1, 2)
    pos = 0.3 + ab[:, :1] * e1 + ab[:, 1:] * e2
    uv = ab @ A.T + np.array([0.25, -0.5])
    P, N, UV = _unweld(pos, np.tile(n, (len(pos), 1)), uv, _grid_tris(6, 4))
    t = mikktspace_tangents(P, N, UV)
    assert_unit_orthogonal(t, N)
    dP = np.stack([e1, e2], 1) @ np.linalg.inv(A)  # columns dP/du, dP/dv
    dPdu, dPdv = dP[:, 0], dP[:, 1]
    np.testing.assert_allclose(t[:, :3], np.tile(dPdu / np.linalg.norm(dPdu), (len(P), 1)),
                               atol=2e-6)
    bitangent = np.cross(N, t[:, :3]) * t[:, 3:]
    assert (bitangent @ -dPdv > 0).all()
    # a map that keeps the orientation (det A > 0: v turns from u like e2 from e1, about n) needs
    # w = -1 for the bitangent to point down v
    expected_w = -1.0 if np.linalg.det(A) > 0 else 1.0
    assert (t[:, 3] == expected_w).all()
    own = mikktspace_tangents(P, N, UV, convention="mikktspace")
    np.testing.assert_array_equal(own[:, 3], -t[:, 3])


def test_180_degree_rule():
    """uv = z^2 around the fan's centre: triangle k and k + n/2 have exactly opposite dP/du, so
    with all of the centre's triangles in the sum the contributions cancel in pairs. The reference
    leaves a triangle's opposite out of its corner's sum (cos <= -1 against the default 180-degree
    threshold): each centre corner then keeps its own triangle's dP/du. Whether the float32 cos
    reaches -1 is a matter of rounding: with 20 triangles it does for every pair (with 40, for 36 of
    40 corners; the others sum everything, like the reference: see test_matches_reference)."""
    P, N, UV = fan_z2(20, bump=0.2)
    t = mikktspace_tangents(P, N, UV)
    assert_unit_orthogonal(t, N)
    P3, UV3 = P.reshape(-1, 3, 3), UV.reshape(-1, 3, 2)
    d = np.stack([P3[:, 1] - P3[:, 0], P3[:, 2] - P3[:, 0]], 2)  # (T, 3, 2)
    duv = np.stack([UV3[:, 1] - UV3[:, 0], UV3[:, 2] - UV3[:, 0]], 2)  # (T, 2, 2)
    dPdu = (d @ np.linalg.inv(duv))[:, :, 0]
    dPdu[:, 2] = 0  # onto the centre's tangent plane (normal +z)
    dPdu /= np.linalg.norm(dPdu, axis=1, keepdims=True)
    np.testing.assert_allclose(t[0::3, :3], dPdu, atol=1e-5)
    assert (t[0::3, 3] == -1).all()  # z^2 keeps the orientation


def test_mirror_seam_splits_w():
    """u = |x|: w is opposite on the two sides of the seam, and the seam vertices (welded: same
    position, normal and uv) get one frame per side."""
    P, N, UV = mirrored()
    t = mikktspace_tangents(P, N, UV)
    assert_unit_orthogonal(t, N)
    cx = P.reshape(-1, 3, 3)[:, :, 0].mean(1).repeat(3)
    left, right = t[cx < 0, 3], t[cx > 0, 3]
    assert (left == left[0]).all() and (right == -left[0]).all()
    seam = np.flatnonzero(np.abs(P[:, 0]) < 1e-12)
    assert set(t[seam, 3].tolist()) == {-1.0, 1.0}
    assert (t[seam[cx[seam] < 0], 0] < -0.9).all() and (t[seam[cx[seam] > 0], 0] > 0.9).all()


@pytest.mark.parametrize("name", ["degenerate", "soup", "uv_sphere", "fan_z2"])
def test_unit_and_orthogonal(name):
    P, N, UV = CASES[name]()
    assert_unit_orthogonal(mikktspace_tangents(P, N, UV), N)


def test_degenerate_only_and_odd_normals():
    """No good triangle at all (the reference fails on such input), zero texcoords, a normal along
    x (the reference's default (1,0,0) is then parallel to it), unnormalised and zero normals."""
    P = np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0], [2, 2, 2], [2, 2, 2], [2, 2, 2]], np.float64)
    N = np.array([[1, 0, 0], [1, 0, 0], [1, 0, 0], [0, 3, 4], [0, 3, 4], [0, 3, 4]], np.float64)
    t = mikktspace_tangents(P, N, np.zeros((6, 2)))
    assert_unit_orthogonal(t, N)
    assert (t[:, 3] == 1).all()
    np.testing.assert_allclose(t[3:, :3], np.tile([1.0, 0.0, 0.0], (3, 1)))
    # zero-UV-area triangles only (every triangle "groups with anything"), and a zero normal
    P2, N2, UV2 = plane(3, 2)
    N2 = N2 * 2.5
    N2[0] = 0
    t2 = mikktspace_tangents(P2, N2, np.full_like(UV2, 0.5))
    assert np.isfinite(t2).all()
    np.testing.assert_allclose(np.linalg.norm(t2[:, :3], axis=1), 1.0, atol=1e-6)
    assert np.abs(t2[1:, 2]).max() < 1e-6


def test_float64_and_float32_input_agree():
    P, N, UV = noisy(6, 6)
    a = mikktspace_tangents(P, N, UV)
    b = mikktspace_tangents(P.astype(np.float32), N.astype(np.float32), UV.astype(np.float32))
    np.testing.assert_array_equal(a, b)


def test_empty_and_bad_input():
    assert mikktspace_tangents(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2))).shape == (0, 4)
    P, N, UV = plane(1, 1)
    for args, match in [
        ((P[:5], N[:5], UV[:5]), "3T rows"),
        ((P, N[:3], UV), "same number of rows"),
        ((P[:, :2], N, UV), "positions"),
        ((P, N, UV[:, :1]), "texcoords"),
        ((np.where(P == 1, np.nan, P), N, UV), "non-finite"),
        ((P * 1e39, N, UV), "non-finite"),
        ((P, N.astype(str), UV), "normals"),
    ]:
        with pytest.raises(InputError, match=match):
            mikktspace_tangents(*args)
    with pytest.raises(InputError, match="convention"):
        mikktspace_tangents(P, N, UV, convention="opengl")


# ---------------------------------------------------------------------------------------------
# the replayed sorts, against literal sequential versions of the reference's loops
# ---------------------------------------------------------------------------------------------
def _quicksort_edges_literal(buf, left, right, seed):
    """QuickSortEdges on one channel, as a plain recursive loop (the reference's algorithm)."""
    n = right - left + 1
    if n < 2:
        return
    if n == 2:
        if buf[left][0] > buf[right][0]:
            buf[left], buf[right] = buf[right], buf[left]
        return
    seed = mk._next_seed(seed)
    i_l, i_r = left, right
    pivot = buf[left + seed % n][0]
    while True:
        while buf[i_l][0] < pivot:
            i_l += 1
        while buf[i_r][0] > pivot:
            i_r -= 1
        if i_l <= i_r:
            buf[i_l], buf[i_r] = buf[i_r], buf[i_l]
            i_l += 1
            i_r -= 1
        if i_l > i_r:
            break
    if left < i_r:
        _quicksort_edges_literal(buf, left, i_r, seed)
    if i_l < right:
        _quicksort_edges_literal(buf, i_l, right, seed)


@pytest.mark.parametrize("seed", range(6))
def test_quicksort_tail_replay(seed):
    rng = np.random.default_rng(seed)
    keys = rng.integers(0, rng.integers(2, 60), rng.integers(3, 400))
    buf = [(int(k), i) for i, k in enumerate(keys)]
    _quicksort_edges_literal(buf, 0, len(buf) - 1, mk._SORT_SEED)
    assert [k for k, _ in buf] == sorted(keys.tolist())
    top = keys.max()
    np.testing.assert_array_equal(mk._quicksort_tail(keys), [i for k, i in buf if k == top])


def _merge_literal(P, key, tmp, left, right, rep):
    """MergeVertsFast as a plain recursive loop: halve the widest extent, Hoare partition, and in a
    run that cannot be split compare each vertex with the earlier ones."""
    pts = P[tmp[left:right + 1]]
    mn, mx = pts.min(0), pts.max(0)
    d = mx - mn
    ch = 1 if (d[1] > d[0] and d[1] > d[2]) else (2 if d[2] > d[0] else 0)
    sep = np.float32(0.5) * (mx[ch] + mn[ch])
    if sep >= mx[ch] or sep <= mn[ch]:
        for a in range(left, right + 1):
            for b in range(left, a):
                if key[tmp[a]] == key[tmp[b]]:
                    rep[tmp[a]] = rep[tmp[b]]
                    break
        return
    i_l, i_r = left, right
    while i_l < i_r:
        ready_l = ready_r = False
        while not ready_l and i_l < i_r:
            ready_l = not P[tmp[i_l], ch] < sep
            i_l += not ready_l
        while not ready_r and i_l < i_r:
            ready_r = P[tmp[i_r], ch] < sep
            i_r -= not ready_r
        if ready_l and ready_r:
            tmp[i_l], tmp[i_r] = tmp[i_r], tmp[i_l]
            i_l += 1
            i_r -= 1
    if i_l == i_r:
        if P[tmp[i_r], ch] < sep:
            i_l += 1
        else:
            i_r -= 1
    if left < i_r:
        _merge_literal(P, key, tmp, left, i_r, rep)
    if i_l < right:
        _merge_literal(P, key, tmp, i_l, right, rep)


@pytest.mark.parametrize("make", [soup, noisy, uv_sphere, degenerate])
def test_reference_vertex_ids_replay(make):
    P, N, UV = (np.asarray(a, np.float32) for a in make())
    vid = mk._weld(P, N, UV)
    key = [tuple(row) for row in np.concatenate([P, N, UV], 1).tolist()]
    # cells along the widest axis, as GenerateSharedVerticesIndexList makes them
    lo, hi = P.min(0), P.max(0)
    d = hi - lo
    ch = 1 if (d[1] > d[0] and d[1] > d[2]) else (2 if d[2] > d[0] else 0)
    with np.errstate(all="ignore"):
        f = np.float32(2048) * ((P[:, ch] - lo[ch]) / (hi[ch] - lo[ch]))
    cell = np.clip(np.trunc(np.nan_to_num(f)), 0, 2047).astype(int)
    rep = [4 * (c // 3) + c % 3 for c in range(len(P))]
    for c in np.unique(cell):
        tmp = np.flatnonzero(cell == c).tolist()
        if len(tmp) > 1:
            _merge_literal(P, key, tmp, 0, len(tmp) - 1, rep)
    np.testing.assert_array_equal(mk._reference_vertex_ids(P, vid)[vid], rep)
    # the weld itself: the same partition as exact equality of (position, normal, texcoord)
    _, expected = np.unique(np.asarray(key), axis=0, return_inverse=True)
    pairs = np.unique(np.stack([vid, expected.ravel()], 1), axis=0)
    assert len(pairs) == len(np.unique(vid)) == len(np.unique(expected))


def test_large_mesh_time():
    """A 40k-triangle sphere in well under a few seconds (100k triangles: ~0.5 s measured)."""
    P, N, UV = uv_sphere(200, 100)
    start = time.perf_counter()
    t = mikktspace_tangents(P, N, UV)
    seconds = time.perf_counter() - start
    print(f"{len(P) // 3} triangles: {seconds:.2f} s")
    assert_unit_orthogonal(t, N)
    assert seconds < 10
