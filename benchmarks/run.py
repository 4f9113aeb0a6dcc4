"""`make bench`: every benchmark table, one after another, in one run.

    python benchmarks/run.py [--only core,vision,scale] [--threads 2]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
SUITES = {
    "core": ["core.py"],
    "vision": ["vision.py"],
    "scale": ["scale.py"],
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
        code = subprocess.call([sys.executable, str(script), "--threads", str(args.threads)])
        print(f"({name}: {time.perf_counter() - t0:.0f} s, exit {code})", flush=True)
        if code:
            failed.append(name)
    if failed:
        print(f"failed: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
