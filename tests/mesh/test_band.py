"""The narrow band's compiled cell tests against the same tests written with whole-grid NumPy operations."""

import numpy as np
import pytest

from o3drbf.mesh.band import candidate_cells, corners_to_evaluate

OFFSETS = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]


def numpy_candidates(vals, level, margin):
    d = vals - level
    n = [s - 1 for s in d.shape]
    corners = np.stack([d[a:a + n[0], b:b + n[1], c:c + n[2]] for a, b, c in OFFSETS])
    mn, mx, am = corners.min(axis=0), corners.max(axis=0), np.abs(corners).min(axis=0)
    return ((mn <= 0) & (mx >= 0)) | (am <= margin * (mx - mn))


def numpy_corners(vals, exact, changed, level, margin):
    cand = numpy_candidates(vals, level, margin)
    touched = np.zeros(cand.shape, dtype=bool)
    p = np.stack(changed, axis=1)
    for o in OFFSETS:
        c = p - o
        c = c[((c >= 0) & (c < cand.shape)).all(axis=1)]
        touched[tuple(c.T)] = True
    need = np.zeros(vals.shape, dtype=bool)
    for a, b, c in OFFSETS:
        need[a:a + cand.shape[0], b:b + cand.shape[1], c:c + cand.shape[2]] |= touched & cand
    return np.nonzero(need & ~exact)


def field(shape, seed):
    """Waves crossing zero everywhere, the grid's faces included, plus a little noise; rounded to 1/64 so
    that many values are exactly 0 or exactly the level (the tests' ``<=`` matter there)."""
    rng = np.random.default_rng(seed)
    x, y, z = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape], indexing="ij")
    f = 0.3 * np.sin(6 * x) + 0.25 * np.cos(7 * y) + 0.2 * np.sin(5 * z + 1) + 0.01 * rng.standard_normal(shape)
    return np.round(f * 64) / 64


@pytest.mark.parametrize("level, margin", [(0.0, 0.0), (0.0, 0.5), (4 / 64, 0.5), (-6 / 64, 0.2)])
def test_candidate_cells_are_numpys(level, margin):
    vals = field((33, 25, 41), 1)
    got = candidate_cells(vals, level, margin)
    want = numpy_candidates(vals, level, margin)
    assert got.shape == want.shape and got.dtype == bool
    assert 0 < want.sum() < want.size and np.array_equal(got, want)
    assert (vals == level).sum() > 50 and want[-1].any() and want[:, :, -1].any()


@pytest.mark.parametrize("level, margin", [(0.0, 0.0), (0.0, 0.5), (3 / 64, 0.5)])
def test_corners_to_evaluate_are_numpys_in_c_order(level, margin):
    vals = field((30, 34, 27), 2)
    rng = np.random.default_rng(3)
    exact = rng.random(vals.shape) < 0.4
    exact[0] = True  # a whole face exact: those corners are never asked for
    changed = np.nonzero(rng.random(vals.shape) < 0.05)  # points on the faces and edges of the grid among them
    got = corners_to_evaluate(vals, exact, changed, level, margin)
    want = numpy_corners(vals, exact, changed, level, margin)
    assert len(want[0]) > 100 and (vals == level).sum() > 50 and (want[2] == vals.shape[2] - 1).any()
    for g, w in zip(got, want):
        assert np.array_equal(g, w)
    none = corners_to_evaluate(vals, exact, tuple(np.zeros(0, np.int64) for _ in range(3)), level, margin)
    assert all(len(c) == 0 for c in none)


def test_values_kept_off_zero_as_the_whole_grid_numpy_form_does():
    """The compiled crossing steps and nudge give, bit for bit, the NumPy form they replaced: the median
    step of the sign-changing edges along all three axes, and every |d| below a hundredth of it set to
    +-that, 0 to the negative side."""
    from o3drbf.extract import CORNER_GAP, _keep_off_corners

    def numpy_form(d):
        steps = []
        for axis in range(3):
            a = np.moveaxis(d, axis, 0)
            cross = (a[:-1] < 0) != (a[1:] < 0)
            steps.append(np.abs(a[1:] - a[:-1])[cross])
        eps = CORNER_GAP * float(np.median(np.concatenate(steps)))
        out = d.copy()
        small = np.abs(out) < eps
        out[small] = np.where(out[small] > 0, eps, -eps)
        return out

    rng = np.random.default_rng(3)
    x = np.linspace(-1, 1, 41)
    d = np.sqrt(x[:, None, None] ** 2 + 0.5 * x[None, :33, None] ** 2 + x[None, None, :29] ** 2) - 0.6
    d += rng.normal(scale=1e-3, size=d.shape)
    d[rng.random(d.shape) < 0.01] = 0.0
    d[rng.random(d.shape) < 0.01] *= 1e-6
    want = numpy_form(d)
    assert (want != d).sum() > 100  # values were moved
    assert np.array_equal(_keep_off_corners(d), want)
