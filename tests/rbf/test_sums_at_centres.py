"""Kernel sums at the centres themselves, each pair once (compiled), against the direct sum and NumPy."""

import numpy as np
import pytest

from o3drbf.rbf.compiled import direct_sum, direct_sum_at_centres
from o3drbf.rbf.kernels import Gaussian, MultiOrder
from o3drbf.rbf.sums import kernel_sum


@pytest.mark.parametrize("kernel", [MultiOrder(10, 0.01), Gaussian(0.3)], ids=["multiorder", "gaussian"])
@pytest.mark.parametrize("share", [1.0, 0.9, 0.1])
def test_sums_at_centres_are_the_direct_sums(kernel, share):
    rng = np.random.default_rng(5)
    c = rng.uniform(-1, 1, (700, 3))
    w = rng.standard_normal(700)
    index = np.sort(rng.choice(700, int(share * 700), replace=False))
    f, g = direct_sum_at_centres(kernel, c, w, index)
    f_direct, g_direct = direct_sum(kernel, c, w, c[index], gradient=True)
    f_numpy, g_numpy = kernel_sum(kernel, c, w, c[index], gradient=True, compiled=False)
    for ref, got in ((f_direct, f), (g_direct, g), (f_numpy, f), (g_numpy, g)):
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_sums_at_centres_refuse_bad_indices():
    c, w = np.zeros((4, 3)), np.ones(4)
    with pytest.raises(ValueError, match="repeated"):
        direct_sum_at_centres(MultiOrder(10, 0.01), c + np.arange(4)[:, None], w, np.array([0, 0]))
    with pytest.raises(ValueError, match="integers in"):
        direct_sum_at_centres(MultiOrder(10, 0.01), c, w, np.array([4]))
