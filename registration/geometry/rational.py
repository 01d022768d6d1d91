"""The rational polynomial models: projective (degree 1) and polyprojective (paper eq. 5).

``x' = (a.phi(u), b.phi(u)) / c.phi(u)`` in normalised coordinates (:class:`Normalisation` of
the source and destination points), ``phi`` the monomials up to the model's degree. Estimated by
a normalised DLT, then the geometric error (Euclidean distance in destination pixels) refined by
Levenberg-Marquardt or Nelder-Mead behind a barrier that keeps the denominator positive where
the model is fitted (:data:`MIN_DENOMINATOR`). Use them through :mod:`registration.geometry.models`.

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
from typing import Any, ClassVar

import numpy as np
import scipy.spatial
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.geometry.estimation import (
    Array,
    Chain,
    FailedEstimation,
    Inverted,
    Normalisation,
    _check_pair,
    _nonfinite_reason,
    _residuals,
)
from registration.geometry.optimisers import _check_optimizer, _refine
from registration.geometry.rational_fit import (
    _batch_collinear,
    _batch_normalise,
    _collinear_triple,
    _degenerate_points_reason,
    _design,
    _dlt,
    _exponents,
    _forward_n,
    _geometric_fun,
    _linear_poly,
    _powers,
    _split,
    n_polyprojective_params,
)


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
    """``"PolyProjective"`` for any degree's class, else the class's name."""
    return "PolyProjective" if isinstance(model, PolyProjective) else type(model).__name__


def _identity_params(degree: int) -> Array:
    j = (degree + 1) * (degree + 2) // 2
    p = np.zeros(n_polyprojective_params(degree))
    p[j - 3] = 1.0  # a: u
    p[2 * j - 2] = 1.0  # b: v
    return p


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
        """The model of ``self(other(x))``: Projective for a Projective or a model that composes
        as one (``composes_as_projective``: a Translation), else a Chain."""
        if getattr(other, "composes_as_projective", False):
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
    other than 2 (for :func:`registration.geometry.ransac_fit.ransac`, which takes a model class).
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

    def design(self, xy: ArrayLike) -> Array:
        """The monomials of source px ``xy`` (``(N, 2)``) in this model's source normalisation,
        ``(N, J)``: what :meth:`param_jacobian` takes again for the same points."""
        return _design(self.src_norm.forward(as_points(xy)), self.degree)

    def param_jacobian(self, xy: ArrayLike, design: Array | None = None) -> tuple[Array, Array]:
        """Destination px of source px ``xy`` (``(N, 2)``) and their derivatives with respect to
        :attr:`params`, ``(N, 2, P)`` px per unit (the normalisations held fixed): what a joint
        adjustment of many frames' models linearises (:mod:`registration.adjustment`).
        ``design``: :meth:`design` of ``xy``, when the caller keeps it (the same points over
        many parameter values)."""
        phi = self.design(xy) if design is None else design
        xn, yn, den = self._normalised_values(phi)
        with np.errstate(divide="ignore", invalid="ignore"):
            g = phi / den[:, None] / self.dst_norm.scale
            j = phi.shape[1]
            jac = np.zeros((len(phi), 2, 3 * j - 1))
            jac[:, 0, :j] = g
            jac[:, 1, j : 2 * j] = g
            jac[:, 0, 2 * j :] = -(xn / den / self.dst_norm.scale)[:, None] * phi[:, :-1]
            jac[:, 1, 2 * j :] = -(yn / den / self.dst_norm.scale)[:, None] * phi[:, :-1]
        return self.dst_norm.backward(np.stack([xn, yn], axis=1)), jac

    def param_jacobian_by_row(self, design: Array) -> tuple[Array, Array, Array, Array, Array]:
        """:meth:`param_jacobian` (to the bit) by row, from :meth:`design` of the points:
        ``(values (N, 2), ix, iy, jx (N, 2J - 1), jy (N, 2J - 1))``. The x row depends on the
        numerator ``a`` and the denominator ``c`` only (parameters ``ix``), the y row on ``b``
        and ``c`` (``iy``); the Jacobian's other entries are 0 by the model's form."""
        xn, yn, den = self._normalised_values(design)
        j = design.shape[1]
        ix, iy = np.r_[0:j, 2 * j : 3 * j - 1], np.r_[j : 2 * j, 2 * j : 3 * j - 1]
        s = self.dst_norm.scale
        with np.errstate(divide="ignore", invalid="ignore"):
            g = design / den[:, None] / s
            jx = np.hstack([g, -(xn / den / s)[:, None] * design[:, :-1]])
            jy = np.hstack([g, -(yn / den / s)[:, None] * design[:, :-1]])
        values = self.dst_norm.backward(np.stack([xn, yn], axis=1))
        return values, ix, iy, jx, jy

    def apply_design(self, design: Array) -> Array:
        """Destination px of the points whose :meth:`design` is ``design``: the first part of
        :meth:`param_jacobian` to the bit, without the derivatives."""
        xn, yn, _ = self._normalised_values(design)
        return self.dst_norm.backward(np.stack([xn, yn], axis=1))

    def _normalised_values(self, phi: Array) -> tuple[Array, Array, Array]:
        a, b, c = _split(self.params, self.degree)
        den = phi @ c
        with np.errstate(divide="ignore", invalid="ignore"):
            return phi @ a / den, phi @ b / den, den

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
