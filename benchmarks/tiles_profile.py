"""CPU time per stage of the tiled path, on the scene of ``benchmarks/tiles.py``.

Runs ``reconstruct_tiled`` from a memory-mapped binary PLY on a LocalCluster
started here (so that the workers' whole CPU time can be read before and
after), and prints CPU seconds (user + system) per stage:

- client: reading the bounds and the sample, the global fit f0, the k-d
  partition and the spread of the points to the tiles, the assembly of the
  coarse lattice and the weld;
- tasks: the per-tile fits, the coarse and the fine (meshing) passes, summed
  over the tasks as measured inside them;
- Dask overhead: the workers' CPU beyond their tasks' (start-up, imports,
  (de)serialization, heartbeats), and the scheduler's (in this process).

CPU time, not wall time: on a machine shared with other work the wall clock
says little.  Lines of JSON with ``--json FILE``.

    .venv/bin/python benchmarks/tiles_profile.py [--points 300000] [--workers 2] [--resolution 256]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _cpu():
    import psutil

    t = psutil.Process().cpu_times()
    return t.user + t.system + t.children_user + t.children_system


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--resolution", default="256")
    ap.add_argument("--json", metavar="FILE", help="append the record as one line of JSON")
    ap.add_argument("--label", default="")
    ap.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                    help="an option of reconstruct_tiled (a key of o3drbf.options.DEFAULTS; the value read as Python)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import distributed

    from o3drbf.io.files import open_ply_vertices, write_points
    from o3drbf.tiles.run import reconstruct_tiled
    from tiles import scene

    pts, nrm, sdf = scene(args.points)
    folder = Path(tempfile.mkdtemp(prefix="o3drbf-profile-"))
    path = folder / "scene.ply"
    write_points(path, pts, nrm)
    del pts, nrm
    resolution = args.resolution if args.resolution == "auto" else int(args.resolution)
    import ast

    extra = {k: ast.literal_eval(v) for k, v in (o.split("=", 1) for o in args.option)}
    cluster = distributed.LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, memory_limit="8GiB",
                                       dashboard_address=":0")
    client = distributed.Client(cluster)
    try:
        before = client.run(_cpu)
        c0, t0 = _cpu(), time.perf_counter()
        surface, mesh, stats = reconstruct_tiled(open_ply_vertices(path), scheduler=client, resolution=resolution, **extra)
        wall = time.perf_counter() - t0
        client_cpu = _cpu() - c0
        after = client.run(_cpu)
    finally:
        client.close()
        cluster.close()
        path.unlink()
        folder.rmdir()
    meta = surface.metadata
    fit_cpu, ext_cpu = meta["cpu"], stats["extraction"]["cpu"]
    workers_cpu = sum(after[w] - before[w] for w in after)
    tasks_cpu = fit_cpu["tiles_tasks"] + ext_cpu["coarse_tasks"] + ext_cpu["fine_tasks"]
    client_stages = fit_cpu["prepare"] + fit_cpu["base"] + fit_cpu["spread"] + ext_cpu["weld"]
    rows = {
        "client: bounds, sample, noise": fit_cpu["prepare"],
        "client: global fit f0": fit_cpu["base"],
        "client: partition + spread to tiles": fit_cpu["spread"],
        "tasks: per-tile fit": fit_cpu["tiles_tasks"],
        "tasks: coarse lattice": ext_cpu["coarse_tasks"],
        "tasks: fine meshing": ext_cpu["fine_tasks"],
        "client: weld": ext_cpu["weld"],
        "Dask: workers beyond their tasks": workers_cpu - tasks_cpu,
        "client: scheduler, waiting, coarse assembly, band": client_cpu - client_stages,
    }
    d = np.abs(sdf(np.asarray(mesh.vertices)))
    total = client_cpu + workers_cpu
    print(f"\n{args.points:,} points, {stats['tiles']} tiles, {args.workers} workers, resolution {resolution} {args.label}")
    print("| stage | CPU s |\n|---|---|")
    for k, v in rows.items():
        print(f"| {k} | {v:.1f} |")
    print(f"| **total CPU** | **{total:.1f}** |")
    cons = stats["constraints"]
    print(f"wall {wall:.1f} s; constraints per tile {cons}; exact nodes {stats['extraction']['evaluated']:,}; "
          f"mesh {stats['triangles']:,} triangles; mean |SDF| {d.mean():.5f}, p99 {np.percentile(d, 99):.5f}; "
          f"watertight {mesh.is_watertight()}; load {open('/proc/loadavg').read().split()[:3]}")
    if args.json:
        rec = {"label": args.label, "options": extra, "points": args.points, "tiles": stats["tiles"], "workers": args.workers, "resolution": resolution,
               "cpu": rows, "total_cpu": total, "wall": wall, "constraints": cons, "evaluated": stats["extraction"]["evaluated"],
               "triangles": stats["triangles"], "mean_sdf": float(d.mean()), "p99_sdf": float(np.percentile(d, 99))}
        with open(args.json, "a") as fh:
            fh.write(json.dumps(rec) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
