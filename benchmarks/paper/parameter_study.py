"""The paper's parameter study: fitness error and average curvature over lambda, delta and tau.

Dinh, Turk & Slabaugh (2002), section 6: lambda (surface smoothing) trades
fitness error for smoothness; delta and tau (multi-order basis) set how far
each basis function reaches and how much it bends (the paper: delta 5..40,
tau 0.005..0.025, lambda up to about 0.003).

Here: a noisy torus; one parameter varied at a time around the defaults
(delta 10, tau 0.01, lambda 0.001), meshes at resolution 64.  For each run:
fitness error (input points to the mesh), average curvature (the exact
torus averages |H| = 1/(2 r) = 2 over its area, printed for reference),
Chamfer L1 to the analytic torus, genus.  Prints one table and writes a
2x3 plot of fitness error and curvature per parameter (PyVista Chart2D,
offscreen).

    .venv/bin/python benchmarks/paper/parameter_study.py [--out results/parameters]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "2")

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

DEFAULTS = {"lambda_surface": 1e-3, "delta": 10.0, "tau": 0.01}
GRIDS = {
    "lambda_surface": (1e-4, 3e-4, 1e-3, 3e-3, 1e-2),
    "delta": (3.0, 5.0, 10.0, 20.0, 40.0),
    "tau": (0.005, 0.01, 0.025),
}


def plot(results, path: Path) -> str:
    """Fitness error (mean) and average curvature vs each parameter, one chart per parameter."""
    from o3drbf.io.files import atomic_path
    from o3drbf.pictures import headless

    headless()
    import pyvista as pv

    plotter = pv.Plotter(shape=(2, len(GRIDS)), off_screen=True, window_size=[1500, 800], border=False)
    for j, param in enumerate(GRIDS):
        rows = [r for r in results if r["param"] == param and r["fe"] is not None]
        if not rows:
            continue
        log = param == "lambda_surface"
        xs = [math.log10(r["value"]) if log else r["value"] for r in rows]
        xlabel = "log10(lambda)" if log else param
        for i, (key, label, colour) in enumerate((("fe", "fitness error (mean)", "#1f4fd1"), ("curv", "average curvature", "#cc3311"))):
            ys = [r[key] for r in rows]
            chart = pv.Chart2D(x_label=xlabel, y_label=label)
            chart.line(xs, ys, color=colour, width=3.0)
            chart.scatter(xs, ys, color=colour, size=8, style="o")
            plotter.subplot(i, j)
            plotter.set_background("white")
            plotter.add_chart(chart)
    with atomic_path(path) as tmp:
        plotter.screenshot(tmp)
    plotter.close()
    return str(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/parameters", help="output folder (default %(default)s)")
    ap.add_argument("--points", type=int, default=6000, help="input points on the torus (default %(default)s)")
    ap.add_argument("--noise", type=float, default=0.005, help="noise along the normals, data units (default %(default)s)")
    ap.add_argument("--surface-count", type=int, default=2000, help="Poisson-disc surface constraints (default %(default)s)")
    ap.add_argument("--resolution", type=int, default=64, help="marching-cubes cells along the longest side (default %(default)s)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the sample and the constraints (default %(default)s)")
    args = ap.parse_args(argv)

    import numpy as np

    from o3drbf import reconstruct
    from o3drbf.mesh.metrics import average_curvature, chamfer, fitness_error, mesh_report
    from o3drbf.synthetic.shapes import Torus

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    shape = Torus(0.7, 0.25)
    points, normals = shape.sample(args.points, noise=args.noise, seed=args.seed)
    truth, _ = shape.sample(100_000, noise=0.0, seed=args.seed + 7)
    # Mean |H| of the exact torus, averaged by area: H = (R + 2 r cos v) / (2 r (R + r cos v)).
    v = np.linspace(0, 2 * np.pi, 20001)[:-1]
    w = shape.R + shape.r * np.cos(v)
    exact_curv = float(np.sum(np.abs((shape.R + 2 * shape.r * np.cos(v)) / (2 * shape.r * w)) * w) / np.sum(w))
    print(f"Torus(R {shape.R}, r {shape.r}): {len(points):,} points, noise {args.noise:g}; {args.surface_count:,} surface constraints; "
          f"resolution {args.resolution}; exact mean |H| (area-weighted) {exact_curv:.3f}")

    cache, results = {}, []
    for param, grid in GRIDS.items():
        for value in grid:
            params = {**DEFAULTS, param: value}
            key = tuple(sorted(params.items()))
            if key not in cache:
                t = time.perf_counter()
                try:
                    rec = reconstruct(points, normals, surface_count=args.surface_count, resolution=args.resolution, seed=args.seed, **params)
                    fe = fitness_error(points, rec.mesh)
                    cache[key] = dict(
                        fe=fe["mean"], rms=fe["rms"], curv=average_curvature(rec.mesh),
                        ch=chamfer(rec.mesh, truth, n_samples=50_000, seed=args.seed)["l1"], genus=mesh_report(rec.mesh)["genus"],
                        seconds=time.perf_counter() - t, note="",
                    )
                except RuntimeError as exc:
                    cache[key] = dict(fe=None, seconds=time.perf_counter() - t, note=str(exc).split(". The fit")[0])
            results.append({"param": param, "value": value, **cache[key]})

    names = {"lambda_surface": "lambda", "delta": "delta", "tau": "tau"}
    print()
    print("| varied | value | fitness error mean | fitness error RMS | average curvature | Chamfer L1 to truth | genus | time (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in results:
        if r["fe"] is None:
            print(f"| {names[r['param']]} | {r['value']:g} | - | - | - | - | - | {r['seconds']:.1f} ({r['note']}) |")
        else:
            print(f"| {names[r['param']]} | {r['value']:g} | {r['fe']:.5f} | {r['rms']:.5f} | {r['curv']:.3f} | {r['ch']:.5f} | {r['genus']} | {r['seconds']:.1f} |")
    print(f"(others at delta 10, tau 0.01, lambda 0.001; data units, torus R 0.7, r 0.25; exact average curvature {exact_curv:.3f})")
    try:
        print(f"plot: {plot(results, out / 'parameter_study.png')}")
    except Exception as exc:  # pragma: no cover - no OpenGL
        print(f"plot: skipped ({exc})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
