"""Free-space consistency: points that a camera proved empty are outliers.

A camera that observed a surface point q along a ray proves the segment from
the camera to q is empty (design-notes.md, "Free-space consistency").  For
each camera j a z-buffer is splatted from the points j saw, with cells of
about one point spacing; a point x that projects into cell u is in j's free
space when

    z_j(x) < Z_j(u) - t

where Z_j(u) is the *smallest*, over u and its eight neighbouring cells, of
the *farthest* depth splatted into a cell.  The farthest depth of a cell
ignores spurious returns in front of the surface along the same rays; the
minimum over the 3 x 3 neighbourhood keeps depth edges (silhouettes) from
putting the foreground into the background's free space, and an empty cell
in the neighbourhood makes the test abstain.  Both choices err on the side of
keeping points.

Camera j confirms x when one of the points j saw lies within ``t`` plus one
spacing of x (x itself included when j saw it).  A point is an outlier when
at least ``min_conflicts`` cameras put it in free space and at most
``max_confirmations`` cameras confirm it: a spurious return is confirmed by
its own camera only, a genuine point seen by two cameras survives a stray
conflict.

Cost: one projection per (point, camera), one z-buffer and one KD-tree per
camera: O(N x cameras) apart from the tree queries.  A centre sensor (a
terrestrial scanner) has a spherical image: azimuth and elevation about its
centre, cells of one spacing at the median range, the range as depth; the
azimuth is measured from the mean direction of the points so the seam falls
behind the sensor when they lie to one side.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.constraints.visibility import seen_by
from o3drbf.validation import as_points, as_vectors, check_choice, check_number

__all__ = ["FreeSpaceCheck", "free_space_check", "point_confidence", "seen_by"]

#: Default tolerance t in mean point spacings (and at least 3 noise sigmas).
TOLERANCE_SPACINGS = 2.0
#: Without point_camera: a point is isolated (no surface support) when its
#: SUPPORT_NEIGHBOURS-th neighbour is farther than SUPPORT_SPACINGS spacings.
SUPPORT_NEIGHBOURS = 4
SUPPORT_SPACINGS = 3.0
#: Most cells per z-buffer side (bounds memory for unbounded images).
MAX_CELLS_PER_SIDE = 4096


@dataclass(frozen=True, eq=False)
class FreeSpaceCheck:
    """What :func:`free_space_check` found.

    Attributes
    ----------
    conflicts : (N,) int array
        Cameras whose free space holds each point.
    confirmations : (N,) int array
        Cameras that observed a surface at each point.
    outlier : (N,) bool array
        ``conflicts >= min_conflicts`` and ``confirmations <= max_confirmations``.
    tolerance : float
        The depth tolerance t used (data units).
    spacing : float
        The point spacing used for the z-buffer footprint (data units).
    cameras_used : int
        Cameras that had a z-buffer (blind cameras are skipped).
    reason : str
        One line: what was removed and why.
    parameters : dict
    """

    conflicts: np.ndarray
    confirmations: np.ndarray
    outlier: np.ndarray
    tolerance: float
    spacing: float
    cameras_used: int
    reason: str
    parameters: dict = field(default_factory=dict)

    @property
    def total(self) -> int:
        return int(len(self.outlier))

    @property
    def removed(self) -> int:
        return int(self.outlier.sum())

    @property
    def kept_indices(self) -> np.ndarray:
        """Sorted indices of the points that are not outliers."""
        return np.flatnonzero(~self.outlier)

    def __str__(self) -> str:
        return self.reason


def _camera_list(cameras) -> list:
    from o3drbf.cameras.model import Camera

    cams = [cameras] if isinstance(cameras, Camera) else list(cameras)
    if not cams:
        raise ValueError("cameras is empty; give at least one camera for the free-space check")
    for i, c in enumerate(cams):
        if not isinstance(c, Camera):
            raise ValueError(f"cameras[{i}] is a {type(c).__name__}, not an o3drbf.cameras.model.Camera")
    return cams


def _median_spacing(points: np.ndarray, sample: int = 20_000, seed: int = 0) -> float:
    """Median nearest-neighbour distance (robust to sparse outliers), from a seeded subset."""
    rng = np.random.default_rng(seed)
    q = points if len(points) <= sample else points[rng.choice(len(points), sample, replace=False)]
    d, _ = cKDTree(points).query(q, k=2, workers=-1)
    s = float(np.median(d[:, 1]))
    if not s > 0:
        raise ValueError("points are (mostly) duplicates: their median spacing is zero; remove duplicates first")
    return s


def _image_coordinates(cam, points: np.ndarray):
    """Image-plane coordinates (N, 2), depth (N,), and the image-plane size of one spacing per unit depth (None: constant)."""
    if cam.kind == "center":  # spherical image: (azimuth, elevation) in radians, the range as depth
        angles, depth = cam.spherical(points)
        ok = np.isfinite(angles).all(axis=1)
        if ok.any():  # the seam opposite the points' mean azimuth
            a = angles[ok, 0]
            mean = np.arctan2(np.sin(a).sum(), np.cos(a).sum())
            angles[ok, 0] = np.angle(np.exp(1j * (a - mean)))
        return angles, depth, 1.0
    pix, depth = cam.project(points)
    if cam.kind == "pinhole":
        return pix, depth, 0.5 * (cam.K[0, 0] + cam.K[1, 1])
    return pix, depth, None  # direction sensor: orthographic


def _cell(cam, focal, spacing: float, depth: np.ndarray) -> float:
    """Image cell of one spacing at the median ``depth``: pixels (at least one), radians, or data units."""
    if focal is None:
        return spacing
    size = focal * spacing / float(np.median(depth))
    return size if cam.kind == "center" else max(1.0, size)


def _neighbourhood_min(image: np.ndarray, outside: float) -> np.ndarray:
    """The smallest value of each pixel's 3 x 3 neighbourhood, ``outside`` beyond the edges (what
    ``scipy.ndimage.minimum_filter(image, size=3, mode="constant", cval=outside)`` gives, without
    importing ``scipy.ndimage`` for it)."""
    padded = np.pad(image, 1, constant_values=outside)
    rows, cols = image.shape
    out = padded[1:-1, 1:-1].copy()
    for dy in range(3):
        for dx in range(3):
            np.minimum(out, padded[dy:dy + rows, dx:dx + cols], out=out)
    return out


def _zbuffer_test(cam, points, seen, spacing, tolerance, empty="unknown"):
    """Per point: (in free space of cam (N,) bool, usable bool). ``seen``: (N,) bool, the points cam saw."""
    n = len(points)
    pix, depth, focal = _image_coordinates(cam, points)
    src = seen & (depth > 0) & np.isfinite(pix).all(axis=1)
    if not src.any():
        return np.zeros(n, dtype=bool), False
    cell = _cell(cam, focal, spacing, depth[src])
    front = (depth > 0) & np.isfinite(pix).all(axis=1)
    if cam.kind == "pinhole" and cam.width is not None and cam.height is not None:
        lo = np.zeros(2)
        hi = np.array([cam.width, cam.height], dtype=float)
    else:
        lo = pix[src].min(axis=0) - cell
        hi = pix[src].max(axis=0) + cell
    dims = np.ceil((hi - lo) / cell).astype(np.int64) + 1
    if (dims > MAX_CELLS_PER_SIDE).any():
        cell *= float(dims.max()) / MAX_CELLS_PER_SIDE
        dims = np.ceil((hi - lo) / cell).astype(np.int64) + 1
    ij = np.full((n, 2), -1, dtype=np.int64)
    ij[front] = np.floor((pix[front] - lo) / cell).astype(np.int64)
    inside = front & (ij >= 0).all(axis=1) & (ij < dims).all(axis=1)
    flat = ij[:, 0] * dims[1] + ij[:, 1]
    zfar = np.full(int(dims[0] * dims[1]), -np.inf)
    s = src & inside
    np.maximum.at(zfar, flat[s], depth[s])
    hit = np.isfinite(zfar)
    zfar = zfar.reshape(dims)
    # Smallest farthest depth over the 3 x 3 neighbourhood.
    if empty == "abstain":  # an empty neighbour makes the test abstain
        znear = _neighbourhood_min(zfar, -np.inf).ravel()
    else:  # empty neighbours are ignored; an empty own cell abstains ("unknown") or saw nothing ("free")
        znear = _neighbourhood_min(np.where(np.isfinite(zfar), zfar, np.inf), np.inf).ravel()
        if empty == "unknown":
            znear[~hit] = -np.inf
    free = np.zeros(n, dtype=bool)
    free[inside] = depth[inside] < znear[flat[inside]] - tolerance
    return free, True


def _supported(points: np.ndarray, spacing: float, k: int = SUPPORT_NEIGHBOURS) -> np.ndarray:
    """(N,) bool: the ``k``-th neighbour lies within ``SUPPORT_SPACINGS`` spacings (not an isolated point)."""
    d, _ = cKDTree(points).query(points, k=k + 1, workers=-1)
    return d[:, -1] <= SUPPORT_SPACINGS * spacing


def _first_layer(cam, points: np.ndarray, spacing: float, tolerance: float, supported=None) -> np.ndarray:
    """(N,) bool: points on the first surface ``cam`` sees, without knowing which points it saw.

    Per image cell (one spacing), the nearest depth among supported points
    (not isolated: spurious returns are); a supported point within
    ``tolerance`` of its cell's nearest depth counts as seen.
    """
    n = len(points)
    sup = _supported(points, spacing) if supported is None else supported
    pix, depth, focal = _image_coordinates(cam, points)
    front = (depth > 0) & np.isfinite(pix).all(axis=1)
    if cam.kind == "pinhole" and cam.width is not None and cam.height is not None:
        with np.errstate(invalid="ignore"):
            front &= (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0) & (pix[:, 1] < cam.height)
    use = front & sup
    if not use.any():
        return np.zeros(n, dtype=bool)
    cell = _cell(cam, focal, spacing, depth[use])
    lo = pix[front].min(axis=0)
    ij = np.zeros((n, 2), dtype=np.int64)
    ij[front] = np.floor((pix[front] - lo) / cell).astype(np.int64)
    dims = ij[front].max(axis=0) + 1
    flat = ij[:, 0] * dims[1] + ij[:, 1]
    _, inverse = np.unique(flat[front], return_inverse=True)
    nearest = np.full(inverse.max() + 1, np.inf)
    np.minimum.at(nearest, inverse[use[front]], depth[front][use[front]])
    seen = np.zeros(n, dtype=bool)
    seen[front] = use[front] & (depth[front] <= nearest[inverse] + tolerance)
    return seen


def free_space_check(
    points,
    cameras,
    point_camera=None,
    *,
    tolerance: float | None = None,
    noise: float | None = None,
    spacing: float | None = None,
    min_conflicts: int = 1,
    max_confirmations: int = 1,
    visible=None,
    empty: str = "unknown",
) -> FreeSpaceCheck:
    """Find points that lie in the free space some camera observed.

    Parameters
    ----------
    points : (N, 3) array_like
        All input points (data units), outliers included.
    cameras : sequence of Camera
        The cameras that saw the points (pinhole, direction, or centre
        sensors with their spherical image).
    point_camera : (N,) int array_like or (N, C) bool array_like, optional
        The camera that produced each point (-1 unknown), or which cameras
        saw each point.  The z-buffer of camera j is splatted from the points
        j saw.  Without it (and without ``visible``) camera j is taken to
        see the first layer of supported (non-isolated) points in each image
        cell of one spacing: the nearest such depth plus ``tolerance``.
    tolerance : float, optional
        Depth tolerance t (data units, > 0).  Default: the larger of
        ``TOLERANCE_SPACINGS`` spacings and three ``noise`` sigmas.
    noise : float, optional
        Standard deviation of the noise along the rays (data units), for the
        default tolerance.
    spacing : float, optional
        Point spacing (z-buffer footprint), data units.  Default: the median
        nearest-neighbour distance.
    min_conflicts : int
        Conflicts needed to call a point an outlier (>= 1).
    max_confirmations : int
        Most confirmations an outlier may have (>= 0).
    visible : (N, C) bool array_like, optional
        Precomputed sightings (e.g. from ``visibility``), used when
        ``point_camera`` is None.
    empty : {"unknown", "abstain", "free"}
        What an image cell without any sample means.  "unknown": nothing
        known; a point whose own cell is empty is not tested, empty
        neighbours are ignored.  "abstain": as "unknown", and a point next
        to an empty cell is not tested either (most conservative).  "free": a
        ray that hit nothing (range scans that return every hit; not for
        photographs or scanners that drop returns).

    Returns
    -------
    FreeSpaceCheck
        Per-point ``conflicts``, ``confirmations`` and ``outlier`` mask.

    Raises
    ------
    ValueError
        Bad shapes or parameters, or no camera that can hold a z-buffer.
    """
    pts = as_points(points, min_count=4)
    cams = _camera_list(cameras)
    n, c = len(pts), len(cams)
    check_choice("empty", empty, ("unknown", "abstain", "free"))
    min_conflicts = check_number("min_conflicts", min_conflicts, low=1, integer=True)
    max_confirmations = check_number("max_confirmations", max_confirmations, low=0, integer=True)
    if spacing is None:
        spacing = _median_spacing(pts)
    spacing = check_number("spacing", spacing, low=0.0, low_open=True)
    if noise is not None:
        noise = check_number("noise", noise, low=0.0)
    if tolerance is None:
        tolerance = max(TOLERANCE_SPACINGS * spacing, 3.0 * (noise or 0.0))
    tolerance = check_number("tolerance", tolerance, low=0.0, low_open=True)
    if point_camera is not None:
        seen = seen_by(point_camera, n, c)
        source = "point_camera"
    elif visible is not None:
        seen = seen_by(np.asarray(visible, dtype=bool), n, c)
        source = "visible"
    else:
        seen = np.stack([_first_layer(cam, pts, spacing, tolerance) for cam in cams], axis=1)
        source = "first supported layer"
    conflicts = np.zeros(n, dtype=np.int64)
    confirmations = np.zeros(n, dtype=np.int64)
    radius = tolerance + spacing
    used = 0
    for j, cam in enumerate(cams):
        free, ok = _zbuffer_test(cam, pts, seen[:, j], spacing, tolerance, empty)
        if not ok:
            continue
        used += 1
        conflicts += free
        src = np.flatnonzero(seen[:, j])
        d, _ = cKDTree(pts[src]).query(pts, k=1, distance_upper_bound=radius, workers=-1)
        confirmations += np.isfinite(d)
    if used == 0:
        raise ValueError(
            "no camera can hold a z-buffer (the cameras saw no point); "
            "give the points each camera saw (point_camera), or skip the free-space check"
        )
    outlier = (conflicts >= min_conflicts) & (confirmations <= max_confirmations)
    reason = (
        f"free-space check ({used} of {c} cameras, sightings from {source}): {int(outlier.sum())} of {n} points are in "
        f"the free space of >= {min_conflicts} camera(s) with <= {max_confirmations} confirmation(s) "
        f"(tolerance {tolerance:.3g}, spacing {spacing:.3g})"
    )
    return FreeSpaceCheck(
        conflicts=conflicts,
        confirmations=confirmations,
        outlier=outlier,
        tolerance=float(tolerance),
        spacing=float(spacing),
        cameras_used=used,
        reason=reason,
        parameters={"min_conflicts": min_conflicts, "max_confirmations": max_confirmations, "source": source, "empty": empty},
    )


def point_confidence(
    confirmations,
    points=None,
    normals=None,
    cameras=None,
    point_camera=None,
    *,
    full_confirmations: int = 2,
    floor: float = 0.1,
    min_cos: float = 0.2,
) -> np.ndarray:
    """Per-point trust in (0, 1], to scale smoothing as ``lambda_i = lambda / confidence_i``.

    ``confidence = views * angle`` where

    - ``views = (1 + min(confirmations, full)) / (1 + full)``: a point
      confirmed by ``full_confirmations`` cameras or more gets 1, an
      unconfirmed one ``1 / (1 + full)``;
    - ``angle = max(|cos theta|, min_cos)`` with theta the angle between the
      normal and the ray to the point's camera (the best of its cameras for
      a mask), when ``points``, ``normals``, ``cameras`` and ``point_camera``
      are all given; else 1.  Grazing samples are the least accurate.

    The product is clipped to ``[floor, 1]``.

    Parameters
    ----------
    confirmations : (N,) int array_like
        E.g. ``FreeSpaceCheck.confirmations``.
    points, normals : (N, 3) array_like, optional
    cameras : sequence of Camera, optional
    point_camera : (N,) int array_like or (N, C) bool array_like, optional
    full_confirmations : int
        Confirmations that earn full trust (>= 1).
    floor : float
        Smallest confidence, in (0, 1].
    min_cos : float
        Smallest grazing factor, in (0, 1].

    Returns
    -------
    (N,) float array in [floor, 1]
    """
    conf = np.asarray(confirmations)
    if conf.ndim != 1 or not np.issubdtype(conf.dtype, np.number) or (conf < 0).any():
        raise ValueError(f"confirmations must be a 1-D array of counts >= 0, got shape {conf.shape}")
    n = len(conf)
    full = check_number("full_confirmations", full_confirmations, low=1, integer=True)
    floor = check_number("floor", floor, low=0.0, high=1.0, low_open=True)
    min_cos = check_number("min_cos", min_cos, low=0.0, high=1.0, low_open=True)
    views = (1.0 + np.minimum(conf, full)) / (1.0 + full)
    angle = np.ones(n)
    given = [a is not None for a in (points, normals, cameras, point_camera)]
    if any(given) and not all(given):
        raise ValueError("the grazing-angle factor needs points, normals, cameras and point_camera together; give all four or none")
    if all(given):
        pts = as_points(points)
        if len(pts) != n:
            raise ValueError(f"points has {len(pts)} rows for {n} confirmations")
        nrm = as_vectors(normals, n)
        cams = _camera_list(cameras)
        seen = seen_by(point_camera, n, len(cams))
        best = np.zeros(n)
        for j, cam in enumerate(cams):
            idx = np.flatnonzero(seen[:, j])
            if len(idx):
                d, _ = cam.toward(pts[idx])
                best[idx] = np.maximum(best[idx], np.abs(np.einsum("ij,ij->i", d, nrm[idx])))
        angle = np.where(seen.any(axis=1), np.maximum(best, min_cos), 1.0)
    return np.clip(views * angle, floor, 1.0)
