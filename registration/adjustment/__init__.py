"""The sequence adjustment (beyond the paper; the paper registers each frame alone, section 4.4):
the global models of many frames estimated together from each frame's control points to the map
and links between frames that see the same ground, so that consecutive frames agree with each
other as well as each agrees with the map.
"""

from registration.adjustment.fields import (
    FieldFrame,
    FieldSolveConfig,
    refined_grid,
    solve_corrections,
)
from registration.adjustment.links import (
    link_key,
    links_from_arrays,
    links_to_arrays,
    measure_links,
)
from registration.adjustment.map_points import (
    FrameMapPoints,
    MapPoint,
    apply_map_points,
    moved_onto,
    similarity_onto,
)
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
    "FrameMapPoints",
    "MapPoint",
    "FieldFrame",
    "FieldSolveConfig",
    "FrameLinks",
    "SequenceAdjustConfig",
    "SequenceEvidence",
    "Window",
    "adjust_models",
    "adjust_sequence",
    "adjust_window",
    "apply_map_points",
    "moved_onto",
    "similarity_onto",
    "as_polyprojective",
    "link_key",
    "links_from_arrays",
    "links_to_arrays",
    "measure_links",
    "predicted_error",
    "refined_grid",
    "solve_corrections",
    "window_plan",
]
