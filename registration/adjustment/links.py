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

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.adjustment.solve import FrameLinks
from registration.matching import ProbeConfig, find_probes, textured_probes

# A link survives when a homography of the pair's measured points explains it within this
# many corrected px (RANSAC, then least squares on the inliers).
LINK_INLIER_PX = 1.0
MIN_LINKS = 8


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
) -> FrameLinks:
    """Links between raw frames ``k`` and ``l`` (grey ``(H, W)`` uint8) predicted through their
    models (``base_from_corrected``) and the lens (raw <-> corrected px); none when fewer than
    ``MIN_LINKS`` survive. ``probes_k``: frame ``k``'s
    :func:`registration.matching.textured_probes`, when the caller keeps them."""
    cfg = config or ProbeConfig()
    p = textured_probes(grey_k, cfg) if probes_k is None else probes_k
    empty = FrameLinks(k, l, np.zeros((0, 2)), np.zeros((0, 2)))
    if len(p) < MIN_LINKS:
        return empty
    q = lens.raw_from_corrected(model_l.inverse(model_k.apply(lens.corrected_from_raw(p))))
    known = np.isfinite(q).all(axis=1)
    p, q = p[known], q[known]
    m, ok = find_probes(grey_k, grey_l, p, q, cfg)
    src_k, src_l = lens.corrected_from_raw(p[ok]), lens.corrected_from_raw(m[ok])
    if len(src_k) < MIN_LINKS:
        return empty
    h, inl = cv2.findHomography(src_k, src_l, cv2.RANSAC, LINK_INLIER_PX, maxIters=2000)
    if h is None:
        return empty
    inl = inl.ravel().astype(bool)
    h, _ = cv2.findHomography(src_k[inl], src_l[inl], 0)
    pred = cv2.perspectiveTransform(src_k.reshape(-1, 1, 2), h).reshape(-1, 2)
    keep = np.hypot(*(pred - src_l).T) <= LINK_INLIER_PX
    if keep.sum() < MIN_LINKS:
        return empty
    return FrameLinks(k, l, src_k[keep], src_l[keep])
