"""A probe's texture test (``structure_strength``): the patch-by-patch computation used where
probes cover little of a frame agrees with the whole image's filters on a real photo, and both
give the known structure tensor of a ramp (one direction only: nothing pins the other)."""

from __future__ import annotations

import cv2
import numpy as np

from registration.matching import ProbeConfig
from registration.matching.probes import (
    PATCHWISE_BELOW,
    _image_strength,
    _patch_strength,
    probe_grid,
    structure_strength,
)
from tests.conftest import shared_data


def _photo() -> np.ndarray:
    path = shared_data("sdd-reference-frames") / "bookstore/video0/reference.jpg"
    return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)


def test_patches_and_whole_image_agree_on_a_real_photo():
    grey = _photo()
    for grid_px in (24, 83):
        p = probe_grid(grey.shape[::-1], ProbeConfig(grid_px=grid_px))
        a, b = _patch_strength(grey, p, 15), _image_strength(grey, p, 15)
        assert np.all(np.abs(a - b) <= 1e-5 * np.maximum(b, 1.0)), np.max(np.abs(a - b))
        assert np.array_equal(a >= 40.0, b >= 40.0)
        assert 0 < np.mean(b >= 40.0) < 1  # the threshold separates real patches


def test_sparse_probes_are_measured_patch_by_patch():
    grey = _photo()
    h, w = grey.shape
    sparse = probe_grid((w, h), ProbeConfig(grid_px=83))
    dense = probe_grid((w, h), ProbeConfig(grid_px=24))
    assert len(sparse) * 33**2 < PATCHWISE_BELOW * h * w <= len(dense) * 33**2
    np.testing.assert_array_equal(
        structure_strength(grey, sparse, 15), _patch_strength(grey, sparse, 15)
    )
    np.testing.assert_array_equal(
        structure_strength(grey, dense, 15), _image_strength(grey, dense, 15)
    )


def test_a_ramp_pins_one_direction_only():
    """I(x, y) = 2x: Scharr/16 gives gx = 2 x 32 / 16 = 4 (its 3-10-3 weights sum to 16 over
    a two-pixel step), gy = 0; the tensor [[16, 0], [0, 0]] has smaller eigenvalue 0. With a
    second ramp across it (I = 2x + y) it is [[16, 8], [8, 4]], rank 1: 0 again."""
    ys, xs = np.mgrid[0:100, 0:100]
    p = np.array([[50.0, 50.0], [30.0, 60.0]])
    for image in (2 * xs, 2 * xs + ys):
        grey = image.astype(np.uint8)
        for strength in (_patch_strength, _image_strength):
            np.testing.assert_allclose(strength(grey, p, 15), 0.0, atol=1e-3)


def test_a_bowl_pins_both_directions_by_its_known_amount():
    """I(x, y) = dx² + dy² about the patch's centre: Scharr/16 gives gx = 4 dx and gy = 4 dy
    exactly (a central difference of a square), so over the 31 px patch the tensor is
    16 mean(d²) I = 16 x 80 I: both eigenvalues 1280. A strength that lost either direction, or
    the patch's extent, would not give it."""
    ys, xs = np.mgrid[0:100, 0:100].astype(np.float64)
    p = np.array([[50.0, 50.0]])
    bowl = (xs - 50) ** 2 + (ys - 50) ** 2
    for strength in (_patch_strength, _image_strength):
        np.testing.assert_allclose(strength(bowl, p, 15), 1280.0, rtol=1e-6)
