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
the model is re-fitted at once on the worker; export as QGIS ``.points`` (``points.py``).
"""

from __future__ import annotations

import numpy as np

from app.gui import calls, controlpoints, scene2d
from app.gui.context import Client
from app.gui.controlpoints import Edits
from app.gui.project import REFERENCE_FILE, reference_from_file, reference_to_bytes
from app.gui.state import ReferenceFit
from app.gui.views.base import View
from app.gui.views.seed.panel import SeedPanel
from app.gui.views.seed.points import ReferencePoints
from app.gui.views.seed.scene import (
    INLIER,
    KEPT,
    MANUAL,
    OUTLIER,
    PAIR_COLOURS,
    REMOVED,
    RESIDUAL,
    SELECTED,
    UNGATED,
    SeedScene,
    gate_outlines,
    magnifier_crop,
    magnifier_crop_corrected,
    magnifier_side,
)
from registration import global_registration
from registration.lens import Camera

MID_OPACITY_AFTER_FIT = 0.5
"""The mid base image's opacity once a fine fit succeeded (when the analyst had it off)."""


def inside(xy: np.ndarray, geom) -> np.ndarray:
    """Which of ``xy`` (N, 2) px lie on an image of ``geom``'s size."""
    xy = np.asarray(xy, float)
    return (
        np.isfinite(xy).all(axis=1)
        & (xy[:, 0] >= -0.5)
        & (xy[:, 0] <= geom.width - 0.5)
        & (xy[:, 1] >= -0.5)
        & (xy[:, 1] <= geom.height - 0.5)
    )


def match_sample(frame_xy: np.ndarray, eligible: np.ndarray, n_max: int) -> np.ndarray:
    """Indices of at most ``n_max`` of the ``eligible`` matches, spread over the frame: on a
    grid of about ``n_max`` cells, every cell's first match (in index order), then every
    cell's second, and so on; the same matches give the same sample."""
    idx = np.flatnonzero(eligible)
    if len(idx) <= n_max:
        return idx
    xy = frame_xy[idx]
    side = max(int(np.ceil(np.sqrt(n_max))), 1)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    cell = np.floor((xy - lo) / np.maximum(hi - lo, 1e-9) * (side - 1e-9)).astype(int)
    key = cell[:, 1] * side + cell[:, 0]
    by_cell = np.lexsort((np.arange(len(key)), key))  # by cell, then index
    first = np.r_[0, np.flatnonzero(np.diff(key[by_cell])) + 1]
    rank = np.empty(len(key), int)
    starts = np.repeat(first, np.diff(np.r_[first, len(key)]))
    rank[by_cell] = np.arange(len(key)) - starts
    take = np.lexsort((np.arange(len(key)), rank))[:n_max]
    return idx[np.sort(take)]


def review_counts(coarse, show, on_images, n_drawn: int, lines: bool) -> str:
    """The review's counts: inliers, what is shown, what the lines draw and leave out."""
    n_in = int(coarse.inliers.sum())
    n_show = int(show.sum())
    off = int((show & ~on_images).sum())
    text = f"Coarse step: **{n_in}** inlier matches of {coarse.n_matches}"
    if n_show != n_in:
        text += f", {n_show} shown with the outliers asked for"
    if not lines:
        return text + "; match lines hidden."
    text += f"; lines drawn for {n_drawn} of them, spread over the frame"
    if off:
        text += f" ({off} with an end outside the images shown are left out)"
    return text + "."


class SeedView(View):
    MODE = "Seed"
    CLICKABLE = ("frame", "base")

    panel: SeedPanel
    scene: SeedScene

    def make_scene(self, scene, root_name):
        return SeedScene(scene, root_name)

    def make_panel(self, gui):
        return SeedPanel(gui)

    def connect(self) -> None:
        p = self.panel
        p.on_reference_frame_changed(lambda k, client: self.set_reference(k))
        p.on_pair_chosen(lambda pair, client: self.set_pair(pair))
        p.on_seed_edits(
            undo=lambda client: self.undo(),
            clear_pair2=lambda client: self.clear_pair2(),
            clear_all=lambda client: self.clear_seed(),
        )
        p.on_fit_view(self.fit_view)
        p.on_preset_changed(lambda value, client: self.set_setting("preset", value))
        p.on_transform_changed(lambda value, client: self.set_setting("transform", value))
        p.on_local_field_changed(lambda value, client: self.set_setting("run_local", value))
        p.on_adjust_changed(lambda value, client: self.set_setting("adjust", value))
        p.on_use_typed(self.use_typed)
        p.on_run_coarse(lambda client: self.run_fit(client, fine=False))
        p.on_run_fine(self.run_fine)
        p.on_review_changed(lambda client: self.request_overlays())
        p.on_mid_opacity_changed(lambda client: self.submit("mid", self.draw_mid))
        self.points = ReferencePoints(
            self.ctx,
            p.cps,
            self.scene,
            submit=self.submit,
            on_fit_changed=self._fit_changed,
            redraw_overlays=lambda: self.submit("overlays", self.draw_overlays),
            on_selected=self._point_selected,
        )
        self.scene.on_drag = self.on_marker_drag
        self._mid_cache: tuple | None = None
        self._grab: dict[tuple[str, int], np.ndarray] = {}  # drag: marker - pointer, px
        # ((k, γ), full-size corrected frame) for the magnifier

    # ---------------------------------------------------------------- the control points
    @property
    def table(self) -> controlpoints.ControlPointTable | None:
        """The reference frame's control-point table (None before a fine fit)."""
        return self.points.table

    @property
    def selected(self) -> int | None:
        return self.points.cp.selected

    def select_point(self, row_id: int, client: Client = None) -> None:
        self.points.cp.select(row_id, client)

    def disable_worst(self) -> int | None:
        return self.points.disable_worst()

    def export_points(self, client: Client = None) -> bool:
        return self.points.export(client)

    def _point_selected(self) -> None:
        self.request_overlays()
        self.submit("magnifier", self.draw_magnifier)

    def _fit_changed(self) -> None:
        """The fit the run uses changed (worker or job thread): texts, overlays, mid image."""
        self._mid_cache = None
        self.refresh_text()
        self.ctx.state_changed()
        self.request_overlays()
        self.submit("mid", self.draw_mid)

    # ---------------------------------------------------------------- inputs and state
    def on_inputs(self) -> None:
        inp = self.ctx.inputs
        self.scene.layout(inp.frame_size, inp.base_size)
        self._mid_cache = None
        self.points.cp.table = None
        self.points.cp.selected = None
        with self.state.lock:
            st = self.state
            ref, preset, transform, local, adjust = (
                st.reference_frame,
                st.preset,
                st.transform,
                st.run_local,
                st.adjust,
            )
        self.panel.show_settings(preset, transform, local, adjust)
        self.panel.configure(inp.n_frames)
        self.panel.reference_frame = ref
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
        path = self.ctx.project.folder / REFERENCE_FILE
        loaded = reference_from_file(path) if path.exists() else None
        with self.state.lock:
            if loaded is None or loaded[0] != self.state.reference_key():
                return
            key, coarse, fine = loaded
            self.state.reference = ReferenceFit(key, coarse, fine, fine)
        if fine is not None:
            self.points.refit(save=False)

    def save_reference(self) -> None:
        with self.state.lock:
            ref = self.state.reference
        if ref is None:
            return
        self.ctx.project.write_file(
            REFERENCE_FILE, reference_to_bytes(ref.key, ref.coarse, ref.fine_auto)
        )

    def set_reference(self, k: int) -> None:
        with self.state.lock:
            if self.ctx.inputs is None or k == self.state.reference_frame:
                return
            self.state.reference_frame = int(np.clip(k, 0, self.ctx.inputs.n_frames - 1))
            self.state.push_undo()
            self.state.seed_frame = self.state.seed2_frame = None
            self._follow_typed()
            self.state.revision += 1
        self._mid_cache = None
        self.ctx.save()
        self.ctx.state_changed()
        self.submit("images", self.draw_images)

    def set_setting(self, name: str, value) -> None:
        with self.state.lock:
            if getattr(self.state, name) == value:
                return
            setattr(self.state, name, value)
            self.state.revision += 1
        self.ctx.save()
        self.ctx.state_changed()
        self.request_overlays()

    def set_pair(self, pair: int) -> None:
        with self.state.lock:
            self.state.seed_pair = pair
        self.refresh_text()

    # ---------------------------------------------------------------- seeds (callbacks)
    def undo(self) -> None:
        """Take back the last change of the seeds or of the control points."""
        with self.state.lock:
            if not self.state.pop_undo():
                return
        self._seeds_changed(refit_reference=True)

    def clear_pair2(self) -> None:
        with self.state.lock:
            self.state.push_undo()
            self.state.seed2_frame = self.state.seed2_base = None
            self.state.seed2_typed = None
            self.state.revision += 1
        self._seeds_changed()

    def clear_seed(self) -> None:
        """Clear both seed pairs (undoable)."""
        with self.state.lock:
            self.state.push_undo()
            self.state.seed2_frame = self.state.seed2_base = None
            self.state.seed2_typed = None
            self.state.seed_frame = self.state.seed_base = None
            self.state.revision += 1
        self._seeds_changed()

    def _point_from_click(self, plane: str, xy) -> tuple[float, float] | None:
        """A click's point: raw frame px for the frame (clicks land in corrected px), base px
        for the map; None off the frame's valid region."""
        xy = np.asarray(xy, float)
        if plane != "frame":
            return (float(xy[0]), float(xy[1]))
        with self.state.lock:
            camera = self.state.camera()
        raw = camera.raw_from_corrected(xy[None])[0]
        if not np.isfinite(raw).all():
            return None
        return (float(raw[0]), float(raw[1]))

    def on_click(self, plane: str, xy, client: Client) -> None:
        """Frame clicks are corrected pixels (stored raw); map clicks base pixels."""
        if plane not in ("frame", "base"):
            return
        point = self._point_from_click(plane, xy)
        if point is None:
            return
        if self.points.manual_mode:
            self.points.manual_click(plane, point, client)
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

    def use_typed(self, heading_deg: float, scale: float, client: Client = None) -> bool:
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
        self.ctx.save()
        self.refresh_text()
        self.ctx.state_changed()
        self.submit("seeds", self.draw_seeds)
        if refit_reference:
            # The restored edits' least-squares re-fit: on the worker, never on a callback.
            self.submit("refit", self.points.refit)
        with self.state.lock:
            ready = self.state.seed is not None and self.state.current_reference() is None
        if ready and self.panel.fit_after_seed_change:
            self.run_fit(None, fine=True)

    def on_marker_drag(self, plane: str, pair: int, event) -> None:
        """A seed marker is being dragged (runs on viser's event loop, in order: quick work only).

        The marker keeps its offset from the pointer where it was grabbed (the ring is grabbed
        off its centre), and follows the pointer; the seed changes when it is dropped."""
        cam = self.ctx.camera_position(event.client)
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
        point = self._point_from_click(plane, xy)
        if point is None:
            return
        self.ctx.submit("seed-drop", lambda: self.place_seed(plane, point, pair))

    def seed_pairs_corrected(self) -> dict:
        """``{pair: (frame point in corrected px or None, map point or None)}``."""
        with self.state.lock:
            st = self.state
            camera = st.camera()
            raw = {1: (st.seed_frame, st.seed_base), 2: (st.seed2_frame, st.seed2_base)}
        out = {}
        for i, (f, b) in raw.items():
            fc = None if f is None else camera.corrected_from_raw(np.array([f], float))[0]
            out[i] = (fc, None if b is None else np.asarray(b, float))
        return out

    def refresh_text(self) -> None:
        if self.ctx.inputs is None:
            return
        with self.state.lock:
            st = self.state
            pairs = {1: (st.seed_frame, st.seed_base), 2: (st.seed2_frame, st.seed2_base)}
            active, seed, seed2 = st.seed_pair, st.seed, st.seed2
            typed = st.seed2_typed
            gamma, frame_size = st.gamma, st.frame_size
            ref = st.current_reference()
            stale = ref is None and st.reference is not None
            coarse = ref.coarse if ref is not None else None
            fine = ref.fine if ref is not None else None
            edited = not st.cp_edits.empty
        lines = []
        hp = calls.heading_from_pairs(seed, seed2, gamma, frame_size)
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
            self.panel.show_coarse(None, "", stale=stale)
        self.panel.show_fine(fine, edited)

    def fit_view(self, planes: tuple[str, ...], client: Client = None) -> None:
        """Point the camera at the named planes (``"frame"``, ``"base"``)."""
        self.ctx.focus(self.scene.geoms(planes), client)

    # ---------------------------------------------------------------- fits (job thread)
    def _config(self):
        with self.state.lock:
            st = self.state
            return calls.pipeline_config(st.preset, st.degree, st.run_local)

    def run_fit(self, client: Client = None, *, fine: bool) -> bool:
        """The coarse step (and the fine step when ``fine``) for the current seed, as a job;
        while another fit runs, the newest request waits and runs after it."""
        inp = self.ctx.inputs
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
            if progress.cancel.is_set():  # a cancelled fit changes nothing
                self.notify(client, "Fit cancelled", "The previous fit is kept", "blue")
                return
            with self.state.lock:
                self.state.reference = ReferenceFit(key, coarse)
                self.state.cp_edits = Edits()
                self.state.revision += 1
            self._mid_cache = None
            self.points.cp.table = None
            self.save_reference()
            self.ctx.save()
            self.refresh_text()
            self.ctx.state_changed()
            self.request_overlays()
            self.submit("magnifier", self.draw_magnifier)
            hc = calls.heading_from_coarse(coarse)
            if hc is not None and seed2 is None:
                # The estimate is where a correction starts from.
                self.panel.show_typed(hc.heading_deg, hc.scale)
            if not coarse:
                self.notify(client, "Coarse step failed", coarse.reason, "red")
                return
            if fine:
                progress(1, 2, "fine step")
                self._fine(inp, k, gamma, coarse, key, cfg, client, progress.cancel)

        return self.ctx.run_job("reference fit", job, client, queue=True)

    def run_fine(self, client: Client = None) -> bool:
        inp = self.ctx.inputs
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
        return self.ctx.run_job(
            "fine step",
            lambda progress: self._fine(
                inp, k, gamma, ref.coarse, ref.key, cfg, client, progress.cancel
            ),
            client,
        )

    def _fine(self, inp, k, gamma, coarse, key, cfg, client: Client, cancel) -> None:
        fine = global_registration.fine_register_reference(
            inp.frame(k), inp.base, gamma, coarse, cfg.fine, match_in=cfg.match_in,
            base_valid=inp.base_valid,
        )  # fmt: skip
        if cancel.is_set():  # the coarse step (finished before) stays; the fine one is dropped
            self.notify(client, "Fine step cancelled", "The fine fit is unchanged", "blue")
            return
        with self.state.lock:
            ref = self.state.reference
            if ref is None or ref.key != key:
                return  # the seed moved meanwhile: a newer fit is queued
            ref.fine_auto = ref.fine = fine
            self.state.cp_edits = Edits()
            self.state.revision += 1
        self._mid_cache = None
        self.save_reference()
        self.ctx.save()
        if not fine:
            self.notify(client, "Fine step failed", fine.reason, "red")
        self.points.refit(save=False)
        if fine and self.panel.mid_opacity_value == 0.0:
            self.panel.mid_opacity_value = MID_OPACITY_AFTER_FIT  # its callback draws it
        else:
            self.submit("mid", self.draw_mid)

    # ---------------------------------------------------------------- drawing (worker)
    def request_overlays(self) -> None:
        self.submit("overlays", self.draw_overlays)

    def draw_images(self) -> None:
        inp = self.ctx.inputs
        if inp is None or "frame" not in self.scene.planes:
            return
        with self.state.lock:
            ref, g = self.state.reference_frame, self.state.gamma
        frame_rgb = self.corrected_preview(ref, g)
        with self.ctx.atomic():
            self.scene.show_images(frame_rgb, inp.base_preview(2 * self.ctx.display_max))
        self.ctx.shown[self.MODE] = (ref, g)
        self.draw_overlays()
        self.draw_mid()
        self.draw_magnifier()

    def corrected_preview(self, k: int, gamma: float, max_side: int | None = None) -> np.ndarray:
        """Frame ``k`` corrected for ``gamma`` (RGB), its longer side at most ``max_side``."""
        img = self.ctx.inputs.preview(k, max_side or self.ctx.display_max)
        # The camera of the image drawn (a preview has its own size, the same γ).
        return scene2d.to_rgb(Camera.of(img, gamma).undistort(img))

    def draw_seeds(self) -> None:
        if "frame" not in self.scene.planes:
            return
        with self.ctx.atomic():
            self.scene.draw_seeds(self.seed_pairs_corrected())
        self.draw_magnifier()

    def draw_overlays(self) -> None:
        if "frame" not in self.scene.planes or self.ctx.inputs is None:
            return
        review = self.panel.review()
        with self.state.lock:
            ref = self.state.current_reference()
            coarse = ref.coarse if ref is not None else None
            camera = self.state.camera()
        pairs = self.seed_pairs_corrected()
        manual = self.points.manual_frame
        with self.ctx.atomic():
            self.scene.draw_seeds(pairs)
            # Matches: inliers; outliers and matches outside the gate on request; as lines, a
            # sample spread over the frame, of those whose both ends lie on the images shown.
            if coarse is None or coarse.n_matches == 0:
                self.scene.draw_matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)))
                self.panel.show_review_counts("")
            else:
                show = coarse.inliers.copy()
                if review.outliers:
                    show |= coarse.gated
                if review.ungated:
                    show |= ~coarse.gated
                cols = np.where(
                    coarse.inliers[:, None],
                    INLIER,
                    np.where(coarse.gated[:, None], OUTLIER, UNGATED),
                ).astype(np.uint8)
                fp, bp = self.scene.planes["frame"].geom, self.scene.planes["base"].geom
                on_images = inside(coarse.frame_xy, fp) & inside(coarse.base_xy, bp)
                drawn = match_sample(coarse.frame_xy, show & on_images, review.max_lines)
                if not review.match_lines:
                    drawn = np.zeros(0, int)
                self.scene.draw_matches(coarse.frame_xy[drawn], coarse.base_xy[drawn], cols[drawn])
                self.panel.show_review_counts(
                    review_counts(coarse, show, on_images, len(drawn), review.match_lines)
                )
            outlines = []
            if review.gate and coarse is not None:
                outlines = gate_outlines(coarse)
            self.scene.draw_gate(outlines)
            self._draw_control_points(review)
            self.scene.draw_manual_pending(
                None if manual is None else camera.corrected_from_raw(np.array([manual]))[0]
            )
        self.ctx.shown[f"{self.MODE}:overlays"] = self.state.revision

    def _draw_control_points(self, review) -> None:
        t = self.table
        if t is None or not len(t.ids):
            self.scene.draw_control_points(
                np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)), None, False
            )
            self.scene.draw_selected(None, None)
            return
        show = t.enabled | review.outliers
        manual = np.array([s == controlpoints.MANUAL for s in t.source])
        cols = np.where(
            manual[:, None], MANUAL, np.where(t.enabled[:, None], KEPT, REMOVED)
        ).astype(np.uint8)
        vectors = None
        ok = show & np.isfinite(t.residual)
        if t.model is not None and ok.any():
            scale = review.vector_scale or scene2d.auto_vector_scale(
                t.residual[t.enabled], self.scene.planes["base"].geom.width
            )
            self.vector_scale_used = scale
            start = t.base_xy[ok]
            vcols = np.where(t.enabled[ok][:, None], RESIDUAL, REMOVED).astype(np.uint8)
            vectors = (start, start + scale * t.residual_xy[ok], vcols)
        self.scene.draw_control_points(
            t.corrected_xy[show], t.base_xy[show], cols[show], vectors, review.template_lines
        )
        i = self.points.cp.selected_row()
        if i is None:
            self.scene.draw_selected(None, None)
        else:
            self.scene.draw_selected(t.corrected_xy[i], t.base_xy[i])

    def draw_magnifier(self) -> None:
        """Crops around the selected control point, else the active seed pair: frame | map."""
        inp = self.ctx.inputs
        if inp is None:
            return
        with self.state.lock:
            g, k, active = self.state.gamma, self.state.reference_frame, self.state.seed_pair
        pairs = self.seed_pairs_corrected()
        fxy, bxy = pairs[active]
        t = self.table
        i = self.points.cp.selected_row()
        if i is not None:
            fxy, bxy = t.corrected_xy[i], t.base_xy[i]
        with self.state.lock:
            camera = self.state.camera(g)
        raw = scene2d.to_rgb(inp.frame(k))
        base = inp.base_preview(max(inp.base_size))
        colour = PAIR_COLOURS[active] if i is None else SELECTED
        self.panel.show_magnifier(
            np.concatenate(
                [
                    magnifier_crop_corrected(raw, camera, fxy, colour),
                    np.full((magnifier_side(), 8, 3), 255, np.uint8),
                    magnifier_crop(base, bxy, colour),
                ],
                axis=1,
            )
        )

    def draw_mid(self) -> None:
        """The reference frame warped into the map by the fine model, blended over the map."""
        from registration.coords import rescale
        from registration.geometry import warp_image
        from registration.render import viz

        if "base" not in self.scene.planes or self.ctx.inputs is None:
            return
        with self.state.lock:
            ref = self.state.current_reference()
            fine = ref.fine if ref is not None else None
            k, g = self.state.reference_frame, self.state.gamma
            camera = self.state.camera()
        alpha = self.panel.mid_opacity_value
        if fine is None or not fine or alpha <= 0.0:
            self.scene.draw_mid(None)
            return
        inp = self.ctx.inputs
        base_rgb = inp.base_preview(2 * self.ctx.display_max)
        key = (id(fine), k, g)
        if self._mid_cache is None or self._mid_cache[0] != key:
            hp, wp = base_rgb.shape[:2]
            fx = inp.base_size[0] / wp
            model = fine.base_from_corrected

            def raw_from_preview(xy):
                return camera.raw_from_corrected(model.inverse(rescale(xy, fx)))

            warped, valid = warp_image(
                scene2d.to_rgb(inp.frame(k)), raw_from_preview, wp, hp, step=8
            )
            self._mid_cache = (key, warped, valid)
        _, warped, valid = self._mid_cache
        self.scene.draw_mid(viz.blend(warped, base_rgb, alpha, mask=valid))
