"""Reading point clouds and writing meshes, safely.

Outputs are written atomically (a temporary file in the same folder, then a
rename), so a crash never leaves a half-written file; an output path that is
one of the inputs is refused, so an input is never overwritten.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["atomic_path", "read_points", "write_mesh", "write_points", "check_output", "POINT_FORMATS", "MESH_FORMATS"]

POINT_FORMATS = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
MESH_FORMATS = (".ply", ".obj", ".stl", ".off", ".gltf", ".glb")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    The temporary keeps the final suffix, so writers that choose the format
    by extension (Open3D) work.
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {parent}")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=parent)
    os.close(fd)
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def check_output(output: str | os.PathLike, inputs=(), formats=MESH_FORMATS) -> Path:
    """Validate an output path: known extension, not one of the inputs, folder exists."""
    out = Path(output)
    if out.suffix.lower() not in formats:
        raise ValueError(f"output {str(out)!r} has an unsupported extension; valid: {', '.join(formats)}")
    for inp in inputs:
        if inp is None:
            continue
        inp = Path(inp)
        if inp.exists() and out.exists() and os.path.samefile(inp, out):
            raise ValueError(f"output {str(out)!r} is the input file; choose another name (inputs are never overwritten)")
    if not (out.parent if str(out.parent) else Path(".")).is_dir():
        raise FileNotFoundError(f"output folder does not exist: {out.parent}")
    return out


def read_points(path: str | os.PathLike):
    """Read a point cloud file (PLY, PCD, XYZ, XYZN, XYZRGB, PTS).

    Returns
    -------
    points : (N, 3) array
    normals : (N, 3) array or None
    colors : (N, 3) array in [0, 1] or None

    Raises
    ------
    FileNotFoundError, ValueError
        Missing, unreadable or empty files, with the path in the message.
    """
    import open3d as o3d

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"input file not found: {path}")
    if path.is_dir():
        raise ValueError(f"input {path} is a folder; give a point cloud file ({', '.join(POINT_FORMATS)})")
    if path.suffix.lower() not in POINT_FORMATS:
        raise ValueError(f"cannot read {path}: unsupported extension {path.suffix!r}; valid: {', '.join(POINT_FORMATS)}")
    try:
        with open(path, "rb") as fh:
            fh.read(1)
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror}") from None
    pcd = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(pcd.points, dtype=float)
    if len(pts) == 0:
        raise ValueError(f"{path} holds no points (empty, or not a readable {path.suffix} file)")
    normals = np.asarray(pcd.normals, dtype=float) if pcd.has_normals() else None
    colors = np.asarray(pcd.colors, dtype=float) if pcd.has_colors() else None
    return pts, normals, colors


def write_points(path: str | os.PathLike, points, normals=None, colors=None) -> Path:
    """Write a point cloud atomically (format from the extension)."""
    import open3d as o3d

    path = check_output(path, formats=POINT_FORMATS)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=float)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=float))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=float))
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(tmp, pcd):
            raise OSError(f"Open3D could not write {path}")
    return path


def write_mesh(path: str | os.PathLike, mesh, inputs=()) -> Path:
    """Write an Open3D ``TriangleMesh`` atomically (format from the extension)."""
    import open3d as o3d

    path = check_output(path, inputs=inputs)
    if path.suffix.lower() == ".stl" and not mesh.has_triangle_normals():
        mesh.compute_triangle_normals()
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(tmp, mesh):
            raise OSError(f"Open3D could not write {path}")
    return path
