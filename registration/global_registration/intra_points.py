"""Control points of a frame for its fine polyprojective step (paper 4.3.2 and 4.4), all with
``src`` in corrected-frame px and ``dst`` in the reference's px.

* :func:`template_points`: the template grid against one base-pixel reference (4.3.2).
* :func:`gridded_points`: gridded SIFT against the mid base image and the previous frame (4.4).
* :func:`intra_template_points`: templates against the mid base image, then the previous frame
  and the base map where the ones before have no content (the default preset).
* :func:`flow_points`: beyond the paper, the fast preset's: points drawn from the dense flow of
  the frame against the mid base image (the flow the local stage then reuses), templates only
  along the frame's border and where the flow has no points.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from registration.matching import (
    ControlPoints,
    FrameFlow,
    edge_ring,
    frame_flow,
    grid_spacing,
    gridded_sift,
    joint_flow_reference,
    sift,
    template_control_points,
    template_grid,
)
from registration.matching.dense_flow import FlowSettings


def template_points(
    view, reference, base_from_corrected, template_cfg, *, ref_valid=None, fallback=None,
    centres=None, ref_other_sensor=True,
) -> ControlPoints:  # fmt: skip
    """Template control points of the view (:class:`registration.global_registration.coarse_records.FrameView`) against a
    base-pixel reference (and fallback references, see
    :func:`registration.matching.templates.template_control_points`; ``centres`` replace the grid and
    its edge ring; ``ref_other_sensor``: the reference is the base map, not an image made
    from the video)."""
    model = base_from_corrected
    cps = template_control_points(
        view.grey,
        reference,
        lambda xy: model.apply(view.to_corrected(xy)),
        lambda b: view.from_corrected(model.inverse(b)),
        template_cfg,
        ref_valid=ref_valid,
        fallback=fallback,
        centres=centres,
        ref_other_sensor=ref_other_sensor,
    )
    return points_to_corrected(cps, view)


def points_to_corrected(cps: ControlPoints, view) -> ControlPoints:
    """``cps`` with ``src`` moved from the view's pixels to corrected-frame pixels."""
    if view.lens is None or not len(cps.src):
        return cps
    return ControlPoints(view.to_corrected(cps.src), cps.dst, cps.score, cps.source)


def gridded_points(view, frame_sift, model, joint, prev, cfg) -> ControlPoints:
    """Gridded-SIFT control points against the mid base image and the previous frame (paper
    4.4), ``src`` corrected px."""
    mid_sift = joint.derived.get(
        "mid_sift",
        lambda: sift.detect_sift(
            joint.mid_grey, cfg.gridded.sift, mask=joint.mid_valid.astype(np.uint8)
        ),
    )
    refs_fine = [
        gridded_sift.Reference(
            joint.mid_grey,
            lambda xy: model.apply(view.to_corrected(xy)),
            lambda b: view.from_corrected(model.inverse(b)),
            mid_sift,
        )
    ]
    if prev is not None:
        p = prev.base_from_corrected
        pv = prev.view
        if prev.sift is None:
            prev.sift = sift.detect_sift(pv.grey, cfg.gridded.sift)
        refs_fine.append(
            gridded_sift.Reference(
                pv.grey,
                lambda xy: pv.from_corrected(p.inverse(model.apply(view.to_corrected(xy)))),
                lambda xy: view.from_corrected(model.inverse(p.apply(pv.to_corrected(xy)))),
                prev.sift,
            )
        )
    cps = gridded_sift.gridded_sift_control_points(
        view.grey, refs_fine, cfg.gridded, frame_keypoints=frame_sift
    )
    return points_to_corrected(cps, view)


def intra_template_points(
    view, model, joint, prev, cfg, *, template_cfg=None, centres=None
) -> ControlPoints:
    """Template control points against the mid base image, then the previous frame and the
    base map where the ones before have no content (``src`` corrected px); ``template_cfg``
    replaces ``cfg.template``, ``centres`` the grid and its edge ring."""
    fallbacks = []
    if prev is not None:
        p, pv = prev.base_from_corrected, prev.view
        fallbacks.append(gridded_sift.Reference(
            pv.grey, lambda xy: pv.from_corrected(p.inverse(model.apply(view.to_corrected(xy))))
        ))  # fmt: skip
    if cfg.base_fallback and joint.base_grey is not None:
        fallbacks.append(gridded_sift.Reference(
            joint.base_grey, lambda xy: model.apply(view.to_corrected(xy)),
            valid=joint.base_valid, other_sensor=True,
        ))  # fmt: skip
    return template_points(
        view, joint.mid_grey, model, template_cfg or cfg.template, ref_valid=joint.mid_valid,
        fallback=fallbacks, centres=centres, ref_other_sensor=False,
    )  # fmt: skip


def flow_points(
    view, model, joint, prev, cfg, flow_cfg: FlowSettings
) -> tuple[ControlPoints, FrameFlow]:
    """Control points from the frame's dense flow against the mid base image, measured through
    ``model`` (the coarse ``base_from_corrected``), plus templates where the flow gives none.

    The flow (:func:`registration.matching.dense_flow.frame_flow`, with ``flow_cfg``'s flow settings,
    the local stage's) gives a point every ``cfg.flow_point_spacing_px`` frame px (or the
    template grid's spacing where that is finer: its ``min_templates`` floor on small frames)
    where the mid base image has content. Templates (``cfg.template``, searched as by
    :func:`intra_template_points`, previous frame and base map included) cover what the flow
    cannot: the frame's border (the edge ring, whose points hold the polyprojective where the
    lens stretches the ground most and the flow keeps a margin) and the grid centres with no
    flow point within that spacing (ground the mid base image does not show).

    Returns:
        ``(control points, flow)``; ``source`` 0 for the flow points; the flow is kept for the
        local stage (:func:`registration.local.refine.frame_field`).
    """
    fh, fw = view.grey.shape
    reference = joint_flow_reference(joint, fw, flow_cfg)
    tcfg = cfg.template
    grid_px = grid_spacing(fw, fh, tcfg)
    # Never sparser than the template grid would be (its min_templates floor on small frames).
    spacing = min(cfg.flow_point_spacing_px, grid_px)
    flow = frame_flow(
        view.grey, lambda q: model.apply(view.to_corrected(q)), reference, flow_cfg,
        point_step_px=spacing,
    )  # fmt: skip
    sets = [
        points_to_corrected(
            ControlPoints(
                flow.point_frame_xy, flow.point_base_xy, np.ones(len(flow.point_base_xy))
            ),
            view,
        )
    ]
    grid = template_grid(fw, fh, tcfg)
    holes = grid[_far_from(grid, flow.point_frame_xy, spacing)]
    if len(holes):
        sets.append(intra_template_points(view, model, joint, prev, cfg, centres=holes))
    if tcfg.edge_template_px > 0:
        ring = edge_ring(fw, fh, tcfg.edge_template_px, grid_px)
        ring_cfg = dataclasses.replace(tcfg, template_px=tcfg.edge_template_px, edge_template_px=0)
        sets.append(
            intra_template_points(
                view, model, joint, prev, cfg, template_cfg=ring_cfg, centres=ring
            )
        )
    return ControlPoints.concatenate(sets), flow


def _far_from(centres: NDArray, points: NDArray, distance: float) -> NDArray[np.bool_]:
    """``(N,)`` bool: the ``centres`` with no ``points`` within ``distance`` (both ``(., 2)``)."""
    if not len(points):
        return np.ones(len(centres), bool)
    d2 = ((centres[:, None, :].astype(np.float64) - points[None, :, :]) ** 2).sum(axis=2)
    return d2.min(axis=1) > distance**2
