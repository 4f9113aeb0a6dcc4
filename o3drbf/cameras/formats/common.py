"""What every camera-file reader shares: errors that name the file and line, lines read, image sizes from headers."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["Where", "content_lines", "image_size_of", "read_lines"]


class Where:
    """Prefixes errors with the file and the line or entry they concern."""

    def __init__(self, path: Path):
        self.path = path

    def error(self, where: str | None, message: str) -> ValueError:
        return ValueError(f"{self.path}{', ' + where if where else ''}: {message}")

    def floats(self, tokens: Sequence[str], where: str, what: str) -> np.ndarray:
        try:
            vals = np.array([float(s) for s in tokens])
        except ValueError:
            raise self.error(where, f"{what}: expected numbers, got {' '.join(tokens)!r}") from None
        if not np.isfinite(vals).all():
            raise self.error(where, f"{what}: NaN or infinite value in {' '.join(tokens)!r}")
        return vals


def read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror}") from None


def content_lines(path: Path):
    """(line number, text) of lines that are not comments, blanks kept."""
    return [(i + 1, s) for i, s in enumerate(read_lines(path)) if not s.lstrip().startswith("#")]


def image_size_of(path: Path) -> tuple[int, int] | None:
    """(width, height) of an image file from its header (Pillow, lazy: no pixels decoded), or None if unknown."""
    if not path.is_file():
        return None
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, ValueError):  # unreadable, or not an image format Pillow knows
        return None

