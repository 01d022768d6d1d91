"""Choosing the distortion parameter γ so that straight world lines come out straight.

The paper (section 3) applied a range of γ to one frame and picked, by eye, the one with the
straightest streets (γ = 0.7 for its camera). This module measures straightness and finds γ:

* :func:`straightness`: RMS distance, in corrected pixels, of corrected polyline points from each
  polyline's best-fit (total least squares) straight line; per line and pooled over all points.
* :func:`estimate_gamma_from_lines`: the Harris γ minimising the pooled straightness of given
  polylines (dense γ grid for the residual-versus-γ curve, then a bounded scalar search), with an
  uncertainty from a bootstrap over the lines. Distances are measured in raw-pixel units (the
  corrected distance divided by the correction's local magnification, lines refitted with those
  weights): measured in corrected pixels, a γ that shrinks the frame would also shrink the noise
  and be preferred on noisy edges.
* :func:`estimate_gamma_auto`: the same from the image alone: line segments from OpenCV's
  FastLineDetector (LSD as fallback) are chained into long edges (curved in the raw image; ends
  must meet head-on, with the same edge polarity), their points snapped to the sub-pixel gradient
  maximum, and γ is fitted robustly: an MSAC-style truncated cost over the whole γ grid (an edge
  that is not straight at γ costs a constant), then refits on the edges straight at that γ, so
  edges curved in the world (kerbs, roundabouts, trees) do not pull the estimate.
* :func:`fit_division_from_lines`: the one-parameter division model fitted the same way.
* :func:`fit_polynomial_from_lines`: the polynomial model (paper eq. 3) by least squares on the
  same residuals, to see where one parameter stops being enough.

LINES.json (what the GUI saves; :func:`load_lines` / :func:`save_lines`)::

    {"version": 1,
     "image_size": [W, H],
     "lines": [[[x, y], [x, y], [x, y], ...], ...]}

* ``version``: the integer 1.
* ``image_size``: the raw image's width and height in pixels (positive integers); it must match
  the image the lines are used with.
* ``lines``: one or more polylines, each a list of at least 3 ``[x, y]`` points in *raw* pixel
  coordinates (pixel centres at integers, ``(0, 0)`` = centre of the top-left pixel), tracing
  something straight in the world; every point within the image (``-0.5 <= x <= W - 0.5``, same
  for y). No other keys are allowed.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, optimize
from scipy.spatial import cKDTree

from registration.coords import as_points, rescale
from registration.distortion import (
    DivisionModel,
    HarrisModel,
    PolynomialModel,
    RadialModel,
    check_valid,
    harris_gamma_limit,
)
from registration.io import MAX_TEXT_FILE_BYTES

log = logging.getLogger(__name__)

LINES_FORMAT_VERSION = 1
MIN_POINTS_PER_LINE = 3

# Lower end of the default γ search range: pincushion correction of this strength is far beyond
# any real lens this project meets (the paper's camera: +0.7).
DEFAULT_GAMMA_MIN = -1.0


# --------------------------------------------------------------------------------------------
# Polylines and LINES.json


def as_polylines(polylines, name: str = "line") -> list[NDArray[np.float64]]:
    """Validate a list of polylines: each an ``(N_i, 2)`` float array with ``N_i >= 3``.

    Raises:
        ValueError: naming the first offending line (0-based index) and what is wrong with it.
    """
    if isinstance(polylines, np.ndarray) and polylines.ndim == 2:
        polylines = [polylines]
    lines = list(polylines)
    if not lines:
        raise ValueError("no lines given; at least one line of 3 or more points is needed")
    out = []
    for i, line in enumerate(lines):
        try:
            pts = as_points(line, f"{name} {i}")
        except ValueError as exc:
            raise ValueError(str(exc)) from None
        if len(pts) < MIN_POINTS_PER_LINE:
            raise ValueError(
                f"{name} {i} has {len(pts)} point{'s' if len(pts) != 1 else ''}; "
                f"each line needs at least {MIN_POINTS_PER_LINE}"
            )
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"{name} {i} has non-finite coordinates")
        out.append(pts)
    return out


@dataclass(frozen=True)
class LinesFile:
    """Contents of a LINES.json file (see the module docstring)."""

    image_size: tuple[int, int]
    lines: list[NDArray[np.float64]]


def parse_lines(obj: object, source: str = "LINES.json") -> LinesFile:
    """Validate a decoded LINES.json object; ValueError (one line, naming ``source``) if invalid."""

    def bad(msg: str) -> ValueError:
        return ValueError(f"{source}: {msg}")

    if not isinstance(obj, dict):
        raise bad(f"must be a JSON object, got {type(obj).__name__}")
    unknown = sorted(set(obj) - {"version", "image_size", "lines"})
    if unknown:
        raise bad(f"unknown key {unknown[0]!r} (allowed: version, image_size, lines)")
    for key in ("version", "image_size", "lines"):
        if key not in obj:
            raise bad(f"missing key {key!r}")
    if obj["version"] != LINES_FORMAT_VERSION or isinstance(obj["version"], bool):
        raise bad(f"version must be {LINES_FORMAT_VERSION}, got {obj['version']!r}")
    size = obj["image_size"]
    if (
        not isinstance(size, list)
        or len(size) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)
    ):
        raise bad(f"image_size must be [width, height] as positive integers, got {size!r}")
    w, h = size
    lines = obj["lines"]
    if not isinstance(lines, list) or not lines:
        raise bad("lines must be a non-empty list of polylines")
    out = []
    for i, line in enumerate(lines):
        if not isinstance(line, list):
            raise bad(f"lines[{i}] must be a list of [x, y] points, got {type(line).__name__}")
        for j, p in enumerate(line):
            if (
                not isinstance(p, list)
                or len(p) != 2
                or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                    for v in p
                )
            ):
                raise bad(f"lines[{i}][{j}] must be an [x, y] pair of finite numbers, got {p!r}")
            x, y = p
            if not (-0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5):
                raise bad(f"lines[{i}][{j}] = {p!r} lies outside the {w}x{h} image")
        if len(line) < MIN_POINTS_PER_LINE:
            raise bad(
                f"lines[{i}] has {len(line)} point{'s' if len(line) != 1 else ''}; "
                f"each line needs at least {MIN_POINTS_PER_LINE}"
            )
        out.append(np.asarray(line, dtype=np.float64).reshape(-1, 2))
    return LinesFile((w, h), out)


def load_lines(path: str | Path) -> LinesFile:
    """Read and validate a LINES.json file.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: not JSON or not a valid LINES.json (one line naming the file and problem).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"lines file not found: {path}")
    if path.is_dir():
        raise ValueError(f"lines file {path} is a directory")
    if path.stat().st_size > MAX_TEXT_FILE_BYTES:
        raise ValueError(
            f"lines file {path} has {path.stat().st_size >> 20} MiB, over the "
            f"{MAX_TEXT_FILE_BYTES >> 20} MiB limit"
        )
    text = path.read_bytes()
    if not text.strip():
        raise ValueError(f"{path}: file is empty")
    try:
        obj = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        msg = str(exc).splitlines()[0]
        raise ValueError(f"{path}: not valid JSON ({msg})") from None
    return parse_lines(obj, str(path))


def lines_to_json(lines, image_size: tuple[int, int]) -> dict:
    """The LINES.json object for ``lines`` (validated) on an image of ``image_size`` (W, H)."""
    obj = {
        "version": LINES_FORMAT_VERSION,
        "image_size": [int(image_size[0]), int(image_size[1])],
        "lines": [[[float(x), float(y)] for x, y in pts] for pts in as_polylines(lines)],
    }
    parse_lines(obj)
    return obj


def save_lines(path: str | Path, lines, image_size: tuple[int, int]) -> None:
    """Write ``lines`` (raw pixels) as LINES.json."""
    Path(path).write_text(json.dumps(lines_to_json(lines, image_size)) + "\n")


# --------------------------------------------------------------------------------------------
# Straightness


@dataclass(frozen=True)
class Straightness:
    """How straight polylines are after correction.

    Attributes:
        per_line: ``(L,)`` RMS distance (corrected px) of each line's corrected points from its
            total-least-squares straight line.
        overall: RMS over all points of all lines (corrected px).
        n_points: ``(L,)`` points per line.
    """

    per_line: NDArray[np.float64]
    overall: float
    n_points: NDArray[np.int64]


class _PackedLines:
    """Polylines concatenated for vectorised per-line total-least-squares fits."""

    def __init__(self, lines: list[NDArray]) -> None:
        self.lines = lines
        self.points = np.concatenate(lines)
        self.counts = np.array([len(p) for p in lines], dtype=np.int64)
        self.index = np.repeat(np.arange(len(lines)), self.counts)

    def fit(
        self, corrected: NDArray, weights: NDArray | None = None
    ) -> tuple[NDArray, NDArray, NDArray]:
        """Per-line (weighted) TLS fit.

        Returns:
            ``(L,)`` weighted sum of squared perpendicular distances, ``(N, 2)`` offsets from
            the lines' (weighted) means, ``(L, 2)`` unit normals.
        """
        idx, L = self.index, len(self.lines)
        w = np.ones(len(corrected)) if weights is None else weights
        wsum = np.bincount(idx, w, L)
        mean = np.stack([np.bincount(idx, w * corrected[:, k], L) / wsum for k in (0, 1)], axis=1)
        d = corrected - mean[idx]
        sxx = np.bincount(idx, w * d[:, 0] * d[:, 0], L)
        syy = np.bincount(idx, w * d[:, 1] * d[:, 1], L)
        sxy = np.bincount(idx, w * d[:, 0] * d[:, 1], L)
        # The TLS normal is perpendicular to the principal direction of the 2x2 scatter matrix.
        theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)
        normals = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
        # Summing the projections avoids the eigenvalue's cancellation (half_tr - disc loses
        # ~1e-9 relative to the spread of the points, i.e. 1e-6 px on long lines).
        r = np.sum(d * normals[idx], axis=1)
        return np.bincount(idx, w * r * r, L), d, normals

    def ssr_for(self, model: RadialModel, *, weighted: bool = False) -> NDArray[np.float64]:
        """``(L,)`` sum of squared distances of the corrected points from each line's TLS fit.

        With ``weighted`` each distance is divided by the correction's local magnification across
        the line (``|J^T n|`` for the Jacobian ``J`` of corrected_from_raw and the line normal
        ``n``), i.e. expressed in raw pixels, and the lines are refitted with those weights: the
        maximum-likelihood cost for isotropic noise in the raw image. Without it, a γ that
        shrinks the corrected frame (negative γ) also shrinks the noise and wins on noisy edges.
        """
        corrected = model.corrected_from_raw(self.points)
        if not np.all(np.isfinite(corrected)):
            return np.full(len(self.lines), np.inf)
        if not weighted:
            return self.fit(corrected)[0]
        return self.fit(corrected, self._weights(model, corrected))[0]

    def residuals_for(self, model: RadialModel, *, weighted: bool = True) -> NDArray[np.float64]:
        """``(N,)`` signed distances of the corrected points from their line's TLS fit."""
        corrected = model.corrected_from_raw(self.points)
        w = self._weights(model, corrected) if weighted else np.ones(len(corrected))
        _, d, normals = self.fit(corrected, w)
        return np.sqrt(w) * np.sum(d * normals[self.index], axis=1)

    def _weights(self, model: RadialModel, corrected: NDArray) -> NDArray[np.float64]:
        """``1 / |J^T n|²`` per point, with ``n`` the normal of an unweighted fit."""
        _, _, normals = self.fit(corrected)
        c = model.c
        radial = self.points - c
        r_raw = np.linalg.norm(radial, axis=1)
        ok = r_raw > 1e-9
        rhat = np.where(ok[:, None], radial / np.where(ok, r_raw, 1)[:, None], [1.0, 0.0])
        # Radial magnification by a one-sided (inward, always valid) difference; tangential
        # magnification = corrected radius / raw radius.
        eps = np.minimum(0.5, r_raw)[:, None]
        inner = model.corrected_from_raw(self.points - eps * rhat)
        with np.errstate(invalid="ignore", divide="ignore"):
            s_r = np.where(ok, np.linalg.norm(corrected - inner, axis=1) / eps[:, 0], 1.0)
            s_t = np.where(ok, np.linalg.norm(corrected - c, axis=1) / np.where(ok, r_raw, 1), 1.0)
        cos = np.sum(normals[self.index] * rhat, axis=1)
        return 1.0 / (s_r**2 * cos**2 + s_t**2 * (1 - cos**2))


def straightness(polylines, model: RadialModel, *, raw_units: bool = False) -> Straightness:
    """Straightness of raw-pixel polylines after correction by ``model``.

    Args:
        polylines: list of ``(N_i, 2)`` raw-pixel arrays, ``N_i >= 3``, each along something
            straight in the world.
        model: a valid radial model (:func:`registration.distortion.check_valid`).
        raw_units: express each distance in raw pixels (divided by the correction's local
            magnification across the line; the lines refitted with those weights) instead of
            corrected pixels: comparable between models that magnify the frame differently;
            this is the cost the estimators minimise.

    Returns:
        :class:`Straightness` in corrected (or, with ``raw_units``, raw) pixels.

    Raises:
        ValueError: a line with fewer than 3 points (named by index), or an invalid model.
    """
    lines = as_polylines(polylines)
    check_valid(model)
    packed = _PackedLines(lines)
    ssr = packed.ssr_for(model, weighted=raw_units)
    return Straightness(
        per_line=np.sqrt(ssr / packed.counts),
        overall=float(np.sqrt(ssr.sum() / packed.counts.sum())),
        n_points=packed.counts,
    )


# --------------------------------------------------------------------------------------------
# γ from lines


@dataclass(frozen=True)
class GammaEstimate:
    """Result of a γ estimation (Harris model, paper eq. 4).

    Attributes:
        gamma: the estimate (dimensionless).
        uncertainty: its standard error (dimensionless): bootstrap over lines when at least
            3 lines were used, else from the curvature of the cost at the minimum.
        uncertainty_method: ``"bootstrap"`` or ``"curvature"``.
        method: ``"lines"`` (given polylines) or ``"auto"`` (detected edges).
        width, height, center: the raw frame the estimate is for.
        lines_used: the ``(N_i, 2)`` raw-pixel polylines the final fit used.
        per_line_residual: ``(L,)`` straightness RMS (corrected px) of each used line at ``gamma``.
        residual: pooled straightness RMS (corrected px) at ``gamma``.
        residual_uncorrected: the same at γ = 0 (no correction).
        gamma_grid, residual_curve: ``(G,)`` pooled straightness RMS of the used lines versus γ,
            in raw pixels (:func:`straightness` with ``raw_units``; the cost minimised), for a
            plot.
        gamma_range: ``(lo, hi)`` searched.
        n_rejected: lines dropped as curved in the world (robust fits), with their residuals
            (``rejected_residual``, corrected px at ``gamma``).
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

    @property
    def n_lines(self) -> int:
        return len(self.lines_used)

    def model(self) -> HarrisModel:
        return HarrisModel(self.gamma, self.width, self.height, self.center)

    def to_dict(self, *, include_lines: bool = False) -> dict:
        """JSON-ready summary (floats and lists)."""
        d = {
            "gamma": float(self.gamma),
            "uncertainty": float(self.uncertainty),
            "uncertainty_method": self.uncertainty_method,
            "method": self.method,
            "n_lines": self.n_lines,
            "n_rejected": int(self.n_rejected),
            "n_points": int(sum(len(p) for p in self.lines_used)),
            "residual_px": float(self.residual),
            "residual_uncorrected_px": float(self.residual_uncorrected),
            "gamma_range": [float(self.gamma_range[0]), float(self.gamma_range[1])],
            "image_size": [int(self.width), int(self.height)],
            "gamma_grid": self.gamma_grid.tolist(),
            "residual_curve": self.residual_curve.tolist(),
            "per_line_residual_px": self.per_line_residual.tolist(),
        }
        if include_lines:
            d["lines"] = [p.tolist() for p in self.lines_used]
        return d


def _gamma_bounds(
    width: int, height: int, center, gamma_range: tuple[float, float] | None
) -> tuple[float, float]:
    limit = harris_gamma_limit(width, height, center)
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
    """``(G,)`` grid and ``(L, G)`` per-line SSR on it."""
    grid = np.linspace(lo, hi, grid_size)
    curves = np.stack(
        [packed.ssr_for(HarrisModel(float(g), width, height, center), weighted=True) for g in grid],
        axis=1,
    )
    return grid, curves


def _grid_argmin(grid: NDArray, cost: NDArray) -> float:
    """Minimum of a sampled cost, refined by a parabola through the best sample's neighbours."""
    i = int(np.argmin(cost))
    if 0 < i < len(grid) - 1 and np.all(np.isfinite(cost[i - 1 : i + 2])):
        y0, y1, y2 = cost[i - 1 : i + 2]
        den = y0 - 2 * y1 + y2
        if den > 0:
            return float(grid[i] + 0.5 * (y0 - y2) / den * (grid[1] - grid[0]))
    return float(grid[i])


def estimate_gamma_from_lines(
    polylines,
    width: int,
    height: int,
    *,
    center: tuple[float, float] | None = None,
    gamma_range: tuple[float, float] | None = None,
    grid_size: int = 241,
    n_bootstrap: int = 200,
    seed: int = 0,
    inlier_px: float | None = None,
    method: str = "lines",
) -> GammaEstimate:
    """The Harris γ that makes raw-pixel polylines straightest after correction.

    Minimises the pooled straightness (sum of squared TLS distances, in raw pixels: see
    :func:`straightness` with ``raw_units``) over γ:
    the cost is sampled on a dense grid over the valid range (the residual curve), and the best
    grid cell is refined by a bounded scalar search (``scipy.optimize.minimize_scalar``).

    Args:
        polylines: list of ``(N_i, 2)`` raw-pixel arrays, ``N_i >= 3``.
        width, height: raw frame size in pixels (fixes the model's centre and normalisation).
        center: distortion centre; None = frame centre.
        gamma_range: ``(lo, hi)`` to search; default ``(-1, limit)`` with ``limit`` the largest
            valid γ for the frame (just above 1).
        grid_size: number of γ samples of the residual curve.
        n_bootstrap: bootstrap resamples of the lines for the uncertainty (seeded by ``seed``).
        inlier_px: None = every line counts fully (lines drawn by a user). A value τ (raw px)
            makes the fit robust (detected edges, some curved in the world): γ minimises
            ``Σ_l N_l min(ms_l(γ), τ²)`` over the grid (``ms_l`` = line l's mean squared
            distance, in raw-pixel units), then is refined on the lines within τ, repeatedly,
            until that set is stable. Dropped lines are reported in ``n_rejected``.
        method: label stored in the result.

    Returns:
        :class:`GammaEstimate`.

    Raises:
        ValueError: a line with fewer than 3 points (named), or an invalid γ range.
    """
    lines = as_polylines(polylines)
    HarrisModel(0.0, width, height, center)  # validates the frame and centre
    lo, hi = _gamma_bounds(width, height, center, gamma_range)
    packed = _PackedLines(lines)
    grid, curves = _fit_curves(packed, width, height, center, lo, hi, grid_size)
    keep = np.ones(len(lines), dtype=bool)
    if inlier_px is None:
        gamma = _minimise(packed, curves, keep, grid, width, height, center)
    else:
        if not inlier_px > 0:
            raise ValueError(f"inlier_px must be positive, got {inlier_px}")
        # MSAC over lines: each line costs min(its mean square, τ²), so a line that is not
        # straight at γ (curved in the world, or a mis-chained edge) costs a constant and cannot
        # pull γ; the minimum over the whole grid is global, not a local refinement.
        tau2 = float(inlier_px) ** 2
        ms = curves / packed.counts[:, None]
        score = (packed.counts[:, None] * np.minimum(ms, tau2)).sum(axis=0)
        i0 = int(np.argmin(score))
        keep = ms[:, i0] <= tau2
        if keep.sum() < 2:
            keep = np.zeros(len(lines), dtype=bool)
            keep[np.argsort(ms[:, i0])[:2]] = True
        for _ in range(10):
            gamma = _minimise(packed, curves, keep, grid, width, height, center)
            res = np.sqrt(
                packed.ssr_for(HarrisModel(gamma, width, height, center), weighted=True)
                / packed.counts
            )
            new_keep = res <= inlier_px
            if new_keep.sum() < 2 or np.array_equal(new_keep, keep):
                break
            keep = new_keep
    res = np.sqrt(
        packed.ssr_for(HarrisModel(gamma, width, height, center), weighted=True) / packed.counts
    )
    used = [p for p, k in zip(lines, keep, strict=True) if k]
    n_used = packed.counts[keep]
    kept_curves = curves[keep]
    curve = np.sqrt(kept_curves.sum(axis=0) / n_used.sum())
    model = HarrisModel(gamma, width, height, center)
    ssr_used = packed.ssr_for(model)[keep]
    uncertainty, how = _uncertainty(
        packed, keep, grid, gamma, width, height, center, n_bootstrap, seed
    )
    uncorrected = packed.ssr_for(HarrisModel(0.0, width, height, center))[keep]
    return GammaEstimate(
        gamma=gamma,
        uncertainty=uncertainty,
        uncertainty_method=how,
        method=method,
        width=int(width),
        height=int(height),
        center=center,
        lines_used=used,
        per_line_residual=np.sqrt(ssr_used / n_used),
        residual=float(np.sqrt(ssr_used.sum() / n_used.sum())),
        residual_uncorrected=float(np.sqrt(uncorrected.sum() / n_used.sum())),
        gamma_grid=grid,
        residual_curve=curve,
        gamma_range=(lo, hi),
        n_rejected=int((~keep).sum()),
        rejected_residual=res[~keep],
    )


def _minimise(packed, curves, keep, grid, width, height, center) -> float:
    """Bounded scalar search of the kept lines' total SSR around the best grid sample."""
    total = curves[keep].sum(axis=0)
    i = int(np.argmin(total))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    sub = _PackedLines([p for p, k in zip(packed.lines, keep, strict=True) if k])

    def cost(g: float) -> float:
        return float(sub.ssr_for(HarrisModel(float(g), width, height, center), weighted=True).sum())

    res = optimize.minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": 1e-7})
    g = float(res.x)
    return g if cost(g) <= total[i] else float(grid[i])


def _uncertainty(
    packed, keep, grid, gamma, width, height, center, n_bootstrap, seed
) -> tuple[float, str]:
    n_lines = int(keep.sum())
    sub = _PackedLines([p for p, k in zip(packed.lines, keep, strict=True) if k])
    if n_lines >= 3 and n_bootstrap > 0:
        # Per-line cost curves on a fine local grid; a resample's cost is a weighted sum of them.
        local = np.unique(np.clip(gamma + np.linspace(-0.1, 0.1, 101), grid[0], grid[-1]))
        curves = np.stack(
            [
                sub.ssr_for(HarrisModel(float(g), width, height, center), weighted=True)
                for g in local
            ],
            axis=1,
        )
        rng = np.random.default_rng(seed)
        counts = rng.multinomial(n_lines, np.full(n_lines, 1.0 / n_lines), size=n_bootstrap)
        costs = counts.astype(np.float64) @ curves
        est = np.array([_grid_argmin(local, c) for c in costs])
        return float(np.std(est, ddof=1)), "bootstrap"
    # Least-squares curvature: var(γ) = 2 σ² / S''(γ), σ² = S_min / dof (dof = points - 2 per
    # line - 1 for γ); treats points as independent, so it is optimistic for dense polylines.
    h = 1e-3 * max(1.0, abs(gamma))
    lo, hi = grid[0], grid[-1]
    g0 = min(max(gamma, lo + h), hi - h)
    s = [
        float(sub.ssr_for(HarrisModel(g, width, height, center), weighted=True).sum())
        for g in (g0 - h, g0, g0 + h)
    ]
    d2 = (s[0] - 2 * s[1] + s[2]) / h**2
    dof = max(int(sub.counts.sum()) - 2 * n_lines - 1, 1)
    if d2 <= 0:
        return float("inf"), "curvature"
    return float(np.sqrt(2 * (s[1] / dof) / d2)), "curvature"


# --------------------------------------------------------------------------------------------
# Polynomial model for comparison


def fit_division_from_lines(
    polylines, width: int, height: int, *, center: tuple[float, float] | None = None
) -> tuple[DivisionModel, Straightness]:
    """Fit the one-parameter division model to straight polylines (bounded scalar search).

    Minimises the same raw-pixel straightness cost as :func:`estimate_gamma_from_lines` over
    the model's valid λ range.

    Returns:
        ``(model, straightness)`` at the optimum (straightness in raw pixels).
    """
    lines = as_polylines(polylines)
    packed = _PackedLines(lines)
    lo, hi = DivisionModel(0.0, width, height, center).lam_limits()
    lo, hi = lo * (1 - 1e-6), hi * (1 - 1e-6)

    def cost(lam: float) -> float:
        return float(
            packed.ssr_for(DivisionModel(float(lam), width, height, center), weighted=True).sum()
        )

    grid = np.linspace(lo, hi, 201)
    i = int(np.argmin([cost(v) for v in grid]))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    res = optimize.minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": 1e-8})
    model = DivisionModel(float(res.x), width, height, center)
    return model, straightness(lines, model, raw_units=True)


def fit_polynomial_from_lines(
    polylines,
    width: int,
    height: int,
    *,
    n_coeffs: int = 2,
    center: tuple[float, float] | None = None,
    initial: PolynomialModel | None = None,
) -> tuple[PolynomialModel, Straightness]:
    """Fit the polynomial model (paper eq. 3) with ``n_coeffs`` of k1..k3 to straight polylines.

    Least squares (``scipy.optimize.least_squares``) on every point's perpendicular distance from
    its line's TLS fit, in raw pixels (see :func:`straightness`, ``raw_units``); parameters for
    which outer raw pixels would have no
    corrected position are penalised. Starts from ``initial`` or from the best Harris γ
    (``k1 = -γ/2``).

    Returns:
        ``(model, straightness)`` at the optimum (straightness in raw pixels).
    """
    if n_coeffs not in (1, 2, 3):
        raise ValueError(f"n_coeffs must be 1, 2 or 3, got {n_coeffs}")
    lines = as_polylines(polylines)
    packed = _PackedLines(lines)
    big = 1e3 * np.hypot(width, height)

    def make(p):
        k = list(p) + [0.0] * (3 - n_coeffs)
        return PolynomialModel(float(k[0]), float(k[1]), float(k[2]), width, height, center)

    if initial is None:
        # Least-squares polynomial through the best Harris model's f over the corrected radii
        # the frame reaches; halved towards 0 until valid (strong barrel distortion saturates
        # the raw radius, which an eq.-3 polynomial can only follow up to its fold).
        harris = HarrisModel(
            estimate_gamma_from_lines(lines, width, height, center=center, n_bootstrap=0).gamma,
            width,
            height,
            center,
        )
        rho_m = harris.max_raw_rho()
        rho_c = (
            float(
                np.linalg.norm(
                    harris.corrected_from_raw([harris.c + [rho_m * harris.r_n, 0]])[0] - harris.c
                )
            )
            / harris.r_n
        )
        rho = np.linspace(0, rho_c, 200)[1:]
        target = rho / np.sqrt(1 + harris.gamma * rho**2)
        basis = np.stack([rho ** (2 * j + 3) for j in range(n_coeffs)], axis=1)
        k = np.linalg.lstsq(basis, target - rho, rcond=None)[0]
        for _ in range(60):
            if make(k).is_valid():
                break
            k = 0.5 * k
        x0 = k
    else:
        x0 = np.array([initial.k1, initial.k2, initial.k3][:n_coeffs])

    def residuals(p):
        model = make(p)
        if not model.is_valid():
            return np.full(len(packed.points), big)
        return packed.residuals_for(model, weighted=True)

    sol = optimize.least_squares(residuals, x0, method="trf", x_scale="jac")
    model = make(sol.x)
    return model, straightness(lines, model, raw_units=True)


# --------------------------------------------------------------------------------------------
# A generated chart


def straight_edge_chart(width: int, height: int, *, seed: int = 0) -> NDArray[np.uint8]:
    """``(height, width)`` uint8 test chart of straight edges: long roads at random angles over
    rotated blocks (a stand-in for a street grid; always available, unlike real imagery).

    Used by tests, benchmarks and demos: distort it with a known model
    (:func:`registration.distortion.simulate_raw_frame`) and estimate the model back.
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


# --------------------------------------------------------------------------------------------
# Automatic: detected edges


@dataclass(frozen=True)
class AutoLineConfig:
    """Edge detection and chaining for :func:`estimate_gamma_auto`.

    Lengths are in pixels of the working image (the input downscaled to ``work_width``).
    """

    work_width: int = 1280  # px; wider images are downscaled (INTER_AREA) for detection
    min_segment_px: float = 12.0  # FastLineDetector length_threshold
    fld_distance_px: float = 1.41421356  # FLD distance_threshold (OpenCV default)
    fld_canny: tuple[float, float] = (
        20.0,
        40.0,
    )  # FLD Canny thresholds (OpenCV: 50, 50; lower finds soft edges)
    link_gap_px: float = 60.0  # largest gap between chained ends (bridges cars, dashed lanes)
    link_overlap_px: float = 4.0  # largest overlap of chained segment ends
    link_lateral_px: float = 1.5  # largest sideways offset of the next segment's end
    link_angle_deg: float = 12.0  # largest direction change between chained segments
    min_edge_fraction: float = 0.08  # shortest kept edge, fraction of the working diagonal
    max_edges: int = 200  # longest edges kept
    sample_step_px: float = 3.0  # spacing of edge samples
    max_points_per_edge: int = 80  # longer edges are thinned evenly (fit cost ~ points)
    snap_radius_px: float = 2.0  # sub-pixel snapping search, either side of the segment
    blur_sigma_px: float = 1.0  # Gaussian blur before the gradient for snapping
    inlier_px: float = 0.5  # robust fit: an edge straighter than this RMS (px) at γ is an inlier


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
    candidates = []
    if len(pairs):
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
        candidates = list(zip(a_ok[order].tolist(), b_ok[order].tolist(), strict=True))
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    link = {}  # end id -> linked end id
    for ea, eb in candidates:
        if ea in link or eb in link:
            continue
        ra, rb = find(ea // 2), find(eb // 2)
        if ra == rb:
            continue
        parent[ra] = rb
        link[ea], link[eb] = eb, ea
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
    """Move each point along ``normal`` to the sub-pixel maximum of the gradient along it.

    The gradient is projected on ``normal`` (signed), so a sample on one side of a thin line
    never jumps to the opposite-polarity edge on the other side.
    """
    offsets = np.arange(-radius, radius + 0.25, 0.5)
    q = pts[:, None, :] + offsets[None, :, None] * normal[None, None, :]
    vals = _sample(gx, q) * normal[0] + _sample(gy, q) * normal[1]
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


def detect_edges(image: NDArray, config: AutoLineConfig | None = None) -> list[NDArray[np.float64]]:
    """Long edges of ``image`` as raw-pixel polylines (chained line segments, snapped sub-pixel).

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` image (BGR order for colour).
        config: detection settings.

    Returns:
        list of ``(N_i, 2)`` arrays in the input image's pixel coordinates, longest first.
    """
    config = config or AutoLineConfig()
    grey = _to_grey(image)
    h, w = grey.shape
    scale = _work_scale(w, config)
    work = (
        grey
        if scale == 1.0
        else cv2.resize(grey, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    )
    segs = detect_segments(work, config)
    if len(segs) == 0:
        return []
    blurred = cv2.GaussianBlur(work.astype(np.float32), (0, 0), config.blur_sigma_px)
    gx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3)
    polarity = _segment_polarity(gx, gy, segs)
    min_len = config.min_edge_fraction * float(np.hypot(*work.shape))
    edges = []
    for chain in chain_segments(segs, config, polarity):
        pieces = []
        for k, rev in chain:
            a, b = segs[k, :2], segs[k, 2:]
            if rev:
                a, b = b, a
            length = float(np.linalg.norm(b - a))
            m = max(int(length // config.sample_step_px), 1)
            # Stay half a step inside each segment: FLD's end points can overshoot corners.
            t = (np.arange(m) + 0.5) / m
            pts = a + t[:, None] * (b - a)
            d = (b - a) / max(length, 1e-12)
            # Normal pointing up the intensity gradient (polarity is for the native direction).
            normal = np.array([-d[1], d[0]]) * polarity[k] * (-1.0 if rev else 1.0)
            snapped, ok = _snap_points(gx, gy, pts, normal, config.snap_radius_px)
            pieces.append(snapped[ok])
        pts = np.concatenate(pieces) if pieces else np.zeros((0, 2))
        if len(pts) < 3:
            continue
        span = float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
        if span < min_len:
            continue
        edges.append((span, pts))
    edges.sort(key=lambda e: -e[0])
    out = []
    for _, pts in edges[: config.max_edges]:
        if len(pts) > config.max_points_per_edge:
            # Even thinning keeps the ends (where the curvature information is).
            pts = pts[
                np.round(np.linspace(0, len(pts) - 1, config.max_points_per_edge)).astype(int)
            ]
        out.append(pts)
    if scale != 1.0:
        out = [rescale(pts, 1.0 / scale) for pts in out]
    return out


def estimate_gamma_auto(
    image: NDArray,
    *,
    center: tuple[float, float] | None = None,
    gamma_range: tuple[float, float] | None = None,
    config: AutoLineConfig | None = None,
    n_bootstrap: int = 200,
    seed: int = 0,
) -> GammaEstimate:
    """Estimate γ from the image alone: detected long edges, robust straightness fit.

    Edges that remain far less straight than the rest at the fitted γ (curved kerbs, roundabouts,
    trees) are dropped and γ refitted until the set is stable (see
    :func:`estimate_gamma_from_lines` with ``inlier_px``).

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` raw image (BGR for colour; any dtype).
        center, gamma_range, n_bootstrap, seed: as in :func:`estimate_gamma_from_lines`.
        config: edge detection and rejection settings.

    Raises:
        ValueError: when fewer than 2 usable edges are found.
    """
    config = config or AutoLineConfig()
    img = np.asarray(image)
    if img.ndim not in (2, 3) or img.size == 0:
        raise ValueError(f"image must be a non-empty (H, W) or (H, W, C) array, got {img.shape}")
    h, w = img.shape[:2]
    edges = detect_edges(img, config)
    log.debug("estimate_gamma_auto: %d edges", len(edges))
    if len(edges) < 2:
        raise ValueError(
            f"found {len(edges)} long straight-ish edge{'s' if len(edges) != 1 else ''} in the "
            f"{w}x{h} image; at least 2 are needed to estimate gamma automatically (draw lines "
            f"and use a LINES.json instead)"
        )
    return estimate_gamma_from_lines(
        edges,
        w,
        h,
        center=center,
        gamma_range=gamma_range,
        n_bootstrap=n_bootstrap,
        seed=seed,
        inlier_px=config.inlier_px / _work_scale(w, config),
        method="auto",
    )
