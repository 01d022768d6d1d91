"""What every geometric model shares: the protocol, the falsy estimation failure, input
checks, the coordinate normalisation, the optimisers (our Levenberg-Marquardt, Nelder-Mead),
parameter quantisation, and the inverse and chain wrappers.

The models themselves are in :mod:`registration.rational` (projective, polyprojective) and
:mod:`registration.models` (translation, similarity, affine; the public entry point, which
re-exports everything here that callers use).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points

__all__ = [
    "OPTIMIZERS",
    "Chain",
    "FailedEstimation",
    "GeometricModel",
    "Inverted",
    "Normalisation",
    "levenberg_marquardt",
    "quantize",
    "quantized",
]

OPTIMIZERS = ("lstsq", "lm", "nelder-mead")

Array = NDArray[np.float64]

# Relative singular-value level below which a point set or a design matrix counts as rank
# deficient. Far above float64 round-off (1e-16) and far below anything a real, well spread
# point set produces in normalised coordinates.
_RANK_TOL = 1e-9


# --------------------------------------------------------------------------------------------
# Failure object and protocol
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FailedEstimation:
    """Falsy result of an estimation that could not produce a model.

    Attributes:
        reason: one line saying why, e.g. ``"degenerate: source points are collinear"``.
    """

    reason: str

    def __bool__(self) -> bool:
        return False

    def __str__(self) -> str:
        return self.reason


@runtime_checkable
class GeometricModel(Protocol):
    """What every model provides. All point arrays are ``(N, 2)`` float64 pixels."""

    min_samples: ClassVar[int]

    @property
    def params(self) -> Array: ...

    def apply(self, xy: ArrayLike) -> Array: ...

    def inverse(self, xy: ArrayLike) -> Array: ...

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> Array: ...

    def with_params(self, params: ArrayLike) -> GeometricModel: ...

    def compose(self, other: GeometricModel) -> GeometricModel: ...

    def to_dict(self) -> dict[str, Any]: ...


def _residuals(model: Any, src: ArrayLike, dst: ArrayLike) -> Array:
    src_ = as_points(src, "src")
    dst_ = as_points(dst, "dst")
    if src_.shape != dst_.shape:
        raise ValueError(f"src and dst must have the same shape, got {src_.shape} and {dst_.shape}")
    return np.hypot(*(model.apply(src_) - dst_).T)


def _check_pair(src: ArrayLike, dst: ArrayLike, weights: ArrayLike | None):
    """Validate shapes (raise) and return (src, dst, weights or None) as float64 arrays."""
    src_ = as_points(src, "src")
    dst_ = as_points(dst, "dst")
    if src_.shape != dst_.shape:
        raise ValueError(f"src and dst must have the same shape, got {src_.shape} and {dst_.shape}")
    w = None
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (src_.shape[0],):
            raise ValueError(f"weights must have shape ({src_.shape[0]},), got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weights must be finite and non-negative")
    return src_, dst_, w


def _check_optimizer(optimizer: str) -> None:
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {optimizer!r}")


def _nonfinite_reason(src: Array, dst: Array, w: Array | None) -> str | None:
    if not np.all(np.isfinite(src)):
        return (
            f"non-finite source coordinates ({int((~np.isfinite(src)).any(axis=1).sum())} points)"
        )
    if not np.all(np.isfinite(dst)):
        return f"non-finite destination coordinates ({int((~np.isfinite(dst)).any(axis=1).sum())} points)"
    if w is not None and not np.any(w > 0):
        return "all weights are zero"
    return None


# --------------------------------------------------------------------------------------------
# Normalisation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Normalisation:
    """Isotropic similarity ``n = (x - center) * scale`` from pixels to normalised coordinates.

    Attributes:
        center: ``(cx, cy)`` pixel mapped to the origin.
        scale: normalised units per pixel (> 0).
    """

    center: tuple[float, float] = (0.0, 0.0)
    scale: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"Normalisation.scale must be finite and > 0, got {self.scale}")
        cx, cy = self.center
        object.__setattr__(self, "center", (float(cx), float(cy)))
        object.__setattr__(self, "scale", float(self.scale))

    @classmethod
    def from_points(cls, xy: ArrayLike) -> Normalisation:
        """Map the bounding box of the finite points in ``xy`` into ``[-1, 1]`` (longer side).

        Coincident points give the identity scale around their position.
        """
        pts = as_points(xy)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts) == 0:
            return cls()
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        half = float(np.max(hi - lo)) / 2.0
        return cls(tuple((lo + hi) / 2.0), 1.0 / half if half > 0 else 1.0)

    @classmethod
    def for_extent(cls, width: float, height: float) -> Normalisation:
        """Map an image of ``width`` x ``height`` pixels (centres ``0..W-1``) into ``[-1, 1]``."""
        if width <= 0 or height <= 0:
            raise ValueError(f"image extent must be positive, got {width}x{height}")
        half = max(width, height) / 2.0
        return cls(((width - 1) / 2.0, (height - 1) / 2.0), 1.0 / half)

    @property
    def matrix(self) -> Array:
        """3x3 homogeneous matrix of the map pixels -> normalised."""
        s = self.scale
        return np.array([[s, 0, -s * self.center[0]], [0, s, -s * self.center[1]], [0, 0, 1.0]])

    def forward(self, xy: Array) -> Array:
        """Pixels ``(N, 2)`` -> normalised ``(N, 2)``."""
        return (xy - np.asarray(self.center)) * self.scale

    def backward(self, xy: Array) -> Array:
        """Normalised ``(N, 2)`` -> pixels ``(N, 2)``."""
        return xy / self.scale + np.asarray(self.center)

    def rescaled(self, s: float) -> Normalisation:
        """The same normalised frame for coordinates rescaled by ``s`` (``x_s = (x+.5)s-.5``)."""
        c = (np.asarray(self.center) + 0.5) * s - 0.5
        return Normalisation((float(c[0]), float(c[1])), self.scale / s)

    def to_dict(self) -> dict[str, Any]:
        return {"center": list(self.center), "scale": self.scale}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Normalisation:
        return cls(tuple(d["center"]), float(d["scale"]))


# --------------------------------------------------------------------------------------------
# Optimisers and quantisation
# --------------------------------------------------------------------------------------------


# A stage's output model is rounded to multiples of 2^-34 (~6e-11) in its parameters (of order
# one in normalised coordinates, so ~1e-7 px). It was introduced against MINPACK, whose result
# depends in its last bits on the memory alignment of its work arrays; our own
# :func:`levenberg_marquardt` does not, and the rounding stays as a guard for any other
# last-bit difference (another BLAS, another thread count): unrounded, ~1e-13 differences
# decide which control points REQCON drops and which cells the local stage keeps downstream,
# and two runs would drift apart by pixels.
_QUANTUM_EXP = 34


def quantize(params: Array) -> Array:
    """``params`` rounded to multiples of ``2**-34`` (see above)."""
    p = np.asarray(params, np.float64)
    return np.ldexp(np.round(np.ldexp(p, _QUANTUM_EXP)), -_QUANTUM_EXP)


def quantized(model: Any) -> Any:
    """``model`` with its parameters rounded by :func:`quantize` (None stays None)."""
    return None if model is None else model.with_params(quantize(model.params))


def _refine(
    p0: Array,
    fun: Callable[[Array], Array],
    jac: Callable[[Array], Array] | None,
    optimizer: str,
) -> Array:
    """Minimise the sum of squared geometric residuals from ``p0`` with the chosen optimiser."""
    if optimizer == "lm":
        if jac is not None and len(fun(p0)) >= len(p0):
            return levenberg_marquardt(p0, fun, jac)
        res = scipy.optimize.least_squares(
            fun, p0, jac=jac if jac is not None else "2-point", method="trf",
            ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=200 * (len(p0) + 1),
        )  # fmt: skip
        return res.x
    if optimizer == "nelder-mead":
        return _nelder_mead(p0, fun)
    return p0


def levenberg_marquardt(
    p0: Array,
    fun: Callable[[Array], Array],
    jac: Callable[[Array], Array],
    *,
    tol: float = 1e-12,
    max_nfev: int | None = None,
) -> Array:
    """Levenberg-Marquardt minimisation of ``|fun(p)|^2`` from ``p0``, in numpy.

    Marquardt's damping scaled by the Jacobian's column norms (kept at their largest, as
    MINPACK does), solved through the normal equations of the column-scaled problem (17-29
    parameters of normalised coordinates: well enough conditioned). Stops when a step lowers the
    cost by less than ``tol`` relative, or is shorter than ``tol`` relative to the scaled
    parameters, or after ``max_nfev`` evaluations (``200 (n + 1)`` by default).

    Why not MINPACK (``scipy.optimize.least_squares(method="lm")``): its vectorised loops peel
    differently with the memory alignment of its work arrays, so the same residuals and
    Jacobians gave trial steps differing in their last bits from one process to the next, and
    the fit ended ~1e-9 apart; REQCON and the next frames amplified that to pixels. Here every
    operation is a BLAS/LAPACK call or an element-wise numpy operation whose result does not
    depend on where its arrays lie, so the same inputs give the same bits in every process.
    """
    p = np.array(p0, dtype=np.float64)
    n = len(p)
    max_nfev = 200 * (n + 1) if max_nfev is None else int(max_nfev)
    r = fun(p)
    cost = float(r @ r)
    if not math.isfinite(cost):
        return p
    nfev, nu = 1, 2.0
    J = jac(p)
    scale = np.sqrt((J * J).sum(axis=0))
    lam = None
    while nfev < max_nfev:
        scale = np.where(scale > 0, scale, 1.0)
        # The problem in scaled parameters u = scale * p: unit-diagonal normal equations.
        js = J / scale
        a = js.T @ js
        g = js.T @ r
        if not (np.isfinite(a).all() and np.isfinite(g).all()):
            return p  # no usable Jacobian here (the model undefined at a point)
        if lam is None:
            lam = max(1e-3 * float(np.max(np.diag(a))), 1e-12)
        if float(np.max(np.abs(g))) <= tol * math.sqrt(cost):
            return p  # gradient zero to working precision
        # The most the quadratic model can still gain (the undamped step's reduction): the
        # convergence test, which a heavily damped step's small reduction cannot fake.
        u_gn = np.linalg.lstsq(a, -g, rcond=None)[0]
        gain = float(-g @ u_gn)
        if gain <= tol * cost:
            return p
        # The undamped step first: damping turns the step towards the gradient, which can point
        # into the denominator barrier (a fit ending on it) where the full step clears it.
        undamped = True
        while nfev < max_nfev:
            if undamped:
                u = u_gn
            else:
                try:
                    u = np.linalg.solve(a + lam * np.eye(n), -g)
                except np.linalg.LinAlgError:
                    u = np.full(n, np.nan)
            if not np.isfinite(u).all():
                lam, nu, undamped = lam * nu, nu * 2.0, False
                nfev += 1  # counted as a trial: this loop must end
                if not lam <= 1e16:  # NaN too
                    return p
                continue
            if float(np.linalg.norm(u)) <= tol * (float(np.linalg.norm(scale * p)) + tol):
                return p
            trial = p + u / scale
            r_trial = fun(trial)
            nfev += 1
            c_trial = float(r_trial @ r_trial)
            predicted = -float(2.0 * (g @ u) + u @ a @ u)
            actual = cost - c_trial if math.isfinite(c_trial) else -math.inf
            if predicted > 0 and actual > 0:
                # Nielsen's update: less damping the better the quadratic model predicted.
                rho = actual / predicted
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                p, r, cost = trial, r_trial, c_trial
                if not lam <= 1e16:
                    # Accepted steps the quadratic model keeps mispredicting (rho ~ 0, gains at
                    # rounding level: a fit pressed against the denominator barrier) double the
                    # damping each time: nothing more to gain.
                    return p
                break
            if undamped:
                undamped = False  # no say on the damping
                continue
            lam, nu = lam * nu, min(nu * 2.0, 1e6)
            if not lam <= 1e16:  # NaN too
                return p
        J = jac(p)
        scale = np.maximum(scale, np.sqrt((J * J).sum(axis=0)))
    return p


def _nelder_mead(p0: Array, fun: Callable[[Array], Array]) -> Array:
    """Nelder-Mead (paper 4.3) on the sum of squared residuals, restarted until it stalls.

    ``adaptive=True`` (Gao & Han parameters) is needed beyond ~10 dimensions. The initial simplex
    steps each normalised coefficient by 1e-3 (about half a pixel at 1000 px extents). A fresh
    simplex around the result is started while that still lowers the cost by more than 1e-9
    relative: a single NM run often collapses its simplex before reaching the minimum.
    """

    def cost(p: Array) -> float:
        r = fun(p)
        v = float(r @ r)
        return v if math.isfinite(v) else math.inf

    n = len(p0)
    p = np.asarray(p0, dtype=np.float64).copy()
    f = cost(p)
    step = 1e-3
    for _ in range(8):
        simplex = np.vstack([p, p + step * np.eye(n)])
        res = scipy.optimize.minimize(
            cost,
            p,
            method="Nelder-Mead",
            options={
                "adaptive": True,
                "initial_simplex": simplex,
                "xatol": 1e-10,
                "fatol": 1e-12 * max(f, 1e-12),
                "maxfev": 2000 * n,
            },
        )
        improved = f - res.fun
        if res.fun < f:
            p, f = res.x, float(res.fun)
        if improved <= 1e-9 * max(f, 1e-300):
            break
        step = max(step * 0.1, 1e-7)
    return p


# --------------------------------------------------------------------------------------------
# Composition helpers
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Inverted:
    """The inverse of a model as a model: ``apply`` is ``model.inverse`` and vice versa."""

    model: Any
    min_samples: ClassVar[int] = 0

    @property
    def params(self) -> Array:
        return self.model.params

    def apply(self, xy: ArrayLike) -> Array:
        return self.model.inverse(xy)

    __call__ = apply

    def inverse(self, xy: ArrayLike) -> Array:
        return self.model.apply(xy)

    def inverted(self) -> Any:
        return self.model

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> Array:
        return _residuals(self, src, dst)

    def with_params(self, params: ArrayLike) -> Inverted:
        return Inverted(self.model.with_params(params))

    def compose(self, other: Any) -> Chain:
        return Chain(self, other)

    def to_dict(self) -> dict[str, Any]:
        return {"type": "Inverted", "model": self.model.to_dict()}

    @classmethod
    def estimate(cls, src: ArrayLike, dst: ArrayLike, **_: Any) -> FailedEstimation:
        return FailedEstimation("an Inverted model cannot be estimated; estimate the forward model")


@dataclass(frozen=True, eq=False)
class Chain:
    """``outer(inner(x))`` for models that do not compose in closed form (no ``estimate``)."""

    outer: Any
    inner: Any
    min_samples: ClassVar[int] = 0

    @property
    def params(self) -> Array:
        return np.concatenate([self.outer.params, self.inner.params])

    def apply(self, xy: ArrayLike) -> Array:
        return self.outer.apply(self.inner.apply(xy))

    __call__ = apply

    def inverse(self, xy: ArrayLike) -> Array:
        return self.inner.inverse(self.outer.inverse(xy))

    def inverted(self) -> Chain:
        inv = [
            m.inverted() if hasattr(m, "inverted") else Inverted(m)
            for m in (self.inner, self.outer)
        ]
        return Chain(inv[0], inv[1])

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> Array:
        return _residuals(self, src, dst)

    def with_params(self, params: ArrayLike) -> Chain:
        p = np.asarray(params, dtype=np.float64)
        k = len(self.outer.params)
        return Chain(self.outer.with_params(p[:k]), self.inner.with_params(p[k:]))

    def compose(self, other: Any) -> Chain:
        return Chain(self, other)

    def to_dict(self) -> dict[str, Any]:
        return {"type": "Chain", "outer": self.outer.to_dict(), "inner": self.inner.to_dict()}

    @classmethod
    def estimate(cls, src: ArrayLike, dst: ArrayLike, **_: Any) -> FailedEstimation:
        return FailedEstimation("a Chain cannot be estimated; estimate its parts")
