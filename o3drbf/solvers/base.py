"""What every solver shares: the solution record, the convergence warning,
memory accounting and the residual of the regularized system."""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass, field

import numpy as np


__all__ = ["Solution", "ConvergenceWarning", "MemoryRefusal", "available_memory", "memory_limit_or_default", "dense_memory",
           "relative_residual", "RESIDUAL_ROWS", "gigabytes", "busy_machine", "dense_blas_threads", "DENSE_THREADS_MIN"]


class ConvergenceWarning(UserWarning):
    """An iterative solve stopped before reaching its tolerance.

    Examples
    --------
    >>> import warnings
    >>> from o3drbf import ConvergenceWarning
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter('error', ConvergenceWarning)  # an unconverged solve raises instead of warning
    ...     issubclass(ConvergenceWarning, UserWarning)
    True
    """


class MemoryRefusal(MemoryError):
    """A request refused up front because it would not fit in memory (nothing costly was started).

    Parameters
    ----------
    what : str
        What was asked for ("a fast solve of 1,100,000 constraints").
    need, limit : int
        Bytes it needs and bytes it may use.
    fraction : float, optional
        About the largest share of the constraints that would fit (0: none
        worth trying; None: not known).
    api_hint, cli_hint : str, optional
        What to change, in the library's terms (``surface_count``) and the
        command line's (``--surface-count N``); callers that know more
        (the pipeline knows the surface-constraint count) set ``cli_hint``.

    Attributes
    ----------
    what, need, limit, fraction, cli_hint
    """

    def __init__(self, what: str, need: int, limit: int, fraction: float | None = None, api_hint: str | None = None,
                 cli_hint: str | None = None):
        self.what, self.need, self.limit, self.fraction = what, int(need), int(limit), fraction
        self.cli_hint = cli_hint
        if api_hint is None:
            api_hint = "subsample the constraints (surface_count)"
            if fraction:
                api_hint = f"subsample the constraints to about {fraction:.0%} of these (surface_count)"
            api_hint += ", use tiles, or free memory"
        self.api_hint = api_hint
        super().__init__(self.message())

    def message(self, hint: str | None = None, note: str = "") -> str:
        """One line: what, the need, the limit (followed by ``note``), and ``hint`` (default the library's)."""
        return (f"{self.what} needs about {gigabytes(self.need)} but the limit is {gigabytes(self.limit)}{note}; "
                f"{hint or self.api_hint}")

    def __reduce__(self):
        return (type(self), (self.what, self.need, self.limit, self.fraction, self.api_hint, self.cli_hint))


@dataclass
class Solution:
    """Weights, polynomial coefficients and a record of how they were found.

    Attributes
    ----------
    weights : (N,) ndarray
        RBF weights w.
    poly : (M,) ndarray
        Polynomial coefficients p.
    method : str
        "dense", "iterative" or "fast".
    residual : float
        Relative residual of the saddle-point system.
    seconds : float
        Wall time of the solve.
    iterations : int
        Krylov iterations (0 for dense).
    info : dict
        Solver-specific record (factorization, preconditioner, split).

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf import Gaussian, solve
    >>> centres = np.random.default_rng(0).uniform(-1, 1, (30, 3))
    >>> solution = solve(Gaussian(sigma=0.5), centres, np.ones(30), smoothing=1e-3)
    >>> type(solution).__name__, solution.method, solution.iterations
    ('Solution', 'dense', 0)
    """

    weights: np.ndarray
    poly: np.ndarray
    method: str
    residual: float
    seconds: float
    iterations: int = 0
    info: dict = field(default_factory=dict)


def available_memory() -> int:
    """Bytes this process can still allocate.

    The smaller of the machine's available memory (psutil), the address-space
    limit (RLIMIT_AS) less what the process already maps, and a cgroup limit
    less its usage.
    """
    import psutil

    avail = int(psutil.virtual_memory().available)
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft not in (resource.RLIM_INFINITY, -1):
            avail = min(avail, max(0, int(soft) - int(psutil.Process().memory_info().vms)))
    except (ImportError, OSError, ValueError):
        pass
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            with open(limit_file) as fh:
                text = fh.read().strip()
            if text == "max":
                continue
            with open(usage_file) as fh:
                used = int(fh.read().strip())
            limit = int(text)
            if limit < 2**60:
                avail = min(avail, max(0, limit - used))
        except (OSError, ValueError):
            continue
    return avail


#: Share of :func:`available_memory` a solve (and each grid) may plan to use; the rest is the margin
#: for what is not counted (the caller's arrays, allocator slack, other processes).
USABLE_FRACTION = 0.8


def memory_limit_or_default(memory_limit: int | None = None) -> int:
    """Bytes a solve may use: ``memory_limit``, or :data:`USABLE_FRACTION` of :func:`available_memory` now."""
    return int(USABLE_FRACTION * available_memory()) if memory_limit is None else int(memory_limit)


def dense_memory(n: int) -> int:
    """Peak bytes of a dense solve of ``n`` constraints: the double-precision matrix, its single-precision
    copy (factored; :class:`o3drbf.solvers.dense.DenseFactor`'s mixed precision) and slack."""
    return int(12 * (n + 4) ** 2 * 1.1 + 64 * n)


def gigabytes(x: float) -> str:
    """``x`` bytes as ``"1.2 GB"``."""
    return f"{x / 2**30:.1f} GB"


#: Rows at which :func:`relative_residual` measures ``Phi w`` by default (all of them below this).
RESIDUAL_ROWS = 2000


def relative_residual(kernel, centres, y, lam, q, w, p, rows: int | None = None, seed: int = 0) -> float:
    """|| [Phi w + lambda w + Q p - y ; Q^T w] || / ||y||, matrix-free, from the kernel's own sums.

    Parameters
    ----------
    kernel : Kernel
    centres : (N, 3) ndarray
    y, lam : (N,) ndarray
    q : (N, M) ndarray
    w : (N,) ndarray
    p : (M,) ndarray
    rows : int, optional
        Measure the first block at this many rows drawn at random (seeded)
        and scale its norm by ``sqrt(N / rows)``: an unbiased estimate of
        the whole at ``rows / N`` of the cost.  Default: every row.
    seed : int

    Returns
    -------
    float
    """
    from o3drbf.rbf.sums import kernel_sum  # here: importing o3drbf.solvers stays light (o3drbf --help)

    n = len(centres)
    if rows is not None and rows < n:
        idx = np.sort(np.random.default_rng(seed).choice(n, int(rows), replace=False))
        lam_i = lam[idx] if np.ndim(lam) else lam
        r1 = (kernel_sum(kernel, centres, w, centres[idx]) + lam_i * w[idx] + q[idx] @ p - y[idx]) * math.sqrt(n / len(idx))
    else:
        r1 = kernel_sum(kernel, centres, w, centres) + lam * w + q @ p - y
    r2 = q.T @ w
    denom = max(float(np.linalg.norm(y)), np.finfo(float).tiny)
    return float(math.sqrt(float(r1 @ r1 + r2 @ r2)) / denom)




def busy_machine(load: float | None = None, cores: int | None = None) -> bool:
    """Whether more work is waiting than there are cores: the 1-minute load average above ``cores + 0.5``.

    Parameters
    ----------
    load : float, optional
        Default: :func:`os.getloadavg`'s first value (unknown: not busy).
    cores : int, optional
        Default: :func:`os.cpu_count`.
    """
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (AttributeError, OSError):
            return False
    cores = (os.cpu_count() or 1) if cores is None else cores
    return cores > 1 and load > cores + 0.5


#: Dense systems with fewer unknowns than this are factored and solved on one BLAS thread: below it a
#: second thread saves little, and on a busy machine threaded LAPACK spin-waits (docs/data/design-measurements.md,
#: "Dense BLAS threads").
DENSE_THREADS_MIN = 2_000


@contextlib.contextmanager
def dense_blas_threads(n: int):
    """BLAS threads for factoring or solving a dense system of ``n`` unknowns: one below
    :data:`DENSE_THREADS_MIN`, else as configured.

    The count depends on ``n`` only, never on the machine's load at the time: LAPACK's threaded
    factorizations round differently from its one-thread ones, and the same input must give the same
    surface, bit for bit.
    """
    if n >= DENSE_THREADS_MIN:
        yield
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield
