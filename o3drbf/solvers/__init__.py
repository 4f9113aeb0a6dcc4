"""The regularized fit: solve for RBF weights and polynomial coefficients.

Notes
-----
The system (method.md section 2) is the saddle-point problem

    [ Phi + diag(lambda)   Q ] [ w ]   [ y ]
    [ Q^T                  0 ] [ p ] = [ 0 ]

with Phi_ij = phi(|c_i - c_j|), Q the polynomial basis at the centres, y the
target values (0 surface, -1 exterior, +1 interior) and lambda >= 0 the
per-constraint smoothing.  For a positive-definite kernel (multi-order,
Gaussian) Phi + diag(lambda) is factored by Cholesky and p comes from the
small Schur complement Q^T (Phi + Lambda)^{-1} Q.  Thin-plate r^3 is only
conditionally positive definite and is solved as a symmetric indefinite
system.  The iterative method (GMRES) solves the same system with a
Jacobi-preconditioned operator and must agree with the dense one.
"""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np

from o3drbf.rbf.kernels import Kernel
from o3drbf.solvers.base import (RESIDUAL_ROWS, ConvergenceWarning, MemoryRefusal, Solution, available_memory, dense_memory, gigabytes,
                                 memory_limit_or_default,
                                 relative_residual)
from o3drbf.validation import as_points, check_choice, check_number, per_point

__all__ = ["Solution", "solve", "available_memory", "MemoryRefusal", "dense_memory", "ConvergenceWarning", "METHODS",
           "DENSE_MAX", "DENSE_AUTO_MAX", "FAST_EVALUATION_MIN", "choose_method", "Refitter", "solve_fast"]

#: Solver methods. "fast" (grid products + preconditioned Krylov) is in o3drbf.solvers.fast.
METHODS = ("auto", "dense", "iterative", "fast")

#: ``method="auto"`` solves densely up to this many constraints and uses the
#: fast solver above: up to it the dense fit with its robust refits (Woodbury
#: updates of one factorization, :class:`Refitter`) takes about the time of the
#: fast one or less, above it more, refits included, on the robustness study's scans
#: (``benchmarks/fast_study_cells.py --solver dense --solver fast``; docs/data/design-measurements.md,
#: "Solver choice").  ``method="dense"`` still solves up to ``DENSE_MAX``.
DENSE_AUTO_MAX = 7_500

log = logging.getLogger("o3drbf")


def __getattr__(name):
    """``DENSE_MAX`` from :mod:`o3drbf.solvers.dense`, imported on first use: ``import o3drbf.solvers`` loads
    no compiled kernel, SciPy solver or Numba (the command line's help names :data:`DENSE_AUTO_MAX`)."""
    if name == "DENSE_MAX":
        from o3drbf.solvers.dense import DENSE_MAX

        return DENSE_MAX
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

#: Above this many centres a fast-solved surface is evaluated by fast sums too
#: (below it the compiled direct sum is as fast; docs/data/design-measurements.md, "Solver choice").
FAST_EVALUATION_MIN = 20_000


def choose_method(n: int, memory_limit: int | None = None) -> tuple[str, str]:
    """The method ``"auto"`` picks for ``n`` constraints, and why.

    Dense only when it is both the faster choice (``n <= DENSE_AUTO_MAX``)
    and fits in memory; the fast solver otherwise.
    """
    limit = memory_limit_or_default(memory_limit)
    need = dense_memory(n)
    if n > DENSE_AUTO_MAX:
        return "fast", f"{n} constraints > {DENSE_AUTO_MAX}: the fast solver is faster there"
    if need > limit:
        return "fast", f"a dense solve of {n} constraints needs {gigabytes(need)}; limit {gigabytes(limit)}"
    return "dense", f"{n} constraints <= {DENSE_AUTO_MAX} and {gigabytes(need)} fits in {gigabytes(limit)}"


def solve(
    kernel: Kernel,
    centres,
    values,
    smoothing=0.0,
    method: str = "auto",
    rtol: float | None = None,
    max_iterations: int = 1000,
    memory_limit: int | None = None,
    progress: bool = False,
    backend: str = "auto",
) -> Solution:
    """Fit weights and polynomial so that f(c_i) + lambda_i w_i = y_i.

    Parameters
    ----------
    kernel : Kernel
    centres : (N, 3) array_like
        Constraint positions (in the normalized box).
    values : (N,) array_like
        Target values y_i.
    smoothing : float or (N,) array_like
        lambda_i >= 0; 0 interpolates.
    method : {"auto", "dense", "iterative", "fast"}
        "dense": LAPACK Cholesky (or symmetric indefinite) with a residual
        check.  "iterative": GMRES on the dense operator (or a chunked
        matrix-free one when the matrix does not fit).  "fast": fast
        multipole products and a preconditioned Krylov solve
        (:mod:`o3drbf.solvers.fast`).  "auto": dense up to ``DENSE_AUTO_MAX`` constraints when it fits in
        memory, fast above (:func:`choose_method`).
    rtol : float, optional
        Relative residual target for the iterative methods, in (0, 1).
        Default 1e-10 for "iterative", 1e-6 for "fast" (a mesh needs far
        less; the multipole tolerance follows it).
    max_iterations : int
    memory_limit : int, optional
        Bytes the dense solve may use; default 80% of available memory.
    progress : bool
        Show a progress bar (iterative methods).
    backend : {"auto", "grid", "fmm"}
        Products of the fast method (:func:`o3drbf.solvers.fast.fast_operator`): the
        grid (Gaussian-split particle-mesh, multi-order kernel) or fmm3dpy.

    Returns
    -------
    Solution

    Raises
    ------
    ValueError
        Bad shapes or parameters, or too few constraints for the polynomial.
    MemoryError
        A dense solve that would not fit in ``memory_limit``; the message
        names the limit and the alternatives.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf import MultiOrder, solve
    >>> rng = np.random.default_rng(0)
    >>> centres, values = rng.uniform(-1, 1, (50, 3)), rng.normal(size=50)
    >>> solution = solve(MultiOrder(delta=8, tau=0.02), centres, values)
    >>> solution.method, bool(solution.residual < 1e-8), solution.weights.shape
    ('dense', True, (50,))
    """
    t0 = time.perf_counter()
    centres, y, lam = system_inputs(centres, values, smoothing, method)
    n = len(centres)
    check_choice("backend", backend, ("auto", "grid", "fmm"))
    if rtol is not None:
        rtol = check_number("rtol", rtol, low=0.0, high=1.0, low_open=True)
    from o3drbf.rbf.sums import polynomial_basis
    from o3drbf.solvers.dense import solve_dense
    from o3drbf.solvers.iterative import solve_gmres

    q = polynomial_basis(centres, kernel.polynomial_degree)
    m = q.shape[1]
    if n < m + 1:
        raise ValueError(f"{kernel.name} basis needs at least {m + 1} constraints, got {n}")
    if m > 1 and np.linalg.matrix_rank(q) < m:
        raise ValueError("constraint points are coplanar: the linear polynomial of the thin-plate basis is not determined")
    limit = memory_limit_or_default(memory_limit)
    need = dense_memory(n + m)
    method = resolve_method(method, n, m, limit)
    if method == "fast":
        return solve_fast(kernel, centres, y, lam, rtol, max_iterations, progress, backend)
    if method == "dense":
        w, p, info = solve_dense(kernel, centres, y, lam, q)
        iterations = 0
    else:
        w, p, iterations, info = solve_gmres(kernel, centres, y, lam, q, 1e-10 if rtol is None else rtol, max_iterations, need <= limit, progress)
    residual = relative_residual(kernel, centres, y, lam, q, w, p)
    sol = Solution(w, p, method, residual, time.perf_counter() - t0, iterations, info)
    if method == "dense" and residual > DENSE_RESIDUAL_WARN:
        warnings.warn(
            f"dense solve residual {residual:.1e} is large: the system is ill-conditioned "
            "(near-duplicate constraints with lambda = 0?); increase lambda",
            ConvergenceWarning,
            stacklevel=2,
        )
    return sol


def system_inputs(centres, values, smoothing, method: str = "auto") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked ``(centres (N, 3), values (N,), smoothing (N,))`` of a solve, and a known ``method``."""
    centres = as_points(centres, name="centres", min_count=1)
    n = len(centres)
    y = np.asarray(values, dtype=float)
    if y.shape != (n,):
        raise ValueError(f"values must have shape ({n},), got {y.shape}")
    if not np.isfinite(y).all():
        raise ValueError("values contain NaN or infinity")
    lam = per_point("smoothing", smoothing, n, low=0.0)
    check_choice("method", method, METHODS)
    return centres, y, lam


def solve_fast(kernel: Kernel, centres, y, lam, rtol: float | None = None, max_iterations: int = 1000, progress: bool = False,
               backend: str = "auto", operator=None, start: dict | None = None) -> Solution:
    """The fast method of :func:`solve` (validated inputs): :func:`o3drbf.solvers.fast.solve` with ``rtol``
    1e-6 by default and at most 200 iterations, logged; ``operator`` (a prebuilt product) is passed on, and
    so are ``start["x0"]`` (a starting ``[w; p]``) and ``start["preconditioner"]`` (an earlier solve's
    ``TwoLevel``, reused) when given; the preconditioner used is put back in ``start`` (never in the
    solution's ``info``: it holds memory), and so is the solve's true residual (``start["residual"]``):
    a refit from that solution with new smoothing starts from it, moved by the smoothing's change,
    instead of a product (:func:`_moved_residual`).

    The system is solved with its centres in :func:`o3drbf.solvers.fast.spatial_order` (the
    sparse parts then read nearby memory; ``start["order"]``, when given, is that order, not
    computed again); ``operator`` must be built on ``centres`` in that order, and ``x0`` and the
    weights returned are in the caller's order."""
    from o3drbf.solvers import fast

    t0 = time.perf_counter()
    n = len(centres)
    order = (start or {}).get("order")
    if order is None:
        order = fast.spatial_order(centres)
    if operator is not None and getattr(operator, "centres", None) is not None and not np.array_equal(operator.centres, centres[order]):
        raise ValueError("operator must be built on the centres in o3drbf.solvers.fast.spatial_order(centres)")
    rtol = 1e-6 if rtol is None else rtol
    x0 = (start or {}).get("x0")
    r0 = None
    if x0 is not None:
        x0 = np.concatenate([x0[:n][order], x0[n:]])
        r0 = _moved_residual((start or {}).get("residual"), x0, lam[order], fast.product_tolerance(rtol))
    sol = fast.solve(kernel, centres[order], y[order], lam[order], rtol=rtol,
                     max_iterations=min(max_iterations, 200), progress=progress, backend=backend, operator=operator,
                     x0=x0 if r0 is None else (x0, r0), preconditioner_object=(start or {}).get("preconditioner"))
    last = (sol.info.get("residual_vector"), np.concatenate([sol.weights, sol.poly]), lam[order], sol.info["eps"])
    weights = np.empty_like(sol.weights)
    weights[order] = sol.weights
    sol.weights = weights
    used = sol.info.pop("preconditioner_object", None)
    sol.info.pop("residual_vector", None)
    if start is not None:
        start["preconditioner"] = used
        start["residual"] = last if last[0] is not None else None
    split = sol.info["split"]
    log.info(
        "solver: fast products (%s) + two-level preconditioned FGMRES, %d constraints: %d iterations, "
        "residual %.1e, %.1f s%s",
        split.get("mode") or split.get("split"), len(centres), sol.iterations, sol.residual, time.perf_counter() - t0,
        "" if (start or {}).get("x0") is None else " (from the previous solution)",
    )
    sol.seconds = time.perf_counter() - t0
    return sol


def _moved_residual(last, x0, lam, eps):
    """The residual of ``x0`` in the system with smoothing ``lam`` (solver order), from the last solve's
    ``(residual, solution, smoothing, product tolerance)`` when ``x0`` is that solution and the products
    are as accurate: the values and centres are the same, so only the smoothing's change moves it
    (``r - (lam - lam_last) w``), and no product is needed.  None otherwise."""
    if last is None:
        return None
    r, x, lam_last, eps_last = last
    if eps != eps_last or len(x) != len(x0) or not np.array_equal(x, x0):
        return None
    r0 = r.copy()
    n = len(lam)
    r0[:n] -= (lam - lam_last) * x0[:n]
    return r0


#: A constraint :class:`Refitter` leaves out of a fast solve keeps its centre
#: with this many times the largest finite smoothing.
DROPPED_SMOOTHING = 1e6


#: A dense solve whose relative residual exceeds this warns (and a Woodbury
#: update of :class:`Refitter` is redone as a fresh solve).
DENSE_RESIDUAL_WARN = 1e-6


def resolve_method(method: str, n: int, m: int, limit: int) -> str:
    """The method a solve of ``n`` constraints and ``m`` polynomial terms runs: "auto" resolved
    (:func:`choose_method`), a dense solve refused above ``DENSE_MAX`` or ``limit`` bytes."""
    from o3drbf.solvers.dense import DENSE_MAX

    if method == "auto":
        method, why = choose_method(n + m, limit)
        log.info("solver: %s (%s)", method, why)
    if method == "dense" and n + m > DENSE_MAX:
        exc = ValueError(
            f"a dense solve of {n} constraints is refused: above {DENSE_MAX} the installed OpenBLAS is known to "
            "crash and the fast solver is faster; use method='fast' (or 'auto')"
        )
        exc.cli_message = (f"a dense solve of {n:,} constraints is refused: above {DENSE_MAX:,} the installed OpenBLAS is "
                           "known to crash and the fast solver is faster; pass --solver auto (or --solver fast)")
        raise exc
    if method == "dense" and dense_memory(n + m) > limit:
        raise MemoryRefusal(f"a dense solve of {n} constraints", dense_memory(n + m), limit,
                            api_hint="use method='fast' (O(N log N)), or fewer constraints (surface_count)",
                            cli_hint="pass --solver fast (or --solver auto), or fewer constraints (--surface-count)")
    return method


class Refitter:
    """One set of constraints solved again and again with new smoothing (robust reweighting).

    When the solve is dense and the kernel positive definite, the first
    factorization is kept and every later smoothing that differs at no more
    than ``max_changed`` constraints is solved by the Woodbury identity
    (:class:`o3drbf.solvers.dense.DenseFactor`): a robust refit that
    down-weights a few constraints costs a few triangular solves, not a new
    factorization.  When it is fast, the products are built once for all
    the centres and every refit starts FGMRES from the previous solution
    (and its residual); it is preconditioned by the last solve's
    preconditioner set to the new smoothing
    (:meth:`o3drbf.solvers.fast.TwoLevel.set_smoothing`).  The first solve's
    is kept for them only with ``refits`` (else freed: a fit without refits
    holds no more memory, and the first refit builds its own); a
    left-out constraint keeps its centre with the smoothing
    ``DROPPED_SMOOTHING`` times the largest finite one (its weight comes out
    ~1e-6 of its neighbours' and is then removed).  Otherwise (the iterative
    method, many changes, an update whose residual exceeds
    ``DENSE_RESIDUAL_WARN``) it is a fresh :func:`solve` of the constraints kept.

    Parameters
    ----------
    kernel : Kernel
    centres : (N, 3) array_like
    values : (N,) array_like
    smoothing : float or (N,) array_like
        The first smoothing, lambda_0.
    method : {"auto", "dense", "iterative", "fast"}
        Resolved once, for N constraints (:func:`choose_method`).
    max_changed : int, optional
        Most changed constraints solved by an update; default N / 8.
    checked : bool
        The caller has already checked that a fast solve fits in memory
        (:func:`o3drbf.solvers.fast.check_memory`); not checked again.
    refits : bool
        Refits may follow the first solve (a robust fit): a fast solve keeps
        its preconditioner for them from the first solve on.
    **options
        Passed to :func:`solve` (``progress``, ``rtol``, ``memory_limit``, ...).
    """

    def __init__(self, kernel: Kernel, centres, values, smoothing=0.0, method: str = "auto", max_changed: int | None = None,
                 checked: bool = False, refits: bool = False, **options):
        self.kernel = kernel
        self.refits = bool(refits)
        self.centres, self.values, self.smoothing = system_inputs(centres, values, smoothing, method)
        n = len(self.centres)
        self.options = options
        self.max_changed = max(1, n // 8) if max_changed is None else int(max_changed)
        from o3drbf.rbf.sums import polynomial_basis

        q = polynomial_basis(self.centres, kernel.polynomial_degree)
        self.q = q
        self.factor = None
        self.operator = None  # the fast method's products, built at its first solve
        # The fast method's last [w; p] ("x0"), its TwoLevel ("preconditioner", set to each new smoothing)
        # and the centres' spatial order ("order").
        self.start = {}
        self.checked = bool(checked)
        limit = memory_limit_or_default(options.get("memory_limit"))
        self.method = method
        if n >= q.shape[1] + 1 and kernel.positive_definite:
            self.method = resolve_method(method, n, q.shape[1], limit)

    def solve(self, smoothing=None) -> tuple[np.ndarray, Solution]:
        """Solve with ``smoothing`` (default lambda_0); ``inf`` leaves a constraint out.

        Parameters
        ----------
        smoothing : (N,) array_like, optional

        Returns
        -------
        keep : (N,) bool ndarray
            The constraints in the solution (finite smoothing).
        solution : Solution
            Of the kept constraints, in their order; ``info["update"]`` is
            "woodbury" (with ``info["changed"]``) when the kept factorization
            was updated.
        """
        lam = self.smoothing if smoothing is None else np.asarray(smoothing, dtype=float)
        if lam.shape != self.smoothing.shape or np.isnan(lam).any() or (lam < 0).any():
            raise ValueError(f"smoothing must be {len(lam)} values >= 0 (inf to leave a constraint out)")
        keep = np.isfinite(lam)
        t0 = time.perf_counter()
        if self.method == "dense" and self.factor is None:
            try:
                from o3drbf.solvers.dense import DenseFactor

                self.factor = DenseFactor(self.kernel, self.centres, self.smoothing, self.q)
            except np.linalg.LinAlgError:
                self.method = "dense-unfactored"
        if self.factor is not None and int((lam != self.smoothing).sum()) <= self.max_changed:
            w, p, changed = self.factor.solve(self.values, lam)
            residual = self.factor.residual(self.values, lam, w, p)
            if not changed:  # the factorization itself, checked once against the kernel's own sums (at sampled rows)
                residual = max(residual, relative_residual(self.kernel, self.centres, self.values, lam, self.q, w, p,
                                                           rows=RESIDUAL_ROWS))
            w = w[keep]
            if residual <= DENSE_RESIDUAL_WARN:
                info = {"factorization": "cholesky"}
                if changed:
                    info.update(update="woodbury", changed=changed)
                return keep, Solution(w, p, "dense", residual, time.perf_counter() - t0, 0, info)
            log.info("Woodbury update of %d constraints: residual %.1e; solving afresh", changed, residual)
        if self.method == "fast" and self.kernel.name in ("multiorder", "gaussian"):
            return keep, self.solve_fast(lam, keep)
        method = "dense" if self.method == "dense-unfactored" else self.method
        return keep, solve(self.kernel, self.centres[keep], self.values[keep], lam[keep], method=method, **self.options)

    def solve_fast(self, lam, keep) -> Solution:
        """A fast solve on the products of all the centres, from the previous solution (see the class)."""
        from o3drbf.solvers import fast

        o = self.options
        if self.operator is None:
            rtol = o.get("rtol") or 1e-6  # before the products are built: what they, the preconditioner and FGMRES take
            self.checked or fast.check_memory(len(self.centres), eps=fast.product_tolerance(rtol), memory_limit=o.get("memory_limit"),
                              kernel=self.kernel, centres=self.centres, evaluation=False)
            self.start["order"] = fast.spatial_order(self.centres)  # the solves' order, once for every refit
            self.operator = fast.fast_operator(self.kernel, self.centres[self.start["order"]],
                                               eps=fast.product_tolerance(rtol), backend=o.get("backend", "auto"), memory_limit=o.get("memory_limit"))
        finite = lam[keep]
        big = DROPPED_SMOOTHING * max(float(finite.max()) if finite.size else 1.0, 1e-12)
        sol = solve_fast(self.kernel, self.centres, self.values, np.where(keep, lam, big), o.get("rtol"), o.get("max_iterations", 1000),
                         o.get("progress", False), o.get("backend", "auto"), operator=self.operator, start=self.start)
        if "x0" not in self.start and not self.refits:  # the first solve, and no refit expected: its preconditioner's memory freed
            self.start.pop("preconditioner", None)
        self.start["x0"] = np.concatenate([sol.weights, sol.poly])
        if keep.all():
            return sol
        return Solution(sol.weights[keep], sol.poly, sol.method, sol.residual, sol.seconds, sol.iterations, dict(sol.info, left_out=int((~keep).sum())))


