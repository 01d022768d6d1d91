"""Counts per road section (``registration.traffic.counts``) on tracks of known motion: each
crossing found once, in the right direction, at the interpolated frame, speed and heading; a
track passing beyond the section's end or turning back counted as it should; the CSVs say
it."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from registration.traffic import TrackRows, count_crossings, write_counts_csvs
from registration.traffic.counts import compass


def _track(tid: int, xy, velocity, first_frame: int = 0) -> TrackRows:
    xy = np.asarray(xy, float)
    v = np.broadcast_to(np.asarray(velocity, float), xy.shape).copy()
    frames = np.arange(first_frame, first_frame + len(xy))
    return TrackRows(tid, frames, xy, v, 1.8, 4.5)


# A section across an east-west road, drawn from (0, -5) to (0, 5): its left is the west.
A, B = (0.0, -5.0), (0.0, 5.0)


def test_crossings_by_direction_frame_speed_and_heading():
    east = _track(1, [[-7.5, 0.0], [-2.5, 0.0], [2.5, 0.0], [7.5, 0.0]], (5.0, 0.0), 10)
    west = _track(2, [[6.0, 2.0], [2.0, 2.0], [-2.0, 2.0]], (-4.0, 0.0), 30)
    beyond = _track(3, [[-5.0, 8.0], [5.0, 8.0]], (10.0, 0.0))  # north of the section's end
    # On the line at a row: counted once, at that row's frame.
    on_line = _track(4, [[-3.0, -1.0], [0.0, -1.0], [3.0, -1.0]], (3.0, 0.0), 50)
    # East, then back west: once each way.
    u_turn = _track(
        5, [[-2.0, 4.0], [2.0, 4.0], [1.0, 4.0], [-1.0, 4.0]], [(4, 0)] * 2 + [(-2, 0)] * 2, 70
    )
    sec = count_crossings([east, west, beyond, on_line, u_turn], "S1", A, B)
    got = [(c.track_id, c.direction, round(c.frame, 3)) for c in sec.crossings]
    assert got == [(1, 1, 11.5), (2, 2, 31.5), (4, 1, 51.0), (5, 1, 70.5), (5, 2, 72.5)]
    by_id = {(c.track_id, c.direction): c for c in sec.crossings}
    assert by_id[(1, 1)].speed_mps == pytest.approx(5.0)
    assert by_id[(1, 1)].heading_deg == pytest.approx(90.0)
    assert by_id[(2, 2)].heading_deg == pytest.approx(270.0)
    assert sec.direction(1)[:1] == (3,) and sec.direction(1)[2] == "E"
    n, speed, heading = sec.direction(2)
    assert (n, heading) == (2, "W") and speed == pytest.approx((4.0 + 2.0) / 2)


def test_counts_csvs(tmp_path):
    east = _track(1, [[-2.0, 0.0], [2.0, 0.0]], (4.0, 0.0))
    north = _track(7, [[10.0, -2.0], [10.0, 2.0]], (0.0, 4.0), 5)
    sections = [
        count_crossings([east, north], "S1", A, B),
        count_crossings([east, north], "S2", (5.0, 0.0), (15.0, 0.0)),  # its left: north
    ]
    counts, crossings = write_counts_csvs(tmp_path, sections)
    rows = list(csv.DictReader(counts.open()))
    assert [(r["section"], r["direction"], r["heading"], r["count"]) for r in rows] == [
        ("S1", "1", "E", "1"), ("S1", "2", "", "0"), ("S2", "1", "", "0"), ("S2", "2", "N", "1"),
    ]  # fmt: skip
    assert rows[0]["meanSpeed"] == "4.000" and rows[3]["firstFrame"] == "5.50"
    rows = list(csv.DictReader(crossings.open()))
    assert [(r["section"], r["trackId"], r["heading"]) for r in rows] == [
        ("S1", "1", "90.0"), ("S2", "7", "0.0"),
    ]  # fmt: skip


def test_compass_and_bad_sections():
    assert (
        compass([350.0, 10.0]) == "N" and compass([135.0]) == "SE" and compass([200, 250]) == "SW"
    )
    with pytest.raises(ValueError, match=r"section S9: its ends must be two distinct points"):
        count_crossings([], "S9", (1.0, 1.0), (1.0, 1.0))
