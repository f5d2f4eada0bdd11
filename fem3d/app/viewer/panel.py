"""The viewer's panel: buttons, hotkeys, the scene and material menus, the material and
grab-radius sliders, the status line and the live energy plots (viser GUI elements).

The panel holds its elements; its callbacks call the :class:`~fem3d.app.viewer.app.Viewer`'s
public actions (which only queue commands), and the simulation thread writes the elements
(:meth:`Panel.update`, :meth:`Panel.show_scene`, :meth:`Panel.sync_E`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from fem3d.app.viewer.colour import FIELDS, NONE
from fem3d.app.viewer.logic import ENERGY_PLOTS, HOTKEYS, EnergyHistory, energy_text
from fem3d.app.viewer.plots import YAxis, y_axis

__all__ = ["Panel"]


class Panel:
    """The GUI elements of a viewer's panel.

    Parameters
    ----------
    viewer : fem3d.app.viewer.app.Viewer
        Whose actions the elements trigger.

    Attributes
    ----------
    widgets : dict
        The elements by name (empty until :meth:`build`).
    """

    def __init__(self, viewer: Any) -> None:
        self._viewer = viewer
        self.widgets: dict[str, Any] = {}
        #: The y axis each energy plot shows (:func:`~fem3d.app.viewer.plots.y_axis`).
        self.y_axes: dict[str, YAxis] = {}
        self._x_scale: dict[str, Any] = {}

    def build(
        self,
        gui: Any,
        *,
        scenes: list[str],
        scene_label: str,
        models: list[str],
        model: str,
        material: dict[str, float],
        radius_range: tuple[float, float, float],
        history: EnergyHistory,
        plot_window: float,
    ) -> None:
        """Add the elements to ``gui`` (a viser GUI API) and wire their callbacks."""
        v = self._viewer
        g: dict[str, Any] = {}
        g["status"] = gui.add_markdown("starting…")
        g["mesh"] = gui.add_button(f"Mesh: skinned ⇄ simulation ({HOTKEYS['mesh']})")
        g["integrator"] = gui.add_button("Integrator: next dynamic scheme (N)")
        g["pause"] = gui.add_button("Pause / resume (space)")
        g["reset"] = gui.add_button("Reset (R)")
        names = list(scenes)
        if scene_label not in names:
            names.append(scene_label)
        g["scene"] = gui.add_dropdown("Scene", tuple(names), initial_value=scene_label)
        models = list(models)
        if model not in models:
            models.append(model)
        g["material"] = gui.add_dropdown("Material", tuple(models), initial_value=model)
        E, nu, rho = material["E"], material["nu"], material["rho"]
        g["E_value"] = gui.add_number("Young's modulus E", initial_value=E, min=1e-12)
        g["E"] = gui.add_slider(
            "E (slider)", min=E / 10.0, max=E * 10.0, step=E / 10.0, initial_value=E
        )
        g["nu"] = gui.add_slider("Poisson's ratio", min=0.0, max=0.49, step=0.01, initial_value=nu)
        g["rho"] = gui.add_slider(
            "Density", min=rho / 10.0, max=rho * 10.0, step=rho / 10.0, initial_value=rho
        )
        lo, hi, r0 = radius_range
        g["radius"] = gui.add_slider(
            "Grab radius", min=lo, max=hi, step=(hi - lo) / 200.0, initial_value=r0
        )
        g["colour"] = gui.add_dropdown("Colour by", (NONE, *FIELDS), initial_value=NONE)
        g["legend"] = gui.add_markdown("")
        g["energy"] = gui.add_markdown("")
        x, *series = history.plot_series(plot_window)
        peaks, scene = history.peaks()
        self._x_scale = {"time": False, "auto": False, "range": [-plot_window, 0.0]}
        for (key, label, color), y, peak in zip(ENERGY_PLOTS, series, peaks, strict=True):
            ax = self.y_axes[key] = y_axis(y, peak, scene)
            g[f"plot_{key}"] = gui.add_uplot(
                data=(x, y),
                series=({"label": "t - now (s)"}, {"label": label, "stroke": color, "width": 2}),
                scales={"x": self._x_scale, "y": ax.scale()},
                axes=({}, ax.axis()),
                legend={"show": False},
                title=label,
                aspect=3.0,
            )
        g["mesh"].on_click(lambda _e: v.toggle_mesh_mode())
        g["integrator"].on_click(lambda _e: v.toggle_integrator())
        g["pause"].on_click(lambda _e: v._gui_toggle_pause())
        g["reset"].on_click(lambda _e: v.reset())
        self._wire_inputs(g)
        for label, key, action in (
            ("Toggle skinned / simulation mesh", HOTKEYS["mesh"], v.toggle_mesh_mode),
            ("Next integrator (linear, implicit, BDF2, Newmark)", HOTKEYS["integrator"],
             v.toggle_integrator),
            ("Pause / resume", HOTKEYS["pause"], v._gui_toggle_pause),
            ("Reset", HOTKEYS["reset"], v.reset),
        ):
            cmd = gui.add_command(label, hotkey=key)
            cmd.on_trigger(lambda _e, a=action: a())
        self.widgets = g

    def _wire_inputs(self, g: dict[str, Any]) -> None:
        """The menus' and sliders' callbacks (a change made by a page, not by the viewer)."""
        v = self._viewer

        def _on_scene(event: Any) -> None:
            if event.client is not None:
                v.switch_scene(str(event.target.value))

        def _on_E(event: Any) -> None:
            if event.client is not None:
                v.set_material(E=float(event.target.value))

        def _on_E_value(event: Any) -> None:
            if event.client is not None:
                value = float(event.target.value)
                if value > 0 and math.isfinite(value):
                    v.set_material(E=value)

        def _on_radius(event: Any) -> None:
            if event.client is not None:
                v.set_pick_radius(float(event.target.value))

        def _on_nu(event: Any) -> None:
            if event.client is not None:
                v.set_material(nu=float(event.target.value))

        def _on_rho(event: Any) -> None:
            if event.client is not None:
                v.set_material(rho=float(event.target.value))

        g["scene"].on_update(_on_scene)

        def _on_colour(event: Any) -> None:
            if event.client is not None:
                v.set_colour_field(str(event.target.value))

        g["colour"].on_update(_on_colour)

        def _on_material(event: Any) -> None:
            if event.client is not None:
                v.switch_material(str(event.target.value))

        g["material"].on_update(_on_material)
        g["E"].on_update(_on_E)
        g["E_value"].on_update(_on_E_value)
        g["radius"].on_update(_on_radius)
        g["nu"].on_update(_on_nu)
        g["rho"].on_update(_on_rho)

    def sync_E(self, E: float) -> None:
        """Show ``E`` in the number field and on the slider (re-centring the slider's range
        on a value typed outside it)."""
        g = self.widgets
        if abs(float(g["E_value"].value) - E) > 1e-9 * E:
            g["E_value"].value = E
        if not (g["E"].min <= E <= g["E"].max):
            g["E"].min, g["E"].max, g["E"].step = E / 10.0, E * 10.0, E / 10.0
        if abs(float(g["E"].value) - E) > 1e-9 * E:
            g["E"].value = E

    def show_scene(self, material: dict[str, float], model: str,
                   radius_range: tuple[float, float, float]) -> None:
        """The material and grab-radius elements of a newly loaded scene."""
        g = self.widgets
        E = material["E"]
        rho = material["rho"]
        g["E"].min, g["E"].max, g["E"].step = E / 10.0, E * 10.0, E / 10.0
        g["E"].value = E
        g["E_value"].value = E
        if model not in g["material"].options:
            g["material"].options = (*g["material"].options, model)
        g["material"].value = model
        lo, hi, r0 = radius_range
        g["radius"].min, g["radius"].max, g["radius"].step = lo, hi, (hi - lo) / 200.0
        g["radius"].value = r0
        g["nu"].value = material["nu"]
        g["rho"].min, g["rho"].max, g["rho"].step = rho / 10.0, rho * 10.0, rho / 10.0
        g["rho"].value = rho

    def show_legend(self, text: str) -> None:
        """The colour map's legend (empty: no colour map)."""
        legend = self.widgets.get("legend")
        if legend is not None and legend.content != text:
            legend.content = text

    def update(self, status: str, latest: Sequence[float] | None, x: np.ndarray,
               series: Sequence[np.ndarray], peaks: tuple[tuple[float, ...], float]) -> None:
        """The status line, the current energies and the energy plots.

        ``peaks`` is :meth:`~fem3d.app.viewer.plots.EnergyHistory.peaks`: each plot's y axis
        spans at least a small fraction of its history's and the scene's energy scale.
        """
        self.widgets["status"].content = status
        self.widgets["energy"].content = energy_text(latest)
        x32 = x.astype(np.float32)  # half the bytes; plenty for a plot
        own, scene = peaks
        for (key, _label, _color), y, peak in zip(ENERGY_PLOTS, series, own, strict=True):
            plot = self.widgets[f"plot_{key}"]
            ax = y_axis(y, peak, scene, self.y_axes.get(key))
            if ax is not self.y_axes.get(key):  # a new axis rebuilds the page's chart: rare
                self.y_axes[key] = ax
                plot.scales = {"x": self._x_scale, "y": ax.scale()}
                plot.axes = ({}, ax.axis())
            plot.data = (x32, y.astype(np.float32))
