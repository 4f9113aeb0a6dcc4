"""o3drbf: smooth, closed surfaces from sparse, noisy 3-D points.

Volumetric regularization with multi-order radial basis functions (Dinh,
Turk & Slabaugh, PAMI 2002): one global implicit function fitted by a
regularized linear solve, meshed by marching cubes.

>>> import o3drbf
>>> from o3drbf.synthetic.shapes import Torus
>>> points, normals = Torus().sample(5000, noise=0.005)
>>> result = o3drbf.reconstruct(points, normals)          # doctest: +SKIP
>>> result.mesh, result.surface(points[:3])               # doctest: +SKIP
"""

from o3drbf.pipeline import DEFAULTS, Reconstruction, estimate_normals, fit, reconstruct
from o3drbf.constraints.core import Constraints
from o3drbf.extract import extract_mesh
from o3drbf.rbf.kernels import KERNELS, Gaussian, Kernel, MultiOrder, ThinPlate, make_kernel
from o3drbf.prep.normalize import Normalization
from o3drbf.solvers import ConvergenceWarning, Solution, solve
from o3drbf.surface import ImplicitSurface

__version__ = "0.1.0"

__all__ = [
    "reconstruct",
    "fit",
    "Reconstruction",
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
    "estimate_normals",
    "DEFAULTS",
]
