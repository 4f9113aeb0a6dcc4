"""Tolerances of the fast sums: the default, the relaxation cap, and the products' tolerance for a solve."""

from __future__ import annotations

__all__ = ["DEFAULT_EPS", "RELAX_CAP", "clip_eps", "product_tolerance"]

#: Default relative tolerance of fast sums (evaluation).
DEFAULT_EPS = 1e-6
#: Loosest product tolerance the relaxation may reach.
RELAX_CAP = 1e-3


def clip_eps(eps: float) -> float:
    """``eps`` clipped to the range the sums take, [1e-13, 1e-2]."""
    return float(min(max(eps, 1e-13), 1e-2))


def product_tolerance(rtol: float) -> float:
    """The fast products' tolerance :func:`o3drbf.solvers.fast.solve` uses for a relative residual ``rtol``."""
    return clip_eps(float(rtol) / 10.0)
