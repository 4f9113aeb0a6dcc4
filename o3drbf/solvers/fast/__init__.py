"""Fast kernel sums and a preconditioned Krylov solve for large N.

Four pieces, each usable on its own:

- :class:`GridSum` (:mod:`~o3drbf.solvers.fast.grid`) -- the default product
  for the multi-order kernel: an Ewald-type Gaussian split, far part by FFT
  on a grid (particle-mesh; the grid itself, :class:`Mesh`, in
  :mod:`~o3drbf.solvers.fast.fftgrid`), near part as a sparse matrix, with
  looser companions for relaxed products (see the class notes);
- :class:`FastSum` (:mod:`~o3drbf.solvers.fast.fmm`) -- ``sum_j w_j
  phi(|x - c_j|)`` at the centres (the matrix-vector product of the fit) or
  at arbitrary targets, with gradients, in O(N log N) time and O(N) memory,
  by fmm3dpy (``backend="fmm"``, and the automatic choice for eps < 1e-8,
  the Gaussian and any kernel the grid cannot take);
- :func:`solve` (:mod:`~o3drbf.solvers.fast.solver`) -- the saddle-point
  system of :mod:`o3drbf.solvers` by flexible GMRES
  (:mod:`~o3drbf.solvers.fast.fgmres`) with a two-level preconditioner
  (:class:`TwoLevel`, :mod:`~o3drbf.solvers.fast.precondition`; called by
  ``o3drbf.solvers.solve(method="fast")``);
- :func:`make_evaluator` (:mod:`~o3drbf.solvers.fast.evaluator`) -- a
  callable for ``ImplicitSurface.evaluator``.

Neighbour lists and near-field sizes are in
:mod:`~o3drbf.solvers.fast.neighbours`; the memory a fit will take, planned
before anything is built, in :mod:`~o3drbf.solvers.fast.memory`.
Measurements of this code (iteration counts, seconds, bytes) are recorded
beside the benchmarks that produced them, ``benchmarks/recorded/fast_solver.md``.

Notes
-----
**Multi-order kernel.**  With ``a, b = kernel.decay_rates`` and
``A, B = kernel.coefficients``,

    phi(r) = (1 + A e^{-a r} + B e^{-b r}) / (4 pi delta^2 r),

a Laplace potential plus two screened-Coulomb (Yukawa) terms.  fmm3dpy's
``lfmm3d`` sums ``c_j / (4 pi r)`` and ``hfmm3d`` with ``zk = 1j a`` sums
``c_j e^{-a r} / (4 pi r)``; both include the ``1/(4 pi)`` and skip the
self-interaction (and any pair closer than ~1e-15), so

    (Phi w)_i = [lfmm(w) + A hfmm_a(w) + B hfmm_b(w)]_i / delta^2 + phi(0) w_i.

- The short-range term (rate a ~ 1/tau, weight |A| ~ (delta tau)^2) is a
  sparse matrix in disguise: it is truncated where ``|A| e^{-a r}/(4 pi
  delta^2 r) < eps phi(0)`` and summed from a KD-tree neighbour list
  (exactly, in float64), unless that list would exceed ``sparse_budget``
  entries, in which case it is one more FMM at tolerance ``eps / |A|``.
- When ``4 tau^2 delta^2 > 1`` the rates and weights are complex
  conjugates: ``A e^{-ar} + B e^{-br} = 2 Re(A e^{-ar})`` is ONE complex-
  wavenumber Helmholtz FMM.
- At or near the confluent point ``4 tau^2 delta^2 = 1`` the weights A, B
  blow up and cancel (|A| ~ 1 / gap); when ``max(|A|, |B|) > 1e3`` (or
  exactly confluent) the fast path refuses with a message (change tau by
  ~1%, or solve densely).

**Far centres.**  The grid covers the box of the centres that have a
neighbour within the near-field radius; the few isolated centres beyond it
(the pipeline's sphere of exterior constraints around the bounding box) are
summed directly, both as sources and as targets (:func:`outside_centres`:
at most ``DIRECT_PAIRS`` kernel evaluations a product, or 0.1 % of the
centres), so that the grid's box, and its memory, is set by the data rather
than by that sphere.  Their kernel at every centre is computed once and kept
where it fits in ``OUTSIDE_BLOCK_SHARE`` of the memory limit
(:func:`~o3drbf.solvers.fast.grid.outside_block_bytes`).  The grid spacing follows the near-field radius (a
neighbour count), not tau.

**Gaussian.**  exp(-(r/sigma)^2) is truncated at ``r = sigma
sqrt(ln(10/eps))`` and applied as a sparse matrix.  **Thin-plate** r^3 has
no fast path here: products are direct (O(N^2) time, O(N) memory).

**Solve.**  FGMRES on the full saddle-point system ``[Phi + Lambda, Q; Q^T,
0]`` with a right *constraint* preconditioner: given an approximate inverse
M of ``Phi + Lambda``, ``p = (Q^T M Q)^{-1} (Q^T M r - t)``, ``w = M r - (M Q)
p``, so every search direction satisfies ``Q^T w = t`` and the iterates
satisfy the polynomial constraint ``Q^T w = 0`` to rounding (the constant
p0 is solved for, not projected away).  M is two-level multiplicative:

1. coarse: a uniform subset C of about N/8 centres, the exact kernel system
   on C factored by Cholesky in single precision, ``z_C = (Phi_CC +
   Lambda_C)^{-1} r_C``; |C| is capped at max(6,000, N/20) and at 16,000
   (6,000 up to N = 120,000, 16,000 from N = 320,000: the Cholesky's set-up
   grows as |C|^3, the iterations a larger C saves cost more as N grows).
   With ``nested`` steps (not the default)
   a larger coarse level is solved by nested FGMRES steps with products on
   C preconditioned by the same scheme on C;
2. residual update ``r' = r - (Phi + Lambda)[:, C] z_C`` (dense block when
   small, else a fast sum from the coarse centres);
3. local: ``z += S^{-1} r'`` with S the near-field matrix of the *tapered*
   kernel ``phi(r) - phi(R)`` on the k = 64 nearest neighbours (positive
   definite, unlike a plain cut-off; entries stored in single precision,
   summed in double), its diagonal damped by 2, solved by
   10 Jacobi-preconditioned CG steps (exact local solves gave the same
   iteration counts with a large fill-in, hence CG).

Product accuracy is relaxed as the residual falls (inexact Krylov, Bouras &
Fraysse 2005): the product tolerance for an Arnoldi step is
``s * eps * ||r_0|| / ||r_j||`` (at most ``RELAX_CAP``; s = ``RELAX_SCALE`` from
``RELAX_SCALE_MIN`` centres on, where cycles are long enough for the products' errors to add up,
else 1), and each restart
recomputes the true residual at full accuracy, so the reported residual is
real.

Examples
--------
>>> import numpy as np
>>> from o3drbf.rbf.kernels import MultiOrder
>>> from o3drbf.solvers import fast
>>> c = np.random.default_rng(0).uniform(-1, 1, (2000, 3))
>>> w = np.random.default_rng(1).normal(size=2000)
>>> op = fast.fast_operator(MultiOrder(10.0, 0.01), c, eps=1e-6)
>>> op.matvec(w).shape
(2000,)
"""

from __future__ import annotations

from o3drbf.solvers.fast.evaluator import make_evaluator
from o3drbf.solvers.fast.fgmres import fgmres
from o3drbf.solvers.fast.fmm import SPARSE_BUDGET, FastSum, default_workers
from o3drbf.solvers.fast.grid import (
    DIRECT_PAIRS,
    GRID_BUDGET,
    GridSum,
    grid_budget,
    grid_bytes,
    long_part,
    near_table,
    outside_centres,
    split_design,
)
from o3drbf.solvers.fast.operator import fast_operator
from o3drbf.solvers.fast.memory import check_memory, fast_memory, fitting_fraction, grid_plan, memory_plan
from o3drbf.solvers.fast.neighbours import (
    HAVE_GRID,
    NNZ_BYTES,
    PRODUCT_NEIGHBOURS_MAX,
    default_neighbours,
    neighbour_radius,
    product_neighbours,
    spatial_order,
)
from o3drbf.solvers.fast.precondition import TwoLevel
from o3drbf.solvers.fast.solver import SolveSettings, solve
from o3drbf.solvers.fast.tolerance import DEFAULT_EPS, MESH_SHIFT, RELAX_CAP, RELAX_SCALE, RELAX_SCALE_MIN, SOLVE_RTOL, clip_eps, mesh_tolerance, product_tolerance

__all__ = ["FastSum", "TwoLevel", "solve", "spatial_order", "SolveSettings", "make_evaluator", "fast_memory", "default_workers", "DEFAULT_EPS",
           "GridSum", "fast_operator", "grid_bytes", "outside_centres", "GRID_BUDGET", "product_tolerance", "check_memory",
           "grid_budget", "memory_plan", "grid_plan", "split_design", "fitting_fraction", "product_neighbours",
           "DIRECT_PAIRS", "HAVE_GRID", "NNZ_BYTES", "PRODUCT_NEIGHBOURS_MAX", "RELAX_CAP", "RELAX_SCALE", "RELAX_SCALE_MIN", "SPARSE_BUDGET",
           "clip_eps", "default_neighbours", "fgmres", "long_part", "near_table", "neighbour_radius", "mesh_tolerance",
           "MESH_SHIFT", "SOLVE_RTOL"]
