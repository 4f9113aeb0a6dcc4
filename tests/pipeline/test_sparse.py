"""Sparse clouds (30-100 points) of closed shapes: one closed piece of the right genus, near the shape; dense inputs unchanged."""

import numpy as np
import pytest

import o3drbf
from o3drbf.constraints.parameters import DELTA_RANGE, DELTA_SPACING, LAMBDA_BASE, LAMBDA_NOISE, SPARSE_SPACING, parameters_from
from o3drbf.synthetic.shapes import Cube, Sphere, Torus

# (shape, points, Euler characteristic, bound on the mean distance of the mesh's vertices to the shape)
CASES = [
    (Sphere(1.0), 30, 2, 0.04),
    (Sphere(1.0), 50, 2, 0.03),
    (Sphere(1.0), 100, 2, 0.02),
    (Torus(0.6, 0.25), 50, 0, 0.08),
    (Torus(0.6, 0.25), 100, 0, 0.04),
    (Cube(), 50, 2, 0.05),
    (Cube(), 100, 2, 0.03),
]


@pytest.mark.parametrize("estimated", [False, True], ids=["exact normals", "estimated normals"])
@pytest.mark.parametrize("shape, n, euler, bound", CASES, ids=[f"{type(c[0]).__name__}-{c[1]}" for c in CASES])
def test_sparse_cloud_gives_one_closed_piece(shape, n, euler, bound, estimated):
    p, normals = shape.sample(n, seed=1)
    r = o3drbf.reconstruct(p, None if estimated else normals, resolution=48)
    m = r.mesh
    assert m.is_watertight() and len(m.cluster_connected_triangles()[1]) == 1
    assert m.euler_poincare_characteristic() == euler
    error = np.abs(shape.signed_distance(np.asarray(m.vertices))).mean()
    assert error < bound, error
    assert "sparse" in r.report.auto["reason"]


def _old_rule(h, sigma):
    """The rule before sparse clouds were treated apart (floor 8, full noise term)."""
    return float(np.clip(DELTA_SPACING / h, *DELTA_RANGE)), LAMBDA_BASE + LAMBDA_NOISE * (sigma / h) ** 2


@pytest.mark.parametrize("h", [0.01, 0.02, 0.035, 0.05, SPARSE_SPACING[0]])
@pytest.mark.parametrize("sigma_h", [0.0, 0.3, 1.0])
def test_dense_spacings_keep_the_rule(h, sigma_h):
    a = parameters_from(h, sigma_h * h)
    delta, lam_rel = _old_rule(h, sigma_h * h)
    assert a.delta == delta and a.lambda_relative == pytest.approx(lam_rel, rel=1e-12)
    assert "sparse" not in a.reason


@pytest.mark.parametrize("shape, n", [(Torus(0.6, 0.25), 3000), (Sphere(1.0), 2000), (Cube(), 3000), (Torus(0.7, 0.25), 15000)])
def test_the_test_suites_dense_inputs_are_not_sparse(shape, n):
    from o3drbf.constraints.parameters import choose_parameters

    p, _ = shape.sample(n, seed=5)
    a = choose_parameters(p)
    assert a.spacing <= SPARSE_SPACING[0] and a.delta == _old_rule(a.spacing, a.noise)[0] == DELTA_RANGE[0]


def test_sparse_rule_falls_continuously():
    lo, hi = SPARSE_SPACING
    hs = np.linspace(lo, 2 * hi, 200)
    d = np.array([parameters_from(h, 0.0).delta for h in hs])
    assert d[0] == DELTA_RANGE[0] and np.all(np.diff(d) < 0) and d[-1] < 1.5
    assert np.abs(np.diff(d)).max() < 0.2
