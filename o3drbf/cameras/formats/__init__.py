"""Camera files: one reader per format, detected from the path, behind a registry keyed by format.

:func:`load_cameras` reads every supported format into the model of
:mod:`o3drbf.cameras.model`:

=====================  =====================================================
JSON                   ``{"cameras": [{"K", "R", "t", "width", "height"}]}``
                       or ``{"centers": [[x, y, z], ...]}`` (optionally
                       ``"points"`` and ``"point_camera"``)
                       (:mod:`~o3drbf.cameras.formats.jsonfile`)
Middlebury             ``*_par.txt``: count, then ``name K(9) R(9) t(3)``
                       (:mod:`~o3drbf.cameras.formats.middlebury`)
COLMAP                 text model folder: ``cameras.txt``, ``images.txt``,
                       ``points3D.txt`` (:mod:`~o3drbf.cameras.formats.colmap`)
Bundler                ``bundle.out`` (v0.3) (:mod:`~o3drbf.cameras.formats.bundler`)
Stanford range scans   ``*.conf``: ``bmesh file tx ty tz qx qy qz qw``
                       (:mod:`~o3drbf.cameras.formats.stanford`)
E57 lidar scans        ``*.e57``: scans with poses (:mod:`o3drbf.cameras.lidar`)
=====================  =====================================================

Each returns a :class:`~o3drbf.cameras.model.CameraSet`: the cameras, plus
the points and which cameras saw them when the format has them.  Malformed
files raise :class:`ValueError` naming the file and the line or entry.

A format is a :class:`Format` in :data:`FORMATS`: its reader
``read(path, image_size=None, read_scans=False)`` and the files it refers to
``referenced(path)`` (which an output must never overwrite; registered with
:data:`o3drbf.io.files.REFERENCED_FILES` when this package is imported).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from o3drbf.cameras.formats import bundler, colmap, jsonfile, middlebury, stanford
from o3drbf.cameras.formats.jsonfile import save_cameras_json
from o3drbf.cameras.model import CameraSet
from o3drbf.validation import check_number

__all__ = ["FORMATS", "Format", "load_cameras", "load_range_scans", "referenced_files", "save_cameras_json"]


@dataclass(frozen=True)
class Format:
    """One camera file format.

    Attributes
    ----------
    read : callable
        ``read(path, image_size=None, read_scans=False) -> CameraSet``; a
        format ignores the arguments it has no use for.
    referenced : callable
        ``referenced(path) -> list of Path``: the files the input refers to.
    """

    read: Callable[..., CameraSet]
    referenced: Callable[[Path], list]


def _read_e57(path: Path, image_size=None, read_scans: bool = False) -> CameraSet:
    """E57 scans and their poses (:func:`o3drbf.cameras.lidar.load_e57`; pye57 imported only here)."""
    from o3drbf.cameras.lidar import load_e57

    return load_e57(path)


#: The formats :func:`load_cameras` reads, keyed by the name :func:`_detect` gives.
FORMATS = {
    "json": Format(jsonfile.read, jsonfile.referenced),
    "middlebury": Format(middlebury.read, middlebury.referenced),
    "colmap": Format(colmap.read, colmap.referenced),
    "bundler": Format(bundler.read, bundler.referenced),
    "stanford": Format(stanford.read, stanford.referenced),
    "e57": Format(_read_e57, lambda path: [path]),
}


_FORMATS_HELP = (
    "a .json camera file, a Middlebury *_par.txt, a COLMAP text model folder (cameras.txt, images.txt), "
    "a Bundler bundle.out, a Stanford .conf, or an E57 file with scan poses"
)


def _detect(path: Path) -> tuple[str, Path]:
    """The format of a camera file or folder (a key of :data:`FORMATS`) and the file or folder its reader takes."""
    if path.is_dir():
        for sub in (path, path / "sparse", path / "sparse" / "0"):
            if (sub / "cameras.txt").is_file() and (sub / "images.txt").is_file():
                return "colmap", sub
        for rel in ("bundle.out", "bundle/bundle.out"):
            if (path / rel).is_file():
                return "bundler", path / rel
        for pattern, kind in (("*.conf", "stanford"), ("*_par.txt", "middlebury")):
            found = sorted(path.glob(pattern))
            if len(found) == 1:
                return kind, found[0]
            if len(found) > 1:
                raise ValueError(f"{path}: several {pattern} files ({', '.join(f.name for f in found)}); name one")
        raise ValueError(f"{path}: no camera file found; expected {_FORMATS_HELP}")
    if not path.exists():
        raise FileNotFoundError(f"camera file not found: {path}")
    name = path.name.lower()
    if name.endswith(".json"):
        return "json", path
    if name.endswith(".conf"):
        return "stanford", path
    if name.endswith(".e57"):
        return "e57", path
    if name in ("cameras.txt", "images.txt", "points3d.txt"):
        return "colmap", path.parent
    if name.endswith("_par.txt"):
        return "middlebury", path
    with open(path, "rb") as fh:
        head = fh.read(4096).decode("utf-8", errors="replace")
    if name.endswith(".out") or head.startswith("# Bundle file"):
        return "bundler", path
    lines = [s.split() for s in head.splitlines() if s.strip()]
    if len(lines) >= 2 and len(lines[0]) == 1 and lines[0][0].isdigit() and len(lines[1]) == 22:
        return "middlebury", path
    raise ValueError(f"cannot tell the camera format of {path}; expected {_FORMATS_HELP}")



def load_cameras(path: str | os.PathLike, image_size: tuple[int, int] | None = None, read_scans: bool = False) -> CameraSet:
    """Read cameras from a file or folder, detecting the format.

    Parameters
    ----------
    path : path-like
        A ``.json`` file, a Middlebury ``*_par.txt``, a COLMAP text model
        folder (or one of its files; ``sparse/0`` is searched too), a Bundler
        ``bundle.out`` (or its folder), a Stanford ``.conf``, or an ``.e57``
        file (its scans' poses and points, :func:`o3drbf.cameras.lidar.load_e57`).
    image_size : (int, int), optional
        ``(width, height)`` for formats that do not store it (Middlebury,
        Bundler) when the images are not beside the file.  Without it the
        image size is read from the images if present, else left unbounded.
        Bundler's principal point is the image centre, so without a size
        the image coordinates are centred.
    read_scans : bool
        Stanford ``.conf`` only: also read the scans (see
        :func:`load_range_scans`).

    Returns
    -------
    CameraSet
        The cameras, with ``points``/``colors``/``observations`` for COLMAP
        and Bundler, ``points``/``point_camera`` for JSON files that have
        them and for Stanford scans with ``read_scans``.

    Raises
    ------
    FileNotFoundError
        The path does not exist.
    ValueError
        Unknown format or malformed content; the message names the file and
        the line or entry.
    """
    path = Path(path)
    if image_size is not None:
        if len(image_size) != 2:
            raise ValueError(f"image_size must be (width, height), got {image_size!r}")
        image_size = tuple(check_number(n, v, low=1, integer=True) for n, v in zip(("width", "height"), image_size))
    kind, target = _detect(path)
    return FORMATS[kind].read(target, image_size=image_size, read_scans=read_scans)



def referenced_files(path: str | os.PathLike) -> list[Path]:
    """Files an input refers to, which an output must never overwrite.

    The scans of a Stanford ``.conf``, the images of a Middlebury
    calibration or a Bundler ``list.txt``, and the files of a COLMAP text
    model.  Other inputs refer to nothing.  Reading is cheap (no scan or
    image is opened).

    Parameters
    ----------
    path : path-like

    Returns
    -------
    list of Path
        Existing or not; empty when ``path`` cannot be read as a camera file.
    """
    path = Path(path)
    if not path.exists():
        return []
    try:
        kind, target = _detect(path)
    except ValueError:
        return []
    return FORMATS[kind].referenced(target)


def load_range_scans(conf_path: str | os.PathLike) -> CameraSet:
    """Read a Stanford ``.conf`` and all its scans, in world coordinates.

    Parameters
    ----------
    conf_path : path-like
        The ``.conf`` file; the scans (PLY) are beside it.

    Returns
    -------
    CameraSet
        One ``"direction"`` sensor per scan (looking along the scan's local
        -z), ``points`` (N, 3) of all scans in world coordinates and
        ``point_camera`` (N,) the index of the scan each point came from.
    """
    path = Path(conf_path)
    if path.is_dir():
        kind, path = _detect(path)
        if kind != "stanford":
            raise ValueError(f"{conf_path}: no .conf file in the folder")
    elif not path.exists():
        raise FileNotFoundError(f"scan configuration not found: {path}")
    return stanford.read(path, read_scans=True)


def _register_referenced_files() -> None:
    from o3drbf.io import files

    if referenced_files not in files.REFERENCED_FILES:
        files.REFERENCED_FILES.append(referenced_files)


_register_referenced_files()
