"""The product a fast solve takes: :func:`fast_operator` picks the grid sum or the FMM."""

from __future__ import annotations

from o3drbf.rbf.kernels import Kernel, MultiOrder
from o3drbf.solvers.fast.fmm import FastSum
from o3drbf.solvers.fast.grid import GridSum
from o3drbf.solvers.fast.neighbours import HAVE_GRID, product_neighbours
from o3drbf.solvers.fast.tolerance import DEFAULT_EPS

__all__ = ["fast_operator"]


def fast_operator(kernel: Kernel, centres, eps: float = DEFAULT_EPS, backend: str = "auto", memory_limit: int | None = None,
                  neighbours: int | None = None):
    """The product for a fast solve: :class:`GridSum` or :class:`FastSum`.

    ``backend="auto"`` takes the grid for the multi-order kernel when numba is
    there, ``eps >= 1e-8`` and the grid fits :func:`grid_budget` (it is
    multi-threaded, fmm3dpy's wheel is not), else the FMM (``"fmm"``).  The grid's near field has
    ``neighbours``, default :func:`product_neighbours` (``memory_limit``): right for
    products at the centres; evaluation at many targets wants fewer (:func:`default_neighbours`)."""
    if neighbours is None:
        neighbours = product_neighbours(len(centres), memory_limit)
    if backend not in ("auto", "grid", "fmm"):
        raise ValueError(f"backend must be 'auto', 'grid' or 'fmm', got {backend!r}")
    if backend == "grid":
        return GridSum(kernel, centres, eps=eps, neighbours=neighbours)
    if backend == "auto" and HAVE_GRID and isinstance(kernel, MultiOrder) and kernel.coefficients is not None \
            and eps >= 1e-8 and len(centres) >= 64:
        try:
            return GridSum(kernel, centres, eps=eps, neighbours=neighbours)
        except MemoryError as exc:
            import logging

            logging.getLogger("o3drbf").warning(
                "fast products: %s; falling back to fmm3dpy (single-threaded wheel: ~%.0f s a product)",
                exc, 30.0 * len(centres) / 1e5,
            )
    return FastSum(kernel, centres, eps=eps)
