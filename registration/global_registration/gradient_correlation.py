"""Correlation rounds of the coarse step (beyond the paper): the coarse model refined by
templates of gradient magnitude at reduced scale, with large search ranges.

SIFT descriptors across another date, season and sensor often disagree (on the OrthoLoC UAV
photo against an official orthophoto of another date, one right ratio-test match in 65 at full
resolution), while the edges of streets, kerbs and buildings stay where they were. Starting from
the coarse model (or only from the heading and scale of a seed), each round warps the base into
the frame's geometry at a reduced scale, correlates a dense grid of templates of the two images'
gradient magnitude over a wide search range (:mod:`registration.matching.templates`), and fits the model
the matches support (RANSAC, then the choice among similarity, affine and projective by spatial
cross-validation); later rounds use a finer scale and a narrower range. Measured on that
OrthoLoC pair from the seed's similarity alone: 52 px mean error with intensity correlation,
2.7 px with gradient magnitude after four rounds.

All models are ``base_from_corrected`` (corrected-frame pixels to base pixels).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.special import bdtrc

from registration.coords import image_size, rescale
from registration.geometry import Projective, RansacConfig, ransac, scale_at_frame_centre
from registration.matching import (
    TemplateConfig,
    downscale,
    downscale_mask,
    gradient_magnitude,
    template_control_points,
)


@dataclass(frozen=True)
class CorrelationConfig:
    """Correlation rounds (all beyond the paper; none in the ``paper`` preset).

    Attributes:
        rounds: ``(side_px, search_px)`` per round: the frame is resampled so that its longer
            side has ``side_px`` pixels (never above full resolution), and ``search_px`` is
            the search range's side in pixels at that scale. Empty = no correlation rounds.
        template: the templates (side, spacing in pixels at the round's scale, minimum
            score), correlated on the images' gradient magnitude; its ``search_px`` is set per
            round.
        ransac: RANSAC on the matches, pixels at the round's scale.
        min_inliers: fewest RANSAC inliers a round needs to replace the model.
    """

    rounds: tuple[tuple[float, int], ...] = ()
    template: TemplateConfig = field(
        default_factory=lambda: TemplateConfig(
            template_px=31,
            spacing_px=12,
            search_px=40,
            min_score=0.3,
            dither_iterations=0,
            edge_template_px=0,
            min_template_std=3.0,
            signal="intensity",
        )  # fmt: skip
    )
    ransac: RansacConfig = field(
        default_factory=lambda: RansacConfig(threshold_px=1.5, max_iterations=5000, refine="lm")
    )
    min_inliers: int = 12

    def __post_init__(self) -> None:
        for side, search in self.rounds:
            if not (side >= 32 and search >= 2):
                raise ValueError(
                    f"CorrelationConfig.rounds need side_px >= 32 and search_px >= 2, got "
                    f"({side}, {search})"
                )
        if self.min_inliers < 4:
            raise ValueError(f"CorrelationConfig.min_inliers must be >= 4, got {self.min_inliers}")


@dataclass(frozen=True)
class CorrelationResult:
    """Outcome of :func:`refine_by_correlation`.

    Attributes:
        model: the refined ``base_from_corrected`` projective (the start when no round
            succeeded).
        kind: the kind of model the last accepted round kept.
        inliers: RANSAC inliers of the last accepted round (0 = none accepted).
        rounds: rounds accepted.
        frame_xy, base_xy: the last accepted round's inlier matches, full-scale corrected frame
            px and base px.
    """

    model: Projective
    kind: str
    inliers: int = 0
    rounds: int = 0
    frame_xy: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    base_xy: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))


def refine_by_correlation(
    images: GradientImages,
    start: Projective,
    config: CorrelationConfig,
    select: Callable[[NDArray, NDArray, Projective], tuple[Projective, str]],
    rng: np.random.Generator,
    kind: str = "projective",
) -> CorrelationResult:
    """Refine ``start`` by the rounds of ``config`` (module doc).

    Args:
        images: the frame's and the base's gradient magnitude (:func:`gradient_images`).
        start: ``base_from_corrected`` to start from.
        config: the rounds.
        select: ``(frame_xy, base_xy, projective) -> (model, kind)``, the model choice on a
            round's inliers (full-scale pixels).
        rng: random generator of RANSAC.
        kind: the kind of ``start``.
    """
    out = CorrelationResult(start, kind)
    for side, search in config.rounds:
        found = _one_round(images, out.model, side, search, config, rng)
        if found is None:
            continue
        src, dst, model = found
        out = CorrelationResult(model, "projective", len(src), out.rounds + 1, src, dst)
    if out.rounds:
        # The model choice on the last round's matches only: during the rounds a projective
        # follows a strongly tilted frame's perspective, which the next round's windows need.
        model, kind = select(out.frame_xy, out.base_xy, out.model)
        out = replace(out, model=model, kind=kind)
    return out


@dataclass(frozen=True)
class GradientImages:
    """Both images' full-resolution gradient magnitude (uint8, :func:`gradient_magnitude`),
    the base's validity and the frame's pixel link (its pixels <-> corrected pixels)."""

    frame: NDArray[np.uint8]
    base: NDArray[np.uint8]
    valid: NDArray[np.bool_] | None
    to_corrected: Callable[[NDArray], NDArray]
    from_corrected: Callable[[NDArray], NDArray]


def gradient_images(
    frame_grey: NDArray[np.uint8],
    to_corrected: Callable[[NDArray], NDArray],
    from_corrected: Callable[[NDArray], NDArray],
    base: NDArray,
    base_valid: NDArray | None,
) -> GradientImages:
    """What the correlation rounds and :func:`agreement` read, computed once for a frame and
    a map (1.7 s for an 80 MP map, once instead of four times per coarse step).

    Args:
        frame_grey: the image control points are found in (raw or corrected frame), ``(H, W)``.
        to_corrected, from_corrected: its pixels <-> corrected pixels (``(N, 2)``).
        base: base map (grey or colour); base_valid: ``(Hb, Wb)`` bool, where it has content
            (None = everywhere).
    """
    # Gradient magnitude at full resolution, then area-averaged per round: the density of fine
    # edges (lane markings, kerbs, cars, roof texture) survives the reduction, which the
    # gradient of the reduced image loses (on the OrthoLoC pair: 2.7 px against 42 px).
    return GradientImages(
        gradient_magnitude(frame_grey), gradient_magnitude(base), base_valid, to_corrected,
        from_corrected,
    )  # fmt: skip


def _match_round(images: GradientImages, model, side: int, search: int, config: CorrelationConfig):
    """The templates of one round: ``(control points at the round's scale, s, s_b,
    base_from_small)`` with the frame resampled to ``side`` px (scale ``s``) and the base to the
    same ground resolution under ``model`` (``s_b``)."""
    w, h = image_size(images.frame)
    s = min(1.0, side / max(w, h))
    scale = scale_at_frame_centre(model, images.to_corrected, w, h)
    s_b = min(1.0, s / scale) if np.isfinite(scale) and scale > 0 else s
    small, base_small = downscale(images.frame, s), downscale(images.base, s_b)
    valid_small = None
    if images.valid is not None:
        valid_small = downscale_mask(images.valid, s_b)

    def base_from_small(xy: NDArray) -> NDArray:
        return rescale(model.apply(images.to_corrected(rescale(xy, 1.0 / s))), s_b)

    def small_from_base(xy: NDArray) -> NDArray:
        return rescale(images.from_corrected(model.inverse(rescale(xy, 1.0 / s_b))), s)

    tcfg = dataclasses.replace(config.template, search_px=int(search))
    cps = template_control_points(
        small, base_small, base_from_small, small_from_base, tcfg, ref_valid=valid_small
    )
    return cps, s, s_b, base_from_small


def _one_round(images: GradientImages, model, side, search, config, rng):
    """One round: ``(frame_xy, base_xy, model)`` of the RANSAC inliers (full-scale corrected
    and base px), or None."""
    cps, s, s_b, _ = _match_round(images, model, side, search, config)
    if len(cps) < config.min_inliers:
        return None
    # RANSAC in corrected pixels (at the round's scale): a raw frame's lens distortion is not
    # projective.
    src_small = rescale(images.to_corrected(rescale(cps.src, 1.0 / s)), s)
    fit = ransac(src_small, cps.dst, Projective, config.ransac, rng)
    if not fit or fit.n_inliers < config.min_inliers:
        return None
    src = rescale(src_small[fit.inliers], 1.0 / s)
    dst = rescale(cps.dst[fit.inliers], 1.0 / s_b)
    refit = Projective.estimate(src, dst, initial=fit.model.rescaled(1.0 / s, 1.0 / s_b),
                                optimizer="lm")  # fmt: skip
    return (src, dst, refit) if refit else None


@dataclass(frozen=True)
class Agreement:
    """How well the images confirm a model (:func:`agreement`).

    Attributes:
        agreeing: templates of the last round's grid whose gradient-magnitude match lies within
            ``ransac.threshold_px`` of where the model puts them.
        matched: templates that found a match anywhere in their search range.
        chance_p: probability that ``agreeing`` or more of ``matched`` agree by chance, each
            match falling anywhere in its search square (binomial tail; 1 when none agree).
    """

    agreeing: int
    matched: int
    chance_p: float


def agreement(images: GradientImages, model: Projective, config: CorrelationConfig) -> Agreement:
    """How the last round's templates confirm ``model``: an image-based check of a model,
    independent of the SIFT matches it may come from. A wrong model still gets a few agreeing
    templates by chance (a match falls within the threshold's disc of its ``search_px`` square
    with probability ``pi r² / search_px²``, 7 % for the default rounds), hence ``chance_p``."""
    if not config.rounds:
        return Agreement(0, 0, 1.0)
    side, search = config.rounds[-1]
    cps, _, _, base_from_small = _match_round(images, model, side, search, config)
    if not len(cps):
        return Agreement(0, 0, 1.0)
    pred = base_from_small(cps.src)
    r = config.ransac.threshold_px
    k = int(np.count_nonzero(np.hypot(*(pred - cps.dst).T) <= r))
    p_one = min(1.0, math.pi * r * r / float(search) ** 2)
    # P(X >= k) = P(X > k - 1)
    return Agreement(k, len(cps), float(bdtrc(k - 1, len(cps), p_one)) if k else 1.0)
