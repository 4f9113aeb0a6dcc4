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
