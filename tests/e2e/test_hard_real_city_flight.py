"""The hard flight of the sequence-adjustment issue, over real city texture: a lens a little
beyond Harris, a slow rolling shutter, shake, and a map turned 149°.

The issue reported a flight like this (real city texture; Harris γ 0.7 plus a small extra radial
term, 4 raw px at the corners; 0.15 s rolling shutter; 0.6° shake; a map turned 149°; 12 frames
of 1280x960) on which the three last frames ended 4.4-10.2 px off while marked ``ok``. Here the
simulator renders it from a real 4K nadir drone photo of Songdo intersections (roofs, roads,
markings, trees) with the paper-hard profile's camera, k2 = -0.0076, and its base map turned by
149°; one click at the reference frame's centre, default preset. Every frame must come out
close to the truth, or be flagged.

Measured (this release): after the global stage 0.517 px mean, after the local stage 0.193
(frames 0.13-0.22); predicted errors 0.04-0.13 px; none flagged. The reference frame's own
fourth-order estimate was k2 = -0.0069 ± 0.0002 (truth -0.0076), below the 0.02 under which one
frame cannot tell the lens from relief, so Harris is kept; the local stage absorbs the rest.
"""

from __future__ import annotations

import numpy as np
import pytest

from registration.evaluation import evaluate_truth
from registration.synth import load_truth, simulate
from registration.synth.profiles import profile_config
from tests.conftest import register, shared_data

K2 = -0.0076


@pytest.fixture(scope="module")
def songdo_flight(tmp_path_factory):
    scene = shared_data("songdo-vision-drone", "images") / "00164.jpg"
    out = tmp_path_factory.mktemp("songdo") / "sim"
    cfg = profile_config(
        "paper-hard",
        frame_size=(1280, 960),
        n_frames=12,
        lens_k2=K2,
        base_heading_deg=149.0,
        frame_scale=0.8,
        video=False,
    )
    simulate(out, cfg, scene=scene)
    return out


@pytest.mark.slow
def test_a_hard_flight_over_real_city_texture_has_no_frame_off_and_marked_ok(
    songdo_flight, tmp_path
):
    truth = load_truth(songdo_flight)
    assert truth.n_frames == 12
    result = register(songdo_flight, tmp_path / "out")
    assert [r.status for r in result.records] == ["ok"] * 12
    report = evaluate_truth(result, truth)
    local = np.array([f["local"]["mean"] for f in report.per_frame])
    flagged = [f["frame"] for f in report.per_frame if f["flagged"]]
    # No frame worse than the 1.5 px may go unflagged; measured 0.13-0.22 px, none
    # flagged.
    unflagged_off = [k for k, e in enumerate(local) if e > 1.5 and k not in flagged]
    assert not unflagged_off, (unflagged_off, local)
    assert local.max() < 0.5, local
    assert report.summary["local"]["mean"] < 0.3, report.summary["local"]
    assert report.summary["global"]["mean"] < 0.8, report.summary["global"]
    # The reference frame measured the lens beyond Harris, with the right sign and about its
    # size, and (below the level at which one frame tells it from relief) kept Harris.
    k2 = result.records[result.reference_frame].stats["lens"]["k2"]
    assert -0.0095 < k2 < -0.0055, k2
    assert result.records[result.reference_frame].lens_k2 == 0.0
