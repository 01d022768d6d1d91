"""Files in and out (no registration logic): images and their limits, frame sources (video, folders,
globs), text inputs and file identities, and the one atomic writer every output goes through.
"""

from registration.io.atomic import (
    atomic_path,
    encode_npz,
    temp_target,
    write_bytes_atomic,
    write_image_atomic,
    write_json_atomic,
    write_npz_atomic,
)
from registration.io.files import (
    SAMPLE_BYTES,
    check_not_an_input,
    file_fingerprint,
    file_sha256,
    input_locations,
    read_text_file,
)
from registration.io.frames import (
    VIDEO_BACKWARD_BLOCK,
    FrameReadError,
    FrameSource,
    check_frames_match,
    check_recorded_frames,
    check_result_frames,
    frames_difference,
    input_differs,
    open_frames,
)
from registration.io.images import (
    MAX_FRAME_PIXELS,
    MIN_IMAGE_SIDE,
    decode_image_file,
    image_header_size,
    incomplete_image,
    read_image,
)

__all__ = [
    "FrameReadError",
    "FrameSource",
    "MAX_FRAME_PIXELS",
    "MIN_IMAGE_SIDE",
    "SAMPLE_BYTES",
    "check_not_an_input",
    "temp_target",
    "input_locations",
    "VIDEO_BACKWARD_BLOCK",
    "decode_image_file",
    "encode_npz",
    "file_fingerprint",
    "file_sha256",
    "image_header_size",
    "incomplete_image",
    "check_frames_match",
    "check_recorded_frames",
    "check_result_frames",
    "frames_difference",
    "input_differs",
    "open_frames",
    "read_image",
    "read_text_file",
    "atomic_path",
    "write_bytes_atomic",
    "write_image_atomic",
    "write_json_atomic",
    "write_npz_atomic",
]
