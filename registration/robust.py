"""Robust model fitting: RANSAC (paper 4.3.1) and REQCON (paper 4.3.2, 4.4).

Both are generic over the :class:`registration.models.GeometricModel` protocol: a model class
with ``min_samples`` and ``estimate(src, dst, *, initial, optimizer)`` returning a model or a
falsy ``FailedEstimation``, and models with ``residuals(src, dst)``. Both return a
:class:`FitResult` (falsy on failure, with a reason). Randomness is injected (``rng``); nothing
is printed.

References:
    Loveland & Rosten, section 4.3.1 (RANSAC: 4-point samples, 5 px inlier threshold, at most
    1000 iterations, Nelder-Mead refinement) and 4.3.2 (REQCON: fit, drop the worst 5 %, refit,
    until the mean error of the remaining points is below 2 px).
    Fischler & Bolles, "Random sample consensus", CACM 24(6), 1981 (adaptive trial count).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points

__all__ = [
    "FitResult",
    "cross_validated_error",
    "hull_coverage",
    "simplest_supported",
    "RansacConfig",
    "ReqconConfig",
    "adaptive_max_iterations",
    "ransac",
    "reqcon",
]

log = logging.getLogger(__name__)

_REFINES = ("nelder-mead", "lm", "lstsq", "none")
_OPTIMIZERS = ("nelder-mead", "lm", "lstsq")


@dataclass(frozen=True)
class RansacConfig:
    """RANSAC settings (paper 4.3.1 unless noted).

    Attributes:
        sample_size: points per random sample (paper 4.3.1: 4, the minimum for a projective).
            Must be at least the model's ``min_samples``.
        threshold_px: inlier threshold on the Euclidean residual, destination pixels (paper: 5).
            Smaller is stricter.
        max_iterations: upper bound on random samples (paper: 1000).
        confidence: probability of having drawn at least one all-inlier sample at which sampling
            stops early (standard adaptive RANSAC; not in the paper, which always ran 1000;
            1.0 disables early stopping).
        refine: optimiser for the final refit on the inliers: ``"nelder-mead"`` (paper),
            ``"lm"`` (Levenberg-Marquardt, same minimum, much faster), ``"lstsq"`` (linear
            only) or ``"none"`` (keep the best sample's model).
        min_inliers: fewest inliers of the final model that count as success (not in the paper;
            guards against accepting a random sample's model; raised to ``min_samples + 1``).
    """

    sample_size: int = 4
    threshold_px: float = 5.0
    max_iterations: int = 1000
    confidence: float = 0.999
    refine: str = "nelder-mead"
    min_inliers: int = 8

    def __post_init__(self) -> None:
        if self.sample_size < 1:
            raise ValueError(f"sample_size must be >= 1, got {self.sample_size}")
        if not (self.threshold_px > 0):
            raise ValueError(f"threshold_px must be > 0, got {self.threshold_px}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if not (0 < self.confidence <= 1):
            raise ValueError(f"confidence must be in (0, 1], got {self.confidence}")
        if self.refine not in _REFINES:
            raise ValueError(f"refine must be one of {_REFINES}, got {self.refine!r}")
        if self.min_inliers < 1:
            raise ValueError(f"min_inliers must be >= 1, got {self.min_inliers}")


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


@dataclass(frozen=True, eq=False)
class FitResult:
    """Outcome of a robust fit; truthy exactly when ``success``.

    Attributes:
        model: the final model (``None`` when no model could be fitted at all).
        inliers: ``(N,)`` bool over the input points: RANSAC inliers, or the points REQCON kept.
        residuals: ``(N,)`` Euclidean residuals of *all* input points under ``model``, pixels
            (NaN when there is no model).
        iterations: RANSAC samples drawn, or REQCON fit rounds.
        success: whether the fit met its criterion.
        reason: why it failed ("" on success).
        history: REQCON: mean residual of the kept points after each round (pixels);
            RANSAC: best inlier count after each improvement.
        sigma_px: REQCON: robust standard deviation of the kept points' residuals (pixels,
            Rayleigh scale ``median / sqrt(2 ln 2)``): the quality of the fit.
    """

    model: Any
    inliers: NDArray[np.bool_]
    residuals: NDArray[np.float64]
    iterations: int
    success: bool
    reason: str = ""
    history: tuple[float, ...] = field(default_factory=tuple)
    sigma_px: float = float("nan")

    def __bool__(self) -> bool:
        return bool(self.success)

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))


# Median of a Rayleigh distribution of unit scale: the length of a 2-D residual whose
# components are independent unit Gaussians has median sqrt(2 ln 2).
_RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


def adaptive_max_iterations(inlier_ratio: float, sample_size: int, confidence: float) -> float:
    """Samples needed to draw one all-inlier sample with probability ``confidence``.

    ``k = log(1 - confidence) / log(1 - w**s)``, rounded up. ``inf`` when ``w = 0``; ``0`` when
    ``w = 1`` or ``confidence = 0``.

    >>> adaptive_max_iterations(0.5, 4, 0.99)
    72.0
    """
    if not (0 <= inlier_ratio <= 1):
        raise ValueError(f"inlier_ratio must be in [0, 1], got {inlier_ratio}")
    if not (0 <= confidence <= 1):
        raise ValueError(f"confidence must be in [0, 1], got {confidence}")
    if confidence == 0:
        return 0.0
    p_good = inlier_ratio**sample_size
    if p_good <= 0:
        return math.inf
    if p_good >= 1:
        return 0.0
    if confidence >= 1:
        return math.inf
    return float(math.ceil(math.log1p(-confidence) / math.log1p(-p_good)))


def _pairs(src: ArrayLike, dst: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    s, d = as_points(src, "src"), as_points(dst, "dst")
    if s.shape != d.shape:
        raise ValueError(f"src and dst must have the same shape, got {s.shape} and {d.shape}")
    return s, d


def _failed(n: int, reason: str, iterations: int, model: Any = None, **kw: Any) -> FitResult:
    inl = kw.pop("inliers", np.zeros(n, dtype=bool))
    res = kw.pop("residuals", np.full(n, np.nan))
    return FitResult(model, inl, res, iterations, False, reason, **kw)


def _safe_residuals(model: Any, src: NDArray, dst: NDArray) -> NDArray[np.float64]:
    with np.errstate(all="ignore"):
        r = model.residuals(src, dst)
    return np.where(np.isfinite(r), r, np.inf)


def _search_serial(s, d, fs, fd, idx_all, model_type, k_random, config, gen):
    """One sample at a time through ``model_type.estimate`` (any model of the protocol)."""
    n = len(s)
    best_model, best_count, best_cost = None, -1, math.inf
    best_inl = np.zeros(n, dtype=bool)
    history: list[float] = []
    limit = float(config.max_iterations)
    trial = 0
    while trial < min(limit, config.max_iterations):
        trial += 1
        sample = gen.choice(idx_all, size=k_random, replace=False)
        model = model_type.estimate(np.vstack([fs, s[sample]]), np.vstack([fd, d[sample]]))
        if not model:
            continue
        r = _safe_residuals(model, s, d)
        inl = r < config.threshold_px
        count = int(inl.sum())
        cost = float(r[inl].sum())
        if count > best_count or (count == best_count and cost < best_cost):
            best_model, best_count, best_cost, best_inl = model, count, cost, inl
            history.append(float(count))
            limit = min(
                limit,
                adaptive_max_iterations(count / len(idx_all), k_random, config.confidence),
            )
    return best_model, best_count, best_inl, history, trial


# Hypotheses scored per batch by the vectorised search: large enough to amortise numpy's
# per-call cost, small enough that the adaptive stop wastes little.
_BATCH = 64


def _draw_samples(gen: np.random.Generator, idx_all: NDArray, k: int, b: int) -> NDArray:
    """``(b, k)`` samples of distinct indices from ``idx_all`` (rows with repeats redrawn)."""
    out = gen.integers(0, len(idx_all), size=(b, k))
    for _ in range(100):
        srt = np.sort(out, axis=1)
        bad = (srt[:, 1:] == srt[:, :-1]).any(axis=1) if k > 1 else np.zeros(b, bool)
        if not bad.any():
            break
        out[bad] = gen.integers(0, len(idx_all), size=(int(bad.sum()), k))
    return idx_all[out]


def _score(mats: NDArray, hs: NDArray, d: NDArray, thr: float) -> tuple[NDArray, NDArray]:
    """Inlier counts and summed inlier residuals of ``(b, 3, 3)`` matrices on the pairs
    ``hs`` (homogeneous source, ``(n, 3)``) -> ``d`` (``(n, 2)``)."""
    proj = hs @ mats.transpose(0, 2, 1)  # (b, n, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.hypot(proj[..., 0] / proj[..., 2] - d[:, 0], proj[..., 1] / proj[..., 2] - d[:, 1])
    r = np.where(np.isfinite(r) & (proj[..., 2] > 0), r, np.inf)
    inl = r < thr
    return inl.sum(axis=1), np.where(inl, r, 0.0).sum(axis=1)


# Above this many pairs, hypotheses are first scored on a fixed random subset of this size and
# only each batch's best few on all pairs (preemptive scoring): the inlier share of a subset
# estimates the whole set's closely enough to rank hypotheses, at a fraction of the cost.
_SUBSET = 256
_FULLY_SCORED = 4


def _search_batched(s, d, fs, fd, idx_all, model_type, k_random, config, gen):
    """The same search with ``model_type.minimal_batch`` fitting many samples at once (closed
    forms for the linear models, a batched DLT for the projective) and scoring them together
    (preemptively on a subset when there are many pairs); the best sample is then fitted again
    with ``estimate`` so that the result is the model the serial search would return for it."""
    n = len(s)
    hs_all = np.c_[s[idx_all], np.ones(len(idx_all))]
    d_all = d[idx_all]
    sub = None
    if len(idx_all) > 2 * _SUBSET:
        sub = np.sort(gen.choice(len(idx_all), _SUBSET, replace=False))
    best_count, best_cost, best_sample = -1, math.inf, None
    history: list[float] = []
    limit = float(config.max_iterations)
    trial = 0
    thr = config.threshold_px
    batch = 8  # grows to _BATCH: an easy problem stops after a few samples, as serially
    while trial < min(limit, config.max_iterations):
        b = int(min(batch, min(limit, config.max_iterations) - trial))
        batch = min(2 * batch, _BATCH)
        samples = _draw_samples(gen, idx_all, k_random, b)
        trial += b
        src_b = np.concatenate([np.broadcast_to(fs, (b, *fs.shape)), s[samples]], axis=1)
        dst_b = np.concatenate([np.broadcast_to(fd, (b, *fd.shape)), d[samples]], axis=1)
        mats, ok = model_type.minimal_batch(src_b, dst_b)
        if not ok.any():
            continue
        mats, samples = mats[ok], samples[ok]
        if sub is not None:
            pre, _ = _score(mats, hs_all[sub], d_all[sub], thr)
            top = np.argsort(-pre, kind="stable")[:_FULLY_SCORED]
            mats, samples = mats[top], samples[top]
        counts, costs = _score(mats, hs_all, d_all, thr)
        # Best of the batch: most inliers, then the smaller cost, then the earlier sample.
        j = int(np.lexsort((np.arange(len(counts)), costs, -counts))[0])
        if counts[j] > best_count or (counts[j] == best_count and costs[j] < best_cost):
            best_count, best_cost, best_sample = int(counts[j]), float(costs[j]), samples[j]
            history.append(float(best_count))
            limit = min(
                limit,
                adaptive_max_iterations(best_count / len(idx_all), k_random, config.confidence),
            )
    if best_sample is None:
        return None, -1, np.zeros(n, bool), history, trial
    model = model_type.estimate(np.vstack([fs, s[best_sample]]), np.vstack([fd, d[best_sample]]))
    if not model:
        return None, -1, np.zeros(n, bool), history, trial
    inl = _safe_residuals(model, s, d) < thr
    return model, int(inl.sum()), inl, history, trial


def ransac(
    src: ArrayLike,
    dst: ArrayLike,
    model_type: Any,
    config: RansacConfig = RansacConfig(),
    rng: np.random.Generator | int | None = None,
    *,
    fixed: tuple[ArrayLike, ArrayLike] | None = None,
) -> FitResult:
    """RANSAC over point pairs, then a refit of the best consensus set (paper 4.3.1).

    Each trial draws ``sample_size`` distinct pairs, fits ``model_type.estimate`` (linear) and
    counts the pairs within ``threshold_px``; degenerate samples (collinear, duplicate, folding)
    make ``estimate`` fail and are skipped. Ties in the inlier count go to the smaller sum of
    inlier residuals. Sampling stops after ``max_iterations`` or once
    :func:`adaptive_max_iterations` of the best inlier ratio is reached. The best model is refit
    on its inliers with ``config.refine`` (started from it), and the inliers are recomputed.

    Args:
        src, dst: ``(N, 2)`` pixel coordinates of corresponding points.
        model_type: a model class (e.g. ``Projective``) with ``min_samples`` and ``estimate``.
        config: see :class:`RansacConfig`.
        rng: seed or generator; the same seed gives the same result.
        fixed: optional ``(src, dst)`` pairs, ``(M, 2)`` each, that join every sample (beyond the
            paper: a clicked seed point makes a similarity a one-point sample). They only shape
            the samples: inliers, the consensus and the refit count the data pairs alone, so a
            fixed pair that is a few pixels off does not bias the final model.

    Returns:
        :class:`FitResult`; ``history`` holds the best inlier count after each improvement.
    """
    s, d = _pairs(src, dst)
    n = len(s)
    gen = np.random.default_rng(rng)
    k = config.sample_size
    min_s = int(model_type.min_samples)
    if k < min_s:
        raise ValueError(
            f"sample_size={k} is below {getattr(model_type, '__name__', model_type)}'s "
            f"min_samples={min_s}"
        )
    min_inliers = max(config.min_inliers, min_s + 1)
    fs = fd = np.zeros((0, 2))
    if fixed is not None:
        fs, fd = _pairs(*fixed)
        if len(fs) >= k:
            raise ValueError(f"{len(fs)} fixed pairs leave no room in samples of {k}")
    k_random = k - len(fs)
    finite = np.isfinite(s).all(axis=1) & np.isfinite(d).all(axis=1)
    idx_all = np.flatnonzero(finite)
    if len(idx_all) < max(k_random, min_inliers):
        return _failed(
            n,
            f"needs at least {max(k_random, min_inliers)} finite point pairs, got {len(idx_all)}",
            0,
        )

    search = _search_batched if hasattr(model_type, "minimal_batch") else _search_serial
    best_model, best_count, best_inl, history, trial = search(
        s, d, fs, fd, idx_all, model_type, k_random, config, gen
    )
    if best_model is None:
        return _failed(
            n, f"all {trial} samples were degenerate (collinear or duplicate points)", trial
        )
    if best_count < min_inliers:
        return _failed(
            n,
            f"no consensus: the best of {trial} samples has {best_count} inliers within "
            f"{config.threshold_px} px of {len(idx_all)} pairs (needs {min_inliers})",
            trial,
            best_model,
            inliers=best_inl,
            residuals=_safe_residuals(best_model, s, d),
            history=tuple(history),
        )

    model = best_model
    if config.refine != "none":
        refit = model_type.estimate(
            s[best_inl],
            d[best_inl],
            initial=None if config.refine == "lstsq" else best_model,
            optimizer=config.refine,
        )
        if refit:
            model = refit
        else:
            log.debug("RANSAC refit on %d inliers failed: %s", best_count, refit.reason)
    r = _safe_residuals(model, s, d)
    inl = r < config.threshold_px
    if inl.sum() < best_count and model is not best_model:
        # The refit lost consensus (it should not); keep the sample's model.
        model = best_model
        r = _safe_residuals(model, s, d)
        inl = r < config.threshold_px
    return FitResult(model, inl, r, trial, True, "", tuple(history))


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
    model_type = type(initial_model)
    min_s = int(getattr(initial_model, "min_samples", 1))  # instance: degree-aware
    guard = max(
        config.min_points if config.min_points is not None else 3 * min_s,
        math.ceil(config.min_fraction * n),
        min_s,
    )
    kept = np.isfinite(s).all(axis=1) & np.isfinite(d).all(axis=1)
    if kept.sum() < guard:
        return _failed(
            n,
            f"needs at least {guard} finite point pairs (min_points guard), got {int(kept.sum())}",
            0,
        )
    scale = np.ones(n) if noise_scale is None else np.asarray(noise_scale, np.float64).ravel()
    if scale.shape != (n,) or not (scale[kept] > 0).all():
        raise ValueError(f"reqcon: noise_scale must be ({n},) and positive, got {scale.shape}")
    scale = scale / float(np.median(scale[kept]))
    model = initial_model
    history: list[float] = []
    n_valid = int(kept.sum())
    k_sigma = config.outlier_sigmas or math.sqrt(2 * math.log(max(n_valid, 2) / 0.01))
    for it in range(1, config.max_iterations + 1):
        extra = {} if domain is None else {"domain": domain}
        fit = model_type.estimate(
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
        mean_kept = float(np.mean(r[kept]))
        sigma = float(np.median(rs[kept])) / _RAYLEIGH_MEDIAN
        history.append(mean_kept)
        n_kept = int(kept.sum())
        n_drop = max(1, math.ceil(config.drop_fraction * n_kept))
        if mean_kept < config.target_mean_error_px:
            return FitResult(model, kept.copy(), r, it, True, "", tuple(history), sigma)
        if config.stop == "outliers":
            n_out = int(np.count_nonzero(rs[kept] > k_sigma * sigma))
            if n_out == 0:
                return FitResult(model, kept.copy(), r, it, True, "", tuple(history), sigma)
            n_drop = min(n_drop, n_out)
        if config.stop == "outliers" and n_kept - n_drop < guard:
            # The guard protects against collapse; reaching it is the answer, not a failure.
            return FitResult(model, kept.copy(), r, it, True, "", tuple(history), sigma)
        if n_kept - n_drop < guard:
            return _failed(
                n,
                f"mean error {mean_kept:.3g} px of {n_kept} kept points is still above "
                f"{config.target_mean_error_px} px, and dropping {n_drop} more would go below "
                f"the guard of {guard} points",
                it,
                model,
                inliers=kept.copy(),
                residuals=r,
                history=tuple(history),
            )
        kept_idx = np.flatnonzero(kept)
        # Stable sort so that ties drop deterministically (lowest index kept).
        worst = kept_idx[np.argsort(-rs[kept_idx], kind="stable")[:n_drop]]
        kept[worst] = False
    if config.stop == "outliers":
        r = _safe_residuals(model, s, d)
        sigma = float(np.median((r / scale)[kept])) / _RAYLEIGH_MEDIAN
        return FitResult(
            model, kept.copy(), r, config.max_iterations, True, "", tuple(history), sigma
        )
    return _failed(
        n,
        f"mean error still {history[-1]:.3g} px after {config.max_iterations} rounds",
        config.max_iterations,
        model,
        inliers=kept.copy(),
        residuals=_safe_residuals(model, s, d),
        history=tuple(history),
    )


def spatial_folds(src: ArrayLike, cells: int = 3) -> NDArray[np.int64]:
    """``(N,)`` fold index of each point: the cell of a ``cells`` x ``cells`` grid over the
    points' bounding box it falls in (cells without points are no folds)."""
    pts = as_points(src, "src")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = np.maximum(hi - lo, 1e-9)
    ij = np.minimum(((pts - lo) / span * cells).astype(np.int64), cells - 1)
    return ij[:, 1] * cells + ij[:, 0]


def _refit(model: Any, src: NDArray, dst: NDArray, domain: NDArray | None) -> Any:
    """``model``'s type fitted to the pairs, started from ``model`` (least squares)."""
    kw = {} if domain is None or not hasattr(model, "degree") or model.degree < 2 else {
        "domain": domain
    }  # fmt: skip
    return type(model).estimate(src, dst, initial=model, optimizer="lm", **kw)


def cross_validated_error(
    model: Any, src: ArrayLike, dst: ArrayLike, *, cells: int = 3, domain: ArrayLike | None = None
) -> float:
    """Mean held-out residual (pixels) of ``model``'s type under spatial cross-validation.

    The points are split by a ``cells`` x ``cells`` grid over their extent; each cell is
    predicted by the model fitted to all the others (started from ``model``). Cells at the edge
    of the points are then predicted by extrapolation, which is exactly what a model does
    wherever the points do not reach (the corners of a frame over a map with no-data areas, or
    over another date whose buildings changed): a model whose extra terms only fit the points it
    saw predicts them badly. ``inf`` when a fold cannot be fitted.
    """
    s, d = _pairs(src, dst)
    dom = None if domain is None else as_points(domain, "domain")
    folds = spatial_folds(s, cells)
    held = np.full(len(s), np.nan)
    for f in np.unique(folds):
        out = folds == f
        if (~out).sum() <= len(np.asarray(model.params)):
            return math.inf
        fit = _refit(model, s[~out], d[~out], dom)
        if not fit:
            return math.inf
        with np.errstate(all="ignore"):
            held[out] = np.hypot(*(fit.apply(s[out]) - d[out]).T)
    held = np.where(np.isfinite(held), held, 1e6)
    return float(np.mean(held))


def hull_coverage(src: ArrayLike, probes: ArrayLike) -> float:
    """Share of the ``probes`` (e.g. the centres of a grid of cells over the frame) inside the
    convex hull of ``src``: how much of the frame the points span (1 = all of it)."""
    import cv2

    s, dom = as_points(src, "src"), as_points(probes, "probes")
    s = s[np.isfinite(s).all(axis=1)]
    if len(s) < 3:
        return 0.0
    hull = cv2.convexHull(s.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    if len(hull) < 3:
        return 0.0
    # Inside a convex polygon: on the same side of every edge.
    edge = np.roll(hull, -1, axis=0) - hull
    rel = dom[:, None, :] - hull[None, :, :]
    cross = edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]
    inside = (cross >= 0).all(axis=1) | (cross <= 0).all(axis=1)
    return float(np.mean(inside))


def simplest_supported(
    fits: list[tuple[str, Any]],
    src: ArrayLike,
    dst: ArrayLike,
    *,
    domain: ArrayLike | None = None,
    probes: ArrayLike | None = None,
    min_coverage: dict[str, float] | None = None,
    margin: float = 0.05,
) -> tuple[str, Any]:
    """The model of ``fits`` (``(name, model)`` pairs ordered from simplest to richest, each
    fitted to ``src -> dst``) with the smallest spatially cross-validated error
    (:func:`cross_validated_error`); a richer model must beat a simpler one by more than
    ``margin`` (relative) to be kept. Cross-validation tests extrapolation within the points'
    extent only; beyond it a richer model's extra terms are unchecked, so with ``probes`` (the
    centres of a grid of cells over where the model will be used, the frame) a model named in
    ``min_coverage`` is a candidate only when the points span at least that share of them
    (:func:`hull_coverage`). The first model is always a candidate. ``domain``: where a
    polyprojective must stay defined."""
    if not fits:
        raise ValueError("simplest_supported needs at least one fitted model")
    coverage = 1.0 if probes is None else hull_coverage(src, probes)
    need = min_coverage or {}
    best_name, best_model = fits[0]
    best_err = cross_validated_error(best_model, src, dst, domain=domain)
    for name, model in fits[1:]:
        if coverage < need.get(name, 0.0):
            continue
        err = cross_validated_error(model, src, dst, domain=domain)
        if err < (1.0 - margin) * best_err:
            best_name, best_model, best_err = name, model, err
    return best_name, best_model
