"""Local displacement-field refinement (paper section 5).

After the global (polyprojective) registration a frame still differs from the mid base image by a
few pixels that vary over the image (rolling shutter, non-planar city, residual optics). The paper
removes them with a field of displacement vectors: the registered frame and the mid base image are
cut into 200x200 neighbourhoods with centres 200 px apart, SIFT keypoints are matched inside each
neighbourhood, REQCON turns the matches into one consensus vector per neighbourhood, and the grid
of vectors is interpolated to every pixel (no smoothing).

Layout and direction (fixed by the project brief):

* :class:`DisplacementField` holds a regular grid: node ``(i, j)`` (row ``i``, column ``j``) sits at
  base pixel ``origin + (j, i) * spacing``; ``vectors`` is ``(Gy, Gx, 2)`` float32 ``(dx, dy)`` in
  base px; ``valid`` is ``(Gy, Gx)`` bool and marks the nodes whose vector was *measured*; vectors
  of the other nodes are filled from their neighbours, so ``vectors`` is always complete.
* ``registered_local(x) = registered_global(x + d(x))``: ``d(x)`` says where, in the globally
  registered frame (base coordinates), the content that belongs at base pixel ``x`` actually is.
  Hence ``base_to_frame_local(x) = base_to_frame_global(x + d(x))`` and ``frame_to_base_local(q)``
  solves ``x + d(x) = frame_to_base_global(q)`` (:func:`local_frame_to_base`).

Moving cars (the paper's warning, section 5): a neighbourhood's vector must come from the ground.
Three defences, each documented in :class:`LocalConfig`: neighbourhoods much larger than a road,
matches gated to a small displacement (the global residual is a few px, a car between two frames
moves more), and a guard that rejects a cell (i) whose rejected matches contain a second coherent
motion of similar support (two motions, we cannot tell which is the ground) or (ii) whose vector
disagrees with the median of its neighbours by more than a tolerance (a cell dominated by a
column of cars that all move alike). Rejected cells are filled from their neighbours.

This module is the stage's entry point (:func:`estimate_field`, the reference frame's and each
frame's field); the settings are in :mod:`registration.local.config`, the matching and per-cell
consensus in :mod:`registration.local.consensus`, the spline fit in :mod:`registration.local.spline`,
the DIS flow samples in :mod:`registration.matching.dense_flow`, and the field with its
application and inversion in :mod:`registration.geometry.displacement_field`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.coords import bbox_of, frame_outline
from registration.geometry import DisplacementField
from registration.lens import Camera
from registration.local.config import (
    FieldStats,
    LocalConfig,
)
from registration.local.consensus import (
    detect_keypoints,
    estimate_field_from_keypoints,
    estimate_field_from_matches,
)
from registration.matching import (
    FlowReference,
    FrameFlow,
    flow_matches,
    flow_samples,
    frame_flow_matches,
    joint_flow_reference,
)
from registration.matching import grey as matching_grey


def estimate_field(
    registered: NDArray,
    reference: NDArray,
    config: LocalConfig = LocalConfig(),
    *,
    valid_mask: NDArray | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
    reference_keypoints: Any | None = None,
) -> tuple[DisplacementField, FieldStats]:
    """Displacement field between a globally registered frame and the mid base image (paper 5).

    Args:
        registered: ``(H, W)`` grey uint8, frame k globally registered into base px; pixel
            ``(0, 0)`` is base ``origin``.
        reference: ``(H, W)`` grey uint8, the mid base image over the same crop.
        valid_mask: ``(H, W)`` bool, where both images have data (None = everywhere).
        origin: base px of the crop's pixel (0, 0).
        reference_keypoints: the reference's keypoints in base px if already detected (e.g. once
            per sequence over the whole mid base image); None = detect in ``reference``.

    Returns:
        ``(field, stats)``; ``field`` follows ``registered_local(x) = registered(x + d(x))``.
    """
    registered = np.asarray(registered)
    reference = np.asarray(reference)
    if registered.shape != reference.shape or registered.ndim != 2:
        raise ValueError(
            f"registered and reference must be grey images of one shape, got {registered.shape} "
            f"and {reference.shape}"
        )
    if registered.dtype != np.uint8 or reference.dtype != np.uint8:
        raise ValueError(
            f"registered and reference must be uint8, got {registered.dtype} and {reference.dtype}"
        )
    h, w = registered.shape
    t0 = time.perf_counter()
    if config.method == "flow":
        pos, disp = flow_matches(
            registered, reference, config, valid_mask=valid_mask, origin=origin
        )
        t1 = time.perf_counter()
        field_, stats = estimate_field_from_matches(
            pos, disp, w, h, config, origin=origin, valid_mask=valid_mask
        )
        return field_, replace(stats, time_detect_s=t1 - t0, time_total_s=time.perf_counter() - t0)
    kp_reg = detect_keypoints(registered, config, mask=valid_mask, origin=origin)
    if reference_keypoints is None:
        kp_ref = detect_keypoints(reference, config, mask=valid_mask, origin=origin)
    else:
        kp_ref = reference_keypoints
    t1 = time.perf_counter()
    field_, stats = estimate_field_from_keypoints(
        kp_reg, kp_ref, w, h, config, origin=origin, valid_mask=valid_mask
    )
    return field_, replace(stats, time_detect_s=t1 - t0, time_total_s=time.perf_counter() - t0)


def estimate_field_in_frame(
    frame_grey: NDArray[np.uint8],
    base_from_frame: Callable[[NDArray], NDArray],
    reference: FlowReference,
    config: LocalConfig = LocalConfig(),
    *,
    flow: FrameFlow | None = None,
) -> tuple[DisplacementField, FieldStats] | tuple[None, None]:
    """Displacement field of a frame against the mid base image from :func:`frame_flow_matches`
    (``method="flow"``), over the base-pixel box the frame covers; the per-cell consensus and the
    moving-car guard are those of :func:`estimate_field_from_matches`.

    Args:
        frame_grey: ``(H, W)`` uint8 raw frame.
        base_from_frame: the global mapping, ``(N, 2)`` raw frame px -> base px.
        reference: the mid base image (:func:`prepare_flow_reference`).
        flow: the frame's flow against ``reference`` when already measured (by the global stage,
            with raw frame px, through an earlier model: :func:`frame_flow`); None = measure it
            through ``base_from_frame``.

    Returns:
        ``(field, stats)``, or ``(None, None)`` when the frame covers no base pixels.
    """
    if config.method != "flow":
        raise ValueError(f"estimate_field_in_frame needs method='flow', got {config.method!r}")
    frame_grey = np.asarray(frame_grey)
    if frame_grey.ndim != 2 or frame_grey.dtype != np.uint8:
        raise ValueError(
            f"frame_grey must be a (H, W) uint8 image, got {frame_grey.shape} {frame_grey.dtype}"
        )
    t0 = time.perf_counter()
    h, w = frame_grey.shape
    hb, wb = reference.valid.shape
    outline = base_from_frame(frame_outline(w, h))
    outline = outline[np.isfinite(outline).all(axis=1)]
    if len(outline) < 3:
        return None, None
    x0, y0, x1, y1 = bbox_of(outline, (wb, hb))
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None, None
    if flow is None:
        pos, disp = frame_flow_matches(frame_grey, base_from_frame, reference, config)
    else:
        pos, disp = flow_samples(flow, base_from_frame, config)
    t1 = time.perf_counter()
    # Where both have data, for the per-cell "outside" test: the footprint and the mid base.
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillPoly(mask, [np.round(outline - (x0, y0)).astype(np.int32)], 1)
    mask &= reference.valid[y0:y1, x0:x1]
    field_, stats = estimate_field_from_matches(
        pos, disp, x1 - x0, y1 - y0, config, origin=(x0, y0), valid_mask=mask
    )
    return field_, replace(stats, time_detect_s=t1 - t0, time_total_s=time.perf_counter() - t0)


def config_dict(config: LocalConfig) -> dict[str, Any]:
    """The config as a plain dict (for result folders / JSON)."""
    return asdict(config)


def reference_field(fine, base_size: tuple[int, int], config: LocalConfig, footprint=None):
    """The reference frame's inter-sensor displacement field (beyond the paper) from its template
    control points: each match says where the base map shows what the global model puts at
    ``model(src)``, i.e. a sample ``d(dst) = model(src) - dst`` of the field of
    :mod:`registration.local`. The per-cell REQCON and the moving-car guard of the local stage
    turn them into a field; mismatches are outvoted by their neighbourhood.

    With ``config.fit == "spline"`` and ``footprint`` (``(N, 2)`` base px, the frame's outline
    under its global model), the field's nodes cover the whole footprint, not only the control
    points' extent: beyond the last control points (the corners, where the frame's radial
    correction stretches the ground most) the spline continues the field's slope.

    Returns ``(field, stats)``, or ``(None, None)`` without control points.
    """
    ok = np.isfinite(fine.src).all(axis=1) & np.isfinite(fine.dst).all(axis=1)
    if not ok.any():
        return None, None
    dst = fine.dst[ok]
    disp = fine.base_from_corrected.apply(fine.src[ok]) - dst
    wb, hb = base_size
    extent = dst
    if footprint is not None and config.fit == "spline":
        outline = np.asarray(footprint, np.float64).reshape(-1, 2)
        extent = np.r_[dst, outline[np.isfinite(outline).all(axis=1)]]
    x0, y0 = np.clip(np.floor(extent.min(axis=0)).astype(int), 0, (wb - 1, hb - 1))
    x1, y1 = np.clip(np.ceil(extent.max(axis=0)).astype(int) + 1, (x0 + 1, y0 + 1), (wb, hb))
    size, origin = (x1 - x0, y1 - y0), (x0, y0)
    field, stats = estimate_field_from_matches(dst, disp, *size, config, origin=origin)
    if field is None or not config.support_folds:
        return field, stats
    scale, held = field_support(dst, disp, size, origin, config)
    if scale < SUPPORT_KEEP:
        # Not kept where unconfirmed: zero vectors on the same lattice, so that the sequence
        # adjustment still makes the frame's local stage consistent with its neighbours' (a
        # frame without a field would be held at its global stage there).
        kept = node_support(field, *held) >= SUPPORT_KEEP
        vectors = np.where(kept[..., None], field.vectors, 0).astype(field.vectors.dtype)
        field = DisplacementField(field.origin, field.spacing, vectors, field.valid)
        stats = replace(stats, support_nodes=round(float(kept.mean()), 4))
    return field, replace(stats, support_scale=round(scale, 4))


# Held-out points whose displacement is largest are left out of the support's factor: template
# mismatches, which any field leaves as they are.
SUPPORT_TRIM = 0.2
# A factor of at least this keeps the field whole; under it only the nodes whose own factor
# reaches it are kept (:func:`node_support`), the others are zero vectors: a field the points
# support loses some of its amplitude to the held-out points' noise (0.93 on a simulated
# reference frame whose field is right and takes it from 0.71 to 0.09 px; scaled by it, 0.10
# px). On the real flyover, 35 of the 66 frames registered to the map confirm 0.80-1.00 and 31
# confirm 0.00-0.80, all but one from frame 424 on. Scaling an unconfirmed field instead of
# dropping it left the real OrthoLoC pair at 2.02 px (0.67 confirmed) where its global stage is
# 1.12; dropping the whole of it cost fields that are right but confirmed 0.71-0.80 (the long
# flight's anchors, below).
SUPPORT_KEEP = 0.8


def field_support(
    dst: NDArray, disp: NDArray, size: tuple[int, int], origin, config: LocalConfig
) -> tuple[float, tuple[NDArray, NDArray, NDArray]]:
    """How much of the field fitted to the samples (``dst`` ``(N, 2)`` base px, displacement
    ``disp`` ``(N, 2)``) samples it was not fitted to confirm: ``config.support_folds`` folds
    (a seeded permutation, so the same points give the same factor), each fold's samples
    predicted by the field of the others; the least-squares factor between prediction and
    displacement over the held-out samples (the ``SUPPORT_TRIM`` largest displacements left
    out), clipped to [0, 1]. 1 where too few samples to say.

    Measured on the real OrthoLoC photo (1024x768) against the official orthophoto: 0.59-0.67
    against the one of another date (0.67 with 5 folds), where the field took the frame from
    1.12 to 2.75 px mean off the reference registration (scaled by the factor: 2.02); 1.01-1.04
    against the one of the same date, where it helps (1.00 -> 0.93, scaled by 1)."""
    k = config.support_folds
    none = np.empty((0, 2))
    if len(dst) < 2 * k * config.min_matches:
        return 1.0, (none, none, none)
    fold = np.random.default_rng(0).permutation(len(dst)) % k
    at, held, predicted = [], [], []
    for f in range(k):
        train = fold != f
        part, _ = estimate_field_from_matches(dst[train], disp[train], *size, config, origin=origin)
        if part is not None:
            at.append(dst[~train])
            held.append(disp[~train])
            predicted.append(part.sample(dst[~train], outside="clamp"))
    if not held:
        return 1.0, (none, none, none)
    x, d, p = np.concatenate(at), np.concatenate(held), np.concatenate(predicted)
    ok = np.isfinite(p).all(axis=1)
    x, d, p = x[ok], d[ok], p[ok]
    if not len(d):
        return 1.0, (none, none, none)
    keep = np.hypot(*d.T) <= np.quantile(np.hypot(*d.T), 1.0 - SUPPORT_TRIM)
    x, d, p = x[keep], d[keep], p[keep]
    denominator = float(np.sum(p**2))
    if denominator <= 0:
        return 1.0, (x, d, p)
    return float(np.clip(np.sum(d * p) / denominator, 0.0, 1.0)), (x, d, p)


def node_support(field: DisplacementField, at: NDArray, held: NDArray, predicted: NDArray):
    """``(Gy, Gx)`` the factor of :func:`field_support` node by node: the held-out samples
    (base px ``at`` ``(N, 2)``, displacement ``held``, the other folds' field there
    ``predicted``) weighted by a Gaussian of ``NODE_RADIUS`` node spacings about each node. A
    node with less than ``NODE_MIN_WEIGHT`` samples' weight near it gets 0 (nothing confirms
    it)."""
    nodes = field.node_xy.reshape(-1, 2)
    if not len(at):
        return np.zeros(field.shape)
    agree, power = np.sum(held * predicted, axis=1), np.sum(predicted**2, axis=1)
    num, den, weight = (np.empty(len(nodes)) for _ in range(3))
    # Nodes a block at a time: a weight matrix of every node and sample at once can reach
    # hundreds of MB for a large field.
    for i in range(0, len(nodes), 256):
        d2 = np.sum((nodes[i : i + 256, None, :] - at[None, :, :]) ** 2, axis=2)
        w = np.exp(-0.5 * d2 / (NODE_RADIUS * field.spacing) ** 2)
        num[i : i + 256], den[i : i + 256], weight[i : i + 256] = w @ agree, w @ power, w.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where((weight >= NODE_MIN_WEIGHT) & (den > 0), num / den, 0.0)
    return np.clip(factor, 0.0, 1.0).reshape(field.shape)


# A node is confirmed by the held-out samples of the cell it stands for: Gaussian weights with
# a standard deviation of half the node spacing, and at least this much weight. Measured: the
# 120-frame long flight's anchors (whole fields confirmed 0.71-0.80, right) keep their
# confirmed nodes, 0.382 -> 0.375 px after the local stage, its last tenth 1.14x -> 1.09x the
# first; the real OrthoLoC pair (0.67 confirmed, the field wrong) keeps 2 % of its nodes,
# 1.12 -> 1.13 px. Weights over a whole spacing kept more: long flight 0.366 px but 1.11x,
# OrthoLoC 1.23 px (10 % of its nodes).
NODE_RADIUS = 0.5
NODE_MIN_WEIGHT = 8.0


def frame_field(frame, camera: Camera, model, joint, config: LocalConfig, flow=None):
    """The displacement field of an intra-sensor frame against the mid base image (paper
    section 5): ``frame`` raw (H, W[, 3]) taken by ``camera``, ``model`` its
    ``base_from_corrected``, ``joint`` the :class:`registration.global_registration.joint_base.JointBase`
    (its flow reference or keypoints are prepared once and kept there), ``flow`` the frame's
    :class:`FrameFlow` (raw frame px) when the global stage measured it already. Returns
    ``(field, stats)`` or ``(None, None)``."""
    from registration.render import render_to_base

    hb, wb = joint.mid_grey.shape
    camera.check(frame)
    w = camera.width

    def base_from_raw(q):
        return model.apply(camera.corrected_from_raw(q))

    grey = matching_grey.to_grey(frame)
    if config.method == "flow":
        # Measured in the frame's geometry: no rendering of the frame into base pixels.
        reference = joint_flow_reference(joint, w, config)
        return estimate_field_in_frame(grey, base_from_raw, reference, config, flow=flow)
    box = bbox_of(model.apply(camera.outline()), (wb, hb), 2)
    x0, y0, x1, y1 = box
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None, None
    registered, valid = render_to_base(grey, camera, model, box)
    reference = joint.mid_grey[y0:y1, x0:x1]
    both = valid & joint.mid_valid[y0:y1, x0:x1]
    # The mid base image is the reference of every frame: detect its keypoints once.
    keypoints = joint.derived.get(
        "local_keypoints", lambda: detect_keypoints(joint.mid_grey, config, mask=joint.mid_valid)
    )
    return estimate_field(
        registered,
        reference,
        config,
        valid_mask=both,
        origin=(x0, y0),
        reference_keypoints=keypoints,
    )
