"""``o3drbf view``: placeholder, filled in by issue 6."""

from __future__ import annotations

import argparse


def add_view_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    parser.add_argument("input", help="point cloud, scan JSON or saved model")
    return parser


def main_view(args: argparse.Namespace) -> int:
    raise RuntimeError("o3drbf view is not implemented yet")
