"""Global registration to the base map (paper section 4).

Inter-sensor (4.3), for the reference frame against the base map:
  coarse: grey, 1/4 scale, SIFT, ratio matching, location gating around the one seed point,
  RANSAC projective with Nelder-Mead refinement (:func:`coarse_register`);
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
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from registration import features
from registration.coords import bbox_of, frame_outline, image_size, rescale
from registration.distortion import HarrisModel, undistort_image
from registration.features import (
    ControlPoints,
    GatingConfig,
    GriddedSiftConfig,
    Keypoints,
    SiftConfig,
    TemplateConfig,
)
from registration.models import PolyProjective, Projective
from registration.robust import FitResult, RansacConfig, ReqconConfig, ransac, reqcon

Seed = tuple[float, float, float, float]


@dataclass(frozen=True)
class CoarseConfig:
    """Coarse projective step at a reduced scale (paper 4.3.1, reused for intra-sensor frames).

    Attributes:
        scale: image scale of the coarse step (paper: both images sub-sampled to 1/4).
        sift: SIFT settings at that scale.
        ratio: Lowe's ratio test threshold for matching (stricter when smaller).
        gating: location gating around the seed correspondence (paper 4.3.1).
        ransac: RANSAC settings, in coarse-scale pixels (paper: 4 points, 5 px, 1000 iterations,
            Nelder-Mead refinement).
    """

    scale: float = 0.25
    sift: SiftConfig = field(default_factory=SiftConfig)
    ratio: float = 0.8
    gating: GatingConfig = field(default_factory=GatingConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)


@dataclass(frozen=True)
class FineConfig:
    """Fine polyprojective step of the inter-sensor registration (paper 4.3.2).

    Attributes:
        degree: polyprojective degree n (paper: 2, i.e. 17 coefficients).
        template: template grid and normalised cross-correlation (paper: 75x75 px every 50 px,
            20x20 search neighbourhood).
        reqcon: REQCON settings (paper: drop the worst 5 % until the mean error < 2 px,
            Nelder-Mead).
    """

    degree: int = 2
    template: TemplateConfig = field(default_factory=TemplateConfig)
    reqcon: ReqconConfig = field(default_factory=ReqconConfig)


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
            matched within corresponding windows) or ``"template"`` (normalised
            cross-correlation of the template grid against the joint base, as in 4.3.2).
        gridded: gridded-SIFT settings (paper: 50 px windows, 100 px spacing, decimate by 3).
        template: template settings when ``control_points == "template"``.
        reqcon: REQCON settings (paper: 5 %, 2 px, Nelder-Mead).
        use_previous_frame: also match against the previously registered frame (paper 4.4's
            joint base), which keeps control points available when the helicopter drifts away
            from the mid base image's footprint.
    """

    prediction_gate_px: float = 150.0
    coarse_nfeatures: int = 0
    control_points: Literal["gridded_sift", "template"] = "gridded_sift"
    gridded: GriddedSiftConfig = field(default_factory=GriddedSiftConfig)
    template: TemplateConfig = field(default_factory=TemplateConfig)
    reqcon: ReqconConfig = field(default_factory=ReqconConfig)
    use_previous_frame: bool = True

    def __post_init__(self) -> None:
        if self.control_points not in ("gridded_sift", "template"):
            raise ValueError(
                f"IntraConfig.control_points must be 'gridded_sift' or 'template', "
                f"got {self.control_points!r}"
            )
        if self.control_points == "template" and not self.template.warp_reference:
            raise ValueError(
                "IntraConfig: template control points need template.warp_reference=True "
                "(the previous frame is searched in the frame's geometry)"
            )


@dataclass
class CoarseResult:
    """Outcome of a coarse projective step; match arrays are full-scale pixels.

    ``frame_xy`` are corrected-frame pixels, ``base_xy`` base pixels (or, for intra-sensor
    frames, base pixels of the joint base). ``gated`` marks matches that passed the location gate,
    ``inliers`` the RANSAC inliers among all matches.
    """

    success: bool
    reason: str
    base_from_corrected: Projective | None
    frame_xy: NDArray[np.float64]
    base_xy: NDArray[np.float64]
    gated: NDArray[np.bool_]
    inliers: NDArray[np.bool_]
    n_keypoints_frame: int
    n_keypoints_base: int
    gate_center_base: NDArray[np.float64] | None = None
    gate_radius_base: float | None = None
    time_s: float = 0.0

    @property
    def n_matches(self) -> int:
        return int(len(self.frame_xy))

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    def __bool__(self) -> bool:
        return self.success


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

    @property
    def residual_rms_px(self) -> float:
        r = self.residuals[self.kept]
        return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")

    def __bool__(self) -> bool:
        return self.success


@dataclass
class CoarseFeatures:
    """SIFT keypoints of an image at the coarse scale (``xy`` in coarse-scale pixels)."""

    keypoints: Keypoints
    scale: float


def corrected_grey(frame_raw: NDArray, gamma: float) -> NDArray[np.uint8]:
    """Radially corrected grey frame on the raw frame's canvas (paper section 3)."""
    w, h = image_size(frame_raw)
    corrected, _ = undistort_image(frame_raw, HarrisModel(gamma, w, h), canvas="same")
    return features.to_grey(corrected)


@dataclass
class FrameView:
    """The grey image control points are found in, and its pixels' link to corrected pixels.

    With ``match_in="corrected"`` (the paper) the image is the radially corrected frame on the
    raw frame's canvas and the link is the identity; its corners lose the content that the
    correction pushes outside the canvas (at γ = 0.7 the raw corners move 1.8x further out), so
    the global model extrapolates there. With ``match_in="raw"`` the image is the raw frame and
    the exact Harris model links its pixels to corrected ones: every raw pixel can carry a control
    point and the frame is not resampled before matching.
    """

    grey: NDArray[np.uint8]
    harris: HarrisModel | None

    def to_corrected(self, xy: NDArray) -> NDArray:
        return xy if self.harris is None else self.harris.corrected_from_raw(xy)

    def from_corrected(self, xy: NDArray) -> NDArray:
        return xy if self.harris is None else self.harris.raw_from_corrected(xy)


def frame_view(frame_raw: NDArray, gamma: float, match_in: str) -> FrameView:
    """See :class:`FrameView`."""
    if match_in == "corrected":
        return FrameView(corrected_grey(frame_raw, gamma), None)
    if match_in == "raw":
        w, h = image_size(frame_raw)
        return FrameView(features.to_grey(frame_raw), HarrisModel(gamma, w, h))
    raise ValueError(f"match_in must be 'raw' or 'corrected', got {match_in!r}")


def coarse_features(
    grey: NDArray[np.uint8], config: CoarseConfig, mask=None, view: FrameView | None = None
) -> CoarseFeatures:
    """SIFT at the coarse scale (paper 4.3.1 steps 1, 2 and 4).

    With a ``view``, keypoint positions are converted to corrected-frame pixels (at the coarse
    scale), so that everything downstream is in corrected coordinates.
    """
    s = config.scale
    small = features.downscale(grey, s)
    small_mask = None
    if mask is not None:
        small_mask = (features.downscale(mask.astype(np.uint8) * 255, s) > 250).astype(np.uint8)
    kp = features.detect_sift(small, config.sift, mask=small_mask)
    if view is not None and view.harris is not None and len(kp.xy):
        kp = dataclasses.replace(kp, xy=rescale(view.to_corrected(rescale(kp.xy, 1.0 / s)), s))
    return CoarseFeatures(kp, s)


def _fit_coarse(
    frame_feats: CoarseFeatures,
    refs: list[tuple[CoarseFeatures, NDArray | None]],
    config: CoarseConfig,
    gate: NDArray[np.bool_] | None | callable,
    rng: np.random.Generator,
    n_keypoints_base: int,
    known: list[features.Matches | None] | None = None,
) -> CoarseResult:
    """Match the frame against each reference separately, gate, RANSAC at the coarse scale.

    ``refs`` holds (features, to_base) pairs: ``to_base`` maps the reference's full-scale pixels
    to base pixels (None = already base pixels). Matching each reference on its own keeps the
    ratio test from rejecting a point because it appears in two references. ``known`` gives
    matches already computed, per reference (None = match here).
    """
    s = config.scale
    frame_xy, base_xy = [], []
    for i, (feats, to_base) in enumerate(refs):
        m = known[i] if known is not None else None
        if m is None:
            m = features.match_ratio(frame_feats.keypoints, feats.keypoints, config.ratio)
        if len(m.idx_a) == 0:
            continue
        f_full = rescale(frame_feats.keypoints.xy[m.idx_a], 1.0 / s)
        b_full = rescale(feats.keypoints.xy[m.idx_b], 1.0 / s)
        if to_base is not None:
            b_full = to_base(b_full)
        frame_xy.append(f_full)
        base_xy.append(b_full)
    frame_xy = np.concatenate(frame_xy) if frame_xy else np.zeros((0, 2))
    base_xy = np.concatenate(base_xy) if base_xy else np.zeros((0, 2))
    ok = np.isfinite(base_xy).all(axis=1)
    gated = ok if gate is None else ok & gate(frame_xy, base_xy)
    inliers = np.zeros(len(frame_xy), bool)
    result = CoarseResult(
        success=False,
        reason="",
        base_from_corrected=None,
        frame_xy=frame_xy,
        base_xy=base_xy,
        gated=gated,
        inliers=inliers,
        n_keypoints_frame=len(frame_feats.keypoints.xy),
        n_keypoints_base=n_keypoints_base,
    )
    n_gated = int(gated.sum())
    if n_gated < Projective.min_samples:
        result.reason = f"coarse step: only {n_gated} matches passed the location gate (need 4)"
        return result
    idx = np.flatnonzero(gated)
    fit = ransac(
        rescale(frame_xy[idx], s), rescale(base_xy[idx], s), Projective, config.ransac, rng
    )
    if not fit:
        result.reason = f"coarse step: RANSAC failed: {fit.reason}"
        return result
    inliers[idx[fit.inliers]] = True
    result.base_from_corrected = fit.model.rescaled(1.0 / s, 1.0 / s)
    result.success = True
    return result


def coarse_register(
    frame_raw: NDArray,
    base: NDArray,
    gamma: float,
    seed: Seed | None,
    config,
    *,
    base_features: CoarseFeatures | None = None,
    rng: np.random.Generator | int | None = 0,
    base_valid: NDArray[np.bool_] | None = None,
) -> CoarseResult:
    """Coarse inter-sensor registration of the reference frame (paper 4.3.1).

    Args:
        frame_raw: raw reference frame (H, W[, 3]) uint8.
        base: base map (Hb, Wb[, 3]) uint8.
        gamma: Harris γ of the frame.
        seed: ``(fx, fy, bx, by)``: one corresponding point, raw frame px and base px; None runs
            without location gating.
        config: a :class:`registration.config.PipelineConfig`.
        base_features: coarse SIFT of the base, when already computed.
        base_valid: ``(Hb, Wb)`` bool, where the base has data; no keypoint is taken elsewhere.
    """
    t0 = time.perf_counter()
    cfg: CoarseConfig = config.coarse
    rng = np.random.default_rng(rng)
    w, h = image_size(frame_raw)
    view = frame_view(frame_raw, gamma, config.match_in)
    frame_feats = coarse_features(view.grey, cfg, view=view)
    if base_features is None:
        base_features = coarse_features(features.to_grey(base), cfg, mask=base_valid)
    gate = None
    seed_corr = seed_base = None
    if seed is not None:
        seed_corr = HarrisModel(gamma, w, h).corrected_from_raw([seed[:2]])[0]
        seed_base = np.asarray(seed[2:], float)

        # The gate's slack is in coarse-scale pixels, like the rest of the coarse step.
        s = cfg.scale
        seed_corr_c, seed_base_c = rescale(seed_corr, s)[0], rescale(seed_base, s)[0]

        def gate(fxy, bxy):
            return features.gate_by_seed(
                rescale(fxy, s), rescale(bxy, s), seed_corr_c, seed_base_c, cfg.gating
            )

    result = _fit_coarse(
        frame_feats,
        [(base_features, None)],
        cfg,
        gate,
        rng,
        len(base_features.keypoints.xy),
    )
    if seed is not None:
        result.gate_center_base = seed_base
        result.gate_radius_base = (
            features.gate_radius(cfg.gating, frame_size=(w * cfg.scale, h * cfg.scale)) / cfg.scale
        )
    result.time_s = time.perf_counter() - t0
    return result


def _fit_fine(
    cps: ControlPoints,
    initial: Projective | PolyProjective,
    degree: int,
    reqcon_cfg,
    t0: float,
    domain: NDArray | None = None,
) -> FineResult:
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
    if n < start.min_samples:
        empty.reason = (
            f"fine step: only {n} control points, a degree-{degree} polyprojective needs "
            f"at least {start.min_samples}"
        )
        empty.time_s = time.perf_counter() - t0
        return empty
    fit: FitResult = reqcon(cps.src, cps.dst, start, reqcon_cfg, domain=domain)
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
    )
    result.time_s = time.perf_counter() - t0
    return result


def fine_register_reference(
    frame_raw: NDArray,
    base: NDArray,
    gamma: float,
    coarse: CoarseResult,
    config,
    *,
    base_valid: NDArray[np.bool_] | None = None,
) -> FineResult:
    """Fine inter-sensor registration of the reference frame (paper 4.3.2).

    The template grid of the corrected frame is matched in the base map around where the coarse
    projective puts it; REQCON fits the polyprojective starting from the coarse model. With
    ``base_valid`` (``(Hb, Wb)`` bool), no match window may touch the base's no-data.
    """
    t0 = time.perf_counter()
    if not coarse:
        raise ValueError("fine_register_reference needs a successful coarse result")
    cfg: FineConfig = config.fine
    model = coarse.base_from_corrected
    view = frame_view(frame_raw, gamma, config.match_in)
    cps = _template_points(view, features.to_grey(base), model, cfg.template, ref_valid=base_valid)
    return _fit_fine(cps, model, cfg.degree, cfg.reqcon, t0, frame_domain(frame_raw, gamma))


def frame_domain(frame_raw: NDArray, gamma: float, n: int = 9) -> NDArray[np.float64]:
    """An ``n`` x ``n`` grid over the whole raw frame in corrected pixels: where a frame's global
    model must stay defined (no pole of the polyprojective inside the frame)."""
    w, h = image_size(frame_raw)
    gx, gy = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, n))
    return HarrisModel(gamma, w, h).corrected_from_raw(np.c_[gx.ravel(), gy.ravel()])


def _template_points(
    view: FrameView, reference, base_from_corrected, template_cfg, *, ref_valid=None, fallback=None
):
    """Template control points of the view against a base-pixel reference (and a fallback
    reference, see :func:`features.template_control_points`); ``src`` corrected px."""
    model = base_from_corrected
    cps = features.template_control_points(
        view.grey,
        reference,
        lambda xy: model.apply(view.to_corrected(xy)),
        lambda b: view.from_corrected(model.inverse(b)),
        template_cfg,
        ref_valid=ref_valid,
        fallback=fallback,
    )
    return _points_to_corrected(cps, view)


def _points_to_corrected(cps: ControlPoints, view: FrameView) -> ControlPoints:
    if view.harris is None or not len(cps.src):
        return cps
    return ControlPoints(view.to_corrected(cps.src), cps.dst, cps.score, cps.source)


@dataclass
class JointBase:
    """What intra-sensor registration matches a frame against (paper 4.4).

    Attributes:
        mid_grey: the mid base image, grey, in base pixels (Hb, Wb); 0 where ``mid_valid`` is
            False.
        mid_valid: (Hb, Wb) bool, where the mid base image has content.
        mid_coarse: coarse SIFT of the mid base image.
        mid_sift: full-scale SIFT of the mid base image (gridded-SIFT control points), lazily.
        previous: the previously registered frame, or None.
        previous_index: that frame's index in the sequence.
        local_keypoints: the mid base image's keypoints for the local stage (paper preset), once.
        flow_reference: the mid base image prepared for the flow local stage, once.
    """

    mid_grey: NDArray[np.uint8]
    mid_valid: NDArray[np.bool_]
    mid_coarse: CoarseFeatures
    mid_sift: Keypoints | None = None
    previous: PreviousFrame | None = None
    previous_index: int | None = None
    local_keypoints: object | None = None
    flow_reference: object | None = None


@dataclass
class PreviousFrame:
    """The last registered frame: its view (image and pixel link), model and features."""

    view: FrameView
    base_from_corrected: PolyProjective
    coarse: CoarseFeatures
    sift: Keypoints | None = None


def previous_frame_state(frame_raw: NDArray, gamma: float, model, config) -> PreviousFrame:
    """What the next frame needs of a registered frame (its image, model, features)."""
    view = frame_view(frame_raw, gamma, config.match_in)
    sift = None
    if config.intra.control_points == "gridded_sift":
        sift = features.detect_sift(view.grey, config.intra.gridded.sift)
    coarse = coarse_features(view.grey, _intra_coarse_config(config), view=view)
    return PreviousFrame(view, model, coarse, sift)


def _intra_coarse_config(config) -> CoarseConfig:
    """The coarse step's settings for intra-sensor frames (``IntraConfig.coarse_nfeatures``)."""
    n = config.intra.coarse_nfeatures
    if not n:
        return config.coarse
    return dataclasses.replace(
        config.coarse, sift=dataclasses.replace(config.coarse.sift, nfeatures=n)
    )


def make_joint_base(mid_base: NDArray, mid_valid: NDArray[np.bool_], config) -> JointBase:
    """Prepare the mid base image for intra-sensor registration (computes its coarse SIFT once)."""
    grey = features.to_grey(mid_base)
    grey = np.where(mid_valid, grey, 0).astype(np.uint8)
    return JointBase(grey, mid_valid, coarse_features(grey, config.coarse, mask=mid_valid))


def register_intra(
    frame_raw: NDArray,
    gamma: float,
    joint: JointBase,
    config,
    *,
    rng: np.random.Generator | int | None = 0,
) -> tuple[CoarseResult, FineResult, PreviousFrame | None]:
    """Register one frame against the joint base (paper 4.4).

    Returns the coarse and fine results and, on success, the frame's state to serve as the
    ``previous`` frame of the next one.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(rng)
    cfg: IntraConfig = config.intra
    view = frame_view(frame_raw, gamma, config.match_in)
    ccfg = _intra_coarse_config(config)
    frame_coarse = coarse_features(view.grey, ccfg, view=view)
    prev = joint.previous if cfg.use_previous_frame else None
    refs: list[tuple[CoarseFeatures, object]] = []
    known: list[features.Matches | None] = []
    if prev is not None:
        refs.append((prev.coarse, prev.base_from_corrected.apply))
        known.append(
            features.match_ratio(frame_coarse.keypoints, prev.coarse.keypoints, ccfg.ratio)
        )
    gate = None
    mid = joint.mid_coarse
    if joint.previous is not None:
        predict = joint.previous.base_from_corrected.apply
        shift = np.zeros(2)
        if prev is not None:
            shift = _median_shift(frame_coarse, prev.coarse, known[0], refs[0][1], predict)
        mid = _coarse_near(mid, predict, shift, view, frame_raw.shape, cfg.prediction_gate_px)
        limit = cfg.prediction_gate_px

        def gate(fxy, bxy):
            return np.linalg.norm(predict(fxy) + shift - bxy, axis=1) < limit

    refs.insert(0, (mid, None))
    known.insert(0, None)
    n_base = sum(len(r[0].keypoints.xy) for r in refs)
    coarse = _fit_coarse(frame_coarse, refs, ccfg, gate, rng, n_base, known)
    coarse.time_s = time.perf_counter() - t0
    if not coarse:
        return coarse, _failed_fine(coarse.reason), None

    t1 = time.perf_counter()
    model = coarse.base_from_corrected
    frame_sift = None
    if cfg.control_points == "gridded_sift":
        frame_sift = features.detect_sift(view.grey, cfg.gridded.sift)
        if joint.mid_sift is None:
            joint.mid_sift = features.detect_sift(
                joint.mid_grey, cfg.gridded.sift, mask=joint.mid_valid.astype(np.uint8)
            )
        refs_fine = [
            features.Reference(
                joint.mid_grey,
                lambda xy: model.apply(view.to_corrected(xy)),
                lambda b: view.from_corrected(model.inverse(b)),
                joint.mid_sift,
            )
        ]
        if prev is not None:
            p = prev.base_from_corrected
            pv = prev.view
            refs_fine.append(
                features.Reference(
                    pv.grey,
                    lambda xy: pv.from_corrected(p.inverse(model.apply(view.to_corrected(xy)))),
                    lambda xy: view.from_corrected(model.inverse(p.apply(pv.to_corrected(xy)))),
                    prev.sift,
                )
            )
        cps = features.gridded_sift_control_points(
            view.grey, refs_fine, cfg.gridded, frame_keypoints=frame_sift
        )
        cps = _points_to_corrected(cps, view)
    else:
        fallback = None
        if prev is not None:
            p, pv = prev.base_from_corrected, prev.view
            fallback = features.Reference(
                pv.grey, lambda xy: pv.from_corrected(p.inverse(model.apply(view.to_corrected(xy))))
            )
        cps = _template_points(
            view, joint.mid_grey, model, cfg.template, ref_valid=joint.mid_valid, fallback=fallback
        )
    if prev is not None and len(cps.src):
        # Points found in the previous frame (source 1) are in its raw pixels: to base pixels.
        from_prev = cps.source == 1
        dst = cps.dst.copy()
        dst[from_prev] = prev.base_from_corrected.apply(prev.view.to_corrected(dst[from_prev]))
        cps = ControlPoints(cps.src, dst, cps.score, cps.source)
    keep = np.isfinite(cps.dst).all(axis=1) & np.isfinite(cps.src).all(axis=1)
    if not keep.all():
        cps = ControlPoints(cps.src[keep], cps.dst[keep], cps.score[keep], cps.source[keep])
    fine = _fit_fine(cps, model, config.fine.degree, cfg.reqcon, t1, frame_domain(frame_raw, gamma))
    if not fine:
        return coarse, fine, None
    state = PreviousFrame(view, fine.base_from_corrected, frame_coarse, frame_sift)
    return coarse, fine, state


def footprint_bbox(
    frame_to_base, width: int, height: int, base_size: tuple[int, int], margin: int = 2
) -> tuple[int, int, int, int]:
    """Integer ``(x0, y0, x1, y1)`` box of base pixels covered by a ``width`` x ``height`` frame
    under ``frame_to_base`` (a callable on ``(N, 2)`` frame px), clipped to the base."""
    return bbox_of(frame_to_base(frame_outline(width, height)), base_size, margin)


def _failed_fine(reason: str) -> FineResult:
    z = np.zeros((0, 2))
    return FineResult(False, reason, None, z, z, np.zeros(0, bool), np.zeros(0), 0)


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
