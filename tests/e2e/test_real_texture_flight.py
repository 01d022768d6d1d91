"""A flight over real texture against a real map of another date: small, low-texture frames.

The simulator renders 320x240 frames from one real nadir drone photo of a roundabout (SDD
deathCircle, video 0: asphalt, painted lines, a lawn), and the base map is another flight's photo
of the same place (video 2: other light, other people). Their homography is estimated from the
two photos (full-resolution SIFT, MAGSAC, ~130 inliers at 0.6 px RMS), so the absolute truth is
only as good as that (~1 px); the motion between frames is exact (both come from the same
scene). Before the fast path's templates followed the frame's size, 7 of these 16 frames failed
and 5 of the rest were returned 4-1270 px off: 320x240 frames held ~30 templates of which
10-22 matched (24 needed), the fast path's coverage check refused matches on half of the frame,
and the SIFT fallback fitted a projective to 8 clustered matches."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from registration.run import get_preset
from registration.synth import SimConfig, load_truth, simulate
from tests.conftest import register, shared_data

W, H = 320, 240
N_FRAMES = 16


def _scene_to_base(scene_path, base_path) -> np.ndarray:
    a = cv2.imread(str(scene_path), cv2.IMREAD_GRAYSCALE)
    b = cv2.imread(str(base_path), cv2.IMREAD_GRAYSCALE)
    sift = cv2.SIFT_create(nfeatures=20000)
    ka, da = sift.detectAndCompute(a, None)
    kb, db = sift.detectAndCompute(b, None)
    pairs = cv2.BFMatcher().knnMatch(da, db, k=2)
    good = [m for m, n in pairs if m.distance < 0.75 * n.distance]
    pa = np.float32([ka[m.queryIdx].pt for m in good])
    pb = np.float32([kb[m.trainIdx].pt for m in good])
    hom, inliers = cv2.findHomography(pa, pb, cv2.USAC_MAGSAC, 1.0, maxIters=20000,
                                      confidence=0.9999)  # fmt: skip
    assert hom is not None and inliers.sum() >= 80, "the two photos no longer register"
    return hom


@pytest.fixture(scope="module")
def roundabout(tmp_path_factory):
    folder = shared_data("sdd-reference-frames", "deathCircle")
    scene, base = folder / "video0" / "reference.jpg", folder / "video2" / "reference.jpg"
    out = tmp_path_factory.mktemp("roundabout") / "sim"
    simulate(
        out,
        SimConfig(frame_size=(W, H), n_frames=N_FRAMES, seed=1, video=False),
        scene=scene,
        base=base,
        base_from_scene=_scene_to_base(scene, base).ravel().tolist(),
    )
    return out


def _errors(result, truth) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: mean error after global against the truth (base px; nan where failed) and
    mean error of the motion to the reference frame after local (exact; px of base)."""
    gx, gy = np.meshgrid(np.linspace(20, W - 20, 8), np.linspace(20, H - 20, 6))
    q = np.c_[gx.ravel(), gy.ravel()]
    ref_truth, ref_est = truth.frame_to_base(0, q), result.frame_to_base(0, q, stage="local")
    absolute, motion = [], []
    for k in range(truth.n_frames):
        if result.status(k) != "ok":
            absolute.append(np.nan)
            motion.append(np.nan)
            continue
        est = result.frame_to_base(k, q, stage="global")
        absolute.append(np.nanmean(np.hypot(*(est - truth.frame_to_base(k, q)).T)))
        # Where frame k's points lie relative to the reference frame's, against the truth's.
        moved = result.frame_to_base(k, q, stage="local") - ref_est
        moved_truth = truth.frame_to_base(k, q) - ref_truth
        motion.append(np.nanmean(np.hypot(*(moved - moved_truth).T)))
    return np.array(absolute), np.array(motion)


@pytest.mark.slow
def test_small_low_texture_frames_over_a_real_map_register_every_frame(roundabout, tmp_path):
    truth = load_truth(roundabout)
    result = register(roundabout, tmp_path / "out")
    failed = [k for k in range(N_FRAMES) if result.status(k) != "ok"]
    assert not failed, [result.records[k].reason for k in failed]
    stats = [result.records[k].stats for k in range(1, N_FRAMES)]
    assert [st["coarse_path"] for st in stats] == ["fast"] * (N_FRAMES - 1), stats
    # Frame 10's agreeing templates span 47 % of it, and the SIFT step finds 7 matches: the fast
    # path's model is kept, and the record says so.
    kept = [st["fast_path_reason"] for st in stats if st.get("fast_path_reason")]
    assert len(kept) <= 3 and all("kept, as the SIFT step failed" in r for r in kept), kept
    absolute, motion = _errors(result, truth)
    # measured: after global 0.92-1.37 px against the photos' homography; motion 0.26-0.62 px
    assert absolute.max() < 3.0, absolute
    assert np.nanmean(motion[1:]) < 0.8 and motion.max() < 1.5, motion


@pytest.mark.slow
def test_the_sift_fallback_alone_fails_with_reasons_and_never_grossly(roundabout, tmp_path):
    """With the fast path off, the paper's SIFT step alone finds 7-14 keypoints per frame here:
    frames with too few matches fail with a reason. None is returned grossly wrong any more: a
    projective on 8 matches in one part of the frame put its far side up to 760 px off, and a
    polyprojective on control points along one side 190 px; both models are now chosen by the
    matches' spread and cross-validation (``projective_or_simpler``,
    ``IntraConfig.sparse_support``; on this grid, 20 px inside the frame, the second moves
    frame 4 only from 8.3 to 7.6 px, so its own test is in test_model_choice.py).
    What remains is the fallback's real limit on such frames: measured, 6 of 16 fail, and the
    frames returned are 0.9-7.6 px off but one, 11.8 px."""
    truth = load_truth(roundabout)
    cfg = get_preset("default")
    sift_only = dataclasses.replace(cfg, intra=dataclasses.replace(cfg.intra, fast_coarse=False))
    result = register(roundabout, tmp_path / "out", config=sift_only)
    absolute, _ = _errors(result, truth)
    ok = np.isfinite(absolute)
    assert ok.sum() >= N_FRAMES // 2, absolute
    assert absolute[ok].max() < 25.0, absolute
    for k in np.flatnonzero(~ok):
        assert "coarse step" in result.records[k].reason, result.records[k]
