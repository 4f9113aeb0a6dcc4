"""The fast solve's tolerance against what the mesh shows: a torus fitted at several ``rtol``.

``o3drbf.reconstruct`` on ``Torus().sample(N, seed=1)`` with normals and ``surface_count`` (the
command line's defaults otherwise), once per tolerance in one process: the automatic one
(:func:`o3drbf.solvers.fast.mesh_tolerance`, the default) and each fixed ``--rtol``.  Per run:
FGMRES iterations of the first solve and all rounds, fit and extract seconds, process CPU seconds
of the run, and two distances of the mesh's vertices, in mesh cells: to the analytic torus
(mean |SDF|) and to the tightest run's surface (``|f| / |grad f|`` of that fit at the vertices:
how far the looser solve moved the surface).

Usage::

    python benchmarks/fast_tolerance.py [--points 90000] [--count 30000] [--rtol 1e-6 1e-5 ...] [--out FILE.jsonl]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np


def run(points, normals, count, rtol):
    """One reconstruction; ``rtol`` None: the automatic tolerance."""
    import o3drbf
    import o3drbf.solvers as solvers
    import o3drbf.solvers.fast.tolerance as tol

    auto, solve_fast = tol.mesh_tolerance, solvers.solve_fast
    seen, its = [], []

    def counted(*a, **k):
        sol = solve_fast(*a, **k)
        its.append(sol.iterations)
        return sol

    def fixed(values, cell, *a, **k):
        seen.append(auto(values, cell, *a, **k) if rtol is None else rtol)
        return seen[-1]

    tol.mesh_tolerance, solvers.solve_fast = fixed, counted
    try:
        c0, t0 = time.process_time(), time.perf_counter()
        r = o3drbf.reconstruct(points, normals, surface_count=count)
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    finally:
        tol.mesh_tolerance, solvers.solve_fast = auto, solve_fast
    return r, {"rtol": seen[0] if seen else None, "cpu": cpu, "wall": wall, "iterations": its}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=90000)
    ap.add_argument("--count", type=int, default=30000)
    ap.add_argument("--rtol", type=float, nargs="*", default=[1e-7, 1e-6, 1e-4, 1e-3])
    ap.add_argument("--out", default=None, help="append one JSON line a run here")
    args = ap.parse_args(argv)
    from o3drbf.synthetic.shapes import Torus

    torus = Torus()
    points, normals = torus.sample(args.points, seed=1)
    runs = [None] + sorted(args.rtol)
    results = []
    for rtol in runs:
        r, rec = run(points, normals, args.count, rtol)
        results.append((r, rec))
    tight = results[1][0].surface  # the smallest fixed rtol
    git = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    for (r, rec), rtol in zip(results, runs):
        v = np.asarray(r.mesh.vertices)
        rep = r.report
        cell = 2.0 / rep.resolution / float(r.surface.normalization.scale)  # data units
        f, g = tight.evaluate(v, gradient=True)
        moved = np.abs(f) / np.maximum(np.linalg.norm(g, axis=1), 1e-12)
        sdf = np.abs(torus.signed_distance(v))
        robust = rep.robust or {}
        row = {"points": args.points, "count": args.count, "constraints": rep.surface_constraints, "rtol_asked": rtol,
               "rtol": rec["rtol"], "iterations": rec["iterations"], "residual": rep.residual, "robust_rounds": robust.get("rounds"),
               "fit_s": sum(s.seconds for s in rep.stages if s.name == "fit"),
               "extract_s": sum(s.seconds for s in rep.stages if s.name == "extract"),
               "wall_s": rec["wall"], "cpu_s": rec["cpu"], "cell": cell,
               "mean_abs_sdf": float(sdf.mean()), "mean_abs_sdf_cells": float(sdf.mean() / cell),
               "shift_mean_cells": float(moved.mean() / cell), "shift_max_cells": float(moved.max() / cell),
               "load": os.getloadavg()[0], "code": git}
        print(json.dumps(row))
        if args.out:
            with open(args.out, "a") as fh:
                fh.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
