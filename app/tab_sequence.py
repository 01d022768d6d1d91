"""Sequence view: register every frame (paper 4.4 and 5) in the background, then review frame by frame.

"Register all frames" runs ``register_sequence`` (resuming a result folder that is partly done,
so frames already registered survive a killed server) with a progress bar and a cancel button.
For the frame under the scrubber: the frame warped into the base map (through the result's
``base_to_frame``) over the map as a blend, checkerboard or flicker; the control points' residual
vectors (scalable); the local displacement field's magnitude as a heat map (the paper's Fig. 5)
with a colour bar. Below the map, the per-frame residual RMS over the whole sequence with
excursions flagged; clicking that plot jumps to the frame (it is an image plane in the scene, so
clicks reach Python); "Jump to worst frame" does the same for the largest error.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

import numpy as np

from app import scene2d
from app.state import OVERLAYS
from app.view import GAP_PX, View
from registration import config, evaluation, pipeline

RESIDUAL_OK = (255, 220, 0)
RESIDUAL_REMOVED = (240, 50, 50)
OUTLINE = (0, 200, 255)
PLOT_W, PLOT_H = 960, 200
FLICKER_S = 0.5
PLAY_S = 0.4
WARP_CACHE_FRAMES = 12  # ~10 MB each at a 2048-px base preview


def excursion_flags(values: np.ndarray) -> np.ndarray:
    """Frames ``registration.evaluation.find_excursions`` flags as sudden excursions (bool (N,))."""
    flags = np.zeros(len(values), bool)
    if len(values) < 3:
        return flags
    for e in evaluation.find_excursions(np.arange(len(values)), values):
        flags[int(e["frame"])] = True
    return flags


class SequenceTab(View):
    MODE = "Sequence"

    def build(self) -> None:
        gui = self.gui
        self.run_md = gui.add_markdown("")
        self.btn_run = gui.add_button("Register all frames")
        self.btn_cancel = gui.add_button("Cancel", color="red", disabled=True)
        self.bar = gui.add_progress_bar(0.0, visible=False)
        self.scrub = gui.add_slider("Frame", 0, 1, 1, 0)
        self.play = gui.add_checkbox("Play", False)
        self.stage = gui.add_dropdown("Stage", ("local", "global"), initial_value="local")
        self.overlay = gui.add_dropdown("Overlay", OVERLAYS, initial_value=OVERLAYS[0])
        self.opacity = gui.add_slider("Opacity", 0.0, 1.0, 0.05, 0.5)
        self.show_vectors = gui.add_checkbox("Residual vectors", True)
        self.vec_scale = gui.add_slider("Vector scale", 1.0, 100.0, 1.0, 10.0)
        self.show_field = gui.add_checkbox("Displacement heat map (Fig. 5)", False)
        self.colourbar = gui.add_image(
            np.full((40, 320, 3), 255, np.uint8), label="|d| (base px)", visible=False
        )
        self.frame_md = gui.add_markdown("")
        self.btn_worst = gui.add_button("Jump to worst frame")
        self.btn_run.on_click(lambda ev: self.run(ev.client))
        self.btn_cancel.on_click(lambda ev: self.app.jobs.request_cancel())
        self.scrub.on_update(lambda ev: self.set_frame(int(ev.target.value)))
        self.play.on_update(lambda ev: self._play_changed())
        for h in (
            self.stage,
            self.overlay,
            self.opacity,
            self.show_vectors,
            self.vec_scale,
            self.show_field,
        ):
            h.on_update(lambda ev: self._view_changed())
        self.btn_worst.on_click(lambda ev: self.jump_to_worst())
        self.result = None
        # Recently registered frames at preview size (a played loop then costs no warping).
        self._warp_cache: OrderedDict[tuple, tuple] = OrderedDict()
        self._base_rgb: np.ndarray | None = None
        self._plot_x: tuple[int, int] = (0, 1)
        self._field_handle = None  # the heat-map node
        self._threads_stop = threading.Event()
        self._flicker_on = True
        threading.Thread(target=self._ticker, name="sequence-ticker", daemon=True).start()

    # ---------------------------------------------------------------- inputs and state
    def on_inputs(self) -> None:
        inp = self.app.inputs
        bw, bh = inp.base_size
        self.make_plane("base", bw, bh)
        # The error plot sits under the map, as wide as the map.
        ph = int(round(bw * PLOT_H / PLOT_W))
        old = self.image_planes.pop("plot", None)
        if old is not None and old.handle is not None:
            old.handle.remove()
        s = scene2d.WORLD_PER_PX
        geom = scene2d.PlaneGeometry(bw, ph, position=(bw / 2 * s, (bh + GAP_PX + ph / 2) * s, 0.0))
        self.image_planes["plot"] = scene2d.ImagePlane(self.scene, f"{self.root_name}/plot", geom)
        self._base_rgb = None
        self._warp_cache.clear()
        self.result = None
        with self.state.lock:
            k = self.state.seq_frame
            result_dir = self.state.result_dir
            self.opacity.value = self.state.opacity
            self.vec_scale.value = self.state.vector_scale
            if self.state.overlay in OVERLAYS:
                self.overlay.value = self.state.overlay
            self.stage.value = self.state.stage
        self.scrub.max = max(inp.n_frames - 1, 1)
        self.scrub.disabled = inp.n_frames <= 1
        self.scrub.value = k
        if result_dir:
            self.load_result(result_dir)
        self.update_run_text()

    def on_show(self) -> None:
        self.request_render()

    def load_result(self, out_dir) -> None:
        import registration

        try:
            result = registration.load(out_dir)
        except (OSError, ValueError) as exc:
            self.app._remember_error(f"could not open result {out_dir}: {exc}")
            self.result = None
            return
        inp = self.app.inputs
        if inp is not None and (
            result.n_frames != inp.n_frames or tuple(result.frame_size) != inp.frame_size
        ):
            self.app._remember_error(f"result {out_dir} does not match the inputs; ignored")
            self.result = None
            return
        self.result = result
        self._warp_cache.clear()

    def set_frame(self, k: int) -> None:
        with self.state.lock:
            if self.app.inputs is None:
                return
            k = int(np.clip(k, 0, self.app.inputs.n_frames - 1))
            if k == self.state.seq_frame and self.app.shown.get(self.MODE, (None,))[0] == k:
                return
            self.state.seq_frame = k
            self.state.revision += 1
        if int(self.scrub.value) != k:
            self.scrub.value = k  # runs set_frame again, which then returns early
        self.app.save()
        self.request_render()

    def _view_changed(self) -> None:
        with self.state.lock:
            self.state.opacity = float(self.opacity.value)
            self.state.vector_scale = float(self.vec_scale.value)
            self.state.overlay = str(self.overlay.value)
            self.state.stage = str(self.stage.value)
        self.app.save()
        self.request_render()

    def shutdown(self) -> None:
        self._threads_stop.set()

    def _play_changed(self) -> None:
        pass  # the ticker thread reads the checkbox

    def _ticker(self) -> None:
        """Play and flicker clocks (post render requests; never draw themselves)."""
        last_play = last_flicker = time.monotonic()
        while not self._threads_stop.wait(0.05):
            if self.state.mode != self.MODE or self.app.inputs is None:
                continue
            now = time.monotonic()
            if self.play.value and now - last_play >= PLAY_S:
                last_play = now
                with self.state.lock:
                    k = (self.state.seq_frame + 1) % max(self.app.inputs.n_frames, 1)
                self.set_frame(k)
            if self.overlay.value == "flicker" and now - last_flicker >= FLICKER_S:
                last_flicker = now
                self._flicker_on = not self._flicker_on
                self.app.worker.submit("sequence-flicker", self._apply_flicker)

    # ---------------------------------------------------------------- running
    def update_run_text(self) -> None:
        self.btn_run.disabled = False
        with self.state.lock:
            seed = self.state.seed
        r = self.result
        if r is None:
            done = "no result yet"
        else:
            st = [rec.get("status") for rec in r.records]
            done = f"{st.count('ok')} ok, {st.count('failed')} failed, {st.count('pending')} pending of {r.n_frames}"
        seed_txt = "seeded" if seed else "**no seed** (coarse step ungated)"
        self.run_md.content = f"Result: {done}; {seed_txt}."

    def run(self, client=None) -> bool:
        inp = self.app.inputs
        if inp is None:
            return False
        with self.state.lock:
            st = self.state
            seed, ref, gamma, preset = st.seed, st.reference_frame, st.gamma, st.preset
            coarse, fine = st.coarse, st.fine
            out_dir = str(self.app.project.result_dir)
            st.result_dir = out_dir
        self.app.save()
        # The Seed view's steps are reused only if made for exactly these settings.
        seed_tab = self.app.tabs["Seed"]
        current = coarse and fine and seed_tab.computed_key == seed_tab.reference_key()
        reference = (coarse, fine) if current else None

        def job(cancel) -> None:
            self.btn_cancel.disabled = False
            self.btn_run.disabled = True
            self.bar.visible = True
            self.bar.value = 0.0
            last = [0.0]

            def progress(done, total) -> None:
                self.bar.value = 100.0 * done / max(total, 1)
                now = time.monotonic()
                if now - last[0] > 1.0:  # show finished frames as they land
                    last[0] = now
                    self.load_result(out_dir)
                    self.update_run_text()
                    self.app.worker.submit("sequence-plot", self.draw_plot)

            try:
                kwargs = dict(
                    seed=seed,
                    reference_frame=ref,
                    config=config.get_preset(preset),
                    preset=preset,
                    base_path=inp.base_path,
                    resume=True,
                    progress=progress,
                    cancel=cancel,
                )
                if reference is not None:
                    kwargs["reference"] = reference
                try:
                    pipeline.register_sequence(inp.frames, inp.base, gamma, out_dir, **kwargs)
                except ValueError as exc:
                    if "cannot resume" not in str(exc):
                        raise
                    # γ, seed, reference frame or preset changed since the folder was made: keep
                    # the old result beside it and start a fresh one.
                    old = self.app.project.archive_result()
                    self.notify(
                        client,
                        "Starting a new result",
                        f"{exc}; the old one is kept in {old}",
                        "yellow",
                    )
                    self.result = None
                    pipeline.register_sequence(inp.frames, inp.base, gamma, out_dir, **kwargs)
            finally:
                self.btn_cancel.disabled = True
                self.bar.visible = False
                self.load_result(out_dir)
                self.update_run_text()
                self.request_render()
            if cancel.is_set():
                self.notify(
                    client,
                    "Registration cancelled",
                    "Frames done so far are kept; run again to continue",
                    "yellow",
                )
            else:
                self.notify(client, "Registration finished", self.run_md.content, "green")

        started = self.app.jobs.start("register", job)
        if not started:
            self.notify(client, "Busy", f"{self.app.jobs.name} is running", "yellow")
        return started

    def jump_to_worst(self) -> None:
        vals = self.error_values()
        if vals is None or not np.isfinite(vals).any():
            return
        self.set_frame(int(np.nanargmax(vals)))

    def error_values(self) -> np.ndarray | None:
        """Residual RMS (base px) per frame from the result records; NaN where not ok."""
        r = self.result
        if r is None:
            return None
        out = np.full(r.n_frames, np.nan)
        for k, rec in enumerate(r.records):
            v = (rec.get("stats") or {}).get("residual_rms_px")
            if rec.get("status") == "ok" and v is not None:
                out[k] = float(v)
        return out

    def on_click(self, plane: str, xy, client) -> None:
        """A click on the error plot jumps to that frame."""
        if plane != "plot" or self.app.inputs is None:
            return
        geom = self.image_planes["plot"].geom
        u = (xy[0] + 0.5) * PLOT_W / geom.width  # plot image column
        x0, x1 = self._plot_x
        n = self.app.inputs.n_frames
        k = int(round((u - x0) / max(x1 - x0, 1) * (n - 1)))
        self.set_frame(int(np.clip(k, 0, n - 1)))

    # ---------------------------------------------------------------- drawing (worker)
    def request_render(self) -> None:
        self.app.worker.submit("sequence", self.render)

    def base_rgb(self) -> np.ndarray:
        if self._base_rgb is None:
            self._base_rgb = scene2d.to_rgb(
                scene2d.preview(self.app.inputs.base, 2 * self.app.display_max)
            )
        return self._base_rgb

    def frame_border_in_base(self, k: int, stage: str) -> np.ndarray:
        """The raw frame's border mapped into base pixels, ``(M, 2)`` (finite points only)."""
        r = self.result
        w, h = r.frame_size
        t = np.linspace(0.0, 1.0, 33)
        border = np.concatenate(
            [
                np.stack([t * (w - 1), np.zeros_like(t)], 1),
                np.stack([np.full_like(t, w - 1), t * (h - 1)], 1),
                np.stack([(1 - t) * (w - 1), np.full_like(t, h - 1)], 1),
                np.stack([np.zeros_like(t), (1 - t) * (h - 1)], 1),
            ]
        )
        b = r.frame_to_base(k, border, stage)
        return b[np.isfinite(b).all(axis=1)]

    def registered(self, k: int, stage: str):
        """Frame ``k`` warped into the base preview: ``(rgb, valid)`` or None if not registered.

        Only the box around the frame's footprint is rendered (a frame covers a fraction of a
        large base map), then placed into a base-sized canvas.
        """
        from registration.coords import rescale
        from registration.render import render_registered

        r = self.result
        if r is None or not r.is_ok(k):
            return None
        key = (k, stage, id(r))
        if key in self._warp_cache:
            self._warp_cache.move_to_end(key)
            return self._warp_cache[key]
        base_rgb = self.base_rgb()
        hp, wp = base_rgb.shape[:2]
        f = self.app.inputs.base_size[0] / wp
        warped = np.zeros_like(base_rgb)
        valid = np.zeros((hp, wp), bool)
        border = self.frame_border_in_base(k, stage)
        if len(border):
            lo = rescale(border.min(axis=0, keepdims=True), 1.0 / f)[0]
            hi = rescale(border.max(axis=0, keepdims=True), 1.0 / f)[0]
            pad = 4  # preview px: bilinear support and the local field's small shifts
            x0, y0 = (int(max(0, np.floor(v) - pad)) for v in lo)
            x1 = int(min(wp, np.ceil(hi[0]) + pad + 1))
            y1 = int(min(hp, np.ceil(hi[1]) + pad + 1))
            if x1 > x0 and y1 > y0:
                frame = scene2d.to_rgb(self.app.inputs.frame(k))
                crop, mask = render_registered(
                    frame,
                    lambda xy: r.base_to_frame(k, rescale(xy, f), stage),
                    (x1 - x0, y1 - y0),
                    origin=(x0, y0),
                    step=8,
                    return_mask=True,
                )
                warped[y0:y1, x0:x1] = crop
                valid[y0:y1, x0:x1] = mask
        out = (warped, valid)
        self._warp_cache[key] = out
        while len(self._warp_cache) > WARP_CACHE_FRAMES:
            self._warp_cache.popitem(last=False)
        return out

    def render(self) -> None:
        from registration import viz

        inp = self.app.inputs
        if inp is None or "base" not in self.image_planes:
            return
        with self.state.lock:
            k, stage, overlay = self.state.seq_frame, self.state.stage, self.state.overlay
            alpha, vscale = self.state.opacity, self.state.vector_scale
        base_rgb = self.base_rgb()
        reg = self.registered(k, stage)
        bp = self.image_planes["base"]
        with self.app.server.atomic():
            bp.show(base_rgb)
            if reg is None:
                bp.remove("registered")
            else:
                warped, valid = reg
                if overlay == "checkerboard":
                    tile = max(8, base_rgb.shape[1] // 16)
                    img = viz.checkerboard(warped, base_rgb, tile=tile, mask=valid)
                elif overlay == "flicker":
                    img = viz.blend(warped, base_rgb, 1.0, mask=valid)
                else:
                    img = viz.blend(warped, base_rgb, alpha, mask=valid)
                bp.overlay_image("registered", img)
                if overlay == "flicker":
                    bp._overlays["registered"].visible = self._flicker_on
            self._draw_outline(k, stage)
            self._draw_vectors(k, vscale)
            self._draw_field(k)
        self.draw_plot()
        self._update_frame_md(k)
        self.app.shown[self.MODE] = (k, stage, overlay, reg is not None)

    def _apply_flicker(self) -> None:
        h = self.image_planes.get("base")
        if h is not None and h.has("registered"):
            h._overlays["registered"].visible = self._flicker_on

    def _draw_outline(self, k: int, stage: str) -> None:
        """The frame's border mapped into the map (where the registered frame lies)."""
        bp = self.image_planes["base"]
        r = self.result
        if r is None or not r.is_ok(k):
            bp.remove("outline")
            return
        b = self.frame_border_in_base(k, stage)
        s, e = scene2d.polyline_segments(b)
        bp.segments("outline", s, e, OUTLINE, width=2.0)

    def _draw_vectors(self, k: int, scale: float) -> None:
        bp = self.image_planes["base"]
        r = self.result
        cps = (
            r.control_points(k)
            if (r is not None and r.is_ok(k) and self.show_vectors.value)
            else None
        )
        if cps is None:
            bp.remove("residuals")
            return
        src, dst, kept, _ = cps
        pred = r.frame_to_base(k, r.harris.raw_from_corrected(src), "global")
        ok = np.isfinite(pred).all(axis=1) & np.isfinite(dst).all(axis=1)
        tip = dst + scale * (pred - dst)
        cols = np.where(kept[:, None], RESIDUAL_OK, RESIDUAL_REMOVED).astype(np.uint8)
        bp.segments("residuals", dst[ok], tip[ok], cols[ok], width=2.0)

    def _draw_field(self, k: int) -> None:
        from registration import viz

        bp = self.image_planes["base"]
        r = self.result
        fld = r.field(k) if (r is not None and r.is_ok(k) and self.show_field.value) else None
        name = f"{self.root_name}/field"
        if fld is None:
            if self._field_handle is not None:
                self._field_handle.remove()
                self._field_handle = None
            self.colourbar.visible = False
            return
        rgba, vmax = viz.field_cells_image(fld.vectors, fld.valid)
        x0, y0, x1, y1 = fld.extent
        geom = bp.geom
        s = geom.scale
        # extent is in base pixel coordinates; its centre maps to the world like any base point.
        centre = geom.world_from_pixel(
            np.array([(x0 + x1) / 2.0, (y0 + y1) / 2.0]), dz=scene2d.OVERLAY_DZ * 0.75
        )
        # Upsample a little (nearest) so each cell is a crisp square in the texture.
        big = np.repeat(np.repeat(rgba, 8, axis=0), 8, axis=1)
        self._field_handle = self.scene.add_image(
            name,
            big,
            (x1 - x0) * s,
            (y1 - y0) * s,
            format="png",
            position=tuple(centre),
            cast_shadow=False,
            receive_shadow=False,
        )
        self.colourbar.image = viz.colorbar(0.0, vmax, label="local displacement |d| (base px)")
        self.colourbar.visible = True

    def draw_plot(self) -> None:
        from registration import viz

        vals = self.error_values()
        plane = self.image_planes.get("plot")
        if plane is None:
            return
        with self.state.lock:
            k = self.state.seq_frame
        if vals is None:
            plane_img = np.full((PLOT_H, PLOT_W, 3), 255, np.uint8)
            self._plot_x = (40, PLOT_W - 10)
        else:
            plane_img, self._plot_x = viz.series_plot(
                vals,
                flagged=excursion_flags(vals),
                current=k,
                width=PLOT_W,
                height=PLOT_H,
                label="residual RMS per frame (base px); red = excursion; click to jump",
            )
        plane.show(plane_img)

    def _update_frame_md(self, k: int) -> None:
        r = self.result
        if r is None:
            self.frame_md.content = f"Frame {k}: no registration result yet."
            return
        rec = r.records[k]
        stats = rec.get("stats") or {}
        parts = [f"Frame {k}: **{rec.get('status')}**"]
        if rec.get("status") != "ok":
            parts.append(str(rec.get("reason", "")))
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
        t = stats.get("time_s")
        if isinstance(t, dict) and "total" in t:
            t = t["total"]
        if isinstance(t, int | float):
            parts.append(f"time {t:.2f} s")
        self.frame_md.content = "; ".join(parts)
