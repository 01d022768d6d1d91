"""Figures of a registration: the displacement field's components as images (paper Fig. 5) and
semi-transparent overlays of a frame over the reference (paper Fig. 6).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.geometry import DisplacementField

# --------------------------------------------------------------------------------------------
# Field component images (paper Fig. 5)


def diverging_colormap(values: NDArray, limit: float) -> NDArray[np.uint8]:
    """Blue (-limit) - white (0) - red (+limit) BGR colours for ``values`` (NaN -> grey)."""
    t = np.clip(np.nan_to_num(values / max(limit, 1e-9)), -1.0, 1.0)
    pos = np.clip(t, 0, 1)
    neg = np.clip(-t, 0, 1)
    # BGR: red = (0, 0, 255), blue = (255, 0, 0); fade from white.
    b = 255 * (1 - pos)
    g = 255 * (1 - pos) * (1 - neg)
    r = 255 * (1 - neg)
    out = np.clip(np.stack([b, g, r], axis=-1), 0, 255).astype(np.uint8)
    out[~np.isfinite(values)] = (128, 128, 128)
    return out


def _legend(height: int, limit: float, title: str, width: int = 90) -> NDArray[np.uint8]:
    """A vertical colour bar ``(height, width, 3)`` from +limit (top) to -limit with ticks."""
    panel = np.full((height, width, 3), 255, np.uint8)
    top, bottom = 28, max(height - 12, 40)
    bar_h = max(bottom - top, 2)
    vals = np.linspace(limit, -limit, bar_h)[:, None] * np.ones((1, 18))
    panel[top : top + bar_h, 8:26] = diverging_colormap(vals, limit)
    cv2.rectangle(panel, (8, top), (25, top + bar_h - 1), (0, 0, 0), 1)
    cv2.putText(panel, title, (4, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for frac, v in ((0.0, limit), (0.5, 0.0), (1.0, -limit)):
        y = int(round(top + frac * (bar_h - 1)))
        cv2.line(panel, (26, y), (31, y), (0, 0, 0), 1)
        cv2.putText(
            panel,
            f"{v:+.2f}" if v else "0",
            (33, y + 4),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return panel


def field_component_images(
    field: DisplacementField,
    width: int,
    height: int,
    origin: tuple[float, float] = (0.0, 0.0),
    *,
    limit_px: float | None = None,
    legend: bool = True,
    show_nodes: bool = True,
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """The interpolated field's horizontal and vertical components as images (paper Fig. 5).

    Args:
        field: the displacement field.
        width, height, origin: the base crop to draw (e.g. the frame's footprint box).
        limit_px: colour scale +-limit px for both images (None = per component, the largest
            magnitude among the measured vectors, at least 0.5 px; larger values saturate).
        legend: append a colour bar with the scale in px on the right.
        show_nodes: mark the grid nodes (filled dot: measured; ring: filled from neighbours).

    Returns:
        ``(u_img, v_img)`` BGR uint8 ``(height, width [+ legend], 3)``; grey outside the field.
    """
    d = field.dense(width, height, origin)
    # Scale to the measured vectors: filled cells at the edge of a footprint can carry
    # extrapolated values that would wash out the colours of the rest.
    vec = field.vectors[field.valid] if field.valid.any() else field.vectors.reshape(-1, 2)
    images = []
    for c, title in ((0, "dx px"), (1, "dy px")):
        limit = limit_px if limit_px is not None else float(max(np.abs(vec[:, c]).max(), 0.5))
        img = diverging_colormap(d[..., c], limit)
        if show_nodes:
            nodes = field.node_xy.reshape(-1, 2) - np.asarray(origin)
            for (x, y), ok in zip(nodes, field.valid.ravel(), strict=True):
                if 0 <= x < width and 0 <= y < height:
                    p = (int(round(x)), int(round(y)))
                    cv2.circle(img, p, 3, (0, 0, 0), -1 if ok else 1, cv2.LINE_AA)
        if legend:
            img = np.concatenate([img, _legend(height, limit, title)], axis=1)
        images.append(img)
    return images[0], images[1]


# --------------------------------------------------------------------------------------------
# Overlay (paper Fig. 6)


def _bgr(image: NDArray) -> NDArray[np.uint8]:
    image = np.asarray(image)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def overlay(
    frame_registered: NDArray,
    reference: NDArray,
    alpha: float = 0.5,
    *,
    mask: NDArray | None = None,
) -> NDArray[np.uint8]:
    """Frame k semi-transparently over the reference (paper Fig. 6).

    Args:
        frame_registered: ``(H, W[, 3])`` uint8 registered frame (base px crop).
        reference: same size, the reference (mid base image) over the same crop.
        alpha: opacity of the frame, 0..1.
        mask: ``(H, W)`` where the frame has data (None = everywhere); elsewhere the reference
            shows alone.

    Returns:
        ``(H, W, 3)`` BGR uint8.
    """
    if not 0 <= alpha <= 1:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    a, b = _bgr(frame_registered), _bgr(reference)
    if a.shape != b.shape:
        raise ValueError(f"frame {a.shape} and reference {b.shape} differ in size")
    out = cv2.addWeighted(a, alpha, b, 1 - alpha, 0.0)
    if mask is not None:
        out[~np.asarray(mask, bool)] = b[~np.asarray(mask, bool)]
    return out
