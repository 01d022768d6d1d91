"""A whole sequence: the reference frame to the base map, every other frame to the joint base,
then the local field, written frame by frame and atomically into a result folder so that an
interrupted run resumes without redoing finished frames (paper Fig. 3).

This module is the orchestration: it checks the inputs, registers the reference frame (paper
4.3) and renders the mid base image, hands the other frames to a chunk executor
(:mod:`registration.run.intra_frames`: the serial one here, or :mod:`registration.run.dask_executor` on a Dask
cluster) and writes what they give through :class:`registration.run.writer.ResultWriter`. The
stages themselves live in their modules: ``coarse``, ``global_registration``, ``local``,
``render``, ``anchoring``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration.coords import image_size
from registration.errors import ReferenceFrameUnusable, RegistrationFailed
from registration.geometry import model_from_dict, scale_at_frame_centre
from registration.global_registration import (
    CoarseResult,
    FineResult,
    coarse_register,
    fine_register_reference,
    make_joint_base,
    normalise_seeds,
    register_with_lens,
)
from registration.io import FrameSource
from registration.lens import Camera, check_harris_gamma
from registration.local import reference_field
from registration.render import render_to_base
from registration.run.adjust import adjust_result
from registration.run.anchoring import ANCHOR_STAGE, anchor_box, footprint, render_anchor
from registration.run.chunks import ChunkContext, ChunkExecutor, chunk_jobs, processing_order
from registration.run.config import PipelineConfig, config_from_dict
from registration.run.identity import make_metadata
from registration.run.intra_frames import SerialExecutor, read_frame
from registration.run.records import MID_BASE, FrameRecord
from registration.run.records import frame_arrays as _frame_arrays
from registration.run.records import frame_stats as _stats
from registration.run.result import RegistrationResult
from registration.run.result_folder import LOCK_NAME, folder_state, remove_result
from registration.run.writer import ResultWriter

Progress = Callable[[int, int], None]


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
        raise ReferenceFrameUnusable(
            f"cannot read reference frame {reference_frame}: {exc}", reference_frame
        ) from None
    if (rw, rh) != (w, h):
        raise ReferenceFrameUnusable(
            f"reference frame {reference_frame} is {rw}x{rh} pixels but the sequence's first "
            f"readable frame is {w}x{h}",
            reference_frame,
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
    executor: ChunkExecutor | None = None,
    overlap: bool | None = None,
    adjust_progress: Progress | None = None,
) -> RegistrationResult:
    """Register every frame of ``frames`` to ``base`` and write the result folder ``out_dir``.

    Args:
        frames: the sequence (:func:`registration.io.frames.open_frames`).
        base: base map, BGR uint8 (Hb, Wb, 3).
        gamma: Harris γ of the frames.
        config: pipeline configuration (:mod:`registration.run.config`); ``config.chunk_frames``
            splits the sequence into independent chunks (:func:`chunk_plan`).
        seed: one corresponding point ``(fx, fy, bx, by)`` (raw reference-frame px, base px),
            or a list of two (they fix heading and scale); None searches all headings and
            scales.
        base_valid: ``(Hb, Wb)`` bool, False where the base map has no data
            (:func:`registration.gis.basemap.read_base_map`); no control point is taken there.
        reference_frame: the frame registered inter-sensor (paper: the first).
        resume: continue a result folder made with the same inputs and configuration.
        force: delete the result already in ``out_dir`` and start over.
        progress: called with ``(frames done, n_frames)`` after each frame.
        cancel: when set, the run stops after the frame in progress (finished frames are kept).
        adjust_progress: called with ``(frames adjusted, frames ok)`` as the sequence
            adjustment (``config.adjust``) makes frames final.
        reference: coarse and fine results for the reference frame computed beforehand (the
            app's seed step), used instead of recomputing them.
        base_georef: the base map's :class:`registration.gis.georef.GeoReference` (or its
            ``to_dict()``), recorded in ``result.json`` as ``base_georef`` so that the result
            maps to map coordinates (``result.frame_to_map``); None for a plain image.
        executor: where the chunks run (:class:`SerialExecutor` when None;
            :class:`registration.run.dask_executor.DaskExecutor` on a Dask cluster). The result does
            not depend on it; this process writes every frame as its output arrives.
        overlap: decode frames ahead and run each frame's local stage in a second thread
            while the next frame's global stage runs (:func:`run_chunk`), so that both cores
            work; the result is the same to the bit. None (default): on for a run in this
            process, off on a Dask cluster (its workers are single-threaded processes, one per
            core).

    Returns:
        The result, as :func:`registration.load` would open it.

    Raises:
        ValueError: unusable input (γ out of range, seed outside the images, an unreadable
            reference frame, a folder holding another run or being written by another process,
            see :class:`registration.run.writer.ResultWriter`); :class:`RegistrationFailed` when the
            reference frame cannot be registered.
    """
    out_dir = Path(out_dir)
    meta = _checked_metadata(
        frames, base, gamma, seed, reference_frame, base_valid, base_georef, base_path, config,
        preset,
    )  # fmt: skip
    # A run that fails at the reference frame has computed nothing: when it made the folder
    # (or found it empty), it leaves it as it was, so that a run with a corrected click or γ
    # needs no --force.
    before = folder_state(out_dir)
    try:
        return _register(
            frames, base, gamma, out_dir, meta, config, seed, base_valid, reference_frame,
            resume, force, progress, cancel, reference, executor, overlap, adjust_progress,
        )  # fmt: skip
    except (RegistrationFailed, ReferenceFrameUnusable) as exc:
        if before in ("missing", "empty") and exc.frame == reference_frame:
            _discard_failed_start(out_dir, made_folder=before == "missing")
        raise


def _discard_failed_start(out_dir: Path, *, made_folder: bool) -> None:
    """Remove what a run that failed at its reference frame wrote into a folder it found
    empty (and the folder and its lock file when the run made it)."""
    remove_result(out_dir)
    if made_folder:
        (out_dir / LOCK_NAME).unlink(missing_ok=True)
        try:
            out_dir.rmdir()  # only when nothing else is in it
        except OSError:
            pass


def _register(
    frames, base, gamma, out_dir, meta, config, seed, base_valid, reference_frame, resume,
    force, progress, cancel, reference, executor, overlap, adjust_progress,
) -> RegistrationResult:  # fmt: skip
    """:func:`register_sequence` after its inputs were checked."""
    with ResultWriter.create(out_dir, meta, frames=frames, resume=resume, force=force) as writer:
        n = len(frames)
        n_done = sum(writer.done(k) for k in range(n))
        if progress:
            progress(n_done, n)
        mid_missing = not (out_dir / MID_BASE).is_file()
        camera = Camera(gamma, *frames.size)
        mid, valid, model, camera = _reference_step(
            frames, base, camera, seed, reference_frame, config, writer, reference, base_valid
        )
        config = _at_base_resolution(config, camera, model_from_dict(model))
        n_done = sum(writer.done(k) for k in range(n))
        if progress:
            progress(n_done, n)
        context = ChunkContext(
            frames, base, base_valid, camera, config, reference_frame, model, mid, valid,
            meta["inputs"]["frames"], executor is None if overlap is None else overlap,
        )  # fmt: skip
        jobs = chunk_jobs(writer, n, reference_frame, config)
        cancelled = cancel is not None and cancel.is_set()
        if jobs and not cancelled:
            outputs = (executor or SerialExecutor()).run(context, jobs, cancel)
            n_done = _write_outputs(writer, outputs, n_done, n, progress, cancel)
        if n_done == n and (jobs or mid_missing):
            _write_mosaic(writer, context)
        if config.adjust is not None and n_done == n and not (cancel and cancel.is_set()):
            adjust_result(writer, frames, config.adjust, adjust_progress, cancel)
    return RegistrationResult(out_dir)


def _checked_metadata(
    frames, base, gamma, seed, reference_frame, base_valid, base_georef, base_path, config, preset
) -> dict:
    """``result.json``'s content for a run of these inputs (:func:`make_metadata`), after the
    checks that refuse unusable ones (:func:`validate_inputs`, the no-data mask's shape)."""
    validate_inputs(frames, base, gamma, seed, reference_frame)
    if base_valid is not None and np.shape(base_valid) != base.shape[:2]:
        raise ValueError(
            f"base_valid has shape {np.shape(base_valid)}, the base map {base.shape[:2]}"
        )
    if base_georef is not None and not isinstance(base_georef, dict):
        base_georef = base_georef.to_dict()
    return make_metadata(
        frames, base, base_path, gamma, seed, reference_frame, config, preset,
        extra={"base_georef": base_georef}, base_valid=base_valid,
    )  # fmt: skip


def _write_outputs(writer, outputs, n_done: int, n: int, progress, cancel) -> int:
    """Write each frame the chunks yield (``(k, record, arrays)``), once, reporting progress,
    until they end or ``cancel`` is set; the number of frames done."""
    try:
        for k, record, arrays in outputs:
            if not writer.done(k):  # a chunk redone after its worker died repeats it
                writer.write_frame(k, record, arrays)
                n_done += 1
                if progress:
                    progress(n_done, n)
            if cancel is not None and cancel.is_set():
                break
    finally:
        outputs.close()
    return n_done


def _reference_step(
    frames, base, camera: Camera, seed, ref, config: PipelineConfig, writer, reference,
    base_valid=None,
) -> tuple[NDArray, NDArray, dict, Camera]:  # fmt: skip
    """Register the reference frame (or load it when resuming): ``(mid, valid, model,
    camera)``, the mid base image, its mask, the reference frame's model as recorded and the
    camera every frame is registered with (``camera`` with the lens beyond Harris that the
    reference frame's registration found, :func:`registration.global_registration.lens_refit.register_with_lens`)."""
    out_dir = writer.out_dir
    frame, problem = read_frame(frames, ref)
    if frame is None:
        raise ReferenceFrameUnusable(problem, ref)
    wb, hb = image_size(base)
    if writer.done(ref):
        rec = RegistrationResult(out_dir)
        if not rec.is_ok(ref):
            raise RegistrationFailed(
                f"the reference frame {ref} failed before: {rec.records[ref].reason}", ref
            )
        # Resuming: the mid base image is rendered again from the record, exactly as the
        # uninterrupted run rendered it (each chunk adds its own anchors, run_chunk).
        camera = camera.with_k2(rec.camera.k2)
        mid, valid = render_to_base(
            frame, camera, rec.own_model(ref), (0, 0, wb, hb), rec.field(ref)
        )
        if writer.read_mid_base() is None:
            writer.write_mid_base(mid, valid)
        return mid, valid, rec.records[ref].model, camera

    t0 = time.perf_counter()
    if reference is not None:
        coarse, fine = reference
    else:
        coarse = coarse_register(frame, base, camera, seed, config.coarse, match_in=config.match_in,
                                 base_valid=base_valid, rng=config.random_seed + ref)  # fmt: skip
        if coarse:
            fine = fine_register_reference(
                frame, base, camera, coarse, config.fine, match_in=config.match_in,
                base_valid=base_valid,
            )  # fmt: skip
        else:
            fine = FineResult.failed(coarse.reason)
    times = {"coarse": coarse.time_s, "fine": fine.time_s}
    lens = None
    if fine and config.lens.estimate_k2:
        t1 = time.perf_counter()
        camera, fine, lens = register_with_lens(
            frame, base, camera, coarse, fine, config.fine, config.lens,
            match_in=config.match_in, base_valid=base_valid,
        )  # fmt: skip
        times["lens"] = time.perf_counter() - t1
    times["total"] = time.perf_counter() - t0
    if not fine:
        writer.write_frame(ref, FrameRecord.failed(fine.reason))
        raise RegistrationFailed(
            f"the reference frame {ref} could not be registered to the base map: {fine.reason}",
            ref,
            remedy="" if coarse else coarse.remedy,
        )
    model = fine.base_from_corrected
    field_, field_stats = None, None
    config = _at_base_resolution(config, camera, model)
    if config.run_local and config.reference_local is not None:
        field_, field_stats = reference_field(
            fine, (wb, hb), config.reference_local, footprint(camera, model)
        )
    # The mid base image is the reference frame registered with its own field: every other
    # frame's local stage aligns to it, so its accuracy is theirs.
    mid, valid = render_to_base(frame, camera, model, (0, 0, wb, hb), field_)
    writer.write_mid_base(mid, valid)
    stats = _stats(coarse, fine, times, field_stats)
    if lens is not None:
        stats["lens"] = lens.to_dict()
    record = FrameRecord(
        "ok", stage="inter-sensor", stats=stats, model=model.to_dict(), lens_k2=camera.k2
    )
    writer.write_frame(ref, record, _frame_arrays(fine, field_, field_stats))
    return mid, valid, record.model, camera


def _at_base_resolution(config: PipelineConfig, camera: Camera, model) -> PipelineConfig:
    """``config`` with the local stage and the reference frame's and anchors' own field set for
    the base map's resolution (:meth:`registration.local.config.LocalConfig.for_base_scale` at the
    reference frame's scale, base px per frame px at its centre under ``model``, its
    ``base_from_corrected``). Derived from the recorded model, so a resumed run or a Dask
    worker uses the same settings. The reference frame's and anchors' own field takes the
    settings for ``camera``'s lens (:meth:`PipelineConfig.reference_local_for`), resolved here
    once: ``reference_local_beyond_harris`` is then None."""
    scale = scale_at_frame_centre(model, camera.corrected_from_raw, camera.width, camera.height)
    changes = {"local": config.local.for_base_scale(scale)}
    reference_local = config.reference_local_for(camera.k2)
    if reference_local is not None:
        changes["reference_local"] = reference_local.for_base_scale(scale)
    if config.reference_local_beyond_harris is not None:
        changes["reference_local_beyond_harris"] = None
    if all(getattr(config, k) is v for k, v in changes.items()):
        return config
    return dataclasses.replace(config, **changes)


def _write_mosaic(writer: ResultWriter, ctx: ChunkContext) -> None:
    """Write ``mid_base.png`` as the reference frame plus every anchor where it is still empty,
    in processing order (what a single chain's mid base image ends as; each chunk registered
    against the reference frame and its own anchors only). Written once the run is complete,
    so that it does not depend on the order in which chunks finished."""
    if ctx.config.intra.reanchor_coverage <= 0:
        return
    result = RegistrationResult(writer.out_dir)
    order = processing_order(result.n_frames, ctx.reference_frame)[1:]
    anchors = [k for k in order if result.is_ok(k) and result.records[k].stage == ANCHOR_STAGE]
    if not anchors:
        return
    joint = make_joint_base(ctx.mid.copy(), ctx.mid_valid.copy())
    hb, wb = joint.mid_valid.shape
    for k in anchors:
        if anchor_box(ctx.camera, result.own_model(k), (wb, hb)) is None:
            continue  # the frame is not read: its box needs only the camera and model
        # As the run filled it: only the anchor's pixels within its fill radius.
        render_anchor(
            joint, ctx.frames.get(k), ctx.camera, result.own_model(k), result.field(k),
            ctx.config.intra.anchor_fill_radius,
        )  # fmt: skip
    writer.write_mid_base(joint.mid_image, joint.mid_valid)


def load_config(out_dir: str | Path) -> PipelineConfig:
    """The configuration a result folder was made with."""
    meta = json.loads((Path(out_dir) / "result.json").read_text())
    return config_from_dict(meta["config"])
