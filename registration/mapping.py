"""The interface every registered sequence shares (a result folder and the simulator's truth):
``frame_to_base`` and ``base_to_frame`` of frame ``k`` at a stage (``conventions.md``).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

try:
    import fcntl
except ImportError:  # not POSIX: no lock (documented in README "Reliability")
    fcntl = None


STAGES = ("global", "local")


class SequenceMapping(Protocol):
    """What a registration result and the simulator's ground truth both provide."""

    @property
    def n_frames(self) -> int: ...

    def frame_to_base(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]: ...

    def base_to_frame(
        self, k: int, xy: ArrayLike, stage: str = "local", *, clip: bool = True
    ) -> NDArray[np.float64]:
        """``clip=False``: raw px beyond the frame's edge are returned rather than NaN."""
        ...


def _check_stage(stage: str) -> None:
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {', '.join(STAGES)}, got {stage!r}")
