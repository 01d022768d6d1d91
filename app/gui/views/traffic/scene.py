"""Traffic view: its scene (the base map, every track coloured by speed, the vehicles of the
frame shown, the selected track)."""

from __future__ import annotations

import cv2
import numpy as np

from app.gui.views.base import Scene

SELECTED = (255, 255, 255)


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

    def draw_tracks(self, starts, ends, colours) -> None:
        """Every track's consecutive positions (base px) as segments, ``colours`` (N, 3)."""
        self.planes["base"].segments("tracks", starts, ends, colours, width=2.0)

    def draw_vehicles(self, xy, colours) -> None:
        """The vehicles of the frame shown (base px)."""
        plane = self.planes["base"]
        if len(xy):
            plane.markers("vehicles", xy, colours, shape="cross", size_px=12, width=2.5)
        else:
            plane.remove("vehicles")

    def draw_selected(self, starts, ends) -> None:
        """The selected track, drawn over the others."""
        plane = self.planes["base"]
        if len(starts):
            plane.segments("selected", starts, ends, SELECTED, width=4.0)
        else:
            plane.remove("selected")
