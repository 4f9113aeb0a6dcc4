"""Fewer surface constraints where the surface is flat (``surface_adaptive``), checked against geometry known exactly."""

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from o3drbf import PointSet, build_constraints
from o3drbf.constraints.adaptive import adaptive_subset, plane_deviation, spacing_factors, thin_by_factor
from o3drbf.constraints.core import surface_constraints
from o3drbf.options import ConstraintOptions


def grid(n=60, size=1.0):
    u = np.linspace(-size, size, n)
    x, y = np.meshgrid(u, u)
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def test_plane_deviation_of_a_sphere_matches_the_paraboloid_formula():
    # a dense cap of a sphere of radius R: the k nearest points of the pole fill a disc of radius r,
    # whose RMS distance to their best plane is kappa r^2 / (4 sqrt 3) to leading order (kappa = 1 / R)
    rng = np.random.default_rng(0)
    radius = 5.0
    uv = rng.uniform(-1, 1, (200_000, 2))
    uv = uv[np.hypot(uv[:, 0], uv[:, 1]) < 1]
    z = radius - np.sqrt(radius**2 - (uv**2).sum(axis=1))
    pts = np.column_stack([uv, z])
    dev, rad = plane_deviation(pts, np.zeros((1, 3)), k=500)
    r = rad[0]  # the disc's radius, to within the sag
    assert dev[0] == pytest.approx(r * r / (radius * 4 * np.sqrt(3)), rel=0.03)


def test_plane_deviation_takes_the_noise_off():
    rng = np.random.default_rng(1)
    pts = grid(120)
    noisy = pts + np.column_stack([np.zeros((len(pts), 2)), rng.normal(0, 0.01, len(pts))])
    raw, _ = plane_deviation(noisy, pts[::97], k=64)
    clean, _ = plane_deviation(noisy, pts[::97], k=64, noise=0.01)
    assert np.median(raw) == pytest.approx(0.01, rel=0.1)  # the noise itself, as a plane fit sees it
    assert np.median(clean) < 0.3 * np.median(raw)


def test_spacing_factors_give_the_sag_asked_for():
    # a paraboloid of curvature kappa over a disc of radius R: deviation kappa R^2 / (4 sqrt 3); the spacing s
    # returned must sag kappa s^2 / 8 = tolerance * spacing
    kappa, big_r, spacing, tol = 2.0, 0.1, 0.02, 0.05
    dev = kappa * big_r**2 / (4 * np.sqrt(3))
    m = spacing_factors([dev], [big_r], spacing, tol, max_factor=100.0)[0]
    s = m * spacing
    assert kappa * s * s / 8 == pytest.approx(tol * spacing, rel=1e-9)
    assert spacing_factors([0.0, 1e9], [big_r, big_r], spacing, tol, 1.6).tolist() == [1.6, 1.0]


def test_thin_by_factor_keeps_factor_one_and_spreads_the_rest():
    pts = grid(40)
    fac = np.where(pts[:, 0] < 0, 1.0, 2.0)
    kept = thin_by_factor(pts, fac, seed=3)
    r = 2.0 / 39
    left = pts[:, 0] < 0
    assert np.all(np.isin(np.flatnonzero(left), kept))  # every factor-1 point kept
    right = kept[~left[kept]]
    assert len(right) < 0.4 * (~left).sum()
    # brute force: no two kept points of the thinned side closer than 2 r
    assert pdist(pts[right]).min() >= 2 * r * (1 - 1e-9)
    assert np.array_equal(kept, thin_by_factor(pts, fac, seed=3))


def test_adaptive_subset_thins_the_flat_part_only():
    # a flat square beside a half-cylinder of radius 0.05 (curvature 20): only the flat part is thinned
    rng = np.random.default_rng(2)
    flat = np.column_stack([rng.uniform(-1, 0, 40_000), rng.uniform(-0.5, 0.5, 40_000), np.zeros(40_000)])
    t = rng.uniform(0, np.pi, 40_000)
    tube = np.column_stack([0.5 + 0.05 * np.cos(t), rng.uniform(-0.5, 0.5, 40_000), 0.05 * np.sin(t)])
    pts = np.concatenate([flat, tube])
    idx = surface_constraints(pts, count=8000, seed=0)
    kept = adaptive_subset(pts, idx, tolerance=0.01, max_factor=1.6, seed=0)
    assert set(kept) <= set(idx)
    on_tube = pts[:, 0] > 0.4
    top = on_tube & (pts[:, 2] > 0.01) & (np.abs(pts[:, 1]) < 0.45)  # away from the tube's open ends
    assert np.isin(idx[top[idx]], kept).all()
    flat_ratio = (~on_tube[kept]).sum() / (~on_tube[idx]).sum()
    assert 0.3 < flat_ratio < 0.6


def test_build_constraints_option_off_is_the_uniform_rule_and_on_is_a_subset():
    from o3drbf.synthetic.shapes import Sphere

    points, normals = Sphere(1.0).sample(12_000, seed=0)
    data = PointSet.create(points, normals)
    uniform = build_constraints(data)
    thinned = build_constraints(data, ConstraintOptions(surface_adaptive=0.01))
    assert abs(uniform.constraints.counts()["surface"] - 4000) <= 80  # points / 3, the uniform rule
    assert set(thinned.surface_index) < set(uniform.surface_index)
    assert thinned.spacing == uniform.spacing  # the parameters follow the uniform subset's spacing
    plain = build_constraints(data, ConstraintOptions(surface_adaptive=0.01, denoise=False))
    assert np.array_equal(plain.surface_index, thinned.surface_index)  # without the noise step too


def test_bad_tolerance_is_one_line():
    with pytest.raises(ValueError, match="surface_adaptive"):
        ConstraintOptions(surface_adaptive=-1.0).validate()
