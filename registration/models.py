"""Geometric models behind one protocol: translation, projective and polyprojective (paper eq. 5).

Every model maps ``(N, 2)`` float64 ``(x, y)`` pixel arrays to ``(N, 2)`` arrays and is named
target-first by its users (``base_from_frame``). Models are immutable (frozen dataclasses);
``with_params`` returns a new one.

The projective and polyprojective models work internally in *normalised* coordinates: a
similarity (:class:`Normalisation`) maps the source points' bounding box (or an image extent) to
about ``[-1, 1]`` and another one does the same for the destination. The normalisations are part
of the model, and ``params`` (what optimisers see) are the coefficients in normalised space, so
every coefficient is of order one and well conditioned, whatever the image size. ``apply`` and
``inverse`` convert from and to pixels.

Estimation (``Model.estimate``) returns the model or a falsy :class:`FailedEstimation` carrying a
reason (too few points, non-finite input, collinear or otherwise degenerate points). It starts
from a linear (normalised DLT) solution, or from ``initial``, and optionally refines the geometric
error (Euclidean distance in destination pixels) with Levenberg-Marquardt or Nelder-Mead.

References:
    Loveland & Rosten, "Acquisition and registration of aerial video imagery of urban traffic",
    section 4.3.2, eq. 5 (polyprojective / rational polynomial model).
    Hartley & Zisserman, "Multiple View Geometry", 2nd ed., algorithm 4.2 (normalised DLT).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
import scipy.optimize
import scipy.spatial
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points

__all__ = [
    "OPTIMIZERS",
    "Affine",
    "Chain",
    "FailedEstimation",
    "GeometricModel",
    "Inverted",
    "MIN_DENOMINATOR",
    "Normalisation",
    "PolyProjective",
    "Projective",
    "Similarity",
    "Translation",
    "model_from_dict",
    "n_polyprojective_params",
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
# Rational polynomial machinery (shared by Projective = degree 1 and PolyProjective)
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=16)
def _exponents(degree: int) -> tuple[tuple[int, int], ...]:
    """Monomial exponents ``(i, j)`` of ``u^i v^j`` in the paper's order (eq. 5).

    Descending total degree, and within a degree descending power of ``u``; so the list ends with
    ``u, v, 1`` and for degree 1 the coefficients are the homography's rows.
    """
    return tuple((i, d - i) for d in range(degree, -1, -1) for i in range(d, -1, -1))


def n_polyprojective_params(degree: int) -> int:
    """Number of free coefficients of a degree-``n`` polyprojective: ``3 (n+1)(n+2)/2 - 1``.

    >>> n_polyprojective_params(2), n_polyprojective_params(3)
    (17, 29)
    """
    return 3 * (degree + 1) * (degree + 2) // 2 - 1


def _powers(x: Array, degree: int) -> Array:
    out = np.empty((degree + 1,) + x.shape)
    out[0] = 1.0
    for k in range(1, degree + 1):
        out[k] = out[k - 1] * x
    return out


def _design(un: Array, degree: int) -> Array:
    """Monomials ``phi`` of normalised points ``un`` (N, 2) -> (N, J)."""
    pu, pv = _powers(un[:, 0], degree), _powers(un[:, 1], degree)
    return np.stack([pu[i] * pv[j] for i, j in _exponents(degree)], axis=1)


def _split(params: Array, degree: int) -> tuple[Array, Array, Array]:
    """Rows ``a``, ``b``, ``c`` (the last with its constant 1 appended), each (J,)."""
    j = (degree + 1) * (degree + 2) // 2
    return params[:j], params[j : 2 * j], np.append(params[2 * j :], 1.0)


def _forward_n(params: Array, degree: int, un: Array) -> tuple[Array, Array, Array]:
    """Normalised forward map: returns (xn (N,2), denominator D (N,), phi (N,J))."""
    a, b, c = _split(params, degree)
    phi = _design(un, degree)
    den = phi @ c
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = np.stack([phi @ a, phi @ b], axis=1) / den[:, None]
    return xn, den, phi


def _degenerate_points_reason(pts: Array, which: str) -> str | None:
    centred = pts - pts.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    if s[0] <= 0 or not np.isfinite(s[0]):
        return f"degenerate: all {which} points coincide"
    if s[1] / s[0] < _RANK_TOL:
        return f"degenerate: {which} points are collinear"
    return None


def _collinear_triple(pts: Array) -> bool:
    """True when any 3 of a few points are (nearly) collinear (minimal-sample check)."""
    n = len(pts)
    scale = max(float(np.ptp(pts, axis=0).max()), 1e-300)
    for i in range(n):
        for j in range(i + 1, n):
            for k in range(j + 1, n):
                d1, d2 = pts[j] - pts[i], pts[k] - pts[i]
                if abs(d1[0] * d2[1] - d1[1] * d2[0]) < 1e-9 * scale * scale:
                    return True
    return False


def _dlt(sn: Array, dn: Array, degree: int, w: Array | None) -> Array | str:
    """Normalised DLT: homogeneous least squares for (a, b, c) with ||.|| = 1, then c0 := 1.

    Each pair gives ``a.phi - x c.phi = 0`` and ``b.phi - y c.phi = 0``. Returns the params or a
    failure reason.
    """
    phi = _design(sn, degree)
    n, j = phi.shape
    zeros = np.zeros_like(phi)
    rows_x = np.hstack([phi, zeros, -dn[:, :1] * phi])
    rows_y = np.hstack([zeros, phi, -dn[:, 1:] * phi])
    a_mat = np.vstack([rows_x, rows_y])
    if w is not None:
        sw = np.sqrt(w)
        a_mat = a_mat * np.concatenate([sw, sw])[:, None]
    if a_mat.shape[0] < a_mat.shape[1]:
        # Pad so that the SVD returns a full right basis (the null space has dimension >= 1).
        a_mat = np.vstack([a_mat, np.zeros((a_mat.shape[1] - a_mat.shape[0], a_mat.shape[1]))])
    _, s, vt = np.linalg.svd(a_mat, full_matrices=False)
    if not np.all(np.isfinite(s)):
        return "non-finite design matrix"
    if s[-2] < _RANK_TOL * s[0]:
        return (
            f"degenerate: the points do not determine the {3 * j - 1} coefficients "
            f"(design matrix rank {int(np.sum(s > _RANK_TOL * s[0]))} < {3 * j - 1})"
        )
    h = vt[-1]
    if abs(h[-1]) < 1e-12 * np.max(np.abs(h)):
        return "degenerate: the solution maps the centre of the source points to infinity"
    h = h / h[-1]
    return h[:-1]


def _linear_poly(sn: Array, dn: Array, degree: int, w: Array | None) -> Array | str:
    """Linear start for degree >= 2: full numerators over a *linear* denominator.

    Solves ``a.phi - x (c_u u + c_v v) = x`` (and the same for ``y``) in least squares, with the
    denominator's terms of degree >= 2 fixed at 0. Why not the full DLT: with all of ``c`` free,
    any model multiplied top and bottom by a common linear factor ``1 + alpha u + beta v`` maps
    (almost) the same, so for a near-projective scene the full linear system has a near
    3-dimensional null space and, with noise, returns a model whose denominator vanishes inside
    the image. The nonlinear refinement then frees all of ``c`` (paper eq. 5).
    """
    phi = _design(sn, degree)
    n, j = phi.shape
    uv = sn  # the degree-1 terms of the denominator
    zeros = np.zeros_like(phi)
    a_mat = np.vstack(
        [np.hstack([phi, zeros, -dn[:, :1] * uv]), np.hstack([zeros, phi, -dn[:, 1:] * uv])]
    )
    rhs = np.concatenate([dn[:, 0], dn[:, 1]])
    if w is not None:
        sw = np.concatenate([np.sqrt(w), np.sqrt(w)])
        a_mat, rhs = a_mat * sw[:, None], rhs * sw
    if a_mat.shape[0] < a_mat.shape[1]:
        return f"degenerate: {n} point pairs cannot determine a degree-{degree} polyprojective"
    sv = np.linalg.svd(a_mat, compute_uv=False)
    if not np.all(np.isfinite(sv)):
        return "non-finite design matrix"
    rank = int(np.sum(sv > _RANK_TOL * sv[0]))
    if rank < a_mat.shape[1]:
        return (
            f"degenerate: the points do not determine a degree-{degree} polyprojective "
            f"(linear design rank {rank} < {a_mat.shape[1]})"
        )
    sol = np.linalg.lstsq(a_mat, rhs, rcond=None)[0]
    p = np.zeros(n_polyprojective_params(degree))
    p[: 2 * j] = sol[: 2 * j]
    p[-2:] = sol[2 * j :]
    return p


# Smallest denominator ``c.phi`` (1 at the source normalisation's centre) that the nonlinear fit
# may reach on the control points and on a grid over their bounding box. Not in the paper: it is
# a barrier that keeps the model from folding through infinity inside the region it is fitted
# on, which a polyprojective can otherwise do at almost no cost (numerator and denominator
# sharing a linear factor that changes sign). A factor of 10 in the denominator across the
# image is far more perspective than an aerial view shows.
MIN_DENOMINATOR = 0.1

# Residual value (pixels) returned for parameters beyond the barrier: optimisers reject the step.
_BARRIER_RESIDUAL = 1e8


def _domain_grid(sn: Array, k: int = 9) -> Array:
    lo, hi = sn.min(axis=0), sn.max(axis=0)
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], k), np.linspace(lo[1], hi[1], k))
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def _geometric_fun(
    degree: int,
    sn: Array,
    dst: Array,
    dst_norm: Normalisation,
    sw: Array | None,
    p0: Array,
    domain_n: Array | None = None,
):
    """Residual vector (2N,) in destination pixels and its Jacobian, for normalised params.

    Parameters whose denominator drops below a floor on the points, on their bounding box or on
    the extra ``domain_n`` points (normalised) give the constant residual ``_BARRIER_RESIDUAL``
    (a barrier; see there), for degree >= 2. The floor is :data:`MIN_DENOMINATOR`, or the
    start ``p0``'s own smallest denominator there when it is lower but positive: a start from a
    previous fit that ended on the floor (then rounded, :func:`quantized`) lies a hair under
    it, and turning the barrier off for it let a re-anchored frame's fit put a pole inside the
    frame (a corner 172 px off). When ``p0`` already folds somewhere there, parameters that
    fold the map at one of the points themselves (denominator <= 0 there) still get the barrier
    residual, as long as ``p0`` does not: a long Gauss-Newton step from such a start otherwise
    lands on a fold that lets a few outliers fit (seen re-anchoring a long flight's frame).
    """
    phi = _design(sn, degree)
    phic = phi[:, :-1]
    j = phi.shape[1]
    dn = dst_norm.forward(dst)
    inv_s = 1.0 / dst_norm.scale
    parts = [phi, _design(_domain_grid(sn), degree)]
    if domain_n is not None and len(domain_n):
        parts.append(_design(domain_n, degree))
    phi_all = np.vstack(parts)
    barrier = np.full(2 * len(sn), _BARRIER_RESIDUAL)
    start_min = float(np.min(phi_all @ _split(p0, degree)[2]))
    use_barrier = degree >= 2 and start_min > 0
    floor = min(MIN_DENOMINATOR, start_min)
    no_fold = degree >= 2 and not use_barrier and bool(np.min(phi @ _split(p0, degree)[2]) > 0)

    def fun(p: Array) -> Array:
        a, b, c = _split(p, degree)
        if use_barrier and np.min(phi_all @ c) < floor:
            return barrier
        if no_fold and not np.min(phi @ c) > 0:
            return barrier
        den = phi @ c
        r = np.concatenate([(phi @ a / den - dn[:, 0]), (phi @ b / den - dn[:, 1])]) * inv_s
        if sw is not None:
            r *= np.concatenate([sw, sw])
        return r

    def jac(p: Array) -> Array:
        a, b, c = _split(p, degree)
        den = phi @ c
        xn, yn = phi @ a / den, phi @ b / den
        g = phi / den[:, None] * inv_s
        n = len(den)
        out = np.zeros((2 * n, 3 * j - 1))
        out[:n, :j] = g
        out[n:, j : 2 * j] = g
        out[:n, 2 * j :] = -(xn / den * inv_s)[:, None] * phic
        out[n:, 2 * j :] = -(yn / den * inv_s)[:, None] * phic
        if sw is not None:
            out *= np.concatenate([sw, sw])[:, None]
        return out

    return fun, jac


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


class _RationalModel:
    """Shared implementation of ``x' = (a.phi(u), b.phi(u)) / c.phi(u)`` in normalised space."""

    params: Array
    src_norm: Normalisation
    dst_norm: Normalisation

    @property
    def degree(self) -> int:
        raise NotImplementedError

    def _post_init(self) -> None:
        p = np.array(self.params, dtype=np.float64).reshape(-1)
        expected = n_polyprojective_params(self.degree)
        if p.shape != (expected,):
            raise ValueError(
                f"{type(self).__name__} of degree {self.degree} needs {expected} params, got {p.shape}"
            )
        p.flags.writeable = False
        object.__setattr__(self, "params", p)

    def apply(self, xy: ArrayLike) -> Array:
        """Map source pixels ``(N, 2)`` to destination pixels ``(N, 2)`` (inf/NaN at D = 0)."""
        un = self.src_norm.forward(as_points(xy))
        a, b, c = _split(self.params, self.degree)
        coef = np.stack([a, b, c])
        out = np.empty_like(un)
        chunk = 1 << 16  # cache-sized blocks
        with np.errstate(divide="ignore", invalid="ignore"):
            for lo in range(0, len(un), chunk):
                blk = un[lo : lo + chunk]
                pu, pv = _powers(blk[:, 0], self.degree), _powers(blk[:, 1], self.degree)
                f = np.zeros((3, len(blk)))
                for k, (i, j) in enumerate(_exponents(self.degree)):
                    f += coef[:, k : k + 1] * (pu[i] * pv[j])
                out[lo : lo + chunk] = (f[:2] / f[2]).T
        return self.dst_norm.backward(out)

    __call__ = apply

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> Array:
        """Euclidean distances ``|apply(src) - dst|`` in destination pixels, shape ``(N,)``."""
        return _residuals(self, src, dst)

    def denominator(self, xy: ArrayLike) -> Array:
        """The homogeneous denominator ``c.phi(u)`` at source pixels (> 0 where the map is valid)."""
        pts = as_points(xy)
        _, den, _ = _forward_n(self.params, self.degree, self.src_norm.forward(pts))
        return den

    def with_params(self, params: ArrayLike):
        """The same model type and normalisation with new normalised-space params."""
        return dataclasses.replace(self, params=np.asarray(params, dtype=np.float64))

    def rescaled(self, src_scale: float, dst_scale: float):
        """The model for coordinates rescaled as ``x_s = (x + 0.5) s - 0.5`` on each side.

        ``new.apply(rescale(x, src_scale)) == rescale(self.apply(x), dst_scale)``. A projective
        fitted at 1/4 scale becomes the full-scale one with ``rescaled(4, 4)``. Exact: only the
        normalisations change, the normalised params are kept.
        """
        for name, s in (("src_scale", src_scale), ("dst_scale", dst_scale)):
            if not (math.isfinite(s) and s > 0):
                raise ValueError(f"{name} must be finite and > 0, got {s}")
        return dataclasses.replace(
            self,
            src_norm=self.src_norm.rescaled(src_scale),
            dst_norm=self.dst_norm.rescaled(dst_scale),
        )

    def _projective_matrix_n(self) -> Array:
        """The degree-<=1 part as a normalised 3x3 homography (exact for Projective)."""
        a, b, c = _split(self.params, self.degree)
        return np.array([a[-3:], b[-3:], c[-3:]])

    def to_dict(self) -> dict[str, Any]:
        """JSON-able description; :func:`model_from_dict` restores it exactly."""
        return {
            "type": _base_name(self),
            "degree": self.degree,
            "params": [float(v) for v in self.params],
            "src_norm": self.src_norm.to_dict(),
            "dst_norm": self.dst_norm.to_dict(),
        }

    @classmethod
    def _estimate_rational(
        cls,
        degree: int,
        src: ArrayLike,
        dst: ArrayLike,
        *,
        initial: Any,
        optimizer: str,
        weights: ArrayLike | None,
        label: str,
        min_samples: int,
        make: Callable[[Array, Normalisation, Normalisation], Any],
        domain: ArrayLike | None = None,
    ):
        _check_optimizer(optimizer)
        s, d, w = _check_pair(src, dst, weights)
        n = len(s)
        if n < min_samples:
            return FailedEstimation(
                f"needs at least {min_samples} point pairs for {label}, got {n}"
            )
        reason = _nonfinite_reason(s, d, w)
        if reason is None:
            reason = _degenerate_points_reason(s, "source") or _degenerate_points_reason(
                d, "destination"
            )
        if reason is None and n == 4 and degree == 1:
            if _collinear_triple(s):
                reason = "degenerate: 3 of the 4 source points are collinear"
            elif _collinear_triple(d):
                reason = "degenerate: 3 of the 4 destination points are collinear"
        if reason is not None:
            return FailedEstimation(reason)

        if initial is not None:
            src_norm, dst_norm = initial.src_norm, initial.dst_norm
        else:
            src_norm, dst_norm = Normalisation.from_points(s), Normalisation.from_points(d)
        sn = src_norm.forward(s)
        if initial is not None and optimizer != "lstsq":
            p0 = np.array(initial.params, dtype=np.float64)
        else:
            dn = dst_norm.forward(d)
            p0 = _dlt(sn, dn, degree, w) if degree == 1 else _linear_poly(sn, dn, degree, w)
            if isinstance(p0, str):
                return FailedEstimation(p0)
        if optimizer != "lstsq":
            domain_n = None if domain is None else src_norm.forward(as_points(domain, "domain"))
            fun, jac = _geometric_fun(
                degree, sn, d, dst_norm, None if w is None else np.sqrt(w), p0, domain_n
            )
            p0 = _refine(p0, fun, jac, optimizer)
        if not np.all(np.isfinite(p0)):
            return FailedEstimation(f"non-finite parameters after {optimizer} fit")
        _, den, _ = _forward_n(p0, degree, sn)
        if not np.all(den > 0):
            return FailedEstimation(
                f"degenerate: the model's denominator is <= 0 at {int(np.sum(~(den > 0)))} of the "
                f"{n} source points (the map folds through infinity)"
            )
        return make(p0, src_norm, dst_norm)


def _base_name(model: Any) -> str:
    for name, t in _TYPES.items():
        if isinstance(model, t):
            return name
    return type(model).__name__


def _identity_params(degree: int) -> Array:
    j = (degree + 1) * (degree + 2) // 2
    p = np.zeros(n_polyprojective_params(degree))
    p[j - 3] = 1.0  # a: u
    p[2 * j - 2] = 1.0  # b: v
    return p


# --------------------------------------------------------------------------------------------
# Translation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Translation:
    """``x' = x + t``; params ``(tx, ty)`` in pixels."""

    params: Array = field(default_factory=lambda: np.zeros(2))
    min_samples: ClassVar[int] = 1

    def __post_init__(self) -> None:
        p = np.array(self.params, dtype=np.float64).reshape(-1)
        if p.shape != (2,):
            raise ValueError(f"Translation needs 2 params, got {p.shape}")
        p.flags.writeable = False
        object.__setattr__(self, "params", p)

    def apply(self, xy: ArrayLike) -> Array:
        """Source pixels ``(N, 2)`` -> destination pixels ``(N, 2)``."""
        return as_points(xy) + self.params

    __call__ = apply

    def inverse(self, xy: ArrayLike) -> Array:
        """Destination pixels ``(N, 2)`` -> source pixels ``(N, 2)`` (exact)."""
        return as_points(xy) - self.params

    def inverted(self) -> Translation:
        return Translation(-self.params)

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> Array:
        """Euclidean distances ``|apply(src) - dst|`` in pixels, shape ``(N,)``."""
        return _residuals(self, src, dst)

    def with_params(self, params: ArrayLike) -> Translation:
        return Translation(np.asarray(params, dtype=np.float64))

    def as_projective(self) -> Projective:
        return Projective.from_matrix(
            np.array([[1, 0, self.params[0]], [0, 1, self.params[1]], [0, 0, 1.0]])
        )

    def compose(self, other: Any) -> Any:
        """The model of ``self(other(x))``."""
        if isinstance(other, Translation):
            return Translation(self.params + other.params)
        if isinstance(other, Projective):
            return self.as_projective().compose(other)
        return Chain(self, other)

    def to_dict(self) -> dict[str, Any]:
        return {"type": "Translation", "params": [float(v) for v in self.params]}

    @classmethod
    def estimate(
        cls,
        src: ArrayLike,
        dst: ArrayLike,
        *,
        initial: Translation | None = None,
        optimizer: str = "lstsq",
        weights: ArrayLike | None = None,
    ) -> Translation | FailedEstimation:
        """Weighted mean displacement.

        That closed form is the exact minimiser of the sum of squared Euclidean residuals, so
        every ``optimizer`` returns it and ``initial`` is not needed.
        """
        _check_optimizer(optimizer)
        s, d, w = _check_pair(src, dst, weights)
        if len(s) < 1:
            return FailedEstimation("needs at least 1 point pair for a translation, got 0")
        reason = _nonfinite_reason(s, d, w)
        if reason is not None:
            return FailedEstimation(reason)
        return cls(np.average(d - s, axis=0, weights=w))


# --------------------------------------------------------------------------------------------
# Projective
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Projective(_RationalModel):
    """Homography with ``h33 = 1`` in normalised coordinates; 8 params.

    ``params = (h11, h12, h13, h21, h22, h23, h31, h32)`` of the normalised matrix
    ``Hn = T_dst H T_src^-1``; :attr:`matrix` is the pixel-space ``H`` scaled to ``H[2,2] = 1``.
    """

    params: Array = field(default_factory=lambda: _identity_params(1))
    src_norm: Normalisation = Normalisation()
    dst_norm: Normalisation = Normalisation()
    min_samples: ClassVar[int] = 4

    def __post_init__(self) -> None:
        self._post_init()

    @property
    def degree(self) -> int:
        return 1

    @classmethod
    def from_matrix(
        cls,
        matrix: ArrayLike,
        src_norm: Normalisation | None = None,
        dst_norm: Normalisation | None = None,
    ) -> Projective:
        """Build from a pixel-space 3x3 homography, expressed in the given normalisations."""
        h = np.asarray(matrix, dtype=np.float64)
        if h.shape != (3, 3) or not np.all(np.isfinite(h)):
            raise ValueError(f"matrix must be a finite 3x3 array, got shape {h.shape}")
        src_norm = src_norm or Normalisation()
        dst_norm = dst_norm or Normalisation()
        hn = dst_norm.matrix @ h @ np.linalg.inv(src_norm.matrix)
        if abs(hn[2, 2]) < 1e-12 * np.abs(hn).max():
            raise ValueError(
                "matrix maps the source normalisation centre to infinity; choose another src_norm"
            )
        hn = hn / hn[2, 2]
        return cls(hn.reshape(-1)[:8], src_norm, dst_norm)

    @property
    def matrix(self) -> Array:
        """Pixel-space 3x3 homography with ``H[2, 2] = 1`` (when finite)."""
        hn = np.append(self.params, 1.0).reshape(3, 3)
        h = np.linalg.inv(self.dst_norm.matrix) @ hn @ self.src_norm.matrix
        return h / h[2, 2] if abs(h[2, 2]) > 1e-300 else h

    def inverse(self, xy: ArrayLike) -> Array:
        """Exact inverse map ``(N, 2)``; NaN for points mapped from infinity."""
        pts = self.dst_norm.forward(as_points(xy))
        try:
            hi = np.linalg.inv(np.append(self.params, 1.0).reshape(3, 3))
        except np.linalg.LinAlgError:  # singular homography: no point has a unique preimage
            return np.full(pts.shape, np.nan)
        x, y = pts[:, 0], pts[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            w = hi[2, 0] * x + hi[2, 1] * y + hi[2, 2]
            un = np.empty_like(pts)
            un[:, 0] = (hi[0, 0] * x + hi[0, 1] * y + hi[0, 2]) / w
            un[:, 1] = (hi[1, 0] * x + hi[1, 1] * y + hi[1, 2]) / w
        out = self.src_norm.backward(un)
        out[~np.isfinite(out).all(axis=1)] = np.nan
        return out

    def inverted(self) -> Projective:
        """The inverse model (swapped normalisations)."""
        hi = np.linalg.inv(np.append(self.params, 1.0).reshape(3, 3))
        return Projective((hi / hi[2, 2]).reshape(-1)[:8], self.dst_norm, self.src_norm)

    def compose(self, other: Any) -> Any:
        """The model of ``self(other(x))``: Projective for a Projective/Translation, else a Chain."""
        if isinstance(other, Translation):
            other = other.as_projective()
        if isinstance(other, Projective):
            h = self.matrix @ other.matrix
            try:
                return Projective.from_matrix(h, other.src_norm, self.dst_norm)
            except ValueError:
                return Chain(self, other)
        return Chain(self, other)

    @classmethod
    def estimate(
        cls,
        src: ArrayLike,
        dst: ArrayLike,
        *,
        initial: Projective | None = None,
        optimizer: str = "lstsq",
        weights: ArrayLike | None = None,
    ) -> Projective | FailedEstimation:
        """Fit ``dst ~ H src`` to ``(N, 2)`` pixel pairs, N >= 4.

        Args:
            src, dst: ``(N, 2)`` pixel coordinates.
            initial: start for ``"lm"``/``"nelder-mead"``, re-expressed (exactly) in the data's
                normalisations; without it the normalised DLT gives the start.
            optimizer: ``"lstsq"`` (normalised DLT only), ``"lm"`` or ``"nelder-mead"`` (geometric
                error in destination pixels).
            weights: optional ``(N,)`` non-negative weights of the squared residuals.

        Returns:
            The model, or a falsy :class:`FailedEstimation` with the reason.
        """
        if initial is not None:
            # Re-express the start in the data's normalisations (exact for a homography), so
            # that e.g. a pixel-space ``from_matrix`` start is as well conditioned as a DLT one.
            try:
                initial = Projective.from_matrix(
                    initial.matrix, Normalisation.from_points(src), Normalisation.from_points(dst)
                )
            except ValueError:
                pass  # non-finite input or centre at infinity: keep it; estimate reports why
        return cls._estimate_rational(
            1, src, dst, initial=initial, optimizer=optimizer, weights=weights,
            label="a projective", min_samples=4,
            make=lambda p, sn, dn: cls(p, sn, dn),
        )  # fmt: skip

    @classmethod
    def minimal_batch(cls, src: Array, dst: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Normalised DLT of many samples at once (RANSAC's inner loop): ``(B, k, 2)`` each side
        (k >= 4) -> ``(B, 3, 3)`` pixel homographies and ``(B,)`` validity. Invalid: a collinear
        triple on either side, or a homography that folds (denominator <= 0 at a sample point),
        the same checks as :meth:`estimate`."""
        b, k = src.shape[:2]
        ok = ~(_batch_collinear(src) | _batch_collinear(dst))
        ts, sn = _batch_normalise(src)
        td, dn = _batch_normalise(dst)
        x, y = sn[..., 0], sn[..., 1]
        u, v = dn[..., 0], dn[..., 1]
        z, o = np.zeros_like(x), np.ones_like(x)
        rows_u = np.stack([x, y, o, z, z, z, -u * x, -u * y, -u], axis=2)
        rows_v = np.stack([z, z, z, x, y, o, -v * x, -v * y, -v], axis=2)
        a = np.concatenate([rows_u, rows_v], axis=1)  # (B, 2k, 9)
        with np.errstate(all="ignore"):
            _, _, vh = np.linalg.svd(np.nan_to_num(a), full_matrices=True)
            hn = vh[:, -1, :].reshape(b, 3, 3)
            h = np.linalg.inv(td) @ hn @ ts
            den = np.einsum("bj,bkj->bk", h[:, 2, :], np.concatenate([src, np.ones((b, k, 1))], 2))
            sign = np.where(np.mean(den, axis=1) < 0, -1.0, 1.0)
            h = h * sign[:, None, None]
            den = den * sign[:, None]
            h = h / np.where(np.abs(h[:, 2, 2]) > 1e-300, h[:, 2, 2], 1.0)[:, None, None]
        ok &= (den > 0).all(axis=1) & np.isfinite(h).all(axis=(1, 2))
        return h, ok


# --------------------------------------------------------------------------------------------
# Affine and similarity (beyond the paper: the coarse step's model selection and its
# one-point-plus-seed samples)
# --------------------------------------------------------------------------------------------


def _batch_collinear(pts: Array) -> NDArray[np.bool_]:
    """``(B,)`` True where any 3 of a sample's points ``(B, k, 2)`` are (nearly) collinear."""
    k = pts.shape[1]
    scale = np.maximum(np.ptp(pts, axis=1).max(axis=1), 1e-300)
    bad = np.zeros(len(pts), bool)
    for i in range(k):
        for j in range(i + 1, k):
            for m in range(j + 1, k):
                d1, d2 = pts[:, j] - pts[:, i], pts[:, m] - pts[:, i]
                bad |= np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) < 1e-9 * scale * scale
    return bad


def _batch_normalise(pts: Array) -> tuple[Array, Array]:
    """Per-sample similarity ``(B, 3, 3)`` taking points ``(B, k, 2)`` to zero mean and mean
    distance sqrt(2), and the normalised points."""
    c = pts.mean(axis=1)
    dist = np.sqrt(((pts - c[:, None]) ** 2).sum(axis=2)).mean(axis=1)
    sc = np.sqrt(2.0) / np.maximum(dist, 1e-300)
    t = np.zeros((len(pts), 3, 3))
    t[:, 0, 0] = t[:, 1, 1] = sc
    t[:, :2, 2] = -sc[:, None] * c
    t[:, 2, 2] = 1.0
    return t, (pts - c[:, None]) * sc[:, None, None]


class _LinearModel:
    """Shared part of :class:`Affine` and :class:`Similarity`: ``x' = A x + t`` in pixels.

    Both are linear in their parameters, so least squares is their exact geometric fit and every
    optimizer gives it. ``matrix`` is the pixel-space 3x3 matrix; ``as_projective`` turns the
    model into the equivalent :class:`Projective` (what the rest of the pipeline consumes).
    """

    params: Array

    @property
    def matrix(self) -> Array:
        raise NotImplementedError

    def apply(self, xy: ArrayLike) -> Array:
        """Source pixels ``(N, 2)`` -> destination pixels ``(N, 2)``."""
        m = self.matrix
        return as_points(xy) @ m[:2, :2].T + m[:2, 2]

    __call__ = apply

    def inverse(self, xy: ArrayLike) -> Array:
        """Destination pixels ``(N, 2)`` -> source pixels (exact; NaN for a singular model)."""
        m = self.matrix
        pts = as_points(xy)
        try:
            a_inv = np.linalg.inv(m[:2, :2])
        except np.linalg.LinAlgError:
            return np.full(pts.shape, np.nan)
        return (pts - m[:2, 2]) @ a_inv.T

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> Array:
        """Euclidean distances ``|apply(src) - dst|`` in destination pixels, shape ``(N,)``."""
        return _residuals(self, src, dst)

    def with_params(self, params: ArrayLike):
        return type(self)(np.asarray(params, dtype=np.float64))

    def as_projective(self) -> Projective:
        return Projective.from_matrix(self.matrix)

    def compose(self, other: Any) -> Any:
        """The model of ``self(other(x))`` (a Projective, or a Chain for non-linear ``other``)."""
        return self.as_projective().compose(other)

    def rescaled(self, src_scale: float, dst_scale: float):
        """The model for coordinates rescaled as ``x_s = (x + 0.5) s - 0.5`` on each side."""
        to_src = np.array([[1 / src_scale, 0, 0.5 / src_scale - 0.5], [0, 1 / src_scale,
                           0.5 / src_scale - 0.5], [0, 0, 1.0]])  # fmt: skip
        to_dst = np.array([[dst_scale, 0, 0.5 * dst_scale - 0.5], [0, dst_scale,
                           0.5 * dst_scale - 0.5], [0, 0, 1.0]])  # fmt: skip
        return type(self).from_matrix(to_dst @ self.matrix @ to_src)

    def to_dict(self) -> dict[str, Any]:
        return {"type": type(self).__name__, "params": [float(v) for v in self.params]}

    @classmethod
    def from_matrix(cls, matrix: ArrayLike):
        raise NotImplementedError

    @classmethod
    def _checked(cls, src, dst, weights, optimizer):
        _check_optimizer(optimizer)
        s, d, w = _check_pair(src, dst, weights)
        if len(s) < cls.min_samples:
            return FailedEstimation(
                f"needs at least {cls.min_samples} point pairs for {cls._label}, got {len(s)}"
            )
        reason = _nonfinite_reason(s, d, w)
        if reason is None and cls.min_samples >= 3:
            reason = _degenerate_points_reason(s, "source") or _degenerate_points_reason(
                d, "destination"
            )
        if reason is None and np.ptp(s, axis=0).max() <= 0:
            reason = "degenerate: all source points coincide"
        if reason is not None:
            return FailedEstimation(reason)
        return s, d, (np.ones(len(s)) if w is None else w)


@dataclass(frozen=True, eq=False)
class Affine(_LinearModel):
    """``x' = A x + t``; params ``(a11, a12, tx, a21, a22, ty)`` in pixels."""

    params: Array = field(default_factory=lambda: np.array([1.0, 0, 0, 0, 1.0, 0]))
    min_samples: ClassVar[int] = 3
    _label: ClassVar[str] = "an affine"

    def __post_init__(self) -> None:
        p = np.array(self.params, dtype=np.float64).reshape(-1)
        if p.shape != (6,):
            raise ValueError(f"Affine needs 6 params, got {p.shape}")
        p.flags.writeable = False
        object.__setattr__(self, "params", p)

    @property
    def matrix(self) -> Array:
        return np.vstack([self.params.reshape(2, 3), [0.0, 0.0, 1.0]])

    @classmethod
    def from_matrix(cls, matrix: ArrayLike) -> Affine:
        m = np.asarray(matrix, dtype=np.float64)
        return cls((m[:2] / m[2, 2]).reshape(-1))

    @classmethod
    def estimate(
        cls,
        src: ArrayLike,
        dst: ArrayLike,
        *,
        initial: Any = None,
        optimizer: str = "lstsq",
        weights: ArrayLike | None = None,
    ) -> Affine | FailedEstimation:
        """Weighted least squares on ``(N, 2)`` pixel pairs, N >= 3 (exact geometric fit)."""  # fmt: skip
        checked = cls._checked(src, dst, weights, optimizer)
        if isinstance(checked, FailedEstimation):
            return checked
        s, d, w = checked
        c_s, c_d = np.average(s, axis=0, weights=w), np.average(d, axis=0, weights=w)
        sw = np.sqrt(w)[:, None]
        a, *_ = np.linalg.lstsq((s - c_s) * sw, (d - c_d) * sw, rcond=None)
        lin = a.T
        if not np.all(np.isfinite(lin)) or abs(np.linalg.det(lin)) < 1e-12 * np.abs(lin).max() ** 2:
            return FailedEstimation("degenerate: the affine fit is singular")
        return cls(np.c_[lin, c_d - lin @ c_s].reshape(-1))

    @classmethod
    def minimal_batch(cls, src: Array, dst: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Exact affines of many 3-point samples: ``(B, 3, 2)`` each side -> ``(B, 3, 3)``
        pixel matrices and ``(B,)`` validity (False for collinear samples)."""
        b = len(src)
        ok = ~(_batch_collinear(src) | _batch_collinear(dst))
        m = np.tile(np.eye(3), (b, 1, 1))
        if ok.any():
            a = np.concatenate([src[ok], np.ones((int(ok.sum()), 3, 1))], axis=2)  # rows [x y 1]
            sol = np.linalg.solve(a, dst[ok])  # (n, 3, 2): A^T stacked with t
            m[ok, :2, :] = np.transpose(sol, (0, 2, 1))
        return m, ok & np.isfinite(m).all(axis=(1, 2))


@dataclass(frozen=True, eq=False)
class Similarity(_LinearModel):
    """``x' = s R(theta) x + t``; params ``(a, b, tx, ty)`` with ``s R = [[a, -b], [b, a]]``.

    ``theta`` is counter-clockwise in the (x right, y down) image, i.e. clockwise on screen;
    :attr:`rotation_deg` and :attr:`scale` read it back.
    """

    params: Array = field(default_factory=lambda: np.array([1.0, 0, 0, 0]))
    min_samples: ClassVar[int] = 2
    _label: ClassVar[str] = "a similarity"

    def __post_init__(self) -> None:
        p = np.array(self.params, dtype=np.float64).reshape(-1)
        if p.shape != (4,):
            raise ValueError(f"Similarity needs 4 params, got {p.shape}")
        p.flags.writeable = False
        object.__setattr__(self, "params", p)

    @classmethod
    def from_rotation(
        cls, rotation_deg: float, scale: float, src_point: ArrayLike, dst_point: ArrayLike
    ) -> Similarity:
        """The similarity of the given rotation and scale sending ``src_point`` to ``dst_point``."""
        th = math.radians(rotation_deg)
        a, b = scale * math.cos(th), scale * math.sin(th)
        (x, y), (u, v) = np.asarray(src_point, float), np.asarray(dst_point, float)
        return cls(np.array([a, b, u - (a * x - b * y), v - (b * x + a * y)]))

    @property
    def matrix(self) -> Array:
        a, b, tx, ty = self.params
        return np.array([[a, -b, tx], [b, a, ty], [0.0, 0.0, 1.0]])

    @property
    def scale(self) -> float:
        return float(math.hypot(self.params[0], self.params[1]))

    @property
    def rotation_deg(self) -> float:
        return float(math.degrees(math.atan2(self.params[1], self.params[0])))

    @classmethod
    def from_matrix(cls, matrix: ArrayLike) -> Similarity:
        """The similarity part of a 3x3 matrix (exact for a similarity matrix)."""
        m = np.asarray(matrix, dtype=np.float64) / matrix[2][2]
        a, b = (m[0, 0] + m[1, 1]) / 2, (m[1, 0] - m[0, 1]) / 2
        return cls(np.array([a, b, m[0, 2], m[1, 2]]))

    @classmethod
    def estimate(
        cls,
        src: ArrayLike,
        dst: ArrayLike,
        *,
        initial: Any = None,
        optimizer: str = "lstsq",
        weights: ArrayLike | None = None,
    ) -> Similarity | FailedEstimation:
        """Weighted least squares (Umeyama without reflection) on ``(N, 2)`` pairs, N >= 2."""  # fmt: skip
        checked = cls._checked(src, dst, weights, optimizer)
        if isinstance(checked, FailedEstimation):
            return checked
        s, d, w = checked
        c_s, c_d = np.average(s, axis=0, weights=w), np.average(d, axis=0, weights=w)
        zs = (s - c_s) @ np.array([1.0, 1j])
        zd = (d - c_d) @ np.array([1.0, 1j])
        den = float(np.sum(w * np.abs(zs) ** 2))
        if not den > 0:
            return FailedEstimation("degenerate: all source points coincide")
        z = np.sum(w * zd * np.conj(zs)) / den
        a, b = float(z.real), float(z.imag)
        t = c_d - np.array([a * c_s[0] - b * c_s[1], b * c_s[0] + a * c_s[1]])
        return cls(np.array([a, b, t[0], t[1]]))

    @classmethod
    def minimal_batch(cls, src: Array, dst: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Least-squares similarities of many samples: ``(B, k, 2)`` each side -> ``(B, 3, 3)``
        pixel matrices and ``(B,)`` validity (False where the source points coincide)."""
        c_s, c_d = src.mean(axis=1), dst.mean(axis=1)
        zs = (src - c_s[:, None]) @ np.array([1.0, 1j])
        zd = (dst - c_d[:, None]) @ np.array([1.0, 1j])
        den = (np.abs(zs) ** 2).sum(axis=1)
        ok = den > 1e-12 * np.maximum(np.abs(src).max(axis=(1, 2)), 1.0) ** 2
        z = (zd * np.conj(zs)).sum(axis=1) / np.where(ok, den, 1.0)
        a, b = z.real, z.imag
        m = np.zeros((len(src), 3, 3))
        m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1] = a, -b, b, a
        m[:, 0, 2] = c_d[:, 0] - (a * c_s[:, 0] - b * c_s[:, 1])
        m[:, 1, 2] = c_d[:, 1] - (b * c_s[:, 0] + a * c_s[:, 1])
        m[:, 2, 2] = 1.0
        return m, ok & (np.hypot(a, b) > 0)


# --------------------------------------------------------------------------------------------
# PolyProjective (paper eq. 5)
# --------------------------------------------------------------------------------------------


def _eval_with_grad(coef: Array, degree: int, u: Array, v: Array) -> tuple[Array, Array, Array]:
    """Numerators and denominator ``f`` (3, N) and their derivatives by ``u`` and ``v``.

    ``coef`` is (3, J): rows ``a``, ``b``, ``c`` (with its constant). Accumulates monomial by
    monomial on 1-D arrays, which is much faster than building (N, J) design matrices.
    """
    pu, pv = _powers(u, degree), _powers(v, degree)
    n = len(u)
    f, fu, fv = np.zeros((3, n)), np.zeros((3, n)), np.zeros((3, n))
    for k, (i, j) in enumerate(_exponents(degree)):
        col = coef[:, k : k + 1]
        f += col * (pu[i] * pv[j])
        if i:
            fu += (i * col) * (pu[i - 1] * pv[j])
        if j:
            fv += (j * col) * (pu[i] * pv[j - 1])
    return f, fu, fv


def _inverse_newton(
    coef: Array, degree: int, yn: Array, u0: Array, tol_n: float, max_iter: int = 50
) -> tuple[Array, Array]:
    """Vectorised damped Newton for ``f(u) = yn`` in normalised space.

    Returns ``(u (N, 2), converged (N,) bool)``. A point converges when its normalised error is
    below ``tol_n`` with a positive denominator and the same Jacobian orientation as at the
    source centre (so the folded side of the map is never accepted). A step that increases
    the error is halved (down to 1/1024, then the point is given up).
    """
    n = len(yn)
    u = np.where(np.isfinite(u0), u0, 0.0)
    conv = np.zeros(n, dtype=bool)
    # Orientation of the map at the source centre (u = 0, where D = 1).
    _, fu0, fv0 = _eval_with_grad(coef, degree, np.zeros(1), np.zeros(1))
    x0 = coef[:2, -1]
    det0 = (fu0[0, 0] - x0[0] * fu0[2, 0]) * (fv0[1, 0] - x0[1] * fv0[2, 0]) - (
        fv0[0, 0] - x0[0] * fv0[2, 0]
    ) * (fu0[1, 0] - x0[1] * fu0[2, 0])
    sign0 = 1.0 if det0 >= 0 else -1.0

    active = np.flatnonzero(np.isfinite(u0).all(axis=1))
    ua = u[active]
    prev_u = ua.copy()
    prev_err = np.full(len(active), np.inf)
    delta = np.zeros_like(ua)
    t = np.ones(len(active))
    for _ in range(max_iter):
        if len(active) == 0:
            break
        f, fu, fv = _eval_with_grad(coef, degree, ua[:, 0], ua[:, 1])
        den = f[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = f[0] / den, f[1] / den
            rx, ry = yn[active, 0] - x, yn[active, 1] - y
            err = np.hypot(rx, ry)
            jxu, jyu = (fu[0] - x * fu[2]) / den, (fu[1] - y * fu[2]) / den
            jxv, jyv = (fv[0] - x * fv[2]) / den, (fv[1] - y * fv[2]) / den
            det = jxu * jyv - jxv * jyu
        done = (err <= tol_n) & (den > 0) & (np.sign(det) == sign0)
        u[active[done]] = ua[done]
        conv[active[done]] = True
        worse = ~done & ~(err < prev_err)
        # Rejected step: go back and halve it.
        t[worse] *= 0.5
        ua[worse] = prev_u[worse] + t[worse, None] * delta[worse]
        # Accepted point: new Newton step.
        acc = ~done & ~worse
        with np.errstate(divide="ignore", invalid="ignore"):
            du = (jyv * rx - jxv * ry) / det
            dv = (-jyu * rx + jxu * ry) / det
        prev_u[acc] = ua[acc]
        prev_err[acc] = err[acc]
        delta[acc] = np.stack([du[acc], dv[acc]], axis=1)
        t[acc] = 1.0
        ua[acc] = ua[acc] + delta[acc]
        keep = ~done & (t > 1e-3) & np.isfinite(ua).all(axis=1)
        active, ua, prev_u, prev_err, delta, t = (
            active[keep], ua[keep], prev_u[keep], prev_err[keep], delta[keep], t[keep]
        )  # fmt: skip
    return u, conv


@dataclass(frozen=True, eq=False)
class PolyProjective(_RationalModel):
    """Polyprojective (rational polynomial) model of degree ``n``, paper eq. 5.

    ``x' = (a.phi(u), b.phi(u)) / c.phi(u)`` with ``phi`` all monomials ``u^i v^j``, ``i+j <= n``
    of the *normalised* source point (order: descending total degree, ending ``u, v, 1``), and the
    constant of ``c`` fixed to 1. ``params = (a (J), b (J), c without its constant (J-1))`` with
    ``J = (n+1)(n+2)/2``: 17 params for ``n = 2``, 29 for ``n = 3``.

    Use :meth:`of_degree` to get a class whose ``min_samples`` and default degree suit a degree
    other than 2 (for :func:`registration.robust.ransac`, which takes a model class).
    """

    degree: int = 2  # type: ignore[assignment]
    params: Array = field(default_factory=lambda: np.array([]))
    src_norm: Normalisation = Normalisation()
    dst_norm: Normalisation = Normalisation()
    min_samples: ClassVar[int] = 9  # ceil(17 / 2) for the paper's degree 2
    default_degree: ClassVar[int] = 2

    def __post_init__(self) -> None:
        if not isinstance(self.degree, (int, np.integer)) or self.degree < 1:
            raise ValueError(f"PolyProjective degree must be an integer >= 1, got {self.degree!r}")
        object.__setattr__(self, "degree", int(self.degree))
        # Instances report their own degree's need (the class attribute is for degree 2).
        object.__setattr__(self, "min_samples", self.min_samples_for(self.degree))
        if np.size(self.params) == 0:
            object.__setattr__(self, "params", _identity_params(self.degree))
        self._post_init()

    @staticmethod
    def min_samples_for(degree: int) -> int:
        """Point pairs needed to determine a degree-``n`` model (2 equations per pair)."""
        return (n_polyprojective_params(degree) + 1) // 2

    @classmethod
    def of_degree(cls, degree: int) -> type[PolyProjective]:
        """A subclass whose ``min_samples`` and ``estimate`` default fit ``degree``."""
        return _poly_class(int(degree))

    @classmethod
    def identity(cls, degree: int = 2, src_norm: Normalisation | None = None) -> PolyProjective:
        n = src_norm or Normalisation()
        return cls(degree, _identity_params(degree), n, n)

    @classmethod
    def from_projective(
        cls,
        proj: Projective,
        degree: int = 2,
        src_norm: Normalisation | None = None,
        dst_norm: Normalisation | None = None,
    ) -> PolyProjective:
        """The polyprojective giving exactly ``proj``'s mapping (higher-order terms zero).

        Args:
            proj: the projective model (e.g. a 1/4-scale fit after ``rescaled(4, 4)``).
            degree: polynomial degree ``n`` (paper: 2).
            src_norm, dst_norm: normalisations for the new model (default: ``proj``'s), e.g.
                ``Normalisation.for_extent(W, H)`` of the frame and its image in the base.
        """
        sn = src_norm or proj.src_norm
        dn = dst_norm or proj.dst_norm
        hn = proj.params if (sn == proj.src_norm and dn == proj.dst_norm) else (
            Projective.from_matrix(proj.matrix, sn, dn).params
        )  # fmt: skip
        j = (degree + 1) * (degree + 2) // 2
        p = np.zeros(n_polyprojective_params(degree))
        p[j - 3 : j] = hn[0:3]
        p[2 * j - 3 : 2 * j] = hn[3:6]
        p[3 * j - 3 : 3 * j - 1] = hn[6:8]
        return cls(degree, p, sn, dn)

    def projective_part(self) -> Projective:
        """The degree-1 terms alone as a Projective (the start of the numerical inverse)."""
        hn = self._projective_matrix_n()
        return Projective(hn.reshape(-1)[:8], self.src_norm, self.dst_norm)

    def inverse(self, xy: ArrayLike, *, tol_px: float = 1e-9) -> Array:
        """Numerical inverse: destination pixels ``(N, 2)`` -> source pixels ``(N, 2)``.

        Vectorised damped Newton with the analytic Jacobian, started from the inverse of the
        projective part; points that fail from there are retried from the nearest node of a
        coarse grid of forward-mapped source points (normalised source box ``[-2, 2]^2``).
        NaN where Newton does not reach ``tol_px`` (destination pixels), where the denominator
        is not positive, or where the solution lies on the folded side of the map.
        """
        pts = as_points(xy)
        out = np.full(pts.shape, np.nan)
        finite = np.isfinite(pts).all(axis=1)
        if not finite.any():
            return out
        yn_all = self.dst_norm.forward(pts[finite])
        tol_n = tol_px * self.dst_norm.scale
        a, b, c = _split(self.params, self.degree)
        coef = np.stack([a, b, c])
        proj = self.projective_part()
        u = np.empty_like(yn_all)
        conv = np.zeros(len(yn_all), dtype=bool)
        # Chunks keep the working arrays in cache (several times faster on frame-sized grids).
        chunk = 1 << 15
        with np.errstate(all="ignore"):
            for lo in range(0, len(yn_all), chunk):
                yn = yn_all[lo : lo + chunk]
                u0 = self.src_norm.forward(proj.inverse(self.dst_norm.backward(yn)))
                u[lo : lo + chunk], conv[lo : lo + chunk] = _inverse_newton(
                    coef, self.degree, yn, u0, tol_n
                )
            if not conv.all():
                g = np.linspace(-2.0, 2.0, 41)
                grid = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
                gx, gden, _ = _forward_n(self.params, self.degree, grid)
                good = (gden > 0) & np.isfinite(gx).all(axis=1)
                grid, gx = grid[good], gx[good]
                bad = np.flatnonzero(~conv)
                if len(grid):
                    _, nearest = scipy.spatial.cKDTree(gx).query(yn_all[bad])
                    ub, cb = _inverse_newton(coef, self.degree, yn_all[bad], grid[nearest], tol_n)
                    u[bad[cb]] = ub[cb]
                    conv[bad[cb]] = True
        res = self.src_norm.backward(u)
        res[~conv] = np.nan
        out[finite] = res
        return out

    def inverted(self) -> Inverted:
        return Inverted(self)

    def compose(self, other: Any) -> Chain:
        """The model of ``self(other(x))`` (a :class:`Chain`)."""
        return Chain(self, other)

    @classmethod
    def estimate(
        cls,
        src: ArrayLike,
        dst: ArrayLike,
        *,
        initial: PolyProjective | Projective | None = None,
        optimizer: str = "lstsq",
        weights: ArrayLike | None = None,
        degree: int | None = None,
        domain: ArrayLike | None = None,
    ) -> PolyProjective | FailedEstimation:
        """Fit the degree-``n`` polyprojective to ``(N, 2)`` pixel pairs.

        Args:
            src, dst: ``(N, 2)`` pixel coordinates; ``N >= min_samples_for(degree)``.
            initial: start for ``"lm"``/``"nelder-mead"`` (its degree and normalisations are kept;
                a Projective is first converted with :meth:`from_projective` in normalisations
                of the data's bounding boxes).
            optimizer: ``"lstsq"`` (linear DLT-like fit ``a.phi - x c.phi = 0``), ``"lm"`` or
                ``"nelder-mead"`` (sum of squared geometric residuals, destination pixels).
            weights: optional ``(N,)`` non-negative weights of the squared residuals.
            degree: ``n``; default ``initial``'s degree, else the class default (2).
            domain: optional ``(M, 2)`` source pixels where the model must stay defined: the
                nonlinear fit keeps the denominator above :data:`MIN_DENOMINATOR` there too
                (e.g. the whole frame, which reaches beyond the control points' bounding box).

        Returns:
            The model, or a falsy :class:`FailedEstimation` with the reason.
        """
        if isinstance(initial, Projective):
            initial = PolyProjective.from_projective(
                initial,
                degree or cls.default_degree,
                Normalisation.from_points(src),
                Normalisation.from_points(dst),
            )
        if degree is None:
            degree = initial.degree if initial is not None else cls.default_degree
        if initial is not None and initial.degree != degree:
            raise ValueError(
                f"initial has degree {initial.degree}, but degree={degree} was asked for"
            )
        ms = cls.min_samples_for(degree)
        target = cls if cls.default_degree == degree else PolyProjective
        return cls._estimate_rational(
            degree, src, dst, initial=initial, optimizer=optimizer, weights=weights,
            label=f"a degree-{degree} polyprojective", min_samples=ms,
            make=lambda p, sn, dn: target(degree, p, sn, dn), domain=domain,
        )  # fmt: skip


@functools.lru_cache(maxsize=8)
def _poly_class(degree: int) -> type[PolyProjective]:
    if degree < 1:
        raise ValueError(f"PolyProjective degree must be >= 1, got {degree}")
    if degree == 2:
        return PolyProjective
    return type(
        f"PolyProjective{degree}",
        (PolyProjective,),
        {
            "min_samples": PolyProjective.min_samples_for(degree),
            "default_degree": degree,
            "__doc__": f"PolyProjective with default degree {degree}.",
        },
    )


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


_TYPES: dict[str, type] = {
    "Translation": Translation,
    "Similarity": Similarity,
    "Affine": Affine,
    "Projective": Projective,
    "PolyProjective": PolyProjective,
    "Chain": Chain,
    "Inverted": Inverted,
}


def model_from_dict(d: dict[str, Any]) -> Any:
    """Restore a model written by ``to_dict()`` (JSON-able dict with a ``"type"`` key).

    Raises:
        ValueError: for an unknown type or missing keys, naming them.
    """
    if not isinstance(d, dict) or "type" not in d:
        raise ValueError(f"model dict needs a 'type' key, got {d!r:.200}")
    kind = d["type"]
    try:
        if kind == "Translation":
            return Translation(np.asarray(d["params"], dtype=np.float64))
        if kind in ("Similarity", "Affine"):
            return _TYPES[kind](np.asarray(d["params"], dtype=np.float64))
        if kind == "Projective":
            return Projective(
                np.asarray(d["params"], dtype=np.float64),
                Normalisation.from_dict(d["src_norm"]),
                Normalisation.from_dict(d["dst_norm"]),
            )
        if kind == "PolyProjective":
            return PolyProjective(
                int(d["degree"]),
                np.asarray(d["params"], dtype=np.float64),
                Normalisation.from_dict(d["src_norm"]),
                Normalisation.from_dict(d["dst_norm"]),
            )
        if kind == "Chain":
            return Chain(model_from_dict(d["outer"]), model_from_dict(d["inner"]))
        if kind == "Inverted":
            return Inverted(model_from_dict(d["model"]))
    except KeyError as e:
        raise ValueError(f"model dict of type {kind!r} lacks key {e.args[0]!r}") from None
    raise ValueError(f"unknown model type {kind!r}; expected one of {sorted(_TYPES)}")


def _from_dict(cls: type, d: dict[str, Any]) -> Any:
    """Restore a model of this class from ``to_dict()`` output (see :func:`model_from_dict`)."""
    model = model_from_dict(d)
    if not isinstance(model, cls):
        raise ValueError(f"dict describes a {d.get('type')!r}, not a {cls.__name__}")
    return model


for _cls in (Translation, Similarity, Affine, Projective, PolyProjective, Chain, Inverted):
    _cls.from_dict = classmethod(_from_dict)  # type: ignore[attr-defined]
del _cls
