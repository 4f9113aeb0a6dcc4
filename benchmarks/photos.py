"""Benchmark: the photographs-to-coloured-mesh pipeline on the Middlebury temple.

Issue 7 target (2 cores): the 16-image templeSparseRing at 128 voxels along
the box's longest side (the README's box: 128 x 82 x 61 voxels) in under
120 s, with every image's silhouette matched at IoU > 0.9.  Prints a table
of stage times and counts, the IoU per image, and the total against the
target; optionally writes the model and the Fig. 9 picture.  Not a unit test.

    .venv/bin/python benchmarks/photos.py [--voxels 128] [--out DIR] [--picture]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from o3drbf.photo.pipeline import picture, run_photos

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
TEMPLE = SHARED / "middlebury_templeSparseRing"
TARGET_SECONDS = 120.0
TARGET_IOU = 0.9


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(TEMPLE), help="image folder with its *_par.txt (default: the shared temple)")
    ap.add_argument("--voxels", type=int, default=128)
    ap.add_argument("--photo-consistency", type=float, default=None, help="override the carving default (0: visual hull only)")
    ap.add_argument("--bounds", default="auto", choices=["auto", "silhouettes"])
    ap.add_argument("--out", default=None, help="folder for model.ply (and fig9.png with --picture)")
    ap.add_argument("--picture", action="store_true")
    args = ap.parse_args(argv)
    folder = Path(args.data)
    if not folder.is_dir():
        print(f"skipped: {folder} not found (needs ../shared/data)")
        return 0
    par = sorted(folder.glob("*_par.txt"))
    options = {}
    if args.photo_consistency is not None:
        options["photo_consistency"] = args.photo_consistency or None
    t0 = time.perf_counter()
    r = run_photos(folder, par[0] if par else None, voxels=args.voxels, bounds=args.bounds, **options)
    total = time.perf_counter() - t0
    s, c, rec = r.stats, r.carve.stats, r.reconstruction.stats
    rows = [
        ("read images", s["read_seconds"], f"{len(r.cameras)} images {r.cameras[0].width}x{r.cameras[0].height}"),
        ("silhouettes", s["segment_seconds"], f"foreground {100 * np.mean(c['silhouette_fraction']):.1f}% of pixels"),
        ("bounds", c["bounds_seconds"], f"from {s['bounds_source']}; grid {'x'.join(map(str, c['grid']))} = {c['voxels']:,} voxels"),
        ("visual hull", c["hull_seconds"], f"{c['hull_voxels']:,} kept, {c['silhouette_carved']:,} carved"),
        ("photo-consistency", c["photo_seconds"], f"{c['photo_carved']:,} carved {c['photo_carved_per_sweep']}, {c['photo_protected']:,} kept on the outline"),
        ("shell + colours", c["shell_seconds"], f"{c['shell_voxels']:,} shell voxels, {c['shell_views_mean']:.1f} views each, {c['shell_unseen']:,} unseen"),
        ("constraints", rec["constraints_seconds"], f"{rec['surface_constraints']:,} surface, {rec['exterior_constraints']:,} exterior, {rec['sphere_constraints']:,} sphere"),
        ("solve", rec["solve_seconds"], f"{rec['solver']}, residual {rec['residual']:.1e}"),
        ("marching cubes", rec["extract_seconds"], f"{s['triangles']:,} triangles, watertight {'yes' if s['watertight'] else 'NO'}, {s['components']} component(s)"),
        ("colour", s["color_seconds"], "from the photographs"),
        ("silhouette IoU", s["iou_seconds"], f"min {r.iou.min():.3f}, mean {r.iou.mean():.3f} (raw segmentation: min {r.iou_raw.min():.3f}, mean {r.iou_raw.mean():.3f})"),
    ]
    print(f"o3drbf photos benchmark: {folder.name}, {args.voxels} voxels along the longest side\n")
    print(f"| {'stage':<18} | {'seconds':>8} | result")
    print(f"|{'-' * 20}|{'-' * 10}|{'-' * 60}")
    for name, sec, what in rows:
        print(f"| {name:<18} | {sec:8.2f} | {what}")
    print()
    print("| image | IoU | IoU (raw segmentation)")
    print("|-------|-----|-----------------------")
    for cam, a, b in zip(r.cameras, r.iou, r.iou_raw):
        print(f"| {cam.name} | {a:.3f} | {b:.3f}")
    ok_time = total < TARGET_SECONDS
    ok_iou = bool((r.iou > TARGET_IOU).all())
    print()
    print(f"total {total:.1f} s (target < {TARGET_SECONDS:.0f} s: {'met' if ok_time else 'MISSED'}); "
          f"IoU > {TARGET_IOU} in every image: {'yes' if ok_iou else 'NO'}")
    if args.out:
        from o3drbf.io.files import write_mesh

        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_mesh(out / "model.ply", r.mesh)
        print(f"wrote {out / 'model.ply'}")
        if args.picture:
            picture(r.mesh, r.cameras[0], r.images[0], out / "fig9.png")
            print(f"wrote {out / 'fig9.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
