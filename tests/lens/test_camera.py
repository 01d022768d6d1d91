"""The camera object the stages share (registration.lens.camera): the exact Harris model of
conventions.md for the frame size, built once, and the conversions the stages make with it."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from registration.coords import frame_outline
from registration.lens import Camera, HarrisModel, as_camera, undistort_image

W, H = 64, 48


def test_camera_holds_the_harris_model_of_its_gamma_and_size():
    cam = Camera(0.7, W, H)
    assert cam.lens == HarrisModel(0.7, W, H)
    assert cam.size == (W, H)
    xy = np.array([[0.0, 0.0], [10.5, 3.25], [W - 1.0, H - 1.0]])
    assert np.array_equal(cam.corrected_from_raw(xy), HarrisModel(0.7, W, H).corrected_from_raw(xy))
    assert np.array_equal(cam.raw_from_corrected(xy), HarrisModel(0.7, W, H).raw_from_corrected(xy))


def test_corner_goes_where_the_formula_of_the_conventions_puts_it():
    # Raw corner (0, 0) of a 64x48 frame: c = (31.5, 23.5), r_n = 40, rho' = |c| / 40;
    # corrected = c + (x' - c) / sqrt(1 - gamma rho'^2).
    cam = Camera(0.5, W, H)
    c = np.array([31.5, 23.5])
    rho2 = (c @ c) / 40.0**2
    expected = c + (np.zeros(2) - c) / np.sqrt(1 - 0.5 * rho2)
    assert np.allclose(cam.corrected_from_raw([[0.0, 0.0]])[0], expected, atol=1e-12)


def test_grids_and_outline_at_gamma_zero_are_the_raw_positions():
    cam = Camera(0.0, W, H)
    grid = cam.grid(3, 2)
    assert np.array_equal(grid, [[0, 0], [31.5, 0], [63, 0], [0, 47], [31.5, 47], [63, 47]])
    cells = cam.cell_centres(2)  # 2x2 cells of 32x24 px
    assert np.array_equal(cells, [[15.5, 11.5], [47.5, 11.5], [15.5, 35.5], [47.5, 35.5]])
    assert np.array_equal(cam.outline(8), frame_outline(W, H, 8))


def test_conversions_move_points_outwards_for_barrel_correction():
    cam = Camera(0.7, W, H)
    raw = np.array([[0.0, 0.0], [W - 1.0, H - 1.0]])
    corr = cam.corrected_from_raw(raw)
    c = np.array([(W - 1) / 2, (H - 1) / 2])
    assert (np.hypot(*(corr - c).T) > np.hypot(*(raw - c).T)).all()
    assert np.allclose(cam.raw_from_corrected(corr), raw, atol=1e-9)
    assert np.array_equal(cam.grid(2, 2)[[0, 3]], corr)


def test_undistort_is_the_same_canvas_correction():
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    cam = Camera(0.7, W, H)
    expected, _ = undistort_image(frame, HarrisModel(0.7, W, H), canvas="same")
    assert np.array_equal(cam.undistort(frame), expected)
    with pytest.raises(ValueError, match="32x48 frame"):
        cam.undistort(frame[:, :32])


def test_as_camera_takes_a_gamma_or_a_camera_of_the_frame_size():
    frame = np.zeros((H, W), np.uint8)
    assert as_camera(0.7, frame) == Camera(0.7, W, H)
    cam = Camera(0.7, W, H)
    assert as_camera(cam, frame) is cam
    with pytest.raises(ValueError, match="64x48 frame given to the camera of 65x48"):
        as_camera(Camera(0.7, W + 1, H), frame)


def test_camera_pickles_with_its_model():
    cam = pickle.loads(pickle.dumps(Camera(0.7, W, H)))  # sent to Dask workers
    assert cam == Camera(0.7, W, H) and cam.lens == HarrisModel(0.7, W, H)
    assert isinstance(cam.gamma, float)


def test_stretch_is_the_harris_area_scale():
    # Harris maps a corrected radius rho (in half diagonals) to the raw radius
    # rho / sqrt(1 + gamma rho^2); the corrected image is enlarged in area by (1 + gamma rho^2)^2,
    # so sqrt |det J| = 1 + gamma rho^2.
    cam = Camera(0.7, 640, 480)
    xy = cam.grid(9, 7)
    rho2 = (((xy - [319.5, 239.5]) / 400.0) ** 2).sum(axis=1)
    np.testing.assert_allclose(cam.stretch(xy), 1 + 0.7 * rho2, rtol=2e-3)
    np.testing.assert_allclose(Camera(0.0, 640, 480).stretch(xy), 1.0, rtol=1e-9)
