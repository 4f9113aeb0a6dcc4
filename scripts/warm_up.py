"""Compile o3drbf's Numba kernels once, into their on-disk cache, and its modules into bytecode, so a user's
first run does not pay for it.

The bytecode is what a wheel's installation writes; an editable install (``make``'s) leaves it to the
first import, which cannot write it where ``PYTHONDONTWRITEBYTECODE`` is set, so every run would compile
o3drbf's sources again.  Run by ``scripts/setup.sh`` after installing (and again whenever a source file changed):
small reconstructions on the command line's path (with its closing summary): points with normals (with the dense
solver, then the fast one, which larger clouds get) and a range scan with cameras, written into a temporary folder
and thrown away.  ``benchmarks/user_path.py`` runs it too before timing anything.

    python scripts/warm_up.py
"""

from __future__ import annotations

import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path


def compile_bytecode() -> bool:
    """Byte-compile the o3drbf package (and its viewers) in place; True when every module compiled."""
    import compileall

    root = Path(__file__).resolve().parent.parent
    ok = True
    for folder in ("o3drbf", "viewers"):
        if (root / folder).is_dir():
            ok &= bool(compileall.compile_dir(root / folder, quiet=1))
    return ok


def main() -> int:
    t0 = time.perf_counter()
    if not compile_bytecode():
        print("warm-up: some o3drbf modules did not byte-compile (see above)", file=sys.stderr)
        return 1
    from o3drbf.cli import main as cli
    from o3drbf.io.files import write_points
    from o3drbf.synthetic.scans import range_scans, write_scan_json
    from o3drbf.synthetic.shapes import Torus

    import open3d as o3d

    with tempfile.TemporaryDirectory(prefix="o3drbf-warm-up-") as tmp:
        folder = Path(tmp)
        points, normals = Torus().sample(1500, seed=0)
        cloud = write_points(folder / "torus.ply", points, normals)
        mesh = o3d.geometry.TriangleMesh.create_torus(torus_radius=0.7, tube_radius=0.25, radial_resolution=40, tubular_resolution=20)
        scan_points, owner, cameras = range_scans(mesh, n_views=3, width=80, height=60, seed=0)
        scan = write_scan_json(folder / "scan.json", scan_points, cameras, point_camera=owner)
        for source, extra in ((cloud, []), (cloud, ["--solver", "fast"]), (scan, [])):
            # Not -q: the closing summary's mesh checks (self-intersections) have kernels of their own.
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                code = cli(["reconstruct", str(source), "-o", str(folder / "mesh.ply")] + extra)
            if code:
                print(f"warm-up: reconstruct {source.name} {' '.join(extra)} exited {code}", file=sys.stderr)
                return code
        # Dense solves from 2,000 constraints factor a float32 copy (o3drbf.solvers.dense), filled with the
        # double matrix in one pass (lower_pair), or copied from it (lower_single): their kernels too.
        import numpy as np

        from o3drbf.rbf.compiled import lower_pair, lower_single
        from o3drbf.rbf.kernels import MultiOrder

        lower_single(np.asfortranarray(np.eye(8)))
        lower_pair(MultiOrder(10, 0.01), np.eye(3), np.ones(3))
        # Poisson-disc subsampling (clouds with more points than surface constraints): its dart throwing.
        from o3drbf.prep.darts import greedy_darts

        greedy_darts(np.eye(3), np.arange(3), 0.5)
        # The fast solve's local step (from 3,000 constraints): products with its single-precision matrix.
        import scipy.sparse as sp

        from o3drbf.solvers.fast.neighbours import csr_matvec

        csr_matvec(sp.identity(3, dtype=np.float32, format="csr"), np.ones(3))
        # A fast solve beyond the exact preconditioner's size (3,000 centres), so that its relaxed products take
        # the looser grids: their near fields restricted from the product's, their single-precision potentials.
        from o3drbf.solvers import solve

        surface = Torus().sample(3200, seed=1)[0]
        centres = np.vstack([surface, 1.3 * surface[:400]])
        values = np.r_[np.zeros(len(surface)), -np.ones(400)]
        solve(MultiOrder(10, 0.01), centres, values, np.full(len(centres), 1e-4), method="fast")
    print(f"warm-up: compiled kernels cached in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
