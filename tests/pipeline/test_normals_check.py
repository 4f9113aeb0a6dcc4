"""Given normals that are wrong (all inward, flipped at random, facing away from their camera) are found and repaired."""

import numpy as np
import pytest

import o3drbf
from o3drbf.prep.orientation import check_normals
from o3drbf.synthetic.shapes import Cube, Torus, TorusStack

TORUS = Torus(0.6, 0.25)
SIZES = dict(surface_count=600, resolution=40)


def _flipped_at_random(normals, fraction=0.5, seed=3):
    q = normals.copy()
    flip = np.random.default_rng(seed).random(len(q)) < fraction
    q[flip] = -q[flip]
    return q


@pytest.mark.parametrize("shape, n", [(TORUS, 3000), (Cube(), 3000), (TorusStack(3), 6000), (TORUS, 50)])
def test_check_repairs_inward_and_randomly_flipped_normals(shape, n):
    p, nrm = shape.sample(n, seed=1)
    kept, check = check_normals(p, nrm)
    assert kept is nrm and check.action == "kept" and not check.changed
    for wrong in (-nrm, _flipped_at_random(nrm)):
        fixed, check = check_normals(p, wrong)
        assert check.changed and check.reason
        assert (np.einsum("ij,ij->i", fixed, nrm) > 0).mean() > 0.99, check
        assert np.array_equal(np.abs(fixed), np.abs(nrm))  # only signs change


def test_a_thin_wall_and_an_open_patch_are_left_alone():
    # the two sides of a thin plate point opposite ways: not an inconsistency
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, (2000, 2))
    top = np.column_stack([xy[:1000], np.full(1000, 0.01)])
    bottom = np.column_stack([xy[1000:], np.full(1000, -0.01)])
    p = np.vstack([top, bottom])
    n = np.vstack([np.tile([0, 0, 1.0], (1000, 1)), np.tile([0, 0, -1.0], (1000, 1))])
    fixed, check = check_normals(p, n)
    assert fixed is n and not check.changed, check
    # one side of a plane seen (an open height field): the outside cannot be told, nothing is flipped
    up = n[:1000]
    assert check_normals(top, up)[0] is up


def test_normals_facing_away_from_their_camera_are_flipped():
    import open3d as o3d

    from o3drbf.synthetic.scans import range_scans

    sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=30)
    pts, owner, cams = range_scans(sphere, n_views=2, width=40, height=30, seed=0)
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    assert check_normals(pts, nrm, cams, owner)[0] is nrm
    bad = _flipped_at_random(nrm, 0.1)
    fixed, check = check_normals(pts, bad, cams, owner)
    assert check.away_from_camera == int((np.einsum("ij,ij->i", bad, nrm) < 0).sum()) > 0
    np.testing.assert_array_equal(fixed, nrm)


@pytest.fixture(scope="module")
def torus_normals():
    p, n = TORUS.sample(3000, seed=5)
    return p, n, o3drbf.reconstruct(p, n, **SIZES)


def _error(mesh):
    return float(np.abs(TORUS.signed_distance(np.asarray(mesh.vertices))).mean())


@pytest.mark.parametrize("case", ["inward", "half flipped"])
def test_reconstruct_repairs_wrong_normals(torus_normals, case):
    p, n, good = torus_normals
    wrong = -n if case == "inward" else _flipped_at_random(n)
    r = o3drbf.reconstruct(p, wrong, **SIZES)
    m = r.mesh
    assert m.is_watertight() and len(m.cluster_connected_triangles()[1]) == 1
    assert m.euler_poincare_characteristic() == 0  # genus 1
    assert _error(m) < 1.2 * _error(good.mesh) + 1e-4
    assert r.report.normals_repaired and good.report.normals_repaired == ""


def test_correct_normals_give_the_same_mesh_bit_for_bit(torus_normals, monkeypatch):
    p, n, good = torus_normals
    import o3drbf.pipeline.run as run  # where reconstruct looks its stages up

    monkeypatch.setattr(run, "check_given_normals", lambda data, seed=0: (data, None))
    unchecked = o3drbf.reconstruct(p, n, **SIZES)
    np.testing.assert_array_equal(np.asarray(unchecked.mesh.vertices), np.asarray(good.mesh.vertices))
    np.testing.assert_array_equal(np.asarray(unchecked.mesh.triangles), np.asarray(good.mesh.triangles))


def test_the_summary_says_the_normals_were_repaired(tmp_path, capsys):
    from o3drbf.cli import main
    from o3drbf.io.files import write_points

    p, n = TORUS.sample(2000, seed=2)
    src = write_points(tmp_path / "inward.ply", p, -n)
    assert main(["reconstruct", str(src), "-o", str(tmp_path / "m.ply"), "--surface-count", "400", "--resolution", "32"]) == 0
    out = capsys.readouterr()
    assert "normals          flipped: they pointed inward" in out.out
    assert "normals repaired" in out.err
