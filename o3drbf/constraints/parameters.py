"""Automatic parameters: delta, tau and lambda from the data's spacing and noise.

The paper ties its parameters to the sampling density of the normalized
2x2x2 box (method.md section 5: mean nearest-neighbour spacing 0.035-0.051
for delta 10, tau 0.01).  Here the rule is made explicit:

- ``h``: mean nearest-neighbour distance of the surface constraints (the
  Poisson-disc subset the kernel actually sees), box units;
- ``sigma``: the noise of the points across the surface, box units, from
  :func:`estimate_noise` (local quadric fits);
- ``delta = clip(DELTA_SPACING / h, floor(h), 40)``: the basis's medium-range decay
  length ``1 / delta`` is a fixed number of constraint spacings, so that each
  basis function spans its neighbours whatever the density, but never longer
  than 1/8 of the box: beyond ``1 / delta`` the first-order (membrane) term
  of the energy rules, so a region no camera saw (the underside of a part
  scanned from above) closes flat between the seen edges, as Poisson's does,
  instead of bulging out along the tangents of the seen walls.  The floor is
  8 while the *points'* mean spacing ``h_p <= SPARSE_SPACING[0]`` (a dense
  cloud keeps it whatever number of constraints is picked from it) and moves
  linearly to
  ``SPARSE_DELTA_SPACING / h`` (a decay length of four spacings) at
  ``h_p = SPARSE_SPACING[1]`` and beyond (:func:`sparseness`): on a sparse
  cloud a decay length of 1/8 of the box is shorter than the spacing
  itself, f sags between the constraints and the surface falls apart into
  pieces, or vanishes, while a decay length much longer than a few
  spacings bridges the holes of a torus;
- ``tau = clip(TAU_SPACING * h, 0.005, 0.025)``: the short range follows the
  spacing inside the paper's range (it matters little);
- ``lambda = phi(0) * (LAMBDA_BASE + LAMBDA_NOISE * (sigma / h)^2)``: the
  smoothing acts relative to the kernel's value at zero (the diagonal of the
  system), and grows with the noise variance measured in constraint spacings;
  constraints moved onto local fits (denoised) keep a floor of
  ``LAMBDA_BASE_DENOISED`` instead: their leftover error is correlated along
  the surface, which the predicted ``sigma`` does not see.  The noise term
  fades out with the same sparseness as the delta floor: the neighbourhoods
  of a sparse cloud are as wide as its features, so the local fits measure
  the shape, not the noise.

Calibration: the constants were fitted by a sweep on a noisy torus
(Chamfer L1 to the analytic shape) and recalibrated on the robustness
study's range scans (``benchmarks/paper/robustness.py``).  What the sweep
showed: lambda matters most, and too little smoothing costs more than too
much, so the noise term is set a little high; delta matters less, and the
smallest decay length that still spans the neighbours is best under noise;
tau changes little.  The delta floor of 8 closes unseen undersides flat;
``LAMBDA_BASE`` is small on clean scans, ``LAMBDA_BASE_DENOISED`` larger on
denoised constraints.  The measurements are in ``docs/data/design-measurements.md``
("Automatic parameters").
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.validation import as_points, check_number

__all__ = [
    "AutoParameters",
    "choose_parameters",
    "estimate_noise",
    "parameters_from",
    "PAPER_PARAMETERS",
    "SPARSE_SPACING",
    "sparseness",
]

#: The paper's fixed values (normalized box): what ``--no-auto`` uses.
PAPER_PARAMETERS = {"delta": 10.0, "tau": 0.01, "lambda_surface": 1e-3}

# Rule constants (fitted by the calibration sweep, see the module notes; measurements in docs/data/design-measurements.md).
DELTA_SPACING = 0.12
TAU_SPACING = 0.25
LAMBDA_BASE = 0.003
LAMBDA_BASE_DENOISED = 0.03
LAMBDA_NOISE = 1.5
DELTA_RANGE = (8.0, 40.0)
#: Constraint spacings (box units) between which a cloud counts as sparse:
#: dense at or below the first (the floor and the noise term in full),
#: sparse at or above the second (neither).
SPARSE_SPACING = (0.06, 0.12)
#: The delta floor of a sparse cloud: ``SPARSE_DELTA_SPACING / h``.
SPARSE_DELTA_SPACING = 0.25
TAU_RANGE = (0.005, 0.025)


@dataclass(frozen=True)
class AutoParameters:
    """Parameters chosen from the data, and what they were chosen from.

    Attributes
    ----------
    delta, tau : float
        Multi-order basis parameters (normalized box).
    lambda_surface : float
        Smoothing of the surface constraints.
    lambda_relative : float
        ``lambda_surface / phi(0)``.
    spacing : float
        Mean nearest-neighbour distance of the surface constraints (box units).
    noise : float
        Estimated noise standard deviation across the surface (box units).
    scale : float
        Box units per data unit (``spacing / scale`` is in data units).
    reason : str
        One line: the inputs and the rule.
    """

    delta: float
    tau: float
    lambda_surface: float
    lambda_relative: float
    spacing: float
    noise: float
    scale: float
    reason: str

    def as_dict(self) -> dict:
        """Plain-float dictionary (for JSON and ``Reconstruction.stats``)."""
        return asdict(self)


def estimate_noise(points, k: int = 20, max_points: int = 4000, seed: int = 0) -> float:
    """Standard deviation of the points across the surface they sample.

    For each of up to ``max_points`` query points (a seeded random subset),
    its ``k`` nearest neighbours are put in their PCA frame and a quadratic
    height field ``z = a x^2 + b xy + c y^2 + d x + e y + f`` is fitted by
    least squares; ``RSS / (k - 6)`` estimates the noise variance there (the
    quadric absorbs the curvature that a plane fit would count as noise, and
    the divisor corrects for the six fitted coefficients).  The estimate is
    the median over the query points of the local RMS, which ignores the
    minority of neighbourhoods that straddle an edge, two sheets or an
    outlier.

    A neighbourhood must be wide compared with the noise, or its PCA plane
    follows the noise and the estimate falls short: when the estimate
    exceeds a quarter of the median neighbourhood radius, it is repeated on
    a random subset thin enough to widen the neighbourhoods to four
    estimates (at least 200 points kept; at most three rounds).

    Parameters
    ----------
    points : (N, 3) array_like
        At least 10 points.
    k : int
        Neighbourhood size, 10..200.
    max_points : int
        Query points used (>= 1).
    seed : int

    Returns
    -------
    float
        In the points' units; ~0 for exact samples of a smooth surface.
    """
    pts = as_points(points, min_count=10)
    k = check_number("k", k, low=10, high=200, integer=True)
    max_points = check_number("max_points", max_points, low=1, integer=True)
    seed = check_number("seed", seed, low=0, integer=True)
    rng = np.random.default_rng(seed)
    sigma, radius = _local_noise(pts, min(k, len(pts)), max_points, rng)
    for _ in range(3):
        if sigma <= 0.25 * radius or len(pts) <= 200:
            break
        keep = max(200, int(len(pts) * (radius / (4.0 * sigma)) ** 2))
        pts = pts[rng.choice(len(pts), keep, replace=False)]
        sigma, radius = _local_noise(pts, min(k, len(pts)), max_points, rng)
    return sigma


def _local_noise(pts: np.ndarray, k: int, max_points: int, rng) -> tuple[float, float]:
    """(median local quadric-fit RMS, median k-neighbourhood radius)."""
    query = np.arange(len(pts)) if len(pts) <= max_points else np.sort(rng.choice(len(pts), max_points, replace=False))
    dist, nb = cKDTree(pts).query(pts[query], k=k, workers=-1)
    local = pts[nb] - pts[nb].mean(axis=1, keepdims=True)  # (Q, k, 3)
    _, _, vt = np.linalg.svd(local, full_matrices=False)  # rows of vt: principal axes
    uvw = np.einsum("qkd,qjd->qkj", local, vt)  # coordinates in the PCA frame; z = smallest axis
    x, y, z = uvw[..., 0], uvw[..., 1], uvw[..., 2]
    size = np.sqrt((x * x + y * y).mean(axis=1, keepdims=True)) + 1e-300
    x, y = x / size, y / size  # conditioning
    design = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=2)  # (Q, k, 6)
    gram = np.einsum("qki,qkj->qij", design, design) + 1e-12 * np.eye(6)
    rhs = np.einsum("qki,qk->qi", design, z)
    coef = np.linalg.solve(gram, rhs[..., None])[..., 0]
    resid = z - np.einsum("qki,qi->qk", design, coef)
    local_sigma = np.sqrt((resid * resid).sum(axis=1) / max(k - 6, 1))
    return float(np.median(local_sigma)), float(np.median(dist[:, -1]))


def sparseness(spacing: float) -> float:
    """How sparse a cloud of mean point spacing ``h`` (box units) is, in [0, 1].

    0 while ``h <= SPARSE_SPACING[0]``, 1 from ``SPARSE_SPACING[1]`` on,
    linear between.  The delta floor is ``(1 - sparseness) * DELTA_RANGE[0]
    + sparseness * SPARSE_DELTA_SPACING / h`` and the noise term of lambda is
    scaled by ``1 - sparseness``.
    """
    lo, hi = SPARSE_SPACING
    return float(np.clip((float(spacing) - lo) / (hi - lo), 0.0, 1.0))


def parameters_from(spacing: float, noise: float, scale: float = 1.0, denoised: bool = False,
                    point_spacing: float | None = None) -> AutoParameters:
    """The rule: (spacing h, noise sigma) in box units -> delta, tau, lambda.

    See the module notes.  ``scale`` (box units per data unit) is only
    recorded, for reporting in data units.  ``denoised``: the constraints
    were moved onto local fits and ``noise`` is what the fits predict is left
    (the lambda floor is then ``LAMBDA_BASE_DENOISED``).  ``point_spacing``:
    the mean nearest-neighbour spacing of all the points (box units), which
    says how sparse the cloud is (:func:`sparseness`); default ``spacing``.
    """
    h = check_number("spacing", spacing, low=0.0, low_open=True)
    sigma = check_number("noise", noise, low=0.0)
    h_points = h if point_spacing is None else check_number("point_spacing", point_spacing, low=0.0, low_open=True)
    from o3drbf.rbf.kernels import MultiOrder

    sparse = sparseness(h_points)
    floor = (1.0 - sparse) * DELTA_RANGE[0] + sparse * SPARSE_DELTA_SPACING / h
    delta = float(np.clip(DELTA_SPACING / h, floor, DELTA_RANGE[1]))
    tau = float(np.clip(TAU_SPACING * h, *TAU_RANGE))
    ratio = sigma / h
    base = LAMBDA_BASE_DENOISED if denoised else LAMBDA_BASE
    lam_rel = base + (1.0 - sparse) * LAMBDA_NOISE * ratio * ratio
    lam = lam_rel * MultiOrder(delta, tau).value_at_zero
    if sparse == 0.0:
        delta_text = f"clip({DELTA_SPACING:g}/h, {DELTA_RANGE[0]:g}, {DELTA_RANGE[1]:g})"
        noise_text = f"{LAMBDA_NOISE:g} (noise/h)^2"
    else:
        delta_text = (f"clip({DELTA_SPACING:g}/h, {floor:.3g}, {DELTA_RANGE[1]:g}) (points' spacing {h_points:.3g}, sparse {sparse:.2f}: "
                      f"floor {1 - sparse:.2f} x {DELTA_RANGE[0]:g} + {sparse:.2f} x {SPARSE_DELTA_SPACING:g}/h)")
        noise_text = f"{1 - sparse:.2f} x {LAMBDA_NOISE:g} (noise/h)^2"
    reason = (
        f"spacing h {h:.4f}, noise {sigma:.4f} ({ratio:.2f} h) in box units{' (denoised constraints)' if denoised else ''}: "
        f"delta = {delta_text} = {delta:.3g}, tau = {TAU_SPACING:g} h = {tau:.3g}, "
        f"lambda = ({base:g} + {noise_text}) phi(0) = {lam_rel:.3g} phi(0) = {lam:.3g}"
    )
    return AutoParameters(delta, tau, float(lam), float(lam_rel), float(h), float(sigma), float(scale), reason)


def choose_parameters(points, *, surface_count: int | None = 3000, surface_radius: float | None = None, seed: int = 0) -> AutoParameters:
    """Choose delta, tau and lambda for these points.

    The points are normalized into the 2x2x2 box, the surface constraints
    are picked as :func:`o3drbf.reconstruct` would (Poisson-disc subset of
    ``surface_count`` points, or radius ``surface_radius``), their mean
    nearest-neighbour spacing and the points' noise (:func:`estimate_noise`
    on all points) go through :func:`parameters_from`.

    Parameters
    ----------
    points : (N, 3) array_like
        Surface samples (after any outlier removal).
    surface_count, surface_radius, seed
        As in :func:`o3drbf.reconstruct`.

    Returns
    -------
    AutoParameters
    """
    from o3drbf.constraints.core import surface_constraints
    from o3drbf.prep.normalize import Normalization
    from o3drbf.prep.sampling import mean_spacing

    pts = as_points(points, min_count=10)
    norm = Normalization.from_points(pts)
    box = norm.forward(pts)
    idx = surface_constraints(box, count=surface_count, radius=surface_radius, seed=seed)
    return parameters_from(mean_spacing(box[idx]), estimate_noise(box, seed=seed), norm.scale, point_spacing=mean_spacing(box))
