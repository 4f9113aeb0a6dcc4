"""Time the command line the way a user runs it, against Open3D Poisson and ferreus_rbf.

Every tool runs in its own process under ``/usr/bin/time -v`` (wall seconds and peak
resident memory), on inputs generated here:

- ``torus-15k``: a torus sample with normals (``o3drbf.synthetic``), written by
  ``o3drbf.io.files.write_points``; ``o3drbf reconstruct IN.ply -o OUT.ply``, no options;
- ``scan-3views``: three synthetic range scans of the Stanford bunny (or of a torus
  mesh when the bunny is absent) with their cameras, as an o3drbf scan ``.json``;
- ``torus-90k --surface-count 30000`` and ``torus-300k --surface-count 100000``
  (skipped with ``--quick``).

Peers on the same points: Open3D Poisson (depth 8 and 9) after Open3D normal
estimation and consistent orientation (what a user without normals runs), and
ferreus_rbf when importable (linear kernel, the points plus two off-surface points per
point along the normals, as many points as o3drbf's surface constraints; meshed by its
marching tetrahedra at the same 128-cell resolution).

Usage::

    python benchmarks/user_path.py [--quick] [--out DIR]

Prints a markdown table (seconds, GB, ratios to o3drbf) and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BUNNY = ROOT.parent / "shared" / "data" / "stanford_bunny" / "reconstruction" / "bun_zipper.ply"


def o3drbf_command() -> list[str]:
    """The installed console script next to this Python, else ``python -m o3drbf``."""
    exe = Path(sys.executable).with_name("o3drbf")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "o3drbf"]


def timed(cmd: list[str], env=None) -> dict:
    """Run ``cmd`` under /usr/bin/time -v: wall seconds, peak RSS (GB), return code, output tail."""
    t0 = time.perf_counter()
    timer = ["/usr/bin/time", "-v"] if Path("/usr/bin/time").exists() else []
    proc = subprocess.run(timer + cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr)
    rss = int(m.group(1)) / 2**20 if m else float("nan")
    return {"seconds": wall, "gb": rss, "rc": proc.returncode, "out": proc.stdout[-2000:], "err": proc.stderr[-3000:]}


# --------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------
def make_inputs(folder: Path, quick: bool) -> list[dict]:
    from o3drbf.io.files import write_points
    from o3drbf.synthetic.shapes import Torus

    cases = []
    p, n = Torus().sample(15000, seed=0)
    write_points(folder / "torus15k.ply", p, n)
    cases.append({"name": "torus 15k pts, defaults", "input": folder / "torus15k.ply", "points": folder / "torus15k.ply",
                  "args": [], "count": 3000})
    scan = make_scan(folder)
    cases.append({"name": "3-view range scan (json), defaults", "input": scan[0], "points": scan[1], "args": [], "count": 3000})
    if not quick:
        for total, count in ((90000, 30000), (300000, 100000)):
            p, n = Torus().sample(total, seed=1)
            path = folder / f"torus{total // 1000}k.ply"
            write_points(path, p, n)
            cases.append({"name": f"torus {total // 1000}k pts, --surface-count {count}", "input": path, "points": path,
                          "args": ["--surface-count", str(count)], "count": count})
    return cases


def make_scan(folder: Path):
    """Three range scans 120 degrees apart with cameras: (scan .json, points .ply with estimated normals)."""
    import open3d as o3d

    from o3drbf.io.files import write_points
    from o3drbf.synthetic.scans import range_scans, write_scan_json

    if BUNNY.exists():
        mesh = o3d.io.read_triangle_mesh(str(BUNNY))
        up = (0.0, 1.0, 0.0)
    else:
        mesh = o3d.geometry.TriangleMesh.create_torus(torus_radius=0.7, tube_radius=0.25, radial_resolution=60,
                                                      tubular_resolution=30)
        up = (0.0, 0.0, 1.0)
    points, owner, cams = range_scans(mesh, n_views=3, elevation=20.0, up=up, width=200, height=150, seed=0)
    path = write_scan_json(folder / "scan3.json", points, cams, point_camera=owner)
    # Peers get the same points with Open3D normals oriented toward the owning camera.
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
    nrm = np.asarray(pcd.normals).copy()
    centres = np.array([c.center for c in cams])[np.maximum(owner, 0)]
    flip = np.einsum("ij,ij->i", nrm, centres - points) < 0
    nrm[flip] *= -1
    ply = folder / "scan3_points.ply"
    write_points(ply, points, nrm)
    return Path(path), ply


# --------------------------------------------------------------------------------------
# peers (each run as a separate process by this same file)
# --------------------------------------------------------------------------------------
def peer_poisson(points: str, depth: int, out: str) -> None:
    import open3d as o3d

    pcd = o3d.io.read_point_cloud(points)
    pcd.normals = o3d.utility.Vector3dVector(np.zeros((0, 3)))  # estimate them, as a user without normals would
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
    pcd.orient_normals_consistent_tangent_plane(15)
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    o3d.io.write_triangle_mesh(out, mesh)
    print(json.dumps({"vertices": len(mesh.vertices), "triangles": len(mesh.triangles)}))


def peer_ferreus(points: str, count: int, out: str) -> None:
    import ferreus_rbf as fr
    import open3d as o3d
    from ferreus_rbf.interpolant_config import InterpolantSettings, RBFKernelType

    pcd = o3d.io.read_point_cloud(points)
    p, n = np.asarray(pcd.points), np.asarray(pcd.normals)
    if len(p) > count:
        idx = np.random.default_rng(0).choice(len(p), count, replace=False)
        p, n = p[idx], n[idx]
    lo, hi = p.min(axis=0), p.max(axis=0)
    off = 0.01 * float(np.linalg.norm(hi - lo))
    x = np.vstack([p, p + off * n, p - off * n])  # outward normals: f = signed distance
    y = np.r_[np.zeros(len(p)), np.full(len(p), off), np.full(len(p), -off)]
    rbf = fr.RBFInterpolator(x, y, InterpolantSettings(RBFKernelType.Linear))
    pad = 0.05 * (hi - lo)
    extents = np.r_[lo - pad, hi + pad]
    mesh = rbf.build_isosurface(extents, float((hi - lo + 2 * pad).max()) / 128, 0.0)
    print(json.dumps({"vertices": len(mesh.vertices), "triangles": len(mesh.facets)}))


def have_ferreus() -> bool:
    try:
        import ferreus_rbf  # noqa: F401
    except ImportError:
        return False
    return True


# --------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------
def summary_field(text: str, key: str) -> str:
    m = re.search(rf"^\s*{key}\s+(.*)$", text, re.M)
    return m.group(1).strip() if m else ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the two small cases only (~2 minutes)")
    ap.add_argument("--out", type=Path, default=None, help="folder for inputs and meshes (default: a temporary one)")
    ap.add_argument("--no-peers", action="store_true", help="o3drbf only")
    ap.add_argument("--peer", nargs=4, metavar=("KIND", "POINTS", "ARG", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.peer:
        kind, points, arg, out = args.peer
        if kind == "poisson":
            peer_poisson(points, int(arg), out)
        else:
            peer_ferreus(points, int(arg), out)
        return 0
    folder = args.out or Path(tempfile.mkdtemp(prefix="o3drbf-user-path-"))
    folder.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    load0 = os.getloadavg()
    cases = make_inputs(folder, args.quick)
    peers = [] if args.no_peers else [("Open3D Poisson d8 (+normals)", "poisson", 8), ("Open3D Poisson d9 (+normals)", "poisson", 9)]
    if not args.no_peers and have_ferreus():
        peers.append(("ferreus_rbf linear (+marching tets)", "ferreus", None))
    rows = []
    for case in cases:
        out = folder / (Path(case["input"]).stem + "_o3drbf.ply")
        r = timed(o3drbf_command() + ["reconstruct", str(case["input"]), "-o", str(out)] + case["args"], env=env)
        if r["rc"] != 0:
            print(r["err"], file=sys.stderr)
        detail = "; ".join(x for x in (summary_field(r["out"], "solve"), summary_field(r["out"], "mesh")) if x)
        rows.append((case["name"], "o3drbf reconstruct", r, None, detail))
        base = r["seconds"]
        for label, kind, arg in peers:
            pout = folder / (Path(case["input"]).stem + f"_{kind}{arg or ''}.ply")
            a = str(arg if arg is not None else case["count"])
            pr = timed([sys.executable, str(Path(__file__).resolve()), "--peer", kind, str(case["points"]), a, str(pout)], env=env)
            if pr["rc"] != 0:
                print(pr["err"], file=sys.stderr)
            info = pr["out"].strip().splitlines()[-1] if pr["rc"] == 0 and pr["out"].strip() else "failed"
            rows.append((case["name"], label, pr, base, info))
    load1 = os.getloadavg()
    print(f"\nload average at start {load0[0]:.2f} / {load0[1]:.2f} / {load0[2]:.2f}, "
          f"at end {load1[0]:.2f} / {load1[1]:.2f} / {load1[2]:.2f}; {os.cpu_count()} cores; inputs in {folder}\n")
    print("| case | tool | seconds | peak GB | time / o3drbf | notes |")
    print("|---|---|---|---|---|---|")
    for name, tool, r, base, info in rows:
        ratio = "1" if base is None else f"{r['seconds'] / base:.2f}"
        status = "" if r["rc"] == 0 else f" (exit {r['rc']})"
        print(f"| {name} | {tool}{status} | {r['seconds']:.1f} | {r['gb']:.2f} | {ratio} | {info} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
