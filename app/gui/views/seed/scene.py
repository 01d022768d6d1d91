"""Seed view: its scene (the frame and the map side by side, seed markers, matches, the gate,
control points and their residuals, the mid base image) and the magnifier's crops."""

from __future__ import annotations

import cv2
import numpy as np

from app.gui import scene2d
from app.gui.views.base import GAP_PX, Scene

INLIER = (40, 230, 60)
OUTLIER = (240, 50, 50)
UNGATED = (150, 150, 150)
PAIR_COLOURS = {1: (255, 215, 0), 2: (0, 200, 255)}
KEPT = (40, 230, 60)
REMOVED = (240, 50, 50)
MANUAL = (255, 120, 255)
RESIDUAL = (255, 220, 0)
GATE = (255, 0, 255)
SELECTED = (255, 255, 255)
MAGNIFIER_PX = 48
"""Half-size (image pixels) of the magnifier's crops around a seed or selected point."""
MAGNIFIER_ZOOM = 3


class SeedScene(Scene):
    """Frame and map side by side, seed markers, matches, gate, control points, mid base image."""

    def __init__(self, scene, root_name: str) -> None:
        super().__init__(scene, root_name)
        self.markers: dict[tuple[str, int], scene2d.DragMarker] = {}
        self.labels: dict[tuple[str, int], object] = {}
        self.match_lines = None
        self.template_lines = None
        self.on_drag = None  # set by the view: (plane, pair, phase, event) -> None

    def layout(self, frame_size, base_size) -> None:
        """The frame drawn as tall as the map on its left, a gap, the map."""
        w, h = frame_size
        bw, bh = base_size
        for m in list(self.markers.values()):
            m.remove()
        self.markers.clear()
        scale = scene2d.WORLD_PER_PX * bh / h
        self.make_plane("frame", w, h, scale=scale)
        self.make_plane("base", bw, bh, x_offset=w * bh / h + GAP_PX)

    def show_images(self, frame_rgb, base_rgb) -> None:
        self.planes["frame"].show(frame_rgb)
        self.planes["base"].show(base_rgb)

    def draw_seeds(self, pairs: dict) -> None:
        """``pairs[i] = (frame point (corrected px) or None, map point or None)`` for i = 1, 2."""
        for i, (fxy, bxy) in pairs.items():
            for plane_name, xy in (("frame", fxy), ("base", bxy)):
                key = (plane_name, i)
                plane = self.planes[plane_name]
                if xy is None or not plane.geom.contains(xy):
                    if key in self.markers:
                        self.markers.pop(key).remove()
                        self.labels.pop(key).remove()
                    plane.remove(f"seed{i}")
                    plane.remove(f"seed{i}_cross")
                    continue
                self._place(key, plane, xy, PAIR_COLOURS[i], i)

    def _place(self, key, plane, xy, colour, i) -> None:
        if key in self.markers:
            self.markers[key].move_to(xy)
        else:
            m = scene2d.DragMarker(
                self.scene,
                f"{self.root_name}/seed_{key[0]}_{i}",
                plane,
                xy,
                colour,
                square=key[0] == "base",
            )
            self.markers[key] = m
            if self.on_drag is not None:
                handler = self.on_drag

                async def on_drag(event, plane_name=key[0], pair=i) -> None:
                    handler(plane_name, pair, event)

                m.handle.on_drag("left")(on_drag)
        # Visible marker: a ring (frame) or square (map) with a fine cross at the exact point.
        ring = "square" if key[0] == "base" else "circle"
        half = 13.0
        plane.markers(f"seed{i}", [xy], colour, shape=ring, size_px=half, width=3.0)
        plane.markers(f"seed{i}_cross", [xy], colour, shape="cross", size_px=half * 0.45, width=1.5)
        pos = plane.geom.world_from_pixel(np.asarray(xy, float), 5 * scene2d.OVERLAY_DZ)
        label = self.labels.get(key)
        if label is None:
            self.labels[key] = self.scene.add_label(
                f"{self.root_name}/seed_label_{key[0]}_{i}",
                str(i),
                position=tuple(pos),
                anchor="bottom-left",
                font_screen_scale=1.3,
            )
        else:
            label.position = tuple(pos)

    def move_marker(self, plane_name: str, pair: int, xy) -> None:
        """Follow a drag (the marker, its cross and label; the state changes at the drop)."""
        key = (plane_name, pair)
        if key in self.markers:
            self._place(key, self.planes[plane_name], xy, PAIR_COLOURS[pair], pair)

    def set_zoom(self, world_per_screen_px: float) -> None:
        super().set_zoom(world_per_screen_px)
        for m in self.markers.values():
            m.resize()

    def draw_matches(self, frame_xy, base_xy, colours) -> None:
        if self.match_lines is not None:
            self.match_lines.remove()
            self.match_lines = None
        if len(frame_xy):
            fp, bp = self.planes["frame"], self.planes["base"]
            pts = scene2d.segments_between(fp.geom, frame_xy, bp.geom, base_xy)
            cols = np.repeat(np.asarray(colours, np.uint8)[:, None, :], 2, axis=1)
            self.match_lines = self.scene.add_line_segments(
                f"{self.root_name}/matches", pts, cols, thickness=1.5, thickness_units="screen"
            )

    def draw_gate(self, outlines: list[np.ndarray]) -> None:
        bp = self.planes["base"]
        a, b = [], []
        for poly in outlines:
            s, e = scene2d.polyline_segments(np.vstack([poly, poly[:1]]))
            a.append(s)
            b.append(e)
        if a:
            bp.segments("gate", np.concatenate(a), np.concatenate(b), GATE, width=1.0)
        else:
            bp.remove("gate")

    def draw_control_points(
        self, frame_xy, base_xy, colours, vectors, template_lines: bool
    ) -> None:
        """Dots on both images; ``vectors`` = (start, end, colours) on the map or None."""
        fp, bp = self.planes["frame"], self.planes["base"]
        if self.template_lines is not None:
            self.template_lines.remove()
            self.template_lines = None
        if not len(frame_xy):
            fp.remove("cps")
            bp.remove("cps")
            bp.remove("residuals")
            return
        fp.points("cps", frame_xy, colours, size_px=3.5)
        bp.points("cps", base_xy, colours, size_px=3.5)
        if template_lines:
            pts = scene2d.segments_between(fp.geom, frame_xy, bp.geom, base_xy)
            self.template_lines = self.scene.add_line_segments(
                f"{self.root_name}/template_matches",
                pts,
                np.repeat(np.asarray(colours, np.uint8)[:, None, :], 2, axis=1),
                thickness=1.0,
                thickness_units="screen",
            )
        if vectors is None:
            bp.remove("residuals")
        else:
            bp.segments("residuals", *vectors, width=2.0)

    def draw_selected(self, frame_xy, base_xy) -> None:
        for name, xy in (("frame", frame_xy), ("base", base_xy)):
            plane = self.planes[name]
            if xy is None:
                plane.remove("selected")
            else:
                plane.markers("selected", [xy], SELECTED, shape="circle", size_px=12, width=2.5)

    def draw_manual_pending(self, frame_xy) -> None:
        fp = self.planes["frame"]
        if frame_xy is None:
            fp.remove("manual_pending")
        else:
            fp.markers("manual_pending", [frame_xy], MANUAL, shape="x", size_px=9, width=2.5)

    def draw_mid(self, rgb) -> None:
        if rgb is None:
            self.planes["base"].remove("mid")
        else:
            self.planes["base"].overlay_image("mid", rgb)


def gate_outlines(coarse) -> list[np.ndarray]:
    """The location gate the coarse step used, as polygons on the map (base px): the region
    where gated matches could lie (``CoarseResult.gate_outline_base``); none without a seed."""
    own = getattr(coarse, "gate_outline_base", None)
    return [] if own is None else [np.asarray(own, np.float64)]


def magnifier_side() -> int:
    return 2 * MAGNIFIER_PX * MAGNIFIER_ZOOM


def magnifier_crop_corrected(raw: np.ndarray, camera, xy, colour) -> np.ndarray:
    """:func:`magnifier_crop` of the corrected frame, resampled straight from the ``raw`` frame
    through ``camera`` (``registration.lens.Camera`` of ``raw``'s size): exact wherever the raw
    frame has the point, also in the corners, where corrected positions fall outside a
    corrected image of the frame's size."""
    from registration.geometry import remap

    side = magnifier_side()
    if xy is None or not np.isfinite(xy).all():
        return np.full((side, side, 3), 225, np.uint8)
    u = (np.arange(side) - side / 2) / MAGNIFIER_ZOOM
    gx, gy = np.meshgrid(float(xy[0]) + 0.5 + u, float(xy[1]) + 0.5 + u)
    src = camera.raw_from_corrected(np.c_[gx.ravel(), gy.ravel()]).reshape(side, side, 2)
    out = remap(raw, src.astype(np.float32), interpolation="nearest", border_value=225)
    return _cross(np.ascontiguousarray(out), colour)


def magnifier_crop(image: np.ndarray, xy, colour) -> np.ndarray:
    """A ``2*MAGNIFIER_PX`` square around ``xy`` (grey when None), enlarged, with a cross."""
    side = magnifier_side()
    if xy is None or not np.isfinite(xy).all():
        return np.full((side, side, 3), 225, np.uint8)
    x, y = float(xy[0]), float(xy[1])
    # Sub-pixel exact: an affine resample centred on the point.
    m = np.array(
        [
            [MAGNIFIER_ZOOM, 0, side / 2 - (x + 0.5) * MAGNIFIER_ZOOM],
            [0, MAGNIFIER_ZOOM, side / 2 - (y + 0.5) * MAGNIFIER_ZOOM],
        ]
    )
    out = cv2.warpAffine(
        image, m, (side, side), flags=cv2.INTER_NEAREST, borderValue=(225, 225, 225)
    )
    return _cross(out, colour)


def _cross(out: np.ndarray, colour) -> np.ndarray:
    """The magnifier's centre cross, drawn on ``out`` in ``colour``."""
    side = out.shape[0]
    c = side // 2
    col = tuple(int(v) for v in colour)
    cv2.line(out, (c - 12, c), (c - 4, c), col, 1)
    cv2.line(out, (c + 4, c), (c + 12, c), col, 1)
    cv2.line(out, (c, c - 12), (c, c - 4), col, 1)
    cv2.line(out, (c, c + 4), (c, c + 12), col, 1)
    return out
