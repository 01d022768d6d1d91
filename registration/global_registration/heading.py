"""Heading and scale between a frame and the base map, before any registration (paper 4.3.1).

The paper's single clicked correspondence "allowed location based filtering of the SIFT
features"; its map was within ~10° and ~20 % of the frame. A helicopter circles and a drone
flies any heading, and orthophotos come at 0.1-1 m/px, so here the rotation and scale of the
location gate come from the data, not from a north-up assumption:

* **One seed** (:func:`prior_from_seed`). A candidate match ``(p, q)`` and the seed
  ``(p0, q0)`` define the similarity that sends ``p - p0`` to ``q - q0``: its rotation is the
  angle between the two vectors and its scale the ratio of their lengths. Right matches all vote
  for the true heading and scale, wrong ones anywhere, so a 2-D histogram over (heading,
  log scale) peaks at the truth even with a few percent right matches. A vote counts only when
  the two keypoints' own SIFT orientation and size differences agree with it (a right match
  agrees; a random one rarely does).
* **One seed, few votes** (:func:`prior_from_patch`): across years and sensors a handful of
  right matches can be outvoted (or nothing votes). The images themselves then give a second
  estimate: the map's patch around the click is correlated with the frame resampled around its
  click at every heading and scale. The coarse step tries both gates and keeps the better
  supported registration.
* **Two seeds** (:func:`prior_from_seeds`) fix heading and scale exactly.
* **No seed** (:func:`priors_without_seed`): each match's keypoint orientation and size
  difference plus its position give a whole similarity; the 4-D Hough transform of Lowe (2004,
  section 7.3) over (heading, scale, translation) lists the candidate registrations, strongest
  first.

A :class:`SimilarityPrior` then gates matches (:func:`gate_by_prior`: the paper's location test,
with a sector whose direction and radii are the estimate's) and guides a second, local matching
(:func:`guided_matches`: each frame keypoint is compared only with base keypoints near where the
prior puts it, so the ratio test runs among few candidates and keeps right matches that a global
ratio test loses to look-alikes elsewhere in the map).

Points are ``(N, 2)`` float64 pixels of the image they belong to (``conventions.md``); angles are
degrees, counter-clockwise in the (x right, y down) image, i.e. clockwise on screen, the
convention of :class:`registration.geometry.linear.Similarity`. OpenCV's keypoint ``angle`` turns the same
way, so a right match's ``angle_base - angle_frame`` equals the heading.

References:
    Loveland & Rosten, section 4.3.1 (seed point, location based filtering).
    D. G. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 60(2), 2004,
    section 7.3 (Hough transform of keypoint poses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from registration.coords import as_points
from registration.geometry import Similarity
from registration.matching import Keypoints, Matches


@dataclass(frozen=True)
class HeadingConfig:
    """Settings of the heading and scale estimate and of the gate built on it.

    Distances are pixels of the images the points live in (coarse-scale pixels in the coarse
    step); ``*_deg`` are degrees.

    Attributes:
        bin_deg: heading bin of the one-seed histogram (5; finer bins split the peak of a
            frame whose perspective and lens make the local heading vary by a few degrees).
        bin_log_scale: natural-log scale bin of that histogram (0.05, i.e. 5 %).
        max_log_scale: scales ``exp(+-max_log_scale)`` are searched (2.5: 0.08x to 12x, e.g. a
            2560 px frame against a map at 1 m/px or at 0.1 m/px).
        attribute_tolerance_deg: a vote counts only when the keypoints' orientation difference
            is within this of the vote's heading (30; SIFT orientations of a right match agree
            to ~10-15° across sensors, a random match's are uniform).
        attribute_tolerance_log_scale: and their size ratio within this (natural log) of the
            vote's scale (0.5, i.e. a factor 1.65).
        min_seed_distance_px: votes of matches closer than this to the seed are not counted
            (20): near the seed its own click error dominates the vote's direction and length.
        seed_error_px: expected error of a clicked point in each image (full-scale pixels;
            turned into coarse pixels by the caller), part of the gate's slack (8).
        max_rotation_deg: the gate's rotation tolerance about the estimated heading (10): what
            perspective and lens leave of the local heading across a frame after the estimate.
        max_scale_error: the gate's relative scale tolerance about the estimated scale (0.15).
        slack_px: the gate's absolute slack on top of the click errors (4).
        hough_bin_deg: heading bin of the no-seed 4-D Hough transform (30, Lowe 2004).
        hough_bin_octaves: scale bin of that transform in octaves (1, Lowe 2004).
        hough_bin_extent: translation bin as a fraction of the frame's projected size (0.25,
            Lowe 2004).
        max_candidates: strongest no-seed Hough bins tried (6).
        min_votes: fewest votes a candidate needs (4).
        guided_ratio: ratio test among the candidates of a guided match (0.9: the candidates
            are few and near the prediction, so a looser test than the global 0.8 keeps more
            right matches without letting look-alikes from elsewhere in).
        guided_neighbours: at most this many base keypoints nearest to a prediction are
            compared (32).
        patch_below_votes: a one-seed estimate with fewer votes than this gets a second
            opinion from the images themselves around the seed (:func:`prior_from_patch`;
            6; 0 = never). Across years and sensors a few right SIFT matches can be outvoted.
        patch_radius_px: that patch's radius (40 px of the base, at the base's pyramid level
            where the patch spans about a sixth of the base's shorter side).
        patch_min_ncc: the patch estimate is used only when its best normalised correlation
            reaches this (0.3).
    """

    bin_deg: float = 5.0
    bin_log_scale: float = 0.05
    max_log_scale: float = 2.5
    attribute_tolerance_deg: float = 30.0
    attribute_tolerance_log_scale: float = 0.5
    min_seed_distance_px: float = 20.0
    seed_error_px: float = 8.0
    max_rotation_deg: float = 10.0
    max_scale_error: float = 0.15
    slack_px: float = 4.0
    hough_bin_deg: float = 30.0
    hough_bin_octaves: float = 1.0
    hough_bin_extent: float = 0.25
    max_candidates: int = 6
    min_votes: int = 4
    guided_ratio: float = 0.9
    guided_neighbours: int = 32
    patch_below_votes: int = 6
    patch_radius_px: int = 40
    patch_min_ncc: float = 0.3

    def __post_init__(self) -> None:
        for name in ("bin_deg", "bin_log_scale", "max_log_scale", "hough_bin_deg",
                     "hough_bin_octaves", "hough_bin_extent"):  # fmt: skip
            if not getattr(self, name) > 0:
                raise ValueError(f"HeadingConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.guided_ratio <= 1:
            raise ValueError(
                f"HeadingConfig.guided_ratio must be in (0, 1], got {self.guided_ratio}"
            )
        if not 0 <= self.max_scale_error < 1:
            raise ValueError(
                f"HeadingConfig.max_scale_error must be in [0, 1), got {self.max_scale_error}"
            )
        if self.patch_below_votes < 0 or self.patch_radius_px < 8:
            raise ValueError(
                "HeadingConfig.patch_below_votes must be >= 0 and patch_radius_px >= 8, got "
                f"{self.patch_below_votes} and {self.patch_radius_px}"
            )
        if self.max_candidates < 1 or self.min_votes < 1 or self.guided_neighbours < 2:
            raise ValueError(
                "HeadingConfig.max_candidates and min_votes must be >= 1 and guided_neighbours "
                f">= 2, got {self.max_candidates}, {self.min_votes}, {self.guided_neighbours}"
            )


@dataclass(frozen=True)
class SimilarityPrior:
    """An estimate ``base ~ anchor_base + scale R(heading) (frame - anchor_frame)``.

    Attributes:
        heading_deg: rotation from frame to base, degrees in [0, 360).
        scale: base pixels per frame pixel.
        anchor_frame: ``(2,)`` frame point the estimate is exact at (the seed, or the centroid
            of the Hough bin's matches).
        anchor_base: ``(2,)`` its base position.
        source: ``"two seeds"``, ``"seed"`` or ``"no seed"``.
        votes: support of the estimate (matches in the histogram peak; 2 for two seeds).
        ambiguity: the strongest competing peak's votes over this one's (0 = unambiguous,
            near 1 = two headings or scales are equally likely).
        anchor_error_px: how far (these pixels) the anchor's base position may be off: the
            click errors of a seed, or the spread of the bin's matches.
    """

    heading_deg: float
    scale: float
    anchor_frame: NDArray[np.float64]
    anchor_base: NDArray[np.float64]
    source: str
    votes: int
    ambiguity: float = 0.0
    anchor_error_px: float = 0.0

    @property
    def similarity(self) -> Similarity:
        return Similarity.from_rotation(
            self.heading_deg, self.scale, self.anchor_frame, self.anchor_base
        )

    def apply(self, xy: ArrayLike) -> NDArray[np.float64]:
        """Frame points ``(N, 2)`` -> predicted base points ``(N, 2)``."""
        return self.similarity.apply(xy)

    def rescaled(self, frame_scale: float, base_scale: float) -> SimilarityPrior:
        """The same estimate for images resampled by ``frame_scale`` and ``base_scale``."""

        def rs(xy, s):
            return (np.asarray(xy, float) + 0.5) * s - 0.5

        return SimilarityPrior(
            self.heading_deg,
            self.scale * base_scale / frame_scale,
            rs(self.anchor_frame, frame_scale),
            rs(self.anchor_base, base_scale),
            self.source,
            self.votes,
            self.ambiguity,
            self.anchor_error_px * base_scale,
        )


def attribute_differences(
    frame_kp: Keypoints, base_kp: Keypoints, matches: Matches
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(heading_deg, log_scale)`` per match from the keypoints' orientation and size."""
    dtheta = (base_kp.angle[matches.idx_b] - frame_kp.angle[matches.idx_a]) % 360.0
    with np.errstate(divide="ignore", invalid="ignore"):
        dlog = np.log(base_kp.size[matches.idx_b] / frame_kp.size[matches.idx_a])
    return dtheta, np.nan_to_num(dlog, nan=0.0, posinf=0.0, neginf=0.0)


def angle_gap_deg(a: NDArray, b: NDArray | float) -> NDArray:
    """Smallest absolute difference between headings, degrees in [0, 180]."""
    d = (np.asarray(a) - b) % 360.0
    return np.minimum(d, 360.0 - d)


def prior_from_seeds(
    frame_points: ArrayLike, base_points: ArrayLike, seed_error_px: float = 0.0
) -> SimilarityPrior:
    """Heading and scale fixed by two correspondences (``(2, 2)`` frame and base points).

    Raises:
        ValueError: when the two points coincide in either image.
    """
    f, b = as_points(frame_points, "frame_points"), as_points(base_points, "base_points")
    if f.shape != (2, 2) or b.shape != (2, 2):
        raise ValueError(f"two seeds need (2, 2) points on each side, got {f.shape} and {b.shape}")
    df, db = f[1] - f[0], b[1] - b[0]
    if math.hypot(*df) < 1.0 or math.hypot(*db) < 1.0:
        raise ValueError(
            "the two seeds must be different points in both images (they are less than 1 px "
            f"apart: frame {f.tolist()}, base {b.tolist()})"
        )
    heading = math.degrees(math.atan2(db[1], db[0]) - math.atan2(df[1], df[0])) % 360.0
    scale = math.hypot(*db) / math.hypot(*df)
    return SimilarityPrior(
        heading, scale, f.mean(axis=0), b.mean(axis=0), "two seeds", 2, 0.0, seed_error_px
    )


def _smooth_circular(hist: NDArray[np.float64], sigma: float = 1.0) -> NDArray[np.float64]:
    """Gaussian smoothing of a (heading, scale) histogram, circular along heading."""
    pad = 3
    wrapped = np.vstack([hist[-pad:], hist, hist[:pad]]).astype(np.float32)
    return cv2.GaussianBlur(wrapped, (5, 5), sigma, borderType=cv2.BORDER_CONSTANT)[pad:-pad]


def prior_from_seed(
    frame_xy: ArrayLike,
    base_xy: ArrayLike,
    attr_heading_deg: NDArray,
    attr_log_scale: NDArray,
    seed_frame: ArrayLike,
    seed_base: ArrayLike,
    config: HeadingConfig = HeadingConfig(),
    *,
    seed_error_px: float = 0.0,
) -> SimilarityPrior | None:
    """Heading and scale from candidate matches voting relative to one seed (see module doc).

    Args:
        frame_xy, base_xy: ``(N, 2)`` candidate matches (frame and base pixels).
        attr_heading_deg, attr_log_scale: ``(N,)`` the keypoints' own orientation and
            log-size differences (:func:`attribute_differences`).
        seed_frame, seed_base: the seed, ``(2,)`` each.
        config: bins and tolerances.
        seed_error_px: how far the seed may be off (these pixels), recorded in the prior.

    Returns:
        The prior at the histogram's peak (refined to the mean of its votes), or None when no
        match votes.
    """
    p, q = as_points(frame_xy, "frame_xy"), as_points(base_xy, "base_xy")
    p0, q0 = np.asarray(seed_frame, float).reshape(2), np.asarray(seed_base, float).reshape(2)
    a, b = p - p0, q - q0
    ra, rb = np.hypot(a[:, 0], a[:, 1]), np.hypot(b[:, 0], b[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        heading = np.degrees(np.arctan2(b[:, 1], b[:, 0]) - np.arctan2(a[:, 1], a[:, 0])) % 360.0
        log_scale = np.log(rb / ra)
    votes = (
        (ra >= config.min_seed_distance_px)
        & (rb > 0)
        & np.isfinite(log_scale)
        & (np.abs(log_scale) < config.max_log_scale)
        & (angle_gap_deg(heading, attr_heading_deg) <= config.attribute_tolerance_deg)
        & (np.abs(log_scale - attr_log_scale) <= config.attribute_tolerance_log_scale)
    )
    if not votes.any():
        return None
    n_h = int(round(360.0 / config.bin_deg))
    n_s = int(math.ceil(2 * config.max_log_scale / config.bin_log_scale))
    hi = np.floor(heading[votes] / 360.0 * n_h).astype(int) % n_h
    si = np.clip(
        np.floor((log_scale[votes] + config.max_log_scale) / config.bin_log_scale), 0, n_s - 1
    ).astype(int)
    hist = np.zeros((n_h, n_s))
    np.add.at(hist, (hi, si), 1.0)
    smooth = _smooth_circular(hist)
    i, j = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    peak_heading = (i + 0.5) * 360.0 / n_h
    peak_log = (j + 0.5) * config.bin_log_scale - config.max_log_scale
    # Refine: mean of the votes within 1.5 bins of the peak (circular mean for the heading).
    near = (
        votes
        & (angle_gap_deg(heading, peak_heading) <= 1.5 * config.bin_deg)
        & (np.abs(log_scale - peak_log) <= 1.5 * config.bin_log_scale)
    )
    if near.any():
        ang = np.radians(heading[near])
        peak_heading = math.degrees(math.atan2(np.sin(ang).mean(), np.cos(ang).mean())) % 360.0
        peak_log = float(np.median(log_scale[near]))
    # Ambiguity: the strongest peak at least 3 bins away in heading or scale.
    far = _far_from(int(i), int(j), n_h, n_s)
    rival = float(smooth[far].max()) if far.any() else 0.0
    return SimilarityPrior(
        float(peak_heading),
        float(math.exp(peak_log)),
        p0,
        q0,
        "seed",
        int(near.sum()),
        rival / max(float(smooth[i, j]), 1e-12),
        seed_error_px,
    )


# The patch search's grid: heading step (degrees) and natural-log scale step, refined once by
# a grid a quarter as fine around the best cell; the search margin (base-level px) around the
# seed for its click error.
_PATCH_STEP_DEG = 10.0
_PATCH_STEP_LOG = 0.1
_PATCH_MARGIN_PX = 8
_PATCH_MAX_LEVEL = 5


def prior_from_patch(
    frame_grey: NDArray,
    base_grey: NDArray,
    seed_frame: ArrayLike,
    seed_base: ArrayLike,
    config: HeadingConfig = HeadingConfig(),
    *,
    base_valid: NDArray | None = None,
    seed_error_px: float = 0.0,
) -> SimilarityPrior | None:
    """Heading and scale from the images around one seed, by correlation (no keypoints).

    The base patch around the seed is compared with the frame resampled around its seed at
    every heading (10° steps) and scale (``exp(+-max_log_scale)``, log steps of 0.1), allowing
    a few pixels for the click's error; the best normalised correlation wins and is refined on
    a grid a quarter as fine. It needs no SIFT match at all, so it holds where a map of another
    date leaves too few right matches to outvote the wrong ones; a small patch pins the heading
    better than the scale, so the result is a candidate to try, not a verdict.

    Args:
        frame_grey: ``(H, W)`` uint8 frame (corrected pixels, any scale).
        base_grey: ``(Hb, Wb)`` uint8 base map.
        seed_frame, seed_base: the seed, ``(2,)`` each, in those images' pixels.
        config: ``patch_radius_px``, ``patch_min_ncc`` and ``max_log_scale``.
        base_valid: optional ``(Hb, Wb)`` bool, where the base has content.
        seed_error_px: recorded in the prior.

    Returns:
        A :class:`SimilarityPrior` (``votes`` 0; ``ambiguity`` the best correlation at least
        3 cells away over the best), or None when the patch leaves the base or nothing
        correlates to ``patch_min_ncc``.
    """
    p0, q0 = np.asarray(seed_frame, float).reshape(2), np.asarray(seed_base, float).reshape(2)
    radius = config.patch_radius_px
    patch = _base_patch(base_grey, base_valid, q0, radius)
    if patch is None:
        return None
    level, window, centre = patch
    frames = _pyramid(frame_grey, _PATCH_MAX_LEVEL)

    def score(heading_deg: float, log_scale: float) -> float:
        return _patch_ncc(frames, p0, radius, level, window, centre, heading_deg, log_scale)

    headings = np.arange(0.0, 360.0, _PATCH_STEP_DEG)
    n_log = int(math.floor(config.max_log_scale / _PATCH_STEP_LOG))
    logs = np.arange(-n_log, n_log + 1) * _PATCH_STEP_LOG
    grid = np.array([[score(h, ls) for ls in logs] for h in headings])
    i, j = np.unravel_index(int(np.argmax(grid)), grid.shape)
    best = float(grid[i, j])
    if not best >= config.patch_min_ncc:
        return None
    far = _far_from(int(i), int(j), len(headings), len(logs))
    rival = float(grid[far].max()) if far.any() else 0.0
    fine = [
        (score(headings[i] + dh, logs[j] + dl), dh, dl)
        for dh in np.arange(-2, 3) * _PATCH_STEP_DEG / 4
        for dl in np.arange(-2, 3) * _PATCH_STEP_LOG / 4
    ]
    top, dh, dl = max(fine, key=lambda f: f[0])
    return SimilarityPrior(
        float((headings[i] + dh) % 360.0),
        float(math.exp(logs[j] + dl)),
        p0,
        q0,
        "seed",
        0,
        max(rival, 0.0) / max(top, 1e-12),
        seed_error_px,
    )


def _base_patch(
    base_grey: NDArray, base_valid: NDArray | None, q0: NDArray, radius: int
) -> tuple[int, NDArray[np.float32], NDArray[np.bool_]] | None:
    """The base around the seed ``q0`` (base px) at the pyramid level where the patch of
    ``radius`` px is about a sixth of the base's shorter side (at most level 4).

    Returns:
        ``(level, window, centre)``: ``window`` the ``(2 r + 1, 2 r + 1)`` float32 search area
        (``r = radius + _PATCH_MARGIN_PX``, for the seed's click error) and ``centre`` the
        ``(2 radius + 1,) * 2`` bool mask of the base's content around the seed; None when the
        search area leaves the base or less than half of the patch has content.
    """
    margin = _PATCH_MARGIN_PX
    hb, wb = base_grey.shape[:2]
    level = int(np.clip(round(math.log2(max(min(hb, wb) / 6.0 / radius, 1.0))), 0, 4))
    base = _pyramid(base_grey, level)[-1]
    valid = None
    if base_valid is not None:
        valid = _pyramid(base_valid.astype(np.float32), level)[-1] > 0.99
    qc = (q0 + 0.5) / 2**level - 0.5
    x0, y0 = int(round(qc[0])), int(round(qc[1]))
    r = radius + margin
    if x0 - r < 0 or y0 - r < 0 or x0 + r >= base.shape[1] or y0 + r >= base.shape[0]:
        return None
    window = base[y0 - r : y0 + r + 1, x0 - r : x0 + r + 1]
    centre = np.ones((2 * radius + 1,) * 2, bool)
    if valid is not None:
        centre = valid[y0 - radius : y0 + radius + 1, x0 - radius : x0 + radius + 1]
        if centre.mean() < 0.5:
            return None
    return level, window, centre


def _patch_ncc(
    frames: list[NDArray[np.float32]],
    p0: NDArray,
    radius: int,
    level: int,
    window: NDArray[np.float32],
    centre: NDArray[np.bool_],
    heading_deg: float,
    log_scale: float,
) -> float:
    """Best normalised correlation over ``window`` (:func:`_base_patch`) of the frame patch
    around the seed ``p0`` (frame px) resampled at ``heading_deg`` and ``exp(log_scale)`` base
    px per frame px from the nearest coarser level of ``frames`` (:func:`_pyramid`); -1 when
    less than half the patch has content or it is flat."""
    step = 2.0**level / math.exp(log_scale)  # frame px per base-level px
    lf = int(np.clip(math.floor(math.log2(max(step, 1.0))), 0, _PATCH_MAX_LEVEL))
    k = step / 2.0**lf
    t = math.radians(heading_deg)
    a = k * np.array([[math.cos(t), math.sin(t)], [-math.sin(t), math.cos(t)]])
    off = (p0 + 0.5) / 2.0**lf - 0.5 - a @ np.array([radius, radius], float)
    warp = np.hstack([a, off[:, None]])
    img = frames[lf]
    size = (2 * radius + 1, 2 * radius + 1)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    tpl = cv2.warpAffine(img, warp, size, flags=flags)
    inside = cv2.warpAffine(np.ones_like(img), warp, size, flags=flags) > 0.99
    mask = centre & inside
    if mask.mean() < 0.5 or float(tpl[mask].std()) < 1.0:
        return -1.0
    if mask.all():
        out = cv2.matchTemplate(window, tpl, cv2.TM_CCOEFF_NORMED)
    else:
        out = cv2.matchTemplate(window, tpl, cv2.TM_CCOEFF_NORMED, mask=mask.astype(np.uint8))
    out = np.nan_to_num(out, nan=-1.0, posinf=-1.0, neginf=-1.0)
    return float(out.max())


def _pyramid(image: NDArray, levels: int) -> list[NDArray[np.float32]]:
    """``[image, pyrDown(image), ...]``, ``levels + 1`` float32 images (each at least 1 px)."""
    out = [np.asarray(image, np.float32)]
    for _ in range(levels):
        if min(out[-1].shape[:2]) < 2:
            out.append(out[-1])
        else:
            out.append(cv2.pyrDown(out[-1]))
    return out


def _far_from(i: int, j: int, n_h: int, n_s: int) -> NDArray[np.bool_]:
    """Cells at least 3 cells from ``(i, j)`` in heading (circular) or scale."""
    di = np.minimum(np.abs(np.arange(n_h) - i), n_h - np.abs(np.arange(n_h) - i))[:, None]
    dj = np.abs(np.arange(n_s) - j)[None, :]
    return (di >= 3) | (dj >= 3)


def priors_without_seed(
    frame_xy: ArrayLike,
    base_xy: ArrayLike,
    attr_heading_deg: NDArray,
    attr_log_scale: NDArray,
    frame_extent: float,
    config: HeadingConfig = HeadingConfig(),
) -> list[SimilarityPrior]:
    """Candidate registrations from the 4-D Hough transform of the matches' similarities.

    Each match's keypoint orientation and size difference give a rotation and scale, and with
    its position a translation; each votes for the two nearest bins in each of the four
    dimensions (Lowe 2004, 7.3). The ``max_candidates`` fullest bins with at least
    ``min_votes`` distinct matches become priors: the least-squares similarity of the bin's
    matches, anchored at their frame centroid, strongest first; ``ambiguity`` is the next
    candidate's votes over this one's.

    Args:
        frame_xy, base_xy: ``(N, 2)`` candidate matches (frame and base pixels).
        attr_heading_deg, attr_log_scale: ``(N,)`` keypoint orientation and log-size
            differences.
        frame_extent: the frame's larger side (these pixels): sets the translation bins.
        config: bins and limits.
    """
    p, q = as_points(frame_xy, "frame_xy"), as_points(base_xy, "base_xy")
    n = len(p)
    if n < config.min_votes:
        return []
    member, inverse, counts = _hough_bins(
        p, q, attr_heading_deg, attr_log_scale, frame_extent, config
    )
    # Strongest first; ties broken by the bin key (np.unique's lexicographic order) for
    # reproducibility.
    order = np.argsort(-counts, kind="stable")
    priors: list[SimilarityPrior] = []
    used: list[frozenset] = []
    for bi in order:
        if counts[bi] < config.min_votes or len(priors) >= config.max_candidates:
            break
        idx = np.unique(member[inverse == bi])
        key = frozenset(idx.tolist())
        # Neighbouring bins share most of their votes: skip near-duplicates.
        if any(len(key & u) > 0.5 * len(key) for u in used):
            continue
        used.append(key)
        prior = _prior_from_bin(p, q, idx, config)
        if prior is not None:
            priors.append(prior)
    for k in range(len(priors)):
        nxt = priors[k + 1].votes if k + 1 < len(priors) else 0
        priors[k] = _with_ambiguity(priors[k], nxt / max(priors[k].votes, 1))
    return priors


def _hough_bins(
    p: NDArray[np.float64],
    q: NDArray[np.float64],
    attr_heading_deg: NDArray,
    attr_log_scale: NDArray,
    frame_extent: float,
    config: HeadingConfig,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """The 4-D Hough votes of the ``(N, 2)`` matches ``p`` -> ``q``: each match's similarity
    (rotation and scale from its keypoints, translation from its position) votes for the two
    nearest bins in each dimension, 16 votes in all.

    Returns:
        ``(member, inverse, counts)``: ``(16 N,)`` the match and the bin (index into the
        distinct bins, in np.unique's lexicographic order of their keys) of every vote, and
        each bin's number of votes.
    """
    n = len(p)
    th = np.radians(attr_heading_deg)
    s = np.exp(attr_log_scale)
    rot_p = np.c_[np.cos(th) * p[:, 0] - np.sin(th) * p[:, 1],
                  np.sin(th) * p[:, 0] + np.cos(th) * p[:, 1]]  # fmt: skip
    t = q - s[:, None] * rot_p
    # Continuous bin coordinates; a vote goes to the two nearest bins in each dimension.
    coords = np.c_[
        np.asarray(attr_heading_deg) / config.hough_bin_deg,
        np.asarray(attr_log_scale) / math.log(2.0) / config.hough_bin_octaves,
        t / (config.hough_bin_extent * frame_extent * s[:, None]),
    ]
    n_heading = int(round(360.0 / config.hough_bin_deg))
    base_bin = np.floor(coords - 0.5).astype(np.int64)
    corners = np.array(np.meshgrid(*[[0, 1]] * 4, indexing="ij")).reshape(4, -1).T  # (16, 4)
    bins = base_bin[:, None, :] + corners[None, :, :]  # (N, 16, 4)
    bins[..., 0] %= n_heading
    flat = bins.reshape(-1, 4)
    member = np.repeat(np.arange(n), 16)
    _, inverse, counts = np.unique(flat, axis=0, return_inverse=True, return_counts=True)
    return member, inverse.reshape(-1), counts


def _prior_from_bin(
    p: NDArray[np.float64], q: NDArray[np.float64], idx: NDArray[np.int64], config: HeadingConfig
) -> SimilarityPrior | None:
    """The ``"no seed"`` prior of a Hough bin's matches ``idx``: their trimmed least-squares
    similarity, anchored at their frame centroid, with their median residual (base px) as the
    anchor's error; None when it cannot be fitted or its scale is beyond ``max_log_scale``."""
    sim, idx = _trimmed_similarity(p, q, idx)
    if sim is None or not abs(math.log(max(sim.scale, 1e-300))) < config.max_log_scale:
        return None
    anchor = p[idx].mean(axis=0)
    spread = float(np.median(np.hypot(*(sim.apply(p[idx]) - q[idx]).T)))
    return SimilarityPrior(
        sim.rotation_deg % 360.0,
        sim.scale,
        anchor,
        sim.apply(anchor[None])[0],
        "no seed",
        int(len(idx)),
        0.0,
        spread,
    )


def _trimmed_similarity(p, q, idx, rounds: int = 3):
    """Least-squares similarity of the pairs ``idx``, refitted without those beyond three
    times the median residual (a bin also catches a few wrong matches)."""
    sim = None
    for _ in range(rounds):
        fit = Similarity.estimate(p[idx], q[idx])
        if not fit:
            return sim, idx
        sim = fit
        r = np.hypot(*(sim.apply(p[idx]) - q[idx]).T)
        keep = r <= 3.0 * max(float(np.median(r)), 1e-9)
        if keep.all() or keep.sum() < 2:
            break
        idx = idx[keep]
    return sim, idx


def _with_ambiguity(prior: SimilarityPrior, ambiguity: float) -> SimilarityPrior:
    return SimilarityPrior(
        prior.heading_deg,
        prior.scale,
        prior.anchor_frame,
        prior.anchor_base,
        prior.source,
        prior.votes,
        float(ambiguity),
        prior.anchor_error_px,
    )


def gate_radius_px(
    prior: SimilarityPrior, frame_xy: ArrayLike, config: HeadingConfig = HeadingConfig()
) -> NDArray[np.float64]:
    """``(N,)`` base-pixel radius around ``prior.apply(frame_xy)`` inside which a match passes
    the gate: the anchor's own error, the slack, and the rotation and scale tolerances times the
    distance from the anchor."""
    p = as_points(frame_xy, "frame_xy")
    r = np.hypot(*(p - prior.anchor_frame).T)
    rel = math.radians(config.max_rotation_deg) + config.max_scale_error
    return config.slack_px + prior.anchor_error_px + rel * prior.scale * r


def gate_by_prior(
    frame_xy: ArrayLike,
    base_xy: ArrayLike,
    prior: SimilarityPrior,
    config: HeadingConfig = HeadingConfig(),
) -> NDArray[np.bool_]:
    """``(N,)`` matches whose base point lies within :func:`gate_radius_px` of where the prior
    puts their frame point: the paper's location gate around the seed, with the sector's
    direction and radii taken from the estimate."""
    p, q = as_points(frame_xy, "frame_xy"), as_points(base_xy, "base_xy")
    dist = np.hypot(*(prior.apply(p) - q).T)
    return np.isfinite(dist) & (dist <= gate_radius_px(prior, p, config))


def guided_matches(
    frame_kp: Keypoints,
    base_kp: Keypoints,
    predicted_xy: NDArray[np.float64],
    radius_px: NDArray[np.float64] | float,
    heading_deg: float,
    scale: float,
    config: HeadingConfig = HeadingConfig(),
    *,
    ratio: float | None = None,
) -> Matches:
    """Match each frame keypoint among the base keypoints near its predicted position.

    Candidates are the ``guided_neighbours`` base keypoints nearest to ``predicted_xy[i]``
    within ``radius_px`` whose orientation and size differences agree with ``heading_deg`` and
    ``scale`` (``attribute_tolerance_*``); the nearest descriptor wins when it passes the ratio
    test against the second nearest candidate (``ratio``, default ``guided_ratio``; a lone
    candidate passes). Of equal descriptor distances, the candidate nearest the prediction wins.

    Args:
        frame_kp, base_kp: keypoints (frame and base pixels).
        predicted_xy: ``(N_frame, 2)`` predicted base position of every frame keypoint (NaN =
            no prediction).
        radius_px: search radius in base pixels, scalar or ``(N_frame,)``.
        heading_deg, scale: expected keypoint orientation and size change.
        config: tolerances.
        ratio: ratio-test threshold among the candidates.

    Returns:
        :class:`~registration.matching.sift.Matches` (``idx_a`` frame, ``idx_b`` base).
    """
    ratio = config.guided_ratio if ratio is None else ratio
    n_f = len(frame_kp)
    pred = np.asarray(predicted_xy, np.float64).reshape(-1, 2)
    if pred.shape != (n_f, 2):
        raise ValueError(f"predicted_xy must be ({n_f}, 2), got {pred.shape}")
    if n_f == 0 or len(base_kp) == 0:
        return Matches.empty()
    safe, valid = _guided_candidates(frame_kp, base_kp, pred, radius_px, heading_deg, scale, config)
    rows = np.flatnonzero(valid.any(axis=1))
    if len(rows) == 0:
        return Matches.empty()
    return _ratio_test_among(frame_kp, base_kp, rows, safe, valid, ratio)


def _guided_candidates(
    frame_kp: Keypoints,
    base_kp: Keypoints,
    pred: NDArray[np.float64],
    radius_px: NDArray[np.float64] | float,
    heading_deg: float,
    scale: float,
    config: HeadingConfig,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Each frame keypoint's candidates: the ``k = min(guided_neighbours, N_base)`` base
    keypoints nearest its prediction ``pred`` (``(N_frame, 2)`` base px, NaN = none), nearest
    first.

    Returns:
        ``(safe, valid)``, both ``(N_frame, k)``: the candidates' base keypoint indices (0 where
        there is none) and whether each is one: within ``radius_px`` of the prediction, with an
        orientation and size change within ``attribute_tolerance_*`` of ``heading_deg`` and
        ``scale``.
    """
    n_f = len(frame_kp)
    radius = np.broadcast_to(np.asarray(radius_px, np.float64), (n_f,))
    ok = np.isfinite(pred).all(axis=1) & np.isfinite(radius)
    k = min(config.guided_neighbours, len(base_kp))
    tree = cKDTree(base_kp.xy)
    dist = np.full((n_f, k), np.inf)
    idx = np.full((n_f, k), len(base_kp), np.int64)
    if ok.any():
        d, i = tree.query(pred[ok], k=k, distance_upper_bound=float(radius[ok].max()))
        dist[ok], idx[ok] = d.reshape(-1, k), i.reshape(-1, k)
    valid = (dist <= radius[:, None]) & (idx < len(base_kp))
    safe = np.where(valid, idx, 0)
    log_s = math.log(scale)
    size_gap = np.abs(
        np.log(np.maximum(base_kp.size[safe], 1e-12) / np.maximum(frame_kp.size[:, None], 1e-12))
        - log_s
    )
    angle_gap = angle_gap_deg(base_kp.angle[safe] - frame_kp.angle[:, None], heading_deg)
    valid &= (size_gap <= config.attribute_tolerance_log_scale) & (
        angle_gap <= config.attribute_tolerance_deg
    )
    return safe, valid


def _ratio_test_among(
    frame_kp: Keypoints,
    base_kp: Keypoints,
    rows: NDArray[np.int64],
    safe: NDArray[np.int64],
    valid: NDArray[np.bool_],
    ratio: float,
) -> Matches:
    """The nearest descriptor among each frame keypoint ``rows``' valid candidates
    (:func:`_guided_candidates`), kept when it passes the ratio test against the second
    nearest (a lone candidate passes); of equal distances the candidate nearest the
    prediction wins."""
    k = safe.shape[1]
    # Descriptor distances of the candidates, in chunks to bound memory.
    desc_d = np.full((len(rows), k), np.inf, np.float32)
    fd, bd = frame_kp.descriptors, base_kp.descriptors
    for lo in range(0, len(rows), 2048):
        r = rows[lo : lo + 2048]
        diff = bd[safe[r]] - fd[r][:, None, :]
        desc_d[lo : lo + 2048] = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
    desc_d[~valid[rows]] = np.inf
    # argmin takes the first of equal distances: the candidate nearest the prediction.
    best = np.argmin(desc_d, axis=1)
    d1 = desc_d[np.arange(len(rows)), best]
    masked = desc_d.copy()
    masked[np.arange(len(rows)), best] = np.inf
    d2 = masked.min(axis=1)
    keep = np.isfinite(d1) & ((~np.isfinite(d2)) | (d1 < ratio * d2))
    rows, best, d1, d2 = rows[keep], best[keep], d1[keep], d2[keep]
    return Matches(
        rows.astype(np.int64),
        safe[rows, best].astype(np.int64),
        d1.astype(np.float64),
        np.where(np.isfinite(d2), d2, d1).astype(np.float64),
    )
