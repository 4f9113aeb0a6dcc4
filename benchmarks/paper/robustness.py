"""Robustness against Open3D Poisson: noisy, sparse, incomplete, misregistered range scans.

Synthetic range scans (:func:`o3drbf.synthetic.scans.range_scans`, 200x150-pixel
pinhole cameras on rings around the object) of six solids the repo builds:

- ``torus-stack``: three stacked tori (genus 3, three components, narrow gaps);
- ``cube``: sharp edges and corners;
- ``bracket``: an L-shaped CAD part with two through-holes (sharp, genus 2);
- ``double-torus``: two fused tori (smooth, genus 2);
- ``thin-plate``: a slab 3 % as thick as it is wide (thin part);
- ``pipe``: an open tube whose wall is 5 % of its diameter (thin walls, genus 1)

(:mod:`o3drbf.synthetic.solids`), with

- noise: Gaussian along the rays, sigma in {0, 0.5, 1} % of the bounding-box
  diagonal;
- outliers: {0, 2, 5} % of the points, half spurious returns in the
  cameras' free space (:func:`range_scans`'s ``outliers``) and half uniform
  in the mesh's box padded by 10 % (camera unknown);
- misregistration: {0, 0.5} % of the diagonal: each scan and its camera moved
  by one rigid error (:func:`o3drbf.synthetic.scans.misregister`, as Berger
  et al.'s ``registration_error``); the misregistered cells are a slice
  (noise 0.5 %, outliers 0 and 2 %), the rest a full grid: 6 meshes x 2
  views x 3 noises x 3 outlier levels + 6 x 2 x 2 = 132 cells;
- views: 3 (120 degrees apart, 20 degrees above the equator: the
  undersides are never seen, so the scans are incomplete) or 6 (those three
  plus three 20 degrees below, 60 degrees between them in azimuth: nearly
  complete, overlapping, non-uniform density).

Every method gets the same points and cameras.  o3drbf runs on the raw
points with its defaults, exactly as ``o3drbf reconstruct scan.ply --cameras
cams.json`` does (:func:`o3drbf.reconstruct` with nothing else: automatic
parameters, outliers="auto", robust fit; no pre-filter).  Poisson runs as the
Open3D tutorial does: statistical outlier removal (20 neighbours, 2 standard
deviations, whatever the outlier level, since a user does not know it),
normals estimated (30 neighbours) and oriented toward the cameras
(:func:`o3drbf.evaluation.compare.open3d_normals`), screened Poisson depth 8;
``poisson-trim`` is the same mesh with the vertices below the 5 % density
quantile removed (Open3D's usual trimming; never closed).

Measures against the true mesh (the whole of it, unseen undersides
included): Chamfer L1 (data units), F-score at 1 % of the diagonal, normal
consistency, watertight (Open3D's ``is_watertight()``:
:func:`o3drbf.mesh.metrics.mesh_report`).  A cell is a win when o3drbf has
a lower Chamfer than both Poisson variants and an F-score no lower than
theirs by more than 0.005 (the strict count, a higher F-score too, is
printed beside it).

Outputs in ``--out``: ``robustness.jsonl`` (one row per run, appended as the
runs finish, so an interrupted study resumes), ``robustness.csv``,
``robustness.json``, ``robustness.md`` (the table and the summary lines) and
``robustness.png`` (Chamfer vs noise per method, one panel per outliers x
views).

    .venv/bin/python benchmarks/paper/robustness.py [--out results/paper] [--quick]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "2")

import argparse  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

NOISES = (0.0, 0.5, 1.0)  # % of the bounding-box diagonal
OUTLIERS = (0.0, 2.0, 5.0)  # % of the points
VIEWS = (3, 6)
MISREGISTRATION = (0.0, 0.5)  # % of the bounding-box diagonal, per scan
#: The misregistered scans are a slice of the grid, not all of it (the study's cost):
#: noise and outliers for MISREGISTRATION > 0.
MISREGISTERED_CELLS = {"noise": (0.5,), "outliers": (0.0, 2.0)}
METHODS = ("o3drbf", "poisson", "poisson-trim")
MESHES = ("torus-stack", "cube", "bracket", "double-torus", "thin-plate", "pipe")
FSCORE_PCT = 1.0  # F-score distance threshold, % of the diagonal
#: F-scores this close count as a tie (both near 1 on complete scans; 30,000
#: samples a side leave about this much sampling noise).
F_TIE = 0.005
TRIM_QUANTILE = 0.05
COLUMNS = ("mesh", "views", "outliers_pct", "noise_pct", "misregistration_pct", "method", "points", "chamfer_l1", "f_score", "normal_consistency", "watertight",
           "delta", "tau", "lambda_surface", "surface_constraints", "noise_estimate", "registered", "seconds", "error")


def make_mesh(name: str):
    """The true mesh (Open3D) of one of :data:`MESHES`."""
    import numpy as np
    import open3d as o3d

    if name == "torus-stack":
        from o3drbf.synthetic.shapes import TorusStack

        mesh = o3d.geometry.TriangleMesh()
        for t in TorusStack().tori:
            part = o3d.geometry.TriangleMesh.create_torus(torus_radius=t.R, tube_radius=t.r, radial_resolution=120, tubular_resolution=60)
            mesh += part.translate(np.asarray(t.center, dtype=float))
        return mesh
    if name == "cube":
        from o3drbf.synthetic.shapes import Cube

        half = Cube().half
        mesh = o3d.geometry.TriangleMesh.create_box(2 * half, 2 * half, 2 * half).translate((-half, -half, -half))
        return mesh.subdivide_midpoint(4)
    from o3drbf.synthetic.solids import SOLIDS, solid_mesh

    if name in SOLIDS:
        return solid_mesh(name)
    raise ValueError(f"unknown mesh {name!r}; valid: {', '.join(MESHES)}")


def scan(mesh, views: int, noise_pct: float, outliers_pct: float, seed: int, misregistration_pct: float = 0.0):
    """(points, point_camera, cameras, diagonal): range scans plus uniform outliers in the padded box."""
    import numpy as np

    from o3drbf.synthetic.scans import misregister, range_scans

    v = np.asarray(mesh.vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    sigma = noise_pct / 100 * diag
    spurious = outliers_pct / 200  # half of the outliers: spurious returns in the free space
    if views == 3:
        pts, owner, cams = range_scans(mesh, n_views=3, elevation=20.0, noise=sigma, outliers=spurious, seed=seed)
    elif views == 6:  # three above, three below, interleaved in azimuth
        pa, oa, ca = range_scans(mesh, n_views=3, elevation=20.0, noise=sigma, outliers=spurious, seed=seed)
        pb, ob, cb = range_scans(mesh, n_views=3, elevation=-20.0, azimuth=60.0, noise=sigma, outliers=spurious, seed=seed + 1)
        pts, owner, cams = np.vstack([pa, pb]), np.concatenate([oa, ob + 3]), ca + cb
    else:
        raise ValueError(f"views must be 3 or 6, got {views}")
    if misregistration_pct:
        pts, cams = misregister(pts, owner, cams, misregistration_pct / 100 * diag, seed=seed + 29)
    n_out = int(round(outliers_pct / 200 / (1 - outliers_pct / 200) * len(pts)))
    if n_out:
        rng = np.random.default_rng(seed + 17)
        pad = 0.1 * (hi - lo)
        pts = np.vstack([pts, rng.uniform(lo - pad, hi + pad, size=(n_out, 3))])
        owner = np.concatenate([owner, np.full(n_out, -1, dtype=owner.dtype)])
    return pts, owner, cams, diag


def measure(mesh, truth, seed: int) -> dict:
    """Chamfer L1, F-score at FSCORE_PCT % of the truth's diagonal, normal consistency, watertight."""
    import numpy as np

    from o3drbf.mesh.metrics import chamfer, f_score, mesh_report, normal_consistency

    if len(mesh.triangles) == 0:
        raise ValueError("empty mesh")
    v = np.asarray(truth.vertices)
    tau = FSCORE_PCT / 100 * float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    rep = mesh_report(mesh)
    return {
        "chamfer_l1": chamfer(mesh, truth, n_samples=30_000, seed=seed)["l1"],
        "f_score": f_score(mesh, truth, tau, n_samples=30_000, seed=seed)["f"],
        "normal_consistency": normal_consistency(mesh, truth, n_samples=30_000, seed=seed),
        "watertight": bool(rep["watertight"]),
    }


def run_case(mesh_name, mesh, views, outliers_pct, noise_pct, misregistration_pct, args) -> list[dict]:
    """Every method on one scan; one row per method."""
    import numpy as np
    import open3d as o3d

    from o3drbf import reconstruct
    from o3drbf.evaluation.compare import open3d_normals
    from o3drbf.prep.outliers import statistical_outliers

    raw, raw_owner, cams, _ = scan(mesh, views, noise_pct, outliers_pct, args.seed, misregistration_pct)
    kept, _ = statistical_outliers(raw)
    pts, owner = raw[kept], raw_owner[kept]  # what Poisson gets
    base = {"mesh": mesh_name, "views": views, "outliers_pct": outliers_pct, "noise_pct": noise_pct,
            "misregistration_pct": misregistration_pct, "points": len(raw)}
    rows = []
    t = time.perf_counter()
    row = dict(base, method="o3drbf")
    try:
        sizes = {k: v for k, v in (("surface_count", args.surface_count), ("resolution", args.resolution)) if v is not None}
        rec = reconstruct(raw, cameras=cams, point_camera=raw_owner, seed=args.seed, **sizes)
        p = rec.report.parameters
        row.update(delta=p["delta"], tau=p["tau"], lambda_surface=p["lambda_surface"], surface_constraints=rec.report.surface_constraints,
                   registered=bool(rec.report.registration and rec.report.registration["applied"]))
        row["seconds"] = time.perf_counter() - t
        row.update(measure(rec.mesh, mesh, args.seed))
    except (RuntimeError, ValueError) as exc:
        row.update(seconds=time.perf_counter() - t, error=str(exc).splitlines()[0][:120])
    rows.append(row)
    t = time.perf_counter()
    try:
        normals = open3d_normals(pts, cams, owner)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        pcd.normals = o3d.utility.Vector3dVector(normals)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            pm, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=args.poisson_depth)
        seconds = time.perf_counter() - t
        dens = np.asarray(dens)
        rows.append(dict(base, method="poisson", seconds=seconds, **measure(pm, mesh, args.seed)))
        trimmed = o3d.geometry.TriangleMesh(pm)
        trimmed.remove_vertices_by_mask(dens < np.quantile(dens, TRIM_QUANTILE))
        rows.append(dict(base, method="poisson-trim", seconds=seconds, **measure(trimmed, mesh, args.seed)))
    except (RuntimeError, ValueError) as exc:
        for method in ("poisson", "poisson-trim"):
            rows.append(dict(base, method=method, seconds=time.perf_counter() - t, error=str(exc).splitlines()[0][:120]))
    return rows


def _key(r) -> tuple:
    return (r["mesh"], int(r["views"]), float(r["outliers_pct"]), float(r["noise_pct"]), float(r.get("misregistration_pct", 0.0)), r["method"])


def _fmt(x, spec):
    return "-" if x is None else format(x, spec)


def _case(c) -> str:
    m, v, o, n, g = c
    return f"{m} {v} views {o:g}% outliers {n:g}% noise" + (f" {g:g}% misregistration" if g else "")


def verdicts(rows) -> dict:
    """Per cell: does o3drbf beat both Poisson variants on Chamfer and F-score, and is it watertight?"""
    by = {_key(r): r for r in rows}
    out = {}
    for case in sorted({k[:5] for k in by}):
        a = by.get(case + ("o3drbf",))
        peers = [by.get(case + (m,)) for m in ("poisson", "poisson-trim")]
        if a is None or any(p is None for p in peers):
            continue
        ok = a.get("chamfer_l1") is not None
        strict = ok and all(p.get("chamfer_l1") is None or (a["chamfer_l1"] < p["chamfer_l1"] and a["f_score"] > p["f_score"]) for p in peers)
        beats = ok and all(p.get("chamfer_l1") is None or (a["chamfer_l1"] < p["chamfer_l1"] and a["f_score"] >= p["f_score"] - F_TIE)
                           for p in peers)
        out[case] = {"beats": bool(beats), "strict": bool(strict), "watertight": bool(ok and a.get("watertight"))}
    return out


def wins(rows) -> list[str]:
    """The targets, checked: wins in >= 90 % of cells, watertight in 100 %."""
    v = verdicts(rows)
    n = len(v)
    lost = [c for c, x in v.items() if not x["beats"]]
    open_ = [c for c, x in v.items() if not x["watertight"]]
    strict = sum(x["strict"] for x in v.values())
    lines = [
        f"o3drbf (defaults, raw points) beats both Poisson variants on Chamfer L1, with an F-score at least theirs "
        f"(within {F_TIE:g}), in {n - len(lost)} of {n} cells" + (f" ({100 * (n - len(lost)) / n:.0f} %; target 90 %)" if n else "")
        + f"; strictly higher F-score too in {strict}",
        f"o3drbf watertight (Open3D's is_watertight) in {n - len(open_)} of {n} cells (target all)",
    ]
    if lost:
        lines.append("Not won: " + "; ".join(_case(c) for c in lost))
    if open_:
        lines.append("Not watertight: " + "; ".join(_case(c) for c in open_))
    pw = sum(bool(r.get("watertight")) for r in rows if r["method"] == "poisson")
    lines.append(f"Poisson (untrimmed) watertight in {pw} of {n} cells")
    return lines


def table(rows) -> str:
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    by = {_key(r): r for r in rows}
    v = verdicts(rows)
    head = ("| mesh | views | outliers % | noise % | misreg. % | "
            + " | ".join(f"{m} Chamfer / F / closed" for m in methods) + " | o3drbf wins |")
    out = [head, "|" + "---|" * (6 + len(methods))]
    for case in sorted({k[:5] for k in by}):
        cells = []
        for m in methods:
            r = by.get(case + (m,))
            if r is None:
                cells.append("")
            elif r.get("chamfer_l1") is None:
                cells.append(f"failed ({r.get('error', '')[:40]})")
            else:
                cells.append(f"{r['chamfer_l1']:.4f} / {r['f_score']:.3f} / {'yes' if r['watertight'] else 'no'}")
        win = "" if case not in v else ("yes" if v[case]["beats"] else "**no**")
        out.append(f"| {case[0]} | {case[1]} | {case[2]:g} | {case[3]:g} | {case[4]:g} | " + " | ".join(cells) + f" | {win} |")
    return "\n".join(out)


def against_poisson(by: dict, case: tuple):
    """(o3drbf's Chamfer / the better Poisson's, o3drbf's F-score - the better Poisson's) for one cell, or None when a run failed."""
    a = by[case + ("o3drbf",)]
    peers = [by[case + (m,)] for m in ("poisson", "poisson-trim") if by[case + (m,)].get("chamfer_l1") is not None]
    if a.get("chamfer_l1") is None or not peers:
        return None
    return a["chamfer_l1"] / min(p["chamfer_l1"] for p in peers), a["f_score"] - max(p["f_score"] for p in peers)


def summary(rows) -> str:
    """One line per (views, misregistration, outliers, noise) over the meshes: wins, Chamfer and F-score ratios, watertight."""
    import numpy as np

    by = {_key(r): r for r in rows}
    v = verdicts(rows)
    groups = sorted({(c[1], c[4], c[2], c[3]) for c in v})
    out = ["| views | misreg. % | outliers % | noise % | o3drbf wins | Chamfer: o3drbf / best Poisson (median, worst) "
           "| F-score: o3drbf - best Poisson (median) | watertight: o3drbf / Poisson |", "|---|---|---|---|---|---|---|---|"]
    for g in groups:
        cells = [c for c in v if (c[1], c[4], c[2], c[3]) == g]
        against = [x for x in (against_poisson(by, c) for c in cells) if x is not None]
        ratios, dfs = [x[0] for x in against], [x[1] for x in against]
        wins_ = sum(v[c]["beats"] for c in cells)
        closed = sum(v[c]["watertight"] for c in cells)
        pclosed = sum(bool(by[c + ("poisson",)].get("watertight")) for c in cells)
        out.append(f"| {g[0]} | {g[1]:g} | {g[2]:g} | {g[3]:g} | {wins_} of {len(cells)} | "
                   + (f"{np.median(ratios):.2f}x, {max(ratios):.2f}x" if ratios else "-") + " | "
                   + (f"{np.median(dfs):+.3f}" if dfs else "-") + f" | {closed} / {pclosed} of {len(cells)} |")
    return "\n".join(out)


def by_solid(rows) -> str:
    """One line per solid: cells won with 3 and with 6 views, and the median Chamfer ratio to the better Poisson (the table in docs/studies.md)."""
    import numpy as np

    by = {_key(r): r for r in rows}
    v = verdicts(rows)
    out = ["| solid | views | cells won | Chamfer ratio (median) |", "|---|---|---|---|"]
    for mesh in [m for m in MESHES if any(c[0] == m for c in v)]:
        won, ratio = [], []
        for views in VIEWS:
            cells = [c for c in v if c[0] == mesh and c[1] == views]
            rs = [x[0] for x in (against_poisson(by, c) for c in cells) if x is not None]
            won.append(f"{sum(v[c]['beats'] for c in cells)} of {len(cells)}")
            ratio.append(f"{np.median(rs):.2f}x" if rs else "-")
        out.append(f"| {mesh} | {' / '.join(str(x) for x in VIEWS)} | {' / '.join(won)} | {' / '.join(ratio)} |")
    return "\n".join(out)


def plot(rows, path: Path) -> str:
    """Chamfer L1 (relative to the mesh's diagonal) vs noise; one panel per (outliers, views), no misregistration.

    Lines: o3drbf and Poisson, median over the meshes; markers: each mesh,
    filled where the mesh is watertight.  Shared y-axis.
    """
    import numpy as np

    from o3drbf.io.files import atomic_path
    from o3drbf.pictures import headless

    headless()
    import pyvista as pv

    colours = {"o3drbf": "#1f4fd1", "poisson": "#cc3311", "poisson-trim": "#ff9966"}
    diag = {}
    for name in {r["mesh"] for r in rows}:
        v = np.asarray(make_mesh(name).vertices)
        diag[name] = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    rows = [r for r in rows if not float(r.get("misregistration_pct", 0.0)) and r.get("chamfer_l1") is not None]
    outs = sorted({float(r["outliers_pct"]) for r in rows})
    views = sorted({int(r["views"]) for r in rows})
    ymax = max(100 * r["chamfer_l1"] / diag[r["mesh"]] for r in rows) * 1.05
    plotter = pv.Plotter(shape=(len(views), len(outs)), off_screen=True, window_size=[520 * len(outs), 420 * len(views)], border=False)
    for i, v in enumerate(views):
        for j, o in enumerate(outs):
            chart = pv.Chart2D(x_label="noise (% of diagonal)", y_label="Chamfer L1 (% of diagonal)")
            chart.title = f"{v} views, {o:g}% outliers"
            chart.y_range = [0.0, ymax]
            for m, colour in colours.items():
                sel = [r for r in rows if r["method"] == m and int(r["views"]) == v and float(r["outliers_pct"]) == o]
                noises = sorted({r["noise_pct"] for r in sel})
                if not noises:
                    continue
                med = [float(np.median([100 * r["chamfer_l1"] / diag[r["mesh"]] for r in sel if r["noise_pct"] == n])) for n in noises]
                chart.line(noises, med, color=colour, width=3.0, label=f"{m} (median of meshes)" if (i, j) == (0, 0) else "")
                closed = [r for r in sel if r["watertight"]]
                if closed:
                    chart.scatter([r["noise_pct"] for r in closed], [100 * r["chamfer_l1"] / diag[r["mesh"]] for r in closed],
                                  color=colour, size=8, style="o", label=f"{m}: watertight" if (i, j) == (0, 0) else "")
                opened = [r for r in sel if not r["watertight"]]
                if opened:
                    chart.scatter([r["noise_pct"] for r in opened], [100 * r["chamfer_l1"] / diag[r["mesh"]] for r in opened],
                                  color=colour, size=8, style="x", label=f"{m}: not watertight" if (i, j) == (0, 0) else "")
            if (i, j) == (0, 0):
                chart.legend_visible = True
            plotter.subplot(i, j)
            plotter.set_background("white")
            plotter.add_chart(chart)
    with atomic_path(path) as tmp:
        plotter.screenshot(tmp)
    plotter.close()
    return str(path)


def write_outputs(rows, out: Path, settings: str) -> None:
    from o3drbf.io.files import atomic_path

    rows = sorted(rows, key=_key)
    with atomic_path(out / "robustness.csv") as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({c: r.get(c) for c in COLUMNS})
    with atomic_path(out / "robustness.json") as tmp, open(tmp, "w") as fh:
        json.dump({"settings": settings, "rows": rows, "wins": wins(rows)}, fh, indent=1)
    text = "\n".join([
        "# Robustness: o3drbf's defaults vs Open3D Poisson on synthetic range scans", "", settings, "",
        "## Summary over the meshes", "", summary(rows), "", *[f"- {line}" for line in wins(rows)], "",
        "## By solid", "", by_solid(rows), "",
        "## Every cell", "",
        f"Cells: Chamfer L1 to the true mesh (data units) / F-score at {FSCORE_PCT:g} % of the diagonal / watertight (Open3D).", "",
        table(rows), "",
    ])
    with atomic_path(out / "robustness.md") as tmp, open(tmp, "w") as fh:
        fh.write(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/paper", help="output folder (default %(default)s)")
    ap.add_argument("--quick", action="store_true", help="one mesh (torus stack), 3 views, outliers 0 and 5 %%, noise 0 and 1 %%")
    ap.add_argument("--meshes", nargs="+", choices=MESHES, default=list(MESHES))
    ap.add_argument("--resolution", type=int, default=None, help="marching-cubes cells (default: reconstruct's)")
    ap.add_argument("--surface-count", type=int, default=None, help="surface constraints (default: reconstruct's)")
    ap.add_argument("--poisson-depth", type=int, default=8, help="Open3D Poisson octree depth (default %(default)s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fresh", action="store_true", help="ignore the rows of an earlier (interrupted) run")
    args = ap.parse_args(argv)
    meshes, views, outs, noises, misregs = args.meshes, VIEWS, OUTLIERS, NOISES, MISREGISTRATION
    if args.quick:
        meshes, views, outs, noises, misregs = ["torus-stack"], (3,), (0.0, 5.0), (0.0, 1.0), (0.0,)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "robustness.jsonl"
    rows = []
    if log_path.exists() and not args.fresh:
        rows = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
        rows = [r for r in rows if r["method"] in METHODS]
    elif log_path.exists():
        log_path.unlink()
    done = {_key(r) for r in rows}
    from o3drbf.options import DEFAULTS

    sizes = (f"{args.surface_count or DEFAULTS['surface_count']} surface constraints, resolution {args.resolution or DEFAULTS['resolution']}"
             + ("" if args.surface_count is None and args.resolution is None else " (fixed by the study, not the defaults)"))
    settings = (f"Range scans 200x150 px; 3 views at elevation +20 deg, 6 views: +-20 deg; outliers half spurious returns, half uniform; "
                f"misregistration: each scan moved rigidly; o3drbf: raw points, cameras, its defaults ({sizes}); "
                f"Poisson: statistical outlier removal, normals oriented to the cameras, depth {args.poisson_depth}, "
                f"trim quantile {TRIM_QUANTILE}; seed {args.seed}.")
    print(settings, flush=True)
    meshes_cache = {}
    for g in misregs:
        for mesh_name in meshes:
            for v in views:
                for o in outs if not g else [x for x in outs if x in MISREGISTERED_CELLS["outliers"]]:
                    for nz in noises if not g else [x for x in noises if x in MISREGISTERED_CELLS["noise"]]:
                        if all((mesh_name, v, o, nz, g, m) in done for m in METHODS):
                            continue
                        if mesh_name not in meshes_cache:
                            meshes_cache[mesh_name] = make_mesh(mesh_name)
                        t = time.perf_counter()
                        new = run_case(mesh_name, meshes_cache[mesh_name], v, o, nz, g, args)
                        with open(log_path, "a") as fh:
                            for r in new:
                                fh.write(json.dumps(r) + "\n")
                        rows = [r for r in rows if _key(r) not in {_key(x) for x in new}] + new
                        print(f"{_case((mesh_name, v, o, nz, g))} ({time.perf_counter() - t:.0f} s): "
                              + ", ".join(f"{r['method']} {_fmt(r.get('chamfer_l1'), '.4f')}{'' if r.get('watertight') else ' (open)'}" for r in new),
                              flush=True)
                        write_outputs(rows, out, settings)
    rows = [r for r in rows if r["mesh"] in meshes]
    write_outputs(rows, out, settings)
    print()
    print(table(sorted(rows, key=_key)))
    for line in wins(rows):
        print(f"- {line}")
    try:
        print(f"plot: {plot(rows, out / 'robustness.png')}")
    except Exception as exc:  # pragma: no cover - no OpenGL
        print(f"plot: skipped ({exc})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
