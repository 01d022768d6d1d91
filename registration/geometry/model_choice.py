"""Choosing the simplest model the points support (beyond the paper): spatial cross-validation,
how much of the frame the points' hull covers, and the choice between a model and its simpler
relatives.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.geometry.fit_result import _pairs


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
