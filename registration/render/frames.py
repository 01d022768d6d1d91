"""Frames rendered into base-map pixels (paper sections 5 and 6): through the global model and the
local field, cropped to what a frame or the sequence covers, and a frame's footprint on the map.

Pure functions: they return arrays (BGR uint8, like cv2); :mod:`registration.render.video`
writes them out.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.coords import frame_outline, image_size
from registration.geometry import warp
from registration.lens import Camera, as_camera

Box = tuple[int, int, int, int]  # (x0, y0, width, height) in base px


def render_to_base(
    frame_raw: NDArray,
    camera: Camera | float,
    base_from_corrected,
    box: tuple[int, int, int, int],
    field=None,
) -> tuple[NDArray, NDArray[np.bool_]]:
    """The raw frame resampled once into the base-pixel box ``(x0, y0, x1, y1)``, with its
    validity mask: base pixels map to raw pixels through the displacement field (when given:
    ``x + d(x)``, :mod:`registration.local`), the model's inverse and the Harris model
    (:func:`render_registered`), so the frame is interpolated only once. ``camera``: the frames'
    :class:`registration.lens.camera.Camera` (or their Harris γ)."""
    camera = as_camera(camera, frame_raw)
    x0, y0, x1, y1 = box

    def raw_from_base(b):
        if field is not None:
            b = b + field.sample(b, outside="clamp")
        return camera.raw_from_corrected(base_from_corrected.inverse(b))

    return warp.warp_image(frame_raw, raw_from_base, x1 - x0, y1 - y0, origin=(x0, y0))


# Raw px from the frame's edge within which an unclipped mapping is evaluated exactly: more than
# the lattice's interpolation error there (render_registered).
EDGE_EXACT_PX = 0.5


def render_registered(
    frame_raw: NDArray,
    base_to_frame_fn: Callable[[NDArray], NDArray],
    out_size: tuple[int, int],
    origin: tuple[float, float] = (0.0, 0.0),
    *,
    step: int = 8,
    interpolation: str = "linear",
    return_mask: bool = False,
    unclipped: bool = False,
):
    """A raw frame rendered into base pixels.

    Args:
        frame_raw: ``(H, W[, C])`` the frame as recorded.
        base_to_frame_fn: ``(N, 2)`` base px -> ``(N, 2)`` raw px of the frame (NaN = none), e.g.
            ``lambda b: result.base_to_frame(k, b, "local")``.
        out_size: ``(width, height)`` of the output crop.
        origin: base px of output pixel ``(0, 0)``.
        step: the mapping is evaluated every ``step`` px and interpolated in between
            (:func:`registration.geometry.warp.source_map_from_function`).
        return_mask: also return the ``(height, width)`` bool mask of pixels with data.
        unclipped: ``base_to_frame_fn`` carries the mapping on beyond the frame's edge (NaN
            only well beyond it): the pixels whose interpolated raw px lie within
            ``EDGE_EXACT_PX`` of the frame's edge are evaluated exactly, rather than every pixel
            next to a NaN node (a band along the whole edge, ``step`` px wide).

    Returns:
        The image (``frame_raw``'s dtype and channels; 0 where the frame has no data), or
        ``(image, mask)``.
    """
    w, h = (int(v) for v in out_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"output size must be positive, got {w}x{h}")
    source = warp.source_map_from_function(
        base_to_frame_fn, w, h, step=step, origin=origin, source_size=image_size(frame_raw),
        exact_edge_px=EDGE_EXACT_PX if unclipped else 0.0,
    )  # fmt: skip
    if step > 1 and not unclipped:
        # The coarse map is NaN wherever one of the surrounding nodes falls outside the frame,
        # which would eat up to ``step`` px of every frame border: evaluate that band exactly.
        nan = ~warp.finite_points(source)
        if nan.any() and not nan.all():
            k = np.ones((2 * step + 1, 2 * step + 1), np.uint8)
            band = nan & (cv2.dilate((~nan).astype(np.uint8), k) > 0)
            ys, xs = np.nonzero(band)
            pts = np.c_[xs + float(origin[0]), ys + float(origin[1])]
            source[ys, xs] = np.asarray(base_to_frame_fn(pts), np.float32)
    image = warp.remap(frame_raw, source, interpolation=interpolation)
    if not return_mask:
        return image
    fw, fh = image_size(frame_raw)
    with np.errstate(invalid="ignore"):
        mask = (
            warp.finite_points(source)
            & (source[..., 0] >= -0.5)
            & (source[..., 0] <= fw - 0.5)
            & (source[..., 1] >= -0.5)
            & (source[..., 1] <= fh - 0.5)
        )
    return image, mask


def footprint(
    frame_to_base_fns: Iterable[Callable[[NDArray], NDArray]],
    frame_size: tuple[int, int],
    base_size: tuple[int, int] | None = None,
    *,
    pad: int = 0,
) -> Box:
    """Bounding box of the union of the frames' footprints in base pixels.

    Args:
        frame_to_base_fns: one ``(N, 2)`` raw px -> ``(N, 2)`` base px mapping per frame (failed
            frames may return NaN; they are skipped).
        frame_size: ``(W, H)`` of the raw frames.
        base_size: clip the box to the base map ``(W, H)``; None = no clipping.
        pad: px added on every side before clipping.

    Returns:
        ``(x0, y0, width, height)`` integers; ``(0, 0, 0, 0)`` when no frame maps anywhere.
    """
    outline = frame_outline(*frame_size)
    lo = np.array([np.inf, np.inf])
    hi = -lo
    for fn in frame_to_base_fns:
        pts = np.asarray(fn(outline), float)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts):
            lo = np.minimum(lo, pts.min(axis=0))
            hi = np.maximum(hi, pts.max(axis=0))
    if not np.isfinite(lo).all():
        return 0, 0, 0, 0
    x0, y0 = np.floor(lo).astype(int) - pad
    x1, y1 = np.ceil(hi).astype(int) + 1 + pad
    if base_size is not None:
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, int(base_size[0])), min(y1, int(base_size[1]))
    return int(x0), int(y0), int(max(x1 - x0, 0)), int(max(y1 - y0, 0))
