"""Cameras and sensors: the model every camera file is read into.

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
own frame; :attr:`Camera.direction` is that axis in world coordinates.  A
:class:`CameraSet` is what a camera file holds: the cameras, plus the points
and which cameras saw them when the format has them.

The files are read by :mod:`o3drbf.cameras.formats` (one reader per format,
detected from the path); its public functions :func:`load_cameras`,
:func:`load_range_scans`, :func:`referenced_files` and
:func:`save_cameras_json` can also be imported from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Iterator, Sequence

import numpy as np

from o3drbf.validation import check_choice, check_number

__all__ = [
    "Camera",
    "CameraSet",
    "FLIP",
    "KINDS",
    "as_cameras",
    "load_cameras",
    "load_range_scans",
    "referenced_files",
    "save_cameras_json",
    "quaternion_to_matrix",
    "unit_quaternion",
]

#: The kinds of sensor a :class:`Camera` can be.
KINDS = ("pinhole", "center", "direction")

#: Largest ``|R R^T - I|`` accepted for a rotation read from a file.
ORTHONORMAL_TOLERANCE = 1e-4

#: Flips a frame that looks along -z (Bundler, Stanford scanners) into one that
#: looks along +z with y down (OpenCV): a half turn about x.
FLIP = np.diag([1.0, -1.0, -1.0])


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


def unit_quaternion(q: Sequence[float], tolerance: float = 1e-3) -> np.ndarray:
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

    Examples
    --------
    >>> from o3drbf.cameras.model import Camera
    >>> camera = Camera.look_at(eye=(0.0, -3.0, 0.0), target=(0.0, 0.0, 0.0), width=64, height=48)
    >>> camera.center.round(6).tolist(), bool(camera.in_view([[0.0, 0.0, 0.0]])[0])
    ([0.0, -3.0, 0.0], True)
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



#: The camera files' functions, defined in :mod:`o3drbf.cameras.formats` (which reads files into this model).
_FILE_FUNCTIONS = ("load_cameras", "load_range_scans", "referenced_files", "save_cameras_json")


def __getattr__(name: str):
    """``from o3drbf.cameras.model import load_cameras`` keeps working: the file functions, imported on first use."""
    if name in _FILE_FUNCTIONS:
        from o3drbf.cameras import formats

        return getattr(formats, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
