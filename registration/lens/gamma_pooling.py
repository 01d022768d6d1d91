"""Each line's own γ and its error model, pooled into one γ: the fit behind
:func:`registration.lens.gamma_from_lines.estimate_gamma_from_lines`.

Every line's straightness (SSR in raw pixels) is a parabola in γ around its own γ with a
curvature ``b``; its own γ is off by its pixel noise and by a structural error (world features
are not quite straight, ``STRUCTURE_KAPPA``). :func:`_fit_gamma` iterates the per-line terms
(:func:`_line_terms`) and their pooled, curvature-weighted mean (:func:`_pool`), optionally
dropping lines that disagree (``OUTLIER_Z``); :func:`_robust_start` gives a robust fit its
global start and the rival γ it cannot rule out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from registration.lens.line_straightness import _PackedLines

# A line's noise (RMS distance at its own best γ) is floored at this many raw pixels: snapped
# edges are not better than this, and exact synthetic lines would otherwise get infinite weight.
NOISE_FLOOR_PX = 0.05
# Straight world features are not quite straight in an image (kerbs and paint a few cm off, a
# line joined from pieces slightly offset, roof edges at varying height): a line's own γ
# scatters about the truth by about STRUCTURE_KAPPA / sens**STRUCTURE_POWER beyond its pixel
# noise, where sens is how strongly γ bends the line (RMS over its points of the distance's
# derivative in γ, working pixels per unit γ). Measured on 5400 lines of real nadir images seen
# through known lenses (Songdo, SDD, OrthoLoC; linked at the true γ): with this prior the
# standardised errors have the same spread at every sensitivity. Each estimate rescales it
# (at least MIN_STRUCTURE_SCALE) when its lines disagree more.
STRUCTURE_KAPPA = 0.1
STRUCTURE_POWER = 0.8
MIN_STRUCTURE_SCALE = 0.5
# In a robust fit's cost each group of lines costs at most OUTLIER_Z² = 9 (not explained);
# another γ whose cost is within this of the best (less than half a group's worth) and this far
# away is a rival explanation the lines cannot rule out.
AMBIGUITY_COST = 4.0
AMBIGUITY_MIN_APART = 0.1
# Robust fits drop a line whose own γ is more than this many standard deviations (its noise and
# the between-line scatter) from the common estimate.
OUTLIER_Z = 3.0


@dataclass(frozen=True)
class _LineTerms:
    """Each line's own γ and the variance of its deviation from the common γ."""

    gamma: NDArray  # (L,) the γ at which the line alone is straightest
    b: NDArray  # (L,) curvature of its SSR in γ (raw px² per unit γ²); 0 = no information
    noise_var: NDArray  # (L,) variance of gamma from the line's pixel noise (inf = no info)
    structure_var: NDArray  # (L,) prior variance from its structural error (see STRUCTURE_*)
    rms_min: NDArray  # (L,) RMS distance at its own γ (raw px)


def _grid_minima(grid: NDArray, curves: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Per-line minimum of sampled SSR curves ``(L, G)``, refined by a parabola through the
    best sample and its neighbours: ``(γ*, SSR*, curvature b*)``, each ``(L,)`` (b* = 0 where
    the minimum is at an end of the grid)."""
    c = np.where(np.isfinite(curves), curves, np.inf)
    i = np.argmin(c, axis=1)
    rows = np.arange(len(c))
    j = np.clip(i, 1, len(grid) - 2)
    y0, y1, y2 = c[rows, j - 1], c[rows, j], c[rows, j + 1]
    step = grid[1] - grid[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        den = y0 - 2 * y1 + y2
        inner = (i == j) & np.isfinite(den) & (den > 0)
        t = np.where(inner, 0.5 * (y0 - y2) / np.where(inner, den, 1), 0.0)
        gamma = np.where(inner, grid[j] + t * step, grid[i])
        ssr = np.where(inner, y1 - 0.25 * (y0 - y2) * t, c[rows, i])
        b = np.where(inner, den / (2 * step**2), 0.0)
    return gamma, np.maximum(ssr, 0.0), b


def _robust_start(
    grid_min: tuple[NDArray, NDArray, NDArray],
    counts: NDArray,
    lo: float,
    hi: float,
    px_scale: float,
    groups: NDArray,
) -> tuple[float, NDArray]:
    """Global start of a robust fit, in γ: the γ minimising ``Σ_l min(z_l(γ)², OUTLIER_Z²) /
    size(group_l)`` with ``z_l = (γ_l - γ) / σ_l`` (each line's own γ and its prior standard
    deviation, from its sampled SSR curve): each group of side-by-side lines costs at most a
    constant, and the lines that pin γ down tightly decide where the consensus is."""
    g_star, ssr_star, b_star = grid_min
    n = counts.astype(np.float64)
    info = b_star > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        noise2 = np.maximum(ssr_star / np.maximum(n - 3, 1), (NOISE_FLOOR_PX * px_scale) ** 2)
        sens = np.sqrt(np.where(info, b_star, 0) / n) / px_scale
        var = noise2 / b_star + STRUCTURE_KAPPA**2 / sens ** (2 * STRUCTURE_POWER)
    ok = info & np.isfinite(var)
    if not ok.any():
        return float(np.clip(0.0, lo, hi)), ok, ()
    cand = np.linspace(lo, hi, max(int((hi - lo) / 0.002), 2))
    z2 = (g_star[ok, None] - cand[None, :]) ** 2 / var[ok, None]
    _, inv, size = np.unique(groups, return_inverse=True, return_counts=True)
    cost = (np.minimum(z2, OUTLIER_Z**2) / size[inv][ok, None]).sum(axis=0)
    i0 = int(np.argmin(cost))
    g0 = float(cand[i0])
    keep = np.zeros(len(counts), dtype=bool)
    keep[ok] = (g_star[ok] - g0) ** 2 / var[ok] <= OUTLIER_Z**2
    # Other local minima almost as good and clearly elsewhere: the lines do not decide.
    inner = (cost[1:-1] <= cost[:-2]) & (cost[1:-1] <= cost[2:])
    minima = np.flatnonzero(np.r_[cost[0] < cost[1], inner, cost[-1] < cost[-2]])
    alt = [
        float(cand[i])
        for i in minima
        if cost[i] - cost[i0] <= AMBIGUITY_COST and abs(cand[i] - g0) > AMBIGUITY_MIN_APART
    ]
    return g0, keep, tuple(alt)


def _line_terms(
    packed: _PackedLines,
    width: int,
    height: int,
    center,
    g0: float,
    grid_min: tuple[NDArray, NDArray],
    px_scale: float,
) -> _LineTerms:
    """Per-line terms around ``g0``: SSR curvature by central (or, past a line's validity
    limit, backward) differences; own γ by a Newton step where the line's grid minimum is near
    ``g0``, else that grid minimum; noise from the SSR at the line's own γ."""
    step = 0.01

    smm, sm, s0, sp = packed.harris_ssr(
        [g0 - 2 * step, g0 - step, g0, g0 + step], width, height, center
    ).T
    b = (sp + sm - 2 * s0) / (2 * step**2)
    half_slope = (sp - sm) / (4 * step)
    back = ~np.isfinite(sp) & np.isfinite(s0)
    if back.any():
        b = np.where(back, (s0 - 2 * sm + smm) / (2 * step**2), b)
        half_slope = np.where(back, (3 * s0 - 4 * sm + smm) / (4 * step), half_slope)
    g_star, ssr_star, _ = grid_min
    n = packed.counts.astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        info = np.isfinite(b) & np.isfinite(half_slope) & (b > 0)
        newton = g0 - half_slope / np.where(info, b, 1)
        near = info & (np.abs(g_star - g0) < 0.05)
        gamma = np.where(near, newton, g_star)
        local_min = s0 - half_slope**2 / np.where(info, b, 1)
        ssr_min = np.where(near, np.clip(local_min, 0, ssr_star), ssr_star)
        noise2 = np.maximum(ssr_min / np.maximum(n - 3, 1), (NOISE_FLOOR_PX * px_scale) ** 2)
        noise_var = np.where(info, noise2 / np.where(info, b, 1), np.inf)
        # γ's leverage on the line: RMS over its points of d(distance)/dγ, in working pixels.
        sens = np.sqrt(np.where(info, b, 0) / n) / px_scale
        structure_var = np.where(info, STRUCTURE_KAPPA**2 / sens ** (2 * STRUCTURE_POWER), np.inf)
    return _LineTerms(
        gamma=np.where(np.isfinite(gamma), gamma, g0),
        b=np.where(info, b, 0.0),
        noise_var=noise_var,
        structure_var=structure_var,
        rms_min=np.sqrt(ssr_min / n),
    )


@dataclass(frozen=True)
class _Pooled:
    mean: float
    variance: float  # of the mean
    s2: float  # structural scale²
    share: NDArray  # (L,) each line's share of the mean
    n_groups: int
    n_effective: float  # Kish effective number of groups


def _pool(gamma_l: NDArray, b: NDArray, noise: NDArray, structure: NDArray, group) -> _Pooled:
    """The lines' γ combined as the straightest-overall γ, with an honest variance.

    The mean weights each line by its SSR curvature ``b`` (minimising the summed straightness:
    the paper's "straightest streets", and the least-squares answer for pixel noise); long
    lines far from the centre dominate. Its variance follows the error model: within a group
    of side-by-side lines the pixel noise averages out but the structural errors (variance
    ``s² structure``) are taken as fully correlated; groups are independent. ``s²`` (at least
    ``MIN_STRUCTURE_SCALE²``) is chosen, Paule-Mandel style, so that the groups' deviations
    from their inverse-variance mean match their number minus one: when the groups disagree
    more than the prior says, every structural variance grows.
    """
    _, inv = np.unique(group, return_inverse=True)
    K = int(inv.max()) + 1
    B = np.bincount(inv, b, K)
    gk = np.bincount(inv, b * gamma_l, K) / B
    noise_k = np.bincount(inv, b * b * noise, K) / B**2
    struct_k = (np.bincount(inv, b * np.sqrt(structure), K) / B) ** 2

    def q_of(s2):
        wk = 1.0 / (noise_k + s2 * struct_k)
        m = np.sum(wk * gk) / np.sum(wk)
        return float(np.sum(wk * (gk - m) ** 2))

    s2 = MIN_STRUCTURE_SCALE**2
    if K >= 2 and q_of(s2) > K - 1:
        lo, hi = s2, s2 * 4
        while q_of(hi) > K - 1 and hi < 1e12:
            lo, hi = hi, hi * 4
        for _ in range(50):
            mid = np.sqrt(lo * hi)
            lo, hi = (mid, hi) if q_of(mid) > K - 1 else (lo, mid)
        s2 = hi
    share_k = B / B.sum()
    return _Pooled(
        mean=float(np.sum(share_k * gk)),
        variance=float(np.sum(share_k**2 * (noise_k + s2 * struct_k))),
        s2=s2,
        share=(b / B[inv]) * share_k[inv],
        n_groups=K,
        n_effective=1.0 / float(np.sum(share_k**2)),
    )


def _fit_gamma(
    packed: _PackedLines,
    width: int,
    height: int,
    center,
    lo: float,
    hi: float,
    g0: float,
    keep: NDArray,
    inlier_px: float | None,
    grid_min: tuple[NDArray, NDArray, NDArray],
    px_scale: float,
    groups: NDArray,
) -> tuple[float, NDArray, _LineTerms, _Pooled | None]:
    """Iterate: per-line terms at γ, pooled mean, (robust) line selection.

    Returns:
        ``(γ clipped to [lo, hi], keep, terms at γ, pooled result or None when no kept line
        constrains γ)``.
    """
    g, keep = float(g0), keep.copy()
    pooled = None
    for _ in range(30):
        terms = _line_terms(packed, width, height, center, g, grid_min, px_scale)
        use = keep & np.isfinite(terms.noise_var)
        if not use.any():
            return g, keep, terms, None
        pooled = _pool(
            terms.gamma[use],
            terms.b[use],
            terms.noise_var[use],
            terms.structure_var[use],
            groups[use],
        )
        g_new = float(np.clip(pooled.mean, lo, hi))
        new_keep = keep
        if inlier_px is not None:
            with np.errstate(invalid="ignore"):
                z = np.abs(terms.gamma - pooled.mean) / np.sqrt(
                    terms.noise_var + pooled.s2 * terms.structure_var
                )
            new_keep = (terms.rms_min <= inlier_px) & (z <= OUTLIER_Z)
            if not (new_keep & np.isfinite(terms.noise_var)).any():
                new_keep = keep
        done = abs(g_new - g) < 1e-7 and np.array_equal(new_keep, keep)
        g, keep = g_new, new_keep
        if done:
            break
    terms = _line_terms(packed, width, height, center, g, grid_min, px_scale)
    use = keep & np.isfinite(terms.noise_var)
    if not use.any():
        return g, keep, terms, None
    pooled = _pool(
        terms.gamma[use], terms.b[use], terms.noise_var[use], terms.structure_var[use], groups[use]
    )
    return float(np.clip(pooled.mean, lo, hi)), keep, terms, pooled


def _t_factor(dof: float) -> float:
    """Student's t 97.5 % quantile over the normal one: widens ±2σ for few lines."""
    from scipy.special import stdtrit

    return float(stdtrit(max(dof, 1.0), 0.975) / 1.959963984540054)
