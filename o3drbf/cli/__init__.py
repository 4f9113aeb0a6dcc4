"""The command line (``o3drbf``): argument parsing and the closing summary only."""

from o3drbf.startup import no_hugepage_advice

no_hugepage_advice()  # before NumPy is imported (see o3drbf.startup)

from o3drbf.cli.commands import build_parser, main, run  # noqa: E402

__all__ = ["main", "run", "build_parser"]
