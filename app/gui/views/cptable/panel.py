"""The control-point table's widgets (Seed view: the reference frame, editable; Sequence view: the
frame under the scrubber, read-only): a summary, a page of rows as a clickable HTML table, the
selected point's actions, export as QGIS ``.points``.

Clicking a row sends ``("cp-select:<scope>", id)`` through the app's event channel
(``static/events.js``); the "Point id" box does the same without the script.
"""

from __future__ import annotations

import numpy as np

from app.gui.controlpoints import SORTS, ControlPointTable
from app.gui.security import escape_md

PAGE_ROWS = 25


def _fmt(v: float, digits: int = 1) -> str:
    return "–" if not np.isfinite(v) else f"{v:.{digits}f}"


def table_html(table: ControlPointTable, positions, selected: int | None, scope: str) -> str:
    """An HTML table of the rows at ``positions`` (clickable; the selected row highlighted)."""
    head = "".join(
        f"<th>{h}</th>"
        for h in ("id", "frame x", "frame y", "map x", "map y", "dx", "dy", "res.", "source", "on")
    )
    rows = []
    res = table.residual
    for i in positions:
        rid = int(table.ids[i])
        cls = []
        if rid == selected:
            cls.append("selected")
        if not table.enabled[i]:
            cls.append("off")
        fx, fy = table.frame_xy[i]
        bx, by = table.base_xy[i]
        dx, dy = table.residual_xy[i]
        cells = (
            f"<td>{rid}</td><td>{_fmt(fx)}</td><td>{_fmt(fy)}</td><td>{_fmt(bx)}</td>"
            f"<td>{_fmt(by)}</td><td>{_fmt(dx, 2)}</td><td>{_fmt(dy, 2)}</td>"
            f"<td>{_fmt(res[i], 2)}</td><td style='text-align:left'>{escape_md(table.source[i])}</td>"
            f"<td>{'✓' if table.enabled[i] else '✗'}</td>"
        )
        rows.append(
            f'<tr data-row="{rid}" class="{" ".join(cls)}" '
            f"onclick=\"window.aerialreg && window.aerialreg.send('cp-select:{scope}', {rid})\">"
            f"{cells}</tr>"
        )
    return (
        '<div class="aerialreg-scroll"><table class="aerialreg-table">'
        f"<thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table></div>"
    )


class ControlPointPanel:
    """Widgets of one control-point table (build inside a folder)."""

    def __init__(self, gui, *, editable: bool, scope: str) -> None:
        self.scope = scope
        self.editable = editable
        self.summary = gui.add_markdown("No control points yet.")
        self.sort = gui.add_dropdown("Sort by", SORTS, initial_value=SORTS[0])
        self.page = gui.add_button_group("Rows", ("◀ previous", "next ▶"))
        self.table = gui.add_html("")
        self.selected = gui.add_number("Point id", -1, min=-1, step=1)
        options = ("Centre", "Enable / disable", "Delete") if editable else ("Centre",)
        self.actions = gui.add_button_group("Selected point", options)
        if editable:
            self.bulk = gui.add_button_group(
                "Points", ("Disable worst", "Add manual", "Reset edits")
            )
            self.manual_md = gui.add_markdown("")
        self.export = gui.add_button("Export control points (.points)")
        self.offset = 0

    def show(self, table: ControlPointTable | None, selected: int | None, note: str = "") -> None:
        """Show ``table`` (None: nothing to show) with ``selected`` highlighted."""
        if table is None or not len(table.ids):
            self.summary.content = note or "No control points yet."
            self.table.content = ""
            return
        order = table.order(str(self.sort.value))
        n = len(order)
        self.offset = int(np.clip(self.offset, 0, max(n - 1, 0) // PAGE_ROWS * PAGE_ROWS))
        page = order[self.offset : self.offset + PAGE_ROWS]
        model = getattr(table.model, "degree", None)
        kind = {1: "projective"}.get(model, f"polyprojective {model}") if model else "no model"
        text = (
            f"**{n}** points, **{table.n_enabled}** enabled; RMS of the enabled "
            f"**{_fmt(table.rms, 3)} px** ({kind}); rows {self.offset + 1}-"
            f"{self.offset + len(page)} of {n}, sorted by {escape_md(self.sort.value)}"
        )
        if table.reason:
            text += f"  \n**Fit failed:** {escape_md(table.reason)}"
        if note:
            text += f"  \n{note}"
        self.summary.content = text
        self.table.content = table_html(table, page, selected, self.scope)

    def offset_for(self, table: ControlPointTable, row_id: int) -> int | None:
        """The page offset that shows ``row_id`` (the table jumps to a selected point)."""
        order = table.order(str(self.sort.value))
        pos = np.flatnonzero(table.ids[order] == int(row_id))
        if not len(pos):
            return None
        return int(pos[0]) // PAGE_ROWS * PAGE_ROWS

    def turn(self, direction: int, n_rows: int) -> None:
        self.offset = int(np.clip(self.offset + direction * PAGE_ROWS, 0, max(n_rows - 1, 0)))
        self.offset -= self.offset % PAGE_ROWS
