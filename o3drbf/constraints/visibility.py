"""Which cameras see which points, and the exterior constraints they prove.

A camera that sees a surface point proves the segment between them is empty
(method.md section 4).  :func:`visibility` decides, for every point and
camera, whether the point is in front of the camera, inside its image and
unobstructed; :func:`exterior_constraints` turns each such sighting into an
exterior point (f = -1) a fixed distance from the surface toward the camera.

Occlusion is decided by casting rays against an occupancy proxy of the
points (a walk through its voxels, :class:`VoxelOccluder`; Open3D's
``RaycastingScene`` for a mesh occluder): the voxels that hold a point,
dilated once (26-neighbourhood) so that the shell has no holes where
the samples cover the surface more finely than a voxel (default voxel: three
mean spacings).  A ray starts ``margin`` away from its point so that it
leaves the point's own voxels; a ray that grazes the surface stays inside the
proxy longer and counts as blocked, which errs on the safe side (fewer
sightings, about half of the front-facing ones on random samples).  By
default points share one ray per small cell of voxels.

Limits: a ray can still slip through the proxy where the samples leave a
hole larger than a voxel, and parts thinner than ``margin`` cannot hide
their far side.  The ``offset / 2`` test in :func:`exterior_constraints`
catches most of what follows from either, but not all: give sparse data a
larger ``voxel_size``, or all input points as ``occluder``.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from numba import njit, prange
from scipy.spatial import cKDTree

from o3drbf.cameras.model import as_cameras
from o3drbf.mesh.arrays import mesh_arrays, raycasting_scene
from o3drbf.prep.sampling import mean_spacing
from o3drbf.validation import as_points, check_number, shown

__all__ = ["visibility", "exterior_constraints", "occupancy_mesh", "seen_by", "VoxelOccluder"]

#: Default voxel size of the occupancy proxy, in mean point spacings.
VOXEL_SPACINGS = 3.0
#: Default ray start offset, in voxel sizes.
MARGIN_VOXELS = 3.5
#: Dilations (26-neighbourhood) of the occupied voxels.  A ray that crosses the
#: surface at x passes through x's voxel, which the dilation fills as soon as a
#: sample lies within one voxel of x: the shell has no tunnels where the
#: samples cover the surface more finely than a voxel.
DILATION = 1
#: Side of the cells whose points share one ray (``rays="voxel"``), in voxel sizes.
GROUP_VOXELS = 2.0
#: Most cells in the dense occupancy grid; coarser voxels beyond.
MAX_GRID_CELLS = 64_000_000
#: Rays per occlusion test (bounds memory).
RAY_CHUNK = 2_000_000
#: Exterior candidates kept per wanted exterior point before Poisson-disc.
OVERSAMPLE = 2


def _threads() -> int:
    """CPUs this process may use (Open3D's automatic choice oversubscribes shared machines)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _label(cam, c: int) -> str:
    return f"camera {c}" + (f" ({cam.name})" if cam.name else "")


def _spacing(points: np.ndarray, tree: cKDTree | None = None, sample: int = 20_000, seed: int = 0) -> float:
    """Mean nearest-neighbour distance, estimated from a random subset of queries."""
    if len(points) < 2:
        raise ValueError("at least 2 points are needed to estimate their spacing")
    spacing = mean_spacing(points, sample=sample, tree=tree, seed=seed)
    if spacing <= 0:
        raise ValueError("points are (mostly) duplicates: their mean spacing is zero")
    return spacing


def _occupancy(points: np.ndarray, voxel_size: float):
    """Dense occupancy grid of the points, dilated ``DILATION`` times and padded.

    Returns the grid (nx, ny, nz) bool, its origin (3,) and the voxel size
    (enlarged if the grid would exceed ``MAX_GRID_CELLS``).
    """
    lo = points.min(axis=0)
    extent = points.max(axis=0) - lo
    pad = DILATION + 1
    cells = float(np.prod(extent / voxel_size + 2 * pad + 1))
    if cells > MAX_GRID_CELLS:
        voxel_size *= (cells / MAX_GRID_CELLS) ** (1 / 3) * 1.01
    origin = lo - pad * voxel_size
    ijk = np.floor((points - origin) / voxel_size).astype(np.int64)
    occ = np.zeros(ijk.max(axis=0) + pad + 1, dtype=bool)
    occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return _dilated(occ, DILATION), origin, voxel_size


def _dilated(occ: np.ndarray, steps: int) -> np.ndarray:
    """``occ`` grown by ``steps`` voxels along every axis and diagonal (a cube of side ``2 steps + 1``: what
    ``scipy.ndimage.binary_dilation`` gives with a 3 x 3 x 3 structure, ``steps`` iterations and nothing
    beyond the edges), one axis at a time."""
    out = occ.copy()
    for _ in range(steps):
        for axis in range(out.ndim):
            grown = out.copy()
            lead = [slice(None)] * out.ndim
            rest = [slice(None)] * out.ndim
            lead[axis], rest[axis] = slice(1, None), slice(None, -1)
            grown[tuple(lead)] |= out[tuple(rest)]
            grown[tuple(rest)] |= out[tuple(lead)]
            out = grown
    return out


def _boundary_faces(occ: np.ndarray, origin: np.ndarray, voxel_size: float):
    """Vertices ``(V, 3)`` and triangles ``(T, 3)`` of the faces between occupied and empty cells."""
    cdims = np.array(occ.shape) + 1  # corner grid
    quads = []
    for axis in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis] = slice(0, -1)
        hi[axis] = slice(1, None)
        base = np.argwhere(occ[tuple(lo)] != occ[tuple(hi)])  # face between cells i and i+1
        if not len(base):
            continue
        base[:, axis] += 1
        u, v = [k for k in range(3) if k != axis]
        du = np.zeros(3, np.int64)
        dv = np.zeros(3, np.int64)
        du[u] = 1
        dv[v] = 1
        quads.append(np.stack([base, base + du, base + du + dv, base + dv], axis=1))
    if not quads:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    corners = np.concatenate(quads)  # (F, 4, 3) corner indices
    flat = (corners[..., 0] * cdims[1] + corners[..., 1]) * cdims[2] + corners[..., 2]
    used = np.zeros(int(np.prod(cdims)), dtype=bool)
    used[flat.ravel()] = True
    ids = np.flatnonzero(used)
    quad = np.searchsorted(ids, flat)
    tri = np.concatenate([quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]]).astype(np.int32)
    ijk = np.stack(np.unravel_index(ids, tuple(cdims)), axis=1)
    return origin + voxel_size * ijk, tri


def _voxel_groups(points: np.ndarray, voxel_size: float):
    """Group points by voxel: ``(inverse (N,), representatives (G, 3))``, the mean point of each voxel."""
    ijk = np.floor((points - points.min(axis=0)) / voxel_size).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    flat = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    reps = np.stack([np.bincount(inverse, weights=points[:, k]) for k in range(3)], axis=1) / counts[:, None]
    return inverse, reps


def occupancy_mesh(points, voxel_size: float):
    """The occupancy proxy: boundary faces of the voxels that hold a point.

    Parameters
    ----------
    points : (N, 3) array_like
    voxel_size : float
        Side of the voxels (> 0).  Enlarged when the grid would exceed
        ``MAX_GRID_CELLS`` cells.

    Returns
    -------
    vertices : (V, 3) array
    triangles : (T, 3) int32 array
    voxel_size : float
        The voxel size used.
    """
    pts = as_points(points)
    voxel_size = check_number("voxel_size", voxel_size, low=0.0, low_open=True)
    occ, origin, vs = _occupancy(pts, voxel_size)
    verts, tri = _boundary_faces(occ, origin, vs)
    return verts, tri, vs


def seen_by(point_camera, n: int, c: int) -> np.ndarray:
    """``(n, c)`` bool mask from a camera index per point (-1 unknown) or a mask.

    Parameters
    ----------
    point_camera : (n,) int array_like or (n, c) bool array_like
    n, c : int
        Number of points and of cameras.

    Returns
    -------
    (n, c) bool array
    """
    pc = np.asarray(point_camera)
    if pc.dtype == bool:
        if pc.shape != (n, c):
            raise ValueError(f"point_camera as a mask must have shape ({n}, {c}), got {pc.shape}")
        return pc.copy()
    if pc.shape != (n,):
        raise ValueError(f"point_camera must have shape ({n},) (camera index per point, -1 unknown), got {pc.shape}")
    if not np.issubdtype(pc.dtype, np.number) or (pc != np.round(pc)).any():
        raise ValueError("point_camera must hold whole numbers (camera index, -1 for unknown)")
    pc = pc.astype(np.int64)
    bad = (pc < -1) | (pc >= c)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"point_camera[{i}] = {pc[i]} is not a camera index: there are {c} cameras (-1 for unknown)")
    mask = np.zeros((n, c), dtype=bool)
    ok = pc >= 0
    mask[np.flatnonzero(ok), pc[ok]] = True
    return mask


def _known(point_camera, n: int, c: int) -> np.ndarray | None:
    return None if point_camera is None else seen_by(point_camera, n, c)


class VoxelOccluder:
    """The occupancy proxy as a grid: a segment is blocked where it crosses a face between an occupied and an
    empty voxel of the grid.

    Those faces are the proxy's boundary faces (:func:`occupancy_mesh`), so
    this is ray casting against them: a segment that enters occupied voxels,
    or starts in one and leaves it for an empty one, is blocked; one that
    leaves the grid straight from the occupied voxels it starts in is not
    (the grid's outer faces are not the proxy's).  Each segment walks the
    grid voxel by voxel (Amanatides and Woo), in compiled code.

    Parameters
    ----------
    occ : (nx, ny, nz) bool array
    origin : (3,) array
        Lowest corner of voxel (0, 0, 0).
    voxel_size : float
    """

    def __init__(self, occ: np.ndarray, origin: np.ndarray, voxel_size: float):
        self.occ = np.ascontiguousarray(occ, dtype=np.bool_)
        self.origin = np.asarray(origin, dtype=float)
        self.voxel_size = float(voxel_size)

    def blocked(self, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """``(K,)`` bool: whether each segment ``starts[i] -> ends[i]`` (data coordinates) meets an occupied voxel."""
        a = np.ascontiguousarray((np.asarray(starts, dtype=float) - self.origin) / self.voxel_size)
        b = np.ascontiguousarray((np.asarray(ends, dtype=float) - self.origin) / self.voxel_size)
        out = np.empty(len(a), dtype=np.bool_)
        _walk_segments(a, b, self.occ, out)
        return out


@njit(cache=True, parallel=True)
def _walk_segments(a, b, occ, out):
    """``out[r]``: segment ``a[r] -> b[r]`` (grid units: voxel (i, j, k) is [i, i + 1) x ...) passes between an
    occupied and an empty voxel."""
    for r in prange(a.shape[0]):
        out[r] = _walk(a[r], b[r], occ)


@njit(cache=True)
def _walk(a, b, occ):
    dims = occ.shape
    t0, t1 = 0.0, 1.0
    d = np.empty(3)
    for ax in range(3):  # the part of the segment inside the grid
        d[ax] = b[ax] - a[ax]
        if d[ax] == 0.0:
            if a[ax] < 0.0 or a[ax] > dims[ax]:
                return False
        else:
            lo, hi = -a[ax] / d[ax], (dims[ax] - a[ax]) / d[ax]
            if lo > hi:
                lo, hi = hi, lo
            t0, t1 = max(t0, lo), min(t1, hi)
    if t0 > t1:
        return False
    cell = np.empty(3, np.int64)
    step = np.empty(3, np.int64)
    t_max = np.empty(3)
    t_delta = np.empty(3)
    for ax in range(3):
        c = min(max(np.int64(np.floor(a[ax] + t0 * d[ax])), 0), dims[ax] - 1)
        cell[ax] = c
        if d[ax] > 0.0:
            step[ax], t_max[ax], t_delta[ax] = 1, (c + 1 - a[ax]) / d[ax], 1.0 / d[ax]
        elif d[ax] < 0.0:
            step[ax], t_max[ax], t_delta[ax] = -1, (c - a[ax]) / d[ax], -1.0 / d[ax]
        else:
            step[ax], t_max[ax], t_delta[ax] = 0, np.inf, np.inf
    inside = occ[cell[0], cell[1], cell[2]]
    while True:
        ax = 0
        if t_max[1] < t_max[ax]:
            ax = 1
        if t_max[2] < t_max[ax]:
            ax = 2
        if t_max[ax] > t1:
            return False
        cell[ax] += step[ax]
        if cell[ax] < 0 or cell[ax] >= dims[ax]:
            return False
        if occ[cell[0], cell[1], cell[2]] != inside:
            return True
        t_max[ax] += t_delta[ax]


def _resolve_occluder(pts, occluder, voxel_size, margin, tree=None):
    """Set up occlusion: ``(occluder or None, voxel_size, margin, occluding points or None)``: a
    :class:`VoxelOccluder` of the occluding points, or an Open3D ray-casting scene of a mesh.

    ``tree``: an optional KD-tree of the occluding points (``pts`` for a mesh).
    """
    if isinstance(occluder, str):
        if occluder not in ("voxels", "none"):
            raise ValueError(
                f"occluder must be 'voxels', 'none', an (K, 3) array of points or an Open3D mesh, got {shown(occluder) if not isinstance(occluder, np.ndarray) else f'an array of shape {occluder.shape}'}"
            )
        ref = pts
    elif hasattr(occluder, "triangles") or hasattr(occluder, "triangle"):
        ref = None
    else:
        ref = as_points(occluder, name="occluder", min_count=2)
    if voxel_size is None:
        # `tree`, if given, is a KD-tree of these same points.
        voxel_size = VOXEL_SPACINGS * _spacing(pts if ref is None else ref, tree)
    else:
        voxel_size = check_number("voxel_size", voxel_size, low=0.0, low_open=True)
    if isinstance(occluder, str) and occluder == "none":
        return None, voxel_size, 0.0, ref
    if ref is None:
        verts, tri = mesh_arrays(occluder, "occluder")
        scene = raycasting_scene(verts, tri)
    else:
        occ, origin, voxel_size = _occupancy(ref, voxel_size)
        scene = VoxelOccluder(occ, origin, voxel_size)
    margin = MARGIN_VOXELS * voxel_size if margin is None else check_number("margin", margin, low=0.0)
    return scene, voxel_size, margin, ref


def _unobstructed(scene, cam, origins: np.ndarray, margin: float, span: float) -> np.ndarray:
    """``(K,)`` bool: the segment from each origin (moved ``margin`` toward the camera) to the camera is free.

    ``scene``: a :class:`VoxelOccluder` or an Open3D ray-casting scene."""
    free = np.empty(len(origins), dtype=bool)
    for start in range(0, len(origins), RAY_CHUNK):
        p = origins[start : start + RAY_CHUNK]
        d, dist = cam.toward(p)
        if cam.kind == "direction":
            dist = np.full(len(p), span)
        near = dist <= margin  # the camera is within the margin: nothing can be between
        if isinstance(scene, VoxelOccluder):
            begin = p + margin * d
            hit = scene.blocked(begin, begin + d * np.maximum(dist - margin, 0.0)[:, None])
        else:
            import open3d as o3d

            rays = np.empty((len(p), 6), dtype=np.float32)
            rays[:, :3] = p + margin * d
            rays[:, 3:] = d * np.maximum(dist - margin, 0.0)[:, None]  # t in [0, 1] spans start -> camera
            rays[near, 3:] = d[near]
            hit = scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0, nthreads=_threads()).numpy().astype(bool)
        free[start : start + len(p)] = ~hit | near
    return free


def _visibility(pts, cams, occluder, voxel_size, margin, point_camera, strict, rays="voxel", tree=None):
    n, c = len(pts), len(cams)
    known = _known(point_camera, n, c)
    if rays not in ("voxel", "point"):
        raise ValueError(f"rays must be 'voxel' or 'point', got {rays!r}")
    scene, voxel_size, margin, ref = _resolve_occluder(pts, occluder, voxel_size, margin, tree)
    if scene is not None and rays == "voxel":
        group, origins = _voxel_groups(pts, GROUP_VOXELS * voxel_size)
    else:
        group, origins = np.arange(n), pts
    # Rays of direction sensors end beyond everything.
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    if ref is not None and ref is not pts:
        lo, hi = np.minimum(lo, ref.min(axis=0)), np.maximum(hi, ref.max(axis=0))
    span = 2.0 * float(np.linalg.norm(hi - lo)) + 2.0 * margin + 1e-9
    visible = np.zeros((n, c), dtype=bool)
    front = np.zeros(c, dtype=np.int64)
    in_view = np.zeros(c, dtype=np.int64)
    for j, cam in enumerate(cams):
        in_front_j, ok = cam.in_view(pts)
        front[j] = in_front_j.sum()
        in_view[j] = ok.sum()
        idx = np.flatnonzero(ok)
        if scene is None or not len(idx):
            visible[idx, j] = True
            continue
        groups = np.flatnonzero(np.bincount(group[idx], minlength=len(origins)))
        free = np.zeros(len(origins), dtype=bool)
        free[groups] = _unobstructed(scene, cam, origins[groups], margin, span)
        visible[idx, j] = free[group[idx]]
    if known is not None:
        visible |= known
    seen = visible.sum(axis=0)
    if strict:
        if not front.any():
            raise ValueError(
                f"all {n} points are behind every camera; check the pose convention "
                "(x_cam = R X + t, the camera looks along +z of its frame)"
            )
        if not in_view.any():
            raise ValueError(f"none of the {n} points projects inside any camera's image; check K and the image size")
        blind = np.flatnonzero(seen == 0)
        if len(blind):
            j = int(blind[0])
            raise ValueError(
                f"{len(blind)} camera(s) see no point, first {_label(cams[j], j)}: of {n} points, {front[j]} are in "
                f"front of it, {in_view[j]} inside its image, none unobstructed"
            )
    info = {"in_front": front, "in_view": in_view, "seen": seen, "voxel_size": voxel_size, "margin": margin}
    return visible, info, ref


def visibility(
    points,
    cameras,
    occluder: Any = "voxels",
    voxel_size: float | None = None,
    margin: float | None = None,
    point_camera=None,
    strict: bool = True,
    rays: str = "voxel",
) -> np.ndarray:
    """Which cameras see which points.

    Camera ``c`` sees point ``i`` when the point is in front of the camera,
    inside its image, and the segment between them is not blocked; points
    known to come from a camera (``point_camera``) are visible from it by
    definition.

    Parameters
    ----------
    points : (N, 3) array_like
    cameras : sequence of :class:`o3drbf.cameras.model.Camera`
        Pinhole cameras, centres, or direction sensors (whose free space is
        the half-line against their viewing direction).
    occluder : "voxels", "none", (K, 3) array_like or Open3D TriangleMesh
        What blocks rays: the voxels holding the points (default), nothing,
        the voxels holding other points (e.g. all input points when
        ``points`` is a subset), or a mesh.
    voxel_size : float, optional
        Voxel side of the occupancy proxy; default ``VOXEL_SPACINGS`` times
        the mean nearest-neighbour spacing of the occluding points.
    margin : float, optional
        Rays start this far from their point so they leave its own voxels;
        default ``MARGIN_VOXELS`` voxel sizes.
    point_camera : (N,) int array_like or (N, C) bool array_like, optional
        The camera that produced each point (-1: unknown), or a mask of known
        sightings (COLMAP tracks).
    strict : bool
        Raise when every point is behind every camera or outside every image,
        or when a camera sees no point.
    rays : {"voxel", "point"}
        Cast one ray per camera and cell of ``GROUP_VOXELS`` voxel sizes, from
        the mean of the cell's points, and share the answer among them
        (default, many times fewer rays), or one ray per point.  Front and image tests are
        always per point.

    Returns
    -------
    (N, C) bool array

    Raises
    ------
    ValueError
        Bad input; with ``strict``, cameras that see nothing (named).
    """
    pts = as_points(points)
    cams = as_cameras(cameras)
    visible, _, _ = _visibility(pts, cams, occluder, voxel_size, margin, point_camera, strict, rays)
    return visible


def exterior_constraints(
    points,
    cameras,
    offset: float,
    ratio: float = 0.1,
    seed: int = 0,
    visible=None,
    occluder: Any = "voxels",
    point_camera=None,
    **rays,
):
    """Exterior points (f = -1) a fixed distance from the surface toward the cameras.

    For every point and every camera that sees it, a candidate sits at
    ``p + offset * u``, ``u`` the unit vector toward the camera centre (or
    against a direction sensor's viewing direction).  Candidates closer
    than ``offset / 2`` to any input point are dropped (they would land
    inside a thin part or across a narrow gap); the rest are Poisson-disc
    subsampled to about ``ratio * N``.

    Parameters
    ----------
    points : (N, 3) array_like
        Surface points.
    cameras : sequence of :class:`o3drbf.cameras.model.Camera`
    offset : float
        Distance of every exterior point from its surface point (> 0).
    ratio : float
        Wanted exterior points per surface point (the paper: about 0.1).
    seed : int
        Seeds the candidate thinning and the Poisson-disc order.
    visible : (N, C) bool array_like, optional
        Precomputed :func:`visibility`; otherwise computed here with
        ``occluder``, ``point_camera`` and ``**rays``.
    occluder, point_camera
        As in :func:`visibility`.  When ``occluder`` is an array of points,
        the ``offset / 2`` test also uses them.
    **rays
        ``voxel_size``, ``margin`` and ``rays`` of :func:`visibility`.

    Returns
    -------
    exterior : (M, 3) array
    info : dict
        ``seen`` (C,) points each camera sees; ``in_front``, ``in_view``
        (C,) (when visibility was computed here); ``candidates`` sightings in
        total; ``thinned`` of them kept at random (at most ``OVERSAMPLE``
        times the target) before the distance test; ``dropped_close`` those too close to the data;
        ``exterior`` M; ``source`` (M,) surface point and ``camera`` (M,)
        camera of each exterior point; ``offset``, ``voxel_size``, ``margin``.

    Raises
    ------
    ValueError
        Bad input, cameras that see no point, points behind every camera, or
        no candidate left.
    """
    from o3drbf.prep.sampling import poisson_disc

    unknown = sorted(set(rays) - {"voxel_size", "margin", "rays"})
    if unknown:
        raise ValueError(f"unknown argument(s) {', '.join(unknown)} of exterior_constraints; valid: voxel_size, margin, rays")
    voxel_size, margin = rays.get("voxel_size"), rays.get("margin")
    pts = as_points(points)
    cams = as_cameras(cameras)
    n, c = len(pts), len(cams)
    offset = check_number("offset", offset, low=0.0, low_open=True)
    ratio = check_number("ratio", ratio, low=0.0, low_open=True)
    seed = check_number("seed", seed, low=0, integer=True)
    # The points exterior constraints keep away from; its KD-tree also gives the spacing.
    is_points = not isinstance(occluder, str) and not (hasattr(occluder, "triangles") or hasattr(occluder, "triangle"))
    ref = as_points(occluder, name="occluder", min_count=2) if is_points else pts
    tree = cKDTree(ref)
    if visible is None:
        visible, info, _ = _visibility(pts, cams, occluder, voxel_size, margin, point_camera, True, rays.get("rays", "voxel"), tree)
    else:
        visible = np.asarray(visible)
        if visible.shape != (n, c) or visible.dtype != bool:
            raise ValueError(f"visible must be an ({n}, {c}) bool array, got {visible.dtype} {visible.shape}")
        seen = visible.sum(axis=0)
        if not seen.any():
            raise ValueError(f"no camera sees any of the {n} points (visible is all False)")
        info = {"seen": seen, "voxel_size": voxel_size, "margin": margin}
    total = int(visible.sum())
    target = max(1, int(round(ratio * n)))
    keep_prob = min(1.0, OVERSAMPLE * target / total)
    rng = np.random.default_rng(seed)
    cand, src, cam_of = [], [], []
    for j, cam in enumerate(cams):
        idx = np.flatnonzero(visible[:, j])
        if keep_prob < 1:
            idx = idx[rng.random(len(idx)) < keep_prob]
        if not len(idx):
            continue
        u, _ = cam.toward(pts[idx])
        cand.append(pts[idx] + offset * u)
        src.append(idx)
        cam_of.append(np.full(len(idx), j, dtype=np.int64))
    cand = np.concatenate(cand) if cand else np.zeros((0, 3))
    src = np.concatenate(src) if src else np.zeros(0, np.int64)
    cam_of = np.concatenate(cam_of) if cam_of else np.zeros(0, np.int64)
    d, _ = tree.query(cand, distance_upper_bound=0.5 * offset, workers=-1)
    # Numerical slack: the source point itself is exactly `offset` away.
    ok = ~(d < 0.5 * offset)
    dropped = int((~ok).sum())
    cand, src, cam_of = cand[ok], src[ok], cam_of[ok]
    if not len(cand):
        raise ValueError(
            f"every exterior candidate ({dropped}) lands closer than offset/2 = {0.5 * offset:g} to an input point; "
            "use a smaller offset"
        )
    if len(cand) > target:
        sel = poisson_disc(cand, count=target, seed=seed)
        cand, src, cam_of = cand[sel], src[sel], cam_of[sel]
    info.update(
        candidates=total,
        thinned=int(ok.size),
        dropped_close=dropped,
        exterior=len(cand),
        source=src,
        camera=cam_of,
        offset=offset,
    )
    return cand, info
