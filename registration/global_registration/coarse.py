"""The coarse projective step (paper 4.3.1), at any heading and scale between frame and map.

Paper steps: grey, 1/4 scale, one manually identified correspondence, SIFT in both images,
matches, RANSAC (4 points, 5 px, 1000 iterations) with Nelder-Mead. The paper's map was within
~10° and ~20 % of its frames; ours may be at any heading and resolution, so (beyond the paper):

1. The heading and scale are estimated first (:mod:`registration.global_registration.heading`): from the seed's
   vote histogram, fixed by a second seed, or, without a seed, from the 4-D Hough transform of
   the matches (several candidates are tried and the best is kept only if it is clearly best).
2. The location gate keeps the matches the estimate allows around the seed (paper), and, with
   ``guided``, a second matching among base keypoints near each predicted position adds the
   right matches a global ratio test loses to look-alikes elsewhere in a large map.
3. With ``match_base_scale`` the base's coarse scale follows the estimated scale, so both coarse
   images have about the same ground resolution (a map at 0.5x or 2x the frame's).
4. RANSAC (paper), then ``refine_rounds`` of guided re-matching around the fitted model, and a
   choice among similarity, affine and projective (``models``) by spatial cross-validation and
   how much of the frame the points span: an affine or projective whose extra terms are not
   supported by the points extrapolates badly at the frame's corners.
5. With ``correlation`` rounds, gradient-magnitude template correlation at reduced scale refines
   the result, or rescues a seeded one SIFT could not find (:mod:`registration.global_registration.gradient_correlation`).
6. A result that contradicts the clicked seed by more than the click can be off is refused with a
   message that says so, never returned silently.

All models are ``base_from_corrected``: corrected-frame pixels to base pixels. The intra-sensor
coarse step (paper 4.4) shares :func:`fit_coarse` with a prediction gate instead of the seed.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from registration.coords import frame_outline, rescale
from registration.geometry import (
    quantized,
)
from registration.global_registration import heading
from registration.global_registration.coarse_fit import _attempt, _select_model
from registration.global_registration.coarse_records import (
    CoarseBase,
    CoarseConfig,
    CoarseResult,
    coarse_features,
    coarse_scale,
    frame_view,
    normalise_seeds,
)
from registration.global_registration.gradient_correlation import (
    agreement,
    gradient_images,
    refine_by_correlation,
)
from registration.global_registration.heading import SimilarityPrior
from registration.lens import Camera, as_camera
from registration.matching import grey, sift

# ------------------------------------------------------------------------------------------
# Inter-sensor coarse step


def _seed_priors(seeds, lens, frame, base, matches, attr, config) -> list[SimilarityPrior]:
    """The prior(s) of the seed(s), in coarse pixels (empty when no match votes)."""
    sf, sb = frame.scale, base.scale
    fr = _seed_frame_points(seeds, lens)
    bs = np.array([s[2:] for s in seeds], float)
    if len(seeds) == 2:
        prior = heading.prior_from_seeds(fr, bs)
        prior = dataclasses.replace(prior, anchor_frame=fr[0], anchor_base=bs[0])
    else:
        f_xy = frame.keypoints.xy[matches.idx_a]
        b_xy = base.keypoints.xy[matches.idx_b]
        prior = heading.prior_from_seed(
            f_xy, b_xy, *attr, rescale(fr[0], sf)[0], rescale(bs[0], sb)[0], config.heading
        )
        if prior is None:
            return []
        prior = prior.rescaled(1.0 / sf, 1.0 / sb)
    return [_with_click_error(prior, config).rescaled(sf, sb)]


def _seed_frame_points(seeds, lens) -> NDArray:
    """The seeds' frame points in corrected pixels, ``(n, 2)``."""
    fr = np.array([s[:2] for s in seeds], float)
    return fr if lens is None else lens.corrected_from_raw(fr)


def seed_gaps(model, seeds, lens) -> NDArray[np.float64]:
    """``(n, 2)`` base px: each seed's clicked base point minus where ``model``
    (``base_from_corrected``) puts its frame point (raw px through ``lens``; None = none)."""
    clicked = np.array([s[2:] for s in seeds], float).reshape(-1, 2)
    return clicked - model.apply(_seed_frame_points(seeds, lens))


def _with_click_error(prior: SimilarityPrior, config) -> SimilarityPrior:
    """A full-scale seed prior whose anchor may be off by the clicks' error in both images."""
    err = config.heading.seed_error_px * (1.0 + prior.scale)
    return dataclasses.replace(prior, anchor_error_px=err)


def _patch_prior(seed, lens, view, cbase, s_f, s_b, priors, config) -> list[SimilarityPrior]:
    """The seed's heading and scale from image correlation (:func:`heading.prior_from_patch`),
    in coarse pixels, as a list of at most one prior: empty when it finds nothing or agrees
    with the first of ``priors`` within the gate's tolerances."""
    hcfg = config.heading
    fr = _seed_frame_points([seed], lens)
    valid = None
    if cbase.valid is not None:
        valid = grey.downscale_mask(cbase.valid, s_b)
    found = heading.prior_from_patch(
        grey.downscale(view.grey, s_f), grey.downscale(cbase.grey, s_b),
        rescale(fr, s_f)[0], rescale(np.array([seed[2:]], float), s_b)[0], hcfg,
        base_valid=valid,
    )  # fmt: skip
    if found is None:
        return []
    # The click error is in full-scale pixels, as for the SIFT prior.
    found = _with_click_error(found.rescaled(1.0 / s_f, 1.0 / s_b), config).rescaled(s_f, s_b)
    if priors:
        first = priors[0]
        same_heading = float(heading.angle_gap_deg(found.heading_deg, first.heading_deg)) <= (
            hcfg.max_rotation_deg
        )
        if same_heading and abs(math.log(found.scale / first.scale)) <= hcfg.max_scale_error:
            return []
    return [found]


def _gate_outline(prior: SimilarityPrior, w: int, h: int, lens, config) -> NDArray:
    """The base region where gated matches can lie (full-scale): the frame's outline under the
    prior, pushed outwards by the gate's radius at each outline point."""
    outline = frame_outline(w, h, per_edge=16)
    corr = outline if lens is None else lens.corrected_from_raw(outline)
    centre = prior.apply(corr)
    radius = heading.gate_radius_px(prior, corr, config.heading)
    mid = centre.mean(axis=0)
    direction = centre - mid
    norm = np.maximum(np.hypot(*direction.T), 1e-9)[:, None]
    return centre + direction / norm * radius[:, None]


def coarse_register(
    frame_raw: NDArray,
    base: NDArray,
    camera: Camera | float,
    seed,
    cfg: CoarseConfig,
    *,
    match_in: str,
    base_features: CoarseBase | None = None,
    base_valid: NDArray | None = None,
    rng: np.random.Generator | int | None = 0,
) -> CoarseResult:
    """Coarse inter-sensor registration of the reference frame (paper 4.3.1, module doc).

    Args:
        frame_raw: raw reference frame (H, W[, 3]) uint8.
        base: base map (Hb, Wb[, 3]) uint8.
        camera: the frame's :class:`registration.lens.camera.Camera`, or its Harris γ.
        seed: None, one ``(fx, fy, bx, by)`` correspondence (raw frame px, base px), or a list of
            two (they fix heading and scale).
        cfg: the coarse step's settings (``PipelineConfig.coarse``).
        match_in: where keypoints are found, ``"corrected"`` or ``"raw"`` (:class:`FrameView`,
            ``PipelineConfig.match_in``).
        base_features: the base's coarse keypoints cache (:class:`CoarseBase`), when kept
            between calls.
        base_valid: (Hb, Wb) bool, where the base map has content; ignored with
            ``base_features``.
        rng: seed or generator of the random samples.

    Returns:
        :class:`CoarseResult`; falsy with a one-line reason when no registration is found, when
        the seed contradicts the one found, or without a seed when two disagree.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(rng)
    seeds = normalise_seeds(seed)
    camera = as_camera(camera, frame_raw)
    w, h = camera.size
    view = frame_view(frame_raw, camera, match_in)
    s_f = coarse_scale(w, h, cfg)
    frame = coarse_features(view.grey, cfg, view=view, scale=s_f)
    cbase = base_features if base_features is not None else CoarseBase(base, cfg, base_valid)
    base_c = cbase.features(s_f)
    lens = camera.lens
    priors, matches, attr = _priors(seeds, lens, frame, base_c, cfg, w, h)
    if cfg.match_base_scale and priors:
        # Re-detect the base at the scale that matches the frame's ground resolution.
        full_scale = priors[0].scale * s_f / base_c.scale
        s_b = min(1.0, s_f / full_scale)
        if abs(math.log(s_b / base_c.scale)) > math.log(1.5):
            base_c = cbase.features(s_b)
            priors, matches, attr = _priors(seeds, lens, frame, base_c, cfg, w, h)
    if len(seeds) == 1 and (not priors or priors[0].votes < cfg.heading.patch_below_votes):
        priors = priors + _patch_prior(seeds[0], lens, view, cbase, s_f, base_c.scale, priors, cfg)
    domain = rescale(camera.cell_centres(10), s_f)
    attempts = _try_priors(priors, frame, base_c, matches, cfg, rng, seeds, domain)
    result = replace(
        _decide(attempts, priors, seeds, frame, base_c, cfg, w, h, lens),
        n_keypoints_frame=len(frame.keypoints),
        n_keypoints_base=len(base_c.keypoints),
        seeds=tuple(seeds),
    )
    if cfg.correlation.rounds and (result.success or (seeds and priors)):
        # The seed's own similarity start is the prior that won (the first when none did).
        won = max(range(len(attempts)), key=lambda i: attempts[i].score) if attempts else 0
        result = _correlate(
            result, view, cbase, priors[won], seeds, s_f, cfg, rng, domain, base_c.scale
        )
    if seeds and result.success:
        result = _check_seed(result, seeds, lens, cfg)
    confirm = result.image_agreement
    if result.success and len(seeds) < 2 and confirm and confirm.chance_p > cfg.max_chance_p:
        result = _refuse_unconfirmed(result, len(seeds))
    return replace(
        result,
        base_from_corrected=quantized(result.base_from_corrected),
        time_s=time.perf_counter() - t0,
    )


def _try_priors(priors, frame, base_c, matches, cfg: CoarseConfig, rng, seeds, domain) -> list:
    """An attempt (:func:`_attempt`) per heading-and-scale prior, in order; without a seed they
    stop once a registration stands out clearly from the candidates left (their Hough votes
    bound how many matches they could gather)."""
    attempts = []
    for i, prior in enumerate(priors):
        attempts.append(_attempt(prior, frame, base_c, matches, cfg, rng, bool(seeds), domain))
        best = max(a.score for a in attempts)
        if (
            not seeds
            and i + 1 < len(priors)
            and best
            >= max(2 * cfg.min_inliers_unseeded, 2 * cfg.decisive_ratio * priors[i + 1].votes)
        ):
            break
    return attempts


# The correlation rounds' model replaces the SIFT one only when this many times as many
# templates agree with it.
_CORRELATION_GAIN = 1.25


def _correlate(result, view, cbase, prior, seeds, s_f, cfg, rng, probes, s_b) -> CoarseResult:
    """The result refined by the correlation rounds, started from the SIFT model and, with a
    seed, from the seed's similarity too; the start whose last round fits more template
    matches wins. A seeded result that SIFT could not find is rescued when a round succeeds."""
    starts = []
    if result.success:
        starts.append((result.base_from_corrected, result.model_kind))
    if seeds:
        full = prior.rescaled(1.0 / s_f, 1.0 / s_b)
        starts.append((full.similarity.as_projective(), "similarity"))

    def select(src, dst, model):
        small = rescale(src, s_f), rescale(dst, s_f)
        chosen, kind = _select_model(*small, cfg.models, model.rescaled(s_f, s_f), probes)
        return chosen.rescaled(1.0 / s_f, 1.0 / s_f), kind

    if not starts:
        return result
    images = gradient_images(
        view.grey, view.to_corrected, view.from_corrected, cbase.grey, cbase.valid
    )
    best = None
    for model, kind in starts:
        out = refine_by_correlation(images, model, cfg.correlation, select, rng, kind)
        if out.rounds and (best is None or out.inliers > best.inliers):
            best = out
    if best is None:
        if result.success:
            confirm = agreement(images, result.base_from_corrected, cfg.correlation)
            return replace(result, image_agreement=confirm)
        return result
    after = agreement(images, best.model, cfg.correlation)
    if result.success:
        # The SIFT model stays unless the images agree clearly better with the refined one
        # (another date or sensor can pull correlation by a few pixels where SIFT was right).
        before = agreement(images, result.base_from_corrected, cfg.correlation)
        if not after.agreeing > _CORRELATION_GAIN * before.agreeing:
            return replace(result, correlation_inliers=after.agreeing, image_agreement=before)
    refined = replace(
        result,
        image_agreement=after,
        base_from_corrected=best.model,
        model_kind=best.kind,
        correlation_inliers=best.inliers,
    )
    if result.success:
        return refined
    return replace(refined, success=True, reason="", remedy="", gate=result.gate or "seed")


# The reference frame's matches are exact (brute force) below this many descriptor pairs (~1 s
# per 40 M here): a one-off per sequence, and FLANN's approximate neighbours change with its
# random trees, which moved the reference frame's registration by up to 0.3 px between seeds.
_EXACT_MAX_PAIRS = 400_000_000


def _priors(seeds, lens, frame, base_c, cfg, w, h):
    n_pairs = len(frame.keypoints) * len(base_c.keypoints)
    method = "bf" if n_pairs <= _EXACT_MAX_PAIRS else "flann"
    matches = sift.match_ratio(frame.keypoints, base_c.keypoints, cfg.ratio, method=method)
    attr = heading.attribute_differences(frame.keypoints, base_c.keypoints, matches)
    if seeds:
        priors = _seed_priors(seeds, lens, frame, base_c, matches, attr, cfg)
    else:
        priors = heading.priors_without_seed(
            frame.keypoints.xy[matches.idx_a],
            base_c.keypoints.xy[matches.idx_b],
            *attr,
            max(w, h) * frame.scale,
            cfg.heading,
        )
    return priors, matches, attr


# Where a click would help the coarse step, the reason says so in these words; the front ends
# add how to give one (``CoarseResult.remedy``).
CLICK_HELPS = "click one corresponding point in the frame and the map to help"


def _decide(attempts, priors, seeds, frame, base_c, cfg, w, h, lens) -> CoarseResult:
    """Build the result from the best attempt (or say why there is none)."""
    sf, sb = frame.scale, base_c.scale
    empty = np.zeros((0, 2))
    none = CoarseResult(False, "", None, empty, empty, np.zeros(0, bool), np.zeros(0, bool), 0, 0)
    if not priors:
        reason = (
            "coarse step: no SIFT match between the frame and the map supports any heading "
            "and scale"
        )
        if seeds:
            return replace(none, reason=f"{reason} around the seed; check the seed click")
        return replace(none, reason=f"{reason}; {CLICK_HELPS}", remedy="click")
    # Most support first; ties keep the candidates' order (stable).
    order = sorted(range(len(attempts)), key=lambda i: -attempts[i].score)
    best_i = order[0]
    best, prior = attempts[best_i], priors[best_i]
    full = prior.rescaled(1 / sf, 1 / sb)
    found = replace(
        none,
        frame_xy=rescale(best.frame_xy, 1 / sf),
        base_xy=rescale(best.base_xy, 1 / sb),
        gated=best.gated,
        inliers=best.inliers,
        heading_deg=full.heading_deg,
        scale=full.scale,
        gate={"two seeds": "two seeds", "seed": "seed"}.get(prior.source, "no seed"),
        ambiguity=prior.ambiguity,
        gate_center_base=full.anchor_base,
    )
    if seeds:
        outline = _gate_outline(full, w, h, lens, cfg)
        found = replace(
            found,
            gate_outline_base=outline,
            gate_radius_base=float(np.max(np.hypot(*(outline - full.anchor_base).T))),
        )
    if best.model is None:
        if seeds:
            return replace(found, reason=f"coarse step: {best.reason}; check the seed click")
        return replace(found, reason=f"coarse step: {best.reason}; {CLICK_HELPS}", remedy="click")
    if not seeds:
        why = _undecided_without_seed(best, attempts, order, cfg, w, h, sf, sb)
        if why:
            return replace(found, reason=f"coarse step: {why}; {CLICK_HELPS}", remedy="click")
    return replace(
        found,
        base_from_corrected=best.model.rescaled(1.0 / sf, 1.0 / sb),
        model_kind=best.kind,
        success=True,
    )


def _undecided_without_seed(best, attempts, order, cfg, w, h, sf, sb) -> str:
    """Why the best unseeded attempt cannot be trusted ("" when it can): too few inliers, or a
    rival nearly as well supported that puts the frame elsewhere."""
    if best.score < cfg.min_inliers_unseeded:
        return (
            f"without a seed the best registration has only {best.score} inliers (need "
            f"{cfg.min_inliers_unseeded})"
        )
    corners = frame_outline(w, h, per_edge=2) * sf
    for i in order[1:]:
        other = attempts[i]
        if other.model is None or other.score * cfg.decisive_ratio < best.score:
            continue
        gap = np.nanmax(np.hypot(*(best.model.apply(corners) - other.model.apply(corners)).T))
        if not gap <= 4 * cfg.ransac.threshold_px:
            return (
                f"cannot decide without a seed: two registrations {gap / sb:.0f} map px apart "
                f"have {best.score} and {other.score} inliers"
            )
    return ""


def _refuse_unconfirmed(result: CoarseResult, n_seeds: int) -> CoarseResult:
    """Refuse a registration the images do not confirm (``CoarseConfig.max_chance_p``): the
    keypoints that made it agree by chance, as on a map of another date whose keypoints barely
    repeat; saying so lets the analyst add the click that fixes heading and scale."""
    a = result.image_agreement
    help_ = (
        "check the click, or click a second corresponding point to fix heading and scale"
        if n_seeds
        else CLICK_HELPS
    )
    return replace(
        result,
        success=False,
        reason=(
            f"coarse step: the images do not confirm the registration found: {a.agreeing} of "
            f"{a.matched} map templates agree with it, as chance alone would (p = "
            f"{a.chance_p:.2g}); {help_}"
        ),
        remedy="" if n_seeds else "click",
        base_from_corrected=None,
    )


def _check_seed(result: CoarseResult, seeds, lens, cfg: CoarseConfig) -> CoarseResult:
    """Refuse a registration that puts a seed's frame point far from its clicked base point."""
    scale = result.scale or 1.0
    limit = cfg.seed_check_px + cfg.heading.seed_error_px * (1.0 + scale)
    gaps = seed_gaps(result.base_from_corrected, seeds, lens)
    for (fx, fy, bx, by), d in zip(seeds, gaps, strict=True):
        at = (bx - d[0], by - d[1])
        gap = float(np.hypot(*d))
        if not gap <= limit:
            return replace(
                result,
                success=False,
                reason=(
                    f"coarse step: the registration found puts the seed's frame point "
                    f"({fx:.0f}, {fy:.0f}) at map ({at[0]:.0f}, {at[1]:.0f}), {gap:.0f} px from "
                    f"the clicked ({bx:.0f}, {by:.0f}); check the click (both points must show "
                    "the same ground spot)"
                ),
                base_from_corrected=None,
            )
    return result
