"""The surface-constraint rate swept on the robustness study's cells (a fixed-parameter sweep, not the defaults).

Each o3drbf cell of a recorded study (``docs/data/robustness-study7.jsonl``) is
scanned again with the same seed and reconstructed with
``reconstruct(raw, cameras=..., point_camera=...)`` as the study does, except
that ``surface_count="auto"`` takes one constraint per ``--rate`` points instead
of :data:`o3drbf.options.AUTO_SIZES`'s ``points_per_constraint``.  One JSON row
per cell, with the recorded study's Chamfer, constraint count and seconds beside
it, so the two can be compared cell by cell.  Only cells whose count the rate
changes are run (more than 3 x ``min_constraints`` points).  Interrupted runs
resume.

    python benchmarks/paper/count_rule.py --rate 5 --out results/count-rule-5.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import robustness as rb  # noqa: E402

STUDY = Path(__file__).resolve().parents[2] / "docs" / "data" / "robustness-study7.jsonl"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=int, required=True, help="points per surface constraint (the default rule: 3)")
    ap.add_argument("--out", required=True, help="JSON-lines file (appended to; an interrupted run resumes)")
    ap.add_argument("--study", default=str(STUDY), help="recorded study rows (default %(default)s)")
    args = ap.parse_args(argv)

    import o3drbf.options as options
    from o3drbf import reconstruct

    options.AUTO_SIZES["points_per_constraint"] = args.rate
    least = options.AUTO_SIZES["min_constraints"]
    study = [json.loads(line) for line in Path(args.study).read_text().splitlines() if line.strip()]
    cells = [r for r in study if r["method"] == "o3drbf" and r["points"] // 3 > least]
    out = Path(args.out)
    done = {rb._key(json.loads(line)) for line in out.read_text().splitlines() if line.strip()} if out.exists() else set()
    meshes = {}
    for cell in cells:
        if rb._key(cell) in done:
            continue
        name = cell["mesh"]
        mesh = meshes.setdefault(name, rb.make_mesh(name))
        raw, owner, cams, _ = rb.scan(mesh, int(cell["views"]), cell["noise_pct"], cell["outliers_pct"], 0, cell["misregistration_pct"])
        row = {k: cell[k] for k in ("mesh", "views", "outliers_pct", "noise_pct", "misregistration_pct", "method", "points")}
        row["rate"] = args.rate
        t = time.perf_counter()
        try:
            rec = reconstruct(raw, cameras=cams, point_camera=owner, seed=0)
            row.update(surface_constraints=rec.report.surface_constraints, seconds=time.perf_counter() - t, **rb.measure(rec.mesh, mesh, 0))
        except (RuntimeError, ValueError) as exc:
            row["error"] = str(exc).splitlines()[0][:200]
        row.update(study_chamfer=cell.get("chamfer_l1"), study_constraints=cell.get("surface_constraints"), study_seconds=cell.get("seconds"))
        with open(out, "a") as fh:
            fh.write(json.dumps(row) + "\n")
        ratio = row.get("chamfer_l1", float("nan")) / cell["chamfer_l1"]
        print(f"{rb._case(rb._key(cell)[:5])}: {row.get('surface_constraints')} constraints (study {cell.get('surface_constraints')}), "
              f"Chamfer {ratio:.3f} x the study's", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
