"""What a robust fit returns (:class:`FitResult`, falsy on failure with its reason), shared by
RANSAC and REQCON, and the input checks both make.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points


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
