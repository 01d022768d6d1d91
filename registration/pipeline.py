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
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration import features
from registration.config import PipelineConfig, config_from_dict, config_to_dict
from registration.coords import image_size
from registration.distortion import HarrisModel, check_valid
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
from registration.io import (
    FrameSource,
    read_image,
    write_image_atomic,
    write_json_atomic,
    write_npz_atomic,
)
from registration.result import FORMAT, VERSION, RegistrationResult, frame_record_path
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


def _metadata(
    frames, base, base_path, gamma, seed, reference_frame, config, preset, base_georef=None
) -> dict:
    if base_georef is not None and not isinstance(base_georef, dict):
        base_georef = base_georef.to_dict()
    return {
        "format": FORMAT,
        "version": VERSION,
        "n_frames": len(frames),
        "gamma": float(gamma),
        "frame_size": list(frames.size),
        "base_size": list(image_size(base)),
        "base_path": str(base_path) if base_path else None,
        "frames_source": frames.description,
        "reference_frame": int(reference_frame),
        "seed": None if seed is None else [float(v) for v in seed],
        "preset": preset,
        "config": config_to_dict(config),
        "base_georef": base_georef,
    }


# Keys that must agree for --resume to continue a result rather than mix two different runs.
_RESUME_KEYS = ("n_frames", "gamma", "frame_size", "base_size", "reference_frame", "seed", "config")


def validate_inputs(frames: FrameSource, base: NDArray, gamma, seed, reference_frame) -> None:
    """ValueError naming the problem for a γ, seed or reference frame that cannot work."""
    w, h = frames.size
    check_valid(HarrisModel(float(gamma), w, h))
    if not 0 <= reference_frame < len(frames):
        raise ValueError(
            f"reference frame {reference_frame} out of range: the sequence has {len(frames)} frames"
        )
    if seed is not None:
        fx, fy, bx, by = seed
        wb, hb = image_size(base)
        if not (0 <= fx <= w - 1 and 0 <= fy <= h - 1):
            raise ValueError(f"seed frame point ({fx}, {fy}) lies outside the {w}x{h} frame")
        if not (0 <= bx <= wb - 1 and 0 <= by <= hb - 1):
            raise ValueError(f"seed base point ({bx}, {by}) lies outside the {wb}x{hb} base map")


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


def _frame_arrays(fine: FineResult, field, field_stats=None) -> dict[str, NDArray]:
    arrays = {
        "src": fine.src.astype(np.float64),
        "dst": fine.dst.astype(np.float64),
        "kept": fine.kept.astype(np.uint8),
        "residuals": fine.residuals.astype(np.float64),
    }
    if fine.source is not None:
        arrays["source"] = np.asarray(fine.source, np.int16)
    if field is not None:
        arrays.update({f"field_{k}": np.asarray(v) for k, v in field.to_arrays().items()})
    if field_stats is not None:
        arrays.update({f"field_stats_{k}": v for k, v in field_stats.to_arrays().items()})
    return arrays


def _stats(
    coarse: CoarseResult, fine: FineResult, times: dict[str, float], field_stats=None
) -> dict:
    kept = fine.residuals[fine.kept] if len(fine.residuals) else np.zeros(0)
    stats = {
        "n_keypoints_frame": coarse.n_keypoints_frame,
        "n_keypoints_base": coarse.n_keypoints_base,
        "n_matches": coarse.n_matches,
        "n_gated": int(coarse.gated.sum()),
        "n_coarse_inliers": coarse.n_inliers,
        "n_control_points": int(len(fine.src)),
        "n_inliers": int(fine.kept.sum()),
        "reqcon_iterations": int(fine.iterations),
        "residual_rms_px": float(np.sqrt(np.mean(kept**2))) if len(kept) else None,
        "residual_mean_px": float(np.mean(kept)) if len(kept) else None,
        "time_s": {name: round(v, 4) for name, v in times.items()},
    }
    if field_stats is not None:
        stats["local"] = field_stats.to_dict()
    return stats


class _Writer:
    def __init__(self, out_dir: Path) -> None:
        self.out_dir = out_dir

    def done(self, k: int) -> bool:
        return frame_record_path(self.out_dir, k, ".json").is_file()

    def write(self, k: int, record: dict, arrays: dict[str, NDArray] | None) -> None:
        # The arrays first, the record last: a record on disk means the frame is complete.
        if arrays:
            write_npz_atomic(frame_record_path(self.out_dir, k, ".npz"), **arrays)
        write_json_atomic(frame_record_path(self.out_dir, k, ".json"), {"k": k, **record})


def _prepare_out(out_dir: Path, meta: dict, resume: bool) -> None:
    meta_path = out_dir / "result.json"
    if meta_path.is_file():
        if not resume:
            raise ValueError(
                f"{out_dir} already holds a registration result; pass --resume to continue it "
                "or choose another folder"
            )
        try:
            old = json.loads(meta_path.read_text())
        except json.JSONDecodeError:
            raise ValueError(f"cannot resume: {meta_path} is corrupt") from None
        for key in _RESUME_KEYS:
            if old.get(key) != json.loads(json.dumps(meta[key])):
                raise ValueError(
                    f"cannot resume {out_dir}: its {key} differs from this run's "
                    f"({old.get(key)!r} vs {meta[key]!r})"
                    if key != "config"
                    else f"cannot resume {out_dir}: it was made with a different configuration"
                )
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "frames").mkdir(exist_ok=True)
    write_json_atomic(meta_path, meta)


def register_sequence(
    frames: FrameSource,
    base: NDArray,
    gamma: float,
    out_dir: str | Path,
    *,
    config: PipelineConfig,
    preset: str | None = None,
    base_path: str | Path | None = None,
    seed: tuple[float, float, float, float] | None = None,
    reference_frame: int = 0,
    resume: bool = False,
    progress: Progress | None = None,
    cancel: threading.Event | None = None,
    reference: tuple[CoarseResult, FineResult] | None = None,
    base_georef=None,
    base_valid: NDArray[np.bool_] | None = None,
) -> RegistrationResult:
    """Register every frame of ``frames`` to ``base`` and write the result folder ``out_dir``.

    Args:
        frames: the sequence (:func:`registration.io.open_frames`).
        base: base map, BGR uint8 (Hb, Wb, 3).
        gamma: Harris γ of the frames.
        config: pipeline configuration (:mod:`registration.config`).
        seed: one corresponding point ``(fx, fy, bx, by)``: raw reference-frame px, base px.
        reference_frame: the frame registered inter-sensor (paper: the first).
        resume: continue a result folder made with the same inputs and configuration.
        progress: called with ``(frames done, n_frames)`` after each frame.
        cancel: when set, the run stops after the frame in progress (finished frames are kept).
        reference: coarse and fine results for the reference frame computed beforehand (the
            app's seed step), used instead of recomputing them.
        base_georef: the base map's :class:`registration.georef.GeoReference` (or its
            ``to_dict()``), recorded in ``result.json`` as ``base_georef`` so that the result
            maps to map coordinates (``result.frame_to_map``); None for a plain image.
        base_valid: ``(Hb, Wb)`` bool, False where the base map has no data
            (:func:`registration.io.read_base_map`); no control point is taken there.

    Returns:
        The result, as :func:`registration.load` would open it.

    Raises:
        ValueError: unusable input (γ out of range, seed outside the images, a folder holding
            another run); :class:`RegistrationFailed` when the reference frame cannot be
            registered.
    """
    out_dir = Path(out_dir)
    validate_inputs(frames, base, gamma, seed, reference_frame)
    if base_valid is not None and np.shape(base_valid) != base.shape[:2]:
        raise ValueError(
            f"base_valid has shape {np.shape(base_valid)}, the base map {base.shape[:2]}"
        )
    meta = _metadata(
        frames, base, base_path, gamma, seed, reference_frame, config, preset, base_georef
    )
    _prepare_out(out_dir, meta, resume)
    writer = _Writer(out_dir)
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
        _set_previous(joint, frames, gamma, result, previous_in_order(k, reference_frame), config)
        frame = frames.get(k)
        record, arrays, state = _register_one(frame, k, gamma, joint, config)
        writer.write(k, record, arrays)
        if state is not None:
            joint.previous = state
            joint.previous_index = k
        n_done += 1
        if progress:
            progress(n_done, n)
    result.reload()
    return result


def _reference_step(
    frames, base, gamma, seed, ref, config, writer, reference, base_valid=None
) -> JointBase:
    """Register the reference frame (or load it when resuming) and build the joint base."""
    out_dir = writer.out_dir
    frame = frames.get(ref)
    if writer.done(ref):
        rec = RegistrationResult(out_dir)
        if not rec.is_ok(ref):
            raise RegistrationFailed(
                f"the reference frame {ref} failed before: {rec.records[ref].get('reason')}"
            )
        mid = read_image(out_dir / "mid_base.png")
        valid = read_image(out_dir / "mid_base_valid.png", grey=True) > 127
        joint = make_joint_base(mid, valid, config)
        joint.previous = previous_frame_state(frame, gamma, rec.model(ref), config)
        joint.previous_index = ref
        return joint

    t0 = time.perf_counter()
    if reference is not None:
        coarse, fine = reference
    else:
        coarse = coarse_register(
            frame, base, gamma, seed, config, rng=config.random_seed + ref, base_valid=base_valid
        )
        fine = (
            fine_register_reference(frame, base, gamma, coarse, config, base_valid=base_valid)
            if coarse
            else FineResult(False, coarse.reason, None, *_empty_points())
        )
    times = {"coarse": coarse.time_s, "fine": fine.time_s, "total": time.perf_counter() - t0}
    if not fine:
        writer.write(
            ref, {"status": "failed", "reason": fine.reason, "stats": {}, "model": None}, None
        )
        raise RegistrationFailed(
            f"the reference frame {ref} could not be registered to the base map ({fine.reason}); "
            "check --seed and --gamma"
        )
    model = fine.base_from_corrected
    wb, hb = image_size(base)
    field, field_stats = None, None
    if config.run_local and config.reference_local is not None:
        field, field_stats = reference_field(fine, (wb, hb), config.reference_local)
    # The mid base image is the reference frame registered with its own field: every other
    # frame's local stage aligns to it, so its accuracy is theirs.
    mid, valid = render_to_base(frame, gamma, model, (0, 0, wb, hb), field)
    write_image_atomic(out_dir / "mid_base.png", mid)
    write_image_atomic(out_dir / "mid_base_valid.png", valid.astype(np.uint8) * 255)
    record = {
        "status": "ok",
        "reason": "",
        "stage": "inter-sensor",
        "stats": _stats(coarse, fine, times, field_stats),
        "model": model.to_dict(),
    }
    writer.write(ref, record, _frame_arrays(fine, field, field_stats))
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
