"""The intra-sensor coarse step's fast path (beyond the paper): a frame predicted from the
previous one, confirmed by correlation, with the SIFT coarse step as the fallback.

Two consecutive frames of one sensor differ by the helicopter's motion between two exposures:
mostly a shift (up to ~170 px at 2560x1920 on the simulator's default flight), a fraction of a
degree of rotation and a little scale. The previous frame's registration moved by that shift
predicts the frame to a few tens of pixels, so the coarse SIFT step (1/4-scale SIFT, two
ratio-test matchings, RANSAC: ~0.27 s of CPU per 2560x1920 frame) is needed only when the
prediction cannot be confirmed. :func:`fast_coarse`:

1. **shift**: phase correlation of the frame against the previous frame at half the coarse
   scale (Hanning window, ~1 ms at 320x240); refused when the peak is weak
   (:data:`MIN_RESPONSE`) or the shift exceeds ``IntraConfig.fast_max_shift`` (a share of the
   frame's shorter side: beyond it the frames overlap too little to trust a global shift, and
   the SIFT step, which searches the whole joint base, is the safer tool);
2. **matches**: a grid of :data:`TEMPLATE_PX` templates at the coarse scale, each searched in
   the previous frame within ``+-SEARCH_PX / 2`` of its shifted position (normalised
   cross-correlation, sub-pixel peak; :mod:`registration.matching.templates` in the paper's direct
   mode);
3. **model**: every match is taken through the previous frame's model into base pixels and a
   projective is fitted by RANSAC at the coarse scale, exactly as the SIFT step fits its
   matches with the previous frame (:func:`registration.global_registration.coarse_fit.fit_coarse`);
4. **check**: at least ``IntraConfig.fast_min_inliers`` inliers, at least
   :data:`MIN_INLIER_SHARE` of the matches, spanning at least :data:`FIRST_COVERAGE` of the
   frame; spanning :data:`MIN_COVERAGE` to it, a similarity or an affine replaces the
   projective (:func:`registration.global_registration.coarse_fit.projective_or_simpler`) and is returned, falsy, for
   the caller to keep where the SIFT step fails.

A failed step returns a falsy :class:`registration.global_registration.coarse_records.CoarseResult` whose ``reason`` says
why; the caller then runs the SIFT step. Everything is deterministic (seeded RANSAC, no
threads whose order matters) within a process.

On in the default preset (``IntraConfig.fast_coarse``), off in the paper's. It was opt-in while
runs with it in separate processes differed now and then in a fit's last bits; the cause was
MINPACK's Levenberg-Marquardt (its result depends on memory alignment), which
:func:`registration.geometry.optimisers.levenberg_marquardt` replaced.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import replace

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.coords import image_size, rescale
from registration.geometry import Projective, hull_coverage, quantized, ransac
from registration.global_registration.coarse_fit import projective_or_simpler
from registration.global_registration.coarse_records import CoarseConfig, CoarseResult, FrameView
from registration.matching import TemplateConfig, downscale, template_control_points

# Template side and spacing at the coarse scale (px): 31 px at 1/4 scale is 124 frame px,
# large enough that a car cannot dominate one, and ~100 templates over a 640x480 coarse frame.
TEMPLATE_PX = 31
SPACING_PX = 48
# A coarse frame smaller than 640x480 (a frame under 640 px, which the coarse step keeps at
# full scale) gets a spacing down to its shorter side / this, so that it still has ~100
# templates: at 320x240, 48 px left ~30, of which 10-22 matched on a real roundabout's asphalt,
# under the 24 the check needs, and the SIFT fallback then failed or went wrong.
TEMPLATES_PER_SIDE = 10
MIN_SPACING_PX = 16
# Search range side at the coarse scale: +-8 px (32 frame px at 1/4 scale) covers the phase
# correlation's error (a global shift, 5-8 frame px off on the simulated flights) plus the
# rotation between frames at the corners (0.6 deg over 1600 px: 17 px).
SEARCH_PX = 16
# Phase-correlation peaks measured between consecutive simulated frames: 0.74-0.93 at 320x240
# (a quarter of that between unrelated images); below this the shift is not trusted.
MIN_RESPONSE = 0.2
# Inliers must be at least this share of the template matches (consecutive frames of one
# sensor: ~90 % on the simulated flights; a wrong shift leaves a scatter of coincidences).
MIN_INLIER_SHARE = 0.5
# ...and span at least FIRST_COVERAGE of a 10 x 10 grid of cell centres over the frame: a
# projective fitted to one corner of the frame extrapolates badly elsewhere. Between
# MIN_COVERAGE and it, a simpler model (registration.global_registration.coarse_fit.projective_or_simpler) is kept
# where the SIFT step fails: frames that are half uniform asphalt (a real roundabout at
# 320x240) span 40-50 %, and the SIFT step finds 5-14 keypoints there. Taken before the SIFT
# step instead, it moved a 640x480 flight over the same roundabout by 0.03-0.05 px (better
# against a map at half the resolution, worse against the native one), so the SIFT step stays
# first.
FIRST_COVERAGE = 0.5
MIN_COVERAGE = 0.3

_TEMPLATES = TemplateConfig(
    spacing_px=SPACING_PX,
    template_px=TEMPLATE_PX,
    search_px=SEARCH_PX,
    min_score=0.5,
    warp_reference=False,
    dither_iterations=0,
    anchor="centre",
    edge_template_px=0,
)


def phase_shift(small: NDArray, prev_small: NDArray) -> tuple[NDArray[np.float64], float]:
    """``(shift, response)``: where the content at a point of ``small`` lies in ``prev_small``
    (``prev_xy = xy + shift``, px of these images) by phase correlation at half their size, and
    the peak's response (0..1, OpenCV's ``phaseCorrelate``)."""
    a = downscale(small, 0.5).astype(np.float32)
    b = downscale(prev_small, 0.5).astype(np.float32)
    window = cv2.createHanningWindow(a.shape[::-1], cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(a, b, window)
    # Half-size px to ``small`` px (x_s = (x + 0.5) * s - 0.5 with s = 2 for a shift).
    sx = small.shape[1] / a.shape[1]
    sy = small.shape[0] / a.shape[0]
    return np.array([dx * sx, dy * sy]), float(response)


def fast_coarse(
    view: FrameView,
    small: NDArray[np.uint8],
    prev_view: FrameView,
    prev_small: NDArray[np.uint8],
    prev_to_base: Callable[[NDArray], NDArray],
    scale: float,
    config: CoarseConfig,
    *,
    max_shift: float,
    min_inliers: int,
    rng: np.random.Generator,
) -> CoarseResult:
    """The frame's coarse ``base_from_corrected`` from the previous frame (module doc).

    Args:
        view, prev_view: the frame's and the previous frame's views (same kind: raw or
            corrected grey at full scale).
        small, prev_small: their greys resampled by ``scale`` (:func:`features.downscale`).
        prev_to_base: the previous frame's model, its corrected px -> base px.
        scale: the coarse scale (``small`` px per frame px).
        config: the coarse step's settings (its RANSAC).
        max_shift: largest accepted shift, as a share of the frame's shorter side.
        min_inliers: fewest RANSAC inliers that confirm the prediction.
        rng: RANSAC's random generator.

    Returns:
        A :class:`CoarseResult` (``gate == "fast"``); falsy with the reason when a check fails.
    """
    t0 = time.perf_counter()
    w, h = image_size(view.grey)
    result = CoarseResult(
        success=False,
        reason="",
        base_from_corrected=None,
        frame_xy=np.zeros((0, 2)),
        base_xy=np.zeros((0, 2)),
        gated=np.zeros(0, bool),
        inliers=np.zeros(0, bool),
        n_keypoints_frame=0,
        n_keypoints_base=0,
        gate="fast",
    )

    def done(result: CoarseResult, reason: str = "") -> CoarseResult:
        return replace(
            result,
            reason=f"fast path: {reason}" if reason else "",
            time_s=time.perf_counter() - t0,
        )

    shift, response = phase_shift(small, prev_small)
    problem = _shift_problem(shift, response, max_shift, max_shift * min(w, h) * scale, scale)
    if problem:
        return done(result, problem)
    cps = _match_templates(small, prev_small, shift)
    n = len(cps)
    result = replace(result, n_keypoints_frame=n)
    if n < max(min_inliers, Projective.min_samples):
        return done(result, f"{n} templates matched the previous frame (need {min_inliers})")
    frame_xy = view.to_corrected(rescale(cps.src, 1.0 / scale))
    base_xy = prev_to_base(prev_view.to_corrected(rescale(cps.dst, 1.0 / scale)))
    ok = np.isfinite(base_xy).all(axis=1) & np.isfinite(frame_xy).all(axis=1)
    result = replace(
        result, frame_xy=frame_xy, base_xy=base_xy, gated=ok, inliers=np.zeros(n, bool)
    )
    idx = np.flatnonzero(ok)
    if len(idx) < max(min_inliers, Projective.min_samples):
        return done(result, f"only {len(idx)} matches map into the base through the previous frame")
    return done(*_fit_and_check(result, cps.src, idx, small, view, scale, config, min_inliers, rng))


def _shift_problem(
    shift: NDArray[np.float64], response: float, max_shift: float, limit: float, scale: float
) -> str:
    """Why the phase-correlation ``shift`` (coarse px; ``response`` its peak) is not trusted
    (a weak peak, or longer than ``limit`` coarse px = ``max_shift`` of the frame), or ""."""
    if not response >= MIN_RESPONSE:
        return f"phase-correlation peak {response:.2f} < {MIN_RESPONSE} (no clear shift)"
    if not np.hypot(*shift) <= limit:
        return (
            f"shift {np.hypot(*shift) / scale:.0f} px from the previous frame exceeds "
            f"{max_shift:g} of the frame ({limit / scale:.0f} px)"
        )
    return ""


def _match_templates(small: NDArray[np.uint8], prev_small: NDArray[np.uint8], shift: NDArray):
    """Template matches (:class:`ControlPoints`, coarse px) of ``small`` in ``prev_small``
    around the positions moved by ``shift``, on a grid of at least ~``TEMPLATES_PER_SIDE``
    templates per side."""
    spacing = int(min(SPACING_PX, max(MIN_SPACING_PX, min(small.shape[:2]) // TEMPLATES_PER_SIDE)))
    templates = dataclasses.replace(_TEMPLATES, spacing_px=spacing)
    return template_control_points(small, prev_small, lambda xy: xy + shift, None, templates)


def _fit_and_check(
    result: CoarseResult,
    src_small: NDArray[np.float64],
    idx: NDArray[np.int64],
    small: NDArray[np.uint8],
    view: FrameView,
    scale: float,
    config: CoarseConfig,
    min_inliers: int,
    rng: np.random.Generator,
) -> tuple[CoarseResult, str]:
    """Steps 3-4 (module doc) on the matches ``idx`` that map into the base: RANSAC on
    ``result.frame_xy`` -> ``result.base_xy`` at the coarse scale, then the inlier and coverage
    checks (``src_small``: all matches' coarse px in ``small``). Returns ``result`` with its
    inliers, model and success, and why the prediction is not confirmed ("" when it is)."""
    frame_xy, base_xy, n = result.frame_xy, result.base_xy, len(src_small)
    fit = ransac(
        rescale(frame_xy[idx], scale), rescale(base_xy[idx], scale), Projective, config.ransac, rng
    )
    if not fit:
        return result, f"RANSAC failed: {fit.reason}"
    result.inliers[idx[fit.inliers]] = True  # the result's own array, made for it above
    n_in = int(fit.n_inliers)
    if n_in < min_inliers or n_in < MIN_INLIER_SHARE * n:
        return (
            result,
            f"{n_in} of {n} matches agree (need {min_inliers} and {MIN_INLIER_SHARE:.0%})",
        )
    probes = _cell_centres(*image_size(small))
    inl = idx[fit.inliers]
    coverage = hull_coverage(src_small[inl], probes)
    if coverage < MIN_COVERAGE:
        why = f"the agreeing matches span {coverage:.0%} of the frame (need {MIN_COVERAGE:.0%})"
        return result, why
    corrected_probes = view.to_corrected(rescale(probes, 1.0 / scale))
    model, kind = projective_or_simpler(
        rescale(frame_xy[inl], scale), rescale(base_xy[inl], scale), fit.model, config,
        corrected_probes, scale,
    )  # fmt: skip
    full = quantized(model.rescaled(1.0 / scale, 1.0 / scale))
    result = replace(result, model_kind=kind, base_from_corrected=full)
    if coverage < FIRST_COVERAGE:
        # The SIFT step, which sees the whole joint base, goes first; this simpler model is
        # kept only when it fails (registration.global_registration.intra.register_intra).
        return result, (
            f"the agreeing matches span {coverage:.0%} of the frame (need {FIRST_COVERAGE:.0%} "
            f"to go before the SIFT step)"
        )
    return replace(result, success=True), ""


def _cell_centres(width: int, height: int, cells: int = 10) -> NDArray[np.float64]:
    t = (np.arange(cells) + 0.5) / cells
    gx, gy = np.meshgrid(t * width - 0.5, t * height - 0.5)
    return np.c_[gx.ravel(), gy.ravel()]
