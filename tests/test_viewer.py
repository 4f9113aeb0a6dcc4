"""``o3drbf view``: offscreen pictures, the interactive app under Xvfb, picking, errors.

The scene is a small synthetic range scan of a torus (three cameras), so
every fit here takes about a second.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import numpy as np
import open3d as o3d
import pytest

from o3drbf.cli.commands import main
from o3drbf.synthetic.scans import range_scans, write_scan_json
from o3drbf.synthetic.shapes import Torus

pv = pytest.importorskip("pyvista")

from o3drbf.viewers.app import COLORS, SLIDERS, ViewerApp, parse_script  # noqa: E402
from o3drbf.viewers.geometry import camera_frusta, view_up, wind_like_normals  # noqa: E402
from o3drbf.viewers.inputs import load_view_input, model_constraints  # noqa: E402
from o3drbf.viewers.refit import FitParams, Refitter, pick_values  # noqa: E402

SMALL = ["--resolution", "24", "--surface-count", "300", "--poisson-depth", "6", "--window-size", "800", "400"]
PARAMS = FitParams(resolution=24, surface_count=300)


def _rgb(hex_colour: str) -> np.ndarray:
    return np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)])


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    d = tmp_path_factory.mktemp("viewer")
    t = Torus(0.6, 0.25)
    mesh = o3d.geometry.TriangleMesh.create_torus(t.R, t.r, 48, 24)
    points, point_camera, cameras = range_scans(mesh, n_views=3, width=64, height=48, noise=0.002, seed=0)
    write_scan_json(d / "scan.json", points, cameras, point_camera)
    o3d.io.write_point_cloud(str(d / "points.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
    return d


@pytest.fixture(scope="module")
def fitted(scan):
    """An offscreen app on the scan, fitted once (shared: fits cost time)."""
    app = ViewerApp.offscreen(load_view_input(str(scan / "scan.json")), PARAMS, window_size=(800, 400), poisson=False)
    app.fit_now()
    yield app
    app.close()


def _colour_pixels(image: np.ndarray, colour: str, x_from: int) -> int:
    """Pixels of exactly ``colour`` (+-2 per channel) right of ``x_from``.

    The control column (160 pixels of an 800-pixel window) holds the legend
    check boxes in the same colours; only the 3-D panels count.
    """
    rgb = image[:, x_from:, :3].astype(int)
    return int((np.abs(rgb - _rgb(colour)).max(axis=2) <= 2).sum())


# ---------------------------------------------------------------------------
# (a) offscreen screenshot through the command line


def test_screenshot_cli_shows_points_constraints_and_surface(scan, tmp_path, capsys):
    out = tmp_path / "view.png"
    code = main(["view", str(scan / "scan.json"), "--screenshot", str(out), *SMALL])
    assert code == 0, capsys.readouterr().err
    line = capsys.readouterr().out
    assert "mesh" in line and "triangles" in line and str(out) in line
    image = pv.read_texture(str(out)).to_image().point_data.active_scalars
    image = np.asarray(image).reshape(400, 800, -1)[::-1]  # rows top to bottom
    rgb = image[..., :3].astype(int)
    background = np.all(rgb == 255, axis=2)
    assert background.mean() < 0.97  # something is drawn
    # The paper's Fig. 8 colours: blue surface constraints, green exterior
    # constraints, in the 3-D area of both panels (not just the legend).
    blue = _colour_pixels(image, COLORS["surface"], x_from=170)
    green = _colour_pixels(image, COLORS["exterior"], x_from=170)
    assert blue > 200 and green > 20
    assert blue > 3 * green  # about ten surface constraints per exterior one (exterior_ratio 0.1)
    # The Poisson panel (right of 480 px) has a shaded mesh: many non-white pixels.
    assert (~background[:, 480:]).mean() > 0.05


def test_layers_toggle_what_is_drawn(fitted, tmp_path):
    """Blue pixels come from the surface-constraint layer: hiding it removes them."""
    def shot(name):
        path = fitted.save_screenshot(tmp_path / name)
        img = pv.read_texture(str(path)).to_image().point_data.active_scalars
        return np.asarray(img).reshape(400, 800, -1)[::-1]

    shown = _colour_pixels(shot("a.png"), COLORS["surface"], x_from=170)
    fitted.on_key("2")
    try:
        assert fitted.visible["surface"] is False
        hidden = _colour_pixels(shot("b.png"), COLORS["surface"], x_from=170)
    finally:
        fitted.on_key("2")
    assert shown > 200 and hidden == 0


# ---------------------------------------------------------------------------
# (b) the interactive app under Xvfb


def test_interactive_app_under_xvfb_responds_to_sliders(scan, fitted):
    xvfb = shutil.which("xvfb-run")
    if xvfb is None:
        pytest.skip("xvfb-run is not installed (scripts/setup.sh installs it): cannot open a window here")
    # An iso-level inside f's range near the data (f's scale is set by the smoothing).
    ext = fitted.refitter.constraints["exterior"]
    level = -0.5 * float(np.median(np.abs(fitted.refitter.surface.evaluate(ext))))
    lam = 10 * fitted.result.params.lambda_surface
    script = f"wait; print; set level {level!r}; set lambda_surface {lam!r}; wait; print; pick 0.85 0 0; key 1; quit"
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")
    for name in ("DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW"):  # the offscreen fixture set an EGL window for this process
        env.pop(name, None)
    proc = subprocess.run(
        [xvfb, "-a", sys.executable, "-m", "o3drbf.cli", "view", str(scan / "scan.json"), *SMALL, "--script", script],
        capture_output=True, text=True, timeout=150, env=env,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("o3drbf view: mesh")]
    assert len(lines) == 2, proc.stdout
    before, after = lines
    tri = [int(re.search(r"mesh (\d+) triangles", ln).group(1)) for ln in lines]
    assert tri[0] > 500 and tri[1] > 500 and tri[0] != tri[1]
    assert "level 0," in before and f"level {level:g}," in after
    assert f"lambda_surface {lam:.3g}" in after
    # The first (automatic) fit in the window equals the one made here.
    assert f"lambda_surface {fitted.result.params.lambda_surface:.3g}" in before
    assert re.search(r"pick \(0\.85, 0\.0, 0\.0\) f \S+ \|grad f\| \S+", proc.stdout)


# ---------------------------------------------------------------------------
# (c) picking


def test_pick_reports_f_and_gradient_norm(fitted):
    surface = fitted.refitter.surface
    p = np.array([0.85, 0.02, 0.01])
    f, g = fitted.on_pick(p)
    assert f == pytest.approx(float(surface.evaluate(p[None])[0]), rel=1e-12, abs=1e-15)
    assert g == pytest.approx(float(np.linalg.norm(surface.gradient(p[None])[0])), rel=1e-12)
    # Independent truth for |grad f|: central differences of f.
    h = 1e-5
    fd = [(surface.evaluate((p + h * e)[None])[0] - surface.evaluate((p - h * e)[None])[0]) / (2 * h) for e in np.eye(3)]
    assert g == pytest.approx(float(np.linalg.norm(fd)), rel=1e-4)
    text = fitted.pick_actor.GetInput()
    assert f"f = {f:.4g}" in text and f"norm(grad f) = {g:.4g}" in text
    with pytest.raises(ValueError, match="3-vector"):
        pick_values(surface, [0.0, np.nan, 0.0])


# ---------------------------------------------------------------------------
# sliders, jobs, saving, saved models


def test_sliders_refit_or_reextract(scan):
    data = load_view_input(str(scan / "scan.json"))
    app = ViewerApp.offscreen(data, PARAMS, window_size=(800, 400), poisson=False)
    try:
        first = app.fit_now()
        assert first.refit and first.mesh is not None
        assert first.params.delta is not None and first.params.tau is not None  # chosen by the fit, shown on the sliders
        assert app.sliders["delta"].GetRepresentation().GetValue() == pytest.approx(first.params.delta)
        # Resolution only: the same function, extracted again.
        assert app.set_slider("resolution", 16) is not None
        res = app.refitter.wait()
        app.show_result(res)
        assert not res.refit and res.surface is first.surface and len(res.mesh.triangles) < len(first.mesh.triangles)
        # Two requests while busy merge: the result has both, one refit.
        app.set_slider("delta", 2 * first.params.delta)
        app.set_slider("level", 0.0)  # unchanged: no job
        app.set_slider("tau", first.params.tau / 2)
        res = app.refitter.wait()
        assert res.refit and res.params.delta == pytest.approx(2 * first.params.delta) and res.params.tau == pytest.approx(first.params.tau / 2)
        assert res.params.lambda_surface == pytest.approx(first.params.lambda_surface)
        assert res.surface.kernel.params["delta"] == pytest.approx(2 * first.params.delta)
        with pytest.raises(ValueError, match="slider goes from"):
            app.set_slider("resolution", 5000)
        with pytest.raises(ValueError, match="unknown slider"):
            app.on_slider("sigma", 1.0)
    finally:
        app.close()


def test_failed_extraction_keeps_the_app_alive(fitted):
    rf = Refitter(fitted.data, fitted.refitter.params, surface=fitted.refitter.surface, constraints=fitted.refitter.constraints)
    try:
        rf.request(level=50.0)  # far above f's range: no surface
        res = rf.wait()
        assert res.mesh is None and "No surface found" in res.error and not res.refit
    finally:
        rf.close()


def test_save_mesh_and_never_over_the_input(fitted, tmp_path, monkeypatch):
    out = fitted.save_mesh(tmp_path / "m.ply")
    mesh = o3d.io.read_triangle_mesh(str(out))
    assert len(mesh.triangles) == len(fitted.result.mesh.triangles)
    monkeypatch.setattr(fitted.data, "source", str(out))  # as if m.ply were the input
    with pytest.raises(ValueError, match="is the input file"):
        fitted.save_mesh(out)
    png = tmp_path / "in.png"
    png.write_bytes(b"x")
    monkeypatch.setattr(fitted.data, "source", str(png))
    with pytest.raises(ValueError, match="is the input file"):
        fitted.save_screenshot(png)
    assert png.read_bytes() == b"x"


def test_saved_model_reextracts_but_does_not_refit(fitted, tmp_path, capsys):
    model = fitted.refitter.surface.save(tmp_path / "model.npz")
    out = tmp_path / "model.png"
    assert main(["view", str(model), "--screenshot", str(out), "--resolution", "20", "--window-size", "800", "400"]) == 0
    assert out.stat().st_size > 1000
    data = load_view_input(str(model))
    parts = model_constraints(data.model)
    counts = data.model.metadata["counts"]
    assert len(parts["surface"]) == counts["surface"] and len(parts["exterior"]) == counts["exterior"]
    # The split matches the kinds the fit itself recorded.
    for kind in ("surface", "exterior", "sphere"):
        assert np.allclose(parts[kind], fitted.refitter.constraints[kind], atol=1e-12), kind
    app = ViewerApp.offscreen(data, FitParams(resolution=20), window_size=(800, 400))
    try:
        assert not app.poisson_enabled
        app.fit_now()
        assert app.params.delta == pytest.approx(data.model.kernel.params["delta"])
        assert app.set_slider("delta", 30.0) is None  # fixed
        assert not app.refitter.busy
        with pytest.raises(ValueError, match="cannot be refitted"):
            app.refitter.request(tau=0.02)
        assert app.set_slider("resolution", 28) is not None
        res = app.refitter.wait()
        assert not res.refit and res.mesh is not None
    finally:
        app.close()


# ---------------------------------------------------------------------------
# geometry helpers


def test_frusta_corners_project_to_the_image_corners(scan):
    cams = load_view_input(str(scan / "scan.json")).cameras
    verts, lines, centers = camera_frusta(cams, depth=0.3)
    assert len(centers) == len(cams) and len(verts) == 5 * len(cams) and len(lines) == 8 * len(cams)
    for k, cam in enumerate(cams):
        assert np.allclose(verts[5 * k], cam.center)
        pix, depth = cam.project(verts[5 * k + 1 : 5 * k + 5])
        assert np.allclose(pix, [[0, 0], [cam.width, 0], [cam.width, cam.height], [0, cam.height]], atol=1e-9)
        assert np.allclose(depth, 0.3)
    assert np.allclose(view_up(cams), [0, 0, 1], atol=1e-9)  # camera_ring's up is z
    assert np.allclose(view_up(cams, "y"), [0, 1, 0])


def test_winding_follows_vertex_normals():
    sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, 10)
    v, t = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    t_in = t[:, ::-1]  # wound inward, normals outward
    fixed = wind_like_normals(v, t_in, v)
    geo = np.cross(v[fixed[:, 1]] - v[fixed[:, 0]], v[fixed[:, 2]] - v[fixed[:, 0]])
    assert np.all(np.einsum("ij,ij->i", geo, v[fixed].mean(axis=1)) > 0)
    assert np.array_equal(np.sort(fixed, axis=1), np.sort(t, axis=1))


# ---------------------------------------------------------------------------
# (d) bad input, help, headless import


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--screenshot", "{d}/out.jpg"], ".png"),
        (["--screenshot", "{d}/missing_dir/out.png"], "does not exist"),
        (["--cameras", "{d}/scan.json", "--screenshot", "{d}/o.png"], "already holds cameras"),
        (["--resolution", "1", "--screenshot", "{d}/o.png"], "resolution"),
        (["--poisson-depth", "20", "--screenshot", "{d}/o.png"], "poisson-depth"),
        (["--script", "jump 3"], "unknown script command"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(scan, capsys, extra, message):
    code = main(["view", str(scan / "scan.json"), *[a.format(d=scan) for a in extra]])
    err = capsys.readouterr().err
    assert code == 2 and message in err and err.count("\n") == 1, err


def test_bad_inputs_exit_2(scan, tmp_path, capsys, monkeypatch):
    assert main(["view", str(tmp_path / "nothing.ply"), "--screenshot", str(tmp_path / "o.png")]) == 2
    assert "not found" in capsys.readouterr().err
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a model")
    assert main(["view", str(junk), "--screenshot", str(tmp_path / "o.png")]) == 2
    assert "not an o3drbf model" in capsys.readouterr().err
    assert main(["view", str(junk), "--cameras", str(scan / "scan.json")]) == 2
    assert "saved model" in capsys.readouterr().err
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if sys.platform.startswith("linux"):
        assert main(["view", str(scan / "points.ply"), *SMALL]) == 2
        assert "--screenshot" in capsys.readouterr().err


def test_parse_script():
    assert parse_script("set level 0.1; wait;print; pick 1 2 3; key 1; quit") == [
        ("set", "level", 0.1), ("wait",), ("print",), ("pick", (1.0, 2.0, 3.0)), ("key", "1"), ("quit",)
    ]
    with pytest.raises(ValueError, match="unknown slider"):
        parse_script("set sigma 1")
    with pytest.raises(ValueError, match="takes 1"):
        parse_script("key")
    assert set(SLIDERS) == {"lambda_surface", "delta", "tau", "level", "resolution"}


def test_help_and_import_need_no_display_or_pyvista():
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-m", "o3drbf.cli", "view", "--help"], capture_output=True, text=True, env=env, timeout=60)
    assert proc.returncode == 0 and "--screenshot" in proc.stdout and "--script" not in proc.stdout
    code = "import sys, o3drbf, o3drbf.cli.commands; o3drbf.cli.commands.build_parser(); import o3drbf.viewers.app; print('pyvista' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == "False", proc.stderr


def test_sample_scan_for_the_readme_picture(tmp_path):
    from o3drbf.viewers.sample_scan import main as sample_main

    out = tmp_path / "tori.json"
    assert sample_main([str(out), "--views", "2"]) == 0
    data = load_view_input(str(out))
    assert len(data.cameras) == 2 and len(data.points) > 1000
    assert set(np.unique(data.point_camera)) == {0, 1}
    # Every point lies on one of the three tori.
    from o3drbf.synthetic.shapes import TorusStack

    assert np.abs(TorusStack(3).signed_distance(data.points)).max() < 0.05
    assert sample_main([str(tmp_path / "tori.txt")]) == 2
