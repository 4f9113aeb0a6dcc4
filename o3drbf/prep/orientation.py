"""Given normals checked against the data, and repaired when they are wrong.

Wrong normals are the most common silent failure of a normal-based fit:
exterior constraints go along the normals, so a normal pointing inward puts
an "outside" constraint inside the object.  Two tests, both on the points
alone (no fit needed):

- consistency: between neighbouring points, the fraction whose normals
  clearly point opposite ways, each pair compared after reflecting one
  normal in the plane that bisects the two points (so that a sphere's
  normals agree exactly, and the two sides of a sharp edge or of a thin wall
  agree too).  Correct normals disagree almost nowhere; normals flipped at
  random disagree on about half the pairs;
- outside direction: at the vertices of each piece's convex hull the
  outward normal must point out of the hull (positive dot product with the
  mean outward normal of the hull facets around that vertex).  Normals that
  all point inward fail it at nearly every hull vertex.

With cameras and ``point_camera`` a third test is exact: a point's camera
saw its front, so its normal must face that camera.

:func:`check_normals` applies them and repairs what fails: normals facing
away from their own camera are flipped; inconsistent normals are
re-oriented over the neighbour graph (Open3D's
``orient_normals_consistent_tangent_plane`` on the given directions), each
neighbour-graph piece then turned outward by the hull test, and only the
given normals that disagree with the result are flipped; consistent normals
that point inward are flipped as a whole.  Normals that pass are returned
unchanged (the same array).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["NormalCheck", "check_normals", "normal_disagreement", "inward_fraction", "INCONSISTENT_MAX", "INWARD_MIN", "CHECK_MAX"]

#: Given normals are re-oriented when more than this fraction of the
#: neighbour pairs on one sheet point opposite ways.
INCONSISTENT_MAX = 0.1

#: A piece's normals are flipped as a whole when at least this fraction of
#: its convex-hull vertices have normals pointing into the hull.
INWARD_MIN = 0.8

#: At most this many points (a seeded random subset) are tested.
CHECK_MAX = 20000

_NEIGHBOURS = 8
_MIN_PIECE = 20


@dataclass
class NormalCheck:
    """What :func:`check_normals` found and did.

    Attributes
    ----------
    action : str
        "kept", "flipped toward cameras", "flipped", "re-oriented" (or two
        of them joined by " + ").
    flipped : int
        Normals flipped.
    disagreement : float
        Fraction of same-sheet neighbour pairs with opposite normals, before.
    inward : float
        Fraction of convex-hull vertices with normals into the hull, before
        (NaN when no piece was large enough to test).
    away_from_camera : int
        Normals facing away from the camera that saw their point (0 without
        cameras).
    reason : str
        One line for the summary.
    """

    action: str = "kept"
    flipped: int = 0
    disagreement: float = 0.0
    inward: float = float("nan")
    away_from_camera: int = 0
    reason: str = ""

    @property
    def changed(self) -> bool:
        """True when any normal was flipped."""
        return self.flipped > 0


def _pair_scores(points: np.ndarray, normals: np.ndarray, k: int):
    """k-nearest-neighbour pairs (i, j) and how well their normals agree.

    The score compares n_i with n_j reflected in the plane that bisects the
    segment p_i p_j: ``n_i . n_j - 2 (n_i . d)(n_j . d)``, d the unit vector
    from p_i to p_j.  It is symmetric in i and j, exactly 1 between any two
    points of a sphere with outward normals, about 1 across a sharp edge and
    between the two sides of a thin wall (where the plain n_i . n_j is about
    0 or -1), and its sign flips with either normal.
    """
    k = min(k, len(points) - 1)
    _, nb = cKDTree(points).query(points, k=k + 1, workers=-1)
    i = np.repeat(np.arange(len(points)), k)
    j = nb[:, 1:].ravel()
    d = points[j] - points[i]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    score = np.einsum("ij,ij->i", normals[i], normals[j]) - 2.0 * np.einsum("ij,ij->i", normals[i], d) * np.einsum("ij,ij->i", normals[j], d)
    return i, j, score


def normal_disagreement(points, normals, k: int = _NEIGHBOURS) -> float:
    """Fraction of neighbour pairs whose normals clearly point opposite ways.

    Pairs are compared by the reflected score of :func:`_pair_scores`; only
    clear ones (``|score| > 0.5``) count.

    Parameters
    ----------
    points, normals : (N, 3) ndarray
    k : int
        Neighbours per point.

    Returns
    -------
    float
        In [0, 1]; 0 when no pair qualifies.
    """
    pts, nrm = np.asarray(points, dtype=float), np.asarray(normals, dtype=float)
    _, _, score = _pair_scores(pts, nrm, k)
    clear = np.abs(score) > 0.5
    return float(np.mean(score[clear] < 0)) if clear.any() else 0.0


def _hull_votes(points: np.ndarray, normals: np.ndarray):
    """(inward, tested): hull vertices whose normal points into the convex hull, and how many were tested."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(points)
    except (QhullError, ValueError):
        return 0, 0
    outward = np.zeros_like(points)
    for simplex, eq in zip(hull.simplices, hull.equations):
        outward[simplex] += eq[:3]
    verts = hull.vertices
    score = np.einsum("ij,ij->i", normals[verts], outward[verts])
    return int((score < 0).sum()), int(len(verts))


def _pieces(points: np.ndarray, k: int) -> np.ndarray:
    """Connected components of the symmetric k-nearest-neighbour graph (labels)."""
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components

    k = min(k, len(points) - 1)
    _, nb = cKDTree(points).query(points, k=k + 1, workers=-1)
    rows = np.repeat(np.arange(len(points)), k)
    graph = sparse.coo_matrix((np.ones(rows.size), (rows, nb[:, 1:].ravel())), shape=(len(points), len(points)))
    return connected_components(graph, directed=False)[1]


def inward_fraction(points, normals, k: int = 10) -> float:
    """Fraction of convex-hull vertices (of each neighbour-graph piece) whose normal points into the hull.

    Parameters
    ----------
    points, normals : (N, 3) ndarray
    k : int
        Neighbours of the graph whose connected pieces are tested apart.

    Returns
    -------
    float
        NaN when no piece has enough points for a hull.
    """
    pts, nrm = np.asarray(points, dtype=float), np.asarray(normals, dtype=float)
    labels = _pieces(pts, k)
    inward = tested = 0
    for c in np.unique(labels):
        sel = labels == c
        if sel.sum() >= _MIN_PIECE:
            a, b = _hull_votes(pts[sel], nrm[sel])
            inward, tested = inward + a, tested + b
    return inward / tested if tested else float("nan")


def _reoriented(points: np.ndarray, normals: np.ndarray, k: int) -> np.ndarray:
    """The given normal lines oriented consistently over the neighbour graph, each piece outward by its hull.

    Orientation spreads along a maximum spanning tree of the ``k``-nearest
    neighbour graph.  An edge (i, j) compares n_i with n_j reflected in the
    plane that bisects the segment p_i p_j: on a sphere the reflection is
    n_i exactly, across a sharp edge or between the two sides of a thin wall
    it still points the way n_i does, where the plain n_i . n_j is about 0
    or -1.  The spanning tree keeps the edges where that comparison is
    clearest.
    """
    from scipy import sparse
    from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

    n = len(points)
    i, j, score = _pair_scores(points, normals, k)
    cost = sparse.coo_matrix((2.0 - np.abs(score), (i, j)), shape=(n, n)).tocsr()
    cost = cost.maximum(cost.T)  # symmetric: an edge found from either end (the score is symmetric in i, j)
    agree = sparse.coo_matrix((np.where(score >= 0, 1.0, -1.0), (i, j)), shape=(n, n)).tocsr()
    agree = agree + agree.T  # +-1 or +-2 where both ends found the edge: the sign is what counts
    tree = minimum_spanning_tree(cost)
    tree = tree + tree.T
    sign = np.ones(n)
    _, labels = connected_components(tree, directed=False)
    for c in np.unique(labels):
        root = int(np.flatnonzero(labels == c)[0])
        order, parent = breadth_first_order(tree, root, directed=False)
        step = np.sign(np.asarray(agree[parent[order[1:]], order[1:]]).ravel())
        for node, up, s in zip(order[1:], parent[order[1:]], step):
            sign[node] = sign[up] * s
    out = normals * sign[:, None]
    pieces = _pieces(points, 10)
    for c in np.unique(pieces):
        sel = pieces == c
        a, b = _hull_votes(points[sel], out[sel]) if sel.sum() >= _MIN_PIECE else (0, 0)
        if b and a > b / 2:
            out[sel] = -out[sel]
        elif not b and np.einsum("ij,ij->i", out[sel], points[sel] - points[sel].mean(axis=0)).mean() < 0:
            out[sel] = -out[sel]
    return out


def check_normals(points, normals, cameras=None, point_camera=None, *, k: int = 15, seed: int = 0) -> tuple[np.ndarray, NormalCheck]:
    """Check given normals against the points (and cameras) and repair them when they are wrong.

    Parameters
    ----------
    points, normals : (N, 3) array_like
        The points and their given (outward) normals.
    cameras : sequence of Camera, optional
    point_camera : (N,) array_like of int, optional
        The camera that saw each point (-1: unknown).
    k : int
        Neighbours for the consistent re-orientation.
    seed : int
        Seed of the subset tested when there are more than ``CHECK_MAX`` points.

    Returns
    -------
    normals : (N, 3) ndarray
        The given array itself when nothing was wrong, else a repaired copy.
    NormalCheck
    """
    pts = np.asarray(points, dtype=float)
    nrm = np.asarray(normals, dtype=float)
    out = nrm
    actions, notes, flipped = [], [], np.zeros(len(pts), dtype=bool)
    away = 0
    if cameras is not None and point_camera is not None:
        pc = np.asarray(point_camera).reshape(-1)
        seen = np.flatnonzero(pc >= 0)
        facing = np.ones(len(pts))
        for c, camera in enumerate(cameras):
            sel = seen[pc[seen] == c]
            if len(sel):
                facing[sel] = np.einsum("ij,ij->i", nrm[sel], camera.toward(pts[sel])[0])
        bad = facing < 0
        away = int(bad.sum())
        if away:
            out = out.copy()
            out[bad] = -out[bad]
            flipped |= bad
            actions.append("flipped toward cameras")
            notes.append(f"{away:,} facing away from the camera that saw them")
    if len(pts) < _MIN_PIECE:
        return out, NormalCheck("+".join(actions) or "kept", int(flipped.sum()), 0.0, float("nan"), away,
                                "; ".join(notes) or "too few points to check")
    # The tests on a seeded subset of large clouds: both are fractions, which a random subset keeps.
    test = np.arange(len(pts)) if len(pts) <= CHECK_MAX else np.sort(np.random.default_rng(seed).choice(len(pts), CHECK_MAX, replace=False))
    disagreement = normal_disagreement(pts[test], out[test])
    inward = inward_fraction(pts[test], out[test])
    if cameras is None or point_camera is None:
        if disagreement > INCONSISTENT_MAX:
            fixed = _reoriented(pts, out, k)
            wrong = np.einsum("ij,ij->i", fixed, out) < 0
            if wrong.any():
                out = np.where(wrong[:, None], -out, out)
                flipped ^= wrong
                actions.append("re-oriented")
                notes.append(f"{disagreement:.0%} of neighbouring normals pointed opposite ways: re-oriented consistently, "
                             f"{int(wrong.sum()):,} flipped")
        elif np.isfinite(inward) and inward >= INWARD_MIN:
            out = -out
            flipped = ~flipped
            actions.append("flipped")
            notes.append(f"they pointed inward ({inward:.0%} of the convex-hull points): all flipped")
    action = " + ".join(actions) or "kept"
    reason = "; ".join(notes) if notes else (f"consistent ({disagreement:.1%} of neighbouring normals disagree), outward"
                                             + ("" if not np.isfinite(inward) else f" ({inward:.0%} of the convex-hull points inward)"))
    return out, NormalCheck(action, int(flipped.sum()), float(disagreement), float(inward), away, reason)
