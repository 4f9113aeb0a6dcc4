"""o3drbf: smooth, closed surfaces from sparse, noisy 3-D points.

Volumetric regularization with multi-order radial basis functions (Dinh,
Turk & Slabaugh, PAMI 2002): one global implicit function fitted by a
regularized linear solve, meshed by marching cubes.

>>> import o3drbf
>>> from o3drbf.synthetic.shapes import Torus
>>> points, normals = Torus().sample(5000, noise=0.005)
>>> result = o3drbf.reconstruct(points, normals)          # doctest: +SKIP
>>> result.mesh, result.surface(points[:3])               # doctest: +SKIP

The stages of :func:`reconstruct` are public too (:mod:`o3drbf.pipeline`):
read -> register (scans with cameras) -> outliers -> constraints -> parameters -> fit -> extract -> colour
(-> confidence and trim, when asked).
"""

from o3drbf.startup import defer_open3d_plotly

defer_open3d_plotly()  # before anything imports open3d (see o3drbf.startup)

from o3drbf.constraints.core import Constraints  # noqa: E402
from o3drbf.extract import extract_mesh
from o3drbf.options import DEFAULTS, Options
from o3drbf.pipeline import (
    Reconstruction,
    Report,
    build_constraints,
    check_given_normals,
    choose_parameters,
    colour,
    ensure_normals,
    estimate_normals,
    mesh_surface,
    fit,
    fit_surface,
    mesh_confidence,
    reconstruct,
    register_scans,
    remove_outliers,
)
from o3drbf.pointset import PointSet, read_input
from o3drbf.prep.normalize import Normalization
from o3drbf.rbf.kernels import KERNELS, Gaussian, Kernel, MultiOrder, ThinPlate, make_kernel, register_kernel
from o3drbf.solvers import ConvergenceWarning, Solution, solve
from o3drbf.surface import ImplicitSurface

__version__ = "0.2.0"

__all__ = [
    "reconstruct",
    "Reconstruction",
    "Report",
    "Options",
    "DEFAULTS",
    "PointSet",
    "read_input",
    "register_scans",
    "remove_outliers",
    "check_given_normals",
    "ensure_normals",
    "build_constraints",
    "choose_parameters",
    "fit_surface",
    "mesh_surface",
    "colour",
    "mesh_confidence",
    "fit",
    "ImplicitSurface",
    "extract_mesh",
    "solve",
    "Solution",
    "ConvergenceWarning",
    "Constraints",
    "Normalization",
    "Kernel",
    "MultiOrder",
    "ThinPlate",
    "Gaussian",
    "KERNELS",
    "make_kernel",
    "register_kernel",
    "estimate_normals",
]
