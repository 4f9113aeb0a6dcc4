"""Core benchmark (issue 2): 3,000 constraints, fit + 128^3 extraction.

Prints one table: the multi-order basis, thin-plate and Gaussian on the
same constraints, and Open3D Poisson (depth 8) on the same points, in the
same run, with ratios to the multi-order time.  Target: multi-order fit +
128^3 extraction under 5 s on 2 cores (the paper: 1.5 min solve + 14.5 min
marching cubes on a 195 MHz R10000).

    python benchmarks/core.py [--threads 2] [--resolution 128]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=int(os.environ.get("OMP_NUM_THREADS", 2)))
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--points", type=int, default=20000)
    args = parser.parse_args(argv)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)

    import numpy as np

    import o3drbf
    from o3drbf.pipeline import DEFAULTS
    from o3drbf.extract import extract_mesh
    from o3drbf.mesh.metrics import chamfer, mesh_report
    from o3drbf.evaluation.peers import poisson
    from o3drbf.synthetic.shapes import Torus

    torus = Torus(0.6, 0.25)
    points, normals = torus.sample(args.points, noise=0.005, seed=1)
    truth, _ = torus.sample(100_000, seed=2)
    # warm-up: compile the Numba loops once, outside the timings
    o3drbf.reconstruct(points[:500], normals[:500], surface_count=100, resolution=16)

    rows = []
    base = None
    for basis, params in (("multiorder", {}), ("thinplate", {}), ("gaussian", {"sigma": 0.1})):
        t0 = time.perf_counter()
        r = o3drbf.reconstruct(points, normals, basis=basis, extract=False, surface_count=3000, **params)
        t_fit = time.perf_counter() - t0
        t0 = time.perf_counter()
        try:
            mesh = extract_mesh(r.surface, resolution=args.resolution)
            t_ext = time.perf_counter() - t0
            rep = mesh_report(mesh)
            ch = chamfer(mesh, truth)["l1"]
            note = f"{rep['triangles']:,} tri, {'closed' if rep['watertight'] else 'OPEN'}, chi {rep['euler_characteristic']}, {rep['components']} comp."
        except RuntimeError:
            t_ext, ch, note = time.perf_counter() - t0, float("nan"), "no surface"
        total = t_fit + t_ext
        base = base or total
        rows.append((f"o3drbf {basis}", len(r.constraints), t_fit, r.solution.seconds, t_ext, total, total / base, ch, note))

    t0 = time.perf_counter()
    peer = poisson(points, normals, depth=8)
    t_peer = time.perf_counter() - t0
    rep = mesh_report(peer)
    rows.append(("Open3D Poisson depth 8", len(points), float("nan"), float("nan"), float("nan"), t_peer, t_peer / base, chamfer(peer, truth)["l1"],
                 f"{rep['triangles']:,} tri, {'closed' if rep['watertight'] else 'OPEN'}, chi {rep['euler_characteristic']}, {rep['components']} comp."))

    print(f"\nCore benchmark: noisy torus ({args.points:,} points, sigma 0.005), {args.resolution}^3 grid, {args.threads} threads, "
          f"defaults delta={DEFAULTS['delta']}, tau={DEFAULTS['tau']}, lambda={DEFAULTS['lambda_surface']}")
    print("| method | constraints | fit s (solve s) | extract s | total s | x multi-order | Chamfer L1 to truth | mesh |")
    print("|---|---|---|---|---|---|---|---|")
    for name, n, fit, solve, ext, total, ratio, ch, note in rows:
        fit_s = "-" if np.isnan(fit) else f"{fit:.2f} ({solve:.2f})"
        ext_s = "-" if np.isnan(ext) else f"{ext:.2f}"
        print(f"| {name} | {n:,} | {fit_s} | {ext_s} | {total:.2f} | {ratio:.2f} | {ch:.4f} | {note} |")
    target = rows[0][5]
    print(f"\ntarget: multi-order fit + {args.resolution}^3 extraction < 5 s: {target:.2f} s -> {'MET' if target < 5 else 'NOT MET'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
