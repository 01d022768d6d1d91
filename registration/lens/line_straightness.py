"""How straight polylines are through a lens model (paper section 3): per-line deviation from a
straight line after correction, vectorised over many lines.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from registration.lens.lines_file import (
    as_polylines,
)
from registration.lens.radial import (
    HarrisModel,
    RadialModel,
    check_valid,
)

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
        self.starts = np.r_[0, np.cumsum(self.counts)[:-1]]

    def harris_ssr(
        self, gammas, width: int, height: int, center=None, chunk: int = 16
    ) -> NDArray[np.float64]:
        """``(L, G)`` :meth:`ssr_for` with ``weighted=True`` for Harris models of every γ in
        ``gammas`` at once (the same numbers, vectorised over γ; inf where a line has a point
        beyond the model's validity)."""
        frame = HarrisModel(0.0, width, height, center)
        c, r_n = frame.c, frame.r_n
        d = self.points - c
        r = np.linalg.norm(d, axis=1)
        u = (r / r_n) ** 2
        rhat = d / np.maximum(r, 1e-9)[:, None]
        gammas = np.atleast_1d(np.asarray(gammas, np.float64))
        out = np.empty((len(self.lines), len(gammas)))
        for k in range(0, len(gammas), chunk):
            g = gammas[k : k + chunk, None]
            with np.errstate(invalid="ignore", divide="ignore"):
                f = 1.0 / np.sqrt(1.0 - g * u[None, :])
            bad = ~np.isfinite(f)
            f = np.where(bad, 1.0, f)
            x, y = d[:, 0] * f, d[:, 1] * f  # corrected, relative to the centre
            nx, ny = self._tls_normals(x, y, None)
            cos = nx[:, self.index] * rhat[:, 0] + ny[:, self.index] * rhat[:, 1]
            # 1 / |J^T n|²: stretch f³ along the radius, f across it.
            w = 1.0 / (f**6 * cos**2 + f**2 * (1 - cos**2))
            nx, ny, dx, dy = self._tls_normals(x, y, w, return_offsets=True)
            res = dx * nx[:, self.index] + dy * ny[:, self.index]
            ssr = np.add.reduceat(w * res * res, self.starts, axis=1)
            ssr[np.add.reduceat(bad, self.starts, axis=1) > 0] = np.inf
            out[:, k : k + chunk] = ssr.T
        return out

    def _tls_normals(self, x: NDArray, y: NDArray, w: NDArray | None, return_offsets=False):
        """Per-line TLS normals of ``(G, N)`` coordinates (optionally weighted)."""
        idx, st = self.index, self.starts
        if w is None:
            wsum = self.counts[None, :].astype(np.float64)
            mx = np.add.reduceat(x, st, axis=1) / wsum
            my = np.add.reduceat(y, st, axis=1) / wsum
            dx, dy = x - mx[:, idx], y - my[:, idx]
            sxx = np.add.reduceat(dx * dx, st, axis=1)
            syy = np.add.reduceat(dy * dy, st, axis=1)
            sxy = np.add.reduceat(dx * dy, st, axis=1)
        else:
            wsum = np.add.reduceat(w, st, axis=1)
            mx = np.add.reduceat(w * x, st, axis=1) / wsum
            my = np.add.reduceat(w * y, st, axis=1) / wsum
            dx, dy = x - mx[:, idx], y - my[:, idx]
            sxx = np.add.reduceat(w * dx * dx, st, axis=1)
            syy = np.add.reduceat(w * dy * dy, st, axis=1)
            sxy = np.add.reduceat(w * dx * dy, st, axis=1)
        theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)
        nx, ny = -np.sin(theta), np.cos(theta)
        if return_offsets:
            return nx, ny, dx, dy
        return nx, ny

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
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.stack(
                [np.bincount(idx, w * corrected[:, k], L) / wsum for k in (0, 1)], axis=1
            )
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
        finite = np.isfinite(corrected).all(axis=1)
        if finite.all():
            w = self._weights(model, corrected) if weighted else None
            return self.fit(corrected, w)[0]
        # Lines with a point beyond the model's validity (γ past the frame's limit) get inf;
        # the others are still measured.
        bad = np.bincount(self.index, ~finite, len(self.lines)) > 0
        corrected = np.where(finite[:, None], corrected, self.points)
        w = self._weights(model, corrected) if weighted else None
        ssr = self.fit(corrected, w)[0]
        ssr[bad] = np.inf
        return ssr

    def residuals_for(self, model: RadialModel, *, weighted: bool = True) -> NDArray[np.float64]:
        """``(N,)`` signed distances of the corrected points from their line's TLS fit."""
        corrected = model.corrected_from_raw(self.points)
        w = self._weights(model, corrected) if weighted else np.ones(len(corrected))
        _, d, normals = self.fit(corrected, w)
        return np.sqrt(w) * np.sum(d * normals[self.index], axis=1)

    def _weights(self, model: RadialModel, corrected: NDArray) -> NDArray[np.float64]:
        """``1 / |J^T n|²`` per point, with ``n`` the normal of an unweighted fit."""
        _, _, normals = self.fit(corrected)
        radial = self.points - model.c
        r_raw = np.linalg.norm(radial, axis=1)
        rhat = np.where(
            (r_raw > 1e-9)[:, None], radial / np.maximum(r_raw, 1e-9)[:, None], [1.0, 0.0]
        )
        s_r, s_t = model.correction_stretch(self.points)
        cos = np.sum(normals[self.index] * rhat, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            w = 1.0 / (s_r**2 * cos**2 + s_t**2 * (1 - cos**2))
        return np.where(np.isfinite(w), w, 0.0)


def straightness(polylines, model: RadialModel, *, raw_units: bool = False) -> Straightness:
    """Straightness of raw-pixel polylines after correction by ``model``.

    Args:
        polylines: list of ``(N_i, 2)`` raw-pixel arrays, ``N_i >= 3``, each along something
            straight in the world.
        model: a valid radial model (:func:`registration.lens.radial.check_valid`).
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
