"""Scaling benchmark of the fast (grid or FMM products + two-level FGMRES) fit and extraction.

For each N: N constraints on a torus (surface, f = 0, lambda 1e-3) plus 10%
exterior ones (offset 0.05 along the normal, f = -1, lambda 2), in the
normalized box.  Reports fit time and iterations, peak memory (ru_maxrss of a
fresh process per N), the extraction time of a 256^3 mesh (o3drbf.extract's
coarse-to-fine narrow band + marching cubes, f from the fast evaluator), the
dense solve where it fits (N <= --dense-max) and Open3D Poisson (depth 9) on
the same surface points, as ratios, and the load average.  Every size runs in
its own subprocess so peaks are per N.  ``--large`` adds 300k and 1M: each is
refused up front (with its memory estimate) when it would not fit.

    python benchmarks/scale.py --sizes 3000,10000,30000,100000 --threads 2
    python benchmarks/scale.py --sizes 30000,100000 --large --no-poisson \
        --preconditioner '{"nested": 0, "damping": 1.5}'   # the scheme before the nested level

Thread counts are fixed before NumPy loads (OMP / OpenBLAS / MKL) and printed.
fmm3dpy's PyPI wheel is single-threaded whatever the setting.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time


def _set_threads(n: int) -> None:
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(n)


def problem(n, seed=0):
    import numpy as np

    from o3drbf.synthetic.shapes import Torus

    ns = int(round(n / 1.1))
    ne = n - ns
    p, nrm = Torus().sample(ns, seed=seed)
    idx = np.random.default_rng(seed + 1).choice(ns, ne, replace=False)
    c = np.vstack([p, p[idx] + 0.05 * nrm[idx]])
    y = np.r_[np.zeros(ns), -np.ones(ne)]
    lam = np.r_[np.full(ns, 1e-3), np.full(ne, 2.0)]
    return c, y, lam, p, nrm


def band_targets(grid: int, width: float = 1.5):
    """Nodes of a grid^3 lattice on [-1.1, 1.1]^3 within ``width`` cells of the torus."""
    import numpy as np

    from o3drbf.synthetic.shapes import Torus

    t = Torus()
    ax = np.linspace(-1.1, 1.1, grid)
    h = ax[1] - ax[0]
    out = []
    for z in ax:  # slab by slab: bounded memory
        xx, yy = np.meshgrid(ax, ax, indexing="ij")
        pts = np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)])
        keep = np.abs(t.signed_distance(pts)) < width * h
        out.append(pts[keep])
    return np.concatenate(out), h


def run_one(args) -> dict:
    """One size, in this (fresh) process."""
    import resource

    import numpy as np

    from o3drbf.solvers import fast
    from o3drbf.rbf.kernels import MultiOrder
    from o3drbf.solvers import available_memory, solve
    from o3drbf.rbf.sums import kernel_sum

    n = args.n
    kernel = MultiOrder(args.delta, args.tau)
    c, y, lam, surf, nrm = problem(n)
    res = {"n": n}
    limit = int(0.8 * available_memory()) if args.memory_limit is None else int(args.memory_limit * 2**30)
    need = fast.memory_plan(kernel, c, rtol=args.rtol, limit=limit)["total"]  # the fit and a mesh, from these centres
    if need > limit:
        res["refused"] = f"needs ~{need / 2**30:.1f} GB > limit {limit / 2**30:.1f} GB"
        return res
    if args.mode == "dense":
        t = time.perf_counter()
        sol = solve(kernel, c, y, lam, method="dense")
        res["dense_s"] = time.perf_counter() - t
        res["peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
        return res
    if args.mode == "poisson":
        import open3d as o3d

        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(surf))
        pc.normals = o3d.utility.Vector3dVector(nrm)
        t = time.perf_counter()
        o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=9)
        res["poisson_s"] = time.perf_counter() - t
        return res
    if n > args.max_run:
        res["refused"] = (f"not run (above --max-run {args.max_run}): fast fit + mesh memory plan "
                          f"{need / 2**30:.1f} GB (limit {limit / 2**30:.1f} GB)")
        return res
    cpu0 = time.process_time()
    t = time.perf_counter()
    pre = json.loads(args.preconditioner) if args.preconditioner else None
    sol = fast.solve(kernel, c, y, lam, rtol=args.rtol, max_iterations=args.max_iterations, backend=args.backend,
                     preconditioner=pre)
    sol.info.pop("preconditioner_object", None)  # (the fit's memory, not the mesh's)
    res["fit_s"] = time.perf_counter() - t
    res["fit_cpu_s"] = time.process_time() - cpu0
    res["backend"] = sol.info["split"].get("split", sol.info["split"].get("mode", "?"))[:4]
    res["setup_s"] = sol.info["setup_seconds"]
    res["iterations"] = sol.iterations
    res["residual"] = sol.residual
    res["history"] = [round(math.log10(h), 1) for h in sol.info["history"]]
    res["solve_s"] = sol.info["solve_seconds"]
    res["coarse"] = sol.info["preconditioner"]["coarse"]
    res["short_nnz"] = sol.info["split"].get("short_nnz", sol.info["split"].get("near_nnz", 0))
    res["fit_peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    # Extraction: 256^3 coarse-to-fine band (o3drbf.extract) + marching cubes.
    from skimage.measure import marching_cubes

    from o3drbf.extract import evaluate_grid, grid_for

    cpu0 = time.process_time()
    t = time.perf_counter()
    ev = fast.make_evaluator(kernel, c, sol.weights, eps=args.eval_eps, backend=args.backend)
    calls = []

    def func(pts):
        calls.append(len(pts))
        return ev(pts, False) + sol.poly[0]

    origin, h, shape = grid_for(np.array([[-1.1] * 3, [1.1] * 3]), args.grid, multiple=8)
    vals, exact = evaluate_grid(func, origin, h, shape)
    verts, faces, _, _ = marching_cubes(vals, 0.0, spacing=(h, h, h))
    _, grads = ev(verts + origin, True)  # exact vertex normals, as extract_mesh does
    res["band_s"] = time.perf_counter() - t
    res["mesh_cpu_s"] = time.process_time() - cpu0
    res["band_points"] = int(sum(calls))
    res["coarse_s"] = 0.0
    res["vertices"] = len(verts)
    # Check a sample of the evaluated nodes against the direct sum.
    where = np.argwhere(exact)
    idx = np.random.default_rng(0).choice(len(where), min(2000, len(where)), replace=False)
    pts = origin + where[idx] * h
    ref = kernel_sum(kernel, c, sol.weights, pts) + sol.poly[0]
    got = vals[tuple(where[idx].T)]
    res["band_err"] = float(np.abs(got - ref).max() / np.abs(ref).max())
    res["peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="3000,10000,30000,100000")
    ap.add_argument("--large", action="store_true", help="also 300,000 and 1,000,000 (refused up front if too big)")
    ap.add_argument("--backend", default="auto", choices=["auto", "grid", "fmm"])
    ap.add_argument("--max-run", type=int, default=300_000, help="larger sizes are refused up front (with the estimate)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--delta", type=float, default=10.0)
    ap.add_argument("--tau", type=float, default=0.01)
    ap.add_argument("--rtol", type=float, default=1e-6)
    ap.add_argument("--max-iterations", type=int, default=200)
    ap.add_argument("--eval-eps", type=float, default=1e-6)
    ap.add_argument("--grid", type=int, default=256)
    ap.add_argument("--dense-max", type=int, default=10000)
    ap.add_argument("--memory-limit", type=float, default=None, help="GB (default 80%% of available)")
    ap.add_argument("--no-poisson", action="store_true")
    ap.add_argument("--preconditioner", default=None,
                    help='TwoLevel options as JSON, e.g. \'{"nested": 0, "damping": 1.5}\' (the old capped scheme)')
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--mode", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    _set_threads(args.threads)
    if args.n is not None:  # child
        print(json.dumps(run_one(args)))
        return 0

    sizes = [int(float(s)) for s in args.sizes.split(",")] + ([300_000, 1_000_000] if args.large else [])
    print((f"preconditioner: {args.preconditioner}\n" if args.preconditioner else "")
          + f"threads: OMP/OpenBLAS/MKL = {args.threads} (fmm3dpy wheel: single-threaded); "
          f"multiorder delta {args.delta} tau {args.tau}; rtol {args.rtol:g}; eval eps {args.eval_eps:g}; "
          f"grid {args.grid}^3", flush=True)

    def child(n, mode):
        cmd = [sys.executable, __file__, "--n", str(n), "--mode", mode or "fast", "--threads", str(args.threads),
               "--delta", str(args.delta), "--tau", str(args.tau), "--rtol", str(args.rtol),
               "--max-iterations", str(args.max_iterations), "--eval-eps", str(args.eval_eps),
               "--grid", str(args.grid), "--backend", args.backend,
               "--max-run", str(args.max_run)]
        if args.memory_limit is not None:
            cmd += ["--memory-limit", str(args.memory_limit)]
        if args.preconditioner:
            cmd += ["--preconditioner", args.preconditioner]
        out = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
        if out.returncode != 0:
            return {"n": n, "error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else "failed"}
        return json.loads(out.stdout.strip().splitlines()[-1])

    head = (f"{'N':>8} {'prod':>4} {'fit s':>7} {'its':>4} {'res':>7} {'|C|':>5} {'peak GB':>7} {'eval pts':>8} "
            f"{'mesh s':>7} {'fit+mesh':>8} {'dense s':>7} {'fast/dense':>10} "
            f"{'poisson s':>9} {'fast/poisson':>12} {'exp':>5} {'load':>5}")
    print(head, flush=True)
    prev = None
    for n in sizes:
        r = child(n, "fast")
        if "refused" in r or "error" in r:
            print(f"{n:>8} {r.get('refused') or r.get('error')}", flush=True)
            continue
        d = child(n, "dense") if n <= args.dense_max else {}
        p = {} if args.no_poisson else child(n, "poisson")
        total = r["fit_s"] + r["band_s"]
        load = os.getloadavg()[0]
        exp = "" if prev is None else f"{math.log(r['fit_s'] / prev[1]) / math.log(n / prev[0]):5.2f}"
        ds = f"{d['dense_s']:7.1f}" if "dense_s" in d else f"{'-':>7}"
        dr = f"{r['fit_s'] / d['dense_s']:10.2f}" if "dense_s" in d else f"{'-':>10}"
        ps = f"{p['poisson_s']:9.1f}" if "poisson_s" in p else f"{'-':>9}"
        pr = f"{r['fit_s'] / p['poisson_s']:12.1f}" if "poisson_s" in p else f"{'-':>12}"
        print(f"{n:>8} {r['backend']:>4} {r['fit_s']:7.1f} {r['iterations']:>4} {r['residual']:7.1e} {r['coarse']:>5} "
              f"{r['peak_gb']:7.2f} {r['band_points']:>8} {r['band_s']:7.1f} {total:8.1f} "
              f"{ds} {dr} {ps} {pr} {exp:>5} {load:5.1f}", flush=True)
        print(f"{'':>8} (log10 residual by iteration {r['history']})", flush=True)
        print(f"{'':>8} (CPU s: fit {r['fit_cpu_s']:.1f}, mesh {r['mesh_cpu_s']:.1f}; setup {r['setup_s']:.1f} s, short-range nnz {r['short_nnz']}, fit peak "
              f"{r['fit_peak_gb']:.2f} GB, mesh nodes max |f - direct| / max|f| {r['band_err']:.1e}, {r['vertices']} vertices"
              + (f", dense peak {d['peak_gb']:.2f} GB" if "peak_gb" in d else "") + ")", flush=True)
        prev = (n, r["fit_s"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
