"""The tiled implicit surface f(x) = f0(x) + sum_t W_t(x) g_t(x).

f0 is a global coarse fit, g_t the fit of tile t's residual, and
W_t = w_t / sum_s w_s the partition of unity of :mod:`o3drbf.tiles.partition`.
Everything is evaluated in the global normalized box; the public methods
take and return data coordinates, like :class:`o3drbf.surface.ImplicitSurface`.
f > 0 inside, f < 0 outside.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from o3drbf.io.files import atomic_path
from o3drbf.prep.normalize import Normalization
from o3drbf.rbf.kernels import make_kernel
from o3drbf.surface import DataCoordinates, ImplicitSurface, json_default
from o3drbf.tiles.partition import Partition, box_distance, wendland, wendland_derivative

__all__ = ["TiledSurface"]

FORMAT = "o3drbf-tiled-surface"
VERSION = 1


def _bare(s: ImplicitSurface) -> ImplicitSurface:
    """A copy without caches or evaluators (picklable, identical values)."""
    return ImplicitSurface(s.kernel, s.centres, s.weights, s.poly, Normalization.identity(), dict(s.metadata))


@dataclass
class TiledSurface(DataCoordinates):
    """A partition-of-unity blend of a global fit and per-tile residual fits.

    Parameters
    ----------
    base : ImplicitSurface
        f0, in box coordinates (identity normalization).
    tiles : list of ImplicitSurface
        g_t, one per tile, in box coordinates (identity normalization).
    partition : Partition
        Cells and supports, box coordinates.
    normalization : Normalization
        Data -> box map shared by all parts.
    metadata : dict
        JSON-serializable provenance (kept through save/load).
    """

    base: ImplicitSurface
    tiles: list
    partition: Partition
    normalization: Normalization = field(default_factory=Normalization.identity)
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        if len(self.tiles) != len(self.partition):
            raise ValueError(f"tiled surface: {len(self.tiles)} tile fits for {len(self.partition)} tiles")
        self.base = _bare(self.base)
        self.tiles = [_bare(t) for t in self.tiles]

    def __getstate__(self):
        # Drop kernel-table caches: they are rebuilt where the surface is used.
        state = dict(self.__dict__)
        state["base"] = _bare(self.base)
        state["tiles"] = [_bare(t) for t in self.tiles]
        return state

    # -- evaluation --------------------------------------------------------------
    def evaluate_box(self, points, gradient: bool = False, approximate: bool = False):
        """f (and grad f) at points in box coordinates.

        Each point's value depends on that point only (not on the batch), so
        a lattice node gets the same value in every tile that evaluates it.

        Parameters
        ----------
        points : (M, 3) array_like
        gradient : bool
        approximate : bool
            Kernel from cubic tables (meshing), see ImplicitSurface.evaluate_box.

        Returns
        -------
        values : (M,) array
        gradients : (M, 3) array, only if ``gradient``
        """
        x = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3))
        m = len(x)
        out = self.base.evaluate_box(x, gradient=gradient, approximate=approximate)
        vals, grads = (out if gradient else (out, None))
        num = np.zeros(m)
        total = np.zeros(m)
        if gradient:
            gnum = np.zeros((m, 3))
            gtotal = np.zeros((m, 3))
        part = self.partition
        for t, g in enumerate(self.tiles):
            idx = part.in_support(x, t)
            if idx.size == 0:
                continue
            xt = x[idx]
            r, gr = box_distance(xt, part.centre[t], part.rho[t])
            w = wendland(r)
            if gradient:
                gv, gg = g.evaluate_box(xt, gradient=True, approximate=approximate)
                dw = wendland_derivative(r)[:, None] * gr
                gnum[idx] += dw * gv[:, None] + w[:, None] * gg
                gtotal[idx] += dw
            else:
                gv = g.evaluate_box(xt, approximate=approximate)
            num[idx] += w * gv
            total[idx] += w
        covered = total > 0
        safe = np.where(covered, total, 1.0)
        corr = np.where(covered, num / safe, 0.0)
        vals = vals + corr
        if not gradient:
            return vals
        gcorr = np.where(covered[:, None], gnum / safe[:, None] - (num / safe**2)[:, None] * gtotal, 0.0)
        return vals, grads + gcorr

    def root_box(self) -> np.ndarray:
        """(2, 3) box (data coordinates) where sum_t w_t > 0 is guaranteed."""
        b = np.array([self.partition.lo.min(axis=0), self.partition.hi.max(axis=0)])
        return self.normalization.inverse(b)

    # -- persistence ---------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write one ``.npz`` (no pickles, written atomically); exact round trip with :meth:`load`."""
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"model file must end in .npz, got {str(path)!r}")
        parts = [self.base, *self.tiles]
        header = {
            "format": FORMAT,
            "version": VERSION,
            "tiles": len(self.tiles),
            "kernels": [p.kernel.to_dict() for p in parts],
            "metadata": self.metadata,
        }
        counts = np.array([len(p.centres) for p in parts], dtype=np.int64)
        pcounts = np.array([len(p.poly) for p in parts], dtype=np.int64)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(
                    fh,
                    header=np.array(json.dumps(header, default=json_default)),
                    centres=np.concatenate([p.centres for p in parts]),
                    weights=np.concatenate([p.weights for p in parts]),
                    poly=np.concatenate([p.poly for p in parts]),
                    counts=counts,
                    poly_counts=pcounts,
                    center=np.asarray(self.normalization.center, dtype=float),
                    scale=np.array(float(self.normalization.scale)),
                    **self.partition.to_arrays(),
                )
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "TiledSurface":
        """Read a model written by :meth:`save`, checking every array's shape.

        Raises
        ------
        FileNotFoundError
            No such file.
        ValueError
            Not a tiled-surface file, a newer version, or inconsistent arrays.
        """
        path = Path(path)
        names = ("centres", "weights", "poly", "counts", "poly_counts", "center", "scale",
                 "tile_lo", "tile_hi", "tile_centre", "tile_rho")
        try:
            with np.load(path, allow_pickle=False) as data:
                header = json.loads(str(data["header"]))
                a = {k: data[k] for k in names}
        except FileNotFoundError:
            raise FileNotFoundError(f"model file not found: {path}") from None
        except (OSError, ValueError, KeyError) as exc:
            raise ValueError(f"{path} is not an o3drbf tiled model file ({exc}); write it with TiledSurface.save") from None
        if not isinstance(header, dict) or header.get("format") != FORMAT:
            raise ValueError(f"{path} is not an o3drbf tiled model file (format {header.get('format') if isinstance(header, dict) else None!r})")
        if header.get("version", 0) > VERSION:
            raise ValueError(f"{path} was written by a newer o3drbf (tiled version {header['version']}); upgrade o3drbf")
        t = int(header.get("tiles", -1))
        counts, pcounts = a["counts"], a["poly_counts"]
        bad = None
        if t < 1 or counts.shape != (t + 1,) or pcounts.shape != (t + 1,) or len(header.get("kernels", [])) != t + 1:
            bad = f"{t} tiles but {counts.shape} centre counts and {len(header.get('kernels', []))} kernels"
        elif (counts < 1).any() or a["centres"].shape != (int(counts.sum()), 3) or a["weights"].shape != (int(counts.sum()),):
            bad = f"centres {a['centres'].shape} / weights {a['weights'].shape} do not match counts summing to {int(counts.sum())}"
        elif a["poly"].shape != (int(pcounts.sum()),):
            bad = f"poly {a['poly'].shape} does not match poly counts summing to {int(pcounts.sum())}"
        elif any(a[k].shape != (t, 3) for k in ("tile_lo", "tile_hi", "tile_centre", "tile_rho")):
            bad = f"tile boxes are not ({t}, 3)"
        elif a["center"].shape != (3,) or a["scale"].shape != () or not float(a["scale"]) > 0:
            bad = "normalization center/scale malformed"
        elif not all(np.isfinite(a[k]).all() for k in names):
            bad = "non-finite values"
        elif not (a["tile_rho"] > 0).all() or not (a["tile_hi"] > a["tile_lo"]).all():
            bad = "tile boxes with non-positive size"
        if bad:
            raise ValueError(f"{path}: corrupt tiled model ({bad}); re-save it with TiledSurface.save")
        parts = []
        c0 = p0 = 0
        for i in range(t + 1):
            kernel = make_kernel(**header["kernels"][i])
            c1, p1 = c0 + int(counts[i]), p0 + int(pcounts[i])
            expected = 1 if kernel.polynomial_degree == 0 else 4
            if p1 - p0 != expected:
                raise ValueError(f"{path}: corrupt tiled model (part {i} has {p1 - p0} polynomial terms, kernel needs {expected})")
            parts.append(ImplicitSurface(kernel, a["centres"][c0:c1], a["weights"][c0:c1], a["poly"][p0:p1], Normalization.identity()))
            c0, p0 = c1, p1
        partition = Partition(a["tile_lo"], a["tile_hi"], a["tile_centre"], a["tile_rho"])
        norm = Normalization(center=a["center"], scale=float(a["scale"]))
        return cls(parts[0], parts[1:], partition, norm, header.get("metadata", {}))
