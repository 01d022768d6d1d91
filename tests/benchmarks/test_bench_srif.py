"""Tests for the SRIF benchmark's check of which plane the images' texture follows
(benchmarks/srif.py), against truths made exact by warping a real aerial image with a known
similarity, and a second plane made by shifting part of the warped image."""

from __future__ import annotations

import cv2
import numpy as np

from benchmarks.srif import corner_error, dominant_plane, follows_another_plane
from registration.geometry import Similarity
from tests.conftest import shared_data

SHIFT = np.array([[0, 0, 9.0], [0, 0, -8.0]])  # 12.04 px everywhere


def _pair(shifted_from_x: float | None = None):
    """Image 1 = a real SRIF image; image 2 = image 1 turned 30° and scaled 0.8 (exact truth),
    with a no-data border like SRIF's; from ``shifted_from_x`` (share of the width) rightwards,
    image 2 shows image 1 moved by :data:`SHIFT` instead (a second plane, as roofs)."""
    folder = shared_data("srif-optical-optical")
    im1 = cv2.imread(str(folder / "pair3_2.jpg"))
    h, w = im1.shape[:2]
    truth = Similarity.from_rotation(30.0, 0.8, (w / 2, h / 2), (260.0, 250.0)).matrix[:2]
    im2 = cv2.warpAffine(im1, truth, (520, 500), flags=cv2.INTER_LINEAR)
    if shifted_from_x is not None:
        other = cv2.warpAffine(im1, truth + SHIFT, (520, 500), flags=cv2.INTER_LINEAR)
        x0 = int(shifted_from_x * 520)
        im2[:, x0:] = other[:, x0:]
    valid = cv2.warpAffine(np.ones(im1.shape[:2], np.uint8), truth, (520, 500)) > 0
    return im1, im2, valid, truth


def test_an_exact_truth_is_the_plane_the_texture_follows():
    im1, im2, valid, truth = _pair()
    n_plane, n_truth, shift, _ = dominant_plane(im1, im2, valid, truth)
    assert n_plane >= 100 and n_truth == n_plane and shift < 1.0, (n_plane, n_truth, shift)
    assert not follows_another_plane(n_plane, n_truth, shift)


def test_a_truth_12_px_off_is_found_and_corrected():
    im1, im2, valid, truth = _pair()
    n_plane, n_truth, shift, corrected = dominant_plane(im1, im2, valid, truth + SHIFT)
    h, w = im1.shape[:2]
    assert n_plane >= 100 and n_truth == 0 and abs(shift - 12.04) < 1.0, (n_plane, shift)
    assert corner_error(lambda p: p @ corrected[:, :2].T + corrected[:, 2], truth, w, h) < 1.0
    assert follows_another_plane(n_plane, n_truth, shift)


def test_a_second_plane_counts_only_when_it_clearly_outnumbers_the_truths():
    im1, im2, valid, truth = _pair(shifted_from_x=0.2)  # most of image 2 on the other plane
    n_plane, n_truth, shift, _ = dominant_plane(im1, im2, valid, truth)
    assert n_plane > 2 * n_truth > 0 and abs(shift - 12.04) < 1.0, (n_plane, n_truth, shift)
    assert follows_another_plane(n_plane, n_truth, shift)
    im1, im2, valid, truth = _pair(shifted_from_x=0.45)  # about half on each
    n_plane, n_truth, shift, _ = dominant_plane(im1, im2, valid, truth)
    assert n_truth > 0 and n_plane < 2 * n_truth, (n_plane, n_truth, shift)
    assert not follows_another_plane(n_plane, n_truth, shift)
