"""Stanford range-scan configurations (``*.conf``): one pose per scan, the scans beside it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from o3drbf.cameras.formats.common import Where, read_lines
from o3drbf.cameras.model import FLIP, Camera, CameraSet, quaternion_to_matrix, unit_quaternion

__all__ = ["read", "referenced"]


def read(path: Path, image_size=None, read_scans: bool = False) -> CameraSet:
    """Read a Stanford ``.conf``: ``bmesh file tx ty tz qx qy qz qw`` per scan, ``p_world = R(q)^T p_scan + t``.

    The scanner looks along -z of each scan frame; the ``camera`` line is a
    viewer camera and is skipped.

    Parameters
    ----------
    path : Path
        The ``.conf`` file; the scans (PLY) are beside it.
    image_size
        Not used (the sensors have no image).
    read_scans : bool
        Also read the scans, in world coordinates, with the scan of each point.

    Returns
    -------
    CameraSet
        One ``"direction"`` sensor per scan; with ``read_scans``, ``points`` and ``point_camera``.

    Raises
    ------
    ValueError
        Malformed content or a missing scan, naming the file and the line.
    """
    w = Where(path)
    cameras, files = [], []
    for lineno, s in enumerate(read_lines(path), start=1):
        tok = s.split()
        if not tok or tok[0].startswith("#") or tok[0] == "camera":
            continue
        where = f"line {lineno}"
        if tok[0] not in ("bmesh", "mesh"):
            raise w.error(where, f"unknown keyword {tok[0]!r}; expected 'bmesh file tx ty tz qx qy qz qw'")
        if len(tok) != 9:
            raise w.error(where, f"expected 'bmesh file tx ty tz qx qy qz qw' (9 fields), got {len(tok)}")
        v = w.floats(tok[2:], where, f"pose of {tok[1]}")
        try:
            q = unit_quaternion(v[3:])
        except ValueError as exc:
            raise w.error(where, f"{tok[1]}: {exc}") from None
        Rq = quaternion_to_matrix(*q)
        # scan frame: p_scan = Rq (p_world - t); flip it to look along +z.
        cameras.append(Camera(R=FLIP @ Rq, t=-FLIP @ Rq @ v[:3], kind="direction", name=tok[1]))
        files.append((lineno, path.parent / tok[1]))
    if not cameras:
        raise w.error(None, "no 'bmesh' line: the file lists no scan")
    for lineno, f in files:
        if not f.is_file():
            raise w.error(f"line {lineno}", f"scan file {f.name} not found beside the .conf (count mismatch between the .conf and its scans)")
    if not read_scans:
        return CameraSet(cameras, source=str(path), format="stanford")
    from o3drbf.io.files import read_points

    parts, owner = [], []
    for c, ((lineno, f), cam) in enumerate(zip(files, cameras)):
        try:
            p, _, _ = read_points(f)
        except ValueError as exc:
            raise w.error(f"line {lineno}", str(exc)) from None
        # p_world = R(q)^T p_scan + t, and p_scan = FLIP x_cam.
        parts.append((p @ FLIP) @ cam.R + cam.center)
        owner.append(np.full(len(p), c, dtype=np.int64))
    return CameraSet(cameras, np.concatenate(parts), None, np.concatenate(owner), None, str(path), "stanford")



def referenced(path: Path) -> list[Path]:
    """The scans the ``bmesh`` lines name (beside the file)."""
    out = []
    for s in read_lines(path):
        tok = s.split()
        if len(tok) >= 2 and tok[0] in ("bmesh", "mesh"):
            out.append(path.parent / tok[1])
    return out
