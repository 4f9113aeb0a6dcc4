"""Run every paper experiment (Figs. 2, 3/4, 7, 8, the parameter study, the robustness study and its settings sweep) and print their tables.

Each script runs as a subprocess with the same interpreter, writing into
``OUT/<name>`` (default ``results/``; the robustness study writes into
``OUT`` itself); its output (the markdown tables) is
printed as it comes.  Fig. 8 skips itself when the shared bunny data are
absent.  Exit status: 0 when every script exits 0, else 1 (the others still
run).

    .venv/bin/python benchmarks/paper/run_all.py [--out results] [--only fig2 fig7]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
SCRIPTS = {
    "fig2": ("fig2_cube_corner.py", "fig2"),
    "fig34": ("fig34_bases.py", "fig34"),
    "fig7": ("fig7_subset.py", "fig7"),
    "fig8": ("fig8_bunny.py", "fig8"),
    "parameters": ("parameter_study.py", "parameters"),
    # Writes robustness.md/.csv/.json/.png straight into OUT (results/paper/robustness.md).
    "robustness": ("robustness.py", "."),
    # The fixed-parameter sweep on the study's cells without outliers: settings.md beside robustness.md.
    "settings": ("settings.py", "."),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results", help="parent output folder (default %(default)s)")
    ap.add_argument("--only", nargs="+", choices=list(SCRIPTS), help="run only these experiments")
    args = ap.parse_args(argv)

    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env.setdefault(var, "2")
    names = args.only or list(SCRIPTS)
    summary = []
    for name in names:
        script, folder = SCRIPTS[name]
        print(f"\n## {name}: {script}\n", flush=True)
        t = time.perf_counter()
        rc = subprocess.call([sys.executable, str(HERE / script), "--out", str(Path(args.out) / folder)], env=env)
        summary.append((name, rc, time.perf_counter() - t))
    print("\n| experiment | exit | time (s) |\n|---|---|---|")
    for name, rc, seconds in summary:
        print(f"| {name} | {rc} | {seconds:.1f} |")
    return 0 if all(rc == 0 for _, rc, _ in summary) else 1


if __name__ == "__main__":
    sys.exit(main())
