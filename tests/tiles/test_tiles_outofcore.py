"""Tiled reconstruction from files that need not fit in memory, the untiled size limit, the tiled summary."""

from __future__ import annotations

import numpy as np
import pytest

from o3drbf.io.files import open_ply_vertices
from o3drbf.synthetic.shapes import Torus

SHAPE = Torus(0.7, 0.25)


def _write_ply(path, fmt: str, props: list, rows: np.ndarray, trailer: bytes = b"", faces: int = 0) -> None:
    """A PLY by hand: ``props`` [(type, name)], ``rows`` a structured array in the file's byte order."""
    head = [b"ply", f"format {fmt} 1.0".encode(), b"comment hand-written", f"element vertex {len(rows)}".encode()]
    head += [f"property {t} {n}".encode() for t, n in props]
    if faces:
        head += [f"element face {faces}".encode(), b"property list uchar int vertex_indices"]
    head.append(b"end_header")
    with open(path, "wb") as fh:
        fh.write(b"\n".join(head) + b"\n")
        fh.write(rows.tobytes())
        fh.write(trailer)


def test_memory_mapped_ply_reads_exactly_what_open3d_reads(tmp_path):
    import open3d as o3d

    rng = np.random.default_rng(0)
    p, n = rng.normal(size=(3001, 3)) * 100.0, rng.normal(size=(3001, 3))
    # 1. Open3D's own binary output (doubles, little-endian).
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    cloud.normals = o3d.utility.Vector3dVector(n)
    o3d.io.write_point_cloud(str(tmp_path / "a.ply"), cloud, write_ascii=False)
    # 2. Big-endian floats with colours and an extra scalar in between, then a face element.
    props = [("float", "x"), ("float", "y"), ("float", "z"), ("uchar", "red"), ("uchar", "green"), ("uchar", "blue"),
             ("float", "quality"), ("float", "nx"), ("float", "ny"), ("float", "nz")]
    dt = np.dtype([(name, ">" + {"float": "f4", "uchar": "u1"}[t]) for t, name in props])
    rows = np.zeros(len(p), dt)
    for k, name in enumerate("xyz"):
        rows[name] = p[:, k]
        rows["n" + name] = n[:, k]
    rows["red"], rows["quality"] = 7, 0.5
    face = b"\x03" + np.array([0, 1, 2], ">i4").tobytes()
    _write_ply(tmp_path / "b.ply", "binary_big_endian", props, rows, trailer=face, faces=1)
    for name in ("a.ply", "b.ply"):
        ref = o3d.io.read_point_cloud(str(tmp_path / name))
        v = open_ply_vertices(tmp_path / name)
        assert len(v) == len(p) and v.has_normals
        chunks = list(v.chunks(1000))
        assert [c[0] for c in chunks] == [0, 1000, 2000, 3000]
        pts = np.concatenate([c[1] for c in chunks])
        nrm = np.concatenate([c[2] for c in chunks])
        assert pts.dtype == np.float64 and np.array_equal(pts, np.asarray(ref.points))
        assert np.array_equal(nrm, np.asarray(ref.normals))
        idx = np.array([0, 5, 2999, 3000])
        assert np.array_equal(v.gather(idx)[0], np.asarray(ref.points)[idx])
    # ASCII and truncated files are refused with what to do instead.
    o3d.io.write_point_cloud(str(tmp_path / "c.ply"), cloud, write_ascii=True)
    with pytest.raises(ValueError, match="read_points"):
        open_ply_vertices(tmp_path / "c.ply")
    data = (tmp_path / "a.ply").read_bytes()
    (tmp_path / "d.ply").write_bytes(data[: len(data) - 100])
    with pytest.raises(ValueError, match="truncated"):
        open_ply_vertices(tmp_path / "d.ply")


OPTIONS = {"tiles": 3, "surface_count_per_tile": 300, "global_count": 200, "client": "synchronous", "seed": 1}


def test_tiled_fit_from_a_file_equals_the_fit_from_the_array(tmp_path):
    import open3d as o3d

    from o3drbf.tiles.fit import fit_tiled

    pts, nrm = SHAPE.sample(3000, seed=5)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    cloud.normals = o3d.utility.Vector3dVector(nrm)
    o3d.io.write_point_cloud(str(tmp_path / "t.ply"), cloud, write_ascii=False)
    ref = o3d.io.read_point_cloud(str(tmp_path / "t.ply"))
    # A 1,500-point sample decides f0 and the cuts; the file is read 700 points at a time into per-tile files.
    small = {"partition_sample": 1500, **OPTIONS}
    from_array = fit_tiled(np.asarray(ref.points), np.asarray(ref.normals), chunk_points=3000, **small)
    store = tmp_path / "store"
    from_file = fit_tiled(open_ply_vertices(tmp_path / "t.ply"), chunk_points=700, tile_dir=store, **small)
    assert np.array_equal(from_file.base.weights, from_array.base.weights)
    for a, b in zip(from_file.tiles, from_array.tiles):
        assert np.array_equal(a.centres, b.centres) and np.array_equal(a.weights, b.weights)
    x = np.random.default_rng(3).uniform(-1, 1, size=(300, 3))
    assert np.array_equal(from_file(x), from_array(x))
    # The tiles really read files: one per tile, holding the points of its support (6 doubles each).
    files = sorted(store.glob("tile-*.f8"))
    assert len(files) == 3
    sizes = [f.stat().st_size // 56 for f in files]
    assert sizes == [t["points"] for t in from_file.metadata["tiles"]]
    assert sum(sizes) > len(pts)  # supports overlap
    # With the sample smaller than N the partition still covers every point (root box from the full bounds).
    part = from_file.partition
    box = from_file.normalization.forward(pts)
    assert (box >= part.lo.min(0)).all() and (box <= part.hi.max(0)).all()
    assert from_file.metadata["partition_sample"] == 1500
    with pytest.raises(ValueError, match="no normals"):
        cloud.normals = o3d.utility.Vector3dVector(np.zeros((0, 3)))
        o3d.io.write_point_cloud(str(tmp_path / "bare.ply"), cloud, write_ascii=False)
        fit_tiled(open_ply_vertices(tmp_path / "bare.ply"), **OPTIONS)


def test_too_large_input_without_tiles_is_refused_naming_tiles_auto(tmp_path, monkeypatch, capsys):
    from o3drbf.cli import main
    from o3drbf.io.files import write_points
    from o3drbf.options import UNTILED_MEMORY, check_untiled_fits, untiled_memory

    # The rule by hand: 512 MiB + 2,200 bytes per point, refused above 80 % of what is available.
    need = 512 * 2**20 + 2200 * 1_000_000
    assert untiled_memory(1_000_000) == need and UNTILED_MEMORY["usable_fraction"] == 0.8
    check_untiled_fits(1_000_000, available=int(need / 0.8) + 1)
    with pytest.raises(ValueError, match=r"1,000,000 points need about 2\.5 GiB .* pass --tiles auto"):
        check_untiled_fits(1_000_000, available=int(need / 0.8) - 1)
    check_untiled_fits(None, available=0)  # unknown size: nothing to check
    # The command line refuses before reading (from the PLY header), in one line, and writes nothing.
    pts, nrm = SHAPE.sample(4000, seed=2)
    write_points(tmp_path / "t.ply", pts, nrm)
    import o3drbf.io.files as files
    import o3drbf.pointset as pointset

    monkeypatch.setattr("o3drbf.solvers.base.available_memory", lambda: 600 * 2**20)
    monkeypatch.setattr(pointset, "read_input", lambda *a, **k: pytest.fail("read before the size check"))
    out = tmp_path / "m.ply"
    assert main(["reconstruct", str(tmp_path / "t.ply"), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "4,000 points need about 0.5 GiB" in err[0] and "--tiles auto" in err[0]
    assert not out.exists()
    # A format without a point count in its header is checked once read.
    monkeypatch.undo()
    monkeypatch.setattr("o3drbf.solvers.base.available_memory", lambda: 600 * 2**20)
    np.savetxt(tmp_path / "t.xyz", pts)
    assert files.point_count(tmp_path / "t.xyz") is None and files.point_count(tmp_path / "t.ply") == 4000
    data = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data.replace(b"element vertex 4000", b"element vertex 900000000"))
    assert files.point_count(tmp_path / "cut.ply") is None  # a corrupt count is the reader's to report
    assert main(["reconstruct", str(tmp_path / "cut.ply"), "-o", str(out), "-q"]) == 2
    assert "truncated" in capsys.readouterr().err
    assert main(["reconstruct", str(tmp_path / "t.xyz"), "-o", str(out), "-q"]) == 2
    assert "--tiles auto" in capsys.readouterr().err


def test_tiled_command_reads_a_binary_ply_mapped_and_reports_tiles_and_workers(tmp_path, capsys):
    import resource

    import open3d as o3d

    from o3drbf.cli import main
    from o3drbf.io.files import write_points
    from o3drbf.tiles.run import reconstruct_tiled

    pts, nrm = SHAPE.sample(4000, seed=1)
    write_points(tmp_path / "t.ply", pts, nrm)
    assert b"binary" in (tmp_path / "t.ply").read_bytes()[:200]
    out = tmp_path / "m.ply"
    args = ["reconstruct", str(tmp_path / "t.ply"), "-o", str(out), "--tiles", "3", "--scheduler", "synchronous",
            "--resolution", "32"]
    assert main(args) == 0
    text = capsys.readouterr().out
    for field in ("memory-mapped", "tiles            3; constraints per tile min", "blend overlap    25%",
                  "workers          1:", "peak", "watertight       yes (Open3D's is_watertight: closed, manifold, no self-intersecting",
                  "Euler characteristic 0, 1 component(s)"):
        assert field in text, field
    mesh = o3d.io.read_triangle_mesh(str(out))
    assert mesh.is_watertight() and mesh.euler_poincare_characteristic() == 0
    # The stats behind the summary.
    surf, mesh, stats = reconstruct_tiled(pts, nrm, tiles=3, scheduler="synchronous", resolution=32,
                                          surface_count_per_tile=300, global_count=200)
    per_tile = [t["constraints"] for t in surf.metadata["tiles"]]
    c = stats["constraints"]
    assert (c["min"], c["median"], c["max"]) == (min(per_tile), float(np.median(per_tile)), max(per_tile))
    for t in surf.metadata["tiles"]:  # about 300 Poisson-disc surface constraints plus about 10 % exterior ones
        assert t["constraints"] == t["surface"] + t["exterior"] and 200 < t["surface"] < 400
        assert 0 < t["exterior"] <= 0.15 * t["surface"]  # exterior_ratio 0.1, Poisson-disc "about"
    from o3drbf.options import DEFAULTS

    assert stats["overlap"] == DEFAULTS["overlap"] and stats["min_overlap"] == DEFAULTS["min_overlap"] and stats["points"] == 4000
    (name, w), = stats["workers"].items()  # in-process: one worker, this process
    assert name.startswith("pid ") and w["tasks"] == 3 * 3  # fit, coarse lattice, meshing per tile
    assert 0 < w["seconds"] <= stats["fit_seconds"] + stats["extract_seconds"]
    assert 50 * 2**20 < w["peak_rss"] <= resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
