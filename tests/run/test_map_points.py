"""An analyst's map points on a registered flight (``registration.run.set_map_points``), against
the simulator's exact truth: a frame registered 30 base px off, which its links cannot reach
and which the adjustment can only flag, is put back by one map point without pulling its
neighbours; adding points and adjusting again reaches the same bits as a run that had them from
the start, and leaves the frames before their window as they were; bad points are refused in one
line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import registration
from registration.adjustment import MapPoint, SequenceAdjustConfig
from registration.errors import ResultBusy
from registration.io import file_sha256, open_frames
from registration.run.adjust import adjust_result
from registration.run.config import config_to_dict
from registration.run.map_points import read_map_points, set_map_points
from registration.run.result_folder import ResultLock
from registration.run.writer import ResultWriter
from registration.synth import load_truth
from tests.run.test_adjust import _grid, _map_error, _plant_offset, _strip_adjustment

# Windows of 4 frames, 2 final each: the 6 frames take windows (0, 4) and (2, 6); frame 4 is
# only in the second.
SMALL = SequenceAdjustConfig(window_frames=4, final_frames=2, link_steps=(1, 2))
PLANTED = 4
OFFSET = (18.0, 24.0)  # 30 base px: beyond the links' search


def _folder(sim_seq, default_result, out: Path) -> Path:
    """``default_result`` as each frame's own registration left it, with frame PLANTED
    registered OFFSET off, and SMALL as the folder's adjustment settings (the frames' own
    registrations do not depend on them)."""
    shutil.copytree(default_result.out_dir, out)
    frames = open_frames(sim_seq / "frames")
    _strip_adjustment(out, frames)
    _plant_offset(out, frames, PLANTED, OFFSET)
    meta = json.loads((out / "result.json").read_text())
    meta["config"]["adjust"] = config_to_dict(SMALL)
    (out / "result.json").write_text(json.dumps(meta))
    return out


def _adjust(sim_seq, out: Path) -> None:
    frames = open_frames(sim_seq / "frames")
    writer = ResultWriter(out, ResultLock(out).acquire(), frames)
    try:
        adjust_result(writer, frames, SMALL)
    finally:
        writer.close()


def _points(sim_seq, n: int = 1) -> list[MapPoint]:
    """``n`` map points of frame PLANTED at the truth, as an analyst would click them."""
    truth = load_truth(sim_seq)
    w, h = truth.frame_size
    xy = np.array([[0.3 * w, 0.35 * h], [0.7 * w, 0.65 * h]])[:n]
    base = truth.frame_to_base(PLANTED, xy)
    return [MapPoint(PLANTED, tuple(f), tuple(b)) for f, b in zip(xy, base, strict=True)]


@pytest.fixture(scope="module")
def with_points(sim_seq, default_result, tmp_path_factory):
    out = _folder(sim_seq, default_result, tmp_path_factory.mktemp("mp") / "out")
    set_map_points(out, _points(sim_seq))
    _adjust(sim_seq, out)
    return out


def test_map_points_put_back_a_frame_its_links_cannot_reach(sim_seq, default_result, with_points):
    truth = load_truth(sim_seq)
    result = registration.load(with_points)
    assert _map_error(result.unadjusted(), truth, PLANTED) > 25
    adjustment = result.records[PLANTED].stats["adjustment"]
    # Measured 30.07 -> 0.20 px at the global stage and 0.13 at the local one (the frame's
    # own registration, before it was planted off: 0.24 and 0.10), with 844 link points;
    # without the map point it keeps its 30 px and is flagged "no links to its neighbours".
    assert _map_error(result, truth, PLANTED) < 0.5
    assert _map_error(result, truth, PLANTED, "local") < 0.5
    assert adjustment["flagged"] == "" and adjustment["n_links"] > 50
    assert adjustment["n_map_points"] == 1 and adjustment["map_point_rms_px"] < 1.0
    assert adjustment["n_controls"] == 0
    assert "own control points were set aside" in adjustment["note"]
    for k in (1, 2, 3, 5):
        own = _map_error(default_result.unadjusted(), truth, k)
        assert _map_error(result, truth, k) < own + 0.1, k
        own_local = _map_error(default_result.unadjusted(), truth, k, "local")
        assert _map_error(result, truth, k, "local") < own_local + 0.05, k
        assert "n_map_points" not in result.records[k].stats["adjustment"]
    assert read_map_points(with_points) == _points(sim_seq)


def test_points_added_later_reach_the_same_bits_and_keep_earlier_windows(
    sim_seq, default_result, with_points, tmp_path, monkeypatch
):
    out = _folder(sim_seq, default_result, tmp_path / "out")
    hashed = []  # the adjustment keeps each record's hash of its input image
    monkeypatch.setattr("registration.run.writer.file_sha256", hashed.append)
    _adjust(sim_seq, out)
    assert registration.load(out).records[PLANTED].stats["adjustment"]["flagged"]
    before = {k: (out / "frames" / f"{k:06d}.json").read_bytes() for k in range(6)}
    # Two points, then the one of the run that had it from the start.
    for points in (_points(sim_seq, 2), _points(sim_seq, 1)):
        undone = set_map_points(out, points)
        assert undone == [2, 3, 4, 5]  # the window (2, 6) holds frame 4; (0, 4) does not
        result = registration.load(out)
        assert [result.is_adjusted(k) for k in range(6)] == [True] * 2 + [False] * 4
        for k in (0, 1):
            assert (out / "frames" / f"{k:06d}.json").read_bytes() == before[k]
        _adjust(sim_seq, out)
    for k in range(6):
        for suffix in (".json", ".npz"):
            a = (out / "frames" / f"{k:06d}{suffix}").read_bytes()
            b = (with_points / "frames" / f"{k:06d}{suffix}").read_bytes()
            assert a == b, (k, suffix)
    assert not hashed
    frames = open_frames(sim_seq / "frames")
    for k, record in enumerate(registration.load(out).records):
        assert record.input_sha256 == file_sha256(frames.path(k)), k
    # Removing it again: back to the run without it.
    assert set_map_points(out, []) == [2, 3, 4, 5]
    _adjust(sim_seq, out)
    for k in range(6):
        assert (out / "frames" / f"{k:06d}.json").read_bytes() == before[k], k


def test_a_mis_click_on_a_good_frame_is_flagged_and_moves_nothing(
    sim_seq, default_result, tmp_path
):
    """A map point 6 base px from the truth on frame 2, which is registered well: its image
    confirms its own model, not the click's, so the frame stays (within 0.05 px of the run
    without the point) and is flagged for its map point; its neighbours do not move."""
    out = _folder(sim_seq, default_result, tmp_path / "out")
    _adjust(sim_seq, out)
    without = registration.load(out)
    truth = load_truth(sim_seq)
    w, h = truth.frame_size
    fxy = np.array([[0.5 * w, 0.5 * h]])
    bxy = truth.frame_to_base(2, fxy)[0] + [6.0, 0.0]
    set_map_points(out, [MapPoint(2, tuple(fxy[0]), tuple(bxy))])
    _adjust(sim_seq, out)
    result = registration.load(out)
    adjustment = result.records[2].stats["adjustment"]
    assert adjustment["flagged"].startswith("its map points are") and adjustment["n_controls"] > 0
    assert "which its image confirms" in adjustment["note"] and "it is kept" in adjustment["note"]
    for k in (1, 2, 3):
        for stage in ("global", "local"):
            g = _grid(truth)
            moved = np.hypot(
                *(result.frame_to_base(k, g, stage) - without.frame_to_base(k, g, stage)).T
            )
            assert moved.mean() < 0.05, (k, stage)


def test_bad_map_points_are_refused_in_one_line(sim_seq, with_points):
    (good,) = _points(sim_seq)[:1]
    cases = [
        (MapPoint(6, good.frame_xy, good.base_xy), r"frame 6: no such frame \(.*0\.\.5\)"),
        (MapPoint(0, good.frame_xy, good.base_xy), r"frame 0: it is the reference frame"),
        (MapPoint(2, (-40.0, 10.0), good.base_xy), r"frame point \(-40\.0, 10\.0\) is outside"),
        (MapPoint(2, good.frame_xy, (1e6, 5.0)), r"map point \(1000000\.0, 5\.0\) is outside"),
    ]
    for point, message in cases:
        with pytest.raises(ValueError, match=message) as err:
            set_map_points(with_points, [point])
        assert "\n" not in str(err.value)
    assert read_map_points(with_points) == _points(sim_seq)  # nothing changed
    lock = ResultLock(with_points).acquire()
    try:
        with pytest.raises(ResultBusy):
            set_map_points(with_points, [])
    finally:
        lock.release()


def test_a_folder_without_the_adjustment_refuses_map_points(sim_seq, tmp_path, default_result):
    out = tmp_path / "out"
    shutil.copytree(default_result.out_dir, out)
    meta = json.loads((out / "result.json").read_text())
    meta["config"]["adjust"] = None
    (out / "result.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="registered without the sequence adjustment"):
        set_map_points(out, _points(sim_seq))


def test_the_adjust_command_adds_a_point_and_adjusts_again(
    sim_seq, default_result, tmp_path, capsys
):
    """``aerialreg adjust OUT --add K,FX,FY,BX,BY``: the point stored, the frames it touches
    adjusted again with the folder's own settings and frame source, the frame's outcome said."""
    from app.cli import main as cli_main

    out = _folder(sim_seq, default_result, tmp_path / "out")
    assert cli_main(["adjust", str(out), "--json"]) == 0  # no points: adjusts the rest
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_readjusted"] == 6 and summary["n_map_points"] == 0
    assert registration.load(out).records[PLANTED].stats["adjustment"]["flagged"]
    (p,) = _points(sim_seq)
    spec = f"{PLANTED}," + ",".join(f"{v:.4f}" for v in (*p.frame_xy, *p.base_xy))
    assert cli_main(["adjust", str(out), "--add", spec]) == 0
    text = capsys.readouterr().out
    assert "1 map point(s)" in text and "adjusted 4 frame(s) again" in text
    assert f"frame {PLANTED}: 1 map point(s)" in text and "set aside" in text
    assert "flagged" not in text
    truth = load_truth(sim_seq)
    assert _map_error(registration.load(out), truth, PLANTED) < 0.5
    assert cli_main(["adjust", str(out), "--add", "4,1,2"]) == 2
    assert "--add must be K,FX,FY,BX,BY, got '4,1,2'" in capsys.readouterr().err
    # Frames that are not the run's: refused in one line, before anything is adjusted.
    other = tmp_path / "other"
    other.mkdir()
    for k in range(3):
        shutil.copy(sim_seq / "frames" / f"{k:06d}.png", other)
    before = read_map_points(out)
    assert cli_main(["adjust", str(out), "--frames", str(other), "--add", spec]) == 2
    assert (
        "the frames (3 of 640x480) are not the result's (6 of 640x480)" in capsys.readouterr().err
    )
    assert read_map_points(out) == before  # no point changed, no frame left to adjust again
    assert all(registration.load(out).is_adjusted(k) for k in range(6))
    assert cli_main(["adjust", str(out), "--remove", str(PLANTED), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_map_points"] == 0 and summary["n_readjusted"] == 4
    assert registration.load(out).records[PLANTED].stats["adjustment"]["flagged"]
