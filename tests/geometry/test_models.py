"""Tests for registration.geometry.models against known transforms and exact ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from registration.coords import rescale
from registration.geometry import (
    Chain,
    FailedEstimation,
    GeometricModel,
    Inverted,
    Normalisation,
    PolyProjective,
    Projective,
    Translation,
    model_from_dict,
    n_polyprojective_params,
)

W, H = 1280, 960
# base_from_frame of a realistic frame: ~10 deg rotation, ~20 % scale, mild perspective.
H_TRUE = np.array(
    [
        [1.18 * np.cos(0.17), -1.18 * np.sin(0.17), 420.0],
        [1.18 * np.sin(0.17), 1.18 * np.cos(0.17), 150.0],
        [3e-5, -2e-5, 1.0],
    ]
)
CORNERS = np.array([[0, 0], [W - 1, 0], [W - 1, H - 1], [0, H - 1]], dtype=float)


def true_projective() -> Projective:
    return Projective.from_matrix(H_TRUE)


def true_poly(degree: int = 2) -> PolyProjective:
    """The projective plus a mild quadratic warp (a few px) in numerator and denominator."""
    proj = true_projective()
    base = PolyProjective.from_projective(
        proj,
        degree,
        Normalisation.for_extent(W, H),
        Normalisation.from_points(proj.apply(CORNERS)),
    )
    p = base.params.copy()
    j = (degree + 1) * (degree + 2) // 2
    p[0] += 0.004  # a: u^2 (or u^3)
    p[1] -= 0.003  # a: next monomial
    p[j + 2] += 0.005  # b
    p[2 * j] += 0.002  # c: highest-degree u term
    p[2 * j + 1] -= 0.001
    return base.with_params(p)


def frame_grid(step: int = 16) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(0, W, step, dtype=float), np.arange(0, H, step, dtype=float))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def test_param_counts_follow_eq5():
    assert n_polyprojective_params(2) == 17
    assert n_polyprojective_params(3) == 29
    assert PolyProjective(2).params.shape == (17,)
    assert PolyProjective(3).params.shape == (29,)
    assert Projective().params.shape == (8,)
    assert Translation().params.shape == (2,)
    assert PolyProjective.min_samples == 9
    assert PolyProjective.of_degree(3).min_samples == 15
    assert PolyProjective(3).min_samples == 15 and PolyProjective(2).min_samples == 9
    assert Projective.min_samples == 4 and Translation.min_samples == 1


def test_models_satisfy_protocol():
    for m in (Translation(), Projective(), true_poly(), Chain(true_poly(), Projective())):
        assert isinstance(m, GeometricModel)


def test_true_poly_is_really_nonprojective():
    g = frame_grid(64)
    d = np.linalg.norm(true_poly().apply(g) - true_projective().apply(g), axis=1)
    assert 2.0 < d.max() < 40.0


@pytest.mark.parametrize("degree", [2, 3])
def test_polyprojective_round_trip_frame_grid(degree):
    poly = true_poly(degree)
    g = frame_grid(8)
    back = poly.inverse(poly.apply(g))
    assert np.all(np.isfinite(back))
    assert np.abs(back - g).max() < 1e-6


def test_polyprojective_inverse_then_apply_on_base_points():
    poly = true_poly()
    base_pts = poly.apply(frame_grid(40)) + np.array([3.3, -2.7])
    frame_pts = poly.inverse(base_pts)
    assert np.abs(poly.apply(frame_pts) - base_pts).max() < 1e-6


def test_polyprojective_inverse_nan_without_preimage():
    # x' = u + 0.5 u^2 (normalised): the image of the u axis is x' >= -0.5, so x' = -2 has no
    # preimage; the map folds at u = -1 and only the unfolded branch may be returned.
    p = np.zeros(17)
    p[3] = 1.0  # a: u
    p[0] = 0.5  # a: u^2
    p[10] = 1.0  # b: v
    m = PolyProjective(2, p)
    out = m.inverse([[-2.0, 0.0], [0.5, 0.25], [np.nan, 1.0]])
    assert np.all(np.isnan(out[0]))
    assert np.allclose(m.apply(out[1:2]), [[0.5, 0.25]], atol=1e-9)
    assert out[1, 0] > -1.0  # the unfolded branch
    assert np.all(np.isnan(out[2]))


def test_from_projective_reproduces_projective_exactly():
    proj = true_projective()
    g = frame_grid(32)
    for norms in [
        (None, None),
        (Normalisation.for_extent(W, H), Normalisation((900.0, 700.0), 1e-3)),
    ]:
        for degree in (2, 3):
            poly = PolyProjective.from_projective(proj, degree, *norms)
            assert np.abs(poly.apply(g) - proj.apply(g)).max() < 1e-8
            assert np.abs(poly.inverse(proj.apply(g)) - g).max() < 1e-6


def test_projective_matrix_round_trip_and_exact_inverse():
    proj = Projective.from_matrix(
        H_TRUE, Normalisation.for_extent(W, H), Normalisation((800, 600), 0.002)
    )
    assert np.allclose(proj.matrix, H_TRUE, rtol=1e-12, atol=1e-12)
    g = frame_grid(32)
    hom = np.hstack([g, np.ones((len(g), 1))]) @ H_TRUE.T
    assert np.abs(proj.apply(g) - hom[:, :2] / hom[:, 2:]).max() < 1e-9
    assert np.abs(proj.inverse(proj.apply(g)) - g).max() < 1e-9
    # A point on the vanishing line has no finite image, and the inverse of a point at the
    # horizon of the inverse is NaN rather than inf.
    assert np.all(np.isnan(proj.inverted().inverse(np.array([[0.0, -1.0 / H_TRUE[2, 1]]]))))


def test_rescaled_matches_coords_rescale():
    proj = true_projective()
    g = frame_grid(32)
    for ss, ds in [(0.25, 0.25), (4.0, 4.0), (0.5, 2.0)]:
        r = proj.rescaled(ss, ds)
        assert np.abs(r.apply(rescale(g, ss)) - rescale(proj.apply(g), ds)).max() < 1e-8
    poly = true_poly()
    r = poly.rescaled(0.25, 0.5)
    assert np.abs(r.apply(rescale(g, 0.25)) - rescale(poly.apply(g), 0.5)).max() < 1e-8


def test_quarter_scale_fit_becomes_full_scale_start():
    """The paper's coarse step: fit at 1/4 scale, rescale, and reproduce the full-scale truth."""
    rng = np.random.default_rng(7)
    src_full = rng.uniform([0, 0], [W - 1, H - 1], (50, 2))
    dst_full = true_projective().apply(src_full)
    quarter = Projective.estimate(rescale(src_full, 0.25), rescale(dst_full, 0.25))
    assert quarter
    full = quarter.rescaled(4.0, 4.0)
    g = frame_grid(32)
    assert np.abs(full.apply(g) - true_projective().apply(g)).max() < 1e-6
    start = PolyProjective.from_projective(full, 2)
    assert np.abs(start.apply(g) - true_projective().apply(g)).max() < 1e-6


def test_projective_estimate_noiseless(rng):
    src = rng.uniform([0, 0], [W - 1, H - 1], (30, 2))
    dst = true_projective().apply(src)
    g = frame_grid(32)
    for opt in ("lstsq", "lm", "nelder-mead"):
        m = Projective.estimate(src, dst, optimizer=opt)
        assert m, getattr(m, "reason", "")
        assert np.abs(m.apply(g) - true_projective().apply(g)).max() < 1e-6, opt


def test_projective_minimal_sample_is_exact():
    dst = true_projective().apply(CORNERS)
    m = Projective.estimate(CORNERS, dst)
    assert m and np.allclose(m.matrix, H_TRUE, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("degree", [2, 3])
def test_polyprojective_estimate_noiseless(rng, degree):
    truth = true_poly(degree)
    src = rng.uniform([0, 0], [W - 1, H - 1], (200, 2))
    dst = truth.apply(src)
    m = PolyProjective.estimate(src, dst, optimizer="lm", degree=degree)
    assert m, getattr(m, "reason", "")
    assert m.degree == degree and m.params.shape == (n_polyprojective_params(degree),)
    g = frame_grid(16)
    assert np.abs(m.apply(g) - truth.apply(g)).max() < 1e-6


def test_polyprojective_estimate_noisy(rng):
    truth = true_poly()
    sigma = 1.0
    src = rng.uniform([0, 0], [W - 1, H - 1], (600, 2))
    dst = truth.apply(src) + rng.normal(0, sigma, src.shape)
    m = PolyProjective.estimate(src, dst, optimizer="lm")
    assert m
    rms = np.sqrt(np.mean(m.residuals(src, dst) ** 2))
    # 2-D RMS of the noise is sqrt(2) sigma, minus the 17 fitted degrees of freedom.
    assert 0.9 * np.sqrt(2) * sigma < rms < 1.1 * np.sqrt(2) * sigma
    g = frame_grid(32)
    assert np.abs(m.apply(g) - truth.apply(g)).max() < 1.0
    assert np.mean(np.linalg.norm(m.apply(g) - truth.apply(g), axis=1)) < 0.3


def test_estimate_from_projective_initial_converges(rng):
    truth = true_poly()
    src = rng.uniform([0, 0], [W - 1, H - 1], (150, 2))
    dst = truth.apply(src)
    m = PolyProjective.estimate(src, dst, initial=true_projective(), optimizer="lm")
    assert m and np.abs(m.apply(src) - dst).max() < 1e-6


def test_weights_ignore_zero_weight_outliers(rng):
    src = rng.uniform([0, 0], [W - 1, H - 1], (40, 2))
    dst = true_projective().apply(src)
    dst[[3, 17]] += 50.0
    w = np.ones(40)
    w[[3, 17]] = 0.0
    for opt in ("lstsq", "lm"):
        m = Projective.estimate(src, dst, weights=w, optimizer=opt)
        assert np.abs(m.matrix - H_TRUE).max() < 1e-8


def test_nelder_mead_reaches_lm_minimum(rng):
    truth = true_poly()
    src = rng.uniform([0, 0], [W - 1, H - 1], (60, 2))
    dst = truth.apply(src) + rng.normal(0, 1.0, src.shape)
    start = PolyProjective.from_projective(true_projective(), 2, truth.src_norm, truth.dst_norm)
    costs = {}
    for opt in ("lm", "nelder-mead"):
        m = PolyProjective.estimate(src, dst, initial=start, optimizer=opt)
        assert m
        costs[opt] = float(np.sum(m.residuals(src, dst) ** 2))
    start_cost = float(np.sum(start.residuals(src, dst) ** 2))
    assert costs["lm"] < 0.5 * start_cost
    assert abs(costs["nelder-mead"] - costs["lm"]) <= 0.01 * costs["lm"]


def test_translation_estimate_and_compose():
    src = np.array([[0.0, 0.0], [10.0, 5.0], [3.0, 7.0]])
    t = Translation.estimate(src, src + [2.5, -1.0])
    assert t and np.allclose(t.params, [2.5, -1.0])
    assert np.allclose(t.compose(t.inverted()).params, 0.0)
    p = t.compose(true_projective())
    assert isinstance(p, Projective)
    assert np.allclose(p.apply(src), true_projective().apply(src) + [2.5, -1.0])
    assert not Translation.estimate(np.zeros((0, 2)), np.zeros((0, 2)))


def test_compose_with_inverse_is_identity():
    g = frame_grid(40)
    proj = true_projective()
    ident = proj.compose(proj.inverted())
    assert isinstance(ident, Projective)
    assert np.allclose(ident.matrix, np.eye(3), atol=1e-12)
    poly = true_poly()
    chain = poly.inverted().compose(poly)
    assert isinstance(chain, Chain)
    assert np.abs(chain.apply(g) - g).max() < 1e-6
    assert np.abs(chain.inverse(g) - g).max() < 1e-6


def test_chain_order_and_inverse():
    poly, proj = true_poly(), Projective.from_matrix([[0.5, 0, 10], [0, 0.5, -4], [0, 0, 1]])
    g = frame_grid(64)
    chain = proj.compose(poly)  # proj(poly(x))
    assert np.allclose(chain.apply(g), proj.apply(poly.apply(g)))
    assert np.abs(chain.inverse(chain.apply(g)) - g).max() < 1e-6
    assert np.abs(chain.inverted().apply(chain.apply(g)) - g).max() < 1e-6
    assert not Chain.estimate(g, g)


def test_residuals_are_euclidean():
    t = Translation([3.0, 4.0])
    assert np.allclose(t.residuals([[0, 0], [1, 1]], [[0, 0], [4, 5]]), [5.0, 0.0])


@pytest.mark.parametrize(
    "model",
    [
        Translation([1.5, -2.0]),
        Projective.from_matrix(H_TRUE, Normalisation.for_extent(W, H)),
        true_poly(2),
        true_poly(3),
        Chain(true_poly(), Inverted(true_projective())),
    ],
)
def test_to_dict_round_trip_is_exact(model):
    d = json.loads(json.dumps(model.to_dict()))
    back = model_from_dict(d)
    assert type(back) is type(model)
    assert type(type(model).from_dict(d)) is type(model)
    g = frame_grid(64)
    assert np.array_equal(back.apply(g), model.apply(g))


def test_model_from_dict_rejects_unknown():
    with pytest.raises(ValueError, match="unknown model type 'Shear'"):
        model_from_dict({"type": "Shear"})
    with pytest.raises(ValueError, match="lacks key 'params'"):
        model_from_dict({"type": "Projective"})
    with pytest.raises(ValueError, match="not a PolyProjective"):
        PolyProjective.from_dict(Translation().to_dict())


def test_degenerate_inputs_give_falsy_reasons():
    line = np.stack([np.linspace(0, 100, 20), np.linspace(5, 55, 20)], axis=1)
    res = Projective.estimate(line, line * 2)
    assert isinstance(res, FailedEstimation) and not res
    assert "collinear" in res.reason
    res = PolyProjective.estimate(line[:5] + [[0, 0], [0, 9], [3, 0], [0, 0], [1, 1]], line[:5])
    assert not res
    assert res.reason == "needs at least 9 point pairs for a degree-2 polyprojective, got 5"
    pts = np.random.default_rng(0).uniform(0, 100, (12, 2))
    bad = pts.copy()
    bad[4, 1] = np.nan
    res = PolyProjective.estimate(pts, bad)
    assert not res and "non-finite" in res.reason
    res = Projective.estimate(np.ones((6, 2)), pts[:6])
    assert not res and "coincide" in res.reason
    # 3 of 4 points collinear: the homography is not determined.
    res = Projective.estimate([[0, 0], [1, 1], [2, 2], [0, 5]], [[0, 0], [1, 0], [3, 4], [0, 5]])
    assert not res and "collinear" in res.reason
    # Duplicated points do not add constraints: 9 pairs but only 5 distinct.
    dup = np.vstack([pts[:5], pts[:4]])
    res = PolyProjective.estimate(dup, dup * 1.1)
    assert not res and "degenerate" in res.reason


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="same shape"):
        Projective.estimate(np.zeros((5, 2)), np.zeros((6, 2)))
    with pytest.raises(ValueError, match="optimizer"):
        Projective.estimate(np.zeros((5, 2)), np.zeros((5, 2)), optimizer="bfgs")
    with pytest.raises(ValueError, match=r"shape \(N, 2\)"):
        true_poly().apply(np.zeros((5, 3)))
    with pytest.raises(ValueError, match="needs 17 params"):
        PolyProjective(2, np.zeros(16))
    with pytest.raises(ValueError, match="src_scale"):
        true_projective().rescaled(0.0, 1.0)


def test_levenberg_marquardt_reaches_minpacks_minimum():
    """Our LM (same bits in every process) against scipy's MINPACK on a curved least-squares
    problem (Rosenbrock's, plus a noisy exponential fit): the same minimum."""
    import scipy.optimize

    from registration.geometry import levenberg_marquardt

    def rosen(p):
        return np.array([10.0 * (p[1] - p[0] ** 2), 1.0 - p[0]])

    def rosen_jac(p):
        return np.array([[-20.0 * p[0], 10.0], [-1.0, 0.0]])

    np.testing.assert_allclose(
        levenberg_marquardt([-1.2, 1.0], rosen, rosen_jac), [1, 1], atol=1e-9
    )
    t = np.linspace(0, 4, 60)
    y = 2.5 * np.exp(-1.3 * t) + 0.4 + np.random.default_rng(3).normal(0, 0.02, t.size)

    def fun(p):
        return p[0] * np.exp(-p[1] * t) + p[2] - y

    def jac(p):
        e = np.exp(-p[1] * t)
        return np.c_[e, -p[0] * t * e, np.ones_like(t)]

    ours = levenberg_marquardt([1.0, 0.5, 0.0], fun, jac)
    ref = scipy.optimize.least_squares(fun, [1.0, 0.5, 0.0], jac=jac, method="lm", xtol=1e-14).x
    # Both stop within 1e-12 of the minimum's cost, which fixes the parameters to ~1e-6.
    assert fun(ours) @ fun(ours) <= fun(ref) @ fun(ref) * (1 + 1e-10)
    np.testing.assert_allclose(ours, ref, rtol=1e-6)


def test_levenberg_marquardt_stops_where_the_jacobian_or_steps_are_not_finite():
    """A Jacobian with NaN (the model undefined at the start) or residuals that are infinite
    beyond the start: the start comes back, the loop ends (it once spun on NaN steps)."""
    from registration.geometry import levenberg_marquardt

    p0 = np.array([1.0, 2.0])
    calls = []

    def fun(p):
        calls.append(1)
        return np.array([p[0] - 3.0, p[1] + 1.0, 0.5])

    out = levenberg_marquardt(p0, fun, lambda p: np.full((3, 2), np.nan))
    np.testing.assert_array_equal(out, p0)
    # Every trial step lands where the residuals are infinite (a barrier all around the start).
    start_cost = [True]

    def walled(p):
        if start_cost[0]:
            start_cost[0] = False
            return np.array([1.0, 1.0, 1.0])
        return np.full(3, np.inf)

    out = levenberg_marquardt(p0, walled, lambda p: np.eye(3, 2), max_nfev=500)
    np.testing.assert_array_equal(out, p0)


def _start_under_the_floor(coef: float):
    """Degree-2 identity with denominator ``1 + coef * u * v`` on five points at the corners
    and centre of [-0.5, 0.5]^2 (normalised), their destinations and helpers."""
    from registration.geometry.rational import _identity_params
    from registration.geometry.rational_fit import _exponents

    degree = 2
    sn = np.array([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5], [0.5, 0.5], [0.0, 0.0]])
    dst = sn * 100.0 + 500.0
    p0 = _identity_params(degree)
    j = (degree + 1) * (degree + 2) // 2
    uv = 2 * j + next(i for i, e in enumerate(_exponents(degree)) if tuple(e) == (1, 1))
    p0[uv] = coef
    return degree, sn, dst, Normalisation.from_points(dst), p0, uv


def test_a_fit_from_a_start_under_the_floor_keeps_the_starts_own_floor():
    """A start whose smallest denominator over the points' bounding box is positive but under
    MIN_DENOMINATOR (a previous fit that ended on the floor, then rounded) keeps a barrier at
    its own smallest denominator: no step may go lower. Without it the barrier was off and a
    re-anchored long-flight frame's fit put a pole inside the frame (a corner 172 px off)."""
    from registration.geometry import MIN_DENOMINATOR
    from registration.geometry.rational_fit import _BARRIER_RESIDUAL, _geometric_fun

    # Denominator 1 - 3.8 u v: 0.05 at (0.5, 0.5) and (-0.5, -0.5), its minimum over the box.
    degree, sn, dst, norm, p0, uv = _start_under_the_floor(-3.8)
    fun, _ = _geometric_fun(degree, sn, dst, norm, None, p0)
    assert not (fun(p0) == _BARRIER_RESIDUAL).any()  # the start itself is usable
    better = p0.copy()
    better[uv] = -3.0  # 0.25 there: back towards the floor
    assert not (fun(better) == _BARRIER_RESIDUAL).any()
    deeper = p0.copy()
    deeper[uv] = -3.9  # 0.025: positive at the points, but under the start's own minimum
    assert 0 < 1 - 3.9 * 0.25 < 0.05 < MIN_DENOMINATOR
    assert (fun(deeper) == _BARRIER_RESIDUAL).all()


def test_a_fit_from_a_start_that_folds_in_its_domain_still_never_folds_at_its_points():
    """A start whose denominator is positive at the points but <= 0 elsewhere in the domain
    has no floor to keep; a step that folds the map at one of the points (denominator <= 0
    there) must still be refused (barrier residual), or a long Gauss-Newton step can land on a
    fold that fits outliers (a long flight's anchor failed so)."""
    from registration.geometry.rational_fit import (
        _BARRIER_RESIDUAL,
        _design,
        _geometric_fun,
        _split,
    )

    degree, sn, dst, norm, p0, uv = _start_under_the_floor(-3.8)
    domain_n = np.array([[1.0, 1.0]])  # 1 - 3.8 < 0: the start folds there
    fun, _ = _geometric_fun(degree, sn, dst, norm, None, p0, domain_n)
    assert not (fun(p0) == _BARRIER_RESIDUAL).any()
    deeper = p0.copy()
    deeper[uv] = -3.9  # still positive at the points: allowed without a floor
    assert not (fun(deeper) == _BARRIER_RESIDUAL).any()
    folded = p0.copy()
    folded[uv] = -5.0  # 1 - 5 * 0.25 < 0 at two of the points
    assert (_design(sn, degree) @ _split(folded, degree)[2]).min() <= 0
    assert (fun(folded) == _BARRIER_RESIDUAL).all()


def test_polyprojective_param_jacobian_matches_finite_differences():
    """``param_jacobian`` (what the sequence adjustment linearises): the values are ``apply``'s
    and each column is the model's change per unit of that parameter, to finite-difference
    precision, on a model with real curvature and normalisations."""
    from registration.geometry import Normalisation

    rng = np.random.default_rng(3)
    base = PolyProjective.identity(2).params
    m = PolyProjective(
        2,
        base + rng.normal(0, 0.02, base.size),
        Normalisation((320.0, 240.0), 1 / 400),
        Normalisation((900.0, 700.0), 1 / 500),
    )
    xy = rng.uniform(0, 640, (12, 2))
    values, jac = m.param_jacobian(xy)
    np.testing.assert_allclose(values, m.apply(xy), rtol=0, atol=1e-9)
    assert jac.shape == (12, 2, 17)
    eps = 1e-6
    for i in range(17):
        p = m.params.copy()
        p[i] += eps
        num = (PolyProjective(2, p, m.src_norm, m.dst_norm).apply(xy) - values) / eps
        np.testing.assert_allclose(jac[:, :, i], num, rtol=1e-4, atol=1e-3)
