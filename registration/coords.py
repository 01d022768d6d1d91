"""Point-array helpers shared by every stage: validation and rescaling between image scales."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def as_points(xy: ArrayLike, name: str = "points") -> NDArray[np.float64]:
    """Return ``xy`` as a float64 ``(N, 2)`` array; a single ``(2,)`` point becomes ``(1, 2)``.

    Raises:
        ValueError: naming ``name`` and the offending shape when it is not ``(N, 2)``.
    """
    arr = np.asarray(xy, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == 2:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {arr.shape}")
    return arr


def rescale(xy: ArrayLike, scale: float | ArrayLike) -> NDArray[np.float64]:
    """Map pixel coordinates to an image rescaled by ``scale`` (pixel centres at integers).

    ``x_s = (x + 0.5) * scale - 0.5``; e.g. ``scale=0.25`` goes from full to quarter resolution.
    ``scale`` may also be per axis, ``(sx, sy)`` (an image resized to a rounded size).
    """
    return (as_points(xy) + 0.5) * scale - 0.5


def image_size(image: NDArray) -> tuple[int, int]:
    """``(width, height)`` of an ``(H, W)`` or ``(H, W, C)`` image."""
    return int(image.shape[1]), int(image.shape[0])


def frame_outline(width: int, height: int, per_edge: int = 32) -> NDArray[np.float64]:
    """``(4 * per_edge, 2)`` pixel centres along the border of a ``width`` x ``height`` image,
    clockwise from the top-left corner (each corner once)."""
    t = np.linspace(0.0, 1.0, per_edge, endpoint=False)
    w1, h1 = width - 1.0, height - 1.0
    return np.concatenate(
        [
            np.c_[t * w1, np.zeros_like(t)],
            np.c_[np.full_like(t, w1), t * h1],
            np.c_[w1 - t * w1, np.full_like(t, h1)],
            np.c_[np.zeros_like(t), h1 - t * h1],
        ]
    )


def bbox_of(pts: NDArray, base_size: tuple[int, int], margin: int = 2) -> tuple[int, int, int, int]:
    """Integer ``(x0, y0, x1, y1)`` box around ``pts`` (base px), clipped to the base."""
    pts = pts[np.isfinite(pts).all(axis=1)]
    if not len(pts):
        return 0, 0, 0, 0
    wb, hb = base_size
    x0 = int(max(0, np.floor(pts[:, 0].min()) - margin))
    y0 = int(max(0, np.floor(pts[:, 1].min()) - margin))
    x1 = int(min(wb, np.ceil(pts[:, 0].max()) + margin + 1))
    y1 = int(min(hb, np.ceil(pts[:, 1].max()) + margin + 1))
    return x0, y0, x1, y1
