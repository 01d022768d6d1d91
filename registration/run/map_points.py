"""The analyst's map points of a result folder (``map_points.json``;
:mod:`registration.adjustment.map_points`): read them, and change them so that the sequence
adjustment takes them in.

Changing them makes every frame from the first adjustment window that holds a changed frame
not adjusted again; the next resumed run (``aerialreg register --resume``, the app's *Solve
again*) adjusts those frames, and reaches the same bits as an uninterrupted run that had the
points from the start: windows before that one never see the changed frames, and the frames they
made final are held as written.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from registration.adjustment import MapPoint, window_plan
from registration.io import write_json_atomic
from registration.run.config import config_from_dict
from registration.run.records import MAP_POINTS_JSON, _read_meta, read_record
from registration.run.result_folder import ResultLock
from registration.run.writer import ResultWriter


def read_map_points(out_dir: str | Path) -> list[MapPoint]:
    """The folder's map points, in the order they were given (none: ``[]``).

    Raises:
        ValueError: one line naming the file, when it cannot be read.
    """
    path = Path(out_dir) / MAP_POINTS_JSON
    if not path.is_file():
        return []
    try:
        return [MapPoint.from_json(p) for p in json.loads(path.read_text())["points"]]
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise ValueError(f"{path}: not a list of map points ({exc})") from None


def set_map_points(out_dir: str | Path, points: Sequence[MapPoint]) -> list[int]:
    """Make ``points`` the folder's map points (replacing those it had); returns the frames no
    longer adjusted (module docstring), which a resumed run adjusts again.

    Raises:
        ValueError: one line naming the point and the problem: a frame out of range, failed,
            the reference frame (fitted in the Seed view), a point outside the frame or the
            map, a folder made without the sequence adjustment; :class:`ResultBusy` while
            another process writes the folder.
    """
    out_dir = Path(out_dir)
    meta = _read_meta(out_dir)
    n, reference = int(meta["n_frames"]), int(meta["reference_frame"])
    adjust = config_from_dict(meta["config"]).adjust
    if adjust is None:
        raise ValueError(
            f"{out_dir} was registered without the sequence adjustment, which map points act "
            "through: register it with --adjust"
        )
    points = list(points)
    for p in points:
        _check(out_dir, meta, p, n, reference)
    lock = ResultLock(out_dir).acquire()
    try:
        old = read_map_points(out_dir)
        changed = {p.k for p in set(old) ^ set(points)}
        if not changed:
            return []
        start = min(
            w.start for w in window_plan(n, adjust) if any(w.start <= k < w.end for k in changed)
        )
        writer = ResultWriter(out_dir, lock)
        undone = []
        # Frames first, then the points: a run stopped between them leaves the old points
        # and frames to adjust again, never frames adjusted without the points said.
        for k in range(start, n):
            rec = read_record(out_dir, k)
            if rec.adjusted_model is None and "adjustment" not in rec.stats:
                continue
            stats = {name: v for name, v in rec.stats.items() if name != "adjustment"}
            writer.write_record(k, replace(rec, adjusted_model=None, stats=stats))
            undone.append(k)
        write_json_atomic(out_dir / MAP_POINTS_JSON, {"points": [p.to_json() for p in points]})
        return undone
    finally:
        lock.release()


def _check(out_dir: Path, meta: dict, p: MapPoint, n: int, reference: int) -> None:
    where = f"map point of frame {p.k}"
    if not 0 <= p.k < n:
        raise ValueError(f"{where}: no such frame (the result has frames 0..{n - 1})")
    if p.k == reference:
        raise ValueError(
            f"{where}: it is the reference frame, whose control points are edited in the Seed "
            "view (the mid base image every other frame is registered to is made of it)"
        )
    rec = read_record(out_dir, p.k)
    if not rec.ok:
        raise ValueError(
            f"{where}: it has no registration to correct ({rec.status}: {rec.reason}); "
            "register it again first"
        )
    for name, xy, (w, h) in (
        ("frame", p.frame_xy, meta["frame_size"]),
        ("map", p.base_xy, meta["base_size"]),
    ):
        if not (-0.5 <= xy[0] <= w - 0.5 and -0.5 <= xy[1] <= h - 0.5):
            raise ValueError(
                f"{where}: {name} point ({xy[0]:.1f}, {xy[1]:.1f}) is outside the {name} ({w} x {h} px)"
            )
