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

from o3drbf.startup import defer_open3d_plotly, prefer_numba_workqueue

defer_open3d_plotly()  # before anything imports open3d (see o3drbf.startup)
prefer_numba_workqueue()  # before any compiled module runs in parallel

#: Where each public name lives: imported on first use (PEP 562), so ``import o3drbf`` and
#: ``o3drbf --help`` do not load SciPy, Numba and Open3D until something needs them.
_PUBLIC = {
    "o3drbf.constraints.core": ("Constraints",),
    "o3drbf.extract": ("extract_mesh",),
    "o3drbf.options": ("DEFAULTS", "Options", "PhotoOptions", "CompareOptions", "ViewOptions"),
    "o3drbf.pipeline": ("Reconstruction", "Report", "build_constraints", "check_given_normals", "choose_parameters", "colour",
                        "ensure_normals", "estimate_normals", "mesh_surface", "fit", "fit_surface", "mesh_confidence", "reconstruct",
                        "register_scans", "remove_outliers"),
    "o3drbf.pointset": ("PointSet", "read_input"),
    "o3drbf.prep.normalize": ("Normalization",),
    "o3drbf.rbf.kernels": ("KERNELS", "Gaussian", "Kernel", "MultiOrder", "ThinPlate", "make_kernel", "register_kernel"),
    "o3drbf.solvers": ("ConvergenceWarning", "Solution", "solve"),
    "o3drbf.surface": ("ImplicitSurface",),
}
_HOME = {name: module for module, names in _PUBLIC.items() for name in names}


def __getattr__(name: str):
    module = _HOME.get(name)
    if module is None:
        raise AttributeError(f"module 'o3drbf' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # the next access is a plain attribute
    return value


def __dir__():
    return sorted(set(globals()) | set(_HOME))


__version__ = "0.2.0"

__all__ = [
    "reconstruct",
    "Reconstruction",
    "Report",
    "Options",
    "PhotoOptions",
    "CompareOptions",
    "ViewOptions",
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
