"""The image-only consistency measure (registration.evaluation.consistency) against known truth:
frames cut from one texture at known sub-pixel offsets, and mappings that are right, or wrong by a
known amount in one frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from registration.evaluation.consistency import map_agreement, pair_consistency, summarise
from registration.matching import ProbeConfig, probe_grid

W, H = 320, 240
OFFSETS = np.array([[40.0, 30.0], [47.3, 25.4], [55.1, 21.8]])  # frame k's corner in the texture


def _texture(rng) -> np.ndarray:
    noise = rng.normal(0, 1, (400, 480)).astype(np.float32)
    img = cv2.GaussianBlur(noise, (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min()) * 220 + 20
    return img.astype(np.float32)


def _frames(rng) -> list[np.ndarray]:
    tex = _texture(rng)
    out = []
    for ox, oy in OFFSETS:
        m = np.float32([[1, 0, ox], [0, 1, oy]])
        out.append(
            cv2.warpAffine(tex, m, (W, H), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
            .round()
            .astype(np.uint8)
        )
    return out


class _Shifts:
    """A registration made of one translation per frame (base = texture px)."""

    lens = None

    def __init__(self, offsets):
        self.offsets = np.asarray(offsets, float)

    def frame_to_base(self, k, xy, stage="local"):
        return np.asarray(xy, float) + self.offsets[k]

    def base_to_frame(self, k, xy, stage="local"):
        return np.asarray(xy, float) - self.offsets[k]


@pytest.fixture(scope="module")
def frames():
    return _frames(np.random.default_rng(7))


def test_a_right_mapping_measures_at_the_noise_and_a_wrong_one_by_its_error(frames):
    right = pair_consistency(_Shifts(OFFSETS), frames[0], frames[1], 0, 1)
    assert right.n_probes > 50 and len(right.errors) > 0.8 * right.n_probes
    assert np.median(right.errors) < 0.08 and np.percentile(right.errors, 90) < 0.15
    # Frame 1 registered 1.5 px too far right (and 0.4 px down): every point is off by that.
    wrong = OFFSETS.copy()
    wrong[1] += (1.5, 0.4)
    off = pair_consistency(_Shifts(wrong), frames[0], frames[1], 0, 1)
    assert abs(np.median(off.errors) - np.hypot(1.5, 0.4)) < 0.1
    # The floor is what a homography fitted to the measurements leaves: the same either way.
    assert np.nanmedian(off.floor) < 0.08
    # and the patches are found at the same places, whatever the prediction said.
    common, i, j = np.intersect1d(
        right.probes @ [1, 1000], off.probes @ [1, 1000], return_indices=True
    )
    assert len(common) > 0.8 * len(right.errors)
    np.testing.assert_allclose(off.measured[j], right.measured[i], atol=0.05)
    s = summarise([right, off])
    assert s["n_pairs"] == 2 and s["n_points"] == len(right.errors) + len(off.errors)
    assert s["floor_p90_px"] < 0.2 and s["p90_over_floor"] > 5


def test_a_prediction_beyond_the_search_range_is_not_measured(frames):
    wrong = OFFSETS.copy()
    wrong[2] += (30.0, 0.0)
    far = pair_consistency(_Shifts(wrong), frames[0], frames[2], 0, 2)
    assert len(far.errors) == 0 and far.n_probes > 50


def test_edges_and_blank_patches_are_not_probed_and_excluded_boxes_are_left_out():
    stripes = np.zeros((H, W), np.uint8)
    stripes[:, ::8] = 255  # vertical lines: the patch slides along them
    stripes = cv2.GaussianBlur(stripes, (0, 0), 1.0)
    flat = _Shifts(np.zeros((2, 2)))
    assert pair_consistency(flat, stripes, stripes, 0, 1).n_probes == 0
    cfg = ProbeConfig(exclude=((0, 0, 100, 100),))
    p = probe_grid((W, H), cfg)
    assert len(p) and not ((p[:, 0] <= 100) & (p[:, 1] <= 100)).any()
    assert len(probe_grid((W, H), ProbeConfig())) > len(p)


def test_map_agreement_is_high_for_the_same_ground_and_low_for_another(frames):
    a = frames[0]
    valid = np.ones(a.shape, bool)
    brighter = cv2.convertScaleAbs(a, alpha=0.6, beta=60)  # another sensor's grey levels
    same = map_agreement(brighter, valid, a)
    other = map_agreement(frames[0], valid, np.ascontiguousarray(frames[2][::-1]))
    assert same > 0.9 and other < 0.3
    assert map_agreement(a, np.zeros_like(valid), a) is None
