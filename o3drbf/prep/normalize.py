"""Normalization of data into the 2x2x2 box where the method's parameters live."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from o3drbf.validation import as_points

__all__ = ["Normalization"]


@dataclass(frozen=True)
class Normalization:
    """A similarity ``x_box = (x - center) * scale`` mapping data into [-1, 1]^3.

    The longest side of the data's bounding box spans exactly 2 (the box the
    paper's delta, tau and lambda refer to); the other sides are centred.
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
