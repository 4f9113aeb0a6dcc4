"""The paper's Figs. 3/4: thin-plate, Gaussian and multi-order bases on the same constraints.

Dinh, Turk & Slabaugh (2002), Figs. 3 and 4 and section 6: at 3,264
constraints the multi-order basis solved in 1.5 min, the thin-plate (r^3)
in 7.9 min and the Gaussian in 2.6 min (195 MHz R10000), and the
multi-order surface was the best of the three.

Here: a noisy ``TorusStack(3)`` (the paper's 'towers', idealized); for
each basis and each target N (surface + exterior + sphere constraints, the
dense solver) the solve time, and at N = 3,264 the quality: Chamfer L1 and
Hausdorff to the analytic shape sampled densely, components, Euler
characteristic (3 stacked tori: 3 components, chi 0 each).  Prints two
tables, writes a solve-time plot (PyVista Chart2D, offscreen) and a 3-panel
picture with the meshes.

    .venv/bin/python benchmarks/paper/fig34_bases.py [--out results/fig34]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "2")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

BASES = ("multiorder", "thinplate", "gaussian")
PAPER_MIN = {"multiorder": 1.5, "thinplate": 7.9, "gaussian": 2.6}
COLOURS = {"multiorder": "#1f4fd1", "thinplate": "#cc3311", "gaussian": "#10a03a"}
SPHERE = 64
RATIO = 0.1


def _surface_count(n_total: int) -> int:
    """Surface constraints giving about n_total with 10% exterior and 64 sphere constraints."""
    return max(10, int(round((n_total - SPHERE) / (1.0 + RATIO))))


def plot(times, path: Path) -> str:
    """Solve time vs N, one line per basis (PyVista Chart2D, offscreen)."""
    from o3drbf.io.files import atomic_path
    from o3drbf.pictures import headless

    headless()
    import pyvista as pv

    chart = pv.Chart2D(x_label="constraints N", y_label="dense solve time (s)")
    chart.title = "Solve time vs N (dense, 2 threads)"
    for basis, pts in times.items():
        xs = [n for n, _ in pts]
        ys = [s for _, s in pts]
        chart.line(xs, ys, color=COLOURS[basis], width=3.0, label=basis)
        chart.scatter(xs, ys, color=COLOURS[basis], size=8, style="o")
    plotter = pv.Plotter(off_screen=True, window_size=[900, 600])
    plotter.set_background("white")
    plotter.add_chart(chart)
    with atomic_path(path) as tmp:
        plotter.screenshot(tmp)
    plotter.close()
    return str(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/fig34", help="output folder (default %(default)s)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 2000, 3264, 5000, 8000], help="target constraint counts N (default %(default)s)")
    ap.add_argument("--quality-n", type=int, default=3264, help="N for the quality table (default %(default)s)")
    ap.add_argument("--points", type=int, default=24000, help="input points sampled on the tori (default %(default)s)")
    ap.add_argument("--noise", type=float, default=0.004, help="noise along the normals, data units (default %(default)s)")
    ap.add_argument("--resolution", type=int, default=96, help="marching-cubes cells along the longest side (default %(default)s)")
    ap.add_argument("--bases", nargs="+", default=list(BASES), choices=BASES, help="bases (default %(default)s)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the sample and the constraints (default %(default)s)")
    args = ap.parse_args(argv)

    import numpy as np

    from o3drbf import reconstruct
    from o3drbf.io.files import write_mesh
    from o3drbf.mesh.metrics import chamfer, mesh_report
    from o3drbf.synthetic.shapes import TorusStack

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    shape = TorusStack(3)
    points, normals = shape.sample(args.points, noise=args.noise, seed=args.seed)
    truth, _ = shape.sample(200_000, noise=0.0, seed=args.seed + 7)
    print(f"TorusStack(3): {len(points):,} points, noise {args.noise:g}; delta 10, tau 0.01, sigma 0.1, lambda 0.001; dense solver")
    common = dict(lambda_surface=1e-3, exterior_ratio=RATIO, sphere_count=SPHERE, solver="dense", seed=args.seed)

    # -- solve time vs N ------------------------------------------------------
    times = {b: [] for b in args.bases}
    for basis in args.bases:  # warm-up (imports, JIT compilation): not timed
        reconstruct(points, normals, basis=basis, surface_count=200, extract=False, **common)
    for n_target in args.sizes:
        for basis in args.bases:
            rec = reconstruct(points, normals, basis=basis, surface_count=_surface_count(n_target), extract=False, **common)
            n = sum(rec.constraints.counts().values())
            times[basis].append((n, rec.stats["solve_seconds"]))
    print()
    print("| target N | " + " | ".join(f"{b}: N, solve (s)" for b in args.bases) + " |")
    print("|---|" + "---|" * len(args.bases))
    for i, n_target in enumerate(args.sizes):
        print(f"| {n_target:,} | " + " | ".join(f"{times[b][i][0]:,}, {times[b][i][1]:.2f}" for b in args.bases) + " |")
    print("paper, 3,264 constraints (R10000): " + ", ".join(f"{b} {PAPER_MIN[b]} min" for b in args.bases))

    # -- quality at N = 3,264 ------------------------------------------------
    rows, panels = [], []
    for basis in args.bases:
        t = time.perf_counter()
        try:
            rec = reconstruct(points, normals, basis=basis, surface_count=_surface_count(args.quality_n), resolution=args.resolution, **common)
        except RuntimeError as exc:
            rows.append((basis, None, None, None, time.perf_counter() - t, str(exc).split(". The fit")[0]))
            panels.append((f"{basis}: no surface", None))
            continue
        seconds = time.perf_counter() - t
        n = sum(rec.constraints.counts().values())
        ch = chamfer(rec.mesh, truth, n_samples=100_000, seed=args.seed)
        rep = mesh_report(rec.mesh)
        write_mesh(out / f"fig34_{basis}.ply", rec.mesh)
        rows.append((basis, n, ch, rep, seconds, rec.stats["solve_seconds"]))
        panels.append((basis, rec.mesh))
    print()
    print(f"| basis (N ~ {args.quality_n:,}) | constraints | Chamfer L1 | Hausdorff | components | Euler characteristic | genus | closed | solve (s) | total (s) | paper solve |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for basis, n, ch, rep, seconds, extra in rows:
        if ch is None:
            print(f"| {basis} | - | - | - | - | - | - | no surface ({extra}) | - | {seconds:.1f} | {PAPER_MIN[basis]} min |")
            continue
        print(
            f"| {basis} | {n:,} | {ch['l1']:.5f} | {ch['hausdorff']:.4f} | {rep['components']} | {rep['euler_characteristic']} | {rep['genus']} | "
            f"{'yes' if rep['closed'] else 'NO'} | {extra:.2f} | {seconds:.1f} | {PAPER_MIN[basis]} min |"
        )
    print("(data units: tori R 0.6, r 0.2; truth: 3 components, Euler characteristic 0, genus 3; Chamfer to 200,000 points on the analytic surface)")

    for name, fn in (("plot", lambda: plot(times, out / "fig34_solve_time.png")),
                     ("picture", lambda: str(__import__("o3drbf.pictures", fromlist=["side_by_side"]).side_by_side(
                         panels, out / "fig34_bases.png", window_size=(1500, 500), points=np.asarray(points)[::10])))):
        try:
            print(f"{name}: {fn()}")
        except Exception as exc:  # pragma: no cover - no OpenGL
            print(f"{name}: skipped ({exc})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
