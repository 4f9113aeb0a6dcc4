"""The implicit surface object: gradients, chunking, persistence."""

import numpy as np
import pytest

from o3drbf.rbf.kernels import Gaussian, MultiOrder, ThinPlate
from o3drbf.prep.normalize import Normalization
from o3drbf.solvers import solve
from o3drbf.surface import ImplicitSurface


def fitted(kernel, rng):
    d = rng.standard_normal((300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = np.vstack([0.6 * d[:270], 0.7 * d[270:]])
    y = np.r_[np.zeros(270), -np.ones(30)]
    sol = solve(kernel, x, y, np.where(y == 0, 1e-3, 2.0))
    norm = Normalization(center=np.array([10.0, -5.0, 2.0]), scale=0.25)  # data = box / 0.25 + centre
    return ImplicitSurface(kernel, x, sol.weights, sol.poly, norm, {"note": "test", "lambda": 1e-3})


@pytest.mark.parametrize("kernel", [MultiOrder(10, 0.01), MultiOrder(40, 0.025), Gaussian(0.3), ThinPlate()], ids=repr)
def test_gradient_matches_finite_differences(kernel, rng):
    s = fitted(kernel, rng)
    p = s.normalization.inverse(rng.uniform(-0.9, 0.9, (40, 3)))
    g = s.gradient(p)
    h = 1e-5
    fd = np.column_stack([(s(p + h * e) - s(p - h * e)) / (2 * h) for e in np.eye(3)])
    assert np.allclose(g, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_normals_point_outward_and_are_unit(rng):
    s = fitted(MultiOrder(), rng)
    d = rng.standard_normal((50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p = s.normalization.inverse(0.6 * d)
    n = s.normals(p)
    assert np.allclose(np.linalg.norm(n, axis=1), 1)
    dots = np.einsum("ij,ij->i", n, d)
    assert (dots > 0.5).all() and dots.mean() > 0.95
    # inside positive, outside negative
    assert s(s.normalization.inverse(np.zeros(3)))[0] > 0
    assert s(s.normalization.inverse(np.array([0.9, 0, 0])))[0] < 0


def test_evaluation_is_chunked_and_chunks_do_not_change_values(rng):
    s = fitted(MultiOrder(), rng)
    p = rng.uniform(-1, 1, (1000, 3))
    whole = s.evaluate_box(p)
    chunked = s.evaluate_box(p, chunk_bytes=8 * 300 * 7)
    assert np.allclose(whole, chunked, rtol=1e-12, atol=1e-14)
    assert s(p[0]).shape == (1,)


def test_save_load_round_trip_is_exact(tmp_path, rng):
    for kernel in (MultiOrder(7.5, 0.013), Gaussian(0.25), ThinPlate()):
        s = fitted(kernel, rng)
        path = s.save(tmp_path / "model.npz")
        t = ImplicitSurface.load(path)
        assert t.kernel == s.kernel
        assert t.metadata == s.metadata
        p = s.normalization.inverse(rng.uniform(-1, 1, (200, 3)))
        assert np.array_equal(s(p), t(p))
        assert np.array_equal(s.gradient(p), t.gradient(p))
    assert [f.name for f in tmp_path.iterdir()] == ["model.npz"]  # no temporary left behind


def test_load_and_save_errors(tmp_path, rng):
    s = fitted(MultiOrder(), rng)
    with pytest.raises(ValueError, match="must end in .npz"):
        s.save(tmp_path / "model.bin")
    with pytest.raises(FileNotFoundError, match="model file not found"):
        ImplicitSurface.load(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="not an o3drbf model file"):
        ImplicitSurface.load(bad)
    other = tmp_path / "other.npz"
    np.savez(other, a=np.ones(3))
    with pytest.raises(ValueError, match="not an o3drbf model file"):
        ImplicitSurface.load(other)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        s(np.ones((4, 2)))
