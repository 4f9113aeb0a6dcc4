"""Geometry for drawing: camera frusta, the up direction and the start view, consistently wound
triangles, display subsamples, distances between meshes (arrays only)."""

from __future__ import annotations

import numpy as np

__all__ = ["camera_frusta", "view_up", "view_direction", "wind_like_normals", "subsample", "look_at", "vertex_distances"]


def camera_frusta(cameras, depth: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Line segments drawing each pinhole camera as a pyramid (its view frustum).

    Parameters
    ----------
    cameras : sequence of Camera
    depth : float
        Distance from the centre to the drawn image rectangle (data units).

    Returns
    -------
    vertices : (V, 3) array
    lines : (L, 2) int array
        Index pairs into ``vertices``: four edges from the centre to the
        image corners and the four sides of the image rectangle, per camera.
    centers : (C, 3) array
        The centres of every camera with a position (pinhole or centre-only).
    """
    verts, lines, centers = [], [], []
    for cam in cameras or ():
        if cam.kind == "direction":
            continue
        c = np.asarray(cam.center, dtype=float)
        centers.append(c)
        if cam.kind != "pinhole":
            continue
        w = cam.width if cam.width else 2 * cam.K[0, 2]
        h = cam.height if cam.height else 2 * cam.K[1, 2]
        pix = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], dtype=float)
        rays = np.linalg.solve(cam.K, pix.T).T  # camera frame, z = 1
        corners = c + (rays * depth) @ cam.R  # R^T (depth * ray), back in the world
        base = sum(len(v) for v in verts)
        verts.append(np.vstack([c, corners]))
        lines += [(base, base + k) for k in range(1, 5)]
        lines += [(base + k, base + 1 + k % 4) for k in range(1, 5)]
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 2), dtype=int), np.asarray(centers).reshape(-1, 3)
    return np.vstack(verts), np.asarray(lines, dtype=int), np.asarray(centers).reshape(-1, 3)


def view_up(cameras=None, up: str = "auto") -> np.ndarray:
    """The scene's up direction: an axis (``"x"``, ``"y"``, ``"z"``) or, with
    ``"auto"``, the pinhole cameras' mean image-up direction (else +z).

    Image rows grow downward, so a camera's up is minus the second row of R.
    """
    axes = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
    if up in axes:
        return np.array(axes[up])
    if up != "auto":
        raise ValueError(f"up must be 'auto', 'x', 'y' or 'z', got {up!r}")
    ups = [-np.asarray(c.R)[1] for c in (cameras or ()) if c.kind == "pinhole"]
    if ups:
        u = np.mean(ups, axis=0)
        n = float(np.linalg.norm(u))
        if n > 0.5:  # the cameras agree on an up direction
            return u / n
    return np.array(axes["z"])


def view_direction(up) -> np.ndarray:
    """Unit vector from the scene centre to the eye: from the side and above."""
    u = np.asarray(up, dtype=float)
    u = u / np.linalg.norm(u)
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - u * (helper @ u)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    d = 1.0 * e1 - 1.2 * e2 + 1.4 * u
    return d / np.linalg.norm(d)


def wind_like_normals(vertices, triangles, vertex_normals) -> np.ndarray:
    """Triangles re-wound (per triangle) so their right-hand normal agrees with the vertex normals.

    Renderers take the winding as the outside; a mesh whose winding and
    normals disagree is drawn lit from behind (dark).

    Parameters
    ----------
    vertices : (V, 3) array
    triangles : (T, 3) int array
    vertex_normals : (V, 3) array

    Returns
    -------
    (T, 3) int array
    """
    v = np.asarray(vertices, dtype=float)
    t = np.asarray(triangles)
    n = np.asarray(vertex_normals, dtype=float)
    if not len(t) or n.shape != v.shape:
        return t.copy()
    geo = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    flip = np.einsum("ij,ij->i", geo, n[t].sum(axis=1)) < 0
    out = t.copy()
    out[flip] = out[flip][:, ::-1]
    return out


def subsample(count: int, cap: int, seed: int = 0) -> np.ndarray:
    """Indices of at most ``cap`` of ``count`` items, drawn without replacement, sorted (deterministic).

    Parameters
    ----------
    count : int
        How many items there are.
    cap : int
        How many to keep at most (>= 1).
    seed : int
        The same ``(count, cap, seed)`` always gives the same indices.

    Returns
    -------
    (min(count, cap),) int array
        All of ``range(count)`` when ``count <= cap``.
    """
    count, cap = int(count), int(cap)
    if cap < 1:
        raise ValueError(f"the display cap must be at least 1 point, got {cap}; raise --max-points")
    if count <= cap:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, size=cap, replace=False))


def look_at(bounds, up, view_angle: float, zoom: float = 1.0) -> list[tuple]:
    """A camera position that shows the box ``bounds`` from the side and above, ``up`` up.

    Parameters
    ----------
    bounds : (2, 3) array
        Low and high corners.
    up : (3,) array
    view_angle : float
        The camera's vertical view angle in degrees.
    zoom : float
        1 fits the box's bounding sphere in 75% of the view; below 1 shows more around it.

    Returns
    -------
    [eye, focal point, up] : list of three 3-tuples (PyVista's ``camera_position``)
    """
    lo, hi = np.asarray(bounds, dtype=float)
    c = (lo + hi) / 2
    radius = 0.5 * float(np.linalg.norm(hi - lo)) or 1.0
    half_angle = np.radians(view_angle / 2)
    eye = c + radius / np.sin(half_angle) / (0.75 * zoom) * view_direction(up)
    return [tuple(eye), tuple(c), tuple(np.asarray(up, dtype=float))]


def vertex_distances(vertices, other_vertices, other_triangles) -> np.ndarray:
    """Unsigned distance from each vertex to the nearest point of another triangle mesh.

    Open3D's ray-casting scene (single precision), with both meshes shifted
    by the other mesh's centre so that far-from-origin data keeps its digits.

    Parameters
    ----------
    vertices : (V, 3) array
    other_vertices : (W, 3) array
    other_triangles : (F, 3) int array

    Returns
    -------
    (V,) float array
    """
    import open3d as o3d

    from o3drbf.mesh.arrays import raycasting_scene

    ov = np.asarray(other_vertices, dtype=float)
    origin = 0.5 * (ov.min(axis=0) + ov.max(axis=0))
    scene = raycasting_scene(ov - origin, np.asarray(other_triangles))
    query = o3d.core.Tensor(np.ascontiguousarray(np.asarray(vertices, dtype=float) - origin, dtype=np.float32))
    return scene.compute_distance(query).numpy().astype(float)
