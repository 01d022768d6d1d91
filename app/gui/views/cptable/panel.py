"""The control-point table's widgets (Seed view: the reference frame, editable; Sequence view: the
frame under the scrubber, read-only): a summary, a page of rows as a clickable HTML table, the
selected point's actions, export as QGIS ``.points``.

Clicking a row sends ``("cp-select:<scope>", id)`` through the app's event channel
(``static/events.js``); the "Point id" box does the same without the script.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from app.gui.context import Client
from app.gui.controlpoints import SORTS, ControlPointTable
from app.gui.security import escape_md
from app.gui.views.widgets import ClientCallback, on_change, on_choice, on_press, on_upload

PAGE_ROWS = 25


def _fmt(v: float, digits: int = 1) -> str:
    return "–" if not np.isfinite(v) else f"{v:.{digits}f}"


def table_html(
    table: ControlPointTable,
    positions,
    selected: int | None,
    scope: str,
    unit: tuple[str, float] | None = None,
) -> str:
    """An HTML table of the rows at ``positions`` (clickable; the selected row highlighted);
    ``unit``: ``(name, map units per base px)`` adds the residual in map units."""
    names = ["id", "frame x", "frame y", "map x", "map y", "dx", "dy", "res. (px)"]
    if unit is not None:
        names.append(f"res. ({escape_md(unit[0])})")
    head = "".join(f"<th>{h}</th>" for h in (*names, "source", "on"))
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
            f"<td>{_fmt(res[i], 2)}</td>"
            + (f"<td>{_fmt(res[i] * unit[1], 3)}</td>" if unit is not None else "")
            + f"<td style='text-align:left'>{escape_md(table.source[i])}</td>"
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
            # A manual point's map side typed instead of clicked (QGIS's "enter coordinates"):
            # map coordinates of a georeferenced base, else base px.
            self.typed_x = gui.add_number("Map x (typed)", 0.0, step=0.01)
            self.typed_y = gui.add_number("Map y (typed)", 0.0, step=0.01)
            self.btn_typed = gui.add_button("Place the map point at these coordinates")
            # Control points made elsewhere (QGIS's Georeferencer, an earlier project).
            self.upload = gui.add_upload_button("Import control points (.points)", icon=None)
        self.export = gui.add_button("Export control points (.points)")
        self.offset = 0  # position of the first row shown, in the sorted order

    # ---------------------------------------------------------------- callbacks
    def on_sort_changed(self, callback: ClientCallback) -> None:
        self.sort.on_update(lambda event: callback(event.client))

    def on_page(self, callback: Callable[[int, Client], None]) -> None:
        """``callback(direction, client)``: -1 for the previous page, +1 for the next."""
        on_choice(
            self.page,
            {
                "◀ previous": lambda client: callback(-1, client),
                "next ▶": lambda client: callback(1, client),
            },
        )

    def on_select(self, callback: Callable[[int, Client], None]) -> None:
        """``callback(row id, client)`` when the analyst types a point id."""
        on_change(self.selected, int, callback)

    def on_point_actions(
        self,
        *,
        centre: ClientCallback,
        toggle: ClientCallback | None = None,
        delete: ClientCallback | None = None,
    ) -> None:
        """The selected point's buttons (``toggle`` and ``delete`` of an editable table)."""
        actions = {"Centre": centre}
        if self.editable:
            actions.update({"Enable / disable": toggle, "Delete": delete})
        on_choice(self.actions, {k: v for k, v in actions.items() if v is not None})

    def on_edits(
        self,
        *,
        disable_worst: ClientCallback,
        add_manual: ClientCallback,
        reset: ClientCallback,
    ) -> None:
        """The editable table's buttons for all points."""
        on_choice(
            self.bulk,
            {"Disable worst": disable_worst, "Add manual": add_manual, "Reset edits": reset},
        )

    def on_export(self, callback: ClientCallback) -> None:
        on_press(self.export, callback)

    def on_import(self, callback: Callable[[str, bytes, Client], None]) -> None:
        """``callback(file name, content, client)`` for an uploaded ``.points`` (editable)."""
        on_upload(self.upload, "control.points", callback)

    def on_typed_map_point(self, callback: Callable[[float, float, Client], None]) -> None:
        """``callback(x, y, client)`` with the typed map coordinates (editable table)."""
        on_press(
            self.btn_typed,
            lambda client: callback(float(self.typed_x.value), float(self.typed_y.value), client),
        )

    # ---------------------------------------------------------------- values
    @property
    def sort_key(self) -> str:
        """How rows are sorted (one of :data:`app.gui.controlpoints.SORTS`)."""
        return str(self.sort.value)

    @property
    def selected_id(self) -> int:
        """The id in the "Point id" box (-1: none)."""
        return int(self.selected.value)

    @selected_id.setter
    def selected_id(self, row_id: int) -> None:
        self.selected.value = int(row_id)

    def show_manual_hint(self, text: str) -> None:
        """What to click next while a manual point is being added ("" otherwise)."""
        self.manual_md.content = text

    def show(
        self,
        table: ControlPointTable | None,
        selected: int | None,
        note: str = "",
        unit: tuple[str, float] | None = None,
    ) -> None:
        """Show ``table`` (None: nothing to show) with ``selected`` highlighted; ``unit``:
        ``(name, map units per base px)`` of a georeferenced base, for residuals in map units."""
        if table is None or not len(table.ids):
            self.summary.content = note or "No control points yet."
            self.table.content = ""
            return
        order = table.order(self.sort_key)
        n = len(order)
        self.offset = int(np.clip(self.offset, 0, max(n - 1, 0) // PAGE_ROWS * PAGE_ROWS))
        page = order[self.offset : self.offset + PAGE_ROWS]
        model = getattr(table.model, "degree", None)
        kind = {1: "projective"}.get(model, f"polyprojective {model}") if model else "no model"
        text = (
            f"**{n}** points, **{table.n_enabled}** enabled; RMS of the enabled "
            f"**{_fmt(table.rms, 3)} px**"
            + (f" = {_fmt(table.rms * unit[1], 3)} {escape_md(unit[0])}" if unit else "")
            + f" ({kind}); rows {self.offset + 1}-"
            f"{self.offset + len(page)} of {n}, sorted by {escape_md(self.sort_key)}"
        )
        if table.reason:
            text += f"  \n**Fit failed:** {escape_md(table.reason)}"
        if note:
            text += f"  \n{note}"
        self.summary.content = text
        self.table.content = table_html(table, page, selected, self.scope, unit)

    def offset_for(self, table: ControlPointTable, row_id: int) -> int | None:
        """The page offset that shows ``row_id`` (the table jumps to a selected point)."""
        order = table.order(self.sort_key)
        pos = np.flatnonzero(table.ids[order] == int(row_id))
        if not len(pos):
            return None
        return int(pos[0]) // PAGE_ROWS * PAGE_ROWS

    def turn(self, direction: int, n_rows: int) -> None:
        self.offset = int(np.clip(self.offset + direction * PAGE_ROWS, 0, max(n_rows - 1, 0)))
        self.offset -= self.offset % PAGE_ROWS
