"""The command line (``o3drbf``): argument parsing and the closing summary only."""

from o3drbf.cli.commands import build_parser, main

__all__ = ["main", "build_parser"]
