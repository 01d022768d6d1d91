"""Tests of registration.features: known warps, exact ground truth, false matches at named indices.

Images: a seeded generated texture (always available) and real imagery from ``../shared/data``
(skipped with a reason when absent), warped with known transforms through
``registration.warp.remap``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from registration import coords, warp
from registration.features import (
    ControlPoints,
    GriddedSiftConfig,
    Keypoints,
    Reference,
    SiftConfig,
    TemplateConfig,
    detect_sift,
    downscale,
    gridded_sift_control_points,
    match_ratio,
    subpixel_peak,
    template_control_points,
    template_grid,
    to_grey,
    window_centres,
)
from tests.conftest import shared_data

# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def texture(width: int, height: int, seed: int = 0) -> np.ndarray:
    """Seeded aerial-like uint8 texture: smoothed noise at two scales plus rectangles and lines."""
    rng = np.random.default_rng(seed)
    fine = cv2.GaussianBlur(rng.normal(size=(height, width)).astype(np.float32), (0, 0), 1.5)
    coarse = cv2.GaussianBlur(rng.normal(size=(height, width)).astype(np.float32), (0, 0), 6.0)
    img = 110 + 60 * fine / fine.std() * 0.5 + 40 * coarse / coarse.std() * 0.5
    for _ in range(width * height // 4000):
        x, y = rng.integers(0, width), rng.integers(0, height)
        w, h = rng.integers(6, 30), rng.integers(6, 30)
        cv2.rectangle(
            img, (int(x), int(y)), (int(x + w), int(y + h)), float(rng.uniform(30, 230)), -1
        )
    for _ in range(width * height // 20000):
        p = rng.integers(0, [width, height])
        q = rng.integers(0, [width, height])
        cv2.line(
            img, tuple(int(v) for v in p), tuple(int(v) for v in q), float(rng.uniform(0, 255)), 2
        )
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    return np.clip(img, 0, 255).astype(np.uint8)


def homography_fn(h: np.ndarray):
    def fn(xy: np.ndarray) -> np.ndarray:
        xy = coords.as_points(xy)
        p = np.c_[xy, np.ones(len(xy))] @ h.T
        return p[:, :2] / p[:, 2:]

    return fn


def similarity(scale: float, angle_deg: float, centre_src, centre_dst) -> np.ndarray:
    """3x3 matrix of the similarity sending ``centre_src`` to ``centre_dst``."""
    a = math.radians(angle_deg)
    r = scale * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    t = np.asarray(centre_dst, float) - r @ np.asarray(centre_src, float)
    return np.block([[r, t[:, None]], [np.zeros((1, 2)), np.ones((1, 1))]])


def warp_into(image: np.ndarray, src_from_out, width: int, height: int) -> np.ndarray:
    """Render ``image`` in the output geometry defined by ``src_from_out`` (output px -> image px)."""
    return warp.remap(image, warp.source_map_from_function(src_from_out, width, height))


def real_grey(*parts: str, scale: float) -> np.ndarray:
    path = shared_data(*parts)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f"unreadable image {path}"
    return downscale(to_grey(img), scale)


# ---------------------------------------------------------------------------------------------
# grey conversion and subsampling
# ---------------------------------------------------------------------------------------------


def test_to_grey_accepts_channels_and_dtypes():
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    expected = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(to_grey(bgr), expected)
    np.testing.assert_array_equal(
        to_grey(np.dstack([bgr, np.full((20, 30), 7, np.uint8)])), expected
    )
    np.testing.assert_array_equal(to_grey(expected[:, :, None]), expected)
    assert to_grey(expected) is expected  # no copy for uint8 grey
    np.testing.assert_array_equal(to_grey(expected.astype(np.uint16) * 257), expected)
    np.testing.assert_array_equal(to_grey(expected / 255.0), expected)
    np.testing.assert_array_equal(to_grey(expected.astype(np.float32)), expected)
    out = to_grey(bgr.astype(np.float64) / 255.0)
    assert out.dtype == np.uint8 and out.shape == (20, 30)
    assert np.abs(out.astype(int) - expected).max() <= 1


@pytest.mark.parametrize(
    ("image", "message"),
    [
        (np.zeros((4, 4, 2), np.uint8), r"\(4, 4, 2\)"),
        (np.zeros((0, 5), np.uint8), "empty"),
        (np.zeros((4, 4), np.int32), "int32"),
        (np.zeros(5, np.uint8), r"\(5,\)"),
    ],
)
def test_to_grey_rejects_bad_input(image, message):
    with pytest.raises(ValueError, match=message):
        to_grey(image)


def test_downscale_matches_coords_rescale():
    # A small bright blob at a known sub-pixel position must land where coords.rescale says.
    h, w = 400, 480
    ys, xs = np.mgrid[0:h, 0:w]
    centre = np.array([201.3, 157.8])
    blob = 255 * np.exp(-((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / (2 * 6.0**2))
    small = downscale(blob.astype(np.float32), 0.25)
    assert small.shape == (100, 120)
    sy, sx = np.mgrid[0 : small.shape[0], 0 : small.shape[1]]
    got = np.array([(sx * small).sum(), (sy * small).sum()]) / small.sum()
    np.testing.assert_allclose(got, coords.rescale(centre, 0.25)[0], atol=0.02)
    with pytest.raises(ValueError, match="scale"):
        downscale(blob, 0.0)


# ---------------------------------------------------------------------------------------------
# SIFT and ratio matching
# ---------------------------------------------------------------------------------------------


def test_detect_sift_shapes_mask_and_flat_image():
    img = texture(240, 200)
    kp = detect_sift(img)
    assert len(kp) > 50
    assert kp.xy.dtype == np.float64 and kp.xy.shape == (len(kp), 2)
    assert kp.descriptors.dtype == np.float32 and kp.descriptors.shape == (len(kp), 128)
    assert kp.size.shape == kp.angle.shape == kp.response.shape == (len(kp),)
    assert Keypoints(kp.xy, kp.descriptors, kp.size).angle.tolist() == [0.0] * len(kp)
    assert len(kp.subset(kp.xy[:, 0] < 100)) == int((kp.xy[:, 0] < 100).sum())
    half = kp.rescaled(0.5)
    np.testing.assert_allclose(half.xy, coords.rescale(kp.xy, 0.5))
    np.testing.assert_allclose(half.size, kp.size / 2)
    mask = np.zeros(img.shape, np.uint8)
    mask[:, :120] = 1
    left = detect_sift(img, mask=mask)
    assert 0 < len(left) < len(kp)
    assert (left.xy[:, 0] < 120.5).all()
    assert len(detect_sift(np.full((200, 240), 90, np.uint8))) == 0
    assert len(detect_sift(img, mask=np.zeros_like(img))) == 0
    assert len(detect_sift(img, SiftConfig(nfeatures=20))) <= 25  # OpenCV keeps ties
    with pytest.raises(ValueError, match="mask shape"):
        detect_sift(img, mask=np.ones((3, 3), np.uint8))


def _sift_agrees_with_homography(img: np.ndarray, h: np.ndarray, method: str) -> None:
    height, width = img.shape
    warped = warp_into(img, homography_fn(np.linalg.inv(h)), width, height)
    a, b = detect_sift(img), detect_sift(warped)
    m = match_ratio(a, b, 0.8, method=method)
    assert len(m) > 100
    err = np.linalg.norm(homography_fn(h)(a.xy[m.idx_a]) - b.xy[m.idx_b], axis=1)
    inliers = err < 3.0
    assert inliers.mean() > 0.8
    assert np.median(err[inliers]) < 1.0
    assert np.median(err[inliers]) < 0.3  # in practice ~0.1 px


@pytest.mark.parametrize("method", ["bf", "flann"])
def test_sift_matches_agree_with_known_homography_texture(method):
    img = texture(480, 360, seed=1)
    h = similarity(1.1, 12.0, (240, 180), (235, 185))
    h[2, :2] = (2e-5, -3e-5)
    _sift_agrees_with_homography(img, h, method)


def test_sift_matches_agree_with_known_homography_real():
    img = real_grey("songdo-vision-drone", "images", "00164.jpg", scale=1 / 6)  # 640x360
    h = similarity(1.05, -8.0, (320, 180), (330, 170))
    h[2, :2] = (1e-5, 2e-5)
    _sift_agrees_with_homography(img, h, "auto")


def test_match_ratio_ratio_test_and_empty_inputs():
    rng = np.random.default_rng(3)
    base = rng.uniform(0, 1, (4, 128)).astype(np.float32)
    # a0 is close to b0 only; a1 is equally close to b1 and b2 (ambiguous -> rejected).
    b = np.stack([base[0], base[1] + 0.05, base[1] - 0.05, base[3]])
    a = np.stack([base[0] + 0.01, base[1]])
    m = match_ratio(a, b, 0.8, method="bf")
    assert m.idx_a.tolist() == [0] and m.idx_b.tolist() == [0]
    assert m.ratio[0] < 0.8
    empty = Keypoints.empty()
    assert len(match_ratio(empty, b)) == 0
    assert len(match_ratio(a, empty)) == 0
    assert len(match_ratio(a, b[:1])) == 0  # one candidate cannot pass a ratio test
    with pytest.raises(ValueError, match="ratio"):
        match_ratio(a, b, 0.0)
    with pytest.raises(ValueError, match="method"):
        match_ratio(a, b, method="exhaustive")


# ---------------------------------------------------------------------------------------------
# control points container
# ---------------------------------------------------------------------------------------------


def test_control_points_container():
    cp = ControlPoints(np.ones((3, 2)), np.zeros((3, 2)), [0.9, 0.8, 0.7])
    assert cp.source.tolist() == [0, 0, 0] and cp.score.dtype == np.float64
    both = ControlPoints.concatenate([cp, ControlPoints.empty(), cp.subset([2])])
    assert len(both) == 4 and both.score.tolist() == [0.9, 0.8, 0.7, 0.7]
    assert len(ControlPoints.concatenate([])) == 0
    with pytest.raises(ValueError, match="equal length"):
        ControlPoints(np.ones((3, 2)), np.zeros((2, 2)), np.zeros(3))


# ---------------------------------------------------------------------------------------------
# template grid, sub-pixel peak, dither, jitter, texture check
# ---------------------------------------------------------------------------------------------


def fourier_shift(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Exact band-limited shift: output(x, y) = image(x - dx, y - dy)."""
    h, w = image.shape
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    spec = np.fft.fft2(image.astype(np.float64)) * np.exp(-2j * np.pi * (fx * dx + fy * dy))
    return np.real(np.fft.ifft2(spec)).astype(np.float32)


def test_subpixel_peak_recovers_fractional_shift():
    rng = np.random.default_rng(7)
    img = cv2.GaussianBlur(rng.normal(size=(160, 160)).astype(np.float32), (0, 0), 2.0)
    for dx, dy in [(0.3, -0.45), (-0.2, 0.15), (0.49, 0.0)]:
        shifted = fourier_shift(img, dx, dy)
        tpl = img[43:118, 43:118]  # 75 x 75 around (80, 80)
        window = shifted[33:128, 33:128]  # +-10 px search
        res = cv2.matchTemplate(window, tpl, cv2.TM_CCOEFF_NORMED)
        _, _, _, (px, py) = cv2.minMaxLoc(res)
        for method in ("quadratic", "parabolic"):
            off = (
                np.array([px, py])
                - 10
                + subpixel_peak(res[py - 1 : py + 2, px - 1 : px + 2], method)[0]
            )
            np.testing.assert_allclose(off, [dx, dy], atol=0.1, err_msg=method)
    # An exact quadratic surface is recovered exactly.
    u = np.arange(-1, 2)
    x, y = np.meshgrid(u, u)
    surface = -((x - 0.3) ** 2) - 2 * (y + 0.2) ** 2 + 0.5 * (x - 0.3) * (y + 0.2)
    np.testing.assert_allclose(subpixel_peak(surface, "quadratic")[0], [0.3, -0.2], atol=1e-9)
    assert subpixel_peak(surface, "none")[0].tolist() == [0.0, 0.0]


def bent_warp(ref_size, frame_size, scale=1.2, angle=10.0):
    """ref_from_frame: similarity (``scale``, ``angle``) plus a small non-projective bend
    (quadratic, 3 px at the frame's top and bottom edges, 2 px at its corners)."""
    fw, fh = frame_size
    rw, rh = ref_size
    sim = homography_fn(similarity(scale, angle, (fw / 2, fh / 2), (rw / 2, rh / 2)))

    def ref_from_frame(xy: np.ndarray) -> np.ndarray:
        out = sim(xy)
        u = (xy[:, 0] - fw / 2) / (fw / 2)
        v = (xy[:, 1] - fh / 2) / (fh / 2)
        out[:, 0] += 3.0 * v**2
        out[:, 1] += 2.0 * u * v
        return out

    return ref_from_frame


def coarse_model(ref_size, frame_size, scale=1.2, angle=10.0):
    """A similarity a few px off the truth (translation (3, -2), scale +0.4 %), and its inverse."""
    fw, fh = frame_size
    rw, rh = ref_size
    h = similarity(scale * 1.004, angle + 0.2, (fw / 2, fh / 2), (rw / 2 + 3.0, rh / 2 - 2.0))
    return homography_fn(h), homography_fn(np.linalg.inv(h))


def _template_recovery(ref: np.ndarray, frame_size) -> ControlPoints:
    ref_size = (ref.shape[1], ref.shape[0])
    truth = bent_warp(ref_size, frame_size)
    frame = warp_into(ref, truth, *frame_size)
    coarse, coarse_inv = coarse_model(ref_size, frame_size)
    # The coarse model is several px off the truth.
    grid = template_grid(*frame_size).astype(float)
    assert np.median(np.linalg.norm(coarse(grid) - truth(grid), axis=1)) > 2.5
    cp = template_control_points(frame, ref, coarse, coarse_inv, TemplateConfig())
    err = np.linalg.norm(cp.dst - truth(cp.src), axis=1)
    assert len(cp) > 0.8 * len(grid)
    assert np.median(err) < 0.2, f"median error {np.median(err):.3f} px"
    assert (cp.score >= 0.5).all()
    return cp


def test_template_control_points_recover_known_warp_texture():
    _template_recovery(texture(700, 560, seed=2), (460, 340))


def test_template_control_points_recover_known_warp_real():
    ref = real_grey("songdo-vision-drone", "images", "00972.jpg", scale=0.25)  # 960x540
    _template_recovery(ref, (560, 360))


def test_template_direct_correlation_paper_mode():
    # Without the reference warp (paper 4.3.2) a pure translation is recovered exactly.
    ref = texture(400, 320, seed=3)
    shift = np.array([40 + 3.4, 40 - 2.7])
    frame = warp_into(ref, lambda xy: xy + shift, 300, 240)
    guess = np.array([41.0, 41.0])  # the coarse model, 3-4 px off
    for cfg in (TemplateConfig(warp_reference=False), TemplateConfig.paper()):
        cp = template_control_points(frame, ref, lambda xy: xy + guess, lambda xy: xy - guess, cfg)
        assert len(cp) == len(template_grid(300, 240, cfg))
        assert np.median(np.linalg.norm(cp.dst - (cp.src + shift), axis=1)) < 0.1


def test_dithered_correlation_reduces_subpixel_bias():
    ref = real_grey("songdo-vision-drone", "images", "00972.jpg", scale=0.25)
    shift = np.array([3.3, -2.6])  # fractional: the plain peak fit is biased here
    frame = warp_into(ref, lambda xy: xy + shift + 100, 560, 340)
    model = lambda xy: xy + 100.0  # noqa: E731
    errs = []
    for n in (0, 1):
        cp = template_control_points(frame, ref, model, None, TemplateConfig(dither_iterations=n))
        errs.append(np.percentile(np.linalg.norm(cp.dst - (cp.src + shift + 100), axis=1), 90))
    assert errs[1] < 0.15 and errs[1] < 0.7 * errs[0], errs


def test_template_grid_and_jitter():
    cfg = TemplateConfig()
    grid = template_grid(400, 300, cfg)
    assert len(grid) == 7 * 5
    assert (np.diff(np.unique(grid[:, 0])) == 50).all()
    assert grid[:, 0].min() >= 37 and grid[:, 0].max() <= 400 - 38
    d = TemplateConfig(jitter_px=12.5, jitter_seed=4)
    g1, g2 = template_grid(400, 300, d), template_grid(400, 300, d)
    np.testing.assert_array_equal(g1, g2)  # reproducible
    assert np.abs(g1 - grid).max() <= 12 and (g1 != grid).any()
    assert (g1 >= 37).all() and (g1[:, 0] <= 362).all() and (g1[:, 1] <= 262).all()
    assert (template_grid(400, 300, TemplateConfig(jitter_px=12.5, jitter_seed=5)) != g1).any()
    assert len(template_grid(60, 300, cfg)) == 0  # narrower than one template


def test_jittered_templates_still_recover_warp():
    ref = texture(700, 560, seed=2)
    ref_size, frame_size = (700, 560), (460, 340)
    truth = bent_warp(ref_size, frame_size)
    frame = warp_into(ref, truth, *frame_size)
    coarse, coarse_inv = coarse_model(ref_size, frame_size)
    cfg = TemplateConfig(jitter_px=12.5, anchor="centre")
    cp = template_control_points(frame, ref, coarse, coarse_inv, cfg)
    grid = template_grid(*frame_size, cfg)
    assert {tuple(p) for p in cp.src.astype(int)} <= {tuple(p) for p in grid}
    assert np.median(np.linalg.norm(cp.dst - truth(cp.src), axis=1)) < 0.2


def test_structure_anchor_follows_the_texture_and_reduces_error():
    ref = real_grey("songdo-vision-drone", "images", "00972.jpg", scale=0.25)
    ref_size, frame_size = (ref.shape[1], ref.shape[0]), (560, 360)
    truth = bent_warp(ref_size, frame_size)
    frame = warp_into(ref, truth, *frame_size)
    coarse, coarse_inv = coarse_model(ref_size, frame_size)
    med = {}
    for anchor in ("centre", "structure"):
        cp = template_control_points(frame, ref, coarse, coarse_inv, TemplateConfig(anchor=anchor))
        med[anchor] = np.median(np.linalg.norm(cp.dst - truth(cp.src), axis=1))
        on_grid = np.isin(cp.src, template_grid(*frame_size)).all()
        assert on_grid == (anchor == "centre")
    assert med["structure"] < 0.9 * med["centre"], med
    # A frame textured only right of x = 200: templates straddling it anchor right of centre.
    tex = texture(400, 200, seed=8)
    tex[:, :200] = 128
    model = lambda xy: xy + 0.0  # noqa: E731
    cp = template_control_points(tex, tex, model, model, TemplateConfig())
    centres = template_grid(400, 200)
    nearest = centres[np.argmin(np.linalg.norm(cp.src[:, None] - centres[None], axis=2), axis=1)]
    straddling = nearest[:, 0] - 37 < 200  # template's left part is flat
    assert straddling.sum() >= 2
    assert (cp.src[straddling, 0] - nearest[straddling, 0] > 5).all()
    np.testing.assert_allclose(cp.dst, cp.src, atol=0.05)


def test_texture_check_skips_flat_templates():
    ref = texture(500, 400, seed=4)
    ref[:, 250:] = 120  # flat right half (asphalt, roof)
    ref[:, 250:] += np.random.default_rng(1).integers(
        0, 2, (400, 250), dtype=np.uint8
    )  # faint noise
    frame = ref[40:360, 40:460].copy()
    model, inverse = (lambda xy: xy + 40.0), (lambda xy: xy - 40.0)
    cp = template_control_points(frame, ref, model, inverse, TemplateConfig())
    assert len(cp) > 0
    # Every kept template lies (with its 75 px extent) at least partly on the textured half.
    assert (cp.src[:, 0] + 40 - 37 < 250).all()
    np.testing.assert_allclose(cp.dst, cp.src + 40.0, atol=0.1)
    loose = template_control_points(
        frame, ref, model, inverse, TemplateConfig(min_template_std=0, min_score=-1)
    )
    assert len(loose) > len(cp)


def test_template_empty_and_flat_inputs_give_empty_control_points():
    flat = np.full((300, 400), 77, np.uint8)
    ref = texture(400, 300)
    ident = lambda xy: xy  # noqa: E731
    for frame, reference in [(flat, ref), (ref, flat), (flat, flat), (ref[:50, :50], ref)]:
        cp = template_control_points(frame, reference, ident, ident, TemplateConfig())
        assert isinstance(cp, ControlPoints) and len(cp) == 0
        assert cp.src.shape == (0, 2) and cp.dst.shape == (0, 2)
    # A model sending everything outside the reference, or to NaN.
    far = lambda xy: xy + 10_000.0  # noqa: E731
    assert len(template_control_points(ref, ref, far, None, TemplateConfig())) == 0
    nan = lambda xy: np.full_like(xy, np.nan)  # noqa: E731
    assert len(template_control_points(ref, ref, nan, None, TemplateConfig())) == 0
    with pytest.raises(ValueError, match="ref_from_frame"):
        template_control_points(ref, ref, lambda xy: xy[:, :1], None, TemplateConfig())
    with pytest.raises(ValueError, match="subpixel"):
        TemplateConfig(subpixel="cubic")
    with pytest.raises(ValueError, match="anchor"):
        TemplateConfig(anchor="corner")


# ---------------------------------------------------------------------------------------------
# gridded SIFT
# ---------------------------------------------------------------------------------------------


def _window_of(xy: np.ndarray, centres: np.ndarray, half: float) -> np.ndarray:
    """Index of the window containing each point (-1 if none)."""
    inside = (np.abs(xy[:, None, :] - centres[None, :, :]) <= half + 1e-9).all(axis=2)
    return np.where(inside.any(axis=1), inside.argmax(axis=1), -1)


def test_gridded_sift_windows_and_accuracy():
    ref = texture(620, 520, seed=5)
    frame_size = (500, 400)
    h = similarity(1.0, 5.0, (250, 200), (312, 258))
    truth = homography_fn(h)
    frame = warp_into(ref, truth, *frame_size)
    coarse = homography_fn(h @ similarity(1.0, 0.0, (0, 0), (2.0, -3.0)))  # 3.6 px off
    cfg = GriddedSiftConfig()
    cp = gridded_sift_control_points(frame, [(ref, coarse, None)], cfg)
    centres = window_centres(*frame_size, cfg)
    half = (cfg.window_px - 1) / 2
    assert len(cp) > 30
    win = _window_of(cp.src, centres, half)
    assert (win >= 0).all(), "frame points outside every window"
    # Each match lies in its window's reference box (mapped corners + margin).
    corners = centres[win][:, None, :] + half * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    mapped = coarse(corners.reshape(-1, 2)).reshape(-1, 4, 2)
    lo = mapped.min(axis=1) - cfg.window_margin_px
    hi = mapped.max(axis=1) + cfg.window_margin_px
    assert ((cp.dst >= lo) & (cp.dst <= hi)).all()
    err = np.linalg.norm(cp.dst - truth(cp.src), axis=1)
    assert (err < 3).mean() > 0.9 and np.median(err) < 0.5
    assert (cp.score > 0).all() and (cp.source == 0).all()


def test_gridded_sift_matches_only_within_corresponding_windows():
    # A scene made of one tile repeated 3 x 3: global matching is ambiguous (every keypoint has
    # identical twins), window-limited matching is not.
    tile = texture(200, 200, seed=6)
    ref = np.tile(tile, (3, 3))
    frame_size = (420, 420)
    offset = np.array([92.0, 95.0])
    truth = lambda xy: xy + offset  # noqa: E731
    frame = warp_into(ref, truth, *frame_size)
    glob = match_ratio(detect_sift(frame), detect_sift(ref), 0.8)
    cp = gridded_sift_control_points(
        frame, [(ref, truth, lambda xy: xy - offset)], GriddedSiftConfig(decimate=1)
    )
    assert len(cp) > 5 * max(len(glob), 1)
    np.testing.assert_allclose(
        np.median(np.linalg.norm(cp.dst - truth(cp.src), axis=1)), 0, atol=0.3
    )


def test_gridded_sift_two_references_cached_keypoints_and_exact_decimation():
    ref0 = texture(600, 500, seed=7)
    frame_size = (480, 380)
    h0 = similarity(1.0, 3.0, (240, 190), (300, 250))
    frame = warp_into(ref0, homography_fn(h0), *frame_size)
    # Second reference: the frame itself shifted (as the previous registered frame would be).
    shift = np.array([-12.0, 7.0])
    ref1 = warp_into(frame, lambda xy: xy - shift, 520, 420)
    refs = [
        (ref0, homography_fn(h0), homography_fn(np.linalg.inv(h0))),
        Reference(ref1, lambda xy: xy + shift, lambda xy: xy - shift),
    ]
    full = gridded_sift_control_points(frame, refs, GriddedSiftConfig(decimate=1))
    assert set(np.unique(full.source)) == {0, 1}
    truth0 = homography_fn(h0)(full.src)
    truth1 = full.src + shift
    err = np.where(full.source[:, None] == 0, full.dst - truth0, full.dst - truth1)
    assert np.median(np.linalg.norm(err, axis=1)) < 0.5

    dec = gridded_sift_control_points(frame, refs, GriddedSiftConfig(decimate=3))
    assert len(dec) == math.ceil(len(full) / 3)
    full_rows = {(*s, *d) for s, d in zip(full.src.round(6), full.dst.round(6), strict=True)}
    assert all(
        (*s, *d) in full_rows for s, d in zip(dec.src.round(6), dec.dst.round(6), strict=True)
    )
    # Spread over the windows, not concentrated in the first ones.
    centres = window_centres(*frame_size, GriddedSiftConfig())
    assert len(np.unique(_window_of(dec.src, centres, 24.5))) > 0.6 * len(
        np.unique(_window_of(full.src, centres, 24.5))
    )

    # Precomputed keypoints (whole images) give the same kind of result.
    kf, k0 = detect_sift(frame), detect_sift(ref0)
    cached = gridded_sift_control_points(
        frame, [(*refs[0], k0), refs[1]], GriddedSiftConfig(decimate=1), frame_keypoints=kf
    )
    assert abs(len(cached) - len(full)) < 0.2 * len(full)
    assert set(np.unique(cached.source)) == {0, 1}


def test_gridded_sift_empty_and_flat_inputs():
    flat = np.full((300, 400), 50, np.uint8)
    ref = texture(400, 300)
    ident = lambda xy: xy  # noqa: E731
    for frame, refs in [
        (flat, [(ref, ident, ident)]),
        (ref, [(flat, ident, ident)]),
        (ref, []),
        (ref[:30, :30], [(ref, ident, ident)]),
        (ref, [(ref, lambda xy: xy + 5000.0, None)]),
    ]:
        cp = gridded_sift_control_points(frame, refs)
        assert isinstance(cp, ControlPoints) and len(cp) == 0
    with pytest.raises(ValueError, match=r"refs\[0\]"):
        gridded_sift_control_points(ref, [ref])
    with pytest.raises(ValueError, match="decimate"):
        GriddedSiftConfig(decimate=0)


def test_templates_fall_back_to_a_second_reference_where_the_first_has_no_content():
    """Templates whose search window touches the first reference's empty part are searched in the
    fallback; each point names its reference and its dst is in that reference's pixels."""
    frame = texture(480, 360, seed=21)
    t_ref, t_fb = np.array([30.4, -12.7]), np.array([-8.2, 5.6])
    ref = warp_into(frame, lambda xy: xy - t_ref, 560, 420)  # ref(x) = frame(x - t_ref)
    fb = warp_into(frame, lambda xy: xy - t_fb, 500, 380)
    ref_valid = np.ones(ref.shape, bool)
    ref_valid[:, 300:] = False  # no content right of x = 300 (frame x ~ 270)
    ref[~ref_valid] = 0
    cfg = TemplateConfig(spacing_px=40, template_px=41, search_px=10, dither_iterations=1)
    cps = template_control_points(
        frame,
        ref,
        lambda xy: xy + t_ref + 1.5,  # the model is 1.5 px off; the search corrects it
        None,
        cfg,
        ref_valid=ref_valid,
        fallback=Reference(fb, lambda xy: xy + t_fb - 1.0),
    )
    from_ref, from_fb = cps.source == 0, cps.source == 1
    assert from_ref.sum() >= 20 and from_fb.sum() >= 20
    # Where the first reference has content it is used; the fallback only beyond it.
    assert (cps.src[from_ref, 0] + t_ref[0] + cfg.half_template + cfg.search_radius < 300 + 2).all()
    assert (cps.src[from_fb, 0] + t_ref[0] + cfg.half_template + cfg.search_radius > 300 - 2).all()
    np.testing.assert_allclose(
        cps.dst[from_ref] - cps.src[from_ref], np.tile(t_ref, (from_ref.sum(), 1)), atol=0.15
    )
    np.testing.assert_allclose(
        cps.dst[from_fb] - cps.src[from_fb], np.tile(t_fb, (from_fb.sum(), 1)), atol=0.15
    )
    # Without a fallback those templates are simply not matched.
    alone = template_control_points(
        frame, ref, lambda xy: xy + t_ref + 1.5, None, cfg, ref_valid=ref_valid
    )
    assert (alone.source == 0).all() and len(alone) == from_ref.sum()
    with pytest.raises(ValueError, match="fallback reference needs warp_reference=True"):
        template_control_points(
            frame,
            ref,
            lambda xy: xy + t_ref,
            None,
            TemplateConfig(warp_reference=False),
            fallback=Reference(fb, lambda xy: xy + t_fb),
        )


def test_min_templates_shrinks_the_spacing_for_small_frames():
    cfg = TemplateConfig(spacing_px=100, template_px=75, min_templates=200)
    big = template_grid(2560, 1920, cfg)
    assert len(big) == 25 * 19  # the spacing holds enough templates: unchanged
    small = template_grid(640, 480, cfg)
    assert len(small) >= 200 and len(template_grid(640, 480, TemplateConfig(spacing_px=100))) < 40
    step = np.diff(np.unique(small[:, 0]))
    assert (step == step[0]).all() and step[0] < 100
