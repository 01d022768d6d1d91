"""The reference frame's control points in the Seed view: the fine fit's points plus the analyst's
edits (points switched on or off, deleted, added by hand) in the shared control-point table
(:class:`app.gui.views.cptable.table.ControlPointTableView`), the least-squares re-fit that
follows every edit, and export as QGIS ``.points``.

Edits change the state (undoable) and post the re-fit to the worker; the re-fit publishes the
fit the run will use (``ReferenceFit.fine``) and asks the view to redraw.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from app.gui import controlpoints, scene2d
from app.gui.context import Client, ViewContext
from app.gui.controlpoints import Edits
from app.gui.views.cptable.panel import ControlPointPanel
from app.gui.views.cptable.table import ControlPointTableView
from app.gui.views.seed.scene import SeedScene
from registration import global_registration

CENTRE_MARGIN_PX = 150
"""Map and frame pixels shown around a selected point on both images."""


class ReferencePoints:
    """The Seed view's control-point table and its edits.

    Args:
        ctx: the app as the view sees it.
        panel: the table's widgets (editable).
        scene: the Seed view's scene (the camera centres on its planes).
        submit: the view's worker requests (``(key, fn)``, latest per key wins).
        on_fit_changed: the fit the run uses changed (re-fitted): redraw what shows it.
        redraw_overlays: the overlays changed (no table, the manual point's first click).
        on_selected: a point was selected: redraw the overlays and the magnifier.

    Attributes:
        manual_mode: the next two clicks add a manual point (frame, then map).
        manual_frame: raw frame px of a manual point's first click, or None.
    """

    def __init__(
        self,
        ctx: ViewContext,
        panel: ControlPointPanel,
        scene: SeedScene,
        *,
        submit: Callable[[str, Callable[[], None]], None],
        on_fit_changed: Callable[[], None],
        redraw_overlays: Callable[[], None],
        on_selected: Callable[[], None],
    ) -> None:
        self.ctx, self.state = ctx, ctx.state
        self.panel, self.scene = panel, scene
        self.submit = submit
        self.on_fit_changed = on_fit_changed
        self.redraw_overlays = redraw_overlays
        self.manual_mode = False
        self.manual_frame: tuple[float, float] | None = None
        self.cp = ControlPointTableView(
            ctx,
            panel,
            scope="seed",
            note="",
            empty_note="Run the fine step to list its control points.",
            region=self._region,
            on_selected=lambda row_id, client: on_selected(),
        )
        panel.on_point_actions(
            centre=self.centre_selected, toggle=self.toggle_selected, delete=self.delete_selected
        )
        panel.on_edits(
            disable_worst=lambda client: self.disable_worst(),
            add_manual=self.toggle_manual,
            reset=lambda client: self.reset_edits(),
        )
        panel.on_export(self.export)
        panel.on_typed_map_point(self.typed_map_point)
        panel.on_import(self.import_points)

    @property
    def table(self) -> controlpoints.ControlPointTable | None:
        return self.cp.table

    # ---------------------------------------------------------------- the table (worker)
    def refit(self, save: bool = True) -> None:
        """The table for the current fine fit plus the analyst's edits; re-fit when edited.

        A least-squares fit: run it on the worker or a job, never on a callback."""
        inp = self.ctx.inputs
        with self.state.lock:
            ref = self.state.current_reference()
            edits = self.state.cp_edits.copy()
            gamma, k = self.state.gamma, self.state.reference_frame
            camera = None if inp is None else self.state.camera()
        if inp is None or ref is None or ref.fine_auto is None:
            self.cp.table = None
            self.show()
            self.redraw_overlays()
            return
        auto = ref.fine_auto
        table = controlpoints.table_from_points(
            auto.src,
            auto.dst,
            auto.kept,
            auto.source,
            "reference",
            camera,
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
        self.cp.table = table
        if save:
            self.ctx.save()
        self.show()
        self.on_fit_changed()

    def show(self) -> None:
        """The table and, while a manual point is being added, what to click next."""
        if not self.manual_mode:
            hint = ""
        elif self.manual_frame is None:
            hint = "**Adding a manual point:** click it on the frame, then on the map."
        else:
            hint = "**Adding a manual point:** now click the same place on the map."
        self.panel.show_manual_hint(hint)
        self.cp.show()

    def _region(self, table, i: int) -> list[scene2d.PlaneGeometry]:
        """Both images around row ``i``'s frame and map points."""
        fp, bp = self.scene.planes["frame"].geom, self.scene.planes["base"].geom
        a = fp.world_from_pixel(table.corrected_xy[i])
        b = bp.world_from_pixel(table.base_xy[i])
        span = CENTRE_MARGIN_PX * scene2d.WORLD_PER_PX
        lo = np.minimum(a[:2], b[:2]) - span
        hi = np.maximum(a[:2], b[:2]) + span
        return [
            scene2d.PlaneGeometry(
                int((hi[0] - lo[0]) / scene2d.WORLD_PER_PX),
                int((hi[1] - lo[1]) / scene2d.WORLD_PER_PX),
                position=((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.0),
            )
        ]

    # ---------------------------------------------------------------- edits (callbacks)
    def _n_auto(self) -> int:
        with self.state.lock:
            ref = self.state.current_reference()
        return 0 if ref is None or ref.fine_auto is None else len(ref.fine_auto.src)

    def _selected_or_say(self, client: Client) -> int | None:
        if self.cp.selected_row() is None:
            self.ctx.notify(
                client, "No point selected", "Click a row of the table first", color="yellow"
            )
            return None
        return self.cp.selected

    def centre_selected(self, client: Client = None) -> None:
        if self._selected_or_say(client) is not None:
            self.cp.centre_on_selected(client)

    def toggle_selected(self, client: Client = None) -> None:
        """Switch the selected point on or off, then re-fit."""
        rid = self._selected_or_say(client)
        if rid is None:
            return
        on = bool(self.table.enabled[self.table.row(rid)])
        n_auto = self._n_auto()
        with self.state.lock:
            self.state.push_undo()
            if rid < n_auto:
                self.state.cp_edits.enabled[rid] = not on
            else:
                self.state.cp_edits.manual_enabled[rid] = not on
            self.state.revision += 1
        self.submit("refit", self.refit)

    def delete_selected(self, client: Client = None) -> None:
        """Remove the selected point from the table, then re-fit."""
        rid = self._selected_or_say(client)
        if rid is None:
            return
        n_auto = self._n_auto()
        with self.state.lock:
            self.state.push_undo()
            edits = self.state.cp_edits
            if rid < n_auto:
                edits.deleted.add(rid)
            else:
                del edits.manual[rid - n_auto]
                edits.manual_enabled = {
                    (i if i < rid else i - 1): v
                    for i, v in edits.manual_enabled.items()
                    if i != rid
                }
            self.cp.selected = None
            self.state.revision += 1
        self.submit("refit", self.refit)

    def disable_worst(self) -> int | None:
        """Disable the enabled point with the largest residual and re-fit (returns its id)."""
        worst = None if self.table is None else self.table.worst_enabled()
        if worst is None:
            return None
        n_auto = self._n_auto()
        with self.state.lock:
            self.state.push_undo()
            if worst < n_auto:
                self.state.cp_edits.enabled[worst] = False
            else:
                self.state.cp_edits.manual_enabled[worst] = False
            self.state.revision += 1
        self.submit("refit", self.refit)
        return worst

    def reset_edits(self) -> None:
        """Back to REQCON's points (undoable), then re-fit."""
        if self.table is None:
            return
        with self.state.lock:
            self.state.push_undo()
            self.state.cp_edits = Edits()
            self.state.revision += 1
        self.submit("refit", self.refit)

    def toggle_manual(self, client: Client = None) -> None:
        """Start (or stop) adding a manual point: the next clicks are frame, then map."""
        with self.state.lock:
            ok = self.state.current_reference() is not None
        if not ok:
            self.ctx.notify(
                client,
                "Fit the reference frame first",
                "Manual points refine a fine fit",
                color="yellow",
            )
            return
        self.manual_mode = not self.manual_mode
        self.manual_frame = None
        self.redraw_overlays()
        self.show()

    def manual_click(self, plane: str, point: tuple[float, float], client: Client) -> None:
        """A click while adding a manual point: raw frame px first, then base px."""
        if plane == "frame":
            self.manual_frame = point
        elif self.manual_frame is None:
            self.ctx.notify(
                client,
                "Frame first",
                "Click the point on the frame, then on the map",
                color="yellow",
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
        self.show()
        self.redraw_overlays()

    def typed_map_point(self, x: float, y: float, client: Client = None) -> bool:
        """The map side of the manual point being added, typed: map coordinates in the base
        map's CRS when it is georeferenced, else base px."""
        if not self.manual_mode or self.manual_frame is None:
            self.ctx.notify(
                client,
                "Frame point first",
                "Press Add manual and click the point on the frame, then type its map coordinates",
                color="yellow",
            )
            return False
        georef = getattr(self.ctx.inputs, "base_georef", None)
        if not (np.isfinite(x) and np.isfinite(y)):
            self.ctx.notify(client, "Not a position", f"({x}, {y})", color="red")
            return False
        b = georef.base_from_map([[x, y]])[0] if georef is not None else np.array([x, y])
        w, h = self.ctx.inputs.base_size
        if not (-0.5 <= b[0] <= w - 0.5 and -0.5 <= b[1] <= h - 0.5):
            self.ctx.notify(
                client,
                "Outside the map",
                f"({x:g}, {y:g}) is at base pixel ({b[0]:.1f}, {b[1]:.1f}), outside the "
                f"{w}x{h} map",
                color="red",
            )
            return False
        self.manual_click("base", (float(b[0]), float(b[1])), client)
        return True

    def import_points(self, name: str, content: bytes, client: Client = None) -> bool:
        """Add the control points of an uploaded QGIS ``.points`` file (of the reference frame;
        :func:`app.gui.controlpoints.read_qgis_points`) as manual points, enabled as the file
        says (undoable), then re-fit."""
        import tempfile
        from pathlib import Path

        from registration.evaluation.points import MAX_POINTS_FILE_BYTES

        inp = self.ctx.inputs
        with self.state.lock:
            fitted = self.state.current_reference() is not None
        if inp is None or not fitted:
            self.ctx.notify(
                client, "Fit the reference frame first", "Imported points refine a fine fit",
                color="yellow",
            )  # fmt: skip
            return False
        if len(content) > MAX_POINTS_FILE_BYTES:
            self.ctx.notify(client, "Not imported", f"{name} is over the size limit", color="red")
            return False
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / (Path(name).name or "control.points")
            path.write_bytes(content)
            try:
                rows, enabled = controlpoints.read_qgis_points(
                    path, inp.frame_size, inp.base_size, getattr(inp, "base_georef", None)
                )
            except (ValueError, UnicodeDecodeError) as exc:
                self.ctx.notify(client, "Not imported", str(exc), color="red")
                return False
        n_auto = self._n_auto()
        with self.state.lock:
            self.state.push_undo()
            edits = self.state.cp_edits
            first = n_auto + len(edits.manual)
            edits.manual.extend(tuple(float(v) for v in row) for row in rows)
            for i in np.flatnonzero(~enabled):
                edits.manual_enabled[first + int(i)] = False
            self.state.revision += 1
        self.submit("refit", self.refit)
        off = int((~enabled).sum())
        self.ctx.notify(
            client,
            "Control points imported",
            f"{len(rows)} manual points from {name}" + (f" ({off} disabled)" if off else ""),
            color="green",
        )
        return True

    def export(self, client: Client = None) -> bool:
        """The table as QGIS ``.points`` in the project, sent to the browser."""
        with self.state.lock:
            k = self.state.reference_frame
        path = self.ctx.project.folder / f"reference_frame_{k:06d}.points"
        return self.cp.export(path, client, when_empty="Run the fine step first")
