"""Frame-to-frame links against known truth: two frames cut from one texture at known sub-pixel
offsets, models that put them slightly wrong on the map, and a car that moved between them."""

from __future__ import annotations

import cv2
import numpy as np

from registration.adjustment import measure_links
from registration.geometry import PolyProjective, Projective
from registration.lens import HarrisModel

W, H = 320, 240
OFFSET_K, OFFSET_L = np.array([40.0, 30.0]), np.array([52.7, 24.4])  # frames' corners in the scene


def _frames():
    rng = np.random.default_rng(5)
    tex = cv2.GaussianBlur(rng.normal(0, 1, (400, 480)).astype(np.float32), (0, 0), 2.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min()) * 220 + 20
    out = []
    for ox, oy in (OFFSET_K, OFFSET_L):
        m = np.float32([[1, 0, ox], [0, 1, oy]])
        img = cv2.warpAffine(tex, m, (W, H), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
        out.append(img.round().astype(np.uint8))
    return out


def _shift(t) -> PolyProjective:
    return PolyProjective.from_projective(
        Projective.from_matrix(np.array([[1, 0, t[0]], [0, 1, t[1]], [0, 0, 1.0]]))
    )


def test_links_find_the_same_ground_and_leave_out_what_moved():
    grey_k, grey_l = _frames()
    # A car: a bright block in frame l 4 px right of where the ground puts it.
    car = grey_k[100:116, 150:180].copy()
    y0, x0 = 100 + int(OFFSET_K[1] - OFFSET_L[1]), 150 + int(round(OFFSET_K[0] - OFFSET_L[0])) + 4
    grey_l[y0 : y0 + 16, x0 : x0 + 30] = np.clip(car.astype(int) + 60, 0, 255)
    lens = HarrisModel(0.0, W, H)
    # The models put frame l 1.5 px off on the map: the links must follow the images.
    links = measure_links(grey_k, grey_l, 0, 1, _shift(OFFSET_K), _shift(OFFSET_L + 1.5), lens)
    assert len(links.src_k) > 50
    d = links.src_l - links.src_k
    # The sub-pixel peak's bias on a cubic-resampled, rounded texture: 0.05 px measured.
    np.testing.assert_allclose(np.median(d, axis=0), OFFSET_K - OFFSET_L, atol=0.08)
    assert np.abs(d - (OFFSET_K - OFFSET_L)).max() < 0.3
    on_car = (
        (links.src_k[:, 0] > 140) & (links.src_k[:, 0] < 190)
        & (links.src_k[:, 1] > 90) & (links.src_k[:, 1] < 126)
    )  # fmt: skip
    assert not on_car.any()


def test_no_links_where_the_frames_share_no_texture():
    blank = np.full((H, W), 128, np.uint8)
    lens = HarrisModel(0.0, W, H)
    links = measure_links(blank, blank, 0, 1, _shift((0, 0)), _shift((0, 0)), lens)
    assert len(links.src_k) == 0 and links.k == 0 and links.l == 1
