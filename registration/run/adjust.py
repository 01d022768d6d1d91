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

import numpy as np

from registration.adjustment import (
    ControlPointSet,
    FrameAdjustment,
    FrameField,
    SequenceAdjustConfig,
    SequenceEvidence,
    adjust_sequence,
    as_polyprojective,
    correction_at,
    pool_corrections,
    refined_grid,
)
from registration.geometry import DisplacementField, model_from_dict
from registration.matching import to_grey
from registration.run.result import RegistrationResult
from registration.run.writer import ResultWriter

# Frames kept decoded: a window's links reach this far back at most.
_GREY_CACHE = 64


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
    frames (the frames written so far stay; a resumed run goes on from them)."""
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
    for adjusted, solution in adjust_sequence(evidence, config, final):
        if cancel is not None and cancel.is_set():
            break
        field_ = (
            None if adjusted.k in evidence.fixed
            else fields.consistent(adjusted.k, solution, adjusted.window)
        )  # fmt: skip
        _write_adjusted(writer, result, adjusted, field_)
        written += 1
        if progress:
            progress(done + written, total)
    return written


class _Fields:
    """Each frame's local field made consistent with its neighbours'
    (:func:`registration.adjustment.consistent_field`), from the result's own fields."""

    def __init__(
        self, result: RegistrationResult, evidence: SequenceEvidence, config: SequenceAdjustConfig
    ) -> None:
        self.result, self.evidence = result, evidence
        self.radius, self.baseline = config.field_radius, config.field_baseline_px
        self.support = config.field_support
        w, h = result.frame_size
        lens = result.lens

        def clip(q):
            # The nearest point of the raw frame, in corrected px: beyond the frame even a
            # margin of 5 % let the two models' extrapolations part far enough to break the
            # local stage's inversion (a long flight's anchors).
            raw = lens.raw_from_corrected(q)
            raw = np.c_[np.clip(raw[:, 0], -0.5, w - 0.5), np.clip(raw[:, 1], -0.5, h - 0.5)]
            return np.where(np.isfinite(raw), lens.corrected_from_raw(raw), q)

        self.clip = clip
        # Corrections of frame j on a grid, under one window's solution (keyed by the window:
        # the same for every frame of the window on that grid).
        self._corrections: dict = {}

    def _correction(self, j: int, solution, window, grid: DisplacementField):
        key = (j, window, (grid.origin, grid.spacing, grid.shape))
        if key not in self._corrections:
            field_j = self.result.field(j)
            self._corrections[key] = None if field_j is None else correction_at(
                FrameField(field_j, self.evidence.models[j], solution[j]),
                grid.node_xy.reshape(-1, 2), self.clip,
            )  # fmt: skip
        return self._corrections[key]

    def consistent(self, k: int, solution, window) -> DisplacementField | None:
        """Frame k's consistency field from its neighbours in ``solution``, the models of the
        window ``(start, end)`` that made it final; None without one."""
        own_field = self.result.field(k) if self.radius else None
        if own_field is None:
            return None
        for key in [key for key in self._corrections if key[0] < k - self.radius]:
            del self._corrections[key]
        grid = refined_grid(own_field)
        outline = self.evidence.outline
        at = solution[k].apply(outline)
        corrections = [self._correction(k, solution, window, grid)]
        for j in range(k - self.radius, k + self.radius + 1):
            if j == k or j not in solution:
                continue
            apart = float(np.mean(np.hypot(*(solution[j].apply(outline) - at).T)))
            c = self._correction(j, solution, window, grid) if apart <= self.baseline else None
            if c is not None:
                corrections.append(c)
        self.result.release(k - self.radius - 1)
        if len(corrections) == 1:
            return None  # no neighbour close enough: its own local stage
        return pool_corrections(grid, corrections, self.support)


def _evidence(result: RegistrationResult, frames, config: SequenceAdjustConfig) -> SequenceEvidence:
    """The adjustment's view of a result: own models, kept control points with their noise,
    grey frames read on demand."""
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

    return SequenceEvidence(
        models, controls, grey, result.lens, _outline(result), frozenset({result.reference_frame})
    )


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
    writer.write_frame(k, record, arrays)


def _outline(result: RegistrationResult) -> np.ndarray:
    """``(M, 2)`` corrected px: a 9 x 7 grid over the raw frame, corners included. (Over a
    margin of 15 % beyond the frame the prior held the real flyover's models too firmly:
    k -> k+1 at 1.0x instead of 0.94x the floor.)"""
    w, h = result.frame_size
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 7))
    outline = result.lens.corrected_from_raw(np.c_[gx.ravel(), gy.ravel()])
    return outline[np.isfinite(outline).all(axis=1)]  # a strong lens may not reach the margin
