"""Synthetic photographs of a coloured mesh, by ray casting.

:func:`render_views` casts one ray through the centre ``(u + 0.5, v + 0.5)``
of every pixel of each calibrated pinhole camera against the mesh (Open3D
``RaycastingScene``) and colours the first hit by barycentric interpolation
of the vertex colours of the triangle it lands on.  There is no shading: a
pixel is exactly the surface colour at the 3-D point it sees, which is what
makes these images a test truth for colouring from photographs
(:mod:`o3drbf.mesh.color`) and for carving.  :func:`save_images` writes the
images as PNG files, atomically.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from o3drbf.cameras.model import Camera, as_cameras
from o3drbf.io.files import atomic_path
from o3drbf.mesh.arrays import mesh_arrays, raycasting_scene

__all__ = ["View", "render_views", "pixel_rays", "save_images"]

#: Colour of a mesh that has none.
GREY = (0.5, 0.5, 0.5)


@dataclass(frozen=True, eq=False)
class View:
    """One rendered photograph.

    Attributes
    ----------
    image : (H, W, 3) float64 array
        Colours in [0, 1]; the background colour where the pixel misses the mesh.
    mask : (H, W) bool array
        The pixel centre's ray hits the mesh.
    depth : (H, W) float64 array
        Camera z coordinate of the hit (``inf`` on the background).
    camera : Camera
    """

    image: np.ndarray
    mask: np.ndarray
    depth: np.ndarray
    camera: Camera


def pixel_rays(camera: Camera) -> np.ndarray:
    """Rays through every pixel centre of a pinhole camera.

    Parameters
    ----------
    camera : Camera
        Pinhole, with ``width`` and ``height``.

    Returns
    -------
    (H * W, 6) float64 array
        Origin (the camera centre) and direction ``R^T K^-1 [u + 0.5, v + 0.5, 1]``
        per pixel, row-major (``v`` slow, ``u`` fast).  The direction is *not*
        unit length: its camera-frame z component is 1, so the ray parameter of
        a hit is the depth (camera z) of the hit.
    """
    return as_cameras(camera, "images", sized=True)[0].pixel_rays().reshape(-1, 6)


def _vertex_colors(mesh, n: int, vertex_colors) -> np.ndarray:
    if vertex_colors is None:
        has = getattr(mesh, "has_vertex_colors", None)
        if callable(has) and has():
            vertex_colors = np.asarray(mesh.vertex_colors)
        elif hasattr(mesh, "vertex") and "colors" in getattr(mesh.vertex, "keys", lambda: [])():
            vertex_colors = mesh.vertex.colors.numpy()
        else:
            return np.broadcast_to(np.asarray(GREY), (n, 3)).astype(float)
    c = np.asarray(vertex_colors, dtype=float)
    if c.shape != (n, 3):
        raise ValueError(f"vertex_colors must have one RGB row per vertex: expected ({n}, 3), got {c.shape}")
    if not np.isfinite(c).all() or c.min() < 0 or c.max() > 1:
        raise ValueError("vertex_colors must be finite floats in [0, 1]")
    return c


def render_views(
    mesh,
    cameras: Sequence[Camera],
    vertex_colors=None,
    background=(0.0, 0.0, 0.0),
) -> list[View]:
    """Ray-cast a coloured mesh into calibrated pinhole images.

    Parameters
    ----------
    mesh : Open3D TriangleMesh, path, or (vertices (V, 3), triangles (T, 3))
    cameras : sequence of Camera
        Pinhole cameras with ``width`` and ``height`` (a CameraSet works too).
    vertex_colors : (V, 3) array_like of floats in [0, 1], optional
        Default: the mesh's vertex colours, else grey (0.5).
    background : (3,) array_like
        Colour of pixels that miss the mesh.

    Returns
    -------
    list of View
        One per camera, in order.

    Notes
    -----
    A pixel ``(u, v)`` (integer indices, row ``v``, column ``u``) shows the
    first hit of the ray through ``(u + 0.5, v + 0.5)``; its colour is
    ``(1 - a - b) c0 + a c1 + b c2`` with ``(a, b)`` the hit's barycentric
    coordinates in triangle ``(i0, i1, i2)``.  No lighting, no anti-aliasing.
    """
    import open3d as o3d

    v, t = mesh_arrays(mesh)
    colors = _vertex_colors(mesh, len(v), vertex_colors)
    bg = np.asarray(background, dtype=float).reshape(-1)
    if bg.shape != (3,) or not np.isfinite(bg).all():
        raise ValueError(f"background must be an RGB triple, got {np.asarray(background).tolist()}")
    cams = as_cameras(cameras, "images", sized=True)
    scene = raycasting_scene(v, t)
    views = []
    for cam in cams:
        rays = pixel_rays(cam)
        ans = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
        hit = ans["t_hit"].numpy().astype(float)
        mask = np.isfinite(hit)
        prim = ans["primitive_ids"].numpy()[mask].astype(np.int64)
        uv = ans["primitive_uvs"].numpy()[mask].astype(float)
        tri = t[prim]
        bary = np.column_stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]])
        img = np.empty((mask.size, 3))
        img[:] = bg
        img[mask] = np.clip(np.einsum("nk,nkc->nc", bary, colors[tri]), 0.0, 1.0)
        # The ray parameter is the hit's camera z (directions have unit camera z);
        # recompute it in float64 from the hit point for accuracy.
        depth = np.full(mask.size, np.inf)
        pts = np.einsum("nk,nkc->nc", bary, v[tri])
        depth[mask] = cam.to_camera(pts)[:, 2]
        shape = (cam.height, cam.width)
        views.append(View(img.reshape(shape + (3,)), mask.reshape(shape), depth.reshape(shape), cam))
    return views


def save_images(views: Sequence[View], folder: str | os.PathLike, prefix: str = "view") -> list[Path]:
    """Write each view's image as an 8-bit PNG, atomically.

    Parameters
    ----------
    views : sequence of View
    folder : path-like
        An existing folder.
    prefix : str
        Files are named ``{prefix}_{index:03d}.png``.

    Returns
    -------
    list of Path
    """
    import open3d as o3d

    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {folder}")
    out = []
    for i, view in enumerate(views):
        path = folder / f"{prefix}_{i:03d}.png"
        img = np.ascontiguousarray(np.round(np.clip(view.image, 0, 1) * 255).astype(np.uint8))
        with atomic_path(path) as tmp:
            if not o3d.io.write_image(tmp, o3d.geometry.Image(img)):
                raise OSError(f"Open3D could not write {path}")
        out.append(path)
    return out
