"""E57 scans with their scanner poses: points in world coordinates and one scanner camera per scan.

An E57 scan stores its points in its own frame and, optionally, a pose
(rotation quaternion ``q`` and translation ``t``) that takes them to the
file's world frame: ``X = R(q) @ p_scan + t``.  A terrestrial scanner sits
at the origin of its scan frame and sees all around, so each posed scan
becomes a ``"center"`` :class:`~o3drbf.cameras.model.Camera` at ``t`` with
the scan's frame (:meth:`~o3drbf.cameras.model.Camera.from_pose`), as a
Stanford ``.conf`` pose becomes a direction sensor.  Exterior constraints
then go toward the scanner and the free-space outlier check uses its
spherical z-buffer.

A scan without a pose is read in the file's frame (the E57 standard's
identity default) but gives no scanner: its position is unknown, and a
scanner guessed at the origin would carve free space through the object.
One log line says so.  A pose with NaN or infinite values is refused,
naming the scan.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from o3drbf.cameras.model import Camera, CameraSet, quaternion_to_matrix, unit_quaternion
from o3drbf.io.lidar import CHUNK_POINTS, e57_chunks, e57_scans, las_chunks

__all__ = ["load_e57", "scan_camera", "LidarPoints"]

log = logging.getLogger("o3drbf")


def scan_camera(path, scan) -> Camera:
    """The scanner camera of one E57 scan (:class:`o3drbf.io.lidar.E57Scan` with a pose).

    Raises
    ------
    ValueError
        The pose has NaN or infinite values, or a quaternion that is not of
        unit length; the message names the file and the scan.
    """
    where = f"{path}, scan {scan.index} {scan.name!r}"
    q, t = np.asarray(scan.rotation, dtype=float), np.asarray(scan.translation, dtype=float)
    values = np.concatenate([q, t])
    # libe57 reads a number too large for a double as +-DBL_MAX: an overflow, not a position
    if not (np.isfinite(values) & (np.abs(values) < np.finfo(float).max)).all():
        raise ValueError(f"{where}: the pose has NaN or infinite values (rotation w x y z {q.tolist()}, translation {t.tolist()}); "
                         "fix the pose or remove the scan (nothing was written)")
    try:
        w, x, y, z = q
        R = quaternion_to_matrix(*unit_quaternion([x, y, z, w]))
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    return Camera.from_pose(R, t, name=scan.name)


def load_e57(path: str | os.PathLike, chunk_size: int = CHUNK_POINTS) -> CameraSet:
    """Read every scan of an E57 file in world coordinates, with a scanner camera per posed scan.

    Every pose is checked before any point is read; the points are then
    read scan by scan, in chunks, into one array.

    Parameters
    ----------
    path : path-like
    chunk_size : int
        Point records decoded at a time.

    Returns
    -------
    CameraSet
        ``cameras``: one ``"center"`` scanner per scan with a pose, in file
        order (empty when no scan has one); ``points`` (N, 3) in world
        coordinates; ``point_camera`` (N,): the camera of each point's scan
        (its scan index when every scan has a pose), -1 for scans without a
        pose, or None when no scan has one.

    Raises
    ------
    ImportError
        pye57 is missing; the message names the install.
    FileNotFoundError, ValueError
        Missing, truncated or corrupt files, NaN poses, no valid point.
    """
    path = Path(path)
    scans = e57_scans(path)
    cameras, owner_of = [], []
    for scan in scans:
        if scan.has_pose:
            owner_of.append(len(cameras))
            cameras.append(scan_camera(path, scan))
        else:
            owner_of.append(-1)
    total = sum(s.count for s in scans)
    points = np.empty((total, 3))
    owner = np.empty(total, dtype=np.int64)
    k = 0
    for scan, j in zip(scans, owner_of):
        if j >= 0:
            cam = cameras[j]
            R, t = cam.R.T, cam.center  # scan -> world
        for local in e57_chunks(path, scan, chunk_size):
            m = len(local)
            points[k:k + m] = local if j < 0 else np.einsum("ij,kj->ki", R, local) + t
            owner[k:k + m] = j
            k += m
    if k == 0:
        raise ValueError(f"{path}: no points (every record is marked invalid, or the scans are empty)")
    points, owner = points[:k], owner[:k]
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} point(s) with NaN or infinite coordinates (first at index {int(np.argmax(bad))})")
    missing = [s for s in scans if not s.has_pose]
    if missing:
        shown = ", ".join(f"{s.index} {s.name!r}" for s in missing[:3]) + (", ..." if len(missing) > 3 else "")
        log.warning("%s: %d of %d scan(s) have no pose (%s): their points are read in the file's frame, without a scanner "
                    "position, so no free-space constraints nor free-space outlier check come from them", path, len(missing),
                    len(scans), shown)
    point_camera = owner if cameras else None
    return CameraSet(cameras, points, None, point_camera, None, str(path), "e57")


class LidarPoints:
    """A LAS, LAZ or E57 file as a chunked point source for :mod:`o3drbf.tiles`: never read whole.

    The interface of :class:`o3drbf.io.files.PlyVertices` (``count``,
    ``has_normals``, ``chunks``, ``gather``) plus ``cameras`` and
    ``point_camera``: an E57 file's posed scans are scanners in world
    coordinates (:func:`scan_camera`) and each point's camera is its scan's,
    as :func:`load_e57` reads them; a LAS or LAZ file has neither.  Every
    pass decodes the file chunk by chunk, so a process holds one chunk of
    points at a time (``gather`` the points asked for, ``point_camera`` one
    index per scan).

    Parameters
    ----------
    path : path-like
        ``.las``, ``.laz`` or ``.e57``.
    chunk_size : int
        Records decoded at a time.

    Raises
    ------
    ImportError
        laspy, lazrs or pye57 missing; the message names the install.
    FileNotFoundError, ValueError
        As :func:`o3drbf.io.lidar.read_las` and :func:`load_e57`: a missing,
        empty, truncated or corrupt file, a NaN pose, non-finite coordinates.

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> from o3drbf.synthetic.lidar import write_las
    >>> path = write_las(tempfile.mkdtemp() + "/p.las", np.random.default_rng(0).uniform(-1, 1, (2500, 3)))
    >>> source = LidarPoints(path, chunk_size=1000)
    >>> source.count, source.has_normals, source.cameras is None, [len(p) for _, p, _ in source.chunks()]
    (2500, False, True, [1000, 1000, 500])
    """

    has_normals = False

    def __init__(self, path, chunk_size: int = CHUNK_POINTS):
        from o3drbf.io.lidar import LAS_FORMATS, LIDAR_FORMATS, las_point_count

        self.path = Path(path)
        self.chunk_size = max(1, int(chunk_size))
        suffix = self.path.suffix.lower()
        if suffix not in LIDAR_FORMATS:
            raise ValueError(f"{self.path}: not a LAS, LAZ or E57 file ({', '.join(LIDAR_FORMATS)})")
        self.is_e57 = suffix not in LAS_FORMATS
        self.cameras, self._owner, self._scans, self._starts = None, None, None, None
        if self.is_e57:
            self._scans = e57_scans(self.path)
            cams, owner = [], []
            for scan in self._scans:  # every pose checked before any point is read
                owner.append(len(cams) if scan.has_pose else -1)
                if scan.has_pose:
                    cams.append(scan_camera(self.path, scan))
            self.cameras, self._owner = (cams or None), np.array(owner, dtype=np.int64)
            counts = [sum(len(p) for p in e57_chunks(self.path, s, self.chunk_size)) for s in self._scans]  # valid records
            self._starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
            self.count = int(self._starts[-1])
        else:
            self.count = las_point_count(self.path)
        if self.count == 0:
            raise ValueError(f"{self.path}: no points")

    def __len__(self) -> int:
        return self.count

    @property
    def point_camera(self):
        """Each point's camera (its scan's scanner, -1 for a scan without a pose), or None without scanners."""
        return None if self.cameras is None else _ScanOwner(self._starts, self._owner)

    def _pieces(self):
        """(points (m, 3) in world coordinates) chunk by chunk, in file order."""
        if not self.is_e57:
            for pts, _ in las_chunks(self.path, self.chunk_size):
                yield pts
            return
        cams = self.cameras or []
        for scan, j in zip(self._scans, self._owner):
            for local in e57_chunks(self.path, scan, self.chunk_size):
                if j < 0:
                    yield local
                else:
                    yield local @ cams[j].R + cams[j].center  # scan -> world: R^T p + t

    def chunks(self, size: int | None = None):
        """``(start, points, None)`` for consecutive chunks of the file (``size`` is the decoder's, not used)."""
        start = 0
        for pts in self._pieces():
            if not np.isfinite(pts).all():
                bad = start + int(np.flatnonzero(~np.isfinite(pts).all(axis=1))[0])
                raise ValueError(f"{self.path}: point {bad} has NaN or infinite coordinates; fix or remove it")
            yield start, pts, None
            start += len(pts)
        if start != self.count:
            raise ValueError(f"{self.path}: {start:,} points read, not the {self.count:,} announced; the file changed or is truncated")

    def gather(self, index):
        """The points at sorted ``index`` (one pass over the file) and None for normals."""
        index = np.asarray(index, dtype=np.int64)
        out = np.empty((len(index), 3))
        for start, pts, _ in self.chunks():
            a, b = np.searchsorted(index, [start, start + len(pts)])
            out[a:b] = pts[index[a:b] - start]
        return out, None


class _ScanOwner:
    """The camera index of points by position: scan k holds points ``starts[k]:starts[k+1]``."""

    def __init__(self, starts: np.ndarray, owner: np.ndarray):
        self.starts, self.owner = starts, owner

    def __len__(self) -> int:
        return int(self.starts[-1])

    def __getitem__(self, key) -> np.ndarray:
        if isinstance(key, slice):
            idx = np.arange(*key.indices(len(self)), dtype=np.int64)
        else:
            idx = np.asarray(key, dtype=np.int64)
        return self.owner[np.searchsorted(self.starts, idx, side="right") - 1]
