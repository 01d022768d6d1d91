"""A whole sequence: the reference frame to the base map, every other frame to the joint base,
then the local field, written frame by frame and atomically into a result folder so that an
interrupted run resumes without redoing finished frames (paper Fig. 3).

Processing order: the reference frame, then the frames after it in order, then the frames before
it backwards, so that the "previous" frame (paper 4.4) is always the registered neighbour nearer
to the reference.

Chunks (``PipelineConfig.chunk_frames``, beyond the paper): the frames after the reference frame,
and those before it, are split into chunks of consecutive frames (:func:`chunk_plan`). A chunk
is registered from the reference frame's mid base image and its own anchors only, so chunks are
independent: they run one after the other here, or in parallel on a Dask cluster
(:mod:`registration.distributed`) with the same result. The process that calls
:func:`register_sequence` registers the reference frame and writes every frame's record.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from registration import features
from registration.camera import Camera
from registration.coarse import CoarseBase, normalise_seeds
from registration.config import PipelineConfig, config_from_dict
from registration.coords import bbox_of, image_size
from registration.distortion import check_harris_gamma
from registration.global_registration import (
    CoarseResult,
    FineResult,
    IntraConfig,
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
from registration.local import DisplacementField, LocalConfig, frame_field, reference_field
from registration.models import model_from_dict
from registration.overlap import FramesAhead, LocalAhead
from registration.render import render_to_base
from registration.result import MID_BASE, RegistrationResult, ResultWriter, make_metadata
from registration.result import frame_arrays as _frame_arrays
from registration.result import frame_stats as _stats

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]
# What a chunk gives for each frame: ``(k, record, arrays)``, as ResultWriter.write_frame takes.
FrameOutput = tuple[int, dict, "dict[str, NDArray] | None"]


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


# --------------------------------------------------------------------------------------------
# Chunks


@dataclass(frozen=True)
class Chunk:
    """Consecutive frames in processing order, registered together (``PipelineConfig
    .chunk_frames``).

    Attributes:
        index: the chunk's place in :func:`chunk_plan`.
        frames: the frames, in processing order.
        follows_reference: the first frame's predecessor is the reference frame; otherwise the
            first frame has no registered predecessor and is registered to the mid base image
            alone or, where that fails, to the base map (a chunk start, :func:`run_chunk`).
    """

    index: int
    frames: tuple[int, ...]
    follows_reference: bool


def chunk_plan(n_frames: int, reference_frame: int, chunk_frames: int) -> list[Chunk]:
    """The chunks of a sequence: the frames after the reference frame (forwards) and those
    before it (backwards from it), each split into runs of at most ``chunk_frames`` consecutive
    frames of (nearly) equal length, the longer ones first; ``chunk_frames`` 0 gives one chunk
    of every frame but the reference, in processing order (the paper's single chain)."""
    forwards = list(range(reference_frame + 1, n_frames))
    backwards = list(range(reference_frame - 1, -1, -1))
    if chunk_frames <= 0:
        rest = forwards + backwards
        return [Chunk(0, tuple(rest), True)] if rest else []
    chunks: list[Chunk] = []
    for run in (forwards, backwards):
        n_chunks = math.ceil(len(run) / chunk_frames)
        start = 0
        for i in range(n_chunks):
            size = len(run) // n_chunks + (i < len(run) % n_chunks)
            chunks.append(Chunk(len(chunks), tuple(run[start : start + size]), start == 0))
            start += size
    return chunks


@dataclass
class DoneFrame:
    """A frame of a chunk that a resumed run already has: what the chunk needs to carry on as
    the uninterrupted run did (its model for the next frame, an anchor's field to add it to the
    chunk's mid base image)."""

    ok: bool
    anchor: bool = False
    model: dict | None = None
    field: DisplacementField | None = None


@dataclass
class ChunkJob:
    """A chunk to register: its frames, less those in ``done`` (already written)."""

    chunk: Chunk
    done: dict[int, DoneFrame] = field(default_factory=dict)

    @property
    def todo(self) -> list[int]:
        return [k for k in self.chunk.frames if k not in self.done]


@dataclass
class ChunkContext:
    """What every chunk of a run shares (built once by the driver; pickled to Dask workers).

    Attributes:
        frames: the sequence (paths: a worker reads the frames itself).
        base: base map, BGR uint8 (Hb, Wb, 3); base_valid: (Hb, Wb) bool or None.
        camera: the frames' camera (Harris γ and frame size).
        config: the run's configuration.
        reference_frame: the reference frame's index; reference_model: its model as recorded.
        mid, mid_valid: the mid base image (the reference frame in base pixels) and its mask.
        frames_identity: the frames' identity as the driver recorded it (``result.json``
            ``inputs.frames``); a worker checks that it reads the same files.
        overlap: keep both cores busy within a chunk (frames decoded ahead, the local stage
            in a second thread; :func:`run_chunk`). Off by default: see ``register_sequence``.
    """

    frames: FrameSource
    base: NDArray
    base_valid: NDArray | None
    camera: Camera
    config: PipelineConfig
    reference_frame: int
    reference_model: dict
    mid: NDArray
    mid_valid: NDArray
    frames_identity: dict | None = None
    overlap: bool = False
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_cache"] = {}  # per process
        return state

    def coarse_base(self) -> CoarseBase:
        """The base map's coarse features, computed once per process (chunk starts)."""
        if "coarse_base" not in self._cache:
            self._cache["coarse_base"] = CoarseBase(self.base, self.config.coarse, self.base_valid)
        return self._cache["coarse_base"]

    def joint_base(self) -> JointBase:
        """A fresh joint base: the reference frame's mid base image, no anchors yet."""
        return _joint_base(self.mid.copy(), self.mid_valid.copy(), self.base, self.base_valid,
                           self.config.intra)  # fmt: skip


class ChunkExecutor(Protocol):
    """Runs chunk jobs and yields each frame's output as it is ready, in any order. Closing the
    iterator, or setting ``cancel``, stops the work still running."""

    def run(
        self,
        context: ChunkContext,
        jobs: Sequence[ChunkJob],
        cancel: threading.Event | None = None,
    ) -> Iterator[FrameOutput]: ...


class SerialExecutor:
    """The chunks one after the other in this process (a frame is computed when the caller
    asks for it, so the caller's cancel check between frames is enough)."""

    def run(self, context, jobs, cancel=None) -> Iterator[FrameOutput]:
        for job in jobs:
            yield from run_chunk(context, job)


def run_chunk(context: ChunkContext, job: ChunkJob) -> Iterator[FrameOutput]:
    """Register the frames of ``job`` not yet done, in order, yielding ``(k, record, arrays)``
    for each. Within a chunk, frames chain as in the paper: each is registered against the mid
    base image (plus the chunk's anchors) and its predecessor, the nearest registered frame
    towards the reference frame; a frame without one in the chunk (a chunk start) is registered
    by :func:`_register_start`. Frames already done are replayed from their records, so that
    the frames after them see exactly what the uninterrupted run saw.

    With ``context.overlap`` both cores are kept busy (:mod:`registration.overlap`): the next
    frames are decoded ahead, and a frame's local stage runs in a second thread while the next
    frame's global stage runs (the next frame needs only its global model). The local stage
    reads nothing that the global stage changes, and whatever changes the joint base (an
    anchor) waits for the local stage in flight, yet the two threads together now and then
    change a fit in its last bits (see ``register_sequence``: off by default)."""
    ctx, cfg = context, context.config
    local_cfg = _local_config(cfg)
    joint = ctx.joint_base()
    anchoring = _Anchoring(ctx, joint)
    models: dict[int, object] = {}  # registered frames of this chunk (None: failed)
    todo = [k for k in job.chunk.frames if k not in job.done]
    frames = FramesAhead(ctx.frames, todo) if ctx.overlap and len(todo) > 1 else ctx.frames
    local = LocalAhead(enabled=ctx.overlap)
    pending: list[tuple[int, _Global, NDArray]] = []  # at most one frame, its local stage running

    def finish_pending() -> Iterator[FrameOutput]:
        while pending:
            k, glob, frame = pending.pop(0)
            yield k, *glob.finish(*local.result(k))[:2]

    try:
        for k in job.chunk.frames:
            done = job.done.get(k)
            if done is not None:
                models[k] = model_from_dict(done.model) if done.ok else None
                if done.ok and done.anchor and cfg.intra.reanchor_coverage > 0:
                    yield from finish_pending()
                    frame = ctx.frames.get(k)
                    _render_anchor(joint, frame, ctx.camera, models[k], done.field)
                continue
            t_read = time.perf_counter()
            frame, problem = read_frame(frames, k)
            t_read = time.perf_counter() - t_read
            if frame is None:
                # Unreadable or of another size: marked failed, the chunk goes on (the next
                # frame takes the last good one as its previous frame).
                models[k] = None
                yield from finish_pending()
                yield k, _failed_record(problem), None
                continue
            prev = _predecessor(k, job.chunk, models, ctx.reference_frame)
            _set_previous(joint, ctx, prev, models)
            glob = None
            if prev is None:
                yield from finish_pending()
                record, arrays, state = _register_start(frame, k, ctx, joint, anchoring)
            else:
                glob = _register_global(frame, k, ctx.camera, joint, cfg)
                glob.times["read"] = t_read
                if glob.ok and cfg.run_local and not anchoring.wanted(frame, glob.state):
                    # The local stage in the background; the frame is yielded when it is done.
                    local.submit(k, _local_stage, frame, ctx.camera, glob, joint, local_cfg)
                    models[k] = glob.state.base_from_corrected
                    joint.previous, joint.previous_index = glob.state, k
                    yield from finish_pending()
                    pending.append((k, glob, frame))
                    if not ctx.overlap:  # done already: written before the next frame starts
                        yield from finish_pending()
                    continue
                yield from finish_pending()
                field_out = _local_stage(frame, ctx.camera, glob, joint, local_cfg)
                record, arrays, state = glob.finish(*field_out)
                record, arrays, state, _ = anchoring.maybe(frame, k, record, arrays, state)
            models[k] = state.base_from_corrected if state is not None else None
            if state is not None:
                joint.previous, joint.previous_index = state, k
            if "time_s" in record.get("stats", {}):
                record["stats"]["time_s"].setdefault("read", round(t_read, 4))
            yield k, record, arrays
        yield from finish_pending()
    finally:
        local.close()
        if frames is not ctx.frames:
            frames.close()


def _predecessor(k: int, chunk: Chunk, models: dict, ref: int) -> int | None:
    """The frame ``k`` chains from: the nearest registered frame of the chunk towards the
    reference frame, the reference frame itself for a chunk that follows it, else None."""
    members = set(chunk.frames)
    p = previous_in_order(k, ref)
    while p != ref:
        if p not in members:
            return None
        if models.get(p) is not None:
            return p
        p = previous_in_order(p, ref)
    return ref if chunk.follows_reference else None


def _set_previous(joint: JointBase, ctx: ChunkContext, prev: int | None, models: dict) -> None:
    """Make ``joint.previous`` frame ``prev`` (None: no previous frame)."""
    if joint.previous_index == prev:
        return
    if prev is None:
        joint.previous = joint.previous_index = None
        return
    model = model_from_dict(ctx.reference_model) if prev == ctx.reference_frame else models[prev]
    joint.previous = previous_frame_state(
        ctx.frames.get(prev), ctx.camera, model, ctx.config.intra, match_in=ctx.config.match_in
    )
    joint.previous_index = prev


def _register_start(frame, k: int, ctx: ChunkContext, joint: JointBase, anchoring):
    """A frame without a registered predecessor (the first of a chunk that does not follow the
    reference frame): registered intra-sensor against the joint base alone (the coarse step
    matches the whole mid base image, no prediction gate), re-anchored as any frame when it lies
    little on the mid base image. Where that fails, or the frame lies little on the mid base
    image and its anchor does not confirm the intra-sensor model, it is registered to the base
    map as the reference frame is, without a seed (coarse step at any heading and scale, then
    the fine step), and becomes an anchor."""
    record, arrays, state = _register_one(frame, k, ctx.camera, joint, ctx.config)
    confirmed = False
    if state is not None:
        record, arrays, state, anchored = anchoring.maybe(frame, k, record, arrays, state)
        confirmed = anchored is not False
        record.setdefault("stats", {})["chunk_start"] = "anchored" if anchored else "mid base image"
        if confirmed:
            return record, arrays, state
    first_reason = record.get("reason") or record.get("stats", {}).get("anchor", "")
    t0 = time.perf_counter()
    cfg = ctx.config
    coarse = coarse_register(frame, ctx.base, ctx.camera, None, cfg.coarse, match_in=cfg.match_in,
                             base_features=ctx.coarse_base(), rng=cfg.random_seed + k)  # fmt: skip
    if coarse:
        fine = register_anchor(frame, ctx.base, ctx.camera, coarse.base_from_corrected, cfg.fine,
                               match_in=cfg.match_in, base_valid=ctx.base_valid)  # fmt: skip
    else:
        fine = FineResult(False, coarse.reason, None, *_empty_points())
    if not fine:
        if state is not None:  # the intra-sensor result stands, unconfirmed (as in a chain)
            record["stats"]["chunk_start"] = f"unconfirmed: base map: {fine.reason}"
            return record, arrays, state
        reason = f"no predecessor: mid base image: {first_reason}; base map: {fine.reason}"
        return _failed_record(reason), None, None
    times = {"coarse": coarse.time_s, "fine": fine.time_s}
    record, arrays, state = anchoring.anchor(frame, fine, coarse, times, t0)
    record["stats"]["chunk_start"] = "base map"
    return record, arrays, state


# --------------------------------------------------------------------------------------------
# The run


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
    overlap: bool = False,
) -> RegistrationResult:
    """Register every frame of ``frames`` to ``base`` and write the result folder ``out_dir``.

    Args:
        frames: the sequence (:func:`registration.io.open_frames`).
        base: base map, BGR uint8 (Hb, Wb, 3).
        gamma: Harris γ of the frames.
        config: pipeline configuration (:mod:`registration.config`); ``config.chunk_frames``
            splits the sequence into independent chunks (:func:`chunk_plan`).
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
        executor: where the chunks run (:class:`SerialExecutor` when None;
            :class:`registration.distributed.DaskExecutor` on a Dask cluster). The result does
            not depend on it; this process writes every frame as its output arrives.
        overlap: decode frames ahead and run each frame's local stage in a second thread
            while the next frame's global stage runs (:func:`run_chunk`). Opt-in: on a loaded
            machine the two threads now and then change a fit in its last bits (measured: 3
            runs in 4, a later frame's corner moved by up to 2 px through REQCON), so runs
            with it are not bit-reproducible; without it they are.

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
        n_done = sum(writer.done(k) for k in range(n))
        if progress:
            progress(n_done, n)
        mid_missing = not (out_dir / MID_BASE).is_file()
        camera = Camera(gamma, *frames.size)
        mid, valid, model = _reference_step(
            frames, base, camera, seed, reference_frame, config, writer, reference, base_valid
        )
        n_done = sum(writer.done(k) for k in range(n))
        if progress:
            progress(n_done, n)
        context = ChunkContext(
            frames, base, base_valid, camera, config, reference_frame, model, mid, valid,
            meta["inputs"]["frames"], overlap,
        )  # fmt: skip
        jobs = chunk_jobs(writer, n, reference_frame, config)
        cancelled = cancel is not None and cancel.is_set()
        if jobs and not cancelled:
            outputs = (executor or SerialExecutor()).run(context, jobs, cancel)
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
        if n_done == n and (jobs or mid_missing):
            _write_mosaic(writer, context)
    return RegistrationResult(out_dir)


def chunk_jobs(writer: ResultWriter, n_frames: int, ref: int, config) -> list[ChunkJob]:
    """The chunks of :func:`chunk_plan` that have frames left to do, each with what it needs of
    the frames already done (a resumed run)."""
    result = None
    jobs = []
    for chunk in chunk_plan(n_frames, ref, config.chunk_frames):
        done_ks = [k for k in chunk.frames if writer.done(k)]
        if len(done_ks) == len(chunk.frames):
            continue
        done = {}
        if done_ks:
            result = result or RegistrationResult(writer.out_dir)
            for k in done_ks:
                rec = result.records[k]
                ok = rec.get("status") == "ok"
                anchor = ok and rec.get("stage") == ANCHOR_STAGE
                done[k] = DoneFrame(
                    ok,
                    anchor,
                    rec.get("model") if ok else None,
                    result.field(k) if anchor else None,
                )
        jobs.append(ChunkJob(chunk, done))
    return jobs


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
    frames, base, camera: Camera, seed, ref, config: PipelineConfig, writer, reference,
    base_valid=None,
) -> tuple[NDArray, NDArray, dict]:  # fmt: skip
    """Register the reference frame (or load it when resuming): ``(mid, valid, model)``, the mid
    base image, its mask and the reference frame's model as recorded."""
    out_dir = writer.out_dir
    frame, problem = read_frame(frames, ref)
    if frame is None:
        raise ValueError(f"{problem}; choose another --reference-frame")
    wb, hb = image_size(base)
    if writer.done(ref):
        rec = RegistrationResult(out_dir)
        if not rec.is_ok(ref):
            raise RegistrationFailed(
                f"the reference frame {ref} failed before: {rec.records[ref].get('reason')}"
            )
        # Resuming: the mid base image is rendered again from the record, exactly as the
        # uninterrupted run rendered it (each chunk adds its own anchors, run_chunk).
        mid, valid = render_to_base(frame, camera, rec.model(ref), (0, 0, wb, hb), rec.field(ref))
        if writer.read_mid_base() is None:
            writer.write_mid_base(mid, valid)
        return mid, valid, rec.records[ref]["model"]

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
            fine = FineResult(False, coarse.reason, None, *_empty_points())
    times = {"coarse": coarse.time_s, "fine": fine.time_s, "total": time.perf_counter() - t0}
    if not fine:
        writer.write_frame(ref, _failed_record(fine.reason))
        raise RegistrationFailed(
            f"the reference frame {ref} could not be registered to the base map: {fine.reason}"
        )
    model = fine.base_from_corrected
    field_, field_stats = None, None
    if config.run_local and config.reference_local is not None:
        field_, field_stats = reference_field(
            fine, (wb, hb), config.reference_local, _footprint(camera, model)
        )
    # The mid base image is the reference frame registered with its own field: every other
    # frame's local stage aligns to it, so its accuracy is theirs.
    mid, valid = render_to_base(frame, camera, model, (0, 0, wb, hb), field_)
    writer.write_mid_base(mid, valid)
    record = {
        "status": "ok",
        "reason": "",
        "stage": "inter-sensor",
        "stats": _stats(coarse, fine, times, field_stats),
        "model": model.to_dict(),
    }
    writer.write_frame(ref, record, _frame_arrays(fine, field_, field_stats))
    return mid, valid, record["model"]


def _joint_base(mid, valid, base, base_valid, intra: IntraConfig) -> JointBase:
    joint = make_joint_base(mid, valid)
    if intra.base_fallback:
        joint.base_grey = features.to_grey(base)
        joint.base_valid = base_valid
    return joint


def _write_mosaic(writer: ResultWriter, ctx: ChunkContext) -> None:
    """Write ``mid_base.png`` as the reference frame plus every anchor where it is still empty,
    in processing order (what a single chain's mid base image ends as; each chunk registered
    against the reference frame and its own anchors only). Written once the run is complete,
    so that it does not depend on the order in which chunks finished."""
    if ctx.config.intra.reanchor_coverage <= 0:
        return
    result = RegistrationResult(writer.out_dir)
    order = processing_order(result.n_frames, ctx.reference_frame)[1:]
    anchors = [
        k for k in order if result.is_ok(k) and result.records[k].get("stage") == ANCHOR_STAGE
    ]
    if not anchors:
        return
    mid, valid = ctx.mid.copy(), ctx.mid_valid.copy()
    hb, wb = valid.shape
    for k in anchors:
        box = _anchor_box(ctx.camera, result.model(k), (wb, hb))
        if box is None:
            continue  # the frame is not read: its box needs only the camera and model
        x0, y0, x1, y1 = box
        image, image_valid = render_to_base(
            ctx.frames.get(k), ctx.camera, result.model(k), box, result.field(k)
        )
        hole = np.asarray(image_valid, bool) & ~valid[y0:y1, x0:x1]
        mid[y0:y1, x0:x1][hole] = image[hole]
        valid[y0:y1, x0:x1] |= hole
    writer.write_mid_base(mid, valid)


ANCHOR_STAGE = "inter-sensor anchor"


def _anchor_box(camera: Camera, model, base_size) -> tuple[int, int, int, int] | None:
    """Base-pixel box a frame covers under ``model``, or None when it is empty."""
    box = bbox_of(_footprint(camera, model), base_size, 2)
    x0, y0, x1, y1 = box
    return None if x1 - x0 < 2 or y1 - y0 < 2 else box


def _footprint(camera: Camera, model) -> NDArray:
    """``(N, 2)`` base px of the frame's outline under ``model`` (``base_from_corrected``)."""
    return model.apply(camera.outline())


def _render_anchor(joint: JointBase, frame, camera: Camera, model, field_) -> None:
    """Add a re-anchored frame to the mid base image (where it is empty)."""
    hb, wb = joint.mid_valid.shape
    box = _anchor_box(camera, model, (wb, hb))
    if box is None:
        return
    image, valid = render_to_base(frame, camera, model, box, field_)
    add_to_mid_base(joint, image, valid, box)


class _Anchoring:
    """Re-anchoring of long flights (``IntraConfig.reanchor_coverage``, beyond the paper)."""

    def __init__(self, ctx: ChunkContext, joint: JointBase):
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
        stats = record.setdefault("stats", {})
        stats["mid_coverage"] = round(coverage, 3)
        if not fine:
            stats["anchor"] = f"not re-anchored: {fine.reason}"
            return record, arrays, state, False
        shift = _median_gap(fine.base_from_corrected, intra, self.camera)
        if not shift <= cfg.reanchor_max_shift_px:
            stats["anchor"] = f"not re-anchored: the map fit is {shift:.1f} px from the frame's"
            return record, arrays, state, False
        times = dict(stats.get("time_s", {}))
        record, arrays, state = self.anchor(frame, fine, _NoCoarse(), times, t0)
        record["stats"].update(mid_coverage=round(coverage, 3), anchor_shift_px=round(shift, 3))
        # How the intra-sensor step that the anchor confirmed found the frame.
        for key in ("coarse_path", "fast_path_reason"):
            if key in stats:
                record["stats"][key] = stats[key]
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
                _footprint(self.camera, model),
            )  # fmt: skip
        if self.config.intra.reanchor_coverage > 0:
            _render_anchor(self.joint, frame, self.camera, model, field_)
        times["anchor"] = round(time.perf_counter() - t0, 4)
        record = {"status": "ok", "reason": "", "stage": ANCHOR_STAGE,
                  "stats": _stats(coarse, fine, times, field_stats), "model": model.to_dict()}  # fmt: skip
        state = previous_frame_state(
            frame, self.camera, model, self.config.intra, match_in=self.config.match_in
        )
        return record, _frame_arrays(fine, field_, field_stats), state


class _NoCoarse:
    """Coarse counts of a frame that had no coarse step of its own (an anchor)."""

    n_keypoints_frame = n_keypoints_base = n_matches = n_inliers = 0
    gated = np.zeros(0, bool)
    model_kind = "none"
    heading_deg = None


def _median_gap(a, b, camera: Camera) -> float:
    """Median distance (base px) between two ``base_from_corrected`` models over the frame."""
    c = camera.grid(9, 7)
    d = np.hypot(*(a.apply(c) - b.apply(c)).T)
    return float(np.median(d)) if np.isfinite(d).any() else float("inf")


def _empty_points():
    z = np.zeros((0, 2))
    return z, z, np.zeros(0, bool), np.zeros(0), 0


class _Global:
    """A frame's global stage (coarse and fine, :func:`register_intra`) and what its record
    needs once the local stage is done (:meth:`finish`)."""

    def __init__(self, record=None, arrays=None, coarse=None, fine=None, state=None, times=None):
        self.record, self.arrays = record, arrays  # set when the global stage failed
        self.coarse, self.fine, self.state = coarse, fine, state
        self.times = times or {}

    @property
    def ok(self) -> bool:
        return self.record is None

    def finish(self, field=None, field_stats=None, local_s: float | None = None):
        """``(record, arrays, state)`` of the frame, with the local stage's field."""
        if not self.ok:
            return self.record, self.arrays, None
        times = dict(self.times)
        read = times.pop("read", None)
        if local_s is not None:
            times["local"] = local_s
        # Work done for the frame (its local stage may have overlapped the next frame's).
        times["total"] = times.pop("global") + times.get("local", 0.0)
        if read is not None:
            times["read"] = read
        record = {
            "status": "ok",
            "reason": "",
            "stage": "intra-sensor",
            "stats": _stats(self.coarse, self.fine, times, field_stats),
            "model": self.fine.base_from_corrected.to_dict(),
        }
        return record, _frame_arrays(self.fine, field, field_stats), self.state


def _register_global(frame, k, camera: Camera, joint: JointBase, config: PipelineConfig) -> _Global:
    t0 = time.perf_counter()
    try:
        coarse, fine, state = register_intra(
            frame, camera, joint, config.intra, config.coarse, degree=config.fine.degree,
            match_in=config.match_in, rng=config.random_seed + k,
        )  # fmt: skip
    except np.linalg.LinAlgError as exc:
        reason = f"degenerate fit: {exc}"
        return _Global({"status": "failed", "reason": reason, "stats": {}, "model": None})
    times = {"coarse": coarse.time_s, "fine": fine.time_s}
    if not fine:
        stats = _stats(coarse, fine, times) if coarse else {"time_s": times}
        record = {"status": "failed", "reason": fine.reason, "stats": stats, "model": None}
        return _Global(record, _frame_arrays(fine, None) if len(fine.src) else None)
    times["global"] = time.perf_counter() - t0
    return _Global(coarse=coarse, fine=fine, state=state, times=times)


def _local_config(config: PipelineConfig) -> LocalConfig | None:
    """The local stage's settings, None when it is off (``PipelineConfig.run_local``)."""
    return config.local if config.run_local else None


def _local_stage(frame, camera: Camera, glob: _Global, joint: JointBase, cfg: LocalConfig | None):
    """``(field, stats, seconds)`` of a frame registered by ``glob`` (no field when its global
    stage failed or the local stage is off: ``cfg`` None)."""
    if cfg is None or not glob.ok:
        return None, None, None
    t1 = time.perf_counter()
    field_, field_stats = frame_field(frame, camera, glob.fine.base_from_corrected, joint, cfg)
    return field_, field_stats, time.perf_counter() - t1


def _register_one(frame, k, camera: Camera, joint: JointBase, config: PipelineConfig):
    """``(record, arrays, state)`` of an intra-sensor frame: global then local stage."""
    glob = _register_global(frame, k, camera, joint, config)
    return glob.finish(*_local_stage(frame, camera, glob, joint, _local_config(config)))


def load_config(out_dir: str | Path) -> PipelineConfig:
    """The configuration a result folder was made with."""
    meta = json.loads((Path(out_dir) / "result.json").read_text())
    return config_from_dict(meta["config"])
