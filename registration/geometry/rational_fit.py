"""Fitting a rational polynomial map ``x' = (a.phi(u), b.phi(u)) / c.phi(u)`` (paper eq. 5):
the monomials and design matrix, degeneracy checks, the normalised DLT and the linear start, and
the geometric cost with its denominator barrier that the nonlinear refinement minimises. All in
normalised coordinates (:class:`registration.geometry.estimation.Normalisation`); the model classes that
use them are in :mod:`registration.geometry.rational`.

References:
    Loveland & Rosten, section 4.3.2, eq. 5 (polyprojective / rational polynomial model).
    Hartley & Zisserman, "Multiple View Geometry", 2nd ed., algorithm 4.2 (normalised DLT).
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from registration.geometry.estimation import _RANK_TOL, Array, Normalisation

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


_ONE = np.ones(1)


def _split(params: Array, degree: int) -> tuple[Array, Array, Array]:
    """Rows ``a``, ``b``, ``c`` (the last with its constant 1 appended), each (J,)."""
    j = (degree + 1) * (degree + 2) // 2
    return params[:j], params[j : 2 * j], np.concatenate((params[2 * j :], _ONE))


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
    c0 = _split(p0, degree)[2]
    start_min = float(np.min(phi_all @ c0))
    use_barrier = degree >= 2 and start_min > 0
    floor = min(MIN_DENOMINATOR, start_min)
    no_fold = degree >= 2 and not use_barrier and bool(np.min(phi @ c0) > 0)

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
