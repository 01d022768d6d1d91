"""Seed view: its panel (the seed pairs, heading and scale, the run settings, the fits' results,
the review options, the magnifier and the reference frame's control-point table)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from app.gui.calls import TYPED_SEED_DISTANCE_PX
from app.gui.context import Client
from app.gui.security import escape_md
from app.gui.state import TRANSFORMS
from app.gui.views.cptable.panel import ControlPointPanel
from app.gui.views.seed.scene import MAGNIFIER_PX, MAGNIFIER_ZOOM
from app.gui.views.widgets import ClientCallback, on_any_change, on_change, on_choice, on_press
from registration.run import config

ALERT_STYLE = (
    "background:#fff0f0;border-left:4px solid #e03131;color:#8a1c1c;padding:6px 8px;"
    "margin:4px 0;font-size:0.85rem;white-space:normal"
)
FIT_TARGETS = {"Frame": ("frame",), "Map": ("base",), "Both": ("frame", "base")}
"""The "Fit view to" buttons: the planes each shows."""


@dataclass(frozen=True)
class ReviewOptions:
    """What the match review draws.

    Attributes:
        match_lines: draw the coarse step's matches as lines between frame and map.
        max_lines: at most this many match lines (a sample spread over the frame).
        outliers: matches and control points REQCON or RANSAC rejected, too.
        ungated: matches outside the seed's location gate, too.
        gate: the gate's outline on the map.
        template_lines: control points as lines between frame and map.
        vector_scale: residual vectors' length per base px of residual (0 = automatic).
    """

    outliers: bool
    ungated: bool
    gate: bool
    template_lines: bool
    vector_scale: float
    match_lines: bool = True
    max_lines: int = 150


class SeedPanel:
    """Widgets of the Seed view: typed values and callbacks for the view."""

    def __init__(self, gui) -> None:
        self.ref_slider = gui.add_slider("Reference frame", 0, 1, 1, 0)
        self.pair = gui.add_button_group("Place seed pair", ("Pair 1", "Pair 2"))
        self.seed_md = gui.add_markdown("")
        self.alert = gui.add_html("")
        self.heading_md = gui.add_markdown("")
        self.edit = gui.add_button_group("Seed", ("Undo", "Clear pair 2", "Clear all"))
        with gui.add_folder("Correct heading and scale", expand_by_default=False):
            self.heading_in = gui.add_number("Heading (°)", 0.0, min=-360.0, max=360.0, step=0.1)
            self.scale_in = gui.add_number(
                "Scale (map px per frame px)", 1.0, min=1e-3, max=1e3, step=1e-4
            )
            self.btn_typed = gui.add_button("Use typed heading and scale")
            gui.add_markdown(
                f"_Typed values reach the coarse step as a second seed pair "
                f"{TYPED_SEED_DISTANCE_PX:.0f} px from the seed (drawn as pair 2, it follows "
                "pair 1). Placing pair 2 by hand instead fixes heading and scale exactly too. "
                "Heading: clockwise on screen from the frame to the map._"
            )
        self.fit = gui.add_button_group("Fit view to", ("Frame", "Map", "Both"))
        self.magnifier = gui.add_image(
            np.full(
                (2 * MAGNIFIER_PX * MAGNIFIER_ZOOM, 4 * MAGNIFIER_PX * MAGNIFIER_ZOOM + 8, 3),
                240,
                np.uint8,
            ),
            label="Magnifier: frame | map",
            format="png",
        )
        with gui.add_folder("Run settings", expand_by_default=False):
            self.preset = gui.add_dropdown("Preset", tuple(config.PRESETS), initial_value="default")
            self.transform = gui.add_dropdown(
                "Transform", tuple(TRANSFORMS), initial_value="polyprojective 2"
            )
            self.local = gui.add_checkbox("Local displacement field", True)
            self.adjust = gui.add_checkbox("Adjust the frames together", True)
            self.auto_fit = gui.add_checkbox("Fit after each seed change", True)
        self.btn_coarse = gui.add_button("Run coarse step")
        self.coarse_md = gui.add_markdown("")
        self.btn_fine = gui.add_button("Run fine step")
        self.fine_md = gui.add_markdown("")
        with gui.add_folder("Review", expand_by_default=False):
            self.review_md = gui.add_markdown("")
            self.show_match_lines = gui.add_checkbox("Match lines", True)
            self.max_lines = gui.add_slider("Match lines drawn (at most)", 10, 1000, 10, 150)
            self.show_outliers = gui.add_checkbox("Show outliers", False)
            self.show_ungated = gui.add_checkbox("Show matches outside the gate", False)
            self.show_gate = gui.add_checkbox("Show the gate", True)
            self.show_template_matches = gui.add_checkbox("Template matches as lines", False)
            self.vec_scale = gui.add_slider(
                "Residual vector scale (0 = auto)", 0.0, 200.0, 1.0, 0.0
            )
            self.mid_opacity = gui.add_slider("Mid base image opacity", 0.0, 1.0, 0.05, 0.0)
        with gui.add_folder("Control points"):
            self.cps = ControlPointPanel(gui, editable=True, scope="seed")

    # ---------------------------------------------------------------- callbacks
    def on_reference_frame_changed(self, callback: Callable[[int, Client], None]) -> None:
        on_change(self.ref_slider, int, callback)

    def on_pair_chosen(self, callback: Callable[[int, Client], None]) -> None:
        """``callback(pair, client)``: which seed pair (1 or 2) the next clicks place."""
        on_choice(
            self.pair,
            {
                "Pair 1": lambda client: callback(1, client),
                "Pair 2": lambda client: callback(2, client),
            },
        )

    def on_seed_edits(
        self, *, undo: ClientCallback, clear_pair2: ClientCallback, clear_all: ClientCallback
    ) -> None:
        on_choice(self.edit, {"Undo": undo, "Clear pair 2": clear_pair2, "Clear all": clear_all})

    def on_use_typed(self, callback: Callable[[float, float, Client], None]) -> None:
        """``callback(heading_deg, scale, client)`` with the typed heading and scale."""
        on_press(
            self.btn_typed,
            lambda client: callback(
                float(self.heading_in.value), float(self.scale_in.value), client
            ),
        )

    def on_fit_view(self, callback: Callable[[tuple[str, ...], Client], None]) -> None:
        """``callback(plane names, client)``: the planes to fit the camera to."""
        on_choice(
            self.fit,
            {
                label: (lambda client, keys=keys: callback(keys, client))
                for label, keys in FIT_TARGETS.items()
            },
        )

    def on_preset_changed(self, callback: Callable[[str, Client], None]) -> None:
        on_change(self.preset, str, callback)

    def on_transform_changed(self, callback: Callable[[str, Client], None]) -> None:
        on_change(self.transform, str, callback)

    def on_local_field_changed(self, callback: Callable[[bool, Client], None]) -> None:
        on_change(self.local, bool, callback)

    def on_adjust_changed(self, callback: Callable[[bool, Client], None]) -> None:
        on_change(self.adjust, bool, callback)

    def on_run_coarse(self, callback: ClientCallback) -> None:
        on_press(self.btn_coarse, callback)

    def on_run_fine(self, callback: ClientCallback) -> None:
        on_press(self.btn_fine, callback)

    def on_review_changed(self, callback: ClientCallback) -> None:
        on_any_change(
            (
                self.show_match_lines,
                self.max_lines,
                self.show_outliers,
                self.show_ungated,
                self.show_gate,
                self.show_template_matches,
                self.vec_scale,
            ),
            callback,
        )

    def on_mid_opacity_changed(self, callback: ClientCallback) -> None:
        self.mid_opacity.on_update(lambda event: callback(event.client))

    # ---------------------------------------------------------------- values
    def configure(self, n_frames: int) -> None:
        self.ref_slider.max = max(n_frames - 1, 1)
        self.ref_slider.disabled = n_frames <= 1

    @property
    def reference_frame(self) -> int:
        return int(self.ref_slider.value)

    @reference_frame.setter
    def reference_frame(self, k: int) -> None:
        self.ref_slider.value = int(k)

    def show_settings(
        self, preset: str, transform: str, run_local: bool, adjust: bool = True
    ) -> None:
        """The run settings of the session (an unknown preset leaves the dropdown as it is)."""
        if preset in self.preset.options:
            self.preset.value = preset
        self.transform.value = transform
        self.local.value = run_local
        self.adjust.value = adjust

    @property
    def fit_after_seed_change(self) -> bool:
        return bool(self.auto_fit.value)

    def review(self) -> ReviewOptions:
        return ReviewOptions(
            outliers=bool(self.show_outliers.value),
            ungated=bool(self.show_ungated.value),
            gate=bool(self.show_gate.value),
            template_lines=bool(self.show_template_matches.value),
            vector_scale=float(self.vec_scale.value),
            match_lines=bool(self.show_match_lines.value),
            max_lines=int(self.max_lines.value),
        )

    def show_review_counts(self, text: str) -> None:
        """What the match review draws, with counts (markdown)."""
        self.review_md.content = text

    @property
    def mid_opacity_value(self) -> float:
        """Opacity of the reference frame warped over the map (0: not drawn)."""
        return float(self.mid_opacity.value)

    @mid_opacity_value.setter
    def mid_opacity_value(self, alpha: float) -> None:
        self.mid_opacity.value = float(alpha)

    def show_typed(self, heading_deg: float, scale: float) -> None:
        """Where a correction of heading and scale starts from (rounded as the boxes show)."""
        self.heading_in.value = round(heading_deg, 1)
        self.scale_in.value = round(scale, 4)

    def show_magnifier(self, image: np.ndarray) -> None:
        self.magnifier.image = image

    # ---------------------------------------------------------------- texts
    def show_seeds(self, pairs: dict, active: int, typed: bool) -> None:
        rows = ["| pair | frame (raw px) | map (px) |", "|---|---|---|"]
        for i in (1, 2):
            f, b = pairs[i]
            ft = f"({f[0]:.1f}, {f[1]:.1f})" if f else "—"
            bt = f"({b[0]:.1f}, {b[1]:.1f})" if b else "—"
            mark = " ◀" if i == active else ""
            how = " (typed)" if i == 2 and typed and f else ""
            rows.append(f"| {i}{mark}{how} | {ft} | {bt} |")
        text = "\n".join(rows)
        f1, b1 = pairs[1]
        if not f1 or not b1:
            nxt = "frame (left)" if not f1 else "map (right)"
            text += f"\n\n_Click the {nxt} to place pair 1; drag a marker to refine it._"
        self.seed_md.content = text

    def show_heading(self, text: str) -> None:
        self.heading_md.content = text

    def show_alert(self, failures: list[tuple[str, str]]) -> None:
        """Failed steps, prominently (red box under the seed table): ``(title, reason)``."""
        self.alert.content = "".join(
            f'<div class="aerialreg-alert" style="{ALERT_STYLE}"><b>{escape_md(title)}:</b> '
            f"{escape_md(reason)}</div>"
            for title, reason in failures
        )

    def show_coarse(self, c, gate_text: str, *, stale: bool = False) -> None:
        """The coarse step's counts (``c``: ``CoarseResult`` or None); ``stale``: a fit exists
        but for other settings."""
        if c is None:
            self.coarse_md.content = (
                "_Settings changed since the last fit: run it again._" if stale else ""
            )
            return
        self.coarse_md.content = (
            "| keypoints frame | keypoints map | matches | gated | inliers |\n|---|---|---|---|---|\n"
            f"| {c.n_keypoints_frame} | {c.n_keypoints_base} | {c.n_matches} | {int(c.gated.sum())} "
            f"| {c.n_inliers} |\n\n{gate_text}; {c.time_s:.2f} s" + ("" if c else "; **failed**")
        )

    def show_fine(self, fine, edited: bool) -> None:
        if fine is None:
            self.fine_md.content = ""
            return
        n, kept = len(fine.src), int(fine.kept.sum())
        how = (
            "re-fitted to the enabled points"
            if edited
            else f"REQCON kept {kept}, {fine.iterations} iterations"
        )
        model = f"; {fine.model_kind} kept: {fine.model_reason}" if fine.model_reason else ""
        self.fine_md.content = (
            f"{n} control points; {how}; residual RMS {fine.residual_rms_px:.2f} px; "
            f"{fine.time_s:.2f} s" + ("" if fine else "; **failed**") + model
        )
