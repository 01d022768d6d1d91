"""``run_traffic``: a registered sequence's traffic into an output folder, resumable.

Layout of ``OUT``:

* ``traffic.json``: what the run is made of (the result's fingerprint, the settings, frame times
  and metric frame); written first. A later run into the same folder resumes only when these
  agree (else a one-line error: nothing stored is overwritten silently).
* ``detections/KKKKKK.json``: each usable frame's vehicle candidates, written atomically as
  found; a resumed run reads them instead of redoing the frame.
* ``tracks.csv``, ``tracksMeta.csv``, ``recordingMeta.csv``, ``tracks_wgs84.csv`` (with a CRS),
  ``trajectories.geojson``, ``trajectories.gpkg``, ``velocity_field.tif``, ``summary.json``:
  from the detections, every run (:mod:`registration.traffic.outputs`).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration.io import write_bytes_atomic
from registration.traffic.background import WorkGrid
from registration.traffic.config import TrafficConfig
from registration.traffic.outputs import (
    write_ind_csvs,
    write_trajectory_layers,
    write_velocity_field,
    write_wgs84_csv,
)
from registration.traffic.sequence import (
    detect_sequence,
    result_fingerprint,
    tracks_from_detections,
    usable_frames,
)
from registration.traffic.timing import MetricFrame, frame_times

FORMAT = "aerialreg-traffic"
VERSION = 1
# Fewer usable frames than this cannot make a background and a track.
MIN_FRAMES = 3


def _identity(
    result, config: TrafficConfig, times, time_source: str, metric: MetricFrame, exclude
) -> dict:
    excluded = None
    if exclude is not None:
        mask = np.ascontiguousarray(exclude, np.bool_)
        excluded = hashlib.sha256(repr(mask.shape).encode() + np.packbits(mask).tobytes())
    return {
        "format": FORMAT,
        "version": VERSION,
        "result": str(Path(result.out_dir).resolve()),
        "result_sha256": result_fingerprint(result),
        "config": config.to_dict(),
        "time_source": time_source,
        "times_sha256": hashlib.sha256(np.asarray(times).tobytes()).hexdigest(),
        "metric": metric.description,
        "exclude_sha256": None if excluded is None else excluded.hexdigest(),
    }


def _check_folder(out: Path, identity: dict) -> None:
    """Refuse (one line) a folder holding another run's traffic."""
    path = out / "traffic.json"
    if not path.is_file():
        if out.is_dir() and any(out.iterdir()):
            raise FileExistsError(
                f"{out} is not empty and holds no traffic run (no traffic.json); choose a new "
                "folder"
            )
        return
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        raise FileExistsError(f"{path} is unreadable; remove it or choose a new folder") from None
    for key, what in _IDENTITY_KEYS.items():
        if old.get(key) != identity.get(key):
            raise FileExistsError(
                f"{out} holds traffic of another run ({what}); choose a new folder or remove it"
            )


# What must agree for a run to resume in a folder, and how to say that it does not.
_IDENTITY_KEYS = {
    "format": "another format",
    "result_sha256": "the registration result differs",
    "config": "the settings differ",
    "times_sha256": "the frame times differ",
    "metric": "the metric frame differs",
    "exclude_sha256": "the excluded regions differ",
}


def find_traffic(
    result,
    frames,
    folder: Path,
    metric: MetricFrame,
    times: NDArray[np.float64],
    use: list[int],
    config: TrafficConfig,
    *,
    exclude: NDArray[np.bool_] | None = None,
    progress: Callable[[int, int], None] | None = None,
    cancel: Callable[[], bool] | None = None,
):
    """Detections (stored in ``folder``, :func:`detect_sequence`) and tracks of ``result``'s
    usable frames ``use``: ``(tracks, sizes, detections, grid)``
    (:func:`tracks_from_detections`), or None when ``cancel`` stopped it first. ``result``
    needs only the result interface (``frame_to_base``, ``base_to_frame``, ``frame_size``,
    ``base_size``, ``reference_frame``): the benchmark runs it on plain OpenCV's homographies.
    ``exclude``: a base-sized bool mask (:func:`run_traffic`)."""
    grid = WorkGrid.for_result(
        result, result.reference_frame, metric.metres_per_base_px(), config.cell_m
    )
    mask = None
    if exclude is not None:
        import cv2

        mask = cv2.resize(exclude.astype(np.uint8), grid.size, interpolation=cv2.INTER_NEAREST)
        mask = mask.astype(bool)
    detections = dict(
        detect_sequence(
            result, frames, grid, metric, times, use, config, folder,
            exclude=mask, progress=progress, cancel=cancel,
        )
    )  # fmt: skip
    if len(detections) < len(use):
        return None
    tracks, sizes = tracks_from_detections(detections, use, times, metric, config)
    return tracks, sizes, detections, grid


def run_traffic(
    result,
    frames,
    out: str | Path,
    *,
    fps: float | None = None,
    gsd_m: float | None = None,
    config: TrafficConfig | None = None,
    exclude=None,
    progress: Callable[[int, int], None] | None = None,
    cancel: Callable[[], bool] | None = None,
) -> dict:
    """Detect, track and write the traffic of ``result`` (a loaded registration result) seen in
    ``frames`` (its frame source) into ``out``; returns the summary (also ``summary.json``).

    Args:
        fps: frame rate (frames/s) when the frames carry no timestamps (images), or to override
            a video's.
        gsd_m: metres per base pixel when the base has no projected CRS in metres.
        exclude: ``(H, W)`` bool mask over the base map of places never to look for vehicles
            (the analyst's regions: car parks, a roof that shimmers), or None.
        progress: ``progress(done, total)`` per frame.
        cancel: polled between blocks; the run stops (what it stored stays) when it says True.

    Raises:
        ValueError: one line: no usable frames, unknown frame times or metres, bad settings.
        FileExistsError: ``out`` holds something else (one line).
    """
    config = config or TrafficConfig()
    config.validate()
    out = Path(out)
    metric = MetricFrame.for_result(result.georef, gsd_m)
    video = getattr(frames, "video_path", None)
    times, time_source = frame_times(result.n_frames, video=video, fps=fps)
    use, skipped = usable_frames(result)
    if len(use) < MIN_FRAMES:
        raise ValueError(
            f"{len(use)} usable frame(s) of {result.n_frames} in {result.out_dir} (failed or "
            f"flagged: {len(skipped)}); traffic needs at least {MIN_FRAMES}"
        )
    if exclude is not None and tuple(np.shape(exclude)) != tuple(result.base_size[::-1]):
        h, w = np.shape(exclude)[:2]
        raise ValueError(
            f"excluded regions are a {w}x{h} mask, the base map is "
            f"{result.base_size[0]}x{result.base_size[1]}"
        )
    identity = _identity(result, config, times, time_source, metric, exclude)
    _check_folder(out, identity)
    out.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(out / "traffic.json", json.dumps(identity, indent=1).encode() + b"\n")
    found = find_traffic(
        result, frames, out / "detections", metric, times, use, config,
        exclude=exclude, progress=progress, cancel=cancel,
    )  # fmt: skip
    if found is None:
        done = len(list((out / "detections").glob("*.json")))
        return {"out": str(out), "cancelled": True, "frames_done": done}
    tracks, sizes, detections, grid = found
    span = float(times[use[-1]] - times[use[0]])
    rate = (len(use) - 1) / span if span > 0 else float("nan")
    files = write_ind_csvs(out, tracks, sizes, metric, rate, span, time_source)
    files += [p for p in [write_wgs84_csv(out, tracks, metric)] if p is not None]
    files += write_trajectory_layers(out, tracks, metric)
    files.append(
        write_velocity_field(out, tracks, metric, config.field_cell_m, config.field_min_count)
    )
    speeds = np.concatenate([t.speed for t in tracks]) if tracks else np.zeros(0)
    summary = {
        "out": str(out),
        "n_frames": result.n_frames,
        "n_used": len(use),
        "skipped": {str(k): why for k, why in sorted(skipped.items())},
        "n_detections": int(sum(len(d) for d in detections.values())),
        "n_tracks": len(tracks),
        "median_speed_mps": float(np.median(speeds)) if len(speeds) else None,
        "time_source": time_source,
        "metric": metric.description,
        "cell_m": round(metric.metres_per_base_px() * grid.cell_base_px, 4),
        "files": [p.name for p in files],
    }
    write_bytes_atomic(out / "summary.json", json.dumps(summary, indent=1).encode() + b"\n")
    return summary
