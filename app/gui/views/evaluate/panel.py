"""Evaluate view: its panel (the frame, the point being marked, the marks' table, Table 2 and
its own wide window)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import numpy as np

from app.gui.context import Client
from app.gui.security import escape_md
from app.gui.state import ANCHORS
from app.gui.views.widgets import ClientCallback, on_change, on_choice, on_press, on_upload

# The paper's Table 2 locations first, so the table reads like the paper's.
POINT_NAMES = ("NW", "NE", "Center", "SW", "SE")
TableFormat = Literal["csv", "markdown"]
"""How Table 2 is downloaded: ``TABLE2.csv`` or ``TABLE2.md``."""


class EvaluatePanel:
    """Widgets of the Evaluate view (and the Table 2 window): typed values and callbacks."""

    def __init__(self, gui) -> None:
        self.frame_slider = gui.add_slider("Frame", 0, 1, 1, 0)
        self.point_dd = gui.add_dropdown("Point", POINT_NAMES[:1], initial_value=POINT_NAMES[0])
        self.mark = gui.add_button_group(
            "Mark", ("New point", "Suggest", "Propose next", "Confirm", "Delete")
        )
        self.hint_md = gui.add_markdown("")
        self.marks_html = gui.add_html("")
        self.anchor = gui.add_dropdown(
            "Motion measured from",
            ANCHORS,
            initial_value=ANCHORS[0],
            hint="reference: each point's position in the reference frame (needs it marked there); "
            "mean: its mean position over the marked frames",
        )
        self.btn_table = gui.add_button("Compute Table 2")
        self.table_md = gui.add_markdown("")
        self.btn_export = gui.add_button("Export POINTS.csv")
        self.upload_points = gui.add_upload_button("Import POINTS.csv", icon=None)
        # Table 2 gets its own wide window (the sidebar is too narrow for 13 columns).
        self.table_panel = gui.add_panel(visible=False)
        with self.table_panel.add_tab("Table 2"):
            self.table2_md = gui.add_markdown("")
            self.download = gui.add_button_group("Download Table 2", ("CSV", "Markdown"))

    # ---------------------------------------------------------------- callbacks
    def on_frame_changed(self, callback: Callable[[int, Client], None]) -> None:
        on_change(self.frame_slider, int, callback)

    def on_point_changed(self, callback: Callable[[str, Client], None]) -> None:
        on_change(self.point_dd, str, callback)

    def on_anchor_changed(self, callback: Callable[[str, Client], None]) -> None:
        on_change(self.anchor, str, callback)

    def on_mark_actions(
        self,
        *,
        new_point: ClientCallback,
        propose_next: ClientCallback,
        suggest: ClientCallback,
        confirm: ClientCallback,
        delete: ClientCallback,
    ) -> None:
        """The Mark buttons, one action each."""
        on_choice(
            self.mark,
            {
                "New point": new_point,
                "Suggest": suggest,
                "Propose next": propose_next,
                "Confirm": confirm,
                "Delete": delete,
            },
        )

    def on_compute_table(self, callback: ClientCallback) -> None:
        on_press(self.btn_table, callback)

    def on_export_points(self, callback: ClientCallback) -> None:
        on_press(self.btn_export, callback)

    def on_import_points(self, callback: Callable[[str, bytes, Client], None]) -> None:
        """``callback(file name, content, client)`` for an uploaded POINTS.csv."""
        on_upload(self.upload_points, "POINTS.csv", callback)

    def on_download_table(self, callback: Callable[[TableFormat, Client], None]) -> None:
        on_choice(
            self.download,
            {
                "CSV": lambda client: callback("csv", client),
                "Markdown": lambda client: callback("markdown", client),
            },
        )

    # ---------------------------------------------------------------- values
    def configure(self, n_frames: int) -> None:
        self.frame_slider.max = max(n_frames - 1, 1)
        self.frame_slider.disabled = n_frames <= 1

    @property
    def frame(self) -> int:
        return int(self.frame_slider.value)

    @frame.setter
    def frame(self, k: int) -> None:
        self.frame_slider.value = int(k)

    def show_anchor(self, anchor: str) -> None:
        self.anchor.value = anchor

    def show_points(self, names: tuple[str, ...], current: str) -> None:
        """The point dropdown offers ``names`` and shows ``current`` (one of them)."""
        self.point_dd.options = names
        if self.point_dd.value != current:
            self.point_dd.value = current

    def show_table2_window(self, visible: bool) -> None:
        self.table_panel.visible = visible

    def show_marks(self, rows: list[dict], current: str) -> None:
        """``rows``: point, frame, x, y, pending (``PendingMark`` or None), residual (base px or
        None), offset (raw px from the registration's prediction, or None)."""
        if not rows:
            self.marks_html.content = ""
            self.hint_md.content = (
                "No points yet: click a ground point (e.g. a road marking) in the frame."
            )
            return
        body = []
        for r in rows:
            status = _status(r["pending"])
            res, off = _num(r["residual"]), _num(r.get("offset"))
            cls = "pending" if r["pending"] is not None else ""
            if r["point"] == current and r["current_frame"]:
                cls += " selected"
            body.append(
                f'<tr data-row="{r["frame"]}" class="{cls}" onclick="window.aerialreg && '
                f"window.aerialreg.send('eval-mark', [{_js_str(r['point'])}, {r['frame']}])\">"
                f"<td style='text-align:left'>{escape_md(r['point'])}</td><td>{r['frame']}</td>"
                f"<td>{r['x']:.1f}</td><td>{r['y']:.1f}</td>"
                f"<td style='text-align:left'>{escape_md(status)}</td><td>{off}</td><td>{res}</td></tr>"
            )
        n_pending = sum(r["pending"] is not None for r in rows)
        self.hint_md.content = (
            f"{len(rows)} marks"
            + (
                f", **{n_pending} proposed and not confirmed** (they count nowhere until confirmed)"
                if n_pending
                else ""
            )
            + ". Offset: raw px from where the registration puts the point (from its first "
            "confirmed mark); residual: base px from the point's anchor position, what Table 2 "
            "averages."
        )
        self.marks_html.content = (
            '<div class="aerialreg-scroll"><table class="aerialreg-table"><thead><tr><th>point</th>'
            "<th>frame</th><th>x</th><th>y</th><th>status</th><th>offset</th><th>res. (px)</th>"
            "</tr></thead>"
            f"<tbody>{''.join(body)}</tbody></table></div>"
        )

    def show_table2(self, markdown: str | None, summary: str) -> None:
        self.table_md.content = summary
        if markdown is None:
            self.table_panel.visible = False
            return
        self.table2_md.content = markdown
        self.table_panel.visible = True
        self.table_panel.float(x=16, y=-16, width=820)


def _num(value: float | None) -> str:
    return "–" if value is None or not np.isfinite(value) else f"{value:.2f}"


def _status(mark) -> str:
    """A mark's status cell: marked, proposed (refined, with its correlation), or why not."""
    if mark is None:
        return "marked"
    if not mark.confirmable:
        return f"predicted only ({mark.note}): click the point"
    if np.isfinite(mark.score):
        return f"proposed, NCC {mark.score:.2f}"
    return mark.note or "proposed"


def _js_str(text: str) -> str:
    """A JavaScript string literal safe inside a double-quoted HTML attribute."""
    import json

    return json.dumps(str(text)).replace("&", "&amp;").replace('"', "&quot;").replace("<", "&lt;")
