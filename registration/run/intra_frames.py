"""Registering the intra-sensor frames of one chunk (paper 4.4 and 5): each frame's global stage
against the joint base, then its local field, the frame's record written as soon as it is done;
re-anchoring where a frame leaves the mid base image (:mod:`registration.run.anchoring`). The
order and chunks are planned in :mod:`registration.run.chunks`.

Processing order: the reference frame, then the frames after it in order, then the frames before
it backwards, so that the "previous" frame (paper 4.4) is always the registered neighbour nearer
to the reference.

The frames after the reference frame, and those before it, are split into chunks of consecutive
frames (:func:`chunk_plan`, ``PipelineConfig.chunk_frames``). A chunk is registered from the
reference frame's mid base image and its own anchors only (:mod:`registration.run.anchoring`), so
chunks are independent: :mod:`registration.run.pipeline` runs them one after the other, or on a Dask
cluster (:mod:`registration.run.dask_executor`), with the same result.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.coords import image_size
from registration.geometry import model_from_dict
from registration.global_registration import (
    FineResult,
    JointBase,
    coarse_register,
    previous_frame_state,
    register_anchor,
    register_intra,
)
from registration.io import FrameSource
from registration.lens import Camera
from registration.local import LocalConfig, frame_field
from registration.run.anchoring import Anchoring, render_anchor
from registration.run.chunk_links import ChunkLinks, linked_done_frames
from registration.run.chunks import (
    Chunk,
    ChunkContext,
    ChunkJob,
    FrameOutput,
    previous_in_order,
)
from registration.run.config import PipelineConfig
from registration.run.prefetch import FramesAhead, LocalAhead
from registration.run.records import FrameRecord
from registration.run.records import frame_arrays as _frame_arrays
from registration.run.records import frame_stats as _stats

# Local stages that may run at once while the main thread goes on with the next frames' global
# stages. With one, the default preset's local stage (the longer of the two at 2560x1920) paced
# the run and the main thread waited for it; with two, and the main thread no longer waiting for
# the previous local stage before the next global one, whichever core is free takes the next
# piece of work (2560x1920 flight, H.264, medians of alternated runs: README, "Registration
# speed"; together with the DIS patch stride of config.LOCAL_FLOW).
LOCAL_WORKERS = 2


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

    With ``context.overlap`` both cores are kept busy (:mod:`registration.run.prefetch`): the next
    frames are decoded ahead, and a frame's local stage runs in the background while the next
    frames' global stages run (the next frame needs only its global model), up to
    ``LOCAL_WORKERS`` local stages at once. Frames are yielded in order as their local stages
    finish. The local stage reads nothing that the global stage changes, and whatever changes
    the joint base (an anchor) waits for the local stages in flight, so the result is the
    serial one to the bit (:func:`_overlapping`)."""
    todo = [k for k in job.chunk.frames if k not in job.done]
    links = _chunk_links(context, job)
    with _overlapping(context, todo) as (frames, local):
        for k, record, arrays, frame in _chunk_frames(context, job, frames, local):
            if links is not None and record.ok:
                # This thread's CPU (the local stages run in others): the adjustment's share
                # of the registration, as the benchmarks report it.
                t0 = time.thread_time()
                arrays = {**(arrays or {}), **links.add(k, frame, record.model)}
                links_cpu = round(time.thread_time() - t0, 4)
                record = record.with_stats(
                    time_s={**record.stats.get("time_s", {}), "links_cpu": links_cpu}
                )
            yield k, record, arrays


def _chunk_links(ctx: ChunkContext, job: ChunkJob) -> ChunkLinks | None:
    """The links the chunk's frames measure as they are registered, for the sequence
    adjustment (None without it), with the frames they link to that the chunk does not
    register (the reference frame for a chunk that follows it; those a resumed chunk has) read
    again (:mod:`registration.run.chunk_links`)."""
    adjust = ctx.config.adjust
    if adjust is None:
        return None
    links = ChunkLinks(adjust, ctx.camera.lens, tuple(ctx.frames.size))
    ref = ctx.reference_frame
    if job.chunk.follows_reference and any(abs(k - ref) in adjust.link_steps for k in job.todo):
        links.remember(ref, ctx.frames.get(ref), ctx.reference_model)
    for k in linked_done_frames(job.chunk.frames, job.done, adjust.link_steps):
        links.remember(k, ctx.frames.get(k), job.done[k].model)
    return links


@contextmanager
def _overlapping(ctx: ChunkContext, todo: list[int]):
    """``(frames, local)`` for a chunk's frames ``todo``: with ``ctx.overlap`` the frames decoded
    ahead (:class:`FramesAhead`) and local stages run by up to ``LOCAL_WORKERS`` threads
    (:class:`LocalAhead`), else the frame source itself and local stages run at once.

    OpenCV's own threads (results do not depend on their number) are held to one meanwhile
    while both stages are heavy (template control points: the main thread and the local
    workers keep both cores busy, more threads only contend), and left alone when the global
    stage measures the frame's flow (``IntraConfig.control_points == "flow"``): it is then the
    longer of the two, and its OpenCV calls use the core the light local stage leaves idle
    (measured with one local worker, 2560x1920 flight, H.264, median of 4 alternated runs:
    0.274 s per frame held to one thread, 0.225 s not)."""
    frames = FramesAhead(ctx.frames, todo) if ctx.overlap and len(todo) > 1 else ctx.frames
    local = LocalAhead(enabled=ctx.overlap, workers=LOCAL_WORKERS)
    cv_threads = cv2.getNumThreads()
    hold_cv_threads = ctx.overlap and ctx.config.intra.control_points != "flow"
    if hold_cv_threads:
        cv2.setNumThreads(1)
    try:
        yield frames, local
    finally:
        local.close()
        if frames is not ctx.frames:
            frames.close()
        if hold_cv_threads:
            cv2.setNumThreads(cv_threads)


def _chunk_frames(ctx: ChunkContext, job: ChunkJob, frames, local) -> Iterator[tuple]:
    """The frames of ``job`` registered in order (:func:`run_chunk`), as ``(k, record, arrays,
    frame)`` (``frame``: the raw image, None where it could not be read): read from
    ``frames``, their local stages run by ``local``; done frames replayed from their records."""
    cfg = ctx.config
    local_cfg = _local_config(cfg)
    joint = ctx.joint_base()
    anchoring = Anchoring(ctx, joint)
    models: dict[int, object] = {}  # registered frames of this chunk (None: failed)
    # Frames whose local stage runs (or waits for a worker), oldest first.
    pending: list[tuple[int, _Global, NDArray]] = []

    def finish_pending(keep: int = 0) -> Iterator[FrameOutput]:
        """Yield the pending frames in order: those done, then more until ``keep`` are left."""
        while pending and (len(pending) > keep or local.done(pending[0][0])):
            k, glob, frame = pending.pop(0)
            yield k, *glob.finish(*local.result(k))[:2], frame

    for k in job.chunk.frames:
        done = job.done.get(k)
        if done is not None:
            models[k] = model_from_dict(done.model) if done.ok else None
            if done.ok and done.anchor and cfg.intra.reanchor_coverage > 0:
                yield from finish_pending()
                frame = ctx.frames.get(k)
                render_anchor(
                    joint, frame, ctx.camera, models[k], done.field,
                    cfg.intra.anchor_fill_radius,
                )  # fmt: skip
            continue
        t_read = time.perf_counter()
        frame, problem = read_frame(frames, k)
        t_read = time.perf_counter() - t_read
        if frame is None:
            # Unreadable or of another size: marked failed, the chunk goes on (the next
            # frame takes the last good one as its previous frame).
            models[k] = None
            yield from finish_pending()
            yield k, FrameRecord.failed(problem), None, None
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
                pending.append((k, glob, frame))
                # Overlapped, the next global stage starts while up to LOCAL_WORKERS local
                # stages run; serial, the frame is done already and written at once.
                yield from finish_pending(keep=LOCAL_WORKERS if ctx.overlap else 0)
                continue
            yield from finish_pending()
            field_out = _local_stage(frame, ctx.camera, glob, joint, local_cfg)
            record, arrays, state = glob.finish(*field_out)
            record, arrays, state, _ = anchoring.maybe(frame, k, record, arrays, state)
        models[k] = state.base_from_corrected if state is not None else None
        if state is not None:
            joint.previous, joint.previous_index = state, k
        times = record.stats.get("time_s")
        if times is not None and "read" not in times:
            record = record.with_stats(time_s={**times, "read": round(t_read, 4)})
        yield k, record, arrays, frame
    yield from finish_pending()


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
        record = record.with_stats(chunk_start="anchored" if anchored else "mid base image")
        if confirmed:
            return record, arrays, state
    first_reason = record.reason or record.stats.get("anchor", "")
    t0 = time.perf_counter()
    cfg = ctx.config
    coarse = coarse_register(frame, ctx.base, ctx.camera, None, cfg.coarse, match_in=cfg.match_in,
                             base_features=ctx.coarse_base(), rng=cfg.random_seed + k)  # fmt: skip
    if coarse:
        fine = register_anchor(frame, ctx.base, ctx.camera, coarse.base_from_corrected, cfg.fine,
                               match_in=cfg.match_in, base_valid=ctx.base_valid)  # fmt: skip
    else:
        fine = FineResult.failed(coarse.reason)
    if not fine:
        if state is not None:  # the intra-sensor result stands, unconfirmed (as in a chain)
            return (
                record.with_stats(chunk_start=f"unconfirmed: base map: {fine.reason}"),
                arrays,
                state,
            )
        reason = f"no predecessor: mid base image: {first_reason}; base map: {fine.reason}"
        return FrameRecord.failed(reason), None, None
    times = {"coarse": coarse.time_s, "fine": fine.time_s}
    record, arrays, state = anchoring.anchor(frame, fine, coarse, times, t0)
    return record.with_stats(chunk_start="base map"), arrays, state


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


# --------------------------------------------------------------------------------------------
# One intra-sensor frame: global stage, then local stage


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
        record = FrameRecord(
            "ok",
            stage="intra-sensor",
            stats=_stats(self.coarse, self.fine, times, field_stats),
            model=self.fine.base_from_corrected.to_dict(),
        )
        return record, _frame_arrays(self.fine, field, field_stats), self.state


def _register_global(frame, k, camera: Camera, joint: JointBase, config: PipelineConfig) -> _Global:
    t0 = time.perf_counter()
    try:
        coarse, fine, state = register_intra(
            frame, camera, joint, config.intra, config.coarse, degree=config.fine.degree,
            match_in=config.match_in, rng=config.random_seed + k, flow_cfg=config.local,
        )  # fmt: skip
    except np.linalg.LinAlgError as exc:
        reason = f"degenerate fit: {exc}"
        return _Global(FrameRecord.failed(reason))
    times = {"coarse": coarse.time_s, "fine": fine.time_s}
    if not fine:
        stats = _stats(coarse, fine, times) if coarse else {"time_s": times}
        record = FrameRecord.failed(fine.reason, stats)
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
    view = glob.state.view
    raw = view.lens is not None
    # The global stage's grey raw frame, when it matched in the raw frame (no second conversion),
    # and its flow against the mid base image, when its control points came from one in raw px.
    image = view.grey if raw else frame
    flow = glob.fine.flow if raw and cfg.method == "flow" else None
    model = glob.fine.base_from_corrected
    field_, field_stats = frame_field(image, camera, model, joint, cfg, flow=flow)
    return field_, field_stats, time.perf_counter() - t1


def _register_one(frame, k, camera: Camera, joint: JointBase, config: PipelineConfig):
    """``(record, arrays, state)`` of an intra-sensor frame: global then local stage."""
    glob = _register_global(frame, k, camera, joint, config)
    return glob.finish(*_local_stage(frame, camera, glob, joint, _local_config(config)))
