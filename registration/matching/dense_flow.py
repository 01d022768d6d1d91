"""Dense samples for the local stage from DIS optical flow (``LocalConfig.method = "flow"``):
flow between a registered crop and the reference, and the frame-side flow against a prepared
mid base image (:class:`FlowReference`). See :mod:`registration.local` for the stage itself.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.coords import rescale
from registration.geometry import warp
from registration.matching import grey as matching_grey


class FlowSettings(Protocol):
    """The flow's settings, as :class:`registration.local.LocalConfig` holds them (the local stage
    and, in the ``fast`` preset, the intra-sensor control points share one flow per frame). Sizes
    in frame px; see ``LocalConfig`` for each field's meaning and default."""

    flow_preset: str
    flow_refinement_iterations: int | None
    flow_patch_stride: int | None
    flow_scale: float
    flow_min_width_px: int
    flow_step_px: int
    flow_margin_px: int
    max_displacement_px: float


DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def flow_matches(
    registered: NDArray,
    reference: NDArray,
    config: FlowSettings,
    *,
    valid_mask: NDArray | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Matches for ``method="flow"``: dense DIS optical flow (Kroeger et al. 2016,
    cv2.DISOpticalFlow) from the reference to the registered image, sampled every
    ``flow_step_px`` where both images have data at least ``flow_margin_px`` around.

    The flow at reference pixel ``x`` is where ``x``'s content sits in the registered image,
    i.e. a displacement sample ``d(x)``; each sample votes in its neighbourhood exactly like a
    SIFT match, so REQCON and the moving-car guard apply unchanged.

    Returns:
        ``(pos, disp)``: ``(M, 2)`` base px of the samples and ``(M, 2)`` displacements.
    """
    h, w = reference.shape
    dis = dis_flow(config)
    flow = dis.calc(np.ascontiguousarray(reference), np.ascontiguousarray(registered), None)
    step = config.flow_step_px
    ys, xs = np.mgrid[step // 2 : h : step, step // 2 : w : step]
    if valid_mask is not None:
        k = 2 * config.flow_margin_px + 1
        inner = cv2.erode((np.asarray(valid_mask) > 0).astype(np.uint8), np.ones((k, k), np.uint8))
        ok = inner[ys, xs] > 0
        ys, xs = ys[ok], xs[ok]
    else:
        m = config.flow_margin_px
        ok = (xs >= m) & (xs < w - m) & (ys >= m) & (ys < h - m)
        ys, xs = ys[ok], xs[ok]
    pos = np.c_[xs.ravel(), ys.ravel()].astype(np.float64) + np.asarray(origin, np.float64)
    disp = flow[ys.ravel(), xs.ravel()].astype(np.float64)
    # The gate of the SIFT path: a residual beyond max_displacement_px is not the ground.
    keep = np.einsum("ij,ij->i", disp, disp) <= config.max_displacement_px**2
    return pos[keep], disp[keep]


@dataclass(frozen=True)
class FlowReference:
    """The mid base image prepared once per sequence for :func:`estimate_field_in_frame`.

    Attributes:
        valid: ``(Hb, Wb)`` bool, where the mid base image has content (base px).
        small: the grey mid base image resampled with area averaging to
            ``(round(Hb * scale), round(Wb * scale))``.
        small_valid: ``small``'s pixels whose every source pixel is valid.
        scale_xy: ``small`` px = ``(base px + 0.5) * scale_xy - 0.5`` (per axis: exact also when
            ``Wb * scale`` is not an integer).
    """

    valid: NDArray[np.bool_]
    small: NDArray[np.uint8]
    small_valid: NDArray[np.bool_]
    scale_xy: NDArray[np.float64]


def prepare_flow_reference(
    grey: NDArray[np.uint8], valid: NDArray[np.bool_], scale: float
) -> FlowReference:
    """See :class:`FlowReference`; ``grey`` and ``valid`` are ``(Hb, Wb)`` in base px."""
    small, scale_xy = _area_resize(grey, scale)
    small_valid, _ = _area_resize(valid.astype(np.uint8) * 255, scale)
    return FlowReference(np.asarray(valid, bool), small, small_valid == 255, scale_xy)


def joint_flow_reference(joint, width: int, config: FlowSettings) -> FlowReference:
    """The flow reference of the joint base's mid base image for ``width`` px wide frames,
    prepared once and kept in ``joint.derived`` (``JointBase.derived``)."""
    return joint.derived.get(
        "flow_reference",
        lambda: prepare_flow_reference(joint.mid_grey, joint.mid_valid, flow_scale(width, config)),
    )


def _area_resize(image: NDArray, scale: float) -> tuple[NDArray, NDArray[np.float64]]:
    """``image`` resampled by about ``scale`` (:func:`features.downscale`) and the exact
    per-axis scale of the result."""
    if scale == 1:
        return image, np.ones(2)
    out = matching_grey.downscale(image, scale)
    return out, np.array([out.shape[1] / image.shape[1], out.shape[0] / image.shape[0]])


def dis_flow(config: FlowSettings):
    """OpenCV's DIS optical flow with ``config``'s preset and refinement."""
    dis = cv2.DISOpticalFlow_create(DIS_PRESETS[config.flow_preset])
    if config.flow_refinement_iterations is not None:
        dis.setVariationalRefinementIterations(config.flow_refinement_iterations)
    if config.flow_patch_stride is not None:
        dis.setPatchStride(config.flow_patch_stride)
    return dis


def flow_scale(width: int, config: FlowSettings) -> float:
    """The scale the flow of a ``width`` px wide frame is computed at (``flow_scale``, raised
    so the flow image is at least ``flow_min_width_px`` wide)."""
    if config.flow_min_width_px <= 0:
        return config.flow_scale
    return max(config.flow_scale, min(1.0, config.flow_min_width_px / width))


@dataclass(frozen=True)
class FrameFlow:
    """Correspondences of a frame with the mid base image from one dense DIS flow
    (:func:`frame_flow`), in two samplings.

    Attributes:
        frame_xy: ``(N, 2)`` frame px where the frame shows the content of ``base_xy``: the
            samples every ``flow_step_px`` that the local stage votes with.
        base_xy: ``(N, 2)`` base px.
        point_frame_xy, point_base_xy: ``(P, 2)`` the same every ``point_step_px``, from the
            flow averaged over ``FLOW_POINT_BOX`` flow pixels: control points for the global
            model (empty without ``point_step_px``).
    """

    frame_xy: NDArray[np.float64]
    base_xy: NDArray[np.float64]
    point_frame_xy: NDArray[np.float64]
    point_base_xy: NDArray[np.float64]


# Control points from the flow (FrameFlow.point_*) are read from the flow averaged over this many
# flow pixels square: a single flow pixel carries the noise of one DIS patch; the average, like
# a template, pools the flow over ~10 frame px (at 2560x1920: 5 px at half scale). Little rides
# on it: boxes of 5, 9 and 15 flow px gave 0.623, 0.627 and 0.623 px after global on the tests'
# 640x480 sequence (the fast preset).
FLOW_POINT_BOX = 5


def frame_flow(
    frame_grey: NDArray[np.uint8],
    base_from_frame: Callable[[NDArray], NDArray],
    reference: FlowReference,
    config: FlowSettings,
    *,
    point_step_px: int = 0,
) -> FrameFlow:
    """Dense correspondences of a frame with the mid base image, measured in the frame's own
    geometry.

    The mid base image is warped into the frame (at :func:`flow_scale`) through
    ``base_from_frame``, and DIS optical flow runs from it to the frame: where the warped
    reference shows base point ``B`` at frame point ``p`` (``B = g(p)`` as the warp's map
    interpolates it, :func:`registration.geometry.warp.lattice_source`), the frame shows that content at
    ``p + f(p)``. So ``(p + f(p), B)`` is a correspondence whatever ``g`` is, as long as ``g`` is
    within the flow's reach (a few px): the coarse model serves for the global model's control
    points and any later model for the local field (:func:`flow_samples`). The frame is never
    resampled, and the costly inverse of ``g`` is never evaluated.

    Args:
        frame_grey: ``(H, W)`` uint8 frame.
        base_from_frame: ``(N, 2)`` frame px -> base px (NaN = none).
        reference: the mid base image (:func:`prepare_flow_reference`).
        point_step_px: also sample the averaged flow every this many frame px
            (``FrameFlow.point_*``); 0 = not.
    """
    h, w = frame_grey.shape
    s = flow_scale(w, config)
    small, s = _area_resize(frame_grey, s)
    hs, ws = small.shape
    rs = reference.scale_xy

    def base_from_small(p: NDArray) -> NDArray:
        return base_from_frame(rescale(p, 1.0 / s))

    smap = warp.source_map_from_function(lambda p: rescale(base_from_small(p), rs), ws, hs, step=8)
    warped = warp.remap(reference.small, smap, interpolation="linear")
    # Map pixels without a source (NaN) sample outside the image, which reads as no content.
    both = warp.remap(warp.as_uint8_mask(reference.small_valid), smap, interpolation="nearest") > 0
    flow = dis_flow(config).calc(warped, np.ascontiguousarray(small), None)

    def sample(flow_img: NDArray, step: int, margin: int) -> tuple[NDArray, NDArray]:
        inner = cv2.erode(both.astype(np.uint8), np.ones((2 * margin + 1,) * 2, np.uint8))
        ys, xs = np.mgrid[step // 2 : hs : step, step // 2 : ws : step]
        ok = inner[ys, xs] > 0
        ys, xs = ys[ok], xs[ok]
        p = np.c_[xs, ys].astype(np.float64)
        # The base point whose content the warped reference shows at p: the map as rendered
        # (between its lattice nodes), not the model at p, which parts from it by tenths of
        # a px in a strongly corrected frame's corners.
        base = rescale(smap[ys, xs].astype(np.float64), 1.0 / rs)
        frame_xy = rescale(p + flow_img[ys, xs], 1.0 / s)
        keep = np.isfinite(base).all(axis=1) & np.isfinite(frame_xy).all(axis=1)
        return frame_xy[keep], base[keep]

    margin = round(config.flow_margin_px * s[0])
    frame_xy, base_xy = sample(flow, max(1, round(config.flow_step_px * s[0])), margin)
    points = (np.zeros((0, 2)), np.zeros((0, 2)))
    if point_step_px:
        averaged = cv2.blur(flow, (FLOW_POINT_BOX, FLOW_POINT_BOX))
        points = sample(averaged, max(1, round(point_step_px * s[0])), margin + FLOW_POINT_BOX // 2)
    return FrameFlow(frame_xy, base_xy, *points)


def flow_samples(
    flow: FrameFlow, base_from_frame: Callable[[NDArray], NDArray], config: FlowSettings
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The local stage's samples of a :class:`FrameFlow` under the frame's global mapping
    ``base_from_frame``: ``(pos, disp)``, ``(M, 2)`` base px ``B`` and ``d(B) = g(p + f(p)) - B``,
    the field of :mod:`registration.local` at ``B`` (exact through ``g``), within
    ``max_displacement_px``."""
    pos = flow.base_xy
    disp = np.asarray(base_from_frame(flow.frame_xy), np.float64) - pos
    keep = np.isfinite(disp).all(axis=1)
    keep[keep] = np.einsum("ij,ij->i", disp[keep], disp[keep]) <= config.max_displacement_px**2
    return pos[keep], disp[keep]


def frame_flow_matches(
    frame_grey: NDArray[np.uint8],
    base_from_frame: Callable[[NDArray], NDArray],
    reference: FlowReference,
    config: FlowSettings,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Displacement samples against the mid base image, measured in the frame's own geometry
    through the global mapping ``base_from_frame`` (:func:`frame_flow` then
    :func:`flow_samples` with the same mapping).

    Args:
        frame_grey: ``(H, W)`` uint8 raw frame.
        base_from_frame: the global mapping, ``(N, 2)`` raw frame px -> base px (NaN = none).
        reference: the mid base image (:func:`prepare_flow_reference`).

    Returns:
        ``(pos, disp)``: ``(M, 2)`` base px ``B`` and displacements ``d(B)``, base px.
    """
    flow = frame_flow(frame_grey, base_from_frame, reference, config)
    return flow_samples(flow, base_from_frame, config)
