"""The implicit surface f(x) = P(x) + sum_i w_i phi(|x - c_i|), as an object.

f > 0 inside, f = 0 on the surface, f < 0 outside.  Points are given and
returned in the data's own coordinates; internally f lives in the
normalized 2x2x2 box (:class:`~o3drbf.prep.normalize.Normalization`).
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from o3drbf.validation import as_points, shown
from o3drbf.io.files import atomic_path
from o3drbf.rbf.kernels import Kernel, make_kernel
from o3drbf.prep.normalize import Normalization
from o3drbf.rbf.sums import DEFAULT_CHUNK_BYTES, kernel_sum, polynomial_basis

__all__ = ["DataCoordinates", "ImplicitSurface", "json_default"]

_FORMAT = "o3drbf-implicit-surface"
_VERSION = 1


class DataCoordinates:
    """f, grad f and normals in data coordinates, for any implicit function
    with ``evaluate_box(points, gradient)`` (box coordinates) and a ``normalization``."""

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


@dataclass
class ImplicitSurface(DataCoordinates):
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

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> import tempfile, pathlib, o3drbf
    >>> surface = o3drbf.reconstruct(points, normals, surface_count=200, extract_mesh=False).surface
    >>> path = pathlib.Path(tempfile.mkdtemp()) / 'sphere.npz'
    >>> _ = surface.save(path)
    >>> again = o3drbf.ImplicitSurface.load(path)
    >>> bool(np.allclose(again(points[:5]), surface(points[:5])))
    True
    """

    kernel: Kernel
    centres: np.ndarray
    weights: np.ndarray
    poly: np.ndarray
    normalization: Normalization = field(default_factory=Normalization.identity)
    metadata: dict = field(default_factory=dict)
    #: Optional faster evaluator ``(box_points, gradient) -> values[, grads]`` (e.g. fast multipole).
    evaluator: object = field(default=None, repr=False, compare=False)
    #: The meshing evaluator (:func:`o3drbf.extract.mesh_evaluator`) once built for this surface, so that the
    #: robust pass's residuals and marching cubes share one grid sum; not saved.
    meshing: object = field(default=None, repr=False, compare=False)

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

        return _direct.kernel_table(self.kernel)

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
        from o3drbf.io.files import check_outputs

        check_outputs([path])

        def verify(tmp):  # read back (validated) before the rename: a short write fails here
            try:
                back = type(self).load(tmp)
            except ValueError as exc:
                raise OSError(f"cannot write {path}: the model read back is invalid ({_one_line(exc)}); nothing was written") from None
            if back.centres.shape != self.centres.shape or not np.array_equal(back.weights, self.weights):
                raise OSError(f"cannot write {path}: the model read back differs; nothing was written")

        with atomic_path(path, verify=verify) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(
                    fh,
                    header=np.array(json.dumps(header, default=json_default)),
                    centres=self.centres,
                    weights=self.weights,
                    poly=self.poly,
                    center=np.asarray(self.normalization.center, dtype=float),
                    scale=np.array(self.normalization.scale),
                )
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ImplicitSurface":
        """Read a model written by :meth:`save`, validating every field.

        Never unpickles (``allow_pickle=False``).  Checks the header (JSON
        object, format, version, kernel through :func:`make_kernel`), the
        arrays' shapes, dtypes and finiteness, and that there is one weight
        per centre and one polynomial coefficient per basis term.

        Raises
        ------
        FileNotFoundError
            No such file.
        ValueError
            Not a zip/npz file, truncated, or a field is missing or invalid;
            the message names the file and the field.
        """
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"model file not found: {path}")
        if path.is_dir():
            raise ValueError(f"model {path} is a folder; give the .npz file written by --save-model")
        arrays = {}
        try:
            with np.load(path, allow_pickle=False) as data:
                if not hasattr(data, "files"):
                    raise ValueError("holds a single array, not an o3drbf model")
                for key in ("header", *_ARRAYS):
                    if key not in data.files:
                        raise ValueError(f"field {key!r} is missing")
                    try:
                        arrays[key] = data[key]
                    except ValueError as exc:  # object arrays need pickle: refused
                        raise ValueError(f"field {key!r} cannot be read without pickle ({exc})") from None
        except FileNotFoundError:
            raise FileNotFoundError(f"model file not found: {path}") from None
        except ValueError as exc:
            raise ValueError(f"{path} is not an o3drbf model file: {_one_line(exc)}") from None
        except (OSError, EOFError, KeyError, zipfile.BadZipFile, RuntimeError) as exc:  # truncated or not a zip
            raise ValueError(f"{path} is not an o3drbf model file (truncated or not an .npz): {_one_line(exc)}") from None

        def bad(field_name: str, message: str) -> ValueError:
            return ValueError(f"{path}: field {field_name!r} {message}; the file is corrupt or not written by o3drbf")

        raw = arrays["header"]
        if raw.shape != () or raw.dtype.kind != "U":
            raise bad("header", f"must be one JSON string, got dtype {raw.dtype} shape {raw.shape}")
        try:
            header = json.loads(str(raw))
        except (json.JSONDecodeError, RecursionError) as exc:
            raise bad("header", f"is not valid JSON ({_one_line(exc)})") from None
        if not isinstance(header, dict):
            raise bad("header", f"must be a JSON object, got {type(header).__name__}")
        if header.get("format") != _FORMAT:
            raise bad("header.format", f"is {header.get('format')!r}, expected {_FORMAT!r}")
        version = header.get("version")
        if not isinstance(version, int) or isinstance(version, bool) or version < 1:
            raise bad("header.version", f"must be a whole number >= 1, got {shown(version)}")
        if version > _VERSION:
            raise ValueError(f"{path} was written by a newer o3drbf (version {version}); upgrade o3drbf to read it")
        kdict = header.get("kernel")
        if not isinstance(kdict, dict) or not isinstance(kdict.get("name"), str):
            raise bad("header.kernel", f"must be an object with a 'name', got {kdict!r}")
        kparams = {k: v for k, v in kdict.items() if k != "name"}
        for k, v in kparams.items():
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not np.isfinite(v):
                raise bad(f"header.kernel.{k}", f"must be a finite number, got {v!r}")
        try:
            kernel = make_kernel(kdict["name"], **kparams)
        except ValueError as exc:
            raise bad("header.kernel", f"is invalid: {_one_line(exc)}") from None
        metadata = header.get("metadata", {})
        if not isinstance(metadata, dict):
            raise bad("header.metadata", f"must be a JSON object, got {type(metadata).__name__}")

        def floats(key: str, shape: tuple) -> np.ndarray:
            a = arrays[key]
            if a.dtype.kind not in "fiu":
                raise bad(key, f"must hold numbers, got dtype {a.dtype}")
            if a.shape != shape:
                raise bad(key, f"has shape {a.shape}, expected {shape}")
            a = a.astype(float, copy=False)
            if not np.isfinite(a).all():
                raise bad(key, "has NaN or infinite entries")
            return a

        a = arrays["centres"]
        if a.ndim != 2 or a.shape[1:] != (3,):
            raise bad("centres", f"has shape {a.shape}, expected (N, 3)")
        n = a.shape[0]
        if n == 0:
            raise bad("centres", "is empty (no RBF centre)")
        centres = floats("centres", (n, 3))
        if arrays["weights"].shape != (n,):
            raise bad("weights", f"has shape {arrays['weights'].shape}, expected ({n},): one weight per centre (count mismatch)")
        weights = floats("weights", (n,))
        m = polynomial_basis(np.zeros((1, 3)), kernel.polynomial_degree).shape[1]
        poly = floats("poly", (m,))
        center = floats("center", (3,))
        scale = float(floats("scale", ())[()])
        if scale <= 0:
            raise bad("scale", f"must be > 0, got {shown(scale)}")
        # Normalization stored as arrays too, so the round trip is bit-exact.
        norm = Normalization(center=center, scale=scale)
        return cls(kernel, centres, weights, poly, norm, metadata)


_ARRAYS = ("centres", "weights", "poly", "center", "scale")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def json_default(o):
    """``json.dumps`` default for the model headers: NumPy arrays and scalars as plain lists and numbers."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")
