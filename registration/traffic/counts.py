"""Counts per road section (beyond the paper): how many tracked vehicles crossed a line the
analyst drew across a road, in each direction, and how fast.

A section is a segment ``a -> b`` in the run's metric frame (metres, x east, y north:
:class:`registration.traffic.MetricFrame`). A track crosses it where the straight step between
two consecutive positions of the track meets the segment; the crossing's frame, speed and
heading are interpolated along that step. Direction 1 is from the left of ``a -> b`` to its
right, direction 2 the other way; each direction is also named by the compass heading its
vehicles travel on average. A vehicle that turns back over the line is counted each time.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.io import write_bytes_atomic
from registration.traffic.outputs import TrackRows, _csv

COMPASS = ("N", "NE", "E", "SE", "S", "SW", "W", "NW")
COUNT_COLUMNS = (
    "section", "direction", "heading", "count", "meanSpeed", "firstFrame", "lastFrame",
)  # fmt: skip
CROSSING_COLUMNS = ("section", "direction", "trackId", "frame", "speed", "heading")


@dataclass(frozen=True)
class Crossing:
    """Track ``track_id`` crossed the section at ``frame`` (interpolated) in ``direction``
    (1: from the left of ``a -> b`` to its right; 2: back), at ``speed_mps``, heading
    ``heading_deg`` (clockwise from north)."""

    track_id: int
    frame: float
    direction: int
    speed_mps: float
    heading_deg: float


@dataclass(frozen=True)
class SectionCounts:
    """The crossings of section ``name`` (``a``, ``b``: its ends, metres), in frame order."""

    name: str
    a: tuple[float, float]
    b: tuple[float, float]
    crossings: tuple[Crossing, ...]

    def direction(self, d: int) -> tuple[int, float, str]:
        """``(count, mean speed m/s, compass heading)`` of direction ``d`` (``(0, nan, "")``
        without crossings)."""
        cs = [c for c in self.crossings if c.direction == d]
        if not cs:
            return 0, float("nan"), ""
        return (
            len(cs),
            float(np.mean([c.speed_mps for c in cs])),
            compass([c.heading_deg for c in cs]),
        )


def compass(headings_deg: ArrayLike) -> str:
    """The 8-point compass name of the circular mean of ``headings_deg`` (clockwise from
    north)."""
    h = np.radians(np.asarray(headings_deg, float))
    mean = np.degrees(np.arctan2(np.sin(h).sum(), np.cos(h).sum())) % 360.0
    return COMPASS[int(round(mean / 45.0)) % 8]


def count_crossings(
    tracks: list[TrackRows], name: str, a: ArrayLike, b: ArrayLike
) -> SectionCounts:
    """The crossings of the section ``a -> b`` (metres, ``(2,)`` each) by ``tracks``.

    Raises:
        ValueError: one line, for a section shorter than a centimetre or not finite.
    """
    a, b = np.asarray(a, float).reshape(2), np.asarray(b, float).reshape(2)
    ab = b - a
    if not (np.isfinite(ab).all() and np.hypot(*ab) >= 0.01):
        raise ValueError(f"section {name}: its ends must be two distinct points, got {a}, {b}")
    found = []
    for tr in tracks:
        p = np.asarray(tr.xy_m, float)
        if len(p) < 2:
            continue
        side = _cross(ab, p - a)  # > 0: left of a -> b (x east, y north)
        q0, q1 = p[:-1], p[1:]
        step = q1 - q0
        # The step q0 -> q1 meets the line where side changes sign (q1 may lie on it; q0 on it
        # counts for the step before, so a vehicle on the line is counted once).
        change = (side[:-1] != 0) & (np.sign(side[:-1]) != np.sign(side[1:]))
        for i in np.flatnonzero(change):
            t = side[i] / (side[i] - side[i + 1])
            hit = q0[i] + t * step[i]
            s = float(np.dot(hit - a, ab) / np.dot(ab, ab))
            if not 0.0 <= s <= 1.0:
                continue
            v = (1 - t) * tr.velocity[i] + t * tr.velocity[i + 1]
            found.append(Crossing(
                int(tr.track_id),
                float((1 - t) * tr.frames[i] + t * tr.frames[i + 1]),
                1 if side[i] > 0 else 2,
                float(np.hypot(*v)),
                float(np.degrees(np.arctan2(v[0], v[1])) % 360.0),
            ))  # fmt: skip
    found.sort(key=lambda c: (c.frame, c.track_id))
    return SectionCounts(name, (float(a[0]), float(a[1])), (float(b[0]), float(b[1])), tuple(found))


def count_sections(tracks: list[TrackRows], metric, sections) -> list[SectionCounts]:
    """:func:`count_crossings` of each ``(name, a, b)`` in ``sections``, whose ends are base px
    (as the analyst draws them), through the run's ``metric`` frame
    (:class:`registration.traffic.MetricFrame`)."""
    out = []
    for name, a, b in sections:
        ends = metric.metres_from_base(np.array([a, b], float))
        out.append(count_crossings(tracks, name, ends[0], ends[1]))
    return out


def _cross(u: NDArray, v: NDArray) -> NDArray:
    """z of ``u x v`` for ``u`` ``(2,)`` and ``v`` ``(N, 2)``."""
    return u[0] * v[:, 1] - u[1] * v[:, 0]


def write_counts_csvs(out: Path, sections: list[SectionCounts]) -> tuple[Path, Path]:
    """``counts.csv`` (per section and direction: heading, count, mean speed m/s, first and
    last frame) and ``crossings.csv`` (one row per crossing) in ``out``, atomically."""
    out = Path(out)
    rows, crossing_rows = [], []
    for sec in sections:
        for d in (1, 2):
            n, speed, heading = sec.direction(d)
            frames = [c.frame for c in sec.crossings if c.direction == d]
            rows.append([
                sec.name, d, heading, n, "" if not n else f"{speed:.3f}",
                "" if not n else f"{min(frames):.2f}", "" if not n else f"{max(frames):.2f}",
            ])  # fmt: skip
        crossing_rows += [
            [sec.name, c.direction, c.track_id, f"{c.frame:.2f}", f"{c.speed_mps:.3f}",
             f"{c.heading_deg:.1f}"]
            for c in sec.crossings
        ]  # fmt: skip
    paths = (out / "counts.csv", out / "crossings.csv")
    write_bytes_atomic(paths[0], _csv(rows, COUNT_COLUMNS))
    write_bytes_atomic(paths[1], _csv(crossing_rows, CROSSING_COLUMNS))
    return paths
