"""Memory of a fast fit, planned without building it: :func:`memory_plan`, :func:`check_memory`."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.rbf.kernels import MultiOrder
from o3drbf.solvers.base import MemoryRefusal, memory_limit_or_default
from o3drbf.solvers.fast.fftgrid import Mesh
from o3drbf.solvers.fast.fgmres import RESTART
from o3drbf.solvers.fast.grid import (SUBSET_NEIGHBOURS, SUBSET_SHARE, near_entries, near_table, outside_block_bytes, outside_centres,
                                      served_tolerance, split_design)
from o3drbf.solvers.fast.neighbours import (HAVE_GRID, NNZ_BYTES, default_neighbours, neighbour_radius, product_neighbours,
                                            store_near)
from o3drbf.solvers.fast.tolerance import DEFAULT_EPS, clip_eps, product_tolerance

__all__ = ["fast_memory", "grid_plan", "near_choice", "memory_plan", "check_memory", "fitting_fraction"]

#: Iterations of a cycle whose Krylov basis the plans count: a cycle touches its basis only as far as it goes, and
#: the solves of the user's path take fewer (a million centres took 72, where the basis beyond this is a fifth of
#: the peak); counting the whole cycle (fgmres.RESTART) would plan memory that a fit does not take.
KRYLOV_PLANNED = 50
#: Bytes of FMM working memory per point (fmm3dpy at 1e-6; benchmarks/recorded/fast_solver.md).
_FMM_BYTES_PER_POINT = 8_000
#: Bytes per centre of the kd-tree, the sorted copies and the index arrays every product keeps.
_PER_CENTRE_BYTES = 200
#: Bytes per centre of a near field summed on the fly (its sum in cell order, then in the centres').
_ON_THE_FLY_BYTES = 2 * 8


def fast_memory(n: int, restart: int = RESTART, eps: float = 1e-6) -> int:
    """Rough peak bytes of a fast solve with ``n`` constraints, from ``n`` alone.

    The FMM route (fmm3dpy's working memory) or the grid route's near parts
    (1,800 stored entries a row: the product's and its two companions', unless
    :func:`~o3drbf.solvers.fast.neighbours.store_near` sums them on the fly) with 4,000 bytes of grid a
    centre; the estimate that knows the centres is :func:`memory_plan`."""
    fmm = _FMM_BYTES_PER_POINT * n * (1.0 if eps <= 1e-6 else 0.6) + 12 * n * 300
    grid = (NNZ_BYTES * n * 1800 if store_near(n * 1100) else _ON_THE_FLY_BYTES * n) + 4e3 * n
    krylov = 2 * (min(restart, KRYLOV_PLANNED) + 2) * n * 8
    precond = 12 * n * 65 + 64 * n + 8 * 6000**2 + 256 * 2**20 + (12 * (n // 8) * 1000 if n > 144_000 else 0)
    return int(max(fmm, grid) + krylov + precond)


def _core_box(centres, tree, rc, outside=None):
    """(outside indices, core lo, core hi, core count) of a grid with near radius ``rc``."""
    if outside is None:
        outside = outside_centres(centres, tree, rc)
    if len(outside):
        mask = np.ones(len(centres), bool)
        mask[outside] = False
        core = centres[mask]
    else:
        core = centres
    return outside, core.min(axis=0), core.max(axis=0), len(core)


def grid_plan(kernel, centres, tree, eps: float, neighbours: int | None = None, radius: float | None = None,
              outside=None, box=None, near: bool = True, memo: dict | None = None) -> dict:
    """What a :class:`GridSum` with these arguments would take, without building it.

    Parameters
    ----------
    kernel : MultiOrder
    centres : (N, 3) array
    tree : cKDTree
        Of ``centres``.
    eps, neighbours, radius, outside
        As for :class:`GridSum`.
    box : (2, 3) array_like, optional
        A box the grid must cover too (:meth:`GridSum.cover`).
    near : bool
        Count the stored near-field matrix of products at the centres
        (evaluation at targets has none; :func:`near_choice` turns it into a
        near field summed on the fly).
    memo : dict, optional
        Neighbour radii already found on this tree, by neighbour count (filled in).

    Returns
    -------
    dict
        ``grid`` (the kernel transform, kept), ``work`` (the transforms of
        one product, and the rows of a near field summed on the fly, freed
        after it), ``near`` (sparse matrix), ``potential`` (one grid
        potential), bytes; ``h``, ``radius`` (design), ``outside``,
        ``entries`` (of the near field), ``core`` (centres on the grid).
    """
    n = len(centres)
    e = clip_eps(eps)
    if radius is None:
        k = default_neighbours(n) if neighbours is None else neighbours
        memo = {} if memo is None else memo
        if k not in memo:
            memo[k] = neighbour_radius(centres, tree, k)
        radius = memo[k]
    rc = float(radius)
    sigma, _, h, half = split_design(rc, e / 10)
    outside, lo, hi, n_core = _core_box(centres, tree, rc, outside)
    if box is not None:
        lo, hi = np.minimum(lo, box[0]), np.maximum(hi, box[1])
    grid = Mesh.nbytes(lo, hi, h, half, e >= 1e-4, "kept")
    work = Mesh.nbytes(lo, hi, h, half, e >= 1e-4, "work")
    pad = (half + 2) * h
    cells = float(np.prod([math.ceil((hi[i] - lo[i] + 2 * pad) / h) + 1 for i in range(3)]))
    nnz = near_entries(centres, tree, near_table(kernel, rc, sigma, e / 10)[0], n_core) if near else 0.0
    return {"grid": int(grid), "work": int(work), "near": int(NNZ_BYTES * nnz + 8 * n_core) if near else 0,
            "potential": int(8 * cells), "h": h, "radius": rc, "outside": outside, "entries": nnz,
            "core": n_core}


def near_choice(plan: dict, store: bool | None = None, limit: int | None = None) -> dict:
    """A :func:`grid_plan` of products at the centres with their near field stored or summed on the fly
    (``store``; default :func:`~o3drbf.solvers.fast.neighbours.store_near` of its entries at ``limit``,
    as :class:`GridSum` chooses): ``store`` set, and on the fly ``near`` 0 and its rows in ``work``."""
    out = dict(plan)
    out["store"] = store_near(plan["entries"], limit) if store is None else bool(store)
    if not out["store"]:
        out["near"] = 0
        out["work"] = plan["work"] + _ON_THE_FLY_BYTES * plan["core"]
    return out


def _settings(options=None):
    """The :class:`TwoLevelSettings` a :class:`TwoLevel` takes with these ``options`` over its defaults."""
    from dataclasses import replace

    from o3drbf.solvers.fast.precondition import TwoLevelSettings

    return replace(TwoLevelSettings(), **(options or {}))


def _twolevel_plan(kernel, centres, tree, lam_count, coarse_update_nnz, eps, options=None, limit=None) -> int:
    """Bytes of a :class:`TwoLevel` on these centres, for an operator at tolerance ``eps``, with its default
    options (``options`` overrides)."""
    from o3drbf.solvers.fast.precondition import COARSE_SINGLE, coarse_size

    st = _settings(options)
    n = len(centres)
    total = (4 + 4) * n * (st.neighbours + 1) + 64 * n  # the tapered near matrix: a float32 entry and an int32 column each (built in place)
    mc, nested = coarse_size(n, st)
    if mc < n and 4 * n * mc <= st.dense_budget:  # the coarse-to-fine block, in single precision
        total += 4 * n * mc
    elif 64 <= mc <= SUBSET_SHARE * n:  # the coarse centres' own grid sum, at every centre (GridSum.from_subset)
        sub = centres[np.sort(np.random.default_rng(2).choice(n, mc, replace=False))]
        tol = served_tolerance(st.eps, eps)  # as GridSum.from_subset asks it
        g = grid_plan(kernel, sub, cKDTree(sub), tol if tol > eps else tol / 10, neighbours=SUBSET_NEIGHBOURS, near=False)
        block = 8 * n * len(g["outside"])  # its far centres' kernel at every centre, one a tolerance (GridSum.at)
        total += g["grid"] + g["work"] + 32 * n + (2 * block if block <= outside_block_bytes(limit) else 0)
    elif mc < n:
        total += int(coarse_update_nnz * mc / n) * NNZ_BYTES
    if not nested:
        # The coarse matrix's lower triangle (its upper half never touched) is evaluated and factored in single
        # precision (2 mc^2); the plan keeps the fallback where that breaks down: the lower triangle in double,
        # and the factor's in single while the double one is alive (double: the matrix and its factor in place).
        return int(total + (6 if COARSE_SINGLE else 12) * mc * mc)
    sub_idx = np.sort(np.random.default_rng(2).choice(n, mc, replace=False))
    sub = centres[sub_idx]
    sub_tree = cKDTree(sub)
    g = near_choice(grid_plan(kernel, sub, sub_tree, max(st.nested_eps, 1e-8), neighbours=product_neighbours(mc)), limit=limit)
    inner = _twolevel_plan(kernel, sub, sub_tree, mc, g["near"] / NNZ_BYTES, max(st.nested_eps, eps), options, limit)
    krylov = 2 * (nested + 2) * mc * 8
    return int(total + g["grid"] + g["near"] + inner + krylov + _PER_CENTRE_BYTES * mc)  # (its work: below the outer's)


def _coarse_rows(n: int, eps: float, options=None) -> tuple[float, int] | None:
    """(tolerance, count) of the coarse rows a :class:`TwoLevel` on ``n`` centres asks of an operator at
    ``eps`` (its second coarse correction), when that tolerance is a companion's of its own; else None."""
    from o3drbf.solvers.fast.precondition import coarse_size, second_correction

    st = _settings(options)
    if not second_correction(n, st):
        return None
    tol = served_tolerance(st.post_eps, eps)
    return (tol, coarse_size(n, st)[0]) if tol != eps else None


def memory_plan(kernel, centres, rtol: float = 1e-6, eps: float | None = None, restart: int = RESTART, preconditioner: dict | None = None,
                evaluation: bool = True, box=None, extraction_bytes: int = 0, limit: int | None = None) -> dict:
    """Peak bytes of a fast fit on these centres (and of evaluating and meshing it), without building anything.

    It follows the solve as it runs: during FGMRES the products at the
    solve's tolerance and their two looser companions (each a grid and a
    near-field matrix), the two-level preconditioner (tapered near field,
    coarse Cholesky or the nested level with its own grid, and the grid of
    its coarse rows at ``post_eps`` with the second correction), the Krylov
    basis; at the end the evaluator's grid joins the products; meshing
    holds the evaluator's grid enlarged to ``box`` and ``extraction_bytes``.
    Kernels or tolerances the grid does not take are estimated by
    :func:`fast_memory`.

    Parameters
    ----------
    kernel : Kernel
    centres : (N, 3) array
    rtol : float
        Relative residual of the solve; the products' tolerance is
        :func:`product_tolerance` of it unless ``eps`` is given.
    eps : float, optional
    restart : int
        FGMRES cycle length; its Krylov basis is counted for at most ``KRYLOV_PLANNED`` iterations.
    preconditioner : dict, optional
        Options of :class:`TwoLevel`.
    evaluation : bool
        Count the evaluator (:func:`make_evaluator`, at ``DEFAULT_EPS``) and meshing.
    box : (2, 3) array_like, optional
        The meshing lattice's box (default: the centres' box padded by 5 % of its span).
    extraction_bytes : int
        Marching cubes' own arrays (:func:`o3drbf.options.extraction_memory`).
    limit : int, optional
        The memory limit the products' near-field size follows
        (:func:`product_neighbours`); default :func:`memory_limit_or_default`.

    Returns
    -------
    dict
        ``total`` (the peak, bytes), ``fit``, ``end_of_fit``, ``mesh``
        (the three phases), ``parts`` (bytes by piece) and ``route``
        ("grid" or "fmm").
    """
    centres = np.ascontiguousarray(centres, dtype=float)
    n = len(centres)
    e = product_tolerance(rtol) if eps is None else clip_eps(eps)
    grid_ok = HAVE_GRID and isinstance(kernel, MultiOrder) and kernel.coefficients is not None and e >= 1e-8 and n >= 64
    if not grid_ok:
        need = fast_memory(n, restart, e)
        return {"total": need, "fit": need, "end_of_fit": need, "mesh": need, "parts": {}, "route": "fmm"}
    tree = cKDTree(centres)
    base = _PER_CENTRE_BYTES * n
    memo = {}
    main = near_choice(grid_plan(kernel, centres, tree, e, neighbours=product_neighbours(n, limit), memo=memo), limit=limit)
    out = main["outside"]
    parts = {"grid": main["grid"], "near": main["near"]}
    far = 8 * len(out) * n  # the far centres' kernel at every centre (GridSum._outside_block)
    if far <= outside_block_bytes(limit):
        parts["far centres"] = far
    work = [main["work"]]
    rc300 = neighbour_radius(centres, tree, min(300, max(n // 300, 64)))

    def companion(tol):  # a looser companion's grid (GridSum._tier, with its tier_radius)
        return grid_plan(kernel, centres, tree, tol, radius=max(rc300, main["h"] / split_design(1.0, tol / 10)[2]), outside=out)

    tier_nnz = 0
    for tol in (1e-3, 1e-4):
        if tol >= 10 * e:
            t = near_choice(companion(tol), store=main["store"])
            parts[f"grid {tol:g}"], parts[f"near {tol:g}"] = t["grid"], t["near"]
            work.append(t["work"])
            tier_nnz = t["near"] / NNZ_BYTES if tol == 1e-3 else tier_nnz
    rows = _coarse_rows(n, e, preconditioner)
    if rows is not None and f"grid {rows[0]:g}" not in parts:  # the coarse rows' companion (GridSum.rows)
        t = companion(rows[0])
        parts[f"grid {rows[0]:g}"] = t["grid"]
        parts[f"near {rows[0]:g}"] = int(t["near"] * rows[1] / n)  # at the coarse centres only
        work.append(t["work"])
    parts["preconditioner"] = _twolevel_plan(kernel, centres, tree, n, tier_nnz or main["near"] / NNZ_BYTES, e, preconditioner,
                                             limit)
    parts["krylov"] = int(2 * (min(restart, KRYLOV_PLANNED) + 1) * (n + 4) * 8 + 3 * n * 4 * 8)
    products = sum(v for k, v in parts.items() if k.startswith(("grid", "near")))
    fit = base + products + parts["preconditioner"] + parts["krylov"] + max(work)
    end = mesh = 0
    if evaluation:
        if box is None:
            _, lo, hi, _ = _core_box(centres, tree, main["radius"], out)
            pad = 0.05 * float((hi - lo).max())
            box = np.stack([lo - pad, hi + pad])
        at_centres = grid_plan(kernel, centres, tree, DEFAULT_EPS, near=False, outside=out, memo=memo)
        at_box = grid_plan(kernel, centres, tree, DEFAULT_EPS, near=False, box=np.asarray(box, dtype=float), outside=out,
                           memo=memo)
        # The vertex normals come from a second grid at a tenth of the tolerance, beside the values' one.
        fine = grid_plan(kernel, centres, tree, DEFAULT_EPS / 10, near=False, box=np.asarray(box, dtype=float), outside=out,
                         memo=memo)
        parts["evaluator"] = at_box["grid"] + at_box["potential"]
        parts["evaluator gradients"] = fine["grid"] + fine["potential"]
        end = base + products + at_centres["grid"] + at_centres["potential"] + max(work + [at_centres["work"]])
        mesh = base + parts["evaluator"] + parts["evaluator gradients"] + max(at_box["work"], fine["work"]) + int(extraction_bytes)
    return {"total": int(max(fit, end, mesh)), "fit": int(fit), "end_of_fit": int(end), "mesh": int(mesh), "parts": parts,
            "route": "grid"}


def check_memory(n: int, restart: int = RESTART, eps: float = 1e-6, memory_limit: int | None = None, kernel=None, centres=None,
                 **plan) -> dict | None:
    """Refuse, before anything is built, a fast solve that would not fit in ``memory_limit`` bytes.

    With ``kernel`` and ``centres`` the need is :func:`memory_plan`'s (``plan``
    holds its other arguments), else :func:`fast_memory`'s.  The limit
    defaults to 80 % of the memory available now.

    Returns
    -------
    dict or None
        The plan (None without centres).

    Raises
    ------
    MemoryRefusal
        Naming the need, the limit and the share of the constraints that would fit.
    """
    limit = memory_limit_or_default(memory_limit)
    result = None
    if centres is not None and kernel is not None:
        result = memory_plan(kernel, centres, eps=eps, restart=restart, limit=limit, **plan)
        need = result["total"]
    else:
        need = fast_memory(n, restart, eps)
    if need > limit:
        fraction = None
        if centres is not None and kernel is not None:
            fraction = fitting_fraction(kernel, centres, limit, eps=eps, restart=restart, limit=limit, **plan)
        raise MemoryRefusal(f"a fast solve of {n} constraints", need, limit, fraction=fraction,
                            cli_hint="use fewer constraints (--surface-count) or --tiles auto")
    return result


def fitting_fraction(kernel, centres, fit_in: int, **plan) -> float:
    """About the largest share of ``centres`` (a seeded random subset, like a sparser subsample) whose
    :func:`memory_plan` (with ``plan``) fits in ``fit_in`` bytes (0 if not even 1 % does)."""
    n = len(centres)
    rng = np.random.default_rng(3)
    order = rng.permutation(n)
    frac = 1.0
    need = memory_plan(kernel, centres, **plan)["total"]
    for _ in range(8):
        frac *= min(0.9, max(0.2, (fit_in / need) ** 1.25))
        m = int(frac * n)
        if m < max(100, n // 100):
            return 0.0
        need = memory_plan(kernel, centres[np.sort(order[:m])], **plan)["total"]
        if need <= fit_in:
            return frac
    return 0.0
