"""``o3drbf photos``: placeholder, filled in by issue 7."""

from __future__ import annotations

import argparse


def add_photos_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    parser.add_argument("images", help="folder of calibrated images")
    return parser


def main_photos(args: argparse.Namespace) -> int:
    raise RuntimeError("o3drbf photos is not implemented yet")
