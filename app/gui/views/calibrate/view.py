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

from app.gui import scene2d
from app.gui.context import Client
from app.gui.messages import browser_message
from app.gui.views.base import View
from app.gui.views.calibrate.panel import CalibratePanel
from app.gui.views.calibrate.scene import CalibrateScene
from registration.lens import (
    Camera,
    check_valid,
    estimate_gamma_auto,
    estimate_gamma_from_flight,
    estimate_gamma_from_lines,
    harris_gamma_limit,
    lines_to_json,
    straightness,
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
SETTLE_S = 0.35
"""After this long without a new γ/frame request, the full-resolution image replaces the preview."""


class _Cancelled(Exception):
    """Raised from an estimate's progress callback when the analyst pressed Cancel."""


class CalibrateView(View):
    MODE = "Calibrate"
    CLICKABLE = ("frame",)

    panel: CalibratePanel
    scene: CalibrateScene

    def make_scene(self, scene, root_name):
        return CalibrateScene(scene, root_name)

    def make_panel(self, gui):
        return CalibratePanel(gui)

    def connect(self) -> None:
        p = self.panel
        p.on_frame_changed(lambda k, client: self.set_frame(k))
        p.on_gamma_changed(self.set_gamma)
        p.on_overlays_changed(lambda client: self.request_overlays())
        p.on_new_line(lambda client: self.new_line())
        p.on_finish_line(lambda client: self.finish_line())
        p.on_undo_point(lambda client: self.undo_point())
        p.on_clear_lines(lambda client: self.clear_lines())
        p.on_estimate_from_lines(lambda client: self.estimate(auto=False, client=client))
        p.on_estimate_automatically(lambda client: self.estimate(auto=True, client=client))
        p.on_estimate_from_motion(lambda client: self.estimate_from_motion(client=client))
        p.on_use_estimate(self.use_estimate)
        p.on_import_lines(self.import_lines)
        self._settle_timer: threading.Timer | None = None
        self._timer_lock = threading.Lock()
        self._stopped = False
        self.last_estimate = None
        self.last_how = ""
        self.gamma_source: tuple[float, str] | None = None  # (γ, its estimate's text) in use

    # ---------------------------------------------------------------- inputs and state
    def on_inputs(self) -> None:
        inp = self.ctx.inputs
        w, h = inp.frame_size
        self.scene.make_plane("frame", w, h)
        limit = harris_gamma_limit(w, h)
        self.gamma_max = float(np.floor((limit - 1e-3) * 1000) / 1000)
        self.panel.configure(inp.n_frames, self.gamma_max)
        with self.state.lock:
            k, g = self.state.calib_frame, self.state.gamma
            self.panel.show_gamma(g)
        self.panel.frame = k
        self.last_estimate = None
        self.update_lines_text()

    def on_show(self) -> None:
        self.request_render()

    def set_frame(self, k: int) -> None:
        with self.state.lock:
            if self.ctx.inputs is None:
                return
            k = int(np.clip(k, 0, self.ctx.inputs.n_frames - 1))
            if k == self.state.calib_frame and self.ctx.shown.get(self.MODE):
                return
            self.state.calib_frame = k
            self.state.revision += 1
        self.ctx.save(soon=True)
        self.request_render()

    def set_gamma(self, gamma: float, client: Client = None) -> bool:
        """Validate and set γ (slider, number box, estimate); False (and a notification) if invalid."""
        if self.ctx.inputs is None:
            return False
        try:
            if not np.isfinite(gamma):
                raise ValueError(f"γ must be a finite number, got {gamma}")
            with self.state.lock:
                camera = self.state.camera(float(gamma))
            check_valid(camera.lens)
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
            self.ctx.save()
            self.ctx.state_changed()
        if self.last_estimate is not None:
            self._show_estimate(pending=self._pending(gamma))
        self.request_render()
        return True

    def on_click(self, plane: str, xy, client: Client) -> None:
        """Add a point (given in corrected pixels of the shown image) to the open polyline."""
        with self.state.lock:
            raw = self.state.camera().raw_from_corrected(np.asarray(xy, float)[None])[0]
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

    def import_lines(self, name: str, content: bytes, client: Client = None) -> bool:
        """Replace the lines by those of an uploaded LINES.json (the format ``aerialreg
        calibrate --lines`` reads) drawn on frames of this size."""
        import json as _json

        from registration.lens import parse_lines
        from registration.lens.lines_file import MAX_LINES_FILE_BYTES

        inp = self.ctx.inputs
        if inp is None:
            return False
        try:
            if len(content) > MAX_LINES_FILE_BYTES:
                raise ValueError(f"{name} is {len(content) / 1e6:.1f} MB, over the limit")
            parsed = parse_lines(_json.loads(content.decode("utf-8-sig")), name)
        except (ValueError, UnicodeDecodeError) as exc:
            self.notify(client, "Lines not imported", browser_message(exc), "red")
            return False
        if tuple(parsed.image_size) != tuple(inp.frame_size):
            w, h = parsed.image_size
            self.notify(
                client,
                "Lines not imported",
                f"{name} was drawn on {w}x{h} frames; these are "
                f"{inp.frame_size[0]}x{inp.frame_size[1]}",
                "red",
            )
            return False
        with self.state.lock:
            self.state.lines = [[(float(x), float(y)) for x, y in ln] for ln in parsed.lines]
            self.state.line_open = False
            self.state.revision += 1
        self._lines_changed()
        self.notify(client, "Lines imported", f"{len(parsed.lines)} lines from {name}", "green")
        return True

    def _lines_changed(self) -> None:
        self.ctx.save()
        self.save_lines_file()
        self.update_lines_text()
        self.request_overlays()

    def _finished_lines(self) -> list[np.ndarray]:
        """The lines of ≥ 3 points (raw px, ``(N, 2)`` each) (call under the lock)."""
        return [np.asarray(ln, float) for ln in self.state.lines if len(ln) >= 3]

    def save_lines_file(self) -> None:
        """Write LINES.json (registration.lens.gamma_from_lines's format) for the finished lines."""
        inp = self.ctx.inputs
        with self.state.lock:
            lines = self._finished_lines()
        if inp is None:
            return
        obj = lines_to_json(lines, inp.frame_size) if lines else None
        if obj is None:
            self.ctx.project.lines_path.unlink(missing_ok=True)
            return
        self.ctx.project.write_file("LINES.json", json.dumps(obj) + "\n")

    def scores(self) -> tuple[list[float], float] | None:
        """Straightness (px) of each finished line at the current γ, and overall; None if n/a."""
        if self.ctx.inputs is None:
            return None
        with self.state.lock:
            lines = self._finished_lines()
            camera = self.state.camera()
        if not lines:
            return None
        s = straightness(lines, camera.lens)
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
    def estimate(self, *, auto: bool, client: Client = None) -> None:
        inp = self.ctx.inputs
        if inp is None:
            return
        with self.state.lock:
            lines = self._finished_lines()
            k = self.state.calib_frame
        if not auto and not lines:
            self.notify(client, "No lines", "Draw at least one line of ≥ 3 points first", "yellow")
            return

        def job(progress) -> None:
            self.panel.show_estimating("Estimating γ ...")
            if auto:
                est = estimate_gamma_auto(inp.frame(k))
            else:
                est = estimate_gamma_from_lines(lines, *inp.frame_size)
            if progress.cancel.is_set():
                self._cancelled(client)
                return
            self._estimated(est, "automatically" if auto else "from lines", client)

        self.ctx.run_job("estimate γ", job, client)

    def estimate_from_motion(self, client: Client = None, *, as_default: bool = False) -> None:
        """γ from the matches between frame pairs spread over the flight. ``as_default``: the
        estimate the app runs when frames are opened and no γ was ever set (``App(auto_gamma=
        True)``, ``aerialreg app``): queued behind a running job, and it sets γ as
        ``aerialreg register --gamma auto`` would, where γ is still unset then
        (:meth:`_adopt_as_default`)."""
        inp = self.ctx.inputs
        if inp is None:
            return
        if inp.n_frames < 2:
            self.notify(client, "One frame", "γ from motion needs 2 frames or more", "yellow")
            return

        def job(progress) -> None:
            self.panel.show_estimating("Estimating γ from the frames' motion ...")
            progress(0, None, "choosing how many frames apart")

            def pairs_done(done: int, total: int) -> None:
                if progress.cancel.is_set():
                    raise _Cancelled
                progress(done, total, "frame pairs matched")

            try:
                est = estimate_gamma_from_flight(inp.frame, inp.n_frames, progress=pairs_done)
            except _Cancelled:
                est = None
            if est is None or progress.cancel.is_set():
                self._cancelled(client)
                return
            how = f"from {len(est.frame_pairs)} frame pairs {est.step} apart"
            self._estimated(est, how, client)
            if as_default:
                self._adopt_as_default(est, how, client)

        self.ctx.run_job("estimate γ from motion", job, client, queue=as_default)

    def _adopt_as_default(self, est, how: str, client: Client) -> None:
        """The opening estimate becomes γ when none was set meanwhile and it passes the rule
        the command line's ``--gamma auto`` applies; otherwise it waits to be accepted, and
        the analyst is told why."""
        with self.state.lock:
            unset = not self.state.gamma_set
        if not unset:
            return  # the analyst chose γ meanwhile: the estimate is only shown
        problem = est.unusable_as_default()
        if problem:
            self.notify(
                client,
                "γ not set",
                f"the frames' motion does not determine it ({problem}): set it here (slider, "
                "lines along streets, or 0 for a lens without distortion)",
                "yellow",
            )
            return
        if self.use_estimate(client):
            self.gamma_source = (
                float(est.gamma),
                f"± {est.uncertainty:.4f} (estimated {how} when the frames were opened, as "
                "`aerialreg register --gamma auto` does)",
            )
            self._show_estimate(pending=False)
            self.notify(
                client,
                "γ set from the frames' motion",
                f"{est.gamma:.4f} ± {est.uncertainty:.4f}, as `aerialreg register` would use",
                "green",
            )

    def _cancelled(self, client: Client) -> None:
        """A cancelled estimate changes nothing: the previous estimate's text comes back."""
        with self.state.lock:
            g = self.state.gamma
        if self.last_estimate is not None:
            self._show_estimate(pending=self._pending(g))
        else:
            self.panel.show_estimating("")
        self.notify(client, "Estimate cancelled", f"γ stays {g:.4f}", "blue")

    def _estimated(self, est, how: str, client: Client) -> None:
        """Show an estimate beside the γ in use; it replaces γ only when the analyst presses
        *Use the estimated γ* (on the job's thread)."""
        self.last_estimate, self.last_how = est, how
        with self.state.lock:
            g = self.state.gamma
        self._show_estimate(pending=self._pending(g))
        self.request_overlays()

    def _pending(self, gamma: float) -> bool:
        est = self.last_estimate
        return est is not None and abs(float(est.gamma) - float(gamma)) > 1e-12

    def _show_estimate(self, *, pending: bool) -> None:
        with self.state.lock:
            g, is_set = self.state.gamma, self.state.gamma_set
        source = self.gamma_source
        if source is not None and abs(source[0] - g) <= 1e-12:
            current = f"{g:.4f} {source[1]}"
        else:
            current = f"{g:.4f}" + ("" if is_set else " (not calibrated yet)")
        self.panel.show_estimate(self.last_estimate, self.last_how, current, pending)

    def use_estimate(self, client: Client = None) -> bool:
        """Apply the last estimate's γ (the analyst accepted it)."""
        est = self.last_estimate
        if est is None:
            self.notify(client, "No estimate", "Estimate γ first", "yellow")
            return False
        if not self.set_gamma(float(est.gamma), client):
            return False
        self.gamma_source = (
            float(est.gamma),
            f"± {est.uncertainty:.4f} (estimated {self.last_how})",
        )
        self._show_estimate(pending=False)
        return True

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
        inp = self.ctx.inputs
        img = inp.frame(k) if max_side is None else inp.preview(k, max_side)
        # The camera of the image drawn (a preview has its own size, the same γ).
        return scene2d.to_rgb(Camera.of(img, gamma).undistort(img))

    def render(self, *, full: bool, rev: int | None = None) -> None:
        inp = self.ctx.inputs
        if inp is None or "frame" not in self.scene.planes:
            return
        with self.state.lock:
            k, g, cur = self.state.calib_frame, self.state.gamma, self.state.revision
        if rev is not None and rev != cur:
            return  # a newer request superseded this settle render
        if full and max(inp.frame_size) <= self.ctx.display_max:
            last = self.ctx.shown.get(self.MODE)
            if last and last[:2] == (k, g):
                return  # the preview was already full resolution
        rgb = self.corrected_image(k, g, None if full else self.ctx.display_max)
        with self.ctx.atomic():
            self.scene.show_frame(rgb)
            self._draw(g)
        self.ctx.shown[self.MODE] = (k, g, rgb.shape[1], rgb.shape[0])
        self.update_lines_text()

    def draw_overlays(self) -> None:
        if "frame" not in self.scene.planes:
            return
        with self.state.lock:
            g = self.state.gamma
        with self.ctx.atomic():
            self._draw(g)
        self.update_lines_text()

    def _draw(self, gamma: float) -> None:
        """The grid, the analyst's lines and the estimate's lines, corrected for ``gamma``."""
        with self.state.lock:
            camera = self.state.camera(gamma)
            lines = [list(ln) for ln in self.state.lines]
            open_last = self.state.line_open
        self.scene.draw_grid(self.panel.show_grid)
        corrected, colours = [], []
        for i, ln in enumerate(lines):
            corrected.append(camera.corrected_from_raw(np.asarray(ln, float).reshape(-1, 2)))
            last_open = open_last and i == len(lines) - 1
            colours.append(OPEN_LINE_COLOUR if last_open else LINE_COLOURS[i % len(LINE_COLOURS)])
        self.scene.draw_lines(corrected, colours)
        est = self.last_estimate
        detected = None
        if est is not None and self.panel.show_lines_used and est.method == "auto":
            detected = [camera.corrected_from_raw(np.asarray(c, float)) for c in est.lines_used]
        self.scene.draw_detected(detected)
