"""The coarse projective step (paper 4.3.1), at any heading and scale between frame and map.

Paper steps: grey, 1/4 scale, one manually identified correspondence, SIFT in both images,
matches, RANSAC (4 points, 5 px, 1000 iterations) with Nelder-Mead. The paper's map was within
~10° and ~20 % of its frames; ours may be at any heading and resolution, so (beyond the paper):

1. The heading and scale are estimated first (:mod:`registration.heading`): from the seed's
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
   the result, or rescues a seeded one SIFT could not find (:mod:`registration.correlation`).
6. A result that contradicts the clicked seed by more than the click can be off is refused with a
   message that says so, never returned silently.

All models are ``base_from_corrected``: corrected-frame pixels to base pixels. The intra-sensor
coarse step (paper 4.4) shares :func:`fit_coarse` with a prediction gate instead of the seed.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from registration import features, heading
from registration.camera import Camera, as_camera
from registration.coords import frame_outline, image_size, rescale
from registration.correlation import (
    Agreement,
    CorrelationConfig,
    agreement,
    gradient_images,
    refine_by_correlation,
)
from registration.distortion import HarrisModel, TwoTermHarrisModel
from registration.features import Keypoints, SiftConfig
from registration.heading import HeadingConfig, SimilarityPrior
from registration.models import Affine, Projective, Similarity, quantized
from registration.robust import RansacConfig, hull_coverage, ransac, simplest_supported

Seed = tuple[float, float, float, float]

__all__ = [
    "CoarseBase",
    "CoarseConfig",
    "CoarseFeatures",
    "CoarseResult",
    "FrameView",
    "Seed",
    "coarse_features",
    "coarse_register",
    "coarse_scale",
    "fit_coarse",
    "frame_view",
    "normalise_seeds",
]

_MODELS = {"similarity": Similarity, "affine": Affine, "projective": Projective}


@dataclass(frozen=True)
class CoarseConfig:
    """Coarse projective step at a reduced scale (paper 4.3.1, reused for intra-sensor frames).

    Attributes:
        scale: image scale of the coarse step (paper: both images sub-sampled to 1/4).
        min_side_px: beyond the paper: the coarse frame's longer side is at least this many
            pixels (0 = always ``scale``). 1/4 of the paper's 2560 px frames is 640 px; 1/4 of a
            640 px frame (160 px) leaves too little for SIFT.
        sift: SIFT settings at that scale.
        ratio: Lowe's ratio test threshold for matching (stricter when smaller).
        heading: heading and scale estimate and the location gate built on it
            (:mod:`registration.heading`).
        ransac: RANSAC settings, in coarse-scale pixels (paper: 4 points, 5 px, 1000 iterations,
            Nelder-Mead refinement).
        guided: beyond the paper: add matches found among the base keypoints near where the
            heading estimate puts each frame keypoint, and keep only those consistent with a
            similarity through the seed before RANSAC.
        refine_rounds: beyond the paper: rounds of re-matching within ``refine_radius_px`` of
            where the fitted model puts each keypoint, each followed by a refit.
        refine_radius_px: search radius of those rounds, coarse base pixels.
        match_base_scale: beyond the paper: detect the base's coarse keypoints at the scale
            that gives both images the same ground resolution once the scale is estimated
            (only when it differs from the frame's by more than 1.5x).
        models: candidate models, chosen on the final inliers by BIC (paper: projective only).
        prefilter_slope: beyond the paper, with ``guided``: the threshold of the similarity
            pre-filter through the anchor grows by this times the estimated scale times the
            matches' extent (coarse px), so that a frame whose perspective a similarity cannot
            follow keeps its far matches (0: the RANSAC threshold plus the anchor's error).
        correlation: beyond the paper: rounds of gradient-magnitude template correlation at
            reduced scale that refine the result (and, with a seed, rescue a failed SIFT step
            from the seed's heading and scale): :mod:`registration.correlation`. None by
            default (the paper).
        min_inliers_unseeded: fewest inliers a registration found without a seed needs (12).
        decisive_ratio: without a seed, the best candidate must have at least this many times
            the inliers of any candidate that disagrees with it (1.5), else the step reports
            that it cannot decide.
        seed_check_px: a result that puts the seed's frame point farther than this (full-scale
            base pixels, plus the click errors) from the clicked base point is refused (40).
        max_chance_p: with ``correlation`` rounds and fewer than two seeds, a result is refused
            when chance alone would make at least as many templates of the last round agree
            with it with a probability above this (:func:`registration.correlation.agreement`):
            the images do not show it (2e-3; 1 = never). On the 200 real SRIF pairs it refuses
            8 one-click results, 7 of them wrong by 12-1107 px and one right (3.9 px; p 0.13),
            and 10 results without a click, all wrong by 44-768 px; the least confirmed right
            result kept has p 3e-4, the best confirmed wrong one refused 0.013. Two seeds fix
            heading and scale themselves, so their result is kept and ``image_agreement`` says
            how weakly it is confirmed.
    """

    scale: float = 0.25
    min_side_px: int = 0
    sift: SiftConfig = field(default_factory=SiftConfig)
    ratio: float = 0.8
    heading: HeadingConfig = field(default_factory=HeadingConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)
    guided: bool = False
    refine_rounds: int = 0
    refine_radius_px: float = 3.0
    match_base_scale: bool = False
    models: tuple[str, ...] = ("projective",)
    prefilter_slope: float = 0.0
    correlation: CorrelationConfig = field(default_factory=CorrelationConfig)
    min_inliers_unseeded: int = 12
    decisive_ratio: float = 1.5
    seed_check_px: float = 40.0
    max_chance_p: float = 2e-3

    def __post_init__(self) -> None:
        if not 0 < self.scale <= 1:
            raise ValueError(f"CoarseConfig.scale must be in (0, 1], got {self.scale}")
        if self.min_side_px < 0 or self.refine_rounds < 0:
            raise ValueError(
                f"CoarseConfig.min_side_px and refine_rounds must be >= 0, got "
                f"{self.min_side_px}, {self.refine_rounds}"
            )
        if not 0 < self.max_chance_p <= 1:
            raise ValueError(
                f"CoarseConfig.max_chance_p must be in (0, 1], got {self.max_chance_p}"
            )
        unknown = [m for m in self.models if m not in _MODELS]
        if not self.models or unknown:
            raise ValueError(
                f"CoarseConfig.models must be a non-empty subset of {sorted(_MODELS)}, "
                f"got {self.models!r}"
            )


@dataclass
class CoarseResult:
    """Outcome of a coarse projective step; match arrays are full-scale pixels.

    ``frame_xy`` are corrected-frame pixels, ``base_xy`` base pixels (or, for intra-sensor
    frames, base pixels of the joint base). ``gated`` marks matches that passed the location gate,
    ``inliers`` the RANSAC inliers among all matches. ``heading_deg`` and ``scale`` are the
    estimate the gate used (rotation frame -> base in degrees, clockwise on screen; base px per
    frame px), ``gate`` says what it was built from, ``gate_outline_base`` is the region of the
    base where gated matches can lie (a polygon, ``(M, 2)`` base px), and ``model_kind`` which
    model was kept, ``image_agreement`` how the last correlation round's templates confirm it
    (None without correlation rounds), ``seeds`` the clicks it was given (``(fx, fy, bx, by)``,
    raw frame px and base px; the fine step may refit through them). For intra-sensor frames,
    ``path`` is the step that produced the model (``"fast"``: :mod:`registration.fast_coarse`,
    ``"sift"``: the SIFT step) and ``fast_reason`` why the fast path was not used (``"off"``
    when it is disabled or there is no previous frame; empty when it was used).
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
    heading_deg: float | None = None
    scale: float | None = None
    gate: str = ""
    gate_outline_base: NDArray[np.float64] | None = None
    model_kind: str = "projective"
    ambiguity: float | None = None
    correlation_inliers: int = 0
    image_agreement: Agreement | None = None
    path: str = ""
    fast_reason: str = ""
    seeds: tuple[Seed, ...] = ()

    @property
    def n_matches(self) -> int:
        return int(len(self.frame_xy))

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    def __bool__(self) -> bool:
        return self.success


@dataclass
class CoarseFeatures:
    """SIFT keypoints of an image at the coarse scale (``xy`` in coarse-scale pixels)."""

    keypoints: Keypoints
    scale: float


@dataclass
class FrameView:
    """The grey image control points are found in, and its pixels' link to corrected pixels.

    With ``match_in="corrected"`` (the paper) the image is the radially corrected frame on the
    raw frame's canvas and the link is the identity; its corners lose the content that the
    correction pushes outside the canvas (at γ = 0.7 the raw corners move 1.8x further out), so
    the global model extrapolates there. With ``match_in="raw"`` the image is the raw frame and
    the camera's lens model links its pixels to corrected ones: every raw pixel can carry a control
    point and the frame is not resampled before matching.
    """

    grey: NDArray[np.uint8]
    lens: HarrisModel | TwoTermHarrisModel | None

    def to_corrected(self, xy: NDArray) -> NDArray:
        return xy if self.lens is None else self.lens.corrected_from_raw(xy)

    def from_corrected(self, xy: NDArray) -> NDArray:
        return xy if self.lens is None else self.lens.raw_from_corrected(xy)


def corrected_grey(frame_raw: NDArray, camera: Camera | float) -> NDArray[np.uint8]:
    """Radially corrected grey frame on the raw frame's canvas (paper section 3); ``camera``:
    the frame's :class:`registration.camera.Camera` or its Harris γ."""
    return features.to_grey(as_camera(camera, frame_raw).undistort(frame_raw))


def frame_view(frame_raw: NDArray, camera: Camera | float, match_in: str) -> FrameView:
    """See :class:`FrameView`; ``camera``: the frame's :class:`registration.camera.Camera` (or
    its Harris γ)."""
    camera = as_camera(camera, frame_raw)
    if match_in == "corrected":
        return FrameView(corrected_grey(frame_raw, camera), None)
    if match_in == "raw":
        return FrameView(features.to_grey(frame_raw), camera.lens)
    raise ValueError(f"match_in must be 'raw' or 'corrected', got {match_in!r}")


def coarse_scale(width: int, height: int, config: CoarseConfig) -> float:
    """The frame's coarse scale: ``config.scale``, raised so that the longer side keeps at least
    ``config.min_side_px`` pixels (never above 1)."""
    s = config.scale
    if config.min_side_px:
        s = max(s, config.min_side_px / max(width, height, 1))
    return min(1.0, s)


def coarse_features(
    grey: NDArray[np.uint8],
    config: CoarseConfig,
    mask=None,
    view: FrameView | None = None,
    *,
    scale: float | None = None,
) -> CoarseFeatures:
    """SIFT at the coarse scale (paper 4.3.1 steps 1, 2 and 4).

    ``scale`` defaults to ``config.scale``. With a ``view``, keypoint positions are converted to
    corrected-frame pixels (at the coarse scale), so that everything downstream is in corrected
    coordinates. ``mask`` (``(H, W)``, non-zero = usable) keeps keypoints whose SIFT support lies
    inside it: the coarse mask is eroded by 3 px so that the edge of a no-data area (black
    corners of a rotated orthophoto) does not make keypoints of its own.
    """
    s = config.scale if scale is None else scale
    small = features.downscale(grey, s)
    small_mask = None
    if mask is not None:
        small_mask = features.downscale_mask(mask, s).astype(np.uint8)
        small_mask = cv2.erode(small_mask, np.ones((7, 7), np.uint8))
    kp = features.detect_sift(small, config.sift, mask=small_mask)
    if view is not None and view.lens is not None and len(kp.xy):
        kp = dataclasses.replace(kp, xy=rescale(view.to_corrected(rescale(kp.xy, 1.0 / s)), s))
    return CoarseFeatures(kp, s)


class CoarseBase:
    """The base map's coarse keypoints, computed once per scale (and region) and cached.

    Args:
        base: base map (Hb, Wb[, 3]) uint8.
        config: the coarse step's settings.
        valid: optional (Hb, Wb) bool, where the base has content (no-data elsewhere).
    """

    def __init__(self, base: NDArray, config: CoarseConfig, valid: NDArray | None = None):
        self.grey = features.to_grey(base)
        self.valid = None if valid is None else np.asarray(valid, bool)
        if self.valid is not None and self.valid.shape != self.grey.shape:
            raise ValueError(
                f"base validity mask is {self.valid.shape[::-1]} but the base is "
                f"{self.grey.shape[::-1]} (W, H)"
            )
        self.config = config
        self._cache: dict[tuple, CoarseFeatures] = {}

    @property
    def size(self) -> tuple[int, int]:
        return image_size(self.grey)

    def features(
        self, scale: float, box: tuple[int, int, int, int] | None = None
    ) -> CoarseFeatures:
        """Keypoints at ``scale`` (coarse px of the whole base), optionally only inside the
        full-scale box ``(x0, y0, x1, y1)`` (detected on that crop: cheaper on a large map)."""
        key = (round(scale, 6), box)
        if key not in self._cache:
            grey, valid, offset = self.grey, self.valid, np.zeros(2)
            if box is not None:
                x0, y0, x1, y1 = box
                # Snap the crop to whole coarse pixels so that crop and full-map coarse
                # coordinates agree exactly.
                step = max(1, round(1 / scale))
                x0, y0 = x0 // step * step, y0 // step * step
                grey = grey[y0:y1, x0:x1]
                valid = None if valid is None else valid[y0:y1, x0:x1]
                offset = np.array([x0, y0], float) * scale
            feats = coarse_features(grey, self.config, mask=valid, scale=scale)
            kp = feats.keypoints
            if box is not None and len(kp):
                kp = dataclasses.replace(kp, xy=kp.xy + offset)
            self._cache[key] = CoarseFeatures(kp, scale)
        return self._cache[key]


def normalise_seeds(seed) -> list[Seed]:
    """``None``, one ``(fx, fy, bx, by)`` or a sequence of up to two of them -> list of seeds."""
    if seed is None:
        return []
    arr = np.asarray(seed, dtype=np.float64)
    if arr.shape == (4,):
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 4 or len(arr) > 2 or not np.isfinite(arr).all():
        raise ValueError(
            f"seed must be one or two finite (fx, fy, bx, by) correspondences, got {seed!r}"
        )
    return [tuple(float(v) for v in row) for row in arr]


# ------------------------------------------------------------------------------------------
# Fitting


def _ransac_config(config: CoarseConfig, **changes) -> RansacConfig:
    return dataclasses.replace(config.ransac, **changes)


# Share of the frame the inliers must span for a model's extra terms to be considered, as in
# the fine step (registration.global_registration.FINE_MIN_COVERAGE says why and what it gave).
COARSE_MIN_COVERAGE = {"affine": 0.3, "projective": 0.5}


def _select_model(src, dst, kinds: Sequence[str], current: Projective, probes) -> tuple:
    """The model among ``kinds`` that predicts held-out parts of the pairs best
    (:func:`registration.robust.simplest_supported`, spatial cross-validation): an affine's or
    a projective's extra terms are kept only where the points span enough of the frame
    (:data:`COARSE_MIN_COVERAGE`), since undetermined ones extrapolate badly at the frame's
    corners. Returns ``(Projective, kind)``."""
    fits = []
    for kind in ("similarity", "affine", "projective"):
        if kind in kinds:
            m = current if kind == "projective" else _MODELS[kind].estimate(src, dst)
            if m:
                fits.append((kind, m))
    if not fits:
        return current, "projective"
    kind, model = simplest_supported(
        fits, src, dst, probes=probes, min_coverage=COARSE_MIN_COVERAGE
    )
    return (model if kind == "projective" else model.as_projective()), kind


def projective_or_simpler(
    src: NDArray, dst: NDArray, fitted: Projective, config: CoarseConfig, probes, scale: float
) -> tuple[Projective, str]:
    """``(model, kind)``: the projective ``fitted`` to the inlier pairs ``src -> dst`` (px at
    ``scale``) when they span at least :data:`COARSE_MIN_COVERAGE`'s share for it of ``probes``
    (full-scale corrected px over the frame; None = no check), else the model
    :func:`_select_model` chooses among ``config.models`` (a projective on matches in one part
    of the frame can put its far side hundreds of pixels off)."""
    if probes is None or len(config.models) < 2:
        return fitted, "projective"
    probes = rescale(probes, scale)
    if hull_coverage(src, probes) >= COARSE_MIN_COVERAGE["projective"]:
        return fitted, "projective"
    return _select_model(src, dst, config.models, fitted, probes)


@dataclass
class _Attempt:
    """One prior's outcome, in coarse pixels: every ratio match plus the guided ones (``gated``
    marks those the gate let through), the inliers of the kept model among them, and ``score``:
    how many gated candidates the kept model fits (its support)."""

    model: Projective | None
    kind: str
    frame_xy: NDArray
    base_xy: NDArray
    gated: NDArray
    inliers: NDArray
    reason: str
    score: int = 0


def _attempt(
    prior: SimilarityPrior,
    frame: CoarseFeatures,
    base: CoarseFeatures,
    matches: features.Matches,
    config: CoarseConfig,
    rng: np.random.Generator,
    anchored: bool,
    domain: NDArray,
) -> _Attempt:
    """Gate (and guide) the matches with a coarse-pixel prior, RANSAC, refine (module doc).

    Consensus searches (:func:`_consensus`) on two sets of pairs when ``guided``: the gated
    ratio matches (the paper; right matches are then often the majority, and a strongly tilted
    frame's perspective survives), and those plus the guided matches, pre-filtered by a
    similarity through the anchor (more right matches when the ratio test keeps few, as across
    years and sensors); each from a projective and from an affine RANSAC. The search whose
    model fits the most gated candidates wins, the simplest model among those within
    ``_NEAR_BEST`` of it. ``domain``: centres of a 10 x 10 grid of cells over the frame in
    coarse corrected pixels (for the model choice).
    """
    hcfg = config.heading
    fk, bk = frame.keypoints, base.keypoints
    all_p, all_q = fk.xy[matches.idx_a], bk.xy[matches.idx_b]
    gated = heading.gate_by_prior(all_p, all_q, prior, hcfg)
    n_ratio = len(all_p)
    if config.guided and len(fk):
        radius = heading.gate_radius_px(prior, fk.xy, hcfg)
        g = heading.guided_matches(
            fk, bk, prior.apply(fk.xy), radius, prior.heading_deg, prior.scale, hcfg
        )
        new = ~np.isin(g.idx_a, matches.idx_a[gated])
        all_p = np.vstack([all_p, fk.xy[g.idx_a[new]]])
        all_q = np.vstack([all_q, bk.xy[g.idx_b[new]]])
        gated = np.concatenate([gated, np.ones(int(new.sum()), bool)])
    out = _Attempt(None, "", all_p, all_q, gated, np.zeros(len(all_p), bool), "")
    sources = [np.flatnonzero(gated[:n_ratio])]
    if config.guided:
        sources.append(_similarity_prefilter(all_p, all_q, np.flatnonzero(gated), prior, config,
                                             rng, anchored))  # fmt: skip
    found_all = []
    firsts = [Projective] + ([Affine] if "affine" in config.models and config.guided else [])
    for idx in sources:
        if len(idx) < Projective.min_samples:
            continue
        for first in firsts:
            found = _consensus(all_p[idx], all_q[idx], fk, bk, prior, config, rng, domain, first)
            if found is None:
                continue
            # One yardstick for every search: the gated candidates the final model fits (the
            # refinement's own matches would favour a search that confirms itself).
            support = _support(found[0], all_p[gated], all_q[gated], config)
            found_all.append((support, found))
    best, best_support = None, -1
    if found_all:
        top = max(f[0] for f in found_all)
        # The simplest model among the nearly best wins (ties: the first found).
        near = [f for f in found_all if f[0] >= _NEAR_BEST * top]
        best_support, best = min(near, key=lambda f: _COMPLEXITY[f[1][1]])
    if best is None:
        n = int(gated.sum())
        out.reason = (
            f"only {n} matches agree with the heading {prior.heading_deg:.0f}° and scale "
            f"{prior.scale * frame.scale / base.scale:.2f} estimated {_from(prior)}"
            if n < Projective.min_samples
            else f"RANSAC found no consensus among the {n} gated matches"
        )
        return out
    model, kind, fit_p, fit_q = best
    out.model, out.kind, out.score = model, kind, best_support
    out.inliers = gated & (np.hypot(*(model.apply(all_p) - all_q).T) < config.ransac.threshold_px)
    return out


def _support(model, p, q, config: CoarseConfig) -> int:
    return int(np.count_nonzero(np.hypot(*(model.apply(p) - q).T) < config.ransac.threshold_px))


def _similarity_prefilter(p, q, idx, prior, config, rng, anchored) -> NDArray:
    """The pairs ``idx`` consistent with a similarity through the anchor (one pair plus the seed
    per sample): most wrong guided matches go before the projective RANSAC."""
    if len(idx) < Similarity.min_samples + 1:
        return idx
    extent = float(np.ptp(p[idx], axis=0).max())
    thr = (
        config.ransac.threshold_px
        + prior.anchor_error_px
        + config.prefilter_slope * prior.scale * extent
    )
    fixed = (prior.anchor_frame[None], prior.anchor_base[None]) if anchored else None
    cfg = _ransac_config(config, sample_size=2, threshold_px=thr, refine="lstsq", min_inliers=4)
    sim = ransac(p[idx], q[idx], Similarity, cfg, rng, fixed=fixed)
    if sim and sim.n_inliers >= Projective.min_samples:
        return idx[sim.inliers]
    return idx


# Searches whose support is within this share of the best count as equally good; the simplest
# model among them is kept (a richer one fits a few more pairs of a partial overlap and
# extrapolates worse).
_NEAR_BEST = 0.9
_COMPLEXITY = {"similarity": 0, "affine": 1, "projective": 2}


def _consensus(p, q, fk, bk, prior, config, rng, domain, first=Projective):
    """RANSAC on the pairs (the ``first`` model: projective, or affine then refitted as a
    projective), the model the points support (:func:`_select_model`), then ``refine_rounds``
    of guided re-matching within ``refine_radius_px`` of that model and a projective RANSAC on
    those matches; a round that fits fewer of the original pairs is undone. Returns ``(model,
    kind, fitted frame px, fitted base px)`` or None."""
    fit = ransac(p, q, first, _ransac_config(config, sample_size=first.min_samples), rng)
    if not fit:
        return None
    start = fit.model if first is Projective else fit.model.as_projective()
    if first is not Projective:
        refit = Projective.estimate(p[fit.inliers], q[fit.inliers], initial=start, optimizer="lm")
        start = refit if refit else start
    model, kind = _select_model(p[fit.inliers], q[fit.inliers], config.models, start, domain)
    best = (model, kind, p[fit.inliers], q[fit.inliers])
    support = _support(model, p, q, config)
    for _ in range(config.refine_rounds):
        g = heading.guided_matches(
            fk, bk, best[0].apply(fk.xy), config.refine_radius_px, prior.heading_deg,
            prior.scale, config.heading, ratio=0.95,
        )  # fmt: skip
        if len(g) < Projective.min_samples:
            break
        gp, gq = fk.xy[g.idx_a], bk.xy[g.idx_b]
        refit = ransac(gp, gq, Projective, config.ransac, rng)
        if not refit:
            break
        m, k = _select_model(gp[refit.inliers], gq[refit.inliers], config.models, refit.model,
                             domain)  # fmt: skip
        s = _support(m, p, q, config)
        if s < support:
            break
        best, support = (m, k, gp[refit.inliers], gq[refit.inliers]), s
    return best


def _from(prior: SimilarityPrior) -> str:
    return {"two seeds": "from the two seeds", "seed": "around the seed"}.get(
        prior.source, "without a seed"
    )


def fit_coarse(
    frame_feats: CoarseFeatures,
    refs: list[tuple[CoarseFeatures, Callable | None]],
    config: CoarseConfig,
    gate: Callable | None,
    rng: np.random.Generator,
    n_keypoints_base: int,
    known: list[features.Matches | None] | None = None,
    probes: NDArray | None = None,
) -> CoarseResult:
    """Match the frame against each reference separately, gate, RANSAC at the coarse scale
    (the intra-sensor coarse step, paper 4.4).

    ``refs`` holds (features, to_base) pairs: ``to_base`` maps the reference's full-scale pixels
    to base pixels (None = already base pixels). Matching each reference on its own keeps the
    ratio test from rejecting a point because it appears in two references. ``known`` gives
    matches already computed, per reference (None = match here). ``gate`` is called with
    full-scale ``(frame_xy, base_xy)`` and returns a bool mask (None = no gate). With
    ``probes`` (``(N, 2)`` full-scale corrected px spread over the frame, e.g. cell centres),
    inliers spanning less than half of the frame get a simpler model
    (:func:`projective_or_simpler`): on a real roundabout at 320x240, a projective on 8 matches
    in one part of the frame put its far side up to 760 px off.
    """
    s = frame_feats.scale
    frame_xy, base_xy = [], []
    for i, (feats, to_base) in enumerate(refs):
        m = known[i] if known is not None else None
        if m is None:
            m = features.match_ratio(frame_feats.keypoints, feats.keypoints, config.ratio)
        if len(m.idx_a) == 0:
            continue
        f_full = rescale(frame_feats.keypoints.xy[m.idx_a], 1.0 / s)
        b_full = rescale(feats.keypoints.xy[m.idx_b], 1.0 / feats.scale)
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
        gate="prediction from the previous frame" if gate is not None else "none",
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
    src, dst = rescale(frame_xy[inliers], s), rescale(base_xy[inliers], s)
    model, result.model_kind = projective_or_simpler(src, dst, fit.model, config, probes, s)
    result.base_from_corrected = quantized(model.rescaled(1.0 / s, 1.0 / s))
    result.success = True
    return result


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
        valid = features.downscale_mask(cbase.valid, s_b)
    found = heading.prior_from_patch(
        features.downscale(view.grey, s_f), features.downscale(cbase.grey, s_b),
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
        camera: the frame's :class:`registration.camera.Camera`, or its Harris γ.
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
    attempts = []
    for i, prior in enumerate(priors):
        attempts.append(_attempt(prior, frame, base_c, matches, cfg, rng, bool(seeds), domain))
        best = max(a.score for a in attempts)
        # Without a seed, stop once a registration stands out clearly from the candidates
        # left (their Hough votes bound how many matches they could gather).
        if (
            not seeds
            and i + 1 < len(priors)
            and best
            >= max(2 * cfg.min_inliers_unseeded, 2 * cfg.decisive_ratio * priors[i + 1].votes)
        ):
            break
    result = _decide(attempts, priors, seeds, frame, base_c, cfg, w, h, lens)
    result.n_keypoints_frame = len(frame.keypoints)
    result.n_keypoints_base = len(base_c.keypoints)
    result.seeds = tuple(seeds)
    if cfg.correlation.rounds and (result.success or (seeds and priors)):
        # The seed's own similarity start is the prior that won (the first when none did).
        won = max(range(len(attempts)), key=lambda i: attempts[i].score) if attempts else 0
        _correlate(result, view, cbase, priors[won], seeds, s_f, cfg, rng, domain, base_c.scale)
    if seeds and result.success:
        _check_seed(result, seeds, lens, cfg)
    confirm = result.image_agreement
    if result.success and len(seeds) < 2 and confirm and confirm.chance_p > cfg.max_chance_p:
        _refuse_unconfirmed(result, len(seeds))
    result.base_from_corrected = quantized(result.base_from_corrected)
    result.time_s = time.perf_counter() - t0
    return result


# The correlation rounds' model replaces the SIFT one only when this many times as many
# templates agree with it.
_CORRELATION_GAIN = 1.25


def _correlate(result, view, cbase, prior, seeds, s_f, cfg, rng, probes, s_b) -> None:
    """Refine the result by the correlation rounds, started from the SIFT model and, with a
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
        return
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
            result.image_agreement = agreement(images, result.base_from_corrected, cfg.correlation)
        return
    after = agreement(images, best.model, cfg.correlation)
    if result.success:
        # The SIFT model stays unless the images agree clearly better with the refined one
        # (another date or sensor can pull correlation by a few pixels where SIFT was right).
        before = agreement(images, result.base_from_corrected, cfg.correlation)
        result.correlation_inliers = after.agreeing
        if not after.agreeing > _CORRELATION_GAIN * before.agreeing:
            result.image_agreement = before
            return
    result.image_agreement = after
    result.base_from_corrected = best.model
    result.model_kind = best.kind
    result.correlation_inliers = best.inliers
    if not result.success:
        result.success, result.reason = True, ""
        result.gate = result.gate or "seed"


# The reference frame's matches are exact (brute force) below this many descriptor pairs (~1 s
# per 40 M here): a one-off per sequence, and FLANN's approximate neighbours change with its
# random trees, which moved the reference frame's registration by up to 0.3 px between seeds.
_EXACT_MAX_PAIRS = 400_000_000


def _priors(seeds, lens, frame, base_c, cfg, w, h):
    n_pairs = len(frame.keypoints) * len(base_c.keypoints)
    method = "bf" if n_pairs <= _EXACT_MAX_PAIRS else "flann"
    matches = features.match_ratio(frame.keypoints, base_c.keypoints, cfg.ratio, method=method)
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


def _decide(attempts, priors, seeds, frame, base_c, cfg, w, h, lens) -> CoarseResult:
    """Build the result from the best attempt (or say why there is none)."""
    sf, sb = frame.scale, base_c.scale
    empty = np.zeros((0, 2))
    result = CoarseResult(False, "", None, empty, empty, np.zeros(0, bool), np.zeros(0, bool), 0, 0)
    if not priors:
        result.reason = (
            "coarse step: no SIFT match between the frame and the map supports any heading "
            "and scale"
            + (" around the seed; check the seed click" if seeds else "; click one "
               "corresponding point in the frame and the map (--seed FX,FY,BX,BY) to help")
        )  # fmt: skip
        return result
    # Most support first; ties keep the candidates' order (stable).
    order = sorted(range(len(attempts)), key=lambda i: -attempts[i].score)
    best_i = order[0]
    best, prior = attempts[best_i], priors[best_i]
    result.frame_xy, result.base_xy = rescale(best.frame_xy, 1 / sf), rescale(best.base_xy, 1 / sb)
    result.gated, result.inliers = best.gated, best.inliers
    full = prior.rescaled(1 / sf, 1 / sb)
    result.heading_deg, result.scale = full.heading_deg, full.scale
    result.gate = {"two seeds": "two seeds", "seed": "seed"}.get(prior.source, "no seed")
    result.ambiguity = prior.ambiguity
    result.gate_center_base = full.anchor_base
    if seeds:
        outline = _gate_outline(full, w, h, lens, cfg)
        result.gate_outline_base = outline
        result.gate_radius_base = float(np.max(np.hypot(*(outline - full.anchor_base).T)))
    if best.model is None:
        result.reason = f"coarse step: {best.reason}" + (
            "; check the seed click" if seeds else
            "; click one corresponding point (--seed FX,FY,BX,BY) to help"
        )  # fmt: skip
        return result
    if not seeds:
        if best.score < cfg.min_inliers_unseeded:
            result.reason = (
                f"coarse step: without a seed the best registration has only "
                f"{best.score} inliers (need {cfg.min_inliers_unseeded}); click one "
                "corresponding point in the frame and the map (--seed FX,FY,BX,BY) to help"
            )
            return result
        corners = frame_outline(w, h, per_edge=2) * sf
        for i in order[1:]:
            other = attempts[i]
            if other.model is None or other.score * cfg.decisive_ratio < best.score:
                continue
            gap = np.nanmax(np.hypot(*(best.model.apply(corners) - other.model.apply(corners)).T))
            if not gap <= 4 * cfg.ransac.threshold_px:
                result.reason = (
                    f"coarse step: cannot decide without a seed: two registrations {gap / sb:.0f} "
                    f"map px apart have {best.score} and {other.score} inliers; click one "
                    "corresponding point in the frame and the map (--seed FX,FY,BX,BY) to help"
                )
                return result
    result.base_from_corrected = best.model.rescaled(1.0 / sf, 1.0 / sb)
    result.model_kind = best.kind
    result.success = True
    return result


def _refuse_unconfirmed(result: CoarseResult, n_seeds: int) -> None:
    """Refuse a registration the images do not confirm (``CoarseConfig.max_chance_p``): the
    keypoints that made it agree by chance, as on a map of another date whose keypoints barely
    repeat; saying so lets the analyst add the click that fixes heading and scale."""
    a = result.image_agreement
    help_ = (
        "check the click, or click a second corresponding point to fix heading and scale"
        if n_seeds
        else "click one corresponding point in the frame and the map (--seed FX,FY,BX,BY) to help"
    )
    result.success = False
    result.reason = (
        f"coarse step: the images do not confirm the registration found: {a.agreeing} of "
        f"{a.matched} map templates agree with it, as chance alone would (p = "
        f"{a.chance_p:.2g}); {help_}"
    )
    result.base_from_corrected = None


def _check_seed(result: CoarseResult, seeds, lens, cfg: CoarseConfig) -> None:
    """Refuse a registration that puts a seed's frame point far from its clicked base point."""
    scale = result.scale or 1.0
    limit = cfg.seed_check_px + cfg.heading.seed_error_px * (1.0 + scale)
    gaps = seed_gaps(result.base_from_corrected, seeds, lens)
    for (fx, fy, bx, by), d in zip(seeds, gaps, strict=True):
        at = (bx - d[0], by - d[1])
        gap = float(np.hypot(*d))
        if not gap <= limit:
            result.success = False
            result.reason = (
                f"coarse step: the registration found puts the seed's frame point "
                f"({fx:.0f}, {fy:.0f}) at map ({at[0]:.0f}, {at[1]:.0f}), {gap:.0f} px from the "
                f"clicked ({bx:.0f}, {by:.0f}); check the click (both points must show the "
                "same ground spot)"
            )
            result.base_from_corrected = None
            return
