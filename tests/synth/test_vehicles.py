"""The simulator's moving vehicles: lanes whose vehicles keep their distance (``vehicle_gap_m``),
and a time headway beyond it (``vehicle_headway_s``)."""

from __future__ import annotations

import numpy as np
import pytest

from registration.evaluation.traffic import touching
from registration.synth import SimConfig, load_truth, simulate
from registration.synth import city as citymod


def _lane_gaps(v: dict, lay) -> tuple[np.ndarray, np.ndarray]:
    """``(gaps px, index)``: for each vehicle with another in its lane (same axis and direction,
    centres within 1 m across), the smallest bumper-to-bumper gap to them, along the lane and
    around its wrap, and that vehicle's index into ``v``."""
    gaps, index = [], []
    along = np.where(v["axis"] == 0, v["x"], v["y"])
    across = np.where(v["axis"] == 0, v["y"], v["x"])
    for i in range(len(along)):
        same = (
            (v["axis"] == v["axis"][i])
            & (v["direction"] == v["direction"][i])
            & (np.abs(across - across[i]) < 1.0 / lay.gsd)
        )
        same[i] = False
        if not same.any():
            continue
        length = lay.width if v["axis"][i] == 0 else lay.height
        d = np.abs(along[same] - along[i])
        d = np.minimum(d, length - d)  # around the wrap
        gaps.append(np.min(d - (v["length"][same] + v["length"][i]) / 2.0))
        index.append(i)
    return np.array(gaps), np.array(index, np.intp)


def _same_lane_gaps(v: dict, lay) -> np.ndarray:
    """The gaps (px) of :func:`_lane_gaps`."""
    return _lane_gaps(v, lay)[0]


@pytest.fixture(scope="module")
def layout():
    return citymod.make_layout(1400, 1100, gsd=0.3, seed=4)


@pytest.mark.parametrize("t", [0.0, 3.7, 61.0])
def test_vehicles_of_a_lane_keep_their_distance(layout, t):
    free = citymod.traffic_states(layout, 0, 60.0, t)
    kept = citymod.traffic_states(layout, 0, 60.0, t, min_gap_m=2.0)
    # Dense traffic (60 a km): vehicles that ignore each other overlap in their lanes.
    assert _same_lane_gaps(free, layout).min() < 0
    gaps = _same_lane_gaps(kept, layout) * layout.gsd
    assert gaps.min() >= 2.0 - 1e-6, gaps.min()
    # The same vehicles (sizes, colours, lanes), each lane at one speed.
    for key in ("vehicle", "axis", "direction", "length", "width", "rgb"):
        np.testing.assert_array_equal(kept[key], free[key])
    lanes = {}
    for i in range(len(kept["speed"])):
        c = kept["y"][i] if kept["axis"][i] == 0 else kept["x"][i]
        key = (int(kept["axis"][i]), int(kept["direction"][i]), round(c * layout.gsd / 3.0))
        lanes.setdefault(key, set()).add(round(float(kept["speed"][i]), 6))
    assert max(len(s) for s in lanes.values()) == 1
    assert len({s.pop() for s in lanes.values()}) > 3  # the lanes' speeds differ


@pytest.mark.parametrize("t", [0.0, 3.7, 61.0])
def test_vehicles_keep_a_time_headway_behind_the_one_ahead(layout, t):
    # 2 m and 1 s of the lane's speed (8-16 m/s): 10-18 m bumper to bumper, in every lane (25
    # vehicles a km, the simulator's default: every lane has room for it).
    gap_only = citymod.traffic_states(layout, 0, 25.0, t, min_gap_m=2.0)
    kept = citymod.traffic_states(layout, 0, 25.0, t, min_gap_m=2.0, headway_s=1.0)
    gaps, index = _lane_gaps(kept, layout)
    gaps, lane_speed = gaps * layout.gsd, kept["speed"][index] * layout.gsd
    assert len(gaps) > 20
    assert np.all(gaps >= 2.0 + 1.0 * lane_speed - 1e-6), (gaps - lane_speed).min()
    assert _same_lane_gaps(gap_only, layout).min() * layout.gsd < 8.0  # 2 m alone is closer
    for key in ("vehicle", "speed", "length", "width", "rgb"):
        np.testing.assert_array_equal(kept[key], gap_only[key])
    # 60 a km leaves some lanes too little room for 1 s: they share it out, 2 m at least.
    dense = citymod.traffic_states(layout, 0, 60.0, t, min_gap_m=2.0, headway_s=1.0)
    dense_gaps, index = _lane_gaps(dense, layout)
    dense_gaps = dense_gaps * layout.gsd
    assert dense_gaps.min() >= 2.0 - 1e-6
    assert np.any(dense_gaps < 2.0 + dense["speed"][index] * layout.gsd)


def test_a_headway_needs_a_gap():
    with pytest.raises(ValueError, match="vehicle_headway_s .1.0. needs vehicle_gap_m"):
        SimConfig(vehicle_headway_s=1.0).validate()
    with pytest.raises(ValueError, match="vehicle_headway_s must be in"):
        SimConfig(vehicle_gap_m=2.0, vehicle_headway_s=-1.0).validate()


def test_spacing_moves_only_vehicles_too_close_and_leaves_a_full_lane_as_drawn():
    s0 = np.array([10.0, 30.0, 50.0])
    assert np.array_equal(citymod._spaced(s0, np.full(3, 30.0), 5.0, 100.0), s0)
    moved = citymod._spaced(s0, np.full(3, 15.0), 5.0, 100.0)
    np.testing.assert_allclose(moved, [10.0, 30.0, 50.0])  # 20 px apart already: unchanged
    moved = citymod._spaced(np.array([95.0, 5.0]), np.full(2, 15.0), 5.0, 100.0)
    np.testing.assert_allclose(moved, [95.0, 15.0])  # the gap across the lane's wrap


def test_simulated_flight_with_a_gap_has_fewer_touching_vehicles(tmp_path):
    shares = {}
    for gap in (None, 2.0):
        cfg = SimConfig(
            frame_size=(320, 240), n_frames=4, video=False, traffic_per_km=60.0, vehicle_gap_m=gap
        )
        out = tmp_path / str(gap)
        simulate(out, cfg)
        truth = load_truth(out)
        assert truth.config["vehicle_gap_m"] == gap
        v = truth.vehicles()
        crowd = [touching(v, np.flatnonzero(v["frame"] == k)) for k in range(4)]
        shares[gap] = float(np.concatenate(crowd).mean())
    assert shares[2.0] < 0.5 * shares[None], shares


def test_a_negative_gap_is_refused():
    with pytest.raises(ValueError, match="vehicle_gap_m must be in"):
        SimConfig(vehicle_gap_m=-1.0).validate()
