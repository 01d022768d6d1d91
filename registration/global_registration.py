"""Global registration to the base map (paper section 4).

Inter-sensor (4.3), for the reference frame against the base map:
  coarse: :mod:`registration.coarse` (SIFT at 1/4 scale, heading and scale estimated from the
  seed or without one, location gating, RANSAC projective);
  fine: the coarse model rescaled to a full-scale polyprojective start, a grid of templates matched
  by normalised cross-correlation, REQCON (:func:`fine_register_reference`).
  The reference frame warped into base coordinates is the "mid base image".

Intra-sensor (4.4), for every other frame against the joint base (mid base image plus the
previously registered frame): coarse projective at 1/4 scale, gated by where the previous frame's
model predicts each keypoint, then the fine polyprojective from gridded SIFT (paper) or templates
(default preset), REQCON (:func:`register_intra`).

All models here are ``base_from_corrected``: corrected-frame pixels to base pixels.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from registration import features
from registration.camera import Camera, as_camera
from registration.coarse import (
    CoarseBase,
    CoarseConfig,
    CoarseFeatures,
    CoarseResult,
    FrameView,
    Seed,
    coarse_features,
    coarse_register,
    coarse_scale,
    fit_coarse,
    frame_view,
    seed_gaps,
)
from registration.coords import bbox_of, frame_outline, image_size, rescale
from registration.fast_coarse import fast_coarse
from registration.features import ControlPoints, GriddedSiftConfig, Keypoints
from registration.intra_points import (
    flow_points,
    gridded_points,
    intra_template_points,
    template_points,
)
from registration.local_field import LocalConfig
from registration.local_flow import FrameFlow
from registration.models import (
    Affine,
    PolyProjective,
    Projective,
    Similarity,
    Translation,
    quantized,
)
from registration.robust import FitResult, ReqconConfig, hull_coverage, reqcon, simplest_supported
from registration.templates import TemplateConfig

__all__ = [
    "CoarseBase",
    "CoarseConfig",
    "CoarseFeatures",
    "CoarseResult",
    "FineConfig",
    "FineResult",
    "FrameView",
    "IntraConfig",
    "JointBase",
    "PreviousFrame",
    "Seed",
    "coarse_register",
    "fine_register_reference",
    "frame_view",
    "make_joint_base",
    "previous_frame_state",
    "add_to_mid_base",
    "mid_coverage",
    "register_anchor",
    "register_intra",
]


@dataclass(frozen=True)
class FineConfig:
    """Fine polyprojective step of the inter-sensor registration (paper 4.3.2).

    Attributes:
        degree: polyprojective degree n (paper: 2, i.e. 17 coefficients).
        template: template grid and normalised cross-correlation (paper: 75x75 px every 50 px,
            20x20 search neighbourhood).
        reqcon: REQCON settings (paper: drop the worst 5 % until the mean error < 2 px,
            Nelder-Mead).
        check_support: beyond the paper: keep the projective part where the kept control
            points do not support the degree-``degree`` terms over the frame
            (:func:`registration.robust.supported_by_points`); the paper always keeps the
            polyprojective.
        click_refit_px: beyond the paper (0 = off, the paper): where the fitted model puts a
            clicked frame point farther than this from its clicked map point (base px), the
            step is run again from the coarse model moved through the click, and that fit is
            kept when it passes within this distance of the click. Where the images hold two
            planes (roofs displaced by parallax between two dates, and the ground), the first
            fit follows the one with more texture; the analyst's click says which one the
            traffic is on. A fit the images do not support near the click is never kept, so a
            careless click cannot drag a right registration.
    """

    degree: int = 2
    template: TemplateConfig = field(default_factory=TemplateConfig)
    reqcon: ReqconConfig = field(default_factory=ReqconConfig)
    check_support: bool = False
    click_refit_px: float = 0.0

    def __post_init__(self) -> None:
        if not (self.click_refit_px >= 0 and math.isfinite(self.click_refit_px)):
            raise ValueError(
                f"FineConfig.click_refit_px must be a finite distance >= 0, got "
                f"{self.click_refit_px!r}"
            )


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
            :func:`registration.intra_points.flow_points`).
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
            coarse step only when a check fails (:mod:`registration.fast_coarse`; the frame's
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


@dataclass
class FineResult:
    """Outcome of a fine polyprojective step.

    ``src`` are corrected-frame pixels, ``dst`` base pixels (N, 2); ``kept`` marks the points
    REQCON kept; ``residuals`` (N,) are the final model's errors in base pixels for every point.
    """

    success: bool
    reason: str
    base_from_corrected: PolyProjective | None
    src: NDArray[np.float64]
    dst: NDArray[np.float64]
    kept: NDArray[np.bool_]
    residuals: NDArray[np.float64]
    iterations: int
    time_s: float = 0.0
    source: NDArray[np.int_] | None = None
    model_kind: str = "polyprojective"
    model_reason: str = ""
    sigma_px: float = float("nan")
    # The frame's dense flow against the mid base image when its control points came from it
    # (IntraConfig.control_points == "flow"), for the local stage to reuse; not written out.
    flow: FrameFlow | None = None

    @classmethod
    def failed(cls, reason: str) -> FineResult:
        """A failed step with ``reason`` and no points."""
        z = np.zeros((0, 2))
        return cls(False, reason, None, z, z, np.zeros(0, bool), np.zeros(0), 0)

    @property
    def residual_rms_px(self) -> float:
        r = self.residuals[self.kept]
        return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")

    def __bool__(self) -> bool:
        return self.success


def _fit_fine(
    cps: ControlPoints,
    initial: Projective | PolyProjective,
    degree: int,
    reqcon_cfg,
    t0: float,
    domain: NDArray | None = None,
    check_support: bool | Literal["sparse"] = False,
    probes: NDArray | None = None,
    noise_scale: NDArray | None = None,
) -> FineResult:
    """REQCON on the control points from ``initial``; with ``check_support``, the projective is
    kept where the points do not support the polyprojective (:func:`_fall_back_if_unsupported`);
    ``"sparse"``: only where the kept points span less of ``probes`` than
    :data:`FINE_MIN_COVERAGE` asks of a polyprojective. ``noise_scale``: the points' relative
    measurement noise (:func:`registration.robust.reqcon`).
    """
    n = len(cps.src)
    start = (
        initial
        if isinstance(initial, PolyProjective)
        else PolyProjective.from_projective(initial, degree)
    )
    empty = FineResult(
        success=False,
        reason="",
        base_from_corrected=None,
        src=cps.src,
        dst=cps.dst,
        kept=np.zeros(n, bool),
        residuals=np.full(n, np.nan),
        iterations=0,
        source=getattr(cps, "source", None),
    )
    if n < 3 * start.min_samples and check_support and isinstance(initial, Projective):
        # Too few points for REQCON on the polyprojective: the coarse model stays, said so.
        empty.success = True
        empty.base_from_corrected = PolyProjective.from_projective(initial, degree)
        empty.residuals = np.asarray(initial.residuals(cps.src, cps.dst), float)
        empty.model_kind = "coarse"
        empty.model_reason = (
            f"only {n} control points matched (REQCON on a degree-{degree} polyprojective "
            f"needs {3 * start.min_samples}): the coarse model is kept"
        )
        empty.time_s = time.perf_counter() - t0
        return empty
    if n < start.min_samples:
        empty.reason = (
            f"fine step: only {n} control points, a degree-{degree} polyprojective needs "
            f"at least {start.min_samples}"
        )
        empty.time_s = time.perf_counter() - t0
        return empty
    fit: FitResult = reqcon(
        cps.src, cps.dst, start, reqcon_cfg, domain=domain, noise_scale=noise_scale
    )
    result = FineResult(
        success=bool(fit),
        reason="" if fit else f"fine step: REQCON failed: {fit.reason}",
        base_from_corrected=fit.model if fit else None,
        src=cps.src,
        dst=cps.dst,
        kept=np.asarray(fit.inliers, bool),
        residuals=np.asarray(fit.residuals, float),
        iterations=int(fit.iterations),
        source=getattr(cps, "source", None),
        sigma_px=float(fit.sigma_px),
    )
    if check_support == "sparse" and fit and probes is not None:
        coverage = hull_coverage(cps.src[result.kept], probes)
        check_support = coverage < FINE_MIN_COVERAGE["polyprojective"]
    if fit and check_support and degree > 1 and domain is not None:
        _fall_back_if_unsupported(result, degree, domain, probes)
    if result.success:
        # The model as recorded (reproducible runs, models.quantized) and its residuals.
        result.base_from_corrected = quantized(result.base_from_corrected)
        result.residuals = np.asarray(result.base_from_corrected.residuals(cps.src, cps.dst))
    result.time_s = time.perf_counter() - t0
    return result


# Models the fine step may fall back to, simplest first (all expressed as polyprojectives).
_FALLBACKS = (("similarity", Similarity), ("affine", Affine), ("projective", Projective))


# Share of the frame the kept control points must span for the fine step to consider a model:
# beyond the points, cross-validation cannot check a model's extra terms, and a
# polyprojective's curvature explodes there (on SRIF pairs whose overlap covers part of image
# 1, its corners went thousands of pixels off while cross-validation within the overlap
# preferred it). The affine's two extra terms (shear, unequal scales) need points over 30 % of
# the frame: fitted to points clustered in a small part of it they follow what the points there
# share (buildings leaning differently between dates, another orthorectification) and carry it
# to the far corners, where a similarity stays closer (200 real SRIF pairs, one click: 171 -> 176
# under 10 px; at 50 %, 178, but a simulated frame half off its map lost 0.2 px median).
FINE_MIN_COVERAGE = {"affine": 0.3, "projective": 0.5, "polyprojective": 0.8}


def _fall_back_if_unsupported(
    result: FineResult, degree: int, domain: NDArray, probes: NDArray | None
) -> None:
    """Keep the model (similarity, affine, projective or the polyprojective) that predicts
    held-out parts of the kept control points best (spatial cross-validation,
    :func:`registration.robust.simplest_supported`): points covering only part of the frame (a
    map with no-data areas, another date with changed buildings) let a richer model's extra
    terms extrapolate wildly elsewhere, which would make the fine step worse than the coarse
    one."""
    src, dst = result.src[result.kept], result.dst[result.kept]
    poly = result.base_from_corrected
    fits = []
    for name, cls in _FALLBACKS:
        if cls is Projective:
            m = Projective.estimate(src, dst, initial=poly.projective_part(), optimizer="lm")
            dlt = Projective.estimate(src, dst) if not m else None
            if dlt:
                # The polyprojective's projective part can be a start from which the fit folds
                # (its extra terms carried some of the perspective): then the projective was no
                # candidate, and a 25°-oblique photo kept a similarity 40 px off.
                m = Projective.estimate(src, dst, initial=dlt, optimizer="lm")
        else:
            m = cls.estimate(src, dst)
        if m:
            fits.append((name, m))
    fits.append(("polyprojective", poly))
    kind, model = simplest_supported(
        fits, src, dst, domain=domain, probes=probes, min_coverage=FINE_MIN_COVERAGE
    )
    result.model_kind = kind
    if kind == "polyprojective":
        result.model_reason = (
            f"the degree-{degree} polyprojective predicts held-out parts of the {len(src)} kept "
            "control points better than the simpler models"
        )
        return
    proj = model if kind == "projective" else model.as_projective()
    result.base_from_corrected = PolyProjective.from_projective(
        proj, degree, poly.src_norm, poly.dst_norm
    )
    result.model_reason = (
        f"the {kind} predicts held-out parts of the {len(src)} kept control points at least as "
        "well as the richer models, whose extra terms the points do not determine"
    )


def fine_register_reference(
    frame_raw: NDArray,
    base: NDArray,
    camera: Camera | float,
    coarse: CoarseResult,
    cfg: FineConfig,
    *,
    match_in: str,
    base_valid: NDArray | None = None,
) -> FineResult:
    """Fine inter-sensor registration of the reference frame (paper 4.3.2).

    The template grid of the corrected frame is matched in the base map around where the coarse
    projective puts it (never where ``base_valid``, ``(Hb, Wb)`` bool, marks no data); REQCON
    fits the polyprojective starting from the coarse model. With ``cfg.check_support`` the
    projective is kept where the points do not support the polyprojective
    (``FineResult.model_kind`` and ``model_reason`` say which and why). With
    ``cfg.click_refit_px``, a fit that misses the coarse step's clicks is run again through them
    (:class:`FineConfig`). ``camera``: the frame's :class:`registration.camera.Camera` (or its
    Harris γ); ``match_in``: where control points are found (``PipelineConfig.match_in``).
    """
    if not coarse:
        raise ValueError("fine_register_reference needs a successful coarse result")
    camera = as_camera(camera, frame_raw)

    def fit(start):
        return _fine_against_base(frame_raw, base, camera, start, cfg, match_in, base_valid)

    fine = fit(coarse.base_from_corrected)
    if cfg.click_refit_px and coarse.seeds:
        fine = _refit_through_clicks(fine, coarse, fit, camera, cfg.click_refit_px)
    return fine


def _refit_through_clicks(fine, coarse, fit, camera: Camera, limit_px: float) -> FineResult:
    """``fine``, or the fit started from the coarse model moved through the clicks when
    ``fine`` misses them by more than ``limit_px`` and that fit passes within it
    (``FineConfig.click_refit_px``). ``fit``: start model -> FineResult."""

    def miss(model) -> float:
        return float(np.hypot(*seed_gaps(model, coarse.seeds, camera.lens).T).max())

    was = miss(fine.base_from_corrected if fine else coarse.base_from_corrected)
    if not was > limit_px:
        return fine
    # The coarse model moved by its own mean miss at the clicks: the template search (+-10 px)
    # then reaches the plane through the click and no longer the one the first fit followed.
    moved = Translation(seed_gaps(coarse.base_from_corrected, coarse.seeds, camera.lens).mean(0))
    again = fit(moved.compose(coarse.base_from_corrected))
    if not again:
        why = f"the fit started there failed: {again.reason}"
    elif again.model_kind == "coarse":
        why = "too few control points match there"
    else:
        now = miss(again.base_from_corrected)
        if now <= limit_px and now < was:
            again.model_reason = (
                f"refitted through the click: the first fit passed {was:.1f} px from it, this "
                f"one {now:.1f} px ({int(again.kept.sum())} control points); {again.model_reason}"
            )
            again.time_s += fine.time_s
            return again
        why = f"the fit started there settled {now:.1f} px from it"
    fine.time_s += again.time_s
    if fine:
        fine.model_reason = (
            f"passes {was:.1f} px from the click, not refitted through it ({why}); "
            f"{fine.model_reason}"
        )
    return fine


def register_anchor(
    frame_raw: NDArray,
    base: NDArray,
    camera: Camera,
    start,
    cfg: FineConfig,
    *,
    match_in: str,
    base_valid: NDArray | None = None,
) -> FineResult:
    """Re-anchor a frame to the base map (beyond the paper; ``IntraConfig.reanchor_coverage``):
    the inter-sensor fine step of the reference frame (templates against the base map, REQCON),
    started from ``start``, the frame's intra-sensor ``base_from_corrected`` (no click needed:
    it is accurate to a few pixels)."""
    return _fine_against_base(frame_raw, base, camera, start, cfg, match_in, base_valid)


# How a template's matching error grows with the radial correction's stretch (see below).
STRETCH_NOISE_POWER = 2.0


def _fine_against_base(frame_raw, base, camera, model, cfg: FineConfig, match_in, base_valid):
    """Template control points of the frame in the base map around ``model``, then REQCON."""
    t0 = time.perf_counter()
    camera = as_camera(camera, frame_raw)
    view = frame_view(frame_raw, camera, match_in)
    cps = template_points(view, features.to_grey(base), model, cfg.template, ref_valid=base_valid)
    # A template where the radial correction stretched the frame s times matches with about
    # s^2 times the error (the reference frame of a simulated gamma 0.7 lens, against truth:
    # median 0.19, 0.39, 0.79, 0.92 px at s ~ 1.15, 1.5, 1.95, 2.5): REQCON must not drop
    # those as outliers of the centre's templates.
    noise = camera.stretch(cps.src) ** STRETCH_NOISE_POWER if len(cps.src) else None
    # The probes of robust.hull_coverage: how much of the frame the control points span.
    return _fit_fine(
        cps, model, cfg.degree, cfg.reqcon, t0, frame_domain(frame_raw, camera), cfg.check_support,
        camera.cell_centres(10), noise,
    )  # fmt: skip


def frame_domain(frame_raw: NDArray, camera: Camera | float, n: int = 9) -> NDArray[np.float64]:
    """An ``n`` x ``n`` grid over the whole raw frame in corrected pixels: where a frame's global
    model must stay defined (no pole of the polyprojective inside the frame). ``camera``: the
    frame's :class:`registration.camera.Camera` (or its Harris γ)."""
    return as_camera(camera, frame_raw).grid(n, n)


@dataclass
class JointBase:
    """What intra-sensor registration matches a frame against (paper 4.4).

    Attributes:
        mid_grey: the mid base image, grey, in base pixels (Hb, Wb); 0 where ``mid_valid`` is
            False.
        mid_valid: (Hb, Wb) bool, where the mid base image has content.
        mid_coarse: coarse SIFT of the mid base image, when first needed (:func:`mid_coarse`).
        mid_image: the mid base image as rendered (colour), for writing it out.
        base_grey, base_valid: the base map (grey) and its content mask, searched by the
            templates that neither the mid base image nor the previous frame can take
            (``IntraConfig.base_fallback``).
        mid_sift: full-scale SIFT of the mid base image (gridded-SIFT control points), lazily.
        previous: the previously registered frame, or None.
        previous_index: that frame's index in the sequence.
        local_keypoints: the mid base image's keypoints for the local stage (paper preset), once.
        flow_reference: the mid base image prepared for the flow local stage, once.
    """

    mid_grey: NDArray[np.uint8]
    mid_valid: NDArray[np.bool_]
    mid_coarse: CoarseFeatures | None = None
    mid_image: NDArray[np.uint8] | None = None
    base_grey: NDArray[np.uint8] | None = None
    base_valid: NDArray[np.bool_] | None = None
    mid_sift: Keypoints | None = None
    previous: PreviousFrame | None = None
    previous_index: int | None = None
    local_keypoints: object | None = None
    flow_reference: object | None = None
    _prepare_lock: threading.Lock = field(
        default_factory=threading.Lock, init=False, repr=False, compare=False
    )

    def prepared(self, name: str, make: Callable[[], object]) -> object:
        """The member ``name`` (``local_keypoints`` or ``flow_reference``), made by ``make()``
        the first time it is asked for. Local stages of several frames run at once
        (:mod:`registration.overlap`): the first to ask makes it, the others wait for it."""
        with self._prepare_lock:
            if getattr(self, name) is None:
                setattr(self, name, make())
            return getattr(self, name)


@dataclass
class PreviousFrame:
    """The last registered frame: its view (image and pixel link), model and features.

    ``coarse`` (its coarse SIFT) and ``small`` (its grey at the coarse scale, for the fast
    path) are computed when first needed (:func:`previous_coarse`, :func:`previous_small`): a
    frame the fast path registers never needs its SIFT."""

    view: FrameView
    base_from_corrected: PolyProjective
    coarse: CoarseFeatures | None = None
    sift: Keypoints | None = None
    small: NDArray[np.uint8] | None = None


def previous_frame_state(
    frame_raw: NDArray, camera: Camera, model, cfg: IntraConfig, *, match_in: str
) -> PreviousFrame:
    """What the next frame needs of a registered frame (its image, model, features)."""
    view = frame_view(frame_raw, camera, match_in)
    sift = None
    if cfg.control_points == "gridded_sift":
        sift = features.detect_sift(view.grey, cfg.gridded.sift)
    return PreviousFrame(view, model, None, sift)


def previous_coarse(prev: PreviousFrame, ccfg: CoarseConfig) -> CoarseFeatures:
    """The previous frame's coarse SIFT (computed once) with the intra-sensor coarse settings
    ``ccfg`` (:func:`intra_coarse_config`)."""
    if prev.coarse is None:
        prev.coarse = coarse_features(prev.view.grey, ccfg, view=prev.view)
    return prev.coarse


def previous_small(prev: PreviousFrame, scale: float) -> NDArray[np.uint8]:
    """The previous frame's grey at ``scale`` (computed once)."""
    if prev.small is None:
        prev.small = features.downscale(prev.view.grey, scale)
    return prev.small


def intra_coarse_config(coarse: CoarseConfig, intra: IntraConfig) -> CoarseConfig:
    """The coarse step's settings for intra-sensor frames: ``coarse`` with at most
    ``intra.coarse_nfeatures`` keypoints per frame."""
    n = intra.coarse_nfeatures
    if not n:
        return coarse
    return dataclasses.replace(coarse, sift=dataclasses.replace(coarse.sift, nfeatures=n))


def make_joint_base(mid_base: NDArray, mid_valid: NDArray[np.bool_]) -> JointBase:
    """Prepare the mid base image for intra-sensor registration (computes its coarse SIFT once)."""
    grey = features.to_grey(mid_base)
    grey = np.where(mid_valid, grey, 0).astype(np.uint8)
    return JointBase(grey, mid_valid, mid_image=mid_base)


def mid_coarse(joint: JointBase, cfg: CoarseConfig) -> CoarseFeatures:
    """The mid base image's coarse SIFT (computed when first needed, after each change)."""
    if joint.mid_coarse is None:
        joint.mid_coarse = coarse_features(joint.mid_grey, cfg, mask=joint.mid_valid)
    return joint.mid_coarse


def add_to_mid_base(joint: JointBase, image: NDArray, valid: NDArray[np.bool_], box) -> None:
    """Fill the mid base image's empty pixels inside ``box`` = ``(x0, y0, x1, y1)`` from
    ``image`` (a re-anchored frame rendered into that box, with its ``valid`` mask); content
    already there (the reference frame, earlier anchors) is kept, so a run's mid base image
    depends only on which frames were anchors and in which order. Its features and the prepared
    local-stage references are dropped (recomputed when next needed)."""
    x0, y0, x1, y1 = box
    hole = np.asarray(valid, bool) & ~joint.mid_valid[y0:y1, x0:x1]
    if not hole.any():
        return
    joint.mid_grey[y0:y1, x0:x1][hole] = features.to_grey(image)[hole]
    if joint.mid_image is not None:
        joint.mid_image[y0:y1, x0:x1][hole] = image[hole]
    joint.mid_valid[y0:y1, x0:x1] |= hole
    joint.mid_coarse = joint.mid_sift = joint.local_keypoints = joint.flow_reference = None


def mid_coverage(joint: JointBase, camera: Camera, model) -> float:
    """Share of the frame (a 16 x 12 grid of raw pixels) that ``model`` puts on content of the
    mid base image."""
    w, h = camera.size
    gx, gy = np.meshgrid((np.arange(16) + 0.5) * w / 16 - 0.5, (np.arange(12) + 0.5) * h / 12 - 0.5)
    b = model.apply(camera.corrected_from_raw(np.c_[gx.ravel(), gy.ravel()]))
    hb, wb = joint.mid_valid.shape
    xi, yi = np.round(b[:, 0]), np.round(b[:, 1])
    ok = np.isfinite(b).all(axis=1) & (xi >= 0) & (xi < wb) & (yi >= 0) & (yi < hb)
    inside = np.zeros(len(b), bool)
    inside[ok] = joint.mid_valid[yi[ok].astype(int), xi[ok].astype(int)]
    return float(inside.mean())


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
    flow_cfg: LocalConfig | None = None,
) -> tuple[CoarseResult, FineResult, PreviousFrame | None]:
    """Register one frame against the joint base (paper 4.4).

    ``cfg`` are the intra-sensor settings, ``coarse_cfg`` the coarse step's (the mid base
    image's coarse SIFT; the frames' with :func:`intra_coarse_config`), ``degree`` that of the
    polyprojective (``FineConfig.degree``), ``match_in`` where control points are found
    (``PipelineConfig.match_in``), ``flow_cfg`` the flow settings (the local stage's) that
    ``cfg.control_points == "flow"`` needs.

    The coarse step is the fast path (:mod:`registration.fast_coarse`, with
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
    coarse, fast, fast_reason = None, None, "off"
    if cfg.fast_coarse and prev is not None:
        ccfg = intra_coarse_config(coarse_cfg, cfg)
        s = coarse_scale(*image_size(view.grey), ccfg)
        state.small = features.downscale(view.grey, s)
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
            fast.success, fast.reason, coarse = True, "", fast
    coarse.path = "fast" if coarse.gate == "fast" else "sift"
    coarse.fast_reason = fast_reason
    coarse.time_s = time.perf_counter() - t0
    if not coarse:
        if fast_reason and fast_reason != "off":
            # Both steps failed: say why the fast one did too.
            coarse.reason = f"{coarse.reason}; {fast_reason}"
        return coarse, FineResult.failed(coarse.reason), None

    t1 = time.perf_counter()
    model = coarse.base_from_corrected
    flow = None
    if cfg.control_points == "gridded_sift":
        state.sift = features.detect_sift(view.grey, cfg.gridded.sift)
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
    noise = camera.stretch(cps.src) ** STRETCH_NOISE_POWER if len(cps.src) else None
    fine = _fit_fine(
        cps, model, degree, cfg.reqcon, t1, frame_domain(frame_raw, camera),
        "sparse" if cfg.sparse_support else False, camera.cell_centres(10), noise_scale=noise,
    )  # fmt: skip
    fine.flow = flow
    if not fine:
        return coarse, fine, None
    state.base_from_corrected = fine.base_from_corrected
    return coarse, fine, state


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
    model choice (:func:`registration.coarse.fit_coarse`). Returns the result and the frame's
    coarse features."""
    ccfg = intra_coarse_config(coarse_cfg, cfg)
    frame_coarse = coarse_features(view.grey, ccfg, view=view)
    prev = joint.previous if cfg.use_previous_frame else None
    refs: list[tuple[CoarseFeatures, object]] = []
    known: list[features.Matches | None] = []
    if prev is not None:
        prev_coarse = previous_coarse(prev, ccfg)
        refs.append((prev_coarse, prev.base_from_corrected.apply))
        known.append(
            features.match_ratio(frame_coarse.keypoints, prev_coarse.keypoints, ccfg.ratio)
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
