"""The local stage made consistent in time by the frame-to-frame links (beyond the paper).

Each frame's local stage (its own model and the displacement field measured on it against the
mid base image or the map) is right for that frame alone: its field carries the frame's own
matching noise, and where the frame was matched against the map rather than the mid base image
(re-anchored frames, frames beyond the mid base image) it carries the other season's
disagreements too. The links the sequence adjustment measured (the same ground seen in frames
``k`` and ``k + s``) say where two frames' local stages must agree.

So each frame ``k`` gets a correction ``e_k``, a field on a grid in base px, that moves its local
stage, ``x = own_local_k(q) + e_k(x)``, estimated together over a window by linear least squares:

* links: ``own_local_k(p) + e_k(x) = own_local_l(p') + e_l(x)`` for each link ``(p, p')``,
  with a soft-L1 loss (iteratively reweighted);
* each node of each frame's correction: ``e_k = 0`` (a frame's own local stage is evidence
  too: without links it stays as it is);
* neighbouring nodes of one frame: ``e_k(n) = e_k(n')`` (the correction is a smooth warp:
  where links are sparse it follows the nodes that have them).

The noise of each kind is read from the window, not assumed. A link pair's noise is what a
homography between its points leaves (the floor, as the flyover's scorer measures it; at least
``min_link_sigma_px``). A frame's own local stage may move by as much as its best-agreeing pair
disagrees through the two frames' local stages beyond that floor (and beyond the estimates'
sampling error), at least the window's typical frame's, times ``prior_scale``; its correction
varies between neighbouring nodes by a share of that, at most ``max_smooth_sigma_px``. So:

* frames whose local stages already agree to within their links' noise are held where they
  are. The simulator's local stage is within 0.1 px of the truth while its links are only
  within 0.2-0.6 px of it: a fixed noise model (0.5 px per node, 0.15 per link) moved it
  0.10 -> 0.14 px from the truth and made consecutive frames disagree more (0.14 -> 0.28 px),
  the measured one leaves it within 0.001 px;
* a frame whose own registration went wrong disagrees with every neighbour: it is free, and
  follows them as a whole (a frame planted 15 px off: its local stage 15.0 -> 0.20 px from the
  truth), while its neighbours keep the noise of their pairs with each other and are not pulled
  (a window-wide noise let that frame pull them 0.10 -> 0.5-0.65 px).

``prior_scale`` (16) is calibrated on the real flyover, where a best pair's excess is a lower
bound of a frame's noise: 4, 8, 12, 16 and 20 gave k -> k+5 at 1.35x, 1.18x, 1.12x, 1.14x and
1.13x the floor with the map agreement 0.431, 0.427, 0.423, 0.423 and 0.418 (with the window's
typical noise from its frames' best pairs; :func:`_field_sigmas` says why it is now from all
its pairs).

Frames held (those made final by an earlier window, the reference frame) enter with their
corrections fixed. The links fix differences between frames; what is common to all of them
(a shift of the whole window) only the priors hold, at their mean: the map agreement of the
frames' own local stages is kept on average while their disagreements are removed.

A correction is stored as the field ``δ = -e`` on top of the frame's own local stage
(``x + δ(x) = own_local(q)``, :func:`registration.geometry.local_frame_to_base`), on a grid
with twice the nodes per side of the frame's own field (:func:`refined_grid`).

This replaced averaging each frame's field with its neighbours' node by node (those whose views
were within 5 base px): that assumed the neighbours' fields differ by noise alone, so it left
frames that move further between frames as they were, and it could not see where two frames
disagree, only that their fields differ. On the real flyover, frames k -> k+1 and k -> k+5 after
the local stage went from 1.26x and 1.67x the floor (pooled) to 0.90x and 1.14x (solved); the
map agreement went 0.439 -> 0.423, that of the adjusted global stage (0.425): the own fields'
part of the agreement with a map of another season is where they disagree with each other.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import cg, splu

from registration.adjustment.solve import FrameLinks
from registration.geometry import DisplacementField

# The consistency field has twice the nodes per side of the frame's own field: the corrections
# vary between the own field's nodes.
REFINE = 2


def refined_grid(field_: DisplacementField, factor: int = REFINE) -> DisplacementField:
    """An empty field (zeros, nothing valid) on ``field_``'s grid with ``factor`` times the
    nodes per side, over the same extent."""
    gy, gx = field_.shape
    shape = ((gy - 1) * factor + 1, (gx - 1) * factor + 1)
    return DisplacementField(
        field_.origin, field_.spacing / factor, np.zeros((*shape, 2), np.float32),
        np.zeros(shape, bool),
    )  # fmt: skip


@dataclass(frozen=True)
class FieldSolveConfig:
    """How the consistency solve weighs its evidence. The noise of the links and of each
    frame's own local stage are measured in each window (module docstring); these scale them.

    Attributes:
        prior_scale: a frame's measured field noise is multiplied by this to give how far its
            own local stage may be moved at a node (calibrated on the real flyover: module
            docstring).
        smooth_ratio: how much a correction may differ between neighbouring nodes, as a share
            of that.
        max_smooth_sigma_px: at most this (base px): a frame free to move moves as a whole.
        min_sigma_px: the smallest field noise (base px): frames whose local stages already
            agree to within their links' noise are held at this.
        min_link_sigma_px: the smallest link noise (base px): a homography's floor measures
            the links' scatter, not errors they share with the frames' texture (on the real
            flyover the floor says 0.06 px; more freedom for the fields there bought
            consistency with map agreement).
        iterations: reweighting rounds of the soft-L1 loss on the links.
        typical_quantile: a frame's field noise is at least this quantile of the window's
            pairs' excess (:func:`_field_sigmas`).
    """

    prior_scale: float = 16.0
    smooth_ratio: float = 0.8
    min_sigma_px: float = 0.02
    min_link_sigma_px: float = 0.15
    max_smooth_sigma_px: float = 0.4
    iterations: int = 4
    typical_quantile: float = 0.25

    def __post_init__(self) -> None:
        names = (
            "prior_scale", "smooth_ratio", "min_sigma_px", "min_link_sigma_px",
            "max_smooth_sigma_px",
        )  # fmt: skip
        for name in names:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if not self.iterations >= 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations!r}")
        if not 0.0 <= self.typical_quantile <= 1.0:
            raise ValueError(f"typical_quantile must be in [0, 1], got {self.typical_quantile!r}")


@dataclass(frozen=True)
class FieldFrame:
    """One frame in the consistency solve.

    Attributes:
        to_base: corrected px ``(N, 2)`` -> base px through the frame's own local stage.
        grid: solved frames: the grid (origin, spacing, shape) its correction lives on;
            held frames: their correction as stored (``δ = -e``), or None for none.
        held: whether the frame's correction is fixed.
    """

    to_base: Callable[[NDArray], NDArray]
    grid: DisplacementField | None
    held: bool


@dataclass(frozen=True)
class _Pair:
    """One link pair in base px: where each side's own local stage puts the links, the
    disagreement left to correct (held corrections applied), and the links' noise."""

    k: int
    l: int  # noqa: E741
    at: NDArray[np.float64]
    target: NDArray[np.float64]
    floor_ms: float
    excess_ms: float


def _pairs(
    frames: Mapping[int, FieldFrame], links: Sequence[FrameLinks], solved, cache=None
) -> list[_Pair]:
    out = []
    for lk in links:
        fk, fl = frames.get(lk.k), frames.get(lk.l)
        if fk is None or fl is None or (lk.k not in solved and lk.l not in solved):
            continue
        key = (lk.k, lk.l)
        if cache is None or key not in cache:
            through = _through_own(fk, fl, lk)
            if cache is not None:
                cache[key] = through
        else:
            through = cache[key]
        if through is None:
            continue
        xk, xl, floor = through
        at = 0.5 * (xk + xl)
        t = xl - xk  # e_k(at) - e_l(at) = xl - xk
        for f, sign, j in ((fk, 1.0, lk.k), (fl, -1.0, lk.l)):
            if j not in solved and f.grid is not None:
                # A held frame's correction moves its side of the link: e = -δ.
                t = t + sign * f.grid.sample(at, outside="clamp")
        # What the local stages' disagreement exceeds the floor by, beyond what two mean
        # squares read from medians of n points differ by anyway (about 1.5/√n each).
        excess = _robust_ms(t) - floor * (1.0 + 3.0 / np.sqrt(len(t)))
        out.append(_Pair(lk.k, lk.l, at, t, floor, max(excess, 0.0)))
    return out


def _through_own(fk: FieldFrame, fl: FieldFrame, lk: FrameLinks):
    """``(xk, xl, floor)``: the link's points through each frame's own local stage (base px,
    where both map) and the links' own noise there (:func:`_floor_ms`), or None with fewer than
    8 such points. Neither depends on the window: a caller may keep them for the next."""
    xk, xl = fk.to_base(lk.src_k), fl.to_base(lk.src_l)
    ok = np.isfinite(xk).all(axis=1) & np.isfinite(xl).all(axis=1)
    if ok.sum() < 8:
        return None
    xk, xl = xk[ok], xl[ok]
    return xk, xl, _floor_ms(lk.src_k[ok], lk.src_l[ok], xl)


def _robust_ms(r: NDArray) -> float:
    """Mean square of the 2D vectors ``r`` from their median square (a 2D normal's squared
    length has median ``2 ln 2 σ²`` and mean ``2 σ²``): cars and mismatches do not count."""
    return float(np.median(np.sum(r**2, axis=1)) / np.log(2.0))


def _floor_ms(src_k: NDArray, src_l: NDArray, base_l: NDArray) -> float:
    """The links' own noise (mean square, base px): what a homography between the two frames'
    link points leaves (corrected px of frame ``l``), scaled to base px by how far the links
    spread in each."""
    # Least median of squares finds the ground's homography among cars and mismatches; refitted
    # by least squares on its inliers, so that the residuals are not those it minimised (their
    # median is what the noise is read from).
    h, inliers = cv2.findHomography(src_k, src_l, cv2.LMEDS)
    if h is None or inliers.sum() < 8:
        return np.inf
    inliers = inliers.ravel().astype(bool)
    h, _ = cv2.findHomography(src_k[inliers], src_l[inliers], 0)
    if h is None:
        return np.inf
    pred = cv2.perspectiveTransform(src_k.reshape(-1, 1, 2), h).reshape(-1, 2)
    spread_frame = np.mean(np.sum((src_l - src_l.mean(axis=0)) ** 2, axis=1))
    spread_base = np.mean(np.sum((base_l - base_l.mean(axis=0)) ** 2, axis=1))
    return _robust_ms(pred - src_l) * spread_base / max(spread_frame, 1e-12)


def solve_corrections(
    frames: Mapping[int, FieldFrame],
    links: Sequence[FrameLinks],
    config: FieldSolveConfig | None = None,
    cache: dict | None = None,
) -> dict[int, DisplacementField]:
    """Each solved frame's correction field ``δ = -e`` (module docstring) on its grid, with
    ``valid`` where links reached a node; frames without any link keep a zero field.

    The noise model is read from the links (module docstring): frames that agree to within
    their links' noise are held where they are, frames that disagree are moved as far as their
    links show.

    ``cache``: a dict the caller keeps from one window to the next, holding each link pair's
    points through the frames' own local stages and the links' noise (neither depends on the
    window; a sliding window meets most pairs twice). Only for frames whose ``to_base`` stays
    the same while it is kept."""
    cfg = config or FieldSolveConfig()
    solved = sorted(k for k, f in frames.items() if not f.held and f.grid is not None)
    offset, n_unknowns = {}, 0
    for k in solved:
        offset[k] = n_unknowns
        n_unknowns += frames[k].grid.shape[0] * frames[k].grid.shape[1]
    if n_unknowns == 0:
        return {}
    touched = np.zeros(n_unknowns, bool)
    pairs = [p for p in _pairs(frames, links, offset, cache) if np.isfinite(p.floor_ms)]
    if not pairs:
        e = np.zeros((n_unknowns, 2))
        return {k: _as_field(frames[k].grid, e, touched, offset[k]) for k in solved}
    rows, cols, vals, link_sigma = [], [], [], []
    n_rows = 0
    for p in pairs:
        r = np.arange(n_rows, n_rows + len(p.at))
        for k, sign in ((p.k, 1.0), (p.l, -1.0)):
            if k in offset:
                idx, w = frames[k].grid.bilinear(p.at)
                rows.append(np.repeat(r, 4))
                cols.append((idx + offset[k]).ravel())
                vals.append(sign * w.ravel())
                touched[(idx + offset[k]).ravel()] = True
        link_sigma.append(np.full(len(r), max(np.sqrt(p.floor_ms / 2), cfg.min_link_sigma_px)))
        n_rows += len(r)
    a = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(n_rows, n_unknowns),
    )
    t = np.concatenate([p.target for p in pairs])
    sigma_l = np.concatenate(link_sigma)
    sigma_f = _field_sigmas(pairs, solved, cfg)
    shapes = [frames[k].grid.shape for k in solved]
    prior = np.concatenate(
        [np.full(gy * gx, sigma_f[k] ** -2) for k, (gy, gx) in zip(solved, shapes, strict=True)]
    )
    smooth = _smoothness(
        shapes, [min(cfg.smooth_ratio * sigma_f[k], cfg.max_smooth_sigma_px) ** -2 for k in solved]
    )
    fixed = sp.diags(prior) + smooth
    weights = sigma_l**-2
    e = np.zeros((n_unknowns, 2))
    for _ in range(cfg.iterations):
        aw = a.T.multiply(weights).tocsr()
        e = _solve_spd((aw @ a + fixed).tocsr(), np.asarray(aw @ t), e)
        z = np.sum((a @ e - t) ** 2, axis=1) / sigma_l**2
        weights = 1.0 / (np.sqrt(1.0 + z) * sigma_l**2)  # soft-L1
    return {k: _as_field(frames[k].grid, e, touched, offset[k]) for k in solved}


def _field_sigmas(pairs: Sequence[_Pair], solved, cfg: FieldSolveConfig) -> dict[int, float]:
    """Each solved frame's field noise per coordinate (base px): half the excess mean square
    (two frames share it, over two coordinates) of its best-agreeing pair, and at least the
    window's typical pair's (one pair is a small sample), times ``prior_scale``. A frame whose
    own registration went wrong disagrees with every neighbour and is free to follow them; its
    neighbours keep the noise of their pairs with each other, and are not pulled by it.

    The typical pair is the ``typical_quantile`` (a quarter) of all the window's pairs' excess.
    It was the median of each frame's best pair: a minimum of four excesses clipped at zero,
    that median was zero wherever over half the frames had one pair within its floor, and the
    whole window was then held at ``min_sigma_px``. On the real flyover frames 60-69 were held
    so while the frames before them moved 0.26 px, and k -> k+5 across them went from 0.52 px
    (their own local stages) to 0.71 px. The window's pairs' lower quartile, the median and the
    35th percentile took the flyover's k -> k+5 to 1.10x, 1.06x and 1.08x the floor (1.15x
    before), the map agreement's mean paired difference from the frames' own local stages to
    -0.013, -0.024 and -0.016 (-0.009 before; medians -0.001 to -0.000); an estimate of each
    frame's noise from all its pairs at once (non-negative least squares, pair = sum of its
    frames') was zero for most frames and held them (1.44x)."""
    excess = {k: [] for k in solved}
    for p in pairs:
        for k in (p.k, p.l):
            if k in excess:
                excess[k].append(p.excess_ms)
    best = {k: min(v) for k, v in excess.items() if v}
    typical = (
        float(np.quantile([p.excess_ms for p in pairs], cfg.typical_quantile)) if pairs else 0.0
    )
    return {
        k: max(cfg.prior_scale * np.sqrt(max(best.get(k, 0.0), typical) / 4), cfg.min_sigma_px)
        for k in solved
    }


def _smoothness(shapes: Sequence[tuple[int, int]], weights: Sequence[float]) -> sp.csr_matrix:
    """``DᵀWD`` for the differences between 4-neighbouring nodes of each frame's grid, each
    frame's with its weight."""
    blocks = [w * _grid_laplacian(gy, gx) for (gy, gx), w in zip(shapes, weights, strict=True)]
    return sp.block_diag(blocks, format="csr")


@lru_cache(maxsize=16)
def _grid_laplacian(gy: int, gx: int) -> sp.csr_matrix:
    """The graph Laplacian of a ``gy`` x ``gx`` grid of 4-neighbours (the frames of a flight
    share a few grid shapes: built once each, it was a third of the fields' solve)."""
    return (sp.kron(sp.identity(gy), _path(gx)) + sp.kron(_path(gy), sp.identity(gx))).tocsr()


def _path(n: int) -> sp.csr_matrix:
    """The graph Laplacian of a path of ``n`` nodes (``DᵀD`` of its first differences)."""
    if n < 2:
        return sp.csr_matrix((n, n))
    d = sp.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n))
    return (d.T @ d).tocsr()


def _as_field(
    grid: DisplacementField, e: NDArray, touched: NDArray, start: int
) -> DisplacementField:
    gy, gx = grid.shape
    n = gy * gx
    vec = -e[start : start + n].reshape(gy, gx, 2)
    return DisplacementField(
        grid.origin, grid.spacing, vec.astype(np.float32),
        touched[start : start + n].reshape(gy, gx).copy(),
    )  # fmt: skip


# Conjugate gradients stop at this share of the right-hand side. 1e-10 took twice the
# iterations for nothing measurable: the real flyover's 160 solves 17,372 -> 9,231 iterations,
# every frame's local registration within 3e-5 px of the tighter solve's; paper-hard 2560x1920
# 253 -> 125, within 2e-10 px.
CG_RTOL = 1e-6


def _solve_spd(normal: sp.csr_matrix, rhs: NDArray, x0: NDArray | None = None) -> NDArray:
    """``normal⁻¹ rhs`` (``rhs`` ``(N, 2)``) for a symmetric positive definite ``normal``:
    conjugate gradients preconditioned by its diagonal, from ``x0`` (the previous reweighting
    round's solution), to ``CG_RTOL`` of the right-hand side; SuperLU where that does not
    converge. On the real flyover's windows 5.6x faster than SuperLU with a symmetric ordering."""
    precondition = sp.diags(1.0 / normal.diagonal())
    out = np.empty_like(rhs)
    for c in range(rhs.shape[1]):
        start = None if x0 is None else x0[:, c]
        out[:, c], info = cg(
            normal, rhs[:, c], x0=start, rtol=CG_RTOL, M=precondition, maxiter=5000
        )
        if info != 0:
            lu = splu(
                normal.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )  # fmt: skip
            return lu.solve(rhs)
    return out
