"""``o3drbf photos``: photographs -> carved shell -> closed coloured mesh.

Truth: ray-cast photographs of a unit sphere with a known colour pattern
(see tests/photo/test_carve.py); on the shared data, the Middlebury temple's
silhouettes.
"""

import numpy as np
import pytest

from o3drbf.cli.commands import main
from o3drbf.mesh.metrics import chamfer
from o3drbf.photo.pipeline import readme_bounds, run_photos

from test_carve import BOX, colour_of, photos  # noqa: F401  (fixture)

FAST = dict(voxels=32, surface_count=600, resolution=40)


@pytest.fixture(scope="module")
def result(photos):  # noqa: F811
    _, cams, images, _ = photos
    return run_photos(None, images=images, cameras=cams, bounds=BOX, **FAST)


def test_synthetic_photographs_give_the_coloured_sphere(result, photos):  # noqa: F811
    mesh_true = photos[0]
    r = result
    h = r.carve.voxel_size
    assert r.stats["watertight"] and r.stats["components"] == 1
    assert (r.iou > 0.9).all(), r.iou
    assert (r.iou_raw > 0.9).all()
    v = np.asarray(r.mesh.vertices)
    radial = np.linalg.norm(v, axis=1) - 1.0
    assert np.abs(radial).max() < 1.5 * h, (np.abs(radial).max(), h)
    ch = chamfer(r.mesh, mesh_true, n_samples=20000)
    assert ch["l1"] < 0.3 * h, (ch, h)
    assert ch["hausdorff"] < 1.5 * h, (ch, h)
    # colours against the known pattern at each vertex's direction
    err = np.abs(np.asarray(r.mesh.vertex_colors) - colour_of(v))
    assert err.mean() < 0.03, err.mean()
    assert np.percentile(err, 95) < 0.1


def test_stats_per_stage(result):
    s = result.stats
    for key in ("read_seconds", "reconstruct_seconds", "color_seconds", "iou_seconds", "triangles", "watertight"):
        assert key in s
    c = s["carve"]
    assert c["voxels"] == c["silhouette_carved"] + c["hull_voxels"]
    assert c["shell_voxels"] == len(result.carve.points)
    assert s["reconstruct"]["surface_constraints"] > 0 and s["reconstruct"]["exterior_constraints"] > 0


def _write_middlebury(folder, cams, images):
    import skimage.io

    lines = [str(len(cams))]
    for i, (cam, im) in enumerate(zip(cams, images)):
        name = f"img{i:02d}.png"
        skimage.io.imsave(folder / name, (np.clip(im, 0, 1) * 255).round().astype(np.uint8), check_contrast=False)
        vals = np.concatenate([cam.K.ravel(), cam.R.ravel(), cam.t])
        lines.append(name + " " + " ".join(f"{x:.17g}" for x in vals))
    par = folder / "test_par.txt"
    par.write_text("\n".join(lines) + "\n")
    return par


def test_cli_writes_coloured_mesh_and_picture(tmp_path, photos, capsys):  # noqa: F811
    import open3d as o3d
    import skimage.io

    _, cams, images, _ = photos
    par = _write_middlebury(tmp_path, cams, images)
    (tmp_path / "README.txt").write_text("The bounding box is\n(-1.25 -1.25 -1.25)\n(1.25 1.25 1.25)\n")
    out = tmp_path / "model.ply"
    pic = tmp_path / "fig.png"
    code = main(["photos", str(tmp_path), "--calibration", str(par), "-o", str(out), "--voxels", "32",
                 "--surface-count", "600", "--resolution", "40", "--picture", str(pic), "--picture-camera", "img03.png"])
    assert code == 0
    text = capsys.readouterr().out
    for key in ("box from README", "carved by silhouettes", "surface voxels", "constraints", "triangles", "watertight yes", "IoU per image"):
        assert key in text, key
    mesh = o3d.io.read_triangle_mesh(str(out))
    assert mesh.has_vertex_colors() and len(mesh.triangles) > 1000
    img = skimage.io.imread(pic)
    assert img.shape[:2] == (120, 2 * 160 + 8)
    # the rendered model sits where the photo shows the sphere (camera pose honoured)
    photo_mask = img[:, :160].max(axis=2) > 30
    render_mask = img[:, 168:].max(axis=2) > 30
    iou = (photo_mask & render_mask).sum() / (photo_mask | render_mask).sum()
    assert iou > 0.85, iou


def test_colmap_model_with_an_images_folder(tmp_path, photos):  # noqa: F811
    """A COLMAP text model (sparse/0) whose images sit in images/: the same result as in memory."""
    import skimage.io
    from scipy.spatial.transform import Rotation

    _, cams, images, _ = photos
    (tmp_path / "images").mkdir()
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    cam_lines, img_lines = [], []
    for i, (cam, im) in enumerate(zip(cams, images)):
        name = f"frame_{i}.png"
        skimage.io.imsave(tmp_path / "images" / name, (im * 255).round().astype(np.uint8), check_contrast=False)
        K = cam.K
        cam_lines.append(f"{i + 1} PINHOLE {cam.width} {cam.height} {K[0, 0]:.17g} {K[1, 1]:.17g} {K[0, 2]:.17g} {K[1, 2]:.17g}")
        qx, qy, qz, qw = Rotation.from_matrix(cam.R).as_quat()
        img_lines += [f"{i + 1} {qw:.17g} {qx:.17g} {qy:.17g} {qz:.17g} {cam.t[0]:.17g} {cam.t[1]:.17g} {cam.t[2]:.17g} {i + 1} {name}", ""]
    (model / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (model / "images.txt").write_text("\n".join(img_lines) + "\n")
    (model / "points3D.txt").write_text("")
    r = run_photos(tmp_path, bounds=BOX, **FAST)
    assert [c.name for c in r.cameras] == [f"frame_{i}.png" for i in range(len(cams))]
    assert (r.iou > 0.9).all()
    assert np.allclose(r.cameras[3].center, cams[3].center, atol=1e-9)


def test_bundler_file_kept_apart_from_its_images(tmp_path, photos):  # noqa: F811
    """bundle.out + list.txt in one folder, the images in another: the
    principal point (Bundler: the image centre) comes from the images."""
    import skimage.io

    _, cams, images, _ = photos
    cal, imgs = tmp_path / "cal", tmp_path / "imgs"
    cal.mkdir()
    imgs.mkdir()
    flip = np.diag([1.0, -1.0, -1.0])
    lines = ["# Bundle file v0.3", f"{len(cams)} 0"]
    for i, (cam, im) in enumerate(zip(cams, images)):
        skimage.io.imsave(imgs / f"v{i}.png", (im * 255).round().astype(np.uint8), check_contrast=False)
        lines.append(f"{cam.K[0, 0]:.17g} 0 0")
        lines += [" ".join(f"{x:.17g}" for x in row) for row in flip @ cam.R]
        lines.append(" ".join(f"{x:.17g}" for x in flip @ cam.t))
    (cal / "bundle.out").write_text("\n".join(lines) + "\n")
    (cal / "list.txt").write_text("".join(f"v{i}.png\n" for i in range(len(cams))))
    r = run_photos(imgs, cal / "bundle.out", bounds=BOX, **FAST)
    assert np.allclose(r.cameras[0].K, cams[0].K)
    assert (r.iou > 0.9).all()


def test_cli_errors_exit_2(tmp_path, photos, capsys):  # noqa: F811
    _, cams, images, _ = photos
    par = _write_middlebury(tmp_path, cams[:3], images[:3])
    out = str(tmp_path / "m.ply")
    assert main(["photos", str(tmp_path / "nope"), "--calibration", str(par), "-o", out]) == 2
    assert "image folder not found" in capsys.readouterr().err
    (tmp_path / "img01.png").unlink()
    assert main(["photos", str(tmp_path), "--calibration", str(par), "-o", out]) == 2
    assert "img01.png" in capsys.readouterr().err
    assert main(["photos", str(tmp_path), "--calibration", str(tmp_path / "none_par.txt"), "-o", out]) == 2
    assert "calibration not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["photos", str(tmp_path), "--bounds", "1 2 3", "-o", out])


def test_readme_bounds(tmp_path):
    assert readme_bounds(tmp_path) is None
    (tmp_path / "README.txt").write_text("The (tight) bounding box for the model is\n(-0.07 0.02 -0.01)\n(0.03, 0.18, 0.06)\n")
    assert np.allclose(readme_bounds(tmp_path), [[-0.07, 0.02, -0.01], [0.03, 0.18, 0.06]])


@pytest.mark.shared_data
def test_temple_silhouettes_match():
    """The Middlebury temple (16 views) at a low resolution: every image's
    silhouette is matched with IoU > 0.9 (the full 128^3 run is in
    benchmarks/photos.py)."""
    from conftest import shared_data_or_skip

    folder = shared_data_or_skip() / "middlebury_templeSparseRing"
    if not folder.is_dir():
        pytest.skip(f"{folder} not present")
    r = run_photos(folder, folder / "templeSR_par.txt", voxels=64, surface_count=2000, resolution=64, iou_stride=2)
    assert r.stats["bounds_source"] == "README"
    assert r.stats["watertight"]
    assert (r.iou > 0.9).all(), r.iou.round(3)
    assert r.mesh.has_vertex_colors()
