"""COLMAP text models: ``cameras.txt`` (intrinsics), ``images.txt`` (poses), ``points3D.txt`` (the sparse points and their tracks)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from o3drbf.cameras.formats.common import Where, content_lines
from o3drbf.cameras.model import Camera, CameraSet, quaternion_to_matrix, unit_quaternion

__all__ = ["read", "referenced"]

# Leading parameters of COLMAP camera models: one focal length or two.
_COLMAP_ONE_FOCAL = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"}
_COLMAP_TWO_FOCAL = {"PINHOLE", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV", "FOV", "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE"}


def read(folder: Path, image_size=None, read_scans: bool = False) -> CameraSet:
    """Read a COLMAP text model: ``cameras.txt``, ``images.txt`` and, when present, ``points3D.txt`` (points, colours, tracks).

    A reader of :data:`o3drbf.cameras.formats.FORMATS`: a :class:`~o3drbf.cameras.model.CameraSet`, or
    :class:`ValueError` naming the file and the line or entry.

    Parameters
    ----------
    folder : Path
        The model's folder.
    """
    files = {name: folder / name for name in ("cameras.txt", "images.txt", "points3D.txt")}
    for name in ("cameras.txt", "images.txt"):
        if not files[name].is_file():
            raise ValueError(f"{folder}: not a COLMAP text model: {name} is missing")
    # cameras.txt: CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]
    w = Where(files["cameras.txt"])
    intrinsics = {}
    for lineno, s in content_lines(files["cameras.txt"]):
        tok = s.split()
        if not tok:
            continue
        where = f"line {lineno}"
        if len(tok) < 5:
            raise w.error(where, f"expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got {s.strip()!r}")
        model = tok[1].upper()
        if model in _COLMAP_ONE_FOCAL:
            need = 3
        elif model in _COLMAP_TWO_FOCAL:
            need = 4
        else:
            raise w.error(where, f"unknown camera model {tok[1]!r}")
        v = w.floats(tok[2:], where, f"camera {tok[0]}")
        if len(v) < 2 + need:
            raise w.error(where, f"model {model} needs at least {need} parameters, got {len(v) - 2}")
        if need == 3:
            fx = fy = v[2]
            cx, cy = v[3], v[4]
        else:
            fx, fy, cx, cy = v[2:6]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        if tok[0] in intrinsics:
            raise w.error(where, f"camera id {tok[0]} appears twice")
        intrinsics[tok[0]] = (K, int(v[0]), int(v[1]))
    # images.txt: two lines per image; the second (2-D points) may be empty.
    w = Where(files["images.txt"])
    lines = content_lines(files["images.txt"])
    cameras, image_index = [], {}
    i = 0
    while i < len(lines):
        lineno, s = lines[i]
        tok = s.split()
        if not tok:
            i += 1
            continue
        where = f"line {lineno}"
        if len(tok) < 10:
            raise w.error(where, f"expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got {s.strip()!r}")
        v = w.floats(tok[1:8], where, f"image {tok[0]} pose")
        if tok[8] not in intrinsics:
            raise w.error(where, f"image {tok[0]} refers to camera {tok[8]}, which cameras.txt does not define")
        K, width, height = intrinsics[tok[8]]
        try:
            qw, qx, qy, qz = unit_quaternion(v[:4])
            cam = Camera(K=K, R=quaternion_to_matrix(qx, qy, qz, qw), t=v[4:7], width=width, height=height, name=" ".join(tok[9:]))
        except ValueError as exc:
            raise w.error(where, f"image {tok[0]}: {exc}") from None
        if tok[0] in image_index:
            raise w.error(where, f"image id {tok[0]} appears twice")
        image_index[tok[0]] = len(cameras)
        cameras.append(cam)
        i += 2  # skip the 2-D points line
    if not cameras:
        raise w.error(None, "no image is registered")
    points = colors = observations = None
    if files["points3D.txt"].is_file():
        # POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)
        w = Where(files["points3D.txt"])
        pts, cols, obs = [], [], []
        for lineno, s in content_lines(files["points3D.txt"]):
            tok = s.split()
            if not tok:
                continue
            where = f"line {lineno}"
            if len(tok) < 8 or (len(tok) - 8) % 2:
                raise w.error(where, f"expected 'POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)...', got {s.strip()!r}")
            v = w.floats(tok[1:7], where, f"point {tok[0]}")
            for image_id in tok[8::2]:
                if image_id not in image_index:
                    raise w.error(where, f"point {tok[0]} is seen by image {image_id}, which images.txt does not define")
                obs.append((len(pts), image_index[image_id]))
            pts.append(v[:3])
            cols.append(v[3:6] / 255.0)
        if pts:
            points, colors = np.array(pts), np.array(cols)
            observations = np.array(obs, dtype=np.int64).reshape(-1, 2)
    return CameraSet(cameras, points, colors, None, observations, str(folder), "colmap")



def referenced(folder: Path) -> list[Path]:
    """The model's three files."""
    return [folder / n for n in ("cameras.txt", "images.txt", "points3D.txt")]
