"""The shared helpers that replaced duplicated or hand-written code (issue 13):
Camera.pixel_rays, quaternion_to_matrix (scipy), image sizes (Pillow),
validation.as_rgb, MultiOrder.series_coefficients, prep.sampling.mean_spacing
(sampled), bilinear sampling (scipy.ndimage) and RSS sampling (psutil)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from o3drbf.cameras.model import Camera, CameraSet, as_cameras, quaternion_to_matrix
from o3drbf.prep.sampling import mean_spacing
from o3drbf.rbf.kernels import MultiOrder
from o3drbf.validation import as_rgb


# -- cameras -------------------------------------------------------------------


def test_pixel_rays_of_an_axis_aligned_camera():
    """R = I, t = 0: the ray of pixel (u, v) is ((u + .5 - cx) / f, (v + .5 - cy) / f, 1) from the origin."""
    f, cx, cy = 50.0, 16.0, 12.0
    cam = Camera(K=np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]]), R=np.eye(3), t=np.zeros(3), width=32, height=24)
    rays = cam.pixel_rays()
    assert rays.shape == (24, 32, 6)
    np.testing.assert_array_equal(rays[..., :3], 0.0)
    v, u = 7, 19
    np.testing.assert_allclose(rays[v, u, 3:], [(u + 0.5 - cx) / f, (v + 0.5 - cy) / f, 1.0], rtol=1e-14)
    sub = cam.pixel_rays(stride=5)
    assert sub.shape == (5, 7, 6)
    np.testing.assert_allclose(sub, rays[::5, ::5], rtol=1e-14)
    unit = cam.pixel_rays(unit=True)
    np.testing.assert_allclose(np.linalg.norm(unit[..., 3:], axis=-1), 1.0, rtol=1e-14)
    np.testing.assert_allclose(unit[..., 3:] * rays[..., 5:], rays[..., 3:] * unit[..., 5:], atol=1e-15)  # same directions


def test_pixel_rays_project_back_to_their_pixel_centres():
    cam = Camera.look_at([2.0, -3.0, 1.5], [0.1, 0.2, -0.1], up=[0, 0, 1], fov=50, width=40, height=30)
    rays = cam.pixel_rays().reshape(-1, 6)
    np.testing.assert_allclose(rays[:, :3], np.broadcast_to(cam.center, (len(rays), 3)))
    depth = np.linspace(0.5, 4.0, len(rays))
    pixels, z = cam.project(rays[:, :3] + depth[:, None] * rays[:, 3:])
    vv, uu = np.mgrid[0:30, 0:40]
    np.testing.assert_allclose(pixels, np.column_stack([uu.ravel(), vv.ravel()]) + 0.5, atol=1e-9)
    np.testing.assert_allclose(z, depth, rtol=1e-12)  # camera-z 1 directions: the ray parameter is the depth
    with pytest.raises(ValueError, match="pinhole camera with width and height"):
        Camera.from_center([0, 0, 1]).pixel_rays()


def test_as_cameras_one_check_for_every_camera_list():
    pin = Camera.look_at([0, 0, 5.0], [0, 0, 0], up=[0, 1, 0], width=8, height=6, name="p")
    centre = Camera.from_center([1.0, 2, 3], name="c")
    unsized = Camera(K=pin.K, R=pin.R, t=pin.t)
    assert as_cameras(pin) == [pin]
    assert as_cameras(CameraSet([pin, centre])) == [pin, centre]
    assert as_cameras((pin, unsized), "images") == [pin, unsized]
    assert as_cameras([], allow_empty=True) == []
    for args, kwargs, message in [
        (([],), {}, "cameras is empty"),
        (([pin, "x"],), {}, "camera 1 is a str, not an o3drbf.cameras.model.Camera"),
        (([pin, centre], "images"), {}, r"camera 1 \(c\) is a 'center' sensor; images need pinhole cameras"),
        (([unsized], "images"), {"sized": True}, "camera 0 has no image size"),
    ]:
        with pytest.raises(ValueError, match=message):
            as_cameras(*args, **kwargs)


def test_quaternion_to_matrix_known_rotations():
    s = math.sqrt(0.5)
    np.testing.assert_allclose(quaternion_to_matrix(0, 0, s, s), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)  # 90 deg about z
    np.testing.assert_allclose(quaternion_to_matrix(1, 0, 0, 0), np.diag([1.0, -1, -1]), atol=1e-15)  # 180 deg about x
    np.testing.assert_allclose(quaternion_to_matrix(0, 0, 0, 7.0), np.eye(3), atol=1e-15)  # normalized first
    with pytest.raises(ValueError, match="not a finite non-zero quaternion"):
        quaternion_to_matrix(0, 0, 0, 0)


def test_image_sizes_come_from_the_file_header(tmp_path):
    from PIL import Image

    from o3drbf.cameras.model import load_cameras

    Image.new("RGB", (37, 21)).save(tmp_path / "a.png")
    Image.new("RGB", (45, 19)).save(tmp_path / "b.jpg")
    (tmp_path / "c.png").write_bytes(b"not an image")
    line = " 100 0 18 0 100 10 0 0 1 1 0 0 0 1 0 0 0 1 0 0 3\n"
    (tmp_path / "x_par.txt").write_text("4\n" + "".join(n + line for n in ("a.png", "b.jpg", "c.png", "missing.png")))
    cams = load_cameras(tmp_path / "x_par.txt")
    assert [(c.width, c.height) for c in cams] == [(37, 21), (45, 19), (None, None), (None, None)]


# -- images --------------------------------------------------------------------


def test_as_rgb_one_rule_for_every_dtype():
    u8 = np.array([[[0, 128, 255]]], np.uint8)
    np.testing.assert_allclose(as_rgb(u8), [[[0, 128 / 255, 1]]], rtol=1e-15)
    u16 = np.array([[[0, 65535, 13107]]], np.uint16)
    np.testing.assert_allclose(as_rgb(u16), [[[0, 1, 0.2]]], rtol=1e-15)
    grey = np.array([[0.25, 1.0]])
    out = as_rgb(grey, dtype=np.float32)
    assert out.shape == (1, 2, 3) and out.dtype == np.float32
    np.testing.assert_array_equal(out[0, :, 1], [0.25, 1.0])
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[..., 3] = 255
    assert as_rgb(rgba).shape == (2, 2, 3) and as_rgb(rgba).max() == 0
    assert as_rgb(np.full((1, 1, 3), 7, np.int64)).max() == pytest.approx(7 / np.iinfo(np.int64).max)
    for bad, message in [
        (np.full((2, 2, 3), 1.5), r"photo: float pixel values outside \[0, 1\]"),
        (np.full((2, 2, 3), np.nan), "NaN or infinite"),
        (np.zeros((2, 2, 3), bool), "dtype bool"),
        (np.full((2, 2, 3), -1, np.int16), "negative integer"),
        (np.zeros((2, 2, 5)), r"got shape \(2, 2, 5\)"),
        (np.zeros((0, 2, 3)), r"got shape \(0, 2, 3\)"),
    ]:
        with pytest.raises(ValueError, match=message):
            as_rgb(bad, "photo")


def test_bilinear_sampling_is_exact_on_a_linear_image():
    from o3drbf.mesh.color import _bilinear

    h, w = 6, 9
    rows, cols = np.mgrid[0:h, 0:w]
    img = np.stack([2.0 * (cols + 0.5) + 3.0 * (rows + 0.5), np.ones((h, w)), -(cols + 0.5)], axis=-1)  # linear in (u, v)
    rng = np.random.default_rng(4)
    inside = np.column_stack([rng.uniform(0.5, w - 0.5, 200), rng.uniform(0.5, h - 0.5, 200)])
    got = _bilinear(img, inside)
    np.testing.assert_allclose(got[:, 0], 2 * inside[:, 0] + 3 * inside[:, 1], rtol=1e-12)
    np.testing.assert_allclose(got[:, 2], -inside[:, 0], rtol=1e-12)
    outside = np.array([[-3.0, 2.5], [w + 4.0, h + 1.0]])  # the edge pixels extend
    np.testing.assert_allclose(_bilinear(img, outside)[:, 0], [2 * 0.5 + 3 * 2.5, 2 * (w - 0.5) + 3 * (h - 0.5)])


# -- kernels and spacing -------------------------------------------------------


@pytest.mark.parametrize("delta,tau", [(10.0, 0.01), (40.0, 0.01), (2.0, 0.3)])
def test_series_coefficients_are_a_a_n_plus_b_b_n(delta, tau):
    """D_n = A a^n + B b^n from the kernel's coefficients and decay rates (real regime)."""
    k = MultiOrder(delta, tau)
    (A, B), (a, b) = k.coefficients, k.decay_rates
    want = [(A * a**n + B * b**n).real for n in (1, 3, 4, 5)]
    np.testing.assert_allclose(k.series_coefficients(), want, rtol=1e-9)
    assert k.scale == pytest.approx(4 * math.pi * delta**2)
    r = np.array([1e-4 / abs(a)])
    d1, d3, d4, d5 = k.series_coefficients()
    series = (-d1 - d3 * r**2 / 6 + d4 * r**3 / 24 - d5 * r**4 / 120) / k.scale
    assert series[0] == pytest.approx(k.value_at_zero, rel=1e-7)  # and phi(0) is the closed form


def test_mean_spacing_exact_and_sampled():
    pts = np.random.default_rng(5).uniform(0, 1, (3000, 3))
    d = cKDTree(pts).query(pts, k=2)[0][:, 1]
    assert mean_spacing(pts) == pytest.approx(d.mean(), rel=1e-14)
    assert mean_spacing(pts, sample=5000) == pytest.approx(d.mean(), rel=1e-14)  # sample >= N: all points
    est = mean_spacing(pts, sample=500, seed=1)
    assert est == mean_spacing(pts, sample=500, seed=1, tree=cKDTree(pts))  # deterministic, tree reused
    assert est != pytest.approx(d.mean(), rel=1e-6) and est == pytest.approx(d.mean(), rel=0.1)
    with pytest.raises(ValueError, match="sample"):
        mean_spacing(pts, sample=0)


def test_rss_peak_sees_a_large_allocation():
    import mmap

    from o3drbf.evaluation.compare import _RssPeak

    # Fresh anonymous pages, written: np.ones could reuse heap memory that earlier tests freed but the
    # process still holds (two CI runs saw 4-8 kB of growth for a 100 MB block).
    with _RssPeak(interval=0.002) as peak:
        block = mmap.mmap(-1, 100 * 2**20)
        np.frombuffer(block, dtype=np.uint8)[:] = 1
        time.sleep(0.3)
        block.close()
    assert peak.peak_bytes is not None and peak.peak_bytes > 80 * 2**20