"""Calibrate view: choose the Harris γ (paper section 3) by eye, from lines, or automatically.

Shows the radially corrected frame for the current γ (JPEG preview at display resolution while
the slider moves, full resolution once it settles), straight reference lines over it (the paper's
Fig. 2) and the analyst's polylines along streets, drawn as corrected for the current γ with
their straightness scores (``registration.calibration``). Lines are stored in raw pixels, so they
stay on the same street whatever γ is shown, and saved in the LINES.json format.
"""

from __future__ import annotations

import threading

import numpy as np

from app import scene2d
from app.view import View
from registration import calibration, distortion

LINE_COLOURS = np.array(
    [
        [255, 80, 80],
        [80, 200, 255],
        [120, 255, 120],
        [255, 160, 40],
        [220, 120, 255],
        [255, 255, 255],
    ],
    np.uint8,
)
OPEN_LINE_COLOUR = (255, 235, 0)
GRID_COLOUR = (0, 255, 255)
SETTLE_S = 0.35
"""After this long without a new γ/frame request, the full-resolution image replaces the preview."""


class CalibrateTab(View):
    MODE = "Calibrate"

    def build(self) -> None:
        import viser.uplot as up

        gui = self.gui
        self.frame_slider = gui.add_slider("Frame", 0, 1, 1, 0)
        self.gamma_slider = gui.add_slider("γ", -0.5, 1.0, 0.005, 0.0)
        self.gamma_number = gui.add_number("γ (exact)", 0.0, min=-5.0, max=5.0, step=0.0001)
        self.grid_box = gui.add_checkbox("Straight reference lines (Fig. 2)", True)
        with gui.add_folder("Lines along streets"):
            self.lines_md = gui.add_markdown(
                "Click points along a street that is straight on the ground."
            )
            self.btn_new = gui.add_button("New line")
            self.btn_finish = gui.add_button("Finish line")
            self.btn_undo = gui.add_button("Undo last point")
            self.btn_clear = gui.add_button("Clear lines", color="red")
        with gui.add_folder("Estimate γ"):
            self.btn_est_lines = gui.add_button("Estimate γ from lines")
            self.btn_est_auto = gui.add_button("Estimate γ automatically")
            self.estimate_md = gui.add_markdown("")
            self.plot = gui.add_uplot(
                data=(np.array([0.0, 1.0]), np.array([0.0, 0.0])),
                series=(
                    up.Series(label="γ"),
                    up.Series(label="residual (px)", stroke="blue", width=2),
                ),
                title="Straightness residual vs γ",
                scales={"x": up.Scale(time=False, auto=True), "y": up.Scale(auto=True)},
                aspect=1.6,
                visible=False,
            )
        self.frame_slider.on_update(lambda ev: self.set_frame(int(ev.target.value), ev.client))
        self._quiet = threading.local()  # set while this thread syncs the two γ widgets
        self.gamma_slider.on_update(lambda ev: self._gamma_widget(ev))
        self.gamma_number.on_update(lambda ev: self._gamma_widget(ev))
        self.grid_box.on_update(lambda ev: self.request_render())
        self.btn_new.on_click(lambda ev: self.new_line())
        self.btn_finish.on_click(lambda ev: self.finish_line())
        self.btn_undo.on_click(lambda ev: self.undo_point())
        self.btn_clear.on_click(lambda ev: self.clear_lines())
        self.btn_est_lines.on_click(lambda ev: self.estimate(auto=False, client=ev.client))
        self.btn_est_auto.on_click(lambda ev: self.estimate(auto=True, client=ev.client))
        self._settle_timer: threading.Timer | None = None
        self._timer_lock = threading.Lock()
        self._stopped = False
        self.labels: list = []

    # ---------------------------------------------------------------- state changes (callbacks)
    def on_inputs(self) -> None:
        inp = self.app.inputs
        w, h = inp.frame_size
        self.make_plane("frame", w, h)
        limit = distortion.harris_gamma_limit(w, h)
        self.gamma_max = float(np.floor((limit - 1e-3) * 1000) / 1000)
        with self.state.lock:
            k, g = self.state.calib_frame, self.state.gamma
        self.frame_slider.max = max(inp.n_frames - 1, 1)
        self.frame_slider.disabled = inp.n_frames <= 1
        self.frame_slider.value = k
        self.gamma_slider.max = self.gamma_max
        self.gamma_number.max = self.gamma_max
        self._sync_gamma_widgets(g)
        self._update_lines_md()

    def on_show(self) -> None:
        self.request_render()

    def set_frame(self, k: int, client=None) -> None:
        with self.state.lock:
            if self.app.inputs is None:
                return
            k = int(np.clip(k, 0, self.app.inputs.n_frames - 1))
            if k == self.state.calib_frame and self.app.shown.get(self.MODE):
                return
            self.state.calib_frame = k
            self.state.revision += 1
        self.app.save()
        self.request_render()

    def set_gamma(self, gamma: float, client=None) -> bool:
        """Validate and set γ (slider, number box, estimate); False (and a notification) if invalid."""
        inp = self.app.inputs
        if inp is None:
            return False
        try:
            if not np.isfinite(gamma):
                raise ValueError(f"γ must be a finite number, got {gamma}")
            distortion.check_valid(distortion.HarrisModel(float(gamma), *inp.frame_size))
        except ValueError as exc:
            self.notify(client, "Invalid γ", str(exc), color="red")
            with self.state.lock:
                self._sync_gamma_widgets(self.state.gamma)
            return False
        with self.state.lock:
            changed = gamma != self.state.gamma
            self.state.gamma = float(gamma)
            self.state.revision += 1
            # Under the lock: callbacks from two tabs run concurrently, and the widgets must end
            # showing the γ of whichever set the state last, not of whichever synced last.
            self._sync_gamma_widgets(gamma)
        if changed:
            self.app.save()
        self.request_render()
        return True

    def _gamma_widget(self, ev) -> None:
        # Assigning a widget's value from Python runs its callback synchronously in this thread;
        # when that assignment is our own sync (slider <-> number box), the slider's rounded value
        # must not overwrite the exact γ.
        if getattr(self._quiet, "on", False):
            return
        self.set_gamma(float(ev.target.value), ev.client)

    def _sync_gamma_widgets(self, gamma: float) -> None:
        self._quiet.on = True
        try:
            self._assign_gamma_widgets(gamma)
        finally:
            self._quiet.on = False

    def _assign_gamma_widgets(self, gamma: float) -> None:
        slider_value = float(
            np.clip(round(gamma / 0.005) * 0.005, self.gamma_slider.min, self.gamma_slider.max)
        )
        if (
            abs(self.gamma_slider.value - gamma) > 0.0025 + 1e-12
            and abs(self.gamma_slider.value - slider_value) > 1e-12
        ):
            self.gamma_slider.value = slider_value
        if abs(self.gamma_number.value - gamma) > 1e-9:
            self.gamma_number.value = round(float(gamma), 6)

    def on_click(self, plane: str, xy, client) -> None:
        """Add a point (given in corrected pixels of the shown image) to the open polyline."""
        inp = self.app.inputs
        with self.state.lock:
            model = distortion.HarrisModel(self.state.gamma, *inp.frame_size)
            raw = model.raw_from_corrected(np.asarray(xy, float)[None])[0]
            if not np.isfinite(raw).all():
                return
            if not self.state.line_open or not self.state.lines:
                self.state.lines.append([])
                self.state.line_open = True
            self.state.lines[-1].append((float(raw[0]), float(raw[1])))
            self.state.revision += 1
        self._lines_changed()

    def new_line(self) -> None:
        with self.state.lock:
            if self.state.line_open and self.state.lines and not self.state.lines[-1]:
                return
            self.state.lines.append([])
            self.state.line_open = True
        self._lines_changed()

    def finish_line(self) -> None:
        with self.state.lock:
            self.state.line_open = False
            # Lines need at least 3 points to say anything about curvature.
            self.state.lines = [ln for ln in self.state.lines if len(ln) >= 3]
        self._lines_changed()

    def undo_point(self) -> None:
        with self.state.lock:
            if self.state.lines and self.state.lines[-1]:
                self.state.lines[-1].pop()
                self.state.line_open = True
                if not self.state.lines[-1]:
                    self.state.lines.pop()
        self._lines_changed()

    def clear_lines(self) -> None:
        with self.state.lock:
            self.state.lines = []
            self.state.line_open = False
        self._lines_changed()

    def _lines_changed(self) -> None:
        self.app.save()
        self.save_lines_file()
        self._update_lines_md()
        self.app.worker.submit("calibrate-overlays", self.draw_overlays)

    def save_lines_file(self) -> None:
        """Write LINES.json (registration.calibration's format) for the finished lines."""
        inp = self.app.inputs
        with self.state.lock:
            lines = [np.asarray(ln, float) for ln in self.state.lines if len(ln) >= 3]
        if inp is None:
            return
        import json

        obj = calibration.lines_to_json(lines, inp.frame_size) if lines else None
        if obj is None:
            self.app.project.lines_path.unlink(missing_ok=True)
            return
        self.app.project.write_file("LINES.json", json.dumps(obj) + "\n")

    def scores(self) -> tuple[list[float], float] | None:
        """Straightness (px) of each finished line at the current γ, and overall; None if n/a."""
        inp = self.app.inputs
        with self.state.lock:
            lines = [np.asarray(ln, float) for ln in self.state.lines if len(ln) >= 3]
            g = self.state.gamma
        if inp is None or not lines:
            return None
        s = calibration.straightness(lines, distortion.HarrisModel(g, *inp.frame_size))
        return [float(v) for v in s.per_line], float(s.overall)

    def _update_lines_md(self) -> None:
        with self.state.lock:
            n = len(self.state.lines)
            open_pts = (
                len(self.state.lines[-1]) if self.state.line_open and self.state.lines else None
            )
        text = [
            f"{n} line(s)." + (f" Open line: {open_pts} point(s)." if open_pts is not None else "")
        ]
        try:
            sc = self.scores()
        except ValueError as exc:
            sc = None
            text.append(f"Straightness unavailable: {exc}")
        if sc is not None:
            per, overall = sc
            text.append("| line | RMS off straight (px) |\n|---|---|")
            text[-1] += "".join(f"\n| {i + 1} | {v:.2f} |" for i, v in enumerate(per))
            text.append(f"Overall: **{overall:.2f} px**")
        text.append("Click on the image to add points; *Finish line* keeps lines with ≥ 3 points.")
        self.lines_md.content = "\n\n".join(text)

    # ---------------------------------------------------------------- estimation (job thread)
    def estimate(self, *, auto: bool, client=None) -> None:
        inp = self.app.inputs
        if inp is None:
            return
        with self.state.lock:
            lines = [np.asarray(ln, float) for ln in self.state.lines if len(ln) >= 3]
            k = self.state.calib_frame
        if not auto and not lines:
            self.notify(client, "No lines", "Draw at least one line of ≥ 3 points first", "yellow")
            return

        def job(cancel) -> None:
            self.estimate_md.content = "Estimating γ ..."
            if auto:
                est = calibration.estimate_gamma_auto(inp.frame(k))
            else:
                est = calibration.estimate_gamma_from_lines(lines, *inp.frame_size)
            self.show_estimate(est, auto)
            self.set_gamma(float(est.gamma), client)

        if not self.app.jobs.start("estimate γ", job):
            self.notify(client, "Busy", f"{self.app.jobs.name} is running", "yellow")

    def show_estimate(self, est, auto: bool) -> None:
        how = "automatically" if auto else "from lines"
        text = (
            f"γ = **{est.gamma:.4f}** ± {est.uncertainty:.4f} ({how}, {est.uncertainty_method}); "
            f"{est.n_lines} lines used"
            + (f", {est.n_rejected} rejected as curved" if est.n_rejected else "")
            + f"; straightness {est.residual:.2f} px (uncorrected {est.residual_uncorrected:.2f} px)"
        )
        self.estimate_md.content = text
        ok = np.isfinite(est.residual_curve)
        data = (
            np.asarray(est.gamma_grid, np.float64)[ok],
            np.asarray(est.residual_curve, np.float64)[ok],
        )
        self.last_estimate = est
        self.plot.data = data
        self.plot.visible = True

    def shutdown(self) -> None:
        with self._timer_lock:
            if self._settle_timer is not None:
                self._settle_timer.cancel()
            self._stopped = True

    # ---------------------------------------------------------------- drawing (worker thread)
    def request_render(self) -> None:
        self.app.worker.submit("calibrate", lambda: self.render(full=False))
        with self._timer_lock:
            if self._settle_timer is not None:
                self._settle_timer.cancel()
            if self._stopped:
                return
            with self.state.lock:
                rev = self.state.revision
            self._settle_timer = threading.Timer(
                SETTLE_S,
                lambda: self.app.worker.submit(
                    "calibrate", lambda: self.render(full=True, rev=rev)
                ),
            )
            self._settle_timer.daemon = True
            self._settle_timer.start()

    def corrected_image(self, k: int, gamma: float, max_side: int | None) -> np.ndarray:
        """Corrected frame ``k`` (RGB) at full size or with its longer side ≤ ``max_side``."""
        img = self.app.inputs.frame(k) if max_side is None else self.app.inputs.preview(k, max_side)
        h, w = img.shape[:2]
        corrected, _ = distortion.undistort_image(
            img, distortion.HarrisModel(gamma, w, h), canvas="same"
        )
        return scene2d.to_rgb(corrected)

    def render(self, *, full: bool, rev: int | None = None) -> None:
        inp = self.app.inputs
        if inp is None or "frame" not in self.image_planes:
            return
        with self.state.lock:
            k, g, cur = self.state.calib_frame, self.state.gamma, self.state.revision
        if rev is not None and rev != cur:
            return  # a newer request superseded this settle render
        if full and max(inp.frame_size) <= self.app.display_max:
            last = self.app.shown.get(self.MODE)
            if last and last[:2] == (k, g):
                return  # the preview was already full resolution
        rgb = self.corrected_image(k, g, None if full else self.app.display_max)
        with self.app.server.atomic():
            self.image_planes["frame"].show(rgb)
            self._draw_overlays(g)
        self.app.shown[self.MODE] = (k, g, rgb.shape[1], rgb.shape[0])

    def draw_overlays(self) -> None:
        with self.state.lock:
            g = self.state.gamma
        with self.app.server.atomic():
            self._draw_overlays(g)
        self._update_lines_md()

    def _draw_overlays(self, gamma: float) -> None:
        plane = self.image_planes["frame"]
        inp = self.app.inputs
        w, h = inp.frame_size
        # The reference lines are straight on screen whatever γ is: draw them once.
        if self.grid_box.value and not plane.has("grid"):
            a, b = [], []
            for x in np.linspace(0, w - 1, 9)[1:-1]:
                a.append((x, 0))
                b.append((x, h - 1))
            for y in np.linspace(0, h - 1, 7)[1:-1]:
                a.append((0, y))
                b.append((w - 1, y))
            plane.segments("grid", a, b, GRID_COLOUR, width=1.0)
        elif not self.grid_box.value:
            plane.remove("grid")
        with self.state.lock:
            lines = [list(ln) for ln in self.state.lines]
            open_last = self.state.line_open
        model = distortion.HarrisModel(gamma, w, h)
        a, b, cols, pts, pcols = [], [], [], [], []
        for i, ln in enumerate(lines):
            if not ln:
                continue
            c = model.corrected_from_raw(np.asarray(ln, float))
            colour = (
                OPEN_LINE_COLOUR
                if (open_last and i == len(lines) - 1)
                else LINE_COLOURS[i % len(LINE_COLOURS)]
            )
            pts.append(c)
            pcols.append(np.broadcast_to(np.asarray(colour, np.uint8), (len(c), 3)))
            if len(c) >= 2:
                s, e = scene2d.polyline_segments(c)
                a.append(s), b.append(e)
                cols.append(np.broadcast_to(np.asarray(colour, np.uint8), (len(s), 3)))
        if a:
            plane.segments(
                "lines", np.concatenate(a), np.concatenate(b), np.concatenate(cols), width=3.0
            )
        else:
            plane.remove("lines")
        if pts:
            plane.points(
                "line_points", np.concatenate(pts), np.concatenate(pcols), size_px=max(w, h) / 250
            )
        else:
            plane.remove("line_points")
