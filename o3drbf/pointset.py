"""The input, checked once: points with their normals, cameras and colours.

Every stage of :func:`o3drbf.reconstruct` takes and returns a
:class:`PointSet`.  It is validated when it is made (shapes, finite values,
normals of unit length, camera indices in range) and carries what stages
would otherwise recompute: the KD-tree and the mean nearest-neighbour
spacing are built lazily, once.  :func:`read_input` makes one from a file
(point clouds, and files that hold points and cameras).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

import o3drbf.cameras.formats  # noqa: F401  (registers the files camera inputs refer to, for output checks)
from o3drbf.io.lidar import LAS_FORMATS
from o3drbf.validation import as_points, as_vectors

__all__ = ["PointSet", "read_input", "CAMERA_INPUTS"]

#: Inputs that hold points *and* cameras (a folder is a COLMAP model; an E57
#: file's scans have scanner poses).
CAMERA_INPUTS = (".conf", ".out", ".json", ".e57")


@dataclass(frozen=True, eq=False)
class PointSet:
    """Surface samples and what is known about them, in data coordinates.

    Make one with :meth:`create` (which validates); the constructor trusts
    its arguments.

    Attributes
    ----------
    points : (N, 3) ndarray of float64
    normals : (N, 3) ndarray or None
        Outward unit normals.
    cameras : list of Camera or None
        The cameras (or scanners) that saw the points.
    point_camera : (N,) ndarray of int or None
        Index of the camera that produced each point (-1: unknown).
    colors : (N, 3) ndarray in [0, 1] or None
    source : str
        Where the data came from (a file name), for messages.
    camera_source : str
        The camera file, for messages.
    normals_estimated : bool
        The normals were estimated (not given).

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> from o3drbf import PointSet
    >>> data = PointSet.create(points, normals)
    >>> len(data.points), data.normals is not None, round(data.spacing, 3)
    (600, True, 0.072)
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    cameras: list | None = None
    point_camera: np.ndarray | None = None
    colors: np.ndarray | None = None
    source: str = ""
    camera_source: str = ""
    normals_estimated: bool = False
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def create(cls, points, normals=None, *, cameras=None, point_camera=None, colors=None, source: str = "", min_count: int = 10) -> "PointSet":
        """Validate and bundle the input.

        Parameters
        ----------
        points : (N, 3) array_like, open3d.geometry.PointCloud or open3d.t.geometry.PointCloud
            A point cloud's normals and colours are used when present and not
            given explicitly.
        normals : (N, 3) array_like, optional
        cameras : sequence of Camera, CameraSet or path, optional
        point_camera : (N,) int array_like, optional
        colors : (N, 3) array_like, optional
            In [0, 1] (or 0..255 integers).
        source : str
            A name for messages.
        min_count : int
            Fewest points accepted.

        Raises
        ------
        ValueError
            Empty, NaN, too few points, wrong shapes, camera indices out of range.
        """
        cloud_normals = cloud_colors = None
        if hasattr(points, "point") and not isinstance(points, np.ndarray):  # open3d.t.geometry.PointCloud
            attrs = points.point
            if "normals" in attrs:
                cloud_normals = attrs["normals"].numpy()
            if "colors" in attrs:
                cloud_colors = attrs["colors"].numpy()
            points = attrs["positions"].numpy()
        elif hasattr(points, "points") and not isinstance(points, np.ndarray):  # legacy open3d PointCloud
            if points.has_normals():
                cloud_normals = np.asarray(points.normals)
            if points.has_colors():
                cloud_colors = np.asarray(points.colors)
        pts = as_points(points, min_count=min_count)
        n = len(pts)
        normals = cloud_normals if normals is None else normals
        nrm = None if normals is None else as_vectors(normals, n, name="normals")
        colors = cloud_colors if colors is None else colors
        col = None if colors is None else _colors(colors, n)
        cams, camera_source = _cameras(cameras)
        pc = None
        if point_camera is not None:
            pc = np.asarray(point_camera)
            if pc.shape != (n,) or not np.issubdtype(pc.dtype, np.integer):
                raise ValueError(f"point_camera must be an ({n},) integer array, got {pc.dtype} {pc.shape}")
            if cams is None:
                raise ValueError("point_camera needs cameras")
            if pc.max() >= len(cams) or pc.min() < -1:
                raise ValueError(f"point_camera values must be -1 or camera indices 0..{len(cams) - 1}")
            pc = None if (pc < 0).all() else pc.astype(np.int64)
        return cls(pts, nrm, cams, pc, col, str(source), camera_source)

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, keep) -> "PointSet":
        """The points selected by ``keep`` (a boolean mask or indices), with their data."""
        keep = np.asarray(keep)

        def pick(a):
            return None if a is None else a[keep]

        return replace(self, points=self.points[keep], normals=pick(self.normals), point_camera=pick(self.point_camera),
                       colors=pick(self.colors), _cache={})

    def with_normals(self, normals, estimated: bool = False) -> "PointSet":
        """The same points with these normals (``estimated``: not measured)."""
        return replace(self, normals=as_vectors(normals, len(self), name="normals"), normals_estimated=bool(estimated), _cache=self._cache)

    @property
    def kdtree(self):
        """A :class:`scipy.spatial.cKDTree` of the points (built once)."""
        if "kdtree" not in self._cache:
            from scipy.spatial import cKDTree

            self._cache["kdtree"] = cKDTree(self.points)
        return self._cache["kdtree"]

    @property
    def spacing(self) -> float:
        """Mean nearest-neighbour distance (data units; computed once)."""
        if "spacing" not in self._cache:
            d, _ = self.kdtree.query(self.points, k=2, workers=-1)
            self._cache["spacing"] = float(d[:, 1].mean())
        return self._cache["spacing"]

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) array: the lower and upper corners of the points' box."""
        return np.stack([self.points.min(axis=0), self.points.max(axis=0)])


def _colors(colors, n: int) -> np.ndarray:
    c = np.asarray(colors)
    if c.shape != (n, 3):
        raise ValueError(f"colors must have shape ({n}, 3), got {c.shape}")
    if np.issubdtype(c.dtype, np.integer):
        c = c / 255.0
    c = np.asarray(c, dtype=float)
    if not np.isfinite(c).all() or c.min() < 0 or c.max() > 1:
        raise ValueError("colors must be in [0, 1] (floats) or 0..255 (integers)")
    return c


def _cameras(cameras):
    """(list of Camera or None, the file they came from or "")."""
    if cameras is None:
        return None, ""
    if isinstance(cameras, (str, bytes)) or hasattr(cameras, "__fspath__"):
        from o3drbf.cameras.model import load_cameras

        cameras = load_cameras(cameras)
    source = str(getattr(cameras, "source", "") or "")
    cams = list(cameras)
    if not cams:
        raise ValueError(f"{source + ': ' if source else ''}cameras is empty; give at least one camera (or None to use normals)")
    return cams, source


def read_input(path: str | os.PathLike, cameras: str | os.PathLike | None = None, *, min_count: int = 10) -> PointSet:
    """Read INPUT (and an optional camera file) into a :class:`PointSet`.

    Parameters
    ----------
    path : path
        A point cloud file (PLY, PCD, XYZ, XYZN, XYZRGB, PTS: normals and
        colours used when present; LAS and LAZ lidar points, read in chunks),
        or a file holding points and cameras: a Stanford ``.conf`` (range
        scans), a COLMAP text folder, a Bundler ``bundle.out``, an o3drbf
        scan ``.json``, or an E57 file (one scanner per scan pose;
        :func:`o3drbf.cameras.lidar.load_e57`).
    cameras : path, optional
        Cameras that saw the points (any format :func:`o3drbf.cameras.model.load_cameras` reads).
        Refused when ``path`` already holds cameras.

    Raises
    ------
    FileNotFoundError, ValueError
        Missing or unreadable files, files without points, cameras given twice.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> import tempfile, pathlib
    >>> from o3drbf import read_input
    >>> from o3drbf.io.files import write_points
    >>> path = write_points(pathlib.Path(tempfile.mkdtemp()) / 'sphere.ply', points, normals)
    >>> data = read_input(path)
    >>> len(data.points), data.normals.shape
    (600, (600, 3))
    """
    from o3drbf.io import files

    p = Path(path)
    if p.is_dir() or p.suffix.lower() in CAMERA_INPUTS:
        from o3drbf.cameras.model import load_cameras

        if not p.exists():
            raise FileNotFoundError(f"input not found: {p}")
        if cameras is not None:
            raise ValueError(f"{p} already holds cameras; drop --cameras")
        cams = load_cameras(p, read_scans=True) if p.suffix.lower() == ".conf" else load_cameras(p)
        if cams.points is None or len(cams.points) == 0:
            raise ValueError(f"{p} holds cameras but no points; give a point cloud as INPUT and this file as --cameras")
        colors = getattr(cams, "colors", None)
        if not len(cams):  # an E57 file without any scan pose: points only
            return PointSet.create(cams.points, None, colors=colors, source=str(p), min_count=min_count)
        return PointSet.create(cams.points, None, cameras=cams, point_camera=cams.point_camera, colors=colors,
                               source=str(p), min_count=min_count)
    if p.suffix.lower() in LAS_FORMATS:
        from o3drbf.io.lidar import read_las

        points, colors = read_las(p)
        return PointSet.create(points, None, cameras=cameras, colors=colors, source=str(p), min_count=min_count)
    points, normals, colors = files.read_points(p)
    return PointSet.create(points, normals, cameras=cameras, colors=colors, source=str(p), min_count=min_count)
