"""Pictures of meshes and points (PyVista, imported lazily: the rest of
o3drbf never needs it, so the library stays headless)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from o3drbf.io.files import atomic_path

__all__ = ["headless", "to_pyvista", "side_by_side", "plot", "in_notebook", "jupyter_backend"]

#: Mesh, point and exterior colours of :func:`plot` and :func:`side_by_side`.
MESH_COLOR = "#c8d2e6"
POINT_COLOR = "#cc3311"
EXTERIOR_COLOR = "#3366cc"


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
         view=(1.0, -1.2, 0.9), viewup=(0.0, 0.0, 1.0)):
    """Show a mesh with PyVista: inline in Jupyter, in a window on a desktop, offscreen otherwise.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh
        The mesh of the first panel.
    points : (N, 3) array_like, optional
        Points drawn small (red) over the first panel, e.g. the surface constraints.
    exterior : (M, 3) array_like, optional
        Points drawn small (blue) over the first panel, e.g. the exterior constraints.
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
    view, viewup : 3-tuple
        Camera direction from the scene's centre, and the data's up axis.

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
        plotter.view_vector(view, viewup=viewup)  # framed on the mesh, not on far-away points
        if i == 0:
            for extra, color in ((points, POINT_COLOR), (exterior, EXTERIOR_COLOR)):
                if extra is not None and len(extra):
                    plotter.add_points(np.asarray(extra, dtype=float).reshape(-1, 3), color=color, point_size=3, reset_camera=False)
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
