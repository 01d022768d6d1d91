"""Tests for registration.global_registration.heading: heading and scale from one seed, two seeds or none, the gate
built on them and guided matching, against known similarities with outliers at named indices."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from registration.geometry import Similarity
from registration.global_registration import (
    HeadingConfig,
    SimilarityPrior,
    attribute_differences,
    gate_by_prior,
    guided_matches,
    prior_from_patch,
    prior_from_seed,
    prior_from_seeds,
    priors_without_seed,
)
from registration.matching import Keypoints, detect_sift, match_ratio, to_grey
from tests.conftest import shared_data

TRUE_HEADING, TRUE_SCALE = 143.0, 0.55


def _matches(rng, heading=TRUE_HEADING, scale=TRUE_SCALE, n_true=60, n_false=540):
    """Candidate matches: ``n_true`` right ones (1 px noise, keypoint attributes agreeing with
    the similarity up to SIFT-like noise), the rest random with random attributes."""
    truth = Similarity.from_rotation(heading, scale, (320, 240), (900, 700))
    src = rng.uniform(0, [640, 480], (n_true + n_false, 2))
    dst = truth.apply(src) + rng.normal(0, 1.0, src.shape)
    dst[n_true:] = rng.uniform(0, 1800, (n_false, 2))
    att_h = np.r_[heading + rng.normal(0, 8, n_true), rng.uniform(0, 360, n_false)] % 360
    att_s = np.r_[math.log(scale) + rng.normal(0, 0.15, n_true), rng.normal(0, 0.7, n_false)]
    return truth, src, dst, att_h, att_s


@pytest.mark.parametrize("heading", [0.0, 90.0, 143.0, 180.0, 271.0])
@pytest.mark.parametrize("scale", [0.5, 1.0, 2.0])
def test_prior_from_seed_at_any_heading_and_scale(rng, heading, scale):
    truth, src, dst, att_h, att_s = _matches(rng, heading, scale)
    seed_src = np.array([300.0, 200.0])
    seed_dst = truth.apply(seed_src[None])[0] + (1.5, -1.2)  # a click ~2 px off
    prior = prior_from_seed(src, dst, att_h, att_s, seed_src, seed_dst)
    gap = abs((prior.heading_deg - heading + 180) % 360 - 180)
    assert gap < 2.0, f"heading {prior.heading_deg:.1f} vs {heading}"
    assert prior.scale == pytest.approx(scale, rel=0.04)
    assert prior.votes >= 20 and prior.ambiguity < 0.6


def test_gate_by_prior_keeps_the_right_matches_and_drops_named_wrong_ones(rng):
    truth, src, dst, att_h, att_s = _matches(rng)
    seed_src = np.array([300.0, 200.0])
    seed_dst = truth.apply(seed_src[None])[0]
    # Named wrong matches, each breaking one bound of the gate just beyond its tolerance.
    far = seed_src + np.array([250.0, 120.0])
    rot = Similarity.from_rotation(TRUE_HEADING + 25, TRUE_SCALE, seed_src, seed_dst)
    big = Similarity.from_rotation(TRUE_HEADING, TRUE_SCALE * 1.4, seed_src, seed_dst)
    mirror = 2 * seed_dst - truth.apply(far[None])[0]
    named = {600: rot.apply(far[None])[0], 601: big.apply(far[None])[0], 602: mirror}
    src = np.vstack([src, [far] * 3])
    dst = np.vstack([dst, list(named.values())])
    prior = SimilarityPrior(TRUE_HEADING, TRUE_SCALE, seed_src, seed_dst, "seed", 60, 0.0, 4.0)
    keep = gate_by_prior(src, dst, prior)
    assert keep[:60].all(), "every right match passes the gate"
    for i in named:
        assert not keep[i], f"named wrong match {i} passed"
    assert keep[:60].sum() / keep.sum() > 0.5  # from 10 % right matches before the gate


def test_prior_from_two_seeds_is_exact_and_rejects_coincident_points():
    truth = Similarity.from_rotation(212.0, 1.7, (0, 0), (500, 400))
    f = np.array([[100.0, 80.0], [400.0, 300.0]])
    prior = prior_from_seeds(f, truth.apply(f))
    assert prior.heading_deg == pytest.approx(212.0) and prior.scale == pytest.approx(1.7)
    np.testing.assert_allclose(prior.apply(f), truth.apply(f), atol=1e-9)
    with pytest.raises(ValueError, match="different points"):
        prior_from_seeds(np.array([[5.0, 5.0], [5.2, 5.0]]), truth.apply(f))


def test_priors_without_seed_find_the_similarity_first(rng):
    truth, src, dst, att_h, att_s = _matches(rng, 250.0, 1.6, n_true=40, n_false=760)
    priors = priors_without_seed(src, dst, att_h, att_s, 640.0)
    assert priors, "no candidate"
    best = priors[0]
    assert abs((best.heading_deg - 250.0 + 180) % 360 - 180) < 3.0
    assert best.scale == pytest.approx(1.6, rel=0.05)
    probe = np.array([[0.0, 0.0], [639.0, 479.0]])
    assert np.abs(best.apply(probe) - truth.apply(probe)).max() < 15.0
    assert best.ambiguity < 0.7


def test_priors_without_seed_on_pure_noise_are_weak(rng):
    _, src, dst, att_h, att_s = _matches(rng, n_true=0, n_false=400)
    priors = priors_without_seed(src, dst, att_h, att_s, 640.0)
    assert not priors or priors[0].votes < 12


def _keypoints(xy, desc, angle, size) -> Keypoints:
    return Keypoints(np.asarray(xy, float), np.asarray(desc, np.float32), np.asarray(size, float),
                     np.asarray(angle, float), np.zeros(len(xy)))  # fmt: skip


def test_guided_matches_find_the_right_partner_among_look_alikes(rng):
    """Each frame keypoint has its partner near the prediction and a look-alike (same
    descriptor plus a little noise) far away: a global ratio test rejects both, the guided
    search keeps the right one."""
    n = 50
    fxy = rng.uniform(0, 600, (n, 2))
    desc = rng.normal(0, 1, (n, 128)).astype(np.float32)
    truth = Similarity.from_rotation(60.0, 0.8, (0, 0), (100, 50))
    bxy = np.vstack([truth.apply(fxy), truth.apply(fxy) + rng.uniform(150, 300, (n, 2))])
    bdesc = np.vstack(
        [desc + rng.normal(0, 0.03, desc.shape), desc + rng.normal(0, 0.032, desc.shape)]
    )
    frame = _keypoints(fxy, desc, np.full(n, 10.0), np.full(n, 4.0))
    base = _keypoints(bxy, bdesc, np.full(2 * n, 70.0), np.full(2 * n, 3.2))
    assert len(match_ratio(frame, base, 0.8)) < n / 2
    pred = truth.apply(fxy) + rng.normal(0, 3, (n, 2))
    m = guided_matches(frame, base, pred, 20.0, 60.0, 0.8)
    assert len(m) == n and (m.idx_b == m.idx_a).all()
    # Keypoints whose orientation disagrees with the heading by more than the tolerance drop.
    wrong = _keypoints(bxy, bdesc, np.full(2 * n, 150.0), np.full(2 * n, 3.2))
    assert len(guided_matches(frame, wrong, pred, 20.0, 60.0, 0.8)) == 0


def test_prior_from_seed_on_a_real_pair_at_several_headings():
    """A real aerial image against the same place four years later (SRIF pair 1, known
    similarity), the first image turned by 0, 90, 180 and 270 degrees more: one seed from the
    ground truth gives the heading within 2 degrees and the scale within 3 %."""
    folder = shared_data("srif-optical-optical")
    gt = np.vstack([np.loadtxt(folder / "gt_1.txt"), [0, 0, 1]])
    a0 = to_grey(cv2.imread(str(folder / "pair1_1.jpg")))
    b = to_grey(cv2.imread(str(folder / "pair1_2.jpg")))
    kb = detect_sift(b, mask=(b > 0).astype(np.uint8))
    h, w = a0.shape
    seed_a0 = np.array([w / 2, h / 2])
    for turns in range(4):
        a = np.rot90(a0, -turns).copy()  # clockwise on screen
        # a's pixel (x, y) shows a0's pixel rot^-1: build a0_from_a for the truth.
        a0_from_a = np.eye(3)
        for _ in range(turns):
            # one clockwise quarter turn: a(x, y) = prev(y, H_prev - 1 - x)
            hp = a0.shape[0] if _ % 2 == 0 else a0.shape[1]
            a0_from_a = a0_from_a @ np.array([[0, 1, 0], [-1, 0, hp - 1], [0, 0, 1.0]])
        b_from_a = gt @ a0_from_a
        ka = detect_sift(a)
        m = match_ratio(ka, kb, 0.8)
        seed_a = np.linalg.solve(a0_from_a, np.r_[seed_a0, 1])[:2]
        seed_b = (b_from_a @ np.r_[seed_a, 1])[:2] + (1.0, 1.5)
        prior = prior_from_seed(ka.xy[m.idx_a], kb.xy[m.idx_b], *attribute_differences(ka, kb, m),
                                seed_a, seed_b)  # fmt: skip
        true_heading = math.degrees(math.atan2(b_from_a[1, 0], b_from_a[0, 0])) % 360
        true_scale = math.sqrt(abs(np.linalg.det(b_from_a[:2, :2])))
        gap = abs((prior.heading_deg - true_heading + 180) % 360 - 180)
        assert gap < 2.0, f"turn {turns}: heading {prior.heading_deg:.1f} vs {true_heading:.1f}"
        assert prior.scale == pytest.approx(true_scale, rel=0.03)


@pytest.mark.parametrize("heading,scale", [(0.0, 1.0), (143.0, 0.55), (250.0, 1.8)])
def test_prior_from_patch_recovers_a_known_similarity(heading, scale):
    """A real aerial image resampled by a known similarity about a seed 2 px off: the patch
    search gives the heading within 3 degrees and the scale within 6 %, with no keypoint."""
    folder = shared_data("srif-optical-optical")
    frame = to_grey(cv2.imread(str(folder / "pair3_2.jpg")))
    seed_f = np.array([260.0, 250.0])
    seed_b = np.array([400.0, 380.0])
    truth = Similarity.from_rotation(heading, scale, seed_f, seed_b)
    base = cv2.warpAffine(frame, truth.matrix[:2], (800, 760), flags=cv2.INTER_LINEAR)
    prior = prior_from_patch(frame, base, seed_f, seed_b + (1.2, -1.6), base_valid=base > 0)
    assert prior is not None
    gap = abs((prior.heading_deg - heading + 180) % 360 - 180)
    assert gap < 3.0, f"heading {prior.heading_deg:.1f} vs {heading}"
    assert prior.scale == pytest.approx(scale, rel=0.06)
    assert prior.votes == 0 and prior.source == "seed"


def test_prior_from_patch_finds_nothing_on_a_blank_map_or_at_its_edge():
    frame = np.random.default_rng(1).integers(0, 255, (200, 200), dtype=np.uint8)
    blank = np.full((300, 300), 128, np.uint8)
    assert prior_from_patch(frame, blank, (100, 100), (150, 150)) is None
    assert prior_from_patch(frame, frame, (100, 100), (5, 100)) is None  # patch leaves the map


def test_heading_config_validation():
    with pytest.raises(ValueError, match="guided_ratio"):
        HeadingConfig(guided_ratio=1.5)
    with pytest.raises(ValueError, match="bin_deg"):
        HeadingConfig(bin_deg=0)
    with pytest.raises(ValueError, match="patch_radius_px"):
        HeadingConfig(patch_radius_px=2)
