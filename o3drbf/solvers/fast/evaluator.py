"""The evaluator of a fitted surface by fast sums (``ImplicitSurface.evaluator``)."""

from __future__ import annotations

import numpy as np

from o3drbf.rbf.kernels import Kernel
from o3drbf.solvers.fast.grid import GridSum
from o3drbf.solvers.fast.operator import fast_operator
from o3drbf.solvers.fast.neighbours import default_neighbours
from o3drbf.solvers.fast.tolerance import DEFAULT_EPS

__all__ = ["make_evaluator"]


def make_evaluator(kernel: Kernel, centres, weights, eps: float = DEFAULT_EPS, chunk: int = 1_000_000,
                   backend: str = "auto", shared=None):
    """A callable ``(points (M, 3), gradient) -> values (M,) [, grads (M, 3)]`` for
    ``ImplicitSurface.evaluator``: ``sum_i w_i phi(|x - c_i|)`` without the
    polynomial, by FMM with targets (multi-order), sparse sums (Gaussian) or
    direct sums (thin-plate); ``backend`` as in :func:`fast_operator` (the
    grid for the multi-order kernel by default).  Targets are processed
    ``chunk`` at a time.  ``evaluator.cover(lo, hi)`` prepares the grid for
    targets in that box (:meth:`GridSum.cover`; a no-op for other backends).

    ``shared`` is an evaluator this function made and the places of
    ``centres`` among its grid sum's centres (a robust refit of the same
    constraints, some left out: ``numpy.flatnonzero(keep)``).  Where that
    grid sum holds exactly these centres there, with the same kernel and
    ``eps``, its grid sums (the values' and the gradients' finer one) serve
    these weights, zero at the centres not among ``centres``: no new grid
    sum.  ``evaluator.fast_sum`` is the grid sum and ``evaluator.weights``
    the weights over its centres."""
    fine = None
    shared_sums = _shared_sums(shared, kernel, centres, weights, eps)
    if shared_sums is not None:
        fast, fine, weights = shared_sums
    else:  # few neighbours: the near part of an evaluation is summed afresh at every target
        fast = fast_operator(kernel, centres, eps=eps, backend=backend, neighbours=default_neighbours(len(centres)))
    if isinstance(fast, GridSum):
        # The grid's gradients are ~10x less accurate than its values: gradients
        # (vertex normals, few points) come from a second grid at eps / 10.
        fine = {} if fine is None else fine

        def pick(gradient):
            if not gradient:
                return fast
            if "op" not in fine:
                try:
                    fine["op"] = GridSum(kernel, fast.centres, eps=eps / 10, tree=fast.tree, outside=fast.outside,
                                         neighbours=default_neighbours(fast.n))
                    if "box" in fine:
                        fine["op"].cover(*fine["box"])
                except MemoryError as exc:  # gradients from the values' grid (~10 eps) rather than a failure this late
                    import logging

                    logging.getLogger("o3drbf").info("gradients from the evaluation grid: %s", exc)
                    fine["op"] = fast
            return fine["op"]

        def cover(lo, hi):
            fine["box"] = (lo, hi)
            return fast.cover(lo, hi)
    else:

        def pick(gradient):
            return fast

        def cover(lo, hi):
            return False
    weights = np.ascontiguousarray(weights, dtype=float)
    if weights.shape != (fast.n,):
        raise ValueError(f"weights must have shape ({fast.n},), got {weights.shape}")

    def evaluator(points, gradient=False):
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        op = pick(gradient)
        if len(pts) <= chunk:
            return op.evaluate(weights, pts, gradient=gradient)
        parts = [op.evaluate(weights, pts[s : s + chunk], gradient=gradient) for s in range(0, len(pts), chunk)]
        if gradient:
            return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        return np.concatenate(parts)

    evaluator.fast_sum = fast
    evaluator.weights = weights
    evaluator.cover = cover
    evaluator.sharing = (kernel, eps, fine)
    return evaluator


def _shared_sums(shared, kernel, centres, weights, eps):
    """``(grid sum, its gradients' cache, weights over its centres)`` of ``shared`` (see :func:`make_evaluator`)
    when it serves these centres, kernel and ``eps``; else None."""
    if shared is None:
        return None
    other, index = shared
    fast, (k, e, fine) = getattr(other, "fast_sum", None), getattr(other, "sharing", (None, None, None))
    if not (isinstance(fast, GridSum) and fine is not None and k == kernel and e == eps):
        return None
    full = fast.weights_over(centres, index, weights)
    return None if full is None else (fast, fine, full)
