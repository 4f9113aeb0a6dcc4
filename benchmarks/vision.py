"""Benchmark: visibility and exterior constraints on vision-sized data.

Issue 3 targets (2 cores): visibility and exterior constraints for 1,000,000
points and 16 cameras in under 30 s; Poisson-disc subsampling of 1,000,000
points to 3,000 in under 5 s.  Prints a table; not a unit test.

    .venv/bin/python benchmarks/vision.py [--points 1000000] [--cameras 16]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from o3drbf.cameras.model import Camera, load_range_scans
from o3drbf.prep.sampling import poisson_disc
from o3drbf.synthetic.shapes import TorusStack
from o3drbf.constraints.visibility import exterior_constraints, visibility

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def ring(n: int, distance: float = 3.5, elevation: float = 25.0) -> list[Camera]:
    e = np.radians(elevation)
    return [
        Camera.look_at(distance * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)]), [0, 0, 0], fov=50, width=1280, height=960)
        for a in 2 * np.pi * np.arange(n) / n
    ]


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--cameras", type=int, default=16)
    args = ap.parse_args(argv)
    shape = TorusStack(3, 0.6, 0.2, 0.1)
    points, _ = shape.sample(args.points, seed=0)
    cams = ring(args.cameras)
    rows = []

    vis, dt = timed(lambda: visibility(points, cams))
    rows.append(("visibility", f"{len(points):,} pts x {len(cams)} cams", dt, None, f"{vis.sum():,} sightings"))

    (ext, info), dt = timed(lambda: exterior_constraints(points, cams, offset=0.03, ratio=0.1))
    inside = int((shape.signed_distance(ext) <= 0).sum())
    rows.append(("visibility + exterior, ratio 0.1", f"{len(points):,} pts x {len(cams)} cams", dt, 30.0, f"{len(ext):,} exterior, {inside} inside"))

    def subset_pipeline():
        surface = poisson_disc(points, count=3000, seed=0)
        return exterior_constraints(points[surface], cams, offset=0.03, ratio=0.1, occluder=points)

    (ext, info), dt = timed(subset_pipeline)
    inside = int((shape.signed_distance(ext) <= 0).sum())
    rows.append(("3,000 surface + exterior, occluder all", f"{len(points):,} pts x {len(cams)} cams", dt, 30.0, f"{len(ext):,} exterior, {inside} inside"))

    sel, dt = timed(lambda: poisson_disc(points, count=3000, seed=0))
    rows.append(("poisson_disc to 3,000 (sampling.py)", f"{len(points):,} pts", dt, 5.0, f"{len(sel):,} kept"))

    conf = SHARED / "stanford_bunny" / "data" / "bun.conf"
    if conf.is_file():
        scans, dt_load = timed(lambda: load_range_scans(conf))
        rows.append(("load bun.conf + 10 scans", f"{len(scans.points):,} pts", dt_load, None, ""))
        (ext, info), dt = timed(
            lambda: exterior_constraints(scans.points, scans, offset=0.002, ratio=0.1, point_camera=scans.point_camera)
        )
        rows.append(("bunny exterior (direction sensors)", f"{len(scans.points):,} pts x {len(scans)} scans", dt, None, f"{len(ext):,} exterior"))

    print(f"{'step':40s} {'size':28s} {'time (s)':>9s} {'target':>7s}  result")
    for name, size, dt, target, result in rows:
        tgt = "" if target is None else f"< {target:g}"
        flag = "" if target is None else ("  ok" if dt < target else "  SLOW")
        print(f"{name:40s} {size:28s} {dt:9.2f} {tgt:>7s}  {result}{flag}")


if __name__ == "__main__":
    main()
