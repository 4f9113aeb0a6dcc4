"""Poisson-disc subsampling and spacing against analytic answers."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from o3drbf.prep.sampling import fibonacci_sphere, mean_spacing, poisson_disc
from o3drbf.synthetic.shapes import Cube, Sphere, Torus, TorusStack, cube_corner


def test_mean_spacing_of_a_grid_is_its_step():
    g = np.stack(np.meshgrid(*[np.arange(5) * 0.3] * 3, indexing="ij"), -1).reshape(-1, 3)
    assert mean_spacing(g) == pytest.approx(0.3)


@pytest.mark.parametrize("count", [300, 3000])
def test_poisson_disc_count_separation_coverage_determinism(count):
    p, _ = Torus().sample(50_000, seed=3)
    idx = poisson_disc(p, count=count, seed=7)
    assert abs(len(idx) - count) <= 0.02 * count + 1
    assert np.all(np.diff(idx) > 0)
    sub = p[idx]
    d, _ = cKDTree(sub).query(sub, k=2)
    r = d[:, 1].min()
    # maximal: every input point is within ~2 r of a kept one
    cover, _ = cKDTree(sub).query(p)
    assert cover.max() < 2.0 * r
    assert np.array_equal(idx, poisson_disc(p, count=count, seed=7))
    assert not np.array_equal(idx, poisson_disc(p, count=count, seed=8))


def test_poisson_disc_by_radius():
    p, _ = Sphere(1.0).sample(20_000, seed=1)
    idx = poisson_disc(p, radius=0.1)
    d, _ = cKDTree(p[idx]).query(p[idx], k=2)
    assert d[:, 1].min() >= 0.1
    # area 4 pi, each disc of radius r/2 is disjoint: count <= 4 pi / (pi (r/2)^2) = 1600
    assert 400 < len(idx) < 1600


def test_poisson_disc_errors_and_edge_cases():
    p = np.random.default_rng(0).random((100, 3))
    assert len(poisson_disc(p, count=1000)) == 100
    with pytest.raises(ValueError, match="exactly one of count or radius"):
        poisson_disc(p)
    with pytest.raises(ValueError, match="radius must be in"):
        poisson_disc(p, radius=-1)
    with pytest.raises(ValueError, match="points is empty"):
        poisson_disc(np.zeros((0, 3)), count=3)


def test_fibonacci_sphere_is_on_the_sphere():
    s = fibonacci_sphere(500, radius=2.0, center=(1, 2, 3))
    assert np.allclose(np.linalg.norm(s - [1, 2, 3], axis=1), 2.0)
    assert abs(s.mean(axis=0) - [1, 2, 3]).max() < 0.01


@pytest.mark.parametrize("shape", [Sphere(0.8), Torus(0.6, 0.2), TorusStack(3), Cube(0.5)], ids=lambda s: type(s).__name__)
def test_shape_samples_lie_on_the_surface_with_outward_normals(shape):
    p, n = shape.sample(2000, seed=2)
    assert np.abs(shape.signed_distance(p)).max() < 1e-9
    h = 1e-4
    q = p + h * n
    assert (shape.signed_distance(q) > 0).all()
    noisy, _ = shape.sample(5000, noise=0.01, seed=2)
    assert np.std(shape.signed_distance(noisy)) == pytest.approx(0.01, rel=0.1)


def test_cube_corner_sees_three_faces():
    p, n = cube_corner(900)
    assert set(map(tuple, n.astype(int))) == {(1, 0, 0), (0, 1, 0), (0, 0, 1)}


def _kd_tree_darts(points, order, radius):
    """The reference: the KD-tree loop the compiled dart throwing replaced."""
    from scipy.spatial import cKDTree

    tree = cKDTree(points)
    taken = np.zeros(len(points), dtype=bool)
    accepted = []
    for idx in order.tolist():
        if not taken[idx]:
            accepted.append(idx)
            taken[tree.query_ball_point(points[idx], radius)] = True
    return np.asarray(accepted, dtype=np.int64)


@pytest.mark.parametrize("case", ["random", "lattice ties", "torus"])
def test_compiled_darts_accept_what_the_kd_tree_loop_accepts(case):
    from o3drbf.prep.darts import greedy_darts

    rng = np.random.default_rng(7)
    if case == "random":
        pts, radius = rng.uniform(-1, 1, (4000, 3)), 0.11
    elif case == "lattice ties":  # neighbours exactly at the radius: kept out by both (|p - q| <= r is taken)
        g = np.arange(12, dtype=float)
        pts, radius = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) * 0.25 - 1.0, 0.5
    else:
        from o3drbf.synthetic.shapes import Torus

        pts, radius = Torus().sample(6000, seed=2)[0], 0.03
    order = rng.permutation(len(pts))
    got = greedy_darts(pts, order, radius)
    np.testing.assert_array_equal(got, _kd_tree_darts(pts, order, radius))
    assert 10 < len(got) < len(pts)


def test_poisson_disc_is_the_kd_tree_loops_subset():
    from o3drbf.prep import sampling
    from o3drbf.synthetic.shapes import Torus

    pts = Torus().sample(20000, seed=3)[0]
    kept = poisson_disc(pts, count=3000, seed=4)
    original = sampling._greedy
    try:
        sampling._greedy = lambda points, order, radius, tree=None: _kd_tree_darts(points, order, radius)
        reference = poisson_disc(pts, count=3000, seed=4)
    finally:
        sampling._greedy = original
    np.testing.assert_array_equal(kept, reference)


def test_a_grid_too_fine_to_index_falls_back_to_the_kd_tree_loop():
    from o3drbf.prep import sampling
    from o3drbf.prep.darts import greedy_darts

    rng = np.random.default_rng(3)
    pts = np.vstack([rng.uniform(0, 1e-3, (300, 3)), [[1e4, 1e4, 0.0]]])  # a far point: 1e14 rows of cells
    order = rng.permutation(len(pts))
    assert greedy_darts(pts, order, 1e-4) is None
    np.testing.assert_array_equal(sampling._greedy(pts, order, 1e-4), _kd_tree_darts(pts, order, 1e-4))


@pytest.mark.parametrize("fallback", [False, True])
def test_poisson_disc_builds_the_candidates_kd_tree_only_for_the_fallback_and_once(monkeypatch, fallback):
    """The compiled darts need no KD-tree of the candidates; the KD-tree loop (a grid too fine to index)
    builds one for the whole radius search, not one a radius."""
    from o3drbf.prep import sampling

    built = []

    class Counting(sampling.cKDTree):
        def __init__(self, data, *args, **kwargs):
            built.append(len(data))
            super().__init__(data, *args, **kwargs)

    monkeypatch.setattr(sampling, "cKDTree", Counting)
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 1e-3, (2000, 3))
    if fallback:
        pts = np.vstack([pts, [[1e4, 1e4, 0.0]]])  # a far point: 1e14 rows of cells
    kept = sampling.poisson_disc(pts, count=200, seed=4)
    assert abs(len(kept) - 200) <= 10 + fallback
    assert len(built) == 1 + fallback  # the spacing of a random subset's, and the candidates' for the fallback
