"""``o3drbf photos``: calibrated photographs to a closed, coloured mesh (the paper's Fig. 9).

    o3drbf photos IMAGES_DIR --calibration FILE -o model.ply [--picture fig9.png]

Stages (each with a progress bar and a summary line):

1. read the calibration (Middlebury ``*_par.txt``, Bundler ``bundle.out`` with
   its list, COLMAP text model) and the images it names;
2. carve a voxel volume (:func:`o3drbf.photo.carve.carve`): silhouettes by
   background colour, then visibility-aware photo-consistency;
3. reconstruct (:func:`o3drbf.pipeline.reconstruct`): the shell voxels are the
   surface points, exterior constraints go toward the cameras that see them,
   the largest component is kept;
4. colour the mesh from the photographs (:func:`o3drbf.mesh.color.color_mesh`;
   the shell voxels' colours where no camera sees a vertex);
5. check: silhouette intersection over union per image, by ray casting the
   mesh from every camera; optionally a picture of the coloured model next
   to an input photograph from the same camera.

:func:`run_photos` does it all from Python and returns a :class:`PhotosResult`.
"""

from __future__ import annotations

import logging
import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from o3drbf.options import PHOTO_DEFAULTS, PHOTO_OUTLIER_VOXELS, PHOTO_OVERRIDES, Options, PhotoOptions
from o3drbf.photo import carve as carving
from o3drbf.validation import as_rgb

__all__ = ["run_photos", "PhotosResult", "readme_bounds", "picture", "photo_inputs", "camera_index", "summary", "PHOTO_DEFAULTS",
           "PHOTO_OVERRIDES", "PHOTO_OUTLIER_VOXELS", "PhotoOptions"]

log = logging.getLogger("o3drbf")



@dataclass
class PhotosResult:
    """What :func:`run_photos` returns.

    Attributes
    ----------
    mesh : open3d.geometry.TriangleMesh
        Closed, coloured mesh (world coordinates of the calibration).
    cameras : list of Camera
    images : list of (H, W, 3) float arrays
    masks : list of (H, W) bool arrays
        The silhouettes used for carving.
    carve : CarveResult
    reconstruction : Reconstruction
    iou : (n_cameras,) array
        Silhouette IoU per image, against the silhouettes restricted to where
        the carving box projects (what can be object).
    iou_raw : (n_cameras,) array
        Against the raw silhouettes.
    stats : dict
        Timings and counts per stage.
    """

    mesh: object
    cameras: list
    images: list
    masks: list
    carve: object
    reconstruction: object
    iou: np.ndarray
    iou_raw: np.ndarray
    stats: dict = field(default_factory=dict)


_TRIPLE = r"\(\s*([-+0-9.eE]+)[\s,]+([-+0-9.eE]+)[\s,]+([-+0-9.eE]+)\s*\)"


def readme_bounds(folder: str | os.PathLike) -> np.ndarray | None:
    """The bounding box a Middlebury ``README.txt`` gives, or None.

    Looks for "bounding box" followed by two ``(x y z)`` triples.
    """
    folder = Path(folder)
    for name in ("README.txt", "readme.txt", "README"):
        p = folder / name
        if not p.is_file():
            continue
        text = p.read_text(encoding="utf-8", errors="replace")
        k = text.lower().find("bounding box")
        if k < 0:
            continue
        found = re.findall(_TRIPLE, text[k:])
        if len(found) >= 2:
            b = np.array(found[:2], dtype=float)
            lo, hi = b.min(axis=0), b.max(axis=0)
            if (hi > lo).all():
                return np.stack([lo, hi])
    return None


def _load(images_dir, calibration):
    from o3drbf.cameras.model import load_cameras

    folder = Path(images_dir)
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder not found: {folder}")
    cal = Path(calibration) if calibration else folder
    if calibration and not cal.exists():
        raise FileNotFoundError(f"calibration not found: {cal}")
    cams = load_cameras(cal)
    if cams.format == "bundler" and cams[0].width is None:
        # Bundler's principal point is the image centre: the loader needs the size.
        first = carving.find_image(folder, cams[0].name)
        if first is not None:
            h, w = carving.read_image(first).shape[:2]
            cams = load_cameras(cal, image_size=(w, h))
    bad = [c.name or str(i) for i, c in enumerate(cams) if c.kind != "pinhole"]
    if bad:
        raise ValueError(f"{cal}: cameras {', '.join(bad[:3])} are not pinhole cameras; photographs need K, R, t")
    if cams.format == "middlebury":  # its image sizes are the photographs' own: check them against the principal points
        for cam in cams:
            if cam.width is not None and cam.height is not None:
                carving._check_principal_point(cam.name, cam, cam.width, cam.height)
    images, cams2 = carving.read_images(folder, cams)
    return images, cams2, cams


def run_photos(images_dir, calibration=None, *, options: PhotoOptions | None = None, seed: int = 0, progress: bool = False, images=None,
               cameras=None, **overrides) -> PhotosResult:
    """Calibrated photographs to a closed, coloured mesh.

    Parameters
    ----------
    images_dir : path-like
        Folder of the photographs (ignored when ``images`` and ``cameras``
        are given).
    calibration : path-like, optional
        Camera file or folder (default: found in ``images_dir``).
    options : PhotoOptions, optional
        The carving box (``bounds``), the carving (``carving``, a
        :class:`~o3drbf.options.CarveOptions`), the fit of the carved shell
        (``surface``, an :class:`~o3drbf.options.Options`:
        :data:`o3drbf.options.DEFAULTS` with
        :data:`o3drbf.options.PHOTO_OVERRIDES`; carved shells are dense and
        nearly noise-free, so it smooths less and places one exterior
        constraint per two surface constraints) and the silhouette check's
        stride.  Default :class:`~o3drbf.options.PhotoOptions`.
    seed : int
        Seed for every random choice.
    progress : bool
        Progress bars per stage.
    images, cameras : optional
        Images and cameras already in memory, instead of reading files.
    **overrides
        Flat option names over ``options`` (:meth:`PhotoOptions.create`):
        ``voxels`` (carving voxels along the box's longest side),
        ``bounds``, ``threshold``, ..., and any option of
        :func:`o3drbf.reconstruct` (``resolution``: the marching cubes',
        ``delta``, ``surface_count``, ``solver``...).

    Returns
    -------
    PhotosResult

    Raises
    ------
    ValueError
        Bad options (checked before any file is read), unreadable inputs, too few shell voxels.

    Examples
    --------
    >>> import numpy as np, open3d as o3d
    >>> from o3drbf.photo.pipeline import run_photos
    >>> from o3drbf.synthetic.render import render_views
    >>> from o3drbf.synthetic.scans import camera_ring
    >>> sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=20).paint_uniform_color([0.8, 0.3, 0.2])
    >>> cameras = camera_ring((0, 0, 0), 1.0, n_views=6, elevation=30, width=64, height=48, fov=50)
    >>> images = [view.image for view in render_views(sphere, cameras)]
    >>> result = run_photos(None, images=images, cameras=cameras, bounds=[[-1.25] * 3, [1.25] * 3], voxels=32,
    ...                     surface_count=300, resolution=24)
    >>> radii = np.linalg.norm(np.asarray(result.mesh.vertices), axis=1)
    >>> result.mesh.is_watertight(), bool(abs(np.median(radii) - 1) < 0.05), result.mesh.has_vertex_colors()
    (True, True, True)
    """
    from o3drbf.pipeline import reconstruct
    from o3drbf.mesh.color import color_mesh
    from o3drbf.mesh.metrics import mesh_report

    opts = PhotoOptions.create(options, **overrides).validate()
    carve_opts, bounds = opts.carving, opts.bounds
    stats: dict = {}
    t0 = time.perf_counter()
    if images is None or cameras is None:
        images, cams, _ = _load(images_dir, calibration)
        readme = readme_bounds(images_dir) if images_dir is not None else None
    else:
        cams = list(cameras)
        images = [as_rgb(im, f"image {i}", np.float32) for i, im in enumerate(images)]
        readme = None
    stats["read_seconds"] = time.perf_counter() - t0

    if isinstance(bounds, str):
        if bounds not in ("auto", "silhouettes"):
            raise ValueError(f"bounds must be 'auto', 'silhouettes' or six numbers, got {bounds!r}")
        box = readme if bounds == "auto" else None
        stats["bounds_source"] = "README" if box is not None else "silhouettes"
    else:
        box = carving.check_bounds(bounds)
        stats["bounds_source"] = "given"

    t0 = time.perf_counter()
    masks = carving.silhouettes(images, background=carve_opts.background, threshold=carve_opts.threshold, min_area=carve_opts.min_area)
    stats["segment_seconds"] = time.perf_counter() - t0
    cv = carving.carve(images, cams, bounds=box, options=carve_opts, masks=masks, progress=progress)
    stats["carve"] = cv.stats
    if len(cv.points) < 10:
        raise ValueError(f"carving left {len(cv.points)} shell voxels; at least 10 needed (raise voxels, --voxels, or check bounds)")

    t0 = time.perf_counter()
    surface = opts.surface
    radius = surface.outliers.radius if surface.outliers.radius is not None else PHOTO_OUTLIER_VOXELS * cv.voxel_size
    surface = Options.create(surface, outlier_radius=radius, bounds=cv.bounds)  # the carving's box and voxels
    rec = reconstruct(cv.points, cameras=cams, point_camera=cv.best_camera(), options=surface, seed=seed, progress=progress)
    stats["reconstruct_seconds"] = time.perf_counter() - t0
    stats["reconstruct"] = rec.stats

    mesh, dropped = largest_component(rec.mesh)
    stats["mesh_pieces_dropped"] = dropped
    t0 = time.perf_counter()
    mesh = color_mesh(mesh, cameras=cams, images=images, points=cv.points, colors=cv.colors)
    stats["color_seconds"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    box_used = cv.bounds
    inside = carving.box_masks(box_used, cams)
    hits = carving.mesh_masks(mesh, cams, stride=opts.iou_stride)
    st = slice(None, None, opts.iou_stride)
    iou = carving.mask_iou(hits, [(m & b)[st, st] for m, b in zip(masks, inside)])
    iou_raw = carving.mask_iou(hits, [m[st, st] for m in masks])
    stats["iou_seconds"] = time.perf_counter() - t0
    rep = mesh_report(mesh)
    stats["watertight"] = bool(rep["watertight"])
    stats["components"] = rep["components"]
    stats["triangles"] = len(mesh.triangles)
    stats["vertices"] = len(mesh.vertices)
    return PhotosResult(mesh, cams, images, masks, cv, rec, iou, iou_raw, stats)


def largest_component(mesh):
    """The mesh's largest connected piece (by triangles), and how many pieces were dropped."""
    import open3d as o3d

    if len(mesh.triangles) == 0:
        return mesh, 0
    labels, counts, _ = mesh.cluster_connected_triangles()
    labels = np.asarray(labels)
    if len(counts) <= 1:
        return mesh, 0
    out = o3d.geometry.TriangleMesh(mesh)
    out.remove_triangles_by_mask(labels != int(np.argmax(counts)))
    out.remove_unreferenced_vertices()
    return out, len(counts) - 1


# -- picture ------------------------------------------------------------------


def render_model(mesh, camera, lighting: bool = False) -> np.ndarray:
    """Render a coloured mesh offscreen from a calibrated camera with PyVista.

    Returns
    -------
    (H, W, 3) uint8 array
    """
    from o3drbf.pictures import headless, to_pyvista

    headless()
    import pyvista as pv

    W, H = camera.width, camera.height
    plotter = pv.Plotter(off_screen=True, window_size=[W, H])
    plotter.set_background("black")
    poly = to_pyvista(mesh)
    if mesh.has_vertex_colors():
        rgb = (np.clip(np.asarray(mesh.vertex_colors), 0, 1) * 255).astype(np.uint8)
        plotter.add_mesh(poly, scalars=rgb, rgb=True, lighting=lighting)
    else:
        plotter.add_mesh(poly, color="#c8d2e6", lighting=True)
    K, R = camera.K, camera.R
    c = camera.center
    cam = plotter.camera
    cam.position = tuple(c)
    cam.focal_point = tuple(c + R[2])
    cam.up = tuple(-R[1])
    cam.view_angle = math.degrees(2 * math.atan(0.5 * H / K[1, 1]))
    # principal point away from the image centre: shift the projection
    cam.SetWindowCenter(-(K[0, 2] - 0.5 * W) / (0.5 * W), (K[1, 2] - 0.5 * H) / (0.5 * H))
    depth = np.linalg.norm(np.asarray(mesh.vertices) - c, axis=1)
    cam.clipping_range = (max(1e-6, 0.5 * float(depth.min())), 2.0 * float(depth.max()))
    img = plotter.screenshot(return_img=True)
    plotter.close()
    return np.asarray(img)[:, :, :3]


def photo_inputs(images_dir, calibration=None) -> list[Path]:
    """The files ``o3drbf photos`` reads, which no output may overwrite.

    The image folder, the calibration (or the folder it is found in), and
    every photograph the calibration names that exists in the image folder
    (or its ``images`` subfolder).  The files a calibration itself refers to
    are added by :func:`o3drbf.io.files.check_outputs`.

    Parameters
    ----------
    images_dir : path-like
    calibration : path-like, optional

    Returns
    -------
    list of Path
        Unreadable calibrations contribute only their own path (reading them
        later names the problem).
    """
    from o3drbf.cameras.model import load_cameras

    folder = Path(images_dir)
    cal = Path(calibration) if calibration else folder
    files = [folder, cal]
    try:
        cams = load_cameras(cal)
    except (ValueError, OSError):
        return files
    for cam in cams:
        found = carving.find_image(folder, cam.name) if cam.name else None
        if found is not None:
            files.append(found)
    return files


def picture(mesh, camera, photo, path, lighting: bool = False, inputs=()) -> Path:
    """The input photograph and the coloured model from the same camera, side by side (PNG).

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh
        With vertex colours.
    camera : Camera
        Pinhole camera with width and height.
    photo : (H, W, 3) array
        The photograph taken by ``camera``.
    path : path-like
        Output ``.png``, written atomically and read back before it replaces ``path``.
    inputs : iterable of path-like
        Files the picture must not overwrite (:func:`o3drbf.io.files.check_outputs`).
    """
    import skimage.io

    from o3drbf.io.files import atomic_path, check_outputs, write_failed

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"picture must be a .png file, got {str(path)!r}")
    check_outputs([path], inputs)
    render = render_model(mesh, camera, lighting=lighting)
    photo8 = (np.clip(as_rgb(photo, "photo", np.float32), 0, 1) * 255).round().astype(np.uint8)
    gap = np.full((photo8.shape[0], 8, 3), 255, dtype=np.uint8)
    panel = np.concatenate([photo8, gap, render], axis=1)
    def verify(tmp):
        try:
            back = skimage.io.imread(tmp)
        except Exception as exc:  # noqa: BLE001 - any decoder failure means a bad write
            raise write_failed(path, f"the picture does not read back ({exc})") from None
        if back.shape[:2] != panel.shape[:2]:
            raise write_failed(path, f"the picture reads back as {back.shape[1]}x{back.shape[0]}, not {panel.shape[1]}x{panel.shape[0]}")

    with atomic_path(path, verify=verify) as tmp:
        skimage.io.imsave(tmp, panel, check_contrast=False)
    return path


# -- the command's summary ---------------------------------------------------------


def camera_index(spec: str, cameras) -> int:
    """The camera ``spec`` names: an index 0..n-1 or an image name (``o3drbf photos --picture-camera``); ValueError otherwise."""
    names = [c.name for c in cameras]
    if spec in names:
        return names.index(spec)
    try:
        i = int(spec)
    except ValueError:
        raise ValueError(f"--picture-camera {spec!r} is neither an index 0..{len(cameras) - 1} nor an image name ({', '.join(names[:3])}, ...)") from None
    if not 0 <= i < len(cameras):
        raise ValueError(f"--picture-camera {i} is out of range; valid: 0..{len(cameras) - 1}")
    return i


def summary(res: PhotosResult, images_dir, output, picture_path=None, seconds=None) -> str:
    """Per-stage summary of :func:`run_photos`."""
    s, c, r = res.stats, res.carve.stats, res.reconstruction.stats
    cam0 = res.cameras[0]
    worst = int(np.argmin(res.iou))
    lines = [
        f"o3drbf photos: {images_dir} -> {output}",
        f"  read         {len(res.cameras)} calibrated images, {cam0.width}x{cam0.height} ({s['read_seconds']:.1f} s)",
        f"  silhouettes  foreground {100 * np.mean(c['silhouette_fraction']):.1f}% of pixels on average ({s['segment_seconds']:.1f} s)",
        f"  carve        box from {s['bounds_source']}, grid {'x'.join(map(str, c['grid']))} = {c['voxels']:,} voxels of {c['voxel_size']:.4g}; "
        f"{c['silhouette_carved']:,} carved by silhouettes, {c['photo_carved']:,} by photo-consistency "
        f"({c['photo_protected']:,} kept on the outline) ({c['hull_seconds'] + c['photo_seconds']:.1f} s)",
        f"  shell        {c['shell_voxels']:,} surface voxels, seen by {c['shell_views_mean']:.1f} cameras on average, "
        f"{c['shell_unseen']:,} by none ({c['shell_seconds']:.1f} s)",
        f"  constraints  {r['surface_constraints']:,} surface, {r['exterior_constraints']:,} exterior, {r['sphere_constraints']:,} sphere; "
        f"{r['outliers_removed']:,} outlying voxels removed",
        f"  fit          {r['solver']}, relative residual {r['residual']:.1e} ({r['solve_seconds']:.1f} s); mesh extracted in {r['extract_seconds']:.1f} s",
        f"  mesh         {s['triangles']:,} triangles, {s['vertices']:,} vertices, watertight {'yes' if s['watertight'] else 'NO'}, "
        f"{s['components']} component(s) ({s['mesh_pieces_dropped']} small piece(s) dropped); coloured in {s['color_seconds']:.1f} s",
        f"  check        silhouette IoU per image min {res.iou.min():.3f} ({res.cameras[worst].name}), mean {res.iou.mean():.3f} "
        f"(raw segmentation: min {res.iou_raw.min():.3f}, mean {res.iou_raw.mean():.3f}) ({s['iou_seconds']:.1f} s)",
    ]
    if picture_path:
        lines.append(f"  picture      {picture_path} ({s.get('picture_seconds', 0):.1f} s)")
    if seconds is not None:
        lines.append(f"  total time   {seconds:.1f} s")
    return "\n".join(lines)
