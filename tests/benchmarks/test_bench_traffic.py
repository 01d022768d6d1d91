"""``aerialreg bench traffic``'s plumbing: the traffic stage on aerialreg's registration and on
plain OpenCV stabilisation, scored against the vehicle truth in one run, with CPU per frame."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main as cli_main


@pytest.mark.slow
def test_traffic_bench_scores_both_registrations_against_the_truth(capsys):
    argv = ["bench", "traffic", "--size", "480x360", "--frames", "12", "--seed", "2", "--json"]
    assert cli_main(argv) == 0
    out = json.loads(capsys.readouterr().out)["traffic"]
    assert (out["size"], out["frames"], out["profile"]) == ([480, 360], 12, "default")
    assert list(out["rows"]) == ["aerialreg", "opencv"]
    for row in out["rows"].values():
        assert 0 < row["precision"] <= 1 and 0 < row["recall"] <= 1 and row["mota"] <= 1
        assert row["truth_tracks"] > 0 and row["frames"] > 0
        for key in ("position_rmse_m", "speed_rmse_mps", "cpu_s_per_frame"):
            assert np.isfinite(row[key]) and row[key] > 0, key
        assert row["registration_cpu_s_per_frame"] > 0
        # Leaving out touching vehicles leaves no more true objects (the flights' vehicles keep
        # their distance in their lanes; they still meet at intersections).
        assert 0 < row["separable"]["truth_objects"] <= row["truth_objects"]
        # Every frame of the flight is scored, the ones a registration lost too.
        assert row["frames"] == 12
    table = out["markdown"]
    assert "| aerialreg (default preset) |" in table and "| plain OpenCV stabilisation |" in table
    assert table.count(", separable vehicles |") == 2


@pytest.mark.parametrize(
    "argv, size, frames",
    [
        (["traffic"], "1280x960", 25),
        (["traffic", "--profile", "long-flight"], "640x480", 120),
        (["traffic", "--profile", "paper-hard"], "1280x960", 25),
        (["traffic", "--frames", "9"], "1280x960", 9),
    ],
)
def test_traffic_bench_takes_the_profile_s_flight(monkeypatch, capsys, argv, size, frames):
    """A profile's own size and frames (a long flight is 120 frames), else the suite's 25."""
    import types

    from app.cli.commands import bench

    seen = {}
    stub = types.SimpleNamespace(TITLE="t", run=lambda args: seen.update(vars(args)) or {})
    monkeypatch.setattr(bench, "suite_module", lambda name: stub)
    assert cli_main(["bench", *argv]) == 0
    assert (seen["size"], seen["frames"]) == (size, frames)
