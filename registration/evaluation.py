"""Accuracy of a registration (paper section 6): the paper's Table 2, per-frame error statistics
and "sudden excursions".

Two sources of ground points:

* **Simulated truth** (:func:`evaluate_truth`): the simulator knows where every ground point is in
  every frame. For stage ``s`` ("global" or "local") the *error* of frame ``k`` at base point
  ``b`` is ``|result.frame_to_base(k, truth.base_to_frame(k, b), s) - b|`` in base px, and its
  *motion* the distance of that registered position from the same ground point's registered
  position in the reference frame; both on a dense grid of base points (every
  ``grid_step_px``) inside frame ``k``. The local stage aligns frames with the mid base image
  (the reference frame as registered), so it removes motion; the error against the truth cannot
  fall below the reference frame's own (global) error.
* **Hand-marked points** (:func:`evaluate_points`): the same ground points clicked in several raw
  frames (file format: :func:`read_points_csv`). Their positions in the global and local sequences
  are the clicked raw positions mapped by ``result.frame_to_base(k, xy, stage)`` (the registered
  image at ``b`` shows raw frame pixel ``base_to_frame(k, b)``, so a point seen at raw ``q`` is seen
  at ``frame_to_base(k, q)`` in the registered sequence: marking in raw frames once is equivalent
  to marking in each registered sequence, without the re-marking noise).

Stage "unregistered" (paper: "initially unregistered (but radially corrected) input sequence"):
a ground point's position in frame ``k`` after the Harris correction only, in corrected-frame px.
Its *motion* in frame ``k`` is the distance of that position from the point's corrected position
in the reference frame (the frame the sequence is registered to; the paper's "base frame 1").

Motion (Table 2, paper: "the mean and standard deviations of the points' motion"): for the global
and local stages, likewise the distance of the point's registered position in frame ``k`` from
its registered position in the reference frame (``anchor="reference"``, the default) or, for
hand-marked points, from its mean registered position over the marked frames
(``anchor="mean"``). The anchor frame itself is left out (its motion is zero by definition).
With simulated truth a second table in the same layout gives the errors against the truth. ``mu`` is the mean and ``sigma`` the population standard deviation
(ddof 0) of a point's motions over the frames; the "Average" columns are the means of ``mu`` and
of ``sigma`` over the locations (this reproduces the paper's Average column: e.g. Unregistered
(86.7+96.0+69.0+125.9+88.8)/5 = 93.3 and (46.0+60.0+49.2+50.2+46.2)/5 = 50.3).

Sudden excursions (paper 6: "occasional sudden excursions that are larger than would be
anticipated"): frames whose mean error exceeds the median of their neighbours (``window`` frames
either side) by more than ``k_mad`` robust standard deviations (1.4826 MAD) of those excesses over
the whole sequence *and* by more than ``floor_px``.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.camera import Camera
from registration.coords import as_points, frame_outline

STAGES = ("unregistered", "global", "local")
STAGE_LABELS = {"unregistered": "Unregistered", "global": "Post-Global", "local": "Post-Local"}
LOCATIONS = ("NW", "NE", "Center", "SW", "SE")
POINTS_HEADER = ("point", "frame", "x", "y")
ANCHORS = ("reference", "mean")


@dataclass(frozen=True)
class EvaluationConfig:
    """Settings of the evaluation.

    Attributes:
        grid_step_px: spacing of the dense grid of ground points, base px (truth mode).
        table_frames: frames spread evenly over the sequence for Table 2 (paper 6: 10).
        table_inset: the five Table 2 locations sit this fraction of the frame size in from the
            reference frame's corners (NW, NE, SW, SE) and at its centre (truth mode).
        anchor: "reference" or "mean": what a hand-marked point's motion is measured from.
        excursion_window: neighbours either side a frame's error is compared with.
        excursion_k_mad: robust standard deviations above the typical jump that flag a frame.
        excursion_floor_px: a flagged jump must also exceed this, px (tiny jumps do not count).
    """

    grid_step_px: float = 16.0
    table_frames: int = 10
    table_inset: float = 0.10
    anchor: str = "reference"
    excursion_window: int = 2
    excursion_k_mad: float = 4.0
    excursion_floor_px: float = 1.0

    def __post_init__(self) -> None:
        if not self.grid_step_px > 0:
            raise ValueError(f"grid step must be positive, got {self.grid_step_px}")
        if self.table_frames < 1:
            raise ValueError(f"frames for the table must be >= 1, got {self.table_frames}")
        if not 0 <= self.table_inset < 0.5:
            raise ValueError(f"table inset must be in [0, 0.5), got {self.table_inset}")
        if self.anchor not in ANCHORS:
            raise ValueError(f"anchor must be one of {', '.join(ANCHORS)}, got {self.anchor!r}")


# --------------------------------------------------------------------------------------------
# Table 2


@dataclass
class Table2:
    """The paper's Table 2: rows = stages, columns = locations x (mu, sigma) plus their average.

    Attributes:
        locations: column names in order.
        mu, sigma, n: ``stage -> list`` per location (NaN / 0 where a location has no motion).
        frames: ``location -> frames`` that entered the table.
    """

    locations: list[str]
    mu: dict[str, list[float]]
    sigma: dict[str, list[float]]
    n: dict[str, list[int]]
    frames: dict[str, list[int]] = field(default_factory=dict)

    @property
    def stages(self) -> list[str]:
        return [s for s in STAGES if s in self.mu]

    def average(self, stage: str) -> tuple[float, float]:
        """``(mean of mu, mean of sigma)`` over the locations that have values."""
        mu = np.asarray(self.mu[stage], float)
        sd = np.asarray(self.sigma[stage], float)
        ok = np.isfinite(mu)
        if not ok.any():
            return math.nan, math.nan
        return float(mu[ok].mean()), float(sd[ok].mean())

    def to_markdown(self, decimals: int = 1) -> str:
        """Markdown in the paper's layout (a location header row, then a mu/sigma row)."""
        cols = [*self.locations, "Average"]
        lines = ["| Stage |" + "".join(f" {c} | |" for c in cols)]
        lines.append("|---|" + "---:|---:|" * len(cols))
        lines.append("| |" + " μ | σ |" * len(cols))
        for s in self.stages:
            cells = [*zip(self.mu[s], self.sigma[s], strict=True), self.average(s)]
            row = "".join(f" {_fmt(m, decimals)} | {_fmt(sd, decimals)} |" for m, sd in cells)
            lines.append(f"| {STAGE_LABELS[s]} |{row}")
        return "\n".join(lines) + "\n"

    def to_csv(self, decimals: int = 3) -> str:
        """CSV, one row per stage: ``Stage,NW_mu,NW_sigma,...,Average_mu,Average_sigma``."""
        cols = [*self.locations, "Average"]
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["Stage", *[f"{c}_{q}" for c in cols for q in ("mu", "sigma")]])
        for s in self.stages:
            cells = [*zip(self.mu[s], self.sigma[s], strict=True), self.average(s)]
            w.writerow([STAGE_LABELS[s], *[_fmt(v, decimals, "") for pair in cells for v in pair]])
        return buf.getvalue()

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"locations": list(self.locations), "frames": self.frames, "rows": {}}
        for s in self.stages:
            am, asd = self.average(s)
            out["rows"][s] = {
                "label": STAGE_LABELS[s],
                "mu": [_num(v) for v in self.mu[s]],
                "sigma": [_num(v) for v in self.sigma[s]],
                "n": list(self.n[s]),
                "average_mu": _num(am),
                "average_sigma": _num(asd),
            }
        return out


def _fmt(v: float, decimals: int, nan: str = "–") -> str:
    return nan if not np.isfinite(v) else f"{v:.{decimals}f}"


def _num(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def table2_from_motions(
    motions: dict[str, dict[str, ArrayLike]],
    locations: Sequence[str],
    frames: dict[str, list[int]] | None = None,
) -> Table2:
    """Table 2 from motions: ``motions[stage][location]`` = 1-D array of px (NaN = missing).

    ``mu`` = mean, ``sigma`` = population standard deviation (ddof 0) of the finite motions.
    """
    mu: dict[str, list[float]] = {}
    sd: dict[str, list[float]] = {}
    n: dict[str, list[int]] = {}
    for s in STAGES:
        if s not in motions:
            continue
        mu[s], sd[s], n[s] = [], [], []
        for loc in locations:
            v = np.asarray(motions[s].get(loc, []), float).ravel()
            v = v[np.isfinite(v)]
            n[s].append(int(v.size))
            mu[s].append(float(v.mean()) if v.size else math.nan)
            sd[s].append(float(v.std(ddof=0)) if v.size else math.nan)
    return Table2(list(locations), mu, sd, n, dict(frames or {}))


def table_frames(n_frames: int, count: int) -> list[int]:
    """``count`` frames spread evenly over ``0..n_frames-1`` (first and last included)."""
    if n_frames <= 0:
        return []
    return sorted({int(round(v)) for v in np.linspace(0, n_frames - 1, min(count, n_frames))})


# --------------------------------------------------------------------------------------------
# Excursions and statistics


def error_stats(err: ArrayLike) -> dict[str, float | int | None]:
    """``{n, mean, median, p95, max}`` of the finite values (None when there are none)."""
    e = np.asarray(err, float).ravel()
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"n": 0, "mean": None, "median": None, "p95": None, "max": None}
    return {
        "n": int(e.size),
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "p95": float(np.percentile(e, 95)),
        "max": float(e.max()),
    }


def find_excursions(
    frames: Sequence[int], errors: Sequence[float], config: EvaluationConfig = EvaluationConfig()
) -> list[dict[str, float]]:
    """Frames whose error jumps against their neighbours (module docstring).

    Args:
        frames: frame indices in sequence order.
        errors: one error per frame, px (NaN = no value; skipped).

    Returns:
        ``[{frame, error, baseline, excess}]`` for the flagged frames, in frame order.
    """
    f = np.asarray(frames, int)
    e = np.asarray(errors, float)
    ok = np.isfinite(e)
    f, e = f[ok], e[ok]
    order = np.argsort(f, kind="stable")
    f, e = f[order], e[order]
    n = len(e)
    if n < 3:
        return []
    w = max(1, config.excursion_window)
    base = np.empty(n)
    for i in range(n):
        nb = np.r_[e[max(0, i - w) : i], e[i + 1 : i + 1 + w]]
        base[i] = np.median(nb)
    excess = e - base
    med = np.median(excess)
    scale = 1.4826 * np.median(np.abs(excess - med))
    flag = (excess > med + config.excursion_k_mad * scale) & (excess > config.excursion_floor_px)
    return [
        {
            "frame": int(f[i]),
            "error": float(e[i]),
            "baseline": float(base[i]),
            "excess": float(excess[i]),
        }
        for i in np.nonzero(flag)[0]
    ]


# --------------------------------------------------------------------------------------------
# Reports


@dataclass
class EvaluationReport:
    """Everything :func:`evaluate_truth` / :func:`evaluate_points` measured.

    Attributes:
        mode: "truth" or "points".
        table: Table 2 (the paper's definition: motion relative to the reference frame, or to
            the mean position with the "mean" anchor).
        per_frame: one dict per evaluated frame: ``frame``, ``status`` and per stage the
            :func:`error_stats` of that frame (truth: errors against the truth on the dense grid,
            plus ``"motion"``: per stage the motion relative to the reference frame; points: the
            marked points' motion).
        summary: per stage, statistics of all errors pooled plus the mean of the per-frame means.
        table_absolute: truth mode only: Table 2 of the errors against the truth.
        summary_motion: truth mode only: like ``summary`` for the motion.
        excursions: per stage ("global", "local") the frames :func:`find_excursions` flags.
        definitions: the definitions used, in words (kept in the JSON for the reader).
    """

    mode: str
    table: Table2
    per_frame: list[dict[str, Any]]
    summary: dict[str, dict[str, Any]]
    excursions: dict[str, list[dict[str, float]]]
    definitions: dict[str, str]
    reference_frame: int = 0
    n_frames: int = 0
    table_absolute: Table2 | None = None
    summary_motion: dict[str, dict[str, Any]] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "mode": self.mode,
            "n_frames": self.n_frames,
            "reference_frame": self.reference_frame,
            "table2": self.table.to_dict(),
            "table2_absolute": None
            if self.table_absolute is None
            else self.table_absolute.to_dict(),
            "summary": self.summary,
            "summary_motion": self.summary_motion,
            "excursions": self.excursions,
            "per_frame": self.per_frame,
            "definitions": self.definitions,
        }

    def to_markdown(self) -> str:
        unit = "base px; Unregistered in corrected-frame px"
        out = [
            f"### Table 2: motion relative to the reference frame {self.reference_frame} "
            f"({self.mode} mode; {unit})",
            "",
            self.table.to_markdown(),
        ]
        if self.table_absolute is not None:
            out += [
                "### Table 2 layout: error against the truth",
                "",
                self.table_absolute.to_markdown(),
            ]
        sections = [("Error against the truth" if self.mode == "truth" else "Motion", self.summary)]
        if self.summary_motion is not None:
            sections.append(("Motion relative to the reference frame", self.summary_motion))
        for title, summary in sections:
            out += [
                f"### {title}, all evaluated points",
                "",
                "| Stage | n | mean | median | p95 | max | mean of frame means |",
                "|---|---:|---:|---:|---:|---:|---:|",
            ]
            for s in STAGES:
                st = summary.get(s)
                if not st:
                    continue
                vals = [st.get(k) for k in ("mean", "median", "p95", "max", "mean_of_frame_means")]
                cells = " | ".join("–" if v is None else f"{v:.3f}" for v in vals)
                out.append(f"| {STAGE_LABELS[s]} | {st.get('n', 0)} | {cells} |")
            out.append("")
        out.append("### Sudden excursions")
        out.append("")
        any_exc = False
        for s in ("global", "local"):
            exc = self.excursions.get(s, [])
            if exc:
                any_exc = True
                items = ", ".join(
                    f"frame {x['frame']} ({x['error']:.2f} px vs {x['baseline']:.2f})" for x in exc
                )
                out.append(f"- {STAGE_LABELS[s]}: {items}")
        if not any_exc:
            out.append("- none")
        failed = [
            p["frame"] for p in self.per_frame if p.get("status") not in (None, "ok", "damaged")
        ]
        if failed:
            out.append("")
            out.append(f"Frames without a registration: {', '.join(map(str, failed))}")
        damaged = [p["frame"] for p in self.per_frame if p.get("status") == "damaged"]
        if damaged:
            out.append("")
            out.append(
                f"Frames with a damaged record (not evaluated; `aerialreg register --resume` "
                f"redoes them): {', '.join(map(str, damaged))}"
            )
        return "\n".join(out) + "\n"

    def per_frame_csv(self) -> str:
        """CSV ``frame,status,<stage>_n,<stage>_mean,...`` one row per evaluated frame (truth
        mode adds ``motion_<stage>_...`` columns)."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        keys = ("n", "mean", "median", "p95", "max")
        motion = any("motion" in p for p in self.per_frame)
        head = ["frame", "status", *[f"{s}_{k}" for s in STAGES for k in keys]]
        if motion:
            head += [f"motion_{s}_{k}" for s in ("global", "local") for k in keys]
        w.writerow(head)
        for p in self.per_frame:
            row = [p["frame"], p.get("status", "")]
            for s in STAGES:
                st = p.get(s) or {}
                row += ["" if st.get(k) is None else st.get(k) for k in keys]
            if motion:
                for s in ("global", "local"):
                    st = p.get("motion", {}).get(s) or {}
                    row += ["" if st.get(k) is None else st.get(k) for k in keys]
            w.writerow(row)
        return buf.getvalue()


def _summary(errors_by_stage: dict[str, list[NDArray]], per_frame: list[dict]) -> dict[str, dict]:
    """Pooled statistics per stage; ``per_frame`` = one ``{stage: error_stats}`` per frame."""
    out = {}
    for s, chunks in errors_by_stage.items():
        allv = np.concatenate(chunks) if chunks else np.zeros(0)
        st = error_stats(allv)
        means = [p[s]["mean"] for p in per_frame if p.get(s) and p[s]["mean"] is not None]
        st["mean_of_frame_means"] = float(np.mean(means)) if means else None
        st["n_frames"] = len(means)
        out[s] = st
    return out


def _excursions(per_frame: list[dict], config: EvaluationConfig) -> dict[str, list]:
    out = {}
    for s in ("global", "local"):
        frames = [p["frame"] for p in per_frame]
        errs = [
            (p[s]["mean"] if p.get(s) and p[s]["mean"] is not None else math.nan) for p in per_frame
        ]
        out[s] = find_excursions(frames, errs, config)
    return out


def _status(result: Any, k: int) -> str:
    records = getattr(result, "records", None)
    if records is not None:
        try:
            return str(records[k].get("status", "ok"))
        except (IndexError, AttributeError, TypeError):
            return "ok"
    return "ok"


def _camera(result: Any) -> Camera:
    camera = getattr(result, "camera", None)
    if isinstance(camera, Camera):
        return camera
    w, hh = result.frame_size
    return Camera(float(result.gamma), int(w), int(hh))


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


def _definitions(mode: str, config: EvaluationConfig) -> dict[str, str]:
    d = {
        "unregistered": "distance of a ground point's Harris-corrected position in frame k from its "
        "corrected position in the reference frame (corrected-frame px); the reference frame "
        "itself is left out",
        "sigma": "population standard deviation (ddof 0) over the frames",
        "average": "mean of mu and mean of sigma over the locations",
        "excursions": f"frame mean error above the median of {config.excursion_window} neighbours "
        f"either side by more than {config.excursion_k_mad:g} robust SD (1.4826 MAD) and "
        f"{config.excursion_floor_px:g} px",
    }
    if mode == "truth":
        d["global/local"] = (
            "error: |result.frame_to_base(k, truth.base_to_frame(k, b), stage) - b| (base px) on a "
            f"grid every {config.grid_step_px:g} base px inside frame k; motion: the distance of "
            "that registered position from the same ground point's registered position in the "
            "reference frame. Table 2 (motion; table2_absolute: error) at five ground points (the "
            f"reference frame's corners inset {config.table_inset:.0%}, and its centre) in "
            f"{config.table_frames} frames spread evenly over the sequence, the reference frame "
            "left out of the motion"
        )
    else:
        ref = "the reference frame" if config.anchor == "reference" else "the mean over its frames"
        d["global/local"] = (
            "distance of a hand-marked point's registered position "
            f"(result.frame_to_base(k, raw xy, stage), base px) from its position in {ref}"
        )
    return d


# --------------------------------------------------------------------------------------------
# Points mode


@dataclass
class PointMarks:
    """Hand-marked ground points: ``marks[point][frame] = (x, y)`` raw px; ``order`` = point
    names in order of first appearance; ``source`` = the file."""

    marks: dict[str, dict[int, tuple[float, float]]]
    order: list[str]
    source: str = ""

    @property
    def locations(self) -> list[str]:
        """Point names: the paper's NW, NE, Center, SW, SE order when all names are among them,
        else the order of first appearance."""
        if set(self.order) <= set(LOCATIONS):
            return [loc for loc in LOCATIONS if loc in self.marks]
        return list(self.order)


def read_points_csv(
    path: str | os.PathLike,
    n_frames: int,
    frame_size: tuple[int, int],
    *,
    min_frames: int = 2,
) -> PointMarks:
    """Read hand-marked ground points.

    Format (UTF-8 CSV; blank lines and lines starting with ``#`` are ignored)::

        point,frame,x,y
        NW,0,211.5,180.25
        NW,10,215.0,176.0
        Center,0,1279.5,960.0

    * The header names the columns ``point``, ``frame``, ``x``, ``y`` (any order; extra columns,
      e.g. a note, are ignored).
    * ``point``: the ground point's name (the paper's five: NW, NE, Center, SW, SE; any name works).
    * ``frame``: frame index k, counting from 0 in reading order.
    * ``x``, ``y``: the point's position in frame k's RAW pixels (as recorded, lens-distorted;
      pixel centres at integers).
    * Each point is marked at most once per frame and in at least ``min_frames`` frames.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: one line naming the problem, the line number and the value.
    """
    from registration.io import read_text_file

    p = Path(path)
    text = read_text_file(p, "points file")
    name = p.name
    w, h = frame_size
    rows = [
        (i + 1, line)
        for i, line in enumerate(text.splitlines())
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not rows:
        raise ValueError(f"{name} is empty: expected the header 'point,frame,x,y' and rows")
    head_no, head_line = rows[0]
    header = [c.strip().lower() for c in next(csv.reader([head_line]))]
    missing = [c for c in POINTS_HEADER if c not in header]
    if missing:
        if len(missing) == len(POINTS_HEADER):
            raise ValueError(
                f"{name} line {head_no}: missing header 'point,frame,x,y' (got {head_line.strip()!r})"
            )
        raise ValueError(
            f"{name} line {head_no}: header lacks column {missing[0]!r} (got {head_line.strip()!r})"
        )
    col = {c: header.index(c) for c in POINTS_HEADER}
    marks: dict[str, dict[int, tuple[float, float]]] = {}
    where: dict[tuple[str, int], int] = {}
    order: list[str] = []
    for line_no, line in rows[1:]:
        fields = next(csv.reader([line]))
        if len(fields) < len(header):
            raise ValueError(
                f"{name} line {line_no}: expected {len(header)} fields ({','.join(header)}), "
                f"got {len(fields)}: {line.strip()!r}"
            )
        point = fields[col["point"]].strip()
        if not point:
            raise ValueError(f"{name} line {line_no}: empty point name")
        ftxt = fields[col["frame"]].strip()
        try:
            k = int(ftxt)
        except ValueError:
            raise ValueError(
                f"{name} line {line_no}: frame must be an integer, got {ftxt!r}"
            ) from None
        if not 0 <= k < n_frames:
            raise ValueError(
                f"{name} line {line_no}: frame {k} is not in the result (frames 0..{n_frames - 1})"
            )
        xy = []
        for c in ("x", "y"):
            t = fields[col[c]].strip()
            try:
                v = float(t)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise ValueError(f"{name} line {line_no}: {c} must be a finite number, got {t!r}")
            xy.append(v)
        x, y = xy
        if not (-0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5):
            raise ValueError(
                f"{name} line {line_no}: ({x:g}, {y:g}) lies outside the {w}x{h} raw frame"
            )
        if (point, k) in where:
            raise ValueError(
                f"{name} line {line_no}: point {point!r} is marked twice in frame {k} "
                f"(first on line {where[(point, k)]})"
            )
        where[(point, k)] = line_no
        if point not in marks:
            marks[point] = {}
            order.append(point)
        marks[point][k] = (x, y)
    if not marks:
        raise ValueError(f"{name} has a header but no points")
    for point in order:
        if len(marks[point]) < min_frames:
            frames = ", ".join(map(str, sorted(marks[point])))
            raise ValueError(
                f"{name}: point {point!r} is marked in {len(marks[point])} frame(s) ({frames}); "
                f"at least {min_frames} are needed"
            )
    return PointMarks(marks, order, str(p))


def point_positions(result: Any, marks: PointMarks) -> dict[str, dict[str, dict[int, NDArray]]]:
    """``positions[stage][point][frame] = (2,)``: corrected px (unregistered) or base px."""
    camera = _camera(result)
    out: dict[str, dict[str, dict[int, NDArray]]] = {s: {} for s in STAGES}
    for point, by_frame in marks.marks.items():
        for s in STAGES:
            out[s][point] = {}
        for k, xy in sorted(by_frame.items()):
            q = np.asarray([xy], float)
            out["unregistered"][point][k] = camera.corrected_from_raw(q)[0]
            for s in ("global", "local"):
                out[s][point][k] = np.asarray(result.frame_to_base(k, q, s), float)[0]
    return out


def evaluate_points(
    result: Any, marks: PointMarks, config: EvaluationConfig = EvaluationConfig()
) -> EvaluationReport:
    """Table 2 from hand-marked points (module docstring; file format: :func:`read_points_csv`).

    Raises:
        ValueError: with ``anchor="reference"`` a point not marked in the reference frame.
    """
    ref = int(result.reference_frame)
    if config.anchor == "reference":
        for point in marks.order:
            if ref not in marks.marks[point]:
                raise ValueError(
                    f"point {point!r} is not marked in the reference frame {ref} "
                    "(needed to measure motion from it; or use the mean anchor)"
                )
    pos = point_positions(result, marks)
    locations = marks.locations
    motions: dict[str, dict[str, list[float]]] = {s: {} for s in STAGES}
    used: dict[str, list[int]] = {}
    by_frame: dict[int, dict[str, list[float]]] = {}
    for point in locations:
        frames = sorted(marks.marks[point])
        used[point] = [k for k in frames if not (config.anchor == "reference" and k == ref)]
        for s in STAGES:
            p = np.array([pos[s][point][k] for k in frames])
            if config.anchor == "reference":
                anchor = pos[s][point][ref]
            else:
                ok = np.isfinite(p).all(axis=1)
                anchor = p[ok].mean(axis=0) if ok.any() else np.full(2, np.nan)
            d = np.linalg.norm(p - anchor, axis=1)
            vals = []
            for k, v in zip(frames, d, strict=True):
                if config.anchor == "reference" and k == ref:
                    continue
                vals.append(float(v))
                by_frame.setdefault(k, {t: [] for t in STAGES})[s].append(float(v))
            motions[s][point] = vals
    table = table2_from_motions(motions, locations, used)
    per_frame = []
    pooled: dict[str, list[NDArray]] = {s: [] for s in STAGES}
    for k in sorted(by_frame):
        rec: dict[str, Any] = {"frame": k, "status": _status(result, k)}
        rec["n_points"] = len(by_frame[k]["global"])
        for s in STAGES:
            v = np.asarray(by_frame[k][s], float)
            rec[s] = error_stats(v)
            pooled[s].append(v[np.isfinite(v)])
        per_frame.append(rec)
    return EvaluationReport(
        mode="points",
        table=table,
        per_frame=per_frame,
        summary=_summary(pooled, per_frame),
        excursions=_excursions(per_frame, config),
        definitions=_definitions("points", config),
        reference_frame=ref,
        n_frames=int(result.n_frames),
    )


@dataclass(frozen=True)
class PointProposal:
    """Where :func:`propose_point` found the point: ``xy`` (2,) px (NaN if not found) and the
    NCC ``score`` of the match."""

    xy: NDArray[np.float64]
    score: float


def propose_point(
    image_a: NDArray,
    xy: ArrayLike,
    image_b: NDArray,
    *,
    template_px: int = 41,
    search_px: int = 64,
    min_score: float = 0.5,
) -> PointProposal:
    """Propose the position in ``image_b`` of the point marked at ``xy`` in ``image_a`` (to help
    marking the same ground point in the next frame): normalised cross-correlation of a
    ``template_px`` template around ``xy`` over +-``search_px``, sub-pixel by a parabola fit.

    Args:
        image_a, image_b: ``(H, W[, 3])`` uint8 frames (e.g. consecutive raw frames).
        xy: ``(2,)`` the marked point in ``image_a``, px.

    Returns:
        A :class:`PointProposal`; ``xy`` is NaN when the template leaves ``image_a`` or the best
        score is below ``min_score``.
    """
    import cv2

    def grey(img):
        img = np.asarray(img)
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img

    a, b = grey(image_a), grey(image_b)
    x, y = (float(v) for v in np.asarray(xy, float).reshape(2))
    nan = PointProposal(np.full(2, np.nan), float("nan"))
    ht = template_px // 2
    cx, cy = int(round(x)), int(round(y))
    if cx - ht < 0 or cy - ht < 0 or cx + ht + 1 > a.shape[1] or cy + ht + 1 > a.shape[0]:
        return nan
    tmpl = a[cy - ht : cy + ht + 1, cx - ht : cx + ht + 1]
    x0, y0 = max(cx - ht - search_px, 0), max(cy - ht - search_px, 0)
    x1 = min(cx + ht + search_px + 1, b.shape[1])
    y1 = min(cy + ht + search_px + 1, b.shape[0])
    if x1 - x0 < tmpl.shape[1] or y1 - y0 < tmpl.shape[0] or float(tmpl.std()) < 1e-6:
        return nan
    res = cv2.matchTemplate(b[y0:y1, x0:x1], tmpl, cv2.TM_CCOEFF_NORMED)
    _, score, _, (px, py) = cv2.minMaxLoc(res)
    if score < min_score:
        return PointProposal(np.full(2, np.nan), float(score))
    sx = sy = 0.0
    if 0 < px < res.shape[1] - 1:
        sx = _parabola(res[py, px - 1], res[py, px], res[py, px + 1])
    if 0 < py < res.shape[0] - 1:
        sy = _parabola(res[py - 1, px], res[py, px], res[py + 1, px])
    # Template centre in b, plus the sub-pixel part of the marked point.
    bx = x0 + px + sx + ht + (x - cx)
    by = y0 + py + sy + ht + (y - cy)
    return PointProposal(np.array([bx, by]), float(score))


def _parabola(left: float, centre: float, right: float) -> float:
    den = left - 2.0 * centre + right
    if den >= 0:
        return 0.0
    return float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))


__all__ = [
    "PointProposal",
    "propose_point",
    "ANCHORS",
    "LOCATIONS",
    "STAGES",
    "EvaluationConfig",
    "EvaluationReport",
    "PointMarks",
    "Table2",
    "check_compatible",
    "error_stats",
    "evaluate_points",
    "evaluate_truth",
    "find_excursions",
    "ground_grid",
    "point_positions",
    "read_points_csv",
    "table2_from_motions",
    "table_frames",
    "table_points",
    "truth_errors",
]
