"""Robust fitting: iteratively reweighted smoothing of the surface constraints.

The regularized system gives, at every constraint, f(c_i) = y_i - lambda_i w_i
(design-notes.md), so a constraint's pull on the surface is set by lambda_i
alone: down-weighting an outlier is a change of its lambda, nothing else.

Each round measures the geometric residual of every SURFACE constraint,
``d_i = |f(c_i)| / |grad f(c_i)|`` (box units), the scale
``s = max(1.4826 * median(d), noise_scale)``, and weights ``u_i`` in [0, 1]:

- Huber (first rounds): ``u = min(1, k s / d)``;
- Tukey biweight (last rounds) with a flat core: ``u = 1`` for ``d <= k s``,
  ``u = ((1 - (d / c s)^2) / (1 - (k / c)^2))^2`` up to ``c s``, else 0, and
  a constraint with ``u = 0`` is dropped from the fit.

The flat core matters: a larger lambda is more smoothing, so down-weighting
every constraint a little (the plain biweight) would shrink the whole
surface, raise every residual and never settle.  For the same reason the
default Huber threshold is k = 3, not the textbook 1.345: with 1.345 the
inliers beyond k s (a sizeable fraction of a Gaussian sample) are
down-weighted, the fit smooths where they sit, their residuals grow and the
dropped set keeps growing (docs/data/design-measurements.md, "Robust fitting").

Then ``lambda_i = lambda_0,i / max(u_i, MIN_WEIGHT)`` and the constraints are
refitted.  Nothing is refitted when no residual of the first fit reaches
``c s`` (data consistent with its noise: clean data costs one residual
evaluation).  The loop stops when nothing exceeds ``k s``, when the set of
constraints beyond ``k s`` and the dropped set are the same as in the
previous round of the same kind, or after ``rounds`` refits.  Exterior,
interior and sphere constraints keep their lambda.

A refit changes lambda of a few constraints, and the surface moves only
near them (on noisy range scans, within a few constraint spacings of a
changed constraint: docs/data/design-measurements.md, "Robust fitting").  So after
a refit the residuals are measured again only within ``local_radius``
spacings of the constraints whose lambda changed; a seeded sample of the
others is measured too (half of it the nearest beyond that radius, where
an unmeasured change would be largest), and if any of those moved by more than
``LOCAL_CHECK_TOLERANCE * k s`` every residual is measured again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from o3drbf.constraints.core import SURFACE, Constraints
from o3drbf.validation import check_number

__all__ = ["RobustReport", "robust_reweight", "huber_weights", "tukey_weights", "geometric_residuals", "constraint_residuals", "MAD_FACTOR",
           "LOCAL_RADIUS_SPACINGS"]

#: 1 / Phi^-1(3/4): the MAD of a Gaussian times this is its standard deviation.
MAD_FACTOR = 1.4826
#: Smallest weight (largest lambda multiplier) of a down-weighted constraint.
MIN_WEIGHT = 1e-6
#: Lambda used as the base of a surface constraint given lambda = 0 (which no weight could change).
ZERO_SMOOTHING = 1e-4
#: After a refit, residuals are measured again within this many constraint spacings of a changed constraint.
LOCAL_RADIUS_SPACINGS = 10.0
#: Constraints outside that neighbourhood measured as a check (a seeded sample) ...
LOCAL_CHECK_SAMPLES = 256
#: ... whose residuals may have moved by at most this fraction of ``huber_k * s`` (else all are measured again).
LOCAL_CHECK_TOLERANCE = 0.01


@dataclass(frozen=True, eq=False)
class RobustReport:
    """What :func:`robust_reweight` did.

    Attributes
    ----------
    rounds : int
        Refits after the first fit (0: nothing was down-weighted).
    downweighted : int
        Surface constraints with a residual beyond ``huber_k * scale`` at the
        last reweighting (weight < 1).
    dropped : int
        Surface constraints removed from the final fit (Tukey weight 0).
    scale : float
        The residual scale s of the last reweighting (box units).
    seconds : float
        Wall time, fits included.
    weights : (M,) array
        Final weight of every input constraint (1 for non-surface ones, 0 if dropped).
    kept : (K,) int array
        Indices of the input constraints in the final fit.
    constraints : Constraints
        The constraints of the final fit (lambda scaled, dropped ones removed).
    residuals : (S,) array
        Geometric residual ``|f| / |grad f|`` (box units) of every SURFACE
        constraint at the final fit, in their input order (those beyond
        ``local_radius`` of the last changes as last measured, within
        ``LOCAL_CHECK_TOLERANCE * huber_k * scale``).
    history : list of dict
        Per round: kind, scale, down-weighted, dropped, median residual, and
        ``measured``: how many residuals were measured for that round (all of
        them for the first fit, then the neighbourhood of the changes plus the
        check sample, or all of them when the check failed).
    converged : bool
        Stopped because the down-weighted set stopped changing (or was empty).
    """

    rounds: int
    downweighted: int
    dropped: int
    scale: float
    seconds: float
    weights: np.ndarray
    kept: np.ndarray
    constraints: Constraints
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))
    history: list = field(default_factory=list)
    converged: bool = True

    def __str__(self) -> str:
        return (
            f"robust fit: {self.rounds} reweighting round(s), {self.downweighted} surface constraint(s) down-weighted, "
            f"{self.dropped} dropped, scale {self.scale:.3g} (box units){'' if self.converged else ', not converged'}"
        )


def geometric_residuals(surface, points) -> np.ndarray:
    """``|f| / |grad f|`` at points in box coordinates: about the distance to the zero set.

    When the surface carries its meshing grid sum (``surface.meshing``, from
    :func:`o3drbf.extract.mesh_evaluator`), f and grad f come from it: its
    tolerance, a fraction of max |f|, is far below the residual scale, and its
    gradients are about ten times that (a finer grid for gradients alone would
    cost more than the whole measurement).

    Parameters
    ----------
    surface : ImplicitSurface
    points : (M, 3) array_like
        Box coordinates.

    Returns
    -------
    (M,) array (inf where the gradient vanishes and f does not)
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    meshing = _meshing_grid(surface)
    f, g = meshing(pts, gradient=True) if meshing is not None else surface.evaluate_box(pts, gradient=True)
    return _distance(f, g)


def _meshing_grid(surface):
    """The surface's meshing grid sum (``surface.meshing`` of kind "grid"), or None."""
    meshing = getattr(surface, "meshing", None)
    return meshing if getattr(meshing, "kind", None) == "grid" else None


def _distance(f: np.ndarray, g: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(g, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.abs(f) / norm
    return np.where(np.abs(f) == 0, 0.0, np.where(norm > 0, d, np.inf))


def constraint_residuals(surface, constraints: Constraints, index: np.ndarray) -> np.ndarray:
    """:func:`geometric_residuals` at ``constraints.points[index]``.

    When the surface carries its meshing grid sum, f and grad f come from it (as in
    :func:`geometric_residuals`).  Otherwise, when the surface's
    centres are the constraints' points (a fit of all of them, evaluated directly), the sums
    come from :func:`o3drbf.rbf.compiled.direct_sum_at_centres`, which evaluates each pair of
    centres once for both ends; they agree with ``evaluate_box``'s to
    rounding.  Otherwise (a fast evaluator, constraints left out, a kernel without a compiled
    form) this is ``geometric_residuals(surface, constraints.points[index])``.
    """
    from o3drbf.rbf import compiled

    centres = getattr(surface, "centres", None)
    if (_meshing_grid(surface) is None and getattr(surface, "evaluator", None) is None and centres is not None
            and compiled.supports(surface.kernel) and centres.shape == constraints.points.shape
            and np.array_equal(centres, constraints.points)):
        from o3drbf.rbf.sums import polynomial_basis

        f, g = compiled.direct_sum_at_centres(surface.kernel, centres, surface.weights, index)
        degree = surface.kernel.polynomial_degree
        f = f + polynomial_basis(centres[index], degree) @ surface.poly
        if degree >= 1:
            g = g + surface.poly[1:4]
        return _distance(f, g)
    return geometric_residuals(surface, constraints.points[index])


class _Neighbourhoods:
    """Residuals measured again near the constraints a refit changed (see the module notes)."""

    def __init__(self, points: np.ndarray, radius_spacings: float):
        self.points = points
        self.radius_spacings = radius_spacings
        self.radius = None  # set at the first refit: clean data (no refit) never pays for the spacing
        self.rng = np.random.default_rng(0)

    def remeasure(self, surface, d: np.ndarray, changed: np.ndarray, tolerance: float) -> tuple:
        """(new residuals, how many were measured): near ``changed``, checked on a sample elsewhere."""
        from scipy.spatial import cKDTree

        n = len(self.points)
        if len(changed) == 0 or len(changed) > n // 8:
            return geometric_residuals(surface, self.points), n
        if self.radius is None:
            spacing = float(np.median(cKDTree(self.points).query(self.points, k=2, workers=-1)[0][:, 1])) if n > 1 else 0.0
            self.radius = self.radius_spacings * spacing
        gap = cKDTree(self.points[changed]).query(self.points, workers=-1)[0]
        gap[changed] = 0.0
        near = gap <= self.radius
        if near.sum() > n // 2:
            return geometric_residuals(surface, self.points), n
        outside = np.flatnonzero(~near)
        half = min(LOCAL_CHECK_SAMPLES // 2, len(outside))
        # The check looks first where an unmeasured change would be largest: the nearest beyond the radius.
        order = np.argsort(gap[outside], kind="stable")
        shell, far = outside[order[:half]], outside[order[half:]]
        sample = np.concatenate([shell, self.rng.choice(far, size=min(half, len(far)), replace=False)]).astype(int)
        inside = np.flatnonzero(near)
        both = np.concatenate([inside, sample])
        fresh = geometric_residuals(surface, self.points[both])
        moved = np.abs(fresh[len(inside):] - d[sample])
        moved[np.isinf(fresh[len(inside):]) & np.isinf(d[sample])] = 0.0
        if not (np.nan_to_num(moved, nan=np.inf) <= tolerance).all():
            return geometric_residuals(surface, self.points), n + len(both)
        out = d.copy()
        out[both] = fresh
        return out, len(both)


def huber_weights(d, threshold: float) -> np.ndarray:
    """``min(1, threshold / d)`` for residuals ``d >= 0`` (``threshold = k s``)."""
    d = np.asarray(d, dtype=float)
    with np.errstate(divide="ignore"):
        return np.where(d > threshold, threshold / d, 1.0)


def tukey_weights(d, threshold: float, core: float = 0.0) -> np.ndarray:
    """Tukey's biweight ``(1 - (d / threshold)^2)^2`` below ``threshold = c s``, else 0.

    With ``core = k s > 0`` the weight is 1 up to ``core`` and the biweight
    rescaled to 1 there beyond: ``((1 - (d / c s)^2) / (1 - (k / c)^2))^2``.
    """
    d = np.asarray(d, dtype=float)
    r = np.minimum(d / threshold, 1.0)
    top = 1.0 - min(core / threshold, 1.0) ** 2 if core > 0 else 1.0
    return np.minimum(((1.0 - r**2) / top) ** 2, 1.0)


def robust_reweight(
    fit: Callable[[Constraints], tuple],
    constraints: Constraints,
    noise_scale: float,
    *,
    rounds: int = 4,
    huber_k: float = 3.0,
    tukey_c: float = 4.685,
    huber_rounds: int | None = None,
    first=None,
    refit: Callable[[np.ndarray], tuple] | None = None,
    local_radius: float | None = LOCAL_RADIUS_SPACINGS,
) -> tuple:
    """Fit, then refit with the surface constraints' lambda scaled by robust weights.

    Parameters
    ----------
    fit : callable
        ``fit(constraints) -> (surface, solution)``: one regularized fit
        (e.g. ``lambda c: o3drbf.pipeline.fit(c, kernel, normalization)``).
        The surface must evaluate in box coordinates (``evaluate_box``).
    constraints : Constraints
        In the normalized box; lambda of the SURFACE constraints is the base
        ``lambda_0`` (zeros are replaced by ``ZERO_SMOOTHING``, only for
        down-weighted constraints).
    noise_scale : float
        Smallest residual scale s (box units, >= 0): the noise of the points,
        e.g. ``o3drbf.constraints.parameters.estimate_noise`` in box units,
        or a fraction of the spacing for exact data.  It keeps clean data
        from being reweighted.
    rounds : int
        Most refits (>= 1).
    huber_k : float
        Huber threshold in scales (> 0).
    tukey_c : float
        Tukey threshold in scales (> huber_k): beyond it a constraint is dropped.
    huber_rounds : int, optional
        Refits with Huber weights before switching to Tukey; default
        ``max(1, rounds // 2)``.
    first : (surface, solution), optional
        An existing fit of ``constraints`` (saves the first fit).
    refit : callable, optional
        ``refit(smoothing) -> (surface, solution)``: the fit of ``constraints``
        with the smoothing ``smoothing`` (one value per constraint, ``inf``
        for a dropped one), used for the refits instead of ``fit`` on the
        kept constraints; e.g. :class:`o3drbf.solvers.Refitter`, which
        updates one dense factorization instead of solving afresh.
    local_radius : float or None
        After a refit, measure residuals again only within this many
        constraint spacings of the constraints whose lambda changed (checked
        on a sample of the others; see the module notes).  ``None``: measure
        every residual after every refit.

    Returns
    -------
    surface : ImplicitSurface
        The final fit.
    solution : Solution
    report : RobustReport
    """
    t0 = time.perf_counter()
    if not isinstance(constraints, Constraints):
        raise ValueError(f"constraints must be an o3drbf.constraints.core.Constraints, got {type(constraints).__name__}")
    if not callable(fit):
        raise ValueError("fit must be a callable fit(constraints) -> (surface, solution)")
    noise_scale = check_number("noise_scale", noise_scale, low=0.0)
    rounds = check_number("rounds", rounds, low=1, integer=True)
    huber_k = check_number("huber_k", huber_k, low=0.0, low_open=True)
    tukey_c = check_number("tukey_c", tukey_c, low=huber_k, low_open=True)
    n_huber = max(1, rounds // 2) if huber_rounds is None else check_number("huber_rounds", huber_rounds, low=0, high=rounds, integer=True)
    if local_radius is not None:
        local_radius = check_number("local_radius", local_radius, low=0.0)
    surf = np.flatnonzero(constraints.kind == SURFACE)
    if len(surf) == 0:
        raise ValueError("constraints have no SURFACE constraint to reweight; give surface constraints or skip the robust fit")
    lam0 = np.asarray(constraints.smoothing, dtype=float)
    base = np.where(lam0[surf] > 0, lam0[surf], ZERO_SMOOTHING)
    m = len(constraints)
    surface, solution = fit(constraints) if first is None else first
    pts = constraints.points[surf]
    d = constraint_residuals(surface, constraints, surf)
    measured = len(pts)
    local = None if local_radius is None else _Neighbourhoods(pts, local_radius)
    lam_fit = lam0[surf].copy()  # lambda of the surface constraints in the current fit (inf: dropped)
    weights = np.ones(m)
    kept = np.arange(m)
    current = constraints
    history: list[dict] = []
    previous = None
    previous_kind = ""
    done = 0
    converged = False
    s = noise_scale
    huber_done = 0
    for r in range(rounds + 1):
        s = max(MAD_FACTOR * float(np.median(d[np.isfinite(d)])) if np.isfinite(d).any() else 0.0, noise_scale)
        if s <= 0:
            converged = True  # exact fit and no noise floor: nothing to reweight
            break
        down = d > huber_k * s
        if r == 0 and not (d >= tukey_c * s).any():
            history.append({"kind": "check", "scale": s, "downweighted": 0, "dropped": 0, "median_residual": float(np.median(d)), "measured": measured})
            converged = True  # nothing beyond c s: consistent with the noise, no refit
            break
        tukey = huber_done >= n_huber
        state = (down.tobytes(), (d >= tukey_c * s).tobytes())
        if not tukey and state == previous:  # Huber settled: on to Tukey
            tukey = True
            huber_done = n_huber
        u = tukey_weights(d, tukey_c * s, huber_k * s) if tukey else huber_weights(d, huber_k * s)
        drop = u <= 0
        history.append({"kind": "tukey" if tukey else "huber", "scale": s, "downweighted": int(down.sum()),
                        "dropped": int(drop.sum()), "median_residual": float(np.median(d)), "measured": measured})
        if not down.any():
            converged = True
            break
        if tukey and state == previous and previous_kind == "tukey":
            converged = True
            break
        if r == rounds:
            break
        previous_kind = "tukey" if tukey else "huber"
        huber_done += not tukey
        previous = state
        lam = lam0.copy()
        lam[surf] = np.where(u < 1, base / np.maximum(u, MIN_WEIGHT), lam0[surf])
        keep = np.ones(m, dtype=bool)
        keep[surf[drop]] = False
        weights = np.ones(m)
        weights[surf] = np.where(drop, 0.0, u)
        kept = np.flatnonzero(keep)
        current = Constraints(constraints.points[keep], constraints.values[keep], lam[keep], constraints.kind[keep])
        surface, solution = fit(current) if refit is None else refit(np.where(keep, lam, np.inf))
        done += 1
        lam_new = np.where(drop, np.inf, lam[surf])
        changed = np.flatnonzero(lam_new != lam_fit)
        lam_fit = lam_new
        if local is None:
            d, measured = geometric_residuals(surface, pts), len(pts)
        else:
            d, measured = local.remeasure(surface, d, changed, LOCAL_CHECK_TOLERANCE * huber_k * s)
    report = RobustReport(
        rounds=done,
        downweighted=int((weights[surf] < 1).sum()) if done else 0,
        dropped=int((weights[surf] == 0).sum()) if done else 0,
        scale=float(s),
        seconds=time.perf_counter() - t0,
        weights=weights,
        kept=kept,
        constraints=current,
        residuals=d,
        history=history,
        converged=converged,
    )
    return surface, solution, report
