"""Accuracy of a registration (paper section 6): the paper's Table 2 from hand-marked points, error
statistics against the simulator's exact truth, sudden excursions, and the plain-OpenCV baselines
the benchmarks compare against.
"""

from registration.evaluation.baselines import (
    BaselineConfig,
    StabiloConfig,
    apply_homography,
    homography,
    register_baseline,
    register_chained,
    register_per_frame,
    register_stabilo,
    sift_features,
    stabilo_homography,
)
from registration.evaluation.consistency import (
    ConsistencyConfig,
    PairConsistency,
    map_agreement,
    pair_consistency,
    summarise,
)
from registration.evaluation.points import (
    PointMarks,
    evaluate_points,
    point_positions,
    read_points_csv,
)
from registration.evaluation.proposals import (
    MarkProposal,
    PatchStructure,
    ProposalConfig,
    SuggestedPoint,
    patch_structure,
    propose_mark,
    propose_through,
    propose_unregistered,
    suggest_points,
)
from registration.evaluation.report import find_excursions
from registration.evaluation.table2 import LOCATIONS, STAGES, EvaluationConfig, Table2, table_frames
from registration.evaluation.truth import (
    check_compatible,
    evaluate_truth,
    table_points,
    truth_errors,
)

__all__ = [
    "ConsistencyConfig",
    "PairConsistency",
    "map_agreement",
    "pair_consistency",
    "summarise",
    "BaselineConfig",
    "EvaluationConfig",
    "LOCATIONS",
    "PointMarks",
    "STAGES",
    "StabiloConfig",
    "Table2",
    "apply_homography",
    "check_compatible",
    "evaluate_points",
    "evaluate_truth",
    "find_excursions",
    "homography",
    "point_positions",
    "MarkProposal",
    "PatchStructure",
    "ProposalConfig",
    "SuggestedPoint",
    "patch_structure",
    "propose_mark",
    "propose_through",
    "propose_unregistered",
    "suggest_points",
    "read_points_csv",
    "register_baseline",
    "register_chained",
    "register_per_frame",
    "register_stabilo",
    "sift_features",
    "stabilo_homography",
    "table_frames",
    "table_points",
    "truth_errors",
]
