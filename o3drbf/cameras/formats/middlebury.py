"""Middlebury multi-view calibrations (``*_par.txt``): the image count, then ``imgname k11..k33 r11..r33 t1 t2 t3`` per line."""

from __future__ import annotations

from pathlib import Path

from o3drbf.cameras.formats.common import Where, image_size_of, read_lines
from o3drbf.cameras.model import Camera, CameraSet

__all__ = ["read", "referenced"]


def read(path: Path, image_size=None, read_scans: bool = False) -> CameraSet:
    """Read a Middlebury calibration: the image count, then ``name K(9) R(9) t(3)`` per line.

    A reader of :data:`o3drbf.cameras.formats.FORMATS`: a :class:`~o3drbf.cameras.model.CameraSet`, or
    :class:`ValueError` naming the file and the line or entry.

    Parameters
    ----------
    path : Path
        The ``*_par.txt`` file.
    image_size : (int, int), optional
        ``(width, height)`` when the images are not beside the file (else read from them, or left unbounded).
    """
    w = Where(path)
    lines = [(i + 1, s.split()) for i, s in enumerate(read_lines(path)) if s.strip()]
    if not lines:
        raise w.error(None, "empty file; expected the image count on line 1")
    lineno, first = lines[0]
    if len(first) != 1 or not first[0].isdigit():
        raise w.error(f"line {lineno}", f"expected the image count, got {' '.join(first)!r}")
    count = int(first[0])
    cameras = []
    for lineno, tok in lines[1:]:
        where = f"line {lineno}"
        if len(tok) != 22:
            raise w.error(where, f"expected 'imgname k11..k33 r11..r33 t1 t2 t3' (22 fields), got {len(tok)}")
        v = w.floats(tok[1:], where, f"calibration of {tok[0]}")
        size = image_size or image_size_of(path.parent / tok[0])
        try:
            cameras.append(
                Camera(
                    K=v[:9].reshape(3, 3),
                    R=v[9:18].reshape(3, 3),
                    t=v[18:21],
                    width=None if size is None else size[0],
                    height=None if size is None else size[1],
                    name=tok[0],
                )
            )
        except ValueError as exc:
            raise w.error(where, f"{tok[0]}: {exc}") from None
    if len(cameras) != count:
        raise w.error(None, f"line 1 announces {count} images but the file has {len(cameras)} calibration lines (count mismatch)")
    return CameraSet(cameras, source=str(path), format="middlebury")



def referenced(path: Path) -> list[Path]:
    """The images named on the calibration lines (beside the file)."""
    out = []
    for s in read_lines(path)[1:]:
        tok = s.split()
        if tok:
            out.append(path.parent / tok[0])
    return out
