"""Benchmark: tiled reconstruction on Dask (o3drbf.tiles) vs Open3D Poisson depth 10.

A generated scene, sampled with true normals: one long torus (major radius 8,
tube 0.6) for the default 1M points; ``--large`` samples 10M points on a 3 x 3
grid of such tori (not run by default).  o3drbf fits ``fit_tiled`` on a
LocalCluster (``--workers`` processes x 1 thread) and meshes with
``extract_tiled`` on the same cluster; Open3D screened Poisson (depth 10) runs
on the same points and normals in a separate process (so its peak memory is
its own).  Prints a markdown table: wall time, peak resident memory (per
worker for o3drbf, of the process for Poisson), mesh size, watertightness,
components, and the distance of the mesh vertices to the analytic surface,
then the per-tile records (time per tile, per constraint).

    .venv/bin/python benchmarks/tiles.py [--points 1000000] [--large] [--workers 2] [--resolution 256]
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing as mp
import resource
import sys
import time

import numpy as np

from o3drbf.synthetic.shapes import Torus


def scene(n: int, large: bool, seed: int = 0):
    """(points, normals, signed_distance) of the benchmark scene."""
    k = 3 if large else 1
    tori = [Torus(8.0, 0.6, center=(20.0 * i, 20.0 * j, 0.0)) for i in range(k) for j in range(k)]
    per = [n // len(tori) + (1 if i < n % len(tori) else 0) for i in range(len(tori))]
    parts = [t.sample(m, seed=seed + i) for i, (t, m) in enumerate(zip(tori, per))]
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([q for _, q in parts])

    def sdf(x):
        return np.min([t.signed_distance(x) for t in tori], axis=0)

    return pts, nrm, sdf


def _peak_rss() -> int:
    """Peak resident set size of this process, bytes (Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _poisson(pts, nrm, depth, queue):
    import open3d as o3d

    t0 = time.perf_counter()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.normals = o3d.utility.Vector3dVector(nrm)
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    seconds = time.perf_counter() - t0
    queue.put((seconds, _peak_rss(), np.asarray(mesh.vertices), np.asarray(mesh.triangles)))


def run_poisson(pts, nrm, depth=10):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_poisson, args=(pts, nrm, depth, q))
    p.start()
    out = q.get()
    p.join()
    return out


def closed_manifold(mesh) -> bool:
    """Edge-manifold without boundary and vertex-manifold (Open3D's is_watertight
    adds a self-intersection test, far too slow for Poisson's millions of triangles)."""
    return bool(mesh.is_edge_manifold(allow_boundary_edges=False) and mesh.is_vertex_manifold())


def mesh_row(name, seconds, memory, verts, tris, sdf, watertight, components):
    d = np.abs(sdf(verts))
    return (f"| {name} | {seconds:.1f} | {memory} | {len(verts):,} | {len(tris):,} | {watertight} | {components} | "
            f"{d.mean():.4f} | {np.percentile(d, 99):.4f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=None, help="points (default 1M, or 10M with --large)")
    ap.add_argument("--large", action="store_true", help="10M points on a 3 x 3 grid of tori")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--tiles", default="auto")
    ap.add_argument("--no-poisson", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    logging.getLogger("distributed").setLevel(logging.WARNING)
    import open3d as o3d
    from distributed import Client, LocalCluster

    from o3drbf.tiles.extract import extract_tiled
    from o3drbf.tiles.fit import fit_tiled

    n = args.points or (10_000_000 if args.large else 1_000_000)
    pts, nrm, sdf = scene(n, args.large)
    tiles = args.tiles if args.tiles == "auto" else int(args.tiles)
    rows = []
    if not args.no_poisson:
        sec, rss, v, t = run_poisson(pts, nrm, 10)
        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
        rows.append(mesh_row("Open3D Poisson depth 10", sec, f"{rss / 2**30:.2f} GiB", v, t, sdf, closed_manifold(m),
                             len(m.cluster_connected_triangles()[1])))
    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    client = Client(cluster)
    logging.info("dashboard %s", client.dashboard_link)
    t0 = time.perf_counter()
    surf = fit_tiled(pts, nrm, tiles=tiles, client=client, progress=False)
    t_fit = time.perf_counter() - t0
    stats = {}
    t1 = time.perf_counter()
    mesh = extract_tiled(surf, resolution=args.resolution, client=client, stats=stats)
    t_ext = time.perf_counter() - t1
    peaks = client.run(_peak_rss)
    client.close()
    cluster.close()
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    mem = ", ".join(f"{p / 2**30:.2f}" for p in peaks.values()) + " GiB/worker"
    rows.append(mesh_row(f"o3drbf tiles ({surf.metadata['tile_count']} tiles, {args.workers} workers, res {args.resolution})",
                         t_fit + t_ext, mem, v, t, sdf, closed_manifold(mesh), len(mesh.cluster_connected_triangles()[1])))
    print(f"\n{n:,} points; load average {open('/proc/loadavg').read().split()[:3]}\n")
    print("| method | seconds | peak memory | vertices | triangles | closed manifold | components | mean abs SDF | p99 abs SDF |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    infos = surf.metadata["tiles"]
    sec = np.array([i["seconds"] for i in infos])
    con = np.array([i["constraints"] for i in infos])
    print(f"\nfit {t_fit:.1f} s (global f0 {surf.metadata['base']['seconds']:.1f} s on {surf.metadata['base']['constraints']} "
          f"constraints; tiles {surf.metadata['tiles_seconds']:.1f} s wall), extraction {t_ext:.1f} s "
          f"(coarse {stats['coarse_seconds']:.1f} s, fine {stats['fine_seconds']:.1f} s, {stats['evaluated']:,} exact nodes, lattice {stats['lattice']})")
    print(f"per tile fit: median {np.median(sec):.2f} s, max {sec.max():.2f} s, {np.median(con):.0f} constraints "
          f"({1e3 * np.median(sec / np.maximum(con, 1)):.2f} ms per constraint); per tile extraction "
          f"{stats['fine_seconds'] * args.workers / len(infos):.2f} s worker time")
    return 0


if __name__ == "__main__":
    sys.exit(main())
