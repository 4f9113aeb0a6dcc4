"""The paper's Fig. 7: every point as a constraint vs a Poisson-disc subset.

Dinh, Turk & Slabaugh (2002), Fig. 7: the toy dinosaur's head
reconstructed from all its points and from a Poisson-disc subset; the
fitness error barely changes (0.008 full vs 0.009 subset), so a few thousand
constraints suffice.

Here: a noisy ``TorusStack(3)``; every input point a surface constraint
(``surface_count=None``) vs a Poisson-disc subset, the same exterior ratio
(0.1) and basis (multi-order, delta 10, tau 0.01, lambda 0.001).  The
fitness error is measured from *all* input points to each mesh (as the
paper), next to the Chamfer distance to the analytic surface and the
times.  The full solve is dense by default (8,000 points: about 8,900
constraints); ``--points 20000 --full-solver fast`` runs the paper-sized
case with the fast multipole solver (minutes).

    .venv/bin/python benchmarks/paper/fig7_subset.py [--out results/fig7]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "2")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

PAPER = {"full": 0.008, "subset": 0.009}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/fig7", help="output folder (default %(default)s)")
    ap.add_argument("--points", type=int, default=8000, help="input points, all used by the full fit (default %(default)s)")
    ap.add_argument("--subset", type=int, default=2000, help="Poisson-disc subset size (default %(default)s)")
    ap.add_argument("--noise", type=float, default=0.003, help="noise along the normals, data units (default %(default)s)")
    ap.add_argument("--full-solver", default="dense", choices=("auto", "dense", "iterative", "fast"), help="solver of the full fit (default %(default)s)")
    ap.add_argument("--resolution", type=int, default=96, help="marching-cubes cells along the longest side (default %(default)s)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the sample and the constraints (default %(default)s)")
    args = ap.parse_args(argv)

    import numpy as np

    from o3drbf import reconstruct
    from o3drbf.io.files import write_mesh
    from o3drbf.mesh.metrics import chamfer, fitness_error, mesh_report
    from o3drbf.synthetic.shapes import TorusStack

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    shape = TorusStack(3)
    points, normals = shape.sample(args.points, noise=args.noise, seed=args.seed)
    truth, _ = shape.sample(200_000, noise=0.0, seed=args.seed + 7)
    diag = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    print(f"TorusStack(3): {len(points):,} points, noise {args.noise:g} (bounding-box diagonal {diag:.3f}); multi-order delta 10, tau 0.01, lambda 0.001")

    runs = [("full", None, args.full_solver), ("subset", args.subset, "dense")]
    rows, panels = [], []
    for name, count, solver in runs:
        t = time.perf_counter()
        rec = reconstruct(points, normals, surface_count=count, solver=solver, resolution=args.resolution, seed=args.seed)
        seconds = time.perf_counter() - t
        fe = fitness_error(points, rec.mesh)
        ch = chamfer(rec.mesh, truth, n_samples=100_000, seed=args.seed)
        rep = mesh_report(rec.mesh)
        write_mesh(out / f"fig7_{name}.ply", rec.mesh)
        s = rec.stats
        rows.append((name, s, fe, ch, rep, seconds))
        panels.append((f"{name}: {s['surface_constraints']:,} surface constraints", rec.mesh))

    print()
    print("| fit | surface constraints | exterior + sphere | solver | fitness error mean | RMS | max | mean / bbox diagonal | Chamfer L1 to truth | genus | solve (s) | total (s) | paper fitness error |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, s, fe, ch, rep, seconds in rows:
        print(
            f"| {name} | {s['surface_constraints']:,} | {s['exterior_constraints'] + s['sphere_constraints']:,} | {s['solver']} | "
            f"{fe['mean']:.5f} | {fe['rms']:.5f} | {fe['max']:.4f} | {fe['mean'] / diag:.2e} | {ch['l1']:.5f} | {rep['genus']} | "
            f"{s['solve_seconds']:.2f} | {seconds:.1f} | {PAPER[name]} |"
        )
    print("(fitness error: distance from all input points to the mesh, data units; the paper's values are for the dinosaur head in its own units)")
    try:
        from o3drbf.pictures import side_by_side

        print(f"picture: {side_by_side(panels, out / 'fig7_subset.png', window_size=(1200, 600))}")
    except Exception as exc:  # pragma: no cover - no OpenGL
        print(f"picture: skipped ({exc})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
