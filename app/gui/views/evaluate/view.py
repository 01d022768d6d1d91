"""Evaluate view: mark the same ground points in several frames, then the paper's Table 2 (section 6).

Points are marked on the raw frames (raw pixels, as POINTS.csv stores them). A click sets the
current point in the shown frame (a new click moves it). "Suggest" offers corners worth marking
near the paper's five locations. "Propose next" places the point in the next frame where the
registration predicts it from the point's first confirmed mark and refines it by correlation only
where the patch fixes both directions (``registration.evaluation.proposals``); the proposal
(orange) is *pending*: it counts nowhere (not in Table 2, not in POINTS.csv) until the analyst
confirms it or moves it with a click, and one left at the prediction (along an edge, bland,
ambiguous) cannot be confirmed. Each mark shows its offset from the registration's prediction
(raw px) and its residual (base px, local stage, from the point's anchor position, the quantity
Table 2 averages). Table 2 comes from
``registration.evaluation`` with the anchor chosen here, is shown in its own wide panel and can
be downloaded as CSV and markdown.
"""

from __future__ import annotations

import csv
import io

import numpy as np

from app.gui import scene2d
from app.gui.context import Client
from app.gui.state import ANCHORS, PendingMark
from app.gui.views.base import View
from app.gui.views.evaluate.panel import POINT_NAMES, EvaluatePanel, TableFormat
from app.gui.views.evaluate.scene import EvaluateScene
from registration import evaluation

MARK = (0, 255, 120)
MARK_CURRENT = (255, 230, 0)
PROPOSED = (255, 140, 0)


class EvaluateView(View):
    MODE = "Evaluate"
    CLICKABLE = ("frame",)

    panel: EvaluatePanel
    scene: EvaluateScene

    def make_scene(self, scene, root_name):
        return EvaluateScene(scene, root_name)

    def make_panel(self, gui):
        return EvaluatePanel(gui)

    def connect(self) -> None:
        p = self.panel
        p.on_frame_changed(lambda k, client: self.set_frame(k))
        p.on_point_changed(lambda name, client: self.set_point(name))
        p.on_mark_actions(
            new_point=lambda client: self.new_point(),
            propose_next=self.propose_next,
            suggest=self.suggest,
            confirm=self.confirm,
            delete=lambda client: self.delete_mark(),
        )
        p.on_anchor_changed(lambda anchor, client: self.set_anchor(anchor))
        p.on_compute_table(self.compute_table)
        p.on_export_points(self.export_csv)
        p.on_import_points(self.import_points)
        p.on_download_table(self.download_table)
        self.ctx.events.on("eval-mark", self._mark_event)

    # ---------------------------------------------------------------- state
    def on_inputs(self) -> None:
        inp = self.ctx.inputs
        self.scene.make_plane("frame", *inp.frame_size)
        with self.state.lock:
            k, anchor = self.state.eval_frame, self.state.anchor
        self.panel.configure(inp.n_frames)
        self.panel.frame = k
        self.panel.show_anchor(anchor)
        self._refresh_points()

    def on_show(self) -> None:
        self._refresh_points()
        self.request_render()

    def set_visible(self, visible: bool) -> None:
        super().set_visible(visible)
        with self.state.lock:
            has_table = self.state.report is not None
        if not visible or has_table:
            self.panel.show_table2_window(visible)

    def on_state_changed(self) -> None:
        self._refresh_points()

    def _refresh_points(self) -> None:
        """The point dropdown now; the marks' table (residuals through the result: tens of ms
        and more) on the worker."""
        with self.state.lock:
            names = sorted(self.state.points, key=_natural) or [POINT_NAMES[0]]
            cur = self.state.point_name
        if cur not in names:
            names.append(cur)
        self.panel.show_points(tuple(names), cur)
        self.submit("marks", self.show_marks)

    def show_marks(self) -> None:
        """The marks' table with each mark's residual (worker)."""
        rows = self.mark_rows()
        with self.state.lock:
            cur = self.state.point_name
        self.panel.show_marks(rows, cur)

    def set_frame(self, k: int) -> None:
        with self.state.lock:
            if self.ctx.inputs is None:
                return
            k = int(np.clip(k, 0, self.ctx.inputs.n_frames - 1))
            same = k == self.state.eval_frame and self.ctx.shown.get(self.MODE) == (k,)
            self.state.eval_frame = k
        if same:
            return  # e.g. the slider's own callback after we moved it
        if self.panel.frame != k:
            self.panel.frame = k
        self.ctx.save(soon=True)
        self._refresh_points()
        self.request_render()

    def set_point(self, name: str) -> None:
        with self.state.lock:
            self.state.point_name = name
        self.ctx.save()
        self._refresh_points()
        self.request_overlays()

    def set_anchor(self, anchor: str) -> None:
        if anchor not in ANCHORS:
            return
        with self.state.lock:
            self.state.anchor = anchor
        self.ctx.save()
        self._refresh_points()

    def _mark_event(self, value, client) -> None:
        try:
            name, k = str(value[0]), int(value[1])
        except (TypeError, ValueError, IndexError):
            return
        with self.state.lock:
            if name not in self.state.points:
                return
            self.state.point_name = name
        self.set_frame(k)

    def new_point(self) -> None:
        with self.state.lock:
            used = set(self.state.points) | {self.state.point_name}
            free = [n for n in POINT_NAMES if n not in used]
            i = 1
            while f"P{i}" in used:
                i += 1
            self.state.point_name = free[0] if free else f"P{i}"
        self._refresh_points()
        self.ctx.save()

    def on_click(self, plane: str, xy, client) -> None:
        """Set (or move) the current point in the shown frame, raw pixels: a confirmed mark."""
        with self.state.lock:
            name, k = self.state.point_name, self.state.eval_frame
            self.state.points.setdefault(name, {})[k] = (float(xy[0]), float(xy[1]))
            self.state.pending.pop((name, k), None)
            self.state.revision += 1
        self._points_changed()

    def confirm(self, client: Client = None) -> bool:
        """Accept the proposal for the current point in the shown frame as it is."""
        with self.state.lock:
            key = (self.state.point_name, self.state.eval_frame)
            mark = self.state.pending.get(key)
            if mark is not None and mark.confirmable:
                del self.state.pending[key]
                self.state.revision += 1
        if mark is not None and not mark.confirmable:
            self.notify(
                client,
                "Click the point instead",
                "This proposal is only where the registration puts the point "
                f"({mark.note}); confirming it would measure nothing.",
                "yellow",
            )
            return False
        if mark is None:
            self.notify(
                client,
                "Nothing to confirm",
                "The current point has no proposal in this frame",
                "yellow",
            )
            return False
        self._points_changed()
        return True

    def delete_mark(self) -> None:
        with self.state.lock:
            name, k = self.state.point_name, self.state.eval_frame
            marks = self.state.points.get(name, {})
            marks.pop(k, None)
            self.state.pending.pop((name, k), None)
            if not marks:
                self.state.points.pop(name, None)
        self._points_changed()

    def _points_changed(self) -> None:
        self.ctx.save()
        self.write_points_csv()
        self._refresh_points()
        self.request_overlays()
        self.ctx.state_changed()

    # ---------------------------------------------------------------- registration calls
    def confirmed_marks(self) -> dict[str, dict[int, tuple[float, float]]]:
        """The marks without pending proposals: what counts."""
        with self.state.lock:
            return self.state.confirmed_marks()

    def points_rows(self) -> list[tuple[int, str, float, float]]:
        """Confirmed marks as ``(frame, point, x, y)`` rows sorted by point then frame."""
        pts = self.confirmed_marks()
        return [
            (k, p, xy[0], xy[1])
            for p in sorted(pts, key=_natural)
            for k, xy in sorted(pts[p].items())
        ]

    def mark_residuals(self) -> dict[tuple[str, int], float]:
        """Per mark (pending ones included, for information): distance in base px (local stage)
        from the point's anchor position, as Table 2 measures it."""
        with self.state.lock:
            r, anchor = self.state.result, self.state.anchor
            marks = {p: dict(m) for p, m in self.state.points.items() if m}
        if r is None or not marks:
            return {}
        pm = evaluation.PointMarks(marks=marks, order=sorted(marks, key=_natural), source="app")
        pos = evaluation.point_positions(r, pm)["local"]
        confirmed = self.confirmed_marks()
        out = {}
        for p, by_frame in pos.items():
            if anchor == "reference":
                a = by_frame.get(r.reference_frame)
            else:
                good = [by_frame[k] for k in confirmed.get(p, {}) if np.isfinite(by_frame[k]).all()]
                a = np.mean(good, axis=0) if good else None
            for k, xy in by_frame.items():
                out[(p, k)] = float(np.hypot(*(xy - a))) if a is not None else float("nan")
        return out

    def mark_offsets(self) -> dict[tuple[str, int], float]:
        """Per mark: its distance (raw px) from where the registration (local stage) predicts
        it from the point's first confirmed mark; the image's view of the registration's error
        there, shown beside the residual."""
        with self.state.lock:
            r = self.state.result
            marks = {p: dict(m) for p, m in self.state.points.items() if m}
            confirmed = self.state.confirmed_marks()
        out: dict[tuple[str, int], float] = {}
        if r is None:
            return out
        for p, by_frame in marks.items():
            origin = sorted(confirmed.get(p, {}).items())
            if not origin:
                continue
            k0, xy0 = origin[0]
            b = r.frame_to_base(k0, np.asarray([xy0], float), "local")
            for k, xy in by_frame.items():
                pred = r.base_to_frame(k, b, "local")[0]
                out[(p, k)] = float(np.hypot(*(np.asarray(xy) - pred)))
        return out

    def mark_rows(self) -> list[dict]:
        with self.state.lock:
            pts = {p: dict(m) for p, m in self.state.points.items()}
            pending = dict(self.state.pending)
            k0 = self.state.eval_frame
        try:
            res, offsets = self.mark_residuals(), self.mark_offsets()
        except (ValueError, IndexError):
            res, offsets = {}, {}
        rows = []
        for p in sorted(pts, key=_natural):
            for k, (x, y) in sorted(pts[p].items()):
                rows.append(
                    {
                        "point": p,
                        "frame": k,
                        "x": x,
                        "y": y,
                        "pending": pending.get((p, k)),
                        "residual": res.get((p, k)),
                        "offset": offsets.get((p, k)),
                        "current_frame": k == k0,
                    }
                )
        return rows

    def points_csv(self) -> str:
        """Confirmed marks as POINTS.csv (``registration.evaluation.points.read_points_csv``); pending
        proposals follow as ``#`` comment lines, which the reader ignores."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["point", "frame", "x", "y"])
        for k, p, x, y in self.points_rows():
            w.writerow([p, k, f"{x:.3f}", f"{y:.3f}"])
        with self.state.lock:
            pending = sorted(self.state.pending.items())
            pts = {p: dict(m) for p, m in self.state.points.items()}
        for (p, k), mark in pending:
            xy = pts.get(p, {}).get(k)
            if xy is not None:
                why = f"NCC {mark.score:.3f}" if np.isfinite(mark.score) else mark.note
                buf.write(f"# proposed, not confirmed ({why}): {p},{k},{xy[0]:.3f},{xy[1]:.3f}\n")
        return buf.getvalue()

    def write_points_csv(self) -> str:
        text = self.points_csv()
        self.ctx.project.write_file("POINTS.csv", text)
        return text

    def import_points(self, name: str, content: bytes, client: Client = None) -> bool:
        """Replace the marks by those of an uploaded POINTS.csv (the format ``aerialreg
        evaluate --points`` reads, raw px of these frames); they count as confirmed."""
        import tempfile
        from pathlib import Path

        from registration.evaluation.points import MAX_POINTS_FILE_BYTES

        inp = self.ctx.inputs
        if inp is None:
            return False
        if len(content) > MAX_POINTS_FILE_BYTES:
            self.notify(client, "Points not imported", f"{name} is over the size limit", "red")
            return False
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / (Path(name).name or "POINTS.csv")
            path.write_bytes(content)
            try:
                marks = evaluation.read_points_csv(path, inp.n_frames, inp.frame_size, min_frames=1)
            except ValueError as exc:
                self.notify(client, "Points not imported", str(exc), "red")
                return False
        with self.state.lock:
            self.state.points = {p: dict(m) for p, m in marks.marks.items()}
            self.state.pending = {}
            self.state.point_name = marks.order[0]
            self.state.revision += 1
        self._points_changed()
        n = sum(len(m) for m in marks.marks.values())
        self.notify(
            client,
            "Points imported",
            f"{n} marks of {len(marks.order)} points from {name}",
            "green",
        )
        return True

    def export_csv(self, client: Client = None) -> bool:
        """Save POINTS.csv, check it with the evaluation module's reader, and send it."""
        text = self.write_points_csv()
        inp = self.ctx.inputs
        if inp is not None:
            try:
                evaluation.read_points_csv(
                    self.ctx.project.points_path, inp.n_frames, inp.frame_size
                )
            except ValueError as exc:
                self.notify(client, "POINTS.csv saved, but not usable yet", str(exc), "yellow")
        self.ctx.send_download(client, "POINTS.csv", text.encode("utf-8"))
        self.notify(
            client, "POINTS.csv", f"saved to {self.ctx.project.points_path} and sent", "green"
        )
        return True

    def propose_next(self, client: Client = None) -> bool:
        """Propose the current point in the next frame, pending until confirmed.

        With a registration result the proposal starts at the registration's prediction from
        the point's first confirmed mark and is refined by correlation only where the patch
        fixes both directions (``registration.evaluation.propose_through``); otherwise it stays
        at the prediction, says why, and cannot be confirmed. Before any registration it is
        searched around the same position in the next frame.
        """
        inp = self.ctx.inputs
        with self.state.lock:
            name, k = self.state.point_name, self.state.eval_frame
            xy = self.state.points.get(name, {}).get(k)
            # Proposals start from the point's first confirmed mark, never from earlier
            # proposals (chained correlation slides along roads).
            origin = sorted(self.state.confirmed_marks().get(name, {}).items()) or [(k, xy)]
            result = self.state.result
        if inp is None:
            return False
        if xy is None:
            self.notify(
                client, "Mark the point first", f"{name} is not marked in frame {k}", "yellow"
            )
            return False
        if k + 1 >= inp.n_frames:
            self.notify(client, "Last frame", "There is no next frame", "yellow")
            return False

        def work() -> None:
            if result is not None:
                k0, xy0 = origin[0]
                prop = evaluation.propose_through(
                    result, inp.frame(k0), k0, xy0, inp.frame(k + 1), k + 1
                )
            else:
                prop = evaluation.propose_unregistered(inp.frame(k), xy, inp.frame(k + 1))
            if not np.all(np.isfinite(prop.xy)):
                self.notify(
                    client,
                    "No proposal",
                    f"{name} could not be placed in frame {k + 1}: {prop.reason}",
                    "yellow",
                )
                return
            mark = PendingMark(prop.score, prop.offset_px, prop.refined, prop.reason)
            with self.state.lock:
                self.state.points.setdefault(name, {})[k + 1] = (
                    float(prop.xy[0]),
                    float(prop.xy[1]),
                )
                self.state.pending[(name, k + 1)] = mark
                self.state.revision += 1
            self.set_frame(k + 1)
            self._points_changed()
            if not prop.refined:
                self.notify(
                    client,
                    "Not refined: click the point",
                    f"{name} in frame {k + 1} is only where the registration puts it "
                    f"({prop.reason}).",
                    "yellow",
                )

        self.submit("propose", work)
        return True

    def suggest(self, client: Client = None) -> bool:
        """Suggest points worth marking in the shown frame, one near each of the paper's five
        locations (``registration.evaluation.suggest_points``), as pending marks to confirm."""
        inp = self.ctx.inputs
        with self.state.lock:
            result, k = self.state.result, self.state.eval_frame
        if inp is None:
            return False
        if result is None:
            self.notify(
                client, "No result", "Register the sequence first (Sequence view)", "yellow"
            )
            return False

        def job(progress) -> None:
            progress(0, 1, "looking for corners seen in several frames")
            found = evaluation.suggest_points(result, inp.frame, k)
            if progress.cancel.is_set():
                return
            with self.state.lock:
                added = []
                for s in found:
                    if k in self.state.points.get(s.location, {}):
                        continue  # the analyst's own mark stays
                    self.state.points.setdefault(s.location, {})[k] = (
                        float(s.xy[0]),
                        float(s.xy[1]),
                    )
                    self.state.pending[(s.location, k)] = PendingMark(
                        note=f"suggested: a corner seen in {s.n_frames} frames"
                    )
                    added.append(s.location)
                self.state.revision += 1
            progress(1, 1)
            self._points_changed()
            self.notify(
                client,
                "Suggested points",
                (
                    f"{', '.join(added)} in frame {k}: confirm the ones on the ground"
                    if added
                    else f"no new point found in frame {k}"
                ),
                "blue",
            )

        return self.ctx.run_job("suggest points", job, client)

    def compute_table(self, client: Client = None) -> bool:
        """Table 2 (paper section 6) from the confirmed marks and the registration result."""
        with self.state.lock:
            result, anchor = self.state.result, self.state.anchor
            n_pending = len(self.state.pending)
        if result is None:
            self.notify(
                client, "No result", "Register the sequence first (Sequence view)", "yellow"
            )
            return False
        marks = {p: m for p, m in self.confirmed_marks().items() if len(m) >= 2}
        if not marks:
            self.notify(
                client,
                "Too few marks",
                "Mark each point in at least 2 frames (confirmed)",
                "yellow",
            )
            return False

        def job(progress) -> None:
            pm = evaluation.PointMarks(marks=marks, order=sorted(marks, key=_natural), source="app")
            try:
                report = evaluation.evaluate_points(
                    result, pm, evaluation.EvaluationConfig(anchor=anchor)
                )
            except ValueError as exc:
                msg = str(exc).replace(
                    "or use the mean anchor", "or choose 'mean' under 'Motion measured from'"
                )
                self.notify(client, "Table 2 not possible", msg, "yellow")
                return
            if progress.cancel.is_set():  # a cancelled job changes nothing
                return
            with self.state.lock:
                self.state.report = report
            text = report.table.to_markdown()
            exc_frames = sorted({e["frame"] for es in report.excursions.values() for e in es})
            if exc_frames:
                text += "\nSudden excursions in frames: " + ", ".join(map(str, exc_frames))
            self.ctx.project.write_file("TABLE2.csv", report.table.to_csv())
            self.ctx.project.write_file("TABLE2.md", text)
            summary = (
                f"Table 2 from {sum(len(m) for m in marks.values())} confirmed marks of {len(marks)} "
                f"points, motion from the {anchor} position"
                + (f"; {n_pending} pending proposals left out" if n_pending else "")
                + ". Shown in its own window; saved as TABLE2.csv and TABLE2.md."
            )
            self.panel.show_table2(
                f"**Table 2** (base px; Unregistered in corrected-frame px; anchor: {anchor})\n\n{text}",
                summary,
            )
            self.ctx.state_changed()

        return self.ctx.run_job("table 2", job, client)

    def download_table(self, fmt: TableFormat, client: Client = None) -> bool:
        """Send Table 2 as ``TABLE2.csv`` (``fmt`` "csv") or ``TABLE2.md`` ("markdown")."""
        with self.state.lock:
            report = self.state.report
        if report is None:
            self.notify(client, "No Table 2", "Compute Table 2 first", "yellow")
            return False
        if fmt == "csv":
            name, data = "TABLE2.csv", report.table.to_csv()
        else:
            name, data = "TABLE2.md", report.table.to_markdown()
        self.ctx.send_download(client, name, data.encode("utf-8"))
        return True

    # ---------------------------------------------------------------- drawing (worker)
    def request_render(self) -> None:
        self.submit("render", self.render)

    def request_overlays(self) -> None:
        self.submit("overlays", self.draw_overlays)

    def render(self) -> None:
        inp = self.ctx.inputs
        if inp is None or "frame" not in self.scene.planes:
            return
        with self.state.lock:
            k = self.state.eval_frame
        rgb = scene2d.to_rgb(inp.preview(k, self.ctx.display_max))
        with self.ctx.atomic():
            self.scene.show_frame(rgb)
        self.draw_overlays()
        self.ctx.shown[self.MODE] = (k,)
        inp.prefetch([k + 1, k - 1])

    def draw_overlays(self) -> None:
        if "frame" not in self.scene.planes:
            return
        with self.state.lock:
            k, cur = self.state.eval_frame, self.state.point_name
            marks = []
            for p, m in self.state.points.items():
                if k not in m:
                    continue
                pending = (p, k) in self.state.pending
                colour = PROPOSED if pending else (MARK_CURRENT if p == cur else MARK)
                marks.append((p, np.asarray(m[k], float), colour, "x" if pending else "cross"))
        with self.ctx.atomic():
            self.scene.draw_marks(marks)


def _natural(name: str):
    """Sort key: the paper's locations in its order, then other names with numbers as numbers."""
    rank = POINT_NAMES.index(name) if name in POINT_NAMES else len(POINT_NAMES)
    digits = "".join(c for c in name if c.isdigit())
    return (rank, name.rstrip("0123456789"), int(digits) if digits else -1, name)
