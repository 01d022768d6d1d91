"""Evaluate view: mark the same ground points in several frames, then the paper's Table 2 (section 6).

Points are marked on the raw frames (raw pixels, as POINTS.csv stores them). A click sets the
current point in the shown frame (a new click moves it). "Propose in next frame" finds the point
in the next frame by normalised cross-correlation (or, where that finds nothing, through the
registration result) and shows the proposal (orange) for the analyst to accept as is or move
with a click. Table 2 comes from ``registration.evaluation``; the export is POINTS.csv in
the format ``registration.evaluation.read_points_csv`` reads (and is checked with it).
"""

from __future__ import annotations

import csv
import io

import numpy as np

from app import scene2d
from app.view import View
from registration import evaluation

# The paper's Table 2 locations first, so the table reads like the paper's.
POINT_NAMES = ("NW", "NE", "Center", "SW", "SE")
MARK = (0, 255, 120)
MARK_CURRENT = (255, 230, 0)
PROPOSED = (255, 140, 0)


class EvaluateTab(View):
    MODE = "Evaluate"

    def build(self) -> None:
        gui = self.gui
        self.frame_slider = gui.add_slider("Frame", 0, 1, 1, 0)
        self.point_dd = gui.add_dropdown("Point", POINT_NAMES[:1], initial_value=POINT_NAMES[0])
        self.btn_new = gui.add_button("New point")
        self.btn_propose = gui.add_button("Propose in next frame")
        self.btn_delete = gui.add_button("Delete point in this frame")
        self.marks_md = gui.add_markdown("")
        self.btn_table = gui.add_button("Compute Table 2")
        self.table_md = gui.add_markdown("")
        self.btn_export = gui.add_button("Export POINTS.csv")
        self.frame_slider.on_update(lambda ev: self.set_frame(int(ev.target.value)))
        self.point_dd.on_update(lambda ev: self.set_point(str(ev.target.value)))
        self.btn_new.on_click(lambda ev: self.new_point())
        self.btn_propose.on_click(lambda ev: self.propose_next(ev.client))
        self.btn_delete.on_click(lambda ev: self.delete_mark())
        self.btn_table.on_click(lambda ev: self.compute_table(ev.client))
        self.btn_export.on_click(lambda ev: self.export_csv(ev.client))
        self.proposed: set[tuple[str, int]] = set()
        self.labels: dict[str, object] = {}

    # ---------------------------------------------------------------- state
    def on_inputs(self) -> None:
        inp = self.app.inputs
        w, h = inp.frame_size
        self.make_plane("frame", w, h)
        with self.state.lock:
            k = self.state.eval_frame
        self.frame_slider.max = max(inp.n_frames - 1, 1)
        self.frame_slider.disabled = inp.n_frames <= 1
        self.frame_slider.value = k
        self._refresh_points()

    def on_show(self) -> None:
        self.request_render()

    def _refresh_points(self) -> None:
        with self.state.lock:
            names = sorted(self.state.points, key=_natural) or [POINT_NAMES[0]]
            cur = self.state.point_name
        if cur not in names:
            names.append(cur)
        self.point_dd.options = tuple(names)
        if self.point_dd.value != cur:
            self.point_dd.value = cur
        self._update_marks_md()

    def set_frame(self, k: int) -> None:
        with self.state.lock:
            if self.app.inputs is None:
                return
            k = int(np.clip(k, 0, self.app.inputs.n_frames - 1))
            self.state.eval_frame = k
        if int(self.frame_slider.value) != k:
            self.frame_slider.value = k
        self.app.save()
        self.request_render()

    def set_point(self, name: str) -> None:
        with self.state.lock:
            self.state.point_name = name
        self.app.save()
        self._update_marks_md()
        self.request_overlays()

    def new_point(self) -> None:
        with self.state.lock:
            used = set(self.state.points) | {self.state.point_name}
            free = [n for n in POINT_NAMES if n not in used]
            i = 1
            while f"P{i}" in used:
                i += 1
            self.state.point_name = free[0] if free else f"P{i}"
        self._refresh_points()
        self.app.save()

    def on_click(self, plane: str, xy, client) -> None:
        """Set (or move) the current point in the shown frame, raw pixels."""
        with self.state.lock:
            name, k = self.state.point_name, self.state.eval_frame
            self.state.points.setdefault(name, {})[k] = (float(xy[0]), float(xy[1]))
            self.state.revision += 1
        self.proposed.discard((name, k))
        self._points_changed()

    def delete_mark(self) -> None:
        with self.state.lock:
            name, k = self.state.point_name, self.state.eval_frame
            marks = self.state.points.get(name, {})
            marks.pop(k, None)
            if not marks:
                self.state.points.pop(name, None)
        self.proposed.discard((name, k))
        self._points_changed()

    def _points_changed(self) -> None:
        self.app.save()
        self.write_points_csv()
        self._refresh_points()
        self.request_overlays()

    def _update_marks_md(self) -> None:
        with self.state.lock:
            pts = {p: dict(m) for p, m in self.state.points.items()}
            cur = self.state.point_name
        if not pts:
            self.marks_md.content = (
                "No points yet: click a ground point (e.g. a road marking) in the frame."
            )
            return
        rows = ["| point | frames marked |", "|---|---|"]
        for p in sorted(pts, key=_natural):
            frames = ", ".join(
                str(k) + ("*" if (p, k) in self.proposed else "") for k in sorted(pts[p])
            )
            rows.append(f"| {'**' + p + '**' if p == cur else p} | {frames} |")
        self.marks_md.content = "\n".join(rows) + "\n\n\\* proposed, not yet confirmed by a click"

    # ---------------------------------------------------------------- registration calls
    def points_rows(self) -> list[tuple[int, str, float, float]]:
        """Marked points as ``(frame, point, x, y)`` rows sorted by point then frame."""
        with self.state.lock:
            pts = {p: dict(m) for p, m in self.state.points.items()}
        return [
            (k, p, xy[0], xy[1])
            for p in sorted(pts, key=_natural)
            for k, xy in sorted(pts[p].items())
        ]

    def points_csv(self) -> str:
        """The marks as POINTS.csv text (format: ``registration.evaluation.read_points_csv``)."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["point", "frame", "x", "y"])
        for k, p, x, y in self.points_rows():
            w.writerow([p, k, f"{x:.3f}", f"{y:.3f}"])
        return buf.getvalue()

    def write_points_csv(self) -> str:
        """Write POINTS.csv into the project (atomically); returns its text."""
        text = self.points_csv()
        self.app.project.write_file("POINTS.csv", text)
        return text

    def export_csv(self, client=None) -> bool:
        """Save POINTS.csv, check it with the evaluation module's reader, and send it."""
        text = self.write_points_csv()
        inp = self.app.inputs
        if inp is not None:
            try:
                evaluation.read_points_csv(
                    self.app.project.points_path, inp.n_frames, inp.frame_size
                )
            except ValueError as exc:
                self.notify(client, "POINTS.csv saved, but not usable yet", str(exc), "yellow")
        target = client if client is not None else self.app.server
        target.send_file_download("POINTS.csv", text.encode("utf-8"))
        self.notify(
            client, "POINTS.csv", f"saved to {self.app.project.points_path} and sent", "green"
        )
        return True

    def propose_next(self, client=None) -> bool:
        """Propose the current point in the next frame.

        By normalised cross-correlation (``registration.evaluation.propose_point``); where that
        finds nothing, from the registration result (frame k -> base -> frame k+1, stage "local")
        when there is one.
        """
        result = self.app.tabs["Sequence"].result
        inp = self.app.inputs
        with self.state.lock:
            name, k = self.state.point_name, self.state.eval_frame
            xy = self.state.points.get(name, {}).get(k)
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
            p = evaluation.propose_point(inp.frame(k), xy, inp.frame(k + 1)).xy
            if not np.all(np.isfinite(p)) and result is not None:
                # NCC finds nothing where its template leaves the frame (points near the border)
                # or on bland ground; the registration still maps such points wherever both
                # frames are registered.
                b = result.frame_to_base(k, np.asarray([xy], float), "local")
                p = result.base_to_frame(k + 1, b, "local")[0]
            if not np.all(np.isfinite(p)):
                self.notify(
                    client, "No proposal", f"{name} could not be found in frame {k + 1}", "yellow"
                )
                return
            with self.state.lock:
                self.state.points.setdefault(name, {})[k + 1] = (float(p[0]), float(p[1]))
            self.proposed.add((name, k + 1))
            self.set_frame(k + 1)
            self._points_changed()

        self.app.worker.submit("evaluate-propose", work)
        return True

    def compute_table(self, client=None) -> bool:
        """Table 2 (paper section 6) from the marks and the registration result."""
        seq = self.app.tabs["Sequence"]
        if seq.result is None:
            self.notify(
                client, "No result", "Register the sequence first (Sequence view)", "yellow"
            )
            return False
        with self.state.lock:
            marks = {p: dict(m) for p, m in self.state.points.items() if len(m) >= 2}
        if not marks:
            self.notify(client, "Too few marks", "Mark each point in at least 2 frames", "yellow")
            return False

        def job(cancel) -> None:
            pm = evaluation.PointMarks(marks=marks, order=sorted(marks, key=_natural), source="app")
            try:
                report = evaluation.evaluate_points(seq.result, pm)
            except ValueError as exc:
                self.notify(client, "Table 2 not possible", str(exc), "yellow")
                return
            self.table = report.table
            text = report.table.to_markdown()
            exc_frames = sorted({e["frame"] for es in report.excursions.values() for e in es})
            if exc_frames:
                text += "\nSudden excursions in frames: " + ", ".join(map(str, exc_frames))
            self.table_md.content = text
            self.app.project.write_file("TABLE2.csv", report.table.to_csv())

        if not self.app.jobs.start("table 2", job):
            self.notify(client, "Busy", f"{self.app.jobs.name} is running", "yellow")
            return False
        return True

    # ---------------------------------------------------------------- drawing (worker)
    def request_render(self) -> None:
        self.app.worker.submit("evaluate", self.render)

    def request_overlays(self) -> None:
        self.app.worker.submit("evaluate-overlays", self.draw_overlays)

    def render(self) -> None:
        inp = self.app.inputs
        if inp is None or "frame" not in self.image_planes:
            return
        with self.state.lock:
            k = self.state.eval_frame
        rgb = scene2d.to_rgb(scene2d.preview(inp.frame(k), self.app.display_max))
        with self.app.server.atomic():
            self.image_planes["frame"].show(rgb)
        self.draw_overlays()
        self.app.shown[self.MODE] = (k,)

    def draw_overlays(self) -> None:
        plane = self.image_planes.get("frame")
        if plane is None:
            return
        with self.state.lock:
            k, cur = self.state.eval_frame, self.state.point_name
            marks = [(p, m[k]) for p, m in self.state.points.items() if k in m]
        size = max(plane.geom.width, plane.geom.height) / 80
        a, b, cols = [], [], []
        for p, xy in marks:
            colour = PROPOSED if (p, k) in self.proposed else (MARK_CURRENT if p == cur else MARK)
            s, e = scene2d.cross_segments(xy, size)
            a.append(s)
            b.append(e)
            cols += [colour, colour]
        with self.app.server.atomic():
            if a:
                plane.segments(
                    "marks",
                    np.concatenate(a),
                    np.concatenate(b),
                    np.asarray(cols, np.uint8),
                    width=3.0,
                )
            else:
                plane.remove("marks")
            for name in list(self.labels):
                self.labels.pop(name).remove()
            for p, xy in marks:
                pos = plane.geom.world_from_pixel(np.asarray(xy) + size, dz=3 * scene2d.OVERLAY_DZ)
                self.labels[p] = self.scene.add_label(
                    f"{self.root_name}/label_{p}", p, position=tuple(pos)
                )


def _natural(name: str):
    """Sort key: the paper's locations in its order, then other names with numbers as numbers."""
    rank = POINT_NAMES.index(name) if name in POINT_NAMES else len(POINT_NAMES)
    digits = "".join(c for c in name if c.isdigit())
    return (rank, name.rstrip("0123456789"), int(digits) if digits else -1, name)
