"""Calibrate view: its scene (the corrected frame, the straight reference grid, the analyst's
polylines and the lines an automatic estimate used), drawn from plain arrays."""

from __future__ import annotations

import numpy as np

from app.gui import scene2d
from app.gui.views.base import Scene

GRID_COLOUR = (0, 255, 255)
DETECTED_COLOUR = (255, 0, 200)


class CalibrateScene(Scene):
    """The corrected frame, the reference grid, the analyst's lines, the detected lines."""

    def show_frame(self, rgb: np.ndarray) -> None:
        self.planes["frame"].show(rgb)

    def draw_grid(self, on: bool) -> None:
        plane = self.planes["frame"]
        if not on:
            plane.remove("grid")
            return
        if plane.has("grid"):
            return  # straight on screen whatever γ is: drawn once
        w, h = plane.geom.width, plane.geom.height
        xs = np.linspace(0, w - 1, 9)[1:-1]
        ys = np.linspace(0, h - 1, 7)[1:-1]
        a = [(x, 0) for x in xs] + [(0, y) for y in ys]
        b = [(x, h - 1) for x in xs] + [(w - 1, y) for y in ys]
        plane.segments("grid", a, b, GRID_COLOUR, width=1.0)

    def draw_lines(self, lines: list[np.ndarray], colours: list) -> None:
        """Polylines in corrected pixels with their vertices as dots."""
        plane = self.planes["frame"]
        a, b, cols, pts, pcols = [], [], [], [], []
        for c, colour in zip(lines, colours, strict=True):
            if not len(c):
                continue
            pts.append(c)
            pcols.append(np.broadcast_to(np.asarray(colour, np.uint8), (len(c), 3)))
            if len(c) >= 2:
                s, e = scene2d.polyline_segments(c)
                a.append(s)
                b.append(e)
                cols.append(np.broadcast_to(np.asarray(colour, np.uint8), (len(s), 3)))
        if a:
            plane.segments(
                "lines", np.concatenate(a), np.concatenate(b), np.concatenate(cols), width=3.0
            )
        else:
            plane.remove("lines")
        if pts:
            plane.points("line_points", np.concatenate(pts), np.concatenate(pcols), size_px=7)
        else:
            plane.remove("line_points")

    def draw_detected(self, lines: list[np.ndarray] | None) -> None:
        plane = self.planes["frame"]
        if not lines:
            plane.remove("detected")
            return
        a, b = [], []
        for c in lines:
            if len(c) >= 2:
                s, e = scene2d.polyline_segments(c)
                a.append(s)
                b.append(e)
        if a:
            plane.segments(
                "detected", np.concatenate(a), np.concatenate(b), DETECTED_COLOUR, width=2.0
            )
