"""A probe's texture test (``structure_strength``): the patch-by-patch computation used where
probes cover little of a frame agrees with the whole image's filters on a real photo, and both
give the known structure tensor of a ramp (one direction only: nothing pins the other)."""

from __future__ import annotations

import cv2
import numpy as np

from registration.matching import ProbeConfig
from registration.matching.probes import (
    BAND_ROWS,
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


def _whole_image_strength(grey, points, half):
    """The filters over the whole image at once: what ``_image_strength`` computes band by
    band."""
    g = grey.astype(np.float32)
    gx = cv2.Scharr(g, cv2.CV_32F, 1, 0) / 16.0
    gy = cv2.Scharr(g, cv2.CV_32F, 0, 1) / 16.0
    k = 2 * half + 1
    sxx, syy, sxy = (cv2.boxFilter(a, -1, (k, k)) for a in (gx * gx, gy * gy, gx * gy))
    xi, yi = points[:, 0].astype(int), points[:, 1].astype(int)
    a, c, b = sxx[yi, xi], syy[yi, xi], sxy[yi, xi]
    return (0.5 * (a + c - np.sqrt((a - c) ** 2 + 4 * b * b))).astype(np.float64)


def test_bands_give_the_whole_images_values_to_the_bit():
    """Every probe of a real photo (dense grid, and probes on every row next to a band's edge
    and the image's first and last rows) gets exactly the whole image's value."""
    grey = _photo()
    h, w = grey.shape
    dense = probe_grid((w, h), ProbeConfig(grid_px=24))
    edges = [y for b in range(0, h, BAND_ROWS) for y in (b - 1, b, b + 1) if 0 <= y < h]
    rows = np.array(sorted({0, 1, h - 2, h - 1, *edges}), float)
    xs = np.linspace(0, w - 1, 7)
    at_edges = np.stack(np.meshgrid(xs, rows), axis=-1).reshape(-1, 2)
    for p in (dense, at_edges):
        np.testing.assert_array_equal(
            _image_strength(grey, p, 15), _whole_image_strength(grey, p, 15)
        )
