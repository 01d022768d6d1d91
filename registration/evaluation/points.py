"""Hand-marked ground points (paper section 6): the ``POINTS.csv`` file the app and the CLI
share, the points' registered positions in every frame and Table 2 from them (proposals of where
a marked point lies in another frame: ``proposals``).
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

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
from registration.evaluation.table2 import LOCATIONS, STAGES, EvaluationConfig, table2_from_motions

POINTS_HEADER = ("point", "frame", "x", "y")
# A points file holds hand marks: the paper's five points in every frame of an hour at 5 frames/s
# is 90,000 lines, about 3 MiB. Parsed, a line costs ~900 bytes (a 20 MiB file took 820 MB and
# 17 s), so larger files are refused before reading.
MAX_POINTS_FILE_BYTES = 8 << 20


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
    text = read_text_file(p, "points file", max_bytes=MAX_POINTS_FILE_BYTES)
    name = p.name
    w, h = frame_size
    rows = [
        (i + 1, line)
        for i, line in enumerate(text.splitlines())
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not rows:
        raise ValueError(f"{name} is empty: expected the header 'point,frame,x,y' and rows")
    header, col = _points_header(name, *rows[0])
    marks: dict[str, dict[int, tuple[float, float]]] = {}
    where: dict[tuple[str, int], int] = {}
    order: list[str] = []
    for line_no, line in rows[1:]:
        point, k, x, y = _points_row(name, line_no, line, header, col, n_frames, w, h)
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


def _points_header(name: str, head_no: int, head_line: str) -> tuple[list[str], dict[str, int]]:
    """``(header, col)``: the lower-cased column names of the header line ``head_no`` of the
    file ``name``, and the index of each of ``POINTS_HEADER`` among them (ValueError when one
    is missing)."""
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
    return header, {c: header.index(c) for c in POINTS_HEADER}


def _points_row(
    name: str,
    line_no: int,
    line: str,
    header: list[str],
    col: dict[str, int],
    n_frames: int,
    w: int,
    h: int,
) -> tuple[str, int, float, float]:
    """``(point, frame, x, y)`` of the data line ``line_no`` of the file ``name``: a non-empty
    point name, a frame index in ``0..n_frames - 1`` and a finite position inside the
    ``w`` x ``h`` raw frame (px); ValueError naming the line and the value."""
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
        raise ValueError(f"{name} line {line_no}: frame must be an integer, got {ftxt!r}") from None
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
    return point, k, x, y


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
        rec.update(_adjustment(result, k))
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
