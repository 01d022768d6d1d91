"""The lens beyond Harris, from the reference frame's control points (beyond the paper).

The paper corrects the lens with Harris's one parameter γ (paper section 3). A real lens can need
more: a fourth-order term ``k2`` (:class:`registration.lens.radial.TwoTermHarrisModel`) moves the
corrected image by an amount that grows like ``ρ'⁵`` towards the corners, and it peaks where no
control point is (a template needs its whole window inside the frame, so the outermost raw
pixels, which the correction stretches most, have none). Neither the polyprojective nor a field
fitted to the points can follow it there; every frame inherits what the reference frame gets
wrong, since the mid base image is rendered from it.

:func:`estimate_k2` fits, to the reference frame's control points kept by REQCON (raw px ->
base px), ``base = H(lens_k2(raw) + s(row))``: ``H`` a homography, ``s`` a polynomial of the raw
row per axis (a rolling shutter: rows exposed one after another see a moving camera), by robust
(soft-L1) least squares, once with ``k2 = 0`` and once free. The polyprojective is left out on
purpose: its second-order terms absorb part of the ``k2`` term and part of the rolling shutter,
and fitted with it ``k2`` came out at 0-0.02 even against the exact truth of a 0.04 lens
(simulated paper-hard, 1280x960); with the homography and the row polynomial the matches give
0.037-0.043 on eight such flights. In one frame a small ``k2`` cannot be told from relief
displacement, which is radial about the nadir too: flights with an exact Harris lens gave -0.014
to 0.000, so smaller estimates than ``LensConfig.min_abs_k2`` are not used.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from registration.lens.camera import Camera


@dataclass(frozen=True)
class LensConfig:
    """Whether and how the registration estimates the lens beyond Harris.

    Attributes:
        estimate_k2: estimate ``k2`` from the reference frame and, when it is significant,
            register every frame with it. False = the paper (Harris γ only).
        min_significance: ``k2`` is used only when ``|k2|`` is at least this many standard
            errors (from the robust fit's Jacobian and residual spread).
        min_abs_k2: smaller estimates are not used. Relief displacement is radial about the
            nadir too, so in one frame a small ``k2`` cannot be told from the terrain: even the
            exact truth of simulated flights with an exact Harris lens gives k2 = -0.013 (the
            default flight, 640x480) under this fit, with quadratic terms added alike. Measured
            on the control points: exact Harris lenses -0.014 to 0.000 (six flights; used, -0.014
            moved the default 640x480 flight's error after local from 0.536 to 0.619 px, and
            -0.011 the 120-frame long flight's first tenth from 0.762 to 0.922 px); lenses with
            k2 = 0.04: 0.025 (480x360), 0.033-0.038 (640x480), 0.037-0.043 (1280x960 and
            2560x1920).
        min_rms_reduction: ``k2`` is used only when it lowers the points' RMS residual under
            the fit (the best 90 % of them) by at least this share (measured: 41-66 % for the
            lenses with k2 = 0.04, 0-35 % for exact Harris lenses).
        max_abs_k2: larger estimates are refused (no lens this project meets bends that much
            beyond Harris; a fit that wants it is following something else).
        row_degree: degree of the rolling-shutter polynomial of the raw row (per axis).
        min_points: fewest kept control points to estimate from.
    """

    estimate_k2: bool = False
    min_significance: float = 4.0
    min_abs_k2: float = 0.02
    min_rms_reduction: float = 0.25
    max_abs_k2: float = 0.3
    row_degree: int = 3
    min_points: int = 50

    def __post_init__(self) -> None:
        if not self.min_significance > 0:
            raise ValueError(f"min_significance must be > 0, got {self.min_significance}")
        if not 0 <= self.min_abs_k2 < self.max_abs_k2:
            raise ValueError(
                f"min_abs_k2 must be in [0, max_abs_k2 = {self.max_abs_k2}), got {self.min_abs_k2}"
            )
        if not 0 <= self.min_rms_reduction < 1:
            raise ValueError(f"min_rms_reduction must be in [0, 1), got {self.min_rms_reduction}")
        if not 0 < self.max_abs_k2 <= 0.5:
            raise ValueError(f"max_abs_k2 must be in (0, 0.5], got {self.max_abs_k2}")
        if not 0 <= self.row_degree <= 5:
            raise ValueError(f"row_degree must be 0-5, got {self.row_degree}")
        if not self.min_points >= 20:
            raise ValueError(f"min_points must be at least 20, got {self.min_points}")


@dataclass(frozen=True)
class LensEstimate:
    """What :func:`estimate_k2` found.

    Attributes:
        k2: the estimate (NaN when none was made).
        sigma: its standard error.
        rms_harris_px, rms_px: RMS residual (base px) of the best 90 % of the points under the
            fit with ``k2 = 0`` and with the estimate.
        n_points: points used.
        adopted: whether the estimate is used (significant, plausible, and the fine step
            succeeded with it).
        summary: the estimate in words; reason: the summary and what was done with it.
    """

    k2: float
    sigma: float
    rms_harris_px: float
    rms_px: float
    n_points: int
    adopted: bool
    summary: str
    reason: str

    def refused(self, why: str) -> LensEstimate:
        """The same estimate, not used, for ``why``."""
        return dataclasses.replace(self, adopted=False, reason=f"{self.summary}: {why}")

    def to_dict(self) -> dict:
        """JSON-able (non-finite numbers as None)."""
        return {
            k: (float(v) if np.isfinite(v) else None) if isinstance(v, float) else v
            for k, v in asdict(self).items()
        }


def _none(n: int, reason: str) -> LensEstimate:
    nan = float("nan")
    return LensEstimate(nan, nan, nan, nan, n, False, reason, reason)


# The RMS residuals compare the fits on their best 90 % of points: a few mismatches 20-40 px off
# would otherwise dominate both and hide what k2 explains.
TRIMMED_SHARE = 0.9


def _normalisation(xy: NDArray) -> tuple[NDArray, float]:
    """``(mean (2,), scale)``: ``(xy - mean) / scale`` has unit RMS distance from the origin."""
    mean = xy.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((xy - mean) ** 2, axis=1))))
    return mean, scale if scale > 0 else 1.0


def _trimmed_rms(r: NDArray) -> float:
    """RMS of the smallest ``TRIMMED_SHARE`` of ``r`` (px)."""
    kept = np.sort(r)[: max(1, int(round(TRIMMED_SHARE * len(r))))]
    return float(np.sqrt(np.mean(kept**2)))


def estimate_k2(
    raw_xy: NDArray, base_xy: NDArray, camera: Camera, config: LensConfig
) -> LensEstimate:
    """The lens's fourth-order term from control points of the reference frame (module doc).

    Args:
        raw_xy: ``(N, 2)`` raw frame px of the kept control points.
        base_xy: ``(N, 2)`` their base px.
        camera: the frames' camera (its γ is kept; its ``k2`` is ignored).
        config: :class:`LensConfig`.
    """
    raw_xy, base_xy = np.asarray(raw_xy, np.float64), np.asarray(base_xy, np.float64)
    ok = np.isfinite(raw_xy).all(axis=1) & np.isfinite(base_xy).all(axis=1)
    raw_xy, base_xy = raw_xy[ok], base_xy[ok]
    n = len(raw_xy)
    if n < config.min_points:
        return _none(n, f"k2 not estimated: {n} control points (needs {config.min_points})")
    w, h = camera.size
    deg = config.row_degree
    rows = (raw_xy[:, 1] - (h - 1) / 2) / h
    row_powers = np.stack([rows ** (i + 1) for i in range(deg)], axis=1)

    # Both sides normalised to unit spread about their means (Hartley): unnormalised, the
    # homography's perspective terms are ~1e-5 of its others and the robust fit took ~700
    # iterations (4 s for 642 points); residuals stay in base px.
    base_mean, base_scale = _normalisation(base_xy)
    corr_mean, corr_scale = _normalisation(camera.with_k2(0.0).corrected_from_raw(raw_xy))

    lens0 = camera.with_k2(0.0).lens
    centre, r_n = lens0.c, float(lens0.r_n)
    d_raw = (raw_xy - centre) / r_n
    u_raw = np.sum(d_raw * d_raw, axis=1)
    shift_unit = 100.0 * row_powers  # the rolling shutter's shift per parameter, px

    def forward(p: NDArray, k2: float):
        """Base px predicted, and what the Jacobian needs."""
        xy = camera.with_k2(k2).corrected_from_raw(raw_xy)
        # The rolling shutter's shift, in units of 100 px so that all parameters are ~1.
        xn = (xy + shift_unit @ p[8:].reshape(2, deg).T - corr_mean) / corr_scale
        h = np.r_[p[:8], 1.0].reshape(3, 3)
        q = np.c_[xn, np.ones(n)] @ h.T
        return q[:, :2] / q[:, 2:] * base_scale + base_mean, xn, q, h

    def predict(p: NDArray, k2: float) -> NDArray:
        return forward(p, k2)[0]

    def residuals(p: NDArray, k2: float) -> NDArray:
        r = (predict(p, k2) - base_xy).ravel()
        # A trial k2 that leaves a point without a corrected position costs it 1000 px.
        return np.where(np.isfinite(r), r, 1e3)

    def jacobian(p: NDArray, k2: float, with_k2: bool) -> NDArray:
        """``(2N, [1 +] 8 + 2 deg)`` d residuals / d ([k2,] H, shutter), analytic (finite
        differences cost 13 evaluations per iteration, and the robust fit takes hundreds)."""
        _, xn, q, h = forward(p, k2)
        x, y, z = xn[:, 0], xn[:, 1], q[:, 2]
        pu, pv = q[:, 0] / z, q[:, 1] / z
        inv = base_scale / z
        j = np.zeros((n, 2, 8 + 2 * deg))
        j[:, 0, 0], j[:, 0, 1], j[:, 0, 2] = x * inv, y * inv, inv
        j[:, 1, 3], j[:, 1, 4], j[:, 1, 5] = x * inv, y * inv, inv
        j[:, 0, 6], j[:, 0, 7] = -pu * x * inv, -pu * y * inv
        j[:, 1, 6], j[:, 1, 7] = -pv * x * inv, -pv * y * inv
        # d (base px) / d (normalised corrected x, y).
        dxy = np.empty((n, 2, 2))
        dxy[:, 0, 0] = (h[0, 0] - pu * h[2, 0]) * inv
        dxy[:, 0, 1] = (h[0, 1] - pu * h[2, 1]) * inv
        dxy[:, 1, 0] = (h[1, 0] - pv * h[2, 0]) * inv
        dxy[:, 1, 1] = (h[1, 1] - pv * h[2, 1]) * inv
        j[:, :, 8 : 8 + deg] = dxy[:, :, 0:1] * (shift_unit / corr_scale)[:, None, :]
        j[:, :, 8 + deg :] = dxy[:, :, 1:2] * (shift_unit / corr_scale)[:, None, :]
        if with_k2:
            den = 1.0 - camera.gamma * u_raw - k2 * u_raw * u_raw
            with np.errstate(invalid="ignore", divide="ignore"):
                dc = r_n * d_raw * (0.5 * u_raw * u_raw / (den * np.sqrt(den)))[:, None]
            dk = np.einsum("nij,nj->ni", dxy, dc / corr_scale)
            j = np.concatenate([dk[:, :, None], j], axis=2)
        j = j.reshape(2 * n, -1)
        # A point without a corrected position has NaN rows here, where residuals() gives it a
        # constant 1000 px: its derivative is 0.
        j[~np.isfinite(j)] = 0.0
        return j

    start, _ = cv2.findHomography(
        (camera.with_k2(0.0).corrected_from_raw(raw_xy) - corr_mean) / corr_scale,
        (base_xy - base_mean) / base_scale,
        0,
    )
    if start is None or not np.isfinite(start).all() or abs(start[2, 2]) < 1e-12:
        return _none(n, "k2 not estimated: no homography fits the control points")
    p0 = np.r_[(start / start[2, 2]).ravel()[:8], np.zeros(2 * deg)]
    x_scale = np.ones(len(p0))

    harris = least_squares(
        residuals, p0, jac=lambda p, k2: jacobian(p, k2, False), x_scale=x_scale, args=(0.0,),
        method="lm",
    )  # fmt: skip
    r0 = np.hypot(*(predict(harris.x, 0.0) - base_xy).T)
    # Robust scale: residuals beyond a few of it (moved cars, shadows, mismatches) count less.
    f_scale = max(0.5, 1.4826 * float(np.median(np.abs(r0 - np.median(r0)))) * 2.0)
    fit = least_squares(
        lambda q: residuals(q[1:], q[0]), np.r_[0.0, harris.x],
        jac=lambda q: jacobian(q[1:], q[0], True), x_scale=np.r_[0.01, x_scale],
        loss="soft_l1", f_scale=f_scale, method="trf",
    )  # fmt: skip
    k2 = float(fit.x[0])
    r1 = np.hypot(*(predict(fit.x[1:], k2) - base_xy).T)
    m, n_par = 2 * n, len(fit.x)
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * (2.0 * fit.cost / max(m - n_par, 1))
        sigma = float(np.sqrt(max(cov[0, 0], 0.0)))
    except np.linalg.LinAlgError:
        sigma = float("inf")
    rms0, rms1 = _trimmed_rms(r0), _trimmed_rms(r1)
    summary = (
        f"k2 {k2:+.4f} ± {sigma:.4f} from {n} control points (RMS {rms0:.3f} -> {rms1:.3f} px)"
    )
    found = LensEstimate(k2, sigma, rms0, rms1, n, True, summary, f"{summary}: used")
    if not (np.isfinite(k2) and np.isfinite(sigma)):
        return found.refused("the fit did not converge")
    if abs(k2) > config.max_abs_k2:
        return found.refused(f"beyond ±{config.max_abs_k2:g}, not used")
    if camera.with_k2(k2).lens.validity_problem() is not None:
        return found.refused("not a valid lens on the frame, not used")
    if abs(k2) < config.min_abs_k2:
        return found.refused(
            f"below {config.min_abs_k2:g}, where relief displacement looks alike, Harris kept"
        )
    if abs(k2) < config.min_significance * sigma:
        return found.refused(f"not significant (< {config.min_significance:g} sigma), Harris kept")
    if rms1 > (1.0 - config.min_rms_reduction) * rms0:
        return found.refused(
            f"explains less than {config.min_rms_reduction:.0%} of the residual, Harris kept"
        )
    return found
