"""What every geometric model shares: the protocol, the falsy estimation failure, input
checks, the coordinate normalisation, parameter quantisation, and the inverse and chain
wrappers. The optimisers are in :mod:`registration.geometry.optimisers`.

The models themselves are in :mod:`registration.geometry.rational` (projective, polyprojective) and
:mod:`registration.geometry.models` (translation, similarity, affine; the public entry point, which
re-exports everything here that callers use).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points

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
