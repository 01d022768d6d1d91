"""Files researchers load: inD/rounD-style ``tracks.csv``, ``tracksMeta.csv`` and
``recordingMeta.csv``; ``tracks_wgs84.csv`` (latitude and longitude, with a CRS); trajectory
layers as GeoJSON and GeoPackage; and the velocity field as a GeoTIFF.

Positions are in the metric frame of the run (:class:`~registration.traffic.timing.MetricFrame`:
the map's projected CRS in metres, or base px x GSD with y up), so ``xUtmOrigin`` and
``yUtmOrigin`` are 0. Every file is written atomically.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration.gis.vector import Layer, write_geojson, write_geopackage
from registration.io import atomic_path, write_bytes_atomic
from registration.traffic.timing import MetricFrame
from registration.traffic.track import SmoothTrack

TRACK_COLUMNS = (
    "recordingId",
    "trackId",
    "frame",
    "trackLifetime",
    "xCenter",
    "yCenter",
    "heading",
    "width",
    "length",
    "xVelocity",
    "yVelocity",
    "xAcceleration",
    "yAcceleration",
    "lonVelocity",
    "latVelocity",
    "lonAcceleration",
    "latAcceleration",
)
META_COLUMNS = (
    "recordingId",
    "trackId",
    "initialFrame",
    "finalFrame",
    "numFrames",
    "width",
    "length",
    "class",
    "meanSpeed",
    "maxSpeed",
    "observedFraction",
)
RECORDING_COLUMNS = (
    "recordingId",
    "frameRate",
    "duration",
    "numTracks",
    "numVehicles",
    "numVRUs",
    "latLocation",
    "lonLocation",
    "xUtmOrigin",
    "yUtmOrigin",
    "orthoPxToMeter",
    "crs",
    "timeSource",
)


def _csv(rows: list, header) -> bytes:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue().encode()


def track_heading_deg(track: SmoothTrack) -> NDArray[np.float64]:
    """Direction of travel per row, degrees counter-clockwise from +x (east) in [0, 360); where
    the vehicle stands (< 0.5 m/s) the last direction it moved in."""
    v = track.velocity
    ang = np.degrees(np.arctan2(v[:, 1], v[:, 0])) % 360.0
    moving = np.linalg.norm(v, axis=1) >= 0.5
    if moving.any():
        idx = np.maximum.accumulate(np.where(moving, np.arange(len(v)), -1))
        first = int(np.argmax(moving))
        idx[idx < 0] = first
        ang = ang[idx]
    return ang


def write_ind_csvs(
    out: Path,
    tracks: list[SmoothTrack],
    sizes: dict[int, tuple[float, float]],
    metric: MetricFrame,
    frame_rate: float,
    duration_s: float,
    time_source: str,
    recording_id: int = 1,
) -> list[Path]:
    """``tracks.csv``, ``tracksMeta.csv`` and ``recordingMeta.csv`` (inD's columns; inD's
    ``class`` is "car" or "truck_bus" by length here, the blobs carry no more). ``sizes``:
    ``{track_id: (width m, length m)}``."""
    rows, meta = [], []
    for tr in tracks:
        heading = track_heading_deg(tr)
        h = np.radians(heading)
        fwd = np.column_stack([np.cos(h), np.sin(h)])
        left = np.column_stack([-np.sin(h), np.cos(h)])
        lon_v = (tr.velocity * fwd).sum(1)
        lat_v = (tr.velocity * left).sum(1)
        lon_a = (tr.acceleration * fwd).sum(1)
        lat_a = (tr.acceleration * left).sum(1)
        width, length = sizes.get(tr.track_id, (float("nan"), float("nan")))
        for i, k in enumerate(tr.frames.tolist()):
            rows.append(
                [recording_id, tr.track_id, k, i, f"{tr.xy[i, 0]:.3f}", f"{tr.xy[i, 1]:.3f}"]
                + [f"{heading[i]:.2f}", f"{width:.2f}", f"{length:.2f}"]
                + [f"{a:.3f}" for a in (*tr.velocity[i], *tr.acceleration[i])]
                + [f"{a:.3f}" for a in (lon_v[i], lat_v[i], lon_a[i], lat_a[i])]
            )
        speed = tr.speed
        meta.append(
            [recording_id, tr.track_id, int(tr.frames[0]), int(tr.frames[-1]), len(tr.frames)]
            + [f"{width:.2f}", f"{length:.2f}", "truck_bus" if length > 7.0 else "car"]
            + [f"{speed.mean():.3f}", f"{speed.max():.3f}", f"{tr.observed.mean():.3f}"]
        )
    lat = lon = float("nan")
    if metric.georef is not None and metric.georef.crs is not None and tracks:
        centre = np.concatenate([t.xy for t in tracks]).mean(axis=0, keepdims=True)
        lon, lat = metric.georef.to_crs(centre, 4326)[0]
    recording = [
        recording_id,
        f"{frame_rate:.4f}",
        f"{duration_s:.3f}",
        len(tracks),
        len(tracks),
        0,
        f"{lat:.7f}",
        f"{lon:.7f}",
        0,
        0,
        f"{metric.metres_per_base_px():.5f}",
        metric.description,
        time_source,
    ]
    paths = [out / "tracks.csv", out / "tracksMeta.csv", out / "recordingMeta.csv"]
    write_bytes_atomic(paths[0], _csv(rows, TRACK_COLUMNS))
    write_bytes_atomic(paths[1], _csv(meta, META_COLUMNS))
    write_bytes_atomic(paths[2], _csv([recording], RECORDING_COLUMNS))
    return paths


def write_wgs84_csv(out: Path, tracks: list[SmoothTrack], metric: MetricFrame) -> Path | None:
    """``tracks_wgs84.csv`` (trackId, frame, time, latitude, longitude, speed, heading) where the
    map has a CRS; None without one."""
    if metric.georef is None or metric.georef.crs is None:
        return None
    rows = []
    for tr in tracks:
        ll = metric.georef.to_crs(tr.xy, 4326)
        heading = track_heading_deg(tr)
        for i, k in enumerate(tr.frames.tolist()):
            rows.append(
                [tr.track_id, k, f"{tr.times[i]:.4f}", f"{ll[i, 1]:.8f}", f"{ll[i, 0]:.8f}"]
                + [f"{tr.speed[i]:.3f}", f"{heading[i]:.2f}"]
            )
    path = out / "tracks_wgs84.csv"
    header = ("trackId", "frame", "time", "latitude", "longitude", "speed", "heading")
    write_bytes_atomic(path, _csv(rows, header))
    return path


def trajectory_layer(tracks: list[SmoothTrack], metric: MetricFrame) -> Layer:
    """One LineString per track in the metric frame's coordinates, with id, frames, duration
    and speeds as properties."""
    geoms, props = [], []
    for tr in tracks:
        geoms.append(np.asarray(tr.xy, np.float64))
        props.append(
            {
                "track_id": int(tr.track_id),
                "first_frame": int(tr.frames[0]),
                "last_frame": int(tr.frames[-1]),
                "duration_s": round(float(tr.times[-1] - tr.times[0]), 3),
                "mean_speed_mps": round(float(tr.speed.mean()), 3),
                "max_speed_mps": round(float(tr.speed.max()), 3),
            }
        )
    return Layer("trajectories", "LineString", geoms, props)


def write_trajectory_layers(
    out: Path, tracks: list[SmoothTrack], metric: MetricFrame
) -> list[Path]:
    """``trajectories.geojson`` and ``trajectories.gpkg`` in the map's CRS (a local metric
    frame without one)."""
    layer = trajectory_layer(tracks, metric)
    crs_wkt = metric.georef.crs_wkt if metric.georef is not None else None
    return [
        write_geojson(out / "trajectories.geojson", layer, crs_wkt),
        write_geopackage(out / "trajectories.gpkg", [layer], crs_wkt),
    ]


def velocity_field(
    tracks: list[SmoothTrack], cell_m: float, min_count: int
) -> tuple[NDArray[np.float32], tuple[float, float]]:
    """The companion paper's velocity field: per ``cell_m`` square cell, the mean velocity
    ``(vx, vy)``, the mean speed, the speed's standard deviation and the number of track points
    (``(5, H, W)`` float32, NaN where fewer than ``min_count``) and the metric coordinates
    ``(x0, y_top)`` of the grid's top-left corner."""
    pts = np.concatenate([t.xy for t in tracks]) if tracks else np.zeros((0, 2))
    vel = np.concatenate([t.velocity for t in tracks]) if tracks else np.zeros((0, 2))
    if not len(pts):
        return np.full((5, 1, 1), np.nan, np.float32), (0.0, 0.0)
    x0 = math.floor(pts[:, 0].min() / cell_m) * cell_m
    y_top = math.ceil(pts[:, 1].max() / cell_m) * cell_m
    col = ((pts[:, 0] - x0) // cell_m).astype(int)
    row = ((y_top - pts[:, 1]) // cell_m).astype(int)
    h, w = row.max() + 1, col.max() + 1
    idx = row * w + col
    n = np.bincount(idx, minlength=h * w).astype(np.float64)
    speed = np.linalg.norm(vel, axis=1)
    sums = [np.bincount(idx, weights=a, minlength=h * w) for a in (vel[:, 0], vel[:, 1], speed)]
    sq = np.bincount(idx, weights=speed**2, minlength=h * w)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = [s / n for s in sums]
        std = np.sqrt(np.maximum(sq / n - mean[2] ** 2, 0.0))
    bands = np.stack([*mean, std, n]).reshape(5, h, w).astype(np.float32)
    bands[:4, (n < min_count).reshape(h, w)] = np.nan
    return bands, (float(x0), float(y_top))


def write_velocity_field(
    out: Path, tracks: list[SmoothTrack], metric: MetricFrame, cell_m: float, min_count: int
) -> Path:
    """``velocity_field.tif``: five float32 bands (``vx``, ``vy`` m/s, mean speed, speed
    spread m/s, count) on a ``cell_m`` grid, georeferenced in the map's CRS (no CRS in a local
    metric frame)."""
    import rasterio
    from rasterio.transform import from_origin

    bands, (x0, y_top) = velocity_field(tracks, cell_m, min_count)
    path = out / "velocity_field.tif"
    crs = metric.georef.crs_wkt if metric.georef is not None else None
    with atomic_path(path) as tmp:
        with rasterio.open(
            tmp,
            "w",
            driver="GTiff",
            width=bands.shape[2],
            height=bands.shape[1],
            count=5,
            dtype="float32",
            crs=crs,
            transform=from_origin(x0, y_top, cell_m, cell_m),
            nodata=float("nan"),
            compress="deflate",
        ) as dst:
            dst.write(bands)
            for i, name in enumerate(("vx_mps", "vy_mps", "speed_mps", "speed_std_mps", "count")):
                dst.set_band_description(i + 1, name)
    return path


@dataclass(frozen=True)
class TrackRows:
    """One track as ``tracks.csv`` holds it: ``frames`` ``(M,)``, ``xy_m`` ``(M, 2)`` metres in
    the run's metric frame, ``velocity`` ``(M, 2)`` m/s, ``width_m`` and ``length_m``."""

    track_id: int
    frames: NDArray[np.int64]
    xy_m: NDArray[np.float64]
    velocity: NDArray[np.float64]
    width_m: float
    length_m: float

    @property
    def speed(self) -> NDArray[np.float64]:
        return np.hypot(self.velocity[:, 0], self.velocity[:, 1])


def read_tracks_csv(path: str | Path) -> list[TrackRows]:
    """The tracks of a ``tracks.csv`` this stage wrote (:func:`write_ind_csvs`), by track id.

    Raises:
        ValueError: one line, for a file without inD's track columns or with a bad value.
    """
    from registration.io import read_text_file

    rows = list(csv.DictReader(read_text_file(path, "tracks file").splitlines()))
    need = ("trackId", "frame", "xCenter", "yCenter", "xVelocity", "yVelocity", "width", "length")
    if rows and any(c not in rows[0] for c in need):
        missing = next(c for c in need if c not in rows[0])
        raise ValueError(f"{Path(path).name} has no column {missing!r}: not a tracks.csv")
    by_id: dict[int, list[dict]] = {}
    try:
        for r in rows:
            by_id.setdefault(int(r["trackId"]), []).append(r)
        out = []
        for tid in sorted(by_id):
            rs = sorted(by_id[tid], key=lambda r: int(r["frame"]))
            out.append(
                TrackRows(
                    track_id=tid,
                    frames=np.array([int(r["frame"]) for r in rs], np.int64),
                    xy_m=np.array([[float(r["xCenter"]), float(r["yCenter"])] for r in rs]),
                    velocity=np.array([[float(r["xVelocity"]), float(r["yVelocity"])] for r in rs]),
                    width_m=float(rs[0]["width"]),
                    length_m=float(rs[0]["length"]),
                )
            )
    except ValueError as exc:
        raise ValueError(f"{Path(path).name}: {exc}") from None
    return out
