"""Base maps at any heading and resolution, with the truth kept exact.

The *native* base is the second sensor's rendering on the scene's pixel grid (procedural city), or
the user's base image; ``native_from_scene`` relates it to the scene. A base at heading ``θ`` and
scale ``s`` is the native base turned by ``θ`` and resampled by ``s`` (base px per native px),
drawn on a canvas that holds all of it (black = no data outside)::

    base_from_native = similarity(θ, s)         (pixel centres at integers, conventions.md)
    base_from_scene  = base_from_native @ native_from_scene

In pixel-centre coordinates ``p`` (``(0, 0)`` = centre of the top-left pixel) the similarity is
``p' = s R(θ) (p + 0.5) + t - 0.5`` with ``R(θ) = [[cos θ, -sin θ], [sin θ, cos θ]]`` acting on
``(x, y)`` with ``y`` down: the base's content turns **clockwise on screen** by ``θ`` (the native
``+x`` axis points along ``(cos θ, sin θ)`` in the base). ``t`` puts the turned native image's
top-left extreme at the canvas's top-left edge; at ``θ = 0`` this is ``coords.rescale``'s
``(x + 0.5) s - 0.5``.

Resampling: scaling down first averages pixel areas (``cv2.resize`` INTER_AREA, the
anti-aliasing filter) to the nearest whole size, then the remaining near-identity similarity
(rotation and the rounding of the size) is applied with ``cv2.warpAffine`` (bilinear), whose
pixel convention is OpenCV's (centres at integers), the same as :mod:`registration.geometry.warp`;
``cv2.warpAffine`` rather than a source map because a 2x base of a large city would need a
gigabyte of map. Scaling up is one bilinear ``cv2.warpAffine``.

:func:`rebase` copies a simulated sequence with a new base (frames hard-linked, truth exact).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

# cv2.warpAffine and cv2.remap use int16 positions internally.
MAX_BASE_SIDE = 32000
# A base larger than this many pixels (3 bytes each, plus work copies) is refused.
MAX_BASE_PIXELS = 400_000_000


def _cos_sin(heading_deg: float) -> tuple[float, float]:
    """cos and sin of ``heading_deg``, exact at multiples of 90 degrees."""
    q = float(heading_deg) % 360.0
    exact = {0.0: (1.0, 0.0), 90.0: (0.0, 1.0), 180.0: (-1.0, 0.0), 270.0: (0.0, -1.0)}
    if q in exact:
        return exact[q]
    a = math.radians(q)
    return math.cos(a), math.sin(a)


def check_base_params(heading_deg: float, scale: float) -> None:
    """One-line ValueError for a non-finite heading or a scale outside [0.05, 8]."""
    if not math.isfinite(heading_deg):
        raise ValueError(f"base heading must be a finite angle in degrees, got {heading_deg}")
    if not (math.isfinite(scale) and 0.05 <= scale <= 8.0):
        raise ValueError(f"base scale must be in [0.05, 8] base px per scene px, got {scale}")


def similarity(
    native_size: tuple[int, int], heading_deg: float, scale: float
) -> tuple[NDArray[np.float64], tuple[int, int]]:
    """``(base_from_native (3, 3), canvas (width, height))`` for a native base of
    ``native_size`` turned by ``heading_deg`` and scaled by ``scale`` (see the module docstring).

    Raises:
        ValueError: bad heading/scale, or a canvas over :data:`MAX_BASE_SIDE` per side or
            :data:`MAX_BASE_PIXELS` in all.
    """
    check_base_params(heading_deg, scale)
    w, h = (int(v) for v in native_size)
    c, s = _cos_sin(heading_deg)
    a = float(scale) * np.array([[c, -s], [s, c]])
    corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]) @ a.T  # pixel-edge coordinates
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    t = -lo
    canvas = tuple(int(v) for v in np.maximum(1, np.ceil(hi - lo - 1e-9)))
    m = np.eye(3)
    m[:2, :2] = a
    # p' = a (p + 0.5) + t - 0.5
    m[:2, 2] = a @ np.array([0.5, 0.5]) + t - 0.5
    cw, ch = canvas
    if cw > MAX_BASE_SIDE or ch > MAX_BASE_SIDE or cw * ch > MAX_BASE_PIXELS:
        raise ValueError(
            f"a base turned by {heading_deg:g} deg and scaled by {scale:g} would be {cw}x{ch} px, "
            f"over the limit of {MAX_BASE_SIDE} px per side and {MAX_BASE_PIXELS / 1e6:.0f} MP "
            "(OpenCV's int16 warp positions and memory); use a smaller base scale"
        )
    return m, canvas


def valid_polygon(base_from_native: NDArray, native_size: tuple[int, int]) -> NDArray[np.float64]:
    """``(4, 2)`` corners (pixel edges) of the native base's area in the base, clockwise."""
    w, h = native_size
    pts = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    return pts @ base_from_native[:2, :2].T + base_from_native[:2, 2]


def _pixel_scale_matrix(sx: float, sy: float) -> NDArray[np.float64]:
    """Pixel-centre affine of an image resized by ``(sx, sy)``: ``x_s = (x + 0.5) s - 0.5``."""
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


def resample(
    image: NDArray, out_from_image: NDArray, canvas: tuple[int, int], scale: float
) -> NDArray:
    """Warp ``image`` by the similarity ``out_from_image`` (pixel centres at integers, isotropic
    ``scale``) onto a ``canvas`` ``(width, height)``; black outside the image.

    Scaling down first averages pixel areas (INTER_AREA) so the result does not alias.
    """
    m = np.asarray(out_from_image, np.float64)
    img = np.ascontiguousarray(image)
    h, w = img.shape[:2]
    if scale < 1.0 - 1e-12:
        w1, h1 = max(1, round(w * scale)), max(1, round(h * scale))
        img = cv2.resize(img, (w1, h1), interpolation=cv2.INTER_AREA)
        m = m @ np.linalg.inv(_pixel_scale_matrix(w1 / w, h1 / h))
        h, w = h1, w1
    if np.allclose(m, np.eye(3), rtol=0, atol=1e-12) and (w, h) == tuple(canvas):
        return img
    return cv2.warpAffine(
        img,
        m[:2],
        tuple(int(v) for v in canvas),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(0, 0, 0, 0),
    )


def warp_base(
    native: NDArray, heading_deg: float, scale: float
) -> tuple[NDArray, NDArray[np.float64], tuple[int, int]]:
    """The native base turned by ``heading_deg`` and scaled by ``scale``.

    Returns:
        ``(base image, base_from_native (3, 3), canvas (width, height))``; at heading 0 and
        scale 1 the image is ``native`` itself and the matrix the identity.
    """
    h, w = native.shape[:2]
    m, canvas = similarity((w, h), heading_deg, scale)
    return resample(native, m, canvas, float(scale)), m, canvas


def base_map_info(
    native_size: tuple[int, int],
    native_from_scene: NDArray,
    heading_deg: float,
    scale: float,
    base_from_native: NDArray,
) -> dict:
    """The ``base_map`` record of ``truth.json``: how the base relates to the native base."""
    return {
        "heading_deg": float(heading_deg),
        "scale": float(scale),
        "native_size": [int(v) for v in native_size],
        "native_from_scene": np.asarray(native_from_scene, np.float64).tolist(),
        "base_from_native": np.asarray(base_from_native, np.float64).tolist(),
        "valid_polygon": valid_polygon(base_from_native, native_size).tolist(),
    }
