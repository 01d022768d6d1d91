"""Tests of registration.matching.sift: known warps, exact ground truth, false matches at named indices.

Images: a seeded generated texture (always available) and real imagery from ``../shared/data``
(skipped with a reason when absent), warped with known transforms through
``registration.geometry.warp.remap``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from registration import coords
from registration.geometry import warp
from registration.matching import (
    ControlPoints,
    GriddedSiftConfig,
    Keypoints,
    Reference,
    SiftConfig,
    detect_sift,
    downscale,
    downscale_mask,
    gridded_sift_control_points,
    match_ratio,
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


def test_downscale_mask_keeps_only_areas_wholly_of_content():
    """A 1/4-scale content mask is True where its 4x4 block is all content: a no-data band
    ending mid-block makes that block False, whatever the mask's dtype (bool, 0/1, 0/255)."""
    mask = np.ones((40, 64), bool)
    mask[:, :10] = False  # blocks 0-1 (columns 0-7) wholly, block 2 (columns 8-11) half
    small = downscale_mask(mask, 0.25)
    assert small.shape == (10, 16) and small.dtype == bool
    assert not small[:, :3].any() and small[:, 3:].all()
    for other in (mask.astype(np.uint8), mask.astype(np.uint8) * 255):
        np.testing.assert_array_equal(downscale_mask(other, 0.25), small)
