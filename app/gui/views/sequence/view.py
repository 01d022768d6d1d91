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
*Export* folder writes the result as GIS files and video (``app/views/export.py``).

Scrubbing is fast because the frame is warped at display resolution from a preview of the frame
(decoded ahead by :meth:`app.gui.inputs.Inputs.prefetch`) and only its footprint is encoded and sent.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict

import numpy as np

from app.gui import calls, controlpoints, scene2d
from app.gui.security import escape_md
from app.gui.state import OVERLAYS
from app.gui.views.base import View
from app.gui.views.sequence.export import Exporter
from app.gui.views.sequence.panel import (
    FLICKER_S,
    PLAY_S,
    RESIDUAL_OK,
    RESIDUAL_REMOVED,
    SETTLE_S,
    WARP_CACHE_FRAMES,
    SequencePanel,
    SequenceScene,
    excursion_flags,
)
from registration.run import pipeline

log = logging.getLogger(__name__)


class SequenceView(View):
    MODE = "Sequence"
    CLICKABLE = ("base",)

    def make_scene(self, scene, root_name):
        return SequenceScene(scene, root_name)

    def make_panel(self, gui):
        return SequencePanel(gui)

    def connect(self) -> None:
        p = self.panel
        p.btn_run.on_click(lambda ev: self.run(ev.client))
        p.scrub.on_update(lambda ev: self.set_frame(int(ev.target.value)))
        p.jump.on_click(lambda ev: self.jump(ev.target.value))
        p.btn_rerun.on_click(lambda ev: self.rerun_frame(ev.client))
        for h in (
            p.stage,
            p.overlay,
            p.opacity,
            p.show_vectors,
            p.show_outliers,
            p.vec_scale,
            p.show_field,
        ):
            h.on_update(lambda ev: self._view_changed())
        cps = p.cps
        cps.sort.on_update(lambda ev: self.show_table())
        cps.page.on_click(lambda ev: self.turn_page(-1 if "previous" in ev.target.value else 1))
        cps.selected.on_update(lambda ev: self.select_point(int(ev.target.value), ev.client))
        cps.actions.on_click(lambda ev: self.centre_on_selected(ev.client))
        cps.export.on_click(lambda ev: self.export_points(ev.client))
        self.exporter = Exporter(self.app, p.export)
        self.app.events.on("cp-select:seq", lambda v, client: self.select_point(int(v), client))
        self.app.events.on("plot-frame", lambda v, client: self.set_frame(int(v)))
        self.app.events.on("seq-frame", lambda v, client: self.set_frame(int(v)))
        # Recently shown frames at display size (a played loop then costs no warping).
        self._warp_cache: OrderedDict[tuple, tuple] = OrderedDict()
        self._cache_lock = threading.Lock()  # the worker and the settle thread both warp
        self._threads_stop = threading.Event()
        self._flicker_on = True
        self._settle_timer: threading.Timer | None = None
        self._settle_lock = threading.Lock()
        self._requested: int | None = None  # the frame last asked to be drawn
        self._tables: OrderedDict[tuple, object] = OrderedDict()  # (k, id(result)) -> table
        self.table: controlpoints.ControlPointTable | None = None
        self.table_frame: int | None = None
        self.selected: int | None = None
        threading.Thread(target=self._ticker, name="sequence-ticker", daemon=True).start()

    # ---------------------------------------------------------------- inputs and state
    def on_inputs(self) -> None:
        inp = self.app.inputs
        self.scene.layout(inp.base_size)
        self.clear_cache()
        self.table = None
        with self.state.lock:
            st = self.state
            k, result_dir = st.seq_frame, st.result_dir
            st.result = None
            p = self.panel
            p.opacity.value = st.opacity
            p.vec_scale.value = st.vector_scale
            if st.overlay in OVERLAYS:
                p.overlay.value = st.overlay
            p.stage.value = st.stage
        p.scrub.max = max(inp.n_frames - 1, 1)
        p.scrub.disabled = inp.n_frames <= 1
        p.scrub.value = k
        if result_dir:
            self.load_result(result_dir)
        self.refresh_text()

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
            self.app.record_error(f"could not open result {out_dir}: {exc}")
            result = None
        inp = self.app.inputs
        if (
            result is not None
            and inp is not None
            and (result.n_frames != inp.n_frames or tuple(result.frame_size) != inp.frame_size)
        ):
            self.app.record_error(f"result {out_dir} does not match the inputs; ignored")
            result = None
        with self.state.lock:
            self.state.result = result
        self.clear_cache()
        self.table = None

    def clear_cache(self) -> None:
        """Forget the frames warped so far (benchmarks measure the cold path)."""
        with self._cache_lock:
            self._warp_cache.clear()
        self._tables.clear()

    def result(self):
        with self.state.lock:
            return self.state.result

    def set_frame(self, k: int) -> None:
        with self.state.lock:
            if self.app.inputs is None:
                return
            k = int(np.clip(k, 0, self.app.inputs.n_frames - 1))
            if k == self.state.seq_frame and self._requested == k:
                return  # e.g. the scrubber's own callback after we moved it
            self.state.seq_frame = k
            self._requested = k
            self.state.revision += 1
        if int(self.panel.scrub.value) != k:
            self.panel.scrub.value = k  # runs set_frame again, which then returns early
        self.app.save(soon=True)
        self.request_render()

    def _view_changed(self) -> None:
        p = self.panel
        with self.state.lock:
            self.state.opacity = float(p.opacity.value)
            self.state.vector_scale = float(p.vec_scale.value)
            self.state.overlay = str(p.overlay.value)
            self.state.stage = str(p.stage.value)
        self.app.save()
        self.request_render()

    def shutdown(self) -> None:
        self._threads_stop.set()
        with self._settle_lock:
            if self._settle_timer is not None:
                self._settle_timer.cancel()

    def _ticker(self) -> None:
        """Play and flicker clocks (post render requests; never draw themselves)."""
        last_play = last_flicker = time.monotonic()
        while not self._threads_stop.wait(0.05):
            if not self.visible or self.app.inputs is None:
                continue
            now = time.monotonic()
            if self.panel.play.value and now - last_play >= PLAY_S:
                last_play = now
                with self.state.lock:
                    k = (self.state.seq_frame + 1) % max(self.app.inputs.n_frames, 1)
                self.set_frame(k)
            if self.panel.overlay.value == "flicker" and now - last_flicker >= FLICKER_S:
                last_flicker = now
                self._flicker_on = not self._flicker_on
                self.submit("flicker", lambda: self.scene.set_registered_visible(self._flicker_on))

    # ---------------------------------------------------------------- running
    def refresh_text(self) -> None:
        with self.state.lock:
            st = self.state
            seed, r, transform, local = st.seed, st.result, st.transform, st.run_local
            ref_ok = st.current_reference() is not None and st.current_reference().fine
            preset = st.preset
        if r is None:
            done = "no result yet"
        else:
            s = [rec.get("status") for rec in r.records]
            done = (
                f"{s.count('ok')} ok, {s.count('failed')} failed, {s.count('pending')} pending "
                f"of {r.n_frames}"
            )
        seed_txt = "seeded" if seed else "**no seed**: the coarse step searches without a gate"
        ref_txt = (
            "reference fitted in the Seed view" if ref_ok else "the reference frame is fitted first"
        )
        self.panel.run_md.content = (
            f"Result: {done}; {seed_txt}; {ref_txt}.  \nRun settings: preset {escape_md(preset)}, "
            f"{escape_md(transform)}, local field {'on' if local else 'off'} (Seed view)."
        )
        self.exporter.refresh()
        if r is not None:
            failed = [
                (k, str(rec.get("reason", "")))
                for k, rec in enumerate(r.records)
                if rec.get("status") == "failed"
            ]
            self.panel.show_failed(failed)
        else:
            self.panel.show_failed([])

    def run(self, client=None) -> bool:
        inp = self.app.inputs
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
            cfg = calls.pipeline_config(preset, st.degree, st.run_local)
            out_dir = str(self.app.project.result_dir)
            st.result_dir = out_dir
        self.app.save()

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

            kwargs = dict(
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
            try:
                try:
                    pipeline.register_sequence(inp.frames, inp.base, gamma, out_dir, **kwargs)
                except ValueError as exc:
                    if "cannot resume" not in str(exc):
                        raise
                    # γ, seed, reference frame or settings changed since the folder was made:
                    # keep the old result beside it and start a fresh one.
                    old = self.app.project.archive_result()
                    self.notify(
                        client,
                        "Starting a new result",
                        f"{exc}; the old one is kept in {old}",
                        "yellow",
                    )
                    with self.state.lock:
                        self.state.result = None
                    pipeline.register_sequence(inp.frames, inp.base, gamma, out_dir, **kwargs)
            finally:
                self.load_result(out_dir)
                self.refresh_text()
                self.app.state_changed()
                self.request_render()
            if progress.cancel.is_set():
                self.notify(
                    client,
                    "Registration cancelled",
                    "Frames done so far are kept; run again to continue",
                    "yellow",
                )
            else:
                self.notify(
                    client,
                    "Registration finished",
                    self.panel.run_md.content.split("  \n")[0],
                    "green",
                )

        return self.app.run_job("register", job, client)

    def rerun_frame(self, client=None) -> bool:
        """Register the frame under the scrubber again with its result's own settings."""
        r = self.result()
        inp = self.app.inputs
        with self.state.lock:
            k = self.state.seq_frame
        if r is None or inp is None:
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
        settings = calls.rerun_settings(r)
        out_dir = str(r.out_dir)

        def job(progress) -> None:
            progress(0, 1, f"frame {k}")
            calls.forget_frame(out_dir, k)
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
            )
            self.load_result(out_dir)
            self.refresh_text()
            self.app.state_changed()
            self.request_render()
            rec = self.result().records[k]
            self.notify(
                client,
                f"Frame {k} registered again",
                f"{rec.get('status')} {rec.get('reason', '')}",
                "green",
            )

        return self.app.run_job(f"register frame {k}", job, client)

    def jump(self, which: str) -> None:
        r = self.result()
        if r is None:
            return
        if which.startswith("worst"):
            vals = self.error_values()
            if vals is not None and np.isfinite(vals).any():
                self.set_frame(int(np.nanargmax(vals)))
            return
        with self.state.lock:
            k0 = self.state.seq_frame
        failed = [k for k, rec in enumerate(r.records) if rec.get("status") == "failed"]
        if failed:
            later = [k for k in failed if k > k0]
            self.set_frame(later[0] if later else failed[0])

    def jump_to_worst(self) -> None:
        self.jump("worst frame")

    def error_values(self) -> np.ndarray | None:
        """Residual RMS (base px) per frame from the result records; NaN where not ok."""
        r = self.result()
        if r is None:
            return None
        out = np.full(r.n_frames, np.nan)
        for k, rec in enumerate(r.records):
            v = (rec.get("stats") or {}).get("residual_rms_px")
            if rec.get("status") == "ok" and v is not None:
                out[k] = float(v)
        return out

    def on_click(self, plane: str, xy, client) -> None:
        """A click on the map selects the nearest control point of the frame shown."""
        t = self.table
        if t is None or not len(t.ids):
            return
        d = np.hypot(*(t.base_xy - np.asarray(xy, float)).T)
        i = int(np.nanargmin(d))
        limit = 20 * self.scene.planes["base"].px_per_screen
        if d[i] <= limit:
            self.select_point(int(t.ids[i]), client)

    # ---------------------------------------------------------------- control points
    def control_point_table(self, k: int):
        """The read-only table of frame ``k``'s control points from the result, or None."""
        from registration.run import records

        r = self.result()
        if r is None or not r.is_ok(k):
            return None
        cps = r.control_points(k)
        if cps is None:
            return None
        src, dst, kept, _ = cps
        source = None
        path = records.frame_record_path(r.out_dir, k, ".npz")
        try:
            with np.load(path) as z:
                source = z["source"] if "source" in z.files else None
        except (OSError, ValueError):
            source = None
        kind = (
            "reference"
            if k == r.reference_frame
            else str(r.config.get("intra", {}).get("control_points", "template"))
        )
        return controlpoints.table_from_points(src, dst, kept, source, kind, r.lens, r.model(k))

    def show_table(self) -> None:
        note = "Read-only: edit the reference frame's points in the Seed view; a frame can be registered again."
        if self.table is None:
            self.panel.cps.show(None, None, "No control points for this frame.")
        else:
            self.panel.cps.show(self.table, self.selected, note)

    def turn_page(self, direction: int) -> None:
        if self.table is not None:
            self.panel.cps.turn(direction, len(self.table.ids))
            self.show_table()

    def select_point(self, row_id: int, client=None) -> None:
        t = self.table
        if t is None or row_id < 0 or t.row(row_id) is None:
            return
        self.selected = int(row_id)
        offset = self.panel.cps.offset_for(t, row_id)
        if offset is not None:
            self.panel.cps.offset = offset
        if int(self.panel.cps.selected.value) != row_id:
            self.panel.cps.selected.value = row_id
        self.show_table()
        self.submit("selected", lambda: self.scene.draw_selected(t.base_xy[t.row(row_id)]))
        self.centre_on_selected(client)

    def centre_on_selected(self, client=None) -> None:
        t = self.table
        i = None if t is None or self.selected is None else t.row(self.selected)
        if i is None:
            return
        geom = self.scene.planes["base"].geom
        c = geom.world_from_pixel(t.base_xy[i])
        region = scene2d.PlaneGeometry(300, 225, position=(c[0], c[1], 0.0), scale=geom.scale)
        self.app.focus([region], client)

    def export_points(self, client=None) -> bool:
        """This frame's table as QGIS ``.points`` (see the Seed view's), sent to the browser."""
        if self.table is None:
            self.notify(client, "No control points", "This frame has none", "yellow")
            return False
        with self.state.lock:
            k = self.state.seq_frame
        path = self.app.project.folder / f"frame_{k:06d}.points"
        controlpoints.write_qgis_points(self.table, path, self.app.inputs.base_georef)
        return self.app.offer_file(path, client)

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
            self.registered(k, stage, 2 * self.app.display_max)
        except Exception:  # drawn (and reported) by the worker's render instead
            log.debug("settle warp of frame %d failed", k, exc_info=True)
        # Its own key: a stale settle render must never replace a newer scrub's request.
        self.submit("render-full", lambda: self.render(full=True, rev=rev))

    def frame_border_in_base(self, k: int, stage: str) -> np.ndarray:
        """The raw frame's border mapped into base pixels, ``(M, 2)`` (finite points only)."""
        from registration.coords import frame_outline

        r = self.result()
        b = r.frame_to_base(k, frame_outline(*r.frame_size), stage)
        return b[np.isfinite(b).all(axis=1)]

    def registered(self, k: int, stage: str, side: int | None = None):
        """Frame ``k`` warped into a preview of the map whose longer side is ``side`` px
        (default: the map shown, twice the display size): ``(rgb, valid, box)`` with ``box`` =
        the frame's footprint ``(x0, y0, x1, y1)`` in full base pixels (edges, floats), or None.

        Only the footprint is rendered, from a preview of the frame of about its size there
        (decoded ahead by the read-ahead), so a new frame costs a small warp."""
        from registration.coords import rescale
        from registration.geometry import warp_image
        from registration.render import render_registered

        r = self.result()
        if r is None or not r.is_ok(k):
            return None
        side = side or 2 * self.app.display_max
        key = (k, stage, side, id(r))
        with self._cache_lock:
            if key in self._warp_cache:
                self._warp_cache.move_to_end(key)
                return self._warp_cache[key]
        inp = self.app.inputs
        hp, wp = inp.base_preview(side).shape[:2]
        f = (inp.base_size[0] / wp, inp.base_size[1] / hp)  # full base px per preview px
        border = self.frame_border_in_base(k, stage)
        if not len(border):
            return None
        lo = rescale(border.min(axis=0, keepdims=True), (1.0 / f[0], 1.0 / f[1]))[0]
        hi = rescale(border.max(axis=0, keepdims=True), (1.0 / f[0], 1.0 / f[1]))[0]
        pad = 4  # preview px: bilinear support and the local field's small shifts
        x0, y0 = (int(max(0, np.floor(v) - pad)) for v in lo)
        x1 = int(min(wp, np.ceil(hi[0]) + pad + 1))
        y1 = int(min(hp, np.ceil(hi[1]) + pad + 1))
        if x1 <= x0 or y1 <= y0:
            return None
        frame = inp.preview(k, self.frame_preview_side(x1 - x0, y1 - y0))
        f_frame = (frame.shape[1] / r.frame_size[0], frame.shape[0] / r.frame_size[1])

        def frame_from_base(xy):
            raw = r.base_to_frame(k, rescale(xy, f), stage)
            return rescale(raw, f_frame)

        rgb = scene2d.to_rgb(frame)
        if side >= 2 * self.app.display_max:
            crop, mask = render_registered(
                rgb, frame_from_base, (x1 - x0, y1 - y0), origin=(x0, y0), step=8, return_mask=True
            )
        else:
            # Scrubbing: the mapping on a 16 px lattice and no exact evaluation of the frame's
            # border band (up to 16 preview px of the border stay empty until the settle render).
            crop, mask = warp_image(
                rgb, frame_from_base, x1 - x0, y1 - y0, origin=(x0, y0), step=16
            )
        # Corner coordinates scale linearly: preview edge x0 is full-base edge x0 * f.
        box = (x0 * f[0], y0 * f[1], x1 * f[0], y1 * f[1])
        out = (crop, mask, box)
        with self._cache_lock:
            self._warp_cache[key] = out
            while len(self._warp_cache) > WARP_CACHE_FRAMES:
                self._warp_cache.popitem(last=False)
        return out

    def frame_preview_side(self, width: int, height: int) -> int:
        """Longer side of the frame preview to warp into a ``width x height`` footprint: a
        little more than the footprint (in steps of 256 px, so the read-ahead can guess it)."""
        need = int(np.ceil(max(width, height) * 1.2 / 256.0)) * 256
        return max(need, 512)

    def render(self, full: bool = False, rev: int | None = None) -> None:
        from registration.render import viz

        inp = self.app.inputs
        if inp is None or "base" not in self.scene.planes:
            return
        with self.state.lock:
            st = self.state
            k, stage, overlay = st.seq_frame, st.stage, st.overlay
            alpha, cur = st.opacity, st.revision
        if rev is not None and rev != cur:
            return  # the scrubber moved on: this settle render is stale
        fine_side = 2 * self.app.display_max
        r0 = self.result()
        have_fine = r0 is not None and (k, stage, fine_side, id(r0)) in self._warp_cache
        side = fine_side if (full or have_fine) else self.app.display_max
        if (
            full
            and self.app.shown.get(self.MODE, (None,) * 5)[:2] == (k, stage)
            and self.app.shown[self.MODE][4] == side
        ):
            return  # already shown at full resolution
        base_rgb = inp.base_preview(fine_side)
        reg = self.registered(k, stage, side)
        under_rgb = inp.base_preview(side)
        with self.app.server.atomic():
            self.scene.show_base(base_rgb)
            if reg is None:
                self.scene.show_registered(None, None)
            else:
                crop, mask, box = reg
                hp, wp = under_rgb.shape[:2]
                f = (self.app.inputs.base_size[0] / wp, self.app.inputs.base_size[1] / hp)
                x0, y0 = int(round(box[0] / f[0])), int(round(box[1] / f[1]))
                under = under_rgb[y0 : y0 + crop.shape[0], x0 : x0 + crop.shape[1]]
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
            self.scene.draw_outline(self.frame_border_in_base(k, stage) if ok else None)
            self._frame_table(k)
            self._draw_vectors()
            self._draw_field(k)
        self.draw_plot()
        self._update_frame_md(k)
        self.app.shown[self.MODE] = (k, stage, overlay, reg is not None, side)
        if not full:
            footprint = (0, 0) if reg is None else (reg[0].shape[1], reg[0].shape[0])
            guess = self.frame_preview_side(*footprint) if reg is not None else self.app.display_max
            inp.prefetch([k + 1, k - 1, k + 2], preview_sides=(guess,))

    def _frame_table(self, k: int) -> None:
        if self.table_frame != k or self.table is None:
            key = (k, id(self.result()))
            if key not in self._tables:
                self._tables[key] = self.control_point_table(k)
                while len(self._tables) > WARP_CACHE_FRAMES:
                    self._tables.popitem(last=False)
            self.table = self._tables[key]
            self.table_frame = k
            self.selected = None
            self.panel.cps.offset = 0
            self.scene.draw_selected(None)
            self.show_table()

    def _draw_vectors(self) -> None:
        t = self.table
        if t is None or not self.panel.show_vectors.value or t.model is None:
            self.scene.draw_vectors(None)
            return
        ok = np.isfinite(t.residual) & (t.enabled | bool(self.panel.show_outliers.value))
        scale = float(self.panel.vec_scale.value) or scene2d.auto_vector_scale(
            t.residual[t.enabled], self.scene.planes["base"].geom.width
        )
        self.vector_scale_used = scale
        cols = np.where(t.enabled[:, None], RESIDUAL_OK, RESIDUAL_REMOVED).astype(np.uint8)
        start = t.base_xy[ok]
        self.scene.draw_vectors((start, start + scale * t.residual_xy[ok], cols[ok]))

    def _draw_field(self, k: int) -> None:
        from registration.render import viz

        r = self.result()
        fld = r.field(k) if (r is not None and r.is_ok(k) and self.panel.show_field.value) else None
        if fld is None:
            self.scene.draw_field(None, None)
            self.panel.colourbar.visible = False
            return
        rgba, vmax = viz.field_cells_image(fld.vectors, fld.valid)
        self.scene.draw_field(rgba, fld.extent)
        self.panel.colourbar.image = viz.colorbar(
            0.0, vmax, label="local displacement |d| (base px)"
        )
        self.panel.colourbar.visible = True

    def draw_plot(self) -> None:
        vals = self.error_values()
        r = self.result()
        with self.state.lock:
            k = self.state.seq_frame
        if vals is None or r is None:
            return
        failed = np.array([rec.get("status") == "failed" for rec in r.records])
        self.panel.show_plot(vals, excursion_flags(vals), failed, k)

    def _update_frame_md(self, k: int) -> None:
        r = self.result()
        if r is None:
            self.panel.frame_md.content = f"Frame {k}: no registration result yet."
            return
        rec = r.records[k]
        stats = rec.get("stats") or {}
        parts = [f"Frame {k}: **{escape_md(rec.get('status'))}**"]
        if rec.get("status") != "ok":
            parts.append(escape_md(rec.get("reason", "")))
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
        self.panel.frame_md.content = "; ".join(parts)
