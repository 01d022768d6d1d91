"""Global registration to the base map (paper section 4).

Inter-sensor (4.3), for the reference frame against the base map:
  coarse: :mod:`registration.global_registration.coarse` (SIFT at 1/4 scale, heading and scale estimated from the
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

import math
import time
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from registration.geometry import (
    Affine,
    FitResult,
    PolyProjective,
    Projective,
    ReqconConfig,
    Similarity,
    Translation,
    hull_coverage,
    quantized,
    reqcon,
    simplest_supported,
)
from registration.global_registration.coarse import seed_gaps
from registration.global_registration.coarse_records import (
    CoarseResult,
    frame_view,
)
from registration.global_registration.intra_points import (
    template_points,
)
from registration.lens import Camera, as_camera
from registration.matching import (
    ControlPoints,
    FrameFlow,
    TemplateConfig,
    grey,
)


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
            (:func:`registration.geometry.simplest_supported`); the paper always keeps the
            polyprojective.
        click_refit_px: beyond the paper (0 = off, the paper): where the fitted model puts a
            clicked frame point farther than this from its clicked map point (base px), the
            step is run again from the coarse model moved through the click, and that fit is
            kept when it passes within this distance of the click, or nearer it than the first
            fit by half this distance (a careless click on the right plane), and when at least
            an eighth as many control points hold it as the first fit
            (:data:`CLICK_REFIT_MIN_SHARE`). Where the images hold two planes (roofs displaced
            by parallax between two dates, and the ground), the first fit follows the one with
            more texture; the analyst's click says which one the
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
    # How the fit stands to the analyst's clicks where it passes farther from them than
    # FineConfig.click_refit_px (refitted through them, or not and why); "" otherwise.
    click_note: str = ""
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


def fit_fine(
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
    measurement noise (:func:`registration.geometry.reqcon_fit.reqcon`).
    """
    start = (
        initial
        if isinstance(initial, PolyProjective)
        else PolyProjective.from_projective(initial, degree)
    )
    too_few = _too_few_points(cps, initial, start, degree, check_support, t0)
    if too_few is not None:
        return too_few
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
        result = _fall_back_if_unsupported(result, degree, domain, probes)
    if result.success:
        # The model as recorded (reproducible runs, models.quantized) and its residuals.
        model = quantized(result.base_from_corrected)
        result = replace(
            result,
            base_from_corrected=model,
            residuals=np.asarray(model.residuals(cps.src, cps.dst)),
        )
    return replace(result, time_s=time.perf_counter() - t0)


def _too_few_points(
    cps: ControlPoints, initial, start: PolyProjective, degree: int, check_support, t0: float
) -> FineResult | None:
    """The fine step's result when there are too few control points for REQCON on ``start``:
    the coarse model kept (said so) where the support check allows it, else a failure; None
    when there are enough."""
    n = len(cps.src)
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
        return replace(
            empty,
            success=True,
            base_from_corrected=PolyProjective.from_projective(initial, degree),
            residuals=np.asarray(initial.residuals(cps.src, cps.dst), float),
            model_kind="coarse",
            model_reason=(
                f"only {n} control points matched (REQCON on a degree-{degree} polyprojective "
                f"needs {3 * start.min_samples}): the coarse model is kept"
            ),
            time_s=time.perf_counter() - t0,
        )
    if n < start.min_samples:
        return replace(
            empty,
            reason=(
                f"fine step: only {n} control points, a degree-{degree} polyprojective needs "
                f"at least {start.min_samples}"
            ),
            time_s=time.perf_counter() - t0,
        )
    return None


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
) -> FineResult:
    """Keep the model (similarity, affine, projective or the polyprojective) that predicts
    held-out parts of the kept control points best (spatial cross-validation,
    :func:`registration.geometry.model_choice.simplest_supported`): points covering only part of the frame (a
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
    if kind == "polyprojective":
        return replace(
            result,
            model_kind=kind,
            model_reason=(
                f"the degree-{degree} polyprojective predicts held-out parts of the {len(src)} "
                "kept control points better than the simpler models"
            ),
        )
    proj = model if kind == "projective" else model.as_projective()
    return replace(
        result,
        model_kind=kind,
        base_from_corrected=PolyProjective.from_projective(
            proj, degree, poly.src_norm, poly.dst_norm
        ),
        model_reason=(
            f"the {kind} predicts held-out parts of the {len(src)} kept control points at least "
            "as well as the richer models, whose extra terms the points do not determine"
        ),
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
    (:class:`FineConfig`). ``camera``: the frame's :class:`registration.lens.camera.Camera` (or its
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


# A fit through the click is kept only where the images hold it firmly enough against the first
# fit: at least this share of the first fit's kept control points. Measured: a plane the click
# rightly picks keeps 0.16-0.67 of them (the two-plane test scene at 2-10 px 0.32-0.39; SRIF
# pairs 19, 26, 145, 185 and 186: 0.67, 0.16, 0.34, 0.32, 0.53; pair 26's ground has 1 textured
# patch to the roofs' 76); a click 30-50 px off on a simulated city finds lane markings and kerbs
# repeating along a street there and keeps 0.04-0.10 (22 such refits on the test sequence and a
# paper-hard flight; one at 1280x960 put the frame 41 px off the map, marked ok). The margin is
# narrow on both sides (1.3x): a fifth lost SRIF pair 26 (4.2 px with the refit).
CLICK_REFIT_MIN_SHARE = 0.125


def _refit_through_clicks(fine, coarse, fit, camera: Camera, limit_px: float) -> FineResult:
    """``fine``, or the fit started from the coarse model moved through the clicks when
    ``fine`` misses them by more than ``limit_px`` and that fit passes within it, or nearer
    them than ``fine`` by half of it (``FineConfig.click_refit_px``), and keeps at least
    :data:`CLICK_REFIT_MIN_SHARE` of ``fine``'s control points. ``fit``: start model ->
    FineResult."""

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
    elif fine and again.kept.sum() < CLICK_REFIT_MIN_SHARE * fine.kept.sum():
        why = (
            f"only {int(again.kept.sum())} control points hold a fit there, against "
            f"{int(fine.kept.sum())} for the first fit: check the click"
        )
    else:
        now = miss(again.base_from_corrected)
        # Kept where it passes within the distance of the click, or where it is a plane the
        # images support clearly nearer the click than the first fit's: a click on the ground
        # 8-10 px off still says ground (the roofs' plane 14-16 px from it), while a fit that
        # settles back on the first fit's plane is as far from a careless click as that one.
        if now < was and (now <= limit_px or was - now >= limit_px / 2):
            note = (
                f"refitted through the click: the first fit passed {was:.1f} px from it, "
                f"this one {now:.1f} px ({int(again.kept.sum())} control points)"
            )
            return replace(
                again,
                model_reason=f"{note}; {again.model_reason}",
                click_note=note,
                time_s=again.time_s + fine.time_s,
            )
        why = f"the fit started there settled {now:.1f} px from it"
    fine = replace(fine, time_s=fine.time_s + again.time_s)
    if fine:
        note = f"passes {was:.1f} px from the click, not refitted through it ({why})"
        fine = replace(fine, model_reason=f"{note}; {fine.model_reason}", click_note=note)
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
    cps = template_points(view, grey.to_grey(base), model, cfg.template, ref_valid=base_valid)
    # A template where the radial correction stretched the frame s times matches with about
    # s^2 times the error (the reference frame of a simulated gamma 0.7 lens, against truth:
    # median 0.19, 0.39, 0.79, 0.92 px at s ~ 1.15, 1.5, 1.95, 2.5): REQCON must not drop
    # those as outliers of the centre's templates.
    noise = camera.stretch(cps.src) ** STRETCH_NOISE_POWER if len(cps.src) else None
    # The probes of robust.hull_coverage: how much of the frame the control points span.
    return fit_fine(
        cps, model, cfg.degree, cfg.reqcon, t0, frame_domain(frame_raw, camera), cfg.check_support,
        camera.cell_centres(10), noise,
    )  # fmt: skip


def frame_domain(frame_raw: NDArray, camera: Camera | float, n: int = 9) -> NDArray[np.float64]:
    """An ``n`` x ``n`` grid over the whole raw frame in corrected pixels: where a frame's global
    model must stay defined (no pole of the polyprojective inside the frame). ``camera``: the
    frame's :class:`registration.lens.camera.Camera` (or its Harris γ)."""
    return as_camera(camera, frame_raw).grid(n, n)
