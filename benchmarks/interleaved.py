"""Run the command line of two revisions in turn on the same input: wall and CPU seconds, load, stages, same mesh?

A shared machine's load moves from one minute to the next, so two revisions timed an hour apart
do not compare; run in turn, each pair of runs sees about the same load.  The other revision is
``git archive REV o3drbf`` unpacked into a temporary folder and put first on ``PYTHONPATH`` (this
checkout's editable install bypassed: the imported module's path is checked), run by this
checkout's Python; both trees are byte-compiled first (a tree without ``.pyc`` files, with
PYTHONDONTWRITEBYTECODE set, compiles every module at every run), and each side's Numba cache is
warmed by one untimed run.

    python benchmarks/interleaved.py INPUT [--rev main] [--runs 3]
    python benchmarks/interleaved.py [--rev main] [--runs 3] -- INPUT EXTRA CLI ARGS   (e.g. --surface-count 300000)

Each run is the user's command line as ``benchmarks/user_path.py`` runs it (``--report`` added, no
``-q``: the closing summary and its checks are part of the run).  Prints a markdown table (one row
per run): revision, 1-minute load at the start, wall seconds, CPU seconds (user + system of the
process and its children), the fit / extract / checks stage seconds of ``--report``, and whether
the mesh has exactly the vertices and triangles of the other revision's first timed mesh; then each
stage's median over the runs, by revision.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def load() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def unpack(rev: str, folder: Path) -> Path:
    """``git archive rev o3drbf`` into ``folder``; returns the folder to put on PYTHONPATH."""
    folder.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "o3drbf"], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    compiled(folder / "o3drbf")
    return folder


def compiled(package: Path) -> None:
    """Byte-compile ``package`` (``compileall``): with PYTHONDONTWRITEBYTECODE set no run writes its
    ``.pyc``, and a tree without them would compile every module it imports at every run."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(package)], check=True, capture_output=True)


def run(source: Path | None, args: list[str], out: Path) -> dict:
    """One run of ``python -m o3drbf reconstruct ARGS -o OUT --report``: seconds, CPU, load, stages."""
    env = dict(os.environ)
    if source is not None:
        env["PYTHONPATH"] = str(source)
    # run from the output's folder: the current folder comes first on sys.path, and this checkout's would win
    check = subprocess.run([sys.executable, "-c", "import o3drbf; print(o3drbf.__file__)"], capture_output=True, text=True, env=env,
                           cwd=out.parent)
    where = Path(check.stdout.strip()).resolve()
    expected = (source if source is not None else ROOT) / "o3drbf" / "__init__.py"
    if where != expected.resolve():
        raise SystemExit(f"interleaved: o3drbf imports from {where}, expected {expected}")
    report = out.with_suffix(".json")
    report.unlink(missing_ok=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start_load = load()
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "o3drbf", "reconstruct", *args, "-o", str(out), "--report", str(report)],
                          capture_output=True, text=True, env=env, cwd=out.parent)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode:
        raise SystemExit(f"interleaved: exit {proc.returncode}: {proc.stderr[-500:]}")
    stages = {s["name"]: s["seconds"] for s in json.loads(report.read_text())["stages"]}
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"load": start_load, "wall": wall, "cpu": cpu, "stages": stages}


def mesh_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("input")
    parser.add_argument("--rev", default="main", help="the other revision (default main)")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("extra", nargs="*", help="further reconstruct arguments (with them, put -- before INPUT)")
    a = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="o3drbf-interleaved-") as tmp:
        folder = Path(tmp)
        other = unpack(a.rev, folder / "other")
        compiled(ROOT / "o3drbf")  # (this checkout's .pyc, for the same reason)
        args = [str(Path(a.input).resolve()), *a.extra]
        sides = [(a.rev, other), ("this checkout", None)]
        for name, source in sides:  # warm each side's Numba cache, untimed
            run(source, args, folder / f"warm-{name.replace(' ', '_')}.ply")
        reference = None  # the other revision's first timed mesh (a warm-up run may compile its kernels afresh, and
        # freshly compiled and cached kernels can differ in the last bit)
        print(f"input {a.input}, extra arguments {a.extra or 'none'}; {os.cpu_count()} cores")
        print()
        print("| run | code | load | wall s | CPU s | fit s | extract s | checks s | same mesh as " + a.rev + " |")
        print("|---|---|---|---|---|---|---|---|---|")
        runs = {name: [] for name, _ in sides}
        for i in range(a.runs):
            for name, source in sides:
                out = folder / f"run{i}-{name.replace(' ', '_')}.ply"
                r = run(source, args, out)
                v, t = mesh_arrays(out)
                if reference is None:
                    reference = v, t
                same = v.shape == reference[0].shape and np.array_equal(v, reference[0]) and np.array_equal(t, reference[1])
                st = r["stages"]
                print(f"| {i + 1} | {name} | {r['load']:.2f} | {r['wall']:.2f} | {r['cpu']:.2f} | {st.get('fit', np.nan):.2f} | "
                      f"{st.get('extract', np.nan):.2f} | {st.get('checks', np.nan):.2f} | {'yes' if same else 'no'} |", flush=True)
                runs[name].append(r)
        names = list(dict.fromkeys(k for rs in runs.values() for r in rs for k in r["stages"]))  # in the order of the stages
        print()
        print("| medians | wall s | CPU s | " + " | ".join(names) + " |")
        print("|---|" + "---|" * (len(names) + 2))
        for name, rs in runs.items():
            med = [np.median([r["stages"].get(k, np.nan) for r in rs]) for k in names]
            print(f"| {name} | {np.median([r['wall'] for r in rs]):.2f} | {np.median([r['cpu'] for r in rs]):.2f} | "
                  + " | ".join(f"{m:.3f}" for m in med) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
