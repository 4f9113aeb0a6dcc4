"""Compiled cell tests of the narrow band (Numba): which cells of a grid of f values may hold the iso-surface.

:func:`o3drbf.extract.evaluate_grid` refines a grid level by level and evaluates f only at the corners of
cells that cross the level or come close to it; on a 256-cell grid these tests visit 17 million cells,
which NumPy does in several whole-grid passes (a temporary array each) and these loops in one.

A cell is a *candidate* when its eight corner values ``d = f - level`` change sign, or come closer to
zero than ``margin`` times their own spread: ``(min d <= 0 and max d >= 0) or min |d| <= margin (max d - min d)``
(a local Lipschitz test for a surface between the corners).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["candidate_cells", "corners_to_evaluate", "crossing_steps", "nudge_off_zero"]


@njit(cache=True, inline="always")
def _candidate(vals, i, j, k, level, margin):
    d = vals[i, j, k] - level
    mn = d
    mx = d
    am = abs(d)
    for a in range(2):
        for b in range(2):
            for c in range(2):
                d = vals[i + a, j + b, k + c] - level
                mn = min(mn, d)
                mx = max(mx, d)
                am = min(am, abs(d))
    return (mn <= 0 and mx >= 0) or am <= margin * (mx - mn)


@njit(cache=True, parallel=True)
def _candidate_cells(vals, level, margin, out):
    nx, ny, nz = out.shape
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                out[i, j, k] = _candidate(vals, i, j, k, level, margin)


@njit(cache=True)
def _corners_to_evaluate(vals, exact, ci, cj, ck, level, margin):
    nx, ny, nz = vals.shape
    seen = np.zeros((nx - 1, ny - 1, nz - 1), np.bool_)  # zeroed lazily: only the touched pages are ever written
    need = np.zeros((nx, ny, nz), np.bool_)
    out = np.empty(min(64 * len(ci), nx * ny * nz), np.int64)
    n = 0
    for p in range(len(ci)):
        for a in range(2):
            i = ci[p] - a
            if i < 0 or i >= nx - 1:
                continue
            for b in range(2):
                j = cj[p] - b
                if j < 0 or j >= ny - 1:
                    continue
                for c in range(2):
                    k = ck[p] - c
                    if k < 0 or k >= nz - 1 or seen[i, j, k]:
                        continue
                    seen[i, j, k] = True
                    if not _candidate(vals, i, j, k, level, margin):
                        continue
                    for x in range(i, i + 2):
                        for y in range(j, j + 2):
                            for z in range(k, k + 2):
                                if not exact[x, y, z] and not need[x, y, z]:
                                    need[x, y, z] = True
                                    out[n] = (x * ny + y) * nz + z
                                    n += 1
    return np.sort(out[:n])


def candidate_cells(vals: np.ndarray, level: float = 0.0, margin: float = 0.5) -> np.ndarray:
    """The candidate cells (see the module's text) of a grid of values.

    Parameters
    ----------
    vals : (nx, ny, nz) float ndarray
        f at the grid's points.
    level : float
        The iso-level.
    margin : float
        The Lipschitz margin (0: sign changes only).

    Returns
    -------
    (nx - 1, ny - 1, nz - 1) bool ndarray

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.mesh.band import candidate_cells
    >>> x = np.linspace(-1, 1, 5)
    >>> values = np.broadcast_to(x[:, None, None], (5, 5, 5)).copy()  # the plane x = 0 between the second and third cells
    >>> candidate_cells(values, 0.0, 0.0)[:, 0, 0]
    array([False,  True,  True, False])
    """
    vals = np.ascontiguousarray(vals, dtype=float)
    out = np.empty(tuple(max(n - 1, 0) for n in vals.shape), dtype=bool)
    _candidate_cells(vals, float(level), float(margin), out)
    return out


def corners_to_evaluate(vals: np.ndarray, exact: np.ndarray, changed, level: float = 0.0, margin: float = 0.5):
    """The corners not yet exact of the candidate cells among those with a corner in ``changed``.

    Parameters
    ----------
    vals : (nx, ny, nz) float ndarray
    exact : (nx, ny, nz) bool ndarray
        Where ``vals`` were evaluated (the others interpolated).
    changed : tuple of three int arrays
        Grid points whose values just changed (index arrays, as ``np.nonzero`` gives them).
    level, margin : float
        As in :func:`candidate_cells`.

    Returns
    -------
    tuple of three int arrays
        The points, in C order (as ``np.nonzero`` of a mask of them would give).

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.mesh.band import corners_to_evaluate
    >>> x = np.linspace(-1, 1, 5)
    >>> values = np.broadcast_to(x[:, None, None], (5, 5, 5)).copy()
    >>> exact = np.zeros(values.shape, dtype=bool)
    >>> i, j, k = corners_to_evaluate(values, exact, (np.array([2]), np.array([0]), np.array([0])), 0.0, 0.0)
    >>> sorted(set(i.tolist())), len(i)  # the two cells by point (2, 0, 0): their corners at x = 1, 2, 3
    ([1, 2, 3], 12)
    """
    vals = np.ascontiguousarray(vals, dtype=float)
    exact = np.ascontiguousarray(exact, dtype=bool)
    ci, cj, ck = (np.ascontiguousarray(c, dtype=np.int64) for c in changed)
    flat = _corners_to_evaluate(vals, exact, ci, cj, ck, float(level), float(margin))
    return np.unravel_index(flat, vals.shape)


@njit(cache=True, parallel=True)
def _crossing_steps(d, counts, start, out, fill):
    nx, ny, nz = d.shape
    for i in prange(nx):
        c = start[i] if fill else 0
        for j in range(ny):
            for k in range(nz):
                v = d[i, j, k]
                if i + 1 < nx and (v < 0) != (d[i + 1, j, k] < 0):
                    if fill:
                        out[c] = abs(d[i + 1, j, k] - v)
                    c += 1
                if j + 1 < ny and (v < 0) != (d[i, j + 1, k] < 0):
                    if fill:
                        out[c] = abs(d[i, j + 1, k] - v)
                    c += 1
                if k + 1 < nz and (v < 0) != (d[i, j, k + 1] < 0):
                    if fill:
                        out[c] = abs(d[i, j, k + 1] - v)
                    c += 1
        if not fill:
            counts[i] = c


def crossing_steps(d: np.ndarray) -> np.ndarray:
    """``|d_b - d_a|`` along every grid edge (a, b) whose ends differ in sign (``d < 0`` against ``d >= 0``).

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.mesh.band import crossing_steps
    >>> d = np.zeros((2, 1, 1)); d[0] = -0.25
    >>> crossing_steps(d)
    array([0.25])
    """
    d = np.ascontiguousarray(d, dtype=float)
    counts = np.zeros(d.shape[0], np.int64)
    _crossing_steps(d, counts, counts, np.empty(0), False)
    start = np.zeros(d.shape[0], np.int64)
    np.cumsum(counts[:-1], out=start[1:])
    out = np.empty(int(counts.sum()))
    _crossing_steps(d, counts, start, out, True)
    return out


@njit(cache=True, parallel=True)
def _nudge(d, eps):
    nx, ny, nz = d.shape
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                v = d[i, j, k]
                if abs(v) < eps:
                    d[i, j, k] = eps if v > 0 else -eps


def nudge_off_zero(d: np.ndarray, eps: float) -> None:
    """Set every value of ``d`` (C-contiguous, in place) closer to 0 than ``eps`` to ``+eps`` or ``-eps``,
    keeping its sign (0 counts as negative, as ``d < 0`` does not: it becomes ``-eps``).

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.mesh.band import nudge_off_zero
    >>> d = np.array([[[0.5, 1e-9, 0.0, -1e-9]]])
    >>> nudge_off_zero(d, 0.01); d
    array([[[ 0.5 ,  0.01, -0.01, -0.01]]])
    """
    if not d.flags.c_contiguous:
        raise ValueError("d must be C-contiguous (changed in place)")
    _nudge(d, float(eps))
