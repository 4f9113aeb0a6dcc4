"""docs/quickstart.ipynb runs (its asserts check the report against the analytic shape), and result.plot() draws.

The notebook is committed without outputs; ``make figures`` executes it
(scripts/run_notebook.py) and saves its figure as docs/images/quickstart.png.
"""

import importlib.util
import io

import numpy as np
import pytest

from conftest import REPO

NOTEBOOK = REPO / "docs" / "quickstart.ipynb"


def runner():
    spec = importlib.util.spec_from_file_location("run_notebook", REPO / "scripts" / "run_notebook.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def png_pixels(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def test_committed_notebook_has_no_outputs():
    import nbformat

    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(not c.outputs and c.execution_count is None for c in code), "strip the outputs before committing"
    assert any("figure" in c.metadata.get("tags", []) for c in code)


def test_quickstart_notebook_runs_and_shows_the_comparison():
    nb = runner().execute(NOTEBOOK, timeout=90)  # raises CellExecutionError if any cell (an assert) fails
    image = png_pixels(runner().figure(nb))
    assert image.shape == (500, 1200, 3)
    # two panels, each drawing a mesh: a good part of each half is not the white background
    for half in (image[:, :600], image[:, 600:]):
        assert (half.min(axis=2) < 200).mean() > 0.1
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "| o3drbf |" in text and "| Open3D Poisson depth 8 |" in text


def test_a_failing_cell_fails_the_run(tmp_path):
    import nbformat
    from nbclient.exceptions import CellExecutionError

    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell("report_points = 5\nassert report_points == 6, 'report mismatch'")])
    path = tmp_path / "bad.ipynb"
    nbformat.write(nb, path)
    with pytest.raises(CellExecutionError, match="report mismatch"):
        runner().execute(path, timeout=30)


@pytest.fixture(scope="module")
def small():
    """A Reconstruction of a sphere, its parts made directly (no fit: these tests are about drawing)."""
    import open3d as o3d

    from o3drbf import Constraints, Reconstruction, Report
    from o3drbf.constraints.core import EXTERIOR, SPHERE, SURFACE

    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=20)
    d = np.random.default_rng(0).normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    constraints = Constraints.concat(Constraints.of_kind(d, SURFACE, 0.0), Constraints.of_kind(1.1 * d, EXTERIOR, 0.0),
                                     Constraints.of_kind(3.0 * d[:20], SPHERE, 0.0))
    return Reconstruction(surface=None, mesh=mesh, constraints=constraints, solution=None, report=Report())


def test_plot_writes_the_panels_it_is_given(small, tmp_path):
    import open3d as o3d

    path = tmp_path / "plot.png"
    peer = o3d.geometry.TriangleMesh.create_torus(0.6, 0.25)
    assert small.plot(compare={"Poisson": peer}, constraints=True, screenshot=path, window_size=(400, 200)) is None
    image = png_pixels(path.read_bytes())
    assert image.shape == (200, 400, 3)
    for half in (image[:, :200], image[:, 200:]):
        assert (half.min(axis=2) < 200).mean() > 0.05
    from o3drbf.viewers.app import COLORS

    def near(colour):  # within 40 per channel of the viewer's layer colour (the markers are shaded spheres)
        rgb = np.array([int(colour[i:i + 2], 16) for i in (1, 3, 5)])
        return np.abs(image.astype(int) - rgb).max(axis=2) <= 40

    blue, green = near(COLORS["surface"]), near(COLORS["exterior"])  # the colours of o3drbf view
    assert blue[:, :200].sum() > 20 and green[:, :200].sum() > 5  # constraints drawn on the first panel only
    assert blue[:, 200:].sum() == 0 and green[:, 200:].sum() == 0


def test_plot_without_showing_returns_the_open_plotter(small):
    plotter = small.plot(show=False)
    try:
        assert plotter.shape == (1, 1) and plotter.window_size == [500, 450]
    finally:
        plotter.close()


def test_plot_refuses_what_it_cannot_draw(small, tmp_path):
    from dataclasses import replace

    with pytest.raises(ValueError, match="must be a .png"):
        small.plot(screenshot=tmp_path / "x.jpg")
    with pytest.raises(ValueError, match="no mesh"):
        replace(small, mesh=None).plot()
    assert not list(tmp_path.iterdir())
