"""Radial distortion models and image correction (paper section 3) against exact ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from registration.geometry import prepare_source_map, remap, remap_prepared
from registration.lens import (
    CanvasInfo,
    DivisionModel,
    HarrisModel,
    PolynomialModel,
    check_valid,
    correction,
    correction_canvas,
    distort_image,
    harris_gamma_limit,
    straight_edge_chart,
    straightness,
    undistort_image,
)

W, H = 640, 480


def frame_points(rng, w=W, h=H, n=2000):
    """Random raw points over the whole frame plus its corners and centre."""
    pts = rng.uniform([-0.5, -0.5], [w - 0.5, h - 0.5], size=(n, 2))
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [(w - 1) / 2, (h - 1) / 2]])
    return np.vstack([pts, corners])


MODELS = [
    HarrisModel(0.7, W, H),
    HarrisModel(1.0, W, H),
    HarrisModel(-0.6, W, H),
    HarrisModel(0.5, W, H, center=(300.0, 250.0)),
    PolynomialModel(-0.12, 0.01, 0.002, W, H),
    PolynomialModel(0.2, -0.05, 0.01, W, H),
    DivisionModel(-0.35, W, H),
    DivisionModel(0.4, W, H),
]


@pytest.mark.parametrize("model", MODELS, ids=lambda m: repr(m.params()))
def test_round_trip_raw_corrected_raw(model, rng):
    raw = frame_points(rng)
    corrected = model.corrected_from_raw(raw)
    assert np.all(np.isfinite(corrected))
    back = model.raw_from_corrected(corrected)
    assert np.max(np.abs(back - raw)) < 1e-6


@pytest.mark.parametrize("gamma", [0.3, 0.7, 1.0, -0.5])
def test_harris_inverse_is_negated_gamma(gamma, rng):
    pts = frame_points(rng)
    m, neg = HarrisModel(gamma, W, H), HarrisModel(-gamma, W, H)
    np.testing.assert_array_equal(m.corrected_from_raw(pts), neg.raw_from_corrected(pts))
    np.testing.assert_array_equal(m.raw_from_corrected(pts), neg.corrected_from_raw(pts))


@pytest.mark.parametrize(
    "model", [HarrisModel(0.0, W, H), PolynomialModel(0, 0, 0, W, H), DivisionModel(0.0, W, H)]
)
def test_zero_parameter_is_identity(model, rng):
    pts = frame_points(rng)
    np.testing.assert_allclose(model.corrected_from_raw(pts), pts, atol=1e-12)
    np.testing.assert_allclose(model.raw_from_corrected(pts), pts, atol=1e-12)


def test_harris_matches_conventions_formula():
    # Hand computation for the top-left corner of a 640x480 frame with gamma 0.7:
    # c = (319.5, 239.5), r_n = 400, rho = |x - c| / r_n, x' = c + r_n f(rho) (x - c)/|x - c|.
    m = HarrisModel(0.7, W, H)
    assert m.r_n == 400.0
    np.testing.assert_array_equal(m.c, [319.5, 239.5])
    x = np.array([[0.0, 0.0]])
    v = x[0] - m.c
    rho = np.linalg.norm(v) / 400.0
    f = rho / np.sqrt(1 + 0.7 * rho**2)
    expected = m.c + 400.0 * f * v / np.linalg.norm(v)
    np.testing.assert_allclose(m.raw_from_corrected(x)[0], expected, atol=1e-12)
    # Positive gamma corrects barrel distortion: a raw corner moves outwards when corrected.
    corr = m.corrected_from_raw(x)[0]
    assert np.linalg.norm(corr - m.c) > np.linalg.norm(v)
    # The centre is fixed.
    np.testing.assert_allclose(m.corrected_from_raw([m.c])[0], m.c, atol=1e-12)


def test_division_and_polynomial_agree_with_harris_to_first_order(rng):
    # Small distortion: Harris(γ) ≈ polynomial k1 = -γ/2 ≈ division λ = -γ/2 (corrected side).
    g = 0.02
    pts = frame_points(rng)
    h = HarrisModel(g, W, H).corrected_from_raw(pts)
    p = PolynomialModel.from_harris(HarrisModel(g, W, H)).corrected_from_raw(pts)
    d = DivisionModel(-g / 2, W, H).corrected_from_raw(pts)
    assert np.max(np.abs(p - h)) < 1e-3  # third-order Taylor series
    assert np.max(np.abs(d - h)) < 0.2  # first order only


def test_polynomial_newton_solves_exactly(rng):
    m = PolynomialModel(-0.1, 0.02, -0.003, W, H)
    pts = frame_points(rng)
    corr = m.corrected_from_raw(pts)
    # f(rho_corrected) must equal rho_raw to solver precision.
    rho_c = np.linalg.norm(corr - m.c, axis=1) / m.r_n
    rho_r = np.linalg.norm(pts - m.c, axis=1) / m.r_n
    np.testing.assert_allclose(m._f(rho_c), rho_r, atol=1e-13)


def test_harris_validity_range_message():
    limit = harris_gamma_limit(1280, 960)
    assert 1.0 < limit < 1.002
    with pytest.raises(ValueError) as exc:
        check_valid(HarrisModel(2.5, 1280, 960))
    msg = str(exc.value)
    assert "gamma 2.5 is out of range for a 1280x960 frame" in msg
    assert "valid gamma < 1.0017" in msg
    assert "\n" not in msg
    check_valid(HarrisModel(1.0, 1280, 960))  # just inside
    check_valid(HarrisModel(-5.0, 1280, 960))  # pincushion correction is always defined
    with pytest.raises(ValueError, match="out of range"):
        check_valid(HarrisModel(limit, 1280, 960))


def test_invalid_models_never_give_silent_nan_images():
    img = np.full((H, W), 128, np.uint8)
    for bad in (
        HarrisModel(1.5, W, H),
        PolynomialModel(-0.3, 0, 0, W, H),
        DivisionModel(-1.5, W, H),
    ):
        assert not bad.is_valid()
        with pytest.raises(ValueError, match="out of range"):
            undistort_image(img, bad)
    # The invalid Harris model really does leave raw corners without a corrected position.
    corners = HarrisModel(1.5, W, H).corrected_from_raw([[0, 0]])
    assert np.isnan(corners).all()


def test_polynomial_and_division_validity_ranges():
    msg = PolynomialModel(-0.2, 0, 0, W, H).validity_problem()
    assert "polynomial" in msg and "k1 >" in msg
    assert PolynomialModel(-0.14, 0, 0, W, H).is_valid()
    lo, hi = DivisionModel(0.0, W, H).lam_limits()
    assert (
        DivisionModel(lo * 0.99, W, H).is_valid() and not DivisionModel(lo * 1.01, W, H).is_valid()
    )
    assert "lambda" in DivisionModel(hi * 1.01, W, H).validity_problem()


def _line_image(w, h, lines, margin=0):
    """Thin anti-aliased straight lines (white on black) in a (h+2m, w+2m) image."""
    import cv2

    img = np.zeros((h + 2 * margin, w + 2 * margin), np.uint8)
    for (x0, y0), (x1, y1) in lines:
        p0 = (int(round((x0 + margin) * 16)), int(round((y0 + margin) * 16)))
        p1 = (int(round((x1 + margin) * 16)), int(round((y1 + margin) * 16)))
        cv2.line(img, p0, p1, 255, 2, cv2.LINE_AA, shift=4)
    return img


def _ridge_points(img, horizontal_y, xs, half=6):
    """Intensity centroid in rows horizontal_y ± half for each column xs -> (N, 2) points."""
    pts = []
    for x in xs:
        rows = np.arange(int(horizontal_y) - half, int(horizontal_y) + half + 1)
        v = img[rows, x].astype(np.float64)
        if v.sum() > 0:
            pts.append((x, np.sum(rows * v) / v.sum()))
    return np.array(pts)


def test_correcting_a_distorted_image_of_straight_lines_makes_them_straight():
    gamma, margin = 0.7, 200
    model = HarrisModel(gamma, W, H)
    ys = [60.0, 150.0, 330.0, 420.0]
    straight = _line_image(W, H, [((-margin, y), (W + margin, y)) for y in ys], margin)
    raw = distort_image(straight, model, origin=(-margin, -margin))
    corrected, info = undistort_image(raw, model)
    assert info == CanvasInfo("same", W, H, (0.0, 0.0))
    xs = np.arange(40, W - 40, 8)
    for y in ys:
        # Corrected: the line is back where it was drawn (two resamplings of a 2 px line: within
        # a quarter pixel) and straight to a tenth of a pixel.
        pts = _ridge_points(corrected, y, xs)
        assert np.max(np.abs(pts[:, 1] - y)) < 0.25
        assert straightness([pts], HarrisModel(0.0, W, H)).overall < 0.1
        # Raw: the same line is visibly bent (measured along its predicted raw curve).
        curve = model.raw_from_corrected(np.column_stack([xs, np.full(len(xs), y)]))
        assert np.ptp(curve[:, 1]) > 5.0
        assert straightness([curve], HarrisModel(0.0, W, H)).overall > 1.0


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_undistort_inverts_distort_on_a_chart(interpolation):
    model = HarrisModel(0.5, W, H)
    margin = 200
    chart = straight_edge_chart(W + 2 * margin, H + 2 * margin, seed=3)
    raw = distort_image(chart, model, origin=(-margin, -margin), interpolation="cubic")
    corrected, _ = undistort_image(raw, model, interpolation=interpolation)
    truth = chart[margin : margin + H, margin : margin + W].astype(np.float64)
    err = np.abs(corrected.astype(np.float64) - truth)
    # Two resamplings of a chart with sharp anti-aliased edges: small mean error everywhere.
    assert err[20:-20, 20:-20].mean() < 3.0
    # A wrong gamma is clearly worse.
    wrong, _ = undistort_image(raw, HarrisModel(0.3, W, H), interpolation=interpolation)
    assert (
        np.abs(wrong.astype(np.float64) - truth)[20:-20, 20:-20].mean()
        > 2 * err[20:-20, 20:-20].mean()
    )


def test_full_canvas_holds_every_raw_pixel():
    model = HarrisModel(0.7, W, H)
    raw = np.zeros((H, W, 3), np.uint8)
    raw[0, 0] = (255, 0, 0)  # a marked corner pixel
    raw[H - 1, W - 1] = (0, 0, 255)
    same, same_info = undistort_image(raw, model, canvas="same")
    full, info = undistort_image(raw, model, canvas="full")
    assert same.shape == (H, W, 3) and same.max() == 0  # corners are cropped on "same"
    assert info.kind == "full" and info.width > W and info.height > H
    assert full.shape == (info.height, info.width, 3)
    corr = model.corrected_from_raw([[0, 0], [W - 1, H - 1]])
    canvas_xy = info.canvas_from_corrected(corr)
    np.testing.assert_allclose(info.corrected_from_canvas(canvas_xy), corr)
    assert np.all(canvas_xy >= 0) and np.all(canvas_xy < [info.width, info.height])
    # The marked pixels land where the canvas info says (bilinear spreads them by < 1 px).
    (x0, y0), (x1, y1) = np.round(canvas_xy).astype(int)
    assert full[max(y0 - 1, 0) : y0 + 2, max(x0 - 1, 0) : x0 + 2, 0].max() > 20
    assert full[max(y1 - 1, 0) : y1 + 2, max(x1 - 1, 0) : x1 + 2, 2].max() > 20
    assert full[:, :, 0].sum() > 0 and full[: info.height // 2, : info.width // 2, 2].max() == 0
    # Pincushion correction shrinks the frame: the full canvas is smaller than the raw frame.
    small = correction_canvas(HarrisModel(-0.7, W, H), "full")
    assert small.width < W and small.height < H


def test_full_canvas_refuses_runaway_size():
    with pytest.raises(ValueError, match="full canvas"):
        correction_canvas(HarrisModel(1.0, W, H), "full")


def test_maps_are_cached_per_model_and_canvas():
    correction.clear_map_cache()
    img = np.random.default_rng(0).integers(0, 255, (H, W, 3), dtype=np.uint8)
    model = HarrisModel(0.4, W, H)
    a, _ = undistort_image(img, model)
    info0 = correction._prepared_correction.cache_info()
    b, _ = undistort_image(img, HarrisModel(0.4, W, H))  # equal model -> same cache entry
    grey, _ = undistort_image(img[:, :, 0], model)  # channels do not matter
    info1 = correction._prepared_correction.cache_info()
    assert info1.hits == info0.hits + 2 and info1.misses == info0.misses
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(grey, a[:, :, 0])
    undistort_image(img, model, canvas="full")
    assert correction._prepared_correction.cache_info().misses == info0.misses + 1


def test_prepared_map_matches_float_remap(rng):
    img = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    smooth = np.asarray(
        __import__("cv2").GaussianBlur(img, (0, 0), 3), dtype=np.uint8
    )  # smooth: fixed-point positions differ by <= 1/64 px
    m = HarrisModel(0.6, W, H)
    src, _ = correction.correction_source_map(m)
    for interp in ("nearest", "linear", "cubic"):
        ref = remap(smooth, src, interpolation=interp)
        prepared = prepare_source_map(src, interpolation=interp)
        assert prepared.fixed_point == (interp != "cubic")  # the faster form measured for each
        fast = remap_prepared(smooth, prepared)
        assert np.abs(ref.astype(int) - fast).max() <= 2
        forced = remap_prepared(
            smooth, prepare_source_map(src, interpolation=interp, fixed_point=True)
        )
        assert np.abs(ref.astype(int) - forced).max() <= 2


def test_source_map_is_exact_to_hundredths(rng):
    m = HarrisModel(0.9, W, H)
    src, _ = correction.correction_source_map(m)
    pts = rng.uniform([0, 0], [W - 1, H - 1], (500, 2)).round()
    exact = m.raw_from_corrected(pts)
    got = src[pts[:, 1].astype(int), pts[:, 0].astype(int)]
    assert np.max(np.abs(got - exact)) < 0.01


def test_dtypes_and_channels_preserved():
    model = HarrisModel(0.3, W, H)
    for img in (
        np.zeros((H, W), np.uint8),
        np.zeros((H, W, 3), np.uint8),
        np.zeros((H, W, 4), np.uint8),
        np.zeros((H, W), np.uint16),
        np.zeros((H, W), np.float32),
    ):
        out, _ = undistort_image(img, model)
        assert out.shape == img.shape and out.dtype == img.dtype


def test_bad_arguments_are_named():
    model = HarrisModel(0.3, W, H)
    with pytest.raises(ValueError, match="is 320x240 but the distortion model is for a 640x480"):
        undistort_image(np.zeros((240, 320), np.uint8), model)
    with pytest.raises(ValueError, match="interpolation"):
        undistort_image(np.zeros((H, W), np.uint8), model, interpolation="nearestish")
    with pytest.raises(ValueError, match="canvas"):
        undistort_image(np.zeros((H, W), np.uint8), model, canvas="huge")
    with pytest.raises(ValueError, match="gamma must be finite"):
        HarrisModel(float("nan"), W, H)
    with pytest.raises(ValueError, match="frame size must be positive"):
        HarrisModel(0.1, 0, H)


# ------------------------------------------------------------------------------------------
# an explicit centre (conventions.md: "unless a centre is given explicitly")


def conventions_raw_from_corrected(xy, gamma, w, h, c):
    """The formula of conventions.md written out independently of the project's code."""
    r_n = np.sqrt(w**2 + h**2) / 2
    out = []
    for x, y in xy:
        dx, dy = x - c[0], y - c[1]
        dist = np.sqrt(dx * dx + dy * dy)
        if dist == 0:
            out.append((c[0], c[1]))
            continue
        rho = dist / r_n
        f = rho / np.sqrt(1 + gamma * rho**2) if 1 + gamma * rho**2 > 0 else np.nan
        out.append((c[0] + r_n * f * dx / dist, c[1] + r_n * f * dy / dist))
    return np.array(out)


def test_harris_model_uses_the_given_centre(rng):
    c = (250.25, 301.75)  # well away from the frame centre (319.5, 239.5)
    pts = frame_points(rng, n=300)
    for gamma in (0.7, -0.4):
        m = HarrisModel(gamma, W, H, center=c)
        expected = conventions_raw_from_corrected(pts, gamma, W, H, c)
        np.testing.assert_allclose(m.raw_from_corrected(pts), expected, atol=1e-9)
        # The inverse is the same formula with -gamma, about the same centre.
        expected_inv = conventions_raw_from_corrected(pts, -gamma, W, H, c)
        np.testing.assert_allclose(m.corrected_from_raw(pts), expected_inv, atol=1e-9)
        # The given centre is the fixed point, the frame centre is not.
        np.testing.assert_allclose(m.raw_from_corrected([c])[0], c, atol=1e-12)
        moved = m.raw_from_corrected([[319.5, 239.5]])[0]
        assert np.linalg.norm(moved - [319.5, 239.5]) > 1.0


def test_undistorted_image_with_a_given_centre_matches_an_independent_remap():
    from scipy import ndimage

    gamma, c = 0.6, (270.0, 280.5)
    img = ndimage.gaussian_filter(np.random.default_rng(3).uniform(0, 255, (H, W)), 2.5)
    img = img.astype(np.float32)
    # Independent: corrected pixel (x, y) samples the raw image at the conventions' formula.
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    r_n = np.hypot(W, H) / 2
    dx, dy = xs - c[0], ys - c[1]
    rho = np.hypot(dx, dy) / r_n
    scale = 1.0 / np.sqrt(1 + gamma * rho**2)  # f(rho) / rho
    src_x, src_y = c[0] + dx * scale, c[1] + dy * scale
    expected = ndimage.map_coordinates(img, [src_y, src_x], order=1, mode="constant", cval=0)
    got, info = undistort_image(img, HarrisModel(gamma, W, H, center=c))
    assert info.width == W and info.height == H and info.origin == (0.0, 0.0)
    inner = np.s_[5:-5, 5:-5]
    assert np.abs(got[inner] - expected[inner]).max() < 0.5
    # Ignoring the centre (frame centre instead) would be far off.
    wrong, _ = undistort_image(img, HarrisModel(gamma, W, H))
    assert np.abs(wrong[inner] - expected[inner]).max() > 10


def test_correction_stretch_is_exact_for_harris(rng):
    from registration.lens.radial import _Radial

    m = HarrisModel(0.9, W, H, center=(300.0, 200.0))
    pts = frame_points(rng, n=500)
    s_r, s_t = m.correction_stretch(pts)
    # Against a central finite difference of corrected_from_raw along / across the radius.
    d = pts - m.c
    rhat = d / np.linalg.norm(d, axis=1, keepdims=True)
    that = np.stack([-rhat[:, 1], rhat[:, 0]], axis=1)
    e = 1e-4
    num_r = np.linalg.norm(
        m.corrected_from_raw(pts + e * rhat) - m.corrected_from_raw(pts - e * rhat), axis=1
    ) / (2 * e)
    num_t = np.linalg.norm(
        m.corrected_from_raw(pts + e * that) - m.corrected_from_raw(pts - e * that), axis=1
    ) / (2 * e)
    np.testing.assert_allclose(s_r, num_r, rtol=1e-5)
    np.testing.assert_allclose(s_t, num_t, rtol=1e-5)
    # The generic (numerical) version agrees with the closed form away from the limit.
    g_r, g_t = _Radial.correction_stretch(HarrisModel(0.3, W, H), pts)
    h_r, h_t = HarrisModel(0.3, W, H).correction_stretch(pts)
    np.testing.assert_allclose(g_t, h_t, rtol=1e-6)
    np.testing.assert_allclose(g_r, h_r, rtol=2e-3)


# ------------------------------------------------------------------------------------------
# the range a user may ask for, tiny frames, simulated frames' masks


def test_gamma_range_names_both_ends():
    from registration.lens import check_harris_gamma, harris_gamma_range

    lo, hi = harris_gamma_range(480, 360)
    assert lo == -1.0 and 1.0 < hi < 1.01
    assert check_harris_gamma(-1.0, 480, 360) == -1.0
    assert check_harris_gamma(0.99, 480, 360) == 0.99
    for bad in (-50.0, -1.0001, 2.5, hi, float("nan")):
        with pytest.raises(ValueError) as exc:
            check_harris_gamma(bad, 480, 360)
        msg = str(exc.value)
        assert "valid -1 <= gamma < 1.0046" in msg and "480x360" in msg and "\n" not in msg
    # An explicit centre moves the farthest corner and lowers the limit.
    assert harris_gamma_range(480, 360, (100.0, 100.0))[1] < hi


def test_one_pixel_frame_has_no_limit_and_no_division_by_zero():
    assert harris_gamma_limit(1, 1) == float("inf")
    m = HarrisModel(0.7, 1, 1)
    assert m.is_valid()
    out, _ = undistort_image(np.full((1, 1), 7, np.uint8), m)
    assert out.shape == (1, 1)


def test_simulated_frame_mask_marks_what_sees_the_scene():
    from registration.lens import simulate_raw_frame

    scene = straight_edge_chart(600, 450, seed=5) // 2 + 100  # nothing black in the scene
    for gamma, zoom in ((0.3, 2.5), (1.0, 1.5)):
        raw, scale, mask = simulate_raw_frame(
            scene, HarrisModel(gamma, 320, 240), max_zoom_out=zoom, return_mask=True
        )
        assert mask.shape == raw.shape and mask.dtype == bool
        assert np.all(raw[mask] >= 100)  # every pixel in the mask sees only the scene
        assert not mask[raw == 0].any()  # every blank pixel is outside it
        if gamma == 1.0:
            assert 0.01 < (~mask).mean() < 0.5  # the corners lie beyond the scene
        else:
            assert mask.all()
