"""The traffic stage end to end on a simulated flight, scored against the simulator's true
trajectories (motmetrics), and its resumable output folder."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import register

# 640x480 at 5 frames/s for 4 s: long enough for every vehicle that crosses to make a track.
SIM = {"frame_size": (640, 480), "n_frames": 20, "seed": 2, "video": False}


@pytest.fixture(scope="module")
def traffic_sim(tmp_path_factory):
    from registration.synth import SimConfig, simulate

    root = tmp_path_factory.mktemp("traffic")
    simulate(root / "sim", SimConfig(**SIM))
    result = register(root / "sim", root / "reg", reference_frame=10)
    return root, result


def test_vehicle_truth_is_consistent(traffic_sim):
    from registration.synth import load_truth

    root, _ = traffic_sim
    truth = load_truth(root / "sim")
    v = truth.vehicles()
    assert v is not None and len(v["frame"]) > 100
    fps = truth.config["fps"]
    for tid in np.unique(v["track_id"])[:40]:
        sel = np.nonzero(v["track_id"] == tid)[0]
        if len(sel) < 2:
            continue
        # Constant speed along the lane: consecutive centres advance by speed x time.
        step = np.hypot(np.diff(v["x_base"][sel]), np.diff(v["y_base"][sel]))
        dt = np.diff(v["frame"][sel]) / fps
        np.testing.assert_allclose(
            step, v["speed_mps"][sel][1:] * dt * v["base_px_per_m"], rtol=1e-3
        )


def test_traffic_matches_the_true_trajectories(traffic_sim, tmp_path):
    from registration.evaluation.traffic import score_traffic, truth_metric_frame
    from registration.io import open_frames
    from registration.synth import load_truth
    from registration.traffic import TrafficConfig, run_traffic
    from registration.traffic.sequence import read_detections, tracks_from_detections

    root, result = traffic_sim
    truth = load_truth(root / "sim")
    gsd = truth_metric_frame(truth).gsd_m
    frames = open_frames(root / "sim" / "frames")
    out = tmp_path / "traffic"
    summary = run_traffic(result, frames, out, fps=truth.config["fps"], gsd_m=gsd)
    assert summary["n_used"] == result.n_frames and summary["n_tracks"] > 10
    for name in ("tracks.csv", "tracksMeta.csv", "recordingMeta.csv", "velocity_field.tif"):
        assert (out / name).is_file()
    use = list(range(result.n_frames))
    dets = {k: read_detections(out / "detections", k) for k in use}
    times = np.arange(result.n_frames) / truth.config["fps"]
    tracks, _ = tracks_from_detections(dets, use, times, truth_metric_frame(truth), TrafficConfig())
    score = score_traffic(tracks, truth, use)
    # Limits from this flight (measured 2026-11-29, docs/traffic.md) with margin: a broken
    # background, metric frame or smoother fails them by far.
    assert score.precision > 0.85, score
    assert score.mota > 0.25, score
    assert score.speed_rmse_mps < 2.2, score
    assert score.position_rmse_m < 1.0, score
    speeds = np.concatenate([t.speed for t in tracks])
    assert 8.0 < np.median(speeds) < 16.0  # the simulator's lanes flow at 8-16 m/s


def test_traffic_resumes_and_refuses_another_run(traffic_sim, tmp_path):
    from registration.io import open_frames
    from registration.traffic import run_traffic

    root, result = traffic_sim
    frames = open_frames(root / "sim" / "frames")
    out = tmp_path / "t"
    calls = []

    def cancel_after_first_block():
        calls.append(1)
        return len(calls) > 2

    first = run_traffic(result, frames, out, fps=5.0, gsd_m=0.3, cancel=cancel_after_first_block)
    assert first["cancelled"] and 0 < first["frames_done"] < result.n_frames
    stored = {p.name: p.stat().st_mtime_ns for p in (out / "detections").glob("*.json")}
    full = run_traffic(result, frames, out, fps=5.0, gsd_m=0.3)
    again = {p.name: p.stat().st_mtime_ns for p in (out / "detections").glob("*.json")}
    assert all(again[n] == t for n, t in stored.items())  # not redone
    assert len(again) == result.n_frames
    tracks = (out / "tracks.csv").read_bytes()
    fresh = run_traffic(result, frames, tmp_path / "fresh", fps=5.0, gsd_m=0.3)
    assert (tmp_path / "fresh" / "tracks.csv").read_bytes() == tracks
    assert fresh["n_tracks"] == full["n_tracks"]
    with pytest.raises(FileExistsError, match="frame times differ"):
        run_traffic(result, frames, out, fps=6.0, gsd_m=0.3)
    with pytest.raises(ValueError, match="frame times unknown"):
        run_traffic(result, frames, tmp_path / "x", gsd_m=0.3)
    assert json.loads((out / "traffic.json").read_text())["format"] == "aerialreg-traffic"


def test_excluded_regions_hold_no_vehicles_and_are_part_of_the_run(traffic_sim, tmp_path):
    from registration.io import open_frames
    from registration.traffic import run_traffic
    from registration.traffic.sequence import read_detections

    root, result = traffic_sim
    frames = open_frames(root / "sim" / "frames")
    w, h = result.base_size
    half = w // 2
    exclude = np.zeros((h, w), bool)
    exclude[:, :half] = True
    out = tmp_path / "t"
    run_traffic(result, frames, out, fps=5.0, gsd_m=0.3, exclude=exclude)
    xs = [d.x for k in range(result.n_frames) for d in read_detections(out / "detections", k)]
    whole = tmp_path / "whole"
    run_traffic(result, frames, whole, fps=5.0, gsd_m=0.3)
    xs_all = [d.x for k in range(result.n_frames) for d in read_detections(whole / "detections", k)]
    # Vehicles on both halves without the regions; none in the excluded half with them.
    assert sum(x < half - 10 for x in xs_all) > 20 and sum(x >= half for x in xs_all) > 20
    assert xs and min(xs) >= half - 1
    with pytest.raises(FileExistsError, match="excluded regions differ"):
        run_traffic(result, frames, out, fps=5.0, gsd_m=0.3)
    with pytest.raises(ValueError, match="excluded regions are a 10x10 mask"):
        run_traffic(
            result, frames, tmp_path / "x", fps=5.0, gsd_m=0.3, exclude=np.ones((10, 10), bool)
        )
