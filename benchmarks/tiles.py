"""Benchmark: tiled reconstruction on Dask (o3drbf.tiles) from a file vs Open3D Poisson depth 10 (and 11).

A generated scene, sampled uniformly by area with true normals and a little
noise: a long torus (major radius 8, tube 0.6) that crosses many tiles, two
spheres, a cube and a small torus.  The points are written once to a binary
PLY; both methods start from that file in their own process (so each peak
memory is its own):

- o3drbf (first): the command a user runs, ``o3drbf reconstruct scene.ply --tiles auto -o mesh.ply``
  with its defaults (a memory-mapped file, chunked passes, per-tile point files, a LocalCluster of
  its default workers, the tiled marching cubes at its automatic resolution), timed from process
  start to the mesh written;
- Open3D screened Poisson, depth 10 (``--depth11`` adds depth 11), reading
  the same file.

Prints a markdown table (wall time from the file to the mesh, peak resident
memory: per worker and of the client for o3drbf, of the process for Poisson;
mesh size, closed-manifold, components, distance of the vertices to the
analytic surface), the ratio of times, and the per-tile records (time per
tile, per constraint).

    .venv/bin/python benchmarks/tiles.py [--points 1000000] [--workers N] [--resolution auto] [--depth11] [--keep DIR]
    .venv/bin/python benchmarks/tiles.py --large      # 10,000,000 points (opt-in: make bench-tiles-large)
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from o3drbf.synthetic.shapes import Cube, Sphere, Torus

NOISE = 0.003  # data units (the long torus's tube radius is 0.6)


class Moved:
    """A shape translated by ``offset`` (sample and signed distance)."""

    def __init__(self, shape, offset):
        self.shape, self.offset = shape, np.asarray(offset, float)

    def sample(self, n, noise=0.0, seed=0):
        p, q = self.shape.sample(n, noise=noise, seed=seed)
        return p + self.offset, q

    def signed_distance(self, x):
        return self.shape.signed_distance(np.asarray(x, float) - self.offset)


def scene_shapes():
    """(shape, area) of the scene's objects."""
    return [
        (Torus(8.0, 0.6), 4 * np.pi**2 * 8.0 * 0.6),  # long: crosses many tiles
        (Sphere(2.0, (0.0, 0.0, 0.0)), 4 * np.pi * 2.0**2),  # in the torus's hole
        (Sphere(1.5, (12.0, 3.0, 0.5)), 4 * np.pi * 1.5**2),
        (Moved(Cube(1.2), (-12.0, -2.0, 0.0)), 6 * 2.4**2),
        (Moved(Torus(1.5, 0.5), (3.0, -12.0, 0.0)), 4 * np.pi**2 * 1.5 * 0.5),
    ]


def scene(n: int, seed: int = 0):
    """(points, normals, signed_distance) of the benchmark scene: ``n`` points spread by area."""
    shapes = scene_shapes()
    areas = np.array([a for _, a in shapes])
    per = np.floor(n * areas / areas.sum()).astype(int)
    per[0] += n - per.sum()
    parts = [s.sample(int(m), noise=NOISE, seed=seed + i) for i, ((s, _), m) in enumerate(zip(shapes, per))]
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([q for _, q in parts])

    def sdf(x):
        return np.min([s.signed_distance(x) for s, _ in shapes], axis=0)

    return pts, nrm, sdf


def _peak_rss() -> int:
    """Peak resident set size of this process, bytes.

    VmHWM of /proc/self/status (this process's own memory map); ``ru_maxrss``
    would also count the parent's memory at fork, kept across the spawn's exec.
    """
    from o3drbf.tiles.cluster import peak_rss

    return peak_rss()


def _poisson(path, depth, queue):
    import open3d as o3d

    t0 = time.perf_counter()
    pcd = o3d.io.read_point_cloud(str(path))
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    seconds = time.perf_counter() - t0
    queue.put({"seconds": seconds, "peak": _peak_rss(), "vertices": np.asarray(mesh.vertices), "triangles": np.asarray(mesh.triangles)})


def _tiled(path, workers, resolution, tiles, out_dir):
    """The user's command on the file: ``o3drbf reconstruct scene.ply --tiles auto -o mesh.ply`` (defaults otherwise).

    Timed from process start to the mesh written; ``--save-model`` keeps the per-tile records for the
    tables below. Returns the record, the command's closing summary and the mesh arrays.
    """
    import resource
    import subprocess

    import open3d as o3d

    from o3drbf.tiles.surface import TiledSurface

    mesh_path, model_path = Path(out_dir) / "o3drbf.ply", Path(out_dir) / "o3drbf.npz"
    cmd = [str(Path(sys.executable).with_name("o3drbf")), "reconstruct", str(path), "--tiles", str(tiles), "-o", str(mesh_path),
           "--save-model", str(model_path)]
    cmd += [] if workers is None else ["--workers", str(workers)]
    cmd += [] if resolution == "auto" else ["--resolution", str(resolution)]
    logging.info("%s", " ".join(cmd))
    t0 = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if run.returncode != 0:
        raise RuntimeError(f"o3drbf exited with {run.returncode}: {run.stderr.strip()[-2000:]}")
    mesh = o3d.io.read_triangle_mesh(str(mesh_path))
    with np.load(model_path) as model:
        tiled = "counts" in model.files  # --tiles auto runs untiled when the input fits (and says so)
    meta = TiledSurface.load(model_path).metadata if tiled else None
    return {"seconds": seconds, "peak": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024, "summary": run.stdout.strip(),
            "vertices": np.asarray(mesh.vertices), "triangles": np.asarray(mesh.triangles), "meta": meta}


def in_process(target, *args):
    """Run ``target(*args, queue)`` in a fresh (spawned) process and return what it put on the queue."""
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=target, args=(*args, q))
    p.start()
    import queue

    while True:  # a child that dies (Open3D's Poisson has segfaulted here) must not leave this waiting forever
        try:
            out = q.get(timeout=5)
            break
        except queue.Empty:
            if not p.is_alive():
                raise RuntimeError(f"{target.__name__} died with exit code {p.exitcode} before returning a result")
    p.join()
    return out


def mesh_facts(verts, tris):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris))
    closed = bool(m.is_edge_manifold(allow_boundary_edges=False) and m.is_vertex_manifold())
    return closed, len(m.cluster_connected_triangles()[1])


def mesh_row(name, seconds, memory, verts, tris, sdf):
    """A table row. 'closed manifold' is edge-manifold without boundary and vertex-manifold (Open3D's
    is_watertight adds a self-intersection test, far too slow for Poisson's millions of triangles)."""
    closed, components = mesh_facts(verts, tris)
    d = np.abs(sdf(verts))
    return (f"| {name} | {seconds:.1f} | {memory} | {len(verts):,} | {len(tris):,} | {closed} | {components} | "
            f"{d.mean():.4f} | {np.percentile(d, 99):.4f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=None, help="points (default 1M, or 10M with --large)")
    ap.add_argument("--large", action="store_true", help="10,000,000 points")
    ap.add_argument("--workers", type=int, default=None, help="--workers of the command (default: its own)")
    ap.add_argument("--resolution", default="auto", help="--resolution of the command (default: auto, its own)")
    ap.add_argument("--tiles", default="auto")
    ap.add_argument("--no-poisson", action="store_true")
    ap.add_argument("--depth11", action="store_true", help="also Open3D Poisson depth 11")
    ap.add_argument("--keep", metavar="DIR", help="write the scene's PLY here and keep it (default: a temporary folder)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    from o3drbf.io.files import write_points

    n = args.points or (10_000_000 if args.large else 1_000_000)
    tiles = args.tiles if args.tiles == "auto" else int(args.tiles)
    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="o3drbf-bench-"))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"scene-{n}.ply"
    pts, nrm, sdf = scene(n)
    if path.exists() and args.keep:
        logging.info("scene: %s kept from an earlier run", path)
    else:
        t0 = time.perf_counter()
        write_points(path, pts, nrm)
        logging.info("scene: %s points written to %s (%.0f MB) in %.1f s", f"{n:,}", path, path.stat().st_size / 1e6, time.perf_counter() - t0)
    del pts, nrm
    rows, times = [], {}
    logging.info("o3drbf tiled ...")
    r = _tiled(path, args.workers, args.resolution, tiles, folder)
    meta = r["meta"]
    if meta is None:
        rows.insert(0, mesh_row(f"o3drbf reconstruct --tiles {tiles} (ran untiled: the input fits)", r["seconds"],
                                f"{r['peak'] / 2**30:.2f} GiB", r["vertices"], r["triangles"], sdf))
    else:
        mem = ", ".join(f"{w['peak_rss'] / 2**30:.2f}" for w in meta["workers"].values())
        mem += f" GiB/worker (fit); largest process {r['peak'] / 2**30:.2f} GiB"
        rows.insert(0, mesh_row(f"o3drbf reconstruct --tiles {tiles} ({meta['tile_count']} tiles)", r["seconds"], mem, r["vertices"],
                                r["triangles"], sdf))
    logging.info("%s", rows[0])
    depths = [] if args.no_poisson else ([10, 11] if args.depth11 else [10])
    for depth in depths:
        logging.info("Open3D Poisson depth %d ...", depth)
        p = in_process(_poisson, path, depth)
        times[depth] = p["seconds"]
        rows.append(mesh_row(f"Open3D Poisson depth {depth}", p["seconds"], f"{p['peak'] / 2**30:.2f} GiB", p["vertices"], p["triangles"], sdf))
        logging.info("%s (o3drbf / Poisson time %.2f)", rows[-1], r["seconds"] / p["seconds"])
        del p
    if not args.keep:
        import shutil

        shutil.rmtree(folder, ignore_errors=True)
    load = open("/proc/loadavg").read().split()[:3]
    print(f"\n{n:,} points (scene: long torus, 2 spheres, cube, small torus; noise {NOISE}); "
          f"load average after the run {' '.join(load)}; {os.cpu_count()} cores\n")
    print("| method | seconds (file -> mesh) | peak memory | vertices | triangles | closed manifold | components | mean abs SDF | p99 abs SDF |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    for depth, sec in times.items():
        print(f"\no3drbf / Poisson depth {depth} time: {r['seconds'] / sec:.2f}")
    if meta is None:
        print("\nthe command's summary:\n" + r["summary"])
        return 0
    infos = meta["tiles"]
    sec = np.array([i["seconds"] for i in infos])
    con = np.array([i["constraints"] for i in infos])
    print(f"\nfit: chunked spread to tile files {meta['spread_seconds']:.1f} s; global f0 {meta['base']['seconds']:.1f} s on "
          f"{meta['base']['constraints']} constraints; tiles {meta['tiles_seconds']:.1f} s wall")
    print(f"constraints per tile: min {con.min():,}, median {np.median(con):,.0f}, max {con.max():,}; "
          f"points per support: median {np.median([i['points'] for i in infos]):,.0f}, fitted from at most "
          f"{max(i['used'] for i in infos):,} ({meta.get('subsampled_tiles', 0)} tiles subsampled)")
    print(f"per tile fit: median {np.median(sec):.2f} s, max {sec.max():.2f} s ({1e3 * np.median(sec / np.maximum(con, 1)):.2f} ms per constraint)")
    print("\nthe command's summary:\n" + r["summary"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
