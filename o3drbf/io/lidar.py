"""Lidar point files: LAS and LAZ (laspy with the lazrs backend) and E57 (pye57).

Both are read in chunks into one preallocated array, so reading holds the
points once plus one chunk.  LAS and LAZ carry points (and colours) only.
An E57 file holds scans, each with its points in its own frame and,
optionally, its pose: :func:`e57_scans` lists them (name, point count,
pose) without reading points, and :func:`e57_chunks` yields one scan's
points in chunks, in the scan's frame.  Turning poses into scanner cameras
and points into world coordinates is :func:`o3drbf.cameras.lidar.load_e57`'s
job (the cameras layer sits above this one).

The libraries are optional (``pip install 'o3drbf[lidar]'``); without them
reading such a file raises :class:`ImportError` whose one line names the
``pip install`` to run.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

__all__ = ["LIDAR_FORMATS", "LAS_FORMATS", "CHUNK_POINTS", "E57Scan", "read_las", "las_chunks", "las_point_count", "e57_scans",
           "e57_chunks", "e57_point_count", "lidar_point_count"]

#: Extensions of the LAS family (laspy) and of E57 (pye57).
LAS_FORMATS = (".las", ".laz")
LIDAR_FORMATS = LAS_FORMATS + (".e57",)
#: Points per chunk when reading.
CHUNK_POINTS = 1_000_000

_INSTALL = {
    "laspy": "pip install 'o3drbf[lidar]' (or: pip install laspy lazrs)",
    "lazrs": "pip install 'o3drbf[lidar]' (or: pip install lazrs)",
    "pye57": "pip install 'o3drbf[lidar]' (or: pip install pye57)",
}


def _module(name: str, path: Path):
    """Import an optional reader library, or raise ImportError naming the install."""
    import importlib

    try:
        return importlib.import_module(name)
    except ImportError:
        raise ImportError(f"reading {path.name} needs the {name} package: {_INSTALL[name]}") from None


def _check_file(path: Path) -> None:
    if not path.exists():
        raise FileNotFoundError(f"input file not found: {path}")
    if path.is_dir():
        raise ValueError(f"input {path} is a folder; give a {path.suffix} file")
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: no points (truncated or empty file)")


@contextlib.contextmanager
def _quiet(name: str) -> Iterator[None]:
    """Silence a library's logger: laspy logs a decoding error before raising it, and the raise says it in one line."""
    logger = logging.getLogger(name)
    previous = logger.level
    logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        logger.setLevel(previous)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0].strip() if text else type(exc).__name__


# -- LAS / LAZ ------------------------------------------------------------------------


def _open_las(path: Path):
    laspy = _module("laspy", path)
    _check_file(path)
    backend = None
    if path.suffix.lower() == ".laz":
        _module("lazrs", path)
        backend = laspy.LazBackend.Lazrs
    try:
        with _quiet("laspy"):
            return laspy.open(str(path), laz_backend=backend)
    except Exception as exc:  # laspy raises its own errors, ValueError and OSError for bad headers
        raise ValueError(f"{path}: not a readable LAS file ({_first_line(exc)}); truncated or corrupt") from None


def las_point_count(path: str | os.PathLike) -> int:
    """Points a LAS or LAZ header announces, without reading them.

    Raises
    ------
    ImportError
        laspy (or lazrs for LAZ) is missing; the message names the install.
    FileNotFoundError, ValueError
        No such file, or an unreadable header.
    """
    path = Path(path)
    with _open_las(path) as reader:
        return int(reader.header.point_count)


def las_chunks(path: str | os.PathLike, chunk_size: int = CHUNK_POINTS) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
    """A LAS or LAZ file's points chunk by chunk: ``(points (m, 3) float64, rgb (m, 3) uint16 or None)``.

    Raises
    ------
    ImportError
        laspy (or lazrs for LAZ) is missing; the message names the install.
    FileNotFoundError, ValueError
        Missing, empty, truncated or corrupt files, no points, with the path in
        the one-line message (a short file before the first point is read).
    """
    from o3drbf.io.files import MAX_POINTS

    path = Path(path)
    with _open_las(path) as reader:
        header = reader.header
        n = int(header.point_count)
        if n == 0:
            raise ValueError(f"{path}: no points (the header announces 0)")
        if n > MAX_POINTS:
            raise ValueError(f"{path}: header announces {n:,} points, more than the {MAX_POINTS:,} supported; the file is corrupt")
        if path.suffix.lower() == ".las":
            need = int(header.offset_to_point_data) + n * int(header.point_format.size)
            have = path.stat().st_size
            if have < need:
                raise ValueError(f"{path}: truncated file: the header announces {n:,} points ({need:,} bytes) "
                                 f"but the file has {have:,} bytes")
        rgb = {"red", "green", "blue"} <= set(header.point_format.dimension_names)
        start = 0
        chunks = reader.chunk_iterator(max(1, int(chunk_size)))
        while True:
            try:
                with _quiet("laspy"):
                    chunk = next(chunks, None)
                if chunk is None:
                    break
                m = len(chunk)
                if start + m > n:
                    raise ValueError(f"more points than the {n:,} the header announces")
                xyz = np.column_stack([np.asarray(chunk.x, float), np.asarray(chunk.y, float), np.asarray(chunk.z, float)])
                colors = np.column_stack([chunk.red, chunk.green, chunk.blue]).astype(np.uint16) if rgb else None
            except Exception as exc:  # lazrs and laspy raise their own errors on short or corrupt data
                raise ValueError(f"{path}: truncated or corrupt point data after {start:,} of {n:,} points ({_first_line(exc)})") from None
            start += m
            yield xyz, colors
    if start != n:
        raise ValueError(f"{path}: truncated file: {start:,} of the {n:,} points the header announces")


def read_las(path: str | os.PathLike, chunk_size: int = CHUNK_POINTS):
    """Read a LAS or LAZ file chunk by chunk (:func:`las_chunks`) into one array.

    Parameters
    ----------
    path : path-like
    chunk_size : int
        Points decoded at a time (laspy's chunk iterator).

    Returns
    -------
    points : (N, 3) float64 array
        Scaled and offset coordinates, as stored.
    colors : (N, 3) array in [0, 1] or None
        From the red, green and blue dimensions when the point format has
        them and they are not all zero (16-bit values, or 8-bit ones stored in
        16 bits).

    Raises
    ------
    ImportError
        laspy (or lazrs for LAZ) is missing; the message names the install.
    FileNotFoundError, ValueError
        Missing, empty, truncated or corrupt files, no points, or non-finite
        coordinates, with the path in the one-line message.
    """
    path = Path(path)
    chunks = las_chunks(path, chunk_size)
    first = next(chunks)  # the header's checks (count, size) before anything is allocated
    n = las_point_count(path)
    points, raw, start = np.empty((n, 3)), None, 0
    for xyz, rgb in itertools.chain([first], chunks):
        m = len(xyz)
        points[start:start + m] = xyz
        if rgb is not None:
            raw = np.empty((n, 3), dtype=np.uint16) if raw is None else raw
            raw[start:start + m] = rgb
        start += m
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} point(s) with NaN or infinite coordinates (first at index {int(np.argmax(bad))})")
    colors = None
    if raw is not None and raw.any():
        colors = raw / (255.0 if raw.max() <= 255 else 65535.0)
    return points, colors


# -- E57 -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class E57Scan:
    """One scan of an E57 file, as its header describes it.

    Attributes
    ----------
    index : int
        Position in the file's ``data3D`` list.
    name : str
        The scan's name (``scan <index>`` when it has none).
    count : int
        Point records, invalid ones included.
    rotation : (4,) array or None
        The pose's unit quaternion ``(w, x, y, z)``; None without a pose.
    translation : (3,) array or None
        The pose's translation; None without a pose.  World points are
        ``R(q) @ p_scan + translation``.
    spherical : bool
        The points are stored as range, azimuth, elevation.
    """

    index: int
    name: str
    count: int
    rotation: np.ndarray | None
    translation: np.ndarray | None
    spherical: bool = False

    @property
    def has_pose(self) -> bool:
        return self.rotation is not None


_CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
_SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")


def _open_e57(path: Path):
    pye57 = _module("pye57", path)
    _check_file(path)
    try:
        return pye57.E57(str(path))
    except Exception as exc:  # libe57 raises E57Exception with a multi-line report
        raise ValueError(f"{path}: not a readable E57 file ({_first_line(exc)}); truncated or corrupt") from None


def _pose_values(node, keys, path: Path, where: str) -> np.ndarray:
    try:
        return np.array([float(node[k].value()) for k in keys])
    except Exception as exc:  # a pose without its numbers
        raise ValueError(f"{path}, {where}: the pose is incomplete ({_first_line(exc)}); fix or remove the pose") from None


def e57_scans(path: str | os.PathLike) -> list[E57Scan]:
    """The scans of an E57 file, from its headers (no point is read).

    Raises
    ------
    ImportError
        pye57 is missing; the message names the install.
    FileNotFoundError, ValueError
        Missing, truncated or corrupt files, no scan, scans without
        coordinates, with the path (and scan) in the one-line message.
    """
    path = Path(path)
    e57 = _open_e57(path)
    try:
        try:
            count = int(e57.scan_count)
        except Exception as exc:
            raise ValueError(f"{path}: not a readable E57 file ({_first_line(exc)})") from None
        if count == 0:
            raise ValueError(f"{path}: the file holds no scan (data3D is empty)")
        scans = []
        for i in range(count):
            try:
                header = e57.get_header(i)
                node = header.node
                name = str(node["name"].value()) if node.isDefined("name") else f"scan {i}"
                fields = set(header.point_fields)
                n = int(header.point_count)
            except Exception as exc:
                raise ValueError(f"{path}, scan {i}: unreadable header ({_first_line(exc)})") from None
            where = f"scan {i} {name!r}"
            if set(_CARTESIAN) <= fields:
                spherical = False
            elif set(_SPHERICAL) <= fields:
                spherical = True
            else:
                raise ValueError(f"{path}, {where}: no cartesianX/Y/Z nor sphericalRange/Azimuth/Elevation fields; not a point scan")
            rotation = translation = None
            if node.isDefined("pose"):
                pose = node["pose"]
                rotation = (_pose_values(pose["rotation"], ("w", "x", "y", "z"), path, where)
                            if pose.isDefined("rotation") else np.array([1.0, 0.0, 0.0, 0.0]))
                translation = (_pose_values(pose["translation"], ("x", "y", "z"), path, where)
                               if pose.isDefined("translation") else np.zeros(3))
            scans.append(E57Scan(i, name, n, rotation, translation, spherical))
        return scans
    finally:
        e57.close()


def e57_point_count(path: str | os.PathLike) -> int:
    """Point records in all scans of an E57 file (invalid ones included), from the headers."""
    return sum(s.count for s in e57_scans(path))


def e57_chunks(path: str | os.PathLike, scan: E57Scan, chunk_size: int = CHUNK_POINTS) -> Iterator[np.ndarray]:
    """One scan's valid points, chunk by chunk, in the scan's own frame.

    Parameters
    ----------
    path : path-like
    scan : E57Scan
        From :func:`e57_scans` on the same file.
    chunk_size : int
        Records decoded at a time.

    Yields
    ------
    (m, 3) float64 array
        Cartesian coordinates (spherical ones converted); records marked
        invalid are dropped.

    Raises
    ------
    ValueError
        Truncated or corrupt point data, naming the file and the scan.
    """
    path = Path(path)
    e57 = _open_e57(path)
    where = f"scan {scan.index} {scan.name!r}"
    try:
        header = e57.get_header(scan.index)
        fields = list(_SPHERICAL if scan.spherical else _CARTESIAN)
        state = "sphericalInvalidState" if scan.spherical else "cartesianInvalidState"
        if state in header.point_fields:
            fields.append(state)
        size = max(1, min(int(chunk_size), max(scan.count, 1)))
        done = 0
        try:
            data, buffers = e57.make_buffers(fields, size)
            reader = header.points.reader(buffers)
        except Exception as exc:
            raise ValueError(f"{path}, {where}: cannot read the points ({_first_line(exc)}); truncated or corrupt") from None
        try:
            while True:
                try:
                    m = int(reader.read())
                except Exception as exc:
                    raise ValueError(f"{path}, {where}: truncated or corrupt point data after {done:,} of {scan.count:,} "
                                     f"points ({_first_line(exc)})") from None
                if m == 0:
                    break
                done += m
                a, b, c = (np.asarray(data[k][:m], dtype=float) for k in fields[:3])
                if scan.spherical:  # range, azimuth, elevation
                    ce = np.cos(c)
                    xyz = np.column_stack([a * ce * np.cos(b), a * ce * np.sin(b), a * np.sin(c)])
                else:
                    xyz = np.column_stack([a, b, c])
                if state in data:
                    xyz = xyz[data[state][:m] == 0]
                yield xyz
        finally:
            reader.close()
        if done != scan.count:
            raise ValueError(f"{path}, {where}: truncated point data: {done:,} of the {scan.count:,} points the header announces")
    finally:
        e57.close()


def lidar_point_count(path: str | os.PathLike) -> int | None:
    """Points a LAS, LAZ or E57 header announces; None for other files, a missing library or an unreadable header."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in LIDAR_FORMATS or not path.is_file():
        return None
    try:
        return las_point_count(path) if suffix in LAS_FORMATS else e57_point_count(path)
    except (ImportError, ValueError, OSError):
        return None
