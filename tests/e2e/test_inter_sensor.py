"""Inter-sensor registration of the reference frame (paper 4.3) at any heading, map resolution
and sensor: the simulator's exact truth with base maps turned and resampled, a wrong click, real
SRIF pairs four years apart, and a real UAV photo against an official orthophoto of another
date (OrthoLoC) with a reference registration from the camera's pose."""

from __future__ import annotations

import dataclasses
import json
import math

import cv2
import numpy as np
import pytest

from registration.geometry import Projective
from registration.global_registration import (
    CoarseBase,
    agreement,
    coarse_register,
    fine_register_reference,
    frame_view,
    gradient_images,
)
from registration.io import open_frames, read_image
from registration.lens import HarrisModel
from registration.matching import to_grey
from registration.run import get_preset
from registration.synth import SimConfig, load_truth, rebase, simulate
from tests.conftest import shared_data

W, H = 640, 480
# The heading sweep's frames: 36 maps x (one click, none) is the suite's costliest test, and
# `aerialreg bench heading` runs the same sweep at 640x480 (README).
SWEEP_SIZE = (480, 360)
HEADINGS = range(0, 360, 30)
# Error of the reference frame's global (fine) model against the exact truth, in frame pixels
# (base px divided by the base's resolution factor), seed 3: 0.27-0.38 measured at every
# heading and resolution at 480x360 with one click, 0.27-0.63 without (0.46-0.53 both at
# 640x480); the bar is 1 px.
REFERENCE_LIMIT_FRAME_PX = 1.0


def _one_frame(tmp_path_factory, size):
    out = tmp_path_factory.mktemp("inter") / "sim"
    simulate(out, SimConfig(frame_size=size, n_frames=1, seed=3, video=False))
    return out


@pytest.fixture(scope="module")
def one_frame(tmp_path_factory):
    return _one_frame(tmp_path_factory, (W, H))


@pytest.fixture(scope="module")
def sweep_frame(tmp_path_factory):
    return _one_frame(tmp_path_factory, SWEEP_SIZE)


def _grid(size=(W, H)) -> np.ndarray:
    gx, gy = np.meshgrid(np.linspace(0, size[0] - 1, 17), np.linspace(0, size[1] - 1, 13))
    return np.c_[gx.ravel(), gy.ravel()]


def _register(sim, seed, base_features: CoarseBase | None = None):
    """Coarse and fine steps on the reference frame; ``base_features`` keeps the map's keypoints
    between calls on the same map (as the app does between clicks)."""
    truth = load_truth(sim)
    frame = open_frames(sim / "frames").get(0)
    base = read_image(sim / "base.png")
    valid = base.max(axis=2) > 0  # the turned map's no-data corners
    cfg = get_preset("default")
    coarse = coarse_register(
        frame, base, truth.gamma, seed, cfg.coarse, match_in=cfg.match_in, base_valid=valid,
        base_features=base_features, rng=0,
    )  # fmt: skip
    if not coarse:
        return coarse, None, truth
    fine = fine_register_reference(
        frame, base, truth.gamma, coarse, cfg.fine, match_in=cfg.match_in, base_valid=valid
    )
    return coarse, fine, truth


def _frame_px_error(fine, truth, scale: float, size=(W, H)) -> float:
    grid = _grid(size)
    est = fine.base_from_corrected.apply(HarrisModel(truth.gamma, *size).corrected_from_raw(grid))
    return float(np.mean(np.hypot(*(est - truth.frame_to_base(0, grid)).T)) / scale)


@pytest.mark.slow
@pytest.mark.parametrize("scale", [0.5, 1.0, 2.0])
def test_reference_frame_at_every_heading_and_map_resolution(sweep_frame, tmp_path, scale):
    """Base map turned 0-330° in 30° steps and resampled at 0.5x, 1x, 2x: one click with a 2 px
    error, and no click at all, both register the reference frame within 1 frame px."""
    rng = np.random.default_rng(int(scale * 10))
    failures = []
    w, h = SWEEP_SIZE
    for heading in HEADINGS:
        sim = rebase(sweep_frame, tmp_path / f"h{heading}", heading, scale)
        truth = load_truth(sim)
        seed_f = np.array([0.45 * w, 0.55 * h])
        a = rng.uniform(0, 2 * math.pi)
        seed_b = truth.frame_to_base(0, seed_f[None])[0] + 2.0 * np.array(
            [math.cos(a), math.sin(a)]
        )
        base = read_image(sim / "base.png")
        base_features = CoarseBase(base, get_preset("default").coarse, base.max(axis=2) > 0)
        for label, seed in (("one click", (*seed_f, *seed_b)), ("no click", None)):
            coarse, fine, truth = _register(sim, seed, base_features)
            if not coarse or not fine:
                failures.append(f"{heading}° {label}: {(fine or coarse).reason}")
                continue
            err = _frame_px_error(fine, truth, scale, SWEEP_SIZE)
            if not err < REFERENCE_LIMIT_FRAME_PX:
                failures.append(f"{heading}° {label}: {err:.2f} frame px")
            if seed is not None:
                true = _true_heading(truth, SWEEP_SIZE)
                gap = abs((coarse.heading_deg - true + 180) % 360 - 180)
                if gap > 3:
                    failures.append(f"{heading}° {label}: heading estimate {gap:.1f}° off")
    assert not failures, f"scale {scale}: " + "; ".join(failures)


def _true_heading(truth, size=(W, H)) -> float:
    """Rotation frame -> base of the truth at the frame centre, degrees."""
    w, h = size
    c = np.array([[w / 2, h / 2], [w / 2 + 20, h / 2]])
    b = truth.frame_to_base(0, c)
    f = HarrisModel(truth.gamma, w, h).corrected_from_raw(c)
    return math.degrees(math.atan2(*(b[1] - b[0])[::-1]) - math.atan2(*(f[1] - f[0])[::-1])) % 360.0


def test_two_clicks_fix_heading_and_scale(one_frame, tmp_path):
    sim = rebase(one_frame, tmp_path / "h135", 135.0, 0.5)
    truth = load_truth(sim)
    f = np.array([[0.3 * W, 0.3 * H], [0.7 * W, 0.7 * H]])
    b = truth.frame_to_base(0, f)
    coarse, fine, truth = _register(sim, [(*f[0], *b[0]), (*f[1], *b[1])])
    assert coarse and fine and coarse.gate == "two seeds"
    assert abs((coarse.heading_deg - _true_heading(truth) + 180) % 360 - 180) < 2.0
    assert _frame_px_error(fine, truth, 0.5) < REFERENCE_LIMIT_FRAME_PX


def test_a_click_on_another_street_is_refused_with_a_reason(one_frame, tmp_path):
    """A click 150 px away from the right spot (another street) must not give a silent wrong
    answer: the step fails and says the click contradicts the registration found."""
    sim = rebase(one_frame, tmp_path / "h90", 90.0, 1.0)
    truth = load_truth(sim)
    seed_f = np.array([0.5 * W, 0.5 * H])
    seed_b = truth.frame_to_base(0, seed_f[None])[0] + (150.0, 0.0)
    coarse, fine, _ = _register(sim, (*seed_f, *seed_b))
    if coarse:  # if it ever succeeds, it must be right despite the click
        assert fine and _frame_px_error(fine, truth, 1.0) < REFERENCE_LIMIT_FRAME_PX
    else:
        assert "click" in coarse.reason and "\n" not in coarse.reason


def test_the_images_confirm_the_true_registration_and_not_a_wrong_one(one_frame, tmp_path):
    """``correlation.agreement``, what ``CoarseConfig.max_chance_p`` refuses on: the reference
    frame against a map turned 143° at 0.5x, with the true projective (fitted to the exact
    truth) and with that model moved 40 map px and turned 20° about the frame's centre."""
    sim = rebase(one_frame, tmp_path / "h143", 143.0, 0.5)
    truth = load_truth(sim)
    frame = open_frames(sim / "frames").get(0)
    base = read_image(sim / "base.png")
    cfg = get_preset("default")
    lens = HarrisModel(truth.gamma, W, H)
    grid = _grid()
    true_model = Projective.estimate(lens.corrected_from_raw(grid), truth.frame_to_base(0, grid))
    c = true_model.apply(np.array([[W / 2, H / 2]]))[0]
    a = math.radians(20.0)
    turn = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    move = np.array([[1, 0, 40 - c[0]], [0, 1, -c[1]], [0, 0, 1]])
    back = np.array([[1, 0, c[0]], [0, 1, c[1]], [0, 0, 1]])
    wrong_model = Projective.from_matrix(back @ turn @ move @ true_model.matrix)
    view = frame_view(frame, truth.gamma, cfg.match_in)
    images = gradient_images(
        view.grey, view.to_corrected, view.from_corrected, to_grey(base), base.max(axis=2) > 0
    )  # fmt: skip
    right = agreement(images, true_model, cfg.coarse.correlation)
    wrong = agreement(images, wrong_model, cfg.coarse.correlation)
    # measured: 1173 agreeing (p ~ 0), and 5 of 46 with p = 0.22
    assert right.agreeing > 0.5 * right.matched and right.chance_p < 1e-100, right
    assert wrong.chance_p > 100 * cfg.coarse.max_chance_p, wrong


# ------------------------------------------------------------------------------------------
# Real imagery


def _srif_pair(folder, i):
    im1 = cv2.imread(str(folder / f"pair{i}_1.jpg"))
    im2 = cv2.imread(str(folder / f"pair{i}_2.jpg"))
    gt = np.loadtxt(folder / f"gt_{i}.txt").reshape(2, 3)
    return im1, im2, cv2.cvtColor(im2, cv2.COLOR_BGR2GRAY) > 0, gt


def _srif_click(i, im1, valid, gt):
    """A point of image 1's central 60 % whose true position lies 15 px inside image 2's
    content, the image-2 side 2 px off in a random direction (seeded by the pair id)."""
    rng = np.random.default_rng(i)
    h1, w1 = im1.shape[:2]
    inner = cv2.erode(valid.astype(np.uint8), np.ones((31, 31), np.uint8))
    for _ in range(2000):
        p = rng.uniform([0.2 * w1, 0.2 * h1], [0.8 * w1, 0.8 * h1])
        q = p @ gt[:, :2].T + gt[:, 2]
        x, y = round(q[0]), round(q[1])
        if 0 <= x < inner.shape[1] and 0 <= y < inner.shape[0] and inner[y, x]:
            a = rng.uniform(0, 2 * math.pi)
            return (*p, *(q + 2.0 * np.array([math.cos(a), math.sin(a)])))
    raise AssertionError(f"pair {i}: no point of image 1 inside image 2")


def _corner_error(model, gt, w, h) -> float:
    c = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    err = np.hypot(*(model.apply(c) - (c @ gt[:, :2].T + gt[:, 2])).T)
    return float(err.mean()) if np.isfinite(err).all() else math.inf


def _srif_corner_error(im1, im2, valid, gt, seed, cfg, *, rng) -> float:
    """Coarse + fine registration of a SRIF pair: mean error at image 1's corners, px."""
    coarse = coarse_register(
        im1, im2, 0.0, seed, cfg.coarse, match_in=cfg.match_in, base_valid=valid, rng=rng
    )
    if not coarse:
        return math.inf
    fine = fine_register_reference(
        im1, im2, 0.0, coarse, cfg.fine, match_in=cfg.match_in, base_valid=valid
    )
    h, w = im1.shape[:2]
    return _corner_error(fine.base_from_corrected, gt, w, h) if fine else math.inf


def _srif_within_10px(im1, im2, valid, gt, seed, cfg, *, rng) -> bool:
    """Coarse + fine registration of a SRIF pair, within 10 px at image 1's corners."""
    return _srif_corner_error(im1, im2, valid, gt, seed, cfg, rng=rng) < 10


@pytest.mark.slow
def test_srif_one_click_beats_no_click_on_real_pairs():
    """SRIF pairs 1-20 (two dates four years apart, rotations up to 360°, scales 0.25-2): the
    corner error of coarse + fine under 10 px for 20 of 20 with one click (measured; 19 before
    the refit through the click took pair 19 off the roofs), 16 of 20 without (measured 80 %;
    plain OpenCV: 20 % over all 200)."""
    folder = shared_data("srif-optical-optical")
    cfg = get_preset("default")
    ok = {"click": 0, "none": 0}
    for i in range(1, 21):
        im1, im2, valid, gt = _srif_pair(folder, i)
        for mode, seed in (("click", _srif_click(i, im1, valid, gt)), ("none", None)):
            ok[mode] += _srif_within_10px(im1, im2, valid, gt, seed, cfg, rng=i)
    assert ok["click"] >= 18, ok  # measured 20 of 20
    assert ok["none"] >= 13, ok  # measured 16 of 20
    assert ok["click"] > ok["none"], ok


def test_srif_click_where_sift_votes_mislead_is_rescued_by_image_correlation():
    """SRIF pair 36 (image 2 four years later and 1.71x finer): around the click a single SIFT
    match votes, for a heading 26° and a scale 3.7x off, and the registration built on it is
    291 px off. The heading and scale found by correlating the images around the click
    (HeadingConfig.patch_below_votes) bring it to 16.3 px at the corners. The pair is marginal
    (16-18 of 361 templates match in the first correlation round, 12 needed): one grey level of
    the gradient image's scaling in a few pixels (NumPy 2.4's float32 percentile) moved it
    between 2.0 and 16.3 px, so the bound is loose. At 16.3 px it is still a miss, and the
    images say so: 6 of 52 templates agree with it, as chance alone would (p 0.2), so by
    default it is refused (``CoarseConfig.max_chance_p``) and the analyst asked for a second
    click; the comparison runs with that check off."""
    folder = shared_data("srif-optical-optical")
    im1, im2, valid, gt = _srif_pair(folder, 36)
    seed = _srif_click(36, im1, valid, gt)
    cfg = get_preset("default")
    refused = coarse_register(
        im1, im2, 0.0, seed, cfg.coarse, match_in=cfg.match_in, base_valid=valid, rng=36
    )
    assert not refused and "do not confirm" in refused.reason, refused.reason
    unchecked = dataclasses.replace(cfg, coarse=dataclasses.replace(cfg.coarse, max_chance_p=1.0))
    rescued = _srif_corner_error(im1, im2, valid, gt, seed, unchecked, rng=36)
    heading = dataclasses.replace(cfg.coarse.heading, patch_below_votes=0)
    without = dataclasses.replace(
        unchecked, coarse=dataclasses.replace(unchecked.coarse, heading=heading)
    )
    misled = _srif_corner_error(im1, im2, valid, gt, seed, without, rng=36)
    assert rescued < 25 and misled > 100, (rescued, misled)  # measured 16.3 and 291


@pytest.mark.slow
def test_srif_click_on_the_ground_wins_over_the_roofs():
    """SRIF pairs 19, 26 and 145, whose texture mostly follows roofs displaced by parallax
    between the two dates (README, "Half of the misses followed the roofs"): the first fine fit
    follows the roofs, over 10 px off at image 1's corners and 14-17 px from the click.
    Refitted from the click (``FineConfig.click_refit_px``) it takes the ground (measured 5.5,
    4.2 and 1.8 px). Pair 26's ground holds 31 control points against the roofs' 198 (0.16):
    the refit is kept above ``CLICK_REFIT_MIN_SHARE``."""
    folder = shared_data("srif-optical-optical")
    cfg = get_preset("default")
    for i in (19, 26, 145):
        im1, im2, valid, gt = _srif_pair(folder, i)
        coarse = coarse_register(
            im1, im2, 0.0, _srif_click(i, im1, valid, gt), cfg.coarse, match_in=cfg.match_in,
            base_valid=valid, rng=i,
        )  # fmt: skip
        errors = {}
        for refit_px in (0.0, cfg.fine.click_refit_px):
            fine = fine_register_reference(
                im1, im2, 0.0, coarse, dataclasses.replace(cfg.fine, click_refit_px=refit_px),
                match_in=cfg.match_in, base_valid=valid,
            )  # fmt: skip
            errors[refit_px] = _corner_error(fine.base_from_corrected, gt, *im1.shape[1::-1])
        assert errors[0.0] > 10 and errors[cfg.fine.click_refit_px] < 8, (i, errors)


def test_srif_registration_the_images_do_not_confirm_is_refused_and_two_clicks_find_it():
    """SRIF pair 76 (image 2 four years later, 0.62x, turned 315°): around the click a single
    SIFT match votes, for a heading 154° and a scale 3.2x off, the images around the click
    suggest nothing better, and the registration built on the vote put image 1's corners
    1107 px off, silently. No template of the map agrees with it (``max_chance_p``): it is
    refused, the message asks for a second click, and with a second click it is 5.3 px off."""
    folder = shared_data("srif-optical-optical")
    im1, im2, valid, gt = _srif_pair(folder, 76)
    cfg = get_preset("default")
    one = _srif_click(76, im1, valid, gt)
    coarse = coarse_register(
        im1, im2, 0.0, one, cfg.coarse, match_in=cfg.match_in, base_valid=valid, rng=76
    )
    assert not coarse and "do not confirm" in coarse.reason and "second" in coarse.reason
    assert coarse.image_agreement.agreeing == 0
    two = [one, _srif_click(1076, im1, valid, gt)]
    assert _srif_corner_error(im1, im2, valid, gt, two, cfg, rng=76) < 8  # measured 5.3


@pytest.mark.slow
def test_srif_one_click_where_the_points_span_part_of_image_1():
    """SRIF pairs 61-80 with one click: 17 of 20 within 10 px at image 1's corners (measured 17;
    15 when an affine fitted to points spanning less than half of image 1 could be kept: its
    shear and unequal scales, carried to the corners where image 2 has no data, left pairs 65
    and 69 12.4 and 10.5 px off)."""
    folder = shared_data("srif-optical-optical")
    cfg = get_preset("default")
    ok = 0
    for i in range(61, 81):
        im1, im2, valid, gt = _srif_pair(folder, i)
        ok += _srif_within_10px(im1, im2, valid, gt, _srif_click(i, im1, valid, gt), cfg, rng=i)
    assert ok >= 16, ok  # measured 17 of 20 (15 before)


def _ortholoc():
    folder = shared_data("ortholoc-uav-vs-orthophoto", "demo_urban_residential")
    k = np.array(
        json.loads((folder / "urban_residential_intrinsics.json").read_text())["intrinsics"]
    )
    pose = np.array(
        json.loads((folder / "urban_residential_extrinsics.json").read_text())["pose_w2c"]
    )
    query = cv2.imread(str(folder / "urban_residential.jpg"))
    dop = cv2.imread(str(folder / "urban_residential_DOP.tif"), cv2.IMREAD_COLOR)
    xdop = cv2.imread(str(folder / "urban_residential_xDOP.tif"), cv2.IMREAD_COLOR)
    return k, pose, query, dop, xdop


def _base_from_query(k, pose, z0):
    """Ground-plane homography query px -> orthophoto px (SOURCE.md's formula; pixel centres at
    integers, the GeoTIFF's affine maps pixel corners)."""
    s, x0, y0 = 0.1815185546875, -92.821044921875, 92.836181640625
    m = np.array([[s, 0, x0 + s / 2], [0, -s, y0 - s / 2], [0, 0, z0], [0, 0, 1]])
    return np.linalg.inv(k @ pose @ m)


def _apply(h, p):
    q = np.c_[p, np.ones(len(p))] @ h.T
    return q[:, :2] / q[:, 2:]


def _ortholoc_reference(k, pose, query, dop):
    """The reference registration query px -> orthophoto px: the ground plane's height fitted
    to plain OpenCV SIFT + MAGSAC matches with the same-date orthophoto (DOP)."""
    kq, kd = cv2.SIFT.create(), cv2.SIFT.create()
    pq, dq = kq.detectAndCompute(cv2.cvtColor(query, cv2.COLOR_BGR2GRAY), None)
    pd, dd = kd.detectAndCompute(cv2.cvtColor(dop, cv2.COLOR_BGR2GRAY), None)
    knn = cv2.BFMatcher().knnMatch(dq, dd, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    a = np.array([pq[m.queryIdx].pt for m in good])
    b = np.array([pd[m.trainIdx].pt for m in good])
    _, mask = cv2.findHomography(a, b, cv2.USAC_MAGSAC, 3.0)
    a, b = a[mask.ravel() > 0], b[mask.ravel() > 0]
    heights = np.arange(-15.0, -10.0, 0.05)
    resid = [np.median(np.hypot(*(_apply(_base_from_query(k, pose, z), a) - b).T)) for z in heights]
    assert min(resid) < 2.0  # the reference itself fits the same-date map
    return _base_from_query(k, pose, heights[int(np.argmin(resid))])


def test_ortholoc_uav_photo_against_an_orthophoto_of_another_date():
    """A real UAV photo (25° off nadir, turned ~90° against the map) against the official
    orthophoto of another date and sensor (xDOP), one click and none: within 2 px (median over the
    frame) of the reference registration from the camera's intrinsics and pose.

    The reference needs the ground's height, which the sample does not give: it is fitted
    here, independently of our pipeline, to plain OpenCV SIFT + MAGSAC matches between the photo
    and the same-date orthophoto (DOP): z0 = -12.75 m, 1.3 px median residual (the SOURCE's
    estimate, -11 m, leaves 8.8 px). Measured: median 1.47 px, mean 2.01 px (the mean is
    pulled by the frame's far edge, where the ground plane model itself is least reliable)."""
    k, pose, query, dop, xdop = _ortholoc()
    ref = _ortholoc_reference(k, pose, query, dop)

    gx, gy = np.meshgrid(np.linspace(0, 1023, 17), np.linspace(0, 767, 13))
    grid = np.c_[gx.ravel(), gy.ravel()]
    seed_b = _apply(ref, np.array([[512.0, 384.0]]))[0] + (1.5, 1.0)
    cfg = get_preset("default")
    coarse = coarse_register(
        query, xdop, 0.0, (512.0, 384.0, *seed_b), cfg.coarse, match_in=cfg.match_in, rng=0
    )
    assert coarse, coarse.reason
    fine = fine_register_reference(query, xdop, 0.0, coarse, cfg.fine, match_in=cfg.match_in)
    assert fine, fine.reason
    err = np.hypot(*(fine.base_from_corrected.apply(grid) - _apply(ref, grid)).T)
    assert np.median(err) < 2.0, f"median {np.median(err):.2f} px"
    # Measured with OpenCV 4.14 (the pinned build): median 1.47 px, mean 2.01 px; 1.68 and
    # 2.92 px before the click's heading and scale were also estimated by image correlation
    # (too few SIFT matches vote here: HeadingConfig.patch_below_votes) (5.0's SIFT
    # gives 1.27 and 2.19 on the same CPU; README, "Known limits").
    assert err.mean() < 2.01 * 1.3, f"mean {err.mean():.2f} px (measured 2.01)"
    # Without a click: the coarse step lands at 3.08 px mean; the fine step kept a similarity
    # 40.1 px off while its projective candidate, fitted from the polyprojective's projective
    # part, folded. Measured now: the projective, median 1.39 px, mean 1.93 px.
    coarse = coarse_register(query, xdop, 0.0, None, cfg.coarse, match_in=cfg.match_in, rng=0)
    assert coarse, coarse.reason
    fine = fine_register_reference(query, xdop, 0.0, coarse, cfg.fine, match_in=cfg.match_in)
    assert fine and fine.model_kind == "projective", fine.model_reason
    err = np.hypot(*(fine.base_from_corrected.apply(grid) - _apply(ref, grid)).T)
    assert np.median(err) < 2.0 and err.mean() < 1.93 * 1.3, (np.median(err), err.mean())


def test_ortholoc_reference_field_is_kept_only_where_left_out_points_confirm_it():
    """The reference frame's own field from its control points to the map (default preset,
    ``LocalConfig.support_folds``). Against the orthophoto of another date its template matches
    disagree among themselves (2.4 px from the global model at the median); the spline fitted to
    all of them took the photo from 1.12 to 2.75 px mean off the reference registration, and
    scaled by the 0.67 of it that the points left out of each of 5 folds confirm (measured), to
    2.02 px. It is kept only at the nodes whose own cell's left-out points confirm them (2 of
    108), zero vectors elsewhere on its lattice: 1.13 px, the global stage's 1.12. Against the
    same-date orthophoto they confirm all of it (measured 1.00) and it is kept as fitted: 1.00
    -> 0.93 px."""
    from registration.geometry import local_frame_to_base
    from registration.lens import Camera
    from registration.local import reference_field
    from registration.run.anchoring import footprint
    from registration.run.pipeline import _at_base_resolution

    k, pose, query, dop, xdop = _ortholoc()
    ref = _ortholoc_reference(k, pose, query, dop)
    gx, gy = np.meshgrid(np.linspace(0, 1023, 33), np.linspace(0, 767, 25))
    grid = np.c_[gx.ravel(), gy.ravel()]
    cfg = get_preset("default")
    camera = Camera(0.0, 1024, 768)
    errors = {}
    for name, base in (("other date", xdop), ("same date", dop)):
        seed_b = _apply(ref, np.array([[512.0, 384.0]]))[0] + (1.5, 1.0)
        coarse = coarse_register(
            query, base, 0.0, (512.0, 384.0, *seed_b), cfg.coarse, match_in=cfg.match_in, rng=0
        )
        fine = fine_register_reference(query, base, 0.0, coarse, cfg.fine, match_in=cfg.match_in)
        model = fine.base_from_corrected
        local_cfg = _at_base_resolution(cfg, camera, model).reference_local
        outline = footprint(camera, model)
        size = base.shape[1::-1]
        field, stats = reference_field(fine, size, local_cfg, outline)
        whole, _ = reference_field(
            fine, size, dataclasses.replace(local_cfg, support_folds=0), outline
        )

        def mean_error(f, model=model):
            return float(
                np.mean(
                    np.hypot(*(local_frame_to_base(model.apply, f, grid) - _apply(ref, grid)).T)
                )
            )

        errors[name] = (stats.support_scale, mean_error(field), mean_error(whole))
        if name == "other date":
            # measured: 2 of its 108 nodes confirmed by their own cell's points
            assert stats.support_nodes <= 0.05, stats.support_nodes
            assert np.count_nonzero(np.abs(field.vectors).sum(axis=-1)) <= 0.05 * field.valid.size
            global_error = float(np.mean(np.hypot(*(model.apply(grid) - _apply(ref, grid)).T)))
    support, dropped, whole = errors["other date"]
    # measured 0.67, 1.126 px (the global stage 1.120, the whole field 2.75)
    assert support < 0.8 and dropped < 1.03 * global_error < 0.6 * whole, (errors, global_error)
    support, kept, whole = errors["same date"]
    assert support >= 0.8 and kept == whole, errors  # measured 1.00: 0.93 px either way
