"""The Seed view's control-point table actions (a mixin of :class:`app.gui.views.seed.view.SeedView`):
the table of the reference frame's fine fit plus the analyst's edits, selection, enable /
disable / delete, manual points, the least-squares re-fit, export as QGIS ``.points``.

Kept apart from the seeding and drawing in ``seed.py``; the mixin uses the view's ``state``,
``app``, ``panel``, ``scene`` and its drawing requests (``request_overlays``, ``draw_overlays``,
``draw_mid``, ``draw_magnifier``, ``refresh_text``).
"""

from __future__ import annotations

import numpy as np

from app.gui import controlpoints, scene2d
from app.gui.controlpoints import Edits
from registration import global_registration
from registration.lens import radial


class ControlPointActions:
    """Control-point table actions of the Seed view."""

    table: controlpoints.ControlPointTable | None
    selected: int | None

    def refit(self, save: bool = True) -> None:
        """The table for the current fine fit plus the analyst's edits; re-fit when edited."""
        inp = self.app.inputs
        with self.state.lock:
            ref = self.state.current_reference()
            edits = self.state.cp_edits.copy()
            gamma, k = self.state.gamma, self.state.reference_frame
        if inp is None or ref is None or ref.fine_auto is None:
            self.table = None
            self.show_table()
            self.request_overlays()
            return
        auto = ref.fine_auto
        harris = radial.HarrisModel(gamma, *inp.frame_size)
        table = controlpoints.table_from_points(
            auto.src,
            auto.dst,
            auto.kept,
            auto.source,
            "reference",
            harris,
            auto.base_from_corrected,
            edits,
        )
        fine = auto
        if not edits.empty and auto.base_from_corrected is not None:
            domain = global_registration.frame_domain(inp.frame(k), gamma)
            table, model = controlpoints.refit(table, auto.base_from_corrected, domain=domain)
            fine = global_registration.FineResult(
                success=model is not None,
                reason=table.reason,
                base_from_corrected=model,
                src=table.corrected_xy,
                dst=table.base_xy,
                kept=table.enabled.copy(),
                residuals=table.residual,
                iterations=0,
            )
        with self.state.lock:
            if self.state.reference is ref:
                ref.fine = fine
                self.state.revision += 1
        self.table = table
        self._mid_cache = None
        if save:
            self.app.save()
        self.show_table()
        self.refresh_text()
        self.app.state_changed()
        self.request_overlays()
        self.submit("mid", self.draw_mid)

    def show_table(self) -> None:
        note = "" if self.table is not None else "Run the fine step to list its control points."
        if self.manual_mode:
            self.panel.cps.manual_md.content = (
                "**Adding a manual point:** click it on the frame, then on the map."
                if self.manual_frame is None
                else "**Adding a manual point:** now click the same place on the map."
            )
        else:
            self.panel.cps.manual_md.content = ""
        self.panel.cps.show(self.table, self.selected, note)

    def turn_page(self, direction: int) -> None:
        if self.table is not None:
            self.panel.cps.turn(direction, len(self.table.ids))
            self.show_table()

    def select_point(self, row_id: int, client=None) -> None:
        """Select a control point (row click, id box): highlight it, page to it, centre the view
        and the magnifier on it."""
        table = self.table
        if table is None or row_id < 0 or table.row(row_id) is None:
            return
        self.selected = int(row_id)
        offset = self.panel.cps.offset_for(table, row_id)
        if offset is not None:
            self.panel.cps.offset = offset
        if int(self.panel.cps.selected.value) != row_id:
            self.panel.cps.selected.value = row_id  # runs select_point again: returns here
        self.show_table()
        self.request_overlays()
        self.submit("magnifier", self.draw_magnifier)
        self.centre_on_selected(client)

    def centre_on_selected(self, client=None) -> None:
        table = self.table
        i = None if table is None or self.selected is None else table.row(self.selected)
        if i is None:
            return
        fp, bp = self.scene.planes["frame"].geom, self.scene.planes["base"].geom
        a = fp.world_from_pixel(table.corrected_xy[i])
        b = bp.world_from_pixel(table.base_xy[i])
        span = 150 * scene2d.WORLD_PER_PX
        lo = np.minimum(a[:2], b[:2]) - span
        hi = np.maximum(a[:2], b[:2]) + span
        region = scene2d.PlaneGeometry(
            int((hi[0] - lo[0]) / scene2d.WORLD_PER_PX),
            int((hi[1] - lo[1]) / scene2d.WORLD_PER_PX),
            position=((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.0),
        )
        self.app.focus([region], client)

    def point_action(self, action: str, client=None) -> None:
        if self.table is None or self.selected is None or self.table.row(self.selected) is None:
            self.notify(client, "No point selected", "Click a row of the table first", "yellow")
            return
        if action == "Centre":
            self.centre_on_selected(client)
            return
        rid = self.selected
        n_auto = self._n_auto()
        with self.state.lock:
            self.state.push_undo()
            edits = self.state.cp_edits
            if action == "Delete":
                if rid < n_auto:
                    edits.deleted.add(rid)
                else:
                    del edits.manual[rid - n_auto]
                    edits.manual_enabled = {
                        (i if i < rid else i - 1): v
                        for i, v in edits.manual_enabled.items()
                        if i != rid
                    }
                self.selected = None
            else:
                on = bool(self.table.enabled[self.table.row(rid)])
                if rid < n_auto:
                    edits.enabled[rid] = not on
                else:
                    edits.manual_enabled[rid] = not on
            self.state.revision += 1
        self.submit("refit", self.refit)

    def _n_auto(self) -> int:
        with self.state.lock:
            ref = self.state.current_reference()
        return 0 if ref is None or ref.fine_auto is None else len(ref.fine_auto.src)

    def bulk_action(self, action: str, client=None) -> None:
        if action == "Add manual":
            with self.state.lock:
                ok = self.state.current_reference() is not None
            if not ok:
                self.notify(
                    client,
                    "Fit the reference frame first",
                    "Manual points refine a fine fit",
                    "yellow",
                )
                return
            self.manual_mode = not self.manual_mode
            self.manual_frame = None
            self.submit("overlays", self.draw_overlays)
            self.show_table()
            return
        if self.table is None:
            return
        with self.state.lock:
            self.state.push_undo()
            if action == "Reset edits":
                self.state.cp_edits = Edits()
            elif action == "Disable worst":
                worst = self.table.worst_enabled()
                if worst is None:
                    return
                if worst < self._n_auto():
                    self.state.cp_edits.enabled[worst] = False
                else:
                    self.state.cp_edits.manual_enabled[worst] = False
            self.state.revision += 1
        self.submit("refit", self.refit)

    def disable_worst(self) -> int | None:
        """Disable the enabled point with the largest residual and re-fit (returns its id)."""
        worst = None if self.table is None else self.table.worst_enabled()
        if worst is not None:
            self.bulk_action("Disable worst")
        return worst

    def manual_click(self, plane: str, point, client) -> None:
        if plane == "frame":
            self.manual_frame = point
        elif self.manual_frame is None:
            self.notify(
                client, "Frame first", "Click the point on the frame, then on the map", "yellow"
            )
            return
        else:
            with self.state.lock:
                self.state.push_undo()
                self.state.cp_edits.manual.append((*self.manual_frame, *point))
                self.state.revision += 1
            self.manual_mode = False
            self.manual_frame = None
            self.submit("refit", self.refit)
        self.show_table()
        self.submit("overlays", self.draw_overlays)

    def export_points(self, client=None) -> bool:
        """The table as QGIS ``.points`` in the project (map coordinates for a georeferenced
        base), sent to the browser."""
        if self.table is None:
            self.notify(client, "No control points", "Run the fine step first", "yellow")
            return False
        with self.state.lock:
            k = self.state.reference_frame
        path = self.app.project.folder / f"reference_frame_{k:06d}.points"
        controlpoints.write_qgis_points(self.table, path, self.app.inputs.base_georef)
        return self.app.offer_file(path, client)
