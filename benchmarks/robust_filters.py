"""Outlier filters end to end: range scans of a mesh with 2% spurious returns (in the cameras' free space)
plus 2% uniform outliers in the padded box; Chamfer L1 of the default reconstruction on all points,
after statistical removal, after free_space_check and/or isolated_points, and on the clean scan.

Usage: python benchmarks/robust_filters.py [torus-stack|cube] [noise % of diagonal]
"""
import sys, time, json, numpy as np
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parent / "paper"))
from robustness import make_mesh
from o3drbf import reconstruct
from o3drbf.synthetic.scans import range_scans
from o3drbf.constraints.freespace import free_space_check
from o3drbf.prep.outliers import isolated_points, statistical_outliers
from o3drbf.mesh.metrics import chamfer
mesh = make_mesh(sys.argv[1] if len(sys.argv) > 1 else "torus-stack")
v = np.asarray(mesh.vertices); lo, hi = v.min(0), v.max(0); diag = float(np.linalg.norm(hi - lo))
noise_pct = float(sys.argv[2]) if len(sys.argv) > 2 else 0.5
sigma = noise_pct / 100 * diag
clean, cown, cams = range_scans(mesh, n_views=3, noise=sigma, seed=0)
pts, own, _ = range_scans(mesh, n_views=3, noise=sigma, outliers=0.02, seed=0)
rng = np.random.default_rng(17); k = int(round(0.02 / 0.98 * len(pts))); pad = 0.1 * (hi - lo)
pts = np.vstack([pts, rng.uniform(lo - pad, hi + pad, (k, 3))]); own = np.concatenate([own, np.full(k, -1)])
truth = np.zeros(len(pts), bool); truth[len(clean):] = True
KW = dict(surface_count=2000, resolution=64, seed=0)
def run(name, p, o):
    t = time.perf_counter()
    try:
        rec = reconstruct(p, cameras=cams, point_camera=o, **KW)
        m = rec.mesh
        extra = ""
        ch = chamfer(m, mesh, n_samples=30000, seed=0)["l1"]
        print(f"{name}: chamfer {ch:.5f} points {len(p)} ({time.perf_counter()-t:.0f} s) {extra}", flush=True)
    except Exception as e:
        print(f"{name}: failed {e}", flush=True)
print(f"noise {noise_pct}% diag {diag:.3f}; {len(clean)} genuine, {truth.sum()} outliers ({k} uniform)")
if True:  # reference rows
    run("clean (no outliers)", clean, cown)
    run("default (all points)", pts, own)
    kept, _ = statistical_outliers(pts); run("statistical", pts[kept], own[kept])
fs = free_space_check(pts, cams, own, noise=sigma)
iso = isolated_points(pts)
bad = fs.outlier | iso
print(f"free space: caught {fs.outlier[truth].mean():.3f} false {fs.outlier[~truth].mean():.4f}; isolated: caught {iso[truth].mean():.3f} false {iso[~truth].mean():.4f}; both: caught {bad[truth].mean():.3f} false {bad[~truth].mean():.4f}")
run("free space + isolated", pts[~bad], own[~bad])
run("free space only", pts[~fs.outlier], own[~fs.outlier])
run("isolated only", pts[~iso], own[~iso])

