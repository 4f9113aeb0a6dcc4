"""Iteratively reweighted robust fit (o3drbf.constraints.robust) against a known sphere."""

import numpy as np
import pytest

from o3drbf.constraints.core import EXTERIOR, SPHERE, SURFACE, Constraints, bounding_sphere
from o3drbf.pipeline import fit
from o3drbf.prep.normalize import Normalization
from o3drbf.constraints.robust import geometric_residuals, huber_weights, robust_reweight, tukey_weights
from o3drbf.synthetic.shapes import Sphere

from conftest import ROBUST_KERNEL as KERNEL, ROBUST_N as N, ROBUST_R as R, radial_error, sphere_constraints  # noqa: E402


def fitter(c):
    return fit(c, KERNEL, Normalization.identity(), solver="dense")


@pytest.fixture(scope="module")
def fits():
    dirty, pts, k = sphere_constraints(0.03)
    clean, _, _ = sphere_constraints(0.0)
    return dirty, clean, pts, k, fitter(dirty), fitter(clean)


def test_robust_fit_recovers_the_clean_fit(fits):
    dirty, clean, pts, k, (plain, _), (clean_fit, _) = fits
    surface, solution, report = robust_reweight(fitter, dirty, noise_scale=0.002, first=(plain, None))
    e_clean, e_plain, e_robust = (radial_error(s, pts) for s in (clean_fit, plain, surface))
    out_dirs = dirty.points[N : N + k]
    o_clean, o_plain, o_robust = (radial_error(s, out_dirs) for s in (clean_fit, plain, surface))
    print(f"mean |r - R| at the samples: clean {e_clean:.5f} plain {e_plain:.5f} robust {e_robust:.5f}; "
          f"toward the outliers: clean {o_clean:.5f} plain {o_plain:.5f} robust {o_robust:.5f}")
    # On this kernel and lambda scattered outliers do measurable but modest harm (about 8%).
    assert e_plain > 1.05 * e_clean and o_plain > o_clean
    # Robust: the clean fit itself (the outliers dropped, every other lambda back to lambda_0).
    assert e_robust == pytest.approx(e_clean, rel=1e-6) and o_robust == pytest.approx(o_clean, rel=1e-6)
    # Exactly the outliers were dropped (truth: they are the last k surface rows).
    dropped = np.flatnonzero(report.weights == 0)
    assert dropped.tolist() == list(range(N, N + k))
    assert report.dropped == k and report.converged and 1 <= report.rounds <= 4
    assert len(report.constraints) == len(dirty) - k
    assert solution.method == "dense"
    assert "dropped" in str(report)


def test_clean_data_costs_nothing(fits):
    _, clean, pts, _, _, (clean_fit, clean_sol) = fits
    calls = []

    def counting(c):
        calls.append(len(c))
        return fitter(c)

    surface, _, report = robust_reweight(counting, clean, noise_scale=0.002, first=(clean_fit, clean_sol))
    assert calls == [] and report.rounds == 0 and report.downweighted == 0 and report.dropped == 0
    g = np.random.default_rng(3).uniform(-1, 1, (500, 3))
    assert np.abs(surface.evaluate_box(g) - clean_fit.evaluate_box(g)).max() == 0.0


def test_noisy_sphere_with_outliers():
    sigma = 0.005
    dirty, pts, k = sphere_constraints(0.03, noise=sigma, seed=4)
    clean, _, _ = sphere_constraints(0.0, noise=sigma, seed=4)
    surface, _, report = robust_reweight(fitter, dirty, noise_scale=sigma)
    plain = fitter(dirty)[0]
    e_clean, e_plain, e_robust = radial_error(fitter(clean)[0], pts), radial_error(plain, pts), radial_error(surface, pts)
    print(f"noisy: clean {e_clean:.5f} plain {e_plain:.5f} robust {e_robust:.5f}; outliers dropped "
          f"{(report.weights[N:N + k] == 0).mean():.3f}, genuine dropped {(report.weights[:N] == 0).mean():.4f}; {report}")
    assert e_robust < 1.5 * e_clean
    assert (report.weights[N : N + k] == 0).mean() >= 0.9
    assert (report.weights[:N] == 0).mean() < 0.01


def test_weights_and_residuals():
    d = np.array([0.0, 1.0, 2.0, 4.0])
    np.testing.assert_allclose(huber_weights(d, 2.0), [1, 1, 1, 0.5])
    np.testing.assert_allclose(tukey_weights(d, 4.0), [1, (1 - 1 / 16) ** 2, (1 - 1 / 4) ** 2, 0])
    np.testing.assert_allclose(tukey_weights(d, 4.0, core=2.0), [1, 1, 1, 0])
    # |f| / |grad f| of a plane-like field is the distance: f = 1 - x (no RBF part, poly [1, -1, 0, 0]).
    from o3drbf.surface import ImplicitSurface

    plane = ImplicitSurface(KERNEL, np.zeros((1, 3)), np.zeros(1), np.array([1.0, -1.0, 0.0, 0.0]))
    if KERNEL.polynomial_degree >= 1:
        np.testing.assert_allclose(geometric_residuals(plane, [[0.25, 0, 0], [1.5, 2, 0]]), [0.75, 0.5])


def test_bad_input(fits):
    dirty = fits[0]
    with pytest.raises(ValueError, match="Constraints"):
        robust_reweight(fitter, np.zeros((3, 3)), 0.01)
    with pytest.raises(ValueError, match="tukey_c"):
        robust_reweight(fitter, dirty, 0.01, huber_k=5.0, tukey_c=4.0)
    no_surface = Constraints.of_kind(np.eye(3), EXTERIOR, 1.0)
    with pytest.raises(ValueError, match="no SURFACE"):
        robust_reweight(fitter, no_surface, 0.01)


def dense_sphere(n, n_out, seed=0):
    """n samples of the sphere and n_out gross outliers 20 % of R outside it (last surface rows), lambda 0.014 phi(0)."""
    pts, _ = Sphere(R).sample(n, noise=0.002, seed=seed)
    rng = np.random.default_rng(seed + 1)
    d = rng.normal(size=(n_out, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return Constraints.concat(
        Constraints.of_kind(np.vstack([pts, 1.2 * R * d]), SURFACE, 1e-4),
        Constraints.of_kind(pts[::10] * (1 + 0.05 / R), EXTERIOR, 2.0),
        Constraints.of_kind(bounding_sphere(pts, 64), SPHERE, 2.0),
    )


def test_residuals_measured_again_only_near_the_changes():
    """The local re-measurement gives the weights and surface of measuring every residual each round."""
    dirty = dense_sphere(3000, 2)
    first = fitter(dirty)
    full = robust_reweight(fitter, dirty, noise_scale=0.002, first=first, local_radius=None)
    local = robust_reweight(fitter, dirty, noise_scale=0.002, first=first)
    n = int((dirty.kind == SURFACE).sum())
    assert full[2].rounds >= 2 and (full[2].weights[n - 2 : n] == 0).all() and full[2].dropped == 2
    np.testing.assert_array_equal(local[2].weights, full[2].weights)
    g = np.random.default_rng(5).uniform(-1, 1, (300, 3))
    np.testing.assert_allclose(local[0].evaluate_box(g), full[0].evaluate_box(g), rtol=0, atol=1e-12)
    measured = [h["measured"] for h in local[2].history]
    # the residuals of the final fit, as measuring all of them gives (within the check's tolerance)
    assert np.abs(local[2].residuals - full[2].residuals).max() <= 0.01 * 3.0 * full[2].scale
    # the first fit measures all; at least one refit only the neighbourhood and the check sample
    assert measured[0] == n and min(measured[1:]) < n // 4, measured
    assert all(h["measured"] == n for h in full[2].history)


def test_local_residuals_fall_back_when_the_check_sees_a_move():
    """Radius 0 re-measures only the changed constraints; their neighbours moved, the sample check sees it."""
    dirty = dense_sphere(3000, 2)
    first = fitter(dirty)
    full = robust_reweight(fitter, dirty, noise_scale=0.002, first=first, local_radius=None)
    tight = robust_reweight(fitter, dirty, noise_scale=0.002, first=first, local_radius=0.0)
    n = int((dirty.kind == SURFACE).sum())
    np.testing.assert_array_equal(tight[2].weights, full[2].weights)
    assert any(h["measured"] > n for h in tight[2].history[1:]), [h["measured"] for h in tight[2].history]


def test_residuals_at_the_constraints_are_evaluate_boxs_to_rounding(fits):
    from o3drbf.constraints.robust import constraint_residuals

    dirty, _, _, _, (plain, _), _ = fits
    surf = np.flatnonzero(dirty.kind == SURFACE)
    assert np.array_equal(plain.centres, dirty.points)  # the pair-once path is taken
    got = constraint_residuals(plain, dirty, surf)
    reference = geometric_residuals(plain, dirty.points[surf])
    np.testing.assert_allclose(got, reference, rtol=1e-9, atol=1e-13)
    # a surface whose centres are not the constraints (one left out): evaluate_box itself
    fewer = fitter(Constraints(dirty.points[1:], dirty.values[1:], dirty.smoothing[1:], dirty.kind[1:]))[0]
    np.testing.assert_array_equal(constraint_residuals(fewer, dirty, surf), geometric_residuals(fewer, dirty.points[surf]))


def test_residuals_from_the_meshing_grid_when_the_surface_has_one(fits):
    """A surface carrying its meshing grid sum (extract.mesh_evaluator) gives the first residuals from it, once,
    within a small fraction of the residual scale of the direct sums."""
    from o3drbf.constraints.robust import constraint_residuals
    from o3drbf.extract import mesh_evaluator

    dirty, _, _, _, (plain, _), _ = fits
    surf = np.flatnonzero(dirty.kind == SURFACE)
    reference = constraint_residuals(plain, dirty, surf)  # no grid yet: the direct pair-once sums
    grid = mesh_evaluator(plain, min_centres=1)
    assert grid.kind == "grid" and plain.meshing is grid and mesh_evaluator(plain, min_centres=1) is grid
    calls = []

    def counting(points, gradient=False):
        calls.append((len(points), gradient))
        return grid(points, gradient)

    counting.kind = "grid"
    plain.meshing = counting
    try:
        got = constraint_residuals(plain, dirty, surf)
    finally:
        plain.meshing = None
    assert calls == [(len(surf), True)]
    # Within 1 % of the Huber threshold (3 s, s = 0.002 here) plus 0.5 % of the residual (the grid's
    # gradients are ~1e-3 relative): no weight decision moves.
    assert (np.abs(got - reference) <= 0.01 * 3 * 0.002 + 0.005 * reference).all()
