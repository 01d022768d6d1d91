"""The evaluation report: per-frame error statistics, sudden excursions (the paper's "occasional
sudden excursions", section 6), failed and damaged frames, and the report that carries Table 2.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.evaluation.table2 import STAGE_LABELS, STAGES, EvaluationConfig, Table2
from registration.lens import Camera

# A frame worse than this (base px, mean error at the local stage) should be flagged by the
# sequence adjustment (issue: "a frame likely to be worse than 2 px is flagged").
FLAG_CHECK_PX = 2.0

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


@dataclass(frozen=True)
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
        out += self._flag_lines()
        damaged = [p["frame"] for p in self.per_frame if p.get("status") == "damaged"]
        if damaged:
            out.append("")
            out.append(
                f"Frames with a damaged record (not evaluated; resuming the registration redoes "
                f"them): {', '.join(map(str, damaged))}"
            )
        return "\n".join(out) + "\n"

    def _flag_lines(self) -> list[str]:
        """The frames the sequence adjustment flagged, and, against the truth, how its flags
        fared: frames worse than :data:`FLAG_CHECK_PX` (mean error at the local stage) left
        unflagged, and good frames flagged."""
        adjusted = [p for p in self.per_frame if "predicted_error_px" in p]
        if not adjusted:
            return []
        flagged = [p for p in adjusted if p.get("flagged")]
        out = ["", "### Frames the sequence adjustment flagged", ""]
        out += [f"- frame {p['frame']}: {p['flagged']}" for p in flagged] or ["- none"]
        if self.mode == "truth":
            bad = [p for p in adjusted if ((p.get("local") or {}).get("mean") or 0) > FLAG_CHECK_PX]
            missed = [p["frame"] for p in bad if not p.get("flagged")]
            false = [p["frame"] for p in flagged if p not in bad]
            out += [
                "",
                f"Against the truth: {len(bad)} of {len(adjusted)} adjusted frames are worse than "
                f"{FLAG_CHECK_PX:g} px (mean, local stage); {len(missed)} of them unflagged "
                f"({', '.join(map(str, missed)) or 'none'}); {len(false)} good frames flagged "
                f"({', '.join(map(str, false)) or 'none'}).",
            ]
        return out

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
        adjusted = any("predicted_error_px" in p for p in self.per_frame)
        if adjusted:
            head += ["predicted_error_px", "flagged"]
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
            if adjusted:
                v = p.get("predicted_error_px")
                row += ["" if v is None else v, p.get("flagged", "")]
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


def _adjustment(result: Any, k: int) -> dict[str, Any]:
    """Frame ``k``'s predicted error and flag from the sequence adjustment (empty without)."""
    records = getattr(result, "records", None)
    if records is None or not 0 <= k < len(records) or not records[k].ok:
        return {}
    a = records[k].stats.get("adjustment")
    if not isinstance(a, dict):
        return {}
    return {"predicted_error_px": a.get("predicted_error_px"), "flagged": a.get("flagged", "")}


def _status(result: Any, k: int) -> str:
    records = getattr(result, "records", None)
    if records is not None:
        try:
            return records[k].status
        except IndexError:
            return "ok"
    return "ok"


def _camera(result: Any) -> Camera:
    camera = getattr(result, "camera", None)
    if isinstance(camera, Camera):
        return camera
    w, hh = result.frame_size
    return Camera(float(result.gamma), int(w), int(hh))


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
