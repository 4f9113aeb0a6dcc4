"""``o3drbf compare``: its arguments (generated from the options' tables) and the command."""

from __future__ import annotations

import argparse
from pathlib import Path

from o3drbf.cli.arguments import add_options, non_negative_int, options_from_args, validated

__all__ = ["add_compare_arguments", "main_compare"]


def add_compare_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``compare`` arguments to a (sub)parser; returns it."""
    parser.description = parser.description or (
        "Run several reconstruction methods on the same points and compare them: "
        "a table (markdown, CSV, JSON) of time, memory, triangles, watertightness and "
        "quality measures, and a picture: one row per method seen from four sides, coloured by distance to the truth."
    )
    parser.add_argument(
        "input",
        help="point cloud file (normals used when present), or a file that holds points and cameras "
        "(Stanford .conf, COLMAP text folder, Bundler bundle.out, o3drbf scan .json)",
    )
    parser.add_argument("--cameras", metavar="FILE", default=None,
                        help="cameras that saw the points: Open3D normals are oriented toward them, o3drbf uses them for exterior constraints")
    parser.add_argument("--truth", metavar="MESH", default=None,
                        help="ground-truth mesh: adds Chamfer, Hausdorff, F-score (1%% of its diagonal) and normal consistency")
    parser.add_argument("-o", "--out", metavar="OUT_DIR", default="comparison",
                        help="output folder for comparison.{md,csv,json,png} (created; default %(default)s)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="sampling seed (default %(default)s)")
    add_options(parser, "compare")
    return parser


def _read_truth(path):
    import open3d as o3d

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"cannot read truth mesh {p}: file not found")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(p))
    if len(mesh.triangles) == 0:
        raise ValueError(f"cannot read truth mesh {p}: no triangles (not a mesh file Open3D reads: PLY, OBJ, STL, OFF, glTF)")
    return mesh


def main_compare(args: argparse.Namespace) -> int:
    """``o3drbf compare``: run, write the tables and the picture, print the table.

    Raises ``ValueError`` / ``FileNotFoundError`` on bad input (the CLI turns
    them into ``o3drbf: error: ...`` and exit status 2).
    """
    from o3drbf.evaluation.compare import UP_AXES, compare_with_meshes
    from o3drbf.evaluation.tables import markdown_table, picture, write_tables
    from o3drbf.io.files import check_outputs
    from o3drbf.pointset import read_input

    options = validated(options_from_args(args, "compare"), "compare")
    truth = _read_truth(args.truth) if args.truth else None
    data = read_input(args.input, cameras=args.cameras)
    points = data.points
    out = Path(args.out or "comparison")
    if out.exists() and not out.is_dir():
        raise ValueError(f"-o {out} is a file; give a folder for comparison.md/.csv/.json/.png")
    inputs = [args.input, args.truth, args.cameras]
    outputs = [out / f"comparison.{ext}" for ext in ("md", "csv", "json", "png")]
    if out.is_dir():
        check_outputs(outputs, inputs)  # before any method runs: never an input, never read-only
    out.mkdir(parents=True, exist_ok=True)
    check_outputs(outputs, inputs)
    rows, meshes = compare_with_meshes(points, data.normals, data.cameras, truth, options=options, seed=args.seed, point_camera=data.point_camera)
    reference = Path(args.truth).name if args.truth else None
    paths = write_tables(rows, out, points=len(points), reference=reference)
    png = picture(meshes, out / "comparison.png", points=points, rows=rows, truth=truth, reference=reference, viewup=UP_AXES[options.up])
    print(f"o3drbf compare: {args.input} ({len(points):,} points) -> {out}/")
    print(markdown_table(rows, len(points), reference), end="")
    for row in rows:
        if row["error"]:
            print(f"  {row['method']} failed: {row['error']}")
    print("  wrote " + ", ".join(str(p) for p in (*paths.values(), png)))
    return 0
