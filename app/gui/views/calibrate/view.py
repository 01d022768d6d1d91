"""Calibrate view: choose the Harris γ (paper section 3) by eye, from lines, or automatically.

Shows the radially corrected frame for the current γ (JPEG preview at display resolution while
the slider moves, full resolution once it settles), straight reference lines over it (the paper's
Fig. 2), the analyst's polylines along streets drawn as corrected for the current γ with their
straightness (``registration.lens.gamma_from_lines``), updated whenever γ changes, and after an automatic
estimate the lines it detected and used. Lines are stored in raw pixels, so they stay on the same
street whatever γ is shown, and saved in the LINES.json format. The residual-versus-γ chart marks
the estimate and the γ shown.
"""

from __future__ import annotations

import json
import threading

import numpy as np
import viser.uplot as up

from app.gui import scene2d
from app.gui.assets import resend_value
from app.gui.security import escape_md
from app.gui.views.base import Scene, View
from registration.lens import (
    correction,
    gamma_from_lines,
    gamma_from_motion,
    line_straightness,
    lines_file,
    radial,
)

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
DETECTED_COLOUR = (255, 0, 200)
SETTLE_S = 0.35
"""After this long without a new γ/frame request, the full-resolution image replaces the preview."""
GAMMA_STEP = 0.005


class CalibratePanel:
    """Widgets of the Calibrate view."""

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
        with gui.add_folder("Estimate γ"):
            self.btn_est_lines = gui.add_button("Estimate γ from lines")
            self.btn_est_auto = gui.add_button("Estimate γ automatically")
            self.btn_est_motion = gui.add_button("Estimate γ from the frames' motion")
            self.show_detected = gui.add_checkbox("Show the lines the estimate used", True)
            self.estimate_md = gui.add_markdown("")
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

    def configure(self, n_frames: int, gamma_max: float) -> None:
        self.frame_slider.max = max(n_frames - 1, 1)
        self.frame_slider.disabled = n_frames <= 1
        self.gamma_slider.max = gamma_max
        self.gamma_number.max = gamma_max

    def quiet(self) -> bool:
        """True while :meth:`show_gamma` assigns the widgets (their callbacks must not act)."""
        return bool(getattr(self._quiet, "on", False))

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

    def show_lines(
        self, n: int, open_points: int | None, per_line, overall, error: str = ""
    ) -> None:
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

    def show_estimate(self, est, how: str, gamma_now: float) -> None:
        head = (
            f"γ = **{est.gamma:.4f}** ± {est.uncertainty:.4f} ({how}, {est.uncertainty_method}); "
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


class CalibrateScene(Scene):
    """The corrected frame, the reference grid, the analyst's lines, the detected lines."""

    def show_frame(self, rgb: np.ndarray) -> None:
        self.planes["frame"].show(rgb)

    def draw_grid(self, on: bool) -> None:
        plane = self.planes["frame"]
        if not on:
            plane.remove("grid")
            return
        if plane.has("grid"):
            return  # straight on screen whatever γ is: drawn once
        w, h = plane.geom.width, plane.geom.height
        xs = np.linspace(0, w - 1, 9)[1:-1]
        ys = np.linspace(0, h - 1, 7)[1:-1]
        a = [(x, 0) for x in xs] + [(0, y) for y in ys]
        b = [(x, h - 1) for x in xs] + [(w - 1, y) for y in ys]
        plane.segments("grid", a, b, GRID_COLOUR, width=1.0)

    def draw_lines(self, lines: list[np.ndarray], colours: list) -> None:
        """Polylines in corrected pixels with their vertices as dots."""
        plane = self.planes["frame"]
        a, b, cols, pts, pcols = [], [], [], [], []
        for c, colour in zip(lines, colours, strict=True):
            if not len(c):
                continue
            pts.append(c)
            pcols.append(np.broadcast_to(np.asarray(colour, np.uint8), (len(c), 3)))
            if len(c) >= 2:
                s, e = scene2d.polyline_segments(c)
                a.append(s)
                b.append(e)
                cols.append(np.broadcast_to(np.asarray(colour, np.uint8), (len(s), 3)))
        if a:
            plane.segments(
                "lines", np.concatenate(a), np.concatenate(b), np.concatenate(cols), width=3.0
            )
        else:
            plane.remove("lines")
        if pts:
            plane.points("line_points", np.concatenate(pts), np.concatenate(pcols), size_px=7)
        else:
            plane.remove("line_points")

    def draw_detected(self, lines: list[np.ndarray] | None) -> None:
        plane = self.planes["frame"]
        if not lines:
            plane.remove("detected")
            return
        a, b = [], []
        for c in lines:
            if len(c) >= 2:
                s, e = scene2d.polyline_segments(c)
                a.append(s)
                b.append(e)
        if a:
            plane.segments(
                "detected", np.concatenate(a), np.concatenate(b), DETECTED_COLOUR, width=2.0
            )


class CalibrateView(View):
    MODE = "Calibrate"
    CLICKABLE = ("frame",)

    def make_scene(self, scene, root_name):
        return CalibrateScene(scene, root_name)

    def make_panel(self, gui):
        return CalibratePanel(gui)

    def connect(self) -> None:
        p = self.panel
        p.frame_slider.on_update(lambda ev: self.set_frame(int(ev.target.value)))
        p.gamma_slider.on_update(lambda ev: self._gamma_widget(ev))
        p.gamma_number.on_update(lambda ev: self._gamma_widget(ev))
        p.grid_box.on_update(lambda ev: self.request_overlays())
        p.show_detected.on_update(lambda ev: self.request_overlays())
        p.btn_new.on_click(lambda ev: self.new_line())
        p.btn_finish.on_click(lambda ev: self.finish_line())
        p.btn_undo.on_click(lambda ev: self.undo_point())
        p.btn_clear.on_click(lambda ev: self.clear_lines())
        p.btn_est_lines.on_click(lambda ev: self.estimate(auto=False, client=ev.client))
        p.btn_est_auto.on_click(lambda ev: self.estimate(auto=True, client=ev.client))
        p.btn_est_motion.on_click(lambda ev: self.estimate_from_motion(client=ev.client))
        self._settle_timer: threading.Timer | None = None
        self._timer_lock = threading.Lock()
        self._stopped = False
        self.last_estimate = None

    # ---------------------------------------------------------------- inputs and state
    def on_inputs(self) -> None:
        inp = self.app.inputs
        w, h = inp.frame_size
        self.scene.make_plane("frame", w, h)
        limit = radial.harris_gamma_limit(w, h)
        self.gamma_max = float(np.floor((limit - 1e-3) * 1000) / 1000)
        self.panel.configure(inp.n_frames, self.gamma_max)
        with self.state.lock:
            k, g = self.state.calib_frame, self.state.gamma
            self.panel.show_gamma(g)
        self.panel.frame_slider.value = k
        self.last_estimate = None
        self.update_lines_text()

    def on_show(self) -> None:
        self.request_render()

    def set_frame(self, k: int) -> None:
        with self.state.lock:
            if self.app.inputs is None:
                return
            k = int(np.clip(k, 0, self.app.inputs.n_frames - 1))
            if k == self.state.calib_frame and self.app.shown.get(self.MODE):
                return
            self.state.calib_frame = k
            self.state.revision += 1
        self.app.save(soon=True)
        self.request_render()

    def set_gamma(self, gamma: float, client=None) -> bool:
        """Validate and set γ (slider, number box, estimate); False (and a notification) if invalid."""
        inp = self.app.inputs
        if inp is None:
            return False
        try:
            if not np.isfinite(gamma):
                raise ValueError(f"γ must be a finite number, got {gamma}")
            radial.check_valid(radial.HarrisModel(float(gamma), *inp.frame_size))
        except ValueError as exc:
            self.notify(client, "Invalid γ", str(exc), color="red")
            with self.state.lock:
                self.panel.show_gamma(self.state.gamma)
            return False
        with self.state.lock:
            changed = gamma != self.state.gamma or not self.state.gamma_set
            self.state.gamma = float(gamma)
            self.state.gamma_set = True
            self.state.revision += 1
            # Under the lock: callbacks from two browser tabs run concurrently, and the widgets
            # must end showing the γ of whichever set the state last, in every tab.
            self.panel.show_gamma(gamma)
            if client is not None:
                self.panel.resend_gamma()
        if changed:
            self.app.save()
            self.app.state_changed()
        self.request_render()
        return True

    def _gamma_widget(self, ev) -> None:
        # Assigning a widget from Python runs its callback synchronously in this thread; the
        # slider's rounded value must not overwrite the exact γ then.
        if self.panel.quiet():
            return
        self.set_gamma(float(ev.target.value), ev.client)

    def on_click(self, plane: str, xy, client) -> None:
        """Add a point (given in corrected pixels of the shown image) to the open polyline."""
        inp = self.app.inputs
        with self.state.lock:
            model = radial.HarrisModel(self.state.gamma, *inp.frame_size)
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
        self.update_lines_text()
        self.request_overlays()

    def save_lines_file(self) -> None:
        """Write LINES.json (registration.lens.gamma_from_lines's format) for the finished lines."""
        inp = self.app.inputs
        with self.state.lock:
            lines = [np.asarray(ln, float) for ln in self.state.lines if len(ln) >= 3]
        if inp is None:
            return
        obj = lines_file.lines_to_json(lines, inp.frame_size) if lines else None
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
        s = line_straightness.straightness(lines, radial.HarrisModel(g, *inp.frame_size))
        return [float(v) for v in s.per_line], float(s.overall)

    def update_lines_text(self) -> None:
        """The lines' table for the current γ (called whenever γ or the lines change)."""
        with self.state.lock:
            n = len(self.state.lines)
            open_pts = (
                len(self.state.lines[-1]) if self.state.line_open and self.state.lines else None
            )
        try:
            sc, error = self.scores(), ""
        except ValueError as exc:
            sc, error = None, str(exc)
        per, overall = sc if sc is not None else (None, None)
        self.panel.show_lines(n, open_pts, per, overall, error)

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

        def job(progress) -> None:
            self.panel.estimate_md.content = "Estimating γ ..."
            if auto:
                est = gamma_from_lines.estimate_gamma_auto(inp.frame(k))
            else:
                est = gamma_from_lines.estimate_gamma_from_lines(lines, *inp.frame_size)
            self.last_estimate = est
            self.panel.show_estimate(est, "automatically" if auto else "from lines", est.gamma)
            self.set_gamma(float(est.gamma), client)
            self.request_overlays()

        self.app.run_job("estimate γ", job, client)

    def estimate_from_motion(self, client=None) -> None:
        """γ from the matches between frame pairs spread over the flight."""
        inp = self.app.inputs
        if inp is None:
            return
        if inp.n_frames < 2:
            self.notify(client, "One frame", "γ from motion needs 2 frames or more", "yellow")
            return

        def job(progress) -> None:
            self.panel.estimate_md.content = "Estimating γ from the frames' motion ..."
            progress(0, None, "choosing how many frames apart")
            est = gamma_from_motion.estimate_gamma_from_flight(
                inp.frame,
                inp.n_frames,
                progress=lambda done, total: progress(done, total, "frame pairs matched"),
            )
            self.last_estimate = est
            how = f"from {len(est.frame_pairs)} frame pairs {est.step} apart"
            self.panel.show_estimate(est, how, est.gamma)
            self.set_gamma(float(est.gamma), client)
            self.request_overlays()

        self.app.run_job("estimate γ from motion", job, client)

    def shutdown(self) -> None:
        with self._timer_lock:
            if self._settle_timer is not None:
                self._settle_timer.cancel()
            self._stopped = True

    # ---------------------------------------------------------------- drawing (worker thread)
    def request_render(self) -> None:
        with self._timer_lock:
            if self._settle_timer is not None:
                self._settle_timer.cancel()
        self.submit("render", lambda: self.render(full=False))
        with self._timer_lock:
            if self._stopped:
                return
            with self.state.lock:
                rev = self.state.revision
            self._settle_timer = threading.Timer(
                # Its own key: a stale settle render must never replace a newer request.
                SETTLE_S,
                lambda: self.submit("render-full", lambda: self.render(full=True, rev=rev)),
            )
            self._settle_timer.daemon = True
            self._settle_timer.start()

    def request_overlays(self) -> None:
        self.submit("overlays", self.draw_overlays)

    def corrected_image(self, k: int, gamma: float, max_side: int | None) -> np.ndarray:
        """Corrected frame ``k`` (RGB) at full size or with its longer side ≤ ``max_side``."""
        img = self.app.inputs.frame(k) if max_side is None else self.app.inputs.preview(k, max_side)
        h, w = img.shape[:2]
        corrected, _ = correction.undistort_image(
            img, radial.HarrisModel(gamma, w, h), canvas="same"
        )
        return scene2d.to_rgb(corrected)

    def render(self, *, full: bool, rev: int | None = None) -> None:
        inp = self.app.inputs
        if inp is None or "frame" not in self.scene.planes:
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
            self.scene.show_frame(rgb)
            self._draw(g)
        self.app.shown[self.MODE] = (k, g, rgb.shape[1], rgb.shape[0])
        self.update_lines_text()

    def draw_overlays(self) -> None:
        if "frame" not in self.scene.planes:
            return
        with self.state.lock:
            g = self.state.gamma
        with self.app.server.atomic():
            self._draw(g)
        self.update_lines_text()

    def _draw(self, gamma: float) -> None:
        w, h = self.app.inputs.frame_size
        model = radial.HarrisModel(gamma, w, h)
        self.scene.draw_grid(bool(self.panel.grid_box.value))
        with self.state.lock:
            lines = [list(ln) for ln in self.state.lines]
            open_last = self.state.line_open
        corrected, colours = [], []
        for i, ln in enumerate(lines):
            corrected.append(model.corrected_from_raw(np.asarray(ln, float).reshape(-1, 2)))
            last_open = open_last and i == len(lines) - 1
            colours.append(OPEN_LINE_COLOUR if last_open else LINE_COLOURS[i % len(LINE_COLOURS)])
        self.scene.draw_lines(corrected, colours)
        est = self.last_estimate
        detected = None
        if est is not None and self.panel.show_detected.value and est.method == "auto":
            detected = [model.corrected_from_raw(np.asarray(c, float)) for c in est.lines_used]
        self.scene.draw_detected(detected)
