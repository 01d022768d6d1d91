"""Evaluate view: its scene (the raw frame with the marks and their names)."""

from __future__ import annotations

import numpy as np

from app.gui import scene2d
from app.gui.views.base import Scene


class EvaluateScene(Scene):
    """The raw frame with the marks (crosses; proposals as x) and their names."""

    def __init__(self, scene, root_name: str) -> None:
        super().__init__(scene, root_name)
        self.labels: dict[str, object] = {}

    def show_frame(self, rgb) -> None:
        self.planes["frame"].show(rgb)

    def draw_marks(self, marks: list[tuple[str, np.ndarray, tuple, str]]) -> None:
        """``marks``: (name, raw xy, colour, shape)."""
        plane = self.planes["frame"]
        for shape in ("cross", "x"):
            sel = [m for m in marks if m[3] == shape]
            if sel:
                plane.markers(
                    f"marks_{shape}",
                    np.array([m[1] for m in sel]),
                    np.array([m[2] for m in sel], np.uint8),
                    shape=shape,
                    size_px=11,
                    width=2.5,
                )
            else:
                plane.remove(f"marks_{shape}")
        for name in list(self.labels):
            self.labels.pop(name).remove()
        for name, xy, _, _ in marks:
            pos = plane.geom.world_from_pixel(np.asarray(xy, float), dz=3 * scene2d.OVERLAY_DZ)
            self.labels[name] = self.scene.add_label(
                f"{self.root_name}/label_{len(self.labels)}",
                name,
                position=tuple(pos),
                anchor="bottom-left",
            )
