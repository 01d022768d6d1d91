"""Drawing helpers that return arrays (no GUI): heat maps with a colour bar, blends, checkerboards.

Shared by the browser app and by debugging scripts. Images are ``(H, W, 3)`` uint8 RGB unless
named otherwise; RGBA outputs are ``(H, W, 4)`` uint8.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

COLORMAPS = {"turbo": cv2.COLORMAP_TURBO, "viridis": cv2.COLORMAP_VIRIDIS, "jet": cv2.COLORMAP_JET}


def _check_image(image: NDArray, name: str) -> NDArray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] not in (3, 4) or image.dtype != np.uint8:
        raise ValueError(
            f"{name} must be an (H, W, 3|4) uint8 image, got {image.shape} {image.dtype}"
        )
    return image


def colorize(
    values: ArrayLike,
    vmin: float,
    vmax: float,
    *,
    cmap: str = "turbo",
    alpha: int = 160,
) -> NDArray[np.uint8]:
    """Scalar field ``(H, W)`` -> RGBA heat map; NaN cells are fully transparent.

    Args:
        values: ``(H, W)`` float array (e.g. displacement magnitude in pixels).
        vmin, vmax: value range mapped to the colour map's ends (values outside are clipped).
        cmap: one of :data:`COLORMAPS`.
        alpha: opacity 0..255 of valid cells.
    """
    if cmap not in COLORMAPS:
        raise ValueError(f"cmap must be one of {sorted(COLORMAPS)}, got {cmap!r}")
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2:
        raise ValueError(f"values must be 2-D, got shape {v.shape}")
    if not vmax > vmin:
        vmax = vmin + 1e-9
    valid = np.isfinite(v)
    t = np.clip((np.where(valid, v, vmin) - vmin) / (vmax - vmin), 0, 1)
    idx = np.round(t * 255).astype(np.uint8)
    bgr = cv2.applyColorMap(idx, COLORMAPS[cmap])
    rgba = np.empty(v.shape + (4,), np.uint8)
    rgba[..., :3] = bgr[..., ::-1]
    rgba[..., 3] = np.where(valid, alpha, 0)
    return rgba


def colorbar(
    vmin: float,
    vmax: float,
    *,
    label: str = "",
    cmap: str = "turbo",
    width: int = 320,
    height: int = 56,
    ticks: int = 5,
) -> NDArray[np.uint8]:
    """A horizontal colour bar with tick labels and a caption, as an RGB image."""
    img = np.full((height, width, 3), 255, np.uint8)
    margin = 14
    bar_h = max(8, height // 3)
    ramp = np.linspace(0, 1, width - 2 * margin)[None, :].repeat(bar_h, 0)
    img[4 : 4 + bar_h, margin : width - margin] = colorize(ramp, 0, 1, cmap=cmap, alpha=255)[
        ..., :3
    ]
    font = cv2.FONT_HERSHEY_SIMPLEX
    for i in range(ticks):
        f = i / (ticks - 1)
        x = int(round(margin + f * (width - 2 * margin - 1)))
        cv2.line(img, (x, 4 + bar_h), (x, 8 + bar_h), (0, 0, 0), 1)
        text = f"{vmin + f * (vmax - vmin):.3g}"
        (tw, th), _ = cv2.getTextSize(text, font, 0.35, 1)
        tx = min(max(0, x - tw // 2), width - tw)
        cv2.putText(img, text, (tx, 10 + bar_h + th), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    if label:
        cv2.putText(img, label, (margin, height - 4), font, 0.38, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def blend(a: NDArray, b: NDArray, alpha: float, mask: ArrayLike | None = None) -> NDArray[np.uint8]:
    """``alpha * a + (1 - alpha) * b`` for same-size RGB images; where ``mask`` is False, ``b``."""
    a = _check_image(a, "a")
    b = _check_image(b, "b")
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    out = cv2.addWeighted(a, float(alpha), b, 1.0 - float(alpha), 0.0)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        np.copyto(out, b, where=~m[..., None])
    return out


def checkerboard(
    a: NDArray, b: NDArray, tile: int = 64, mask: ArrayLike | None = None
) -> NDArray[np.uint8]:
    """Alternate square tiles of ``tile`` pixels from ``a`` and ``b`` (``b`` where mask is False)."""
    a = _check_image(a, "a")
    b = _check_image(b, "b")
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    if tile < 1:
        raise ValueError(f"tile must be >= 1 pixel, got {tile}")
    h, w = a.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    use_a = ((xx // tile + yy // tile) % 2) == 0
    if mask is not None:
        use_a &= np.asarray(mask, dtype=bool)
    return np.where(use_a[..., None], a, b)


def field_cells_image(
    vectors: ArrayLike, valid: ArrayLike, *, vmax: float | None = None, cmap: str = "turbo"
) -> tuple[NDArray[np.uint8], float]:
    """Displacement field grid ``(Gy, Gx, 2)`` -> RGBA heat map of its magnitude, one pixel per cell.

    Returns the image and the ``vmax`` used (the largest valid magnitude when not given).
    """
    vec = np.asarray(vectors, dtype=np.float64)
    ok = np.asarray(valid, dtype=bool) & np.isfinite(vec).all(axis=-1)
    mag = np.where(ok, np.hypot(vec[..., 0], vec[..., 1]), np.nan)
    if vmax is None:
        vmax = float(np.nanmax(mag)) if ok.any() else 1.0
        vmax = max(vmax, 1e-6)
    return colorize(mag, 0.0, vmax, cmap=cmap), vmax


def series_plot(
    values: ArrayLike,
    *,
    flagged: ArrayLike | None = None,
    current: int | None = None,
    width: int = 640,
    height: int = 160,
    label: str = "",
) -> tuple[NDArray[np.uint8], tuple[int, int]]:
    """A per-frame line plot as an RGB image, with flagged frames in red and a cursor.

    Returns the image and ``(x0, x1)``: the pixel columns of the first and last frame, so a click
    at column ``u`` means frame ``round((u - x0) / (x1 - x0) * (n - 1))``.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    n = len(v)
    img = np.full((height, width, 3), 255, np.uint8)
    x0, x1, top, bottom = 40, width - 10, 14, height - 18
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.rectangle(img, (x0, top), (x1, bottom), (200, 200, 200), 1)
    if label:
        cv2.putText(img, label, (x0, 10), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    if n == 0:
        return img, (x0, x1)
    finite = np.isfinite(v)
    vmax = float(np.nanmax(v)) if finite.any() else 1.0
    vmax = max(vmax, 1e-9) * 1.1
    xs = x0 + (np.arange(n) / max(n - 1, 1)) * (x1 - x0)
    ys = bottom - (np.where(finite, v, 0) / vmax) * (bottom - top)
    cv2.putText(img, f"{vmax / 1.1:.3g}", (2, top + 8), font, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "0", (28, bottom), font, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, f"{n - 1}", (x1 - 16, height - 4), font, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
    pts = np.stack([xs, ys], axis=1)
    for i in range(n - 1):
        if finite[i] and finite[i + 1]:
            p, q = pts[i], pts[i + 1]
            cv2.line(
                img, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), (30, 90, 200), 1, cv2.LINE_AA
            )
    flags = np.zeros(n, bool) if flagged is None else np.asarray(flagged, dtype=bool).ravel()
    for i in range(n):
        if not finite[i]:
            cv2.drawMarker(
                img, (int(xs[i]), bottom - 3), (120, 120, 120), cv2.MARKER_TILTED_CROSS, 6
            )
        elif flags[i]:
            cv2.circle(img, (int(xs[i]), int(ys[i])), 4, (220, 30, 30), -1, cv2.LINE_AA)
    if current is not None and 0 <= current < n:
        cx = int(round(xs[current]))
        cv2.line(img, (cx, top), (cx, bottom), (0, 160, 0), 1)
    return img, (x0, x1)
