"""Calibrate view: its panel (the frame and γ widgets, the lines' table, the estimates and the
residual-versus-γ chart)."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import viser.uplot as up

from app.gui.assets import resend_value
from app.gui.context import Client
from app.gui.security import escape_md
from app.gui.views.widgets import ClientCallback, on_any_change, on_change, on_press, on_upload

GAMMA_STEP = 0.005
"""Step of the γ slider; the number box takes γ exactly."""


class CalibratePanel:
    """Widgets of the Calibrate view: typed properties and callbacks for the view."""

    def __init__(self, gui) -> None:
        self.frame_slider = gui.add_slider("Frame", 0, 1, 1, 0)
        self.gamma_slider = gui.add_slider("γ", -0.5, 1.0, GAMMA_STEP, 0.0)
        self.gamma_number = gui.add_number("γ (exact)", 0.0, min=-5.0, max=5.0, step=0.0001)
        self.grid_box = gui.add_checkbox("Straight reference lines (Fig. 2)", True)
        with gui.add_folder("Lines along streets"):
            self.lines_md = gui.add_markdown("Click points along a street that is straight.")
            self.btn_new = gui.add_button("New line")
            self.btn_finish = gui.add_button("Finish line")
            self.btn_undo = gui.add_button("Undo last point")
            self.btn_clear = gui.add_button("Clear lines", color="red")
            self.upload_lines = gui.add_upload_button("Import LINES.json", icon=None)
        with gui.add_folder("Estimate γ"):
            self.btn_est_lines = gui.add_button("Estimate γ from lines")
            self.btn_est_auto = gui.add_button("Estimate γ automatically")
            self.btn_est_motion = gui.add_button("Estimate γ from the frames' motion")
            self.show_detected = gui.add_checkbox("Show the lines the estimate used", True)
            self.estimate_md = gui.add_markdown("")
            self.btn_use_estimate = gui.add_button("Use the estimated γ", visible=False)
            self.plot = gui.add_uplot(
                data=(np.array([0.0, 1.0]), np.array([np.nan, np.nan]), np.array([np.nan, np.nan])),
                series=(
                    up.Series(label="γ"),
                    up.Series(label="residual (px)", stroke="#1c7ed6", width=2),
                    up.Series(
                        label="estimate",
                        stroke="#e03131",
                        width=0,
                        points={"show": True, "size": 9, "fill": "#e03131"},
                    ),
                ),
                title="Straightness residual vs γ",
                scales={"x": up.Scale(time=False, auto=True), "y": up.Scale(auto=True)},
                axes=(up.Axis(label="γ"), up.Axis(label="RMS off straight (raw px)")),
                aspect=1.5,
                visible=False,
            )
        self._quiet = threading.local()  # set while this thread assigns the γ widgets itself

    # ---------------------------------------------------------------- callbacks
    def on_frame_changed(self, callback: Callable[[int, Client], None]) -> None:
        on_change(self.frame_slider, int, callback)

    def on_gamma_changed(self, callback: Callable[[float, Client], None]) -> None:
        """``callback(γ, client)`` when the analyst moves the slider or types γ; not when
        :meth:`show_gamma` assigns them (the slider's rounded value must not replace the exact
        γ then)."""

        def changed(gamma: float, client: Client) -> None:
            if not getattr(self._quiet, "on", False):
                callback(gamma, client)

        on_change(self.gamma_slider, float, changed)
        on_change(self.gamma_number, float, changed)

    def on_overlays_changed(self, callback: ClientCallback) -> None:
        on_any_change((self.grid_box, self.show_detected), callback)

    def on_new_line(self, callback: ClientCallback) -> None:
        on_press(self.btn_new, callback)

    def on_finish_line(self, callback: ClientCallback) -> None:
        on_press(self.btn_finish, callback)

    def on_undo_point(self, callback: ClientCallback) -> None:
        on_press(self.btn_undo, callback)

    def on_clear_lines(self, callback: ClientCallback) -> None:
        on_press(self.btn_clear, callback)

    def on_estimate_from_lines(self, callback: ClientCallback) -> None:
        on_press(self.btn_est_lines, callback)

    def on_estimate_automatically(self, callback: ClientCallback) -> None:
        on_press(self.btn_est_auto, callback)

    def on_estimate_from_motion(self, callback: ClientCallback) -> None:
        on_press(self.btn_est_motion, callback)

    def on_import_lines(self, callback: Callable[[str, bytes, Client], None]) -> None:
        """``callback(file name, content, client)`` for an uploaded LINES.json."""
        on_upload(self.upload_lines, "LINES.json", callback)

    def on_use_estimate(self, callback: ClientCallback) -> None:
        on_press(self.btn_use_estimate, callback)

    # ---------------------------------------------------------------- values
    @property
    def frame(self) -> int:
        return int(self.frame_slider.value)

    @frame.setter
    def frame(self, k: int) -> None:
        self.frame_slider.value = int(k)

    @property
    def show_grid(self) -> bool:
        """Draw the straight reference lines (Fig. 2)."""
        return bool(self.grid_box.value)

    @property
    def show_lines_used(self) -> bool:
        """Draw the lines the automatic estimate used."""
        return bool(self.show_detected.value)

    def configure(self, n_frames: int, gamma_max: float) -> None:
        self.frame_slider.max = max(n_frames - 1, 1)
        self.frame_slider.disabled = n_frames <= 1
        self.gamma_slider.max = gamma_max
        self.gamma_number.max = gamma_max

    def show_gamma(self, gamma: float) -> None:
        """Both γ widgets show ``gamma`` (the slider rounded to its step)."""
        self._quiet.on = True
        try:
            slider = float(
                np.clip(
                    round(gamma / GAMMA_STEP) * GAMMA_STEP,
                    self.gamma_slider.min,
                    self.gamma_slider.max,
                )
            )
            if (
                abs(self.gamma_slider.value - gamma) > GAMMA_STEP / 2 + 1e-12
                and abs(self.gamma_slider.value - slider) > 1e-12
            ):
                self.gamma_slider.value = slider
            if abs(self.gamma_number.value - gamma) > 1e-9:
                self.gamma_number.value = round(float(gamma), 6)
        finally:
            self._quiet.on = False

    def resend_gamma(self) -> None:
        """Send the γ widgets' values to every tab, the one that typed γ included
        (:func:`app.gui.assets.resend_value` says why)."""
        resend_value(self.gamma_number)
        resend_value(self.gamma_slider)

    # ---------------------------------------------------------------- texts
    def show_lines(
        self, n: int, open_points: int | None, per_line, overall, error: str = ""
    ) -> None:
        """The lines' table: ``n`` lines, the open line's point count (None: no open line),
        each finished line's straightness and the overall one (px, or None), or ``error``."""
        text = [
            f"{n} line(s)."
            + (f" Open line: {open_points} point(s)." if open_points is not None else "")
        ]
        if error:
            text.append(f"Straightness unavailable: {escape_md(error)}")
        if per_line is not None:
            rows = "".join(f"\n| {i + 1} | {v:.2f} |" for i, v in enumerate(per_line))
            text.append("| line | RMS off straight (px) |\n|---|---|" + rows)
            text.append(f"Overall: **{overall:.2f} px** at this γ")
        text.append("Click on the image to add points; *Finish line* keeps lines with ≥ 3 points.")
        self.lines_md.content = "\n\n".join(text)

    def show_estimating(self, text: str) -> None:
        """What the running estimate does (until :meth:`show_estimate` replaces it)."""
        self.estimate_md.content = text

    def show_estimate(self, est, how: str, current: str = "", pending: bool = False) -> None:
        """A γ estimate (``registration.lens`` line or motion estimate) and its chart;
        ``current``: the γ in use (with its own uncertainty when it came from an estimate);
        ``pending``: the estimate is not in use yet (the *Use* button shows)."""
        self.btn_use_estimate.visible = pending
        head = (
            f"Estimate: γ = **{est.gamma:.4f}** ± {est.uncertainty:.4f} ({how}, "
            f"{est.uncertainty_method}); "
        )
        if est.method == "motion":
            self.estimate_md.content = head + escape_md(
                f"{est.n_inliers} matches in {est.n_pairs} frame pairs; transfer error "
                f"{est.residual:.2f} px (uncorrected {est.residual_uncorrected:.2f} px); "
                f"{'confident' if est.confident else 'NOT confident'}: {est.evidence}"
            )
        else:
            self.estimate_md.content = (
                head
                + f"{est.n_lines} lines used"
                + (f", {est.n_rejected} rejected as curved" if est.n_rejected else "")
                + f"; straightness {est.residual:.2f} px (uncorrected "
                f"{est.residual_uncorrected:.2f} px)"
            )
        if current:
            self.estimate_md.content += f"\n\nIn use: γ = {escape_md(current)}" + (
                ". *Use the estimated γ* to apply the estimate." if pending else "."
            )
        self._show_curve(est)

    def _show_curve(self, est) -> None:
        grid = np.asarray(est.gamma_grid, np.float64)
        curve = np.asarray(est.residual_curve, np.float64)
        ok = np.isfinite(curve)
        grid, curve = grid[ok], curve[ok]
        marker = np.full(len(grid), np.nan)
        if len(grid):
            i = int(np.argmin(np.abs(grid - est.gamma)))
            marker[i] = curve[i]
        # Explicit ranges: uPlot's autoscale breaks on the NaN that leave the marker series empty.
        lo, hi = (float(grid.min()), float(grid.max())) if len(grid) else (0.0, 1.0)
        ytop = float(np.nanmax(curve)) * 1.1 if len(curve) else 1.0
        self.plot.scales = {
            "x": up.Scale(time=False, auto=False, range=(lo, hi if hi > lo else lo + 1.0)),
            "y": up.Scale(auto=False, range=(0.0, max(ytop, 1e-3))),
        }
        self.plot.data = (grid, curve, marker)
        self.plot.visible = True
