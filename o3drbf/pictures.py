"""Pictures of meshes and points (PyVista, imported lazily: the rest of
o3drbf never needs it, so the library stays headless)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from o3drbf.io.files import atomic_path

__all__ = ["headless", "to_pyvista", "side_by_side"]


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
            plotter.add_mesh(to_pyvista(mesh), color="#c8d2e6", smooth_shading=True, specular=0.3)
        if points is not None and i == 0:
            plotter.add_points(np.asarray(points), color="#cc3311", point_size=2, render_points_as_spheres=False)
        plotter.add_text(title, font_size=11, color="black")
        plotter.view_vector(view, viewup=viewup)
    plotter.link_views()
    with atomic_path(path) as tmp:
        plotter.screenshot(tmp)
    plotter.close()
    return path
