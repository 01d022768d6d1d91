"""Radial distortion (paper section 3): the one-parameter Harris model and friends.

Harris model (paper eq. 1, 2, 4; ``conventions.md``): for a raw frame of width ``W`` and height
``H``, centre ``c = ((W-1)/2, (H-1)/2)`` unless given, normalising radius ``r_n = sqrt(W²+H²)/2``,
a corrected pixel ``x`` maps to the raw pixel ``x' = c + r_n f(ρ) (x-c)/|x-c|`` with
``ρ = |x-c|/r_n`` and ``f(ρ) = ρ / sqrt(1 + γ ρ²)``. The inverse (raw to corrected) is the same
formula with ``-γ``. Positive γ corrects barrel distortion; γ = 0 is the identity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points


@dataclass(frozen=True)
class HarrisModel:
    """Harris radial distortion of a ``width`` x ``height`` raw frame.

    Attributes:
        gamma: distortion parameter γ (dimensionless); the paper's camera: 0.7.
        width, height: raw frame size in pixels.
        center: distortion centre ``(x, y)`` in raw pixels; None = the frame centre.
    """

    gamma: float
    width: int
    height: int
    center: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"frame size must be positive, got {self.width}x{self.height}")
        if not np.isfinite(self.gamma):
            raise ValueError(f"gamma must be finite, got {self.gamma}")

    @property
    def c(self) -> NDArray[np.float64]:
        if self.center is None:
            return np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])
        return np.asarray(self.center, dtype=np.float64)

    @property
    def r_n(self) -> float:
        """Normalising radius: half the frame diagonal, in pixels."""
        return float(np.hypot(self.width, self.height) / 2.0)

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

    def max_raw_rho(self) -> float:
        """Largest normalised radius of a raw pixel centre from the distortion centre."""
        corners = np.array(
            [[0, 0], [self.width - 1, 0], [0, self.height - 1], [self.width - 1, self.height - 1]],
            dtype=np.float64,
        )
        return float(np.max(np.linalg.norm(corners - self.c, axis=1)) / self.r_n)
