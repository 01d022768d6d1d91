"""What the registered outputs show, not only that they exist: the overlay (paper Fig. 6) is the
registered frame blended with the mid base image, and the field images (paper Fig. 5) colour each
pixel by the field's component there. A hand-made result with integer translations makes every
expected pixel known without any warp."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import registration
from registration.geometry import DisplacementField
from registration.io import read_image
from registration.render import write_registered_sequence

W, H = 120, 90
BASE_W, BASE_H = 400, 300
SHIFTS = [(100, 50), (130, 70)]  # frame k pixel q shows base point q + SHIFTS[k]
FIELD_ORIGIN, FIELD_SPACING = (100.0, 40.0), 60.0


def smooth(h, w, seed, channels=3):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w, channels)).astype(np.float32), (0, 0), 3)
    img = (img - img.min()) / (img.max() - img.min()) * 200 + 30
    return img.astype(np.uint8)


class Frames:
    def __init__(self, images):
        self.images = images

    def __len__(self):
        return len(self.images)

    def get(self, k):
        return self.images[k]


def _field() -> DisplacementField:
    """dx runs from -2 to +2 px across the node columns, dy is -1 everywhere."""
    gy, gx = 3, 5
    vectors = np.zeros((gy, gx, 2), np.float32)
    vectors[..., 0] = np.linspace(-2.0, 2.0, gx)[None, :]
    vectors[..., 1] = -1.0
    return DisplacementField(FIELD_ORIGIN, FIELD_SPACING, vectors, np.ones((gy, gx), bool))


@pytest.fixture
def made(tmp_path):
    out = tmp_path / "out"
    (out / "frames").mkdir(parents=True)
    meta = {
        "format": "aerialreg-result",
        "version": 1,
        "n_frames": 2,
        "gamma": 0.0,
        "frame_size": [W, H],
        "base_size": [BASE_W, BASE_H],
        "reference_frame": 0,
    }
    (out / "result.json").write_text(json.dumps(meta))
    for k, (tx, ty) in enumerate(SHIFTS):
        rec = {"status": "ok", "reason": "", "stats": {}}
        rec["model"] = {"type": "Translation", "params": [float(tx), float(ty)]}
        (out / "frames" / f"{k:06d}.json").write_text(json.dumps(rec))
    arrays = {f"field_{n}": v for n, v in _field().to_arrays().items()}
    np.savez(out / "frames" / "000001.npz", **arrays)
    mid = np.zeros((BASE_H, BASE_W, 3), np.uint8)
    mid[40:170, 90:260] = smooth(130, 170, seed=9)  # the reference covers part of the box
    cv2.imwrite(str(out / "mid_base.png"), mid)
    frames = [smooth(H, W, seed=k) for k in range(2)]
    return registration.load(out), frames, mid


def test_overlay_is_the_frame_blended_with_the_mid_base_image(made, tmp_path):
    res, frames, mid = made
    info = write_registered_sequence(res, Frames(frames), tmp_path / "r", stage="global")
    x0, y0, w, h = info["box"]
    assert (x0, y0) == (98, 48)  # union of both footprints, padded by 2
    mid_crop = mid[y0 : y0 + h, x0 : x0 + w].astype(float)
    for k, (tx, ty) in enumerate(SHIFTS):
        expected_frame = np.zeros((h, w, 3))
        expected_frame[ty - y0 : ty - y0 + H, tx - x0 : tx - x0 + W] = frames[k]
        has_frame = np.zeros((h, w), bool)
        has_frame[ty - y0 : ty - y0 + H, tx - x0 : tx - x0 + W] = True
        got_frame = read_image(tmp_path / "r" / "frames" / f"{k:06d}.png").astype(float)
        np.testing.assert_array_equal(got_frame, expected_frame)
        over = read_image(tmp_path / "r" / "overlay" / f"{k:06d}.jpg").astype(float)
        expected = np.where(has_frame[..., None], 0.5 * expected_frame + 0.5 * mid_crop, mid_crop)
        err = np.abs(over - expected)
        # JPEG at quality 92 on smooth images: ~1 DN; showing only the mid base image would be
        # ~45 DN off where the frame is, only the frame ~40 DN off where it is not.
        assert err[has_frame].mean() < 3.0, (k, err[has_frame].mean())
        assert err[~has_frame].mean() < 3.0, (k, err[~has_frame].mean())


def _decode(bgr: np.ndarray, limit: float) -> np.ndarray:
    """Value of a blue-white-red colour (BGR): white 0, pure red +limit, pure blue -limit."""
    b, g, r = (bgr[..., c].astype(float) for c in range(3))
    pos = (r >= 254) & (b < 254)
    neg = (b >= 254) & (r < 254)
    v = np.zeros(bgr.shape[:2])
    v[pos] = (1 - b[pos] / 255) * limit
    v[neg] = -(1 - r[neg] / 255) * limit
    return v


def test_field_images_colour_each_pixel_by_the_fields_component(made, tmp_path):
    res, frames, _ = made
    write_registered_sequence(res, Frames(frames), tmp_path / "r")
    assert not (tmp_path / "r" / "field" / "000000_dx.png").exists()  # frame 0 has no field
    tx, ty = SHIFTS[1]
    dx_img = read_image(tmp_path / "r" / "field" / "000001_dx.png")
    dy_img = read_image(tmp_path / "r" / "field" / "000001_dy.png")
    assert dx_img.shape[0] == H and dx_img.shape[1] >= W  # the frame's footprint (+ legend)
    # Pixels of the footprint away from the node dots: base point (tx + j, ty + i).
    ys, xs = np.mgrid[3:H:7, 2:W:7]
    base_x, base_y = xs + tx, ys + ty
    nodes_x = FIELD_ORIGIN[0] + FIELD_SPACING * np.arange(5)
    nodes_y = FIELD_ORIGIN[1] + FIELD_SPACING * np.arange(3)
    near_x = np.abs(base_x[..., None] - nodes_x).min(axis=-1) < 5
    near_y = np.abs(base_y[..., None] - nodes_y).min(axis=-1) < 5
    far = ~(near_x & near_y)
    # dx: bilinear between node columns, linear here: -2 + 4 (x - x0) / (4 spacing), clamped
    # beyond the outer nodes; the colour scale is the largest measured value, 2 px.
    expected_dx = np.clip(-2 + 4 * (base_x - nodes_x[0]) / (nodes_x[-1] - nodes_x[0]), -2, 2)
    got_dx = _decode(dx_img[ys, xs], 2.0)
    assert np.abs(got_dx - expected_dx)[far].max() < 0.05
    got_dy = _decode(dy_img[ys, xs], 1.0)
    assert np.abs(got_dy + 1.0)[far].max() < 0.05  # pure blue: -1 px at a 1 px scale
