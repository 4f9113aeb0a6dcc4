"""Per-vertex colour for a reconstructed mesh: from photographs, or from coloured points.

From calibrated photographs (method.md section 7), :func:`colors_from_images`
gives each vertex the weighted mean of the pixels it projects to in every
camera that sees it::

    c(x) = sum_k w_k(x) I_k(P_k x) / sum_k w_k(x),    w_k(x) = max(0, n(x) . d_k(x))

with ``n`` the unit vertex normal, ``d_k`` the unit direction from the vertex
to camera ``k``'s centre, and ``I_k(P_k x)`` the image sampled bilinearly at
the vertex's projection.  Camera ``k`` sees the vertex when it projects into
the image and the ray from the camera centre toward it first hits the mesh
itself (ray casting against the mesh: a z-buffer at the vertex's own
position, not at pixel resolution).  The mesh should be fine enough that a
triangle covers about a pixel (:func:`subdivide_for_images`), else colour
detail between vertices is lost.

Without photographs, :func:`colors_from_points` takes inverse-distance
weighted colours of the nearest points of a coloured point cloud (or voxel
centres).  :func:`color_mesh` picks the right one and returns a coloured
copy of the mesh.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.validation import as_points, as_rgb, as_vectors, check_choice, check_number
from o3drbf.cameras.model import Camera, as_cameras
from o3drbf.mesh.arrays import mesh_arrays, raycasting_scene, unique_edges

__all__ = [
    "ColorResult",
    "colors_from_images",
    "colors_from_points",
    "subdivide_for_images",
    "color_mesh",
    "vertex_normals",
    "MAX_TRIANGLES",
]

log = logging.getLogger(__name__)

#: Colour of vertices nothing says anything about.
GREY = 0.5

#: Default cap on the triangles :func:`subdivide_for_images` may produce.
MAX_TRIANGLES = 2_000_000

#: Default visibility tolerance, as a fraction of the mean edge length.
DEPTH_TOLERANCE_EDGES = 0.5


@dataclass(frozen=True, eq=False)
class ColorResult:
    """What :func:`colors_from_images` returns.

    Attributes
    ----------
    colors : (V, 3) float64 array
        RGB in [0, 1] per vertex.
    weight : (V,) float64 array
        Total weight ``sum_k max(0, n . d_k)`` of the cameras that saw each vertex.
    seen : (V,) bool array
        Some camera saw the vertex with positive weight.
    views : (V,) int array
        How many cameras contributed to each vertex.
    filled : int
        Unseen vertices coloured from their coloured neighbours (diffusion
        over the mesh edges) or from the fallback colours.
    unreached : int
        Unseen vertices with no coloured vertex in their connected component,
        left grey (0.5).
    """

    colors: np.ndarray
    weight: np.ndarray
    seen: np.ndarray
    views: np.ndarray
    filled: int = 0
    unreached: int = 0


# -- inputs -------------------------------------------------------------------


def _name(cam) -> str:
    return f"({cam.name}) " if getattr(cam, "name", "") else ""


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, outward on closed meshes.

    The triangle winding gives the normals (counter-clockwise seen from the
    side they point to).  If the mesh is closed (every edge in exactly two
    triangles) and its signed volume is negative, the winding is inward
    throughout and every normal is flipped, so closed meshes get outward
    normals whichever way they are wound.

    Parameters
    ----------
    vertices : (V, 3) array
    triangles : (T, 3) int array

    Returns
    -------
    (V, 3) array
        Unit normals; zero for vertices in no (non-degenerate) triangle.
    """
    v = np.asarray(vertices, dtype=float)
    t = np.asarray(triangles, dtype=np.int64)
    return _vertex_normals(v, t, bool((unique_edges(t)[2] == 2).all()))


def _vertex_normals(v: np.ndarray, t: np.ndarray, closed: bool) -> np.ndarray:
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])  # twice the area times the unit normal
    if closed and np.einsum("ij,ij->", v[t[:, 0]] - v.mean(axis=0), fn) < 0:  # 6 x signed volume
        fn = -fn
    idx = t.ravel()
    n = np.column_stack([np.bincount(idx, np.repeat(fn[:, c], 3), minlength=len(v)) for c in range(3)])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def _bilinear(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Sample an ``(H, W, C)`` image bilinearly at continuous pixel coordinates ``(N, 2)`` (u, v), giving ``(N, C)``.

    Pixel ``(i, j)`` has its centre at ``(j + .5, i + .5)``; outside the
    centres the edge pixels extend (``scipy.ndimage.map_coordinates``, order 1,
    mode "nearest").
    """
    from scipy import ndimage

    rows, cols = pixels[:, 1] - 0.5, pixels[:, 0] - 0.5
    coords = np.stack([rows, cols])
    return np.column_stack([ndimage.map_coordinates(image[:, :, c], coords, order=1, mode="nearest") for c in range(image.shape[2])])


def _diffuse(colors: np.ndarray, known: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Grow colours into unknown vertices front by front: each takes the mean of its neighbours one front nearer.

    Front ``k`` is the unknown vertices ``k`` edges from the nearest known one
    (breadth-first search from all known vertices at once); fronts are
    coloured in order, so the work is linear in the edges.  ``colors`` is
    updated in place.  Returns the mask of vertices coloured this way.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import shortest_path

    nv = len(colors)
    src = np.flatnonzero(known)
    # a super source (index nv) joined to every known vertex
    a = np.concatenate([edges[:, 0], np.full(len(src), nv)])
    b = np.concatenate([edges[:, 1], src])
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(nv + 1, nv + 1)).tocsr()
    level = shortest_path(graph, directed=False, unweighted=True, indices=nv)[:nv] - 1  # known: 0
    # directed edges from a front to the next one
    a, b = np.concatenate([edges[:, 0], edges[:, 1]]), np.concatenate([edges[:, 1], edges[:, 0]])
    step = np.isfinite(level[b]) & (level[b] == level[a] + 1)
    a, b = a[step], b[step]
    order = np.argsort(level[b], kind="stable")
    a, b = a[order], b[order]
    bounds = np.flatnonzero(np.diff(level[b])) + 1
    for fa, fb in zip(np.split(a, bounds), np.split(b, bounds)):
        front, inv = np.unique(fb, return_inverse=True)
        count = np.bincount(inv, minlength=len(front))
        colors[front] = np.column_stack([np.bincount(inv, colors[fa, c], minlength=len(front)) for c in range(3)]) / count[:, None]
    return np.isfinite(level) & (level > 0)


# -- photographs --------------------------------------------------------------


def colors_from_images(
    mesh,
    cameras: Sequence[Camera],
    images: Sequence,
    *,
    normals=None,
    depth_tolerance: float | None = None,
    min_cosine: float = 0.0,
    visibility: bool = True,
    fill: str = "diffuse",
) -> ColorResult:
    """Colour every vertex from the calibrated photographs that see it.

    Parameters
    ----------
    mesh : Open3D TriangleMesh or (vertices (V, 3), triangles (T, 3))
        Closed meshes get outward normals whichever way they are wound
        (:func:`vertex_normals`); give ``normals`` for open ones wound inward.
    cameras : sequence of Camera (or CameraSet)
        Pinhole cameras, one per image.  A camera without ``width``/``height``
        takes its image's size.
    images : sequence of (H, W, 3) arrays
        uint8 (0-255), uint16, or floats in [0, 1]; (H, W) grey and
        (H, W, 4) RGBA (alpha ignored) are accepted.
    normals : (V, 3) array_like, optional
        Outward vertex normals (default: area-weighted from the triangles).
    depth_tolerance : float, optional
        A camera sees a vertex when the ray from its centre toward the vertex
        first hits the mesh no more than this before the vertex (data units).
        Default: half the mean edge length.  A ray aimed at a vertex hits the
        vertex itself, or one of its own triangles within about an edge of it
        where the surface is concave or the ray grazes; an occluder is another
        part of the surface, resolved by the mesh only if it is at least about
        an edge away.  Half an edge lies between the two and far above
        single-precision ray-casting error (1e-6 relative).
    min_cosine : float in [0, 1)
        Ignore views with ``n . d <= min_cosine`` (grazing views blur colours).
    visibility : bool
        Ray-cast visibility (default).  ``False`` uses every camera the vertex
        faces and projects into, occluded or not: only for comparison.
    fill : {"diffuse", "grey"}
        Unseen vertices: take the mean colour of coloured neighbours, front by
        front over the mesh edges ("diffuse"), or stay grey (0.5).

    Returns
    -------
    ColorResult

    Raises
    ------
    ValueError
        Mismatched numbers of cameras and images, an image whose size differs
        from its camera's, a camera that is not pinhole, or cameras that see
        no vertex at all.
    """
    import open3d as o3d

    v, t = mesh_arrays(mesh)
    cams = as_cameras(cameras, "colours from images", allow_empty=True)
    images = list(images)
    if len(cams) != len(images):
        raise ValueError(f"got {len(cams)} camera(s) and {len(images)} image(s); give one image per camera")
    if not cams:
        raise ValueError("no cameras and images given; colour from images needs at least one")
    for i, (cam, img) in enumerate(zip(cams, images)):
        shape = np.shape(img)
        if len(shape) not in (2, 3):
            raise ValueError(f"image {i} must be (H, W, 3) RGB (or (H, W) grey), got shape {shape}")
        h, w = shape[:2]
        if (cam.width is not None and cam.width != w) or (cam.height is not None and cam.height != h):
            raise ValueError(
                f"image {i} is {w}x{h} (width x height) but camera {i} {_name(cam)}expects {cam.width}x{cam.height}"
            )
    edges, _, shared = unique_edges(t)
    n = _vertex_normals(v, t, bool((shared == 2).all())) if normals is None else as_vectors(normals, len(v), name="normals")
    min_cosine = check_number("min_cosine", min_cosine, low=0.0, high=1.0)
    if min_cosine >= 1:
        raise ValueError(f"min_cosine must be below 1, got {min_cosine}")
    check_choice("fill", fill, ("diffuse", "grey"))
    if depth_tolerance is None:
        depth_tolerance = DEPTH_TOLERANCE_EDGES * float(np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1).mean())
    depth_tolerance = check_number("depth_tolerance", depth_tolerance, low=0.0)

    scene = None
    if visibility:
        scene = raycasting_scene(v, t)
    total = np.zeros((len(v), 3))
    weight = np.zeros(len(v))
    views = np.zeros(len(v), dtype=np.int64)
    for i, (cam, img) in enumerate(zip(cams, images)):
        img = as_rgb(img, f"image {i}")  # one float copy at a time
        h, w = img.shape[:2]
        pixels, depth = cam.project(v)
        with np.errstate(invalid="ignore"):
            inside = (depth > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] < w) & (pixels[:, 1] >= 0) & (pixels[:, 1] < h)
        d, dist = cam.toward(v)
        cos = np.einsum("ij,ij->i", n, d)
        ok = inside & (cos > min_cosine) & (cos > 0)
        idx = np.flatnonzero(ok)
        if scene is not None and len(idx):
            rays = np.hstack([np.broadcast_to(cam.center, (len(idx), 3)), -d[idx]]).astype(np.float32)
            hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(float)
            # a miss (inf) can only be a float32 near-miss at the vertex itself: visible
            idx = idx[hit >= dist[idx] - depth_tolerance]
        c = _bilinear(img, pixels[idx])
        total[idx] += cos[idx, None] * c
        weight[idx] += cos[idx]
        views[idx] += 1
    seen = weight > 0
    if not seen.any():
        raise ValueError(
            f"cameras see nothing: no vertex of the mesh is in front of, inside the image of and visible from any of the {len(cams)} camera(s); check the poses"
        )
    colors = np.full((len(v), 3), GREY)
    colors[seen] = total[seen] / weight[seen, None]
    filled = 0
    if fill == "diffuse" and not seen.all():
        filled = int(_diffuse(colors, seen, edges).sum())
    unseen = int((~seen).sum())
    unreached = unseen - filled
    if unseen:
        log.info("colour: %d of %d vertices seen by no camera; %d filled from neighbours, %d left grey", unseen, len(v), filled, unreached)
    return ColorResult(np.clip(colors, 0.0, 1.0), weight, seen, views, filled, unreached)


def subdivide_for_images(mesh, cameras: Sequence[Camera], pixels_per_edge: float = 1.0, max_triangles: int = MAX_TRIANGLES):
    """Subdivide a mesh until its edges project to about ``pixels_per_edge`` pixels.

    Each Open3D midpoint subdivision halves every edge and quadruples the
    triangles; the number of rounds is the smallest that brings the median
    projected edge length (over every camera, edges with both ends inside the
    image) to ``pixels_per_edge`` or below, so that a vertex sits about every
    pixel and the colours keep the photographs' detail.

    Parameters
    ----------
    mesh : Open3D TriangleMesh
    cameras : sequence of Camera
        Pinhole cameras with an image size.
    pixels_per_edge : float
        Target median edge length in pixels, > 0.
    max_triangles : int
        Never produce more triangles than this: rounds stop before the count
        would exceed it (each round multiplies it by 4, so one round too many
        on a 500k-triangle mesh is 8 million triangles, gigabytes for the
        mesh and a minute of ray casting per camera).  The default, 2 million,
        colours in seconds per camera and a few hundred MB.

    Returns
    -------
    Open3D TriangleMesh
        A subdivided copy (the input itself if no round is needed); vertex
        colours, if any, are interpolated.
    """
    import open3d as o3d

    pixels_per_edge = check_number("pixels_per_edge", pixels_per_edge, low=0.0, low_open=True)
    max_triangles = check_number("max_triangles", max_triangles, low=1, integer=True)
    v, t = mesh_arrays(mesh)
    cams = as_cameras(cameras, "colours from images", allow_empty=True)
    lengths = [np.empty(0)]
    edges = unique_edges(t)[0]
    for cam in cams:
        pix, _ = cam.project(v)
        inside = cam.in_image(v)
        e = edges[inside[edges[:, 0]] & inside[edges[:, 1]]]
        lengths.append(np.linalg.norm(pix[e[:, 0]] - pix[e[:, 1]], axis=1))
    lengths = np.concatenate(lengths)
    if not len(lengths):
        raise ValueError("cameras see nothing: no mesh edge projects inside any image, so the pixel size is unknown")
    median = float(np.median(lengths))
    rounds = max(0, math.ceil(math.log2(median / pixels_per_edge))) if median > 0 else 0
    cap = int(math.floor(math.log(max_triangles / len(t), 4))) if len(t) <= max_triangles else 0
    if rounds > cap:
        log.info("subdivide_for_images: %d rounds wanted (median edge %.3g px), %d allowed by max_triangles=%d", rounds, median, cap, max_triangles)
        rounds = cap
    if not hasattr(mesh, "subdivide_midpoint"):
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t.astype(np.int32)))
    if rounds == 0:
        return mesh
    return mesh.subdivide_midpoint(number_of_iterations=rounds)


# -- coloured points ----------------------------------------------------------


def colors_from_points(vertices, points, colors, k: int = 8, power: float = 2.0) -> np.ndarray:
    """Inverse-distance weighted colours of the nearest coloured points.

    Parameters
    ----------
    vertices : (V, 3) array_like or Open3D mesh
        Where colours are wanted.
    points : (N, 3) array_like
        Coloured points (a coloured point cloud, or voxel centres).
    colors : (N, 3) array_like
        Their colours, floats in [0, 1] (or uint8 0-255).
    k : int
        Neighbours averaged (capped at N).
    power : float
        Weights ``1 / distance**power`` (Shepard); a vertex on a point takes
        that point's colour.

    Returns
    -------
    (V, 3) float64 array in [0, 1]
    """
    if hasattr(vertices, "vertices") and not isinstance(vertices, np.ndarray):
        vertices = np.asarray(vertices.vertices)
    x = as_points(vertices, name="vertices")
    pts = as_points(points, name="points")
    c = np.asarray(colors)
    if c.shape != (len(pts), 3):
        raise ValueError(f"colors must have one RGB row per point: expected ({len(pts)}, 3), got {c.shape}")
    if c.dtype == np.uint8:
        c = c / 255.0
    c = c.astype(float)
    if not np.isfinite(c).all() or c.min() < 0 or c.max() > 1:
        raise ValueError("colors must be floats in [0, 1] (or uint8)")
    k = min(check_number("k", k, low=1, integer=True), len(pts))
    power = check_number("power", power, low=0.0)
    dist, idx = cKDTree(pts).query(x, k=k)
    dist = dist.reshape(len(x), k)
    idx = idx.reshape(len(x), k)
    exact = dist[:, 0] == 0
    with np.errstate(divide="ignore"):
        w = np.where(exact[:, None], (dist == 0).astype(float), 1.0 / np.maximum(dist, 1e-300) ** power)
    w /= w.sum(axis=1, keepdims=True)
    return np.clip(np.einsum("vk,vkc->vc", w, c[idx]), 0.0, 1.0)


# -- one entry point ----------------------------------------------------------


def color_mesh(
    mesh,
    *,
    cameras=None,
    images=None,
    points=None,
    colors=None,
    subdivide: bool = False,
    pixels_per_edge: float = 1.0,
    max_triangles: int = MAX_TRIANGLES,
    k: int = 8,
    **options,
):
    """A copy of ``mesh`` with vertex colours from photographs or from coloured points.

    Parameters
    ----------
    mesh : Open3D TriangleMesh or (vertices, triangles)
    cameras, images
        Calibrated photographs (see :func:`colors_from_images`).
    points, colors
        A coloured point cloud or coloured voxel centres (see
        :func:`colors_from_points`).  With photographs as well, they colour
        the vertices no camera sees (instead of diffusing neighbours' colours).
    subdivide : bool
        First subdivide so edges project to about ``pixels_per_edge`` pixels
        (:func:`subdivide_for_images`, at most ``max_triangles``).
    k : int
        Neighbours for :func:`colors_from_points`.
    **options
        Passed to :func:`colors_from_images` (``normals``, ``depth_tolerance``,
        ``min_cosine``, ``visibility``, ``fill``).

    Returns
    -------
    Open3D TriangleMesh
        A new mesh with ``vertex_colors`` set (the input is not modified).
    """
    import open3d as o3d

    v, t = mesh_arrays(mesh)
    if hasattr(mesh, "subdivide_midpoint"):
        out = o3d.geometry.TriangleMesh(mesh)
    else:
        out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t.astype(np.int32)))
    has_images = images is not None or cameras is not None
    has_points = points is not None or colors is not None
    if has_images and (images is None or cameras is None):
        raise ValueError("colour from photographs needs both cameras and images")
    if has_points and (points is None or colors is None):
        raise ValueError("colour from points needs both points and colors")
    if not has_images and not has_points:
        raise ValueError("nothing to colour from: give cameras and images, or points and colors")
    if has_images:
        if subdivide:
            out = subdivide_for_images(out, cameras, pixels_per_edge, max_triangles)
        if has_points:
            options["fill"] = "grey"
        res = colors_from_images(out, cameras, images, **options)
        rgb = res.colors.copy()
        if has_points and not res.seen.all():
            rgb[~res.seen] = colors_from_points(np.asarray(out.vertices)[~res.seen], points, colors, k=k)
    else:
        rgb = colors_from_points(np.asarray(out.vertices), points, colors, k=k)
    out.vertex_colors = o3d.utility.Vector3dVector(rgb)
    return out
