"""A viewer session from options: the points fitted live (:class:`~o3drbf.viewers.app.ViewerApp`), or a finished
mesh as it is (:class:`~o3drbf.viewers.meshview.MeshViewerApp`); on screen, or one screenshot offscreen.

:func:`view` is ``o3drbf view`` from Python (:mod:`o3drbf.cli.view` parses
its flags into :class:`o3drbf.options.ViewOptions`); :func:`parse_script`
reads the scripted sessions tests and demos run.
"""

from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path

from o3drbf.options import ViewOptions
from o3drbf.viewers.app import SLIDERS, ViewerApp, check_png
from o3drbf.viewers.inputs import ViewInput, load_view_input
from o3drbf.viewers.refit import FitParams

__all__ = ["view", "parse_script"]

_SCRIPT_COMMANDS = {"set": 2, "wait": 0, "print": 0, "pick": 3, "key": 1, "quit": 0}


def parse_script(text: str) -> list[tuple]:
    """Steps of a scripted session: ``"set level 0.1; wait; print; pick 0 0 0; quit"``.

    Commands: ``set SLIDER VALUE`` (moves a slider and runs its callback;
    VALUE in the parameter's own units), ``wait`` (until every job is done),
    ``print`` (one line describing the mesh, on stdout), ``pick X Y Z``,
    ``key K`` (a key press delivered through VTK's events, as from the
    window), ``quit``.

    Examples
    --------
    >>> parse_script("set level 0.1; wait; quit")
    [('set', 'level', 0.1), ('wait',), ('quit',)]
    """
    steps = []
    for part in text.split(";"):
        words = shlex.split(part)
        if not words:
            continue
        cmd, rest = words[0], words[1:]
        if cmd not in _SCRIPT_COMMANDS:
            raise ValueError(f"unknown script command {cmd!r}; valid: {', '.join(_SCRIPT_COMMANDS)}")
        if len(rest) != _SCRIPT_COMMANDS[cmd]:
            raise ValueError(f"script command {cmd!r} takes {_SCRIPT_COMMANDS[cmd]} argument(s), got {rest}")
        if cmd == "set":
            if rest[0] not in SLIDERS:
                raise ValueError(f"script: unknown slider {rest[0]!r}; valid: {', '.join(SLIDERS)}")
            steps.append((cmd, rest[0], float(rest[1])))
        elif cmd == "pick":
            steps.append((cmd, tuple(float(v) for v in rest)))
        else:
            steps.append((cmd, *rest))
    return steps


def view(source, cameras=None, *, options: ViewOptions | None = None, screenshot=None, script: str | None = None, seed: int = 0,
         **overrides) -> int:
    """Show ``source`` in the viewer (``o3drbf view``); returns the exit status.

    Parameters
    ----------
    source : path-like
        Points, a file or folder with points and cameras, a saved model
        ``.npz``, or a mesh with faces (shown as it is unless ``refit``).
    cameras : path-like, optional
        Cameras for a plain point cloud.
    options : ViewOptions, optional
        The first fit (``options.fit``) and the display; default
        :class:`~o3drbf.options.ViewOptions`.
    screenshot : path-like, optional
        Render offscreen to this ``.png`` (no display needed) and return.
    script : str, optional
        A scripted session (:func:`parse_script`).
    seed : int
        Seed for sampling.
    **overrides
        Flat option names over ``options`` (:meth:`o3drbf.options.ViewOptions.create`):
        ``zoom``, ``level``, ``resolution``, ``delta``, ...

    Raises
    ------
    ValueError, FileNotFoundError, RuntimeError
        Bad options or inputs (checked before anything is drawn); no display without ``screenshot``.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> from o3drbf.io.files import write_points
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> _ = write_points(folder / "sphere.ply", *Sphere(1.0).sample(600, noise=0.002, seed=0))
    >>> view(folder / "sphere.ply", screenshot=folder / "view.png", poisson=False, resolution=20, surface_count=200,
    ...      window_size=(320, 240))  # doctest: +ELLIPSIS
    o3drbf view: mesh ... wrote .../view.png
    0
    >>> (folder / "view.png").stat().st_size > 0
    True
    """
    opts = ViewOptions.create(options, **overrides).validate()
    params = FitParams.from_options(opts, seed)
    steps = parse_script(script) if script else None
    shot = check_png(screenshot, [source, cameras]) if screenshot else None
    data = load_view_input(str(source), None if cameras is None else str(cameras), refit=opts.refit)
    if data.is_mesh:
        return _view_mesh(source, data, opts, shot, steps)
    for flag, value in (("--color-by", opts.color_by), ("--distance-to", opts.distance_to)):
        if value is not None:
            raise ValueError(f"{flag} needs a mesh with faces as INPUT; {source} is {'fitted (--refit)' if opts.refit else 'not a mesh'}")
    if _screenshot_only(shot, lambda: ViewerApp.offscreen(data, params, opts), lambda app: app.fit_now()):
        return 0
    return ViewerApp.interactive(data, params, opts, steps).run()


def _screenshot_only(shot: Path | None, make_offscreen, prepare=None) -> bool:
    """With a screenshot: render offscreen, write the picture, report; False when a window is wanted (and possible)."""
    if shot is not None:
        app = make_offscreen()
        try:
            if prepare is not None:
                prepare(app)
            app.save_screenshot(shot)
            print(f"o3drbf view: {app.describe()}; wrote {shot}")
        finally:
            app.close()
        return True
    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        raise RuntimeError("no display for the interactive viewer; use --screenshot OUT.png (offscreen) or run it under xvfb-run")
    return False


def _view_mesh(source, data: ViewInput, opts: ViewOptions, shot: Path | None, steps) -> int:
    """A mesh as it is (:mod:`o3drbf.viewers.meshview`)."""
    from o3drbf.viewers.inputs import has_faces, read_mesh_fields
    from o3drbf.viewers.meshview import MESH_LAYERS, MeshViewerApp

    other = None
    if opts.distance_to is not None:
        if not Path(opts.distance_to).is_file():
            raise FileNotFoundError(f"--distance-to: mesh not found: {opts.distance_to}")
        if not has_faces(opts.distance_to):
            raise ValueError(f"--distance-to {opts.distance_to} has no faces; give a mesh file (.ply, .obj, .stl, .off, .gltf)")
        other = read_mesh_fields(opts.distance_to)
    if shot is not None and other is not None:
        shot = check_png(str(shot), [source, opts.distance_to])
    hide = tuple(h for h in opts.hide if h in {name for _, name, _, _ in MESH_LAYERS})
    app_options = dict(color_by=opts.color_by, other=other, up=opts.up, zoom=opts.zoom, save_prefix=opts.save_prefix, hide=hide,
                       window_size=tuple(opts.window_size))
    if _screenshot_only(shot, lambda: MeshViewerApp.offscreen(data, **app_options)):
        return 0
    return MeshViewerApp.interactive(data, **app_options).run(steps)
