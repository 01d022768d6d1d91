"""REQCON (paper 4.3.2, 4.4): successive optimisations with mismatch removal, the worst points
dropped until the rest fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.geometry.fit_result import FitResult, _failed, _pairs, _safe_residuals

_OPTIMIZERS = ("nelder-mead", "lm", "lstsq")


@dataclass(frozen=True)
class ReqconConfig:
    """REQCON settings (paper 4.3.2 unless noted).

    Attributes:
        drop_fraction: fraction of the kept points removed per iteration, worst residuals first
            (paper: 0.05). At least one point is removed per iteration.
        target_mean_error_px: stop when the mean residual of the kept points is below this,
            destination pixels (paper: 2). Smaller is stricter.
        optimizer: inner fit: ``"nelder-mead"`` (paper), ``"lm"`` (same minimum, far faster) or
            ``"lstsq"`` (linear only; for tests and comparison).
        min_points: fewest points REQCON may keep; ``None`` means ``3 * model.min_samples``
            (not in the paper: a guard against collapsing onto a few points).
        min_fraction: also keep at least this fraction of the input (not in the paper).
        max_iterations: upper bound on fit-and-drop rounds (not in the paper; 0.95^100 ~ 0.6 %).
        stop: ``"mean"`` (the paper): drop the worst ``drop_fraction`` each round until the mean
            residual is below ``target_mean_error_px``; failure when the guard is reached first.
            ``"outliers"`` (beyond the paper): a model that cannot represent the data exactly
            (a lens beyond its model, a rolling shutter) may never reach an absolute target,
            and the paper's rule then drops good points until the guard fails the frame. Here
            REQCON also stops, successfully, once no kept point lies beyond
            ``outlier_sigmas`` robust standard deviations (so dropping no longer removes
            outliers), drops only such points (at most ``drop_fraction`` of them per round,
            worst first), and succeeds at the guard too. The robust scale is the Rayleigh one
            of 2-D residuals, ``median / sqrt(2 ln 2)``, also reported as the fit's quality
            (``FitResult.sigma_px``). Where the mean target is met first, both rules agree.
        outlier_sigmas: the ``"outliers"`` rule's threshold in robust standard deviations; None
            = ``sqrt(2 ln(n / 0.01))``, beyond which a Rayleigh sample of ``n`` right points
            reaches with probability ~1 % only (4.9 for 2000 points).
    """

    drop_fraction: float = 0.05
    target_mean_error_px: float = 2.0
    optimizer: str = "nelder-mead"
    min_points: int | None = None
    min_fraction: float = 0.1
    max_iterations: int = 100
    stop: str = "mean"
    outlier_sigmas: float | None = None

    def __post_init__(self) -> None:
        if not (0 < self.drop_fraction < 1):
            raise ValueError(f"drop_fraction must be in (0, 1), got {self.drop_fraction}")
        if not (self.target_mean_error_px > 0):
            raise ValueError(f"target_mean_error_px must be > 0, got {self.target_mean_error_px}")
        if self.optimizer not in _OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {_OPTIMIZERS}, got {self.optimizer!r}")
        if self.min_points is not None and self.min_points < 1:
            raise ValueError(f"min_points must be >= 1 or None, got {self.min_points}")
        if not (0 <= self.min_fraction < 1):
            raise ValueError(f"min_fraction must be in [0, 1), got {self.min_fraction}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if self.stop not in ("mean", "outliers"):
            raise ValueError(f"stop must be 'mean' or 'outliers', got {self.stop!r}")
        if self.outlier_sigmas is not None and not self.outlier_sigmas > 0:
            raise ValueError(f"outlier_sigmas must be > 0 or None, got {self.outlier_sigmas}")


# Median of a Rayleigh distribution of unit scale: the length of a 2-D residual whose
# components are independent unit Gaussians has median sqrt(2 ln 2).
_RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


def reqcon(
    src: ArrayLike,
    dst: ArrayLike,
    initial_model: Any,
    config: ReqconConfig = ReqconConfig(),
    *,
    domain: ArrayLike | None = None,
    noise_scale: ArrayLike | None = None,
) -> FitResult:
    """REQCON (paper 4.3.2): fit, drop the worst points, refit, until the kept points fit well.

    Round ``i``: fit ``type(initial_model)`` to the kept points with ``config.optimizer``, warm
    started from the previous round's model (round 1 from ``initial_model``; its degree and
    normalisation are kept); if the kept points' mean residual is below
    ``target_mean_error_px``, stop with success; otherwise drop the worst
    ``max(1, ceil(drop_fraction * n_kept))`` kept points and go on.

    Args:
        src, dst: ``(N, 2)`` pixel coordinates of corresponding points (non-finite pairs are
            never kept).
        initial_model: starting model, e.g. ``PolyProjective.from_projective(coarse.rescaled(4, 4))``.
        config: see :class:`ReqconConfig`.
        domain: optional ``(M, 2)`` source pixels where the model must stay defined, passed to
            the model's ``estimate`` (polyprojective: the whole frame).
        noise_scale: optional ``(N,)`` positive: how much noisier each point's measurement is
            expected to be than a typical one (beyond the paper). The worst points are then
            those of largest ``residual / noise_scale``, and the ``"outliers"`` rule judges
            that against its robust scale, so that points that are merely less precise
            (templates where a radial correction stretched the frame) are not dropped as
            outliers of the precise ones; scaled to median 1 here (``sigma_px`` is then that
            of a median point).

    Returns:
        :class:`FitResult` with ``inliers`` = the kept points, ``history`` = the mean residual of
        the kept points after each round. Fails (falsy, with reason) when dropping would leave
        fewer than the guard's points, when a fit fails, or after ``max_iterations`` rounds.
    """
    s, d = _pairs(src, dst)
    n = len(s)
    guard = _guard_points(initial_model, n, config)
    kept = np.isfinite(s).all(axis=1) & np.isfinite(d).all(axis=1)
    if kept.sum() < guard:
        return _failed(
            n,
            f"needs at least {guard} finite point pairs (min_points guard), got {int(kept.sum())}",
            0,
        )
    scale = _median_one_scale(noise_scale, kept, n)
    model = initial_model
    history: list[float] = []
    n_valid = int(kept.sum())
    k_sigma = config.outlier_sigmas or math.sqrt(2 * math.log(max(n_valid, 2) / 0.01))
    for it in range(1, config.max_iterations + 1):
        extra = {} if domain is None else {"domain": domain}
        fit = type(initial_model).estimate(
            s[kept], d[kept], initial=model, optimizer=config.optimizer, **extra
        )
        if not fit:
            return _failed(
                n,
                f"fit failed in round {it} on {int(kept.sum())} points: {fit.reason}",
                it,
                model,
                inliers=kept.copy(),
                residuals=_safe_residuals(model, s, d),
                history=tuple(history),
            )
        model = fit
        r = _safe_residuals(model, s, d)
        rs = r / scale
        history.append(float(np.mean(r[kept])))
        done, n_drop = _end_of_round(model, r, rs, kept, it, history, guard, k_sigma, config)
        if done is not None:
            return done
        _drop_worst(kept, rs, n_drop)
    return _after_last_round(model, s, d, kept, scale, history, config)


def _guard_points(initial_model: Any, n: int, config: ReqconConfig) -> int:
    """The fewest points REQCON may keep of ``n``: ``min_points`` (default three times the
    model's ``min_samples``), ``min_fraction`` of ``n`` and ``min_samples``, whichever is most."""
    min_s = int(getattr(initial_model, "min_samples", 1))  # instance: degree-aware
    return max(
        config.min_points if config.min_points is not None else 3 * min_s,
        math.ceil(config.min_fraction * n),
        min_s,
    )


def _median_one_scale(noise_scale: ArrayLike | None, kept: NDArray[np.bool_], n: int) -> NDArray:
    """``(n,)`` the points' noise scale (ones when None) divided by its median over the ``kept``
    points; ValueError unless it is ``(n,)`` and positive there."""
    scale = np.ones(n) if noise_scale is None else np.asarray(noise_scale, np.float64).ravel()
    if scale.shape != (n,) or not (scale[kept] > 0).all():
        raise ValueError(f"reqcon: noise_scale must be ({n},) and positive, got {scale.shape}")
    return scale / float(np.median(scale[kept]))


def _end_of_round(
    model: Any,
    r: NDArray,
    rs: NDArray,
    kept: NDArray[np.bool_],
    it: int,
    history: list[float],
    guard: int,
    k_sigma: float,
    config: ReqconConfig,
) -> tuple[FitResult | None, int]:
    """After round ``it``'s fit: stop (with the result) or how many points to drop.

    Args:
        r, rs: ``(N,)`` residuals, destination px, and the same over the noise scale.
        kept: ``(N,)`` the points the round fitted; ``history``: the mean residual of the kept
            points after each round, this one last.
        guard: fewest points to keep; ``k_sigma``: the ``"outliers"`` rule's threshold in
            robust standard deviations.

    Returns:
        ``(result, 0)`` to stop: success when the mean target is met (or, with the
        ``"outliers"`` rule, no outlier is left or the guard is reached), failure when dropping
        would go below the guard; ``(None, n_drop)`` to drop ``n_drop`` points and go on.
    """
    mean_kept = history[-1]
    sigma = float(np.median(rs[kept])) / _RAYLEIGH_MEDIAN
    n_kept = int(kept.sum())
    n_drop = max(1, math.ceil(config.drop_fraction * n_kept))
    if mean_kept < config.target_mean_error_px:
        return FitResult(model, kept.copy(), r, it, True, "", tuple(history), sigma), 0
    if config.stop == "outliers":
        n_out = int(np.count_nonzero(rs[kept] > k_sigma * sigma))
        if n_out == 0:
            return FitResult(model, kept.copy(), r, it, True, "", tuple(history), sigma), 0
        n_drop = min(n_drop, n_out)
    if config.stop == "outliers" and n_kept - n_drop < guard:
        # The guard protects against collapse; reaching it is the answer, not a failure.
        return FitResult(model, kept.copy(), r, it, True, "", tuple(history), sigma), 0
    if n_kept - n_drop < guard:
        failed = _failed(
            len(r),
            f"mean error {mean_kept:.3g} px of {n_kept} kept points is still above "
            f"{config.target_mean_error_px} px, and dropping {n_drop} more would go below "
            f"the guard of {guard} points",
            it,
            model,
            inliers=kept.copy(),
            residuals=r,
            history=tuple(history),
        )
        return failed, 0
    return None, n_drop


def _drop_worst(kept: NDArray[np.bool_], rs: NDArray, n_drop: int) -> None:
    """Clear ``kept`` (in place) at the ``n_drop`` kept points of largest ``rs``."""
    kept_idx = np.flatnonzero(kept)
    # Stable sort so that ties drop deterministically (lowest index kept).
    worst = kept_idx[np.argsort(-rs[kept_idx], kind="stable")[:n_drop]]
    kept[worst] = False


def _after_last_round(
    model: Any,
    s: NDArray,
    d: NDArray,
    kept: NDArray[np.bool_],
    scale: NDArray,
    history: list[float],
    config: ReqconConfig,
) -> FitResult:
    """The result after ``max_iterations`` rounds without stopping: success with the
    ``"outliers"`` rule (its robust scale from the kept points), failure with ``"mean"``."""
    if config.stop == "outliers":
        r = _safe_residuals(model, s, d)
        sigma = float(np.median((r / scale)[kept])) / _RAYLEIGH_MEDIAN
        return FitResult(
            model, kept.copy(), r, config.max_iterations, True, "", tuple(history), sigma
        )
    return _failed(
        len(s),
        f"mean error still {history[-1]:.3g} px after {config.max_iterations} rounds",
        config.max_iterations,
        model,
        inliers=kept.copy(),
        residuals=_safe_residuals(model, s, d),
        history=tuple(history),
    )
