"""The fast solve alone, on the very system ``o3drbf reconstruct`` builds: dump it once, solve it many ways.

``dump`` runs the command's stages up to the fit (read, outliers, constraints, automatic
parameters; ``--surface-count`` as on the command line) and saves the centres, values,
smoothing, kernel and the solve's relative residual (:func:`o3drbf.solvers.fast.mesh_tolerance`
at the command's mesh resolution) to an ``.npz``.  ``solve`` solves that system as the command
does (:func:`o3drbf.solvers.solve_fast`: the centres in spatial order) or, with ``--input-order``,
in the order the constraints were built (``o3drbf.solvers.fast.solve`` directly), and prints the
iterations, the set-up and solve seconds, the residual history and the near field's storage.
``--set module:NAME=value`` overrides a module constant first (a labelled experiment, not the
default path), e.g. ``--set o3drbf.solvers.fast.neighbours:NEAR_STORE_BYTES=0``.

    python benchmarks/fast_system.py dump torus900k.ply --surface-count 300000 sys300k.npz
    python benchmarks/fast_system.py dump torus1M.ply --all-points sys1m.npz
    python benchmarks/fast_system.py solve sys300k.npz [--iterations 200] [--input-order] [--preconditioner JSON] [--json runs.jsonl]
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import time


def dump(path: str, count: str | None, out: str) -> None:
    import numpy as np

    from o3drbf.io.files import read_points
    from o3drbf.options import Options
    from o3drbf.pipeline.constraints import build_constraints
    from o3drbf.pipeline.fitting import mesh_cells
    from o3drbf.pipeline.outliers import remove_outliers
    from o3drbf.pipeline.parameters import choose_parameters
    from o3drbf.pointset import PointSet
    from o3drbf.solvers.fast.tolerance import mesh_tolerance

    points, normals, colors = read_points(path)
    opts = Options.create(None, **({} if count is None else {"surface_count": None if count == "all" else int(count)})).validate()
    data, _ = remove_outliers(PointSet.create(points, normals, colors=colors), opts.outliers, seed=0)
    cset = build_constraints(data, opts.constraints, seed=0)
    params = choose_parameters(data, cset, opts.parameters, seed=0)
    c = cset.constraints
    rtol = mesh_tolerance(c.values, 2.0 / mesh_cells(opts.extract, cset))
    np.savez(out, centres=c.points, values=c.values, smoothing=params.smoothing, rtol=rtol,
             kernel=json.dumps(params.kernel.to_dict()))
    print(f"{out}: {len(c.points):,} constraints, rtol {rtol:.3g}, {params.kernel!r}")


def solve(path: str, iterations: int, input_order: bool, record: str | None, preconditioner: dict | None = None,
          settings: list[str] = ()) -> None:
    import warnings

    import numpy as np

    from o3drbf.rbf.kernels import make_kernel
    from o3drbf.solvers import solve_fast
    from o3drbf.solvers.fast import solve as solve_in_order
    from o3drbf.solvers.fast import spatial_order

    d = np.load(path)
    kernel = make_kernel(**json.loads(str(d["kernel"])))
    rtol = float(d["rtol"])
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if input_order or preconditioner is not None:
            order = np.arange(len(d["centres"])) if input_order else spatial_order(d["centres"])
            sol = solve_in_order(kernel, d["centres"][order], d["values"][order], d["smoothing"][order], rtol=rtol,
                                 max_iterations=iterations, preconditioner=preconditioner)
        else:
            sol = solve_fast(kernel, d["centres"], d["values"], d["smoothing"], rtol, iterations)
    wall = time.perf_counter() - t0
    info = sol.info
    row = {"system": os.path.basename(path), "n": len(d["centres"]), "order": "input" if input_order else "spatial",
           "iterations": sol.iterations, "residual": sol.residual, "rtol": rtol, "seconds": round(wall, 2),
           "setup_seconds": round(info.get("setup_seconds", 0.0), 2), "solve_seconds": round(info.get("solve_seconds", 0.0), 2),
           "near_field": info["split"].get("near_field"), "grid": info["split"].get("grid"),
           "coarse": info["preconditioner"].get("coarse"), "coarse_solve": info["preconditioner"].get("coarse_solve"),
           "preconditioner": preconditioner, "set": list(settings), "load": round(os.getloadavg()[0], 2)}
    print(json.dumps(row))
    print("history (every 4th):", " ".join(f"{v:.1e}" for v in info.get("history", [])[::4]))
    if record:
        with open(record, "a") as fh:
            fh.write(json.dumps(row) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    d = sub.add_parser("dump", help="the system the command builds, saved")
    d.add_argument("points")
    d.add_argument("out")
    d.add_argument("--surface-count", default=None)
    d.add_argument("--all-points", dest="surface_count", action="store_const", const="all", help="every point a surface constraint")
    s = sub.add_parser("solve", help="solve a dumped system")
    s.add_argument("system")
    s.add_argument("--iterations", type=int, default=200)
    s.add_argument("--input-order", action="store_true", help="the constraints' own order (fast.solve directly)")
    s.add_argument("--set", action="append", default=[], metavar="MODULE:NAME=VALUE", help="override a module constant first")
    s.add_argument("--preconditioner", default=None, metavar="JSON",
                   help="settings of the two-level preconditioner over its defaults, e.g. '{\"nested\": 8}'")
    s.add_argument("--json", default=None, help="append the result as one JSON line here")
    args = ap.parse_args(argv)
    if args.what == "dump":
        dump(args.points, args.surface_count, args.out)
        return 0
    for item in args.set:
        module, rest = item.split(":", 1)
        name, value = rest.split("=", 1)
        setattr(importlib.import_module(module), name, eval(value, {}))  # a benchmark's own flag: numbers only
        print(f"set {module}.{name} = {value}")
    solve(args.system, args.iterations, args.input_order, args.json,
          None if args.preconditioner is None else json.loads(args.preconditioner), args.set)
    return 0


if __name__ == "__main__":
    sys.exit(main())
