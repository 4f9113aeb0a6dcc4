"""`make bench`: every benchmark table, one after another, in one run.

    python benchmarks/run.py [--only user,core,vision,scale,photos] [--threads 2]

``user`` (first) times the command line with its defaults against Open3D
Poisson and ferreus_rbf in the same run (:mod:`user_path`); the others are
fixed-parameter sweeps of the library's pieces, labelled as such.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
SUITES = {
    "user": ["user_path.py"],
    "core": ["core.py"],
    "vision": ["vision.py"],
    "scale": ["scale.py"],
    "photos": ["photos.py"],
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--only", default=",".join(SUITES), help="comma-separated suites: " + ", ".join(SUITES))
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    failed = []
    for name in args.only.split(","):
        if name not in SUITES:
            parser.error(f"unknown suite {name!r}; valid: {', '.join(SUITES)}")
        script = HERE / SUITES[name][0]
        print(f"\n=== {name}: {script.name} ===", flush=True)
        t0 = time.perf_counter()
        env = dict(os.environ)
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS"):
            env[var] = str(args.threads)
        print(f"threads: {args.threads} (OMP/OpenBLAS/Numba)", flush=True)
        code = subprocess.call([sys.executable, str(script)], env=env)
        print(f"({name}: {time.perf_counter() - t0:.0f} s, exit {code})", flush=True)
        if code:
            failed.append(name)
    if failed:
        print(f"failed: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
