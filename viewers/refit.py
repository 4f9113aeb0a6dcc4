"""Refitting and re-extraction off the window's thread.

A :class:`Refitter` runs one job at a time on a worker thread
(:mod:`concurrent.futures`): a *fit* (constraints, solve, marching cubes) when
lambda, delta or tau change, an *extraction* only when the iso-level or the
grid resolution change.  The window polls :meth:`Refitter.poll` from a timer,
so it stays live while a job runs; requests made meanwhile are merged and run
next (the latest value wins).  No PyVista here.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from o3drbf.options import DEFAULTS, VIEWER_OVERRIDES

__all__ = ["FitParams", "FitResult", "Refitter", "pick_values", "run_fit", "run_extract"]


@dataclass(frozen=True)
class FitParams:
    """Everything a refit or re-extraction depends on (the viewer's sliders and options).

    ``lambda_surface``, ``delta`` or ``tau`` left at None are chosen by
    :func:`o3drbf.reconstruct` (from the data when ``auto``, else the
    paper's values); a finished fit reports the values it used.
    """

    lambda_surface: float | None = DEFAULTS["lambda_surface"]
    delta: float | None = DEFAULTS["delta"]
    tau: float | None = DEFAULTS["tau"]
    auto: bool = DEFAULTS["auto"]
    level: float = 0.0
    resolution: int = VIEWER_OVERRIDES["resolution"]
    surface_count: int = VIEWER_OVERRIDES["surface_count"]
    outliers: str = DEFAULTS["outliers"]
    solver: str = DEFAULTS["solver"]
    seed: int = 0

    @classmethod
    def from_options(cls, options, seed: int = 0) -> "FitParams":
        """The first fit of a :class:`~o3drbf.options.ViewOptions` (validated: its resolution and count are whole numbers)."""
        fit = options.fit
        p = fit.parameters
        return cls(lambda_surface=p.lambda_surface, delta=p.delta, tau=p.tau, auto=bool(p.auto), level=float(options.level),
                   resolution=int(fit.extract.resolution), surface_count=int(fit.constraints.surface_count), outliers=fit.outliers.method,
                   solver=fit.fit.solver, seed=int(seed))

    def fit_key(self) -> tuple:
        """The parameters that change the implicit function (a refit)."""
        return (self.lambda_surface, self.delta, self.tau, self.auto, self.surface_count, self.outliers, self.solver, self.seed)

    def mesh_key(self) -> tuple:
        """The parameters that change only the mesh (a re-extraction)."""
        return (self.level, self.resolution)


@dataclass
class FitResult:
    """What a job hands back to the window.

    Attributes
    ----------
    params : FitParams
        The parameters of this mesh, with the values the fit actually used
        in place of None.
    surface : ImplicitSurface
    mesh : open3d.geometry.TriangleMesh or None
        None when f does not cross ``params.level`` (see ``error``).
    constraints : dict
        ``{"surface": (S, 3), "exterior": (E, 3), "sphere": (P, 3)}``, data coordinates.
    refit : bool
        True if the implicit function was refitted (else only re-extracted).
    seconds : float
    error : str
        One-line reason when the job failed (mesh None), else "".
    stats : dict
    """

    params: FitParams
    surface: object
    mesh: object
    constraints: dict
    refit: bool
    seconds: float
    error: str = ""
    stats: dict = field(default_factory=dict)


class _Status:
    """The running job's stage, shared between the worker and the window."""

    def __init__(self):
        self._lock = threading.Lock()
        self._stage = ""

    def set(self, stage: str) -> None:
        with self._lock:
            self._stage = stage

    def get(self) -> str:
        with self._lock:
            return self._stage


def _split_constraints(constraints) -> dict:
    from o3drbf.constraints.core import EXTERIOR, INTERIOR, SPHERE, SURFACE

    kind = constraints.kind
    return {
        "surface": constraints.points[kind == SURFACE],
        "exterior": constraints.points[(kind == EXTERIOR) | (kind == INTERIOR)],
        "sphere": constraints.points[kind == SPHERE],
    }


def used_params(surface, params: FitParams) -> FitParams:
    """``params`` with lambda_surface, delta and tau as ``surface`` was fitted with them."""
    kernel = dict(getattr(surface.kernel, "params", {}))
    lam = surface.metadata.get("lambda_surface", params.lambda_surface)
    return replace(
        params,
        lambda_surface=None if lam is None else float(lam),
        delta=float(kernel["delta"]) if "delta" in kernel else params.delta,
        tau=float(kernel["tau"]) if "tau" in kernel else params.tau,
    )


def run_extract(surface, params: FitParams):
    """The mesh at ``params.level`` and ``params.resolution``, or (None, reason)."""
    from o3drbf.extract import extract_mesh

    try:
        return extract_mesh(surface, resolution=params.resolution, level=params.level), ""
    except RuntimeError as exc:
        return None, " ".join(str(exc).split())


def run_fit(data, params: FitParams, status=None) -> FitResult:
    """Fit the implicit function to ``data`` (a :class:`~o3drbf.viewers.inputs.ViewInput`) and mesh it."""
    from o3drbf.pipeline import reconstruct

    t0 = time.perf_counter()
    if status is not None:
        status.set("fitting (constraints, solve)")
    result = reconstruct(
        data.points,
        None if data.cameras is not None else data.normals,
        cameras=data.cameras,
        point_camera=data.point_camera,
        outliers=params.outliers,
        delta=params.delta,
        tau=params.tau,
        lambda_surface=params.lambda_surface,
        surface_count=min(params.surface_count, len(data.points)),
        solver=params.solver,
        seed=params.seed,
        auto=params.auto,
        extract_mesh=False,
    )
    params = used_params(result.surface, params)
    if status is not None:
        status.set(f"extracting (resolution {params.resolution})")
    mesh, error = run_extract(result.surface, params)
    return FitResult(params, result.surface, mesh, _split_constraints(result.constraints), True, time.perf_counter() - t0, error, result.stats)


class Refitter:
    """Runs fits and extractions one at a time on a worker thread.

    Parameters
    ----------
    data : ViewInput
    params : FitParams
        The starting parameters.
    surface : ImplicitSurface, optional
        A fitted (or loaded) function: then :meth:`request` with only
        level/resolution changes re-extracts it.  Required when ``data`` is
        a saved model (refits are then refused).
    """

    def __init__(self, data, params: FitParams, surface=None, constraints=None):
        self.data = data
        self.params = params
        self.surface = surface if surface is not None else getattr(data, "model", None)
        self.constraints = constraints
        self._fitted_key = params.fit_key() if self.surface is not None else None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="o3drbf-refit")
        self._future: Future | None = None
        self._pending: FitParams | None = None
        self._status = _Status()
        self._started = 0.0
        self._job_refit = False
        self._target = params

    @property
    def can_refit(self) -> bool:
        return not getattr(self.data, "is_model", False)

    @property
    def busy(self) -> bool:
        return self._future is not None or self._pending is not None

    @property
    def target(self) -> FitParams:
        """The parameters shown once every job asked for is done."""
        if self._pending is not None:
            return self._pending
        return self._target if self._future is not None else self.params

    def start(self) -> None:
        """Run the job for the current parameters now (the first fit or extraction).

        Raises
        ------
        RuntimeError
            A job is already running.
        """
        if self._future is not None:
            raise RuntimeError("a job is already running")
        self._start(self.params)

    def status(self) -> str:
        """A one-line description of the running job ("" when idle)."""
        if self._future is None:
            return ""
        stage = self._status.get() or "starting"
        return f"{stage} ... {time.perf_counter() - self._started:.1f} s"

    def request(self, **changes) -> FitParams:
        """Ask for new parameters; the job starts now, or after the running one.

        Returns the parameters that will be shown once every request is done.

        Raises
        ------
        ValueError
            Unknown parameter, or a refit asked of a saved model.
        """
        unknown = set(changes) - set(FitParams.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown viewer parameter(s) {sorted(unknown)}; valid: {sorted(FitParams.__dataclass_fields__)}")
        base = self.target
        new = replace(base, **changes)
        if not self.can_refit and new.fit_key() != base.fit_key():
            raise ValueError("a saved model cannot be refitted; only the iso-level and resolution can change")
        if self._future is None:
            self._start(new)
        else:
            self._pending = new
        return new

    def _start(self, params: FitParams) -> None:
        refit = self.surface is None or params.fit_key() != self._fitted_key
        self._job_refit = refit
        self._started = time.perf_counter()
        self._status.set("")
        if refit:
            self._future = self._pool.submit(run_fit, self.data, params, self._status)
        else:
            self._future = self._pool.submit(self._extract_job, self.surface, self.constraints, params)
        self._target = params

    def _extract_job(self, surface, constraints, params: FitParams) -> FitResult:
        t0 = time.perf_counter()
        self._status.set(f"extracting (resolution {params.resolution}, level {params.level:g})")
        mesh, error = run_extract(surface, params)
        return FitResult(params, surface, mesh, constraints, False, time.perf_counter() - t0, error)

    def poll(self) -> FitResult | None:
        """The finished job's result (once), starting the next pending one; None otherwise.

        A job that raised gives a result with ``mesh=None`` and ``error`` set.
        """
        fut = self._future
        if fut is None or not fut.done():
            return None
        self._future = None
        target = self._target
        try:
            res = fut.result()
        except Exception as exc:  # noqa: BLE001 - shown in the window, the app keeps running
            res = FitResult(target, self.surface, None, self.constraints, self._job_refit, time.perf_counter() - self._started, " ".join(str(exc).split()) or type(exc).__name__)
            self.params = target
        else:
            self.surface = res.surface
            self.constraints = res.constraints
            self._fitted_key = res.params.fit_key()
            self.params = res.params
        if self._pending is not None:
            nxt, self._pending = self._pending, None
            # Values the request left as they were (e.g. None: "let the fit choose")
            # take what the fit used, so they do not look like a change.
            same = {k: getattr(self.params, k) for k in ("lambda_surface", "delta", "tau") if getattr(nxt, k) == getattr(target, k)}
            self._start(replace(nxt, **same))
        return res

    def wait(self, timeout: float | None = None) -> FitResult | None:
        """Block until the current job and any pending one are done (for scripts and tests).

        Returns the last result, or None if nothing was running.
        """
        last = None
        deadline = None if timeout is None else time.perf_counter() + timeout
        while self._future is not None:
            remaining = None if deadline is None else max(0.0, deadline - time.perf_counter())
            self._future.exception(timeout=remaining)
            last = self.poll() or last
        return last

    def close(self) -> None:
        """Drop pending requests and let a running job finish."""
        self._pending = None
        self._pool.shutdown(wait=True, cancel_futures=True)


def pick_values(surface, point) -> tuple[float, float]:
    """f and |grad f| at one point (data coordinates).

    Parameters
    ----------
    surface : ImplicitSurface
    point : (3,) array_like

    Returns
    -------
    (float, float)
    """
    p = np.asarray(point, dtype=float).reshape(-1)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ValueError(f"picked point must be a finite 3-vector, got {np.asarray(point).tolist()}")
    f, g = surface.evaluate(p[None, :], gradient=True)
    return float(f[0]), float(np.linalg.norm(g[0]))
