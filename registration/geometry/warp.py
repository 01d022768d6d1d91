"""The one remap primitive. Every warp in the project (distortion correction, registration to the
base map, the local displacement field) builds a *source map* and calls :func:`remap`.

A source map has shape ``(H_out, W_out, 2)``, float32: for output pixel ``(x, y)`` it holds the
``(x, y)`` position in the source image to sample (pixel centres at integers). NaN marks output
pixels with no source; they receive ``border_value``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

INTERPOLATIONS = {
    "nearest": cv2.INTER_NEAREST,
    "linear": cv2.INTER_LINEAR,
    "cubic": cv2.INTER_CUBIC,
}

# OpenCV converts float maps to fixed point internally; keep "no source" far outside any image
# but inside the int16 range it uses.
_OUTSIDE = -16000.0


def pixel_grid(width: int, height: int) -> NDArray[np.float32]:
    """``(height, width, 2)`` float32 array holding each pixel's own ``(x, y)``."""
    xs, ys = np.meshgrid(
        np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32), indexing="xy"
    )
    return np.stack([xs, ys], axis=-1)


def finite_points(points: NDArray) -> NDArray[np.bool_]:
    """``(...)`` bool: whether both coordinates of each ``(..., 2)`` point are finite
    (``np.isfinite(points).all(axis=-1)`` without numpy's slow reduction over a length-2
    innermost axis: ~4x faster on a frame's source map)."""
    return np.isfinite(points[..., 0]) & np.isfinite(points[..., 1])


def as_uint8_mask(mask: NDArray) -> NDArray[np.uint8]:
    """A bool (or 0/1) mask as uint8 for :func:`remap`: a bool array is viewed, not copied (a
    copy of a map-sized mask per frame cost 2-18 ms)."""
    mask = np.asarray(mask)
    if mask.dtype == np.bool_:
        return mask.view(np.uint8)
    return mask.astype(np.uint8, copy=False)


def remap(
    image: NDArray,
    source_map: NDArray,
    *,
    interpolation: str = "linear",
    border_value: float | tuple[float, ...] = 0,
) -> NDArray:
    """Sample ``image`` at ``source_map`` (output pixel -> source position).

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` array, any dtype cv2.remap accepts.
        source_map: ``(H_out, W_out, 2)`` source positions in pixels; NaN = no source.
        interpolation: ``"nearest"``, ``"linear"`` or ``"cubic"``.
        border_value: value for pixels whose source lies outside ``image`` or is NaN.

    Returns:
        ``(H_out, W_out[, C])`` array of ``image``'s dtype.
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(
            f"interpolation must be one of {sorted(INTERPOLATIONS)}, got {interpolation!r}"
        )
    source_map = np.asarray(source_map)
    if source_map.ndim != 3 or source_map.shape[2] != 2:
        raise ValueError(f"source_map must have shape (H, W, 2), got {source_map.shape}")
    m = _finite_map(source_map)
    if np.isscalar(border_value) and image.ndim == 3:
        border_value = (border_value,) * image.shape[2]
    return cv2.remap(
        image,
        m,
        None,
        INTERPOLATIONS[interpolation],
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=border_value,
    )


def _finite_map(source_map: NDArray) -> NDArray[np.float32]:
    """``source_map`` as float32 with NaN/inf replaced by a far-outside position.

    The common case (all finite, within OpenCV's fixed-point range) returns the map itself,
    uncopied: the checks cost ~4 ms on a 2560x1920 map where the copy-and-patch path costs ~60.
    """
    m = np.asarray(source_map, dtype=np.float32)
    if m.strides[1:] != (8, 4):  # OpenCV takes rows at any stride, pixels packed
        m = np.ascontiguousarray(m)
    if np.isfinite(m).all() and m.min() > _OUTSIDE and m.max() < -_OUTSIDE:
        return m
    m = m.copy() if m is source_map else m
    # NaN -> far outside in place (cv2, ~3x faster than a boolean mask); ±inf is clipped there.
    # A point with one such coordinate lies outside the image either way: remap gives the border.
    cv2.patchNaNs(m.reshape(m.shape[0], -1), _OUTSIDE)
    np.clip(m, _OUTSIDE, -_OUTSIDE, out=m)
    return m


@dataclass(frozen=True, eq=False)
class PreparedMap:
    """A source map prepared once for fast repeated :func:`remap_prepared` calls.

    For nearest and bilinear sampling the map is converted to OpenCV's fixed-point form
    (``cv2.convertMaps``, CV_16SC2): source positions quantised to 1/32 px (position error
    <= 1/64 px, a grey-value error of at most gradient/64); measured on a 2560x1920 colour frame
    (2 cores) it is ~25-30 % faster than ``cv2.remap`` with float maps. For bicubic sampling the
    fixed-point path measured ~25 % *slower*, so the map stays float32 (already sanitised: no
    per-call copy or NaN handling). Use it for maps applied to many images (cached distortion
    correction, one warp per video frame).

    Attributes:
        map1: ``(H_out, W_out, 2)`` int16 integer source positions (fixed point) or float32
            source positions (float).
        map2: ``(H_out, W_out)`` uint16 interpolation-table indices (fixed point, linear or
            cubic) or None (float, or nearest).
        interpolation: ``"nearest"``, ``"linear"`` or ``"cubic"``; fixed at preparation.
    """

    map1: NDArray
    map2: NDArray[np.uint16] | None
    interpolation: str

    @property
    def shape(self) -> tuple[int, int]:
        """``(H_out, W_out)`` of the output image."""
        return int(self.map1.shape[0]), int(self.map1.shape[1])

    @property
    def fixed_point(self) -> bool:
        return self.map1.dtype == np.int16


def prepare_source_map(
    source_map: NDArray, *, interpolation: str = "linear", fixed_point: bool | None = None
) -> PreparedMap:
    """Prepare a ``(H_out, W_out, 2)`` source map (NaN = no source) for :func:`remap_prepared`.

    Args:
        source_map: as for :func:`remap`.
        interpolation: ``"nearest"``, ``"linear"`` or ``"cubic"``.
        fixed_point: force (True) or avoid (False) the fixed-point form; None picks the faster
            one measured here (fixed point for nearest/linear, float for cubic).
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(
            f"interpolation must be one of {sorted(INTERPOLATIONS)}, got {interpolation!r}"
        )
    source_map = np.asarray(source_map)
    if source_map.ndim != 3 or source_map.shape[2] != 2:
        raise ValueError(f"source_map must have shape (H, W, 2), got {source_map.shape}")
    m = _finite_map(source_map)
    if fixed_point is None:
        fixed_point = interpolation != "cubic"
    if not fixed_point:
        return PreparedMap(m, None, interpolation)
    map1, map2 = cv2.convertMaps(m, None, cv2.CV_16SC2, nninterpolation=interpolation == "nearest")
    return PreparedMap(map1, map2, interpolation)


def remap_prepared(
    image: NDArray, prepared: PreparedMap, *, border_value: float | tuple[float, ...] = 0
) -> NDArray:
    """:func:`remap` with a map from :func:`prepare_source_map` (same result, less work per call).

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` array, any dtype cv2.remap accepts.
        prepared: the prepared source map; its interpolation is used.
        border_value: value for pixels whose source lies outside ``image`` or was NaN.

    Returns:
        ``(H_out, W_out[, C])`` array of ``image``'s dtype.
    """
    if np.isscalar(border_value) and image.ndim == 3:
        border_value = (border_value,) * image.shape[2]
    return cv2.remap(
        image,
        prepared.map1,
        prepared.map2,
        INTERPOLATIONS[prepared.interpolation],
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=border_value,
    )


def source_map_from_function(
    source_from_output: Callable[[NDArray], NDArray],
    width: int,
    height: int,
    *,
    step: int = 1,
    origin: tuple[float, float] = (0.0, 0.0),
    source_size: tuple[int, int] | None = None,
    exact_edge_px: float = 0.0,
) -> NDArray[np.float32]:
    """Build a source map by evaluating ``source_from_output`` on the output pixel grid.

    With ``step > 1`` the function is evaluated only on a lattice ``step`` pixels apart (one node
    beyond every edge) and interpolated bilinearly in between: exact for affine maps, within
    0.002 px for a warp with curvature 1e-4 /px at ``step=8`` (more than the global models
    have); it turns a costly numerical inverse over millions of pixels into one over thousands
    (11 ms for a 2560x1920 map). A raw frame's map to the base through a strong radial
    correction curves far more in its corners (γ = 0.7, nodes 8 px apart: 0.1-0.4 base px
    between nodes, 2.5 px at worst): whatever is measured in an image warped through the map
    is read back through :func:`lattice_source`.

    Args:
        source_from_output: ``(N, 2) -> (N, 2)`` function; may return NaN.
        width, height: output size in pixels.
        step: evaluation spacing in output pixels.
        origin: output pixel ``(0, 0)`` corresponds to this ``(x, y)`` in the function's
            coordinates (used to render a crop of a larger canvas).
        source_size: ``(W, H)`` of the source image, when known (``step > 1``): pixels that
            interpolation puts inside it from a lattice cell whose four nodes all lie outside
            it, not all beyond one of its edges, are evaluated exactly
            (:func:`_straddling_cells`).
        exact_edge_px: with ``source_size``, pixels whose interpolated source lies within this
            many source px of its edge are evaluated exactly: for a function not clipped at
            the source's edge, so that a mask of the source's extent follows the exact edge
            where the lattice curves between nodes (0: none).

    Returns:
        ``(height, width, 2)`` float32 source map.
    """
    ox, oy = origin
    if step <= 1:
        grid = pixel_grid(width, height).reshape(-1, 2).astype(np.float64) + (ox, oy)
        return np.asarray(source_from_output(grid), np.float32).reshape(height, width, 2)
    nodes = _lattice(width, height, step, origin)
    gy, gx = nodes.shape[:2]
    coarse = np.asarray(source_from_output(nodes.reshape(-1, 2)), np.float32).reshape(gy, gx, 2)
    source = _densify(coarse, step)[step : step + height, step : step + width]
    if source_size is not None:
        # Pixel x lies in the cell between nodes floor((x + step + 0.5) / step - 0.5) and the
        # next (the extra ring of nodes puts every pixel between two).
        cx = np.minimum((np.arange(width) + step + 0.5) / step - 0.5, gx - 2).astype(int)
        cy = np.minimum((np.arange(height) + step + 0.5) / step - 0.5, gy - 2).astype(int)
        w, h = source_size
        ys, xs = _cell_pixels(_straddling_cells(coarse, source_size), cx, cy)
        sx, sy = source[ys, xs, 0], source[ys, xs, 1]
        with np.errstate(invalid="ignore"):
            # Only what interpolation put inside can be a ghost: where the mapping is smooth
            # the interpolated and the exact source agree to a fraction of a px, inside or out.
            exact = (sx >= -0.5) & (sx <= w - 0.5) & (sy >= -0.5) & (sy <= h - 0.5)
        if exact_edge_px > 0:
            ey, ex = _cell_pixels(_edge_cells(coarse, source_size, exact_edge_px), cx, cy)
            sx, sy = source[ey, ex, 0], source[ey, ex, 1]
            m = exact_edge_px
            with np.errstate(invalid="ignore"):
                near_x = (np.abs(sx + 0.5) <= m) | (np.abs(sx - (w - 0.5)) <= m)
                near_y = (np.abs(sy + 0.5) <= m) | (np.abs(sy - (h - 0.5)) <= m)
                along = (
                    (sx >= -0.5 - m) & (sx <= w - 0.5 + m) & (sy >= -0.5 - m) & (sy <= h - 0.5 + m)
                )
            ys, xs = np.r_[ys, ey], np.r_[xs, ex]
            exact = np.r_[exact, (near_x | near_y) & along]
        if exact.any():
            pix = np.unique(ys[exact] * width + xs[exact])  # row-major, each pixel once
            ys, xs = pix // width, pix % width
            pts = np.c_[xs + float(ox), ys + float(oy)]
            source[ys, xs] = np.asarray(source_from_output(pts), np.float32)
    return source


def _cell_pixels(cells: NDArray[np.bool_], cx: NDArray, cy: NDArray) -> tuple[NDArray, NDArray]:
    """``(ys, xs)`` of every output pixel in the lattice cells marked in ``cells``
    (``(gy - 1, gx - 1)``), given each pixel column's cell ``cx`` and row's ``cy``
    (non-decreasing)."""
    rows, cols = np.nonzero(cells)
    if not len(rows):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    y0, y1 = np.searchsorted(cy, rows), np.searchsorted(cy, rows + 1)
    x0, x1 = np.searchsorted(cx, cols), np.searchsorted(cx, cols + 1)
    span = int(max((y1 - y0).max(), (x1 - x0).max()))
    off = np.arange(span)
    ys = np.broadcast_to((y0[:, None] + off)[:, :, None], (len(rows), span, span))
    xs = np.broadcast_to((x0[:, None] + off)[:, None, :], (len(rows), span, span))
    keep = (ys < y1[:, None, None]) & (xs < x1[:, None, None])
    return ys[keep], xs[keep]


def _edge_cells(coarse: NDArray, source_size: tuple[int, int], margin: float) -> NDArray[np.bool_]:
    """``(gy - 1, gx - 1)``: the lattice cells with all four nodes defined whose interpolated
    source can come within ``margin`` px of the ``source_size`` image's edge (bilinear
    interpolation stays within its nodes' range in each coordinate)."""
    w, h = source_size
    corners = np.stack(
        [coarse[:-1, :-1], coarse[1:, :-1], coarse[:-1, 1:], coarse[1:, 1:]]
    )  # (4, gy - 1, gx - 1, 2)
    with np.errstate(invalid="ignore"):
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        reach_x = (lo[..., 0] <= w - 0.5 + margin) & (hi[..., 0] >= -0.5 - margin)
        reach_y = (lo[..., 1] <= h - 0.5 + margin) & (hi[..., 1] >= -0.5 - margin)
        # Not wholly inside the edge's band on the inner side.
        inner_x = (lo[..., 0] > -0.5 + margin) & (hi[..., 0] < w - 0.5 - margin)
        inner_y = (lo[..., 1] > -0.5 + margin) & (hi[..., 1] < h - 0.5 - margin)
    return _all_four(finite_points(coarse)) & reach_x & reach_y & ~(inner_x & inner_y)


def _straddling_cells(coarse: NDArray, source_size: tuple[int, int]) -> NDArray[np.bool_]:
    """``(gy - 1, gx - 1)``: the lattice cells whose four nodes are all defined and outside the
    ``source_size`` image, but not all beyond the same edge. Bilinear interpolation between
    such nodes can pass through the image: where a mapping jumps between nodes (across a
    model inverse's second branch far from the frame, or a projective's horizon), the
    interpolated map would render a ghost copy of the image's content there."""
    w, h = source_size
    sx, sy = coarse[..., 0], coarse[..., 1]
    with np.errstate(invalid="ignore"):
        sides = np.stack([sx < -0.5, sx > w - 0.5, sy < -0.5, sy > h - 0.5])
    outside = _all_four(sides.any(axis=0) & finite_points(coarse))
    return outside & ~_all_four(sides).any(axis=0)


def _all_four(a: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``(..., gy - 1, gx - 1)``: whether ``a`` (``(..., gy, gx)`` over the lattice's nodes)
    holds at all four nodes of each cell."""
    return a[..., :-1, :-1] & a[..., 1:, :-1] & a[..., :-1, 1:] & a[..., 1:, 1:]


def source_maps_in_boxes(
    source_from_output: Callable[[NDArray], NDArray],
    width: int,
    height: int,
    boxes: NDArray,
    *,
    step: int,
    origin: tuple[float, float] = (0.0, 0.0),
) -> list[NDArray[np.float32]]:
    """The parts ``boxes`` of :func:`source_map_from_function`'s map (``step > 1``), to the bit,
    with the function evaluated only at the lattice nodes those parts need.

    Args:
        boxes: ``(N, 4)`` int ``(x0, y0, x1, y1)`` output pixel boxes (end exclusive) inside
            the ``width`` x ``height`` output.

    Returns:
        One ``(y1 - y0, x1 - x0, 2)`` float32 map per box.
    """
    nodes = _lattice(width, height, step, origin)
    gy, gx = nodes.shape[:2]
    boxes = np.asarray(boxes, np.int64).reshape(-1, 4)
    # Output pixel x is dense pixel x + step; dense pixel d lies between nodes
    # floor((d + 0.5) / step - 0.5) and the next (cv2.resize's bilinear upscaling).
    lo = np.maximum((boxes[:, :2] + step + 0.5) // step - 1, 0).astype(np.int64)
    hi = np.minimum((boxes[:, 2:] - 1 + step + 0.5) // step + 1, [gx - 1, gy - 1]).astype(np.int64)
    need = np.zeros((gy + 1, gx + 1), np.int32)  # a 2-D difference array of the node boxes
    np.add.at(need, (lo[:, 1], lo[:, 0]), 1)
    np.add.at(need, (lo[:, 1], hi[:, 0] + 1), -1)
    np.add.at(need, (hi[:, 1] + 1, lo[:, 0]), -1)
    np.add.at(need, (hi[:, 1] + 1, hi[:, 0] + 1), 1)
    need = need.cumsum(axis=0).cumsum(axis=1)[:gy, :gx] > 0
    coarse = np.full((gy, gx, 2), np.nan, np.float32)
    coarse[need] = np.asarray(source_from_output(nodes[need]), np.float32)
    # Each box from its own nodes: between its first and last node, cv2.resize of a part of
    # the lattice gives the pixels of the whole lattice's resize, to the bit.
    maps = []
    for (x0, y0, x1, y1), (lx, ly), (hx, hy) in zip(boxes, lo, hi, strict=True):
        part = _densify(coarse[ly : hy + 1, lx : hx + 1], step)
        ox, oy = (lx - 1) * step, (ly - 1) * step  # the part's dense origin, output px
        maps.append(part[y0 - oy : y1 - oy, x0 - ox : x1 - ox])
    return maps


def lattice_source(
    source_from_output: Callable[[NDArray], NDArray],
    xy: NDArray,
    *,
    step: int,
    origin: tuple[float, float] = (0.0, 0.0),
) -> NDArray[np.float64]:
    """What the map of :func:`source_map_from_function` (with this ``step`` and ``origin``)
    holds at the output points ``xy`` (``(N, 2)``, any float position): the function
    interpolated bilinearly between its lattice nodes, not the function itself.

    An image warped through that map shows, at output point ``x``, the source content at this
    interpolated position. Where the mapping curves (a frame's stretched corners under a
    strong radial correction: 0.1-0.4 px mean, 2.5 px at worst, between nodes 8 frame px
    apart at γ = 0.7) the function itself is not where that content came from; a match found
    in the warped image must be read back through this. ``step <= 1``: the function.

    Returns:
        ``(N, 2)`` source coordinates (NaN where a surrounding node is undefined).
    """
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if step <= 1 or len(xy) == 0:
        return np.asarray(source_from_output(xy), np.float64).reshape(-1, 2)
    # Node j sits at output px (j - 0.5) * step - 0.5 (_lattice: one extra node before px 0).
    u = (xy - np.asarray(origin, np.float64) + 0.5) / step + 0.5
    j0 = np.floor(u)
    t = u - j0
    corners = [(0, 0), (1, 0), (0, 1), (1, 1)]
    nodes = np.concatenate([(j0 + c - 0.5) * step - 0.5 for c in corners]) + origin
    # Neighbouring points share nodes: the function is evaluated once per distinct node.
    unique, inverse = np.unique(nodes, axis=0, return_inverse=True)
    values = np.asarray(source_from_output(unique), np.float64)[inverse.ravel()]
    v00, v10, v01, v11 = values.reshape(4, len(xy), 2)
    tx, ty = t[:, :1], t[:, 1:]
    top = v00 * (1 - tx) + v10 * tx
    bottom = v01 * (1 - tx) + v11 * tx
    return top * (1 - ty) + bottom * ty


def _lattice(width: int, height: int, step: int, origin: tuple[float, float]) -> NDArray:
    """``(gy, gx, 2)`` evaluation nodes of a ``step``-spaced source map, in the function's
    coordinates.

    Nodes sit at (j + 0.5) * step - 0.5, exactly where cv2.resize's bilinear upscaling by
    ``step`` puts source pixel centres, with one extra ring outside so that every output pixel
    lies between nodes."""
    ox, oy = origin
    gx, gy = -(-width // step) + 2, -(-height // step) + 2
    xs = (np.arange(gx) - 1 + 0.5) * step - 0.5
    ys = (np.arange(gy) - 1 + 0.5) * step - 0.5
    nx, ny = np.meshgrid(xs + ox, ys + oy, indexing="xy")
    return np.stack([nx, ny], axis=2)


def _densify(coarse: NDArray[np.float32], step: int) -> NDArray[np.float32]:
    """The lattice interpolated to every pixel (the extra ring included). cv2.resize
    interpolates float32 with float weights (cv2.remap would quantise positions to 1/32 of a
    cell). NaN propagates to the pixels next to an undefined node, so they stay undefined rather
    than being extrapolated. The result is a view's base: slices of it are what OpenCV takes
    (rows at any stride), so no copy is made."""
    gy, gx = coarse.shape[:2]
    return cv2.resize(coarse, (gx * step, gy * step), interpolation=cv2.INTER_LINEAR)


def warp_image(
    image: NDArray,
    source_from_output: Callable[[NDArray], NDArray],
    width: int,
    height: int,
    *,
    origin: tuple[float, float] = (0.0, 0.0),
    step: int = 8,
    interpolation: str = "linear",
    border_value: float | tuple[float, ...] = 0,
) -> tuple[NDArray, NDArray[np.bool_]]:
    """Render ``image`` into another pixel frame given the output-to-source mapping.

    Args:
        image: source image ``(H, W[, C])``.
        source_from_output: ``(N, 2)`` output coordinates -> ``(N, 2)`` source pixels (NaN = none).
        width, height: output size; output pixel ``(0, 0)`` is ``origin`` in output coordinates.
        step: evaluation spacing of the mapping (see :func:`source_map_from_function`).

    Returns:
        ``(warped, valid)``: the warped image and a ``(height, width)`` bool mask of output
        pixels whose source lies inside ``image``.
    """
    h, w = image.shape[:2]
    source_map = source_map_from_function(
        source_from_output, width, height, step=step, origin=origin, source_size=(w, h)
    )
    sx, sy = source_map[..., 0], source_map[..., 1]
    with np.errstate(invalid="ignore"):
        valid = (sx >= -0.5) & (sx <= w - 0.5) & (sy >= -0.5) & (sy <= h - 0.5)
    warped = remap(image, source_map, interpolation=interpolation, border_value=border_value)
    return warped, valid
