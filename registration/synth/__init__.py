"""Ground-truth helicopter simulator and the built-in demo sequence.

* :func:`simulate` renders a sequence (procedural city or a user scene) with exact truth.
* :func:`load_truth` opens the truth of a simulated folder with the registration-result interface
  (``n_frames``, ``frame_to_base``, ``base_to_frame``), plus ``gamma``, ``lens``, ``frame_size``,
  ``base_path``, ``frames_dir``, ``base_map``.
* :func:`rebase` copies a simulated sequence with its base map turned and/or resampled (frames
  reused, truth exact).
* :data:`PROFILES` names hard flights (``paper-hard``, ``long-flight``, ...):
  ``PROFILES["paper-hard"](frame_size=(640, 480))`` is a :class:`SimConfig`.
* :func:`demo_sequence` builds (once) and returns the cached demo sequence.
"""

from registration.synth.config import SimConfig
from registration.synth.demo import DEMO_CONFIG, demo_dir, demo_sequence
from registration.synth.profiles import PROFILES, Profile, motion_stats
from registration.synth.rebasing import rebase
from registration.synth.sequence import simulate
from registration.synth.truth import SimTruth, load_truth

__all__ = [
    "DEMO_CONFIG",
    "PROFILES",
    "Profile",
    "SimConfig",
    "SimTruth",
    "demo_dir",
    "demo_sequence",
    "load_truth",
    "motion_stats",
    "rebase",
    "simulate",
]
