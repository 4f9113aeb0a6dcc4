"""``o3drbf photos``: its arguments (generated from the options' tables) and the command."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from o3drbf.cli.arguments import add_options, non_negative_int, options_from_args, validated

__all__ = ["add_photos_arguments", "main_photos"]


def add_photos_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The ``o3drbf photos`` arguments."""
    parser.add_argument("images", help="folder of the calibrated photographs")
    parser.add_argument("--calibration", metavar="FILE", default=None,
                        help="camera file or folder: Middlebury *_par.txt, Bundler bundle.out (with its list), COLMAP text model "
                        "(default: found in the image folder)")
    parser.add_argument("-o", "--output", required=True, help="output mesh (.ply, .obj, .off, .gltf; PLY keeps the vertex colours)")
    add_options(parser, "photos")
    g = parser.add_argument_group("output")
    g.add_argument("--picture", metavar="PNG", default=None, help="also write the input photo and the coloured model from the same camera, side by side")
    g.add_argument("--picture-camera", default="0", help="camera for --picture: index or image name (default %(default)s)")
    g.add_argument("--seed", type=non_negative_int, default=0, help="seed for every random choice (default %(default)s)")
    g.add_argument("-q", "--quiet", action="store_true", help="no progress bars or summary")
    g.add_argument("-v", "--verbose", action="store_true", help="log each step")
    return parser


def main_photos(args: argparse.Namespace) -> int:
    """Run ``o3drbf photos``; returns the exit status."""
    from o3drbf.io import files as io
    from o3drbf.photo.pipeline import camera_index, photo_inputs, picture, run_photos, summary

    t_start = time.perf_counter()
    options = validated(options_from_args(args, "photos"), "photos")
    out = io.check_output(args.output)
    if args.picture and Path(args.picture).suffix.lower() != ".png":
        raise ValueError(f"--picture must be a .png file, got {args.picture!r}")
    # the one guard of every command: no output is an input, a file an input refers to, or given twice
    inputs = photo_inputs(args.images, args.calibration)
    io.check_outputs([out, args.picture], inputs)
    res = run_photos(args.images, args.calibration, options=options, seed=args.seed, progress=not args.quiet)
    k = camera_index(args.picture_camera, res.cameras) if args.picture else None
    io.write_mesh(out, res.mesh, inputs=inputs)
    t_pic = 0.0
    if args.picture:
        t0 = time.perf_counter()
        picture(res.mesh, res.cameras[k], res.images[k], args.picture, inputs=inputs)
        t_pic = time.perf_counter() - t0
    res.stats["picture_seconds"] = t_pic
    if not args.quiet:
        print(summary(res, args.images, out, args.picture, time.perf_counter() - t_start))
    return 0
