"""Local displacement-field refinement (paper section 5): a field of consensus vectors on a 200 px
grid between each registered frame and the mid base image.
"""

from registration.local.config import (
    FEW_MATCHES,
    FLOW_OVERRIDES,
    NEIGHBOUR_OUTLIER,
    NO_CONSENSUS,
    OK,
    OUTSIDE,
    RIVAL_MOTION,
    STATUS,
    FieldStats,
    KeypointSet,
    LocalConfig,
)
from registration.local.consensus import (
    CellConsensus,
    cell_consensus,
    consensus_cells,
    detect_keypoints,
    estimate_field_from_keypoints,
    estimate_field_from_matches,
    fill_invalid,
    gated_ratio_matches,
    neighbour_check,
)
from registration.local.refine import (
    estimate_field,
    estimate_field_in_frame,
    frame_field,
    reference_field,
)
from registration.local.spline import estimate_field_spline

__all__ = [
    "CellConsensus",
    "FEW_MATCHES",
    "FLOW_OVERRIDES",
    "FieldStats",
    "KeypointSet",
    "LocalConfig",
    "NEIGHBOUR_OUTLIER",
    "NO_CONSENSUS",
    "OK",
    "OUTSIDE",
    "RIVAL_MOTION",
    "STATUS",
    "cell_consensus",
    "consensus_cells",
    "detect_keypoints",
    "estimate_field",
    "estimate_field_from_keypoints",
    "estimate_field_from_matches",
    "estimate_field_in_frame",
    "estimate_field_spline",
    "fill_invalid",
    "frame_field",
    "gated_ratio_matches",
    "neighbour_check",
    "reference_field",
]
