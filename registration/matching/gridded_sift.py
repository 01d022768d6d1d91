"""Gridded SIFT control points (paper 4.4): keypoints in small windows on a grid, each matched only
to the keypoints of its corresponding window in the reference.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from registration import coords
from registration.matching.control_points import ControlPoints, PointFunction, call_points
from registration.matching.grey import to_grey
from registration.matching.sift import Keypoints, SiftConfig, detect_sift

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Gridded SIFT (paper 4.4)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GriddedSiftConfig:
    """The fine intra-sensor control points (paper 4.4).

    Attributes:
        window_px: side of the square windows around the grid centres in the frame in which
            keypoints are kept, frame px (50, paper 4.4 "50 x 50 templates").
        spacing_px: distance between window centres, frame px (100, paper 4.4).
        ratio: Lowe's ratio test inside each window pair (0.8, Lowe 2004; the paper gives none).
        decimate: keep one match in this many of the combined list of all references (3,
            paper 4.4 "the combined base and previous image list was decimated by a factor of
            3"); 1 keeps all. See :func:`gridded_sift_control_points` for the order.
        window_margin_px: the reference window is the bounding box of the frame window's
            corners mapped by ``ref_from_frame``, grown by this many reference px on each side
            (25; beyond the paper's exact 50 px window: it absorbs the residual error of the
            coarse model, and the box of mapped corners absorbs scale and rotation).
        sift: detector settings (frame and reference alike).
    """

    window_px: int = 50
    spacing_px: int = 100
    ratio: float = 0.8
    decimate: int = 3
    window_margin_px: float = 25.0
    sift: SiftConfig = field(default_factory=SiftConfig)

    @classmethod
    def paper(cls) -> GriddedSiftConfig:
        """The paper's choices (4.4): the reference window is exactly the mapped 50 x 50 window
        (no margin)."""
        return cls(window_margin_px=0.0)

    def __post_init__(self) -> None:
        if self.window_px < 1 or self.spacing_px < 1:
            raise ValueError(
                f"GriddedSiftConfig.window_px and spacing_px must be >= 1, got {self.window_px}, {self.spacing_px}"
            )
        if self.decimate < 1:
            raise ValueError(f"GriddedSiftConfig.decimate must be >= 1, got {self.decimate}")
        if not 0 < self.ratio <= 1:
            raise ValueError(f"GriddedSiftConfig.ratio must be in (0, 1], got {self.ratio}")
        if self.window_margin_px < 0:
            raise ValueError(
                f"GriddedSiftConfig.window_margin_px must be >= 0, got {self.window_margin_px}"
            )


@dataclass(frozen=True)
class GriddedReference:
    """One reference image for :func:`gridded_sift_control_points`.

    Attributes:
        image: the reference image (anything :func:`to_grey` accepts).
        ref_from_frame: frame px -> reference px, ``(N, 2) -> (N, 2)``.
        frame_from_ref: reference px -> frame px (accepted for symmetry; not needed here).
        keypoints: precomputed keypoints of ``image`` (e.g. of the mid base image, computed
            once per sequence); None = detect them inside the needed windows only.
        valid: ``(H, W)`` bool, where ``image`` has content (None = everywhere); used by the
            template matcher's fallbacks.
        other_sensor: the image was taken by another sensor or at another time than the
            frames (the base map; not the mid base image or the previous frame): the template
            matcher's change test (``TemplateConfig.change_log_ratio``) applies to it.
    """

    image: NDArray
    ref_from_frame: PointFunction
    frame_from_ref: PointFunction | None = None
    keypoints: Keypoints | None = None
    valid: NDArray | None = None
    other_sensor: bool = False


Reference = GriddedReference  # short alias used by the pipeline


def window_centres(
    width: int, height: int, config: GriddedSiftConfig = GriddedSiftConfig()
) -> NDArray[np.float64]:
    """``(N, 2)`` centres of the gridded-SIFT windows: a grid with ``spacing_px`` spacing,
    centred in the frame, every window fully inside it (row-major order)."""
    w = config.window_px
    axes = []
    for n_px in (width, height):
        span = n_px - w  # room for window origins 0..n_px - w
        if span < 0:
            return np.zeros((0, 2))
        count = span // config.spacing_px + 1
        first = (span - (count - 1) * config.spacing_px) / 2 + (w - 1) / 2
        axes.append(first + config.spacing_px * np.arange(count))
    gx, gy = np.meshgrid(axes[0], axes[1], indexing="xy")
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def _as_reference(entry: GriddedReference | tuple, k: int) -> GriddedReference:
    if isinstance(entry, GriddedReference):
        return entry
    if isinstance(entry, tuple) and len(entry) in (3, 4):
        return GriddedReference(*entry)
    raise ValueError(
        f"refs[{k}] must be a GriddedReference or a (ref_grey, ref_from_frame, frame_from_ref"
        f"[, keypoints]) tuple, got {type(entry).__name__}"
    )


def gridded_sift_control_points(
    frame_grey: NDArray,
    refs: Sequence[GriddedReference | tuple],
    config: GriddedSiftConfig = GriddedSiftConfig(),
    *,
    frame_keypoints: Keypoints | None = None,
) -> ControlPoints:
    """Gridded SIFT control points (paper 4.4 steps 1-6).

    SIFT runs once on the frame (restricted by a mask to the ``window_px`` windows on the
    ``spacing_px`` grid) and once per reference (restricted to the predicted reference windows,
    unless precomputed keypoints are given); detecting on the whole image and bucketing is far
    cheaper than one detection per window. Each frame window's keypoints are matched, with the
    ratio test, only against the reference keypoints inside its corresponding window: the
    bounding box of the window's corners mapped by ``ref_from_frame``, grown by
    ``window_margin_px``.

    The lists of all references are combined (``source`` = index into ``refs``) and decimated by
    ``config.decimate``: sorted by window (row-major) and, within a window, by decreasing score,
    then every ``decimate``-th entry is kept starting with the first. This keeps exactly
    ``ceil(N / decimate)`` points, spread evenly over the windows, best first in each.

    Args:
        frame_grey: the frame, ``(H, W)`` (anything :func:`to_grey` accepts).
        refs: references (paper: the mid base image and the previous registered frame), each a
            :class:`GriddedReference` or a tuple ``(ref_grey, ref_from_frame, frame_from_ref[,
            keypoints])``.
        config: grid, matching and decimation settings.
        frame_keypoints: precomputed keypoints of the whole frame (optional).

    Returns:
        :class:`ControlPoints`: ``src`` frame px, ``dst`` reference px, ``score`` = 1 - Lowe ratio,
        ``source`` = reference index.
    """
    frame = to_grey(frame_grey)
    fw, fh = coords.image_size(frame)
    references = [_as_reference(e, k) for k, e in enumerate(refs)]
    centres = window_centres(fw, fh, config)
    if len(centres) == 0 or not references:
        return ControlPoints.empty()
    half = (config.window_px - 1) / 2

    if frame_keypoints is None:
        frame_keypoints = _detect_in_frame_windows(frame, centres, config)
    order, bounds = _bucket_by_window(frame_keypoints.xy, centres, config)

    # Window corners in the frame, (N, 4, 2).
    corners = centres[:, None, :] + half * np.array(
        [[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64
    )
    parts: list[tuple[NDArray, ...]] = []
    for k, ref_entry in enumerate(references):
        parts.extend(
            _match_reference(frame_keypoints, order, bounds, corners, ref_entry, k, config)
        )
    if not parts:
        return ControlPoints.empty()
    return _combine_and_decimate(parts, len(centres), config.decimate)


def _detect_in_frame_windows(
    frame: NDArray, centres: NDArray[np.float64], config: GriddedSiftConfig
) -> Keypoints:
    """SIFT on the ``(H, W)`` grey frame, masked to the ``window_px`` windows around the
    ``(N, 2)`` frame-px ``centres``."""
    fw, fh = coords.image_size(frame)
    half = (config.window_px - 1) / 2
    mask = np.zeros((fh, fw), np.uint8)
    for cx, cy in centres:
        x0, y0 = int(math.ceil(cx - half)), int(math.ceil(cy - half))
        mask[y0 : y0 + config.window_px, x0 : x0 + config.window_px] = 1
    return detect_sift(frame, config.sift, mask)


def _bucket_by_window(
    fxy: NDArray[np.float64], centres: NDArray[np.float64], config: GriddedSiftConfig
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Bucket the ``(K, 2)`` frame keypoints ``fxy`` (frame px) by window: nearest grid centre,
    then inside that window?

    Returns:
        ``(order, bounds)``: ``order`` ``(K,)`` keypoint indices sorted by window (those in no
        window first), ``bounds`` ``(N + 1,)``: window ``w``'s keypoints are
        ``order[bounds[w]:bounds[w + 1]]``.
    """
    half = (config.window_px - 1) / 2
    fx0, fy0 = centres[0]
    nx = len(np.unique(centres[:, 0]))
    ny = len(centres) // nx
    gi = (
        np.round((fxy[:, 0] - fx0) / config.spacing_px).astype(np.int64)
        if len(fxy)
        else np.zeros(0, np.int64)
    )
    gj = (
        np.round((fxy[:, 1] - fy0) / config.spacing_px).astype(np.int64)
        if len(fxy)
        else np.zeros(0, np.int64)
    )
    inside = (gi >= 0) & (gi < nx) & (gj >= 0) & (gj < ny)
    win_of = np.where(inside, gj * nx + gi, -1)
    cxy = centres[np.clip(win_of, 0, len(centres) - 1)]
    inside &= (np.abs(fxy - cxy) <= half + 1e-9).all(axis=1) if len(fxy) else inside
    win_of[~inside] = -1
    order = np.argsort(win_of, kind="stable")
    bounds = np.searchsorted(win_of[order], np.arange(len(centres) + 1))
    return order, bounds


def _reference_windows(
    ref_entry: GriddedReference,
    k: int,
    corners: NDArray[np.float64],
    margin: float,
    rw: int,
    rh: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Each frame window's window in reference ``k`` (a ``rw`` x ``rh`` image): the bounding box
    of its ``(N, 4, 2)`` frame-px ``corners`` mapped by ``ref_from_frame``, grown by ``margin``
    reference px.

    Returns:
        ``(lo, hi, usable)``: ``(N, 2)`` box corners, reference px, and ``(N,)`` bool, the box is
        finite and overlaps the image.
    """
    mapped = call_points(
        ref_entry.ref_from_frame, corners.reshape(-1, 2), f"refs[{k}].ref_from_frame"
    )
    mapped = mapped.reshape(-1, 4, 2)
    lo = np.nanmin(mapped, axis=1) - margin
    hi = np.nanmax(mapped, axis=1) + margin
    usable = (
        np.isfinite(mapped).all(axis=(1, 2))
        & (hi[:, 0] >= 0)
        & (hi[:, 1] >= 0)
        & (lo[:, 0] <= rw - 1)
        & (lo[:, 1] <= rh - 1)
    )
    return lo, hi, usable


def _detect_in_boxes(
    ref: NDArray, lo: NDArray[np.float64], hi: NDArray[np.float64], config: GriddedSiftConfig
) -> Keypoints:
    """SIFT on the ``(H, W)`` grey reference, masked to the ``(M, 2)`` boxes ``lo``..``hi``
    (reference px, clipped to the image)."""
    rw, rh = coords.image_size(ref)
    mask = np.zeros((rh, rw), np.uint8)
    for a, b in zip(lo, hi, strict=True):
        x0, y0 = max(0, int(math.floor(a[0]))), max(0, int(math.floor(a[1])))
        x1, y1 = min(rw - 1, int(math.ceil(b[0]))), min(rh - 1, int(math.ceil(b[1])))
        mask[y0 : y1 + 1, x0 : x1 + 1] = 1
    return detect_sift(ref, config.sift, mask)


def _match_reference(
    frame_keypoints: Keypoints,
    order: NDArray[np.int64],
    bounds: NDArray[np.int64],
    corners: NDArray[np.float64],
    ref_entry: GriddedReference,
    k: int,
    config: GriddedSiftConfig,
) -> list[tuple[NDArray, ...]]:
    """Match the frame's keypoints window by window against reference ``k``'s keypoints inside
    the corresponding reference window (ratio test).

    Args:
        frame_keypoints: the frame's keypoints, bucketed by ``order``/``bounds``
            (:func:`_bucket_by_window`).
        corners: ``(N, 4, 2)`` window corners, frame px.

    Returns:
        One ``(src (n, 2) frame px, dst (n, 2) reference px, score (n,), window (n,),
        source (n,))`` tuple per window with matches, in window order; empty if no window of
        the reference is usable or it has fewer than 2 keypoints.
    """
    ref = to_grey(ref_entry.image)
    rw, rh = coords.image_size(ref)
    lo, hi, usable = _reference_windows(ref_entry, k, corners, config.window_margin_px, rw, rh)
    if not usable.any():
        return []
    ref_kp = ref_entry.keypoints
    if ref_kp is None:
        ref_kp = _detect_in_boxes(ref, lo[usable], hi[usable], config)
    if len(ref_kp) < 2:
        return []
    rorder = np.argsort(ref_kp.xy[:, 0], kind="stable")
    rx_sorted = ref_kp.xy[rorder, 0]
    ry = ref_kp.xy[:, 1]
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    parts: list[tuple[NDArray, ...]] = []
    for w in np.flatnonzero(usable):
        f_idx = order[bounds[w] : bounds[w + 1]]
        if len(f_idx) == 0:
            continue
        a0, a1 = np.searchsorted(rx_sorted, [lo[w, 0], hi[w, 0]], side="left")
        cand = rorder[a0:a1]
        cand = cand[(ry[cand] >= lo[w, 1]) & (ry[cand] <= hi[w, 1])]
        if len(cand) < 2:
            continue
        knn = matcher.knnMatch(frame_keypoints.descriptors[f_idx], ref_kp.descriptors[cand], k=2)
        rows = [
            (m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance)
            for m in knn
            if len(m) == 2 and m[0].distance < config.ratio * m[1].distance
        ]
        if not rows:
            continue
        r = np.array(rows, np.float64)
        qi, ti = r[:, 0].astype(np.int64), r[:, 1].astype(np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            score = 1.0 - np.where(r[:, 3] > 0, r[:, 2] / r[:, 3], 1.0)
        n = len(r)
        parts.append(
            (
                frame_keypoints.xy[f_idx[qi]],
                ref_kp.xy[cand[ti]],
                score,
                np.full(n, w, np.int64),
                np.full(n, k, np.int64),
            )
        )
    return parts


def _combine_and_decimate(
    parts: list[tuple[NDArray, ...]], n_windows: int, decimate: int
) -> ControlPoints:
    """Concatenate the per-window match tuples of all references (see
    :func:`_match_reference`) and decimate (paper 4.4): order by window, then best score first,
    keep every ``decimate``-th."""
    src, dst, score, win, source = (np.concatenate(c) for c in zip(*parts, strict=True))
    order_all = np.lexsort((source, -score, win))[::decimate]
    logger.debug(
        "gridded SIFT: %d matches over %d windows, %d kept after decimation by %d",
        len(src),
        n_windows,
        len(order_all),
        decimate,
    )
    return ControlPoints(src[order_all], dst[order_all], score[order_all], source[order_all])
