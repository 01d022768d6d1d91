"""Global registration to the base map (paper section 4): heading and scale from one click, the coarse
projective step at 1/4 scale (4.3.1), the fine polyprojective step with REQCON (4.3.2), and the
intra-sensor registration of every other frame against the mid base image and the previous frame
(4.4).
"""

from registration.global_registration.coarse import coarse_register
from registration.global_registration.coarse_fit import COARSE_MIN_COVERAGE, projective_or_simpler
from registration.global_registration.coarse_records import (
    CoarseBase,
    CoarseConfig,
    CoarseResult,
    corrected_grey,
    frame_view,
    normalise_seeds,
)
from registration.global_registration.fine import (
    FINE_MIN_COVERAGE,
    FineConfig,
    FineResult,
    fine_register_reference,
    frame_domain,
    register_anchor,
)
from registration.global_registration.gradient_correlation import (
    CorrelationConfig,
    agreement,
    gradient_images,
    refine_by_correlation,
)
from registration.global_registration.heading import (
    HeadingConfig,
    SimilarityPrior,
    attribute_differences,
    gate_by_prior,
    guided_matches,
    prior_from_patch,
    prior_from_seed,
    prior_from_seeds,
    priors_without_seed,
)
from registration.global_registration.intra import IntraConfig, previous_frame_state, register_intra
from registration.global_registration.joint_base import (
    JointBase,
    add_to_mid_base,
    make_joint_base,
    mid_coverage,
)
from registration.global_registration.lens_refit import register_with_lens
from registration.global_registration.predicted_coarse import phase_shift

__all__ = [
    "COARSE_MIN_COVERAGE",
    "CoarseBase",
    "CoarseConfig",
    "CoarseResult",
    "CorrelationConfig",
    "FINE_MIN_COVERAGE",
    "FineConfig",
    "FineResult",
    "HeadingConfig",
    "IntraConfig",
    "JointBase",
    "SimilarityPrior",
    "add_to_mid_base",
    "agreement",
    "attribute_differences",
    "coarse_register",
    "corrected_grey",
    "fine_register_reference",
    "frame_domain",
    "frame_view",
    "gate_by_prior",
    "gradient_images",
    "guided_matches",
    "make_joint_base",
    "mid_coverage",
    "normalise_seeds",
    "phase_shift",
    "previous_frame_state",
    "prior_from_patch",
    "prior_from_seed",
    "prior_from_seeds",
    "priors_without_seed",
    "projective_or_simpler",
    "refine_by_correlation",
    "register_anchor",
    "register_intra",
    "register_with_lens",
]
