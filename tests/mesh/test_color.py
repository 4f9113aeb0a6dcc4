"""Colour from photographs and from coloured points, against known colours."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest

from o3drbf.pipeline import reconstruct
from o3drbf.cameras.model import Camera
from o3drbf.mesh.color import (
    ColorResult,
    color_mesh,
    colors_from_images,
    colors_from_points,
    subdivide_for_images,
    vertex_normals,
)
from o3drbf.io.files import write_mesh
from o3drbf.synthetic.render import render_views
from o3drbf.synthetic.scans import camera_ring
from o3drbf.synthetic.shapes import Sphere, Torus

# A smooth colour field on the torus: c(x) = 0.5 + 0.35 (sin 3x, cos 3y, sin(3z + x)).
FREQ = 3.0


def _field(x):
    return 0.5 + 0.35 * np.column_stack([np.sin(FREQ * x[:, 0]), np.cos(FREQ * x[:, 1]), np.sin(FREQ * x[:, 2] + x[:, 0])])


def _field_gradient_norm(x):
    """|grad c| per channel, (N, 3)."""
    return 0.35 * np.column_stack(
        [
            FREQ * np.abs(np.cos(FREQ * x[:, 0])),
            FREQ * np.abs(np.sin(FREQ * x[:, 1])),
            np.abs(np.cos(FREQ * x[:, 2] + x[:, 0])) * math.hypot(FREQ, 1.0),
        ]
    )


def _nearest_on_torus(x, R=0.7, r=0.25):
    q = np.hypot(x[:, 0], x[:, 1])
    ring = np.column_stack([R * x[:, 0] / q, R * x[:, 1] / q, np.zeros(len(x))])
    d = x - ring
    return ring + r * d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def torus_photos():
    """Six photographs of a finely meshed torus painted with the known field, and a reconstruction."""
    truth = o3d.geometry.TriangleMesh.create_torus(0.7, 0.25, 120, 60)
    ring = dict(center=[0, 0, 0], radius=0.95, n_views=3, width=160, height=120)
    cameras = camera_ring(elevation=35, **ring) + camera_ring(elevation=-35, azimuth=60, **ring)
    views = render_views(truth, cameras, _field(np.asarray(truth.vertices)))
    points, normals = Torus().sample(2000, seed=1)
    mesh = reconstruct(points, normals, resolution=30, surface_count=None).mesh
    return mesh, cameras, [v.image for v in views]


def test_known_colours_are_recovered_on_a_reconstructed_torus(torus_photos, tmp_path):
    mesh, cameras, images = torus_photos
    res = colors_from_images(mesh, cameras, images)
    assert isinstance(res, ColorResult)
    x = np.asarray(mesh.vertices)
    assert res.colors.shape == (len(x), 3) and res.seen.all() and res.filled == 0 and res.unreached == 0
    y = _nearest_on_torus(x)
    err = np.abs(res.colors - _field(y))
    # Error budget per vertex and channel: the vertex is off the true surface by
    # g = |x - y|, so a camera up to 60 degrees off the normal sees the true surface
    # up to 2 g away from y (parallax); bilinear sampling adds up to a pixel
    # footprint p = distance / focal.  The colour changes by |grad c| per unit length.
    pixel = np.linalg.norm(cameras[0].center) / cameras[0].K[0, 0]
    budget = float((_field_gradient_norm(y) * (2 * np.linalg.norm(x - y, axis=1)[:, None] + pixel)).mean())
    assert err.mean() < budget, (err.mean(), budget)  # measured 0.0059 against 0.021
    assert np.all(res.views >= 1) and res.views.max() <= len(cameras)

    # Coloured PLY: write, read back, same colours to 8 bits.
    had_colors = mesh.has_vertex_colors()
    colored = color_mesh(mesh, cameras=cameras, images=images)
    assert mesh.has_vertex_colors() == had_colors and colored is not mesh  # the input is left alone
    np.testing.assert_allclose(np.asarray(colored.vertex_colors), res.colors)
    path = write_mesh(tmp_path / "colored.ply", colored)
    back = o3d.io.read_triangle_mesh(str(path))
    assert back.has_vertex_colors()
    np.testing.assert_allclose(np.asarray(back.vertex_colors), res.colors, atol=0.5 / 255 + 1e-9)


def _occlusion_scene():
    """A green unit sphere under a red plate; camera 0 looks straight down through the plate."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=40)
    plate = o3d.geometry.TriangleMesh.create_box(0.9, 0.9, 0.05).translate((-0.45, -0.45, 1.6))
    plate = plate.subdivide_midpoint(2)
    n_sphere = len(sphere.vertices)
    scene = sphere + plate
    colors = np.vstack([np.tile([0.0, 1.0, 0.0], (n_sphere, 1)), np.tile([1.0, 0.0, 0.0], (len(plate.vertices), 1))])
    top = Camera.look_at([0, 0, 5.0], [0, 0, 0], up=[0, 1, 0], fov=40, width=160, height=120, name="top")
    cameras = [top] + camera_ring([0, 0, 0], 1.2, n_views=5, elevation=30, width=160, height=120)
    return scene, n_sphere, colors, cameras


def test_occluded_vertices_take_no_colour_from_cameras_that_cannot_see_them():
    scene, n_sphere, colors, cameras = _occlusion_scene()
    images = [v.image for v in render_views(scene, cameras, colors)]
    v = np.asarray(scene.vertices)
    # Sphere vertices on the upper cap that the plate hides from the top camera:
    # the segment from the camera down to them crosses the plate's square.
    top = cameras[0].center
    s = (1.65 - top[2]) / (v[:, 2] - top[2])  # where the segment reaches the plate's top face
    cross = top[:2] + s[:, None] * (v[:, :2] - top[:2])
    hidden = (np.arange(len(v)) < n_sphere) & (v[:, 2] > 0.2) & (np.abs(cross) < 0.45).all(axis=1)
    assert hidden.sum() > 50
    res = colors_from_images(scene, cameras, images)
    naive = colors_from_images(scene, cameras, images, visibility=False)
    # The ring cameras see the hidden cap (green); the top camera would paint it red.
    assert res.seen[hidden].all()
    assert res.colors[hidden, 0].max() < 0.05, res.colors[hidden, 0].max()
    # Without visibility the same check fails: every hidden vertex is at least 10% red
    # (measured 0.20 to 0.37: the top camera's head-on weight 1 against the ring's grazing ones).
    assert naive.colors[hidden, 0].min() > 0.1
    # and visibility counted one camera fewer for them
    assert (naive.views[hidden] > res.views[hidden]).all()
    # The plate's top (facing the top camera) is red.
    plate_top = (np.arange(len(v)) >= n_sphere) & (v[:, 2] > 1.64)
    assert res.colors[plate_top, 0].min() > 0.95


def test_weights_follow_the_cosine_formula_exactly():
    # A flat square facing +z, seen head-on by one camera (all red) and at 75 degrees by another (all blue).
    verts = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [0, 0, 0]], dtype=float) * 0.2
    tris = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    head = Camera.look_at([0, 0, 3.0], [0, 0, 0], up=[0, 1, 0], fov=30, width=64, height=48)
    angle = math.radians(75)
    grazing = Camera.look_at([3 * math.sin(angle), 0, 3 * math.cos(angle)], [0, 0, 0], up=[0, 0, 1], fov=30, width=64, height=48)
    red = np.zeros((48, 64, 3), dtype=np.uint8)
    red[..., 0] = 255
    blue = np.zeros((48, 64, 3))
    blue[..., 2] = 1.0
    res = colors_from_images((verts, tris), [head, grazing], [red, blue])
    w_head = np.einsum("ij,j->i", head.center - verts, [0, 0, 1]) / np.linalg.norm(head.center - verts, axis=1)
    w_graze = np.einsum("ij,j->i", grazing.center - verts, [0, 0, 1]) / np.linalg.norm(grazing.center - verts, axis=1)
    expected = np.column_stack([w_head, np.zeros(5), w_graze]) / (w_head + w_graze)[:, None]
    np.testing.assert_allclose(res.colors, expected, atol=1e-12)
    np.testing.assert_allclose(res.weight, w_head + w_graze, atol=1e-12)
    assert res.colors[4, 0] == pytest.approx(1 / (1 + math.cos(angle)))  # mostly the head-on colour
    assert (res.views == 2).all()
    # min_cosine drops the grazing view.
    only = colors_from_images((verts, tris), [head, grazing], [red, blue], min_cosine=0.5)
    np.testing.assert_allclose(only.colors, np.tile([1.0, 0, 0], (5, 1)))
    assert (only.views == 1).all()


def test_unseen_vertices_take_their_neighbours_colours():
    verts = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [0, 0, 0]], dtype=float) * 0.2
    tris = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    # A narrow camera sees only the centre vertex.
    cam = Camera.look_at([0, 0, 3.0], [0, 0, 0], up=[0, 1, 0], fov=2, width=8, height=8)
    img = np.full((8, 8, 3), [0.2, 0.4, 0.6])
    res = colors_from_images((verts, tris), [cam], [img])
    assert res.seen.tolist() == [False, False, False, False, True]
    assert res.filled == 4 and res.unreached == 0
    np.testing.assert_allclose(res.colors, np.tile([0.2, 0.4, 0.6], (5, 1)))
    grey = colors_from_images((verts, tris), [cam], [img], fill="grey")
    np.testing.assert_allclose(grey.colors[:4], 0.5)
    assert grey.filled == 0 and grey.unreached == 4
    # A second square far off to the side, in no image and joined to nothing seen: left grey.
    two = (np.vstack([verts, verts + [5.0, 0, 0]]), np.vstack([tris, tris + 5]))
    res = colors_from_images(two, [cam], [img])
    assert res.filled == 4 and res.unreached == 5
    np.testing.assert_allclose(res.colors[5:], 0.5)
    np.testing.assert_allclose(res.colors[:5], np.tile([0.2, 0.4, 0.6], (5, 1)))


def test_vertex_normals_are_outward_on_closed_meshes_whatever_the_winding():
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=12)
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    for tris in (t, t[:, ::-1]):
        n = vertex_normals(v, tris)
        assert np.einsum("ij,ij->i", n, v).min() > 0.95
    # An open mesh follows its winding.
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    np.testing.assert_allclose(vertex_normals(square, np.array([[0, 1, 2], [0, 2, 3]])), np.tile([0, 0, 1.0], (4, 1)))
    np.testing.assert_allclose(vertex_normals(square, np.array([[0, 2, 1], [0, 3, 2]])), np.tile([0, 0, -1.0], (4, 1)))


def test_colors_from_points_recovers_a_linear_field():
    A = np.array([[0.2, -0.1, 0.1], [0.05, 0.25, -0.1], [-0.15, 0.1, 0.2]])
    field = lambda x: 0.5 + x @ A.T  # noqa: E731
    points, _ = Sphere().sample(4000, seed=3)
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=30)
    v = np.asarray(mesh.vertices)
    got = colors_from_points(v, points, field(points), k=8)
    err = np.abs(got - field(v)).mean()
    # A weighted mean of neighbours within distance h of a linear field is off by at most
    # |grad| h; with 4000 points on the unit sphere the 8th neighbour is h ~ sqrt(8 / (pi 4000 / 4 pi)) = 0.09.
    gradient = np.linalg.norm(A, axis=1).max()
    assert err < 0.5 * gradient * 0.09, err  # measured 0.002 (averaging cancels most of the bias)
    # A vertex on a point takes that point's colour; uint8 colours are scaled.
    np.testing.assert_allclose(colors_from_points(points[:3], points, field(points)), field(points[:3]))
    c8 = np.round(field(points) * 255).astype(np.uint8)
    np.testing.assert_allclose(colors_from_points(points[:3], points, c8), c8[:3] / 255.0)
    colored = color_mesh(mesh, points=points, colors=field(points))
    np.testing.assert_allclose(np.asarray(colored.vertex_colors), got)


def test_subdivide_brings_edges_to_about_a_pixel():
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=10)
    cam = Camera.look_at([0, 0, 4.0], [0, 0, 0], up=[0, 1, 0], fov=40, width=160, height=120)

    def median_edge(m):
        v, t = np.asarray(m.vertices), np.asarray(m.triangles)
        e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        pix, _ = cam.project(v)
        return float(np.median(np.linalg.norm(pix[e[:, 0]] - pix[e[:, 1]], axis=1)))

    before = median_edge(mesh)
    fine = subdivide_for_images(mesh, [cam], pixels_per_edge=2.0)
    after = median_edge(fine)
    rounds = round(math.log(len(fine.triangles) / len(mesh.triangles), 4))
    assert rounds == math.ceil(math.log2(before / 2.0)) and rounds >= 2
    assert 0.9 < after <= 2.0 * 1.05  # halved just enough times
    capped = subdivide_for_images(mesh, [cam], pixels_per_edge=0.1, max_triangles=len(mesh.triangles) * 16)
    assert len(capped.triangles) == len(mesh.triangles) * 16


def test_errors():
    verts = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=float)
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    cam = Camera.look_at([0, 0, 5.0], [0, 0, 0], up=[0, 1, 0], fov=60, width=32, height=24)
    img = np.zeros((24, 32, 3))
    mesh = (verts, tris)
    with pytest.raises(ValueError, match="2 camera.*1 image"):
        colors_from_images(mesh, [cam, cam], [img])
    with pytest.raises(ValueError, match="image 0 is 31x24.*expects 32x24"):
        colors_from_images(mesh, [cam], [img[:, :31]])
    with pytest.raises(ValueError, match="pinhole"):
        colors_from_images(mesh, [Camera.from_center([0, 0, 5])], [img])
    away = Camera.look_at([0, 0, 5.0], [0, 0, 10], up=[0, 1, 0], fov=60, width=32, height=24)
    with pytest.raises(ValueError, match="cameras see nothing"):
        colors_from_images(mesh, [away], [img])
    with pytest.raises(ValueError, match="outside \\[0, 1\\]"):
        colors_from_images(mesh, [cam], [img + 2])
    with pytest.raises(ValueError, match="nothing to colour from"):
        color_mesh(mesh)
    with pytest.raises(ValueError, match="both cameras and images"):
        color_mesh(mesh, cameras=[cam])
    with pytest.raises(ValueError, match="one RGB row per point"):
        colors_from_points(verts, verts, np.zeros((3, 3)))
