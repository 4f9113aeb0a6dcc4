"""What ``o3drbf view`` shows, read from disk: points (and cameras), or a saved model.

No PyVista here: everything is arrays, so the loading rules are testable
without a display.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["ViewInput", "load_view_input", "model_constraints"]

#: Suffix of a saved implicit model (``o3drbf reconstruct --save-model``).
MODEL_SUFFIX = ".npz"


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
    """

    source: str
    points: np.ndarray | None = None
    normals: np.ndarray | None = None
    cameras: object = None
    point_camera: np.ndarray | None = None
    model: object = None
    normals_estimated: bool = False

    @property
    def is_model(self) -> bool:
        return self.model is not None

    def bounds(self) -> np.ndarray:
        """(2, 3) box around everything in the data's coordinates."""
        if self.points is not None:
            return np.array([self.points.min(axis=0), self.points.max(axis=0)])
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


def load_view_input(path: str, cameras: str | None = None) -> ViewInput:
    """Read INPUT (and ``--cameras FILE``) the way ``o3drbf reconstruct`` does.

    Parameters
    ----------
    path : str
        A point cloud (PLY, PCD, XYZ, ...), a file or folder holding points
        and cameras (scan JSON, Stanford ``.conf``, COLMAP folder,
        ``bundle.out``), or a saved model ``.npz``.
    cameras : str, optional
        A camera file for a plain point cloud.

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
