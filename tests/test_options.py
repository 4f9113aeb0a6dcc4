"""One table of defaults, one kernel registry, stages callable alone, the typed report."""

import numpy as np
import pytest

import o3drbf
from o3drbf.cli.commands import build_parser, options_from_args
from o3drbf.options import API_ONLY, DEFAULTS, VIEWER_OVERRIDES, Options
from o3drbf.pointset import PointSet
from o3drbf.rbf.kernels import KERNELS, Kernel, register_kernel
from o3drbf.synthetic.shapes import Sphere, Torus


def test_cli_api_viewer_and_compare_share_the_defaults():
    api = Options()
    assert api.flat() == DEFAULTS
    args = build_parser().parse_args(["reconstruct", "in.ply", "-o", "out.ply"])
    assert options_from_args(args) == api
    # Every option of the table is on the command line, with the table's default.
    for name, value in DEFAULTS.items():
        if name in API_ONLY:  # bounds and the tile sizes: Python only
            assert not hasattr(args, name), name
            continue
        assert getattr(args, name) == value, name
    from o3drbf.viewers.refit import FitParams

    viewer = FitParams()
    start = {**DEFAULTS, **VIEWER_OVERRIDES}
    for name in ("lambda_surface", "delta", "tau", "auto", "resolution", "surface_count", "outliers", "solver"):
        assert getattr(viewer, name) == start[name], name
    from o3drbf.evaluation import compare

    args = build_parser().parse_args(["compare", "in.ply"])
    assert args.resolution == DEFAULTS["resolution"]
    assert set(KERNELS) <= set(compare.available_methods())


def test_a_changed_default_reaches_the_command_line(monkeypatch):
    monkeypatch.setitem(DEFAULTS, "surface_count", 1234)
    args = build_parser().parse_args(["reconstruct", "in.ply", "-o", "out.ply"])
    assert args.surface_count == 1234


def test_options_validate_before_any_costly_step():
    with pytest.raises(ValueError, match="unknown option"):
        Options.create(surface_cuont=5)
    with pytest.raises(ValueError, match="delta does not apply to the 'gaussian' kernel"):
        Options.create(kernel="gaussian", delta=-5).validate()
    with pytest.raises(ValueError, match="sigma does not apply to the 'multiorder' kernel"):
        Options.create(sigma=0.3).validate()
    with pytest.raises(ValueError, match="tau must be"):
        Options.create(tau=-1).validate()
    assert Options.create(basis="gaussian", sigma=0.2).parameters.kernel == "gaussian"


class Wendland(Kernel):
    """A compactly supported kernel defined only here: phi(r) = (1 - r/s)^4_+ (4 r/s + 1)."""

    name = "wendland_test"
    polynomial_degree = 0
    positive_definite = True

    def __init__(self, support: float = 1.5):
        self.support = float(support)

    def __call__(self, r):
        q = np.clip(np.asarray(r, dtype=float) / self.support, 0, 1)
        return (1 - q) ** 4 * (4 * q + 1)

    def derivative_over_r(self, r):
        q = np.clip(np.asarray(r, dtype=float) / self.support, 0, 1)
        return -20 * (1 - q) ** 3 / self.support**2

    def derivative(self, r):
        return self.derivative_over_r(r) * np.asarray(r, dtype=float)

    @property
    def params(self):
        return {"support": self.support}


@pytest.fixture
def wendland():
    register_kernel(Wendland)
    yield Wendland
    KERNELS.pop(Wendland.name)


def test_a_kernel_defined_in_a_test_works_end_to_end(wendland, tmp_path):
    p, n = Sphere(1.0).sample(1500, seed=3)
    r = o3drbf.reconstruct(p, n, kernel="wendland_test", surface_count=300, resolution=32, outliers="none")
    assert r.report.basis == "Wendland(support=1.5)"
    assert r.report.parameter_source == {"lambda_surface": "paper"}
    radii = np.linalg.norm(np.asarray(r.mesh.vertices), axis=1)
    assert abs(np.median(radii) - 1) < 0.05
    # Its parameters are validated like any other kernel's, and the CLI offers it.
    with pytest.raises(ValueError, match="delta does not apply"):
        o3drbf.reconstruct(p, n, kernel="wendland_test", delta=3)
    args = build_parser().parse_args(["reconstruct", "x.ply", "-o", "y.ply", "--kernel", "wendland_test"])
    assert options_from_args(args).parameters.kernel == "wendland_test"
    from o3drbf.evaluation.compare import parse_methods

    assert parse_methods("wendland_test,poisson") == ("wendland_test", "poisson")
    # A kernel instance works too.
    r2 = o3drbf.reconstruct(p, n, kernel=Wendland(1.5), surface_count=300, resolution=32, outliers="none")
    np.testing.assert_allclose(np.asarray(r2.mesh.vertices), np.asarray(r.mesh.vertices))


def test_stages_alone_give_what_reconstruct_gives():
    p, n = Torus(0.6, 0.25).sample(3000, noise=0.003, seed=2)
    opts = Options.create(surface_count=600, resolution=40, outliers="none")
    whole = o3drbf.reconstruct(p, n, options=opts)
    data = PointSet.create(p, n)
    data, outl = o3drbf.remove_outliers(data, opts.outliers)
    data, estimated = o3drbf.ensure_normals(data)
    cset = o3drbf.build_constraints(data, opts.constraints)
    params = o3drbf.choose_parameters(data, cset, opts.parameters)
    surface, sol, _ = o3drbf.fit_surface(cset, params, opts.fit)
    mesh = o3drbf.mesh_surface(surface, opts.extract)
    assert not estimated and outl.removed == 0
    np.testing.assert_allclose(np.asarray(mesh.vertices), np.asarray(whole.mesh.vertices))
    rep = whole.report
    assert [t.name for t in rep.stages] == ["read", "outliers", "normals", "constraints", "parameters", "fit", "extract"]
    assert all(t.seconds >= 0 and t.peak_mb > 0 for t in rep.stages)
    assert rep.surface_constraints == len(cset.surface_index) and rep["points"] == 3000


def test_pointset_validates_once_and_caches_spacing():
    p, n = Sphere(1.0).sample(500, seed=1)
    ps = PointSet.create(p, n)
    assert ps.spacing == ps.spacing and ps._cache["spacing"] > 0
    with pytest.raises(ValueError, match="point_camera needs cameras"):
        PointSet.create(p, n, point_camera=np.zeros(500, int))
    with pytest.raises(ValueError, match="colors must"):
        PointSet.create(p, n, colors=np.full((500, 3), 2.0))
    import open3d as o3d

    t = o3d.t.geometry.PointCloud(o3d.core.Tensor(p))
    t.point.normals = o3d.core.Tensor(n)
    tp = PointSet.create(t)
    np.testing.assert_allclose(tp.normals, n / np.linalg.norm(n, axis=1, keepdims=True))
    sub = ps.subset(np.arange(100))
    assert len(sub) == 100 and sub.normals.shape == (100, 3)


def test_lambda_exterior_is_relative_to_phi0_of_the_kernel_used():
    p, n = Sphere(1.0).sample(800, seed=4)
    for delta in (3.0, 20.0):
        r = o3drbf.reconstruct(p, n, delta=delta, tau=0.01, surface_count=200, extract_mesh=False, outliers="none")
        phi0 = r.surface.kernel.value_at_zero
        ext = r.constraints.kind != 0
        np.testing.assert_allclose(r.constraints.smoothing[ext], DEFAULTS["lambda_exterior"] * phi0)
        assert r.report.parameters["lambda_exterior"] == pytest.approx(DEFAULTS["lambda_exterior"] * phi0)


def test_estimated_normals_are_oriented_outward_per_separate_object():
    # Two tori far apart, each flipped inward: orientation is settled per
    # connected piece, so both come back outward.
    a, na = Torus(0.6, 0.25).sample(3000, seed=1)
    b = a + [3.0, 0.0, 0.0]
    normals = o3drbf.estimate_normals(np.vstack([a, b]))
    truth = np.vstack([na, na])
    agree = np.einsum("ij,ij->i", normals, truth)
    assert (agree[:3000] > 0).mean() > 0.98 and (agree[3000:] > 0).mean() > 0.98


def test_public_names_do_not_shadow_modules():
    import importlib

    for name in ("extract", "surface", "pipeline", "options", "pointset"):
        module = importlib.import_module(f"o3drbf.{name}")
        assert getattr(o3drbf, name, module) is module, name


def test_automatic_sizes_follow_the_data():
    from o3drbf.options import auto_resolution, auto_surface_count

    assert auto_surface_count(6_000) == 3000 and auto_surface_count(12_000) == 4000 and auto_surface_count(120_000) == 30_000
    assert auto_surface_count(10**7) == 30_000
    # noisy scans: points / 3 up to 10,000, then points / 6
    assert [auto_surface_count(n, noisy=True) for n in (24_000, 45_000, 90_000, 10**7)] == [8000, 10_000, 15_000, 30_000]
    assert auto_resolution(0.048) == 83 and auto_resolution(0.1) == 64 and auto_resolution(0.012) == 256 and auto_resolution(0.03) == 133
    # One constraint per 3 points when clean (kept as they are); noisy (denoised): at most 10,000 here.
    from o3drbf.pipeline import build_constraints
    from o3drbf.pointset import PointSet

    p, n = Sphere(1.0).sample(48_000, seed=5)
    cset = build_constraints(PointSet.create(p, n))
    assert len(cset.surface_index) == pytest.approx(16_000, rel=0.1) and not cset.denoised
    p, n = Sphere(1.0).sample(48_000, noise=0.01, seed=5)
    cset = build_constraints(PointSet.create(p, n))
    assert len(cset.surface_index) == pytest.approx(10_000, rel=0.1) and cset.denoised


def test_a_resolution_that_cannot_fit_is_refused_before_any_work(monkeypatch):
    import o3drbf.solvers.base as base

    monkeypatch.setattr(base, "available_memory", lambda: 2 * 2**30)
    Options.create(resolution=256).validate()  # 0.3 GB
    with pytest.raises(ValueError, match="resolution 1024 needs about .* GB .* use a smaller --resolution"):
        Options.create(resolution=1024).validate()
