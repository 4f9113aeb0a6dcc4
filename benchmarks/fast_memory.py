"""Where a fast fit's memory goes: resident memory by stage against the up-front estimate.

One size per run, in this process: ``benchmarks/scale.py``'s problem (a torus,
N / 1.1 surface constraints and 10 % exterior ones, delta 10, tau 0.01, rtol
1e-6).  Each stage is run on its own and reports its seconds, the resident
memory after it and the peak resident memory during it (the kernel's high-water
mark, reset before each stage through ``/proc/self/clear_refs``), beside what
:func:`o3drbf.solvers.fast.memory_plan` predicted before anything was built.

Stages (wall and CPU seconds): the product's grid; its near field; the looser companions (1e-3, 1e-4);
the two-level preconditioner; the FGMRES iterations; the evaluator and a
``--grid``^3 mesh of [-1.1, 1.1]^3 (band evaluation, marching cubes, vertex normals), the plan told that box.

    python benchmarks/fast_memory.py --n 100000 [--record benchmarks/recorded/fast_memory.jsonl]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def _status(field: str) -> float:
    """A field of /proc/self/status in GB (VmRSS, VmHWM)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 2**20
    return float("nan")


def _reset_peak() -> None:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:  # not Linux, or not allowed: peaks are then cumulative
        pass


class Stages:
    """Time, resident memory after and peak during each stage."""

    def __init__(self):
        self.rows = []

    def run(self, name, func, *a, **k):
        _reset_peak()
        t, cpu = time.perf_counter(), time.process_time()
        out = func(*a, **k)
        self.add(name, time.perf_counter() - t, time.process_time() - cpu)
        return out

    def add(self, name, seconds, cpu):
        self.rows.append({"stage": name, "seconds": round(seconds, 2), "cpu_s": round(cpu, 2), "rss_gb": round(_status("VmRSS"), 3),
                          "peak_gb": round(_status("VmHWM"), 3)})
        r = self.rows[-1]
        print(f"  {name:<28} {r['seconds']:8.1f} s {r['cpu_s']:8.1f} CPU s  rss {r['rss_gb']:6.2f} GB  peak {r['peak_gb']:6.2f} GB",
              flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--grid", type=int, default=256)
    ap.add_argument("--rtol", type=float, default=1e-6)
    ap.add_argument("--record", default=None, help="append the result as one JSON line to this file")
    args = ap.parse_args(argv)

    import numpy as np

    from scale import problem

    from o3drbf.rbf.kernels import MultiOrder
    from o3drbf.solvers import available_memory, fast
    from o3drbf.solvers.fast import solver as solver_module

    kernel = MultiOrder(10.0, 0.01)
    load0 = os.getloadavg()
    st = Stages()
    c, y, lam, _, _ = st.run("centres", problem, args.n)
    t0, cpu0 = time.perf_counter(), time.process_time()
    limit = int(0.8 * available_memory())
    from o3drbf.extract import evaluate_grid, grid_for

    origin, h, shape = grid_for(np.array([[-1.1] * 3, [1.1] * 3]), args.grid, multiple=8)  # scale.py's lattice
    box = np.stack([origin, origin + h * (np.array(shape) - 1)])
    plan = st.run("plan", fast.memory_plan, kernel, c, rtol=args.rtol, limit=limit, box=box)
    eps = fast.product_tolerance(args.rtol)
    op = st.run("product grid", fast.fast_operator, kernel, c, eps=eps, memory_limit=limit)
    def near(g):  # the stored near field is built on first use; one summed on the fly is never stored
        return g.near if getattr(g, "store", False) else None

    st.run("product near field", near, op)
    st.run("companions 1e-3, 1e-4", lambda: [near(op._tier(t)) for t in (1e-3, 1e-4)])
    real = solver_module.TwoLevel
    solver_module.TwoLevel = lambda *a, **k: st.run("preconditioner", real, *a, **k)
    try:
        _reset_peak()
        t, cpu = time.perf_counter(), time.process_time()
        sol = fast.solve(kernel, c, y, lam, rtol=args.rtol, operator=op)
        sol.info.pop("preconditioner_object", None)  # (the fit's memory, not the mesh's)
        st.add("FGMRES iterations", time.perf_counter() - t - st.rows[-1]["seconds"],
               time.process_time() - cpu - st.rows[-1]["cpu_s"])
    finally:
        solver_module.TwoLevel = real
    fit_s, fit_cpu = time.perf_counter() - t0, time.process_time() - cpu0

    from skimage.measure import marching_cubes

    def mesh():
        ev = fast.make_evaluator(kernel, c, sol.weights)
        ev.cover(*box)
        vals, _ = evaluate_grid(lambda p: ev(p, False) + sol.poly[0], origin, h, shape)
        verts, _, _, _ = marching_cubes(vals, 0.0, spacing=(h, h, h))
        ev(verts + origin, True)
        return len(verts)

    del op
    vertices = st.run("evaluator and mesh", mesh)
    out = {"n": args.n, "near_field": sol.info["split"].get("near_field"), "iterations": sol.iterations, "residual": sol.residual, "fit_s": round(fit_s, 1),
           "fit_cpu_s": round(fit_cpu, 1),
           "vertices": vertices, "peak_gb": max(r["peak_gb"] for r in st.rows),
           "plan_gb": {k: round(v / 2**30, 3) for k, v in plan.items() if isinstance(v, int)},
           "plan_parts_gb": {k: round(v / 2**30, 3) for k, v in plan["parts"].items()},
           "stages": st.rows, "load": [round(x, 2) for x in load0 + os.getloadavg()],
           "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "omp_threads": os.environ.get("OMP_NUM_THREADS")}
    print(json.dumps({k: v for k, v in out.items() if k != "stages"}))
    if args.record:
        with open(args.record, "a") as f:
            f.write(json.dumps(out) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
