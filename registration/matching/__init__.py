"""Correspondences between images (paper 4.3.1, 4.3.2, 4.4): grey conversion and subsampling, SIFT
keypoints with ratio-test matching, SIFT matched window by window on a grid, template grids matched
by normalised cross-correlation, and dense DIS optical flow.
"""

from registration.matching.control_points import ControlPoints
from registration.matching.dense_flow import (
    FlowReference,
    FrameFlow,
    dis_flow,
    flow_matches,
    flow_samples,
    flow_scale,
    frame_flow,
    frame_flow_matches,
    joint_flow_reference,
    prepare_flow_reference,
)
from registration.matching.grey import downscale, downscale_mask, to_grey
from registration.matching.gridded_sift import (
    GriddedSiftConfig,
    Reference,
    gridded_sift_control_points,
    window_centres,
)
from registration.matching.ncc_peaks import subpixel_peak
from registration.matching.probes import (
    ProbeConfig,
    find_probes,
    probe_grid,
    structure_strength,
    textured_probes,
)
from registration.matching.sift import Keypoints, Matches, SiftConfig, detect_sift, match_ratio
from registration.matching.templates import (
    TemplateConfig,
    edge_ring,
    gradient_magnitude,
    grid_spacing,
    template_control_points,
    template_grid,
)

__all__ = [
    "ProbeConfig",
    "find_probes",
    "probe_grid",
    "structure_strength",
    "textured_probes",
    "ControlPoints",
    "FlowReference",
    "FrameFlow",
    "GriddedSiftConfig",
    "Keypoints",
    "Matches",
    "Reference",
    "SiftConfig",
    "TemplateConfig",
    "detect_sift",
    "dis_flow",
    "downscale",
    "downscale_mask",
    "edge_ring",
    "flow_matches",
    "flow_samples",
    "flow_scale",
    "frame_flow",
    "frame_flow_matches",
    "gradient_magnitude",
    "grid_spacing",
    "gridded_sift_control_points",
    "joint_flow_reference",
    "match_ratio",
    "prepare_flow_reference",
    "subpixel_peak",
    "template_control_points",
    "template_grid",
    "to_grey",
    "window_centres",
]
