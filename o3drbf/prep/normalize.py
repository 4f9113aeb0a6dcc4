"""Normalization of data into the 2x2x2 box where the method's parameters live."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from o3drbf.validation import as_points, shown

__all__ = ["Normalization", "check_spans_volume", "extent_ratios", "MIN_EXTENT_RATIO"]

#: Smallest ratio of the thinnest to the widest principal extent of a cloud
#: that :func:`check_spans_volume` accepts.
MIN_EXTENT_RATIO = 1e-3


def extent_ratios(points) -> np.ndarray:
    """Principal extents of the points over the largest: ``(3,)``, descending, first 1.

    The extents are the standard deviations along the principal axes
    (singular values of the centred points).
    """
    pts = as_points(points, min_count=2)
    sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    if sv[0] <= 0:
        raise ValueError("points all coincide: their bounding box has zero size, nothing to reconstruct")
    return sv / sv[0]


def check_spans_volume(points, min_ratio: float = MIN_EXTENT_RATIO) -> np.ndarray:
    """Refuse colinear, flat or extremely anisotropic clouds: they enclose no volume.

    Parameters
    ----------
    points : (N, 3) array_like
    min_ratio : float
        Smallest accepted ratio of the thinnest to the widest principal
        extent, in (0, 1).

    Returns
    -------
    (3,) array
        The extent ratios (:func:`extent_ratios`), when the check passes.

    Raises
    ------
    ValueError
        "points span no volume (they lie on a plane/line: extent ratio ...)".
    """
    ratios = extent_ratios(points)
    try:
        min_ratio = float(min_ratio)
    except (TypeError, ValueError):
        raise ValueError(f"min_ratio must be a number in (0, 1), got {shown(min_ratio)}") from None
    if not 0 < min_ratio < 1:
        raise ValueError(f"min_ratio must be in (0, 1), got {shown(min_ratio)}")
    if ratios[2] < min_ratio:
        what = "a line" if ratios[1] < min_ratio else "a plane"
        raise ValueError(
            f"points span no volume (they lie on {what}: extent ratio {ratios[2]:.2g} < {min_ratio:g}, "
            f"principal extents 1 : {ratios[1]:.2g} : {ratios[2]:.2g}); give normals for an open patch, or more views"
        )
    return ratios


@dataclass(frozen=True)
class Normalization:
    """A similarity ``x_box = (x - center) * scale`` mapping data into [-1, 1]^3.

    The longest side of the data's bounding box spans exactly 2 (the box the
    paper's delta, tau and lambda refer to); the other sides are centred.

    Examples
    --------
    >>> from o3drbf import Normalization
    >>> norm = Normalization.from_points([[0.0, 0.0, 0.0], [4.0, 2.0, 1.0]])
    >>> norm.forward([[4.0, 2.0, 1.0]]).tolist(), norm.inverse([[-1.0, -0.5, -0.25]]).tolist()
    ([[1.0, 0.5, 0.25]], [[0.0, 0.0, 0.0]])
    """

    center: np.ndarray
    scale: float

    @classmethod
    def from_points(cls, points) -> "Normalization":
        pts = as_points(points, min_count=2)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        extent = float((hi - lo).max())
        if extent <= 0:
            raise ValueError("points all coincide: their bounding box has zero size, nothing to reconstruct")
        return cls(center=(lo + hi) / 2.0, scale=2.0 / extent)

    @classmethod
    def identity(cls) -> "Normalization":
        return cls(center=np.zeros(3), scale=1.0)

    def forward(self, points) -> np.ndarray:
        """Data coordinates -> box coordinates."""
        return (np.asarray(points, dtype=float) - self.center) * self.scale

    def inverse(self, points) -> np.ndarray:
        """Box coordinates -> data coordinates."""
        return np.asarray(points, dtype=float) / self.scale + self.center

    def to_dict(self) -> dict:
        return {"center": np.asarray(self.center, dtype=float).tolist(), "scale": float(self.scale)}

    @classmethod
    def from_dict(cls, d: dict) -> "Normalization":
        return cls(center=np.asarray(d["center"], dtype=float), scale=float(d["scale"]))
