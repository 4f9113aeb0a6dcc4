"""The comparison's outputs: ``comparison.md`` for people, ``comparison.csv``/``.json`` with the raw :data:`COLUMNS`,
and ``comparison.png`` (one row per method, one column per view).

:func:`o3drbf.evaluation.compare.compare` makes the rows these functions write.
"""

from __future__ import annotations

import csv
import io as _io
import json
from pathlib import Path

import numpy as np

from o3drbf.options import DEFAULTS

__all__ = ["COLUMNS", "LABELS", "HUMAN_COLUMNS", "TABLE_NOTES", "VIEWS", "method_label", "settings_line", "markdown_table", "write_tables",
           "row_title", "colour_range", "picture_panels", "picture"]

#: Table columns, in order (every row has every key; missing values are None).
COLUMNS = (
    "method",
    "seconds",
    "peak_mb",
    "rss_peak_mb",
    "triangles",
    "vertices",
    "watertight",
    "components",
    "euler_characteristic",
    "genus",
    "fitness_mean",
    "fitness_rms",
    "average_curvature",
    "chamfer_l1",
    "chamfer_l2",
    "hausdorff",
    "f_score",
    "precision",
    "recall",
    "f_threshold",
    "normal_consistency",
    "error",
)

#: Human names of the methods (kernels registered later: ``o3drbf <name>``).
LABELS = {
    "multiorder": "o3drbf multi-order",
    "thinplate": "o3drbf thin-plate",
    "gaussian": "o3drbf Gaussian",
    "poisson": "Open3D Poisson (raw points)",
    "poisson-tutorial": "Open3D Poisson (tutorial: outlier removal + density trim)",
    "bpa": "Open3D ball pivoting",
    "alpha": "Open3D alpha shape",
}

#: ``comparison.md``'s columns: raw key -> header (with units).  Left out of
#: it (kept in the CSV/JSON): ``peak_mb`` (tracemalloc, Python only),
#: ``vertices``, ``fitness_rms``, ``chamfer_l2`` and ``f_threshold`` (one
#: value, in the line above the table).
HUMAN_COLUMNS = {
    "method": "Method",
    "seconds": "Time (s)",
    "rss_peak_mb": "Peak memory (MB)",
    "triangles": "Triangles",
    "watertight": "Watertight",
    "components": "Pieces",
    "euler_characteristic": "Euler characteristic",
    "genus": "Genus",
    "fitness_mean": "Fitness mean (data units)",
    "average_curvature": "Mean curvature (1/data units)",
    "chamfer_l1": "Chamfer L1 (data units)",
    "hausdorff": "Hausdorff (data units)",
    "f_score": "F-score @ τ",
    "precision": "Precision @ τ",
    "recall": "Recall @ τ",
    "normal_consistency": "Normal consistency",
    "error": "Error",
}

#: The notes printed under the table.
TABLE_NOTES = (
    "Peak memory: growth of the process's resident memory while the method ran (psutil, sampled every 5 ms), "
    "Open3D's and Numba's compiled allocations included; methods run one after another, so memory an earlier "
    "method freed but the allocator kept is not counted again. (The Python-only tracemalloc peak is `peak_mb` "
    "in comparison.csv/json.)",
    "Chamfer L1: mean of the two mean surface-to-surface distances (the RMS version is `chamfer_l2` in the CSV); "
    "Hausdorff: the largest sampled distance. F-score, precision, recall: fractions of points sampled on the "
    "two surfaces within τ of the other. Normal consistency: mean |cos| between matched normals (1 is best).",
    "Watertight: Open3D's is_watertight (closed, vertex-manifold, no self-intersections). Pieces: connected "
    "triangle clusters. Fitness: distance from the input points to the mesh.",
)

#: Views of :func:`picture`, left to right.
VIEWS = ("front", "side", "top", "below")


def method_label(name: str) -> str:
    """The human name of a method, ``(default)`` after the default kernel's."""
    label = LABELS.get(name, f"o3drbf {name}")
    return f"{label} (default)" if name == DEFAULTS["kernel"] else label


def _fmt(value) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _threshold(rows):
    values = {r.get("f_threshold") for r in rows} - {None}
    return values.pop() if len(values) == 1 else None


def settings_line(rows, points: int | None = None, reference: str | None = None, threshold: float | None = None) -> str:
    """The one line of settings shared by every row (above the table, on the picture).

    ``threshold`` defaults to the rows' ``f_threshold`` (the F-score's τ).
    """
    threshold = _threshold(rows) if threshold is None else threshold
    parts = []
    if points is not None:
        parts.append(f"{int(points):,} input points")
    if reference is not None:
        parts.append(f"reference: {reference}")
    if threshold is not None:
        parts.append(f"τ = {_fmt(float(threshold))} data units (1% of the reference's bounding-box diagonal)")
    elif reference is None:
        parts.append("no reference mesh: no Chamfer/F-score")
    return " · ".join(parts)


def markdown_table(rows, points: int | None = None, reference: str | None = None) -> str:
    """``comparison.md``: a line of shared settings, the table, notes.

    Columns are :data:`HUMAN_COLUMNS` (those with no value in any row are
    left out); methods by :func:`method_label`; numbers to 4 significant
    digits.
    """
    cols = [c for c in HUMAN_COLUMNS if c == "method" or any(r.get(c) is not None for r in rows)]
    lines = [settings_line(rows, points, reference), "", "| " + " | ".join(HUMAN_COLUMNS[c] for c in cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for r in rows:
        cells = [method_label(r["method"]) if c == "method" else _fmt(r.get(c)) for c in cols]
        lines.append("| " + " | ".join(cell.replace("|", "/") for cell in cells) + " |")
    for note in (note for c, note in zip(("rss_peak_mb", "chamfer_l1", "watertight"), TABLE_NOTES) if c in cols):
        lines.extend(("", note))
    return "\n".join(lines) + "\n"


def write_tables(rows, out_dir, stem: str = "comparison", points: int | None = None, reference: str | None = None) -> dict:
    """Write ``comparison.md``, ``comparison.csv`` and ``comparison.json``.

    Each file is written atomically.  The markdown is
    :func:`markdown_table` (human headers, ``points`` and ``reference``
    named in its first line); the JSON holds the rows exactly (a list of
    objects with the raw keys :data:`COLUMNS`, ``null`` for missing values);
    the CSV has a header with :data:`COLUMNS` and empty cells for missing
    values.

    Returns
    -------
    dict
        ``{"markdown": Path, "csv": Path, "json": Path}``.
    """
    from o3drbf.io.files import atomic_path

    out = Path(out_dir)
    if not out.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {out}")
    rows = [{c: r.get(c) for c in COLUMNS} for r in rows]
    paths = {"markdown": out / f"{stem}.md", "csv": out / f"{stem}.csv", "json": out / f"{stem}.json"}
    buf = _io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(COLUMNS), lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({c: "" if v is None else v for c, v in r.items()})
    texts = {"markdown": markdown_table(rows, points, reference), "csv": buf.getvalue(), "json": json.dumps(rows, indent=2, allow_nan=False) + "\n"}
    for key, path in paths.items():
        with atomic_path(path) as tmp:
            Path(tmp).write_text(texts[key], encoding="utf-8")
    return paths


def _wrap(text: str, width: int = 40) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width)[:3])


def row_title(row: dict) -> str:
    """The title of a method's row in :func:`picture`: its name (wrapped at
    36 characters), then the table's Chamfer L1, F-score, watertight and
    pieces (as in the table)."""
    lines = [_wrap(method_label(row["method"]), 36)]  # long labels on two lines: a panel is narrow
    if row.get("error"):
        return lines[0] + "\n" + _wrap("FAILED: " + row["error"])
    if row.get("chamfer_l1") is not None:
        lines.append(f"Chamfer L1 {_fmt(row['chamfer_l1'])}, F-score {_fmt(row.get('f_score'))}")
    pieces = row.get("components")
    if row.get("watertight") is not None and pieces is not None:
        lines.append(f"watertight {_fmt(row['watertight'])}, {pieces} piece{'' if pieces == 1 else 's'}")
    if row.get("seconds") is not None:
        lines.append(f"{_fmt(row['seconds'])} s, {_fmt(row.get('triangles'))} triangles")
    return "\n".join(lines)


def colour_range(rows) -> tuple[float, float] | None:
    """The shared range of the distance colours: ``(0, 2 τ)`` (τ the F-score
    threshold: the bar's middle), or None without a reference."""
    threshold = _threshold(rows)
    return None if threshold is None else (0.0, 2.0 * float(threshold))


def picture_panels(rows, meshes: dict, points=None, truth=None, reference: str | None = None, max_points: int = 200_000):
    """The panels of :func:`picture`: ``(rows of Panel, header text, colour range, bounds)``.

    One row for the input points, one for the reference (``truth``, when
    given), then one per method in ``rows``' order; one column per view of
    :data:`VIEWS`.  The first panel of each row carries the title
    (:func:`row_title` for methods).  With a reference, method meshes are
    coloured by each vertex's distance to it on :func:`colour_range`.
    Every panel frames ``bounds`` ``(6,)``: the reference's box, else the
    input points' 1st to 99th percentiles (stray outliers and a method's
    far-off pieces fall outside; the titles still count them), padded by 5%;
    None (everything drawn) without either.
    """
    from o3drbf.mesh.metrics import point_distances
    from o3drbf.pictures import Panel

    def line(title, **kw):
        return [Panel(title if j == 0 else "", view=v, **kw) for j, v in enumerate(VIEWS)]

    clim = colour_range(rows) if truth is not None else None
    grid_rows = []
    if points is not None:
        pts = np.asarray(points, dtype=float)
        shown = pts[:: max(1, -(-len(pts) // max_points))]
        title = f"input: {len(pts):,} points" + ("" if len(shown) == len(pts) else f" ({len(shown):,} drawn)")
        grid_rows.append(line(title, points=shown))
    if truth is not None:
        grid_rows.append(line(f"reference{'' if reference is None else ': ' + reference}\n{len(truth.triangles):,} triangles", mesh=truth))
    for row in rows:
        mesh = meshes.get(row["method"])
        ok = mesh is not None and len(mesh.triangles) > 0
        if not ok and not row.get("error"):
            row = {**row, "error": "no mesh"}
        scalars = point_distances(np.asarray(mesh.vertices), truth) if ok and clim is not None else None
        grid_rows.append(line(row_title(row), mesh=mesh if ok else None, scalars=scalars))
    head = ["o3drbf compare" + ("" if points is None else f": {len(points):,} input points") + ("" if reference is None else f", reference {reference}")]
    if clim is not None:
        head.append(f"F-score threshold tau = {_fmt(clim[1] / 2)} data units (1% of the reference's diagonal)")
        head.append("colour: distance to the reference, one scale for every method;")
        head.append("yellow: 2 tau or more")
    else:
        head.append("no reference: red = pieces besides the largest,")
        head.append("orange = back faces (insides seen through holes)")
    head.append("red under a see-through piece: pieces hidden inside it")
    header = "\n".join(head)
    bounds = None
    if truth is not None:
        tv = np.asarray(truth.vertices)
        lo, hi = tv.min(axis=0), tv.max(axis=0)
    elif points is not None:
        lo, hi = np.percentile(np.asarray(points, dtype=float), [1, 99], axis=0)
    if truth is not None or points is not None:
        pad = 0.05 * (hi - lo).max()
        bounds = tuple(float(b) for b in np.column_stack([lo - pad, hi + pad]).ravel())
    return grid_rows, header, clim, bounds


def picture(meshes: dict, path, points=None, rows=None, truth=None, reference: str | None = None, viewup=(0.0, 0.0, 1.0), panel_size: int = 300) -> Path:
    """The comparison picture: one row per method, one column per view.

    Rows (:func:`picture_panels`): the input points, the reference when
    given, then each method, titled with its table numbers; columns:
    :data:`VIEWS` (front, side, top, below).  The PNG is
    ``(len(VIEWS) * panel_size, HEADER_HEIGHT + n_rows * panel_size)``
    pixels (:data:`o3drbf.pictures.HEADER_HEIGHT`).

    Parameters
    ----------
    meshes : dict
        ``{method: mesh or None}`` (None: failed, an empty row).
    path : str or Path
        A ``.png``.
    points : (N, 3) array, optional
    rows : list of dict, optional
        :func:`compare`'s rows for the titles (default: names only).
    truth : open3d.geometry.TriangleMesh, optional
    reference : str, optional
        The reference's name, for the header.
    viewup : 3-tuple
        The data's up axis.
    """
    from o3drbf.pictures import grid

    if not meshes:
        raise ValueError("no meshes to draw")
    if rows is None:
        rows = [{"method": name, "error": None if m is not None and len(m.triangles) else "no mesh"} for name, m in meshes.items()]
    panels, header, clim, bounds = picture_panels(rows, meshes, points, truth, reference)
    return grid(panels, path, panel_size=panel_size, header=header, clim=clim, colour_label="distance to reference (data units)", viewup=viewup, bounds=bounds)
