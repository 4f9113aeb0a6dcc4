"""Cameras and sensors, and the files that describe them.

A :class:`Camera` is one of three kinds of sensor:

``"pinhole"``
    A calibrated perspective camera: ``x_cam = R @ X + t`` and
    ``pixel ~ K @ x_cam`` (OpenCV convention: +z forward, x right, y down,
    pixel origin at the top-left corner of the image, continuous coordinates).
``"center"``
    A sensor at a point that sees in every direction: a position only
    (``{"centers": [...]}``) or a terrestrial scanner at its pose (E57 scans,
    :meth:`Camera.from_pose`).  Free space is the segment toward the centre;
    its image is spherical (:meth:`Camera.spherical`: azimuth and elevation
    about its own axes, the range as depth).
``"direction"``
    An orthographic sensor that looks along one direction, like a sweeping
    line scanner (the Stanford range scans): it has no centre, and its free
    space is the half-line from a point against the viewing direction.

Every kind stores a world-to-sensor pose ``(R, t)`` and looks along +z of its
own frame; :attr:`Camera.direction` is that axis in world coordinates.

:func:`load_cameras` reads every supported format, detected from the path:

=====================  =====================================================
JSON                   ``{"cameras": [{"K", "R", "t", "width", "height"}]}``
                       or ``{"centers": [[x, y, z], ...]}`` (optionally
                       ``"points"`` and ``"point_camera"``)
Middlebury             ``*_par.txt``: count, then ``name K(9) R(9) t(3)``
COLMAP                 text model folder: ``cameras.txt``, ``images.txt``,
                       ``points3D.txt``
Bundler                ``bundle.out`` (v0.3)
Stanford range scans   ``*.conf``: ``bmesh file tx ty tz qx qy qz qw``
E57 lidar scans        ``*.e57``: scans with poses (:mod:`o3drbf.cameras.lidar`)
=====================  =====================================================

Each returns a :class:`CameraSet`: the cameras, plus the points and which
cameras saw them when the format has them.  Malformed files raise
:class:`ValueError` naming the file and the line or entry.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from o3drbf.validation import as_points, check_choice, check_number

__all__ = [
    "Camera",
    "CameraSet",
    "KINDS",
    "as_cameras",
    "load_cameras",
    "load_range_scans",
    "referenced_files",
    "save_cameras_json",
    "quaternion_to_matrix",
]

#: The kinds of sensor a :class:`Camera` can be.
KINDS = ("pinhole", "center", "direction")

#: Largest ``|R R^T - I|`` accepted for a rotation read from a file.
ORTHONORMAL_TOLERANCE = 1e-4

# Flips a frame that looks along -z (Bundler, Stanford scanners) into one that
# looks along +z with y down (OpenCV): a half turn about x.
_FLIP = np.diag([1.0, -1.0, -1.0])


def quaternion_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """Rotation matrix of the unit quaternion ``w + xi + yj + zk``.

    The quaternion is normalized first; it must be non-zero and finite.

    Returns
    -------
    (3, 3) array
    """
    q = np.array([x, y, z, w], dtype=float)
    n = float(np.linalg.norm(q))
    if not np.isfinite(q).all() or n == 0:
        raise ValueError(f"quaternion (x, y, z, w) = {q.tolist()} is not a finite non-zero quaternion")
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(q / n).as_matrix()  # scipy's order is scalar-last (x, y, z, w)


def _unit_quaternion(q: Sequence[float], tolerance: float = 1e-3) -> np.ndarray:
    """Check a quaternion is (nearly) unit length, as files store them."""
    q = np.asarray(q, dtype=float)
    if not np.isfinite(q).all():
        raise ValueError(f"quaternion has NaN or infinite components: {q.tolist()}")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > tolerance:
        raise ValueError(f"quaternion {q.tolist()} has length {n:.6g}; a rotation needs a unit quaternion")
    return q / n


def _rotation(R, name: str = "R") -> np.ndarray:
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        raise ValueError(f"{name} must be a 3x3 matrix, got shape {R.shape}")
    if not np.isfinite(R).all():
        raise ValueError(f"{name} has NaN or infinite entries: {R.tolist()}")
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > ORTHONORMAL_TOLERANCE:
        raise ValueError(f"{name} is not orthonormal (max |R R^T - I| = {err:.3g} > {ORTHONORMAL_TOLERANCE:g})")
    if np.linalg.det(R) < 0:
        raise ValueError(f"{name} is a reflection (det = -1), not a rotation")
    return R


def _frame_looking_along(direction, up=None) -> np.ndarray:
    """Rotation whose third row is ``direction`` (x right, y down w.r.t. ``up``)."""
    z = np.asarray(direction, dtype=float)
    if z.shape != (3,) or not np.isfinite(z).all() or np.linalg.norm(z) == 0:
        raise ValueError(f"direction must be a finite non-zero 3-vector, got {np.asarray(direction).tolist()}")
    z = z / np.linalg.norm(z)
    if up is None:
        up = np.eye(3)[int(np.argmin(np.abs(z)))]
    up = np.asarray(up, dtype=float)
    y = -(up - np.dot(up, z) * z)
    if np.linalg.norm(y) < 1e-9:
        raise ValueError(f"up vector {up.tolist()} is parallel to the viewing direction {z.tolist()}")
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    return np.stack([x, y, z])


@dataclass(frozen=True, eq=False)
class Camera:
    """A sensor that saw the data: a pinhole camera, a centre, or a direction.

    Parameters
    ----------
    K : (3, 3) array_like, optional
        Intrinsic matrix (upper triangular, positive focal lengths); pinhole
        cameras only.
    R : (3, 3) array_like, optional
        World-to-sensor rotation (default identity).
    t : (3,) array_like, optional
        World-to-sensor translation, ``x_cam = R @ X + t`` (default zero).
    width, height : int, optional
        Image size in pixels.  ``None`` leaves the image unbounded (only "in
        front" counts).
    kind : {"pinhole", "center", "direction"}
    name : str
        Image or scan name, for messages.
    """

    K: np.ndarray | None = None
    R: np.ndarray = None  # type: ignore[assignment]
    t: np.ndarray = None  # type: ignore[assignment]
    width: int | None = None
    height: int | None = None
    kind: str = "pinhole"
    name: str = ""

    def __post_init__(self):
        check_choice("kind", self.kind, KINDS)
        R = np.eye(3) if self.R is None else _rotation(self.R)
        t = np.zeros(3) if self.t is None else np.asarray(self.t, dtype=float).reshape(-1)
        if t.shape != (3,) or not np.isfinite(t).all():
            raise ValueError(f"t must be a finite 3-vector, got {np.asarray(self.t).tolist()}")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        if self.kind == "pinhole":
            if self.K is None:
                raise ValueError("a pinhole camera needs an intrinsic matrix K")
            K = np.asarray(self.K, dtype=float)
            if K.shape != (3, 3) or not np.isfinite(K).all():
                raise ValueError(f"K must be a finite 3x3 matrix, got {np.asarray(self.K).tolist()}")
            if np.abs(K[1:, 0]).max() > 0 or abs(K[2, 1]) > 0 or abs(K[2, 2] - 1) > 1e-9 or K[0, 0] <= 0 or K[1, 1] <= 0:
                raise ValueError(
                    f"K must be upper triangular with K[2, 2] = 1 and positive focal lengths, got {K.tolist()}"
                )
            object.__setattr__(self, "K", K)
        elif self.K is not None:
            raise ValueError(f"a {self.kind!r} sensor has no intrinsic matrix; K must be None")
        for name in ("width", "height"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, check_number(name, v, low=1, integer=True))

    # -- constructors -------------------------------------------------------

    @classmethod
    def from_center(cls, center, name: str = "") -> "Camera":
        """A sensor known only by its position."""
        c = np.asarray(center, dtype=float).reshape(-1)
        if c.shape != (3,) or not np.isfinite(c).all():
            raise ValueError(f"center must be a finite 3-vector, got {np.asarray(center).tolist()}")
        return cls(R=np.eye(3), t=-c, kind="center", name=name)

    @classmethod
    def from_pose(cls, rotation, translation, name: str = "") -> "Camera":
        """A terrestrial scanner at a pose, seeing in every direction.

        Parameters
        ----------
        rotation : (3, 3) array_like
            Scanner-to-world rotation: ``X = rotation @ p_scan + translation``
            (an E57 scan's pose).
        translation : (3,) array_like
            The scanner's position in world coordinates.
        name : str

        Returns
        -------
        Camera
            A ``"center"`` sensor at ``translation`` whose frame is the
            scanner's (``to_camera`` gives scan coordinates).
        """
        Rs = _rotation(rotation, "rotation")
        c = np.asarray(translation, dtype=float).reshape(-1)
        if c.shape != (3,) or not np.isfinite(c).all():
            raise ValueError(f"translation must be a finite 3-vector, got {np.asarray(translation).tolist()}")
        return cls(R=Rs.T, t=-Rs.T @ c, kind="center", name=name)

    @classmethod
    def from_direction(cls, direction, name: str = "") -> "Camera":
        """An orthographic sensor looking along ``direction`` (world coordinates)."""
        return cls(R=_frame_looking_along(direction), t=np.zeros(3), kind="direction", name=name)

    @classmethod
    def look_at(
        cls,
        eye,
        target,
        up=(0.0, 0.0, 1.0),
        fov: float = 45.0,
        width: int = 640,
        height: int = 480,
        name: str = "",
    ) -> "Camera":
        """A pinhole camera at ``eye`` looking at ``target``.

        Parameters
        ----------
        eye, target : (3,) array_like
        up : (3,) array_like
            World direction that appears upward in the image.
        fov : float
            Horizontal field of view in degrees, in (0, 180).
        width, height : int
            Image size; the principal point is the image centre.
        """
        eye = np.asarray(eye, dtype=float)
        fov = check_number("fov", fov, low=0.0, high=180.0, low_open=True)
        if fov >= 180:
            raise ValueError(f"fov must be below 180 degrees, got {fov}")
        R = _frame_looking_along(np.asarray(target, dtype=float) - eye, up)
        width = check_number("width", width, low=1, integer=True)
        height = check_number("height", height, low=1, integer=True)
        f = 0.5 * width / math.tan(math.radians(fov) / 2)
        K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
        return cls(K=K, R=R, t=-R @ eye, width=width, height=height, name=name)

    def moved(self, transform) -> "Camera":
        """The same sensor after its scan moved rigidly by ``transform``.

        Parameters
        ----------
        transform : (4, 4) array_like
            A rigid motion of world points, ``x' = T[:3, :3] @ x + T[:3, 3]``.

        Returns
        -------
        Camera
            Sees the moved points exactly where this one saw the originals
            (same pixels, same depths).
        """
        T = np.asarray(transform, dtype=float)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"transform must be a finite 4x4 matrix, got shape {T.shape}")
        Rt, tt = _rotation(T[:3, :3], "transform[:3, :3]"), T[:3, 3]
        R = self.R @ Rt.T
        return replace(self, R=R, t=self.t - R @ tt)

    # -- geometry -----------------------------------------------------------

    @property
    def center(self) -> np.ndarray:
        """``-R^T t``: the camera centre (for a direction sensor, its frame origin)."""
        return -self.R.T @ self.t

    @property
    def direction(self) -> np.ndarray:
        """Unit viewing direction in world coordinates (the sensor's +z axis)."""
        return self.R[2].copy()

    def to_camera(self, points) -> np.ndarray:
        """World points ``(N, 3)`` to sensor coordinates ``R X + t``, ``(N, 3)``."""
        # einsum: BLAS matmul of a tall (N, 3) by a 3x3 is slow and oversubscribes threads.
        return np.einsum("ij,kj->ik", np.asarray(points, dtype=float).reshape(-1, 3), self.R) + self.t

    def project(self, points):
        """Project world points.

        Parameters
        ----------
        points : (N, 3) array_like

        Returns
        -------
        pixels : (N, 2) array
            Pinhole: pixel coordinates (NaN behind the camera).  Direction:
            the orthographic image-plane coordinates (sensor x, y).  Centre:
            NaN (a centre has no image).
        depth : (N,) array
            Pinhole and direction: the sensor z coordinate (> 0 in front).
            Centre: the distance to the centre.
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        if self.kind == "center":
            return np.full((len(pts), 2), np.nan), np.linalg.norm(pts - self.center, axis=1)
        xc = self.to_camera(pts)
        depth = xc[:, 2]
        if self.kind == "direction":
            return xc[:, :2].copy(), depth
        pixels = np.full((len(pts), 2), np.nan)
        front = depth > 0
        x = xc[front, 0] / depth[front]
        y = xc[front, 1] / depth[front]
        K = self.K
        pixels[front, 0] = K[0, 0] * x + K[0, 1] * y + K[0, 2]
        pixels[front, 1] = K[1, 1] * y + K[1, 2]
        return pixels, depth

    def spherical(self, points):
        """Directions of world points about the sensor, in its own frame.

        Parameters
        ----------
        points : (N, 3) array_like

        Returns
        -------
        angles : (N, 2) array
            Azimuth in ``(-pi, pi]`` (about the sensor's z axis, from its x
            axis) and elevation in ``[-pi/2, pi/2]`` (from its xy plane);
            NaN for a point at the centre.
        distance : (N,) array
            Distance to the centre.
        """
        xc = self.to_camera(points)
        r = np.linalg.norm(xc, axis=1)
        angles = np.full((len(xc), 2), np.nan)
        ok = r > 0
        angles[ok, 0] = np.arctan2(xc[ok, 1], xc[ok, 0])
        angles[ok, 1] = np.arcsin(np.clip(xc[ok, 2] / r[ok], -1.0, 1.0))
        return angles, r

    def pixel_rays(self, stride: int = 1, unit: bool = False) -> np.ndarray:
        """Rays from the camera centre through pixel centres (pinhole cameras with an image size).

        Parameters
        ----------
        stride : int
            Every ``stride``-th pixel in each direction (1: all).
        unit : bool
            Unit-length directions.  Default: directions whose camera-frame z
            component is 1, so a hit's ray parameter is its depth (camera z).

        Returns
        -------
        (H', W', 6) float64 array
            Origin (the camera centre) and direction ``R^T K^-1 [u + 0.5, v + 0.5, 1]``
            for the pixel in row ``v``, column ``u``; ``H' = ceil(H / stride)``,
            ``W' = ceil(W / stride)``.
        """
        if self.kind != "pinhole" or self.width is None or self.height is None:
            raise ValueError(f"pixel rays need a pinhole camera with width and height; camera {self.name!r} is {self.kind} {self.width}x{self.height}")
        stride = check_number("stride", stride, low=1, integer=True)
        uu, vv = np.meshgrid(np.arange(0, self.width, stride) + 0.5, np.arange(0, self.height, stride) + 0.5)
        pix = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
        d = np.linalg.solve(self.K, pix.reshape(-1, 3).T).T @ self.R  # rows: R^T K^-1 [u v 1]
        if unit:
            d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = d.reshape(pix.shape)
        return np.concatenate([np.broadcast_to(self.center, d.shape), d], axis=-1)

    def in_view(self, points):
        """In front of the camera, and inside its image.

        Parameters
        ----------
        points : (N, 3) array_like

        Returns
        -------
        front : (N,) bool array
            Positive depth (always true for centre and direction sensors).
        inside : (N,) bool array
            In front and ``0 <= u < width``, ``0 <= v < height`` (an unknown
            size leaves that axis unbounded).
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        if self.kind != "pinhole":
            ones = np.ones(len(pts), dtype=bool)
            return ones, ones.copy()
        pixels, depth = self.project(pts)
        front = depth > 0
        ok = front.copy()
        with np.errstate(invalid="ignore"):
            if self.width is not None:
                ok &= (pixels[:, 0] >= 0) & (pixels[:, 0] < self.width)
            if self.height is not None:
                ok &= (pixels[:, 1] >= 0) & (pixels[:, 1] < self.height)
        return front, ok

    def in_front(self, points) -> np.ndarray:
        """``(N,)`` bool: positive depth (always true for centre and direction sensors)."""
        return self.in_view(points)[0]

    def in_image(self, points) -> np.ndarray:
        """``(N,)`` bool: in front of the camera and inside its image (see :meth:`in_view`)."""
        return self.in_view(points)[1]

    def toward(self, points):
        """Unit directions from points toward the sensor, and how far it is.

        Parameters
        ----------
        points : (N, 3) array_like

        Returns
        -------
        directions : (N, 3) array
            Unit vectors from each point into the free space this sensor
            proves empty: toward the centre, or against the viewing direction.
        distances : (N,) array
            Distance to the centre (``inf`` for a direction sensor).
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        if self.kind == "direction":
            return np.broadcast_to(-self.direction, pts.shape).copy(), np.full(len(pts), np.inf)
        d = self.center - pts
        dist = np.linalg.norm(d, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            d = d / dist[:, None]
        return d, dist

    def to_dict(self) -> dict:
        """JSON-ready description (the format :func:`load_cameras` reads)."""
        if self.kind == "center":
            out = {"kind": "center", "center": self.center.tolist()}
            if not np.array_equal(self.R, np.eye(3)):  # a scanner's orientation
                out["R"] = self.R.tolist()
        else:
            out = {"R": self.R.tolist(), "t": self.t.tolist()}
            if self.kind == "pinhole":
                out = {"K": self.K.tolist(), **out}
            else:
                out = {"kind": "direction", **out}
            if self.width is not None:
                out["width"] = self.width
            if self.height is not None:
                out["height"] = self.height
        if self.name:
            out["name"] = self.name
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        """Inverse of :meth:`to_dict`; also accepts ``{"direction": [...]}``."""
        if not isinstance(d, dict):
            raise ValueError(f"a camera must be a JSON object, got {type(d).__name__}")
        kind = d.get("kind", "pinhole" if "K" in d else None)
        name = str(d.get("name", ""))
        if kind == "center" or (kind is None and "center" in d):
            if "R" in d:
                return cls.from_pose(_array(d, "R", (3, 3)).T, _array(d, "center", (3,)), name=name)
            return cls.from_center(_need(d, "center"), name=name)
        if kind == "direction" and "direction" in d:
            return cls.from_direction(d["direction"], name=name)
        if kind not in KINDS:
            raise ValueError(f"cannot tell the camera kind from keys {sorted(d)}; give K, R, t (pinhole) or 'kind'")
        return cls(
            K=_array(d, "K", (3, 3)) if kind == "pinhole" else None,
            R=_array(d, "R", (3, 3)),
            t=_array(d, "t", (3,)),
            width=d.get("width"),
            height=d.get("height"),
            kind=kind,
            name=name,
        )

    def __repr__(self) -> str:
        label = f" {self.name!r}" if self.name else ""
        if self.kind == "center":
            return f"Camera(center{label} at {np.round(self.center, 6).tolist()})"
        if self.kind == "direction":
            return f"Camera(direction{label} {np.round(self.direction, 6).tolist()})"
        return (
            f"Camera(pinhole{label} at {np.round(self.center, 6).tolist()}, looking "
            f"{np.round(self.direction, 4).tolist()}, {self.width}x{self.height})"
        )


def _need(d: dict, key: str):
    if key not in d:
        raise ValueError(f"missing key {key!r}")
    return d[key]


def _array(d: dict, key: str, shape) -> np.ndarray:
    try:
        a = np.asarray(_need(d, key), dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{key} must be numbers: {exc}") from None
    if a.shape != shape:
        raise ValueError(f"{key} must have shape {shape}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{key} has NaN or infinite entries: {a.tolist()}")
    return a


@dataclass(frozen=True, eq=False)
class CameraSet(Sequence):
    """Cameras read from a file, with the points when the format holds them.

    Behaves as a sequence of :class:`Camera`.

    Attributes
    ----------
    cameras : list of Camera
    points : (N, 3) array or None
        Scan points (Stanford, JSON) or the sparse reconstruction (COLMAP,
        Bundler), in world coordinates.
    colors : (N, 3) array in [0, 1] or None
    point_camera : (N,) int array or None
        Index of the camera or scan that produced each point (-1: unknown).
    observations : (K, 2) int array or None
        ``(point, camera)`` pairs: which images saw each point (COLMAP tracks,
        Bundler view lists).
    source : str
        The file or folder read.
    format : str
        ``"json"``, ``"middlebury"``, ``"colmap"``, ``"bundler"`` or ``"stanford"``.
    """

    cameras: list = field(default_factory=list)
    points: np.ndarray | None = None
    colors: np.ndarray | None = None
    point_camera: np.ndarray | None = None
    observations: np.ndarray | None = None
    source: str = ""
    format: str = ""

    def __len__(self) -> int:
        return len(self.cameras)

    def __getitem__(self, i):
        return self.cameras[i]

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def known_visible(self) -> np.ndarray | None:
        """``(N, C)`` bool: camera ``c`` is known to have seen point ``i``.

        From ``point_camera`` and ``observations``; ``None`` without points.
        """
        if self.points is None:
            return None
        mask = np.zeros((len(self.points), len(self.cameras)), dtype=bool)
        if self.point_camera is not None:
            ok = self.point_camera >= 0
            mask[np.flatnonzero(ok), self.point_camera[ok]] = True
        if self.observations is not None and len(self.observations):
            mask[self.observations[:, 0], self.observations[:, 1]] = True
        return mask

    def __repr__(self) -> str:
        pts = "" if self.points is None else f", {len(self.points)} points"
        return f"CameraSet({len(self.cameras)} {self.format} cameras from {self.source!r}{pts})"


# -- errors -----------------------------------------------------------------


class _Where:
    """Prefixes errors with the file and the line or entry they concern."""

    def __init__(self, path: Path):
        self.path = path

    def error(self, where: str | None, message: str) -> ValueError:
        return ValueError(f"{self.path}{', ' + where if where else ''}: {message}")

    def floats(self, tokens: Sequence[str], where: str, what: str) -> np.ndarray:
        try:
            vals = np.array([float(s) for s in tokens])
        except ValueError:
            raise self.error(where, f"{what}: expected numbers, got {' '.join(tokens)!r}") from None
        if not np.isfinite(vals).all():
            raise self.error(where, f"{what}: NaN or infinite value in {' '.join(tokens)!r}")
        return vals


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror}") from None


# -- JSON -------------------------------------------------------------------


def _load_json(path: Path) -> CameraSet:
    w = _Where(path)
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise w.error(None, f"not a text JSON file (undecodable byte at offset {exc.start}); give a UTF-8 JSON camera file") from None
    except RecursionError:
        raise w.error(None, "JSON nested too deeply; give a camera file as documented") from None
    except json.JSONDecodeError as exc:
        raise w.error(f"line {exc.lineno}", f"invalid JSON: {exc.msg}") from None
    except OSError as exc:
        raise w.error(None, f"cannot read: {exc.strerror}") from None
    if not isinstance(data, dict) or not ({"cameras", "centers"} & set(data)):
        raise w.error(None, 'expected a JSON object with "cameras" (list of {K, R, t, width, height}) or "centers"')
    cameras = []
    for key in ("cameras", "centers"):
        entries = data.get(key, [])
        if not isinstance(entries, list):
            raise w.error(None, f'"{key}" must be a list')
        for i, entry in enumerate(entries):
            try:
                cam = Camera.from_dict(entry) if key == "cameras" else Camera.from_center(entry, name=f"center {i}")
            except ValueError as exc:
                raise w.error(f"{key}[{i}]", str(exc)) from None
            cameras.append(cam)
    if not cameras:
        raise w.error(None, "the file lists no camera")
    points = colors = point_camera = None
    if "points" in data:
        try:
            points = as_points(data["points"], name='"points"')
        except ValueError as exc:
            raise w.error(None, str(exc)) from None
        if "colors" in data:
            try:
                colors = np.asarray(data["colors"], dtype=float)
            except (TypeError, ValueError):
                raise w.error(None, '"colors" must be a list of [r, g, b] numbers, one per point (ragged or non-numeric entries)') from None
            if colors.shape != points.shape:
                raise w.error(None, f'"colors" has shape {colors.shape}; expected {points.shape}, one per point')
            if not np.isfinite(colors).all() or colors.min() < 0 or colors.max() > 1:
                raise w.error(None, '"colors" must be finite and in [0, 1]')
    if "point_camera" in data:
        if points is None:
            raise w.error(None, '"point_camera" given without "points"')
        point_camera = _point_camera(w, data["point_camera"], len(points), len(cameras))
    return CameraSet(cameras, points, colors, point_camera, None, str(path), "json")


def _point_camera(w: _Where, values, n_points: int, n_cameras: int) -> np.ndarray:
    pc = np.asarray(values)
    if pc.shape != (n_points,):
        raise w.error(None, f'"point_camera" has {pc.size} entries for {n_points} points (count mismatch)')
    if pc.size and (not np.issubdtype(pc.dtype, np.number) or (pc != np.round(pc)).any()):
        raise w.error(None, '"point_camera" must be whole numbers (camera index, -1 for unknown)')
    pc = pc.astype(np.int64)
    bad = (pc < -1) | (pc >= n_cameras)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise w.error(
            f"point_camera[{i}]", f"camera index {pc[i]} is out of range: the file has {n_cameras} camera(s) (count mismatch)"
        )
    return pc


def as_cameras(cameras, purpose: str | None = None, sized: bool = False, allow_empty: bool = False) -> list[Camera]:
    """A camera, a :class:`CameraSet` or a sequence of cameras as a checked list.

    Parameters
    ----------
    cameras : Camera, CameraSet or sequence of Camera
    purpose : str, optional
        When given, every camera must be a pinhole camera; the error says
        ``"<purpose> need pinhole cameras"`` (e.g. ``"images"``).
    sized : bool
        Every camera must have ``width`` and ``height``.
    allow_empty : bool
        Accept no cameras at all.

    Returns
    -------
    list of Camera

    Raises
    ------
    ValueError
        Something that is not a Camera, a camera of the wrong kind or
        without an image size, or (unless ``allow_empty``) no cameras.
    """
    if isinstance(cameras, Camera):
        cameras = [cameras]
    cams = list(getattr(cameras, "cameras", cameras))
    if not cams and not allow_empty:
        raise ValueError("cameras is empty; give at least one Camera")
    for i, cam in enumerate(cams):
        label = f"camera {i}" + (f" ({cam.name})" if getattr(cam, "name", "") else "")
        if not isinstance(cam, Camera):
            raise ValueError(f"{label} is a {type(cam).__name__}, not an o3drbf.cameras.model.Camera")
        if purpose is not None and cam.kind != "pinhole":
            raise ValueError(f"{label} is a {cam.kind!r} sensor; {purpose} need pinhole cameras")
        if sized and (cam.width is None or cam.height is None):
            raise ValueError(f"{label} has no image size (width/height); {purpose or 'this'} needs one")
    return cams


def save_cameras_json(path: str | os.PathLike, cameras, points=None, point_camera=None, colors=None) -> Path:
    """Write cameras (and optionally points) in the JSON format, atomically.

    Parameters
    ----------
    path : path-like
        Output ``.json`` file.
    cameras : sequence of Camera
    points : (N, 3) array_like, optional
    point_camera : (N,) int array_like, optional
        Index of the camera that produced each point (-1: unknown).
    colors : (N, 3) array_like in [0, 1], optional

    Returns
    -------
    Path
    """
    from o3drbf.io.files import atomic_path

    path = Path(path)
    if path.suffix.lower() != ".json":
        raise ValueError(f"camera file {str(path)!r} must end in .json")
    cams = list(cameras)
    if not cams or not all(isinstance(c, Camera) for c in cams):
        raise ValueError("cameras must be a non-empty sequence of Camera")
    data: dict = {"cameras": [c.to_dict() for c in cams]}
    if points is not None:
        pts = as_points(points)
        data["points"] = pts.tolist()
        if colors is not None:
            col = np.asarray(colors, dtype=float)
            if col.shape != pts.shape:
                raise ValueError(f"colors must have shape {pts.shape}, got {col.shape}")
            data["colors"] = col.tolist()
        if point_camera is not None:
            pc = _point_camera(_Where(path), point_camera, len(pts), len(cams))
            data["point_camera"] = pc.tolist()
    elif point_camera is not None:
        raise ValueError("point_camera given without points")
    def verify(tmp):  # read back before the rename: a short write would not parse
        try:
            json.loads(Path(tmp).read_text(encoding="utf-8"))
        except (ValueError, OSError) as exc:
            raise OSError(f"cannot write {path}: the file read back is not valid JSON ({exc}); nothing was written") from None

    with atomic_path(path, verify=verify) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(data, fh)
    return path


# -- Middlebury -------------------------------------------------------------


def _image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an image file from its header (Pillow, lazy: no pixels decoded), or None if unknown."""
    if not path.is_file():
        return None
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, ValueError):  # unreadable, or not an image format Pillow knows
        return None


def _load_middlebury(path: Path, image_size=None) -> CameraSet:
    w = _Where(path)
    lines = [(i + 1, s.split()) for i, s in enumerate(_read_lines(path)) if s.strip()]
    if not lines:
        raise w.error(None, "empty file; expected the image count on line 1")
    lineno, first = lines[0]
    if len(first) != 1 or not first[0].isdigit():
        raise w.error(f"line {lineno}", f"expected the image count, got {' '.join(first)!r}")
    count = int(first[0])
    cameras = []
    for lineno, tok in lines[1:]:
        where = f"line {lineno}"
        if len(tok) != 22:
            raise w.error(where, f"expected 'imgname k11..k33 r11..r33 t1 t2 t3' (22 fields), got {len(tok)}")
        v = w.floats(tok[1:], where, f"calibration of {tok[0]}")
        size = image_size or _image_size(path.parent / tok[0])
        try:
            cameras.append(
                Camera(
                    K=v[:9].reshape(3, 3),
                    R=v[9:18].reshape(3, 3),
                    t=v[18:21],
                    width=None if size is None else size[0],
                    height=None if size is None else size[1],
                    name=tok[0],
                )
            )
        except ValueError as exc:
            raise w.error(where, f"{tok[0]}: {exc}") from None
    if len(cameras) != count:
        raise w.error(None, f"line 1 announces {count} images but the file has {len(cameras)} calibration lines (count mismatch)")
    return CameraSet(cameras, source=str(path), format="middlebury")


# -- COLMAP -----------------------------------------------------------------

# Leading parameters of COLMAP camera models: one focal length or two.
_COLMAP_ONE_FOCAL = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"}
_COLMAP_TWO_FOCAL = {"PINHOLE", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV", "FOV", "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE"}


def _content_lines(path: Path):
    """(line number, text) of lines that are not comments, blanks kept."""
    return [(i + 1, s) for i, s in enumerate(_read_lines(path)) if not s.lstrip().startswith("#")]


def _load_colmap(folder: Path) -> CameraSet:
    files = {name: folder / name for name in ("cameras.txt", "images.txt", "points3D.txt")}
    for name in ("cameras.txt", "images.txt"):
        if not files[name].is_file():
            raise ValueError(f"{folder}: not a COLMAP text model: {name} is missing")
    # cameras.txt: CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]
    w = _Where(files["cameras.txt"])
    intrinsics = {}
    for lineno, s in _content_lines(files["cameras.txt"]):
        tok = s.split()
        if not tok:
            continue
        where = f"line {lineno}"
        if len(tok) < 5:
            raise w.error(where, f"expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got {s.strip()!r}")
        model = tok[1].upper()
        if model in _COLMAP_ONE_FOCAL:
            need = 3
        elif model in _COLMAP_TWO_FOCAL:
            need = 4
        else:
            raise w.error(where, f"unknown camera model {tok[1]!r}")
        v = w.floats(tok[2:], where, f"camera {tok[0]}")
        if len(v) < 2 + need:
            raise w.error(where, f"model {model} needs at least {need} parameters, got {len(v) - 2}")
        if need == 3:
            fx = fy = v[2]
            cx, cy = v[3], v[4]
        else:
            fx, fy, cx, cy = v[2:6]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        if tok[0] in intrinsics:
            raise w.error(where, f"camera id {tok[0]} appears twice")
        intrinsics[tok[0]] = (K, int(v[0]), int(v[1]))
    # images.txt: two lines per image; the second (2-D points) may be empty.
    w = _Where(files["images.txt"])
    lines = _content_lines(files["images.txt"])
    cameras, image_index = [], {}
    i = 0
    while i < len(lines):
        lineno, s = lines[i]
        tok = s.split()
        if not tok:
            i += 1
            continue
        where = f"line {lineno}"
        if len(tok) < 10:
            raise w.error(where, f"expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got {s.strip()!r}")
        v = w.floats(tok[1:8], where, f"image {tok[0]} pose")
        if tok[8] not in intrinsics:
            raise w.error(where, f"image {tok[0]} refers to camera {tok[8]}, which cameras.txt does not define")
        K, width, height = intrinsics[tok[8]]
        try:
            qw, qx, qy, qz = _unit_quaternion(v[:4])
            cam = Camera(K=K, R=quaternion_to_matrix(qx, qy, qz, qw), t=v[4:7], width=width, height=height, name=" ".join(tok[9:]))
        except ValueError as exc:
            raise w.error(where, f"image {tok[0]}: {exc}") from None
        if tok[0] in image_index:
            raise w.error(where, f"image id {tok[0]} appears twice")
        image_index[tok[0]] = len(cameras)
        cameras.append(cam)
        i += 2  # skip the 2-D points line
    if not cameras:
        raise w.error(None, "no image is registered")
    points = colors = observations = None
    if files["points3D.txt"].is_file():
        # POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)
        w = _Where(files["points3D.txt"])
        pts, cols, obs = [], [], []
        for lineno, s in _content_lines(files["points3D.txt"]):
            tok = s.split()
            if not tok:
                continue
            where = f"line {lineno}"
            if len(tok) < 8 or (len(tok) - 8) % 2:
                raise w.error(where, f"expected 'POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)...', got {s.strip()!r}")
            v = w.floats(tok[1:7], where, f"point {tok[0]}")
            for image_id in tok[8::2]:
                if image_id not in image_index:
                    raise w.error(where, f"point {tok[0]} is seen by image {image_id}, which images.txt does not define")
                obs.append((len(pts), image_index[image_id]))
            pts.append(v[:3])
            cols.append(v[3:6] / 255.0)
        if pts:
            points, colors = np.array(pts), np.array(cols)
            observations = np.array(obs, dtype=np.int64).reshape(-1, 2)
    return CameraSet(cameras, points, colors, None, observations, str(folder), "colmap")


# -- Bundler ----------------------------------------------------------------


def _load_bundler(path: Path, image_size=None) -> CameraSet:
    """Bundler v0.3: cameras look along -z with y up; image origin at the centre, y up."""
    w = _Where(path)
    lines = [(i + 1, s.split()) for i, s in enumerate(_read_lines(path)) if s.strip() and not s.lstrip().startswith("#")]
    pos = 0

    def take(n_fields, what):
        nonlocal pos
        if pos >= len(lines):
            raise w.error(None, f"file ends early: expected {what}")
        lineno, tok = lines[pos]
        pos += 1
        if n_fields is not None and len(tok) != n_fields:
            raise w.error(f"line {lineno}", f"{what}: expected {n_fields} numbers, got {' '.join(tok)!r}")
        return lineno, w.floats(tok, f"line {lineno}", what)

    lineno, head = take(2, "'num_cameras num_points'")
    if (head != np.round(head)).any() or (head < 0).any():
        raise w.error(f"line {lineno}", f"expected two counts, got {head.tolist()}")
    n_cams, n_pts = int(head[0]), int(head[1])
    # each camera takes 5 lines and each point 3: bound the counts by the file before allocating
    if 5 * n_cams + 3 * n_pts > len(lines) - pos:
        raise w.error(
            None,
            f"file ends early: the header (line {lineno}) announces {n_cams:,} cameras and {n_pts:,} points "
            f"but only {len(lines) - pos:,} lines follow (truncated file or corrupt header)",
        )
    names = None
    for candidate in (path.parent / "list.txt", path.parent.parent / "list.txt"):
        if candidate.is_file():
            names = [s.split()[0] for s in _read_lines(candidate) if s.strip()]
            if len(names) != n_cams:
                raise ValueError(f"{candidate}: lists {len(names)} images but {path} has {n_cams} cameras (count mismatch)")
            break
    cameras, index = [], np.full(n_cams, -1)
    for c in range(n_cams):
        lineno, (f, _k1, _k2) = take(3, f"camera {c}: 'f k1 k2'")
        rows = [take(3, f"camera {c}: rotation row {r + 1}")[1] for r in range(3)]
        lt, t = take(3, f"camera {c}: translation")
        Rb = np.array(rows)
        if f == 0 and not Rb.any():
            continue  # not registered by Bundler
        name = names[c] if names else f"camera {c}"
        size = image_size
        if size is None and names:
            size = _image_size(path.parent / names[c]) or _image_size(path.parent.parent / names[c])
        cx, cy = (0.0, 0.0) if size is None else (size[0] / 2.0, size[1] / 2.0)
        try:
            cam = Camera(
                K=np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]),
                R=_FLIP @ Rb,
                t=_FLIP @ t,
                width=None if size is None else size[0],
                height=None if size is None else size[1],
                name=name,
            )
        except ValueError as exc:
            raise w.error(f"lines {lineno}-{lt}", f"camera {c}: {exc}") from None
        index[c] = len(cameras)
        cameras.append(cam)
    if not cameras:
        raise w.error(None, "no camera is registered (all are zero)")
    pts, cols, obs = [], [], []
    for p in range(n_pts):
        pts.append(take(3, f"point {p}: position")[1])
        cols.append(take(3, f"point {p}: colour")[1] / 255.0)
        lineno, views = take(None, f"point {p}: view list")
        n = int(views[0]) if len(views) else -1
        if n < 0 or len(views) != 1 + 4 * n:
            raise w.error(f"line {lineno}", f"point {p}: view list must be 'n (camera key x y) * n'")
        for cam in views[1::4].astype(int):
            if not 0 <= cam < n_cams or index[cam] < 0:
                raise w.error(f"line {lineno}", f"point {p} is seen by camera {cam}, which is missing or unregistered")
            obs.append((p, index[cam]))
    if pos != len(lines):
        raise w.error(f"line {lines[pos][0]}", f"unexpected data after {n_cams} cameras and {n_pts} points (count mismatch)")
    points = np.array(pts).reshape(-1, 3) if n_pts else None
    return CameraSet(
        cameras,
        points,
        np.array(cols).reshape(-1, 3) if n_pts else None,
        None,
        np.array(obs, dtype=np.int64).reshape(-1, 2) if n_pts else None,
        str(path),
        "bundler",
    )


# -- Stanford .conf -----------------------------------------------------------


def _load_stanford(path: Path, read_scans: bool) -> CameraSet:
    """``bmesh file tx ty tz qx qy qz qw``: ``p_world = R(q)^T p_scan + t``.

    The scanner looks along -z of each scan frame; the ``camera`` line is a
    viewer camera and is skipped.
    """
    w = _Where(path)
    cameras, files = [], []
    for lineno, s in enumerate(_read_lines(path), start=1):
        tok = s.split()
        if not tok or tok[0].startswith("#") or tok[0] == "camera":
            continue
        where = f"line {lineno}"
        if tok[0] not in ("bmesh", "mesh"):
            raise w.error(where, f"unknown keyword {tok[0]!r}; expected 'bmesh file tx ty tz qx qy qz qw'")
        if len(tok) != 9:
            raise w.error(where, f"expected 'bmesh file tx ty tz qx qy qz qw' (9 fields), got {len(tok)}")
        v = w.floats(tok[2:], where, f"pose of {tok[1]}")
        try:
            q = _unit_quaternion(v[3:])
        except ValueError as exc:
            raise w.error(where, f"{tok[1]}: {exc}") from None
        Rq = quaternion_to_matrix(*q)
        # scan frame: p_scan = Rq (p_world - t); flip it to look along +z.
        cameras.append(Camera(R=_FLIP @ Rq, t=-_FLIP @ Rq @ v[:3], kind="direction", name=tok[1]))
        files.append((lineno, path.parent / tok[1]))
    if not cameras:
        raise w.error(None, "no 'bmesh' line: the file lists no scan")
    for lineno, f in files:
        if not f.is_file():
            raise w.error(f"line {lineno}", f"scan file {f.name} not found beside the .conf (count mismatch between the .conf and its scans)")
    if not read_scans:
        return CameraSet(cameras, source=str(path), format="stanford")
    from o3drbf.io.files import read_points

    parts, owner = [], []
    for c, ((lineno, f), cam) in enumerate(zip(files, cameras)):
        try:
            p, _, _ = read_points(f)
        except ValueError as exc:
            raise w.error(f"line {lineno}", str(exc)) from None
        # p_world = R(q)^T p_scan + t, and p_scan = FLIP x_cam.
        parts.append((p @ _FLIP) @ cam.R + cam.center)
        owner.append(np.full(len(p), c, dtype=np.int64))
    return CameraSet(cameras, np.concatenate(parts), None, np.concatenate(owner), None, str(path), "stanford")


# -- detection ----------------------------------------------------------------

_FORMATS_HELP = (
    "a .json camera file, a Middlebury *_par.txt, a COLMAP text model folder (cameras.txt, images.txt), "
    "a Bundler bundle.out, a Stanford .conf, or an E57 file with scan poses"
)


def _detect(path: Path) -> tuple[str, Path]:
    if path.is_dir():
        for sub in (path, path / "sparse", path / "sparse" / "0"):
            if (sub / "cameras.txt").is_file() and (sub / "images.txt").is_file():
                return "colmap", sub
        for rel in ("bundle.out", "bundle/bundle.out"):
            if (path / rel).is_file():
                return "bundler", path / rel
        for pattern, kind in (("*.conf", "stanford"), ("*_par.txt", "middlebury")):
            found = sorted(path.glob(pattern))
            if len(found) == 1:
                return kind, found[0]
            if len(found) > 1:
                raise ValueError(f"{path}: several {pattern} files ({', '.join(f.name for f in found)}); name one")
        raise ValueError(f"{path}: no camera file found; expected {_FORMATS_HELP}")
    if not path.exists():
        raise FileNotFoundError(f"camera file not found: {path}")
    name = path.name.lower()
    if name.endswith(".json"):
        return "json", path
    if name.endswith(".conf"):
        return "stanford", path
    if name.endswith(".e57"):
        return "e57", path
    if name in ("cameras.txt", "images.txt", "points3d.txt"):
        return "colmap", path.parent
    if name.endswith("_par.txt"):
        return "middlebury", path
    with open(path, "rb") as fh:
        head = fh.read(4096).decode("utf-8", errors="replace")
    if name.endswith(".out") or head.startswith("# Bundle file"):
        return "bundler", path
    lines = [s.split() for s in head.splitlines() if s.strip()]
    if len(lines) >= 2 and len(lines[0]) == 1 and lines[0][0].isdigit() and len(lines[1]) == 22:
        return "middlebury", path
    raise ValueError(f"cannot tell the camera format of {path}; expected {_FORMATS_HELP}")


def load_cameras(path: str | os.PathLike, image_size: tuple[int, int] | None = None, read_scans: bool = False) -> CameraSet:
    """Read cameras from a file or folder, detecting the format.

    Parameters
    ----------
    path : path-like
        A ``.json`` file, a Middlebury ``*_par.txt``, a COLMAP text model
        folder (or one of its files; ``sparse/0`` is searched too), a Bundler
        ``bundle.out`` (or its folder), a Stanford ``.conf``, or an ``.e57``
        file (its scans' poses and points, :func:`o3drbf.cameras.lidar.load_e57`).
    image_size : (int, int), optional
        ``(width, height)`` for formats that do not store it (Middlebury,
        Bundler) when the images are not beside the file.  Without it the
        image size is read from the images if present, else left unbounded.
        Bundler's principal point is the image centre, so without a size
        the image coordinates are centred.
    read_scans : bool
        Stanford ``.conf`` only: also read the scans (see
        :func:`load_range_scans`).

    Returns
    -------
    CameraSet
        The cameras, with ``points``/``colors``/``observations`` for COLMAP
        and Bundler, ``points``/``point_camera`` for JSON files that have
        them and for Stanford scans with ``read_scans``.

    Raises
    ------
    FileNotFoundError
        The path does not exist.
    ValueError
        Unknown format or malformed content; the message names the file and
        the line or entry.
    """
    path = Path(path)
    if image_size is not None:
        if len(image_size) != 2:
            raise ValueError(f"image_size must be (width, height), got {image_size!r}")
        image_size = tuple(check_number(n, v, low=1, integer=True) for n, v in zip(("width", "height"), image_size))
    kind, target = _detect(path)
    if kind == "json":
        return _load_json(target)
    if kind == "middlebury":
        return _load_middlebury(target, image_size)
    if kind == "colmap":
        return _load_colmap(target)
    if kind == "bundler":
        return _load_bundler(target, image_size)
    if kind == "e57":
        from o3drbf.cameras.lidar import load_e57

        return load_e57(target)
    return _load_stanford(target, read_scans)


def referenced_files(path: str | os.PathLike) -> list[Path]:
    """Files an input refers to, which an output must never overwrite.

    The scans of a Stanford ``.conf``, the images of a Middlebury
    calibration or a Bundler ``list.txt``, and the files of a COLMAP text
    model.  Other inputs refer to nothing.  Reading is cheap (no scan or
    image is opened).

    Parameters
    ----------
    path : path-like

    Returns
    -------
    list of Path
        Existing or not; empty when ``path`` cannot be read as a camera file.
    """
    path = Path(path)
    if not path.exists():
        return []
    try:
        kind, target = _detect(path)
    except ValueError:
        return []
    out: list[Path] = []
    if kind == "stanford":
        for s in _read_lines(target):
            tok = s.split()
            if len(tok) >= 2 and tok[0] in ("bmesh", "mesh"):
                out.append(target.parent / tok[1])
    elif kind == "middlebury":
        for s in _read_lines(target)[1:]:
            tok = s.split()
            if tok:
                out.append(target.parent / tok[0])
    elif kind == "colmap":
        out += [target / n for n in ("cameras.txt", "images.txt", "points3D.txt")]
    elif kind == "bundler":
        for candidate in (target.parent / "list.txt", target.parent.parent / "list.txt"):
            if candidate.is_file():
                out.append(candidate)
                for s in _read_lines(candidate):
                    if s.strip():
                        name = s.split()[0]
                        out += [candidate.parent / name, target.parent / name]
                break
        out.append(target)
    elif kind in ("json", "e57"):
        out.append(target)
    return out


def load_range_scans(conf_path: str | os.PathLike) -> CameraSet:
    """Read a Stanford ``.conf`` and all its scans, in world coordinates.

    Parameters
    ----------
    conf_path : path-like
        The ``.conf`` file; the scans (PLY) are beside it.

    Returns
    -------
    CameraSet
        One ``"direction"`` sensor per scan (looking along the scan's local
        -z), ``points`` (N, 3) of all scans in world coordinates and
        ``point_camera`` (N,) the index of the scan each point came from.
    """
    path = Path(conf_path)
    if path.is_dir():
        kind, path = _detect(path)
        if kind != "stanford":
            raise ValueError(f"{conf_path}: no .conf file in the folder")
    elif not path.exists():
        raise FileNotFoundError(f"scan configuration not found: {path}")
    return _load_stanford(path, read_scans=True)


def _register_referenced_files() -> None:
    from o3drbf.io import files

    if referenced_files not in files.REFERENCED_FILES:
        files.REFERENCED_FILES.append(referenced_files)


_register_referenced_files()
