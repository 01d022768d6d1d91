"""The traffic stage over a whole registered sequence: which frames to use, their backgrounds in
blocks, detections frame by frame (written as they are found, so a run resumes), then tracks.

:func:`detect_sequence` is the heavy part (one resampling per frame, one median per block);
:func:`tracks_from_detections` is cheap and always redone from the stored detections.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration.io import write_bytes_atomic
from registration.traffic.background import (
    WarpedFrame,
    WorkGrid,
    frame_keep_mask,
    median_background,
    needed_pixels,
    union_box,
    warp_frame,
)
from registration.traffic.config import TrafficConfig
from registration.traffic.detect import Detection, detect_vehicles
from registration.traffic.timing import MetricFrame
from registration.traffic.track import (
    RawTrack,
    SmoothTrack,
    blob_noise,
    lost_end_noise,
    smooth_track,
    track_detections,
)

# Frames sharing one background: their median is computed once (at 30 frames/s a block is 12
# frames; a car moves 4 m in it, far less than the ±2.4 s the samples span).
BLOCK_S = 0.4


def usable_frames(result) -> tuple[list[int], dict[int, str]]:
    """``(frames to use, {frame: why not})``: registered frames the sequence adjustment did not
    flag as unreliable (a flagged frame's position error would become a speed error)."""
    use, skipped = [], {}
    for k in range(result.n_frames):
        status = result.status(k)
        if status != "ok":
            skipped[k] = status
            continue
        adj = (result.records[k].stats or {}).get("adjustment") or {}
        if adj.get("flagged"):
            skipped[k] = f"flagged: {adj['flagged']}"
            continue
        use.append(k)
    return use, skipped


@dataclass(frozen=True)
class Block:
    """Frames ``frames`` judged against the median of ``samples``."""

    frames: tuple[int, ...]
    samples: tuple[int, ...]


def background_blocks(
    frames: list[int], times: NDArray[np.float64], config: TrafficConfig
) -> list[Block]:
    """Consecutive usable ``frames`` grouped into :data:`BLOCK_S` blocks, each with the frames
    nearest in time to ``background_samples`` evenly spaced instants on either side of it within
    ``background_span_s`` (distinct, ascending). A frame nearest to an instant but further than
    ``background_span_s + BLOCK_S`` from the block (across a run of failed frames) is not
    taken: it is not this block's background, and :func:`detect_sequence` no longer holds it."""
    if not frames:
        return []
    t = np.asarray([times[k] for k in frames])
    groups: dict[int, list[int]] = {}
    for k, tk in zip(frames, t, strict=True):
        groups.setdefault(int(np.floor((tk - t[0]) / BLOCK_S)), []).append(k)
    n = config.background_samples
    offsets = config.background_span_s * np.arange(1, n + 1) / n
    blocks = []
    for members in groups.values():
        tc = 0.5 * (times[members[0]] + times[members[-1]])
        picks = set()
        for want in np.concatenate([tc - offsets, tc + offsets]):
            if want < t[0] - BLOCK_S or want > t[-1] + BLOCK_S:
                continue
            i = int(np.argmin(np.abs(t - want)))
            if abs(t[i] - tc) <= config.background_span_s + BLOCK_S:
                picks.add(frames[i])
        blocks.append(Block(tuple(members), tuple(sorted(picks))))
    return blocks


def detections_path(folder: Path, k: int) -> Path:
    return folder / f"{k:06d}.json"


def read_detections(folder: Path, k: int) -> list[Detection] | None:
    """Frame ``k``'s stored detections, or None when missing or unreadable (then redone)."""
    try:
        doc = json.loads(detections_path(folder, k).read_text())
        return [Detection.from_dict(d) for d in doc["detections"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def detect_sequence(
    result,
    frames,
    grid: WorkGrid,
    metric: MetricFrame,
    times: NDArray[np.float64],
    use: list[int],
    config: TrafficConfig,
    folder: Path,
    *,
    exclude: NDArray[np.bool_] | None = None,
    progress: Callable[[int, int], None] | None = None,
    cancel: Callable[[], bool] | None = None,
) -> Iterator[tuple[int, list[Detection]]]:
    """Detect vehicles in every usable frame, block by block, yielding ``(k, detections)`` in
    frame order; each frame's detections are written to ``folder/KKKKKK.json`` (atomically)
    before they are yielded, and frames already there are read, not redone. Each frame's
    vehicles are matched in the usable frame before it (warped again when a resumed run
    stored that one: a resumed run detects what a whole one does).

    ``frames``: the registered frames (``get(k)`` BGR). ``exclude``: working-grid mask of places
    never to look at (the analyst's regions).
    """
    folder.mkdir(parents=True, exist_ok=True)
    mpp = metric.metres_per_base_px()
    blocks = background_blocks(use, times, config)
    warped: dict[int, WarpedFrame | None] = {}
    keep = frame_keep_mask(result)
    matched = motion_frames(use, times, config)
    done = 0
    for block in blocks:
        if cancel is not None and cancel():
            return
        stored = {k: read_detections(folder, k) for k in block.frames}
        todo = [k for k in block.frames if stored[k] is None]
        if todo:
            # Each frame's vehicles are matched in a usable frame before it.
            before = {k: matched[k] for k in todo if k in matched}
            for k in sorted(set(block.samples) | set(todo) | set(before.values())):
                if k not in warped:
                    warped[k] = warp_frame(result, k, frames.get(k), grid, exclude, keep)
            # Only what later blocks can still sample stays.
            t_keep = times[block.frames[0]] - config.background_span_s - BLOCK_S
            matched_in = set(before.values())
            for k in [k for k in warped if times[k] < t_keep and k not in matched_in]:
                del warped[k]
            targets = [warped[k] for k in todo if warped[k] is not None]
            samples = [warped[k] for k in block.samples if warped[k] is not None]
            if targets:
                box = union_box([w.box for w in targets])
                need = needed_pixels(targets, box, config.tolerance_px)
                background = median_background(samples, box, need)
            for k in todo:
                w = warped[k]
                found = []
                if w is not None:
                    prev = warped.get(before[k]) if k in before else None
                    dt = float(times[k] - times[before[k]]) if prev is not None else 0.0
                    found = detect_vehicles(w, background.crop(w.box), grid, mpp, config, prev, dt)
                doc = {"k": k, "detections": [d.to_dict() for d in found]}
                write_bytes_atomic(detections_path(folder, k), json.dumps(doc).encode() + b"\n")
                # As stored (rounded): a resumed run then tracks exactly what a whole one does.
                stored[k] = [Detection.from_dict(d) for d in doc["detections"]]
        for k in block.frames:
            done += 1
            if progress is not None:
                progress(done, len(use))
            yield k, stored[k]


def tracks_from_detections(
    detections: dict[int, list[Detection]],
    use: list[int],
    times: NDArray[np.float64],
    metric: MetricFrame,
    config: TrafficConfig,
) -> tuple[list[SmoothTrack], dict[int, tuple[float, float]]]:
    """Tracks (:func:`track_detections`), smoothed (:func:`smooth_track`), of moving vehicles
    (:func:`_moving_vehicle`) (ids renumbered from 1 in order of first
    appearance), and each one's ``(width m, length m)``: the median over its detections."""
    xy = {
        k: metric.metres_from_base(np.array([[d.x, d.y] for d in ds]).reshape(-1, 2))
        for k, ds in detections.items()
    }
    tracks, sizes = [], {}
    dt_before = {
        k: float(times[k] - times[j]) for k, j in motion_frames(use, times, config).items()
    }
    velocities = {k: shift_velocities(ds, dt_before.get(k), metric) for k, ds in detections.items()}
    for r in track_detections(use, times, xy, config, velocities):
        dets = [
            detections[k][i] for k, i in zip(r.frames.tolist(), r.det_index.tolist(), strict=True)
        ]
        measured = np.array(
            [velocities[k][i] for k, i in zip(r.frames.tolist(), r.det_index.tolist(), strict=True)]
        )
        noise = blob_noise(
            np.array([d.length_m for d in dets]), _axes_in_metres(dets, metric), config
        )
        noise = lost_end_noise(noise, r.frames, use, config)
        velocity = checked_velocities(r, measured, times, dt_before, config)
        s = smooth_track(r, use, times, config, noise, velocity)
        if not _moving_vehicle(s, config):
            continue
        if sideways(s, r, dets, metric, config):
            continue
        s.track_id = len(tracks) + 1
        sizes[s.track_id] = (
            float(np.median([d.width_m for d in dets])),
            float(np.median([d.length_m for d in dets])),
        )
        tracks.append(s)
    return tracks, sizes


def shift_velocities(
    dets: list[Detection], dt: float | None, metric: MetricFrame
) -> NDArray[np.float64]:
    """``(N, 2)`` m/s: the velocity each of a frame's detections measured by matching its
    pixels in the usable frame ``dt`` seconds before (``Detection.shift_x`` / ``shift_y``, base
    px); NaN where it did not, or there is no frame before (``dt`` None)."""
    out = np.full((len(dets), 2), np.nan)
    if dt is None or not dets:
        return out
    at = np.array([[d.x, d.y] for d in dets], np.float64)
    shift = np.array([[d.shift_x, d.shift_y] for d in dets], np.float64)
    ok = np.isfinite(shift).all(axis=1)
    if ok.any():
        moved = metric.metres_from_base(at[ok]) - metric.metres_from_base(at[ok] - shift[ok])
        out[ok] = moved / dt
    return out


def motion_frames(
    use: list[int], times: NDArray[np.float64], config: TrafficConfig
) -> dict[int, int]:
    """For each usable frame, the usable frame its vehicles' pixels are matched in: the latest
    one at least ``config.motion_baseline_s`` before it (the first frame when none is), and
    none beyond ``config.max_gap_s`` (after failed frames a vehicle may be anywhere). At the
    paper's 5 frames/s that is the frame before; at 30 frames/s six frames back, so that a
    vehicle has moved by far more than the match's error (0.1 m)."""
    out = {}
    # Frame times from a rate are sums of rounded steps: 0.2 s may come out 0.19999999999999998.
    baseline = config.motion_baseline_s * (1.0 - 1e-9)
    for i, k in enumerate(use):
        j = i - 1
        while j > 0 and times[k] - times[use[j]] < baseline:
            j -= 1
        if j >= 0 and times[k] - times[use[j]] <= config.max_gap_s:
            out[k] = use[j]
    return out


def checked_velocities(
    raw: RawTrack,
    measured: NDArray[np.float64],
    times: NDArray[np.float64],
    dt_before: dict[int, float],
    config: TrafficConfig,
) -> dict[int, tuple[NDArray, NDArray]]:
    """By frame, the measured velocities ``measured`` ``(M, 2)`` m/s of ``raw``'s detections
    (:func:`shift_velocities`) that the track's blob centres confirm, with their noise ``(2,
    2)`` (m/s)²: ``config.shift_sigma_m`` over ``dt_before[k]``, the time since the frame the
    match was made in.

    A match is kept only where it agrees within ``config.shift_gate_m`` (over that time) with
    how fast the track's blob centres moved between this detection and the one of the same
    track nearest to that time before or after it (within half to twice of it): a vehicle's
    pixels matched on another vehicle or the road are far off that. A detection with no such
    neighbour in its track keeps none."""
    out = {}
    t = times[raw.frames]
    for i, k in enumerate(raw.frames.tolist()):
        if not np.isfinite(measured[i]).all():
            continue
        dt = dt_before[k]
        span = np.abs(t - t[i])
        fits = np.nonzero((span >= 0.5 * dt) & (span <= 2.0 * dt))[0]
        if not len(fits):
            continue
        # Nearest to the match's own interval; of two alike, the earlier.
        j = int(fits[np.argmin(np.abs(span[fits] - dt))])
        centres = (raw.xy[j] - raw.xy[i]) / float(t[j] - t[i])
        if np.linalg.norm(measured[i] - centres) * dt > config.shift_gate_m:
            continue
        out[k] = (measured[i], np.eye(2) * (config.shift_sigma_m / dt) ** 2)
    return out


def _axes_in_metres(dets: list[Detection], metric: MetricFrame) -> NDArray[np.float64]:
    """``(M, 2)`` unit vectors along the detections' blob axes, in metres (the map's axes may
    be turned and flipped against its pixels')."""
    at = np.array([[d.x, d.y] for d in dets], np.float64).reshape(-1, 2)
    a = np.radians([d.axis_deg for d in dets])
    step = metric.metres_from_base(at + np.c_[np.cos(a), np.sin(a)]) - metric.metres_from_base(at)
    return step / np.maximum(np.linalg.norm(step, axis=1, keepdims=True), 1e-12)


def sideways(
    track: SmoothTrack, raw: RawTrack, dets: list[Detection], metric: MetricFrame, config
) -> bool:
    """Whether the track moves across its blobs' long axis rather than along it: vehicles drive
    lengthwise, while the edge of a roof whose relief shifts as the camera flies on slides
    sideways (the real flyover: 54-75 degrees off). Judged on the detections at least
    ``ELONGATED`` times longer than wide, when there are ``min_hits`` of them."""
    long = [i for i, d in enumerate(dets) if d.length_m >= ELONGATED * d.width_m]
    if len(long) < config.min_hits:
        return False
    at = np.searchsorted(track.frames, raw.frames[long])
    # The direction of travel on the base (its pixels' y runs down; the map's may not).
    here = metric.base_from_metres(track.xy[at])
    ahead = metric.base_from_metres(track.xy[at] + track.velocity[at] * 0.1)
    travel = np.degrees(np.arctan2(*(ahead - here)[:, ::-1].T))
    axis = np.array([dets[i].axis_deg for i in long])
    off = np.abs((travel - axis + 90.0) % 180.0 - 90.0)
    return bool(np.median(off) > SIDEWAYS_DEG)


# A blob this many times longer than wide has an axis to judge its travel by, and a track whose
# median angle between its travel and its blobs' axes exceeds SIDEWAYS_DEG is not a vehicle.
ELONGATED = 1.4
SIDEWAYS_DEG = 45.0


def _moving_vehicle(track: SmoothTrack, config: TrafficConfig) -> bool:
    """Whether a smoothed track is moving traffic: long enough in time and space, on average
    faster than roof relief and pedestrians, never faster than town traffic, and seen in most
    of the frames it spans."""
    speed = track.speed
    return (
        track.times[-1] - track.times[0] >= config.min_duration_s
        and track.travel_m >= config.min_travel_m
        and speed.mean() >= config.min_speed_mps
        and speed.max() <= config.max_speed_mps
        and track.observed.mean() >= config.min_observed
    )


def result_fingerprint(result) -> str:
    """SHA-256 of the result's ``result.json`` and every frame record: detections stored for
    another registration are not reused."""
    h = hashlib.sha256()
    root = Path(result.out_dir)
    for p in [root / "result.json", *sorted((root / "frames").glob("*.json"))]:
        try:
            h.update(p.name.encode() + p.read_bytes())
        except OSError:
            h.update(p.name.encode())
    return h.hexdigest()
