"""Intra-sensor registration of every frame but the reference (paper 4.4): the coarse step
predicted from the previous frame or by SIFT, then the fine polyprojective against the joint base
(the mid base image plus the previous frame).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from registration.coords import bbox_of, frame_outline, image_size, rescale
from registration.geometry import (
    Projective,
    ReqconConfig,
)
from registration.global_registration.coarse_fit import fit_coarse
from registration.global_registration.coarse_records import (
    CoarseConfig,
    CoarseFeatures,
    CoarseResult,
    FrameView,
    coarse_features,
    coarse_scale,
    frame_view,
)
from registration.global_registration.fine import (
    STRETCH_NOISE_POWER,
    FineResult,
    fit_fine,
    frame_domain,
)
from registration.global_registration.intra_points import (
    flow_points,
    gridded_points,
    intra_template_points,
)
from registration.global_registration.joint_base import (
    JointBase,
    PreviousFrame,
    mid_coarse,
    previous_coarse,
    previous_small,
)
from registration.global_registration.predicted_coarse import fast_coarse
from registration.lens import Camera
from registration.matching import (
    ControlPoints,
    GriddedSiftConfig,
    TemplateConfig,
    grey,
)
from registration.matching import sift as matching_sift
from registration.matching.dense_flow import FlowSettings


@dataclass(frozen=True)
class IntraConfig:
    """Intra-sensor registration of every other frame (paper 4.4).

    Attributes:
        prediction_gate_px: a coarse match is kept only if it lies within this distance (full-scale
            base px) of where the previous frame's model puts the keypoint, after that prediction
            is moved by the frame-to-frame shift (the median offset of the matches with the
            previous frame, which are same-sensor and mostly right); it replaces the seed point,
            which exists only for the reference frame. It bounds the rotation and scale change
            between frames, not the shift (at 2560x1920 the helicopter's jitter moves the view
            by up to ~200 px between frames).
        coarse_nfeatures: at most this many strongest coarse SIFT keypoints per frame (0 = all,
            the paper). Beyond the paper: a helicopter frame at 1/4 scale yields ~6600, and
            matching cost grows with the product of the two counts; 2000 leave over a thousand
            matches with the previous frame for RANSAC.
        control_points: ``"gridded_sift"`` (paper 4.4: SIFT in 50x50 windows every 100 px,
            matched within corresponding windows), ``"template"`` (normalised
            cross-correlation of the template grid against the joint base, as in 4.3.2) or
            ``"flow"`` (beyond the paper: points from the frame's dense flow against the mid base
            image, which the local stage then reuses instead of measuring its own, with
            templates along the border and where the flow has none:
            :func:`registration.global_registration.intra_points.flow_points`).
        gridded: gridded-SIFT settings (paper: 50 px windows, 100 px spacing, decimate by 3).
        template: template settings when ``control_points`` is ``"template"`` or ``"flow"``.
        flow_point_spacing_px: with ``"flow"``, a control point every this many frame px.
        reqcon: REQCON settings (paper: 5 %, 2 px, Nelder-Mead).
        use_previous_frame: also match against the previously registered frame (paper 4.4's
            joint base), which keeps control points available when the helicopter drifts away
            from the mid base image's footprint.
        reanchor_coverage: beyond the paper (0 = never, the paper): when less than this share
            of a registered frame lies on the mid base image, the frame is registered to the
            base map itself again (an inter-sensor fine step started from its intra-sensor
            model, no click: :func:`register_anchor`) and added to the mid base image where it
            has no content. Once a frame has left the reference frame's footprint, the paper's
            joint base leaves it only the previous frame, and errors accumulate frame after
            frame; anchors bound them by the inter-sensor accuracy.
        anchor_fill_radius: beyond the paper. An anchor fills the mid base image only with its
            pixels within this share of the half-diagonal from the raw frame's centre (None: its
            whole frame). The mid base image's holes lie ahead of the flight, where the anchor
            shows them in its outer ring: there the lens compresses the ground most and the
            anchor's registration is least accurate (a 640x480 reference frame of the long
            flight, after its field: 0.11 px within 0.6 of the half-diagonal, 0.27 px at
            0.7-0.85, 0.77 px at 0.85-0.92, 3.0 px beyond), and every later frame aligned to
            that content inherited it. Left empty, those pixels come from the base map
            (``base_fallback``) until an anchor whose centre is there fills them.
        reanchor_max_shift_px: an anchor whose model differs from the frame's intra-sensor
            model by more than this (base px, median over the frame) is not trusted: the
            frame keeps its intra-sensor registration.
        base_fallback: beyond the paper (template control points only): templates that
            neither the mid base image nor the previous frame cover are matched in the base
            map itself (source 2). A frame flying over new ground has a leading edge that no
            earlier frame saw; without control points there, the polyprojective extrapolates
            (on a flyover at 480x360, hundreds of px at the leading corners).
        fast_coarse: beyond the paper (needs ``use_previous_frame``): predict the frame from
            the previous one (its model moved by the phase-correlation shift between the two),
            confirm the prediction by template matches at the coarse scale, and run the SIFT
            coarse step only when a check fails (:mod:`registration.global_registration.predicted_coarse`; the frame's
            record says which in ``stats["coarse_path"]``). False = always SIFT (the paper); the
            default preset uses it.
        fast_max_shift: the fast path's largest shift from the previous frame, as a share of
            the frame's shorter side (0.15: 288 px at 2560x1920, 72 px at 640x480); a larger
            jump goes to the SIFT step.
        fast_min_inliers: fewest template matches that must agree (RANSAC inliers) to confirm
            the prediction.
        sparse_support: beyond the paper: where the kept control points span less of the frame
            than a polyprojective needs (:data:`FINE_MIN_COVERAGE`), the simplest model that
            predicts held-out points as well is kept, as the reference frame's
            ``FineConfig.check_support`` does everywhere. On a real roundabout at 320x240 (half
            uniform asphalt) with the SIFT coarse step alone, a frame's points lay on one side
            and the polyprojective put the other side 190 px off (mean 16 px; 6 px with the
            similarity kept instead). Frames whose points cover them are unchanged.
    """

    prediction_gate_px: float = 150.0
    coarse_nfeatures: int = 0
    control_points: Literal["gridded_sift", "template", "flow"] = "gridded_sift"
    gridded: GriddedSiftConfig = field(default_factory=GriddedSiftConfig)
    template: TemplateConfig = field(default_factory=TemplateConfig)
    flow_point_spacing_px: int = 96
    reqcon: ReqconConfig = field(default_factory=ReqconConfig)
    use_previous_frame: bool = True
    reanchor_coverage: float = 0.0
    anchor_fill_radius: float | None = None
    reanchor_max_shift_px: float = 20.0
    base_fallback: bool = False
    fast_coarse: bool = False
    fast_max_shift: float = 0.15
    fast_min_inliers: int = 24
    sparse_support: bool = False

    def __post_init__(self) -> None:
        if not 0 < self.fast_max_shift <= 1 or self.fast_min_inliers < 4:
            raise ValueError(
                "IntraConfig.fast_max_shift must be in (0, 1] and fast_min_inliers >= 4, got "
                f"{self.fast_max_shift}, {self.fast_min_inliers}"
            )
        if not 0 <= self.reanchor_coverage <= 1:
            raise ValueError(
                f"IntraConfig.reanchor_coverage must be in [0, 1], got {self.reanchor_coverage}"
            )
        if self.anchor_fill_radius is not None and not 0 < self.anchor_fill_radius <= 1:
            raise ValueError(
                "IntraConfig.anchor_fill_radius must be in (0, 1] or None, got "
                f"{self.anchor_fill_radius}"
            )
        if self.control_points not in ("gridded_sift", "template", "flow"):
            raise ValueError(
                f"IntraConfig.control_points must be 'gridded_sift', 'template' or 'flow', "
                f"got {self.control_points!r}"
            )
        if self.control_points != "gridded_sift" and not self.template.warp_reference:
            raise ValueError(
                f"IntraConfig: {self.control_points} control points need "
                "template.warp_reference=True (the previous frame is searched in the frame's "
                "geometry)"
            )
        if self.flow_point_spacing_px < 1:
            raise ValueError(
                f"IntraConfig.flow_point_spacing_px must be >= 1, got {self.flow_point_spacing_px}"
            )


def previous_frame_state(
    frame_raw: NDArray, camera: Camera, model, cfg: IntraConfig, *, match_in: str
) -> PreviousFrame:
    """What the next frame needs of a registered frame (its image, model, features)."""
    view = frame_view(frame_raw, camera, match_in)
    sift = None
    if cfg.control_points == "gridded_sift":
        sift = matching_sift.detect_sift(view.grey, cfg.gridded.sift)
    return PreviousFrame(view, model, None, sift)


def intra_coarse_config(coarse: CoarseConfig, intra: IntraConfig) -> CoarseConfig:
    """The coarse step's settings for intra-sensor frames: ``coarse`` with at most
    ``intra.coarse_nfeatures`` keypoints per frame."""
    n = intra.coarse_nfeatures
    if not n:
        return coarse
    return dataclasses.replace(coarse, sift=dataclasses.replace(coarse.sift, nfeatures=n))


def register_intra(
    frame_raw: NDArray,
    camera: Camera,
    joint: JointBase,
    cfg: IntraConfig,
    coarse_cfg: CoarseConfig,
    *,
    degree: int,
    match_in: str,
    rng: np.random.Generator | int | None = 0,
    flow_cfg: FlowSettings | None = None,
) -> tuple[CoarseResult, FineResult, PreviousFrame | None]:
    """Register one frame against the joint base (paper 4.4).

    ``cfg`` are the intra-sensor settings, ``coarse_cfg`` the coarse step's (the mid base
    image's coarse SIFT; the frames' with :func:`intra_coarse_config`), ``degree`` that of the
    polyprojective (``FineConfig.degree``), ``match_in`` where control points are found
    (``PipelineConfig.match_in``), ``flow_cfg`` the flow settings (the local stage's) that
    ``cfg.control_points == "flow"`` needs.

    The coarse step is the fast path (:mod:`registration.global_registration.predicted_coarse`, with
    ``IntraConfig.fast_coarse``) or, when that is off or one of its checks fails, the SIFT step
    (:func:`intra_sift_coarse`); ``CoarseResult.path`` says which (``"fast"`` or ``"sift"``) and
    ``fast_reason`` why the fast path was not used.

    Returns the coarse and fine results and, on success, the frame's state to serve as the
    ``previous`` frame of the next one.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(rng)
    view = frame_view(frame_raw, camera, match_in)
    prev = joint.previous if cfg.use_previous_frame else None
    state = PreviousFrame(view, None)
    coarse = _intra_coarse(frame_raw, view, camera, joint, prev, state, cfg, coarse_cfg, rng, t0)
    if not coarse:
        return coarse, FineResult.failed(coarse.reason), None

    t1 = time.perf_counter()
    model = coarse.base_from_corrected
    cps, flow = _intra_control_points(view, model, joint, prev, state, cfg, flow_cfg)
    noise = camera.stretch(cps.src) ** STRETCH_NOISE_POWER if len(cps.src) else None
    fine = fit_fine(
        cps, model, degree, cfg.reqcon, t1, frame_domain(frame_raw, camera),
        "sparse" if cfg.sparse_support else False, camera.cell_centres(10), noise_scale=noise,
    )  # fmt: skip
    fine = replace(fine, flow=flow)
    if not fine:
        return coarse, fine, None
    state.base_from_corrected = fine.base_from_corrected
    return coarse, fine, state


def _intra_coarse(
    frame_raw, view, camera: Camera, joint: JointBase, prev, state: PreviousFrame,
    cfg: IntraConfig, coarse_cfg: CoarseConfig, rng: np.random.Generator, t0: float,
) -> CoarseResult:  # fmt: skip
    """The intra-sensor coarse step (:func:`register_intra`): the fast path when it is on and
    confirmed, else the SIFT step (the fast path's simpler model where that fails too). Fills
    ``state``'s coarse-scale grey and SIFT as they are computed; ``t0`` is when the frame's
    registration began."""
    coarse, fast, fast_reason = None, None, "off"
    if cfg.fast_coarse and prev is not None:
        ccfg = intra_coarse_config(coarse_cfg, cfg)
        s = coarse_scale(*image_size(view.grey), ccfg)
        state.small = grey.downscale(view.grey, s)
        fast = fast_coarse(
            view, state.small, prev.view, previous_small(prev, s), prev.base_from_corrected.apply,
            s, ccfg, max_shift=cfg.fast_max_shift, min_inliers=cfg.fast_min_inliers, rng=rng,
        )  # fmt: skip
        fast_reason = fast.reason
        coarse = fast if fast else None
    if coarse is None:
        coarse, state.coarse = intra_sift_coarse(
            view, frame_raw.shape, joint, cfg, coarse_cfg, rng, probes=camera.cell_centres(10)
        )
        if not coarse and fast is not None and fast.base_from_corrected is not None:
            # The fast path's simpler model from matches on part of the frame is all there is.
            fast_reason = f"{fast_reason}; kept, as the SIFT step failed: {coarse.reason}"
            coarse = replace(fast, success=True, reason="")
    coarse = replace(
        coarse,
        path="fast" if coarse.gate == "fast" else "sift",
        fast_reason=fast_reason,
        time_s=time.perf_counter() - t0,
    )
    if not coarse and fast_reason and fast_reason != "off":
        # Both steps failed: say why the fast one did too.
        coarse = replace(coarse, reason=f"{coarse.reason}; {fast_reason}")
    return coarse


def _intra_control_points(
    view, model, joint: JointBase, prev, state: PreviousFrame, cfg: IntraConfig, flow_cfg
) -> tuple[ControlPoints, object]:
    """The frame's control points (``src`` corrected px, ``dst`` base px; those found in the
    previous frame taken through its model, none non-finite) by the method ``cfg`` names, and
    the frame's flow when they came from one (else None)."""
    flow = None
    if cfg.control_points == "gridded_sift":
        state.sift = matching_sift.detect_sift(view.grey, cfg.gridded.sift)
        cps = gridded_points(view, state.sift, model, joint, prev, cfg)
    elif cfg.control_points == "flow":
        if flow_cfg is None:
            raise ValueError("register_intra: flow control points need flow_cfg")
        cps, flow = flow_points(view, model, joint, prev, cfg, flow_cfg)
    else:
        cps = intra_template_points(view, model, joint, prev, cfg)
    if prev is not None and len(cps.src):
        # Points found in the previous frame (source 1) are in its raw pixels: to base pixels.
        from_prev = cps.source == 1
        dst = cps.dst.copy()
        dst[from_prev] = prev.base_from_corrected.apply(prev.view.to_corrected(dst[from_prev]))
        cps = ControlPoints(cps.src, dst, cps.score, cps.source)
    keep = np.isfinite(cps.dst).all(axis=1) & np.isfinite(cps.src).all(axis=1)
    if not keep.all():
        cps = ControlPoints(cps.src[keep], cps.dst[keep], cps.score[keep], cps.source[keep])
    return cps, flow


def intra_sift_coarse(
    view: FrameView,
    shape,
    joint: JointBase,
    cfg: IntraConfig,
    coarse_cfg: CoarseConfig,
    rng: np.random.Generator,
    probes: NDArray | None = None,
) -> tuple[CoarseResult, CoarseFeatures]:
    """The intra-sensor coarse step of the paper (4.4): the frame's coarse SIFT matched against
    the mid base image and the previous frame, gated by where the previous frame's model
    predicts each keypoint, RANSAC. ``probes``: the frame's cell centres (corrected px) for the
    model choice (:func:`registration.global_registration.coarse_fit.fit_coarse`). Returns the result and the frame's
    coarse features."""
    ccfg = intra_coarse_config(coarse_cfg, cfg)
    frame_coarse = coarse_features(view.grey, ccfg, view=view)
    prev = joint.previous if cfg.use_previous_frame else None
    refs: list[tuple[CoarseFeatures, object]] = []
    known: list[matching_sift.Matches | None] = []
    if prev is not None:
        prev_coarse = previous_coarse(prev, ccfg)
        refs.append((prev_coarse, prev.base_from_corrected.apply))
        known.append(
            matching_sift.match_ratio(frame_coarse.keypoints, prev_coarse.keypoints, ccfg.ratio)
        )
    gate = None
    mid = mid_coarse(joint, coarse_cfg)
    if joint.previous is not None:
        predict = joint.previous.base_from_corrected.apply
        shift = np.zeros(2)
        if prev is not None:
            shift = _median_shift(frame_coarse, prev_coarse, known[0], refs[0][1], predict)
        mid = _coarse_near(mid, predict, shift, view, shape, cfg.prediction_gate_px)
        limit = cfg.prediction_gate_px

        def gate(fxy, bxy):
            return np.linalg.norm(predict(fxy) + shift - bxy, axis=1) < limit

    refs.insert(0, (mid, None))
    known.insert(0, None)
    n_base = sum(len(r[0].keypoints.xy) for r in refs)
    result = fit_coarse(frame_coarse, refs, ccfg, gate, rng, n_base, known, probes=probes)
    return result, frame_coarse


def footprint_bbox(
    frame_to_base, width: int, height: int, base_size: tuple[int, int], margin: int = 2
) -> tuple[int, int, int, int]:
    """Integer ``(x0, y0, x1, y1)`` box of base pixels covered by a ``width`` x ``height`` frame
    under ``frame_to_base`` (a callable on ``(N, 2)`` frame px), clipped to the base."""
    return bbox_of(frame_to_base(frame_outline(width, height)), base_size, margin)


def _median_shift(frame_coarse, prev_coarse, matches, prev_to_base, predict) -> NDArray:
    """Median offset (base px) between where the previous frame's model puts the frame's matched
    coarse keypoints and where their matches in the previous frame lie (zero without matches).
    Same-sensor neighbours match mostly right, so the median is the frame-to-frame shift."""
    if len(matches.idx_a) < Projective.min_samples:
        return np.zeros(2)
    f = rescale(frame_coarse.keypoints.xy[matches.idx_a], 1.0 / frame_coarse.scale)
    b = prev_to_base(rescale(prev_coarse.keypoints.xy[matches.idx_b], 1.0 / prev_coarse.scale))
    off = b - predict(f)
    off = off[np.isfinite(off).all(axis=1)]
    return np.median(off, axis=0) if len(off) else np.zeros(2)


def _coarse_near(mid, predict, shift, view, shape, margin) -> CoarseFeatures:
    """The mid base image's coarse keypoints within ``margin`` base px of the frame's predicted
    footprint (matching cost grows with the number of candidates)."""
    h, w = shape[:2]
    outline = predict(view.to_corrected(frame_outline(w, h))) + shift
    outline = outline[np.isfinite(outline).all(axis=1)]
    if not len(outline):
        return mid
    lo = rescale(outline.min(axis=0) - margin, mid.scale)[0]
    hi = rescale(outline.max(axis=0) + margin, mid.scale)[0]
    xy = mid.keypoints.xy
    near = (xy >= lo).all(axis=1) & (xy <= hi).all(axis=1)
    return CoarseFeatures(mid.keypoints.subset(near), mid.scale)
