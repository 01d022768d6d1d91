"""Seed view: one click on the frame, one on the map, then the coarse and fine steps (paper 4.3).

The reference frame (radially corrected with the project's γ) and the base map lie side by side.
The first click on the frame and the first on the map make the seed correspondence (a new click
on the same image replaces its point). "Run coarse step" calls
``global_registration.coarse_register``; the match view draws its SIFT matches as segments
between the images (RANSAC inliers green, gated outliers red, matches outside the gate grey),
the gate circle on the map, and the counts the paper reports. "Run fine step" calls
``global_registration.fine_register_reference``: the template grid points (kept green, removed by
REQCON red), their residual vectors on the map (scalable), and the reference frame warped into
the map (the mid base image) over the map with an opacity slider.
"""

from __future__ import annotations

import numpy as np

from app import scene2d
from app.view import GAP_PX, View
from registration import config, distortion, global_registration

INLIER = (40, 230, 60)
OUTLIER = (240, 50, 50)
UNGATED = (150, 150, 150)
SEED_FRAME = (255, 230, 0)
SEED_BASE = (255, 0, 255)
KEPT = (40, 230, 60)
REMOVED = (240, 50, 50)
RESIDUAL = (255, 220, 0)


class SeedTab(View):
    MODE = "Seed"

    def build(self) -> None:
        gui = self.gui
        self.ref_slider = gui.add_slider("Reference frame", 0, 1, 1, 0)
        self.seed_md = gui.add_markdown(
            "Click a point on the frame (left), then the same point on the map (right)."
        )
        self.btn_clear = gui.add_button("Clear seed")
        self.preset = gui.add_dropdown("Preset", ("default", "paper"), initial_value="default")
        self.btn_coarse = gui.add_button("Run coarse step")
        self.show_ungated = gui.add_checkbox("Show matches outside the gate", False)
        self.coarse_md = gui.add_markdown("")
        self.btn_fine = gui.add_button("Run fine step")
        self.show_template_matches = gui.add_checkbox("Show template matches as lines", False)
        self.fine_md = gui.add_markdown("")
        self.vec_scale = gui.add_slider("Residual vector scale", 1.0, 100.0, 1.0, 10.0)
        self.mid_opacity = gui.add_slider("Mid base image opacity", 0.0, 1.0, 0.05, 0.0)
        self.ref_slider.on_update(lambda ev: self.set_reference(int(ev.target.value)))
        self.btn_clear.on_click(lambda ev: self.clear_seed())
        self.preset.on_update(lambda ev: self.set_preset(ev.target.value))
        self.btn_coarse.on_click(lambda ev: self.run_coarse(ev.client))
        self.btn_fine.on_click(lambda ev: self.run_fine(ev.client))
        self.show_ungated.on_update(lambda ev: self.request_overlays())
        self.show_template_matches.on_update(lambda ev: self.request_overlays())
        self.vec_scale.on_update(lambda ev: self.request_overlays())
        self.mid_opacity.on_update(lambda ev: self.app.worker.submit("seed-mid", self.draw_mid))
        self._mid_cache: tuple | None = None  # (key, warped rgb, valid) of the mid base image
        self._base_rgb: np.ndarray | None = None
        self._matches = None  # the match-lines node
        self._template_lines = None  # the fine step's template-match lines node
        self.computed_key: dict | None = None  # reference_key() the coarse/fine results are for

    # ---------------------------------------------------------------- inputs and state
    def on_inputs(self) -> None:
        inp = self.app.inputs
        w, h = inp.frame_size
        bw, bh = inp.base_size
        self.make_plane("frame", w, h)
        self.make_plane("base", bw, bh, x_offset=w + GAP_PX)
        self._base_rgb = None
        self._mid_cache = None
        self.preset.options = tuple(config.PRESETS)
        with self.state.lock:
            ref, preset = self.state.reference_frame, self.state.preset
        if preset in self.preset.options:
            self.preset.value = preset
        self.ref_slider.max = max(inp.n_frames - 1, 1)
        self.ref_slider.disabled = inp.n_frames <= 1
        self.ref_slider.value = ref
        self.restore_reference()
        self.update_text()

    # ---------------------------------------------------------------- persistence of the steps
    def reference_key(self) -> dict:
        """What the coarse and fine results depend on (besides the inputs)."""
        with self.state.lock:
            st = self.state
            return {
                "gamma": float(st.gamma),
                "seed": None if st.seed is None else [float(v) for v in st.seed],
                "reference_frame": int(st.reference_frame),
                "preset": st.preset,
            }

    def save_reference(self) -> None:
        from app.project import REFERENCE_FILE, reference_to_bytes

        with self.state.lock:
            coarse, fine = self.state.coarse, self.state.fine
        if coarse is None:
            return
        self.app.project.write_file(
            REFERENCE_FILE, reference_to_bytes(self.computed_key, coarse, fine)
        )

    def restore_reference(self) -> None:
        """Bring back the coarse/fine results saved for exactly the current γ, seed, frame, preset."""
        from app.project import REFERENCE_FILE, reference_from_file

        path = self.app.project.folder / REFERENCE_FILE
        loaded = reference_from_file(path) if path.exists() else None
        if loaded is None or loaded[0] != self.reference_key():
            return
        self.computed_key, coarse, fine = loaded
        with self.state.lock:
            self.state.coarse, self.state.fine = coarse, fine
        with self.state.lock:
            no_seed = self.state.seed is None
        self.show_coarse_text(coarse, no_seed)
        if fine is not None:
            self.show_fine_text(fine)

    def on_show(self) -> None:
        self.update_text()
        self.app.worker.submit("seed-images", self.draw_images)

    def set_reference(self, k: int) -> None:
        with self.state.lock:
            if self.app.inputs is None or k == self.state.reference_frame:
                return
            self.state.reference_frame = int(np.clip(k, 0, self.app.inputs.n_frames - 1))
            self.state.seed_frame = None
            self.state.coarse = self.state.fine = None
            self.state.revision += 1
        self._mid_cache = None
        self.app.save()
        self.update_text()
        self.app.worker.submit("seed-images", self.draw_images)

    def set_preset(self, name: str) -> None:
        with self.state.lock:
            self.state.preset = str(name)
        self.app.save()

    def clear_seed(self) -> None:
        with self.state.lock:
            self.state.seed_frame = self.state.seed_base = None
            self.state.revision += 1
        self.app.save()
        self.update_text()
        self.request_overlays()

    def on_click(self, plane: str, xy, client) -> None:
        """Frame click: corrected pixel -> raw pixel (the seed is in raw pixels); map click: base."""
        xy = np.asarray(xy, float)
        with self.state.lock:
            if plane == "frame":
                model = distortion.HarrisModel(self.state.gamma, *self.app.inputs.frame_size)
                raw = model.raw_from_corrected(xy[None])[0]
                if not np.isfinite(raw).all():
                    return
                self.state.seed_frame = (float(raw[0]), float(raw[1]))
            elif plane == "base":
                self.state.seed_base = (float(xy[0]), float(xy[1]))
            else:
                return
            self.state.revision += 1
        self.app.save()
        self.update_text()
        self.request_overlays()

    def update_text(self) -> None:
        with self.state.lock:
            f, b = self.state.seed_frame, self.state.seed_base
            g = self.state.gamma
        ftxt = f"({f[0]:.1f}, {f[1]:.1f})" if f else "—"
        btxt = f"({b[0]:.1f}, {b[1]:.1f})" if b else "—"
        hint = "" if (f and b) else "  \n_Click the frame (left), then the map (right)._"
        self.seed_md.content = f"Seed: frame (raw px) {ftxt} → map {btxt}; γ = {g:.4f}{hint}"

    # ---------------------------------------------------------------- jobs
    def _config(self):
        with self.state.lock:
            name = self.state.preset
        return config.get_preset(name)

    def run_coarse(self, client=None) -> bool:
        inp = self.app.inputs
        if inp is None:
            return False
        with self.state.lock:
            seed, ref, gamma = self.state.seed, self.state.reference_frame, self.state.gamma
        key = self.reference_key()

        def job(cancel) -> None:
            self.coarse_md.content = "Running the coarse step ..."
            coarse = global_registration.coarse_register(
                inp.frame(ref), inp.base, gamma, seed, self._config()
            )
            with self.state.lock:
                self.state.coarse, self.state.fine = coarse, None
                self.state.revision += 1
            self.computed_key = key
            self._mid_cache = None
            self.show_coarse_text(coarse, seed is None)
            self.save_reference()
            if not coarse:
                self.notify(client, "Coarse step failed", coarse.reason, "red")
            self.request_overlays()

        started = self.app.jobs.start("coarse step", job)
        if not started:
            self.notify(client, "Busy", f"{self.app.jobs.name} is running", "yellow")
        return started

    def show_coarse_text(self, c, no_seed: bool) -> None:
        if no_seed:
            gate = "no location gate (no seed)"
        elif c.gate_radius_base is not None:
            gate = f"gated around the seed (radius {c.gate_radius_base:.0f} px on the map)"
        else:
            gate = "gated by the seed"
        self.coarse_md.content = (
            "| keypoints frame | keypoints map | matches | gated | inliers |\n|---|---|---|---|---|\n"
            f"| {c.n_keypoints_frame} | {c.n_keypoints_base} | {c.n_matches} | {int(c.gated.sum())} "
            f"| {c.n_inliers} |\n\n{gate}; {c.time_s:.2f} s"
            + ("" if c else f"\n\n**Failed:** {c.reason}")
        )

    def show_fine_text(self, fine) -> None:
        n, kept = len(fine.src), int(fine.kept.sum())
        self.fine_md.content = (
            f"{n} template control points, REQCON kept {kept}, removed {n - kept}; "
            f"{fine.iterations} iterations; residual RMS {fine.residual_rms_px:.2f} px; "
            f"{fine.time_s:.2f} s" + ("" if fine else f"\n\n**Failed:** {fine.reason}")
        )

    def run_fine(self, client=None) -> bool:
        inp = self.app.inputs
        with self.state.lock:
            coarse, ref, gamma = self.state.coarse, self.state.reference_frame, self.state.gamma
        if inp is None:
            return False
        if coarse and self.computed_key != self.reference_key():
            self.notify(
                client,
                "Settings changed",
                "γ, the seed, the reference frame or the preset changed since the coarse step: "
                "run the coarse step again",
                "yellow",
            )
            return False
        if not coarse:
            self.notify(
                client,
                "Run the coarse step first",
                "The fine step starts from a successful coarse step",
                "yellow",
            )
            return False

        def job(cancel) -> None:
            self.fine_md.content = "Running the fine step ..."
            fine = global_registration.fine_register_reference(
                inp.frame(ref), inp.base, gamma, coarse, self._config()
            )
            with self.state.lock:
                self.state.fine = fine
                self.state.revision += 1
            self._mid_cache = None
            self.show_fine_text(fine)
            self.save_reference()
            if not fine:
                self.notify(client, "Fine step failed", fine.reason, "red")
            self.request_overlays()
            if self.mid_opacity.value == 0.0 and fine:
                self.mid_opacity.value = 0.5
            else:
                self.app.worker.submit("seed-mid", self.draw_mid)

        started = self.app.jobs.start("fine step", job)
        if not started:
            self.notify(client, "Busy", f"{self.app.jobs.name} is running", "yellow")
        return started

    # ---------------------------------------------------------------- drawing (worker)
    def request_overlays(self) -> None:
        self.app.worker.submit("seed-overlays", self.draw_overlays)

    def base_rgb(self) -> np.ndarray:
        """Base map preview (RGB), longer side ≤ 2x the display size."""
        if self._base_rgb is None:
            self._base_rgb = scene2d.to_rgb(
                scene2d.preview(self.app.inputs.base, 2 * self.app.display_max)
            )
        return self._base_rgb

    def draw_images(self) -> None:
        inp = self.app.inputs
        if inp is None or "frame" not in self.image_planes:
            return
        with self.state.lock:
            ref, g = self.state.reference_frame, self.state.gamma
        calib = self.app.tabs["Calibrate"]
        frame_rgb = calib.corrected_image(ref, g, self.app.display_max)
        with self.app.server.atomic():
            self.image_planes["frame"].show(frame_rgb)
            self.image_planes["base"].show(self.base_rgb())
        self.app.shown[self.MODE] = (ref, g)
        self.draw_overlays()
        self.draw_mid()

    def draw_overlays(self) -> None:
        if "frame" not in self.image_planes:
            return
        fp, bp = self.image_planes["frame"], self.image_planes["base"]
        inp = self.app.inputs
        with self.state.lock:
            sf, sb, g = self.state.seed_frame, self.state.seed_base, self.state.gamma
            coarse, fine = self.state.coarse, self.state.fine
        w, h = inp.frame_size
        mark = max(w, h) / 60
        bmark = max(inp.base_size) / 80
        with self.app.server.atomic():
            if sf is not None:
                c = distortion.HarrisModel(g, w, h).corrected_from_raw([sf])[0]
                fp.segments("seed", *scene2d.cross_segments(c, mark), SEED_FRAME, width=3.0)
            else:
                fp.remove("seed")
            if sb is not None:
                bp.segments("seed", *scene2d.cross_segments(sb, bmark), SEED_BASE, width=3.0)
            else:
                bp.remove("seed")
            self._draw_matches(coarse)
            self._draw_fine(fine)

    def _draw_matches(self, coarse) -> None:
        fp, bp = self.image_planes["frame"], self.image_planes["base"]
        key = f"{self.root_name}/matches"
        if coarse is None or coarse.n_matches == 0:
            if self._matches is not None:
                self._matches.remove()
                self._matches = None
            bp.remove("gate")
            return
        show = coarse.gated | bool(self.show_ungated.value)
        colours = np.where(
            coarse.inliers[:, None], INLIER, np.where(coarse.gated[:, None], OUTLIER, UNGATED)
        ).astype(np.uint8)
        pts = scene2d.segments_between(
            fp.geom, coarse.frame_xy[show], bp.geom, coarse.base_xy[show]
        )
        cols = np.repeat(colours[show][:, None, :], 2, axis=1)
        if len(pts):
            self._matches = self.scene.add_line_segments(
                key, pts, cols, thickness=1.5, thickness_units="screen"
            )
        if coarse.gate_center_base is not None and coarse.gate_radius_base:
            bp.segments(
                "gate",
                *scene2d.circle_segments(coarse.gate_center_base, coarse.gate_radius_base),
                SEED_BASE,
                width=2.0,
            )
        else:
            bp.remove("gate")

    def _draw_fine(self, fine) -> None:
        fp, bp = self.image_planes["frame"], self.image_planes["base"]
        key = f"{self.root_name}/template_matches"
        if self._template_lines is not None:
            self._template_lines.remove()
            self._template_lines = None
        if fine is None or len(fine.src) == 0:
            for name in ("grid",):
                fp.remove(name)
            for name in ("cps", "residuals"):
                bp.remove(name)
            return
        inp = self.app.inputs
        cols = np.where(fine.kept[:, None], KEPT, REMOVED).astype(np.uint8)
        fp.points("grid", fine.src, cols, size_px=max(inp.frame_size) / 200)
        bp.points("cps", fine.dst, cols, size_px=max(inp.base_size) / 300)
        if self.show_template_matches.value:
            pts = scene2d.segments_between(fp.geom, fine.src, bp.geom, fine.dst)
            self._template_lines = self.scene.add_line_segments(
                key,
                pts,
                np.repeat(cols[:, None, :], 2, axis=1),
                thickness=1.0,
                thickness_units="screen",
            )
        if fine.base_from_corrected is not None:
            pred = fine.base_from_corrected.apply(fine.src)
            ok = np.isfinite(pred).all(axis=1)
            scale = float(self.vec_scale.value)
            tip = fine.dst + scale * (pred - fine.dst)
            vcols = np.where(fine.kept[:, None], RESIDUAL, REMOVED).astype(np.uint8)
            bp.segments("residuals", fine.dst[ok], tip[ok], vcols[ok], width=2.0)
        else:
            bp.remove("residuals")

    def draw_mid(self) -> None:
        """The reference frame warped into the map by the fine model, blended over the map."""
        from registration import viz
        from registration.warp import warp_image

        if "base" not in self.image_planes:
            return
        bp = self.image_planes["base"]
        with self.state.lock:
            fine, ref, g = self.state.fine, self.state.reference_frame, self.state.gamma
        alpha = float(self.mid_opacity.value)
        if fine is None or not fine or alpha <= 0.0:
            bp.remove("mid")
            return
        base_rgb = self.base_rgb()
        key = (id(fine), ref, g)
        if self._mid_cache is None or self._mid_cache[0] != key:
            inp = self.app.inputs
            hp, wp = base_rgb.shape[:2]
            fx = inp.base_size[0] / wp
            model = fine.base_from_corrected
            harris = distortion.HarrisModel(g, *inp.frame_size)

            def raw_from_preview(xy):
                # preview base px -> full base px -> corrected frame px -> raw frame px
                from registration.coords import rescale

                return harris.raw_from_corrected(model.inverse(rescale(xy, fx)))

            warped, valid = warp_image(
                scene2d.to_rgb(inp.frame(ref)), raw_from_preview, wp, hp, step=8
            )
            self._mid_cache = (key, warped, valid)
        _, warped, valid = self._mid_cache
        bp.overlay_image("mid", viz.blend(warped, base_rgb, alpha, mask=valid))
