"""Traffic view: its scene (the base map, every track coloured by speed, the vehicles of the
frame shown, the selected track, the road sections)."""

from __future__ import annotations

import cv2
import numpy as np

from app.gui.views.base import Scene

SELECTED = (255, 255, 255)
SECTION = (255, 0, 255)


def speed_colours(speed: np.ndarray, top: float) -> np.ndarray:
    """``(N, 3)`` uint8 RGB for speeds (m/s): slow blue through green to fast red (turbo),
    ``top`` m/s and above red."""
    t = np.clip(np.nan_to_num(np.asarray(speed, float) / max(top, 1e-6)), 0.0, 1.0)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0]
    return lut[(t * 255).round().astype(int)][:, ::-1].copy()  # BGR -> RGB


class TrafficScene(Scene):
    """The base map with the tracks (line segments coloured by speed) and vehicles."""

    def show_base(self, rgb) -> None:
        self.planes["base"].show(rgb)

    def show_registered(self, patch, box) -> None:
        """The registered frame (RGB, map preview px) over the map in ``box`` (full base px
        corner coordinates), under the tracks and boxes; None removes it."""
        plane = self.planes["base"]
        if patch is None:
            plane.remove("registered")
        else:
            plane.overlay_image("registered", patch, box=box)

    def draw_tracks(self, starts, ends, colours) -> None:
        """Every track's consecutive positions (base px) as segments, ``colours`` (N, 3)."""
        self.planes["base"].segments("tracks", starts, ends, colours, width=2.0)

    def draw_vehicles(self, xy, colours, boxes) -> None:
        """The vehicles of the frame shown: centres (base px) and boxes (``(N, 4, 2)`` base px
        corners), coloured by speed."""
        plane = self.planes["base"]
        if len(xy):
            plane.markers("vehicles", xy, colours, shape="cross", size_px=8, width=2.0)
            b = np.asarray(boxes, float).reshape(-1, 4, 2)
            starts, ends = b.reshape(-1, 2), np.roll(b, -1, axis=1).reshape(-1, 2)
            plane.segments("boxes", starts, ends, np.repeat(colours, 4, axis=0), width=2.5)
        else:
            plane.remove("vehicles")
            plane.remove("boxes")

    def draw_selected(self, starts, ends) -> None:
        """The selected track, drawn over the others."""
        plane = self.planes["base"]
        if len(starts):
            plane.segments("selected", starts, ends, SELECTED, width=4.0)
        else:
            plane.remove("selected")

    def draw_sections(self, sections, pending) -> None:
        """The road sections (``(N, 2, 2)`` base px) and the first end of one being drawn."""
        plane = self.planes["base"]
        if len(sections):
            s = np.asarray(sections, float).reshape(-1, 2, 2)
            plane.segments("sections", s[:, 0], s[:, 1], SECTION, width=3.0)
            plane.markers("section-starts", s[:, 0], SECTION, shape="circle", size_px=6)
        else:
            plane.remove("sections")
            plane.remove("section-starts")
        if pending is None:
            plane.remove("section-pending")
        else:
            plane.markers("section-pending", [pending], SECTION, size_px=10, width=2.5)
