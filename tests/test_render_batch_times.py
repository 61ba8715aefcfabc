"""`render_batch` over the times of an animation (`times=`, `geometry=`): each image equals `render` of
the asset posed at its time (`posed_scene`), the meshes no animation moves are not batched, and bad
batched geometry is refused by name."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import jaxpbr as jp
from gltf_animated import skinned
from jaxpbr.io.gltf import read_gltf
from jaxpbr.rendering.gltf_scene import scene_from_asset
from jaxpbr.rendering.mesh import Mesh

KW = {"camera_position": (0.5, 1.4, 5.0), "camera_target": (0.5, 1.2, 0.0), "environment": "procedural:sky"}


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    return skinned(tmp_path_factory.mktemp("rig"))[0]


def _with_floor(gs):
    """The rig's scene with a static floor of 2 triangles added (a mesh no animation moves)."""
    floor = Mesh(positions=np.array([[-3, -0.05, 3], [3, -0.05, 3], [3, -0.05, -3], [-3, -0.05, -3]], np.float32),
                 triangles=np.array([[0, 1, 2], [0, 2, 3]], np.int32), material=jp.Material(base_color=(0.5, 0.5, 0.5)))
    return dataclasses.replace(gs, scene=gs.scene.replace(objects=tuple(gs.scene.objects) + (floor,)))


def test_render_batch_over_times_equals_render_of_each_pose(rig):
    gs = _with_floor(scene_from_asset(read_gltf(rig), width=32, height=24, **KW))
    times = np.array([0.0, 0.6, 1.4], np.float32)
    geometry = jp.posed_geometry(gs, times, animation=0)
    n_floor = len(gs.scene.objects) - 1
    assert str(n_floor) not in geometry and geometry  # the floor does not move: not batched
    imgs = np.asarray(jp.render_batch(gs, times=times, animation=0))
    assert imgs.shape == (3, 24, 32, 3) and np.isfinite(imgs).all()
    for k, t in enumerate(times):
        want = np.asarray(jp.render(jp.posed_scene(gs, float(t), animation=0)))
        np.testing.assert_allclose(imgs[k], want, rtol=1e-5, atol=1e-5 * want.max())
    assert np.abs(imgs[0] - imgs[2]).max() > 0.05
    # the same batch through `geometry=` on the plain scene
    again = np.asarray(jp.render_batch(gs.scene, geometry=geometry))
    np.testing.assert_array_equal(again, imgs)


def test_render_batch_geometry_refused_by_name(rig):
    gs = scene_from_asset(read_gltf(rig), width=16, height=12, **KW)
    mesh = gs.scene.objects[0]
    P = np.asarray(mesh.positions)[None]
    with pytest.raises(ValueError, match=r"geometry\[0\]\['positions'\] has shape"):
        jp.render_batch(gs.scene, geometry={0: {"positions": P[:, :-1]}})
    with pytest.raises(ValueError, match="not a mesh of the scene"):
        jp.render_batch(gs.scene, geometry={len(gs.scene.objects): {"positions": P}})
    with pytest.raises(ValueError, match="must be a dict of"):
        jp.render_batch(gs.scene, geometry={0: {"colours": P}})
    with pytest.raises(ValueError, match="same leading batch axis"):
        jp.render_batch(gs.scene, geometry={0: {"positions": P}}, env_intensity=np.ones(2, np.float32))
    with pytest.raises(ValueError, match="takes the GltfScene"):
        jp.render_batch(gs.scene, times=[0.0, 1.0])
    with pytest.raises(ValueError, match="animation needs times"):
        jp.render_batch(gs.scene, animation=0, env_intensity=np.ones(2, np.float32))
