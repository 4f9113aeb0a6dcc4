"""Synthetic lidar data: terrestrial scans of a mesh, written as E57, LAS or LAZ.

:func:`terrestrial_scans` ray-casts a mesh from scanners standing around it
(each a ``"center"`` camera at its pose, sweeping an azimuth-elevation grid),
:func:`e57_scans_from` turns world points into the per-scan records an E57
file holds (points in each scan's frame, the pose as a quaternion and a
translation), :func:`write_e57` writes them with double-precision coordinates
(so a round trip is exact to float64 arithmetic) and :func:`write_las` writes
points as LAS or LAZ.  The tests use them as the truth for the readers in
:mod:`o3drbf.io.lidar` and :mod:`o3drbf.cameras.lidar`.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np

from o3drbf.cameras.model import Camera
from o3drbf.io.files import atomic_path
from o3drbf.mesh.arrays import mesh_arrays, raycasting_scene
from o3drbf.validation import as_points, check_number

__all__ = ["terrestrial_scans", "e57_scans_from", "write_e57", "write_las"]


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def terrestrial_scans(mesh, positions, step: float = 1.0, noise: float = 0.0, outliers: float = 0.0, yaw=None, seed: int = 0):
    """Ray-cast a mesh from terrestrial scanners at ``positions``.

    Each scanner sweeps a regular grid of azimuth and elevation angles (in
    its own frame, turned about z by its yaw) over the window that holds the
    mesh's bounding sphere; every ray that hits gives a point.

    Parameters
    ----------
    mesh : Open3D TriangleMesh, path, or (vertices (V, 3), triangles (T, 3))
    positions : (S, 3) array_like
        Scanner positions, outside the mesh.
    step : float
        Angular step of the grid in degrees.
    noise : float
        Standard deviation of Gaussian noise along each ray (mesh units).
    outliers : float in [0, 1)
        Fraction of the returned points that are spurious returns: on a
        random scanner's ray that hit the mesh, at a random depth short of
        the hit (in the free space that scanner saw), as
        :func:`o3drbf.synthetic.scans.range_scans` places them.  They are
        the last rows.
    yaw : (S,) array_like, optional
        Each scanner's turn about z in degrees (default: seeded random).
    seed : int

    Returns
    -------
    points : (N, 3) array
        World coordinates.
    point_camera : (N,) int array
        The scanner of each point.
    cameras : list of Camera
        ``Camera.from_pose`` scanners, one per position.
    """
    import open3d as o3d

    v, t = mesh_arrays(mesh)
    pos = as_points(positions, name="positions")
    step = np.radians(check_number("step", step, low=0.0, low_open=True))
    noise = check_number("noise", noise, low=0.0)
    outliers = check_number("outliers", outliers, low=0.0)
    if outliers >= 1:
        raise ValueError(f"outliers is a fraction of the points and must be below 1, got {outliers}")
    rng = np.random.default_rng(check_number("seed", seed, low=0, integer=True))
    yaws = rng.uniform(0.0, 360.0, len(pos)) if yaw is None else np.asarray(yaw, dtype=float).reshape(len(pos))
    centre = (v.min(axis=0) + v.max(axis=0)) / 2
    radius = 0.5 * float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    scene = raycasting_scene(v, t)
    parts, owner, cameras, hits = [], [], [], []
    for k, (p, angle) in enumerate(zip(pos, np.radians(yaws))):
        R = _yaw(angle)  # scanner -> world
        cam = Camera.from_pose(R, p, name=f"scan {k}")
        d = cam.to_camera(centre[None])[0]
        dist = float(np.linalg.norm(d))
        if dist <= radius:
            raise ValueError(f"scanner {k} at {p.tolist()} is inside the mesh's bounding sphere; place it farther away")
        half = np.arcsin(radius / dist) * 1.05
        az0, el0 = np.arctan2(d[1], d[0]), np.arcsin(d[2] / dist)
        el = np.arange(max(el0 - half, -np.pi / 2), min(el0 + half, np.pi / 2), step)
        span = half / max(np.cos(min(abs(el0) + half, np.radians(85.0))), 1e-3)
        az = np.arange(az0 - span, az0 + span, step)
        A, E = np.meshgrid(az, el)
        local = np.column_stack([np.cos(E.ravel()) * np.cos(A.ravel()), np.cos(E.ravel()) * np.sin(A.ravel()), np.sin(E.ravel())])
        dirs = local @ R.T
        rays = np.hstack([np.broadcast_to(p, dirs.shape), dirs]).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(float)
        ok = np.isfinite(hit)
        depth = hit[ok] + (rng.normal(0.0, noise, int(ok.sum())) if noise > 0 else 0.0)
        parts.append(p + dirs[ok] * depth[:, None])
        owner.append(np.full(int(ok.sum()), k, dtype=np.int64))
        cameras.append(cam)
        hits.append((dirs[ok], hit[ok]))
    points = np.concatenate(parts)
    if not len(points):
        raise ValueError("no ray hits the mesh; check the scanner positions")
    n_out = int(round(outliers / (1 - outliers) * len(points)))
    if n_out:
        seen = [k for k in range(len(pos)) if len(hits[k][1])]
        cam_of = rng.choice(seen, size=n_out)
        extra = np.empty((n_out, 3))
        for k in seen:
            sel = np.flatnonzero(cam_of == k)
            dirs, t_hit = hits[k]
            ray = rng.integers(0, len(t_hit), size=len(sel))
            extra[sel] = pos[k] + dirs[ray] * (t_hit[ray] * rng.uniform(0.3, 0.97, size=len(sel)))[:, None]
        parts.append(extra)
        owner.append(cam_of.astype(np.int64))
        points = np.concatenate(parts)
    return points, np.concatenate(owner), cameras


def _quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def e57_scans_from(points, point_camera, cameras) -> list[dict]:
    """Per-scan records for :func:`write_e57` from world points and their scanners.

    Parameters
    ----------
    points : (N, 3) array_like
        World coordinates.
    point_camera : (N,) int array_like
        The scanner of each point.
    cameras : sequence of Camera
        ``"center"`` scanners (their frame is the scan's frame).

    Returns
    -------
    list of dict
        One per camera: ``name``, ``points`` (in the scan's frame),
        ``rotation`` (unit quaternion ``w, x, y, z``, scan to world) and
        ``translation`` (the scanner's position).
    """
    pts = as_points(points)
    pc = np.asarray(point_camera)
    scans = []
    for j, cam in enumerate(cameras):
        scans.append({"name": cam.name or f"scan {j}", "points": cam.to_camera(pts[pc == j]),
                      "rotation": _quaternion_wxyz(cam.R.T), "translation": cam.center.copy()})
    return scans


def write_e57(path: str | os.PathLike, scans) -> Path:
    """Write scans as an E57 file, coordinates in double precision (atomically).

    Parameters
    ----------
    path : path-like
        The ``.e57`` file.
    scans : sequence of dict
        ``points`` (M, 3) in the scan's frame, ``name``, and ``rotation``
        ``(w, x, y, z)`` with ``translation`` (3,), or both None for a scan
        without a pose.  The values are written as given; libe57 cannot
        store NaN or infinite ones.

    Returns
    -------
    Path
    """
    import pye57
    from pye57 import libe57

    path = Path(path)
    with atomic_path(path) as tmp:
        e57 = pye57.E57(tmp, mode="w")
        imf = e57.image_file
        try:
            for i, scan in enumerate(scans):
                pts = np.asarray(scan["points"], dtype=float).reshape(-1, 3)
                node = libe57.StructureNode(imf)
                node.set("guid", libe57.StringNode(imf, "{%s}" % uuid.uuid4()))
                node.set("name", libe57.StringNode(imf, str(scan.get("name", f"scan {i}"))))
                if scan.get("rotation") is not None:
                    pose = libe57.StructureNode(imf)
                    rot = libe57.StructureNode(imf)
                    for key, value in zip("wxyz", np.asarray(scan["rotation"], dtype=float)):
                        rot.set(key, libe57.FloatNode(imf, float(value)))
                    tra = libe57.StructureNode(imf)
                    for key, value in zip("xyz", np.asarray(scan["translation"], dtype=float)):
                        tra.set(key, libe57.FloatNode(imf, float(value)))
                    pose.set("rotation", rot)
                    pose.set("translation", tra)
                    node.set("pose", pose)
                proto = libe57.StructureNode(imf)
                lo = pts.min(axis=0) if len(pts) else np.zeros(3)
                hi = pts.max(axis=0) if len(pts) else np.zeros(3)
                names = ("cartesianX", "cartesianY", "cartesianZ")
                for k, name in enumerate(names):
                    proto.set(name, libe57.FloatNode(imf, float(lo[k]), libe57.E57_DOUBLE, float(lo[k]), float(hi[k])))
                points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
                node.set("points", points)
                e57.data3d.append(node)
                if len(pts):
                    columns = {name: np.ascontiguousarray(pts[:, k]) for k, name in enumerate(names)}
                    buffers = libe57.VectorSourceDestBuffer()
                    for name in names:
                        buffers.append(libe57.SourceDestBuffer(imf, name, columns[name], len(pts), True, True))
                    writer = points.writer(buffers)
                    writer.write(len(pts))
                    writer.close()
        finally:
            e57.close()
    return path


def write_las(path: str | os.PathLike, points, colors=None, scale: float = 1e-5) -> Path:
    """Write points as LAS or LAZ (from the extension; LAZ with lazrs), atomically.

    Parameters
    ----------
    path : path-like
        A ``.las`` or ``.laz`` file.
    points : (N, 3) array_like
    colors : (N, 3) array_like in [0, 1], optional
        Stored as 16-bit red, green, blue (point format 3; else format 0).
    scale : float
        Coordinate resolution (LAS stores integers times the scale, offset
        by the points' minimum).

    Returns
    -------
    Path
    """
    import laspy

    path = Path(path)
    pts = as_points(points)
    header = laspy.LasHeader(point_format=0 if colors is None else 3, version="1.2")
    header.scales = [float(scale)] * 3
    header.offsets = np.floor(pts.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        rgb = np.round(np.clip(np.asarray(colors, dtype=float), 0.0, 1.0) * 65535).astype(np.uint16)
        las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    backend = laspy.LazBackend.Lazrs if path.suffix.lower() == ".laz" else None
    with atomic_path(path) as tmp:
        las.write(tmp, laz_backend=backend)
    return path
