"""The sequence adjustment (beyond the paper; the paper registers each frame alone, section 4.4):
the global models of many frames estimated together from each frame's control points to the map
and links between frames that see the same ground, so that consecutive frames agree with each
other as well as each agrees with the map.
"""

from registration.adjustment.fields import (
    FrameField,
    consistent_field,
    correction_at,
    pool_corrections,
    refined_grid,
)
from registration.adjustment.links import measure_links
from registration.adjustment.sequence import (
    FrameAdjustment,
    SequenceAdjustConfig,
    SequenceEvidence,
    Window,
    adjust_sequence,
    adjust_window,
    as_polyprojective,
    predicted_error,
    window_plan,
)
from registration.adjustment.solve import (
    AdjustmentConfig,
    AdjustmentResult,
    ControlPointSet,
    FrameLinks,
    adjust_models,
)

__all__ = [
    "AdjustmentConfig",
    "AdjustmentResult",
    "ControlPointSet",
    "FrameAdjustment",
    "FrameField",
    "FrameLinks",
    "SequenceAdjustConfig",
    "SequenceEvidence",
    "Window",
    "adjust_models",
    "adjust_sequence",
    "adjust_window",
    "as_polyprojective",
    "consistent_field",
    "correction_at",
    "measure_links",
    "pool_corrections",
    "predicted_error",
    "refined_grid",
    "window_plan",
]
