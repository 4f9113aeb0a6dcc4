"""``--surface-adaptive`` on the 27k-point range scan of ``benchmarks/user_path.py`` (the command line, one run at a time).

The scan is made as ``user_path.py --case scan`` makes it (three views of the
Stanford bunny's ``bun_zipper.ply``, 320 x 240 pixels, seeded); each run is
``o3drbf reconstruct scan27k.json -o OUT --report R.json`` with the default
options, or with ``surface_adaptive=TOL`` (a Python-only option: the command
line's options with it added) and
:data:`o3drbf.constraints.adaptive.MAX_FACTOR` set to ``FACTOR``, or with the
uniform ``--surface-count N``.  One JSON
row per run: surface constraints, the fit stage's seconds, the machine load,
Chamfer L1 to ``bun_zipper.ply`` (100,000 samples, seed 0, as
``benchmarks/bunny_scans.py``) and Open3D's watertight test.

    python benchmarks/paper/adaptive_scan.py --out results/adaptive-scan.jsonl default 0.01:1.6 0.01:1.25 count:4615
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", metavar="default|TOL:FACTOR|count:N", help="default, --surface-adaptive TOL with that "
                    "MAX_FACTOR, or the uniform --surface-count N")
    ap.add_argument("--out", required=True, help="JSON-lines file (appended to)")
    ap.add_argument("--folder", default="results/scan", help="where the scan and the meshes go (default %(default)s)")
    ap.add_argument("--repeats", type=int, default=1, help="runs of each setting, for the seconds (default %(default)s)")
    args = ap.parse_args(argv)

    import open3d as o3d
    import user_path

    from o3drbf.mesh.metrics import chamfer, mesh_report

    folder = Path(args.folder)
    folder.mkdir(parents=True, exist_ok=True)
    scan = folder / "scan27k.json"
    if not scan.exists():
        user_path.make_scan(folder)
    reference = o3d.io.read_triangle_mesh(str(user_path.BUNNY))
    for item in args.runs:
        tol, _, factor = item.partition(":")
        code = "import sys; from o3drbf.cli import main; sys.exit(main(sys.argv[1:]))"
        if item == "default":
            label, extra = "default", []
        elif tol == "count":
            label, extra = f"uniform --surface-count {int(factor)}", ["--surface-count", str(int(factor))]
        else:
            label, extra = f"adaptive {tol} max factor {factor}", []
            code = (f"import o3drbf.constraints.adaptive as a; a.MAX_FACTOR = {float(factor)!r}; "
                    "import o3drbf.cli.commands as c; from o3drbf.options import Options; made = c.options_from_args; "
                    f"c.options_from_args = lambda args, entry='reconstruct': Options.create(made(args, entry), surface_adaptive={float(tol)!r}); "
                    + code)
        for repeat in range(args.repeats):
            out = folder / f"{label.replace(' ', '_')}.ply"
            report = out.with_suffix(".json")
            load = os.getloadavg()[0]
            t = time.perf_counter()
            subprocess.run([sys.executable, "-c", code, "reconstruct", str(scan), "-o", str(out), "--report", str(report), *extra],
                           check=True, capture_output=True)
            seconds = time.perf_counter() - t
            rep = json.loads(report.read_text())
            mesh = o3d.io.read_triangle_mesh(str(out))
            stages = {s["name"]: round(s["seconds"], 2) for s in rep.get("stages", [])}
            row = {"run": label, "repeat": repeat, "seconds": round(seconds, 2), "load": load,
                   "surface_constraints": rep.get("surface_constraints"), "fit_seconds": stages.get("fit"), "stages": stages,
                   "chamfer_l1": chamfer(mesh, reference, n_samples=100_000, seed=0)["l1"], "watertight": bool(mesh_report(mesh)["watertight"])}
            with open(args.out, "a") as fh:
                fh.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
    return 0


def table(rows: list[dict]) -> str:
    """One markdown row per setting (its first run): constraints, Chamfer, watertight; fit seconds of every run."""
    lines = ["| run | surface constraints | Chamfer L1 to bun_zipper (1e-3) | watertight | fit seconds (load) |", "|---|---|---|---|---|"]
    seen: dict[str, list[dict]] = {}
    for r in rows:
        seen.setdefault(r["run"], []).append(r)
    for label, runs in seen.items():
        first = runs[0]
        fits = ", ".join(f"{r['fit_seconds']:.2f} ({r['load']:.1f})" for r in runs)
        lines.append(f"| {label} | {first['surface_constraints']:,} | {first['chamfer_l1'] * 1e3:.3f} | {first['watertight']} | {fits} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
