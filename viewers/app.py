"""``o3drbf view``: the input points, the constraints, the cameras and the iso-surface, with sliders;
or a finished mesh as it is.

Three columns.  Controls: sliders for lambda (surface, log scale), delta,
tau, the iso-level and the grid resolution, each labelled "name = value"
above its tube, and check boxes for the layers (in the layers' colours, so
also the legend).  o3drbf: input points (light grey, 1 px, at most
``--max-points``, default 50,000: a seeded subsample, so dense scans do not
hide the surface), surface constraints (blue squares) and exterior
constraints (green squares), as in the paper's Fig. 8; the cameras as
frusta (orange); the iso-surface f = level.  Open3D Poisson (unless
``--no-poisson``): screened Poisson on the same points, with the same
points and cameras layers and the same camera (linked), so the panels
compare directly.

lambda/delta/tau refit, level/resolution only re-extract.  Jobs run on a
worker thread (:mod:`o3drbf.viewers.refit`), polled by a window timer, so the window
stays live and shows the progress.  The first fit chooses delta, tau and
lambda from the data (``--auto``, as ``o3drbf reconstruct``); the sliders then
show the values used.

Keys: 1-6 toggle layers (points, surface constraints, exterior constraints,
sphere constraints, cameras, iso-surface), m saves the mesh, k saves a
screenshot, p picks the surface point under the mouse and shows f and
|grad f| there, q quits.  VTK's own handlers for these keys (3: red/blue
stereo, p: a red pick box, m: animation) are switched off, as are its other
built-in keys except r (reset camera), w / s (wireframe / surface), f (fly
to) and q: see :mod:`o3drbf.viewers.keys`.

A mesh with faces (``o3drbf view mesh.ply``) is shown as it is, not
refitted (:mod:`o3drbf.viewers.meshview`; ``--color-by FIELD``,
``--distance-to OTHER``); ``--refit`` fits its vertices instead.

``--screenshot OUT.png`` renders the same scene offscreen (no display
needed) and exits.

The options (:class:`o3drbf.options.ViewOptions`) and their flags come from
the one table of :mod:`o3drbf.options`; :mod:`o3drbf.viewers.session` runs a
session from them (``o3drbf view``: :mod:`o3drbf.cli.view`).  PyVista is
imported inside functions only.
"""

from __future__ import annotations

import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from o3drbf.options import VIEW_LAYERS, VIEWER_DISPLAY, ViewOptions
from o3drbf.pictures import CONSTRAINT_COLORS, CONSTRAINT_POINT_SIZE
from o3drbf.viewers.geometry import camera_frusta, look_at, subsample, view_up, wind_like_normals
from o3drbf.viewers.keys import LayerToggles, own_keys, pick_under_mouse, press_key
from o3drbf.viewers.inputs import ViewInput, model_constraints
from o3drbf.viewers.refit import FitParams, FitResult, Refitter, pick_values

__all__ = ["ViewerApp", "COLORS", "LAYERS", "SLIDERS", "check_png"]

#: Layer colours (hex).  Surface constraints blue and exterior constraints
#: green, as in the paper's Fig. 8.
COLORS = {
    "points": VIEWER_DISPLAY["point_color"],
    **CONSTRAINT_COLORS,  # the same as Reconstruction.plot(constraints=True)
    "sphere": "#8fd19e",
    "cameras": "#e07b00",
    "mesh": "#e8dcc8",
    "poisson": "#c8d2e6",
    "pick": "#d62728",
    "background": "#ffffff",
    "controls": "#f2f2f2",
}

#: Toggleable layers: (key, name, label, shown at start).
LAYERS = (
    ("1", "points", "points", True),
    ("2", "surface", "surface constraints", True),
    ("3", "exterior", "exterior constraints", True),
    ("4", "sphere", "sphere constraints", False),
    ("5", "cameras", "cameras", True),
    ("6", "mesh", "iso-surface", True),
)
assert tuple(name for _, name, _, _ in LAYERS) == VIEW_LAYERS, "the options' VIEW_LAYERS name these layers"

#: Sliders: name -> (title, (low, high) in slider units, value format).
#: lambda_surface moves in log10 units; its label shows 10**position.  The
#: label ("title = value") is the viewer's own text above the slider, not
#: VTK's (whose value label sits above and title below, into the next slider).
SLIDERS = {
    "lambda_surface": ("lambda surface", (-6.0, 0.0), ".2g"),
    "delta": ("delta", (1.0, 60.0), ".3g"),
    "tau": ("tau", (0.001, 0.05), ".3g"),
    "level": ("iso-level", (-0.01, 0.01), ".2e"),  # range follows f's scale after each fit
    "resolution": ("grid resolution", (16.0, 256.0), ".0f"),
}
_REFIT_SLIDERS = ("lambda_surface", "delta", "tau")

_POLL_MS = 100


# ----------------------------------------------------------------------------
# the app


def check_png(path, inputs) -> Path:
    """A new ``.png`` output that overwrites none of ``inputs`` (:func:`o3drbf.io.files.check_output`)."""
    from o3drbf.io.files import check_output

    return check_output(path, inputs=inputs, formats=(".png",))


def _headless() -> None:
    from o3drbf.pictures import headless

    headless()


def _poly_from_mesh(mesh):
    """An Open3D mesh as PyVista PolyData, wound like its vertex normals, which it keeps (smooth shading)."""
    import pyvista as pv

    v = np.asarray(mesh.vertices)
    t = np.asarray(mesh.triangles)
    if mesh.has_vertex_normals():
        t = wind_like_normals(v, t, np.asarray(mesh.vertex_normals))
    poly = pv.PolyData(v, np.column_stack([np.full(len(t), 3), t]).ravel())
    if mesh.has_vertex_normals():
        poly.point_data["Normals"] = np.asarray(mesh.vertex_normals)
        poly.point_data.active_normals_name = "Normals"
    return poly


class ViewerApp(LayerToggles):
    """The viewer's scene and behaviour on a ``pyvista.Plotter``.

    Every user action is a plain method (slider callbacks, layer toggles,
    picking, saving), so tests and scripts call them directly.

    Parameters
    ----------
    data : ViewInput
    params : FitParams
        Starting slider values and fit options.
    plotter : pyvista.Plotter
        Laid out by :meth:`_layout`: a control column, the o3drbf panel
        and (when ``poisson``) the Poisson panel.
    options : ViewOptions, optional
        The display: ``poisson`` (a second panel with Open3D Poisson, off
        for a saved model: there are no points) and its ``poisson_depth``,
        ``save_prefix``, ``show_sphere``, ``hide``, ``up``, ``zoom`` and
        ``max_points`` (default :class:`~o3drbf.options.ViewOptions`; its
        fit is ``params``).
    script : list of steps, optional
        From :func:`o3drbf.viewers.session.parse_script`, run by the window timer.
    """

    def __init__(self, data: ViewInput, params: FitParams, plotter, options: ViewOptions | None = None, script=None):
        opts = options or ViewOptions()
        self.options = opts
        self.data = data
        self.plotter = plotter
        self.max_points = int(opts.max_points)
        subsample(1, self.max_points)  # refuses a cap below 1 before any work
        self.poisson_enabled = bool(opts.poisson) and not data.is_model
        self.poisson_depth = opts.poisson_depth
        self.save_prefix = opts.save_prefix
        self.script = list(script or [])
        self.exit_code = 0
        self.poisson_mesh = None
        self._poisson_future = None
        self._poisson_pool = None
        self.result: FitResult | None = None
        self.messages: list[str] = []
        self.visible = {name: shown for _, name, _, shown in LAYERS}
        self.visible["sphere"] = bool(opts.show_sphere)
        for name in opts.hide:
            if name not in self.visible:
                raise ValueError(f"unknown layer {name!r}; valid: {', '.join(self.visible)}")
            self.visible[name] = False
        self.actors: dict[str, object] = {}
        self.sliders: dict[str, object] = {}
        if data.is_model:
            params = replace(params, **data.model_params())
        self.params = params
        self.level_range: tuple[float, float] | None = None
        constraints = model_constraints(data.model) if data.is_model else None
        self.refitter = Refitter(data, params, surface=data.model, constraints=constraints)
        lo, hi = data.bounds()
        self.size = float(np.linalg.norm(hi - lo)) or 1.0
        self.up = view_up(data.cameras, opts.up)
        self.zoom = float(opts.zoom)
        self._building = True  # PyVista calls each slider's callback once as it adds it: not a user action
        self._build()
        self._building = False
        own_keys(plotter, self.key_bindings())
        plotter.enable_surface_point_picking(callback=lambda point: self._guard(self.on_pick, point), show_message=False, show_point=False, left_clicking=False)

    # -- construction -----------------------------------------------------------------

    @staticmethod
    def _layout(data, poisson: bool, window_size) -> dict:
        """Plotter arguments: a control column, the o3drbf panel, and the Poisson panel."""
        panels = 2 if poisson and not data.is_model else 1
        control = min(300.0, 0.2 * window_size[0])
        rest = (window_size[0] - control) / panels
        return dict(shape=(1, 1 + panels), col_weights=[control] + [rest] * panels, window_size=list(window_size))

    @classmethod
    def offscreen(cls, data, params, options: ViewOptions | None = None, script=None, **overrides) -> "ViewerApp":
        """An app on an offscreen plotter (EGL without a display); ``overrides``: flat names over ``options``
        (:meth:`o3drbf.options.ViewOptions.create`)."""
        _headless()
        import pyvista as pv

        opts = ViewOptions.create(options, **overrides)
        plotter = pv.Plotter(off_screen=True, border=False, **cls._layout(data, opts.poisson, opts.window_size))
        return cls(data, params, plotter, opts, script)

    @classmethod
    def interactive(cls, data, params, options: ViewOptions | None = None, script=None, **overrides) -> "ViewerApp":
        """An app on an on-screen plotter (needs a display); ``overrides`` as :meth:`offscreen`'s."""
        import pyvista as pv

        opts = ViewOptions.create(options, **overrides)
        plotter = pv.Plotter(border=True, title=f"o3drbf view: {Path(data.source).name}", **cls._layout(data, opts.poisson, opts.window_size))
        return cls(data, params, plotter, opts, script)

    #: Subplot columns: controls, o3drbf, Open3D Poisson.
    CONTROLS, MAIN, POISSON = 0, 1, 2

    @property
    def control_width(self) -> int:
        """Width of the control column in pixels."""
        w = self.plotter.window_size[0]
        return int(round(w * self.plotter.renderers[self.CONTROLS].GetViewport()[2]))

    def _renderer(self, col: int):
        return self.plotter.renderers[self.plotter.renderers.loc_to_index((0, col))]

    def _build(self) -> None:
        p = self.plotter
        d = self.data
        p.subplot(0, self.CONTROLS)
        p.set_background(COLORS["controls"], all_renderers=False)
        name = Path(d.source).name
        title = f"o3drbf view\n{name if len(name) <= 24 else name[:21] + '...'}" + ("\nsaved model: no refit" if d.is_model else "")
        self.title_actor = p.add_text(title, position=(0.04, 0.985), viewport=True, font_size=7, color="black", name="title")
        self.title_actor.GetTextProperty().SetVerticalJustificationToTop()  # more lines grow downward, not off the top
        p.subplot(0, self.MAIN)
        p.set_background(COLORS["background"], all_renderers=False)
        self._add_input_points(self.MAIN)
        self._add_cameras(self.MAIN)
        p.add_text("o3drbf", position=(0.02, 0.955), viewport=True, font_size=9, color="black", name="main_title")
        self.status_actor = p.add_text("", position=(0.2, 0.955), viewport=True, font_size=8, color="#b00000", name="status")
        self.pick_actor = p.add_text("", position=(0.02, 0.91), viewport=True, font_size=7, color=COLORS["pick"], name="pick")
        self.info_actor = p.add_text("", position=(0.02, 0.015), viewport=True, font_size=6, color="black", name="info")
        self._view_box()
        if self.poisson_enabled:
            p.subplot(0, self.POISSON)
            p.set_background(COLORS["background"], all_renderers=False)
            self._add_input_points(self.POISSON)  # the same layers in both panels: comparable
            self._add_cameras(self.POISSON)
            self.poisson_title = p.add_text(f"Open3D Poisson (depth {self.poisson_depth})", position=(0.02, 0.955), viewport=True, font_size=9, color="black", name="poisson_title")
            self._view_box()
            p.link_views(views=[self.plotter.renderers.loc_to_index((0, self.MAIN)), self.plotter.renderers.loc_to_index((0, self.POISSON))])
        self._add_sliders()
        self._add_buttons()
        p.subplot(0, self.MAIN)
        self._apply_visibility()

    def _view_box(self) -> None:
        """Look at the data from the side and above, the up axis up, the data filling most of the panel."""
        self.plotter.camera_position = look_at(self.data.bounds(), self.up, self.plotter.camera.view_angle, self.zoom)

    def shown(self, points) -> np.ndarray:
        """The drawn part of a point layer: at most ``max_points``, a seeded subsample (the same every time)."""
        pts = np.asarray(points)
        return pts[subsample(len(pts), self.max_points, seed=0)]

    def _add_input_points(self, col: int) -> None:
        """The input points (subsampled, light and small, so the surface stays visible) in one panel."""
        if self.data.points is None:
            return
        self.plotter.add_points(
            self.shown(self.data.points), color=COLORS["points"], point_size=VIEWER_DISPLAY["point_size"],
            render_points_as_spheres=False, lighting=False, name=f"points{col}", reset_camera=False, pickable=False,
        )
        self.actors.setdefault("points_names", []).append((col, f"points{col}"))

    def _frustum_depth(self) -> float:
        return 0.2 * self.size

    def _add_cameras(self, col: int) -> None:
        import pyvista as pv

        verts, lines, centers = camera_frusta(self.data.cameras, depth=self._frustum_depth())
        names = []
        if len(lines):
            poly = pv.PolyData(verts, lines=np.column_stack([np.full(len(lines), 2), lines]).ravel())
            self.plotter.add_mesh(poly, color=COLORS["cameras"], line_width=2, lighting=False, name=f"frusta{col}", reset_camera=False, pickable=False)
            names.append(f"frusta{col}")
        if len(centers):
            self.plotter.add_points(centers, color=COLORS["cameras"], point_size=8, render_points_as_spheres=False, lighting=False, name=f"centers{col}", reset_camera=False, pickable=False)
            names.append(f"centers{col}")
        self.actors.setdefault("cameras_names", []).extend((col, n) for n in names)

    #: Slider geometry in the control column (normalized viewport units):
    #: the tubes' heights, the label's offset above its tube, the caps' height.
    SLIDER_ROWS = (0.84, 0.40)
    SLIDER_LABEL_OFFSET = 0.03
    SLIDER_CAP = 0.03

    def _add_sliders(self) -> None:
        """The five sliders, stacked in the control column, each labelled "title = value" above its tube."""
        p = self.plotter
        p.subplot(0, self.CONTROLS)
        ys = np.linspace(*self.SLIDER_ROWS, len(SLIDERS))
        values = self._slider_values(self.params)
        for (name, (title, rng, fmt)), y in zip(SLIDERS.items(), ys):
            fixed = self.data.is_model and name in _REFIT_SLIDERS
            if name == "level":  # the range follows f's scale once fitted; keep the start value in it
                rng = (min(rng[0], values[name]), max(rng[1], values[name]))
            w = p.add_slider_widget(
                (lambda value, n=name: self.on_slider(n, value)),
                rng=list(rng),
                value=float(np.clip(values[name], *rng)),
                title="",
                pointa=(0.1, y),
                pointb=(0.9, y),
                color="#a8a8a8" if fixed else "#4a4a4a",
                interaction_event="end",
                slider_width=0.015,
                tube_width=0.004,
            )
            rep = w.GetRepresentation()
            rep.ShowSliderLabelOff()  # VTK's value label: replaced by the label above the tube
            rep.SetEndCapWidth(self.SLIDER_CAP)
            if fixed:
                w.ProcessEventsOff()
            self.sliders[name] = w
            self.actors[f"slider_label_{name}"] = p.add_text(
                "", position=(0.06, y + self.SLIDER_LABEL_OFFSET), viewport=True, font_size=6,
                color="#8a8a8a" if fixed else "black", name=f"slider_label_{name}",
            )
            w.AddObserver("InteractionEvent", lambda *_, n=name: self._label_slider(n))  # follows a drag
            self._label_slider(name)

    def slider_label(self, name: str) -> str:
        """The text above a slider: its title and the value at its position (lambda as 10**position)."""
        title, _, fmt = SLIDERS[name]
        pos = float(self.sliders[name].GetRepresentation().GetValue())
        value = 10.0**pos if name == "lambda_surface" else pos
        fixed = " (fixed: model)" if self.data.is_model and name in _REFIT_SLIDERS else ""
        return f"{title} = {format(value, fmt)}{fixed}"

    def _label_slider(self, name: str) -> None:
        self._set_text(self.actors[f"slider_label_{name}"], self.slider_label(name))

    def _add_buttons(self) -> None:
        """Check boxes (layers, in their colours: the legend) and two push buttons (save), in the control column."""
        p = self.plotter
        p.subplot(0, self.CONTROLS)
        rows = [(name, f"{key}  {label}", COLORS[name]) for key, name, label, _ in LAYERS if not (name == "points" and self.data.points is None)]
        rows += [("save", "m  save mesh", None), ("shot", "k  screenshot", None)]
        self.add_button_column(rows, self._button_save)

    def _button_save(self, what: str) -> None:
        self.actors[f"button_{what}"].GetRepresentation().SetState(0)  # a push button, not a toggle
        if what == "save":
            self.save_mesh()
        else:
            self.save_screenshot()

    @staticmethod
    def _slider_values(params: FitParams) -> dict[str, float]:
        """Slider positions for ``params`` (values still to be chosen by the fit show the paper's)."""
        from o3drbf.options import PAPER_VALUES

        lam = PAPER_VALUES["lambda_surface"] if params.lambda_surface is None else params.lambda_surface
        return {
            "lambda_surface": float(np.log10(lam)) if lam > 0 else SLIDERS["lambda_surface"][1][0],
            "delta": PAPER_VALUES["delta"] if params.delta is None else params.delta,
            "tau": PAPER_VALUES["tau"] if params.tau is None else params.tau,
            "level": params.level,
            "resolution": float(params.resolution),
        }

    # -- user actions (plain methods) -------------------------------------------------

    def on_slider(self, name: str, value: float) -> FitParams | None:
        """A slider moved to ``value`` (slider units): request the refit or re-extraction.

        Returns the parameters requested, or None when nothing changed (or
        the slider is fixed for a saved model).
        """
        if name not in SLIDERS:
            raise ValueError(f"unknown slider {name!r}; valid: {', '.join(SLIDERS)}")
        if self._building:
            return None
        value = float(value)
        if name == "lambda_surface":
            new = {"lambda_surface": float(10.0**value)}
        elif name == "resolution":
            new = {"resolution": int(round(value))}
        else:
            new = {name: value}
        target = self.refitter.target
        if all(getattr(target, k) is not None and np.isclose(getattr(target, k), v, rtol=1e-9, atol=0.0) for k, v in new.items()):
            return None  # also the call PyVista makes when it adds the slider
        if self.data.is_model and name in _REFIT_SLIDERS:
            self._say("a saved model cannot be refitted: lambda, delta and tau are fixed")
            return None
        params = self.refitter.request(**new)
        self._update_status()
        return params

    def set_slider(self, name: str, value: float) -> FitParams | None:
        """Move a slider to ``value`` given in the parameter's own units, as a user would."""
        if name not in SLIDERS:
            raise ValueError(f"unknown slider {name!r}; valid: {', '.join(SLIDERS)}")
        pos = float(np.log10(value)) if name == "lambda_surface" else float(value)
        lo, hi = self.level_range if name == "level" and self.level_range else SLIDERS[name][1]
        if not lo <= pos <= hi:
            raise ValueError(f"{name} slider goes from {lo:g} to {hi:g} ({'log10 ' if name == 'lambda_surface' else ''}units), got {pos:g}")
        widget = self.sliders[name]
        widget.GetRepresentation().SetValue(pos)
        self._label_slider(name)
        if not widget.GetProcessEvents():
            self._say(f"{name} is fixed for a saved model")
            return None
        return self.on_slider(name, pos)

    def key_bindings(self) -> dict:
        """Key -> action: the layer keys of :data:`LAYERS`, m save mesh, k screenshot, p pick."""
        keys = {k: (lambda n=name: self._guard(self.toggle_layer, n)) for k, name, _, _ in LAYERS}
        keys["m"] = lambda: self._guard(self.save_mesh)
        keys["k"] = lambda: self._guard(self.save_screenshot)
        keys["p"] = lambda: pick_under_mouse(self.plotter)
        return keys

    def on_key(self, key: str, position: tuple[int, int] | None = None) -> None:
        """Press a key as the window would (VTK events: only the viewer's action runs, see :mod:`o3drbf.viewers.keys`)."""
        if key not in self.key_bindings():
            raise ValueError(f"no action on key {key!r}; keys: {', '.join(self.key_bindings())}, q")
        press_key(self.plotter, key, position)

    def on_pick(self, point) -> tuple[float, float]:
        """Show (and return) f and |grad f| at a picked point (data coordinates)."""
        surface = self.refitter.surface
        if surface is None:
            self._set_text(self.pick_actor, "pick: no surface yet")
            return float("nan"), float("nan")
        f, g = pick_values(surface, point)
        p = np.asarray(point, dtype=float).reshape(3)
        self._set_text(self.pick_actor, f"picked ({p[0]:.4g}, {p[1]:.4g}, {p[2]:.4g}):  f = {f:.4g},  norm(grad f) = {g:.4g}")
        self.plotter.subplot(0, self.MAIN)
        self.plotter.add_points(p[None, :], color=COLORS["pick"], point_size=12, render_points_as_spheres=True, name="picked", reset_camera=False, pickable=False)
        self._render()
        return f, g

    def save_mesh(self, path: str | os.PathLike | None = None) -> Path | None:
        """Write the current iso-surface (default ``PREFIX_mesh.ply``); never over an input."""
        from o3drbf.io.files import check_output, write_mesh

        if self.result is None or self.result.mesh is None:
            self._say("no mesh to save yet")
            return None
        inputs = [self.data.source]
        out = check_output(path or f"{self.save_prefix}_mesh.ply", inputs=inputs)
        write_mesh(out, self.result.mesh, inputs=inputs)
        self._say(f"wrote {out}")
        return out

    def save_screenshot(self, path: str | os.PathLike | None = None) -> Path:
        """Write the window as a PNG (default ``PREFIX.png``), atomically."""
        from o3drbf.io.files import atomic_path

        out = check_png(str(path or f"{self.save_prefix}.png"), [self.data.source])
        self._render()
        with atomic_path(out) as tmp:
            self.plotter.screenshot(tmp)
        self._say(f"wrote {out}")
        return out

    # -- jobs ---------------------------------------------------------------------------

    def fit_now(self) -> FitResult | None:
        """Fit (or extract, for a model) and compute Poisson synchronously; show the results."""
        if self.result is None and not self.refitter.busy:
            self.refitter.start()
        res = self.refitter.wait()
        if res is not None:
            self.show_result(res)
        if self.poisson_enabled and self.poisson_mesh is None:
            self.show_poisson(self._compute_poisson())
        return res

    def start_jobs(self) -> None:
        """Start the first fit and Poisson on worker threads (interactive start)."""
        self.refitter.start()
        if self.poisson_enabled:
            from concurrent.futures import ThreadPoolExecutor

            self._poisson_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="o3drbf-poisson")
            self._poisson_future = self._poisson_pool.submit(self._compute_poisson)
        self._update_status()

    def _compute_poisson(self):
        from o3drbf.evaluation.peers import poisson

        normals = self.data.normals
        if normals is None:
            from o3drbf.evaluation.compare import open3d_normals

            normals = open3d_normals(self.data.points, self.data.cameras, self.data.point_camera)
        return poisson(self.data.points, normals, depth=self.poisson_depth)

    def poll(self) -> FitResult | None:
        """Take finished jobs' results into the scene (called by the window timer)."""
        res = self.refitter.poll()
        if res is not None:
            self.show_result(res)
        fut = self._poisson_future
        if fut is not None and fut.done():
            self._poisson_future = None
            try:
                self.show_poisson(fut.result())
            except Exception as exc:  # noqa: BLE001 - shown in the panel
                self._set_text(self.poisson_title, f"Open3D Poisson failed: {' '.join(str(exc).split())}")
        self._update_status()
        return res

    def show_result(self, res: FitResult) -> None:
        """Put a finished job's mesh and constraints into the left panel."""
        p = self.plotter
        p.subplot(0, self.MAIN)
        if res.mesh is not None or res.refit or self.result is None:
            self.result = res
        else:  # failed extraction: keep the function, show no mesh
            self.result = FitResult(res.params, res.surface, None, res.constraints, res.refit, res.seconds, res.error)
        self.params = res.params
        if res.mesh is not None and len(res.mesh.triangles):
            self.actors["mesh"] = p.add_mesh(_poly_from_mesh(res.mesh), color=COLORS["mesh"], smooth_shading=True, specular=0.3, name="mesh", reset_camera=False)
        else:
            p.remove_actor("mesh", render=False)
            self.actors.pop("mesh", None)
        for kind in ("surface", "exterior", "sphere"):
            pts = None if res.constraints is None else res.constraints.get(kind)
            if pts is not None and len(pts):
                self.actors[kind] = p.add_points(self.shown(pts), color=COLORS[kind], point_size=CONSTRAINT_POINT_SIZE, render_points_as_spheres=True, lighting=False, name=kind, reset_camera=False, pickable=False)
        if res.refit or self.level_range is None:
            self._fit_level_range(res)
            self._sync_sliders(res.params)
        if res.error:
            self._say(res.error)
        self._apply_visibility()
        self._set_text(self.info_actor, self.describe(multiline=True))
        self._render()

    def _sync_sliders(self, params: FitParams) -> None:
        """Show the values a fit used (e.g. chosen automatically) on the refit sliders."""
        values = self._slider_values(params)
        for name in _REFIT_SLIDERS:
            rep = self.sliders[name].GetRepresentation()
            v = values[name]
            if v < rep.GetMinimumValue():
                rep.SetMinimumValue(v)
            if v > rep.GetMaximumValue():
                rep.SetMaximumValue(v)
            rep.SetValue(v)
            self._label_slider(name)

    def _fit_level_range(self, res: FitResult) -> None:
        """Let the iso-level slider span twice f's typical value at the exterior constraints.

        f is 0 on the data and pulled toward -1 outside, but the smoothing of
        the exterior constraints shrinks its scale, often by orders of
        magnitude: a fixed range would be useless.
        """
        c = res.constraints or {}
        pts = c.get("exterior")
        if pts is None or not len(pts):
            pts = c.get("sphere")
        if pts is None or not len(pts) or res.surface is None:
            return
        scale = float(np.median(np.abs(res.surface.evaluate(np.asarray(pts)[:200]))))
        if not np.isfinite(scale) or scale <= 0:
            return
        level = res.params.level
        lo, hi = min(-2 * scale, level), max(2 * scale, level)
        self.level_range = (lo, hi)
        rep = self.sliders["level"].GetRepresentation()
        rep.SetMinimumValue(lo)
        rep.SetMaximumValue(hi)
        rep.SetValue(level)
        self._label_slider("level")

    def show_poisson(self, mesh) -> None:
        self.poisson_mesh = mesh
        p = self.plotter
        p.subplot(0, self.POISSON)
        p.add_mesh(_poly_from_mesh(mesh), color=COLORS["poisson"], smooth_shading=True, specular=0.3, name="poisson", reset_camera=False)
        self._set_text(self.poisson_title, f"Open3D Poisson (depth {self.poisson_depth}): {len(mesh.triangles):,} triangles")
        p.subplot(0, self.MAIN)
        self._render()

    def describe(self, multiline: bool = False) -> str:
        """The mesh and the parameters it was made with: one line (printed by scripts) or several (the panel)."""
        r = self.result
        if r is None:
            return "no mesh yet"
        q = r.params
        counts = {k: len(v) for k, v in (r.constraints or {}).items()}
        def num(v, fmt="g"):
            return "-" if v is None else format(v, fmt)

        parts = [
            f"mesh {len(r.mesh.triangles)} triangles, {len(r.mesh.vertices)} vertices" if r.mesh is not None else f"no mesh ({r.error})",
            f"level {q.level:g}, resolution {q.resolution}",
            f"lambda_surface {num(q.lambda_surface, '.3g')}, delta {num(q.delta)}, tau {num(q.tau)}",
            f"{counts.get('surface', 0)} surface, {counts.get('exterior', 0)} exterior constraints",
            f"{'refit' if r.refit else 'extract'} {r.seconds:.2f} s",
        ]
        if multiline:
            parts[0] = parts[0][:90]
            parts[2] = parts[2].replace(", delta", "\ndelta")
        return ("\n" if multiline else "; ").join(parts)

    # -- window --------------------------------------------------------------------------

    def _apply_visibility(self) -> None:
        for name in ("surface", "exterior", "sphere", "mesh"):
            actor = self._renderer(self.MAIN).actors.get(name)
            if actor is not None:
                actor.SetVisibility(bool(self.visible[name]))
        for layer in ("cameras", "points"):
            for col, name in self.actors.get(f"{layer}_names", []):
                actor = self._renderer(col).actors.get(name)
                if actor is not None:
                    actor.SetVisibility(bool(self.visible[layer]))

    def _set_text(self, actor, text: str) -> None:
        actor.SetInput(text)

    def _say(self, message: str) -> None:
        self.messages.append(message)
        self._set_text(self.status_actor, message)

    def _update_status(self) -> None:
        s = self.refitter.status()
        if self._poisson_future is not None:
            s = (s + "; " if s else "") + "Open3D Poisson ..."
        if s:
            self._set_text(self.status_actor, s)
        elif self.status_actor.GetInput() and self.status_actor.GetInput().endswith(" s"):
            self._set_text(self.status_actor, "")

    def _render(self) -> None:
        if getattr(self.plotter, "render_window", None) is not None:
            self.plotter.render()

    def _on_timer(self, *_):
        """Every 100 ms: take finished jobs in, show the progress, run the script; redraw only if needed."""
        try:
            busy = self.refitter.busy or self._poisson_future is not None
            changed = self.poll() is not None
            scripted = bool(self.script)
            self._run_script()
        except Exception as exc:  # noqa: BLE001 - never let a callback kill the event loop silently
            print(f"o3drbf view: error: {' '.join(str(exc).split())}", file=sys.stderr)
            self.exit_code = 1
            self.quit()
            return
        if busy or changed or scripted:
            self._render()

    def _run_script(self) -> None:
        while self.script:
            step = self.script[0]
            cmd = step[0]
            if cmd == "wait":
                if self.refitter.busy or self._poisson_future is not None or self.result is None:
                    return
            elif cmd == "set":
                self.set_slider(step[1], step[2])
            elif cmd == "print":
                print(f"o3drbf view: {self.describe()}", flush=True)
            elif cmd == "pick":
                f, g = self.on_pick(step[1])
                print(f"o3drbf view: pick {step[1]} f {f:.10g} |grad f| {g:.10g}", flush=True)
            elif cmd == "key":
                self.on_key(step[1])
            elif cmd == "quit":
                self.script = []
                self.quit()
                return
            self.script.pop(0)

    def quit(self) -> None:
        iren = self.plotter.iren
        if iren is not None:
            iren.terminate_app()

    def run(self) -> int:
        """Open the window, start the jobs and run the event loop until closed."""
        p = self.plotter
        self.start_jobs()
        p.iren.add_observer("TimerEvent", self._on_timer)
        p.show(interactive_update=True, auto_close=False)
        p.iren.create_timer(_POLL_MS, repeating=True)
        try:
            p.iren.start()
        finally:
            self.close()
        if self.script:
            print(f"o3drbf view: error: the window closed before the script finished ({len(self.script)} step(s) left)", file=sys.stderr)
            return 1
        return self.exit_code

    def _guard(self, fn, *args):
        try:
            return fn(*args)
        except (ValueError, OSError) as exc:
            self._say(" ".join(str(exc).split()))
            return None

    def close(self) -> None:
        """Stop the workers and close the window."""
        self.refitter.close()
        if self._poisson_pool is not None:
            self._poisson_pool.shutdown(wait=True, cancel_futures=True)
        self.plotter.close()
