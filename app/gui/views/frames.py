"""What the Sequence and Traffic views show of a registration result, computed and kept for
reuse: each frame warped into the map over its footprint (at scrubbing or full resolution), each
frame's control-point table, the per-frame residual RMS and its sudden excursions.

Scrubbing is fast because the frame is warped at display resolution from a preview of the frame
(decoded ahead by :meth:`app.gui.inputs.Inputs.prefetch`) and only its footprint is rendered.
Everything here runs on the worker or the settle timer's thread, never on a callback.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from app.gui import controlpoints, scene2d
from app.gui.context import ViewContext
from registration import evaluation

WARP_CACHE_FRAMES = 16
"""Frames (and control-point tables) kept: a played loop of that many costs no warping."""
FOOTPRINT_PAD_PX = 4
"""Preview pixels around a footprint: bilinear support and the local field's small shifts."""


def excursion_flags(values: np.ndarray) -> np.ndarray:
    """Frames ``registration.evaluation.report.find_excursions`` flags as sudden excursions
    (bool ``(N,)`` for ``(N,)`` per-frame values, NaN where a frame has none)."""
    flags = np.zeros(len(values), bool)
    finite = np.isfinite(values)
    if finite.sum() < 3:
        return flags
    idx = np.flatnonzero(finite)
    for e in evaluation.find_excursions(idx, values[finite]):
        flags[int(e["frame"])] = True
    return flags


def frame_preview_side(width: int, height: int) -> int:
    """Longer side of the frame preview to warp into a ``width x height`` footprint: a little
    more than the footprint (in steps of 256 px, so the read-ahead can guess it)."""
    need = int(np.ceil(max(width, height) * 1.2 / 256.0)) * 256
    return max(need, 512)


class RegisteredFrames:
    """The frames of the open result as the Sequence view draws them.

    Args:
        ctx: the app as the view sees it (inputs, display size).
        result: returns the open ``registration.run.result.RegistrationResult`` (or None).
    """

    def __init__(self, ctx: ViewContext, result: Callable[[], object]) -> None:
        self.ctx = ctx
        self.result = result
        self._warps: OrderedDict[tuple, tuple] = OrderedDict()
        self._lock = threading.Lock()  # the worker and the settle thread both warp
        self._tables: OrderedDict[tuple, object] = OrderedDict()  # (k, id(result)) -> table

    def clear(self) -> None:
        """Forget the frames warped and the tables made so far."""
        with self._lock:
            self._warps.clear()
        self._tables.clear()

    def has_warp(self, k: int, stage: str, side: int) -> bool:
        """Whether frame ``k`` is warped for ``stage`` into a map preview of ``side`` px."""
        r = self.result()
        with self._lock:
            return r is not None and (k, stage, side, id(r)) in self._warps

    def border_in_base(self, k: int, stage: str) -> np.ndarray:
        """The raw frame's border mapped into base pixels, ``(M, 2)`` (finite points only)."""
        from registration.coords import frame_outline

        r = self.result()
        b = r.frame_to_base(k, frame_outline(*r.frame_size), stage)
        return b[np.isfinite(b).all(axis=1)]

    def registered(self, k: int, stage: str, side: int | None = None):
        """Frame ``k`` warped into a preview of the map whose longer side is ``side`` px
        (default: the map shown, twice the display size): ``(rgb, valid, box)`` with ``box`` =
        the frame's footprint ``(x0, y0, x1, y1)`` in full base pixels (edges, floats), or None.

        Only the footprint is rendered, from a preview of the frame of about its size there
        (decoded ahead by the read-ahead), so a new frame costs a small warp."""
        from registration.coords import rescale
        from registration.geometry import warp_image
        from registration.render import render_registered

        r = self.result()
        if r is None or not r.is_ok(k):
            return None
        display_max = self.ctx.display_max
        side = side or 2 * display_max
        key = (k, stage, side, id(r))
        with self._lock:
            if key in self._warps:
                self._warps.move_to_end(key)
                return self._warps[key]
        inp = self.ctx.inputs
        hp, wp = inp.base_preview(side).shape[:2]
        f = (inp.base_size[0] / wp, inp.base_size[1] / hp)  # full base px per preview px
        border = self.border_in_base(k, stage)
        if not len(border):
            return None
        lo = rescale(border.min(axis=0, keepdims=True), (1.0 / f[0], 1.0 / f[1]))[0]
        hi = rescale(border.max(axis=0, keepdims=True), (1.0 / f[0], 1.0 / f[1]))[0]
        pad = FOOTPRINT_PAD_PX
        x0, y0 = (int(max(0, np.floor(v) - pad)) for v in lo)
        x1 = int(min(wp, np.ceil(hi[0]) + pad + 1))
        y1 = int(min(hp, np.ceil(hi[1]) + pad + 1))
        if x1 <= x0 or y1 <= y0:
            return None
        frame = inp.preview(k, frame_preview_side(x1 - x0, y1 - y0))
        f_frame = (frame.shape[1] / r.frame_size[0], frame.shape[0] / r.frame_size[1])

        def frame_from_base(xy):
            raw = r.base_to_frame(k, rescale(xy, f), stage)
            return rescale(raw, f_frame)

        rgb = scene2d.to_rgb(frame)
        if side >= 2 * display_max:
            crop, mask = render_registered(
                rgb, frame_from_base, (x1 - x0, y1 - y0), origin=(x0, y0), step=8, return_mask=True
            )
        else:
            # Scrubbing: the mapping on a 16 px lattice and no exact evaluation of the frame's
            # border band (up to 16 preview px of the border stay empty until the settle render).
            crop, mask = warp_image(
                rgb, frame_from_base, x1 - x0, y1 - y0, origin=(x0, y0), step=16
            )
        # Corner coordinates scale linearly: preview edge x0 is full-base edge x0 * f.
        box = (x0 * f[0], y0 * f[1], x1 * f[0], y1 * f[1])
        out = (crop, mask, box)
        with self._lock:
            self._warps[key] = out
            while len(self._warps) > WARP_CACHE_FRAMES:
                self._warps.popitem(last=False)
        return out

    def map_under(self, reg, side: int) -> np.ndarray:
        """The map preview (longer side ``side`` px) under a :meth:`registered` frame ``reg``
        warped for that preview: ``(h, w, 3)`` RGB, the crop's size."""
        crop, _, box = reg
        under = self.ctx.inputs.base_preview(side)
        hp, wp = under.shape[:2]
        f = (self.ctx.inputs.base_size[0] / wp, self.ctx.inputs.base_size[1] / hp)
        x0, y0 = int(round(box[0] / f[0])), int(round(box[1] / f[1]))
        return under[y0 : y0 + crop.shape[0], x0 : x0 + crop.shape[1]]

    def table(self, k: int) -> controlpoints.ControlPointTable | None:
        """Frame ``k``'s control-point table (read-only), kept for the recent frames."""
        key = (k, id(self.result()))
        if key not in self._tables:
            self._tables[key] = self.control_point_table(k)
            while len(self._tables) > WARP_CACHE_FRAMES:
                self._tables.popitem(last=False)
        return self._tables[key]

    def control_point_table(self, k: int) -> controlpoints.ControlPointTable | None:
        """The read-only table of frame ``k``'s control points from the result, or None."""
        from registration.run import records

        r = self.result()
        if r is None or not r.is_ok(k):
            return None
        cps = r.control_points(k)
        if cps is None:
            return None
        src, dst, kept, _ = cps
        source = None
        path = records.frame_record_path(r.out_dir, k, ".npz")
        try:
            with np.load(path) as z:
                source = z["source"] if "source" in z.files else None
        except (OSError, ValueError):
            source = None
        kind = (
            "reference"
            if k == r.reference_frame
            else str(r.config.get("intra", {}).get("control_points", "template"))
        )
        return controlpoints.table_from_points(src, dst, kept, source, kind, r.lens, r.model(k))

    def error_values(self) -> np.ndarray | None:
        """Residual RMS (base px) per frame from the result records; NaN where not ok."""
        r = self.result()
        if r is None:
            return None
        out = np.full(r.n_frames, np.nan)
        for k, rec in enumerate(r.records):
            v = rec.stats.get("residual_rms_px")
            if rec.status == "ok" and v is not None:
                out[k] = float(v)
        return out
