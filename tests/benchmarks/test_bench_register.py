"""``aerialreg bench register``'s plumbing: the hard-flight profiles (issue 11: error per tenth of
the flight, failed frames, REQCON's kept share, beside the baselines) and the speed options as
rows of their own (issue 15), on a tiny flight."""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import pytest

from app.cli import main as cli_main
from app.cli.commands.bench import PROFILE_RUNS
from benchmarks.register import our_runs, tenths
from registration.run import get_preset
from registration.synth import PROFILES


@pytest.mark.slow
def test_register_bench_on_a_hard_flight_reports_each_method_over_the_flight(capsys):
    """paper-hard, 15 frames at 480x360 (the fewest that meet its 0.6° shake): ours (default
    preset) and both baselines, each with finite errors per tenth; ours fails no frame, keeps
    most of its control points and beats plain OpenCV after the local stage (measured 1.10 px
    against 2.99)."""
    argv = ["bench", "register", "--profile", "paper-hard", "--size", "480x360", "--frames", "15"]
    code = cli_main([*argv, "--json"])
    out = json.loads(capsys.readouterr().out)["register"]
    assert code == 0
    assert (out["profile"], out["size"], out["frames"]) == ("paper-hard", [480, 360], 15)
    rows = out["rows"]
    # No paper preset on a profile.
    assert list(rows) == ["default", "fast", "opencv", "stabilo"]
    for key, row in rows.items():
        for stage in ("global", "local"):
            errors = [row[stage]["mean"], *row[stage]["tenths"].values()]
            assert all(np.isfinite(e) and e > 0 for e in errors), (key, stage, row[stage])
            per_frame = row[stage]["per_frame"]
            assert len(per_frame) == 15
            # 15 frames: tenths of 2 frames; the middle one starts at frame (15 - 2) // 2 = 6.
            first, middle, last = row[stage]["tenths"].values()
            assert np.allclose(
                [first, middle, last],
                [np.mean(per_frame[a:b]) for a, b in ((0, 2), (6, 8), (13, 15))],
                atol=1e-4,
            )
        assert row["times"]["total"] > 0
        # CPU per frame, decoding included: positive for every method, ours split in two.
        cpu = row["cpu"]
        assert cpu["total"] > 0 and cpu["registration"] > 0, (key, cpu)
        assert cpu["total"] == pytest.approx(cpu["registration"] + cpu["adjustment"])
    assert rows["default"]["cpu"]["adjustment"] > 0 and rows["fast"]["cpu"]["adjustment"] < 0.05
    ours = rows["default"]
    assert ours["failed_frames"] == 0 and ours["local"]["frames_off"] == 0
    kept = ours["reqcon_kept"]
    assert 0.5 < kept["min"] <= kept["mean"] <= 1.0, kept
    assert ours["local"]["mean"] < rows["opencv"]["local"]["mean"]
    # The per-tenth table names each method once per stage.
    table = out["markdown"].split("| pipeline | stage |")[1]
    assert table.count("| default preset |") == 2 and table.count("| fast preset (") == 2
    assert table.count("plain OpenCV") == 1 and table.count("Stabilo") == 1


def test_speed_options_add_one_thread_and_the_sift_coarse_step_as_rows():
    def runs(**kw):
        args = argparse.Namespace(**{"profile": None, "speed_options": False, **kw})
        return {key: (config, overlap) for key, config, overlap in our_runs(args)}

    plain = runs()
    assert list(plain) == ["default", "fast", "paper"]
    default, overlap = plain["default"]
    assert default.intra.fast_coarse and overlap  # as `aerialreg register` runs
    assert plain["fast"] == (get_preset("fast"), True)
    assert list(runs(profile="long-flight")) == ["default", "fast"]

    more = runs(speed_options=True)
    assert list(more) == ["default", "fast", "paper", "serial", "sift"]
    assert more["serial"] == (default, False)
    sift_cfg, sift_overlap = more["sift"]
    assert not sift_cfg.intra.fast_coarse and not sift_overlap
    # Nothing else differs from the default preset.
    fast = dataclasses.replace(sift_cfg.intra, fast_coarse=True)
    assert dataclasses.replace(sift_cfg, intra=fast) == default


def test_tenths_average_the_first_middle_and_last_tenth_ignoring_failed_frames():
    values = np.arange(20.0)
    assert tenths(values) == {"first": 0.5, "middle": 9.5, "last": 18.5}
    values[0] = np.nan  # a failed frame
    assert tenths(values)["first"] == 1.0
    assert tenths([3.0, 4.0, 5.0]) == {"first": 3.0, "middle": 4.0, "last": 5.0}
    assert np.isnan(tenths([np.nan, 1.0])["first"])


def test_bench_profiles_are_the_simulators():
    assert set(PROFILE_RUNS) == set(PROFILES)
