"""Shared fixtures: seeded randomness and the real imagery in ``../shared/data`` (read in place)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def shared_data(*parts: str) -> Path:
    """Path inside ``../shared/data``; skips the calling test with a reason when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real imagery not available: {path} is absent (it sits beside the repo in CI)")
    return path


def pytest_collection_modifyitems(config, items) -> None:
    # End-to-end and real-browser tests live in their own folders and carry their marker, so a
    # developer can leave them out (``-m "not e2e and not browser"``) or run one folder alone.
    for item in items:
        folder = item.path.parent.name
        if folder in ("e2e", "browser"):
            item.add_marker(folder)


def pytest_report_header(config) -> str:
    # The accuracy limits are measured with one OpenCV build (SIFT's keypoints differ between
    # builds): say which one ran.
    import cv2
    import scipy

    return f"aerialreg: OpenCV {cv2.__version__}, numpy {np.__version__}, scipy {scipy.__version__}"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


# ---------------------------------------------------------------------------------------------
# One simulated sequence and its registrations, shared by the whole session (each run costs
# seconds; the end-to-end tests of several files read them).

# 640x480, 6 frames, seed 1: small enough for a test, with every stage of the pipeline at work
# (inter-sensor reference frame, intra-sensor frames, local fields).
SIM_SEQUENCE = {"frame_size": (640, 480), "n_frames": 6, "seed": 1, "video": False}
# The middle reference frame of the session's sequence (frames before and after it).
MID_REFERENCE = 3
# Frames of the paper preset's run (the paper's Nelder-Mead and gridded SIFT are slow).
PAPER_FRAMES = 3


def seed_for(sim: Path, k: int = 0) -> tuple[float, float, float, float]:
    """The one clicked correspondence: frame ``k``'s centre and its true base pixel."""
    from registration.synth import load_truth

    truth = load_truth(sim)
    w, h = truth.frame_size
    bx, by = truth.frame_to_base(k, [[w / 2, h / 2]])[0]
    return (w / 2, h / 2, float(bx), float(by))


def register(sim: Path, out: Path, preset: str = "default", frames_dir: Path | None = None, **kw):
    """``register_sequence`` of the simulated sequence ``sim`` (seeded at the reference frame's
    centre), with the preset's configuration unless ``config`` is given."""
    from registration.io import open_frames, read_image
    from registration.run import get_preset, register_sequence
    from registration.synth import load_truth

    return register_sequence(
        open_frames(frames_dir or sim / "frames"),
        read_image(sim / "base.png"),
        load_truth(sim).gamma,
        out,
        config=kw.pop("config", None) or get_preset(preset),
        preset=preset,
        seed=seed_for(sim, kw.get("reference_frame", 0)),
        **kw,
    )


class FirstFrames:
    """The truth of a simulated sequence restricted to its first ``n`` frames (for a result made
    from those frames only)."""

    def __init__(self, truth, n: int) -> None:
        self._truth, self.n_frames = truth, int(n)

    def __getattr__(self, name):
        return getattr(self._truth, name)


@pytest.fixture(scope="session")
def sim_seq(tmp_path_factory) -> Path:
    from registration.synth import SimConfig, simulate

    out = tmp_path_factory.mktemp("sim_seq") / "sim"
    simulate(out, SimConfig(**SIM_SEQUENCE))
    return out


@pytest.fixture(scope="session")
def default_result(sim_seq, tmp_path_factory):
    """The default preset on the session's sequence, reference frame 0."""
    return register(sim_seq, tmp_path_factory.mktemp("reg_default") / "out")


@pytest.fixture(scope="session")
def mid_reference_result(sim_seq, tmp_path_factory):
    """The default preset on the session's sequence, reference frame ``MID_REFERENCE``."""
    out = tmp_path_factory.mktemp("reg_mid") / "out"
    return register(sim_seq, out, reference_frame=MID_REFERENCE)


@pytest.fixture(scope="session")
def paper_result(sim_seq, tmp_path_factory):
    """The paper preset on the first ``PAPER_FRAMES`` frames of the session's sequence."""
    import shutil

    root = tmp_path_factory.mktemp("reg_paper")
    frames = root / "frames"
    frames.mkdir()
    for k in range(PAPER_FRAMES):
        shutil.copy(sim_seq / "frames" / f"{k:06d}.png", frames)
    return register(sim_seq, root / "out", preset="paper", frames_dir=frames)
