"""The robustness study's cells that use the fast solver, o3drbf only, against the recorded Chamfer.

The cells of ``docs/data/robustness-study7.jsonl`` whose o3drbf row has more surface constraints
than the dense solve takes (:data:`o3drbf.solvers.DENSE_AUTO_MAX`), run again exactly as
``benchmarks/paper/robustness.py`` runs them (its ``scan`` and ``measure``, seed 0); prints and
appends (``--out``) one JSON line a cell: Chamfer L1 and F-score now and as recorded, their ratio.

``--above N`` takes the cells with more than N surface constraints instead (``--below M``: at most M); ``--solver`` (repeatable)
runs each cell with those solvers in turn (default the command's ``auto``): ``--above 5000 --below
11000 --solver dense --solver fast`` measures where the fast solve starts to beat the dense one, both in the same run.

    .venv/bin/python benchmarks/fast_study_cells.py [--above N] [--below M] [--every K] [--solver S ...] [--out FILE.jsonl]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "paper"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=None)
    ap.add_argument("--above", type=int, default=None, help="cells with more surface constraints than this (default DENSE_AUTO_MAX)")
    ap.add_argument("--below", type=int, default=None, help="and at most this many (default no limit)")
    ap.add_argument("--every", type=int, default=1, help="every K-th of those cells only (default all)")
    ap.add_argument("--solver", action="append", choices=["auto", "dense", "fast"], help="solvers to run each cell with (default auto)")
    args = ap.parse_args(argv)
    import robustness as study

    from o3drbf import reconstruct
    from o3drbf.solvers import DENSE_AUTO_MAX

    rows = [json.loads(line) for line in (HERE.parent / "docs" / "data" / "robustness-study7.jsonl").read_text().splitlines() if line.strip()]
    above = DENSE_AUTO_MAX if args.above is None else args.above
    cells = [r for r in rows if r.get("method") == "o3drbf" and (r.get("surface_constraints") or 0) > above
             and (args.below is None or r["surface_constraints"] <= args.below)][:: max(args.every, 1)]
    git = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=HERE).stdout.strip()
    for c in cells:
        mesh = study.make_mesh(c["mesh"])
        raw, owner, cams, _ = study.scan(mesh, c["views"], c["noise_pct"], c["outliers_pct"], 0, c["misregistration_pct"])
        for solver in args.solver or ["auto"]:
            t = time.perf_counter()
            rec = reconstruct(raw, cameras=cams, point_camera=owner, seed=0, solver=solver)
            m = study.measure(rec.mesh, mesh, 0)
            row = {k: c[k] for k in ("mesh", "views", "outliers_pct", "noise_pct", "misregistration_pct")}
            row.update(solver=rec.solution.method, asked=solver, iterations=rec.report.iterations,
                       surface_constraints=rec.report.surface_constraints, seconds=time.perf_counter() - t,
                       chamfer_l1=m["chamfer_l1"], recorded_chamfer_l1=c["chamfer_l1"], chamfer_ratio=m["chamfer_l1"] / c["chamfer_l1"],
                       f_score=m["f_score"], recorded_f_score=c["f_score"], watertight=m["watertight"], code=git)
            print(json.dumps(row), flush=True)
            if args.out:
                with open(args.out, "a") as fh:
                    fh.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
