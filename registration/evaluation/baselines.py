"""The pipelines a user would otherwise run, as the benchmarks' baselines.

* Plain OpenCV (:func:`register_baseline`): per frame radial correction with the same Harris γ,
  full-frame SIFT, FLANN ratio matching, ``cv2.findHomography`` with USAC_MAGSAC. The reference
  frame is matched to the base map; every other frame to the reference frame, and the two
  homographies are chained.
* Stabilo's recipe (:func:`register_stabilo`): the frame-to-reference registration of Stabilo
  (R. Fonod, the registration engine of Geo-trax, ``stabilo/cfg/default.yaml``): ORB (2000
  keypoints per frame, twice that in the reference frame) on the raw frame at half size,
  brute-force Hamming matching with the reference frame's descriptors as the query and Lowe's
  ratio 0.9, ``cv2.findHomography`` with MAGSAC++ (2 px at full resolution, 5000 iterations,
  confidence 0.999999) to the reference frame. Stabilo has no lens model: with γ = 0.7 a
  homography between raw frames leaves ~5 px (measured on a simulated 1280x960 hover), so the
  frames are radially corrected first, as a user of such a camera would do. It has no base
  map either: frames reach the base through the plain OpenCV pipeline's link of the reference
  frame, so both baselines share one reference registration.

Both results offer the :class:`registration.mapping.SequenceMapping` interface (stage
``"local"`` equals ``"global"``), so the evaluation scores them exactly like a registration
result.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.global_registration import corrected_grey
from registration.lens import Camera, as_camera


@dataclass(frozen=True)
class BaselineConfig:
    """Plain OpenCV settings (OpenCV defaults unless noted).

    Attributes:
        ratio: Lowe's ratio test.
        magsac_threshold_px: USAC_MAGSAC reprojection threshold (OpenCV's default 3 px... we use
            the paper's 5 px for comparability).
        max_iterations: USAC iteration cap.
        confidence: USAC confidence.
    """

    ratio: float = 0.8
    magsac_threshold_px: float = 5.0
    max_iterations: int = 10000
    confidence: float = 0.999


@dataclass
class BaselineResult:
    """Homographies ``base_from_corrected`` per frame (None where the frame failed)."""

    gamma: float
    frame_size: tuple[int, int]
    homographies: list[NDArray | None]
    times_s: list[float] = field(default_factory=list)
    reference_frame: int = 0

    @property
    def n_frames(self) -> int:
        return len(self.homographies)

    @functools.cached_property
    def camera(self) -> Camera:
        """The frames' camera (built once)."""
        return Camera(self.gamma, *self.frame_size)

    def _inside(self, xy: NDArray) -> NDArray[np.bool_]:
        w, h = self.frame_size
        return (
            (xy[:, 0] >= -0.5) & (xy[:, 0] <= w - 0.5) & (xy[:, 1] >= -0.5) & (xy[:, 1] <= h - 0.5)
        )

    def frame_to_base(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]:
        pts = as_points(xy)
        h = self.homographies[k]
        if h is None:
            return np.full_like(pts, np.nan)
        out = apply_homography(h, self.camera.corrected_from_raw(pts))
        out[~self._inside(pts)] = np.nan
        return out

    def base_to_frame(
        self, k: int, xy: ArrayLike, stage: str = "local", *, clip: bool = True
    ) -> NDArray[np.float64]:
        pts = as_points(xy)
        h = self.homographies[k]
        if h is None:
            return np.full_like(pts, np.nan)
        raw = self.camera.raw_from_corrected(apply_homography(np.linalg.inv(h), pts))
        if clip:
            raw[~self._inside(raw)] = np.nan
        return raw


def degenerate(h: NDArray | None, camera: Camera) -> bool:
    """Whether ``h`` (``base_from_corrected``) cannot be a view of the frame: not finite, the
    horizon through the frame (its corners' w not all of one sign: the outline folds), or the
    outline collapsed on the base (an area under 1e-6 of the frame's). With every corner on one
    side of the horizon the convex outline maps to a convex one, so no other fold can occur. A
    chain of homographies to a frame that no longer sees the reference frame (the long flight's
    last frames) multiplies into such a matrix, rank 2 to 15 digits."""
    if h is None or not np.isfinite(h).all():
        return True
    w, hgt = camera.width, camera.height
    corners = camera.corrected_from_raw(
        np.array([[0.0, 0.0], [w - 1.0, 0.0], [w - 1.0, hgt - 1.0], [0.0, hgt - 1.0]])
    )
    q = np.c_[corners, np.ones(4)] @ np.asarray(h, np.float64).T
    if not (q[:, 2] > 0).all() and not (q[:, 2] < 0).all():
        return True
    xy = q[:, :2] / q[:, 2:]
    area = 0.5 * abs(np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1]))
    return area < 1e-6 * w * hgt


def _without_degenerate(out: BaselineResult) -> BaselineResult:
    """``out`` with every :func:`degenerate` homography taken as a failed frame (None)."""
    out.homographies = [None if degenerate(h, out.camera) else h for h in out.homographies]
    return out


def apply_homography(h: NDArray, xy: NDArray) -> NDArray:
    p = np.c_[xy, np.ones(len(xy))] @ h.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:3]


def sift_features(image: NDArray, mask: NDArray | None = None):
    """Full-frame SIFT of a grey or BGR image: ``(xy (N, 2), descriptors (N, 128))``; ``mask``:
    where keypoints may lie (``(H, W)``, nonzero), None = everywhere."""
    from registration.matching import to_grey

    m = None if mask is None else np.asarray(mask, np.uint8) * 255
    kps, desc = cv2.SIFT_create().detectAndCompute(to_grey(image), m)
    xy = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
    return xy, desc


def homography(a, b, config: BaselineConfig) -> NDArray | None:
    """``b_from_a`` from two :func:`sift_features` results, or None when it cannot be found."""
    xy_a, da = a
    xy_b, db = b
    if da is None or db is None or len(da) < 4 or len(db) < 4:
        return None
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 5}, {"checks": 50})
    pairs = flann.knnMatch(da, db, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < config.ratio * p[1].distance]
    if len(good) < 4:
        return None
    src = xy_a[[m.queryIdx for m in good]]
    dst = xy_b[[m.trainIdx for m in good]]
    h, _ = cv2.findHomography(
        src,
        dst,
        cv2.USAC_MAGSAC,
        config.magsac_threshold_px,
        maxIters=config.max_iterations,
        confidence=config.confidence,
    )
    return h


def register_baseline(
    frames, base: NDArray, gamma: float, *, reference_frame: int = 0, config=BaselineConfig()
) -> BaselineResult:
    """Register ``frames`` (a :class:`registration.io.frames.FrameSource`) with the plain pipeline."""
    from registration.matching import to_grey

    w, h = frames.size
    t0 = time.perf_counter()
    base_feats = sift_features(to_grey(base))
    out = BaselineResult(gamma, (w, h), [None] * len(frames), reference_frame=reference_frame)
    camera = out.camera
    ref_feats = sift_features(corrected_grey(frames.get(reference_frame), camera))
    base_from_ref = homography(ref_feats, base_feats, config)
    return _chain_to_reference(
        frames,
        out,
        base_from_ref,
        lambda frame: homography(sift_features(corrected_grey(frame, camera)), ref_feats, config),
        time.perf_counter() - t0,
    )


def register_per_frame(
    frames, base: NDArray, gamma: float, *, config=BaselineConfig(), base_valid=None
) -> BaselineResult:
    """Plain OpenCV with every frame matched to the map on its own (no chain): full-frame SIFT
    of the corrected frame against the map's, FLANN ratio matching, MAGSAC (None where it finds
    nothing). ``base_valid``: the map's content mask (no keypoints outside it)."""
    from registration.matching import to_grey

    w, h = frames.size
    t0 = time.perf_counter()
    base_feats = sift_features(to_grey(base), mask=base_valid)
    out = BaselineResult(gamma, (w, h), [None] * len(frames))
    setup_s = time.perf_counter() - t0
    for k, frame in frames.iter():
        t1 = time.perf_counter()
        out.homographies[k] = homography(
            sift_features(corrected_grey(frame, out.camera)), base_feats, config
        )
        out.times_s.append(time.perf_counter() - t1 + (setup_s if k == 0 else 0.0))
    return _without_degenerate(out)


def register_chained(
    frames, base: NDArray, gamma: float, *, config=BaselineConfig(), base_valid=None
) -> BaselineResult:
    """Plain OpenCV chained frame to frame: frame 0 matched to the map, every later frame to
    the one before it (SIFT, FLANN, MAGSAC), their homographies multiplied; from the first frame
    that fails on, the chain is broken (None)."""
    from registration.matching import to_grey

    w, h = frames.size
    t0 = time.perf_counter()
    base_feats = sift_features(to_grey(base), mask=base_valid)
    out = BaselineResult(gamma, (w, h), [None] * len(frames))
    setup_s = time.perf_counter() - t0
    prev_feats, base_from_prev = None, None
    for k, frame in frames.iter():
        t1 = time.perf_counter()
        feats = sift_features(corrected_grey(frame, out.camera))
        if k == 0:
            base_from_prev = homography(feats, base_feats, config)
        elif base_from_prev is not None:
            prev_from_k = homography(feats, prev_feats, config)
            base_from_prev = None if prev_from_k is None else base_from_prev @ prev_from_k
        out.homographies[k] = base_from_prev
        prev_feats = feats
        out.times_s.append(time.perf_counter() - t1 + (setup_s if k == 0 else 0.0))
    return _without_degenerate(out)


def _chain_to_reference(frames, out: BaselineResult, base_from_ref, ref_from_frame, setup_s):
    """Fill ``out`` with ``base_from_ref @ ref_from_frame(frame)`` for every frame (the reference
    frame itself: ``base_from_ref``; None where either is missing) and each frame's seconds
    (the reference frame's include ``setup_s``, its features)."""
    ref = out.reference_frame
    for k, frame in frames.iter():
        t1 = time.perf_counter()
        if base_from_ref is not None:
            if k == ref:
                out.homographies[k] = base_from_ref
            else:
                ref_from_k = ref_from_frame(frame)
                if ref_from_k is not None:
                    out.homographies[k] = base_from_ref @ ref_from_k
        out.times_s.append(time.perf_counter() - t1 + (setup_s if k == ref else 0.0))
    return _without_degenerate(out)


def warp_to_base(
    frame_raw: NDArray, camera: Camera | float, base_from_corrected: NDArray, size
) -> NDArray:
    """The baseline's output image: correction (``camera``: the frame's
    :class:`registration.lens.camera.Camera` or its Harris γ), then ``cv2.warpPerspective`` into base
    pixels."""
    corrected = as_camera(camera, frame_raw).undistort(frame_raw)
    return cv2.warpPerspective(corrected, base_from_corrected, tuple(size))


@dataclass(frozen=True)
class StabiloConfig:
    """Stabilo's defaults (``stabilo/cfg/default.yaml``, tuned there for high-altitude drone
    video).

    Attributes:
        max_features: ORB keypoints per frame.
        ref_multiplier: the reference frame gets this many times ``max_features``.
        downsample: keypoints are detected on the frame resized by this, then rescaled.
        ratio: Lowe's ratio test (reference descriptors as the query).
        threshold_px: MAGSAC++ threshold, full-resolution reference-frame px.
        max_iterations, confidence: MAGSAC++ settings.
    """

    max_features: int = 2000
    ref_multiplier: float = 2.0
    downsample: float = 0.5
    ratio: float = 0.9
    threshold_px: float = 2.0
    max_iterations: int = 5000
    confidence: float = 0.999999


def _orb_features(image: NDArray, camera: Camera | float, n: int, scale: float):
    """ORB keypoints (full-resolution corrected px) and descriptors of a frame, radially
    corrected (``camera``: its :class:`registration.lens.camera.Camera` or Harris γ) and resized by
    ``scale``."""
    from registration.coords import rescale
    from registration.matching import downscale, to_grey

    grey = to_grey(image)
    grey = as_camera(camera, grey).undistort(grey)
    small = grey if scale == 1 else downscale(grey, scale)
    kps, desc = cv2.ORB_create(nfeatures=n).detectAndCompute(small, None)
    xy = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
    return rescale(xy, 1.0 / scale), desc


def stabilo_homography(ref_feats, frame_feats, config: StabiloConfig) -> NDArray | None:
    """Stabilo's ``ref_from_frame`` from two :func:`_orb_features` results, or None."""
    xy_r, dr = ref_feats
    xy_f, df = frame_feats
    if dr is None or df is None or len(dr) < 2 or len(df) < 2:
        return None
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(dr, df, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < config.ratio * p[1].distance]
    if len(good) < 4:
        return None
    dst = xy_r[[m.queryIdx for m in good]]
    src = xy_f[[m.trainIdx for m in good]]
    h, _ = cv2.findHomography(
        src, dst, cv2.USAC_MAGSAC, config.threshold_px,
        maxIters=config.max_iterations, confidence=config.confidence,
    )  # fmt: skip
    return h


def register_stabilo(
    frames,
    base_from_ref: NDArray | None,
    gamma: float,
    *,
    reference_frame: int = 0,
    config: StabiloConfig = StabiloConfig(),
) -> BaselineResult:
    """Register ``frames`` to the reference frame with Stabilo's recipe (module doc), and to the
    base through ``base_from_ref`` (corrected reference px -> base px, e.g. the plain OpenCV
    pipeline's ``homographies[reference_frame]``). ``times_s[k]``: seconds for frame ``k``
    (decoding excluded; the reference frame's: its features)."""
    w, h = frames.size
    t0 = time.perf_counter()
    n_ref = round(config.max_features * config.ref_multiplier)
    out = BaselineResult(gamma, (w, h), [None] * len(frames), reference_frame=reference_frame)
    camera = out.camera
    ref_feats = _orb_features(frames.get(reference_frame), camera, n_ref, config.downsample)
    return _chain_to_reference(
        frames,
        out,
        base_from_ref,
        lambda frame: stabilo_homography(
            ref_feats, _orb_features(frame, camera, config.max_features, config.downsample), config
        ),
        time.perf_counter() - t0,
    )
