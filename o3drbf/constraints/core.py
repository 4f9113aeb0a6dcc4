"""Constraints: where f is pinned, to what value, and how firmly.

Surface points get f = 0, exterior points f = -1 (and optional interior
points f = +1), each with its own smoothing lambda.  Builders here work in the
normalized 2x2x2 box; camera-based exterior constraints are in
:mod:`o3drbf.constraints.visibility`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.validation import as_points, as_vectors, check_number, per_point
from o3drbf.prep.sampling import fibonacci_sphere, poisson_disc

__all__ = [
    "SURFACE",
    "EXTERIOR",
    "INTERIOR",
    "SPHERE",
    "KIND_NAMES",
    "Constraints",
    "surface_constraints",
    "exterior_from_normals",
    "bounding_sphere",
]

SURFACE, EXTERIOR, INTERIOR, SPHERE = 0, 1, 2, 3
KIND_NAMES = {SURFACE: "surface", EXTERIOR: "exterior", INTERIOR: "interior", SPHERE: "sphere"}
#: Target value of f for each kind of constraint.
KIND_VALUES = {SURFACE: 0.0, EXTERIOR: -1.0, INTERIOR: 1.0, SPHERE: -1.0}


@dataclass(frozen=True)
class Constraints:
    """A set of constraints: ``f(points[i]) ~ values[i]`` with smoothing ``smoothing[i]``.

    Attributes
    ----------
    points : (M, 3) array
    values : (M,) array
    smoothing : (M,) array
        lambda_i >= 0.
    kind : (M,) int8 array
        SURFACE, EXTERIOR, INTERIOR or SPHERE.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf import Constraints
    >>> from o3drbf.constraints.core import EXTERIOR, SURFACE
    >>> on = Constraints.of_kind(np.zeros((3, 3)), SURFACE, 1e-4)
    >>> off = Constraints.of_kind(np.ones((2, 3)), EXTERIOR, 1e-2)
    >>> both = Constraints.concat(on, off)
    >>> both.values.tolist(), both.counts()['exterior']
    ([0.0, 0.0, 0.0, -1.0, -1.0], 2)
    """

    points: np.ndarray
    values: np.ndarray
    smoothing: np.ndarray
    kind: np.ndarray

    def __post_init__(self):
        n = len(self.points)
        for name in ("values", "smoothing", "kind"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"constraints: {name} has {len(getattr(self, name))} entries for {n} points")

    @classmethod
    def of_kind(cls, points, kind: int, smoothing) -> "Constraints":
        pts = as_points(points, min_count=0)
        n = len(pts)
        return cls(pts, np.full(n, KIND_VALUES[kind]), per_point("smoothing", smoothing, n), np.full(n, kind, np.int8))

    @classmethod
    def concat(cls, *parts: "Constraints") -> "Constraints":
        return cls(
            np.concatenate([p.points for p in parts]).reshape(-1, 3),
            np.concatenate([p.values for p in parts]),
            np.concatenate([p.smoothing for p in parts]),
            np.concatenate([p.kind for p in parts]).astype(np.int8),
        )

    def __len__(self) -> int:
        return len(self.points)

    def select(self, kind: int) -> np.ndarray:
        """The points of one kind."""
        return self.points[self.kind == kind]

    def counts(self) -> dict[str, int]:
        return {name: int((self.kind == k).sum()) for k, name in KIND_NAMES.items()}


def surface_constraints(points, count: int | None = 3000, radius: float | None = None, seed: int = 0) -> np.ndarray:
    """Indices of the surface constraints: a Poisson-disc subset of the points.

    ``count=None`` and ``radius=None`` keep every point.
    """
    pts = as_points(points)
    if count is None and radius is None:
        return np.arange(len(pts))
    if count is not None:
        count = check_number("surface_count", count, low=1, integer=True)
    return poisson_disc(pts, count=count, radius=radius, seed=seed)


def exterior_from_normals(
    points,
    normals,
    offset: float,
    count: int,
    seed: int = 0,
    reference=None,
) -> np.ndarray:
    """Exterior points ``p + offset * n`` at a uniform (Poisson-disc) subset of the points.

    Candidates that land closer than ``offset / 2`` to any reference point
    (default: ``points``) are dropped: they would sit inside a thin part or
    across a narrow gap, where f = -1 would be wrong.

    Parameters
    ----------
    points : (N, 3) array_like
    normals : (N, 3) array_like
        Outward normals (normalized here).
    offset : float
        Distance from the surface, > 0 (box units).
    count : int
        About how many exterior points to make (>= 0).
    reference : (K, 3) array_like, optional
        Points that exterior constraints must keep away from (all input points).

    Returns
    -------
    (M, 3) array, M <= count
    """
    pts = as_points(points)
    nrm = as_vectors(normals, len(pts))
    offset = check_number("exterior_offset", offset, low=0.0, low_open=True)
    count = check_number("exterior count", count, low=0, integer=True)
    if count == 0:
        return np.zeros((0, 3))
    idx = poisson_disc(pts, count=count, seed=seed + 1)
    cand = pts[idx] + offset * nrm[idx]
    ref = pts if reference is None else as_points(reference, name="reference")
    d, _ = cKDTree(ref).query(cand, workers=-1)
    return cand[d >= 0.5 * offset]


def bounding_sphere(points, count: int = 64, factor: float = 1.5) -> np.ndarray:
    """``count`` points on a sphere around the points' bounding box, farther out.

    The sphere is centred on the box centre with radius ``factor`` times the
    half diagonal of the bounding box.
    """
    pts = as_points(points)
    count = check_number("sphere count", count, low=0, integer=True)
    factor = check_number("sphere factor", factor, low=1.0, low_open=True)
    if count == 0:
        return np.zeros((0, 3))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    radius = factor * 0.5 * float(np.linalg.norm(hi - lo))
    return fibonacci_sphere(count, radius=max(radius, math.ulp(1.0)), center=(lo + hi) / 2)
