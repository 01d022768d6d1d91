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

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration import coords

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
    "detect_sift",
    "downscale",
    "gridded_sift_control_points",
    "match_ratio",
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


def downscale_mask(mask: NDArray, scale: float) -> NDArray[np.bool_]:
    """A content mask (``(H, W)``, non-zero = content) at ``scale`` (:func:`downscale`): True
    where the area it averages is (all but 2 %) content."""
    return downscale(np.asarray(mask, bool).astype(np.uint8) * 255, scale) > 250


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
_FLANN_SEED = 0x5EED


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
        # FLANN's randomised kd-trees draw from OpenCV's (thread-local) RNG: seeding it here
        # makes the approximate matches, and everything after them, reproducible.
        cv2.setRNGSeed(_FLANN_SEED)
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
        valid: ``(H, W)`` bool, where ``image`` has content (None = everywhere); used by the
            template matcher's fallbacks.
        other_sensor: the image was taken by another sensor or at another time than the
            frames (the base map; not the mid base image or the previous frame): the template
            matcher's change test (``TemplateConfig.change_log_ratio``) applies to it.
    """

    image: NDArray
    ref_from_frame: PointFunction
    frame_from_ref: PointFunction | None = None
    keypoints: Keypoints | None = None
    valid: NDArray | None = None
    other_sensor: bool = False


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
