"""The sequence adjustment against known truth: frames with exact polyprojective models over
one base plane, each frame's own fit to noisy control points (with outliers at named indices)
as the start, and links between frames that see the same ground (one pair with moving-car
outliers). Adjusted together, neighbours agree with each other, the map error does not grow,
outliers do not pull, and a frame without control points is carried by its links."""

from __future__ import annotations

import numpy as np
import pytest

from registration.adjustment import (
    AdjustmentConfig,
    ControlPointSet,
    FrameLinks,
    adjust_models,
)
from registration.geometry import Normalisation, PolyProjective, Projective

W, H = 640, 480
N = 6
CONTROL_SIGMA = 0.3  # base px: a frame's fine-step control points
LINK_SIGMA = 0.03  # frame px: same-sensor patches of neighbouring frames
BAD_CONTROLS = (3, 17, 40, 41, 42, 90)  # frame 2's control points 15 px off
BAD_LINKS = tuple(range(10, 18))  # pair (1, 2): a car moved 5 px


def _truth(k: int) -> PolyProjective:
    """Frame k: the view moved 40 px right a frame, a little turned, with some curvature."""
    a = np.deg2rad(2.0 * k)
    s = 1.1
    m = np.array(
        [
            [s * np.cos(a), -s * np.sin(a), 300 + 40 * k],
            [s * np.sin(a), s * np.cos(a), 200],
            [2e-5, 1e-5, 1],
        ]
    )
    proj = Projective.from_matrix(m)
    corners = np.array([[0, 0], [W, 0], [W, H], [0, H]], float)
    poly = PolyProjective.from_projective(
        proj, 2, Normalisation.for_extent(W, H), Normalisation.from_points(proj.apply(corners))
    )
    p = poly.params.copy()
    p[0] += 0.003 * (1 + 0.2 * k)  # a u² term that differs from frame to frame
    p[8] -= 0.002
    return poly.with_params(p)


def _grid(step: int = 40) -> np.ndarray:
    xs, ys = np.meshgrid(
        np.arange(20, W - 20, step, dtype=float), np.arange(20, H - 20, step, dtype=float)
    )
    return np.c_[xs.ravel(), ys.ravel()]


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(11)
    truth = [_truth(k) for k in range(N)]
    controls, fits = [], []
    for k in range(N):
        src = rng.uniform(10, [W - 10, H - 10], (120, 2))
        dst = truth[k].apply(src) + rng.normal(0, CONTROL_SIGMA, src.shape)
        if k == 2:
            dst[list(BAD_CONTROLS)] += 15.0
        controls.append(ControlPointSet(k, src, dst, CONTROL_SIGMA))
        good = np.ones(len(src), bool)
        if k == 2:
            good[list(BAD_CONTROLS)] = False  # the frame's own REQCON dropped them
        fits.append(PolyProjective.estimate(src[good], dst[good], initial=truth[k], optimizer="lm"))
    links = []
    for step in (1, 2):
        for k in range(N - step):
            lo = k + step
            p = _grid(32)
            b = truth[k].apply(p)
            q = truth[lo].inverse(b)
            inside = (q[:, 0] > 10) & (q[:, 0] < W - 10) & (q[:, 1] > 10) & (q[:, 1] < H - 10)
            p, q = p[inside], q[inside]
            p = p + rng.normal(0, LINK_SIGMA, p.shape)
            q = q + rng.normal(0, LINK_SIGMA, q.shape)
            if (k, lo) == (1, 2):
                q[list(BAD_LINKS)] += (5.0, 0.0)
            links.append(FrameLinks(k, lo, p, q))
    return truth, fits, controls, links


def _pair_error(models, truth, k, lo) -> float:
    """Median disagreement (base px) of frames k and lo on the ground both see."""
    p = _grid(20)
    q = truth[lo].inverse(truth[k].apply(p))
    inside = (q[:, 0] > 0) & (q[:, 0] < W) & (q[:, 1] > 0) & (q[:, 1] < H)
    return float(np.median(np.hypot(*(models[k].apply(p[inside]) - models[lo].apply(q[inside])).T)))


def _map_error(model, truth) -> float:
    p = _grid(20)
    return float(np.mean(np.hypot(*(model.apply(p) - truth.apply(p)).T)))


def test_neighbours_agree_and_the_map_error_does_not_grow(scene):
    truth, fits, controls, links = scene
    res = adjust_models(fits, links, controls, AdjustmentConfig(link_sigma_px=LINK_SIGMA * 1.1))
    assert res.success, res.message
    before = [_pair_error(fits, truth, k, k + 1) for k in range(N - 1)]
    after = [_pair_error(res.models, truth, k, k + 1) for k in range(N - 1)]
    # Measured: the frames' own fits disagree by 0.10-0.22 px, adjusted by 0.005-0.011 (without
    # the links: 0.10-0.22 still).
    assert np.mean(after) < 0.2 * np.mean(before), (np.round(before, 3), np.round(after, 3))
    map_before = [_map_error(fits[k], truth[k]) for k in range(N)]
    map_after = [_map_error(res.models[k], truth[k]) for k in range(N)]
    # Measured: 0.08-0.16 px from the truth before, 0.04-0.05 after. The outliers (frame 2's
    # control points, the moved car's links) do not pull: with a plain quadratic loss every
    # frame ends 0.38-0.50 px off.
    assert all(a < b for a, b in zip(map_after, map_before, strict=True)), (map_before, map_after)
    assert max(map_after) < 0.1, np.round(map_after, 3)
    assert np.all(np.isfinite(res.link_rms_px)) and np.all(np.isfinite(res.control_rms_px))


def test_a_frame_without_control_points_is_carried_by_its_links(scene):
    truth, fits, controls, links = scene
    moved = list(fits)
    # Frame 3 registered 2 px off, with no control points of its own to say so.
    moved[3] = fits[3].with_params(fits[3].params.copy())
    shift = Projective.from_matrix(np.array([[1, 0, 2.0], [0, 1, -1.5], [0, 0, 1]]))
    p = _grid(16)
    moved[3] = PolyProjective.estimate(
        p, shift.apply(fits[3].apply(p)), initial=fits[3], optimizer="lm"
    )
    assert _map_error(moved[3], truth[3]) > 2.0
    without = [c for c in controls if c.k != 3]
    res = adjust_models(moved, links, without, AdjustmentConfig(link_sigma_px=LINK_SIGMA * 1.1))
    assert _map_error(res.models[3], truth[3]) < 0.3
    assert np.isnan(res.control_rms_px[3]) and np.isfinite(res.link_rms_px[3])


def test_a_failed_frame_and_its_links_are_left_out_and_runs_are_reproducible(scene):
    truth, fits, controls, links = scene
    with_failed = list(fits)
    with_failed[4] = None
    a = adjust_models(with_failed, links, controls)
    b = adjust_models(with_failed, links, controls)
    assert a.models[4] is None and np.isnan(a.link_rms_px[4])
    for ma, mb in zip(a.models, b.models, strict=True):
        assert (ma is None and mb is None) or np.array_equal(ma.params, mb.params)
    assert _map_error(a.models[5], truth[5]) < 0.3  # frame 5 still has its own control points


def test_nothing_to_adjust_and_bad_settings():
    res = adjust_models([None, None], [], [])
    assert res.models == (None, None) and res.n_evaluations == 0
    with pytest.raises(ValueError, match="link_sigma_px must be > 0, got 0"):
        AdjustmentConfig(link_sigma_px=0)
    with pytest.raises(ValueError, match="max_evaluations must be at least 1, got 0"):
        AdjustmentConfig(max_evaluations=0)


def test_a_frame_nothing_constrains_keeps_its_model(scene):
    truth, fits, controls, links = scene
    alone = [c for c in controls if c.k != 5]
    no_links_to_5 = [lk for lk in links if 5 not in (lk.k, lk.l)]
    res = adjust_models(fits, no_links_to_5, alone)
    assert res.success and np.array_equal(res.models[5].params, fits[5].params)
    assert np.isnan(res.link_rms_px[5]) and np.isnan(res.control_rms_px[5])


@pytest.mark.parametrize("degree", [2, 3])
def test_jacobian_by_row_is_the_models_parameter_jacobian(degree):
    """The normal equations take a polyprojective's Jacobian by row (the x row on the
    numerator a and the denominator c, the y row on b and c): the same numbers, and the rest
    is 0."""
    rng = np.random.default_rng(degree)
    model = PolyProjective.from_projective(
        _truth(1).projective_part(), degree, Normalisation.for_extent(W, H),
        _truth(1).dst_norm,
    )  # fmt: skip
    model = model.with_params(model.params + rng.normal(0, 1e-3, model.params.shape))
    pts = rng.uniform(0, [W, H], (50, 2))
    values, jac = model.param_jacobian(pts)
    got, ix, iy, jx, jy = model.param_jacobian_by_row(model.design(pts))
    np.testing.assert_array_equal(got, values)
    np.testing.assert_array_equal(jx, jac[:, 0, ix])
    np.testing.assert_array_equal(jy, jac[:, 1, iy])
    others_x = np.setdiff1d(np.arange(jac.shape[2]), ix)
    others_y = np.setdiff1d(np.arange(jac.shape[2]), iy)
    assert not jac[:, 0, others_x].any() and not jac[:, 1, others_y].any()
    assert len(others_x) == len(others_y) == (degree + 1) * (degree + 2) // 2


def test_covariance_blocks_are_the_inverses_blocks_dense_or_sparse(monkeypatch):
    """A window's predicted errors take diagonal blocks of the normal matrix's inverse: by a
    dense Cholesky inverse up to DENSE_COVARIANCE unknowns, by sparse solves beyond; both are
    numpy's inverse, and a singular matrix gives None either way."""
    import scipy.sparse as sp

    from registration.adjustment import solve

    rng = np.random.default_rng(5)
    n, p = 6, 7  # frames, parameters each: a block band (each frame linked to the next)
    a = rng.normal(size=(n * p, n * p)) * (
        np.abs(np.subtract.outer(np.arange(n * p) // p, np.arange(n * p) // p)) <= 1
    )
    normal = sp.csc_matrix(a @ a.T + 0.1 * np.eye(n * p))
    expected = np.linalg.inv(normal.toarray())
    singular = sp.csc_matrix(np.outer(np.arange(1.0, 8), np.arange(1.0, 8)))
    for dense_limit in (solve.DENSE_COVARIANCE, 0):
        monkeypatch.setattr(solve, "DENSE_COVARIANCE", dense_limit)
        cov = solve._block_inverse(normal)
        for o in range(0, n * p, p):
            np.testing.assert_allclose(cov(o, p), expected[o : o + p, o : o + p], rtol=1e-9)
        assert solve._block_inverse(singular) is None
