"""Input checks shared by every public entry point.

Each check raises :class:`ValueError` naming the argument, the bad value and
what would be valid, so that bad input never crashes deep inside NumPy.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["as_points", "as_vectors", "as_rgb", "check_number", "per_point", "check_choice", "shown"]


def shown(value: Any, digits: int = 6) -> str:
    """A value as a message shows it: numbers to at most ``digits`` significant digits, no NumPy wrappers.

    ``shown(np.float64(2.912149660512057))`` is ``"2.91215"``, ``shown(0.5)``
    ``"0.5"``, ``shown(np.array([1.0, 2.25]))`` ``"[1.0, 2.25]"``; anything
    else is its ``repr`` (strings keep their quotes).

    Parameters
    ----------
    value : Any
        A number (Python or NumPy scalar), a sequence or array of them, or anything.
    digits : int
        Significant digits kept.

    Returns
    -------
    str
    """
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool) or isinstance(value, int):
        return repr(value)
    if isinstance(value, float):
        short = format(value, f".{digits}g")
        return repr(value) if not math.isfinite(value) or float(short) == value else short
    if isinstance(value, (list, tuple)):
        inner = ", ".join(shown(v, digits) for v in value)
        return f"({inner},)" if isinstance(value, tuple) and len(value) == 1 else (f"({inner})" if isinstance(value, tuple) else f"[{inner}]")
    return repr(value)


def as_points(points: Any, name: str = "points", min_count: int = 1, allow_duplicates: bool = True) -> np.ndarray:
    """Coerce to a C-contiguous ``(N, 3)`` float64 array of finite points.

    Accepts array-likes and Open3D ``PointCloud`` objects.

    Raises
    ------
    ValueError
        Wrong shape, fewer than ``min_count`` points, non-finite values, or
        (with ``allow_duplicates=False``) repeated points.
    """
    if hasattr(points, "points") and not isinstance(points, np.ndarray):
        points = np.asarray(points.points)
    try:
        arr = np.asarray(points, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an (N, 3) array of numbers: {exc}") from None
    if arr.ndim == 1 and arr.size == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if arr.shape[0] < min_count:
        what = "is empty" if arr.shape[0] == 0 else f"has {arr.shape[0]} point(s)"
        raise ValueError(f"{name} {what}; at least {min_count} needed")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise ValueError(
            f"{name} has {idx.size} row(s) with NaN or infinite coordinates (first at index {idx[0]}: {shown(arr[idx[0]])})"
        )
    if not allow_duplicates:
        _, first, counts = np.unique(arr, axis=0, return_index=True, return_counts=True)
        if (counts > 1).any():
            k = int((counts > 1).sum())
            i = int(first[np.argmax(counts > 1)])
            raise ValueError(f"{name} has {k} duplicated point(s) (e.g. {shown(arr[i])} at index {i}); remove duplicates first")
    return np.ascontiguousarray(arr)


def as_vectors(vectors: Any, n: int, name: str = "normals", unit: bool = True) -> np.ndarray:
    """Coerce to ``(n, 3)`` finite vectors, normalized to unit length if ``unit``."""
    arr = as_points(vectors, name=name, min_count=0)
    if arr.shape[0] != n:
        raise ValueError(f"{name} must have one row per point: expected ({n}, 3), got {arr.shape}")
    if unit:
        norm = np.linalg.norm(arr, axis=1)
        if (norm == 0).any():
            i = int(np.flatnonzero(norm == 0)[0])
            raise ValueError(f"{name} has zero-length vector(s) (first at index {i}); normals must be non-zero")
        arr = arr / norm[:, None]
    return arr


def check_number(
    name: str,
    value: Any,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    integer: bool = False,
) -> float:
    """Check a scalar parameter is a finite number in ``[low, high]`` (``(low, high]`` if ``low_open``)."""
    lo = "-inf" if low is None else shown(low)
    hi = "inf" if high is None else shown(high)
    valid = f"{'(' if low_open else '['}{lo}, {hi}]"
    if isinstance(value, bool):
        raise ValueError(f"{name} must be a number in {valid}, got {shown(value)}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number in {valid}, got {shown(value)}") from None
    if not math.isfinite(x) or (low is not None and (x < low or (low_open and x == low))) or (high is not None and x > high):
        raise ValueError(f"{name} must be in {valid}, got {shown(value)}")
    if integer:
        if x != int(x):
            raise ValueError(f"{name} must be a whole number in {valid}, got {shown(value)}")
        return int(x)
    return x


def per_point(name: str, value: Any, n: int, low: float = 0.0) -> np.ndarray:
    """Broadcast a scalar or check a length-``n`` array of values ``>= low``."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        check_number(name, float(arr), low=low)
        return np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f"{name} must be a scalar or have shape ({n},), got {arr.shape}")
    bad = ~np.isfinite(arr) | (arr < low)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name} must be finite and >= {shown(low)}; entry {i} is {shown(arr[i])}")
    return arr


def check_choice(name: str, value: Any, choices) -> str:
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, choices))}, got {shown(value)}")
    return value


def as_rgb(image: Any, name: str = "image", dtype: Any = np.float64) -> np.ndarray:
    """Coerce an image to ``(H, W, 3)`` RGB in ``[0, 1]``: the one rule for image arrays.

    Parameters
    ----------
    image : (H, W, 3), (H, W, 4) or (H, W) array_like
        RGB, RGBA (alpha dropped) or grey (repeated into three channels).
        Integers (``uint8``, ``uint16``, ...) are divided by their dtype's
        maximum; floats must already lie in ``[0, 1]``.
    name : str
        What to call the image in error messages.
    dtype : numpy float dtype
        Of the result (``float32`` halves the memory of large photographs).

    Returns
    -------
    (H, W, 3) array of ``dtype``

    Raises
    ------
    ValueError
        Another shape, an empty image, a boolean or non-numeric dtype,
        negative integers, or floats that are not finite or outside ``[0, 1]``.
    """
    a = np.asarray(image)
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4) or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"{name}: expected an (H, W, 3) colour, (H, W, 4) RGBA or (H, W) grey image, got shape {a.shape}")
    a = a[:, :, :3]
    if a.dtype != bool and np.issubdtype(a.dtype, np.integer):
        if np.issubdtype(a.dtype, np.signedinteger) and a.min() < 0:
            raise ValueError(f"{name}: negative integer pixel values; give unsigned integers or floats in [0, 1]")
        return a.astype(dtype) / np.asarray(np.iinfo(a.dtype).max, dtype=dtype)
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"{name} has dtype {a.dtype}; expected unsigned integers (uint8, uint16) or floats in [0, 1]")
    a = a.astype(dtype)
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: NaN or infinite pixel values")
    if a.min() < 0 or a.max() > 1:
        raise ValueError(f"{name}: float pixel values outside [0, 1] (range [{a.min():.3g}, {a.max():.3g}]); scale them to [0, 1] or give uint8")
    return a
