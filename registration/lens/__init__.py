"""The lens (paper section 3): the one-parameter Harris model and its relatives, image correction, the
camera every stage uses, γ from straight lines (traced or detected) and from the frames' motion,
the distortion centre, and a fourth-order term beyond Harris.
"""

from registration.lens.camera import Camera, as_camera
from registration.lens.centre_fit import (
    check_one_parameter,
    fit_center,
    fit_division_from_lines,
    fit_polynomial_from_lines,
)
from registration.lens.correction import (
    CANVASES,
    IMAGE_INTERPOLATIONS,
    CanvasInfo,
    correction_canvas,
    correction_source_map,
    distort_image,
    simulate_raw_frame,
    undistort_image,
)
from registration.lens.gamma_from_lines import (
    CONFIDENT_SIGMA,
    MIN_EFFECTIVE_LINES,
    estimate_gamma_auto,
    estimate_gamma_from_lines,
    line_groups,
)
from registration.lens.gamma_from_motion import (
    DEFAULT_PAIRS,
    MotionGammaConfig,
    choose_step,
    estimate_gamma_from_flight,
    estimate_gamma_from_motion,
    frame_pairs,
    pair_matches,
)
from registration.lens.k2 import LensConfig, estimate_k2
from registration.lens.line_straightness import straightness
from registration.lens.lines_file import lines_to_json, load_lines, parse_lines, save_lines
from registration.lens.radial import (
    HARRIS_GAMMA_MIN,
    DivisionModel,
    HarrisModel,
    PolynomialModel,
    RadialModel,
    TwoTermHarrisModel,
    check_harris_gamma,
    check_valid,
    harris_gamma_limit,
    harris_gamma_range,
)
from registration.lens.straight_edges import straight_edge_chart

__all__ = [
    "CANVASES",
    "CONFIDENT_SIGMA",
    "Camera",
    "CanvasInfo",
    "DEFAULT_PAIRS",
    "DivisionModel",
    "HARRIS_GAMMA_MIN",
    "HarrisModel",
    "IMAGE_INTERPOLATIONS",
    "LensConfig",
    "MIN_EFFECTIVE_LINES",
    "MotionGammaConfig",
    "PolynomialModel",
    "RadialModel",
    "TwoTermHarrisModel",
    "as_camera",
    "check_harris_gamma",
    "check_one_parameter",
    "check_valid",
    "choose_step",
    "correction_canvas",
    "correction_source_map",
    "distort_image",
    "estimate_gamma_auto",
    "estimate_gamma_from_flight",
    "estimate_gamma_from_lines",
    "estimate_gamma_from_motion",
    "estimate_k2",
    "fit_center",
    "fit_division_from_lines",
    "fit_polynomial_from_lines",
    "frame_pairs",
    "harris_gamma_limit",
    "harris_gamma_range",
    "line_groups",
    "lines_to_json",
    "load_lines",
    "pair_matches",
    "parse_lines",
    "save_lines",
    "simulate_raw_frame",
    "straight_edge_chart",
    "straightness",
    "undistort_image",
]
