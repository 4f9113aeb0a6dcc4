"""The compiled cell list of the fast solver (o3drbf.solvers.fast.neighbours.CellList) against brute-force pair sums."""

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from o3drbf.solvers.fast.neighbours import CellList


def _table(radius):
    """f(r) = cos(r) sampled finely beyond the radius, with f'(r) / r."""
    dr = radius / 4000
    r = np.arange(0.0, 1.5 * radius, dr)
    tab = np.cos(r)
    dtab = np.empty_like(r)
    dtab[1:] = -np.sin(r[1:]) / r[1:]
    dtab[0] = -1.0
    return tab, dtab, dr


@pytest.fixture(params=[1, 2], ids=["cells of the radius", "cells of half the radius"])
def cloud(request, monkeypatch):
    """Points and targets; the cell lists built in the test take cells of the radius, then of half of it."""
    from o3drbf.solvers.fast import neighbours

    monkeypatch.setattr(neighbours, "CELLS_PER_POINT", 0 if request.param == 1 else 10**9)
    assert CellList(np.zeros((2, 3)), 1.0).reach == request.param
    rng = np.random.default_rng(4)
    pts = rng.uniform(-1, 1, (700, 3))
    targets = np.ascontiguousarray(np.vstack([rng.uniform(-1.2, 1.2, (300, 3)), pts[:50]]))  # some coincide with points
    return pts, targets


def test_matrix_holds_every_pair_within_the_radius_and_no_other(cloud):
    pts, targets = cloud
    radius = 0.3
    tab, _, dr = _table(radius)
    got = CellList(pts, radius).matrix(targets, tab, dr).toarray()
    d = cdist(targets, pts)
    assert ((got != 0) == (d <= radius)).all()  # cos(r) > 0 here: a stored entry is a pair within the radius
    assert np.abs(got - np.where(d <= radius, np.cos(d), 0.0)).max() < 1e-7


def test_sums_and_gradients_match_the_brute_force_pair_sums(cloud):
    pts, targets = cloud
    radius = 0.25
    tab, dtab, dr = _table(radius)
    w = np.random.default_rng(5).normal(size=len(pts))
    out, grad = np.full(len(targets), 2.0), np.zeros((len(targets), 3))
    CellList(pts, radius).add_sum(targets, w, tab, dtab, dr, out, grad)
    d = cdist(targets, pts)
    near = d <= radius
    want = 2.0 + (np.where(near, np.cos(d), 0.0) * w).sum(axis=1)
    coef = np.where(near & (d > 0), -np.sin(d) / np.where(d > 0, d, 1.0), 0.0) * w
    want_grad = np.einsum("ij,ijk->ik", coef, targets[:, None, :] - pts[None, :, :])
    assert np.abs(out - want).max() < 1e-6
    assert np.abs(grad - want_grad).max() < 1e-5
    only = np.full(len(targets), 2.0)
    CellList(pts, radius).add_sum(targets, w, tab, dtab, dr, only)  # values alone: the same values
    assert np.array_equal(only, out)


def test_self_sum_matches_the_brute_force_sum(cloud):
    """The near sum at the points themselves (the products' near field summed on the fly), in the
    points' order, against every pair within the radius, duplicated points and the self pair included."""
    pts = np.vstack([cloud[0], cloud[0][:20]])  # 20 points twice: pairs at distance 0
    radius = 0.3
    tab, _, dr = _table(radius)
    w = np.random.default_rng(6).normal(size=len(pts))
    d = cdist(pts, pts)
    want = (np.where(d <= radius, np.cos(d), 0.0) * w).sum(axis=1)
    got = CellList(pts, radius).self_sum(w, tab, dr)
    assert np.abs(got - want).max() < 1e-6 * np.abs(w).sum()


def test_spatial_order_keeps_neighbours_close_in_memory():
    """A permutation, deterministic, and near points get near indices: the index gap between each point and
    its 16 nearest is a small fraction of N (in the torus sample's own order it is about N / 3)."""
    from scipy.spatial import cKDTree

    from o3drbf.solvers.fast.neighbours import spatial_order
    from o3drbf.synthetic.shapes import Torus

    p, _ = Torus().sample(20_000, seed=3)
    order = spatial_order(p)
    assert np.array_equal(np.sort(order), np.arange(len(p))) and np.array_equal(order, spatial_order(p))
    near = cKDTree(p).query(p, k=17)[1][:, 1:]

    def gap(points_order):
        place = np.empty(len(p), np.int64)
        place[points_order] = np.arange(len(p))
        return float(np.median(np.abs(place[near] - place[:, None])))

    assert gap(np.arange(len(p))) > len(p) / 5
    assert gap(order) < len(p) / 200
    with pytest.raises(ValueError, match="bits"):
        spatial_order(p, bits=0)
    assert spatial_order(np.zeros((0, 3))).size == 0 and spatial_order(np.zeros((3, 3))).tolist() == [0, 1, 2]


def counting_tree_class():
    """A cKDTree subclass counting the queries of all its trees (``calls``)."""
    from scipy.spatial import cKDTree

    class Counting(cKDTree):
        calls = 0

        def query(self, *args, **kwargs):
            Counting.calls += 1
            return super().query(*args, **kwargs)

    return Counting


def test_neighbour_radius_is_the_sampled_median_and_is_found_once_per_centres_and_k():
    from o3drbf.solvers.fast.neighbours import RADIUS_SAMPLE, neighbour_radius, radius_sample

    pts = np.random.default_rng(7).uniform(-1, 1, (3000, 3))
    Counting = counting_tree_class()
    tree = Counting(pts)
    pick = radius_sample(pts)
    assert len(pick) == RADIUS_SAMPLE == len(np.unique(pick))
    d = np.sort(np.linalg.norm(pts[pick][:, None, :] - pts[None, :, :], axis=2), axis=1)  # brute force
    for k in (20, 50):
        assert neighbour_radius(pts, tree, k) == pytest.approx(np.median(d[:, k - 1]), rel=1e-12)
    assert Counting.calls == 2
    assert neighbour_radius(pts, tree, 20) == pytest.approx(np.median(d[:, 19]), rel=1e-12) and Counting.calls == 2
    # The same centres in another order: the same sample, so the same radius, found without a query.
    perm = np.random.default_rng(3).permutation(len(pts))
    assert np.array_equal(np.sort(perm[radius_sample(pts[perm])]), np.sort(pick))
    assert neighbour_radius(pts[perm], Counting(pts[perm]), 20) == neighbour_radius(pts, tree, 20) and Counting.calls == 2
    few = pts[:500]  # fewer than the sample: every centre, in any order (found once)
    calls = Counting.calls
    assert neighbour_radius(few[::-1], Counting(few[::-1]), 20) == neighbour_radius(few, Counting(few), 20)
    assert Counting.calls == calls + 1
    calls = Counting.calls
    moved = pts + 1e-3
    neighbour_radius(moved, Counting(moved), 20)
    assert Counting.calls == calls + 1  # other centres: found afresh
    swapped = pts.copy()
    swapped[0], swapped[1] = pts[1] + 1e-3, pts[0]  # one point moved (the sum of hashes changes)
    neighbour_radius(swapped, Counting(swapped), 20)
    assert Counting.calls == calls + 2


def test_nearest_distance_is_the_brute_force_one_and_is_found_once_per_centres_in_their_order():
    from o3drbf.solvers.fast.neighbours import nearest_distance

    pts = np.random.default_rng(8).uniform(-1, 1, (2500, 3))
    Counting = counting_tree_class()
    d = cdist(pts, pts)
    np.fill_diagonal(d, np.inf)
    tree = Counting(pts)
    got = nearest_distance(pts, tree)
    np.testing.assert_allclose(got, d.min(axis=1), rtol=1e-12)
    assert Counting.calls == 1
    assert nearest_distance(pts.copy(), tree) is got and Counting.calls == 1  # the same centres: kept
    perm = np.random.default_rng(9).permutation(len(pts))
    np.testing.assert_allclose(nearest_distance(pts[perm], Counting(pts[perm])), got[perm], rtol=1e-12)  # another order: its own
    assert Counting.calls == 2
    moved = pts.copy()
    moved[0, 0] += 1e-9
    nearest_distance(moved, Counting(moved))
    assert Counting.calls == 3  # any change to the centres: found again
    with pytest.raises(ValueError):
        got[0] = 0.0  # the kept answer is read-only
