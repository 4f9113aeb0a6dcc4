"""Marching cubes of a tiled surface on one global lattice, tile by tile, welded exactly.

1. Coarse pass: every tile evaluates f at the coarse lattice nodes (stride
   ``s``) of the coarse cells it owns; the coarse values are assembled here.
2. Band: coarse cells whose corners change sign or come within half their
   spread of the level (:func:`o3drbf.extract` uses the same local Lipschitz
   test), dilated by one coarse cell.
3. Fine pass: every tile takes its own fine cells plus a one-cell halo; a
   node's value is f at that node if it lies in a band cell, else the
   trilinear interpolation of the global coarse values.  A node's value is
   thus a function of the node alone, identical in every tile, and so are
   the marching-cubes vertices on shared lattice edges.  Each tile keeps
   the triangles of the cells it owns (no double faces across tiles) and
   names every vertex by its lattice edge; welding by edge id leaves no
   duplicate vertex and no crack.

Values that come within ``1e-3`` of a typical edge step of the level are
moved off it keeping their sign (one global epsilon), as
:func:`o3drbf.extract.extract_mesh` does; faces are wound outward like there,
and vertices are moved along their edges onto the level set like there
(:func:`o3drbf.extract.refine_on_edges`, in global lattice coordinates).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from o3drbf.extract import CORNER_GAP, extraction_box, grid_for, refine_on_edges
from o3drbf.mesh.band import crossing_steps
from o3drbf.tiles.cluster import run_tasks, tile_client, worker_summary
from o3drbf.validation import check_number

__all__ = ["extract_tiled", "lattice_for"]

log = logging.getLogger("o3drbf")



def lattice_for(surface, resolution: int | None = 128, voxel_size: float | None = None, bounds=None) -> dict:
    """The global lattice (box coordinates) and each tile's coarse-cell ownership.

    Returns
    -------
    dict
        ``origin`` (3,), ``h`` (float), ``shape`` (nodes per axis), ``stride``
        (fine cells per coarse cell), ``coarse`` (coarse cells per axis),
        ``own_lo``, ``own_hi`` ((T, 3) coarse-cell index ranges [lo, hi) that
        partition the coarse cells).
    """
    norm = surface.normalization
    if bounds is None:
        bounds = surface.metadata.get("bounds")
    if bounds is None:
        bounds = surface.root_box()
    box, h_box = extraction_box(norm, bounds, voxel_size)
    res = resolution if voxel_size is None else None
    _, h0, shape0 = grid_for(box, res, h_box)
    cells0 = max(shape0) - 1
    stride = next(s for s in (8, 4, 2, 1) if cells0 // s >= 16 or s == 1)
    origin, h, shape = grid_for(box, res, h_box, multiple=stride)
    coarse = (np.array(shape) - 1) // stride
    part = surface.partition
    step = stride * h
    own_lo = np.clip(np.rint((part.lo - origin) / step), 0, coarse).astype(np.int64)
    own_hi = np.clip(np.rint((part.hi - origin) / step), 0, coarse).astype(np.int64)
    # Cells touching the root box's faces own everything out to the lattice's end.
    root_lo, root_hi = part.lo.min(axis=0), part.hi.max(axis=0)
    own_lo = np.where(part.lo <= root_lo, 0, own_lo)
    own_hi = np.where(part.hi >= root_hi, coarse, own_hi)
    return {"origin": origin, "h": float(h), "shape": tuple(int(v) for v in shape), "stride": int(stride),
            "coarse": tuple(int(v) for v in coarse), "own_lo": own_lo, "own_hi": own_hi}


def _positions(lat, i, j, k):
    o, h = lat["origin"], lat["h"]
    return np.column_stack([o[0] + i * h, o[1] + j * h, o[2] + k * h])


#: The middle level of the fine pass: nodes every MID lattice steps, exact in the coarse band.
MID = 2

#: A coarse cell is in the band when its corners change sign or come within this fraction of their spread of
#: the level (a local Lipschitz test, as in :func:`o3drbf.extract.evaluate_grid`); a middle cell, when they
#: come within FINE_MARGIN (0: they change sign, as on that function's finest level).
BAND_MARGIN = 0.5
FINE_MARGIN = 0.0


def _level_values(lattice, axes, grid, first, stride: int, cells, func, known=None):
    """Values at the lattice nodes ``axes`` (index arrays per axis) from a coarser grid, exact in its marked cells.

    ``grid`` holds values at the nodes ``first + stride * m`` (per axis);
    each node gets the trilinear interpolation of its grid cell's corners,
    or ``func`` at the node when it is a corner of a cell marked in
    ``cells`` (and not ``known`` already).  A node's value depends on the
    node, the grid and the marks only, never on which tile asks.

    Returns
    -------
    values : array of the axes' shape
    exact : bool array, where ``func`` was evaluated
    """
    first = np.broadcast_to(np.asarray(first), (3,))
    ng = np.array(grid.shape)
    rel = [ax - first[a] for a, ax in enumerate(axes)]
    ci = [np.minimum(r // stride, ng[a] - 2) for a, r in enumerate(rel)]
    fr = [(r - ci[a] * stride) / stride for a, r in enumerate(rel)]
    I, J, K = np.meshgrid(ci[0], ci[1], ci[2], indexing="ij")
    X, Y, Z = np.meshgrid(fr[0], fr[1], fr[2], indexing="ij")
    vals = np.zeros(I.shape)
    for a in (0, 1):
        wa = X if a else 1.0 - X
        for b in (0, 1):
            wb = Y if b else 1.0 - Y
            for c in (0, 1):
                wc = Z if c else 1.0 - Z
                vals += (wa * wb * wc) * grid[I + a, J + b, K + c]
    del I, J, K, X, Y, Z
    # A node belongs to the grid cells ceil(r / stride) - 1 .. floor(r / stride).
    cand_lo = [np.clip(-(-r // stride) - 1, 0, ng[a] - 2) for a, r in enumerate(rel)]
    cand_hi = [np.clip(r // stride, 0, ng[a] - 2) for a, r in enumerate(rel)]
    exact = np.zeros(vals.shape, dtype=bool)
    for a in (0, 1):
        ia = cand_hi[0] if a else cand_lo[0]
        for b in (0, 1):
            jb = cand_hi[1] if b else cand_lo[1]
            for c in (0, 1):
                kc = cand_hi[2] if c else cand_lo[2]
                exact |= cells[np.ix_(ia, jb, kc)]
    if known is not None:
        exact &= ~known
    where = np.nonzero(exact)
    if where[0].size:
        vals[where] = func(_positions(lattice, axes[0][where[0]], axes[1][where[1]], axes[2][where[2]]))
    return vals, exact


def coarse_task(t: int, surface=None, lattice: dict | None = None, level: float = 0.0) -> tuple[np.ndarray, np.ndarray] | None:
    """f - level at the coarse nodes of tile ``t``'s coarse cells.

    Returns
    -------
    (lo (3,) int array, values (a, b, c) array) or None
        The first coarse node index and the values; None if the tile owns no cell.
    """
    lo, hi = lattice["own_lo"][t], lattice["own_hi"][t]
    if (hi <= lo).any():
        return None
    s = lattice["stride"]
    idx = np.indices(tuple(hi - lo + 1)).reshape(3, -1) + lo[:, None]
    vals = surface.evaluate_box(_positions(lattice, *(idx * s)), approximate=True) - level
    return lo, vals.reshape(tuple(hi - lo + 1))


def fine_task(t: int, surface=None, lattice: dict | None = None, coarse_values: np.ndarray | None = None, band: np.ndarray | None = None,
              eps: float = 0.0, level: float = 0.0, closed: bool = True, refine: bool = True) -> dict | None:
    """Marching cubes of tile ``t``'s own fine cells (computed with a one-cell halo); ``refine``: vertices moved
    onto f = ``level`` along their lattice edges (:func:`o3drbf.extract.refine_on_edges`).

    Returns
    -------
    dict or None
        ``ids`` (V,) int64 lattice-edge ids, ``verts`` (V, 3) global lattice
        index coordinates, ``normals`` (V, 3) outward unit normals, ``faces``
        (F, 3) indices into ``verts`` (wound outward), ``evaluated`` (int).
    """
    from skimage.measure import marching_cubes

    lo_c, hi_c = lattice["own_lo"][t], lattice["own_hi"][t]
    if (hi_c <= lo_c).any():
        return None
    s = lattice["stride"]
    shape = np.array(lattice["shape"])
    own_lo, own_hi = lo_c * s, hi_c * s  # fine cells [own_lo, own_hi)
    start = np.maximum(own_lo - 1, 0)
    stop = np.minimum(own_hi + 1, shape - 1)  # inclusive node range
    func = (lambda x: surface.evaluate_box(x, approximate=True) - level)
    # Middle level (stride MID): every node a function of the node alone (the global coarse values and band),
    # on the block padded by one middle cell so that every fine node's middle cells are in it.
    axes = [np.arange(start[a], stop[a] + 1) for a in range(3)]
    m = MID if s % MID == 0 and s > MID else 1
    if m == 1:
        vals, exact = _level_values(lattice, axes, coarse_values, 0, s, band, func)
        evaluated = int(exact.sum())
    else:
        mstart = np.maximum((start - m) // m * m, 0)
        mstop = np.minimum(-(-(stop + m) // m) * m, shape - 1)
        mid_axes = [np.arange(mstart[a], mstop[a] + 1, m) for a in range(3)]
        mid, mid_exact = _level_values(lattice, mid_axes, coarse_values, 0, s, band, func)
        evaluated = int(mid_exact.sum())
        corners = [mid[a:a + mid.shape[0] - 1, b:b + mid.shape[1] - 1, c:c + mid.shape[2] - 1]
                   for a in (0, 1) for b in (0, 1) for c in (0, 1)]
        mn, mx, absmin = np.min(corners, axis=0), np.max(corners, axis=0), np.min(np.abs(corners), axis=0)
        cells = ((mn <= 0) & (mx >= 0)) | (absmin <= FINE_MARGIN * (mx - mn))
        del corners
        # Nodes of the middle level keep their value there (exact or not): only the others are evaluated.
        on_mid = [((ax - mstart[a]) % m == 0) for a, ax in enumerate(axes)]
        known = np.zeros(tuple(len(ax) for ax in axes), dtype=bool)
        sel = np.ix_(*[np.flatnonzero(o) for o in on_mid])
        known[sel] = mid_exact[np.ix_(*[(axes[a][on_mid[a]] - mstart[a]) // m for a in range(3)])]
        vals, exact = _level_values(lattice, axes, mid, mstart, m, cells, func, known=known)
        evaluated += int(exact.sum())
    small = np.abs(vals) < eps
    vals[small] = np.where(vals[small] > 0, eps, -eps)
    if closed:
        for a in range(3):
            sl = [slice(None)] * 3
            if start[a] == 0:
                sl[a] = 0
                vals[tuple(sl)] = np.minimum(vals[tuple(sl)], -1e-9)
            if stop[a] == shape[a] - 1:
                sl[a] = -1
                vals[tuple(sl)] = np.minimum(vals[tuple(sl)], -1e-9)
    out = {"evaluated": evaluated}
    if not (vals.min() < 0 < vals.max()) or min(vals.shape) < 2:
        return out
    verts, faces, _, _ = marching_cubes(vals, level=0.0, allow_degenerate=False)
    verts = verts + start
    cell = np.floor(verts[faces].mean(axis=1)).astype(np.int64)
    keep = np.all((cell >= own_lo) & (cell < own_hi), axis=1)
    faces = faces[keep]
    used, faces = np.unique(faces, return_inverse=True)
    faces = faces.reshape(-1, 3)[:, ::-1]  # skimage faces up the gradient (inward): flip to outward
    verts = verts[used]
    frac = np.abs(verts - np.rint(verts))
    axis = np.argmax(frac, axis=1)
    node = np.rint(verts).astype(np.int64)
    rows = np.arange(len(verts))
    node[rows, axis] = np.floor(verts[rows, axis]).astype(np.int64)
    ny, nz = int(shape[1]), int(shape[2])
    ids = ((node[:, 0] * ny + node[:, 1]) * nz + node[:, 2]) * 3 + axis
    # Positions from the (tile-independent) node values in float64: skimage's
    # float32 positions depend on the block's origin, these do not.
    local = node - start
    step = np.zeros_like(local)
    step[rows, axis] = 1
    a = vals[local[:, 0], local[:, 1], local[:, 2]]
    b = vals[local[:, 0] + step[:, 0], local[:, 1] + step[:, 1], local[:, 2] + step[:, 2]]
    if not ((a < 0) != (b < 0)).all():
        raise RuntimeError("tiled extraction: a marching-cubes vertex is not on a sign-changing lattice edge (a bug)")
    verts = node + (a / (a - b))[:, None] * step
    if refine:  # onto f = level along each edge, in global lattice coordinates (the same in every tile); grad f from the last step
        verts, g = refine_on_edges(lambda x, gradient=False: surface.evaluate_box(x, gradient=gradient, approximate=True), verts, vals,
                                   lattice["origin"], lattice["h"], level, first_node=start, gradient=True)
    else:
        _, g = surface.evaluate_box(lattice["origin"] + verts * lattice["h"], gradient=True, approximate=True)
    glen = np.linalg.norm(g, axis=1, keepdims=True)
    normals = -g / np.where(glen > 0, glen, 1.0)
    out.update(ids=ids, verts=verts, normals=normals, faces=np.ascontiguousarray(faces))
    return out


def extract_tiled(surface, options=None, *, level: float = 0.0, closed: bool = True, client=None, progress: bool = False,
                  stats: dict | None = None, refine: bool = True, **option_values):
    """Triangle mesh of the tiled surface's level set, meshed tile by tile and welded.

    Parameters
    ----------
    surface : TiledSurface
    options : Options, optional
        Its ``extract`` group (``resolution``: cells along the longest side
        of the bounds, "auto": :func:`o3drbf.options.auto_resolution` of the
        tiles' median constraint spacing; ``voxel_size`` in data units,
        overriding it; ``bounds``, default ``surface.metadata["bounds"]``)
        and its ``tiles`` group (``scheduler``, ``workers``, ``memory_limit``).
    level : float
    closed : bool
        Cap the surface at the lattice's faces (closed mesh).
    client : None, "synchronous", scheduler address or distributed.Client, optional
        Where tiles run (:func:`o3drbf.tiles.cluster.tile_client`); default the ``scheduler`` option.
    progress : bool
        One bar tick per tile and pass.
    stats : dict, optional
        Filled with counts and timings (``evaluated``, ``coarse_nodes``, seconds,
        CPU seconds per pass ``cpu``) and ``workers``: per worker, tasks,
        summed task seconds and peak memory (:func:`o3drbf.tiles.cluster.worker_summary`).
    refine : bool
        Move every vertex along its lattice edge onto f = ``level`` (three
        false-position steps, as :func:`o3drbf.extract.extract_mesh` does by default).
    **option_values
        Keys of :data:`o3drbf.options.DEFAULTS` over ``options`` (``resolution=128``, ``workers=4``, ...).

    Returns
    -------
    open3d.geometry.TriangleMesh
        Data coordinates, outward faces and vertex normals.

    Raises
    ------
    RuntimeError
        No surface at ``level`` inside ``bounds``.

    Examples
    --------
    >>> from o3drbf.synthetic.shapes import Torus
    >>> from o3drbf.tiles.extract import extract_tiled
    >>> from o3drbf.tiles.fit import fit_tiled
    >>> pts, nrm = Torus(0.7, 0.25).sample(2000, seed=1)
    >>> surface = fit_tiled(pts, nrm, tiles=2, scheduler="synchronous", global_count=300, surface_count_per_tile=500)
    >>> mesh = extract_tiled(surface, resolution=32, scheduler="synchronous")
    >>> mesh.is_watertight(), mesh.euler_poincare_characteristic()
    (True, 0)
    """
    import open3d as o3d

    from o3drbf.options import Options, auto_resolution

    opts = Options.create(options, **option_values)
    opts.extract.validate()
    opts.tiles.validate()
    resolution = opts.extract.resolution
    if resolution == "auto":
        spacings = [t["spacing"] for t in surface.metadata.get("tiles", []) if t.get("constraints") and np.isfinite(t.get("spacing", np.nan))]
        resolution = auto_resolution(float(np.median(spacings)) if spacings else float("nan"))
    voxel_size, bounds = opts.extract.voxel_size, opts.extract.bounds
    run_on = client if client is not None else opts.tiles.scheduler
    workers = opts.tiles.workers
    level = check_number("level", level)
    lat = lattice_for(surface, resolution, voxel_size, bounds)
    count = len(surface.partition)
    nc = np.array(lat["coarse"])
    t0, c0 = time.perf_counter(), time.process_time()
    records: list = []
    with tile_client(run_on, tasks=count, workers=workers, memory_limit=opts.tiles.memory_limit) as c:
        parts = run_tasks(c, coarse_task, count, {"surface": surface, "lattice": lat, "level": level}, progress=progress,
                          desc="coarse lattice", records=records)
        cv = np.full(tuple(nc + 1), np.nan)
        for p in parts:
            if p is not None:
                lo, v = p
                cv[lo[0] : lo[0] + v.shape[0], lo[1] : lo[1] + v.shape[1], lo[2] : lo[2] + v.shape[2]] = v
        if np.isnan(cv).any():
            raise RuntimeError("tiled extraction: coarse lattice nodes left unowned; the tile cells do not cover the bounds (a bug)")
        t_coarse = time.perf_counter() - t0
        corners = [cv[a : a + nc[0], b : b + nc[1], d : d + nc[2]] for a in (0, 1) for b in (0, 1) for d in (0, 1)]
        mn, mx = np.min(corners, axis=0), np.max(corners, axis=0)
        absmin = np.min(np.abs(corners), axis=0)
        band = ((mn <= 0) & (mx >= 0)) | (absmin <= BAND_MARGIN * (mx - mn))
        steps = crossing_steps(cv)
        if steps.size == 0:
            raise RuntimeError(f"No surface found at level {level}: f - level ranges over [{cv.min():.3g}, {cv.max():.3g}] on the coarse lattice")
        eps = CORNER_GAP * float(np.median(steps)) / lat["stride"]
        t1, c1 = time.perf_counter(), time.process_time()
        pieces = run_tasks(c, fine_task, count, {"surface": surface, "lattice": lat, "coarse_values": cv, "band": band,
                                                 "eps": eps, "level": level, "closed": closed, "refine": refine}, progress=progress, desc="meshing tiles",
                           records=records)
        t_fine = time.perf_counter() - t1
    c2 = time.process_time()
    evaluated = int(sum(p["evaluated"] for p in pieces if p is not None))
    pieces = [p for p in pieces if p is not None and "ids" in p]
    if not pieces:
        raise RuntimeError(f"No surface found at level {level} in the fine lattice")
    ids = np.concatenate([p["ids"] for p in pieces])
    verts = np.concatenate([p["verts"] for p in pieces])
    vnorm = np.concatenate([p["normals"] for p in pieces])
    offsets = np.cumsum([0] + [len(p["ids"]) for p in pieces])
    faces = np.concatenate([p["faces"] + off for p, off in zip(pieces, offsets[:-1])])
    uniq, first, inverse = np.unique(ids, return_index=True, return_inverse=True)
    mismatch = float(np.abs(verts - verts[first][inverse]).max()) if len(verts) else 0.0
    faces = inverse[faces]
    box_verts = lat["origin"] + verts[first] * lat["h"]
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(surface.normalization.inverse(box_verts)),
        o3d.utility.Vector3iVector(faces.astype(np.int32)),
    )
    mesh.vertex_normals = o3d.utility.Vector3dVector(np.ascontiguousarray(vnorm[first], dtype=float))
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    if stats is not None:
        stats.update(
            lattice=lat["shape"], stride=lat["stride"], coarse_nodes=int(cv.size), band_cells=int(band.sum()),
            evaluated=evaluated, vertices_before_weld=int(len(ids)),
            vertices=int(len(uniq)), weld_mismatch=mismatch, coarse_seconds=t_coarse, fine_seconds=t_fine,
            seconds=time.perf_counter() - t0, workers=worker_summary(records),
            cpu={"coarse_client": c1 - c0, "fine_client": c2 - c1, "weld": time.process_time() - c2,
                 "coarse_tasks": float(sum(r["cpu"] for r in records[:count])), "fine_tasks": float(sum(r["cpu"] for r in records[count:]))},
        )
    log.info("tiled extraction: lattice %s, %d vertices (%d before welding), %d triangles in %.1f s",
             lat["shape"], len(uniq), len(ids), len(faces), time.perf_counter() - t0)
    return mesh
