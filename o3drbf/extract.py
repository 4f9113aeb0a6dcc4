"""Surface extraction: evaluate f on a grid (coarse to fine, only near the
surface) and run marching cubes.

The cost is in evaluating f, never in marching cubes, so the grid is refined
level by level: a cell of the current level is refined when its corners
change sign or come closer to the iso-level than their own spread (a local
Lipschitz test), dilated by one cell.  Everywhere else values are trilinear
interpolations of same-signed coarse values, which cannot create a spurious
crossing.  ``band=False`` evaluates every grid point (the reference).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from o3drbf.progress import progress_bar
from o3drbf.validation import check_number

if TYPE_CHECKING:
    from o3drbf.mesh.arrays import MeshArrays

__all__ = ["extract_mesh", "extract_arrays", "mesh_lattice", "evaluate_grid", "refine_on_edges", "grid_for", "mesh_evaluator", "GRID_EVALUATION_MIN", "MESH_EPS",
           "AUTO_RESOLUTION", "auto_resolution", "CORNER_GAP", "REFINE_TOL", "NEWTON_DONE"]

#: ``resolution="auto"`` (the default here and in ``o3drbf.DEFAULTS``, whose
#: ``AUTO_SIZES`` holds these): marching-cubes cells per surface-constraint
#: spacing, clipped to a range.
AUTO_RESOLUTION = {"cells_per_spacing": 2.0, "min_resolution": 64, "max_resolution": 256}


def auto_resolution(spacing_box: float) -> int:
    """The marching-cubes resolution ``resolution="auto"`` picks for a constraint spacing (box units; not > 0: the minimum)."""
    a = AUTO_RESOLUTION
    if not spacing_box > 0:
        return a["min_resolution"]
    return int(min(max(round(2.0 * a["cells_per_spacing"] / spacing_box), a["min_resolution"]), a["max_resolution"]))

#: From this many centres on, a surface without its own evaluator is meshed with
#: the grid (particle-mesh) sum of o3drbf.solvers.fast rather than the direct
#: tabulated sum, which is the slower of the two from here on (docs/data/design-measurements.md,
#: "Meshing with grid sums").
GRID_EVALUATION_MIN = 1000
#: Relative tolerance of the grid sums used for meshing, a fraction of max |f|.
#: A value error e moves a vertex by e / |grad f| (a tiny fraction of a cell
#: here) and turns a normal by about 10 e (the grid's gradients are an order
#: less accurate than its values); tighter tolerances cost a larger stencil.
MESH_EPS = 1e-4


def grid_for(bounds, resolution: int | None = 128, voxel_size: float | None = None, multiple: int = 1):
    """Grid origin, spacing and point counts covering ``bounds``.

    Parameters
    ----------
    bounds : (2, 3) array_like
        Lower and upper corners.
    resolution : int
        Cells along the longest side (used if ``voxel_size`` is None).
    voxel_size : float, optional
        Grid spacing; overrides ``resolution``.
    multiple : int
        Cell counts are rounded up to a multiple of this (for coarse levels).

    Returns
    -------
    origin : (3,) array
    spacing : float
    shape : tuple of 3 ints (points per axis)
    """
    b = np.asarray(bounds, dtype=float)
    if b.shape != (2, 3) or not np.isfinite(b).all() or (b[1] <= b[0]).any():
        raise ValueError(f"bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, got {b.tolist()}")
    extent = b[1] - b[0]
    if voxel_size is None:
        resolution = check_number("resolution", resolution, low=2, high=2048, integer=True)
        h = float(extent.max()) / resolution
    else:
        h = check_number("voxel_size", voxel_size, low=0.0, low_open=True)
    cells = np.maximum(np.ceil(extent / h - 1e-9).astype(int), 1)
    cells = ((cells + multiple - 1) // multiple) * multiple
    if np.prod(cells + 1.0) > 2048**3:
        raise ValueError(f"grid of {tuple(cells + 1)} points is too large; lower the resolution or raise voxel_size")
    centre = (b[0] + b[1]) / 2
    origin = centre - cells * h / 2
    return origin, h, tuple(int(c) + 1 for c in cells)


def mesh_evaluator(surface, eps: float = MESH_EPS, min_centres: int = GRID_EVALUATION_MIN, shared=None, box=None):
    """The fastest adequate ``(box points (M, 3), gradient) -> f [, grad f]`` for meshing.

    One grid sum (:class:`o3drbf.solvers.fast.GridSum`) for values and
    normals (gradients from the same grid: ~10 times its tolerance, plenty
    for normals): the surface's own (from
    :func:`o3drbf.solvers.fast.make_evaluator`), else, for the multi-order
    kernel with at least ``min_centres`` centres, a new one at relative
    tolerance ``eps`` (or ``shared``'s).  Otherwise the surface's own evaluator, or the direct
    sum from cubic tables (:meth:`ImplicitSurface.evaluate_box` with
    ``approximate``).  A grid sum is kept in ``surface.meshing`` and
    returned again by the next call with the same ``eps`` and ``min_centres``.

    Parameters
    ----------
    surface : ImplicitSurface
    eps : float
        Tolerance of the grid sum.
    min_centres : int
        Fewest centres for which the grid sum is used.
    shared : (callable, array of int), optional
        Another surface's meshing evaluator of kind "grid" and the places of
        this surface's centres among its grid sum's (a robust refit of the
        same constraints, some left out: ``numpy.flatnonzero(keep)``).  Where
        that grid sum holds exactly these centres there and was made with the
        same ``eps`` and ``min_centres``, it serves this surface too, with
        this surface's weights (zero at the centres it lacks): no new grid sum.
    box : (2, 3) array_like, optional
        Corners (box coordinates) of the lattice the evaluator will serve
        (:func:`mesh_lattice`): a new grid sum covers it from the start.  A
        surface's own evaluator is left as it is (marching cubes enlarges it,
        once the fit's memory is freed).

    Returns
    -------
    callable
        ``func(points, gradient=False)``; ``func.kind`` is "surface",
        "grid" or "table"; ``func.cover(lo, hi)`` prepares it for targets in
        that box (see :meth:`o3drbf.solvers.fast.GridSum.cover`).
    """

    kept = getattr(surface, "meshing", None)
    if kept is not None and getattr(kept, "settings", None) == (eps, min_centres):
        return kept

    def table(pts, gradient=False):
        return surface.evaluate_box(pts, gradient=gradient, approximate=True)

    own = getattr(surface, "evaluator", None)
    table.kind = "surface" if own is not None else "table"
    table.cover = getattr(own, "cover", None) or (lambda lo, hi: False)
    kernel = getattr(surface, "kernel", None)
    from o3drbf.solvers import fast

    op = getattr(own, "fast_sum", None)
    weights = None  # this surface's (below), or over the centres of a grid sum it shares (its own evaluator's, or ``shared``'s)
    if own is not None:
        weights = getattr(own, "weights", surface.weights)
        if not (isinstance(op, fast.GridSum) and op.n == len(weights)):
            return table
    if op is None and shared is not None:
        other, index = shared
        sop = getattr(other, "operator", None)
        if (getattr(other, "kind", None) == "grid" and getattr(other, "settings", None) == (eps, min_centres)
                and isinstance(sop, fast.GridSum) and sop.kernel == kernel):
            weights = sop.weights_over(surface.centres, index, surface.weights)
            op = None if weights is None else sop
    if op is None:  # no evaluator of its own
        from o3drbf.rbf.kernels import MultiOrder

        if kernel is None or len(surface.centres) < min_centres or not (
                fast.HAVE_GRID and isinstance(kernel, MultiOrder) and kernel.coefficients is not None):
            return table
        try:
            op = fast.GridSum(kernel, surface.centres, eps=eps, box=box)
        except (MemoryError, ValueError):
            return table
    from o3drbf.rbf.sums import polynomial_basis

    weights = surface.weights if weights is None else weights
    degree = kernel.polynomial_degree

    def grid(pts, gradient=False):
        x = np.ascontiguousarray(np.asarray(pts, dtype=float).reshape(-1, 3))
        poly = polynomial_basis(x, degree) @ surface.poly
        if not gradient:
            return op.evaluate(weights, x) + poly
        vals, grads = op.evaluate(weights, x, gradient=True)
        if degree >= 1:
            grads = grads + surface.poly[1:4]
        return vals + poly, grads

    grid.kind = "grid"
    grid.operator = op
    grid.cover = op.cover
    grid.settings = (eps, min_centres)
    if hasattr(surface, "meshing"):
        surface.meshing = grid  # kept for the next caller (the robust pass, then marching cubes)
    return grid


def _grid_points(origin, h, index_arrays):
    i, j, k = index_arrays
    return np.column_stack([origin[0] + i * h, origin[1] + j * h, origin[2] + k * h])


def evaluate_grid(
    func,
    origin,
    spacing: float,
    shape,
    level: float = 0.0,
    band: bool = True,
    progress: bool = False,
):
    """Values of ``func`` on a regular grid, exact wherever the iso-surface can be.

    Parameters
    ----------
    func : callable
        ``(M, 3) points -> (M,) values``.
    origin, spacing, shape
        As returned by :func:`grid_for`.
    level : float
        The iso-level of interest.
    band : bool
        Narrow band (default) or every point.

    Returns
    -------
    values : ndarray of ``shape``
    exact : bool ndarray of ``shape``
        Where ``values`` were evaluated rather than interpolated.
    """
    from o3drbf.mesh.band import candidate_cells, corners_to_evaluate

    origin = np.asarray(origin, dtype=float)
    shape = tuple(int(s) for s in shape)
    cells = np.array(shape) - 1
    levels = 0
    if band:
        while (cells % (2 ** (levels + 1)) == 0).all() and cells.max() // 2 ** (levels + 1) >= 16:
            levels += 1
    stride = 2**levels
    bar = progress_bar(progress, total=int(np.prod(shape)) if not band else None, desc="evaluating f", unit="pt", unit_scale=True)
    coarse_shape = tuple(int(c) // stride + 1 for c in cells)
    idx = np.indices(coarse_shape).reshape(3, -1) * stride
    vals = func(_grid_points(origin, spacing, idx)).reshape(coarse_shape)
    exact = np.ones(coarse_shape, dtype=bool)
    _tick(bar, vals.size)
    for lev in range(levels):
        stride //= 2
        # The Lipschitz margin guards coarse levels (a feature between
        # corners); on the finest grid only actual crossings matter.
        margin = 0.5 if lev < levels - 1 else 0.0
        vals = _upsample(vals)
        up_exact = np.zeros(vals.shape, dtype=bool)
        up_exact[::2, ::2, ::2] = exact
        exact = up_exact
        # Surface following: evaluate the missing corners of every cell that
        # crosses (or nearly crosses) the level by the current values, until
        # all such cells are exact.  Interpolated same-signed values cannot
        # cross, so the cells left out contain no surface.
        # The first sweep tests every cell; later ones only the cells with a
        # corner just evaluated (no other cell's test can change).
        cells = candidate_cells(vals, level, margin)
        where = np.nonzero(_corners(cells, vals.shape) & ~exact)
        for _sweep in range(64):
            if where[0].size == 0:
                break
            vals[where] = func(_grid_points(origin, spacing, [w * stride for w in where]))
            exact[where] = True
            _tick(bar, where[0].size)
            where = corners_to_evaluate(vals, exact, where, level, margin)
    if bar is not None:
        bar.close()
    return vals, exact


def _corners(cells, shape):
    """Grid points that are corners of the marked cells."""
    out = np.zeros(shape, dtype=bool)
    nx, ny, nz = cells.shape
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                out[a : a + nx, b : b + ny, c : c + nz] |= cells
    return out


def _upsample(v):
    """Trilinear refinement by 2: (n,) -> (2n - 1,) per axis; even entries unchanged."""
    out = v
    for axis in range(3):
        n = out.shape[axis]
        shape = list(out.shape)
        shape[axis] = 2 * n - 1
        res = np.empty(shape)
        even = [slice(None)] * 3
        even[axis] = slice(0, None, 2)
        odd = [slice(None)] * 3
        odd[axis] = slice(1, None, 2)
        lo = [slice(None)] * 3
        lo[axis] = slice(0, n - 1)
        hi = [slice(None)] * 3
        hi[axis] = slice(1, n)
        res[tuple(even)] = out
        res[tuple(odd)] = 0.5 * (out[tuple(lo)] + out[tuple(hi)])
        out = res
    return out


def _tick(bar, n):
    if bar is not None:
        bar.update(n)


def extraction_box(normalization, bounds, voxel_size=None):
    """The extraction box in box coordinates ((2, 3): lower, upper) and the
    voxel size in box units (None when ``voxel_size``, in data units, is None).

    Raises ValueError for bounds that are not (2, 3) or a voxel size <= 0.
    """
    b = np.asarray(bounds, dtype=float)
    if b.shape != (2, 3):
        raise ValueError(f"bounds must have shape (2, 3), got {b.shape}")
    box = normalization.forward(b)
    box = np.array([box.min(axis=0), box.max(axis=0)])
    h_box = None if voxel_size is None else check_number("voxel_size", voxel_size, low=0.0, low_open=True) * normalization.scale
    return box, h_box


def mesh_lattice(normalization, bounds, resolution: int | None = None, voxel_size: float | None = None):
    """The marching-cubes lattice :func:`extract_mesh` evaluates f on, in box coordinates.

    Parameters
    ----------
    normalization : Normalization
        The surface's (data to box coordinates).
    bounds : (2, 3) array_like
        The region to extract, in data coordinates.
    resolution : int, optional
        Cells along the longest side (used when ``voxel_size`` is None).
    voxel_size : float, optional
        Grid spacing in data units.

    Returns
    -------
    origin : (3,) array
    spacing : float
    shape : tuple of 3 ints
        Points per axis, the cell counts multiples of 8 (the narrow band's coarse levels).
    """
    box, h_box = extraction_box(normalization, bounds, voxel_size)
    return grid_for(box, resolution if voxel_size is None else None, h_box, multiple=8)


def extract_mesh(
    surface,
    resolution: int | str = "auto",
    voxel_size: float | None = None,
    bounds=None,
    level: float = 0.0,
    closed: bool = True,
    normals: str = "exact",
    progress: bool = False,
    evaluator=None,
    refine: bool = True,
):
    """Triangle mesh of the iso-surface f = ``level`` by marching cubes.

    Parameters
    ----------
    surface : ImplicitSurface
    resolution : int or "auto"
        Grid cells along the longest side of ``bounds`` (2..2048); "auto"
        (default): :func:`auto_resolution` of the surface's constraint
        spacing (``surface.metadata["mean_spacing"]``; without it, the
        smallest automatic resolution).
    voxel_size : float, optional
        Grid spacing in data units; overrides ``resolution``.
    bounds : (2, 3) array_like, optional
        Region to extract, in data coordinates.  Default: the box stored in
        ``surface.metadata["bounds"]`` (the data's bounding box, padded), or
        the centres' bounding box.
    level : float
        Iso-level (0 is the surface).
    closed : bool
        Cap the surface where it leaves ``bounds`` so the mesh is closed.
        ``False`` gives an open surface cut at the box.
    normals : {"exact", "grid"}
        Vertex normals from grad f (exact) or from the grid's finite differences.
    progress : bool
        Progress bar.
    refine : bool
        Move each vertex along its grid edge onto f = ``level``
        (:func:`refine_on_edges`; default) rather than leave it where the
        linear interpolation of the corner values puts it.  Marching cubes'
        topology is kept exactly.
    evaluator : callable, optional
        ``(box points, gradient) -> f [, grad f]``; default
        :func:`mesh_evaluator` (the grid sum from ``GRID_EVALUATION_MIN``
        centres on, else the direct tabulated sum).

    Returns
    -------
    open3d.geometry.TriangleMesh
        In data coordinates, with outward vertex normals.

    Raises
    ------
    RuntimeError
        "No surface found": f does not cross ``level`` inside ``bounds``.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> import o3drbf
    >>> surface = o3drbf.reconstruct(points, normals, surface_count=200, extract_mesh=False).surface
    >>> mesh = o3drbf.extract_mesh(surface, resolution=20)
    >>> mesh.is_watertight(), bool(abs(np.median(np.linalg.norm(np.asarray(mesh.vertices), axis=1)) - 1) < 0.02)  # the unit sphere
    (True, True)
    """
    return extract_arrays(surface, resolution, voxel_size, bounds, level, closed, normals, progress, evaluator, refine).to_open3d()


def extract_arrays(
    surface,
    resolution: int | str = "auto",
    voxel_size: float | None = None,
    bounds=None,
    level: float = 0.0,
    closed: bool = True,
    normals: str = "exact",
    progress: bool = False,
    evaluator=None,
    refine: bool = True,
) -> MeshArrays:
    """:func:`extract_mesh`'s mesh as arrays (:class:`o3drbf.mesh.arrays.MeshArrays`), without importing
    Open3D: the same parameters, errors and mesh (``extract_mesh`` is this, turned into an Open3D mesh)."""
    from skimage.measure import marching_cubes

    from o3drbf.mesh.arrays import MeshArrays

    if normals not in ("exact", "grid"):
        raise ValueError(f"normals must be 'exact' or 'grid', got {normals!r}")
    level = check_number("level", level)
    norm = surface.normalization
    if bounds is None:
        bounds = surface.metadata.get("bounds")
    if bounds is None:
        c = norm.inverse(surface.centres)
        bounds = [c.min(axis=0), c.max(axis=0)]
    if isinstance(resolution, str) and resolution == "auto":
        resolution = auto_resolution(float(surface.metadata.get("mean_spacing", float("nan"))))
    origin, h, shape = mesh_lattice(norm, bounds, resolution, voxel_size)

    func = mesh_evaluator(surface) if evaluator is None else evaluator
    cover = getattr(func, "cover", None)
    if cover is not None:  # one evaluation grid for the whole lattice
        cover(origin, origin + (np.array(shape) - 1) * h)
    vals, _ = evaluate_grid(func, origin, h, shape, level=level, band=True, progress=progress)
    vals = _keep_off_corners(vals - level)
    if closed:
        for axis in range(3):
            for end in (0, -1):
                sl = [slice(None)] * 3
                sl[axis] = end
                face = vals[tuple(sl)]
                vals[tuple(sl)] = np.minimum(face, -1e-9)
    if not (vals.min() < 0 < vals.max()):
        raise RuntimeError(
            f"No surface found at level {level}: f - level ranges over [{vals.min():.3g}, {vals.max():.3g}] in the grid"
        )
    verts, faces, grid_normals, _ = marching_cubes(vals, level=0.0, spacing=(h, h, h), allow_degenerate=False)
    # f > 0 inside: skimage winds its triangles to face up the gradient (inward); flip them
    # so triangles face outward, like the vertex normals (positive signed volume).
    faces = np.ascontiguousarray(faces[:, ::-1])
    g = None
    if refine:  # the last step's evaluation also gives the normals' gradients
        if normals == "exact":
            verts, g = refine_on_edges(func, verts / h, vals, origin, h, level, gradient=True)
        else:
            verts = refine_on_edges(func, verts / h, vals, origin, h, level)
        verts = verts * h
    verts_box = verts + origin
    if normals == "exact":
        if g is None:
            _, g = func(verts_box, gradient=True)
        glen = np.linalg.norm(g, axis=1, keepdims=True)
        vnormals = np.where(glen > 0, -g / np.where(glen > 0, glen, 1), grid_normals)
    else:
        vnormals = grid_normals
    return MeshArrays(norm.inverse(verts_box), faces, vnormals).without_degenerate_triangles()


#: A vertex whose last false-position step moved it less than this fraction of its edge takes no
#: more steps: the steps converge superlinearly, so the next one would move it far less (on a smooth
#: surface most vertices skip the last step).
REFINE_TOL = 1e-3

#: A vertex whose Newton step (with the gradient evaluated for its normal) moved it less than this
#: fraction of its edge takes no more steps: Newton's next step would move it by about the square of
#: this, times the edge over the surface's radius of curvature, well under ``REFINE_TOL``.
NEWTON_DONE = 0.01

#: Refined vertices stay this fraction of an edge away from its corners (0.01
#: left slivers that Open3D's self-intersection test flags, on a ball three
#: cells in radius).
_REFINE_GAP = 0.1


def refine_on_edges(func, verts, vals, origin, h: float, level: float = 0.0, steps: int = 3, first_node=None,
                    gradient: bool = False):
    """Marching-cubes vertices moved along their grid edges onto f = ``level``.

    Marching cubes puts a vertex where the straight line between the two
    corner values crosses the level; where f bends across a cell (a thin
    wall, a tight curve) that point is off the surface by up to ``h^2 f'' /
    (8 f')``, the same way everywhere, so thin parts come out thinner.  Each
    vertex instead takes ``steps`` false-position steps (Illinois variant) on
    its own edge, bracketed by the corner values (one evaluation of f per
    vertex and step; three leave a ball 3.3 cells in radius within 1e-5
    cells, where straight lines leave it 0.03 cells inside); a vertex whose
    last step moved it less than ``REFINE_TOL`` of its edge takes no more.
    Where grad f is evaluated (``gradient``, from the second step) the step
    is Newton's along the edge instead, when it stays inside the bracket,
    and a vertex it moved less than ``NEWTON_DONE`` of its edge takes no
    more (the next would move it by about the square of that).
    It never leaves its edge, nor comes closer to a corner than
    ``_REFINE_GAP`` of the edge (unless marching cubes put it closer): the
    triangles keep their cells and the mesh its topology.

    Parameters
    ----------
    func : callable
        ``(M, 3) box points -> (M,) f``.
    verts : (V, 3) ndarray
        Vertices in grid index units (as marching cubes returns them with
        unit spacing): two coordinates whole, one between two whole numbers.
    vals : ndarray
        The grid values ``f - level`` that marching cubes used.
    origin, h
        The grid's first node and spacing (box units).
    level : float
    steps : int
        The most false-position steps a vertex takes.
    first_node : (3,) int array_like, optional
        Index coordinates of ``vals[0, 0, 0]`` when ``verts`` and ``origin``
        refer to a larger lattice (a tile of :func:`o3drbf.tiles.extract.extract_tiled`:
        positions then do not depend on where the tile starts); default 0.
    gradient : bool
        Also return grad f at the vertices: from the vertex's last step's
        evaluation (``func(points, gradient=True)``, from the second step on),
        where the vertex was before that step's update, and from one more
        evaluation for any vertex not refined that far.

    Returns
    -------
    (V, 3) ndarray
        The vertices, in grid index units.
    (V, 3) ndarray
        With ``gradient``: grad f at them (box units).
    """
    v = np.array(verts, dtype=float)
    if not len(v):
        return (v, np.zeros((0, 3))) if gradient else v
    whole = np.rint(v)
    rows = np.arange(len(v))
    axis = np.argmax(np.abs(v - whole), axis=1)
    a = whole.astype(np.int64)  # each vertex's edge runs from corner a to a + 1 along its axis
    a[rows, axis] = np.floor(v[rows, axis]).astype(np.int64)
    base = np.zeros(3, dtype=np.int64) if first_node is None else np.asarray(first_node, dtype=np.int64).reshape(3)
    local = a - base
    keep = local[rows, axis] + 1 < np.array(vals.shape)[axis]
    a, local, axis, rows = a[keep], local[keep], axis[keep], rows[keep]
    b = local.copy()
    b[np.arange(len(b)), axis] += 1
    fa, fb = vals[tuple(local.T)], vals[tuple(b.T)]
    keep = (fa < 0) != (fb < 0)  # a crossing edge (always, for marching cubes' vertices)
    a, axis, rows, fa, fb = a[keep], axis[keep], rows[keep], fa[keep], fb[keep]
    start = a[np.arange(len(a)), axis]
    t = v[rows, axis] - start
    ta, tb = np.zeros(len(t)), np.ones(len(t))
    # Not nearer a corner than _REFINE_GAP of the edge (or than marching cubes put it): several vertices
    # pulled next to one corner make slivers that Open3D's self-intersection test flags.
    lo, hi = np.minimum(t, _REFINE_GAP), np.maximum(t, 1.0 - _REFINE_GAP)
    kept_b = np.zeros(len(t), dtype=bool)
    grads = np.full((len(v), 3), np.nan) if gradient else None
    act = np.arange(len(t))  # the vertices still moving: one whose last step moved less than REFINE_TOL is done
    for step in range(int(steps)):
        if not len(act):
            break
        ta_, tb_, t_, fa_, fb_, kb_ = ta[act], tb[act], t[act], fa[act], fb[act], kept_b[act]
        p = a[act].astype(float)
        p[np.arange(len(p)), axis[act]] += t_
        g = None
        if gradient and (step > 0 or int(steps) == 1):  # from the second step on a vertex is nearly there:
            ft, g = func(origin + p * h, gradient=True)  # its gradient there serves the normals
            grads[rows[act]] = g
        else:
            ft = func(origin + p * h)
        ft = np.asarray(ft, dtype=float).reshape(-1) - level
        same_as_a = (ft < 0) == (fa_ < 0)
        # Illinois: the end kept twice running has its value halved, so the bracket closes from both sides
        # (marching cubes' own interpolation counts as a step that kept a).
        fb_ = np.where(same_as_a & kb_, 0.5 * fb_, fb_)
        fa_ = np.where(~same_as_a & ~kb_, 0.5 * fa_, fa_)
        kb_ = same_as_a
        ta_, fa_ = np.where(same_as_a, t_, ta_), np.where(same_as_a, ft, fa_)
        tb_, fb_ = np.where(same_as_a, tb_, t_), np.where(same_as_a, fb_, ft)
        new_t = ta_ + (tb_ - ta_) * fa_ / (fa_ - fb_)
        done = np.zeros(len(act), dtype=bool)
        if g is not None:  # grad f known here: a Newton step along the edge where it stays inside the bracket
            with np.errstate(divide="ignore", invalid="ignore"):
                nt = t_ - ft / (g[np.arange(len(g)), axis[act]] * h)
            inside = np.isfinite(nt) & (nt > np.minimum(ta_, tb_)) & (nt < np.maximum(ta_, tb_))
            new_t = np.where(inside, nt, new_t)
            done = inside & (np.abs(nt - t_) < NEWTON_DONE)
        new_t = np.clip(new_t, lo[act], hi[act])
        ta[act], tb[act], fa[act], fb[act], kept_b[act] = ta_, tb_, fa_, fb_, kb_
        moved = np.abs(new_t - t_)
        t[act] = new_t
        act = act[(moved >= REFINE_TOL) & ~done]
    v[rows, axis] = start + t
    if not gradient:
        return v
    missing = np.flatnonzero(np.isnan(grads[:, 0]))
    if len(missing):
        grads[missing] = func(origin + v[missing] * h, gradient=True)[1]
    return v, grads


#: Smallest |f| kept at a grid point, as a fraction of the typical change of f
#: along a crossing edge: marching cubes then puts every vertex at least ~this
#: fraction of an edge away from a grid corner (1e-3 still left near-degenerate
#: pairs that Open3D's self-intersection test flags on the demo and the bunny;
#: 3e-3 and 1e-2 left none; a vertex moves by at most 1e-2 of a cell).
CORNER_GAP = 1e-2


def _keep_off_corners(d: np.ndarray) -> np.ndarray:
    """Move values very close to 0 to +-eps, keeping their signs (0 counts as outside).

    Without this, a vertex lands within ~1e-5 cells of a grid corner and
    forms needle triangles that Open3D's self-intersection test flags.
    Welding such vertices afterwards can join different sheets of the
    surface; changing values without changing signs keeps marching cubes'
    topology (and so a closed, manifold mesh) exactly.
    """
    from o3drbf.mesh.band import crossing_steps, nudge_off_zero

    steps = crossing_steps(d)
    if steps.size == 0:
        return d
    out = np.array(d, dtype=float, order="C")
    nudge_off_zero(out, CORNER_GAP * float(np.median(steps)))
    return out
