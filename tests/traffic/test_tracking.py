"""The traffic stage's parts against known answers: the median background, the tracker and
smoother on planted trajectories, frame times and metres, and the output files."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest

from registration.traffic import MetricFrame, TrafficConfig, frame_times, video_frame_times
from registration.traffic.background import WarpedFrame, _sorting_network, median_background
from registration.traffic.outputs import (
    TRACK_COLUMNS,
    velocity_field,
    write_ind_csvs,
    write_trajectory_layers,
)
from registration.traffic.sequence import background_blocks
from registration.traffic.track import (
    RawTrack,
    blob_noise,
    lost_end_noise,
    smooth_track,
    track_detections,
)


def test_sorting_network_sorts_every_binary_input():
    # The 0-1 principle: a comparator network that sorts every 0/1 input sorts everything.
    for n in range(1, 13):
        net = _sorting_network(n)
        for code in range(2**n):
            a = [(code >> i) & 1 for i in range(n)]
            for i, j in net:
                if a[i] > a[j]:
                    a[i], a[j] = a[j], a[i]
            assert a == sorted(a), n


def test_median_background_is_the_median_of_the_samples_present(rng):
    samples = []
    for i in range(9):
        x0, y0 = (int(v) for v in rng.integers(0, 12, 2))
        image = rng.integers(1, 255, (30, 40, 3), dtype=np.uint8)
        mask = rng.random((30, 40)) < 0.7
        samples.append(WarpedFrame(i, image, mask, (x0, y0, x0 + 40, y0 + 30)))
    box = (3, 4, 50, 44)
    bg = median_background(samples, box)
    med, count = bg.image, bg.count
    for y in range(0, 40, 3):
        for x in range(0, 47, 2):
            vals = [
                s.image[y + 4 - s.box[1], x + 3 - s.box[0]]
                for s in samples
                if 0 <= x + 3 - s.box[0] < 40
                and 0 <= y + 4 - s.box[1] < 30
                and s.mask[y + 4 - s.box[1], x + 3 - s.box[0]]
            ]
            assert count[y, x] == len(vals)
            if vals:
                lower = np.sort(np.array(vals), axis=0)[(len(vals) - 1) // 2]
                np.testing.assert_array_equal(med[y, x], lower)


def test_median_background_where_needed_is_the_whole_boxs_there(rng, monkeypatch):
    import registration.traffic.background as bg_mod

    monkeypatch.setattr(bg_mod, "NEED_STRIP", 7)  # several strips on a small box
    samples = []
    for i in range(7):
        x0, y0 = (int(v) for v in rng.integers(0, 12, 2))
        image = rng.integers(1, 255, (30, 40, 3), dtype=np.uint8)
        samples.append(
            WarpedFrame(i, image, rng.random((30, 40)) < 0.8, (x0, y0, x0 + 40, y0 + 30))
        )
    box = (3, 4, 50, 44)
    need = np.zeros((40, 47), bool)
    need[5:30, 10:20] = need[12:38, 25:44] = True
    whole = median_background(samples, box)
    part = median_background(samples, box, need)
    np.testing.assert_array_equal(part.image[need], whole.image[need])
    np.testing.assert_array_equal(part.count[need], whole.count[need])
    np.testing.assert_array_equal(part.spread[need], whole.spread[need])
    # The first strip (rows 0-6) needs columns 10-19 only: the rest of it is left alone.
    assert part.count[:7, :10].max() == 0 and part.count[:7, 20:].max() == 0
    assert whole.count[:7, 20:].max() > 0


def _planted(rng, n_frames=40, fps=5.0, sigma=0.15):
    """Three vehicles at constant velocity (m, m/s) seen at ``fps`` with position noise; the
    second is missed in frames 10-11 and a false detection sits far from all in frame 20."""
    starts = np.array([[0.0, 0.0], [0.0, 3.5], [60.0, -3.5]])
    vel = np.array([[12.0, 0.0], [9.0, 0.0], [-10.0, 0.5]])
    times = np.arange(n_frames) / fps
    dets = {}
    for k, t in enumerate(times):
        xy = starts + vel * t + rng.normal(0, sigma, (3, 2))
        if k in (10, 11):
            xy = xy[[0, 2]]
        if k == 20:
            xy = np.vstack([xy, [[30.0, 40.0]]])
        dets[k] = xy
    return starts, vel, times, dets


def test_tracker_follows_planted_vehicles_through_a_gap(rng):
    starts, vel, times, dets = _planted(rng)
    cfg = TrafficConfig()
    frames = list(range(len(times)))
    raw = track_detections(frames, times, dets, cfg)
    # The lone false detection never makes min_hits; the missed frames do not split a track.
    assert len(raw) == 3
    for r in raw:
        assert len(r.frames) in (38, 40)
    smooth = [smooth_track(r, frames, times, cfg) for r in raw]
    for s in smooth:
        i = int(np.argmin(np.linalg.norm(starts - s.xy[0], axis=1)))
        true_xy = starts[i] + vel[i] * s.times[:, None]
        assert np.sqrt(np.mean(np.sum((s.xy - true_xy) ** 2, axis=1))) < 0.15
        assert np.sqrt(np.mean(np.sum((s.velocity - vel[i]) ** 2, axis=1))) < 0.3
        assert np.abs(s.acceleration).mean() < 0.5
        # The gap frames are filled by the smoother and marked as not observed.
        assert len(s.frames) == 40 and s.observed.sum() == len(raw[smooth.index(s)].frames)


def test_smoother_follows_a_vehicle_that_brakes_and_pulls_away(rng):
    """The smoother's constant-velocity model holds speeds steady between noisy detections,
    yet follows a real change of speed: a car at 14 m/s brakes at 3 m/s² to 5 m/s and pulls
    away again at 2 m/s², seen at 5 frames/s with the detector's 0.35 m noise."""
    fps = 5.0
    times = np.arange(60) / fps
    accel = np.where(times < 2, 0.0, np.where(times < 5, -3.0, np.where(times < 8, 0.0, 2.0)))
    accel = np.where(times >= 11.5, 0.0, accel)
    speed = 14.0 + np.concatenate([[0.0], np.cumsum(accel[:-1]) / fps])
    x = np.concatenate([[0.0], np.cumsum(speed[:-1]) / fps])
    dets = {k: np.array([[x[k], 2.0]]) + rng.normal(0, 0.35, (1, 2)) for k in range(len(times))}
    cfg = TrafficConfig()
    frames = list(range(len(times)))
    (raw,) = track_detections(frames, times, dets, cfg)
    s = smooth_track(raw, frames, times, cfg)
    assert len(s.frames) == len(times)
    err = s.velocity[:, 0] - speed
    # Within 0.4 m/s at the median, 1.5 m/s at worst (where braking starts and ends), against
    # the 0.35 m x 5 /s x sqrt(2) = 2.5 m/s of differencing two detections (measured with the
    # smoother's 0.55 m noise: 0.22 and 0.93 m/s here, 0.18-0.21 and 0.54-1.35 with seeds 0-2;
    # a smoother held at 0.3 m/s² per √s lags by up to 1.9 m/s, at 0.1 by 3.5).
    assert np.median(np.abs(err)) < 0.4, err
    assert np.abs(err).max() < 1.5, err
    # Braking (-3 m/s²) and pulling away (2 m/s²) are seen as such in the acceleration.
    assert s.acceleration[(times > 2.8) & (times < 4.2), 0].mean() < -2.3
    assert s.acceleration[(times > 8.8) & (times < 10.8), 0].mean() > 1.5


def test_blobs_that_lost_part_of_their_vehicle_count_less_along_their_axis():
    """A car at 10 m/s seen at 5 frames/s with 0.2 m noise; in a third of the frames (drawn,
    seeded) its blob lost 1.5 m of one end (a dark windscreen taken for background), so its
    centre is 0.75 m off along the road, ahead or behind. Told how much each blob's length
    differs from the track's median (:func:`blob_noise`), the smoother trusts those blobs less
    along their axis only: over seeds 0-2, position RMSE 0.259 -> 0.135 m and speed RMSE
    0.382 -> 0.152 m/s (measured)."""
    cfg = TrafficConfig()
    fps, n, speed = 5.0, 30, 10.0
    times = np.arange(n) / fps
    frames = list(range(n))
    true = np.c_[speed * times, np.full(n, 2.0)]
    plain_err, aware_err = [], []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        partial = np.zeros(n, bool)
        partial[rng.choice(n, n // 3, replace=False)] = True
        lengths = np.where(partial, 3.0, 4.5)
        sign = rng.choice([-1.0, 1.0], n)
        xy = true + rng.normal(0, 0.2, (n, 2))
        xy[partial, 0] += sign[partial] * 0.75
        (raw,) = track_detections(frames, times, {k: xy[k : k + 1] for k in frames}, cfg)
        noise = blob_noise(lengths[raw.frames], np.tile([1.0, 0.0], (len(raw.frames), 1)), cfg)
        # Across the axis, and for whole blobs, the noise is the configured one.
        np.testing.assert_allclose(noise[:, 1, 1], cfg.smooth_sigma_m**2)
        whole = ~partial[raw.frames]
        np.testing.assert_allclose(noise[whole, 0, 0], cfg.smooth_sigma_m**2)
        np.testing.assert_allclose(noise[~whole, 0, 0], cfg.smooth_sigma_m**2 + 0.75**2)
        # A blob longer than the track's median is not trusted less (a roof's relief on the
        # real flyover would travel far enough to pass for a vehicle).
        longer = blob_noise(np.array([4.5, 4.5, 6.0]), np.tile([1.0, 0.0], (3, 1)), cfg)
        np.testing.assert_allclose(longer[2], np.eye(2) * cfg.smooth_sigma_m**2)
        for out, s in (
            (plain_err, smooth_track(raw, frames, times, cfg)),
            (aware_err, smooth_track(raw, frames, times, cfg, noise)),
        ):
            position = np.sqrt(np.mean(np.sum((s.xy - true[s.frames]) ** 2, axis=1)))
            out.append((position, np.sqrt(np.mean((s.velocity[:, 0] - speed) ** 2))))
    plain, aware = np.mean(plain_err, axis=0), np.mean(aware_err, axis=0)
    assert aware[0] < 0.7 * plain[0] and aware[1] < 0.6 * plain[1], (plain, aware)


def test_background_samples_stay_within_the_span_across_failed_frames():
    # Frames 10-29 failed (4 s at 5 frames/s). Frame 30's block used to take frame 9 (1.8 s
    # before the 2.4 s instant it looked for, 4.2 s from the block), which the detector had
    # already let go: the long simulated flight's OpenCV run stopped on a KeyError there.
    cfg = TrafficConfig()
    times = np.arange(41) / 5.0
    use = list(range(10)) + list(range(30, 41))
    reach = cfg.background_span_s + 0.4
    for block in background_blocks(use, times, cfg):
        centre = 0.5 * (times[block.frames[0]] + times[block.frames[-1]])
        assert all(abs(times[k] - centre) <= reach + 1e-9 for k in block.samples), block
        assert set(block.samples) <= set(use)
    (after_gap,) = [b for b in background_blocks(use, times, cfg) if 30 in b.frames]
    assert min(after_gap.samples) >= 30 and len(after_gap.samples) >= cfg.min_samples
    # Without failed frames the samples are the nearest frames to the instants, as before.
    whole = background_blocks(list(range(41)), times, cfg)
    block = next(b for b in whole if 20 in b.frames)
    assert block.samples == (8, 10, 12, 14, 16, 18, 22, 24, 26, 28, 30, 32), block


def test_a_track_lost_inside_the_flight_trusts_its_last_blobs_less(rng):
    """A car at 12 m/s seen at 5 frames/s with 0.2 m noise, lost at frame 20 of a 30-frame
    flight; in its last two frames its blob merged with the car behind, and the blob's centre
    slid back by 0.8 and 1.6 m (what the simulator's lost tracks show: their ends too slow by
    0.8 m/s on average). Trusted 8 times less there (:func:`lost_end_noise`), the speed at the
    track's end stays near the truth; trusted as much as the others it falls."""
    cfg = TrafficConfig()
    fps, speed = 5.0, 12.0
    times = np.arange(30) / fps
    use = list(range(30))
    seen = list(range(21))
    true = np.c_[speed * times, np.zeros(30)]
    xy = true + rng.normal(0, 0.2, (30, 2))
    xy[19, 0] -= 0.8
    xy[20, 0] -= 1.6
    (raw,) = track_detections(seen, times, {k: xy[k : k + 1] for k in seen}, cfg)
    assert raw.frames.tolist() == seen
    plain = blob_noise(np.full(21, 4.5), np.tile([1.0, 0.0], (21, 1)), cfg)
    scaled = lost_end_noise(plain, raw.frames, use, cfg)
    # The start is the flight's first frame: kept. The last two detections: 8x the sigma.
    np.testing.assert_allclose(scaled[:-2], plain[:-2])
    np.testing.assert_allclose(scaled[-2:], plain[-2:] * 64.0)
    # A track ending at the flight's last frame, or too short, is left alone.
    np.testing.assert_allclose(lost_end_noise(plain, raw.frames, seen, cfg), plain)
    np.testing.assert_allclose(lost_end_noise(plain[:6], raw.frames[:6], use, cfg), plain[:6])
    end_speed = {}
    for name, noise in (("plain", plain), ("scaled", scaled)):
        s = smooth_track(raw, use, times, cfg, noise)
        end_speed[name] = abs(float(s.velocity[-1, 0]) - speed)
    # Measured: 1.63 m/s off trusted alike, 0.13 m/s trusted less.
    assert end_speed["scaled"] < 0.5 and end_speed["plain"] > 1.0, end_speed


def test_tracks_are_reproducible(rng):
    _, _, times, dets = _planted(rng)
    frames = list(range(len(times)))
    a = track_detections(frames, times, dets, TrafficConfig())
    b = track_detections(frames, times, dets, TrafficConfig())
    assert [r.track_id for r in a] == [r.track_id for r in b]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.xy, y.xy)


def test_frame_times_from_fps_and_bad_rates():
    t, src = frame_times(4, fps=5.0)
    np.testing.assert_allclose(t, [0, 0.2, 0.4, 0.6])
    assert "5" in src
    for bad in (0, -3, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="frame rate must be a positive"):
            frame_times(4, fps=bad)
    with pytest.raises(ValueError, match="give the frame rate"):
        frame_times(4)


def test_video_timestamps_come_from_the_container(tmp_path):
    import imageio.v2 as iio

    path = tmp_path / "v.mp4"
    with iio.get_writer(path, fps=7.5, codec="libx264", macro_block_size=1) as w:
        for k in range(9):
            w.append_data(np.full((32, 48, 3), 20 * k, np.uint8))
    t = video_frame_times(path)
    np.testing.assert_allclose(t, np.arange(9) / 7.5, atol=1e-3)
    with pytest.raises(ValueError, match="has 9 timestamps for 10 frames"):
        frame_times(10, video=path)


def test_metric_frame_needs_metres():
    from registration.gis.georef import GeoReference

    with pytest.raises(ValueError, match="no georeference.*--gsd"):
        MetricFrame.for_result(None, None)
    with pytest.raises(ValueError, match="ground sampling distance must be positive"):
        MetricFrame.for_result(None, 0.0)
    geo = GeoReference((0.5, 0.0, 300000.0, 0.0, -0.5, 3700000.0), "EPSG:32643")
    m = MetricFrame.for_result(geo, None)
    # conventions.md: base pixel (x, y) is at A * (x + 0.5, y + 0.5).
    np.testing.assert_allclose(m.metres_from_base([[0, 0]]), [[300000.25, 3699999.75]])
    np.testing.assert_allclose(m.base_from_metres(m.metres_from_base([[7.3, 2.1]])), [[7.3, 2.1]])
    degrees = GeoReference((1e-5, 0.0, 73.0, 0.0, -1e-5, 33.6), "EPSG:4326")
    with pytest.raises(ValueError, match="degree.*--gsd"):
        MetricFrame.for_result(degrees, None)
    assert MetricFrame.for_result(degrees, 0.3).metres_from_base([[10, 10]])[0, 1] == -3.0


def test_outputs_hold_the_planted_tracks(rng, tmp_path):
    starts, vel, times, dets = _planted(rng)
    cfg = TrafficConfig()
    frames = list(range(len(times)))
    tracks = [
        smooth_track(r, frames, times, cfg) for r in track_detections(frames, times, dets, cfg)
    ]
    metric = MetricFrame(None, 0.5)
    write_ind_csvs(
        tmp_path, tracks, {t.track_id: (1.8, 4.5) for t in tracks}, metric, 5.0, 7.8, "--fps 5"
    )
    import csv

    rows = list(csv.DictReader(open(tmp_path / "tracks.csv")))
    assert tuple(rows[0]) == TRACK_COLUMNS
    first = [r for r in rows if r["trackId"] == "1"]
    v = np.array([[float(r["xVelocity"]), float(r["yVelocity"])] for r in first])
    lon = np.array([float(r["lonVelocity"]) for r in first])
    # The longitudinal velocity is the speed; the lateral one ~0 for a straight drive.
    np.testing.assert_allclose(lon, np.linalg.norm(v, axis=1), atol=1e-2)
    assert max(abs(float(r["latVelocity"])) for r in first) < 0.05
    headings = {r["trackId"]: float(r["heading"]) for r in rows}
    assert sorted(round(h / 90) % 4 for h in headings.values()) == [0, 0, 2]
    paths = write_trajectory_layers(tmp_path, tracks, metric)
    doc = json.loads(paths[0].read_text())
    assert [f["geometry"]["type"] for f in doc["features"]] == ["LineString"] * 3
    con = sqlite3.connect(paths[1])
    assert con.execute("SELECT COUNT(*) FROM trajectories").fetchone()[0] == 3
    assert (
        con.execute("SELECT geometry_type_name FROM gpkg_geometry_columns").fetchone()[0]
        == "LINESTRING"
    )
    bands, _ = velocity_field(tracks, 5.0, 3)
    speed = bands[2][np.isfinite(bands[2])]
    assert speed.size and np.all((speed > 8.5) & (speed < 12.6))
    assert np.nansum(bands[4]) == sum(len(t.frames) for t in tracks)


def test_bad_settings_say_which():
    with pytest.raises(ValueError, match="gate_m must be positive"):
        TrafficConfig(gate_m=0).validate()
    with pytest.raises(ValueError, match="min_samples"):
        TrafficConfig(min_samples=20).validate()


def test_gate_follows_the_time_step(rng):
    # A new track's next detection 2.5 m on: at 30 frames/s that is 75 m/s, within the fixed
    # 3 m gate but outside the prediction's 99 % ellipse; at 2 frames/s (5 m/s) it joins.
    cfg = TrafficConfig()
    for fps, joined in ((30.0, False), (2.0, True)):
        times = np.arange(6) / fps
        dets = {0: np.array([[0.0, 0.0]])}
        dets.update({k: np.array([[2.5, 0.0]]) for k in range(1, 6)})
        raw = track_detections(list(range(6)), times, dets, cfg)
        assert [len(r.frames) for r in raw] == ([6] if joined else [5]), fps


def test_a_fast_car_at_five_frames_per_second_is_one_track():
    # 18 m/s at 5 frames/s: 3.6 m between detections, beyond the fixed 3 m gate. A new track
    # reaches as far as a vehicle at 20 m/s goes in the frame interval (4 m), so the car is
    # followed from its first detection.
    times = np.arange(10) / 5.0
    dets = {k: np.array([[18.0 * t, 0.0]]) for k, t in enumerate(times)}
    raw = track_detections(list(range(10)), times, dets, TrafficConfig())
    assert [len(r.frames) for r in raw] == [10]


def test_a_new_track_reaches_far_only_into_the_next_frame():
    # A lone detection in frame 0, nothing in frame 1, then a car 7 m away from frame 2 on. At
    # 20 m/s the car could have come from the lone detection in 0.4 s, but over a missed frame
    # a new track keeps the fixed 3 m gate (the wide reach would chain noise): the car's track
    # starts at frame 2.
    times = np.arange(8) / 5.0
    dets = {0: np.array([[0.0, 0.0]]), 1: np.zeros((0, 2))}
    dets.update({k: np.array([[7.0 + 2.0 * (k - 2), 0.0]]) for k in range(2, 8)})
    raw = track_detections(list(range(8)), times, dets, TrafficConfig())
    assert [r.frames.tolist() for r in raw] == [list(range(2, 8))]


def _blobs_along(velocity_mps, axis_deg, every=1, fps=10.0, n=40, gsd=0.5):
    """Detections of one blob 4.5 x 1.8 m with its long side at ``axis_deg`` on the base,
    moving at ``velocity_mps`` (metres, y up), seen in every ``every``-th frame."""
    from registration.traffic.detect import Detection

    metric = MetricFrame(None, gsd)
    times = np.arange(n) / fps
    dets = {}
    for k, t in enumerate(times):
        x, y = metric.base_from_metres([np.asarray(velocity_mps) * t])[0]
        dets[k] = [Detection(k, x, y, 4.5, 1.8, axis_deg, 8.0, 3.0)] if k % every == 0 else []
    return dets, times, metric


def test_a_blob_that_slides_sideways_is_not_a_vehicle():
    from registration.traffic.sequence import tracks_from_detections

    # Along +x on the map (base +x): a blob long along x is a car; one long along y slides
    # sideways like a roof's edge whose relief shifts. Along +y on the map (base -y, its pixels'
    # y runs down), a blob long along the base's y is a car.
    for velocity, axis, kept in (
        ((10.0, 0.0), 0.0, 1),
        ((10.0, 0.0), 90.0, 0),
        ((0.0, 10.0), 90.0, 1),
        ((0.0, 10.0), 0.0, 0),
        ((7.0, 7.0), 135.0, 1),  # up and right on the map: up and right on the base too
        ((7.0, 7.0), 45.0, 0),
    ):
        dets, times, metric = _blobs_along(velocity, axis)
        tracks, _ = tracks_from_detections(dets, list(dets), times, metric, TrafficConfig())
        assert len(tracks) == kept, (velocity, axis)


def test_a_track_seen_in_too_few_of_its_frames_is_dropped():
    from registration.traffic.sequence import tracks_from_detections

    # Seen every other frame it is kept; every third frame (a third of its span) it is mostly
    # the filter coasting, and dropped.
    for every, kept in ((2, 1), (3, 0)):
        dets, times, metric = _blobs_along((10.0, 0.0), 0.0, every=every)
        tracks, _ = tracks_from_detections(dets, list(dets), times, metric, TrafficConfig())
        assert len(tracks) == kept, every
        if kept:
            assert tracks[0].observed.mean() == pytest.approx(0.5, abs=0.03)


def test_a_vehicle_split_in_two_blobs_is_one_track_and_two_cars_in_a_row_two():
    # From frame 5 on, the car at 10 m/s is also seen as a second blob 2 m behind its centre
    # (a piece its shadow cut off): that starts a second track beside its own, merged back.
    # Two cars 6 m apart in one lane stay two tracks.
    times = np.arange(20) / 10.0
    for gap, tracks in ((2.0, 1), (6.0, 2)):
        dets = {}
        for k, t in enumerate(times):
            xy = [[10.0 * t, 0.0]]
            if k >= 5 or gap > 3:
                xy.append([10.0 * t - gap, 0.0])
            dets[k] = np.array(xy)
        raw = track_detections(list(range(20)), times, dets, TrafficConfig())
        assert len(raw) == tracks, gap
        if tracks == 1:
            assert len(raw[0].frames) == 20
            # Averaged where both were seen: 1 m behind the car's centre.
            np.testing.assert_allclose(raw[0].xy[10], [10.0 - 1.0, 0.0], atol=1e-9)


def test_tracks_that_are_not_moving_traffic_are_dropped(rng):
    from registration.traffic.detect import Detection
    from registration.traffic.sequence import tracks_from_detections

    fps, n = 10.0, 40
    times = np.arange(n) / fps
    # A car at 10 m/s, a roof edge creeping at 1 m/s and a 0.5 s blip, 1 m/px, y up = -row.
    dets = {}
    for k, t in enumerate(times):
        ds = [Detection(k, 10 * t, 0.0, 4.5, 1.8, 0.0, 8.0, 3.0)]
        ds.append(Detection(k, 100 + 1.0 * t, 50.0, 4.0, 2.0, 0.0, 8.0, 3.0))
        if k < 5:
            ds.append(Detection(k, 200 + 20 * t, 100.0, 4.0, 2.0, 0.0, 8.0, 3.0))
        dets[k] = ds
    tracks, sizes = tracks_from_detections(
        dets, list(range(n)), times, MetricFrame(None, 1.0), TrafficConfig()
    )
    assert len(tracks) == 1
    np.testing.assert_allclose(np.median(tracks[0].speed), 10.0, atol=0.1)
    assert sizes[1] == (1.8, 4.5)


def test_quartile_spread_ignores_a_passing_car_but_not_a_shifting_edge(rng):
    h, w, n = 20, 30, 12
    road = np.full((h, w, 3), 90, np.uint8)
    samples = []
    for i in range(n):
        img = np.clip(road + rng.normal(0, 2, road.shape), 0, 255).astype(np.uint8)
        if i in (4, 5):
            img[5:10, 5:15] = (230, 230, 230)  # a white car passing through two samples
        # An edge (a roof against the ground) that moves one pixel per sample.
        img[:, 16 + i :] = 200
        mask = np.ones((h, w), bool)
        if i == 0:
            mask[:, :3] = False  # one sample has no data on the left
        samples.append(WarpedFrame(i, img, mask, (0, 0, w, h)))
    bg = median_background(samples, (0, 0, w, h))
    assert bg.spread[5:10, 5:15].max() <= 10  # the car leaves the spread at the noise
    assert np.abs(bg.image[5:10, 5:15].astype(int) - 90).max() <= 6  # and the median the road
    # Where the edge passes, the samples' middle half spans ground and roof.
    assert bg.spread[:, 19:24].min() >= 100
    # Against numpy's order statistics where a sample is missing (count 11).
    stack = np.stack([s.image for s in samples[1:]]).astype(int)
    lo = np.sort(stack[:, :, :3], axis=0)[11 // 4]
    hi = np.sort(stack[:, :, :3], axis=0)[11 - 1 - 11 // 4]
    np.testing.assert_array_equal(bg.spread[:, :3], (hi - lo).max(axis=2))


class _Truth:
    """A truth with planted vehicles (what score_traffic reads)."""

    def __init__(self, rows):
        cols = ["frame", "track_id", "x_base", "y_base", "ux", "uy", "speed_mps", "length_m"]
        self.v = {c: np.array([r[i] for r in rows], float) for i, c in enumerate(cols)}
        self.v["frame"] = self.v["frame"].astype(int)
        self.v["track_id"] = self.v["track_id"].astype(int)
        self.v["width_m"] = np.full(len(rows), 1.8)
        self.v["base_px_per_m"] = 1.0
        self.root = None

    def vehicles(self):
        return self.v


def test_separable_scoring_leaves_out_touching_vehicles_and_their_pairs():
    from registration.evaluation.traffic import score_traffic, touching
    from registration.traffic.track import SmoothTrack

    # Frame 0: vehicles 1 and 2 overlap in one lane (1 m apart), vehicle 3 alone 20 m on;
    # base px = metres here, y down in base px, up in metres.
    rows = [(0, 1, 0.0, 0.0, 1, 0, 10, 4.5), (0, 2, 1.0, 0.0, 1, 0, 10, 4.5)]
    rows.append((0, 3, 20.0, 0.0, 1, 0, 10, 4.5))
    truth = _Truth(rows)
    np.testing.assert_array_equal(touching(truth.v, np.arange(3)), [True, True, False])

    def track(i, x):
        one = np.array([[x, 0.0]])
        return SmoothTrack(i, np.array([0]), np.zeros(1), one, np.array([[10.0, 0]]),
                           np.zeros((1, 2)), np.zeros(1), np.ones(1, bool))  # fmt: skip

    tracks = [track(1, 0.5), track(2, 20.2)]
    full = score_traffic(tracks, truth, [0])
    assert (full.truth_objects, full.misses, full.false_positives) == (3, 1, 0)
    sep = score_traffic(tracks, truth, [0], separable_only=True)
    # Only vehicle 3 counts, and the track point on the pair is neither a hit nor a false one.
    assert (sep.truth_objects, sep.misses, sep.false_positives) == (1, 0, 0)
    assert sep.precision == 1.0 and abs(sep.position_rmse_m - 0.2) < 1e-9


def test_measured_velocities_steady_a_short_tracks_speed_and_a_wrong_one_is_left_out(rng):
    """Cars at 12 m/s along x seen at 5 frames/s for 8 frames (a track the detector held for
    1.6 s), their blob centres 0.3 m off (about ``measurement_sigma_m``), their motion since the
    frame before measured from their pixels (:func:`~registration.traffic.detect.
    motion_since`) 0.1 m off, except in frame 4, where the match caught an oncoming car (-12
    m/s). The tracker leaves that blob out of the car's track; tracked on positions alone, the
    track holds it, and with the measured velocities the speeds are closer to the truth: the
    wrong one is left out by the blob centres' own motion, and by the smoother's gate."""
    from registration.traffic.sequence import checked_velocities

    cfg = TrafficConfig()
    fps, n = 5.0, 8
    times = np.arange(n) / fps
    use = list(range(n))
    true_v = np.array([12.0, 0.0])
    dt_before = {k: 1.0 / fps for k in use[1:]}
    errors = {"centres": [], "measured": []}
    for _ in range(20):
        xy = true_v * times[:, None] + rng.normal(0, 0.3, (n, 2))
        measured = true_v + rng.normal(0, 0.1 * fps, (n, 2))
        measured[0] = np.nan  # the first frame has no frame before
        measured[4] = (-12.0, 0.0)
        dets = {k: xy[k : k + 1] for k in use}
        # Given to the tracker, frame 4's blob moving the other way is not this car's.
        (raw,) = track_detections(use, times, dets, cfg, {k: measured[k : k + 1] for k in use})
        assert raw.frames.tolist() == [k for k in use if k != 4]
        # Tracked on positions alone, the smoother is handed the wrong velocity too.
        (raw,) = track_detections(use, times, dets, cfg)
        assert raw.frames.tolist() == use
        kept = checked_velocities(raw, measured, times, dt_before, cfg)
        assert sorted(kept) == [k for k in use if k not in (0, 4)]
        for name, velocity in (("centres", None), ("measured", kept)):
            s = smooth_track(raw, use, times, cfg, None, velocity)
            errors[name].append(s.velocity - true_v)
        # Given to the smoother anyway, the oncoming car's velocity falls outside the
        # prediction's ellipse and is not used either.
        given = {k: (measured[k], np.eye(2) * 1.0**2) for k in use[1:]}
        with_wrong = smooth_track(raw, use, times, cfg, None, given)
        np.testing.assert_allclose(with_wrong.velocity, s.velocity, atol=0.5)
    rmse = {k: float(np.sqrt(np.mean(np.sum(np.square(v), axis=2)))) for k, v in errors.items()}
    # Measured: 0.45 m/s from the centres alone, 0.35 with the shifts (weighed at
    # shift_sigma_m, 0.2 m: twice this test's 0.1 m, as on the simulated flights' tails).
    assert rmse["measured"] < 0.85 * rmse["centres"], rmse


def test_a_track_begins_at_its_first_detections_measured_velocity():
    """A car at 12 m/s, seen at 5 frames/s, and the car behind it, 4.5 m back, which enters
    the view one frame later. Without a velocity the first car's new track reaches 4 m into the
    next frame and takes the nearer blob, the car behind (2.1 m from where the first was, the
    first itself 2.4 m on), and neither car keeps a track; begun at its measured velocity each
    track follows its own car."""
    cfg = TrafficConfig()
    times = np.arange(6) / 5.0
    lead = np.c_[12.0 * times + 6.0, np.zeros(6)]
    follow = lead - (4.5, 0.0)
    dets = {k: np.vstack([lead[k], follow[k]]) if k else lead[:1] for k in range(6)}
    velocities = {k: np.tile([12.0, 0.0], (len(dets[k]), 1)) for k in range(6)}
    for given, right in ((velocities, True), (None, False)):
        raw = track_detections(list(range(6)), times, dets, cfg, given)
        steps_right = len(raw) == 2 and all(np.allclose(np.diff(r.xy[:, 0]), 2.4) for r in raw)
        assert steps_right == right, [r.xy[:, 0] for r in raw]


def test_vehicles_are_matched_a_fifth_of_a_second_back_at_any_frame_rate():
    from registration.traffic.sequence import motion_frames

    cfg = TrafficConfig()
    five = np.arange(10) / 5.0
    assert motion_frames(list(range(10)), five, cfg) == {k: k - 1 for k in range(1, 10)}
    thirty = np.arange(40) / 30.0
    back = motion_frames(list(range(40)), thirty, cfg)
    # 6 frames (0.2 s) back; the first frames reach back to frame 0; frame 0 has none.
    assert [back[k] for k in (1, 5, 6, 7, 39)] == [0, 0, 0, 1, 33] and 0 not in back
    # Failed frames 10-19 of the 5 frames/s flight: frame 20 is 2 s after frame 9, beyond
    # max_gap_s, and is matched in none.
    use = [k for k in range(30) if not 10 <= k < 20]
    gap = motion_frames(use, np.arange(30) / 5.0, cfg)
    assert 20 not in gap and gap[21] == 20 and gap[9] == 8


def test_a_track_does_not_take_an_oncoming_cars_blob():
    """Car A drives +x at 12 m/s (5 frames/s) and is missed in frame 6, where car B, driving
    the other way 0.8 m to the side, is first seen right at A's predicted position. Without
    their measured velocities A's track takes B's blob; with them (B's -12 m/s against A's
    +12: ``velocity_gate_mps``) B's blob begins B's own track."""
    cfg = TrafficConfig()
    times = np.arange(13) / 5.0
    a = np.c_[12.0 * times, np.zeros(13)]
    b = np.c_[14.4 - 12.0 * (times - 1.2), np.full(13, 0.8)]
    dets, vel = {}, {}
    for k in range(13):
        rows, v = [], []
        if k != 6:
            rows.append(a[k])
            v.append([12.0, 0.0])
        if k >= 6:
            rows.append(b[k])
            v.append([-12.0, 0.0])
        dets[k], vel[k] = np.array(rows), np.array(v)
    frames = list(range(13))
    for velocities in (None, vel):
        raw = track_detections(frames, times, dets, cfg, velocities)
        track_a = next(r for r in raw if r.frames[0] == 0)
        took_b = 6 in track_a.frames.tolist()
        assert took_b == (velocities is None), track_a.frames
    track_b = next(r for r in raw if r.frames[0] != 0)
    assert track_b.frames.tolist() == list(range(6, 13))


def test_the_smoother_takes_the_blob_centres_whole_scatter():
    # Blob centres scatter about their vehicle as measured on the simulated flights: 0.56 m RMS
    # per axis, half of it kept from one frame to the next (AR(1), correlation 0.49). The
    # tracker's noise (0.35 m: the part that changes between frames) understates that for the
    # smoother: speeds of a car at 12 m/s seen at 5 frames/s, 0.58 against 0.45 m/s RMS.
    import dataclasses

    def speed_rmse(sigma):
        cfg = dataclasses.replace(TrafficConfig(), smooth_sigma_m=sigma)
        errs = []
        for seed in range(6):
            r = np.random.default_rng(seed)
            n, rho, total = 20, 0.49, 0.56
            times = np.arange(n) / 5.0
            e = np.zeros((n, 2))
            e[0] = r.normal(0, total, 2)
            for k in range(1, n):
                e[k] = rho * e[k - 1] + r.normal(0, total * np.sqrt(1 - rho**2), 2)
            xy = np.c_[12.0 * times, np.full(n, 2.0)] + e
            raw = RawTrack(1, np.arange(n), times, xy, np.zeros(n, np.int64))
            errs.append(smooth_track(raw, list(range(n)), times, cfg).speed - 12.0)
        return float(np.sqrt(np.mean(np.square(errs))))

    cfg = TrafficConfig()
    assert cfg.smooth_sigma_m == 0.55
    ours, tracker_noise = speed_rmse(cfg.smooth_sigma_m), speed_rmse(cfg.measurement_sigma_m)
    assert ours < 0.5 and ours < 0.85 * tracker_noise, (ours, tracker_noise)
