"""A whole sequence (paper Fig. 3): configuration and presets, the pipeline (the reference frame, then
every other frame in chunks), re-anchoring to the map, read-ahead, Dask scale-out, and the result
folder (records, identity, lock, reader, writer).
"""

from registration.run.adjust import adjust_folder
from registration.run.anchoring import ANCHOR_STAGE, render_anchor
from registration.run.chunks import (
    ChunkContext,
    ChunkJob,
    chunk_plan,
    previous_in_order,
    processing_order,
)
from registration.run.config import (
    CHANGE_LOG_RATIO,
    PRESETS,
    PipelineConfig,
    config_from_dict,
    config_to_dict,
    get_preset,
)
from registration.run.dask_executor import (
    DaskExecutor,
    DaskUnavailable,
    check_frames,
    open_client,
    open_executor,
    require_distributed,
)
from registration.run.identity import make_metadata
from registration.run.intra_frames import SerialExecutor
from registration.run.map_points import read_map_points, set_map_points
from registration.run.pipeline import (
    RegistrationFailed,
    load_config,
    register_sequence,
    validate_inputs,
)
from registration.run.prefetch import FramesAhead, LocalAhead
from registration.run.records import (
    FrameRecord,
    frame_arrays,
    frame_record_path,
    frame_stats,
    read_record,
    verify_record,
)
from registration.run.result import RegistrationResult, load_result
from registration.run.result_folder import ResultLock, check_out_dir
from registration.run.writer import ResultWriter

__all__ = [
    "adjust_folder",
    "read_map_points",
    "set_map_points",
    "FrameRecord",
    "ANCHOR_STAGE",
    "CHANGE_LOG_RATIO",
    "ChunkContext",
    "ChunkJob",
    "DaskExecutor",
    "DaskUnavailable",
    "FramesAhead",
    "LocalAhead",
    "PRESETS",
    "PipelineConfig",
    "RegistrationFailed",
    "RegistrationResult",
    "ResultLock",
    "ResultWriter",
    "SerialExecutor",
    "check_frames",
    "check_out_dir",
    "chunk_plan",
    "config_from_dict",
    "config_to_dict",
    "frame_arrays",
    "frame_record_path",
    "frame_stats",
    "get_preset",
    "load_config",
    "load_result",
    "make_metadata",
    "open_client",
    "open_executor",
    "previous_in_order",
    "processing_order",
    "read_record",
    "register_sequence",
    "render_anchor",
    "require_distributed",
    "validate_inputs",
    "verify_record",
]
