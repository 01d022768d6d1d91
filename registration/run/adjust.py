"""The sequence adjustment of a registered result folder (``PipelineConfig.adjust``; beyond the
paper): once every frame is registered, each frame's model is estimated again together with its
neighbours' (:mod:`registration.adjustment.sequence`), and its record rewritten, frame by frame
and atomically, with the adjusted model, a predicted error, a flag and the field that makes its
local stage consistent with its neighbours' (:mod:`registration.adjustment.fields`).
The frame's own model and field stay (``model``, ``field_*``): the folder says what each
frame's registration found and what the sequence made of it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from registration.adjustment import (
    ControlPointSet,
    FieldFrame,
    FrameAdjustment,
    SequenceAdjustConfig,
    SequenceEvidence,
    adjust_sequence,
    apply_map_points,
    as_polyprojective,
    links_from_arrays,
    measure_links,
    refined_grid,
    solve_corrections,
)
from registration.adjustment.sequence import probes_for
from registration.geometry import DisplacementField, local_frame_to_base, model_from_dict
from registration.matching import textured_probes, to_grey
from registration.run.map_points import read_map_points
from registration.run.result import RegistrationResult
from registration.run.result_folder import ResultLock
from registration.run.writer import ResultWriter

# Frames kept decoded: a window's links reach this far back at most.
_GREY_CACHE = 64
# Frames whose stored links are kept read (a pair's are with one of its two frames): a window
# and the frames before it it links to, so that each frame's file is read about once.
_LINKS_CACHE = 64


def adjust_folder(
    out_dir: str | Path,
    frames=None,
    progress: Callable[[int, int], None] | None = None,
    cancel: threading.Event | None = None,
) -> int:
    """Adjust the frames of the result folder ``out_dir`` that are not adjusted (after
    :func:`registration.run.set_map_points`, say), with the folder's own settings; ``frames``:
    the run's frame source (None: the one the folder records). Returns the number adjusted.

    Raises:
        ValueError: one line: the folder was made without the adjustment, frames are not
            registered yet (resume the run), or ``frames`` are not the run's; :class:`ResultBusy`
            while another process writes it.
    """
    from registration.io import check_result_frames, open_frames
    from registration.run.config import config_from_dict
    from registration.run.records import _read_meta

    out_dir = Path(out_dir)
    meta = _read_meta(out_dir)
    config = config_from_dict(meta["config"]).adjust
    if config is None:
        raise ValueError(f"{out_dir} was registered without the sequence adjustment (--adjust)")
    lock = ResultLock(out_dir).acquire()
    try:
        writer = ResultWriter(out_dir, lock, frames)
        pending = [k for k in range(writer.n_frames) if not writer.done(k)]
        if pending:
            raise ValueError(
                f"{out_dir}: {len(pending)} frames are not registered yet (first: {pending[0]}); "
                "resume the run (aerialreg register --resume) to register and adjust them"
            )
        if frames is None:
            frames = open_frames(meta["frames_source"])
            writer = ResultWriter(out_dir, lock, frames)
        # The frames the links are measured on must be the run's own (size, count, content).
        check_result_frames(frames, RegistrationResult(out_dir))
        return adjust_result(writer, frames, config, progress, cancel)
    finally:
        lock.release()


def adjust_result(
    writer: ResultWriter,
    frames,
    config: SequenceAdjustConfig,
    progress: Callable[[int, int], None] | None = None,
    cancel: threading.Event | None = None,
) -> int:
    """Adjust the frames of the folder ``writer`` holds that are not adjusted yet (all frames
    registered; ``frames`` the run's frame source); returns the number adjusted now.
    ``progress(done, total)`` counts adjusted frames of all ok frames; ``cancel`` stops between
    frames (the frames written so far stay; a resumed run goes on from them).

    BLAS runs on one thread here: the adjustment's products are small (a frame's 29 parameters),
    and OpenBLAS's threads cost more CPU than they save (the real flyover: 0.031 -> 0.0275 s of
    CPU per frame); the numbers do not then depend on the machine's core count either."""
    with threadpool_limits(limits=1, user_api="blas"):
        return _adjust_result(writer, frames, config, progress, cancel)


def _adjust_result(writer, frames, config, progress, cancel) -> int:
    result = RegistrationResult(writer.out_dir)
    n = result.n_frames
    evidence = _evidence(result, frames, config)
    final = {
        k: as_polyprojective(model_from_dict(result.records[k].adjusted_model), *result.frame_size)
        for k in range(n)
        if result.is_adjusted(k)
    }
    total = sum(m is not None for m in evidence.models)
    done = len(final)
    if progress and done < total:
        progress(done, total)
    written = 0
    fields = _Fields(result, evidence, config)
    for adjusted, _ in adjust_sequence(evidence, config, final):
        if cancel is not None and cancel.is_set():
            break
        _write_adjusted(writer, result, adjusted, fields.consistent(adjusted.k, adjusted.window))
        written += 1
        if progress:
            progress(done + written, total)
    return written


class _Fields:
    """Each frame's local stage made consistent with its neighbours' by the links
    (:func:`registration.adjustment.solve_corrections`), window by window as the models are:
    a window's frames are solved together with the frames before it held at their corrections
    as written (read back from the folder on a resumed run: the same float32 bits)."""

    def __init__(
        self, result: RegistrationResult, evidence: SequenceEvidence, config: SequenceAdjustConfig
    ) -> None:
        self.result, self.evidence, self.config = result, evidence, config
        self._window: tuple[int, int] | None = None
        self._solved: dict[int, DisplacementField] = {}
        self._written: dict[int, DisplacementField | None] = {}
        self._to_base: dict[int, Callable] = {}
        # Each link pair's points through the two frames' own local stages (static: _own_local).
        self._pairs: dict[tuple[int, int], tuple | None] = {}

    def consistent(self, k: int, window: tuple[int, int]) -> DisplacementField | None:
        """Frame k's correction field, from the window ``(start, end)`` that made it final;
        None where it keeps its own local stage (the reference frame, a frame without a
        field, ``config.fields`` None)."""
        if self.config.fields is None or k in self.evidence.fixed:
            return None
        if window != self._window:
            self._solve(*window)
        field_ = self._solved.get(k)
        self._written[k] = field_
        return field_

    def _solve(self, start: int, end: int) -> None:
        steps = self.config.link_steps
        first = max(start - max(steps), 0)
        models = self.evidence.models
        # Frames before ``first`` take no part in this window or any later one.
        for j in [j for j in self._to_base if j < first]:
            del self._to_base[j]
            self.result.release(j)
        for j in [j for j in self._written if j < first]:
            del self._written[j]
        for pair in [pair for pair in self._pairs if pair[0] < first]:
            del self._pairs[pair]
        frames = {}
        for j in range(first, end):
            if models[j] is None:
                continue
            held = j < start or j in self.evidence.fixed
            own = self.result.field(j)
            grid = self._held_correction(j) if held else None
            if not held and own is None:
                held = True  # nothing to correct: its global stage
            elif not held:
                grid = refined_grid(own)
            frames[j] = FieldFrame(self._own_local(j), grid, held)
        links = [
            self.evidence.links(j, j + s, self.config.probes, self.config.link_matcher)
            for s in steps
            for j in range(first, end - s)
            if j + s >= start and models[j] is not None and models[j + s] is not None
        ]
        self._solved = solve_corrections(frames, links, self.config.fields, self._pairs)
        self._window = (start, end)

    def _held_correction(self, j: int) -> DisplacementField | None:
        if j in self._written:
            return self._written[j]
        return self.result.local_stage(j)[2] if self.result.is_adjusted(j) else None

    def _own_local(self, j: int) -> Callable:
        """Corrected px -> base px through frame j's own local stage (its own model and field:
        the local stage the correction applies to, even where map points moved the model the
        adjustment starts from)."""
        if j not in self._to_base:
            model = as_polyprojective(self.result.own_model(j), *self.result.frame_size)
            field_ = self.result.field(j)
            if field_ is None:
                self._to_base[j] = model.apply
            else:
                self._to_base[j] = partial(local_frame_to_base, model.apply, field_)
        return self._to_base[j]


def _evidence(result: RegistrationResult, frames, config: SequenceAdjustConfig) -> SequenceEvidence:
    """The adjustment's view of a result: own models, kept control points with their noise,
    the analyst's map points (:mod:`registration.adjustment.map_points`), grey frames read on
    demand."""
    models, controls = [], []
    width, height = result.frame_size
    for k in range(result.n_frames):
        own = result.own_model(k)
        points = result.control_points(k) if own is not None else None
        if own is None or points is None:
            models.append(None if own is None else as_polyprojective(own, width, height))
            controls.append(None)
            continue
        models.append(as_polyprojective(own, width, height))
        src, dst, kept, _ = points
        sigma = result.records[k].stats.get("residual_sigma_px")
        controls.append(ControlPointSet(
            k, src[kept], dst[kept], float(sigma) if sigma else config.default_control_sigma_px,
        ))  # fmt: skip
    greys: OrderedDict[int, np.ndarray] = OrderedDict()

    def grey(k: int) -> np.ndarray:
        if k not in greys:
            greys[k] = to_grey(frames.get(k))
            while len(greys) > _GREY_CACHE:
                greys.popitem(last=False)
        return greys[k]

    map_points = {}
    own = list(models)  # the neighbours' own models judge a frame's, whatever the order
    for k, points in _map_points_by_frame(result).items():
        if models[k] is None or k == result.reference_frame:
            continue  # refused when they were added; a frame registered again since may fail
        src = result.lens.corrected_from_raw(np.array([p.frame_xy for p in points]))
        dst = np.array([p.base_xy for p in points])
        mp = apply_map_points(
            k, models[k], controls[k], src, dst, np.array([p.sigma_px for p in points]),
            config.solver.f_scale, partial(_links_through, k, own, grey, result.lens, config),
        )  # fmt: skip
        models[k], controls[k], map_points[k] = mp.start, mp.controls, mp
    return SequenceEvidence(
        models, controls, grey, result.lens, _outline(result),
        frozenset({result.reference_frame}), map_points, _stored_links(result),
    )  # fmt: skip


def _stored_links(result: RegistrationResult) -> Callable:
    """``(k, l) -> (links, key)`` or None: the links the run measured as it registered the later
    of the two frames (:mod:`registration.run.chunk_links`), read from that frame's arrays."""
    read: OrderedDict[int, dict] = OrderedDict()

    def stored(k: int, l: int):  # noqa: E741 (the second frame)
        for holder in (l, k):
            if holder not in read:
                read[holder] = links_from_arrays(result.stored_links(holder))
                while len(read) > _LINKS_CACHE:
                    read.popitem(last=False)
            if (k, l) in read[holder]:
                return read[holder][(k, l)]
        return None

    return stored


def _links_through(k: int, models, grey, lens, config: SequenceAdjustConfig, model) -> float:
    """The median distance (base px) between where ``model`` puts frame ``k``'s links to its
    nearest neighbours (k - 1, k + 1) and where the neighbours' own models put them, the links
    measured through ``model``; inf where none is found."""
    probes = textured_probes(grey(k), probes_for(grey(k), config.probes))
    distances = []
    for j in (k - 1, k + 1):
        if 0 <= j < len(models) and models[j] is not None:
            links = measure_links(
                grey(k), grey(j), k, j, model, models[j], lens, config.probes, probes,
                config.link_matcher,
            )  # fmt: skip
            d = model.apply(links.src_k) - models[j].apply(links.src_l)
            distances.append(np.hypot(d[:, 0], d[:, 1]))
    distances = np.concatenate(distances) if distances else np.zeros(0)
    return float(np.median(distances)) if len(distances) else float("inf")


def _map_points_by_frame(result: RegistrationResult) -> dict:
    by_frame: dict[int, list] = {}
    for p in read_map_points(result.out_dir):
        by_frame.setdefault(p.k, []).append(p)
    return by_frame


def _write_adjusted(
    writer: ResultWriter,
    result: RegistrationResult,
    adjusted: FrameAdjustment,
    field_: DisplacementField | None,
) -> None:
    """Rewrite frame ``adjusted.k``'s record with the adjustment, and its arrays with the field
    that makes its local stage consistent with its neighbours' (``consistency_field_*``) where
    there is one; its own model and field stay."""
    k = adjusted.k
    record = replace(result.records[k], adjusted_model=adjusted.model.to_dict()).with_stats(
        adjustment=adjusted.to_dict()
    )
    if field_ is None:
        writer.write_record(k, record)
        return
    arrays = {n: v for n, v in result.arrays(k).items() if not n.startswith("consistency_field_")}
    arrays.update({f"consistency_field_{n}": v for n, v in field_.to_arrays().items()})
    # The frames were checked to be the run's own (adjust_folder) or are (the run itself).
    writer.write_frame(k, record, arrays, keep_input_hash=True)


def _outline(result: RegistrationResult) -> np.ndarray:
    """``(M, 2)`` corrected px: a 9 x 7 grid over the raw frame, corners included. (Over a
    margin of 15 % beyond the frame the prior held the real flyover's models too firmly:
    k -> k+1 at 1.0x instead of 0.94x the floor.)"""
    w, h = result.frame_size
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 7))
    outline = result.lens.corrected_from_raw(np.c_[gx.ravel(), gy.ravel()])
    return outline[np.isfinite(outline).all(axis=1)]  # a strong lens may not reach the margin
