"""Free-space consistency check and point confidence (o3drbf.constraints.freespace)."""

import numpy as np
import pytest

from o3drbf.cameras.model import Camera
from o3drbf.constraints.freespace import free_space_check, point_confidence, seen_by
from o3drbf.synthetic.scans import range_scans


@pytest.fixture(scope="module")
def torus_mesh():
    import open3d as o3d

    return o3d.geometry.TriangleMesh.create_torus(torus_radius=0.7, tube_radius=0.25, radial_resolution=80, tubular_resolution=40)


@pytest.fixture(scope="module")
def scans(torus_mesh):
    """A clean 3-view scan and the same scan with 2% spurious returns in the cameras' free space (last rows)."""
    clean, owner, cams = range_scans(torus_mesh, n_views=3, seed=0)
    dirty, owner2, cams2 = range_scans(torus_mesh, n_views=3, outliers=0.02, seed=0)
    truth = np.zeros(len(dirty), dtype=bool)
    truth[len(clean):] = True
    return clean, owner, cams, dirty, owner2, truth


def test_clean_scan_keeps_genuine_points(scans):
    clean, owner, cams, *_ = scans
    check = free_space_check(clean, cams, owner)
    assert check.outlier.mean() < 0.005
    assert check.cameras_used == 3
    # Every point is confirmed by its own camera.
    assert (check.confirmations >= 1).all()


def test_catches_free_space_returns(scans):
    *_, dirty, owner, truth = scans
    check = free_space_check(dirty, scans[2], owner)
    assert check.outlier[truth].mean() >= 0.9
    assert check.outlier[~truth].mean() < 0.005
    assert f"{check.removed} of {len(dirty)}" in check.reason


def test_noisy_scan_with_noise_tolerance(torus_mesh):
    sigma = 0.02  # 1% of the diagonal
    clean, _, _ = range_scans(torus_mesh, n_views=3, noise=sigma, seed=1)
    dirty, owner, cams = range_scans(torus_mesh, n_views=3, noise=sigma, outliers=0.02, seed=1)
    truth = np.arange(len(dirty)) >= len(clean)
    check = free_space_check(dirty, cams, owner, noise=sigma)
    assert check.tolerance == pytest.approx(3 * sigma)
    assert check.outlier[truth].mean() >= 0.9
    assert check.outlier[~truth].mean() < 0.005


def test_single_point_in_front_of_a_wall():
    """Independent truth: a camera looking at a plane z = 0 from z = 2; a point at z = 1 on the axis is in free space."""
    cam = Camera.look_at((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=60.0, width=64, height=64)
    g = np.linspace(-0.5, 0.5, 41)
    wall = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    wall = np.hstack([wall, np.zeros((len(wall), 1))])
    probes = np.array([[0.0, 0.0, 1.0], [0.1, -0.1, 0.5], [0.0, 0.0, -0.5], [0.05, 0.05, 0.001]])
    pts = np.vstack([wall, probes])
    owner = np.concatenate([np.zeros(len(wall), int), [-1, -1, -1, -1]])
    check = free_space_check(pts, [cam], owner, tolerance=0.05)
    assert check.outlier[-4:].tolist() == [True, True, False, False]  # in front / in front / behind / on the wall
    assert check.conflicts[-4:].tolist() == [1, 1, 0, 0]
    assert check.confirmations[-4:].tolist() == [0, 0, 0, 1]
    assert not check.outlier[: len(wall)].any()
    # A second camera that confirms the probe saves it (confirmations <= 1 rule).
    cam2 = Camera.look_at((2.0, 0.0, 1.0), (0.0, 0.0, 1.0), up=(0.0, 0.0, 1.0), fov=30.0, width=32, height=32)
    owner2 = owner.copy()
    owner2[len(wall)] = 1
    both = free_space_check(np.vstack([pts, pts[len(wall)] + [0.0, 0.0, 0.002]]), [cam, cam2],
                            np.concatenate([owner2, [0]]), tolerance=0.05)
    assert both.confirmations[len(wall)] == 2 and not both.outlier[len(wall)]


def test_without_point_camera_first_layer(scans):
    *_, dirty, owner, truth = scans
    check = free_space_check(dirty, scans[2])
    assert check.parameters["source"] == "first supported layer"
    assert check.outlier[~truth].mean() < 0.005
    assert check.outlier[truth].mean() >= 0.9


def test_bad_input():
    cam = Camera.look_at((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    pts = np.random.default_rng(0).normal(size=(20, 3))
    with pytest.raises(ValueError, match="cameras is empty"):
        free_space_check(pts, [], None)
    with pytest.raises(ValueError, match="point_camera"):
        free_space_check(pts, [cam], np.full(20, 3))
    with pytest.raises(ValueError, match="empty must be one of"):
        free_space_check(pts, [cam], np.zeros(20, int), empty="maybe")
    with pytest.raises(ValueError, match="tolerance"):
        free_space_check(pts, [cam], np.zeros(20, int), tolerance=-1.0)
    with pytest.raises(ValueError, match="no camera can hold"):  # cameras that saw nothing
        free_space_check(pts, [Camera.from_center((0, 0, 5))], np.full(20, -1))
    # a centre sensor holds a spherical z-buffer: a point in front of what it saw is in its free space
    seen = np.vstack([pts, [[0.0, 0.0, 2.0]]])
    check = free_space_check(seen, [Camera.from_center((0, 0, 5))], np.r_[np.zeros(20, int), -1], tolerance=0.1)
    assert check.cameras_used == 1
    assert seen_by(np.array([0, -1, 1]), 3, 2).tolist() == [[True, False], [False, False], [False, True]]


def test_point_confidence_values():
    conf = point_confidence(np.array([0, 1, 2, 5]))
    np.testing.assert_allclose(conf, [1 / 3, 2 / 3, 1.0, 1.0])
    # Grazing factor: a camera on +z; normals at 0, 60 and 90 degrees to the ray.
    cam = Camera.from_direction((0.0, 0.0, -1.0))
    pts = np.zeros((3, 3))
    nrm = np.array([[0.0, 0.0, 1.0], [np.sin(np.pi / 3), 0.0, np.cos(np.pi / 3)], [1.0, 0.0, 0.0]])
    conf = point_confidence(np.array([2, 2, 2]), pts, nrm, [cam], np.zeros(3, int), min_cos=0.2)
    np.testing.assert_allclose(conf, [1.0, 0.5, 0.2])
    assert (point_confidence(np.zeros(3, int), pts, nrm, [cam], np.zeros(3, int)) >= 0.1).all()
    with pytest.raises(ValueError, match="all four"):
        point_confidence(np.zeros(3, int), pts)


def test_neighbourhood_minimum_is_scipys_minimum_filter():
    """The z-buffer's 3 x 3 minimum (empty cells -inf, or +inf when ignored; the same value beyond the
    edges) is scipy.ndimage.minimum_filter's, value for value, on images of one row or column too."""
    from scipy import ndimage

    from o3drbf.constraints.freespace import _neighbourhood_min

    rng = np.random.default_rng(0)
    for shape in [(1, 1), (1, 6), (5, 1), (7, 3), (40, 55)]:
        image = rng.standard_normal(shape)
        image[rng.random(shape) < 0.3] = -np.inf
        for outside, im in [(-np.inf, image), (np.inf, np.where(np.isfinite(image), image, np.inf))]:
            assert np.array_equal(_neighbourhood_min(im, outside), ndimage.minimum_filter(im, size=3, mode="constant", cval=outside))
