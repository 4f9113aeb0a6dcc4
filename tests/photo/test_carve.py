"""Voxel carving from photographs: against ray-cast photographs of a coloured sphere.

Truth: a unit sphere (signed distance |x| - 1) whose colour is a known smooth
function of the position, photographed (ray cast, no shading) by two rings of
six 160x120 cameras.
"""

import numpy as np
import pytest

from o3drbf.photo import carve as cv
from o3drbf.cameras.model import Camera
from o3drbf.synthetic.render import render_views
from o3drbf.synthetic.scans import camera_ring

RES = 32
BOX = np.array([[-1.25] * 3, [1.25] * 3])


def colour_of(p):
    """The sphere's true colour at (directions of) points p, in [0.2, 0.9]."""
    q = p / np.linalg.norm(p, axis=1, keepdims=True)
    return 0.55 + 0.35 * np.column_stack([np.sin(2 * q[:, 0]), np.sin(2 * q[:, 1] + 1), np.cos(2 * q[:, 2])])


@pytest.fixture(scope="module")
def photos():
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=60)
    v = np.asarray(mesh.vertices)
    mesh.vertex_colors = o3d.utility.Vector3dVector(colour_of(v))
    cams = camera_ring((0, 0, 0), 1.0, n_views=6, elevation=35, width=160, height=120, fov=50) + camera_ring(
        (0, 0, 0), 1.0, n_views=6, elevation=-35, width=160, height=120, fov=50, azimuth=30
    )
    views = render_views(mesh, cams)
    return mesh, cams, [w.image for w in views], [w.mask for w in views]


@pytest.fixture(scope="module")
def hull(photos):
    _, cams, images, _ = photos
    return cv.carve(images, cams, bounds=BOX, resolution=RES, photo_consistency=None)


def test_silhouettes_recover_the_rendered_masks(photos):
    _, _, images, masks = photos
    got = cv.silhouettes(images)
    for g, m in zip(got, masks):
        assert (g == m).mean() > 0.999


def test_silhouettes_threshold_background_and_specks():
    img = np.zeros((40, 50, 3))
    img[10:30, 5:25] = (0.8, 0.2, 0.2)
    img[2, 40] = 1.0  # a one-pixel speck
    img[20, 15] = 0.0  # a one-pixel hole
    m = cv.silhouettes([img], min_area=4)[0]
    want = np.zeros((40, 50), bool)
    want[10:30, 5:25] = True
    assert (m == want).all()
    raw = cv.silhouettes([img], min_area=0)[0]
    assert raw[2, 40] and not raw[20, 15]
    # a white background: the object is what differs from white
    white = np.ones((40, 50, 3))
    white[10:30, 5:25] = 0.3
    assert (cv.silhouettes([white], background=(1, 1, 1))[0] == want).all()


def test_shell_lies_on_the_sphere(hull):
    h = hull.voxel_size
    d = np.abs(np.linalg.norm(hull.points, axis=1) - 1.0)
    assert hull.stats["shell_voxels"] == len(hull.points) > 500
    assert d.max() < h, (d.max(), h)
    assert d.mean() < 0.3 * h, (d.mean(), h)
    # the occupied voxels are the sphere's (visual hull: a little more, never less)
    centres = hull.origin + h * np.argwhere(hull.occupancy)
    r = np.linalg.norm(centres, axis=1)
    assert r.max() < 1 + h
    ii = np.indices(hull.occupancy.shape).reshape(3, -1).T
    deep = np.linalg.norm(hull.origin + h * ii, axis=1) < 1 - h
    assert hull.occupancy.reshape(-1)[deep].all()


def test_shell_colours_match_the_truth(hull):
    seen = hull.visibility.any(axis=1)
    assert seen.mean() > 0.9
    err = np.abs(hull.colors[seen] - colour_of(hull.points[seen]))
    assert err.mean() < 0.03, err.mean()
    assert np.median(err) < 0.03


def test_visibility_follows_the_front_facing_cameras(hull, photos):
    _, cams, _, _ = photos
    p = hull.points
    n = p / np.linalg.norm(p, axis=1, keepdims=True)
    for c, cam in enumerate(cams):
        toward, _ = cam.toward(p)
        cos = np.einsum("ij,ij->i", n, toward)
        vis = hull.visibility[:, c]
        assert (cos[vis] > -0.3).all()  # nobody sees through the sphere
        facing = (cos > 0.4) & cam.in_image(p)
        assert vis[facing].mean() > 0.9, (c, vis[facing].mean())
        assert vis[cos < -0.3].sum() == 0
    assert (hull.best_camera() >= 0).mean() > 0.9


def test_seen_bounds_hold_the_object(photos):
    _, cams, _, masks = photos
    b = cv.seen_bounds(cams, masks)
    assert (b[0] < -0.99).all() and (b[1] > 0.99).all()
    assert (b[0] > -1.4).all() and (b[1] < 1.4).all()
    r = cv.carve(photos[2], cams, resolution=RES, photo_consistency=None)
    assert r.stats["bounds_from"] == "silhouettes"
    d = np.abs(np.linalg.norm(r.points, axis=1) - 1.0)
    assert d.mean() < 0.5 * r.voxel_size


def test_photo_consistency_carves_a_fat_hull(photos):
    """Dilated silhouettes make the hull too fat: the extra voxels see the
    black background in some cameras and the sphere in others, so
    photo-consistency removes them and the shell moves back onto the sphere."""
    from scipy import ndimage

    _, cams, images, masks = photos
    fat = [ndimage.binary_dilation(m, iterations=6) for m in masks]
    before = cv.carve(images, cams, bounds=BOX, resolution=RES, masks=fat, photo_consistency=None)
    after = cv.carve(images, cams, bounds=BOX, resolution=RES, masks=fat, photo_consistency=0.1, sweeps=8, keep_silhouettes=False)
    err_before = np.abs(np.linalg.norm(before.points, axis=1) - 1).mean()
    err_after = np.abs(np.linalg.norm(after.points, axis=1) - 1).mean()
    assert after.stats["photo_carved"] > 0
    assert err_after < 0.6 * err_before, (err_before, err_after)
    # it does not eat into the sphere
    ii = np.indices(after.occupancy.shape).reshape(3, -1).T
    inner = np.linalg.norm(after.origin + after.voxel_size * ii, axis=1) < 1 - 1.5 * after.voxel_size
    assert after.occupancy.reshape(-1)[inner].mean() > 0.99
    # on the true silhouettes the outline is protected: nothing true is carved
    kept = cv.carve(images, cams, bounds=BOX, resolution=RES, photo_consistency=0.1)
    assert kept.stats["photo_carved"] <= 0.01 * kept.stats["hull_voxels"]


def test_silhouette_iou_of_meshes(photos):
    import open3d as o3d

    mesh, cams, _, masks = photos
    iou = cv.silhouette_iou(mesh, cams, masks)
    assert iou.shape == (12,) and (iou > 0.995).all()
    small = o3d.geometry.TriangleMesh.create_sphere(radius=0.8, resolution=40)
    iou_small = cv.silhouette_iou(small, cams, masks)
    assert (iou_small < 0.75).all() and (iou_small > 0.5).all()  # about 0.8^2 in area
    assert np.allclose(cv.silhouette_iou(mesh, cams, masks, stride=2), iou, atol=0.01)


def test_box_masks_cover_the_projected_box(photos):
    _, cams, _, masks = photos
    for m, b in zip(masks, cv.box_masks(BOX, cams)):
        assert b[m].all()  # the sphere is inside the box
        assert b.sum() > m.sum()


def test_surface_voxels_of_a_cube():
    occ = np.zeros((6, 6, 6), bool)
    occ[1:5, 1:5, 1:5] = True
    s = cv.surface_voxels(occ)
    assert len(s) == 4**3 - 2**3
    off = cv.surface_offsets(occ, s)
    corner = np.flatnonzero((s == [1, 1, 1]).all(axis=1))[0]
    assert np.allclose(off[corner], -np.ones(3) / np.sqrt(3))


# -- errors ----------------------------------------------------------------------


def test_bad_inputs_raise_value_errors(photos):
    _, cams, images, masks = photos
    with pytest.raises(ValueError, match="count mismatch"):
        cv.carve(images[:3], cams, bounds=BOX, resolution=RES)
    with pytest.raises(ValueError, match="size mismatch"):
        cv.carve([im[:100] for im in images], cams, bounds=BOX, resolution=RES)
    black = [np.zeros_like(im) for im in images]
    with pytest.raises(ValueError, match="sees nothing"):
        cv.carve(black, cams, bounds=BOX, resolution=RES)
    for bad in (0, 1, 1.5, -0.1, "abc", float("nan")):
        with pytest.raises(ValueError, match="threshold"):
            cv.carve(images, cams, bounds=BOX, resolution=RES, threshold=bad)
    with pytest.raises(ValueError, match="background"):
        cv.silhouettes(images, background=(0, 0, 2))
    with pytest.raises(ValueError, match="bounds"):
        cv.carve(images, cams, bounds=[[0, 0, 0], [0, 1, 1]], resolution=RES)
    with pytest.raises(ValueError, match="resolution"):
        cv.carve(images, cams, bounds=BOX, resolution=4)
    with pytest.raises(ValueError, match="photo_consistency"):
        cv.carve(images, cams, bounds=BOX, resolution=RES, photo_consistency=2)
    with pytest.raises(ValueError, match="min_views"):
        cv.carve(images, cams, bounds=BOX, resolution=RES, min_views=1)
    with pytest.raises(ValueError, match="float pixel values"):
        cv.carve([im * 3 for im in images], cams, bounds=BOX, resolution=RES)
    with pytest.raises(ValueError, match="nothing in common|no voxel"):
        cv.carve(images, cams, bounds=[[5, 5, 5], [6, 6, 6]], resolution=RES)
    with pytest.raises(ValueError, match="pinhole"):
        cv.carve(images[:1], [Camera.from_center((0, 0, 5))], bounds=BOX, resolution=RES)


def test_read_images_checks_names_and_sizes(tmp_path, photos):
    import skimage.io

    _, cams, images, _ = photos
    for cam, im in zip(cams[:2], images[:2]):
        skimage.io.imsave(tmp_path / f"{cam.name}.png", (im * 255).astype(np.uint8), check_contrast=False)
    named = [Camera(K=c.K, R=c.R, t=c.t, name=f"{c.name}.png") for c in cams[:2]]
    got, filled = cv.read_images(tmp_path, named)
    assert len(got) == 2 and got[0].shape == (120, 160, 3)
    assert filled[0].width == 160 and filled[0].height == 120  # sizes taken from the files
    assert np.abs(got[0] - images[0]).max() <= 1 / 255 + 1e-6
    with pytest.raises(FileNotFoundError, match="not found.*missing.png"):
        cv.read_images(tmp_path, named + [Camera(K=cams[0].K, name="missing.png")])
    wrong = [Camera(K=c.K, R=c.R, t=c.t, width=320, height=240, name=f"{c.name}.png") for c in cams[:2]]
    with pytest.raises(ValueError, match="size mismatch"):
        cv.read_images(tmp_path, wrong)
    with pytest.raises(FileNotFoundError, match="image folder"):
        cv.read_images(tmp_path / "nope", named)
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="cannot read image"):
        cv.read_images(tmp_path, [Camera(K=cams[0].K, name="broken.png")])
