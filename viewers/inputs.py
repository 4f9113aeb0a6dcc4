"""What ``o3drbf view`` shows, read from disk: points (and cameras), a saved model, or a finished mesh.

No PyVista here: everything is arrays, so the loading rules are testable
without a display.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["ViewInput", "load_view_input", "model_constraints", "has_faces", "read_mesh_fields"]

from o3drbf.io.files import MESH_FORMATS, POINT_FORMATS

#: Suffix of a saved implicit model (``o3drbf reconstruct --save-model``).
MODEL_SUFFIX = ".npz"

#: PLY vertex properties that are geometry or colour, not a field to colour by.
_GEOMETRY_PROPERTIES = ("positions", "normals", "colors")


@dataclass
class ViewInput:
    """The data behind one viewer session.

    Attributes
    ----------
    source : str
        The INPUT path, for titles and messages.
    points : (N, 3) array or None
        Input points (None for a saved model).
    normals : (N, 3) array or None
        Outward normals (given, or estimated once here when neither normals
        nor cameras are available, so refits do not redo it).
    cameras : CameraSet or list of Camera or None
    point_camera : (N,) int array or None
        The camera that produced each point (-1 unknown).
    model : ImplicitSurface or None
        A saved model: no refit possible, only re-extraction.
    normals_estimated : bool
        True when ``normals`` were estimated by Open3D here.
    mesh : (vertices (V, 3), triangles (F, 3)) or None
        A finished mesh, shown as it is (no points, no refit).
    vertex_fields : dict of str -> (V,) array
        The mesh's per-vertex scalar fields (PLY vertex properties beyond
        x, y, z, normals and colours, e.g. ``confidence``).
    vertex_colors : (V, 3) array in [0, 1] or None
    vertex_normals : (V, 3) array or None
    """

    source: str
    points: np.ndarray | None = None
    normals: np.ndarray | None = None
    cameras: object = None
    point_camera: np.ndarray | None = None
    model: object = None
    normals_estimated: bool = False
    mesh: tuple | None = None
    vertex_fields: dict = field(default_factory=dict)
    vertex_colors: np.ndarray | None = None
    vertex_normals: np.ndarray | None = None

    @property
    def is_model(self) -> bool:
        return self.model is not None

    @property
    def is_mesh(self) -> bool:
        return self.mesh is not None

    def bounds(self) -> np.ndarray:
        """(2, 3) box around everything in the data's coordinates."""
        if self.points is not None:
            return np.array([self.points.min(axis=0), self.points.max(axis=0)])
        if self.mesh is not None:
            v = self.mesh[0]
            return np.array([v.min(axis=0), v.max(axis=0)])
        box = self.model.metadata.get("bounds")  # the data's box, padded, saved by reconstruct
        if box is not None and np.asarray(box, dtype=float).shape == (2, 3):
            return np.asarray(box, dtype=float)
        pts = self.model.normalization.inverse(self.model.centres)
        return np.array([pts.min(axis=0), pts.max(axis=0)])

    def model_params(self) -> dict:
        """The saved model's lambda_surface, delta and tau (what the fixed sliders show)."""
        if self.model is None:
            return {}
        out = {k: float(v) for k, v in self.model.kernel.params.items() if k in ("delta", "tau")}
        lam = self.model.metadata.get("lambda_surface")
        if lam is not None:
            out["lambda_surface"] = float(lam)
        return out


def load_view_input(path: str, cameras: str | None = None, refit: bool = False) -> ViewInput:
    """Read INPUT (and ``--cameras FILE``) the way ``o3drbf reconstruct`` does; a mesh as it is.

    Parameters
    ----------
    path : str
        A point cloud (PLY, PCD, XYZ, ...), a file or folder holding points
        and cameras (scan JSON, Stanford ``.conf``, COLMAP folder,
        ``bundle.out``), a saved model ``.npz``, or a mesh with faces (PLY,
        OBJ, STL, OFF, glTF: see :func:`has_faces`).
    cameras : str, optional
        A camera file for a plain point cloud.
    refit : bool
        Take a mesh's vertices as a point cloud to fit (``--refit``)
        instead of showing the mesh as it is.

    Returns
    -------
    ViewInput

    Raises
    ------
    FileNotFoundError
        INPUT or the camera file does not exist.
    ValueError
        Unreadable input, cameras given twice, cameras for a saved model.
    """
    from o3drbf.pointset import read_input

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"input not found: {p}")
    if p.suffix.lower() == MODEL_SUFFIX:
        if cameras:
            raise ValueError(f"{p} is a saved model (no points); --cameras needs a point cloud as INPUT")
        from o3drbf.surface import ImplicitSurface

        return ViewInput(source=str(p), model=ImplicitSurface.load(p))
    if not refit and has_faces(p):
        if cameras:
            raise ValueError(f"{p} is a mesh, shown as it is; --cameras needs a point cloud as INPUT (or add --refit)")
        return read_mesh_fields(p)
    if refit and p.suffix.lower() in MESH_FORMATS and p.suffix.lower() not in POINT_FORMATS:
        return _vertices_as_points(p)
    data = read_input(p, cameras=cameras or None)
    points, normals, cams, point_camera = data.points, data.normals, data.cameras, data.point_camera
    estimated = False
    if normals is None and cams is None:
        from o3drbf.pipeline import estimate_normals

        normals = estimate_normals(points)
        estimated = True
    return ViewInput(
        source=str(p),
        points=points,
        normals=None if normals is None else np.asarray(normals, dtype=float),
        cameras=cams,
        point_camera=None if point_camera is None else np.asarray(point_camera),
        normals_estimated=estimated,
    )


def model_constraints(surface) -> dict[str, np.ndarray]:
    """The constraint positions of a saved model, by kind (data coordinates).

    A model's RBF centres are its constraints, stored surface first, then
    exterior, then sphere (:func:`o3drbf.reconstruct`); the counts saved in
    ``metadata["counts"]`` split them.  Without usable counts, centres where
    f > -0.5 count as surface constraints (f = 0 there) and the rest as
    exterior (f = -1).

    Returns
    -------
    dict
        ``{"surface": (S, 3), "exterior": (E, 3), "sphere": (P, 3)}``.
    """
    centres = surface.normalization.inverse(surface.centres)
    counts = surface.metadata.get("counts") or {}
    order = ("surface", "exterior", "interior", "sphere")
    sizes = [int(counts.get(k, 0)) for k in order]
    if counts and sum(sizes) == len(centres):
        bounds = np.cumsum([0, *sizes])
        parts = {k: centres[bounds[i] : bounds[i + 1]] for i, k in enumerate(order)}
        parts["exterior"] = np.vstack([parts["exterior"], parts.pop("interior")])
        return parts
    f = surface.evaluate(centres)
    return {"surface": centres[f > -0.5], "exterior": centres[f <= -0.5], "sphere": np.zeros((0, 3))}


def has_faces(path) -> bool:
    """Whether ``path`` is a mesh with at least one face.

    A ``.ply`` is a mesh when its header announces ``element face N`` with
    N > 0 (read from the header only); ``.obj``, ``.stl``, ``.off`` and
    ``.gltf`` files are read with Open3D and must hold triangles.  Other
    files (point formats, folders) are not meshes.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if not p.is_file() or suffix not in MESH_FORMATS:
        return False
    if suffix == ".ply":
        import re

        with open(p, "rb") as fh:
            head = fh.read(65536)
        end = head.find(b"end_header")
        header = head[: end if end >= 0 else len(head)].decode("ascii", errors="replace")
        m = re.search(r"^element\s+face\s+(\d+)", header, flags=re.MULTILINE)
        return bool(m) and int(m.group(1)) > 0
    import open3d as o3d

    return len(o3d.io.read_triangle_mesh(str(p)).triangles) > 0


def read_mesh_fields(path) -> ViewInput:
    """A mesh file as it is: vertices, triangles, vertex normals and colours, and every per-vertex scalar field.

    Scalar fields are the PLY vertex properties other than x, y, z,
    normals and colours (read with Open3D's tensor reader, which keeps
    them); other formats have none.

    Raises
    ------
    ValueError
        No triangles, bad indices or non-finite vertices (see
        :func:`o3drbf.mesh.arrays.mesh_arrays`), or fields whose length is
        not the vertex count.
    """
    import open3d as o3d

    from o3drbf.mesh.arrays import mesh_arrays

    p = Path(path)
    mesh = o3d.io.read_triangle_mesh(str(p))
    verts, tris = mesh_arrays(mesh, name=str(p))
    fields: dict[str, np.ndarray] = {}
    if p.suffix.lower() == ".ply":
        attrs = o3d.t.io.read_point_cloud(str(p)).point
        for key in attrs:  # TensorMap iterates over attribute names
            if key in _GEOMETRY_PROPERTIES:
                continue
            values = attrs[key].numpy()
            if values.ndim == 2 and values.shape[1] == 1:
                values = values[:, 0]
            if values.ndim != 1:
                continue  # a vector property: not a scalar field
            if len(values) != len(verts):
                raise ValueError(f"{p}: vertex property {key!r} has {len(values)} values for {len(verts)} vertices; fix the file")
            fields[key] = values.astype(float)
    colors = np.asarray(mesh.vertex_colors, dtype=float) if mesh.has_vertex_colors() else None
    normals = np.asarray(mesh.vertex_normals, dtype=float) if mesh.has_vertex_normals() else None
    return ViewInput(source=str(p), mesh=(verts, tris), vertex_fields=fields, vertex_colors=colors, vertex_normals=normals)


def _vertices_as_points(path: Path) -> ViewInput:
    """A mesh file's vertices as a point cloud to fit (``--refit`` on an .obj, .stl, .off or .gltf)."""
    from o3drbf.pipeline import estimate_normals

    data = read_mesh_fields(path)
    points = data.mesh[0]
    normals = data.vertex_normals if data.vertex_normals is not None else estimate_normals(points)
    return ViewInput(source=str(path), points=points, normals=normals, normals_estimated=data.vertex_normals is None)
