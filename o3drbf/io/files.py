"""Reading point clouds and writing meshes, safely.

Every output o3drbf writes (mesh, points, model, tables, pictures) goes
through :func:`atomic_path`: the writer writes a temporary file in the target
folder, the file is checked (non-empty, flushed to disk, and for meshes and
points read back and compared), then renamed onto the target in one atomic
step.  A crash, an exception, Ctrl-C or (after :func:`install_signal_cleanup`)
SIGTERM never leaves a half-written file nor a stray temporary, and an
existing output is replaced only by a complete, checked one.

:func:`check_outputs` refuses, before any costly step, an output that is an
input (or a file an input refers to: the scans of a Stanford ``.conf``, the
images of a calibration), a folder, or a file in a missing or read-only
folder.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import os
import re
import signal
import tempfile
import threading
import warnings
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from o3drbf.io.ply import MAX_POINTS, PlyVertices, check_ply_header, open_ply_vertices, ply_header, read_plain_ply

__all__ = [
    "atomic_path",
    "read_points",
    "PlyVertices",
    "open_ply_vertices",
    "ply_header",
    "point_count",
    "write_mesh",
    "write_points",
    "check_output",
    "check_outputs",
    "check_mesh_precision",
    "install_signal_cleanup",
    "signal_cleanup",
    "live_temporary_files",
    "remove_temporary_files",
    "write_failed",
    "POINT_FORMATS",
    "MESH_FORMATS",
    "PRECISION_TOLERANCE",
    "MAX_POINTS",
]

POINT_FORMATS = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
#: Mesh formats that round-trip through Open3D (``.glb`` is not listed: Open3D
#: writes binary glTF it cannot read back, 0 triangles).
MESH_FORMATS = (".ply", ".obj", ".stl", ".off", ".gltf")
#: Largest coordinate error a written mesh may carry, relative to its bounding-box diagonal.
PRECISION_TOLERANCE = 1e-5

# -- temporary-file registry ----------------------------------------------------

_LIVE: set[str] = set()
_LOCK = threading.Lock()


def live_temporary_files() -> list[str]:
    """Temporary files :func:`atomic_path` is writing right now (for tests and signal handlers)."""
    with _LOCK:
        return sorted(_LIVE)


def remove_temporary_files() -> int:
    """Delete every live temporary file; returns how many were removed.  Safe to call twice."""
    with _LOCK:
        live = list(_LIVE)
        _LIVE.clear()
    removed = 0
    for tmp in live:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
            removed += 1
    return removed


atexit.register(remove_temporary_files)

_INSTALLED: dict[int, object] = {}


def install_signal_cleanup(signals: Sequence[int] = (signal.SIGTERM,)) -> None:
    """Remove live temporary outputs on SIGTERM (and ``signals``), then exit ``128 + signum``.

    Call once from the command line's entry point (the main thread).  The
    previous handler is kept and called after the clean-up when it is a
    Python callable.  Idempotent.
    """
    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError("install_signal_cleanup must be called from the main thread")
    for signum in signals:
        if signum in _INSTALLED:
            continue
        previous = signal.getsignal(signum)
        _INSTALLED[signum] = previous

        def handler(num, frame, previous=previous):
            remove_temporary_files()
            if callable(previous) and previous not in (signal.SIG_IGN, signal.SIG_DFL):
                previous(num, frame)
            raise SystemExit(128 + num)

        signal.signal(signum, handler)


@contextlib.contextmanager
def signal_cleanup(signals: Sequence[int] = (signal.SIGTERM,)) -> Iterator[None]:
    """Within the block, SIGTERM removes live temporary outputs and exits ``128 + signum``.

    The previous handlers are restored on leaving.  Outside the main thread
    (where Python cannot set handlers) it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in signals}

    def handler(num, frame):
        remove_temporary_files()
        raise SystemExit(128 + num)

    for s in signals:
        signal.signal(s, handler)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


# -- atomic writes ----------------------------------------------------------------


def _folder(path: Path) -> Path:
    return path.parent if str(path.parent) else Path(".")


def _disk_message(path: Path, exc: OSError) -> str:
    if exc.errno == errno.ENOSPC:
        return f"cannot write {path}: the disk is full; free space or choose another folder (nothing was written)"
    if exc.errno == errno.EFBIG:
        limit = "the file size limit was reached (ulimit -f)"
        with contextlib.suppress(ImportError, OSError, ValueError):
            import resource

            soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
            if soft != resource.RLIM_INFINITY:
                limit = f"the file size limit (ulimit -f) is {soft:,} bytes"
        return f"cannot write {path}: {limit}; raise it or choose another folder (nothing was written)"
    if exc.errno == errno.EDQUOT:
        return f"cannot write {path}: disk quota exceeded; free space or choose another folder (nothing was written)"
    return f"cannot write {path}: {exc.strerror or exc}; nothing was written"


def _disk_error(path: Path, exc: OSError) -> OSError:
    """The error for a write the disk or a limit stopped: :func:`_disk_message`, with the errno kept."""
    err = OSError(_disk_message(path, exc))
    err.errno = exc.errno
    return err


def _cause(path: Path, size: int = 0) -> str:
    """Why a write may have come out short: the file-size limit, or free disk space."""
    causes = []
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if soft != resource.RLIM_INFINITY:
            causes.append(f"the file size limit (ulimit -f) is {soft:,} bytes: raise it")
    except (ImportError, OSError, ValueError):
        pass
    try:
        st = os.statvfs(_folder(path))
        free = st.f_bavail * st.f_frsize
        if free < max(size, 1) * 2 + 2**20:
            causes.append(f"the disk is full ({free:,} bytes free): free space")
    except OSError:
        pass
    return "; ".join(causes) if causes else "disk full or a writer failure"


def write_failed(path: str | os.PathLike, what: str, size: int = 0) -> OSError:
    """The error for an output that did not come out whole, naming the likely cause."""
    path = Path(path)
    return OSError(f"cannot write {path}: {what}; {_cause(path, size)} (nothing was written)")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, verify: Callable[[str], None] | None = None) -> Iterator[str]:
    """Yield a temporary path beside ``path``; check it, then rename it onto ``path``.

    The temporary keeps the final suffix, so writers that choose the format
    by extension (Open3D) work.  After the ``with`` block the temporary must
    exist and be non-empty, ``verify(tmp)`` (if given) must not raise, and it
    is flushed to disk before the rename.  On any exception (and on SIGTERM
    with :func:`install_signal_cleanup`) the temporary is removed and
    ``path`` is left as it was.

    Raises
    ------
    FileNotFoundError
        The target folder does not exist.
    OSError
        The writer produced nothing, or the disk is full / the file-size
        limit was reached (the message says which).
    """
    path = Path(path)
    parent = _folder(path)
    if not parent.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {parent}; create it first")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=parent)
    except OSError as exc:
        raise _disk_error(path, exc) from None
    os.close(fd)
    with _LOCK:
        _LIVE.add(tmp)
    try:
        try:
            yield tmp
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT):
                raise _disk_error(path, exc) from None
            raise
        if not os.path.isfile(tmp) or os.path.getsize(tmp) == 0:
            raise write_failed(path, "the writer produced an empty file")
        if verify is not None:
            verify(tmp)
        try:
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        except OSError as exc:
            raise _disk_error(path, exc) from None
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    finally:
        with _LOCK:
            _LIVE.discard(tmp)


# -- output checks --------------------------------------------------------------------


def _same(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.abspath(os.path.realpath(a)) == os.path.abspath(os.path.realpath(b))


#: Readers ``f(path) -> list[Path]`` of the files an input refers to (the
#: scans of a .conf, the images of a calibration).  :mod:`o3drbf.cameras.formats`,
#: a layer above, registers its reader here when it is imported.
REFERENCED_FILES: list = []


def _referenced(inp: Path) -> list[Path]:
    """``inp`` and the files it refers to (see :data:`REFERENCED_FILES`)."""
    files = [inp]
    for reader in REFERENCED_FILES:
        try:
            files += reader(inp)
        except (ValueError, OSError):
            pass  # an unreadable input is reported by its reader, later
    return files


def check_outputs(outputs: Iterable, inputs: Iterable = ()) -> list[Path]:
    """Refuse unsafe outputs before any costly step.

    Parameters
    ----------
    outputs : iterable of path-like or None
        Files about to be written (``None`` entries are skipped).
    inputs : iterable of path-like or None
        Files or folders read; an output may not be one of them, nor any
        file they refer to (the scans listed by a Stanford ``.conf``, the
        images of a calibration, a COLMAP model's files).

    Returns
    -------
    list of Path
        The outputs, in order.

    Raises
    ------
    ValueError
        An output is an input or a file an input refers to, a folder, or
        is given twice.
    FileNotFoundError
        An output's folder does not exist.
    PermissionError
        An output's folder (or an existing output) is not writable.
    """
    outs = [Path(o) for o in outputs if o is not None]
    protected = []
    for inp in inputs:
        if inp is None:
            continue
        protected += _referenced(Path(inp))
    for i, out in enumerate(outs):
        if out.is_dir():
            raise ValueError(f"output {str(out)!r} is a folder; give a file name")
        for other in outs[:i]:
            if _same(out, other):
                raise ValueError(f"output {str(out)!r} is given twice; choose different names")
        for inp in protected:
            if _same(out, inp):
                what = "the input file" if inp in [Path(x) for x in inputs if x is not None] else f"a file an input refers to ({inp})"
                raise ValueError(f"output {str(out)!r} is {what}; choose another name (inputs are never overwritten)")
        parent = _folder(out)
        if not parent.is_dir():
            raise FileNotFoundError(f"output folder does not exist: {parent}; create it first")
        # the mode bits too: a folder marked read-only is refused even for root
        if not os.access(parent, os.W_OK | os.X_OK) or not parent.stat().st_mode & 0o222:
            raise PermissionError(f"output folder {parent} is not writable; choose another folder for {out.name}")
        if out.exists() and (not os.access(out, os.W_OK) or not out.stat().st_mode & 0o222):
            raise PermissionError(f"output {str(out)!r} exists and is read-only; remove it or choose another name")
    return outs


def check_output(output: str | os.PathLike, inputs: Iterable = (), formats: Sequence[str] = MESH_FORMATS) -> Path:
    """Validate one output path: known extension, and the checks of :func:`check_outputs`."""
    out = Path(output)
    if out.suffix.lower() not in formats:
        hint = " (Open3D cannot read back the .glb it writes: use .gltf or .ply)" if out.suffix.lower() == ".glb" else ""
        raise ValueError(f"output {str(out)!r} has an unsupported extension; valid: {', '.join(formats)}{hint}")
    return check_outputs([out], inputs)[0]


# -- precision ----------------------------------------------------------------------


def _precision_error(suffix: str, vertices: np.ndarray, folder: Path) -> float:
    """Largest coordinate error after a write/read round trip of ``vertices`` in ``suffix`` (none in .ply:
    :func:`write_mesh` writes its coordinates as doubles)."""
    if suffix == ".ply":
        return 0.0
    import open3d as o3d

    v = np.asarray(vertices, dtype=float).reshape(-1, 3)
    tri = np.arange(len(v) - len(v) % 3, dtype=np.int32).reshape(-1, 3)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(tri))
    mesh.compute_triangle_normals()
    fd, tmp = tempfile.mkstemp(prefix=".o3drbf-precision.", suffix=suffix, dir=folder)
    os.close(fd)
    with _LOCK:
        _LIVE.add(tmp)
    try:
        if not o3d.io.write_triangle_mesh(tmp, mesh):
            return float("inf")
        back = np.asarray(o3d.io.read_triangle_mesh(tmp).vertices, dtype=float)
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        with _LOCK:
            _LIVE.discard(tmp)
    return _vertex_error(v, back)


def _vertex_error(original: np.ndarray, back: np.ndarray) -> float:
    """Symmetric largest nearest-neighbour distance (formats may reorder or unshare vertices)."""
    if len(back) == 0:
        return float("inf") if len(original) else 0.0
    if back.shape == original.shape:  # same order (PLY, OFF): no search needed
        direct = float(np.abs(back - original).max(initial=0.0))
        if direct == 0.0:
            return 0.0
    from scipy.spatial import cKDTree

    d1 = cKDTree(original).query(back)[0].max()
    d2 = cKDTree(back).query(original)[0].max()
    return float(max(d1, d2))


def _probe(points: np.ndarray) -> np.ndarray:
    """The 8 bounding-box corners and the centre, as 9 vertices (3 triangles)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    centre = (lo + hi) / 2.0
    # nudge off round numbers so the probe sees the format's real resolution
    size = max(float(np.linalg.norm(hi - lo)), 1e-300)
    jitter = size * np.array([0.1234567, 0.2345678, 0.3456789])
    return np.vstack([corners + np.array([[1, -1, 1]]) * jitter * 1e-3, centre + jitter * 1e-3])


def check_mesh_precision(path: str | os.PathLike, points, tolerance: float = PRECISION_TOLERANCE, action: str = "error") -> float:
    """Check that ``path``'s format can hold coordinates like ``points`` to ``tolerance``.

    Writes a 9-vertex probe (the points' bounding box) in the output's format
    beside the output, reads it back and measures the largest coordinate
    error relative to the bounding-box diagonal.  Call it before the costly
    steps, with the input points (the mesh lies in their box).

    Parameters
    ----------
    path : path-like
        The output mesh file (its suffix chooses the format).
    points : (N, 3) array
    tolerance : float
        Largest error allowed, relative to the box diagonal.
    action : {"error", "warn"}

    Returns
    -------
    float
        The relative error measured.

    Raises
    ------
    ValueError
        ``action="error"`` and the format loses more than ``tolerance``.
    """
    from o3drbf.validation import as_points

    path = Path(path)
    pts = as_points(points)
    diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    probe = _probe(pts)
    err = _precision_error(path.suffix.lower(), probe, _folder(path))
    rel = err / diag if diag > 0 else (0.0 if err == 0 else float("inf"))
    if rel > tolerance:
        offset = float(np.abs(pts).max())
        msg = (
            f"output {path}: the {path.suffix} format would move vertices by up to {err:.3g} "
            f"({rel:.2g} of the mesh size; coordinates up to {offset:.3g}); use .ply (float64) or move the data near the origin"
        )
        if action == "warn":
            warnings.warn(msg, stacklevel=2)
        else:
            raise ValueError(msg)
    return rel


# -- readers ------------------------------------------------------------------------

_TEXT_COLUMNS = {".xyz": (3,), ".xyzn": (6,), ".xyzrgb": (6,), ".pts": (3, 4, 6, 7)}


def _check_text_columns(path: Path, allowed: tuple[int, ...]) -> None:
    """Refuse a text point file whose lines have mixed or unexpected column counts, naming the line."""
    first = None
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, start=1):
            tok = line.split()
            if not tok or tok[0].startswith("#"):
                continue
            if path.suffix.lower() == ".pts" and first is None and len(tok) == 1:
                continue  # the count line of some .pts files
            if first is None:
                first = (lineno, len(tok))
                if len(tok) not in allowed:
                    raise ValueError(f"{path}, line {lineno}: {len(tok)} columns; a {path.suffix} file has {' or '.join(map(str, allowed))}")
            elif len(tok) != first[1]:
                raise ValueError(f"{path}, line {lineno}: {len(tok)} columns, but line {first[0]} has {first[1]} (mixed column counts); fix the file")
            for s in tok if lineno <= 1000 else ():  # Open3D parses the rest; spot-check the start
                try:
                    float(s)
                except ValueError:
                    raise ValueError(f"{path}, line {lineno}: {s!r} is not a number") from None
    if first is None:
        raise ValueError(f"{path}: no points (truncated or empty file)")


def point_count(path: str | os.PathLike) -> int | None:
    """Points a PLY, LAS, LAZ or E57 file's header announces (without reading them); None for other formats,
    unreadable headers or a PLY shorter than its header announces (the reader then names the problem)."""
    path = Path(path)
    from o3drbf.io.lidar import LIDAR_FORMATS, lidar_point_count

    if path.suffix.lower() in LIDAR_FORMATS:
        return lidar_point_count(path)
    if path.suffix.lower() != ".ply" or not path.is_file():
        return None
    try:
        check_ply_header(path)
        h = ply_header(path)
    except (OSError, ValueError):
        return None
    return next((count for name, count, _ in h["elements"] if name == "vertex"), None)

def read_points(path: str | os.PathLike):
    """Read a point cloud file (PLY, PCD, XYZ, XYZN, XYZRGB, PTS; LAS and LAZ with :func:`o3drbf.io.lidar.read_las`).

    Returns
    -------
    points : (N, 3) array
    normals : (N, 3) array or None
    colors : (N, 3) array in [0, 1] or None

    Raises
    ------
    FileNotFoundError, ValueError
        Missing, unreadable, truncated or empty files, mixed column counts
        and non-finite coordinates, with the path (and line) in the message.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> from o3drbf.io.files import read_points, write_points
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> path = write_points(pathlib.Path(tempfile.mkdtemp()) / 'sphere.xyz', Sphere(1.0).sample(100, seed=0)[0])
    >>> points, normals, colors = read_points(path)
    >>> points.shape, normals, colors
    ((100, 3), None, None)
    """
    from o3drbf.validation import as_points

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"input file not found: {path}")
    if path.is_dir():
        raise ValueError(f"input {path} is a folder; give a point cloud file ({', '.join(POINT_FORMATS)})")
    suffix = path.suffix.lower()
    from o3drbf.io.lidar import LAS_FORMATS, read_las

    if suffix in LAS_FORMATS:
        points, colors = read_las(path)
        return points, None, colors
    if suffix not in POINT_FORMATS:
        raise ValueError(f"cannot read {path}: unsupported extension {path.suffix!r}; valid: {', '.join(POINT_FORMATS + LAS_FORMATS)} "
                         "(and .e57 as an input with its scans)")
    try:
        with open(path, "rb") as fh:
            fh.read(1)
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror}") from None
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: no points (truncated or empty file)")
    plain = None
    if suffix == ".ply":
        check_ply_header(path)
        plain = read_plain_ply(path)  # a binary point cloud without Open3D (most PLY clouds)
    elif suffix in _TEXT_COLUMNS:
        _check_text_columns(path, _TEXT_COLUMNS[suffix])
    if plain is not None:
        pts, normals, colors = plain
    else:
        import open3d as o3d

        pcd = o3d.io.read_point_cloud(str(path))
        pts = np.asarray(pcd.points, dtype=float)
        normals = np.asarray(pcd.normals, dtype=float) if pcd.has_normals() else None
        colors = np.asarray(pcd.colors, dtype=float) if pcd.has_colors() else None
    if len(pts) == 0:
        raise ValueError(f"{path}: no points (truncated or empty file, or not a readable {path.suffix} file)")
    try:
        pts = as_points(pts, name=str(path))
    except ValueError as exc:
        raise ValueError(f"{exc}; fix or remove those rows") from None
    if normals is not None and not np.isfinite(normals).all():
        raise ValueError(f"{path}: normals have NaN or infinite entries; fix the file or drop its normals")
    return pts, normals, colors


# -- writers ------------------------------------------------------------------------


def write_points(path: str | os.PathLike, points, normals=None, colors=None, inputs: Iterable = ()) -> Path:
    """Write a point cloud atomically (format from the extension), checked by reading it back.

    Parameters
    ----------
    path : path-like
    points : (N, 3) array
    normals, colors : (N, 3) arrays, optional
    inputs : iterable of path-like
        Files the output must not overwrite.
    """
    import open3d as o3d

    path = check_output(path, inputs=inputs, formats=POINT_FORMATS)
    pts = np.asarray(points, dtype=float)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=float))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=float))

    def verify(tmp):
        back = o3d.io.read_point_cloud(tmp)
        if len(back.points) != len(pts):
            raise write_failed(path, f"read back {len(back.points)} of {len(pts)} points", os.path.getsize(tmp))

    with atomic_path(path, verify=verify) as tmp:
        if not o3d.io.write_point_cloud(tmp, pcd):
            raise write_failed(path, "Open3D could not write it")
    return path


def write_mesh(path: str | os.PathLike, mesh, inputs: Iterable = (), tolerance: float = PRECISION_TOLERANCE,
               vertex_fields: dict | None = None) -> Path:
    """Write a triangle mesh atomically (format from the extension).

    A ``.ply`` is written by o3drbf (binary, little-endian: vertex x y z and
    normals as doubles, colours as bytes, triangles as int lists) and read
    back before the rename, every value compared; other formats are written
    by Open3D and read back by it: the triangle count must match and no
    vertex may have moved by more than ``tolerance`` times the bounding-box
    diagonal (formats with float32 or few printed digits lose coordinates far
    from the origin).

    Parameters
    ----------
    path : str or PathLike
    mesh : open3d.geometry.TriangleMesh or MeshArrays
    inputs : iterable of paths
        Files the output must not overwrite.
    tolerance : float
    vertex_fields : dict of str -> (V,) array_like, optional
        Extra per-vertex scalars (e.g. ``{"confidence": c}``), written as
        ``float`` PLY vertex properties after x y z (double), normals and
        colours; ``.ply`` only.  Readable with plyfile or
        ``open3d.t.io.read_point_cloud``; Open3D's mesh readers ignore them.

    Raises
    ------
    ValueError
        The format cannot hold the coordinates (use ``.ply``), or vertex
        fields for a format other than ``.ply``, or of the wrong length.
    OSError
        Open3D failed, or the file read back differs (disk full...).
    """
    path = check_output(path, inputs=inputs)
    fields = _vertex_fields(path, mesh, vertex_fields)
    if path.suffix.lower() == ".ply":  # (the check runs after the block, on the records it wrote)
        with atomic_path(path, verify=lambda tmp: _check_ply(tmp, path, records)) as tmp:
            records = _write_ply(tmp, mesh, fields)
        return path
    import open3d as o3d

    if not hasattr(mesh, "compute_triangle_normals"):  # MeshArrays
        mesh = mesh.to_open3d()
    if path.suffix.lower() == ".stl" and not mesh.has_triangle_normals():
        mesh.compute_triangle_normals()
    v = np.asarray(mesh.vertices, dtype=float)
    n_tri = len(mesh.triangles)

    def verify(tmp):
        back = o3d.io.read_triangle_mesh(tmp)
        if len(back.triangles) != n_tri:
            raise write_failed(path, f"read back {len(back.triangles)} of {n_tri} triangles", os.path.getsize(tmp))
        if len(v):
            diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
            err = _vertex_error(v, np.asarray(back.vertices, dtype=float))
            if err > tolerance * max(diag, np.finfo(float).tiny):
                raise ValueError(
                    f"output {path}: the {path.suffix} format moved vertices by up to {err:.3g} "
                    f"({err / diag if diag else float('inf'):.2g} of the mesh size); use .ply (float64) or move the data near the origin"
                )

    with atomic_path(path, verify=verify) as tmp:
        if not o3d.io.write_triangle_mesh(tmp, mesh):
            raise write_failed(path, "Open3D could not write it")
    return path


def _vertex_fields(path: Path, mesh, vertex_fields: dict | None) -> dict:
    """The extra vertex properties as float32 arrays, checked against the mesh and the format."""
    if not vertex_fields:
        return {}
    if path.suffix.lower() != ".ply":
        raise ValueError(f"output {path}: per-vertex properties ({', '.join(vertex_fields)}) need a .ply output; use a .ply file name")
    n = len(mesh.vertices)
    out = {}
    for name, values in vertex_fields.items():
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", str(name)) or name in ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"):
            raise ValueError(f"vertex property name {name!r} is not a new PLY identifier; use letters, digits and '_'")
        a = np.asarray(values, dtype=np.float32).ravel()
        if len(a) != n:
            raise ValueError(f"vertex property {name!r} has {len(a)} values for {n} vertices; give one per vertex")
        out[str(name)] = a
    return out


def _write_ply(path: str, mesh, fields: dict) -> tuple[np.ndarray, np.ndarray]:
    """Binary little-endian PLY: x y z (double), normals (double), colours (uchar), the fields (float), triangles.
    Returns the vertex and face records written (for :func:`_check_ply`)."""
    v = np.asarray(mesh.vertices, dtype=float)
    t = np.asarray(mesh.triangles, dtype=np.int64)
    columns = [("x", "<f8", v[:, 0]), ("y", "<f8", v[:, 1]), ("z", "<f8", v[:, 2])]
    if mesh.has_vertex_normals():
        nrm = np.asarray(mesh.vertex_normals, dtype=float)
        columns += [(k, "<f8", nrm[:, i]) for i, k in enumerate(("nx", "ny", "nz"))]
    if mesh.has_vertex_colors():
        rgb = np.round(np.clip(np.asarray(mesh.vertex_colors, dtype=float), 0.0, 1.0) * 255).astype(np.uint8)
        columns += [(k, "u1", rgb[:, i]) for i, k in enumerate(("red", "green", "blue"))]
    columns += [(name, "<f4", values) for name, values in fields.items()]
    vertex = np.empty(len(v), dtype=[(name, dt) for name, dt, _ in columns])
    for name, _, values in columns:
        vertex[name] = values
    face = np.empty(len(t), dtype=[("n", "u1"), ("index", "<i4", (3,))])
    face["n"] = 3
    face["index"] = t
    kind = {"<f8": "double", "u1": "uchar", "<f4": "float"}
    header = ["ply", "format binary_little_endian 1.0", "comment written by o3drbf", f"element vertex {len(v)}"]
    header += [f"property {kind[dt]} {name}" for name, dt, _ in columns]
    header += [f"element face {len(t)}", "property list uchar int vertex_indices", "end_header"]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vertex.tobytes())
        fh.write(face.tobytes())
    return vertex, face


def _check_ply(tmp: str, path: Path, records: tuple[np.ndarray, np.ndarray]) -> None:
    """Read back the PLY :func:`_write_ply` wrote: its header's counts and every record, byte for byte."""
    vertex, face = records
    data = Path(tmp).read_bytes()
    end = data.find(b"end_header\n")
    body = data[end + len(b"end_header\n"):] if end >= 0 else b""
    header = data[:end].decode("ascii", errors="replace")
    counts = re.findall(r"element (vertex|face) (\d+)", header)
    if counts != [("vertex", str(len(vertex))), ("face", str(len(face)))] or len(body) != vertex.nbytes + face.nbytes:
        raise write_failed(path, f"read back {len(body):,} bytes of data, {vertex.nbytes + face.nbytes:,} written", len(data))
    if body[: vertex.nbytes] != vertex.tobytes() or body[vertex.nbytes:] != face.tobytes():
        raise write_failed(path, "the records read back differ from those written", len(data))
