"""Tolerances of the fast sums: the default, the relaxation cap, the products' tolerance for a solve, and the
solve's tolerance a mesh can show."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["DEFAULT_EPS", "RELAX_CAP", "RELAX_SCALE", "RELAX_SCALE_MIN", "relax_scale", "MESH_SHIFT", "SOLVE_RTOL", "clip_eps", "product_tolerance", "mesh_tolerance"]

#: Default relative tolerance of fast sums (evaluation).
DEFAULT_EPS = 1e-6
#: Loosest product tolerance the relaxation may reach.
RELAX_CAP = 1e-3
#: The relaxed products' tolerance is ``RELAX_SCALE * eps * ||r_0|| / ||r_j||`` (at most ``RELAX_CAP``) from
#: ``RELAX_SCALE_MIN`` centres on, ``eps * ||r_0|| / ||r_j||`` below: the errors of a cycle's products add up in
#: its true residual, and cycles grow with N; at scale 1 the long cycles of large systems ended with a true
#: residual several times their recurrence's and FGMRES restarted, while short ones showed no gap and the
#: tighter products only cost time (benchmarks/recorded/fast_solver.md, session 18).
RELAX_SCALE = 0.1
RELAX_SCALE_MIN = 15_000
#: The fast solve's relative residual when no mesh sets it.
SOLVE_RTOL = 1e-6
#: The root-mean-square surface shift, in mesh cells, that :func:`mesh_tolerance` allows the solve's residual:
#: small enough that the robustness study's cells on the fast solver keep their Chamfer distance
#: (benchmarks/recorded/fast_solver.md, "The solve's tolerance").
MESH_SHIFT = 5e-4


def relax_scale(n: int) -> float:
    """The relaxation's scale for a solve of ``n`` centres: ``RELAX_SCALE`` from ``RELAX_SCALE_MIN`` on, else 1."""
    return RELAX_SCALE if n >= RELAX_SCALE_MIN else 1.0


def clip_eps(eps: float) -> float:
    """``eps`` clipped to the range the sums take, [1e-13, 1e-2]."""
    return float(min(max(eps, 1e-13), 1e-2))


def product_tolerance(rtol: float) -> float:
    """The fast products' tolerance :func:`o3drbf.solvers.fast.solve` uses for a relative residual ``rtol``."""
    return clip_eps(float(rtol) / 10.0)


def mesh_tolerance(values, cell: float, shift: float = MESH_SHIFT, gradient: float = 1.0) -> float:
    """The relative residual at which a fit's surface moves by about ``shift`` mesh cells (root mean square).

    A residual ``r`` of the system (``||r|| = rtol ||values||``) changes the
    fitted function at constraint i by about ``r_i`` (the smoothing of the
    surface constraints is small), which moves the zero level set there by
    ``r_i / |grad f|``; spread over the N constraints the root-mean-square
    shift is ``rtol ||values|| / (sqrt(N) |grad f|)``.  Setting that to
    ``shift * cell`` gives the tolerance, clipped to [``SOLVE_RTOL``,
    ``RELAX_CAP``] (beyond the cap the relaxed products would be looser
    than the residual asked for).

    Parameters
    ----------
    values : (N,) array_like
        The constraints' target values.
    cell : float
        The mesh cell, in the units of the values (the box).
    shift : float
        Allowed root-mean-square shift, in cells.
    gradient : float
        ``|grad f|`` near the surface (values per box unit); 1 unless known.

    Returns
    -------
    float

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.solvers.fast import mesh_tolerance
    >>> y = np.r_[np.zeros(9900), np.full(100, -1.0)]  # ||y|| = 10, sqrt(N) = 100
    >>> round(mesh_tolerance(y, 0.01, shift=0.001), 12)  # 0.001 cells of 0.01, times 100 / 10
    0.0001
    """
    v = np.asarray(values, dtype=float)
    norm = float(np.linalg.norm(v))
    if not (norm > 0 and cell > 0 and math.isfinite(cell)):
        return SOLVE_RTOL
    rtol = shift * float(cell) * float(gradient) * math.sqrt(len(v)) / norm
    return float(min(max(rtol, SOLVE_RTOL), RELAX_CAP))
