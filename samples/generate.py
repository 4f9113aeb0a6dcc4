"""Write the built-in sample point clouds (all synthetic, made here).

    python samples/generate.py OUT_DIR

torus.ply          noisy torus (8,000 points, sigma 0.5% of the size), with normals
tori_stack.ply     three stacked tori (the paper's 'towers', idealized), with normals
cube_corner.ply    a range image of a cube corner (the paper's Fig. 2), with normals
sphere.xyz         sphere points without normals (normals get estimated)
scan.ply           three synthetic range scans of a torus (noise along the rays, 2 % outliers), no normals
points.ply         the same points (for --cameras)
cams.json          the three scanners' cameras
scan.json          points and cameras in one o3drbf scan file
reference.ply      the true torus mesh (for compare --truth)

The README's command-line examples use these files:

    make samples && .venv/bin/o3drbf reconstruct out/samples/points.ply --cameras out/samples/cams.json -o out/scan_mesh.ply
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from o3drbf.io.files import write_points  # noqa: E402
from o3drbf.synthetic.shapes import Sphere, Torus, TorusStack, cube_corner  # noqa: E402

SAMPLES = {
    "torus.ply": lambda: Torus(0.6, 0.25).sample(8000, noise=0.009, seed=1),
    "tori_stack.ply": lambda: TorusStack(3).sample(12000, noise=0.006, seed=2),
    "cube_corner.ply": lambda: cube_corner(4000, noise=0.002, seed=3),
    "sphere.xyz": lambda: Sphere(1.0).sample(3000, noise=0.005, seed=4),
    # the upper half of a sphere only: the fit closes the rest, --trim removes it (README "Confidence and trimming")
    "half_sphere.ply": lambda: upper_half(*Sphere(1.0).sample(3000, noise=0.002, seed=6)),
}


def upper_half(points, normals):
    """The points (and normals) with z > 0."""
    keep = points[:, 2] > 0
    return points[keep], normals[keep]


def generate(out: Path) -> dict[str, Path]:
    import open3d as o3d

    from o3drbf.cameras.model import save_cameras_json
    from o3drbf.io.files import write_mesh
    from o3drbf.synthetic.scans import range_scans, write_scan_json

    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for name, make in SAMPLES.items():
        pts, nrm = make()
        path = out / name
        write_points(path, pts, None if name.endswith(".xyz") else nrm)
        written[name] = path
    torus = o3d.geometry.TriangleMesh.create_torus(0.6, 0.25, 60, 30)
    torus.compute_vertex_normals()
    pts, owner, cams = range_scans(torus, n_views=3, elevation=20.0, width=160, height=120, noise=0.003, outliers=0.02, seed=5)
    for name in ("scan.ply", "points.ply"):
        written[name] = write_points(out / name, pts)
    written["cams.json"] = save_cameras_json(out / "cams.json", cams)
    written["scan.json"] = write_scan_json(out / "scan.json", pts, cams, owner)
    written["reference.ply"] = write_mesh(out / "reference.ply", torus)
    return written


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", nargs="?", default="out/samples", type=Path)
    for name, path in generate(parser.parse_args().out).items():
        print(path)
