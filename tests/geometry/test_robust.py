"""Tests for registration.geometry.ransac_fit: RANSAC and REQCON with outliers injected at named indices."""

from __future__ import annotations

import math

import numpy as np
import pytest

from registration.geometry import (
    FitResult,
    Normalisation,
    PolyProjective,
    Projective,
    RansacConfig,
    ReqconConfig,
    adaptive_max_iterations,
    ransac,
    reqcon,
)

W, H = 1280, 960
H_TRUE = np.array([[1.16, -0.20, 420.0], [0.20, 1.16, 150.0], [3e-5, -2e-5, 1.0]])
CORNERS = np.array([[0, 0], [W - 1, 0], [W - 1, H - 1], [0, H - 1]], dtype=float)


def true_projective() -> Projective:
    return Projective.from_matrix(H_TRUE)


def true_poly() -> PolyProjective:
    proj = true_projective()
    base = PolyProjective.from_projective(
        proj, 2, Normalisation.for_extent(W, H), Normalisation.from_points(proj.apply(CORNERS))
    )
    p = base.params.copy()
    p[0] += 0.004
    p[1] -= 0.003
    p[8] += 0.005
    p[12] += 0.002
    return base.with_params(p)


def grid(step: int = 32) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(0, W, step, dtype=float), np.arange(0, H, step, dtype=float))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def corrupt(dst, idx, rng, lo, hi):
    """Move dst[idx] by lo..hi px in a random direction."""
    out = dst.copy()
    angle = rng.uniform(0, 2 * np.pi, len(idx))
    length = rng.uniform(lo, hi, len(idx))
    out[idx] += np.stack([np.cos(angle), np.sin(angle)], axis=1) * length[:, None]
    return out


# ---------------------------------------------------------------- adaptive trial count


def test_adaptive_max_iterations_known_values():
    # log(0.01) / log(1 - 0.5**4) = 71.4 -> 72
    assert adaptive_max_iterations(0.5, 4, 0.99) == 72
    assert adaptive_max_iterations(0.1, 4, 0.999) == math.ceil(math.log(0.001) / math.log(1 - 1e-4))
    assert adaptive_max_iterations(1.0, 4, 0.999) == 0
    assert adaptive_max_iterations(0.0, 4, 0.999) == math.inf
    assert adaptive_max_iterations(0.5, 4, 0.0) == 0
    ks = [adaptive_max_iterations(w, 4, 0.999) for w in (0.2, 0.4, 0.6, 0.8)]
    assert ks == sorted(ks, reverse=True)
    with pytest.raises(ValueError, match="inlier_ratio"):
        adaptive_max_iterations(1.5, 4, 0.99)


# ---------------------------------------------------------------- RANSAC


@pytest.fixture
def ransac_data():
    rng = np.random.default_rng(2024)
    src = rng.uniform([0, 0], [W - 1, H - 1], (120, 2))
    dst = true_projective().apply(src) + rng.normal(0, 0.5, src.shape)
    outliers = np.array([2, 11, 12, 30, 47, 48, 49, 63, 77, 90, 101, 115])
    dst = corrupt(dst, outliers, rng, 20.0, 300.0)
    return src, dst, outliers


@pytest.mark.parametrize("refine", ["nelder-mead", "lm", "lstsq", "none"])
def test_ransac_finds_exactly_the_named_outliers(ransac_data, refine):
    src, dst, outliers = ransac_data
    res = ransac(src, dst, Projective, RansacConfig(refine=refine), rng=5)
    assert res and res.success and res.reason == ""
    assert np.array_equal(np.flatnonzero(~res.inliers), outliers)
    assert res.residuals.shape == (len(src),)
    assert np.all(res.residuals[outliers] > 5.0)
    g = grid()
    err = np.abs(res.model.apply(g) - true_projective().apply(g)).max()
    # The refit model is close to the truth; a 4-point sample's model less so.
    assert err < (0.5 if refine != "none" else 10.0)
    # Adaptive stopping: 90 % inliers need far fewer than 1000 samples.
    assert res.iterations < 50


def test_ransac_is_reproducible_with_seed(ransac_data):
    src, dst, _ = ransac_data
    cfg = RansacConfig(refine="lm", confidence=1.0, max_iterations=30)
    a = ransac(src, dst, Projective, cfg, rng=11)
    b = ransac(src, dst, Projective, cfg, rng=np.random.default_rng(11))
    assert a.iterations == b.iterations == 30
    assert np.array_equal(a.model.params, b.model.params)
    assert np.array_equal(a.inliers, b.inliers)


def test_ransac_90_percent_outliers_fails_with_reason():
    rng = np.random.default_rng(3)
    src = rng.uniform([0, 0], [W - 1, H - 1], (300, 2))
    dst = true_projective().apply(src)
    bad = rng.permutation(300)[:270]
    dst[bad] = rng.uniform([0, 0], [1800, 1500], (270, 2))
    res = ransac(src, dst, Projective, RansacConfig(refine="lm"), rng=4)
    assert not res and isinstance(res, FitResult)
    assert res.reason.startswith("no consensus")
    assert res.iterations == 1000


def test_ransac_skips_degenerate_samples():
    # Half the points lie on one line: many samples are degenerate, the rest must still win.
    rng = np.random.default_rng(8)
    line = np.stack([np.linspace(10, 1200, 40), np.linspace(30, 900, 40)], axis=1)
    src = np.vstack([line, rng.uniform([0, 0], [W - 1, H - 1], (40, 2))])
    dst = true_projective().apply(src)
    res = ransac(src, dst, Projective, RansacConfig(refine="lm"), rng=1)
    assert res and res.inliers.all()
    all_line = ransac(line, true_projective().apply(line), Projective, RansacConfig(), rng=1)
    assert not all_line and "degenerate" in all_line.reason


def test_ransac_input_checks():
    pts = np.zeros((10, 2))
    with pytest.raises(ValueError, match="min_samples"):
        ransac(pts, pts, PolyProjective, RansacConfig(sample_size=4))
    with pytest.raises(ValueError, match="refine"):
        RansacConfig(refine="bfgs")
    res = ransac(pts[:3], pts[:3], Projective, RansacConfig())
    assert not res and "needs at least" in res.reason


def test_ransac_polyprojective_samples():
    rng = np.random.default_rng(9)
    truth = true_poly()
    src = rng.uniform([0, 0], [W - 1, H - 1], (150, 2))
    dst = truth.apply(src) + rng.normal(0, 0.3, src.shape)
    outliers = np.arange(0, 150, 10)
    dst = corrupt(dst, outliers, rng, 30.0, 200.0)
    cfg = RansacConfig(sample_size=PolyProjective.min_samples, threshold_px=3.0, refine="lm")
    res = ransac(src, dst, PolyProjective, cfg, rng=2)
    assert res and np.array_equal(np.flatnonzero(~res.inliers), outliers)


# ---------------------------------------------------------------- REQCON


def reqcon_data(n: int, seed: int):
    rng = np.random.default_rng(seed)
    truth = true_poly()
    src = rng.uniform([0, 0], [W - 1, H - 1], (n, 2))
    dst = truth.apply(src) + rng.normal(0, 0.5, src.shape)
    outliers = np.arange(3, n, 5)  # 20 %
    dst = corrupt(dst, outliers, rng, 100.0, 300.0)
    start = PolyProjective.from_projective(true_projective(), 2, truth.src_norm, truth.dst_norm)
    return truth, src, dst, outliers, start


def test_reqcon_removes_named_gross_outliers_lm():
    truth, src, dst, outliers, start = reqcon_data(400, 21)
    res = reqcon(src, dst, start, ReqconConfig(optimizer="lm"))
    assert res and res.reason == ""
    assert not res.inliers[outliers].any()
    assert res.history[-1] < 2.0 and all(h >= 2.0 for h in res.history[:-1])
    assert res.iterations == len(res.history)
    # The drops follow the paper's 5 % schedule: n_kept after k rounds.
    n_kept = 400
    for _ in range(res.iterations - 1):
        n_kept -= max(1, math.ceil(0.05 * n_kept))
    assert res.n_inliers == n_kept
    g = grid()
    assert np.mean(np.linalg.norm(res.model.apply(g) - truth.apply(g), axis=1)) < 0.3
    assert np.allclose(res.residuals, res.model.residuals(src, dst))


def test_reqcon_nelder_mead_matches_lm():
    truth, src, dst, outliers, start = reqcon_data(100, 5)
    lm = reqcon(src, dst, start, ReqconConfig(optimizer="lm"))
    nm = reqcon(src, dst, start, ReqconConfig(optimizer="nelder-mead"))
    assert lm and nm
    assert not nm.inliers[outliers].any() and not lm.inliers[outliers].any()
    # Rounds that still hold gross outliers have several near-equal minima, so the two
    # optimisers may drop a different clean point or two; the end results must agree.
    assert nm.iterations == lm.iterations and nm.n_inliers == lm.n_inliers
    assert np.sum(nm.inliers & lm.inliers) >= 0.95 * lm.n_inliers
    assert abs(nm.history[-1] - lm.history[-1]) <= 0.05 * lm.history[-1]
    g = grid()
    for res in (lm, nm):
        assert np.mean(np.linalg.norm(res.model.apply(g) - truth.apply(g), axis=1)) < 0.5


def test_reqcon_stops_at_once_on_clean_data():
    _, src, _, _, start = reqcon_data(100, 6)
    dst = true_poly().apply(src)
    res = reqcon(src, dst, start, ReqconConfig(optimizer="lm"))
    assert res and res.iterations == 1 and res.inliers.all() and res.history[0] < 1e-6


def test_reqcon_guard_against_collapse():
    rng = np.random.default_rng(12)
    src = rng.uniform([0, 0], [W - 1, H - 1], (200, 2))
    dst = rng.uniform([0, 0], [W - 1, H - 1], (200, 2))  # no model explains these
    start = PolyProjective.identity(2, Normalisation.for_extent(W, H))
    res = reqcon(src, dst, start, ReqconConfig(optimizer="lstsq", min_points=60))
    assert not res and "guard of 60 points" in res.reason
    assert res.n_inliers >= 60
    assert res.model is not None and res.residuals.shape == (200,)
    default_guard = reqcon(src, dst, start, ReqconConfig(optimizer="lstsq"))
    # Default guard: max(3 * 9 min_samples, 10 % of 200) = 27.
    assert not default_guard and "guard of 27 points" in default_guard.reason
    assert default_guard.n_inliers >= 27


def test_reqcon_too_few_points_and_bad_config():
    start = PolyProjective.identity(2)
    pts = np.random.default_rng(0).uniform(0, 100, (20, 2))
    res = reqcon(pts, pts, start, ReqconConfig())
    assert not res and "needs at least 27" in res.reason
    with pytest.raises(ValueError, match="drop_fraction"):
        ReqconConfig(drop_fraction=0.0)
    with pytest.raises(ValueError, match="optimizer"):
        ReqconConfig(optimizer="bfgs")


def test_reqcon_with_projective_model():
    rng = np.random.default_rng(4)
    src = rng.uniform([0, 0], [W - 1, H - 1], (100, 2))
    dst = true_projective().apply(src) + rng.normal(0, 0.5, src.shape)
    outliers = np.array([0, 5, 50, 99])
    dst = corrupt(dst, outliers, rng, 200.0, 400.0)
    start = Projective.from_matrix(np.eye(3) + [[0, 0, 400], [0, 0, 160], [0, 0, 0]])
    res = reqcon(src, dst, start, ReqconConfig(optimizer="lm"))
    assert res and not res.inliers[outliers].any()


def _mismatch_data(rng, n=600, n_out=60):
    """Points from a smooth non-polyprojective warp (a radial term the model cannot represent,
    up to ~1.5 px at the corners) plus 1 px noise, with gross outliers at named indices."""
    src = rng.uniform([0, 0], [W - 1, H - 1], (n, 2))
    c = np.array([W / 2, H / 2])
    rho2 = (((src - c) / np.hypot(W, H) * 2) ** 2).sum(axis=1)
    warped = src + 1.5 * (rho2**2)[:, None] * (src - c) / np.hypot(W, H) * 2
    dst = true_poly().apply(warped) + rng.normal(0, 0.5, (n, 2))
    outliers = np.sort(rng.choice(n, n_out, replace=False))
    dst[outliers] += rng.uniform(8, 40, (n_out, 2)) * rng.choice([-1, 1], (n_out, 2))
    return src, dst, outliers


def test_reqcon_outlier_stop_keeps_good_points_under_model_mismatch(rng):
    src, dst, outliers = _mismatch_data(rng)
    good = np.setdiff1d(np.arange(len(src)), outliers)
    start = PolyProjective.from_projective(true_projective(), 2)
    robust = reqcon(
        src, dst, start, ReqconConfig(optimizer="lm", target_mean_error_px=0.5, stop="outliers")
    )
    assert robust and robust.success
    assert not robust.inliers[outliers].any()
    assert robust.inliers[good].mean() >= 0.9
    assert 0.3 < robust.sigma_px < 2.0
    # The paper's absolute stop on the same points drops good points until the guard fails it.
    paper = reqcon(src, dst, start, ReqconConfig(optimizer="lm", target_mean_error_px=0.5))
    assert not paper or paper.inliers[good].mean() < 0.9


def test_reqcon_noise_scale_keeps_the_less_precise_points(rng):
    # The outer ring's points (a frame's corners after a strong radial correction) are measured
    # with 4x the error of the centre's; gross outliers sit at named indices in both. Judged
    # against the centre's spread, the "outliers" rule drops much of the ring; told each point's
    # relative noise, it keeps the ring and still removes every outlier.
    n = 800
    src = rng.uniform([0, 0], [W - 1, H - 1], (n, 2))
    rho = np.hypot(*((src - [W / 2, H / 2]) / (np.hypot(W, H) / 2)).T)
    noise = np.where(rho > 0.75, 4.0, 1.0)
    dst = true_poly().apply(src) + rng.normal(0, 0.15, (n, 2)) * noise[:, None]
    outliers = np.r_[np.flatnonzero(rho > 0.75)[:8], np.flatnonzero(rho < 0.5)[:12]]
    dst[outliers] += rng.uniform(6, 20, (len(outliers), 2)) * rng.choice(
        [-1, 1], (len(outliers), 2)
    )
    ring = np.setdiff1d(np.flatnonzero(rho > 0.75), outliers)
    start = PolyProjective.from_projective(true_projective(), 2)
    cfg = ReqconConfig(optimizer="lm", target_mean_error_px=0.05, stop="outliers")
    plain = reqcon(src, dst, start, cfg)
    scaled = reqcon(src, dst, start, cfg, noise_scale=noise)
    assert plain and scaled
    assert not scaled.inliers[outliers].any()
    assert scaled.inliers[ring].mean() >= 0.95, scaled.inliers[ring].mean()
    assert plain.inliers[ring].mean() < 0.8, plain.inliers[ring].mean()
    # The robust scale is that of a typical (median-noise) point.
    assert 0.1 < scaled.sigma_px < 0.25, scaled.sigma_px
    with pytest.raises(ValueError, match="noise_scale"):
        reqcon(src, dst, start, cfg, noise_scale=np.zeros(n))


def test_reqcon_noise_scale_is_that_of_the_points_it_keeps(rng):
    """100 named outliers only 3.5 px off, among 500 points with 0.5 px noise per axis: the
    "outliers" rule removes every one and reports the kept points' noise (0.5 px). Taken over
    the dropped points too, the scale would grow by a fifth and let outliers stay."""
    n = 600
    src = rng.uniform([0, 0], [W - 1, H - 1], (n, 2))
    dst = true_poly().apply(src) + rng.normal(0, 0.5, (n, 2))
    outliers = np.arange(3, n, 6)
    angle = rng.uniform(0, 2 * np.pi, len(outliers))
    dst[outliers] += 3.5 * np.c_[np.cos(angle), np.sin(angle)]
    good = np.setdiff1d(np.arange(n), outliers)
    start = PolyProjective.from_projective(true_projective(), 2)
    res = reqcon(
        src, dst, start, ReqconConfig(optimizer="lm", target_mean_error_px=0.05, stop="outliers")
    )
    assert res and not res.inliers[outliers].any(), np.flatnonzero(res.inliers[outliers])
    assert res.inliers[good].mean() >= 0.97
    assert abs(res.sigma_px - 0.5) < 0.05, res.sigma_px
