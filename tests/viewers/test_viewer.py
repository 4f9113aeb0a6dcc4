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

from o3drbf.viewers.app import COLORS, SLIDERS, ViewerApp  # noqa: E402
from o3drbf.viewers.session import parse_script  # noqa: E402
from o3drbf.viewers.geometry import camera_frusta, view_up, wind_like_normals  # noqa: E402
from o3drbf.viewers.inputs import load_view_input, model_constraints  # noqa: E402
from o3drbf.viewers.keys import press_key  # noqa: E402
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


#: What VTK prints when the X server xvfb-run started does not take the connection (seen on a loaded 2-core machine).
XVFB_NOT_READY = "bad X server connection"


def run_under_xvfb(xvfb, args, timeout, env, attempts=3):
    """``o3drbf <args>`` in a fresh Xvfb; started again (up to ``attempts`` times) only when the X server refused the connection."""
    for _ in range(attempts):
        proc = subprocess.run([xvfb, "-a", sys.executable, "-m", "o3drbf.cli", *args], capture_output=True, text=True, timeout=timeout, env=env)
        if proc.returncode == 0 or XVFB_NOT_READY not in proc.stderr:
            return proc
    return proc


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
    proc = run_under_xvfb(xvfb, ["view", str(scan / "scan.json"), *SMALL, "--script", script], timeout=150, env=env)
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


# ---------------------------------------------------------------------------
# keys: the viewer's keys do only the viewer's action (VTK's own handlers are off)


def _shot(plotter) -> np.ndarray:
    """The window as it is now (PyVista's screenshot renders only the first time)."""
    plotter.render()
    return plotter.screenshot()


def _magenta(image: np.ndarray) -> int:
    """Pixels of VTK's red/blue stereo tint (strong red and blue, no green)."""
    rgb = image[..., :3].astype(int)
    return int(((rgb[..., 0] > 150) & (rgb[..., 1] < 60) & (rgb[..., 2] > 150)).sum())


def _pure_red(image: np.ndarray) -> int:
    """Pixels of VTK's pick highlight box (1, 0, 0)."""
    rgb = image[..., :3].astype(int)
    return int(((rgb[..., 0] == 255) & (rgb[..., 1] == 0) & (rgb[..., 2] == 0)).sum())


def test_vtk_handles_3_and_p_itself_on_a_plain_plotter():
    """The control for the tests below: the simulated presses do reach VTK's own handlers."""
    plain = pv.Plotter(off_screen=True, window_size=(300, 200))
    try:
        plain.add_mesh(pv.Sphere(), color="white")
        plain.set_background("white")
        plain.iren.interactor.GetInteractorStyle().SetCurrentRenderer(plain.renderer)
        press_key(plain, "p", (150, 100))
        assert _pure_red(_shot(plain)) > 50  # VTK's red pick box
        press_key(plain, "3")
        assert plain.render_window.GetStereoRender() == 1
        assert _magenta(_shot(plain)) > 0.5 * 300 * 200  # the whole window tinted
    finally:
        plain.close()


def test_a_layer_key_toggles_only_its_layer(fitted):
    def shot():
        return _shot(fitted.plotter)

    before = dict(fitted.visible)
    camera = fitted.plotter.camera_position
    green = _colour_pixels(shot(), COLORS["exterior"], x_from=170)
    fitted.on_key("3")  # exterior constraints; VTK's own "3" would switch on red/blue stereo
    try:
        assert {k for k in before if before[k] != fitted.visible[k]} == {"exterior"}
        assert fitted.plotter.render_window.GetStereoRender() == 0
        image = shot()
        assert _magenta(image) == 0
        assert green > 20 and _colour_pixels(image, COLORS["exterior"], x_from=170) == 0
        assert fitted.plotter.camera_position == camera
    finally:
        fitted.on_key("3")
    assert fitted.visible == before
    with pytest.raises(ValueError, match="no action on key"):
        fitted.on_key("e")


def test_p_picks_without_vtk_highlight_box(fitted):
    ren = fitted.plotter.renderers[fitted.plotter.renderers.loc_to_index((0, fitted.MAIN))]
    verts = np.asarray(fitted.result.mesh.vertices)
    front = verts[np.argmin(np.linalg.norm(verts - np.array(fitted.plotter.camera.position), axis=1))]
    ren.SetWorldPoint(*front, 1.0)
    ren.WorldToDisplay()
    x, y, _ = ren.GetDisplayPoint()
    fitted.plotter.iren.interactor.GetInteractorStyle().SetCurrentRenderer(ren)  # as after a click: VTK's "p" would box
    fitted.on_key("p", (int(round(x)), int(round(y))))
    text = fitted.pick_actor.GetInput()
    picked = np.array([float(v) for v in re.search(r"picked \(([^)]*)\)", text).group(1).split(",")])
    assert np.linalg.norm(picked - front) < 0.05  # the surface point under the mouse
    assert _pure_red(_shot(fitted.plotter)) == 0


# ---------------------------------------------------------------------------
# readable controls: no text overlaps another text or a widget


def _control_boxes(app):
    """Pixel boxes (x0, y0, x1, y1) of every text in the control column, each rendered alone, and the widget pixels.

    Returns (boxes, widget_mask, width): the texts' boxes from screenshots
    with only that text shown, and where the sliders / buttons draw with
    no text shown.
    """
    from vtkmodules.vtkRenderingCore import vtkTextActor

    p = app.plotter
    ren = p.renderers[p.renderers.loc_to_index((0, app.CONTROLS))]
    width = int(round(p.window_size[0] * ren.GetViewport()[2]))
    props = [a for a in ren.GetViewProps()]
    texts = [a for a in props if isinstance(a, vtkTextActor) and a.GetVisibility() and (a.GetInput() or "").strip()]
    text_ids = {id(a) for a in texts}  # by identity: PyVista's Text compares by value
    others = [a for a in props if id(a) not in text_ids and a.GetVisibility()]
    background = np.array(ren.GetBackground()) * 255

    def drawn(image):
        rgb = image[:, :width, :3].astype(float)
        return np.abs(rgb - background).max(axis=2) > 8

    for a in texts:
        a.SetVisibility(0)
    widgets = drawn(_shot(p))
    for a in others:
        a.SetVisibility(0)
    boxes = {}
    for a in texts:
        a.SetVisibility(1)
        rows, cols = np.nonzero(drawn(_shot(p)))
        a.SetVisibility(0)
        boxes[a.GetInput()] = (cols.min(), rows.min(), cols.max(), rows.max())
    for a in texts + others:
        a.SetVisibility(1)
    return boxes, widgets, width


def _assert_readable(app):
    boxes, widgets, width = _control_boxes(app)
    items = list(boxes.items())
    for i, (text, (x0, y0, x1, y1)) in enumerate(items):
        assert 0 < x0 and x1 < width - 1 and 0 < y0 and y1 < widgets.shape[0] - 1, f"{text!r} runs off the control column"
        assert not widgets[y0 : y1 + 1, x0 : x1 + 1].any(), f"{text!r} overlaps a slider or button"
        for other, (u0, v0, u1, v1) in items[i + 1 :]:
            assert x1 < u0 or u1 < x0 or y1 < v0 or v1 < y0, f"{text!r} overlaps {other!r}"
    return boxes


def test_slider_labels_do_not_overlap(fitted):
    for w in fitted.sliders.values():  # all slider text is the viewer's own (VTK's label is off)
        rep = w.GetRepresentation()
        assert not rep.GetShowSliderLabel() and not (rep.GetTitleText() or "").strip()
    boxes = _assert_readable(fitted)
    labels = [fitted.slider_label(n) for n in SLIDERS]
    assert set(labels) <= set(boxes)
    # The labels show the values the fit used.
    assert f"delta = {fitted.result.params.delta:.3g}" in labels
    assert f"lambda surface = {fitted.result.params.lambda_surface:.2g}" in labels


# ---------------------------------------------------------------------------
# point layers: capped, deterministic, in both panels


def test_point_layers_are_capped_deterministically_in_both_panels(scan):
    from o3drbf.options import VIEWER_DISPLAY

    data = load_view_input(str(scan / "scan.json"))

    def drawn(app, col):
        p = app.plotter
        actor = p.renderers[p.renderers.loc_to_index((0, col))].actors[f"points{col}"]
        return np.asarray(pv.wrap(actor.GetMapper().GetInput()).points), actor

    runs = []
    for _ in range(2):
        app = ViewerApp.offscreen(data, PARAMS, window_size=(800, 400), max_points=200)
        try:
            main_pts, actor = drawn(app, app.MAIN)
            poisson_pts, _ = drawn(app, app.POISSON)
            assert actor.GetProperty().GetPointSize() == VIEWER_DISPLAY["point_size"]
            cams = [app.plotter.renderers[app.plotter.renderers.loc_to_index((0, c))].GetActiveCamera() for c in (app.MAIN, app.POISSON)]
            assert cams[0] is cams[1]  # o3drbf and Poisson: one camera
            runs.append(main_pts)
        finally:
            app.close()
        assert len(main_pts) == 200 and np.array_equal(main_pts, poisson_pts)
    assert np.array_equal(runs[0], runs[1])
    # Input points, all different, spread over the whole input (not its first rows).
    index = {tuple(p): i for i, p in enumerate(data.points)}
    rows = [index[tuple(p)] for p in runs[0]]
    assert len(set(rows)) == 200 and max(rows) > 800
    app = ViewerApp.offscreen(data, PARAMS, window_size=(800, 400))
    try:
        assert len(drawn(app, app.MAIN)[0]) == len(data.points)  # below the cap: every point
    finally:
        app.close()
    assert VIEWER_DISPLAY["max_points"] == 50_000


# ---------------------------------------------------------------------------
# a finished mesh: shown as it is


def _write_ply_with_field(path, vertices, triangles, name, values):
    """A binary PLY with faces and one extra float vertex property (written here, independently of any reader)."""
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\n"
        f"property double x\nproperty double y\nproperty double z\nproperty float {name}\n"
        f"element face {len(triangles)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    rec = np.zeros(len(vertices), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("f", "<f4")])
    rec["x"], rec["y"], rec["z"] = np.asarray(vertices).T
    rec["f"] = values
    faces = np.zeros(len(triangles), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, triangles
    path.write_bytes(header.encode() + rec.tobytes() + faces.tobytes())
    return path


@pytest.fixture(scope="module")
def sphere_ply(tmp_path_factory):
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.5, 12)
    v, t = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    path = _write_ply_with_field(tmp_path_factory.mktemp("mesh") / "sphere.ply", v, t, "confidence", v[:, 2] + 1.0)
    return path, v, t


def test_a_mesh_is_shown_as_it_is_coloured_by_a_field(sphere_ply, tmp_path, capsys, monkeypatch):
    from o3drbf.viewers.meshview import MeshViewerApp

    path, v, t = sphere_ply
    monkeypatch.setattr(ViewerApp, "__init__", lambda *a, **k: pytest.fail("a mesh must not go to the fitting viewer"))
    out = tmp_path / "mesh.png"
    assert main(["view", str(path), "--screenshot", str(out), "--color-by", "confidence", "--window-size", "800", "400"]) == 0
    line = capsys.readouterr().out
    assert f"mesh {len(t)} triangles, {len(v)} vertices, shown as it is (no refit)" in line
    assert "colour confidence 0.5 .. 1.5" in line  # z + 1 on a sphere of radius 0.5
    data = load_view_input(str(path))
    assert data.is_mesh and data.points is None
    app = MeshViewerApp.offscreen(data, window_size=(800, 400), color_by="confidence")
    try:
        poly = pv.wrap(app.actors["mesh1"].GetMapper().GetInput())
        assert np.allclose(np.asarray(poly.points), v) and poly.n_cells == len(t)
        assert np.allclose(np.asarray(poly.point_data["confidence"]), v[:, 2] + 1.0, atol=1e-6)
        assert app.actors["mesh1"].GetMapper().GetScalarRange() == pytest.approx((0.5, 1.5), abs=1e-6)
        # The picture: viridis runs from purple (low z) to yellow (high z), so the top of the sphere is redder than the bottom.
        image = _shot(app.plotter)[:, 170:, :3].astype(int)
        mesh_px = np.abs(image - 255).max(axis=2) > 30
        rows = np.nonzero(mesh_px.any(axis=1))[0]
        top, bottom = rows[: len(rows) // 4], rows[-len(rows) // 4 :]
        red_minus_blue = image[..., 0] - image[..., 2]
        assert red_minus_blue[top][mesh_px[top]].mean() > red_minus_blue[bottom][mesh_px[bottom]].mean() + 50
        _assert_readable(app)
        before = dict(app.visible)
        press_key(app.plotter, "2")  # edges; VTK's "2" does nothing, "3" would be stereo
        assert {k for k in before if before[k] != app.visible[k]} == {"edges"} and app.actors["edges1"].GetVisibility()
        press_key(app.plotter, "3")
        assert app.plotter.render_window.GetStereoRender() == 0
    finally:
        app.close()
    # --refit takes the vertices as points, the old behaviour.
    pts = load_view_input(str(path), refit=True)
    assert not pts.is_mesh and np.allclose(pts.points, v)


def test_mesh_options_are_checked(sphere_ply, scan, tmp_path, capsys):
    path, _, _ = sphere_ply
    png = str(tmp_path / "o.png")
    assert main(["view", str(path), "--screenshot", png, "--color-by", "sigma"]) == 2
    err = capsys.readouterr().err
    assert "no per-vertex field 'sigma'" in err and "confidence" in err and "x, y, z" in err
    assert main(["view", str(scan / "points.ply"), "--screenshot", png, "--color-by", "z"]) == 2
    assert "needs a mesh with faces" in capsys.readouterr().err
    assert main(["view", str(path), "--screenshot", png, "--distance-to", str(scan / "points.ply")]) == 2
    assert "has no faces" in capsys.readouterr().err
    assert main(["view", str(path), "--screenshot", png, "--distance-to", str(path), "--color-by", "confidence"]) == 2
    assert "drop --color-by" in capsys.readouterr().err


def test_distance_to_another_mesh_colours_both_panels_with_one_range(tmp_path):
    from o3drbf.viewers.meshview import MeshViewerApp

    sphere = o3d.geometry.TriangleMesh.create_sphere(0.5, 12)
    box = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 2.0).translate((-1.0, -1.0, -1.0)).subdivide_midpoint(3)
    o3d.io.write_triangle_mesh(str(tmp_path / "sphere.ply"), sphere)
    o3d.io.write_triangle_mesh(str(tmp_path / "box.ply"), box)
    app = MeshViewerApp.offscreen(load_view_input(str(tmp_path / "sphere.ply")), window_size=(800, 400), other=load_view_input(str(tmp_path / "box.ply")))
    try:
        a = np.asarray(sphere.vertices)
        b = np.asarray(box.vertices)
        d_ab = app.data.vertex_fields["distance"]
        d_ba = app.other.vertex_fields["distance"]
        # Truth: inside the box [-1, 1]^3 the nearest face is 1 - max|x_i| away.
        assert np.allclose(d_ab, 1.0 - np.abs(a).max(axis=1), atol=1e-6)
        # The sphere mesh is inscribed in the sphere of radius 0.5: |b| - 0.5 within its flatness.
        assert np.all(d_ba >= np.linalg.norm(b, axis=1) - 0.5 - 1e-6) and np.allclose(d_ba, np.linalg.norm(b, axis=1) - 0.5, atol=0.02)
        ranges = [app.actors[f"mesh{c}"].GetMapper().GetScalarRange() for c, _ in app.panels()]
        assert ranges[0] == ranges[1] == pytest.approx((min(d_ab.min(), d_ba.min()), max(d_ab.max(), d_ba.max())), rel=1e-6)
        p = app.plotter
        cams = [p.renderers[p.renderers.loc_to_index((0, c))].GetActiveCamera() for c, _ in app.panels()]
        assert cams[0] is cams[1]  # one camera: both panels move together
        _assert_readable(app)
    finally:
        app.close()


def test_dense_points_leave_the_surface_visible(tmp_path):
    """200k points on a sphere over the sphere's mesh: the default display (50k, light, 1 px) covers little of it."""
    from o3drbf.options import VIEWER_DISPLAY
    from o3drbf.pictures import to_pyvista
    from o3drbf.viewers.inputs import ViewInput

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(200_000, 3))
    pts = 0.5 * pts / np.linalg.norm(pts, axis=1, keepdims=True)
    data = ViewInput(source=str(tmp_path / "dense.ply"), points=pts, normals=2 * pts)
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.5, 60)
    sphere.compute_vertex_normals()

    def covered(**display):
        app = ViewerApp.offscreen(data, PARAMS, window_size=(1600, 800), poisson=False, **display)  # the default window
        try:
            p = app.plotter
            p.subplot(0, app.MAIN)
            p.add_mesh(to_pyvista(sphere), color=COLORS["mesh"], smooth_shading=True, name="mesh", reset_camera=False)
            points = p.renderers[p.renderers.loc_to_index((0, app.MAIN))].actors["points1"]
            points.SetVisibility(0)
            bare = _shot(p)[:, 320:, :3].astype(int)
            points.SetVisibility(1)
            drawn = _shot(p)[:, 320:, :3].astype(int)
        finally:
            app.close()
        surface = np.abs(bare - 255).max(axis=2) > 10
        return float((np.abs(drawn - bare).max(axis=2) > 10)[surface].mean())

    now = covered()
    before = covered(max_points=10**9)  # every point, as before the cap
    assert VIEWER_DISPLAY["point_size"] <= 1.0
    assert now < 0.35 and before > now + 0.2, (now, before)


def test_mesh_window_under_xvfb_keys_toggle_only_their_layer(sphere_ply):
    xvfb = shutil.which("xvfb-run")
    if xvfb is None:
        pytest.skip("xvfb-run is not installed (scripts/setup.sh installs it): cannot open a window here")
    path, v, t = sphere_ply
    env = dict(os.environ)
    for name in ("DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW"):
        env.pop(name, None)
    proc = run_under_xvfb(xvfb, ["view", str(path), "--window-size", "800", "400", "--script", "print; key 2; key 3; print; quit"],
                          timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("o3drbf view: mesh")]
    assert len(lines) == 2, proc.stdout
    assert f"mesh {len(t)} triangles" in lines[0] and "layers mesh; stereo off" in lines[0]
    assert "layers mesh, edges; stereo off" in lines[1]  # "2" showed the edges, "3" did nothing (VTK: stereo)
