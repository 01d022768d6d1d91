"""Geometric models and robust fitting (paper 4.3.1-4.4): one protocol (apply, inverse, residuals,
estimate) for translation, similarity, affine, projective and polyprojective (paper eq. 5); RANSAC,
REQCON and the choice of the simplest supported model; the displacement field (paper section 5) and
the one remap primitive every warp goes through.
"""

from registration.geometry.displacement_field import (
    DisplacementField,
    grid_nodes,
    local_base_to_frame,
    local_frame_to_base,
)
from registration.geometry.estimation import (
    Chain,
    FailedEstimation,
    GeometricModel,
    Inverted,
    Normalisation,
    quantized,
)
from registration.geometry.fit_result import FitResult
from registration.geometry.linear import Affine, Similarity, Translation
from registration.geometry.model_choice import (
    cross_validated_error,
    hull_coverage,
    simplest_supported,
)
from registration.geometry.models import model_from_dict, scale_at_frame_centre
from registration.geometry.optimisers import levenberg_marquardt
from registration.geometry.ransac_fit import RansacConfig, adaptive_max_iterations, ransac
from registration.geometry.rational import PolyProjective, Projective
from registration.geometry.rational_fit import MIN_DENOMINATOR, n_polyprojective_params
from registration.geometry.reqcon_fit import ReqconConfig, reqcon
from registration.geometry.warp import (
    INTERPOLATIONS,
    PreparedMap,
    pixel_grid,
    prepare_source_map,
    remap,
    remap_prepared,
    source_map_from_function,
    warp_image,
)

__all__ = [
    "Affine",
    "Chain",
    "DisplacementField",
    "FailedEstimation",
    "FitResult",
    "GeometricModel",
    "INTERPOLATIONS",
    "Inverted",
    "MIN_DENOMINATOR",
    "Normalisation",
    "PolyProjective",
    "PreparedMap",
    "Projective",
    "RansacConfig",
    "ReqconConfig",
    "Similarity",
    "Translation",
    "adaptive_max_iterations",
    "cross_validated_error",
    "grid_nodes",
    "hull_coverage",
    "levenberg_marquardt",
    "local_base_to_frame",
    "local_frame_to_base",
    "model_from_dict",
    "n_polyprojective_params",
    "pixel_grid",
    "prepare_source_map",
    "quantized",
    "ransac",
    "remap",
    "remap_prepared",
    "reqcon",
    "scale_at_frame_centre",
    "simplest_supported",
    "source_map_from_function",
    "warp_image",
]
