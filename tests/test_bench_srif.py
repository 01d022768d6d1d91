"""Tests for the SRIF benchmark's audit of the published ground truth (benchmarks/srif.py),
against truths made exact by warping a real aerial image with a known similarity."""

from __future__ import annotations

import cv2
import numpy as np

from benchmarks.srif import audit_truth, corner_error
from registration.models import Similarity
from tests.conftest import shared_data


def _pair():
    """Image 1 = a real SRIF image; image 2 = image 1 turned 30° and scaled 0.8 (exact truth),
    with a no-data border like SRIF's."""
    folder = shared_data("srif-optical-optical")
    im1 = cv2.imread(str(folder / "pair3_2.jpg"))
    h, w = im1.shape[:2]
    truth = Similarity.from_rotation(30.0, 0.8, (w / 2, h / 2), (260.0, 250.0)).matrix[:2]
    im2 = cv2.warpAffine(im1, truth, (520, 500), flags=cv2.INTER_LINEAR)
    valid = cv2.warpAffine(np.ones(im1.shape[:2], np.uint8), truth, (520, 500)) > 0
    return im1, im2, valid, truth


def test_audit_confirms_an_exact_truth():
    im1, im2, valid, truth = _pair()
    patches, shift, audited = audit_truth(im1, im2, valid, truth)
    assert patches >= 30 and shift < 1.0, (patches, shift)


def test_audit_finds_a_truth_12_px_off_and_corrects_it():
    im1, im2, valid, truth = _pair()
    wrong = truth + np.array([[0, 0, 9.0], [0, 0, -8.0]])  # 12 px off everywhere
    patches, shift, audited = audit_truth(im1, im2, valid, wrong)
    h, w = im1.shape[:2]
    assert patches >= 30 and abs(shift - 12.04) < 1.0, (patches, shift)
    assert corner_error(lambda p: p @ audited[:, :2].T + audited[:, 2], truth, w, h) < 1.0
