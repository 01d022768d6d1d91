"""The coarse step's settings, result and inputs (paper 4.3.1): :class:`CoarseConfig`,
:class:`CoarseResult`, the frame and the base map at coarse scale with their SIFT keypoints, and
the seed clicks.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.coords import image_size, rescale
from registration.geometry import (
    Affine,
    Projective,
    RansacConfig,
    Similarity,
)
from registration.global_registration.gradient_correlation import (
    Agreement,
    CorrelationConfig,
)
from registration.global_registration.heading import HeadingConfig
from registration.lens import Camera, HarrisModel, TwoTermHarrisModel, as_camera
from registration.matching import Keypoints, SiftConfig
from registration.matching import grey as matching_grey
from registration.matching import sift as matching_sift

Seed = tuple[float, float, float, float]

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
            (:mod:`registration.global_registration.heading`).
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
            from the seed's heading and scale): :mod:`registration.global_registration.gradient_correlation`. None by
            default (the paper).
        min_inliers_unseeded: fewest inliers a registration found without a seed needs (12).
        decisive_ratio: without a seed, the best candidate must have at least this many times
            the inliers of any candidate that disagrees with it (1.5), else the step reports
            that it cannot decide.
        seed_check_px: a result that puts the seed's frame point farther than this (full-scale
            base pixels, plus the click errors) from the clicked base point is refused (40).
        max_chance_p: with ``correlation`` rounds and fewer than two seeds, a result is refused
            when chance alone would make at least as many templates of the last round agree
            with it with a probability above this (:func:`registration.global_registration.gradient_correlation.agreement`):
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


@dataclass(frozen=True)
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
    ``path`` is the step that produced the model (``"fast"``: :mod:`registration.global_registration.predicted_coarse`,
    ``"sift"``: the SIFT step) and ``fast_reason`` why the fast path was not used (``"off"``
    when it is disabled or there is no previous frame; empty when it was used). ``remedy`` is
    ``"click"`` where a seed click would help (the front ends say how to give one; see
    :mod:`registration.errors`). Frozen: the steps that refine a result return a new one.
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
    remedy: str = ""

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
    the frame's :class:`registration.lens.camera.Camera` or its Harris γ."""
    return matching_grey.to_grey(as_camera(camera, frame_raw).undistort(frame_raw))


def frame_view(frame_raw: NDArray, camera: Camera | float, match_in: str) -> FrameView:
    """See :class:`FrameView`; ``camera``: the frame's :class:`registration.lens.camera.Camera` (or
    its Harris γ)."""
    camera = as_camera(camera, frame_raw)
    if match_in == "corrected":
        return FrameView(corrected_grey(frame_raw, camera), None)
    if match_in == "raw":
        return FrameView(matching_grey.to_grey(frame_raw), camera.lens)
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
    small = matching_grey.downscale(grey, s)
    small_mask = None
    if mask is not None:
        small_mask = matching_grey.downscale_mask(mask, s).astype(np.uint8)
        small_mask = cv2.erode(small_mask, np.ones((7, 7), np.uint8))
    kp = matching_sift.detect_sift(small, config.sift, mask=small_mask)
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
        self.grey = matching_grey.to_grey(base)
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
