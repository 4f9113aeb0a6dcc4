"""``o3drbf view``: its arguments (generated from the options' tables, without importing PyVista) and the command."""

from __future__ import annotations

import argparse

from o3drbf.cli.arguments import add_options, non_negative_int, options_from_args, validated

__all__ = ["add_view_arguments", "main_view"]


def add_view_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The ``o3drbf view`` arguments (no PyVista import here: ``o3drbf --help`` stays fast)."""
    parser.add_argument(
        "input",
        help="point cloud (PLY, PCD, XYZ, ...), a file or folder with points and cameras "
        "(o3drbf scan .json, Stanford .conf, COLMAP folder, bundle.out), a saved model .npz, or a mesh with faces",
    )
    parser.add_argument("--cameras", metavar="FILE", help="cameras for a plain point cloud (exterior constraints go toward them)")
    parser.add_argument("--screenshot", metavar="PNG", help="render offscreen to this .png and exit (no display needed)")
    groups = add_options(parser, "view")
    groups["fit"].add_argument("--seed", type=non_negative_int, default=0, help="seed for sampling (default %(default)s)")
    # Scripted session for tests: "set level 0.1; wait; print; quit" (o3drbf.viewers.session.parse_script).
    groups["window"].add_argument("--script", default=None, help=argparse.SUPPRESS)
    return parser


def main_view(args: argparse.Namespace) -> int:
    """Run ``o3drbf view`` (interactive, or offscreen with ``--screenshot``)."""
    options = validated(options_from_args(args, "view"), "view")
    try:
        from o3drbf.viewers.session import view
    except ImportError as exc:
        raise ImportError(f"o3drbf view needs the viewers package and PyVista ({exc}); pip install 'o3drbf[view]'") from None
    return view(args.input, args.cameras, options=options, screenshot=args.screenshot, script=args.script, seed=args.seed)
