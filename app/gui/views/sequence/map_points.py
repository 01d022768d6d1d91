"""Sequence view: the analyst's map points (``registration.run.set_map_points``): on the frame
shown, a click on a feature of the frame (drawn over the map), then a click where that feature
lies on the map, is one more constraint on the frame in the sequence adjustment; *Solve again*
adjusts the frames it touches (the run resumed with the result's own settings).

The frame click is taken in the frame through the registration drawn (the stage shown), so that
the point is the frame's pixel under the cursor, whatever its registration got wrong. Changing
the points goes through the app's job slot, as every write to the result folder does.
"""

from __future__ import annotations

import threading

import numpy as np

from app.gui.context import Client
from app.gui.security import escape_md
from registration.adjustment import MapPoint
from registration.run.map_points import read_map_points, set_map_points

PENDING = (255, 160, 0)
MAP_POINT = (80, 255, 80)
FRAME_POINT = (255, 60, 60)
FRAME_STEP = "**Click the feature in the frame** (drawn over the map; *Flicker* tells them apart)."
MAP_STEP = "**Now click where it lies on the map.**"


class MapPointsTool:
    """The map points' actions and drawing for the Sequence view ``view`` (its widgets:
    ``panel``, a :class:`app.gui.views.sequence.panel.MapPointsPanel`)."""

    def __init__(self, view, panel) -> None:
        self.view, self.panel = view, panel
        self._lock = threading.Lock()
        self._step: str | None = None  # None, "frame" or "map"
        self._pending: tuple[int, np.ndarray, np.ndarray] | None = None  # k, frame xy, base xy
        panel.on_actions(add=self.start, cancel=self.cancel, remove=self.remove, solve=self.solve)

    # ---------------------------------------------------------------- reading
    def points(self) -> list[MapPoint]:
        r = self.view.result()
        if r is None:
            return []
        try:
            return read_map_points(r.out_dir)
        except ValueError as exc:
            self.view.ctx.record_error(str(exc))
            return []

    @property
    def picking(self) -> bool:
        with self._lock:
            return self._step is not None

    # ---------------------------------------------------------------- actions
    def start(self, client: Client = None) -> bool:
        """Wait for the frame click on the frame shown."""
        r = self.view.result()
        with self.view.state.lock:
            k = self.view.state.seq_frame
        problem = self._refusal(r, k)
        if problem:
            self.view.notify(client, "No map point here", problem, "yellow")
            return False
        with self._lock:
            self._step, self._pending = "frame", None
        self.refresh(k)
        return True

    def _refusal(self, r, k: int) -> str:
        if r is None:
            return "Register the sequence first"
        if r.config.get("adjust") is None:
            return (
                "This result was registered without adjusting the frames together, which map "
                "points act through (Seed view, Run settings, then register again)"
            )
        if k == r.reference_frame:
            return "The reference frame is fitted in the Seed view: edit its control points there"
        if not r.is_ok(k):
            return f"Frame {k} has no registration to correct: register it again first"
        return ""

    def cancel(self, client: Client = None) -> None:
        with self._lock:
            self._step, self._pending = None, None
        with self.view.state.lock:
            k = self.view.state.seq_frame
        self.refresh(k)

    def on_click(self, xy, client: Client) -> bool:
        """A click on the map while a point is being placed: take it (True), else False."""
        xy = np.asarray(xy, np.float64)
        with self.view.state.lock:
            k, stage = self.view.state.seq_frame, self.view.state.stage
        with self._lock:
            step, pending = self._step, self._pending
        if step is None:
            return False
        r = self.view.result()
        if step == "frame" or pending is None or pending[0] != k:
            fxy = r.base_to_frame(k, xy[None], stage)[0] if r is not None else np.full(2, np.nan)
            if not np.isfinite(fxy).all():
                self.view.notify(client, "Not on the frame", "Click inside the frame's outline")
                return True
            with self._lock:
                self._step, self._pending = "map", (k, fxy, xy)
            self.refresh(k)
            return True
        point = MapPoint(k, tuple(pending[1]), tuple(xy))
        with self._lock:
            self._step, self._pending = None, None
        others = self.points()
        return self._store([*others, point], k, client, f"Map point added to frame {k}")

    def remove(self, client: Client = None) -> bool:
        with self.view.state.lock:
            k = self.view.state.seq_frame
        points = self.points()
        kept = [p for p in points if p.k != k]
        if len(kept) == len(points):
            self.view.notify(client, "No map points", f"Frame {k} has none", "yellow")
            return False
        return self._store(kept, k, client, f"Map points of frame {k} removed")

    def _store(self, points: list[MapPoint], k: int, client, title: str) -> bool:
        r = self.view.result()
        out_dir = r.out_dir

        def job(progress) -> None:
            progress(0, 1, "map points")
            try:
                undone = set_map_points(out_dir, points)
            except ValueError as exc:
                self.view.notify(client, "Map point refused", str(exc), "red")
                return
            self.view.load_result(out_dir)
            self.view.ctx.state_changed()
            self.view.request_render()
            self.view.notify(
                client,
                title,
                f"{len(undone)} frames to adjust again: press *Solve again*",
                "green",
            )

        return self.view.ctx.run_job("map points", job, client)

    def solve(self, client: Client = None) -> bool:
        """Adjust the frames not adjusted (those the map points touch)."""
        r = self.view.result()
        if r is None:
            self.view.notify(client, "No result", "Register the sequence first", "yellow")
            return False
        if r.config.get("adjust") is None:
            self.view.notify(client, "Nothing to solve", self._refusal(r, -1), "yellow")
            return False
        todo = [k for k in range(r.n_frames) if r.is_ok(k) and not r.is_adjusted(k)]
        if not todo:
            self.view.notify(client, "Nothing to solve", "Every frame is adjusted", "yellow")
            return False
        with self.view.state.lock:
            k = self.view.state.seq_frame

        def done() -> str:
            adj = self.view.result().records[k].stats.get("adjustment") or {}
            text = f"{len(todo)} frames adjusted again"
            if adj.get("n_map_points"):
                text += (
                    f"; frame {k} is {adj['map_point_rms_px']:.2f} base px from its map points, "
                    f"predicted error {adj['predicted_error_px']:.2f} px"
                )
            return text

        return self.view.resume_own_run(client, "solve again", done)

    # ---------------------------------------------------------------- drawing
    def refresh(self, k: int) -> None:
        """The panel's text and the frame's markers."""
        with self._lock:
            step, pending = self._step, self._pending
        points = self.points()
        text = self.text(k, points)
        if step == "frame":
            text = FRAME_STEP + "\n\n" + text
        elif step == "map":
            text = MAP_STEP + "\n\n" + text
        self.panel.show(text, step is not None)
        self.draw(k, points, pending[2] if pending is not None and pending[0] == k else None)

    def text(self, k: int, points: list[MapPoint]) -> str:
        mine = [p for p in points if p.k == k]
        frames = sorted({p.k for p in points})
        parts = [f"Frame {k}: {len(mine)} map point(s)"]
        r = self.view.result()
        adj = r.records[k].stats.get("adjustment") if r is not None else None
        if mine and isinstance(adj, dict) and adj.get("n_map_points"):
            parts.append(f"{adj['map_point_rms_px']:.2f} base px from them after the adjustment")
            if adj.get("note"):
                parts.append(escape_md(adj["note"]))
        elif mine:
            parts.append("not adjusted with them yet: *Solve again*")
        line = "; ".join(parts) + "."
        if frames:
            shown = ", ".join(map(str, frames[:20])) + (" ..." if len(frames) > 20 else "")
            line += f" The flight: {len(points)} map point(s) on frames {shown}."
        return line

    def draw(self, k: int, points: list[MapPoint], pending_xy) -> None:
        """Frame ``k``'s map points: where they lie on the map (green circles), where the
        registration drawn puts their frame points (red crosses), and the point being placed."""
        r = self.view.result()
        bp = self.view.scene.planes.get("base")
        if bp is None:
            return
        mine = [p for p in points if p.k == k]
        with self.view.state.lock:
            stage = self.view.state.stage
        if mine and r is not None and r.is_ok(k):
            on_map = np.array([p.base_xy for p in mine])
            shown = r.frame_to_base(k, np.array([p.frame_xy for p in mine]), stage)
            bp.markers("map-points", on_map, MAP_POINT, shape="circle", size_px=9, width=2.5)
            ok = np.isfinite(shown).all(axis=1)
            bp.markers("map-points-frame", shown[ok], FRAME_POINT, size_px=8)
        else:
            bp.remove("map-points")
            bp.remove("map-points-frame")
        if pending_xy is None:
            bp.remove("map-point-pending")
        else:
            bp.markers("map-point-pending", [pending_xy], PENDING, size_px=10, width=2.5)
