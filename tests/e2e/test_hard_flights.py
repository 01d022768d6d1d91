"""Hard flights (issue 11), against the simulator's exact truth: a flyover whose view leaves the
reference frame's footprint must not accumulate error (``long-flight`` profile, 40 frames at
480x360, 1.5 footprints of travel), and the paper's camera at its worst (``paper-hard``: a lens
beyond Harris, 0.15 s rolling shutter, 0.6° shake) must not fail frames nor lose most of its
control points to an absolute REQCON target."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import ndimage

from registration.evaluation import evaluate_truth
from registration.io import open_frames, read_image
from registration.run import ANCHOR_STAGE, get_preset, register_sequence
from registration.synth import PROFILES, load_truth, simulate

W, H, N = 480, 360, 40


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    out = tmp_path_factory.mktemp("long") / "sim"
    simulate(out, PROFILES["long-flight"](frame_size=(W, H), n_frames=N, video=False))
    return out


def _run(flight, out, config):
    truth = load_truth(flight)
    c = np.array([[W / 2, H / 2]])
    seed = (*c[0], *truth.frame_to_base(0, c)[0])
    result = register_sequence(
        open_frames(flight / "frames"), read_image(flight / "base.png"), truth.gamma, out,
        config=config, seed=seed,
    )  # fmt: skip
    gx, gy = np.meshgrid(np.linspace(0, W - 1, 9), np.linspace(0, H - 1, 7))
    grid = np.c_[gx.ravel(), gy.ravel()]
    err = np.array(
        [np.mean(np.hypot(*(result.frame_to_base(k, grid) - truth.frame_to_base(k, grid)).T))
         for k in range(N)]
    )  # fmt: skip
    return result, err


def _assert_mid_base_is_what_the_run_filled(result, out, intra) -> None:
    """The mid base image written with a re-anchored result holds only the reference frame and
    its anchors' raw pixels within ``intra.anchor_fill_radius`` (what the run filled it with),
    and no ghost of a frame outside its footprint. Checked every 7th pixel, 3 px inside the
    mask's edge (the rendering's lattice and the result's inverse differ by a fraction of a px
    there)."""
    valid = read_image(out / "mid_base_valid.png", grey=True) > 127
    inner = ndimage.binary_erosion(valid, iterations=3)
    ys, xs = np.nonzero(inner)
    b = np.c_[xs, ys][::7].astype(float)
    explained = np.zeros(len(b), bool)
    anchors = [k for k, r in enumerate(result.records) if r.stage == ANCHOR_STAGE]
    centre = np.array([W - 1, H - 1]) / 2
    for k in [result.reference_frame, *anchors]:
        q = result.base_to_frame(k, b, stage="local")
        ok = np.isfinite(q).all(axis=1)
        ok[ok] = (q[ok] >= -0.5).all(axis=1) & (q[ok] <= [W - 0.5, H - 0.5]).all(axis=1)
        if k != result.reference_frame:
            radius = np.hypot(*(q - centre).T) / (np.hypot(W, H) / 2)
            ok &= radius < intra.anchor_fill_radius + 0.01
        explained |= ok
    assert len(b) > 1000 and explained.all(), (len(b), int((~explained).sum()))


@pytest.mark.slow
def test_long_flight_does_not_drift(flight, tmp_path):
    """Default preset (re-anchoring, anchors filling the mid base image from their centre, and
    the base map behind the joint base): the last 10 frames are no worse than 1.2x the first 10
    (the issue's bar; measured 0.601 -> 0.553 px mean after the local stage, 0.642 -> 0.608
    before matches were read through the warp's lattice, 0.725 -> 0.766 when anchors filled
    from their whole frame) and stay within 1.3x the measured figures (last 10 0.553 px, worst
    frame 1.321 px); without re-anchoring and the base map, the chain of
    intra-sensor frames drifts off (measured 7.7 px over the first 10, 719 px over the last)."""
    cfg = get_preset("default")
    result, err = _run(flight, tmp_path / "default", cfg)
    assert all(r.status == "ok" for r in result.records)
    assert any(r.stage == ANCHOR_STAGE for r in result.records)
    first, last = err[:10].mean(), err[-10:].mean()
    assert last <= 1.2 * first, f"first 10 {first:.2f} px, last 10 {last:.2f} px"
    assert last < 0.72 and err.max() < 1.72, err.round(2)  # measured 0.553, 1.321
    _assert_mid_base_is_what_the_run_filled(result, tmp_path / "default", cfg.intra)

    paper_joint = dataclasses.replace(
        cfg, intra=dataclasses.replace(cfg.intra, reanchor_coverage=0.0, base_fallback=False)
    )
    _, drift = _run(flight, tmp_path / "paper-joint", paper_joint)
    # A frame of the drifting chain may fail (NaN): the drift is measured on those that did not.
    assert np.nanmean(drift[-10:]) > 20 * last, drift.round(1)


@pytest.mark.slow
def test_paper_hard_flight_has_no_failed_frame(tmp_path):
    """``paper-hard`` at 640x480, 20 frames: no frame fails (a previous version failed one with
    "REQCON failed: mean error 0.531 px ... still above 0.5"), REQCON keeps almost every
    control point (measured 99.5 %, worst frame 96.1 %; it kept 31-96 of ~150 before), and the
    errors stay within 1.3x the measured figures: local 0.718 px mean, global 0.912 px, with the
    lens's fourth-order term estimated from the reference frame (k2 0.0365, the truth's 0.04;
    with Harris alone 1.047 and 1.134; 0.833 and 1.031 before the photometric line). The issue's
    0.5 px bar, set at 1280x960, is not reached at 640x480: the frame's stretched corners,
    where few templates fit, weigh a lot on the evaluation's ground grid."""
    sim = tmp_path / "hard"
    simulate(sim, PROFILES["paper-hard"](frame_size=(640, 480), n_frames=20, video=False))
    truth = load_truth(sim)
    c = np.array([[320.0, 240.0]])
    seed = (*c[0], *truth.frame_to_base(0, c)[0])
    result = register_sequence(
        open_frames(sim / "frames"), read_image(sim / "base.png"), truth.gamma, tmp_path / "out",
        config=get_preset("default"), seed=seed,
    )  # fmt: skip
    assert [k for k, r in enumerate(result.records) if r.status != "ok"] == []
    kept = [r.stats["n_inliers"] / r.stats["n_control_points"] for r in result.records]
    assert np.mean(kept) >= 0.9 and min(kept) >= 0.75, np.round(kept, 2)
    s = evaluate_truth(result, truth).summary
    assert s["global"]["mean"] < 1.19, s["global"]  # measured 0.912
    assert s["local"]["mean"] < 0.94, s["local"]  # measured 0.718
    assert 0.03 < result.camera.k2 < 0.045, result.records[0].stats["lens"]  # 0.0365


@pytest.mark.slow
def test_a_map_finer_than_the_frames_keeps_the_local_stage_accurate(tmp_path):
    """``paper-hard`` at 640x480, 10 frames, against its map resampled to twice the resolution
    (the reference frame maps a frame px to ~2.4 base px): the local stage's cells, spacing and
    gates and the reference frame's field nodes follow the map (``LocalConfig.base_scale_above``
    of ``local`` and ``reference_local``), so they cover the same ground as against the native
    map. Measured against the paper's lengths in base px (the same run otherwise): error after
    local 1.332 vs 1.327 base px, motion after local 0.460 vs 0.889 (before the change test's
    photometric line: 1.827 vs 1.947 and 0.495 vs 1.345). Before the reference frame's nodes
    followed too (and before the lens's k2 was estimated): error 1.885, motion 1.039; the
    reference frame's field followed its matches' noise and the frames' smoother fields
    disagreed with it."""
    sim = tmp_path / "fine-map"
    cfg = PROFILES["paper-hard"](frame_size=(640, 480), n_frames=10, video=False)
    simulate(sim, dataclasses.replace(cfg, base_scale=2.0))
    truth = load_truth(sim)
    c = np.array([[320.0, 240.0]])
    seed = (*c[0], *truth.frame_to_base(0, c)[0])
    default = get_preset("default")
    error, motion = {}, {}
    for name, above in (("follows", default.local.base_scale_above), ("fixed", None)):
        config = dataclasses.replace(
            default,
            local=dataclasses.replace(default.local, base_scale_above=above),
            reference_local=dataclasses.replace(default.reference_local, base_scale_above=above),
        )
        result = register_sequence(
            open_frames(sim / "frames"), read_image(sim / "base.png"), truth.gamma,
            tmp_path / name, config=config, seed=seed,
        )  # fmt: skip
        assert all(r.status == "ok" for r in result.records)
        ev = evaluate_truth(result, truth)
        error[name] = ev.summary["local"]["mean"]
        motion[name] = ev.summary_motion["local"]["mean"]
    assert motion["follows"] < 0.6 * motion["fixed"], motion  # measured 0.460 vs 0.889
    # Since the change test's photometric line, the error no longer differs (it did before:
    # 1.827 vs 1.947): following the map must not cost accuracy.
    assert error["follows"] < 1.05 * error["fixed"], error  # measured 1.332 vs 1.327
    assert error["follows"] < 1.6, error  # 1.2x the measured 1.332
