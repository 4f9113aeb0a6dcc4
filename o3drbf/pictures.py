"""Pictures of meshes and points (PyVista, imported lazily: the rest of
o3drbf never needs it, so the library stays headless)."""

from __future__ import annotations

import os
from dataclasses import dataclass
import sys
from pathlib import Path

import numpy as np

from o3drbf.io.files import atomic_path

__all__ = ["headless", "to_pyvista", "side_by_side", "Panel", "grid", "views_around", "PIECE_COLOR", "HEADER_HEIGHT",
           "plot", "in_notebook", "jupyter_backend", "CONSTRAINT_COLORS", "CONSTRAINT_POINT_SIZE"]

#: Mesh, point and exterior colours of :func:`plot` and :func:`side_by_side`.
MESH_COLOR = "#c8d2e6"
POINT_COLOR = "#cc3311"
#: Surface constraints blue and exterior constraints green, as in the paper's Fig. 8: the same in
#: ``Reconstruction.plot(constraints=True)`` and in ``o3drbf view``.
CONSTRAINT_COLORS = {"surface": "#1f4fd8", "exterior": "#12a03c"}
#: Marker size (pixels) of constraints drawn over a surface: small enough to leave the surface visible.
CONSTRAINT_POINT_SIZE = 3.0


def headless() -> None:
    """Prepare VTK for rendering without a display; call before importing PyVista.

    Without ``DISPLAY``, asks VTK for an EGL window straight away (instead of
    failing over from X with a warning).  Only when the user has not chosen
    (``VTK_DEFAULT_OPENGL_WINDOW`` unset); otherwise does nothing.
    """
    if not os.environ.get("DISPLAY") and "VTK_DEFAULT_OPENGL_WINDOW" not in os.environ:
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"


def to_pyvista(mesh):
    """An Open3D TriangleMesh as a ``pyvista.PolyData``."""
    import pyvista as pv

    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.triangles)
    faces = np.column_stack([np.full(len(f), 3), f]).ravel()
    return pv.PolyData(v, faces)


def side_by_side(panels, path: str | os.PathLike, window_size=(1600, 800), points=None, view=(1.0, -1.2, 0.9), viewup=(0.0, 0.0, 1.0)) -> Path:
    """Render meshes side by side from the same viewpoint into a PNG (offscreen).

    Parameters
    ----------
    panels : list of (title, open3d.geometry.TriangleMesh)
    path : str or Path
        Output ``.png`` (written atomically).
    points : (N, 3) array, optional
        Input points, drawn small in the first panel.
    view : 3-tuple
        Camera direction from the centre of the scene.
    viewup : 3-tuple
        The data's up axis (e.g. (0, 1, 0) for the Stanford bunny).
    """
    headless()
    import pyvista as pv

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"picture must be a .png file, got {str(path)!r}")
    plotter = pv.Plotter(shape=(1, len(panels)), off_screen=True, window_size=list(window_size), border=False)
    for i, (title, mesh) in enumerate(panels):
        plotter.subplot(0, i)
        plotter.set_background("white")
        if mesh is not None and len(mesh.triangles):
            plotter.add_mesh(to_pyvista(mesh), color=MESH_COLOR, smooth_shading=True, specular=0.3)
        if points is not None and i == 0:
            plotter.add_points(np.asarray(points), color=POINT_COLOR, point_size=2, render_points_as_spheres=False)
        plotter.add_text(title, font_size=11, color="black")
        plotter.view_vector(view, viewup=viewup)
    plotter.link_views()
    with atomic_path(path) as tmp:
        plotter.screenshot(tmp)
    plotter.close()
    return path


#: Colour of the pieces of a mesh other than its largest (and of every piece
#: hidden inside another, seen through it).
PIECE_COLOR = "#e8112d"
#: Height in pixels of the header strip of :func:`grid` (settings and colour bar).
HEADER_HEIGHT = 130
_FRONT_COLOR, _BACK_COLOR, _POINT_COLOR = "#c8d2e6", "#e8a33c", "#cc3311"


@dataclass
class Panel:
    """One panel of :func:`grid`.

    Attributes
    ----------
    title : str
        Drawn at the panel's top left (may hold several lines).
    mesh : open3d.geometry.TriangleMesh, optional
    points : (N, 3) array, optional
        Drawn as small dots (without a mesh: a panel of points).
    scalars : (V,) array, optional
        One value per mesh vertex, coloured on the grid's shared range.
    view : str
        A key of :func:`views_around` (``front``, ``side``, ``top``, ``below``).
    """

    title: str = ""
    mesh: object = None
    points: object = None
    scalars: object = None
    view: str = "front"


def views_around(viewup=(0.0, 0.0, 1.0)) -> dict:
    """Four viewpoints for data whose up axis is ``viewup``.

    Returns
    -------
    dict
        ``{name: (direction (3,), screen_up (3,))}`` for ``front`` (slightly
        from above), ``side`` (90 degrees round the up axis), ``top`` and
        ``below`` (straight up at the underside); ``direction`` points from
        the scene's centre to the camera.
    """
    up = np.asarray(viewup, dtype=float)
    if up.shape != (3,) or not np.linalg.norm(up) > 0:
        raise ValueError(f"viewup must be a non-zero 3-vector, got {viewup!r}")
    up = up / np.linalg.norm(up)
    trial = np.array([0.0, -1.0, 0.0]) if abs(up[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    front = trial - up * (trial @ up)
    front /= np.linalg.norm(front)
    side = np.cross(up, front)
    tilt = 0.35
    return {
        "front": (front + tilt * up + 0.3 * side, up),
        "side": (side + tilt * up - 0.3 * front, up),
        "top": (up, -front),
        "below": (-up, -front),
    }


def _pieces(mesh):
    """Mask ``(F,)`` of the triangles of the largest connected piece, and
    whether the other pieces hide inside it (it is closed and holds most of
    their vertices)."""
    from o3drbf.mesh.arrays import raycasting_scene, unique_edges

    tris = np.asarray(mesh.triangles)
    labels, _, _ = mesh.cluster_connected_triangles()
    labels = np.asarray(labels)
    main = labels == int(np.argmax(np.bincount(labels)))
    hidden = False
    if not main.all() and (unique_edges(tris[main])[2] == 2).all():
        import open3d as o3d

        verts = np.asarray(mesh.vertices)
        others = np.unique(tris[~main])
        occupancy = raycasting_scene(verts, tris[main]).compute_occupancy(o3d.core.Tensor(verts[others].astype(np.float32)))
        hidden = bool(occupancy.numpy().mean() > 0.5)
    return main, hidden


def _poly(verts, tris, scalars=None):
    import pyvista as pv

    poly = pv.PolyData(verts, np.column_stack([np.full(len(tris), 3), tris]).ravel())
    if scalars is not None:
        poly.point_data["distance"] = np.asarray(scalars, dtype=float)
    return poly


def _add_mesh(plotter, mesh, scalars, clim, cmap):
    """Draw one mesh; returns the scalar-mapped actor or None.

    Coloured by ``scalars`` on ``clim`` (every piece), or in one colour with
    back faces orange and the pieces besides the largest in
    :data:`PIECE_COLOR`.  Pieces hidden inside a closed largest piece are
    drawn in :data:`PIECE_COLOR` in either case, and the largest piece is
    then see-through."""
    verts, tris = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    main, hidden = _pieces(mesh)
    body = main if hidden or scalars is None else np.ones(len(tris), dtype=bool)
    kw = dict(smooth_shading=True, specular=0.2, opacity=0.35 if hidden else 1.0)
    actor = None
    if scalars is not None:
        actor = plotter.add_mesh(_poly(verts, tris[body], scalars), scalars="distance", clim=clim, cmap=cmap, show_scalar_bar=False, **kw)
    else:
        plotter.add_mesh(_poly(verts, tris[body]), color=_FRONT_COLOR, backface_params=dict(color=_BACK_COLOR), **kw)
    if not body.all():
        plotter.add_mesh(_poly(verts, tris[~body]), color=PIECE_COLOR, smooth_shading=True)
    return actor


def _text(plotter, text, xy, size, color="black", right=False):
    """Text at ``xy`` (fractions of the panel) at a fixed size in pixels:
    hanging down from ``xy``, or rising from it when ``right`` (bottom right)."""
    actor = plotter.add_text(text, position=xy, viewport=True, font_size=size, color=color)
    prop = actor.GetTextProperty()
    prop.SetBackgroundColor(1.0, 1.0, 1.0)  # readable over a mesh that fills the panel
    prop.SetBackgroundOpacity(0.75)
    if right:
        prop.SetJustificationToRight()
        prop.SetVerticalJustificationToBottom()
    else:
        prop.SetJustificationToLeft()
        prop.SetVerticalJustificationToTop()
    return actor


def grid(
    rows,
    path: str | os.PathLike,
    panel_size: int = 300,
    header: str = "",
    clim=None,
    colour_label: str = "",
    cmap: str = "viridis",
    viewup=(0.0, 0.0, 1.0),
    bounds=None,
) -> Path:
    """Render rows of panels into one PNG (offscreen), under a header strip.

    Every panel of a column is seen from the same viewpoint with the same
    framing (``bounds``), so panels compare at a glance.

    Parameters
    ----------
    rows : list of list of Panel
        Every row the same length.
    path : str or Path
        Output ``.png`` (written atomically).
    panel_size : int
        Pixels per (square) panel.  The picture is
        ``(columns * panel_size, HEADER_HEIGHT + rows * panel_size)``.
    header : str
        Text of the header strip (settings shared by all rows).
    clim : (2,) float, optional
        Range of the panels' ``scalars`` (one for all panels), drawn as a
        colour bar titled ``colour_label`` in the header.
    viewup : 3-tuple
        The data's up axis (:func:`views_around`).
    bounds : (6,) float, optional
        ``(xmin, xmax, ymin, ymax, zmin, zmax)`` framed by every panel
        (default: the union of all meshes and points).

    Returns
    -------
    Path
    """
    headless()
    import pyvista as pv

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"picture must be a .png file, got {str(path)!r}")
    if not rows or not rows[0] or len({len(r) for r in rows}) != 1:
        raise ValueError("grid needs one or more rows of panels, every row the same length")
    views = views_around(viewup)
    n_rows, n_cols = len(rows), len(rows[0])
    if bounds is None:
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for row in rows:
            for p in row:
                for arr in (None if p.mesh is None else np.asarray(p.mesh.vertices), p.points):
                    if arr is not None and len(arr):
                        a = np.asarray(arr, dtype=float)
                        lo, hi = np.minimum(lo, a.min(axis=0)), np.maximum(hi, a.max(axis=0))
        if not np.isfinite(lo).all():
            lo, hi = -np.ones(3), np.ones(3)
        bounds = np.column_stack([lo, hi]).ravel()
    bounds = [float(b) for b in bounds]
    centre = np.array([(bounds[0] + bounds[1]) / 2, (bounds[2] + bounds[3]) / 2, (bounds[4] + bounds[5]) / 2])
    size = panel_size
    window = [n_cols * size, HEADER_HEIGHT + n_rows * size]
    plotter = pv.Plotter(
        shape=(n_rows + 1, n_cols),
        groups=[(0, np.s_[:])],
        row_weights=[HEADER_HEIGHT] + [size] * n_rows,
        off_screen=True,
        window_size=window,
        border=False,
    )
    mapper = None
    for i, row in enumerate(rows):
        for j, p in enumerate(row):
            plotter.subplot(i + 1, j)
            plotter.set_background("white")
            if p.mesh is not None and len(p.mesh.triangles):
                actor = _add_mesh(plotter, p.mesh, p.scalars, clim, cmap)
                if actor is not None:
                    mapper = actor.mapper
            if p.points is not None and len(p.points):
                plotter.add_points(np.asarray(p.points, dtype=float), color=_POINT_COLOR, point_size=2, render_points_as_spheres=False)
            if p.title:
                _text(plotter, p.title, (0.02, 0.98), 8)
            _text(plotter, p.view, (0.98, 0.02), 8, color="#555555", right=True)
            direction, up = views[p.view]
            direction = direction / np.linalg.norm(direction)
            cam = plotter.camera
            cam.focal_point = centre
            cam.position = centre + 10.0 * max(bounds[1] - bounds[0], bounds[3] - bounds[2], bounds[5] - bounds[4], 1e-12) * direction
            cam.up = up
            plotter.reset_camera(bounds=bounds)
            cam.zoom(1.0)
    plotter.subplot(0, 0)
    plotter.set_background("white")
    if header:
        _text(plotter, header, (0.005, 0.95), 9)
    if mapper is not None:
        bar = plotter.add_scalar_bar(title=colour_label, mapper=mapper, n_labels=5, fmt="%.3g", color="black",
                                     position_x=0.56, position_y=0.1, width=0.42, height=0.6, title_font_size=14, label_font_size=13)
        bar.SetTextPositionToPrecedeScalarBar()
    with atomic_path(path) as tmp:
        plotter.screenshot(tmp)
    plotter.close()
    return path


def in_notebook() -> bool:
    """Whether this code runs in a Jupyter kernel (IPython's ZMQ shell)."""
    ipython = sys.modules.get("IPython")
    shell = ipython.get_ipython() if ipython is not None else None
    return shell is not None and type(shell).__name__ == "ZMQInteractiveShell"


def jupyter_backend() -> str:
    """PyVista's Jupyter backend: ``"trame"`` (interactive) when trame is installed, else ``"static"`` (a PNG)."""
    import importlib.util

    have_trame = all(importlib.util.find_spec(name) is not None for name in ("trame", "trame_vtk", "trame_vuetify"))
    return "trame" if have_trame else "static"


def plot(mesh, *, points=None, exterior=None, compare=None, title: str | None = None, show: bool = True,
         screenshot: str | os.PathLike | None = None, backend: str | None = None, window_size=None,
         view=((1.0, -1.2, 0.9), (0.0, 0.0, 1.0))):
    """Show a mesh with PyVista: inline in Jupyter, in a window on a desktop, offscreen otherwise.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh
        The mesh of the first panel.
    points : (N, 3) array_like, optional
        Points drawn small (blue, ``CONSTRAINT_COLORS["surface"]``) over the first panel, e.g. the surface constraints.
    exterior : (M, 3) array_like, optional
        Points drawn small (green, ``CONSTRAINT_COLORS["exterior"]``) over the first panel, e.g. the exterior constraints.
    compare : dict of str to open3d.geometry.TriangleMesh, optional
        Further meshes, one panel each, right of the first, seen from the same (linked) camera.
    title : str, optional
        The first panel's title (default: the triangle count).
    show : bool
        Display the picture (Jupyter: inline, with ``backend``; a desktop: a
        window).  Without a notebook or a display nothing can be shown, and
        only ``screenshot`` is written.
    screenshot : str or Path, optional
        Also write the picture to this ``.png`` (atomically).
    backend : str, optional
        PyVista's Jupyter backend; default :func:`jupyter_backend` ("trame" when installed, else "static").
    window_size : (2,) int, optional
        Pixels; default 500 x 450 per panel.
    view : (direction, up) pair of 3-tuples, or a direction
        Camera direction from the scene's centre, and the data's up axis
        (a direction alone: up is z).

    Returns
    -------
    pyvista.Plotter or None
        With ``show=False``, the open plotter (add to it, then ``.show()``);
        else None (the plotter is closed once shown).

    Raises
    ------
    ValueError
        ``screenshot`` is not a ``.png`` file, or a mesh has no triangles.
    """
    panels = [(title, mesh)] + list((compare or {}).items())
    for name, m in panels:
        if m is None or not len(m.triangles):
            which = f" {name!r}" if name else ""
            raise ValueError(f"plot: the mesh{which} has no triangles; give a mesh (reconstruct with extract_mesh=True)")
    if screenshot is not None and Path(screenshot).suffix.lower() != ".png":
        raise ValueError(f"plot: screenshot must be a .png file, got {str(screenshot)!r}")
    direction, viewup = view if np.ndim(view) == 2 else (view, (0.0, 0.0, 1.0))
    headless()
    import pyvista as pv

    notebook = in_notebook()
    window = os.environ.get("DISPLAY") or sys.platform in ("win32", "darwin")
    size = list(window_size) if window_size is not None else [500 * len(panels), 450]
    plotter = pv.Plotter(shape=(1, len(panels)), off_screen=notebook or not window or not show,
                         notebook=notebook, window_size=size, border=False)
    for i, (name, m) in enumerate(panels):
        plotter.subplot(0, i)
        plotter.set_background("white")
        plotter.add_mesh(to_pyvista(m), color=MESH_COLOR, smooth_shading=True, specular=0.3)
        plotter.view_vector(direction, viewup=viewup)  # framed on the mesh, not on far-away points
        if i == 0:
            for extra, color in ((points, CONSTRAINT_COLORS["surface"]), (exterior, CONSTRAINT_COLORS["exterior"])):
                if extra is not None and len(extra):
                    plotter.add_points(np.asarray(extra, dtype=float).reshape(-1, 3), color=color, point_size=CONSTRAINT_POINT_SIZE,
                                       render_points_as_spheres=True, reset_camera=False)
        plotter.add_text(name if name is not None else f"{len(m.triangles):,} triangles", position=(12, size[1] - 32), font_size=12, color="black")
    if len(panels) > 1:
        plotter.link_views()
    if screenshot is not None:
        with atomic_path(Path(screenshot)) as tmp:
            plotter.screenshot(tmp)
    if not show:
        return plotter
    if notebook:
        plotter.show(jupyter_backend=backend or jupyter_backend())
    elif window:
        plotter.show()
    plotter.close()
    return None
