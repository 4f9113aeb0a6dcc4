"""The surface-constraint rule swept on the robustness study's cells (a fixed-parameter sweep, not the defaults).

Each o3drbf cell of a recorded study (``docs/data/robustness-study7.jsonl``) is
scanned again with the same seed and reconstructed with
``reconstruct(raw, cameras=..., point_camera=...)`` as the study does, except
that ``surface_count="auto"`` takes one constraint per ``--rate`` points instead
of :data:`o3drbf.options.AUTO_SIZES`'s ``points_per_constraint``, or with
``surface_adaptive=--adaptive`` (fewer constraints where the surface is flat,
:mod:`o3drbf.constraints.adaptive`, at most ``--max-factor`` times sparser;
``--select`` runs only the cells whose mesh, views, noise, outliers and
misregistration match its ``key=value`` pairs; ``--count-from`` gives each
cell the uniform subset of as many constraints as an earlier run of this
script had there, to compare a selection with the uniform one at equal count).  One JSON row
per cell, with the recorded study's Chamfer, constraint count and seconds beside
it, so the two can be compared cell by cell.  Only cells whose count the rate
changes are run (more than 3 x ``min_constraints`` points).  Interrupted runs
resume.

    python benchmarks/paper/count_rule.py --rate 5 --out results/count-rule-5.jsonl
    python benchmarks/paper/count_rule.py --adaptive 0.01 --out results/adaptive-0.01.jsonl
    python benchmarks/paper/count_rule.py --summary adaptive=results/adaptive-0.01.jsonl   # the markdown table
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import robustness as rb  # noqa: E402

STUDY = Path(__file__).resolve().parents[2] / "docs" / "data" / "robustness-study7.jsonl"


def summary(rows: list[dict]) -> dict:
    """Totals and ratios to the recorded study of one run's rows (the cells that ran)."""
    import numpy as np

    ok = [r for r in rows if "chamfer_l1" in r and r.get("study_chamfer")]
    ratio = np.array([r["chamfer_l1"] / r["study_chamfer"] for r in ok])
    fewer = np.array([1.0 - r["surface_constraints"] / r["study_constraints"] for r in ok])
    return {
        "cells": len(rows), "failed": len(rows) - len(ok),
        "constraints": int(sum(r["surface_constraints"] for r in ok)), "study_constraints": int(sum(r["study_constraints"] for r in ok)),
        "fewer_median": float(np.median(fewer)), "chamfer_median": float(np.median(ratio)),
        "chamfer_min": float(ratio.min()), "chamfer_max": float(ratio.max()),
        "worse_5": int((ratio > 1.05).sum()), "worse_10": int((ratio > 1.10).sum()),
        "watertight": int(sum(bool(r["watertight"]) for r in ok)),
        "seconds": float(sum(r["seconds"] for r in ok)), "study_seconds": float(sum(r["study_seconds"] for r in ok)),
        "fit_seconds": float(sum(r["fit_seconds"] for r in ok)) if all("fit_seconds" in r for r in ok) else float("nan"),
    }


def table(runs: dict[str, list[dict]]) -> str:
    """One markdown row per run: :func:`summary` against the recorded study."""
    lines = ["| run | cells | surface constraints (study) | fewer, median | Chamfer / study: median (min-max) | > 5 % / > 10 % worse "
             "| watertight | seconds (study) | fit seconds |", "|---|---|---|---|---|---|---|---|---|"]
    for label, rows in runs.items():
        m = summary(rows)
        lines.append(f"| {label} | {m['cells']} | {m['constraints']:,} ({m['study_constraints']:,}) | {100 * m['fewer_median']:.0f} % | "
                     f"{m['chamfer_median']:.3f} ({m['chamfer_min']:.3f}-{m['chamfer_max']:.3f}) | {m['worse_5']} / {m['worse_10']} | "
                     f"{m['watertight']} of {m['cells'] - m['failed']} | {m['seconds']:.0f} ({m['study_seconds']:.0f}) | {m['fit_seconds']:.0f} |")
    return "\n".join(lines) + "\n"


def solid_table(rows: list[dict]) -> str:
    """One markdown row per solid, views and noise (none / some) of one run: fewer constraints and the Chamfer ratio to the study."""
    import numpy as np

    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if "chamfer_l1" in r:
            groups.setdefault((r["mesh"], int(r["views"]), "none" if r["noise_pct"] == 0 else "0.5-1 %"), []).append(r)
    lines = ["| solid | views | noise | cells | fewer, median | Chamfer / study: median (max) |", "|---|---|---|---|---|---|"]
    for (mesh, views, noise), group in groups.items():
        fewer = np.median([1.0 - r["surface_constraints"] / r["study_constraints"] for r in group])
        ratio = [r["chamfer_l1"] / r["study_chamfer"] for r in group]
        lines.append(f"| {mesh} | {views} | {noise} | {len(group)} | {100 * fewer:.0f} % | {np.median(ratio):.3f} ({max(ratio):.3f}) |")
    return "\n".join(lines) + "\n"


def clean_cells(runs: dict[str, list[dict]]) -> dict[str, list[dict]]:
    """Each run's cells without noise, outliers or misregistration."""
    return {label: [r for r in rows if r["noise_pct"] == 0 and r["outliers_pct"] == 0 and r["misregistration_pct"] == 0]
            for label, rows in runs.items()}


def read_rows(path) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def runs_of(items) -> dict[str, list[dict]]:
    """``LABEL=JSONL`` items, or ``JSONL`` files whose rows name their run (a ``run`` field): label -> rows, in order."""
    runs: dict[str, list[dict]] = {}
    for item in items:
        label, sep, path = item.partition("=")
        if sep:
            runs.setdefault(label, []).extend(read_rows(path))
        else:
            for row in read_rows(label):
                runs.setdefault(row["run"], []).append(row)
    return runs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=int, default=None, help="points per surface constraint (default: the default rule's)")
    ap.add_argument("--adaptive", type=float, default=None, help="surface_adaptive tolerance (default: off)")
    ap.add_argument("--max-factor", type=float, default=None, help="o3drbf.constraints.adaptive.MAX_FACTOR (default: the code's)")
    ap.add_argument("--count-from", default=None, metavar="JSONL", help="surface_count per cell from this earlier run's rows")
    ap.add_argument("--seed", type=int, default=0, help="reconstruct's seed (the scans keep the study's; default %(default)s)")
    ap.add_argument("--select", nargs="*", default=[], metavar="KEY=VALUE", help="run only the cells matching these")
    ap.add_argument("--out", help="JSON-lines file (appended to; an interrupted run resumes)")
    ap.add_argument("--summary", nargs="+", metavar="LABEL=JSONL", help="print the markdown table of these runs (LABEL=JSONL, or a JSONL whose rows have a 'run' field) and stop")
    ap.add_argument("--study", default=str(STUDY), help="recorded study rows (default %(default)s)")
    args = ap.parse_args(argv)
    if args.summary:
        print(table(runs_of(args.summary)), end="")
        return 0
    if args.out is None:
        ap.error("give --out (or --summary)")

    import o3drbf.constraints.adaptive as adaptive
    import o3drbf.options as options
    from o3drbf import reconstruct

    if args.rate is None and args.adaptive is None and args.count_from is None and not args.seed:
        ap.error("give --rate, --adaptive, --count-from or --seed")
    counts = {}
    if args.count_from is not None:
        counts = {rb._key(r): r["surface_constraints"] for r in map(json.loads, Path(args.count_from).read_text().splitlines())
                  if r.get("surface_constraints")}
    if args.rate is not None:
        options.AUTO_SIZES["points_per_constraint"] = args.rate
    if args.max_factor is not None:
        adaptive.MAX_FACTOR = args.max_factor
    rate = options.AUTO_SIZES["points_per_constraint"]
    least = options.AUTO_SIZES["min_constraints"]
    study = [json.loads(line) for line in Path(args.study).read_text().splitlines() if line.strip()]
    cells = [r for r in study if r["method"] == "o3drbf" and r["points"] // 3 > least]
    for pair in args.select:
        key, _, value = pair.partition("=")
        cells = [r for r in cells if str(r[key]) == value or (isinstance(r[key], float) and r[key] == float(value))]
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
        row["rate"] = rate
        if args.seed:
            row["seed"] = args.seed
        count = "auto"
        if args.count_from is not None:
            if rb._key(cell) not in counts:
                continue
            count = row["surface_count"] = counts[rb._key(cell)]
        if args.adaptive is not None:
            row.update(adaptive=args.adaptive, max_factor=adaptive.MAX_FACTOR)
        t = time.perf_counter()
        try:
            rec = reconstruct(raw, cameras=cams, point_camera=owner, seed=args.seed, surface_adaptive=args.adaptive,
                              surface_count=count)
            row.update(surface_constraints=rec.report.surface_constraints, seconds=time.perf_counter() - t,
                       fit_seconds=sum(t.seconds for t in rec.report.stages if t.name == "fit"), **rb.measure(rec.mesh, mesh, 0))
        except (RuntimeError, ValueError) as exc:
            row["error"] = str(exc).splitlines()[0][:200]
        row["load"] = os.getloadavg()[0]
        row.update(study_chamfer=cell.get("chamfer_l1"), study_constraints=cell.get("surface_constraints"), study_seconds=cell.get("seconds"))
        with open(out, "a") as fh:
            fh.write(json.dumps(row) + "\n")
        ratio = row.get("chamfer_l1", float("nan")) / cell["chamfer_l1"]
        print(f"{rb._case(rb._key(cell)[:5])}: {row.get('surface_constraints')} constraints (study {cell.get('surface_constraints')}), "
              f"Chamfer {ratio:.3f} x the study's", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
