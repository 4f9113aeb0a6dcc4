"""The fast solve: the saddle-point system by FGMRES with a constraint preconditioner over :class:`TwoLevel`."""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, fields, replace

import numpy as np

from o3drbf.progress import progress_bar
from o3drbf.rbf.kernels import Gaussian, Kernel, MultiOrder
from o3drbf.rbf.sums import polynomial_basis
from o3drbf.solvers.base import ConvergenceWarning, Solution
from o3drbf.solvers.fast.fftgrid import reused_work
from o3drbf.solvers.fast.fgmres import RESTART, fgmres
from o3drbf.solvers.fast.fmm import FastSum
from o3drbf.solvers.fast.operator import fast_operator
from o3drbf.solvers.fast.memory import check_memory
from o3drbf.solvers.fast.precondition import TwoLevel
from o3drbf.solvers.fast.tolerance import RELAX_CAP, clip_eps, product_tolerance, relax_scale

__all__ = ["solve", "SolveSettings"]


@dataclass(frozen=True)
class SolveSettings:
    """How :func:`solve` solves: accuracy, iterations, memory, the preconditioner and the product (fields: see :func:`solve`)."""

    rtol: float = 1e-6
    max_iterations: int = 200
    eps: float | None = None
    restart: int = RESTART
    memory_limit: int | None = None
    preconditioner: dict | None = None
    relax: bool = True
    backend: str = "auto"


@reused_work()  # the grids' potentials share one set of work arrays from one product to the next
def solve(kernel: Kernel, centres, y, lam, settings: SolveSettings | None = None, *, progress: bool = False, operator: FastSum | None = None,
          x0=None, preconditioner_object: TwoLevel | None = None, **overrides) -> Solution:
    """Solve ``[Phi + diag(lam), Q; Q^T, 0] [w; p] = [y; 0]`` with fast products.

    Parameters
    ----------
    kernel : MultiOrder or Gaussian (ThinPlate is refused: use method='dense')
    centres : (N, 3) array
    y, lam : (N,) arrays
    settings : SolveSettings, optional
        The fields below (default :class:`SolveSettings`); ``**overrides``
        are its fields by name, over it.
    rtol : float
        Relative residual ``||K x - b|| / ||b||`` to reach.
    max_iterations : int
        FGMRES iterations (fast products) at most.
    progress : bool
        tqdm bar with iterations and residual.
    eps : float, optional
        Tolerance of the fast products at full accuracy; default ``rtol / 10``
        (fmm3dpy delivers ~eps / 30 relative error).
    restart : int
        FGMRES iterations before a restart from the true residual (default
        :data:`o3drbf.solvers.fast.fgmres.RESTART`).
    memory_limit : int, optional
        Bytes; default 80% of available memory.  Checked before starting.
    preconditioner : dict, optional
        Keyword arguments of :class:`TwoLevel`.
    relax : bool
        Loosen the product tolerance as the residual falls (inexact Krylov).
    operator : FastSum, optional
        A prebuilt product for these centres (or any object with its
        interface, e.g. a dense stand-in for testing the preconditioner).
    backend : {"auto", "grid", "fmm"}
        The product when ``operator`` is None (:func:`fast_operator`).
    x0 : (N + M,) array or a pair of them, optional
        Starting guess ``[w; p]`` (e.g. the solution of a nearby system: a
        robust refit starts from the fit before it), or that guess and its
        residual ``[y; 0] - K x0`` in this system when the caller knows it (a
        refit: the last solve's ``residual_vector`` less the change of
        smoothing times its weights); else one product finds it.
    preconditioner_object : TwoLevel, optional
        A preconditioner built on ``operator`` for an earlier smoothing (a
        robust refit's): set to ``lam`` (:meth:`TwoLevel.set_smoothing`)
        and used instead of a new one.

    Returns
    -------
    Solution
        ``info`` holds the split, the preconditioner's sizes, setup and solve
        seconds, the residual history, ``constraint`` = ``|Q^T w|``,
        ``preconditioner_object`` (the :class:`TwoLevel` used) and
        ``residual_vector`` (``[y; 0] - K [w; p]``, found by the last true product).

    Warns
    -----
    ConvergenceWarning
        When ``rtol`` is not reached; the message gives the residual reached.
    """
    t0 = time.perf_counter()
    unknown = sorted(set(overrides) - {f.name for f in fields(SolveSettings)})
    if unknown:
        raise ValueError(f"unknown setting(s) {', '.join(unknown)} of the fast solve; valid: {', '.join(f.name for f in fields(SolveSettings))}")
    st = replace(settings or SolveSettings(), **overrides)
    rtol, max_iterations, eps, restart, memory_limit = st.rtol, st.max_iterations, st.eps, st.restart, st.memory_limit
    preconditioner, relax, backend = st.preconditioner, st.relax, st.backend
    if not isinstance(kernel, (MultiOrder, Gaussian)):
        raise ValueError(
            f"the fast solver supports the multiorder and gaussian bases, not {kernel.name}; "
            "use method='dense' or 'iterative'"
        )
    centres = np.ascontiguousarray(centres, dtype=float)
    n = len(centres)
    y = np.asarray(y, dtype=float)
    lam = np.broadcast_to(np.asarray(lam, dtype=float), (n,)).copy()
    rtol = float(rtol)
    eps = product_tolerance(rtol) if eps is None else clip_eps(eps)
    if operator is None:  # (a prebuilt operator was checked by whoever built it)
        check_memory(n, restart, eps, memory_limit, kernel=kernel, centres=centres, preconditioner=preconditioner, evaluation=False)
    q = polynomial_basis(centres, kernel.polynomial_degree)
    m = q.shape[1]
    t_setup = time.perf_counter()
    fast = fast_operator(kernel, centres, eps=eps, backend=backend, memory_limit=memory_limit) if operator is None else operator
    if preconditioner_object is not None and preconditioner_object.fast is fast:
        prec_a = preconditioner_object
        prec_a.set_smoothing(lam)
    else:
        prec_a = TwoLevel(fast, lam, **(preconditioner or {}))
    # Constraint preconditioner: exact elimination of p with M ~ (Phi + Lambda)^{-1}.
    mq = np.column_stack([prec_a(q[:, k]) for k in range(m)]) if m else np.zeros((n, 0))
    s = q.T @ mq
    setup_seconds = time.perf_counter() - t_setup

    def prec(v):
        r, t = v[:n], v[n:]
        mr = prec_a(r)
        if not m:
            return mr
        p = np.linalg.solve(s, q.T @ mr - t)
        return np.concatenate([mr - mq @ p, p])

    scale = relax_scale(n)

    def product(v, rel):
        w, p = v[:n], v[n:]
        e = max(eps, min(RELAX_CAP, scale * eps * rel)) if relax else eps
        top = fast.matvec(w, eps=e) + lam * w + q @ p
        return np.concatenate([top, q.T @ w])

    b = np.concatenate([y, np.zeros(m)])
    bar = progress_bar(progress, total=max_iterations, desc="fast FGMRES", unit="it")
    t_solve = time.perf_counter()
    try:
        x, its, res, history, residual = fgmres(product, b, prec, rtol, max_iterations, restart,
                                                 lambda v: product(v, 1.0), bar, start=x0 if isinstance(x0, tuple) else (x0, None))
    finally:
        if bar is not None:
            bar.close()
    w, p = x[:n], x[n:]
    info = {
        "split": fast.info,
        "preconditioner": prec_a.info,
        "eps": eps,
        "setup_seconds": setup_seconds,
        "solve_seconds": time.perf_counter() - t_solve,
        "history": history,
        "constraint": float(np.abs(q.T @ w).max()) if m else 0.0,
        "converged": res <= rtol,
        "preconditioner_object": prec_a,
        "residual_vector": residual,
    }
    if res > rtol:
        warnings.warn(
            f"fast solve reached relative residual {res:.2e} > rtol {rtol:.1e} after {its} iterations; "
            "raise max_iterations, loosen rtol, or use method='dense' where it fits",
            ConvergenceWarning,
            stacklevel=3,
        )
    return Solution(w, p, "fast", float(res), time.perf_counter() - t0, its, info)
