"""Frame-to-frame links against known truth: two frames cut from one texture at known sub-pixel
offsets, models that put them slightly wrong on the map, and a car that moved between them."""

from __future__ import annotations

import cv2
import numpy as np

from registration.adjustment import measure_links
from registration.adjustment.links import link_inlier_px
from registration.adjustment.sequence import probes_for
from registration.geometry import PolyProjective, Projective
from registration.lens import HarrisModel
from registration.matching import ProbeConfig, textured_probes

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


def _count_correlation_searches(monkeypatch) -> list:
    import registration.adjustment.links as links_module

    calls, original = [], links_module.find_probes

    def find_probes(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(links_module, "find_probes", find_probes)
    return calls


def test_lucas_kanade_links_stand_where_part_of_the_ground_leaves_the_homography(monkeypatch):
    """A third of frame l's ground changed (not found) and a third of what is found lies 3 px
    off the rest (ground off the plane): what Lucas-Kanade found is kept, no correlation."""
    calls = _count_correlation_searches(monkeypatch)
    grey_k, grey_l = _frames()
    rng = np.random.default_rng(9)
    grey_l[:80] = cv2.GaussianBlur(rng.normal(128, 60, (80, W)), (0, 0), 2.0).clip(0, 255)
    grey_l[80:, 210:] = np.roll(grey_l[80:, 210:], 3, axis=1)
    lens = HarrisModel(0.0, W, H)
    links = measure_links(grey_k, grey_l, 0, 1, _shift(OFFSET_K), _shift(OFFSET_L + 1.0), lens)
    assert calls == []
    assert len(links.src_k) > 30  # of 108 probes: 55 found, 42 on the plane
    d = links.src_l - links.src_k
    assert np.abs(d - (OFFSET_K - OFFSET_L)).max() < 0.3
    seen_l = links.src_l
    assert (seen_l[:, 1] >= 80 - 15).all() and (seen_l[:, 0] < 210 + 15).all()


def test_correlation_measures_a_pair_lucas_kanade_loses(monkeypatch):
    """Where Lucas-Kanade finds under half the probes (here: none, its result withheld) the
    pair is measured by correlation, and its links are the ground's."""
    import registration.adjustment.links as links_module

    calls = _count_correlation_searches(monkeypatch)
    monkeypatch.setattr(
        links_module, "_flow_probes",
        lambda grey_k, grey_l, p, q, cfg: (np.full_like(p, np.nan), np.zeros(len(p), bool)),
    )  # fmt: skip
    grey_k, grey_l = _frames()
    lens = HarrisModel(0.0, W, H)
    links = measure_links(grey_k, grey_l, 0, 1, _shift(OFFSET_K), _shift(OFFSET_L + 1.0), lens)
    assert calls == [1]
    assert len(links.src_k) > 50
    np.testing.assert_allclose(
        np.median(links.src_l - links.src_k, axis=0), OFFSET_K - OFFSET_L, atol=0.08
    )


def test_links_keep_the_ground_a_homography_of_a_large_pair_cannot_follow():
    """A 2560x1920 frame l sees the scene through a bow of 4 px across the frame (rolling
    shutter and terrain do this, and more so the more pixels a frame has) that its model knows:
    the pair's links are then not one homography of each other, yet 85 % of the textured probes
    are linked, each true to 0.3 px (at the 1 px that suits 1280x960 frames: 60 %)."""
    w, h = 2560, 1920
    rng = np.random.default_rng(5)
    tex = cv2.GaussianBlur(rng.normal(0, 1, (h + 80, w + 80)).astype(np.float32), (0, 0), 2.0)
    tex = ((tex - tex.min()) / (tex.max() - tex.min()) * 220 + 20).astype(np.float32)
    bow = 4.0 / (h / 2) ** 2

    def scene_from_l(pts):
        pts = np.asarray(pts, np.float64)
        x = pts[:, 0] + OFFSET_L[0] + bow * (pts[:, 1] - h / 2) ** 2
        return np.c_[x, pts[:, 1] + OFFSET_L[1]]

    grey_k = cv2.warpAffine(
        tex, np.float32([[1, 0, OFFSET_K[0]], [0, 1, OFFSET_K[1]]]), (w, h),
        flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
    ).round().astype(np.uint8)  # fmt: skip
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    maps = scene_from_l(np.c_[xs.ravel(), ys.ravel()]).reshape(h, w, 2).astype(np.float32)
    grey_l = cv2.remap(tex, maps[..., 0], maps[..., 1], cv2.INTER_CUBIC).round().astype(np.uint8)
    grid = np.stack(np.meshgrid(np.linspace(0, w, 9), np.linspace(0, h, 7)), -1).reshape(-1, 2)
    model_l = PolyProjective.estimate(grid, scene_from_l(grid) + 1.0)  # 1 px off on the map
    lens = HarrisModel(0.0, w, h)
    probes = probes_for(grey_k, ProbeConfig())
    links = measure_links(grey_k, grey_l, 0, 1, _shift(OFFSET_K), model_l, lens, probes)
    truth = scene_from_l(links.src_l) - OFFSET_K
    assert np.abs(truth - links.src_k).max() < 0.3
    assert len(links.src_k) >= 0.85 * len(textured_probes(grey_k, probes))


def test_frames_up_to_1280x960_keep_links_within_1_px():
    assert link_inlier_px((1280, 960)) == link_inlier_px((852, 480)) == 1.0
    assert link_inlier_px((2560, 1920)) == 2.0
