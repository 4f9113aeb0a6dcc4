"""``o3drbf view MESH``: a finished mesh shown as it is, no refit.

A mesh file with faces (``o3drbf view mesh.ply``; see
:func:`o3drbf.viewers.inputs.has_faces`) opens here instead of being taken
as points and refitted (``--refit`` does that).  Its triangles, its vertex
normals (smooth shading, else flat) and its vertex colours are drawn as they
are.

``--color-by FIELD`` colours it by a per-vertex scalar field: any PLY vertex
property other than x, y, z, normals and colours (e.g. ``confidence``,
``distance``), or ``x``, ``y``, ``z``.  ``--distance-to OTHER`` colours it
by each vertex's distance to another mesh and shows OTHER beside it,
coloured by its distance to the mesh: the two panels share the camera and
the colour range, so they compare directly.

Keys: 1 mesh, 2 triangle edges, k screenshot, q quit (VTK's own keys are
switched off, see :mod:`o3drbf.viewers.keys`).
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from o3drbf.viewers.geometry import look_at, vertex_distances, view_up
from o3drbf.viewers.inputs import ViewInput
from o3drbf.viewers.keys import LayerToggles, own_keys, press_key

__all__ = ["MeshViewerApp", "MESH_LAYERS", "COORDINATE_FIELDS", "DISTANCE_FIELD", "color_fields"]

#: Toggleable layers of the mesh viewer: (key, name, label, shown at start).
MESH_LAYERS = (
    ("1", "mesh", "mesh", True),
    ("2", "edges", "triangle edges", False),
)

#: Fields every mesh has: its vertex coordinates.
COORDINATE_FIELDS = ("x", "y", "z")

#: The field ``--distance-to`` adds.
DISTANCE_FIELD = "distance"

_COLORS = {"mesh": "#e8dcc8", "edges": "#404040", "background": "#ffffff", "controls": "#f2f2f2", "nan": "#c8c8c8"}
_CMAP = "viridis"


def color_fields(data: ViewInput) -> dict[str, np.ndarray]:
    """Every field a mesh can be coloured by: its vertex properties and x, y, z."""
    v = data.mesh[0]
    out = {name: v[:, k] for k, name in enumerate(COORDINATE_FIELDS)}
    out.update(data.vertex_fields)
    return out


class MeshViewerApp(LayerToggles):
    """A finished mesh as it is, optionally coloured by a field or by its distance to another mesh.

    Parameters
    ----------
    data : ViewInput
        A mesh (``data.is_mesh``).
    plotter : pyvista.Plotter
        Laid out by :meth:`layout`: a control column and one panel (two
        with ``other``).
    color_by : str, optional
        A field of :func:`color_fields`; with ``other``, only
        :data:`DISTANCE_FIELD` (the default then).
    other : ViewInput, optional
        A second mesh: both are coloured by their distance to each other,
        side by side, same camera and same colour range.
    up : {"auto", "x", "y", "z"}
    zoom : float
    save_prefix : str
        Key k writes ``PREFIX.png``.
    hide : sequence of str
        Layers hidden at start (names in :data:`MESH_LAYERS`).
    """

    CONTROLS, MAIN, OTHER = 0, 1, 2

    def __init__(self, data: ViewInput, plotter, color_by: str | None = None, other: ViewInput | None = None, up: str = "auto", zoom: float = 1.0, save_prefix: str = "o3drbf_view", hide=()):
        if not data.is_mesh:
            raise ValueError(f"{data.source} is not a mesh with faces; MeshViewerApp shows meshes")
        if other is not None and not other.is_mesh:
            raise ValueError(f"--distance-to {other.source} is not a mesh with faces; give a mesh file (.ply, .obj, .stl, .off, .gltf)")
        self.plotter = plotter
        self.save_prefix = save_prefix
        self.messages: list[str] = []
        self.visible = {name: shown for _, name, _, shown in MESH_LAYERS}
        for name in hide:
            if name not in self.visible:
                raise ValueError(f"unknown layer {name!r} for a mesh; valid: {', '.join(self.visible)}")
            self.visible[name] = False
        if other is not None:
            if color_by not in (None, DISTANCE_FIELD):
                raise ValueError(f"--distance-to colours both meshes by their distance; drop --color-by {color_by} (or drop --distance-to)")
            color_by = DISTANCE_FIELD
            a, b = data.mesh, other.mesh
            data = replace(data, vertex_fields={**data.vertex_fields, DISTANCE_FIELD: vertex_distances(a[0], *b)})
            other = replace(other, vertex_fields={**other.vertex_fields, DISTANCE_FIELD: vertex_distances(b[0], *a)})
        self.data, self.other = data, other
        if color_by is not None and color_by not in color_fields(data):
            raise ValueError(f"{data.source} has no per-vertex field {color_by!r}; valid: {', '.join(color_fields(data))}")
        self.color_by = color_by
        self.clim = self._shared_range()
        lo, hi = data.bounds()
        if other is not None:
            lo2, hi2 = other.bounds()
            lo, hi = np.minimum(lo, lo2), np.maximum(hi, hi2)
        self.box = np.array([lo, hi])
        self.up = view_up(None, up)
        self.zoom = float(zoom)
        self.actors: dict[str, object] = {}
        self._build()
        own_keys(plotter, self.key_bindings())

    # -- construction -----------------------------------------------------------------

    @staticmethod
    def layout(two_panels: bool, window_size) -> dict:
        """Plotter arguments: a control column and one or two panels."""
        panels = 2 if two_panels else 1
        control = min(300.0, 0.2 * window_size[0])
        rest = (window_size[0] - control) / panels
        return dict(shape=(1, 1 + panels), col_weights=[control] + [rest] * panels, window_size=list(window_size))

    @classmethod
    def offscreen(cls, data, window_size=(1600, 800), other=None, **kw) -> "MeshViewerApp":
        """An app on an offscreen plotter (EGL without a display)."""
        from o3drbf.pictures import headless

        headless()
        import pyvista as pv

        plotter = pv.Plotter(off_screen=True, border=False, **cls.layout(other is not None, window_size))
        return cls(data, plotter, other=other, **kw)

    @classmethod
    def interactive(cls, data, window_size=(1600, 800), other=None, **kw) -> "MeshViewerApp":
        """An app on an on-screen plotter (needs a display)."""
        import pyvista as pv

        plotter = pv.Plotter(border=True, title=f"o3drbf view: {Path(data.source).name}", **cls.layout(other is not None, window_size))
        return cls(data, plotter, other=other, **kw)

    def panels(self) -> list[tuple[int, ViewInput]]:
        """(column, mesh) of each 3-D panel."""
        return [(self.MAIN, self.data)] + ([(self.OTHER, self.other)] if self.other is not None else [])

    def _shared_range(self) -> tuple[float, float] | None:
        """One colour range over every panel's values of ``color_by`` (finite values only)."""
        if self.color_by is None:
            return None
        values = np.concatenate([color_fields(d)[self.color_by] for _, d in self.panels()])
        values = values[np.isfinite(values)]
        if not len(values):
            raise ValueError(f"field {self.color_by!r} has no finite values; colour by another field")
        lo, hi = float(values.min()), float(values.max())
        return (lo, hi) if hi > lo else (lo - 0.5, lo + 0.5)

    def _renderer(self, col: int):
        return self.plotter.renderers[self.plotter.renderers.loc_to_index((0, col))]

    def _poly(self, d: ViewInput):
        import pyvista as pv

        v, t = d.mesh
        poly = pv.PolyData(v, np.column_stack([np.full(len(t), 3), t]).ravel())
        if d.vertex_normals is not None:
            poly.point_data["Normals"] = d.vertex_normals
            poly.point_data.active_normals_name = "Normals"
        return poly

    def _build(self) -> None:
        p = self.plotter
        p.subplot(0, self.CONTROLS)
        p.set_background(_COLORS["controls"], all_renderers=False)
        name = Path(self.data.source).name
        self.title_actor = p.add_text(f"o3drbf view\n{name if len(name) <= 24 else name[:21] + '...'}\nas it is, no refit", position=(0.04, 0.985), viewport=True, font_size=7, color="black", name="title")
        self.title_actor.GetTextProperty().SetVerticalJustificationToTop()
        self.info_actor = p.add_text(self.describe(multiline=True), position=(0.04, 0.36), viewport=True, font_size=6, color="black", name="info")
        self._add_buttons()
        for col, d in self.panels():
            p.subplot(0, col)
            p.set_background(_COLORS["background"], all_renderers=False)
            poly = self._poly(d)
            style = dict(smooth_shading=d.vertex_normals is not None, specular=0.3, name="mesh", reset_camera=False)
            if self.color_by is not None:
                poly.point_data[self.color_by] = color_fields(d)[self.color_by]
                self.actors[f"mesh{col}"] = p.add_mesh(
                    poly, scalars=self.color_by, clim=list(self.clim), cmap=_CMAP, nan_color=_COLORS["nan"],
                    show_scalar_bar=col == self.MAIN, scalar_bar_args=dict(title=self.color_by, n_labels=3, fmt="%.3g", color="black", vertical=False, position_x=0.25, position_y=0.03, width=0.5, height=0.08),
                    **style,
                )
            elif d.vertex_colors is not None:
                poly.point_data["RGB"] = np.clip(d.vertex_colors, 0.0, 1.0)
                self.actors[f"mesh{col}"] = p.add_mesh(poly, scalars="RGB", rgb=True, **style)
            else:
                self.actors[f"mesh{col}"] = p.add_mesh(poly, color=_COLORS["mesh"], **style)
            self.actors[f"edges{col}"] = p.add_mesh(poly, style="wireframe", color=_COLORS["edges"], line_width=1, lighting=False, name="edges", reset_camera=False, pickable=False, scalars=None)
            title = Path(d.source).name
            if self.other is not None:
                title += f": distance to {Path((self.other if col == self.MAIN else self.data).source).name}"
            elif self.color_by is not None:
                title += f", coloured by {self.color_by}"
            p.add_text(title, position=(0.02, 0.955), viewport=True, font_size=9, color="black", name="panel_title")
            p.camera_position = look_at(self.box, self.up, p.camera.view_angle, self.zoom)
        if self.other is not None:
            p.link_views(views=[self.plotter.renderers.loc_to_index((0, c)) for c, _ in self.panels()])
        p.subplot(0, self.MAIN)
        self._apply_visibility()

    def _add_buttons(self) -> None:
        """Check boxes for the layers and a push button for the screenshot, in the control column."""
        rows = [(name, f"{key}  {label}", _COLORS[name]) for key, name, label, _ in MESH_LAYERS] + [("shot", "k  screenshot", None)]
        self.add_button_column(rows, self._button_shot)

    def _button_shot(self, name: str) -> None:
        self.actors[f"button_{name}"].GetRepresentation().SetState(0)  # a push button
        self._guard(self.save_screenshot)

    # -- actions --------------------------------------------------------------------------

    def key_bindings(self) -> dict:
        """Key -> action: the layer keys of :data:`MESH_LAYERS`, k screenshot."""
        keys = {k: (lambda n=name: self._guard(self.toggle_layer, n)) for k, name, _, _ in MESH_LAYERS}
        keys["k"] = lambda: self._guard(self.save_screenshot)
        return keys

    def _apply_visibility(self) -> None:
        for col, _ in self.panels():
            for name in self.visible:
                actor = self.actors.get(f"{name}{col}")
                if actor is not None:
                    actor.SetVisibility(bool(self.visible[name]))

    def describe(self, multiline: bool = False) -> str:
        """What is shown: counts, the colouring and its range (one line, or short lines for the control column)."""
        v, t = self.data.mesh

        def name(d):
            n = Path(d.source).name
            return n if len(n) <= 24 else n[:21] + "..."

        lines = [f"{len(t):,} triangles", f"{len(v):,} vertices"]
        if self.color_by is not None:
            lo, hi = self.clim
            lines += [f"colour: {self.color_by}", f"  {lo:.4g} .. {hi:.4g}" + (" (both)" if self.other is not None else "")]
        elif self.data.vertex_colors is not None:
            lines.append("colour: vertex colours")
        if self.other is not None:
            for d, o in ((self.data, self.other), (self.other, self.data)):
                dist = d.vertex_fields[DISTANCE_FIELD]
                lines += [f"{name(d)} to {name(o)}:", f"  mean {dist.mean():.4g}, max {dist.max():.4g}"]
        if self.data.vertex_fields:
            lines += ["fields:"] + [f"  {k}" for k in self.data.vertex_fields]
        if multiline:
            return "\n".join(lines)
        one = [f"mesh {len(t)} triangles, {len(v)} vertices, shown as it is (no refit)"]
        if self.color_by is not None:
            lo, hi = self.clim
            one.append(f"colour {self.color_by} {lo:.4g} .. {hi:.4g}" + (" (both panels)" if self.other is not None else ""))
        if self.other is not None:
            for d, o in ((self.data, self.other), (self.other, self.data)):
                dist = d.vertex_fields[DISTANCE_FIELD]
                one.append(f"{Path(d.source).name} to {Path(o.source).name}: mean {dist.mean():.4g}, max {dist.max():.4g}")
        if self.data.vertex_fields:
            one.append("fields: " + ", ".join(self.data.vertex_fields))
        return "; ".join(one)

    def save_screenshot(self, path: str | os.PathLike | None = None) -> Path:
        """Write the window as a PNG (default ``PREFIX.png``), atomically; never over an input."""
        from o3drbf.io.files import atomic_path, check_output

        inputs = [d.source for _, d in self.panels()]
        out = check_output(str(path or f"{self.save_prefix}.png"), inputs=inputs, formats=(".png",))
        self._render()
        with atomic_path(out) as tmp:
            self.plotter.screenshot(tmp)
        self.messages.append(f"wrote {out}")
        return out

    def _guard(self, fn, *args):
        try:
            return fn(*args)
        except (ValueError, OSError) as exc:
            self.messages.append(" ".join(str(exc).split()))
            return None

    def _render(self) -> None:
        if getattr(self.plotter, "render_window", None) is not None:
            self.plotter.render()

    def run(self, script=None) -> int:
        """Open the window and run the event loop until closed.

        ``script``: steps from :func:`o3drbf.viewers.app.parse_script`; a
        mesh takes ``key K``, ``print``, ``wait`` (nothing to wait for) and
        ``quit``, run by a window timer.
        """
        import sys

        p = self.plotter
        steps = list(script or [])
        self.exit_code = 0

        def on_timer(*_):
            try:
                while steps:
                    cmd = steps.pop(0)
                    if cmd[0] == "key":
                        press_key(p, cmd[1])
                    elif cmd[0] == "print":
                        shown = ", ".join(k for k, v in self.visible.items() if v)
                        stereo = "on" if p.render_window.GetStereoRender() else "off"
                        print(f"o3drbf view: {self.describe()}; layers {shown}; stereo {stereo}", flush=True)
                    elif cmd[0] == "quit":
                        p.iren.terminate_app()
                        return
                    elif cmd[0] != "wait":
                        raise ValueError(f"script command {cmd[0]!r} does not apply to a mesh; valid: key, print, wait, quit")
            except Exception as exc:  # noqa: BLE001 - never let a callback kill the event loop silently
                print(f"o3drbf view: error: {' '.join(str(exc).split())}", file=sys.stderr)
                self.exit_code = 1
                p.iren.terminate_app()

        try:
            if steps:
                p.iren.add_observer("TimerEvent", on_timer)
            p.show(interactive_update=True, auto_close=False)
            if steps:
                p.iren.create_timer(100, repeating=True)
            p.iren.start()
        finally:
            self.close()
        if steps:
            print(f"o3drbf view: error: the window closed before the script finished ({len(steps)} step(s) left)", file=sys.stderr)
            return 1
        return self.exit_code

    def close(self) -> None:
        self.plotter.close()
