"""Parameters: the kernel and the per-constraint smoothing (given values, the automatic rule, or the paper's)."""

from __future__ import annotations

import logging

import numpy as np

from o3drbf.constraints.core import SURFACE
from o3drbf.options import PAPER_VALUES, ParameterOptions
from o3drbf.pipeline.records import ConstraintSet, Parameters
from o3drbf.pointset import PointSet
from o3drbf.rbf.kernels import Kernel, MultiOrder, kernel_class, make_kernel
from o3drbf.validation import per_point

__all__ = ["choose_parameters"]

log = logging.getLogger("o3drbf")


def choose_parameters(data: PointSet, cset: ConstraintSet, options: ParameterOptions = ParameterOptions(), *, seed: int = 0,
                      confidence=None) -> Parameters:
    """The kernel and per-constraint smoothing.

    Values given explicitly always win.  With ``options.auto`` the
    multi-order parameters left at None come from the surface constraints'
    spacing and the points' noise (:mod:`o3drbf.constraints.parameters`);
    otherwise from the paper (:data:`o3drbf.options.PAPER_VALUES`).

    Parameters
    ----------
    data : PointSet
        The points the constraints were built from.
    cset : ConstraintSet
    options : ParameterOptions
    seed : int
    confidence : (N,) array_like, optional
        Per point of ``data``, a trust in (0, 1]: its surface smoothing is
        divided by it.

    Returns
    -------
    Parameters

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> from o3drbf import PointSet
    >>> data = PointSet.create(points, normals)
    >>> from o3drbf import build_constraints, choose_parameters
    >>> cset = build_constraints(data)
    >>> params = choose_parameters(data, cset)
    >>> params.kernel.name, len(params.smoothing) == len(cset.constraints.points)
    ('multiorder', True)
    """
    options.validate()
    n = len(data)
    if isinstance(options.kernel, Kernel):
        cls, given = type(options.kernel), dict(options.kernel.params)
    else:
        cls, given = kernel_class(options.kernel), options.kernel_params()
    use_auto = bool(options.auto) and issubclass(cls, MultiOrder)
    names = ("delta", "tau") if issubclass(cls, MultiOrder) else ()
    source = {name: "given" if (name in given) else ("auto" if use_auto else "paper") for name in names}
    source["lambda_surface"] = "given" if options.lambda_surface is not None else ("auto" if use_auto else "paper")
    box = cset.normalization.forward(data.points)
    chosen = None
    noise = 0.0
    if use_auto and "auto" in source.values():
        from o3drbf.constraints.parameters import estimate_noise, parameters_from

        noise = cset.noise if np.isfinite(cset.noise) else estimate_noise(box, seed=seed)
        # The smoothing follows the noise the constraints carry: after denoising, theirs, not the points'.
        chosen = parameters_from(cset.spacing, cset.constraint_noise if cset.denoised else noise, cset.normalization.scale,
                                 denoised=bool(cset.denoised), point_spacing=data.spacing * cset.normalization.scale)
        log.info("automatic parameters: %s", chosen.reason)
        given = {**{"delta": chosen.delta, "tau": chosen.tau}, **given}
    if isinstance(options.kernel, Kernel):
        kernel = options.kernel
    else:
        defaults = {k: PAPER_VALUES[k] for k in cls.parameter_names() if k in PAPER_VALUES}
        kernel = make_kernel(cls.name, **{**defaults, **given})
    _check_width(kernel, options, cset.spacing)
    if source["lambda_surface"] == "auto":
        lam_points = np.full(n, chosen.lambda_relative * kernel.value_at_zero)
    else:
        lam_points = per_point("lambda_surface", PAPER_VALUES["lambda_surface"] if options.lambda_surface is None else options.lambda_surface, n)
    if confidence is not None:
        lam_points = lam_points / np.clip(np.asarray(confidence, dtype=float), 1e-3, 1.0)
    lam_e = float(options.lambda_exterior) * kernel.value_at_zero
    c = cset.constraints
    smoothing = np.where(c.kind == SURFACE, 0.0, lam_e)
    smoothing[c.kind == SURFACE] = lam_points[cset.surface_index]
    return Parameters(kernel, smoothing, float(np.median(lam_points)), lam_e, source,
                      None if chosen is None else chosen.as_dict(), float(noise))


def _check_width(kernel: Kernel, options: ParameterOptions, spacing: float) -> None:
    """Refuse a given Gaussian width under one surface-constraint spacing (box units): the bumps would not overlap."""
    sigma = kernel.params.get("sigma")
    given = options.sigma is not None or isinstance(options.kernel, Kernel)
    if sigma is None or not given or not np.isfinite(spacing) or sigma >= spacing:
        return
    raise ValueError(f"--sigma {sigma:g} is narrower than the surface constraints' spacing {spacing:.3g} (box units): the Gaussians "
                     f"do not overlap and leave no surface between the constraints; give --sigma of at least {spacing:.2g} "
                     f"(about {8 * spacing:.2g}, 8 spacings, suits most data)")
