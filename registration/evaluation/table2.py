"""The paper's Table 2 (section 6) and what the evaluation measures: its settings, the table and how
it is built from motions.

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
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

STAGES = ("unregistered", "global", "local")
STAGE_LABELS = {"unregistered": "Unregistered", "global": "Post-Global", "local": "Post-Local"}
LOCATIONS = ("NW", "NE", "Center", "SW", "SE")
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


@dataclass(frozen=True)
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
