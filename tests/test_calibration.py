"""Straightness, γ estimation (from lines and automatic) and LINES.json, against known truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from registration.calibration import (
    estimate_gamma_auto,
    estimate_gamma_from_lines,
    fit_division_from_lines,
    fit_polynomial_from_lines,
    lines_to_json,
    load_lines,
    parse_lines,
    save_lines,
    straight_edge_chart,
    straightness,
)
from registration.distortion import DivisionModel, HarrisModel, PolynomialModel, simulate_raw_frame
from tests.conftest import shared_data

W, H = 800, 600


def world_lines(w=W, h=H, n_per_line=60):
    """Straight lines (corrected coordinates) spread over the frame, several near the border."""
    specs = [
        ((0.05, 0.08), (0.95, 0.12)),
        ((0.1, 0.9), (0.9, 0.93)),
        ((0.06, 0.1), (0.1, 0.9)),
        ((0.92, 0.05), (0.95, 0.95)),
        ((0.2, 0.3), (0.8, 0.35)),
        ((0.15, 0.7), (0.7, 0.2)),
        ((0.3, 0.05), (0.35, 0.95)),
    ]
    t = np.linspace(0, 1, n_per_line)[:, None]
    return [(np.array(a) + t * (np.array(b) - np.array(a))) * [w - 1, h - 1] for a, b in specs]


def raw_lines(model, noise_px=0.0, rng=None):
    out = [model.raw_from_corrected(p) for p in world_lines(model.width, model.height)]
    if noise_px:
        out = [p + rng.normal(0, noise_px, p.shape) for p in out]
    return out


# ------------------------------------------------------------------------------------------
# straightness


def test_straightness_known_value():
    # TLS fit of (-1, 0), (0, h), (1, 0): the line y = h/3; distances 2h/3, h/3... -> scatter
    # eigenvalue min(2, 2h²/3) -> RMS = sqrt(2h²/9) for small h.
    h = 0.3
    s = straightness([np.array([[-1, 0], [0, h], [1, 0]]) + 100], HarrisModel(0.0, W, H))
    np.testing.assert_allclose(s.per_line, [np.sqrt(2 * h**2 / 9)], rtol=1e-12)
    assert s.n_points.tolist() == [3]


def test_straightness_is_zero_for_the_right_model_only():
    model = HarrisModel(0.7, W, H)
    lines = raw_lines(model)
    good = straightness(lines, model)
    assert good.overall < 1e-9 and np.all(good.per_line < 1e-9)
    bad = straightness(lines, HarrisModel(0.0, W, H))
    assert bad.overall > 2.0
    # Overall = RMS over all points: pooled from the per-line values.
    pooled = np.sqrt(np.sum(bad.per_line**2 * bad.n_points) / bad.n_points.sum())
    assert bad.overall == pytest.approx(pooled)


def test_straightness_rejects_short_lines_naming_them():
    lines = [np.zeros((5, 2)) + [[i, 0] for i in range(5)], np.array([[0.0, 0.0], [1.0, 1.0]])]
    with pytest.raises(ValueError, match="line 1 has 2 points; each line needs at least 3"):
        straightness(lines, HarrisModel(0.1, W, H))
    with pytest.raises(ValueError, match="no lines"):
        straightness([], HarrisModel(0.1, W, H))


# ------------------------------------------------------------------------------------------
# γ from lines


@pytest.mark.parametrize("gamma", [-0.3, 0.0, 0.3, 0.7, 1.0])
def test_gamma_from_exact_lines(gamma):
    est = estimate_gamma_from_lines(raw_lines(HarrisModel(gamma, W, H)), W, H, n_bootstrap=20)
    assert est.gamma == pytest.approx(gamma, abs=1e-4)
    assert est.residual < 1e-3
    # The plotted curve has its minimum at the estimate.
    assert (
        abs(est.gamma_grid[np.argmin(est.residual_curve)] - gamma)
        <= 2 * np.diff(est.gamma_grid).max()
    )
    assert est.gamma_grid.shape == est.residual_curve.shape
    assert est.n_lines == 7 and est.method == "lines"


def test_gamma_from_noisy_lines_with_honest_uncertainty(rng):
    gamma = 0.7
    est = estimate_gamma_from_lines(raw_lines(HarrisModel(gamma, W, H), 0.3, rng), W, H)
    assert abs(est.gamma - gamma) < 0.02
    assert est.uncertainty_method == "bootstrap"
    assert 0 < est.uncertainty < 0.02
    assert abs(est.gamma - gamma) < 4 * est.uncertainty
    assert est.residual == pytest.approx(0.3, rel=0.3)  # noise level, in corrected px ~ raw px
    assert est.residual_uncorrected > 3 * est.residual


def test_gamma_from_two_lines_uses_curvature_uncertainty():
    lines = raw_lines(HarrisModel(0.5, W, H))[:2]
    lines = [p + 0.05 * np.sin(np.arange(len(p)))[:, None] for p in lines]
    est = estimate_gamma_from_lines(lines, W, H)
    assert est.uncertainty_method == "curvature"
    assert np.isfinite(est.uncertainty) and est.uncertainty < 0.05
    assert est.gamma == pytest.approx(0.5, abs=0.02)


def test_robust_fit_rejects_a_curved_world_edge():
    model = HarrisModel(0.6, W, H)
    lines = raw_lines(model)
    # Index 7: an arc of a circle in the world (a roundabout kerb) near the border.
    t = np.linspace(-0.6, 0.6, 80)
    arc = np.column_stack([400 + 330 * np.sin(t), 300 + 330 * np.cos(t) - 40])
    lines.append(model.raw_from_corrected(arc))
    plain = estimate_gamma_from_lines(lines, W, H, n_bootstrap=0)
    robust = estimate_gamma_from_lines(lines, W, H, n_bootstrap=0, inlier_px=0.5)
    assert abs(plain.gamma - 0.6) > 0.05  # the arc spoils the plain fit
    assert robust.gamma == pytest.approx(0.6, abs=1e-3)
    assert robust.n_rejected == 1 and robust.n_lines == 7
    assert all(p is not lines[7] for p in robust.lines_used)


def test_gamma_range_is_respected_and_validated():
    lines = raw_lines(HarrisModel(0.7, W, H))
    est = estimate_gamma_from_lines(lines, W, H, gamma_range=(-0.5, 0.4), n_bootstrap=0)
    assert est.gamma == pytest.approx(0.4, abs=1e-3)
    with pytest.raises(ValueError, match="out of range for a 800x600 frame"):
        estimate_gamma_from_lines(lines, W, H, gamma_range=(1.5, 2.0))


def test_polynomial_fit_recovers_polynomial_distortion():
    truth = PolynomialModel(-0.12, 0.02, 0.0, W, H)
    lines = raw_lines(truth)
    model, s = fit_polynomial_from_lines(lines, W, H, n_coeffs=2)
    assert s.overall < 1e-3
    assert model.k1 == pytest.approx(-0.12, abs=2e-3) and model.k2 == pytest.approx(0.02, abs=3e-3)
    # The one-parameter Harris model cannot straighten these lines as well.
    harris = estimate_gamma_from_lines(lines, W, H, n_bootstrap=0)
    assert harris.residual > 10 * s.overall


def test_division_fit_recovers_division_distortion():
    lines = raw_lines(DivisionModel(-0.4, W, H))
    model, s = fit_division_from_lines(lines, W, H)
    assert model.lam == pytest.approx(-0.4, abs=1e-5) and s.overall < 1e-4


# ------------------------------------------------------------------------------------------
# automatic γ


@pytest.mark.parametrize("gamma", [0.3, 0.7, 1.0])
def test_auto_gamma_on_generated_chart(gamma):
    chart = straight_edge_chart(1400, 1050, seed=0)
    raw, _ = simulate_raw_frame(chart, HarrisModel(gamma, 640, 480))
    est = estimate_gamma_auto(raw, n_bootstrap=50)
    assert abs(est.gamma - gamma) < 0.02
    assert est.method == "auto" and est.n_lines >= 10
    assert est.uncertainty < 0.02


REAL = [
    # (folder, file, raw frame size): nadir views with long straight roads / roof edges.
    ("ortholoc-uav-vs-orthophoto/web_samples", "L34_0128_xdop.jpg", (800, 600)),
    ("songdo-vision-drone/images", "03936.jpg", (960, 540)),
]


@pytest.mark.parametrize("folder,name,size", REAL, ids=[r[1] for r in REAL])
def test_auto_gamma_on_real_images(folder, name, size):
    path = shared_data(*folder.split("/"), name)
    scene = cv2.imread(str(path), cv2.IMREAD_COLOR)
    for gamma in (0.3, 0.7, 1.0):
        raw, _ = simulate_raw_frame(scene, HarrisModel(gamma, *size))
        est = estimate_gamma_auto(raw, n_bootstrap=50)
        assert abs(est.gamma - gamma) < 0.02, (name, gamma, est.gamma)


def test_auto_gamma_needs_edges():
    flat = np.full((300, 400), 128, np.uint8)
    with pytest.raises(ValueError, match="found 0 long"):
        estimate_gamma_auto(flat)


def test_auto_accepts_colour_and_16_bit():
    chart = straight_edge_chart(1000, 750, seed=1)
    raw, _ = simulate_raw_frame(chart, HarrisModel(0.5, 480, 360))
    ref = estimate_gamma_auto(raw, n_bootstrap=0).gamma
    colour = estimate_gamma_auto(cv2.cvtColor(raw, cv2.COLOR_GRAY2BGR), n_bootstrap=0).gamma
    deep = estimate_gamma_auto(raw.astype(np.uint16) * 257, n_bootstrap=0).gamma
    assert colour == pytest.approx(ref, abs=1e-6)
    assert deep == pytest.approx(ref, abs=5e-3)  # stretched to 8 bit: slightly other edges


# ------------------------------------------------------------------------------------------
# LINES.json


def test_lines_json_round_trip(tmp_path):
    lines = raw_lines(HarrisModel(0.4, W, H))
    path = tmp_path / "LINES.json"
    save_lines(path, lines, (W, H))
    loaded = load_lines(path)
    assert loaded.image_size == (W, H)
    assert len(loaded.lines) == len(lines)
    for a, b in zip(loaded.lines, lines, strict=True):
        np.testing.assert_array_equal(a, b)
    assert json.loads(path.read_text())["version"] == 1


GOOD = {"version": 1, "image_size": [100, 80], "lines": [[[1, 1], [50, 2], [99, 3.5]]]}


@pytest.mark.parametrize(
    "change,message",
    [
        ({"version": 2}, "version must be 1, got 2"),
        ({"image_size": [100]}, "image_size must be [width, height]"),
        ({"image_size": [100, True]}, "image_size must be [width, height]"),
        ({"lines": []}, "lines must be a non-empty list"),
        ({"lines": [[[1, 1], [2, 2]]]}, "lines[0] has 2 points; each line needs at least 3"),
        ({"lines": [[[1, 1], [2, 2], [3, "x"]]]}, "lines[0][2] must be an [x, y] pair"),
        ({"lines": [[[1, 1], [2, 2], [300, 3]]]}, "lines[0][2] = [300, 3] lies outside"),
        ({"extra": 1}, "unknown key 'extra'"),
    ],
)
def test_lines_json_validation(change, message):
    obj = {**GOOD, **change}
    with pytest.raises(ValueError) as exc:
        parse_lines(obj, "L.json")
    assert message in str(exc.value) and str(exc.value).startswith("L.json: ")
    assert "\n" not in str(exc.value)


def test_lines_json_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="lines file not found"):
        load_lines(tmp_path / "nope.json")
    empty = tmp_path / "empty.json"
    empty.write_text("")
    with pytest.raises(ValueError, match="file is empty"):
        load_lines(empty)
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_lines(broken)
    missing = tmp_path / "missing.json"
    missing.write_text(json.dumps({"version": 1, "lines": GOOD["lines"]}))
    with pytest.raises(ValueError, match="missing key 'image_size'"):
        load_lines(missing)
    assert lines_to_json(GOOD["lines"], (100, 80)) == {
        **GOOD,
        "lines": [[[1.0, 1.0], [50.0, 2.0], [99.0, 3.5]]],
    }
