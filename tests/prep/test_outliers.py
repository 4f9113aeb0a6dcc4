"""Outlier removal (o3drbf.prep.outliers)."""

from __future__ import annotations

import numpy as np
import pytest

from o3drbf.prep.outliers import largest_components, statistical_outliers, voxel_components


def clusters(seed=0):
    """A dense big cluster (2,000 points), a small one (300) and 40 stray points, shuffled."""
    rng = np.random.default_rng(seed)
    big = rng.uniform(0.0, 1.0, size=(2000, 3))
    small = rng.uniform(0.0, 0.4, size=(300, 3)) + [3.0, 0.0, 0.0]
    stray = rng.uniform(-2.0, 6.0, size=(40, 3))
    stray = stray[np.linalg.norm(stray - np.clip(stray, 0.0, 1.0), axis=1) > 0.5]  # clear of the big cluster
    stray = stray[np.linalg.norm(stray - np.clip(stray, [3.0, 0, 0], [3.4, 0.4, 0.4]), axis=1) > 0.5]
    pts = np.vstack([big, small, stray])
    label = np.repeat([0, 1, 2], [len(big), len(small), len(stray)])
    order = rng.permutation(len(pts))
    return pts[order], label[order]


def test_largest_component_keeps_the_big_cluster_exactly():
    pts, label = clusters()
    kept, report = largest_components(pts, radius=0.2)
    np.testing.assert_array_equal(kept, np.flatnonzero(label == 0))
    assert report.kept == 2000 and report.removed == len(pts) - 2000
    assert report.kept_sizes == [2000] and report.largest_removed == 300
    np.testing.assert_array_equal(report.removed_indices, np.flatnonzero(label != 0))
    assert "kept 2000" in str(report)


def test_keep_two_components():
    pts, label = clusters(1)
    kept, report = largest_components(pts, radius=0.2, keep=2)
    np.testing.assert_array_equal(kept, np.flatnonzero(label < 2))
    assert report.kept_sizes == [2000, 300]


def test_voxel_components_use_the_26_neighbourhood():
    occ = np.zeros((12, 12, 12), bool)
    occ[1:5, 1:5, 1:5] = True  # 64 voxels
    occ[5, 5, 5] = True  # touches the block at a corner only: same component
    occ[7, 7, 7] = True  # one empty voxel away: separate
    occ[10, 2, 2] = occ[10, 3, 2] = True  # a separate pair
    ijk = np.argwhere(occ)
    kept, report = voxel_components(ijk)
    assert report.components == 3 and report.kept_sizes == [65]
    assert {tuple(v) for v in ijk[kept]} == {tuple(v) for v in np.argwhere(occ[:6, :6, :6])}
    kept2, report2 = voxel_components(ijk, keep=2)
    assert report2.kept_sizes == [65, 2] and len(kept2) == 67
    with pytest.raises(ValueError, match="no occupied voxel"):
        voxel_components(np.zeros((0, 3), int))


def test_statistical_outliers_remove_far_points():
    rng = np.random.default_rng(2)
    pts = np.vstack([rng.uniform(0, 1, size=(3000, 3)), [[5.0, 5.0, 5.0], [-4.0, 0.0, 0.0], [0.5, 9.0, 0.5]]])
    kept, report = statistical_outliers(pts, nb_neighbors=20, std_ratio=2.0)
    assert {3000, 3001, 3002} <= set(report.removed_indices.tolist())
    assert report.kept >= 2950  # measured: all 3,000 cluster points kept
    np.testing.assert_array_equal(np.sort(np.concatenate([kept, report.removed_indices])), np.arange(3003))


def test_bad_arguments():
    pts, _ = clusters()
    with pytest.raises(ValueError, match="radius"):
        largest_components(pts, radius=0)
    with pytest.raises(ValueError, match="keep"):
        largest_components(pts, radius=0.1, keep=0)
    with pytest.raises(ValueError, match="std_ratio"):
        statistical_outliers(pts, std_ratio=-1)
