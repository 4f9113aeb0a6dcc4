"""JSON camera files: ``{"cameras": [{"K", "R", "t", "width", "height"}]}`` or ``{"centers": [[x, y, z], ...]}``.

Optionally ``"points"``, ``"colors"`` (in [0, 1]) and ``"point_camera"``
(the camera index of each point, -1 unknown).  :func:`save_cameras_json`
writes the same format.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from o3drbf.cameras.formats.common import Where
from o3drbf.cameras.model import Camera, CameraSet
from o3drbf.validation import as_points

__all__ = ["point_camera_index", "read", "referenced", "save_cameras_json"]


def read(path: Path, image_size=None, read_scans: bool = False) -> CameraSet:
    """Read a JSON camera file: ``{"cameras": [...]}`` or ``{"centers": [...]}``, optionally ``"points"``, ``"colors"``, ``"point_camera"``.

    A reader of :data:`o3drbf.cameras.formats.FORMATS`: a :class:`~o3drbf.cameras.model.CameraSet`, or
    :class:`ValueError` naming the file and the line or entry.

    Parameters
    ----------
    path : Path
        The ``.json`` file.
    """
    w = Where(path)
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise w.error(None, f"not a text JSON file (undecodable byte at offset {exc.start}); give a UTF-8 JSON camera file") from None
    except RecursionError:
        raise w.error(None, "JSON nested too deeply; give a camera file as documented") from None
    except json.JSONDecodeError as exc:
        raise w.error(f"line {exc.lineno}", f"invalid JSON: {exc.msg}") from None
    except OSError as exc:
        raise w.error(None, f"cannot read: {exc.strerror}") from None
    if not isinstance(data, dict) or not ({"cameras", "centers"} & set(data)):
        raise w.error(None, 'expected a JSON object with "cameras" (list of {K, R, t, width, height}) or "centers"')
    cameras = []
    for key in ("cameras", "centers"):
        entries = data.get(key, [])
        if not isinstance(entries, list):
            raise w.error(None, f'"{key}" must be a list')
        for i, entry in enumerate(entries):
            try:
                cam = Camera.from_dict(entry) if key == "cameras" else Camera.from_center(entry, name=f"center {i}")
            except ValueError as exc:
                raise w.error(f"{key}[{i}]", str(exc)) from None
            cameras.append(cam)
    if not cameras:
        raise w.error(None, "the file lists no camera")
    points = colors = point_camera = None
    if "points" in data:
        try:
            points = as_points(data["points"], name='"points"')
        except ValueError as exc:
            raise w.error(None, str(exc)) from None
        if "colors" in data:
            try:
                colors = np.asarray(data["colors"], dtype=float)
            except (TypeError, ValueError):
                raise w.error(None, '"colors" must be a list of [r, g, b] numbers, one per point (ragged or non-numeric entries)') from None
            if colors.shape != points.shape:
                raise w.error(None, f'"colors" has shape {colors.shape}; expected {points.shape}, one per point')
            if not np.isfinite(colors).all() or colors.min() < 0 or colors.max() > 1:
                raise w.error(None, '"colors" must be finite and in [0, 1]')
    if "point_camera" in data:
        if points is None:
            raise w.error(None, '"point_camera" given without "points"')
        point_camera = point_camera_index(w, data["point_camera"], len(points), len(cameras))
    return CameraSet(cameras, points, colors, point_camera, None, str(path), "json")


def point_camera_index(w: Where, values, n_points: int, n_cameras: int) -> np.ndarray:
    """``"point_camera"`` checked: one whole number per point, a camera index or -1 (unknown)."""
    pc = np.asarray(values)
    if pc.shape != (n_points,):
        raise w.error(None, f'"point_camera" has {pc.size} entries for {n_points} points (count mismatch)')
    if pc.size and (not np.issubdtype(pc.dtype, np.number) or (pc != np.round(pc)).any()):
        raise w.error(None, '"point_camera" must be whole numbers (camera index, -1 for unknown)')
    pc = pc.astype(np.int64)
    bad = (pc < -1) | (pc >= n_cameras)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise w.error(
            f"point_camera[{i}]", f"camera index {pc[i]} is out of range: the file has {n_cameras} camera(s) (count mismatch)"
        )
    return pc



def save_cameras_json(path: str | os.PathLike, cameras, points=None, point_camera=None, colors=None) -> Path:
    """Write cameras (and optionally points) in the JSON format, atomically.

    Parameters
    ----------
    path : path-like
        Output ``.json`` file.
    cameras : sequence of Camera
    points : (N, 3) array_like, optional
    point_camera : (N,) int array_like, optional
        Index of the camera that produced each point (-1: unknown).
    colors : (N, 3) array_like in [0, 1], optional

    Returns
    -------
    Path
    """
    from o3drbf.io.files import atomic_path

    path = Path(path)
    if path.suffix.lower() != ".json":
        raise ValueError(f"camera file {str(path)!r} must end in .json")
    cams = list(cameras)
    if not cams or not all(isinstance(c, Camera) for c in cams):
        raise ValueError("cameras must be a non-empty sequence of Camera")
    data: dict = {"cameras": [c.to_dict() for c in cams]}
    if points is not None:
        pts = as_points(points)
        data["points"] = pts.tolist()
        if colors is not None:
            col = np.asarray(colors, dtype=float)
            if col.shape != pts.shape:
                raise ValueError(f"colors must have shape {pts.shape}, got {col.shape}")
            data["colors"] = col.tolist()
        if point_camera is not None:
            pc = point_camera_index(Where(path), point_camera, len(pts), len(cams))
            data["point_camera"] = pc.tolist()
    elif point_camera is not None:
        raise ValueError("point_camera given without points")
    def verify(tmp):  # read back before the rename: a short write would not parse
        try:
            json.loads(Path(tmp).read_text(encoding="utf-8"))
        except (ValueError, OSError) as exc:
            raise OSError(f"cannot write {path}: the file read back is not valid JSON ({exc}); nothing was written") from None

    with atomic_path(path, verify=verify) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(data, fh)
    return path


def referenced(path: Path) -> list[Path]:
    """The file itself (its points are inside it)."""
    return [path]
