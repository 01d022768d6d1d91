"""Ground-truth helicopter simulator and the built-in demo sequence.

* :func:`simulate` renders a sequence (procedural city or a user scene) with exact truth.
* :func:`load_truth` opens the truth of a simulated folder with the registration-result interface
  (``n_frames``, ``frame_to_base``, ``base_to_frame``), plus ``gamma``, ``frame_size``,
  ``base_path``, ``frames_dir``.
* :func:`demo_sequence` builds (once) and returns the cached demo sequence.
"""

from registration.synth.demo import DEMO_CONFIG, demo_dir, demo_sequence
from registration.synth.sequence import SimConfig, SimTruth, load_truth, simulate

__all__ = [
    "DEMO_CONFIG",
    "SimConfig",
    "SimTruth",
    "demo_dir",
    "demo_sequence",
    "load_truth",
    "simulate",
]
