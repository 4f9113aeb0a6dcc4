"""The tiled path on lidar files read chunk by chunk (o3drbf.cameras.lidar.LidarPoints): E57 scans with
their scanners, LAZ points without normals (estimated per tile, oriented along f0)."""

from __future__ import annotations

import numpy as np
import pytest

from o3drbf.cameras.lidar import LidarPoints, load_e57
from o3drbf.pointset import read_input
from o3drbf.synthetic.shapes import Torus

pytest.importorskip("laspy")
pytest.importorskip("pye57")
pytest.importorskip("distributed")

TORUS = Torus(0.6, 0.25)
SCANNERS = [[2.5, 0.0, 1.2], [-1.25, 2.2, 1.0], [-1.25, -2.2, -1.0]]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    import open3d as o3d

    from o3drbf.synthetic.lidar import e57_scans_from, terrestrial_scans, write_e57, write_las

    mesh = o3d.geometry.TriangleMesh.create_torus(0.6, 0.25, 90, 45)
    points, owner, cams = terrestrial_scans(mesh, SCANNERS, step=0.5, noise=0.002, outliers=0.02)
    d = tmp_path_factory.mktemp("lidar")
    write_e57(d / "t.e57", e57_scans_from(points, owner, cams))
    write_las(d / "t.laz", points)
    return d / "t.e57", d / "t.laz"


def test_e57_source_gives_the_points_and_scanners_load_e57_reads(files):
    e57, _ = files
    truth = load_e57(e57, chunk_size=997)
    src = LidarPoints(e57, chunk_size=1500)
    assert src.count == len(truth.points) and len(src.cameras) == len(truth.cameras) == 3
    chunks = list(src.chunks())
    assert np.allclose(np.concatenate([p for _, p, _ in chunks]), truth.points, atol=1e-12)
    assert [s for s, _, _ in chunks] == list(np.cumsum([0] + [len(p) for _, p, _ in chunks[:-1]]))
    idx = np.sort(np.random.default_rng(0).choice(src.count, 700, replace=False))
    pts, nrm = src.gather(idx)
    assert nrm is None and np.allclose(pts, truth.points[idx], atol=1e-12)
    assert np.array_equal(src.point_camera[idx], truth.point_camera[idx])
    assert np.array_equal(src.point_camera[0:src.count], truth.point_camera)
    for a, b in zip(src.cameras, truth.cameras):
        assert np.allclose(a.center, b.center) and np.allclose(a.R, b.R)


def _error(mesh) -> float:
    return float(np.abs(TORUS.signed_distance(np.asarray(mesh.vertices))).mean())


@pytest.mark.parametrize("name", ["e57", "laz"])
def test_chunked_lidar_tiles_match_the_file_read_into_memory(files, name):
    """Chunked (files per tile; a LAZ's normals estimated in each tile and turned outward along f0) against the
    same file read whole (a LAZ's normals estimated once over the cloud): the same outliers removed, meshes
    watertight, one piece, as close to the analytic torus."""
    from o3drbf.tiles.run import reconstruct_tiled

    path = files[0] if name == "e57" else files[1]
    common = dict(tiles=3, scheduler="synchronous", resolution=48)
    _, chunked, a = reconstruct_tiled(LidarPoints(path, chunk_size=3000), **common)
    _, whole, b = reconstruct_tiled(read_input(path), **common)
    assert a["cameras"] == (3 if name == "e57" else 0)
    assert a["kept"] == b["kept"] and a["outliers"] == b["outliers"] > 100
    for mesh in (chunked, whole):
        assert mesh.is_watertight() and len(mesh.cluster_connected_triangles()[1]) == 1
    assert _error(chunked) < 0.0015
    assert _error(chunked) < 1.2 * _error(whole)


def test_command_line_tiles_read_a_laz_chunk_by_chunk(files, tmp_path, capsys):
    from o3drbf.cli import main

    out = tmp_path / "m.ply"
    assert main(["reconstruct", str(files[1]), "--tiles", "3", "-o", str(out), "--resolution", "40", "--scheduler", "synchronous"]) == 0
    text = capsys.readouterr().out
    assert "read chunk by chunk, spread to per-tile files" in text and "watertight       yes" in text
