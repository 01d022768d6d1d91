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
from registration.coords import image_size
from registration.distortion import HarrisModel, check_harris_gamma
from registration.global_registration import (
    CoarseResult,
    FineResult,
    JointBase,
    coarse_register,
    fine_register_reference,
    footprint_bbox,
    make_joint_base,
    previous_frame_state,
    register_intra,
)
from registration.io import FrameSource
from registration.result import RegistrationResult, ResultWriter, make_metadata
from registration.result import frame_arrays as _frame_arrays
from registration.result import frame_stats as _stats
from registration.warp import warp_image

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


def render_to_base(
    frame_raw: NDArray,
    gamma: float,
    base_from_corrected,
    box: tuple[int, int, int, int],
    field=None,
) -> tuple[NDArray, NDArray[np.bool_]]:
    """The raw frame resampled once into the base-pixel box ``(x0, y0, x1, y1)``.

    Returns the image and its validity mask; base pixels map to raw pixels through the
    displacement field (when given: ``x + d(x)``, :mod:`registration.local`), the model's
    inverse and the Harris model, so the frame is interpolated only once.
    """
    w, h = image_size(frame_raw)
    harris = HarrisModel(gamma, w, h)
    x0, y0, x1, y1 = box

    def raw_from_base(b):
        if field is not None:
            b = b + field.sample(b, outside="clamp")
        return harris.raw_from_corrected(base_from_corrected.inverse(b))

    return warp_image(frame_raw, raw_from_base, x1 - x0, y1 - y0, origin=(x0, y0))


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
    # Redone when its record or the mid base image is damaged or missing.
    mid_base = writer.read_mid_base() if writer.done(ref) else None
    if writer.done(ref):
        rec = RegistrationResult(out_dir)
        if not rec.is_ok(ref):
            raise RegistrationFailed(
                f"the reference frame {ref} failed before: {rec.records[ref].get('reason')}"
            )
    if mid_base is not None:
        mid, valid = mid_base
        joint = make_joint_base(mid, valid, config)
        joint.previous = previous_frame_state(frame, gamma, rec.model(ref), config)
        joint.previous_index = ref
        return joint

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
    joint = make_joint_base(mid, valid, config)
    joint.previous = previous_frame_state(frame, gamma, model, config)
    joint.previous_index = ref
    return joint


def reference_field(fine: FineResult, base_size: tuple[int, int], config):
    """The reference frame's inter-sensor displacement field (beyond the paper) from its template
    control points: each match says where the base map shows what the global model puts at
    ``model(src)``, i.e. a sample ``d(dst) = model(src) - dst`` of the field of
    :mod:`registration.local`. The per-cell REQCON and the moving-car guard of the local stage
    turn them into a field; mismatches are outvoted by their neighbourhood.

    Returns ``(field, stats)``, or ``(None, None)`` without control points.
    """
    from registration.local import estimate_field_from_matches

    ok = np.isfinite(fine.src).all(axis=1) & np.isfinite(fine.dst).all(axis=1)
    if not ok.any():
        return None, None
    dst = fine.dst[ok]
    disp = fine.base_from_corrected.apply(fine.src[ok]) - dst
    wb, hb = base_size
    x0, y0 = np.clip(np.floor(dst.min(axis=0)).astype(int), 0, (wb - 1, hb - 1))
    x1, y1 = np.clip(np.ceil(dst.max(axis=0)).astype(int) + 1, (x0 + 1, y0 + 1), (wb, hb))
    return estimate_field_from_matches(dst, disp, x1 - x0, y1 - y0, config, origin=(x0, y0))


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
        field, field_stats = _local_field(frame, gamma, model, joint, config)
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


def _local_field(frame, gamma, model, joint: JointBase, config: PipelineConfig):
    """The frame's displacement field against the mid base image (paper section 5)."""
    from registration.local import (
        detect_keypoints,
        estimate_field,
        estimate_field_in_frame,
        flow_scale,
        prepare_flow_reference,
    )

    hb, wb = joint.mid_grey.shape
    h, w = frame.shape[:2]
    harris = HarrisModel(gamma, w, h)

    def base_from_raw(q):
        return model.apply(harris.corrected_from_raw(q))

    grey = features.to_grey(frame)
    if config.local.method == "flow":
        # Measured in the frame's geometry: no rendering of the frame into base pixels.
        if joint.flow_reference is None:
            joint.flow_reference = prepare_flow_reference(
                joint.mid_grey, joint.mid_valid, flow_scale(w, config.local)
            )
        return estimate_field_in_frame(grey, base_from_raw, joint.flow_reference, config.local)
    box = footprint_bbox(base_from_raw, w, h, (wb, hb))
    x0, y0, x1, y1 = box
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None, None
    registered, valid = render_to_base(grey, gamma, model, box)
    reference = joint.mid_grey[y0:y1, x0:x1]
    both = valid & joint.mid_valid[y0:y1, x0:x1]
    # The mid base image is the reference of every frame: detect its keypoints once.
    if joint.local_keypoints is None:
        joint.local_keypoints = detect_keypoints(joint.mid_grey, config.local, mask=joint.mid_valid)
    return estimate_field(
        registered,
        reference,
        config.local,
        valid_mask=both,
        origin=(x0, y0),
        reference_keypoints=joint.local_keypoints,
    )


def load_config(out_dir: str | Path) -> PipelineConfig:
    """The configuration a result folder was made with."""
    meta = json.loads((Path(out_dir) / "result.json").read_text())
    return config_from_dict(meta["config"])
