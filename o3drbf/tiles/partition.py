"""Tiles: a k-d split of the points balanced by count, and overlapping supports.

A tile ``t`` has a *cell* ``[lo_t, hi_t]`` (the cells of all tiles partition
the root box exactly) and a *support* centred on the cell, ``|x_k - o_t,k| <
rho_t,k``, larger than the cell by an overlap margin on every side.  Its
partition-of-unity weight is the Wendland function of the box distance

    w_t(x) = psi(r),  r = max_k |x_k - o_t,k| / rho_t,k,  psi(r) = (1 - r)^4_+ (4 r + 1)

(design-notes.md, "Tiles with a partition of unity").  Every point of the
root box lies in some cell, and so strictly inside that tile's support:
sum_s w_s > 0 everywhere in the root box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from o3drbf.validation import as_points, check_number

__all__ = ["Partition", "kd_split", "wendland", "wendland_derivative", "box_distance", "ArrayPoints", "scan_bounds",
           "sample_indices", "spread_to_tiles", "read_tile_points"]


def wendland(r: np.ndarray) -> np.ndarray:
    """psi(r) = (1 - r)^4 (4 r + 1) for r < 1, else 0 (psi(0) = 1; C^2 at r = 1).

    Parameters
    ----------
    r : (...) array, r >= 0

    Returns
    -------
    (...) array
    """
    r = np.asarray(r, dtype=float)
    s = np.clip(1.0 - r, 0.0, None)
    return s**4 * (4.0 * r + 1.0)


def wendland_derivative(r: np.ndarray) -> np.ndarray:
    """d psi / d r = -20 r (1 - r)^3 for r < 1, else 0.

    Parameters
    ----------
    r : (...) array, r >= 0

    Returns
    -------
    (...) array
    """
    r = np.asarray(r, dtype=float)
    s = np.clip(1.0 - r, 0.0, None)
    return -20.0 * r * s**3


def box_distance(points: np.ndarray, centre: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """r = max_k |x_k - o_k| / rho_k and its gradient (one-sided on the ridges).

    Parameters
    ----------
    points : (M, 3) array
    centre, rho : (3,) arrays, rho > 0

    Returns
    -------
    r : (M,) array
    grad_r : (M, 3) array
        sign(x_k - o_k) / rho_k on the axis attaining the max, 0 elsewhere.
    """
    d = (np.asarray(points, dtype=float) - centre) / rho
    a = np.abs(d)
    k = np.argmax(a, axis=1)
    rows = np.arange(len(a))
    r = a[rows, k]
    grad = np.zeros_like(d)
    grad[rows, k] = np.sign(d[rows, k]) / rho[k]
    return r, grad


@dataclass(frozen=True)
class Partition:
    """Cells and supports of the tiles (all in the same coordinates).

    Attributes
    ----------
    lo, hi : (T, 3) arrays
        Cell corners; the cells partition the root box ``[lo.min(0), hi.max(0)]``.
    centre : (T, 3) array
        Cell centres o_t (also the supports' centres).
    rho : (T, 3) array
        Support half-sizes: cell half-size plus the overlap margin, > 0.
    """

    lo: np.ndarray
    hi: np.ndarray
    centre: np.ndarray
    rho: np.ndarray

    def __len__(self) -> int:
        return len(self.lo)

    @classmethod
    def from_cells(cls, lo, hi, overlap: float = 0.25, min_overlap: float = 0.0) -> "Partition":
        """Supports around given cells.

        Parameters
        ----------
        lo, hi : (T, 3) array_like
            Cell corners, hi > lo.
        overlap : float
            Margin added on every side, as a fraction of the cell's half-size (>= 0).
        min_overlap : float
            Smallest margin, in the cells' units (>= 0).  ``overlap`` and
            ``min_overlap`` both 0 is refused: the supports must overlap.
        """
        lo = np.asarray(lo, dtype=float).reshape(-1, 3)
        hi = np.asarray(hi, dtype=float).reshape(-1, 3)
        if lo.shape != hi.shape or not (hi > lo).all():
            raise ValueError("tile cells need hi > lo on every axis; check the k-d split")
        overlap = check_number("overlap", overlap, low=0.0)
        min_overlap = check_number("min_overlap", min_overlap, low=0.0)
        if overlap == 0 and min_overlap == 0:
            raise ValueError("overlap and min_overlap are both 0: tile supports must overlap (raise overlap)")
        half = (hi - lo) / 2.0
        rho = half + np.maximum(overlap * half, min_overlap)
        return cls(lo, hi, (lo + hi) / 2.0, rho)

    def weights(self, points) -> np.ndarray:
        """w_t(x) for every point and tile: (M, T) array (dense; for tests and small M)."""
        x = as_points(points, min_count=0)
        out = np.zeros((len(x), len(self)))
        for t in range(len(self)):
            r, _ = box_distance(x, self.centre[t], self.rho[t])
            out[:, t] = wendland(r)
        return out

    def in_support(self, points, t: int) -> np.ndarray:
        """Indices of the points strictly inside tile ``t``'s support (w_t > 0)."""
        x = np.asarray(points, dtype=float)
        inside = np.all(np.abs(x - self.centre[t]) < self.rho[t], axis=1)
        return np.flatnonzero(inside)

    def to_arrays(self) -> dict:
        return {"tile_lo": self.lo, "tile_hi": self.hi, "tile_centre": self.centre, "tile_rho": self.rho}


def kd_split(points, count: int, bounds) -> tuple[np.ndarray, np.ndarray]:
    """Split ``bounds`` into ``count`` boxes holding about equal numbers of points.

    A node meant for ``k`` tiles is cut across the longest side of its box
    at the ``floor(k/2)/k`` quantile of its points' coordinates, recursively
    (any ``count``, not only powers of two).  Deterministic.

    Parameters
    ----------
    points : (N, 3) array_like
        Points inside ``bounds``.
    count : int
        Number of tiles, 1 <= count <= N.
    bounds : (2, 3) array_like
        The root box; every point must lie inside it.

    Returns
    -------
    lo, hi : (count, 3) arrays
        The cells, in depth-first order; they partition ``bounds``.
    """
    pts = as_points(points)
    count = check_number("tiles", count, low=1, high=len(pts), integer=True)
    b = np.asarray(bounds, dtype=float)
    if b.shape != (2, 3) or not (b[1] > b[0]).all():
        raise ValueError(f"bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, got {b.tolist()}")
    if (pts < b[0]).any() or (pts > b[1]).any():
        raise ValueError("kd_split: points lie outside bounds; pass bounds that contain every point")
    cells_lo, cells_hi = [], []

    def split(idx, lo, hi, k):
        if k == 1:
            cells_lo.append(lo)
            cells_hi.append(hi)
            return
        k1 = k // 2
        axis = int(np.argmax(hi - lo))
        x = pts[idx, axis]
        if len(x) >= 2:
            cut = float(np.quantile(x, k1 / k))
        else:
            cut = float(0.5 * (lo[axis] + hi[axis]))
        # Keep both children non-empty as boxes.
        span = hi[axis] - lo[axis]
        cut = min(max(cut, lo[axis] + 1e-6 * span), hi[axis] - 1e-6 * span)
        left = idx[x < cut]
        right = idx[x >= cut]
        hi_left = hi.copy()
        hi_left[axis] = cut
        lo_right = lo.copy()
        lo_right[axis] = cut
        split(left, lo, hi_left, k1)
        split(right, lo_right, hi, k - k1)

    split(np.arange(len(pts)), b[0].copy(), b[1].copy(), count)
    return np.array(cells_lo), np.array(cells_hi)


# -- points that need not fit in memory: chunked passes and per-tile stores -----------------


class ArrayPoints:
    """In-memory points with the chunk interface of :class:`o3drbf.io.files.PlyVertices`.

    Parameters
    ----------
    points : (N, 3) array
    normals : (N, 3) array or None
    point_camera : (N,) int array or None
        The camera of each point (-1 unknown).
    """

    def __init__(self, points: np.ndarray, normals: np.ndarray | None, point_camera: np.ndarray | None = None):
        self.points, self.normals, self.point_camera = points, normals, point_camera
        self.count = len(points)
        self.has_normals = normals is not None

    def __len__(self) -> int:
        return self.count

    def take(self, start: int, stop: int):
        nrm = None if self.normals is None else self.normals[start:stop]
        return self.points[start:stop], nrm

    def gather(self, index):
        index = np.asarray(index, dtype=np.int64)
        nrm = None if self.normals is None else self.normals[index]
        return self.points[index], nrm

    def chunks(self, size: int = 1_000_000):
        size = max(1, int(size))
        for start in range(0, self.count, size):
            pts, nrm = self.take(start, min(start + size, self.count))
            yield start, pts, nrm


def scan_bounds(source, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi): the points' bounding box (data coordinates), one chunk at a time.

    Raises
    ------
    ValueError
        Non-finite coordinates or normals in some chunk (the first such vertex is named).
    """
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for start, pts, nrm in source.chunks(chunk):
        bad = ~np.isfinite(pts).all(axis=1)
        if nrm is not None:
            bad |= ~np.isfinite(nrm).all(axis=1)
        if bad.any():
            raise ValueError(f"point {start + int(np.flatnonzero(bad)[0])} has NaN or infinite coordinates or normals; fix or remove it")
        lo = np.minimum(lo, pts.min(axis=0))
        hi = np.maximum(hi, pts.max(axis=0))
    return lo, hi


def sample_indices(count: int, size: int, seed: int) -> np.ndarray:
    """Sorted indices of a seeded uniform subsample of ``size`` of ``count`` points (all of them when count <= size)."""
    if count <= size:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, size=size, replace=False))


def spread_to_tiles(source, normalization, partition: "Partition", chunk: int, folder=None) -> tuple[list, np.ndarray]:
    """Hand each tile the points in its support (box coordinates), one chunk at a time.

    Parameters
    ----------
    source : PlyVertices or ArrayPoints
        Points (data coordinates), their normals (or None) and, for
        ``ArrayPoints``, each point's camera (``point_camera`` or None).
    normalization : Normalization
        Data -> box map.
    partition : Partition
    chunk : int
        Points read at a time.
    folder : path, optional
        Where the per-tile files go (storage every worker can read); None:
        per-tile arrays in this process.

    Returns
    -------
    stores : list
        Per tile: the path (str) of a float64 file of (m, 7) rows
        ``x y z nx ny nz camera`` (normals 0 without them, camera -1 when
        unknown; read it with :func:`read_tile_points`), or the same (m, 7) array.
    counts : (T,) int array
        Points per tile.

    Tile ``t`` gets its points in input order, so the stores do not depend on ``chunk``.
    """
    from pathlib import Path

    count = len(partition)
    counts = np.zeros(count, dtype=np.int64)
    parts: list = [[] for _ in range(count)]
    paths = None
    if folder is not None:
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        paths = [str(folder / f"tile-{t:05d}.f8") for t in range(count)]
        for p in paths:
            open(p, "wb").close()
    cameras = getattr(source, "point_camera", None)
    for start, pts, nrm in source.chunks(chunk):
        box = normalization.forward(pts)
        rows = np.empty((len(box), STORE_COLUMNS))
        rows[:, :3] = box
        rows[:, 3:6] = 0.0 if nrm is None else nrm
        rows[:, 6] = -1.0 if cameras is None else cameras[start:start + len(box)]
        # Sorted along each axis once per chunk: each tile tests only the points of its support's
        # thinnest slab (fewest points) on one axis.
        orders = [np.argsort(box[:, k], kind="stable") for k in range(3)]
        keys = [box[o, k] for k, o in enumerate(orders)]
        for t in range(count):
            c, r = partition.centre[t], partition.rho[t]
            ranges = [(np.searchsorted(keys[k], c[k] - r[k], "right"), np.searchsorted(keys[k], c[k] + r[k], "left")) for k in range(3)]
            k = int(np.argmin([b - a for a, b in ranges]))
            slab = np.sort(orders[k][ranges[k][0]:ranges[k][1]])
            idx = slab[partition.in_support(box[slab], t)]
            if idx.size == 0:
                continue
            counts[t] += idx.size
            if paths is None:
                parts[t].append(rows[idx])
            else:
                with open(paths[t], "ab") as fh:
                    np.ascontiguousarray(rows[idx], dtype="<f8").tofile(fh)
    if paths is not None:
        return paths, counts
    stores = []
    for t in range(count):
        stores.append(np.concatenate(parts[t]) if parts[t] else np.zeros((0, STORE_COLUMNS)))
        parts[t] = None
    return stores, counts


#: Columns of a tile store: x y z (box), nx ny nz, camera index.
STORE_COLUMNS = 7


def read_tile_points(store) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (m, 3), normals (m, 3), camera (m,) int) of one tile store from :func:`spread_to_tiles` (a path or an array)."""
    if isinstance(store, str):
        rows = np.fromfile(store, dtype="<f8")
        if rows.size % STORE_COLUMNS:
            raise RuntimeError(f"tile store {store} is truncated ({rows.size} values, not rows of {STORE_COLUMNS}); rerun the fit")
        rows = rows.reshape(-1, STORE_COLUMNS).astype(float)
    else:
        rows = np.asarray(store, dtype=float).reshape(-1, STORE_COLUMNS)
    return rows[:, :3].copy(), rows[:, 3:6].copy(), rows[:, 6].astype(np.int64)
