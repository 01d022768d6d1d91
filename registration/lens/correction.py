"""Correcting images for radial distortion (paper section 3, eq. 1): the corrected canvas, the
source map through the lens model, undistorting and distorting images, and a raw frame
simulated through a lens.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.geometry import (
    INTERPOLATIONS,
    PreparedMap,
    prepare_source_map,
    remap,
    remap_prepared,
    source_map_from_function,
)
from registration.lens.radial import RadialModel, check_valid

CANVASES = ("same", "full")
# Image correction offers these two; "nearest" stays available through registration.geometry.warp.
IMAGE_INTERPOLATIONS = ("linear", "cubic")
# The "full" canvas grows without bound as a model approaches its validity limit (the frame's
# corners move to infinity); refuse canvases larger than this many times the raw frame's area.
MAX_FULL_CANVAS_AREA_RATIO = 16.0
# cv2.remap's fixed-point maps hold int16 positions; canvases must stay well inside that.
MAX_CANVAS_SIDE = 32000
# Source maps are evaluated every MAP_STEP canvas pixels and interpolated (see
# correction_source_map); 4 keeps the interpolation error below 0.01 px.
MAP_STEP = 4


# --------------------------------------------------------------------------------------------
# Image correction


@dataclass(frozen=True)
class CanvasInfo:
    """Where a corrected image's pixels lie in corrected-frame coordinates.

    Canvas pixel ``(i, j)`` (column, row) shows corrected coordinate ``origin + (i, j)``.

    Attributes:
        kind: ``"same"`` (raw frame's size and centre, paper Fig. 2; origin (0, 0)) or
            ``"full"`` (the bounding box of the whole raw frame's content after correction).
        width, height: canvas size in pixels.
        origin: corrected coordinate ``(x, y)`` of canvas pixel (0, 0), whole pixels.
    """

    kind: str
    width: int
    height: int
    origin: tuple[float, float] = (0.0, 0.0)

    def canvas_from_corrected(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` corrected-frame pixels -> ``(N, 2)`` canvas pixels."""
        return as_points(xy) - np.asarray(self.origin)

    def corrected_from_canvas(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` canvas pixels -> ``(N, 2)`` corrected-frame pixels."""
        return as_points(xy) + np.asarray(self.origin)

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "width": self.width,
            "height": self.height,
            "origin": [float(self.origin[0]), float(self.origin[1])],
        }


def _raw_boundary(width: int, height: int) -> NDArray[np.float64]:
    """Every pixel centre on the raw frame's border, ``(N, 2)``."""
    xs = np.arange(width, dtype=np.float64)
    ys = np.arange(height, dtype=np.float64)
    return np.concatenate(
        [
            np.stack([xs, np.zeros_like(xs)], 1),
            np.stack([xs, np.full_like(xs, height - 1)], 1),
            np.stack([np.zeros_like(ys), ys], 1),
            np.stack([np.full_like(ys, width - 1), ys], 1),
        ]
    )


def correction_canvas(model: RadialModel, canvas: str = "same") -> CanvasInfo:
    """The canvas :func:`undistort_image` renders on (see :class:`CanvasInfo`).

    Raises:
        ValueError: unknown ``canvas``, invalid model, or a "full" canvas that would exceed
            ``MAX_FULL_CANVAS_AREA_RATIO`` times the raw frame's area.
    """
    if canvas not in CANVASES:
        raise ValueError(f"canvas must be one of {', '.join(CANVASES)}, got {canvas!r}")
    check_valid(model)
    w, h = int(model.width), int(model.height)
    if canvas == "same":
        return CanvasInfo("same", w, h, (0.0, 0.0))
    # Radial maps are monotone in ρ, so the frame border's image bounds the whole frame's.
    corrected = model.corrected_from_raw(_raw_boundary(w, h))
    x0, y0 = np.floor(corrected.min(axis=0))
    x1, y1 = np.ceil(corrected.max(axis=0))
    cw, ch = int(x1 - x0 + 1), int(y1 - y0 + 1)
    if cw * ch > MAX_FULL_CANVAS_AREA_RATIO * w * h or max(cw, ch) > MAX_CANVAS_SIDE:
        raise ValueError(
            f"the full canvas for {_describe(model)} would be {cw}x{ch} px "
            f"(more than {MAX_FULL_CANVAS_AREA_RATIO:g}x the {w}x{h} frame's area): the model is "
            f"close to its validity limit; use canvas 'same'"
        )
    return CanvasInfo("full", cw, ch, (float(x0), float(y0)))


def _describe(model: RadialModel) -> str:
    p = {k: v for k, v in model.params().items() if k != "model"}
    vals = ", ".join(f"{k} {v:g}" for k, v in p.items())
    return f"{model.params()['model']} model ({vals})"


def correction_source_map(
    model: RadialModel, canvas: str = "same"
) -> tuple[NDArray[np.float32], CanvasInfo]:
    """Uncached float32 ``(H_c, W_c, 2)`` source map (canvas pixel -> raw pixel) and its canvas."""
    info = correction_canvas(model, canvas)
    # Evaluating every 4th pixel and interpolating is ~20x faster and within 0.002 px on a
    # 2560x1920 frame at gamma 0.7; where canvas pixels have no raw source (NaN, e.g. pincushion
    # correction on the "same" canvas) the coarse grid would widen the hole by up to 4 px, so
    # such maps are evaluated exactly.
    source_map = source_map_from_function(
        model.raw_from_corrected, info.width, info.height, step=MAP_STEP, origin=info.origin
    )
    if np.isnan(source_map).any():
        source_map = source_map_from_function(
            model.raw_from_corrected, info.width, info.height, origin=info.origin
        )
    return source_map, info


@functools.lru_cache(maxsize=6)
def _prepared_correction(
    model: RadialModel, canvas: str, interpolation: str
) -> tuple[PreparedMap, CanvasInfo]:
    source_map, info = correction_source_map(model, canvas)
    return prepare_source_map(source_map, interpolation=interpolation), info


def clear_map_cache() -> None:
    """Drop the cached correction maps (each 2560x1920 map holds ~30 MB)."""
    _prepared_correction.cache_clear()


def _check_image(image: NDArray, model: RadialModel, what: str = "image") -> None:
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
        shape = getattr(image, "shape", None)
        raise ValueError(f"{what} must be a non-empty (H, W) or (H, W, C) array, got shape {shape}")
    h, w = image.shape[:2]
    if (w, h) != (model.width, model.height):
        raise ValueError(
            f"{what} is {w}x{h} but the distortion model is for a {model.width}x{model.height} frame"
        )


def undistort_image(
    image: NDArray,
    model: RadialModel,
    *,
    canvas: str = "same",
    interpolation: str = "linear",
    border_value: float | tuple[float, ...] = 0,
) -> tuple[NDArray, CanvasInfo]:
    """Correct a raw image's radial distortion (paper eq. 1: ``I_1(x) = I_0(D(x))``).

    The source map for (model, canvas, interpolation) is computed once and cached, prepared by
    :func:`registration.geometry.warp.prepare_source_map` (fixed point for bilinear, float for bicubic),
    so correcting every frame of a video costs one ``cv2.remap`` each.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` raw image; ``(W, H)`` must equal the model's frame.
        model: a valid radial model (:func:`check_valid` is applied).
        canvas: ``"same"``: the raw frame's size and centre (paper Fig. 2; barrel correction
            crops the outer raw content); ``"full"``: a larger canvas holding every raw pixel.
        interpolation: ``"linear"`` (bilinear) or ``"cubic"`` (bicubic).
        border_value: value of canvas pixels with no raw source.

    Returns:
        ``(corrected, info)``: the corrected image (``(H_c, W_c[, C])``, the input's dtype) and
        the :class:`CanvasInfo` mapping its pixels to corrected-frame coordinates.
    """
    if interpolation not in IMAGE_INTERPOLATIONS:
        raise ValueError(
            f"interpolation must be one of {', '.join(IMAGE_INTERPOLATIONS)}, got {interpolation!r}"
        )
    if canvas not in CANVASES:
        raise ValueError(f"canvas must be one of {', '.join(CANVASES)}, got {canvas!r}")
    _check_image(image, model)
    check_valid(model)
    prepared, info = _prepared_correction(model, canvas, interpolation)
    return remap_prepared(image, prepared, border_value=border_value), info


def distort_image(
    straight: NDArray,
    model: RadialModel,
    *,
    origin: tuple[float, float] = (0.0, 0.0),
    interpolation: str = "linear",
    border_value: float | tuple[float, ...] = 0,
) -> NDArray:
    """Synthesise a raw (distorted) frame from an undistorted image (the inverse of correction).

    Raw pixel ``x'`` samples ``straight`` at ``corrected_from_raw(x') - origin``; so ``straight``
    pixel (0, 0) shows corrected coordinate ``origin`` (give a larger image and a negative origin
    to fill the raw frame's corners under barrel distortion).

    Args:
        straight: ``(H_s, W_s[, C])`` image of the undistorted world.
        model: a valid radial model; the output has its frame size.
        origin: corrected coordinate of ``straight``'s pixel (0, 0).
        interpolation: ``"nearest"``, ``"linear"`` or ``"cubic"``.
        border_value: value for raw pixels whose source lies outside ``straight``.

    Returns:
        ``(model.height, model.width[, C])`` raw image.
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(
            f"interpolation must be one of {sorted(INTERPOLATIONS)}, got {interpolation!r}"
        )
    check_valid(model)
    ox, oy = origin
    source_map = source_map_from_function(
        lambda xy: model.corrected_from_raw(xy) - (ox, oy), int(model.width), int(model.height)
    )
    return remap(straight, source_map, interpolation=interpolation, border_value=border_value)


def simulate_raw_frame(
    scene: NDArray,
    model: RadialModel,
    *,
    max_zoom_out: float = 2.5,
    interpolation: str = "linear",
    return_mask: bool = False,
) -> tuple[NDArray, float] | tuple[NDArray, float, NDArray[np.bool_]]:
    """A raw frame of ``model``'s size seeing ``scene`` (undistorted) through the lens.

    ``scene`` is resized (INTER_AREA, keeping its aspect ratio) so that, centred on the
    distortion centre, it covers every raw pixel's corrected position, up to ``max_zoom_out``
    times the frame's half extent (models near their validity limit send the corners to
    infinity; beyond that the frame shows ``0``). Used to test γ estimation on real imagery.

    The scene's border is a perfectly straight line in the world: where it shows in the raw
    frame (the black corners beyond ``max_zoom_out``) it is a fake edge that obeys the model
    exactly. ``return_mask`` gives the raw pixels that see the scene, so an estimator can be
    told to ignore the rest.

    Args:
        scene: ``(H_s, W_s[, C])`` undistorted image.
        model: a valid radial model; the output has its frame size.
        max_zoom_out: cap on covered extent / frame extent.
        interpolation: resampling of the raw frame.
        return_mask: also return the ``(H, W)`` bool mask of raw pixels whose every
            interpolation neighbour lies inside the scene.

    Returns:
        ``(raw, scale)`` or, with ``return_mask``, ``(raw, scale, mask)``: the raw frame and the
        resize factor applied to ``scene`` (scene pixel ``p`` appears at corrected coordinate
        ``c + (p - c_s) * scale``, ``c_s`` its centre).
    """
    import cv2

    if interpolation not in INTERPOLATIONS:
        raise ValueError(
            f"interpolation must be one of {sorted(INTERPOLATIONS)}, got {interpolation!r}"
        )
    check_valid(model)
    w, h = int(model.width), int(model.height)
    corrected = model.corrected_from_raw(_raw_boundary(w, h))
    half = np.abs(corrected - model.c).max(axis=0)
    zoom = min(max(half[0] / (w / 2), half[1] / (h / 2)) * 1.02, max_zoom_out)
    hs, ws = scene.shape[:2]
    scale = max(zoom * w / ws, zoom * h / hs)
    size = (max(round(ws * scale), 1), max(round(hs * scale), 1))
    big = cv2.resize(scene, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC)
    ox, oy = (model.c[0] - (size[0] - 1) / 2, model.c[1] - (size[1] - 1) / 2)
    source_map = source_map_from_function(lambda xy: model.corrected_from_raw(xy) - (ox, oy), w, h)
    raw = remap(big, source_map, interpolation=interpolation, border_value=0)
    if not return_mask:
        return raw, float(size[0] / ws)
    # Source positions whose interpolation neighbours all lie in the scene: nearest rounds,
    # bilinear reads floor and floor + 1, bicubic floor - 1 .. floor + 2.
    lo, hi = {"nearest": (-0.5, 0.5), "linear": (0.0, 1.0), "cubic": (1.0, 3.0)}[interpolation]
    sx, sy = source_map[..., 0], source_map[..., 1]
    with np.errstate(invalid="ignore"):
        mask = (sx >= lo) & (sx <= size[0] - hi) & (sy >= lo) & (sy <= size[1] - hi)
    return raw, float(size[0] / ws), mask
