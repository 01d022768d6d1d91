"""SIFT keypoints with ratio-test matching (paper sections 4.3.1 and 4.4): detection (with an
optional mask), descriptors, and matches by FLANN or brute force with Lowe's ratio test.

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

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration import coords
from registration.matching.grey import to_grey

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
