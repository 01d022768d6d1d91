"""Accuracy against the simulator's exact truth: the result and the truth compared point by point
on a ground grid of every frame, and Table 2 from the truth's own positions of five points.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points, frame_outline
from registration.evaluation.report import (
    EvaluationReport,
    _adjustment,
    _camera,
    _definitions,
    _excursions,
    _status,
    _summary,
    error_stats,
)
from registration.evaluation.table2 import (
    LOCATIONS,
    STAGES,
    EvaluationConfig,
    table2_from_motions,
    table_frames,
)

# --------------------------------------------------------------------------------------------
# Truth mode


# A result registered with an estimated γ (``calibrate``, ``register --gamma auto``) is the same
# sequence seen through a slightly other lens, and is evaluated through its own γ; a γ further
# off than any estimate this project makes (worst 0.02 measured) means another simulation.
GAMMA_ESTIMATE_TOL = 0.05


def check_compatible(result: Any, truth: Any) -> None:
    """Raise ValueError (one line) when a result and a simulator truth describe different
    sequences: frame count, frame size or base size differ, or gamma by more than
    ``GAMMA_ESTIMATE_TOL``."""
    if result.n_frames != truth.n_frames:
        raise ValueError(
            f"the truth does not match the result: {truth.n_frames} frames in the truth, "
            f"{result.n_frames} in the result"
        )
    rs, ts = tuple(result.frame_size), tuple(truth.frame_size)
    if rs != ts:
        raise ValueError(
            f"the truth does not match the result: frame size {ts[0]}x{ts[1]} in the truth, "
            f"{rs[0]}x{rs[1]} in the result"
        )
    if abs(float(result.gamma) - float(truth.gamma)) > GAMMA_ESTIMATE_TOL:
        raise ValueError(
            f"the truth does not match the result: gamma {truth.gamma:g} in the truth, "
            f"{result.gamma:g} in the result (an estimated gamma within "
            f"{GAMMA_ESTIMATE_TOL:g} of the truth's is evaluated)"
        )
    rb, tb = getattr(result, "base_size", None), getattr(truth, "base_size", None)
    if rb is not None and tb is not None and tuple(rb) != tuple(tb):
        raise ValueError(
            f"the truth does not match the result: base size {tb[0]}x{tb[1]} in the truth, "
            f"{rb[0]}x{rb[1]} in the result"
        )


def ground_grid(truth: Any, k: int, step: float) -> NDArray[np.float64]:
    """Base points on a fixed grid (multiples of ``step``) that frame ``k`` sees: ``(N, 2)``."""
    w, h = truth.frame_size
    outline = truth.frame_to_base(k, frame_outline(w, h))
    outline = outline[np.isfinite(outline).all(axis=1)]
    if len(outline) == 0:
        return np.zeros((0, 2))
    x0, y0 = np.floor(outline.min(axis=0) / step) * step
    x1, y1 = np.ceil(outline.max(axis=0) / step) * step
    bw, bh = getattr(truth, "base_size", (math.inf, math.inf))
    x0, y0 = max(x0, 0.0), max(y0, 0.0)
    x1, y1 = min(x1, bw - 1.0), min(y1, bh - 1.0)
    xs = np.arange(x0, x1 + 1e-9, step)
    ys = np.arange(y0, y1 + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    b = np.c_[gx.ravel(), gy.ravel()]
    q = truth.base_to_frame(k, b)
    inside = np.isfinite(q).all(axis=1)
    inside &= (q[:, 0] >= 0) & (q[:, 0] <= w - 1) & (q[:, 1] >= 0) & (q[:, 1] <= h - 1)
    return b[inside]


def truth_errors(
    result: Any, truth: Any, k: int, base_xy: ArrayLike
) -> tuple[dict[str, NDArray], dict[str, NDArray]]:
    """Per-point errors and motions of frame ``k`` at the base points ``base_xy``.

    Returns:
        ``(error, motion)``, each ``{"unregistered", "global", "local"} -> (N,)`` px (NaN where
        undefined). ``error[s] = |result.frame_to_base(k, q_k, s) - b|`` against the truth;
        ``motion[s] = |result.frame_to_base(k, q_k, s) - result.frame_to_base(ref, q_ref, s)|``,
        the paper's "movement remaining" relative to the reference frame, which is all the local
        stage can remove (it aligns frames with the mid base image, i.e. the reference frame as
        registered). For "unregistered" both are the corrected-frame motion.
    """
    b = as_points(base_xy, "base_xy")
    camera = _camera(result)
    ref = int(result.reference_frame)
    q = truth.base_to_frame(k, b)
    q_ref = truth.base_to_frame(ref, b)
    unreg = np.linalg.norm(camera.corrected_from_raw(q) - camera.corrected_from_raw(q_ref), axis=1)
    error, motion = {"unregistered": unreg}, {"unregistered": unreg}
    for s in ("global", "local"):
        p_k = result.frame_to_base(k, q, s)
        error[s] = np.linalg.norm(p_k - b, axis=1)
        motion[s] = np.linalg.norm(p_k - result.frame_to_base(ref, q_ref, s), axis=1)
    return error, motion


def table_points(frame_size: tuple[int, int], inset: float) -> NDArray[np.float64]:
    """Raw px of the five Table 2 locations (NW, NE, Center, SW, SE) in a frame, ``inset`` of
    the frame size in from the corners."""
    w, h = frame_size
    a = inset
    return np.array(
        [
            [a * (w - 1), a * (h - 1)],
            [(1 - a) * (w - 1), a * (h - 1)],
            [0.5 * (w - 1), 0.5 * (h - 1)],
            [a * (w - 1), (1 - a) * (h - 1)],
            [(1 - a) * (w - 1), (1 - a) * (h - 1)],
        ]
    )


def evaluate_truth(
    result: Any,
    truth: Any,
    config: EvaluationConfig = EvaluationConfig(),
    *,
    progress: Callable[[int, int], None] | None = None,
) -> EvaluationReport:
    """Evaluate a result against the simulator's truth (module docstring).

    Per frame: the error statistics against the truth on a dense grid of ground points
    (``per_frame[k][stage]``) and the motion relative to the reference frame
    (``per_frame[k]["motion"][stage]``). Table 2 (``table``) uses the paper's definition,
    motion relative to the reference frame; ``table_absolute`` gives the errors against the truth
    at the same points and frames.

    Args:
        result: a registration result (``registration.load``) or any SequenceMapping with
            ``gamma``, ``frame_size`` and ``reference_frame``.
        truth: ``registration.synth.load_truth(DIR)``.
        progress: called as ``progress(done, total)`` after each frame.
    """
    check_compatible(result, truth)
    n = result.n_frames
    ref = int(result.reference_frame)
    per_frame: list[dict] = []
    pooled: dict[str, list[NDArray]] = {s: [] for s in STAGES}
    pooled_motion: dict[str, list[NDArray]] = {s: [] for s in STAGES}
    for k in range(n):
        b = ground_grid(truth, k, config.grid_step_px)
        error, motion = truth_errors(result, truth, k, b)
        rec: dict[str, Any] = {"frame": k, "status": _status(result, k), "n_points": len(b)}
        rec.update(_adjustment(result, k))
        rec["motion"] = {}
        for s in STAGES:
            e = error[s] if not (s == "unregistered" and k == ref) else np.zeros(0)
            m = motion[s] if k != ref else np.zeros(0)  # zero by definition
            rec[s] = error_stats(e)
            rec["motion"][s] = error_stats(m)
            pooled[s].append(e[np.isfinite(e)])
            pooled_motion[s].append(m[np.isfinite(m)])
        per_frame.append(rec)
        if progress:
            progress(k + 1, n)
    # Table 2: five ground points of the reference frame over evenly spread frames.
    b_pts = truth.frame_to_base(ref, table_points(tuple(result.frame_size), config.table_inset))
    frames = table_frames(n, config.table_frames)
    rel: dict[str, dict[str, list[float]]] = {s: {loc: [] for loc in LOCATIONS} for s in STAGES}
    ab: dict[str, dict[str, list[float]]] = {s: {loc: [] for loc in LOCATIONS} for s in STAGES}
    for k in frames:
        error, motion = truth_errors(result, truth, k, b_pts)
        for i, loc in enumerate(LOCATIONS):
            for s in STAGES:
                if k != ref:
                    rel[s][loc].append(float(motion[s][i]))
                if not (s == "unregistered" and k == ref):
                    ab[s][loc].append(float(error[s][i]))
    used = {loc: [k for k in frames if k != ref] for loc in LOCATIONS}
    return EvaluationReport(
        mode="truth",
        table=table2_from_motions(rel, LOCATIONS, used),
        table_absolute=table2_from_motions(ab, LOCATIONS, {loc: list(frames) for loc in LOCATIONS}),
        per_frame=per_frame,
        summary=_summary(pooled, per_frame),
        summary_motion=_summary(pooled_motion, [p["motion"] for p in per_frame]),
        excursions=_excursions(per_frame, config),
        definitions=_definitions("truth", config),
        reference_frame=ref,
        n_frames=n,
    )
