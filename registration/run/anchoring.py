"""Re-anchoring of long flights (beyond the paper; ``IntraConfig.reanchor_coverage``).

The paper registers every frame to the mid base image and the previous frame, so once a flight's
view leaves the reference frame, each frame inherits its predecessor's error and the error
grows. A frame lying less than ``reanchor_coverage`` on the mid base image is therefore
registered to the base map again (inter-sensor, seeded by its intra-sensor model, no click),
and, when that agrees with the intra-sensor model, it becomes an *anchor*: its registration and
its own field are added to the joint base where the mid base image is empty, so the frames
after it chain from the map rather than from the drift.
"""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import NDArray

from registration.coords import bbox_of, image_size
from registration.global_registration import (
    FineResult,
    JointBase,
    add_to_mid_base,
    mid_coverage,
    previous_frame_state,
    register_anchor,
)
from registration.lens import Camera
from registration.local import reference_field
from registration.render import render_to_base
from registration.run.records import FrameRecord
from registration.run.records import frame_arrays as _frame_arrays
from registration.run.records import frame_stats as _stats

ANCHOR_STAGE = "inter-sensor anchor"


def anchor_box(camera: Camera, model, base_size) -> tuple[int, int, int, int] | None:
    """Base-pixel box a frame covers under ``model``, or None when it is empty."""
    box = bbox_of(footprint(camera, model), base_size, 2)
    x0, y0, x1, y1 = box
    return None if x1 - x0 < 2 or y1 - y0 < 2 else box


def footprint(camera: Camera, model) -> NDArray:
    """``(N, 2)`` base px of the frame's outline under ``model`` (``base_from_corrected``)."""
    return model.apply(camera.outline())


def render_anchor(
    joint: JointBase, frame, camera: Camera, model, field_, fill_radius: float | None = None
) -> None:
    """Add a re-anchored frame to the mid base image where it is empty, only its raw pixels
    within ``fill_radius`` of the centre (``IntraConfig.anchor_fill_radius``; None: all)."""
    hb, wb = joint.mid_valid.shape
    box = anchor_box(camera, model, (wb, hb))
    if box is None:
        return
    image, valid = render_to_base(frame, camera, model, box, field_)
    if fill_radius is not None and fill_radius < 1:
        radius, _ = render_to_base(camera.raw_radius(), camera, model, box, field_)
        valid &= radius < fill_radius
    add_to_mid_base(joint, image, valid, box)


class Anchoring:
    """Re-anchoring of long flights (``IntraConfig.reanchor_coverage``, beyond the paper)."""

    def __init__(self, ctx, joint: JointBase):
        """``ctx``: the run's :class:`registration.run.chunks.ChunkContext`."""
        self.ctx, self.joint = ctx, joint
        self.base, self.base_valid, self.camera = ctx.base, ctx.base_valid, ctx.camera
        self.config = ctx.config

    def wanted(self, frame, state) -> bool:
        """Whether :meth:`maybe` would try to anchor a frame registered as ``state``."""
        cfg = self.config.intra
        if cfg.reanchor_coverage <= 0 or state is None:
            return False
        coverage = mid_coverage(self.joint, self.camera, state.base_from_corrected)
        return coverage < cfg.reanchor_coverage

    def maybe(self, frame, k, record, arrays, state):
        """``(record, arrays, state, anchored)`` of frame ``k``: its intra-sensor result, or,
        when too little of it lies on the mid base image, its registration to the base map
        itself. ``anchored`` is None when no anchor was needed (or re-anchoring is off), True
        when the frame was re-anchored, False when its anchor failed or disagreed."""
        cfg = self.config.intra
        if cfg.reanchor_coverage <= 0 or state is None:
            return record, arrays, state, None
        intra = state.base_from_corrected
        coverage = mid_coverage(self.joint, self.camera, intra)
        if coverage >= cfg.reanchor_coverage:
            return record, arrays, state, None
        t0 = time.perf_counter()
        fine = register_anchor(
            frame, self.base, self.camera, intra, self.config.fine,
            match_in=self.config.match_in, base_valid=self.base_valid,
        )  # fmt: skip
        coverage = round(coverage, 3)
        if not fine:
            why = f"not re-anchored: {fine.reason}"
            return record.with_stats(mid_coverage=coverage, anchor=why), arrays, state, False
        shift = median_gap(fine.base_from_corrected, intra, self.camera)
        if not shift <= cfg.reanchor_max_shift_px:
            why = f"not re-anchored: the map fit is {shift:.1f} px from the frame's"
            return record.with_stats(mid_coverage=coverage, anchor=why), arrays, state, False
        intra_stats = record.stats
        times = dict(intra_stats.get("time_s", {}))
        record, arrays, state = self.anchor(frame, fine, NoCoarse(), times, t0)
        # How the intra-sensor step that the anchor confirmed found the frame.
        found = {k: intra_stats[k] for k in ("coarse_path", "fast_path_reason") if k in intra_stats}
        record = record.with_stats(mid_coverage=coverage, anchor_shift_px=round(shift, 3), **found)
        return record, arrays, state, True

    def anchor(self, frame, fine: FineResult, coarse, times: dict, t0: float):
        """``(record, arrays, state)`` of a frame registered to the base map by ``fine``; the
        frame is added to the mid base image where it has no content (re-anchoring on)."""
        model = fine.base_from_corrected
        field_ = field_stats = None
        if self.config.run_local and self.config.reference_local is not None:
            wb, hb = image_size(self.base)
            field_, field_stats = reference_field(
                fine, (wb, hb), self.config.reference_local,
                footprint(self.camera, model),
            )  # fmt: skip
        if self.config.intra.reanchor_coverage > 0:
            render_anchor(
                self.joint, frame, self.camera, model, field_, self.config.intra.anchor_fill_radius
            )
        times["anchor"] = round(time.perf_counter() - t0, 4)
        record = FrameRecord(
            "ok", stage=ANCHOR_STAGE, stats=_stats(coarse, fine, times, field_stats),
            model=model.to_dict(),
        )  # fmt: skip
        state = previous_frame_state(
            frame, self.camera, model, self.config.intra, match_in=self.config.match_in
        )
        return record, _frame_arrays(fine, field_, field_stats), state


class NoCoarse:
    """Coarse counts of a frame that had no coarse step of its own (an anchor)."""

    n_keypoints_frame = n_keypoints_base = n_matches = n_inliers = 0
    gated = np.zeros(0, bool)
    model_kind = "none"
    heading_deg = None


def median_gap(a, b, camera: Camera) -> float:
    """Median distance (base px) between two ``base_from_corrected`` models over the frame."""
    c = camera.grid(9, 7)
    d = np.hypot(*(a.apply(c) - b.apply(c)).T)
    return float(np.median(d)) if np.isfinite(d).any() else float("inf")
