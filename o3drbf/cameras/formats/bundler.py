"""Bundler v0.3 files (``bundle.out``): cameras ``f k1 k2``, rotation, translation; points with colours and view lists."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from o3drbf.cameras.formats.common import Where, image_size_of, read_lines
from o3drbf.cameras.model import FLIP, Camera, CameraSet

__all__ = ["read", "referenced"]


def read(path: Path, image_size=None, read_scans: bool = False) -> CameraSet:
    """Read a Bundler v0.3 ``bundle.out``: cameras look along -z with y up; image origin at the centre, y up.

    A reader of :data:`o3drbf.cameras.formats.FORMATS`: a :class:`~o3drbf.cameras.model.CameraSet`, or
    :class:`ValueError` naming the file and the line or entry.

    Parameters
    ----------
    path : Path
        The ``bundle.out`` file; image names from a ``list.txt`` beside it or one folder up.
    image_size : (int, int), optional
        ``(width, height)`` when the images are not found (else read from them); the principal point is the image centre.
    """
    w = Where(path)
    lines = [(i + 1, s.split()) for i, s in enumerate(read_lines(path)) if s.strip() and not s.lstrip().startswith("#")]
    pos = 0

    def take(n_fields, what):
        nonlocal pos
        if pos >= len(lines):
            raise w.error(None, f"file ends early: expected {what}")
        lineno, tok = lines[pos]
        pos += 1
        if n_fields is not None and len(tok) != n_fields:
            raise w.error(f"line {lineno}", f"{what}: expected {n_fields} numbers, got {' '.join(tok)!r}")
        return lineno, w.floats(tok, f"line {lineno}", what)

    lineno, head = take(2, "'num_cameras num_points'")
    if (head != np.round(head)).any() or (head < 0).any():
        raise w.error(f"line {lineno}", f"expected two counts, got {head.tolist()}")
    n_cams, n_pts = int(head[0]), int(head[1])
    # each camera takes 5 lines and each point 3: bound the counts by the file before allocating
    if 5 * n_cams + 3 * n_pts > len(lines) - pos:
        raise w.error(
            None,
            f"file ends early: the header (line {lineno}) announces {n_cams:,} cameras and {n_pts:,} points "
            f"but only {len(lines) - pos:,} lines follow (truncated file or corrupt header)",
        )
    names = None
    for candidate in (path.parent / "list.txt", path.parent.parent / "list.txt"):
        if candidate.is_file():
            names = [s.split()[0] for s in read_lines(candidate) if s.strip()]
            if len(names) != n_cams:
                raise ValueError(f"{candidate}: lists {len(names)} images but {path} has {n_cams} cameras (count mismatch)")
            break
    cameras, index = [], np.full(n_cams, -1)
    for c in range(n_cams):
        lineno, (f, _k1, _k2) = take(3, f"camera {c}: 'f k1 k2'")
        rows = [take(3, f"camera {c}: rotation row {r + 1}")[1] for r in range(3)]
        lt, t = take(3, f"camera {c}: translation")
        Rb = np.array(rows)
        if f == 0 and not Rb.any():
            continue  # not registered by Bundler
        name = names[c] if names else f"camera {c}"
        size = image_size
        if size is None and names:
            size = image_size_of(path.parent / names[c]) or image_size_of(path.parent.parent / names[c])
        cx, cy = (0.0, 0.0) if size is None else (size[0] / 2.0, size[1] / 2.0)
        try:
            cam = Camera(
                K=np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]),
                R=FLIP @ Rb,
                t=FLIP @ t,
                width=None if size is None else size[0],
                height=None if size is None else size[1],
                name=name,
            )
        except ValueError as exc:
            raise w.error(f"lines {lineno}-{lt}", f"camera {c}: {exc}") from None
        index[c] = len(cameras)
        cameras.append(cam)
    if not cameras:
        raise w.error(None, "no camera is registered (all are zero)")
    pts, cols, obs = [], [], []
    for p in range(n_pts):
        pts.append(take(3, f"point {p}: position")[1])
        cols.append(take(3, f"point {p}: colour")[1] / 255.0)
        lineno, views = take(None, f"point {p}: view list")
        n = int(views[0]) if len(views) else -1
        if n < 0 or len(views) != 1 + 4 * n:
            raise w.error(f"line {lineno}", f"point {p}: view list must be 'n (camera key x y) * n'")
        for cam in views[1::4].astype(int):
            if not 0 <= cam < n_cams or index[cam] < 0:
                raise w.error(f"line {lineno}", f"point {p} is seen by camera {cam}, which is missing or unregistered")
            obs.append((p, index[cam]))
    if pos != len(lines):
        raise w.error(f"line {lines[pos][0]}", f"unexpected data after {n_cams} cameras and {n_pts} points (count mismatch)")
    points = np.array(pts).reshape(-1, 3) if n_pts else None
    return CameraSet(
        cameras,
        points,
        np.array(cols).reshape(-1, 3) if n_pts else None,
        None,
        np.array(obs, dtype=np.int64).reshape(-1, 2) if n_pts else None,
        str(path),
        "bundler",
    )



def referenced(path: Path) -> list[Path]:
    """The ``list.txt`` beside the file or one folder up, the images it names, and the file itself."""
    out: list[Path] = []
    for candidate in (path.parent / "list.txt", path.parent.parent / "list.txt"):
        if candidate.is_file():
            out.append(candidate)
            for s in read_lines(candidate):
                if s.strip():
                    name = s.split()[0]
                    out += [candidate.parent / name, path.parent / name]
            break
    out.append(path)
    return out
