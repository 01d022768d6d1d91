"""The lens beyond Harris (registration.lens.k2): estimated from control points of known
geometry, and used by the pipeline on a simulated flight whose lens is not Harris."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from registration.evaluation import evaluate_truth
from registration.io import open_frames, read_image
from registration.lens import Camera, HarrisModel, LensConfig, TwoTermHarrisModel, estimate_k2
from registration.run import get_preset, register_sequence
from registration.synth import PROFILES, load_truth, simulate

W, H = 640, 480
OUTLIERS = [5, 50, 123, 200]


def _points(k2: float, seed: int = 0):
    """Raw grid points and where a camera with ``k2``, a rolling shutter's row-dependent shift
    and a homography put them in a base map, with 0.3 px noise and 15-40 px mismatches at
    ``OUTLIERS``."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(16.0, W - 16, 24), np.arange(16.0, H - 16, 24))
    raw = np.c_[gx.ravel(), gy.ravel()]
    corrected = TwoTermHarrisModel(0.7, k2, W, H).corrected_from_raw(raw)
    rows = (raw[:, 1] - (H - 1) / 2) / H
    corrected = corrected + np.c_[3.0 * rows + 1.5 * rows**2, -2.0 * rows]
    a = np.radians(20.0)
    homography = np.array(
        [[1.3 * np.cos(a), -1.3 * np.sin(a), 900.0], [1.3 * np.sin(a), 1.3 * np.cos(a), 400.0],
         [2e-5, -1e-5, 1.0]]
    )  # fmt: skip
    q = np.c_[corrected, np.ones(len(raw))] @ homography.T
    base = q[:, :2] / q[:, 2:] + rng.normal(0.0, 0.3, (len(raw), 2))
    angle = rng.uniform(0, 2 * np.pi, len(OUTLIERS))
    base[OUTLIERS] += rng.uniform(15, 40, (len(OUTLIERS), 1)) * np.c_[np.cos(angle), np.sin(angle)]
    return raw, base


def test_a_known_lens_beyond_harris_is_recovered_despite_mismatches():
    raw, base = _points(0.04)
    est = estimate_k2(raw, base, Camera(0.7, W, H), LensConfig(estimate_k2=True))
    assert est.adopted, est.reason
    assert est.k2 == pytest.approx(0.04, abs=0.002), est.reason
    assert est.rms_px < est.rms_harris_px
    assert est.to_dict()["k2"] == est.k2


def test_an_exact_harris_lens_keeps_harris():
    raw, base = _points(0.0)
    est = estimate_k2(raw, base, Camera(0.7, W, H), LensConfig(estimate_k2=True))
    assert not est.adopted and "below 0.02" in est.reason, est.reason
    assert abs(est.k2) < 0.002
    # A small fourth-order term cannot be told from relief displacement in one frame.
    raw, base = _points(0.012)
    small = estimate_k2(raw, base, Camera(0.7, W, H), LensConfig(estimate_k2=True))
    assert small.k2 == pytest.approx(0.012, abs=0.002) and not small.adopted
    assert "below 0.02, where relief displacement looks alike, Harris kept" in small.reason


def test_too_few_points_or_an_implausible_value_are_refused():
    raw, base = _points(0.04)
    few = estimate_k2(raw[:30], base[:30], Camera(0.7, W, H), LensConfig(estimate_k2=True))
    assert not few.adopted and few.reason == "k2 not estimated: 30 control points (needs 50)"
    assert few.to_dict()["k2"] is None  # JSON-able: NaN is written as null
    capped = estimate_k2(raw, base, Camera(0.7, W, H), LensConfig(max_abs_k2=0.03))
    assert not capped.adopted and "beyond ±0.03, not used" in capped.reason
    with pytest.raises(
        ValueError, match=r"min_abs_k2 must be in \[0, max_abs_k2 = 0.01\), got 0.02"
    ):
        LensConfig(max_abs_k2=0.01)
    # Significant, but explaining too little of the residual: what the fit lacks, not the lens.
    strict = estimate_k2(raw, base, Camera(0.7, W, H), LensConfig(min_rms_reduction=0.99))
    assert not strict.adopted and "explains less than 99% of the residual" in strict.reason


def test_the_camera_is_exactly_harris_without_k2():
    camera = Camera(0.7, W, H)
    assert camera.lens == HarrisModel(0.7, W, H)
    lensed = camera.with_k2(0.04)
    assert lensed.lens == TwoTermHarrisModel(0.7, 0.04, W, H) and lensed != camera
    xy = np.array([[0.0, 0.0], [320.0, 240.0], [639.0, 100.0]])
    back = lensed.raw_from_corrected(lensed.corrected_from_raw(xy))
    np.testing.assert_allclose(back, xy, atol=1e-9)
    # At the corner the fourth-order term moves the corrected point by tens of px.
    assert (
        np.hypot(*(lensed.corrected_from_raw(xy[:1]) - camera.corrected_from_raw(xy[:1]))[0]) > 20
    )


@pytest.mark.slow
def test_a_flight_with_a_lens_beyond_harris_registers_with_the_estimate(tmp_path):
    """``paper-hard`` at 640x480, 10 frames (lens γ 0.7 with k2 = 0.04): the reference frame's
    control points give k2 = 0.034 and every frame is registered with it. Measured error after
    local 0.491 base px against 0.802 with Harris alone (global 0.808 and 0.985); the result
    carries the lens (``result.camera``), and a resumed run equals the uninterrupted one."""
    sim = tmp_path / "sim"
    simulate(sim, PROFILES["paper-hard"](frame_size=(W, H), n_frames=10, video=False))
    truth = load_truth(sim)
    c = np.array([[W / 2, H / 2]])
    seed = (*c[0], *truth.frame_to_base(0, c)[0])
    default = get_preset("default")
    results, error = {}, {}
    for name, config in (
        ("k2", default),
        ("harris", dataclasses.replace(default, lens=LensConfig())),
    ):
        result = register_sequence(
            open_frames(sim / "frames"), read_image(sim / "base.png"), truth.gamma,
            tmp_path / name, config=config, seed=seed,
        )  # fmt: skip
        assert all(r.status == "ok" for r in result.records)
        results[name] = result
        error[name] = evaluate_truth(result, truth).summary["local"]["mean"]
    lensed = results["k2"]
    assert lensed.records[0].lens_k2 == lensed.camera.k2
    assert 0.025 < lensed.camera.k2 < 0.045, lensed.records[0].stats["lens"]  # 0.0339
    assert results["harris"].camera.k2 == 0.0 and "lens" not in results["harris"].records[0].stats
    assert error["k2"] < 0.9 * error["harris"], error  # measured 0.491 vs 0.802
    # Beyond Harris the reference frame's own field bends more freely, where the fourth-order
    # term's estimate is least sure (the corners): its error against the truth, the same
    # control points fitted with each lens's settings, measured 0.450 against 0.560 base px.
    reference = {
        name: _reference_field_error(lensed, truth, camera)
        for name, camera in (("beyond", lensed.camera), ("harris", lensed.camera.with_k2(0.0)))
    }
    assert reference["beyond"] < 0.9 * reference["harris"], reference
    # Resuming with frames 5-9 missing: the camera comes back from the reference record.
    out = tmp_path / "resumed"
    shutil.copytree(tmp_path / "k2", out)
    for k in range(5, 10):
        for f in out.glob(f"frames/{k:06d}.*"):
            f.unlink()
    resumed = register_sequence(
        open_frames(sim / "frames"), read_image(sim / "base.png"), truth.gamma, out,
        config=default, seed=seed, resume=True,
    )  # fmt: skip
    gx, gy = np.meshgrid(np.linspace(0, W - 1, 9), np.linspace(0, H - 1, 7))
    grid = np.c_[gx.ravel(), gy.ravel()]
    for k in range(10):
        np.testing.assert_array_equal(resumed.frame_to_base(k, grid), lensed.frame_to_base(k, grid))


def _reference_field_error(result, truth, camera) -> float:
    """Mean error against the truth (base px, the evaluation's 8 px ground grid) of the reference
    frame of ``result`` through its own model and a field fitted to its control points with the
    default preset's settings for ``camera``'s lens."""
    from types import SimpleNamespace

    from registration.evaluation.truth import ground_grid
    from registration.geometry.displacement_field import local_frame_to_base
    from registration.local import reference_field
    from registration.run.anchoring import footprint
    from registration.run.pipeline import _at_base_resolution

    k = result.reference_frame
    src, dst = (np.asarray(a) for a in result.control_points(k)[:2])
    model, lens = result.own_model(k), result.camera
    config = _at_base_resolution(get_preset("default"), camera, model).reference_local
    fine = SimpleNamespace(src=src, dst=dst, base_from_corrected=model)
    field, _ = reference_field(fine, result.base_size, config, footprint(lens, model))
    base = ground_grid(truth, k, 8.0)
    raw = truth.base_to_frame(k, base)
    found = local_frame_to_base(lambda q: model.apply(lens.corrected_from_raw(q)), field, raw)
    return float(np.nanmean(np.hypot(*(found - base).T)))
