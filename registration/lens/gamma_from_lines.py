"""Choosing the distortion parameter γ so that straight world lines come out straight.

The paper (section 3) applied a range of γ to one frame and picked, by eye, the one with the
straightest streets (γ = 0.7 for its camera). This module measures straightness and finds γ:

* :func:`straightness`: RMS distance, in corrected pixels, of corrected polyline points from each
  polyline's best-fit (total least squares) straight line; per line and pooled over all points.
  Estimators measure it in raw-pixel units (the corrected distance divided by the correction's
  local magnification, lines refitted with those weights): in corrected pixels a γ that shrinks
  the frame would also shrink the noise and be preferred on noisy edges.
* :func:`estimate_gamma_from_lines`: the Harris γ that makes given polylines straightest
  together, with an uncertainty from an error model measured on real images (each line's own γ
  is off by its pixel noise and by a structural error: world features are not quite straight;
  lines side by side share theirs, :func:`line_groups`), a confidence verdict, and, for robust
  fits, rival γ the lines cannot rule out (see :class:`GammaEstimate`).
* :func:`estimate_gamma_auto`: the same from the image alone: line segments are detected,
  snapped sub-pixel, chained into long edges for a first robust γ, then regrouped into lines
  where they are collinear in the corrected frame and refitted
  (:mod:`registration.lens.straight_edges`), the uncertainty reaching wherever they settle when
  linked from either side of the estimate; an optional mask keeps blank borders out.

The distortion centre and the question whether one parameter is enough are in
:mod:`registration.lens.centre_fit`; LINES.json (the GUI's polylines) in
:mod:`registration.lens.lines_file` (re-exported here); each line's own γ, the error model and
the pooled fit behind :func:`estimate_gamma_from_lines` in :mod:`registration.lens.gamma_pooling`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from registration.lens.gamma_pooling import (
    _fit_gamma,
    _grid_minima,
    _LineTerms,
    _Pooled,
    _robust_start,
    _t_factor,
)
from registration.lens.line_straightness import _PackedLines
from registration.lens.lines_file import (
    as_polylines,
    degenerate_reason,
)
from registration.lens.radial import (
    HARRIS_GAMMA_MIN,
    HarrisModel,
    RadialModel,
    harris_gamma_limit,
)
from registration.lens.straight_edges import (
    AutoLineConfig,
    chain_polylines,
    detect_pieces,
    link_collinear,
)

log = logging.getLogger(__name__)


# Lower end of the default γ search range (registration.lens.radial.harris_gamma_range).
DEFAULT_GAMMA_MIN = HARRIS_GAMMA_MIN


# --------------------------------------------------------------------------------------------
# γ from lines (the per-line error model and its constants, NOISE_FLOOR_PX, STRUCTURE_*,
# OUTLIER_Z and AMBIGUITY_*, are in registration.lens.gamma_pooling)

# An estimate is *confident* when its uncertainty is at most this and at least this many
# independent groups of lines carry it (see GammaEstimate); chosen on every real nadir image of
# ../shared/data seen through γ in {0.3, 0.7, 1.0} (aerialreg bench distortion) so that every
# confident estimate there is within 0.02 of the truth.
CONFIDENT_SIGMA = 0.006
MIN_EFFECTIVE_LINES = 2.0
# Automatic estimates link the detected pieces into lines at a γ, so which pieces join depends
# on that γ: linked again from this far either side of the estimate, the pieces may settle at
# another γ, and the uncertainty reaches it. On the real images of `aerialreg bench distortion`
# this lifts the share of errors within 2σ from 83 % to 89 % (3σ: 91 % -> 94 %).
LINK_SPREAD_START = 0.05


@dataclass(frozen=True)
class GammaEstimate:
    """Result of a γ estimation (Harris model, paper eq. 4).

    Every line has its own γ (where it alone is straightest) and a curvature ``b`` (how fast
    its straightness worsens away from it; a line through the centre is straight at any γ and
    has none). γ is the mean of the lines' γ weighted by ``b``: the γ that makes all lines
    together straightest, as the paper chose it by eye. Its uncertainty follows an error model
    measured on real images: each line's γ is off by its pixel noise plus a *structural* error
    (world features are not quite straight), of standard deviation ``STRUCTURE_KAPPA /
    sens**STRUCTURE_POWER`` times a scale fitted to how much the lines disagree
    (``structure_scale``); lines side by side (:func:`line_groups`) share their structural
    error.

    Attributes:
        gamma: the estimate (dimensionless), within ``gamma_range``.
        uncertainty: its standard uncertainty (dimensionless), widened by Student's t for the
            number of line groups the scale was measured on, so that ±2σ is meant as a ~95 %
            interval; it also reaches every rival γ in ``alternatives`` and, for automatic
            estimates, the γ the edges settle at when linked from ``LINK_SPREAD_START`` either
            side (``link_spread``).
        uncertainty_method: ``"random-effects"`` (3 or more line groups) or ``"curvature"``
            (1 or 2 groups: their disagreement cannot be measured; never confident).
        method: ``"lines"`` (given polylines) or ``"auto"`` (detected edges).
        width, height, center: the raw frame the estimate is for (``center`` None = the frame
            centre).
        lines_used: the ``(N_i, 2)`` raw-pixel polylines the final fit used.
        per_line_residual: ``(L,)`` straightness RMS (corrected px) of each used line at ``gamma``.
        residual: pooled straightness RMS (corrected px) at ``gamma``.
        residual_uncorrected: the same at γ = 0 (no correction).
        gamma_grid, residual_curve: ``(G,)`` pooled straightness RMS of the used lines versus γ,
            in raw pixels (:func:`straightness` with ``raw_units``), for a plot.
        gamma_range: ``(lo, hi)`` searched.
        n_rejected: lines dropped as not straight in the world (robust fits), with their
            residuals (``rejected_residual``, raw px at ``gamma``).
        line_gamma: ``(L,)`` each used line's own γ.
        line_weight: ``(L,)`` each used line's share of the estimate (sums to 1).
        structure_scale: the fitted scale of the structural errors (1 = as on the real images
            the prior was measured on; at least ``MIN_STRUCTURE_SCALE``).
        n_effective: effective number of independent line groups, ``1 / Σ share²``.
        confident: ``uncertainty <= CONFIDENT_SIGMA``, at least ``MIN_EFFECTIVE_LINES``
            effective groups, no rival γ, and γ not pressed against the end of the range.
        evidence: one sentence saying why the estimate is or is not confident.
        unclipped_gamma: the weighted mean before clipping to ``gamma_range``.
        alternatives: other γ the lines support almost as well (robust fits: local minima of
            the robust cost within ``AMBIGUITY_COST`` of the best, more than
            ``AMBIGUITY_MIN_APART`` away).
        link_spread: automatic estimates: the largest distance from ``gamma`` at which the
            detected edges settle when linked into lines from ``LINK_SPREAD_START`` either side
            (0 for given polylines).
    """

    gamma: float
    uncertainty: float
    uncertainty_method: str
    method: str
    width: int
    height: int
    center: tuple[float, float] | None
    lines_used: list[NDArray[np.float64]]
    per_line_residual: NDArray[np.float64]
    residual: float
    residual_uncorrected: float
    gamma_grid: NDArray[np.float64]
    residual_curve: NDArray[np.float64]
    gamma_range: tuple[float, float]
    n_rejected: int = 0
    rejected_residual: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    line_gamma: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    line_weight: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    structure_scale: float = 1.0
    n_effective: float = 0.0
    confident: bool = False
    evidence: str = ""
    unclipped_gamma: float = float("nan")
    alternatives: tuple[float, ...] = ()
    link_spread: float = 0.0

    @property
    def n_lines(self) -> int:
        return len(self.lines_used)

    def model(self) -> HarrisModel:
        return HarrisModel(self.gamma, self.width, self.height, self.center)

    def to_dict(self, *, include_lines: bool = False) -> dict:
        """JSON-ready summary (floats and lists)."""
        c = HarrisModel(0.0, self.width, self.height, self.center).c
        d = {
            "gamma": float(self.gamma),
            "uncertainty": float(self.uncertainty),
            "uncertainty_method": self.uncertainty_method,
            "confident": bool(self.confident),
            "evidence": self.evidence,
            "center": [float(c[0]), float(c[1])],
            "method": self.method,
            "n_lines": self.n_lines,
            "n_effective_lines": float(self.n_effective),
            "link_spread": float(self.link_spread),
            "structure_scale": float(self.structure_scale),
            "n_rejected": int(self.n_rejected),
            "n_points": int(sum(len(p) for p in self.lines_used)),
            "residual_px": float(self.residual),
            "residual_uncorrected_px": float(self.residual_uncorrected),
            "gamma_range": [float(self.gamma_range[0]), float(self.gamma_range[1])],
            "image_size": [int(self.width), int(self.height)],
            "gamma_grid": self.gamma_grid.tolist(),
            "residual_curve": self.residual_curve.tolist(),
            "per_line_residual_px": self.per_line_residual.tolist(),
            "per_line_gamma": self.line_gamma.tolist(),
            "per_line_weight": self.line_weight.tolist(),
        }
        if include_lines:
            d["lines"] = [p.tolist() for p in self.lines_used]
        return d


def gamma_bounds(
    width: int, height: int, center, gamma_range: tuple[float, float] | None
) -> tuple[float, float]:
    """The γ range to search: ``gamma_range`` checked and clipped to just inside the frame's
    validity limit, or the Harris minimum up to that limit (ValueError when out of range)."""
    limit = harris_gamma_limit(width, height, center)
    if not np.isfinite(limit):
        raise ValueError(f"a {width}x{height} frame is too small to estimate gamma")
    # Just inside the validity limit: γ = 1.0 must stay reachable on frames whose limit is 1.002.
    hi_max = limit * (1 - 1e-6)
    if gamma_range is None:
        return DEFAULT_GAMMA_MIN, hi_max
    lo, hi = (float(v) for v in gamma_range)
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise ValueError(f"gamma range must be two finite numbers lo < hi, got {gamma_range!r}")
    if lo >= limit:
        raise ValueError(
            f"gamma range {lo:g}..{hi:g} is out of range for a {width}x{height} frame: "
            f"valid gamma < {math.floor(limit * 1e4) / 1e4:.4f}"
        )
    return lo, min(hi, hi_max)


def _fit_curves(
    packed: _PackedLines, width: int, height: int, center, lo: float, hi: float, grid_size: int
) -> tuple[NDArray, NDArray]:
    """``(G,)`` grid and ``(L, G)`` per-line SSR (raw-pixel units) on it."""
    grid = np.linspace(lo, hi, grid_size)
    return grid, packed.harris_ssr(grid, width, height, center)


def line_groups(
    lines: list[NDArray], model: RadialModel, *, angle_deg: float = 10.0, sep_fraction: float = 0.05
) -> NDArray[np.int64]:
    """``(L,)`` group label of each line: lines that run side by side in the corrected frame.

    Neighbouring parallel lines (the rows of one roof, the lanes of one road, both kerbs of a
    street) share whatever bends them (a sagging roof, a road that curves): their errors in γ
    are correlated, so they are pooled as one group. Greedy, longest line first: each
    ungrouped line seeds a group and takes every ungrouped line within ``angle_deg`` of its
    direction, within ``sep_fraction`` of the frame diagonal of its line and overlapping it
    along the line.
    """
    corrected = [model.corrected_from_raw(p) for p in lines]
    corrected = [np.where(np.isfinite(c), c, p) for c, p in zip(corrected, lines, strict=True)]
    mean = np.array([c.mean(axis=0) for c in corrected])
    direction = np.array([_principal_direction(c) for c in corrected])
    t = [(c - m) @ d for c, m, d in zip(corrected, mean, direction, strict=True)]
    lo = np.array([v.min() for v in t])
    hi = np.array([v.max() for v in t])
    sep = sep_fraction * float(np.hypot(model.width, model.height))
    cos_max = np.cos(np.deg2rad(angle_deg))
    labels = -np.ones(len(lines), dtype=np.int64)
    for i in np.argsort(-(hi - lo), kind="stable"):
        if labels[i] >= 0:
            continue
        labels[i] = i
        free = labels < 0
        if not free.any():
            continue
        j = np.flatnonzero(free)
        d = direction[i]
        normal = np.array([-d[1], d[0]])
        rel = mean[j] - mean[i]
        along = rel @ d
        # Extent of line j along line i's direction (its own extent, projected).
        half = 0.5 * (hi[j] - lo[j]) * np.abs(direction[j] @ d)
        near = (
            (np.abs(direction[j] @ d) >= cos_max)
            & (np.abs(rel @ normal) <= sep)
            & (along + half >= lo[i] - sep)
            & (along - half <= hi[i] + sep)
        )
        labels[j[near]] = i
    return labels


def _principal_direction(pts: NDArray) -> NDArray:
    d = pts - pts.mean(axis=0)
    sxx, syy, sxy = np.sum(d[:, 0] ** 2), np.sum(d[:, 1] ** 2), np.sum(d[:, 0] * d[:, 1])
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)
    return np.array([np.cos(theta), np.sin(theta)])


def _assess(
    sigma: float, n_eff: float, n_groups: int, unclipped: float, lo: float, hi: float
) -> tuple[bool, str]:
    """``(confident, one sentence why)`` for an estimate (see ``CONFIDENT_SIGMA``)."""
    if n_groups < 3:
        return False, (
            f"only {n_groups} group(s) of lines: how much they disagree cannot be measured, "
            f"so the uncertainty rests on the prior alone"
        )
    if unclipped > hi + sigma or unclipped < lo - sigma:
        end = "upper" if unclipped > hi else "lower"
        return False, (
            f"the lines want gamma {unclipped:.3f}, beyond the {end} end of the range "
            f"({lo:.4f}..{hi:.4f}): the one-parameter model with this centre cannot straighten them"
        )
    if sigma > CONFIDENT_SIGMA:
        return False, (
            f"the lines constrain gamma only to ±{sigma:.3f} (confident needs ≤ "
            f"{CONFIDENT_SIGMA}): too few long straight lines far from the centre, or lines "
            f"that disagree"
        )
    if n_eff < MIN_EFFECTIVE_LINES:
        return False, (
            f"the estimate rests on {n_eff:.1f} effective group(s) of lines (confident needs "
            f"≥ {MIN_EFFECTIVE_LINES:g}): one feature that is not quite straight would move it"
        )
    return True, f"{n_eff:.1f} effective groups of lines agree to ±{sigma:.4f}"


def estimate_gamma_from_lines(
    polylines,
    width: int,
    height: int,
    *,
    center: tuple[float, float] | None = None,
    gamma_range: tuple[float, float] | None = None,
    grid_size: int = 121,
    inlier_px: float | None = None,
    method: str = "lines",
    px_scale: float = 1.0,
) -> GammaEstimate:
    """The Harris γ that makes raw-pixel polylines straightest after correction.

    Each line's straightness (sum of squared TLS distances, in raw pixels: see
    :func:`straightness` with ``raw_units``) is sampled on a grid over the valid range (the
    pooled curve is kept for plotting) and modelled as a parabola in γ around the current
    estimate; γ is the curvature-weighted mean of the lines' own γ, i.e. the minimum of their
    summed straightness, iterated to convergence; its uncertainty follows the error model of
    :class:`GammaEstimate`.

    Args:
        polylines: list of ``(N_i, 2)`` raw-pixel arrays, ``N_i >= 3``.
        width, height: raw frame size in pixels (fixes the model's centre and normalisation).
        center: distortion centre; None = frame centre.
        gamma_range: ``(lo, hi)`` to search; default ``(-1, limit)`` with ``limit`` the largest
            valid γ for the frame (just above 1).
        grid_size: number of γ samples of the residual curve.
        inlier_px: None = every line counts (lines drawn by a user). A value τ (raw px) makes
            the fit robust (detected edges, some curved in the world): it starts at the γ where
            most groups of lines agree (each line's own γ within ``OUTLIER_Z`` prior standard
            deviations; rival minima of that count are reported in ``alternatives``), then keeps
            only lines that are straighter than τ at their own best γ and whose γ is within
            ``OUTLIER_Z`` standard deviations of the estimate. Dropped lines are reported in
            ``n_rejected``.
        method: label stored in the result.
        px_scale: size of a pixel of the image the lines were measured in, in raw pixels
            (edges detected on a 2x downscaled image: 2); scales the noise floor and the
            structural-error prior (see ``STRUCTURE_KAPPA``).

    Returns:
        :class:`GammaEstimate`.

    Raises:
        ValueError: a line with fewer than 3 points (named), a degenerate line (all points
            within a pixel of each other), an invalid γ range, or a frame too small (1x1).
    """
    lines = as_polylines(polylines)
    for i, p in enumerate(lines):
        problem = degenerate_reason(p)
        if problem:
            raise ValueError(f"line {i} {problem}")
    HarrisModel(0.0, width, height, center)  # validates the frame and centre
    lo, hi = gamma_bounds(width, height, center, gamma_range)
    packed = _PackedLines(lines)
    grid, curves = _fit_curves(packed, width, height, center, lo, hi, grid_size)
    grid_min = _grid_minima(grid, curves)
    if inlier_px is not None and not inlier_px > 0:
        raise ValueError(f"inlier_px must be positive, got {inlier_px}")
    g0, keep, alternatives, groups = _fit_start(
        lines, packed, grid, curves, grid_min, width, height, center, lo, hi, inlier_px, px_scale
    )
    gamma, keep, terms, pooled = _fit_gamma(
        packed, width, height, center, lo, hi, g0, keep, inlier_px, grid_min, px_scale, groups
    )
    result = _estimate_from_fit(
        lines, packed, grid, curves, width, height, center, lo, hi,
        gamma, keep, terms, pooled, method, alternatives,
    )  # fmt: skip
    return _widen_for_alternatives(result, alternatives) if alternatives else result


def _fit_start(
    lines: list[NDArray],
    packed: _PackedLines,
    grid: NDArray,
    curves: NDArray,
    grid_min: tuple[NDArray, NDArray, NDArray],
    width: int,
    height: int,
    center,
    lo: float,
    hi: float,
    inlier_px: float | None,
    px_scale: float,
) -> tuple[float, NDArray, tuple[float, ...], NDArray]:
    """Where :func:`_fit_gamma` starts: ``(g0, keep, alternatives, groups)``.

    ``groups`` ``(L,)`` labels the side-by-side lines (:func:`line_groups`) at the grid γ of
    the smallest pooled SSR (``grid`` ``(G,)``, ``curves`` ``(L, G)``). A plain fit starts
    there with every line kept; a robust one (``inlier_px`` raw px) at :func:`_robust_start`'s
    γ with the lines it keeps that are also straighter than ``inlier_px`` at their own γ (every
    line when none is), and the rival γ it found (``alternatives``).
    """
    keep = np.ones(len(lines), dtype=bool)
    # Side-by-side lines share their errors; the grouping barely depends on γ.
    g_plain = float(grid[int(np.argmin(np.nan_to_num(curves.sum(axis=0), nan=np.inf)))])
    groups = line_groups(lines, HarrisModel(g_plain, width, height, center))
    g0, alternatives = g_plain, ()
    if inlier_px is not None:
        g0, keep, alternatives = _robust_start(grid_min, packed.counts, lo, hi, px_scale, groups)
        keep &= np.sqrt(grid_min[1] / packed.counts) <= inlier_px
        if not keep.any():
            keep[:] = True
    return g0, keep, alternatives, groups


def _estimate_from_fit(
    lines: list[NDArray],
    packed: _PackedLines,
    grid: NDArray,
    curves: NDArray,
    width: int,
    height: int,
    center,
    lo: float,
    hi: float,
    gamma: float,
    keep: NDArray,
    terms: _LineTerms,
    pooled: _Pooled | None,
    method: str,
    alternatives: tuple[float, ...],
) -> GammaEstimate:
    """The :class:`GammaEstimate` of a finished fit (:func:`_fit_gamma`'s ``gamma``, ``keep``
    ``(L,)``, ``terms`` and ``pooled``): its uncertainty (Student's t widened; ``"curvature"``
    and infinite when no kept line constrains γ), the confidence verdict, and the used lines'
    residuals at ``gamma`` (corrected px) and curve over ``grid`` (raw px)."""
    used_idx = np.flatnonzero(keep)
    share = np.zeros(len(lines))
    if pooled is None:
        how, sigma, n_eff, n_groups, s2, unclipped = "curvature", float("inf"), 0.0, 0, 1.0, gamma
    else:
        share[np.flatnonzero(keep & np.isfinite(terms.noise_var))] = pooled.share
        n_eff, n_groups, s2, unclipped = (
            pooled.n_effective,
            pooled.n_groups,
            pooled.s2,
            pooled.mean,
        )
        # Student's t for the groups the structural scale was measured on: with one or two
        # groups their disagreement is not measured at all and the prior alone is widened.
        sigma = float(np.sqrt(pooled.variance) * _t_factor(n_groups - 1))
        how = "random-effects" if n_groups >= 3 else "curvature"
    confident, evidence = _assess(sigma, n_eff, n_groups, unclipped, lo, hi)
    model = HarrisModel(gamma, width, height, center)
    used = [lines[i] for i in used_idx]
    n_used = packed.counts[keep]
    ssr_used = packed.ssr_for(model)[keep]
    res_raw = np.sqrt(packed.ssr_for(model, weighted=True) / packed.counts)
    uncorrected = packed.ssr_for(HarrisModel(0.0, width, height, center))[keep]
    with np.errstate(invalid="ignore"):
        curve = np.sqrt(curves[keep].sum(axis=0) / n_used.sum())
    line_gamma = np.where(share[used_idx] > 0, terms.gamma[used_idx], gamma)
    return GammaEstimate(
        gamma=gamma,
        uncertainty=sigma,
        uncertainty_method=how,
        method=method,
        width=int(width),
        height=int(height),
        center=None if center is None else (float(center[0]), float(center[1])),
        lines_used=used,
        per_line_residual=np.sqrt(ssr_used / n_used),
        residual=float(np.sqrt(ssr_used.sum() / n_used.sum())),
        residual_uncorrected=float(np.sqrt(uncorrected.sum() / n_used.sum())),
        gamma_grid=grid,
        residual_curve=curve,
        gamma_range=(lo, hi),
        n_rejected=int((~keep).sum()),
        rejected_residual=res_raw[~keep],
        line_gamma=line_gamma,
        line_weight=share[used_idx],
        structure_scale=float(np.sqrt(s2)),
        n_effective=float(n_eff),
        confident=confident,
        evidence=evidence,
        unclipped_gamma=float(unclipped),
        alternatives=alternatives,
    )


def _widen_for_alternatives(est: GammaEstimate, alternatives) -> GammaEstimate:
    """``est`` with its uncertainty reaching every rival γ, not confident, saying so."""
    far = max(alternatives, key=lambda a: abs(a - est.gamma))
    listed = ", ".join(f"{a:.3f}" for a in sorted(alternatives))
    return dataclasses.replace(
        est,
        uncertainty=max(est.uncertainty, abs(far - est.gamma)),
        confident=False,
        alternatives=tuple(alternatives),
        evidence=(
            f"ambiguous: the edges are explained almost as well by gamma {listed} as by "
            f"{est.gamma:.3f} (too few straight lines; curved ones fit other gammas)"
        ),
    )


# --------------------------------------------------------------------------------------------
# Automatic: detected edges


def estimate_gamma_auto(
    image: NDArray,
    *,
    mask: NDArray | None = None,
    center: tuple[float, float] | None = None,
    gamma_range: tuple[float, float] | None = None,
    config: AutoLineConfig | None = None,
) -> GammaEstimate:
    """Estimate γ from the image alone: detected edges, linked into lines, robust fit.

    Line segments are detected and snapped (:func:`registration.lens.straight_edges.detect_pieces`),
    chained in the raw image for a first robust γ, then regrouped where they are collinear in
    the frame corrected with that γ (:func:`registration.lens.straight_edges.link_collinear`) and
    refitted, twice: long lines across the frame carry most of γ's information. Lines that are
    not straight at any γ, or whose own γ disagrees with the rest (curved kerbs, roundabouts,
    trees), are dropped (:func:`estimate_gamma_from_lines` with ``inlier_px``). Which pieces
    join depends on the γ they are linked at, so they are linked again from
    ``LINK_SPREAD_START`` either side of the estimate, and its uncertainty reaches wherever they
    settle (``link_spread``).

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` raw image (BGR for colour; any dtype).
        mask: optional ``(H, W)`` validity mask (True / non-zero = real content): edges near
            invalid pixels (a blank border, an overlay) are ignored.
        center, gamma_range: as in :func:`estimate_gamma_from_lines`.
        config: edge detection, linking and rejection settings.

    Raises:
        ValueError: when fewer than 2 usable edges are found, or a mask of the wrong shape.
    """
    config = config or AutoLineConfig()
    img = np.asarray(image)
    if img.ndim not in (2, 3) or img.size == 0:
        raise ValueError(f"image must be a non-empty (H, W) or (H, W, C) array, got {img.shape}")
    h, w = img.shape[:2]
    pieces = detect_pieces(img, config, mask)
    edges = chain_polylines(pieces, config)
    log.debug("estimate_gamma_auto: %d pieces, %d chained edges", len(pieces.points), len(edges))
    if len(edges) < 2:
        raise ValueError(
            f"found {len(edges)} long straight-ish edge{'s' if len(edges) != 1 else ''} in the "
            f"{w}x{h} image; at least 2 are needed to estimate gamma automatically (draw lines "
            f"and use a LINES.json instead)"
        )
    kw = dict(
        center=center,
        gamma_range=gamma_range,
        inlier_px=config.inlier_px / pieces.scale,
        method="auto",
        px_scale=1.0 / pieces.scale,
    )
    est = estimate_gamma_from_lines(edges, w, h, **kw)
    linked = _with_link_spread(pieces, _link_and_refit(pieces, est, w, h, config, kw), config, kw)
    if est.alternatives:
        # The chained edges (found without assuming any γ) admit other γ almost as well: the
        # lines linked around this one cannot rule them out.
        linked = _widen_for_alternatives(linked, est.alternatives)
    return linked


def _link_and_refit(pieces, est: GammaEstimate, w: int, h: int, config, kw) -> GammaEstimate:
    """Link the pieces at ``est``'s γ and refit, twice."""
    for _ in range(2):
        lines = link_collinear(pieces, est.model(), config)
        log.debug("estimate_gamma_auto: %d lines linked at gamma %.4f", len(lines), est.gamma)
        if len(lines) < 2:
            break
        est = estimate_gamma_from_lines(lines, w, h, **kw)
    return est


def _with_link_spread(pieces, est: GammaEstimate, config, kw) -> GammaEstimate:
    """``est`` with its uncertainty reaching the γ the pieces settle at when linked from
    ``LINK_SPREAD_START`` either side of it (see ``link_spread``)."""
    lo, hi = est.gamma_range
    settled = [
        _link_and_refit(
            pieces,
            dataclasses.replace(est, gamma=float(np.clip(est.gamma + d, lo, hi))),
            est.width,
            est.height,
            config,
            kw,
        ).gamma
        for d in (-LINK_SPREAD_START, LINK_SPREAD_START)
    ]
    spread = max(abs(g - est.gamma) for g in settled)
    if spread <= est.uncertainty:
        return dataclasses.replace(est, link_spread=spread)
    confident = est.confident and spread <= CONFIDENT_SIGMA
    linking = (
        f"linked from {LINK_SPREAD_START:g} either side, the edges settle up to {spread:.3f} "
        f"away: which pieces join into lines depends on gamma"
    )
    if confident:
        evidence = est.evidence
    elif est.confident:
        evidence = linking
    else:
        evidence = f"{est.evidence}; {linking}"
    return dataclasses.replace(
        est, uncertainty=spread, link_spread=spread, confident=confident, evidence=evidence
    )
