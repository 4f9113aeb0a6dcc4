"""Key bindings that own their keys: VTK's built-in key handlers do not also run.

VTK's interactor style answers a few character keys itself
(``vtkInteractorStyle::OnChar``): ``3`` switches on red/blue stereo (the
window and every screenshot turn magenta), ``p`` picks and draws a red box
round the picked actor, ``m`` toggles animation, ``e`` quits, ``u`` calls a
user callback, ``j``/``t``/``c``/``a`` switch styles.  :func:`own_keys`
puts an observer on the style's character event, which replaces that
handler: only the keys in :data:`VTK_KEYS_KEPT` still reach VTK, and only
when the viewer does not bind them itself.

:func:`press_key` delivers a key press the way a window does (key press,
character, key release events on the interactor), so tests exercise the
real path offscreen.
"""

from __future__ import annotations

from typing import Callable

__all__ = ["VTK_KEYS_KEPT", "own_keys", "press_key", "pick_under_mouse", "LayerToggles"]

#: VTK's built-in character keys left working: r reset the camera,
#: w / s wireframe / surface, f fly to the point under the mouse, q quit.
VTK_KEYS_KEPT = ("r", "w", "s", "f", "q")


def own_keys(plotter, bindings: dict[str, Callable[[], object]]) -> None:
    """Bind ``bindings`` (key -> callback without arguments) and switch off VTK's other key handlers.

    Parameters
    ----------
    plotter : pyvista.Plotter
        With an interactor (on-screen, or offscreen: PyVista gives those a
        generic interactor).
    bindings : dict
        Single-character keys; each callback runs once per press.

    Raises
    ------
    ValueError
        A key that is not one character, or no interactor.
    """
    iren = getattr(plotter, "iren", None)
    if iren is None or iren.interactor is None:
        raise ValueError("own_keys needs a plotter with an interactor; create it with pyvista.Plotter()")
    for key in bindings:
        if len(key) != 1:
            raise ValueError(f"key bindings are single characters, got {key!r}")
    interactor = iren.interactor
    style = interactor.GetInteractorStyle()
    kept = tuple(k for k in VTK_KEYS_KEPT if k not in bindings)

    def on_char(_obj, _event) -> None:
        if interactor.GetKeyCode() in kept:
            style.OnChar()

    style.AddObserver("CharEvent", on_char)  # an observer replaces the style's OnChar
    for key, callback in bindings.items():
        plotter.add_key_event(key, callback)


def press_key(plotter, key: str, position: tuple[int, int] | None = None) -> None:
    """Deliver one key press to the plotter's interactor as a window would (key press, character, key release).

    Parameters
    ----------
    plotter : pyvista.Plotter
    key : str
        One character.
    position : (x, y) ints, optional
        The mouse position in pixels (origin bottom left), e.g. for ``p``.
    """
    if len(key) != 1:
        raise ValueError(f"press_key takes one character, got {key!r}")
    interactor = plotter.iren.interactor
    x, y = position if position is not None else interactor.GetEventPosition()
    interactor.SetEventInformation(int(x), int(y), 0, 0, key, 0, key)
    for event in ("KeyPressEvent", "CharEvent", "KeyReleaseEvent"):
        interactor.InvokeEvent(event)


def pick_under_mouse(plotter) -> None:
    """Run the interactor's picker at the mouse position (its observers get the point); no highlight box."""
    iren = plotter.iren
    x, y = iren.interactor.GetEventPosition()
    iren.interactor.GetPicker().Pick(x, y, 0, iren.get_poked_renderer(x, y))


class LayerToggles:
    """Show/hide named layers, kept in step with their check-box buttons.

    For a viewer with ``visible`` (layer name -> shown), ``actors`` (where a
    layer's button is ``"button_<name>"``), ``_apply_visibility()`` and
    ``_render()``.
    """

    def set_layer(self, name: str, shown: bool) -> None:
        """Show or hide one layer."""
        if name not in self.visible:
            raise ValueError(f"unknown layer {name!r}; valid: {', '.join(self.visible)}")
        self.visible[name] = bool(shown)
        button = self.actors.get(f"button_{name}")
        if button is not None:
            button.GetRepresentation().SetState(int(bool(shown)))
        self._apply_visibility()
        self._render()

    def toggle_layer(self, name: str) -> bool:
        """Flip one layer; returns whether it is now shown."""
        self.set_layer(name, not self.visible.get(name, False))
        return self.visible[name]

    def add_button_column(self, rows, on_push) -> None:
        """Check boxes (one per layer, in its colour: the legend) and push buttons, down the current subplot.

        ``rows``: (name, label, colour) per button; colour None makes a push
        button that calls ``on_push(name)``.  Needs ``self.plotter``.
        """
        p = self.plotter
        height = p.window_size[1]
        size = max(12, int(0.024 * height))
        step = size + max(4, int(0.01 * height))
        y = int(0.31 * height)
        for name, label, color in rows:
            if color is None:
                callback = (lambda state, n=name: on_push(n))
                value, color = False, "#777777"
            else:
                callback = (lambda state, n=name: self.set_layer(n, bool(state)))
                value = self.visible[name]
            self.actors[f"button_{name}"] = p.add_checkbox_button_widget(
                callback, value=value, position=(10, y), size=size, border_size=2,
                color_on=color, color_off="#ffffff", background_color="#a0a0a0",
            )
            p.add_text(label, position=(16 + size, y + 2), font_size=6, color="black", name=f"label_{name}")
            y -= step
