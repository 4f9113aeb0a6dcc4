"""The demo behind `make demo`: a built-in sample reconstructed by o3drbf
(multi-order basis) and by Open3D Poisson, two meshes and a picture.

    python samples/demo.py --out out
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import o3drbf  # noqa: E402
from o3drbf.io import files as io  # noqa: E402
from o3drbf.cli.commands import summary  # noqa: E402
from o3drbf.mesh.metrics import chamfer, mesh_report  # noqa: E402
from o3drbf.evaluation.peers import poisson  # noqa: E402
from o3drbf.pictures import side_by_side  # noqa: E402
from o3drbf.synthetic.shapes import TorusStack  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("out"))
    parser.add_argument("--resolution", type=int, default=128)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    shape = TorusStack(3)
    points, normals = shape.sample(12000, noise=0.006, seed=2)
    sample = io.write_points(args.out / "tori_stack.ply", points, normals)
    print(f"sample: {sample} ({len(points):,} noisy points on three stacked tori, with normals)")

    t0 = time.perf_counter()
    result = o3drbf.reconstruct(points, normals, resolution=args.resolution, auto=True, progress=True)
    rbf_path = io.write_mesh(args.out / "tori_stack_o3drbf.ply", result.mesh)
    print(summary(result, points, sample, rbf_path, seconds=time.perf_counter() - t0))

    t0 = time.perf_counter()
    peer = poisson(points, normals, depth=8)
    t_peer = time.perf_counter() - t0
    peer_path = io.write_mesh(args.out / "tori_stack_poisson.ply", peer)

    truth = TorusStack(3)
    rows = []
    for name, mesh, seconds in (("o3drbf multi-order", result.mesh, result.stats["total_seconds"]), ("Open3D Poisson depth 8", peer, t_peer)):
        rep = mesh_report(mesh)
        # distance to the truth: the analytic signed distance at mesh vertices, and Chamfer to a dense truth sample
        import numpy as np

        d = np.abs(truth.signed_distance(np.asarray(mesh.vertices)))
        dense, _ = truth.sample(100_000, seed=99)
        ch = chamfer(mesh, dense)
        rows.append((name, seconds, rep["triangles"], rep["watertight"], rep["euler_characteristic"], d.mean(), ch["l1"]))
    print("\n| method | seconds | triangles | watertight | Euler char. (truth 0) | mean |sdf| at vertices | Chamfer L1 to truth |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]:.1f} | {r[2]:,} | {'yes' if r[3] else 'no'} | {r[4]} | {r[5]:.4f} | {r[6]:.4f} |")

    picture = side_by_side(
        [(f"o3drbf multi-order ({len(result.mesh.triangles):,} triangles)", result.mesh), (f"Open3D Poisson depth 8 ({len(peer.triangles):,} triangles)", peer)],
        args.out / "demo.png",
    )
    print(f"\nwrote {rbf_path}, {peer_path} and {picture}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
