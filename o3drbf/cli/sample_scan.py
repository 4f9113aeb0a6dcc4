"""``python -m o3drbf.viewers.sample_scan OUT.json``: the command line of :func:`o3drbf.viewers.sample_scan.write_sample_scan`."""

from __future__ import annotations

import argparse
import sys

from o3drbf.cli.arguments import positive_int

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """Write the sample scan; returns the exit status (2 with one line on bad input)."""
    from o3drbf.viewers import sample_scan

    parser = argparse.ArgumentParser(prog="python -m o3drbf.viewers.sample_scan", description=sample_scan.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", help="output scan .json")
    parser.add_argument("--views", type=positive_int, default=3, help="cameras on the ring (default %(default)s, as in the paper)")
    parser.add_argument("--noise", type=float, default=0.003, help="noise along the rays, data units (default %(default)s)")
    args = parser.parse_args(argv)
    try:
        print(sample_scan.write_sample_scan(args.out, views=args.views, noise=args.noise))
    except (ValueError, FileNotFoundError) as exc:
        print(f"sample_scan: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    return 0
