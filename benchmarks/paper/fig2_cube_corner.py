"""The paper's Fig. 2: a cube corner range image reconstructed with four smoothing values.

Dinh, Turk & Slabaugh (2002), Fig. 2: a range image of the corner of a cube,
reconstructed with the multi-order basis and lambda (surface smoothing)
0, 0.001, 0.03 and 2.0: lambda 0 interpolates and keeps the sharp edges,
larger lambda rounds them, the largest gives a blob.

Here: ``o3drbf.synthetic.shapes.cube_corner`` (points and normals on the three faces
x, y, z = +0.5 a camera at (1, 1, 1) sees), the paper's delta 10 and tau
0.01.  For each lambda: fitness error (input points to the mesh), average
curvature, triangles and whether the mesh is closed; a 4-panel PNG and the
meshes.  A lambda whose fit has no zero crossing (smoothing swamps the
data) is reported as such, with an empty panel.

    .venv/bin/python benchmarks/paper/fig2_cube_corner.py [--out results/fig2]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "2")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

LAMBDAS = (0.0, 0.001, 0.03, 2.0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/fig2", help="output folder (default %(default)s)")
    ap.add_argument("--points", type=int, default=2000, help="range-image points (default %(default)s)")
    ap.add_argument("--noise", type=float, default=0.0, help="noise along the normals, data units (default %(default)s)")
    ap.add_argument("--lambdas", type=float, nargs="+", default=list(LAMBDAS), help="surface smoothing values (default %(default)s)")
    ap.add_argument("--resolution", type=int, default=96, help="marching-cubes cells along the longest side (default %(default)s)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the sample and the constraints (default %(default)s)")
    args = ap.parse_args(argv)

    import numpy as np

    from o3drbf import reconstruct
    from o3drbf.io.files import write_mesh
    from o3drbf.rbf.kernels import MultiOrder
    from o3drbf.mesh.metrics import average_curvature, fitness_error, mesh_report
    from o3drbf.synthetic.shapes import cube_corner

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    points, normals = cube_corner(args.points, noise=args.noise, seed=args.seed)
    phi0 = MultiOrder(10.0, 0.01).value_at_zero
    print(f"cube corner range image: {len(points):,} points, noise {args.noise:g}; multi-order delta 10, tau 0.01 (phi(0) = {phi0:.4g})")

    rows, panels = [], []
    for lam in args.lambdas:
        t = time.perf_counter()
        try:
            rec = reconstruct(points, normals, delta=10.0, tau=0.01, lambda_surface=lam, resolution=args.resolution, seed=args.seed)
        except RuntimeError as exc:
            seconds = time.perf_counter() - t
            msg = str(exc).split(". The fit")[0]
            rows.append((lam, None, None, None, None, seconds, msg))
            panels.append((f"lambda {lam:g}: no surface", None))
            continue
        seconds = time.perf_counter() - t
        fe = fitness_error(points, rec.mesh)
        curv = average_curvature(rec.mesh)
        rep = mesh_report(rec.mesh)
        write_mesh(out / f"fig2_lambda_{lam:g}.ply", rec.mesh)
        rows.append((lam, fe, curv, rep["triangles"], rep["closed"], seconds, ""))
        panels.append((f"lambda {lam:g}", rec.mesh))

    print()
    print("| lambda | fitness error mean | fitness error RMS | fitness error max | average curvature | triangles | closed | time (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for lam, fe, curv, tris, closed, seconds, msg in rows:
        if fe is None:
            print(f"| {lam:g} | - | - | - | - | 0 | no surface ({msg}) | {seconds:.1f} |")
        else:
            print(f"| {lam:g} | {fe['mean']:.5f} | {fe['rms']:.5f} | {fe['max']:.5f} | {curv:.3f} | {tris:,} | {'yes' if closed else 'NO'} | {seconds:.1f} |")
    print("(data units: the cube has side 1; fitness error = distance from the input points to the mesh)")

    try:
        from o3drbf.pictures import side_by_side

        png = side_by_side(panels, out / "fig2_cube_corner.png", window_size=(1800, 500), points=np.asarray(points), view=(1.0, 1.0, 1.0), viewup=(0.0, 0.0, 1.0))
        picture = str(png)
    except Exception as exc:  # pragma: no cover - no OpenGL
        picture = f"skipped ({exc})"
    print(f"picture: {picture}\nmeshes: {out}/fig2_lambda_*.ply")
    return 0


if __name__ == "__main__":
    sys.exit(main())
