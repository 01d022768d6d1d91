"""One control-point table on screen, shared by the Seed view (the reference frame's fine fit,
editable there) and the Sequence view (the frame under the scrubber, read-only): the rows
(:class:`app.gui.controlpoints.ControlPointTable`), the selected row, paging, centring the
camera on the selected point, export as QGIS ``.points``.

What differs between the two views is given, not copied: the notes shown with the table, what
the view redraws when a point is selected, and the region the camera shows around it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from app.gui import controlpoints, scene2d
from app.gui.context import Client, ViewContext
from app.gui.controlpoints import ControlPointTable
from app.gui.views.cptable.panel import ControlPointPanel

RegionOf = Callable[[ControlPointTable, int], list[scene2d.PlaneGeometry]]
"""``(table, row position) -> planes`` the camera shows around a selected point."""


def map_unit(inputs) -> tuple[str, float] | None:
    """``(unit, map units per base px)`` of the opened base map's georeference when it has a
    projected CRS (residuals in metres or feet); None for a plain image or degrees."""
    georef = getattr(inputs, "base_georef", None)
    if georef is None or georef.crs is None or not georef.crs.is_projected:
        return None
    unit = georef.units or "map unit"
    short = {"metre": "m", "meter": "m", "US survey foot": "ft", "foot": "ft"}.get(unit, unit)
    return short, float(np.mean(georef.pixel_size))


class ControlPointTableView:
    """The rows shown in ``panel`` and the selected one.

    Args:
        ctx: the app as the view sees it (events, camera, downloads).
        panel: the table's widgets.
        scope: the event name's scope (clicked rows arrive as ``cp-select:<scope>``).
        note: shown under a table; ``empty_note`` when there is none.
        region: where the camera goes to show a selected point.
        on_selected: ``(row id, client)``: redraw what marks the selected point.

    Attributes:
        table: the rows (None: no table for what is shown).
        selected: id of the selected row, or None.
    """

    def __init__(
        self,
        ctx: ViewContext,
        panel: ControlPointPanel,
        *,
        scope: str,
        note: str,
        empty_note: str,
        region: RegionOf,
        on_selected: Callable[[int, Client], None],
    ) -> None:
        self.ctx = ctx
        self.panel = panel
        self.note, self.empty_note = note, empty_note
        self.region = region
        self.on_selected = on_selected
        self.table: ControlPointTable | None = None
        self.selected: int | None = None
        panel.on_sort_changed(lambda client: self.show())
        panel.on_page(lambda direction, client: self.turn_page(direction))
        panel.on_select(self.select)
        ctx.events.on(f"cp-select:{scope}", lambda value, client: self.select(int(value), client))

    def set_table(self, table: ControlPointTable | None, *, fresh: bool = False) -> None:
        """Show ``table``; ``fresh`` (another frame's table): no selection, first page."""
        self.table = table
        if fresh:
            self.selected = None
            self.panel.offset = 0
        self.show()

    def show(self) -> None:
        note = self.note if self.table is not None else self.empty_note
        self.panel.show(self.table, self.selected, note, map_unit(self.ctx.inputs))

    def turn_page(self, direction: int) -> None:
        if self.table is not None:
            self.panel.turn(direction, len(self.table.ids))
            self.show()

    def selected_row(self) -> int | None:
        """Position of the selected row in :attr:`table`, or None."""
        if self.table is None or self.selected is None:
            return None
        return self.table.row(self.selected)

    def select(self, row_id: int, client: Client = None) -> None:
        """Select a row (a row click, the id box, a click near the point): highlight it, page
        to it, let the view mark it, and centre the camera on it."""
        table = self.table
        if table is None or row_id < 0 or table.row(row_id) is None:
            return
        self.selected = int(row_id)
        offset = self.panel.offset_for(table, row_id)
        if offset is not None:
            self.panel.offset = offset
        if self.panel.selected_id != row_id:
            self.panel.selected_id = row_id  # runs select again (the box's callback)
        self.show()
        self.on_selected(int(row_id), client)
        self.centre_on_selected(client)

    def centre_on_selected(self, client: Client = None) -> None:
        i = self.selected_row()
        if i is not None:
            self.ctx.focus(self.region(self.table, i), client)

    def export(self, path: Path, client: Client = None, *, when_empty: str) -> bool:
        """The table as QGIS ``.points`` at ``path`` (map coordinates for a georeferenced base),
        sent to the browser; ``when_empty`` says why there is nothing to export."""
        if self.table is None:
            self.ctx.notify(client, "No control points", when_empty, color="yellow")
            return False
        controlpoints.write_qgis_points(self.table, path, self.ctx.inputs.base_georef)
        return self.ctx.offer_file(path, client)
