"""Control points (paper sections 4.3.1, 4.3.2 and 4.4): grey conversion and subsampling, SIFT
keypoints with ratio-test matching, location gating around the single seed correspondence, the
template grid matched by normalised cross-correlation, and gridded SIFT matched window by window.

Every function takes and returns points as ``(N, 2)`` float64 ``(x, y)`` arrays with pixel centres
at integer coordinates (``conventions.md``). Transforms are plain callables ``(N, 2) -> (N, 2)``
named target-first (``ref_from_frame``); they may return NaN where they are undefined.

Paper values are the defaults of the frozen config dataclasses below; every field says its unit
and where its value comes from ("paper 4.3.2", "OpenCV default", or "beyond the paper" with the
reason).

References:
    Loveland & Rosten, "Acquisition and registration of aerial video imagery of urban traffic".
    D. G. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 60(2), 2004.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import ArrayLike, NDArray

from registration import coords, warp

logger = logging.getLogger(__name__)

PointFunction = Callable[[NDArray[np.float64]], NDArray[np.float64]]

__all__ = [
    "ControlPoints",
    "GriddedReference",
    "GriddedSiftConfig",
    "Keypoints",
    "Matches",
    "Reference",
    "SiftConfig",
    "TemplateConfig",
    "detect_sift",
    "downscale",
    "gridded_sift_control_points",
    "match_ratio",
    "subpixel_peak",
    "template_control_points",
    "template_grid",
    "to_grey",
    "window_centres",
]


# --------------------------------------------------------------------------------------------
# Grey conversion and subsampling (paper 4.3.1 steps 1-2)
# --------------------------------------------------------------------------------------------


def to_grey(image: ArrayLike) -> NDArray[np.uint8]:
    """Convert an image to 8-bit grey (paper 4.3.1 step 1).

    Args:
        image: ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` BGR or ``(H, W, 4)`` BGRA array (OpenCV
            channel order). dtype uint8 (0..255), uint16 (0..65535, divided by 257) or float.
            Float images are taken to span 0..1 when their maximum is at most 1, otherwise
            0..255; values outside the range are clipped and NaN becomes 0.

    Returns:
        ``(H, W)`` uint8 array (the input itself when it already is one, not a copy).

    Raises:
        ValueError: for an empty image, an unsupported shape or dtype.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)):
        raise ValueError(
            f"image must have shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {img.shape}"
        )
    if img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"image is empty: shape {img.shape}")
    if img.dtype == np.uint8:
        out = img
    elif img.dtype == np.uint16:
        out = np.round(img.astype(np.float32) * (255.0 / 65535.0)).astype(np.uint8)
    elif np.issubdtype(img.dtype, np.floating):
        f = np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        scale = 255.0 if (f.size and float(f.max()) <= 1.0) else 1.0
        out = np.clip(np.round(f * scale), 0, 255).astype(np.uint8)
    else:
        raise ValueError(f"image dtype must be uint8, uint16 or float, got {img.dtype}")
    if out.ndim == 3:
        code = cv2.COLOR_BGR2GRAY if out.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        out = cv2.cvtColor(np.ascontiguousarray(out), code)
    return np.ascontiguousarray(out)


def downscale(image: NDArray, scale: float = 0.25) -> NDArray:
    """Resample an image by ``scale`` with ``cv2.INTER_AREA`` (paper 4.3.1 step 2: 1/4 scale).

    The output is ``max(1, round(W * scale))`` by ``max(1, round(H * scale))``. Points map between
    the two with :func:`registration.coords.rescale` (``x_s = (x + 0.5) * scale - 0.5``), exact
    when ``W * scale`` and ``H * scale`` are integers.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` array.
        scale: output/input size ratio, > 0 (default 0.25, paper 4.3.1).

    Returns:
        The resampled image, same dtype and channel count.
    """
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a finite number > 0, got {scale!r}")
    img = np.asarray(image)
    if img.ndim not in (2, 3) or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(
            f"image must be a non-empty (H, W) or (H, W, C) array, got shape {img.shape}"
        )
    w, h = coords.image_size(img)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


# --------------------------------------------------------------------------------------------
# SIFT keypoints and ratio-test matching (paper 4.3.1 steps 4-5)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SiftConfig:
    """SIFT detector settings. The paper gives none, so these are OpenCV's defaults, which are
    Lowe's (2004) values expressed in OpenCV's units.

    Attributes:
        nfeatures: keep at most this many strongest keypoints; 0 = unlimited (paper 4.3.1 counts
            17,974 base and 8,807 frame keypoints at 1/4 scale, i.e. no cap). OpenCV default.
        n_octave_layers: scale levels per octave (3, Lowe 2004; OpenCV default).
        contrast_threshold: DoG contrast threshold on 0..1 intensities, divided by
            ``n_octave_layers`` inside OpenCV (0.04, OpenCV default; 0.09 = Lowe's 0.03).
        edge_threshold: principal-curvature ratio above which edge responses are dropped
            (10, Lowe 2004; OpenCV default).
        sigma: Gaussian blur of octave 0 in pixels (1.6, Lowe 2004; OpenCV default).
        precise_upscale: OpenCV's ``enable_precise_upscale`` (True; beyond the OpenCV default
            False). With False, keypoints found in OpenCV's 2x upsampled first octave are offset
            by about -0.25 px (measured here: matches between an image and its half-size copy
            were off by (-0.13, -0.13) half-size px, 0.00 with True), which does not cancel
            between images of different scale (base map vs frame). Costs nothing measurable.
    """

    nfeatures: int = 0
    n_octave_layers: int = 3
    contrast_threshold: float = 0.04
    edge_threshold: float = 10.0
    sigma: float = 1.6
    precise_upscale: bool = True

    def __post_init__(self) -> None:
        if self.nfeatures < 0:
            raise ValueError(
                f"SiftConfig.nfeatures must be >= 0 (0 = unlimited), got {self.nfeatures}"
            )
        if self.n_octave_layers < 1:
            raise ValueError(f"SiftConfig.n_octave_layers must be >= 1, got {self.n_octave_layers}")
        if self.contrast_threshold < 0 or self.edge_threshold <= 0 or self.sigma <= 0:
            raise ValueError(
                "SiftConfig thresholds must be positive, got contrast_threshold="
                f"{self.contrast_threshold}, edge_threshold={self.edge_threshold}, sigma={self.sigma}"
            )


@dataclass(frozen=True)
class Keypoints:
    """SIFT keypoints of one image.

    Attributes:
        xy: ``(N, 2)`` float64 positions in pixels of the image they were detected in.
        descriptors: ``(N, 128)`` float32 SIFT descriptors.
        size: ``(N,)`` float64 keypoint diameter in pixels (OpenCV ``KeyPoint.size``).
        angle: ``(N,)`` float64 orientation in degrees, OpenCV convention (zeros if not given).
        response: ``(N,)`` float64 detector response (DoG contrast; zeros if not given).
    """

    xy: NDArray[np.float64]
    descriptors: NDArray[np.float32]
    size: NDArray[np.float64]
    angle: NDArray[np.float64] | None = None
    response: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        n = len(self.xy)
        for name in ("angle", "response"):  # optional: zeros when not known
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.zeros(n))
        if self.xy.shape != (n, 2) or self.descriptors.ndim != 2 or len(self.descriptors) != n:
            raise ValueError(
                f"Keypoints: xy must be (N, 2) and descriptors (N, D), got {self.xy.shape} and "
                f"{self.descriptors.shape}"
            )
        for name in ("size", "angle", "response"):
            if getattr(self, name).shape != (n,):
                raise ValueError(
                    f"Keypoints.{name} must have shape ({n},), got {getattr(self, name).shape}"
                )

    def __len__(self) -> int:
        return len(self.xy)

    @classmethod
    def empty(cls, descriptor_size: int = 128) -> Keypoints:
        """No keypoints."""
        z = np.zeros(0)
        return cls(
            np.zeros((0, 2)), np.zeros((0, descriptor_size), np.float32), z, z.copy(), z.copy()
        )

    def subset(self, index: ArrayLike) -> Keypoints:
        """The keypoints selected by an integer index array or a boolean mask."""
        i = np.asarray(index)
        return Keypoints(
            self.xy[i], self.descriptors[i], self.size[i], self.angle[i], self.response[i]
        )

    def rescaled(self, scale: float) -> Keypoints:
        """The same keypoints in the coordinates of the image rescaled by ``scale``."""
        xy = coords.rescale(self.xy, scale) if len(self) else self.xy.copy()
        return Keypoints(xy, self.descriptors, self.size * scale, self.angle, self.response)


def _sift(config: SiftConfig) -> cv2.SIFT:
    # cv2 5.0 has both cv2.SIFT.create and the older cv2.SIFT_create; prefer the class method.
    create = cv2.SIFT.create if hasattr(cv2, "SIFT") else cv2.SIFT_create
    return create(
        config.nfeatures,
        config.n_octave_layers,
        config.contrast_threshold,
        config.edge_threshold,
        config.sigma,
        enable_precise_upscale=config.precise_upscale,
    )


def detect_sift(
    grey: NDArray, config: SiftConfig = SiftConfig(), mask: NDArray | None = None
) -> Keypoints:
    """Detect and describe SIFT keypoints (paper 4.3.1 step 4, 4.4, 5).

    Args:
        grey: image; anything :func:`to_grey` accepts.
        config: detector settings.
        mask: optional ``(H, W)`` array, keypoints are kept only where it is non-zero.

    Returns:
        :class:`Keypoints` (empty on a featureless image).
    """
    g = to_grey(grey)
    m = None
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != g.shape:
            raise ValueError(f"mask shape {mask.shape} must equal the image shape {g.shape}")
        m = (mask != 0).astype(np.uint8)
        if not m.any():
            return Keypoints.empty()
    kps, desc = _sift(config).detectAndCompute(g, m)
    if desc is None or len(kps) == 0:
        return Keypoints.empty()
    xy = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
    return Keypoints(
        xy=xy,
        descriptors=np.ascontiguousarray(desc, np.float32),
        size=np.array([k.size for k in kps], np.float64),
        angle=np.array([k.angle for k in kps], np.float64),
        response=np.array([k.response for k in kps], np.float64),
    )


@dataclass(frozen=True)
class Matches:
    """Correspondences between two keypoint sets.

    Attributes:
        idx_a: ``(M,)`` int64 indices into the first set.
        idx_b: ``(M,)`` int64 indices into the second set.
        distance: ``(M,)`` float64 descriptor distance of the best match (L2).
        second_distance: ``(M,)`` float64 distance of the second-best candidate (the ratio test's
            denominator); ``distance / second_distance`` is Lowe's ratio.
    """

    idx_a: NDArray[np.int64]
    idx_b: NDArray[np.int64]
    distance: NDArray[np.float64]
    second_distance: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.idx_a)

    @classmethod
    def empty(cls) -> Matches:
        i = np.zeros(0, np.int64)
        return cls(i, i.copy(), np.zeros(0), np.zeros(0))

    @property
    def ratio(self) -> NDArray[np.float64]:
        """``(M,)`` Lowe ratio ``distance / second_distance`` (NaN when unknown)."""
        if self.second_distance is None:
            return np.full(len(self), np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.second_distance > 0, self.distance / self.second_distance, 1.0)

    def subset(self, index: ArrayLike) -> Matches:
        i = np.asarray(index)
        sd = None if self.second_distance is None else self.second_distance[i]
        return Matches(self.idx_a[i], self.idx_b[i], self.distance[i], sd)


# Below this many descriptor pairs (|a| * |b|) exact brute force beats building FLANN trees
# (measured here: ~5 ns per pair for brute force, FLANN ~0.5 s for 22 k x 18 k).
_BF_MAX_PAIRS = 4_000_000


def _descriptors(kp: Keypoints | NDArray) -> NDArray[np.float32]:
    d = kp.descriptors if isinstance(kp, Keypoints) else np.asarray(kp)
    if d.ndim != 2:
        raise ValueError(f"descriptors must be a (N, D) array, got shape {d.shape}")
    return np.ascontiguousarray(d, np.float32)


def match_ratio(
    kp_a: Keypoints | NDArray,
    kp_b: Keypoints | NDArray,
    ratio: float = 0.8,
    method: Literal["auto", "flann", "bf"] = "auto",
) -> Matches:
    """Match each keypoint of ``kp_a`` to its nearest neighbour in ``kp_b`` and keep it when
    Lowe's ratio test passes: ``d1 < ratio * d2`` (paper 4.3.1 step 5; the paper relies on
    "the best match significantly better than the second best").

    Args:
        kp_a, kp_b: :class:`Keypoints` or ``(N, D)`` descriptor arrays.
        ratio: Lowe's ratio threshold (0.8, Lowe 2004), in (0, 1].
        method: ``"flann"`` (kd-tree, 4 trees, 64 checks: approximate, fast for thousands of
            keypoints), ``"bf"`` (exact brute force) or ``"auto"`` (brute force below 4 M
            descriptor pairs, FLANN above).

    Returns:
        :class:`Matches`; empty when either side has fewer than 2 keypoints for a ratio test
        (a single candidate cannot show that it is distinctive).
    """
    if not 0 < ratio <= 1:
        raise ValueError(f"ratio must be in (0, 1], got {ratio}")
    if method not in ("auto", "flann", "bf"):
        raise ValueError(f"method must be 'auto', 'flann' or 'bf', got {method!r}")
    da, db = _descriptors(kp_a), _descriptors(kp_b)
    if len(da) == 0 or len(db) < 2:
        return Matches.empty()
    if da.shape[1] != db.shape[1]:
        raise ValueError(f"descriptor sizes differ: {da.shape[1]} and {db.shape[1]}")
    if method == "auto":
        method = "bf" if len(da) * len(db) <= _BF_MAX_PAIRS else "flann"
    if method == "bf":
        matcher = cv2.BFMatcher(cv2.NORM_L2)
    else:
        matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    knn = matcher.knnMatch(da, db, k=2)
    rows = [
        (m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance) for m in knn if len(m) == 2
    ]
    if not rows:
        return Matches.empty()
    arr = np.array(rows, np.float64)
    keep = arr[:, 2] < ratio * arr[:, 3]
    arr = arr[keep]
    return Matches(arr[:, 0].astype(np.int64), arr[:, 1].astype(np.int64), arr[:, 2], arr[:, 3])


# --------------------------------------------------------------------------------------------
# Control points
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ControlPoints:
    """Corresponding points between a frame and a reference image.

    Attributes:
        src: ``(N, 2)`` float64 frame pixels.
        dst: ``(N, 2)`` float64 reference pixels.
        score: ``(N,)`` float64 match quality, higher is better (NCC peak for templates,
            ``1 - Lowe ratio`` for SIFT).
        source: ``(N,)`` int64 index of the reference each point came from (0 when there is
            only one; filled with zeros when not given).
    """

    src: NDArray[np.float64]
    dst: NDArray[np.float64]
    score: NDArray[np.float64]
    source: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        src = coords.as_points(self.src, "ControlPoints.src") if len(self.src) else np.zeros((0, 2))
        dst = coords.as_points(self.dst, "ControlPoints.dst") if len(self.dst) else np.zeros((0, 2))
        score = np.asarray(self.score, np.float64).reshape(-1)
        n = len(src)
        source = (
            np.zeros(n, np.int64)
            if self.source is None
            else np.asarray(self.source, np.int64).reshape(-1)
        )
        if len(dst) != n or len(score) != n or len(source) != n:
            raise ValueError(
                f"ControlPoints fields must have equal length, got src {len(src)}, dst {len(dst)}, "
                f"score {len(score)}, source {len(source)}"
            )
        object.__setattr__(self, "src", src)
        object.__setattr__(self, "dst", dst)
        object.__setattr__(self, "score", score)
        object.__setattr__(self, "source", source)

    def __len__(self) -> int:
        return len(self.src)

    @classmethod
    def empty(cls) -> ControlPoints:
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64))

    def subset(self, index: ArrayLike) -> ControlPoints:
        """The points selected by an integer index array or a boolean mask."""
        i = np.asarray(index)
        return ControlPoints(self.src[i], self.dst[i], self.score[i], self.source[i])

    @classmethod
    def concatenate(cls, parts: Sequence[ControlPoints]) -> ControlPoints:
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        return cls(
            np.concatenate([p.src for p in parts]),
            np.concatenate([p.dst for p in parts]),
            np.concatenate([p.score for p in parts]),
            np.concatenate([p.source for p in parts]),
        )


def _call_points(fn: PointFunction, xy: NDArray[np.float64], name: str) -> NDArray[np.float64]:
    if len(xy) == 0:
        return np.zeros((0, 2))
    out = np.asarray(fn(xy), np.float64)
    if out.shape != xy.shape:
        raise ValueError(f"{name} must map (N, 2) to (N, 2), got {xy.shape} -> {out.shape}")
    return out


# --------------------------------------------------------------------------------------------
# Template grid matched by normalised cross-correlation (paper 4.3.2)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TemplateConfig:
    """The fine inter-sensor control points (paper 4.3.2).

    Attributes:
        spacing_px: distance between template centres, frame px (50, paper 4.3.2).
        template_px: template side, frame px (75, paper 4.3.2); an even value is rounded up to
            the next odd one so that the centre is a pixel.
        search_px: side of the searched neighbourhood, px (20, paper 4.3.2 "20 x 20
            neighborhood"): offsets ``-search_px//2 .. +search_px//2`` are tried in both axes.
        min_score: NCC peak below which a template is dropped (0.5; beyond the paper, which
            leaves all mismatches to REQCON; -1 keeps every peak).
        subpixel: peak refinement: ``"quadratic"`` (least-squares 2-D quadratic over the 3x3
            neighbourhood of the integer peak), ``"parabolic"`` (separate 3-point parabolas in x
            and y) or ``"none"``. The paper says only "sub-pixel"; quadratic by default.
        warp_reference: True (beyond the paper): warp the reference once into frame geometry
            with the current ``ref_from_frame`` and correlate there, so the ~10° rotation and
            ~20 % scale difference (paper 4.3.2) no longer decorrelate the templates. False =
            the paper: direct correlation in reference pixels around the predicted position
            (measured on a 1/4-scale real frame at 10° and 1.2x: NCC peaks 0.25-0.5 and ~90 %
            mismatches, as the paper expected, so :meth:`paper` also sets ``min_score=-1``).
        dither_iterations: the paper's "dithered" NCC, in our reading (the paper does not define
            it): after the integer peak and its sub-pixel fit, the search window is resampled
            (bilinear) at the estimated sub-pixel offset, i.e. dithered by the fractional part,
            and the template is correlated again over +-1 px; the new sub-pixel fit is added. A
            peak fitted near an integer is much less biased than one between pixels (measured on
            a real 1/4-scale Songdo frame with a fractional offset of (3.3, -2.6) px: median error
            0.083 -> 0.026 px, 90th percentile 0.32 -> 0.05 px; bicubic resampling was no better
            and costs twice as much). Number of such rounds; 1 (paper: "dithered"), 0 disables
            it. Costs about 0.4x the main correlation.
        jitter_px: beyond the paper, off by default: each template centre is moved off the
            regular grid by a seeded, reproducible integer offset, uniform in
            ``[-jitter_px, jitter_px]`` in x and y, so that templates do not sample periodic
            scene structure (lane markings, roof rows, parking bays) at one fixed phase and
            successive calls with different ``jitter_seed`` use different lattices.
        jitter_seed: seed of the jitter offsets.
        anchor: which frame point a template's match is attributed to (only with
            ``warp_reference``). ``"centre"``: the template centre (the paper). ``"structure"``
            (beyond the paper): the structure-tensor-weighted centroid ``c + M^-1 sum G(x)(x - c)``
            with ``G = grad grad^T`` per pixel and ``M = sum G``. Correlation measures the
            texture-weighted mean displacement over the template, which for a locally affine
            error of the current model is exactly the displacement at that centroid, not at the
            centre (measured on a 1/4-scale real frame, model off by 0.4 % scale and 0.2°:
            median error 0.158 -> ~0.12 px).
        min_template_std: texture check (beyond the paper): templates whose grey-level standard
            deviation is below this (grey levels 0..255) are skipped, because flat asphalt,
            roofs and water give flat NCC surfaces with spurious peaks. Applied to the frame
            template and to the searched reference window alike.
        reject_border_peaks: drop templates whose integer peak lies on the border of the search
            range (the true peak may lie outside it, and no sub-pixel fit is possible there).
        map_step_px: evaluation step of ``ref_from_frame`` when the reference is warped into
            frame geometry (8 px, see :func:`registration.warp.source_map_from_function`).
        max_roundtrip_px: with ``frame_from_ref`` given, templates whose centre does not come
            back within this distance through ``frame_from_ref(ref_from_frame(c))`` are skipped
            (the model is not invertible there). Frame px.
        min_templates: beyond the paper: when the grid at ``spacing_px`` holds fewer templates
            than this (small frames), the spacing shrinks until it holds this many (or reaches
            1 px); the edge ring uses the same spacing. 0 = always ``spacing_px``.
        edge_template_px: beyond the paper: when > 0, a ring of extra templates of this size
            along the frame border (corners included, ``spacing_px`` apart, each as close to the
            edge as it fits). The main grid stops ``template_px / 2`` from the border; after a
            strong radial correction that is far from the corners in corrected pixels (at
            γ = 0.7 the correction stretches the raw corners about 6x), so without the ring the
            global model extrapolates there. 0 = no ring (the paper).
    """

    spacing_px: int = 50
    template_px: int = 75
    search_px: int = 20
    min_score: float = 0.5
    subpixel: Literal["quadratic", "parabolic", "none"] = "quadratic"
    warp_reference: bool = True
    dither_iterations: int = 1
    jitter_px: float = 0.0
    jitter_seed: int = 0
    anchor: Literal["centre", "structure"] = "structure"
    min_template_std: float = 4.0
    reject_border_peaks: bool = True
    map_step_px: int = 8
    max_roundtrip_px: float = 1.0
    min_templates: int = 0
    edge_template_px: int = 0

    def __post_init__(self) -> None:
        if self.spacing_px < 1 or self.template_px < 3 or self.search_px < 2:
            raise ValueError(
                "TemplateConfig needs spacing_px >= 1, template_px >= 3, search_px >= 2, got "
                f"{self.spacing_px}, {self.template_px}, {self.search_px}"
            )
        if self.anchor not in ("centre", "structure"):
            raise ValueError(
                f"TemplateConfig.anchor must be 'centre' or 'structure', got {self.anchor!r}"
            )
        if self.subpixel not in ("quadratic", "parabolic", "none"):
            raise ValueError(
                f"TemplateConfig.subpixel must be 'quadratic', 'parabolic' or 'none', got {self.subpixel!r}"
            )
        if (
            self.jitter_px < 0
            or self.min_template_std < 0
            or self.map_step_px < 1
            or self.dither_iterations < 0
        ):
            raise ValueError(
                "TemplateConfig.jitter_px, min_template_std and dither_iterations must be >= 0 and "
                f"map_step_px >= 1, got {self.jitter_px}, {self.min_template_std}, "
                f"{self.dither_iterations}, {self.map_step_px}"
            )

    @classmethod
    def paper(cls) -> TemplateConfig:
        """Exactly the paper's choices (4.3.2): direct correlation in reference pixels, every
        peak kept for REQCON, no texture check; the dithered NCC and sub-pixel peak as above."""
        return cls(warp_reference=False, min_score=-1.0, min_template_std=0.0, anchor="centre")

    @property
    def half_template(self) -> int:
        return self.template_px // 2

    @property
    def search_radius(self) -> int:
        return self.search_px // 2


def template_grid(
    width: int, height: int, config: TemplateConfig = TemplateConfig()
) -> NDArray[np.int64]:
    """Integer template centres for a ``width`` x ``height`` frame, ``(N, 2)`` int64 (x, y).

    A regular grid with ``config.spacing_px`` spacing, centred in the frame, with every template
    fully inside it; then moved by the seeded jitter (``config.jitter_px``) and clipped so the
    templates stay inside. Empty when the frame is smaller than one template.
    """
    h = config.half_template
    spacing = grid_spacing(width, height, config)
    axes = []
    for n_px in (width, height):
        span = n_px - 1 - 2 * h
        if span < 0:
            return np.zeros((0, 2), np.int64)
        count = span // spacing + 1
        first = h + (span - (count - 1) * spacing) // 2
        axes.append(first + spacing * np.arange(count))
    gx, gy = np.meshgrid(axes[0], axes[1], indexing="xy")
    centres = np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.int64)
    if config.jitter_px > 0:
        rng = np.random.default_rng(config.jitter_seed)
        d = int(math.floor(config.jitter_px))
        centres = centres + rng.integers(-d, d + 1, size=centres.shape)
        centres[:, 0] = np.clip(centres[:, 0], h, width - 1 - h)
        centres[:, 1] = np.clip(centres[:, 1], h, height - 1 - h)
    return centres


def grid_spacing(width: int, height: int, config: TemplateConfig) -> int:
    """The template spacing for a ``width`` x ``height`` frame: ``spacing_px``, or less when
    that leaves fewer than ``min_templates`` templates (see :class:`TemplateConfig`)."""
    spacing = config.spacing_px
    span_x = width - 1 - 2 * config.half_template
    span_y = height - 1 - 2 * config.half_template
    if span_x < 0 or span_y < 0:
        return spacing
    while spacing > 1 and (span_x // spacing + 1) * (span_y // spacing + 1) < config.min_templates:
        spacing -= 1
    return spacing


def edge_ring(width: int, height: int, template_px: int, spacing_px: int) -> NDArray[np.int64]:
    """Integer centres of ``template_px`` templates along the border of a ``width`` x ``height``
    frame, as close to the edge as they fit, about ``spacing_px`` apart, corners included;
    ``(N, 2)`` int64, empty when the frame is smaller than one template."""
    h = template_px // 2
    lo_x, hi_x, lo_y, hi_y = h, width - 1 - h, h, height - 1 - h
    if hi_x < lo_x or hi_y < lo_y:
        return np.zeros((0, 2), np.int64)
    nx = max(1, round((hi_x - lo_x) / spacing_px))
    ny = max(1, round((hi_y - lo_y) / spacing_px))
    xs = np.round(np.linspace(lo_x, hi_x, nx + 1)).astype(np.int64)
    ys = np.round(np.linspace(lo_y, hi_y, ny + 1)).astype(np.int64)
    ring = [np.c_[xs, np.full_like(xs, lo_y)], np.c_[xs, np.full_like(xs, hi_y)]]
    if len(ys) > 2:
        inner = ys[1:-1]
        ring += [np.c_[np.full_like(inner, lo_x), inner], np.c_[np.full_like(inner, hi_x), inner]]
    return np.unique(np.vstack(ring).astype(np.int64), axis=0)


def subpixel_peak(
    patches: NDArray, method: Literal["quadratic", "parabolic", "none"] = "quadratic"
) -> NDArray[np.float64]:
    """Sub-pixel offset of correlation peaks from their 3x3 neighbourhoods.

    Args:
        patches: ``(N, 3, 3)`` (or ``(3, 3)``) correlation values around integer maxima, row =
            y, column = x, the maximum at ``[1, 1]``.
        method: ``"quadratic"``: least-squares fit of ``f = c + g.u + u'Hu/2`` to the 9 values
            and its stationary point; falls back to ``"parabolic"`` where ``H`` is not negative
            definite. ``"parabolic"``: independent 3-point parabolas along x and y. ``"none"``.

    Returns:
        ``(N, 2)`` offsets ``(dx, dy)`` in pixels, each clipped to ``[-1, 1]``.
    """
    r = np.asarray(patches, np.float64)
    if r.shape == (3, 3):
        r = r[None]
    if r.ndim != 3 or r.shape[1:] != (3, 3):
        raise ValueError(f"patches must have shape (N, 3, 3), got {r.shape}")
    n = len(r)
    if method == "none":
        return np.zeros((n, 2))
    # Parabolic: vertex of the parabola through (-1, f-), (0, f0), (1, f+).
    fxm, fx0, fxp = r[:, 1, 0], r[:, 1, 1], r[:, 1, 2]
    fym, fyp = r[:, 0, 1], r[:, 2, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        den_x = fxm - 2 * fx0 + fxp
        den_y = fym - 2 * fx0 + fyp
        par = np.stack(
            [
                np.where(den_x < 0, 0.5 * (fxm - fxp) / den_x, 0.0),
                np.where(den_y < 0, 0.5 * (fym - fyp) / den_y, 0.0),
            ],
            axis=1,
        )
    if method == "parabolic":
        return np.clip(np.nan_to_num(par), -1, 1)
    if method != "quadratic":
        raise ValueError(f"method must be 'quadratic', 'parabolic' or 'none', got {method!r}")
    u = np.array([-1.0, 0.0, 1.0])
    ux = u[None, :].repeat(3, 0)  # column offset
    uy = u[:, None].repeat(3, 1)  # row offset
    # Orthogonal basis on the 3x3 grid: 1, x, y, xy, x^2 - 2/3, y^2 - 2/3.
    gx = (r * ux).sum(axis=(1, 2)) / 6
    gy = (r * uy).sum(axis=(1, 2)) / 6
    hxy = (r * ux * uy).sum(axis=(1, 2)) / 4
    hxx = (r * (ux**2 - 2 / 3)).sum(axis=(1, 2))  # = 2 * coefficient of x^2
    hyy = (r * (uy**2 - 2 / 3)).sum(axis=(1, 2))
    det = hxx * hyy - hxy**2
    ok = (hxx < 0) & (det > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = -(hyy * gx - hxy * gy) / det
        dy = -(hxx * gy - hxy * gx) / det
    quad = np.stack([dx, dy], axis=1)
    ok &= np.isfinite(quad).all(axis=1) & (np.abs(quad) <= 1).all(axis=1)
    out = np.where(ok[:, None], quad, par)
    return np.clip(np.nan_to_num(out), -1, 1)


def _box_any(mask: NDArray[np.bool_], centres: NDArray[np.int64], half: int) -> NDArray[np.bool_]:
    """Whether any ``mask`` pixel lies in the boxes around ``centres`` (inside the image)."""
    s = cv2.integral(mask.astype(np.uint8), sdepth=cv2.CV_32S)
    x0, y0 = centres[:, 0] - half, centres[:, 1] - half
    x1, y1 = centres[:, 0] + half + 1, centres[:, 1] + half + 1
    return (s[y1, x1] - s[y0, x1] - s[y1, x0] + s[y0, x0]) > 0


def _peak3(r: NDArray, method: str) -> tuple[float, float]:
    """Scalar twin of :func:`subpixel_peak` for one 3x3 neighbourhood (no numpy overhead)."""
    (a, b, c), (d, e, f), (g, h, i) = r.tolist()
    if method == "none":
        return 0.0, 0.0
    # Parabolic fallback: 3-point parabolas through the centre row and column.
    den_x, den_y = d - 2 * e + f, b - 2 * e + h
    px = 0.5 * (d - f) / den_x if den_x < 0 else 0.0
    py = 0.5 * (b - h) / den_y if den_y < 0 else 0.0
    if method == "quadratic":
        gx = ((c + f + i) - (a + d + g)) / 6
        gy = ((g + h + i) - (a + b + c)) / 6
        hxy = (a + i - c - g) / 4
        col_outer, col_mid = a + d + g + c + f + i, b + e + h
        row_outer, row_mid = a + b + c + g + h + i, d + e + f
        hxx = col_outer / 3 - 2 * col_mid / 3
        hyy = row_outer / 3 - 2 * row_mid / 3
        det = hxx * hyy - hxy * hxy
        if hxx < 0 and det > 0:
            qx = -(hyy * gx - hxy * gy) / det
            qy = -(hxx * gy - hxy * gx) / det
            if abs(qx) <= 1 and abs(qy) <= 1:
                return qx, qy
    return min(max(px, -1.0), 1.0), min(max(py, -1.0), 1.0)


def _structure_centroid(tpl: NDArray[np.uint8], ramp: NDArray[np.float32]) -> tuple[float, float]:
    """Offset from the template centre of its structure-tensor-weighted centroid
    ``M^-1 sum G(u) u`` (see ``TemplateConfig.anchor``), clipped to the template."""
    gx = cv2.Sobel(tpl, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(tpl, cv2.CV_32F, 0, 1, ksize=3)
    # Border rows/columns of Sobel see the reflected border; leave them out.
    gx, gy = gx[1:-1, 1:-1], gy[1:-1, 1:-1]
    u = ramp[1:-1]
    xx, xy, yy = gx * gx, gx * gy, gy * gy
    sxx, sxy, syy = float(xx.sum()), float(xy.sum()), float(yy.sum())
    mx = float(xx.sum(axis=0) @ u) + float(xy.sum(axis=1) @ u)
    my = float(xy.sum(axis=0) @ u) + float(yy.sum(axis=1) @ u)
    # Tikhonov term: along a straight edge M is singular and the centroid undefined there.
    eps = 1e-2 * (sxx + syy)
    a, d = sxx + eps, syy + eps
    det = a * d - sxy * sxy
    if not det > 0:
        return 0.0, 0.0
    h = float(ramp[-1])
    ox = (d * mx - sxy * my) / det
    oy = (a * my - sxy * mx) / det
    return min(max(ox, -h), h), min(max(oy, -h), h)


def _ncc3x3(sub: NDArray, tpl_unit: NDArray[np.float32]) -> NDArray[np.float32]:
    """TM_CCOEFF_NORMED of a template (given zero-mean, unit-norm, flattened) at the 3 x 3
    offsets of ``sub`` (template side + 2), as one matrix product: cheaper than matchTemplate,
    whose DFT set-up dominates for so few offsets."""
    n = tpl_unit.size
    side = sub.shape[0] - 2
    v = sliding_window_view(sub.astype(np.float32), (side, side)).reshape(9, n)
    num = v @ tpl_unit
    s1 = v.sum(axis=1)
    s2 = np.einsum("ij,ij->i", v, v)
    den = np.sqrt(np.maximum(s2 - s1 * s1 / n, 1e-12))
    return (num / den).reshape(3, 3)


def _n_threads() -> int:
    """Worker threads for per-template correlation: OpenCV's thread setting, at most the CPUs."""
    return max(1, min(cv2.getNumThreads(), os.cpu_count() or 1))


def template_control_points(
    frame_grey: NDArray,
    ref_grey: NDArray,
    ref_from_frame: PointFunction,
    frame_from_ref: PointFunction | None = None,
    config: TemplateConfig = TemplateConfig(),
    *,
    centres: NDArray[np.int64] | None = None,
    ref_valid: NDArray | None = None,
    fallback: GriddedReference | None = None,
    _searches: dict | None = None,
) -> ControlPoints:
    """Template grid control points (paper 4.3.2 steps 1, 3, 4).

    A grid of ``template_px`` templates every ``spacing_px`` is cut from the frame; each is
    searched by normalised cross-correlation (``cv2.matchTemplate``, ``TM_CCOEFF_NORMED``) over
    offsets ``+-search_px // 2`` around the position ``ref_from_frame`` predicts; the integer peak
    is refined to sub-pixel (``subpixel``) and by the dithered re-correlation
    (``dither_iterations``). The template centre (or its structure centroid, ``anchor``) becomes
    ``src`` and the matched reference position ``dst``.

    With ``config.warp_reference`` the reference is first resampled into frame geometry once
    (``warp.source_map_from_function(ref_from_frame, ..., step=map_step_px)`` + ``warp.remap``,
    bilinear); a peak at frame offset ``d`` means frame point ``s`` shows the reference content
    at ``ref_from_frame(s + d)``, which is ``dst``. Without it (the paper) the search runs
    directly in reference pixels around ``round(ref_from_frame(c))`` and ``dst`` is that position
    plus the peak offset.

    Templates are skipped when they or their search window are too flat
    (``min_template_std``), when the search window leaves the reference, when the model is
    undefined or not invertible there, when the peak is below ``min_score`` or on the border of
    the search range. The per-template loop runs in ``min(cv2.getNumThreads(), CPUs)`` threads
    (OpenCV releases the GIL); results do not depend on the thread count.

    Args:
        frame_grey: the frame, anything :func:`to_grey` accepts, ``(H, W)``.
        ref_grey: the reference (base map), likewise.
        ref_from_frame: current model, frame px -> reference px, ``(N, 2) -> (N, 2)``.
        frame_from_ref: its inverse, used only for the round-trip check; None skips the check.
        config: grid and search settings.
        centres: template centres to use instead of the grid (integer frame px, each template
            fully inside the frame); the edge ring is then not added.
        ref_valid: ``(Hr, Wr)`` bool, where the reference has content (e.g. the mid base
            image); a template whose search window touches anything else is not searched there.
        fallback: a second reference (image and its ``ref_from_frame``), searched by the
            templates the first cannot take (paper 4.4: the previous frame completes the mid
            base image). Only with ``warp_reference``; warped only when some template needs it.

    Returns:
        :class:`ControlPoints`: ``src`` frame px (template centres or their structure centroids,
        ``config.anchor``), ``dst`` reference px (of the fallback where ``source == 1``),
        ``score`` = NCC peak value; empty when nothing matched.
    """
    if fallback is not None and not config.warp_reference:
        raise ValueError("template_control_points: a fallback reference needs warp_reference=True")
    frame = to_grey(frame_grey)
    ref = to_grey(ref_grey)
    fw, fh = coords.image_size(frame)
    rw, rh = coords.image_size(ref)
    half, rad = config.half_template, config.search_radius
    if centres is None and config.edge_template_px > 0:
        ring = edge_ring(fw, fh, config.edge_template_px, grid_spacing(fw, fh, config))
        edge_cfg = dataclasses.replace(
            config, template_px=config.edge_template_px, edge_template_px=0
        )
        # Both sets search the same warped references: warp them once (``_searches``).
        searches: dict = {}
        return ControlPoints.concatenate(
            [
                template_control_points(
                    frame,
                    ref,
                    ref_from_frame,
                    frame_from_ref,
                    config,
                    centres=template_grid(fw, fh, config),
                    ref_valid=ref_valid,
                    fallback=fallback,
                    _searches=searches,
                ),
                template_control_points(
                    frame,
                    ref,
                    ref_from_frame,
                    frame_from_ref,
                    edge_cfg,
                    centres=ring,
                    ref_valid=ref_valid,
                    fallback=fallback,
                    _searches=searches,
                ),
            ]
        )
    if centres is None:
        centres = template_grid(fw, fh, config)
    if len(centres) == 0:
        return ControlPoints.empty()

    pred = _call_points(ref_from_frame, centres.astype(np.float64), "ref_from_frame")
    keep = np.isfinite(pred).all(axis=1)
    if frame_from_ref is not None and keep.any():
        back = _call_points(frame_from_ref, pred[keep], "frame_from_ref")
        err = np.hypot(*(back - centres[keep]).T)
        keep[np.flatnonzero(keep)[~(err <= config.max_roundtrip_px)]] = False
    if not keep.any():
        return ControlPoints.empty()
    centres, pred = centres[keep], pred[keep]

    win = half + rad  # half-size of the searched window
    use_fallback = np.zeros(len(centres), bool)
    fb_search = None
    if config.warp_reference:
        # Warp the reference into frame geometry once, on a canvas padded by the search radius
        # so that windows of border templates fit; canvas pixel (i, j) = frame pixel (i-rad, j-rad).
        searches = {} if _searches is None else _searches
        if "ref" not in searches:
            searches["ref"] = _search_image(ref, ref_from_frame, ref_valid, fw, fh, rad, config)
        search, invalid = searches["ref"]
        win_centres = centres + rad
        ok = ~_box_any(invalid, win_centres, win)
        if fallback is not None and not ok.all():
            if "fallback" not in searches:
                searches["fallback"] = _search_image(
                    to_grey(fallback.image), fallback.ref_from_frame, None, fw, fh, rad, config
                )
            fb_search, fb_invalid = searches["fallback"]
            use_fallback = ~ok & ~_box_any(fb_invalid, win_centres, win)
            ok |= use_fallback
    else:
        search = ref
        win_centres = np.round(pred).astype(np.int64)
        ok = (
            (win_centres[:, 0] - win >= 0)
            & (win_centres[:, 0] + win <= rw - 1)
            & (win_centres[:, 1] - win >= 0)
            & (win_centres[:, 1] + win <= rh - 1)
        )
        if ref_valid is not None and ok.any():
            ok[ok] = ~_box_any(~np.asarray(ref_valid, bool), win_centres[ok], win)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return ControlPoints.empty()

    side = 2 * rad + 1
    scores = np.full(len(idx), np.nan)
    offsets = np.full((len(idx), 2), np.nan)
    min_std = config.min_template_std
    grow = 2 * half + 3  # template plus a +-1 px search, for the dither re-correlation
    anchors = np.zeros((len(idx), 2))
    use_structure = config.warp_reference and config.anchor == "structure"
    ramp = np.arange(-half, half + 1, dtype=np.float32)

    def correlate(chunk: NDArray[np.int64]) -> None:
        # Fills rows ``chunk`` of scores/offsets; chunks are disjoint, so threads do not
        # collide, and cv2 releases the GIL inside matchTemplate.
        for k in chunk:
            cx, cy = centres[idx[k]]
            wx, wy = win_centres[idx[k]]
            tpl = frame[cy - half : cy + half + 1, cx - half : cx + half + 1]
            image = fb_search if use_fallback[idx[k]] else search
            window = image[wy - win : wy + win + 1, wx - win : wx + win + 1]
            # Texture check on both sides: a flat template or window has no reliable peak.
            if cv2.meanStdDev(tpl)[1][0, 0] < min_std or cv2.meanStdDev(window)[1][0, 0] < min_std:
                continue
            res = cv2.matchTemplate(window, tpl, cv2.TM_CCOEFF_NORMED)
            _, best, _, (px, py) = cv2.minMaxLoc(res)
            if not (0 < px < side - 1 and 0 < py < side - 1):
                if config.reject_border_peaks:
                    continue
                px, py = min(max(px, 1), side - 2), min(max(py, 1), side - 2)
            sx, sy = _peak3(res[py - 1 : py + 2, px - 1 : px + 2], config.subpixel)
            if config.dither_iterations:
                tpl_unit = tpl.astype(np.float32).ravel()
                tpl_unit -= tpl_unit.mean()
                tpl_unit /= max(float(np.linalg.norm(tpl_unit)), 1e-12)
            for _ in range(config.dither_iterations):
                # Resample the window so that the current estimate sits on the integer grid,
                # then correlate again over +-1 px; the peak fit is least biased near 0.
                m = np.array([[1.0, 0.0, px + sx - 1], [0.0, 1.0, py + sy - 1]], np.float32)
                sub = cv2.warpAffine(
                    window,
                    m,
                    (grow, grow),
                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                    borderMode=cv2.BORDER_REPLICATE,
                )
                res2 = _ncc3x3(sub, tpl_unit)
                dx, dy = _peak3(res2, config.subpixel)
                sx, sy = sx + dx, sy + dy
                best = max(best, float(res2[1, 1]))
            scores[k] = best
            offsets[k] = (px - rad + sx, py - rad + sy)
            if use_structure:
                anchors[k] = _structure_centroid(tpl, ramp)

    n_threads = max(1, min(_n_threads(), len(idx) // 64))
    chunks = np.array_split(np.arange(len(idx)), n_threads)
    if n_threads == 1:
        correlate(chunks[0])
    else:
        with ThreadPoolExecutor(n_threads) as pool:
            list(pool.map(correlate, chunks))
    good = np.isfinite(scores) & (scores >= config.min_score)
    if not good.any():
        return ControlPoints.empty()
    idx, scores, offset, anchor = idx[good], scores[good], offsets[good], anchors[good]
    src = centres[idx].astype(np.float64) + anchor
    source = use_fallback[idx].astype(np.int64)
    if config.warp_reference:
        dst = np.full_like(src, np.nan)
        for k, fn in enumerate((ref_from_frame, fallback and fallback.ref_from_frame)):
            sel = source == k
            if sel.any():
                dst[sel] = _call_points(fn, src[sel] + offset[sel], "ref_from_frame")
    else:
        dst = win_centres[idx] + offset
    fin = np.isfinite(dst).all(axis=1)
    logger.debug(
        "template control points: %d of %d templates matched", int(fin.sum()), len(centres)
    )
    return ControlPoints(src[fin], dst[fin], scores[fin], source[fin])


def _search_image(ref, ref_from_frame, ref_valid, fw, fh, rad, config):
    """``ref`` warped into frame geometry on a canvas padded by ``rad`` (canvas pixel (i, j) =
    frame pixel (i - rad, j - rad)), and where that canvas has no reference content."""
    smap = warp.source_map_from_function(
        ref_from_frame, fw + 2 * rad, fh + 2 * rad, step=config.map_step_px, origin=(-rad, -rad)
    )
    search = warp.remap(ref, smap, interpolation="linear")
    rh, rw = ref.shape[:2]
    # NaN fails every comparison, so this also marks pixels without a source.
    sx, sy = smap[..., 0], smap[..., 1]
    invalid = ~((sx >= 0) & (sx <= rw - 1) & (sy >= 0) & (sy <= rh - 1))
    if ref_valid is not None:
        content = np.asarray(ref_valid, np.uint8)
        invalid |= warp.remap(content, smap, interpolation="nearest") == 0
    return search, invalid


# --------------------------------------------------------------------------------------------
# Gridded SIFT (paper 4.4)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GriddedSiftConfig:
    """The fine intra-sensor control points (paper 4.4).

    Attributes:
        window_px: side of the square windows around the grid centres in the frame in which
            keypoints are kept, frame px (50, paper 4.4 "50 x 50 templates").
        spacing_px: distance between window centres, frame px (100, paper 4.4).
        ratio: Lowe's ratio test inside each window pair (0.8, Lowe 2004; the paper gives none).
        decimate: keep one match in this many of the combined list of all references (3,
            paper 4.4 "the combined base and previous image list was decimated by a factor of
            3"); 1 keeps all. See :func:`gridded_sift_control_points` for the order.
        window_margin_px: the reference window is the bounding box of the frame window's
            corners mapped by ``ref_from_frame``, grown by this many reference px on each side
            (25; beyond the paper's exact 50 px window: it absorbs the residual error of the
            coarse model, and the box of mapped corners absorbs scale and rotation).
        sift: detector settings (frame and reference alike).
    """

    window_px: int = 50
    spacing_px: int = 100
    ratio: float = 0.8
    decimate: int = 3
    window_margin_px: float = 25.0
    sift: SiftConfig = field(default_factory=SiftConfig)

    @classmethod
    def paper(cls) -> GriddedSiftConfig:
        """The paper's choices (4.4): the reference window is exactly the mapped 50 x 50 window
        (no margin)."""
        return cls(window_margin_px=0.0)

    def __post_init__(self) -> None:
        if self.window_px < 1 or self.spacing_px < 1:
            raise ValueError(
                f"GriddedSiftConfig.window_px and spacing_px must be >= 1, got {self.window_px}, {self.spacing_px}"
            )
        if self.decimate < 1:
            raise ValueError(f"GriddedSiftConfig.decimate must be >= 1, got {self.decimate}")
        if not 0 < self.ratio <= 1:
            raise ValueError(f"GriddedSiftConfig.ratio must be in (0, 1], got {self.ratio}")
        if self.window_margin_px < 0:
            raise ValueError(
                f"GriddedSiftConfig.window_margin_px must be >= 0, got {self.window_margin_px}"
            )


@dataclass(frozen=True)
class GriddedReference:
    """One reference image for :func:`gridded_sift_control_points`.

    Attributes:
        image: the reference image (anything :func:`to_grey` accepts).
        ref_from_frame: frame px -> reference px, ``(N, 2) -> (N, 2)``.
        frame_from_ref: reference px -> frame px (accepted for symmetry; not needed here).
        keypoints: precomputed keypoints of ``image`` (e.g. of the mid base image, computed
            once per sequence); None = detect them inside the needed windows only.
    """

    image: NDArray
    ref_from_frame: PointFunction
    frame_from_ref: PointFunction | None = None
    keypoints: Keypoints | None = None


Reference = GriddedReference  # short alias used by the pipeline


def window_centres(
    width: int, height: int, config: GriddedSiftConfig = GriddedSiftConfig()
) -> NDArray[np.float64]:
    """``(N, 2)`` centres of the gridded-SIFT windows: a grid with ``spacing_px`` spacing,
    centred in the frame, every window fully inside it (row-major order)."""
    w = config.window_px
    axes = []
    for n_px in (width, height):
        span = n_px - w  # room for window origins 0..n_px - w
        if span < 0:
            return np.zeros((0, 2))
        count = span // config.spacing_px + 1
        first = (span - (count - 1) * config.spacing_px) / 2 + (w - 1) / 2
        axes.append(first + config.spacing_px * np.arange(count))
    gx, gy = np.meshgrid(axes[0], axes[1], indexing="xy")
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def _as_reference(entry: GriddedReference | tuple, k: int) -> GriddedReference:
    if isinstance(entry, GriddedReference):
        return entry
    if isinstance(entry, tuple) and len(entry) in (3, 4):
        return GriddedReference(*entry)
    raise ValueError(
        f"refs[{k}] must be a GriddedReference or a (ref_grey, ref_from_frame, frame_from_ref"
        f"[, keypoints]) tuple, got {type(entry).__name__}"
    )


def gridded_sift_control_points(
    frame_grey: NDArray,
    refs: Sequence[GriddedReference | tuple],
    config: GriddedSiftConfig = GriddedSiftConfig(),
    *,
    frame_keypoints: Keypoints | None = None,
) -> ControlPoints:
    """Gridded SIFT control points (paper 4.4 steps 1-6).

    SIFT runs once on the frame (restricted by a mask to the ``window_px`` windows on the
    ``spacing_px`` grid) and once per reference (restricted to the predicted reference windows,
    unless precomputed keypoints are given); detecting on the whole image and bucketing is far
    cheaper than one detection per window. Each frame window's keypoints are matched, with the
    ratio test, only against the reference keypoints inside its corresponding window: the
    bounding box of the window's corners mapped by ``ref_from_frame``, grown by
    ``window_margin_px``.

    The lists of all references are combined (``source`` = index into ``refs``) and decimated by
    ``config.decimate``: sorted by window (row-major) and, within a window, by decreasing score,
    then every ``decimate``-th entry is kept starting with the first. This keeps exactly
    ``ceil(N / decimate)`` points, spread evenly over the windows, best first in each.

    Args:
        frame_grey: the frame, ``(H, W)`` (anything :func:`to_grey` accepts).
        refs: references (paper: the mid base image and the previous registered frame), each a
            :class:`GriddedReference` or a tuple ``(ref_grey, ref_from_frame, frame_from_ref[,
            keypoints])``.
        config: grid, matching and decimation settings.
        frame_keypoints: precomputed keypoints of the whole frame (optional).

    Returns:
        :class:`ControlPoints`: ``src`` frame px, ``dst`` reference px, ``score`` = 1 - Lowe ratio,
        ``source`` = reference index.
    """
    frame = to_grey(frame_grey)
    fw, fh = coords.image_size(frame)
    references = [_as_reference(e, k) for k, e in enumerate(refs)]
    centres = window_centres(fw, fh, config)
    if len(centres) == 0 or not references:
        return ControlPoints.empty()
    half = (config.window_px - 1) / 2

    if frame_keypoints is None:
        mask = np.zeros((fh, fw), np.uint8)
        for cx, cy in centres:
            x0, y0 = int(math.ceil(cx - half)), int(math.ceil(cy - half))
            mask[y0 : y0 + config.window_px, x0 : x0 + config.window_px] = 1
        frame_keypoints = detect_sift(frame, config.sift, mask)
    # Bucket frame keypoints by window: nearest grid centre, then inside the window?
    fx0, fy0 = centres[0]
    nx = len(np.unique(centres[:, 0]))
    ny = len(centres) // nx
    fxy = frame_keypoints.xy
    gi = (
        np.round((fxy[:, 0] - fx0) / config.spacing_px).astype(np.int64)
        if len(fxy)
        else np.zeros(0, np.int64)
    )
    gj = (
        np.round((fxy[:, 1] - fy0) / config.spacing_px).astype(np.int64)
        if len(fxy)
        else np.zeros(0, np.int64)
    )
    inside = (gi >= 0) & (gi < nx) & (gj >= 0) & (gj < ny)
    win_of = np.where(inside, gj * nx + gi, -1)
    cxy = centres[np.clip(win_of, 0, len(centres) - 1)]
    inside &= (np.abs(fxy - cxy) <= half + 1e-9).all(axis=1) if len(fxy) else inside
    win_of[~inside] = -1
    order = np.argsort(win_of, kind="stable")
    bounds = np.searchsorted(win_of[order], np.arange(len(centres) + 1))

    # Window corners in the frame, (N, 4, 2).
    corners = centres[:, None, :] + half * np.array(
        [[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64
    )
    parts: list[tuple[NDArray, ...]] = []
    for k, ref_entry in enumerate(references):
        ref = to_grey(ref_entry.image)
        rw, rh = coords.image_size(ref)
        mapped = _call_points(
            ref_entry.ref_from_frame, corners.reshape(-1, 2), f"refs[{k}].ref_from_frame"
        )
        mapped = mapped.reshape(-1, 4, 2)
        m = config.window_margin_px
        lo = np.nanmin(mapped, axis=1) - m
        hi = np.nanmax(mapped, axis=1) + m
        usable = (
            np.isfinite(mapped).all(axis=(1, 2))
            & (hi[:, 0] >= 0)
            & (hi[:, 1] >= 0)
            & (lo[:, 0] <= rw - 1)
            & (lo[:, 1] <= rh - 1)
        )
        if not usable.any():
            continue
        ref_kp = ref_entry.keypoints
        if ref_kp is None:
            mask = np.zeros((rh, rw), np.uint8)
            for a, b in zip(lo[usable], hi[usable], strict=True):
                x0, y0 = max(0, int(math.floor(a[0]))), max(0, int(math.floor(a[1])))
                x1, y1 = min(rw - 1, int(math.ceil(b[0]))), min(rh - 1, int(math.ceil(b[1])))
                mask[y0 : y1 + 1, x0 : x1 + 1] = 1
            ref_kp = detect_sift(ref, config.sift, mask)
        if len(ref_kp) < 2:
            continue
        rorder = np.argsort(ref_kp.xy[:, 0], kind="stable")
        rx_sorted = ref_kp.xy[rorder, 0]
        ry = ref_kp.xy[:, 1]
        matcher = cv2.BFMatcher(cv2.NORM_L2)
        for w in np.flatnonzero(usable):
            f_idx = order[bounds[w] : bounds[w + 1]]
            if len(f_idx) == 0:
                continue
            a0, a1 = np.searchsorted(rx_sorted, [lo[w, 0], hi[w, 0]], side="left")
            cand = rorder[a0:a1]
            cand = cand[(ry[cand] >= lo[w, 1]) & (ry[cand] <= hi[w, 1])]
            if len(cand) < 2:
                continue
            knn = matcher.knnMatch(
                frame_keypoints.descriptors[f_idx], ref_kp.descriptors[cand], k=2
            )
            rows = [
                (m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance)
                for m in knn
                if len(m) == 2 and m[0].distance < config.ratio * m[1].distance
            ]
            if not rows:
                continue
            r = np.array(rows, np.float64)
            qi, ti = r[:, 0].astype(np.int64), r[:, 1].astype(np.int64)
            with np.errstate(divide="ignore", invalid="ignore"):
                score = 1.0 - np.where(r[:, 3] > 0, r[:, 2] / r[:, 3], 1.0)
            n = len(r)
            parts.append(
                (
                    frame_keypoints.xy[f_idx[qi]],
                    ref_kp.xy[cand[ti]],
                    score,
                    np.full(n, w, np.int64),
                    np.full(n, k, np.int64),
                )
            )
    if not parts:
        return ControlPoints.empty()
    src, dst, score, win, source = (np.concatenate(c) for c in zip(*parts, strict=True))
    # Decimation (paper 4.4): order by window, then best score first, keep every decimate-th.
    order_all = np.lexsort((source, -score, win))[:: config.decimate]
    logger.debug(
        "gridded SIFT: %d matches over %d windows, %d kept after decimation by %d",
        len(src),
        len(centres),
        len(order_all),
        config.decimate,
    )
    return ControlPoints(src[order_all], dst[order_all], score[order_all], source[order_all])
