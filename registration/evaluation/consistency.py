"""How well a registered sequence holds together, measured from the images alone (no truth):
for real video, where no simulator says where the ground is.

* **Frame-to-frame consistency** (:func:`pair_consistency`): ground points on a grid of raw frame
  ``k`` are carried into raw frame ``k + step`` through the registration and the map
  (``base_to_frame(k + step, frame_to_base(k, p))``); each point's patch of frame ``k`` is then
  found in frame ``k + step`` by normalised cross-correlation around that prediction, and the
  distance between prediction and measurement is the registration's inconsistency there. Only
  patches that pin both directions (the smaller eigenvalue of their structure tensor) and whose
  correlation peak is clear and single count, so edges and blank roofs do not slide.
* **The floor**: a homography fitted to the same measured points (frame ``k`` -> frame
  ``k + step``, robustly) leaves residuals from measurement noise, relief and the rolling
  shutter; a registration cannot be expected to beat what that fit leaves, so consistency is
  reported beside it.
* **Agreement with the map** (:func:`map_agreement`): the registered frame and the base map
  compared by normalised correlation of their gradient magnitudes in windows, the median over the
  windows where both have content and texture (another date and sensor share gradients, not grey
  levels).

Points are ``(N, 2)`` float64 ``(x, y)`` pixels with pixel centres at integer coordinates
(``conventions.md``). ``result`` is anything with the registration-result interface
(``frame_to_base``, ``base_to_frame``), a result folder or the simulator's truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.matching import (
    ProbeConfig,
    find_probes,
    gradient_magnitude,
    textured_probes,
    to_grey,
)


@dataclass(frozen=True)
class ConsistencyConfig:
    """Settings of the image-only measurements.

    Attributes:
        probes: where probes are cut in frame ``k`` and when a measurement in frame ``k + step``
            counts (:class:`registration.matching.ProbeConfig`), raw frame px.
        floor_threshold_px: the robust homography's inlier threshold for the floor.
    """

    probes: ProbeConfig = field(default_factory=ProbeConfig)
    floor_threshold_px: float = 2.0


@dataclass(frozen=True)
class PairConsistency:
    """Frame ``k`` carried into frame ``k + step``.

    Attributes:
        k, step: the pair.
        probes: ``(N, 2)`` raw px of frame ``k`` that were measured.
        predicted: ``(N, 2)`` raw px of frame ``k + step`` where the registration puts them.
        measured: ``(N, 2)`` where their patches are found there.
        errors: ``(N,)`` ``|predicted - measured|`` px.
        floor: ``(N,)`` residuals of a homography fitted to ``probes -> measured`` (NaN when
            fewer than 8 points).
        n_probes: probes that were textured enough to try.
    """

    k: int
    step: int
    probes: NDArray[np.float64]
    predicted: NDArray[np.float64]
    measured: NDArray[np.float64]
    errors: NDArray[np.float64]
    floor: NDArray[np.float64]
    n_probes: int


def _homography_floor(p: NDArray, m: NDArray, lens, threshold: float) -> NDArray[np.float64]:
    """Residuals (raw px) of a homography fitted to ``p -> m`` in corrected px (through
    ``lens``, None = raw px: a homography holds between views of a plane only once the lens is
    taken out), by RANSAC, then least squares on its inliers."""
    if len(p) < 8:
        return np.full(len(p), np.nan)
    pc, mc = (p, m) if lens is None else (lens.corrected_from_raw(p), lens.corrected_from_raw(m))
    h, inl = cv2.findHomography(pc, mc, cv2.RANSAC, threshold, maxIters=2000, confidence=0.999)
    if h is None:
        return np.full(len(p), np.nan)
    inl = inl.ravel().astype(bool)
    if inl.sum() >= 8:
        h, _ = cv2.findHomography(pc[inl], mc[inl], 0)
    pred = cv2.perspectiveTransform(pc.reshape(-1, 1, 2), h).reshape(-1, 2)
    if lens is not None:
        pred = lens.raw_from_corrected(pred)
    return np.hypot(*(pred - m).T)


def pair_consistency(
    result,
    grey_k: NDArray,
    grey_l: NDArray,
    k: int,
    step: int,
    *,
    stage: str = "local",
    config: ConsistencyConfig | None = None,
) -> PairConsistency:
    """Carry frame ``k``'s probes into frame ``k + step`` (module docstring).

    Args:
        result: a registration result (or the simulator's truth); its ``lens`` (raw <->
            corrected px), when it has one, takes the lens out before the floor's homography.
        grey_k, grey_l: raw frames ``k`` and ``k + step``, grey ``(H, W)`` uint8.
        stage: ``"global"`` or ``"local"``.
    """
    cfg = config or ConsistencyConfig()
    p = textured_probes(grey_k, cfg.probes)
    n_probes = len(p)
    q = np.asarray(result.base_to_frame(k + step, result.frame_to_base(k, p, stage), stage))
    known = np.isfinite(q).all(axis=1)
    p, q = p[known], q[known]
    m, ok = find_probes(grey_k, grey_l, p, q, cfg.probes)
    p, q, m = p[ok], q[ok], m[ok]
    return PairConsistency(
        k,
        step,
        p,
        q,
        m,
        np.hypot(*(q - m).T),
        _homography_floor(p, m, getattr(result, "lens", None), cfg.floor_threshold_px),
        n_probes,
    )


def summarise(pairs: list[PairConsistency]) -> dict:
    """Median and 90th percentile of the errors and of the floor over all points of ``pairs``,
    their ratio, and each frame's 90th percentile (``{"k": ..., "p90": ..., "floor_p90": ...}``)."""
    err = np.concatenate([c.errors for c in pairs]) if pairs else np.zeros(0)
    flo = np.concatenate([c.floor for c in pairs]) if pairs else np.zeros(0)
    flo = flo[np.isfinite(flo)]

    def pct(a: NDArray, q: float) -> float | None:
        return float(np.percentile(a, q)) if len(a) else None

    p90, f90 = pct(err, 90), pct(flo, 90)
    return {
        "n_pairs": len(pairs),
        "n_points": int(len(err)),
        "median_px": pct(err, 50),
        "p90_px": p90,
        "floor_median_px": pct(flo, 50),
        "floor_p90_px": f90,
        "p90_over_floor": p90 / f90 if p90 is not None and f90 else None,
        "per_frame": [
            {
                "k": c.k,
                "n": int(len(c.errors)),
                "p90_px": pct(c.errors, 90),
                "floor_p90_px": pct(c.floor[np.isfinite(c.floor)], 90),
            }
            for c in pairs
        ],
    }


def map_agreement(
    registered: NDArray,
    registered_valid: NDArray[np.bool_],
    base: NDArray,
    base_valid: NDArray[np.bool_] | None = None,
    *,
    window_px: int = 48,
    min_gradient: float = 4.0,
) -> float | None:
    """Median normalised correlation of the gradient magnitudes of a registered frame and the
    base map over ``window_px`` windows (both ``(H, W)`` in base px, same crop) where both have
    content everywhere and some texture (mean gradient ``min_gradient`` grey levels per px);
    None when no window qualifies."""
    a = gradient_magnitude(to_grey(registered)).astype(np.float64)
    b = gradient_magnitude(to_grey(base)).astype(np.float64)
    valid = np.asarray(registered_valid, bool)
    if base_valid is not None:
        valid = valid & np.asarray(base_valid, bool)
    h, w = a.shape
    scores = []
    for y in range(0, h - window_px + 1, window_px):
        for x in range(0, w - window_px + 1, window_px):
            if not valid[y : y + window_px, x : x + window_px].all():
                continue
            wa = a[y : y + window_px, x : x + window_px].ravel()
            wb = b[y : y + window_px, x : x + window_px].ravel()
            if wa.mean() < min_gradient or wb.mean() < min_gradient:
                continue
            wa, wb = wa - wa.mean(), wb - wb.mean()
            den = np.sqrt((wa @ wa) * (wb @ wb))
            if den > 0:
                scores.append(float(wa @ wb / den))
    return float(np.median(scores)) if scores else None
