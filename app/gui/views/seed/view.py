"""Seed view: seed the reference frame on the map, fit it (paper 4.3), review and edit its control
points.

The reference frame (radially corrected with the project's γ) and the base map lie side by side,
drawn equally tall. A click on the frame and one on the map place a seed pair (pair 1; "Pair 2"
places an optional second pair that fixes heading and scale); each marker can be dragged to
refine it, and *Undo* takes back the last change. Markers differ in shape (frame: ring, map:
square) and carry their pair's number; the magnifier shows both places enlarged. Once pair 1 is
placed the coarse and fine steps run (``global_registration.coarse_register`` and
``fine_register_reference``), and the panel shows the heading and scale the coarse step used
(estimated from one click, or fixed by two pairs) and, when a step fails, its one-line reason in a
red box. The analyst corrects heading and scale by placing pair 2, or by typing them: typed values
become a second seed pair 100 px from the seed (``calls.second_seed_from_similarity``), drawn as
pair 2 and following pair 1.

Match review: inliers only by default (outliers and matches outside the gate on toggles), the
gate as the region where gated matches could lie (``CoarseResult.gate_outline_base``), the
template control points kept by REQCON and their residual vectors scaled automatically, the mid
base image over the map. The control-point table lists the
fine fit's points (id, frame x/y, map x/y, dx, dy, residual, source, enabled): sort, select
(centres the view and the magnifier on it), enable / disable / delete, add a manual point, and
the model is re-fitted at once; export as QGIS ``.points``.
"""

from __future__ import annotations

import numpy as np

from app.gui import calls, controlpoints, scene2d
from app.gui.controlpoints import Edits
from app.gui.state import ReferenceFit
from app.gui.views.base import View
from app.gui.views.seed.panel import (
    INLIER,
    KEPT,
    MANUAL,
    OUTLIER,
    PAIR_COLOURS,
    REMOVED,
    RESIDUAL,
    SELECTED,
    UNGATED,
    SeedPanel,
    SeedScene,
    gate_outlines,
    magnifier_crop,
    magnifier_side,
)
from app.gui.views.seed.points import ControlPointActions
from registration import global_registration
from registration.lens import correction, radial


class SeedView(ControlPointActions, View):
    MODE = "Seed"
    CLICKABLE = ("frame", "base")

    def make_scene(self, scene, root_name):
        return SeedScene(scene, root_name)

    def make_panel(self, gui):
        return SeedPanel(gui)

    def connect(self) -> None:
        p = self.panel
        p.ref_slider.on_update(lambda ev: self.set_reference(int(ev.target.value)))
        p.pair.on_click(lambda ev: self.set_pair(2 if ev.target.value.endswith("2") else 1))
        p.edit.on_click(lambda ev: self.seed_edit(ev.target.value))
        p.fit.on_click(lambda ev: self.fit_view(ev.target.value, ev.client))
        p.preset.on_update(lambda ev: self.set_setting("preset", str(ev.target.value)))
        p.transform.on_update(lambda ev: self.set_setting("transform", str(ev.target.value)))
        p.local.on_update(lambda ev: self.set_setting("run_local", bool(ev.target.value)))
        p.btn_typed.on_click(
            lambda ev: self.use_typed(float(p.heading_in.value), float(p.scale_in.value), ev.client)
        )
        p.btn_coarse.on_click(lambda ev: self.run_fit(ev.client, fine=False))
        p.btn_fine.on_click(lambda ev: self.run_fine(ev.client))
        for h in (
            p.show_outliers,
            p.show_ungated,
            p.show_gate,
            p.show_template_matches,
            p.vec_scale,
        ):
            h.on_update(lambda ev: self.request_overlays())
        p.mid_opacity.on_update(lambda ev: self.submit("mid", self.draw_mid))
        cps = p.cps
        cps.sort.on_update(lambda ev: self.show_table())
        cps.page.on_click(lambda ev: self.turn_page(-1 if "previous" in ev.target.value else 1))
        cps.selected.on_update(lambda ev: self.select_point(int(ev.target.value), ev.client))
        cps.actions.on_click(lambda ev: self.point_action(ev.target.value, ev.client))
        cps.bulk.on_click(lambda ev: self.bulk_action(ev.target.value, ev.client))
        cps.export.on_click(lambda ev: self.export_points(ev.client))
        self.app.events.on("cp-select:seed", lambda v, client: self.select_point(int(v), client))
        self.scene.on_drag = self.on_marker_drag
        self._mid_cache: tuple | None = None
        self.table: controlpoints.ControlPointTable | None = None
        self.selected: int | None = None
        self.manual_mode = False
        self.manual_frame: tuple[float, float] | None = None  # raw px of a manual point's 1st click
        self._grab: dict[tuple[str, int], np.ndarray] = {}  # drag: marker - pointer, px
        self._corrected_full: tuple | None = (
            None  # ((k, γ), full-size corrected frame) for the magnifier
        )

    # ---------------------------------------------------------------- inputs and state
    def on_inputs(self) -> None:
        inp = self.app.inputs
        self.scene.layout(inp.frame_size, inp.base_size)
        self._mid_cache = None
        self.table = None
        self.selected = None
        with self.state.lock:
            st = self.state
            ref, preset, transform, local = (
                st.reference_frame,
                st.preset,
                st.transform,
                st.run_local,
            )
        p = self.panel
        if preset in p.preset.options:
            p.preset.value = preset
        p.transform.value = transform
        p.local.value = local
        p.ref_slider.max = max(inp.n_frames - 1, 1)
        p.ref_slider.disabled = inp.n_frames <= 1
        p.ref_slider.value = ref
        self.restore_reference()
        self.refresh_text()

    def on_show(self) -> None:
        self.refresh_text()
        self.submit("images", self.draw_images)

    def on_state_changed(self) -> None:
        self.refresh_text()

    def fit_geoms(self):
        return self.scene.geoms()

    def restore_reference(self) -> None:
        """Bring back the fits saved for exactly the current γ, seeds, frame, preset, degree."""
        from app.gui.project import REFERENCE_FILE, reference_from_file

        path = self.app.project.folder / REFERENCE_FILE
        loaded = reference_from_file(path) if path.exists() else None
        with self.state.lock:
            if loaded is None or loaded[0] != self.state.reference_key():
                return
            key, coarse, fine = loaded
            self.state.reference = ReferenceFit(key, coarse, fine, fine)
        if fine is not None:
            self.refit(save=False)

    def save_reference(self) -> None:
        from app.gui.project import REFERENCE_FILE, reference_to_bytes

        with self.state.lock:
            ref = self.state.reference
        if ref is None:
            return
        self.app.project.write_file(
            REFERENCE_FILE, reference_to_bytes(ref.key, ref.coarse, ref.fine_auto)
        )

    def set_reference(self, k: int) -> None:
        with self.state.lock:
            if self.app.inputs is None or k == self.state.reference_frame:
                return
            self.state.reference_frame = int(np.clip(k, 0, self.app.inputs.n_frames - 1))
            self.state.push_undo()
            self.state.seed_frame = self.state.seed2_frame = None
            self._follow_typed()
            self.state.revision += 1
        self._mid_cache = None
        self.app.save()
        self.app.state_changed()
        self.submit("images", self.draw_images)

    def set_setting(self, name: str, value) -> None:
        with self.state.lock:
            if getattr(self.state, name) == value:
                return
            setattr(self.state, name, value)
            self.state.revision += 1
        self.app.save()
        self.app.state_changed()
        self.request_overlays()

    def set_pair(self, pair: int) -> None:
        with self.state.lock:
            self.state.seed_pair = pair
        self.refresh_text()

    def seed_edit(self, action: str) -> None:
        with self.state.lock:
            if action == "Undo":
                if not self.state.pop_undo():
                    return
            else:
                self.state.push_undo()
                self.state.seed2_frame = self.state.seed2_base = None
                self.state.seed2_typed = None
                if action == "Clear all":
                    self.state.seed_frame = self.state.seed_base = None
                self.state.revision += 1
        self._seeds_changed(refit_reference=action == "Undo")

    def clear_seed(self) -> None:
        self.seed_edit("Clear all")

    def on_click(self, plane: str, xy, client) -> None:
        """Frame clicks are corrected pixels (stored raw); map clicks base pixels."""
        xy = np.asarray(xy, float)
        with self.state.lock:
            model = radial.HarrisModel(self.state.gamma, *self.app.inputs.frame_size)
        if plane == "frame":
            raw = model.raw_from_corrected(xy[None])[0]
            if not np.isfinite(raw).all():
                return
            point = (float(raw[0]), float(raw[1]))
        elif plane == "base":
            point = (float(xy[0]), float(xy[1]))
        else:
            return
        if self.manual_mode:
            self.manual_click(plane, point, client)
            return
        self.place_seed(plane, point)

    def place_seed(self, plane: str, point: tuple[float, float], pair: int | None = None) -> None:
        """Set pair ``pair`` (default: the active one)'s point on ``plane`` (raw or base px)."""
        with self.state.lock:
            pair = pair or self.state.seed_pair
            self.state.push_undo()
            name = ("seed" if pair == 1 else "seed2") + ("_frame" if plane == "frame" else "_base")
            setattr(self.state, name, point)
            if pair == 2:
                self.state.seed2_typed = None  # placed by hand: the pairs fix heading and scale
            else:
                self._follow_typed()
            self.state.revision += 1
        self._seeds_changed()

    def _follow_typed(self) -> None:
        """Pair 2 made from a typed heading and scale follows pair 1 (call under the lock)."""
        st = self.state
        if st.seed2_typed is None:
            return
        if st.seed is None:
            st.seed2_frame = st.seed2_base = None
            return
        p2 = calls.second_seed_from_similarity(st.seed, *st.seed2_typed, st.gamma, st.frame_size)
        st.seed2_frame, st.seed2_base = p2[:2], p2[2:]

    def use_typed(self, heading_deg: float, scale: float, client=None) -> bool:
        """Fix heading and scale to typed values: the coarse step gets them as a second seed
        pair (:func:`app.gui.calls.second_seed_from_similarity`), shown as pair 2."""
        problem = None
        with self.state.lock:
            st = self.state
            if st.seed is None:
                problem = ("Place pair 1 first", "Typed heading and scale turn about the seed")
            else:
                try:
                    calls.second_seed_from_similarity(
                        st.seed, heading_deg, scale, st.gamma, st.frame_size
                    )
                except ValueError as exc:
                    problem = ("Heading and scale not used", str(exc))
            if problem is None:
                st.push_undo()
                st.seed2_typed = (float(heading_deg), float(scale))
                self._follow_typed()
                st.revision += 1
        if problem is not None:
            self.notify(client, *problem, "yellow")
            return False
        self._seeds_changed()
        return True

    def _seeds_changed(self, refit_reference: bool = False) -> None:
        self.app.save()
        self.refresh_text()
        self.app.state_changed()
        self.submit("seeds", self.draw_seeds)
        if refit_reference:
            self.refit()
        with self.state.lock:
            ready = self.state.seed is not None and self.state.current_reference() is None
        if ready and self.panel.auto_fit.value:
            self.run_fit(None, fine=True)

    def on_marker_drag(self, plane: str, pair: int, event) -> None:
        """A seed marker is being dragged (runs on viser's event loop, in order: quick work only).

        The marker keeps its offset from the pointer where it was grabbed (the ring is grabbed
        off its centre), and follows the pointer; the seed changes when it is dropped."""
        client = event.client
        cam = (
            client.camera.position
            if client is not None
            else self.app.server.initial_camera.position
        )
        geom = self.scene.planes[plane].geom
        pointer = scene2d.pixel_under_pointer(geom, cam, event.end_position)
        if pointer is None:
            return
        key = (plane, pair)
        if event.phase == "start" or key not in self._grab:
            marker = self.scene.markers.get(key)
            self._grab[key] = (marker.xy if marker is not None else pointer) - pointer
        xy = pointer + self._grab[key]
        if event.phase == "end":
            self._grab.pop(key, None)
            if geom.contains(xy):
                self.on_drop(plane, pair, xy)
            else:
                self.submit("seeds", self.draw_seeds)  # dropped off the image: back in place
            return
        if geom.contains(xy):
            self.scene.move_marker(plane, pair, xy)

    def on_drop(self, plane: str, pair: int, xy) -> None:
        """A dragged marker was dropped at pixel ``xy`` of ``plane`` (corrected px on the frame)."""
        xy = np.asarray(xy, float)
        if plane == "frame":
            with self.state.lock:
                model = radial.HarrisModel(self.state.gamma, *self.app.inputs.frame_size)
            raw = model.raw_from_corrected(xy[None])[0]
            if not np.isfinite(raw).all():
                return
            point = (float(raw[0]), float(raw[1]))
        else:
            point = (float(xy[0]), float(xy[1]))
        self.app.worker.submit("seed-drop", lambda: self.place_seed(plane, point, pair))

    def seed_pairs_corrected(self) -> dict:
        """``{pair: (frame point in corrected px or None, map point or None)}``."""
        with self.state.lock:
            st = self.state
            model = radial.HarrisModel(st.gamma, *st.frame_size)
            raw = {1: (st.seed_frame, st.seed_base), 2: (st.seed2_frame, st.seed2_base)}
        out = {}
        for i, (f, b) in raw.items():
            fc = None if f is None else model.corrected_from_raw(np.array([f], float))[0]
            out[i] = (fc, None if b is None else np.asarray(b, float))
        return out

    def refresh_text(self) -> None:
        if self.app.inputs is None:
            return
        with self.state.lock:
            st = self.state
            pairs = {1: (st.seed_frame, st.seed_base), 2: (st.seed2_frame, st.seed2_base)}
            active, seed, seed2, gamma = st.seed_pair, st.seed, st.seed2, st.gamma
            typed = st.seed2_typed
            ref = st.current_reference()
            key_ok = ref is not None
            coarse = ref.coarse if ref is not None else None
            fine = ref.fine if ref is not None else None
            edited = not st.cp_edits.empty
        size = self.app.inputs.frame_size
        lines = []
        hp = calls.heading_from_pairs(seed, seed2, gamma, size)
        if hp is not None and typed is not None:
            hp = calls.HeadingScale(hp.heading_deg, hp.scale, "typed: pair 2 is made from it")
        if hp is not None:
            lines.append("Pairs: " + hp.text())
        hc = calls.heading_from_coarse(coarse)
        if hc is not None:
            lines.append("Coarse step: " + hc.text())
        elif seed is not None and coarse is None:
            lines.append("_Heading and scale appear when the coarse step has run._")
        self.panel.show_seeds(pairs, active, typed is not None)
        self.panel.show_heading("  \n".join(lines))
        failures = []
        if coarse is not None and not coarse:
            failures.append(("Coarse step failed", coarse.reason))
        elif fine is not None and not fine:
            failures.append(("Fine step failed", fine.reason))
        self.panel.show_alert(failures)
        if coarse is not None:
            gate = "no location gate (no seed)" if seed is None else "gated around the seed"
            self.panel.show_coarse(coarse, gate)
        else:
            self.panel.show_coarse(None, "")
            if not key_ok and self.state.reference is not None:
                self.panel.coarse_md.content = (
                    "_Settings changed since the last fit: run it again._"
                )
        self.panel.show_fine(fine, edited)

    def fit_view(self, which: str, client) -> None:
        keys = {"Frame": ("frame",), "Map": ("base",), "Both": ("frame", "base")}.get(which)
        if keys:
            self.app.focus(self.scene.geoms(keys), client)

    # ---------------------------------------------------------------- fits (job thread)
    def _config(self):
        with self.state.lock:
            st = self.state
            return calls.pipeline_config(st.preset, st.degree, st.run_local)

    def run_fit(self, client=None, *, fine: bool) -> bool:
        """The coarse step (and the fine step when ``fine``) for the current seed, as a job;
        while another fit runs, the newest request waits and runs after it."""
        inp = self.app.inputs
        if inp is None:
            return False

        def job(progress) -> None:
            with self.state.lock:
                st = self.state
                self._follow_typed()  # a typed pair 2 for the γ of now
                k, gamma, seed, seed2 = st.reference_frame, st.gamma, st.seed, st.seed2
                key = st.reference_key()
            cfg = self._config()
            progress(0, 2 if fine else 1, "coarse step")
            try:
                coarse = calls.coarse_register(
                    inp.frame(k), inp.base, gamma, seed, seed2, cfg, base_valid=inp.base_valid
                )
            except ValueError as exc:  # e.g. the two pairs on one point: say it like a failure
                coarse = calls.failed_coarse(f"coarse step: {exc}")
            with self.state.lock:
                self.state.reference = ReferenceFit(key, coarse)
                self.state.cp_edits = Edits()
                self.state.revision += 1
            self._mid_cache = None
            self.table = None
            self.save_reference()
            self.app.save()
            self.refresh_text()
            self.app.state_changed()
            self.request_overlays()
            self.submit("magnifier", self.draw_magnifier)
            hc = calls.heading_from_coarse(coarse)
            if hc is not None and seed2 is None:
                # The estimate is where a correction starts from.
                self.panel.heading_in.value = round(hc.heading_deg, 1)
                self.panel.scale_in.value = round(hc.scale, 4)
            if not coarse:
                self.notify(client, "Coarse step failed", coarse.reason, "red")
                return
            if fine:
                progress(1, 2, "fine step")
                self._fine(inp, k, gamma, coarse, key, cfg, client)

        return self.app.run_job("reference fit", job, client, queue=True)

    def run_fine(self, client=None) -> bool:
        inp = self.app.inputs
        with self.state.lock:
            ref = self.state.current_reference()
            k, gamma = self.state.reference_frame, self.state.gamma
        if inp is None:
            return False
        if ref is None or not ref.coarse:
            self.notify(
                client,
                "Run the coarse step first",
                "The fine step starts from a successful coarse step for the current settings",
                "yellow",
            )
            return False
        cfg = self._config()
        return self.app.run_job(
            "fine step",
            lambda progress: self._fine(inp, k, gamma, ref.coarse, ref.key, cfg, client),
            client,
        )

    def _fine(self, inp, k, gamma, coarse, key, cfg, client) -> None:
        fine = global_registration.fine_register_reference(
            inp.frame(k), inp.base, gamma, coarse, cfg.fine, match_in=cfg.match_in,
            base_valid=inp.base_valid,
        )  # fmt: skip
        with self.state.lock:
            ref = self.state.reference
            if ref is None or ref.key != key:
                return  # the seed moved meanwhile: a newer fit is queued
            ref.fine_auto = ref.fine = fine
            self.state.cp_edits = Edits()
            self.state.revision += 1
        self._mid_cache = None
        self.save_reference()
        self.app.save()
        if not fine:
            self.notify(client, "Fine step failed", fine.reason, "red")
        self.refit(save=False)
        if fine and self.panel.mid_opacity.value == 0.0:
            self.panel.mid_opacity.value = 0.5
        else:
            self.submit("mid", self.draw_mid)

    # ---------------------------------------------------------------- drawing (worker)
    def request_overlays(self) -> None:
        self.submit("overlays", self.draw_overlays)

    def draw_images(self) -> None:
        inp = self.app.inputs
        if inp is None or "frame" not in self.scene.planes:
            return
        with self.state.lock:
            ref, g = self.state.reference_frame, self.state.gamma
        frame_rgb = self.corrected_preview(ref, g)
        with self.app.server.atomic():
            self.scene.show_images(frame_rgb, inp.base_preview(2 * self.app.display_max))
        self.app.shown[self.MODE] = (ref, g)
        self.draw_overlays()
        self.draw_mid()
        self.draw_magnifier()

    def corrected_preview(self, k: int, gamma: float, max_side: int | None = None) -> np.ndarray:
        img = self.app.inputs.preview(k, max_side or self.app.display_max)
        h, w = img.shape[:2]
        corrected, _ = correction.undistort_image(
            img, radial.HarrisModel(gamma, w, h), canvas="same"
        )
        return scene2d.to_rgb(corrected)

    def draw_seeds(self) -> None:
        if "frame" not in self.scene.planes:
            return
        with self.app.server.atomic():
            self.scene.draw_seeds(self.seed_pairs_corrected())
        self.draw_magnifier()

    def draw_overlays(self) -> None:
        if "frame" not in self.scene.planes or self.app.inputs is None:
            return
        p = self.panel
        with self.state.lock:
            ref = self.state.current_reference()
            coarse = ref.coarse if ref is not None else None
        pairs = self.seed_pairs_corrected()
        with self.app.server.atomic():
            self.scene.draw_seeds(pairs)
            # Matches: inliers; outliers and matches outside the gate on request.
            if coarse is None or coarse.n_matches == 0:
                self.scene.draw_matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)))
            else:
                show = coarse.inliers.copy()
                if p.show_outliers.value:
                    show |= coarse.gated
                if p.show_ungated.value:
                    show |= ~coarse.gated
                cols = np.where(
                    coarse.inliers[:, None],
                    INLIER,
                    np.where(coarse.gated[:, None], OUTLIER, UNGATED),
                ).astype(np.uint8)
                self.scene.draw_matches(coarse.frame_xy[show], coarse.base_xy[show], cols[show])
            outlines = []
            if p.show_gate.value and coarse is not None:
                outlines = gate_outlines(coarse)
            self.scene.draw_gate(outlines)
            self._draw_control_points()
            self.scene.draw_manual_pending(
                None
                if self.manual_frame is None
                else radial.HarrisModel(
                    self.state.gamma, *self.app.inputs.frame_size
                ).corrected_from_raw(np.array([self.manual_frame]))[0]
            )
        self.app.shown[f"{self.MODE}:overlays"] = self.state.revision

    def _draw_control_points(self) -> None:
        t = self.table
        if t is None or not len(t.ids):
            self.scene.draw_control_points(
                np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)), None, False
            )
            self.scene.draw_selected(None, None)
            return
        show = t.enabled | bool(self.panel.show_outliers.value)
        manual = np.array([s == controlpoints.MANUAL for s in t.source])
        cols = np.where(
            manual[:, None], MANUAL, np.where(t.enabled[:, None], KEPT, REMOVED)
        ).astype(np.uint8)
        vectors = None
        ok = show & np.isfinite(t.residual)
        if t.model is not None and ok.any():
            scale = float(self.panel.vec_scale.value) or scene2d.auto_vector_scale(
                t.residual[t.enabled], self.scene.planes["base"].geom.width
            )
            self.vector_scale_used = scale
            start = t.base_xy[ok]
            vcols = np.where(t.enabled[ok][:, None], RESIDUAL, REMOVED).astype(np.uint8)
            vectors = (start, start + scale * t.residual_xy[ok], vcols)
        self.scene.draw_control_points(
            t.corrected_xy[show],
            t.base_xy[show],
            cols[show],
            vectors,
            bool(self.panel.show_template_matches.value),
        )
        i = None if self.selected is None else t.row(self.selected)
        if i is None:
            self.scene.draw_selected(None, None)
        else:
            self.scene.draw_selected(t.corrected_xy[i], t.base_xy[i])

    def draw_magnifier(self) -> None:
        """Crops around the selected control point, else the active seed pair: frame | map."""
        inp = self.app.inputs
        if inp is None:
            return
        with self.state.lock:
            g, k, active = self.state.gamma, self.state.reference_frame, self.state.seed_pair
        pairs = self.seed_pairs_corrected()
        fxy, bxy = pairs[active]
        t = self.table
        i = None if t is None or self.selected is None else t.row(self.selected)
        if i is not None:
            fxy, bxy = t.corrected_xy[i], t.base_xy[i]
        if self._corrected_full is None or self._corrected_full[0] != (k, g):
            self._corrected_full = ((k, g), self.corrected_preview(k, g, max(inp.frame_size)))
        frame = self._corrected_full[1]
        base = inp.base_preview(max(inp.base_size))
        colour = PAIR_COLOURS[active] if i is None else SELECTED
        self.panel.magnifier.image = np.concatenate(
            [
                magnifier_crop(frame, fxy, colour),
                np.full((magnifier_side(), 8, 3), 255, np.uint8),
                magnifier_crop(base, bxy, colour),
            ],
            axis=1,
        )

    def draw_mid(self) -> None:
        """The reference frame warped into the map by the fine model, blended over the map."""
        from registration.coords import rescale
        from registration.geometry import warp_image
        from registration.render import viz

        if "base" not in self.scene.planes or self.app.inputs is None:
            return
        with self.state.lock:
            ref = self.state.current_reference()
            fine = ref.fine if ref is not None else None
            k, g = self.state.reference_frame, self.state.gamma
        alpha = float(self.panel.mid_opacity.value)
        if fine is None or not fine or alpha <= 0.0:
            self.scene.draw_mid(None)
            return
        inp = self.app.inputs
        base_rgb = inp.base_preview(2 * self.app.display_max)
        key = (id(fine), k, g)
        if self._mid_cache is None or self._mid_cache[0] != key:
            hp, wp = base_rgb.shape[:2]
            fx = inp.base_size[0] / wp
            model = fine.base_from_corrected
            harris = radial.HarrisModel(g, *inp.frame_size)

            def raw_from_preview(xy):
                return harris.raw_from_corrected(model.inverse(rescale(xy, fx)))

            warped, valid = warp_image(
                scene2d.to_rgb(inp.frame(k)), raw_from_preview, wp, hp, step=8
            )
            self._mid_cache = (key, warped, valid)
        _, warped, valid = self._mid_cache
        self.scene.draw_mid(viz.blend(warped, base_rgb, alpha, mask=valid))
