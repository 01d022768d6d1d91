"""Grey conversion and subsampling (paper 4.3.1 steps 1-2), with masks that follow."""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration import coords

# --------------------------------------------------------------------------------------------
# Grey conversion and subsampling (paper 4.3.1 steps 1-2)
# --------------------------------------------------------------------------------------------


def to_grey(image: ArrayLike) -> NDArray[np.uint8]:
    """Convert an image to 8-bit grey (paper 4.3.1 step 1).

    Args:
        image: ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` BGR or ``(H, W, 4)`` BGRA array (OpenCV
            channel order). dtype uint8 (0..255), uint16 (0..65535, divided by 257) or float.
            Float images are taken to span 0..1 when their maximum is at most 1, otherwise
            0..255; values outside the range are clipped and NaN becomes 0.

    Returns:
        ``(H, W)`` uint8 array (the input itself when it already is one, not a copy).

    Raises:
        ValueError: for an empty image, an unsupported shape or dtype.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)):
        raise ValueError(
            f"image must have shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {img.shape}"
        )
    if img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"image is empty: shape {img.shape}")
    if img.dtype == np.uint8:
        out = img
    elif img.dtype == np.uint16:
        out = np.round(img.astype(np.float32) * (255.0 / 65535.0)).astype(np.uint8)
    elif np.issubdtype(img.dtype, np.floating):
        f = np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        scale = 255.0 if (f.size and float(f.max()) <= 1.0) else 1.0
        out = np.clip(np.round(f * scale), 0, 255).astype(np.uint8)
    else:
        raise ValueError(f"image dtype must be uint8, uint16 or float, got {img.dtype}")
    if out.ndim == 3:
        code = cv2.COLOR_BGR2GRAY if out.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        out = cv2.cvtColor(np.ascontiguousarray(out), code)
    return np.ascontiguousarray(out)


def downscale(image: NDArray, scale: float = 0.25) -> NDArray:
    """Resample an image by ``scale`` with ``cv2.INTER_AREA`` (paper 4.3.1 step 2: 1/4 scale).

    The output is ``max(1, round(W * scale))`` by ``max(1, round(H * scale))``. Points map between
    the two with :func:`registration.coords.rescale` (``x_s = (x + 0.5) * scale - 0.5``), exact
    when ``W * scale`` and ``H * scale`` are integers.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` array.
        scale: output/input size ratio, > 0 (default 0.25, paper 4.3.1).

    Returns:
        The resampled image, same dtype and channel count.
    """
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a finite number > 0, got {scale!r}")
    img = np.asarray(image)
    if img.ndim not in (2, 3) or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(
            f"image must be a non-empty (H, W) or (H, W, C) array, got shape {img.shape}"
        )
    w, h = coords.image_size(img)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def downscale_mask(mask: NDArray, scale: float) -> NDArray[np.bool_]:
    """A content mask (``(H, W)``, non-zero = content) at ``scale`` (:func:`downscale`): True
    where the area it averages is (all but 2 %) content."""
    return downscale(np.asarray(mask, bool).astype(np.uint8) * 255, scale) > 250
