"""Binary PLY files without loading them: the header, and the vertex element memory-mapped.

:func:`open_ply_vertices` maps the vertex element of a binary PLY (little- or
big-endian, any scalar properties) by the header's offsets; the tiled path
(:mod:`o3drbf.tiles`) reads it chunk by chunk, so no process holds all the
points.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Iterator

import numpy as np

__all__ = ["MAX_POINTS", "PlyVertices", "open_ply_vertices", "ply_header", "check_ply_header", "check_ascii_ply_lines", "read_plain_ply"]


#: Largest point count a file header may announce (bounds allocations from a corrupt header).
MAX_POINTS = 2_000_000_000


def check_ply_header(path: Path) -> None:
    """Refuse a PLY whose header announces more data than the file holds (truncated)."""
    with open(path, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply"):
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic on line 1)")
    if end < 0:
        raise ValueError(f"{path}: no points (truncated or empty file): the header has no end_header")
    header = head[:end].decode("ascii", errors="replace")
    m = re.search(r"element\s+vertex\s+(\d+)", header)
    if not m or int(m.group(1)) == 0:
        raise ValueError(f"{path}: no points (truncated or empty file)")
    count = int(m.group(1))
    if count > MAX_POINTS:
        raise ValueError(f"{path}: header announces {count:,} points, more than the {MAX_POINTS:,} supported; the file is corrupt")
    fmt = re.search(r"format\s+(\S+)", header)
    body = path.stat().st_size - (end + len(b"end_header"))
    if fmt and fmt.group(1).startswith("binary"):
        vert = header[m.end():].split("element")[0]
        sizes = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
                 "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
        width = 0
        for line in vert.splitlines():
            tok = line.split()
            if len(tok) == 3 and tok[0] == "property" and tok[1] in sizes:
                width += sizes[tok[1]]
        if width and body < count * width:
            raise ValueError(f"{path}: no points (truncated or empty file): the header announces {count:,} points "
                             f"({count * width:,} bytes) but only {max(body, 0):,} bytes follow")
    elif body <= 1:
        raise ValueError(f"{path}: no points (truncated or empty file)")
    else:
        check_ascii_ply_lines(path, head, end, count)


def check_ascii_ply_lines(path: Path, head: bytes, end: int, count: int) -> None:
    """Refuse an ASCII PLY with fewer vertex lines than its header announces (a truncated file).

    The lines of the elements before the vertex element and of the vertex
    element itself are counted (one line per entry); a last line without a
    newline counts when it holds every vertex property.
    """
    nl = head.find(b"\n", end)
    if nl < 0:
        return  # ply_header names this
    before, properties, seen_vertex = 0, 0, False
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        tok = line.split()
        if len(tok) == 3 and tok[0] == "element":
            if seen_vertex:
                break
            seen_vertex = tok[1] == "vertex"
            if not seen_vertex:
                try:
                    before += int(tok[2])
                except ValueError:
                    return
        elif tok and tok[0] == "property" and seen_vertex:
            properties += 1
    needed = before + count
    lines, last = 0, b""
    with open(path, "rb") as fh:
        fh.seek(nl + 1)
        while lines < needed:
            block = fh.read(1 << 22)
            if not block:
                break
            lines += block.count(b"\n")
            last = block if b"\n" not in block else block.rsplit(b"\n", 1)[1]
    if lines < needed and lines + 1 == needed and len(last.split()) >= properties > 0:
        lines += 1  # the last vertex line, complete but without a newline
    if lines < needed:
        read = max(lines - before, 0)
        raise ValueError(f"{path}: truncated file: the header promises {count:,} vertices but only {read:,} complete vertex "
                         "lines follow; copy or export the file again")


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


class PlyVertices:
    """The vertex element of a binary PLY file, memory-mapped: points read in chunks, never all at once.

    Open with :func:`open_ply_vertices`.  ``x, y, z`` (and ``nx, ny, nz`` when
    present) are returned as float64, exactly as Open3D's reader returns them.

    Attributes
    ----------
    path : Path
    count : int
        Number of vertices N.
    offset : int
        Byte offset of the vertex element in the file.
    dtype : numpy.dtype
        One vertex record (byte order of the file).
    has_normals : bool
    """

    def __init__(self, path: Path, count: int, offset: int, dtype: np.dtype):
        self.path, self.count, self.offset, self.dtype = Path(path), int(count), int(offset), np.dtype(dtype)
        self.has_normals = all(k in self.dtype.names for k in ("nx", "ny", "nz"))

    def __len__(self) -> int:
        return self.count

    def memmap(self) -> np.memmap:
        """(N,) structured read-only memory map of the vertex records."""
        return np.memmap(self.path, dtype=self.dtype, mode="r", offset=self.offset, shape=(self.count,))

    def _columns(self, records, names) -> np.ndarray:
        return np.column_stack([np.asarray(records[k], dtype=np.float64) for k in names])

    def take(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Points (M, 3) and normals (M, 3) or None of vertices ``start:stop`` (float64 copies)."""
        rec = self.memmap()[start:stop]
        pts = self._columns(rec, ("x", "y", "z"))
        nrm = self._columns(rec, ("nx", "ny", "nz")) if self.has_normals else None
        return pts, nrm

    def gather(self, index) -> tuple[np.ndarray, np.ndarray | None]:
        """Points and normals of the vertices at sorted ``index`` ((M,) ints)."""
        rec = self.memmap()[np.asarray(index, dtype=np.int64)]
        pts = self._columns(rec, ("x", "y", "z"))
        nrm = self._columns(rec, ("nx", "ny", "nz")) if self.has_normals else None
        return pts, nrm

    def chunks(self, size: int = 1_000_000) -> Iterator[tuple[int, np.ndarray, np.ndarray | None]]:
        """``(start, points (m, 3), normals (m, 3) or None)`` for consecutive chunks of at most ``size`` vertices."""
        size = max(1, int(size))
        for start in range(0, self.count, size):
            pts, nrm = self.take(start, min(start + size, self.count))
            yield start, pts, nrm


def ply_header(path: str | os.PathLike) -> dict:
    """Parse a PLY header: ``format``, ``header_bytes`` and ``elements`` (list of (name, count, [(type, name) or ("list", ...)])).

    Raises
    ------
    ValueError
        Not a PLY file or no ``end_header``.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no end_header in the first 64 KiB)")
    nl = head.find(b"\n", end)
    if nl < 0:
        raise ValueError(f"{path}: no points (truncated or empty file): nothing after end_header")
    fmt, elements = None, []
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
        elif tok[0] == "element" and len(tok) == 3:
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property" and elements:
            elements[-1][2].append(tuple(tok[1:]))
    return {"format": fmt, "header_bytes": nl + 1, "elements": elements}


def open_ply_vertices(path: str | os.PathLike) -> PlyVertices:
    """Memory-map the vertex element of a binary PLY file (little- or big-endian).

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Not a binary PLY, no vertex element with x, y, z, a list property in
        or before it, or a truncated file (the message says to read it with
        :func:`read_points` instead where that works).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"input file not found: {path}")
    check_ply_header(path)
    h = ply_header(path)
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(h["format"])
    if order is None:
        raise ValueError(f"{path}: {h['format']} PLY cannot be memory-mapped; read it with read_points (or convert it to binary PLY)")
    offset = h["header_bytes"]
    for name, count, props in h["elements"]:
        if any(p[0] == "list" or p[0] not in _PLY_TYPES for p in props):
            raise ValueError(f"{path}: element {name!r} has list or unknown properties before the vertices end; "
                             "read it with read_points")
        dtype = np.dtype([(p[1], order + _PLY_TYPES[p[0]]) for p in props])
        if name == "vertex":
            if not all(k in dtype.names for k in ("x", "y", "z")):
                raise ValueError(f"{path}: the vertex element has no x, y, z properties")
            if path.stat().st_size < offset + count * dtype.itemsize:
                raise ValueError(f"{path}: no points (truncated or empty file): {count:,} vertices announced, fewer bytes follow")
            return PlyVertices(path, count, offset, dtype)
        offset += count * dtype.itemsize
    raise ValueError(f"{path}: no vertex element; not a point cloud")


#: The vertex properties :func:`read_plain_ply` reads (any other sends the file to Open3D's reader).
PLAIN_PROPERTIES = ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue")


def read_plain_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None] | None:
    """Points, normals and colours of a plain binary point-cloud PLY, as Open3D's reader gives them; else None.

    Plain: what :func:`open_ply_vertices` maps, its vertex properties among
    :data:`PLAIN_PROPERTIES`, the normals all three or none, the colours all
    three and ``uchar`` or none.  The points and normals come as float64 and
    the colours divided by 255, as Open3D's ``read_point_cloud`` returns them;
    anything else (ASCII, other properties, lists before the vertices)
    returns None, for that reader.  Reading a file this way does not import
    Open3D.
    """
    try:
        vertices = open_ply_vertices(path)
    except (OSError, ValueError):
        return None
    names = vertices.dtype.names
    rgb = ("red", "green", "blue")
    if (not set(names) <= set(PLAIN_PROPERTIES) or sum(k in names for k in ("nx", "ny", "nz")) not in (0, 3)
            or sum(k in names for k in rgb) not in (0, 3) or any(vertices.dtype[k].kind + str(vertices.dtype[k].itemsize) != "u1"
                                                                 for k in rgb if k in names)):
        return None
    points, normals = vertices.take(0, len(vertices))
    colors = None
    if "red" in names:
        records = vertices.memmap()
        colors = np.column_stack([np.asarray(records[k], dtype=np.float64) for k in rgb]) / 255.0
    return points, normals, colors
