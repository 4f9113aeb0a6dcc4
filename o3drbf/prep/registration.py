"""Scans registered to each other: small rigid errors between range scans corrected.

Scans that come with their poses (range images, depth frames, photogrammetry
views) are rarely registered exactly: each is off by a small rigid motion,
so where two scans overlap the surface appears twice, a fraction of the
noise apart.  Smoothing averages the two sheets but cannot tell which is
right, and the mix changes from place to place with the scans' coverage.
:func:`refine_registration` moves every scan rigidly onto the others
(point-to-plane ICP, each scan in turn against all the others, repeated
until the scans stop moving), then removes the mean motion (the errors are
assumed to average out, as nothing else says where the object is).

The ICP is a few lines of Gauss-Newton rather than Open3D's
``registration_icp``, for two things that one lacks: a prior on the motion
(directions the overlap does not pin, a plane sliding along itself or a
cylinder turning about its axis, stay where the scan was instead of
drifting on the noise: a first version built on Open3D's ICP slid 3-view
scans of a cube, which overlap on one face per pair, by up to the cube's
size) and matches only
between normals turned toward each scan's own sensor (the two sides of a
thin wall face away from each other and are never matched).

The motions are kept only when they make the scans markedly more
consistent: the median point-to-plane distance between overlapping scans
must fall by at least ``min_gain``.  Scans that were registered already
(the noise, not a pose error, separates them) are left exactly as they
were.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from o3drbf.prep.sampling import neighbourhood_scatter
from o3drbf.validation import as_points, check_number

__all__ = ["Registration", "refine_registration", "apply_transforms"]

#: Points per scan used for the ICP (a seeded random subset): the error is
#: rigid, so a few thousand points determine it.
SAMPLE_PER_SCAN = 6000
#: ... and at most this many over all the scans (at least 1,000 a scan), so
#: the cost grows with the number of scans, not with the points.
SAMPLE_TOTAL = 60000
#: Most scans registered: each pass aligns every scan to all the others, so
#: more scans (a video's frames) are a job for a registration tool.
MAX_SCANS = 64
#: Fewest points a scan needs to be registered (others stay where they are).
MIN_SCAN_POINTS = 200
#: Neighbours for each scan's own normals (turned toward the scan's sensor).
NORMAL_NEIGHBOURS = 24
#: Matches between scans count only where the normals agree this well (cosine).
NORMAL_AGREEMENT = 0.8


@dataclass(frozen=True, eq=False)
class Registration:
    """What :func:`refine_registration` found.

    Attributes
    ----------
    transforms : (C, 4, 4) ndarray
        For each scan (camera index), the rigid motion applied to its points
        (``x' = T[:3, :3] @ x + T[:3, 3]``); the identity for scans not
        moved, and for every scan when ``applied`` is False.
    applied : bool
        Whether the points were moved.
    before, after : float
        Median point-to-plane distance (data units) of the scans' points to
        the other scans where they overlap, before and after the motions.
    motion : (C,) ndarray
        Largest displacement of each scan's points by its motion (data units).
    rounds : int
        Passes over the scans.
    scans : int
        Scans registered (those with at least :data:`MIN_SCAN_POINTS` points).
    reason : str
        One line: what was done and why.
    """

    transforms: np.ndarray
    applied: bool
    before: float
    after: float
    motion: np.ndarray
    rounds: int
    scans: int
    reason: str
    parameters: dict = field(default_factory=dict)

    def __str__(self) -> str:
        return self.reason


def apply_transforms(points, point_camera, transforms, vectors: bool = False) -> np.ndarray:
    """Each scan's points moved by its transform (points of no scan, ``point_camera < 0``, stay).

    With ``vectors=True`` the rows are directions (normals): only rotated.
    """
    pts = np.array(as_points(points, min_count=0), dtype=float)
    owner = np.asarray(point_camera)
    for k, T in enumerate(np.asarray(transforms, dtype=float)):
        sel = owner == k
        if sel.any():
            pts[sel] = pts[sel] @ T[:3, :3].T + (0.0 if vectors else T[:3, 3])
    return pts


def _others(arrays: list, k: int) -> np.ndarray:
    """The rows of every scan but scan ``k``, stacked."""
    return np.vstack([a for i, a in enumerate(arrays) if i != k])


def _scan_normals(points: np.ndarray, toward: np.ndarray | None) -> np.ndarray:
    """Normals of one scan's points, turned toward its sensor where ``toward`` (unit directions) is known.

    Each normal is the least-squares plane's of the point's ``NORMAL_NEIGHBOURS`` nearest points (itself
    included), the covariance's eigenvector of the smallest eigenvalue: Open3D's ``estimate_normals`` with
    ``KDTreeSearchParamKNN``, without importing Open3D (whose import is a large part of a short run)."""
    k = min(NORMAL_NEIGHBOURS, len(points))
    _, idx = cKDTree(points).query(points, k=k, workers=-1)
    _, _, scatter = neighbourhood_scatter(points, idx.reshape(len(points), k))
    _, vecs = np.linalg.eigh(scatter)
    n = np.ascontiguousarray(vecs[:, :, 0])
    if toward is not None:
        n = n * np.where(np.einsum("ij,ij->i", n, toward) < 0, -1.0, 1.0)[:, None]
    return n


def _plane_residuals(src: np.ndarray, src_normals: np.ndarray, tgt: np.ndarray, tgt_normals: np.ndarray, tree: cKDTree, reach: float):
    """Signed point-to-plane residuals of ``src`` to its nearest target point within ``reach``.

    A match counts only where the two normals agree within about 37 degrees
    (a point near an edge is not matched to the other face; with normals
    turned toward the sensors, nor the two sides of a thin wall).  Returns
    (kept mask over ``src``, residuals, target normals) of the kept matches.
    """
    d, j = tree.query(src, distance_upper_bound=reach)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    ok &= np.einsum("ij,ij->i", src_normals, tgt_normals[jj]) >= NORMAL_AGREEMENT
    n = tgt_normals[j[ok]]
    return ok, np.einsum("ij,ij->i", src[ok] - tgt[j[ok]], n), n


def _icp(src: np.ndarray, src_normals: np.ndarray, tgt: np.ndarray, tgt_normals: np.ndarray, reach: float, scale: float,
         start: np.ndarray, iterations: int = 8) -> np.ndarray:
    """A point-to-plane ICP of a scan onto the others, with a prior on its motion: its new 4x4 pose.

    ``src`` is the scan as given and ``start`` its present motion.  Each
    Gauss-Newton step solves ``(J^T W J + mu I) x = -J^T W r - mu x0`` for a
    small rotation (scaled by the scan's radius, so all six unknowns are
    displacements) and a translation, Tukey weights at ``4 scale``; ``x0`` is
    the motion so far, so ``mu`` (1 % of the mean eigenvalue) keeps the
    whole motion small: directions the overlap does not pin (a plane sliding
    along itself, a cylinder turning about its axis) stay where the scan was
    instead of drifting on the noise.
    """
    tree = cKDTree(tgt)
    centre = src.mean(axis=0)
    radius = float(np.linalg.norm(src - centre, axis=1).max()) or 1.0
    T = start.copy()
    c = 4.0 * scale
    for _ in range(iterations):
        cur, cur_n = src @ T[:3, :3].T + T[:3, 3], src_normals @ T[:3, :3].T
        ok, r, n = _plane_residuals(cur, cur_n, tgt, tgt_normals, tree, reach)
        if ok.sum() < 12:
            break
        moved_centre = T[:3, :3] @ centre + T[:3, 3]
        pc = (cur[ok] - moved_centre) / radius
        J = np.hstack([np.cross(pc, n), n])
        w = np.clip(1.0 - (r / c) ** 2, 0.0, None) ** 2
        A = (J * w[:, None]).T @ J
        mu = 0.01 * float(np.trace(A)) / 6.0
        if not mu > 0:
            break
        x0 = np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec() * radius, moved_centre - centre])
        x = np.linalg.solve(A + mu * np.eye(6), -(J * w[:, None]).T @ r - mu * x0)
        step = np.eye(4)
        step[:3, :3] = Rotation.from_rotvec(x[:3] / radius).as_matrix()
        step[:3, 3] = moved_centre - step[:3, :3] @ moved_centre + x[3:]
        T = step @ T
        if np.linalg.norm(x) < 1e-3 * scale:
            break
    return T


def _overlap(samples: list, normals: list, reach: float, trees: list | None = None) -> tuple[list, np.ndarray]:
    """For each scan, its sample points matched on another scan within ``reach``; and all the matches' |residuals|.
    ``trees[k]``, when given, is the KD-tree of ``_others(samples, k)``."""
    kept, resid = [], []
    for k in range(len(samples)):
        tgt = _others(samples, k)
        ok, r, _ = _plane_residuals(samples[k], normals[k], tgt, _others(normals, k), cKDTree(tgt) if trees is None else trees[k], reach)
        kept.append(ok)
        resid.append(np.abs(r))
    return kept, np.concatenate(resid)


def _consistency(samples: list, normals: list, pairs: list, reach: float, trees: list | None = None) -> float:
    """Median |point-to-plane| distance of the overlap points ``pairs[k]`` of each scan to the other scans.

    A point that no longer finds a match counts as ``reach`` (sliding scans
    apart does not look consistent).  ``trees`` as in :func:`_overlap`.
    """
    values = []
    for k in range(len(samples)):
        tgt = _others(samples, k)
        tree = cKDTree(tgt) if trees is None else trees[k]
        ok, r, _ = _plane_residuals(samples[k][pairs[k]], normals[k][pairs[k]], tgt, _others(normals, k), tree, reach)
        values.append(np.minimum(np.abs(r), reach))
        values.append(np.full(int((~ok).sum()), reach))
    v = np.concatenate(values)
    return float(np.median(v)) if len(v) else float("nan")


def _motion(T: np.ndarray, pts: np.ndarray) -> float:
    return float(np.linalg.norm(pts @ (T[:3, :3] - np.eye(3)).T + T[:3, 3], axis=1).max()) if len(pts) else 0.0


def refine_registration(points, point_camera, n_cameras: int | None = None, *, toward=None, max_rounds: int = 10,
                        min_gain: float = 0.1, seed: int = 0) -> Registration:
    """Rigid motions that register each scan to the others.

    Parameters
    ----------
    points : (N, 3) array_like
        Data coordinates, outliers and all.
    point_camera : (N,) int array_like
        The scan (camera index) of each point; ``-1`` for points of no scan.
    n_cameras : int, optional
        Number of cameras (default: the largest index + 1).
    toward : (N, 3) array_like, optional
        Unit direction from each point toward its sensor: normals are then
        turned toward the sensors and the two sides of a thin wall are never
        matched (strongly advised; without it the normals are unoriented).
    max_rounds : int
        Most passes over the scans (each scan moved onto all the others in
        turn); the passes stop earlier once no scan moves by more than a
        twentieth of the point spacing.
    min_gain : float in [0, 1)
        The motions are applied only when they lower the median
        point-to-plane distance between overlapping scans by at least this
        fraction.
    seed : int
        Seeds the per-scan subsets.

    Returns
    -------
    Registration
    """
    pts = as_points(points, min_count=0)
    owner = np.asarray(point_camera)
    if owner.shape != (len(pts),):
        raise ValueError(f"point_camera must have one entry per point ({len(pts)}), got shape {owner.shape}")
    view = None if toward is None else as_points(toward, min_count=0)
    if view is not None and len(view) != len(pts):
        raise ValueError(f"toward must have one row per point ({len(pts)}), got {len(view)}")
    max_rounds = check_number("max_rounds", max_rounds, low=1, integer=True)
    min_gain = check_number("min_gain", min_gain, low=0.0, high=1.0)
    if min_gain >= 1.0:
        raise ValueError(f"min_gain must be below 1, got {min_gain}")
    n_cameras = int(owner.max(initial=-1)) + 1 if n_cameras is None else check_number("n_cameras", n_cameras, low=0, integer=True)
    identity = np.tile(np.eye(4), (n_cameras, 1, 1))
    params = {"max_rounds": max_rounds, "min_gain": min_gain}
    scans = [k for k in range(n_cameras) if int((owner == k).sum()) >= MIN_SCAN_POINTS]
    if len(scans) < 2:
        return Registration(identity, False, float("nan"), float("nan"), np.zeros(n_cameras), 0, len(scans),
                            "scans not registered: fewer than two scans with points", params)

    if len(scans) > MAX_SCANS:
        return Registration(identity, False, float("nan"), float("nan"), np.zeros(n_cameras), 0, len(scans),
                            f"{len(scans)} scans left as they were: more than {MAX_SCANS} (register them with a registration "
                            "tool first, or pass register='none')", params)
    rng = np.random.default_rng(seed)
    per_scan = min(SAMPLE_PER_SCAN, max(1000, SAMPLE_TOTAL // len(scans)))
    samples, normals = [], []
    for k in scans:
        idx = np.flatnonzero(owner == k)
        if len(idx) > per_scan:
            idx = np.sort(rng.choice(idx, per_scan, replace=False))
        p = np.array(pts[idx], dtype=float)
        samples.append(p)
        normals.append(_scan_normals(p, None if view is None else view[idx]))
    allp = np.vstack(samples)
    spacing = float(np.median(cKDTree(allp).query(allp[:: max(1, len(allp) // 20000)], k=2)[0][:, 1]))
    # the scans' present disagreement sets the scale of the robust loss and how far a match may be
    trees = [cKDTree(_others(samples, k)) for k in range(len(samples))]  # the scans as given: for the three tests below
    _, resid = _overlap(samples, normals, 3.0 * spacing, trees)
    if len(resid) < 12 * len(scans):
        return Registration(identity, False, float("nan"), float("nan"), np.zeros(n_cameras), 0, len(scans),
                            f"{len(scans)} scans left as they were: they hardly overlap", params)
    scale = max(1.4826 * float(np.median(resid)), 0.05 * spacing)  # the median |r| of a Gaussian is 0.67 sigma
    reach = 2.0 * spacing + 4.0 * scale
    pairs, _ = _overlap(samples, normals, reach, trees)
    before = _consistency(samples, normals, pairs, reach, trees)

    T = [np.eye(4) for _ in scans]
    cur = [x.copy() for x in samples]
    cur_n = [x.copy() for x in normals]
    rounds = 0
    for rounds in range(1, max_rounds + 1):
        moved = 0.0
        for k in range(len(scans)):
            new = _icp(samples[k], normals[k], _others(cur, k), _others(cur_n, k), reach, scale, T[k])
            moved = max(moved, _motion(new @ np.linalg.inv(T[k]), cur[k]))
            T[k] = new
            cur[k] = samples[k] @ new[:3, :3].T + new[:3, 3]
            cur_n[k] = normals[k] @ new[:3, :3].T
        if moved < 0.05 * spacing:
            break
        if rounds == 1 and _consistency(cur, cur_n, pairs, reach) > (1.0 - 0.5 * min_gain) * before:
            # the first pass brings most of the gain (docs/data/design-measurements.md, "Registration passes"):
            # nothing to win here, so no more passes
            break

    # the gauge: the mean motion removed (the pose errors are taken to average out)
    centre = allp.mean(axis=0)
    mean_rot = Rotation.from_matrix(np.stack([t[:3, :3] for t in T])).mean().as_matrix()
    mean_shift = np.mean([t[:3, :3] @ centre + t[:3, 3] - centre for t in T], axis=0)
    G = np.eye(4)
    G[:3, :3] = mean_rot.T
    G[:3, 3] = centre - mean_rot.T @ (centre + mean_shift)
    transforms = identity.copy()
    for j, k in enumerate(scans):
        transforms[k] = G @ T[j]
    final = [x @ transforms[k][:3, :3].T + transforms[k][:3, 3] for x, k in zip(samples, scans)]
    final_n = [x @ transforms[k][:3, :3].T for x, k in zip(normals, scans)]
    after = _consistency(final, final_n, pairs, reach)
    motion = np.zeros(n_cameras)
    for j, k in enumerate(scans):
        motion[k] = _motion(transforms[k], samples[j])
    applied = bool(np.isfinite(before) and np.isfinite(after) and after <= (1.0 - min_gain) * before)
    verdict = "moved" if applied else "left as they were"
    reason = (f"{len(scans)} scans {verdict}: median distance between overlapping scans {before:.3g} -> {after:.3g} "
              f"(needs a {100 * min_gain:.0f} % drop), largest motion {motion.max():.3g} ({rounds} pass{'es' if rounds != 1 else ''})")
    return Registration(transforms if applied else identity, applied, before, after, motion, rounds, len(scans), reason,
                        dict(params, spacing=spacing, reach=reach, scale=scale))
