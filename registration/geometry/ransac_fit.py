"""RANSAC (paper 4.3.1): the best model of a class in the presence of false matches, with an
adaptive trial count, batched scoring and a refinement of the winner.

Both are generic over the :class:`registration.geometry.estimation.GeometricModel` protocol: a model class
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
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.geometry.fit_result import FitResult, _failed, _pairs, _safe_residuals

log = logging.getLogger(__name__)


_REFINES = ("nelder-mead", "lm", "lstsq", "none")


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
    min_inliers, fs, fd, k_random = _sample_layout(model_type, config, fixed)
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

    model, r, inl = _refit_consensus(s, d, model_type, best_model, best_inl, best_count, config)
    return FitResult(model, inl, r, trial, True, "", tuple(history))


def _sample_layout(
    model_type: Any, config: RansacConfig, fixed: tuple[ArrayLike, ArrayLike] | None
) -> tuple[int, NDArray, NDArray, int]:
    """``(min_inliers, fixed_src, fixed_dst, k_random)``: the fewest inliers that count as
    success (``config.min_inliers``, at least ``min_samples + 1``), the ``(M, 2)`` fixed pairs
    that join every sample (``(0, 2)`` without), and how many random pairs complete a sample.

    Raises:
        ValueError: ``sample_size`` below the model's ``min_samples``, or no room left in a
            sample beside the fixed pairs.
    """
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
    return min_inliers, fs, fd, k - len(fs)


def _refit_consensus(
    s: NDArray,
    d: NDArray,
    model_type: Any,
    best_model: Any,
    best_inl: NDArray[np.bool_],
    best_count: int,
    config: RansacConfig,
) -> tuple[Any, NDArray[np.float64], NDArray[np.bool_]]:
    """The best sample's model refitted on its ``best_inl`` inliers with ``config.refine``
    (started from it), and its ``(N,)`` residuals (destination px) and inliers on the ``(N, 2)``
    pairs ``s`` -> ``d``; the sample's own model when the refit fails or loses consensus."""
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
    return model, r, inl
