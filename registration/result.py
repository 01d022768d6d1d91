"""Registration result folders and the mapping interface they share with the simulator's truth.

The interface (fixed by ``conventions.md``)::

    result.n_frames                               # int
    result.frame_to_base(k, xy, stage="local")    # (N,2) raw pixels of frame k -> (N,2) base px
    result.base_to_frame(k, xy, stage="local")    # (N,2) base pixels -> (N,2) raw pixels of k

``stage`` is ``"global"`` or ``"local"``. NaN for points of failed frames or outside what the
result covers; never raises for a valid ``k``.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

STAGES = ("global", "local")


class SequenceMapping(Protocol):
    """What a registration result and the simulator's ground truth both provide."""

    @property
    def n_frames(self) -> int: ...

    def frame_to_base(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]: ...

    def base_to_frame(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]: ...
