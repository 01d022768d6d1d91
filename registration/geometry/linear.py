"""The linear geometric models: translation, similarity and affine, behind the protocol of
:mod:`registration.geometry.estimation`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.geometry.estimation import (
    Array,
    Chain,
    FailedEstimation,
    _check_pair,
    _nonfinite_reason,
    _residuals,
)
from registration.geometry.optimisers import _check_optimizer
from registration.geometry.rational import Projective
from registration.geometry.rational_fit import (
    _batch_collinear,
    _degenerate_points_reason,
)

# --------------------------------------------------------------------------------------------
# Translation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Translation:
    """``x' = x + t``; params ``(tx, ty)`` in pixels."""

    params: Array = field(default_factory=lambda: np.zeros(2))
    min_samples: ClassVar[int] = 1
    # A projective composed with a translation is taken as the exact projective product
    # (:meth:`registration.geometry.rational.Projective.compose`); the other linear models give
    # a Chain there.
    composes_as_projective: ClassVar[bool] = True

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
# Affine and similarity (beyond the paper: the coarse step's model selection and its
# one-point-plus-seed samples)
# --------------------------------------------------------------------------------------------


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
