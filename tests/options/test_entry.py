"""Every entry point takes one options object: ``options=`` and keyword overrides reach the same place, the
defaults are the table, and a bad value is refused once, before any work, in one line."""

from __future__ import annotations

import types

import numpy as np
import pytest

import o3drbf
from o3drbf.options import CompareOptions, Options, PhotoOptions, ViewOptions, defaults
from o3drbf.synthetic.shapes import Sphere


class Stop(Exception):
    pass


@pytest.mark.parametrize("cls, entry", [(Options, "reconstruct"), (PhotoOptions, "photos"), (CompareOptions, "compare"),
                                        (ViewOptions, "view")])
def test_defaults_are_the_table_and_validate(cls, entry):
    opts = cls().validate()
    flat = opts.flat()
    assert flat == defaults(entry)
    assert cls.create(**flat) == opts  # flat names round-trip


def test_reconstruct_honours_options_and_keywords():
    p, n = Sphere(1.0).sample(600, seed=1)
    kw = dict(surface_count=150, resolution=24, outliers="none", robust=False)
    by_options = o3drbf.reconstruct(p, n, options=Options.create(**kw))
    by_keyword = o3drbf.reconstruct(p, n, **kw)
    assert by_options.report.resolution == by_keyword.report.resolution == 24
    np.testing.assert_allclose(np.asarray(by_options.mesh.vertices), np.asarray(by_keyword.mesh.vertices))


def test_photos_honours_options_and_keywords(monkeypatch):
    """The carving's and the fit's options arrive where run_photos hands them on (carve and reconstruct, recorded)."""
    import o3drbf.photo.carve as carving
    import o3drbf.pipeline as pipeline
    from o3drbf.photo.pipeline import run_photos

    seen = {}

    def carve(images, cameras, *, bounds=None, options=None, masks=None, progress=False):
        seen["carve"] = options
        return types.SimpleNamespace(points=np.zeros((20, 3)), best_camera=lambda: None, voxel_size=0.1,
                                     bounds=np.array([[-1.0, -1, -1], [1, 1, 1]]), stats={})

    def reconstruct(points, *, options=None, **kw):
        seen["reconstruct"] = options
        raise Stop

    monkeypatch.setattr(carving, "carve", carve)
    monkeypatch.setattr(pipeline, "reconstruct", reconstruct)
    images = [np.zeros((20, 20, 3)) for _ in range(2)]
    results = []
    for how in ("options", "keyword"):
        kw = dict(voxels=48, delta=6.0, resolution=72, threshold=0.2)
        with pytest.raises(Stop):
            if how == "options":
                run_photos(None, images=images, cameras=[None, None], options=PhotoOptions.create(**kw))
            else:
                run_photos(None, images=images, cameras=[None, None], **kw)
        c, r = seen["carve"], seen["reconstruct"]
        results.append((c.resolution, c.threshold, r.parameters.delta, r.extract.resolution, r.outliers.radius, r.outliers.method))
    # outlier radius: 2.5 voxels of the carving (o3drbf.options.PHOTO_OUTLIER_VOXELS), the method the photos' override
    assert results[0] == results[1] == (48, 0.2, 6.0, 72, pytest.approx(0.25), "largest")


def test_compare_honours_options_and_keywords(monkeypatch):
    """The o3drbf rows run reconstruct with the compare options' Options (recorded), whichever way they came."""
    import o3drbf.pipeline as pipeline
    from o3drbf.evaluation.compare import compare

    seen = []

    def reconstruct(points, normals=None, *, options=None, kernel=None, **kw):
        seen.append((kernel, options.constraints.surface_count, options.extract.resolution, options.fit.solver))
        raise Stop("recorded")

    monkeypatch.setattr(pipeline, "reconstruct", reconstruct)
    p, n = Sphere(1.0).sample(300, seed=2)
    rows_a = compare(p, n, options=CompareOptions.create(methods="gaussian", surface_count=222, resolution=30, solver="dense"))
    rows_b = compare(p, n, methods="gaussian", surface_count=222, resolution=30, solver="dense")
    assert seen == [("gaussian", 222, 30, "dense")] * 2
    assert [r["method"] for r in rows_a] == [r["method"] for r in rows_b] == ["gaussian"]
    assert "recorded" in rows_a[0]["error"]
    with pytest.raises(ValueError, match="poisson_depth"):
        compare(p, n, poisson_depth=40)


def test_view_honours_options_and_keywords(monkeypatch, tmp_path):
    """The viewer's session gets the display options and the first fit (a stand-in app records them)."""
    pytest.importorskip("pyvista")
    import o3drbf.viewers.session as session
    from o3drbf.io.files import write_points

    p, n = Sphere(1.0).sample(300, seed=3)
    write_points(tmp_path / "s.ply", p, n)
    seen = []

    class App:
        @classmethod
        def offscreen(cls, data, params, options):
            seen.append((options.zoom, options.poisson_depth, params.resolution, params.delta))
            return cls()

        def fit_now(self):
            pass

        def save_screenshot(self, path):
            pass

        def describe(self):
            return "stand-in"

        def close(self):
            pass

    monkeypatch.setattr(session, "ViewerApp", App)
    kw = dict(zoom=0.5, poisson_depth=6, resolution=40, delta=7.0)
    shot = tmp_path / "v.png"
    assert session.view(tmp_path / "s.ply", options=ViewOptions.create(**kw), screenshot=shot) == 0
    assert session.view(tmp_path / "s.ply", screenshot=shot, **kw) == 0
    assert seen == [(0.5, 6, 40, 7.0)] * 2
    with pytest.raises(ValueError, match="zoom"):
        session.view(tmp_path / "s.ply", screenshot=shot, zoom=500)


def test_unknown_names_are_refused_with_the_valid_ones():
    for cls in (PhotoOptions, CompareOptions, ViewOptions):
        with pytest.raises(ValueError, match="unknown option.*valid:"):
            cls.create(surface_cuont=5)
