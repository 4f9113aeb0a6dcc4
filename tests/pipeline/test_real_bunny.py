"""The Stanford bunny from its 10 raw range scans and bun.conf alone, against bun_zipper.ply.

No normals are given: the exterior constraints come from the scanners (each
a direction sensor looking along its scan's local -z; method.md section 4).
Open3D screened Poisson runs on the same points the way a user would:
normals estimated by Open3D and flipped to face each point's scanner.

Shared data; skipped with the reason where ../shared/data is absent.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
BUNNY = DATA / "stanford_bunny"

if not DATA.is_dir():
    pytest.skip(f"needs the shared data folder {DATA} (not present: a clone without ../shared)", allow_module_level=True)

import open3d as o3d  # noqa: E402

from o3drbf import reconstruct  # noqa: E402
from o3drbf.cameras.model import load_cameras  # noqa: E402
from o3drbf.mesh.metrics import chamfer, mesh_report, normal_consistency  # noqa: E402
from o3drbf.evaluation.peers import poisson  # noqa: E402

pytestmark = pytest.mark.shared_data

# o3drbf, --outliers largest, surface_count 3000, resolution 96 (1.6 mm cells),
# automatic parameters (the default of the API and the CLI alike), measured:
# Chamfer L1 0.238 mm, normal consistency 0.9795, closed, 1 component, Euler
# characteristic 2 (the paper's fixed parameters gave 0.312 mm and a handle).
# Bounds: Chamfer < 0.29 mm (+22 %): moving the mesh by 0.5 mm (0.354 mm)
# fails it.  1 - normal consistency < 0.028 (measured 0.0235, +19 %): 50
# Taubin smoothing steps (0.9713) or decimation to 1,000 triangles (0.9572)
# fail it, as do the crude bun_zipper_res3/res4 decimations (0.9608, 0.9066).
RBF_CHAMFER = 0.29e-3
RBF_NC = 0.972
# Open3D Poisson depth 8 (untrimmed) on all 362,272 points, measured: Chamfer
# L1 0.068 mm, normal consistency 0.9908, closed, 1 component, Euler
# characteristic 2.  Bounds with the same relative margins; normals oriented
# the wrong way (or not at all) give a far worse surface.
POISSON_CHAMFER = 0.085e-3
POISSON_NC = 0.988


@pytest.fixture(scope="module")
def scans():
    return load_cameras(BUNNY / "data" / "bun.conf", read_scans=True)


@pytest.fixture(scope="module")
def zipper():
    return o3d.io.read_triangle_mesh(str(BUNNY / "reconstruction" / "bun_zipper.ply"))


@pytest.fixture(scope="module")
def rbf(scans):
    return reconstruct(scans.points, cameras=scans, point_camera=scans.point_camera, outliers="largest", surface_count=3000, resolution=96)


@pytest.fixture(scope="module")
def rbf_metrics(rbf, zipper):
    return chamfer(rbf.mesh, zipper, seed=0)["l1"], normal_consistency(rbf.mesh, zipper, seed=0)


def scanner_oriented_normals(scans, k: int = 30) -> np.ndarray:
    """Open3D normals, each flipped to point against its scanner's viewing direction."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scans.points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    n = np.asarray(pcd.normals).copy()
    toward = -np.array([c.direction for c in scans])[scans.point_camera]
    n[np.einsum("ij,ij->i", n, toward) < 0] *= -1
    return n


def test_rbf_from_scans_and_scanners_alone(rbf, rbf_metrics, scans, zipper):
    s = rbf.stats
    assert s["cameras"] == 10 and not s["normals_estimated"]
    assert min(s["points_seen_per_camera"]) > 0
    assert 0 < s["outliers_removed"] < 0.01 * len(scans.points)
    assert 2700 <= s["surface_constraints"] <= 3300 and 250 <= s["exterior_constraints"] <= 350

    rep = mesh_report(rbf.mesh)
    assert rep["closed"] and rep["vertex_manifold"] and rep["components"] == 1, rep
    # Not Open3D-watertight: Open3D's get_self_intersecting_triangles (run
    # in full, 46 s) finds exactly one pair, two triangles meeting near a
    # grid corner (three vertices within 2e-6 of it), flagged by Moller's
    # EPSILON snapping; exact arithmetic finds no crossing.  Measured 1.
    assert rep["self_intersections"] <= 1 and rep["watertight"] == (rep["self_intersections"] == 0), rep
    d, nc = rbf_metrics
    print(f"\no3drbf: Chamfer L1 {d * 1e3:.3f} mm, normal consistency {nc:.4f}, Euler characteristic {rep['euler_characteristic']}")
    assert d < RBF_CHAMFER, f"Chamfer L1 {d * 1e3:.3f} mm"
    assert nc > RBF_NC, f"normal consistency {nc:.4f}"

    # The bounds can fail.
    moved = copy.deepcopy(rbf.mesh).translate((0.0, 0.5e-3, 0.0))
    assert chamfer(moved, zipper, seed=0)["l1"] > RBF_CHAMFER
    assert normal_consistency(rbf.mesh.simplify_quadric_decimation(1000), zipper, seed=0) < RBF_NC


def test_exterior_constraints_lie_outside_the_bunny(rbf, zipper):
    """Exterior constraints (against the scanner directions) are outside the true surface.

    Inside/outside from ray parity against bun_zipper.ply, which is open in
    its base: within 12 mm of the base (55 of 300 constraints) parity is
    unreliable (7 there are called inside, 2 of them below the lowest vertex),
    so only the constraints above that band are checked: measured 0 of 245
    inside.  Mirrored through their closest surface points they are 99.6 %
    inside, so the check can fail.
    """
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(zipper))
    ext = rbf.constraints.select(1)
    ext = ext[ext[:, 1] > np.asarray(zipper.vertices)[:, 1].min() + 0.012].astype(np.float32)
    assert len(ext) > 200
    inside = scene.compute_occupancy(o3d.core.Tensor(ext), nsamples=3).numpy() > 0.5
    assert inside.sum() == 0, f"{inside.sum()} of {len(ext)} exterior constraints inside the bunny"
    closest = scene.compute_closest_points(o3d.core.Tensor(ext))["points"].numpy()
    mirrored = (2 * closest - ext).astype(np.float32)
    assert (scene.compute_occupancy(o3d.core.Tensor(mirrored), nsamples=3).numpy() > 0.5).mean() > 0.9


def test_open3d_poisson_with_scanner_oriented_normals(scans, zipper, rbf_metrics):
    normals = scanner_oriented_normals(scans)
    mesh = poisson(scans.points, normals, depth=8)
    rep = mesh_report(mesh)
    d = chamfer(mesh, zipper, seed=0)["l1"]
    nc = normal_consistency(mesh, zipper, seed=0)
    print(
        f"\nOpen3D Poisson depth 8: Chamfer L1 {d * 1e3:.3f} mm, normal consistency {nc:.4f}, closed {rep['closed']}, "
        f"{rep['components']} component(s), Euler characteristic {rep['euler_characteristic']}, {rep['triangles']:,} triangles"
    )
    assert rep["closed"] and rep["components"] == 1
    assert d < POISSON_CHAMFER and nc > POISSON_NC
    # Poisson uses all 362,272 points, o3drbf 3,000 constraints: Poisson is
    # closer to the zipper mesh (the o3drbf mesh fails both Poisson bounds,
    # which shows they can fail); o3drbf stays within 6x its Chamfer distance.
    rbf_d, rbf_nc = rbf_metrics
    assert rbf_d > POISSON_CHAMFER and rbf_nc < POISSON_NC
    assert rbf_d < 6 * d


def test_fig8_synthetic_scans_give_a_closed_manifold_mesh(zipper):
    """Fig. 8 set-up (3 synthetic range images around +y), constraint seed 1.

    Measured: the marching-cubes output is closed, edge-manifold, genus 0
    (Euler characteristic 2); after extract._clean's vertex welding one edge
    is non-manifold, the mesh is not closed and V - E + F = 3.
    """
    from o3drbf.synthetic.scans import range_scans

    points, owner, cams = range_scans(zipper, n_views=3, elevation=0.0, up=(0.0, 1.0, 0.0), width=200, height=150, seed=0)
    rec = reconstruct(points, cameras=cams, point_camera=owner, surface_count=2168, exterior_ratio=193 / 2168, resolution=128, seed=1)
    rep = mesh_report(rec.mesh)
    assert rep["edge_manifold"] and rep["closed"] and rep["euler_characteristic"] % 2 == 0, rep


def test_default_command_reaches_poisson_detail_on_the_dense_scans(scans, zipper):
    # The automatic sizes give 30,000 constraints and 256 cells for 362k points.
    # Measured: Chamfer L1 0.065 mm with denoised constraints, 0.080 mm without (3,000 constraints at 96 cells: 0.24 mm;
    # Open3D Poisson depth 9 about 0.07 mm), closed, one piece, genus 0.
    r = reconstruct(scans.points, cameras=scans, point_camera=scans.point_camera)
    assert r.report.surface_constraints > 25_000 and r.report.resolution == 256
    rep = mesh_report(r.mesh)
    assert rep["closed"] and rep["components"] == 1 and rep["euler_characteristic"] == 2, rep
    assert chamfer(r.mesh, zipper, seed=0)["l1"] < 0.1e-3
