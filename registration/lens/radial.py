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
canvas pixel through :mod:`registration.geometry.warp`; the source maps are computed once per
(model, canvas, interpolation) and cached (fixed point for bilinear, float for bicubic).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points

# Strongest pincushion correction accepted from a user (see harris_gamma_range).
HARRIS_GAMMA_MIN = -1.0


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
