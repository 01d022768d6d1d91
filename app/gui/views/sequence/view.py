"""Sequence view: register every frame (paper 4.4 and 5) in the background, then review frame by frame.

"Register all frames" runs ``pipeline.register_sequence`` (resuming a result folder that is partly
done, so frames already registered survive a killed server) with the transform chosen in the Seed
view's run settings; progress and time left show in the header. For the frame under the
scrubber: the frame warped into the map (through the result's ``base_to_frame``) over the map as a
blend, checkerboard or flicker, only over the frame's footprint; the control points' residual
vectors (scaled automatically); the local displacement field's magnitude as a heat map (the
paper's Fig. 5) with a colour bar. The per-frame residual RMS is an interactive chart: hover shows
the values, a click jumps to the frame. Failed frames are listed with their reasons; one frame can
be registered again; the frame's control points are listed (read-only) and exported. The
*Export* folder writes the result as GIS files and video (``export.py``).

Scrubbing is fast because the frame is warped at display resolution from a preview of the frame
(decoded ahead by :meth:`app.gui.inputs.Inputs.prefetch`) and only its footprint is encoded and sent
(``frames.py``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from app.gui import calls, controlpoints, scene2d
from app.gui.context import Client
from app.gui.messages import result_started_afresh
from app.gui.security import escape_md
from app.gui.views.base import PLAY_SIDE_FRACTION, PlayClock, View
from app.gui.views.cptable.table import ControlPointTableView
from app.gui.views.frames import RegisteredFrames, excursion_flags, frame_preview_side
from app.gui.views.sequence.earlier import EarlierResults
from app.gui.views.sequence.export import Exporter
from app.gui.views.sequence.map_points import MapPointsTool
from app.gui.views.sequence.panel import DisplayOptions, SequencePanel
from app.gui.views.sequence.scene import RESIDUAL_OK, RESIDUAL_REMOVED, SequenceScene
from registration.errors import ResultDamaged, ResumeMismatch
from registration.run import ANCHOR_STAGE, pipeline

log = logging.getLogger(__name__)


def fit_fingerprint(edits) -> str:
    """The analyst's control-point edits of the reference fit, as a short hash."""
    import hashlib
    import json

    text = json.dumps(edits.to_json(), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


MAP_STAGES = ("inter-sensor", ANCHOR_STAGE)
"""Record stages of frames registered to the map itself."""
FLICKER_S = 0.5
SETTLE_S = 0.35
"""After this long on one frame, it is drawn again at the map preview's full resolution."""
SELECT_RADIUS_PX = 20
"""A click on the map selects the nearest control point within this many screen pixels."""
SELECTED_REGION_PX = (300, 225)
"""Map pixels the camera shows around a selected control point."""
READ_ONLY_NOTE = (
    "Read-only: edit the reference frame's points in the Seed view; a frame can be registered "
    "again."
)


class SequenceView(View):
    MODE = "Sequence"
    CLICKABLE = ("base",)

    panel: SequencePanel
    scene: SequenceScene

    def make_scene(self, scene, root_name):
        return SequenceScene(scene, root_name)

    def make_panel(self, gui):
        return SequencePanel(gui)

    def connect(self) -> None:
        p = self.panel
        p.on_register_all(self.run)
        p.on_frame_changed(lambda k, client: self.set_frame(k))
        p.on_jumps(
            worst=lambda client: self.jump_to_worst(),
            next_failed=lambda client: self.jump_to_next_failed(),
        )
        p.on_register_frame_again(self.rerun_frame)
        p.on_display_changed(lambda client: self._view_changed())
        self.frames = RegisteredFrames(self.ctx, self.result)
        self.earlier = EarlierResults(self.ctx, p, self._restored)
        self.cp = ControlPointTableView(
            self.ctx,
            p.cps,
            scope="seq",
            note=READ_ONLY_NOTE,
            empty_note="No control points for this frame.",
            region=self._region,
            on_selected=self._point_selected,
        )
        p.cps.on_point_actions(centre=self.cp.centre_on_selected)
        p.cps.on_export(self.export_points)
        self.exporter = Exporter(self.ctx, p.export)
        self.map_points = MapPointsTool(self, p.map_points)
        self.ctx.events.on("plot-frame", lambda v, client: self.set_frame(int(v)))
        self.ctx.events.on("seq-frame", lambda v, client: self.set_frame(int(v)))
        self._threads_stop = threading.Event()
        self._flicker_on = True
        self._settle_timer: threading.Timer | None = None
        self._settle_lock = threading.Lock()
        self._requested: int | None = None  # the frame last asked to be drawn
        self.table_frame: int | None = None  # the frame whose control points are listed
        threading.Thread(target=self._ticker, name="sequence-ticker", daemon=True).start()

    # ---------------------------------------------------------------- the control points
    @property
    def table(self) -> controlpoints.ControlPointTable | None:
        """The control-point table of the frame shown (None: it has none)."""
        return self.cp.table

    @property
    def selected(self) -> int | None:
        return self.cp.selected

    def select_point(self, row_id: int, client: Client = None) -> None:
        self.cp.select(row_id, client)

    def _point_selected(self, row_id: int, client: Client) -> None:
        t = self.cp.table
        self.submit("selected", lambda: self.scene.draw_selected(t.base_xy[t.row(row_id)]))

    def _region(self, table, i: int) -> list[scene2d.PlaneGeometry]:
        """The map around row ``i``'s map point."""
        geom = self.scene.planes["base"].geom
        c = geom.world_from_pixel(table.base_xy[i])
        w, h = SELECTED_REGION_PX
        return [scene2d.PlaneGeometry(w, h, position=(c[0], c[1], 0.0), scale=geom.scale)]

    def export_points(self, client: Client = None) -> bool:
        """This frame's table as QGIS ``.points`` (see the Seed view's), sent to the browser."""
        with self.state.lock:
            k = self.state.seq_frame
        path = self.ctx.project.folder / f"frame_{k:06d}.points"
        return self.cp.export(path, client, when_empty="This frame has none")

    # ---------------------------------------------------------------- inputs and state
    def on_inputs(self) -> None:
        inp = self.ctx.inputs
        self.scene.layout(inp.base_size)
        self.clear_cache()
        self.cp.table = None
        with self.state.lock:
            st = self.state
            k, result_dir = st.seq_frame, st.result_dir
            st.result = None
            display = dict(
                opacity=st.opacity, vector_scale=st.vector_scale, overlay=st.overlay, stage=st.stage
            )
        # Outside the lock: the widgets' callbacks save the session.
        self.panel.show_display(**display)
        self.panel.configure(inp.n_frames)
        self.panel.frame = k
        if result_dir:
            self.load_result(result_dir)
        self.earlier.refresh()
        self.refresh_text()

    def _restored(self, out_dir) -> None:
        self.load_result(out_dir)
        self.refresh_text()
        self.request_render()

    def on_show(self) -> None:
        self.refresh_text()
        self.request_render()

    def on_state_changed(self) -> None:
        self.refresh_text()

    def load_result(self, out_dir) -> None:
        import registration

        try:
            result = registration.load(out_dir)
        except (OSError, ValueError) as exc:
            self.ctx.record_error(f"could not open result {out_dir}: {exc}")
            result = None
        inp = self.ctx.inputs
        if (
            result is not None
            and inp is not None
            and (result.n_frames != inp.n_frames or tuple(result.frame_size) != inp.frame_size)
        ):
            self.ctx.record_error(f"result {out_dir} does not match the inputs; ignored")
            result = None
        with self.state.lock:
            self.state.result = result
        self.clear_cache()
        self.cp.table = None

    def clear_cache(self) -> None:
        """Forget the frames warped so far (benchmarks measure the cold path)."""
        self.frames.clear()

    def result(self):
        with self.state.lock:
            return self.state.result

    def set_frame(self, k: int) -> None:
        with self.state.lock:
            if self.ctx.inputs is None:
                return
            k = int(np.clip(k, 0, self.ctx.inputs.n_frames - 1))
            if k == self.state.seq_frame and self._requested == k:
                return  # e.g. the scrubber's own callback after we moved it
            self.state.seq_frame = k
            self._requested = k
            self.state.revision += 1
        if self.panel.frame != k:
            self.panel.frame = k  # runs set_frame again, which then returns early
        self.ctx.save(soon=True)
        self.request_render()

    def _view_changed(self) -> None:
        display = self.panel.display()
        with self.state.lock:
            self.state.opacity = display.opacity
            self.state.vector_scale = display.vector_scale
            self.state.overlay = display.overlay
            self.state.stage = display.stage
        self.ctx.save()
        self.request_render()

    def shutdown(self) -> None:
        self._threads_stop.set()
        with self._settle_lock:
            if self._settle_timer is not None:
                self._settle_timer.cancel()

    def _ticker(self) -> None:
        """Play and flicker clocks (post render requests; never draw themselves)."""
        clock = PlayClock()
        last_flicker = time.monotonic()
        while not self._threads_stop.wait(0.01):
            if not self.visible or self.ctx.inputs is None:
                continue
            now = time.monotonic()
            if clock.due(self.panel.playing, now):
                with self.state.lock:
                    k = (self.state.seq_frame + 1) % max(self.ctx.inputs.n_frames, 1)
                self.set_frame(k)
            if self.panel.flickering and now - last_flicker >= FLICKER_S:
                last_flicker = now
                self._flicker_on = not self._flicker_on
                self.submit("flicker", lambda: self.scene.set_registered_visible(self._flicker_on))

    # ---------------------------------------------------------------- running
    def run_text(self) -> tuple[str, str]:
        """The result's state and what the next run uses: two lines of markdown."""
        with self.state.lock:
            st = self.state
            seed, r, transform, local = st.seed, st.result, st.transform, st.run_local
            adjust = st.adjust
            ref_ok = st.current_reference() is not None and st.current_reference().fine
            preset = st.preset
        if r is None:
            done = "no result yet"
        else:
            s = [rec.status for rec in r.records]
            done = (
                f"{s.count('ok')} ok, {s.count('failed')} failed, {s.count('pending')} pending "
                f"of {r.n_frames}"
            )
        seed_txt = "seeded" if seed else "**no seed**: the coarse step searches without a gate"
        ref_txt = (
            "reference fitted in the Seed view" if ref_ok else "the reference frame is fitted first"
        )
        return (
            f"Result: {done}; {seed_txt}; {ref_txt}.",
            f"Run settings: preset {escape_md(preset)}, {escape_md(transform)}, local field "
            f"{'on' if local else 'off'}, frames adjusted together {'on' if adjust else 'off'} "
            "(Seed view).",
        )

    def refresh_text(self) -> None:
        self.panel.show_run("  \n".join(self.run_text()))
        self.exporter.refresh()
        r = self.result()
        if r is not None:
            failed = [(k, rec.reason) for k, rec in enumerate(r.records) if rec.status == "failed"]
            self.panel.show_failed(failed)
        else:
            self.panel.show_failed([])

    def run(self, client: Client = None) -> bool:
        inp = self.ctx.inputs
        if inp is None:
            return False
        with self.state.lock:
            st = self.state
            seed, seed2, ref, gamma, preset = (
                st.seed,
                st.seed2,
                st.reference_frame,
                st.gamma,
                st.preset,
            )
            fit = st.current_reference()
            reference = (
                (fit.coarse, fit.fine) if fit is not None and fit.coarse and fit.fine else None
            )
            # Which control-point edits the reference fit carries: a result made before the
            # analyst edited them is moved aside, so that the run uses the edited fit.
            edits = fit_fingerprint(st.cp_edits) if reference is not None else None
            cfg = calls.pipeline_config(preset, st.degree, st.run_local, st.adjust)
            out_dir = str(self.ctx.project.result_dir)
            st.result_dir = out_dir
        self.ctx.save()

        def job(progress) -> None:
            last = [0.0]

            def on_progress(done, total) -> None:
                progress(done, total, "frames")
                now = time.monotonic()
                if now - last[0] > 1.0:  # show finished frames as they land
                    last[0] = now
                    self.load_result(out_dir)
                    self.refresh_text()
                    self.submit("plot", self.draw_plot)

            def on_adjust_progress(done, total) -> None:
                progress(done, total, "frames adjusted together")

            kwargs = dict(
                adjust_progress=on_adjust_progress,
                seed=calls.seed_argument(seed, seed2),
                reference_frame=ref,
                config=cfg,
                preset=preset,
                base_path=inp.base_path,
                base_valid=inp.base_valid,
                base_georef=inp.base_georef,
                resume=True,
                progress=on_progress,
                cancel=progress.cancel,
            )
            if reference is not None:
                kwargs["reference"] = reference
            self._start_afresh_if_the_fit_was_edited(edits, client)
            try:
                self._register_or_start_afresh(inp, gamma, out_dir, kwargs, client)
            finally:
                self.load_result(out_dir)
                self.refresh_text()
                self.ctx.state_changed()
                self.request_render()
            if progress.cancel.is_set():
                self.notify(
                    client,
                    "Registration cancelled",
                    "Frames done so far are kept; run again to continue",
                    "yellow",
                )
            else:
                self.notify(client, "Registration finished", self.run_text()[0], "green")

        return self.ctx.run_job("register", job, client)

    def _start_afresh_if_the_fit_was_edited(self, edits: str | None, client) -> None:
        """Move the result aside when the reference fit's control points were edited since it
        was made (recorded in the project's ``result_fit.json``); record the edits of this run.
        A result without the record (an older project) is continued as it is."""
        project = self.ctx.project
        if edits is None:
            return
        recorded = project.read_result_fit()
        if project.result_dir.exists() and recorded is not None and recorded != edits:
            old = project.archive_result()
            with self.state.lock:
                self.state.result = None
            self.notify(
                client,
                "Starting a new result",
                f"the reference frame's control points were edited since the last result was "
                f"made; it is kept as {old.name} (Sequence view, *Earlier results*, restores it) "
                "and a new result is started with the edited fit",
                "yellow",
            )
            self.earlier.refresh()
        if not project.result_dir.exists() or recorded is None:
            project.write_result_fit(edits)

    def _register_or_start_afresh(self, inp, gamma: float, out_dir: str, kwargs, client) -> None:
        """``pipeline.register_sequence`` resuming ``out_dir``; when the folder was made for
        other settings, it is kept beside (``result.prev-N``) and a fresh result started."""
        try:
            pipeline.register_sequence(inp.frames, inp.base, gamma, out_dir, **kwargs)
        except (ResumeMismatch, ResultDamaged) as exc:
            # γ, seed, reference frame or settings changed since the folder was made:
            # keep the old result beside it and start a fresh one.
            old = self.ctx.project.archive_result()
            self.notify(
                client, "Starting a new result", result_started_afresh(exc, old.name), "yellow"
            )
            self.earlier.refresh()
            with self.state.lock:
                self.state.result = None
            pipeline.register_sequence(inp.frames, inp.base, gamma, out_dir, **kwargs)

    def rerun_frame(self, client: Client = None) -> bool:
        """Register the frame under the scrubber again with its result's own settings."""
        r = self.result()
        with self.state.lock:
            k = self.state.seq_frame
        if r is None or self.ctx.inputs is None:
            self.notify(client, "No result", "Register the sequence first", "yellow")
            return False
        if k == r.reference_frame:
            self.notify(
                client,
                "The reference frame",
                "It is fitted in the Seed view; registering all frames again uses the new fit",
                "yellow",
            )
            return False

        def done() -> str:
            rec = self.result().records[k]
            return f"{rec.status} {rec.reason}"

        return self.resume_own_run(
            client, f"register frame {k}", done, before=lambda: calls.forget_frame(r.out_dir, k),
            title=f"Frame {k} registered again",
        )  # fmt: skip

    def resume_own_run(
        self, client: Client, name: str, done: Callable[[], str], before=None, title: str = ""
    ) -> bool:
        """Resume the result's own run (its γ, seed and settings, not the app's current
        choices) as a job: it registers the frames without a record and adjusts those not
        adjusted; ``before()`` runs first in the job, ``done()`` says the outcome."""
        r = self.result()
        inp = self.ctx.inputs
        settings = calls.rerun_settings(r)
        out_dir = str(r.out_dir)

        def job(progress) -> None:
            progress(0, 1, name)
            if before is not None:
                before()
            pipeline.register_sequence(
                inp.frames,
                inp.base,
                settings["gamma"],
                out_dir,
                seed=settings["seed"],
                reference_frame=settings["reference_frame"],
                config=settings["config"],
                preset=settings["preset"],
                base_path=inp.base_path,
                base_valid=inp.base_valid,
                base_georef=inp.base_georef,
                resume=True,
                cancel=progress.cancel,
                adjust_progress=lambda d, t: progress(d, t, "frames adjusted together"),
            )
            self.load_result(out_dir)
            self.refresh_text()
            self.ctx.state_changed()
            self.request_render()
            self.notify(client, title or name[0].upper() + name[1:], done(), "green")

        return self.ctx.run_job(name, job, client)

    def jump_to_worst(self) -> None:
        """Show the frame with the largest residual RMS."""
        vals = self.error_values()
        if vals is not None and np.isfinite(vals).any():
            self.set_frame(int(np.nanargmax(vals)))

    def jump_to_next_failed(self) -> None:
        """Show the next failed frame after the one shown (wrapping round)."""
        r = self.result()
        if r is None:
            return
        with self.state.lock:
            k0 = self.state.seq_frame
        failed = [k for k, rec in enumerate(r.records) if rec.status == "failed"]
        if failed:
            later = [k for k in failed if k > k0]
            self.set_frame(later[0] if later else failed[0])

    def error_values(self) -> np.ndarray | None:
        """Residual RMS (base px) per frame from the result records; NaN where not ok."""
        return self.frames.error_values()

    def on_click(self, plane: str, xy, client: Client) -> None:
        """A click on the map places a map point's frame or map click while one is being
        placed (:mod:`app.gui.views.sequence.map_points`), else selects the nearest control
        point of the frame shown."""
        if self.map_points.on_click(xy, client):
            return
        t = self.cp.table
        if t is None or not len(t.ids):
            return
        d = np.hypot(*(t.base_xy - np.asarray(xy, float)).T)
        i = int(np.nanargmin(d))
        limit = SELECT_RADIUS_PX * self.scene.planes["base"].px_per_screen
        if d[i] <= limit:
            self.cp.select(int(t.ids[i]), client)

    # ---------------------------------------------------------------- drawing (worker)
    def request_render(self) -> None:
        """Render the frame now at scrubbing resolution, then (once the scrubber rests) at the
        map preview's full resolution."""
        with self._settle_lock:
            if self._settle_timer is not None:
                self._settle_timer.cancel()
        self.submit("render", lambda: self.render(full=False))
        with self._settle_lock:
            if self._threads_stop.is_set():
                return
            with self.state.lock:
                rev = self.state.revision
            self._settle_timer = threading.Timer(SETTLE_S, lambda: self._settle(rev))
            self._settle_timer.daemon = True
            self._settle_timer.start()

    def _settle(self, rev: int) -> None:
        """The scrubber rests: warp the frame at full resolution here, on the timer's thread, so
        that the worker stays free for the next scrub; then let the worker draw it."""
        with self.state.lock:
            if rev != self.state.revision:
                return
            k, stage = self.state.seq_frame, self.state.stage
        try:
            self.frames.registered(k, stage, 2 * self.ctx.display_max)
        except Exception:  # drawn (and reported) by the worker's render instead
            log.debug("settle warp of frame %d failed", k, exc_info=True)
        # Its own key: a stale settle render must never replace a newer scrub's request.
        self.submit("render-full", lambda: self.render(full=True, rev=rev))

    def render(self, full: bool = False, rev: int | None = None) -> None:
        from registration.render import viz

        inp = self.ctx.inputs
        if inp is None or "base" not in self.scene.planes:
            return
        display = self.panel.display()
        with self.state.lock:
            st = self.state
            k, stage, overlay = st.seq_frame, st.stage, st.overlay
            alpha, cur = st.opacity, st.revision
        if rev is not None and rev != cur:
            return  # the scrubber moved on: this settle render is stale
        fine_side = 2 * self.ctx.display_max
        if full:
            side = fine_side
        elif self.panel.playing:
            side = int(PLAY_SIDE_FRACTION * self.ctx.display_max)
        elif self.frames.has_warp(k, stage, fine_side):
            side = fine_side
        else:
            side = self.ctx.display_max
        if (
            full
            and self.ctx.shown.get(self.MODE, (None,) * 5)[:2] == (k, stage)
            and self.ctx.shown[self.MODE][4] == side
        ):
            return  # already shown at full resolution
        base_rgb = inp.base_preview(fine_side)
        reg = self.frames.registered(k, stage, side)
        under_rgb = inp.base_preview(side)
        with self.ctx.atomic():
            self.scene.show_base(base_rgb)
            if reg is None:
                self.scene.show_registered(None, None)
            else:
                crop, mask, box = reg
                under = self.frames.map_under(reg, side)
                if overlay == "checkerboard":
                    tile = max(8, under_rgb.shape[1] // 16)
                    img = viz.checkerboard(crop, under, tile=tile, mask=mask)
                elif overlay == "flicker":
                    img = viz.blend(crop, under, 1.0, mask=mask)
                else:
                    img = viz.blend(crop, under, alpha, mask=mask)
                self.scene.show_registered(
                    img, box, visible=overlay != "flicker" or self._flicker_on
                )
            r = self.result()
            ok = r is not None and r.is_ok(k)
            self.scene.draw_outline(self.frames.border_in_base(k, stage) if ok else None)
            self._frame_table(k)
            self._draw_vectors(display)
            self._draw_field(k, display)
            self.map_points.refresh(k)
        self.draw_plot()
        self._update_frame_md(k)
        self.ctx.shown[self.MODE] = (k, stage, overlay, reg is not None, side)
        if not full:
            footprint = (0, 0) if reg is None else (reg[0].shape[1], reg[0].shape[0])
            guess = frame_preview_side(*footprint) if reg is not None else self.ctx.display_max
            inp.prefetch([k + 1, k - 1, k + 2], preview_sides=(guess,))

    def _frame_table(self, k: int) -> None:
        """List frame ``k``'s control points (a new frame: no selection, first page)."""
        if self.table_frame != k or self.cp.table is None:
            table = self.frames.table(k)
            self.table_frame = k
            self.scene.draw_selected(None)
            self.cp.set_table(table, fresh=True)

    def _draw_vectors(self, display: DisplayOptions) -> None:
        t = self.cp.table
        if t is None or not display.vectors or t.model is None:
            self.scene.draw_vectors(None)
            return
        ok = np.isfinite(t.residual) & (t.enabled | display.outliers)
        scale = display.vector_scale or scene2d.auto_vector_scale(
            t.residual[t.enabled], self.scene.planes["base"].geom.width
        )
        self.vector_scale_used = scale
        cols = np.where(t.enabled[:, None], RESIDUAL_OK, RESIDUAL_REMOVED).astype(np.uint8)
        start = t.base_xy[ok]
        self.scene.draw_vectors((start, start + scale * t.residual_xy[ok], cols[ok]))

    def _draw_field(self, k: int, display: DisplayOptions) -> None:
        from registration.render import viz

        r = self.result()
        fld = r.field(k) if (r is not None and r.is_ok(k) and display.field) else None
        if fld is None:
            self.scene.draw_field(None, None)
            self.panel.show_colourbar(None)
            return
        rgba, vmax = viz.field_cells_image(fld.vectors, fld.valid)
        self.scene.draw_field(rgba, fld.extent)
        self.panel.show_colourbar(viz.colorbar(0.0, vmax, label="local displacement |d| (base px)"))

    def draw_plot(self) -> None:
        vals = self.error_values()
        r = self.result()
        with self.state.lock:
            k = self.state.seq_frame
        if vals is None or r is None:
            return
        failed = np.array([rec.status == "failed" for rec in r.records])
        flags = excursion_flags(vals) | np.array([bool(flagged(rec)) for rec in r.records])
        self.panel.show_plot(vals, flags, failed, k, predicted_errors(r.records), self.on_map(r))

    def on_map(self, r) -> np.ndarray:
        """``(N,)`` bool: the frames that carry evidence from the map (the reference frame,
        frames re-anchored to it, frames with the analyst's map points)."""
        out = np.array([rec.ok and rec.stage in MAP_STAGES for rec in r.records], bool)
        out[[p.k for p in self.map_points.points() if p.k < len(out)]] = True
        return out

    def _update_frame_md(self, k: int) -> None:
        self.panel.show_frame_info(self.frame_text(k))

    def frame_text(self, k: int) -> str:
        """Frame ``k``'s status, statistics, lens note and stage times (markdown)."""
        r = self.result()
        if r is None:
            return f"Frame {k}: no registration result yet."
        rec = r.records[k]
        stats = rec.stats
        parts = [f"Frame {k}: **{escape_md(rec.status)}**"]
        if rec.status != "ok":
            parts.append(escape_md(rec.reason))
        elif rec.stage in MAP_STAGES:
            parts.append(
                "registered to the map (the reference frame)"
                if rec.stage == "inter-sensor"
                else "re-anchored to the map"
            )
        labels = {
            "n_control_points": "control points",
            "n_inliers": "kept by REQCON",
            "reqcon_iterations": "REQCON iterations",
            "residual_rms_px": "residual RMS (px)",
        }
        for name, label in labels.items():
            v = stats.get(name)
            if v is not None:
                parts.append(f"{label} {v:.3g}" if isinstance(v, float) else f"{label} {v}")
        adjustment = stats.get("adjustment")
        if isinstance(adjustment, dict):
            parts.append(adjustment_text(adjustment, rec.stage in MAP_STAGES))
        lens = stats.get("lens")
        if isinstance(lens, dict) and lens.get("reason"):
            # The reference frame's estimate of the lens beyond Harris, and whether it was used.
            parts.append("lens: " + escape_md(lens["reason"]))
        times = stats.get("time_s")
        if isinstance(times, dict):
            # Stage times; "total" is the wall time of this run's call, which is near zero for a
            # reference frame fitted beforehand in the Seed view.
            stages = [
                f"{n} {v:.2f} s"
                for n, v in times.items()
                if n != "total" and isinstance(v, int | float)
            ]
            if stages:
                parts.append("time: " + ", ".join(stages))
        return "; ".join(parts)


def flagged(record) -> str:
    """Why the sequence adjustment flagged the frame (``""``: it did not, or there was none)."""
    adjustment = record.stats.get("adjustment") if record.ok else None
    return str(adjustment.get("flagged") or "") if isinstance(adjustment, dict) else ""


def predicted_errors(records) -> np.ndarray | None:
    """Each frame's predicted error (base px) from the sequence adjustment, NaN for frames it
    did not adjust; None when it adjusted none."""
    values = [
        r.stats["adjustment"].get("predicted_error_px")
        if r.ok and isinstance(r.stats.get("adjustment"), dict) else None
        for r in records
    ]  # fmt: skip
    if all(v is None for v in values):
        return None
    return np.array([np.nan if v is None else float(v) for v in values])


def adjustment_text(adjustment: dict, to_map: bool = False) -> str:
    """A frame's outcome of the sequence adjustment, for the frame's line (markdown);
    ``to_map``: the frame's control points were measured on the map itself (the reference frame
    and re-anchored frames), not on the mid base image and the previous frame."""
    on = "the map" if to_map else "the mid base image and the previous frame"
    text = (
        f"adjusted with its neighbours: predicted error "
        f"{adjustment.get('predicted_error_px', float('nan')):.2f} base px, "
        f"{adjustment.get('n_links', 0)} link points, "
        f"{adjustment.get('n_controls', 0)} control points on {on}"
    )
    if adjustment.get("n_map_points"):
        n = adjustment["n_map_points"]
        text += (
            f", {n} map point{'s' if n > 1 else ''} of the analyst's "
            f"({adjustment['map_point_rms_px']:.2f} px from {'them' if n > 1 else 'it'})"
        )
    if adjustment.get("flagged"):
        text += f" — **flagged: {escape_md(str(adjustment['flagged']))}**"
    return text
