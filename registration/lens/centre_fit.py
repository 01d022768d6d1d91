"""Beyond one γ at the frame centre: where the distortion centre is, and whether one parameter
is enough (paper section 3 fixes both; real lenses need not).

* :func:`fit_center`: the Harris γ and the distortion centre together, from the lines of a
  γ estimate, with the centre's uncertainty from the scatter between independent groups of
  lines; it says whether the lines locate the centre, and whether it differs from the frame
  centre.
* :func:`check_one_parameter`: how straight the same lines get with a second radial term
  (``1 / F² = 1 - γ ρ'² - δ ρ'⁴``, Harris at ``δ = 0``) against the one-parameter Harris
  model: clearly straighter lines mean one parameter is not enough for this lens.
* :func:`fit_division_from_lines`, :func:`fit_polynomial_from_lines`: the division model and
  the polynomial model fitted to straight polylines.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from registration.lens.gamma_from_lines import (
    GammaEstimate,
    estimate_gamma_from_lines,
    line_groups,
)
from registration.lens.gamma_pooling import _t_factor
from registration.lens.line_straightness import Straightness, _PackedLines, straightness
from registration.lens.lines_file import as_polylines
from registration.lens.radial import (
    DivisionModel,
    HarrisModel,
    PolynomialModel,
    TwoTermHarrisModel,
    harris_gamma_limit,
)

# The lines locate the centre when its standard uncertainty is at most this fraction of the
# normalising radius (half the diagonal), measured on at least MIN_CENTER_GROUPS independent
# groups of lines; they support moving it when it is also this many standard deviations
# (Mahalanobis, 2-D) from the frame centre.
MAX_CENTER_SIGMA_FRACTION = 0.02
MIN_CENTER_GROUPS = 6
CENTER_SIGNIFICANCE = 3.0
# One parameter is not enough when a second radial term makes the same lines at least this
# much straighter (relative RMS) and by at least this many raw pixels.
ONE_PARAMETER_REL = 0.15
ONE_PARAMETER_ABS_PX = 0.05


@dataclass(frozen=True)
class CenterFit:
    """The Harris γ and distortion centre fitted together (:func:`fit_center`).

    Attributes:
        center: fitted centre ``(x, y)``, raw pixels.
        center_sigma: its standard uncertainties ``(σx, σy)``, raw pixels (cluster-robust over
            groups of lines, widened by Student's t).
        gamma, gamma_uncertainty: γ at that centre and its standard uncertainty.
        frame_center: ``((W-1)/2, (H-1)/2)``.
        offset_px: distance of the fitted centre from the frame centre.
        significance: that offset in standard deviations (Mahalanobis).
        residual_px: pooled straightness RMS (raw px) of the lines at the fit.
        residual_frame_center_px: the same for γ fitted with the frame centre.
        n_groups: independent groups of lines the uncertainty is measured on.
        constrained: the lines locate the centre (see ``MAX_CENTER_SIGMA_FRACTION``).
        supported: constrained and significantly away from the frame centre: use it.
        message: one sentence for the user.
    """

    center: tuple[float, float]
    center_sigma: tuple[float, float]
    gamma: float
    gamma_uncertainty: float
    frame_center: tuple[float, float]
    offset_px: float
    significance: float
    residual_px: float
    residual_frame_center_px: float
    n_groups: int
    constrained: bool
    supported: bool
    message: str

    def to_dict(self) -> dict:
        return {
            k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()
        }


def fit_center(est: GammaEstimate) -> CenterFit:
    """Fit γ and the distortion centre to the lines ``est`` used (same weighting: the summed
    straightness in raw pixels), starting from ``est``.

    The centre's covariance is the cluster-robust (sandwich) estimate with the groups of
    side-by-side lines (:func:`registration.lens.gamma_from_lines.line_groups`) as clusters, so it
    reflects how much independent line groups disagree, not only pixel noise; it is widened by
    Student's t for the number of groups. With fewer than ``MIN_CENTER_GROUPS`` groups the
    centre is reported as not constrained.
    """
    w, h = est.width, est.height
    lines = est.lines_used
    frame = HarrisModel(0.0, w, h)
    c0 = frame.c
    r_n = frame.r_n
    packed = _PackedLines(lines)
    groups = line_groups(lines, est.model())
    _, cluster = np.unique(groups, return_inverse=True)
    K = int(cluster.max()) + 1 if len(cluster) else 0

    def model_of(p) -> HarrisModel:
        c = c0 + np.asarray(p[1:]) * r_n
        return HarrisModel(float(p[0]), w, h, (float(c[0]), float(c[1])))

    def residuals(p) -> NDArray:
        r = packed.residuals_for(model_of(p), weighted=True)
        return np.where(np.isfinite(r), r, 1e3)

    start = np.r_[est.gamma, (np.asarray(est.model().c) - c0) / r_n]
    sol = optimize.least_squares(residuals, start, method="lm", x_scale=[0.1, 0.01, 0.01])
    p = sol.x
    model = model_of(p)
    # Keep the result usable for the whole frame: γ just inside the limit at this centre.
    limit = harris_gamma_limit(w, h, model.center)
    if p[0] >= limit:
        p = np.r_[limit * (1 - 1e-6), p[1:]]
        model = model_of(p)
    r = residuals(p)
    J = sol.jac if np.array_equal(p, sol.x) else optimize.approx_fprime(p, residuals)
    cov = _cluster_covariance(J, r, cluster[packed.index], K)
    scale = np.r_[1.0, r_n, r_n]
    cov = cov * np.outer(scale, scale) * _t_factor(K - 3) ** 2
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    offset = np.asarray(model.c) - c0
    try:
        d2 = float(offset @ np.linalg.solve(cov[1:, 1:], offset))
    except np.linalg.LinAlgError:
        d2 = 0.0
    significance = math.sqrt(max(d2, 0.0))
    res_fit = float(np.sqrt(np.mean(r**2)))
    res_frame = straightness(lines, est.model(), raw_units=True).overall
    constrained = K >= MIN_CENTER_GROUPS and max(sig[1], sig[2]) <= MAX_CENTER_SIGMA_FRACTION * r_n
    supported = constrained and significance >= CENTER_SIGNIFICANCE
    message = _centre_message(
        K, constrained, supported, model.c, sig, offset, significance, res_frame, res_fit
    )
    return CenterFit(
        center=(float(model.c[0]), float(model.c[1])),
        center_sigma=(float(sig[1]), float(sig[2])),
        gamma=float(p[0]),
        gamma_uncertainty=float(sig[0]),
        frame_center=(float(c0[0]), float(c0[1])),
        offset_px=float(np.hypot(*offset)),
        significance=significance,
        residual_px=res_fit,
        residual_frame_center_px=float(res_frame),
        n_groups=K,
        constrained=bool(constrained),
        supported=bool(supported),
        message=message,
    )


def _centre_message(
    K: int,
    constrained: bool,
    supported: bool,
    centre: NDArray,
    sig: NDArray,
    offset: NDArray,
    significance: float,
    res_frame: float,
    res_fit: float,
) -> str:
    """:attr:`CenterFit.message`: whether the ``K`` line groups locate the fitted ``centre``
    ``(2,)`` raw px (``sig`` ``(3,)``: the standard uncertainties of γ, x and y) and support
    moving it by ``offset`` ``(2,)`` px from the frame centre (``significance`` σ;
    straightness ``res_frame`` at the frame centre and ``res_fit`` fitted, raw px)."""
    where = f"({centre[0]:.1f}, {centre[1]:.1f}) ± ({sig[1]:.1f}, {sig[2]:.1f}) px"
    if K < MIN_CENTER_GROUPS:
        return (
            f"only {K} independent group(s) of lines (need {MIN_CENTER_GROUPS}): the centre is "
            f"not constrained; the frame centre is kept"
        )
    if not constrained:
        return (
            f"the lines locate the centre only to {where}: not constrained; the frame centre is "
            f"kept"
        )
    if not supported:
        return (
            f"centre {where} is consistent with the frame centre ({significance:.1f} σ away); "
            f"the frame centre is kept"
        )
    return (
        f"centre {where}, {np.hypot(*offset):.1f} px ({significance:.1f} σ) from the frame "
        f"centre: the lines support it (straightness {res_frame:.3f} -> {res_fit:.3f} px)"
    )


def _cluster_covariance(J: NDArray, r: NDArray, cluster: NDArray, K: int) -> NDArray:
    """Sandwich covariance ``A⁻¹ B A⁻¹`` of least-squares parameters with clustered errors:
    ``A = JᵀJ``, ``B = Σ_k (J_kᵀ r_k)(J_kᵀ r_k)ᵀ``, times ``K / (K - p)``."""
    n_par = J.shape[1]
    A = J.T @ J
    scores = np.stack([np.bincount(cluster, J[:, j] * r, K) for j in range(n_par)], axis=1)
    B = scores.T @ scores
    try:
        Ainv = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return np.full((n_par, n_par), np.inf)
    return Ainv @ B @ Ainv * (K / max(K - n_par, 1))


@dataclass(frozen=True)
class ModelCheck:
    """Is the one-parameter Harris model enough for these lines (:func:`check_one_parameter`)?

    Attributes:
        harris_px: pooled straightness RMS (raw px) of the lines with the estimate's model.
        two_term_px: the same with the best two-term model ``1 / F² = 1 - γ ρ'² - δ ρ'⁴``
            (Harris plus a second radial term; same centre).
        two_term: its ``(γ, δ)``.
        uncorrected_px: the same without correction.
        enough: False when the two-term model is at least ``ONE_PARAMETER_REL`` (relative) and
            ``ONE_PARAMETER_ABS_PX`` (absolute) straighter.
        message: one sentence for the user.
    """

    harris_px: float
    two_term_px: float
    two_term: tuple[float, float]
    uncorrected_px: float
    enough: bool
    message: str

    def to_dict(self) -> dict:
        return {
            k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()
        }


def check_one_parameter(est: GammaEstimate) -> ModelCheck:
    """Compare the straightness of ``est``'s lines under its Harris model with the best model
    with one more radial term, ``1 / F² = 1 - γ ρ'² - δ ρ'⁴`` (which is Harris at ``δ = 0``,
    so it can only do better; same centre, same raw-pixel cost): a clearly straighter fit
    means the lens needs more than one parameter."""
    w, h, c = est.width, est.height, est.center
    lines = est.lines_used
    packed = _PackedLines(lines)
    big = 1e3

    def residuals(p):
        model = TwoTermHarrisModel(float(p[0]), float(p[1]), w, h, c)
        if model.validity_problem():
            return np.full(len(packed.points), big)
        r = packed.residuals_for(model, weighted=True)
        return np.where(np.isfinite(r), r, big)

    harris = float(np.sqrt(np.mean(residuals([est.gamma, 0.0]) ** 2)))
    none = straightness(lines, HarrisModel(0.0, w, h, c), raw_units=True).overall
    sol = optimize.least_squares(residuals, [est.gamma, 0.0], method="trf", x_scale=[0.1, 0.1])
    two = float(np.sqrt(np.mean(residuals(sol.x) ** 2)))
    if two > harris:  # the optimiser never does worse than its start
        two, sol.x = harris, np.array([est.gamma, 0.0])
    gain = harris - two
    enough = not (gain >= ONE_PARAMETER_REL * harris and gain >= ONE_PARAMETER_ABS_PX)
    verdict = "one parameter is enough" if enough else "one parameter is NOT enough"
    message = (
        f"{verdict}: with a second radial term (gamma {sol.x[0]:.3f}, delta {sol.x[1]:.3f}) "
        f"the lines straighten to {two:.3f} px against {harris:.3f} px with Harris alone "
        f"(uncorrected {none:.3f} px)"
    )
    return ModelCheck(
        harris_px=harris,
        two_term_px=two,
        two_term=(float(sol.x[0]), float(sol.x[1])),
        uncorrected_px=float(none),
        enough=bool(enough),
        message=message,
    )


def fit_division_from_lines(
    polylines, width: int, height: int, *, center: tuple[float, float] | None = None
) -> tuple[DivisionModel, Straightness]:
    """Fit the one-parameter division model to straight polylines (bounded scalar search).

    Minimises the same raw-pixel straightness cost as :func:`estimate_gamma_from_lines` over
    the model's valid λ range.

    Returns:
        ``(model, straightness)`` at the optimum (straightness in raw pixels).
    """
    lines = as_polylines(polylines)
    packed = _PackedLines(lines)
    lo, hi = DivisionModel(0.0, width, height, center).lam_limits()
    lo, hi = lo * (1 - 1e-6), hi * (1 - 1e-6)

    def cost(lam: float) -> float:
        return float(
            packed.ssr_for(DivisionModel(float(lam), width, height, center), weighted=True).sum()
        )

    grid = np.linspace(lo, hi, 201)
    i = int(np.argmin([cost(v) for v in grid]))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    res = optimize.minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": 1e-8})
    model = DivisionModel(float(res.x), width, height, center)
    return model, straightness(lines, model, raw_units=True)


def fit_polynomial_from_lines(
    polylines,
    width: int,
    height: int,
    *,
    n_coeffs: int = 2,
    center: tuple[float, float] | None = None,
    initial: PolynomialModel | None = None,
) -> tuple[PolynomialModel, Straightness]:
    """Fit the polynomial model (paper eq. 3) with ``n_coeffs`` of k1..k3 to straight polylines.

    Least squares (``scipy.optimize.least_squares``) on every point's perpendicular distance from
    its line's TLS fit, in raw pixels (see :func:`straightness`, ``raw_units``); parameters for
    which outer raw pixels would have no
    corrected position are penalised. Starts from ``initial`` or from the best Harris γ
    (``k1 = -γ/2``).

    Returns:
        ``(model, straightness)`` at the optimum (straightness in raw pixels).
    """
    if n_coeffs not in (1, 2, 3):
        raise ValueError(f"n_coeffs must be 1, 2 or 3, got {n_coeffs}")
    lines = as_polylines(polylines)
    packed = _PackedLines(lines)
    big = 1e3 * np.hypot(width, height)

    def make(p):
        k = list(p) + [0.0] * (3 - n_coeffs)
        return PolynomialModel(float(k[0]), float(k[1]), float(k[2]), width, height, center)

    if initial is None:
        # Least-squares polynomial through the best Harris model's f over the corrected radii
        # the frame reaches; halved towards 0 until valid (strong barrel distortion saturates
        # the raw radius, which an eq.-3 polynomial can only follow up to its fold).
        harris = HarrisModel(
            estimate_gamma_from_lines(lines, width, height, center=center).gamma,
            width,
            height,
            center,
        )
        rho_m = harris.max_raw_rho()
        rho_c = (
            float(
                np.linalg.norm(
                    harris.corrected_from_raw([harris.c + [rho_m * harris.r_n, 0]])[0] - harris.c
                )
            )
            / harris.r_n
        )
        rho = np.linspace(0, rho_c, 200)[1:]
        target = rho / np.sqrt(1 + harris.gamma * rho**2)
        basis = np.stack([rho ** (2 * j + 3) for j in range(n_coeffs)], axis=1)
        k = np.linalg.lstsq(basis, target - rho, rcond=None)[0]
        for _ in range(60):
            if make(k).is_valid():
                break
            k = 0.5 * k
        x0 = k
    else:
        x0 = np.array([initial.k1, initial.k2, initial.k3][:n_coeffs])

    def residuals(p):
        model = make(p)
        if not model.is_valid():
            return np.full(len(packed.points), big)
        return packed.residuals_for(model, weighted=True)

    sol = optimize.least_squares(residuals, x0, method="trf", x_scale="jac")
    model = make(sol.x)
    return model, straightness(lines, model, raw_units=True)
