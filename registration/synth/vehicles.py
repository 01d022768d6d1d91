"""The simulator's moving vehicles as truth: each vehicle's trajectory, frame by frame.

:func:`simulate` writes ``vehicles.csv`` beside ``truth.json`` (one row per vehicle per frame
whose centre the frame sees), in *scene* pixels, so a copy with another base map
(:func:`~registration.synth.rebase`) stays exact: :meth:`SimTruth.vehicles` maps the rows into
that copy's base pixels. Times are each frame's mid-exposure, the instant the renderer paints the
vehicles at (:class:`~registration.synth.render.FrameRenderer`).

Columns: ``frame``, ``time_s``, ``track_id`` (one trajectory: a vehicle between two wraps at the
city's edge, :func:`~registration.synth.city.traffic_states`), ``vehicle``, ``x_scene``,
``y_scene`` (centre, scene px), ``dx``, ``dy`` (unit direction of travel in the scene),
``speed_mps``, ``length_m``, ``width_m``.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration.synth import city as citymod

VEHICLES_NAME = "vehicles.csv"
COLUMNS = (
    "frame",
    "time_s",
    "track_id",
    "vehicle",
    "x_scene",
    "y_scene",
    "dx",
    "dy",
    "speed_mps",
    "length_m",
    "width_m",
)
# A wrap at the city's edge starts a new trajectory: track_id = vehicle * LAPS + lap mod LAPS.
LAPS = 1000


def moving_vehicles(layout, cfg, t: float) -> dict[str, NDArray]:
    """The flight's moving vehicles at time ``t`` (s), as ``cfg`` (a :class:`SimConfig`) drives
    them: :func:`~registration.synth.city.traffic_states` with its traffic and spacing."""
    return citymod.traffic_states(
        layout, cfg.seed, cfg.traffic_per_km, t, cfg.vehicle_gap_m, cfg.vehicle_headway_s
    )


def frame_vehicles(layout, cfg, geom, k: int) -> dict[str, NDArray]:
    """The vehicles frame ``k`` sees (centre inside the raw frame) at its mid-exposure, as
    :func:`~registration.synth.city.traffic_states` arrays plus ``time_s`` and ``track_id``."""
    t_mid = float(geom.frame_times[k] + 0.5 * geom.readout_s)
    v = moving_vehicles(layout, cfg, t_mid)
    centres = np.column_stack([v["x"], v["y"]])
    raw = geom.raw_from_scene(k, centres) if len(centres) else np.zeros((0, 2))
    with np.errstate(invalid="ignore"):
        seen = np.isfinite(raw).all(axis=1) & geom.in_frame(raw)
    out = {key: np.asarray(a)[seen] for key, a in v.items()}
    out["time_s"] = np.full(int(seen.sum()), t_mid)
    out["track_id"] = out["vehicle"] * LAPS + np.mod(out["lap"], LAPS)
    return out


def vehicle_rows(layout, cfg, geom, k: int) -> list[list]:
    """Rows of ``vehicles.csv`` for frame ``k`` (:data:`COLUMNS`)."""
    v = frame_vehicles(layout, cfg, geom, k)
    gsd = float(cfg.gsd_m)
    rows = []
    for i in range(len(v["x"])):
        along = float(v["direction"][i])
        dx, dy = (along, 0.0) if v["axis"][i] == 0 else (0.0, along)
        rows.append(
            [
                k,
                f"{v['time_s'][i]:.6f}",
                int(v["track_id"][i]),
                int(v["vehicle"][i]),
                f"{v['x'][i]:.4f}",
                f"{v['y'][i]:.4f}",
                dx,
                dy,
                f"{v['speed'][i] * gsd:.5f}",
                f"{v['length'][i] * gsd:.4f}",
                f"{v['width'][i] * gsd:.4f}",
            ]
        )
    return rows


def vehicles_csv(rows: list[list]) -> bytes:
    """``vehicles.csv``'s bytes: header :data:`COLUMNS`, then ``rows``."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    w.writerows(rows)
    return buf.getvalue().encode()


def read_vehicles(path: str | os.PathLike) -> dict[str, NDArray]:
    """``vehicles.csv`` as one array per column (ints for ``frame``, ``track_id``,
    ``vehicle``; floats otherwise). One-line ValueError when a column is missing."""
    path = Path(path)
    with open(path, newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or any(c not in header for c in COLUMNS):
            missing = [c for c in COLUMNS if header is None or c not in header]
            raise ValueError(f"{path} is not a vehicle truth file: missing column(s) {missing}")
        rows = list(reader)
    idx = {c: header.index(c) for c in COLUMNS}
    out = {}
    for c in COLUMNS:
        kind = np.int64 if c in ("frame", "track_id", "vehicle") else np.float64
        out[c] = np.array([r[idx[c]] for r in rows], dtype=kind if rows else None).astype(kind)
    return out
