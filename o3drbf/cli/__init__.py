"""The command line (``o3drbf``): argument parsing and the closing summary only."""

from o3drbf.startup import no_hugepage_advice

no_hugepage_advice()  # before NumPy is imported (see o3drbf.startup)

from o3drbf.cli.commands import build_parser, main  # noqa: E402

__all__ = ["main", "build_parser"]
