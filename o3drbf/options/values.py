"""Option values from text: what a command-line flag or a config string holds.

Each function raises :class:`ValueError` with one line naming what was
expected; the command line (:mod:`o3drbf.cli.arguments`) turns that into
its usage error.
"""

from __future__ import annotations

__all__ = ["whole_number", "count_or_auto", "auto_or_bool", "box_or_rule", "rgb"]


def whole_number(text, low: int | None = 1, auto: bool = False):
    """A whole number >= ``low`` (None: any; or ``"auto"`` when ``auto``).

    Examples
    --------
    >>> whole_number("12"), count_or_auto("auto")
    (12, 'auto')
    """
    if auto and str(text).strip().lower() == "auto":
        return "auto"
    expected = "'auto' or a whole number" if auto else "a whole number"
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise ValueError(f"expected {expected}, got {text!r}") from None
    if low is not None and value < low:
        raise ValueError(f"expected {expected} >= {low}, got {value}")
    return value


def count_or_auto(text):
    """``"auto"`` or a whole number >= 1 (``--surface-count``, ``--resolution``, ``--tiles``)."""
    return whole_number(text, 1, auto=True)


def auto_or_bool(text):
    """``"auto"``, or on/off (yes/no, true/false, 1/0) as a bool (``--denoise``)."""
    t = str(text).strip().lower()
    if t == "auto":
        return "auto"
    if t in ("on", "yes", "true", "1"):
        return True
    if t in ("off", "no", "false", "0"):
        return False
    raise ValueError(f"expected auto, on or off, got {text!r}")


def _numbers(text) -> list[float]:
    return [float(s) for s in str(text).replace(",", " ").split()]


def box_or_rule(text, rules=("auto", "silhouettes")):
    """One of ``rules``, or a box of six numbers ``xmin ymin zmin xmax ymax zmax`` (``o3drbf photos --bounds``)."""
    if text in rules:
        return text
    try:
        values = _numbers(text)
    except ValueError:
        raise ValueError(f"expected {' or '.join(map(repr, rules))} or six numbers 'xmin ymin zmin xmax ymax zmax', got {text!r}") from None
    if len(values) != 6:
        raise ValueError(f"expected six numbers 'xmin ymin zmin xmax ymax zmax', got {len(values)}")
    return values


def rgb(text):
    """An RGB colour ``r,g,b`` with components in [0, 1] (``o3drbf photos --background``)."""
    try:
        values = _numbers(text)
    except ValueError:
        raise ValueError(f"expected an RGB colour 'r,g,b' in [0, 1], got {text!r}") from None
    if len(values) != 3 or min(values) < 0 or max(values) > 1:
        raise ValueError(f"expected an RGB colour 'r,g,b' with components in [0, 1], got {text!r}")
    return values
