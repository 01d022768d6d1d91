"""Sequence view: its panel (widgets, the per-frame chart, failed frames) and its scene (the map
with the registered frame, outline, vectors, heat map); the view itself is ``app/views/sequence.py``."""

from __future__ import annotations

import numpy as np
import viser.uplot as up

from app.gui import scene2d
from app.gui.security import escape_md
from app.gui.state import OVERLAYS
from app.gui.views.base import Scene
from app.gui.views.cptable.panel import ControlPointPanel
from app.gui.views.sequence.export import ExportPanel
from registration import evaluation

RESIDUAL_OK = (255, 220, 0)
RESIDUAL_REMOVED = (240, 50, 50)
OUTLINE = (0, 200, 255)
SELECTED = (255, 255, 255)
FLICKER_S = 0.5
PLAY_S = 0.4
SETTLE_S = 0.35
"""After this long on one frame, it is drawn again at the map preview's full resolution."""
WARP_CACHE_FRAMES = 16
PLOT_TITLE = "Per-frame residual RMS (px): hover for values, click a frame to show it"


def excursion_flags(values: np.ndarray) -> np.ndarray:
    """Frames ``registration.evaluation.report.find_excursions`` flags as sudden excursions (bool (N,))."""
    flags = np.zeros(len(values), bool)
    finite = np.isfinite(values)
    if finite.sum() < 3:
        return flags
    idx = np.flatnonzero(finite)
    for e in evaluation.find_excursions(idx, values[finite]):
        flags[int(e["frame"])] = True
    return flags


class SequencePanel:
    """Widgets of the Sequence view."""

    def __init__(self, gui) -> None:
        self.run_md = gui.add_markdown("")
        self.btn_run = gui.add_button("Register all frames")
        self.scrub = gui.add_slider("Frame", 0, 1, 1, 0)
        self.play = gui.add_checkbox("Play", False)
        self.frame_md = gui.add_markdown("")
        self.jump = gui.add_button_group("Jump to", ("worst frame", "next failed"))
        self.btn_rerun = gui.add_button("Register this frame again")
        self.plot = gui.add_uplot(
            data=(np.array([0.0, 1.0]),) + tuple(np.array([np.nan, np.nan]) for _ in range(4)),
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
        with gui.add_folder("Control points of this frame", expand_by_default=False):
            self.cps = ControlPointPanel(gui, editable=False, scope="seq")
        with gui.add_folder("Export", expand_by_default=False):
            self.export = ExportPanel(gui)

    def show_plot(self, values, flags, failed, current) -> None:
        """The chart: RMS per frame, excursions, failed frames, the frame shown.

        uPlot's autoscale breaks on NaN (it has no NaN gaps, only nulls, which a numpy array
        cannot carry): both axes get explicit ranges, and NaN points are simply not drawn."""
        n = len(values)
        finite = np.asarray(values, np.float64)[np.isfinite(values)]
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
        if n == 1:  # uPlot needs two x values
            x, values, exc, fail, shown = (
                np.append(v, np.nan) for v in (x, values, exc, fail, shown)
            )
            x[1] = 1.0
        self.plot.data = (x, np.asarray(values, np.float64), exc, fail, shown)

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


class SequenceScene(Scene):
    """The map with the registered frame over its footprint, outline, vectors, heat map."""

    def __init__(self, scene, root_name: str) -> None:
        super().__init__(scene, root_name)
        self.field_handle = None
        self.base_shown = False

    def layout(self, base_size) -> None:
        self.make_plane("base", *base_size)
        self.base_shown = False

    def show_base(self, rgb) -> None:
        if not self.base_shown:
            self.planes["base"].show(rgb)
            self.base_shown = True

    def show_registered(self, patch, box, visible: bool = True) -> None:
        bp = self.planes["base"]
        if patch is None:
            bp.remove("registered")
            return
        bp.overlay_image("registered", patch, box=box)
        bp.set_visible("registered", visible)

    def set_registered_visible(self, visible: bool) -> None:
        self.planes["base"].set_visible("registered", visible)

    def draw_outline(self, border) -> None:
        bp = self.planes["base"]
        if border is None or len(border) < 2:
            bp.remove("outline")
            return
        s, e = scene2d.polyline_segments(border)
        bp.segments("outline", s, e, OUTLINE, width=2.0)

    def draw_vectors(self, vectors) -> None:
        bp = self.planes["base"]
        if vectors is None:
            bp.remove("residuals")
        else:
            bp.segments("residuals", *vectors, width=2.0)

    def draw_selected(self, xy) -> None:
        bp = self.planes["base"]
        if xy is None:
            bp.remove("selected")
        else:
            bp.markers("selected", [xy], SELECTED, shape="circle", size_px=12, width=2.5)

    def draw_field(self, rgba, extent) -> None:
        if self.field_handle is not None:
            self.field_handle.remove()
            self.field_handle = None
        if rgba is None:
            return
        x0, y0, x1, y1 = extent
        geom = self.planes["base"].geom
        s = geom.scale
        centre = geom.world_from_pixel(
            np.array([(x0 + x1) / 2.0, (y0 + y1) / 2.0]), dz=scene2d.OVERLAY_DZ * 0.75
        )
        big = np.repeat(np.repeat(rgba, 8, axis=0), 8, axis=1)  # crisp cells
        self.field_handle = self.scene.add_image(
            f"{self.root_name}/field",
            big,
            (x1 - x0) * s,
            (y1 - y0) * s,
            format="png",
            position=tuple(centre),
            cast_shadow=False,
            receive_shadow=False,
        )
