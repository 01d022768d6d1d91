"""Frame-to-frame links for the sequence adjustment: the same ground points found in two frames
(beyond the paper).

A grid of textured probes of frame ``k`` is carried into frame ``l`` through the two frames'
current models and the map, and each probe's patch is found there by normalised
cross-correlation around that prediction (:func:`registration.matching.find_probes`). A robust
homography between the probes and their measurements (in corrected px, where a view of flat
ground is one) then drops what moved on its own (cars) or stands off the ground plane far
enough to matter (roofs seen from two places).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.adjustment.solve import FrameLinks
from registration.matching import ProbeConfig, find_probes, textured_probes

# A link survives when a homography of the pair's measured points explains it within this
# many corrected px (RANSAC, then least squares on the inliers), on frames of up to this
# diagonal; on larger frames within the same share of the diagonal. What a pair's rolling
# shutter and terrain bend away from one homography grows with the frame's pixels, as a roof's
# parallax does: at 1 px a 2560x1920 flight's homographies left a third of its ground's links
# out (75th percentile 1.5 px), and what they kept lay in parts of the frames.
LINK_INLIER_PX = 1.0
LINK_INLIER_DIAGONAL_PX = 1600.0
MIN_LINKS = 8
# Links by Lucas-Kanade are kept when it finds at least this share of the probes and the
# homography keeps at least this share of what it found; else the pair is measured again by
# correlation (which finds the same ground where Lucas-Kanade found it).
FLOW_SHARE = 0.5
# How links are kept, as part of their stored key (:func:`link_key`): links an earlier release
# stored under other rules are measured again rather than mixed with this release's (2: the
# homography's tolerance grows with frames over 1600 px of diagonal, and the correlation search
# follows what Lucas-Kanade found).
LINK_RULES = 2
# A Lucas-Kanade probe whose mean intensity difference exceeds this many times the pair's
# median is a changed patch, not ground.
CHANGED_PATCH = 2.0


def measure_links(
    grey_k: NDArray,
    grey_l: NDArray,
    k: int,
    l: int,  # noqa: E741 (the second frame)
    model_k,
    model_l,
    lens,
    config: ProbeConfig | None = None,
    probes_k: NDArray | None = None,
    matcher: str = "flow",
) -> FrameLinks:
    """Links between raw frames ``k`` and ``l`` (grey ``(H, W)`` uint8) predicted through their
    models (``base_from_corrected``) and the lens (raw <-> corrected px); none when fewer than
    ``MIN_LINKS`` survive. ``probes_k``: frame ``k``'s
    :func:`registration.matching.textured_probes`, when the caller keeps them. ``matcher``:
    ``"flow"`` (pyramidal Lucas-Kanade from the prediction, every probe at once) or ``"ncc"``
    (each probe's patch searched by normalised cross-correlation, with a uniqueness test)."""
    cfg = config or ProbeConfig()
    p = textured_probes(grey_k, cfg) if probes_k is None else probes_k
    if len(p) < MIN_LINKS:
        return FrameLinks(k, l, np.zeros((0, 2)), np.zeros((0, 2)))
    q = lens.raw_from_corrected(model_l.inverse(model_k.apply(lens.corrected_from_raw(p))))
    known = np.isfinite(q).all(axis=1)
    p, q = p[known], q[known]
    src_k, src_l, found = _robust_links(grey_k, grey_l, p, q, lens, cfg, matcher)
    if matcher == "flow" and (found < FLOW_SHARE * len(p) or len(src_k) < FLOW_SHARE * found):
        # Lucas-Kanade goes astray where the prediction is far off (a frame whose own
        # registration went wrong) or the patches changed: the search by correlation then.
        src_k, src_l, _ = _robust_links(grey_k, grey_l, p, q, lens, cfg, "ncc")
    return FrameLinks(k, l, src_k, src_l)


def link_key(model_k, model_l, lens, config: ProbeConfig, matcher: str) -> NDArray[np.uint8]:
    """``(20,)`` uint8: what :func:`measure_links` measures a pair through (the two models, the
    lens, the probes' settings and the matcher, and :data:`LINK_RULES`), as a SHA-1 digest.
    Links stored with their key stand for a measurement again exactly when the key is the same:
    the frames themselves are the run's (a result folder checks its frames' identity)."""
    text = json.dumps(
        [model_k.to_dict(), model_l.to_dict(), repr(lens), repr(config), matcher, LINK_RULES],
        sort_keys=True,
    )
    return np.frombuffer(hashlib.sha1(text.encode()).digest(), np.uint8).copy()


# Arrays of stored links in a frame's ``.npz`` (:func:`links_to_arrays`), three however many
# pairs (reading an array member costs more than its bytes here).
LINKS_PREFIX = "links_"


def links_to_arrays(
    pairs: Sequence[tuple[FrameLinks, NDArray[np.uint8]]],
) -> dict[str, NDArray]:
    """The arrays that store ``pairs`` of links, each with its key (:func:`link_key`):
    ``links_pairs`` ``(n, 4)`` int64 (k, l, first row, end row), ``links_points`` ``(M, 4)``
    float64 (``src_k``, ``src_l``, corrected px) and ``links_keys`` ``(n, 20)`` uint8; none
    without pairs."""
    if not pairs:
        return {}
    rows, points, keys, n = [], [], [], 0
    for links, key in pairs:
        m = len(links.src_k)
        rows.append((links.k, links.l, n, n + m))
        points.append(np.c_[links.src_k, links.src_l].reshape(m, 4))
        keys.append(np.asarray(key, np.uint8).reshape(20))
        n += m
    return {
        LINKS_PREFIX + "pairs": np.array(rows, np.int64),
        LINKS_PREFIX + "points": np.concatenate(points).astype(np.float64),
        LINKS_PREFIX + "keys": np.stack(keys),
    }


def links_from_arrays(arrays) -> dict[tuple[int, int], tuple[FrameLinks, NDArray[np.uint8]]]:
    """The links stored in ``arrays`` (a name -> array mapping, :func:`links_to_arrays`) by
    frame pair ``(k, l)``, each with its key."""
    if LINKS_PREFIX + "pairs" not in arrays:
        return {}
    points = np.asarray(arrays[LINKS_PREFIX + "points"], np.float64).reshape(-1, 4)
    keys = np.asarray(arrays[LINKS_PREFIX + "keys"], np.uint8)
    out = {}
    for (k, l, a, b), key in zip(arrays[LINKS_PREFIX + "pairs"], keys, strict=True):  # noqa: E741
        links = FrameLinks(int(k), int(l), points[a:b, :2].copy(), points[a:b, 2:].copy())
        out[(int(k), int(l))] = links, key
    return out


def link_inlier_px(frame_size: tuple[int, int]) -> float:
    """How far (corrected px) a link may lie from its pair's homography, for frames of
    ``(width, height)`` px: :data:`LINK_INLIER_PX`, more on frames with a diagonal over
    :data:`LINK_INLIER_DIAGONAL_PX`, in proportion."""
    return LINK_INLIER_PX * max(1.0, float(np.hypot(*frame_size)) / LINK_INLIER_DIAGONAL_PX)


def _robust_links(grey_k, grey_l, p, q, lens, cfg: ProbeConfig, matcher: str):
    """The probes ``p`` of frame k measured in frame l around ``q`` (raw px) and kept where a
    homography of all of them explains them (:func:`link_inlier_px`): ``(src_k, src_l,
    found)``, the links in corrected px (empty when fewer than ``MIN_LINKS`` survive) and how
    many probes were found before the homography's test."""
    m, ok = (_flow_probes if matcher == "flow" else find_probes)(grey_k, grey_l, p, q, cfg)
    found = int(ok.sum())
    empty = np.zeros((0, 2)), np.zeros((0, 2)), found
    src_k, src_l = lens.corrected_from_raw(p[ok]), lens.corrected_from_raw(m[ok])
    if len(src_k) < MIN_LINKS:
        return empty
    tol = link_inlier_px(grey_l.shape[1::-1])
    h, inl = cv2.findHomography(src_k, src_l, cv2.RANSAC, tol, maxIters=2000)
    if h is None:
        return empty
    inl = inl.ravel().astype(bool)
    h, _ = cv2.findHomography(src_k[inl], src_l[inl], 0)
    pred = cv2.perspectiveTransform(src_k.reshape(-1, 1, 2), h).reshape(-1, 2)
    keep = np.hypot(*(pred - src_l).T) <= tol
    if keep.sum() < MIN_LINKS:
        return empty
    return src_k[keep], src_l[keep], found


def _flow_probes(grey_k, grey_l, p, q, cfg: ProbeConfig):
    """Where each probe's patch lies in ``grey_l``: pyramidal Lucas-Kanade from the prediction
    ``q``, the patch as its window (``template_px``), one pyramid level over ``search_px``. As
    :func:`registration.matching.find_probes` returns: ``(N, 2)`` px, NaN where not found, and
    the found mask. 4-5x faster than the NCC search on the real flyover, within 0.06 px of it
    at the median (0.11 at the 90th percentile)."""
    if not len(p):
        return np.zeros((0, 2)), np.zeros(0, bool)
    half = cfg.template_px // 2
    found, status, err = cv2.calcOpticalFlowPyrLK(
        grey_k, grey_l, p.astype(np.float32).reshape(-1, 1, 2),
        q.astype(np.float32).reshape(-1, 1, 2).copy(), winSize=(2 * half + 1, 2 * half + 1),
        maxLevel=1, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01),
    )  # fmt: skip
    m = found.reshape(-1, 2).astype(np.float64)
    hb, wb = grey_l.shape
    ok = status.ravel().astype(bool) & np.isfinite(m).all(axis=1)
    # A patch that changed (a car moved into part of it) matches worse than the ground does:
    # its mean intensity difference far above the pair's typical one.
    err = err.ravel()
    if ok.any():
        ok &= err <= CHANGED_PATCH * max(float(np.median(err[ok])), 1.0)
    # Within the search reach of the prediction, and with the whole patch in the image.
    ok &= np.hypot(*(m - q).T) <= cfg.search_px
    ok &= (m[:, 0] >= half) & (m[:, 0] < wb - half) & (m[:, 1] >= half) & (m[:, 1] < hb - half)
    m[~ok] = np.nan
    return m, ok
