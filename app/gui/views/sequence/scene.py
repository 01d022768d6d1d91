"""Sequence view: its scene (the map, with the registered frame over its footprint, the frame's
outline, residual vectors, the local displacement field's heat map and the selected point)."""

from __future__ import annotations

import numpy as np

from app.gui import scene2d
from app.gui.views.base import Scene

RESIDUAL_OK = (255, 220, 0)
RESIDUAL_REMOVED = (240, 50, 50)
OUTLINE = (0, 200, 255)
SELECTED = (255, 255, 255)


class SequenceScene(Scene):
    """The map with the registered frame over its footprint, outline, vectors, heat map."""

    def __init__(self, scene, root_name: str) -> None:
        super().__init__(scene, root_name)
        self.field_handle = None
        self.base_shown = False

    def layout(self, base_size) -> None:
        self.make_plane("base", *base_size)
        self.base_shown = False

    def show_base(self, rgb) -> None:
        if not self.base_shown:
            self.planes["base"].show(rgb)
            self.base_shown = True

    def show_registered(self, patch, box, visible: bool = True) -> None:
        bp = self.planes["base"]
        if patch is None:
            bp.remove("registered")
            return
        bp.overlay_image("registered", patch, box=box)
        bp.set_visible("registered", visible)

    def set_registered_visible(self, visible: bool) -> None:
        self.planes["base"].set_visible("registered", visible)

    def draw_outline(self, border) -> None:
        bp = self.planes["base"]
        if border is None or len(border) < 2:
            bp.remove("outline")
            return
        s, e = scene2d.polyline_segments(border)
        bp.segments("outline", s, e, OUTLINE, width=2.0)

    def draw_vectors(self, vectors) -> None:
        bp = self.planes["base"]
        if vectors is None:
            bp.remove("residuals")
        else:
            bp.segments("residuals", *vectors, width=2.0)

    def draw_selected(self, xy) -> None:
        bp = self.planes["base"]
        if xy is None:
            bp.remove("selected")
        else:
            bp.markers("selected", [xy], SELECTED, shape="circle", size_px=12, width=2.5)

    def draw_field(self, rgba, extent) -> None:
        if self.field_handle is not None:
            self.field_handle.remove()
            self.field_handle = None
        if rgba is None:
            return
        x0, y0, x1, y1 = extent
        geom = self.planes["base"].geom
        s = geom.scale
        centre = geom.world_from_pixel(
            np.array([(x0 + x1) / 2.0, (y0 + y1) / 2.0]), dz=scene2d.OVERLAY_DZ * 0.75
        )
        big = np.repeat(np.repeat(rgba, 8, axis=0), 8, axis=1)  # crisp cells
        self.field_handle = self.scene.add_image(
            f"{self.root_name}/field",
            big,
            (x1 - x0) * s,
            (y1 - y0) * s,
            format="png",
            position=tuple(centre),
            cast_shadow=False,
            receive_shadow=False,
        )
