"""Write a synthetic scan with cameras for ``o3drbf view`` (the README picture).

    python -m o3drbf.viewers.sample_scan OUT.json [--views 3] [--noise 0.003]

Three tori stacked along z (the paper's 'towers', idealized) are ray-cast
from cameras on a ring (:func:`o3drbf.synthetic.scans.range_scans`); the points, the
cameras and which camera saw each point go into one scan JSON that
``o3drbf view`` and ``o3drbf reconstruct`` read.
"""

from __future__ import annotations

import sys
from pathlib import Path

__all__ = ["tori_stack_mesh", "write_sample_scan", "main"]


def tori_stack_mesh(count: int = 3, resolution: int = 64):
    """An Open3D mesh of :class:`o3drbf.synthetic.shapes.TorusStack` (``count`` tori)."""
    import open3d as o3d

    from o3drbf.synthetic.shapes import TorusStack

    mesh = o3d.geometry.TriangleMesh()
    for torus in TorusStack(count).tori:
        part = o3d.geometry.TriangleMesh.create_torus(torus.R, torus.r, resolution, resolution // 2)
        mesh += part.translate(torus.center)
    return mesh


def write_sample_scan(path: str | Path, views: int = 3, noise: float = 0.003, width: int = 160, height: int = 120, seed: int = 0) -> Path:
    """Ray-cast the tori stack from ``views`` cameras and write a scan JSON.

    Returns
    -------
    Path
    """
    from o3drbf.synthetic.scans import range_scans, write_scan_json

    path = Path(path)
    if path.suffix.lower() != ".json":
        raise ValueError(f"scan file must end in .json, got {str(path)!r}")
    # A wide field of view brings the cameras close, so a picture shows them and the data.
    points, point_camera, cameras = range_scans(tori_stack_mesh(), n_views=views, width=width, height=height, fov=70.0, noise=noise, elevation=25.0, seed=seed)
    return write_scan_json(path, points, cameras, point_camera)


def main(argv: list[str] | None = None) -> int:
    """``python -m o3drbf.viewers.sample_scan OUT.json``: its command line is :func:`o3drbf.cli.sample_scan.main`."""
    from o3drbf.cli.sample_scan import main as command

    return command(argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
