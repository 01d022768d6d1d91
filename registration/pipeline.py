"""A whole sequence: the reference frame to the base map, every other frame to the joint base,
then the local field, written frame by frame and atomically into a result folder so that an
interrupted run resumes without redoing finished frames (paper Fig. 3).

Processing order: the reference frame, then the frames after it in order, then the frames before
it backwards, so that the "previous" frame (paper 4.4) is always the registered neighbour nearer
to the reference.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration import features
from registration.coarse import normalise_seeds
from registration.config import PipelineConfig, config_from_dict
from registration.coords import bbox_of, frame_outline, image_size
from registration.distortion import HarrisModel, check_harris_gamma
from registration.global_registration import (
    CoarseResult,
    FineResult,
    JointBase,
    add_to_mid_base,
    coarse_register,
    fine_register_reference,
    make_joint_base,
    mid_coverage,
    previous_frame_state,
    register_anchor,
    register_intra,
)
from registration.io import FrameSource
from registration.local import frame_field, reference_field
from registration.render import render_to_base
from registration.result import RegistrationResult, ResultWriter, make_metadata
from registration.result import frame_arrays as _frame_arrays
from registration.result import frame_stats as _stats

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]


class RegistrationFailed(ValueError):
    """The reference frame could not be registered, so no frame can be."""


def processing_order(n_frames: int, reference_frame: int) -> list[int]:
    """Reference first, then forwards, then backwards from the reference."""
    return [
        reference_frame,
        *range(reference_frame + 1, n_frames),
        *range(reference_frame - 1, -1, -1),
    ]


def previous_in_order(k: int, reference_frame: int) -> int:
    """The neighbour of ``k`` that is processed before it (nearer to the reference)."""
    return k - 1 if k > reference_frame else k + 1


def validate_inputs(frames: FrameSource, base: NDArray, gamma, seed, reference_frame) -> None:
    """ValueError naming the problem for a γ, seed or reference frame that cannot work (out of
    range, unreadable, or of another size than the sequence's first readable frame)."""
    w, h = frames.size
    check_harris_gamma(float(gamma), w, h)
    if not 0 <= reference_frame < len(frames):
        raise ValueError(
            f"reference frame {reference_frame} out of range: the sequence has {len(frames)} frames"
        )
    # Before anything is written: a run cannot start from an unreadable reference frame.
    try:
        rw, rh = image_size(frames.get(reference_frame))
    except ValueError as exc:  # FrameReadError
        raise ValueError(
            f"cannot read reference frame {reference_frame}: {exc}; choose another "
            "--reference-frame"
        ) from None
    if (rw, rh) != (w, h):
        raise ValueError(
            f"reference frame {reference_frame} is {rw}x{rh} pixels but the sequence's first "
            f"readable frame is {w}x{h}; choose another --reference-frame"
        )
    seeds = normalise_seeds(seed)
    wb, hb = image_size(base)
    for fx, fy, bx, by in seeds:
        if not (0 <= fx <= w - 1 and 0 <= fy <= h - 1):
            raise ValueError(f"seed frame point ({fx}, {fy}) lies outside the {w}x{h} frame")
        if not (0 <= bx <= wb - 1 and 0 <= by <= hb - 1):
            raise ValueError(f"seed base point ({bx}, {by}) lies outside the {wb}x{hb} base map")
    if len(seeds) == 2:
        (f0, g0, b0, c0), (f1, g1, b1, c1) = seeds
        if math.hypot(f1 - f0, g1 - g0) < 20 or math.hypot(b1 - b0, c1 - c0) < 20:
            raise ValueError(
                "the two seeds must be at least 20 px apart in both images to fix heading and "
                f"scale, got frame ({f0:g}, {g0:g}) and ({f1:g}, {g1:g}), base ({b0:g}, {c0:g}) "
                f"and ({b1:g}, {c1:g})"
            )


def register_sequence(
    frames: FrameSource,
    base: NDArray,
    gamma: float,
    out_dir: str | Path,
    *,
    config: PipelineConfig,
    preset: str | None = None,
    base_path: str | Path | None = None,
    seed=None,
    base_valid: NDArray | None = None,
    reference_frame: int = 0,
    resume: bool = False,
    force: bool = False,
    progress: Progress | None = None,
    cancel: threading.Event | None = None,
    reference: tuple[CoarseResult, FineResult] | None = None,
    base_georef=None,
) -> RegistrationResult:
    """Register every frame of ``frames`` to ``base`` and write the result folder ``out_dir``.

    Args:
        frames: the sequence (:func:`registration.io.open_frames`).
        base: base map, BGR uint8 (Hb, Wb, 3).
        gamma: Harris γ of the frames.
        config: pipeline configuration (:mod:`registration.config`).
        seed: one corresponding point ``(fx, fy, bx, by)`` (raw reference-frame px, base px),
            or a list of two (they fix heading and scale); None searches all headings and
            scales.
        base_valid: ``(Hb, Wb)`` bool, False where the base map has no data
            (:func:`registration.io.read_base_map`); no control point is taken there.
        reference_frame: the frame registered inter-sensor (paper: the first).
        resume: continue a result folder made with the same inputs and configuration.
        force: delete the result already in ``out_dir`` and start over.
        progress: called with ``(frames done, n_frames)`` after each frame.
        cancel: when set, the run stops after the frame in progress (finished frames are kept).
        reference: coarse and fine results for the reference frame computed beforehand (the
            app's seed step), used instead of recomputing them.
        base_georef: the base map's :class:`registration.georef.GeoReference` (or its
            ``to_dict()``), recorded in ``result.json`` as ``base_georef`` so that the result
            maps to map coordinates (``result.frame_to_map``); None for a plain image.

    Returns:
        The result, as :func:`registration.load` would open it.

    Raises:
        ValueError: unusable input (γ out of range, seed outside the images, an unreadable
            reference frame, a folder holding another run or being written by another process,
            see :class:`registration.result.ResultWriter`); :class:`RegistrationFailed` when the
            reference frame cannot be registered.
    """
    out_dir = Path(out_dir)
    validate_inputs(frames, base, gamma, seed, reference_frame)
    if base_valid is not None and np.shape(base_valid) != base.shape[:2]:
        raise ValueError(
            f"base_valid has shape {np.shape(base_valid)}, the base map {base.shape[:2]}"
        )
    if base_georef is not None and not isinstance(base_georef, dict):
        base_georef = base_georef.to_dict()
    meta = make_metadata(
        frames, base, base_path, gamma, seed, reference_frame, config, preset,
        extra={"base_georef": base_georef},
    )  # fmt: skip
    with ResultWriter.create(out_dir, meta, frames=frames, resume=resume, force=force) as writer:
        n = len(frames)
        order = processing_order(n, reference_frame)
        n_done = sum(writer.done(k) for k in order)
        if progress:
            progress(n_done, n)

        joint = _reference_step(
            frames, base, gamma, seed, reference_frame, config, writer, reference, base_valid
        )
        anchors = _Anchoring(base, base_valid, gamma, config, writer, joint)
        n_done = sum(writer.done(k) for k in order)
        if progress:
            progress(n_done, n)

        result = RegistrationResult(out_dir)
        for k in order[1:]:
            if cancel is not None and cancel.is_set():
                break
            if writer.done(k):
                continue
            frame, problem = read_frame(frames, k)
            if frame is None:
                # Unreadable or of another size: marked failed, the run goes on (the next frame
                # takes the last good one as its previous frame).
                writer.write_frame(k, _failed_record(problem))
            else:
                prev = previous_in_order(k, reference_frame)
                _set_previous(joint, frames, gamma, result, prev, config)
                record, arrays, state = _register_one(frame, k, gamma, joint, config)
                record, arrays, state = anchors.maybe(frame, k, record, arrays, state)
                writer.write_frame(k, record, arrays)
                if state is not None:
                    joint.previous = state
                    joint.previous_index = k
            n_done += 1
            if progress:
                progress(n_done, n)
    result.reload()
    return result


def read_frame(frames: FrameSource, k: int) -> tuple[NDArray | None, str]:
    """``(frame, "")``, or ``(None, why)`` when frame ``k`` cannot be read or its size differs
    from the sequence's (the reference frame's)."""
    try:
        frame = frames.get(k)
    except ValueError as exc:  # FrameReadError
        return None, f"cannot read frame {k}: {exc}"
    w, h = image_size(frame)
    if (w, h) != tuple(frames.size):
        fw, fh = frames.size
        return None, f"frame {k} is {w}x{h} pixels but the reference frame is {fw}x{fh}"
    return frame, ""


def _failed_record(reason: str) -> dict:
    return {"status": "failed", "reason": reason, "stats": {}, "model": None}


def _reference_step(
    frames, base, gamma, seed, ref, config, writer, reference, base_valid=None
) -> JointBase:
    """Register the reference frame (or load it when resuming) and build the joint base."""
    out_dir = writer.out_dir
    frame, problem = read_frame(frames, ref)
    if frame is None:
        raise ValueError(f"{problem}; choose another --reference-frame")
    if writer.done(ref):
        rec = RegistrationResult(out_dir)
        if not rec.is_ok(ref):
            raise RegistrationFailed(
                f"the reference frame {ref} failed before: {rec.records[ref].get('reason')}"
            )
        # Resuming: the mid base image is rebuilt from the records (the reference frame, then
        # the anchors in processing order), exactly as the uninterrupted run built it.
        return _rebuild_joint(frames, base, gamma, rec, config, base_valid)

    t0 = time.perf_counter()
    if reference is not None:
        coarse, fine = reference
    else:
        coarse = coarse_register(
            frame, base, gamma, seed, config, base_valid=base_valid, rng=config.random_seed + ref
        )
        fine = (
            fine_register_reference(frame, base, gamma, coarse, config, base_valid=base_valid)
            if coarse
            else FineResult(False, coarse.reason, None, *_empty_points())
        )
    times = {"coarse": coarse.time_s, "fine": fine.time_s, "total": time.perf_counter() - t0}
    if not fine:
        writer.write_frame(ref, _failed_record(fine.reason))
        raise RegistrationFailed(
            f"the reference frame {ref} could not be registered to the base map: {fine.reason}"
        )
    model = fine.base_from_corrected
    wb, hb = image_size(base)
    field, field_stats = None, None
    if config.run_local and config.reference_local is not None:
        field, field_stats = reference_field(fine, (wb, hb), config.reference_local)
    # The mid base image is the reference frame registered with its own field: every other
    # frame's local stage aligns to it, so its accuracy is theirs.
    mid, valid = render_to_base(frame, gamma, model, (0, 0, wb, hb), field)
    writer.write_mid_base(mid, valid)
    record = {
        "status": "ok",
        "reason": "",
        "stage": "inter-sensor",
        "stats": _stats(coarse, fine, times, field_stats),
        "model": model.to_dict(),
    }
    writer.write_frame(ref, record, _frame_arrays(fine, field, field_stats))
    joint = _joint_base(mid, valid, base, base_valid, config)
    joint.previous = previous_frame_state(frame, gamma, model, config)
    joint.previous_index = ref
    return joint


def _joint_base(mid, valid, base, base_valid, config) -> JointBase:
    joint = make_joint_base(mid, valid, config)
    if config.intra.base_fallback:
        joint.base_grey = features.to_grey(base)
        joint.base_valid = base_valid
    return joint


def _rebuild_joint(frames, base, gamma, rec: RegistrationResult, config, base_valid) -> JointBase:
    """The joint base of a resumed run, from the records alone: the reference frame rendered
    with its model and field, then each anchor frame's pixels where the mid base image is still
    empty, in processing order."""
    ref = rec.reference_frame
    wb, hb = image_size(base)
    frame = frames.get(ref)
    mid, valid = render_to_base(frame, gamma, rec.model(ref), (0, 0, wb, hb), rec.field(ref))
    joint = _joint_base(mid, valid, base, base_valid, config)
    for k in processing_order(rec.n_frames, ref)[1:]:
        r = rec.records[k]
        if r.get("status") == "ok" and r.get("stage") == ANCHOR_STAGE:
            _render_anchor(joint, frames.get(k), gamma, rec.model(k), rec.field(k), config)
    joint.previous = previous_frame_state(frame, gamma, rec.model(ref), config)
    joint.previous_index = ref
    return joint


ANCHOR_STAGE = "inter-sensor anchor"


def _render_anchor(joint: JointBase, frame, gamma, model, field, config) -> None:
    """Add a re-anchored frame to the mid base image (where it is empty)."""
    hb, wb = joint.mid_valid.shape
    w, h = image_size(frame)
    harris = HarrisModel(gamma, w, h)
    box = bbox_of(model.apply(harris.corrected_from_raw(frame_outline(w, h))), (wb, hb), 2)
    x0, y0, x1, y1 = box
    if x1 - x0 < 2 or y1 - y0 < 2:
        return
    image, valid = render_to_base(frame, gamma, model, box, field)
    add_to_mid_base(joint, image, valid, box, config)


class _Anchoring:
    """Re-anchoring of long flights (``IntraConfig.reanchor_coverage``, beyond the paper)."""

    def __init__(self, base, base_valid, gamma, config, writer, joint: JointBase):
        self.base, self.base_valid, self.gamma = base, base_valid, gamma
        self.config, self.writer, self.joint = config, writer, joint

    def maybe(self, frame, k, record, arrays, state):
        """``(record, arrays, state)`` of frame ``k``: its intra-sensor result, or, when too
        little of it lies on the mid base image, its registration to the base map itself."""
        cfg = self.config.intra
        if cfg.reanchor_coverage <= 0 or state is None:
            return record, arrays, state
        intra = state.base_from_corrected
        coverage = mid_coverage(self.joint, frame, self.gamma, intra)
        if coverage >= cfg.reanchor_coverage:
            return record, arrays, state
        t0 = time.perf_counter()
        fine = register_anchor(frame, self.base, self.gamma, intra, self.config,
                               base_valid=self.base_valid)  # fmt: skip
        stats = record.setdefault("stats", {})
        stats["mid_coverage"] = round(coverage, 3)
        if not fine:
            stats["anchor"] = f"not re-anchored: {fine.reason}"
            return record, arrays, state
        shift = _median_gap(fine.base_from_corrected, intra, frame, self.gamma)
        if not shift <= cfg.reanchor_max_shift_px:
            stats["anchor"] = f"not re-anchored: the map fit is {shift:.1f} px from the frame's"
            return record, arrays, state
        model = fine.base_from_corrected
        field = field_stats = None
        if self.config.run_local and self.config.reference_local is not None:
            wb, hb = image_size(self.base)
            field, field_stats = reference_field(fine, (wb, hb), self.config.reference_local)
        _render_anchor(self.joint, frame, self.gamma, model, field, self.config)
        if self.joint.mid_image is not None:
            self.writer.write_mid_base(self.joint.mid_image, self.joint.mid_valid)
        times = dict(stats.get("time_s", {}))
        times["anchor"] = round(time.perf_counter() - t0, 4)
        new_stats = _stats(_NoCoarse(), fine, times, field_stats)
        new_stats.update(mid_coverage=round(coverage, 3), anchor_shift_px=round(shift, 3))
        record = {"status": "ok", "reason": "", "stage": ANCHOR_STAGE, "stats": new_stats,
                  "model": model.to_dict()}  # fmt: skip
        state = previous_frame_state(frame, self.gamma, model, self.config)
        return record, _frame_arrays(fine, field, field_stats), state


class _NoCoarse:
    """Coarse counts of a frame that had no coarse step of its own (an anchor)."""

    n_keypoints_frame = n_keypoints_base = n_matches = n_inliers = 0
    gated = np.zeros(0, bool)
    model_kind = "none"
    heading_deg = None


def _median_gap(a, b, frame, gamma) -> float:
    """Median distance (base px) between two ``base_from_corrected`` models over the frame."""
    w, h = image_size(frame)
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 7))
    c = HarrisModel(gamma, w, h).corrected_from_raw(np.c_[gx.ravel(), gy.ravel()])
    d = np.hypot(*(a.apply(c) - b.apply(c)).T)
    return float(np.median(d)) if np.isfinite(d).any() else float("inf")


def _empty_points():
    z = np.zeros((0, 2))
    return z, z, np.zeros(0, bool), np.zeros(0), 0


def _set_previous(joint: JointBase, frames, gamma, result: RegistrationResult, prev_k, config):
    """Make sure ``joint.previous`` is frame ``prev_k`` (after a resume or a failed frame, the
    nearest earlier registered frame in processing order)."""
    if joint.previous_index == prev_k:
        return
    result.reload()
    ref = result.reference_frame
    k = prev_k
    while k != ref and not result.is_ok(k):
        k = previous_in_order(k, ref)
    if joint.previous_index == k:
        return
    joint.previous = previous_frame_state(frames.get(k), gamma, result.model(k), config)
    joint.previous_index = k


def _register_one(frame, k, gamma, joint: JointBase, config: PipelineConfig):
    t0 = time.perf_counter()
    try:
        coarse, fine, state = register_intra(
            frame, gamma, joint, config, rng=config.random_seed + k
        )
    except np.linalg.LinAlgError as exc:
        reason = f"degenerate fit: {exc}"
        return {"status": "failed", "reason": reason, "stats": {}, "model": None}, None, None
    times = {"coarse": coarse.time_s, "fine": fine.time_s}
    if not fine:
        stats = _stats(coarse, fine, times) if coarse else {"time_s": times}
        record = {"status": "failed", "reason": fine.reason, "stats": stats, "model": None}
        return record, (_frame_arrays(fine, None) if len(fine.src) else None), None
    model = fine.base_from_corrected
    field, field_stats = None, None
    if config.run_local:
        t1 = time.perf_counter()
        field, field_stats = frame_field(frame, gamma, model, joint, config.local)
        times["local"] = time.perf_counter() - t1
    times["total"] = time.perf_counter() - t0
    record = {
        "status": "ok",
        "reason": "",
        "stage": "intra-sensor",
        "stats": _stats(coarse, fine, times, field_stats),
        "model": model.to_dict(),
    }
    return record, _frame_arrays(fine, field, field_stats), state


def load_config(out_dir: str | Path) -> PipelineConfig:
    """The configuration a result folder was made with."""
    meta = json.loads((Path(out_dir) / "result.json").read_text())
    return config_from_dict(meta["config"])
