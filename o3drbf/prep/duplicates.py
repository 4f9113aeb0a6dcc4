"""Exact duplicate points, merged.

Real scans repeat points (overlapping range images, re-exported clouds).  Two
surface constraints at the same place make the interpolation matrix singular
(two identical rows) when lambda is 0, and double the weight of that place
otherwise; merging them first removes both problems.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from o3drbf.validation import as_points

__all__ = ["merge_duplicates"]


def merge_duplicates(points: Any, *per_point: Any, average: bool = True) -> tuple:
    """Merge exactly repeated points, keeping the first occurrence's order.

    Parameters
    ----------
    points : (N, 3) array
    *per_point : (N, ...) arrays or None
        Data attached to each point (normals, colours, camera index...).
        ``None`` is passed through.
    average : bool
        Floating-point per-point data of merged points is averaged (normals
        are renormalized when the input rows were unit length); integer and
        boolean data keep the first occurrence's value.  With
        ``average=False`` every array keeps the first occurrence.

    Returns
    -------
    points : (M, 3) array
        The distinct points, in order of first occurrence.
    *arrays : (M, ...) arrays or None
        Each ``per_point`` array merged alike.
    merged_count : int
        ``N - M``, the number of rows removed.

    Raises
    ------
    ValueError
        Non-finite points, or a per-point array whose length is not N.
    """
    pts = as_points(points, min_count=0)
    n = len(pts)
    arrays = []
    for k, a in enumerate(per_point):
        if a is None:
            arrays.append(None)
            continue
        a = np.asarray(a)
        if a.shape[:1] != (n,):
            raise ValueError(f"per-point array {k} has {a.shape[0] if a.ndim else 0} rows for {n} points; give one row per point")
        arrays.append(a)
    if n == 0:
        return (pts, *arrays, 0)
    # exact duplicates: identical bit patterns (-0.0 and 0.0 are the same point)
    key = np.ascontiguousarray(pts + 0.0)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    merged = n - len(first)
    if merged == 0:
        return (pts, *arrays, 0)
    order = np.argsort(first, kind="stable")  # groups in order of first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    group = rank[inverse]  # group index of each input row, groups numbered by first occurrence
    keep = np.sort(first)
    counts = np.bincount(group, minlength=len(keep)).astype(float)
    out = []
    for a in arrays:
        if a is None:
            out.append(None)
            continue
        if average and np.issubdtype(a.dtype, np.floating):
            flat = a.reshape(n, -1).astype(float)
            sums = np.zeros((len(keep), flat.shape[1]))
            np.add.at(sums, group, flat)
            mean = sums / counts[:, None]
            if flat.shape[1] == 3 and np.allclose(np.linalg.norm(flat, axis=1), 1.0, atol=1e-6):
                norm = np.linalg.norm(mean, axis=1, keepdims=True)
                # opposite normals at one point average to zero: keep the first one then
                mean = np.where(norm > 1e-12, mean / np.where(norm > 0, norm, 1.0), flat[keep])
            out.append(mean.reshape((len(keep),) + a.shape[1:]).astype(a.dtype, copy=False))
        else:
            out.append(a[keep])
    return (pts[keep], *out, int(merged))
