"""From matched samples to a displacement field (paper section 5): keypoints and gated
matching inside each neighbourhood, the per-cell REQCON consensus with its moving-car guards,
the neighbour check and the filling of rejected cells, and the robust spline fit
(``LocalConfig.fit = "spline"``). See :mod:`registration.local` for the stage itself.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.geometry import DisplacementField, grid_nodes
from registration.local.config import (
    FEW_MATCHES,
    NEIGHBOUR_OUTLIER,
    NO_CONSENSUS,
    OK,
    OUTSIDE,
    RIVAL_MOTION,
    FieldStats,
    KeypointSet,
    LocalConfig,
)
from registration.local.spline import estimate_field_spline

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Keypoints and matching


def detect_keypoints(
    grey: NDArray,
    config: LocalConfig = LocalConfig(),
    *,
    mask: NDArray | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
) -> KeypointSet:
    """SIFT keypoints of a grey uint8 crop, positions in base px (crop px + ``origin``).

    Args:
        grey: ``(H, W)`` uint8.
        mask: ``(H, W)`` bool/uint8, where the image has data; eroded by ``mask_erode_px``.
    """
    grey = np.asarray(grey)
    if grey.ndim != 2 or grey.dtype != np.uint8:
        raise ValueError(f"expected a grey uint8 (H, W) image, got {grey.dtype} {grey.shape}")
    cv_mask = None
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != grey.shape:
            raise ValueError(f"mask shape {mask.shape} differs from image shape {grey.shape}")
        cv_mask = (mask > 0).astype(np.uint8) * 255
        if config.mask_erode_px > 0:
            k = 2 * config.mask_erode_px + 1
            cv_mask = cv2.erode(cv_mask, np.ones((k, k), np.uint8))
    sift = cv2.SIFT_create(
        nOctaveLayers=config.sift_n_octave_layers,
        contrastThreshold=config.sift_contrast_threshold,
        edgeThreshold=config.sift_edge_threshold,
        sigma=config.sift_sigma,
    )
    kps, desc = sift.detectAndCompute(grey, cv_mask)
    if not kps:
        return KeypointSet(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    xy = np.array([k.pt for k in kps], np.float64) + np.asarray(origin, np.float64)
    return KeypointSet(xy, np.asarray(desc, np.float32))


def gated_ratio_matches(
    reg_xy: NDArray, reg_desc: NDArray, ref_xy: NDArray, ref_desc: NDArray, config: LocalConfig
) -> tuple[NDArray, NDArray]:
    """Match registered keypoints to reference keypoints within ``max_displacement_px``.

    Both sets are in base px, so a true match lies within the global stage's residual. The
    ratio test is applied among these gated candidates only: repetitive structure farther away
    than any plausible residual cannot veto a distinctive local match. A keypoint with a single
    gated candidate is accepted (REQCON removes the odd mismatch). A reference keypoint claimed
    by several registered ones keeps only the closest descriptor.

    Returns:
        ``(i_reg, i_ref)`` index arrays of the matches.
    """
    from scipy.spatial import cKDTree

    empty = np.zeros(0, np.intp), np.zeros(0, np.intp)
    if len(reg_xy) == 0 or len(ref_xy) == 0:
        return empty
    pairs = cKDTree(reg_xy).sparse_distance_matrix(
        cKDTree(ref_xy), config.max_displacement_px, output_type="ndarray"
    )
    if len(pairs) == 0:
        return empty
    i = pairs["i"].astype(np.intp)
    j = pairs["j"].astype(np.intp)
    a = np.asarray(reg_desc, np.float32)
    b = np.asarray(ref_desc, np.float32)
    d2 = np.einsum("ij,ij->i", a[i] - b[j], a[i] - b[j])
    order = np.lexsort((d2, i))  # by registered keypoint, then descriptor distance
    i, j, d2 = i[order], j[order], d2[order]
    first = np.r_[True, i[1:] != i[:-1]]
    idx_first = np.nonzero(first)[0]
    has_second = np.r_[idx_first[1:], len(i)] - idx_first > 1
    lo = d2[idx_first]
    hi = np.where(has_second, d2[np.minimum(idx_first + 1, len(i) - 1)], np.inf)
    ok = ~has_second | (np.sqrt(lo) < config.ratio * np.sqrt(hi))
    i_reg, i_ref, dist = i[idx_first][ok], j[idx_first][ok], lo[ok]
    if len(i_ref):
        o = np.argsort(dist, kind="stable")
        _, keep = np.unique(i_ref[o], return_index=True)
        keep = np.sort(o[keep])
        i_reg, i_ref = i_reg[keep], i_ref[keep]
    return i_reg, i_ref


# --------------------------------------------------------------------------------------------
# Consensus


@dataclass(frozen=True)
class CellConsensus:
    """Result of :func:`cell_consensus`: ``vector`` (2,) base px at the cell centre (NaN on
    failure), ``kept`` (M,) bool, ``residual_px`` mean residual of the kept matches, ``status``."""

    vector: NDArray[np.float64]
    kept: NDArray[np.bool_]
    residual_px: float
    status: int


class _CellSums:
    """Per-cell sums over the kept matches that the least-squares fits of :func:`consensus_cells`
    need: the count, the positions' first and second moments and their products with the
    displacements. REQCON only ever removes matches, so the sums are updated by subtracting the
    dropped ones instead of being recomputed over every kept match in every round.

    Args:
        rel: ``(C, M, 2)`` match positions relative to the cell centres (padding anywhere).
        disp: ``(C, M, 2)`` displacements.
        kept: ``(C, M)`` bool, the matches summed.
    """

    def __init__(self, rel: NDArray, disp: NDArray, kept: NDArray):
        self.n, self.sr, self.sd, self.srr, self.srd = self._sums(rel, disp, kept)

    @staticmethod
    def _sums(rel: NDArray, disp: NDArray, w: NDArray) -> tuple[NDArray, ...]:
        w = w.astype(np.float64)
        wr_t = (rel * w[..., None]).transpose(0, 2, 1)  # (C, 2, M)
        n = w.sum(axis=1)  # (C,)
        sr = wr_t.sum(axis=2)  # (C, 2): positions
        sd = (disp * w[..., None]).sum(axis=1)  # (C, 2): displacements
        return n, sr, sd, wr_t @ rel, wr_t @ disp  # and (C, 2, 2) position x position, x disp.

    def remove(self, rel: NDArray, disp: NDArray, drop: NDArray) -> None:
        """Subtract the matches ``drop`` (``(C, K)`` bool over ``rel``/``disp`` ``(C, K, 2)``)."""
        n, sr, sd, srr, srd = self._sums(rel, disp, drop)
        self.n, self.sr, self.sd = self.n - n, self.sr - sr, self.sd - sd
        self.srr, self.srd = self.srr - srr, self.srd - srd

    def subset(self, rows: NDArray) -> None:
        """Keep the cells ``rows`` (bool or index over the cells)."""
        self.n, self.sr, self.sd = self.n[rows], self.sr[rows], self.sd[rows]
        self.srr, self.srd = self.srr[rows], self.srd[rows]

    def fit(self, rel: NDArray, model: str, cell_px: float) -> tuple[NDArray, NDArray]:
        """Least-squares displacement model per cell over its kept matches.

        Returns:
            ``(vector (C, 2) at the centre, predicted displacement (C, M, 2) at rel)``. Cells
            with fewer than 6 kept matches, or whose kept matches spread (standard deviation
            along either principal axis) less than ``cell_px / 8``, get a translation (their
            mean).
        """
        safe_n = np.maximum(self.n, 1.0)[:, None]
        vec = self.sd / safe_n
        pred = np.broadcast_to(vec[:, None, :], rel.shape)
        if model != "affine":
            return vec, pred
        mu = self.sr / safe_n
        # Covariance of the kept positions: (sum r r^T - n mu mu^T) / (n - 1).
        cov = (self.srr - self.n[:, None, None] * mu[:, :, None] * mu[:, None, :]) / np.maximum(
            self.n - 1, 1.0
        )[:, None, None]
        a, b, d = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
        eig_min = (a + d) / 2 - np.sqrt(((a - d) / 2) ** 2 + b**2)
        affine = (self.n >= 6) & (np.sqrt(np.maximum(eig_min, 0.0)) >= cell_px / 8.0)
        if not affine.any():
            return vec, pred
        # Normal equations of d = c0 + [x, y] @ C over the kept matches: design rows [1, x, y].
        n_a = len(np.flatnonzero(affine))
        normal = np.empty((n_a, 3, 3))
        normal[:, 0, 0] = self.n[affine]
        normal[:, 0, 1:] = normal[:, 1:, 0] = self.sr[affine]
        normal[:, 1:, 1:] = self.srr[affine]
        rhs = np.empty((n_a, 3, 2))
        rhs[:, 0, :] = self.sd[affine]
        rhs[:, 1:, :] = self.srd[affine]
        coef = np.linalg.solve(normal, rhs)  # (A, 3, 2)
        vec = vec.copy()
        vec[affine] = coef[:, 0, :]
        pred = np.array(pred)
        pred[affine] = coef[:, None, 0, :] + rel[affine] @ coef[:, 1:, :]
        return vec, pred


def consensus_cells(
    pos: NDArray, disp: NDArray, centres: NDArray, members: NDArray, config: LocalConfig
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """REQCON consensus of many neighbourhoods at once (see :func:`cell_consensus`).

    Args:
        pos, disp: ``(N, 2)`` base px of all matches and their displacements.
        centres: ``(C, 2)`` cell centres.
        members: ``(C, M)`` int, each cell's match indices padded with -1.

    Returns:
        ``(vectors (C, 2), kept (C, M) bool, residual_px (C,), status (C,) int8)``; vectors are
        NaN where the status is not OK.
    """
    n_cells = len(members)
    slot = members >= 0
    idx = np.where(slot, members, 0)
    rel = pos[idx] - centres[:, None, :]
    d_all = disp[idx]
    kept = slot.copy()
    n = slot.sum(axis=1)
    status = np.full(n_cells, OK, np.int8)
    status[n < config.min_matches] = FEW_MATCHES
    kept[n < config.min_matches] = False
    vectors = np.full((n_cells, 2), np.nan)
    resid = np.full(n_cells, np.nan)
    max_res = config.reqcon_max_residual_px
    active = np.flatnonzero(n >= config.min_matches)
    # The active cells' arrays shrink with them (most cells settle in a few rounds).
    rel_a, d_a, k = rel[active], d_all[active], kept[active]
    sums = _CellSums(rel_a, d_a, k)
    while len(active):
        v, pred = sums.fit(rel_a, config.cell_model, config.cell_px)
        diff = d_a - pred
        r = np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2)
        nk = k.sum(axis=1)
        mean_r = np.where(k, r, 0.0).sum(axis=1) / nk
        done = mean_r < config.reqcon_target_px
        if max_res is not None:
            done &= np.where(k, r, -np.inf).max(axis=1) <= max_res
        resid[active] = mean_r
        vectors[active[done]] = v[done]
        n_drop = np.maximum(1, np.ceil(config.reqcon_drop_fraction * nk).astype(int))
        fail = ~done & (nk - n_drop < config.min_matches)
        status[active[fail]] = NO_CONSENSUS
        kept[active] = k
        go = ~done & ~fail
        if go.any():
            k, rel_a, d_a, r, n_drop = k[go], rel_a[go], d_a[go], r[go], n_drop[go]
            sums.subset(go)
            drop = _worst_kept(r, k, n_drop)  # (G, K) slot indices, -1 past each cell's n_drop
            rows = np.arange(len(drop))[:, None]
            slots = np.maximum(drop, 0)
            sums.remove(rel_a[rows, slots], d_a[rows, slots], drop >= 0)
            k = k.copy()
            k[np.broadcast_to(rows, drop.shape)[drop >= 0], drop[drop >= 0]] = False
        active = active[go]
    # Rival motion: a second coherent group among the rejected matches, of similar support.
    if config.rival_ratio > 0:
        n_kept = kept.sum(axis=1)
        n_rej = n - n_kept
        suspect = (status == OK) & (
            n_rej >= np.maximum(config.min_matches, config.rival_ratio * n_kept)
        )
        for c in np.flatnonzero(suspect):
            rej = d_all[c][slot[c] & ~kept[c]]
            if _rival_motion(rej, d_all[c][kept[c]].mean(axis=0), int(n_kept[c]), config):
                status[c] = RIVAL_MOTION
    vectors[status != OK] = np.nan
    return vectors, kept, resid, status


def _worst_kept(r: NDArray, kept: NDArray, n_drop: NDArray) -> NDArray[np.int64]:
    """Each row's ``n_drop`` kept slots of largest ``r`` (ties: the lower slot first, as a stable
    sort gives), as ``(C, max n_drop)`` slot indices padded with -1. Only the candidates are
    sorted: a partition finds each row's ``max n_drop`` largest first."""
    width = r.shape[1]
    k_max = int(n_drop.max())
    neg = np.where(kept, -r, np.inf)
    if k_max < width:
        cand = np.argpartition(neg, k_max - 1, axis=1)[:, :k_max]
        # The partition's boundary may split equal values arbitrarily: take every slot tied
        # with the k_max-th value too, so that the stable order below decides the ties.
        bound = np.take_along_axis(neg, cand, axis=1).max(axis=1)
        if (np.isfinite(bound) & ((neg == bound[:, None]).sum(axis=1) > 1)).any():
            cand = np.argsort(neg, axis=1, kind="stable")[:, :k_max]
    else:
        cand = np.broadcast_to(np.arange(width), neg.shape)
    vals = np.take_along_axis(neg, cand, axis=1)
    order = np.lexsort((cand, vals), axis=1)
    worst = np.take_along_axis(cand, order, axis=1)[:, :k_max]
    return np.where(np.arange(k_max)[None, :] < n_drop[:, None], worst, -1)


def _rival_motion(rejected: NDArray, consensus: NDArray, n_kept: int, config: LocalConfig) -> bool:
    """Whether the rejected displacements hold a coherent group of similar support to the kept
    set, away from the consensus. Group centres are tried at (at most 64, evenly chosen)
    rejected matches: a coherent group is dense, so any of its members finds (nearly) all of it."""
    cand = rejected[:: max(1, len(rejected) // 64)]
    dd = np.sqrt(((cand[:, None, :] - rejected[None, :, :]) ** 2).sum(axis=2))
    counts = (dd <= config.rival_radius_px).sum(axis=1)
    best = int(np.argmax(counts))
    if counts[best] < max(config.min_matches, config.rival_ratio * n_kept):
        return False
    c2 = np.median(rejected[dd[best] <= config.rival_radius_px], axis=0)
    return bool(np.linalg.norm(c2 - consensus) > 2 * config.rival_radius_px)


def cell_consensus(
    pos: ArrayLike, disp: ArrayLike, centre: ArrayLike, config: LocalConfig = LocalConfig()
) -> CellConsensus:
    """One neighbourhood's consensus displacement by REQCON plus the rival-motion guard.

    REQCON (paper 4.3.2, 5): fit the model to all matches, drop the worst ``reqcon_drop_fraction``
    (at least one), refit, until the mean residual of the kept matches is below
    ``reqcon_target_px`` (and, with ``reqcon_max_residual_px``, none is further than that). For
    a translation the least-squares fit is the mean of the kept displacement vectors, so no
    numerical optimiser is needed. :func:`consensus_cells` does the same for many cells at once.

    Args:
        pos: ``(M, 2)`` base px of the matches (reference keypoints).
        disp: ``(M, 2)`` displacement registered - reference, base px.
        centre: ``(2,)`` the cell centre, where the vector is reported.
    """
    pos = as_points(pos, "pos") if len(np.asarray(pos)) else np.zeros((0, 2))
    disp = as_points(disp, "disp") if len(np.asarray(disp)) else np.zeros((0, 2))
    if len(pos) != len(disp):
        raise ValueError(f"pos and disp must have the same length, got {len(pos)} and {len(disp)}")
    centre = np.asarray(centre, np.float64).reshape(1, 2)
    members = np.arange(len(pos))[None, :]
    vectors, kept, resid, status = consensus_cells(pos, disp, centre, members, config)
    return CellConsensus(vectors[0], kept[0], float(resid[0]), int(status[0]))


def neighbour_check(
    vectors: NDArray, valid: NDArray, tolerance_px: float, min_count: int = 3
) -> NDArray[np.bool_]:
    """Cells whose measured vector is further than ``tolerance_px`` from the median of their
    measured 8-neighbours (needs ``min_count`` of them). All cells are judged against the same
    input, so one bad cell cannot condemn a good neighbour unless bad cells are the majority of
    that neighbour's neighbours.

    Returns:
        ``(Gy, Gx)`` bool, True = reject.
    """
    gy, gx = valid.shape
    # The 8 neighbours of every cell side by side: (Gy, Gx, 8, 2), NaN where not measured.
    padded = np.pad(
        np.where(valid[..., None], vectors, np.nan),
        ((1, 1), (1, 1), (0, 0)),
        constant_values=np.nan,
    )
    shifts = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)]
    nb = np.stack([padded[1 + di : 1 + di + gy, 1 + dj : 1 + dj + gx] for di, dj in shifts], 2)
    count = np.isfinite(nb[..., 0]).sum(axis=2)
    judged = valid & (count >= min_count)
    reject = np.zeros_like(valid, dtype=bool)
    if judged.any():
        med = np.nanmedian(nb[judged], axis=1)
        reject[judged] = np.linalg.norm(vectors[judged] - med, axis=1) > tolerance_px
    return reject


def fill_invalid(vectors: NDArray, valid: NDArray) -> NDArray[np.float32]:
    """Fill the vectors of invalid cells ring by ring with the mean of their already known
    8-neighbours (nearest-valid extrapolation that averages where several are equally near).
    All-invalid grids become zeros."""
    out = np.where(valid[..., None], vectors, 0.0).astype(np.float32)
    known = valid.copy()
    if not known.any():
        return np.zeros_like(out)
    gy, gx = known.shape
    while not known.all():
        kf = known.astype(np.float32)
        pad_k = np.pad(kf, 1)
        pad_v = np.pad(out * kf[..., None], ((1, 1), (1, 1), (0, 0)))
        cnt = sum(
            pad_k[1 + di : 1 + di + gy, 1 + dj : 1 + dj + gx]
            for di in (-1, 0, 1)
            for dj in (-1, 0, 1)
        )
        tot = sum(
            pad_v[1 + di : 1 + di + gy, 1 + dj : 1 + dj + gx]
            for di in (-1, 0, 1)
            for dj in (-1, 0, 1)
        )
        new = (~known) & (cnt > 0)
        out[new] = tot[new] / cnt[new][:, None]
        known = known | new
    return out


# --------------------------------------------------------------------------------------------
# Estimation


def estimate_field_from_keypoints(
    registered_kp: Any,
    reference_kp: Any,
    width: int,
    height: int,
    config: LocalConfig = LocalConfig(),
    *,
    origin: tuple[float, float] = (0.0, 0.0),
    valid_mask: NDArray | None = None,
) -> tuple[DisplacementField, FieldStats]:
    """Displacement field from SIFT keypoints already detected (both in base px).

    Lets a caller detect the mid base image's keypoints once per sequence (or carry the frame's
    keypoints over from the global stage through its transform) instead of once per frame.

    Args:
        registered_kp, reference_kp: objects with ``.xy`` (N, 2) base px and ``.descriptors``.
        width, height, origin: the crop of base coordinates the field covers.
        valid_mask: ``(height, width)`` where both images have data (for the "outside" test).
    """
    t0 = time.perf_counter()
    reg_xy = np.asarray(registered_kp.xy, np.float64).reshape(-1, 2)
    ref_xy = np.asarray(reference_kp.xy, np.float64).reshape(-1, 2)
    reg_desc = np.asarray(registered_kp.descriptors, np.float32)
    ref_desc = np.asarray(reference_kp.descriptors, np.float32)
    # Reference keypoints may cover the whole mid base image: keep those near the crop.
    m = config.max_displacement_px + config.cell_px
    near = (
        (ref_xy[:, 0] >= origin[0] - m)
        & (ref_xy[:, 0] <= origin[0] + width + m)
        & (ref_xy[:, 1] >= origin[1] - m)
        & (ref_xy[:, 1] <= origin[1] + height + m)
    )
    if not near.all():
        ref_xy, ref_desc = ref_xy[near], ref_desc[near]
    # Match once over the whole crop (the gate makes matching local anyway); the matches are
    # then bucketed by the cell their reference keypoint falls in.
    a, b = gated_ratio_matches(reg_xy, reg_desc, ref_xy, ref_desc, config)
    pos = ref_xy[b]
    field_, stats = estimate_field_from_matches(
        pos, reg_xy[a] - pos, width, height, config, origin=origin, valid_mask=valid_mask
    )
    return field_, replace(
        stats,
        n_keypoints_registered=len(reg_xy),
        n_keypoints_reference=len(ref_xy),
        time_match_s=time.perf_counter() - t0,
    )


def _box_counts(mask: NDArray, cx: NDArray, cy: NDArray, half: float) -> NDArray[np.int64]:
    """``(Gy, Gx)`` non-zero pixels of ``mask`` in the boxes of side ``2 half`` around the crop
    px ``(cx[j], cy[i])`` (clipped to the crop; box edges rounded to whole pixels). Exact, in
    one pass over the mask: row bands summed at the boxes' row edges, then cumulated over the
    columns (cheaper than a whole integral image of a crop of tens of megapixels)."""
    h, w = mask.shape

    def edges(c: NDArray, n: int) -> tuple[NDArray, NDArray]:
        lo = np.clip(np.floor(c - half + 0.5), 0, n).astype(np.int64)
        hi = np.clip(np.floor(c + half + 0.5), 0, n).astype(np.int64)
        return lo, hi

    r0, r1 = edges(cy, h)
    c0, c1 = edges(cx, w)
    rows = np.unique(np.r_[0, h, r0, r1])
    # The mask's rows summed between consecutive row edges (one pass), then cumulated: the
    # integral image at every row edge and column.
    m = (mask > 0).view(np.uint8)
    bands = np.stack(
        [
            cv2.reduce(m[a:b], 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S)[0]
            for a, b in zip(rows[:-1], rows[1:], strict=True)
        ]
    ).astype(np.int64)
    integral = np.zeros((len(rows), w + 1), np.int64)
    integral[1:, 1:] = np.cumsum(np.cumsum(bands, axis=0), axis=1)
    ri0, ri1 = np.searchsorted(rows, r0), np.searchsorted(rows, r1)
    a = integral[ri1[:, None], c1[None, :]] - integral[ri0[:, None], c1[None, :]]
    b = integral[ri1[:, None], c0[None, :]] - integral[ri0[:, None], c0[None, :]]
    return a - b


def _cell_members(
    pos: NDArray, cxs: NDArray, cys: NDArray, half: float, usable: NDArray[np.bool_]
) -> tuple[NDArray, NDArray, NDArray]:
    """The samples of each usable cell (``c - half < p < c + half`` on both axes), ordered by
    index: ``(rows (C,), columns (C,), members (C, M) padded with -1)``, cells
    in row-major order."""
    n = len(pos)
    gy, gx = usable.shape
    if n == 0 or not usable.any():
        ii, jj = np.nonzero(usable)
        return ii, jj, np.full((len(ii), 0), -1, np.int64)
    sp_x = cxs[1] - cxs[0] if gx > 1 else 1.0
    sp_y = cys[1] - cys[0] if gy > 1 else 1.0

    # Candidate cells of each sample along one axis: the cells whose centre lies within
    # ``half`` of it (at most ceil(2 half / spacing) + 1 of them), checked exactly below.
    def candidates(p: NDArray, c: NDArray, sp: float) -> tuple[NDArray, NDArray]:
        k = int(np.ceil(2 * half / sp)) + 1 if len(c) > 1 else 1
        first = np.floor((p - half - c[0]) / sp).astype(np.int64)
        idx = first[:, None] + np.arange(k + 1)[None, :]
        ok = (idx >= 0) & (idx < len(c))
        cc = c[np.clip(idx, 0, len(c) - 1)]
        ok &= (p[:, None] > cc - half) & (p[:, None] < cc + half)
        return idx, ok

    jx, okx = candidates(pos[:, 0], cxs, sp_x)
    iy, oky = candidates(pos[:, 1], cys, sp_y)
    sample = np.arange(n)
    s_all, i_all, j_all = [], [], []
    for a in range(iy.shape[1]):
        for b in range(jx.shape[1]):
            ok = oky[:, a] & okx[:, b]
            s_all.append(sample[ok])
            i_all.append(iy[ok, a])
            j_all.append(jx[ok, b])
    s_all, i_all, j_all = np.concatenate(s_all), np.concatenate(i_all), np.concatenate(j_all)
    keep = usable[i_all, j_all]
    s_all, i_all, j_all = s_all[keep], i_all[keep], j_all[keep]
    cell = i_all * gx + j_all
    # Order within a cell: by index (one sort of a unique integer key).
    order = np.argsort(cell * n + s_all)
    s_all, cell = s_all[order], cell[order]
    cells = np.flatnonzero(usable.ravel())
    counts = np.bincount(cell, minlength=gy * gx)[cells]
    members = np.full((len(cells), int(counts.max()) if len(cells) else 0), -1, np.int64)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    slot = np.arange(len(s_all)) - np.repeat(starts, counts)
    members[np.repeat(np.arange(len(cells)), counts), slot] = s_all
    return cells // gx, cells % gx, members


def estimate_field_from_matches(
    pos: ArrayLike,
    disp: ArrayLike,
    width: int,
    height: int,
    config: LocalConfig = LocalConfig(),
    *,
    origin: tuple[float, float] = (0.0, 0.0),
    valid_mask: NDArray | None = None,
) -> tuple[DisplacementField, FieldStats]:
    """Displacement field from point matches: the per-cell consensus, the moving-car guard and
    the filling of rejected cells (``config.fit == "cells"``), or :func:`estimate_field_spline`
    (``"spline"``, no moving-car guard: its Tukey weights drop what disagrees with the fit).

    Args:
        pos: ``(M, 2)`` base px of the matches in the reference (they pick the cell).
        disp: ``(M, 2)`` displacement registered - reference, base px.
        width, height, origin: the crop of base coordinates the field covers.
        valid_mask: ``(height, width)`` where both images have data (for the "outside" test).
    """
    if config.fit == "spline":
        return estimate_field_spline(pos, disp, width, height, config, origin=origin)
    t0 = time.perf_counter()
    all_pos = np.asarray(pos, np.float64).reshape(-1, 2)
    all_disp = np.asarray(disp, np.float64).reshape(-1, 2)
    (x0, y0), (gx, gy) = grid_nodes(width, height, config.spacing_px, origin)
    status = np.full((gy, gx), OUTSIDE, np.int8)
    n_match = np.zeros((gy, gx), np.int32)
    n_kept = np.zeros((gy, gx), np.int32)
    resid = np.full((gy, gx), np.nan, np.float32)
    vec = np.zeros((gy, gx, 2), np.float64)
    half = config.cell_px / 2.0
    cxs = x0 + config.spacing_px * np.arange(gx, dtype=np.float64)
    cys = y0 + config.spacing_px * np.arange(gy, dtype=np.float64)
    usable = np.ones((gy, gx), bool)
    if valid_mask is not None:
        vm = np.asarray(valid_mask)
        if vm.shape != (height, width):
            raise ValueError(
                f"valid_mask shape {vm.shape} differs from the crop ({height}, {width})"
            )
        inside = _box_counts(vm, cxs - origin[0], cys - origin[1], half)
        usable = inside >= config.min_valid_fraction * float(config.cell_px) ** 2
    ii, jj, members = _cell_members(all_pos, cxs, cys, half, usable)
    if len(ii):
        vectors_c, kept_c, resid_c, status_c = consensus_cells(
            all_pos, all_disp, np.c_[cxs[jj], cys[ii]], members, config
        )
        status[ii, jj] = status_c
        n_match[ii, jj] = (members >= 0).sum(axis=1)
        n_kept[ii, jj] = kept_c.sum(axis=1)
        resid[ii, jj] = resid_c
        ok = status_c == OK
        vec[ii[ok], jj[ok]] = vectors_c[ok]
    valid = status == OK
    if config.neighbour_tolerance_px is not None:
        bad = neighbour_check(vec, valid, config.neighbour_tolerance_px, config.neighbour_min_count)
        status[bad] = NEIGHBOUR_OUTLIER
        valid &= ~bad
    vectors = fill_invalid(vec, valid)
    field_ = DisplacementField((x0, y0), float(config.spacing_px), vectors, valid)
    stats = FieldStats(
        cell_status=status,
        cell_matches=n_match,
        cell_kept=n_kept,
        cell_residual_px=resid,
        time_match_s=time.perf_counter() - t0,
    )
    log.debug("local field: %s", stats.counts())
    return field_, stats
