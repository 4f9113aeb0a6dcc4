"""render_views against analytic truth: a sphere's silhouette and depth, linear colours."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest

from o3drbf.cameras.model import Camera
from o3drbf.synthetic.render import View, pixel_rays, render_views, save_images

RES = 60  # Open3D sphere resolution: latitude step pi / RES


@pytest.fixture(scope="module")
def sphere():
    return o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=RES)


@pytest.fixture(scope="module")
def camera():
    return Camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0], fov=40, width=120, height=90)


def _ray_sphere(rays, radius=1.0):
    """Exact depth (camera z, since directions have unit camera z) of the first hit on a sphere at the origin."""
    o, d = rays[:, :3], rays[:, 3:]
    a = (d * d).sum(1)
    b = 2 * (o * d).sum(1)
    c = (o * o).sum(1) - radius**2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore"):
        return np.where(disc >= 0, (-b - np.sqrt(disc)) / (2 * a), np.inf)


def test_sphere_silhouette_and_depth_match_the_analytic_sphere(sphere, camera):
    view = render_views(sphere, [camera])[0]
    assert isinstance(view, View) and view.image.shape == (90, 120, 3) and view.mask.shape == (90, 120)
    exact = _ray_sphere(pixel_rays(camera)).reshape(90, 120)
    # The mesh is inscribed in the sphere: its facets lie at most the sagitta inside.
    sagitta = 1.0 - math.cos(math.pi / RES)
    # Every pixel the mesh covers is inside the true silhouette ...
    assert not (view.mask & ~np.isfinite(exact)).any()
    # ... and the true silhouette loses only a thin rim to the facets: the disc of radius
    # f tan(asin(R / d)) shrinks by at most f * sagitta / sqrt(d^2 - R^2) pixels (+1 pixel rim).
    f, d = camera.K[0, 0], 4.0
    radius_px = f * math.tan(math.asin(1.0 / d))
    u, v = np.meshgrid(np.arange(120) + 0.5, np.arange(90) + 0.5)
    r = np.hypot(u - camera.K[0, 2], v - camera.K[1, 2])
    inner = r < radius_px - f * sagitta / math.sqrt(d * d - 1) - 1.0
    assert view.mask[inner].all()
    assert abs(view.mask.sum() - math.pi * radius_px**2) / (math.pi * radius_px**2) < 0.02
    # Depth: behind the true sphere by at most the sagitta (along a ray: sagitta / cos, capped).
    both = view.mask & np.isfinite(exact)
    gap = view.depth[both] - exact[both]
    assert gap.min() > -1e-5
    assert np.median(gap) < sagitta
    assert view.depth[45, 60] == pytest.approx(d - 1.0, abs=sagitta)
    assert np.isinf(view.depth[~view.mask]).all()


def test_pixels_show_the_colour_at_the_back_projected_point(sphere, camera):
    v = np.asarray(sphere.vertices)
    A = np.array([[0.3, -0.1, 0.05], [0.0, 0.2, -0.25], [0.1, 0.1, 0.3]])
    color = lambda x: 0.5 + x @ A.T  # noqa: E731  linear, inside [0, 1] on the unit ball
    view = render_views(sphere, [camera], vertex_colors=color(v), background=(0.2, 0.4, 0.6))[0]
    rays = pixel_rays(camera)
    m = view.mask.ravel()
    points = rays[m, :3] + rays[m, 3:] * view.depth.ravel()[m, None]
    # The hit points project back onto the pixel centres (u + 0.5, v + 0.5).
    u, w = np.meshgrid(np.arange(120) + 0.5, np.arange(90) + 0.5)
    pixels, _ = camera.project(points)
    np.testing.assert_allclose(pixels, np.column_stack([u.ravel()[m], w.ravel()[m]]), atol=1e-3)
    # Barycentric interpolation of a linear field is exact on every facet.
    np.testing.assert_allclose(view.image.reshape(-1, 3)[m], color(points), atol=1e-5)
    np.testing.assert_array_equal(view.image[~view.mask], np.broadcast_to([0.2, 0.4, 0.6], (int((~view.mask).sum()), 3)))


def test_nearer_surface_hides_the_farther_one(camera):
    near = o3d.geometry.TriangleMesh.create_box(0.5, 0.5, 0.1).translate((-0.25, -0.25, 1.0))
    far = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 0.1).translate((-1.0, -1.0, -0.5))
    both = near + far
    colors = np.vstack([np.tile([1.0, 0.0, 0.0], (len(near.vertices), 1)), np.tile([0.0, 0.0, 1.0], (len(far.vertices), 1))])
    view = render_views((np.asarray(both.vertices), np.asarray(both.triangles)), [camera], vertex_colors=colors)[0]
    # Box faces are planes: the depth is exact.  Centre pixel sees the near box's top face (z = 1.1).
    assert view.depth[45, 60] == pytest.approx(4.0 - 1.1, abs=1e-5)
    np.testing.assert_allclose(view.image[45, 60], [1, 0, 0])
    # Off the near box but on the far one (z = -0.4).
    f = camera.K[0, 0]
    u = int(60 + f * 0.6 / 4.4)
    assert view.depth[45, u] == pytest.approx(4.4, abs=1e-5)
    np.testing.assert_allclose(view.image[45, u], [0, 0, 1])


def test_mesh_colours_are_the_default_and_grey_without(sphere, camera):
    colored = o3d.geometry.TriangleMesh(sphere)
    colored.paint_uniform_color([0.1, 0.7, 0.3])
    img = render_views(colored, [camera])[0]
    np.testing.assert_allclose(img.image[img.mask], np.broadcast_to([0.1, 0.7, 0.3], (int(img.mask.sum()), 3)), atol=1e-6)
    grey = render_views(sphere, [camera])[0]
    np.testing.assert_allclose(grey.image[grey.mask], 0.5)


def test_save_images_round_trip(sphere, camera, tmp_path):
    view = render_views(sphere, [camera], vertex_colors=(np.asarray(sphere.vertices) + 1) / 2)[0]
    (path,) = save_images([view], tmp_path)
    back = np.asarray(o3d.io.read_image(str(path)))
    assert back.shape == (90, 120, 3) and back.dtype == np.uint8
    assert np.abs(back / 255.0 - view.image).max() <= 0.5 / 255 + 1e-9
    with pytest.raises(FileNotFoundError, match="output folder"):
        save_images([view], tmp_path / "missing")


def test_errors(sphere, camera):
    with pytest.raises(ValueError, match="pinhole"):
        render_views(sphere, [Camera.from_center([0, 0, 4])])
    with pytest.raises(ValueError, match="width/height"):
        render_views(sphere, [Camera(K=camera.K, R=camera.R, t=camera.t)])
    with pytest.raises(ValueError, match="one RGB row per vertex"):
        render_views(sphere, [camera], vertex_colors=np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        render_views(sphere, [camera], vertex_colors=np.full((len(sphere.vertices), 3), 2.0))
    with pytest.raises(ValueError, match="empty"):
        render_views(sphere, [])
