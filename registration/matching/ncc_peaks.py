"""Peaks of normalised cross-correlation: sub-pixel refinement, the peak re-measured without
pixels that changed between the images (shadows, cars), and the template's structure centroid.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Literal

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray


def subpixel_peak(
    patches: NDArray, method: Literal["quadratic", "parabolic", "none"] = "quadratic"
) -> NDArray[np.float64]:
    """Sub-pixel offset of correlation peaks from their 3x3 neighbourhoods.

    Args:
        patches: ``(N, 3, 3)`` (or ``(3, 3)``) correlation values around integer maxima, row =
            y, column = x, the maximum at ``[1, 1]``.
        method: ``"quadratic"``: least-squares fit of ``f = c + g.u + u'Hu/2`` to the 9 values
            and its stationary point; falls back to ``"parabolic"`` where ``H`` is not negative
            definite. ``"parabolic"``: independent 3-point parabolas along x and y. ``"none"``.

    Returns:
        ``(N, 2)`` offsets ``(dx, dy)`` in pixels, each clipped to ``[-1, 1]``.
    """
    r = np.asarray(patches, np.float64)
    if r.shape == (3, 3):
        r = r[None]
    if r.ndim != 3 or r.shape[1:] != (3, 3):
        raise ValueError(f"patches must have shape (N, 3, 3), got {r.shape}")
    n = len(r)
    if method == "none":
        return np.zeros((n, 2))
    # Parabolic: vertex of the parabola through (-1, f-), (0, f0), (1, f+).
    fxm, fx0, fxp = r[:, 1, 0], r[:, 1, 1], r[:, 1, 2]
    fym, fyp = r[:, 0, 1], r[:, 2, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        den_x = fxm - 2 * fx0 + fxp
        den_y = fym - 2 * fx0 + fyp
        par = np.stack(
            [
                np.where(den_x < 0, 0.5 * (fxm - fxp) / den_x, 0.0),
                np.where(den_y < 0, 0.5 * (fym - fyp) / den_y, 0.0),
            ],
            axis=1,
        )
    if method == "parabolic":
        return np.clip(np.nan_to_num(par), -1, 1)
    if method != "quadratic":
        raise ValueError(f"method must be 'quadratic', 'parabolic' or 'none', got {method!r}")
    u = np.array([-1.0, 0.0, 1.0])
    ux = u[None, :].repeat(3, 0)  # column offset
    uy = u[:, None].repeat(3, 1)  # row offset
    # Orthogonal basis on the 3x3 grid: 1, x, y, xy, x^2 - 2/3, y^2 - 2/3.
    gx = (r * ux).sum(axis=(1, 2)) / 6
    gy = (r * uy).sum(axis=(1, 2)) / 6
    hxy = (r * ux * uy).sum(axis=(1, 2)) / 4
    hxx = (r * (ux**2 - 2 / 3)).sum(axis=(1, 2))  # = 2 * coefficient of x^2
    hyy = (r * (uy**2 - 2 / 3)).sum(axis=(1, 2))
    det = hxx * hyy - hxy**2
    ok = (hxx < 0) & (det > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = -(hyy * gx - hxy * gy) / det
        dy = -(hxx * gy - hxy * gx) / det
    quad = np.stack([dx, dy], axis=1)
    ok &= np.isfinite(quad).all(axis=1) & (np.abs(quad) <= 1).all(axis=1)
    out = np.where(ok[:, None], quad, par)
    return np.clip(np.nan_to_num(out), -1, 1)


def _refine_peak(
    tpl, window, config, mask_changes: bool = True
) -> tuple[float, tuple[float, float]] | None:
    """Step 4 for one template: the integer NCC peak over ``window``, its sub-pixel fit and
    ``dither_iterations`` dithered re-correlations; ``(score, (dx, dy))`` with the offset from
    the window's centre, or None when the peak is on the search range's border. With
    ``mask_changes`` and ``change_log_ratio``, all of it once more within +-CHANGE_SEARCH_PX of
    that peak without the pixels that changed between the template and the window there
    (:func:`_unchanged`)."""
    peak = _peak(tpl, window, config, None)
    if peak is None or not (mask_changes and config.change_log_ratio):
        return peak
    rad, r = config.search_radius, CHANGE_SEARCH_PX
    cx, cy = (int(round(v)) for v in peak[1])
    cx, cy = min(max(cx, r - rad), rad - r), min(max(cy, r - rad), rad - r)
    side = tpl.shape[0] + 2 * r
    crop = window[rad + cy - r : rad + cy - r + side, rad + cx - r : rad + cx - r + side]
    for _ in range(CHANGE_ROUNDS):
        # The changes are found where the previous peak put the template: the first peak is
        # pulled towards them, the masked one less, so a second round finds them better.
        keep = _unchanged(tpl, window, peak[1], config)
        if keep.mean() < config.change_min_share:
            break
        masked = _peak(tpl, crop, config, keep)
        if masked is None:  # the masked peak left the +-CHANGE_SEARCH_PX: keep the last
            break
        peak = masked[0], (masked[1][0] + cx, masked[1][1] + cy)
    return peak


# Blur (sigma, px) and dark offset (grey levels) of the change test: the blur keeps a sub-pixel
# misregistration of a sharp edge from looking like a change; the offset keeps noise in black
# pixels from making huge ratios. Changed pixels are widened by CHANGE_GROW_PX.
CHANGE_BLUR_PX = 0.8
CHANGE_DARK = 8.0
CHANGE_GROW_PX = 2
# How far (px) the masked peak is searched around the unmasked one, and how many times the
# changes are found again at the masked peak.
CHANGE_SEARCH_PX = 3
CHANGE_ROUNDS = 2
# Fits of the photometric line: the first to all pixels, each next to those it left unchanged.
CHANGE_FITS = 3


def _unchanged(tpl, window, offset: tuple[float, float], config) -> NDArray[np.bool_]:
    """``(T, T)`` bool over the template: True where the window placed at ``offset`` (bilinear)
    has the brightness the template predicts, within a natural-log ratio of
    ``config.change_log_ratio``. The prediction is a line (gain and offset: another sensor's
    exposure and haze) fitted between the two, again to the pixels it left unchanged: a
    constant ratio (gain only) calls a whole side of a hazy map's template changed."""
    half, rad = config.half_template, config.search_radius
    side = 2 * half + 1
    m = np.array([[1.0, 0.0, rad + offset[0]], [0.0, 1.0, rad + offset[1]]], np.float32)
    at_peak = cv2.warpAffine(
        window, m, (side, side), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )  # fmt: skip
    # float64: the fit sums ~1000 products, which float32 would round enough to move a pixel
    # across the threshold.
    a = cv2.GaussianBlur(tpl.astype(np.float32), (0, 0), CHANGE_BLUR_PX).ravel().astype(float)
    b = cv2.GaussianBlur(at_peak.astype(np.float32), (0, 0), CHANGE_BLUR_PX).ravel().astype(float)
    log_b = np.log(b + CHANGE_DARK)
    use = np.ones(a.size, bool)
    for _ in range(CHANGE_FITS):
        if use.sum() < 3:
            break
        ua, ub = a[use], b[use]
        ma, mb = float(ua.mean()), float(ub.mean())
        da = ua - ma
        gain = float(np.dot(da, ub - mb)) / max(float(np.dot(da, da)), 1e-6)
        pred = np.maximum(gain * (a - ma) + mb, 0.0)
        changed = np.abs(log_b - np.log(pred + CHANGE_DARK)) > config.change_log_ratio
        use = ~changed
    grow = np.ones((2 * CHANGE_GROW_PX + 1,) * 2, np.uint8)
    return cv2.dilate(changed.reshape(tpl.shape[:2]).astype(np.uint8), grow) == 0


def _peak(tpl, window, config, keep) -> tuple[float, tuple[float, float]] | None:
    """:func:`_refine_peak` over the template pixels where ``keep`` (bool, template shape) is
    True, or all of them (None); the search radius is ``window``'s margin around ``tpl``."""
    half = config.half_template
    rad = (window.shape[0] - tpl.shape[0]) // 2
    side = 2 * rad + 1
    if keep is None:
        res = cv2.matchTemplate(window, tpl, cv2.TM_CCOEFF_NORMED)
        if config.dither_iterations:  # not for the intra-sensor grid (no dither): a hot path
            tpl_unit = tpl.astype(np.float32).ravel()
            tpl_unit -= tpl_unit.mean()
            tpl_unit /= max(float(np.linalg.norm(tpl_unit)), 1e-12)
            near = partial(_ncc3x3, tpl_unit=tpl_unit)
    else:
        near = _masked_ncc(tpl, keep)
        res = near(window)
    _, best, _, (px, py) = cv2.minMaxLoc(res)
    if not (0 < px < side - 1 and 0 < py < side - 1):
        if config.reject_border_peaks:
            return None
        px, py = min(max(px, 1), side - 2), min(max(py, 1), side - 2)
    sx, sy = _peak3(res[py - 1 : py + 2, px - 1 : px + 2], config.subpixel)
    grow = 2 * half + 3  # template plus a +-1 px search, for the dithered re-correlation
    for _ in range(config.dither_iterations):
        # Resample the window so that the current estimate sits on the integer grid, then
        # correlate again over +-1 px; the peak fit is least biased near 0.
        m = np.array([[1.0, 0.0, px + sx - 1], [0.0, 1.0, py + sy - 1]], np.float32)
        sub = cv2.warpAffine(
            window, m, (grow, grow), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )  # fmt: skip
        res2 = near(sub)
        dx, dy = _peak3(res2, config.subpixel)
        sx, sy = sx + dx, sy + dy
        best = max(best, float(res2[1, 1]))
    return float(best), (px - rad + sx, py - rad + sy)


def _peak3(r: NDArray, method: str) -> tuple[float, float]:
    """Scalar twin of :func:`subpixel_peak` for one 3x3 neighbourhood (no numpy overhead)."""
    (a, b, c), (d, e, f), (g, h, i) = r.tolist()
    if method == "none":
        return 0.0, 0.0
    # Parabolic fallback: 3-point parabolas through the centre row and column.
    den_x, den_y = d - 2 * e + f, b - 2 * e + h
    px = 0.5 * (d - f) / den_x if den_x < 0 else 0.0
    py = 0.5 * (b - h) / den_y if den_y < 0 else 0.0
    if method == "quadratic":
        gx = ((c + f + i) - (a + d + g)) / 6
        gy = ((g + h + i) - (a + b + c)) / 6
        hxy = (a + i - c - g) / 4
        col_outer, col_mid = a + d + g + c + f + i, b + e + h
        row_outer, row_mid = a + b + c + g + h + i, d + e + f
        hxx = col_outer / 3 - 2 * col_mid / 3
        hyy = row_outer / 3 - 2 * row_mid / 3
        det = hxx * hyy - hxy * hxy
        if hxx < 0 and det > 0:
            qx = -(hyy * gx - hxy * gy) / det
            qy = -(hxx * gy - hxy * gx) / det
            if abs(qx) <= 1 and abs(qy) <= 1:
                return qx, qy
    return min(max(px, -1.0), 1.0), min(max(py, -1.0), 1.0)


def _structure_centroid(tpl: NDArray[np.uint8], ramp: NDArray[np.float32]) -> tuple[float, float]:
    """Offset from the template centre of its structure-tensor-weighted centroid
    ``M^-1 sum G(u) u`` (see ``TemplateConfig.anchor``), clipped to the template."""
    gx = cv2.Sobel(tpl, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(tpl, cv2.CV_32F, 0, 1, ksize=3)
    # Border rows/columns of Sobel see the reflected border; leave them out.
    gx, gy = gx[1:-1, 1:-1], gy[1:-1, 1:-1]
    u = ramp[1:-1]
    xx, xy, yy = gx * gx, gx * gy, gy * gy
    sxx, sxy, syy = float(xx.sum()), float(xy.sum()), float(yy.sum())
    mx = float(xx.sum(axis=0) @ u) + float(xy.sum(axis=1) @ u)
    my = float(xy.sum(axis=0) @ u) + float(yy.sum(axis=1) @ u)
    # Tikhonov term: along a straight edge M is singular and the centroid undefined there.
    eps = 1e-2 * (sxx + syy)
    a, d = sxx + eps, syy + eps
    det = a * d - sxy * sxy
    if not det > 0:
        return 0.0, 0.0
    h = float(ramp[-1])
    ox = (d * mx - sxy * my) / det
    oy = (a * my - sxy * mx) / det
    return min(max(ox, -h), h), min(max(oy, -h), h)


def _ncc3x3(sub: NDArray, tpl_unit: NDArray[np.float32]) -> NDArray[np.float32]:
    """TM_CCOEFF_NORMED of a template (given zero-mean, unit-norm, flattened) at the 3 x 3
    offsets of ``sub`` (template side + 2), as one matrix product: cheaper than matchTemplate,
    whose DFT set-up dominates for so few offsets."""
    n = tpl_unit.size
    side = sub.shape[0] - 2
    v = sliding_window_view(sub.astype(np.float32), (side, side)).reshape(9, n)
    num = v @ tpl_unit
    s1 = v.sum(axis=1)
    s2 = np.einsum("ij,ij->i", v, v)
    den = np.sqrt(np.maximum(s2 - s1 * s1 / n, 1e-12))
    return (num / den).reshape(3, 3)


def _masked_ncc(tpl: NDArray, keep: NDArray[np.bool_]) -> Callable[[NDArray], NDArray]:
    """TM_CCOEFF_NORMED of ``tpl`` over its ``keep`` pixels only (means and norms too) at every
    offset of a window, as a function of the window: three unnormalised correlations, which
    for a few offsets cost less than matchTemplate's masked path. -1 where the window is flat
    over the kept pixels."""
    mask = keep.astype(np.float32)
    n = float(mask.sum())
    t = tpl.astype(np.float32)
    t = (t - float((t * mask).sum()) / n) * mask
    t /= max(float(np.linalg.norm(t)), 1e-12)

    def ncc(window: NDArray) -> NDArray[np.float32]:
        w = window.astype(np.float32)
        num = cv2.matchTemplate(w, t, cv2.TM_CCORR)
        s1 = cv2.matchTemplate(w, mask, cv2.TM_CCORR)
        var = cv2.matchTemplate(w * w, mask, cv2.TM_CCORR) - s1 * s1 / n
        flat = var <= 1e-6 * n
        res = num / np.sqrt(np.where(flat, 1.0, var))
        res[flat] = -1.0
        return res

    return ncc
