"""Both cores busy within a chunk (registration/overlap.py, registration.chunks.run_chunk):
frames decoded ahead and the local stage in a second thread give the serial result, through
failed frames, re-anchored frames and jumps: the same frames registered in the same way, the
models within OVERLAP_GAP_PX of each other. Not bit-exact (why overlap is opt-in): with the local
stage in a second thread, the fine fit of a later frame can differ in its last bits, which can
change which control points REQCON keeps; measured up to 0.64 px at a frame's corner on the
tests' 640x480 sequence (most frames under 0.1 px)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

import registration
from registration.io import FrameReadError, open_frames
from registration.overlap import FramesAhead, LocalAhead
from registration.synth import SimConfig, simulate
from tests.conftest import register

# Largest distance allowed between the overlapped and the serial run's models (base px): the
# measured 0.64 px with a margin (a broken overlap, e.g. a frame given another frame's local
# field, moves frames by pixels).
OVERLAP_GAP_PX = 1.0


def _assert_same(a: Path, b: Path, n: int) -> None:
    """Same frames registered, in the same way, and the models within OVERLAP_GAP_PX of each
    other over the frame."""
    ra, rb = registration.load(a), registration.load(b)
    w, h = ra.frame_size
    gx, gy = np.meshgrid(np.linspace(20, w - 20, 9), np.linspace(20, h - 20, 7))
    q = np.c_[gx.ravel(), gy.ravel()]
    for k in range(n):
        assert ra.records[k]["status"] == rb.records[k]["status"], k
        assert ra.records[k].get("stage") == rb.records[k].get("stage"), k
        if not ra.is_ok(k):
            continue
        for stage in ("global", "local"):
            gap = np.hypot(*(ra.frame_to_base(k, q, stage) - rb.frame_to_base(k, q, stage)).T)
            assert np.nanmax(gap) <= OVERLAP_GAP_PX, (k, stage, np.nanmax(gap))


def test_frames_ahead_returns_the_source_frames_and_its_errors(tmp_path):
    sim = tmp_path / "sim"
    simulate(sim, SimConfig(frame_size=(160, 120), n_frames=5, seed=4, video=False))
    (sim / "frames" / "000002.png").write_bytes(b"not a png")
    frames = open_frames(sim / "frames")
    with FramesAhead(frames, [0, 1, 2, 3, 4], depth=2) as ahead:
        assert len(ahead) == 5 and ahead.size == frames.size
        np.testing.assert_array_equal(ahead.get(0), frames.get(0))
        # Asked out of order (frame 1 skipped, frame 0 again): read directly, still right.
        np.testing.assert_array_equal(ahead.get(3), frames.get(3))
        np.testing.assert_array_equal(ahead.get(0), frames.get(0))
        np.testing.assert_array_equal(ahead.get(4), frames.get(4))
    with FramesAhead(frames, [1, 2, 3]) as ahead:
        ahead.get(1)
        with pytest.raises(FrameReadError, match="000002"):
            ahead.get(2)
        np.testing.assert_array_equal(ahead.get(3), frames.get(3))
    with pytest.raises(ValueError, match="depth"):
        FramesAhead(frames, [0], depth=0)


def test_local_ahead_hands_back_results_and_errors_in_order():
    for enabled in (True, False):
        with LocalAhead(enabled) as pool:
            pool.submit("a", lambda x: x * 2, 21)
            pool.submit("b", lambda: 1 / 0)
            assert pool.pending() == ["a", "b"]
            assert pool.result("a") == 42
            with pytest.raises(ZeroDivisionError):
                pool.result("b")


def test_overlap_gives_the_serial_result(sim_seq, default_result, tmp_path):
    n = len(default_result.records)
    overlapped = register(sim_seq, tmp_path / "overlapped", overlap=True)
    _assert_same(Path(default_result.out_dir), Path(overlapped.out_dir), n)


@pytest.fixture(scope="module")
def rough_sequence(tmp_path_factory) -> tuple[Path, Path]:
    """A slow flyover with frames 2-4 dropped (a 200+ px jump: the SIFT fallback, then an
    anchor) and an unreadable frame in the middle."""
    sim = tmp_path_factory.mktemp("rough") / "sim"
    simulate(
        sim,
        SimConfig(frame_size=(640, 480), n_frames=8, seed=2, video=False, flyover_footprints=0.3),
    )
    frames = sim.parent / "frames"
    frames.mkdir()
    for i, k in enumerate([0, 1, -1, 5, 6, 7]):
        if k < 0:
            (frames / f"{i:06d}.png").write_bytes(b"broken")
        else:
            shutil.copy(sim / "frames" / f"{k:06d}.png", frames / f"{i:06d}.png")
    return sim, frames


def test_overlap_gives_the_serial_result_through_failures_and_anchors(rough_sequence, tmp_path):
    sim, frames = rough_sequence
    a = register(sim, tmp_path / "a", frames_dir=frames, overlap=True)
    b = register(sim, tmp_path / "b", frames_dir=frames)
    stages = [r.get("stage") or r["status"] for r in a.records]
    assert stages[2] == "failed" and "intra-sensor" in stages
    _assert_same(Path(a.out_dir), Path(b.out_dir), len(stages))
