"""The implicit surface f(x) = P(x) + sum_i w_i phi(|x - c_i|), as an object.

f > 0 inside, f = 0 on the surface, f < 0 outside.  Points are given and
returned in the data's own coordinates; internally f lives in the
normalized 2x2x2 box (:class:`~o3drbf.prep.normalize.Normalization`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from o3drbf.validation import as_points
from o3drbf.io.files import atomic_path
from o3drbf.rbf.kernels import Kernel, make_kernel
from o3drbf.prep.normalize import Normalization
from o3drbf.rbf.sums import DEFAULT_CHUNK_BYTES, kernel_sum, polynomial_basis

__all__ = ["ImplicitSurface"]

_FORMAT = "o3drbf-implicit-surface"
_VERSION = 1


@dataclass
class ImplicitSurface:
    """A fitted implicit function.

    Parameters
    ----------
    kernel : Kernel
    centres : (N, 3) array
        RBF centres, in the normalized box.
    weights : (N,) array
    poly : (m,) array
        Polynomial coefficients for the basis ``[1]`` or ``[1 x y z]`` (box coordinates).
    normalization : Normalization
        Data -> box map.
    metadata : dict
        Parameters and provenance (JSON-serializable), kept through save/load.
    """

    kernel: Kernel
    centres: np.ndarray
    weights: np.ndarray
    poly: np.ndarray
    normalization: Normalization = field(default_factory=Normalization.identity)
    metadata: dict = field(default_factory=dict)
    #: Optional faster evaluator ``(box_points, gradient) -> values[, grads]`` (e.g. fast multipole).
    evaluator: object = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        self.centres = np.ascontiguousarray(self.centres, dtype=float)
        self.weights = np.ascontiguousarray(self.weights, dtype=float)
        self.poly = np.ascontiguousarray(self.poly, dtype=float)

    # -- evaluation -------------------------------------------------------------
    def evaluate_box(self, points, gradient: bool = False, chunk_bytes: int = DEFAULT_CHUNK_BYTES, approximate: bool = False):
        """f (and grad f) at points given in box coordinates.

        ``approximate=True`` lets the multi-order kernel come from cubic
        tables (values ~1e-9 relative, gradients ~1e-6): what meshing uses.
        """
        x = np.asarray(points, dtype=float).reshape(-1, 3)
        if self.evaluator is not None:
            out = self.evaluator(x, gradient)
        else:
            table = self._table() if approximate else None
            out = kernel_sum(self.kernel, self.centres, self.weights, x, gradient=gradient, chunk_bytes=chunk_bytes, table=table)
        q = polynomial_basis(x, self.kernel.polynomial_degree)
        if gradient:
            vals, grads = out
            vals = vals + q @ self.poly
            if self.kernel.polynomial_degree >= 1:
                grads = grads + self.poly[1:4]
            return vals, grads
        return out + q @ self.poly

    def _table(self):
        from o3drbf.rbf import compiled as _direct

        if not _direct.supports_table(self.kernel):
            return None
        if getattr(self, "_kernel_table", None) is None or self._kernel_table[0] is not self.kernel:
            self._kernel_table = (self.kernel, _direct.KernelTable(self.kernel))
        return self._kernel_table[1]

    def __call__(self, points) -> np.ndarray:
        """f at ``points`` ((N, 3) or (3,), data coordinates); memory bounded for any N."""
        return self.evaluate(points)

    def evaluate(self, points, gradient: bool = False):
        """f, and with ``gradient=True`` also grad f, at points in data coordinates.

        Returns
        -------
        values : (N,) array
        gradients : (N, 3) array, only if ``gradient``; d f / d x in data coordinates.
        """
        x = as_points(points, min_count=0)
        out = self.evaluate_box(self.normalization.forward(x), gradient=gradient)
        if gradient:
            vals, grads = out
            return vals, grads * self.normalization.scale
        return out

    def gradient(self, points) -> np.ndarray:
        """grad f at ``points`` (data coordinates), shape (N, 3)."""
        return self.evaluate(points, gradient=True)[1]

    def normals(self, points) -> np.ndarray:
        """Outward unit normals -grad f / |grad f| (f > 0 inside)."""
        g = self.gradient(points)
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        return -g / np.where(norm > 0, norm, 1.0)

    # -- persistence --------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write to one ``.npz`` file (written atomically); exact round trip with :meth:`load`."""
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"model file must end in .npz, got {str(path)!r}")
        header = {
            "format": _FORMAT,
            "version": _VERSION,
            "kernel": self.kernel.to_dict(),
            "normalization": self.normalization.to_dict(),
            "metadata": self.metadata,
        }
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(
                    fh,
                    header=np.array(json.dumps(header, default=_json_default)),
                    centres=self.centres,
                    weights=self.weights,
                    poly=self.poly,
                    center=np.asarray(self.normalization.center, dtype=float),
                    scale=np.array(self.normalization.scale),
                )
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ImplicitSurface":
        """Read a model written by :meth:`save`."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                header = json.loads(str(data["header"]))
                arrays = {k: data[k] for k in ("centres", "weights", "poly", "center", "scale")}
        except FileNotFoundError:
            raise FileNotFoundError(f"model file not found: {path}") from None
        except (OSError, ValueError, KeyError) as exc:
            raise ValueError(f"{path} is not an o3drbf model file ({exc})") from None
        if header.get("format") != _FORMAT:
            raise ValueError(f"{path} is not an o3drbf model file (format {header.get('format')!r})")
        if header.get("version", 0) > _VERSION:
            raise ValueError(f"{path} was written by a newer o3drbf (version {header['version']})")
        kernel = make_kernel(**header["kernel"])
        # Normalization stored as arrays too, so the round trip is bit-exact.
        norm = Normalization(center=arrays["center"], scale=float(arrays["scale"]))
        return cls(kernel, arrays["centres"], arrays["weights"], arrays["poly"], norm, header.get("metadata", {}))


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")
