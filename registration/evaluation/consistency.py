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

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.matching import gradient_magnitude, subpixel_peak, to_grey


@dataclass(frozen=True)
class ConsistencyConfig:
    """Settings of the image-only measurements. Lengths in raw frame px.

    Attributes:
        grid_px: spacing of the probe points in frame ``k``.
        template_px: side of the patch cut around each probe (odd).
        search_px: the patch is searched this far around the prediction in each direction; a
            prediction further off than this is not measured (it counts as a miss).
        margin_px: probes closer than this to the frame's border are left out.
        min_ncc: the correlation peak must reach this for a measurement to count.
        min_structure: the smaller eigenvalue of the patch's structure tensor (mean of the
            squared Scharr gradients / 16, grey levels² per px²) must reach this: along an edge
            the peak slides.
        peak_margin: a second peak more than 2 px from the first must be lower by this.
        exclude: raw-px boxes ``(x0, y0, x1, y1)`` whose probes are left out (a burnt-in logo).
        floor_threshold_px: the robust homography's inlier threshold for the floor.
    """

    grid_px: int = 24
    template_px: int = 31
    search_px: int = 8
    margin_px: int = 20
    min_ncc: float = 0.8
    min_structure: float = 40.0
    peak_margin: float = 0.05
    exclude: tuple[tuple[float, float, float, float], ...] = ()
    floor_threshold_px: float = 2.0

    def __post_init__(self) -> None:
        if self.template_px < 5 or self.template_px % 2 == 0:
            raise ValueError(f"template_px must be odd and at least 5, got {self.template_px}")
        for name in ("grid_px", "search_px", "margin_px"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")


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


def probe_grid(size: tuple[int, int], config: ConsistencyConfig) -> NDArray[np.float64]:
    """``(N, 2)`` raw px on a ``grid_px`` lattice inside the margin, outside ``exclude``."""
    w, h = size
    g, m = config.grid_px, max(config.margin_px, config.template_px // 2 + 1)
    xs = np.arange(m, w - m, g, dtype=np.float64)
    ys = np.arange(m, h - m, g, dtype=np.float64)
    p = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    keep = np.ones(len(p), bool)
    for x0, y0, x1, y1 in config.exclude:
        keep &= ~((p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1))
    return p[keep]


def structure_strength(grey: NDArray, points: NDArray, half: int) -> NDArray[np.float64]:
    """The smaller eigenvalue of the structure tensor of the ``(2 half + 1)²`` patch around each
    of ``points`` (integer px), grey levels² per px²: how well a patch pins both directions."""
    g = grey.astype(np.float32)
    gx = cv2.Scharr(g, cv2.CV_32F, 1, 0) / 16.0
    gy = cv2.Scharr(g, cv2.CV_32F, 0, 1) / 16.0
    k = 2 * half + 1
    sxx = cv2.boxFilter(gx * gx, -1, (k, k))
    syy = cv2.boxFilter(gy * gy, -1, (k, k))
    sxy = cv2.boxFilter(gx * gy, -1, (k, k))
    xi, yi = points[:, 0].astype(int), points[:, 1].astype(int)
    a, c, b = sxx[yi, xi], syy[yi, xi], sxy[yi, xi]
    return 0.5 * (a + c - np.sqrt((a - c) ** 2 + 4 * b * b)).astype(np.float64)


def _measure(
    grey_k: NDArray, grey_l: NDArray, p: NDArray, q: NDArray, config: ConsistencyConfig
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Where each patch of ``grey_k`` around ``p`` (integer px) lies in ``grey_l`` near ``q``."""
    half, r = config.template_px // 2, config.search_px
    hl, wl = grey_l.shape
    out = np.full((len(p), 2), np.nan)
    ok = np.zeros(len(p), bool)
    for i, ((px, py), (qx, qy)) in enumerate(zip(p.astype(int), q, strict=True)):
        cx, cy = int(round(qx)), int(round(qy))
        x0, y0 = cx - half - r, cy - half - r
        x1, y1 = cx + half + r + 1, cy + half + r + 1
        if x0 < 0 or y0 < 0 or x1 > wl or y1 > hl:
            continue
        tmpl = grey_k[py - half : py + half + 1, px - half : px + half + 1]
        ncc = cv2.matchTemplate(grey_l[y0:y1, x0:x1], tmpl, cv2.TM_CCOEFF_NORMED)
        _, best, _, (bx, by) = cv2.minMaxLoc(ncc)
        if not best >= config.min_ncc or bx in (0, 2 * r) or by in (0, 2 * r):
            continue  # weak, or on the search border (the true peak may lie outside)
        rival = ncc.copy()
        rival[max(0, by - 2) : by + 3, max(0, bx - 2) : bx + 3] = -1.0
        if rival.max() > best - config.peak_margin:
            continue  # two places look alike: the measurement is not unique
        dx, dy = subpixel_peak(ncc[by - 1 : by + 2, bx - 1 : bx + 2])[0]
        out[i] = (x0 + half + bx + dx, y0 + half + by + dy)
        ok[i] = True
    return out, ok


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
    h, w = grey_k.shape
    p = probe_grid((w, h), cfg)
    p = p[structure_strength(grey_k, p, cfg.template_px // 2) >= cfg.min_structure]
    n_probes = len(p)
    q = np.asarray(result.base_to_frame(k + step, result.frame_to_base(k, p, stage), stage))
    known = np.isfinite(q).all(axis=1)
    p, q = p[known], q[known]
    m, ok = _measure(grey_k, grey_l, p, q, cfg)
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
