"""Synthetic vision data: range scans of a mesh, and space-carving-like voxels.

:func:`range_scans` ray-casts range images of a mesh from viewpoints on a
circle (the paper's Fig. 8: three views 120 degrees apart), with Gaussian
noise along the rays and uniform outliers.  :func:`voxel_shell` imitates the
output of space carving: a thick, jagged shell of voxels around the surface,
stray voxels, and the ring of cameras that carved them.
:func:`write_scan_json` stores points and cameras in the JSON format that
:func:`o3drbf.cameras.model.load_cameras` reads.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from o3drbf.validation import check_number
from o3drbf.cameras.model import Camera, save_cameras_json
from o3drbf.mesh.arrays import mesh_arrays, raycasting_scene

__all__ = ["range_scans", "misregister", "camera_ring", "voxel_shell", "VoxelShell", "write_scan_json"]


def _basis(up) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    up = np.asarray(up, dtype=float)
    if up.shape != (3,) or not np.isfinite(up).all() or np.linalg.norm(up) == 0:
        raise ValueError(f"up must be a finite non-zero 3-vector, got {np.asarray(up).tolist()}")
    up = up / np.linalg.norm(up)
    e1 = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = e1 - np.dot(e1, up) * up
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1), up


def camera_ring(
    center,
    radius: float,
    n_views: int = 3,
    elevation: float = 20.0,
    distance: float | None = None,
    width: int = 200,
    height: int = 150,
    fov: float = 40.0,
    up=(0.0, 0.0, 1.0),
    azimuth: float = 0.0,
) -> list[Camera]:
    """Pinhole cameras on a circle around ``center``, looking at it.

    Parameters
    ----------
    center : (3,) array_like
        The point every camera looks at.
    radius : float
        Radius of a sphere around the object; sets the default distance so
        the sphere fits in every image.
    n_views : int
        Number of cameras, ``360 / n_views`` degrees apart in azimuth.
    elevation : float
        Degrees above the plane perpendicular to ``up``.
    distance : float, optional
        Camera distance from ``center``.
    width, height : int
        Image size in pixels.
    fov : float
        Horizontal field of view in degrees.
    up : (3,) array_like
        The axis of the circle, which also appears up in the images.
    azimuth : float
        Azimuth of the first camera in degrees.

    Returns
    -------
    list of Camera
    """
    center = np.asarray(center, dtype=float)
    radius = check_number("radius", radius, low=0.0, low_open=True)
    n_views = check_number("n_views", n_views, low=1, integer=True)
    elevation = check_number("elevation", elevation, low=-89.0, high=89.0)
    width = check_number("width", width, low=1, integer=True)
    height = check_number("height", height, low=1, integer=True)
    fov = check_number("fov", fov, low=0.0, high=179.0, low_open=True)
    half = math.atan(math.tan(math.radians(fov) / 2) * min(1.0, height / width))  # narrower half-angle
    if distance is None:
        distance = 1.15 * radius / math.sin(half)
    distance = check_number("distance", distance, low=radius, low_open=True)
    e1, e2, upn = _basis(up)
    el = math.radians(elevation)
    cams = []
    for k in range(n_views):
        az = math.radians(azimuth) + 2 * math.pi * k / n_views
        eye = center + distance * (math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * upn)
        cams.append(Camera.look_at(eye, center, up=upn, fov=fov, width=width, height=height, name=f"view {k}"))
    return cams


def range_scans(mesh, n_views: int = 3, *, noise: float = 0.0, outliers: float = 0.0, seed: int = 0, **ring):
    """Ray-cast range images of a mesh from viewpoints on a circle.

    One ray per pixel centre; every ray that hits the mesh gives a point.

    Parameters
    ----------
    mesh : Open3D TriangleMesh, path, or (vertices (V, 3), triangles (T, 3))
    n_views : int
        Cameras ``360 / n_views`` degrees apart (the paper: 3).
    **ring
        The camera ring: ``elevation``, ``distance``, ``width``, ``height``,
        ``fov``, ``up``, ``azimuth`` of :func:`camera_ring` (its defaults);
        the ring is centred on the mesh's bounding-box centre and sized by
        its half diagonal.
    noise : float
        Standard deviation of Gaussian noise along each ray (mesh units).
    outliers : float in [0, 1)
        Fraction of the returned points that are outliers: spurious returns
        of a random camera, on one of its rays that hit the mesh, at a random
        depth between 30% and 97% of the true one (in the free space that
        camera saw, so "seen by its camera" stays true).  They are the last rows.
    seed : int

    Returns
    -------
    points : (N, 3) array
    point_camera : (N,) int array
        The camera that produced each point.
    cameras : list of Camera
    """
    v, t = mesh_arrays(mesh)
    noise = check_number("noise", noise, low=0.0)
    outliers = check_number("outliers", outliers, low=0.0)
    if outliers >= 1:
        raise ValueError(f"outliers is a fraction of the points and must be below 1, got {outliers}")
    seed = check_number("seed", seed, low=0, integer=True)
    lo, hi = v.min(axis=0), v.max(axis=0)
    center = (lo + hi) / 2
    ring_names = ("elevation", "distance", "width", "height", "fov", "up", "azimuth")
    unknown = sorted(set(ring) - set(ring_names))
    if unknown:
        raise ValueError(f"unknown camera-ring argument(s) {', '.join(unknown)}; valid: {', '.join(ring_names)}")
    cams = camera_ring(center, 0.5 * float(np.linalg.norm(hi - lo)), n_views, **ring)
    scene = raycasting_scene(v, t)
    rng = np.random.default_rng(seed)
    import open3d as o3d

    parts, owner, hits = [], [], []
    for k, cam in enumerate(cams):
        rays = cam.pixel_rays(unit=True).reshape(-1, 6)
        d = rays[:, 3:]
        rays = rays.astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(float)
        ok = np.isfinite(hit)
        depth = hit[ok]
        if noise > 0:
            depth = depth + rng.normal(0.0, noise, size=depth.shape)
        parts.append(cam.center + d[ok] * depth[:, None])
        owner.append(np.full(int(ok.sum()), k, dtype=np.int64))
        hits.append((d[ok], hit[ok]))
    points = np.concatenate(parts)
    if not len(points):
        raise ValueError("no ray hits the mesh; check the camera distance and field of view")
    n_out = int(round(outliers / (1 - outliers) * len(points)))
    if n_out:
        cam_of = rng.integers(0, len(cams), size=n_out)
        extra = np.empty((n_out, 3))
        for k in range(len(cams)):
            sel = np.flatnonzero(cam_of == k)
            dirs, t_hit = hits[k]
            if not len(sel):
                continue
            if not len(t_hit):  # this camera saw nothing: give its outliers to camera 0's rays
                cam_of[sel] = 0
                dirs, t_hit = hits[0]
            ray = rng.integers(0, len(t_hit), size=len(sel))
            depth = t_hit[ray] * rng.uniform(0.3, 0.97, size=len(sel))
            extra[sel] = cams[cam_of[sel[0]]].center + dirs[ray] * depth[:, None]
        points = np.vstack([points, extra])
        owner.append(cam_of)
    return points, np.concatenate(owner), cams


def misregister(points, point_camera, cameras, error: float, seed: int = 0):
    """Each scan moved by a small rigid error, as a registration error would leave it.

    As in Berger et al.'s benchmark (``registration_error``): every camera's
    points and the camera itself move together by one rigid motion about the
    scan's centroid, a rotation of ``error / r`` radians about a random axis
    (``r`` the scan's radius about its centroid, so its farthest points move
    by ``error``) followed by a translation of length ``error`` in a random
    direction.  Points of no camera (``point_camera < 0``) stay.

    Parameters
    ----------
    points : (N, 3) array
    point_camera : (N,) int array
    cameras : list of Camera
    error : float
        Displacement scale (data units), e.g. 0.005 of the bounding-box diagonal.
    seed : int

    Returns
    -------
    points : (N, 3) array
        The moved points (a copy).
    cameras : list of Camera
        The cameras at their (wrong) registered poses.
    """
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    error = check_number("error", error, low=0.0)
    points = np.array(points, dtype=float)
    owner = np.asarray(point_camera)
    rng = np.random.default_rng(seed)
    moved = []
    for k, cam in enumerate(cameras):
        sel = owner == k
        axis, shift = rng.normal(size=3), rng.normal(size=3)
        if not sel.any() or error == 0:
            moved.append(cam)
            continue
        c = points[sel].mean(axis=0)
        radius = float(np.linalg.norm(points[sel] - c, axis=1).max()) or 1.0
        Q = Rotation.from_rotvec(axis / np.linalg.norm(axis) * error / radius).as_matrix()
        s = shift / np.linalg.norm(shift) * error
        points[sel] = (points[sel] - c) @ Q.T + c + s
        # x_cam = R X + t with X = Q^T (X' - c - s) + c
        R = cam.R @ Q.T
        moved.append(replace(cam, R=R, t=cam.t + cam.R @ c - R @ (c + s)))
    return points, moved


@dataclass(frozen=True, eq=False)
class VoxelShell:
    """Voxels imitating space carving output.

    Attributes
    ----------
    occupancy : (nx, ny, nz) bool array
    origin : (3,) array
        World position of the corner of voxel (0, 0, 0); voxel ``(i, j, k)``
        has its centre at ``origin + (ijk + 0.5) * voxel_size``.
    voxel_size : float
    cameras : list of Camera
        The ring of cameras that carved the volume; the whole grid is in
        every image.
    stray : (nx, ny, nz) bool array
        The stray voxels (a subset of ``occupancy``), for evaluation.
    """

    occupancy: np.ndarray
    origin: np.ndarray
    voxel_size: float
    cameras: list
    stray: np.ndarray

    def indices(self) -> np.ndarray:
        """``(V, 3)`` int indices of the occupied voxels."""
        return np.argwhere(self.occupancy)

    def centers(self) -> np.ndarray:
        """``(V, 3)`` world coordinates of the occupied voxel centres."""
        return self.origin + (self.indices() + 0.5) * self.voxel_size


def _sdf_function(shape) -> tuple[Callable[[np.ndarray], np.ndarray], np.ndarray | None]:
    """A signed-distance function (negative inside) and, if known, bounds (2, 3)."""
    if hasattr(shape, "signed_distance") and hasattr(shape, "sample"):  # o3drbf.synthetic.shapes
        pts, _ = shape.sample(4096, seed=0)
        return shape.signed_distance, np.stack([pts.min(axis=0), pts.max(axis=0)])
    if callable(shape):
        return shape, None
    import open3d as o3d

    v, t = mesh_arrays(shape)
    scene = raycasting_scene(v, t)

    def sdf(x):
        q = o3d.core.Tensor(np.asarray(x, dtype=np.float32).reshape(-1, 3))
        return scene.compute_signed_distance(q).numpy().astype(float).reshape(np.shape(x)[:-1])

    return sdf, np.stack([v.min(axis=0), v.max(axis=0)])


def voxel_shell(
    shape: Any,
    resolution: int = 64,
    thickness: float = 1.5,
    jitter: float = 1.5,
    stray_fraction: float = 0.02,
    seed: int = 0,
    n_cameras: int = 16,
    bounds=None,
    up=(0.0, 0.0, 1.0),
) -> VoxelShell:
    """A noisy voxel shell around a shape, as space carving leaves it.

    Carving keeps every voxel it cannot prove empty, so the result is a
    thick shell that reaches outward irregularly, with a few stray voxels.
    A voxel is in the shell when its centre's signed distance ``s`` obeys
    ``-thickness * h <= s <= (0.5 + jitter * g) * h`` (``h`` the voxel size,
    ``g >= 0`` a smooth random field with unit RMS, keeping only bumps attached
    to the band ``s <= h / 2``); stray voxels are scattered
    uniformly in the empty space at least two voxels from the shell.

    Parameters
    ----------
    shape : o3drbf.synthetic.shapes shape, closed Open3D mesh, or callable
        Signed distance (negative inside); a callable needs ``bounds``.
    resolution : int
        Voxels along the longest side of the padded bounding box (>= 8).
    thickness : float
        Inward thickness in voxels (>= 0).
    jitter : float
        Outward jaggedness in voxels (>= 0).
    stray_fraction : float
        Stray voxels per shell voxel (>= 0).
    seed : int
    n_cameras : int
        Cameras of the ring (elevation 30 degrees).
    bounds : (2, 3) array_like, optional
        Bounding box ``[min, max]`` of the shape.
    up : (3,) array_like
        Axis of the camera ring.

    Returns
    -------
    VoxelShell
    """
    from scipy import ndimage

    resolution = check_number("resolution", resolution, low=8, integer=True)
    thickness = check_number("thickness", thickness, low=0.0)
    jitter = check_number("jitter", jitter, low=0.0)
    stray_fraction = check_number("stray_fraction", stray_fraction, low=0.0)
    seed = check_number("seed", seed, low=0, integer=True)
    n_cameras = check_number("n_cameras", n_cameras, low=1, integer=True)
    sdf, known = _sdf_function(shape)
    if bounds is None:
        if known is None:
            raise ValueError("bounds ([min, max] of the shape) are needed when shape is a plain function")
        bounds = known
    bounds = np.asarray(bounds, dtype=float)
    if bounds.shape != (2, 3) or not np.isfinite(bounds).all() or (bounds[1] <= bounds[0]).any():
        raise ValueError(f"bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max, got {bounds.tolist()}")
    pad_voxels = 0.5 + 3 * jitter + 4
    h = float((bounds[1] - bounds[0]).max()) / (resolution - 2 * pad_voxels)
    if h <= 0 or resolution <= 2 * pad_voxels:
        raise ValueError(f"resolution {resolution} is too small for jitter {jitter}; raise it")
    origin = bounds[0] - pad_voxels * h
    dims = np.ceil((bounds[1] - bounds[0]) / h + 2 * pad_voxels).astype(int)
    ijk = np.stack(np.meshgrid(*[np.arange(d) for d in dims], indexing="ij"), axis=-1)
    s = np.asarray(sdf(origin + (ijk.reshape(-1, 3) + 0.5) * h), dtype=float).reshape(tuple(dims))
    rng = np.random.default_rng(seed)
    g = ndimage.gaussian_filter(rng.normal(size=tuple(dims)), sigma=1.5, mode="wrap")
    g = np.abs(g) / max(float(np.sqrt((g**2).mean())), 1e-12)
    core = (s >= -thickness * h - 0.5 * h) & (s <= 0.5 * h)
    shell = core | ((s > 0) & (s <= (0.5 + jitter * g) * h))
    if not core.any():
        raise ValueError("the shell is empty: resolution too coarse for the shape")
    # Outward bumps stay attached to the shell (islands of the jitter field are dropped).
    labels, _ = ndimage.label(shell, structure=np.ones((3, 3, 3), bool))
    shell = np.isin(labels, np.unique(labels[core]))
    n_stray = int(round(stray_fraction * shell.sum()))
    far = ~ndimage.binary_dilation(shell, structure=np.ones((3, 3, 3), bool), iterations=2) & (s > 0)
    stray = np.zeros_like(shell)
    if n_stray:
        pool = np.flatnonzero(far)
        pick = rng.choice(pool, size=min(n_stray, len(pool)), replace=False)
        stray.flat[pick] = True
    lo, hi = origin, origin + dims * h  # the whole grid is in view
    cams = camera_ring(
        (lo + hi) / 2, 0.5 * float(np.linalg.norm(hi - lo)), n_cameras, elevation=30.0, width=320, height=240, fov=45.0, up=up
    )
    return VoxelShell(shell | stray, origin, h, cams, stray)


def write_scan_json(path: str | os.PathLike, points, cameras, point_camera=None) -> Path:
    """Write points and their cameras as one JSON file (see :mod:`o3drbf.cameras.model`).

    Parameters
    ----------
    path : path-like
        Output ``.json`` file (written atomically).
    points : (N, 3) array_like
    cameras : sequence of Camera
    point_camera : (N,) int array_like, optional
        The camera that produced each point (-1: unknown).

    Returns
    -------
    Path
    """
    return save_cameras_json(path, cameras, points=points, point_camera=point_camera)
