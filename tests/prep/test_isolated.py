"""Isolated-point rule without cameras, and the degenerate-input check."""

import numpy as np
import pytest

from o3drbf.prep.outliers import isolated_points
from o3drbf.synthetic.shapes import Cube, Sphere, TorusStack


def stacked_tori(n_each, noise=0.0, frac=0.02, seed=0):
    """Three tori sampled separately (genuine rows first) plus uniform outliers in the padded box."""
    parts = [t.sample(n_each, noise=noise, seed=seed + i)[0] for i, t in enumerate(TorusStack().tori)]
    genuine = np.vstack(parts)
    lo, hi = genuine.min(axis=0), genuine.max(axis=0)
    pad = 0.1 * (hi - lo)
    k = int(round(frac / (1 - frac) * len(genuine)))
    out = np.random.default_rng(seed + 9).uniform(lo - pad, hi + pad, (k, 3))
    return np.vstack([genuine, out]), len(genuine)


def test_stacked_tori_with_uniform_outliers():
    pts, ng = stacked_tori(8000)
    mask = isolated_points(pts)
    assert 1 - mask[:ng].mean() >= 0.995  # every torus kept
    for i in range(3):  # each torus separately
        assert mask[i * 8000 : (i + 1) * 8000].mean() < 0.005
    assert mask[ng:].mean() >= 0.9


def test_noisy_tori_catch_the_outliers_off_the_surface():
    sigma = 0.005
    pts, ng = stacked_tori(8000, noise=sigma, seed=3)
    mask = isolated_points(pts)
    assert mask[:ng].mean() < 0.005
    dist = np.abs(TorusStack().signed_distance(pts[ng:]))
    far = dist > 0.03  # beyond 6 sigma (about 2.5 spacings): unmistakable outliers
    assert mask[ng:][far].mean() >= 0.95


def test_separate_small_object_and_edges_are_kept():
    big, _ = Sphere(1.0).sample(6000, seed=1)
    small, _ = Sphere(0.1, center=(3.0, 0.0, 0.0)).sample(150, seed=2)  # far away, 40x fewer points
    cube, _ = Cube(0.5).sample(8000, noise=0.002, seed=3)  # sharp edges and corners
    pts = np.vstack([big, small, cube + (0.0, 4.0, 0.0)])
    mask = isolated_points(pts)
    assert not mask[6000:6150].any()
    assert mask.mean() < 0.001
    # A point hovering off the big sphere's surface (2 spacings out) is caught by the off-surface rule.
    probe = np.array([[0.0, 0.0, 1.05]])
    assert isolated_points(np.vstack([big, probe]))[-1]


def test_isolated_points_input():
    pts = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(ValueError, match="k must be"):
        isolated_points(pts, k=2)
    with pytest.raises(ValueError, match="duplicates"):
        isolated_points(np.zeros((20, 3)))
    assert not isolated_points(pts, spacing=10.0).any()  # thresholds above every distance


def test_check_spans_volume():
    from o3drbf.prep.normalize import check_spans_volume, extent_ratios

    rng = np.random.default_rng(0)
    sphere, _ = Sphere(1.0).sample(500)
    np.testing.assert_allclose(check_spans_volume(sphere), 1.0, atol=0.15)
    # A box 4 x 2 x 1 (uniform inside): extents proportional to the sides (truth: 4 : 2 : 1).
    box = rng.uniform(-0.5, 0.5, (20000, 3)) * [4.0, 2.0, 1.0]
    np.testing.assert_allclose(extent_ratios(box), [1.0, 0.5, 0.25], atol=0.01)
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    flat = np.hstack([rng.uniform(-1, 1, (300, 2)), np.zeros((300, 1))]) @ rot.T + 5.0
    with pytest.raises(ValueError, match="points span no volume \\(they lie on a plane"):
        check_spans_volume(flat)
    with pytest.raises(ValueError, match="give normals for an open patch, or more views"):
        check_spans_volume(flat + rng.normal(0, 1e-5, flat.shape))  # a scan of a wall
    line = np.outer(np.linspace(0, 1, 50), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="they lie on a line"):
        check_spans_volume(line)
    needle = rng.uniform(-0.5, 0.5, (2000, 3)) * [1.0, 1e-4, 1e-4]
    with pytest.raises(ValueError, match="line"):
        check_spans_volume(needle)
    assert check_spans_volume(needle, min_ratio=1e-5)[2] < 1e-3
    with pytest.raises(ValueError, match="coincide"):
        check_spans_volume(np.ones((5, 3)))
    with pytest.raises(ValueError, match="min_ratio"):
        check_spans_volume(sphere, min_ratio=2.0)


def _isolated_reference(pts, k=24, radius_spacings=5.0, min_component=10, off_surface=5.0, off_spacings=1.5):
    """isolated_points as first written: a k=2 query for the spacing, the plane's neighbours by fancy indexing."""
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(pts)
    tree = cKDTree(pts)
    spacing = float(np.median(tree.query(pts, k=2)[0][:, 1]))
    pairs = tree.query_pairs(radius_spacings * spacing, output_type="ndarray")
    graph = sparse.coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    isolated = np.bincount(labels)[labels] < min_component
    _, idx = tree.query(pts, k=k + 1)
    nb = pts[idx[:, 1:]]
    centroid = nb.mean(axis=1)
    q = nb - centroid[:, None, :]
    _, vecs = np.linalg.eigh(np.matmul(q.transpose(0, 2, 1), q) / k)
    normal = vecs[:, :, 0]
    rms = np.sqrt((np.matmul(q, normal[:, :, None])[..., 0] ** 2).mean(axis=1))
    offset = np.abs(np.einsum("ni,ni->n", pts - centroid, normal))
    return isolated | ((offset > off_surface * rms) & (offset > off_spacings * spacing))


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_isolated_points_match_the_first_written_rule(noise):
    pts, _ = stacked_tori(4000, noise=noise, frac=0.03, seed=2)
    pts = np.vstack([pts, pts[:50]])  # duplicates too: a zero nearest distance for those
    got = isolated_points(pts)
    reference = _isolated_reference(pts)
    np.testing.assert_array_equal(got, reference)
    assert 0 < reference.sum() < len(pts)


def test_small_components_at_the_size_limit_and_chains_to_the_surface():
    """Tight clusters of 8 to 11 points far off (the limit is 10), a sparse chain of points leading off
    the surface (each within the component radius of the next, with too few neighbours to tell alone)
    and the same chain detached: the component rule is the full graph's, cluster by cluster."""
    big, _ = Sphere(1.0).sample(5000, seed=4)
    from scipy.spatial import cKDTree

    spacing = float(np.median(cKDTree(big).query(big, k=2)[0][:, 1]))
    r = 5.0 * spacing
    rng = np.random.default_rng(5)
    clusters = [np.array([3.0 + size, 0.0, 0.0]) + rng.normal(scale=0.2 * r, size=(size, 3)) for size in (8, 9, 10, 11)]
    steps = np.arange(1, 7)[:, None] * np.array([0.8 * r, 0.0, 0.0])
    attached = np.array([1.0, 0.0, 0.0]) + steps
    detached = np.array([1.0 + 3 * r, 0.0, 0.0]) + steps + np.array([0.0, 0.0, 0.5])
    pts = np.vstack([big, *clusters, attached, detached])
    got = isolated_points(pts, off_surface=1e9)
    np.testing.assert_array_equal(got, _isolated_reference(pts, off_surface=1e9))
    sizes = np.cumsum([5000, 8, 9, 10, 11, 6, 6])
    assert got[sizes[0]:sizes[2]].all() and not got[sizes[2]:sizes[4]].any()
    assert not got[:sizes[0]].any() and not got[sizes[4]:sizes[5]].any() and got[sizes[5]:].all()


def test_isolated_points_fit_the_planes_chunk_by_chunk_as_all_at_once(monkeypatch):
    """Planes fitted a chunk of points at a time (the last chunk partial), outliers planted in later chunks:
    the same mask as the first written rule, which fits every point's plane at once."""
    from o3drbf.prep import outliers

    pts, _ = stacked_tori(4000, noise=0.01, frac=0.03, seed=2)
    monkeypatch.setattr(outliers, "PLANE_CHUNK", 997)
    got = isolated_points(pts)
    np.testing.assert_array_equal(got, _isolated_reference(pts))
    assert got[-300:].sum() > 100  # the uniform outliers, in the last chunks, are found
