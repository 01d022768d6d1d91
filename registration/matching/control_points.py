"""Control points: matched point pairs from any matcher, with their scores, in one record."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration import coords

PointFunction = Callable[[NDArray[np.float64]], NDArray[np.float64]]


# --------------------------------------------------------------------------------------------
# Control points
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ControlPoints:
    """Corresponding points between a frame and a reference image.

    Attributes:
        src: ``(N, 2)`` float64 frame pixels.
        dst: ``(N, 2)`` float64 reference pixels.
        score: ``(N,)`` float64 match quality, higher is better (NCC peak for templates,
            ``1 - Lowe ratio`` for SIFT).
        source: ``(N,)`` int64 index of the reference each point came from (0 when there is
            only one; filled with zeros when not given).
    """

    src: NDArray[np.float64]
    dst: NDArray[np.float64]
    score: NDArray[np.float64]
    source: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        src = coords.as_points(self.src, "ControlPoints.src") if len(self.src) else np.zeros((0, 2))
        dst = coords.as_points(self.dst, "ControlPoints.dst") if len(self.dst) else np.zeros((0, 2))
        score = np.asarray(self.score, np.float64).reshape(-1)
        n = len(src)
        source = (
            np.zeros(n, np.int64)
            if self.source is None
            else np.asarray(self.source, np.int64).reshape(-1)
        )
        if len(dst) != n or len(score) != n or len(source) != n:
            raise ValueError(
                f"ControlPoints fields must have equal length, got src {len(src)}, dst {len(dst)}, "
                f"score {len(score)}, source {len(source)}"
            )
        object.__setattr__(self, "src", src)
        object.__setattr__(self, "dst", dst)
        object.__setattr__(self, "score", score)
        object.__setattr__(self, "source", source)

    def __len__(self) -> int:
        return len(self.src)

    @classmethod
    def empty(cls) -> ControlPoints:
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64))

    def subset(self, index: ArrayLike) -> ControlPoints:
        """The points selected by an integer index array or a boolean mask."""
        i = np.asarray(index)
        return ControlPoints(self.src[i], self.dst[i], self.score[i], self.source[i])

    @classmethod
    def concatenate(cls, parts: Sequence[ControlPoints]) -> ControlPoints:
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        return cls(
            np.concatenate([p.src for p in parts]),
            np.concatenate([p.dst for p in parts]),
            np.concatenate([p.score for p in parts]),
            np.concatenate([p.source for p in parts]),
        )


def call_points(fn: PointFunction, xy: NDArray[np.float64], name: str) -> NDArray[np.float64]:
    """``fn(xy)`` for ``(N, 2)`` px, checked to be ``(N, 2)`` too (``name`` in the message)."""
    if len(xy) == 0:
        return np.zeros((0, 2))
    out = np.asarray(fn(xy), np.float64)
    if out.shape != xy.shape:
        raise ValueError(f"{name} must map (N, 2) to (N, 2), got {xy.shape} -> {out.shape}")
    return out
