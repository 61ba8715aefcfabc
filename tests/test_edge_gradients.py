"""Derivatives with respect to where the outlines are (silhouettes, occlusion edges, horizons):
`jaxpbr.rendering.edges`, the analytic antialiasing of each sample pass.

The oracle is the gradient the antialiased image estimates: that of the pixel-area-integrated
image, taken here as central differences of a 16 x 16 supersampled render. The supersampled image
is piecewise linear in the parameter at the scale of a sample (its edges jump from sample to
sample), so the difference is taken over a step h of about a pixel, and compared with the mean of
the renderer's gradient over K points spread evenly across [-h, h] (by the mean value theorem,
the difference quotient is the mean of the true derivative over the step). What is left is the
antialiasing's own approximation (one edge per pair of samples, the neighbour's colour for the
far side: first order in the pixel size) and the reference's quantisation (1/16 of a pixel per
edge and row); measured per case in the slow tests' table below and bounded there."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpbr as jp
from jaxpbr.rendering import edges
from jaxpbr.rendering.demo import uv_sphere
from jaxpbr.rendering.mesh import Mesh

W, H = 40, 30
LIGHT = [jp.DirectionalLight(direction=(-0.3, -0.5, -1.0), color=(1, 1, 1), intensity=2.0)]
BG = (0.1, 0.2, 0.3)
RED = jp.Material(base_color=(0.8, 0.2, 0.1), roughness=0.5, emissive=(0.5, 0.5, 0.5))
GREEN = jp.Material(base_color=(0.1, 0.7, 0.2), roughness=0.4)
SP, SN, ST = uv_sphere(12, n_lon=24)


def camera(s=1, yaw=0.0, W=W, H=H):
    return jp.Camera(position=(0.0, 0.0, 4.0), target=(4.0 * jnp.sin(yaw), 0.0, 0.0), fov_y_deg=40.0, width=W, height=H,
                     supersample=s)


def triangle(x):
    v = jnp.array([[-0.8, -0.6, 0.0], [0.9, -0.3, 0.0], [0.1, 0.8, 0.0]], jnp.float64) + x
    return Mesh(positions=v, triangles=np.array([[0, 1, 2]]), material=RED)


def sphere_mesh(x, scale=1.0):
    return Mesh(positions=jnp.asarray(SP, jnp.float64) * 0.8 * scale + x, triangles=ST, normals=SN, material=GREEN)


def scene(objects, s=1, yaw=0.0):
    return jp.Scene(camera=camera(s, yaw), objects=objects, lights=LIGHT, background=BG)


#: name -> scene(p, s): the parameter p moves an outline.
CASES = {
    "triangle_x": lambda p, s: scene([triangle(jnp.array([p, 0.0, 0.0]))], s),
    "triangle_y": lambda p, s: scene([triangle(jnp.array([0.0, p, 0.0]))], s),
    "sphere_mesh_x": lambda p, s: scene([sphere_mesh(jnp.array([p, 0.1, 0.0]))], s),
    "sphere_mesh_scale": lambda p, s: scene([sphere_mesh(jnp.array([0.0, 0.1, 0.0]), 1.0 + p)], s),
    "occlusion": lambda p, s: scene([triangle(jnp.array([p, 0.0, 0.8])), sphere_mesh(jnp.array([0.3, 0.1, 0.0]))], s),
    "camera_yaw": lambda p, s: scene([sphere_mesh(jnp.array([0.0, 0.1, 0.0]))], s, yaw=p),
    "sphere_x": lambda p, s: scene([jp.Sphere(center=jnp.array([p, 0.1, 0.0]), radius=0.8, material=GREEN)], s),
    "sphere_over_plane": lambda p, s: scene([jp.Sphere(center=jnp.array([p, 0.1, 0.0]), radius=0.8, material=GREEN),
                                              jp.Plane(point=(0.0, -0.5, 0.0), normal=(0.0, 1.0, 0.3), material=RED)], s),
}


def render(sc, **kw):
    return jp.render(sc, dtype="float64", **kw)


def reference(sc):
    """The supersampled reference: the samples' mean alone (antialias="none": no edge stage)."""
    return render(sc, antialias="none")


def gradient_images(case, *, S=16, h=0.02, K=8, s=1):
    """(difference quotient of the S x S supersampled image over [-h, h], mean of the render's
    derivative (s x s samples) at K points across the same step), each (H, W, 3)."""
    make = CASES[case]
    fd = (reference(make(h, S)) - reference(make(-h, S))) / (2 * h)
    xs = ((np.arange(K) + 0.5) / K * 2 - 1) * h
    g = sum(jax.jvp(lambda p: render(make(p, s)), (jnp.float64(x),), (jnp.float64(1.0),))[1] for x in xs) / K
    return np.asarray(fd), np.asarray(g)


def compare(fd, g):
    """(relative L2 error of the gradient image, cosine similarity)."""
    l2 = float(np.linalg.norm(g - fd) / np.linalg.norm(fd))
    cos = float(np.sum(fd * g) / np.sqrt(np.sum(fd * fd) * np.sum(g * g)))
    return l2, cos


# ------------------------------------------------------------------------------------------
# Topology
# ------------------------------------------------------------------------------------------


def brute_neighbours(pos, tri):
    """Neighbour per edge by a double loop over the triangles' edges (welded by exact position)."""
    key = [tuple(np.round(p, 9)) for p in np.asarray(pos, np.float64)]
    out = np.full(tri.shape, -1)
    edges_of = {}
    for t, (a, b, c) in enumerate(tri):
        corners = (a, b, c)
        if len({key[a], key[b], key[c]}) < 3:
            continue
        for i in range(3):
            e = frozenset((key[corners[(i + 1) % 3]], key[corners[(i + 2) % 3]]))
            edges_of.setdefault(e, []).append((t, i))
    for users in edges_of.values():
        if len(users) == 2:
            (t0, i0), (t1, i1) = users
            out[t0, i0], out[t1, i1] = t1, t0
    return out


def test_neighbours_weld_seams_and_poles_of_a_uv_sphere():
    """A UV sphere (seam and pole vertices duplicated, pole triangles degenerate) is closed once
    welded: every edge of a non-degenerate triangle has one neighbour, as a brute-force search
    finds, and each neighbour names the triangle back."""
    pos, _, tri = uv_sphere(6, n_lon=12)
    nb = edges.edge_neighbours(pos, tri)
    want = brute_neighbours(pos, tri)
    np.testing.assert_array_equal(nb, want)
    live = want[:, 0] >= 0
    assert live.sum() > 0.8 * len(tri) and np.all(nb[live] >= 0)
    for t in np.flatnonzero(live):
        for i in range(3):
            assert t in nb[nb[t, i]]


def test_neighbours_of_an_open_quad_and_a_fan():
    """Two triangles of a quad share their diagonal, the four sides are boundaries; an edge shared
    by three triangles (a fan of three fins) has no neighbour."""
    quad = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    nb = edges.edge_neighbours(quad, np.array([[0, 1, 2], [0, 2, 3]]))
    np.testing.assert_array_equal(nb, [[-1, 1, -1], [-1, -1, 0]])
    fins = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, -1, 0]], np.float32)
    nb = edges.edge_neighbours(fins, np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]]))
    assert np.all(nb == -1)


# ------------------------------------------------------------------------------------------
# Closed forms and properties (default suite)
# ------------------------------------------------------------------------------------------


def closed_form_square(with_point_gradient: bool):
    """An unlit square (radiance c) over a background b, its left edge parallel to the image's
    columns, moved sideways by x: the point-sampled image's derivative at the edge is 0 (the edge
    crosses no sample), the antialiased image's is the colour step times the edge's speed on the
    image, (b - c) * ppu per row the edge crosses (ppu = H / (2 z tan(fov/2)) pixels per unit at the
    square's depth z), summed over the left half of the image."""
    c, b = np.array([0.9, 0.6, 0.3]), np.array([0.1, 0.2, 0.3])
    fov, z = 40.0, 4.0

    def img(x, **kw):
        v = jnp.array([[-0.6, -0.43, 0.0], [0.6, -0.43, 0.0], [0.6, 0.43, 0.0], [-0.6, 0.43, 0.0]], jnp.float64) + jnp.array([x, 0, 0])
        quad = Mesh(positions=v, triangles=np.array([[0, 1, 2], [0, 2, 3]]), unlit=True,
                    material=jp.Material(base_color=(0, 0, 0), emissive=tuple(c)))
        sc = jp.Scene(camera=jp.Camera(position=(0, 0, z), target=(0, 0, 0), fov_y_deg=fov, width=W, height=H),
                      objects=[quad], background=tuple(b))
        return render(sc, **kw)

    left = np.zeros((H, W, 3))
    left[:, : W // 2] = 1.0
    loss = lambda x, **kw: jnp.sum(img(x, **kw) * left)  # noqa: E731
    ppu = H / (2 * z * math.tan(math.radians(fov) / 2))
    # Rows whose sample (pixel centre) lies inside the square's height (0.86 units).
    y = (1 - 2 * (np.arange(H) + 0.5) / H) * math.tan(math.radians(fov) / 2) * z
    rows = np.count_nonzero(np.abs(y) < 0.43)
    g = float(jax.grad(loss)(0.013))
    np.testing.assert_allclose(g, rows * ppu * np.sum(b - c), rtol=1e-9)
    # The point samples see a step: the derivative of each is 0 at the edge (only two colours).
    base = np.asarray(img(0.013, antialias=False))
    assert {tuple(x) for x in np.unique(np.round(base.reshape(-1, 3), 12), axis=0).tolist()} <= {tuple(c), tuple(b)}
    if with_point_gradient:
        # antialias=False: the same derivative (the blend's, without its value)
        point = np.asarray(jax.jacfwd(lambda x: img(x, antialias=False))(0.013))
        np.testing.assert_allclose(float(jnp.sum(point * left)), g, rtol=1e-9)


def test_point_samples_have_no_edge_derivative_and_the_blend_gives_the_closed_form():
    closed_form_square(with_point_gradient=False)


@pytest.mark.slow
def test_without_the_blend_the_gradient_keeps_the_closed_form():
    closed_form_square(with_point_gradient=True)


def test_the_blend_moves_the_outline_pixels_towards_the_supersampled_image():
    """The forward image: the antialiased pass is closer to the 8 x 8 supersampled image than the
    point samples, on the pixels the outlines cross (a triangle; an analytic sphere over a plane):
    the mean absolute error at least halved (measured: to 0.11 and 0.22 of the point samples'; a
    sphere mesh 0.31)."""
    for case in ("triangle_x", "sphere_over_plane"):
        make = CASES[case]
        ref = np.asarray(reference(make(0.0, 8)))
        aa = np.asarray(render(make(0.0, 1)))
        point = np.asarray(render(make(0.0, 1), antialias=False))
        edge = np.abs(point - ref).sum(-1) > 1e-3
        e_aa, e_pt = np.abs(aa - ref)[edge].mean(), np.abs(point - ref)[edge].mean()
        assert e_aa < 0.5 * e_pt, (case, e_aa, e_pt)


@pytest.mark.slow
def test_render_batch_blends_each_image_as_render_does():
    cams = jp.Camera(position=np.array([[0.0, 0.0, 4.0], [0.5, 0.3, 4.0]]), target=(0.0, 0.0, 0.0), fov_y_deg=40.0,
                     width=24, height=18)
    sc = jp.Scene(camera=jp.Camera(position=(0.0, 0.0, 4.0), width=24, height=18, fov_y_deg=40.0),
                  objects=[sphere_mesh(jnp.array([0.0, 0.1, 0.0])), jp.Sphere(center=(0.9, -0.3, 0.5), radius=0.4, material=RED)],
                  lights=LIGHT, background=BG)
    batch = np.asarray(jp.render_batch(sc, cameras=cams))
    for k in range(2):
        one = np.asarray(jp.render(sc.replace(camera=sc.camera.replace(position=np.asarray(cams.position)[k]))))
        np.testing.assert_allclose(batch[k], one, atol=2e-6)
    point = np.asarray(jp.render(sc, antialias=False))
    assert np.abs(batch[0] - point).max() > 0.05  # (the outlines were blended)


def stiff_meshes(x):
    """Meshes where the edge maths is at its limits, side by side in one view: an edge through a
    column of pixel centres (x = 0), a degenerate triangle (two corners equal) and a sliver (1e-7
    high), a square whose sides run along rows and columns of samples, and a triangle with a
    corner behind the camera (z = 4)."""
    px = 2 * math.tan(math.radians(20.0)) * 4.0 / H  # one pixel at depth 0 (square pixels)
    return [
        Mesh(positions=jnp.array([[-1.0, -1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.2, 0.0]]) + x, triangles=np.array([[0, 1, 2]]),
             material=RED),
        Mesh(positions=jnp.array([[0.3, -1.0, 0.0], [1.2, -1.0, 0.0], [1.2, -1.0, 0.0], [0.3, -0.6, 0.0], [1.2, -0.6, 0.0],
                                  [0.7, -0.6 + 1e-7, 0.0]]) + x, triangles=np.array([[0, 1, 2], [3, 4, 5]]), material=GREEN),
        Mesh(positions=jnp.array([[1.0, 0.0, 0.0], [1.0 + 6 * px, 0.0, 0.0], [1.0 + 6 * px, 6 * px, 0.0], [1.0, 6 * px, 0.0]]) + x,
             triangles=np.array([[0, 1, 2], [0, 2, 3]]), material=RED),
        Mesh(positions=jnp.array([[-1.5, 0.4, 0.0], [-0.2, 0.6, 0.0], [-0.8, 0.9, 6.0]]) + x, triangles=np.array([[0, 1, 2]]),
             material=GREEN, double_sided=True),
    ]


def stiff_analytic(x):
    """The camera inside an analytic sphere (no contour in view), and a plane seen edge-on."""
    return [jp.Sphere(center=jnp.array([0.0, 0.0, 4.0]) + x, radius=2.0, material=GREEN),
            jp.Plane(point=jnp.array([0.0, 0.0, 0.0]) + x, normal=(0.0, 1.0, 0.0), material=RED)]


@pytest.mark.slow  # ~35 s each: the gradient of a staged render compiled for each scene and dtype
@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("objects", [stiff_meshes, stiff_analytic], ids=["meshes", "analytic"])
def test_edge_gradients_stay_finite_on_stiff_cases(objects, dtype):
    """Finite values and gradients (a translation of every vertex and analytic object, and the
    camera's yaw) where the edge maths is at its limits."""

    def loss(x, yaw):
        sc = jp.Scene(camera=camera(1, yaw), objects=objects(x), lights=LIGHT, background=BG)
        return jnp.sum(jp.render(sc, dtype=dtype))

    val, grads = jax.value_and_grad(loss, argnums=(0, 1))(jnp.zeros(3, dtype), jnp.asarray(0.0, dtype))
    assert np.isfinite(float(val))
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grads), grads
    assert float(jnp.abs(grads[0]).sum()) > 0  # (the outlines moved something)


# ------------------------------------------------------------------------------------------
# Against finite differences of supersampled images (slow)
# ------------------------------------------------------------------------------------------

#: Measured (40 x 30, S = 16, h = 0.02, K = 8, float64): relative L2 error of the gradient image /
#: cosine similarity. triangle_x 0.174 / 0.989, triangle_y 0.194 / 0.982, sphere_mesh_x 0.179 /
#: 0.993, sphere_mesh_scale 0.141 / 0.993, occlusion 0.176 / 0.989, camera_yaw 0.118 / 0.997,
#: sphere_x 0.175 / 0.993, sphere_over_plane 0.180 / 0.990. Bounds: 0.25 and 0.97 (the interior-only
#: gradient is at about 1, `test_without_the_edges_the_gradient_misses_the_silhouettes`).
L2_BOUND, COS_BOUND = 0.25, 0.97


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(CASES))
def test_edge_gradient_matches_finite_differences_of_the_supersampled_image(case):
    fd, g = gradient_images(case)
    l2, cos = compare(fd, g)
    assert l2 < L2_BOUND and cos > COS_BOUND, (case, l2, cos)


@pytest.mark.slow
def test_edge_gradient_error_shrinks_with_the_samples():
    """The difference from the supersampled image's gradient is the antialiasing's first-order
    approximation: with 2 x 2 samples per pixel (each blending over a cell half as wide) it is
    smaller (measured 0.176 -> 0.096)."""
    one = compare(*gradient_images("triangle_x", s=1))[0]
    two = compare(*gradient_images("triangle_x", s=2))[0]
    assert two < 0.7 * one, (one, two)


@pytest.mark.slow
def test_without_the_edges_the_gradient_misses_the_silhouettes():
    """The same comparison for the interior-only gradient (the point samples' own derivative), on
    the flat-shaded triangle whose image changes almost only where its edges move: the control that
    the bounds above can fail (the interior alone is as far from the reference as 0 is)."""
    make = CASES["triangle_x"]
    h, K = 0.02, 8
    fd = (render(make(h, 16)) - render(make(-h, 16))) / (2 * h)
    xs = ((np.arange(K) + 0.5) / K * 2 - 1) * h
    g = sum(jax.jvp(lambda p: render(make(p, 1)), (jnp.float64(x),), (jnp.float64(1.0),))[1] for x in xs) / K
    # The interior alone: the point samples' own derivative, a central difference over a step that
    # moves no outline across a sample.
    eps = 1e-7
    interior_only = (render(make(eps, 1), antialias=False) - render(make(-eps, 1), antialias=False)) / (2 * eps)
    l2_edges = compare(np.asarray(fd), np.asarray(g))[0]
    l2_interior = compare(np.asarray(fd), np.asarray(interior_only))[0]
    assert l2_edges < L2_BOUND < 0.9 < l2_interior, (l2_edges, l2_interior)
