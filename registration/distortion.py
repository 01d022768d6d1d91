"""Radial distortion (paper section 3): the one-parameter Harris model and friends.

Every model here is radial about a centre ``c`` and normalised by ``r_n``, exactly as the paper's
eq. 2 and ``conventions.md``: for a raw frame of width ``W`` and height ``H``, ``c = ((W-1)/2,
(H-1)/2)`` unless given, ``r_n = sqrt(W²+H²)/2`` (half the diagonal). A corrected pixel ``x`` maps
to the raw pixel ``x' = c + r_n f(ρ) (x-c)/|x-c|`` with ``ρ = |x-c|/r_n``; ``f`` is the model.

* :class:`HarrisModel` (paper eq. 4): ``f(ρ) = ρ / sqrt(1 + γ ρ²)``. The inverse (raw to
  corrected) is the same formula with ``-γ``. Positive γ corrects barrel distortion; γ = 0 is the
  identity; the paper's camera used γ = 0.7.
* :class:`PolynomialModel` (paper eq. 3): ``f(ρ) = ρ (1 + k1 ρ² + k2 ρ⁴ + k3 ρ⁶)``; raw to
  corrected is solved numerically (safeguarded Newton, vectorised). Barrel correction has k1 < 0.
  To third order the Harris model is ``k1 = -γ/2, k2 = 3γ²/8, k3 = -5γ³/16``.
* :class:`DivisionModel` (one-parameter division model, Fitzgibbon 2001): raw to corrected is
  ``ρ = ρ' / (1 + λ ρ'²)``; corrected to raw has the closed form ``ρ' = 2ρ / (1 + sqrt(1 - 4λρ²))``.
  Barrel correction has λ < 0 (to first order λ ≈ -γ/2).

All models are frozen dataclasses (hashable: usable as cache keys) with the same two methods,
``raw_from_corrected(xy)`` and ``corrected_from_raw(xy)``, mapping ``(N, 2)`` float pixels.

A model is *valid* for its frame when every raw pixel centre has a corrected position (the radial
function is monotone up to the frame's farthest pixel). :func:`check_valid` raises a ValueError
naming the valid parameter range otherwise; :func:`undistort_image` calls it, so an invalid model
never produces an image with silent holes.

Image correction (:func:`undistort_image`) samples the raw image at ``raw_from_corrected`` of every
canvas pixel through :mod:`registration.warp`; the source maps are computed once per
(model, canvas, interpolation) and cached (fixed point for bilinear, float for bicubic).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.warp import (
    INTERPOLATIONS,
    PreparedMap,
    prepare_source_map,
    remap,
    remap_prepared,
    source_map_from_function,
)

CANVASES = ("same", "full")
# Strongest pincushion correction accepted from a user (see harris_gamma_range).
HARRIS_GAMMA_MIN = -1.0
# Image correction offers these two; "nearest" stays available through registration.warp.
IMAGE_INTERPOLATIONS = ("linear", "cubic")
# The "full" canvas grows without bound as a model approaches its validity limit (the frame's
# corners move to infinity); refuse canvases larger than this many times the raw frame's area.
MAX_FULL_CANVAS_AREA_RATIO = 16.0
# cv2.remap's fixed-point maps hold int16 positions; canvases must stay well inside that.
MAX_CANVAS_SIDE = 32000
# Source maps are evaluated every MAP_STEP canvas pixels and interpolated (see
# correction_source_map); 4 keeps the interpolation error below 0.01 px.
MAP_STEP = 4


class _Radial:
    """Shared geometry of the radial models: centre, normalising radius and the frame's extent.

    Subclasses are frozen dataclasses with ``width``, ``height`` and ``center`` fields.
    """

    width: int
    height: int
    center: tuple[float, float] | None

    def _check_frame(self) -> None:
        if int(self.width) != self.width or int(self.height) != self.height:
            raise ValueError(f"frame size must be integer pixels, got {self.width}x{self.height}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"frame size must be positive, got {self.width}x{self.height}")
        if self.center is not None and (
            len(self.center) != 2 or not np.all(np.isfinite(np.asarray(self.center, float)))
        ):
            raise ValueError(f"center must be a finite (x, y) pair, got {self.center!r}")

    @property
    def c(self) -> NDArray[np.float64]:
        """Distortion centre ``(x, y)`` in raw pixels."""
        if self.center is None:
            return np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])
        return np.asarray(self.center, dtype=np.float64)

    @property
    def r_n(self) -> float:
        """Normalising radius: half the frame diagonal, in pixels."""
        return float(np.hypot(self.width, self.height) / 2.0)

    def max_raw_rho(self) -> float:
        """Largest normalised radius of a raw pixel centre from the distortion centre."""
        corners = np.array(
            [[0, 0], [self.width - 1, 0], [0, self.height - 1], [self.width - 1, self.height - 1]],
            dtype=np.float64,
        )
        return float(np.max(np.linalg.norm(corners - self.c, axis=1)) / self.r_n)

    def _frame_text(self) -> str:
        return f"{self.width}x{self.height} frame"

    def _scale_radially(self, xy: NDArray, factor_of_rho2) -> NDArray[np.float64]:
        """``c + (xy - c) * factor(ρ²)`` with ``ρ`` the normalised radius of ``xy``."""
        c = self.c
        d = (xy - c) / self.r_n
        rho2 = np.sum(d * d, axis=1)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            factor = factor_of_rho2(rho2)
        return c + (xy - c) * factor[:, None]

    def correction_stretch(self, xy: ArrayLike) -> tuple[NDArray, NDArray]:
        """Local magnification of ``corrected_from_raw`` at raw pixels ``xy`` (``(N, 2)``).

        Returns:
            ``(s_r, s_t)``, each ``(N,)``: corrected length per raw length along the radius
            (one-sided inward difference of 0.5 px, valid wherever ``xy`` is) and across it
            (corrected radius / raw radius); 1 at the centre, NaN where undefined.
        """
        xy = as_points(xy)
        c = self.c
        radial = xy - c
        r_raw = np.linalg.norm(radial, axis=1)
        ok = r_raw > 1e-9
        rhat = np.where(ok[:, None], radial / np.where(ok, r_raw, 1)[:, None], [1.0, 0.0])
        eps = np.minimum(0.5, r_raw)[:, None]
        corrected = self.corrected_from_raw(xy)
        inner = self.corrected_from_raw(xy - eps * rhat)
        with np.errstate(invalid="ignore", divide="ignore"):
            s_r = np.where(ok, np.linalg.norm(corrected - inner, axis=1) / eps[:, 0], 1.0)
            s_t = np.where(ok, np.linalg.norm(corrected - c, axis=1) / np.where(ok, r_raw, 1), 1.0)
        if not ok.all():
            # At the centre both equal the derivative of the radial map at 0.
            at0 = self.corrected_from_raw(c + [[0.5, 0.0]])[0]
            s0 = float(np.linalg.norm(at0 - c) / 0.5)
            s_r, s_t = np.where(ok, s_r, s0), np.where(ok, s_t, s0)
        return s_r, s_t

    # Subclasses: validity_problem() -> str | None, raw_from_corrected, corrected_from_raw.
    def validity_problem(self) -> str | None:  # pragma: no cover - overridden
        raise NotImplementedError

    def is_valid(self) -> bool:
        """True when every raw pixel centre has a corrected position (see :func:`check_valid`)."""
        return self.validity_problem() is None


@dataclass(frozen=True)
class HarrisModel(_Radial):
    """Harris radial distortion of a ``width`` x ``height`` raw frame (paper eq. 4).

    Attributes:
        gamma: distortion parameter γ (dimensionless); the paper's camera: 0.7 (paper 3).
        width, height: raw frame size in pixels.
        center: distortion centre ``(x, y)`` in raw pixels; None = the frame centre.
    """

    gamma: float
    width: int
    height: int
    center: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        self._check_frame()
        if not np.isfinite(self.gamma):
            raise ValueError(f"gamma must be finite, got {self.gamma}")

    @staticmethod
    def _apply(xy: NDArray, gamma: float, c: NDArray, r_n: float) -> NDArray:
        d = (xy - c) / r_n
        rho2 = np.sum(d * d, axis=1, keepdims=True)
        denom = 1.0 + gamma * rho2
        with np.errstate(invalid="ignore", divide="ignore"):
            out = c + r_n * d / np.sqrt(denom)
        out[(denom <= 0).ravel()] = np.nan
        return out

    def raw_from_corrected(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` corrected pixels -> ``(N, 2)`` raw pixels (NaN where undefined)."""
        return self._apply(as_points(xy), self.gamma, self.c, self.r_n)

    def corrected_from_raw(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels -> ``(N, 2)`` corrected pixels (the same formula with -γ)."""
        return self._apply(as_points(xy), -self.gamma, self.c, self.r_n)

    def correction_stretch(self, xy: ArrayLike) -> tuple[NDArray, NDArray]:
        """Exact local magnification of ``corrected_from_raw`` (see ``_Radial``): with
        ``F = 1 / sqrt(1 - γ ρ'²)`` the corrected radius is ``F`` times the raw one, so
        across the radius the stretch is ``F`` and along it ``dρ/dρ' = F³``."""
        d = (as_points(xy) - self.c) / self.r_n
        u = np.sum(d * d, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            f = 1.0 / np.sqrt(1.0 - self.gamma * u)
        return f**3, f

    def gamma_limit(self) -> float:
        """Largest valid γ (exclusive) for this frame and centre: ``1 / ρ'_max²``."""
        return harris_gamma_limit(self.width, self.height, self.center)

    def validity_problem(self) -> str | None:
        limit = self.gamma_limit()
        if self.gamma < limit:
            return None
        return (
            f"gamma {self.gamma:g} is out of range for a {self._frame_text()}: valid gamma < "
            f"{_floor(limit)} (raw pixels beyond normalised radius {1 / np.sqrt(self.gamma):.3f} "
            f"would have no corrected position; the farthest raw pixel is at "
            f"{self.max_raw_rho():.4f})"
        )

    def params(self) -> dict:
        return {"model": "harris", "gamma": float(self.gamma)}


@dataclass(frozen=True)
class TwoTermHarrisModel(_Radial):
    """Harris (paper eq. 4) plus a fourth-order radial term that no one-parameter Harris model
    can absorb: a lens beyond the paper's model (beyond the paper).

    Raw to corrected (normalised radii as in ``conventions.md``, ``ρ'`` raw, ``ρ`` corrected)::

        ρ = ρ' / sqrt(1 - γ ρ'² - k2 ρ'⁴)

    With ``k2 = 0`` this is exactly the Harris model (conventions: raw to corrected is the
    formula with ``-γ``), and the model delegates to :class:`HarrisModel` bit for bit. ``k2 > 0``
    bends the frame's outer part further (stronger barrel towards the corners), ``k2 < 0`` less.
    Corrected to raw is solved by Newton's method inside a bisection bracket, to ~1e-15 of
    ``r_n``.

    Attributes:
        gamma: Harris γ.
        k2: the fourth-order coefficient (dimensionless, radius normalised by ``r_n``).
        width, height: raw frame size, px.
        center: distortion centre ``(x, y)`` in raw pixels; None = the frame centre.
    """

    gamma: float
    k2: float
    width: int
    height: int
    center: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        self._check_frame()
        if not (np.isfinite(self.gamma) and np.isfinite(self.k2)):
            raise ValueError(f"gamma and k2 must be finite, got {self.gamma}, {self.k2}")

    @functools.cached_property
    def harris(self) -> HarrisModel:
        """The Harris model of γ alone."""
        return HarrisModel(self.gamma, self.width, self.height, self.center)

    @functools.cached_property
    def raw_rho_limit(self) -> float:
        """Largest normalised raw radius (exclusive) where the lens is defined and monotone:
        the first root of ``1 - γ u - k2 u²`` (``u = ρ'²``) or, for ``k2 < 0``, where
        ``dρ/dρ' ∝ 1 + k2 ρ'⁴`` vanishes; inf when neither exists."""
        g, k = float(self.gamma), float(self.k2)
        roots = np.roots([-k, -g, 1.0]) if k != 0 else (np.array([1.0 / g]) if g > 0 else [])
        u = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 and r.real > 0]
        lim = float(np.sqrt(min(u))) if u else float("inf")
        if k < 0:
            lim = min(lim, float((-1.0 / k) ** 0.25))
        return lim

    def _g(self, rho_raw: NDArray) -> NDArray:
        u = rho_raw * rho_raw
        with np.errstate(invalid="ignore", divide="ignore"):
            return rho_raw / np.sqrt(1.0 - self.gamma * u - self.k2 * u * u)

    def _dg(self, rho_raw: NDArray) -> NDArray:
        u = rho_raw * rho_raw
        d = 1.0 - self.gamma * u - self.k2 * u * u
        with np.errstate(invalid="ignore", divide="ignore"):
            return (1.0 + self.k2 * u * u) / (d * np.sqrt(d))

    def corrected_from_raw(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels -> ``(N, 2)`` corrected pixels (closed form; NaN where
        undefined)."""
        if self.k2 == 0:
            return self.harris.corrected_from_raw(xy)
        xy = as_points(xy)
        c, r_n = self.c, self.r_n
        d = (xy - c) / r_n
        u = np.sum(d * d, axis=1)
        den = 1.0 - self.gamma * u - self.k2 * u * u
        with np.errstate(invalid="ignore", divide="ignore"):
            out = c + r_n * d / np.sqrt(den)[:, None]
        out[~((den > 0) & (np.sqrt(u) < self.raw_rho_limit))] = np.nan
        return out

    def raw_from_corrected(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` corrected pixels -> ``(N, 2)`` raw pixels (Newton; NaN where no raw radius
        inside the lens's monotone range maps there)."""
        if self.k2 == 0:
            return self.harris.raw_from_corrected(xy)
        xy = as_points(xy)
        c, r_n = self.c, self.r_n
        target = np.linalg.norm(xy - c, axis=1) / r_n
        rho = self._solve(target)
        with np.errstate(invalid="ignore", divide="ignore"):
            factor = np.where(target > 0, rho / np.where(target > 0, target, 1.0), 1.0)
        return c + (xy - c) * factor[:, None]

    def _solve(self, target: NDArray) -> NDArray:
        """Raw radius ``ρ'`` with ``g(ρ') = target`` (g increasing on [0, raw_rho_limit))."""
        lim = self.raw_rho_limit
        finite = np.isfinite(target)
        t = np.where(finite, target, 0.0)
        if np.isfinite(lim):
            hi_val = lim * (1.0 - 1e-12)
            reach = float(self._g(np.array(hi_val)))
        else:
            hi_val = max(1.0, float(t.max(initial=0.0)))
            while float(self._g(np.array(hi_val))) < t.max(initial=0.0):
                hi_val *= 2.0
            reach = float("inf")
        lo = np.zeros_like(t)
        hi = np.full_like(t, hi_val)
        # Start from the Harris inverse (exact for k2 = 0), clipped into the bracket.
        with np.errstate(invalid="ignore", divide="ignore"):
            start = t / np.sqrt(1.0 + self.gamma * t * t)
        rho = np.where(np.isfinite(start) & (start > 0) & (start < hi), start, 0.5 * hi)
        for _ in range(200):
            f = self._g(rho) - t
            lo = np.where(f < 0, rho, lo)
            hi = np.where(f > 0, rho, hi)
            with np.errstate(invalid="ignore", divide="ignore"):
                new = rho - f / self._dg(rho)
            bad = ~(np.isfinite(new) & (new >= lo) & (new <= hi))
            new = np.where(bad, 0.5 * (lo + hi), new)
            done = np.all(np.abs(new - rho) <= 1e-15 + 1e-14 * np.abs(rho))
            rho = new
            if done:
                break
        rho[~finite | (t >= reach)] = np.nan
        return rho

    def validity_problem(self) -> str | None:
        """None when every raw pixel centre has a corrected position, else a one-line reason."""
        rho_m = self.max_raw_rho()
        if rho_m < self.raw_rho_limit:
            return None
        return (
            f"lens gamma {self.gamma:g}, k2 {self.k2:g} is not valid on a {self.width}x"
            f"{self.height} frame: raw radius {self.raw_rho_limit:.4f} < the farthest raw "
            f"pixel's {rho_m:.4f} (1 - gamma u - k2 u^2 must stay positive and 1 + k2 u^2 > 0 "
            "for u = rho'^2 up to the corners)"
        )

    def params(self) -> dict:
        return {"model": "harris+k2", "gamma": float(self.gamma), "k2": float(self.k2)}


@dataclass(frozen=True)
class PolynomialModel(_Radial):
    """Polynomial radial distortion (paper eq. 3): ``f(ρ) = ρ (1 + k1 ρ² + k2 ρ⁴ + k3 ρ⁶)``.

    ``f`` maps the corrected normalised radius to the raw one (same direction and normalisation
    as :class:`HarrisModel`); raw to corrected is solved numerically, to ~1e-12 of ``r_n``.

    Attributes:
        k1, k2, k3: coefficients (dimensionless, radius normalised by ``r_n``); barrel: k1 < 0.
        width, height: raw frame size in pixels.
        center: distortion centre ``(x, y)`` in raw pixels; None = the frame centre.
    """

    k1: float
    k2: float
    k3: float
    width: int
    height: int
    center: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        self._check_frame()
        if not np.all(np.isfinite([self.k1, self.k2, self.k3])):
            raise ValueError(f"k1, k2, k3 must be finite, got {(self.k1, self.k2, self.k3)}")

    @classmethod
    def from_harris(cls, model: HarrisModel) -> PolynomialModel:
        """Third-order Taylor expansion of a Harris model (a starting point for fits)."""
        g = model.gamma
        return cls(-g / 2, 3 * g**2 / 8, -5 * g**3 / 16, model.width, model.height, model.center)

    def _f(self, rho: NDArray) -> NDArray:
        r2 = rho * rho
        return rho * (1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3)))

    def _df(self, rho: NDArray) -> NDArray:
        r2 = rho * rho
        return 1 + r2 * (3 * self.k1 + r2 * (5 * self.k2 + r2 * 7 * self.k3))

    @functools.cached_property
    def _fold(self) -> tuple[float, float]:
        """``(ρ0, f(ρ0))``: first corrected radius where ``f' = 0`` (inf, inf when monotone)."""
        # f'(ρ) = 1 + 3k1 u + 5k2 u² + 7k3 u³ with u = ρ²: smallest positive real root.
        roots = np.roots([7 * self.k3, 5 * self.k2, 3 * self.k1, 1.0])
        real = roots[np.abs(roots.imag) < 1e-12].real if roots.size else np.array([])
        pos = real[real > 0]
        if pos.size == 0:
            return float("inf"), float("inf")
        rho0 = float(np.sqrt(pos.min()))
        return rho0, float(self._f(np.array(rho0)))

    def raw_from_corrected(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` corrected pixels -> ``(N, 2)`` raw pixels (closed form)."""
        k1, k2, k3 = self.k1, self.k2, self.k3
        out = self._scale_radially(as_points(xy), lambda u: 1 + u * (k1 + u * (k2 + u * k3)))
        # Beyond the fold f decreases again: those corrected radii are not the model's image of
        # any raw pixel, so they have no defined raw position.
        rho0 = self._fold[0]
        if np.isfinite(rho0):
            rho = np.linalg.norm((as_points(xy) - self.c) / self.r_n, axis=1)
            out[rho > rho0] = np.nan
        return out

    def corrected_from_raw(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels -> ``(N, 2)`` corrected pixels (NaN beyond the fold of ``f``)."""
        xy = as_points(xy)
        c = self.c
        target = np.linalg.norm(xy - c, axis=1) / self.r_n
        rho = self._solve(target)
        with np.errstate(invalid="ignore", divide="ignore"):
            factor = np.where(target > 0, rho / np.where(target > 0, target, 1), 1.0)
        return c + (xy - c) * factor[:, None]

    def _solve(self, target: NDArray) -> NDArray:
        """ρ in [0, ρ0] with f(ρ) = target, by Newton's method kept inside a bisection bracket."""
        rho0, f0 = self._fold
        lo = np.zeros_like(target)
        if np.isfinite(rho0):
            hi = np.full_like(target, rho0)
        else:
            h = max(1.0, float(target.max(initial=0.0)))
            while self._f(np.array(h)) < target.max(initial=0.0):
                h *= 2
            hi = np.full_like(target, h)
        rho = np.clip(target, lo, hi)
        for _ in range(100):
            fval = self._f(rho) - target
            lo = np.where(fval < 0, rho, lo)
            hi = np.where(fval > 0, rho, hi)
            d = self._df(rho)
            with np.errstate(invalid="ignore", divide="ignore"):
                step = fval / d
            new = rho - step
            outside = ~((new > lo) & (new < hi)) | ~np.isfinite(new)
            new = np.where(outside, 0.5 * (lo + hi), new)
            if np.all(np.abs(new - rho) <= 1e-15 + 1e-14 * np.abs(rho)):
                rho = new
                break
            rho = new
        rho = np.where(target > f0, np.nan, rho)
        return rho

    def validity_problem(self) -> str | None:
        rho_m = self.max_raw_rho()
        _, f0 = self._fold
        if f0 > rho_m:
            return None
        k1_min = -4.0 / (27.0 * rho_m**2)
        return (
            f"polynomial k=({self.k1:g}, {self.k2:g}, {self.k3:g}) is out of range for a "
            f"{self._frame_text()}: f(rho) folds over at raw radius {f0:.4f} < the farthest raw "
            f"pixel's {rho_m:.4f}, so outer raw pixels have no corrected position (with k2 = k3 "
            f"= 0 the valid range is k1 > {_ceil(k1_min)})"
        )

    def params(self) -> dict:
        return {"model": "polynomial", "k1": self.k1, "k2": self.k2, "k3": self.k3}


@dataclass(frozen=True)
class DivisionModel(_Radial):
    """One-parameter division model: raw to corrected is ``ρ = ρ' / (1 + λ ρ'²)``.

    Attributes:
        lam: λ (dimensionless, radius normalised by ``r_n``); barrel correction: λ < 0.
        width, height: raw frame size in pixels.
        center: distortion centre ``(x, y)`` in raw pixels; None = the frame centre.
    """

    lam: float
    width: int
    height: int
    center: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        self._check_frame()
        if not np.isfinite(self.lam):
            raise ValueError(f"lambda must be finite, got {self.lam}")

    def raw_from_corrected(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` corrected pixels -> ``(N, 2)`` raw pixels (NaN where undefined)."""
        lam = self.lam
        # 2 / (1 + sqrt(1 - 4λρ²)) is the rationalised root: stable at λ -> 0 and ρ -> 0.
        return self._scale_radially(as_points(xy), lambda u: 2.0 / (1.0 + np.sqrt(1 - 4 * lam * u)))

    def corrected_from_raw(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels -> ``(N, 2)`` corrected pixels (NaN where undefined)."""
        lam = self.lam

        def factor(u):
            den = 1.0 + lam * u
            # Past λρ'² = 1 (λ > 0) the map folds back; past 1 + λρ'² = 0 (λ < 0) it blows up.
            return np.where((den > 0) & (lam * u < 1), 1.0 / den, np.nan)

        return self._scale_radially(as_points(xy), factor)

    def lam_limits(self) -> tuple[float, float]:
        """Valid open interval of λ for this frame: ``(-1/ρ'_max², 1/ρ'_max²)``."""
        lim = 1.0 / self.max_raw_rho() ** 2
        return -lim, lim

    def validity_problem(self) -> str | None:
        lo, hi = self.lam_limits()
        if lo < self.lam < hi:
            return None
        return (
            f"division lambda {self.lam:g} is out of range for a {self._frame_text()}: valid "
            f"{_ceil(lo)} < lambda < {_floor(hi)} (outer raw pixels would have no corrected position)"
        )

    def params(self) -> dict:
        return {"model": "division", "lambda": float(self.lam)}


RadialModel = HarrisModel | TwoTermHarrisModel | PolynomialModel | DivisionModel


def _floor(v: float, digits: int = 4) -> str:
    """``v`` rounded down to ``digits`` decimals (an upper limit that is safe to quote)."""
    return f"{np.floor(v * 10**digits) / 10**digits:.{digits}f}"


def _ceil(v: float, digits: int = 4) -> str:
    return f"{np.ceil(v * 10**digits) / 10**digits:.{digits}f}"


def harris_gamma_limit(width: int, height: int, center: tuple[float, float] | None = None) -> float:
    """Supremum of valid Harris γ for a frame: ``1 / ρ'_max²`` (just above 1 for the centre).

    For γ at or above it, ``1 - γ ρ'²`` reaches 0 inside the frame and the farthest raw pixels
    have no corrected position. Any γ below it (including all negative γ) is valid. A 1x1 frame
    centred on its one pixel has no limit (inf).
    """
    rho = HarrisModel(0.0, width, height, center).max_raw_rho()
    return float("inf") if rho == 0 else 1.0 / rho**2


def harris_gamma_range(
    width: int, height: int, center: tuple[float, float] | None = None
) -> tuple[float, float]:
    """The γ a user may ask for: ``[HARRIS_GAMMA_MIN, harris_gamma_limit)``.

    Every γ below the limit is mathematically valid, but pincushion correction stronger than
    γ = -1 shrinks the frame's corners to less than 71 % of their radius (γ = -50: 14 %, a
    mostly black image): no lens this project meets needs it, and it is what a mistyped sign
    or value produces. Automatic estimation searches the same range.
    """
    return HARRIS_GAMMA_MIN, harris_gamma_limit(width, height, center)


def check_harris_gamma(
    gamma: float, width: int, height: int, center: tuple[float, float] | None = None
) -> float:
    """``gamma`` if it is in :func:`harris_gamma_range`, else ValueError naming the range."""
    lo, hi = harris_gamma_range(width, height, center)
    if not (np.isfinite(gamma) and lo <= gamma < hi):
        where = "" if center is None else f" with centre ({center[0]:g}, {center[1]:g})"
        raise ValueError(
            f"gamma {gamma:g} is out of range for a {width}x{height} frame{where}: valid "
            f"{lo:g} <= gamma < {_floor(hi)} (below {lo:g} the corrected frame shrinks to "
            f"a small disc; at the upper limit the farthest raw pixels have no corrected "
            f"position)"
        )
    return float(gamma)


def check_valid(model: RadialModel) -> RadialModel:
    """Raise ValueError naming the valid parameter range unless every raw pixel of the model's
    frame has a corrected position; returns ``model`` for chaining."""
    problem = model.validity_problem()
    if problem:
        raise ValueError(problem)
    return model


# --------------------------------------------------------------------------------------------
# Image correction


@dataclass(frozen=True)
class CanvasInfo:
    """Where a corrected image's pixels lie in corrected-frame coordinates.

    Canvas pixel ``(i, j)`` (column, row) shows corrected coordinate ``origin + (i, j)``.

    Attributes:
        kind: ``"same"`` (raw frame's size and centre, paper Fig. 2; origin (0, 0)) or
            ``"full"`` (the bounding box of the whole raw frame's content after correction).
        width, height: canvas size in pixels.
        origin: corrected coordinate ``(x, y)`` of canvas pixel (0, 0), whole pixels.
    """

    kind: str
    width: int
    height: int
    origin: tuple[float, float] = (0.0, 0.0)

    def canvas_from_corrected(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` corrected-frame pixels -> ``(N, 2)`` canvas pixels."""
        return as_points(xy) - np.asarray(self.origin)

    def corrected_from_canvas(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` canvas pixels -> ``(N, 2)`` corrected-frame pixels."""
        return as_points(xy) + np.asarray(self.origin)

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "width": self.width,
            "height": self.height,
            "origin": [float(self.origin[0]), float(self.origin[1])],
        }


def _raw_boundary(width: int, height: int) -> NDArray[np.float64]:
    """Every pixel centre on the raw frame's border, ``(N, 2)``."""
    xs = np.arange(width, dtype=np.float64)
    ys = np.arange(height, dtype=np.float64)
    return np.concatenate(
        [
            np.stack([xs, np.zeros_like(xs)], 1),
            np.stack([xs, np.full_like(xs, height - 1)], 1),
            np.stack([np.zeros_like(ys), ys], 1),
            np.stack([np.full_like(ys, width - 1), ys], 1),
        ]
    )


def correction_canvas(model: RadialModel, canvas: str = "same") -> CanvasInfo:
    """The canvas :func:`undistort_image` renders on (see :class:`CanvasInfo`).

    Raises:
        ValueError: unknown ``canvas``, invalid model, or a "full" canvas that would exceed
            ``MAX_FULL_CANVAS_AREA_RATIO`` times the raw frame's area.
    """
    if canvas not in CANVASES:
        raise ValueError(f"canvas must be one of {', '.join(CANVASES)}, got {canvas!r}")
    check_valid(model)
    w, h = int(model.width), int(model.height)
    if canvas == "same":
        return CanvasInfo("same", w, h, (0.0, 0.0))
    # Radial maps are monotone in ρ, so the frame border's image bounds the whole frame's.
    corrected = model.corrected_from_raw(_raw_boundary(w, h))
    x0, y0 = np.floor(corrected.min(axis=0))
    x1, y1 = np.ceil(corrected.max(axis=0))
    cw, ch = int(x1 - x0 + 1), int(y1 - y0 + 1)
    if cw * ch > MAX_FULL_CANVAS_AREA_RATIO * w * h or max(cw, ch) > MAX_CANVAS_SIDE:
        raise ValueError(
            f"the full canvas for {_describe(model)} would be {cw}x{ch} px "
            f"(more than {MAX_FULL_CANVAS_AREA_RATIO:g}x the {w}x{h} frame's area): the model is "
            f"close to its validity limit; use canvas 'same'"
        )
    return CanvasInfo("full", cw, ch, (float(x0), float(y0)))


def _describe(model: RadialModel) -> str:
    p = {k: v for k, v in model.params().items() if k != "model"}
    vals = ", ".join(f"{k} {v:g}" for k, v in p.items())
    return f"{model.params()['model']} model ({vals})"


def correction_source_map(
    model: RadialModel, canvas: str = "same"
) -> tuple[NDArray[np.float32], CanvasInfo]:
    """Uncached float32 ``(H_c, W_c, 2)`` source map (canvas pixel -> raw pixel) and its canvas."""
    info = correction_canvas(model, canvas)
    # Evaluating every 4th pixel and interpolating is ~20x faster and within 0.002 px on a
    # 2560x1920 frame at gamma 0.7; where canvas pixels have no raw source (NaN, e.g. pincushion
    # correction on the "same" canvas) the coarse grid would widen the hole by up to 4 px, so
    # such maps are evaluated exactly.
    source_map = source_map_from_function(
        model.raw_from_corrected, info.width, info.height, step=MAP_STEP, origin=info.origin
    )
    if np.isnan(source_map).any():
        source_map = source_map_from_function(
            model.raw_from_corrected, info.width, info.height, origin=info.origin
        )
    return source_map, info


@functools.lru_cache(maxsize=6)
def _prepared_correction(
    model: RadialModel, canvas: str, interpolation: str
) -> tuple[PreparedMap, CanvasInfo]:
    source_map, info = correction_source_map(model, canvas)
    return prepare_source_map(source_map, interpolation=interpolation), info


def clear_map_cache() -> None:
    """Drop the cached correction maps (each 2560x1920 map holds ~30 MB)."""
    _prepared_correction.cache_clear()


def _check_image(image: NDArray, model: RadialModel, what: str = "image") -> None:
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
        shape = getattr(image, "shape", None)
        raise ValueError(f"{what} must be a non-empty (H, W) or (H, W, C) array, got shape {shape}")
    h, w = image.shape[:2]
    if (w, h) != (model.width, model.height):
        raise ValueError(
            f"{what} is {w}x{h} but the distortion model is for a {model.width}x{model.height} frame"
        )


def undistort_image(
    image: NDArray,
    model: RadialModel,
    *,
    canvas: str = "same",
    interpolation: str = "linear",
    border_value: float | tuple[float, ...] = 0,
) -> tuple[NDArray, CanvasInfo]:
    """Correct a raw image's radial distortion (paper eq. 1: ``I_1(x) = I_0(D(x))``).

    The source map for (model, canvas, interpolation) is computed once and cached, prepared by
    :func:`registration.warp.prepare_source_map` (fixed point for bilinear, float for bicubic),
    so correcting every frame of a video costs one ``cv2.remap`` each.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` raw image; ``(W, H)`` must equal the model's frame.
        model: a valid radial model (:func:`check_valid` is applied).
        canvas: ``"same"``: the raw frame's size and centre (paper Fig. 2; barrel correction
            crops the outer raw content); ``"full"``: a larger canvas holding every raw pixel.
        interpolation: ``"linear"`` (bilinear) or ``"cubic"`` (bicubic).
        border_value: value of canvas pixels with no raw source.

    Returns:
        ``(corrected, info)``: the corrected image (``(H_c, W_c[, C])``, the input's dtype) and
        the :class:`CanvasInfo` mapping its pixels to corrected-frame coordinates.
    """
    if interpolation not in IMAGE_INTERPOLATIONS:
        raise ValueError(
            f"interpolation must be one of {', '.join(IMAGE_INTERPOLATIONS)}, got {interpolation!r}"
        )
    if canvas not in CANVASES:
        raise ValueError(f"canvas must be one of {', '.join(CANVASES)}, got {canvas!r}")
    _check_image(image, model)
    check_valid(model)
    prepared, info = _prepared_correction(model, canvas, interpolation)
    return remap_prepared(image, prepared, border_value=border_value), info


def distort_image(
    straight: NDArray,
    model: RadialModel,
    *,
    origin: tuple[float, float] = (0.0, 0.0),
    interpolation: str = "linear",
    border_value: float | tuple[float, ...] = 0,
) -> NDArray:
    """Synthesise a raw (distorted) frame from an undistorted image (the inverse of correction).

    Raw pixel ``x'`` samples ``straight`` at ``corrected_from_raw(x') - origin``; so ``straight``
    pixel (0, 0) shows corrected coordinate ``origin`` (give a larger image and a negative origin
    to fill the raw frame's corners under barrel distortion).

    Args:
        straight: ``(H_s, W_s[, C])`` image of the undistorted world.
        model: a valid radial model; the output has its frame size.
        origin: corrected coordinate of ``straight``'s pixel (0, 0).
        interpolation: ``"nearest"``, ``"linear"`` or ``"cubic"``.
        border_value: value for raw pixels whose source lies outside ``straight``.

    Returns:
        ``(model.height, model.width[, C])`` raw image.
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(
            f"interpolation must be one of {sorted(INTERPOLATIONS)}, got {interpolation!r}"
        )
    check_valid(model)
    ox, oy = origin
    source_map = source_map_from_function(
        lambda xy: model.corrected_from_raw(xy) - (ox, oy), int(model.width), int(model.height)
    )
    return remap(straight, source_map, interpolation=interpolation, border_value=border_value)


def simulate_raw_frame(
    scene: NDArray,
    model: RadialModel,
    *,
    max_zoom_out: float = 2.5,
    interpolation: str = "linear",
    return_mask: bool = False,
) -> tuple[NDArray, float] | tuple[NDArray, float, NDArray[np.bool_]]:
    """A raw frame of ``model``'s size seeing ``scene`` (undistorted) through the lens.

    ``scene`` is resized (INTER_AREA, keeping its aspect ratio) so that, centred on the
    distortion centre, it covers every raw pixel's corrected position, up to ``max_zoom_out``
    times the frame's half extent (models near their validity limit send the corners to
    infinity; beyond that the frame shows ``0``). Used to test γ estimation on real imagery.

    The scene's border is a perfectly straight line in the world: where it shows in the raw
    frame (the black corners beyond ``max_zoom_out``) it is a fake edge that obeys the model
    exactly. ``return_mask`` gives the raw pixels that see the scene, so an estimator can be
    told to ignore the rest.

    Args:
        scene: ``(H_s, W_s[, C])`` undistorted image.
        model: a valid radial model; the output has its frame size.
        max_zoom_out: cap on covered extent / frame extent.
        interpolation: resampling of the raw frame.
        return_mask: also return the ``(H, W)`` bool mask of raw pixels whose every
            interpolation neighbour lies inside the scene.

    Returns:
        ``(raw, scale)`` or, with ``return_mask``, ``(raw, scale, mask)``: the raw frame and the
        resize factor applied to ``scene`` (scene pixel ``p`` appears at corrected coordinate
        ``c + (p - c_s) * scale``, ``c_s`` its centre).
    """
    import cv2

    if interpolation not in INTERPOLATIONS:
        raise ValueError(
            f"interpolation must be one of {sorted(INTERPOLATIONS)}, got {interpolation!r}"
        )
    check_valid(model)
    w, h = int(model.width), int(model.height)
    corrected = model.corrected_from_raw(_raw_boundary(w, h))
    half = np.abs(corrected - model.c).max(axis=0)
    zoom = min(max(half[0] / (w / 2), half[1] / (h / 2)) * 1.02, max_zoom_out)
    hs, ws = scene.shape[:2]
    scale = max(zoom * w / ws, zoom * h / hs)
    size = (max(round(ws * scale), 1), max(round(hs * scale), 1))
    big = cv2.resize(scene, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC)
    ox, oy = (model.c[0] - (size[0] - 1) / 2, model.c[1] - (size[1] - 1) / 2)
    source_map = source_map_from_function(lambda xy: model.corrected_from_raw(xy) - (ox, oy), w, h)
    raw = remap(big, source_map, interpolation=interpolation, border_value=0)
    if not return_mask:
        return raw, float(size[0] / ws)
    # Source positions whose interpolation neighbours all lie in the scene: nearest rounds,
    # bilinear reads floor and floor + 1, bicubic floor - 1 .. floor + 2.
    lo, hi = {"nearest": (-0.5, 0.5), "linear": (0.0, 1.0), "cubic": (1.0, 3.0)}[interpolation]
    sx, sy = source_map[..., 0], source_map[..., 1]
    with np.errstate(invalid="ignore"):
        mask = (sx >= lo) & (sx <= size[0] - hi) & (sy >= lo) & (sy <= size[1] - hi)
    return raw, float(size[0] / ws), mask
