"""Long edges of an image that may be straight in the world, for γ estimation (paper section 3).

The paper picked γ by eye so that streets look straight. :mod:`registration.lens.gamma_from_lines` does it
automatically from edges found here, in two passes:

1. *Pieces*: line segments from OpenCV's FastLineDetector (LSD as fallback) on the image
   downscaled to ``work_width``, each sampled every few pixels and snapped to the sub-pixel
   gradient maximum across it. Pixels outside an optional validity mask (and a margin around
   them) give no samples, so a frame's blank border never becomes an edge.
2. *Raw chains* (:func:`chain_polylines`): pieces whose ends meet nearly head-on, with the same
   edge polarity, are chained into long edges that may curve (a straight street seen through a
   distorting lens). Good enough for a first γ.
3. *Corrected lines* (:func:`link_collinear`): with a first γ, every piece is mapped to the
   corrected frame, where a straight world line is straight again; pieces that are collinear
   there (same polarity, a merged straightness within a fraction of a pixel, gaps up to a third
   of the frame) are grouped into one line. A road edge interrupted by parked cars, or the two
   sides of an intersection, become one line across the frame: edges far from the centre and
   long carry almost all of γ's information (a line through the centre is straight at any γ).

All lengths in :class:`AutoLineConfig` are in pixels of the working image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial import cKDTree

from registration.coords import rescale
from registration.lens.radial import RadialModel


@dataclass(frozen=True)
class AutoLineConfig:
    """Edge detection, chaining and linking for automatic γ estimation.

    Lengths are in pixels of the working image (the input downscaled to ``work_width``).
    """

    work_width: int = 1280  # px; wider images are downscaled (INTER_AREA) for detection
    min_segment_px: float = 12.0  # FastLineDetector length_threshold
    fld_distance_px: float = 1.41421356  # FLD distance_threshold (OpenCV default)
    # FLD Canny thresholds (OpenCV: 50, 50; lower finds soft edges)
    fld_canny: tuple[float, float] = (20.0, 40.0)
    link_gap_px: float = 60.0  # raw chains: largest gap between chained ends (cars, dashes)
    link_overlap_px: float = 4.0  # raw chains: largest overlap of chained segment ends
    link_lateral_px: float = 1.5  # raw chains: largest sideways offset of the next segment's end
    link_angle_deg: float = 12.0  # raw chains: largest direction change between segments
    min_edge_fraction: float = 0.08  # shortest kept edge or line, fraction of the diagonal
    max_edges: int = 200  # longest edges kept
    sample_step_px: float = 3.0  # spacing of edge samples
    max_points_per_edge: int = 80  # longer edges are thinned evenly (fit cost ~ points)
    snap_radius_px: float = 2.0  # sub-pixel snapping search, either side of the segment
    blur_sigma_px: float = 1.0  # Gaussian blur before the gradient for snapping
    mask_margin_px: float = 5.0  # samples closer than this to an invalid pixel are dropped
    inlier_px: float = 0.5  # robust fit: a line straighter than this RMS (px) is usable
    # Corrected-frame linking (pass 3).
    min_piece_px: float = 15.0  # shortest piece that takes part
    piece_angle_deg: float = 2.0  # largest angle between two linked pieces (corrected frame)
    piece_lateral_px: float = 2.0  # largest offset of a piece from the other's line (raw px)
    max_gap_fraction: float = 0.35  # largest gap between linked pieces, fraction of diagonal
    gap_ratio: float = 3.0  # ... and at most this many times the two pieces' summed length
    link_rms_px: float = 0.5  # a linked group must stay this straight (RMS, raw px)
    max_points_per_line: int = 160  # linked lines are thinned evenly to this many points


def _to_grey(image: NDArray) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[:, :, :3]
        if img.shape[2] != 3:
            raise ValueError(f"image must have 1, 3 or 4 channels, got {img.shape[2]}")
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY)
    if img.ndim != 2:
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {img.shape}")
    if img.dtype != np.uint8:
        f = img.astype(np.float64)
        lo, hi = np.nanmin(f), np.nanmax(f)
        img = (
            np.zeros(f.shape, np.uint8)
            if hi <= lo
            else ((f - lo) * (255.0 / (hi - lo))).astype(np.uint8)
        )
    return img


def detect_segments(grey: NDArray[np.uint8], config: AutoLineConfig) -> NDArray[np.float64]:
    """``(S, 4)`` line segments ``x1, y1, x2, y2`` (FastLineDetector; LSD when unavailable)."""
    try:
        fld = cv2.ximgproc.createFastLineDetector(
            int(round(config.min_segment_px)),
            float(config.fld_distance_px),
            float(config.fld_canny[0]),
            float(config.fld_canny[1]),
            3,
            False,
        )
        segs = fld.detect(grey)
    except AttributeError:  # opencv without contrib
        segs = cv2.createLineSegmentDetector().detect(grey)[0]
        if segs is not None:
            s = segs.reshape(-1, 4)
            keep = np.hypot(s[:, 2] - s[:, 0], s[:, 3] - s[:, 1]) >= config.min_segment_px
            segs = s[keep]
    if segs is None or len(segs) == 0:
        return np.zeros((0, 4))
    return np.asarray(segs, np.float64).reshape(-1, 4)


def chain_segments(
    segments: NDArray, config: AutoLineConfig, polarity: NDArray | None = None
) -> list[list[tuple[int, bool]]]:
    """Greedily chain segments whose ends meet nearly head-on into long (possibly curved) edges.

    Args:
        segments: ``(S, 4)`` ``x1, y1, x2, y2``.
        config: linking tolerances.
        polarity: optional ``(S,)`` +1/-1 gradient sign across each segment (left normal of its
            native direction); chained segments must agree along the chain (dark-to-bright
            stays dark-to-bright), so the two edges of a thin line are never joined.

    Returns:
        chains, each a list of ``(segment index, reversed)`` in order along the edge.
    """
    s = np.asarray(segments, np.float64).reshape(-1, 4)
    n = len(s)
    if n == 0:
        return []
    candidates = _facing_end_pairs(s, config, polarity)
    return _walk_chains(_link_ends(candidates, n), n)


def _facing_end_pairs(
    s: NDArray[np.float64], config: AutoLineConfig, polarity: NDArray | None
) -> list[tuple[int, int]]:
    """Pairs of segment ends that may be chained, best first (short gap, head-on).

    Ends are numbered ``2 * segment + end`` (end 0 = ``x1, y1``, end 1 = ``x2, y2`` of the
    ``(S, 4)`` segments ``s``, px). A pair qualifies when the ends belong to different segments,
    their outward directions are within ``link_angle_deg`` of opposite, the gap along them is
    between ``-link_overlap_px`` and ``link_gap_px``, each end's sideways offset is at most
    ``link_lateral_px`` and (with ``polarity``, ``(S,)`` +1/-1) the polarities agree along the
    chain.
    """
    p = np.stack([s[:, :2], s[:, 2:]], axis=1)  # (n, 2 ends, 2)
    u = p[:, 1] - p[:, 0]
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    # Outward direction at each end: end 0 points along -u, end 1 along +u.
    out = np.stack([-u, u], axis=1)  # (n, 2, 2)
    ends = p.reshape(-1, 2)
    outs = out.reshape(-1, 2)
    tree = cKDTree(ends)
    pairs = tree.query_pairs(config.link_gap_px + config.link_overlap_px, output_type="ndarray")
    cos_max = np.cos(np.deg2rad(config.link_angle_deg))
    if not len(pairs):
        return []
    a, b = pairs[:, 0], pairs[:, 1]
    ok = (a // 2) != (b // 2)
    a, b = a[ok], b[ok]
    g = ends[b] - ends[a]
    oa, ob = outs[a], outs[b]
    # Ends meet head-on: outward directions opposite, gap along the direction, small offset.
    facing = -np.sum(oa * ob, axis=1) >= cos_max
    along = np.sum(g * oa, axis=1)
    lat_a = np.abs(oa[:, 0] * g[:, 1] - oa[:, 1] * g[:, 0])
    lat_b = np.abs(ob[:, 0] * g[:, 1] - ob[:, 1] * g[:, 0])
    ok = (
        facing
        & (along >= -config.link_overlap_px)
        & (along <= config.link_gap_px)
        & (lat_a <= config.link_lateral_px)
        & (lat_b <= config.link_lateral_px)
    )
    if polarity is not None:
        # Along the chain, a segment left through its end 1 (or entered at end 0) runs in its
        # native direction.
        pol = np.asarray(polarity, np.float64)
        pa = pol[a // 2] * np.where(a % 2 == 1, 1.0, -1.0)
        pb = pol[b // 2] * np.where(b % 2 == 0, 1.0, -1.0)
        ok &= pa == pb
    score = np.linalg.norm(g, axis=1) + 10.0 * (1 + np.sum(oa * ob, axis=1))
    a_ok, b_ok = a[ok], b[ok]
    order = np.argsort(score[ok], kind="stable")
    return list(zip(a_ok[order].tolist(), b_ok[order].tolist(), strict=True))


def _link_ends(candidates: list[tuple[int, int]], n: int) -> dict[int, int]:
    """Link end pairs greedily in the order given, each end at most once and never closing a
    loop among the ``n`` segments: ``{end id: linked end id}`` (both directions)."""
    parent, find = _union_find(n)
    link = {}  # end id -> linked end id
    for ea, eb in candidates:
        if ea in link or eb in link:
            continue
        ra, rb = find(ea // 2), find(eb // 2)
        if ra == rb:
            continue
        parent[ra] = rb
        link[ea], link[eb] = eb, ea
    return link


def _walk_chains(link: dict[int, int], n: int) -> list[list[tuple[int, bool]]]:
    """The chains of the ``n`` segments joined by ``link`` (:func:`_link_ends`), in order of
    their lowest segment index, each a list of ``(segment index, reversed)`` from one extremity
    to the other."""
    chains, seen = [], np.zeros(n, bool)
    for start in range(n):
        if seen[start]:
            continue
        # Walk to one extremity of the chain, then collect forwards.
        seg, entry = start, 0
        for _ in range(n):
            other = link.get(2 * seg + entry)
            if other is None:
                break
            seg, entry = other // 2, 1 - other % 2
        chain = []
        for _ in range(n):
            seen[seg] = True
            chain.append((seg, entry == 1))  # entering at end 1 means traversed reversed
            other = link.get(2 * seg + (1 - entry))
            if other is None:
                break
            seg, entry = other // 2, other % 2
        chains.append(chain)
    return chains


def _sample(img: NDArray[np.float32], q: NDArray) -> NDArray:
    """Bilinear samples of ``img`` at ``(..., 2)`` positions ``q``."""
    flat = q.reshape(-1, 2)
    v = ndimage.map_coordinates(img, [flat[:, 1], flat[:, 0]], order=1, mode="nearest")
    return v.reshape(q.shape[:-1])


def _segment_polarity(gx, gy, segs: NDArray) -> NDArray:
    """+1/-1: sign of the intensity gradient across each segment along its left normal."""
    a, b = segs[:, :2], segs[:, 2:]
    d = (b - a) / np.maximum(np.linalg.norm(b - a, axis=1, keepdims=True), 1e-12)
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)
    t = np.linspace(0.2, 0.8, 5)
    q = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]
    g = _sample(gx, q) * nrm[:, None, 0] + _sample(gy, q) * nrm[:, None, 1]
    return np.where(np.median(g, axis=1) >= 0, 1.0, -1.0)


def _snap_points(gx, gy, pts: NDArray, normal: NDArray, radius: float) -> tuple[NDArray, NDArray]:
    """Move each point along its ``normal`` (``(2,)`` or ``(N, 2)``) to the sub-pixel maximum
    of the gradient along it.

    The gradient is projected on ``normal`` (signed), so a sample on one side of a thin line
    never jumps to the opposite-polarity edge on the other side.
    """
    normal = np.broadcast_to(normal, pts.shape)
    offsets = np.arange(-radius, radius + 0.25, 0.5)
    q = pts[:, None, :] + offsets[None, :, None] * normal[:, None, :]
    vals = _sample(gx, q) * normal[:, None, 0] + _sample(gy, q) * normal[:, None, 1]
    i = np.argmax(vals, axis=1)
    interior = (i > 0) & (i < len(offsets) - 1)
    ii = np.clip(i, 1, len(offsets) - 2)
    r = np.arange(len(pts))
    y0, y1, y2 = vals[r, ii - 1], vals[r, ii], vals[r, ii + 1]
    den = y0 - 2 * y1 + y2
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(den < 0, 0.5 * (y0 - y2) / den, 0.0)
    t = offsets[ii] + np.clip(frac, -0.5, 0.5) * 0.5
    ok = interior & (den < 0) & (y1 > 0)
    return pts + t[:, None] * normal, ok


def _work_scale(width: int, config: AutoLineConfig) -> float:
    return min(1.0, config.work_width / width)


@dataclass(frozen=True)
class EdgePieces:
    """Snapped line segments of one image, in the input image's pixel coordinates.

    Attributes:
        points: per piece, ``(n_i, 2)`` snapped samples in order along the segment.
        bright: ``(S, 2)`` unit normal of each piece pointing to its brighter side.
        chains: raw-domain chains (:func:`chain_segments`): ``(piece index, reversed)`` in
            order along each chain.
        scale: working scale (working px = input px x ``scale``).
        width, height: input image size.
    """

    points: list[NDArray[np.float64]]
    bright: NDArray[np.float64]
    chains: list[list[tuple[int, bool]]]
    scale: float
    width: int
    height: int

    @property
    def diagonal(self) -> float:
        return float(np.hypot(self.width, self.height))


def _valid_distance(mask: NDArray | None, work_size: tuple[int, int]) -> NDArray | None:
    """Distance (working px) of every working pixel from the nearest invalid one; None = no
    mask. A working pixel is invalid when any input pixel under it is."""
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.dtype != bool:
        m = m != 0
    if m.all():
        return None
    w, h = work_size
    small = m.astype(np.uint8) * 255
    if small.shape[::-1] != (w, h):
        small = cv2.resize(small, (w, h), interpolation=cv2.INTER_AREA)
    valid = (small == 255).astype(np.uint8)
    return cv2.distanceTransform(valid, cv2.DIST_L2, 3)


def detect_pieces(
    image: NDArray, config: AutoLineConfig | None = None, mask: NDArray | None = None
) -> EdgePieces:
    """Line segments of ``image``, snapped sub-pixel, with their raw-domain chains.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` image (BGR order for colour; any dtype).
        config: detection settings.
        mask: optional ``(H, W)`` validity mask (True / non-zero = real image content);
            samples within ``config.mask_margin_px`` working pixels of invalid ones are dropped.

    Raises:
        ValueError: a mask whose shape differs from the image's.
    """
    config = config or AutoLineConfig()
    grey = _to_grey(image)
    h, w = grey.shape
    if mask is not None and np.shape(mask) != (h, w):
        raise ValueError(f"mask is {np.shape(mask)} but the image is {(h, w)} (H, W)")
    scale = _work_scale(w, config)
    work = (
        grey
        if scale == 1.0
        else cv2.resize(grey, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    )
    dist = _valid_distance(mask, (work.shape[1], work.shape[0]))
    empty = EdgePieces([], np.zeros((0, 2)), [], scale, w, h)
    segs = detect_segments(work, config)
    if len(segs) == 0:
        return empty
    blurred = cv2.GaussianBlur(work.astype(np.float32), (0, 0), config.blur_sigma_px)
    gx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3)
    polarity = _segment_polarity(gx, gy, segs)
    a, b = segs[:, :2], segs[:, 2:]
    length = np.linalg.norm(b - a, axis=1)
    m = np.maximum((length // config.sample_step_px).astype(int), 1)
    owner = np.repeat(np.arange(len(segs)), m)
    first = np.r_[0, np.cumsum(m)[:-1]]
    # Stay half a step inside each segment: FLD's end points can overshoot corners.
    t = (np.arange(len(owner)) - first[owner] + 0.5) / m[owner]
    pts = a[owner] + t[:, None] * (b - a)[owner]
    d = (b - a) / np.maximum(length, 1e-12)[:, None]
    # Normal pointing up the intensity gradient (towards the brighter side).
    bright = np.stack([-d[:, 1], d[:, 0]], axis=1) * polarity[:, None]
    snapped, ok = _snap_points(gx, gy, pts, bright[owner], config.snap_radius_px)
    if dist is not None:
        ij = np.clip(np.round(snapped).astype(int), 0, [dist.shape[1] - 1, dist.shape[0] - 1])
        ok &= dist[ij[:, 1], ij[:, 0]] >= config.mask_margin_px
    keep = np.bincount(owner, ok, len(segs)) >= 3
    points = np.split(snapped, first[1:])
    oks = np.split(ok, first[1:])
    kept_pts = [p[o] for p, o, k in zip(points, oks, keep, strict=True) if k]
    chains = [
        [(int(k), bool(rev)) for k, rev in chain]
        for chain in chain_segments(segs[keep], config, polarity[keep])
    ]
    kept_bright = bright[keep].reshape(-1, 2)
    if scale != 1.0:
        kept_pts = [rescale(p, 1.0 / scale) for p in kept_pts]
    return EdgePieces(kept_pts, kept_bright, chains, scale, w, h)


def _thin(pts: NDArray, n_max: int) -> NDArray:
    """Evenly thinned to at most ``n_max`` points, keeping both ends."""
    if len(pts) <= n_max:
        return pts
    return pts[np.round(np.linspace(0, len(pts) - 1, n_max)).astype(int)]


def _span(pts: NDArray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))


def chain_polylines(pieces: EdgePieces, config: AutoLineConfig) -> list[NDArray[np.float64]]:
    """The raw chains as polylines (input px), longest first, at least ``min_edge_fraction`` of
    the diagonal long and at most ``max_edges`` of them."""
    min_len = config.min_edge_fraction * pieces.diagonal
    edges = []
    for chain in pieces.chains:
        pts = np.concatenate(
            [pieces.points[k][::-1] if rev else pieces.points[k] for k, rev in chain]
        )
        if len(pts) < 3:
            continue
        span = _span(pts)
        if span >= min_len:
            edges.append((span, pts))
    edges.sort(key=lambda e: -e[0])
    return [_thin(p, config.max_points_per_edge) for _, p in edges[: config.max_edges]]


def detect_edges(
    image: NDArray, config: AutoLineConfig | None = None, mask: NDArray | None = None
) -> list[NDArray[np.float64]]:
    """Long (possibly curved) edges of ``image`` as raw-pixel polylines, longest first.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` image (BGR order for colour).
        config: detection settings.
        mask: optional validity mask (see :func:`detect_pieces`).
    """
    config = config or AutoLineConfig()
    return chain_polylines(detect_pieces(image, config, mask), config)


def _union_find(n: int):
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    return parent, find


def link_collinear(
    pieces: EdgePieces, model: RadialModel, config: AutoLineConfig
) -> list[NDArray[np.float64]]:
    """Group pieces that are collinear in the frame corrected by ``model`` into lines.

    Each piece's samples are mapped to the corrected frame and weighted by the inverse squared
    magnification across the piece, so every straightness below is in raw pixels. Two pieces are
    candidates when their directions differ by at most ``piece_angle_deg``, each lies within
    ``piece_lateral_px`` (plus the angle tolerance over the gap) of the other's line, they face
    the same way (polarity) and the gap between them is at most ``max_gap_fraction`` of the
    diagonal and ``gap_ratio`` times their summed length; candidates are merged greedily, best
    first, while the merged group's weighted total-least-squares RMS stays within
    ``link_rms_px`` (from running moments, so each test is O(1)).

    Lines are found where they are straight under ``model``, which pulls a refit towards the γ
    they were linked at (linked at the truth + δ, real frames refit at about the truth + δ/2).

    Returns:
        raw-pixel polylines (input px), ordered along each line, longest first; lines shorter
        than ``min_edge_fraction`` of the diagonal are dropped, longer ones thinned to
        ``max_points_per_line``.
    """
    s = pieces.scale
    min_piece = config.min_piece_px / s
    idx = [
        i
        for i, p in enumerate(pieces.points)
        if len(p) >= 3 and np.linalg.norm(p[-1] - p[0]) >= min_piece
    ]
    if not idx:
        return []
    cp = _corrected_pieces(pieces, idx, model)
    tau2 = (config.link_rms_px / s) ** 2
    candidates = _collinear_pairs(cp, pieces, config, tau2)
    gmom, find = _merge_groups(candidates, cp.mom, tau2)
    return _group_lines(cp, gmom, find, tau2, pieces.diagonal, config)


@dataclass(frozen=True)
class _CorrectedPieces:
    """The ``L`` pieces taking part in :func:`link_collinear`, seen in the corrected frame
    (corrected px relative to the model's centre unless noted).

    Attributes:
        raw: the pieces' ``(N_i, 2)`` raw samples (input px).
        q: ``(N, 2)`` all samples, corrected (0 where the model is undefined), piece by piece.
        first, last: ``(L,)`` index in ``q`` of each piece's first and last sample.
        d, nrm: ``(L, 2)`` unit direction (first to last sample) and its normal ``(-dy, dx)``.
        mid: ``(L, 2)`` midpoint of the first and last sample.
        half_len: ``(L,)`` half the distance from the first to the last sample.
        mag_mid: ``(L,)`` RMS magnification across the piece (corrected px per raw px).
        mom: ``(L, 6)`` weighted moments ``(W, Wx, Wy, Wxx, Wxy, Wyy)`` (:func:`_piece_moments`).
        bad: ``(L,)`` the piece has a sample beyond the model's validity (takes no part).
        bright: ``(L, 2)`` the bright-side normal (raw; radial maps keep it on the same side).
    """

    raw: list[NDArray]
    q: NDArray
    first: NDArray
    last: NDArray
    d: NDArray
    nrm: NDArray
    mid: NDArray
    half_len: NDArray
    mag_mid: NDArray
    mom: NDArray
    bad: NDArray
    bright: NDArray


def _corrected_pieces(pieces: EdgePieces, idx: list[int], model: RadialModel) -> _CorrectedPieces:
    """The pieces ``idx`` of ``pieces`` mapped to the frame corrected by ``model``."""
    raw = [pieces.points[i] for i in idx]
    counts = np.array([len(p) for p in raw])
    L = len(raw)
    owner = np.repeat(np.arange(L), counts)
    pts = np.concatenate(raw)
    first = np.r_[0, np.cumsum(counts)[:-1]]
    last = first + counts - 1
    c0 = np.asarray(model.c)
    cor = model.corrected_from_raw(pts)
    finite = np.isfinite(cor).all(axis=1)
    q = np.where(finite[:, None], cor, 0.0) - c0
    # Piece directions in the corrected frame (first to last sample).
    d = q[last] - q[first]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)
    # Moments per piece: (W, Wx, Wy, Wxx, Wxy, Wyy), relative to the centre.
    mom, ok, mag2 = _piece_moments(model, pts, owner, L, nrm)
    # Pieces with any undefined sample (beyond the model's validity) do not take part.
    bad = np.bincount(owner, ~ok, L) > 0
    mag_mid = np.sqrt(np.bincount(owner, np.where(ok, mag2, 0), L) / counts)
    # Bright side in the corrected frame: the raw bright normal, mapped (radial maps keep it
    # on the same side of the piece).
    bright = pieces.bright[idx]
    mid = 0.5 * (q[first] + q[last])
    half_len = 0.5 * np.linalg.norm(q[last] - q[first], axis=1)
    return _CorrectedPieces(raw, q, first, last, d, nrm, mid, half_len, mag_mid, mom, bad, bright)


def _collinear_pairs(
    cp: _CorrectedPieces, pieces: EdgePieces, config: AutoLineConfig, tau2: float
) -> list[tuple[int, int]]:
    """Pairs ``(i, j)`` of corrected pieces that may be linked (:func:`link_collinear`'s
    tests), best first (smallest lateral offset, raw px, then gap); ``tau2``: the largest
    weighted mean squared distance from a line, raw px²."""
    s = pieces.scale
    d, nrm, mid, half_len, mag_mid, bad = cp.d, cp.nrm, cp.mid, cp.half_len, cp.mag_mid, cp.bad
    reach = config.max_gap_fraction * pieces.diagonal
    # Offsets of collinear pieces differ by their lateral tolerance plus the angle tolerance
    # over their distance (at most the reach plus both lengths).
    angle = np.deg2rad(config.piece_angle_deg)
    far = reach * max(float(np.nanpercentile(mag_mid, 90)), 1.0) + 4 * float(np.median(half_len))
    pairs = _candidate_pairs(mid, d, angle, config.piece_lateral_px / s + far * np.tan(angle))
    if not len(pairs):
        return []
    a, b = pairs[:, 0], pairs[:, 1]
    ok = ~bad[a] & ~bad[b]
    # Same polarity: the bright normals point the same way once directions are aligned.
    ok &= np.sum(cp.bright[a] * cp.bright[b], axis=1) > 0
    g = mid[b] - mid[a]
    with np.errstate(invalid="ignore", divide="ignore"):
        lat_b = np.abs(np.sum(g * nrm[a], axis=1)) / mag_mid[b]
        lat_a = np.abs(np.sum(g * nrm[b], axis=1)) / mag_mid[a]
        along = np.abs(np.sum(g * d[a], axis=1))
        gap = (along - half_len[a] - half_len[b]) / np.sqrt(mag_mid[a] * mag_mid[b])
        raw_len = 2 * (half_len[a] / mag_mid[a] + half_len[b] / mag_mid[b])
    # A short piece's direction is uncertain: the lateral tolerance grows with distance.
    tol = config.piece_lateral_px / s + np.maximum(gap, 0) * np.tan(
        np.deg2rad(config.piece_angle_deg)
    )
    ok &= (lat_a <= tol) & (lat_b <= tol)
    # Short pieces are weak evidence of a line: they bridge only short gaps.
    max_gap = np.minimum(reach, config.gap_ratio * raw_len)
    ok &= (gap <= max_gap) & (gap >= -0.5 * np.minimum(half_len[a], half_len[b]))
    # A pair that is not straight on its own never joins one group.
    ok[ok] &= _tls_ms(cp.mom[a[ok]] + cp.mom[b[ok]]) <= tau2
    score = 0.5 * (lat_a + lat_b) + 0.01 * np.maximum(gap, 0)
    order = np.argsort(score[ok], kind="stable")
    return list(zip(a[ok][order].tolist(), b[ok][order].tolist(), strict=True))


def _merge_groups(candidates: list[tuple[int, int]], mom: NDArray, tau2: float):
    """Merge the candidate pairs greedily, in order, while the merged group's weighted mean
    squared distance from its TLS line stays within ``tau2``: ``(gmom, find)``, the ``(L, 6)``
    moments of each group at its root and the union-find root of each piece."""
    parent, find = _union_find(len(mom))
    gmom = mom.copy()
    for i, j in candidates:
        ri, rj = find(i), find(j)
        if ri == rj:
            continue
        m = gmom[ri] + gmom[rj]
        if _tls_ms(m[None])[0] > tau2:
            continue
        parent[ri] = rj
        gmom[rj] = m
    return gmom, find


def _group_lines(
    cp: _CorrectedPieces, gmom: NDArray, find, tau2: float, diagonal: float, config: AutoLineConfig
) -> list[NDArray[np.float64]]:
    """The groups' raw samples as polylines ordered along each group's corrected direction,
    longest first, at most ``max_edges``, each thinned to ``max_points_per_line``; pieces
    beyond the model's validity, single pieces that are not straight (``tau2``) and lines
    shorter than ``min_edge_fraction`` of the ``diagonal`` (raw px) are dropped."""
    groups: dict[int, list[int]] = {}
    for i in range(len(cp.raw)):
        if not cp.bad[i]:
            groups.setdefault(find(i), []).append(i)
    min_len = config.min_edge_fraction * diagonal
    lines = []
    for members in groups.values():
        m = gmom[find(members[0])]
        if len(members) == 1 and _tls_ms(m[None])[0] > tau2:
            continue
        p = np.concatenate([cp.raw[i] for i in members])
        qq = np.concatenate([cp.q[cp.first[i] : cp.last[i] + 1] for i in members])
        # Order along the group's direction in the corrected frame.
        order = np.argsort(qq @ _tls_direction(m), kind="stable")
        p = p[order]
        span = float(np.linalg.norm(p[-1] - p[0]))
        if span >= min_len:
            lines.append((span, p))
    lines.sort(key=lambda e: -e[0])
    return [_thin(p, config.max_points_per_line) for _, p in lines[: config.max_edges]]


def _piece_moments(model: RadialModel, pts: NDArray, owner: NDArray, L: int, nrm: NDArray):
    """``(L, 6)`` weighted moments of each piece's corrected samples (relative to the centre),
    per-sample validity and squared magnification across the piece."""
    cor = model.corrected_from_raw(pts)
    ok = np.isfinite(cor).all(axis=1)
    c0 = np.asarray(model.c)
    q = np.where(ok[:, None], cor, 0.0) - c0
    s_r, s_t = model.correction_stretch(pts)
    rad = pts - c0
    rhat = rad / np.maximum(np.linalg.norm(rad, axis=1), 1e-9)[:, None]
    cos = np.sum(nrm[owner] * rhat, axis=1)
    with np.errstate(invalid="ignore"):
        mag2 = s_r**2 * cos**2 + s_t**2 * (1 - cos**2)
    ok &= np.isfinite(mag2) & (mag2 > 0)
    wt = np.where(ok, 1.0 / np.where(ok, mag2, 1.0), 0.0)
    x, y = q[:, 0], q[:, 1]
    mom = np.stack(
        [np.bincount(owner, wt * v, L) for v in (np.ones_like(x), x, y, x * x, x * y, y * y)],
        axis=1,
    )
    return mom, ok, mag2


def _candidate_pairs(mid: NDArray, d: NDArray, max_angle: float, max_offset: float) -> NDArray:
    """``(P, 2)`` index pairs ``i < j`` of pieces (midpoints ``mid``, unit directions ``d``,
    undirected) whose directions differ by at most ``max_angle`` radians and whose lines' offsets
    from the centre differ by at most ``max_offset`` pixels: a box query in (angle, offset), so
    a frame full of parallel lines (a grid, a car park) does not compare every pair."""
    theta = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)
    rho = mid[:, 0] * -np.sin(theta) + mid[:, 1] * np.cos(theta)
    # Directions near 0 and near pi are the same: repeat those at theta + pi (offset negated).
    wrap = np.flatnonzero(theta < max_angle)
    idx = np.r_[np.arange(len(theta)), wrap]
    feat = np.stack(
        [np.r_[theta, theta[wrap] + np.pi] * (max_offset / max_angle), np.r_[rho, -rho[wrap]]],
        axis=1,
    )
    pairs = cKDTree(feat).query_pairs(max_offset, p=np.inf, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    a, b = idx[pairs[:, 0]], idx[pairs[:, 1]]
    keep = a != b
    pairs = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)[keep]
    if len(wrap):
        pairs = np.unique(pairs, axis=0)
    return pairs


def _tls_scatter(m: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Weight and centred scatter ``(W, cxx, cxy, cyy)`` of moments ``(..., 6)``."""
    W = np.maximum(m[..., 0], 1e-300)
    sx, sy, sxx, sxy, syy = (m[..., k] for k in range(1, 6))
    return W, sxx - sx * sx / W, sxy - sx * sy / W, syy - sy * sy / W


def _tls_ms(m: NDArray) -> NDArray:
    """Weighted mean squared distance from the total-least-squares line of moments ``(K, 6)``."""
    W, cxx, cxy, cyy = _tls_scatter(m)
    half_tr = 0.5 * (cxx + cyy)
    det = cxx * cyy - cxy * cxy
    # Smaller eigenvalue as det / larger one: no cancellation for long, thin point sets.
    lam_max = half_tr + np.sqrt(np.maximum(half_tr * half_tr - det, 0.0))
    return np.maximum(det, 0.0) / np.maximum(lam_max, 1e-300) / W


def _tls_direction(m: NDArray) -> NDArray:
    _, cxx, cxy, cyy = _tls_scatter(m)
    theta = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
    return np.array([np.cos(theta), np.sin(theta)])


def straight_edge_chart(width: int, height: int, *, seed: int = 0) -> NDArray[np.uint8]:
    """``(height, width)`` uint8 test chart of straight edges: long roads at random angles over
    rotated blocks (a stand-in for a street grid; always available, unlike real imagery).

    Used by tests, benchmarks and demos: distort it with a known model
    (:func:`registration.lens.correction.simulate_raw_frame`) and estimate the model back.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"chart size must be positive, got {width}x{height}")
    rng = np.random.default_rng(seed)
    img = np.full((height, width), 70, np.uint8)
    # Coordinates in 1/16 px (cv2 shift=4) so edges sit at sub-pixel positions, anti-aliased.
    for _ in range(max(4, int(40 * width * height / 1.2e6))):
        cx, cy = rng.uniform(0, width), rng.uniform(0, height)
        a, b = rng.uniform(0.04, 0.2, 2) * width
        box = cv2.boxPoints(((cx, cy), (a, b), rng.uniform(0, 180)))
        color = int(rng.integers(100, 160))
        cv2.fillPoly(img, [np.round(box * 16).astype(np.int32)], color, cv2.LINE_AA, shift=4)
    diag = float(np.hypot(width, height))
    for _ in range(14):
        ang = rng.uniform(0, np.pi)
        d = np.array([np.cos(ang), np.sin(ang)])
        c = np.array([rng.uniform(0.1, 0.9) * width, rng.uniform(0.1, 0.9) * height])
        p0, p1 = (np.round((c + s * d * diag) * 16).astype(int) for s in (-1, 1))
        thickness = max(int(rng.integers(8, 20) * width / 1000), 2)
        color = int(rng.choice([20, 230]))
        cv2.line(img, tuple(p0), tuple(p1), color, thickness, cv2.LINE_AA, shift=4)
    return img
