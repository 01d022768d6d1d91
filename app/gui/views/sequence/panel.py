"""Sequence view: its panel (the run, the scrubber and play, the per-frame chart, failed frames,
display options, the analyst's map points, the frame's control points and the export)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import viser.uplot as up

from app.gui.context import Client
from app.gui.security import escape_md
from app.gui.state import OVERLAYS
from app.gui.views.cptable.panel import ControlPointPanel
from app.gui.views.sequence.export_panel import ExportPanel
from app.gui.views.widgets import ClientCallback, on_any_change, on_change, on_choice, on_press

PLOT_TITLE = "Per-frame residual RMS (px): hover for values, click a frame to show it"
MAP_POINTS_NOTE = (
    "A point of this frame and where it lies on the map: one more constraint on the frame "
    "when the frames are adjusted together (Seed view, Run settings). *Add* then click the "
    "feature in the frame, then on the map; *Solve again* adjusts the frames it touches."
)


class MapPointsPanel:
    """Widgets of the Sequence view's "Map points" folder."""

    def __init__(self, gui) -> None:
        self.md = gui.add_markdown(MAP_POINTS_NOTE)
        self.status_md = gui.add_markdown("")
        self.btn_add = gui.add_button("Add a map point on this frame")
        self.btn_cancel = gui.add_button("Cancel the point", visible=False)
        self.btn_remove = gui.add_button("Remove this frame's map points")
        self.btn_solve = gui.add_button("Solve again")

    def on_actions(
        self,
        *,
        add: ClientCallback,
        cancel: ClientCallback,
        remove: ClientCallback,
        solve: ClientCallback,
    ) -> None:
        on_press(self.btn_add, add)
        on_press(self.btn_cancel, cancel)
        on_press(self.btn_remove, remove)
        on_press(self.btn_solve, solve)

    def show(self, text: str, picking: bool) -> None:
        self.status_md.content = text
        self.btn_cancel.visible = picking
        self.btn_add.visible = not picking


@dataclass(frozen=True)
class DisplayOptions:
    """How the frame under the scrubber is drawn over the map.

    Attributes:
        stage: ``"local"`` (with the displacement field) or ``"global"``.
        overlay: one of :data:`app.gui.state.OVERLAYS` (blend, checkerboard, flicker).
        opacity: of the frame in the blend, 0..1.
        vectors: draw the control points' residual vectors.
        outliers: include the vectors of points REQCON removed.
        vector_scale: vector length per base px of residual (0 = automatic).
        field: draw the local displacement field's magnitude (Fig. 5).
    """

    stage: str
    overlay: str
    opacity: float
    vectors: bool
    outliers: bool
    vector_scale: float
    field: bool


class SequencePanel:
    """Widgets of the Sequence view: typed values and callbacks for the view."""

    def __init__(self, gui) -> None:
        self.run_md = gui.add_markdown("")
        self.btn_run = gui.add_button("Register all frames")
        self.scrub = gui.add_slider("Frame", 0, 1, 1, 0)
        self.play = gui.add_checkbox("Play", False)
        self.frame_md = gui.add_markdown("")
        self.jump = gui.add_button_group("Jump to", ("worst frame", "next failed"))
        self.btn_rerun = gui.add_button("Register this frame again")
        self.plot = gui.add_uplot(
            data=(np.array([0.0, 1.0]),) + tuple(np.array([np.nan, np.nan]) for _ in range(6)),
            series=(
                up.Series(label="frame"),
                up.Series(
                    label="RMS (px)", stroke="#1c7ed6", width=2, points={"show": True, "size": 5}
                ),
                up.Series(
                    label="excursion",
                    stroke="#e03131",
                    width=0,
                    points={"show": True, "size": 9, "fill": "#e03131"},
                ),
                up.Series(
                    label="failed",
                    stroke="#868e96",
                    width=0,
                    points={"show": True, "size": 9, "fill": "#868e96"},
                ),
                up.Series(
                    label="shown",
                    stroke="#2b8a3e",
                    width=0,
                    points={"show": True, "size": 11, "fill": "#2b8a3e"},
                ),
                up.Series(
                    label="predicted error (px)",
                    stroke="#f08c00",
                    width=2,
                    dash=[6, 4],
                ),
                up.Series(
                    label="on the map",
                    stroke="#7048e8",
                    width=0,
                    points={"show": True, "size": 9, "fill": "#7048e8"},
                ),
            ),
            title=PLOT_TITLE,
            scales={
                "x": up.Scale(time=False, auto=False, range=(0.0, 1.0)),
                "y": up.Scale(auto=False, range=(0.0, 1.0)),
            },
            axes=(up.Axis(label="frame"), up.Axis(label="px")),
            cursor={"drag": {"x": False, "y": False}},
            aspect=1.7,
        )
        self._plot_ranges: tuple | None = None
        self.failed_html = gui.add_html("")
        with gui.add_folder("Display", expand_by_default=False):
            self.stage = gui.add_dropdown("Stage", ("local", "global"), initial_value="local")
            self.overlay = gui.add_dropdown("Overlay", OVERLAYS, initial_value=OVERLAYS[0])
            self.opacity = gui.add_slider("Opacity", 0.0, 1.0, 0.05, 0.5)
            self.show_vectors = gui.add_checkbox("Residual vectors", True)
            self.show_outliers = gui.add_checkbox("Vectors of points REQCON removed", False)
            self.vec_scale = gui.add_slider("Vector scale (0 = auto)", 0.0, 200.0, 1.0, 0.0)
            self.show_field = gui.add_checkbox("Displacement heat map (Fig. 5)", False)
            self.colourbar = gui.add_image(
                np.full((40, 320, 3), 255, np.uint8), label="|d| (base px)", visible=False
            )
        with gui.add_folder("Map points", expand_by_default=False):
            self.map_points = MapPointsPanel(gui)
        with gui.add_folder("Control points of this frame", expand_by_default=False):
            self.cps = ControlPointPanel(gui, editable=False, scope="seq")
        with gui.add_folder("Earlier results", expand_by_default=False):
            self.earlier_md = gui.add_markdown("No earlier results in this project.")
            self.earlier = gui.add_dropdown("Earlier result", ("–",), initial_value="–")
            self.btn_restore = gui.add_button("Restore this result")
        with gui.add_folder("Export", expand_by_default=False):
            self.export = ExportPanel(gui)

    # ---------------------------------------------------------------- callbacks
    def on_restore(self, callback: Callable[[str, Client], None]) -> None:
        """*Restore this result*, with the label of the earlier result chosen."""
        on_press(self.btn_restore, lambda client: callback(str(self.earlier.value), client))

    def show_earlier(self, labels: tuple[str, ...]) -> None:
        """The earlier results (newest first) in the dropdown; none: a note and no button."""
        self.earlier.options = labels or ("–",)
        self.earlier.value = (labels or ("–",))[0]
        self.earlier.visible = self.btn_restore.visible = bool(labels)
        self.earlier_md.content = (
            f"{len(labels)} earlier result(s), kept when a run had to start afresh; restoring one "
            "also restores the γ, seed, reference frame and preset it was made with."
            if labels
            else "No earlier results in this project."
        )

    def on_register_all(self, callback: ClientCallback) -> None:
        on_press(self.btn_run, callback)

    def on_frame_changed(self, callback: Callable[[int, Client], None]) -> None:
        on_change(self.scrub, int, callback)

    def on_jumps(self, *, worst: ClientCallback, next_failed: ClientCallback) -> None:
        on_choice(self.jump, {"worst frame": worst, "next failed": next_failed})

    def on_register_frame_again(self, callback: ClientCallback) -> None:
        on_press(self.btn_rerun, callback)

    def on_display_changed(self, callback: ClientCallback) -> None:
        on_any_change(
            (
                self.stage,
                self.overlay,
                self.opacity,
                self.show_vectors,
                self.show_outliers,
                self.vec_scale,
                self.show_field,
            ),
            callback,
        )

    # ---------------------------------------------------------------- values
    def configure(self, n_frames: int) -> None:
        self.scrub.max = max(n_frames - 1, 1)
        self.scrub.disabled = n_frames <= 1

    @property
    def frame(self) -> int:
        return int(self.scrub.value)

    @frame.setter
    def frame(self, k: int) -> None:
        self.scrub.value = int(k)

    @property
    def playing(self) -> bool:
        return bool(self.play.value)

    @property
    def flickering(self) -> bool:
        return self.overlay.value == "flicker"

    def display(self) -> DisplayOptions:
        return DisplayOptions(
            stage=str(self.stage.value),
            overlay=str(self.overlay.value),
            opacity=float(self.opacity.value),
            vectors=bool(self.show_vectors.value),
            outliers=bool(self.show_outliers.value),
            vector_scale=float(self.vec_scale.value),
            field=bool(self.show_field.value),
        )

    def show_display(
        self, *, opacity: float, vector_scale: float, overlay: str, stage: str
    ) -> None:
        """The saved display settings (an unknown overlay leaves the dropdown as it is)."""
        self.opacity.value = opacity
        self.vec_scale.value = vector_scale
        if overlay in OVERLAYS:
            self.overlay.value = overlay
        self.stage.value = stage

    # ---------------------------------------------------------------- texts and images
    def show_run(self, text: str) -> None:
        """The result's state and the run settings (markdown)."""
        self.run_md.content = text

    def show_frame_info(self, text: str) -> None:
        """The frame under the scrubber: status, statistics, stage times (markdown)."""
        self.frame_md.content = text

    def show_colourbar(self, image: np.ndarray | None) -> None:
        """The heat map's colour bar (None: hidden)."""
        if image is None:
            self.colourbar.visible = False
            return
        self.colourbar.image = image
        self.colourbar.visible = True

    def show_plot(self, values, flags, failed, current, predicted=None, marked=None) -> None:
        """The chart: RMS per frame, excursions and flagged frames, failed frames, the frame
        shown, each frame's predicted error where the frames were adjusted together, and the
        frames that carry evidence from the map (``marked``: the reference frame, re-anchored
        frames, frames with the analyst's map points; drawn at the chart's foot).

        uPlot's autoscale breaks on NaN (it has no NaN gaps, only nulls, which a numpy array
        cannot carry): both axes get explicit ranges, and NaN points are simply not drawn."""
        n = len(values)
        predicted = np.full(n, np.nan) if predicted is None else np.asarray(predicted, np.float64)
        both = np.concatenate([np.asarray(values, np.float64), predicted])
        finite = both[np.isfinite(both)]
        ymax = float(finite.max()) * 1.15 if len(finite) else 1.0
        ymax = max(ymax, 1e-3)
        ranges = (max(n - 1, 1), round(ymax, 6))
        if ranges != self._plot_ranges:
            self._plot_ranges = ranges
            self.plot.scales = {
                "x": up.Scale(time=False, auto=False, range=(0.0, float(ranges[0]))),
                "y": up.Scale(auto=False, range=(0.0, float(ranges[1]))),
            }
        x = np.arange(n, dtype=np.float64)
        shown = np.full(n, np.nan)
        if 0 <= current < n:
            shown[current] = values[current] if np.isfinite(values[current]) else 0.0
        exc = np.where(flags, values, np.nan)
        fail = np.where(failed, 0.0, np.nan)
        marks = np.zeros(n, bool) if marked is None else np.asarray(marked, bool)
        points = np.where(marks, 0.03 * ymax, np.nan)
        if n == 1:  # uPlot needs two x values
            x, values, exc, fail, shown, predicted, points = (
                np.append(v, np.nan) for v in (x, values, exc, fail, shown, predicted, points)
            )
            x[1] = 1.0
        self.plot.data = (x, np.asarray(values, np.float64), exc, fail, shown, predicted, points)

    def show_failed(self, failed: list[tuple[int, str]]) -> None:
        if not failed:
            self.failed_html.content = ""
            return
        rows = "".join(
            f'<tr data-row="{k}" onclick="window.aerialreg && window.aerialreg.send(\'seq-frame\', {k})">'
            f"<td>{k}</td><td style='text-align:left;white-space:normal'>{escape_md(reason)}</td></tr>"
            for k, reason in failed
        )
        self.failed_html.content = (
            f"<b>{len(failed)} failed frame(s)</b> (click to show)"
            '<div class="aerialreg-scroll"><table class="aerialreg-table">'
            f"<thead><tr><th>frame</th><th>reason</th></tr></thead><tbody>{rows}</tbody></table></div>"
        )
