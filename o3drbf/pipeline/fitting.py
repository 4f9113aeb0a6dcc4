"""Fit: the implicit function solved for, robustly reweighted; the memory a fast fit needs checked before it starts."""

from __future__ import annotations

import logging

import numpy as np

from o3drbf.constraints.core import Constraints
from o3drbf.options import AUTO_SIZES, PAPER_VALUES, ExtractOptions, FitOptions, Options, auto_resolution, auto_surface_count
from o3drbf.pipeline.records import ConstraintSet, Parameters
from o3drbf.prep.normalize import Normalization
from o3drbf.rbf.kernels import Kernel, MultiOrder
from o3drbf.solvers import FAST_EVALUATION_MIN, Refitter, Solution, solve
from o3drbf.surface import ImplicitSurface

__all__ = ["fit", "surface_of", "check_fit_memory", "mesh_cells", "EARLY_CHECK_MIN", "EARLY_CHECK_SLACK", "early_fit_check", "fit_surface",
           "ROBUST_SHIFT"]

log = logging.getLogger("o3drbf")

#: The root-mean-square surface shift, in residual scales, that the robust refits of a fast-evaluated
#: fit allow their solve's residual (:func:`o3drbf.solvers.fast.mesh_tolerance`); the last refit is
#: then solved on to the mesh's tolerance.
ROBUST_SHIFT = 1e-2


def fit(constraints: Constraints, kernel: Kernel, normalization: Normalization, solver: str = "auto", progress: bool = False,
        **solve_options) -> tuple[ImplicitSurface, Solution]:
    """Fit an implicit surface to constraints given in the normalized box.

    Parameters
    ----------
    constraints : Constraints
        Points, target values and smoothing, in the box.
    kernel : Kernel
    normalization : Normalization
        Data <-> box, kept by the surface.
    solver : {"auto", "dense", "iterative", "fast"}
    progress : bool
    **solve_options
        Passed to :func:`o3drbf.solvers.solve`.

    Returns
    -------
    ImplicitSurface, Solution

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf import Constraints, MultiOrder, Normalization, fit
    >>> from o3drbf.constraints.core import SPHERE, SURFACE
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, _ = Sphere(0.5).sample(200, seed=0)  # in the normalized box already
    >>> outer, _ = Sphere(0.9).sample(40, seed=1)
    >>> constraints = Constraints.concat(Constraints.of_kind(points, SURFACE, 1e-4), Constraints.of_kind(outer, SPHERE, 1e-4))
    >>> surface, solution = fit(constraints, MultiOrder(delta=8, tau=0.02), Normalization.identity())
    >>> bool(surface([[0.0, 0.0, 0.0]])[0] > 0 > surface([[0.7, 0.0, 0.0]])[0])  # positive inside, negative outside
    True
    """
    sol = solve(kernel, constraints.points, constraints.values, constraints.smoothing, method=solver, progress=progress, **solve_options)
    return surface_of(sol, constraints.points, kernel, normalization), sol


def surface_of(sol: Solution, centres, kernel: Kernel, normalization: Normalization, shared=None) -> ImplicitSurface:
    """The implicit surface of a solution at its centres (box units); fast-solved large ones evaluate by fast sums
    (``shared``: another surface's evaluator and these centres' places among its centres, whose grid sums serve
    this one too: :func:`o3drbf.solvers.fast.make_evaluator`)."""
    surf = ImplicitSurface(kernel, centres, sol.weights, sol.poly, normalization)
    if sol.method == "fast" and len(centres) >= FAST_EVALUATION_MIN:
        from o3drbf.solvers.fast import make_evaluator

        surf.evaluator = make_evaluator(kernel, centres, sol.weights, shared=shared)
    return surf


def check_fit_memory(cset: ConstraintSet, params: Parameters, options: FitOptions = FitOptions(),
                     extract: ExtractOptions | None = None) -> dict | None:
    """Refuse, before the fit starts, a fast fit (and its meshing) that would not fit in memory.

    The need is :func:`o3drbf.solvers.fast.memory_plan`'s for these
    centres (products, preconditioner, Krylov basis, then the evaluator and
    marching cubes at the extraction's resolution); the limit 80 % of the
    memory available now.  Dense solves are checked by the solver itself
    (also up front).

    Parameters
    ----------
    cset : ConstraintSet
    params : Parameters
    options : FitOptions
    extract : ExtractOptions, optional
        The meshing to plan for (None: no mesh).

    Returns
    -------
    dict or None
        The plan (None when the solve is not fast).

    Raises
    ------
    MemoryRefusal
        With ``cli_hint`` naming a ``--surface-count`` that would fit (when
        one would) and ``--tiles auto``.
    """
    from o3drbf.options import extraction_memory
    from o3drbf.rbf.sums import polynomial_basis
    from o3drbf.solvers import MemoryRefusal, choose_method, fast

    pts = cset.constraints.points
    n = len(pts)
    m = polynomial_basis(pts[:1], params.kernel.polynomial_degree).shape[1]
    method = options.solver if options.solver != "auto" else choose_method(n + m)[0]
    if method != "fast" or not params.kernel.positive_definite:
        return None
    extraction, box = 0, None
    if extract is not None:
        res = extract.resolution if extract.resolution != "auto" else auto_resolution(cset.spacing)
        extraction = extraction_memory(int(res)) if extract.voxel_size is None else 0
        if cset.bounds is not None:
            b = cset.normalization.forward(np.asarray(cset.bounds, dtype=float))
            box = np.stack([b.min(axis=0), b.max(axis=0)])
    try:
        return fast.check_memory(n, eps=fast.product_tolerance(1e-6), kernel=params.kernel, centres=pts,
                                 evaluation=extract is not None and n >= FAST_EVALUATION_MIN, box=box, extraction_bytes=extraction)
    except MemoryRefusal as exc:
        surface = cset.constraints.counts()["surface"]
        hints = []
        if exc.fraction:
            count = int(exc.fraction * surface)
            digits = max(len(str(count)) - 2, 0)
            hints.append(f"--surface-count {count // 10**digits * 10**digits}")
        hints.append("--tiles auto")
        exc.cli_hint = "pass " + " or ".join(hints)
        exc.what = f"a fast fit of {n:,} constraints ({surface:,} surface)" + (" and its mesh" if extract is not None else "")
        exc.args = (exc.message(),)
        raise


#: From this many expected constraints on, :func:`early_fit_check` estimates the fit's memory right
#: after reading (below it the stages before the fit take seconds anyway).
EARLY_CHECK_MIN = 50_000
#: :func:`early_fit_check` refuses only when its estimate exceeds the limit by this factor (it works
#: on a random subset of the points, not the constraints; :func:`check_fit_memory` decides the rest).
EARLY_CHECK_SLACK = 1.25


def early_fit_check(points, options: Options, extract: bool = True, seed: int = 0) -> None:
    """Refuse, seconds after reading, a fit that clearly would not fit in memory.

    The constraint count is the one the options will give (``surface_count``
    or ``"auto"`` or every point, plus exterior and sphere constraints); the
    memory is :func:`o3drbf.solvers.fast.memory_plan`'s for a seeded random
    subset of the points of that size, in the normalized box, with the
    multi-order kernel of the paper's values.  It refuses only above
    ``EARLY_CHECK_SLACK`` times the limit and only from ``EARLY_CHECK_MIN``
    constraints, for a fast solve of a multi-order kernel; the exact check
    (:func:`check_fit_memory`) comes before the fit.

    Raises
    ------
    MemoryRefusal
        With ``cli_hint`` naming a ``--surface-count`` that would fit (when
        one would) and ``--tiles auto``.
    """
    from o3drbf.solvers import MemoryRefusal, fast
    from o3drbf.solvers.base import memory_limit_or_default

    c, p = options.constraints, options.parameters
    n_points = len(points)
    if c.surface_radius is not None or options.fit.solver == "dense":
        return
    kernel = p.kernel if isinstance(p.kernel, Kernel) else None
    if kernel is None and str(p.kernel) != "multiorder":
        return
    if kernel is not None and not isinstance(kernel, MultiOrder):
        return
    surface = n_points if c.surface_count is None else (
        auto_surface_count(n_points) if c.surface_count == "auto" else min(int(c.surface_count), n_points))
    total = int(round(surface * (1 + c.exterior_ratio))) + int(c.sphere_count)
    if total < EARLY_CHECK_MIN:
        return
    norm = Normalization.from_points(points)
    rng = np.random.default_rng(seed)
    centres = norm.forward(np.asarray(points, dtype=float)[np.sort(rng.choice(n_points, min(total, n_points), replace=False))])
    if total > len(centres):  # exterior constraints beside the surface ones
        extra = centres[rng.choice(len(centres), total - len(centres))] + rng.normal(scale=c.exterior_offset, size=(total - len(centres), 3))
        centres = np.vstack([centres, extra])
    kernel = kernel or MultiOrder(PAPER_VALUES["delta"], PAPER_VALUES["tau"])
    limit = memory_limit_or_default()
    extraction = 0
    if extract and options.extract.voxel_size is None:
        from o3drbf.options import extraction_memory

        res = options.extract.resolution
        extraction = extraction_memory(AUTO_SIZES["max_resolution"] if res == "auto" else int(res))
    try:
        fast.check_memory(total, eps=fast.product_tolerance(1e-6), memory_limit=int(EARLY_CHECK_SLACK * limit), kernel=kernel,
                          centres=centres, evaluation=extract, extraction_bytes=extraction)
    except MemoryRefusal as exc:
        hints = []
        fraction = fast.fitting_fraction(kernel, centres, limit, eps=fast.product_tolerance(1e-6), evaluation=extract,
                                         extraction_bytes=extraction, limit=limit)
        if fraction:
            count = int(fraction * surface)
            digits = max(len(str(count)) - 2, 0)
            hints.append(f"--surface-count {count // 10**digits * 10**digits}")
        hints.append("--tiles auto")
        raise MemoryRefusal(f"a fast fit of about {total:,} constraints ({surface:,} surface)" + (" and its mesh" if extract else ""),
                            exc.need, limit, fraction=fraction, cli_hint="pass " + " or ".join(hints)) from None


def mesh_cells(extract: ExtractOptions, cset: ConstraintSet) -> float:
    """Mesh cells along the box's longest side for these extraction options: the resolution asked for, the
    automatic one, or the box's side over a voxel size (data units)."""
    if extract.voxel_size is not None:
        return 2.0 / (float(extract.voxel_size) * float(cset.normalization.scale))
    return float(auto_resolution(cset.spacing) if extract.resolution == "auto" else int(extract.resolution))


def fit_surface(cset: ConstraintSet, params: Parameters, options: FitOptions = FitOptions(), *, progress: bool = False,
                checked: bool = False, resolution: float | None = None, lattice=None):
    """Solve for the implicit function; robustly reweighted by default.

    The robust pass (:func:`o3drbf.constraints.robust.robust_reweight`) refits
    with new smoothing until the down-weighted constraints settle.  A fit of
    ``FAST_EVALUATION_MIN`` constraints or more solves those refits only to
    move the surface by ``ROBUST_SHIFT`` residual scales (they serve to
    measure residuals), then solves the last one on to the mesh's tolerance.

    Parameters
    ----------
    cset : ConstraintSet
    params : Parameters
    options : FitOptions
    progress : bool
    checked : bool
        :func:`check_fit_memory` has passed: the solver does not check again.
    resolution : float, optional
        Cells along the box's longest side in the mesh the fit is for (default: the
        automatic one for the constraint spacing); a fast solve stops where
        its residual moves the surface by a small fraction of such a cell
        (:func:`o3drbf.solvers.fast.mesh_tolerance`).
    lattice : (2, 3) array_like, optional
        Corners, in box coordinates, of the lattice the fit will be meshed on
        (:func:`o3drbf.pipeline.meshing.mesh_lattice_box`): the meshing grid sum the
        robust pass builds (below ``FAST_EVALUATION_MIN``) covers it from the
        start, so marching cubes needs no larger grid and, after a fit without
        refits, no new potential.  A surface's own evaluator (from
        ``FAST_EVALUATION_MIN``) is enlarged by marching cubes, after the fit.

    Returns
    -------
    surface : ImplicitSurface
    solution : Solution
    robust : dict or None
        Rounds, down-weighted and dropped constraints, scale, seconds, and
        ``constraints`` (those of the final fit); None when not robust.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> from o3drbf import PointSet
    >>> data = PointSet.create(points, normals)
    >>> from o3drbf import build_constraints, choose_parameters, fit_surface
    >>> cset = build_constraints(data)
    >>> surface, solution, robust = fit_surface(cset, choose_parameters(data, cset))
    >>> solution.method, bool(abs(surface(points)).max() < 0.01)
    ('dense', True)
    """
    options.validate()
    c = cset.constraints
    constraints = Constraints(c.points, c.values, params.smoothing, c.kind)
    # One factorization for the first fit and every robust refit (Woodbury updates of the dense one).
    session = Refitter(params.kernel, constraints.points, constraints.values, constraints.smoothing, method=options.solver,
                       checked=checked, refits=options.robust, progress=progress)
    # The residual scale never falls below half a constraint spacing, so
    # clean data are not reweighted (no refit when no residual reaches
    # Tukey's c times the scale).
    scale = max(params.noise, 0.5 * cset.spacing) if np.isfinite(cset.spacing) else params.noise
    rtol = loose = None
    if session.method == "fast":
        from o3drbf.solvers.fast.tolerance import mesh_tolerance

        cells = float(resolution) if resolution else auto_resolution(cset.spacing)
        rtol = session.options["rtol"] = mesh_tolerance(constraints.values, 2.0 / cells)  # the box's longest side is 2
        # The robust refits of a fast-evaluated fit only measure residuals against the scale: solved to
        # move the surface by a small fraction of it, and the last one finished to ``rtol`` afterwards.
        # (Below FAST_EVALUATION_MIN the residuals' direct sums cost more than the iterations saved.)
        if scale > 0 and len(constraints) >= FAST_EVALUATION_MIN:
            loose = max(rtol, mesh_tolerance(constraints.values, scale, shift=ROBUST_SHIFT))
    last = {}

    def refit(smoothing=None):
        last["smoothing"] = smoothing
        keep, solution = session.solve(smoothing)
        index = np.flatnonzero(keep)
        # A refit evaluates by the first fit's grid sums (the same centres, some left out) with its own weights.
        fitted = surface_of(solution, constraints.points[keep], params.kernel, cset.normalization,
                            shared=(last.get("evaluator"), index))
        last.setdefault("evaluator", fitted.evaluator)
        if fitted.evaluator is not None or "grid" in last:
            from o3drbf.extract import mesh_evaluator

            # A fast-evaluated fit: its own grid, wrapped, serves residuals and meshing.  Another refit: the
            # first fit's meshing grid sum, over the same centres, serves it with its weights.
            mesh_evaluator(fitted, shared=(last.get("grid"), index))
        return fitted, solution

    surface, sol = refit()
    robust = None
    if options.robust:
        from o3drbf.constraints.robust import robust_reweight

        if resolution is not None:
            from o3drbf.extract import mesh_evaluator

            # The grid marching cubes will use (a fast fit's own evaluation grid, or a new one), built now: the
            # first residuals, f and grad f, come from it (not from a grid ten times as fine for gradients alone),
            # and the refits' residuals too (below).
            last["grid"] = mesh_evaluator(surface, box=lattice)

        if loose is not None:
            session.options["rtol"] = loose
        surface, sol, rep = robust_reweight(
            lambda c: fit(c, params.kernel, cset.normalization, solver=options.solver, progress=progress),
            constraints, scale, first=(surface, sol), refit=refit,
        )
        if loose is not None:
            session.options["rtol"] = rtol
            if rep.rounds and loose > rtol:  # the last refit, solved on from where it stopped
                surface, sol = refit(last["smoothing"])
        robust = {"rounds": int(rep.rounds), "downweighted": int(rep.downweighted), "dropped": int(rep.dropped),
                  "scale": float(rep.scale), "seconds": float(rep.seconds), "constraints": rep.constraints}
        if rep.downweighted or rep.dropped:
            log.info("robust fit: %d round(s), %d constraints down-weighted, %d dropped (scale %.3g box units)",
                     rep.rounds, rep.downweighted, rep.dropped, rep.scale)
    surface.metadata = {
        "basis": params.kernel.to_dict(),
        "lambda_surface": params.lambda_surface,
        "lambda_exterior": params.lambda_exterior,
        "exterior_offset": cset.exterior_offset,
        "counts": cset.constraints.counts(),
        "mean_spacing": cset.spacing,
        "bounds": None if cset.bounds is None else cset.bounds.tolist(),
        "normals_estimated": cset.normals_estimated,
        "parameter_source": params.source,
    }
    log.info("solved %d constraints (%s) in %.2f s, relative residual %.1e", len(constraints), sol.method, sol.seconds, sol.residual)
    return surface, sol, robust
